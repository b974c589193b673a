"""Astrometric effects: where the tracker sees a star versus its catalogue J2000.0 place.

Each is a DIRECTION-stage effect with one parameter, a *scale* of the physical effect
(0 = absent, 1 = as physics predicts): ``u' = u + s · Δ(u)`` where ``Δ`` is the full
correction computed by :mod:`stellar_cal_ros.core.astrometry` (pyerfa).  Estimating the
scale tells the user whether the effect is present, and how strongly, without fitting any
free-form correction.
"""

from __future__ import annotations

import numpy as np

from stellar_cal_ros.core import astrometry
from stellar_cal_ros.effects.base import Effect, FrameContext, Stage
from stellar_cal_ros.errors import ModelError

STANDARD_PRESSURE_PA = 101325.0
STANDARD_TEMPERATURE_C = 10.0


class _ScaledDirection(Effect):
    stage = Stage.DIRECTION
    parameter_names = ("scale",)
    units = ("1",)
    default_sigma = (1.0,)

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


class Aberration(_ScaledDirection):
    """Annual + diurnal aberration of starlight."""

    id = "aberration"
    requires = ("site",)
    explanation = (
        "The observer moves (Earth's orbit, 30 km/s; Earth's rotation, up to 0.46 km/s), so "
        "starlight arrives tilted toward the direction of motion by up to 20.5 arcsec. Over a "
        "small field it is almost a uniform shift (absorbed by the attitude), leaving a "
        "differential scale/shear of ~1e-4 x field: residuals that grow toward the field edge "
        "and whose pattern is fixed to the sky, not the tracker."
    )

    def delta(self, u_i, ctx):  # noqa: D102
        u = astrometry.aberration(u_i, np.full(len(u_i), ctx.stamp), ctx.site, 1.0)
        return u - u_i


class Refraction(_ScaledDirection):
    """Atmospheric refraction (ground-based trackers)."""

    id = "refraction"
    requires = ("site", "weather")
    explanation = (
        "The atmosphere bends starlight toward the zenith by about 58 arcsec x tan(zenith "
        "distance) x (P/1013 hPa) x (283 K/T). Across the field the bending differs between "
        "the low and high edge: a compression along the vertical that grows as the tracker "
        "looks lower. Residual correlates with elevation; absent in space."
    )

    def delta(self, u_i, ctx):  # noqa: D102
        if ctx.site is None:
            raise ModelError("refraction needs the site (/gnss/fix) in the frame context")
        p = ctx.pressure_pa if np.isfinite(ctx.pressure_pa) else STANDARD_PRESSURE_PA
        T = ctx.air_temperature_c if np.isfinite(ctx.air_temperature_c) else STANDARD_TEMPERATURE_C
        u = astrometry.refraction(u_i, np.full(len(u_i), ctx.stamp), ctx.site,
                                  pressure_hpa=p / 100.0, temperature_c=T)
        return u - u_i


class ProperMotion(_ScaledDirection):
    """Proper motion of the stars from J2000.0 to the date (Hipparcos 2)."""

    id = "proper_motion"
    explanation = (
        "Stars move on the sky, up to several arcsec per year for nearby ones; messages carry "
        "J2000.0 places, so after 27 years a few stars sit up to 100 arcsec from where the "
        "model expects them. Residual: large errors on a few particular stars (by catalog id), "
        "always the same direction for the same star, whatever the attitude."
    )

    def delta(self, u_i, ctx):  # noqa: D102
        from stellar_cal_ros.core.catalog import load_catalog, posix_to_jyear

        ids = np.asarray(ctx.catalog_id, dtype=np.int64).reshape(-1)
        out = np.zeros_like(u_i)
        if ids.size == 0:  # no identifications in the context: no star is known
            return out
        if ids.size != len(u_i):
            raise ModelError(f"proper_motion: {ids.size} catalog ids for {len(u_i)} directions")
        cat = _full_catalog(load_catalog)
        idx = cat.index_of(ids)
        known = idx >= 0
        if np.any(known):
            sub = cat.subset(idx[known])
            jyear = float(posix_to_jyear(ctx.stamp))
            out[known] = sub.directions(jyear) - sub.directions(2000.0)
        return out


_CATALOG = None


def _full_catalog(loader):
    global _CATALOG
    if _CATALOG is None:
        _CATALOG = loader(mag_limit=None)
    return _CATALOG
