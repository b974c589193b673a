"""The filters' one IMU propagation: attitude, and velocity and position where carried.

Over the samples between two star frames (numpy only).

Every Kalman filter of the package (PSCE, swaying-base, traditional) propagates with
:class:`ImuPropagation`; the method only turns its result into its own transition (which
blocks, which process noise).

Sensor model (:class:`SensorModel`, the one sensor Jacobian ``G``): a gyro or accelerometer
reading ``x`` is corrected as ``x̂ = (I + E)⁻¹ (x − b)`` with the bias ``b(θ)`` and error
matrix ``E(θ)`` of the model's sensor effects, and

    G = ∂x̂/∂θ = −(I + E)⁻¹ (∂b/∂θ + ∂E/∂θ x̂) = [I, x̂ᵀ ⊗ I] Γ,

``Γ`` (3 or 12, P) being ``−(I + E)⁻¹ ∂b/∂θ`` stacked on ``−(I + E)⁻¹ ∂E/∂θ`` (the last
only when an effect scales the sensor).

Propagation over ``(t_a, t_b]`` (:meth:`ImuPropagation.step`), from the rows of an
:class:`~stellar_cal_ros.core.imu_prefix.ImuPrefix` (the reference strapdown under the
parameters ``θ_ref`` it was built with) and ``Q = R̂(t_a) C(t_a)ᵀ`` mapping its frame onto
the current nominal attitude:

* attitude ``R̂(t_b) = Exp(F_φ δθ) Q C(t_b)`` with ``δθ = θ̂ − θ_ref`` and
  ``F_φ = Q Σ_j C_mid,j [I, ŵ_jᵀ ⊗ I] Δt_j Γ_g`` the attitude error per parameter error
  (``φ̇ = R̂ G_g δθ``, summed exactly between frames since φ̇ has no φ term; ``C_mid`` the
  mean of the sample's end attitudes: a rate error over a sample rotates the attitude by
  ``R_start J_l(φ) δω Δt``, the midpoint to first order).  The attitude at ``t_a`` and
  ``t_b`` inside their samples is second order (:meth:`ImuPrefix.at`: the rate linear
  through the sample's and the previous sample's means); ``F`` weights the partial
  samples by their length alone: exact for a bias (the line's weights sum to the
  length), and for a scale or misalignment off by the line's share ``a (1 − a) / 2`` of
  the rate's change over one sample (~1e-5 of the column at 1 rad/s² and 100 Hz, within
  the finite-difference check of ``test/test_propagation.py``);
* with an accelerometer, velocity and position: ``v̂(t_b) = v̂(t_a) + Q Σ C Δu + Σ g Δt +
  F_v δθ``, ``r̂`` likewise with the trapezoid weights, their attitude columns
  ``−[Δv]×`` and parameter columns ``F_v, F_r`` (specific-force sensor rows, and the
  attitude error's effect on the rotated specific force).  These parameter columns take
  each sample's *start* attitude: first order in a sample's rotation ω Δt (their error is
  ~ω Δt / 2 of the column, 2e-2 at 0.6 rad/s and 100 Hz, 1e-4 at a ship's sway), kept
  as the swaying-base filter has always had them; the midpoint forms (sensor rows at
  ``C_mid``, the attitude error at each segment's middle) are second order, and change the
  wrong-reference ``traditional`` filter's installation by up to 0.2 σ on Zhang's bags;
* the corrections ``F δθ`` are first order in the change of the sensor parameters since the
  reference was built.  The *fast path* is this property of the propagation: a reference
  built once serves every interval while the first-order attitude correction stays below
  ``max_correction_rad`` (the neglected second-order term is below its square) and the
  reference is younger than ``window_s``; otherwise the reference is rebuilt from the
  interval's first sample under the current θ̂ (then ``δθ = 0``: the per-sample
  propagation).  ``exact=True`` rebuilds it for every interval (the reference path).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from stellar_cal_ros.core.imu_prefix import ImuPrefix
from stellar_cal_ros.core.rotation import so3_exp

SensorFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]


def inv3(M: np.ndarray) -> np.ndarray:
    """Inverse of a 3×3 matrix (adjugate; the sensor matrices I + E are near the identity)."""
    (a, b, c), (d, e, f), (g, h, i) = M.tolist()
    A, B, C = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * A + b * B + c * C
    return np.array([[A, c * h - b * i, b * f - c * e],
                     [B, a * i - c * g, c * d - a * f],
                     [C, b * g - a * h, a * e - b * d]]) / det


class SensorModel:
    """Corrections of one IMU sensor and their Jacobian in θ (see the module docstring).

    Parameters
    ----------
    model : callable
        ``θ -> (b (3,), E (3, 3), ∂b/∂θ (3, P), ∂E/∂θ (3, 3, P))``.
    theta0 : ndarray (P,)
        Where to tabulate it.
    step : ndarray (P,)
        A step per parameter (e.g. the prior σ) to check that the model is affine in θ:
        then :meth:`at` is two small products instead of a call of ``model``.
    """

    def __init__(self, model: SensorFn, theta0: np.ndarray, step: np.ndarray) -> None:
        self.model = model
        self.theta0 = np.asarray(theta0, dtype=float).copy()
        b0, E0, Jb, JE = model(self.theta0)
        b1, E1, Jb1, JE1 = model(self.theta0 + step)
        self._affine = (b0, E0, Jb, JE) if (
            np.array_equal(Jb, Jb1) and np.array_equal(JE, JE1)
            and np.allclose(b1, b0 + Jb @ step, rtol=1e-9, atol=1e-300)
            and np.allclose(E1, E0 + JE @ step, rtol=1e-9, atol=1e-300)) else None
        self._cache: tuple[np.ndarray, tuple] | None = None  # (θ, (b, A, E, Jb, JE))
        #: an affine model whose error matrix is zero at every θ (no scale or misalignment)
        self._no_E = self._affine is not None and not (self._affine[1].any()
                                                       or self._affine[3].any())

    def _correction(self, theta: np.ndarray) -> tuple:
        theta = np.asarray(theta)
        hit = self._cache
        if hit is not None and hit[0].shape == theta.shape and (hit[0] == theta).all():
            return hit[1]  # (np.array_equal's test, without its conversions)
        if self._affine is None:
            b, E, Jb, JE = self.model(theta)
        else:
            b0, E0, Jb, JE = self._affine
            d = theta - self.theta0
            b = b0 + Jb @ d
            # E = E0 + JE d is zero then (at a finite θ): A is None, as E.any() gives
            E = None if self._no_E and np.isfinite(d).all() else E0 + JE @ d
        out = (b, inv3(np.eye(3) + E) if E is not None and E.any() else None, Jb, JE)
        self._cache = (np.array(theta, dtype=float), out)
        return out

    def at(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """``(b, A, Γ)`` at ``theta``: ``A = (I + E)⁻¹`` (None when E = 0)."""
        b, A, Jb, JE = self._correction(theta)
        P = Jb.shape[1]
        JbE = np.hstack([Jb, JE.reshape(3, -1)])
        M = -JbE if A is None else -(A @ JbE)
        G = np.concatenate([M[:, :P], M[:, P:].reshape(9, P)]) if JE.any() else M[:, :P]
        return b, A, G

    def corrected(self, x: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """Corrected readings ``(I + E)⁻¹ (x − b)`` at ``theta`` (x (3,) or (n, 3))."""
        b, A = self._correction(theta)[:2]
        return x - b if A is None else (x - b) @ A.T

    def jacobian(self, x_hat: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """Per reading ``G = [I, x̂ᵀ ⊗ I] Γ`` (n, 3, P) of corrected readings ``x_hat``."""
        G = self.at(theta)[2]
        x_hat = np.atleast_2d(x_hat)
        out = np.broadcast_to(G[:3], (len(x_hat), 3, G.shape[1])).copy()
        if len(G) > 3:
            out += np.einsum("nj,ijp->nip", x_hat, G[3:].reshape(3, 3, -1))
        return out


def sensor_rows(C: np.ndarray, x: np.ndarray, w: np.ndarray, scaled: bool) -> np.ndarray:
    """Per-segment rows ``[C, C ⊗ x̂ᵀ] w`` (n, 3, 3 or 12) that Γ turns into ∂(C x̂ w)/∂θ."""
    n = len(w)
    Z = np.empty((n, 3, 12 if scaled else 3))
    np.multiply(C, w[:, None, None], out=Z[:, :, :3])
    if scaled:
        np.multiply(Z[:, :, :3, None], x[:, None, None, :],
                    out=Z[:, :, 3:].reshape(n, 3, 3, 3))
    return Z


@dataclass
class Step:
    """The propagation over one interval (see :meth:`ImuPropagation.step`)."""

    R: np.ndarray  #: nominal attitude at t_b (3, 3)
    F: np.ndarray  #: (q, 3, P): attitude[, velocity, position] errors per θ error, inertial
    T: float  #: interval length, s
    #: (2, 3): specific-force increment of the velocity and its share of the position
    #: (inertial, first-order corrections included); None without an accelerometer
    dvr: np.ndarray | None = None
    #: (2, 3): gravitation increment of the velocity and its share of the position
    gravity: np.ndarray | None = None


class ImuPropagation:
    """The one IMU propagation of the filters (see the module docstring).

    Parameters
    ----------
    nominal_dt : float
        Nominal IMU sample interval, s.
    gyro : SensorModel
    accel : SensorModel, optional
        With it (and ``gravity``) the propagation carries velocity and position.
    gravity : callable, optional
        ``t (n,) -> (n, 3)`` gravitation at relative times, m/s².
    max_correction_rad : float
        A first-order attitude correction above this rebuilds the reference.
    window_s : float
        A reference older than this (in samples of ``nominal_dt``) is rebuilt.
    exact : bool
        Rebuild the reference for every interval (per-sample propagation under θ̂).

    The samples come from an :class:`~stellar_cal_ros.core.imu.ImuBuffer` (its indices);
    :meth:`appended` and :meth:`dropped` keep the reference rows in step with it.
    """

    def __init__(self, nominal_dt: float, gyro: SensorModel, accel: SensorModel | None = None,
                 gravity=None, max_correction_rad: float = 1e-5, window_s: float = math.inf,
                 exact: bool = False) -> None:
        self.nominal_dt = float(nominal_dt)
        self.gyro, self.accel, self.gravity = gyro, accel, gravity
        self.max_correction_rad = float(max_correction_rad)
        self.window = (max(int(round(window_s / nominal_dt)), 1)
                       if math.isfinite(window_s) else math.inf)
        self.exact = bool(exact)
        self.prefix: ImuPrefix | None = None
        self.theta_ref: np.ndarray | None = None
        self.ref_start = 0  # absolute index of the reference's first sample
        self._gamma: tuple = ()
        self.rebuilds = 0  #: references rebuilt because the correction grew too large

    # ------------------------------------------------------------------ reference
    def rebuild(self, imu, k: int, theta: np.ndarray, stop: int | None = None) -> None:
        """A new reference from sample ``k`` (to ``stop``, default all held) under ``theta``."""
        b, A, Gg = self.gyro.at(theta)
        start = None
        if k > 0:  # the sample before: the coning and sculling terms and slope of sample k
            t_prev = float(imu.t[k - 1])
            dt_prev = t_prev - imu.interval_start(k - 1)
            w_prev = self.gyro.corrected(imu.w[k - 1], theta)
            dv = self.accel.corrected(imu.f[k - 1], theta) * dt_prev if self.accel \
                else np.zeros(3)
            start = (t_prev, w_prev * dt_prev, dv, w_prev, dt_prev)
        accel = None
        if self.accel is not None:
            b_a, A_a, Ga = self.accel.at(theta)
            accel = (b_a, A_a)
            self._gamma = (Gg, Ga)
        else:
            self._gamma = (Gg,)
        self.prefix = ImuPrefix(self.nominal_dt, b, A, accel=accel, gravity=self.gravity,
                                base=imu.base + k, start=start)
        self.theta_ref = np.array(theta, dtype=float)
        self.ref_start = imu.base + k
        self._extend(imu, k, len(imu) if stop is None else stop)

    def _extend(self, imu, a: int, b: int) -> None:
        """Rows of samples ``a:b`` of ``imu``, up to the end of the reference's window.

        A sample at or past ``ref_start + window`` is never read under this reference
        (:meth:`step` rebuilds first), and the next reference computes it again: the rows
        stop there (the rows are the same floats however the extension is split).
        """
        if not self.exact and self.window != math.inf:
            b = min(b, self.ref_start + self.window - imu.base)
        if b > a:
            self.prefix.extend(imu.t[a:b], imu.w[a:b],
                               imu.f[a:b] if self.accel is not None else None)

    def appended(self, imu, first: int, theta: np.ndarray) -> None:
        """Samples ``first:`` of ``imu`` are new: extend the reference if it reaches them."""
        if self.exact:
            return  # rebuilt per interval
        if self.prefix is None:
            self.rebuild(imu, 0, theta)
        elif self.prefix.end == imu.base + first:
            self._extend(imu, first, len(imu))

    def dropped(self, imu) -> None:
        """``imu`` dropped its first samples: drop the rows before its new first one."""
        if self.prefix is not None and imu.base > self.prefix.base:
            self.prefix.drop(imu.base - self.prefix.base)

    # ------------------------------------------------------------------ propagation
    def step(self, imu, k: int, m: int, ta: float, tb: float, R_a: np.ndarray,
             theta: np.ndarray, interval=None):
        """Propagate from ``t_a`` (in sample ``k``) to ``t_b`` (in sample ``m``).

        ``R_a`` is the nominal attitude at ``t_a``; ``theta`` the current parameters.
        ``interval``: what turns the reference's rows into the result (default
        :meth:`_interval`, a :class:`Step`; the same arguments, None when the first-order
        correction is too large), e.g. a filter's compiled propagation and transition.
        """
        interval = interval or self._interval
        pre = self.prefix
        if self.exact or pre is None or imu.base + k < pre.base or \
                imu.base + m - self.ref_start >= self.window:
            self.rebuild(imu, k, theta, m + 1 if self.exact else None)
        elif pre.end <= imu.base + m:
            self._extend(imu, pre.end - imu.base, len(imu))
        out = interval(imu, k, m, ta, tb, R_a, theta)
        if out is None:  # the first-order correction is too large: rebuild under θ̂
            self.rebuilds += 1
            self.rebuild(imu, k, theta, m + 1 if self.exact else None)
            out = interval(imu, k, m, ta, tb, R_a, theta)
        return out

    def rows(self, imu, k: int, m: int) -> tuple:
        """The reference's per-sample arrays and the rows ``(j, mj)`` of samples ``k, m``.

        ``(tp, C, w_hat, phi, slope, f_hat, du, gdt, j, mj)`` (the accelerometer rows with
        one), as :meth:`_interval` reads them: for a compiled form of it.
        """
        pre = self.prefix
        off = imu.base - pre.base
        return (pre.tp, pre.C, pre.w_hat, pre.phi, pre.slope, pre.f_hat, pre.du, pre.gdt,
                k + off, m + off)

    def _interval(self, imu, k: int, m: int, ta: float, tb: float, R_a: np.ndarray,
                  theta: np.ndarray) -> Step | None:
        pre = self.prefix
        off = imu.base - pre.base
        j, mj = k + off, m + off  # rows of the reference
        ends = imu.t[k:m + 1].copy()
        ends[-1] = tb
        n = len(ends)
        dts = np.empty(n)
        dts[0] = ends[0] - ta
        np.subtract(ends[1:], ends[:-1], out=dts[1:])
        T = tb - ta
        Ca, Cb = pre.at(j, ta), pre.at(mj, tb)
        Q = R_a @ Ca.T
        Gg = self._gamma[0]
        C_start = pre.C[j:mj + 1].copy()
        C_start[0] = Ca
        # a rate error δω over a sample rotates the attitude by R_start J_l(φ) δω Δt =
        # R_mid δω Δt to first order in the sample's rotation φ
        C_mid = pre.C[j + 1:mj + 2] + C_start
        C_mid[-1] = Cb + C_start[-1]
        delta = theta - self.theta_ref
        scaled = len(Gg) > 3
        if self.accel is None:
            # Σ_j C_mid,j [1, ŵ_jᵀ] Δt_j / 2 as one product: (9, 1 or 4)
            X = np.empty((n, 4 if scaled else 1))
            X[:, 0] = 0.5 * dts
            if scaled:
                np.multiply(pre.w_hat[j:mj + 1], X[:, :1], out=X[:, 1:])
            M = (C_mid.reshape(n, 9).T @ X).reshape(3, 3, -1)
            Zsum = np.concatenate([M[:, :, 0], M[:, :, 1:].reshape(3, 9)], axis=1) \
                if scaled else M[:, :, 0]
            F = (Q @ (Zsum @ Gg))[None]
            corr = F[0] @ delta
            if corr @ corr > self.max_correction_rad ** 2:
                return None
            return Step(so3_exp(corr) @ (Q @ Cb), F, T)
        Zg = sensor_rows(C_mid, pre.w_hat[j:mj + 1], 0.5 * dts, scaled)
        Kg = Zg.shape[2]
        Ga = self._gamma[1]
        frac = dts / (pre.tp[j + 1:mj + 2] - pre.tp[j:mj + 1])
        W = np.empty((2, n))  # weights: 1 (sums), trapezoid weight of δv in δr
        W[0] = 1.0
        np.subtract(tb, ends, out=W[1])
        W[1] += 0.5 * dts
        # specific-force and gravitation increments in the reference frame (the first,
        # partial sample starts at t_a)
        DG = np.empty((n, 6))
        DG[:, :3] = np.einsum("nij,nj->ni", C_start, pre.du[j:mj + 1]) * frac[:, None]
        DG[:, 3:] = pre.gdt[j:mj + 1] * frac[:, None]
        sums = W @ DG  # rows: Σ, Σ rem; columns: specific force, gravitation
        QD = Q @ sums[:, :3].T  # (3, 2)
        # specific-force rows at each sample's start attitude and the attitude error at
        # each segment's start (first order in a sample's rotation: see the module notes)
        Za = sensor_rows(C_start, pre.f_hat[j:mj + 1], dts, len(Ga) > 3)
        Ka = Za.shape[2]
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
        F = np.empty((3, 3, Gg.shape[1]))  # ∂(attitude, velocity, position)/∂θ
        F[0] = YZ[0].reshape(3, Kg) @ Gg
        F[1:] = Za_sums @ Ga - Xc @ Gg
        F = Q @ F  # inertial
        corr = F @ delta  # first-order nominal corrections
        if corr[0] @ corr[0] > self.max_correction_rad ** 2:
            return None
        dvr = QD.T + corr[1:]  # specific-force δv and its δr share, with corrections
        return Step(so3_exp(corr[0]) @ Q @ Cb, F, T, dvr, sums[:, 3:])

    # ------------------------------------------------------------------ checkpoints
    def state(self) -> dict:
        """The reference (rows and parameters) as arrays."""
        out = {"rebuilds": np.asarray(self.rebuilds), "ref_start": np.asarray(self.ref_start)}
        if self.prefix is not None:
            out["prefix"] = self.prefix.state()
            out["theta_ref"] = self.theta_ref.copy()
        return out

    def load_state(self, state: dict) -> None:
        """Restore :meth:`state`."""
        self.rebuilds = int(state["rebuilds"])
        self.ref_start = int(state["ref_start"])
        if "prefix" not in state:
            self.prefix = None
            return
        self.theta_ref = np.array(state["theta_ref"], dtype=float)
        Gg = self.gyro.at(self.theta_ref)[2]
        self._gamma = (Gg,) if self.accel is None else (Gg, self.accel.at(self.theta_ref)[2])
        accel = None if self.accel is None else (np.zeros(3), None)
        self.prefix = ImuPrefix(self.nominal_dt, np.zeros(3), accel=accel,
                                gravity=self.gravity)
        self.prefix.load_state(state["prefix"])

