"""The attitude step test at rest (``diagnosis.installation_step``, issue 21 item 3; unseen
case ``knock``): a tracker installation that jumps once is said first, with its time and
size; a clean bag says nothing.

A clean psce bag (300 s, seed 21) whose stars from 75 % of the run on are shifted by 20″
(0.385 px) along 30° in the image (``knock``'s shift: a rotation of the tracker about its
x and y axes against the IMU, ``(−10, 17.3, 0)″``), diagnosed with the baseline model: the
line tells the time of the step and its size within 3σ; the same bag without the shift has
no such line.  The same on a swaying base, which never rests (all its frames tested; unseen
case ``sway_knock``).  The level on clean bags, ``dt_step`` and ``gsf_asym`` is in
doc/benchmarks.md ("An installation that steps once", "on a swaying base").
"""

from __future__ import annotations

import numpy as np
import pytest

from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.diagnosis import installation_step
from stellar_cal_ros.diagnosis.injection import clean_simulation
from stellar_cal_ros.diagnosis.installation_step import COMPONENT, contrast
from stellar_cal_ros.diagnosis.run import diagnose
from stellar_cal_ros.methods.replay import bag_data_from_simulation

STEP_ARCSEC = 20.0
ANGLE_DEG = 30.0
AT = 0.75


def _diagnosed(tmp_path, knock: bool, method: str = "psce") -> tuple[dict, float, float]:
    """The diagnosis of the clean bag, its stars shifted from :data:`AT` on if ``knock``.

    With the first shifted frame's time (s from the first frame) and the shift (px).
    """
    sim, model = clean_simulation(method, False, 21, 300.0)
    t0, t1 = sim.star_frames[0].stamp_ns, sim.star_frames[-1].stamp_ns
    px = STEP_ARCSEC * ARCSEC * sim.prior.camera.fx
    shift = px * np.array([np.cos(np.deg2rad(ANGLE_DEG)),
                                                    np.sin(np.deg2rad(ANGLE_DEG))])
    after = [f for f in sim.star_frames if f.stamp_ns - t0 >= AT * (t1 - t0)]
    if knock:
        for f in after:
            f.uv = np.asarray(f.uv, dtype=float) + shift
    at = (after[0].stamp_ns - t0) * 1e-9
    return diagnose(bag_data_from_simulation(sim), sim.prior, method, model, tmp_path,
                    plots=False, verbose=False), at, px


def _said_first(got: dict, at: float, px: float) -> None:
    """The installation step's line first, its time, rotation and shift the truth's."""
    first = got["unexplained"][0]
    assert first["component"] == COMPONENT, got["unexplained"]
    step = got["installation_step"]
    assert step["p_value"] * 1e4 < 0.01  # beyond any Bonferroni family of ~100 tests
    assert abs(step["t"] - at) < 2.0 and step["t_before"] < step["t"], (step["t"], at)
    # the rotation that shifts the stars by +0.385 px along 30 deg: du = fx dy, dv = -fy dx
    a = np.deg2rad(ANGLE_DEG)
    truth = np.array([-STEP_ARCSEC * np.sin(a), STEP_ARCSEC * np.cos(a)])
    d, s = np.asarray(step["step_arcsec"][:2]), np.asarray(step["sigma_arcsec"][:2])
    assert np.all(np.abs(d - truth) < 3 * s), (d, s)
    assert abs(step["shift_px"] - px) < 3 * step["sigma_px"], (step["shift_px"], px)
    assert abs(step["angle_deg"] - ANGLE_DEG) < 10.0
    assert "installation steps at t~" in first["regressor"] and "px along" in first["regressor"]
    assert first["change_px"] == step["shift_px"]


def test_an_installation_that_steps_once_is_said_first_with_its_time_and_size(tmp_path):
    """Fails on b9b645c (no ``installation_step``; no 'unexplained' line at all)."""
    got, at, px = _diagnosed(tmp_path / "knock", True)
    _said_first(got, at, px)
    assert got["installation_step"]["at_rest"]


