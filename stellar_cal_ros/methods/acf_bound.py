"""Cramér–Rao bound of the ACF calibration and its errors against a known truth.

For tests and benchmarks (a calibration never sees the truth): :func:`crlb_acf` is the
Fisher bound of :func:`~stellar_cal_ros.methods.acf.run_acf`'s problem at the true
parameters, :func:`installation_error_arcsec` / :func:`grid_projection_error` measure a
result against the truth (the latter over the detector, optionally without the rotation
about a single sweep axis, :func:`sweep_axis_imu`, that no method can observe).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from stellar_cal_ros.core.rotation import so3_exp, so3_log
from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.effects.registry import create_many
from stellar_cal_ros.errors import StellarCalError
from stellar_cal_ros.io.calibration import Calibration
from stellar_cal_ros.methods.acf import (
    ACF_EFFECTS,
    MIN_FRAMES,
    MIN_STARS_PER_FRAME,
    AcfResult,
    _initial_attitude,
    _prepare_frames,
    _Problem,
)
from stellar_cal_ros.methods.acf_covariance import _arw_density, _inverse
from stellar_cal_ros.methods.acf_data import AcfData, GyroChain, load_acf_data, select_frames
from stellar_cal_ros.methods.star_model import StarModel


def installation_error_covariance(cov: np.ndarray, model: StarModel,
                                  theta: np.ndarray) -> np.ndarray:
    """Covariance (arcsec², tracker axes) of :func:`installation_error_arcsec` from θ's.

    The installation parameter δ is a right rotation of the prior's mounting, so an error
    ``ε = δ̂ − δ`` moves ``Log(R_truthᵀ R_est)`` by ``J_r(δ) ε``: with δ of a few degrees the
    mixing (a few %) matters when one component (about a sweep axis) rests on a wide prior.
    ``cov`` is the covariance of θ (P, P) or of ``[φ, θ]`` (3 + P, 3 + P).
    """
    from stellar_cal_ros.core.rotation import right_jacobian

    off = cov.shape[0] - model.size
    sl = model.slices["installation"]
    idx = np.arange(sl.start, sl.stop) + off
    Jr = right_jacobian(theta[sl])
    return Jr @ cov[np.ix_(idx, idx)] @ Jr.T / ARCSEC ** 2


@dataclass
class AcfBound:
    """Cramér–Rao bound of the ACF problem at the true parameters (:func:`crlb_acf`).

    All matrices are covariances of ``[φ, θ]`` (first-frame attitude, then the model's θ in
    its units), the nuisance φ included and marginalised by the inversion:

    * ``crlb_white`` — centroid noise only: the gyro chain ties the attitudes exactly;
    * ``crlb`` — with the gyro angle random walk: the attitudes of the frames carry the
      random-walk errors ``a_k`` (``Cov(a_k, a_l) = q min(s_k, s_l) I``, ``s = |t − t_ref|``,
      same side of the reference frame), i.e. the data covariance is
      ``σ² I + Σ A_k Q_kl A_lᵀ`` — the bound of an estimator weighting by that covariance;
    * ``estimator`` — the covariance of :func:`run_acf` with the linear loss (least squares
      with weights 1/σ², random walk ignored in the fit) in the same linearisation:
      ``N⁻¹ + N⁻¹ (Σ M_k Q_kl M_lᵀ) N⁻¹`` (what run_acf reports with σ̂ = σ).

    The prior rows ``(θ − θ_prior)/σ_prior`` are part of the information in all three (the
    estimator has them); with wide priors they matter only for unobservable directions (the
    installation about a single-axis sweep axis), where the "bound" is the prior.
    """

    parameter_names: list[str]
    model: StarModel
    theta_true: np.ndarray
    crlb_white: np.ndarray
    crlb: np.ndarray
    estimator: np.ndarray
    arw_q: float  # rad²/s
    n_frames: int
    n_stars: int
    jacobian: np.ndarray  # whitened star rows then prior rows, at the truth

    def sigma(self, which: str = "crlb") -> np.ndarray:
        """1-σ of ``[φ, θ]`` from ``crlb``, ``crlb_white`` or ``estimator``."""
        return np.sqrt(np.diag(getattr(self, which)))

    def installation_sigma_arcsec(self, which: str = "crlb") -> np.ndarray:
        """1-σ (arcsec, tracker axes) of :func:`installation_error_arcsec`."""
        cov = installation_error_covariance(getattr(self, which), self.model, self.theta_true)
        return np.sqrt(np.diag(cov))


def crlb_acf(
    source: str | os.PathLike[str] | AcfData,
    prior: Calibration,
    truth: Calibration,
    effects: Sequence[str] | None = None,
    *,
    frames: Any = None,
    sigma_px: float | None = None,
    gyro_arw: float | None = None,
    reference_frame: int = 0,
) -> AcfBound:
    """Cramér–Rao bound of the ACF calibration (Fisher ``Jᵀ R⁻¹ J`` at the truth).

    The model is run_acf's: effects (default :data:`ACF_EFFECTS`) with the prior's σ as
    prior information, the first-frame attitude φ as nuisance, every identified star of the
    selected frames (no gate), centroid σ from the messages or ``sigma_px``.  The Jacobian is
    :class:`_Problem`'s analytic one at θ = the truth (:func:`~stellar_cal_ros.methods.
    replay.truth_parameters`), with the gyro chain propagated from the measured rates
    corrected by the true sensor parameters and the reference attitude from a joint Wahba
    fit under the true camera and installation (error ~1", immaterial for the Jacobian).
    ``gyro_arw`` as for :func:`run_acf` (rad/√s; default from the IMU messages).  See
    :class:`AcfBound` for the three covariances returned.

    Model mismatch (a gyro bias that is not estimated, astrometric effects) does not enter a
    bound; it shows as errors beyond it.
    """
    from stellar_cal_ros.methods.replay import truth_parameters

    data = source if isinstance(source, AcfData) else load_acf_data(source)
    ids = list(ACF_EFFECTS if effects is None else effects)
    model = StarModel(create_many(ids), prior)
    theta = truth_parameters(model, truth)
    chain = GyroChain(data, model, theta)
    idx = select_frames(len(data.frames), frames)
    fr = _prepare_frames(data, idx, chain, prior.time_offset, sigma_px, MIN_STARS_PER_FRAME)
    if len(fr) < MIN_FRAMES:
        raise StellarCalError(f"the bound needs at least {MIN_FRAMES} frames with stars")
    t_ref = fr[min(max(reference_frame, 0), len(fr) - 1)].t_rel + prior.time_offset
    R_i_b0 = _initial_attitude(fr, chain, model, theta, t_ref, None)
    for f in fr:
        f.use = None  # every identified star
    problem = _Problem(model, chain, fr, R_i_b0, t_ref, model.initial_value,
                       model.initial_sigma)
    problem.theta_lin = theta.copy()
    _, J = problem.evaluate(np.concatenate([np.zeros(3), theta]))
    n_star = problem.n_star
    Js = J[:n_star]
    info = Js.T @ Js + J[n_star:].T @ J[n_star:]
    cov_white = _inverse(info)
    q = _arw_density(data.imu, gyro_arw)
    if q > 0:
        # whitened data covariance I + B Q Bᵀ, B = blockdiag(A_k), A_k = attitude columns
        rows = np.cumsum([0] + [2 * len(f.uv) for f in fr])
        m = len(fr)
        M = np.zeros((problem.n_x, 3 * m))
        BtB = np.zeros((3 * m, 3 * m))
        s = np.array([abs(f.t_rel - t_ref) for f in fr])
        side = np.array([f.t_rel >= t_ref for f in fr])
        for k in range(m):
            Jk = Js[rows[k]:rows[k + 1]]
            M[:, 3 * k:3 * k + 3] = Jk.T @ Jk[:, :3]
            BtB[3 * k:3 * k + 3, 3 * k:3 * k + 3] = Jk[:, :3].T @ Jk[:, :3]
        K = np.where(side[:, None] == side[None, :], np.minimum(s[:, None], s[None, :]), 0.0)
        Q = q * np.kron(K, np.eye(3))
        # Woodbury: Jᵀ(I + BQBᵀ)⁻¹J = JᵀJ − M Q (I + BᵀB Q)⁻¹ Mᵀ
        Y = np.linalg.solve(np.eye(3 * m) + Q @ BtB, Q)  # = (I + Q BᵀB)⁻¹ Q, symmetric
        Y = 0.5 * (Y + Y.T)
        cov = _inverse(info - M @ Y @ M.T)
        est = cov_white + cov_white @ (M @ Q @ M.T) @ cov_white
    else:
        cov = est = cov_white
    names = ["attitude.phi_x", "attitude.phi_y", "attitude.phi_z"] + model.parameter_names()
    return AcfBound(names, model, theta, cov_white, cov, 0.5 * (est + est.T), q, len(fr),
                    n_star // 2, J)


def installation_error_arcsec(estimated: Calibration, truth: Calibration) -> np.ndarray:
    """Rotation vector (arcsec, tracker axes) of ``R_truthᵀ R_estimated``."""
    dR = truth.R_imu_st.T @ estimated.R_imu_st
    return so3_log(dR) / ARCSEC


def sweep_axis_imu(result: AcfResult) -> np.ndarray:
    """Unit rotation axis (IMU frame) of the gyro attitude change from first to last frame.

    For a single-axis sweep, an installation rotation about this axis cannot be told from a
    first-attitude rotation: the :func:`grid_projection_error` can remove it.
    """
    t = result.data.rel(np.array([result.data.frames[i].stamp_ns for i in result.frames]))
    R0, _ = result.chain.attitude(float(t.min()))
    R1, _ = result.chain.attitude(float(t.max()))
    a = so3_log(R0.T @ R1)
    return a / np.linalg.norm(a)


def grid_projection_error(estimated: Calibration, truth: Calibration, n: int = 21,
                          free_axis_imu: np.ndarray | None = None) -> tuple[float, float]:
    """Worst and RMS pixel error over an n×n detector grid of the IMU-direction mapping.

    Each grid pixel is unprojected with the true camera and installation to an IMU-frame
    direction, which is then projected with the estimated installation and camera.  With
    ``free_axis_imu`` the estimated installation is first rotated about that IMU axis by the
    angle that minimises the RMS (the component a single-axis sweep cannot observe).
    """
    cam_t, cam_e = truth.camera, estimated.camera
    g = np.linspace(0.0, 1.0, n)
    uu, vv = np.meshgrid(g * (cam_t.width - 1), g * (cam_t.height - 1))
    uv = np.column_stack([uu.ravel(), vv.ravel()])
    v_imu = cam_t.unproject(uv) @ truth.R_imu_st.T

    def errors(alpha: float) -> np.ndarray:
        R = estimated.R_imu_st
        if free_axis_imu is not None:
            R = so3_exp(alpha * np.asarray(free_axis_imu, dtype=float)) @ R
        return np.linalg.norm(cam_e.project(v_imu @ R) - uv, axis=1)

    alpha = 0.0
    if free_axis_imu is not None:
        from scipy.optimize import minimize_scalar

        alpha = float(minimize_scalar(lambda a: float(np.mean(errors(a) ** 2)),
                                      bounds=(-0.1, 0.1), method="bounded",
                                      options={"xatol": 1e-10}).x)
    e = errors(alpha)
    return float(np.max(e)), float(np.sqrt(np.mean(e ** 2)))
