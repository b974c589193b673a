"""A gyro bias that wanders: the noise scales' ``gyro_bias_rw`` (issue 21 item 1).

The model's gyro bias is a constant (its effect states no random walk); a bag whose bias
wanders (gyro bias instability, :func:`~stellar_cal_ros.sim.tracker_errors.gyro_bias_walk`,
the unseen case ``bias_walk10``'s) leaves the stars' innovations over-dispersed.
``--noise-scale gyro_bias_rw=D`` states the walk (deg/h/√h): the process noise of the
``gyro_bias`` block, on the numpy reference and the compiled step alike.
"""

from __future__ import annotations

import numpy as np
import pytest

from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.core.units import DEG_PER_HOUR
from stellar_cal_ros.methods.frames import bag_data_from_simulation
from stellar_cal_ros.methods.kernel import StarFilter
from stellar_cal_ros.methods.replay import replay
from stellar_cal_ros.sim import tracker_errors
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

#: the unseen case bias_walk10's walk, deg/h/√h per axis
WALK = 3.0


def test_gyro_bias_rw_parses_stores_and_says_it_rescaled():
    s = NoiseScales.parse("gyro_bias_rw=2.6")
    assert s.gyro_bias_rw == 2.6 and not s.identity and s.star == s.gyro == 1.0
    assert s.as_dict()["gyro_bias_rw_deg_h_sqrth"] == 2.6
    assert NoiseScales.from_dict(s.as_dict()) == s
    assert "gyro_bias_rw_deg_h_sqrth" not in NoiseScales().as_dict()  # 0: as today
    assert NoiseScales.from_dict(NoiseScales().as_dict()).gyro_bias_rw == 0.0
    for bad in ("gyro_bias_rw=-1", "gyro_bias_rw=nan", "gyro_bias_rw=x"):
        with pytest.raises(ValueError):
            NoiseScales.parse(bad)


@pytest.fixture(scope="module")
def walking():
    """A 150 s psce_rotations bag (seed 21) whose gyro bias walks at :data:`WALK`."""
    sim = simulate(get_scenario("psce_rotations"), duration=150.0, seed=21)
    tracker_errors.gyro_bias_walk(sim, WALK, 21)
    return sim, bag_data_from_simulation(sim)


def _run(walking, walk, compiled, monkeypatch):
    sim, data = walking
    monkeypatch.setattr(StarFilter, "compiled_step", compiled)
    noise = NoiseScales(gyro_bias_rw=walk) if walk else None
    return replay(data, sim.prior, "psce", noise=noise, keep_tables=False)


def test_the_walk_is_the_gyro_bias_blocks_process_noise_on_both_paths(walking, monkeypatch):
    """The stated walk is the ``gyro_bias`` block's q (and nothing else's); the compiled step
    and the numpy reference give the same run with it, and the run with the truth's walk
    fits where the constant bias does not (NIS/dof, the YAML's consistency block)."""
    runs = {(walk, compiled): _run(walking, walk, compiled, monkeypatch)
            for walk, compiled in ((0.0, False), (WALK, False), (WALK, True))}
    flt0, flt = runs[0.0, False].filter, runs[WALK, False].filter
    sl = flt.model.slices["gyro_bias"]
    q = (WALK * DEG_PER_HOUR / 60.0) ** 2
    np.testing.assert_allclose(flt._q_diag[3 + sl.start:3 + sl.stop], q, rtol=1e-12)
    other = np.ones(len(flt._q_diag), dtype=bool)
    other[3 + sl.start:3 + sl.stop] = False
    np.testing.assert_array_equal(flt._q_diag[other], flt0._q_diag[other])
    assert not np.any(flt0._q_diag[3 + sl.start:3 + sl.stop])
    fast = runs[WALK, True].filter
    sig = np.sqrt(np.diag(flt.P))[:flt.theta.size]
    assert fast.model.compiled_chain() is not None
    assert np.max(np.abs(fast.theta - flt.theta) / sig) <= 2e-3
    cons0 = runs[0.0, False].calibration.extra["consistency"]
    cons = runs[WALK, False].calibration.extra["consistency"]
    # measured (seed 21, 150 s): NIS/dof 1.28 without the walk, 0.996 with it
    assert cons0["nis_per_dof"] > 1.2 and abs(cons["nis_per_dof"] - 1.0) < 0.1
    assert not cons0["noise_rescaled"] and cons["noise_rescaled"]
    assert cons["noise"]["gyro_bias_rw_deg_h_sqrth"] == WALK


