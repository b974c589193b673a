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

    uses_weather = True

    def delta_stars(self, u, t, catalog_id, site, pressure_pa, air_temperature_c):  # noqa: D102
        if site is None:
            raise ModelError("refraction needs the site (/gnss/fix) in the frame context")
        p = np.where(np.isfinite(pressure_pa), pressure_pa, STANDARD_PRESSURE_PA)
        T = np.where(np.isfinite(air_temperature_c), air_temperature_c, STANDARD_TEMPERATURE_C)
        return astrometry.refraction(u, t, site, pressure_hpa=p / 100.0, temperature_c=T) - u
