"""Covariance and observability of the ACF least squares (numpy only).

The solver's covariance ``(J_sᵀ W J_s / s² + J_pᵀ J_p)⁻¹`` with the variance factor s² of
the star rows, the extra covariance the gyro angle random walk adds between frames
(sandwich form), the equilibrated inverse the bounds share, and the SVD report of what the
star data determine.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from stellar_cal_ros.io.bag import ImuSeries


@dataclass
class ObservabilityReport:
    """What the star data determine, from the SVD of the whitened star Jacobian.

    Columns are scaled by the prior σ of each parameter (the first-attitude columns by the
    installation prior σ), so a singular value ``s`` compares the data's information on a
    combination with the prior's: ``s < 1`` means the prior dominates.
    """

    parameter_names: list[str]
    singular_values: np.ndarray
    directions: np.ndarray  # (n, n) right singular vectors as columns (scaled parameters)
    weak: list[dict[str, Any]]
    prior_dominated: list[str]
    sigma_ratio: dict[str, float]  # posterior σ / prior σ
    correlations: list[tuple[str, str, float]]

    def summary(self) -> str:
        """Human-readable text."""
        lines = [f"condition number (prior-scaled star Jacobian): "
                 f"{self.singular_values[0] / max(self.singular_values[-1], 1e-300):.3g}"]
        for w in self.weak:
            comb = " ".join(f"{c:+.2f}·{n}" for n, c in w["combination"].items())
            lines.append(f"  weak direction s={w['singular_value']:.3g}: {comb}")
        if self.prior_dominated:
            lines.append("  prior-dominated (posterior σ > 0.5 prior σ): "
                         + ", ".join(self.prior_dominated))
        for a, b, r in self.correlations:
            lines.append(f"  correlation {a} ~ {b}: {r:+.3f}")
        return "\n".join(lines)


def _equilibrated_inverse(info: np.ndarray) -> np.ndarray:
    """Inverse of an information matrix, equilibrated first.

    The columns span ~12 decades (rad, px, distortion coefficients); a singular matrix
    (an unobservable direction without prior) falls back to the pseudo-inverse.
    """
    d = 1.0 / np.sqrt(np.maximum(np.diag(info), 1e-300))
    scaled = info * np.outer(d, d)
    try:
        inv = np.linalg.inv(scaled)
    except np.linalg.LinAlgError:
        inv = np.linalg.pinv(scaled, hermitian=True)
    return inv * np.outer(d, d)


def _inverse(info: np.ndarray) -> np.ndarray:
    """:func:`_equilibrated_inverse`, symmetrized (the bounds' covariances)."""
    inv = _equilibrated_inverse(info)
    return 0.5 * (inv + inv.T)


def _covariance(J: np.ndarray, r: np.ndarray, n_star: int, weights: np.ndarray,
                n_x: int) -> tuple[np.ndarray, float]:
    """``(J_sᵀ W J_s / s² + J_pᵀ J_p)⁻¹`` and the variance factor s² of the star rows.

    ``W`` holds the robust IRLS weights (1 for the linear loss); s² comes from the rows with
    weight ≥ 0.5 (all rows for the linear loss; ``|r| < 2·f_scale`` for Huber).
    """
    Js, Jp = J[:n_star], J[n_star:]
    rs = r[:n_star]
    inl = weights >= 0.5  # robust losses: the variance factor from the inliers only
    dof = max(inl.sum() - n_x, 1.0)
    s2 = float(np.sum(rs[inl] ** 2) / dof)
    info = (Js * weights[:, None]).T @ Js / s2 + Jp.T @ Jp
    return _equilibrated_inverse(info), s2


def _arw_density(imu: ImuSeries, gyro_arw: float | None) -> float:
    """Angle random walk density q (rad²/s): given, or from the IMU messages' covariance."""
    if gyro_arw is not None:
        return float(gyro_arw) ** 2
    cov = imu.angular_velocity_covariance
    if cov is None or len(imu) < 2:
        return 0.0
    var = float(np.mean(np.asarray(cov, dtype=float).reshape(9)[[0, 4, 8]]))
    dt = float(np.median(np.diff(imu.stamp_ns))) * 1e-9
    return max(var, 0.0) * dt


def _random_walk_term(cov: np.ndarray, J: np.ndarray, w: np.ndarray, s2: float,
                      frames: Sequence[Any], t_ref: float, q: float) -> np.ndarray:
    """Covariance added by gyro angle random walk (sandwich form).

    The gyro-propagated attitude of frame k carries an error ``a_k`` with
    ``Cov(a_k, a_l) = q · min(s_k, s_l) · I`` (``s = |t − t_ref|``, same side of the reference
    frame; independent sides), common to all stars of the frame.  With the whitened star rows
    ``J_k`` of frame k and their attitude block ``A_k = J_k[:, :3]`` the estimate moves by
    ``N⁻¹ Σ_k J_kᵀ W_k A_k a_k / s²``, so the extra covariance is
    ``N⁻¹ [Σ_kl M_k Q_kl M_lᵀ] N⁻¹ / s⁴`` with ``M_k = J_kᵀ W_k A_k``, accumulated with tail
    sums over the sorted ``s`` (Brownian covariance = ∫ 1[u < s_k] 1[u < s_l] du).
    """
    n_x = J.shape[1]
    rows = np.cumsum([0] + [2 * len(f.uv) for f in frames])
    Ms, ss, side = [], [], []
    for k, f in enumerate(frames):
        Jk = J[rows[k]:rows[k + 1]]
        wk = w[rows[k]:rows[k + 1]]
        Ms.append((Jk * wk[:, None]).T @ Jk[:, :3])
        ss.append(abs(f.t_rel - t_ref))
        side.append(f.t_rel >= t_ref)
    Z = np.zeros((n_x, n_x))
    for sgn in (True, False):
        sel = [k for k in range(len(frames)) if side[k] == sgn]
        if not sel:
            continue
        sel.sort(key=lambda k: ss[k])
        tail = np.zeros((n_x, 3))
        tails = []
        for k in reversed(sel):
            tail = tail + Ms[k]
            tails.append(tail.copy())
        tails.reverse()
        prev = 0.0
        for j, k in enumerate(sel):
            du = ss[k] - prev
            prev = ss[k]
            Z += du * tails[j] @ tails[j].T
    # whitened residuals: attitude error a shifts r by A a (A already divided by σ)
    Z *= q / (s2 * s2)
    return cov @ Z @ cov


def _observability(J: np.ndarray, n_star: int, weights: np.ndarray, scale: np.ndarray,
                   names: list[str], cov: np.ndarray, prior_sigma: np.ndarray,
                   s2: float) -> ObservabilityReport:
    Js = J[:n_star] * np.sqrt(weights / s2)[:, None] * scale[None, :]
    _, sv, Vt = np.linalg.svd(Js, full_matrices=False)
    weak = []
    for i in np.flatnonzero(sv < 1.0):
        v = Vt[i]
        order = np.argsort(-np.abs(v))
        comb = {names[j]: float(v[j]) for j in order if abs(v[j]) > 0.1}
        weak.append({"singular_value": float(sv[i]), "combination": comb})
    sig = np.sqrt(np.diag(cov))
    ratio = {n: float(s / p) for n, s, p in zip(names, sig, prior_sigma, strict=True)
             if np.isfinite(p)}
    dominated = [n for n, q in ratio.items() if q > 0.5]
    corr = cov / np.outer(sig, sig)
    pairs = []
    for a in range(len(names)):
        for b in range(a + 1, len(names)):
            if abs(corr[a, b]) > 0.9:
                pairs.append((names[a], names[b], float(corr[a, b])))
    return ObservabilityReport(names, sv, Vt.T, weak, dominated, ratio, pairs)
