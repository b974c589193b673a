"""Single-frame star-tracker attitude: Wahba solution and pixel-space refinement.

``R_i_st`` maps star-tracker vectors to the inertial frame: ``u_i = R_i_st @ d_st``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stellar_cal_ros.core.camera import CameraModel
from stellar_cal_ros.core.rotation import scipy_matrix_roundtrip, skew, so3_exp
from stellar_cal_ros.errors import ModelError


@dataclass
class FrameAttitude:
    """Result of a single-frame attitude fit."""

    R_i_st: np.ndarray  # (3, 3)
    residuals: np.ndarray  # (n, 2) px, measured − predicted
    covariance: np.ndarray  # (3, 3) rad², of a right perturbation of R_i_st
    iterations: int


def wahba(
    directions_st: np.ndarray, directions_i: np.ndarray, weights: np.ndarray | None = None
) -> np.ndarray:
    """Least-squares rotation ``R_i_st`` with ``directions_i ≈ R_i_st @ directions_st``.

    One frame of :func:`batched_wahba` (the one Wahba solver).  Needs at least two
    non-parallel directions.
    """
    if len(directions_st) < 2:
        raise ModelError("Wahba's problem needs at least two stars")
    w = None if weights is None else np.asarray(weights, dtype=float)[None]
    return batched_wahba(
        np.asarray(directions_st, dtype=float)[None], np.asarray(directions_i, dtype=float)[None], w
    )[0]


def batched_wahba(
    directions_st: np.ndarray, directions_ref: np.ndarray, weights: np.ndarray | None = None
) -> np.ndarray:
    """Least-squares rotations ``R`` with ``directions_ref ≈ R @ directions_st`` (SVD).

    ``B = Σ w ref stᵀ = U S Vᵀ``, ``R = U diag(1, 1, det U · det V) Vᵀ``, for many frames at
    once, then through a unit quaternion (:class:`scipy.spatial.transform.Rotation`'s floats:
    :func:`~stellar_cal_ros.core.rotation.scipy_matrix_roundtrip`), which
    keeps ``RᵀR`` at the identity to ~1e-15 (2e-15 without).  With equal weights a frame's
    ``R`` is bit for bit :meth:`~scipy.spatial.transform.Rotation.align_vectors`'s, at a
    fraction of its per-call cost.

    Parameters
    ----------
    directions_st : numpy.ndarray, shape (F, n, 3)
        Directions in the frame to orient (the tracker's).
    directions_ref : numpy.ndarray, shape (F, n, 3)
        The same stars in the reference frame.
    weights : numpy.ndarray, shape (F, n), optional
        Non-negative weight of each pair (equal weights if omitted).

    Returns
    -------
    numpy.ndarray, shape (F, 3, 3)
    """
    if weights is None:
        B = np.einsum("fki,fkj->fij", directions_ref, directions_st)
    else:
        B = np.einsum("fk,fki,fkj->fij", weights, directions_ref, directions_st)
    U, _, Vt = np.linalg.svd(B)
    sign = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    U[:, :, 2] *= sign[:, None]
    return scipy_matrix_roundtrip(U @ Vt)


def fit_frame_attitude(
    camera: CameraModel,
    uv: np.ndarray,
    directions_i: np.ndarray,
    sigma_px: float = 1.0,
    R_i_st0: np.ndarray | None = None,
    max_iterations: int = 10,
) -> FrameAttitude:
    """Fit ``R_i_st`` of one frame by Gauss-Newton on pixel residuals.

    The start is the Wahba solution of the unprojected centroids (or ``R_i_st0``).  The
    perturbation is on the right: ``R = R_hat · Exp(δ)``, so ``d_st = Exp(−δ) R_hat^T u``
    and ``∂d_st/∂δ = [d_st]×``.
    """
    uv = np.asarray(uv, dtype=float)
    u_i = np.asarray(directions_i, dtype=float)
    R = wahba(camera.unproject(uv), u_i) if R_i_st0 is None else np.array(R_i_st0, dtype=float)
    R, info, iterations = refine_frame_rotation(camera, uv, u_i, R, max_iterations)
    d = u_i @ R
    residuals = uv - camera.project(d)
    return FrameAttitude(R, residuals, sigma_px**2 * np.linalg.inv(info), iterations)


def refine_frame_rotation(
    camera: CameraModel,
    uv: np.ndarray,
    directions_i: np.ndarray,
    R_i_st0: np.ndarray,
    max_iterations: int = 10,
) -> tuple[np.ndarray, np.ndarray, int]:
    """The Gauss-Newton iterations of :func:`fit_frame_attitude` from ``R_i_st0``.

    Returns ``(R_i_st, JᵀJ of the last step, iterations)``, without the residuals and
    covariance at the result (for callers that need the rotation only: the same rotation
    as the fit's, one projection fewer).
    """
    uv = np.asarray(uv, dtype=float)
    u_i = np.asarray(directions_i, dtype=float)
    R = np.array(R_i_st0, dtype=float)
    info = np.eye(3)
    iterations = 0
    for iterations in range(1, max_iterations + 1):  # noqa: B007 (returned)
        d = u_i @ R  # rows: R^T u
        pred, J_d = camera.project_direction(d)  # no parameter Jacobian: same floats
        r = (uv - pred).reshape(-1)
        J = np.einsum("nij,njk->nik", J_d, skew(d)).reshape(-1, 3)
        info = J.T @ J
        step = np.linalg.solve(info, J.T @ r)
        R = R @ so3_exp(step)
        if np.abs(step).max() < 1e-12:
            break
    return R, info, iterations
