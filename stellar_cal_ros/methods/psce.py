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
per-sample update and no less accurate.  The attitude and ``Φ_φθ`` come from the filters'
one IMU propagation (:class:`~stellar_cal_ros.core.propagation.ImuPropagation`).

Measurement (their eqs. 23-26): the centroid of every identified star, predicted through
the effects (:class:`~stellar_cal_ros.methods.star_model.StarModel`), minus the extracted
one.  Stars are χ² gated one by one (2 dof) on the innovation covariance, then all accepted
stars of the frame are processed together by an iterated EKF update (re-linearizing while
the correction is large, as at start-up when the datasheet model is pixels off) with the
Joseph-form covariance update, followed by the reset ``R̂ ← Exp(δφ) R̂``, ``θ̂ ← θ̂ + δθ``.

Frame handling, acquisition (with the initial attitude error correlated with θ), the gate,
the iterated update, re-acquisition and IMU gap bridging are the shared kernel's
(:mod:`stellar_cal_ros.methods.kernel`); this module holds what is PSCE's own: the state
(attitude and θ, no navigation blocks; the kernel's attitude transition).
"""

from __future__ import annotations

from dataclasses import dataclass

from stellar_cal_ros.methods.kernel import (  # noqa: F401 (re-exported for callers)
    FilterCounters,
    FrameUpdate,
    KernelConfig,
    NoImuError,
    StarFilter,
)
from stellar_cal_ros.methods.registry import STAGES_WITHOUT_ACCEL, MethodSpec
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

METHOD = MethodSpec(
    name="psce", kind="filter",
    summary="Tan et al. 2018: a rotating vehicle; installation, gyro bias and camera "
            "intrinsics from star centroids",
    baseline=BASELINE_EFFECTS,
    stages=STAGES_WITHOUT_ACCEL,
    filter_cls=PsceFilter, config_cls=PsceConfig)
