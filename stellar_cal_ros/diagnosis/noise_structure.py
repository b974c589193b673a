"""Structure the stars' σ is measured without, beyond the cells' means and star means.

Part of :func:`~stellar_cal_ros.diagnosis.noise_stars.star_noise` (cases the diagnosis was not
built on, ``benchmarks/unseen_cases.py``): a bias periodic in the centroid's sub-pixel
phase (pixel locking) is removed before the variance is taken, and the per-star repeat's
and the detector cells' χ² are referred to the lag correlation noise correlated over frames
gives their means (:func:`lagged_chi2`, the exact variance of a finite track's mean).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from stellar_cal_ros.core import distributions as dist
from stellar_cal_ros.core.noise import long_run  # the one long-run factor (also here: ns.long_run)
from stellar_cal_ros.diagnosis.stats import finite_rows, speed_squared


def subpixel_columns(uv: np.ndarray) -> np.ndarray:
    """:func:`minus_subpixel`'s regressors ``(n, 2, 4)``: ``sin, cos 2πu`` on u, ``v``'s on v."""
    ph = 2.0 * np.pi * np.asarray(uv, dtype=float)
    X = np.zeros((len(ph), 2, 4))
    X[:, 0, :2] = np.stack([np.sin(ph[:, 0]), np.cos(ph[:, 0])], 1)
    X[:, 1, 2:] = np.stack([np.sin(ph[:, 1]), np.cos(ph[:, 1])], 1)
    return X


def subpixel_block(uv: np.ndarray, columns: np.ndarray | None = None) -> np.ndarray:
    """:func:`minus_fits`' block of the sub-pixel fit, NaN on the rows whose ``uv`` is not finite.

    ``columns``: the projected regressors (:func:`minus_subpixel`); None: the raw
    :func:`subpixel_columns` of ``uv``.
    """
    X = subpixel_columns(uv) if columns is None else np.asarray(columns, dtype=float)
    return np.where(finite_rows(uv)[:, None, None], X, np.nan)


def minus_subpixel(r: np.ndarray, share: np.ndarray, uv: np.ndarray, alpha: float,
                   star: np.ndarray | None = None,
                   lags: tuple[float, float] | None = None,
                   columns: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray, float]:
    """``r`` without a bias periodic in the sub-pixel phase of ``uv``, where it is significant.

    :func:`minus_fits` of the one block :func:`subpixel_block`: per axis ``sin 2πu, cos
    2πu`` (``v`` for the rows), the 4 coefficients' χ² tested at ``alpha``; when
    significant the fit is removed (pixel locking is structure, an 'unexplained' lead of
    its own, not noise: measured, unseen case ``scurve``, 0.08 px said as "sigma 1.46x too
    small"), each residual's share of its dof reduced by its leverage.  Otherwise ``r`` is
    returned unchanged.  Also returns the χ²'s p-value (1 when not tested).

    ``lags``: the stars' noise correlated along their tracks (:func:`minus_fits`).  Taken
    as white, pure AR(1) noise of τ 5 frames fired this fit in 41.5 % of 200 draws at
    ``alpha`` 1 %, referred in 1.5 % (one 300 s bag's residuals,
    ``benchmarks/nuisance_level.py``).

    ``columns``: :func:`subpixel_columns` of ``uv`` projected and whitened as ``r`` (the
    within-frame residuals, as :func:`minus_rolling`'s ``x``), fitted jointly over both
    axes (the frame's attitude fit mixes them).  Fitted raw, the regressors are not in the
    space ``r`` lies in: 0.08 px of locking left the stars' scale at 1.04 ± 0.006 on
    white noise (100 draws, projected: ~1.00; ``benchmarks/nuisance_level.py``).
    """
    r, share, (p,) = minus_fits(r, share, [subpixel_block(uv, columns)], alpha, star, lags)
    return r, share, p


def minus_rolling(r: np.ndarray, share: np.ndarray, x: np.ndarray | None, alpha: float,
                  star: np.ndarray | None = None,
                  lags: tuple[float, float] | None = None
                  ) -> tuple[np.ndarray, np.ndarray, float]:
    """``r`` without its fit by a rolling shutter's shape ``x``, where it is significant.

    ``x``: :func:`~stellar_cal_ros.diagnosis.stats.rolling_columns` projected and whitened
    as ``r`` (the within-frame residuals).  :func:`minus_fits` of its one column (the
    readout time), its χ² tested at ``alpha``; when significant the fit is removed (a
    rolling shutter is structure, an 'unexplained' lead of its own, not noise: measured,
    unseen case ``sway_rolling``, 30 ms read as "sigma x39" grouped by row), each
    residual's share of its row's 2 dof reduced by half its leverage (the leverages sum to
    1: one coefficient, one dof removed, as :func:`minus_subpixel` counts 4 for 4).
    Otherwise ``r`` is returned unchanged.  Also returns the χ²'s p-value (1 when not
    tested).  ``lags``: as :func:`minus_subpixel`'s (taken as white, pure AR(1) noise fired
    this fit in 8 % of 200 draws, referred in 0 %).
    """
    r, share, (p,) = minus_fits(r, share, [rolling_block(x)], alpha, star, lags)
    return r, share, p


def rolling_block(x: np.ndarray | None) -> np.ndarray | None:
    """:func:`minus_fits`' block of the rolling-shutter fit ``(n, 2, 1)``, or None."""
    return None if x is None else np.asarray(x, dtype=float)[:, :, None]


#: rows a structure fit needs to be tested (:func:`minus_fits`)
MIN_ROWS = 50


def minus_fits(r: np.ndarray, share: np.ndarray, blocks: list[np.ndarray | None],
               alpha: float, star: np.ndarray | None = None,
               lags: tuple[float, float] | None = None
               ) -> tuple[np.ndarray, np.ndarray, tuple[float, ...]]:
    """``r`` without the structure fits of ``blocks`` that are significant, each given the others.

    ``blocks``: each a fit's regressors ``(n, 2, p_k)`` (row, axis, coefficient),
    projected and whitened as ``r`` (:func:`subpixel_block`, :func:`rolling_block`), or
    None (not tested: p 1).  A block is tested on the rows where ``r``, ``share`` (> 0) and
    every tested block are finite; a block with fewer than :data:`MIN_ROWS` finite rows, or
    a column of zeros there, is not tested (nor are any when their columns are dependent
    on the rows used).  All the blocks' columns are fitted together
    (:func:`track_fit`) and each block's χ² is its coefficients' given the others' (their
    covariance ``G H G``'s block), in units of the mean ``share`` left, tested at ``alpha``
    on its ``p_k`` dof.  The blocks that fire are then fitted together without those that
    did not, and removed, each row's share reduced by its part of ``tr(G H)``
    (:func:`track_fit`).  Returns ``(r, share, p per block)``, ``r`` and ``share``
    unchanged when none fires.

    ``lags``: the stars' noise correlated along their tracks (``(w, φ)`` of
    :func:`~.noise.track_lags`, each ``star``'s rows in time order): the χ² and the
    shares are referred to it (:func:`track_fit`, as the detector cells' means are by
    :func:`lagged_chi2`); None: white.

    Fitted in turn, the first fit takes what it shares with the next: a 3 ms rolling
    readout on white noise fired the sub-pixel fit, run first, in 6 of 100 draws at 1 %
    (mean p 0.33; 10 ms: 92 of 100); each given the other, 3 of 100, the white level (mean
    p 0.49; 10 ms: 3), and a 0.08 px locking fires the rolling fit in 0 of 100
    (``benchmarks/nuisance_level.py``, doc/benchmarks.md).  One block: its plain fit.
    """
    out_p = [1.0] * len(blocks)
    ok = finite_rows(r) & (share > 0)
    use = []
    for k, X in enumerate(blocks):
        if X is None:
            continue
        fin = np.all(np.isfinite(X), axis=(1, 2))
        if (ok & fin).sum() < MIN_ROWS or not np.all(np.sum(X[ok & fin] ** 2, axis=(0, 1)) > 0):
            continue
        use.append(k)
        ok &= fin
    if not use or ok.sum() < MIN_ROWS:
        return r, share, tuple(out_p)
    X = np.concatenate([blocks[k][ok] for k in use], axis=2)
    sizes = [blocks[k].shape[2] for k in use]
    cuts = np.cumsum([0] + sizes)
    track = np.zeros(len(r)) if star is None else np.asarray(star)  # (white: not read)
    lags = (0.0, 0.0) if lags is None else lags
    SX = along_tracks(X, track[ok], lags)
    try:
        _, chi2, _ = _track_fit(r[ok], X, SX, sizes)
    except np.linalg.LinAlgError:  # the blocks' columns dependent on these rows: not tested
        return r, share, tuple(out_p)
    unit = max(float(np.mean(share[ok])), 1e-12)
    fired = []
    for j, k in enumerate(use):
        out_p[k] = float(dist.chi2.sf(chi2[j] / unit, sizes[j]))
        if out_p[k] < alpha:
            fired.extend(range(cuts[j], cuts[j + 1]))
    if not fired:
        return r, share, tuple(out_p)
    fit, _, lev = (_track_fit(r[ok], X[:, :, fired], SX[:, :, fired])
                   if len(fired) < X.shape[2] else _track_fit(r[ok], X, SX))
    out, share_out = r.copy(), share.copy()
    out[ok] = r[ok] - fit
    share_out[ok] = share[ok] * np.clip(1.0 - lev, 0.0, 1.0)
    return out, share_out, tuple(out_p)


def along_tracks(x: np.ndarray, track: np.ndarray, lags: tuple[float, float]) -> np.ndarray:
    """``Σ x``: the tracks' unit-variance noise covariance applied to the columns of ``x``.

    ``x``: ``(n, ...)``, rows of each ``track`` in time order (consecutive rows of a track
    taken as consecutive frames, as :func:`lagged_chi2` and :func:`track_model` take
    them); ``lags`` ``(w, φ)``: white plus an AR(1) of coefficient ``φ`` carrying ``w`` of
    the variance (``Σ_ij = w φ^|i−j|`` off the diagonal, 1 on it; tracks independent).
    The AR part by one forward and one backward recursion over all rows (``Σ_AR x = f + b
    − x``, ``f_t = x_t + φ f_{t−1}``), the carry from the previous track removed as
    ``φ^(t − start + 1)`` times its last value: O(n), no n × n matrix.
    """
    w, phi = float(lags[0]), float(lags[1])
    x = np.asarray(x, dtype=float)
    if not phi > 0.0 or w == 0.0 or len(x) == 0:
        return x.copy()
    # here only: scipy.signal imports scipy.stats (≈ 24 MiB), which a round without an
    # AR(1) part does not need
    from scipy.signal import lfilter

    order = np.argsort(np.asarray(track), kind="stable")
    xs = x[order].reshape(len(x), -1)
    ts = np.asarray(track)[order]
    pos = np.arange(len(ts))

    def run(z, t):
        """The forward recursion over rows ``z`` of tracks ``t``, each track started anew."""
        new = np.r_[True, t[1:] != t[:-1]]
        first = np.maximum.accumulate(np.where(new, pos, 0))
        f = lfilter([1.0], [1.0, -phi], z, axis=0)
        before = np.where((first > 0)[:, None], f[np.maximum(first - 1, 0)], 0.0)
        return f - (phi ** (pos - first + 1).astype(float))[:, None] * before

    ar = run(xs, ts) + run(xs[::-1], ts[::-1])[::-1] - xs
    out = np.empty_like(xs)
    out[order] = (1.0 - w) * xs + w * ar
    return out.reshape(x.shape)


def track_fit(r: np.ndarray, X: np.ndarray, track: np.ndarray, lags: tuple[float, float]
              ) -> tuple[np.ndarray, float, np.ndarray]:
    """The least-squares fit of ``r`` by ``X`` with its χ² referred to the tracks' correlation.

    ``r``: whitened residuals ``(n, 2)``, ``X``: regressors ``(n, 2, p)`` (row, axis,
    coefficient), rows of each ``track`` in time order, ``lags`` ``(w, φ)`` as
    :func:`along_tracks` takes them.  The coefficients ``b = G Xᵀr`` (``G = (XᵀX)⁻¹``)
    vary as ``G H G`` with ``H = Xᵀ Σ X`` under that noise (``Σ``: :func:`along_tracks`,
    the axes independent), so their χ² is ``(Xᵀr)ᵀ H⁻¹ (Xᵀr)``, of ``p`` dof (``XᵀX`` for
    white noise: the plain fit's χ²).  Removing the fit takes ``tr(P Σ) = tr(G H)`` of
    the expected sum of squares, not ``p``: each row's share ``½ Σ_axes x_iᵀ G (Σ X)_i``
    (``½ x_iᵀ G x_i`` for white noise, the leverages the white fits use).  Returns the
    fit ``X b`` ``(n, 2)``, the χ² and those shares.
    """
    return _track_fit(r, X, along_tracks(X, track, lags))


def _track_fit(r: np.ndarray, X: np.ndarray, SX: np.ndarray,
               sizes: list[int] | None = None):
    """:func:`track_fit` given ``SX = Σ X`` (:func:`along_tracks`).

    ``sizes``: the columns in consecutive blocks; then the χ² is an array, each block's
    ``b_kᵀ [(G H G)_kk]⁻¹ b_k`` (its coefficients given the other blocks'; one block:
    :func:`track_fit`'s).
    """
    n, _, p = X.shape
    Xf = X.reshape(n * 2, p)
    G = np.linalg.inv(Xf.T @ Xf)
    c = Xf.T @ r.reshape(n * 2)
    H = Xf.T @ SX.reshape(n * 2, p)
    H = 0.5 * (H + H.T)
    if sizes is None or len(sizes) == 1:
        chi2 = float(c @ np.linalg.solve(H, c))
        chi2 = chi2 if sizes is None else np.array([chi2])
    else:
        b, V = G @ c, G @ H @ G
        cuts = np.cumsum([0] + list(sizes))
        chi2 = np.array([float(b[i:j] @ np.linalg.solve(V[i:j, i:j], b[i:j]))
                         for i, j in zip(cuts[:-1], cuts[1:], strict=True)])
    fit = (Xf @ (G @ c)).reshape(n, 2)
    lev = 0.5 * np.einsum("iap,pq,iaq->i", X, G, SX)
    return fit, chi2, lev


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
    ok = finite_rows(r)
    order, st = in_track_order(np.asarray(star)[ok])
    a, b, same = lag_pairs(r[ok][order], st)
    if same.sum() < 20:
        return 1.0, 0.0, int(same.sum())
    den = math.sqrt(float(np.sum(a * a)) * float(np.sum(b * b)))
    n = np.bincount(np.unique(st, return_inverse=True)[1]).astype(float)
    n = n[n >= 2]
    rho = _unbiased_rho(float(np.sum(a * b)) / den, n) if den > 0 else 0.0
    # the pairs ρ is worth: the raw ratio's σ 1/√pairs over its slope in ρ (short tracks
    # read ρ weakly: slope 0.25 at 3 frames, 0.87 at 10; white 3-frame tracks were called
    # correlated 8 times in 200 on the raw pairs)
    slope = _slope(n, rho)
    return (1.0 + rho) / (1.0 - rho), rho, int(same.sum() * min(slope, 1.0) ** 2)


def in_track_order(track: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(order, track[order])``: each track's rows together, in time order.

    The rows given in time order (a stable sort), as the lag pairs (:func:`lag_pairs`)
    take them.
    """
    order = np.argsort(track, kind="stable")
    return order, np.asarray(track)[order]


def lag_pairs(xs: np.ndarray, ts: np.ndarray, k: int = 1
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A track's rows ``k`` apart: ``(later, earlier, same)``.

    ``xs``: rows in track order (:func:`in_track_order`), ``ts`` their tracks; ``same[i]``:
    rows ``i`` and ``i + k`` of the sorted rows are of one track.
    """
    same = ts[k:] == ts[:-k]
    return xs[k:][same], xs[:-k][same], same


def _slope(n: np.ndarray, rho: float, step: float = 1e-4) -> float:
    """d/dρ of the ratio :func:`_unbiased_rho` solves (one-sided, within [0, 0.95])."""
    lo = min(max(rho, 0.0), 0.95 - step)
    return (_lag_ratio(n, lo + step) - _lag_ratio(n, lo)) / step


def rho_slope(n: np.ndarray, rho: float) -> float:
    """d/dρ of the lag-1 ratio tracks of ``n`` frames read about their means (at ``rho``).

    :func:`track_inflation`'s ρ̂ moves by ``d raw / rho_slope`` when its raw ratio moves by
    ``d raw`` (the linearization :func:`~.noise_stars.star_noise`'s σ takes).
    """
    return _slope(np.asarray(n, dtype=float), rho)


def mean_factor(n: np.ndarray, rho: float, share: float = 1.0) -> np.ndarray:
    """``n`` × the variance of the mean of ``n`` frames of unit-variance track noise.

    The noise: white plus an AR(1) of coefficient ``rho`` carrying ``share`` (``w``) of the
    variance, lags ``ρ_k = w ρ^k`` (k ≥ 1; ``share`` 1: a pure AR(1), 0: white).  ``1 + 2
    Σ_{k<n} (1 − k/n) w ρ^k = (1 − w) + w [(1 + ρ)/(1 − ρ) − 2ρ (1 − ρⁿ) / (n (1 − ρ)²)]``:
    1 for one frame, ``1 + w ρ`` for two, the long-run factor of :func:`long_run` only as
    ``n`` grows (ρ 0.82, 55 frames: 8.2 of 10.1; the long-run factor made the tests it
    divides ~10 % conservative on such tracks).
    """
    n = np.maximum(np.asarray(n, dtype=float), 1.0)
    if not rho > 0.0:
        return np.ones_like(n)
    ar = (1.0 + rho) / (1.0 - rho) - 2.0 * rho * (1.0 - rho**n) / (n * (1.0 - rho) ** 2)
    return ar if share == 1.0 else (1.0 - share) + share * ar


def lagged_chi2(r: np.ndarray, group: np.ndarray, track: np.ndarray, rho: float,
                use: np.ndarray, min_count: int = 1, share: float = 1.0) -> float:
    """``Σ_g n_g ‖r̄_g‖² / F_g``: the χ² of the group means of ``r``, each referred to its lag.

    ``r``: whitened residuals ``(n, 2)`` (rows of each ``track`` in time order), ``group``:
    the groups whose means are tested (the stars for the per-star repeat, the detector
    cells), ``use``: the rows that count, groups of at least ``min_count`` rows.  A group's
    mean holds ``m_{g,s}`` rows of each track ``s`` in it; under noise correlated along
    the tracks (an AR(1) of lag-1 ``rho``, :func:`track_inflation`) ``n_g ‖r̄_g‖²`` has the
    expectation ``2 F_g``, ``F_g = Σ_s m_{g,s} f(m_{g,s}) / n_g`` (``f``:
    :func:`mean_factor`, a track's rows in a group taken as consecutive): each group's
    term divided by its own ``F_g`` is a χ² of 2 dof.  White noise (``rho`` 0): the plain
    χ².  ``share``: the AR(1)'s share of the variance (white + AR(1) noise,
    :func:`track_model`; 1: pure AR(1)).
    """
    ok = np.asarray(use, dtype=bool) & finite_rows(r)
    if not ok.any():
        return 0.0
    x, gi, _, n, F = _group_terms(r, group, track, rho, ok, share)
    means = np.stack([np.bincount(gi, x[:, c]) / n for c in range(2)], 1)
    keep = n >= min_count
    return float(np.sum(n[keep] * (means[keep] ** 2).sum(1) / F[keep]))


def _group_terms(r: np.ndarray, group: np.ndarray, track: np.ndarray, rho: float,
                 ok: np.ndarray, share: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`lagged_chi2`'s pieces over rows ``ok``.

    ``(r[ok], group index, track index, n_g, F_g)``.
    """
    x = r[ok]
    _, gi = np.unique(np.asarray(group)[ok], return_inverse=True)
    _, ti = np.unique(np.asarray(track)[ok], return_inverse=True)
    gi, ti = np.asarray(gi).reshape(-1), np.asarray(ti).reshape(-1)
    n = np.bincount(gi).astype(float)
    pair, pi = np.unique(gi.astype(np.int64) * (int(ti.max()) + 1) + ti, return_inverse=True)
    m = np.bincount(np.asarray(pi).reshape(-1)).astype(float)
    F = np.bincount(pair // (int(ti.max()) + 1), m * mean_factor(m, rho, share),
                    minlength=len(n)) / n
    return x, gi, ti, n, F


#: sign-flip draws of :func:`flip_p` (fixed seed): its p to ~0.002 at 0.01
FLIP_DRAWS = 2000


def flip_p(r: np.ndarray, group: np.ndarray, track: np.ndarray, rho: float, use: np.ndarray,
           share: float = 1.0, draws: int = FLIP_DRAWS, seed: int = 0) -> float:
    """The p of :func:`lagged_chi2`'s statistic against its sign-flip distribution.

    With no field that repeats from frame to frame, each ``track``'s residuals are as
    likely with their signs flipped together (noise independent between stars, symmetric,
    however correlated along its track): the statistic over ``draws`` random flips of
    whole tracks (fixed ``seed``) is its reference, ``p = (1 + #{flipped ≥ observed}) /
    (1 + draws)``.  Unlike the χ² of ``2 × groups`` dof it takes neither the rows' variance
    (the frames' attitude fit leaves each row ``1 − lev/2`` of it: on the false-alarm
    bags the cells' χ² read 0.66 σ below its χ² mean) nor the tracks' correlation model
    (the factors ``F_g`` weight the groups alike in every flip) as given.  One part is
    not exact: the frames' fit couples a frame's stars (by their leverage, ~3/n a row)
    and a flip of ``r`` does not flip that coupling.
    """
    from scipy.sparse import csr_matrix

    ok = np.asarray(use, dtype=bool) & finite_rows(r)
    if not ok.any():
        return 1.0
    x, gi, ti, n, F = _group_terms(r, group, track, rho, ok, share)
    w = 1.0 / (n * F)
    shape = (len(n), int(ti.max()) + 1)
    T = [csr_matrix((x[:, c], (gi, ti)), shape=shape) for c in range(2)]
    obs = float(np.sum(w * sum(np.asarray(t.sum(axis=1)).reshape(-1) ** 2 for t in T)))
    rng = np.random.default_rng(seed)
    above, chunk = 0, 250
    for lo in range(0, draws, chunk):
        s = rng.integers(0, 2, size=(shape[1], min(chunk, draws - lo))) * 2.0 - 1.0
        stat = w @ sum(np.asarray(t @ s) ** 2 for t in T)
        above += int(np.count_nonzero(stat >= obs * (1.0 - 1e-12)))
    return (1.0 + above) / (1.0 + draws)


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
    return float(brentq(h, 0.0, 0.95, xtol=1e-8))


#: lags the white + AR(1) model is fitted on (:func:`track_model`): at ρ 0.82 (τ 5 frames)
#: the AR part's lag 10 is still 0.14 of its lag 1
MODEL_LAGS = 10
#: groups of stars the model's σ is taken over (delete-a-group jackknife; each replicate
#: one Gauss-Newton step from the full fit, :func:`_step_mixed`).  A jackknife of ``G``
#: groups is a variance of ``G − 1`` dof: with 10, the printed σ of the long-run factor
#: scattered ±24 % from bag to bag and its z = (K − truth)/σ had SD √(9/7) and more
#: (``benchmarks/mixed_noise.py`` 150 s seeds 21-30: rms z 1.29, though K's seed-to-seed
#: SD matched the mean printed σ); with 40 (or one a star, when fewer) the z of white +
#: AR(1) tracks of 40 stars has SD 1.13 (10 groups: 1.31, 200 draws; the rest is K's
#: skew: its σ grows with φ̂, so a low K̂ prints a small σ)
JACKKNIFE_GROUPS = 40
#: the AR(1)'s share below 1 by this many of its σ: white + AR(1), else a pure AR(1)
SHARE_Z = 3.0
#: the fit's bound on ``w``: above 1, so that a pure AR(1)'s ``w`` scatters on both sides
#: of 1 and its jackknife σ is not cut by the bound (bounded at 1, pure AR(1) tracks of
#: 0.82 read 'w below 1 by 3 σ' in 10 of 100 draws: half their fits sat on the bound)
W_MAX = 1.5
#: the fit's bound on ``φ`` (beyond it the long-run factor (1 + φ)/(1 − φ) runs away)
PHI_MAX = 0.95


@dataclass
class TrackNoise:
    """The stars' track noise: white plus an AR(1) (:func:`track_model`)."""

    rho: float  #: lag-1 ρ as a pure AR(1) reads it (:func:`track_inflation`): the test
    pairs: int  #: what ``rho`` is worth (its σ ≈ 1/√pairs)
    phi: float  #: the AR(1)'s coefficient (``rho`` when pure)
    share: float = 1.0  #: the AR(1)'s share of the variance (1: pure AR(1), 0: white)
    factor_sigma: float = math.nan  #: σ of :attr:`factor` (jackknife over the stars)
    share_sigma: float = math.nan  #: σ of the fitted share

    @property
    def factor(self) -> float:
        """The long-run factor (:func:`long_run`)."""
        return long_run(self.phi, self.share)


def track_model(r: np.ndarray, star: np.ndarray, lags: int = MODEL_LAGS,
                cell: np.ndarray | None = None) -> TrackNoise:
    """The stars' track noise as white plus an AR(1): ``ρ_k = w φ^k`` for ``k ≥ 1``.

    A tracker's centroid noise is rarely one AR(1): photon noise is white from frame to
    frame, the PSF's and background's errors drift over a few frames.  Read as a pure
    AR(1) from the lag-1 correlation alone (:func:`track_inflation`) such noise gives the
    long-run factor far too small (white 0.05 px + AR(1) 0.03 px, τ 5 frames: lag-1 ρ̂
    0.2, factor (1 + ρ)/(1 − ρ) = 1.5; true (1 − w) + w (1 + φ)/(1 − φ) = 3.4, ``w`` 0.26,
    φ 0.82), and the detector cells' χ² then called the noise a 'repeating field' (p < 1 %
    on 5 of 6 seeds, ``benchmarks/mixed_noise.py``).

    ``r``: whitened residuals about each star's mean (rows in time order), as
    :func:`track_inflation` takes them.  When the lag-1 ρ is significant (3 σ), ``(w, φ)``
    are fitted to the pooled lag ratios of lags 1..``lags``, each referred to what tracks
    of their lengths read about their means (:func:`_lag_k_moments`, the bias
    :func:`_unbiased_rho` handles at lag 1), weighted by their pairs; their σ by a
    delete-a-group jackknife over :data:`JACKKNIFE_GROUPS` groups of stars (each
    replicate one Gauss-Newton step from the full fit: :func:`_step_mixed`).  The model is
    white + AR(1) only where ``w`` is below 1 by :data:`SHARE_Z` of its σ; else the pure
    AR(1) of lag 1, today's numbers exactly (its factor's σ by the same jackknife).

    ``cell``: each row's detector cell where ``r`` had its cells' means taken before its
    star means (the finite rows of a cell being the rows its mean was taken over): the lag
    expectations then allow for what the cells' means take of the tracks' noise
    (:func:`_cell_lag_terms`; without it the AR(1)'s φ read 0.0025 low and its factor
    1.8 % low on ``psce_rotations`` bags, ``benchmarks/mixed_noise.py``).
    """
    _, rho, pairs = track_inflation(r, star)
    out = TrackNoise(rho, pairs, rho)
    if not (pairs and rho > 3.0 / math.sqrt(pairs)):
        return out
    sums, n, group = _lag_sums(r, star, lags)
    cells = None if cell is None else _cell_lag_terms(r, star, cell, lags)
    fit = _fit_mixed(sums, n, cells=cells)
    G = int(group.max()) + 1 if len(group) else 0
    if G < 3:
        return out
    jack = []
    for g in range(G):
        keep = group != g
        sub = sums[:, :, keep]
        raw1 = float(sub[0, 0].sum() / math.sqrt(sub[0, 1].sum() * sub[0, 2].sum()))
        sub_cells = None if cells is None else (lambda phi, keep=keep: cells(phi)[:, :, keep])
        jack.append((*_step_mixed(sub, n[keep], fit, sub_cells),
                     long_run(_unbiased_rho(raw1, n[keep][n[keep] >= 2]), 1.0)))
    J = np.array([(w, long_run(phi, w), f1) for w, phi, f1 in jack])
    var = (G - 1.0) / G * np.sum((J - J.mean(0)) ** 2, axis=0)
    w_sigma, f_sigma, f1_sigma = (float(math.sqrt(v)) for v in var)
    w, phi = fit
    if w + SHARE_Z * w_sigma < 1.0:
        return TrackNoise(rho, pairs, phi, w, f_sigma, w_sigma)
    out.factor_sigma, out.share_sigma = f1_sigma, w_sigma
    return out


def _lag_sums(r: np.ndarray, star: np.ndarray, lags: int
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per star, lag ``k`` = 1..``lags``: Σ x_t x_{t+k}, Σ x_{t+k}², Σ x_t² (both axes).

    Returns the sums ``(lags, 3, stars)``, the stars' row counts and each star's jackknife
    group.
    """
    ok = finite_rows(r)
    order, st = in_track_order(np.asarray(star)[ok])
    rr = r[ok][order]
    _, si = np.unique(st, return_inverse=True)
    S = int(si.max()) + 1 if len(si) else 0
    sums = np.zeros((lags, 3, S))
    for k in range(1, lags + 1):
        a, b, same = lag_pairs(rr, si, k)
        s = si[k:][same]
        for j, v in enumerate(((a * b).sum(1), (a * a).sum(1), (b * b).sum(1))):
            sums[k - 1, j] = np.bincount(s, v, minlength=S)
    n = np.bincount(si, minlength=S).astype(float)
    # groups by a fixed permutation of the stars (not their order: ids cluster by sky)
    group = np.random.default_rng(0).permutation(S) % min(JACKKNIFE_GROUPS, S)
    return sums, n, group


def _cell_lag_terms(r: np.ndarray, star: np.ndarray, cell: np.ndarray, lags: int):
    """What the detector cells' means add to the lag expectations of :func:`_lag_k_moments`.

    ``r``'s finite rows had their cell's mean taken (``y = x − m_c``), then their star's
    (``z = y − ȳ``).  For unit-variance track noise of lags ``φ^|i − j|`` along each star's
    rows in track order (stars independent; φ = 0: white) ``cov(y_i, y_j) = γ_ij − a_i(c_j)
    − a_j(c_i) + B_(c_i c_j)`` with ``a_i(c) = cov(x_i, m_c) = Σ_(l ∈ c, star i's) γ_il /
    n_c`` and ``B_cc' = cov(m_c, m_c')``; the part beyond ``γ``, ``D``, adds to the star's
    lag-``k`` sum ``Σ_(t ≤ n−k) [D_(t,t+k) − (R_t + R_(t+k))/n] + (n − k) ΣD/n²`` (``R``:
    ``D``'s row sums) and to its pairs' first members' squares the same at ``k = 0`` over
    ``t ≤ n − k``.  Returns ``terms(φ)``: ``(lags, 2, stars)`` (numerator, denominator;
    stars as :func:`_lag_sums` numbers them), kept per φ.
    """
    from scipy.signal import lfilter

    ok = finite_rows(r)
    order, st = in_track_order(np.asarray(star)[ok])
    _, si = np.unique(st, return_inverse=True)
    _, ci = np.unique(np.asarray(cell)[ok][order], return_inverse=True)
    S = int(si.max()) + 1 if len(si) else 0
    C = int(ci.max()) + 1 if len(ci) else 0
    nc = np.bincount(ci, minlength=C).astype(float)
    ends = np.cumsum(np.bincount(si, minlength=S))
    spans = [(ends[s - 1] if s else 0, ends[s]) for s in range(S)]
    memo: dict[float, np.ndarray] = {}

    def terms(phi: float) -> np.ndarray:
        phi = float(phi) if phi > 0.0 else 0.0
        if phi in memo:
            return memo[phi]
        F = []  # per star: Σ_(l in c) φ^|i − l| over its rows l, (rows, cells)
        Braw = np.zeros((C, C))
        for a, b in spans:
            c = ci[a:b]
            Ind = np.zeros((b - a, C))
            Ind[np.arange(b - a), c] = 1.0
            if phi > 0.0:
                f = lfilter([1.0], [1.0, -phi], Ind, axis=0)
                g = lfilter([1.0], [1.0, -phi], Ind[::-1], axis=0)[::-1]
                Fs = f + g - Ind
            else:
                Fs = Ind
            F.append(Fs)
            Braw += Ind.T @ Fs
        B = Braw / np.outer(nc, nc)
        out = np.zeros((lags, 2, S))
        for s, (a, b) in enumerate(spans):
            c = ci[a:b]
            n = b - a
            A = F[s] / nc[None, :]
            nsc = np.bincount(c, minlength=C).astype(float)
            R = -(A @ nsc) - A.sum(0)[c] + B[c] @ nsc
            tot = R.sum()
            Dtt = -2.0 * A[np.arange(n), c] + B[c, c]
            for k in range(1, lags + 1):
                m = n - k
                if m <= 0:
                    break
                t = np.arange(m)
                diag = np.sum(-A[t, c[t + k]] - A[t + k, c[t]] + B[c[t], c[t + k]])
                out[k - 1, 0, s] = diag - (R[:m].sum() + R[k:].sum()) / n + m * tot / n**2
                out[k - 1, 1, s] = Dtt[:m].sum() - 2.0 * R[:m].sum() / n + m * tot / n**2
        memo[phi] = out
        return out

    return terms


def _lag_k_moments(n: np.ndarray, rho: float, share: float, k: np.ndarray,
                   cells=None, lag: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_lag_moments` at lags ``k`` of white + AR(1) tracks (``share`` the AR's).

    A stationary track of ``n`` frames with lags ``γ``: ``E Σ_{t ≤ n−k} (x_t − x̄)(x_{t+k}
    − x̄) = (n − k) γ_k − (n + k) V + 2 C_k`` and, ``γ_k`` taken as 1, the sum of squares
    of the pairs' first members; ``V`` the mean's variance, ``C_k = Σ_{t ≤ k} cov(x_t,
    x̄)``: ``k/n`` for white noise, ``[k (1 + ρ) − ρ (1 − ρ^k)(1 + ρ^(n−k))/(1 − ρ)] / (n
    (1 − ρ))`` for the AR(1).  Both linear in the covariance: the white part's and the
    AR's weighted by ``1 − w`` and ``w``.  Tracks of at most ``k`` frames have no pair.
    ``cells``: :func:`_cell_lag_terms` of the tracks (their rows had their detector cells'
    means taken before their own), whose terms at ``lag`` (indices into its lags) are added
    to the white part's and the AR's.  Returns the sums over the tracks, one per lag.
    """
    n = np.asarray(n, dtype=float)[None, :]
    k = np.asarray(k, dtype=float)[:, None]
    has = n > k
    nk = np.where(has, n - k, 0.0)
    wn, wd = np.sum(-nk / n, 1), np.sum(nk * (1.0 - 1.0 / n), 1)
    if cells is not None:
        lag = (k[:, 0] - 1).astype(int) if lag is None else lag
        cw = cells(0.0)[lag].sum(2)
        wn, wd = wn + cw[:, 0], wd + cw[:, 1]
    if not rho > 0.0 or share == 0.0:
        return wn, wd
    V = mean_factor(n, rho) / n
    C = (k * (1.0 + rho) - rho * (1.0 - rho**k) * (1.0 + rho ** nk) / (1.0 - rho)) \
        / (n * (1.0 - rho))
    rest = np.where(has, -(n + k) * V + 2.0 * C, 0.0)
    an, ad = np.sum(nk * rho**k + rest, 1), np.sum(nk + rest, 1)
    if cells is not None:
        ca = cells(rho)[lag].sum(2)
        an, ad = an + ca[:, 0], ad + ca[:, 1]
    return (1.0 - share) * wn + share * an, (1.0 - share) * wd + share * ad


def _mixed_residuals(sums: np.ndarray, n: np.ndarray, cells=None):
    """The weighted residuals of :func:`_fit_mixed` as a function of ``(w, φ)``, or None.

    ``sums``: :func:`_lag_sums` of the stars used; each lag's pooled ratio minus what
    white + AR(1) tracks of the stars' lengths read (:func:`_lag_k_moments`), weighted by
    the square root of its pairs (``cells``: :func:`_cell_lag_terms` of the stars, as
    :func:`_lag_k_moments` takes it).  None with fewer than two lags that have pairs.
    """
    tot = sums.sum(2)
    den = np.sqrt(tot[:, 1] * tot[:, 2])
    lag = np.flatnonzero(den > 0)
    if len(lag) < 2:
        return None
    raw = tot[lag, 0] / den[lag]
    k = lag + 1.0
    pairs = np.sum(np.maximum(n[None, :] - k[:, None], 0.0), 1)
    wt = np.sqrt(pairs / pairs.max())

    def resid(p):
        num, d = _lag_k_moments(n, p[1], p[0], k, cells, lag)
        return wt * (np.where(d > 0, num / np.where(d > 0, d, 1.0), 0.0) - raw)

    resid.raw = raw  # (the start of a fit: lags 1 and 2)
    return resid


def _fit_mixed(sums: np.ndarray, n: np.ndarray, start: tuple[float, float] | None = None,
               cells=None) -> tuple[float, float]:
    """``(w, φ)`` whose expected lag ratios (:func:`_lag_k_moments`) fit the pooled ones.

    ``sums``: :func:`_lag_sums` of the stars used; least squares weighted by each lag's
    pairs (:func:`_mixed_residuals`), ``w`` in [0, :data:`W_MAX`], ``φ`` in [0, 0.95],
    from ``start`` or from lags 1 and 2 (``cells``: as :func:`_mixed_residuals` takes it).
    """
    from scipy.optimize import least_squares

    resid = _mixed_residuals(sums, n, cells)
    if resid is None:
        return 1.0, 0.0
    if start is None:
        r1, r2 = float(resid.raw[0]), float(resid.raw[1])
        phi0 = float(np.clip(r2 / r1, 0.2, 0.9)) if r1 > 0 else 0.5
        start = (float(np.clip(r1 / phi0, 0.05, 0.95)), phi0)
    x0 = np.clip(start, [1e-6, 1e-6], [W_MAX - 1e-6, PHI_MAX - 1e-6])
    fit = least_squares(resid, x0, bounds=([0.0, 0.0], [W_MAX, PHI_MAX]), xtol=1e-8)
    return float(fit.x[0]), float(fit.x[1])


def _step_mixed(sums: np.ndarray, n: np.ndarray, fit: tuple[float, float], cells=None
                ) -> tuple[float, float]:
    """One Gauss-Newton step of :func:`_fit_mixed` on ``sums`` from ``fit``, in its bounds.

    A jackknife replicate (a group of stars left out) moves the fit by ~σ/√groups: one
    step from the full fit is its refit to second order, at three evaluations of the
    residuals instead of a bounded least squares (so the jackknife can take many groups,
    :data:`JACKKNIFE_GROUPS`).  ``cells``: as :func:`_mixed_residuals` takes it.
    """
    resid = _mixed_residuals(sums, n, cells)
    if resid is None:
        return fit
    p = np.asarray(fit, dtype=float)
    r0 = resid(p)
    h = 1e-6
    J = np.stack([(resid(p + h * e) - r0) / h for e in np.eye(2)], 1)
    step = np.linalg.lstsq(J, -r0, rcond=None)[0]
    # the refit's bounds: a full fit on φ's bound (strongly correlated tracks) otherwise
    # steps its replicates toward φ = 1, where long_run explodes (φ .95, w .5, 40 stars:
    # the factor's σ median 7.6, max 2e3 against the factor's 20)
    return (float(np.clip(p[0] + step[0], 0.0, W_MAX)),
            float(np.clip(p[1] + step[1], 0.0, PHI_MAX)))


def correlated(rho: float, pairs: int, material: float, phi: float | None = None,
               share: float = 1.0, factor_sigma: float = math.nan
               ) -> dict[str, float] | None:
    """The stars' noise correlated from frame to frame, if it is (else None).

    Significant (the lag-1 ``ρ`` above 3 of its σ ``1/√pairs``) and material (the long-run
    inflation ``f`` above ``1 + material``): each frame's stars then carry ~1/f of what
    white noise of their σ would about the slowly varying parameters, so a filter that
    takes the noise as white must take σ √f (measured: unseen case ``ar1``, τ = 5 frames;
    without it a candidate's score test, which assumes white innovations, added
    thermal_focal_length at p = 6e-4).  ``f``: :func:`long_run` of the tracks' model
    (:func:`track_model`: white + AR(1) of coefficient ``phi`` carrying ``share`` of the
    variance; ``phi`` None and ``share`` 1, a pure AR(1) of ``ρ``: ``(1 + ρ)/(1 − ρ)``);
    ``factor_sigma``: σ of ``f`` (``sigma_scale_sigma`` the σ of √f).
    """
    phi = rho if phi is None else phi
    f = long_run(phi, share)
    if pairs and rho > 3.0 / math.sqrt(pairs) and f > 1.0 + material:
        out = {"rho": float(rho), "inflation": float(f), "sigma_scale": float(math.sqrt(f))}
        if share != 1.0:
            out.update(phi=float(phi), ar_share=float(share))
        if math.isfinite(factor_sigma):
            out["sigma_scale_sigma"] = float(factor_sigma / (2.0 * math.sqrt(f)))
        return out
    return None


def correlated_line(c: dict[str, float], applied_star: float) -> str:
    """The noise verdict's line for :func:`correlated`.

    One phrasing: the terminal and the report both show ``noise.verdict``.  Two factors
    make the scale to use, and the line names both: ``applied_star`` (the stars' scale the
    diagnosis now runs with, relative to the messages' σ) is the stars' scatter within
    frames (``applied_star / sigma_scale``: the white scale, measured or kept as stated)
    times ``sigma_scale`` ``= √((1+ρ)/(1−ρ))`` for the correlation.  Said as ``sigma
    x3.08: use --noise-scale star=2.97``, the two numbers read as a contradiction (unseen
    case ``ar1``: the scatter 0.964 x the stated).  White + AR(1) noise (``ar_share`` in
    ``c``) names its two parts, and ``sigma_scale`` its σ where measured.
    """
    k = c["sigma_scale"]
    white = applied_star / k
    model = f"lag-1 rho = {c['rho']:.2f}"
    if "ar_share" in c:
        model = (f"white + AR(1): {model}, an AR(1) of coefficient {c['phi']:.2f} carrying "
                 f"{c['ar_share']:.2f} of the variance")
    pm = f" +- {c['sigma_scale_sigma']:.2g}" if "sigma_scale_sigma" in c else ""
    # the advice's correlation: the AR(1)'s coefficient and share for white + AR(1) noise
    # (`NoiseScales.parse`: its star_inflation is the factor printed)
    arg = f"rho={c['rho']:.2f}" if "ar_share" not in c else \
        f"rho={c['phi']:.2f},share={c['ar_share']:.2f}"
    return (f"the stars' centroid noise is correlated from frame to frame along each star's "
            f"track ({model}): noise, not an effect; each frame carries "
            f"~1/{c['inflation']:.3g} of what white noise of its sigma would, so a filter "
            f"that takes it as white needs the sigma x{k:.3g}{pm} "
            f"(= sqrt({c['inflation']:.3g})) "
            f"on top of the stars' scatter within frames ({white:.3g} x the messages' "
            f"sigma): use --noise-scale star={applied_star:.3g},{arg} (their "
            "product, the one scale to give, and the correlation it stands for; applied; "
            f"NIS/dof then reads ~1/{c['inflation']:.3g}, judged against it)")


#: the fixed-pattern test's bands: this many detector columns (rows) each
PATTERN_BAND_PX = 8
#: the bands on each side a band's mean is compared with (a smooth field cancels)
PATTERN_REACH = 4
#: a star's rows in one band weigh at most this many rows together (a star dwelling on a
#: band, a PSCE dwell of ~55 frames, would carry the band alone: no coincidence across the
#: stars to test; columns seed 21, 300 s window: p 0.042 at full weight, 2.9e-4 capped at 2)
PATTERN_CAP = 2.0


@dataclass
class FixedPattern:
    """A centroid offset fixed to detector columns (rows): :func:`fixed_pattern`'s test."""

    z: float  #: ``(T − E T) / SD T`` under sign flips of whole tracks
    p: float  #: its p-value (a scaled χ² matched to the flips' mean and variance)
    #: the band that adds most to the statistic: its offset from its neighbours (the
    #: residuals' units × ``scale``: px where ``scale`` is each row's σ) and its first pixel
    top: float = 0.0
    at_px: float = math.nan
    #: the pattern's size (px, :func:`band_offset_size`) where it was measured, else nan
    size_px: float = math.nan
    #: ``T``'s z and p against the residuals' own noise (white, or AR(1) along the
    #: tracks), not the flips: :func:`fixed_pattern`
    model_z: float = 0.0
    model_p: float = 1.0


#: the passes of :func:`pixel_means`' two-way fit (stars' means and pixels' offsets)
PIXEL_PASSES = 30


def pixel_means(r: np.ndarray, pos: np.ndarray, star: np.ndarray, cap: float = PATTERN_CAP,
                scale: np.ndarray | None = None, star_means: bool = True
                ) -> tuple[np.ndarray, np.ndarray]:
    """Each row's pixel's offset in ``r`` beside the stars' own means, and its share of it.

    The pattern :func:`fixed_pattern` found, at the detector's resolution (its bands of 8
    px straddle a defect's edges: removed by bands, the 8-column pattern of the ``columns``
    case left a star dwelling on a band's good column 7/8 of the offset, read again as
    AR(1) noise): ``r ≈ m_star + c_pixel`` fitted by least squares (alternating passes,
    :data:`PIXEL_PASSES`), each star's rows in a pixel weighing at most ``cap`` rows
    together (as the test's).  Fitted jointly, not about the stars' means: a star on a
    defective column for most of its track takes the column's offset into its mean
    otherwise, read as a catalogue error ('repeat star by star', columns seed 21, ranked
    before the pattern's line).  The offsets are centred (their weighted mean 0: the
    frames' fit holds the common part).  Returns ``(c × scale, share)`` per row
    (``share``: the row's weight over its pixel's, its part of the offset's one dof; 0
    where ``r`` or ``pos`` is not finite).  ``star_means`` False: the stars' means are not
    fitted (0), where the pattern was found between the stars as well
    (:attr:`FixedPattern.model_p`: a star dwelling on a band carries its offset in its
    mean, which the two-way fit would leave to a per-star error).
    """
    x = np.asarray(r, dtype=float)
    pos = np.asarray(pos, dtype=float)
    ok = np.isfinite(x) & np.isfinite(pos)
    mean, lev = np.zeros(len(x)), np.zeros(len(x))
    rows = np.flatnonzero(ok)
    if len(rows) == 0:
        return mean, lev
    _, si = np.unique(np.asarray(star)[rows], return_inverse=True)
    si = np.asarray(si).reshape(-1)
    xr = x[rows]
    col = np.floor(pos[rows]).astype(np.int64)
    col -= col.min()
    ncol = int(col.max()) + 1
    cell = si * ncol + col
    om = np.minimum(1.0, cap / np.bincount(cell, minlength=(int(si.max()) + 1) * ncol)[cell])
    ws, wc = np.bincount(si, om), np.bincount(col, om, minlength=ncol)
    wc_safe = np.maximum(wc, 1e-300)
    c = np.zeros(ncol)
    m = np.zeros(len(ws))
    for _ in range(PIXEL_PASSES if star_means else 1):
        if star_means:
            m = np.bincount(si, om * (xr - c[col])) / ws
        c = np.bincount(col, om * (xr - m[si]), minlength=ncol) / wc_safe
        c -= np.sum(wc * c) / np.sum(wc)
    u = np.ones(len(rows)) if scale is None else np.asarray(scale, dtype=float)[rows]
    mean[rows] = c[col] * u
    lev[rows] = om / wc_safe[col]
    return mean, lev


def band_offset_size(offset: np.ndarray, pos: np.ndarray, at_px: float,
                     band: int = PATTERN_BAND_PX, reach: int = PATTERN_REACH) -> float:
    """The size (px) of the fixed pattern :func:`fixed_pattern` found at band ``at_px``.

    ``offset``: each row's pixel's offset (px, :func:`pixel_means`: fitted beside the
    stars' own means, which take part of a band's offset into a star dwelling on it),
    ``pos`` its detector position.  The size is the mean offset of the rows in a window of
    ``band`` px less that of the rows in the ``reach`` bands on either side, the window
    slid over the phases within a band of ``at_px`` to the one departing most: the test's
    bands are fixed to multiples of ``band``, and one straddling a defect's edge reads
    part of it (unseen case ``columns``: bands of 8 columns from column 97, the test's top
    band 96-103 holds 7/8 of one, and it printed 0.106 px, less the stars' means, for
    0.15).  nan without rows at ``at_px``.
    """
    pos = np.asarray(pos, dtype=float)
    ok = np.isfinite(pos) & np.isfinite(offset)
    if not ok.any():
        return math.nan
    col = np.floor(pos[ok]).astype(np.int64)
    lo = min(int(col.min()), int(math.floor(at_px)) - (reach + 1) * band)
    col -= lo
    n = int(col.max()) + 1 + (reach + 2) * band
    S = np.concatenate([[0.0], np.cumsum(np.bincount(col, np.asarray(offset)[ok],
                                                     minlength=n))])
    N = np.concatenate([[0.0], np.cumsum(np.bincount(col, minlength=n).astype(float))])
    best = math.nan
    for a in range(int(math.floor(at_px)) - lo - band + 1,
                   int(math.floor(at_px)) - lo + band):
        a0, a1 = max(a - reach * band, 0), min(a + band + reach * band, n)
        n_in, n_nb = N[a + band] - N[a], N[a1] - N[a0] - (N[a + band] - N[a])
        if n_in <= 0 or n_nb <= 0:
            continue
        h = (S[a + band] - S[a]) / n_in - (S[a1] - S[a0] - (S[a + band] - S[a])) / n_nb
        if not abs(h) <= abs(best):
            best = h
    return float(abs(best))


def less_smooth(r: np.ndarray, pos: np.ndarray, extent: float | None,
                periods: tuple[int, ...] = (1, 2, 3, 4)) -> np.ndarray:
    """``r`` less its least-squares fit by a smooth function of the detector position ``pos``.

    The function: a straight line and the sines and cosines of ``periods`` ``k`` periods
    across ``extent`` px (None: ``pos``'s span), the ripple lines' own
    (:data:`~.stats.POSITION_PERIODS`).  :func:`fixed_pattern`'s bands cancel a field
    linear over their neighbours only: a ripple's curvature leaks into every band (unseen
    case ``ripple``, ``0.08 sin(2π 3 u / 1024)`` px: 1 − cos over ±4 bands leaves 8 % of
    it, which the Gaussian null read as a fixed pattern of 0.098 px, p 4e-5, and its
    removal took the ripple out of the lines that name it).  A fixed pattern is what the
    smooth fit leaves; the smooth part stays for the ripple lines.  Rows with ``r`` or
    ``pos`` not finite are not fitted and kept as given.
    """
    x = np.asarray(r, dtype=float)
    pos = np.asarray(pos, dtype=float)
    ok = np.isfinite(x) & np.isfinite(pos)
    if ok.sum() <= 2 + 2 * len(periods):
        return x
    span = float(np.ptp(pos[ok]))
    ext = extent if extent is not None and extent > 0 else span
    if not (ext > 0 and span > 0):
        return x
    a = pos[ok]
    ph = [2.0 * np.pi * k * a / ext for k in periods]
    X = np.stack([np.ones(len(a)), (a - a.mean()) / span]
                 + [np.sin(q) for q in ph] + [np.cos(q) for q in ph], 1)
    out = x.copy()
    out[ok] = x[ok] - X @ np.linalg.lstsq(X, x[ok], rcond=None)[0]
    return out


def fixed_pattern(r: np.ndarray, share: np.ndarray, pos: np.ndarray, star: np.ndarray,
                  band: int = PATTERN_BAND_PX, reach: int = PATTERN_REACH,
                  cap: float = PATTERN_CAP, scale: np.ndarray | None = None,
                  row_var: np.ndarray | None = None) -> FixedPattern | None:
    """A mean offset of ``r`` (one axis) tied to fine bands of the detector position ``pos``.

    A CCD fixed pattern (columns that read a centroid 0.15 px further along u, unseen case
    ``columns``) makes a star's residual jump for the frames its centroid sits on a
    defective band: its track looks correlated (AR(1)) and the stars differ in level (σ
    wrong star by star), both noise verdicts fooled by a structure in the residuals' mean.
    Tested before them: the residuals about each ``star``'s mean (a per-star error, a
    catalogue position, cancels; only what changes along a track counts) are averaged in
    bands of ``band`` px of ``pos``, each star's rows in a band weighing at most ``cap``
    rows together, and each band's mean taken less the mean of the ``reach`` bands on
    either side (a smooth field, a missing distortion, cancels); ``T = Σ_b w_b h_b²``.
    ``T`` is a quadratic form ``sᵀ A s`` in each track's sign ``s``: under the null (each
    star's noise symmetric, the stars independent, correlated along its track or not, its σ
    its own) its distribution over sign flips of whole tracks has mean ``tr A`` and
    variance ``2 Σ_{i≠j} A_ij²``, exact for any noise along the tracks (the weights depend
    on the positions only); ``p``: the scaled χ² of those two moments.  ``r``: whitened
    residuals (one axis, rows with ``share`` > 0 and finite ``pos`` tested); ``scale``:
    each row's units of the band means returned (None: 1); ``row_var``: each row's noise
    variance in ``r``'s units where the frames' noise differs (:func:`frame_variances`;
    None: one variance), which the Gaussian null then also takes, its larger p said.  None
    when fewer than :data:`MIN_ROWS` rows or 3 bands are tested.
    """
    ok = np.isfinite(r) & np.isfinite(pos) & (share > 0)
    rows = np.flatnonzero(ok)
    if len(rows) < MIN_ROWS:
        return None
    x = np.asarray(r, dtype=float)[rows]
    _, si = np.unique(np.asarray(star)[rows], return_inverse=True)
    si = np.asarray(si).reshape(-1)
    ns = np.bincount(si).astype(float)
    d = x - (np.bincount(si, x) / ns)[si]
    b = np.floor(np.asarray(pos, dtype=float)[rows] / band).astype(np.int64)
    first = int(b.min())
    b -= first
    nb_count = int(b.max()) + 1
    cell = si * nb_count + b
    om = np.minimum(1.0, cap / np.bincount(cell, minlength=len(ns) * nb_count)[cell])
    nb = np.bincount(b, om, minlength=nb_count)
    S = np.zeros((len(ns), nb_count))  # each star's weighted sum of d in each band
    np.add.at(S, (si, b), om * d)
    # h = L (band sums): the band's mean less the mean of its neighbours' rows
    L = np.zeros((nb_count, nb_count))
    for k in range(nb_count):
        if nb[k] == 0:
            continue
        near = [j for j in range(max(k - reach, 0), min(k + reach + 1, nb_count))
                if j != k and nb[j] > 0]
        nn = float(nb[near].sum()) if near else 0.0
        if nn == 0.0:
            continue
        L[k, k] = 1.0 / nb[k]
        L[k, near] = -1.0 / nn
    used = np.any(L != 0.0, axis=1)
    if used.sum() < 3:
        return None
    w = np.where(used, nb, 0.0)
    C = S @ L.T  # each star's part of each band's h
    h = C.sum(0)
    T = float(np.sum(w * h * h))
    Cw = C * np.sqrt(w)
    diag = np.sum(Cw * Cw, 1)
    mean = float(diag.sum())
    M = Cw.T @ Cw
    var = 2.0 * (float(np.sum(M * M)) - float(np.sum(diag * diag)))
    if not (mean > 0.0 and var > 0.0):
        return None
    g, dof = var / (2.0 * mean), 2.0 * mean * mean / var
    p = float(dist.chi2.sf(T / g, dof))
    u = np.ones(len(rows)) if scale is None else np.asarray(scale, dtype=float)[rows]
    band_mean = np.bincount(b, om * d * u, minlength=nb_count) / np.maximum(nb, 1e-300)
    k = int(np.argmax(w * h * h))
    top = float(L[k] @ (nb * band_mean))  # (its mean less its neighbours', in scale's units)
    mz, mp = _model_moments(T, d, si, ns, b, om, L, w)
    if row_var is not None:
        hz, hp = _model_moments(T, d, si, ns, b, om, L, w,
                                np.asarray(row_var, dtype=float)[rows])
        mz, mp = (hz, hp) if hp > mp else (mz, mp)
    return FixedPattern((T - mean) / math.sqrt(var), p, top, float((k + first) * band),
                        model_z=mz, model_p=mp)


def _model_moments(T: float, d: np.ndarray, si: np.ndarray, ns: np.ndarray, b: np.ndarray,
                   om: np.ndarray, L: np.ndarray, w: np.ndarray,
                   v: np.ndarray | None = None) -> tuple[float, float]:
    """:func:`fixed_pattern`'s ``T`` against the residuals' own noise: ``(z, p)``.

    The flips of whole tracks let each track carry any pattern of its own, so they test
    only a coincidence across the stars; where the stars dwell in a few bands (the
    ``rows`` case on PSCE: a star's v spans ~6 px while it crosses the columns) a band
    holds 2-3 stars and the flips' p stays above 1e-4 (seeds 21-30: 8e-4 .. 0.06) for an
    offset of 0.13 px in residuals of σ 0.05.  Here the rows' ``d`` (about each star's
    mean: a per-star error cancels) are Gaussian with one variance, their empirical one,
    and correlated along a track as AR(1) at most (:func:`track_inflation`'s factor on
    every cell's variance: conservative for ρ > 0); ``T = hᵀ W h`` with ``h = L S`` has
    ``Cov S = s² f (diag Σ om² − Wsᵀ diag(1/n) Ws)`` (``Ws``: each star's weight in each
    band) and the scaled χ² of its mean and variance gives ``p``.

    ``v``: each row's own noise variance (:func:`frame_variances`), for ``s²`` one: ``Cov S``
    of rows about their star's mean then holds each row's variance (``diag Σ om² v − Ws
    Qᵀ/n − Q Wsᵀ/n + Ws diag(Σ v / n²) Wsᵀ``, ``Q``: each star's ``om v`` in each band).
    A noise that grows in a few frames (smear in the slews: unseen case ``rate_noise``,
    σ ∝ √(1 + (2 v / v95)²), seed 21) made one variance read bands of 8 px at z 24 (p
    1e-44) where the flips' exact p was 0.08; with the frames' variances z 0.95.
    """
    nb_count = L.shape[0]
    cell = si * nb_count + b
    Ws = np.bincount(cell, om, minlength=len(ns) * nb_count).reshape(len(ns), nb_count)
    dof_left = len(d) - len(ns)
    if dof_left <= 0:
        return 0.0, 1.0
    f, _, _ = track_inflation(d[:, None], si)
    if v is None:
        cov = np.diag(np.bincount(b, om * om, minlength=nb_count)) - (Ws.T / ns) @ Ws
        s2 = float(d @ d) / dof_left * f
    else:
        Q = np.bincount(cell, om * v, minlength=len(ns) * nb_count).reshape(len(ns), nb_count)
        cov = np.diag(np.bincount(b, om * om * v, minlength=nb_count)) \
            - (Ws.T / ns) @ Q - (Q.T / ns) @ Ws \
            + (Ws.T * (np.bincount(si, v, minlength=len(ns)) / ns**2)) @ Ws
        s2 = f
    sw = np.sqrt(w)
    K = s2 * (sw[:, None] * (L @ cov @ L.T) * sw[None, :])
    mean, var = float(np.trace(K)), 2.0 * float(np.sum(K * K))
    if not (mean > 0.0 and var > 0.0):
        return 0.0, 1.0
    g, dof = var / (2.0 * mean), 2.0 * mean * mean / var
    return (T - mean) / math.sqrt(var), float(dist.chi2.sf(T / g, dof))


#: :func:`frame_variances`' level: the frames' noise differs when their mean squared
#: residuals spread more than one variance lets them at this p (clean psce 300 s s21:
#: p 0.14; ``rows`` 0.35, ``columns`` 0.035: no frame variances, their tests unchanged;
#: ``rate_noise`` p 0)
FRAME_VAR_ALPHA = 1e-6


def frame_variances(e: np.ndarray, frame: np.ndarray) -> np.ndarray | None:
    """Each row's noise variance from its frame, where the frames' noise differs; else None.

    ``e``: each row's mean square per axis (whitened residuals less each frame's attitude
    fit, ``(r_u² + r_v²) / 2``, or a row's ``q / m``); the frames' means of ``e`` spread as
    ``χ²`` with (frames − 1) dof
    about the rows' mean under one variance (each frame's mean's variance ``var(e) / n``,
    the rows' own ``var(e)``: heavy tails alone do not make it fire).  Past
    :data:`FRAME_VAR_ALPHA` each row gets its frame's median ``e`` over ln 2 (a χ²₂/2's
    median: a few stars on a defect do not lift it), the noise of that frame.
    """
    e = np.asarray(e, dtype=float)
    ok = np.isfinite(e)
    _, fi = np.unique(np.asarray(frame)[ok], return_inverse=True)
    fi = np.asarray(fi).reshape(-1)
    n = np.bincount(fi).astype(float)
    var_e = float(np.var(e[ok]))
    if len(n) < 3 or not var_e > 0.0:
        return None
    m = np.bincount(fi, e[ok]) / n
    X = float(np.sum(n * (m - e[ok].mean()) ** 2)) / var_e
    if not dist.chi2.sf(X, len(n) - 1) < FRAME_VAR_ALPHA:
        return None
    # (each frame's median at once: the rows sorted by frame, then value; the two middle
    # rows' mean, as np.median's, bit for bit: a median per frame in a loop was ~5 CPU-s
    # of the 2-h round)
    eo = e[ok]
    srt = eo[np.lexsort((eo, fi))]
    nn = n.astype(int)
    first = np.concatenate([[0], np.cumsum(nn)[:-1]])
    med = (srt[first + (nn - 1) // 2] + srt[first + nn // 2]) / 2.0
    out = np.full(len(e), np.nan)
    out[np.flatnonzero(ok)] = np.maximum(med[fi] / math.log(2.0), 1e-12)
    return out


#: a frame-common noise is named at this one-sided p of its score test (:func:`frame_common`)
COMMON_ALPHA = 1e-3
#: ... and where it adds at least this share to the variance of the frames' mean
#: innovations the filter predicts (a smaller one changes no σ the user reads by more than
#: the noise verdict's materiality)
COMMON_SHARE = 0.1
#: the frames with at least this many accepted stars are the test's
COMMON_MIN_STARS = 3
#: the median of a χ²₁ (:func:`frame_common`'s robust check)
CHI2_1_MEDIAN = 0.4549364231195724
#: the frames' noise scale is measured in this many classes of their rate (:func:`frame_common`)
COMMON_RATE_CLASSES = 8


def frame_common(res, mask: np.ndarray, sigma_px: np.ndarray, focal: tuple[float, float],
                 R_imu_st: np.ndarray | None) -> dict[str, float] | None:
    """A noise common to all stars of a frame, white between frames: its σ and test.

    Every star of a frame shifted by one error ``j_k`` (px per axis, σ_j), independent from
    frame to frame: an attitude or image jitter faster than the frames that the gyro does
    not see (unseen case ``frame_jitter``).  The stars' σ is measured within each frame
    (:func:`~.noise_stars.star_noise`: the frame's rotation fitted out, ``j_k`` with it) and
    the gyro's from its samples, so neither sees it; it is in the frames' *mean*
    innovation, which the filter predicts.  Per frame and axis (u, v) of ``mask``'s accepted
    stars (at least :data:`COMMON_MIN_STARS`): ``m`` the mean innovation weighted by
    ``1/σ_i²`` (``sigma_px`` the σ the run used), its predicted variance ``c = (Σ w_i
    √P_i / W)² + s²/W`` (``P_i = S_i − σ_i²`` each star's prediction part of its innovation
    covariance, one attitude error all stars share; ``s`` = ``scale``, the stars' measured σ
    scale; ``W = Σ w_i``) and the filter's gain on the common part ``K = P̄ / (P̄ + 1/W)``.
    A white ``j_k`` the filter follows by ``K`` each frame adds ``σ_j² a``, ``a = 2 / (2 −
    K)``, to ``E[m²]`` (the innovation is ``j_k`` less the filter's running mean of the
    earlier ones, variance ``σ_j² K / (2 − K)``).  The score test of ``σ_j² = 0``: ``z = Σ
    a (m² − c) / c² / √(2 Σ a² / c²)`` (one-sided; the innovations are white under the
    model); σ_j² by weighted least squares of ``m² − c`` on ``a`` (weights ``1 / (c + σ_j²
    a)²``, twice), its σ by the sandwich over the frames with the lag-one products (a
    filter following white jitter makes consecutive innovations correlate).  Measured on
    the 300-s psce bag with 0.04 px per axis (s21): 0.0367 / 0.0393 px (u / v), z 128 / 146;
    clean: z 0.01 / 0.03, mean m²/c 0.98.

    The same estimate on the slower and the faster half of the frames (by the gyro rate):
    a frame-common error that grows with the motion (the stamps' noise, a smear, a σ that
    grows with the rate) is not this white one; ``{sigma_px, sigma_sigma_px, z, p_value,
    share, slow_px, slow_z, fast_px, fast_sigma_px, slow_sigma_px, growth_z, median_z,
    frames}`` (px, per axis, the two axes pooled; ``median_z`` the pairs' median of
    ``d² / c_d`` against a χ²₁'s in its σ), or None (fewer than 20 frames).
    """
    from stellar_cal_ros.diagnosis.stats import Rows, accepted, frames_of, image_velocity

    ok = np.asarray(mask, dtype=bool) & accepted(res) & np.isfinite(sigma_px) & (sigma_px > 0)
    if ok.sum() < 20:
        return None
    frames, k = frames_of(np.asarray(res["frame"])[ok])
    n = np.bincount(k).astype(float)
    var = np.asarray(sigma_px, dtype=float)[ok] ** 2
    w = 1.0 / var
    W = np.bincount(k, w)
    rate = np.bincount(k, np.sqrt(sum(np.asarray(res[c], dtype=float)[ok] ** 2
                                      for c in ("omega_x", "omega_y", "omega_z")))) / n
    vel = image_velocity(Rows(res, ok), focal, R_imu_st)
    ms, pcs, vs, within = [], [], [], np.zeros(len(n))
    for ax, (nu_key, s_key) in enumerate((("du", "s_uu"), ("dv", "s_vv"))):
        if vel is not None:
            vs.append(np.bincount(k, w * vel[:, ax]) / W)
        nu = np.asarray(res[nu_key], dtype=float)[ok]
        P = np.maximum(np.asarray(res[s_key], dtype=float)[ok] - var, 0.0)
        ms.append(np.bincount(k, w * nu) / W)
        within += np.bincount(k, w * (nu - ms[-1][k]) ** 2)
        pcs.append((np.bincount(k, w * np.sqrt(P)) / W) ** 2)
    # the stars' noise scale (of the σ used) from the scatter about the frames' means, per
    # rate class of the frames: a noise that grows with the motion (a smear, unseen case
    # smear2; rate_noise) makes the slewing frames' means vary more than one scale says
    dof = 2.0 * (n - 1.0)
    s2 = np.zeros(len(n))
    for part in np.array_split(np.argsort(rate, kind="stable"), COMMON_RATE_CLASSES):
        s2[part] = np.sum(within[part]) / max(float(np.sum(dof[part])), 1.0)
    cs = [pc + s2 / W for pc in pcs]
    as_ = [2.0 / (2.0 - pc / (pc + 1.0 / W)) for pc in pcs]
    use = (n >= COMMON_MIN_STARS) & np.all([np.isfinite(x) for x in ms], axis=0)
    if use.sum() < 20:
        return None
    m, c, a = (np.stack(x, 1)[use] for x in (ms, cs, as_))  # (frames, 2)
    # a frame-common error that follows the motion is no white noise (a time offset, the
    # image's smear along its motion, unseen case smear2): each axis's means less their
    # fit by a constant, the frame's image velocity v and v |v|, the null's variance by
    # each frame's share 1 - h of the fit (its leverage h)
    if vs:
        v = np.stack(vs, 1)[use]
        curve = speed_squared(v)
        for ax in range(2):
            sd = np.sqrt(c[:, ax])
            X = np.stack([np.ones(len(m)), v[:, ax], curve[:, ax]], 1) / sd[:, None]
            y = m[:, ax] / sd
            Q, _ = np.linalg.qr(X)
            m[:, ax] = (y - Q @ (Q.T @ y)) * sd
            h = np.sum(Q**2, 1)
            c[:, ax] *= 1.0 - h
            a[:, ax] *= 1.0 - h
    slow = rate[use] <= np.median(rate[use])

    # consecutive frames' differences: an error that changes slowly (a missing effect the
    # filter follows, what the fit above leaves of one) drops out, a white one does not:
    # E[(m_k - m_(k-1))^2] = c_k + c_(k-1) + σ_j² (4 ā - 2) (the filter's running mean of
    # the jitter makes consecutive innovations correlate by -K/2)
    fi = np.flatnonzero(use)
    pair = np.flatnonzero(np.diff(np.asarray(frames)[fi]) == 1)
    if len(pair) < 20:
        return None
    d2 = (m[pair + 1] - m[pair]) ** 2
    cd = c[pair + 1] + c[pair]
    b = 2.0 * (a[pair + 1] + a[pair]) - 2.0
    shared = c[pair + 1]  # (a pair's later frame is the next pair's earlier one)
    nxt = np.flatnonzero(pair[1:] == pair[:-1] + 1)

    def fit(sel: np.ndarray) -> tuple[float, float, float]:
        """(σ_j², its σ, z) on the pairs ``sel`` (rows of ``pair``)."""
        nx = nxt[sel[nxt] & sel[nxt + 1]]
        g = np.where(sel[:, None], b / cd**2, 0.0)
        var0 = float(np.sum(2.0 * (g * cd) ** 2) + 4.0 * np.sum(
            g[nx] * g[nx + 1] * 2.0 * shared[nx] ** 2))
        z = float(np.sum(g * (d2 - cd)) / math.sqrt(max(var0, 1e-300)))
        s2 = 0.0
        for _ in range(2):
            wt = np.where(sel[:, None], b / (cd + s2 * b) ** 2, 0.0)
            s2 = max(float(np.sum(wt * (d2 - cd)) / np.sum(wt * b)), 0.0)
        wt = np.where(sel[:, None], b / (cd + s2 * b) ** 2, 0.0)
        u = (wt * (d2 - cd - s2 * b)).sum(1)  # per pair, both axes
        v = float(np.sum(u * u) + 2.0 * np.sum(u[nx] * u[nx + 1])) / float(
            np.sum(wt * b)) ** 2
        return s2, math.sqrt(max(v, 0.0)), z

    slow = slow[pair] & slow[pair + 1]
    # (and the pairs' median: a few frames far off, a step of the installation at rest or
    # a frame whose stars were misidentified, carry the sums above but not the median of
    # d² / c_d, a χ²₁'s 0.455 under the model; its σ 1.06 / √N with the overlapping pairs'
    # squares correlated by 1/4, N / 1.5 of them independent)
    ratio = (d2 / cd).reshape(-1)
    med_z = float((np.median(ratio) - CHI2_1_MEDIAN) / (1.0614 * math.sqrt(1.5 / len(ratio))))
    s2, e2, z = fit(np.ones(len(pair), dtype=bool))
    s2s, e2s, zs = fit(slow)
    s2f, e2f, _ = fit(~slow)

    def px(x2: float, e: float) -> tuple[float, float]:
        # (σ of σ_j from that of σ_j²; at σ_j² 0 the one-σ bound's root)
        x = math.sqrt(x2)
        return x, (e / (2.0 * x) if x > 0 else math.sqrt(e))

    sig, sig_e = px(s2, e2)
    slow_px, slow_e = px(s2s, e2s)
    fast_px, fast_e = px(s2f, e2f)
    return {"sigma_px": sig, "sigma_sigma_px": sig_e, "z": z,
            "p_value": float(dist.norm.sf(z)),
            "share": float(s2 * np.mean(a) / np.median(c)),
            "slow_px": slow_px, "slow_sigma_px": slow_e, "slow_z": zs,
            "fast_px": fast_px, "fast_sigma_px": fast_e,
            "growth_z": float((s2f - s2s) / math.hypot(e2f, e2s)) if e2f + e2s > 0 else 0.0,
            "median_z": med_z, "frames": int(use.sum())}
