"""Gyro scale-factor errors: the diagonal of the gyro error matrix E."""

from __future__ import annotations

from stellar_cal_ros.effects._sensor import SensorMatrix
from stellar_cal_ros.effects.base import Plausible, Stage


class GyroScaleFactor(SensorMatrix):
    """Gyro scale-factor errors (diagonal of E)."""

    id = "gyro_scale_factor"
    stage = Stage.GYRO
    order = 20
    block = "gyro"
    entries = ((0, 0), (1, 1), (2, 2))
    parameter_names = ("sx", "sy", "sz")
    units = ("1",) * 3
    default_sigma = (2e-4,) * 3
    display_units = ("ppm", 1e6)
    plausible = Plausible(1000.0, "ppm")  # MEMS
    explanation = (
        "A gyro reports its rate a few ppm too large or small, so every slew is over- or "
        "under-measured in proportion to its angle. Residual: jumps after each rotation about "
        "that axis, proportional to the angle turned; nothing while at rest. Typical: 10-500 ppm. "
        "Look-alike: a mount that flexes with the gravity direction gives the same residual "
        "when the tracker is tilted out and back by less than ~60 deg (sin θ ≈ θ); a full turn, "
        "or a rotation about the vertical, tells them apart (flexure has none about it)."
    )
