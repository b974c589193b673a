"""Shared form of the astrometric effects: where the tracker sees a star versus its J2000.0 place.

Not an effect module (the registry skips ``_`` modules): ``aberration.py``,
``refraction.py`` and ``proper_motion.py`` each subclass :class:`ScaledDirection`.  Each is a
DIRECTION-stage effect with one parameter, a *scale* of the physical effect
(0 = absent, 1 = as physics predicts): ``u' = u + s · Δ(u)`` where ``Δ`` is the full
correction computed by :mod:`stellar_cal_ros.core.astrometry` (pyerfa).  Estimating the
scale tells the user whether the effect is present, and how strongly, without fitting any
free-form correction.
"""

from __future__ import annotations

import numpy as np

from stellar_cal_ros.effects.base import Effect, ExportRole, FrameContext, Plausible, Stage


class ScaledDirection(Effect):
    """``u' = u + s · Δ(u)``: one parameter, the scale of a correction physics fixes (1)."""

    stage = Stage.DIRECTION
    parameter_names = ("scale",)
    units = ("1",)
    default_sigma = (1.0,)
    physical_value = 1.0
    display_units = ("x physical", 1.0)
    plausible = Plausible(1.0, "x physical")
    export_role = ExportRole.STAR_DIRECTIONS

    def delta(self, u_i: np.ndarray, ctx: FrameContext) -> np.ndarray:
        """Full (scale 1) correction of the directions (n, 3)."""
        raise NotImplementedError

    def _cached_delta(self, u_i: np.ndarray, ctx: FrameContext) -> np.ndarray:
        # One entry per effect, keyed by the *content* of everything delta() reads: a key
        # on id(u_i) returned stale (even wrongly shaped) corrections when a caller passed
        # a subset u_i[mask] with the same context and Python reused a freed array's id.
        u = np.ascontiguousarray(u_i, dtype=float)
        key = (
            u.shape, u.tobytes(),
            np.ascontiguousarray(ctx.catalog_id, dtype=np.int64).tobytes(),
            float(ctx.stamp), ctx.site,
            *(float(x) if np.isfinite(x) else None
              for x in (ctx.pressure_pa, ctx.air_temperature_c)),
        )
        cache = ctx.extra.setdefault("_direction_cache", {})
        hit = cache.get(self.id)
        if hit is None or hit[0] != key:
            hit = (key, self.delta(u, ctx))
            cache[self.id] = hit
        return hit[1]

    def directions(self, value, u_i, ctx):  # noqa: D102
        return u_i + value[0] * self._cached_delta(u_i, ctx)

    def directions_jacobian(self, value, u_i, ctx):  # noqa: D102
        return self._cached_delta(u_i, ctx)[:, :, None]

    def affine_form(self):  # noqa: D102 - u' = u + s Δ(u, ctx): Δ comes with the frame
        return True
