"""core.distributions against scipy.stats: the same values over grids that include the edges.

The package computes its p-values, critical values and scores with
:mod:`stellar_cal_ros.core.distributions` (scipy.special's ufuncs: no ``scipy.stats``
import, ≈ 20 MiB of a round, issue 24.2).  Each function here is compared with its
``scipy.stats`` namesake at 1e-12 relative (nan where it gives nan, a scalar where it gives
one) on arguments inside, at and beyond the support and the shapes' ranges.
"""

from __future__ import annotations

import itertools
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from scipy import stats

from stellar_cal_ros.core import distributions as dist

X = np.r_[-np.inf, -50.0, -3.0, -1.0, -1e-300, -0.0, 0.0, 1e-300, 1e-8, 0.05, 0.5, 1.0,
          1.5, 2.0, 3.7, 10.0, 37.0, 80.0, 300.0, 1e4, np.inf, np.nan]
Q = np.r_[-0.1, 0.0, 1e-300, 1e-30, 1e-12, 1e-6, 0.001, 0.025, 0.05, 0.2, 0.5, 0.8, 0.975,
          0.999, 1 - 1e-12, 1.0, 1.1, np.nan]
DF = [-1.0, 0.0, 0.5, 1, 2, 3, 7.5, 30, 200, 5000, np.inf, np.nan]
NC = [-1.0, 0.0, 1e-3, 0.5, 3.0, 12.0, 60.0, np.nan]


def _same(mine, theirs, what: str) -> None:
    assert np.ndim(mine) == np.ndim(theirs), what
    np.testing.assert_allclose(np.asarray(mine, float), np.asarray(theirs, float), rtol=1e-12,
                               atol=0.0, equal_nan=True, err_msg=what)


def _grid(*axes):
    """The arguments' grid, each as a flat array (every combination once)."""
    return [np.array(c, dtype=float) for c in zip(*itertools.product(*axes), strict=True)]


@pytest.mark.parametrize("name, method, axes", [
    ("chi2", "sf", (X, DF)), ("chi2", "isf", (Q, DF)), ("chi2", "ppf", (Q, DF)),
    ("ncx2", "sf", (X, DF, NC)),
    ("norm", "sf", (X,)), ("norm", "ppf", (Q,)), ("norm", "isf", (Q,)),
    ("t", "sf", (X, DF)), ("t", "cdf", (X, DF)), ("t", "isf", (Q, DF)),
    ("f", "sf", (X, DF, DF)),
    ("nct", "sf", (X, [0.5, 1, 3, 30, 200], [-3.0, -0.5, 0.0, 0.5, 2.0, 8.0, np.nan])),
])
def test_each_distribution_function_gives_scipy_stats_values(name, method, axes) -> None:
    mine, theirs = getattr(getattr(dist, name), method), getattr(getattr(stats, name), method)
    args = _grid(*axes)
    with np.errstate(all="ignore"):
        _same(mine(*args), theirs(*args), f"{name}.{method} on the grid")
        for one in zip(*args, strict=True):  # scalars in, scalars out
            _same(mine(*one), theirs(*one), f"{name}.{method}{one}")
        _same(mine(args[0][:3].tolist(), *(a[0] for a in args[1:])),  # a list and a scalar
              theirs(args[0][:3].tolist(), *(a[0] for a in args[1:])), f"{name}.{method} list")


def test_chi2_takes_integer_dof_arrays_and_lists_as_scipy_stats() -> None:
    for df in (1, 4, np.array([2, 10])):
        _same(dist.chi2.sf(np.array([0.5, 40.0]), df),
              stats.chi2.sf(np.array([0.5, 40.0]), df), f"chi2.sf df={df}")
        _same(dist.chi2.ppf([0.025, 0.975], df), stats.chi2.ppf([0.025, 0.975], df),
              f"chi2.ppf df={df}")


def test_binom_sf_gives_scipy_stats_values() -> None:
    k = [-np.inf, -3, -1, -0.5, 0, 0.5, 1, 2, 5, 9.99, 10, 11, 250, 1000, np.inf, np.nan]
    n = [-1, 0, 1, 10, 10.5, 300, 5000]
    p = [-0.1, 0.0, 1e-6, 0.011, 0.3, 0.5, 0.99, 1.0, 1.2, np.nan]
    args = _grid(k, n, p)
    with np.errstate(all="ignore"):
        _same(dist.binom.sf(*args), stats.binom.sf(*args), "binom.sf on the grid")
        _same(dist.binom.sf(12, 3000, 0.011), stats.binom.sf(12, 3000, 0.011), "binom.sf int")


def test_norm_pdf_with_loc_and_scale_gives_scipy_stats_values() -> None:
    x = np.linspace(-6, 6, 97)
    for loc, scale in ((0, 1), (0, 0.37), (1.5, 2.0), (0, 0.0), (0, -1.0)):
        with np.errstate(all="ignore"):
            mine, theirs = dist.norm.pdf(x, loc, scale), stats.norm.pdf(x, loc, scale)
        _same(mine, theirs, f"pdf {loc} {scale}")
    _same(dist.norm.pdf(X), stats.norm.pdf(X), "pdf edges")


def test_rankdata_gives_scipy_stats_ranks() -> None:
    rng = np.random.default_rng(3)
    for x in (rng.normal(size=501), rng.integers(0, 7, size=300).astype(float),
              np.array([3.0, 2, 1, 2, 2, 2, 1]), np.array([1.0]), np.zeros(0),
              np.array([1.0, np.nan, 0.0]), rng.normal(size=(4, 5)), np.r_[-0.0, 0.0, 1]):
        np.testing.assert_array_equal(dist.rankdata(x), stats.rankdata(x))


def test_no_module_of_the_package_imports_scipy_stats() -> None:
    """Every module but the ROS nodes imported: no ``scipy.stats`` (nor ``scipy.signal``,
    which imports it; noise_structure imports it only for an AR(1) part)."""
    code = textwrap.dedent("""
        import importlib, pkgutil, sys
        import stellar_cal_ros
        for m in pkgutil.walk_packages(stellar_cal_ros.__path__, "stellar_cal_ros."):
            if not m.name.startswith(("stellar_cal_ros.nodes", "stellar_cal_ros.__main__")):
                importlib.import_module(m.name)
        print(sorted(m for m in sys.modules if m.startswith(("scipy.stats", "scipy.signal"))))
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.splitlines()[-1] == "[]", proc.stdout[-2000:]