def test_replay_takes_the_walk_and_its_result_says_so(walking, tmp_path, capsys):
    """``replay --noise-scale gyro_bias_rw=3``: the terminal and the result's consistency
    block say the gyro bias was given a random walk (the CLI in-process)."""
    from stellar_cal_ros.cli import main
    from stellar_cal_ros.io.calibration import load_calibration
    from stellar_cal_ros.sim.world import write_simulation

    sim, _ = walking
    bag = tmp_path / "walk.mcap"
    write_simulation(sim, bag)
    capsys.readouterr()
    rc = main(["replay", str(bag), "--method", "psce", "--prior",
               str(tmp_path / "walk.prior.yaml"), "-o", str(tmp_path / "r.yaml"), "-q",
               "--noise-scale", f"gyro_bias_rw={WALK:g}"])
    out = capsys.readouterr()
    assert rc == 0, out.err[-2000:]
    assert "gyro bias random walk 3 deg/h/sqrt(h)" in out.out
    cons = load_calibration(tmp_path / "r.yaml").extra["consistency"]
    assert cons["noise_rescaled"] and cons["noise"]["gyro_bias_rw_deg_h_sqrth"] == WALK
    assert abs(cons["nis_per_dof"] - 1.0) < 0.1


def test_the_swaying_filter_takes_the_walk_in_place_of_its_gauss_markov_bias():
    """swaying_base holds the gyro bias as a Gauss–Markov process (τ 1 day): a stated walk
    replaces it (it was silently ignored: q 0 on the block) and leaves the accelerometer's."""
    from stellar_cal_ros.methods.swaying import SwayingConfig, SwayingFilter

    sim = simulate(get_scenario("swaying"), duration=20.0, seed=21)
    data = bag_data_from_simulation(sim)
    flts = {}
    for walk in (0.0, WALK):
        noise = NoiseScales(gyro_bias_rw=walk) if walk else None
        flts[walk] = replay(data, sim.prior, "swaying_base", noise=noise,
                            keep_tables=False).filter
    assert isinstance(flts[WALK], SwayingFilter)
    sl = flts[WALK].model.slices["gyro_bias"]
    np.testing.assert_allclose(flts[WALK].q_theta[sl], (WALK * DEG_PER_HOUR / 60.0) ** 2)
    assert np.all(np.isinf(flts[WALK].tau[sl])) and not np.any(flts[WALK].gm_sigma[sl])
    assert np.all(flts[0.0].tau[sl] == SwayingConfig().gauss_markov["gyro_bias"][0])
    other = np.ones(len(flts[WALK].tau), dtype=bool)
    other[sl] = False
    np.testing.assert_array_equal(flts[WALK].tau[other], flts[0.0].tau[other])
    np.testing.assert_array_equal(flts[WALK].gm_sigma[other], flts[0.0].gm_sigma[other])


# ------------------------------------------------------------- the diagnosis measures it
#: the noise seed of the diagnosis's bags (seed 21's realized walk is 2.05 / 1.49 deg/h/√h
#: over 15 / 30 s blocks, far below its density: a test of the estimate against the
#: density wants a realization near it; seed 22's: 3.08 / 3.35, doc/benchmarks.md)
SEED = 22


def _realized(sim, walk: np.ndarray, block: float) -> float:
    """The density (deg/h/√h) of the walk's increments over ``block`` s, RMS of the axes."""
    t = np.asarray(sim.imu.stamp_ns, dtype=float) * 1e-9
    idx = np.searchsorted(t - t[0], np.arange(0.0, t[-1] - t[0], block))
    inc = np.diff(walk[idx], axis=0)
    return float(np.sqrt(np.mean(inc**2) / block) / DEG_PER_HOUR * 60.0)


@pytest.fixture(scope="module")
def walking22():
    """A 150 s psce_rotations bag (seed :data:`SEED`), its bias walking at :data:`WALK`."""
    sim = simulate(get_scenario("psce_rotations"), duration=150.0, seed=SEED)
    walk = tracker_errors.gyro_bias_walk(sim, WALK, SEED)
    return sim, bag_data_from_simulation(sim), walk


