"""Inertial sensor errors: ``w_meas = (I + E) w_true + b + noise`` (contract §3).

Gyro effects act in the GYRO stage, accelerometer effects in the ACCEL stage.  Biases add to
``b``; scale factors fill the diagonal of ``E``, misalignments its off-diagonal entries.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from stellar_cal_ros.effects.base import Effect, Stage

DEG_PER_HOUR = np.pi / 180.0 / 3600.0
_OFF_DIAGONAL = ((0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1))


def _sigma(prior: Any, block: str, key: str, default: tuple[float, ...], index=None):
    values = (prior.sigma or {}).get(block, {}).get(key)
    if values is None:
        return np.asarray(default, dtype=float)
    values = np.asarray(values, dtype=float)
    return values if index is None else values[index]


class _Bias(Effect):
    block = "gyro"
    parameter_names = ("bx", "by", "bz")

    def _get(self, cal: Any) -> np.ndarray:
        return cal.gyro_bias if self.block == "gyro" else cal.accel_bias

    def initial(self, prior):  # noqa: D102
        sigma = _sigma(prior, self.block, "bias", self.default_sigma)
        return np.array(self._get(prior), dtype=float), sigma

    def store(self, value, sigma, cal):  # noqa: D102
        if self.block == "gyro":
            cal.gyro_bias = np.array(value, dtype=float)
        else:
            cal.accel_bias = np.array(value, dtype=float)
        cal.sigma.setdefault(self.block, {})["bias"] = [float(s) for s in sigma]

    def sensor_bias(self, value):  # noqa: D102
        return np.asarray(value, dtype=float)

    def sensor_bias_jacobian(self, value):  # noqa: D102
        return np.eye(3)


class _Matrix(Effect):
    block = "gyro"
    entries: tuple[tuple[int, int], ...] = ((0, 0), (1, 1), (2, 2))

    def _matrix(self, cal: Any) -> np.ndarray:
        return cal.gyro_error_matrix if self.block == "gyro" else cal.accel_error_matrix

    def initial(self, prior):  # noqa: D102
        E = np.asarray(self._matrix(prior), dtype=float)
        flat = [3 * i + j for i, j in self.entries]
        sigma = _sigma(prior, self.block, "error_matrix", (np.nan,) * 9)
        sigma = sigma[flat] if sigma.size == 9 else np.full(len(flat), np.nan)
        sigma = np.where(np.isfinite(sigma) & (sigma > 0), sigma, self.default_sigma)
        return np.array([E[i, j] for i, j in self.entries]), sigma

    def store(self, value, sigma, cal):  # noqa: D102
        E = np.array(self._matrix(cal), dtype=float)
        for (i, j), v in zip(self.entries, value, strict=True):
            E[i, j] = v
        if self.block == "gyro":
            cal.gyro_error_matrix = E
        else:
            cal.accel_error_matrix = E
        block = cal.sigma.setdefault(self.block, {})
        s = list(block.get("error_matrix") or [0.0] * 9)
        for (i, j), v in zip(self.entries, sigma, strict=True):
            s[3 * i + j] = float(v)
        block["error_matrix"] = s

    def sensor_matrix(self, value):  # noqa: D102
        E = np.zeros((3, 3))
        for (i, j), v in zip(self.entries, value, strict=True):
            E[i, j] = v
        return E

    def sensor_matrix_jacobian(self, value):  # noqa: D102
        J = np.zeros((3, 3, self.size))
        for k, (i, j) in enumerate(self.entries):
            J[i, j, k] = 1.0
        return J


class GyroBias(_Bias):
    """Gyro bias b, rad/s (IMU axes)."""

    id = "gyro_bias"
    stage = Stage.GYRO
    block = "gyro"
    units = ("rad/s",) * 3
    default_sigma = (0.05 * DEG_PER_HOUR,) * 3
    simulation_units = ("deg/h", "deg/h", "deg/h")
    simulation_scale = (DEG_PER_HOUR,) * 3
    explanation = (
        "Each gyro reads a small constant rate when at rest. Integrated, it turns the "
        "propagated attitude at a steady rate, so star residuals drift linearly in time "
        "between star updates and the attitude error grows with the gap. Navigation grade: "
        "0.001-0.1 deg/h."
    )


class GyroScaleFactor(_Matrix):
    """Gyro scale-factor errors (diagonal of E)."""

    id = "gyro_scale_factor"
    stage = Stage.GYRO
    block = "gyro"
    entries = ((0, 0), (1, 1), (2, 2))
    parameter_names = ("sx", "sy", "sz")
    units = ("1",) * 3
    default_sigma = (2e-4,) * 3
    explanation = (
        "A gyro reports its rate a few ppm too large or small, so every slew is over- or "
        "under-measured in proportion to its angle. Residual: jumps after each rotation about "
        "that axis, proportional to the angle turned; nothing while at rest. Typical: 10-500 ppm. "
        "Look-alike: a mount that flexes with the gravity direction gives the same residual "
        "when the tracker is tilted out and back by less than ~60 deg (sin θ ≈ θ); a full turn, "
        "or a rotation about the vertical, tells them apart (flexure has none about it)."
    )


class GyroMisalignment(_Matrix):
    """Gyro axis misalignment (off-diagonal of E), rad."""

    id = "gyro_misalignment"
    stage = Stage.GYRO
    block = "gyro"
    entries = _OFF_DIAGONAL
    parameter_names = ("e01", "e02", "e10", "e12", "e20", "e21")
    units = ("rad",) * 6
    default_sigma = (5e-4,) * 6
    explanation = (
        "The gyro sensitive axes are not exactly orthogonal / not aligned with imu_link: a "
        "rotation about one axis leaks into the others. Residual: after a slew about x, an "
        "attitude error about y or z proportional to the angle. Typical: 10-200 arcsec."
    )


class AccelBias(_Bias):
    """Accelerometer bias, m/s²."""

    id = "accel_bias"
    stage = Stage.ACCEL
    block = "accelerometer"
    units = ("m/s^2",) * 3
    default_sigma = (1e-3,) * 3
    explanation = (
        "Each accelerometer reads a small constant specific force. In an inertial-frame "
        "navigation it tilts the apparent gravity: the velocity residual grows linearly. "
        "Navigation grade: 10-100 ug."
    )

    def _get(self, cal: Any) -> np.ndarray:
        return cal.accel_bias


class AccelScaleFactor(_Matrix):
    """Accelerometer scale-factor errors (diagonal of the accelerometer E)."""

    id = "accel_scale_factor"
    stage = Stage.ACCEL
    block = "accelerometer"
    entries = ((0, 0), (1, 1), (2, 2))
    parameter_names = ("sx", "sy", "sz")
    units = ("1",) * 3
    default_sigma = (2e-4,) * 3
    explanation = (
        "Accelerometers over- or under-report specific force in proportion to it; gravity "
        "along an axis then reads wrong by g times the error. Residual: velocity error that "
        "depends on which axis points down. Typical: 10-500 ppm."
    )
