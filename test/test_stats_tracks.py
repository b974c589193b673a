"""The structure tests' level when a star's noise stays correlated along its track.

:func:`~stellar_cal_ros.diagnosis.stats.frame_robust_t` with ``track`` (each row's star)
and ``track_lags = (w, φ)`` (the tracks' model, ``noise_structure.track_model``) adds the
same-star covariance ``w φ^l`` the frames' lag window leaves out.  Here synthetic runs: 150
frames, 150 stars each seen for 10-80 consecutive frames (as ``benchmarks/ar1_level.py``'s
draws), a frame-common error (the attitude) and per-star centroid noise white, AR(1) of ρ
0.82 (τ 5 frames), or white + AR(1) (share 0.265, the mixed bags of
``benchmarks/mixed_noise.py``), the model given as simulated; the regressor a property of
the star (its magnitude, column, radius: constant along its track up to a little drift) or
of the frame.  Under each, the two-sided p of the slope must be uniform: its mean 0.5
within 3 σ of a mean of uniforms, the rates below 5 % and 1 % within 3 σ of a binomial at
those rates.  The frames alone (before: white tracks still take that form) fail these under
correlated tracks (measured, 400 draws: 12-14 % below 5 %, 4 % below 1 %), which the last
test keeps in view.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from stellar_cal_ros.diagnosis import stats

FRAMES, TRACKS = 150, 150
DRAWS = 400


def _draw(rng, rho, share, frame_x):
    """``(x, y, frame, star)`` rows in frame order: one synthetic evaluation window."""
    n = rng.integers(10, 81, TRACKS)  # each star's track length, frames
    f0 = rng.integers(0, FRAMES - n + 1)
    ar = np.empty((TRACKS, 80))  # AR(1) of unit variance along each track
    ar[:, 0] = rng.standard_normal(TRACKS)
    for i in range(1, 80):
        ar[:, i] = rho * ar[:, i - 1] + math.sqrt(1.0 - rho * rho) * rng.standard_normal(TRACKS)
    noise = math.sqrt(share) * ar + math.sqrt(1.0 - share) * rng.standard_normal((TRACKS, 80))
    keep = np.arange(80)[None, :] < n[:, None]
    s = np.broadcast_to(np.arange(TRACKS)[:, None], keep.shape)[keep]
    f = (f0[:, None] + np.arange(80)[None, :])[keep]
    e = noise[keep]
    x = (rng.standard_normal(TRACKS)[:, None]  # a star's property, a little drift
         + 0.1 * rng.standard_normal((TRACKS, 80)))[keep]
    e = e + 0.5 * rng.standard_normal(FRAMES)[f]  # the frame's attitude error, every star
    if frame_x:
        x = np.cumsum(rng.standard_normal(FRAMES))[f]  # a slowly drifting frame property
    order = np.argsort(f, kind="stable")
    return x[order], e[order], f[order], s[order]


def _pvalues(rho, share, frame_x, track, seed):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(DRAWS):
        x, y, frame, star = _draw(rng, rho, share, frame_x)
        lags = (share, rho) if track and rho > 0 else None  # the tracks' model (white: none)
        out.append(stats.frame_robust_t(stats.normal_scores(x), y, frame, track=star,
                                        track_lags=lags)[1])
    return np.array(out)


def _uniform(p):
    """Mean and the rates below 5 % and 1 % within 3 σ of uniform p-values."""
    n = len(p)
    assert abs(p.mean() - 0.5) < 3.0 * math.sqrt(1.0 / 12.0 / n), p.mean()
    for level in (0.05, 0.01):
        rate = float(np.mean(p < level))
        assert abs(rate - level) < 3.0 * math.sqrt(level * (1.0 - level) / n), (level, rate)


@pytest.mark.parametrize("rho,share", [(0.0, 1.0), (0.81873, 1.0), (0.81873, 0.265)],
                         ids=["white", "ar1", "white+ar1"])
def test_star_regressor_test_holds_its_level_on_correlated_tracks(rho, share):
    _uniform(_pvalues(rho, share, frame_x=False, track=True, seed=11))


@pytest.mark.parametrize("rho,share", [(0.0, 1.0), (0.81873, 0.265)],
                         ids=["white", "white+ar1"])
def test_frame_regressor_test_holds_its_level_with_the_tracks(rho, share):
    _uniform(_pvalues(rho, share, frame_x=True, track=True, seed=12))


def test_frames_alone_read_a_star_property_under_ar1_tracks_as_structure():
    """Why the tracks' model is needed: with the frames alone (the lag window from the
    frame scores' lag-1) the same draws give far more than 1 % below 1 %."""
    p = _pvalues(0.81873, 1.0, frame_x=False, track=False, seed=11)
    assert np.mean(p < 0.01) > 0.01 + 3.0 * math.sqrt(0.01 * 0.99 / DRAWS)


