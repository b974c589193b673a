"""Per-star residual tables: write and read CSV (always) or Parquet (if pyarrow is installed).

A residual table is a ``dict[str, numpy.ndarray]`` of equal-length 1-D columns.  The batch
(ACF) solver and the Kalman filters write the columns

``t, frame, catalog_id, u, v, u_pred, v_pred, du, dv, s_uu, s_uv, s_vv, magnitude, gated``

(``t`` the frame's POSIX time in s — its ``header.stamp``, as the star tracker reported it —
``frame`` its index in the bag, ``du = u − u_pred``, ``s_*`` the innovation covariance in px²,
``gated`` True where the measurement was rejected / down-weighted); the Kalman filters add
``nis``, the star direction ``x_st y_st z_st``, the body rate ``omega_*`` (rad/s) and the
``head_temperature`` (°C, NaN without one).  Any further columns are allowed and kept in
order.  A history table (``RESULT.history.csv``) has one row per update: ``t`` (POSIX s),
``nis``, ``dof``, ``stars``, ``gated``, ``iterations``, then every parameter
``effect.parameter`` and its ``sigma.effect.parameter`` in the effects' units.

CSV round trip: floats are written with 17 significant digits (exact), integers as integers,
booleans as ``True``/``False``.  :func:`read_residuals` infers each column's type back (bool if
every cell is ``True``/``False``, int64 if every cell is an integer literal, float64 if every
cell parses as a number, otherwise str).
"""

from __future__ import annotations

import csv
import os
import sys
from pathlib import Path

import numpy as np

from stellar_cal_ros.errors import StellarCalError

#: a table of at least this many cells is written by the compiled formatter even when
#: numba is not loaded yet (loading it costs ≈ 0.5 CPU-s; repr ≈ 0.5 µs a cell)
_COMPILED_CELLS = 2_000_000

RESIDUAL_COLUMNS = ("t", "frame", "catalog_id", "u", "v", "u_pred", "v_pred", "du", "dv",
                    "s_uu", "s_uv", "s_vv", "magnitude", "gated")


