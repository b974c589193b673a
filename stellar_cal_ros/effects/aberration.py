"""Annual + diurnal aberration of starlight (a scale of pyerfa's correction)."""

from __future__ import annotations

from stellar_cal_ros.core import astrometry
from stellar_cal_ros.effects._direction import ScaledDirection


class Aberration(ScaledDirection):
    """Annual + diurnal aberration of starlight."""

    id = "aberration"
    order = 20
    requires = ("site",)
    explanation = (
        "The observer moves (Earth's orbit, 30 km/s; Earth's rotation, up to 0.46 km/s), so "
        "starlight arrives tilted toward the direction of motion by up to 20.5 arcsec. Over a "
        "small field it is almost a uniform shift (absorbed by the attitude), leaving a "
        "differential scale/shear of ~1e-4 x field: residuals that grow toward the field edge "
        "and whose pattern is fixed to the sky, not the tracker."
    )

    def delta_stars(self, u, t, catalog_id, site, pressure_pa, air_temperature_c):  # noqa: D102
        return astrometry.aberration(u, t, site, 1.0) - u
