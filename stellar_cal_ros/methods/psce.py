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

Frame handling, acquisition (with the initial attitude error correlated with θ), the gate,
the iterated update, re-acquisition and IMU gap bridging are the shared kernel's
(:mod:`stellar_cal_ros.methods.kernel`); this module holds what is PSCE's own: the state
(attitude and θ, no navigation blocks) and the propagation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stellar_cal_ros.core.imu_prefix import ImuPrefix
from stellar_cal_ros.core.rotation import (
    quat_from_matrix,
    quat_from_rotvec,
    quat_to_matrix,
    so3_exp,
)
from stellar_cal_ros.core.strapdown import attitude_increments, quat_cumprod
from stellar_cal_ros.effects.base import Stage
from stellar_cal_ros.errors import ModelError
from stellar_cal_ros.methods.kernel import (  # noqa: F401 (re-exported for callers)
    FilterCounters,
    FrameUpdate,
    KernelConfig,
    NoImuError,
    StarFilter,
)
from stellar_cal_ros.methods.registry import MethodSpec
from stellar_cal_ros.methods.star_model import StarModel

BASELINE_EFFECTS = (
    "gyro_bias",
    "installation",
    "principal_point",
    "focal_length",
    "radial_k1k2",
    "tangential",
)


@dataclass
class PsceConfig(KernelConfig):
    """Noise levels and decisions of the PSCE filter (Tan et al. Table 1 defaults)."""

    fast_propagation: bool = True  #: prefix-integrated gyro (exact to 2nd order in δθ)
    fast_propagation_max_rad: float = 1e-5  #: larger first-order corrections: exact path


