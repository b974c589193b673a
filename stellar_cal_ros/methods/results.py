"""What a filter run produces, for every method: tables, running statistics, the result.

* :data:`RESIDUAL_COLUMNS` — one per-star residual schema for every method (``t`` the
  reported frame stamp in POSIX s); :class:`TableSink` keeps the rows in memory or streams
  them to a CSV / Parquet file (memory then does not grow with the bag).
* :class:`RunStats` — running statistics over an evaluation window (the second half of the
  bag by default): innovation RMS against what the model expects, NIS per degree of freedom
  with its χ² interval, lag-1 whiteness of the frame-mean whitened innovations, and the
  prequential log-likelihood the diagnosis compares models with.  The same numbers as the
  functions of :mod:`stellar_cal_ros.diagnosis.stats` on the whole residual table, in O(1)
  memory.
* :func:`consistency` — the verdict every result YAML carries
  (``consistency: {nis_per_dof, interval, whiteness_p, verdict}``): when the model does not
  fit, the σ of the result are conditional on a wrong model and the CLI says so.
* :func:`result_calibration`, :func:`equivalent_principal_point` (:func:`boresight_pixel`,
  :func:`epp_jacobian`), :class:`ReplayResult`.
"""

from __future__ import annotations

import contextlib
import contextvars
import copy
import dataclasses
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from stellar_cal_ros.effects.base import FrameContext
from stellar_cal_ros.io.calibration import Calibration, store_estimate
from stellar_cal_ros.io.residuals import TableWriter
from stellar_cal_ros.methods.star_model import StarModel

RESIDUAL_COLUMNS = (
    "t", "frame", "catalog_id", "u", "v", "u_pred", "v_pred", "du", "dv",
    "s_uu", "s_uv", "s_vv", "nis", "magnitude", "gated",
    "x_st", "y_st", "z_st", "omega_x", "omega_y", "omega_z", "head_temperature",
)
#: inside :func:`keeping_frames`: each new :class:`RunStats` keeps its frames' terms
_KEEP_FRAMES: contextvars.ContextVar[bool] = contextvars.ContextVar("keep_frames", default=False)
#: a star's NIS is capped here in the log-likelihood (a few misidentified stars must not
#: dominate the comparison of two models)
NIS_CAP = 13.8


def logdet_weight(cap: float) -> float:
    """The weight of each star's ``log det S`` beside its NIS capped at ``cap`` (2 dof).

    ``P(χ²₄ < cap) = 1 − e^(−cap/2) (1 + cap/2)``: with it the capped log-likelihood's score
    has mean 0 at the true covariance for any parameter of ``S`` (a noise scale), as the
    uncapped one's does.  For ``ν ~ N(0, S)``, ``z = S^(−½) ν`` and any ``A`` (``S^(−½) ∂S
    S^(−½)``), ``E[zᵀAz · 1(|z|² < cap)] = tr A · P(χ²₄ < cap)`` (spherical symmetry), while
    the log-determinant's derivative is ``tr A``: at weight 1 a cap biases every variance
    estimated on the likelihood low (at 13.8 by 0.8 % of the NIS's share; the gyro noise's
    share of a star's ``S`` is a few %, so its scale by ~x0.98 at the stated noise and
    ~x0.99 at 57x, doc/benchmarks.md H264).  A mean parameter's score is unbiased either way
    (odd in ``z``).  A gated star counts at the cap with the window's mean log-determinant,
    weighted alike.
    """
    h = 0.5 * cap
    return 1.0 - math.exp(-h) * (1.0 + h) if math.isfinite(cap) else 1.0


#: :func:`logdet_weight` at :data:`NIS_CAP`
LOGDET_WEIGHT = logdet_weight(NIS_CAP)
_LOG_2PI_2 = 2 * np.log(2 * np.pi)  # the log-likelihood's constant (as a float64)


@contextlib.contextmanager
def keeping_frames() -> Iterator[None]:
    """Runs started inside keep their window's log-likelihood frame by frame.

    (:meth:`RunStats.frame_log_likelihood`: a few numbers a frame, without the residual
    table, which on a 2-h bag costs 1.3 CPU-s and ~80 MB a run.)
    """
    token = _KEEP_FRAMES.set(True)
    try:
        yield
    finally:
        _KEEP_FRAMES.reset(token)


def residual_rows(upd, frame_index: int, ids: np.ndarray, mag: np.ndarray,
                  head_temperature: float) -> dict[str, np.ndarray]:
    """The residual-table rows of one frame update (:class:`~.kernel.FrameUpdate`)."""
    return residual_block([upd.stamp], [len(upd.uv)], frame_index, upd.uv, upd.uv_pred,
                          upd.S, upd.nis_stars, upd.accepted, upd.directions_st,
                          np.asarray(upd.omega_b).reshape(1, 3), ids, mag, [head_temperature])


def residual_block(stamps, counts, frame_index: int, uv, uv_pred, S, nis_stars, accepted,
                   directions, omega, ids, mag, head_temperature) -> dict[str, np.ndarray]:
    """The residual-table rows of frame updates in a row, their stars' arrays stacked.

    :func:`residual_rows` of each (``frame_index`` the first's): a frame's values
    (``stamps``, ``omega`` (K, 3), ``head_temperature``) on each of its ``counts`` rows.
    """
    n = np.asarray(counts, dtype=np.int64)
    nu = uv - uv_pred

    def each(v) -> np.ndarray:
        return np.repeat(np.asarray(v, dtype=float), n)

    return {
        "t": each(stamps),
        "frame": np.repeat(np.arange(frame_index, frame_index + len(n), dtype=np.int64), n),
        "catalog_id": np.asarray(ids, dtype=np.int64),
        "u": uv[:, 0], "v": uv[:, 1], "u_pred": uv_pred[:, 0],
        "v_pred": uv_pred[:, 1], "du": nu[:, 0], "dv": nu[:, 1],
        "s_uu": S[:, 0, 0], "s_uv": S[:, 0, 1], "s_vv": S[:, 1, 1],
        "nis": nis_stars, "magnitude": np.asarray(mag, dtype=float),
        "gated": ~accepted,
        "x_st": directions[:, 0], "y_st": directions[:, 1], "z_st": directions[:, 2],
        "omega_x": each(omega[:, 0]), "omega_y": each(omega[:, 1]),
        "omega_z": each(omega[:, 2]),
        "head_temperature": each(head_temperature),
    }