def test_a_swaying_base_that_never_rests_is_tested_over_all_its_frames(tmp_path):
    """Fails on 8e3e396 (``installation_step`` null on a swaying base: no frames at rest)."""
    got, at, px = _diagnosed(tmp_path / "knock", True, "swaying_base")
    _said_first(got, at, px)
    assert not got["installation_step"]["at_rest"]
    assert "never rests" in got["unexplained"][0]["regressor"]
    clean, _, _ = _diagnosed(tmp_path / "clean", False, "swaying_base")
    assert not any(u["component"] == COMPONENT for u in clean["unexplained"]), \
        clean["unexplained"]
    assert clean["installation_step"]["p_value"] > 1e-3


def test_the_same_bag_without_the_step_has_no_such_line(tmp_path):
    """The clean bag: the test runs (its entry), passes, and no line (chi2 18.8, p 0.065)."""
    clean, _, _ = _diagnosed(tmp_path, False)
    assert not any(u["component"] == COMPONENT for u in clean["unexplained"]), \
        clean["unexplained"]
    assert clean["installation_step"]["p_value"] > 1e-3


def test_the_step_contrast_takes_a_straight_line_out():
    """The fit's step row: zero on a constant and a slope, one on the step."""
    c = contrast(6)
    j = np.arange(-6, 6)
    assert abs(c @ np.ones(12)) < 1e-12 and abs(c @ j) < 1e-12
    assert abs(c @ (j >= 0) - 1.0) < 1e-12


def _knocked_discovery(tmp_path, method: str, effects: dict | None = None,
                       at: float = AT) -> dict:
    """``discover`` (gyro_scale_factor the one candidate) on the clean bag (plus
    ``effects``) whose stars are shifted by the knock from ``at`` of the run on."""
    from stellar_cal_ros.diagnosis.auto import discover

    sim, model = clean_simulation(method, False, 21, 300.0, effects)
    t0, t1 = sim.star_frames[0].stamp_ns, sim.star_frames[-1].stamp_ns
    px = STEP_ARCSEC * ARCSEC * sim.prior.camera.fx
    a = np.deg2rad(ANGLE_DEG)
    for f in sim.star_frames:
        if f.stamp_ns - t0 >= at * (t1 - t0):
            f.uv = np.asarray(f.uv, dtype=float) + px * np.array([np.cos(a), np.sin(a)])
    return discover(bag_data_from_simulation(sim), sim.prior, method, model, tmp_path,
                    candidates=["gyro_scale_factor"], plots=False, verbose=False, workers=0)


def test_a_gyro_scale_that_explains_nothing_beside_the_knock_is_not_added(tmp_path):
    """The swaying bag with the knock (``sway_knock``): gyro_scale_factor is significant
    alone, taking up the filter's catch-up after the step, but beside the step fitted as a
    nuisance (``auto._beside_knock``) its ratio is nothing, so it is refused and the
    reason names the step.  Fails on 8e3e396 (gyro_scale_factor added)."""
    got = _knocked_discovery(tmp_path, "swaying_base")
    assert "gyro_scale_factor" not in got["added"], got["added"]
    b = got["path"][-1]["beyond_remainder"]["gyro_scale_factor"]
    assert b["p_value"] > 0.01 and b["statistic"] < 10, b
    assert 15 < np.linalg.norm(b["step_fitted_arcsec"]) < 25, b  # the knock's 20"
    why = [r["reason"] for r in got["path"][-1]["rejected"]
           if r["effect"] == "gyro_scale_factor"]
    assert why and "explains nothing beside the stars' attitude step" in why[0], why
    assert got["unexplained"][0]["component"] == COMPONENT, got["unexplained"]


def test_a_candidate_is_split_at_the_step():
    """The frames' log-likelihood gain before the step and after it, as 2 Δℓ / dispersion."""
    from stellar_cal_ros.diagnosis.installation_step import MIN_BEFORE, before_and_after

    stamps = np.arange(100.0)
    without = np.stack([stamps, np.zeros(100)])
    with_c = np.stack([stamps, np.where(stamps >= 60, 1.0, 0.01)])
    got = before_and_after(without, with_c, 60.0, 2.0, 3)
    assert got["before"]["frames"] == 60 and got["after"]["frames"] == 40
    assert np.isclose(got["before"]["statistic"], 0.6) and got["before"]["p_value"] > 0.5
    assert np.isclose(got["after"]["statistic"], 40.0) and got["after"]["p_value"] < 1e-7
    assert before_and_after(without, with_c, MIN_BEFORE - 1.0, 2.0, 3) is None


