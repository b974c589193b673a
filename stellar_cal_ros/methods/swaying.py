"""Swaying-base installation calibration in the inertial frame (Zhang et al., IEEE Access 2018).

Error-state EKF over an inertial-frame strapdown (GCRS axes), built on the shared kernel
(:mod:`stellar_cal_ros.methods.kernel`: frame handling, acquisition, gate, iterated update,
re-acquisition, IMU gap bridging).  This module holds what is the method's own.

State: attitude ``R̂_i_b`` (left error φ, as PSCE), the parameters θ of the model's effects
(baseline :data:`BASELINE_EFFECTS` = ``gyro_bias, accel_bias, installation``: the paper's 15
states with the navigation errors), and the navigation blocks ``velocity`` v̂ⁱ and
``position`` r̂ⁱ (relative to the site at t0, so no 6e6 m numbers enter the filter)::

    x = [φ (3), δθ (P), δvⁱ (3), δrⁱ (3)]

Continuous error model (Zhang eqs. 6 and 8, written for any GYRO/ACCEL-stage effect)::

    φ̇  = R̂ G_g δθ − R̂ n_g,            G_g = −(I+E_g)⁻¹ (∂b_g/∂θ + ∂E_g/∂θ ω̂)
    δv̇ = −[R̂ f̂]× φ + R̂ G_a δθ + R̂ n_a,  G_a = −(I+E_a)⁻¹ (∂b_a/∂θ + ∂E_a/∂θ f̂)
    δṙ = δv
    δθ̇_j = −δθ_j / τ_j + η_j           (first-order Gauss–Markov; τ = ∞: random constant)

Because φ̇ has no φ term, the transition over the IMU samples between two star frames is
summed exactly, and the covariance is propagated once per frame.  The strapdown (coning
and sculling) is the filters' one IMU propagation (:class:`~stellar_cal_ros.core.propagation.
ImuPropagation`: a reference strapdown accumulated once per sample, rebuilt after
``reference_window_s`` or when the first-order corrections for the change of θ̂ grow;
:meth:`SwayingFilter._transition` turns its sums into Φ; both, and the position
reference's update, in one compiled call each by default, the numpy path the reference:
``compiled_propagation``, ``compiled_reference``).  The Earth-orientation
quantities (gravitation, site position and velocity in the GCRS) are tabulated on a grid
computed in chunks as the data advance, so the filter streams with bounded memory.

Measurements
------------
Z1, the inertial reference: the base stays at the site apart from the sway, whose velocity
reaches 1.5 m/s (Zhang eq. 19) but whose *displacement* stays bounded (≤ 2 m).  Used as white
noise on the velocity (Zhang eq. 9 taken literally) the sway swamps the ``g ψ t`` signature
of a tilt; so Z1 is position matching, ``ν = (r_site(t) − r_site(t0)) − r̂ = δr − d(t)``,
``R = σ_d² I`` every ``position_interval_s`` (``velocity_reference="velocity"`` gives the
literal form).  A tilt then shows as ``½ g ψ t²`` against a bounded noise.

Z2, star directions, in pixel space through :class:`~stellar_cal_ros.methods.star_model.
StarModel` (to first order Zhang's ``Z2 = Ĉ lˢ − lⁱ``, with a full-rank per-star noise, the
tracker's σ, the shared gate and any camera or time effect).

What the reference bag ``swaying_ideal`` supports (386 s, three base orientations) is in
doc/benchmarks.md: the installation about x/y is tied to the principal point (they separate
only through the perspective term) and the IMU error matrix; :func:`~stellar_cal_ros.methods.
bounds.crlb` gives the Cramér–Rao bound of any model on any bag.

Neglected, with their size (target 0.5"): polar motion (≤ 0.5", absorbed by the
accelerometer bias), dut1 (set ``SwayingConfig.dut1`` from IERS Bulletin A; the reference
bags use 0), gravity anomaly and deflection of the vertical (estimated as accelerometer
bias), gravity gradient over the sway and tides (< 0.6 µg).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from stellar_cal_ros.core import earth
from stellar_cal_ros.core.jit import HAVE_NUMBA
from stellar_cal_ros.core.propagation import Step
from stellar_cal_ros.core.rotation import skew
from stellar_cal_ros.core.state import Block, nominal_view
from stellar_cal_ros.core.units import DEG_PER_HOUR, G0
from stellar_cal_ros.errors import ModelError
from stellar_cal_ros.methods.kernel import FrameUpdate, KernelConfig, StarFilter
from stellar_cal_ros.methods.registry import MethodSpec
from stellar_cal_ros.methods.star_model import StarModel

log = logging.getLogger(__name__)

BASELINE_EFFECTS = ("gyro_bias", "accel_bias", "installation")


@dataclass
class SwayingConfig(KernelConfig):
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
    max_iterations: int = 4
    relinearize_rad: float = 2e-5  #: iterate while the attitude correction exceeds this
    grid_step_s: float = 0.25  #: Earth-orientation grid (gravitation, site), linear interp.
    grid_chunk_s: float = 600.0  #: the grid is computed in chunks of this length
    #: a frame's first-order attitude correction for θ̂ − θ_ref larger than this rebuilds
    #: the reference strapdown under the current θ (second-order error < ½ this², 5e-9 rad)
    fast_propagation_max_rad: float = 1e-4
    reference_window_s: float = 120.0  #: a reference strapdown older than this is rebuilt


class EarthGrid:
    """Earth-orientation tables on a regular grid, computed in chunks as time advances.

    ``functions`` maps a name to ``f(t_posix (n,)) -> (n, k)``; :meth:`interp` interpolates
    linearly (a 0.25 s grid: the Earth turns 1.8e-5 rad between nodes, error < 1e-10).
    Chunks older than the two most recent ones used are dropped (bounded memory).
    """

    def __init__(self, t0: float, step: float, chunk_s: float, functions: dict) -> None:
        self.t0, self.step = float(t0), float(step)
        self.K = max(int(round(chunk_s / step)), 1)
        self.functions = functions
        self._chunks: dict[int, dict[str, np.ndarray]] = {}

    def _chunk(self, c: int) -> dict[str, np.ndarray]:
        ch = self._chunks.get(c)
        if ch is None:
            t = self.t0 + (c * self.K + np.arange(self.K + 1)) * self.step
            ch = {name: np.asarray(fn(t), dtype=float).reshape(len(t), -1)
                  for name, fn in self.functions.items()}
            self._chunks[c] = ch
            for old in [k for k in self._chunks if k < c - 1]:
                del self._chunks[old]
        return ch

    def interp(self, name: str, t: np.ndarray | float) -> np.ndarray:
        """Table ``name`` at relative times ``t`` (n, k)."""
        if np.ndim(t) == 0:  # one time (the position reference's): the same floats, no groups
            x = float(t) / self.step
            i = math.floor(x)
            a = x - i
            c = i // self.K
            table = self._chunk(c)[name]
            j = i - c * self.K
            return ((1.0 - a) * table[j] + a * table[j + 1])[None]
        t = np.atleast_1d(np.asarray(t, dtype=float))
        x = t / self.step
        i = np.floor(x).astype(np.int64)
        a = (x - i)[:, None]
        c = i // self.K
        if len(c) and c[0] == c[-1] and (c == c[0]).all():  # one chunk (the usual case)
            cc = int(c[0])
            table = self._chunk(cc)[name]
            j = i - cc * self.K
            return (1.0 - a) * table[j] + a * table[j + 1]  # (the rows of the groups below)
        out = None
        for cc in np.unique(c).tolist():
            sel = c == cc
            table = self._chunk(int(cc))[name]
            j = i[sel] - cc * self.K
            vals = (1.0 - a[sel]) * table[j] + a[sel] * table[j + 1]
            if out is None:
                out = np.empty((len(t), table.shape[1]))
            out[sel] = vals
        return out


class SwayingFilter(StarFilter):
    """Inertial-frame error-state Kalman filter (see the module docstring).

    Parameters
    ----------
    model : StarModel
        Effects (parameter layout θ) and the prior.
    t0 : float
        POSIX time of relative zero.
    site : Site
        Site of the base (``/gnss/fix``).
    config : SwayingConfig
    nominal_dt : float
        Nominal IMU interval, s.
    consider : int
        Trailing θ entries of ``model`` that are consider parameters (see the kernel).

    IMU samples come through :meth:`extend_imu` (relative s, rad/s, m/s²).
    """

    method = "swaying_base"
    compiled_star_update = True  # (the kernel's; the numpy update stays the reference)
    #: the propagation between frames (the strapdown's sums over the IMU samples, Φ, the
    #: covariance, sensitivity, velocity and position) in one compiled call
    #: (:func:`~.frame_step.swaying_propagate`; False: :meth:`ImuPropagation._interval` and
    #: :meth:`_transition` in numpy, the reference; ``compiled_step`` False: numpy too)
    compiled_propagation = True
    #: the position (Z1) reference's update and injection in one compiled call
    #: (:func:`~.frame_step.reference_update`; False: the numpy update, the reference)
    compiled_reference = True
    #: a frame's propagation, position reference (when due) and star update in one compiled
    #: call (:func:`~.frame_step.swaying_frame`; False: the three calls above, the reference)
    compiled_frame = True
    #: the gyro watch's first frames committed a batch at once too (the kernel's
    #: :attr:`~.kernel.StarFilter.commit_early_frames`: this batch has no frame taken one
    #: at a time; each would make its own call): the same floats, records and verdicts
    commit_early_frames = True
    #: what :meth:`_fused_update` does in its call: a subclass with its own keeps the calls
    _FRAME_HOOKS = ("_transition", "_propagate_interval", "_before_star_update",
                    "_reference_update", "reference_measurement", "propagate", "_star_update",
                    "_compiled_star_update", "_inflate_bridged", "rate_at", "inject",
                    "_fused_update", "site_position", "site_positions")
    checkpoint_fields = {**StarFilter.checkpoint_fields,
                         "last_reference_t": "last_reference_t",
                         "level_check_deg": "level_check_deg",
                         "reference_history": "reference_history"}
    navigation_blocks = (Block("velocity", 3, navigation=True, driven_by="accel"),
                         Block("position", 3, navigation=True))

    def __init__(self, model: StarModel, t0: float, site: earth.Site,
                 config: SwayingConfig | None = None, *, nominal_dt: float,
                 consider: int = 0) -> None:
        super().__init__(model, t0, config or SwayingConfig(), nominal_dt, consider)
        c = self.config
        self.site = site
        P = self.P_est
        self.iv, self.ir = self.layout.sl("velocity"), self.layout.sl("position")
        # process noise of θ: Gauss–Markov where configured, else the effect's random walk;
        # a gyro bias random walk the noise scales state (``gyro_bias_rw``) replaces its
        # Gauss–Markov (the kernel set it in q_theta)
        self.tau = np.full(P, np.inf)
        self.gm_sigma = np.zeros(P)
        for eff in model.effects:
            sl = model.slices[eff.id]
            if eff.id == "gyro_bias" and self.gyro_bias_rw > 0:
                continue
            if sl.stop <= P and eff.id in c.gauss_markov:
                tau, s = c.gauss_markov[eff.id]
                self.tau[sl] = tau
                self.gm_sigma[sl] = s
                self.q_theta[sl] = 0.0
        self.q_accel = (c.accel_vrw_mps_sqrth / 60.0) ** 2
        self.r_site0 = earth.site_position_gcrs(site, self.t0, c.dut1)
        self.grid = EarthGrid(self.t0, c.grid_step_s, c.grid_chunk_s, self._grid_functions())
        self._inv_tau = np.where(np.isfinite(self.tau), 1.0 / self.tau, 0.0)
        self._Phi = np.eye(self.N)
        self._diag_it = (np.arange(self.it.start, self.it.stop),) * 2
        self._qd_setup()
        # the compiled propagation's Q_d and decay inputs, and its M without consider
        self._qd_arrays = (self._qd_index.astype(np.int64), np.array(self._qd),
                           np.ascontiguousarray(self._inv_tau[:self.P_est]))
        self._no_consider = np.zeros((self.N, 0))
        # the frame's one call (compiled_frame): its step (built on first use) and constants
        self._frame_one = None
        self._no_site = np.zeros(3)
        self._R_reference = c.sway_displacement_sigma_m**2 * np.eye(3)
        self.last_reference_t = -np.inf
        self.level_check_deg = float("nan")
        self.reference_history: dict[str, list] = {"t": [], "nu_x": [], "nu_y": [],
                                                    "nu_z": [], "nis": []}

    def _grid_functions(self) -> dict:
        site, dut1, r0 = self.site, self.config.dut1, self.r_site0
        return {"g": lambda t: earth.gravitation_gcrs(site, t, dut1),
                "r": lambda t: earth.site_position_gcrs(site, t, dut1) - r0,
                "v": lambda t: earth.site_velocity_gcrs(site, t, dut1)}

    def _qd_setup(self) -> None:
        """Process noise Q_d(T) of an interval on its (flat) entries.

        White gyro / accel noise (q T on φ and δv, q T²/2 on δv–δr, q T³/3 on δr), θ random
        walk (q T) and Gauss–Markov (σ² (1 − e^{−2T/τ})):
        ``q1 T + q2 T² + q3 T³ + gm2 (1 − e^{−itau2 T})`` per entry.
        """
        N, qa = self.N, self.q_accel
        entries = []
        for j in range(3):
            a, v, r_ = self.ia.start + j, self.iv.start + j, self.ir.start + j
            entries += [(a, a, self.q_gyro, 0.0, 0.0, 0.0, 0.0), (v, v, qa, 0.0, 0.0, 0.0, 0.0),
                        (v, r_, 0.0, qa / 2, 0.0, 0.0, 0.0), (r_, v, 0.0, qa / 2, 0.0, 0.0, 0.0),
                        (r_, r_, 0.0, 0.0, qa / 3, 0.0, 0.0)]
        for p in range(self.P_est):
            q = self.it.start + p
            entries.append((q, q, self.q_theta[p], 0.0, 0.0, self.gm_sigma[p] ** 2,
                            2.0 * self._inv_tau[p]))
        e = np.array(entries, dtype=float).reshape(-1, 7)
        self._qd_index = (e[:, 0] * N + e[:, 1]).astype(int)
        self._qd = tuple(e[:, c_] for c_ in range(2, 7))

    def accel_noise_density(self) -> float:
        """White specific-force noise, m/s/√s."""
        return self.config.accel_vrw_mps_sqrth / 60.0

    # ------------------------------------------------------------------ nominal values
    velocity = nominal_view("velocity", "Nominal inertial velocity, m/s (GCRS).")
    position = nominal_view("position", "Nominal position relative to the site at t0, m "
                                        "(GCRS axes).")

    @property
    def v(self) -> np.ndarray:
        """Nominal inertial velocity (alias of ``velocity``)."""
        return self.velocity

    @property
    def r(self) -> np.ndarray:
        """Nominal position relative to the site at t0 (alias of ``position``)."""
        return self.position

    # ------------------------------------------------------------------ Earth
    def site_position(self, t: float) -> np.ndarray:
        """Site position relative to the site at ``t0``, GCRS, m."""
        return self.site_positions(t)[0]

    def site_positions(self, t: np.ndarray | float) -> np.ndarray:
        """Site positions at relative times ``t`` (n, 3), as :meth:`site_position`'s, GCRS, m.

        One interpolation of the Earth grid: a row each, the same floats as one call a time.
        """
        return self.grid.interp("r", t)

    def site_velocity(self, t: float) -> np.ndarray:
        """Site inertial velocity, GCRS, m/s."""
        return self.grid.interp("v", t)[0]

    # ------------------------------------------------------------------ propagation
    def gravitation(self, t: np.ndarray) -> np.ndarray:
        """Gravitation at relative times ``t`` (n, 3), GCRS, m/s² (the Earth grid)."""
        return self.grid.interp("g", t)

    def _transition(self, step: Step) -> None:
        """Velocity, position and ``P ← Φ P Φᵀ + Q_d`` over a propagation step.

        ``Φ``: the step's parameter columns of the attitude, velocity and position rows, the
        attitude columns ``−[Δv]×`` of the velocity and position, ``T I`` from velocity to
        position and the Gauss–Markov decay of θ; ``Q_d`` from :meth:`_qd_setup`.
        """
        T, Pe = step.T, self.P_est
        ia, it, iv, ir = self.ia, self.it, self.iv, self.ir
        Phi, F = self._Phi, step.F
        F_b = None
        if self.model.size:
            Phi[ia, it] = F[0][:, :Pe]
            Phi[iv.start:ir.stop, it] = F[1:, :, :Pe].reshape(6, Pe)
            Phi[self._diag_it] = np.exp(-T * self._inv_tau)
            if self.n_consider:
                F_b = np.zeros((self.N, self.n_consider))
                F_b[ia] = F[0][:, Pe:]
                F_b[iv.start:ir.stop] = F[1:, :, Pe:].reshape(6, -1)
        dvr = step.dvr
        Phi[iv.start:ir.stop, ia] = -skew(dvr).reshape(6, 3)
        Phi[ir, iv] = T * np.eye(3)
        self.position = self.position + self.velocity * T + dvr[1] + step.gravity[1]
        self.velocity = self.velocity + dvr[0] + step.gravity[0]
        q1, q2, q3, gm2, itau2 = self._qd
        q = (q1 + (q2 + q3 * T) * T) * T + gm2 * -np.expm1(-T * itau2)
        self.state.propagate(Phi, (self._qd_index, q), F_b)

    def _propagate_interval(self, k: int, m: int, t_target: float) -> None:
        """The kernel's, or with :attr:`compiled_propagation` the same in one compiled call.

        Taken when the method's transition is this class's (a subclass with its own keeps
        the numpy path) and numba is there.
        """
        if not (self.compiled_propagation and self.compiled_step and HAVE_NUMBA) or \
                type(self)._transition is not SwayingFilter._transition:
            super()._propagate_interval(k, m, t_target)
            return
        self.R_i_b = self.propagation.step(self.imu, k, m, self.t, t_target, self.R_i_b,
                                           self.theta, self._compiled_interval)

    def _compiled_interval(self, imu, k, m, ta, tb, R_a, theta) -> np.ndarray | None:
        """:func:`~.frame_step.swaying_propagate` of the interval (P, M, v, r set here).

        Returns the new attitude, or None (nothing changed) when the reference is to be
        rebuilt (:meth:`ImuPropagation.step`'s ``interval``).
        """
        from stellar_cal_ros.methods.frame_step import swaying_propagate

        prop = self.propagation
        Gg, Ga = (np.ascontiguousarray(g, dtype=float) for g in prop._gamma)
        qd_index, qd, inv_tau = self._qd_arrays
        sens = self.state.sensitivity
        M = self._no_consider if sens is None else np.ascontiguousarray(sens.M)
        ok, R_b, P, M, vel, pos = swaying_propagate(
            *prop.rows(imu, k, m), float(ta), float(tb), np.ascontiguousarray(R_a),
            Gg, Ga, theta - prop.theta_ref, prop.max_correction_rad,
            np.ascontiguousarray(self.state.P), M, self.P_est, inv_tau, qd_index, qd,
            self.velocity, self.position)
        if not ok:
            return None
        self.state.P = P
        if sens is not None:
            sens.M = M
        self.velocity, self.position = vel, pos
        return R_b

    def _fused_update(self, uv, u_i, ctx, sigma, t_exp) -> tuple[bool, FrameUpdate | None]:
        """With :attr:`compiled_frame`: the frame's three steps in one compiled call.

        Propagation, position reference (when due) and star update
        (:func:`~.frame_step.swaying_frame`).

        ``(False, None)`` (nothing changed: the three calls of :meth:`update`) when one of
        them would take its numpy path, a re-acquisition is pending, the IMU does not cover
        ``t_exp``, the rows hold a bridged sample or leave the reference (its window), or
        the reference is to be rebuilt.  The same formulas as the three calls; the rate is
        the gyro's affine bias at θ̂ (a model with an error matrix keeps the three calls).
        """
        us = self._frame_update()
        if not us or self._gap_pending or t_exp <= self.t:
            return False, None
        imu, prop = self.imu, self.propagation
        pre = prop.prefix
        m = imu.index(t_exp)
        k = self._k
        if m >= len(imu) or pre is None or imu.base + k < pre.base or \
                imu.base + m - prop.ref_start >= prop.window:
            return False, None
        if pre.end <= imu.base + m:  # (as ImuPropagation.step: the rows do not depend on it)
            prop._extend(imu, pre.end - imu.base, len(imu))
            pre = prop.prefix
        from stellar_cal_ros.methods import frame_step

        if frame_step.fused_sample(imu.t, imu.cum_bridged, k, t_exp, imu.base, pre.base,
                                   pre.end, prop.ref_start, float(prop.window)) != m:
            return False, None
        c = self.config
        due = t_exp - self.last_reference_t >= c.position_interval_s - 1e-6
        site = self.site_position(t_exp) if due else self._no_site
        st = self.state
        sens = st.sensitivity
        M, score, info, acc = us._sensitivity(sens)
        if sens is None:
            M = self._no_consider
        u, uvc, sg = us._frame(u_i, uv, sigma)
        du, bscale = us.compiled_chain.frame_inputs(u, ctx)
        Gg, Ga = (np.ascontiguousarray(g_, dtype=float) for g_ in prop._gamma)
        qd_index, qd, inv_tau = self._qd_arrays
        b0, _, Jb, _ = prop.gyro._affine
        out = frame_step.swaying_frame(
            *prop.rows(imu, k, m), float(self.t), float(t_exp), np.ascontiguousarray(self.R_i_b),
            Gg, Ga, self.theta - prop.theta_ref, prop.max_correction_rad,
            np.ascontiguousarray(st.P), M, self.P_est, inv_tau, qd_index, qd, self.velocity,
            self.position, due, site, self._R_reference, score, info, acc, b0, Jb,
            prop.gyro.theta0, imu.w[m], self.theta, uvc, u, sg, float(self._stamp_rel - t_exp),
            *us.chain, *us.directions, du, bscale, us.cfg)
        (status, ints, floats, accepted, uv_pred, S, nis_stars, dirs, omega, R_prior, R, P,
         M, vel, pos, nu, nis, dx) = out
        if status == frame_step.REBUILD:
            return False, None
        st.P = P
        if sens is not None:
            sens.M = M
        self.R_i_b = R
        self.velocity, self.position = vel, pos
        self.t = t_exp
        self._k = m
        self.omega = omega
        if self.gyro_watch is not None:
            self._R_prior = (R_prior, False)
        if due:
            self.last_reference_t = t_exp
            if sens is not None:
                sens.frames += acc
            self._reference_done(nu, float(nis))
        return True, self._compiled_result((status, ints, floats, accepted, uv_pred, S,
                                            nis_stars, dirs, omega), uv, u_i, ctx, sigma,
                                           t_exp, dx)

    def prepare_frames(self, frames: list[tuple], shift: float | None | bool = False,
                       ready: tuple[float, float] | None = None) -> int:
        """The coming frames' :meth:`_fused_update` calls in one compiled call (a batch).

        :func:`~.frame_step.swaying_frames` over the leading frames of ``frames`` (as the
        kernel's :meth:`~.kernel.StarFilter.prepare_frames`) that the frame's one call
        would take as things stand: enough stars, in order, the IMU covering each
        exposure, rows inside the reference's window and without a bridged sample, no
        covariance check due among them; the position reference's due frames and site
        positions found here from the exposure times (a fixed exposure shift: ``shift``
        None, a moving one, batches nothing).  The state is not changed:
        :meth:`commit_batch` commits the leading updated frames at once, the driver takes
        the rest frame by frame (their own calls).  A batch may hold one frame (the batch
        equals one call a frame: its own call is then never loaded).  Returns the frames
        stepped.
        """
        self._batch = None
        us = self._frame_update() if self.compiled_step and self.batched_step and \
            self.initialized else False
        w = self.gyro_watch
        if not us or not frames or self._gap_pending or self.t is None or \
                (w is not None and w["done"]):
            return 0
        if shift is False:
            shift = self.model.fixed_exposure_shift(self.theta, self.P_est)
        if shift is None:
            return 0
        from stellar_cal_ros.methods import frame_step

        c = self.config
        every = c.covariance_check_every
        left = every - self.counters.updates % every if every and not self.checks_deferred \
            else len(frames)
        left = min(left, self.batch_frames_max)
        imu, prop = self.imu, self.propagation
        t, k, last, t_ref = self.t, self._k, self.last_stamp, self.last_reference_t
        run, due = [], []
        for uv, u_i, ctx, sigma, t_rel, acc in frames[:left]:
            if ctx is None or len(uv) < c.min_stars or not math.isfinite(t_rel) or \
                    (last is not None and t_rel <= last):
                break
            t_exp = t_rel + shift
            pre = prop.prefix
            m = imu.index(t_exp)
            if not run and t_exp > t and m < len(imu) and pre is not None and \
                    imu.base + k >= pre.base and imu.base + m - prop.ref_start >= prop.window:
                # the reference's window ends in the first frame: rebuilt here, from the
                # frame's first sample under θ̂, as its own propagation would
                # (ImuPropagation.step), so that the frame is batched too
                prop.rebuild(imu, k, self.theta)
                pre = prop.prefix
            if t_exp <= t or m >= len(imu) or pre is None or imu.base + k < pre.base or \
                    imu.base + m - prop.ref_start >= prop.window:
                break
            if pre.end <= imu.base + m:  # (as _fused_update: the rows do not depend on it)
                prop._extend(imu, pre.end - imu.base, len(imu))
                pre = prop.prefix
            if frame_step.fused_sample(imu.t, imu.cum_bridged, k, t_exp, imu.base, pre.base,
                                       pre.end, prop.ref_start, float(prop.window)) != m:
                break
            d = t_exp - t_ref >= c.position_interval_s - 1e-6
            if d:
                t_ref = t_exp
            off = imu.base - pre.base
            run.append((uv, u_i, sigma, t_rel - t_exp, ctx, k + off, m + off, t, t_exp, m,
                        acc, t_rel))
            due.append(d)
            t, k, last = t_exp, m, t_rel
        if not run:
            return 0
        self._batch = self._frames_batch(us, run, np.array(due))
        return self._batch.done if self._batch is not None else 0

    def _frames_batch(self, us, run: list, due: np.ndarray):
        """:func:`~.frame_step.swaying_frames` of ``run`` (:meth:`prepare_frames`'s frames).

        A :class:`~.frame_step.FrameBatch` (its frames carry their ``due`` flag last), or
        None: no frame done.
        """
        from stellar_cal_ros.methods import frame_step

        st = self.state
        if not st.P.flags.c_contiguous:
            st.P = np.ascontiguousarray(st.P)
        sens = st.sensitivity
        M, score, info, _ = us._sensitivity(sens)
        if sens is None:
            M = self._no_consider
        prop, imu = self.propagation, self.imu
        pre = prop.prefix
        offs, col, uv, u, sigma, du, bscale, base = us.stack(run)
        site = np.zeros((len(run), 3))
        rows = np.flatnonzero(due)
        if len(rows):
            site[rows] = self.site_positions(np.array([run[i][8] for i in rows.tolist()]))
        Gg, Ga = (np.ascontiguousarray(g_, dtype=float) for g_ in prop._gamma)
        qd_index, qd, inv_tau = self._qd_arrays
        b0, _, Jb, _ = prop.gyro._affine
        R = self.R_i_b if self.R_i_b.flags.c_contiguous else np.ascontiguousarray(self.R_i_b)
        out = frame_step.swaying_frames(
            pre.tp, pre.C, pre.w_hat, pre.phi, pre.slope, pre.f_hat, pre.du, pre.gdt,
            col[:, 0].astype(np.int64), col[:, 1].astype(np.int64),
            np.ascontiguousarray(col[:, 2]), np.ascontiguousarray(col[:, 3]), R, Gg, Ga,
            prop.theta_ref, prop.max_correction_rad, st.P, M, self.P_est, inv_tau, qd_index,
            qd, self.velocity, self.position, due, site, self._R_reference, score, info,
            col[:, 5] != 0.0, b0, Jb, prop.gyro.theta0, imu.w, col[:, 4].astype(np.int64),
            self.theta, uv, u, sigma, offs, base, *us.chain, *us.directions, du, bscale,
            us.cfg)
        if not int(out[0]):
            return None
        frames = [f + (bool(d_),) for f, d_ in zip(run, due.tolist(), strict=True)]
        return frame_step.FrameBatch(out, frames, offs, prop._gamma, pre, st.P, self.theta,
                                     self.R_i_b, M)

    def _commit_more(self, out: tuple, frames: list, q: int) -> None:
        """:meth:`commit_batch`'s part for this method: navigation and position references.

        The velocity and position after frame ``q − 1``, and each due reference's count,
        sensitivity frame and history row in order (what :meth:`_fused_update` does).
        """
        vel, pos, nu, nis = out[17:21]
        self.velocity = vel[q - 1].copy()
        self.position = pos[q - 1].copy()
        sens = self.state.sensitivity
        h = self.reference_history
        key = "position_updates" if self.config.velocity_reference == "position" \
            else "velocity_updates"
        for i in range(q):
            f = frames[i]
            if not f[12]:
                continue
            self.last_reference_t = f[8]
            if sens is not None:
                sens.frames += f[10]
            self.counters.add(key)
            h["t"].append(self.t0 + f[8])
            for j, ax in enumerate("xyz"):
                h[f"nu_{ax}"].append(float(nu[i, j]))
            h["nis"].append(float(nis[i]))

    def _frame_update(self):
        """The star update's :class:`~.frame_step.FusedStep` for :meth:`_fused_update`.

        False when the frame's call cannot be taken as the filter is configured (built once).
        """
        us = self._frame_one
        if us is not None:
            return us
        st = self.state
        prop = self.propagation
        us = False
        own = type(self)
        if self.compiled_frame and self.compiled_propagation and self.compiled_reference and \
                self.compiled_star_update and self.compiled_step and HAVE_NUMBA and \
                all(getattr(own, h) is getattr(SwayingFilter, h) for h in self._FRAME_HOOKS) \
                and [b.sl for b in st._rotations] == [self.ia] and \
                self.config.velocity_reference == "position" and \
                prop.accel is not None and not prop.exact and prop.gyro._no_E and \
                (self.iv.start, self.ir.start) == (3 + self.P_est, 6 + self.P_est):
            from stellar_cal_ros.methods.frame_step import FusedStep

            us = FusedStep.build_update(self, StarFilter) or False
        self._frame_one = us
        return us

    # ------------------------------------------------------------------ acquisition
    def _acquire_navigation(self, t_exp: float) -> None:
        c = self.config
        self.velocity = self.site_velocity(t_exp)
        self.position = self.site_position(t_exp)
        self.state.assign(self.iv, self.iv, c.initial_velocity_sigma_mps**2 * np.eye(3))
        self.state.assign(self.ir, self.ir, c.sway_displacement_sigma_m**2 * np.eye(3))
        self._level_check(t_exp)

    def _after_reacquire(self) -> None:
        self.last_reference_t = self.t  # the next Z1 a full interval later

    def _level_check(self, t_exp: float) -> None:
        """Log the angle between the measured and the expected specific force (1 s mean)."""
        imu = self.imu
        sel = (imu.t > t_exp - 1.0) & (imu.t <= t_exp + 1e-9)
        if not np.any(sel):
            return
        f_b = self.propagation.accel.corrected(imu.f[sel], self.theta).mean(axis=0)
        f_i = self.R_i_b @ f_b
        a_site = earth.site_acceleration_gcrs(self.site, self.t0 + t_exp, self.config.dut1)
        f_exp = a_site - self.grid.interp("g", t_exp)[0]
        ang = math.degrees(math.acos(float(np.clip(
            f_i @ f_exp / np.linalg.norm(f_i) / np.linalg.norm(f_exp), -1, 1))))
        self.level_check_deg = ang
        (log.warning if ang > 10.0 else log.info)(
            "coarse alignment: star attitude vs accelerometer level differ by %.3f deg "
            "(sway accelerations included)", ang)

    # ------------------------------------------------------------------ Z1
    def reference_measurement(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Z1: innovation, H (3, N) and R (3, 3) of the inertial reference."""
        c = self.config
        H = np.zeros((3, self.N))
        if c.velocity_reference == "position":
            nu = self.site_position(self.t) - self.position
            H[:, self.ir] = np.eye(3)
            R = c.sway_displacement_sigma_m**2 * np.eye(3)
        elif c.velocity_reference == "velocity":
            nu = self.site_velocity(self.t) - self.velocity
            H[:, self.iv] = np.eye(3)
            R = c.sway_velocity_sigma_mps**2 * np.eye(3)
        else:
            raise ModelError(f"unknown velocity_reference {c.velocity_reference!r}")
        return nu, H, R

    def _before_star_update(self) -> None:
        """Apply Z1 (at most every ``position_interval_s``)."""
        if self.t - self.last_reference_t < self.config.position_interval_s - 1e-6:
            return
        self.last_reference_t = self.t
        nu, H, R = self.reference_measurement()
        nis = self._reference_update(H, nu, R)
        self._reference_done(nu, nis)

    def _reference_done(self, nu: np.ndarray, nis: float) -> None:
        """The reference's count and history row (at ``self.t``)."""
        key = "position_updates" if self.config.velocity_reference == "position" \
            else "velocity_updates"
        self.counters.add(key)
        h = self.reference_history  # emptied by the driver into its statistics
        h["t"].append(self.t0 + self.t)  # POSIX s, as the residual table
        for j, ax in enumerate("xyz"):
            h[f"nu_{ax}"].append(float(nu[j]))
        h["nis"].append(nis)


    def _reference_update(self, H: np.ndarray, nu: np.ndarray, R: np.ndarray) -> float:
        """Update with Z1 and inject the correction; its NIS.

        With :attr:`compiled_reference` the update and the covariance's reset in one
        compiled call, the nominal values' box-plus here; not for a filter with its own
        injection (the Cramér–Rao bound's) or a rotation block besides the attitude.
        """
        st = self.state
        if not (self.compiled_reference and self.compiled_step and HAVE_NUMBA) or \
                type(self).inject is not StarFilter.inject or \
                [b.sl for b in st._rotations] != [self.ia]:
            dx, nis = st.linear_update(H, nu, R)
            self.inject(dx)
            return nis
        from stellar_cal_ros.methods.frame_step import reference_update

        sens = st.sensitivity
        if sens is None:
            M, score, info, acc = self._no_consider, np.zeros(0), np.zeros((0, 0)), False
        else:
            M, score, info, acc = (np.ascontiguousarray(sens.M), sens.score, sens.info,
                                   bool(sens.accumulate))
        dx, nis, st.P, M = reference_update(np.ascontiguousarray(st.P), M, score, info, acc,
                                            np.ascontiguousarray(H, dtype=float),
                                            np.asarray(nu, dtype=float),
                                            np.ascontiguousarray(R, dtype=float))
        if sens is not None:
            sens.M = M
            sens.frames += acc
        st.boxplus(dx)
        self._omega_stale = True
        return float(nis)


def replay_swaying(bag, prior, effects: list[str] | None = None,
                   config: SwayingConfig | None = None, progress: bool = False, **kw):
    """:func:`~stellar_cal_ros.methods.replay.replay` with the swaying-base filter."""
    from stellar_cal_ros.methods.replay import replay

    return replay(bag, prior, "swaying_base", effects, config, progress=progress, **kw)


def crlb_swaying(bag, prior, truth, effects: list[str] | None = None,
                 config: SwayingConfig | None = None, filter_cls=None):
    """Cramér–Rao bound of the swaying-base model (:func:`~.bounds.crlb`)."""
    from stellar_cal_ros.methods.bounds import crlb

    return crlb(bag, prior, truth, "swaying_base", effects, config, filter_cls)


def replay_lookahead(config: SwayingConfig) -> float:
    """IMU seconds a replay holds ahead of a frame: a full reference window (vectorized)."""
    return 0.0 if config.exact_propagation else (config.reference_window_s or 120.0) + 1.0


METHOD = MethodSpec(
    name="swaying_base", kind="filter",
    summary="Zhang et al. 2018: a ship at sea, accelerometer-levelled, in the inertial "
            "frame; needs /gnss/fix",
    baseline=BASELINE_EFFECTS, needs_site=True,
    filter_cls=SwayingFilter, config_cls=SwayingConfig, imu_lookahead=replay_lookahead)
