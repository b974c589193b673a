"""Unseen cases a real tracker and IMU produce (issue 21 acceptance), reduced.

Each test simulates a short ``psce_rotations`` bag with one error no library effect models
(``sim/tracker_errors.py``), runs the current model once and checks what the diagnosis's
tests say against the truth: an effect outside the library is found by the regressor that
carries it, with its size; noise that is only correlated or on one axis is named as noise,
not as structure.  The whole table (every case through ``stellar-cal discover``):
``benchmarks/unseen_cases.py``, doc/benchmarks.md "Cases the diagnosis was not built on".
"""

from __future__ import annotations

import dataclasses
import math
import re
from types import SimpleNamespace

import numpy as np
import pytest
from scipy import stats as sps

from stellar_cal_ros.core.gating import chi2_2_quantile
from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.diagnosis import (
    flexure,
    leads,
    noise,
    noise_stars,
    output,
    printing,
    rolling,
    shape_drift,
    stats,
)
from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
from stellar_cal_ros.diagnosis.noise_structure import correlated
from stellar_cal_ros.diagnosis.output import line_tests
from stellar_cal_ros.diagnosis.parallel import Spare
from stellar_cal_ros.diagnosis.runstats import evaluate
from stellar_cal_ros.diagnosis.twin import make_twin
from stellar_cal_ros.diagnosis.twin_command import noise_line
from stellar_cal_ros.methods.psce import PsceConfig
from stellar_cal_ros.methods.replay import bag_data_from_simulation
from stellar_cal_ros.sim import tracker_errors
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

DURATION = 150.0
SIGMA = 0.05  # the scenario's centroid noise, px


def _bag(post, seed=21, noise_free=True, duration=DURATION, **changes):
    sc = get_scenario("psce_rotations")
    if noise_free:
        changes["centroid_noise_px"] = 0.0
    sim = simulate(dataclasses.replace(sc, **changes), duration=duration, seed=seed)
    post(sim)
    return sim


def _findings(sim, star_noise=False, ranked=False):
    """The 'unexplained' tests of the current model's run, as the diagnosis makes them
    (and the stars' noise measured on it, with ``star_noise``; with ``ranked``, as
    ``output.finish`` ranks them: the rolling shutter first when the lines before it are
    its doing, and which follow it)."""
    prior = sim.prior
    data = bag_data_from_simulation(sim)
    run = evaluate(data, method_spec("psce"), rerun_prior(prior), (), 0.5,
                   keep_residuals=True)
    if ranked:

        runs = SimpleNamespace(spec=method_spec("psce"), fraction=0.5, noise=None,
                               classes=(), on_bag=lambda fn, *a: fn(data, *a))
        return rolling.first_if_cause(line_tests(run.residuals, prior, 0.5), run, runs,
                                      line_tests)
    res, cam = run.residuals, prior.camera
    mask = stats.evaluation_mask(res, 0.5)
    centre = (cam.cx, cam.cy)
    found = line_tests(res, prior, 0.5)
    if not star_noise:
        return found
    ok = mask & ~np.asarray(res["gated"]).astype(bool)
    sig = np.sqrt(0.5 * (np.asarray(res["s_uu"]) + np.asarray(res["s_vv"])))
    return found, noise_stars.star_noise(res, np.where(ok, sig, np.nan), np.ones(len(sig)), ok,
                                   cam.fx, cam.fy, centre, prior.R_imu_st)


def test_pixel_locking_is_unexplained_with_the_subpixel_phase_first():
    """An S-curve of 0.08 px (``A sin 2πu`` per axis): the first 'unexplained' line is the
    sub-pixel phase, its size 2A over the regressor's 5-95 % range (0.158 px) within 15 %;
    before this test the structure was measured as noise ("sigma 1.46x too small")."""
    amp = 0.08

    def post(sim):
        tracker_errors.s_curve(sim, amp)
        tracker_errors.renoise(sim, lambda m, uv: SIGMA, SIGMA, 21)

    found = _findings(_bag(post))
    assert found and found[0].regressor.startswith(stats.SUBPIXEL), found[:3]
    # the other leads are tested without it: none of the gravity leads its per-dwell
    # means lent them before (radial vs gravity_x_st, t = -6.6)
    assert not any(f.regressor.startswith("gravity") for f in found)
    want = 2.0 * amp * np.sin(2.0 * np.pi * 0.2)  # sin's 5-95 % range: ±0.951
    assert abs(found[0].slope_px) == pytest.approx(want, rel=0.15)


def test_rolling_shutter_readout_is_measured_from_the_row_shape():
    """Rows read out over 30 ms (stamp at the middle row): the rolling-shutter test (row x
    image velocity from the gyro) is significant and the readout it prints, its fit plus
    the fit of the re-run with that fit taken out (``stats.readout_s``), is the truth
    within 1 ms (29.73 here; seeds 21-25: 29.81 +- 0.10 ms, the fit's frame-robust sigma
    0.31-0.47 ms).  One run's fit alone reads ~12 % short (26.3 ms; the one-pass line
    25.1): the filter's calibration takes up part of the shape."""
    def post(sim):
        tracker_errors.rolling_shutter(sim, 0.03)
        tracker_errors.renoise(sim, lambda m, uv: SIGMA, SIGMA, 21)

    lines, follows = _findings(_bag(post), ranked=True)
    found = [f for f in lines if f.regressor.startswith(stats.ROLLING)]
    assert found and found[0].p_value < 0.01
    readout = float(found[0].regressor.split("readout ")[1].split(" ms")[0])
    assert readout == pytest.approx(30.0, abs=1.0)
    # ranked first: by p it came after 'u vs radius' (t = -12.6, p = 1.6e-6; its own t =
    # -101 is referred to t_nu with nu ~ 2-3, the slews' few frames), a footprint of the
    # calibration the slews pull, gone in a run with the fitted readout taken out
    assert lines[0] is found[0], lines[:3]
    assert follows and all(not lines[i].regressor.startswith(stats.ROLLING) for i in follows)
    assert ("radius", "u") in {(lines[i].regressor, lines[i].component) for i in follows}


def test_a_rolling_shutter_is_not_read_as_a_fixed_pattern_of_the_columns():
    """30 ms readout on 300 s of PSCE, seed 24 (unseen case ``rolling``'s bag): the stars'
    means per band of columns hold the shutter's displacement in the slews, and the
    fixed-pattern test fires on them (u: p 3.5e-5, a 'pattern' of 1.06 px).  Removed, it
    took the shutter from the other lines (its t −49 → −11: not significant among 86
    tests) and 'catalogue star' came first.  Where the rolling shutter's fit is
    significant the pattern is not removed: the shutter's line is first again, its readout
    the truth within 1 ms.  Fails on main (the pattern removed, no shutter line)."""
    def post(sim):
        tracker_errors.rolling_shutter(sim, 0.03)
        tracker_errors.renoise(sim, lambda m, uv: SIGMA, SIGMA, 24)

    lines, _ = _findings(_bag(post, seed=24, duration=300.0), ranked=True)
    assert lines and lines[0].regressor.startswith(stats.ROLLING), lines[:3]
    readout = float(lines[0].regressor.split("readout ")[1].split(" ms")[0])
    assert readout == pytest.approx(30.0, abs=1.0)
    assert not [f for f in lines if "fixed pattern" in f.regressor], lines


def _column_readout(seed):
    def post(sim):
        tracker_errors.rolling_shutter(sim, 0.03, "u")
        tracker_errors.renoise(sim, lambda m, uv: SIGMA, SIGMA, seed)
    return post


def test_a_column_readout_is_tested_along_the_columns():
    """Columns read out over 30 ms (column u seen (u/W - 1/2) T after the stamp; unseen case
    ``rolling_cols``): the rolling-shutter test along the columns, (u - c_x) x image
    velocity, is a line of its own (one more test of the family), its readout over the
    detector's columns the truth within 3 ms (27.7 here), and the rows' test finds nothing.
    Fails on main: the rows' test was the only one (no line named the column readout)."""
    lines, _ = _findings(_bag(_column_readout(21)), ranked=True)
    cols = [f for f in lines if stats.rolling_axis(f.regressor) == "u"]
    assert cols and cols[0].regressor.startswith(stats.ROLLING_NAMES["u"]), lines[:8]
    assert cols[0].p_value < 0.01 and cols[0].component == "u, v"
    readout = float(cols[0].regressor.split("readout ")[1].split(" ms")[0])
    assert readout == pytest.approx(30.0, abs=3.0)
    assert not [f for f in lines if stats.rolling_axis(f.regressor) == "v"], lines


def test_a_line_the_readout_leaves_at_a_small_share_of_itself_follows_it():
    """A line still found in the shutter's re-run follows it where it kept at most 10 % of
    its size there and fell at 1 % (each size's sigma its size over its t): unseen case
    ``rolling_cols`` s22, u vs radius -0.47 px (t -7.05) left at -0.012 px (t -5.73).  A
    line that keeps its size, or one whose fall is within its noise, stays.  Fails on
    main (a line still found there stayed before the shutter's line: no ``shrunk``)."""
    line = stats.RegressorFinding("radius", "u", -7.05, 2e-6, -0.47)
    assert rolling.shrunk(line, (-0.012, -5.73), 0.01)
    assert rolling.gone(line, {("radius", "u"): (-0.012, -5.73)}, alpha=0.01)
    assert not rolling.gone(line, {("radius", "u"): (-0.012, -5.73)})  # (keys only: as before)
    assert not rolling.gone(line, {("radius", "u")}, alpha=0.01)
    assert not rolling.shrunk(line, (-0.3, -5.0), 0.01)  # (64 % left: another cause's too)
    assert not rolling.shrunk(line, (-0.06, -4.0), 0.01)  # (13 % left)
    weak = stats.RegressorFinding("radius", "u", -2.5, 1e-3, -0.05)  # sigma 0.02 px
    assert not rolling.shrunk(weak, (-0.004, -4.0), 0.01)  # fall 0.046: z 2.30 < 2.33
    assert rolling.shrunk(weak, (-0.004, -4.0), 0.05)


def test_a_column_readout_first_and_its_echoes_after_it():
    """300 s of PSCE, seed 22, a 30 ms column readout (unseen case ``rolling_cols``): the
    stars' noise takes the shutter out along the columns (the innovations' fit is theirs, p
    0.0027), so its σ scale reads the noise (x1.2, x6.7 with the rows' shape taken out) and
    the calibration the readout pulled repeats star by star beyond it; on the bag with the
    fitted readout (28.7 ms) taken out the repeat is gone (z 3.0, p 0.003, with the rows'
    shape: the columns' leftover) and the radius and ripple lines are left at 2-3 % of their
    size: the shutter's line (its fit's: the line tests' own is not significant on nu ~ 2)
    goes first, every line ranked before it follows it.  Fails on main (the repeat, two
    radius lines and two ripples before it)."""
    sim = _bag(_column_readout(22), seed=22, duration=300.0)
    run, runs = _psce_run(sim)
    res, cam = run.residuals, run.calibration.camera
    assert stats.readout_axis(rolling.of_run(run, 0.5)) == "u"
    args = (res, stats.evaluation_mask(res, 0.5), cam.fx, cam.fy, (cam.cx, cam.cy),
            run.calibration.R_imu_st)
    cols, rows = noise.line_noise(*args, "u"), noise.line_noise(*args, "v")
    assert cols.scale < 1.5 < 3.0 < rows.scale, (cols.scale, rows.scale)
    found = line_tests(res, run.calibration, 0.5)
    found = sorted(found + [rolling.finding(run, 0.5, 0.01)],
                   key=lambda f: (f.p_value, -abs(f.statistic)))
    lines, after = rolling.first_if_cause(found, run, runs, line_tests)
    assert stats.rolling_axis(lines[0].regressor) == "u", lines[:6]
    readout = float(lines[0].regressor.split("readout ")[1].split(" ms")[0])
    assert readout == pytest.approx(30.0, abs=1.5)
    # (every line ranked before it follows it: the repeat, the radius lines, the ripples)
    before = found[:next(i for i, f in enumerate(found) if stats.rolling_axis(f.regressor))]
    assert len(before) >= 5 and [f for f in before if f.regressor == "catalogue star"]
    assert {id(f) for f in before} <= {id(lines[i]) for i in after}, \
        [(f.regressor, f.statistic) for f in lines]


def test_a_library_effect_standing_in_for_a_column_readout_is_refused():
    """300 s of PSCE, seed 22, a 30 ms column readout (unseen case ``rolling_cols``'s bag):
    the rolling-shutter fit on the innovations is the columns' (t -20.7, p 0.0027 with the
    x2 of the two directions; readout 28.7 ms), and radial_k3, which discover added for it
    (k3 -198; ratio 237.7), explains the data beyond that fit in the capped currency
    (243.1: the model is far off, the slews' stars are capped) while the fit stays beside
    it.  On the bag with the fitted readout taken out of the centroids its ratio is 5.2
    (p 0.023): not needed, refused as the shutter's stand-in, and the fit's line is printed
    (the line tests' own, t -32 on ν ≈ 2, is not significant among ~90).  Fails on main
    (no column fit: the rows' fit read p 0.51, and radial_k3 was added)."""
    from stellar_cal_ros.diagnosis.discover import Reference, candidate_prior

    sim = _bag(_column_readout(22), seed=22, duration=300.0)
    data, spec, prior = bag_data_from_simulation(sim), method_spec("psce"), \
        rerun_prior(sim.prior)
    base = evaluate(data, spec, prior, (), 0.5, keep_residuals=True)
    shutter = rolling.of_run(base, 0.5)
    assert shutter["axis"] == "u" and shutter["p_value"] < 0.01, shutter
    assert shutter["p_value"] == pytest.approx(2 * shutter["by_axis"]["u"]["p_value"])
    assert shutter["readout_ms"] == pytest.approx(30.0, abs=3.0)
    assert shutter["by_axis"]["v"]["p_value"] > 0.1
    k3 = candidate_prior(prior, "radial_k3", prior)
    with_k3 = evaluate(data, spec, k3, ("radial_k3",), 0.5, keep_residuals=True,
                       candidate=True)
    lam, p, _ = Reference.of(base).compare(with_k3, 1)
    c = SimpleNamespace(effect="radial_k3", statistic=lam, dof=1, seen_dof=1.0,
                        p_adjusted=min(1.0, 11 * p))
    disp = Reference.of(base).dispersion
    assert p < 1e-20
    fit = rolling.of_run(with_k3, 0.5)
    assert rolling.stand_in(c, disp, fit, shutter, 0.01) is None  # beyond it, capped
    assert rolling.needs_without(c, disp, fit, shutter, 0.01)
    got = rolling.ratio_without_on_bag(data, spec, prior, (), 0.5, None, (),
                                       base.calibration, shutter["coefficient"], "u", k3,
                                       "radial_k3", 1.0)
    assert got[0] < 10.0 and got[1] > 0.01, got
    b = rolling.not_without(c, got, shutter, 0.01)
    assert b is not None and not b["needed"] and b["without_readout"]
    assert "along the columns" in b["reason"], b["reason"]
    # needed there: not refused
    assert rolling.not_without(c, (lam, p), shutter, 0.01) is None
    # the refusal's cause printed: the fit's line, named by the columns, its size in px
    assert rolling.refused_beside(b)
    line = rolling.finding(base, 0.5, 0.01)
    assert line.regressor.startswith(stats.ROLLING_NAMES["u"]) and line.component == "u, v"
    assert line.p_value == shutter["p_value"] and 0.3 < line.slope_px < 5.0, line


def test_frame_stamp_jitter_is_unexplained_along_the_image_motion_first():
    """Every frame stamped N(0, 1 ms) off its exposure (unseen case ``jitter``; outside the
    library): the first 'unexplained' line is the stars' spread along their image motion
    from frame to frame (``stats.motion_spread``), its stamp noise the truth within its
    scatter (0.77 ms: the window's one slew holds 13 pairs of frames, σ of σ̂ ~25 %).  On main the
    first line was 'u vs radius' (the filter's camera terms pulled in the slews) and the
    rate's 'size' test reached t 2.0-2.6 (300 s, seed 21)."""
    sim = _bag(lambda sim: tracker_errors.stamp_jitter(sim, 1e-3, 21), noise_free=False)
    found = _findings(sim)
    assert found and found[0].component == "along motion", found[:3]
    assert found[0].regressor.startswith(stats.MOTION)
    ms = float(found[0].regressor.split(": ")[1].split(" ms")[0])
    assert ms == pytest.approx(1.0, rel=0.4), found[0]
    # (one slew in this window: its across-motion reference has ~7 dof, Bonferroni p 1.9e-4;
    # 300 s, two slews: 3.3e-14)
    assert found[0].p_value < 0.01


def test_a_bias_along_the_motion_growing_as_speed_squared_is_unexplained_beyond_a_time_offset():
    """A centroid bias along each star's image motion ∝ its speed squared, 0.1 px at the
    run's 95th-percentile speed (unseen case ``smear2``; outside the library), the model
    with time_offset (what ``discover`` adds: its dt is the bias's projection on an offset,
    0.38 ms): the first 'unexplained' line is the along-motion residual against the image
    rate squared beyond a time offset (``stats.speed_curve``), Bonferroni p < 0.01 (measured
    8.7e-4), its size what the same test reads on the bias itself (the truth's remainder
    beyond the offset's share, 0.0258 px) less the filter's share (0.0218 px measured: the
    filter's attitude takes part of it along each slew; the size's σ ~ 0.003).  Fails on
    coord2 4193ce7 (no such test: discover said nothing at 300 s, seeds 21, 22).  600 s: 4
    slews in the window (at 300 s, 2 slews: t -6.6/-7.6, ν 7, Bonferroni p 0.025/0.0096).
    The clean bag of the same seed, same model: no such line (t -0.78)."""
    speeds = []

    def post(sim):
        speeds.extend(np.linalg.norm(v, axis=1) for v in tracker_errors.image_velocity(sim))
        tracker_errors.speed_squared_smear(sim, 0.1)
        tracker_errors.renoise(sim, lambda m, uv: SIGMA, SIGMA, 21)

    def lines(sim):
        run = evaluate(bag_data_from_simulation(sim), method_spec("psce"),
                       rerun_prior(sim.prior), ("time_offset",), 0.5, keep_residuals=True)
        return run, line_tests(run.residuals, run.calibration, 0.5)

    run, found = lines(_bag(post, duration=600.0))
    assert found and found[0].regressor == stats.CURVE, found[:3]
    assert found[0].component == stats.CURVE_COMPONENT and found[0].p_value < 0.01
    # the truth of the same size: the test on the bias alone (the stars' own image velocity)
    res, cam = run.residuals, run.calibration.camera
    focal, centre = (cam.fx, cam.fy), (cam.cx, cam.cy)
    m = stats.evaluation_mask(res, 0.5) & stats.accepted(res)
    ok, vel, _, _ = stats.motion_columns(stats.Rows(res, m), focal, centre,
                                         run.calibration.R_imu_st)
    sub = {k: np.asarray(v)[m][ok] for k, v in res.items()}
    s95 = np.percentile(np.concatenate(speeds), 95)  # (the run's, as the bias is made)
    bias = 0.1 * np.linalg.norm(vel, axis=1)[:, None] * vel / s95**2
    sub["du"], sub["dv"] = bias[:, 0], bias[:, 1]
    truth = stats.speed_curve(sub, stats.motion_columns(sub, focal, centre,
                                                        run.calibration.R_imu_st)).slope_px
    assert found[0].slope_px == pytest.approx(truth, rel=0.3), (found[0].slope_px, truth)
    _, clean = lines(_bag(lambda sim: None, noise_free=False, duration=600.0))
    assert not [f for f in clean if f.regressor == stats.CURVE], clean[:3]