def test_the_diagnosis_names_the_walk_and_its_density(walking22, tmp_path):
    """``diagnose`` measures the walk (ML over its density, beyond the white gyro noise),
    says it as noise with the value to state, judges the noise again with it and tests the
    candidates with it: no physical effect nor 'unexplained' lead (main: "the stars see
    more attitude motion than the gyro's noise explains", no density)."""
    from stellar_cal_ros.diagnosis.run import diagnose

    sim, data, walk = walking22
    s = diagnose(data, sim.prior, "psce", [], tmp_path / "d", plots=False, verbose=False,
                 workers=0)
    noise = s["noise"]
    lines = [x for x in noise["verdict"] if x.startswith("the gyro bias wanders")]
    assert lines, noise["verdict"]
    w = noise["gyro_bias_rw"]
    d, sd = w["deg_h_sqrth"], w["sigma"]
    assert w["accepted"] and w["p_value"] < w["alpha"] and w["over_white_gyro"] > 0
    # a walk's bias estimate does not follow the rate (noise_runs.walk_motion; measured
    # min p 0.54 over the axes on this bag with 3.7 deg/h/sqrt(h))
    assert min(w["motion_p"]) > 0.05, w
    # measured (seed 22): 3.7 +- 0.70 deg/h/sqrt(h); the realized walk 3.08 / 3.35 (15 / 30 s)
    assert abs(d - WALK) < 3 * sd and abs(d - _realized(sim, walk, 15.0)) < 3 * sd
    assert f"~{d:.2g} +- {sd:.2g} deg/h/sqrt(h)" in lines[0]
    assert lines[0].endswith(f"use --noise-scale gyro_bias_rw={d:.2g}")
    assert noise["applied"]["gyro_bias_rw_deg_h_sqrth"] == d and noise["rescaled"]
    assert "skipped" not in noise and "motion_beyond_noise" not in noise  # judged with it
    assert not any(c["status"] == "ranked" and c.get("significant")
                   for c in s.get("candidates", []))
    assert not s["unexplained"], s["unexplained"]


def test_a_clean_bag_is_not_searched_and_a_forced_search_takes_no_walk(monkeypatch):
    """A clean bag is neither far off nor beyond its gyro samples: no search, the verdict
    as before.  The search forced on it finds its maximum at the floor (a constant bias) and
    takes nothing."""
    from stellar_cal_ros.diagnosis import noise_runs
    from stellar_cal_ros.diagnosis.run import measure_bag

    sim = simulate(get_scenario("psce_rotations"), duration=150.0, seed=SEED)
    data = bag_data_from_simulation(sim)
    v = measure_bag(data, sim.prior, "psce", [], NoiseScales())
    assert v.walk is None and "gyro_bias_rw" not in v.as_json()
    assert v.lines()[-1].startswith("noise as stated"), v.lines()
    monkeypatch.setattr(noise_runs, "walk_asked", lambda *a: True)
    forced = measure_bag(data, sim.prior, "psce", [], NoiseScales())
    assert forced.walk is not None and not forced.walk["accepted"], forced.walk
    assert forced.applied == v.applied and forced.lines() == v.lines()


def test_diagnose_takes_the_noise_scale_option(walking22, tmp_path, capsys):
    """``diagnose --noise-scale gyro_bias_rw=3`` runs the rounds with the walk (the same
    parser as replay's): with ``--noise stated`` the noise block is the one given."""
    import json

    from stellar_cal_ros.cli import main
    from stellar_cal_ros.sim.world import write_simulation

    sim, _, _ = walking22
    bag = tmp_path / "walk.mcap"
    write_simulation(sim, bag)
    rc = main(["diagnose", str(bag), "--calibration", str(tmp_path / "walk.prior.yaml"),
               "--method", "psce", "-o", str(tmp_path / "d"), "--no-plots", "--workers", "0",
               "--noise", "stated", "--noise-scale", f"gyro_bias_rw={WALK:g}"])
    out = capsys.readouterr()
    assert rc == 0, out.err[-2000:]
    noise = json.loads((tmp_path / "d" / "diagnosis.json").read_text())["noise"]
    assert noise["applied"]["gyro_bias_rw_deg_h_sqrth"] == WALK and noise["rescaled"]
    assert main(["diagnose", str(bag), "--calibration", str(tmp_path / "walk.prior.yaml"),
                 "--method", "psce", "-o", str(tmp_path / "e"),
                 "--noise-scale", "gyro_bias_rw=-1"]) == 1
    assert "gyro bias random walk must be >= 0" in capsys.readouterr().err


