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
initial covariance carries exactly that correlation: ``φ₀ = −M δθ + r + noise`` with
``M = (H_φᵀH_φ)⁻¹ H_φᵀ H_θ`` and ``r`` the second-order remainder in δθ, whose second
moment is measured by refitting the frame at sigma points of the prior (datasheet priors make
``r`` ~10 µrad: negligible beside the noise of a 0.05-px tracker, dominant for a noise-free
one, which without it started with NEES ~1000 and ended inconsistent).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg.lapack import dpotrf as _potrf
from scipy.linalg.lapack import dpotrs as _potrs
from scipy.linalg.lapack import dtrtrs as _trtrs

from stellar_cal_ros.core.attitude import fit_frame_attitude, wahba
from stellar_cal_ros.core.kalman import block_nis, check_covariance, chi2_gate
from stellar_cal_ros.core.rotation import (
    quat_from_matrix,
    quat_from_rotvec,
    quat_to_matrix,
    so3_exp,
    so3_log,
)
from stellar_cal_ros.core.strapdown import (
    _quat_multiply_soa,
    attitude_increments,
    quat_cumprod,
)
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
    fov_margin: float = 1.3  #: stars predicted beyond this × the half-diagonal: rejected
    gap_reacquire_s: float = 0.1  #: a frame after more IMU gap than this re-acquires attitude
    init_outlier_px: float = 5.0  #: init: drop stars off by more than this after the fit
    mismatch_factor: float = 3.0  #: frame median NIS this × the χ² median: model mismatch
    lost_lock_factor: float = 1e4  #: ... this ×: the attitude is lost, the frame rejected
    reinit_after: int = 3  #: consecutive frames with stars but no accepted update: re-acquire
    covariance_check_every: int = 50  #: check P (finite, symmetric, PD) every N updates
    fast_propagation: bool = True  #: prefix-integrated gyro (exact to 2nd order in δθ)
    fast_propagation_max_rad: float = 1e-5  #: larger first-order corrections: exact path


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
    reinitializations: int = 0
    covariance_checks: int = 0
    covariance_repairs: int = 0
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
    nominal_dt : float, optional
        Nominal IMU interval (gap detection, the first sample's interval); default the
        median interval of ``imu_t``.
    """

    def __init__(self, model: StarModel, imu_t: np.ndarray, imu_w: np.ndarray, t0: float,
                 config: PsceConfig | None = None, *, nominal_dt: float | None = None) -> None:
        self.model = model
        self.config = config or PsceConfig()
        self.t0 = t0
        self.imu_t = np.asarray(imu_t, dtype=float)
        self.imu_w = np.asarray(imu_w, dtype=float)
        # (t buffer, w buffer, imu_t view, imu_w view) of _append_imu; not state
        self._imu_cap: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        if nominal_dt is not None:
            self.nominal_dt = float(nominal_dt)
        else:
            self.nominal_dt = float(np.median(np.diff(self.imu_t))) if len(self.imu_t) > 1 \
                else 0.01
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
        self._mismatch_warned = False
        self._mismatch_bits = 0  # model-mismatch flags of the last 10 frames
        self.last_stamp: float | None = None
        self._eye = np.eye(n)
        self._rejected_in_row = 0
        self._gap_pending = False
        cam = model.prior.camera
        half_diag = np.hypot(max(cam.cx, cam.width - cam.cx), max(cam.cy, cam.height - cam.cy))
        self._fov_r2 = (self.config.fov_margin * half_diag / min(cam.fx, cam.fy)) ** 2
        self._good: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._stamp_posix = 0.0  # reported stamp of the frame being processed (POSIX s)
        self._stamp_rel = 0.0  # the same, relative to t0 (from integer ns: exact)
        self._prefix: _ImuPrefix | None = None
        b, E, Jb, JE = model.sensor_model(self.theta, Stage.GYRO)
        # Fast propagation needs rates linear in θ with a constant Jacobian: bias-type GYRO
        # effects only (∂E/∂θ = 0); scale-factor / misalignment effects use the exact path.
        self._gyro_linear = not np.any(JE)
        if self.config.fast_propagation and self._gyro_linear:
            self._prefix = _ImuPrefix(self.nominal_dt, self.theta, b, E, Jb,
                                      self.config.imu_gap_factor)
            self._prefix.extend(self.imu_t, self.imu_w)

    # ------------------------------------------------------------------ propagation
    def extend_imu(self, imu_t: np.ndarray, imu_w: np.ndarray) -> int:
        """Append IMU samples (live use); returns how many were accepted.

        Samples not later than the last one held, or with non-finite values, are dropped
        and counted (``counters.extra['imu_dropped']``).
        """
        t = np.asarray(imu_t, dtype=float).reshape(-1)
        w = np.asarray(imu_w, dtype=float).reshape(-1, 3)
        last = float(self.imu_t[-1]) if len(self.imu_t) else -np.inf
        if len(t) <= _SMALL:  # live use: the same decisions without the array machinery
            ok = _imu_ok_small(t.tolist(), w.tolist(), last)
            if not all(ok):
                ok = np.array(ok, dtype=bool)
                t, w = t[ok], w[ok]
        else:
            ok = np.isfinite(t) & np.all(np.isfinite(w), axis=1)
            ok &= t > last
            ok &= np.concatenate([[True], np.diff(t) > 0]) if len(t) else ok
            if len(t) and not np.all(np.diff(t[ok]) > 0):
                ok[:] = False  # unordered batch: let the caller sort it
            t, w = t[ok], w[ok]
        dropped = len(ok) - len(t)
        if dropped:
            self.counters.extra["imu_dropped"] = self.counters.extra.get("imu_dropped", 0) + dropped
        self._append_imu(t, w)
        if self._prefix is not None:
            self._prefix.extend(t, w)
        return len(t)

    def _append_imu(self, t: np.ndarray, w: np.ndarray) -> None:
        """``imu_t``, ``imu_w`` += the samples, in buffers with spare room (amortized O(1)).

        ``imu_t`` and ``imu_w`` are views of the buffers; anything that replaces them
        (:meth:`drop_imu`, a restored checkpoint) makes the next call start new buffers.
        """
        m = len(t)
        if m == 0:
            return
        n = len(self.imu_t)
        cap = self._imu_cap
        if cap is None or cap[2] is not self.imu_t or cap[3] is not self.imu_w \
                or n + m > len(cap[0]):
            size = max(2 * (n + m), 1024)
            tb, wb = np.empty(size), np.empty((size, 3))
            tb[:n] = self.imu_t
            wb[:n] = self.imu_w
        else:
            tb, wb = cap[0], cap[1]
        tb[n:n + m] = t
        wb[n:n + m] = w
        self.imu_t, self.imu_w = tb[:n + m], wb[:n + m]
        self._imu_cap = (tb, wb, self.imu_t, self.imu_w)

    def drop_imu(self, cut: int) -> int:
        """Forget the first ``cut`` IMU samples (live use: bounded memory); returns how many.

        Once initialized, only samples before the current one (``_k``) are dropped.
        """
        cut = max(0, min(int(cut), len(self.imu_t) - 1))
        if self.initialized:
            cut = min(cut, self._k)
        if cut == 0:
            return 0
        self.imu_t = self.imu_t[cut:].copy()
        self.imu_w = self.imu_w[cut:].copy()
        self._k = max(self._k - cut, 0)
        if self._prefix is not None:
            self._prefix.drop(cut)
        return cut

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
        pre = self._prefix
        if pre is not None and t_target <= pre.t_end and self._propagate_fast(t_target):
            return
        self._propagate_exact(t_target)

    def _propagate_fast(self, t_target: float) -> bool:
        """Propagation from the prefix integrals (see :class:`_ImuPrefix`); False: not valid.

        With rates ``ω̂(θ) = ω̂_ref + G (θ − θ_ref)`` the attitude over the interval is
        ``Exp(Φ_φθ (θ − θ_ref)) R̂(t_a) ΔR_ref`` to first order in ``θ − θ_ref``, with
        ``Φ_φθ = R̂(t_a) C(t_a)ᵀ ∫ C dt · G`` — the same Φ the covariance needs.  The
        neglected second-order term is below ``|Φ_φθ δθ|²``; larger corrections than
        ``fast_propagation_max_rad`` take the exact path.
        """
        pre = self._prefix
        ta, tb = self.t, t_target
        imu_t = self.imu_t
        ma = int(np.searchsorted(imu_t, ta, side="left"))
        mb = int(np.searchsorted(imu_t, tb, side="left"))
        if mb >= pre.n or ta <= pre.tp[0]:
            return False
        Ca = pre.at(ma, ta)
        Cb = pre.at(mb, tb)
        if ma == mb:
            integral = Cb * (tb - ta)
        else:
            integral = pre.C[ma + 1] * (pre.tp[ma + 1] - ta) + (pre.S[mb] - pre.S[ma + 1]) \
                + Cb * (tb - pre.tp[mb])
        R0 = self.R_i_b
        R0Ca = R0 @ Ca.T
        Phi = (R0Ca @ integral) @ pre.G  # (3, P)
        delta = self.theta - pre.theta_ref
        corr = Phi @ delta
        if corr @ corr > self.config.fast_propagation_max_rad ** 2:
            return False
        self.R_i_b = so3_exp(corr) @ (R0Ca @ Cb)
        P = self.P
        if self.model.size:
            PhiP = Phi @ P[3:, 3:]
            Pfa = P[:3, 3:] + PhiP
            P[:3, :3] += Phi @ P[3:, :3] + P[:3, 3:] @ Phi.T + PhiP @ Phi.T
            P[:3, 3:] = Pfa
            P[3:, :3] = Pfa.T
        total = tb - ta
        q = self.q_gyro * total
        P[0, 0] += q
        P[1, 1] += q
        P[2, 2] += q
        if self.model.size:
            P.flat[3 * (len(P) + 1)::len(P) + 1] += self.q_theta * total  # diagonal of P_θθ
        n_gap, gap_time = pre.gaps(ma, mb, ta, tb)
        if n_gap or gap_time:
            self._inflate_for_gap(n_gap, gap_time, tb)
        self.omega = pre.w_hat[mb] + pre.G @ delta
        self.t = tb
        self._k = mb
        return True

    def _inflate_for_gap(self, n_gap: int, gap_time: float, t_target: float) -> None:
        """Inflate the attitude covariance over an IMU gap; after a long gap re-acquire.

        The rate over a gap is unknown (a slew may be in it), so a frame after more than
        ``gap_reacquire_s`` of gap re-acquires the attitude from its stars.
        """
        self.counters.imu_gaps += n_gap
        self.P[:3, :3] += (self.config.gap_rate_sigma * gap_time) ** 2 * np.eye(3)
        if gap_time > self.config.gap_reacquire_s:
            self._gap_pending = True
        if n_gap:
            log.warning("IMU gap before t=%.3f s: %s", t_target,
                        "attitude re-acquired from the stars" if self._gap_pending else
                        f"attitude uncertainty inflated by "
                        f"{self.config.gap_rate_sigma * gap_time:.3g} rad")

    def _propagate_exact(self, t_target: float) -> None:
        """Per-sample propagation with the current θ (any GYRO-stage effects)."""
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
        # Gap samples: count those entered in this interval, inflate by the overlap.
        k = self._k
        sample_dt = np.diff(self.imu_t[max(k - 1, 0):m + 1])
        if k == 0:
            sample_dt = np.concatenate([[self.nominal_dt], sample_dt])
        gap = sample_dt > self.config.imu_gap_factor * self.nominal_dt
        if np.any(gap):
            n_gap = int(np.sum(gap[1:]))
            gap_time = float(np.sum(dts[gap]))
            self._inflate_for_gap(n_gap, gap_time, t_target)
        self.R_i_b = R_all[-1]
        self.omega = w_hat[-1]
        self.t = t_target
        self._k = m

    def rate_at(self, t: float) -> np.ndarray:
        """Corrected body rate of the IMU sample covering relative time ``t``."""
        m = min(int(np.searchsorted(self.imu_t, t, side="left")), len(self.imu_t) - 1)
        pre = self._prefix
        if pre is not None and m < pre.n:
            return pre.w_hat[m] + pre.G @ (self.theta - pre.theta_ref)
        return self.model.corrected_rates(self.theta, self.imu_w[m:m + 1])[0]

    # ------------------------------------------------------------------ star frames
    def initialize(self, uv: np.ndarray, u_i: np.ndarray, ctx: FrameContext,
                   sigma: np.ndarray) -> bool:
        """Initialize the attitude from one frame; return False if it cannot."""
        model, theta = self.model, self.theta
        shift, _ = model.time_shift(theta, ctx)
        t_exp = self._stamp_rel + shift
        if t_exp <= self.imu_t[0] - self.nominal_dt or t_exp >= self.imu_t[-1]:
            self.counters.skipped_no_imu += 1
            return False
        if self.t is not None and t_exp < self.t - 1e-9:
            return False
        camera = model.camera_at(theta, ctx)
        R_imu_st, _ = model.installation_at(theta, ctx)
        keep = _wahba_inliers(camera, uv, u_i, self.config.init_outlier_px)
        fit = None
        for _ in range(3):
            if keep.sum() < max(self.config.min_stars, 3):
                return False
            try:
                R0 = wahba(camera.unproject(uv[keep]), u_i[keep])
                fit = fit_frame_attitude(camera, uv[keep], u_i[keep], R_i_st0=R0)
            except (ModelError, np.linalg.LinAlgError, ValueError) as exc:
                log.warning("attitude fit failed at t=%.3f s: %s", t_exp, exc)
                return False
            err = np.linalg.norm(fit.residuals, axis=1)
            if not np.all(np.isfinite(err)):
                return False
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
        if not np.all(np.isfinite(info)) or np.linalg.cond(info) > 1e12:
            return False
        M = np.linalg.solve(info, Hf.T @ Ht) if model.size else np.zeros((3, 0))
        s2 = float(np.mean(sigma[keep] ** 2))
        Ptt = self.P[3:, 3:]
        Q_lin = self._init_linearization_error(uv[keep], u_i[keep], ctx, fit.R_i_st, R_i_b,
                                               M, Ht) if model.size else 0.0
        self.P[:3, :3] = M @ Ptt @ M.T + s2 * np.linalg.inv(info) + Q_lin
        self.P[:3, 3:] = -M @ Ptt
        self.P[3:, :3] = self.P[:3, 3:].T
        self.counters.init_frames += 1
        self._rejected_in_row = 0
        self._good = (self.P.copy(), self.theta.copy(), self.R_i_b.copy())
        log.info("attitude initialized at t=%.3f s from %d stars", t_exp, int(keep.sum()))
        return True

    def _init_linearization_error(self, uv: np.ndarray, u_i: np.ndarray, ctx: FrameContext,
                                  R_i_st: np.ndarray, R_i_b: np.ndarray, M: np.ndarray,
                                  Ht: np.ndarray) -> np.ndarray:
        """Second moment of the second-order part of the initial attitude error.

        The frame fit under the current model gives ``φ₀ = −M δθ`` only to first order in
        δθ; with datasheet priors (pixels of principal point, 0.2° of installation) the
        quadratic remainder ``r = ½ yᵀ H y`` (``δθ = L y``, ``L Lᵀ = P_θθ``, y ~ N(0, I))
        is some 10 µrad, far above the centroid-noise term of a 0.005-px tracker; ignoring
        it makes the filter start, and with little process noise stay, overconfident.
        H is measured by refitting the frame under ``θ̂ + δ`` for ``δ = ±L_j`` and
        ``L_j + L_k``: ``e_j = ½ H_jj`` is the even part along ``L_j`` and ``H_jk =
        r(L_j + L_k) − e_j − e_k``.  Then ``E r = Σ e_j`` and
        ``Cov r = 2 Σ e_j e_jᵀ + Σ_{j<k} H_jk H_jkᵀ`` (exact for a quadratic r).
        """
        model, theta = self.model, self.theta
        try:
            L = np.linalg.cholesky(self.P[3:, 3:])
        except np.linalg.LinAlgError:
            w, V = np.linalg.eigh(self.P[3:, 3:])
            L = V * np.sqrt(np.clip(w, 0.0, None))
        # columns that do not move the stars of one frame (gyro bias) contribute nothing
        HL = np.linalg.norm(Ht @ L, axis=0)
        cols = np.flatnonzero(HL > 1e-9 * (1.0 + HL.max()))

        def remainder(delta: np.ndarray) -> np.ndarray | None:
            th = theta + delta
            R_imu_st, _ = model.installation_at(th, ctx)
            try:
                fit = fit_frame_attitude(model.camera_at(th, ctx), uv, u_i, R_i_st0=R_i_st,
                                         max_iterations=2)
            except (ModelError, np.linalg.LinAlgError, ValueError):
                return None
            phi = so3_log((fit.R_i_st @ R_imu_st.T) @ R_i_b.T) + M @ delta
            return phi if np.all(np.isfinite(phi)) else None

        e = {}
        for j in cols:
            rp, rm = remainder(L[:, j]), remainder(-L[:, j])
            if rp is not None and rm is not None:
                e[j] = 0.5 * (rp + rm)
        if not e:
            return np.zeros((3, 3))
        mean = sum(e.values())
        cov = 2.0 * sum(np.outer(v, v) for v in e.values())
        keys = sorted(e)
        for a, j in enumerate(keys):
            for k in keys[a + 1:]:
                r = remainder(L[:, j] + L[:, k])
                if r is not None:
                    h = r - e[j] - e[k]
                    cov = cov + np.outer(h, h)
        return cov + np.outer(mean, mean)

    def _attitude_function(self, phi: np.ndarray | None = None):
        R_now = self.R_i_b if phi is None else so3_exp(phi) @ self.R_i_b
        w = self.omega
        # Time from the current state to the frame stamp, from exact relative times; the
        # model asks for stamp + shift in POSIX s, of which only the (small) shift is used.
        stamp_posix = self._stamp_posix
        base = self._stamp_rel - self.t

        def attitude(t_posix: float) -> tuple[np.ndarray, np.ndarray]:
            dt = (t_posix - stamp_posix) + base
            R = R_now if abs(dt) < 1e-12 else R_now @ so3_exp(w * dt)
            return R, w

        return attitude

    def update(self, uv: np.ndarray, u_i: np.ndarray, ctx: FrameContext,
               sigma: np.ndarray) -> FrameUpdate | None:
        """Propagate to the frame's exposure and update with its stars."""
        model = self.model
        shift, _ = model.time_shift(self.theta, ctx)
        t_exp = self._stamp_rel + shift
        try:
            self.propagate(t_exp)
        except _NoImuError:
            self.counters.skipped_no_imu += 1
            return None
        if self._gap_pending:
            self._gap_pending = False
            if self.initialize(uv, u_i, ctx, sigma):
                self.counters.reinitializations += 1
                self.counters.init_frames -= 1
                self.counters.extra["reacquired_after_gap"] = \
                    self.counters.extra.get("reacquired_after_gap", 0) + 1
                return None
        n = len(uv)
        R_meas = sigma**2
        theta0 = self.theta.copy()
        pred0 = model.predict(theta0, u_i, ctx, self._attitude_function())
        H0 = np.concatenate([pred0.H_attitude, pred0.H_parameters], axis=2)  # (n,2,N)
        nu0 = uv - pred0.uv
        S_blocks = (H0 @ self.P) @ H0.transpose(0, 2, 1)
        S_blocks[:, 0, 0] += R_meas
        S_blocks[:, 1, 1] += R_meas
        nis_stars = block_nis(nu0, S_blocks)
        # Gate relative to the frame's typical misfit: a misidentified star stands out from
        # the other stars of its frame, while a model that misses an effect raises every
        # star's NIS. Gating those against the absolute threshold would reject whole frames
        # and leave nothing to diagnose; scaling the gate by the frame's median NIS (over
        # the χ² median) keeps rejecting outliers and keeps the honest innovations.
        finite = [v for v in nis_stars.tolist() if math.isfinite(v)]
        scale = 1.0
        if len(finite) >= 3:
            scale = max(1.0, _median(finite) / _CHI2_2_MEDIAN)
        mismatch = scale > self.config.mismatch_factor
        # the last 10 frames as bits: one odd frame is counted, a pattern is reported
        self._mismatch_bits = ((self._mismatch_bits << 1) | int(mismatch)) & 0x3FF
        if mismatch:
            self.counters.extra["frames_model_mismatch"] = \
                self.counters.extra.get("frames_model_mismatch", 0) + 1
            if not self._mismatch_warned and bin(self._mismatch_bits).count("1") >= 3:
                self._mismatch_warned = True
                log.warning("t=%.3f s: the stars' median NIS is %.0fx what the model expects "
                            "(3 or more of the last 10 frames): the model misses an effect "
                            "(run stellar-cal diagnose)", t_exp, scale)
        accepted = nis_stars <= self.gate * scale  # NaN (star behind the tracker) is rejected
        if scale > self.config.lost_lock_factor:
            # Innovations a hundred sigma off on the typical star: not a missing effect but a
            # lost attitude (e.g. after an IMU gap in a slew). Reject the frame; a few of
            # those in a row re-acquire the attitude from the stars.
            accepted[:] = False
            self.counters.extra["frames_lost_lock"] = \
                self.counters.extra.get("frames_lost_lock", 0) + 1
        # A star whose catalogue direction is outside the field of view is misidentified,
        # whatever its NIS: far outside the detector the distortion polynomial folds back
        # and its huge Jacobian would let the gate pass it.
        d = pred0.directions_st
        front = d[:, 2] > 0
        if front.all():  # no zero or NaN divisor: no floating-point warnings to silence
            in_fov = (d[:, 0] ** 2 + d[:, 1] ** 2) / d[:, 2] ** 2 <= self._fov_r2
        else:
            with np.errstate(divide="ignore", invalid="ignore"):
                r2 = (d[:, 0] ** 2 + d[:, 1] ** 2) / d[:, 2] ** 2
            in_fov = front & (r2 <= self._fov_r2)
        if not in_fov.all():
            self.counters.extra["stars_outside_fov"] = \
                self.counters.extra.get("stars_outside_fov", 0) + int((~in_fov).sum())
            accepted &= in_fov
        self.counters.stars_gated += int(n - accepted.sum())
        result = FrameUpdate(ctx.stamp, t_exp, accepted, uv, pred0.uv, S_blocks, nis_stars,
                             float("nan"), 0, pred0.directions_st, self.omega.copy(), 0)
        if accepted.sum() < self.config.min_stars:
            self.counters.skipped_few_stars += 1
            self._rejected_in_row += 1
            if self._rejected_in_row >= self.config.reinit_after:
                # Lost lock (e.g. after an IMU gap during a slew): re-acquire the attitude
                # from this frame, keeping θ and its covariance.
                log.warning("t=%.3f s: %d frames in a row rejected, re-acquiring the attitude",
                            t_exp, self._rejected_in_row)
                if self.initialize(uv, u_i, ctx, sigma):
                    self.counters.reinitializations += 1
                    self.counters.init_frames -= 1
            return result
        self._rejected_in_row = 0
        idx = np.flatnonzero(accepted)
        ctx_acc = None  # the accepted stars' context: only if the update relinearizes
        z = uv[idx].reshape(-1)
        Rm = np.repeat(R_meas[idx], 2)
        N = 3 + model.size
        dx = np.zeros(N)
        H = H0[idx].reshape(-1, N)
        h = pred0.uv[idx].reshape(-1)
        it = 0
        sig = np.sqrt(np.diag(self.P))
        nu = z - h
        nis = float("nan")
        sig_floor = np.maximum(sig, 1e-300)
        for it in range(1, self.config.max_iterations + 1):
            PHt = self.P @ H.T
            S = H @ PHt
            S.ravel()[::len(S) + 1] += Rm  # the diagonal
            # LAPACK directly (Cholesky, then triangular solves): the numpy.linalg wrappers
            # cost more than the 2n × 2n factorization itself
            c, info = _potrf(S, lower=1, clean=1, overwrite_a=1)
            if info != 0:
                self.counters.extra["update_failed"] = self.counters.extra.get(
                    "update_failed", 0) + 1
                log.warning("t=%.3f s: innovation covariance not positive definite: frame "
                            "skipped", t_exp)
                return result
            if it == 1:
                y, _ = _trtrs(c, nu, lower=1)
                nis = float(y @ y)
            Kt, _ = _potrs(c, PHt.T, lower=1)  # S⁻¹ H P = Kᵀ
            K = Kt.T
            dx_new = K @ (z - h + H @ dx)
            change = np.max(np.abs(dx_new - dx) / sig_floor)
            dx = dx_new
            if it == self.config.max_iterations:
                break
            if it == 1:
                # Relinearize only if the correction is large enough for second-order terms
                # to matter: a rotation of more than relinearize_rad or a parameter moving by
                # more than relinearize_sigma of its prior-relative uncertainty.
                dphi = dx[:3]
                small = math.sqrt(dphi.dot(dphi)) < self.config.relinearize_rad and (
                    np.abs(dx[3:]) < self.config.relinearize_sigma * sig_floor[3:]).all()
                if small:
                    break
            elif change < self.config.iteration_tolerance:
                break
            if ctx_acc is None:
                ctx_acc = _subset_context(ctx, idx)
            pred = model.predict(theta0 + dx[3:], u_i[idx], ctx_acc,
                                 self._attitude_function(dx[:3]))
            H = np.concatenate([pred.H_attitude, pred.H_parameters], axis=2).reshape(-1, N)
            h = pred.uv.reshape(-1)
        if not (np.isfinite(dx).all() and np.isfinite(K).all()):
            self.counters.extra["update_failed"] = self.counters.extra.get("update_failed", 0) + 1
            log.warning("t=%.3f s: non-finite update: frame skipped", t_exp)
            return result
        # Joseph form (stays symmetric PD with the iterated, not exactly optimal gain)
        A = self._eye - K @ H
        P = A @ self.P @ A.T + (K * Rm) @ K.T
        # reset: R ← Exp(δφ) R, θ ← θ + δθ; left-error reset Jacobian I + ½[δφ]×
        dphi = dx[:3]
        self.R_i_b = so3_exp(dphi) @ self.R_i_b
        self.theta = theta0 + dx[3:]
        x, y_, z_ = 0.5 * dphi
        G = np.array([[1.0, -z_, y_], [z_, 1.0, -x], [-y_, x, 1.0]])
        P[:3, :] = G @ P[:3, :]
        P[:, :3] = P[:, :3] @ G.T
        self.P = 0.5 * (P + P.T)
        self.omega = self.rate_at(self.t)
        self.counters.updates += 1
        if self.config.covariance_check_every and \
                self.counters.updates % self.config.covariance_check_every == 0:
            self._check_covariance()
        result.nis = nis
        result.dof = int(len(z))
        result.iterations = it
        return result

    def _check_covariance(self) -> None:
        """Cheap health check of P; repair (or roll back) instead of going on corrupted."""
        self.counters.covariance_checks += 1
        try:
            check_covariance(self.P, "PSCE covariance")
        except ModelError as exc:
            self.counters.covariance_repairs += 1
            P = 0.5 * (self.P + self.P.T)
            if np.all(np.isfinite(P)):
                w, V = np.linalg.eigh(P)
                w = np.maximum(w, 1e-12 * max(float(w.max()), 1e-300))
                self.P = (V * w) @ V.T
                log.warning("%s: repaired (eigenvalues clipped)", exc)
            elif self._good is not None:
                self.P, self.theta, self.R_i_b = (a.copy() for a in self._good)
                log.warning("%s: rolled back to the last healthy state", exc)
            else:
                raise
            return
        self._good = (self.P.copy(), self.theta.copy(), self.R_i_b.copy())

    def process_frame(self, uv: np.ndarray, u_i: np.ndarray, ctx: FrameContext,
                      sigma: np.ndarray, t_rel: float | None = None) -> FrameUpdate | None:
        """Handle one (cleaned) star frame: initialize or update; count skips.

        ``t_rel`` is the frame stamp relative to ``t0`` in s, best computed from integer
        nanoseconds (``(stamp_ns − t0_ns) · 1e-9``); default ``ctx.stamp − t0``.
        """
        self.counters.frames += 1
        t_rel = ctx.stamp - self.t0 if t_rel is None else float(t_rel)
        if not np.isfinite(t_rel):
            self.counters.extra["skipped_bad_stamp"] = \
                self.counters.extra.get("skipped_bad_stamp", 0) + 1
            return None
        if self.last_stamp is not None:
            if t_rel == self.last_stamp:
                self.counters.skipped_duplicate += 1
                return None
            if t_rel < self.last_stamp:
                self.counters.skipped_out_of_order += 1
                log.warning("star frame at %.6f is older than the last one: skipped", ctx.stamp)
                return None
        good = np.isfinite(uv).all(axis=1) & np.isfinite(u_i).all(axis=1) & \
            np.isfinite(sigma) & (sigma > 0)
        if not good.all():
            self.counters.stars_invalid += int((~good).sum())
            uv, u_i, sigma = uv[good], u_i[good], sigma[good]
            ctx = _subset_context(ctx, np.flatnonzero(good))
        if len(uv) < self.config.min_stars:
            self.counters.skipped_few_stars += 1
            return None
        self.last_stamp = t_rel
        self._stamp_posix = ctx.stamp
        self._stamp_rel = t_rel
        if not self.initialized:
            self.initialize(uv, u_i, ctx, sigma)
            return None
        return self.update(uv, u_i, ctx, sigma)

    # ------------------------------------------------------------------ outputs
    def sigma(self) -> np.ndarray:
        """1-sigma of the error state [φ, θ]."""
        return np.sqrt(np.clip(np.diag(self.P), 0.0, None))


def _median(values: list[float]) -> float:
    """``np.median`` of a short list of finite floats (the same value, less overhead)."""
    s = sorted(values)
    k = len(s) // 2
    return s[k] if len(s) % 2 else (s[k - 1] + s[k]) / 2.0


def _imu_ok_small(t: list[float], w: list[list[float]], last: float) -> list[bool]:
    """:meth:`PsceFilter.extend_imu`'s sample check for a few samples, in plain Python.

    Finite, after ``last``, after the previous sample of the batch (``t_i − t_{i−1} > 0``,
    as ``np.diff``), and the accepted ones increasing (else none is accepted).
    """
    isfinite = math.isfinite
    ok = []
    for i, ti in enumerate(t):
        wi = w[i]
        ok.append(isfinite(ti) and isfinite(wi[0]) and isfinite(wi[1]) and isfinite(wi[2])
                  and ti > last and (i == 0 or ti - t[i - 1] > 0))
    kept = [ti for ti, k in zip(t, ok, strict=True) if k]
    if any(not b - a > 0 for a, b in zip(kept, kept[1:], strict=False)):
        return [False] * len(t)
    return ok


def _wahba_inliers(camera, uv: np.ndarray, u_i: np.ndarray, outlier_px: float) -> np.ndarray:
    """Stars consistent with one rotation (drops misidentified ones before the pixel fit).

    Wahba on the unprojected centroids, then repeatedly drop the worst star while it is
    off by more than ``max(outlier_px / f, 5 × median)`` in angle.
    """
    d = camera.unproject(uv)
    keep = np.all(np.isfinite(d), axis=1) & np.all(np.isfinite(u_i), axis=1)
    floor = outlier_px / max(camera.fx, camera.fy)
    for _ in range(len(uv)):
        if keep.sum() < 3:
            break
        R = wahba(d[keep], u_i[keep])
        ang = np.full(len(uv), np.inf)
        ang[keep] = np.linalg.norm(d[keep] @ R.T - u_i[keep], axis=1)
        worst = int(np.argmax(np.where(keep, ang, -1.0)))
        if ang[worst] <= max(floor, 5.0 * float(np.median(ang[keep]))):
            break
        keep[worst] = False
    return keep


def _subset_context(ctx: FrameContext, idx: np.ndarray) -> FrameContext:
    """The context of a subset of the frame's stars (per-star arrays sliced)."""
    return dataclasses.replace(
        ctx,
        catalog_id=np.asarray(ctx.catalog_id)[idx] if len(ctx.catalog_id) else ctx.catalog_id,
        magnitude=np.asarray(ctx.magnitude)[idx] if len(ctx.magnitude) else ctx.magnitude,
        extra={},
    )


_BLOCK = 32  # samples per block of the prefix's attitude products (see _ImuPrefix)
_CHUNK = 16384  # samples per piece of a long extension (cache)
_SMALL = 8  # extensions of up to this many samples take the scalar path (live use)
_STALE_DQ = np.zeros((0, 4))  # block_dq while _lv holds the partial block
_PREFIX_ROWS = {  # per-sample arrays of _ImuPrefix: trailing shape, dtype
    "tp": ((), np.float64), "w_hat": ((3,), np.float64), "C": ((3, 3), np.float64),
    "S": ((3, 3), np.float64), "gap": ((), np.bool_), "gap_count": ((), np.int64),
    "gap_time": ((), np.float64),
}


class _ImuPrefix:
    """Gyro attitude and its time integral, accumulated once per IMU sample.

    With the rates ``ω̂_ref`` of the reference parameters ``θ_ref`` (the prior), ``C(t)``
    is the body attitude at ``t`` relative to the start of the data and ``S_k = Σ_{j<k}
    C_{j+1} Δt_j``.  Over any interval ``(t_a, t_b]``: ``ΔR = C(t_a)ᵀ C(t_b)`` and
    ``Σ R̂_j Δt_j = R̂(t_a) C(t_a)ᵀ (S differences + partial samples)`` — two lookups
    instead of a per-sample loop per star frame.  Increments have the coning correction.

    Samples are appended with :meth:`extend` (the constructor holds none) and old ones
    dropped with :meth:`drop`, so a live filter keeps the fast path.  Every stored value is
    independent of how the samples were split into calls: the attitude products are formed
    in blocks of ``_BLOCK`` samples at fixed absolute positions (a prefix scan within each
    block, which for sample k reads only samples ≤ k of its block, then a sequential chain
    of block anchors), and the sums are sequential accumulations; so a live filter fed in
    arbitrary batches reproduces the replay bit for bit.  (Rounding over hours ~1e-12 rad.)

    Batches of up to ``_SMALL`` samples (a live filter appends one 200 Hz sample at a time)
    take a scalar path, :meth:`_extend_small`, which performs the very same floating-point
    operations in the same order as the block scan — it keeps the scan's intermediate
    levels of the current partial block (``_lv``) and extends them by one position — and
    so stores the same values bit for bit, at a fraction of the fixed cost of the vectorized
    path (≈ 0.03 instead of ≈ 0.25 ms per call).
    """

    def __init__(self, nominal_dt: float, theta_ref: np.ndarray, b: np.ndarray, E: np.ndarray,
                 Jb: np.ndarray, gap_factor: float) -> None:
        self.nominal_dt = float(nominal_dt)
        self.gap_factor = float(gap_factor)
        self.theta_ref = theta_ref.copy()
        self.b = np.asarray(b, dtype=float).copy()
        if np.any(E):
            self.A = np.linalg.inv(np.eye(3) + E)
            self.G = -self.A @ Jb
        else:
            self.A = None
            self.G = -Jb
        self.n = 0  # samples held
        self.base = 0  # absolute index of the first sample held (samples dropped before it)
        self._at_cache: tuple[tuple[tuple[int, float], np.ndarray], ...] = \
            (((-1, 0.0), np.eye(3)),) * 2  # at(): ((absolute sample, t), C)
        self.t_end = -np.inf
        self.dtheta_last = np.zeros(3)  # for the coning term of the next sample
        self.anchor = np.array([0.0, 0.0, 0.0, 1.0])  # attitude at the current block's start
        self.block_dq = np.zeros((0, 4))  # increments of the current (partial) block
        # scan levels of the current partial block for the scalar path: one entry per
        # position, each the 6 levels (increment, then after each of the 5 scan steps) as
        # 4 floats; None: not known (after load_state), rebuilt from block_dq when needed
        self._lv: list[list[list[float]]] | None = []
        # Storage with spare capacity (amortized appends, drops without copies); the
        # public arrays are views: tp, C, S, gap_count, gap_time have n + 1 rows
        # (boundaries), w_hat and gap n rows (samples).
        self._lo = 0
        self._buf = {k: np.zeros((0,) + shape, dtype=dt) for k, (shape, dt) in _PREFIX_ROWS.items()}
        self._buf["C"] = np.eye(3)[None].copy()
        self._buf["S"] = np.zeros((1, 3, 3))
        self._buf["gap_count"] = np.zeros(1, dtype=np.int64)
        self._buf["gap_time"] = np.zeros(1)
        self._buf["tp"] = np.zeros(1)
        self._buf["w_hat"] = np.zeros((1, 3))
        self._buf["gap"] = np.zeros(1, dtype=bool)
        self._views()

    def _views(self) -> None:
        lo, n, buf = self._lo, self.n, self._buf
        for k in _PREFIX_ROWS:
            setattr(self, k, buf[k][lo:lo + n + (0 if k in ("w_hat", "gap") else 1)])

    def _reserve(self, m: int) -> None:
        """Room for m more samples: compact or grow the buffers."""
        rows = self.n + 1 + m
        cap = len(self._buf["tp"])
        if self._lo + rows <= cap:
            return
        new_cap = rows if self.n == 0 else max(2 * rows, 1024)
        lo, n = self._lo, self.n
        for k, (shape, dt) in _PREFIX_ROWS.items():
            old = self._buf[k]
            arr = np.zeros((new_cap,) + shape, dtype=dt)
            arr[:n + 1] = old[lo:lo + n + 1]
            self._buf[k] = arr
        self._lo = 0

    def extend(self, imu_t: np.ndarray, imu_w: np.ndarray) -> None:
        """Append samples (stamps increasing, after the last one held)."""
        m = len(imu_t)
        if m == 0:
            return
        if m > _CHUNK:  # cache-sized pieces; the result does not depend on the split
            self._reserve(m)
            for a in range(0, m, _CHUNK):
                self.extend(imu_t[a:a + _CHUNK], imu_w[a:a + _CHUNK])
            return
        first = self.base == 0 and self.n == 0
        if m <= _SMALL and not first:
            self._extend_small(imu_t, imu_w)
            return
        t_prev = imu_t[0] - self.nominal_dt if first else self.tp[-1]
        dt = np.diff(np.concatenate([[t_prev], imu_t]))
        d = imu_w - self.b
        if self.A is not None:  # explicit sums: the same rounding for any batch size
            A = self.A
            d = np.stack([d[:, 0] * A[i, 0] + d[:, 1] * A[i, 1] + d[:, 2] * A[i, 2]
                          for i in range(3)], axis=1)
        dth = d * dt[:, None]
        prev = np.concatenate([self.dtheta_last[None], dth[:-1]])
        phi = dth + np.cross(prev, dth) / 12.0
        if first:
            phi[0] = dth[0]
        block_dq = self._partial_dq()
        seq = np.concatenate([block_dq, quat_from_rotvec(phi)])
        r, old = len(seq), len(block_dq)
        nb = -(-r // _BLOCK)
        pad = np.zeros((nb * _BLOCK, 4))
        pad[:, 3] = 1.0
        pad[:r] = seq
        levels = np.empty((6, 4, _BLOCK)) if r % _BLOCK else None
        L = _block_scan(pad.reshape(nb, _BLOCK, 4), levels)  # (4, nb, B)
        anchors = np.empty((4, nb))
        a = self.anchor
        for j in range(nb):
            anchors[:, j] = a
            if j < nb - 1 or r % _BLOCK == 0:
                a = _quat_mul_normalized(a, L[:, j, -1])
        q = np.empty_like(L)
        _quat_multiply_soa(anchors[:, :, None], L, q, np.empty(L.shape[1:]))
        gap = dt > self.gap_factor * self.nominal_dt
        if first:
            gap[0] = False
        self._reserve(m)
        buf, i0 = self._buf, self._lo + self.n  # row of the last boundary held
        if first:
            buf["tp"][i0] = t_prev
        buf["tp"][i0 + 1:i0 + m + 1] = imu_t
        buf["w_hat"][i0:i0 + m] = d
        buf["gap"][i0:i0 + m] = gap
        C = buf["C"][i0 + 1:i0 + m + 1]
        _quat_soa_to_matrix(q.reshape(4, -1)[:, old:r], C)
        S = buf["S"][i0:i0 + m + 1]
        np.multiply(C, dt[:, None, None], out=S[1:])
        np.cumsum(S, axis=0, out=S)  # row 0 is the last sum held: sequential continuation
        gc = buf["gap_count"][i0:i0 + m + 1]
        gc[1:] = gap
        np.cumsum(gc, out=gc)
        gt = buf["gap_time"][i0:i0 + m + 1]
        gt[1:] = np.where(gap, dt, 0.0)
        np.cumsum(gt, out=gt)
        self.n += m
        self.t_end = float(imu_t[-1])
        self.dtheta_last = dth[-1].copy()
        self.anchor = a
        self.block_dq = seq[(nb - 1) * _BLOCK:].copy() if r % _BLOCK else np.zeros((0, 4))
        # the scan levels of the partial block, per position (for _extend_small)
        self._lv = levels[:, :, :r % _BLOCK].transpose(2, 0, 1).tolist() \
            if levels is not None else []
        self._views()

    def _partial_dq(self) -> np.ndarray:
        """Increments of the current partial block, (r, 4)."""
        if self._lv is None:
            return self.block_dq
        return np.array([p[0] for p in self._lv], dtype=float).reshape(-1, 4)

    def _levels(self) -> list[list[list[float]]]:
        """``_lv``, rebuilt from ``block_dq`` if unknown (same operations as the scan)."""
        if self._lv is None:
            lv: list[list[list[float]]] = []
            for q in self.block_dq.tolist():
                lv.append(_scan_position(lv, q))
            self._lv = lv
        return self._lv

    def _extend_small(self, imu_t: np.ndarray, imu_w: np.ndarray) -> None:
        """A few samples, one at a time: the floating-point operations of :meth:`extend`.

        Per sample: the bias-corrected rate (explicit sums with ``A``), the coning-corrected
        increment, its quaternion (:func:`quat_from_rotvec`, for all samples at once: the
        same function as the vectorized path), the scan position's levels from those of
        earlier positions (:func:`_scan_position`), normalization, the anchor product (the
        operation order of ``_quat_multiply_soa``), the matrix, and the sequential sums.
        """
        m = len(imu_t)
        ts = np.asarray(imu_t, dtype=float).tolist()
        ws = np.asarray(imu_w, dtype=float).reshape(m, 3).tolist()
        bx, by, bz = self.b.tolist()
        A = self.A.tolist() if self.A is not None else None
        self._reserve(m)
        buf, i0 = self._buf, self._lo + self.n  # row of the last boundary held
        t_prev = float(buf["tp"][i0])
        px, py, pz = self.dtheta_last.tolist()
        gap_dt = self.gap_factor * self.nominal_dt
        rows = []
        phis = np.empty((m, 3))
        for j in range(m):
            t = ts[j]
            dt = t - t_prev
            wx, wy, wz = ws[j]
            dx, dy, dz = wx - bx, wy - by, wz - bz
            if A is not None:
                dx, dy, dz = (dx * A[0][0] + dy * A[0][1] + dz * A[0][2],
                              dx * A[1][0] + dy * A[1][1] + dz * A[1][2],
                              dx * A[2][0] + dy * A[2][1] + dz * A[2][2])
            hx, hy, hz = dx * dt, dy * dt, dz * dt
            # np.cross(prev, dth) / 12.0
            cx = py * hz - pz * hy
            cy = pz * hx - px * hz
            cz = px * hy - py * hx
            phis[j] = (hx + cx / 12.0, hy + cy / 12.0, hz + cz / 12.0)
            rows.append((t, dt, dx, dy, dz))
            px, py, pz = hx, hy, hz
            t_prev = t
        dqs = quat_from_rotvec(phis).tolist()
        lv = self._levels()
        anchor = self.anchor.tolist()
        ax, ay, az, aw = anchor
        S_prev = buf["S"][i0].ravel().tolist()
        gc_prev = int(buf["gap_count"][i0])
        gt_prev = float(buf["gap_time"][i0])
        for j in range(m):
            t, dt, dx, dy, dz = rows[j]
            i = i0 + j
            levels = _scan_position(lv, dqs[j])
            x, y, z, w = levels[-1]
            nrm = math.sqrt(x * x + y * y + z * z + w * w)
            x, y, z, w = x / nrm, y / nrm, z / nrm, w / nrm
            if len(lv) == _BLOCK - 1:  # the block is complete: next anchor, new block
                anchor = _quat_mul_normalized(np.array(anchor), np.array([x, y, z, w])).tolist()
                lv = []
            else:
                lv.append(levels)
            # anchor ⊗ L (operation order of _quat_multiply_soa)
            qx = aw * x + ax * w + ay * z - az * y
            qy = aw * y - ax * z + ay * w + az * x
            qz = aw * z + ax * y - ay * x + az * w
            qw = aw * w - ax * x - ay * y - az * z
            ax, ay, az, aw = anchor
            C = _quat_to_matrix_rows(qx, qy, qz, qw)
            S_prev = [s_ + c_ * dt for s_, c_ in zip(S_prev, C, strict=True)]
            gap = dt > gap_dt
            gc_prev += gap
            gt_prev = gt_prev + (dt if gap else 0.0)
            buf["tp"][i + 1] = t
            buf["w_hat"][i] = (dx, dy, dz)
            buf["gap"][i] = gap
            buf["C"][i + 1].flat = C
            buf["S"][i + 1].flat = S_prev
            buf["gap_count"][i + 1] = gc_prev
            buf["gap_time"][i + 1] = gt_prev
        self._lv = lv
        self.anchor = np.array(anchor)
        self.block_dq = _STALE_DQ
        self.n += m
        self.t_end = ts[-1]
        self.dtheta_last = np.array([px, py, pz])
        self._views()

    def drop(self, cut: int) -> None:
        """Forget the first ``cut`` samples (indices shift down by ``cut``)."""
        cut = min(int(cut), self.n - 1)
        if cut <= 0:
            return
        self._lo += cut
        self.n -= cut
        self.base += cut
        self._views()

    def state(self) -> dict[str, np.ndarray]:
        """Everything that defines the prefix, as arrays (checkpoints)."""
        out = {k: np.asarray(getattr(self, k)).copy() for k in _PREFIX_ROWS}
        for k in ("nominal_dt", "gap_factor", "theta_ref", "b", "G", "n", "base", "t_end",
                  "dtheta_last", "anchor"):
            out[k] = np.asarray(getattr(self, k)).copy()
        out["block_dq"] = self._partial_dq().copy()
        if self.A is not None:
            out["A"] = self.A.copy()
        return out

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        """Restore :meth:`state`."""
        for k, v in state.items():
            if k in _PREFIX_ROWS:
                continue
            v = np.array(v)
            setattr(self, k, v.item() if v.ndim == 0 else v)
        self.A = np.array(state["A"]) if "A" in state else None
        self.n, self.base = int(self.n), int(self.base)
        self._lv = None  # rebuilt from block_dq by the scalar path when needed
        self._at_cache = (((-1, 0.0), np.eye(3)),) * 2
        self._lo = 0
        self._buf = {}
        for k, (shape, dt) in _PREFIX_ROWS.items():
            rows = self.n + (0 if k in ("w_hat", "gap") else 1)
            arr = np.zeros((self.n + 1,) + shape, dtype=dt)
            arr[:rows] = state[k]
            self._buf[k] = arr
        self._views()

    def at(self, m: int, t: float) -> np.ndarray:
        """``C(t)`` for ``t`` in sample ``m``.

        The last two results are kept (by absolute sample and time): a star frame's
        propagation starts where the previous one ended.
        """
        key = (self.base + m, t)
        for k, C in self._at_cache:
            if k == key:
                return C
        tau = t - self.tp[m]
        C = self.C[m] @ so3_exp(self.w_hat[m] * tau) if tau > 0.0 else self.C[m].copy()
        self._at_cache = (self._at_cache[-1], (key, C))
        return C

    def gaps(self, ma: int, mb: int, ta: float, tb: float) -> tuple[int, float]:
        """Gap samples entered in ``(t_a, t_b]`` and the time the interval spends in gaps."""
        gap = self.gap
        if not (gap[ma] or gap[mb] or self.gap_count[mb] != self.gap_count[ma + 1]):
            return 0, 0.0
        if ma == mb:
            return 0, (tb - ta) if gap[ma] else 0.0
        n_gap = int(self.gap_count[mb + 1] - self.gap_count[ma + 1])
        t = float(self.gap_time[mb] - self.gap_time[ma + 1])
        if gap[ma]:
            t += self.tp[ma + 1] - ta
        if gap[mb]:
            t += tb - self.tp[mb]
        return n_gap, t


_CHI2_2_MEDIAN = 2.0 * np.log(2.0)  # median of χ² with 2 dof


class _NoImuError(Exception):
    """The IMU data do not reach the requested time."""


def _block_scan(dq: np.ndarray, levels: np.ndarray | None = None) -> np.ndarray:
    """Inclusive Hamilton products within each block: (nb, B, 4) → (4, nb, B), normalized.

    Hillis-Steele scan along the block: the value at position k combines positions ≤ k
    only, with the same operations for any number of blocks or trailing padding.  With
    ``levels`` (``(log2 B + 1, 4, B)``), the last block's values before the first and after
    each step are written there (unnormalized; for :func:`_scan_position`).
    """
    Q = np.ascontiguousarray(np.moveaxis(dq, 2, 0))
    B = Q.shape[2]
    s, lvl = 1, 0
    if levels is not None:
        levels[0] = Q[:, -1]
    while s < B:
        out = np.empty((4, Q.shape[1], B - s))
        _quat_multiply_soa(Q[:, :, :-s], Q[:, :, s:], out, np.empty(out.shape[1:]))
        Q[:, :, s:] = out
        s *= 2
        lvl += 1
        if levels is not None:
            levels[lvl] = Q[:, -1]
    Q /= np.sqrt(Q[0] * Q[0] + Q[1] * Q[1] + Q[2] * Q[2] + Q[3] * Q[3])
    return Q


def _scan_position(lv: list[list[list[float]]], q: list[float]) -> list[list[float]]:
    """The scan levels of the next position of a block, from those of the earlier ones.

    The operations of :func:`_block_scan` for one position ``k = len(lv)``: at step ``l``
    (stride ``s = 2^l``) ``Q[k] ← Q[k − s] ⊗ Q[k]`` if ``k ≥ s`` (the order of
    ``_quat_multiply_soa``); returns the ``log2 B + 1`` levels, the last unnormalized.
    """
    k = len(lv)
    x, y, z, w = q
    out = [q]
    s, lvl = 1, 0
    while s < _BLOCK:
        if k >= s:
            ax, ay, az, aw = lv[k - s][lvl]
            x, y, z, w = (aw * x + ax * w + ay * z - az * y,
                          aw * y - ax * z + ay * w + az * x,
                          aw * z + ax * y - ay * x + az * w,
                          aw * w - ax * x - ay * y - az * z)
        out.append([x, y, z, w])
        s *= 2
        lvl += 1
    return out


def _quat_to_matrix_rows(x: float, y: float, z: float, w: float) -> list[float]:
    """:func:`_quat_soa_to_matrix` of one quaternion, the 9 entries row by row."""
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return [1.0 - 2.0 * (yy + zz), 2.0 * (xy - wz), 2.0 * (xz + wy),
            2.0 * (xy + wz), 1.0 - 2.0 * (xx + zz), 2.0 * (yz - wx),
            2.0 * (xz - wy), 2.0 * (yz + wx), 1.0 - 2.0 * (xx + yy)]


def _quat_mul_normalized(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``p ⊗ q`` normalized (scalar-last)."""
    px, py, pz, pw = (float(v) for v in p)
    qx, qy, qz, qw = (float(v) for v in q)
    x = pw * qx + px * qw + py * qz - pz * qy
    y = pw * qy - px * qz + py * qw + pz * qx
    z = pw * qz + px * qy - py * qx + pz * qw
    w = pw * qw - px * qx - py * qy - pz * qz
    n = (x * x + y * y + z * z + w * w) ** 0.5
    return np.array([x / n, y / n, z / n, w / n])


def _quat_soa_to_matrix(q: np.ndarray, out: np.ndarray) -> None:
    """Rotation matrices of unit quaternions ``(4, m)`` (scalar-last) into ``out`` (m, 3, 3)."""
    x, y, z, w = q
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    out[:, 0, 0] = 1.0 - 2.0 * (yy + zz)
    out[:, 0, 1] = 2.0 * (xy - wz)
    out[:, 0, 2] = 2.0 * (xz + wy)
    out[:, 1, 0] = 2.0 * (xy + wz)
    out[:, 1, 1] = 1.0 - 2.0 * (xx + zz)
    out[:, 1, 2] = 2.0 * (yz - wx)
    out[:, 2, 0] = 2.0 * (xz - wy)
    out[:, 2, 1] = 2.0 * (yz + wx)
    out[:, 2, 2] = 1.0 - 2.0 * (xx + yy)
