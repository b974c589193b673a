"""Shared form of the inertial sensor errors: ``w_meas = (I + E) w_true + b + noise``.

Not an effect module (the registry skips ``_`` modules): the gyro and accelerometer effects
(``gyro_bias.py``, ``gyro_scale_factor.py``, ...) each subclass one of these.  Gyro effects
act in the GYRO stage, accelerometer effects in the ACCEL stage.  Biases add to ``b``; scale
factors fill the diagonal of ``E``, misalignments its off-diagonal entries.  The values live
in the calibration's own ``gyro`` / ``accelerometer`` blocks (contract §3).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from stellar_cal_ros.effects.base import Effect, ExportRole

OFF_DIAGONAL = ((0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1))


def _sigma(prior: Any, block: str, key: str, default: tuple[float, ...], index=None):
    values = (prior.sigma or {}).get(block, {}).get(key)
    if values is None:
        return np.asarray(default, dtype=float)
    values = np.asarray(values, dtype=float)
    return values if index is None else values[index]


class SensorBias(Effect):
    """A sensor bias b (3,), in the calibration's ``gyro`` or ``accelerometer`` block."""

    block = "gyro"
    export_role = ExportRole.IMU
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


class SensorMatrix(Effect):
    """Entries of a sensor error matrix E, in the calibration's sensor block."""

    block = "gyro"
    export_role = ExportRole.IMU
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
