"""Cheaper bookkeeping of the replay, same values (issue 17, item 2).

* the site is a running median over the window of fixes: equal to ``np.median`` of the
  window after every fix, with duplicates, even and odd counts and eviction;
* residual CSV cells are written with ``repr``/``str`` straight from ``tolist()``: the same
  text as the per-element formatting they replace.
"""

from __future__ import annotations

import numpy as np

from stellar_cal_ros.io.residuals import _format
from stellar_cal_ros.methods.frames import SiteEstimator


def test_running_median_equals_numpy_median_of_the_window() -> None:
    rng = np.random.default_rng(7)
    est = SiteEstimator(max_fixes=7)
    kept: list[tuple[float, float, float]] = []
    for i in range(60):
        row = (float(rng.choice([10.0, 10.5, rng.normal(10, 1)])), float(rng.normal(110, 1)),
               float(rng.integers(0, 3)))
        assert est.add(i, *row)
        kept = (kept + [row])[-7:]
        a = np.array(kept)
        site = est.site
        assert (site.latitude_deg, site.longitude_deg, site.height_m) == tuple(
            float(np.median(a[:, k])) for k in range(3))
    assert not est.add(61, float("nan"), 0.0, 0.0)  # invalid: not added, site unchanged
    assert est.site is site


def _reference_format(col: np.ndarray) -> list[str]:
    """The per-element formatting ``_format`` replaced."""
    if col.dtype == bool:
        return ["True" if x else "False" for x in col.tolist()]
    if np.issubdtype(col.dtype, np.integer):
        return [str(int(x)) for x in col.tolist()]
    if np.issubdtype(col.dtype, np.floating):
        return [repr(float(x)) if np.isfinite(x) else str(float(x)) for x in col.tolist()]
    return [str(x) for x in col.tolist()]


def test_csv_cells_unchanged() -> None:
    rng = np.random.default_rng(8)
    cols = [rng.normal(size=500) * 10.0 ** rng.integers(-300, 300, 500),
            np.array([np.nan, np.inf, -np.inf, 0.0, -0.0, 5e-324, 1e300]),
            rng.normal(size=50).astype(np.float32), rng.integers(-10**15, 10**15, 50),
            np.arange(5, dtype=np.uint32), rng.random(50) > 0.5, np.array(["a", "b c"])]
    for col in cols:
        assert _format(col) == _reference_format(col), col.dtype