def test_a_knock_during_a_slew_is_no_gyro_scale_and_is_said(tmp_path):
    """Unseen case ``knock_slew``: the knock 1 s into psce's first slew from 75 % of the run
    on.  The line's test at rest does not see it (χ²₃ 18.8, p 0.065); gyro_scale_factor
    was added (p 3.6e-177, sy −74 ± 1.7 ppm).  The rival's test over all frames finds the
    step (χ²₃ 1021 at 241.0 s), gyro_scale_factor explains nothing before it (ratio 0.5 on
    183 frames; 824 after): refused, and the step is said from that test, first.  Fails on
    8e3e396 (gyro_scale_factor added, no 'unexplained' line)."""
    from stellar_cal_ros.diagnosis.auto import discover

    sim, model = clean_simulation("psce", False, 21, 300.0)
    t0 = sim.star_frames[0].stamp_ns
    t = (np.asarray(sim.imu.stamp_ns) - t0) * 1e-9
    rate = np.linalg.norm(np.asarray(sim.imu.angular_velocity, dtype=float), axis=1)
    slew = t[np.argmax((rate > 0.5 * np.percentile(rate, 95)) & (t >= AT * t[-1]))]
    px = STEP_ARCSEC * ARCSEC * sim.prior.camera.fx
    a = np.deg2rad(ANGLE_DEG)
    for f in sim.star_frames:
        if (f.stamp_ns - t0) * 1e-9 >= slew + 1.0:
            f.uv = np.asarray(f.uv, dtype=float) + px * np.array([np.cos(a), np.sin(a)])
    got = discover(bag_data_from_simulation(sim), sim.prior, "psce", model, tmp_path,
                   candidates=["gyro_scale_factor"], plots=False, verbose=False, workers=0)
    assert "gyro_scale_factor" not in got["added"], got["added"]
    b = got["path"][-1]["beyond_remainder"]["gyro_scale_factor"]
    assert b["p_value"] > 0.01 and b["statistic"] < 10, b
    assert abs(b["installation_step"]["t"] - (slew + 1.0)) < 2.0, (b["installation_step"], slew)
    first = got["unexplained"][0]
    assert first["component"] == COMPONENT and "moving or not" in first["regressor"], first
    assert abs(first["change_px"] - px) < 0.05, (first["change_px"], px)


def test_a_true_gyro_scale_beside_a_knock_is_added(tmp_path):
    """Unseen case ``knock_gsf``: ``knock``'s step on the psce bag with a true 100-ppm gyro
    scale on z (3x its MDB).  The step makes most of the excess, so the scale (p 5.4e-50)
    removed 6 % of it, under the explained floor: missed on main e100362.  Now a candidate
    a firing step hid is tested beside the step fitted as a nuisance: added, and the
    step's line is still said first."""
    got = _knocked_discovery(tmp_path, "psce", {"gyro_scale_factor": [0.0, 0.0, 1e-4]})
    assert got["added"] == ["gyro_scale_factor"], got["added"]
    beside = got["path"][0]["added"]["beside_step"]
    assert beside["p_value"] < 1e-6, beside
    sz, sigma = got["final_estimates"]["gyro_scale_factor"]["sz"]
    assert abs(sz - 1e-4) < 0.2e-4, (sz, sigma)
    assert got["unexplained"][0]["component"] == COMPONENT, got["unexplained"]
    _hidden(got, tmp_path)


def _hidden(got: dict, out) -> None:
    """The step's nuisance in no output: not added, in no model, not in calibration.yaml,
    nowhere in diagnosis.json (the "what could still be hiding" biases listed its
    parameters, and the terminal printed "would bias ... _installation_step.dy by 0.571
    arcsec": knock_gsf_early s24 on 95751ef)."""
    import json

    from stellar_cal_ros.diagnosis.installation_step import STEP_ID
    from stellar_cal_ros.effects import registry

    assert STEP_ID not in json.dumps(got), [r["effect"] for r in got.get("reliability", [])]
    assert STEP_ID not in got["added"] and STEP_ID not in got["final_estimates"]
    assert all(STEP_ID not in s["model"] for s in got["path"]), got["path"]
    assert STEP_ID not in (out / "calibration.yaml").read_text()
    assert STEP_ID not in registry.available() + registry.candidates()


