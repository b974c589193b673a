"""Gyro axis misalignment: the off-diagonal entries of the gyro error matrix E."""

from __future__ import annotations

from stellar_cal_ros.effects._sensor import OFF_DIAGONAL, SensorMatrix
from stellar_cal_ros.effects.base import Plausible, Stage


class GyroMisalignment(SensorMatrix):
    """Gyro axis misalignment (off-diagonal of E), rad."""

    id = "gyro_misalignment"
    stage = Stage.GYRO
    order = 30
    block = "gyro"
    entries = OFF_DIAGONAL
    parameter_names = ("e01", "e02", "e10", "e12", "e20", "e21")
    units = ("rad",) * 6
    default_sigma = (5e-4,) * 6
    plausible = Plausible(1.0, "mrad")  # ~200 arcsec
    explanation = (
        "The gyro sensitive axes are not exactly orthogonal / not aligned with imu_link: a "
        "rotation about one axis leaks into the others. Residual: after a slew about x, an "
        "attitude error about y or z proportional to the angle. Typical: 10-200 arcsec."
    )
