"""Extra per-star regressors the residual table lacks, computed from the bag.

The gravity direction in the tracker frame is what gravity-dependent mount bending
(flexure) follows: a tracker rotation proportional to the lateral gravity that no library
effect models.  It is taken from the accelerometer (the specific force is −g when the
platform does not accelerate), averaged over ``window_s`` around each exposure and
rotated into the tracker frame with the *calibrated* installation:

    g_st = R_imu_stᵀ · (−f̄_b / |f̄_b|)

Only the unit direction is used, so an accelerometer scale error or bias of datasheet
size does not matter.  When the bag has no usable accelerometer data (all zero or
non-finite), no column is added.
"""

from __future__ import annotations

import numpy as np

from stellar_cal_ros.io.calibration import Calibration
from stellar_cal_ros.methods.replay import BagData

Table = dict[str, np.ndarray]

#: accelerometer norm (m/s²) below which the specific force is not taken as gravity
MIN_SPECIFIC_FORCE = 5.0


#: the span (s) of the specific force's mean that is the load a mount bends under (the
#: flexure probe, :mod:`~stellar_cal_ros.diagnosis.flexure`, and a twin's injected
#: flexure): a mount follows its load quasi-statically, so the mean is only short enough
#: to keep the accelerometer's noise out.  The 1 s of the gravity regressors kept 0.967 of
#: the swaying base's acceleration, so the probe read a flexure's true response 3.4 % high
#: (10.34″/g for 10 on 200 s sway_flex, seed 21; 10.04 at 0.1 s, 10.04 at 0.02 s)
LOAD_WINDOW_S = 0.1


def gravity_in_tracker(data: BagData, calibration: Calibration, t_posix: np.ndarray,
                       window_s: float = 1.0) -> np.ndarray | None:
    """Unit gravity direction in the tracker frame at POSIX times ``t_posix`` (n, 3).

    The specific force's mean over ``window_s`` about each time (1 s: the 'unexplained'
    lines' gravity regressors; :data:`LOAD_WINDOW_S`: the load a mount bends under).
    """
    f = np.asarray(data.imu_f, dtype=float)
    t_imu = np.asarray(data.imu_t, dtype=float)
    if f.ndim != 2 or len(f) < 2 or not np.all(np.isfinite(f)):
        return None
    if np.median(np.linalg.norm(f, axis=1)) < MIN_SPECIFIC_FORCE:
        return None
    t_rel = np.asarray(t_posix, dtype=float) - data.t0
    # Window means by cumulative sums (the IMU series is sorted in time).
    c = np.vstack([np.zeros((1, 3)), np.cumsum(f, axis=0)])
    lo = np.searchsorted(t_imu, t_rel - 0.5 * window_s, side="left")
    hi = np.searchsorted(t_imu, t_rel + 0.5 * window_s, side="right")
    hi = np.maximum(hi, lo + 1)
    lo = np.minimum(lo, len(f) - 1)
    hi = np.minimum(hi, len(f))
    mean_f = (c[hi] - c[lo]) / np.maximum(hi - lo, 1)[:, None]
    g_b = -mean_f / np.maximum(np.linalg.norm(mean_f, axis=1, keepdims=True), 1e-300)
    R_imu_st = calibration.installation.as_matrix()
    return g_b @ R_imu_st  # rows: R_imu_stᵀ g_b


def add_gravity_regressors(res: Table, data: BagData, calibration: Calibration) -> Table:
    """A copy of the residual table with the gravity direction in the tracker frame.

    ``gravity_x_st, gravity_y_st`` (unit vector) and their recent change (``gravity_x_st
    change``: minus their average over the past :data:`CHANGE_TAU_S`).
    """
    out = dict(res)
    if len(res.get("t", ())) == 0:
        return out
    t = np.asarray(res["t"], dtype=float)
    uniq, inv = np.unique(t, return_inverse=True)  # one computation per frame
    g = gravity_in_tracker(data, calibration, uniq)
    if g is None:
        return out
    out["gravity_x_st"] = g[inv, 0]
    out["gravity_y_st"] = g[inv, 1]
    # the recent change: a mount that bends with gravity turns the tracker when the gravity
    # direction changes, and the filter, whose attitude follows the gyro, sees it then and
    # for a few seconds after (until its attitude follows the stars again): gravity minus
    # its causal exponential average over CHANGE_TAU_S
    for k, name in ((0, "gravity_x_st change"), (1, "gravity_y_st change")):
        out[name] = (g[:, k] - _causal_average(uniq, g[:, k], CHANGE_TAU_S))[inv]
    return out


#: time constant (s) of the "recent change" of a frame regressor
CHANGE_TAU_S = 10.0


def _causal_average(t: np.ndarray, x: np.ndarray, tau: float) -> np.ndarray:
    """Exponential moving average of ``x`` over the past ``tau`` s (at the times ``t``)."""
    out = np.empty_like(x)
    acc = x[0] if len(x) else 0.0
    prev = t[0] if len(t) else 0.0
    for i, (ti, xi) in enumerate(zip(t.tolist(), x.tolist(), strict=True)):
        a = float(np.exp(-max(ti - prev, 0.0) / tau))
        acc = a * acc + (1.0 - a) * xi
        out[i] = acc
        prev = ti
    return out