@pytest.fixture(scope="module")
def ar1_sim():
    """The unseen case 'ar1', reduced: each star's noise an AR(1) over frames (τ = 5
    frames, marginal σ as stated).  Seed 22: on seed 21 the cells' χ² referred to the exact
    finite-track factor reads p = 0.0035, 1 of seeds 21-33 below 1 % (see below), and the
    verdict then does not call the noise correlated."""
    return _bag(lambda sim: tracker_errors.ar1_noise(sim, SIGMA, 5.0, 22), seed=22)


def test_noise_correlated_over_frames_is_noise_not_a_repeat_nor_a_period(ar1_sim):
    """Each star's centroid noise an AR(1) over frames (τ = 5 frames, marginal σ as
    stated): no 'unexplained' line (before: 'repeating vs catalogue star' t = 16.5 and two
    periodic frame-mean lines: the star-mean χ² and Fisher's g assumed white noise), no
    per-star repeat, no repeating field (the detector cells' χ², referred to the same
    factor: 105 / 68 dof, p = 0.002, while ρ was read about the star means without their
    bias, 0.78); the noise is named correlated (lag-1 ρ of the star tracks e^(-1/5) = 0.82
    within 0.04), with σ √((1+ρ)/(1−ρ)) to use.  The clean bag's tracks are not called
    correlated.  With each cell's mean referred to the exact variance of a mean of its
    tracks' frames (no longer the conservative long-run factor), seeds 21-33 read ρ
    0.798-0.820 and the cells' p 0.0035 (seed 21), 0.08-0.84 on the 12 others (χ²/dof 1.06
    ± 0.05 over the 13; this seed, 22: 0.31); the level itself is
    test_repeat_and_cell_chi2_hold_their_level_on_pure_ar1_tracks."""
    found, sn = _findings(ar1_sim, star_noise=True)
    assert found == []
    assert sn.repeat_p > 0.01 and sn.structure_p > 0.01
    c = correlated(sn.track_rho, sn.track_pairs, 0.1)
    assert c is not None and c["rho"] == pytest.approx(np.exp(-0.2), abs=0.04)
    _, clean = _findings(_bag(lambda s: None, noise_free=False), star_noise=True)
    assert correlated(clean.track_rho, clean.track_pairs, 0.1) is None


def test_star_scatter_under_ar1_noise_reads_the_truth_within_its_sigma():
    """Issue 21.2: each star's noise an AR(1) over frames (τ = 5 frames, marginal σ as
    stated), 10 seeds: the stars' scatter within frames reads 1 (the truth), each seed within
    its printed σ.  The detector cells' means took part of the AR(1) variance (a track
    crosses a cell in tens of correlated frames: a cell mean varies by 1ᵀΣ1/n², counted as
    1/n): the scale read 0.940 +- 0.006 here (300 s bags, seeds 21-50: 0.968 +- 0.003), not
    the filter (pure AR(1) draws on the same rows, no filter: 0.963).  Its σ took the rows as
    independent (0.0098 for a seed-to-seed SD of 0.018, mean z² 41); a track's consecutive
    ‖r‖² correlate by ρ², now counted (``StarNoise.inflation``).  Now: mean 0.996, mean z²
    0.81 (300 s, 30 seeds: 1.005 +- 0.0035, mean z² 1.7)."""
    got = []
    for seed in range(21, 31):
        _, sn = _findings(_bag(lambda sim, seed=seed: tracker_errors.ar1_noise(
            sim, SIGMA, 5.0, seed), seed=seed), star_noise=True)
        got.append((sn.scale, sn.sigma))
    s, e = np.array(got).T
    z = (s - 1.0) / e
    assert abs(s.mean() - 1.0) < 3.0 * e.mean() / np.sqrt(len(s)), s
    # mean z² is 1 ± 0.45 (χ²_10 / 10) when the printed σ is honest
    assert np.mean(z**2) < 2.5, z


def _ar1_tracks(rng, rho, frames, tracks):
    """``tracks`` star tracks of ``frames`` AR(1) residuals (u, v), each about its mean."""
    x = np.zeros((tracks, frames, 2))
    x[:, 0] = rng.standard_normal((tracks, 2))
    for t in range(1, frames):
        x[:, t] = rho * x[:, t - 1] + np.sqrt(1.0 - rho**2) * rng.standard_normal((tracks, 2))
    x -= x.mean(1, keepdims=True)
    return x.reshape(-1, 2), np.repeat(np.arange(tracks), frames)


def test_track_rho_is_unbiased_about_the_star_means_and_short_tracks_read_white():
    """noise_structure.track_inflation on pure AR(1) tracks (known truth): the pooled lag-1
    ρ about each star's mean, solved with the exact moments of tracks of their lengths,
    reads 0.82 within 4 σ (Bartlett's σ = √((1 − ρ²)/N), N the pairs of both axes; the
    (1 + ρ) b approximation gave 0.817 over 200 seeds, SD
    1.15 σ); the (1 + 3ρ) b it had over-corrected to 0.847 (10 σ).  White noise on tracks of
    2-3 frames (a pair about its mean reads exactly −1) is white: ρ 0 on 2 frames, not
    called correlated on 3 (it had read ρ 0.95, σ ×6.2 applied as 'correlated noise')."""
    from stellar_cal_ros.diagnosis.noise_structure import track_inflation

    rho = np.exp(-0.2)
    r, star = _ar1_tracks(np.random.default_rng(5), rho, 55, 400)
    _, got, pairs = track_inflation(r, star)
    assert abs(got - rho) < 4.0 * np.sqrt((1.0 - rho**2) / (2 * pairs)), got
    rng = np.random.default_rng(6)
    r, star = _ar1_tracks(rng, 0.0, 2, 300)
    assert track_inflation(r, star)[:2] == (1.0, 0.0)
    # 3 frames: the exact moments read white noise as ρ ≈ 0 (200 draws: mean 0.027, SD
    # 0.039, clipped at 0); ρ is worth the pairs times the raw ratio's slope² (0.25 here),
    # so it is not called correlated (it was 8 times in 200 on the raw pairs)
    for _ in range(20):
        _, got, pairs = track_inflation(*_ar1_tracks(rng, 0.0, 3, 300))
        assert got < 0.2 and correlated(got, pairs, 0.1) is None, (got, pairs)


