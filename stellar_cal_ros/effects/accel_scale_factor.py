"""Accelerometer scale-factor errors: the diagonal of the accelerometer error matrix."""

from __future__ import annotations

from stellar_cal_ros.effects._sensor import SensorMatrix
from stellar_cal_ros.effects.base import Plausible, Stage


class AccelScaleFactor(SensorMatrix):
    """Accelerometer scale-factor errors (diagonal of the accelerometer E)."""

    id = "accel_scale_factor"
    stage = Stage.ACCEL
    order = 20
    block = "accelerometer"
    entries = ((0, 0), (1, 1), (2, 2))
    parameter_names = ("sx", "sy", "sz")
    units = ("1",) * 3
    default_sigma = (2e-4,) * 3
    display_units = ("ppm", 1e6)
    plausible = Plausible(1000.0, "ppm")
    explanation = (
        "Accelerometers over- or under-report specific force in proportion to it; gravity "
        "along an axis then reads wrong by g times the error. Residual: velocity error that "
        "depends on which axis points down. Typical: 10-500 ppm."
    )
