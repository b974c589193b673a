"""Kalman-filter building blocks shared by the estimators (numpy only).

Functional style after filterpy: every function takes and returns arrays, shapes are in the
docstrings, nothing is hidden in an object.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from stellar_cal_ros.errors import ModelError


def joseph_update(P: np.ndarray, K: np.ndarray, H: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Covariance after a Kalman update, Joseph form.

    ``P+ = (I − K H) P (I − K H)ᵀ + K R Kᵀ`` stays symmetric positive definite even when K
    is not exactly optimal (iterated updates, rounding) — the short form ``(I − K H) P``
    does not.  Shapes: P (N, N), K (N, M), H (M, N), R (M, M).
    """
    A = np.eye(P.shape[0]) - K @ H
    out = A @ P @ A.T + K @ R @ K.T
    return 0.5 * (out + out.T)


def gain(P: np.ndarray, H: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kalman gain ``K = P Hᵀ S⁻¹`` and innovation covariance ``S = H P Hᵀ + R``."""
    PHt = P @ H.T
    S = H @ PHt + R
    S = 0.5 * (S + S.T)
    try:
        c = np.linalg.cholesky(S)
    except np.linalg.LinAlgError as exc:
        raise ModelError("innovation covariance is not positive definite") from exc
    K = np.linalg.solve(c.T, np.linalg.solve(c, PHt.T)).T
    return K, S


def block_nis(nu: np.ndarray, S_blocks: np.ndarray) -> np.ndarray:
    """Per-measurement normalized innovation squared for 2×2 blocks.

    ``nu`` (n, 2), ``S_blocks`` (n, 2, 2) → (n,) values ``νᵀ S⁻¹ ν`` (χ² with 2 dof).
    """
    a, b, d = S_blocks[:, 0, 0], S_blocks[:, 0, 1], S_blocks[:, 1, 1]
    det = a * d - b * b
    x, y = nu[:, 0], nu[:, 1]
    return (d * x * x - 2 * b * x * y + a * y * y) / det


def chi2_gate(probability: float, dof: int = 2) -> float:
    """χ² threshold a consistent measurement exceeds with ``1 − probability`` chance."""
    return float(chi2.ppf(probability, dof))


def check_covariance(P: np.ndarray, name: str = "covariance") -> None:
    """Raise :class:`ModelError` unless P is finite, symmetric and positive definite."""
    if not np.all(np.isfinite(P)):
        raise ModelError(f"{name} has non-finite entries")
    if np.max(np.abs(P - P.T)) > 1e-9 * max(1.0, float(np.max(np.abs(P)))):
        raise ModelError(f"{name} is not symmetric")
    try:
        np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        raise ModelError(f"{name} is not positive definite") from None


def nees(error: np.ndarray, P: np.ndarray) -> float:
    """Normalized estimation error squared ``eᵀ P⁻¹ e`` (χ² with len(e) dof if consistent)."""
    return float(error @ np.linalg.solve(P, error))
