"""The compiled table formatter writes what ``repr``/``str`` write, byte for byte (issue 24.1)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stellar_cal_ros.core import float_text
from stellar_cal_ros.io import residuals

pytestmark = pytest.mark.skipif(not float_text.HAVE_NUMBA, reason="needs numba")


def _by_repr(cols: list[np.ndarray]) -> str:
    """Each row's cells as repr (floats) / str (ints, bools), joined by ',' and CRLF."""
    rows = zip(*[c.tolist() for c in cols], strict=True)
    return "".join(",".join(repr(v) if isinstance(v, float) else str(v) for v in row) + "\r\n"
                   for row in rows)


def _specials() -> np.ndarray:
    v = [0.0, -0.0, math.nan, -math.nan, math.inf, -math.inf, 5e-324, 1e-323,
         2.2250738585072014e-308, 2.225073858507201e-308, 1.7976931348623157e308,
         # repr's layout boundaries: fixed for 1e-4 <= |x| < 1e16, else exponent
         1e16, 9999999999999998.0, 1e15, 1e17, 1.5e16, 1e-4, 1e-5, 9.999999999999999e-05,
         0.0001, 0.00012345, 1.5e-5, 123.0, 1e22, 1e23, 0.1, 0.3, 2 / 3, 4.35, 0.5, 1.25,
         9007199254740993.0, 1e100, 1e-100, 1e300, 1e-300]
    v += [2.0 ** e for e in range(-1074, 1024)]
    v += [10.0 ** e for e in range(-323, 309)]
    v += [math.nextafter(x, math.inf) for x in v if math.isfinite(x)]
    v += [-x for x in v]
    return np.array(v, dtype=np.float64)


def test_specials_every_power_of_two_and_ten_and_layout_boundaries_as_repr():
    x = _specials()
    assert float_text.table_text([x]) == _by_repr([x])


def test_a_million_random_doubles_of_every_exponent_as_repr():
    rng = np.random.default_rng(20261127)
    bits = rng.integers(0, 2 ** 64, 1_000_000, dtype=np.uint64, endpoint=False)
    x = bits.view(np.float64)  # every exponent, subnormals and NaN payloads
    y = rng.standard_normal(200_000) * np.exp(rng.uniform(-40, 40, 200_000))
    z = rng.integers(-10 ** 7, 10 ** 7, 200_000) / 10.0 ** rng.integers(0, 8, 200_000)
    for col in (x, y, z):
        assert float_text.table_text([col]) == _by_repr([col])


def test_mixed_columns_ints_bools_and_narrow_floats_as_str_and_repr():
    rng = np.random.default_rng(3)
    n = 1000
    cols = [rng.standard_normal(n), rng.integers(-5, 60, n), rng.random(n) < 0.3,
            rng.standard_normal(n).astype(np.float32),
            np.array([np.iinfo(np.int64).min, np.iinfo(np.int64).max, 0, -1] * (n // 4)),
            rng.integers(0, 2 ** 32, n, dtype=np.uint32), np.full(n, 7.0)]
    assert float_text.table_text(cols) == _by_repr(cols)
    # columns it does not write: None, and the caller writes with repr
    assert float_text.table_text([np.array(["a"] * 3), np.zeros(3)]) is None
    assert float_text.table_text([np.array([2 ** 64 - 1], dtype=np.uint64)]) is None


def test_history_file_the_same_bytes_with_and_without_the_compiled_path(tmp_path, monkeypatch):
    rng = np.random.default_rng(5)
    n = 300
    table = {"t": 1.7953488e9 + np.arange(n) * 0.5 + 0.0037003, "nis": rng.chisquare(40, n),
             "dof": rng.integers(30, 50, n), "gated": rng.random(n) < 0.1,
             "x": rng.standard_normal(n) * 1e-9, "sigma.x": np.exp(rng.uniform(-30, 5, n))}
    monkeypatch.setattr(residuals, "_COMPILED_CELLS", 0)
    residuals.write_residuals(tmp_path / "a.csv", table)
    monkeypatch.setattr(residuals, "_compiled_text", lambda cols: None)  # repr's path
    residuals.write_residuals(tmp_path / "b.csv", table)
    a, b = (tmp_path / "a.csv").read_bytes(), (tmp_path / "b.csv").read_bytes()
    assert a == b
    back = residuals.read_residuals(tmp_path / "a.csv")
    for k, v in table.items():
        np.testing.assert_array_equal(back[k], v)