def test_a_gyro_error_that_follows_the_rate_is_not_taken_for_a_walk():
    """The z gyro 500 ppm high for positive rates and low for negative (``gsf_asym``'s IMU)
    on the clean psce bag (200 s, seed 21): the model is far off, and a walk of ~42
    deg/h/√h explains the stars' misfit (p = 0, +140 over white gyro noise), but the walk's
    z bias estimate follows the rate (:func:`~stellar_cal_ros.diagnosis.noise_runs.
    walk_motion`: p 6.5e-10 on z, 0.41 / 0.31 on x / y), so it is not taken and the noise
    is as without it.  Fails on f405315 (the walk accepted; 29 deg/h/√h on the 300-s bag)."""
    from stellar_cal_ros.diagnosis.injection import clean_simulation
    from stellar_cal_ros.diagnosis.run import measure_bag

    sim, model = clean_simulation("psce", False, 21, 200.0)
    w = np.asarray(sim.imu.angular_velocity, dtype=float).copy()
    w[:, 2] *= 1.0 + 500e-6 * np.sign(w[:, 2])
    sim.imu.angular_velocity = w
    v = measure_bag(bag_data_from_simulation(sim), sim.prior, "psce", list(model),
                    NoiseScales())
    walk = v.walk
    assert walk is not None and walk["p_value"] < walk["alpha"], walk  # the walk fits ...
    assert not walk["accepted"], walk  # ... but follows the motion
    assert walk["motion_p"][2] < 1e-6 and min(walk["motion_p"][:2]) > 0.01, walk
    assert walk["why"].startswith("its z bias estimate follows the gyro's rate"), walk
    # the bag's head temperature (0.78 deg C over the window) does not explain it beside the
    # rate (walk_motion's temperature columns: p 0.46 on z)
    assert walk["follows"] == "rate" and "beside it the head temperature p = " in walk["why"]
    assert v.applied.gyro_bias_rw == 0.0 and v.skipped
    # the refused walk is said on the terminal (and in the report), after the skip: what
    # was searched, its value and why (before: in diagnosis.json's gyro_bias_rw alone)
    lines = v.lines()
    assert lines[0].startswith("not measured: ") and lines[1] == (
        f"a gyro bias random walk was searched (the model states none): "
        f"~{walk['deg_h_sqrth']:.3g} +- {walk['sigma']:.2g} deg/h/sqrt(h) fits best "
        f"(p = {walk['p_value']:.2g}) but is not taken: {walk['why']} "
        "(noise.gyro_bias_rw in diagnosis.json)"), lines
    assert "not taken: its z bias estimate follows the gyro's rate (p = " in lines[1]


def test_a_tracker_wobble_is_not_taken_for_a_walk():
    """The tracker wobbling 0.1 px (5 arcsec) with a 45 s period against the IMU, which no
    gyro sees (unseen case ``wobble``, an effect outside the library), on the clean psce bag
    (200 s, seed 21): the model is far off and a walk explains the stars' misfit, but the
    walk's bias estimate comes back with the wobble's period (Fisher's g on its 5-s
    increments, :func:`~stellar_cal_ros.diagnosis.noise_runs.comes_back`), so it is not
    taken.  Fails on 43ed2dc (a walk of ~10 deg/h/sqrt(h) taken on the 300-s bag, no line)."""
    from stellar_cal_ros.diagnosis.injection import clean_simulation
    from stellar_cal_ros.diagnosis.run import measure_bag

    sim, model = clean_simulation("psce", False, 21, 200.0)
    t0 = sim.star_frames[0].stamp_ns
    for f in sim.star_frames:
        ph = 2.0 * np.pi * (f.stamp_ns - t0) * 1e-9 / 45.0
        f.uv = np.asarray(f.uv, dtype=float) + 0.1 * np.array([np.sin(ph), np.cos(ph)])
    v = measure_bag(bag_data_from_simulation(sim), sim.prior, "psce", list(model),
                    NoiseScales())
    walk = v.walk
    assert walk is not None and walk["p_value"] < walk["alpha"], walk  # the walk fits ...
    assert not walk["accepted"], walk  # ... but comes back every 45 s
    assert min(walk["periodic_p"]) < 1e-4, walk
    assert "bias estimate comes back every" in walk["why"], walk
    period = float(walk["why"].split("comes back every ")[1].split(" s")[0])
    assert 38.0 < period < 55.0, walk  # the wobble's 45 s, within the ordinates' spacing
    assert v.applied.gyro_bias_rw == 0.0


