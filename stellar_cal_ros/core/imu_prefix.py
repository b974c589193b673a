"""The reference strapdown of the filters' IMU propagation, accumulated once per IMU sample.

See :class:`ImuPrefix`; :mod:`stellar_cal_ros.core.propagation` turns its rows into the
propagation over a star interval.  numpy, and with numba the block scan and the attitude
matrices compiled (:func:`~stellar_cal_ros.core.jit.quat_block_scan`,
:func:`~stellar_cal_ros.core.jit.anchored_matrices`: the same floats, a quarter of the cost).
"""

from __future__ import annotations

import math

import numpy as np

from stellar_cal_ros.core.jit import (
    HAVE_NUMBA,
    anchored_matrices,
    prefix_sample_rows,
    quat_block_scan,
)
from stellar_cal_ros.core.rotation import quat_from_rotvec, so3_exp
from stellar_cal_ros.core.strapdown import _quat_multiply_soa, _so3_integral_coefficients

_BLOCK = 32  # samples per block of the prefix's attitude products (see ImuPrefix)
_CHUNK = 16384  # samples per piece of a long extension (cache)
_SMALL = 8  # extensions of up to this many samples take the scalar path (live use)
_STALE_DQ = np.zeros((0, 4))  # block_dq while _lv holds the partial block
_EYE = np.eye(3)  # (prefix_sample_rows' A without one)
_NO_ROWS, _NO_VEC = np.zeros((0, 3)), np.zeros(3)  # (... and its rows without accelerometer)
_PREFIX_ROWS = {  # per-sample arrays of ImuPrefix: trailing shape, dtype
    "tp": ((), np.float64), "w_hat": ((3,), np.float64), "C": ((3, 3), np.float64),
    "phi": ((3,), np.float64), "slope": ((3,), np.float64),
}
_ACCEL_ROWS = {"f_hat": ((3,), np.float64), "du": ((3,), np.float64),
               "gdt": ((3,), np.float64)}
_BOUNDARY = ("tp", "C")  # n + 1 rows (sample boundaries); the others n rows (samples)


