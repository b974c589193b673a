"""The per-star repeat and detector-cell χ² on pure AR(1) star tracks: do their p hold the level.

The stars' noise tests (:func:`~stellar_cal_ros.diagnosis.noise_stars.star_noise`) refer the
χ² of the star means and of the detector cells' means to the lag correlation of the tracks
(:func:`~stellar_cal_ros.diagnosis.noise_structure.track_inflation` estimates ``ρ``,
:func:`~stellar_cal_ros.diagnosis.noise_structure.lagged_chi2` divides each mean by the
exact variance of a mean of its tracks' frames; the repeat is the stars' sum of squares
after the cells' means, :func:`~stellar_cal_ros.diagnosis.noise_stars.star_after_cells`,
referred to the exact trace of the AR(1) covariance through its projection).  Here the
residuals are pure AR(1) tracks of known ``ρ`` (unit variance, 10-80 frames each, 150
stars, each track crossing 1-3 of 108 cells in consecutive segments, rows in time order
as a residual table holds them), so both p-values must be uniform: the table prints their
mean (0.5), the share below 5 % and 1 %, Kolmogorov-Smirnov's p, and the same for the
long-run factor ``(1 + ρ)/(1 − ρ)`` with the approximate ``ρ`` the tests had before
(``--old``; its repeat rows are ``star_after_cells`` divided by that factor since H53, not
the star-mean count the repeat had before).

White + AR(1) tracks (``--rho 0.81873:0.265``: the AR(1) carries 0.265 of the variance,
the rest white) are read by the tracks' white + AR(1) model
(:func:`~stellar_cal_ros.diagnosis.noise_structure.track_model`); ``--pure`` reads every
draw as one AR(1) of its lag-1 ρ, as before that model.

Run::

    .venv/bin/python benchmarks/ar1_level.py --reps 1000 --rho 0.81873,0.5,0,0.81873:0.265
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy import stats as sps

from stellar_cal_ros.diagnosis import noise_structure as ns
from stellar_cal_ros.diagnosis.noise_stars import _minus_cell_means, star_after_cells, star_means

#: the cells of noise_stars (6 x 6 grid x 3 magnitude classes) and its CELL_MIN
CELLS, CELL_MIN = 108, 8


def draw(rng, rho: float, stars: int = 150, lengths: tuple[int, int] = (10, 80),
         share: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``stars`` AR(1) tracks (u, v) of unit variance: rows ``(n, 2)``, star ids, cell ids.

    Each track has a length uniform in ``lengths``, starts at a frame in [0, 200) and
    crosses 1-3 cells in consecutive segments; rows sorted by frame (then star).
    ``share`` below 1: white + AR(1) tracks, the AR(1) carrying ``share`` of the variance
    (a white draw after the rest; ``share`` 1 draws the same as before).
    """
    n = rng.integers(lengths[0], lengths[1] + 1, size=stars)
    x = np.empty((stars, lengths[1], 2))
    x[:, 0] = rng.standard_normal((stars, 2))
    e = rng.standard_normal((stars, lengths[1], 2)) * np.sqrt(1.0 - rho**2)
    for t in range(1, lengths[1]):
        x[:, t] = rho * x[:, t - 1] + e[:, t]
    start = rng.integers(0, 200, size=stars)
    pieces = rng.integers(1, 4, size=stars)
    rows, star, cell, frame = [], [], [], []
    for s in range(stars):
        cuts = np.sort(rng.choice(np.arange(1, n[s]), size=pieces[s] - 1, replace=False))
        seg = np.searchsorted(cuts, np.arange(n[s]), side="right")
        rows.append(x[s, :n[s]])
        star.append(np.full(n[s], s))
        cell.append(rng.integers(0, CELLS, size=pieces[s])[seg])
        frame.append(start[s] + np.arange(n[s]))
    r, star, cell, frame = (np.concatenate(a) for a in (rows, star, cell, frame))
    if share != 1.0:
        r = np.sqrt(share) * r + np.sqrt(1.0 - share) * rng.standard_normal(r.shape)
    order = np.lexsort((star, frame))
    return r[order], star[order], cell[order]