def test_a_true_gyro_scale_beside_an_early_knock_is_added_at_its_size(tmp_path):
    """Unseen case ``knock_gsf_early``: the knock at 55 % of the run (30 window frames
    before it, no slew among them) and a true 100-ppm gyro scale on z.  On main 85c1dc8
    missed: the scale (2 % of the excess) was judged on the frames before the step (ratio
    2.1, p 0.55).  Beside the step fitted as a nuisance (its 20″ fitted, hidden in the
    model from then on) the scale is added at its size, and the step's line is said first
    with the size it had when it fired."""
    got = _knocked_discovery(tmp_path, "psce", {"gyro_scale_factor": [0.0, 0.0, 1e-4]},
                             at=0.55)
    assert got["added"] == ["gyro_scale_factor"], got["added"]
    beside = got["path"][0]["added"]["beside_step"]
    assert beside["p_value"] < 1e-6, beside
    assert 15 < np.linalg.norm(beside["step_fitted_arcsec"]) < 25, beside
    est = got["final_estimates"]["gyro_scale_factor"]
    for axis, truth in (("sx", 0.0), ("sy", 0.0), ("sz", 1e-4)):
        v, s = est[axis]
        assert abs(v - truth) < 4 * s + 5e-6, (axis, v, s)
    first = got["unexplained"][0]
    assert first["component"] == COMPONENT, got["unexplained"]
    assert "fitted beside the final model" in first["regressor"], first
    _sized_as_fitted(first, tmp_path)
    _hidden(got, tmp_path)


def _sized_as_fitted(line: dict, out) -> None:
    """The step's line says the knock's size as the final model fits it: the rotation
    (arcsec, the stars' sign, :data:`ANGLE_DEG`'s ``(−10, 17.3, 0)″``) and the stars'
    shift at the detector's centre (px, ``change_px``, the number printed after the line)
    within 3σ of the truth, and the text prints those numbers (``out``: the discovery's)."""
    import re

    from stellar_cal_ros.io.calibration import load_calibration

    d = np.asarray(line["detail"]["step_fitted_arcsec"])
    s = np.asarray(line["detail"]["step_fitted_sigma_arcsec"])
    a = np.deg2rad(ANGLE_DEG)
    truth = STEP_ARCSEC * np.array([-np.sin(a), np.cos(a), 0.0])
    assert np.all(np.abs(d - truth) < 3 * s), (d, s, truth)
    px = STEP_ARCSEC * ARCSEC * load_calibration(out / "calibration.yaml").camera.fx
    sigma = line["detail"]["step_fitted_sigma_px"]
    assert line["change_px"] == line["detail"]["step_fitted_px"]
    assert abs(line["change_px"] - px) < 3 * sigma, (line["change_px"], sigma, px)
    said = re.search(r'steps at t~[\d.]+ s by ([\d.]+)" .*the stars jump ([\d.]+) \+- ([\d.]+) '
                     r"px", line["regressor"])
    assert said, line["regressor"]
    assert abs(float(said[1]) - np.linalg.norm(d)) < 0.06, (said[1], d)
    assert abs(float(said[2]) - line["change_px"]) < 0.001 and float(said[3]) > 0, said[0]


def test_a_true_gyro_scale_beside_a_knock_before_the_window_is_added(tmp_path):
    """Unseen case ``knock_gsf_run20``: the knock at 20 % of the run (60 s, before the
    evaluation window) and a true 100-ppm gyro scale on z.  The window has no step to
    test, and every candidate's run takes part of the knock in its first half: the scale
    2 Δℓ −939 (seed 21), nothing significant, missed on main 17d7d23.  The step test over
    the frames before the window (moving or not) finds it, the step is fitted from then on
    (hidden), and beside it the scale is added at its size; the step's line says where it
    was found."""
    from stellar_cal_ros.diagnosis.installation_step import BEFORE

    got = _knocked_discovery(tmp_path, "psce", {"gyro_scale_factor": [0.0, 0.0, 1e-4]},
                             at=0.2)
    first = got["path"][0]
    assert first["action"] == "step", [s["action"] for s in got["path"]]
    b = first["step_before_window"]
    assert abs(b["installation_step"]["t"] - 60.0) < 2.0 and b["p_value"] < 1e-6, b
    assert 15 < np.linalg.norm(b["step_fitted_arcsec"]) < 25, b
    assert got["added"] == ["gyro_scale_factor"], got["added"]
    est = got["final_estimates"]["gyro_scale_factor"]
    for axis, truth in (("sx", 0.0), ("sy", 0.0), ("sz", 1e-4)):
        v, s = est[axis]
        assert abs(v - truth) < 4 * s + 5e-6, (axis, v, s)
    line = got["unexplained"][0]
    assert line["component"] == COMPONENT and BEFORE in line["regressor"], got["unexplained"]
    # (on coord 4c5e68b the line said the test's own step, 90.8", 0.844 px: where a slew
    # starts the filter over-answers the knock and the largest step is a frame late)
    _sized_as_fitted(line, tmp_path)
    _hidden(got, tmp_path)