class ImuPrefix:
    """The reference strapdown: attitude (and specific-force increments) per IMU sample.

    Under the sensor corrections of reference parameters ``θ_ref`` (the bias ``b`` and
    ``A = (I + E)⁻¹`` of the gyro, and of the accelerometer when ``accel`` is given), per
    sample ``j`` (the interval ``(tp_j, tp_{j+1}]`` ending at its stamp): the corrected rate
    ``w_hat``, the rotation increment ``phi`` (coning-corrected) and ``C_j``, the body
    attitude at ``tp_j`` relative to the start of the reference (``C_{j+1} = C_j
    Exp(phi_j)``); with an accelerometer also the corrected specific force ``f_hat``, its
    velocity increment ``du`` in the body frame at the sample start (rotation and sculling
    compensated, :func:`~stellar_cal_ros.core.strapdown.velocity_increments`) and the
    gravitation increment ``gdt = g(mid) Δt`` (``gravity(t)``, a function of time only).
    Over any interval the attitude change is ``C(t_a)ᵀ C(t_b)``: two lookups
    (:meth:`at`), and every sum the propagation needs is a sum of these rows.

    Inside a sample, :meth:`at` takes the rate as linear through the sample's and the
    previous sample's mean rates (the contract's samples are means over their interval):
    ``slope_j`` is that line's change over the sample times its length
    (:func:`sample_slopes`), and the rotation to a fraction ``a`` of the sample is
    :func:`in_sample_rotvec` (second order; holding the sample's mean rate, the first-order
    split, errs by ``ω̇ Δt² a (1 − a) / 2``: 0.11" RMS on the swaying scenario at 100 Hz,
    ``benchmarks/insample_attitude.py``).

    The first sample of a reference takes its coning and sculling terms and its slope from
    ``start`` (the end time, rotation and velocity increments of the sample before it,
    corrected alike, and optionally its corrected rate and length), or from nothing at the
    start of the data (no slope: the first-order split).

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

    def __init__(self, nominal_dt: float, b: np.ndarray, A: np.ndarray | None = None, *,
                 accel: tuple[np.ndarray, np.ndarray | None] | None = None,
                 gravity=None, base: int = 0,
                 start: tuple | None = None) -> None:
        self.nominal_dt = float(nominal_dt)
        self.b = np.asarray(b, dtype=float).copy()
        self.A = None if A is None else np.asarray(A, dtype=float).copy()
        self.has_accel = accel is not None
        self.b_a, self.A_a = (None, None) if accel is None else (
            np.asarray(accel[0], dtype=float).copy(),
            None if accel[1] is None else np.asarray(accel[1], dtype=float).copy())
        self.gravity = gravity
        self.n = 0  # samples held
        self.base = int(base)  # absolute index of the first sample held
        self._at_cache: tuple[tuple[tuple[int, float], np.ndarray], ...] = \
            (((-1, 0.0), np.eye(3)),) * 2  # at(): ((absolute sample, t), C)
        self.t_end = -np.inf
        self.dtheta_last = np.zeros(3)  # for the coning term of the next sample
        self.dv_last = np.zeros(3)  # for the sculling term of the next sample
        self.w_last = np.zeros(3)  # corrected rate of the previous sample (its slope)
        self.dt_last = 0.0  # length of the previous sample; 0: none (no slope)
        self.t_start = None if start is None else float(start[0])
        if start is not None:
            self.dtheta_last = np.asarray(start[1], dtype=float).copy()
            self.dv_last = np.asarray(start[2], dtype=float).copy()
            if len(start) > 3:
                self.w_last = np.asarray(start[3], dtype=float).copy()
                self.dt_last = float(start[4])
        self.anchor = np.array([0.0, 0.0, 0.0, 1.0])  # attitude at the current block's start
        self.block_dq = np.zeros((0, 4))  # increments of the current (partial) block
        # scan levels of the current partial block for the scalar path: one entry per
        # position, each the 6 levels (increment, then after each of the 5 scan steps) as
        # 4 floats; None: not known (after load_state), rebuilt from block_dq when needed
        self._lv: list[list[list[float]]] | None = []
        # Storage with spare capacity (amortized appends, drops without copies); the
        # public arrays are views: tp, C have n + 1 rows (boundaries), the others n rows
        # (samples).
        self._lo = 0
        self._fields = dict(_PREFIX_ROWS, **(_ACCEL_ROWS if self.has_accel else {}))
        self._buf = {k: np.zeros((1,) + shape, dtype=dt)
                     for k, (shape, dt) in self._fields.items()}
        self._buf["C"][0] = np.eye(3)
        self._views()

    @property
    def end(self) -> int:
        """Absolute index of the first sample not held."""
        return self.base + self.n

    def _views(self) -> None:
        lo, n, buf = self._lo, self.n, self._buf
        for k in self._fields:
            setattr(self, k, buf[k][lo:lo + n + (1 if k in _BOUNDARY else 0)])

    def _reserve(self, m: int) -> None:
        """Room for m more samples: compact or grow the buffers."""
        rows = self.n + 1 + m
        cap = len(self._buf["tp"])
        if self._lo + rows <= cap:
            return
        new_cap = rows if self.n == 0 else max(2 * rows, 1024)
        lo, n = self._lo, self.n
        for k, (shape, dt) in self._fields.items():
            old = self._buf[k]
            arr = np.zeros((new_cap,) + shape, dtype=dt)
            arr[:n + 1] = old[lo:lo + n + 1]
            self._buf[k] = arr
        self._lo = 0

    def extend(self, imu_t: np.ndarray, imu_w: np.ndarray, imu_f: np.ndarray | None = None
               ) -> None:
        """Append samples (stamps increasing, after the last one held; ``imu_f`` with accel)."""
        m = len(imu_t)
        if m == 0:
            return
        if m > _CHUNK:  # cache-sized pieces; the result does not depend on the split
            self._reserve(m)
            for a in range(0, m, _CHUNK):
                self.extend(imu_t[a:a + _CHUNK], imu_w[a:a + _CHUNK],
                            None if imu_f is None else imu_f[a:a + _CHUNK])
            return
        first = self.n == 0
        if m <= _SMALL and not first:
            self._extend_small(imu_t, imu_w, imu_f)
            return
        if first:
            t_prev = imu_t[0] - self.nominal_dt if self.t_start is None else self.t_start
        else:
            t_prev = self.tp[-1]
        self._reserve(m)
        buf, i0 = self._buf, self._lo + self.n  # row of the last boundary held
        if HAVE_NUMBA:  # the per-sample rows in one compiled pass (the same floats)
            dt, dth = self._sample_rows(i0, imu_t, imu_w, imu_f, t_prev)
            phi = buf["phi"][i0:i0 + m]
        else:
            dt = np.diff(np.concatenate([[t_prev], imu_t]))
            d = _corrected(imu_w, self.b, self.A)
            dth = d * dt[:, None]
            prev = np.concatenate([self.dtheta_last[None], dth[:-1]])
            phi = dth + _cross_rows(prev, dth) / 12.0
        block_dq = self._partial_dq()
        seq = np.concatenate([block_dq, quat_from_rotvec(phi)])
        r, old = len(seq), len(block_dq)
        nb = -(-r // _BLOCK)
        pad = np.zeros((nb * _BLOCK, 4))
        pad[:, 3] = 1.0
        pad[:r] = seq
        levels = np.empty((6, 4, _BLOCK)) if r % _BLOCK else None
        L = _scan(pad.reshape(nb, _BLOCK, 4), levels)  # (4, nb, B)
        # the blocks' anchors in Python floats (the same operations as on arrays; a
        # 4 096-sample extension has 128 of them)
        anchors = np.empty((4, nb))
        a = _anchor_chain(self.anchor.tolist(), L[:, :, -1].T.tolist(),
                          nb if r % _BLOCK == 0 else nb - 1, anchors)
        if first:
            buf["tp"][i0] = t_prev
        buf["tp"][i0 + 1:i0 + m + 1] = imu_t
        if not HAVE_NUMBA:
            buf["w_hat"][i0:i0 + m] = d
            buf["phi"][i0:i0 + m] = phi
            self._slope_rows(i0, d, dt)
        _attitudes(anchors, L, old, r, buf["C"][i0 + 1:i0 + m + 1])
        if self.has_accel and not HAVE_NUMBA:
            self._accel_rows(i0, imu_t, dt, dth, imu_f)
        self.n += m
        self.t_end = float(imu_t[-1])
        self.dtheta_last = dth[-1].copy()
        self.anchor = np.array(a)
        self.block_dq = seq[(nb - 1) * _BLOCK:].copy() if r % _BLOCK else np.zeros((0, 4))
        # the scan levels of the partial block, per position (for _extend_small)
        self._lv = levels[:, :, :r % _BLOCK].transpose(2, 0, 1).tolist() \
            if levels is not None else []
        self._views()

    def _sample_rows(self, i0: int, imu_t: np.ndarray, imu_w: np.ndarray,
                     imu_f: np.ndarray | None, t_prev: float) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`extend`'s per-sample rows at ``i0`` in one compiled pass; ``(dt, dth)``.

        :func:`~stellar_cal_ros.core.jit.prefix_sample_rows` writes ``w_hat``, ``phi``,
        ``slope`` (and ``f_hat``, ``du``) into the buffers, the same floats as
        :func:`_corrected`, the coning term, :meth:`_slope_rows` and :meth:`_accel_rows`;
        the gravitation rows (``gravity``, a function of time) and the rare samples whose
        increment is 1e-2 rad or more (``du`` from the closed forms) in numpy here.  Updates
        the slope's and the sculling's previous sample (not ``dtheta_last``).
        """
        m = len(imu_t)
        buf = self._buf
        imu_t = np.ascontiguousarray(imu_t, dtype=float)
        imu_w = np.ascontiguousarray(imu_w, dtype=float).reshape(m, 3)
        dt, dth = np.empty(m), np.empty((m, 3))
        rows = slice(i0, i0 + m)
        accel = self.has_accel
        if accel:
            imu_f = np.ascontiguousarray(imu_f, dtype=float).reshape(m, 3)
            f_hat, du, dv = buf["f_hat"][rows], buf["du"][rows], np.empty((m, 3))
            b_a, A_a = self.b_a, self.A_a
        else:
            imu_f, f_hat, du, dv = _NO_ROWS, _NO_ROWS, _NO_ROWS, _NO_ROWS
            b_a, A_a = _NO_VEC, None
        big = prefix_sample_rows(
            imu_t, imu_w, imu_f, float(t_prev), self.b, _EYE if self.A is None else self.A,
            self.A is not None, b_a, _EYE if A_a is None else A_a, A_a is not None,
            self.dtheta_last, self.w_last, float(self.dt_last), self.dv_last, accel, dt, dth,
            buf["w_hat"][rows], buf["phi"][rows], buf["slope"][rows], f_hat, du, dv)
        self.w_last = buf["w_hat"][i0 + m - 1].copy()
        self.dt_last = float(dt[-1])
        if accel:
            if big:  # (the closed forms: numpy's sin and cos)
                du[:] = sculled_increments(
                    dth, dv, np.concatenate([self.dtheta_last[None], dth[:-1]]),
                    np.concatenate([self.dv_last[None], dv[:-1]]))
            buf["gdt"][rows] = self.gravity(imu_t - 0.5 * dt) * dt[:, None]
            self.dv_last = dv[-1].copy()
        return dt, dth

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

    def _slope_rows(self, i0: int, w: np.ndarray, dt: np.ndarray) -> None:
        """The ``slope`` rows of the samples written at ``i0`` (elementwise: any batch size)."""
        w_prev = np.concatenate([self.w_last[None], w[:-1]])
        dt_prev = np.concatenate([[self.dt_last], dt[:-1]])
        self._buf["slope"][i0:i0 + len(dt)] = sample_slopes(w, dt, w_prev, dt_prev)
        self.w_last = w[-1].copy()
        self.dt_last = float(dt[-1])

    def _accel_rows(self, i0: int, imu_t: np.ndarray, dt: np.ndarray, dth: np.ndarray,
                    imu_f: np.ndarray) -> None:
        """The specific-force rows of the samples written at ``i0``.

        Elementwise: the same values for any batch size.
        """
        fa = _corrected(np.asarray(imu_f, dtype=float).reshape(-1, 3), self.b_a, self.A_a)
        dv = fa * dt[:, None]
        dth_prev = np.concatenate([self.dtheta_last[None], dth[:-1]])
        dv_prev = np.concatenate([self.dv_last[None], dv[:-1]])
        m = len(dt)
        buf = self._buf
        buf["f_hat"][i0:i0 + m] = fa
        buf["du"][i0:i0 + m] = sculled_increments(dth, dv, dth_prev, dv_prev)
        buf["gdt"][i0:i0 + m] = self.gravity(imu_t - 0.5 * dt) * dt[:, None]
        self.dv_last = dv[-1].copy()

    def _extend_small(self, imu_t: np.ndarray, imu_w: np.ndarray,
                      imu_f: np.ndarray | None = None) -> None:
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
        rows = []
        phis = np.empty((m, 3))
        dths = np.empty((m, 3))
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
            dths[j] = (hx, hy, hz)
            rows.append((t, dt, dx, dy, dz))
            px, py, pz = hx, hy, hz
            t_prev = t
        dqs = quat_from_rotvec(phis).tolist()
        lv = self._levels()
        anchor = self.anchor.tolist()
        ax, ay, az, aw = anchor
        for j in range(m):
            t, dt, dx, dy, dz = rows[j]
            i = i0 + j
            levels = _scan_position(lv, dqs[j])
            x, y, z, w = levels[-1]
            nrm = math.sqrt(x * x + y * y + z * z + w * w)
            x, y, z, w = x / nrm, y / nrm, z / nrm, w / nrm
            if len(lv) == _BLOCK - 1:  # the block is complete: next anchor, new block
                anchor = _anchor_chain(anchor, [(x, y, z, w)], 1)
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
            buf["tp"][i + 1] = t
            buf["w_hat"][i] = (dx, dy, dz)
            buf["C"][i + 1].flat = C
        buf["phi"][i0:i0 + m] = phis
        dts = np.array([r[1] for r in rows])
        self._slope_rows(i0, np.array([r[2:] for r in rows]), dts)
        if self.has_accel:
            self._accel_rows(i0, np.asarray(ts), dts, dths, imu_f)
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

    _SCALARS = ("nominal_dt", "b", "n", "base", "t_end", "dtheta_last", "dv_last", "w_last",
                "dt_last", "anchor")

    def state(self) -> dict[str, np.ndarray]:
        """Everything that defines the prefix, as arrays (checkpoints; not ``gravity``)."""
        out = {k: np.asarray(getattr(self, k)).copy() for k in self._fields}
        for k in self._SCALARS:
            out[k] = np.asarray(getattr(self, k)).copy()
        out["block_dq"] = self._partial_dq().copy()
        for k in ("A", "b_a", "A_a", "t_start"):
            if getattr(self, k) is not None:
                out[k] = np.asarray(getattr(self, k)).copy()
        return out

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        """Restore :meth:`state` (into a prefix built with the same accelerometer setting)."""
        for k, v in state.items():
            if k in self._fields:
                continue
            v = np.array(v)
            setattr(self, k, v.item() if v.ndim == 0 else v)
        for k in ("A", "b_a", "A_a", "t_start"):
            if k not in state:
                setattr(self, k, None)
        self.n, self.base = int(self.n), int(self.base)
        self._lv = None  # rebuilt from block_dq by the scalar path when needed
        self._at_cache = (((-1, 0.0), np.eye(3)),) * 2
        self._lo = 0
        self._buf = {}
        for k, (shape, dt) in self._fields.items():
            rows = self.n + (1 if k in _BOUNDARY else 0)
            arr = np.zeros((self.n + 1,) + shape, dtype=dt)
            arr[:rows] = state[k]
            self._buf[k] = arr
        self._views()

    def at(self, m: int, t: float) -> np.ndarray:
        """``C(t)`` for ``t`` in row ``m`` (:func:`in_sample_rotvec` of its fraction).

        The last two results are kept (by absolute sample and time): a star frame's
        propagation starts where the previous one ended.
        """
        key = (self.base + m, t)
        for k, C in self._at_cache:
            if k == key:
                return C
        a = (t - self.tp[m]) / (self.tp[m + 1] - self.tp[m])
        C = self.C[m] @ so3_exp(in_sample_rotvec(a, self.phi[m], self.slope[m])) if a > 0.0 \
            else self.C[m].copy()
        self._at_cache = (self._at_cache[-1], (key, C))
        return C


