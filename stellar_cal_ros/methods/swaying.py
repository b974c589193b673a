"""Swaying-base installation calibration in the inertial frame (Zhang et al., IEEE Access 2018).

Error-state extended Kalman filter over an inertial-frame strapdown (GCRS axes).

Nominal state: attitude ``R̂_i_b``, velocity ``v̂ⁱ`` and position ``r̂ⁱ`` (position kept
relative to the site at the bag start, ``r_site(t0)``, so no 6e6 m numbers enter the filter),
and the parameter vector ``θ̂`` of the model's effects.  The baseline effect set
(:data:`BASELINE_EFFECTS`) is ``gyro_bias, accel_bias, installation`` (the paper's 15 states
with the navigation errors); further library effects (``gyro_scale_factor``,
``accel_scale_factor``, ``time_offset``, camera effects, …) enter through
:class:`~stellar_cal_ros.methods.star_model.StarModel`.

Default model (``stellar-cal replay --method swaying_base``)
------------------------------------------------------------
The baseline **plus every effect the prior's sigma block calls uncertain**
(:func:`prior_uncertain_effects`: a positive sigma on ``cx, cy`` adds ``principal_point``, on
the gyro error matrix's diagonal ``gyro_scale_factor``, …; a zero or absent sigma keeps the
quantity fixed at its prior value), plus ``--effects`` (``-id`` removes one).  Zhang et al.
assume a calibrated star sensor and a calibrated IMU error matrix; a datasheet prior that
says otherwise must not be overruled silently, because a fixed wrong parameter goes into the
installation: on the reference bag ``swaying_ideal`` (principal point (5, 10) px off,
distortion, 100 ppm / 100" IMU error matrix) the baseline alone gives installation errors
(516, −303, 52)" (NIS/dof 3.8), the baseline + IMU error matrix (522, −247, −0.5)" (NIS/dof
3.1: the principal point goes into the tilt); with the prior-driven model the filter is
consistent (NIS/dof 1.00, every parameter within 2σ of the truth).  The library function
:func:`replay_swaying` keeps the explicit form (baseline + ``effects``), which the diagnosis
and the benchmarks use.

What that bag supports (386 s, three base orientations; measured, truth only for checking):

* the *equivalent principal point* (image of the IMU-fixed nominal boresight, the
  principal-point / tilt combination a star tracker sees, as in the PSCE replay) and the
  installation *about the boresight*: errors (−0.22, +0.00) px and −5.4" against σ
  (0.23, 0.12) px and 6.3";
* the installation about the tracker x/y axes on its own: errors (−3, +15)" against σ
  (13, 16)" — the principal point and the tilt separate only through the perspective term.

Both σ are set by the gyro misalignment, which the bag determines only to 30-57 % of its
100" prior σ: with the IMU error matrix known, the equivalent principal point reaches
σ (0.002, 0.003) px (0.1") and the boresight rotation 0.35"; with the camera calibrated too,
every installation axis is within 0.5" (σ 0.14, 0.07, 0.35").  The 0.5" of Zhang et al. is
therefore reached for the quantities a star tracker can observe only with a pre-calibrated
IMU error matrix (or a longer / richer motion); the filter reports honest σ otherwise.

These σ are information limits, not filter losses: the posterior Cramér–Rao bound of this
model (:func:`crlb_swaying`, Jacobians on the true trajectory; ``benchmarks/swaying_bound.py``)
is (12.8, 16.3, 6.3)" with the shipped prior, (11.2, 11.1, 0.35)" with the IMU error matrix
known, (0.15, 0.07, 0.35)" with camera and IMU error matrix known — the filter's σ equal it to
< 0.1 %.  In the last case the rotation about the boresight is star-noise limited (half the
centroid σ halves it; the Z1 reference does not matter), i.e. ~0.35" / √(duration / 386 s).

Error state (true − nominal), ``N = 9 + P``::

    x = [φ (3), δθ (P), δvⁱ (3), δrⁱ (3)],   R_i_b = Exp(φ) R̂_i_b  (left, inertial, as PSCE)

(attitude and θ first, in :attr:`StarModel.slices` order, as in PSCE: ``sigma()[:3]`` is the
attitude, ``sigma()[3:3 + P]`` the parameters — the diagnosis reads them that way).

Continuous error model (Zhang eqs. 6 and 8, written for any GYRO/ACCEL-stage effect)::

    φ̇  = R̂ G_g δθ − R̂ n_g,            G_g = −(I+E_g)⁻¹ (∂b_g/∂θ + ∂E_g/∂θ ω̂)
    δv̇ = −[R̂ f̂]× φ + R̂ G_a δθ + R̂ n_a,  G_a = −(I+E_a)⁻¹ (∂b_a/∂θ + ∂E_a/∂θ f̂)
    δṙ = δv
    δθ̇_j = −δθ_j / τ_j + η_j           (first-order Gauss–Markov; τ = ∞: random constant)

(``−[R̂ f̂]× φ = [gⁱ]× ψ`` of Zhang eq. 8 with ψ = −φ on a base at rest.)  Because φ̇ has no φ
term, the transition over the IMU samples between two star frames is summed exactly
(cumulative sums, no matrix exponential), so the covariance is propagated once per frame.
The strapdown itself is vectorized over windows of 120 s of samples (reference frame,
coning and sculling), and a frame's propagation is a handful of matrix products over those
tables with first-order corrections for the change of θ̂ (:meth:`SwayingFilter.propagate`):
~750x real time filtering on swaying_ideal with the CLI's default model, ~600x with
reading the bag (per-sample propagation: ~370x / ~330x); the star prediction
(:meth:`StarModel.predict`) is now ~40 % of the filtering time.

Measurements
------------
Z1, the inertial reference (what makes the method work on a swaying base).  The base stays
at the site apart from the sway, whose *velocity* reaches 1.5 m/s (Zhang eq. 19) — used as
white measurement noise on ``v̂ⁱ − v_siteⁱ`` (Zhang eq. 9 taken literally) it swamps the
``g ψ t`` signature of a tilt (1" gives 5e-5 m/s² → 5 mm/s after 100 s).  The *displacement*,
the integral of the sway velocity, stays bounded (≤ 2 m): "the location of the swaying base
should be constant after integrating over a span of time".  So Z1 is the integral of
Zhang's Z1 — position matching::

    ν = (r_siteⁱ(t) − r_siteⁱ(t0)) − r̂ⁱ_rel(t) = δrⁱ − d(t),   R = σ_d² I

with ``d`` the unknown sway displacement (σ_d = ``sway_displacement_sigma_m``, default 2 m)
at ``position_interval_s`` (1 s).  A tilt now shows as ``½ g ψ t²`` (0.24 m after 100 s
for 1") against a bounded, zero-mean-periodic noise; the initial sway velocity ``δv(0)``
(σ ``initial_velocity_sigma_mps``) is a state.  The price of the sway: σ_d = 2 m instead of
the few mm of a base at rest, i.e. ~10⁵ less leveling information per sample; the periodic
noise is modelled as white (conservative: a sinusoid averages out as 1/N, faster than the
1/√N the filter assumes).  ``velocity_reference="velocity"`` gives the literal velocity
form for comparison (R = σ_v² I).

Z2, star directions, in pixel space: the catalogue direction ``lⁱ`` predicted through the
model (attitude, installation, prior camera) versus the measured centroid, with the
Jacobians of :meth:`StarModel.predict`.  To first order this is Zhang's
``Z2 = Ĉ lˢ − lⁱ = lⁱ × (ψ + Ĉ μ)`` with ``lˢ = camera.unproject(uv)``, mapped through the
camera Jacobian — but the pixel form has a full-rank 2×2 noise per star (the 3-vector form's
covariance is singular along ``lⁱ``), takes the tracker's per-star sigma directly, gates each
star with a 2-dof χ², lets camera or time-offset effects be added, and writes the same
residual table as PSCE (``t`` in POSIX seconds, the reported frame stamp).  Camera effects
are estimated when the model contains them (see "Default model" above).

Coarse alignment: the first frame with enough stars gives ``R_i_st`` (pixel-space Wahba /
Gauss–Newton), ``R̂_i_b = R_i_st R̂_imu_stᵀ`` with the initial attitude error correlated with
the installation error exactly as in PSCE; the accelerometers check the level (logged).

Neglected, with their size (target 0.5"):

* polar motion (≤ 0.5") — tilts the inertial gravity direction by the same angle; the level
  reference enters only through Z1, which the stars dominate, and the error is absorbed by
  the accelerometer bias (g·0.5" = 2.4 µg); the site position error (≤ 15 m, constant) goes
  into δr(0).
* dut1 (|UT1−UTC| < 0.9 s) — rotates the site about the pole by up to 13"; set
  ``SwayingConfig.dut1`` from IERS Bulletin A in the field.  The reference bags use 0.
* gravity anomaly / deflection of the vertical — normal (WGS84) gravity is used; a
  deflection ξ looks like an accelerometer bias g·ξ in each base orientation and is
  estimated as such; the vertical gravity gradient over the sway (3e-6 s⁻²·2 m = 0.6 µg)
  and lunisolar tides (< 0.2 µg) are below the accelerometer noise.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stellar_cal_ros.core import earth
from stellar_cal_ros.core.attitude import fit_frame_attitude
from stellar_cal_ros.core.catalog import radec_to_unit
from stellar_cal_ros.core.kalman import block_nis, chi2_gate
from stellar_cal_ros.core.rotation import (
    quat_from_matrix,
    quat_from_rotvec,
    quat_to_matrix,
    skew,
    so3_exp,
)
from stellar_cal_ros.core.strapdown import (
    attitude_increments,
    attitude_prefix,
    quat_cumprod,
    velocity_increments,
)
from stellar_cal_ros.effects import registry
from stellar_cal_ros.effects.base import FrameContext, Stage
from stellar_cal_ros.errors import ModelError
from stellar_cal_ros.io.calibration import Calibration
from stellar_cal_ros.methods.psce import FilterCounters, FrameUpdate
from stellar_cal_ros.methods.replay import (
    RESIDUAL_COLUMNS,
    TOPIC_FIX,
    BagData,
    ReplayResult,
    _interp_many,
    _log_counters,
    _Progress,
    clean_frame,
    equivalent_principal_point,
    read_bag_data,
    result_calibration,
)
from stellar_cal_ros.methods.star_model import StarModel

log = logging.getLogger(__name__)

BASELINE_EFFECTS = ("gyro_bias", "accel_bias", "installation")
DEG_PER_HOUR = np.pi / 180.0 / 3600.0
ARCSEC = np.rad2deg(1.0) * 3600.0  #: arcsec per radian
G0 = 9.80665


@dataclass
class SwayingConfig:
    """Noise levels and decisions of the swaying-base filter (defaults: Zhang Table 1)."""

    centroid_sigma_px: float = 0.058  #: used when a star message has sigma = 0 (≈ 3")
    gyro_arw_deg_sqrth: float = 0.003 / 60.0  #: 0.003 °/h/√Hz
    accel_vrw_mps_sqrth: float = 5e-6 * G0 * 60.0  #: 5 µg/√Hz
    #: first-order Gauss–Markov sensor states: effect id → (τ s, steady-state σ per parameter)
    gauss_markov: dict[str, tuple[float, float]] = field(default_factory=lambda: {
        "gyro_bias": (86400.0, 0.005 * DEG_PER_HOUR),
        "accel_bias": (86400.0, 5e-6 * G0),
    })
    #: Z1 form: "position" (integral; sway displacement as noise) or "velocity" (literal)
    velocity_reference: str = "position"
    sway_displacement_sigma_m: float = 2.0  #: σ_d of the sway displacement (position form)
    sway_velocity_sigma_mps: float = 1.5  #: σ_v of the sway velocity (velocity form)
    initial_velocity_sigma_mps: float = 2.0  #: σ of δv at alignment (sway velocity then)
    position_interval_s: float = 1.0  #: Z1 every this many seconds (at star frames)
    dut1: float = 0.0  #: UT1 − UTC, s
    gate_probability: float = 0.9999  #: per-star χ² (2 dof) acceptance probability
    min_stars: int = 3
    max_iterations: int = 4  #: iterated-EKF relinearizations per frame
    relinearize_rad: float = 2e-5  #: iterate while the attitude correction exceeds this
    imu_gap_factor: float = 3.0
    gap_rate_sigma: float = 1e-3  #: rad/s over an IMU gap
    gap_accel_sigma: float = 0.5  #: m/s² over an IMU gap
    #: a frame after more IMU gap than this re-acquires attitude, velocity and position (a
    #: sway period is ~10 s: the rate during a gap is unknown after a fraction of it)
    gap_reacquire_s: float = 0.1
    #: this many frames in a row with too few stars passing the gate re-acquire (lost lock)
    reinit_after: int = 3
    init_outlier_px: float = 5.0
    grid_step_s: float = 0.25  #: Earth-orientation grid (gravitation, site), linear interp.
    #: per-sample propagation between star frames (the reference; ~10x slower)
    exact_propagation: bool = False
    #: a frame's first-order attitude correction for θ̂ − θ_window larger than this rebuilds
    #: the reference strapdown under the current θ (second-order error < ½ this², 5e-9 rad)
    fast_propagation_max_rad: float = 1e-4
    reference_window_s: float = 120.0  #: length of a reference strapdown window


class _NoImuError(Exception):
    """The IMU data do not reach the requested time."""


class SwayingFilter:
    """Inertial-frame error-state Kalman filter (see the module docstring).

    Parameters
    ----------
    model : StarModel
        Effects (parameter layout θ) and the prior.
    imu_t, imu_w, imu_f : ndarray
        IMU stamps (s relative to ``t0``, end of each interval), mean rates (rad/s) and mean
        specific forces (m/s²).
    t0 : float
        POSIX time of relative zero.
    site : Site
        Site of the base (``/gnss/fix``).
    """

    method = "swaying_base"

    def __init__(self, model: StarModel, imu_t, imu_w, imu_f, t0: float, site: earth.Site,
                 config: SwayingConfig | None = None) -> None:
        self.model = model
        self.config = config or SwayingConfig()
        c = self.config
        self.t0 = float(t0)
        self.site = site
        self.imu_t = np.asarray(imu_t, dtype=float)
        self.imu_w = np.asarray(imu_w, dtype=float)
        self.imu_f = np.asarray(imu_f, dtype=float)
        self.nominal_dt = float(np.median(np.diff(self.imu_t[:1000])))
        P = model.size
        self.P_size = P
        # attitude first, then θ (the PSCE layout the diagnosis relies on), navigation last
        self.ia, self.it = slice(0, 3), slice(3, 3 + P)
        self.iv, self.ir = slice(3 + P, 6 + P), slice(6 + P, 9 + P)
        self.N = 9 + P
        self.theta = model.initial_value.copy()
        self.P = np.zeros((self.N, self.N))
        self.P[self.it, self.it] = np.diag(model.initial_sigma**2)
        # process noise of θ: Gauss–Markov where configured, else the effect's random walk
        self.tau = np.full(P, np.inf)
        self.q_theta = np.zeros(P)  # random-walk density² (unit²/s)
        self.gm_sigma = np.zeros(P)
        for eff in model.effects:
            sl = model.slices[eff.id]
            if eff.id in c.gauss_markov:
                tau, s = c.gauss_markov[eff.id]
                self.tau[sl] = tau
                self.gm_sigma[sl] = s
            else:
                self.q_theta[sl] = eff.process_noise_density() ** 2
        self.q_gyro = (np.deg2rad(c.gyro_arw_deg_sqrth) / 60.0) ** 2
        self.q_accel = (c.accel_vrw_mps_sqrth / 60.0) ** 2
        # Earth-orientation grid: gravitation, site position and velocity (GCRS)
        t_lo = float(self.imu_t[0]) - 2.0
        t_hi = float(self.imu_t[-1]) + 2.0
        self.grid = np.arange(t_lo, t_hi + c.grid_step_s, c.grid_step_s)
        tp = self.t0 + self.grid
        self.grid_g = earth.gravitation_gcrs(site, tp, c.dut1)
        r = earth.site_position_gcrs(site, tp, c.dut1)
        self.r_site0 = earth.site_position_gcrs(site, self.t0, c.dut1)
        self.grid_r = r - self.r_site0
        self.grid_v = earth.site_velocity_gcrs(site, tp, c.dut1)
        # Increments of every IMU sample under the prior sensor model, once (vectorized):
        # a frame's propagation corrects them to first order for θ̂ − θ_ref (the coning and
        # sculling cross terms of a bias change are < 1e-12 rad / 1e-9 m/s a sample).
        dt_full = np.diff(self.imu_t, prepend=self.imu_t[0] - self.nominal_dt)
        self._dt_full = dt_full
        self._w_ref, *_ = self._corrected(self.imu_w, Stage.GYRO)
        self._f_ref, *_ = self._corrected(self.imu_f, Stage.ACCEL)
        self._phi_ref = attitude_increments(self._w_ref, dt_full, coning=True)
        self._du_ref = velocity_increments(self._w_ref, self._f_ref, dt_full, sculling=True)
        self._theta_ref = self.theta.copy()
        # gravitation increment g(t_mid) Δt of every sample
        self._gdt = self._interp(self.grid_g, self.imu_t - 0.5 * dt_full) * dt_full[:, None]
        # reference strapdown window of the fast propagation (built on first use)
        self._win = (0, 0)
        self._win_theta = self.theta.copy()
        self.reference_rebuilds = 0
        self._cref_cache: tuple | None = None
        self._sensor_cache: dict = {}
        self._affine = {st: self._affine_sensor(st) for st in (Stage.GYRO, Stage.ACCEL)}
        # constant parts of the per-frame transition and process noise
        self._inv_tau = np.where(np.isfinite(self.tau), 1.0 / self.tau, 0.0)
        self._Phi = np.eye(self.N)
        self._diag_it = (np.arange(self.it.start, self.it.stop),) * 2
        # process noise Q_d(T) of an interval, on its (flat) entries: white gyro / accel
        # noise (q T on φ and δv, q T²/2 on δv–δr, q T³/3 on δr), θ random walk (q T) and
        # Gauss–Markov (σ² (1 − e^{−2T/τ})) — q1 T + q2 T² + q3 T³ + gm2 (1 − e^{−itau2 T})
        N, qa = self.N, self.q_accel
        entries = []
        for j in range(3):
            a, v, r_ = self.ia.start + j, self.iv.start + j, self.ir.start + j
            entries += [(a, a, self.q_gyro, 0.0, 0.0, 0.0, 0.0), (v, v, qa, 0.0, 0.0, 0.0, 0.0),
                        (v, r_, 0.0, qa / 2, 0.0, 0.0, 0.0), (r_, v, 0.0, qa / 2, 0.0, 0.0, 0.0),
                        (r_, r_, 0.0, 0.0, qa / 3, 0.0, 0.0)]
        for p in range(P):
            q = self.it.start + p
            entries.append((q, q, self.q_theta[p], 0.0, 0.0, self.gm_sigma[p] ** 2,
                            2.0 * self._inv_tau[p]))
        e = np.array(entries, dtype=float).reshape(-1, 7)
        self._qd_index = (e[:, 0] * N + e[:, 1]).astype(int)
        self._qd = tuple(e[:, c_] for c_ in range(2, 7))
        # nominal navigation state
        self.R_i_b: np.ndarray | None = None
        self.v = np.zeros(3)
        self.r = np.zeros(3)
        self.t: float | None = None
        self.omega = np.zeros(3)
        self._k = 0
        self.counters = FilterCounters()
        self.counters.extra.update({"position_updates": 0, "velocity_updates": 0})
        self.gate = chi2_gate(c.gate_probability, 2)
        self.last_stamp: float | None = None
        self.last_reference_t = -np.inf
        self._frame = (self.t0, 0.0)  # (POSIX, relative) stamp of the frame being processed
        self._gap_pending = False  # an IMU gap longer than gap_reacquire_s was propagated over
        self._rejected_in_row = 0  # frames in a row with fewer than min_stars accepted
        self.reference_history: dict[str, list] = {"t": [], "nu_x": [], "nu_y": [],
                                                    "nu_z": [], "nis": []}

    # ------------------------------------------------------------------ Earth
    def _interp(self, table: np.ndarray, t: np.ndarray | float) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t, dtype=float))
        x = (t - self.grid[0]) / self.config.grid_step_s
        i = np.clip(np.floor(x).astype(int), 0, len(self.grid) - 2)
        a = (x - i)[:, None]
        return (1.0 - a) * table[i] + a * table[i + 1]

    def site_position(self, t: float) -> np.ndarray:
        """Site position relative to the site at ``t0``, GCRS, m."""
        return self._interp(self.grid_r, t)[0]

    def site_velocity(self, t: float) -> np.ndarray:
        """Site inertial velocity, GCRS, m/s."""
        return self._interp(self.grid_v, t)[0]

    # ------------------------------------------------------------------ propagation
    @property
    def initialized(self) -> bool:
        """True once the attitude has been initialized from a star frame."""
        return self.R_i_b is not None

    def _segments(self, t_target: float):
        k = self._k
        m = int(np.searchsorted(self.imu_t, t_target, side="left"))
        if m >= len(self.imu_t):
            raise _NoImuError()
        ends = np.concatenate([self.imu_t[k:m], [t_target]])
        starts = np.concatenate([[self.t], self.imu_t[k:m]])
        return ends, ends - starts, self.imu_w[k:m + 1], self.imu_f[k:m + 1], m

    def _corrected(self, raw: np.ndarray, stage: Stage):
        b, E, Jb, JE = self.model.sensor_model(self.theta, stage)
        if np.any(E):
            A = np.linalg.inv(np.eye(3) + E)
            return (raw - b) @ A.T, A, Jb, JE
        return raw - b, None, Jb, JE

    def _affine_sensor(self, stage: Stage):
        """``(b, E, ∂b/∂θ, ∂E/∂θ, [∂b/∂θ, ∂E/∂θ], scaled)`` at θ_ref if affine in θ.

        The library's sensor effects (biases, scale factors, misalignments) are; then the
        per-frame sensor model is two small matrix products instead of a loop over the
        effects.  ``None`` (a registered non-affine effect): :meth:`StarModel.sensor_model`
        every time.
        """
        b0, E0, Jb, JE = self.model.sensor_model(self.theta, stage)
        sig = self.model.initial_sigma
        step = np.where(np.isfinite(sig) & (sig > 0), sig, 1e-3)
        b1, E1, Jb1, JE1 = self.model.sensor_model(self.theta + step, stage)
        affine = (np.array_equal(Jb, Jb1) and np.array_equal(JE, JE1)
                  and np.allclose(b1, b0 + Jb @ step, rtol=1e-9, atol=1e-300)
                  and np.allclose(E1, E0 + JE @ step, rtol=1e-9, atol=1e-300))
        if not affine:
            return None
        return b0, E0, Jb, JE, np.hstack([Jb, JE.reshape(3, -1)]), bool(JE.any())

    def _sensor(self, stage: Stage):
        """``(b, A, Γ)`` of the current θ (cached per θ) for a sensor stage.

        ``b`` the bias, ``A = (I+E)⁻¹`` (None when E = 0) and Γ (3 or 12, P) with
        ``∂(corrected x̂)/∂θ = −(I+E)⁻¹ (∂b/∂θ + ∂E/∂θ x̂) = [I, x̂ᵀ⊗I] Γ``: 3 rows when no
        estimated effect scales the sensor (``∂E/∂θ = 0``), else 12 — the bias part, then
        ``−(I+E)⁻¹ ∂E/∂θ`` with its (row, column) pair flattened, matching the per-sample
        rows ``[C Δt, (C ⊗ x̂) Δt]`` of :meth:`_sensor_rows`.
        """
        hit = self._sensor_cache.get(stage)
        theta = self.theta
        if hit is not None and hit[0] is theta and np.array_equal(hit[1], theta):
            return hit[2]
        aff = self._affine[stage]
        if aff is None:
            b, E, Jb, JE = self.model.sensor_model(theta, stage)
            JbE = np.hstack([Jb, JE.reshape(3, -1)])
            scaled = bool(JE.any())
        else:
            b0, E0, Jb, JE, JbE, scaled = aff
            d = theta - self._theta_ref
            b, E = b0 + Jb @ d, E0 + JE @ d
        P = self.P_size
        A = _inv3(np.eye(3) + E) if E.any() else None
        M = -JbE if A is None else -(A @ JbE)
        G = np.concatenate([M[:, :P], M[:, P:].reshape(9, P)]) if scaled else M[:, :P]
        out = (b, A, G)
        self._sensor_cache[stage] = (theta, theta.copy(), out)
        return out

    @staticmethod
    def _sensor_rows(C: np.ndarray, x: np.ndarray, w: np.ndarray, scaled: bool) -> np.ndarray:
        """Per-segment rows (n, 3, 3 or 12) that :meth:`_sensor`'s Γ turns into ∂(C x̂ Δt)/∂θ."""
        n = len(w)
        Z = np.empty((n, 3, 12 if scaled else 3))
        np.multiply(C, w[:, None, None], out=Z[:, :, :3])
        if scaled:
            np.multiply(Z[:, :, :3, None], x[:, None, None, :], out=Z[:, :, 3:].reshape(n, 3, 3, 3))
        return Z

    def _build_window(self, lo: int, hi: int) -> None:
        """Reference strapdown of samples ``lo:hi`` under the current θ (vectorized, once).

        In a reference frame (the body at the start of sample ``lo``): the attitudes
        ``C_k`` at the sample boundaries, and per sample the corrected rate and specific
        force, the rotation increment (coning) and the specific-force increment (sculling)
        rotated by the attitude at the sample start, ``C_k Δu_k``, next to the gravitation
        increment (one (n, 6) table: one product per frame).  The coning / sculling terms of
        the first sample use the sample before it, as a whole-bag integration would.
        """
        lo0 = max(lo - 1, 0)
        dt = self._dt_full[lo0:hi]
        out, gam = [], []
        for raw, stage in ((self.imu_w[lo0:hi], Stage.GYRO), (self.imu_f[lo0:hi], Stage.ACCEL)):
            b, A, G = self._sensor(stage)
            out.append(raw - b if A is None else (raw - b) @ A.T)
            gam.append(G)
        w, f = out
        # Γ of the window's θ: between rebuilds E changes by < 1e-5, so the sensitivities
        # (Jacobian and first-order correction) change by that relative amount — negligible
        self._win_G = tuple(gam)
        s = lo - lo0
        phi = attitude_increments(w, dt, coning=True)[s:]
        du = velocity_increments(w, f, dt, sculling=True)[s:]
        C = attitude_prefix(phi)  # (n+1, 3, 3), C[j]: start of sample lo + j
        self._win = (lo, hi)
        self._win_theta = self.theta.copy()
        self._win_w, self._win_f, self._win_phi, self._win_du = w[s:], f[s:], phi, du
        self._win_C = C
        self._win_DG = np.hstack([np.einsum("nij,nj->ni", C[:-1], du), self._gdt[lo:hi]])
        self._cref_cache = None

    def _cref(self, t: float) -> np.ndarray:
        """Reference-frame attitude ``C(t)`` at a time inside a sample of the window.

        The sample's rotation increment is split linearly in time, as the per-sample path
        splits a sample at a frame stamp.
        """
        cache = self._cref_cache
        if cache is not None and cache[0] == t:
            return cache[1]
        m = min(int(self.imu_t.searchsorted(t)), len(self.imu_t) - 1)
        a = (t - (self.imu_t[m] - self._dt_full[m])) / self._dt_full[m]
        j = m - self._win[0]
        C = self._win_C[j] @ so3_exp(a * self._win_phi[j])
        self._cref_cache = (t, C)
        return C

    def propagate(self, t_target: float) -> None:
        """Propagate the nominal state and the covariance to ``t_target`` (relative s).

        Everything per IMU sample is computed vectorized once per *reference window*
        (:meth:`_build_window`, ``reference_window_s`` = 120 s of samples, under the θ̂ of the
        time it is built, θ_w): the strapdown in a reference frame (attitudes ``C_k`` at the
        sample boundaries, specific-force increments ``C_k Δu_k`` with coning and sculling,
        gravitation ``g Δt``).  Per star frame, with ``Q = R̂(t_a) C(t_a)ᵀ`` mapping that
        frame onto the current nominal, the sums over the ~50 samples since the last frame are
        a handful of matrix products (no per-sample Python work):

        * nominal: ``R̂(t_b) = Exp(Φ_φθ δθ) Q C(t_b)``, ``v̂(t_b) = v̂(t_a) + Q Σ C Δu + Φ_vθ δθ +
          Σ g Δt``, ``r̂`` likewise with the trapezoid weights, ``δθ = θ̂ − θ_w``: first order
          in the change of the sensor parameters since the window was built.  A correction
          above ``fast_propagation_max_rad`` (1e-4 rad; second-order error < 5e-9 rad)
          rebuilds the window under the current θ̂ (on swaying_ideal the corrections stay
          below 3.5e-5 rad; the traditional filter's wandering θ̂ rebuilds now and then).
        * error-state transition Φ over the interval, from the same sums.  φ̇ has no φ term
          and δθ is constant between frames (up to the Gauss–Markov decay, ≥ 1 day), so
          summing the per-sample transitions is the exact discretisation of the continuous
          model over the interval; the covariance is propagated once per frame
          (``Φ P Φᵀ + Q_d``, Q_d of the white noises integrated over the interval) — the same
          covariance a per-sample recursion gives, at one N×N product per frame (the star
          and Z1 updates come only at frames, so nothing needs P in between).

        The per-sample path is kept (:meth:`_propagate_samples`,
        ``SwayingConfig.exact_propagation``) for reference.  Referenced to the same θ, one
        frame of the two agrees to 3e-13 rad and 2e-8 m/s; the per-sample path corrects the
        prior's increments to first order, which on swaying_ideal (misalignment 4e-4 from
        the prior) leaves it 1e-6 m/s a frame off, so whole replays differ by ≤ 0.04 σ
        (test_fast_propagation_matches_per_sample).
        """
        if t_target <= self.t:
            if t_target < self.t - 1e-9:
                raise ModelError("cannot propagate backwards in time")
            return
        if self.config.exact_propagation:
            self._propagate_samples(t_target)
            return
        k = self._k
        imu_t = self.imu_t
        m = int(imu_t.searchsorted(t_target))
        if m >= len(imu_t):
            raise _NoImuError()
        c = self.config
        lo, hi = self._win
        if k < lo or m >= hi:
            # a new window of the reference strapdown, from the current sample on
            width = max(int(round(c.reference_window_s / self.nominal_dt)), 2 * (m - k + 2))
            self._build_window(k, min(k + width, len(imu_t)))
        self._propagate_window(t_target, k, m)

    def _propagate_window(self, t_target: float, k: int, m: int) -> None:
        """:meth:`propagate` over samples ``k..m`` of the current reference window."""
        ta, tb = self.t, t_target
        lo = self._win[0]
        ends = self.imu_t[k:m + 1].copy()
        ends[-1] = tb
        n = len(ends)
        dts = np.empty(n)
        dts[0] = ends[0] - ta
        np.subtract(ends[1:], ends[:-1], out=dts[1:])
        frac = dts / self._dt_full[k:m + 1]
        T = tb - ta
        W = np.empty((2, n))  # weights: 1 (sums), trapezoid weight of δv in δr
        W[0] = 1.0
        np.subtract(tb, ends, out=W[1])
        W[1] += 0.5 * dts
        Ca, Cb = self._cref(ta), self._cref(tb)
        Q = self.R_i_b @ Ca.T
        j, mj = k - lo, m - lo  # window rows
        # specific-force and gravitation increments in the reference frame; the first
        # (partial) sample starts at t_a
        DG = self._win_DG[j:mj + 1] * frac[:, None]
        DG[0, :3] = (Ca @ self._win_du[j]) * frac[0]
        sums = W @ DG  # rows: Σ, Σ rem; columns: specific force, gravitation
        QD = Q @ sums[:, :3].T  # (3, 2)
        P = self.P_size
        ia, it, iv, ir = self.ia, self.it, self.iv, self.ir
        Phi = self._Phi
        if P:
            Gg, Ga = self._win_G
            C_start = self._win_C[j:mj + 1].copy()
            C_start[0] = Ca
            # a rate error δω over a sample rotates the attitude by R_start J_l(φ) δω Δt =
            # R_mid δω Δt to first order in the sample's rotation φ (R_end would leave
            # ½ φ × δω Δt a sample, systematic under a scale-factor / misalignment error)
            C_mid = self._win_C[j + 1:mj + 2] + C_start
            C_mid[-1] = Cb + C_start[-1]
            Zg = self._sensor_rows(C_mid, self._win_w[j:mj + 1], 0.5 * dts, len(Gg) > 3)
            Za = self._sensor_rows(C_start, self._win_f[j:mj + 1], dts, len(Ga) > 3)
            Kg, Ka = Zg.shape[2], Za.shape[2]
            # Σ_j [D_j]× (attitude sensitivity at the start of segment j), plain and
            # rem-weighted, = Σ_i [Σ_{j>i} w_j D_j]× Z_i: tail sums of D, one product with Z
            D = DG[:, :3]
            Y = np.empty((n, 7))
            Y[:, 0] = 1.0
            WD = W[:, :, None] * D  # (2, n, 3)
            tails = WD.sum(axis=1)[:, None, :] - np.cumsum(WD, axis=1)
            Y[:, 1:4], Y[:, 4:] = tails[0], tails[1]
            YZ = Y.T @ Zg.reshape(n, 3 * Kg)  # (7, 3 Kg)
            Tx = YZ[1:].reshape(2, 3, 3, Kg)
            Xc = np.stack([Tx[:, 1, 2] - Tx[:, 2, 1], Tx[:, 2, 0] - Tx[:, 0, 2],
                           Tx[:, 0, 1] - Tx[:, 1, 0]], axis=1)  # (2, 3, Kg)
            Za_sums = (W @ Za.reshape(n, 3 * Ka)).reshape(2, 3, Ka)
            F = np.empty((3, 3, P))  # ∂(attitude, velocity, position)/∂θ, reference frame
            F[0] = YZ[0].reshape(3, Kg) @ Gg
            F[1:] = Za_sums @ Ga - Xc @ Gg
            F = Q @ F  # inertial
            corr = F @ (self.theta - self._win_theta)  # first-order nominal corrections
            if corr[0] @ corr[0] > self.config.fast_propagation_max_rad ** 2:
                # θ moved too far from the window's reference for a first-order correction:
                # a new (short) window under the current θ, then corr = 0
                self.reference_rebuilds += 1
                width = max(int(round(1.0 / self.nominal_dt)) * 10, 2 * (m - k + 2))
                self._build_window(k, min(k + width, len(self.imu_t)))
                self._propagate_window(t_target, k, m)
                return
            Phi[ia, it] = F[0]
            Phi[iv.start:ir.stop, it] = F[1:].reshape(6, P)
            Phi[self._diag_it] = np.exp(-T * self._inv_tau)
            dvr = QD.T + corr[1:]  # specific-force δv and its δr share, with corrections
            self.R_i_b = so3_exp(corr[0]) @ Q @ Cb
        else:
            dvr = QD.T
            self.R_i_b = Q @ Cb
        Phi[iv.start:ir.stop, ia] = -skew(dvr).reshape(6, 3)
        Phi[ir, iv] = T * np.eye(3)
        self.r = self.r + self.v * T + dvr[1] + sums[1, 3:]
        self.v = self.v + dvr[0] + sums[0, 3:]
        self._propagate_covariance(Phi, T, dts, t_target, k, m)
        self.t = t_target
        self._k = m
        self._omega_stale = True  # the corrected rate of sample m, when next needed

    def _propagate_covariance(self, Phi: np.ndarray, T: float, dts: np.ndarray,
                              t_target: float, k: int, m: int) -> None:
        """``P ← Φ P Φᵀ + Q_d`` over an interval of length T (segments ``dts`` of samples k..m).

        ``Q_d``: the white gyro / accelerometer noises integrated over the interval
        (``q T`` on φ and δv, ``q T²/2`` and ``q T³/3`` on δv–δr and δr), and the
        Gauss–Markov / random-walk driving noise of θ.  A sample whose interval is longer
        than ``imu_gap_factor`` nominal intervals (missing samples before it) inflates the
        attitude and velocity covariance by its overlap with the interval; it is counted
        once, in the interval where it ends (a frame stamp usually falls inside it).
        """
        Pn = Phi @ self.P @ Phi.T
        q1, q2, q3, gm2, itau2 = self._qd
        Pn.ravel()[self._qd_index] += (q1 + (q2 + q3 * T) * T) * T + gm2 * -np.expm1(-T * itau2)
        sample_dt = self._dt_full[k:m + 1]
        thr = self.config.imu_gap_factor * self.nominal_dt
        if sample_dt.max() > thr:
            gaps = sample_dt > thr
            self.counters.imu_gaps += int(np.sum(gaps[:-1]))
            gap = float(np.sum(dts[gaps]))
            ia, iv = self.ia, self.iv
            Pn[ia, ia] += (self.config.gap_rate_sigma * gap) ** 2 * np.eye(3)
            Pn[iv, iv] += (self.config.gap_accel_sigma * gap) ** 2 * np.eye(3)
            if gap > self.config.gap_reacquire_s:
                self._gap_pending = True
            log.warning("IMU gap of %.3f s before t=%.3f s: %s", gap, t_target,
                        "re-acquiring from the stars" if self._gap_pending
                        else "uncertainty inflated")
        self.P = 0.5 * (Pn + Pn.T)

    @staticmethod
    def _sensor_G(A, Jb, JE, x_hat: np.ndarray) -> np.ndarray:
        """Per-sample ∂(corrected)/∂θ = −(I+E)⁻¹ (∂b/∂θ + ∂E/∂θ x̂), shape (n, 3, P)."""
        n, P = len(x_hat), Jb.shape[1]
        G = np.broadcast_to(-(Jb if A is None else A @ Jb), (n, 3, P)).copy()
        if np.any(JE):
            JEx = np.einsum("ijp,nj->nip", JE, x_hat)
            if A is not None:
                JEx = np.einsum("ik,nkp->nip", A, JEx)
            G -= JEx
        return G

    def _propagate_samples(self, t_target: float) -> None:
        """Per-sample propagation (the reference for :meth:`propagate`; same model)."""
        ends, dts, w_raw, f_raw, m = self._segments(t_target)
        w_hat, Ag, Jbg, JEg = self._corrected(w_raw, Stage.GYRO)
        f_hat, Aa, Jba, JEa = self._corrected(f_raw, Stage.ACCEL)
        idx = np.arange(self._k, m + 1)
        frac = (dts / self._dt_full[idx])[:, None]
        phi = self._phi_ref[idx] * frac + (w_hat - self._w_ref[idx]) * dts[:, None]
        du = self._du_ref[idx] * frac + (f_hat - self._f_ref[idx]) * dts[:, None]
        q = np.empty((len(phi) + 1, 4))
        q[0] = quat_from_matrix(self.R_i_b)
        q[1:] = quat_from_rotvec(phi)
        R_all = quat_to_matrix(quat_cumprod(q))  # (n+1): start, then interval ends
        R_start, R_end = R_all[:-1], R_all[1:]
        dv_i = np.einsum("nij,nj->ni", R_start, du)  # specific-force increments, inertial
        g = self._interp(self.grid_g, ends - 0.5 * dts)
        dv_tot = dv_i + g * dts[:, None]
        v_ends = self.v + np.cumsum(dv_tot, axis=0)
        v_prev = np.vstack([self.v[None, :], v_ends[:-1]])
        T = float(ends[-1] - self.t)
        self.r = self.r + np.sum(0.5 * (v_prev + v_ends) * dts[:, None], axis=0)
        self.v = v_ends[-1]
        # ---- error-state transition over the interval
        N, P = self.N, self.P_size
        iv, ia, it, ir = self.iv, self.ia, self.it, self.ir
        Phi = np.eye(N)
        S = skew(dv_i)  # (n, 3, 3)
        rem = (ends[-1] - ends) + 0.5 * dts  # weight of each δv increment in δr
        Phi[iv, ia] = -np.sum(S, axis=0)
        Phi[ir, ia] = -np.einsum("n,nij->ij", rem, S)
        Phi[ir, iv] = T * np.eye(3)
        if P:
            Gg = self._sensor_G(Ag, Jbg, JEg, w_hat)
            R_mid = 0.5 * (R_start + R_end)  # first order in the sample rotation (J_l)
            A = np.einsum("nij,njp,n->nip", R_mid, Gg, dts)  # φ increments per δθ
            C = np.cumsum(A, axis=0)
            C_prev = np.concatenate([np.zeros((1, 3, P)), C[:-1]], axis=0)
            Ga = self._sensor_G(Aa, Jba, JEa, f_hat)
            B = np.einsum("nij,njp,n->nip", R_start, Ga, dts)
            inc = -np.einsum("nij,njp->nip", S, C_prev) + B  # δv increments per δθ
            Phi[ia, it] = C[-1]
            Phi[iv, it] = np.sum(inc, axis=0)
            Phi[ir, it] = np.einsum("n,nip->ip", rem, inc)
            decay = np.where(np.isfinite(self.tau), np.exp(-T / self.tau), 1.0)
            Phi[it, it] = np.diag(decay)
        self._propagate_covariance(Phi, T, dts, t_target, self._k, m)
        self.R_i_b = R_end[-1]
        self.omega = w_hat[-1]
        self.t = t_target
        self._k = m

    def rate_at(self, t: float) -> np.ndarray:
        """Corrected body rate of the IMU sample covering relative time ``t``."""
        m = min(int(np.searchsorted(self.imu_t, t, side="left")), len(self.imu_t) - 1)
        b, A, _ = self._sensor(Stage.GYRO)
        w = self.imu_w[m] - b
        return w if A is None else A @ w

    # ------------------------------------------------------------------ initialization
    def initialize(self, uv, u_i, ctx: FrameContext, sigma, t_rel: float) -> bool:
        """Coarse alignment from one star frame (stamp ``t_rel``); False if it cannot."""
        model, theta, c = self.model, self.theta, self.config
        shift, _ = model.time_shift(theta, ctx)
        t_exp = t_rel + shift
        if t_exp <= self.imu_t[0] - self.nominal_dt or t_exp >= self.imu_t[-1]:
            self.counters.skipped_no_imu += 1
            return False
        camera = model.camera_at(theta, ctx)
        R_imu_st, _ = model.installation_at(theta, ctx)
        keep = np.ones(len(uv), dtype=bool)
        fit = None
        for _ in range(3):
            if keep.sum() < max(c.min_stars, 3):
                return False
            fit = fit_frame_attitude(camera, uv[keep], u_i[keep])
            err = np.linalg.norm(fit.residuals, axis=1)
            bad = err > max(c.init_outlier_px, 5 * float(np.median(err)))
            if not np.any(bad):
                break
            keep[np.flatnonzero(keep)[bad]] = False
        self.t = t_exp
        self._k = int(np.searchsorted(self.imu_t, t_exp, side="left"))
        self.R_i_b = fit.R_i_st @ R_imu_st.T
        self.omega = self.rate_at(t_exp)
        self.v = self.site_velocity(t_exp)
        self.r = self.site_position(t_exp)
        idx = np.flatnonzero(keep)
        pred = model.predict(theta, u_i[keep], _subset(ctx, idx), self._attitude_function())
        Hf = pred.H_attitude.reshape(-1, 3)
        Ht = pred.H_parameters.reshape(-1, model.size)
        info = Hf.T @ Hf
        M = np.linalg.solve(info, Hf.T @ Ht) if model.size else np.zeros((3, 0))
        s2 = float(np.mean(sigma[keep] ** 2))
        it, ia = self.it, self.ia
        Ptt = self.P[it, it]
        self.P[ia, ia] = M @ Ptt @ M.T + s2 * np.linalg.inv(info)
        self.P[ia, it] = -M @ Ptt
        self.P[it, ia] = self.P[ia, it].T
        self.P[self.iv, self.iv] = c.initial_velocity_sigma_mps**2 * np.eye(3)
        self.P[self.ir, self.ir] = c.sway_displacement_sigma_m**2 * np.eye(3)
        self.counters.init_frames += 1
        self._level_check(t_exp)
        log.info("attitude initialized at t=%.3f s from %d stars", t_exp, int(keep.sum()))
        return True

    def _level_check(self, t_exp: float) -> None:
        """Log the angle between the measured and the expected specific force (1 s mean)."""
        sel = (self.imu_t > t_exp - 1.0) & (self.imu_t <= t_exp + 1e-9)
        if not np.any(sel):
            return
        f_b = self.model.corrected_rates(self.theta, self.imu_f[sel], Stage.ACCEL).mean(axis=0)
        f_i = self.R_i_b @ f_b
        a_site = earth.site_acceleration_gcrs(self.site, self.t0 + t_exp, self.config.dut1)
        f_exp = a_site - self._interp(self.grid_g, t_exp)[0]
        ang = np.degrees(np.arccos(np.clip(f_i @ f_exp / np.linalg.norm(f_i)
                                           / np.linalg.norm(f_exp), -1, 1)))
        self.level_check_deg = float(ang)
        (log.warning if ang > 10.0 else log.info)(
            "coarse alignment: star attitude vs accelerometer level differ by %.3f deg "
            "(sway accelerations included)", ang)

    def _attitude_function(self, phi: np.ndarray | None = None):
        R_now = self.R_i_b if phi is None else so3_exp(phi) @ self.R_i_b
        t_now, w = self.t, self.omega

        frame_posix, frame_rel = self._frame

        def attitude(t_posix: float):
            # relative time from the frame's integer-ns stamp (no 1.8e9 s cancellation)
            dt = (t_posix - frame_posix) + (frame_rel - t_now)
            R = R_now if abs(dt) < 1e-12 else R_now @ so3_exp(w * dt)
            return R, w

        return attitude

    # ------------------------------------------------------------------ updates
    def _apply(self, dx: np.ndarray) -> None:
        """Inject the error estimate into the nominal state and reset."""
        dphi = dx[self.ia]
        self.R_i_b = so3_exp(dphi) @ self.R_i_b
        self.v = self.v + dx[self.iv]
        self.r = self.r + dx[self.ir]
        self.theta = self.theta + dx[self.it]
        Gr = np.eye(3) + 0.5 * skew(dphi)
        ia = self.ia
        self.P[ia, :] = Gr @ self.P[ia, :]
        self.P[:, ia] = self.P[:, ia] @ Gr.T
        self._omega_stale = True  # θ changed: the corrected rate, when next needed

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

    def reference_measurement(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Z1: innovation, H (3, N) and R (3, 3) of the inertial reference."""
        c = self.config
        H = np.zeros((3, self.N))
        if c.velocity_reference == "position":
            nu = self.site_position(self.t) - self.r
            H[:, self.ir] = np.eye(3)
            R = c.sway_displacement_sigma_m**2 * np.eye(3)
        elif c.velocity_reference == "velocity":
            nu = self.site_velocity(self.t) - self.v
            H[:, self.iv] = np.eye(3)
            R = c.sway_velocity_sigma_mps**2 * np.eye(3)
        else:
            raise ModelError(f"unknown velocity_reference {c.velocity_reference!r}")
        return nu, H, R

    def reference_update(self) -> None:
        """Apply Z1 (at most every ``position_interval_s``)."""
        if self.t - self.last_reference_t < self.config.position_interval_s - 1e-6:
            return
        self.last_reference_t = self.t
        nu, H, R = self.reference_measurement()
        HP = H @ self.P
        S = HP @ H.T + R
        X = np.linalg.solve(S, np.column_stack([HP, nu]))
        K = X[:, :-1].T
        nis = float(nu @ X[:, -1])
        self.P = _joseph(self.P, K, H, HP, R)
        self._apply(K @ nu)
        key = "position_updates" if self.config.velocity_reference == "position" \
            else "velocity_updates"
        self.counters.extra[key] = self.counters.extra.get(key, 0) + 1
        h = self.reference_history
        h["t"].append(self.t0 + self.t)  # POSIX s, as the residual table
        for j, ax in enumerate("xyz"):
            h[f"nu_{ax}"].append(float(nu[j]))
        h["nis"].append(nis)

    def _jacobian(self, pred) -> np.ndarray:
        """H (n, 2, N) of a prediction (attitude and θ columns; navigation columns zero)."""
        H = np.zeros((len(pred.uv), 2, self.N))
        H[:, :, self.ia] = pred.H_attitude
        H[:, :, self.it] = pred.H_parameters
        return H

    def star_update(self, uv, u_i, ctx: FrameContext, sigma) -> FrameUpdate | None:
        """Z2: every identified star of the frame (per-star χ² gate, iterated EKF)."""
        model, c = self.model, self.config
        N, ia, it = self.N, self.ia, self.it
        n = len(uv)
        R_meas = sigma**2
        theta0 = self.theta
        pred0 = model.predict(theta0, u_i, ctx, self._attitude_function())
        H0 = self._jacobian(pred0)
        nu0 = uv - pred0.uv
        H2 = H0.reshape(-1, N)
        HP0 = H2 @ self.P
        S_blocks = np.einsum("nij,nkj->nik", HP0.reshape(n, 2, N), H0)
        S_blocks[:, 0, 0] += R_meas
        S_blocks[:, 1, 1] += R_meas
        nis_stars = block_nis(nu0, S_blocks)
        accepted = nis_stars <= self.gate
        n_acc = int(accepted.sum())
        self.counters.stars_gated += n - n_acc
        result = FrameUpdate(self._frame[0], self.t, accepted, uv, pred0.uv, S_blocks, nis_stars,
                             float("nan"), 0, pred0.directions_st, self.omega.copy(), 0)
        if n_acc < c.min_stars:
            self.counters.skipped_few_stars += 1
            self._rejected_in_row += 1
            if self._rejected_in_row >= c.reinit_after:
                # lost lock: the attitude is off by more than the gate allows
                log.warning("t=%.3f s: %d frames in a row rejected, re-acquiring",
                            self.t, self._rejected_in_row)
                self.reacquire(uv, u_i, ctx, sigma, self._frame[1])
            return result
        self._rejected_in_row = 0
        if n_acc < n:
            idx = np.flatnonzero(accepted)
            rows = np.repeat(2 * idx, 2) + np.tile([0, 1], n_acc)
            H2, HP0 = H2[rows], HP0[rows]
        else:
            idx = None
        r_diag = np.repeat(R_meas if idx is None else R_meas[idx], 2)
        nu = nu0.reshape(-1) if idx is None else nu0[idx].reshape(-1)
        # first iteration: the innovation covariance at the prior linearization gives the gain,
        # the frame NIS and, on a linear frame, the update (one solve for all three)
        S0 = HP0 @ H2.T
        S0.ravel()[::len(S0) + 1] += r_diag
        X = np.linalg.solve(S0, np.column_stack([HP0, nu]))
        K = X[:, :-1].T
        nis = float(nu @ X[:, -1])
        dx = K @ nu
        H, HP = H2, HP0
        it_count = 1
        if np.linalg.norm(dx[ia]) >= c.relinearize_rad and c.max_iterations > 1:
            sel = np.arange(n) if idx is None else idx
            ctx_acc = _subset(ctx, sel)
            z = uv[sel].reshape(-1)
            for it_count in range(2, c.max_iterations + 1):  # noqa: B007
                pred = model.predict(theta0 + dx[it], u_i[sel], ctx_acc,
                                     self._attitude_function(dx[ia]))
                H = self._jacobian(pred).reshape(-1, N)
                h = pred.uv.reshape(-1)
                HP = H @ self.P
                S = HP @ H.T
                S.ravel()[::len(S) + 1] += r_diag
                K = np.linalg.solve(S, HP).T
                dx_new = K @ (z - h + H @ dx)
                step = dx_new - dx
                dx = dx_new
                if np.linalg.norm(step[ia]) < c.relinearize_rad:
                    break
        self.P = _joseph(self.P, K, H, HP, r_diag)
        self._apply(dx)
        self.counters.updates += 1
        result.nis = nis
        result.dof = int(len(nu))
        result.iterations = it_count
        return result

    def process_frame(self, uv, u_i, ctx: FrameContext, sigma,
                      t_rel: float | None = None) -> FrameUpdate | None:
        """Handle one cleaned star frame: initialize, or propagate + Z1 + Z2; count skips.

        ``t_rel``: the frame stamp relative to ``t0`` (from integer ns; default
        ``ctx.stamp − t0``).
        """
        self.counters.frames += 1
        if t_rel is None:
            t_rel = ctx.stamp - self.t0
        self._frame = (ctx.stamp, float(t_rel))
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
            self.initialize(uv, u_i, ctx, sigma, t_rel)
            return None
        shift, _ = self.model.time_shift(self.theta, ctx)
        try:
            self.propagate(t_rel + shift)
        except _NoImuError:
            self.counters.skipped_no_imu += 1
            return None
        if self._gap_pending:
            # the rate over the gap is unknown (a sway period is ~10 s): attitude, velocity
            # and position from this frame and the site, as at the start; θ is kept
            self._gap_pending = False
            if self.reacquire(uv, u_i, ctx, sigma, t_rel):
                self.counters.extra["reacquired_after_gap"] = \
                    self.counters.extra.get("reacquired_after_gap", 0) + 1
                return None
        self.reference_update()
        return self.star_update(uv, u_i, ctx, sigma)

    def reacquire(self, uv, u_i, ctx: FrameContext, sigma, t_rel: float) -> bool:
        """Re-initialize the navigation state from a star frame and the site; keep θ.

        After an IMU gap or a lost lock the nominal attitude, velocity and position carry
        errors the covariance does not describe; updating them would pull θ.  Their rows and
        columns of P are cleared and :meth:`initialize` sets them as at the start (attitude
        from the stars with its θ correlation, velocity and position from the site).  False
        (state unchanged) if the frame cannot align.
        """
        saved = (self.P.copy(), self.R_i_b, self.v.copy(), self.r.copy(), self.t, self._k)
        nav = np.concatenate([np.arange(sl.start, sl.stop) for sl in (self.ia, self.iv, self.ir)])
        self.P[nav, :] = 0.0
        self.P[:, nav] = 0.0
        if not self.initialize(uv, u_i, ctx, sigma, t_rel):
            self.P, self.R_i_b, self.v, self.r, self.t, self._k = saved
            return False
        self.counters.init_frames -= 1
        self.counters.reinitializations += 1
        self._rejected_in_row = 0
        self.last_reference_t = self.t  # the next Z1 a full interval later
        return True

    def sigma(self) -> np.ndarray:
        """1-sigma of the error state."""
        return np.sqrt(np.clip(np.diag(self.P), 0.0, None))


def _inv3(M: np.ndarray) -> np.ndarray:
    """Inverse of a 3×3 matrix (adjugate; the sensor matrices I + E are near the identity)."""
    (a, b, c), (d, e, f), (g, h, i) = M.tolist()
    A, B, C = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * A + b * B + c * C
    return np.array([[A, c * h - b * i, b * f - c * e],
                     [B, a * i - c * g, c * d - a * f],
                     [C, b * g - a * h, a * e - b * d]]) / det


def _joseph(P: np.ndarray, K: np.ndarray, H: np.ndarray, HP: np.ndarray,
            R: np.ndarray) -> np.ndarray:
    """Joseph-form update ``(I − KH) P (I − KH)ᵀ + K R Kᵀ`` with ``HP = H P`` given.

    ``R`` is a full matrix or the diagonal of one.  Same algebra as
    :func:`~stellar_cal_ros.core.kalman.joseph_update` without the N×N identity and the dense
    diagonal R.
    """
    AP = P - K @ HP
    KR = K * R if R.ndim == 1 else K @ R
    out = AP - (AP @ H.T) @ K.T + KR @ K.T
    return 0.5 * (out + out.T)


def _residual_table(frames: list) -> dict[str, np.ndarray]:
    """The per-star residual table (PSCE columns) of all updated frames at once.

    ``frames``: (FrameUpdate, frame index, catalogue ids, magnitudes, head temperature).
    """
    if not frames:
        return {k: np.zeros(0) for k in RESIDUAL_COLUMNS}
    upds = [f[0] for f in frames]
    n = np.array([len(u.uv) for u in upds])
    per_frame = lambda values: np.repeat(np.asarray(values), n)  # noqa: E731
    uv = np.concatenate([u.uv for u in upds])
    uv_pred = np.concatenate([u.uv_pred for u in upds])
    S = np.concatenate([u.S for u in upds])
    d_st = np.concatenate([u.directions_st for u in upds])
    omega = np.repeat(np.array([u.omega_b for u in upds]), n, axis=0)
    nu = uv - uv_pred
    cols = {
        "t": per_frame([u.stamp for u in upds]), "frame": per_frame([f[1] for f in frames]),
        "catalog_id": np.concatenate([f[2] for f in frames]),
        "u": uv[:, 0], "v": uv[:, 1], "u_pred": uv_pred[:, 0], "v_pred": uv_pred[:, 1],
        "du": nu[:, 0], "dv": nu[:, 1],
        "s_uu": S[:, 0, 0], "s_uv": S[:, 0, 1], "s_vv": S[:, 1, 1],
        "nis": np.concatenate([u.nis_stars for u in upds]),
        "magnitude": np.concatenate([f[3] for f in frames]),
        "gated": ~np.concatenate([u.accepted for u in upds]),
        "x_st": d_st[:, 0], "y_st": d_st[:, 1], "z_st": d_st[:, 2],
        "omega_x": omega[:, 0], "omega_y": omega[:, 1], "omega_z": omega[:, 2],
        "head_temperature": per_frame([f[4] for f in frames]),
    }
    total = int(n.sum())
    return {k: np.asarray(cols[k]) if k in cols else np.full(total, np.nan)
            for k in RESIDUAL_COLUMNS}


def _subset(ctx: FrameContext, idx: np.ndarray) -> FrameContext:
    return dataclasses.replace(
        ctx,
        catalog_id=np.asarray(ctx.catalog_id)[idx] if len(ctx.catalog_id) else ctx.catalog_id,
        magnitude=np.asarray(ctx.magnitude)[idx] if len(ctx.magnitude) else ctx.magnitude,
        extra={},
    )


def _positive(values, index=None) -> bool:
    if values is None:
        return False
    if isinstance(values, dict):  # camera_calibration_parsers matrix layout
        values = values.get("data")
    try:
        a = np.asarray(values, dtype=float).ravel()
    except (TypeError, ValueError):
        return False
    if index is not None:
        a = a[[i for i in index if i < a.size]]
    return bool(np.any(np.isfinite(a) & (a > 0)))


def prior_uncertain_effects(prior: Calibration) -> list[str]:
    """Effects beyond :data:`BASELINE_EFFECTS` that the prior's ``sigma`` block calls uncertain.

    The default model of ``stellar-cal replay --method swaying_base`` (see the module
    docstring): an effect is estimated when the prior gives a positive sigma for one of its
    quantities; a quantity whose sigma is zero or absent is trusted and stays fixed at the
    prior value.  Mapping (contract §3 keys → effect ids)::

        camera.camera_matrix fx, fy          → focal_length
        camera.camera_matrix cx, cy          → principal_point
        camera.distortion_coefficients k1 k2 → radial_k1k2;  p1 p2 → tangential;  k3 → radial_k3
        gyro.error_matrix diagonal           → gyro_scale_factor;  off-diagonal → gyro_misalignment
        accelerometer.error_matrix diagonal  → accel_scale_factor
        time_offset                          → time_offset
        effects.<id> (any positive entry)    → <id> (a registered effect)

    The accelerometer's off-diagonal entries have no library effect; a positive sigma there is
    logged and ignored.
    """
    sig = prior.sigma or {}
    out: set[str] = set()
    cam = sig.get("camera", {}) or {}
    K = cam.get("camera_matrix")
    if _positive(K, (0, 4)):
        out.add("focal_length")
    if _positive(K, (2, 5)):
        out.add("principal_point")
    dist = cam.get("distortion_coefficients")
    if _positive(dist, (0, 1)):
        out.add("radial_k1k2")
    if _positive(dist, (2, 3)):
        out.add("tangential")
    if _positive(dist, (4,)):
        out.add("radial_k3")
    gyro = sig.get("gyro", {}) or {}
    if _positive(gyro.get("error_matrix"), (0, 4, 8)):
        out.add("gyro_scale_factor")
    if _positive(gyro.get("error_matrix"), (1, 2, 3, 5, 6, 7)):
        out.add("gyro_misalignment")
    acc = sig.get("accelerometer", {}) or {}
    if _positive(acc.get("error_matrix"), (0, 4, 8)):
        out.add("accel_scale_factor")
    if _positive(acc.get("error_matrix"), (1, 2, 3, 5, 6, 7)):
        log.info("prior: accelerometer misalignment sigma given, but no library effect "
                 "models it; kept at the prior value")
    if _positive(sig.get("time_offset")):
        out.add("time_offset")
    for eid, block in (sig.get("effects", {}) or {}).items():
        vals = list(block.values()) if isinstance(block, dict) else block
        if eid in registry.EFFECTS and any(_positive(v) for v in np.atleast_1d(
                np.asarray(vals, dtype=object)).ravel()):
            out.add(eid)
    out -= set(BASELINE_EFFECTS)
    order = {k: n for n, k in enumerate(registry.EFFECTS)}
    return sorted(out, key=lambda e: order.get(e, len(order)))


def resolve_effects(prior: Calibration, requested: list[str] | None,
                    automatic: bool = True) -> list[str]:
    """Effects to add to the baseline: the prior's uncertain ones, then ``requested``.

    ``requested`` items ``-id`` remove an effect (``--effects -time_offset``); the baseline
    effects cannot be removed.
    """
    out = prior_uncertain_effects(prior) if automatic else []
    for item in requested or []:
        if item.startswith("-"):
            eid = item[1:]
            if eid in BASELINE_EFFECTS:
                raise ModelError(f"{eid} is in the swaying_base baseline and cannot be removed")
            out = [e for e in out if e != eid]
        elif item not in out and item not in BASELINE_EFFECTS:
            out.append(item)
    return out


def derived_quantities(model: StarModel, theta: np.ndarray, P_theta: np.ndarray) -> dict:
    """The observable combinations: equivalent principal point and installation about z.

    A principal-point shift and an installation tilt about the tracker x/y axes move the
    whole star field alike (they separate only through the perspective term); what the data
    fix is their combination, the image position of the IMU-fixed nominal boresight
    (:func:`~stellar_cal_ros.methods.replay.equivalent_principal_point`).  The rotation about
    the boresight (tracker z) has no such partner.
    """
    out = dict(equivalent_principal_point(model, theta, P_theta))
    if "installation" in model.slices:
        k = model.slices["installation"].start + 2
        out["installation_boresight_arcsec"] = float(theta[k] * ARCSEC)
        out["installation_boresight_sigma_arcsec"] = float(
            np.sqrt(max(P_theta[k, k], 0.0)) * ARCSEC)
    return out


def build_model(prior: Calibration, effects: list[str] | None,
                baseline=BASELINE_EFFECTS) -> StarModel:
    """StarModel of the baseline plus ``effects``."""
    return StarModel(registry.create_many(list(baseline) + list(effects or [])), prior)


def run_filter(filter_cls, bag: str | Path | BagData, prior: Calibration,
               effects: list[str] | None = None, config=None,
               progress: bool = False) -> ReplayResult:
    """Replay a bag through ``filter_cls`` (a :class:`SwayingFilter` or subclass)."""
    data = bag if isinstance(bag, BagData) else read_bag_data(bag)
    if data.site is None:
        raise ModelError(f"the {filter_cls.method} method needs the site ({TOPIC_FIX}) "
                         "for gravitation and the inertial reference")
    model = build_model(prior, effects)
    flt = filter_cls(model, data.imu_t, data.imu_w, data.imu_f, data.t0, data.site, config)
    c = flt.config
    width, height = prior.camera.width, prior.camera.height
    frames_out: list = []  # (update, frame index, catalogue ids, magnitudes, head temperature)
    hist: dict[str, list] = {"t": [], "nis": [], "dof": [], "stars": [], "gated": [],
                             "iterations": []}
    theta_hist, var_hist = [], []
    prog = _Progress(len(data.frames), progress)
    t_start = time.perf_counter()
    # per-frame context scalars, interpolated for all frames at once
    stamps = np.array([f.stamp_ns for f in data.frames], dtype=np.int64)
    head = _interp_many(data.head_temperature, stamps)
    air = _interp_many(data.air_temperature, stamps)
    pressure = _interp_many(data.pressure, stamps)
    for i, frame in enumerate(data.frames):
        prog(i)
        ok = clean_frame(frame, width, height)
        n_ok = int(ok.sum())
        flt.counters.stars_invalid += len(ok) - n_ok
        if not n_ok:
            flt.counters.frames += 1
            flt.counters.skipped_few_stars += 1
            continue
        ids = frame.catalog_id[ok].astype(np.int64)
        mag = frame.magnitude[ok]
        ctx = FrameContext(stamp=frame.stamp_ns * 1e-9, catalog_id=ids, magnitude=mag,
                           site=data.site, head_temperature_c=float(head[i]),
                           air_temperature_c=float(air[i]), pressure_pa=float(pressure[i]))
        u_i = radec_to_unit(frame.right_ascension[ok], frame.declination[ok])
        sig = frame.sigma[ok]
        sig = np.where(sig > 0, sig, c.centroid_sigma_px)
        t_rel = (frame.stamp_ns - data.t0_ns) * 1e-9
        upd = flt.process_frame(frame.uv[ok], u_i, ctx, sig, t_rel)
        if upd is None:
            continue
        frames_out.append((upd, i, ids, mag, ctx.head_temperature_c))
        if np.isfinite(upd.nis):
            hist["t"].append(upd.stamp)
            hist["nis"].append(upd.nis)
            hist["dof"].append(upd.dof)
            n_acc = int(upd.accepted.sum())
            hist["stars"].append(n_acc)
            hist["gated"].append(len(upd.accepted) - n_acc)
            hist["iterations"].append(upd.iterations)
            theta_hist.append(flt.theta.copy())
            var_hist.append(np.diag(flt.P).copy())
    filter_seconds = time.perf_counter() - t_start
    if not flt.initialized:
        raise ModelError("no star frame could initialize the attitude "
                         f"(counters: {vars(flt.counters)})")
    sig = flt.sigma()
    cal = result_calibration(prior, model, flt.theta, sig[flt.it], flt.method,
                             data.t0 + flt.t)
    history = {k: np.asarray(v) for k, v in hist.items()}
    names = model.parameter_names()
    th = np.asarray(theta_hist).reshape(-1, model.size)
    sd = np.sqrt(np.clip(np.asarray(var_hist).reshape(-1, flt.N), 0.0, None))
    sg = sd[:, flt.it]
    for j, name in enumerate(names):
        history[name] = th[:, j]
        history["sigma." + name] = sg[:, j]
    nav = np.hstack([sd[:, flt.ia], sd[:, flt.iv], sd[:, flt.ir]])
    for j, key in enumerate(("attitude", "velocity", "position")):
        for k, ax in enumerate("xyz"):
            history[f"sigma.{key}.{ax}"] = nav[:, 3 * j + k]
    counters = {k: v for k, v in vars(flt.counters).items() if k != "extra"}
    counters.update(flt.counters.extra)
    _log_counters(counters)
    combos = derived_quantities(model, flt.theta, flt.P[flt.it, flt.it])
    cal.extra["derived"] = combos
    derived = {"reference": {k: np.asarray(v) for k, v in flt.reference_history.items()},
               "level_check_deg": getattr(flt, "level_check_deg", float("nan")), **combos}
    return ReplayResult(
        calibration=cal,
        residuals=_residual_table(frames_out),
        history=history,
        counters=counters,
        read_seconds=data.read_seconds,
        filter_seconds=filter_seconds,
        duration=float(data.imu_t[-1] - data.imu_t[0]),
        filter=flt,
        derived=derived,
    )


def replay_swaying(bag: str | Path | BagData, prior: Calibration,
                   effects: list[str] | None = None, config: SwayingConfig | None = None,
                   progress: bool = False) -> ReplayResult:
    """Run the inertial-frame swaying-base filter over a bag."""
    return run_filter(SwayingFilter, bag, prior, effects, config, progress)


def bound_filter_class(filter_cls=SwayingFilter):
    """``filter_cls`` whose nominal state is never corrected (see :func:`crlb_swaying`).

    What remains is the covariance recursion with every Jacobian evaluated on the nominal
    trajectory it starts on.
    """

    class BoundFilter(filter_cls):
        method = f"{filter_cls.method}_crlb"

        def _apply(self, dx: np.ndarray) -> None:
            """No injection: θ stays at the truth, the attitude on the truth-driven strapdown."""

    BoundFilter.__name__ = BoundFilter.__qualname__ = f"{filter_cls.__name__}Bound"
    return BoundFilter


def crlb_swaying(bag: str | Path | BagData, prior: Calibration, truth: Calibration,
                 effects: list[str] | None = None, config: SwayingConfig | None = None,
                 filter_cls=SwayingFilter) -> ReplayResult:
    """Posterior Cramér–Rao bound of the filter's error-state model over a bag.

    For a model with additive Gaussian noise that is linear in the error state, the
    posterior CRLB recursion of Tichavský, Muravchik & Nehorai (IEEE TSP 1998) is the
    Kalman covariance recursion with every Jacobian evaluated on the *true* trajectory and
    parameters (the Fisher information of the data plus the prior's ``P0⁻¹``).  Here: the
    model's θ is the truth (``truth`` with the prior's σ block, so the prior information is
    the filter's), the attitude is the coarse star alignment under the true camera and
    installation followed by the strapdown of the truth-corrected IMU (error ≈ 1" —
    immaterial for the Jacobians), nothing is injected (``_apply`` is a no-op), every star is
    used (no gate) and there is no relinearization.  The returned ``filter.P`` (and
    ``calibration.sigma``) is the bound; ``derived`` holds the bound of the observable
    combinations.  ``effects``: the model's effects beyond the baseline, as for
    :func:`replay_swaying`.

    The bound is the bound *of this model*: it treats the sway displacement as white noise of
    σ_d (``sway_displacement_sigma_m``) at the Z1 interval, as the filter does; an estimator
    that modelled the sway's waveform could extract more from Z1.
    """
    ref = copy.deepcopy(truth)
    ref.sigma = copy.deepcopy(prior.sigma)
    cfg = dataclasses.replace(config or SwayingConfig(), gate_probability=1.0, max_iterations=1)
    return run_filter(bound_filter_class(filter_cls), bag, ref, effects, cfg)


def print_summary(result: ReplayResult, output=None, residuals=None) -> None:
    """Human summary of a swaying-base replay (accuracy-relevant numbers first)."""
    res, hist, cal = result.residuals, result.history, result.calibration
    ok = ~res["gated"].astype(bool) if len(res["gated"]) else np.zeros(0, bool)
    half = len(ok) // 2
    du, dv = res["du"][half:][ok[half:]], res["dv"][half:][ok[half:]]
    rms = (float(np.sqrt(np.mean(du**2))), float(np.sqrt(np.mean(dv**2)))) if du.size \
        else (float("nan"),) * 2
    nis = float(np.sum(hist["nis"]) / max(np.sum(hist["dof"]), 1)) if len(hist["nis"]) \
        else float("nan")
    print(f"replayed {result.duration:.0f} s in {result.read_seconds:.2f} s reading + "
          f"{result.filter_seconds:.2f} s filtering = {result.speed:.0f}x real time")
    print(f"star innovation RMS (second half, accepted): u={rms[0]:.4f} v={rms[1]:.4f} px; "
          f"NIS/dof {nis:.3f}")
    ref = result.derived.get("reference", {})
    if len(ref.get("nis", [])):
        print(f"inertial reference (Z1): {len(ref['nis'])} updates, NIS/dof "
              f"{np.mean(ref['nis']) / 3:.3f}")
    print("counts: " + ", ".join(f"{k}={v}" for k, v in result.counters.items() if v))
    arcsec = ARCSEC
    flt = result.filter
    extra = [e.id for e in flt.model.effects if e.id not in BASELINE_EFFECTS]
    print("model: " + ", ".join(BASELINE_EFFECTS) + (" + " + ", ".join(extra) if extra else ""))
    sl = flt.model.slices["installation"]
    print("installation delta (tracker axes): "
          + "  ".join(f"{v:+.3f}\"+-{s:.3f}" for v, s in zip(
              flt.theta[sl] * arcsec, flt.sigma()[flt.it][sl] * arcsec, strict=True)))
    d = result.derived
    if "equivalent_principal_point_px" in d:
        print("observable combinations: equivalent principal point ({:.3f}, {:.3f}) +- "
              "({:.3f}, {:.3f}) px; installation about the boresight {:+.3f}\" +- {:.3f}\""
              .format(*d["equivalent_principal_point_px"],
                      *d["equivalent_principal_point_sigma_px"],
                      d["installation_boresight_arcsec"],
                      d["installation_boresight_sigma_arcsec"]))
    print(f"installation quaternion_xyzw: {np.round(cal.installation.as_quat(), 9).tolist()}")
    print(f"gyro bias: {np.round(np.rad2deg(cal.gyro_bias) * 3600, 5).tolist()} deg/h; "
          f"accelerometer bias: {np.round(np.asarray(cal.accel_bias) / G0 * 1e6, 2).tolist()} ug")
    if output:
        print(f"wrote {output}" + (f" and {residuals}" if residuals else ""))


def cli_replay(args, prior: Calibration, effects: list[str], filter_cls=None,
               config=None) -> int:
    """``stellar-cal replay --method swaying_base``: run, write YAML/residuals/history.

    The model is the baseline, plus every effect the prior's sigma block calls uncertain
    (:func:`prior_uncertain_effects`), plus ``effects`` (``-id`` removes one).
    """
    from stellar_cal_ros.io.calibration import save_calibration
    from stellar_cal_ros.io.residuals import write_residuals

    config = config or SwayingConfig()
    effects = resolve_effects(prior, effects)
    if getattr(args, "centroid_sigma", None) is not None:
        config.centroid_sigma_px = args.centroid_sigma
    if getattr(args, "gyro_arw", None) is not None:
        config.gyro_arw_deg_sqrth = args.gyro_arw
    result = run_filter(filter_cls or SwayingFilter, args.bag, prior, effects, config,
                        progress=not getattr(args, "quiet", False))
    save_calibration(result.calibration, args.output)
    if args.residuals:
        write_residuals(args.residuals, result.residuals)
    history_path = getattr(args, "history", None) or Path(args.output).with_suffix(
        ".history.csv")
    write_residuals(history_path, result.history)
    print_summary(result, args.output, args.residuals)
    return 0
