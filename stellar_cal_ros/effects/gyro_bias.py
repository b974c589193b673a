"""Gyro bias: a constant rate each gyro reads at rest (contract §3 ``gyro.bias``)."""

from __future__ import annotations

from stellar_cal_ros.core.units import DEG_PER_HOUR
from stellar_cal_ros.effects._sensor import SensorBias
from stellar_cal_ros.effects.base import Plausible, Stage


class GyroBias(SensorBias):
    """Gyro bias b, rad/s (IMU axes)."""

    id = "gyro_bias"
    stage = Stage.GYRO
    order = 10
    block = "gyro"
    units = ("rad/s",) * 3
    default_sigma = (0.05 * DEG_PER_HOUR,) * 3
    plausible = Plausible(1.0, "deg/h")
    simulation_units = ("deg/h", "deg/h", "deg/h")
    simulation_scale = (DEG_PER_HOUR,) * 3
    explanation = (
        "Each gyro reads a small constant rate when at rest. Integrated, it turns the "
        "propagated attitude at a steady rate, so star residuals drift linearly in time "
        "between star updates and the attitude error grows with the gap. Navigation grade: "
        "0.001-0.1 deg/h."
    )