def in_sample_rotvec(a, phi, slope):
    """Rotation vector from a sample's start to the fraction ``a`` (0..1) of its interval.

    ``a φ + a (a − 1) / 2 · slope``: the rate linear in time, its mean over the sample the
    sample's (``φ`` the sample's increment, :func:`sample_slopes` the line's change), so
    the whole increment at ``a = 1`` (continuous at the sample boundaries).  The one formula
    of the filters' in-sample attitude: the compiled frame step compiles this function.
    """
    return a * phi + (0.5 * a * (a - 1.0)) * slope


def sample_slopes(w: np.ndarray, dt: np.ndarray, w_prev: np.ndarray,
                  dt_prev: np.ndarray) -> np.ndarray:
    """Per sample (n, 3): the change of the rate over the sample times its length.

    The rate linear through the mean rates ``w_prev`` and ``w`` of two consecutive samples
    (lengths ``dt_prev``, ``dt``; their means sit at the intervals' midpoints) changes by
    ``k = (w − w_prev) / ((dt + dt_prev) / 2)`` per second; the row is ``k dt²`` (the
    simulator's and the contract's samples are interval means: ``benchmarks/
    insample_attitude.py`` checks the result against the truth).  0 where there is no
    previous sample (``dt_prev`` 0).  Elementwise: the same values for any batch size.
    """
    k = 2.0 * dt * dt / (dt + dt_prev)
    out = (w - w_prev) * k[:, None]
    out[~(dt_prev > 0.0)] = 0.0
    return out


