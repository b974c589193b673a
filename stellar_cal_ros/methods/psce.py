"""PSCE Kalman filter: predicted-star-centroid-error calibration (Tan et al., Sensors 2018).

Error-state extended Kalman filter.  Nominal state: the IMU attitude ``R̂_i_b`` and the
parameter vector ``θ̂`` of the model's effects (baseline: ``gyro_bias, installation,
principal_point, focal_length, radial_k1k2, tangential`` — Tan et al. eq. 21).  Error state
``x = [φ (3), δθ (P)]`` with the attitude error a left perturbation in the inertial frame,
``R_i_b = Exp(φ) R̂_i_b`` (their eq. 7).

Process model (their eqs. 17-22, generalized to any GYRO-stage effect)::

    φ̇ = R̂_i_b (ω − ω̂) = R̂_i_b G δθ − R̂_i_b n_g,    G = −(I + E)⁻¹ (∂b/∂θ + ∂E/∂θ · ω̂)
    δθ̇ = n_θ   (random walk, zero for constants)

There is no φ term in φ̇, so the transition over a star interval is *exactly*
``Φ = [[I, Σ_j R̂_j G_j Δt_j], [0, I]]`` and ``Q_φφ = σ_g² Σ Δt · I`` (isotropic gyro noise
is invariant under rotation).  The covariance is therefore propagated once per star frame
with this exact discretization, summed over the IMU samples in between: cheaper than a
per-sample update and no less accurate.

Measurement (their eqs. 23-26): the centroid of every identified star, predicted through
the effects (:class:`~stellar_cal_ros.methods.star_model.StarModel`), minus the extracted
one.  Stars are χ² gated one by one (2 dof) on the innovation covariance, then all accepted
stars of the frame are processed together by an iterated EKF update (re-linearizing while
the correction is large, as at start-up when the datasheet model is pixels off) with the
Joseph-form covariance update, followed by the reset ``R̂ ← Exp(δφ) R̂``, ``θ̂ ← θ̂ + δθ``.

Initialization: the first frame with enough stars gives the attitude by a pixel-space Wahba
fit under the prior model; its error is correlated with the camera and installation errors
(a principal point offset is indistinguishable from an attitude tilt in one frame), and the
initial covariance carries exactly that correlation: ``φ₀ = −M δθ + noise`` with
``M = (H_φᵀH_φ)⁻¹ H_φᵀ H_θ``.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field

import numpy as np

from stellar_cal_ros.core.attitude import fit_frame_attitude
from stellar_cal_ros.core.kalman import block_nis, chi2_gate, joseph_update
from stellar_cal_ros.core.rotation import (
    quat_from_matrix,
    quat_from_rotvec,
    quat_to_matrix,
    skew,
    so3_exp,
)
from stellar_cal_ros.core.strapdown import attitude_increments, quat_cumprod
from stellar_cal_ros.effects.base import FrameContext, Stage
from stellar_cal_ros.errors import ModelError
from stellar_cal_ros.methods.star_model import StarModel

log = logging.getLogger(__name__)

BASELINE_EFFECTS = (
    "gyro_bias",
    "installation",
    "principal_point",
    "focal_length",
    "radial_k1k2",
    "tangential",
)


@dataclass
class PsceConfig:
    """Noise levels and decisions of the PSCE filter."""

    centroid_sigma_px: float = 0.05  #: used when a star message has sigma = 0
    gyro_arw_deg_sqrth: float = 0.001  #: angle random walk of each gyro
    gate_probability: float = 0.9999  #: per-star χ² (2 dof) acceptance probability
    min_stars: int = 3  #: fewer accepted stars: the frame is skipped
    max_iterations: int = 5  #: iterated-EKF relinearizations per frame
    iteration_tolerance: float = 1e-3  #: stop when the correction changes < tol·σ
    relinearize_rad: float = 2e-4  #: iterate only if the attitude correction exceeds this
    relinearize_sigma: float = 0.5  #: ... or a parameter moves by more than this × σ
    imu_gap_factor: float = 3.0  #: an IMU interval longer than this × nominal is a gap
    gap_rate_sigma: float = 1e-3  #: rad/s, rate uncertainty over an IMU gap
    init_outlier_px: float = 5.0  #: init: drop stars off by more than this after the fit


@dataclass
class FrameUpdate:
    """What one star-frame update did (for residual files and statistics)."""

    stamp: float
    t_exposure: float
    accepted: np.ndarray  # (n,) bool
    uv: np.ndarray  # (n, 2) measured
    uv_pred: np.ndarray  # (n, 2) predicted before the update (innovation = uv − uv_pred)
    S: np.ndarray  # (n, 2, 2) innovation covariance of each star
    nis_stars: np.ndarray  # (n,)
    nis: float  # frame NIS over the accepted stars
    dof: int
    directions_st: np.ndarray  # (n, 3)
    omega_b: np.ndarray  # (3,)
    iterations: int


@dataclass
class FilterCounters:
    """Counted (and logged) skips and events."""

    frames: int = 0
    updates: int = 0
    init_frames: int = 0
    skipped_few_stars: int = 0
    skipped_out_of_order: int = 0
    skipped_duplicate: int = 0
    skipped_no_imu: int = 0
    stars_invalid: int = 0
    stars_gated: int = 0
    imu_gaps: int = 0
    extra: dict[str, int] = field(default_factory=dict)


class PsceFilter:
    """The PSCE error-state Kalman filter over contract IMU samples and star frames.

    Parameters
    ----------
    model : StarModel
        Effects (state layout) and the prior.
    imu_t : ndarray (N,)
        IMU stamps, s relative to ``t0`` (end of each sample interval).
    imu_w : ndarray (N, 3)
        Measured mean rates, rad/s.
    t0 : float
        POSIX time of relative time zero (for the effects' context).
    config : PsceConfig
    """

    def __init__(self, model: StarModel, imu_t: np.ndarray, imu_w: np.ndarray, t0: float,
                 config: PsceConfig | None = None) -> None:
        self.model = model
        self.config = config or PsceConfig()
        self.t0 = t0
        self.imu_t = np.asarray(imu_t, dtype=float)
        self.imu_w = np.asarray(imu_w, dtype=float)
        self.nominal_dt = float(np.median(np.diff(self.imu_t))) if len(self.imu_t) > 1 else 0.01
        self.theta = model.initial_value.copy()
        n = 3 + model.size
        self.P = np.zeros((n, n))
        self.P[3:, 3:] = np.diag(model.initial_sigma**2)
        self.q_theta = np.concatenate(
            [e.process_noise_density() for e in model.effects]) ** 2 if model.effects \
            else np.zeros(0)
        self.q_gyro = (np.deg2rad(self.config.gyro_arw_deg_sqrth) / 60.0) ** 2
        self.R_i_b: np.ndarray | None = None
        self.t: float | None = None
        self.omega = np.zeros(3)
        self._k = 0  # index of the first IMU sample whose interval ends after self.t
        self.counters = FilterCounters()
        self.gate = chi2_gate(self.config.gate_probability, 2)
        self.last_stamp: float | None = None

    # ------------------------------------------------------------------ propagation
    def extend_imu(self, imu_t: np.ndarray, imu_w: np.ndarray) -> int:
        """Append IMU samples (live use); returns how many were accepted.

        Samples not later than the last one held, or with non-finite values, are dropped
        and counted (``counters.extra['imu_dropped']``).
        """
        t = np.asarray(imu_t, dtype=float).reshape(-1)
        w = np.asarray(imu_w, dtype=float).reshape(-1, 3)
        last = self.imu_t[-1] if len(self.imu_t) else -np.inf
        ok = np.isfinite(t) & np.all(np.isfinite(w), axis=1)
        ok &= t > last
        ok &= np.concatenate([[True], np.diff(t) > 0]) if len(t) else ok
        if len(t) and not np.all(np.diff(t[ok]) > 0):
            ok[:] = False  # unordered batch: let the caller sort it
        dropped = int(len(t) - ok.sum())
        if dropped:
            self.counters.extra["imu_dropped"] = self.counters.extra.get("imu_dropped", 0) + dropped
        self.imu_t = np.concatenate([self.imu_t, t[ok]])
        self.imu_w = np.concatenate([self.imu_w, w[ok]])
        return int(ok.sum())

    @property
    def initialized(self) -> bool:
        """True once the attitude has been initialized from a star frame."""
        return self.R_i_b is not None

    def _segments(self, t_target: float) -> tuple[np.ndarray, np.ndarray, int]:
        """Interval lengths and raw rates from ``self.t`` to ``t_target``."""
        k = self._k
        m = int(np.searchsorted(self.imu_t, t_target, side="left"))
        if m >= len(self.imu_t):
            raise _NoImuError()
        ends = np.concatenate([self.imu_t[k:m], [t_target]])
        starts = np.concatenate([[self.t], self.imu_t[k:m]])
        return ends - starts, self.imu_w[k:m + 1], m

    def propagate(self, t_target: float) -> None:
        """Propagate nominal attitude and covariance to ``t_target`` (relative s)."""
        if t_target <= self.t:
            if t_target < self.t - 1e-9:
                raise ModelError("cannot propagate backwards in time")
            return
        dts, w_raw, m = self._segments(t_target)
        theta = self.theta
        b, E, Jb, JE = self.model.sensor_model(theta, Stage.GYRO)
        if np.any(E):
            A = np.linalg.inv(np.eye(3) + E)
            w_hat = (w_raw - b) @ A.T
        else:
            A = None
            w_hat = w_raw - b
        phi = attitude_increments(w_hat, dts, coning=True)
        q = np.empty((len(phi) + 1, 4))
        q[0] = quat_from_matrix(self.R_i_b)
        q[1:] = quat_from_rotvec(phi)
        qs = quat_cumprod(q)
        R_all = quat_to_matrix(qs[1:])
        # Φ_φθ = Σ R̂_j G_j Δt_j
        if self.model.size:
            Rdt = np.einsum("nij,n->ij", R_all, dts)
            G_b = -Jb if A is None else -A @ Jb
            Phi = Rdt @ G_b
            if np.any(JE):
                # −Σ R̂_j (I+E)⁻¹ (∂E/∂θ ω̂_j) Δt_j
                JEw = np.einsum("ijp,nj->nip", JE, w_hat)
                if A is not None:
                    JEw = np.einsum("ik,nkp->nip", A, JEw)
                Phi = Phi - np.einsum("nij,njp,n->ip", R_all, JEw, dts)
            P = self.P
            Pfa = P[:3, 3:] + Phi @ P[3:, 3:]
            P[:3, :3] = P[:3, :3] + Phi @ P[3:, :3] + P[:3, 3:] @ Phi.T + Phi @ P[3:, 3:] @ Phi.T
            P[:3, 3:] = Pfa
            P[3:, :3] = Pfa.T
        total = float(np.sum(dts))
        self.P[:3, :3] += self.q_gyro * total * np.eye(3)
        if self.model.size:
            self.P[3:, 3:] += np.diag(self.q_theta * total)
        gaps = dts[1:-1] > self.config.imu_gap_factor * self.nominal_dt if len(dts) > 2 else []
        if np.any(gaps):
            n_gap = int(np.sum(gaps))
            self.counters.imu_gaps += n_gap
            gap_time = float(np.sum(dts[1:-1][gaps]))
            self.P[:3, :3] += (self.config.gap_rate_sigma * gap_time) ** 2 * np.eye(3)
            log.warning("IMU gap of %.3f s before t=%.3f s: attitude uncertainty inflated",
                        gap_time, t_target)
        self.R_i_b = R_all[-1]
        self.omega = w_hat[-1]
        self.t = t_target
        self._k = m

    def rate_at(self, t: float) -> np.ndarray:
        """Corrected body rate of the IMU sample covering relative time ``t``."""
        m = min(int(np.searchsorted(self.imu_t, t, side="left")), len(self.imu_t) - 1)
        return self.model.corrected_rates(self.theta, self.imu_w[m:m + 1])[0]

    # ------------------------------------------------------------------ star frames
    def initialize(self, uv: np.ndarray, u_i: np.ndarray, ctx: FrameContext,
                   sigma: np.ndarray) -> bool:
        """Initialize the attitude from one frame; return False if it cannot."""
        model, theta = self.model, self.theta
        shift, _ = model.time_shift(theta, ctx)
        t_exp = ctx.stamp - self.t0 + shift
        if t_exp <= self.imu_t[0] - self.nominal_dt or t_exp >= self.imu_t[-1]:
            self.counters.skipped_no_imu += 1
            return False
        camera = model.camera_at(theta, ctx)
        R_imu_st, _ = model.installation_at(theta, ctx)
        keep = np.ones(len(uv), dtype=bool)
        fit = None
        for _ in range(3):
            if keep.sum() < max(self.config.min_stars, 3):
                return False
            fit = fit_frame_attitude(camera, uv[keep], u_i[keep])
            err = np.linalg.norm(fit.residuals, axis=1)
            bad = err > max(self.config.init_outlier_px, 5 * float(np.median(err)))
            if not np.any(bad):
                break
            idx = np.flatnonzero(keep)
            keep[idx[bad]] = False
        R_i_b = fit.R_i_st @ R_imu_st.T
        self.t = t_exp
        self._k = int(np.searchsorted(self.imu_t, t_exp, side="left"))
        self.R_i_b = R_i_b
        self.omega = self.rate_at(t_exp)
        pred = model.predict(theta, u_i[keep], _subset_context(ctx, np.flatnonzero(keep)),
                             self._attitude_function())
        Hf = pred.H_attitude.reshape(-1, 3)
        Ht = pred.H_parameters.reshape(-1, model.size)
        info = Hf.T @ Hf
        M = np.linalg.solve(info, Hf.T @ Ht) if model.size else np.zeros((3, 0))
        s2 = float(np.mean(sigma[keep] ** 2))
        Ptt = self.P[3:, 3:]
        self.P[:3, :3] = M @ Ptt @ M.T + s2 * np.linalg.inv(info)
        self.P[:3, 3:] = -M @ Ptt
        self.P[3:, :3] = self.P[:3, 3:].T
        self.counters.init_frames += 1
        log.info("attitude initialized at t=%.3f s from %d stars", t_exp, int(keep.sum()))
        return True

    def _attitude_function(self, phi: np.ndarray | None = None):
        R_now = self.R_i_b if phi is None else so3_exp(phi) @ self.R_i_b
        t_now, w = self.t, self.omega

        def attitude(t_posix: float) -> tuple[np.ndarray, np.ndarray]:
            dt = t_posix - self.t0 - t_now
            R = R_now if abs(dt) < 1e-12 else R_now @ so3_exp(w * dt)
            return R, w

        return attitude

    def update(self, uv: np.ndarray, u_i: np.ndarray, ctx: FrameContext,
               sigma: np.ndarray) -> FrameUpdate | None:
        """Propagate to the frame's exposure and update with its stars."""
        model = self.model
        shift, _ = model.time_shift(self.theta, ctx)
        t_exp = ctx.stamp - self.t0 + shift
        try:
            self.propagate(t_exp)
        except _NoImuError:
            self.counters.skipped_no_imu += 1
            return None
        n = len(uv)
        R_meas = sigma**2
        theta0 = self.theta.copy()
        pred0 = model.predict(theta0, u_i, ctx, self._attitude_function())
        H0 = np.concatenate([pred0.H_attitude, pred0.H_parameters], axis=2)  # (n,2,N)
        nu0 = uv - pred0.uv
        S_blocks = np.einsum("nij,jk,nlk->nil", H0, self.P, H0)
        S_blocks[:, 0, 0] += R_meas
        S_blocks[:, 1, 1] += R_meas
        nis_stars = block_nis(nu0, S_blocks)
        accepted = nis_stars <= self.gate
        self.counters.stars_gated += int(n - accepted.sum())
        result = FrameUpdate(ctx.stamp, t_exp, accepted, uv, pred0.uv, S_blocks, nis_stars,
                             float("nan"), 0, pred0.directions_st, self.omega.copy(), 0)
        if accepted.sum() < self.config.min_stars:
            self.counters.skipped_few_stars += 1
            return result
        idx = np.flatnonzero(accepted)
        ctx_acc = _subset_context(ctx, idx)
        z = uv[idx].reshape(-1)
        Rm = np.repeat(R_meas[idx], 2)
        N = 3 + model.size
        dx = np.zeros(N)
        H = H0[idx].reshape(-1, N)
        h = pred0.uv[idx].reshape(-1)
        it = 0
        sig = np.sqrt(np.diag(self.P))
        for it in range(1, self.config.max_iterations + 1):
            PHt = self.P @ H.T
            S = H @ PHt + np.diag(Rm)
            K = np.linalg.solve(S, PHt.T).T
            dx_new = K @ (z - h + H @ dx)
            change = np.max(np.abs(dx_new - dx) / np.maximum(sig, 1e-300))
            dx = dx_new
            if it == self.config.max_iterations:
                break
            if it == 1:
                # Relinearize only if the correction is large enough for second-order terms
                # to matter: a rotation of more than relinearize_rad or a parameter moving by
                # more than relinearize_sigma of its prior-relative uncertainty.
                small = np.linalg.norm(dx[:3]) < self.config.relinearize_rad and np.all(
                    np.abs(dx[3:]) < self.config.relinearize_sigma * np.maximum(sig[3:], 1e-300)
                )
                if small:
                    break
            elif change < self.config.iteration_tolerance:
                break
            pred = model.predict(theta0 + dx[3:], u_i[idx], ctx_acc,
                                 self._attitude_function(dx[:3]))
            H = np.concatenate([pred.H_attitude, pred.H_parameters], axis=2).reshape(-1, N)
            h = pred.uv.reshape(-1)
        nu = z - pred0.uv[idx].reshape(-1)
        S0 = H0[idx].reshape(-1, N) @ self.P @ H0[idx].reshape(-1, N).T + np.diag(Rm)
        nis = float(nu @ np.linalg.solve(S0, nu))
        self.P = joseph_update(self.P, K, H, np.diag(Rm))
        # reset: R ← Exp(δφ) R, θ ← θ + δθ; left-error reset Jacobian I + ½[δφ]×
        dphi = dx[:3]
        self.R_i_b = so3_exp(dphi) @ self.R_i_b
        self.theta = theta0 + dx[3:]
        G = np.eye(3) + 0.5 * skew(dphi)
        self.P[:3, :] = G @ self.P[:3, :]
        self.P[:, :3] = self.P[:, :3] @ G.T
        self.omega = self.rate_at(self.t)
        self.counters.updates += 1
        result.nis = nis
        result.dof = int(len(z))
        result.iterations = it
        return result

    def process_frame(self, uv: np.ndarray, u_i: np.ndarray, ctx: FrameContext,
                      sigma: np.ndarray) -> FrameUpdate | None:
        """Handle one (cleaned) star frame: initialize or update; count skips."""
        self.counters.frames += 1
        if self.last_stamp is not None:
            if ctx.stamp == self.last_stamp:
                self.counters.skipped_duplicate += 1
                return None
            if ctx.stamp < self.last_stamp:
                self.counters.skipped_out_of_order += 1
                log.warning("star frame at %.6f is older than the last one: skipped", ctx.stamp)
                return None
        if len(uv) < self.config.min_stars:
            self.counters.skipped_few_stars += 1
            return None
        self.last_stamp = ctx.stamp
        if not self.initialized:
            self.initialize(uv, u_i, ctx, sigma)
            return None
        return self.update(uv, u_i, ctx, sigma)

    # ------------------------------------------------------------------ outputs
    def sigma(self) -> np.ndarray:
        """1-sigma of the error state [φ, θ]."""
        return np.sqrt(np.clip(np.diag(self.P), 0.0, None))


def _subset_context(ctx: FrameContext, idx: np.ndarray) -> FrameContext:
    """The context of a subset of the frame's stars (per-star arrays sliced)."""
    return dataclasses.replace(
        ctx,
        catalog_id=np.asarray(ctx.catalog_id)[idx] if len(ctx.catalog_id) else ctx.catalog_id,
        magnitude=np.asarray(ctx.magnitude)[idx] if len(ctx.magnitude) else ctx.magnitude,
        extra={},
    )


class _NoImuError(Exception):
    """The IMU data do not reach the requested time."""
