"""The stamp-noise test (``stats.motion_test``): its level against errors that last a
whole slew, its power and size on a stamp jitter (issue 21 item 3, unseen case
``jitter``).

Synthetic per-frame sums shaped like a 300 s psce window (``stats.frame_offsets`` of the
clean runs: ~40 ms of stamp per frame's noise in the dwells, 0.06-0.09 ms in the slews'
14 frames, two slews): the test is the stars' frame offsets along their motion, frame to
frame, against the same across it.  Its level on clean filter runs (both methods, with
and without the sky, 50 seeds) is in doc/benchmarks.md ("Frame stamp jitter").
"""

from __future__ import annotations

import numpy as np
import pytest

from stellar_cal_ros.diagnosis import stats

FRAMES = 300
SLEWS = (slice(60, 74), slice(180, 194))


def _draw(rng, jitter_s=0.0, slew_error_s=0.0, kappa=1.0):
    """``(frames, g, I, g⊥, I⊥, speed)`` with the stars' noise ``kappa`` x the stated, an
    along-motion error constant over each slew (the filter's, lasting a slew: a sign per
    slew) and a stamp noise of ``jitter_s`` per frame."""
    info = 1.0 / rng.uniform(0.038, 0.046, FRAMES) ** 2  # s^-2: ~40 ms per dwell frame
    b = np.zeros(FRAMES)
    for sl in SLEWS:
        n = sl.stop - sl.start
        info[sl] = 1.0 / rng.uniform(0.06e-3, 0.09e-3, n) ** 2
        b[sl] = slew_error_s * rng.choice([-1.0, 1.0])
    infop = info * rng.uniform(0.9, 1.1, FRAMES)
    d = b + jitter_s * rng.standard_normal(FRAMES) + np.sqrt(kappa / info) * \
        rng.standard_normal(FRAMES)
    dp = np.sqrt(kappa / infop) * rng.standard_normal(FRAMES)
    return np.arange(FRAMES), d * info, info, dp * infop, infop, 300.0


def test_the_stamp_noise_test_holds_its_level_under_slew_long_errors():
    """400 draws with an along-motion error of 0.5 ms over each slew (7x a slew frame's
    own σ) and the stars' noise 1.3x the stated: the one-sided p below 5 % / 1 % at most
    at its rate (binomial 3σ: 8.3 % / 2.5 %).  Without the frame-to-frame differences the
    slews' error reads as a stamp noise (along² 30x across², every draw)."""
    rng = np.random.default_rng(76)
    p = np.array([stats.motion_test(*_draw(rng, slew_error_s=0.5e-3, kappa=1.69)).p_value
                  for _ in range(400)])
    assert np.mean(p < 0.05) <= 0.083 and np.mean(p < 0.01) <= 0.025, \
        (np.mean(p < 0.05), np.mean(p < 0.01))
    frames, g, info, gp, infop, _ = _draw(rng, slew_error_s=0.5e-3, kappa=1.69)
    slew = np.r_[SLEWS[0], SLEWS[1]]
    assert np.mean((g / info)[slew] ** 2) > 10 * np.mean((gp / infop)[slew] ** 2)


@pytest.mark.parametrize("jitter_ms,level", [(1.0, 1e-9), (0.3, 2e-4)])
def test_a_stamp_jitter_is_found_and_sized(jitter_ms, level):
    """A stamp noise of 1 ms (0.3 ms) per frame beside the slews' 0.5 ms error, 50 draws:
    p below 1e-9 in every draw (below 2e-4, about α = 1 % over the ~45 'unexplained' tests,
    in 85 %: the across-motion reference has the slews' ~15 dof, F(ν, ν)); its size
    (printed in ms, and px at the image speed) the truth within 3 of its standard errors
    over the draws (~26 pairs of slew frames: σ ~19 % of one draw)."""
    rng = np.random.default_rng(7)
    got = [stats.motion_test(*_draw(rng, jitter_s=jitter_ms * 1e-3, slew_error_s=0.5e-3,
                                    kappa=1.69)) for _ in range(50)]
    assert all(f.component == "along motion" and f.regressor.startswith(stats.MOTION)
               for f in got)
    p = np.array([f.p_value for f in got])
    assert np.mean(p < level) >= (1.0 if jitter_ms == 1.0 else 0.85), p
    ms = np.array([float(f.regressor.split(": ")[1].split(" ms")[0]) for f in got])
    assert abs(np.mean(ms) - jitter_ms) < 3.0 * np.std(ms) / np.sqrt(len(ms)) + 0.03 * jitter_ms
    assert np.std(ms) < 0.25 * jitter_ms
    px = np.array([f.slope_px for f in got])
    assert px == pytest.approx(ms * 1e-3 * 300.0, rel=0.06)  # ms printed to 2 digits