def _corrected(x: np.ndarray, b: np.ndarray, A: np.ndarray | None) -> np.ndarray:
    """``A (x − b)`` per row, with explicit sums (the same rounding for any batch size)."""
    d = x - b
    if A is None:
        return d
    return np.stack([d[:, 0] * A[i, 0] + d[:, 1] * A[i, 1] + d[:, 2] * A[i, 2]
                     for i in range(3)], axis=1)


def sculled_increments(dth: np.ndarray, dv: np.ndarray, dth_prev: np.ndarray,
                       dv_prev: np.ndarray) -> np.ndarray:
    """Velocity increments in the body frame at each sample's start (n, 3).

    :func:`~stellar_cal_ros.core.strapdown.velocity_increments` with the previous sample's
    increments given (elementwise: the same values for any batch size).
    """
    p = np.sqrt(dth[:, 0] * dth[:, 0] + dth[:, 1] * dth[:, 1] + dth[:, 2] * dth[:, 2])
    a, b = _so3_integral_coefficients(p)
    c1 = _cross_rows(dth, dv)
    du = dv + a[:, None] * c1 + b[:, None] * _cross_rows(dth, c1)
    du += (_cross_rows(dth_prev, dv) + _cross_rows(dv_prev, dth)) / 12.0
    return du


