"""Accelerometer bias (contract §3 ``accelerometer.bias``)."""

from __future__ import annotations

from typing import Any

import numpy as np

from stellar_cal_ros.effects._sensor import SensorBias
from stellar_cal_ros.effects.base import Plausible, Stage


class AccelBias(SensorBias):
    """Accelerometer bias, m/s²."""

    id = "accel_bias"
    stage = Stage.ACCEL
    order = 10
    block = "accelerometer"
    units = ("m/s^2",) * 3
    default_sigma = (1e-3,) * 3
    plausible = Plausible(1e-2, "m/s^2")  # ~1 mg
    explanation = (
        "Each accelerometer reads a small constant specific force. In an inertial-frame "
        "navigation it tilts the apparent gravity: the velocity residual grows linearly. "
        "Navigation grade: 10-100 ug."
    )

    def _get(self, cal: Any) -> np.ndarray:
        return cal.accel_bias