class TableSink:
    """Rows of a table, kept in memory or streamed to ``path`` (CSV / Parquet).

    ``append(chunk)`` with a dict of equal-length arrays, or :meth:`append_row` with one row
    of scalars; :meth:`table` returns the whole table in memory mode (an empty dict when
    streaming: read the file).  Rows are buffered and handed on in blocks of about
    ``chunk_rows`` (one formatting pass per column per block instead of per frame): the
    file and the table are the same as with one chunk per call.
    """

    #: True for a sink that keeps nothing (the driver then does not build its rows)
    discard = False

    def __init__(self, path=None, columns: tuple[str, ...] | None = None,
                 chunk_rows: int = 1024) -> None:
        self.path = path
        self.columns = columns
        self.chunk_rows = int(chunk_rows)
        self._chunks: list[dict[str, np.ndarray]] = []
        self._writer = TableWriter(path) if path is not None else None
        self.rows = 0
        self._buf: list[dict[str, np.ndarray]] = []  # chunks of one layout, not yet merged
        self._buf_key: tuple | None = None
        self._buf_rows = 0
        self._row_keys: tuple[str, ...] | None = None  # append_row buffer
        self._row_values: list[list] = []
        self._row_arrays: list[list[np.ndarray]] = []
        self._row_take: np.ndarray | None = None

    def append(self, chunk: dict[str, np.ndarray], ends: list[int] | None = None) -> None:
        """Add rows.

        ``ends``: the rows of ``chunk`` are pieces the caller would add a call each, these
        their ends (the last: the chunk's length): the same blocks are handed on as with a
        call a piece (the buffer's cuts fall where they would).
        """
        n = len(next(iter(chunk.values()))) if chunk else 0
        self.rows += n
        if self._row_values:
            self._flush_rows()
        if ends is None or len(ends) < 2:
            self._buffer(chunk, n)
            return
        a = 0
        while a < n:  # up to the piece that fills the buffer, at a time
            need = a + self.chunk_rows - self._buf_rows
            b = next((e for e in ends if e >= need), n)
            self._buffer(chunk if (a, b) == (0, n) else
                         {k: v[a:b] for k, v in chunk.items()}, b - a)
            a = b

    def append_row(self, keys: tuple[str, ...], values: list,
                   arrays: tuple[np.ndarray, ...] = (), take: np.ndarray | None = None) -> None:
        """Add one row: column names (pass the same tuple every call) and their values.

        ``values``: the first cells (scalars); the others ``np.concatenate(arrays)[take]``
        (pass the same ``take`` every call), gathered for all buffered rows at once: the
        cells are what ``values + np.concatenate(arrays)[take].tolist()`` would give (the
        arrays are copied).
        """
        if (keys is not self._row_keys or take is not self._row_take) and self._row_values:
            self._flush_rows()
        self._row_keys = keys
        self._row_take = take
        self._row_values.append(values)
        if take is not None:
            self._row_arrays.append([np.array(a, dtype=float) for a in arrays])
        self.rows += 1
        if len(self._row_values) >= self.chunk_rows:
            self._flush_rows()

    def append_rows(self, keys: tuple[str, ...], values: list[list],
                    arrays: tuple[np.ndarray, ...], take: np.ndarray) -> None:
        """:meth:`append_row` of several rows at once, the same cells.

        Row ``i``: ``values[i]`` and the rows ``a[i]`` of each of ``arrays`` (2-D, handed
        over: the caller no longer writes to them).
        """
        if (keys is not self._row_keys or take is not self._row_take) and self._row_values:
            self._flush_rows()
        self._row_keys = keys
        self._row_take = take
        i, m = 0, len(values)
        while i < m:  # up to a chunk's end at a time, as row by row
            j = min(m, i + self.chunk_rows - len(self._row_values))
            self._row_values += values[i:j]
            self._row_arrays += zip(*(a[i:j] for a in arrays), strict=True)
            self.rows += j - i
            i = j
            if len(self._row_values) >= self.chunk_rows:
                self._flush_rows()

    def _flush_rows(self) -> None:
        rows, self._row_values = self._row_values, []
        arrays, self._row_arrays = self._row_arrays, []
        keys = self._row_keys
        chunk = {k: np.array(c) for k, c in zip(keys, zip(*rows, strict=True), strict=False)}
        if self._row_take is not None:  # the array cells: one gather for every row
            block = np.concatenate([np.stack(c) for c in zip(*arrays, strict=True)],
                                   axis=1)[:, self._row_take]
            head = len(rows[0])
            if head + block.shape[1] != len(keys):
                raise ValueError(f"{len(keys)} columns, {head + block.shape[1]} cells a row")
            chunk.update(zip(keys[head:], block.T, strict=True))
        elif len(chunk) != len(keys):
            raise ValueError(f"{len(keys)} columns, {len(rows[0])} cells a row")
        self._buffer(chunk, len(rows))

    def _buffer(self, chunk: dict[str, np.ndarray], n: int) -> None:
        # chunks merge only with chunks of the same columns and dtypes (same values, same
        # formatting); a different layout first hands on what is held (a writer refuses a
        # change of columns at once, as without the buffer)
        key = tuple((k, np.asarray(v).dtype.str) for k, v in chunk.items())
        if self._buf and key != self._buf_key:
            self._flush()
        self._buf.append(chunk)
        self._buf_key = key
        self._buf_rows += n
        if self._buf_rows >= self.chunk_rows:
            self._flush()

    def _flush(self) -> None:
        """Hand the buffered chunks on as one."""
        if self._row_values:
            self._flush_rows()
        buf, self._buf, self._buf_rows = self._buf, [], 0
        if not buf:
            return
        # (one chunk: the sink's own dict of the caller's arrays; :meth:`table` empties its
        # chunks' dicts as it joins them, which must not empty a dict the caller keeps)
        merged = dict(buf[0]) if len(buf) == 1 else {
            k: np.concatenate([np.asarray(c[k]) for c in buf]) for k in buf[0]}
        if self._writer is not None:
            self._writer.append(merged)
        else:
            self._chunks.append(merged)

    def close(self) -> None:
        """Finish the file (streaming mode)."""
        self._flush()
        if self._writer is not None:
            if self._writer.columns is None and self.columns:
                self._writer.append({k: np.zeros(0) for k in self.columns})
            self._writer.close()

    def table(self) -> dict[str, np.ndarray]:
        """The rows in memory (memory mode)."""
        if self._writer is not None:
            return {}
        self._flush()
        if not self._chunks:
            return {k: np.zeros(0) for k in (self.columns or ())}
        # column by column, each column's chunks dropped once joined: the table and its
        # chunks are not held at once (a 2-h bag's residual table is ~65 MB), and the sink
        # keeps the joined table as its one chunk (a second call returns the same arrays)
        chunks, self._chunks = self._chunks, []
        out = {}
        for k in list(chunks[0]):
            out[k] = np.concatenate([c.pop(k) for c in chunks])
        self._chunks = [dict(out)]
        return out