@pytest.mark.parametrize("dtype", [np.int64, np.int32, np.uint32, np.uint64])
def test_frame_index_is_uniques_inverse_for_stacked_and_unordered_frames(dtype):
    """``stats.frame_index`` gives ``np.unique``'s inverse, dtype included, for frames in
    time order (counted), stacked twice or out of order over few values (ranked through a
    table of the values: ``shaped_tests``' u-then-v rows) and spread over many values
    (sorted); ``stats.frames_of`` gives ``np.unique``'s values and inverse (floats too)."""
    rng = np.random.default_rng(7)
    ordered = np.repeat(np.arange(5, 3000), rng.integers(1, 30, 2995)).astype(dtype)
    cases = [ordered, np.concatenate([ordered, ordered]), ordered[::-1],
             rng.integers(0, 50, 1000).astype(dtype), np.array([3, 1], dtype=dtype),
             np.array([7, 7, 2, 9, 2], dtype=dtype), np.array([0, 10**12, 5], dtype=dtype)
             if np.iinfo(dtype).max > 10**12 else np.array([0, 10**9, 5], dtype=dtype)]
    if np.issubdtype(dtype, np.signedinteger):
        cases.append(np.array([-5, 3, -5, 0], dtype=dtype))
    for c in cases + [c.astype(float) for c in cases[:2]]:
        want_frames, want = np.unique(c, return_inverse=True)
        if c.dtype.kind in "iu":
            got = stats.frame_index(c)
            assert got.dtype == want.dtype
            np.testing.assert_array_equal(got, want)
        # frames_of: the frames too (the clock and step tests' frame offsets, H237)
        frames, got = stats.frames_of(c)
        assert frames.dtype == want_frames.dtype and got.dtype == want.dtype
        np.testing.assert_array_equal(frames, want_frames)
        np.testing.assert_array_equal(got, want)


def test_line_tests_shared_pieces_give_the_same_floats():
    """What the line tests now make once for several tests (issue 24.2) gives the floats
    made per test before: ``LineSlope`` is ``np.polyfit(x, y, 1)[0]`` bit for bit (a
    regressor's four components), ``frame_robust_t`` with the caller's ``index`` equals it
    without (``shaped_tests``' and ``regressor_tests``' rows)."""
    rng = np.random.default_rng(3)
    x = rng.normal(size=5000) * 3.0 + 7.0
    line = stats.LineSlope(x)
    for y in (rng.normal(size=5000), 0.2 * x + rng.normal(size=5000), -0.0 * x,
              rng.standard_t(3, size=5000) ** 2):
        assert line.slope(y) == np.polyfit(x, y, 1)[0]
    frames = np.repeat(np.arange(250), 20)
    cl = np.concatenate([frames, frames])
    track = np.tile(np.arange(20), 500)
    xx, yy = rng.normal(size=10000), rng.normal(size=10000)
    for kw in ({}, {"track": track, "track_lags": (0.3, 0.8)},
               {"track": track, "track_level": True, "dof": True}):
        assert stats.frame_robust_t(xx, yy, cl, index=stats.frame_index(cl), **kw) == \
            stats.frame_robust_t(xx, yy, cl, **kw)


def test_finite_rows_is_all_of_isfinite_over_a_row():
    """``stats.finite_rows`` (column by column, ~10x faster on a 2-h table) gives
    ``np.all(np.isfinite(a), axis=1)``: NaN and ±inf anywhere in a row, 1-12 columns
    (above 8 numpy's own), no rows, integers."""
    rng = np.random.default_rng(9)
    for cols in (1, 2, 3, 6, 8, 12):
        a = rng.normal(size=(400, cols))
        a[rng.random(a.shape) < 0.05] = np.nan
        a[rng.random(a.shape) < 0.02] = -np.inf
        for x in (a, a[:, ::-1], np.empty((0, cols)), np.ones((5, cols), dtype=int)):
            got = stats.finite_rows(x)
            assert got.dtype == bool
            np.testing.assert_array_equal(got, np.all(np.isfinite(x), axis=1))