def test_what_could_still_hide_lists_no_bias_of_the_hidden_step(monkeypatch):
    """The "what could still be hiding" rows of a model holding the step's nuisance: the
    screening's sensitivities cover every parameter of the model, the nuisance's too; none
    of its quantities is listed (knock_gsf_early s24 on 95751ef printed "would bias ...
    _installation_step.dy by 0.571 arcsec")."""
    from types import SimpleNamespace

    from stellar_cal_ros.diagnosis import discover, reliability
    from stellar_cal_ros.diagnosis.installation_step import STEP_ID

    seen = {}

    def external(det, rows, sigma):
        seen.update(rows)
        return {"effect": "time_offset"}

    monkeypatch.setattr(reliability, "external_reliability", external)
    names = ["installation.rx", f"{STEP_ID}.dx", f"{STEP_ID}.dy"]
    base = SimpleNamespace(names=names, sigma_by_name=dict)
    c = SimpleNamespace(effect="time_offset", detect=object(), run=None,
                        screen=SimpleNamespace(sensitivity=[np.ones(1)] * 3,
                                               derived={"epp.u0": np.ones(1)}))
    discover.hidden_effects(base, [c])
    assert sorted(seen) == ["epp.u0", "installation.rx"], sorted(seen)


def test_a_step_over_moving_frames_says_its_size_is_the_tests_jump():
    """Where no fitted step exists (a candidate refused beside a step found moving or not,
    or a platform that never rests), the line's size is the test's own: the frames'
    attitude jump, the filter's answer to the motion included (``knock_gsf_run20`` s21:
    96.8" at 60.0 s for a true 20" knock).  The line says so; at rest, and where the final
    model fits the step (H230), the size is a step's and nothing is added.  On main 423125a
    the moving line printed the jump as the step."""
    from stellar_cal_ros.diagnosis.auto import FITTED_STEP

    def line(at_rest, where="", sized=""):
        return installation_step.InstallationStep(
            60.0, 59.75, [50.9, 13.5, 96.8], [0.7, 0.7, 5.9], 0.99, 0.01, 15.0, 500.0, 600,
            1e-9, at_rest).regressor(where, sized)

    jump = installation_step.JUMP
    assert f'by 110" ({jump}; about' in line(True, installation_step.MOVING)
    assert jump in line(False) and jump in line(True, installation_step.BEFORE)
    assert jump not in line(True) and jump not in line(True, installation_step.MOVING,
                                                       FITTED_STEP)
    assert line(False).endswith("the largest of 600 frames of a platform that never rests)")