def test_repeat_and_cell_chi2_hold_their_level_on_pure_ar1_tracks():
    """The per-star repeat's and the detector cells' χ² on pure AR(1) tracks (ρ 0.82, 10-80
    frames, 150 stars, tracks crossing 1-3 cells; ``benchmarks/ar1_level.py``'s draws):
    each mean referred to the exact variance of a mean of its tracks' frames
    (``noise_structure.lagged_chi2``, ρ estimated as the diagnosis does), the p-values are
    uniform: their mean 0.5 within 4 σ (σ = 1/√(12 R), R draws; 1000 draws: 0.501 and 0.490,
    5 % level 0.060 and 0.048; the repeat after the cells' means, ``star_after_cells`` with
    its exact AR(1) trace, 400 draws: 0.492, 5 % level 0.062).  The long-run factor
    (1+ρ)/(1−ρ) they had read 0.874 and 0.946 (no p below 5 % in 200 draws) and ρ̂ 0.816;
    the exact moments: ρ̂ 0.819 ± 0.006."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from ar1_level import draw, pvalues

    rho, reps = np.exp(-0.2), 100
    rng = np.random.default_rng(11)
    P = np.array([pvalues(*draw(rng, rho)) for _ in range(reps)])
    for j in range(2):
        assert abs(P[:, j].mean() - 0.5) < 4.0 / np.sqrt(12.0 * reps), (j, P[:, j].mean())
    assert abs(P[:, 2].mean() - rho) < 4.0 * P[:, 2].std() / np.sqrt(reps)


def test_structure_fits_take_one_dof_per_coefficient():
    """noise_structure.minus_rolling (one coefficient) and minus_subpixel (2 per axis) take
    exactly that many dof from the rows' 2 each when their fit is removed: Σ 2 Δshare = 1
    and 4 (the leverages of a least-squares fit sum to its coefficients).  minus_rolling
    had taken 2 for 1."""
    from stellar_cal_ros.diagnosis.noise_structure import minus_rolling, minus_subpixel

    rng = np.random.default_rng(9)
    n = 2000
    share = np.ones(n)
    x = rng.standard_normal((n, 2))
    r = rng.standard_normal((n, 2)) + 0.3 * x  # a readout far above its sigma
    _, got, _ = minus_rolling(r, share, x, 0.01)
    assert 2.0 * float(np.sum(share - got)) == pytest.approx(1.0, rel=1e-9)
    uv = rng.uniform(0.0, 1024.0, (n, 2))
    r = rng.standard_normal((n, 2)) + 0.3 * np.sin(2.0 * np.pi * uv)  # pixel locking
    _, got, _ = minus_subpixel(r, share, uv, 0.01)
    assert 2.0 * float(np.sum(share - got)) == pytest.approx(4.0, rel=1e-9)


def test_joint_structure_fit_tests_each_block_given_the_other():
    """noise_structure.minus_fits fits the blocks together and tests each given the others:
    on white noise a block's χ² is exactly the drop in the residual sum of squares its
    columns make beside the other block's (the partial χ²), so a block that overlaps a real
    structure of the other does not take it (here: a readout far above its σ and a
    sub-pixel block that shares a third of its shape; fitted first, as before, the sub-pixel
    block took it: p < 1e-6).  The blocks that fire are removed by their own fit, with one
    dof per coefficient."""
    from stellar_cal_ros.diagnosis.noise_structure import minus_fits

    rng = np.random.default_rng(9)
    n = 3000
    share = np.ones(n)
    x = rng.standard_normal((n, 2, 1))
    S = rng.standard_normal((n, 2, 4))
    S[:, :, 0] += 0.6 * x[:, :, 0]  # the blocks overlap
    r = rng.standard_normal((n, 2))
    got, sh, (p_s, p_x) = minus_fits(r, share, [S, x], 0.01)
    assert p_s > 0.01 and p_x > 0.01 and got is r  # noise alone: nothing removed

    def rss(X):
        Xf = X.reshape(2 * n, -1)
        e = r.reshape(-1) - Xf @ np.linalg.lstsq(Xf, r.reshape(-1), rcond=None)[0]
        return float(e @ e)

    full = rss(np.concatenate([S, x], 2))
    assert sps.chi2.isf(p_s, 4) == pytest.approx(rss(x) - full, rel=1e-6)
    assert sps.chi2.isf(p_x, 1) == pytest.approx(rss(S) - full, rel=1e-6)
    r = r + 0.2 * x[:, :, 0]  # a readout: the rolling block fires, the sub-pixel does not
    got, sh, (p_s, p_x) = minus_fits(r, share, [S, x], 0.01)
    assert p_x < 1e-6 and p_s > 0.01, (p_s, p_x)
    assert 2.0 * float(np.sum(share - sh)) == pytest.approx(1.0, rel=1e-9)
    b = float(np.sum(x[:, :, 0] * r) / np.sum(x ** 2))
    assert np.allclose(got, r - b * x[:, :, 0])
    assert minus_fits(r, share, [S], 0.01)[2][0] < 1e-6  # alone, it takes the readout


def test_along_tracks_is_the_tracks_covariance_and_white_fits_are_the_plain_ones():
    """noise_structure.along_tracks applies the tracks' white + AR(1) covariance (``Σ_ij =
    w φ^|i−j|``, 1 on the diagonal, tracks independent, rows of a track in time order and
    interleaved with other tracks as a residual table holds them) without forming it: equal
    to the dense product to 1e-12.  track_fit on white tracks (φ 0) is the plain fit: its χ²
    ``bᵀXᵀXb`` and leverages summing to half its coefficients."""
    from stellar_cal_ros.diagnosis.noise_structure import along_tracks, track_fit

    rng = np.random.default_rng(4)
    track = rng.integers(0, 9, 400)
    X = rng.standard_normal((400, 2, 3))
    for w, phi in ((1.0, 0.82), (0.27, 0.6), (1.0, 0.95)):
        want = np.zeros_like(X)
        for t in np.unique(track):
            i = np.flatnonzero(track == t)
            k = np.arange(len(i))
            S = w * phi ** np.abs(k[:, None] - k[None, :]) + (1.0 - w) * np.eye(len(i))
            want[i] = np.einsum("ij,jab->iab", S, X[i])
        assert np.abs(along_tracks(X, track, (w, phi)) - want).max() < 1e-12
    r = rng.standard_normal((400, 2))
    fit, chi2, lev = track_fit(r, X, track, (1.0, 0.0))
    Xf = X.reshape(800, 3)
    b = np.linalg.lstsq(Xf, r.reshape(800), rcond=None)[0]
    assert chi2 == pytest.approx(float(b @ Xf.T @ Xf @ b), rel=1e-10)
    assert np.allclose(fit.reshape(800), Xf @ b) and lev.sum() == pytest.approx(1.5)


@pytest.fixture(scope="module")
def ar1_table():
    """``benchmarks/nuisance_level.py``'s residual table of a 150 s ``psce_rotations`` bag
    (seed 22, the current model's run), its camera and installation."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import nuisance_level

    return nuisance_level, nuisance_level.table(DURATION, 22)


def _fires(nl, table, rho, reps, seed=7, subpixel=0.0, readout=0.0):
    """How many of ``reps`` draws of centroid noise (AR(1) of ``rho``, 0 white; plus
    ``subpixel`` px of locking and a ``readout`` s rolling shutter) put into ``table``
    (``benchmarks/nuisance_level.py``) fire the sub-pixel and the rolling fit at 1 %, and
    their mean p-values."""
    res, cam, R = table
    rng = np.random.default_rng(seed)
    P = np.array([(sn.subpixel_p, sn.rolling_p) for sn in (
        nl.one(res, cam, R, SIGMA * nl.track_noise(res, rng, rho), subpixel, readout)
        for _ in range(reps))])
    return (P < noise_stars.ALPHA).sum(0), P.mean(0)


def _level_limit(reps):
    """1 % of ``reps`` draws plus 4 binomial σ."""
    return reps * 0.01 + 4.0 * np.sqrt(reps * 0.01 * 0.99)


def test_structure_fits_hold_their_level_on_ar1_noise(ar1_table, monkeypatch):
    """The sub-pixel (pixel locking) and rolling-shutter fits star_noise removes where their
    χ² is significant at 1 %: on pure AR(1) centroid noise (τ 5 frames, the 'ar1' case's;
    20 draws put into one bag's residual table, ``benchmarks/nuisance_level.py``) they fire
    in at most 1 % + 4 binomial σ of the draws (≤ 1 of 20): their χ² referred to the tracks'
    correlation (noise_structure.track_fit, the model the cells' test reads): 0 and 0 of 20
    here.  Taken as white (before H72) the sub-pixel fit fired in 6 of these 20 draws (a
    300 s table, 200 draws: 0.415; the comparison: the benchmark test below).  White noise
    keeps the white fits (no model: the previous code's numbers bit for bit)."""
    nl, table = ar1_table
    got, _ = _fires(nl, table, np.exp(-0.2), 20)
    assert np.all(got <= _level_limit(20)), got
    # white noise: no track model, so the fits are the white ones
    res, cam, R = table
    noise = SIGMA * nl.track_noise(res, np.random.default_rng(3), 0.0)
    sn = nl.one(res, cam, R, noise)
    monkeypatch.setattr(noise_stars, "_fit_lags", lambda *a: None)
    white = nl.one(res, cam, R, noise)
    assert (sn.scale, sn.sigma, sn.subpixel_p, sn.rolling_p, sn.structure) == \
        (white.scale, white.sigma, white.subpixel_p, white.rolling_p, white.structure)


def test_a_nonpositive_trace_estimate_falls_back_to_the_sandwich(ar1_table, monkeypatch):
    """The AR(1) scale's σ comes from a stochastic trace (noise_stars.quadratic_variance,
    one probe on a large table): should its estimate of Var log s² come out ≤ 0 or not
    finite, star_noise falls back to the sandwich × the tracks' factor (a finite,
    positive σ), never a square root of a negative number."""
    nl, (res, cam, R) = ar1_table
    noise_draw = SIGMA * nl.track_noise(res, np.random.default_rng(7), 0.9)
    sn = nl.one(res, cam, R, noise_draw)
    assert sn.log_variance is not None and sn.log_variance > 0  # the path is taken
    for bad in (-1e-6, 0.0, float("nan")):
        monkeypatch.setattr(noise_stars, "_correlated_variance", lambda *a, v=bad: v)
        fb = nl.one(res, cam, R, noise_draw)
        assert fb.log_variance is None and fb.scale == pytest.approx(sn.scale, rel=1e-12)
        assert np.isfinite(fb.sigma) and 0.5 * sn.sigma < fb.sigma < 2.0 * sn.sigma


def test_ar1_scale_sigma_is_its_scatter_over_draws(ar1_table):
    """The stars' scale σ printed under AR(1) centroid noise (τ ≈ 9.5 frames, φ 0.9) is the
    scale's SD over 160 pure draws into one 150 s bag's residual table: SD / rms printed σ
    within 1 ± 2 of the ratio's σ, 1/√(2 (N − 1)) (0.056).  The σ counts the variance of
    Σ q through the frames' attitude fit and the cells' means, and that of the dof the cells'
    shares take from ρ̂ (read from the same residuals: a realization with more long-run
    power reads both more Σ q and a higher ρ̂; noise_stars._correlated_variance).  Here
    1.073; the sandwich × the tracks' factor (main) read 1.264 on the same draws (0.973 /
    1.130 with seed 5; 300 s bags 21-90: 1.129 ± 0.096, main 1.224 ± 0.104)."""
    nl, (res, cam, R) = ar1_table
    reps = 160
    rng = np.random.default_rng(7)
    got = np.array([(sn.scale, sn.sigma) for sn in (
        nl.one(res, cam, R, SIGMA * nl.track_noise(res, rng, 0.9)) for _ in range(reps))])
    ratio = got[:, 0].std(ddof=1) / np.sqrt(np.mean(got[:, 1] ** 2))
    assert abs(ratio - 1.0) < 2.0 / np.sqrt(2.0 * (reps - 1)), ratio


@pytest.mark.benchmark
def test_structure_fits_hold_their_level_on_ar1_noise_against_white_fits(ar1_table,
                                                                          monkeypatch):
    """The full comparison (H72): 40 draws of pure AR(1) noise (τ 5 frames) into the table,
    the fits referred to the tracks' correlation fire in ≤ 1 % + 4 binomial σ (≤ 3 of 40;
    0 and 1 here), taken as white they fired the sub-pixel fit in 15 of the same 40 (14
    before the joint fit; a 300 s table, 200 draws: 0.415 and 0.080)."""
    nl, table = ar1_table
    got, _ = _fires(nl, table, np.exp(-0.2), 40)
    assert np.all(got <= _level_limit(40)), got
    monkeypatch.setattr(noise_stars, "_fit_lags", lambda *a: None)
    old, _ = _fires(nl, table, np.exp(-0.2), 40)
    assert old[0] > _level_limit(40), old  # the white sub-pixel fit's false alarms


def test_a_readout_does_not_fire_the_subpixel_fit(ar1_table):
    """A 10 ms rolling readout on white centroid noise (20 draws into the table): the
    rolling fit fires in every draw and the sub-pixel fit, tested given it
    (noise_structure.minus_fits), at its level: ≤ 1 % + 4 binomial σ (≤ 1 of 20; 0 here),
    its mean p within 4 σ (1/√(12 · 20)) of ½ (0.56).  Fitted first and alone (before), the
    sub-pixel fit took part of the readout's shape: 7 of 20, mean p 0.09 (300 s table: 3 ms
    fired it in 6 of 100, mean p 0.33; ``benchmarks/nuisance_level.py --rho 0 --readout
    3``).  And a 0.08 px pixel locking does not fire the rolling fit (≤ 1 of 20)."""
    nl, table = ar1_table
    got, p = _fires(nl, table, 0.0, 20, seed=3, readout=0.010)
    assert got[1] == 20 and got[0] <= _level_limit(20), got
    assert abs(p[0] - 0.5) < 4.0 / np.sqrt(12.0 * 20), p
    got, p = _fires(nl, table, 0.0, 20, seed=3, subpixel=0.08)
    assert got[0] == 20 and got[1] <= _level_limit(20), got


def test_structure_fits_find_pixel_locking_and_a_readout_under_ar1_noise(ar1_table):
    """Referred to the tracks' correlation, the fits still find what they are for under
    AR(1) noise (τ 5 frames): pixel locking of PIXEL px and a 3 ms readout fire in every
    one of 10 draws, and once removed the stars' scale reads 1 (truth) within 4 of its
    SD over the draws / √10."""
    nl, (res, cam, R) = ar1_table
    rng = np.random.default_rng(5)
    for sub, ro, k in ((0.01, 0.0, 0), (0.0, 0.003, 1)):
        got = [nl.one(res, cam, R, SIGMA * nl.track_noise(res, rng, np.exp(-0.2)), sub, ro)
               for _ in range(10)]
        p = np.array([(sn.subpixel_p, sn.rolling_p)[k] for sn in got])
        assert np.all(p < noise_stars.ALPHA), p
        s = np.array([sn.scale for sn in got])
        assert abs(s.mean() - 1.0) < 4.0 * s.std(ddof=1) / np.sqrt(len(s)), s


def test_pixel_locking_removed_leaves_the_white_scale_at_one(ar1_table):
    """Pixel locking of 0.08 px on white centroid noise (10 draws into one bag's residual
    table): the sub-pixel fit fires in every draw, and its regressors taken through the
    frames' attitude fit as the residuals are (noise_structure.subpixel_columns projected
    by stats.within_frame) leave the stars' scale at 1 (truth) within 4 of its SD over
    the draws / √10, each draw within 4 of its printed σ.  Fitted raw (before), the locking
    the attitude fit had taken part of was left in: 1.045 ± 0.007 (300 s table, 100 draws,
    ``benchmarks/nuisance_level.py --rho 0 --subpixel 0.08``), read as track correlation
    too (ρ̂ 0.05 for 0)."""
    nl, (res, cam, R) = ar1_table
    rng = np.random.default_rng(11)
    got = [nl.one(res, cam, R, SIGMA * nl.track_noise(res, rng, 0.0), 0.08)
           for _ in range(10)]
    assert all(sn.subpixel_p < noise_stars.ALPHA for sn in got)
    s = np.array([sn.scale for sn in got])
    assert abs(s.mean() - 1.0) < 4.0 * s.std(ddof=1) / np.sqrt(len(s)), s
    assert all(abs(sn.scale - 1.0) < 4.0 * sn.sigma for sn in got), s


def test_one_noisy_gyro_axis_is_measured_per_axis():
    """The gyro's z axis 4x its stated white noise, x and y as stated: the samples' scale
    is the axes' RMS (√6 = 2.45; the median of the axes said 1.0 and discover then added a
    gyro_misalignment), with each axis within 5 %; equal axes keep the median."""
    from stellar_cal_ros.diagnosis.noise_imu import imu_sample_scale, sample_noise

    sim = _bag(lambda s: tracker_errors.imu_noise_axis(s, "gyro", 2, 4.0, 5),
               noise_free=False)
    s, e, white, axes = imu_sample_scale(bag_data_from_simulation(sim), "psce", "gyro",
                                         NoiseScales())
    assert white and s == pytest.approx(np.sqrt(6.0), abs=max(3 * e, 0.05))
    assert np.allclose(axes, [1.0, 1.0, 4.0], rtol=0.05)
    x = np.random.default_rng(3).standard_normal((20000, 3)) * [1.0, 1.1, 0.95]
    s1, _, _, mad = sample_noise(x, axes=True)
    assert s1 == pytest.approx(float(np.median(mad)))


def test_rolling_shutter_on_a_swaying_base_is_no_noise_and_has_no_stand_in():
    """30 ms readout on a swaying base (~3 px of sway), 100 s: the stars' σ is measured
    without the readout's shape (before: "sigma x39", by row, 'correlated'), the shape's
    fit on the innovations is significant (readout within 20 %), and a time_offset, which
    discover added for it before, explains nothing beyond that fit
    (:func:`~stellar_cal_ros.diagnosis.flexure.beyond`, discover's stand-in rule).  On a
    clean swaying bag the fit is not significant (the rule does not fire)."""
    from stellar_cal_ros.diagnosis import flexure, rolling
    from stellar_cal_ros.diagnosis.discover import Reference, candidate_prior
    from stellar_cal_ros.diagnosis.injection import SWAY_CLEAN

    def runs(readout):
        sc = dataclasses.replace(get_scenario("swaying"), centroid_noise_px=0.0)
        sim = simulate(sc, duration=100.0, seed=21, effects=dict(SWAY_CLEAN))
        if readout:
            tracker_errors.rolling_shutter(sim, readout)
        tracker_errors.renoise(sim, lambda m, uv: SIGMA, SIGMA, 21)
        data, spec, prior = bag_data_from_simulation(sim), method_spec("swaying_base"), \
            rerun_prior(sim.prior)
        base = evaluate(data, spec, prior, (), 0.5, keep_residuals=True, star_noise=True)
        return data, spec, prior, base

    data, spec, prior, base = runs(0.03)
    # the readout's shape removed, the stars' σ is near the stated (1.18; x18.1 without it)
    # and the model is too far off for the noise to be measured: taken as stated
    assert base.star_noise.scale < 1.3
    assert correlated(base.star_noise.track_rho, base.star_noise.track_pairs, 0.1) is None
    assert "too far off" in noise.far_off(base, base.star_noise)
    shutter = rolling.of_run(base, 0.5)
    assert shutter["p_value"] < 0.01
    assert shutter["readout_ms"] == pytest.approx(30.0, rel=0.2)
    # the readout the line prints (its fit + the re-run's, stats.readout_s): within 1 ms
    from types import SimpleNamespace

    runner = SimpleNamespace(spec=spec, fraction=0.5, noise=None, classes=(),
                             on_bag=lambda fn, *a: fn(data, *a))
    lines, _ = rolling.first_if_cause(line_tests(base.residuals, prior, 0.5), base, runner,
                                      line_tests)
    assert lines[0].regressor.startswith(stats.ROLLING), lines[:2]
    assert float(lines[0].regressor.split("readout ")[1].split(" ms")[0]) == \
        pytest.approx(30.0, abs=1.0)
    # the same re-run started before the line tests (a cluster's worker beside them): the
    # same lines, the re-run made once, by the runner's 'spare', not its 'on_bag'
    calls = []

    def spare(fn, *a):
        calls.append(fn.__name__)
        return Spare(lambda: fn(data, *a))

    ahead = SimpleNamespace(spec=spec, fraction=0.5, noise=None, classes=(), spare=spare,
                            on_bag=lambda fn, *a: calls.append("on_bag"))
    started = rolling.start_lines_without(base, ahead, line_tests)
    assert calls == ["lines_without_on_bag"] and started[0] == shutter
    again, _ = rolling.first_if_cause(line_tests(base.residuals, prior, 0.5), base, ahead,
                                      line_tests, started=started)
    assert [f.regressor for f in again] == [f.regressor for f in lines]
    assert calls == ["lines_without_on_bag"]
    # where the re-run fails the line keeps its one-pass slope, over the detector's rows
    # as well (stats.readout_s, the one formula; was 2 c_y of the filter-pulled principal
    # point): twice the rows, twice the readout, the fits unchanged
    failed = SimpleNamespace(spec=spec, fraction=0.5, noise=None, classes=(),
                             on_bag=lambda fn, *a: None)

    def one_pass(cal):
        got, _ = rolling.first_if_cause(line_tests(base.residuals, cal, 0.5), base, failed,
                                        line_tests)
        line = next(f for f in got if f.regressor.startswith(stats.ROLLING))
        return float(line.regressor.split("readout ")[1].split(" ms")[0])

    rows2 = dataclasses.replace(prior, camera=dataclasses.replace(
        prior.camera, height=2 * prior.camera.height))
    ms = one_pass(prior)
    assert one_pass(rows2) == pytest.approx(2 * ms, abs=0.16)
    fitted = base.calibration
    assert rolling.of_table(base.residuals, dataclasses.replace(fitted, camera=dataclasses.replace(
        fitted.camera, height=2 * fitted.camera.height)), 0.5)["readout_ms"] == \
        pytest.approx(2 * shutter["readout_ms"], rel=1e-12)
    assert ms == pytest.approx(30.0, rel=0.2)
    # the rule, where the noise had been rescaled as before (x18): time_offset is then
    # significant alone, and explains nothing beyond the fit
    scaled = NoiseScales(star=18.1)
    base = evaluate(data, spec, prior, (), 0.5, keep_residuals=True, noise=scaled)
    with_to = evaluate(data, spec, candidate_prior(prior, "time_offset", prior),
                       ("time_offset",), 0.5, keep_residuals=True, candidate=True,
                       noise=scaled)
    lam, p, _ = Reference.of(base).compare(with_to, 1)
    b = flexure.beyond(lam, 1, Reference.of(base).dispersion, rolling.of_run(with_to, 0.5),
                       rolling.of_run(base, 0.5))
    assert p < 0.01 and not b["needed"], (lam, p, b)
    # the fit stays significant beside it: discover refuses it as the shutter's stand-in
    assert rolling.stand_in(SimpleNamespace(statistic=lam, dof=1),
                            Reference.of(base).dispersion, rolling.of_run(with_to, 0.5),
                            rolling.of_run(base, 0.5), 0.01) is not None
    assert rolling.of_run(runs(0.0)[3], 0.5)["p_value"] > 0.01


def test_a_shutter_fit_that_vanishes_beside_a_candidate_does_not_refuse_it():
    """``rolling.stand_in`` on the numbers of the acceptance case swaying_time_tilt_misalignment
    (200 s, round 1; true 5 ms time offset, model far off): the shutter's fit on the current
    model (χ² 65 291 uncapped, 1 156.9 with each star's NIS capped as Λ's is) is gone beside
    time_offset (2.5, p 0.72; capped gain 0).  With the uncapped χ² the beyond ratio read
    135.6 + (2.5 − 65 290.6)/177.7 = −231.8 (the full 900 s case −1013.8) and refused
    time_offset before 15398c3; in one currency it is 129.1 (p 6e-30): time_offset explains
    the data beyond the shutter's shape, and the fit vanishing beside it says the same.  A
    candidate that explains less than the fit loses beside it, with the fit still
    significant, is refused, its ratio negative (no χ² tail)."""
    c = SimpleNamespace(statistic=135.609, dof=1)
    disp = 177.7206
    shutter = {"t": -4.066, "p_value": 1.26e-3, "chi2": 65290.61, "chi2_capped": 1156.861}
    gone = {"t": 0.358, "p_value": 0.723, "chi2": 2.457, "chi2_capped": 0.0}
    assert rolling.stand_in(c, disp, gone, shutter, 0.01) is None
    b = flexure.beyond(c.statistic, 1, disp, gone, shutter)
    assert b["statistic"] == pytest.approx(129.10, abs=0.01) and b["needed"], b
    assert c.statistic + (gone["chi2"] - shutter["chi2"]) / disp == pytest.approx(-231.75,
                                                                                   abs=0.01)
    kept = dict(gone, t=-12.0, p_value=1e-12)
    assert rolling.stand_in(c, disp, kept, shutter, 0.01) is None  # needed beyond it
    weak = SimpleNamespace(statistic=3.0, dof=1)
    b = rolling.stand_in(weak, disp, kept, shutter, 0.01)
    assert b["statistic"] == pytest.approx(3.0 - 1156.861 / disp) and b["negative"]
    assert not b["needed"] and b["remainder"] == rolling.REMAINDER
    assert rolling.stand_in(weak, disp, gone, shutter, 0.01) is None  # the fit vanished


def test_rolling_taken_out_interpolates_all_stamps_at_once_as_frame_by_frame():
    """``rolling.taken_out`` reads the gyro rate at every frame stamp in one ``np.interp``
    per axis: the centroids it writes are those of the frame-by-frame reading (3
    ``np.interp`` per frame, as before), bit for bit, and a frame without stars is kept."""
    sim = simulate(get_scenario("psce_rotations"), duration=8.0, seed=5)
    data = bag_data_from_simulation(sim)
    data = dataclasses.replace(data, frames=[dataclasses.replace(data.frames[0], uv=np.zeros(
        (0, 2)))] + list(data.frames[1:]))
    cal, coef = sim.prior, 1.3e-5
    cam = cal.camera
    got = rolling.taken_out(data, cal, coef)
    assert got.frames[0] is data.frames[0]
    for f, g in zip(data.frames[1:], got.frames[1:], strict=True):
        uv = np.asarray(f.uv, dtype=float).reshape(-1, 2)
        t = (f.stamp_ns - data.t0_ns) * 1e-9
        w = [np.interp(t, data.imu_t, data.imu_w[:, k]) for k in range(3)]
        sub = {"x_st": (uv[:, 0] - cam.cx) / cam.fx, "y_st": (uv[:, 1] - cam.cy) / cam.fy,
               "z_st": np.ones(len(uv)), "v": uv[:, 1],
               **{f"omega_{a}": np.full(len(uv), w[k]) for k, a in enumerate("xyz")}}
        want = uv - coef * stats.rolling_columns(sub, (cam.fx, cam.fy), (cam.cx, cam.cy),
                                                 cal.R_imu_st)
        assert np.array_equal(np.asarray(g.uv), want)
    assert not np.array_equal(np.asarray(got.frames[1].uv), np.asarray(data.frames[1].uv))


def _measured_noise(data, prior):
    """The stars' noise as the diagnosis measures it (the current model's run, its
    within-frame estimate, the verdict's scales): (verdict, applied scales, StarNoise)."""
    run = evaluate(data, method_spec("psce"), rerun_prior(prior), (), 0.5, star_noise=True)
    v = noise.NoiseVerdict(NoiseScales(), NoiseScales())
    size = (prior.camera.width, prior.camera.height)
    return v, noise.judge_stars(v, run.star_noise, SIGMA, size, 1), run.star_noise


def test_twin_renders_the_correlated_noise_it_measured(ar1_sim):
    """Issue 21.4: a twin renders the stars' noise the run measured.  The 'ar1' bag's
    diagnosis applies star = scatter x √((1+ρ)/(1−ρ)) with ρ (``consistency.noise``
    carries ``star_correlated``); the twin had rendered white noise at that applied scale
    (seed 21: scatter 2.85, ρ 0).  Now each star's noise is the simulator's AR(1)
    (``tracker_errors.Ar1Tracks``) along its track.  A twin at the bag's truth (marginal
    1.0, ρ = e^(-1/5)) re-measured gives the user bag's scatter and ρ within 3 σ of their
    difference (the scale's σ for AR(1) noise: the white one times √((1+ρ²)/(1−ρ²)), a
    sample variance of correlated values; ρ: Bartlett's); a twin at the measured scales
    gives ρ back within 3 σ and is correlated; the white case stays white."""
    data = bag_data_from_simulation(ar1_sim)
    prior = ar1_sim.prior
    v, applied, sn = _measured_noise(data, prior)
    assert v.correlated is not None and applied.star_rho == pytest.approx(sn.track_rho)
    # the scatter within frames is applied when it differs from 1 (else kept as stated: with
    # its σ counted for the correlation, 0.96 +- 0.02 is no longer called 'too large')
    white = v.star if (v.star_p < noise.ALPHA and abs(v.star - 1.0) > noise.MATERIAL) else 1.0
    assert applied.star == pytest.approx(white * applied.star_inflation, rel=1e-9)
    assert NoiseScales.from_dict(applied.as_dict()) == applied  # through the result YAML
    # the twin command's one line: the scatter it renders and the correlation
    line = noise_line(applied)
    assert f"stars' sigma x{white:.3g} of the messages'" in line, line
    assert f"AR(1), lag-1 rho {sn.track_rho:.2f}; a white-noise filter needs " \
           f"x{applied.star:.3g}" in line, line

    def sigmas(v, sn):
        rho = sn.track_rho
        return (v.star_sigma * np.sqrt((1 + rho**2) / (1 - rho**2)),
                np.sqrt((1 - rho**2) / (2 * sn.track_pairs)))

    s_user, r_user = sigmas(v, sn)
    rho = float(np.exp(-0.2))
    truth = NoiseScales(star=np.sqrt((1 + rho) / (1 - rho)), star_rho=rho)
    v_t, _, sn_t = _measured_noise(make_twin(data, prior, {}, 3, "psce", truth).data, prior)
    s_t, r_t = sigmas(v_t, sn_t)
    assert abs(v_t.star - v.star) < 3 * np.hypot(s_user, s_t), (v_t.star, v.star)
    assert abs(sn_t.track_rho - sn.track_rho) < 3 * np.hypot(r_user, r_t)
    v_m, applied_m, sn_m = _measured_noise(
        make_twin(data, prior, {}, 3, "psce", applied).data, prior)
    assert v_m.correlated is not None
    assert abs(sn_m.track_rho - sn.track_rho) < 3 * np.hypot(r_user, sigmas(v_m, sn_m)[1])
    # white: the scale, uncorrelated
    v_w, applied_w, sn_w = _measured_noise(
        make_twin(data, prior, {}, 3, "psce", NoiseScales(star=1.3)).data, prior)
    assert v_w.correlated is None and applied_w.star_rho == 0.0
    assert v_w.star == pytest.approx(1.3, abs=4 * v_w.star_sigma)


def test_correlated_noise_advice_is_a_command_the_replay_accepts(ar1_sim, tmp_path, capsys):
    """Issue 21.3: on the 'ar1' bag ``discover`` names the noise correlated and prints the
    scale to use with its ρ (``--noise-scale star=K,rho=R``); ``replay`` takes that exact
    advice and judges its NIS against the declared correlation: the verdict is consistent,
    NIS/dof x k² (k² = (1+ρ)/(1−ρ)) within 10 % of 1, no MODEL MISMATCH.  Before, the advice
    named only star=K and the replay with it said "MODEL MISMATCH (with the rescaled noise):
    NIS/dof 0.11, whiteness p 9.5e-44" (300 s bag, star=2.96): a white filter with σ x K reads
    NIS/dof 1/k², and the frame means follow each other by ρ; the same run without the rho
    still says so here."""
    import re

    import yaml

    from stellar_cal_ros.cli import main
    from stellar_cal_ros.sim.world import write_simulation

    bag = tmp_path / "ar1.mcap"
    write_simulation(ar1_sim, bag)
    prior = str(tmp_path / "ar1.prior.yaml")
    capsys.readouterr()
    rc = main(["discover", str(bag), "--calibration", prior, "--method", "psce", "-o",
               str(tmp_path / "d"), "--workers", "0", "--no-plots",
               "--candidates", "pixel_aspect"])
    out = capsys.readouterr().out
    assert rc == 0
    advice = re.findall(r"use --noise-scale (star=[0-9.]+,rho=[0-9.]+)", out)
    assert advice, out[-3000:]
    rho = float(advice[-1].split("rho=")[1])
    assert rho == pytest.approx(np.exp(-0.2), abs=0.04)

    def replay_with(scale, *extra):
        capsys.readouterr()
        res = tmp_path / f"rep{len(scale)}.yaml"
        assert main(["replay", str(bag), "--prior", prior, "--method", "psce", "-o",
                     str(res), "--noise-scale", scale, "-q", *extra]) == 0
        return capsys.readouterr().out, yaml.safe_load(res.read_text())["consistency"]

    text, cons = replay_with(advice[-1], "--viz", str(tmp_path / "v.mcap"), "--residuals",
                             str(tmp_path / "r.csv"))
    assert cons["verdict"] == "consistent" and "MODEL MISMATCH" not in text, text
    # the HTML report of the run (``report --residuals``) judges it as the replay does: its
    # NIS/dof x k² in the run's band; before, "smaller than the noise model expects (noise
    # set too high?)" beside the YAML's 'consistent'
    assert main(["report", str(tmp_path / f"rep{len(advice[-1])}.yaml"), "--residuals",
                 str(tmp_path / "r.csv"), "-o", str(tmp_path / "html")]) == 0
    page = (tmp_path / "html" / "report.html").read_text()
    shown = re.search(r"NIS/dof <b>([0-9.]+)</b> \(x([0-9.]+) for the stars' noise declared "
                      r"correlated", page)
    assert shown and "consistent with the noise model" in page, page[:3000]
    assert "smaller than the noise model expects" not in page
    assert float(shown.group(2)) == pytest.approx(cons["correlated"]["inflation"], rel=1e-2)
    assert float(shown.group(1)) == pytest.approx(cons["nis_per_dof"], rel=0.02)
    # the view (replay --viz) judges the run as the replay does, under the declared ρ
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(tmp_path / "v.mcap", "rb") as fh:
        views = [m for _s, c, _m, m in make_reader(
            fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
            topics=["/calibrator/view"])]
    assert views[-1].verdict == "consistent"
    assert "NOISE OVERSTATED" not in text
    assert cons["nis_per_dof"] == pytest.approx(1.0, abs=0.1), cons
    assert cons["nis_per_dof"] == pytest.approx(
        cons["correlated"]["nis_per_dof_raw"] * (1 + rho) / (1 - rho), rel=1e-9)
    # the same scale without its ρ: judged as white noise, it is the contradiction it was
    text, cons = replay_with(advice[-1].split(",")[0])
    assert cons["verdict"] == "model mismatch" and "MODEL MISMATCH" in text


def test_a_wandering_gyro_bias_adds_no_library_effect(tmp_path):
    """Gyro bias instability (a random walk of 1 deg/h/√h per axis, the model's bias a
    constant; outside the library), ``discover``: the stars see more attitude motion than
    the gyro's own samples show, the noise's search measures the walk (truth within 3 σ;
    it beats the best library candidate's run, H151) and runs the round with it, and no
    library effect is added for it.  Before H151 the noise line only named a wandering
    gyro bias among the causes ('beyond').  Before, the screening's score test,
    whose information is that of white innovations, was trusted on innovations that drift
    together: seed 22 added gyro_scale_factor (gyro_misalignment 'significant alone', p
    2.8e-8) with both re-runs gaining nothing; the 300 s unseen case ``bias_walk`` (0.3
    deg/h/√h) added gyro_misalignment at score p 1.5e-14, its re-run +4 of log-likelihood
    for 6 parameters.  Now no score test is local there: every candidate is re-run and
    decided by the prequential ratio.  Reduced (~20 CPU-s): 150 s, the two candidates."""
    from stellar_cal_ros.diagnosis.run import diagnose

    sim = _bag(lambda s: tracker_errors.gyro_bias_walk(s, 1.0, 22), seed=22, noise_free=False)
    summary = diagnose(bag_data_from_simulation(sim), sim.prior, "psce", [], tmp_path / "rep",
                       auto=True, candidates=["gyro_misalignment", "gyro_scale_factor"],
                       plots=False, verbose=False, workers=0)
    walk = summary["noise"]["gyro_bias_rw"]
    assert walk["accepted"], walk
    # measured (seed 22): 1.16 +- 0.32, p 4e-23; penalised likelihood +101 against the best
    # candidate's -99 (gyro_misalignment, 6 parameters)
    assert abs(walk["deg_h_sqrth"] - 1.0) < 3 * walk["sigma"], walk
    assert walk["rival"]["walk_qaic_gain"] > walk["rival"]["qaic_gain"], walk
    assert summary["noise"]["verdict"][0].startswith("the gyro bias wanders: a random walk")
    assert "gyro_bias_rw=" in summary["noise"]["verdict"][0]
    assert summary["added"] == [], summary["path"]



def test_an_effect_exchanged_in_is_checked_next_round(tmp_path):
    """Unseen case ``bias_walk`` (0.3 deg/h/√h) at seed 27: round 1 refuses the walk (its z
    bias estimate follows the rate, p 0.0029) and adds gyro_misalignment (p 3.7e-13);
    round 2 takes the walk and exchanges gyro_misalignment for gyro_scale_factor (the
    prequential likelihood compares the two, not gyro_scale_factor with nothing).  An
    effect exchanged in is checked in the next round as any added before: with the walk
    its estimates are 0 within 1.6σ (7 ± 5, −0.2 ± 2, −11 ± 7 ppm) and it is dropped.
    Fails on 8e3e396 (gyro_scale_factor added, never checked)."""
    from stellar_cal_ros.diagnosis.auto import discover

    sim = _bag(lambda s: tracker_errors.gyro_bias_walk(s, 0.3, 27), seed=27, noise_free=False,
               duration=300.0)
    got = discover(bag_data_from_simulation(sim), sim.prior, "psce", [], tmp_path,
                   candidates=["gyro_misalignment", "gyro_scale_factor"], plots=False,
                   verbose=False, workers=0)
    actions = [s["action"] for s in got["path"]]
    assert "exchange" in actions, actions
    assert got["added"] == [], got["path"]
    assert got["noise"]["gyro_bias_rw"]["accepted"], got["noise"]["gyro_bias_rw"]

def _step_noise(factor):
    """The stated 0.05 px right for the first half of the frames, ``factor`` x in the rest."""
    def post(sim):
        frames = sim.star_frames
        h = len(frames) // 2
        tracker_errors.renoise(SimpleNamespace(star_frames=frames[:h]), lambda m, uv: SIGMA,
                               SIGMA, 21)
        tracker_errors.renoise(SimpleNamespace(star_frames=frames[h:]),
                               lambda m, uv: factor * SIGMA, SIGMA, 22)
    return post


def test_noise_that_changes_mid_run_is_said_with_both_scales():
    """The stars' σ as stated for the first half of the run, 2x in the second (the
    evaluation window): the verdict applies the window's x2 (within 3 σ) and says that the
    σ changes over the run, with the scale before the window (x1 within 3 σ).  Before, only
    "looks 2.02 x too small: use star=2.02" (unseen case ``step2x``, 300 s), nothing of the
    first half.  A noise as stated throughout says nothing of a change (its two scales
    agree: 1.013 and 1.009 on the 300 s bags of the unseen cases whose noise is stated
    right)."""
    sim = _bag(_step_noise(2.0))
    v, applied, sn = _measured_noise(bag_data_from_simulation(sim), sim.prior)
    c = v.changes
    assert c is not None, (v.star, sn.before)
    assert abs(c["window"] - 2.0) < 3 * c["sigma_window"], c
    assert abs(c["before"] - 1.0) < 3 * c["sigma_before"], c
    assert applied.star == pytest.approx(c["window"]) and "star" in v.rejected
    line = [x for x in v.lines() if "changes over the run" in x]
    assert line and f"x{c['before']:.3g}" in line[0] and f"x{c['window']:.3g}" in line[0]
    assert v.as_json()["star_changes"] == c
    sim = _bag(_step_noise(1.0))
    v1, applied1, _ = _measured_noise(bag_data_from_simulation(sim), sim.prior)
    assert v1.changes is None and applied1.identity, v1.lines()


def _bright_noisier(factor):
    """Unseen case ``mag_inverted_bright``: true σ 0.05·2^(−(m − 4)/2) px, the messages'
    σ 0.05·2^((m − 4)/2); ``factor`` x the true σ in the second half of the frames."""
    def post(sim):
        frames = sim.star_frames
        h = len(frames) // 2
        for part, k, seed in ((frames[:h], 1.0, 21), (frames[h:], factor, 22)):
            tracker_errors.renoise(
                SimpleNamespace(star_frames=part),
                lambda m, uv, k=k: k * SIGMA * 2.0 ** (-(np.nan_to_num(m, nan=4.0) - 4.0) / 2),
                SIGMA, seed)
        for f in frames:
            m = np.nan_to_num(np.asarray(f.magnitude, dtype=float), nan=4.0)
            f.sigma = SIGMA * 2.0 ** ((m - 4.0) / 2.0)
    return post


def test_a_noise_grouped_by_magnitude_does_not_change_over_the_run_with_the_sky():
    """The bright stars noisier than their messages say, the faint ones quieter (σ ratio
    2^−(m − 4): x4 at mag 2, x0.25 at 6), steady over the run: grouped by magnitude, and
    no "the stars' sigma changes over the run".  The one pooled scale mixes the groups in
    the stars' shares, which change with the sky (unseen case ``mag_inverted_bright``
    s21/s22, 300 s: x0.502 at 75-150 s, x0.691 in the window; the mixes' truth 0.489 and
    0.693): judged at each star's group's σ, both stretches read 1.  Fails on main 6c738a9
    (the change said; 150 s seed 21: x0.762 +- 0.021 before, x0.495 +- 0.0079 in the
    window).  The groups are steps of a smooth ratio, so the mix within a group still
    moves the stretch before a little (x1.126 +- 0.018 of the groups' σ, below the
    material change).  A noise that does double in the second half (the window) beside
    the same groups is said, of the magnitude groups' σ: x1 in the window and half the
    steady bag's stretch before (the same draws: 0.563 = 0.5 x 1.126)."""
    sim = _bag(_bright_noisier(1.0))
    v, _, sn = _measured_noise(bag_data_from_simulation(sim), sim.prior)
    assert v.group is not None and v.group["by"] == "magnitude", v.lines()
    assert v.changes is None, (v.changes, sn.before)
    assert not [x for x in v.lines() if "changes over the run" in x]
    steady, steady_sigma = noise._at_groups(sn.early, v.group)
    sim = _bag(_bright_noisier(2.0))
    v, _, _ = _measured_noise(bag_data_from_simulation(sim), sim.prior)
    c = v.changes
    assert v.group is not None and v.group["by"] == "magnitude", v.lines()
    assert c is not None and c["by"] == "magnitude", v.lines()
    assert abs(c["before"] - 0.5 * steady) < 3 * math.hypot(c["sigma_before"],
                                                            0.5 * steady_sigma), (c, steady)
    assert abs(c["window"] - 1.0) < 3 * c["sigma_window"], c
    line = [x for x in v.lines() if "changes over the run" in x]
    assert line and f"x{c['before']:.3g} +- {c['sigma_before']:.2g} of the magnitude " \
        "groups' sigma" in line[0], line

def test_error_repeating_star_by_star_prints_a_true_lower_bound():
    """Each star off by its own fixed offset (``tracker_errors.star_offsets``, 0.03 px rms
    per axis: a catalogue position error) in a 150 s psce bag of 0.05 px noise: the verdict
    says the residuals repeat star by star, "a per-star position error of at least X px
    rms per axis" with X below the offsets' true rms (the detector cells' means take part
    of it; seeds 21-23: X 0.0147, 0.0093, 0.0113 px for 0.029-0.030), and the stars' scale
    measured without it is as stated within 3 σ (seed 21: 1.0062 +- 0.011)."""
    box = {}
    sim = _bag(lambda s: box.update(off=tracker_errors.star_offsets(s, 0.03, 21)),
               noise_free=False)
    v, _, sn = _measured_noise(bag_data_from_simulation(sim), sim.prior)
    assert v.repeat is not None and v.repeat["p_value"] < 1e-6, v.lines()
    seen = {int(c) for f in sim.star_frames for c in np.asarray(f.catalog_id).tolist()}
    truth = float(np.sqrt(np.mean([box["off"][c] ** 2 for c in seen])))
    x = v.repeat["rms_px"]
    assert 0.25 * truth < x < truth, (x, truth)
    line = [t for t in v.lines() if "repeat star by star" in t]
    assert line and f"at least {x:.2g} px" in line[0]
    assert abs(v.star - 1.0) < 3 * v.star_sigma, (v.star, v.star_sigma)


def test_repeating_field_prints_its_rms_over_the_noise():
    """A field fixed on the detector (a 6 x 6 checkerboard of +-0.006 px in u, -+ in v:
    0.12 of the 0.05 px noise per axis, no rotation nor translation of the frame) in a
    150 s psce bag: the verdict says the stars show a repeating field, "X x the noise rms",
    with X the truth within 3 of its σ (from the χ²'s, sqrt(2 dof + 4 excess)).  X was the
    whole χ² over the rows' dof, noise included: 0.19 (3.9 σ high), now 0.144."""
    a = 0.006

    def checkerboard(sim):
        w, h = sim.prior.camera.width, sim.prior.camera.height
        for f in sim.star_frames:
            uv = np.asarray(f.uv, dtype=float)
            sgn = np.where((np.floor(6 * uv[:, 0] / w) + np.floor(6 * uv[:, 1] / h)) % 2,
                           -1.0, 1.0)
            f.uv = uv + a * np.stack([sgn, -sgn], 1)

    sim = _bag(checkerboard, noise_free=False)
    _, _, sn = _measured_noise(bag_data_from_simulation(sim), sim.prior)
    line = noise.structured(sn)
    assert "repeating field" in line and sn.structure_p < 1e-6, line
    x = float(line.split(" x the noise rms")[0].rsplit(", ", 1)[1])
    excess = sn.structure - sn.structure_dof
    sd = np.sqrt(2 * sn.structure_dof + 4 * excess) / (2 * np.sqrt(excess * sn.m.sum()))
    assert abs(x - a / SIGMA) < 3 * sd, (x, a / SIGMA, sd)


def test_heavy_tailed_noise_is_named_and_gaussian_noise_is_not():
    """Student-t centroid noise (3 dof) at the stated 0.05 px RMS: the verdict names the
    heavy tails (the share of stars beyond the Gaussian 99.9 % bound > 8 x its 0.1 %) and
    the gated core's σ (the 300 s unseen case ``t3``: x0.842, 1.4 % beyond); before, only
    "sigma 1.19 x too large" beside "218 stars gated: misidentified stars".  The printed
    share is the one Student-t noise has at the measured core scale.  Gaussian noise and 3 %
    of 10-sigma outliers (gated, the rest Gaussian) say nothing of tails."""
    v, _, sn = _measured_noise(*_sim_prior(lambda s: tracker_errors.heavy_tails(
        s, SIGMA, 3.0, 21)))
    t = v.tails
    assert t is not None and t["share"] > noise.TAILS * t["expected"] and t["p_value"] < 1e-6
    assert any("heavy-tailed" in x for x in v.lines())
    # the printed share is Student-t's own at the core's scale: each axis t_3 σ/√3, the
    # stars the filter's gate accepts (χ²₂ at its probability, of the stated σ), beyond
    # the bound at the measured scale; within 3 σ of the share's binomial σ and the
    # scale's (seed 21: 1.59 % printed, 1.70 % expected, σ 0.27 %; seeds 22-24: 1.76 /
    # 1.68, 1.24 / 1.91, 1.59 / 1.29 %)
    x = (np.random.default_rng(0).standard_t(3.0, (1_000_000, 2)) ** 2).sum(1) / 3.0
    x = x[x < chi2_2_quantile(PsceConfig().gate_probability)]

    def share(scale):
        return float(np.mean(x > noise.TAIL_BOUND * scale**2))

    n, expected = int(np.sum(sn.m[~sn.unknown] > 0)), share(v.star)
    d_scale = 0.5 * (share(v.star - v.star_sigma) - share(v.star + v.star_sigma))
    assert abs(t["share"] - expected) < 3.0 * np.hypot(
        np.sqrt(expected * (1.0 - expected) / n), d_scale), (t, expected, n, d_scale)
    assert v.as_json()["star_tails"] == t
    for post in (lambda s: None, lambda s: tracker_errors.outliers(s, 0.03, 10.0, 21)):
        v0, _, _ = _measured_noise(*_sim_prior(post, noise_free=False))
        assert v0.tails is None, v0.lines()


def test_heavy_tails_beside_a_per_star_verdict_are_judged_against_its_mixture():
    """Unseen case ``sway_t4`` at seed 23 (Student-t of 4 dof at the stated 0.058 px RMS on
    the swaying base): a per-star verdict of chance (F 1.39, p 0.0045, the stars' variance
    spread 0.15; clean swaying seed 2047 reads the same F with Gaussian noise) had the tails
    judged at each star's own scale, which takes a star's wide residuals in: no tail line
    on main 8ee8e1e (0.92 % beyond at the one scale).  Now they are judged at the one scale
    against the share a mixture of that spread has beyond the bound (0.14 %), by the
    margin :data:`~.noise.TAILS` asks beyond Gaussian noise's: named.  A σ wrong by 30 %
    star by star (``sigma_per_star``, 0.82 % beyond at the one scale) has a mixture share of
    0.73 %: not named (test_noise).  Since H195 the per-star F's dof allow for the rows'
    kurtosis: that verdict of chance is gone on this bag, and the tails are judged against
    Gaussian noise's 0.1 % (0.92 %, p 1e-19)."""
    from stellar_cal_ros.diagnosis.injection import SWAY_CLEAN
    from stellar_cal_ros.diagnosis.run import measure_bag

    assert noise.mixture_share(0.0) == pytest.approx(1e-3, rel=1e-9)
    assert noise.mixture_share(0.15) == pytest.approx(1.39e-3, abs=1e-5)
    assert noise.mixture_share(0.6) == pytest.approx(7.30e-3, abs=5e-5)
    sc = dataclasses.replace(get_scenario("swaying"), centroid_noise_px=0.0)
    sim = simulate(sc, duration=200.0, seed=23, effects=dict(SWAY_CLEAN))
    tracker_errors.heavy_tails(sim, 0.058, 4.0, 23)
    v = measure_bag(bag_data_from_simulation(sim), sim.prior, "swaying_base", [],
                    NoiseScales(), components=())
    assert v.per_star is None, v.lines()
    t = v.tails
    assert t is not None, v.lines()
    assert t["expected"] == pytest.approx(noise.mixture_share(0.0))
    assert t["share"] > t["expected"] + (noise.TAILS - 1.0) * 1e-3 and t["p_value"] < 1e-6
    assert any("heavy-tailed" in x for x in v.lines()), v.lines()


def test_gated_stars_are_the_tails_or_misidentified_never_both(tmp_path):
    """One claim about one piece of evidence: Student-t noise (3 dof, unseen case ``t3``)
    gates ~2 % of the stars; the diagnosis names the noise heavy-tailed, and its data
    quality must not also call the gated stars "misidentified stars" (before: "121 stars
    gated (1.9 % of 6255 ...): misidentified stars. ... repair the data" beside "stars the
    gate rejects are likely its tails, not misidentified stars").  Gaussian noise with 3 %
    of 10-sigma outliers (misidentifications) is the data's fault: said so, no tails."""
    from stellar_cal_ros.diagnosis.run import diagnose
    from stellar_cal_ros.methods.results import GATED_FACTOR

    cases = {"t3": _bag(lambda s: tracker_errors.heavy_tails(s, SIGMA, 3.0, 21)),
             "outliers": _bag(lambda s: tracker_errors.outliers(s, 0.03, 10.0, 21),
                              noise_free=False)}
    for name, sim in cases.items():
        s = diagnose(bag_data_from_simulation(sim), sim.prior, "psce", [], tmp_path / name,
                     candidates=["pixel_aspect"], plots=False, verbose=False, workers=0)
        gated = s["counts"]["stars_gated"]
        assert gated > GATED_FACTOR * 1e-4 * 6000, s["counts"]  # far beyond the gate's 0.01 %
        tails = any("heavy-tailed" in x for x in s["noise"]["verdict"])
        misid = [x for x in s["data_quality"] if "misidentified" in x]
        assert tails == (name == "t3"), s["noise"]["verdict"]
        assert bool(misid) == (name == "outliers"), s["data_quality"]
        said = [x for x in s["terminal"] if "misidentified" in x]
        # the terminal says 'misidentified' once, as the data's fault or as what they are not
        assert len(said) == 1 and ("not misidentified" in said[0]) == (name == "t3"), said


def _sim_prior(post, **kw):
    sim = _bag(post, **kw)
    return bag_data_from_simulation(sim), sim.prior


# ---- fourth pass (H100): cases built after the diagnosis, reduced


def _radial_magnitude_bias(px_per_mag):
    """``tracker_errors.radial_by_mag`` then the stated noise; returns (post, the
    stars' magnitudes per frame)."""
    mags = []

    def post(sim):
        tracker_errors.radial_by_mag(sim, px_per_mag)
        mags.extend(np.nan_to_num(np.asarray(f.magnitude, dtype=float), nan=4.0)
                    for f in sim.star_frames)
        tracker_errors.renoise(sim, lambda m, uv: SIGMA, SIGMA, 21)
    return post, mags


def test_radial_bias_with_magnitude_is_unexplained_by_magnitude_with_its_size():
    """Unseen case ``magbias_radial`` (fourth pass): stars pushed away from the principal
    point by 0.03 px per magnitude fainter than 4, the same at every radius.  No library
    effect is named (``discover`` adds nothing on 300 s, seed 21); the first 'unexplained'
    line is the radial residual vs magnitude.  Its size reads short of the true bias's
    straight-line change over the magnitudes' 5-95 % range (150 s seed 21: 0.0390 for
    0.0527 px, 0.74x; the run's calibration takes part of it and the bias is a hinge at
    mag 4, not a line): asserted within 0.5-1.2x of it."""
    k = 0.03
    post, mags = _radial_magnitude_bias(k)
    found = _findings(_bag(post))
    assert found and found[0].regressor == "magnitude" and found[0].component == "radial", \
        found[:3]
    assert found[0].p_value < 1e-6
    m = np.concatenate(mags[len(mags) // 2:])
    lo, hi = np.percentile(m, [5.0, 95.0])
    slope = np.polyfit(m, k * np.maximum(m - 4.0, 0.0), 1)[0]
    assert 0.5 < abs(found[0].slope_px) / (slope * (hi - lo)) < 1.2


def test_noise_twice_the_stated_before_the_window_only_is_said_and_not_applied():
    """Unseen case ``step2x_first``: the stars' σ 2x the stated in the first half of the
    run, as stated in the second (the evaluation window).  The change over the run is said
    with both scales (x2 before the window, x1 in it, each within 3 σ), and nothing is
    applied: the window is as stated (``step2x``, its mirror, applies the window's x2)."""
    def post(sim):
        frames = sim.star_frames
        h = len(frames) // 2
        tracker_errors.renoise(SimpleNamespace(star_frames=frames[:h]),
                               lambda m, uv: 2.0 * SIGMA, SIGMA, 21)
        tracker_errors.renoise(SimpleNamespace(star_frames=frames[h:]), lambda m, uv: SIGMA,
                               SIGMA, 22)

    sim = _bag(post)
    v, applied, sn = _measured_noise(bag_data_from_simulation(sim), sim.prior)
    c = v.changes
    assert c is not None, (v.star, sn.before)
    assert abs(c["before"] - 2.0) < 3 * c["sigma_before"], c
    assert abs(c["window"] - 1.0) < 3 * c["sigma_window"], c
    assert applied.identity and "star" in v.rejected
    line = [x for x in v.lines() if "changes over the run" in x]
    assert line and "the window's is not told from the stated, which is kept" in line[0]


def test_one_noisy_accelerometer_axis_on_a_swaying_base_is_measured_per_axis():
    """Unseen case ``sway_accel_z4``: the accelerometer's z axis 4x its stated white noise,
    x, y and the gyro as stated, on the swaying base: the accelerometer's samples read the
    axes' RMS (√6 = 2.45) with each axis within 5 % (300 s discover:
    'accel ... looks 2.49 +- 0.013 x larger than stated ... per axis x0.999, x0.989,
    x4.07', nothing added)."""
    from stellar_cal_ros.diagnosis.injection import SWAY_CLEAN
    from stellar_cal_ros.diagnosis.noise_imu import imu_sample_scale

    sim = simulate(get_scenario("swaying"), duration=DURATION, seed=21,
                   effects=dict(SWAY_CLEAN))
    tracker_errors.imu_noise_axis(sim, "accel", 2, 4.0, 21)
    data = bag_data_from_simulation(sim)
    s, e, white, axes = imu_sample_scale(data, "swaying_base", "accel", NoiseScales())
    assert white and s == pytest.approx(np.sqrt(6.0), abs=max(3 * e, 0.05))
    assert np.allclose(axes, [1.0, 1.0, 4.0], rtol=0.05)


def test_star_noise_understated_and_gyro_noise_overstated_are_both_measured():
    """Unseen case ``s06_gyro_over3``: the stars' σ field 0.6x the truth and the gyro's
    stated ARW 3x its truth (wrong in opposite directions): the stars' scale reads 1/0.6
    and the gyro's samples 1/3, each within 3 σ (300 s discover: gyro x0.333 +- 0.0014,
    stars x1.68 +- 0.013, both said with the value to use, nothing added)."""
    from stellar_cal_ros.diagnosis.noise_imu import imu_sample_scale

    sc = get_scenario("psce_rotations")
    sim = simulate(dataclasses.replace(sc, gyro_arw_deg_sqrth=sc.gyro_arw_deg_sqrth / 3.0),
                   duration=DURATION, seed=21)
    for f in sim.star_frames:
        f.sigma = np.asarray(f.sigma, dtype=float) * 0.6
    data = bag_data_from_simulation(sim)
    v, applied, _ = _measured_noise(data, sim.prior)
    assert abs(v.star - 1.0 / 0.6) < 3 * v.star_sigma and applied.star == pytest.approx(v.star)
    g, eg, white, _ = imu_sample_scale(data, "psce", "gyro", NoiseScales())
    assert white and abs(g - 1.0 / 3.0) < 3 * eg, (g, eg)


def _top_beside_leads(post, candidates, seed=21, duration=DURATION):
    """``discover``'s choice of the candidate to add (``auto._top``) on a PSCE bag (150 s)
    that ``post`` changes (then the stated 0.05 px noise): the baseline run and each
    candidate's, the leads (``leads.of_run``) of the baseline."""
    from stellar_cal_ros.diagnosis import leads

    sim = _bag(post, seed=seed, duration=duration)
    tracker_errors.renoise(sim, lambda m, uv: SIGMA, SIGMA, seed)
    top, refused, results, base, _ = _top_of(sim, "psce", candidates)
    return top, refused, results, leads.of_run(base, 0.5)


def _top_of(sim, method, candidates):
    """``auto._top`` on ``sim``'s bag with ``method`` from the baseline: ``(top, refused,
    results, the baseline's run, the discovery's state)``."""
    from stellar_cal_ros.diagnosis import auto
    from stellar_cal_ros.diagnosis.discover import Reference, candidate_prior

    data, spec, prior = bag_data_from_simulation(sim), method_spec(method), \
        rerun_prior(sim.prior)
    base = evaluate(data, spec, prior, (), 0.5, keep_residuals=True)
    results = []
    for effect in candidates:
        run = evaluate(data, spec, candidate_prior(prior, effect, prior), (effect,), 0.5,
                       keep_residuals=True, candidate=True)
        dof = len(run.theta) - len(base.theta)
        lam, p, _ = Reference.of(base).compare(run, dof)
        results.append(SimpleNamespace(effect=effect, statistic=lam, dof=dof,
                                       significant_alone=p < 0.01 / len(candidates),
                                       p_adjusted=p, run=run))
    runs = SimpleNamespace(spec=spec, fraction=0.5, noise=None, classes=(),
                           on_bag=lambda fn, *a: fn(data, *a),
                           later=lambda fn, *a: lambda: fn(data, *a),
                           run_all=lambda tasks, done=None: {
                               t.key: evaluate(data, spec, t.prior, t.effects, 0.5,
                                               keep_residuals=True, candidate=t.candidate)
                               for t in tasks})
    state = auto._State([], (), prior)
    top, refused = auto._top(runs, state, base, None, prior, prior, results, lambda s: None)
    return top, refused, results, base, state


@pytest.mark.parametrize("seed, duration", [(21, DURATION), (22, 300.0)])
def test_a_step_on_one_detector_quadrant_gets_no_library_name(seed, duration):
    """Unseen case ``quadrant`` (stars of the upper-left quadrant moved 0.05 px along u and
    v; no library effect makes a step): image_plane_tilt is significant alone (150 s seed
    21: Λ 80 for 2 dof, p 4e-18; 300 s seed 22: Λ 222, the unseen case's own bag, whose
    discover added it at −12.6, 11.4 mrad), but the detector's per-cell offset field is a
    lead (t 16-27, 0.025-0.03 px) and the tilt explains nothing beyond it: ``discover``
    does not add it.  The field beside both models is fitted on the window itself, per
    quarter of its time (``leads.window_gain``): with the lead's direction fitted before
    the window, whose 72 coefficients carry their own noise, the 300 s seed-22 tilt read
    26.5 beyond it (p 1.7e-6) and was added on main 319db59."""
    top, refused, results, found = _top_beside_leads(
        lambda sim: tracker_errors.quadrant_step(sim, 0.05), ("image_plane_tilt",), seed,
        duration)
    assert results[0].significant_alone, results[0]
    cells = found["cells"]
    assert cells["p_value"] < 1e-6 and 0.01 < cells["size_px"] < 0.05, cells
    assert top is None, top.effect
    (c, b), = refused
    assert c.effect == "image_plane_tilt" and not b["needed"] and b["lead"] == "cells", b


def test_the_lines_a_detector_step_echoes_follow_the_cells_field():
    """Unseen case ``quadrant`` (0.05 px on the upper-left quadrant), its own 300 s seed-22
    bag: the cells field's line (a candidate refused beside it) leads at t 27, and the
    step's echoes on the detector's positions were ranked after it as leads of their own
    (main 17d7d23's second line: ``u residual vs v (row) (periodic 1024 px, sin)`` t 16.9,
    the step's fundamental over the rows; then ``v residual vs u (column)`` t −14.0).  With
    the field's fit taken out of the residuals the line tests no longer find them: they
    follow the field (``leads.fields_first``), after the lines it does not explain.  The
    magnitude line of a saturation is not the field's (next test's bag, ``on_the_detector``).
    """
    from stellar_cal_ros.diagnosis import leads

    def post(sim):
        tracker_errors.quadrant_step(sim, 0.05)
        tracker_errors.renoise(sim, lambda m, uv: SIGMA, SIGMA, 22)

    run, runs = _psce_run(_bag(post, seed=22, duration=300.0))
    plain = line_tests(run.residuals, run.calibration, 0.5)
    cells = leads.findings(run, 0.5, ("cells",), 0.01)
    assert len(cells) == 1 and cells[0].statistic > 20, cells
    found = sorted(cells + plain, key=lambda f: (f.p_value, -abs(f.statistic)))
    lines, follows = output.causes_first(found, run, runs, frozenset(map(id, cells)))
    echoes = {(f.regressor, f.component): f for f in plain if f.p_value < 1e-10}
    assert {("v (row) (periodic 1024 px, sin)", "u"), ("u (column)", "v")} <= set(echoes), \
        list(echoes)
    assert lines[0] is cells[0]
    assert all(lines.index(f) in follows for f in echoes.values()), (
        [(f.regressor, f.component) for f in lines], follows)
    # the lines that stay lead before them, and none of them is the step's
    stays = [f for i, f in enumerate(lines[1:], 1) if i not in follows]
    assert lines[1:len(stays) + 1] == stays and not any(f.p_value < 1e-10 for f in stays)
    # a saturation's magnitude line is gone without a cells field too (few stars a cell),
    # but it is not on the detector's positions: it never follows the field
    mag = stats.RegressorFinding("magnitude", "radial", 7.1, 2.4e-7, 0.0187)
    assert not leads.on_the_detector(mag) and leads.on_the_detector(echoes[
        ("v (row) (periodic 1024 px, sin)", "u")])


def test_a_saturations_hinge_is_the_magnitude_fields_not_the_cells(tmp_path):
    """Unseen case ``saturation`` (stars brighter than magnitude 4 pulled toward the
    detector's centre, 0.04 px a magnitude; 0 for the fainter 90 %: a hinge), its own 300 s
    seed-22 bag through ``discover --auto`` (image_plane_tilt the candidate).  The magnitude
    field was a straight line in magnitude (3 columns): what it missed of the hinge is per
    star, and the cells field (81 stars on 36 cells) took that up as well: coord 6fcb798
    read cells t 8.71, magnitude t 8.41, each t 5.3 beyond the other, and image_plane_tilt,
    refused beside both, recorded the cells field alone (``lead``): the cells line was
    printed first, the magnitude field's never (judged wrong).  The field is now piecewise
    linear in magnitude (knots at the stars' quartiles, ``leads.columns``: 4 functions x u,
    v, radius = 12 columns; ``columns`` counts them over the window's 4 parts) and the
    refusal records every field it stands in for (``leads``).  Fails on coord 6fcb798."""
    from stellar_cal_ros.diagnosis.auto import discover

    sim = _bag(lambda s: tracker_errors.saturation_pull(s, 0.04), seed=22, duration=300.0)
    tracker_errors.renoise(sim, lambda m, uv: SIGMA, SIGMA, 22)
    got = discover(bag_data_from_simulation(sim), sim.prior, "psce", [], tmp_path,
                   candidates=["image_plane_tilt"], plots=False, verbose=False, workers=0)
    assert got["added"] == [], got["path"]
    b = got["path"][-1]["beyond_remainder"]["image_plane_tilt"]
    assert not b["needed"] and b["lead"] == "cells", b
    assert b["leads"] == ["cells", "magnitude"], b
    first, second = got["unexplained"][:2]
    assert first["detail"]["field"] == "magnitude" and second["detail"]["field"] == "cells"
    assert first["detail"]["columns"] == 4 * 12, first["detail"]
    # measured t 13.5 against the cells' 8.71 (the straight line: 8.41)
    assert first["statistic"] > 11.0 and first["statistic"] > second["statistic"] + 3.0
    # its size: the pull's 99th percentile over the window's stars is 0.058 px (magnitude
    # 2.55); the filter's camera states take part of it (measured 0.0405 px, the line 0.0246)
    assert 0.032 < first["change_px"] < 0.058, first



def test_a_weaker_field_and_the_lines_a_stronger_field_explains_follow_it():
    """Unseen case ``saturation`` (bright stars pulled toward the centre), its own 300 s
    seed-22 bag, the baseline run: the magnitude field's line leads (t 13.5), the cells
    field's (t 8.7) is printed second although beside the magnitude field it is gone (t
    2.41: its per-cell offsets took the pull's per-star part), and so is the 'radial residual
    vs magnitude' line (t 7.2) and 'radial residual vs gravity_x_st' (t 4.8: the stars in
    view change with the attitude).  Each now follows the magnitude field
    (``leads.fields_first``, the one rule of every printed field; the cells field's echoes on
    the detector's positions are its special case, previous test).  Fails on main 423125a
    (only the cells field's echoes could follow: nothing moved)."""
    from stellar_cal_ros.diagnosis import leads, printing

    sim = _bag(lambda s: tracker_errors.saturation_pull(s, 0.04), seed=22, duration=300.0)
    tracker_errors.renoise(sim, lambda m, uv: SIGMA, SIGMA, 22)
    run, runs = _psce_run(sim)
    plain = line_tests(run.residuals, run.calibration, 0.5)
    fields = leads.findings(run, 0.5, ("cells", "magnitude"), 0.01)
    found = sorted(fields + plain, key=lambda f: (f.p_value, -abs(f.statistic)))
    kinds = [(f.detail or {}).get("field") for f in found]
    assert kinds[:2] == ["magnitude", "cells"], [(f.regressor, f.statistic) for f in found]
    # measured: 13.5 and 8.71; beside the magnitude field the cells field keeps t 2.41
    assert found[0].statistic > 11.0 and 7.0 < found[1].statistic < found[0].statistic - 3.0
    beside = leads.field_fit(leads.without(run.residuals, 0.5, "magnitude"), 0.5, "cells")
    assert abs(beside["t"]) < 3.5 and not leads.significant({"cells": beside}, 0.01), beside
    lines, follows = output.causes_first(found, run, runs, frozenset(map(id, fields)))
    cells = next(f for f in fields if f.detail["field"] == "cells")
    magnitude = next(f for f in fields if f.detail["field"] == "magnitude")
    assert lines[0] is magnitude and 0 not in follows
    assert follows[lines.index(cells)] == "magnitude field", follows
    radial = next(f for f in plain if (f.regressor, f.component) == ("magnitude", "radial"))
    assert follows.get(lines.index(radial)) == "magnitude field", follows
    # every line that follows comes after every line that stays
    assert sorted(follows) == list(range(len(lines) - len(follows), len(lines)))
    said = printing.follows_phrase({"follows": follows[lines.index(cells)]})
    assert said == ("follows the magnitude field: gone once the field's fit is taken out of "
                    "the centroids"), said

def test_a_mount_flexing_on_a_swaying_base_gets_no_library_name():
    """Unseen case ``sway_flex`` (a mount turned 10″ per unit lateral specific force on the
    swaying base), reduced to 120 s: gyro_scale_factor is significant alone (the sway turns
    gravity as it turns the IMU), but the gravity field (the flexure probe's response,
    ``leads.gravity_of``) is a lead of the baseline and the scale factor explains nothing
    beyond it: ``discover`` does not add it, and the field reads the flexure.  On main
    ea90b97 gyro_scale_factor was added (the 200 s case: −46, −43 ppm, nothing
    unexplained): no gravity lead before an add, and the simulator turned the mount with
    gravity alone, not the sway's acceleration the accelerometer (and the probe) sees."""
    from stellar_cal_ros.diagnosis.injection import SWAY_CLEAN

    sim = simulate(get_scenario("swaying"), duration=120.0, seed=21,
                   effects={**SWAY_CLEAN, "mount_flexure": 10.0})
    top, refused, results, _, state = _top_of(sim, "swaying_base", ("gyro_scale_factor",))
    assert results[0].significant_alone, results[0]
    assert top is None, top.effect
    g = state.lead["gravity"]
    assert g["p_value"] < 1e-6, g
    # the printed size against the truth, within 3 of the sigma it prints (measured 9.47
    # +- 0.66).  Over seeds (benchmarks/flexure_read.py, doc/benchmarks.md "The flexure's
    # printed size" and "The flexure's printed sigma"): the response is exact (next test)
    # and the clean bags' own fit, 189 seeds at 200 s, has SD 0.55 against the printed
    # (frame-robust) sigma 0.55, the whitened 0.53 printed until 2026-11-28
    assert abs(g["arcsec_per_g"] - 10.0) < 3 * g["sigma_arcsec_per_g"], g
    (c, b), = refused
    assert c.effect == "gyro_scale_factor" and not b["needed"] and b["lead"] == "gravity", b


def test_the_flexure_probe_reads_a_swaying_mounts_true_response():
    """The flexure the gravity field prints is ``c = Σ Sᵀ C⁻¹ ν / Σ Sᵀ C⁻¹ S`` (the
    innovations ``ν`` on the probe's response ``S``): the truth when the response of the
    real flexure is ``c S``.  Paired bags (the same seed's noise, ``clean_simulation``), 120 s
    of sway with and without a 10″/g mount: the innovations' difference is the flexure's own
    response, noise-free, and its fit on ``S`` must be 10.  Measured 10.01 (the probe's load
    over ``context.LOAD_WINDOW_S``, 0.1 s); with the 1 s mean of the gravity regressors it
    was 10.33 (the sway's acceleration attenuated; the test fails there), the systematic
    part of the case's reading; the rest of seeds 21/22's 8.8/9.06″/g at 200 s is their
    noise (the clean bags alone read −1.48/−1.21″/g; 54 clean seeds: SD 0.61″/g against
    the printed σ 0.53-0.54).  Tolerance 1 % (a third of what the 1 s window made; no
    noise enters)."""
    from stellar_cal_ros.diagnosis.injection import clean_simulation

    spec = method_spec("swaying_base")
    runs = {}
    for size in (0.0, 10.0):
        sim, _ = clean_simulation("swaying_base", False, 21, 120.0,
                                  {"mount_flexure": size} if size else None)
        data, prior = bag_data_from_simulation(sim), rerun_prior(sim.prior)
        runs[size] = evaluate(data, spec, prior, (), 0.5, keep_residuals=True).residuals
    moved = flexure.measure_on_bag(data, spec, prior, (), 0.5)
    win = {k: {c: np.asarray(v)[stats.evaluation_mask(r, 0.5)] for c, v in r.items()}
           for k, r in runs.items()}
    flexed, clean = flexure._aligned(win[10.0], win[0.0])
    flexed, probe = flexure._aligned(flexed, moved)
    clean, _ = flexure._aligned(clean, probe)
    m = stats.accepted(flexed) & stats.accepted(probe) & stats.accepted(clean)
    assert m.sum() > 1000, m.sum()
    per = flexure.PROBE / ARCSEC
    S = np.stack([probe[c][m] - flexed[c][m] for c in ("du", "dv")], 1) / per
    own = {k: v[m] for k, v in flexed.items()}
    own.update(du=flexed["du"][m] - clean["du"][m], dv=flexed["dv"][m] - clean["dv"][m])
    fit = stats.whitened_fit(own, S)
    assert fit is not None
    assert abs(fit[2] / 10.0 - 1.0) < 0.01, fit


def test_a_ripple_along_the_columns_is_unexplained_by_u_with_its_amplitude():
    """Unseen case ``ripple`` (fourth pass): the columns ripple, ``0.08 sin(2π 3 u /
    width)`` px (``tracker_errors.column_ripple``; rms 0.057 px, outside the library).  No
    straight line in u follows three periods: main's first line was ``v residual vs v
    (row)`` (t 11.6, 0.031 px: the calibration's focal length taking the ripple's slope
    into both axes), the column's own line fourth at 0.0056 px.  The ripple family of
    :func:`stats.shaped_tests` names it first: the u residual vs ``u (column) (periodic 341
    px, ...)`` (1024 px / 3), its amplitude 0.0767 px on 150 s seed 21; asserted within
    0.85-1.1x of 0.08 (the run's calibration absorbs a part; a straight-line size would
    read 2x the amplitude)."""
    found = _findings(_bag(lambda sim: (tracker_errors.column_ripple(sim, 0.08, 3.0),
                                        tracker_errors.renoise(sim, lambda m, uv: SIGMA,
                                                               SIGMA, 21))))
    assert found, "no 'unexplained' line"
    top = found[0]
    assert top.regressor.startswith(f"u (column) ({stats.RIPPLE} 341 px"), found[:3]
    assert top.component == "u" and top.p_value < 1e-10, top
    assert 0.85 * 0.08 < top.slope_px < 1.1 * 0.08, top


def test_the_ripple_family_holds_its_level_on_white_draws():
    """The ripple tests (:data:`stats.POSITION_PERIODS` periods across the detector, u and
    v, sin and cos, each axis displaced: 32 tests, all in the 'unexplained' lines'
    Bonferroni family) on a clean 150 s bag's own rows (frames, stars, positions), its
    innovations replaced by white draws at 0.05 px, 30 draws: the 960 t have mean 0 and SD
    1 within 3 of their standard errors (seed 5: mean -0.016, SD 0.976), and the unadjusted
    p is below 1 % in 1 % of them within 3 binomial σ (6, 9.6 expected; family of 80).  The level of
    the whole family on clean bags, both methods: ``benchmarks/false_alarms.py`` and
    ``benchmarks/structure_null.py`` (doc/benchmarks.md)."""
    sim = _bag(lambda sim: tracker_errors.renoise(sim, lambda m, uv: SIGMA, SIGMA, 21))
    prior, cam = sim.prior, sim.prior.camera
    run = evaluate(bag_data_from_simulation(sim), method_spec("psce"), rerun_prior(prior), (),
                   0.5, keep_residuals=True)
    res0 = dict(run.residuals)
    mask = stats.evaluation_mask(res0, 0.5)
    n = len(res0["du"])
    rng = np.random.default_rng(5)
    t, small = [], 0
    for _ in range(30):
        res = dict(res0, du=SIGMA * rng.standard_normal(n), dv=SIGMA * rng.standard_normal(n),
                   gated=np.zeros(n, bool))
        found = stats.regressor_tests(res, mask, (cam.cx, cam.cy), alpha=1.01,
                                      focal=(cam.fx, cam.fy), R_imu_st=prior.R_imu_st,
                                      height=cam.height, width=cam.width)
        ripple = [f for f in found if f.regressor.startswith(("u (column) (", "v (row) ("))
                  and stats.RIPPLE in f.regressor]
        assert len(ripple) == 8 * len(stats.POSITION_PERIODS)
        t += [f.statistic for f in ripple]
        # the unadjusted p below 1 % (< 1 / the family's size: the adjusted p not capped)
        small += sum(f.p_value < 0.01 * len(found) for f in ripple)
    t = np.asarray(t)
    assert abs(t.mean()) < 3 / np.sqrt(len(t)), t.mean()
    assert abs(t.std(ddof=1) - 1) < 3 / np.sqrt(2 * (len(t) - 1)), t.std(ddof=1)
    assert abs(small - 0.01 * len(t)) < 3 * np.sqrt(0.01 * 0.99 * len(t)), (small, len(t))


def test_a_declared_temperature_topic_without_messages_is_absent(tmp_path):
    """A bag that declares /star_tracker/temperature but holds no message on it (a node that
    advertised and never published; unseen case ``focal_drift``) has no head temperature:
    thermal_focal_length is not applicable for that reason, not 'not testable with this
    motion' at an infinite MDB.  The air temperature it does hold is read."""
    from stellar_cal_ros.core.types import ScalarSeries
    from stellar_cal_ros.diagnosis.discover import _applicable
    from stellar_cal_ros.io.bag import BagReader
    from stellar_cal_ros.methods.frames import read_bag_data
    from stellar_cal_ros.sim.world import write_simulation

    sim = simulate(get_scenario("psce_rotations"), duration=10.0, seed=3)
    n_air = len(sim.air_temperature)
    sim.head_temperature = ScalarSeries(np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0))
    bag = write_simulation(sim, tmp_path / "no_head.mcap")["bag"]
    with BagReader(bag) as r:
        assert r.topics()["/star_tracker/temperature"].message_count == 0
    data = read_bag_data(bag)
    assert data.head_temperature is None and len(data.air_temperature) == n_air > 0
    assert _applicable("thermal_focal_length", method_spec("psce"), data) == (
        "needs /star_tracker/temperature, absent from the bag")


def test_bright_stars_pulled_toward_the_centre_lead_by_magnitude():
    """Bright stars' centroids pulled toward the detector centre, 0.04 px per magnitude
    brighter than 4 (unseen case ``saturation``, outside the library; 300 s as the case):
    the first 'unexplained' line is carried by the magnitude (`radial vs magnitude`, t 9.0,
    0.0211 px in the case's `discover`), with the saturation's sign (the radial residual
    grows toward the faint stars, which it spares) and the true pull's size (its σ ~11 %).
    (On 150 s bags the first line is `v vs v (row)`, even at 0.08 px per magnitude:
    doc/benchmarks.md, fifth pass.)"""
    def post(sim):
        tracker_errors.saturation_pull(sim, 0.04)
        tracker_errors.renoise(sim, lambda m, uv: SIGMA, SIGMA, 21)

    sim = _bag(post, duration=300.0)
    found = _findings(sim)
    assert found and found[0].regressor == "magnitude", found[:3]
    assert found[0].component == "radial" and found[0].statistic > 0, found[:3]
    # its size, the true pull's straight line over the window's magnitudes (5-95 %)
    t0 = sim.star_frames[0].stamp_ns
    mag = np.concatenate([np.asarray(f.magnitude, dtype=float) for f in sim.star_frames
                          if f.stamp_ns - t0 >= 150e9])
    mag = mag[np.isfinite(mag)]
    lo, hi = np.percentile(mag, [5, 95])
    want = np.polyfit(mag, -0.04 * np.maximum(4.0 - mag, 0.0), 1)[0] * (hi - lo)
    assert found[0].slope_px == pytest.approx(want, rel=0.25), want


def _psce_run(sim):
    """The current model's psce run of ``sim`` (window 0.5, residuals kept) and the runner
    ``output.causes_first`` is given (in this process, on ``sim``'s bag)."""
    data = bag_data_from_simulation(sim)
    run = evaluate(data, method_spec("psce"), rerun_prior(sim.prior), (), 0.5,
                   keep_residuals=True)
    return run, SimpleNamespace(spec=method_spec("psce"), fraction=0.5, noise=None,
                                classes=(), on_bag=lambda fn, *a: fn(data, *a),
                                later=lambda fn, *a: lambda: fn(data, *a),
                                spare=lambda fn, *a: Spare(lambda: fn(data, *a)))


def _ranked(sim):
    """The current model's run of ``sim`` and its lines ranked as ``output.finish`` ranks them."""
    run, runs = _psce_run(sim)
    found = line_tests(run.residuals, sim.prior, 0.5)
    ranked = output.causes_first(found, run, runs)
    # the re-runs started before the line tests (a cluster's workers beside them): the same
    started = (shape_drift.start_first_runs(run, runs, line_tests),
               rolling.start_lines_without(run, runs, line_tests))
    again = output.causes_first(found, run, runs, started=started)
    assert [(f.regressor, f.p_value, f.detail) for f in again[0]] == \
        [(f.regressor, f.p_value, f.detail) for f in ranked[0]] and again[1] == ranked[1]
    return run, found, ranked


def _drifting(drift, size):
    """A 300 s bag with ``drift(sim, size)`` and the stated noise: the simulation, the
    current model's run, its lines ranked with the causes first and which follow one (main
    ranks no time line first)."""
    def post(sim):
        drift(sim, size)
        tracker_errors.renoise(sim, lambda m, uv: SIGMA, SIGMA, 21)

    sim = _bag(post, duration=300.0)
    run, plain, (found, follows) = _ranked(sim)
    assert plain and not plain[0].regressor.startswith("time"), plain[:3]  # (main's first line)
    return sim, run, found, follows


def test_a_drifting_focal_length_is_named_first_and_its_static_scale_lines_follow_it():
    """The focal length drifting linearly, -75 -> +75 ppm over 300 s (unseen case
    ``focal_drift``, no temperature topic: outside the library).  The constant-f model
    lags it: its lines ranked by p are the static scale's (u vs u, v vs v and their
    one-period sines, t ~ 20); the rule names the drift first, its size the truth's within
    3 σ (144 ± 25 ppm read for 150, 0.105 px at the detector's corner), and the static
    scale's lines follow it (gone on the run with the drift taken out)."""
    ppm = 150.0
    sim, run, found, follows = _drifting(tracker_errors.focal_drift, ppm)
    assert found[0].regressor.startswith(shape_drift.REGRESSOR), found[:3]
    assert found[0].component == "radial" and found[0].statistic > 5.0, found[0]
    d = found[0].detail
    span_ns = sim.star_frames[-1].stamp_ns - sim.star_frames[0].stamp_ns
    want = ppm * d["run_s"] / (span_ns * 1e-9)
    assert abs(d["ppm_over_run"] - want) < 3.0 * d["sigma_ppm"], (d, want)
    assert d["sigma_ppm"] < 0.25 * want, d
    corner = shape_drift.corner_px(run.calibration)
    assert found[0].slope_px == pytest.approx(want * 1e-6 * corner, rel=3.0 * d["sigma_ppm"]
                                              / want)
    gone = {rolling.line_key(found[i]) for i in follows}
    assert {("u (column)", "u"), ("v (row)", "v")} <= gone, gone
    assert set(follows.values()) == {shape_drift.CAUSE} and 0 not in follows


def test_the_focal_drift_rule_is_silent_on_a_clean_bag():
    """A clean bag (300 s, seed 21): the static scale and its change are not both
    significant (measured on seeds 21-26: the change's t within +-1.2), nor a tilt's, no run
    is made and the lines are as ranked before."""
    sim = _bag(lambda s: tracker_errors.renoise(s, lambda m, uv: SIGMA, SIGMA, 21),
               duration=300.0)
    run, plain, (found, follows) = _ranked(sim)
    fit = shape_drift.of_table(run.residuals, run.calibration, 0.5)
    assert fit is not None and abs(fit["change_t"]) < 3.0, fit
    assert not shape_drift.lagging(fit, 0.01)
    for tilt in shape_drift.SHAPES[1:]:  # (measured on seeds 21-32: |t| < 2.6)
        fit = shape_drift.of_table(run.residuals, run.calibration, 0.5, tilt)
        assert fit is not None and abs(fit["change_t"]) < 3.5, fit
        assert not shape_drift.lagging(fit, 0.01)
    assert found == plain and not follows


def test_a_drifting_detector_tilt_is_named_first_and_its_static_keystone_lines_follow_it():
    """The detector's tilt about u drifting linearly, -1.5 -> +1.5 mrad over 300 s (unseen
    case ``tilt_drift``, 0 on average; image_plane_tilt is static: outside the library).
    psce estimates no tilt, but its principal point and tangential p1 span the keystone
    (0.999) and lag it: its lines ranked by p are the static keystone's (v vs v (row) and
    its one-period cosine, radial vs v (row), t ~ 24) and main names no time.  The shape
    rule names the tilt's drift first, its size the truth's within 3 σ (2.92 ± 0.27 mrad
    read for 3), and the static keystone's lines follow it."""
    mrad = 1.5
    sim, run, found, follows = _drifting(tracker_errors.tilt_drift, mrad)
    tilt = shape_drift.SHAPES[1]
    assert found[0].regressor.startswith(tilt.regressor), found[:3]
    assert found[0].component == "radial" and found[0].statistic > 5.0, found[0]
    d = found[0].detail
    assert d["shape"] == "tau_x" and d["spanned"] > shape_drift.SPANNED, d
    span_ns = sim.star_frames[-1].stamp_ns - sim.star_frames[0].stamp_ns
    want = 2.0 * mrad * d["run_s"] / (span_ns * 1e-9)
    assert abs(d["mrad_over_run"] - want) < 3.0 * d["sigma_mrad"], (d, want)
    assert d["sigma_mrad"] < 0.25 * want, d
    # the principal point's v drifting reads the same (reviewer RC): the line says both
    fy = run.calibration.camera.fy
    assert d["c_y_px_over_run"] == pytest.approx(d["mrad_over_run"] * 1e-3 * fy), d
    assert "principal point's v (c_y) drifting by" in found[0].regressor, found[0]
    corner = shape_drift.corner_px(run.calibration, tilt)
    assert found[0].slope_px == pytest.approx(want * 1e-3 * corner, rel=3.0 * d["sigma_mrad"]
                                              / want)
    gone = {rolling.line_key(found[i]) for i in follows}
    assert {("v (row)", "radial"), ("v (row) (periodic 1024 px", "v")} <= gone, gone
    assert set(follows.values()) == {tilt.cause} and 0 not in follows
    said = printing.unexplained_phrase({"component": "radial", "regressor": found[0].regressor,
                                        "change_px": found[0].slope_px, "detail": d})
    assert said[1].endswith("px at the detector's corner over the run"), said
    assert printing.follows_phrase({"follows": tilt.cause}).endswith("gone once the drift is "
                                                                     "taken out of the centroids")
    assert not any(f.regressor.startswith(shape_drift.REGRESSOR) for f in found)


def test_the_shape_patterns_are_the_cameras_own():
    """The tilts' keystones the rule tests (``stats.shape_pattern``) are the camera model's
    tau_x / tau_y Jacobians to first order (their signs: OpenCV's tilt matrix), and the
    scale's the focal length's; psce's camera parameters span a tilt's keystone."""
    from stellar_cal_ros.core.camera import CameraModel

    cam = CameraModel.pinhole(1024, 1024, 3000.0, 515.0, 508.0)
    rng = np.random.default_rng(3)
    u = rng.uniform(0, cam.width, 500)
    v = rng.uniform(0, cam.height, 500)
    centre, focal = (cam.cx, cam.cy), (cam.fx, cam.fy)
    cal = SimpleNamespace(camera=cam)
    for shape, effect in (("scale", "focal_length"), ("tau_x", "image_plane_tilt")):
        got = stats.shape_pattern(shape, u, v, centre, focal)
        jac = shape_drift.patterns(cal, (effect,))(u, v)[:, :, 0]
        assert np.allclose(got, jac, atol=0.01 * np.abs(jac).max()), shape
    jac = shape_drift.patterns(cal, ("image_plane_tilt",))(u, v)[:, :, 1]
    got = stats.shape_pattern("tau_y", u, v, centre, focal)
    assert np.allclose(got, jac, atol=0.01 * np.abs(jac).max())
    assert shape_drift.camera_columns(method_spec("swaying_base").baseline) == ()


def test_a_cause_line_and_the_flexure_findings_do_not_follow_another_cause(monkeypatch):
    """The rolling-shutter rule's re-run gives back only what the line tests make: the
    focal drift's own line (another cause's, ``detail["cause"]``) and the flexure-shaped
    findings after an add (``keep``) cannot be in it, and were said to follow the shutter
    (a reviewer's mock on main f52b5c4: the drift line moved behind the rolling line,
    'follows: rolling shutter').  A line the re-run lost still follows it."""
    from stellar_cal_ros.diagnosis import rolling, shape_drift

    def line(reg, t, detail=None):
        return stats.RegressorFinding(reg, "u", t, 1e-9, 0.05, detail)

    drift = line("time x radius (the focal length changes", 7.0, {"cause": shape_drift.CAUSE})
    flex = line("gravity_st x probe response (mount flexure", 9.0)
    lost = line("u (column)", 8.0)
    shutter = line(stats.ROLLING + ")", -50.0)
    found = [drift, flex, lost, shutter]
    monkeypatch.setattr(rolling, "of_run",
                        lambda run, fraction, axis=None: {"coefficient": 1e-5, "axis": "v"})
    cal = SimpleNamespace(camera=SimpleNamespace(height=1024, width=1024))
    run = SimpleNamespace(ok=True, prior=object(), effects=(), calibration=cal)
    runs = SimpleNamespace(spec=None, fraction=0.5, noise=None, classes=(),
                           on_bag=lambda fn, *a: ([], None))
    out, after = rolling.first_if_cause(found, run, runs, None, frozenset({id(flex)}))
    assert out[0] is drift and out[1] is flex, [f.regressor for f in out]
    assert out[2].regressor.startswith(stats.ROLLING) and out[3] is lost and after == {3}
    # without ``keep`` the flexure finding follows like any line; the cause's stays
    out, after = rolling.first_if_cause(found, run, runs, None)
    assert out[0] is drift and out[1].regressor.startswith(stats.ROLLING) and after == {2, 3}


def test_an_added_camera_shape_beside_a_one_axis_shape_may_stand_in_for_it() -> None:
    """Case ``u_cubic`` (a centroid bias along u alone, cubic in the column: outside the
    library): ``discover`` adds pixel_aspect (−141 ppm, the cubic's linear part) and 'u
    residual vs u (column)' lines are left.  The summary says the aspect may stand in for
    a u-only distortion (``output.axis_remainder``, text only); not when the other axis
    shows its own shape too, nor when nothing added is a camera effect.  The lines are the
    seed-21 run's first two."""
    from stellar_cal_ros.diagnosis.output import axis_remainder

    def line(component, regressor, t, px):
        return {"regressor": regressor, "component": component, "statistic": t,
                "p_value": 1e-8, "change_px": px}

    u_lines = [line("u", "u (column) (periodic 1024 px, sin)", 11.0, 0.0114),
               line("u", "u (column) (periodic 512 px, sin)", -7.4, 0.0100)]
    a = axis_remainder(u_lines, ["pixel_aspect"])
    assert a is not None and a["axis"] == "u" and a["lines"] == 2
    assert a["effects"] == ["pixel_aspect"] and a["statistic"] == 11.0
    assert a["text"].startswith("pixel_aspect may stand in for a u-only distortion")
    assert "0.0114 px, t=11.0" in a["text"]
    v_only = [dict(u, component="v", regressor=u["regressor"].replace("u (column)", "v (row)"))
              for u in u_lines]
    assert axis_remainder(v_only, ["image_plane_tilt"])["axis"] == "v"
    assert axis_remainder(u_lines + v_only[:1], ["pixel_aspect"]) is None  # both axes
    assert axis_remainder(u_lines, ["time_offset"]) is None  # no camera effect added
    assert axis_remainder(u_lines, []) is None


@pytest.mark.parametrize("rho,axes,truth", [(0.0, (2.0, 1.0), float(np.sqrt(2.5))),
                                            (0.8, (1.0, 1.0), 1.0)])
def test_anisotropic_or_uv_correlated_noise_reads_its_isotropic_scale(rho, axes, truth):
    """Centroid noise unlike the messages' isotropic σ (unseen cases ``aniso_u2x``: 0.1 px
    along u, 0.05 along v; ``uv_corr``: u and v correlated, ρ 0.8, 0.05 px each): the stars'
    scale is the isotropic ML one, √((2² + 1) / 2) = 1.58 and 1, within 3σ (150 s, seed 21:
    1.584 ± 0.021 and 0.995 ± 0.014; seeds 22-24 z −2.3 to +0.2)."""
    def post(sim):
        tracker_errors.uv_noise(sim, (axes[0] * SIGMA, axes[1] * SIGMA), rho, SIGMA, 21)

    sim = _bag(post)
    v, applied, _ = _measured_noise(bag_data_from_simulation(sim), sim.prior)
    assert v.star == pytest.approx(truth, abs=3 * v.star_sigma), (v.star, v.star_sigma)
    assert v.star_sigma < 0.03 and v.group is None
    assert (abs(applied.star - truth) < 3 * v.star_sigma) if truth != 1.0 else \
        applied.identity


def test_a_mount_turning_with_the_head_temperature_gets_no_library_name():
    """Unseen case ``thermal_mount`` (the mount turned 2″/°C with the head temperature, the
    head cooling 30 -> 11 °C with τ 100 s; 7″ = 0.13 px over the window), its 300 s seed-21
    bag: gyro_scale_factor and gyro_misalignment are significant alone (p 4.4e-68, 1.8e-53:
    a turning installation's ω × δ in the slews), but the temperature field (the filter's
    response to a tracker turn with the head temperature about each axis,
    ``leads.temperature_of``) is a lead of the baseline and neither explains anything
    beyond it (ratios −1.3 for 3 dof, −1.0 for 6): ``discover`` adds neither, and the field
    reads the turn's rate (measured 1.99 ± 0.27″/°C: the truth within 3 of the sigma it
    prints) and its turn over the window (6.9″, 0.134 px; truth 2″/°C × 3.45 °C).  On main
    f4c055a gyro_scale_factor was added (then exchanged for gyro_misalignment, −67 ± 70″,
    ..., the truth 0) and no line named the temperature: there is no temperature field."""
    sc = get_scenario("psce_rotations")
    sim = simulate(dataclasses.replace(sc, head_temperature_tau_s=100.0), duration=300.0,
                   seed=21)
    tracker_errors.thermal_mount(sim, 2.0)
    top, refused, results, _, state = _top_of(sim, "psce", ("gyro_scale_factor",
                                                            "gyro_misalignment"))
    assert all(r.significant_alone for r in results), results
    assert top is None, top.effect
    f = state.lead["temperature"]
    assert f["p_value"] < 1e-3, f
    assert abs(f["arcsec_per_c"] - 2.0) < 3 * f["sigma_arcsec_per_c"], f
    # the window (150-300 s) of the head's 10 + 20 exp(-t / 100 s): 3.47 deg C
    assert abs(f["temperature_change_c"] - 20.0 * (np.exp(-1.5) - np.exp(-3.0))) < 0.05, f
    # the turn over the window against the truth's (2"/deg C over that range, at the plate
    # scale), within 3 of the sigma the rate prints
    px = f["temperature_change_c"] / tracker_errors.ARCSEC_PER_PX
    assert abs(f["turn_px"] - 2.0 * px) < 3 * f["sigma_arcsec_per_c"] * px, f
    assert {c.effect for c, _ in refused} == {"gyro_scale_factor", "gyro_misalignment"}
    assert all(not b["needed"] and b["lead"] == "temperature" for _, b in refused), refused
    # worth running: its MDB (leads.temperature_mdb) below a plausible mount's
    assert f["mdb_arcsec_per_c"] < leads.PLAUSIBLE_MOUNT_ARCSEC_PER_C, f


def _temperature_of(sim, method="psce", said=None):
    """``leads.temperature_of`` on the baseline of ``sim``'s bag: ``(fit, lines told, bound)``
    (``said``: filled with the not-testable line's numbers)."""
    data, spec, prior = bag_data_from_simulation(sim), method_spec(method), \
        rerun_prior(sim.prior)
    base = evaluate(data, spec, prior, (), 0.5, keep_residuals=True)
    runs = SimpleNamespace(spec=spec, fraction=0.5, noise=None, classes=(),
                           later=lambda fn, *a: lambda: fn(data, *a))
    told: list[str] = []
    fit = leads.temperature_of(runs, base, prior, (), 0.01, told.append, "the baseline",
                               said)
    return fit, told, leads.temperature_bound(base.residuals, 0.5, 0.01)


def test_the_temperature_field_runs_where_its_mdb_is_a_plausible_mounts():
    """The temperature field is worth running where its MDB (the turn its two-step test
    sees with power 80 %, ``leads.temperature_mdb``, checked by injection in
    doc/benchmarks.md) is at most a plausible mount's 2.5″/°C, else the user reads "not
    testable: temperature changed X deg C".  The clean 300 s psce bag, seed 21 (the head
    0.78 °C over the window, nearly a straight line in time, which the gyro bias takes up):
    MDB 11.7″/°C, not testable, no field (H246's gate, a change of 1 °C, chosen for cost,
    did not run it either).  The same bag cooling with τ 100 s (``thermal_still``, 3.45 °C
    over the window, curved): MDB 0.62″/°C, the field fitted and nothing found (p 0.53).
    The bound made before any run (the turn about the best-seen axis, nothing taken up by
    the model) is below both (0.56, 0.13″/°C), as a bound must be.  Fails on coord 44f8153
    (no MDB: the field's gate was the change alone, and nothing said)."""
    sc = get_scenario("psce_rotations")
    said: dict = {}
    fit, told, bound = _temperature_of(simulate(sc, duration=300.0, seed=21), said=said)
    assert fit is None and len(told) == 2, told
    assert told[0].startswith("testing for a head-temperature-shaped remainder"), told
    mdb = float(re.search(r"would see ([0-9.]+) arcsec per deg C", told[1]).group(1))
    assert told[1].startswith("a mount turning with the head temperature is not testable: "
                              "temperature changed 0.78 deg C over the window"), told
    assert mdb == pytest.approx(11.7, abs=0.1) and bound["mdb"] < mdb, (told, bound)
    # the line's numbers as diagnosis.json's path[].temperature_not_testable holds them
    assert said["from_bound"] is False and f"{said['mdb_arcsec_per_c']:.3g}" == f"{mdb:.3g}"
    assert f"{said['temperature_change_c']:.2g}" == "0.78", said
    assert "a turn about an axis at random, above a plausible mount's 2.5)" in told[1], told
    fit, told, bound = _temperature_of(simulate(dataclasses.replace(
        sc, head_temperature_tau_s=100.0), duration=300.0, seed=21))
    assert fit is not None and fit["p_value"] > 0.01, fit
    assert fit["mdb_arcsec_per_c"] == pytest.approx(0.623, abs=0.01), fit
    assert bound["mdb"] < fit["mdb_arcsec_per_c"] and len(told) == 1, (bound, told)


def test_the_temperature_fields_not_testable_line_is_in_diagnosis_json(tmp_path, capsys):
    """``discover`` (120 s psce, seed 8, a hidden 10 ms time offset: a candidate that may
    stand in for a mount turning with the head temperature) prints "a mount turning with
    the head temperature is not testable: temperature changed X deg C ..." and that
    round's ``path[]`` entry holds its numbers (``temperature_not_testable``, H284): the
    change X the head temperature's range over the window's frames (the bag's series at
    the frames: 0.322 °C), M the MDB printed (here the bound's, 3.14″/°C: no probe run).
    Fails on coord 0e2fd9e (the line alone: no key)."""
    import json

    from stellar_cal_ros.diagnosis.run import diagnose

    sim = simulate(get_scenario("psce_rotations"), duration=120.0, seed=8,
                   effects={"time_offset": 0.01})
    diagnose(bag_data_from_simulation(sim), sim.prior, "psce", [], tmp_path, plots=False,
             auto=True, max_rounds=1, candidates=["time_offset"])
    line = next(x for x in capsys.readouterr().out.splitlines()
                if "head temperature is not testable" in x)
    got = re.search(r"changed ([0-9.]+) deg C over the window \(even a model that takes "
                    r"none of the turn up would see at best ([0-9.]+) arcsec per deg C", line)
    assert got, line
    step = json.loads((tmp_path / "diagnosis.json").read_text())["path"][0]
    said = step["temperature_not_testable"]
    assert said["from_bound"] is True, said
    assert f"{said['temperature_change_c']:.2g}" == got.group(1), (said, line)
    assert f"{said['mdb_arcsec_per_c']:.3g}" == got.group(2), (said, line)
    assert said["mdb_arcsec_per_c"] > leads.PLAUSIBLE_MOUNT_ARCSEC_PER_C
    t = np.array([f.stamp_ns for f in sim.star_frames], dtype=float)
    head = sim.head_temperature
    window = np.interp(t[t >= np.median(t)], head.stamp_ns.astype(float), head.value)
    assert said["temperature_change_c"] == pytest.approx(np.ptp(window), rel=1e-6), said


def _mag_inverted(sim):
    """True σ 0.05·2^((m − 4)/2) px, the σ field 0.05·2^(−(m − 4)/2): upside down."""
    tracker_errors.renoise(sim, lambda m, uv: SIGMA * 2.0 ** ((m - 4.0) / 2.0), SIGMA, 21)
    for f in sim.star_frames:
        f.sigma = SIGMA * 2.0 ** (-(np.asarray(f.magnitude, dtype=float) - 4.0) / 2.0)


def test_a_sigma_whose_magnitude_dependence_is_upside_down_is_grouped_not_wrong_star_by_star():
    """The σ field's magnitude dependence upside down (unseen case ``mag_inverted``: the
    truth/stated ratio 2^(m − 4), doubling per magnitude): the stars' σ is grouped by
    magnitude, each group's scale the truth's RMS ratio over the window's rows within 3σ
    (150 s, seed 21: 1.177/1.663/2.186/2.784/3.330/3.782 for 1.128/1.754/2.140/2.675/3.390/
    3.764), and the ratio's change within the groups is no "wrong star by star ... at
    random, not a trend in magnitude" (on main: F 2.67, p 3.5e-6, "~7.8 % at random";
    at 300 s, seeds 21 / 22, ~11 / ~9.6 %): the stars' levels trend in magnitude within
    the groups (``noise_stars._magnitude_trend``), divided out before the per-star test.
    A σ field off by a random factor per star (``sigma_per_star``'s 30 % lognormal) is
    still wrong star by star, with no trend taken out."""
    sim = _bag(_mag_inverted)
    v, applied, _ = _measured_noise(bag_data_from_simulation(sim), sim.prior)
    assert v.per_star is None, v.per_star
    assert not any("wrong star by star" in x for x in v.lines()), v.lines()
    g = v.group
    assert g is not None and g["by"] == "magnitude" and applied.group_by == "magnitude"
    edges, scales = np.asarray(g["edges"], dtype=float), np.asarray(g["scales"], dtype=float)
    half = sim.star_frames[len(sim.star_frames) // 2:]
    m = np.concatenate([np.asarray(f.magnitude, dtype=float) for f in half])
    k = np.searchsorted(edges, m, side="right")
    truth = np.array([math.sqrt(np.mean(4.0 ** (m[k == i] - 4.0))) for i in range(len(scales))])
    assert len(scales) >= 4 and np.all(np.abs(scales - truth) < 3.0 * np.asarray(g["sigma"])), \
        (scales, truth, g["sigma"])

    def per_star(sim):
        tracker_errors.renoise(sim, lambda m, uv: SIGMA, SIGMA, 21)
        rng = np.random.default_rng(21 + 1299709)
        fac: dict[int, float] = {}
        for f in sim.star_frames:
            f.sigma = SIGMA * np.array([fac.setdefault(int(c), float(np.exp(
                0.3 * rng.standard_normal() - 0.045))) for c in np.asarray(f.catalog_id)])

    sim = _bag(per_star)
    v, _, _ = _measured_noise(bag_data_from_simulation(sim), sim.prior)
    assert v.per_star is not None and v.per_star["magnitude_trend"] == 0.0, v.per_star
    assert v.per_star["p_value"] < 1e-50 and 0.5 * v.per_star["spread"] == pytest.approx(
        0.3, abs=0.1)


def _sigma_as_variance(sim):
    for f in sim.star_frames:
        f.sigma = np.asarray(f.sigma, dtype=float) ** 2


def _gross_outliers(sim):
    assert tracker_errors.gross_outliers(sim, 0.015, 20.0, 50.0, 21) > 50


@pytest.mark.parametrize("post,truth", [(_sigma_as_variance, 20.0), (_gross_outliers, 1.0)])
def test_a_sigma_field_holding_the_variance_or_outliers_tens_of_px_off_read_their_scale(
        post, truth):
    """Unseen cases ``sigma_as_var`` (the σ field holds σ², 0.0025 for 0.05 px: x20) and
    ``gross_outliers`` (1.5 % of the centroids 20-50 px off, misidentified stars; σ
    right): the stars' scale is the truth within 3σ (150 s, seed 21: 19.91 ± 0.22 and
    0.997 ± 0.011; 103 centroids moved), one scale, no groups, no per-star verdict, no
    heavy tails (the outliers are gated, not the noise's tails)."""
    sim = _bag(post, noise_free=False)
    v, applied, _ = _measured_noise(bag_data_from_simulation(sim), sim.prior)
    assert v.star == pytest.approx(truth, abs=3.0 * v.star_sigma), (v.star, v.star_sigma)
    assert v.star_sigma < 0.015 * truth and v.group is None and v.per_star is None
    assert not v.tails
    assert applied.star == pytest.approx(v.star) if truth != 1.0 else applied.identity


def test_a_gauss_markov_gyro_bias_has_its_sigma_and_correlation_time():
    """``tracker_errors.gyro_bias_gauss_markov`` (unseen case ``gyro_gm``: 1 deg/h, τ 30 s):
    over 10 000 s at 10 Hz (333 τ, 3 axes) the bias's SD is 1 deg/h within 15 % (its
    standard error ~2.5 %) and its correlation at lag τ e^-1 within 0.1."""
    t = np.arange(100_000, dtype=np.int64) * 100_000_000
    sim = SimpleNamespace(imu=SimpleNamespace(stamp_ns=t, angular_velocity=np.zeros((len(t),
                                                                                      3))))
    b = tracker_errors.gyro_bias_gauss_markov(sim, 1.0, 30.0, 21)
    assert np.array_equal(sim.imu.angular_velocity, b)
    sd = np.rad2deg(b.std(axis=0)) * 3600.0
    assert np.all(np.abs(sd - 1.0) < 0.15), sd
    lag = 300
    rho = [np.corrcoef(b[:-lag, i], b[lag:, i])[0, 1] for i in range(3)]
    assert np.all(np.abs(np.array(rho) - math.exp(-1.0)) < 0.1), rho


def test_a_lens_zone_is_unexplained_as_a_radial_step_first():
    """A lens zone (H250): beyond 400 px from the principal point the image scale 300 ppm
    larger (a 0.12 px radial step there, ``tracker_errors.lens_zone``), 150 s of PSCE, seed
    21.  The model's focal length and radial polynomial take the step's smooth part; what
    is left is a step less its polynomial, which no straight line in the radius follows:
    on main f4c055a the first line was the radial residual vs ``v (row)`` (t -7.6; at 300 s
    ``discover`` said 'repeating vs catalogue star' first and a noise line blamed the
    catalogue positions, seeds 21 and 22).  The radial step tests (``stats.ZONE``, a step at
    the stars' radius quartiles less what r, r^3, r^5 take of it) put the zone first (t 10.3
    at the median radius, 423 px).  Fails on main (no such test)."""
    def post(sim):
        tracker_errors.lens_zone(sim, 400.0, 300.0)
        tracker_errors.renoise(sim, lambda m, uv: SIGMA, SIGMA, 21)

    found = _findings(_bag(post))
    assert found and found[0].regressor.startswith(stats.ZONE), found[:3]
    assert found[0].statistic > 7.0


def test_a_lens_zones_echoes_follow_its_radial_step_line():
    """Unseen case ``lens_zone`` (beyond 400 px the image scale 300 ppm larger), 300 s of
    PSCE, seed 21, the baseline run as ``discover`` ranks its lines: coord2 3ff819c ranked
    'residual repeating vs catalogue star' first (t 12.2, p 1.3e-17: a star keeps its radius
    along its track, so the step repeats star by star), the step line at the median radius
    (429 px) second (t 12.3, p 3.3e-17) and another step line (514 px, t -9.8) third (the
    unseen case's ``discover`` at s21: t 11.8, 11.2, -10.6).  The strongest step line
    is a cause (``leads.fields_first``): the step fitted at the radius that takes most of
    the window's χ² (``leads.zone_without``: 398 px measured; the quartile's step left the
    508 px line and the repeat) and taken out of the residuals, the line tests no longer
    find the repeat nor the other step line: they follow it.  Fails on coord2 (the repeat
    first, nothing follows)."""
    from stellar_cal_ros.diagnosis import leads, printing

    def post(sim):
        tracker_errors.lens_zone(sim, 400.0, 300.0)
        tracker_errors.renoise(sim, lambda m, uv: SIGMA, SIGMA, 21)

    run, runs = _psce_run(_bag(post, duration=300.0))
    found = line_tests(run.residuals, run.calibration, 0.5)
    repeat = next(f for f in found if f.regressor == "catalogue star")
    steps = [f for f in found if f.regressor.startswith(stats.ZONE)]
    assert len(steps) >= 2 and steps[0].statistic > 7.0, found[:4]
    lines, follows = output.causes_first(found, run, runs)
    assert lines[0].regressor == steps[0].regressor and 0 not in follows, [
        (f.regressor, f.statistic) for f in lines[:3]]
    cause = "radial step of the image scale"  # (leads.CAUSES["zone"])
    assert follows.get(lines.index(repeat)) == cause, follows
    assert follows.get([f.regressor for f in lines].index(steps[1].regressor)) == cause, \
        follows
    assert sorted(follows) == list(range(len(lines) - len(follows), len(lines)))
    said = printing.follows_phrase({"follows": cause})
    assert said == ("follows the radial step of the image scale: gone once the step's fit is "
                    "taken out of the centroids"), said
    cam = run.calibration.camera
    radius = leads.zone_without(run.residuals, 0.5, (cam.cx, cam.cy))[1]
    # the grid's spacing ~5 px; the step's radius read within 20 px (measured 398)
    assert abs(radius - 400.0) < 20.0, radius


@pytest.mark.parametrize("case", ["stray_light", "catalogue"])
def test_a_repeat_that_a_smooth_row_structure_explains_follows_it(case, monkeypatch):
    """Unseen case ``stray_light`` (300 s PSCE seed 21, the baseline run as ``discover``
    ranks its lines): the bias fades over 40 px from the first rows, finer than the
    detector cells the per-star repeat test takes out first, so the stars that dwell near
    the edge repeat, and the repeat (t 8.3, chi2 328 / 156 in the unseen case's
    ``discover``) ranked before the 'v (row)' lines (t -8.0, 7.6) and the noise line blamed
    the catalogue positions.  Without a smooth function of the row (the ripple lines' own,
    ``leads.position_without``) the repeat is 150 / 156: it follows the strongest row line,
    which leads.  A per-star catalogue error (unseen case ``catalogue``, N(0, 2") per axis)
    repeats beside any such function (1563 -> 1287 / 156): its line stays first, followed
    by nothing.  Fails on coord 0e2fd9e for ``stray_light`` (nothing follows)."""
    import importlib.util
    import sys
    from pathlib import Path

    # (the unseen case's own bag: its post-processing, seed 21)
    spec = importlib.util.spec_from_file_location(
        "unseen_cases", Path(__file__).resolve().parents[1] / "benchmarks" / "unseen_cases.py")
    uc = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "unseen_cases", uc)
    spec.loader.exec_module(uc)
    c = uc.CASES[case]
    run, runs = _psce_run(_bag(lambda sim: c.post(sim, 21),
                               noise_free="centroid_noise_px" in c.scenario_changes,
                               duration=300.0))
    found = line_tests(run.residuals, run.calibration, 0.5)
    repeat = next(f for f in found if f.regressor == "catalogue star")
    lines, follows = output.causes_first(found, run, runs)
    shown = [(f.regressor, round(f.statistic, 1)) for f in lines[:4]]
    if case == "catalogue":
        assert lines[0] is repeat and 0 not in follows, (shown, follows)
        return
    cause = "smooth structure over the detector's rows (v)"  # (leads.CAUSES["rows"])
    assert lines[0].regressor.startswith("v (row)") and 0 not in follows, shown
    assert follows.get(lines.index(repeat)) == cause, (shown, follows)
    assert leads.position_lead(lines[0]) == "rows" and leads.CAUSES["rows"] == cause
    said = printing.follows_phrase({"follows": cause})
    assert said == ("follows the smooth structure over the detector's rows (v): gone once "
                    "its smooth fit over the rows is taken out of the centroids"), said
    # the noise verdict's lines follow it too: the repeat's, and the IMU noise's reason
    # (the unseen case's discover s21/s22 said "IMU noise taken as stated: ... the attitude
    # follows the per-star errors of the stars in view"; fails on coord 994992f)
    rep = {"chi2": 328.0, "dof": 156.0, "p_value": 2.4e-14, "rms_px": 0.0061}
    v = noise.NoiseVerdict(NoiseScales(), NoiseScales(), repeat=rep,
                           imu_skipped=noise.repeat_reason(rep["rms_px"]))
    assert any("the per-star errors of the stars in view" in x for x in v.lines()), v.lines()
    got = v.following(follows[lines.index(repeat)])
    assert got.repeat["follows"] == cause and got.as_json()["star_repeat"]["follows"] == cause
    said = [x for x in got.lines() if "repeat star by star" in x]
    assert len(said) == 2 and all(cause in x for x in said), said
    assert "IMU noise taken as stated: the stars' residuals repeat star by star (0.0061 px " \
        "rms): the attitude follows the displacement the smooth structure over the " \
        "detector's rows (v) makes of the stars in view" in said[1], said


def test_a_lens_zones_step_line_says_its_fitted_step_and_the_noise_repeat_follows_it():
    """Unseen case ``lens_zone`` (beyond 400 px the image scale 300 ppm larger: 0.12 px at
    the radius), 300 s of PSCE, seed 21, the baseline run as ``discover`` ranks its lines.
    The step line leads at a quartile's radius (429 px): its line now says the step fitted
    (``leads.zone_without``, the step of the image scale, ``r / q`` beyond ``q``: the unit
    step left the scale's growth beyond the radius, which the 338 px line of the unseen
    case's ``discover`` read beside it): radius 397 px, 0.096 px there, 243 ppm measured
    (a size of what the filter left, as every line's: its focal length and radial terms
    take part of the step over the run, ~20 % here; the unseen case's ``discover`` at s21
    prints 0.11 px at 398 px, 271 ppm).  Once it is taken out, no step line is left.
    The noise verdict's star-by-star repeat then says it follows the step, not the
    catalogue.  Fails on coord 01f1a6b (no fit on the line; the noise line blamed the
    catalogue positions)."""
    from stellar_cal_ros.diagnosis import leads

    def post(sim):
        tracker_errors.lens_zone(sim, 400.0, 300.0)
        tracker_errors.renoise(sim, lambda m, uv: SIGMA, SIGMA, 21)

    run, runs = _psce_run(_bag(post, duration=300.0))
    found = line_tests(run.residuals, run.calibration, 0.5)
    lines, follows = output.causes_first(found, run, runs)
    lead = lines[0]
    assert lead.regressor.startswith(stats.ZONE) and 0 not in follows, lead
    d = lead.detail
    assert d["cause"] == leads.CAUSES["zone"]
    assert abs(d["radius_px"] - 400.0) < 20.0, d
    # (the truth 0.12 px, 300 ppm; what the filter leaves of it 0.8-0.9x)
    assert d["step_px"] == pytest.approx(0.12 * 0.85, rel=0.12), d
    assert d["scale_ppm"] == pytest.approx(300.0 * 0.85, rel=0.12), d
    said = printing.unexplained_phrase({"regressor": lead.regressor, "component": "u, v",
                                        "change_px": lead.slope_px, "detail": d})[1]
    assert f"fitted: a step of {d['step_px']:.2g} px at {d['radius_px']:.0f} px, the image " \
        f"scale {d['scale_ppm']:.3g} ppm larger beyond it" in said, said
    # every other step line follows the fitted step
    assert all(i in follows for i, f in enumerate(lines)
               if f is not lead and f.regressor.startswith(stats.ZONE)), follows
    cam = run.calibration.camera
    less = leads.zone_without(run.residuals, 0.5, (cam.cx, cam.cy))[0]
    assert not [f for f in line_tests(less, run.calibration, 0.5)
                if f.regressor.startswith(stats.ZONE)]
    # the noise verdict's repeat, where its line follows the step, is the step's
    rep = {"chi2": 371.0, "dof": 156.0, "p_value": 1.3e-19, "rms_px": 0.0069}
    v = noise.NoiseVerdict(NoiseScales(), NoiseScales(), repeat=rep)
    assert "from the catalogue positions" in next(x for x in v.lines() if "repeat" in x)
    v = noise.NoiseVerdict(NoiseScales(), NoiseScales(),
                           repeat=dict(rep, follows=leads.CAUSES["zone"]))
    line = next(x for x in v.lines() if "repeat" in x)
    assert "that follows the radial step of the image scale" in line, line
    assert "not the catalogue positions" in line, line


def test_a_noise_step_in_magnitude_is_grouped_at_its_step_not_wrong_star_by_star():
    """Unseen case ``mag2x`` reduced: faint stars (mag >= 4.5) 2x the stated 0.05 px, bright
    as stated, 300 s PSCE seed 21.  The magnitude bins are quantiles; the step falls inside
    one and was merged at a quantile's edge: coord d4e631d grouped at 4.12 and 4.80 mag
    (x1.04, x1.75, x1.98: the middle group mixed) and the verdict said the σ "wrong star by
    star ~10 % at random within the magnitude groups" (F 2.53, p 4.7e-12; the unseen case's
    discover at s21: edge 4.02, F 3.72).  Each edge is now placed where the two levels beside
    it fit best (``noise_stars._placed``), alike groups merged again: one edge at 4.505 mag
    (the stars' magnitudes about 4.5 are ~0.05 apart), the faint group 1.98 +- 0.015 for 2,
    and no star-by-star spread left (the bright group reads 1.056 +- 0.017 here, without the
    verdict's weighting by the groups; the discover at s21: x0.987 +- 0.016, x2 +- 0.014,
    edge 4.5)."""
    sim = _bag(lambda sim: tracker_errors.renoise(
        sim, lambda m, uv: np.where(m < 4.5, SIGMA, 2.0 * SIGMA), SIGMA, 21), duration=300.0)
    _, sn = _findings(sim, star_noise=True)
    cam = sim.prior.camera
    best = noise_stars.significant_grouping(
        noise_stars.star_groups(sn, (cam.width, cam.height)), 1)
    assert best["by"] == "magnitude" and len(best["edges"]) == 1, best
    assert abs(best["edges"][0] - 4.5) < 0.06, best
    assert abs(best["scales"][1] - 2.0) < 3.0 * best["sigma"][1], best
    assert noise_stars.star_levels(sn, None, noise_stars.group_index(sn, best)) is None


def test_a_lost_lock_is_its_own_first_line_with_when_and_how_often():
    """A glitch: every star of the frames at 100-102 s of a 150 s PSCE bag 40 px off (the
    frames 100.25-101.75 s).  The filter rejects them, re-acquires on a glitched frame,
    rejects the good frames after it and re-acquires again: 2 re-acquisitions, 6 frames
    counted lost, two spans of 3 frames rejected in a row (t from the first frame kept,
    0.75 s: 99.5-100.5 s and 101.5-102.5 s).  The diagnosis says it in a line of its own,
    first (before the counts), with when, how often and what to check; before (coord
    01f1a6b) only a clause of the noise line ("the filter lost lock") and two counts.  A
    run that keeps lock has no entry."""
    def glitch(sim):
        t0 = sim.star_frames[0].stamp_ns
        for f in sim.star_frames:
            if 100.0 <= (f.stamp_ns - t0) * 1e-9 < 102.0:
                f.uv = np.asarray(f.uv, dtype=float) + 40.0
        tracker_errors.renoise(sim, lambda m, uv: SIGMA, SIGMA, 21)

    sim = _bag(glitch, duration=150.0)
    run = evaluate(bag_data_from_simulation(sim), method_spec("psce"),
                   rerun_prior(sim.prior), (), 0.5, keep_residuals=True)
    lock = run.lock_losses()
    assert lock["reinitializations"] == 2 and lock["frames_lost_lock"] == 6, lock
    assert [k for _, _, k in lock["episodes"]] == [3, 3], lock
    (a0, b0, _), (a1, b1, _) = lock["episodes"]
    first = float(np.min(run.residuals["t"])) - sim.star_frames[0].stamp_ns * 1e-9
    # the glitch's frames, t from the first frame kept: within a frame (0.5 s)
    assert a0 == pytest.approx(100.25 - first, abs=0.5) and b1 <= 103.5 - first, lock
    lines = printing.data_quality_lines({"counts": {"frames": 300}, "data_quality": [],
                                         "lost_lock": lock})
    assert lines[0].startswith("lost lock: the filter lost the attitude and re-acquired it "
                               "2 times (6 frames counted lost; rejected in a row at t="
                               f"{a0:.2f}-{b0:.2f} s (3 frames), {a1:.2f}-{b1:.2f} s "
                               "(3 frames), t from the first frame kept)"), lines[0]
    assert "check the bag and the prior at those times" in lines[0]
    assert lines[1].startswith("counts: ")
    clean = evaluate(bag_data_from_simulation(_bag(lambda sim: None, noise_free=False)),
                     method_spec("psce"), rerun_prior(sim.prior), (), 0.5)
    assert clean.lock_losses() is None
    assert printing.data_quality_lines({"counts": {"frames": 300}, "data_quality": []}) == [
        "counts: frames=300"]


def test_no_radial_step_line_on_a_clean_bag():
    """The radial step tests hold their level: a clean 150 s PSCE bag (seed 22, the
    scenario's own 0.05 px noise) has no step line."""
    found = _findings(_bag(lambda sim: None, seed=22, noise_free=False))
    assert not [f for f in found if f.regressor.startswith(stats.ZONE)], found


def test_an_aliased_vibration_is_unexplained_at_its_alias_period():
    """A 7.3-Hz attitude vibration of 0.08 px against the IMU (``tracker_errors.vibration``),
    sampled by the 2-Hz frames: aliased to 0.7 Hz (1.43 s).  The first lines are the frame
    means' periodic ones at the alias's period, their amplitude the truth within 25 %
    (``discover`` on 300 s, seeds 21 / 22: 1.43 s, 0.084 / 0.082 px, H250)."""
    def post(sim):
        tracker_errors.vibration(sim, 0.08, 7.3, 0.3)

    found = _findings(_bag(post, noise_free=False))
    assert found and found[0].regressor.startswith("time (periodic, 1.43 s"), found[:3]
    assert found[0].slope_px == pytest.approx(0.08, rel=0.25)