def _columns(table: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    if not table:
        raise StellarCalError("residual table has no columns")
    cols = {str(k): np.asarray(v) for k, v in table.items()}
    lengths = {k: v.shape[0] if v.ndim == 1 else -1 for k, v in cols.items()}
    if any(n < 0 for n in lengths.values()):
        bad = [k for k, n in lengths.items() if n < 0]
        raise StellarCalError(f"residual columns must be 1-D, not {bad}")
    if len(set(lengths.values())) > 1:
        raise StellarCalError(f"residual columns differ in length: {lengths}")
    return cols


def _format(col: np.ndarray) -> list[str]:
    """CSV cells of a column, straight from ``tolist()``.

    Floats as ``repr`` (shortest round trip; ``nan``, ``inf``, ``-inf`` too: ``repr`` and
    ``str`` agree on Python floats), anything else (``True``/``False``, integers) as ``str``.
    """
    if col.dtype.kind == "f":
        return list(map(repr, col.tolist()))
    return list(map(str, col.tolist()))


def _compiled_text(cols: list[np.ndarray]) -> str | None:
    """The rows' text from the compiled formatter, or None (then ``repr`` writes them).

    :func:`.float_text.table_text` writes the bytes ``repr`` writes, ≈ 6x faster on
    full-precision floats (a 2-h replay's history: 0.4 -> 0.1 CPU-s); used when numba is
    loaded anyway or the table is large enough to pay for loading it.
    """
    if len(cols[0]) * len(cols) < _COMPILED_CELLS and "numba" not in sys.modules:
        return None
    from stellar_cal_ros.core import float_text  # imports numba

    return float_text.table_text(cols)


def _write_rows(fh, csv_writer, cols: list[np.ndarray]) -> None:
    """The CSV rows of ``cols``: joined directly when no cell can need quoting.

    Numbers and booleans (``repr``/``str`` of floats, integers, ``True``/``False``) never
    hold a delimiter, quote or line break, so the ``excel`` dialect writes them as
    ``cell,cell,...`` and CRLF — the same bytes, without the writer's per-cell checks; any other
    column (strings) goes through ``csv_writer``.
    """
    if len(cols) > 1 and all(c.dtype.kind in "fiub" for c in cols):
        text = _compiled_text(cols)
        if text is not None:
            fh.write(text)
            return
        if len(cols[0]):
            # the rows' cells in one C pass: ``repr`` of a list of tuples of Python floats,
            # ints and bools writes each cell as ``repr`` (= ``str`` for ints and bools) and
            # joins them with ", " and "), (" — strings no number's cells hold — 1.6x faster
            # than a ``repr`` call per cell (a 1 024-row history chunk: 68 -> 42 ms)
            text = repr(list(zip(*[c.tolist() for c in cols], strict=True)))
            fh.write(text[2:-2].replace("), (", "\r\n").replace(", ", ",") + "\r\n")
        return
    formatted = [_format(c) for c in cols]
    if formatted and all(c.dtype.kind in "fiub" for c in cols):
        if formatted[0]:
            fh.write("\r\n".join(formatted[0]) + "\r\n")
        return
    csv_writer.writerows(zip(*formatted, strict=True))


def write_residuals(path: str | os.PathLike[str], table: dict[str, np.ndarray]) -> Path:
    """Write a residual table to ``path`` (``.parquet`` → Parquet, anything else → CSV).

    Raises
    ------
    StellarCalError
        Columns of different lengths / not 1-D, or ``.parquet`` without pyarrow.
    """
    path = Path(path)
    cols = _columns(table)
    if path.suffix.lower() == ".parquet":
        try:
            import pyarrow as pa
            import pyarrow.parquet as pq
        except ImportError:
            raise StellarCalError(
                f"cannot write {path}: Parquet needs pyarrow, which is not installed; "
                "write a .csv file instead") from None
        pq.write_table(pa.table({k: pa.array(v) for k, v in cols.items()}), path)
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(list(cols))
        _write_rows(fh, w, list(cols.values()))
    return path


def _parse(cells: list[str]) -> np.ndarray:
    if cells and all(c in ("True", "False") for c in cells):
        return np.array([c == "True" for c in cells], dtype=bool)
    try:
        return np.array([int(c) for c in cells], dtype=np.int64)
    except ValueError:
        pass
    try:
        return np.array([float(c) for c in cells], dtype=np.float64)
    except ValueError:
        return np.array(cells, dtype=str)


def read_residuals(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Read a table written by :func:`write_residuals` (CSV, or Parquet with pyarrow)."""
    path = Path(path)
    if not path.is_file():
        raise StellarCalError(f"residual file {path} does not exist")
    if path.suffix.lower() == ".parquet":
        try:
            import pyarrow.parquet as pq
        except ImportError:
            raise StellarCalError(f"cannot read {path}: Parquet needs pyarrow, which is not "
                                  "installed") from None
        t = pq.read_table(path)
        return {name: t.column(name).to_numpy() for name in t.column_names}
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise StellarCalError(f"residual file {path} is empty")
    header, body = rows[0], rows[1:]
    if any(len(r) != len(header) for r in body):
        raise StellarCalError(f"residual file {path}: rows of unequal length")
    return {name: _parse([r[i] for r in body]) for i, name in enumerate(header)}


class TableWriter:
    """Append table chunks to a CSV or Parquet file (the columns fixed by the first chunk).

    ``with TableWriter(path) as w: w.append(chunk)`` — each chunk a dict of equal-length
    1-D arrays with the same columns.  CSV rows are written as they come; Parquet chunks are
    buffered into row groups of at least ``row_group`` rows.
    """

    def __init__(self, path: str | os.PathLike[str], row_group: int = 65536) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.parquet = self.path.suffix.lower() == ".parquet"
        self.row_group = int(row_group)
        self.columns: list[str] | None = None
        self.rows = 0
        self._fh = None
        self._csv = None
        self._pq = None
        self._pending: list[dict[str, np.ndarray]] = []
        self._pending_rows = 0

    def __enter__(self) -> TableWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def append(self, table: dict[str, np.ndarray]) -> None:
        """Append one chunk."""
        cols = _columns(table)
        n = len(next(iter(cols.values())))
        if self.columns is None:
            self.columns = list(cols)
            if not self.parquet:
                self._fh = open(self.path, "w", newline="")  # noqa: SIM115 (closed in close)
                self._csv = csv.writer(self._fh)
                self._csv.writerow(self.columns)
        elif list(cols) != self.columns:
            raise StellarCalError(f"{self.path}: chunk columns {list(cols)} differ from "
                                  f"{self.columns}")
        self.rows += n
        if not n:
            return
        if self.parquet:
            self._pending.append(cols)
            self._pending_rows += n
            if self._pending_rows >= self.row_group:
                self._flush_parquet()
        else:
            _write_rows(self._fh, self._csv, [cols[k] for k in self.columns])

    def _flush_parquet(self) -> None:
        if not self._pending:
            return
        try:
            import pyarrow as pa
            import pyarrow.parquet as pq
        except ImportError:
            raise StellarCalError(f"cannot write {self.path}: Parquet needs pyarrow") from None
        merged = {k: np.concatenate([c[k] for c in self._pending]) for k in self.columns}
        tab = pa.table({k: pa.array(v) for k, v in merged.items()})
        if self._pq is None:
            self._pq = pq.ParquetWriter(self.path, tab.schema)
        self._pq.write_table(tab)
        self._pending, self._pending_rows = [], 0

    def close(self) -> None:
        """Flush and close (a file with only the header if nothing was appended)."""
        if self.parquet:
            self._flush_parquet()
            if self._pq is not None:
                self._pq.close()
                self._pq = None
        elif self._fh is not None:
            self._fh.close()
            self._fh = None