def test_fisher_g_holds_its_level_on_white_series_and_finds_a_period():
    """:func:`~stellar_cal_ros.diagnosis.stats.fisher_g` on 55 white samples (the 5-s
    increments of a 300-s walk): the rate below 1 % is 1 % (2 000 draws, ±0.45 % at 2σ),
    and a sinusoid of amplitude 2 in unit noise with a 9.2-sample period is found (p < 1e-6)
    at its period."""
    from stellar_cal_ros.diagnosis.stats import fisher_g

    rng = np.random.default_rng(7)
    ps = np.array([fisher_g(rng.standard_normal(55))[0] for _ in range(2000)])
    assert abs(np.mean(ps < 0.01) - 0.01) < 0.0045, np.mean(ps < 0.01)
    assert abs(np.mean(ps < 0.1) - 0.1) < 0.0135, np.mean(ps < 0.1)
    t = np.arange(55)
    p, k = fisher_g(2.0 * np.sin(2.0 * np.pi * t / 9.2) + rng.standard_normal(55))
    assert p < 1e-6 and k == 6, (p, k)


def test_a_refused_walk_is_said_and_one_not_found_is_not():
    """The verdict's lines with a walk refused by a rival effect (beats_rivals' record),
    by the motion guard, and with a walk the search did not find (no line: its own test
    decided, as on a far-off model whose walk has no maximum)."""
    from stellar_cal_ros.diagnosis.noise import NoiseVerdict

    def verdict(walk):
        v = NoiseVerdict(NoiseScales(), NoiseScales(), star_sigma=0.01)
        v.walk = walk
        return v.lines()

    base = {"deg_h_sqrth": 0.87, "sigma": 0.21, "p_value": 1e-5, "alpha": 0.005,
            "accepted": False}
    rival = dict(base, rival={"effect": "time_offset", "parameters": 1, "qaic_gain": 90.0,
                              "walk_qaic_gain": 40.0},
                 why="time_offset explains more (90 against 40 in penalised likelihood)")
    lines = verdict(rival)
    assert lines[0] == ("a gyro bias random walk was searched (the model states none): "
                        "~0.87 +- 0.21 deg/h/sqrt(h) fits best (p = 1e-05) but is not "
                        "taken: time_offset explains more (90 against 40 in penalised "
                        "likelihood) (noise.gyro_bias_rw in diagnosis.json)"), lines
    assert lines[1].startswith("noise as stated ("), lines
    # the terminal and the report print the verdict's lines
    from stellar_cal_ros.diagnosis.printing import noise_lines
    from stellar_cal_ros.diagnosis.report_html import _discovery_html

    summary = {"noise": {"verdict": lines}}
    assert noise_lines(summary)[0] == "noise: " + lines[0]
    assert "fits best (p = 1e-05) but is not taken: time_offset explains more" in \
        _discovery_html(summary)
    moved = dict(base, motion_p=[0.4, 0.5, 8e-16],
                 why="its z bias estimate follows the gyro's rate (p = 8e-16): ...")
    assert verdict(moved)[0].startswith(
        "a gyro bias random walk was searched (the model states none): ~0.87 +- 0.21 "
        "deg/h/sqrt(h) fits best (p = 1e-05) but is not taken: its z bias estimate "
        "follows"), verdict(moved)
    # a walk the search itself refused (bias_walk seed 26: 0.435 +- 0.125, p 4.8e-13, white
    # gyro noise x2.39 fitting as well; the clean swaying bag's far-off first round: 0.112,
    # white x27.3) is not said: its own tests decided
    white = dict(base, why="white gyro noise x2.39 fits as well (by 0.616 in log-likelihood)")
    for lost in (white, dict(base, p_value=0.3, why="not significant (p = 0.3)"),
                 dict(base, sigma=None, why="no maximum in range"), None):
        assert not any("random walk was searched" in x for x in verdict(lost))


def _cooling(post, seed=21):
    """The 300 s psce bag with its head cooling 30 -> 11 deg C (tau 100 s), ``post`` applied."""
    import dataclasses

    sim = simulate(dataclasses.replace(get_scenario("psce_rotations"),
                                       head_temperature_tau_s=100.0), duration=300.0, seed=seed)
    post(sim)
    return sim


