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

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stellar_cal_ros.core import earth
from stellar_cal_ros.core.attitude import fit_frame_attitude
from stellar_cal_ros.core.catalog import radec_to_unit
from stellar_cal_ros.core.kalman import block_nis, chi2_gate, joseph_update
from stellar_cal_ros.core.rotation import (
    quat_from_matrix,
    quat_from_rotvec,
    quat_to_matrix,
    skew,
    so3_exp,
)
from stellar_cal_ros.core.strapdown import attitude_increments, quat_cumprod, velocity_increments
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
    _log_counters,
    _Progress,
    clean_frame,
    equivalent_principal_point,
    frame_context,
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
    init_outlier_px: float = 5.0
    grid_step_s: float = 0.25  #: Earth-orientation grid (gravitation, site), linear interp.


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

    def propagate(self, t_target: float) -> None:
        """Propagate the nominal state and the covariance to ``t_target`` (relative s)."""
        if t_target <= self.t:
            if t_target < self.t - 1e-9:
                raise ModelError("cannot propagate backwards in time")
            return
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
            A = np.einsum("nij,njp,n->nip", R_end, Gg, dts)  # φ increments per δθ
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
        Pn = Phi @ self.P @ Phi.T
        Pn[ia, ia] += self.q_gyro * T * np.eye(3)
        qa = self.q_accel
        Pn[iv, iv] += qa * T * np.eye(3)
        Pn[ir, ir] += qa * T**3 / 3.0 * np.eye(3)
        Pn[iv, ir] += qa * T**2 / 2.0 * np.eye(3)
        Pn[ir, iv] += qa * T**2 / 2.0 * np.eye(3)
        if P:
            gm = np.where(np.isfinite(self.tau),
                          self.gm_sigma**2 * (1.0 - np.exp(-2.0 * T / self.tau)), 0.0)
            Pn[it, it] += np.diag(gm + self.q_theta * T)
        gaps = dts[1:-1] > self.config.imu_gap_factor * self.nominal_dt if len(dts) > 2 else []
        if np.any(gaps):
            self.counters.imu_gaps += int(np.sum(gaps))
            gap = float(np.sum(dts[1:-1][gaps]))
            Pn[ia, ia] += (self.config.gap_rate_sigma * gap) ** 2 * np.eye(3)
            Pn[iv, iv] += (self.config.gap_accel_sigma * gap) ** 2 * np.eye(3)
            log.warning("IMU gap of %.3f s before t=%.3f s: uncertainty inflated", gap, t_target)
        self.P = 0.5 * (Pn + Pn.T)
        self.R_i_b = R_end[-1]
        self.omega = w_hat[-1]
        self.t = t_target
        self._k = m

    def rate_at(self, t: float) -> np.ndarray:
        """Corrected body rate of the IMU sample covering relative time ``t``."""
        m = min(int(np.searchsorted(self.imu_t, t, side="left")), len(self.imu_t) - 1)
        return self.model.corrected_rates(self.theta, self.imu_w[m:m + 1])[0]

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
        self.omega = self.rate_at(self.t)

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
        S = H @ self.P @ H.T + R
        K = np.linalg.solve(S, H @ self.P).T
        nis = float(nu @ np.linalg.solve(S, nu))
        self.P = joseph_update(self.P, K, H, R)
        self._apply(K @ nu)
        key = "position_updates" if self.config.velocity_reference == "position" \
            else "velocity_updates"
        self.counters.extra[key] = self.counters.extra.get(key, 0) + 1
        h = self.reference_history
        h["t"].append(self.t0 + self.t)  # POSIX s, as the residual table
        for j, ax in enumerate("xyz"):
            h[f"nu_{ax}"].append(float(nu[j]))
        h["nis"].append(nis)

    def star_update(self, uv, u_i, ctx: FrameContext, sigma) -> FrameUpdate | None:
        """Z2: every identified star of the frame (per-star χ² gate, iterated EKF)."""
        model, c = self.model, self.config
        N, ia, it = self.N, self.ia, self.it
        n = len(uv)
        R_meas = sigma**2
        theta0 = self.theta.copy()

        def jac(pred):
            H = np.zeros((len(pred.uv), 2, N))
            H[:, :, ia] = pred.H_attitude
            H[:, :, it] = pred.H_parameters
            return H

        pred0 = model.predict(theta0, u_i, ctx, self._attitude_function())
        H0 = jac(pred0)
        nu0 = uv - pred0.uv
        S_blocks = np.einsum("nij,jk,nlk->nil", H0, self.P, H0)
        S_blocks[:, 0, 0] += R_meas
        S_blocks[:, 1, 1] += R_meas
        nis_stars = block_nis(nu0, S_blocks)
        accepted = nis_stars <= self.gate
        self.counters.stars_gated += int(n - accepted.sum())
        result = FrameUpdate(self._frame[0], self.t, accepted, uv, pred0.uv, S_blocks, nis_stars,
                             float("nan"), 0, pred0.directions_st, self.omega.copy(), 0)
        if accepted.sum() < c.min_stars:
            self.counters.skipped_few_stars += 1
            return result
        idx = np.flatnonzero(accepted)
        ctx_acc = _subset(ctx, idx)
        z = uv[idx].reshape(-1)
        Rm = np.diag(np.repeat(R_meas[idx], 2))
        H = H0[idx].reshape(-1, N)
        h = pred0.uv[idx].reshape(-1)
        dx = np.zeros(N)
        it_count = 0
        for it_count in range(1, c.max_iterations + 1):  # noqa: B007
            S = H @ self.P @ H.T + Rm
            K = np.linalg.solve(S, H @ self.P).T
            dx_new = K @ (z - h + H @ dx)
            step = dx_new - dx
            dx = dx_new
            if np.linalg.norm(step[ia]) < c.relinearize_rad:
                break
            pred = model.predict(theta0 + dx[it], u_i[idx], ctx_acc,
                                 self._attitude_function(dx[ia]))
            H = jac(pred).reshape(-1, N)
            h = pred.uv.reshape(-1)
        H0a = H0[idx].reshape(-1, N)
        nu = z - pred0.uv[idx].reshape(-1)
        S0 = H0a @ self.P @ H0a.T + Rm
        nis = float(nu @ np.linalg.solve(S0, nu))
        self.P = joseph_update(self.P, K, H, Rm)
        self._apply(dx)
        self.counters.updates += 1
        result.nis = nis
        result.dof = int(len(z))
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
        self.reference_update()
        return self.star_update(uv, u_i, ctx, sigma)

    def sigma(self) -> np.ndarray:
        """1-sigma of the error state."""
        return np.sqrt(np.clip(np.diag(self.P), 0.0, None))


