"""Atmospheric refraction for ground-based trackers (a scale of pyerfa's correction)."""

from __future__ import annotations

import numpy as np

from stellar_cal_ros.core import astrometry
from stellar_cal_ros.effects._direction import ScaledDirection
from stellar_cal_ros.errors import ModelError

STANDARD_PRESSURE_PA = 101325.0
STANDARD_TEMPERATURE_C = 10.0


class Refraction(ScaledDirection):
    """Atmospheric refraction (ground-based trackers)."""

    id = "refraction"
    order = 30
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