class NullSink(TableSink):
    """A table sink that keeps nothing (a live node publishes its residuals instead)."""

    discard = True

    def append(self, chunk) -> None:  # noqa: D102
        return None

    def append_row(self, keys, values, arrays=(), take=None) -> None:  # noqa: D102
        return None

    def append_rows(self, keys, values, arrays, take) -> None:  # noqa: D102
        return None


def frame_sums(upd) -> np.ndarray:
    """One frame's terms of :meth:`RunStats.add` (10,) over its accepted stars.

    ``[n, Σ log det S, Σ min(NIS, cap), Σ du², Σ dv², Σ S_uu, Σ S_vv, Σ NIS, whitened u
    mean · √n, whitened v mean · √n]`` (whitened: Cholesky ``L⁻¹ ν``).  The compiled frame
    step computes the same (:func:`~stellar_cal_ros.methods.frame_step.frame_sums`) and hands
    it over as ``FrameUpdate.sums``.  A frame with common noises in its R (a stamp noise, a
    frame-common shift) adds to the third its ``upd.joint``
    (:func:`~stellar_cal_ros.core.covariance.joint_correction`): the log-likelihood is then
    the frame's, whose stars share the stamp's one error and the shift.
    """
    acc = upd.accepted
    n = int(acc.sum())
    out = np.zeros(10)
    out[0] = n
    if not n:
        return out
    S = upd.S
    if n == len(acc):  # every star accepted: the same values without the copies
        nu, Sa, nis_acc = upd.uv - upd.uv_pred, S, upd.nis_stars
    else:
        nu, Sa, nis_acc = (upd.uv - upd.uv_pred)[acc], S[acc], upd.nis_stars[acc]
    det = Sa[:, 0, 0] * Sa[:, 1, 1] - Sa[:, 0, 1] ** 2
    out[1] = float(np.sum(np.log(np.maximum(det, 1e-300))))
    out[2] = float(np.sum(np.minimum(nis_acc, NIS_CAP)))
    out[3] = float(nu[:, 0] @ nu[:, 0])
    out[4] = float(nu[:, 1] @ nu[:, 1])
    out[5] = float(Sa[:, 0, 0].sum())
    out[6] = float(Sa[:, 1, 1].sum())
    out[7] = float(np.sum(nis_acc))
    l11 = np.sqrt(Sa[:, 0, 0])
    l21 = Sa[:, 0, 1] / l11
    l22 = np.sqrt(np.maximum(Sa[:, 1, 1] - l21**2, 1e-300))
    w1 = nu[:, 0] / l11
    w2 = (nu[:, 1] - l21 * w1) / l22
    out[8] = float(w1.mean()) * math.sqrt(n)
    out[9] = float(w2.mean()) * math.sqrt(n)
    joint = getattr(upd, "joint", 0.0)
    if joint:
        out[2] += joint
    return out


def _running(start: float, x: np.ndarray) -> float:
    """``start + x[0] + x[1] + ...`` added in that order (the same float as a loop)."""
    if not len(x):
        return start
    return float(np.add.accumulate(np.concatenate([[start], x]))[-1])


def nis_band(dof: int) -> tuple[float, float]:
    """The 95 % band of a NIS/dof of ``dof`` (> 0) degrees of freedom.

    ``χ²_dof / dof ≈ N(1, 2/dof)``: the run's (:meth:`RunStats.nis_per_dof`), its
    reference's (:func:`consistency`), the live view's moving window (``viz``).
    """
    half = 1.959964 * math.sqrt(2.0 / dof)
    return max(0.0, 1.0 - half), 1.0 + half