def pvalues(r: np.ndarray, star: np.ndarray, cell: np.ndarray, old: bool = False
            ) -> tuple[float, float, float]:
    """(repeat p, cells p, ρ) as the stars' noise tests make them, each test on ``r`` alone.

    ``old``: the long-run factor with the ``(ρ̂ + b)/(1 − b)`` correction they had before.
    """
    keep = np.bincount(cell)[cell] >= CELL_MIN
    _, _, chi2, dof = _minus_cell_means(r, cell, keep)
    _, _, r_star, _ = star_means(r, np.ones(len(r)), star)
    if old:
        rho = _old_rho(r_star, star)
        f = (1.0 + rho) / (1.0 - rho)
        rep, rep_dof = star_after_cells(r, cell, keep, star)
        rep, chi2 = rep / f, chi2 / f
    else:  # the tracks' white + AR(1) model (a pure AR(1) unless the lags ask for white)
        track = ns.track_model(r_star, star)
        rho = track.phi
        rep, rep_dof = star_after_cells(r, cell, keep, star, None, rho, track.share)
        if rho > 0:
            chi2 = ns.lagged_chi2(r, cell, star, rho, keep, share=track.share)
    return float(sps.chi2.sf(rep, rep_dof)), float(sps.chi2.sf(chi2, dof)), float(rho)


def _old_rho(r: np.ndarray, star: np.ndarray) -> float:
    """The pooled lag-1 ρ corrected by ``(1 + ρ) b`` (before the exact moments)."""
    order = np.argsort(star, kind="stable")
    rr, st = r[order], star[order]
    same = st[1:] == st[:-1]
    a, b = rr[1:][same], rr[:-1][same]
    raw = float(np.sum(a * b)) / np.sqrt(float(np.sum(a * a)) * float(np.sum(b * b)))
    n = np.bincount(np.unique(st, return_inverse=True)[1]).astype(float)
    bias = float(np.sum(1.0 - 1.0 / n[n >= 2])) / int(same.sum())
    return float(np.clip((raw + bias) / (1.0 - bias), 0.0, 0.95))


def main() -> int:
    """Print the level table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=1000)
    ap.add_argument("--rho", default="0.81873,0.5,0",
                    help="AR(1) coefficients, each RHO or RHO:SHARE (white + AR(1), the AR "
                         "carrying SHARE of the variance)")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--old", action="store_true", help="also the long-run factor")
    ap.add_argument("--pure", action="store_true",
                    help="the tracks read as one AR(1) of their lag-1 rho (before H59)")
    args = ap.parse_args()
    if args.pure:
        ns.SHARE_Z = float("inf")
    print(f"{'rho':>7} {'share':>5} {'factor':>9} {'test':>7} {'mean p':>12} {'p<5%':>6} "
          f"{'p<1%':>6} {'KS p':>7} {'rho hat':>13}")
    for item in args.rho.split(","):
        rho_s, _, share_s = item.partition(":")
        rho, share = float(rho_s), float(share_s or 1.0)
        for old in ((False, True) if args.old else (False,)):
            rng = np.random.default_rng(args.seed)
            t0 = time.process_time()
            P = np.array([pvalues(*draw(rng, rho, share=share), old=old)
                          for _ in range(args.reps)])
            for j, name in enumerate(("repeat", "cells")):
                p = P[:, j]
                print(f"{rho:7.4g} {share:5.3g} {'long-run' if old else 'finite':>9} {name:>7} "
                      f"{p.mean():6.3f}+-{p.std() / np.sqrt(len(p)):.3f} "
                      f"{np.mean(p < 0.05):6.3f} {np.mean(p < 0.01):6.3f} "
                      f"{sps.kstest(p, 'uniform').pvalue:7.2g} "
                      f"{P[:, 2].mean():6.3f}+-{P[:, 2].std():.3f}")
            print(f"        ({args.reps} draws, {time.process_time() - t0:.1f} CPU-s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
