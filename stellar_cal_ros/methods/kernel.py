"""The estimation kernel shared by every star-tracker Kalman filter of the package.

A filter is an error-state EKF whose state is a :class:`~stellar_cal_ros.core.state.
StateLayout` of typed blocks: the IMU attitude (a left rotation in the inertial frame,
``R_i_b = Exp(φ) R̂_i_b``, Tan et al. eq. 7), one block per estimated effect of the
:class:`~stellar_cal_ros.methods.star_model.StarModel` (θ), and whatever navigation blocks
the method adds (the swaying-base filter's velocity and position).  Everything that is the
same for all methods lives here, once:

* frame handling: bad stamps, duplicates and out-of-order frames, invalid stars (non-finite
  centroids or directions, σ ≤ 0), too few stars — each counted in :class:`FilterCounters`;
* acquisition (:meth:`StarFilter.initialize`, in :mod:`~stellar_cal_ros.methods.
  acquisition`): the attitude from one frame by a pixel-space Wahba fit under the current
  model, with the initial attitude error correlated with θ exactly as the fit makes it
  (``φ₀ = −M δθ + r + noise``), and the navigation blocks set by the method;
* re-acquisition (:meth:`StarFilter.reacquire`) after an IMU gap longer than
  ``gap_reacquire_s`` or ``reinit_after`` rejected frames in a row (lost lock): the
  navigation blocks are cleared and set again from a frame, θ and its covariance are kept;
* the star update: prediction and Jacobians of every star through the effects, one gate
  policy (:class:`~stellar_cal_ros.core.gating.GatePolicy`: per-star χ² scaled by the
  frame's median NIS, field of view, lost lock), the iterated EKF update with the Joseph form
  (:func:`~stellar_cal_ros.core.covariance.iterated_update`), the injection into the nominal
  state (box-plus per block) and the covariance reset; periodic check-and-repair of P;
* IMU faults, once: samples go through :class:`~stellar_cal_ros.core.imu.ImuBuffer`, which
  bridges missing intervals; the propagation inflates the covariance by the bridging error;
* a gyro that breaks the contract (deg/s, dead, swapped or mirrored axes): the gyro's own
  rotation between frames is compared with the stars' (:mod:`~stellar_cal_ros.core.
  gyro_check`, the ACF's check too); a fault found over the first frames raises
  :class:`~stellar_cal_ros.errors.DataError` naming it, one found later flags the result
  (:attr:`StarFilter.data_faults`);
* the sensitivity of the state to *consider* parameters (candidate effects kept at their
  prior value): :class:`~stellar_cal_ros.core.covariance.Sensitivity`, for score tests and
  reliability in the diagnosis.

The covariance belongs to :class:`~stellar_cal_ros.core.state.ErrorState` (:attr:`StarFilter.
state`): the kernel and the methods change it only through its methods.

The IMU propagation is :class:`~stellar_cal_ros.core.propagation.ImuPropagation` (attitude,
and velocity and position when the method's blocks are driven by the accelerometer), one for
every method.

A method (:mod:`~stellar_cal_ros.methods.psce`, :mod:`~stellar_cal_ros.methods.swaying`)
declares its navigation blocks (:attr:`StarFilter.navigation_blocks`), its transition from
the propagation (:meth:`StarFilter._transition`: which blocks, which process noise) and its
extra measurements (:meth:`StarFilter._before_star_update`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from stellar_cal_ros.core import covariance as cov
from stellar_cal_ros.core import gyro_check
from stellar_cal_ros.core.gating import GatePolicy, block_nis, fov_tan2
from stellar_cal_ros.core.imu import ImuBuffer
from stellar_cal_ros.core.propagation import ImuPropagation, SensorModel, Step
from stellar_cal_ros.core.state import Block, ErrorState, StateLayout, nominal_view
from stellar_cal_ros.core.units import DEG_PER_HOUR, DEG_PER_SQRT_HOUR
from stellar_cal_ros.effects.base import FrameContext, Stage
from stellar_cal_ros.errors import ModelError
from stellar_cal_ros.methods.acquisition import (  # noqa: F401 (re-exported for callers)
    Acquisition,
    subset_context,
    wahba_inliers,
)
from stellar_cal_ros.methods.star_model import StarModel, state_attitude

log = logging.getLogger(__name__)


class NoImuError(Exception):
    """The IMU data do not reach the requested time."""


@dataclass
class FrameUpdate:
    """What one star-frame update did (for residual tables and statistics)."""

    stamp: float  #: reported stamp, POSIX s
    t_exposure: float  #: modelled exposure time, s relative to t0
    accepted: np.ndarray  #: (n,) bool
    uv: np.ndarray  #: (n, 2) measured
    uv_pred: np.ndarray  #: (n, 2) predicted before the update (innovation = uv − uv_pred)
    S: np.ndarray  #: (n, 2, 2) innovation covariance of each star
    nis_stars: np.ndarray  #: (n,)
    nis: float  #: frame NIS over the accepted stars (NaN: no update)
    dof: int
    directions_st: np.ndarray  #: (n, 3)
    omega_b: np.ndarray  #: (3,)
    iterations: int
    #: the frame's terms of the running statistics (:func:`~.results.frame_sums`; None:
    #: computed from the fields when needed)
    sums: np.ndarray | None = None
    #: the frame's ``−2 log`` likelihood less its stars' own where the run states a stamp
    #: noise (:func:`~stellar_cal_ros.core.covariance.joint_correction`; 0: none)
    joint: float = 0.0


@dataclass
class FilterCounters:
    """Counted (and logged) skips and events of a filter."""

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

    def add(self, key: str, n: int = 1) -> None:
        """Increment a counter (a field, else an ``extra`` entry)."""
        if key in _COUNTER_FIELDS:
            setattr(self, key, getattr(self, key) + n)
        else:
            self.extra[key] = self.extra.get(key, 0) + n

    def as_dict(self) -> dict[str, int]:
        """Every counter, ``extra`` flattened."""
        d = {k: v for k, v in vars(self).items() if k != "extra"}
        d.update(self.extra)
        return d


_COUNTER_FIELDS = {f.name for f in dataclasses.fields(FilterCounters)} - {"extra"}


@dataclass
class KernelConfig:
    """Noise levels and decisions shared by the filters (methods subclass it)."""

    centroid_sigma_px: float = 0.05  #: used when a star message has sigma = 0
    #: measured noise scales (:class:`~stellar_cal_ros.core.noise.NoiseScales`): the stars'
    #: σ they rescale; ARW / VRW are already scaled in the fields (``NoiseScales.apply``)
    noise: Any = None
    gyro_arw_deg_sqrth: float = 0.001  #: angle random walk of each gyro
    gate_probability: float = 0.9999  #: per-star χ² (2 dof) acceptance probability
    min_stars: int = 3  #: fewer accepted stars: the frame is skipped
    max_iterations: int = 5  #: iterated-EKF relinearizations per frame
    iteration_tolerance: float = 1e-3  #: stop when the correction changes < tol·σ
    relinearize_rad: float = 2e-4  #: iterate only if the attitude correction exceeds this
    relinearize_sigma: float = 0.5  #: ... or a parameter moves by more than this × σ
    imu_bridge_factor: float = 1.5  #: an IMU interval longer than this × nominal is bridged
    #: rebuild the reference strapdown for every interval (per-sample propagation under the
    #: current θ: the reference path, several times slower)
    exact_propagation: bool = False
    #: a first-order attitude correction for θ̂ − θ_ref larger than this rebuilds the
    #: reference strapdown under the current θ̂ (second-order error < this²)
    fast_propagation_max_rad: float = 1e-5
    reference_window_s: float = math.inf  #: a reference older than this is rebuilt
    gap_rate_sigma: float = 1e-3  #: rad/s, rate error over a gap of several samples
    gap_accel_sigma: float = 0.5  #: m/s², specific-force error over such a gap
    fov_margin: float = 1.3  #: stars predicted beyond this × the half-diagonal: rejected
    gap_reacquire_s: float = 0.1  #: a frame after more IMU gap than this re-acquires
    init_outlier_px: float = 5.0  #: acquisition: drop stars off by more than this
    mismatch_factor: float = 3.0  #: frame median NIS this × the χ² median: model mismatch
    lost_lock_factor: float = 1e4  #: ... this ×: the attitude is lost, the frame rejected
    scale_gate_by_frame: bool = True  #: False: plain χ² gate (bound computations)
    reinit_after: int = 3  #: consecutive frames with stars but no accepted update: re-acquire
    #: a re-acquisition lost again before any accepted update doubles the rejected frames
    #: the next one waits for, up to 2**this x ``reinit_after``
    reacquire_backoff: int = 4
    covariance_check_every: int = 50  #: check P (finite, symmetric, PD) every N updates
    init_second_order: bool = True  #: initial attitude covariance with the 2nd-order term
    unit_check: bool = True  #: check the gyro against the stars (deg/s, dead, axes)
    #: a gyro fault over the first frames raises (False: flagged only — a diagnosis's
    #: candidate runs, whose gyro-error estimates may diverge with a wrong candidate)
    unit_check_raises: bool = True


_FRAME_STEP: list = []


def _frame_step_module():
    """:mod:`.frame_step` (imported on first use: it imports numba), then remembered."""
    if not _FRAME_STEP:
        from stellar_cal_ros.methods import frame_step

        _FRAME_STEP.append(frame_step)
    return _FRAME_STEP[0]


class StarFilter(Acquisition):
    """Error-state EKF over IMU samples and star frames (see the module docstring).

    Parameters
    ----------
    model : StarModel
        Effects (θ layout) and the prior.  Its last ``consider`` parameters are *consider*
        parameters: predicted through, kept at their prior value, and only tracked by
        :attr:`sensitivity`.
    t0 : float
        POSIX time of relative time zero.
    config : KernelConfig
    nominal_dt : float
        Nominal IMU sample interval, s.
    consider : int
        Number of trailing θ entries of ``model`` that are consider parameters.
    """

    method = "kernel"
    #: predict stars through the model's compiled chain when it has one, and update with
    #: the compiled gain (False: the effects' Python methods and numpy/LAPACK — the
    #: reference path, the same estimates to rounding amplified by the start-up)
    compiled_step = True
    #: a replay's run of frames takes the fused step in one compiled call
    #: (:meth:`prepare_frames`; False: one call a frame — the same floats)
    batched_step = True
    #: at most this many frames a batch
    batch_frames_max = 64
    #: a batch is committed at once within the gyro watch's first frames too (the same
    #: records and verdicts; a fault judged there raises after the batch's frames were
    #: stepped — a raise ends the run); False: those frames are taken one at a time from
    #: the batch (:meth:`~.frame_step.FrameBatch.take`), a fault raising in its frame's turn
    commit_early_frames = False
    #: a frame the fused step does not take (a method with its own propagation or
    #: measurements: the swaying-base filter) is updated by the compiled star update after
    #: the numpy propagation (:func:`~.frame_step.star_update`; False: the numpy update,
    #: the reference; ``compiled_step`` False: the numpy update too)
    compiled_star_update = False
    #: the method's navigation blocks after θ (e.g. the swaying filter's velocity); their
    #: nominal values start at zero and are set by :meth:`_acquire_navigation`
    navigation_blocks: tuple[Block, ...] = ()
    #: what a checkpoint keeps of the filter besides its error state (blocks, covariance,
    #: nominal values, sensitivity), counters, IMU buffer and propagation: checkpoint name →
    #: attribute (:mod:`~stellar_cal_ros.methods.checkpoint`); a method adds its own
    checkpoint_fields: dict[str, str] = {
        "time": "t", "last_stamp": "last_stamp", "imu_index": "_k", "omega": "_omega",
        "omega_stale": "_omega_stale", "stamp_posix": "_stamp_posix",
        "stamp_rel": "_stamp_rel", "rejected_in_row": "_rejected_in_row",
        "reacquire_streak": "_reacquire_streak",
        "gap_pending": "_gap_pending", "last_good": "_good", "prior_attitude": "_R_prior",
        "mismatch_warned": "_mismatch_warned", "mismatch_bits": "_mismatch_bits",
        "gyro_watch": "gyro_watch", "data_faults": "data_faults"}

    #: the periodic covariance check waits for :meth:`run_checks` (:meth:`defer_checks`)
    checks_deferred = False

    def __init__(self, model: StarModel, t0: float, config: KernelConfig, nominal_dt: float,
                 consider: int = 0) -> None:
        self.model = model
        self.config = config
        c = config
        self.t0 = float(t0)
        self.n_consider = int(consider)
        P_all = model.size
        self.P_est = P_all - self.n_consider
        blocks = [Block("attitude", 3, kind="rotation", navigation=True, driven_by="gyro")]
        blocks += [Block(e.id, e.size, nominal="theta", index=model.slices[e.id])
                   for e in model.effects if model.slices[e.id].stop <= self.P_est]
        blocks += list(self.navigation_blocks)
        self.layout = StateLayout(blocks)
        self.N = self.layout.size
        self.ia = slice(0, 3)
        self.it = slice(3, 3 + self.P_est)
        self._nav_blocks = tuple(b.name for b in self.navigation_blocks)
        nominal = {"attitude": None, "theta": model.initial_value.copy()}
        nominal.update({b.value_name: np.zeros(b.size) for b in self.navigation_blocks})
        #: nominal values, covariance and consider sensitivity (the one owner of P)
        self.state = ErrorState(self.layout, nominal, self.n_consider)
        self.state.assign(self.it, self.it, np.diag(model.initial_sigma[:self.P_est] ** 2))
        q = [e.process_noise_density() for e in model.effects]
        self.q_theta = (np.concatenate(q) ** 2 if q else np.zeros(0))[:self.P_est]
        #: the gyro bias's random walk the noise scales state (deg/h/√h; 0: none)
        self.gyro_bias_rw = float(getattr(c.noise, "gyro_bias_rw", 0.0) or 0.0)
        #: σ (s) of the noise in the frames' stamps the noise scales state (0: none): each
        #: frame's R gains its stars' common motion in it (:func:`~stellar_cal_ros.core.
        #: covariance.stamp_column`)
        self.stamp_sigma = 1e-3 * float(getattr(c.noise, "stamp_ms", 0.0) or 0.0)
        #: σ (px per axis) of a shift all stars of a frame share, white between frames, the
        #: noise scales state (0: none): each frame's R gains σ_f² I₂ in every star pair's
        #: block (:func:`~stellar_cal_ros.core.covariance.common_columns`)
        self.frame_sigma = float(getattr(c.noise, "frame_px", 0.0) or 0.0)
        sl = model.slices.get("gyro_bias")
        if self.gyro_bias_rw > 0 and sl is not None and sl.stop <= self.P_est:
            # (deg/h/√h → rad/s/√s)
            self.q_theta[sl] = (self.gyro_bias_rw * DEG_PER_HOUR / 60.0) ** 2
        self.q_gyro = (c.gyro_arw_deg_sqrth * DEG_PER_SQRT_HOUR) ** 2
        self.imu = ImuBuffer(nominal_dt, c.imu_bridge_factor, c.gap_rate_sigma,
                             c.gap_accel_sigma, c.gap_reacquire_s,
                             math.sqrt(self.q_gyro / nominal_dt),
                             self.accel_noise_density() / math.sqrt(nominal_dt))
        self.nominal_dt = float(nominal_dt)
        sig = model.initial_sigma
        step = np.where(np.isfinite(sig) & (sig > 0), sig, 1e-3)

        def sensor(stage: Stage) -> SensorModel:
            return SensorModel(lambda th: model.sensor_model(th, stage), self.theta, step)

        accel = any(b.driven_by == "accel" for b in self.navigation_blocks)
        #: the IMU propagation (attitude; velocity and position with an accelerometer)
        self.propagation = ImuPropagation(
            self.nominal_dt, sensor(Stage.GYRO), sensor(Stage.ACCEL) if accel else None,
            self.gravitation if accel else None, c.fast_propagation_max_rad,
            c.reference_window_s, c.exact_propagation)
        self._q_diag = np.concatenate([np.full(3, self.q_gyro), self.q_theta,
                                       np.zeros(self.N - 3 - self.P_est)])
        #: the effects' free steps (:attr:`~.effects.base.Effect.steps_at`), in time order:
        #: ``(T, θ slice, effect, k)``; taken once a frame's stamp reaches ``T``
        #: (:meth:`_take_steps`; not kept by a checkpoint: a diagnosis' nuisance)
        self._steps = sorted(((float(T), model.slices[e.id], e, k) for e in model.effects
                              if e.steps_at and model.slices[e.id].stop <= self.P_est
                              for k, T in enumerate(e.steps_at)), key=lambda x: x[0])
        #: the next step's stamp (POSIX s; inf: none left)
        self._step_at = self._steps[0][0] if self._steps else math.inf
        self._next_step = 0
        self._frame_step = None  # the fused compiled step (frame_step.FusedStep; False: none)
        self._update_step = None  # the compiled star update alone (the same; False: none)
        self._batch = None  # the coming frames' fused steps (frame_step.FrameBatch)
        self.t: float | None = None
        self._omega = np.zeros(3)
        self._omega_stale = False
        self._k = 0  # index of the first IMU sample whose interval ends after self.t
        self.counters = FilterCounters()
        self.gate = GatePolicy(c.gate_probability, c.mismatch_factor, c.lost_lock_factor,
                               fov_tan2(model.prior.camera, c.fov_margin),
                               c.scale_gate_by_frame)
        self.update_policy = cov.UpdatePolicy(c.max_iterations, c.iteration_tolerance,
                                              c.relinearize_rad, c.relinearize_sigma)
        self._mismatch_warned = False
        self._mismatch_bits = 0  # model-mismatch flags of the last 10 frames
        self.last_stamp: float | None = None
        self._rejected_in_row = 0
        self._reacquire_streak = 0  # lost-lock re-acquisitions since the last accepted update
        self._gap_pending = False
        self._good: tuple[np.ndarray, ...] | None = None
        self._stamp_posix = 0.0  # reported stamp of the frame being processed (POSIX s)
        self._stamp_rel = 0.0  # the same, relative to t0 (from integer ns: exact)
        #: the gyro-against-stars check's state (None: off or decided)
        self.gyro_watch = gyro_check.new_watch() if c.unit_check else None
        #: the gyro watch's installation (the prior's)
        self._R_imu_st_prior = model.prior.R_imu_st
        self._R_prior: tuple[np.ndarray, bool] | None = None  # (R_i_b propagated, gap)
        self.data_faults: list[str] = []  #: why the result is degraded (one line each)

    # ------------------------------------------------------------------ views
    @property
    def P(self) -> np.ndarray:
        """Error-state covariance (N, N), held by :attr:`state`."""
        return self.state.P

    @P.setter
    def P(self, value: np.ndarray) -> None:
        self.state.P = value

    R_i_b = nominal_view("attitude", "Nominal IMU attitude (body to inertial); None before "
                                     "acquisition.")
    theta = nominal_view("theta", "Nominal parameters of every effect of the model (consider "
                                  "ones included).")

    @property
    def sensitivity(self) -> cov.Sensitivity | None:
        """The state's sensitivity to the consider parameters (None: none)."""
        return self.state.sensitivity

    @property
    def initialized(self) -> bool:
        """True once the attitude has been acquired from a star frame."""
        return self.R_i_b is not None

    @property
    def omega(self) -> np.ndarray:
        """Corrected body rate at the current time (current θ)."""
        if self._omega_stale:
            self._omega = self.rate_at(self.t)
            self._omega_stale = False
        return self._omega

    @omega.setter
    def omega(self, value: np.ndarray) -> None:
        self._omega = value
        self._omega_stale = False

    @property
    def imu_t(self) -> np.ndarray:
        """Held IMU stamps, s relative to t0."""
        return self.imu.t

    def sigma(self) -> np.ndarray:
        """1-sigma of the error state (attitude, θ, navigation)."""
        return self.state.sigma()

    def theta_estimated(self) -> np.ndarray:
        """The estimated part of θ."""
        return self.theta[:self.P_est]

    # ------------------------------------------------------------------ IMU input
    def extend_imu(self, t: np.ndarray, w: np.ndarray, f: np.ndarray | None = None) -> int:
        """Append IMU samples (relative s, rad/s, m/s²); returns how many were accepted.

        Non-finite samples and stamps not after the last one held are dropped and counted
        (``imu_dropped``); the intervals they leave are bridged by :class:`ImuBuffer`.
        """
        t = np.asarray(t, dtype=float).reshape(-1)
        w = np.asarray(w, dtype=float).reshape(-1, 3)
        ff = None if f is None else np.asarray(f, dtype=float).reshape(-1, 3)
        ok = np.isfinite(t) & np.all(np.isfinite(w), axis=1)
        if ff is not None:
            ok &= np.all(np.isfinite(ff), axis=1)
        if len(t):
            # strictly increasing after the removals: each kept stamp must exceed every
            # earlier kept one (a running maximum; a rejected stamp never raises it)
            run = np.maximum.accumulate(np.where(ok, t, -np.inf))
            prev = np.concatenate([[self.imu.t_end], np.maximum(run[:-1], self.imu.t_end)])
            ok &= t > prev
        dropped = int(len(t) - ok.sum())
        if dropped:
            self.counters.add("imu_dropped", dropped)
        if not ok.all():
            t, w = t[ok], w[ok]
            ff = None if ff is None else ff[ok]
        if not len(t):
            return 0
        n0 = len(self.imu)
        before = self.imu.counters["imu_bridged"]
        self.imu.append(t, w, ff)
        self.counters.imu_gaps += self.imu.counters["imu_bridged"] - before
        self.propagation.appended(self.imu, n0, self.theta)
        return len(t)

    def drop_imu(self, cut: int) -> int:
        """Forget the first ``cut`` IMU samples (bounded memory); returns how many.

        Once initialized only samples before the current one are dropped.
        """
        cut = max(0, min(int(cut), len(self.imu) - 1))
        if self.initialized:
            cut = min(cut, self._k - 1)
        if cut <= 0:
            return 0
        self.imu.drop(cut)
        self._k -= cut
        self.propagation.dropped(self.imu)
        return cut

    # ------------------------------------------------------------------ method hooks
    def accel_noise_density(self) -> float:
        """White specific-force noise the method models, m/s/√s (0: it uses no accelerometer)."""
        return 0.0

    def gravitation(self, t: np.ndarray) -> np.ndarray:
        """Gravitation at relative times ``t`` (n, 3), m/s² (methods that carry velocity)."""
        raise NotImplementedError

    def _transition(self, step: Step) -> None:
        """``P ← Φ P Φᵀ + Q`` for ``Φ = [[I, Φ_φθ], [0, I]]`` over the step (the default).

        Attitude rows driven by θ, nothing else: the estimated columns of ``Φ_φθ`` drive the
        covariance, the consider ones the sensitivity; ``Q = diag(σ_g², q_θ, 0…) T`` (random
        walks).  A method with navigation blocks overrides it.
        """
        F = step.F[0]
        self.state.propagate_coupled(self.ia, self.it, F[:, :self.P_est],
                                     self._q_diag * step.T, F[:, self.P_est:])

    # ------------------------------------------------------------------ propagation
    def propagate(self, t_target: float) -> None:
        """Propagate nominal state and covariance to ``t_target`` (relative s)."""
        if t_target <= self.t:
            if t_target < self.t - 1e-9:
                raise ModelError(
                    f"cannot propagate backwards in time: to {t_target:.4f} s from "
                    f"{self.t:.4f} s ({(self.t - t_target) * 1e3:.3g} ms back; the time "
                    "effects' estimate puts this exposure before one already processed: "
                    "the model cannot run at this value)")
            return
        k = self._k
        m = self.imu.index(t_target)
        if m >= len(self.imu):
            raise NoImuError()
        self._propagate_interval(k, m, t_target)
        self._inflate_bridged(k, m, self.t, t_target)
        self.t = t_target
        self._k = m
        self._omega_stale = True  # the corrected rate of sample m, when next needed

    def _propagate_interval(self, k: int, m: int, t_target: float) -> None:
        """Nominal attitude and :meth:`_transition` from ``self.t`` to ``t_target``.

        ``k``, ``m``: the IMU samples of the two times.  A method may do both in one
        compiled call (the swaying-base filter's ``compiled_propagation``).
        """
        step = self.propagation.step(self.imu, k, m, self.t, t_target, self.R_i_b,
                                     self.theta)
        self.R_i_b = step.R
        self._transition(step)

    def rate_at(self, t: float) -> np.ndarray:
        """Corrected body rate of the IMU sample covering relative time ``t``."""
        m = min(self.imu.index(t), len(self.imu) - 1)
        return self.propagation.gyro.corrected(self.imu.w[m], self.theta)

    def _acquire_navigation(self, t_exp: float) -> None:
        """Set the method's navigation blocks (nominal and covariance) at acquisition."""

    def _before_star_update(self) -> None:
        """Extra measurements before the star update (the swaying filter's reference)."""

    def _after_reacquire(self) -> None:
        """Bookkeeping after a successful re-acquisition."""

    # ------------------------------------------------------------------ propagation helpers
    def _inflate_bridged(self, ma: int, mb: int, ta: float, tb: float) -> None:
        """Covariance inflation by the bridged IMU intervals in ``(ta, tb]``."""
        var_w, var_f, long_gap, n_entered = self.imu.bridged_variance(ta, tb, ma, mb)
        if not var_w and not n_entered:
            return
        self.state.add_noise({"gyro": var_w, "accel": var_f})
        if long_gap:
            self._gap_pending = True
            log.warning("IMU gap before t=%.3f s: the attitude is re-acquired from the stars",
                        tb)
        elif n_entered:  # short gaps are counted (imu_bridged) and reported at the end
            log.debug("IMU gap before t=%.3f s bridged: attitude uncertainty inflated by "
                      "%.3g rad", tb, math.sqrt(var_w))

    # ------------------------------------------------------------------ acquisition
    def _attitude_function(self, phi: np.ndarray | None = None):
        """``shift -> (R_i_b, ω)`` around the current state, for :meth:`StarModel.predict`.

        Time from the current state to the frame stamp comes from exact relative times; the
        model asks for the attitude ``shift`` seconds after the frame's reported stamp.
        """
        return state_attitude(self.R_i_b, self.omega, self._stamp_rel - self.t, phi)

    def _predict(self, theta: np.ndarray, u_i: np.ndarray, ctx: FrameContext,
                 phi: np.ndarray | None = None):
        """The model's prediction of ``u_i`` around the current state (and ``phi``)."""
        return self.model.predict_state(theta, u_i, ctx, self.R_i_b, self.omega,
                                        self._stamp_rel - self.t, phi,
                                        compiled=self.compiled_step)

    # ------------------------------------------------------------------ state snapshots
    def _snapshot(self, full: bool = False) -> tuple:
        """Copy of the estimate (P, nominal values); ``full`` adds time and sensitivity."""
        snap = (self.state.snapshot(sensitivity=full),)
        if full:
            snap += (self.t, self._k)
        return snap

    def _restore(self, snap: tuple) -> None:
        self.state.restore(snap[0])
        if len(snap) > 1:
            self.t, self._k = snap[1:]
        self._omega_stale = True

    # ------------------------------------------------------------------ updates
    def inject(self, dx: np.ndarray) -> None:
        """Apply the error estimate to the nominal state (box-plus) and reset P."""
        self.state.inject(dx)
        self._omega_stale = True

    def _star_jacobian(self, pred) -> tuple[np.ndarray, np.ndarray]:
        """``H`` (n, 2, N) of a prediction and its consider columns (n, 2, m)."""
        n = len(pred.uv)
        H = np.zeros((n, 2, self.N))
        H[:, :, self.ia] = pred.H_attitude
        H[:, :, self.it] = pred.H_parameters[:, :, :self.P_est]
        return H, pred.H_parameters[:, :, self.P_est:]

    def update(self, uv: np.ndarray, u_i: np.ndarray, ctx: FrameContext,
               sigma: np.ndarray) -> FrameUpdate | None:
        """Propagate to the frame's exposure and update with its stars."""
        model = self.model
        shift = model.exposure_shift(self.theta, ctx)
        t_exp = self._stamp_rel + shift
        if self.compiled_step:
            done, result = self._fused_update(uv, u_i, ctx, sigma, t_exp)
            if done:
                return result
        try:
            self.propagate(t_exp)
        except NoImuError:
            self.counters.skipped_no_imu += 1
            return None
        if self.gyro_watch is not None:
            self._R_prior = (self.R_i_b.copy(), self._gap_pending)
        if self._gap_pending:
            self._gap_pending = False
            if self.reacquire(uv, u_i, ctx, sigma):
                self.counters.add("reacquired_after_gap")
                return None
        self._before_star_update()
        return self._star_update(uv, u_i, ctx, sigma, t_exp)

    def _star_update(self, uv, u_i, ctx, sigma, t_exp) -> FrameUpdate:
        """The star update of a propagated state (the numpy reference path).

        With :attr:`compiled_star_update` (and :attr:`compiled_step`) the same update in one
        compiled call (:meth:`_compiled_star_update`), when the model has a compiled chain.
        """
        if self.compiled_star_update and self.compiled_step:
            result = self._compiled_star_update(uv, u_i, ctx, sigma, t_exp)
            if result is not None:
                return result
        c = self.config
        n = len(uv)
        N = self.N
        R_meas = sigma**2
        theta0 = self.theta.copy()
        pred0 = self._predict(theta0, u_i, ctx)
        H0, Hb0 = self._star_jacobian(pred0)
        nu0 = uv - pred0.uv
        jit = cov.compiled_kernels() if self.compiled_step else None
        # the frame's common noises: one stamp error δt moves every star (R gains c cᵀ,
        # c = σ_t ∂uv/∂t), one shift of all its stars (R gains σ_f² I₂ in every pair's block)
        c_t = cov.common_columns(pred0.H_attitude, ctx.R_i_b, ctx.omega_b, self.stamp_sigma,
                                 self.frame_sigma) \
            if self.stamp_sigma > 0 or self.frame_sigma > 0 else None
        if jit is not None:
            Hs, Ps = (H0, self.P) if c_t is None else (
                np.concatenate([H0, c_t], axis=2), cov.augment(self.P, c_t.shape[2]))
            S_blocks, nis_stars = jit.star_blocks(np.ascontiguousarray(Hs),
                                                  np.ascontiguousarray(Ps),
                                                  np.ascontiguousarray(R_meas, dtype=float),
                                                  nu0)
        else:
            S_blocks = (H0 @ self.P) @ H0.transpose(0, 2, 1)
            S_blocks[:, 0, 0] += R_meas
            S_blocks[:, 1, 1] += R_meas
            if c_t is not None:
                S_blocks += c_t @ c_t.transpose(0, 2, 1)
            nis_stars = block_nis(nu0, S_blocks)
        gate = self.gate.decide(nis_stars, pred0.directions_st)
        accepted = gate.accepted
        n_acc = int(np.count_nonzero(accepted))
        self._gated(gate.mismatch, gate.scale, gate.lost_lock, gate.outside_fov, n, n_acc, t_exp)
        result = FrameUpdate(ctx.stamp, t_exp, accepted, uv, pred0.uv, S_blocks, nis_stars,
                             float("nan"), 0, pred0.directions_st, self.omega.copy(), 0)
        if n_acc < c.min_stars:
            self._too_few(uv, u_i, ctx, sigma, t_exp)
            return result
        self._rejected_in_row = self._reacquire_streak = 0
        idx = np.flatnonzero(accepted)
        if n_acc == n:  # every star accepted (the usual case): the same values, no copies
            z, r_diag = uv.reshape(-1), np.repeat(R_meas, 2)
            H, h = H0.reshape(-1, N), pred0.uv.reshape(-1)
        else:
            z = uv[idx].reshape(-1)
            r_diag = np.repeat(R_meas[idx], 2)
            H = H0[idx].reshape(-1, N)
            h = pred0.uv[idx].reshape(-1)
        ctx_acc = None

        def relinearize(dx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            nonlocal ctx_acc
            if ctx_acc is None:
                ctx_acc = subset_context(ctx, idx)
            th = theta0.copy()
            th[:self.P_est] += dx[self.it]
            pred = self._predict(th, u_i[idx], ctx_acc, dx[self.ia])
            Hn, _ = self._star_jacobian(pred)
            return Hn.reshape(-1, N), pred.uv.reshape(-1)

        Hb = Hb0[idx].reshape(-1, self.n_consider) if self.n_consider else None
        common = None if c_t is None else c_t[idx].reshape(-1, c_t.shape[2])
        # (the frame's likelihood where the stars share the stamp's error or a shift: its
        # log det at the prior, its NIS the update's first pass)
        logdet = cov.frame_logdet(self.P, H, r_diag, common) if common is not None else 0.0
        res = self.state.iterated_update(H, h, z, r_diag, relinearize, self.update_policy,
                                         self.ia, self.it, Hb, compiled=self.compiled_step,
                                         common=common)
        if not res.ok:
            self._failed(res.reason, t_exp)
            return result
        if common is not None:
            result.joint = cov.joint_correction(res.nis, logdet, S_blocks, nis_stars, accepted)
        self.inject(res.dx)
        self._updated(result, res.nis, int(len(z)), res.iterations)
        return result

    def _compiled_star_update(self, uv, u_i, ctx, sigma, t_exp) -> FrameUpdate | None:
        """:meth:`_star_update` through :func:`~.frame_step.star_update`; None: not taken.

        Not taken (the numpy update) when :meth:`~.frame_step.FusedStep.build_update` gives
        none: no compiled chain, or a filter with its own injection or prediction.

        The numpy path's bookkeeping (gate counts, too few stars, a failure's line, the
        counters) around one compiled call; the navigation blocks' correction is injected
        here (the call injects the attitude and θ̂ and resets the covariance).
        """
        us = self._update_step
        if us is None:
            us = self._update_step = _frame_step_module().FusedStep.build_update(
                self, StarFilter) or False
        if not us:
            return None
        st = self.state
        if not st.P.flags.c_contiguous:
            st.P = np.ascontiguousarray(st.P)
        R = self.R_i_b
        if not (R.flags.c_contiguous and R.flags.writeable):
            R = self.R_i_b = np.array(R, dtype=float)
        omega = self.omega
        status, ints, floats, accepted, uv_pred, S, nis_stars, dirs, dx = us.update(
            st.P, self.theta, R, st.sensitivity, omega, uv, u_i, sigma,
            self._stamp_rel - self.t, ctx)
        return self._compiled_result((status, ints, floats, accepted, uv_pred, S, nis_stars,
                                      dirs, omega), uv, u_i, ctx, sigma, t_exp, dx)

    def _compiled_result(self, got: tuple, uv, u_i, ctx, sigma, t_exp,
                         dx: np.ndarray | None = None) -> FrameUpdate:
        """The bookkeeping of a compiled update (gate counts, result, skip, failure, counts).

        ``got``: ``(status, ints, floats, accepted, uv_pred, S, nis_stars, directions,
        omega)`` of the call.  ``dx`` (the star update alone, :meth:`_compiled_star_update`):
        the correction whose navigation blocks are injected here, and a frame with enough
        stars ends a run of rejected frames even when its update fails (the numpy update's
        order); None: the fused step's.
        """
        frame_step = _frame_step_module()
        status, ints, floats, accepted, uv_pred, S, nis_stars, dirs, omega = got
        n, n_acc = len(uv), int(ints[0])
        self._count_gated(ints[None], floats[None], (n,), (n_acc,), (t_exp,))
        result = FrameUpdate(ctx.stamp, t_exp, accepted, uv, uv_pred, S, nis_stars,
                             float("nan"), 0, dirs, omega.copy(), 0)
        if status == frame_step.FEW_STARS:
            self._too_few(uv, u_i, ctx, sigma, t_exp)
            return result
        if dx is not None:
            self._rejected_in_row = self._reacquire_streak = 0
        if status != frame_step.UPDATED:
            self._failed(frame_step.REASONS[status], t_exp)
            return result
        st = self.state
        if dx is not None:
            nom = st.nominal
            for b in self.navigation_blocks:  # (vector blocks: FusedStep.build_update)
                nom[b.value_name] = nom[b.value_name] + dx[self.layout.sl(b.name)]
        sens = st.sensitivity
        if sens is not None and sens.accumulate:
            sens.frames += 1
        self._omega_stale = True
        result.sums = floats[2:12]
        self._updated(result, float(floats[0]), 2 * n_acc, int(ints[1]))
        return result

    # ------------------------------------------------------------------ one compiled call
    def _fused_update(self, uv, u_i, ctx, sigma, t_exp) -> tuple[bool, FrameUpdate | None]:
        """Propagation and star update in one compiled call (:mod:`.frame_step`).

        ``(False, None)`` when the frame needs the numpy path (nothing changed): no compiled
        chain, a method with its own transition or measurements, a bridged IMU sample, a
        re-acquisition pending, a reference strapdown to rebuild.
        """
        frame_step = _frame_step_module()
        fs = self._fused_step()
        rows = self._fused_rows(self.t, self._k, [t_exp]) if fs else None
        if not rows:
            self._batch = None
            return False, None
        m, j, mj = rows[0]
        imu, prop = self.imu, self.propagation
        pre = prop.prefix
        st = self.state
        sens = st.sensitivity
        P = st.P if st.P.flags.c_contiguous else np.ascontiguousarray(st.P)
        st.P = P
        batch = self._batch
        got = batch.take(P, self.theta, self.R_i_b, sens, uv, j, mj, self.t, t_exp,
                         prop._gamma, pre) if batch is not None else None
        if got is None:  # not a frame of the batch (or none): the one call
            self._batch = None
            got = fs.call(P, self.theta, self.R_i_b, sens, pre, j, mj, self.t, t_exp, prop,
                          imu.w[m], uv, u_i, sigma, self._stamp_rel - t_exp, ctx)
        status, ints, floats, accepted, uv_pred, S, nis_stars, dirs, omega, R_prior = got
        if status == frame_step.REBUILD:
            return False, None
        self.t = t_exp
        self._k = m
        self.omega = omega
        if self.gyro_watch is not None:
            self._R_prior = (R_prior, False)
        return True, self._compiled_result((status, ints, floats, accepted, uv_pred, S,
                                            nis_stars, dirs, omega), uv, u_i, ctx, sigma, t_exp)

    def _fused_step(self):
        """The filter's :class:`~.frame_step.FusedStep` (built on first use), or False."""
        fs = self._frame_step
        if fs is None:
            fs = self._frame_step = _frame_step_module().FusedStep.build(self, StarFilter) \
                or False
        return fs

    def _fused_rows(self, t: float | None, k: int, t_exps: list[float]
                    ) -> list[tuple[int, int, int]]:
        """``(m, j, mj)`` of the fused step of frames in a row, the first from ``(t, k)``.

        ``t_exps``: their exposure times, each frame's step from the one before.  ``m`` the
        IMU sample covering ``t_exp``, ``j..mj`` the rows of the reference prefix; for the
        leading frames that take the fused step (:func:`~.frame_step.fused_sample`), up to
        the first that takes the numpy path: a bridged sample in the interval, a
        re-acquisition pending, a time not after the one before, or rows outside the
        reference.
        """
        if self._gap_pending or t is None:
            return []
        imu, prop = self.imu, self.propagation
        pre = prop.prefix
        if pre is None:
            return []
        fused_sample = _frame_step_module().fused_sample
        off = imu.base - pre.base
        out = []
        for te in t_exps:
            if te <= t:
                break
            m = int(fused_sample(imu.t, imu.cum_bridged, k, te, imu.base, pre.base, pre.end,
                                 prop.ref_start, float(prop.window)))
            if m < 0:
                break
            out.append((m, k + off, m + off))
            t, k = te, m
        return out

    def batches_moving_shift(self) -> bool:
        """Whether :meth:`prepare_frames` batches frames whose exposure shift moves.

        An estimated time offset (``StarModel.affine_exposure_shift``): the compiled call
        finds each frame's exposure time.  The driver then gathers a replay's ready frames
        in runs for it even so.
        """
        return bool(self.compiled_step and self.batched_step and self._fused_step()
                    and self.model.affine_exposure_shift() is not None)

    def prepare_frames(self, frames: list[tuple], shift: float | None | bool = False,
                       ready: tuple[float, float] | None = None) -> int:
        """Run the fused step of a run of coming frames in one compiled call (a replay's pump).

        ``frames``: ``(uv, u_i, ctx, sigma, t_rel, accumulate)`` of the frames
        :meth:`process_frame` will be given next, in that order (``accumulate``: the
        sensitivity's flag the caller will set for it).  The leading frames that take the
        fused step as things stand (valid stars, in order, no covariance check due among
        them) are stepped by :func:`~.frame_step.frame_steps` at once; each
        :meth:`process_frame` then takes its frame's result and state instead of a call of
        its own — the same floats.  Any other frame (or any other call) drops what is left.
        Returns the frames stepped.

        ``shift``: the exposure shift every frame has
        (:meth:`~.star_model.StarModel.fixed_exposure_shift`; False: computed here).  None
        (an estimated time offset): each frame's exposure time, IMU rows and the reference's
        bounds are found in the compiled call from the state after the frame before
        (:meth:`batches_moving_shift`); ``ready = (imu_end, lookahead)`` then stops the
        batch before a frame the driver would not hand on yet under that state
        (``imu_end <= t_exp + lookahead``; None: every frame is ready).
        """
        self._batch = None
        fs = self._fused_step() if self.compiled_step and self.batched_step and \
            self.initialized else False
        if not fs or len(frames) < 2:  # (the driver's [] drops a batch's rest: no shift)
            return 0
        if shift is False:
            shift = self.model.fixed_exposure_shift(self.theta, self.P_est)
        # a frame's exposure time depends on the frames before it in the batch when the shift
        # moves (an estimated time offset): the compiled call finds it (vary)
        vary = self.model.affine_exposure_shift() if shift is None else None
        if shift is None and vary is None:
            return 0
        c = self.config
        every = c.covariance_check_every
        left = every - self.counters.updates % every if every and not self.checks_deferred \
            else len(frames)
        left = min(left, self.batch_frames_max)  # (the batch keeps each frame's state)
        t, k, last = self.t, self._k, self.last_stamp
        imu = self.imu
        run = []
        for uv, u_i, ctx, sigma, t_rel, acc in frames[:left]:
            if ctx is None or len(uv) < c.min_stars or not math.isfinite(t_rel) or \
                    (last is not None and t_rel <= last) or ctx.stamp >= self._step_at:
                break  # (a step is taken frame by frame: process_frame)
            if vary is not None:  # (the call finds the rest)
                run.append((uv, u_i, sigma, math.nan, ctx, 0, 0, t, math.nan, 0, acc, t_rel))
            else:
                run.append((uv, u_i, sigma, ctx, acc, t_rel))
            last = t_rel
        if vary is None:  # each frame's rows from the one before, up to the first without
            t_exps = [f[5] + shift for f in run]
            rows = self._fused_rows(t, k, t_exps)
            run = [(uv, u_i, sigma, t_rel - tb, ctx, j, mj, ta, tb, m, acc, t_rel)
                   for (uv, u_i, sigma, ctx, acc, t_rel), ta, tb, (m, j, mj) in zip(
                       run, [t, *t_exps], t_exps, rows, strict=False)]
        if len(run) < 2:
            return 0
        st = self.state
        if not st.P.flags.c_contiguous:
            st.P = np.ascontiguousarray(st.P)
        pre, prop = self.propagation.prefix, self.propagation
        if vary is not None:
            if self._gap_pending or t is None or pre is None:
                return 0
            end, look = ready if ready is not None else (math.inf, 0.0)
            window = float(prop.window)
            vary = vary + (np.array([1.0, k, imu.base, pre.base, pre.end, prop.ref_start,
                                     window, end, look]),)
        self._batch = fs.batch(st.P, self.theta, self.R_i_b, st.sensitivity, pre, prop, imu,
                               run, vary)
        return self._batch.done if self._batch is not None else 0

    def commit_batch(self, limit: int):
        """Commit the prepared batch's leading updated frames at once (at most ``limit``).

        What :meth:`process_frame` of each would do, frame after frame, for frames the
        batch stepped (:meth:`prepare_frames`) to ``UPDATED`` with a finite NIS, given as
        prepared (valid stars: the caller knows): counters, gate counts, the state after
        the last of them (only that one is written), a covariance check due at the last,
        the gyro watch fed each frame's propagated and updated attitudes
        (:func:`~stellar_cal_ros.core.gyro_check.watch_frames`: the same records and
        verdicts, frame after frame).  None (nothing done) when the batch is not at its
        start, its first frame is not such a frame, or the gyro watch is within its first
        frames and :attr:`commit_early_frames` is False (a fault there raises in that
        frame's turn).
        The frames after those committed are taken one at a time as before.  Returns the
        :class:`~.frame_step.BatchCommit` (the frames' values for the statistics and the
        history; their :class:`FrameUpdate` on request).
        """
        b = self._batch
        w = self.gyro_watch
        if b is None or b.i or limit < 1 or (w is not None and (w["done"] or (
                w["frames"] < gyro_check.EARLY_FRAMES and not self.commit_early_frames))):
            return None
        frame_step = _frame_step_module()
        (_, status, ints, floats, _, _, _, _, _, omega, R_pr, Ps, ths, Rs, Ms, scs,
         ins) = b.out[:17]  # (a method's batch may return more: _commit_more's)
        q = min(int(limit), b.done)
        ok = (status[:q] == frame_step.UPDATED) & np.isfinite(floats[:q, 0])
        if not ok.all():
            q = int(np.argmin(ok))
        if q < 1:
            return None
        frames = b.frames
        last = q - 1
        f_last = frames[last]
        st = self.state
        sens = st.sensitivity
        st.P[...] = Ps[last]  # (the arrays the batch was made from: FrameBatch.take's)
        self.theta[...] = ths[last]
        self.R_i_b[...] = Rs[last]
        if sens is not None:
            sens.M[...] = Ms[last]
            sens.score[...] = scs[last]
            sens.info[...] = ins[last]
            sens.frames += sum(1 for f in frames[:q] if f[10])
            sens.accumulate = f_last[10]
        b.i = q
        self._commit_more(b.out, frames, q)
        fc = self.counters
        fc.frames += q
        self.last_stamp = f_last[11]
        self._stamp_posix = f_last[4].stamp
        self._stamp_rel = f_last[11]
        self.t = f_last[8]
        self._k = f_last[9]
        self.omega = omega[last].copy()
        self._omega_stale = True
        self._R_prior = None
        offs = b.offs
        n = [offs[i + 1] - offs[i] for i in range(q)]
        n_acc = ints[:q, 0].tolist()
        self._count_gated(ints, floats, n, n_acc, [f[8] for f in frames[:q]])
        self._count_updates(q)
        if self.gyro_watch is not None:
            R_post = Rs[:q].copy()
            R_post[last] = self.R_i_b  # (the state after a check's repair, as frame by frame)
            t_exp = [f[8] for f in frames[:q]]
            uv = [f[0] for f in frames[:q]]
            u_i = [f[1] for f in frames[:q]]
            unproject = self.model.prior.camera.unproject
            i = 0
            while i < q and self.gyro_watch is not None:
                i, cause = gyro_check.watch_frames(self.gyro_watch, t_exp, uv, u_i, R_pr, R_post,
                                                   self._R_imu_st_prior, unproject, i, q)
                self.t = t_exp[i - 1]  # (the verdict's log line names the frame)
                self._gyro_verdict(cause)
            self.t = f_last[8]
        return frame_step.BatchCommit(b, q, n, n_acc, st.sigma(), self.theta_estimated(),
                                      self.P_est, FrameUpdate)

    def _commit_more(self, out: tuple, frames: list, q: int) -> None:
        """A method's own part of :meth:`commit_batch` (its batch's ``out``): none here.

        Called with the state after frame ``q − 1`` written, before the counters and checks.
        """

    # ------------------------------------------------------------------ update bookkeeping
    def _count_gated(self, ints: np.ndarray, floats: np.ndarray, n: Sequence[int],
                     n_acc: Sequence[int], t_exp: Sequence[float]) -> None:
        """:meth:`_gated` of compiled steps in a row (one frame, or a batch's committed ones).

        Row ``i`` of ``ints`` / ``floats`` (:func:`~.frame_step.frame_step`'s) is frame ``i``'s
        gate: mismatch, lost lock and stars outside the field (``ints[i, 2:5]``), the NIS
        scale (``floats[i, 1]``); ``n``, ``n_acc``: its stars and accepted stars.
        """
        q = len(n)
        if ints[:q, 2:5].any():  # a mismatch, lost lock or stars outside: frame by frame
            for i in range(q):
                self._gated(bool(ints[i, 2]), float(floats[i, 1]), bool(ints[i, 3]),
                            int(ints[i, 4]), n[i], n_acc[i], t_exp[i])
        else:  # what _gated does for q frames none of which is flagged
            self._mismatch_bits = (self._mismatch_bits << q) & 0x3FF
            self.counters.stars_gated += sum(n) - sum(n_acc)

    def _count_updates(self, q: int) -> None:
        """Count ``q`` frames updated in a row (the state now the last one's).

        The counters, and the covariance check when one is due at the last (none is due
        before it: the caller's part; :meth:`prepare_frames` ends a batch there).
        """
        self._rejected_in_row = self._reacquire_streak = 0
        fc = self.counters
        fc.updates += q
        every = self.config.covariance_check_every
        if every and fc.updates % every == 0 and not self.checks_deferred:
            self._batch = None  # (the check may repair the state)
            self._check_covariance()

    def _gated(self, mismatch: bool, scale: float, lost: bool, outside: int, n: int,
               n_acc: int, t_exp: float) -> None:
        """Count what the gate decided (and warn once about a model mismatch pattern)."""
        # the last 10 frames as bits: one odd frame is counted, a pattern is reported
        self._mismatch_bits = ((self._mismatch_bits << 1) | int(mismatch)) & 0x3FF
        if mismatch:
            self.counters.add("frames_model_mismatch")
            if not self._mismatch_warned and bin(self._mismatch_bits).count("1") >= 3:
                self._mismatch_warned = True
                log.warning("t=%.3f s: the stars' median NIS is %.0fx what the model expects "
                            "(3 or more of the last 10 frames): the model misses an effect "
                            "(run stellar-cal diagnose)", t_exp, scale)
        if lost:
            self.counters.add("frames_lost_lock")
        if outside:
            self.counters.add("stars_outside_fov", outside)
        self.counters.stars_gated += n - n_acc

    def _too_few(self, uv, u_i, ctx, sigma, t_exp) -> None:
        """A frame with too few accepted stars: skipped; a few in a row re-acquire.

        ``reinit_after`` rejected frames in a row re-acquire; when re-acquisitions keep
        failing or keep being lost before any accepted update (a model far from the data:
        a diagnosis's wrong candidate), each further one waits for twice as many rejected
        frames (at most 2**``reacquire_backoff`` x): every attempt costs a full
        second-order initialisation, ~0.2-0.4 s, and was made at every third frame.
        """
        c = self.config
        self.counters.skipped_few_stars += 1
        self._rejected_in_row += 1
        wait = c.reinit_after << min(self._reacquire_streak, c.reacquire_backoff)
        if self._rejected_in_row >= wait:
            # lost lock (e.g. after an IMU gap during a slew): re-acquire from this frame
            log.warning("t=%.3f s: %d frames in a row rejected, re-acquiring the attitude",
                        t_exp, self._rejected_in_row)
            self._reacquire_streak += 1
            if not self.reacquire(uv, u_i, ctx, sigma):
                self._rejected_in_row = 0  # the next attempt waits ``wait`` frames again

    def _failed(self, reason: str, t_exp: float) -> None:
        self.counters.add("update_failed")
        log.warning("t=%.3f s: %s: frame skipped", t_exp, reason)

    def _updated(self, result: FrameUpdate, nis: float, dof: int, iterations: int) -> None:
        self._count_updates(1)
        result.nis = nis
        result.dof = dof
        result.iterations = iterations

    def defer_checks(self) -> None:
        """Leave the periodic checks to :meth:`run_checks` (the live node's timer).

        The gyro judgement (:meth:`defer_gyro_judgement`) and the covariance health check
        due every ``covariance_check_every`` updates then run between frames, not in a
        frame's update (where the check's eigen-decomposition put the frame in the
        latency tail); the counts are the same once the checks have run.
        """
        self.checks_deferred = True
        self.defer_gyro_judgement()

    def run_checks(self) -> None:
        """Run what :meth:`defer_checks` left due (may raise as a frame's update would)."""
        self.judge_gyro()
        self.check_covariance_due()

    def check_covariance_due(self) -> None:
        """The deferred covariance check, if an update count it was due at has passed."""
        every = self.config.covariance_check_every
        if not (self.checks_deferred and every):
            return
        due = self.counters.updates // every
        if due > self.counters.covariance_checks:  # one check for all that are due
            self.counters.covariance_checks = due - 1
            self._check_covariance()

    def _check_covariance(self) -> None:
        """Cheap health check of P; repair (or roll back) instead of going on corrupted."""
        self.counters.covariance_checks += 1
        try:
            self.state.check(f"{self.method} covariance")
        except ModelError as exc:
            self.counters.covariance_repairs += 1
            if self.state.repair():
                log.warning("%s: repaired (eigenvalues clipped)", exc)
            elif self._good is not None:
                self._restore(self._good)
                log.warning("%s: rolled back to the last healthy state", exc)
            else:
                raise
            return
        self._good = self._snapshot()

    def _take_steps(self, stamp: float) -> None:
        """The effects' steps ``stamp`` reaches: each a free jump of the parameters.

        Their variance grows by the effect's default σ² (a step of independent size, its
        prior σ), after the effect is shown its estimate just before
        (:meth:`~.effects.base.Effect.stepped`): the filter marginalizes one step after the
        other, so a step per slew is a few states however many slews
        (:class:`~stellar_cal_ros.diagnosis.slew_steps.SlewSteps`).  An effect that
        :attr:`~.effects.base.Effect.keeps_before_step` has its second half of parameters
        set to the first half (value, covariance rows and columns, sensitivity rows) before
        the first half steps: the value before the last step, which the frames after it go
        on refining (never in the measurement).  Taken before the update of the first frame
        whose stamp (POSIX s) is at or after the step's time.
        """
        steps, i = self._steps, self._next_step
        P, theta = self.state.P, self.theta
        sens = self.state.sensitivity
        while i < len(steps) and stamp >= steps[i][0]:
            _, sl, eff, k = steps[i]
            at = np.arange(self.it.start + sl.start, self.it.start + sl.stop)
            # (P[at, at]: the diagonal)
            eff.stepped(k, theta[sl].copy(), np.sqrt(np.maximum(P[at, at], 0.0)))
            var = np.square(np.asarray(eff.default_sigma, dtype=float))
            if eff.keeps_before_step:
                m = len(at) // 2
                cur, old = at[:m], at[m:]
                P[old, :] = P[cur, :]
                P[:, old] = P[:, cur]
                theta[sl.start + m:sl.stop] = theta[sl.start:sl.start + m]
                if sens is not None:
                    sens.M[old] = sens.M[cur]
                at, var = cur, var[:m]
            P[at, at] += var
            i += 1
        self._next_step = i
        self._step_at = steps[i][0] if i < len(steps) else math.inf
        self._batch = None  # (a prepared batch stepped from the covariance before)

    def process_frame(self, uv: np.ndarray, u_i: np.ndarray, ctx: FrameContext,
                      sigma: np.ndarray, t_rel: float | None = None,
                      valid: bool = False) -> FrameUpdate | None:
        """Handle one star frame: acquire or update; count every skip.

        ``t_rel`` is the frame stamp relative to ``t0`` in s, best computed from integer
        nanoseconds (``(stamp_ns − t0_ns) · 1e-9``); default ``ctx.stamp − t0``.
        ``valid``: the caller knows every centroid, direction and σ finite and σ > 0
        (:attr:`~stellar_cal_ros.methods.frames.FrameInputs.valid`): not checked again.
        """
        self.counters.frames += 1
        t_rel = ctx.stamp - self.t0 if t_rel is None else float(t_rel)
        if not math.isfinite(t_rel):
            self.counters.add("skipped_bad_stamp")
            return None
        if self.last_stamp is not None:
            if t_rel == self.last_stamp:
                self.counters.skipped_duplicate += 1
                return None
            if t_rel < self.last_stamp:
                self.counters.skipped_out_of_order += 1
                log.warning("star frame at %.6f is older than the last one: skipped", ctx.stamp)
                return None
        # the whole frame at once first (the usual case: every star valid)
        if not valid and not (np.isfinite(uv).all() and np.isfinite(u_i).all()
                              and np.isfinite(sigma).all() and (sigma > 0).all()):
            good = np.isfinite(uv).all(axis=1) & np.isfinite(u_i).all(axis=1) & \
                np.isfinite(sigma) & (sigma > 0)
            self.counters.stars_invalid += int((~good).sum())
            uv, u_i, sigma = uv[good], u_i[good], sigma[good]
            ctx = subset_context(ctx, np.flatnonzero(good))
        if len(uv) < self.config.min_stars:
            self.counters.skipped_few_stars += 1
            return None
        self.last_stamp = t_rel
        self._stamp_posix = ctx.stamp
        self._stamp_rel = t_rel
        if ctx.stamp >= self._step_at:
            self._take_steps(ctx.stamp)
        if not self.initialized:
            if self.initialize(uv, u_i, ctx, sigma) and self.gyro_watch is not None:
                self._watch_gyro(uv, u_i, None)
            return None
        self._R_prior = None
        upd = self.update(uv, u_i, ctx, sigma)
        if self._R_prior is not None and self.gyro_watch is not None:
            R, gap = self._R_prior
            self._R_prior = None
            self._watch_gyro(uv, u_i, None if gap else R)
        return upd
