"""A noise in the frames' stamps in the filter's measurement covariance (issue 21, H277).

One stamp error ``δt ~ N(0, σ_t²)`` per frame moves all its stars at once, by
``J_t δt`` with ``J_t = ∂uv/∂t = H_attitude R_i_b ω`` (:func:`~stellar_cal_ros.core.
covariance.stamp_column`): the frame's R gains the rank-one ``σ_t² J_t J_tᵀ``
(``--noise-scale stamp=MS``), not an independent per-star term.

* ``J_t`` equals the finite difference of the prediction in the stamp, both prediction paths;
* the update with the common column equals a linear update with the full R (gain, NIS,
  Joseph covariance), numpy and compiled;
* a jittered bag (1 ms rms stamps) replayed with ``stamp=1``: the compiled path equals the
  numpy reference (psce's fused step, the swaying filter's star update), and the stars'
  NIS/dof comes back to 1 (5-8 without it);
* ``stamp`` parses, round-trips through the calibration file's dict, and 0 is the identity.
"""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np
import pytest

from stellar_cal_ros.core import covariance as cov
from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.effects.base import FrameContext
from stellar_cal_ros.methods.frames import bag_data_from_simulation
from stellar_cal_ros.methods.kernel import StarFilter
from stellar_cal_ros.methods.replay import replay
from stellar_cal_ros.sim import tracker_errors
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

jit = pytest.importorskip("stellar_cal_ros.core.jit")


def _jittered(scenario: str, duration: float, seed: int, jitter_ms: float):
    sim = simulate(get_scenario(scenario), duration=duration, seed=seed)
    if jitter_ms:
        tracker_errors.stamp_jitter(sim, jitter_ms * 1e-3, seed)
    return sim, bag_data_from_simulation(sim)


@pytest.fixture(scope="module")
def psce_bag():
    """120 s of psce_rotations (seed 21: two slews), stamps N(0, 1 ms) off their exposures."""
    return _jittered("psce_rotations", 120.0, 21, 1.0)




