"""Structure the stars' σ is measured without, beyond the cells' means and star means.

Part of :func:`~stellar_cal_ros.diagnosis.noise_stars.star_noise` (cases the diagnosis was not
built on, ``benchmarks/unseen_cases.py``): a bias periodic in the centroid's sub-pixel
phase (pixel locking) is removed before the variance is taken, and the per-star repeat's
and the detector cells' χ² are referred to the lag correlation noise correlated over frames
gives their means (:func:`lagged_chi2`, the exact variance of a finite track's mean).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats as sps
from scipy.optimize import brentq


def minus_subpixel(r: np.ndarray, share: np.ndarray, uv: np.ndarray, alpha: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """``r`` without a bias periodic in the sub-pixel phase of ``uv``, where it is significant.

    Per axis, the whitened residuals fitted by ``sin 2πu, cos 2πu`` (``v`` for the rows),
    the 4 coefficients' χ² tested at ``alpha``; when significant the fit is removed
    (pixel locking is structure, an 'unexplained' lead of its own, not noise: measured,
    unseen case ``scurve``, 0.08 px said as "sigma 1.46x too small"), each residual's share
    of its dof reduced by its leverage.  Otherwise ``r`` is returned unchanged.
    """
    ok = np.all(np.isfinite(r), axis=1) & (share > 0) & np.all(np.isfinite(uv), axis=1)
    if ok.sum() < 50:
        return r, share
    out, share_out, chi2, lev = r.copy(), share.copy(), 0.0, np.zeros(int(ok.sum()))
    fits = []
    for k in range(2):
        ph = 2.0 * np.pi * uv[ok, k]
        X = np.stack([np.sin(ph), np.cos(ph)], 1)
        G = np.linalg.inv(X.T @ X)
        b = G @ (X.T @ r[ok, k])
        chi2 += float(b @ np.linalg.solve(G, b)) / max(float(np.mean(share[ok])), 1e-12)
        fits.append(X @ b)
        lev += 0.5 * np.einsum("ij,jk,ik->i", X, G, X)
    if sps.chi2.sf(chi2, 4) >= alpha:
        return r, share
    out[ok] = r[ok] - np.stack(fits, 1)
    share_out[ok] = share[ok] * np.clip(1.0 - lev, 0.0, 1.0)
    return out, share_out


def minus_rolling(r: np.ndarray, share: np.ndarray, x: np.ndarray | None, alpha: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """``r`` without its fit by a rolling shutter's shape ``x``, where it is significant.

    ``x``: :func:`~stellar_cal_ros.diagnosis.stats.rolling_columns` projected and whitened
    as ``r`` (the within-frame residuals).  One coefficient (the readout time), its χ²
    tested at ``alpha``; when significant the fit is removed (a rolling shutter is
    structure, an 'unexplained' lead of its own, not noise: measured, unseen case
    ``sway_rolling``, 30 ms read as "sigma x39" grouped by row), each residual's share of
    its row's 2 dof reduced by half its leverage (the leverages sum to 1: one coefficient,
    one dof removed, as :func:`minus_subpixel` counts 4 for 4).  Otherwise ``r`` is
    returned unchanged.
    """
    if x is None:
        return r, share
    ok = np.all(np.isfinite(r), axis=1) & (share > 0) & np.all(np.isfinite(x), axis=1)
    info = float(np.sum(x[ok] ** 2))
    if ok.sum() < 50 or not info > 0:
        return r, share
    b = float(np.sum(x[ok] * r[ok])) / info
    chi2 = b * b * info / max(float(np.mean(share[ok])), 1e-12)
    if sps.chi2.sf(chi2, 1) >= alpha:
        return r, share
    out, share_out = r.copy(), share.copy()
    out[ok] = r[ok] - b * x[ok]
    share_out[ok] = share[ok] * np.clip(1.0 - 0.5 * np.sum(x[ok] ** 2, 1) / info, 0.0, 1.0)
    return out, share_out


def track_inflation(r: np.ndarray, star: np.ndarray) -> tuple[float, float, int]:
    """How much more than ``1/n`` a star's mean varies: ``((1 + ρ) / (1 − ρ), ρ, pairs)``.

    ``pairs``: what ``ρ`` is worth (its σ ≈ ``1/√pairs``): the consecutive pairs times the
    square of the slope by which their raw ratio follows ``ρ`` (< 1 on short tracks).

    ``ρ``: the lag-one correlation of ``r`` (whitened residuals about each star's mean, rows
    in time order) between a star's consecutive residuals, pooled over the stars and axes,
    clipped to [0, 0.95]; the AR(1) factor of the mean's variance.  White centroid noise
    gives ~1 (the χ² of :func:`~.noise_stars.star_means` unchanged); an error fixed per
    star gives ~1 too (its mean is removed first); noise correlated over τ frames gives
    about ``2 τ``
    (measured: unseen case ``ar1``, τ = 5 frames, χ² 427 for 156 dof without it).

    The residuals are taken about each star's own mean, which biases the pooled lag
    correlation low.  Pooled as a ratio of sums over many tracks, the estimate reads the
    ratio of the expectations, exact for AR(1) tracks of the tracks' lengths
    (:func:`_lag_moments`), solved for ``ρ`` (:func:`_unbiased_rho`).  The approximation it
    replaces, ``ρ = (ρ̂ + b)/(1 − b)``, ``b = Σ_s (1 − 1/n_s) / pairs`` (``var(x̄) ≈ (1 +
    ρ)/(n (1 − ρ))``), read 0.816 for 0.819 on tracks of 10-80 frames (the factor 9.9 for
    10.0: the repeat's χ² 2 % high, its level at 5 % 0.11 over 200 draws; exact: 0.075);
    Marriott & Pope's ``(1 + 3ρ)/n`` is one track's ratio, whose own ratio bias pooling
    averages away: it over-corrected (55-frame tracks: raw 0.783, 0.847 for 0.82) and, at
    tracks of 2-3 frames, turned white noise into ρ = 0.95.  The factor is steep near 1
    (ρ 0.78 → 8.1, 0.82 → 10.1): uncorrected, the AR(1) case's ρ̂ = 0.78 of a true
    e^(−1/5) = 0.82 left the cells' χ² 105 for 68 dof (p = 0.002) on a 150 s bag, a
    'repeating field' of noise.  The returned factor is the long-run one (a track's mean
    over ``n`` frames: :func:`mean_factor`, as the tests of :func:`lagged_chi2` use).
    """
    ok = np.all(np.isfinite(r), axis=1)
    rr, st = r[ok], np.asarray(star)[ok]
    order = np.argsort(st, kind="stable")  # each star's rows, in time order
    rr, st = rr[order], st[order]
    same = st[1:] == st[:-1]
    if same.sum() < 20:
        return 1.0, 0.0, int(same.sum())
    a, b = rr[1:][same], rr[:-1][same]
    den = math.sqrt(float(np.sum(a * a)) * float(np.sum(b * b)))
    n = np.bincount(np.unique(st, return_inverse=True)[1]).astype(float)
    n = n[n >= 2]
    rho = _unbiased_rho(float(np.sum(a * b)) / den, n) if den > 0 else 0.0
    # the pairs ρ is worth: the raw ratio's σ 1/√pairs over its slope in ρ (short tracks
    # read ρ weakly: slope 0.25 at 3 frames, 0.87 at 10; white 3-frame tracks were called
    # correlated 8 times in 200 on the raw pairs)
    slope = _slope(n, rho)
    return (1.0 + rho) / (1.0 - rho), rho, int(same.sum() * min(slope, 1.0) ** 2)


def _slope(n: np.ndarray, rho: float, step: float = 1e-4) -> float:
    """d/dρ of the ratio :func:`_unbiased_rho` solves (one-sided, within [0, 0.95])."""
    lo = min(max(rho, 0.0), 0.95 - step)
    return (_lag_ratio(n, lo + step) - _lag_ratio(n, lo)) / step


def mean_factor(n: np.ndarray, rho: float) -> np.ndarray:
    """``n`` × the variance of the mean of ``n`` frames of a unit-variance AR(1) of lag-1 ``rho``.

    ``1 + 2 Σ_{k<n} (1 − k/n) ρ^k = (1 + ρ)/(1 − ρ) − 2ρ (1 − ρⁿ) / (n (1 − ρ)²)``: 1 for
    one frame, ``1 + ρ`` for two, the long-run factor of :func:`track_inflation` only as
    ``n`` grows (ρ 0.82, 55 frames: 8.2 of 10.1; the long-run factor made the tests it
    divides ~10 % conservative on such tracks).
    """
    n = np.maximum(np.asarray(n, dtype=float), 1.0)
    if not rho > 0.0:
        return np.ones_like(n)
    return (1.0 + rho) / (1.0 - rho) - 2.0 * rho * (1.0 - rho**n) / (n * (1.0 - rho) ** 2)


def lagged_chi2(r: np.ndarray, group: np.ndarray, track: np.ndarray, rho: float,
                use: np.ndarray, min_count: int = 1) -> float:
    """``Σ_g n_g ‖r̄_g‖² / F_g``: the χ² of the group means of ``r``, each referred to its lag.

    ``r``: whitened residuals ``(n, 2)`` (rows of each ``track`` in time order), ``group``:
    the groups whose means are tested (the stars for the per-star repeat, the detector
    cells), ``use``: the rows that count, groups of at least ``min_count`` rows.  A group's
    mean holds ``m_{g,s}`` rows of each track ``s`` in it; under noise correlated along
    the tracks (an AR(1) of lag-1 ``rho``, :func:`track_inflation`) ``n_g ‖r̄_g‖²`` has the
    expectation ``2 F_g``, ``F_g = Σ_s m_{g,s} f(m_{g,s}) / n_g`` (``f``:
    :func:`mean_factor`, a track's rows in a group taken as consecutive): each group's
    term divided by its own ``F_g`` is a χ² of 2 dof.  White noise (``rho`` 0): the plain
    χ².
    """
    ok = np.asarray(use, dtype=bool) & np.all(np.isfinite(r), axis=1)
    if not ok.any():
        return 0.0
    x = r[ok]
    _, gi = np.unique(np.asarray(group)[ok], return_inverse=True)
    _, ti = np.unique(np.asarray(track)[ok], return_inverse=True)
    n = np.bincount(gi).astype(float)
    means = np.stack([np.bincount(gi, x[:, c]) / n for c in range(2)], 1)
    pair, pi = np.unique(gi.astype(np.int64) * (int(ti.max()) + 1) + ti, return_inverse=True)
    m = np.bincount(pi).astype(float)
    F = np.bincount(pair // (int(ti.max()) + 1), m * mean_factor(m, rho),
                    minlength=len(n)) / n
    keep = n >= min_count
    return float(np.sum(n[keep] * (means[keep] ** 2).sum(1) / F[keep]))


def _lag_moments(n: np.ndarray, rho: float) -> tuple[float, float]:
    """``Σ_tracks E Σ_t (x_t − x̄)(x_{t+1} − x̄)`` and ``E Σ_{t<n} (x_t − x̄)²`` of AR(1) tracks.

    Unit variance, ``n`` frames each: with ``V = f(n)/n`` (:func:`mean_factor`) and ``g =
    (1 − ρⁿ)/(n (1 − ρ))`` (a track end's covariance with the mean), ``(n − 1) ρ − (n + 1)
    V + 2 g`` and ``(n − 1) − (n + 1) V + 2 g``.
    """
    V = mean_factor(n, rho) / n
    g = (1.0 - rho**n) / (n * (1.0 - rho))
    rest = -(n + 1.0) * V + 2.0 * g
    return float(np.sum((n - 1.0) * rho + rest)), float(np.sum((n - 1.0) + rest))


def _lag_ratio(n: np.ndarray, rho: float) -> float:
    """What the pooled lag-one ratio of AR(1) tracks of ``n`` frames reads.

    The ratio of :func:`_lag_moments`; :func:`_unbiased_rho` solves it, :func:`_slope` is its
    slope.
    """
    num, den = _lag_moments(n, rho)
    return num / den


def _unbiased_rho(raw: float, n: np.ndarray) -> float:
    """The AR(1) ``ρ`` whose tracks of ``n`` frames read ``raw`` about their means, in [0, 0.95].

    The ratio of the expectations (:func:`_lag_moments`) solved for ``ρ``: ``raw`` pools
    the pairs of many tracks, so it reads that ratio; 0 when ``raw`` is at most what white
    noise reads (``−1/(n − 1)`` per track: −1 for a 2-frame track).
    """
    def h(rho: float) -> float:
        return _lag_ratio(n, rho) - raw

    if not len(n) or h(0.0) >= 0.0:
        return 0.0
    if h(0.95) <= 0.0:
        return 0.95
    return float(brentq(h, 0.0, 0.95, xtol=1e-6))


def correlated(rho: float, pairs: int, material: float) -> dict[str, float] | None:
    """The stars' noise correlated from frame to frame, if it is (else None).

    Significant (``ρ`` above 3 of its σ ``1/√pairs``) and material (the inflation ``f =
    (1 + ρ)/(1 − ρ)`` above ``1 + material``): each frame's stars then carry ~1/f of what
    white noise of their σ would about the slowly varying parameters, so a filter that
    takes the noise as white must take σ √f (measured: unseen case ``ar1``, τ = 5 frames;
    without it a candidate's score test, which assumes white innovations, added
    thermal_focal_length at p = 6e-4).
    """
    f = (1.0 + rho) / (1.0 - rho)
    if pairs and rho > 3.0 / math.sqrt(pairs) and f > 1.0 + material:
        return {"rho": float(rho), "inflation": float(f), "sigma_scale": float(math.sqrt(f))}
    return None


def correlated_line(c: dict[str, float], applied_star: float) -> str:
    """The noise verdict's line for :func:`correlated`.

    One phrasing: the terminal and the report both show ``noise.verdict``.  Two factors
    make the scale to use, and the line names both: ``applied_star`` (the stars' scale the
    diagnosis now runs with, relative to the messages' σ) is the stars' scatter within
    frames (``applied_star / sigma_scale``: the white scale, measured or kept as stated)
    times ``sigma_scale`` ``= √((1+ρ)/(1−ρ))`` for the correlation.  Said as ``sigma
    x3.08: use --noise-scale star=2.97``, the two numbers read as a contradiction (unseen
    case ``ar1``: the scatter 0.964 x the stated).
    """
    k = c["sigma_scale"]
    white = applied_star / k
    return (f"the stars' centroid noise is correlated from frame to frame along each star's "
            f"track (lag-1 rho = {c['rho']:.2f}): noise, not an effect; each frame carries "
            f"~1/{c['inflation']:.3g} of what white noise of its sigma would, so a filter "
            f"that takes it as white needs the sigma x{k:.3g} (= sqrt({c['inflation']:.3g})) "
            f"on top of the stars' scatter within frames ({white:.3g} x the messages' "
            f"sigma): use --noise-scale star={applied_star:.3g},rho={c['rho']:.2f} (their "
            "product, the one scale to give, and the correlation it stands for; applied; "
            f"NIS/dof then reads ~1/{c['inflation']:.3g}, judged against it)")