def _jittered_swaying(seed: int, knock_arcsec: float = 0.0, method: str = "swaying_base",
                      jitter_s: float = 1e-3, **where):
    """The step test of a clean 300-s swaying bag whose frames are stamped N(0, 1 ms) off
    their exposure (unseen case ``sway_jitter``), the baseline model's run; with
    ``knock_arcsec`` its stars from :data:`AT` on shifted as :func:`_diagnosed`'s (along
    :data:`ANGLE_DEG`).  Returns the test, the first shifted frame's time and the shift (px).
    ``method``, ``jitter_s``: another bag (``psce``: unseen case ``jitter``), another
    jitter (0: none); ``where``: :func:`~stellar_cal_ros.diagnosis.output.step_test`'s
    ``everywhere``, ``before``."""
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.output import step_test
    from stellar_cal_ros.diagnosis.runstats import evaluate
    from stellar_cal_ros.sim import tracker_errors

    sim, _ = clean_simulation(method, False, seed, 300.0)
    if jitter_s:
        tracker_errors.stamp_jitter(sim, jitter_s, seed)
    t0, t1 = sim.star_frames[0].stamp_ns, sim.star_frames[-1].stamp_ns
    px = knock_arcsec * ARCSEC * sim.prior.camera.fx
    after = [f for f in sim.star_frames if f.stamp_ns - t0 >= AT * (t1 - t0)]
    for f in after:
        f.uv = np.asarray(f.uv, dtype=float) + px * np.array(
            [np.cos(np.deg2rad(ANGLE_DEG)), np.sin(np.deg2rad(ANGLE_DEG))])
    run = evaluate(bag_data_from_simulation(sim), method_spec(method),
                   rerun_prior(sim.prior), (), 0.5, keep_residuals=True)
    return step_test(run.residuals, sim.prior, 0.5, **where), \
        (after[0].stamp_ns - t0) * 1e-9, px


def test_a_noise_in_the_frames_stamps_is_no_step_and_a_knock_beside_it_is_found():
    """Frames stamped N(0, 1 ms) off their exposure on the swaying base (unseen case
    ``sway_jitter``): an attitude noise ∝ the rate, which one common covariance of the
    whitened steps leaves under-whitened where the image moves fastest.  Each frame's
    spread now holds the stamps' noise the frames show (``stamp_noise_ms``, 0.93-1.06 on
    seeds 21-26: 3σ 0.15): no step at seeds 21, 22, 26, where coord b07c33a read one at
    p 0.0048 / 0.0019 / 1.3e-5 (χ²₃ 24.8 / 26.7 / 36.9; s22's 'installation steps at t~256.5 s'
    line).  A 60″ knock (1.15 px) beside the jitter is still found at its time, its size
    within 3σ (s21: 1.51 ± 0.26 px, χ²₃ 37.7)."""
    for seed in (21, 22, 26):
        step, _, _ = _jittered_swaying(seed)
        assert step.p_value > 0.01, (seed, step)
        assert step.stamp_noise_ms == pytest.approx(1.0, abs=0.15), (seed, step)
        assert "stamp_noise_ms" in step.as_json()
    step, at, px = _jittered_swaying(21, 60.0)
    assert step.p_value < 1e-4 and abs(step.t - at) < 2.0, (step, at)
    assert abs(step.shift_px - px) < 3 * step.sigma_px, (step.shift_px, step.sigma_px, px)
    assert abs(step.angle_deg - ANGLE_DEG) < 10.0
    assert step.stamp_noise_ms == pytest.approx(1.0, abs=0.15), step  # (0.90 beside it)
    assert f"each frame's spread with the stamps' noise, {step.stamp_noise_ms:.2g} ms rms" \
        in step.regressor()


def test_a_step_before_the_window_on_jittered_stamps_is_tested_at_rest():
    """Where the platform rests and slews (psce, unseen case ``jitter``: frames stamped
    N(0, 1 ms) off), the step test before the window over all frames
    (``everywhere``, ``before``: discover --auto's knock before the window) read the
    filter's answer to the stamps' errors at the slews' ends as a knock: χ²₃ 5583 at
    64.0 s (s21), 7155 (s22), beyond STEP_BEFORE_ALPHA 1e-6 (a step was then fitted and
    only the window-gain check kept it out); the stamps' noise in each frame's spread
    leaves 759 / 2971 (the steps across the rate).  Where the frames tested show a stamp
    noise it is made over the frames at rest: χ²₃ 13.4 / 12.1, p 0.77 / 1 (clean s21 13.5
    at rest).  The clean bag is still tested over all its frames (χ²₃ 17.6, p 0.15).
    Fails on main (s21 p 0)."""
    for seed in (21, 22):
        step, _, _ = _jittered_swaying(seed, method="psce", everywhere=True, before=True)
        assert step.at_rest and step.p_value > 0.01, (seed, step)
    step, _, _ = _jittered_swaying(21, method="psce", jitter_s=0.0, everywhere=True,
                                   before=True)
    assert not step.at_rest and step.p_value > 0.01, step