@dataclass
class RunStats:
    """Running statistics of the innovations over the evaluation window (O(1) memory).

    Frames with a reported stamp ≥ ``eval_start`` (POSIX s; None: every frame) count.
    Over the window's accepted stars: sums of squared innovations and of their predicted
    variances, per-star NIS (2 dof each), and the frame-mean whitened innovations for the
    lag-1 whiteness test; over all its stars the capped Gaussian log-likelihood.
    """

    eval_start: float | None = None
    frames: int = 0
    stars: int = 0
    stars_all: int = 0
    accepted_total: int = 0  #: accepted stars over the whole run (window or not)
    gated: int = 0  #: stars of the window the gate rejected
    sum_logdet: float = 0.0  #: Σ log det S over the window's accepted stars
    #: Σ min(NIS, cap) over them (and the frames' stamp corrections: :func:`frame_sums`)
    sum_nis_capped: float = 0.0
    sum_du2: float = 0.0
    sum_dv2: float = 0.0
    sum_suu: float = 0.0
    sum_svv: float = 0.0
    sum_nis: float = 0.0
    frame_nis: float = 0.0
    frame_dof: int = 0
    ref_nis: float = 0.0  #: the method's other measurements (the swaying filter's Z1)
    ref_dof: int = 0
    # lag-1 whiteness of the frame-mean whitened innovations (u, v): Σx, Σx², Σx_k x_{k−1}
    _w: dict[str, list[float]] = field(default_factory=lambda: {
        "n": [0, 0], "s": [0.0, 0.0], "s2": [0.0, 0.0], "lag": [0.0, 0.0],
        "first": [0.0, 0.0], "last": [0.0, 0.0]})

    def __post_init__(self) -> None:
        # the window's frames' [stamp, stars, accepted, Σ log det S, Σ min(NIS, cap)]
        # column blocks, inside :func:`keeping_frames` only (not a field: no checkpoint,
        # no merge of sums carries it)
        self._frames: list[np.ndarray] | None = [] if _KEEP_FRAMES.get() else None

    def add(self, upd) -> None:
        """Add one frame update (:class:`~.kernel.FrameUpdate`).

        Any object with its fields will do; without the compiled step's ``sums`` they are
        computed here (the viz rebuilds frames from a residual table).
        """
        pre = getattr(upd, "sums", None)
        n = int(pre[0]) if pre is not None else int(np.count_nonzero(upd.accepted))
        self.accepted_total += n
        if self.eval_start is not None and upd.stamp < self.eval_start:
            return
        self.stars_all += len(upd.uv)
        self.gated += len(upd.uv) - n
        if math.isfinite(upd.nis):
            self.frame_nis += upd.nis
            self.frame_dof += upd.dof
        if not n:
            if self._frames is not None:
                self._frames.append(np.array([[upd.stamp], [len(upd.uv)], [0.0], [0.0], [0.0]]))
            return
        self.frames += 1
        # Python floats in one call (the same values as ``float(sums[k])`` each)
        sums = (pre if pre is not None else frame_sums(upd)).tolist()
        if self._frames is not None:
            self._frames.append(np.array([[upd.stamp], [len(upd.uv)], [n], [sums[1]],
                                          [sums[2]]], dtype=float))
        self.sum_logdet += sums[1]
        self.sum_nis_capped += sums[2]
        self.stars += n
        self.sum_du2 += sums[3]
        self.sum_dv2 += sums[4]
        self.sum_suu += sums[5]
        self.sum_svv += sums[6]
        self.sum_nis += sums[7]
        w = self._w
        for k, x in enumerate((sums[8], sums[9])):
            if w["n"][k]:
                w["lag"][k] += x * w["last"][k]
            else:
                w["first"][k] = x
            w["n"][k] += 1
            w["s"][k] += x
            w["s2"][k] += x * x
            w["last"][k] = x

    def add_block(self, stamps: list, n_stars: list, nis: np.ndarray, dof: list,
                  sums: np.ndarray) -> None:
        """:meth:`add` of frames in a row at once, bit for bit (a replay's batch).

        Frame ``i``: its reported stamp, its stars, NIS, dof and :func:`frame_sums` row
        ``sums[i]`` (the compiled step's).  The float sums are accumulated in the frames'
        order (``np.add.accumulate`` from the running value: the additions one ``add`` a
        frame makes), the integer ones summed.
        """
        sums = np.asarray(sums, dtype=float)
        n = sums[:, 0].astype(np.int64)
        self.accepted_total += int(n.sum())
        keep = np.ones(len(n), dtype=bool) if self.eval_start is None else \
            np.asarray(stamps, dtype=float) >= self.eval_start
        if not keep.all():
            n, nis, sums = n[keep], np.asarray(nis)[keep], sums[keep]
            n_stars = [x for x, k in zip(n_stars, keep, strict=True) if k]
            dof = [x for x, k in zip(dof, keep, strict=True) if k]
        if not len(n):
            return
        self.stars_all += sum(n_stars)
        self.gated += sum(n_stars) - int(n.sum())
        if self._frames is not None:
            st = np.asarray(stamps, dtype=float)
            self._frames.append(np.stack([st[keep] if not keep.all() else st,
                                          np.asarray(n_stars, dtype=float), n.astype(float),
                                          sums[:, 1], sums[:, 2]]))
        nis = np.asarray(nis, dtype=float)
        fin = np.isfinite(nis)
        self.frame_nis = _running(self.frame_nis, nis[fin])
        self.frame_dof += sum(d for d, f in zip(dof, fin.tolist(), strict=True) if f)
        has = n > 0
        if not has.all():
            n, sums = n[has], sums[has]
        if not len(n):
            return
        self.frames += len(n)
        self.stars += int(n.sum())
        for name, k in (("sum_logdet", 1), ("sum_nis_capped", 2), ("sum_du2", 3),
                        ("sum_dv2", 4), ("sum_suu", 5), ("sum_svv", 6), ("sum_nis", 7)):
            setattr(self, name, _running(getattr(self, name), sums[:, k]))
        w = self._w
        for k in (0, 1):
            x = sums[:, 8 + k]
            if w["n"][k]:
                w["lag"][k] = _running(w["lag"][k], x * np.concatenate([[w["last"][k]], x[:-1]]))
            else:
                w["first"][k] = float(x[0])
                w["lag"][k] = _running(w["lag"][k], x[1:] * x[:-1])
            w["n"][k] += len(x)
            w["s"][k] = _running(w["s"][k], x)
            w["s2"][k] = _running(w["s2"][k], x * x)
            w["last"][k] = float(x[-1])

    def add_reference(self, stamp: float, nis: float, dof: int) -> None:
        """Add one update of another measurement (e.g. the inertial reference Z1)."""
        if (self.eval_start is None or stamp >= self.eval_start) and math.isfinite(nis):
            self.ref_nis += nis
            self.ref_dof += dof

    def merge(self, later: RunStats) -> None:
        """Add the statistics of ``later`` (the frames that came after this one's), exactly.

        Every sum adds; the lag-1 sum gains the one product across the seam (this one's last
        frame mean with ``later``'s first).
        """
        mine, theirs = self.__dict__, later.__dict__
        for name in _SUMS:
            mine[name] += theirs[name]
        if self._frames is not None and later._frames is not None:
            self._frames += later._frames
        a, b = self._w, later._w
        for k in (0, 1):
            if not b["n"][k]:
                continue
            if a["n"][k]:
                a["lag"][k] += b["lag"][k] + a["last"][k] * b["first"][k]
            else:
                a["first"][k], a["lag"][k] = b["first"][k], b["lag"][k]
            for key in ("n", "s", "s2"):
                a[key][k] += b[key][k]
            a["last"][k] = b["last"][k]

    def current(self) -> RunStats:
        """The statistics a verdict is made of now (this object: its window is fixed)."""
        return self

    # ------------------------------------------------------------------ summaries
    def log_likelihood(self) -> float:
        """Gaussian log-likelihood of the window's innovations, each star's NIS capped.

        Innovations are one-step-ahead predictions, so this is a prequential likelihood.  A
        gated star counts at the cap with the window's mean accepted log-determinant (its
        own covariance is that of a wrong identity predicted far off; every model is scored
        alike on the stars it rejects) — as :func:`stellar_cal_ros.diagnosis.stats.
        log_likelihood` does with the median on a whole table.  Every log-determinant is
        weighted by :data:`LOGDET_WEIGHT` (the cap's consistency, :func:`logdet_weight`).
        With a stamp noise in R the stars of a frame share its error: each frame's
        :func:`~stellar_cal_ros.core.covariance.joint_correction` is added (uncapped,
        unweighted; in ``sum_nis_capped``): the frame's likelihood, not its stars'.
        """
        if not self.stars:
            return math.nan
        w = LOGDET_WEIGHT
        fill = w * self.sum_logdet / self.stars
        c = _LOG_2PI_2
        return -0.5 * (self.sum_nis_capped + w * self.sum_logdet + self.stars * c
                       + self.gated * (NIS_CAP + fill + c))

    def frame_log_likelihood(self) -> np.ndarray | None:
        """:meth:`log_likelihood` frame by frame, when the run kept its frames' terms.

        ``(2, frames)``: the window's frames' reported stamps (ascending) and each frame's
        terms (its stars' alike, a gated star at the cap with the window's mean
        log-determinant); they sum to :meth:`log_likelihood`.  ``None`` unless the run ran
        inside :func:`keeping_frames` (the IMU noise search's runs: their sandwich σ,
        :meth:`stellar_cal_ros.diagnosis.noise_imu.ScaleSearch.sandwich`).
        """
        if self._frames is None:
            return None
        if not self.stars or not self._frames:
            return np.zeros((2, 0))
        f = np.concatenate(self._frames, axis=1)
        f = f[:, np.argsort(f[0], kind="stable")]
        c = _LOG_2PI_2
        w = LOGDET_WEIGHT
        fill = w * self.sum_logdet / self.stars
        terms = -0.5 * (f[4] + w * f[3] + f[2] * c + (f[1] - f[2]) * (NIS_CAP + fill + c))
        return np.stack([f[0], terms])

    def window(self, fraction: float) -> dict[str, Any]:
        """The statistics the diagnosis decides with, over the evaluation window."""
        nis, (lo, hi) = self.nis_per_dof()
        n = self.stars
        mean_sq = (self.sum_du2 + self.sum_dv2) / n if n else math.nan
        noise = (self.sum_suu + self.sum_svv) / n if n else math.nan
        return {"log_likelihood": self.log_likelihood(),
                "nis": {"mean": 2 * nis, "lower": 2 * lo, "upper": 2 * hi, "n": n},
                "whiteness": self.whiteness(), "rms": self.rms(),
                "expected_rms": self.expected_rms(), "excess_variance": mean_sq - noise,
                "noise_variance": noise, "n_window": n, "n_accepted": self.accepted_total,
                "fraction": fraction}

    def rms(self) -> tuple[float, float]:
        """Innovation RMS (u, v) of the accepted stars, px."""
        if not self.stars:
            return math.nan, math.nan
        return math.sqrt(self.sum_du2 / self.stars), math.sqrt(self.sum_dv2 / self.stars)

    def expected_rms(self) -> tuple[float, float]:
        """RMS the model predicts (u, v), px."""
        if not self.stars:
            return math.nan, math.nan
        return math.sqrt(self.sum_suu / self.stars), math.sqrt(self.sum_svv / self.stars)

    def nis_per_dof(self) -> tuple[float, tuple[float, float]]:
        """Mean per-star NIS / 2 over accepted stars and its 95 % χ² interval."""
        if not self.stars:
            return math.nan, (math.nan, math.nan)
        dof = 2 * self.stars
        return self.sum_nis / dof, nis_band(dof)

    def whiteness(self) -> dict[str, float]:
        """Lag-1 autocorrelation of the frame-mean whitened innovations and its p-value."""
        w = self._w
        out: dict[str, float] = {}
        ps = []
        for k, name in enumerate(("u", "v")):
            n = w["n"][k]
            if n <= 2:
                out[f"lag1_{name}"] = 0.0
                ps.append(1.0)
                continue
            m = w["s"][k] / n
            num = w["lag"][k] - m * (2 * w["s"][k] - w["first"][k] - w["last"][k]) \
                + (n - 1) * m * m
            den = max(w["s2"][k] - n * m * m, 1e-300)
            r = num / den
            out[f"lag1_{name}"] = r
            ps.append(math.erfc(abs(r) * math.sqrt(n) / math.sqrt(2.0)))
        out["p_value"] = min(1.0, 2 * min(ps))
        return out

    def summary(self) -> dict[str, Any]:
        """Everything as plain numbers."""
        nis, interval = self.nis_per_dof()
        ref = self.ref_nis / self.ref_dof if self.ref_dof else math.nan
        return {"frames": self.frames, "stars": self.stars, "rms_px": list(self.rms()),
                "reference_nis_per_dof": ref,
                "expected_rms_px": list(self.expected_rms()), "nis_per_dof": nis,
                "nis_interval": list(interval), "whiteness": self.whiteness(),
                "loglik": self.log_likelihood(), "eval_start": self.eval_start}


