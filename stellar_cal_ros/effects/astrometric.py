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
        key = (self.id, id(u_i))
        cache = ctx.extra.setdefault("_direction_cache", {})
        if key not in cache:
            cache[key] = self.delta(u_i, ctx)
        return cache[key]

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

        cat = _full_catalog(load_catalog)
        idx = cat.index_of(np.asarray(ctx.catalog_id))
        out = np.zeros_like(u_i)
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