@pytest.mark.parametrize("compiled", [True, False])
def test_stamp_column_is_the_prediction_s_derivative_in_time(psce_bag, compiled) -> None:
    sim, data = psce_bag
    f = replay(data, sim.prior, "psce", effects=["time_offset"], keep_tables=False).filter
    fr = data.frames[len(data.frames) // 2]
    rng = np.random.default_rng(7)
    u = rng.normal(size=(12, 3)) * 0.05 + f.R_i_b @ f.model._R_imu_st_prior @ [0, 0, 1.0]
    u /= np.linalg.norm(u, axis=1)[:, None]
    omega = np.array([0.03, -0.05, 0.08])  # rad/s: a 5 deg/s slew
    base, h, sigma_t = 0.013, 1e-6, 2e-3

    def pred(b):
        ctx = FrameContext(stamp=fr.stamp_ns * 1e-9)
        return f.model.predict_state(f.theta, u, ctx, f.R_i_b, omega, b, compiled=compiled), ctx

    p0, ctx0 = pred(base)
    fd = (pred(base + h)[0].uv - pred(base - h)[0].uv) / (2 * h)
    got = cov.stamp_column(p0.H_attitude, ctx0.R_i_b, ctx0.omega_b, sigma_t)
    assert np.max(np.abs(fd)) > 100.0  # px/s: the stars move
    np.testing.assert_allclose(got, sigma_t * fd, rtol=0, atol=1e-6 * np.max(np.abs(fd)))


@pytest.mark.parametrize("compiled", [True, False])
@pytest.mark.parametrize("frame_px", [0.0, 0.2])
def test_a_common_column_is_the_full_r(compiled, frame_px) -> None:
    """One column (the stamp's) and three (the stamp's and a frame-common shift's two, H296:
    ``common_columns``): the update equals a linear update with the full R."""
    rng = np.random.default_rng(8)
    n, N = 9, 14
    A = rng.normal(size=(N, N))
    P = A @ A.T / N + np.eye(N) * 1e-3
    H = rng.normal(size=(2 * n, N))
    r = np.repeat(rng.uniform(0.01, 0.1, n), 2)
    H_att = rng.normal(size=(n, 2, 3))
    c = cov.common_columns(H_att, np.eye(3), np.array([0.1, -0.2, 0.3]), 0.3, frame_px
                           ).reshape(2 * n, -1)
    if not frame_px:
        c = c[:, 0]
        np.testing.assert_array_equal(c, cov.stamp_column(
            H_att, np.eye(3), np.array([0.1, -0.2, 0.3]), 0.3).reshape(-1))
    else:
        assert c.shape == (2 * n, 3) and np.all(c[0::2, 1] == frame_px) \
            and np.all(c[1::2, 2] == frame_px) and not c[0::2, 2].any()
    z, h = rng.normal(size=2 * n), np.zeros(2 * n)
    res = cov.iterated_update(P, H, h, z, r, None, cov.UpdatePolicy(), compiled=compiled,
                              common=c)
    C = c.reshape(2 * n, -1)
    dx, Pn, K, nis = cov.linear_update(P, H, z - h, np.diag(r) + C @ C.T)
    assert res.ok
    np.testing.assert_allclose(res.dx, dx, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(res.K, K, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(0.5 * (res.P + res.P.T), Pn, rtol=1e-9, atol=1e-14)
    assert res.nis == pytest.approx(nis, rel=1e-10)


@pytest.mark.parametrize("compiled", [True, False])
def test_the_frame_s_likelihood_holds_the_stamp_s_one_error(compiled) -> None:
    """``joint_correction`` added to the accepted stars' own ``−2 log`` terms (each its
    block of ``S = H P Hᵀ + R + c cᵀ`` and NIS) gives the frame's joint Gaussian ``−2 log``
    likelihood (dense, to rounding); ``frame_logdet`` is its log det; one star: 0.  Numpy
    and the compiled copy (``frame_step``); the terms the stars' sum leaves out are large
    where the stamp's column is (here 5-20x the noise)."""
    from stellar_cal_ros.methods import frame_step

    fn = frame_step._joint_correction if compiled else cov.joint_correction
    rng = np.random.default_rng(9)
    n, N = 11, 9
    A = rng.normal(size=(N, N)) * 0.01
    P = A @ A.T
    H = rng.normal(size=(2 * n, N))
    r = np.repeat(rng.uniform(0.04, 0.06, n) ** 2, 2)
    c = rng.normal(size=2 * n) * 0.3
    S = H @ P @ H.T + np.diag(r) + np.outer(c, c)
    nu = rng.multivariate_normal(np.zeros(2 * n), S)
    blocks = np.array([S[2 * i:2 * i + 2, 2 * i:2 * i + 2] for i in range(n)])
    nu2 = nu.reshape(n, 2)
    own = np.array([nu2[i] @ np.linalg.solve(blocks[i], nu2[i]) for i in range(n)])
    acc = np.ones(n, dtype=bool)
    acc[[2, 7]] = False
    k = np.repeat(acc, 2)
    Sa, va = S[np.ix_(k, k)], nu[k]
    nis_f = float(va @ np.linalg.solve(Sa, va))
    logdet = cov.frame_logdet(P, H[k], r[k], c[k])
    assert logdet == pytest.approx(np.linalg.slogdet(Sa)[1], rel=1e-12)
    got = fn(nis_f, logdet, blocks, own, acc)
    stars = sum(own[i] + np.linalg.slogdet(blocks[i])[1] for i in np.flatnonzero(acc))
    assert got + stars == pytest.approx(nis_f + logdet, rel=1e-10)
    assert got < -10.0  # (the stars' sum counts the shared column once per star)
    one = np.zeros(n, dtype=bool)
    one[4] = True
    single = nu2[4] @ np.linalg.solve(blocks[4], nu2[4])
    assert fn(single, np.linalg.slogdet(blocks[4])[1], blocks, own, one) == pytest.approx(
        0.0, abs=1e-9)


def _equal_runs(a, b, tol_sigma: float) -> None:
    assert a.counters == b.counters
    fa, fb = a.filter, b.filter
    sig = np.sqrt(np.diag(fb.P))[3:3 + fb.P_est]
    assert np.max(np.abs(fa.theta[:fb.P_est] - fb.theta[:fb.P_est]) / sig) <= tol_sigma
    np.testing.assert_allclose(np.diag(fa.P), np.diag(fb.P), rtol=1e-5)
    nis_a, nis_b = (r.stats.current().nis_per_dof()[0] for r in (a, b))
    assert nis_a == pytest.approx(nis_b, rel=1e-6)
    # (the log-likelihood with the frames' stamp correction: the compiled frame_sums' own)
    sa, sb = (r.stats.current() if hasattr(r.stats, "current") else r.stats for r in (a, b))
    assert sa.log_likelihood() == pytest.approx(sb.log_likelihood(), rel=1e-6)


def test_psce_compiled_equals_numpy_and_the_nis_comes_back(psce_bag, monkeypatch) -> None:
    """psce (the fused compiled step): with ``stamp=1`` the compiled run equals the numpy
    reference within the start-up's amplification (test_compiled_step's 2e-3 σ), and the
    stars' NIS/dof is ~1 (measured: 1.03 with it, 6.6 without, seed 21, 60 s; σ of a
    frame-correlated NIS/dof over 60 s ≈ 0.05)."""
    sim, data = psce_bag
    runs = {}
    for compiled in (True, False):
        monkeypatch.setattr(StarFilter, "compiled_step", compiled)
        runs[compiled] = replay(data, sim.prior, "psce", noise=NoiseScales(stamp_ms=1.0),
                                keep_tables=False)
    _equal_runs(runs[True], runs[False], 2e-3)
    monkeypatch.setattr(StarFilter, "compiled_step", True)
    without = replay(data, sim.prior, "psce", keep_tables=False)
    assert without.stats.current().nis_per_dof()[0] > 3.0
    assert runs[True].stats.current().nis_per_dof()[0] == pytest.approx(1.0, abs=0.15)


def test_swaying_compiled_star_update_equals_numpy(monkeypatch) -> None:
    """The swaying-base filter's compiled star update (``frame_step.star_update``) with a
    stamp noise equals its numpy update, and its NIS/dof comes back to ~1."""
    from stellar_cal_ros.diagnosis.injection import clean_simulation
    from stellar_cal_ros.methods.swaying import SwayingFilter

    sim, _ = clean_simulation("swaying_base", False, 22, 60.0)  # (the model's own effects)
    tracker_errors.stamp_jitter(sim, 1e-3, 22)
    data = bag_data_from_simulation(sim)
    runs = {}
    for compiled in (True, False):
        monkeypatch.setattr(SwayingFilter, "compiled_star_update", compiled)
        monkeypatch.setattr(SwayingFilter, "compiled_frame", compiled)
        runs[compiled] = replay(data, sim.prior, "swaying_base",
                                noise=NoiseScales(stamp_ms=1.0), keep_tables=False)
    _equal_runs(runs[True], runs[False], 1e-3)
    assert runs[True].stats.current().nis_per_dof()[0] == pytest.approx(1.0, abs=0.15)


def test_stamp_noise_parses_and_round_trips() -> None:
    s = NoiseScales.parse("star=1.2,stamp=0.8")
    assert s.stamp_ms == 0.8 and not s.identity
    assert s.as_dict()["stamp_sigma_ms"] == 0.8
    assert NoiseScales.from_dict(s.as_dict()) == s
    assert NoiseScales(stamp_ms=0.0).identity and "stamp_sigma_ms" not in NoiseScales().as_dict()
    with pytest.raises(ValueError, match="stamp noise"):
        NoiseScales.parse("stamp=-1")
    # a frame-common shift (H296): ``frame=PX``, saved as ``frame_sigma_px``
    f = NoiseScales.parse("stamp=0.8,frame=0.04")
    assert (f.stamp_ms, f.frame_px) == (0.8, 0.04) and f.as_dict()["frame_sigma_px"] == 0.04
    assert NoiseScales.from_dict(f.as_dict()) == f
    assert NoiseScales(frame_px=0.0).identity and "frame_sigma_px" not in NoiseScales().as_dict()
    with pytest.raises(ValueError, match="frame-common noise"):
        NoiseScales.parse("frame=-0.1")


@pytest.fixture(scope="module")
def sway_jitter_verdict():
    """Unseen case ``sway_jitter`` s22 (300-s swaying base, stamps N(0, 1 ms) off): the
    noise verdict of the model's run as a round makes it, and the lines it told."""
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.injection import clean_simulation
    from stellar_cal_ros.diagnosis.noise_runs import measure
    from stellar_cal_ros.diagnosis.parallel import Runs, Task

    sim, _ = clean_simulation("swaying_base", False, 22, 300.0)
    tracker_errors.stamp_jitter(sim, 1e-3, 22)
    runs = Runs(bag_data_from_simulation(sim), method_spec("swaying_base"), 0.5)
    runs.noise = NoiseScales()
    prior = rerun_prior(sim.prior)
    # the model's run as a round makes it (its residuals kept: the stamps' test reads them)
    base = runs.run_all([Task("model", prior, (), keep_residuals=True, star_noise=True)])[
        "model"]
    told: list[str] = []
    return measure(runs, prior, (), base, told.append, ("gyro", "accel")), told


def test_the_noise_verdict_applies_the_stamps_it_names_and_the_nis_comes_back(
        sway_jitter_verdict) -> None:
    """Unseen case ``sway_jitter`` s22: the baseline is too far off for the noise (NIS/dof
    5.86) and the verdict named the stamps but took the noise 'as stated' (H263).  Now the
    model is run again with that noise in each frame's R and the verdict made on that run:
    its first line names the stamps and says ``use --noise-scale stamp=X``, the noise
    applied holds them, and the NIS/dof comes back to ~1 (H263's seeds 21-23: the stamps'
    size read back 0.97-1.04 ms, σ ≈ 0.05).
    Fails on main (taken as stated: ``NoiseScales`` has no ``stamp_ms``)."""
    v, _ = sway_jitter_verdict
    j = v.stamp_jitter
    assert not v.skipped and j is not None and "applied_ms" in j, (v.skipped, j)
    assert j["applied_ms"] == pytest.approx(1.0, abs=0.15)
    assert v.applied.stamp_ms == j["applied_ms"] and v.rescaled
    assert j["nis_before"] > 4.0 and j["nis_after"] == pytest.approx(1.0, abs=0.15), j
    first = v.lines()[0]
    assert first.startswith("the frames' stamps jitter ") and first.endswith(
        f"use --noise-scale stamp={j['applied_ms']:.2g}"), first
    assert v.as_json()["applied"]["stamp_sigma_ms"] == j["applied_ms"]


def test_the_stamps_nis_before_in_the_json_is_the_nis_dof_printed(sway_jitter_verdict) -> None:
    """``noise.stamp_jitter.nis_before`` is the NIS/dof the 'too far off' line printed for
    the same run (at the stars' measured σ, :func:`~stellar_cal_ros.diagnosis.noise.misfit`)
    and the one the stamps' line prints; ``nis_share`` is of that number (``nis_before -
    nis_share`` is the 'without it' printed).  Fails on main (the raw NIS/dof was stored,
    the one at the measured σ printed)."""
    v, told = sway_jitter_verdict
    j = v.as_json()["stamp_jitter"]
    far = [t for t in told if "that the model does not state" in t]
    assert far, told  # the first: the model's run's
    printed, without = re.search(r"it makes NIS/dof ([0-9.e+-]+)(?: at the stars' measured "
                                 r"sigma, x[0-9.e+-]+)?, ([0-9.e+-]+) without it", far[0]).groups()
    assert printed == f"{j['nis_before']:.3g}", (far[0], j)
    assert without == f"{j['nis_before'] - j['nis_share']:.3g}", (far[0], j)
    assert f"NIS/dof {j['nis_before']:.3g} -> {j['nis_after']:.3g}" in v.lines()[0]


@pytest.fixture(scope="module")
def sway_runs():
    """60 s of the swaying base (seed 22), stamps N(0, 1 ms) and N(0, 2 ms) off, each
    replayed with ``stamp=1`` in R (the residual tables kept)."""
    from stellar_cal_ros.diagnosis.injection import clean_simulation

    out = {}
    for ms in (1.0, 2.0):
        sim, _ = clean_simulation("swaying_base", False, 22, 60.0)
        tracker_errors.stamp_jitter(sim, ms * 1e-3, 22)
        out[ms] = replay(bag_data_from_simulation(sim), sim.prior, "swaying_base",
                         noise=NoiseScales(stamp_ms=1.0))
    return out


def _motion(r, stamp: float):
    """The stamps' line's test on ``r``'s window, its null's stamp noise ``stamp`` (s)."""
    from stellar_cal_ros.diagnosis import stats

    cam = r.calibration.camera
    return stats.stamp_line(r.residuals, stats.evaluation_mask(r.residuals, 0.5),
                            (cam.fx, cam.fy), (cam.cx, cam.cy), r.calibration.R_imu_st, stamp)


def test_the_stamps_line_tests_a_spread_beyond_the_stamp_noise_in_r(sway_runs) -> None:
    """The stamps' line ('... vs image rate, frame to frame') on a run with the stamps'
    noise in its R: its null holds that noise (``stats.stamp_noise``'s ``sigma_t``, the
    stars' covariance taken without its share), so the stamps the run states are no line
    (1 ms stated, 1 ms true: p 0.86; read against no stamp noise, as before, p 3.8e-8 and
    the line printed beside the noise verdict's stamps: unseen cases ``jitter`` s21,
    ``sway_jitter`` s21/s22); a noise beyond the stated one is (2 ms true, 1 ms stated:
    p 0.0079, its size read 2.1 ms).  The line tests take the stated noise from the run's
    calibration.  Fails on main (no line left beside the stamps: there the line prints)."""
    from stellar_cal_ros.diagnosis import stats
    from stellar_cal_ros.diagnosis.output import line_tests

    r = sway_runs[1.0]
    lines = line_tests(r.residuals, r.calibration, 0.5)
    assert not [f for f in lines if f.regressor.startswith(stats.MOTION)], lines
    stated, before = _motion(r, 1e-3), _motion(r, 0.0)
    assert stated.p_value > 0.1 and before.p_value < 1e-6, (stated, before)
    assert "1 ms stated" in stated.regressor
    beyond = _motion(sway_runs[2.0], 1e-3)
    assert beyond.p_value < 0.01, beyond
    assert float(beyond.regressor.split(": ")[1].split(" ms")[0]) == pytest.approx(2.0, abs=0.3)


def test_a_twin_renders_the_stamp_noise_it_is_given(psce_bag) -> None:
    """A twin (``twin``, ``--verify``) of a run with ``stamp=1`` renders its frames' stamps
    1 ms off (``sim.tracker_errors.stamp_errors``): replayed without it the stars' NIS/dof
    is far off as on the user's bag (measured 7.4 there), with it ~1.  Fails on main (the
    twin's stamps exact: NIS/dof ~1 without the stamps)."""
    from stellar_cal_ros.diagnosis.twin import make_twin

    sim, data = psce_bag
    cal = replay(data, sim.prior, "psce", noise=NoiseScales(stamp_ms=1.0),
                 keep_tables=False).calibration
    twin = make_twin(data, cal, {}, seed=3, method="psce")
    assert twin.noise.stamp_ms == 1.0
    without = replay(twin.data, twin.prior, "psce", keep_tables=False)
    with_ = replay(twin.data, twin.prior, "psce", noise=NoiseScales(stamp_ms=1.0),
                   keep_tables=False)
    assert without.stats.current().nis_per_dof()[0] > 3.0
    assert with_.stats.current().nis_per_dof()[0] == pytest.approx(1.0, abs=0.15)


def test_a_time_offsets_ratio_beside_the_stamp_noise_is_its_score_test():
    """Unseen case ``sway_jitter`` s22 (300-s swaying base, stamps N(0, 1 ms), the verdict's
    ``stamp=0.97`` in R): discover added time_offset +0.065 +- 0.040 ms (1.6 σ) with 'score
    23.3, p = 4e-05', its ratio Λ = 2Δℓ of the two runs.  The score test of the same run
    read LM 4.24 (its information 0.056 ms on the window, the re-run's 0.040 over the run:
    the stamps are in both), but ℓ summed the stars of a frame as independent, each with
    its share of the stamp's one error: the time offset, whose columns are the stamp's,
    gained the likelihood of every star.  With the frame's likelihood
    (``covariance.joint_correction``) Λ is the score test's to within their spread
    (χ²₁-sized: both are 2Δℓ to first order; the ratio is prequential, its τ learnt as
    the window goes: no larger).  Fails on main 6c738a9 (Λ 23.25)."""
    from stellar_cal_ros.diagnosis import screening
    from stellar_cal_ros.diagnosis.discover import (
        Reference,
        candidate_prior,
        method_spec,
        rerun_prior,
    )
    from stellar_cal_ros.diagnosis.injection import clean_simulation
    from stellar_cal_ros.diagnosis.parallel import Runs, Task

    sim, _ = clean_simulation("swaying_base", False, 22, 300.0)
    tracker_errors.stamp_jitter(sim, 1e-3, 22)
    runs = Runs(bag_data_from_simulation(sim), method_spec("swaying_base"), 0.5)
    runs.noise = NoiseScales(stamp_ms=0.97)
    prior = rerun_prior(sim.prior)
    out = runs.run_all([
        Task("base", prior, (), screen=("time_offset",)),
        Task("time_offset", candidate_prior(prior, "time_offset", sim.prior), ("time_offset",),
             candidate=True)])
    base, run = out["base"], out["time_offset"]
    lm = screening.collect([base])["time_offset"].statistic
    lam = Reference.of(base).compare(run, 1)[0]
    sl = run.slices["time_offset"]
    z = run.theta[sl[0]] / np.sqrt(run.P[sl[0], sl[0]])
    assert lm == pytest.approx(4.2, abs=0.3) and abs(z) == pytest.approx(1.62, abs=0.1)
    # (measured: Λ 1.23 against z² 2.63 and LM 4.20; main 23.25; χ²₁'s SD is √2)
    assert abs(lam - z * z) < 2.0 * math.sqrt(2.0) and lam < lm, (lam, lm, z)


def _round_one(seed: int, post) -> tuple:
    """A 300-s psce bag (``post`` applied) and the model without effects run on it, as
    discover's first round: ``(run, the stamps' test, noise.stamp_jitter at its misfit)``."""
    from stellar_cal_ros.diagnosis import clock, noise, stats
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.runstats import evaluate

    sc = dataclasses.replace(get_scenario("psce_rotations"), centroid_noise_px=0.0)
    sim = simulate(sc, duration=300.0, seed=seed)
    post(sim)
    tracker_errors.renoise(sim, lambda m, uv: 0.05, 0.05, seed)
    run = evaluate(bag_data_from_simulation(sim), method_spec("psce"), rerun_prior(sim.prior),
                   (), 0.5, keep_residuals=True, star_noise=True)
    cam = run.calibration.camera
    share = clock.stamp_share(run.residuals, stats.evaluation_mask(run.residuals, 0.5),
                              (cam.fx, cam.fy), (cam.cx, cam.cy), run.calibration.R_imu_st)
    s, nis = noise.misfit(run, run.star_noise)
    return run, share, noise.stamp_jitter(run, run.calibration, 0.5, s, nis)


def test_a_smear_is_not_named_as_the_frames_stamp_noise():
    """Unseen case ``smear15`` s22 (a centroid bias along each star's motion growing with its
    speed squared, 0.15 px at the run's 95th-percentile speed; no stamp noise), the model
    without effects as discover's first round runs it: the frames' offsets along the motion
    follow their speed (the smear's coefficient fitted on their differences, -0.77 ms ± 0.07
    at 202 px/s: 0.15 px / 202 px/s = 0.74 ms), so the stamps' test read a 0.14 ms noise at
    p 0.0041 and the noise verdict applied it (NIS/dof 1.3 -> 1.18; coord 0a04010 since H299's
    joint likelihood).  Beside the smear's column (``clock.stamp_share``, the clock's smear
    part): p 0.040, no stamp noise named.  The stamps' own test where the frames carry a
    stamp noise (unseen case ``jitter`` s22, N(0, 1 ms): 0.84 ms, p 9e-15) is the one
    without the smear's column, bit for bit: a random stamp error does not follow the speed
    (the smear's coefficient beside it -1.11 ± 0.78 ms).  Fails on coord 08e0444 (p 0.0041,
    the 0.14 ms named)."""
    smear = _round_one(22, lambda sim: tracker_errors.speed_squared_smear(sim, 0.15))
    assert smear[1] is not None and smear[1][0] > 0.01, smear[1]
    assert smear[2] is None, smear[2]

    from stellar_cal_ros.diagnosis import stats

    run, share, named = _round_one(22, lambda sim: tracker_errors.stamp_jitter(sim, 1e-3, 22))
    cam = run.calibration.camera
    found = stats.accepted_offsets(run.residuals, stats.evaluation_mask(run.residuals, 0.5),
                                   (cam.fx, cam.fy), (cam.cx, cam.cy), run.calibration.R_imu_st)
    assert share[:2] == stats.stamp_noise(*found[1][:5]), share
    assert share[0] < 1e-10 and share[1] == pytest.approx(1e-3, abs=0.25e-3), share
    assert named is not None and named["ms"] == pytest.approx(share[1] * 1e3)