#: the additive fields of :class:`RunStats` (all but the window start and the lag sums)
_SUMS = tuple(f.name for f in dataclasses.fields(RunStats) if f.name not in ("eval_start", "_w"))


def _copy_stats(st: RunStats) -> RunStats:
    out = copy.copy(st)
    out._w = {k: list(v) for k, v in st._w.items()}
    return out


@dataclass
class HalfWindowStats:
    """:class:`RunStats` of the second half of the data seen so far (the live node's window).

    A replay judges the second half of the bag (the filter has converged there); a live run
    has no end to take a half of.  This keeps the statistics in blocks of data time — at
    most ``max_blocks``; adjacent blocks merge pairwise as the run grows, so memory stays
    bounded for a node that runs for days — and :meth:`current` merges the blocks that
    start at or after the middle of the frame stamps seen so far: the replay's window, up to
    one block (span / ``max_blocks`` or less, times 2).  ``add`` / ``add_reference`` as
    :class:`RunStats`.
    """

    max_blocks: int = 128
    block_s: float = 1.0  #: data time a new block covers (doubles at each merge)
    t_first: float | None = None  #: first frame stamp seen, POSIX s
    t_last: float | None = None  #: latest
    starts: list[float] = field(default_factory=list)
    blocks: list[RunStats] = field(default_factory=list)
    accepted_total: int = 0  #: accepted stars of the whole run
    #: the merged closed blocks of the window and what they were merged for (a verdict at
    #: 1 Hz merges one block, not all, while the window's first block stays the same)
    _merged: tuple | None = field(default=None, repr=False, compare=False)

    def _block(self, t: float) -> RunStats:
        if self.t_first is None:
            self.t_first = t
        self.t_last = t if self.t_last is None else max(self.t_last, t)
        if not self.blocks or t >= self.starts[-1] + self.block_s:
            self.starts.append(t)
            self.blocks.append(RunStats())
            if len(self.blocks) > self.max_blocks:
                self._coarsen()
        return self.blocks[-1]

    def _coarsen(self) -> None:
        starts, blocks = [], []
        for k in range(0, len(self.blocks), 2):
            b = self.blocks[k]
            if k + 1 < len(self.blocks):
                b.merge(self.blocks[k + 1])
            starts.append(self.starts[k])
            blocks.append(b)
        self.starts, self.blocks = starts, blocks
        self.block_s *= 2.0

    def add(self, upd) -> None:
        """Add one frame update."""
        self.accepted_total += int(np.count_nonzero(upd.accepted))
        self._block(float(upd.stamp)).add(upd)

    def add_reference(self, stamp: float, nis: float, dof: int) -> None:
        """Add one update of another measurement."""
        self._block(float(stamp)).add_reference(stamp, nis, dof)

    def current(self) -> RunStats:
        """The merged statistics of the second half of the frames seen so far."""
        if self.t_first is None:
            return RunStats()
        mid = self.t_first + 0.5 * (self.t_last - self.t_first)
        i = next((k for k, t in enumerate(self.starts) if t >= mid), len(self.starts))
        last = len(self.blocks) - 1
        key = (i, last, self.block_s)
        if self._merged is None or self._merged[0] != key:
            closed = RunStats()
            for b in self.blocks[i:last]:
                closed.merge(b)
            self._merged = (key, closed)
        out = _copy_stats(self._merged[1])
        if i <= last:
            out.merge(self.blocks[last])
        out.eval_start = self.starts[i] if i <= last else mid
        out.accepted_total = self.accepted_total
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> HalfWindowStats:
        """Inverse of :func:`stats_state` (a checkpoint)."""
        d = {k: v for k, v in d.items() if k != "_merged"}
        return cls(**{**d, "blocks": _blocks_from_rows(np.asarray(d["blocks"])),
                      "starts": [float(t) for t in d["starts"]]})