def _cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross(a, b)`` of (n, 3) rows: the same products and differences, less overhead."""
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    out = np.empty(a.shape)
    np.subtract(a1 * b2, a2 * b1, out=out[:, 0])
    np.subtract(a2 * b0, a0 * b2, out=out[:, 1])
    np.subtract(a0 * b1, a1 * b0, out=out[:, 2])
    return out


_NO_LEVELS = np.empty((0, 4, _BLOCK))  # quat_block_scan's "no levels wanted"


def _scan(dq: np.ndarray, levels: np.ndarray | None) -> np.ndarray:
    """:func:`_block_scan`, compiled where numba is (the same floats)."""
    if HAVE_NUMBA:
        return quat_block_scan(dq, _NO_LEVELS if levels is None else levels)
    return _block_scan(dq, levels)


def _attitudes(anchors: np.ndarray, L: np.ndarray, old: int, r: int, C: np.ndarray) -> None:
    """The attitude matrices of scan positions ``old .. r − 1`` into ``C``.

    Each block's anchor (``anchors`` (4, nb)) times its scan values ``L`` (4, nb, B);
    compiled where numba is (the same floats).
    """
    if HAVE_NUMBA:
        anchored_matrices(anchors, L, old, r, C)
        return
    q = np.empty_like(L)
    _quat_multiply_soa(anchors[:, :, None], L, q, np.empty(L.shape[1:]))
    _quat_soa_to_matrix(q.reshape(4, -1)[:, old:r], C)


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


def _anchor_chain(a: list[float], ends: list[list[float]], k: int,
                  out: np.ndarray | None = None) -> list[float]:
    """The anchor after ``k`` blocks: ``a ← a ⊗ ends[j]`` normalized, ``j < k`` (scalar-last).

    Python floats (a 4 096-sample extension has 128 blocks: a Python loop is cheaper than
    numpy calls); with ``out`` (4, nb) also the anchor at each block's start, ``out[:, j]``
    the one before the product with ``ends[j]``.
    """
    px, py, pz, pw = a
    rows = [(px, py, pz, pw)]
    for j in range(k):
        qx, qy, qz, qw = ends[j]
        x = pw * qx + px * qw + py * qz - pz * qy
        y = pw * qy - px * qz + py * qw + pz * qx
        z = pw * qz + px * qy - py * qx + pz * qw
        w = pw * qw - px * qx - py * qy - pz * qz
        n = (x * x + y * y + z * z + w * w) ** 0.5
        px, py, pz, pw = x / n, y / n, z / n, w / n
        rows.append((px, py, pz, pw))
    if out is not None:
        out[:] = np.array(rows[:out.shape[1]]).T
    return [px, py, pz, pw]


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