def _gyro_x_bias_with_temperature(sim, deg_h_per_c=2.0):
    ht = sim.head_temperature
    temp = np.interp(sim.imu.stamp_ns, ht.stamp_ns, ht.value)
    w = np.asarray(sim.imu.angular_velocity, dtype=float).copy()
    w[:, 0] += deg_h_per_c * DEG_PER_HOUR * (temp - temp.mean())
    sim.imu.angular_velocity = w


@pytest.mark.parametrize("post,follows,p_rate,p_temperature", [
    (lambda sim: tracker_errors.thermal_mount(sim, 2.0), "rate", 3.7e-6, 0.30),
    (_gyro_x_bias_with_temperature, "head temperature", 1.8e-5, 9.9e-7)])
def test_a_walk_refused_on_a_cooling_bag_names_the_regressor_it_follows(
        post, follows, p_rate, p_temperature):
    """A walk's bias estimate that moves with something is refused with the regressor named
    (``noise_runs.walk_motion``'s temperature columns beside the rate's, ``follows_motion``).
    Unseen case ``thermal_mount`` (the mount turning 2″/°C with the head temperature, no
    gyro error; the walk its noise search found there: 0.681 deg/h/√h), seed 21: the x
    estimate follows the rate (p 7.8e-5; beside the temperature's columns 3.7e-6), not the
    temperature (beside the rate 0.30): "follows the gyro's rate", no longer "a gyro error
    that is a function of the motion" (the turn is seen in the slews).  A gyro x bias
    changing 2 deg/h per deg C with the same cooling (the same walk): the x estimate
    follows the temperature (alone 6.9e-5, beside the rate 9.9e-7) more than the rate
    (alone 4.9e-4, beside the temperature 1.8e-5): "follows the head temperature" (on
    main: "follows the gyro's rate ...: a gyro error that is a function of the motion").
    The p's within a factor 100 (seed 21's)."""
    from stellar_cal_ros.diagnosis.discover import rerun_prior
    from stellar_cal_ros.diagnosis.noise_runs import follows_motion, walk_motion

    sim = _cooling(post)
    moved = walk_motion(bag_data_from_simulation(sim), "psce", rerun_prior(sim.prior), (),
                        NoiseScales(gyro_bias_rw=0.681))
    walk: dict = {}
    assert follows_motion(walk, moved), moved
    said = "gyro's rate" if follows == "rate" else follows
    assert walk["follows"] == follows and walk["why"].startswith(
        f"its x bias estimate follows the {said}"), walk
    rate, temp = moved[0][6], moved[0][7]
    assert p_rate / 100 < rate < p_rate * 100 and p_temperature / 100 < temp < \
        min(1.0, p_temperature * 100), moved[0]
    assert "a gyro error that is a function of the motion" not in walk["why"], walk


def test_a_walk_estimate_following_the_temperature_alone_is_said_so():
    """``follows_motion`` with the head temperature's columns significant and the rate's not
    (walk_motion's tuple: p_temperature, the rate beside it, the temperature beside the
    rate): the walk is refused, "follows the head temperature" with both p's beside; where
    the bag has no head temperature the rate's old sentence is kept."""
    from stellar_cal_ros.diagnosis.noise_runs import follows_motion

    nan = float("nan")
    moved = [(1.0, 0.4, 55, 0.5, 10.0, 0.5, 0.6, 0.5), (1.0, 0.3, 55, 0.5, 10.0, 2e-9, 0.2,
                                                         4e-9),
             (1.0, 0.5, 55, 0.5, 10.0, 0.7, 0.6, 0.8)]
    walk: dict = {}
    assert follows_motion(walk, moved) and walk["follows"] == "head temperature", walk
    assert walk["why"] == (
        "its y bias estimate follows the head temperature (p = 2e-09; beside the gyro's rate "
        "p = 4e-09, the rate beside it p = 0.2): a mount turning with the temperature or a "
        "gyro bias changing with it, not a wandering bias"), walk
    walk = {}
    plain = [m[:5] + (nan, nan, nan) for m in moved]
    plain[2] = (9.0, 1e-8) + plain[2][2:]
    assert follows_motion(walk, plain) and walk["follows"] == "rate", walk
    assert walk["why"] == ("its z bias estimate follows the gyro's rate (p = 1e-08): a gyro "
                           "error that is a function of the motion, not a wandering bias")
    assert not follows_motion({}, [m[:5] + (0.5, 0.5, 0.5) for m in moved[:1]] * 3)