#: a RunStats as one row of numbers (a checkpoint): its scalar fields (None: NaN), then the
#: whiteness sums two by two
_ROW_FIELDS = tuple(f.name for f in dataclasses.fields(RunStats) if f.name != "_w")
_ROW_INT = frozenset(f.name for f in dataclasses.fields(RunStats) if f.type == "int")
_W_KEYS = ("n", "s", "s2", "lag", "first", "last")


def _blocks_rows(blocks: list[RunStats]) -> np.ndarray:
    rows = np.empty((len(blocks), len(_ROW_FIELDS) + 2 * len(_W_KEYS)))
    for row, b in zip(rows, blocks, strict=True):
        row[:len(_ROW_FIELDS)] = [math.nan if (v := getattr(b, n)) is None else v
                                  for n in _ROW_FIELDS]
        row[len(_ROW_FIELDS):] = [x for k in _W_KEYS for x in b._w[k]]
    return rows


def _blocks_from_rows(rows: np.ndarray) -> list[RunStats]:
    out = []
    m = len(_ROW_FIELDS)
    for row in rows.tolist():
        kw = {n: int(v) if n in _ROW_INT else (None if v != v else v)
              for n, v in zip(_ROW_FIELDS, row[:m], strict=True)}
        w = {k: row[m + 2 * i:m + 2 * i + 2] for i, k in enumerate(_W_KEYS)}
        w["n"] = [int(x) for x in w["n"]]
        out.append(RunStats(**kw, _w=w))
    return out


def stats_state(st: RunStats | HalfWindowStats) -> dict[str, Any]:
    """The statistics as plain values (a checkpoint; :func:`stats_from_dict` reads them).

    A :class:`HalfWindowStats`' blocks are one array (a row each), its start stamps another,
    its cache of merged blocks is left out: a live node's checkpoint holds up to 128 blocks,
    which ``dataclasses.asdict`` took ~7 ms to copy (and ~90 kB of JSON).
    """
    if isinstance(st, HalfWindowStats):
        return {"max_blocks": st.max_blocks, "block_s": st.block_s, "t_first": st.t_first,
                "t_last": st.t_last, "starts": np.asarray(st.starts, dtype=float),
                "blocks": _blocks_rows(st.blocks), "accepted_total": st.accepted_total}
    return dataclasses.asdict(st)


def stats_from_dict(d: dict[str, Any]) -> RunStats | HalfWindowStats:
    """A :class:`RunStats` or :class:`HalfWindowStats` from :func:`stats_state`."""
    return HalfWindowStats.from_dict(d) if "blocks" in d else RunStats(**d)


#: NIS/dof beyond the χ² interval by more than this is a model mismatch (small departures
#: of a long run are linearization, not a missing effect)
NIS_TOLERANCE = 0.1
#: whiteness p-value below this: correlated innovations, a model mismatch
WHITENESS_P = 1e-3


def consistency(stats: RunStats, noise: Any = None) -> dict[str, Any]:
    """``{nis_per_dof, interval, whiteness_p, verdict}`` of a run (see the module docstring).

    ``verdict``: ``consistent``; ``model mismatch`` (the stars' or the method's other
    measurements' NIS/dof above its interval and above 1 + :data:`NIS_TOLERANCE`, or star
    innovations correlated from frame to frame, p < :data:`WHITENESS_P`) — the model
    misses an effect and the σ are conditional on it;
    ``conservative`` (NIS/dof well below its interval: noise levels set too high);
    ``no data``.

    ``noise``: the run's :class:`~stellar_cal_ros.core.noise.NoiseScales`.  When it
    declares the stars' noise correlated from frame to frame (``star_rho`` ρ > 0, the
    diagnosis's ``--noise-scale star=K,rho=R``), the stars' σ holds the factor
    ``k = star_inflation`` a white-noise filter needs, so each frame's NIS/dof reads ~1/k²
    and the frame means follow each other by up to ρ₁ (ρ for a pure AR(1), w ρ for white +
    AR(1), ``share=w``): NIS/dof is judged times k² (its interval widened by the correlated
    squares' √(1 + 2 Σ ρ_k²)) and the whiteness test is one-sided, lag-1 above ρ₁
    (:meth:`~stellar_cal_ros.core.noise.NoiseScales.star_lags`).  Judged as white, the
    advice the diagnosis printed read "MODEL MISMATCH (with the rescaled noise): NIS/dof
    0.11, whiteness p 9.5e-44" (unseen case ``ar1``, 300 s, star=2.96).
    """
    nis, (lo, hi) = stats.nis_per_dof()
    wh = stats.whiteness()
    p = wh["p_value"]
    rho = float(getattr(noise, "star_rho", 0.0) or 0.0)
    declared = {}
    if rho > 0.0 and math.isfinite(nis):
        k2 = float(noise.star_inflation) ** 2
        raw, nis = nis, nis * k2
        lag1, bartlett, squares = noise.star_lags()
        widen = math.sqrt(squares)
        lo, hi = max(0.0, 1.0 - (1.0 - lo) * widen), 1.0 + (hi - 1.0) * widen
        # lag-1 of the frame means above the declared one (w ρ; Bartlett's σ √(b/n) of its
        # estimate), the upper tail of the larger axis, Bonferroni over the two
        n = max(min(stats._w["n"]), 1)
        over = max(wh.get("lag1_u", 0.0), wh.get("lag1_v", 0.0)) - lag1
        p = min(1.0, math.erfc(over * math.sqrt(n / bartlett) / math.sqrt(2.0)))
        declared = {"star_rho": rho, "star_ar_share": float(noise.star_ar_share),
                    "nis_per_dof_raw": raw, "inflation": k2,
                    "lag1": [wh.get("lag1_u", 0.0), wh.get("lag1_v", 0.0)]}
    ref = stats.ref_nis / stats.ref_dof if stats.ref_dof else math.nan
    ref_hi = nis_band(stats.ref_dof)[1] if stats.ref_dof else math.inf
    if not math.isfinite(nis):
        verdict = "no data"
    elif nis > max(hi, 1.0 + NIS_TOLERANCE) or p < WHITENESS_P or (
            math.isfinite(ref) and ref > max(ref_hi, 1.0 + NIS_TOLERANCE)):
        verdict = "model mismatch"
    elif nis < min(lo, 1.0 - NIS_TOLERANCE):
        verdict = "conservative"
    else:
        verdict = "consistent"
    out = {"nis_per_dof": nis, "interval": [lo, hi], "whiteness_p": p, "verdict": verdict,
           "stars": stats.stars, "rms_px": list(stats.rms()),
           "expected_rms_px": list(stats.expected_rms())}
    if stats.eval_start is not None:  # POSIX s: the window's first reported frame stamp
        out["window_start"] = float(stats.eval_start)
    if stats.ref_dof:
        out["reference_nis_per_dof"] = ref
    if declared:
        out["correlated"] = declared
    return out


