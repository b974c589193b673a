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
summed exactly, and the covariance is propagated once per frame.  The strapdown is
vectorized over *reference windows* of ``reference_window_s`` of samples (coning and
sculling), with first-order corrections for the change of θ̂ since the window was built
(:meth:`SwayingFilter.propagate`).  The Earth-orientation quantities (gravitation, site
position and velocity in the GCRS) are tabulated on a grid computed in chunks as the data
advance, so the filter streams with bounded memory.

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
from stellar_cal_ros.core.rotation import (
    quat_from_matrix,
    quat_from_rotvec,
    quat_to_matrix,
    skew,
    so3_exp,
)
from stellar_cal_ros.core.state import Block
from stellar_cal_ros.core.strapdown import (
    attitude_increments,
    attitude_prefix,
    quat_cumprod,
    velocity_increments,
)
from stellar_cal_ros.core.units import DEG_PER_HOUR, G0
from stellar_cal_ros.effects.base import Stage
from stellar_cal_ros.errors import ModelError
from stellar_cal_ros.methods.kernel import KernelConfig, NoImuError, StarFilter
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
    #: per-sample propagation between star frames (the reference; ~10x slower)
    exact_propagation: bool = False
    #: a frame's first-order attitude correction for θ̂ − θ_window larger than this rebuilds
    #: the reference strapdown under the current θ (second-order error < ½ this², 5e-9 rad)
    fast_propagation_max_rad: float = 1e-4
    reference_window_s: float = 120.0  #: length of a reference strapdown window


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
        t = np.atleast_1d(np.asarray(t, dtype=float))
        x = t / self.step
        i = np.floor(x).astype(np.int64)
        a = (x - i)[:, None]
        c = i // self.K
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
        # process noise of θ: Gauss–Markov where configured, else the effect's random walk
        self.tau = np.full(P, np.inf)
        self.gm_sigma = np.zeros(P)
        for eff in model.effects:
            sl = model.slices[eff.id]
            if sl.stop <= P and eff.id in c.gauss_markov:
                tau, s = c.gauss_markov[eff.id]
                self.tau[sl] = tau
                self.gm_sigma[sl] = s
                self.q_theta[sl] = 0.0
        self.q_accel = (c.accel_vrw_mps_sqrth / 60.0) ** 2
        self.r_site0 = earth.site_position_gcrs(site, self.t0, c.dut1)
        self.grid = EarthGrid(self.t0, c.grid_step_s, c.grid_chunk_s, self._grid_functions())
        self._theta_ref = self.theta.copy()
        self._win = (0, 0)
        self._win_theta = self.theta.copy()
        self.reference_rebuilds = 0
        self._cref_cache: tuple | None = None
        self._sensor_cache: dict = {}
        self._affine = {st: self._affine_sensor(st) for st in (Stage.GYRO, Stage.ACCEL)}
        self._inv_tau = np.where(np.isfinite(self.tau), 1.0 / self.tau, 0.0)
        self._Phi = np.eye(self.N)
        self._diag_it = (np.arange(self.it.start, self.it.stop),) * 2
        self._qd_setup()
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
    @property
    def velocity(self) -> np.ndarray:
        """Nominal inertial velocity, m/s (GCRS)."""
        return self.state.nominal["velocity"]

    @velocity.setter
    def velocity(self, value: np.ndarray) -> None:
        self.state.nominal["velocity"] = value

    @property
    def position(self) -> np.ndarray:
        """Nominal position relative to the site at t0, m (GCRS axes)."""
        return self.state.nominal["position"]

    @position.setter
    def position(self, value: np.ndarray) -> None:
        self.state.nominal["position"] = value

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
        return self.grid.interp("r", t)[0]

    def site_velocity(self, t: float) -> np.ndarray:
        """Site inertial velocity, GCRS, m/s."""
        return self.grid.interp("v", t)[0]

    # ------------------------------------------------------------------ sensor model
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

        ``b`` the bias, ``A = (I+E)⁻¹`` (None when E = 0) and Γ (3 or 12, P_all) with
        ``∂(corrected x̂)/∂θ = −(I+E)⁻¹ (∂b/∂θ + ∂E/∂θ x̂) = [I, x̂ᵀ⊗I] Γ``: 3 rows when no
        effect scales the sensor (``∂E/∂θ = 0``), else 12 — the bias part, then
        ``−(I+E)⁻¹ ∂E/∂θ`` with its (row, column) pair flattened, matching the per-sample
        rows ``[C Δt, (C ⊗ x̂) Δt]`` of :meth:`_sensor_rows`.
        """
        hit = self._sensor_cache.get(stage)
        theta = self.theta
        if hit is not None and np.array_equal(hit[0], theta):
            return hit[1]
        aff = self._affine[stage]
        if aff is None:
            b, E, Jb, JE = self.model.sensor_model(theta, stage)
            JbE = np.hstack([Jb, JE.reshape(3, -1)])
            scaled = bool(JE.any())
        else:
            b0, E0, Jb, JE, JbE, scaled = aff
            d = theta - self._theta_ref
            b, E = b0 + Jb @ d, E0 + JE @ d
        P = self.model.size
        A = _inv3(np.eye(3) + E) if E.any() else None
        M = -JbE if A is None else -(A @ JbE)
        G = np.concatenate([M[:, :P], M[:, P:].reshape(9, P)]) if scaled else M[:, :P]
        out = (b, A, G)
        self._sensor_cache[stage] = (theta.copy(), out)
        return out

    def _corrected(self, raw: np.ndarray, stage: Stage) -> np.ndarray:
        b, A, _ = self._sensor(stage)
        return raw - b if A is None else (raw - b) @ A.T

    @staticmethod
    def _sensor_rows(C: np.ndarray, x: np.ndarray, w: np.ndarray, scaled: bool) -> np.ndarray:
        """Per-segment rows (n, 3, 3 or 12) that :meth:`_sensor`'s Γ turns into ∂(C x̂ Δt)/∂θ."""
        n = len(w)
        Z = np.empty((n, 3, 12 if scaled else 3))
        np.multiply(C, w[:, None, None], out=Z[:, :, :3])
        if scaled:
            np.multiply(Z[:, :, :3, None], x[:, None, None, :], out=Z[:, :, 3:].reshape(n, 3, 3, 3))
        return Z

    def rate_at(self, t: float) -> np.ndarray:
        """Corrected body rate of the IMU sample covering relative time ``t``."""
        m = min(self.imu.index(t), len(self.imu) - 1)
        return self._corrected(self.imu.w[m], Stage.GYRO)

    # ------------------------------------------------------------------ propagation
    def _sample_dt(self, lo: int, hi: int) -> np.ndarray:
        """Interval lengths of samples ``lo:hi``."""
        t = self.imu.t
        prev = t[lo - 1] if lo > 0 else t[0] - self.nominal_dt
        return np.diff(t[lo:hi], prepend=prev)

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
        imu = self.imu
        dt = self._sample_dt(lo0, hi)
        w = self._corrected(imu.w[lo0:hi], Stage.GYRO)
        f = self._corrected(imu.f[lo0:hi], Stage.ACCEL)
        # Γ of the window's θ: between rebuilds E changes by < 1e-5, so the sensitivities
        # (Jacobian and first-order correction) change by that relative amount — negligible
        self._win_G = (self._sensor(Stage.GYRO)[2], self._sensor(Stage.ACCEL)[2])
        s = lo - lo0
        phi = attitude_increments(w, dt, coning=True)[s:]
        du = velocity_increments(w, f, dt, sculling=True)[s:]
        C = attitude_prefix(phi)  # (n+1, 3, 3), C[j]: start of sample lo + j
        dt = dt[s:]
        self._win = (lo, hi)
        self._win_theta = self.theta.copy()
        self._win_dt = dt
        self._win_w, self._win_f, self._win_phi, self._win_du = w[s:], f[s:], phi, du
        self._win_C = C
        gdt = self.grid.interp("g", imu.t[lo:hi] - 0.5 * dt) * dt[:, None]
        self._win_DG = np.hstack([np.einsum("nij,nj->ni", C[:-1], du), gdt])
        self._cref_cache = None

    def _on_imu_dropped(self, cut: int) -> None:
        lo, hi = self._win
        self._win = (lo - cut, hi - cut)

    def _cref(self, t: float) -> np.ndarray:
        """Reference-frame attitude ``C(t)`` at a time inside a sample of the window.

        The sample's rotation increment is split linearly in time, as the per-sample path
        splits a sample at a frame stamp.
        """
        cache = self._cref_cache
        if cache is not None and cache[0] == t:
            return cache[1]
        m = min(self.imu.index(t), len(self.imu) - 1)
        j = m - self._win[0]
        a = (t - (self.imu.t[m] - self._win_dt[j])) / self._win_dt[j]
        C = self._win_C[j] @ so3_exp(a * self._win_phi[j])
        self._cref_cache = (t, C)
        return C

    def propagate(self, t_target: float) -> None:
        """Propagate the nominal state and the covariance to ``t_target`` (relative s).

        Everything per IMU sample is computed vectorized once per *reference window*
        (:meth:`_build_window`, under the θ̂ of the time it is built, θ_w).  Per star frame,
        with ``Q = R̂(t_a) C(t_a)ᵀ`` mapping that frame onto the current nominal, the sums
        over the samples since the last frame are a handful of matrix products:

        * nominal: ``R̂(t_b) = Exp(Φ_φθ δθ) Q C(t_b)``, ``v̂(t_b) = v̂(t_a) + Q Σ C Δu + Φ_vθ δθ +
          Σ g Δt``, ``r̂`` likewise with the trapezoid weights, ``δθ = θ̂ − θ_w``: first order
          in the change of the sensor parameters since the window was built; a correction
          above ``fast_propagation_max_rad`` rebuilds the window under the current θ̂.
        * error-state transition Φ over the interval, from the same sums (φ̇ has no φ term
          and δθ is constant between frames up to the Gauss–Markov decay, so summing the
          per-sample transitions is the exact discretisation); ``P ← Φ P Φᵀ + Q_d`` once.

        The per-sample path (:meth:`_propagate_samples`, ``exact_propagation``) is kept as
        the reference (test_fast_propagation_matches_per_sample).
        """
        if t_target <= self.t:
            if t_target < self.t - 1e-9:
                raise ModelError("cannot propagate backwards in time")
            return
        k = self._k
        m = self.imu.index(t_target)
        if m >= len(self.imu):
            raise NoImuError()
        if self.config.exact_propagation:
            self._propagate_samples(t_target, k, m)
            return
        lo, hi = self._win
        if k < lo or m >= hi:
            # a new window of the reference strapdown, from the current sample on
            width = max(int(round(self.config.reference_window_s / self.nominal_dt)),
                        2 * (m - k + 2))
            self._build_window(k, min(k + width, len(self.imu)))
        self._propagate_window(t_target, k, m)

    def _propagate_window(self, t_target: float, k: int, m: int) -> None:
        """:meth:`propagate` over samples ``k..m`` of the current reference window."""
        ta, tb = self.t, t_target
        lo = self._win[0]
        j, mj = k - lo, m - lo  # window rows
        ends = self.imu.t[k:m + 1].copy()
        ends[-1] = tb
        n = len(ends)
        dts = np.empty(n)
        dts[0] = ends[0] - ta
        np.subtract(ends[1:], ends[:-1], out=dts[1:])
        frac = dts / self._win_dt[j:mj + 1]
        T = tb - ta
        W = np.empty((2, n))  # weights: 1 (sums), trapezoid weight of δv in δr
        W[0] = 1.0
        np.subtract(tb, ends, out=W[1])
        W[1] += 0.5 * dts
        Ca, Cb = self._cref(ta), self._cref(tb)
        Q = self.R_i_b @ Ca.T
        # specific-force and gravitation increments in the reference frame; the first
        # (partial) sample starts at t_a
        DG = self._win_DG[j:mj + 1] * frac[:, None]
        DG[0, :3] = (Ca @ self._win_du[j]) * frac[0]
        sums = W @ DG  # rows: Σ, Σ rem; columns: specific force, gravitation
        QD = Q @ sums[:, :3].T  # (3, 2)
        Pe = self.P_est
        ia, it, iv, ir = self.ia, self.it, self.iv, self.ir
        Phi = self._Phi
        F_b = None
        if self.model.size:
            Gg, Ga = self._win_G
            C_start = self._win_C[j:mj + 1].copy()
            C_start[0] = Ca
            # a rate error δω over a sample rotates the attitude by R_start J_l(φ) δω Δt =
            # R_mid δω Δt to first order in the sample's rotation φ
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
            F = np.empty((3, 3, self.model.size))  # ∂(attitude, velocity, position)/∂θ
            F[0] = YZ[0].reshape(3, Kg) @ Gg
            F[1:] = Za_sums @ Ga - Xc @ Gg
            F = Q @ F  # inertial
            corr = F @ (self.theta - self._win_theta)  # first-order nominal corrections
            if corr[0] @ corr[0] > self.config.fast_propagation_max_rad ** 2:
                # θ moved too far from the window's reference for a first-order correction:
                # a new (short) window under the current θ, then corr = 0
                self.reference_rebuilds += 1
                width = max(int(round(1.0 / self.nominal_dt)) * 10, 2 * (m - k + 2))
                self._build_window(k, min(k + width, len(self.imu)))
                self._propagate_window(t_target, k, m)
                return
            Phi[ia, it] = F[0][:, :Pe]
            Phi[iv.start:ir.stop, it] = F[1:, :, :Pe].reshape(6, Pe)
            Phi[self._diag_it] = np.exp(-T * self._inv_tau)
            if self.n_consider:
                F_b = np.zeros((self.N, self.n_consider))
                F_b[ia] = F[0][:, Pe:]
                F_b[iv.start:ir.stop] = F[1:, :, Pe:].reshape(6, -1)
            dvr = QD.T + corr[1:]  # specific-force δv and its δr share, with corrections
            self.R_i_b = so3_exp(corr[0]) @ Q @ Cb
        else:
            dvr = QD.T
            self.R_i_b = Q @ Cb
        Phi[iv.start:ir.stop, ia] = -skew(dvr).reshape(6, 3)
        Phi[ir, iv] = T * np.eye(3)
        self.position = self.position + self.velocity * T + dvr[1] + sums[1, 3:]
        self.velocity = self.velocity + dvr[0] + sums[0, 3:]
        self._propagate_covariance(Phi, F_b, T, k, m, ta, tb)
        self.t = t_target
        self._k = m
        self._omega_stale = True  # the corrected rate of sample m, when next needed

    def _propagate_covariance(self, Phi: np.ndarray, F_b: np.ndarray | None, T: float,
                              k: int, m: int, ta: float, tb: float) -> None:
        """``P ← Φ P Φᵀ + Q_d`` over an interval of length T, then the bridging inflation."""
        q1, q2, q3, gm2, itau2 = self._qd
        q = (q1 + (q2 + q3 * T) * T) * T + gm2 * -np.expm1(-T * itau2)
        self.state.propagate(Phi, (self._qd_index, q), F_b)
        self._inflate_bridged(k, m, ta, tb)

    def _propagate_samples(self, t_target: float, k: int, m: int) -> None:
        """Per-sample propagation under the current θ (the reference for :meth:`propagate`)."""
        imu = self.imu
        ends = np.concatenate([imu.t[k:m], [t_target]])
        starts = np.concatenate([[self.t], imu.t[k:m]])
        dts = ends - starts
        k0 = max(k - 1, 0)
        full = self._sample_dt(k0, m + 1)
        w_hat = self._corrected(imu.w[k0:m + 1], Stage.GYRO)
        f_hat = self._corrected(imu.f[k0:m + 1], Stage.ACCEL)
        s = k - k0
        frac = (dts / full[s:])[:, None]
        phi = attitude_increments(w_hat, full, coning=True)[s:] * frac
        du = velocity_increments(w_hat, f_hat, full, sculling=True)[s:] * frac
        w_hat, f_hat = w_hat[s:], f_hat[s:]
        q = np.empty((len(phi) + 1, 4))
        q[0] = quat_from_matrix(self.R_i_b)
        q[1:] = quat_from_rotvec(phi)
        R_all = quat_to_matrix(quat_cumprod(q))  # (n+1): start, then interval ends
        R_start, R_end = R_all[:-1], R_all[1:]
        dv_i = np.einsum("nij,nj->ni", R_start, du)  # specific-force increments, inertial
        g = self.grid.interp("g", ends - 0.5 * dts)
        v_ends = self.velocity + np.cumsum(dv_i + g * dts[:, None], axis=0)
        v_prev = np.vstack([self.velocity[None, :], v_ends[:-1]])
        T = float(ends[-1] - self.t)
        self.position = self.position + np.sum(0.5 * (v_prev + v_ends) * dts[:, None], axis=0)
        self.velocity = v_ends[-1]
        N, Pe = self.N, self.P_est
        iv, ia, it, ir = self.iv, self.ia, self.it, self.ir
        Phi = np.eye(N)
        S = skew(dv_i)  # (n, 3, 3)
        rem = (ends[-1] - ends) + 0.5 * dts  # weight of each δv increment in δr
        Phi[iv, ia] = -np.sum(S, axis=0)
        Phi[ir, ia] = -np.einsum("n,nij->ij", rem, S)
        Phi[ir, iv] = T * np.eye(3)
        F_b = None
        if self.model.size:
            Gg = self._per_sample_G(Stage.GYRO, w_hat)
            Ga = self._per_sample_G(Stage.ACCEL, f_hat)
            R_mid = 0.5 * (R_start + R_end)  # first order in the sample rotation (J_l)
            A = np.einsum("nij,njp,n->nip", R_mid, Gg, dts)  # φ increments per δθ
            C = np.cumsum(A, axis=0)
            C_prev = np.concatenate([np.zeros((1, 3, self.model.size)), C[:-1]], axis=0)
            B = np.einsum("nij,njp,n->nip", R_start, Ga, dts)
            inc = -np.einsum("nij,njp->nip", S, C_prev) + B  # δv increments per δθ
            F = np.stack([C[-1], np.sum(inc, axis=0), np.einsum("n,nip->ip", rem, inc)])
            Phi[ia, it], Phi[iv, it], Phi[ir, it] = F[0, :, :Pe], F[1, :, :Pe], F[2, :, :Pe]
            Phi[it, it] = np.diag(np.where(np.isfinite(self.tau), np.exp(-T / self.tau), 1.0))
            if self.n_consider:
                F_b = np.zeros((N, self.n_consider))
                F_b[ia], F_b[iv], F_b[ir] = F[0, :, Pe:], F[1, :, Pe:], F[2, :, Pe:]
        self._propagate_covariance(Phi, F_b, T, k, m, self.t, t_target)
        self.R_i_b = R_end[-1]
        self.omega = w_hat[-1]
        self.t = t_target
        self._k = m

    def _per_sample_G(self, stage: Stage, x_hat: np.ndarray) -> np.ndarray:
        """Per-sample ∂(corrected)/∂θ = −(I+E)⁻¹ (∂b/∂θ + ∂E/∂θ x̂), shape (n, 3, P_all)."""
        _, A, Gam = self._sensor(stage)
        n, P = len(x_hat), self.model.size
        G = np.broadcast_to(Gam[:3], (n, 3, P)).copy()
        if len(Gam) > 3:
            G += np.einsum("nj,ijp->nip", x_hat, Gam[3:].reshape(3, 3, P))
        return G

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
        f_b = self._corrected(imu.f[sel], Stage.ACCEL).mean(axis=0)
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
        dx, nis = self.state.linear_update(H, nu, R)
        self.inject(dx)
        key = "position_updates" if self.config.velocity_reference == "position" \
            else "velocity_updates"
        self.counters.add(key)
        h = self.reference_history  # emptied by the driver into its statistics
        h["t"].append(self.t0 + self.t)  # POSIX s, as the residual table
        for j, ax in enumerate("xyz"):
            h[f"nu_{ax}"].append(float(nu[j]))
        h["nis"].append(nis)


def _inv3(M: np.ndarray) -> np.ndarray:
    """Inverse of a 3×3 matrix (adjugate; the sensor matrices I + E are near the identity)."""
    (a, b, c), (d, e, f), (g, h, i) = M.tolist()
    A, B, C = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * A + b * B + c * C
    return np.array([[A, c * h - b * i, b * f - c * e],
                     [B, a * i - c * g, c * d - a * f],
                     [C, b * g - a * h, a * e - b * d]]) / det


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
