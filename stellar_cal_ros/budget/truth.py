"""The attitude error a calibration actually makes, knowing the truth (simulations only)."""

from __future__ import annotations

from typing import Any

import numpy as np

from stellar_cal_ros.budget.analysis import axes_rms
from stellar_cal_ros.budget.propagation import (
    N_PARAMETERS,
    frame_attitude_errors,
    random_frames,
)

__all__ = ["actual_attitude_errors", "parameter_error"]


def parameter_error(truth: Any, estimate: Any) -> np.ndarray:
    """``δx`` (21,) of an estimated calibration against the true one.

    Camera parameters: estimate − truth; installation: ψ with
    ``R̂_imu_st = R_imu_st · Exp(ψ)`` (tracker axes, rad).
    """
    dx = np.zeros(N_PARAMETERS)
    dx[:18] = estimate.camera.parameters() - truth.camera.parameters()
    dx[18:] = (truth.installation.inv() * estimate.installation).as_rotvec()
    return dx


def actual_attitude_errors(truth: Any, estimate: Any, frames: int, stars_per_frame: int,
                           seed: int) -> dict[str, dict[str, float]]:
    """RMS attitude error (arcsec) over random frames, exactly, per convention.

    The frames are those :func:`~stellar_cal_ros.budget.analysis.run_budget` draws first with
    the same seed (same camera size, uniform over the detector), without centroid noise: the
    error the calibration alone makes.
    """
    rng = np.random.default_rng(seed)
    field = random_frames(truth.camera, frames, stars_per_frame, rng)
    errors = frame_attitude_errors(truth.camera, field, parameter_error(truth, estimate))
    return {conv: axes_rms(np.mean(e**2, axis=0)) for conv, e in errors.items()}