#: the live status text of each consistency verdict (``/diagnostics`` of the node and of
#: ``replay --viz``) (constant texts: a monitor keys on
#: them; the numbers are in the status' values ``consistency.*``)
VERDICT_MESSAGES = {
    "model mismatch": "model mismatch: the innovations exceed the noise model (NIS/dof "
                      "above its interval or correlated in time); the model misses an "
                      "effect and every sigma is conditional on it: run `stellar-cal "
                      "diagnose` on a recording",
    "conservative": "innovations below the noise model (NIS/dof under its interval): noise "
                    "levels set too high",
}


def mismatch_text(cons: dict[str, Any]) -> str:
    """The loud line a model mismatch or a conservative noise earns (empty when consistent).

    Either can be a wrong *noise* as much as a wrong model (issue 21): a star σ stated too
    small raises every NIS by its square, a gyro noise stated too small makes the
    innovations follow each other; the text says so and names the commands that tell.
    """
    verdict = cons.get("verdict")
    nis = cons.get("nis_per_dof", math.nan)
    rescaled = " (with the rescaled noise)" if cons.get("noise_rescaled") else ""
    if verdict == "conservative":
        return (f"NOISE OVERSTATED?{rescaled}: star NIS/dof {nis:.2f} (expected "
                f"{cons['interval'][0]:.2f}-{cons['interval'][1]:.2f}): the innovations are "
                f"smaller than the stated noise allows, as if the stars' sigma were "
                f"{1.0 / math.sqrt(max(nis, 1e-12)):.2g}x too large; every sigma below is "
                "then too wide. `stellar-cal replay --estimate-noise` measures the scales.")
    if verdict != "model mismatch":
        return ""
    ref = cons.get("reference_nis_per_dof")
    ref_text = f", reference NIS/dof {ref:.2f}" if ref is not None else ""
    return (f"MODEL MISMATCH{rescaled}: star NIS/dof {nis:.2f}{ref_text} (expected "
            f"{cons['interval'][0]:.2f}-{cons['interval'][1]:.2f}), whiteness p = "
            f"{cons['whiteness_p']:.2g}: the model misses an effect or the stated noise is "
            f"wrong (a star sigma {math.sqrt(max(nis, 0.0)):.2g}x too small, or a gyro noise "
            "too small, looks alike); every sigma below is conditional on this. Run "
            "`stellar-cal diagnose --auto`: it measures the noise first, then tests the "
            "effects (or `replay --estimate-noise` for the noise alone).")


#: counters that say the input broke the contract (repaired, bridged or skipped): any of
#: them makes a residual structure suspect before any model effect is
DATA_FAULTS = {
    "imu_invalid": "IMU samples with non-finite values or stamps (bridged)",
    "imu_late": "IMU samples older than the released ones (dropped)",
    "imu_duplicate": "IMU samples with a repeated stamp (dropped)",
    "imu_gaps": "gaps in the IMU stream (bridged)",
    "imu_long_gaps": "IMU gaps too long to bridge (filter re-acquired)",
    "frames_late": "star frames later than the reorder window (dropped)",
    "frames_duplicate": "star frames with a repeated stamp (dropped)",
    "frames_overflow": "star frames dropped by a full queue",
    "skipped_out_of_order": "star frames out of order (skipped)",
    "skipped_no_imu": "star frames without IMU around them (skipped)",
    "stars_bad_sigma": "stars with a negative or NaN centroid sigma (default used)",
    # the driver counts every star of a message its rule does not use (frames.star_masks)
    "stars_invalid": "stars not usable: non-finite, unidentified or off the detector "
                     "(dropped)",
    "env_invalid": "invalid environment samples (dropped)",
    "fixes_invalid": "invalid position fixes (dropped)",
    # what the bag reader read past (``--on-error skip``): a truncated recording is
    # calibrated on what it holds, said here rather than "no input fault counted"
    "messages_skipped": "malformed messages (skipped)",
    "bag_parts_lost": "damaged or truncated parts of the bag (skipped; `stellar-cal info` "
                      "lists them)",
}
#: gated stars beyond this many times the gate's false-alarm count (and at least
#: :data:`GATED_MIN`) point at misidentified stars rather than noise — when the accepted
#: stars are consistent (NIS/dof ≤ :data:`GATED_CONSISTENT`); a model far off gates stars
#: (and loses lock) by itself, and that is the diagnosis's business, not the data's
GATED_FACTOR = 20.0
GATED_MIN = 10
GATED_CONSISTENT = 1.5


def data_quality(counters: dict[str, Any], stars_accepted: int,
                 nis_per_dof: float = math.nan, gate_probability: float = 0.9999,
                 heavy_tails: bool = False) -> list[str]:
    """What the counters say about the input, one phrase each (empty: nothing wrong).

    A diagnosis reads these first: a bridged IMU gap or misidentified stars leave residual
    structure that a model effect would fit for the wrong reason.  ``nis_per_dof``: of the
    accepted stars (NaN: unknown, gated stars judged alone).  ``heavy_tails``: the noise
    verdict found the accepted stars' noise heavy-tailed
    (:func:`~stellar_cal_ros.diagnosis.noise.heavy_tails`); the stars the gate rejects are
    then its tails, said with the noise, not "misidentified stars" of damaged input (one
    claim about one piece of evidence: unseen case ``t3`` read both).
    """
    out = [f"{int(counters[k])} {text}" for k, text in DATA_FAULTS.items()
           if counters.get(k)]
    gated = int(counters.get("stars_gated", 0))
    expected = (1.0 - gate_probability) * (stars_accepted + gated)
    consistent = not nis_per_dof > GATED_CONSISTENT
    if consistent and not heavy_tails and gated > max(GATED_MIN, GATED_FACTOR * expected):
        share = gated / max(stars_accepted + gated, 1)
        out.append(f"{gated} stars gated ({100 * share:.2g} % of {stars_accepted + gated}; "
                   f"a consistent model gates about {expected:.0f}) while the accepted ones "
                   "fit: misidentified stars")
    return out


def counts_line(counters: dict[str, Any]) -> str:
    """The input counters in one line (the non-zero ones): what replay and the diagnosis print."""
    return "counts: " + ", ".join(f"{k}={v}" for k, v in counters.items() if v)