def _residual_rows(rows: dict[str, list], upd: FrameUpdate, frame_index: int, ids, mag,
                   ctx: FrameContext) -> None:
    """Append one frame's per-star rows (PSCE residual-table columns) as arrays."""
    n = len(upd.uv)
    nu = upd.uv - upd.uv_pred
    cols = {
        "t": np.full(n, upd.stamp), "frame": np.full(n, frame_index), "catalog_id": ids,
        "u": upd.uv[:, 0], "v": upd.uv[:, 1], "u_pred": upd.uv_pred[:, 0],
        "v_pred": upd.uv_pred[:, 1], "du": nu[:, 0], "dv": nu[:, 1],
        "s_uu": upd.S[:, 0, 0], "s_uv": upd.S[:, 0, 1], "s_vv": upd.S[:, 1, 1],
        "nis": upd.nis_stars, "magnitude": mag, "gated": ~upd.accepted,
        "x_st": upd.directions_st[:, 0], "y_st": upd.directions_st[:, 1],
        "z_st": upd.directions_st[:, 2],
        "omega_x": np.full(n, upd.omega_b[0]), "omega_y": np.full(n, upd.omega_b[1]),
        "omega_z": np.full(n, upd.omega_b[2]),
        "head_temperature": np.full(n, ctx.head_temperature_c),
    }
    for k in rows:
        rows[k].append(np.asarray(cols.get(k, np.full(n, np.nan))))


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
    rows: dict[str, list] = {k: [] for k in RESIDUAL_COLUMNS}
    hist: dict[str, list] = {"t": [], "nis": [], "dof": [], "stars": [], "gated": [],
                             "iterations": []}
    theta_hist, sigma_hist, nav_sigma = [], [], []
    prog = _Progress(len(data.frames), progress)
    t_start = time.perf_counter()
    for i, frame in enumerate(data.frames):
        prog(i)
        ok = clean_frame(frame, width, height)
        flt.counters.stars_invalid += int((~ok).sum())
        if not np.any(ok):
            flt.counters.frames += 1
            flt.counters.skipped_few_stars += 1
            continue
        ids = frame.catalog_id[ok].astype(np.int64)
        mag = frame.magnitude[ok]
        ctx = frame_context(data, frame, ids, mag)
        u_i = radec_to_unit(frame.right_ascension[ok], frame.declination[ok])
        sig = np.where(frame.sigma[ok] > 0, frame.sigma[ok], c.centroid_sigma_px)
        t_rel = (frame.stamp_ns - data.t0_ns) * 1e-9
        upd = flt.process_frame(frame.uv[ok], u_i, ctx, sig, t_rel)
        if upd is None:
            continue
        _residual_rows(rows, upd, i, ids, mag, ctx)
        if np.isfinite(upd.nis):
            hist["t"].append(upd.stamp)
            hist["nis"].append(upd.nis)
            hist["dof"].append(upd.dof)
            hist["stars"].append(int(upd.accepted.sum()))
            hist["gated"].append(int((~upd.accepted).sum()))
            hist["iterations"].append(upd.iterations)
            theta_hist.append(flt.theta.copy())
            s = flt.sigma()
            sigma_hist.append(s[flt.it])
            nav_sigma.append(np.concatenate([s[flt.ia], s[flt.iv], s[flt.ir]]))
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
    sg = np.asarray(sigma_hist).reshape(-1, model.size)
    for j, name in enumerate(names):
        history[name] = th[:, j]
        history["sigma." + name] = sg[:, j]
    nav = np.asarray(nav_sigma).reshape(-1, 9)
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
        residuals={k: np.concatenate(v) if v else np.zeros(0) for k, v in rows.items()},
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