class PsceFilter(StarFilter):
    """The PSCE error-state Kalman filter over contract IMU samples and star frames.

    Parameters
    ----------
    model : StarModel
        Effects (state layout) and the prior.
    t0 : float
        POSIX time of relative time zero.
    config : PsceConfig
    nominal_dt : float
        Nominal IMU interval, s.
    consider : int
        Trailing θ entries of ``model`` that are consider parameters (see the kernel).

    IMU samples come through :meth:`extend_imu` (relative s, rad/s).
    """

    method = "psce"

    def __init__(self, model: StarModel, t0: float, config: PsceConfig | None = None, *,
                 nominal_dt: float, consider: int = 0) -> None:
        super().__init__(model, t0, config or PsceConfig(), nominal_dt, consider)
        self._prefix: ImuPrefix | None = None
        b, E, Jb, JE = model.sensor_model(self.theta, Stage.GYRO)
        # Fast propagation needs rates linear in θ with a constant Jacobian: bias-type GYRO
        # effects only (∂E/∂θ = 0); estimated scale-factor / misalignment effects use the
        # exact path.  Consider parameters stay at their prior: only their transition columns
        # are needed, summed over the interval's samples (_consider_columns).
        self._gyro_linear = not np.any(JE[:, :, :self.P_est])
        JE_b = JE[:, :, self.P_est:]
        self._consider_JE = JE_b if np.any(JE_b) else None
        if self._consider_JE is not None and np.any(E):
            self._consider_JE = np.einsum("ik,kjp->ijp", np.linalg.inv(np.eye(3) + E),
                                          self._consider_JE)
        if self.config.fast_propagation and self._gyro_linear:
            self._prefix = ImuPrefix(self.nominal_dt, self.theta, b, E, Jb)
        self._q_diag = np.concatenate([np.full(3, self.q_gyro), self.q_theta])

    # ------------------------------------------------------------------ IMU
    def _on_imu_appended(self, first: int) -> None:
        if self._prefix is not None:
            self._prefix.extend(self.imu.t[first:], self.imu.w[first:])

    def _on_imu_dropped(self, cut: int) -> None:
        if self._prefix is not None:
            self._prefix.drop(cut)

    def rate_at(self, t: float) -> np.ndarray:
        """Corrected body rate of the IMU sample covering relative time ``t``."""
        m = min(self.imu.index(t), len(self.imu) - 1)
        pre = self._prefix
        if pre is not None and m < pre.n:
            return pre.w_hat[m] + pre.G @ (self.theta - pre.theta_ref)
        return self.model.corrected_rates(self.theta, self.imu.w[m:m + 1])[0]

    # ------------------------------------------------------------------ propagation
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

    def _apply_transition(self, Phi: np.ndarray, total: float) -> None:
        """``P ← Φ P Φᵀ + Q`` for ``Φ = [[I, Φ_φθ], [0, I]]`` over ``total`` seconds.

        ``Phi`` (3, P_all): the estimated columns drive the covariance, the consider ones
        the sensitivity.
        """
        self.state.propagate_coupled(self.ia, self.it, Phi[:, :self.P_est],
                                     self._q_diag * total, Phi[:, self.P_est:])

    def _propagate_fast(self, t_target: float) -> bool:
        """Propagation from the prefix integrals (see :class:`ImuPrefix`); False: not valid.

        With rates ``ω̂(θ) = ω̂_ref + G (θ − θ_ref)`` the attitude over the interval is
        ``Exp(Φ_φθ (θ − θ_ref)) R̂(t_a) ΔR_ref`` to first order in ``θ − θ_ref``, with
        ``Φ_φθ = R̂(t_a) C(t_a)ᵀ ∫ C dt · G`` — the same Φ the covariance needs.  The
        neglected second-order term is below ``|Φ_φθ δθ|²``; larger corrections than
        ``fast_propagation_max_rad`` take the exact path.
        """
        pre = self._prefix
        ta, tb = self.t, t_target
        imu_t = self.imu.t
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
        if self._consider_JE is not None:
            Phi = Phi.copy()
            Phi[:, self.P_est:] += R0Ca @ self._consider_columns(ma, mb, ta, tb, Cb)
        self._apply_transition(Phi, tb - ta)
        self._inflate_bridged(ma, mb, ta, tb)
        self.omega = pre.w_hat[mb] + pre.G @ delta
        self.t = tb
        self._k = mb
        return True

    def _consider_columns(self, ma: int, mb: int, ta: float, tb: float,
                          Cb: np.ndarray) -> np.ndarray:
        """``−Σ_j C_j (I+E)⁻¹ (∂E/∂β ω̂_j) Δt_j`` over ``(ta, tb]`` (3, m), prefix frame.

        The rate-error Jacobian of the consider scale factors / misalignments, summed with
        the attitude at each segment's end, as :meth:`_propagate_exact` does.
        """
        pre = self._prefix
        ends = np.append(pre.tp[ma + 1:mb + 1], tb)
        dts = np.diff(ends, prepend=ta)
        C = np.concatenate([pre.C[ma + 1:mb + 1], Cb[None]])
        JEw = np.einsum("ijp,nj->nip", self._consider_JE, pre.w_hat[ma:mb + 1])
        return -np.einsum("nij,njp,n->ip", C, JEw, dts)

    def _propagate_exact(self, t_target: float) -> None:
        """Per-sample propagation with the current θ (any GYRO-stage effects)."""
        imu = self.imu
        k = self._k
        m = imu.index(t_target)
        if m >= len(imu):
            raise NoImuError()
        ends = np.concatenate([imu.t[k:m], [t_target]])
        starts = np.concatenate([[self.t], imu.t[k:m]])
        dts = ends - starts
        w_raw = imu.w[k:m + 1]
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
        R_all = quat_to_matrix(quat_cumprod(q)[1:])
        total = float(np.sum(dts))
        if self.model.size:
            # Φ_φθ = Σ R̂_j G_j Δt_j,  G_j = −(I+E)⁻¹ (∂b/∂θ + ∂E/∂θ ω̂_j)
            Rdt = np.einsum("nij,n->ij", R_all, dts)
            Phi = Rdt @ (-Jb if A is None else -A @ Jb)
            if np.any(JE):
                JEw = np.einsum("ijp,nj->nip", JE, w_hat)
                if A is not None:
                    JEw = np.einsum("ik,nkp->nip", A, JEw)
                Phi = Phi - np.einsum("nij,njp,n->ip", R_all, JEw, dts)
            self._apply_transition(Phi, total)
        else:
            self.state.add_diagonal(self._q_diag * total)
        self._inflate_bridged(k, m, self.t, t_target)
        self.R_i_b = R_all[-1]
        self.omega = w_hat[-1]
        self.t = t_target
        self._k = m


METHOD = MethodSpec(
    name="psce", kind="filter",
    summary="Tan et al. 2018: a rotating vehicle; installation, gyro bias and camera "
            "intrinsics from star centroids",
    baseline=BASELINE_EFFECTS,
    # no accelerometer model
    stages=(Stage.GYRO, Stage.DIRECTION, Stage.TIME, Stage.TRACKER, Stage.CAMERA),
    filter_cls=PsceFilter, config_cls=PsceConfig)