def quality_line(faults: list[str], then: str = "", lead: str = "data quality first") -> str:
    """The data faults of :func:`data_quality` in one line ('' when there are none).

    The one phrasing of replay's end-of-run summary and the diagnosis's terminal; ``then``:
    what to do besides repairing the data (the diagnosis: judge its candidates with it);
    ``lead``: the diagnosis's "data quality first" (read before its candidates, and what the
    fault campaign reads as a run's flag, :func:`~stellar_cal_ros.sim.fault_campaign.
    result_flag`), replay's "data quality" (its counted skips are no flag: the result's
    ``data_quality.degraded`` is).
    """
    if not faults:
        return ""
    from stellar_cal_ros.errors import held_damage_note

    note = held_damage_note()  # (the command line under --on-error skip: counted once here)
    return (f"{lead}: " + "; ".join(faults + ([note] if note else [])) + ". Residual "
            "structure from damaged "
            "input looks like a missing effect: repair the data" + (f" ({then})" if then else "")
            + ".")


# ---------------------------------------------------------------------------- results
@dataclass
class ReplayResult:
    """Outputs of a filter run."""

    calibration: Calibration
    covariance: tuple[list[str], np.ndarray]  #: names and covariance of the estimated θ
    residuals: dict[str, np.ndarray]
    history: dict[str, np.ndarray]
    counters: dict[str, int]
    read_seconds: float
    filter_seconds: float
    duration: float
    filter: Any = None
    derived: dict[str, Any] = field(default_factory=dict)
    stats: RunStats | None = None
    method: str = ""
    effects: list[str] = field(default_factory=list)
    #: frames released with a stale input only the consider parameters need (stamps, ns)
    consider_stale_ns: list[int] = field(default_factory=list)

    @property
    def speed(self) -> float:
        """Bag seconds per wall-clock second (reading + filtering)."""
        return self.duration / max(self.read_seconds + self.filter_seconds, 1e-9)


def result_calibration(prior: Calibration, model: StarModel, theta: np.ndarray,
                       sigma: np.ndarray, method: str, stamp: float,
                       estimated: int | None = None) -> Calibration:
    """The prior with every estimated effect stored; σ of the estimated quantities only.

    ``estimated``: how many leading entries of θ are estimated (the rest are consider
    parameters, not stored); default all.  See :func:`~stellar_cal_ros.io.calibration.
    store_estimate` (the result lists its estimated effects).
    """
    n = model.size if estimated is None else estimated
    effects = [e for e in model.effects if model.slices[e.id].stop <= n]
    return store_estimate(prior, effects, model.slices, theta, sigma, method, stamp)


def boresight_pixel(camera, R_imu_st: np.ndarray, boresight_imu: np.ndarray) -> np.ndarray:
    """Image position (px) of the IMU-fixed direction ``boresight_imu``, to first order.

    ``(cx + fx·d_x/d_z, cy + fy·d_y/d_z)`` with ``d = R_imu_stᵀ b``: for the nominal boresight,
    the equivalent principal point (Tan et al. §3.4) — the one definition used by the
    results, the diagnosis and the fault campaign.
    """
    d = R_imu_st.T @ np.asarray(boresight_imu, dtype=float)
    return np.array([camera.cx + camera.fx * d[0] / d[2], camera.cy + camera.fy * d[1] / d[2]])


def epp_jacobian(model: StarModel, theta: np.ndarray, columns: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The equivalent principal point at ``theta`` and its gradient (2, columns).

    The gradient with respect to ``theta[:columns]`` by central differences (step
    ``1e-6 · max(1, |θ_j|)``).
    """
    ctx = FrameContext(stamp=0.0)
    b = model.prior.R_imu_st[:, 2]  # nominal boresight in the IMU frame

    def value(th: np.ndarray) -> np.ndarray:
        return boresight_pixel(model.camera_at(th, ctx), model.installation_at(th, ctx)[0], b)

    J = np.zeros((2, columns))
    for j in range(columns):
        h = 1e-6 * max(1.0, abs(theta[j]))
        tp, tm = theta.copy(), theta.copy()
        tp[j] += h
        tm[j] -= h
        J[:, j] = (value(tp) - value(tm)) / (2 * h)
    return value(theta), J


def equivalent_principal_point(model: StarModel, theta: np.ndarray,
                               P_theta: np.ndarray) -> dict[str, Any]:
    """Image position of the IMU-fixed nominal boresight (Tan et al. §3.4), with sigma.

    ``(cx − fx·δ_y, cy + fy·δ_x)`` to first order (:func:`boresight_pixel`): the combination
    of principal point and installation tilt that a star tracker observes directly; it
    converges long before its two parts separate.  ``P_theta`` covers the leading entries of
    θ it has rows for.
    """
    v0, J = epp_jacobian(model, theta, len(P_theta))
    cov = J @ P_theta @ J.T
    return {"equivalent_principal_point_px": [float(v0[0]), float(v0[1])],
            "equivalent_principal_point_sigma_px": [float(np.sqrt(cov[0, 0])),
                                                    float(np.sqrt(cov[1, 1]))]}


def derived_quantities(model: StarModel, theta: np.ndarray, P_theta: np.ndarray) -> dict:
    """The observable combinations: equivalent principal point, installation about z."""
    from stellar_cal_ros.core.units import ARCSEC

    out = dict(equivalent_principal_point(model, theta, P_theta))
    if "installation" in model.slices:
        k = model.slices["installation"].start + 2
        out["installation_boresight_arcsec"] = float(theta[k] / ARCSEC)
        out["installation_boresight_sigma_arcsec"] = float(
            np.sqrt(max(P_theta[k, k], 0.0)) / ARCSEC)
    return out


def truth_parameters(model: StarModel, truth: Calibration) -> np.ndarray:
    """θ of a true calibration in the model's layout (for tests and benchmarks only).

    Every effect reads its value from ``truth`` as it would from a prior, except the
    installation, whose parameter is the rotation from the *prior's* nominal mounting:
    ``δ = Log(R_priorᵀ R_truth)``.
    """
    out = np.empty(model.size)
    for eff in model.effects:
        sl = model.slices[eff.id]
        if eff.id == "installation":
            out[sl] = (model.prior.installation.inv() * truth.installation).as_rotvec()
        else:
            value, _ = copy.deepcopy(eff).initial(truth)  # a copy: initial() may keep state
            out[sl] = value
    return out


def loss_line(record: dict) -> str:
    """One line of what a read past damage lost (``--on-error skip``; '' when nothing)."""
    if not record.get("bag_parts_lost") and not record.get("messages_skipped"):
        return ""
    read = record.get("seconds_read")
    return quality_line(data_quality(record, 0) + (
        [f"{read:.1f} s of data read"] if read is not None else []), lead="data quality")
