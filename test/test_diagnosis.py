"""Model discovery: the missing effect ranks first, adding it brings the noise floor back."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from stellar_cal_ros.diagnosis import stats
from stellar_cal_ros.diagnosis.run import diagnose
from stellar_cal_ros.methods.replay import read_bag_data, replay_psce
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate, write_simulation

CANDIDATES = ["time_offset", "pixel_aspect", "radial_k3", "gyro_scale_factor",
              "image_plane_tilt"]
NOISE = 0.05


def _bag(tmp_path, effects, duration=300.0, seed=21):
    sim = simulate(get_scenario("psce_rotations"), duration=duration, seed=seed, effects=effects)
    paths = write_simulation(sim, tmp_path / "bag.mcap")
    return sim, paths, read_bag_data(paths["bag"])


def test_hidden_time_offset_is_found_and_fixed(tmp_path):
    sim, paths, data = _bag(tmp_path, {"time_offset": 0.01})
    base = replay_psce(data, sim.prior)
    summary = diagnose(data, base.calibration, "psce", [], tmp_path / "rep",
                       candidates=CANDIDATES, plots=False, verbose=False)
    first = summary["candidates"][0]
    assert first["effect"] == "time_offset" and first["significant"]
    assert summary["recommendation"] == "time_offset"
    assert max(summary["residual_rms_px"]) > 5 * NOISE
    assert max(first["rms_after_px"]) <= 1.05 * NOISE
    again = replay_psce(data, sim.prior, ["time_offset"])
    res = again.residuals
    assert max(stats.rms(res, stats.evaluation_mask(res))) <= 1.05 * NOISE
    sig = again.calibration.sigma["time_offset"]
    assert abs(again.calibration.time_offset - 0.01) < 3 * sig
    on_disk = json.loads((tmp_path / "rep" / "diagnosis.json").read_text())
    assert on_disk["format"] == "stellar_cal_diagnosis/1"
    for key in ("residual_rms_px", "expected_rms_px", "candidates", "unexplained"):
        assert key in on_disk
    assert set(on_disk["candidates"][0]) >= {"effect", "score", "rms_after_px", "p_value"}
    # copycats of the time offset are not claimed: tested after it, none is needed
    assert not any(c["significant"] for c in summary["candidates"][1:]), summary["candidates"]
    # and with it added (re-run from its calibration) no residual structure is left
    assert summary["unexplained"] == [], summary["unexplained"]


def test_second_effect_behind_a_large_one_is_named_after_it(tmp_path):
    """Two effects missing: the large one first; the small one, too weak to count alone,
    is significant once the large one is in the model, and ahead of the copycats then."""
    sim, paths, data = _bag(tmp_path, {"time_offset": 0.02, "pixel_aspect": 1e-4})
    base = replay_psce(data, sim.prior)
    cands = CANDIDATES + ["gyro_misalignment"]
    summary = diagnose(data, base.calibration, "psce", [], tmp_path / "rep",
                       candidates=cands, plots=False, verbose=False)
    by = {c["effect"]: c for c in summary["candidates"]}
    assert summary["candidates"][0]["effect"] == "time_offset"
    assert summary["recommendation"] == "time_offset"
    pa = by["pixel_aspect"]
    assert not pa["significant_alone"] and pa["significant"], pa
    assert pa["after"]["effect"] == "time_offset" and pa["after"]["p_value"] < 1e-10
    after = [c for c in summary["candidates"] if c["after"]]
    assert max(after, key=lambda c: c["after"]["score"])["effect"] == "pixel_aspect"
    assert not by["gyro_misalignment"]["significant"]  # significant alone, a copycat


# Covered in the default suite, over every candidate (a superset of CANDIDATES):
# test_false_alarms.py::test_clean_bag_raises_no_alarm[psce-False-...] (nothing significant,
# no recommendation, nothing unexplained, noise as stated); a clean run's residuals at the
# noise: test_twin.py (RMS = noise to 5 %) and, on the reference bag,
# test_psce.py::test_reference_bag_innovations (RMS <= 1.03 x noise, NIS in its interval).
@pytest.mark.benchmark
def test_clean_data_claims_nothing(tmp_path):
    sim, paths, data = _bag(tmp_path, {}, seed=22)
    base = replay_psce(data, sim.prior)
    summary = diagnose(data, base.calibration, "psce", [], tmp_path / "rep",
                       candidates=CANDIDATES, plots=False, verbose=False)
    assert not any(c["significant"] for c in summary["candidates"])
    assert summary["recommendation"] is None
    assert max(summary["residual_rms_px"]) <= 1.05 * NOISE


def test_effect_outside_the_library_is_unexplained(tmp_path):
    """A magnitude-dependent centroid bias: no library effect, regressor 'magnitude'."""
    sim, paths, data = _bag(tmp_path, {"magnitude_bias": [0.1, 30.0]}, seed=23)
    base = replay_psce(data, sim.prior)
    summary = diagnose(data, base.calibration, "psce", [], tmp_path / "rep",
                       candidates=CANDIDATES, plots=True, verbose=False)
    assert not any(c["significant"] for c in summary["candidates"])
    regressors = {u["regressor"] for u in summary["unexplained"]}
    assert "magnitude" in regressors
    assert (tmp_path / "rep" / "report.html").exists()
    assert (tmp_path / "rep" / "vector_field.png").stat().st_size > 10_000


def test_time_offset_without_rotation_is_unobservable(tmp_path):
    """At rest (acf scenario at zero rate) a time offset cannot be seen: flagged, not ranked."""
    sc = get_scenario("acf_sweep")
    sc.motion_factory = lambda dur: __import__(
        "stellar_cal_ros.sim.motion", fromlist=["ConstantRateSweep"]).ConstantRateSweep(
        np.eye(3), np.array([1.0, 0.0, 0.0]), 0.0, dur)
    sc.effects = {"installation": [100.0, 200.0, 300.0]}
    sim = simulate(sc, duration=60.0, seed=3)
    paths = write_simulation(sim, tmp_path / "rest.mcap")
    data = read_bag_data(paths["bag"])
    base = replay_psce(data, sim.prior)
    summary = diagnose(data, base.calibration, "psce", [], tmp_path / "rep",
                       candidates=["time_offset"], plots=False, verbose=False)
    assert [u["effect"] for u in summary["unobservable"]] == ["time_offset"]
    assert summary["candidates"] == []


USER_EFFECT = textwrap.dedent('''
    import numpy as np
    from stellar_cal_ros.effects.base import Effect, Stage

    class ReadoutDelay(Effect):
        """A user's own name for a frame timing error (TIME stage)."""

        id = "readout_delay"
        stage = Stage.TIME
        parameter_names = ("delay",)
        units = ("s",)
        default_sigma = (0.05,)
        explanation = "Frames are stamped at readout end instead of mid-exposure."

        def time_shift(self, value, ctx):
            return float(value[0])

        def time_shift_jacobian(self, value, ctx):
            return np.ones(1)
''')


def test_user_effect_runs_the_whole_loop_from_the_command_line(tmp_path, cli):
    """simulate → replay → diagnose with a plugin file → replay with it: RMS at the floor.

    The diagnose runs as ``python -m stellar_cal_ros`` in a subprocess (the module entry
    point, and the user's effect file loaded in the Dask worker processes its default of
    one worker per core starts); the other three commands through ``cli.main`` here (the
    same parser and code, without a second interpreter's imports each)."""
    from stellar_cal_ros.effects import registry

    module = tmp_path / "my_effect.py"
    module.write_text(USER_EFFECT)
    exe = [sys.executable, "-m", "stellar_cal_ros"]

    def subprocess_run(*args):
        out = subprocess.run(exe + list(args), capture_output=True, text=True, timeout=600)
        assert out.returncode == 0, out.stderr[-2000:]
        return out.stdout

    run = cli

    bag = tmp_path / "u.mcap"
    run("simulate", "--scenario", "psce_rotations", "--duration", "200", "--seed", "5",
        "--effect", "time_offset=0.01", "-o", str(bag))
    prior = tmp_path / "u.prior.yaml"
    run("replay", str(bag), "--method", "psce", "--prior", str(prior), "-o",
        str(tmp_path / "base.yaml"), "-q")
    text = subprocess_run("diagnose", str(bag), "--calibration", str(tmp_path / "base.yaml"),
                          "--method", "psce", "--effect-module", str(module), "--candidates",
                          "readout_delay,pixel_aspect", "-o", str(tmp_path / "rep"),
                          "--no-plots")
    assert "recommendation: add --effects readout_delay" in text
    try:
        text = run("replay", str(bag), "--method", "psce", "--prior", str(prior),
                   "--effect-module", str(module), "--effects", "readout_delay", "-o",
                   str(tmp_path / "fixed.yaml"), "-q")
    finally:  # the user's effect leaves this process's registry with the test
        registry.EFFECTS.pop("readout_delay", None)
    line = next(x for x in text.splitlines() if x.startswith("innovation RMS"))
    rms = [float(p.split("=")[1].split()[0]) for p in line.split(":")[1].split(";")[0].split()
           if "=" in p]
    assert max(rms) <= 1.05 * NOISE
    fixed = (tmp_path / "fixed.yaml").read_text()
    assert "readout_delay" in fixed


def test_diagnosis_json_is_the_same_bytes_run_after_run(tmp_path, cli):
    """Issue 21: two ``diagnose`` runs of one bag write byte-identical ``diagnosis.json``.

    Each run in its own interpreter with another string hashing (``PYTHONHASHSEED`` 1 and
    2), as two runs of the command are: before, the 'what could still be hiding' entries'
    ``sigma`` / ``sigma_shown`` came from a set of parameter names, and their order (here
    ``tangential.p1`` first or last) changed from run to run."""
    import os

    bag = tmp_path / "b.mcap"
    cli("simulate", "--scenario", "psce_rotations", "--duration", "100", "--seed", "5",
        "-o", str(bag))
    written = []
    for seed in ("1", "2"):
        out = tmp_path / f"d{seed}"
        p = subprocess.run([sys.executable, "-m", "stellar_cal_ros", "diagnose", str(bag),
                            "--calibration", str(tmp_path / "b.prior.yaml"), "--method",
                            "psce", "--candidates", "pixel_aspect,time_offset,radial_k1k2",
                            "-o", str(out), "--no-plots", "--workers", "0"],
                           capture_output=True, text=True, timeout=600,
                           env={**os.environ, "PYTHONHASHSEED": seed})
        assert p.returncode == 0, p.stderr[-2000:]
        written.append((out / "diagnosis.json").read_bytes())
    summary = json.loads(written[0])
    # the case the test is about: entries with several sigma rows
    assert any(len(e.get("sigma", {})) > 1 for e in summary["reliability"])
    assert written[0] == written[1]


def test_diagnosis_json_does_not_depend_on_how_the_screening_is_split(tmp_path, monkeypatch):
    """Issue 21/24: ``diagnosis.json`` describes the bag and the model, not the schedule.

    ``--workers 0`` scores every candidate in the base run (one screening part); with two
    workers too, the candidates' runs made ahead beside it (here in this process,
    ``Runs.workers`` 2 as a 2-worker cluster has it; until H265 the base run scored
    gyro_scale_factor only and a screening run beside it every candidate).  Before, the
    part holding thermal_focal_length waited for the head temperature, and its run's
    ``env_stale`` (frames released with a stale temperature: here the sensor's series
    ends early) went into the counts when that part was the base run (``--workers 0``) and not
    when it was not (2 workers): the model, PSCE's baseline, reads no temperature, and a
    replay of it counts none.  The candidate's stale input is ``env_stale_candidates``,
    joined over the screening's runs by frame.  The file has no timing field: the whole of
    it is compared (floats to rounding)."""
    from stellar_cal_ros.diagnosis import parallel
    from stellar_cal_ros.diagnosis import run as run_module

    cands = ["gyro_scale_factor", "time_offset", "pixel_aspect", "thermal_focal_length"]
    sim, paths, data = _bag(tmp_path, {}, duration=100.0, seed=21)
    # the sensor's temperature ends 10 s before the bag: those frames wait for it in vain
    # and go with its last value (stale; 2 frames a second)
    h = data.head_temperature
    keep = (h.stamp_ns - data.t0_ns) * 1e-9 < 90.0
    data = dataclasses.replace(data, head_temperature=dataclasses.replace(
        h, stamp_ns=h.stamp_ns[keep], value=h.value[keep], variance=h.variance[keep]))
    calibration = replay_psce(data, sim.prior).calibration
    # a model that reads the temperature counts them
    stale = replay_psce(data, calibration, ["thermal_focal_length"]).counters["env_stale"]
    assert stale >= 18
    opened = []

    def runner(*args, **kw):
        ctx = parallel.open_runner(*args, **kw)

        class Split:
            def __enter__(self):
                runs = ctx.__enter__()
                runs.workers = workers
                opened.append(runs)
                return runs

            def __exit__(self, *exc):
                return ctx.__exit__(*exc)
        return Split()

    monkeypatch.setattr(run_module, "open_runner", runner)
    written = {}
    for workers in (1, 2):
        out = tmp_path / f"w{workers}"
        diagnose(data, calibration, "psce", [], out, candidates=cands, plots=False,
                 verbose=False, workers=0)
        written[workers] = (out / "diagnosis.json").read_text()
    assert [r.workers for r in opened] == [1, 2]
    one, two = json.loads(written[1]), json.loads(written[2])
    # the case: thermal is scored (its part waited for the temperature), the bag has gaps
    assert any(e["effect"] == "thermal_focal_length"
               for k in ("candidates", "screened_out") for e in one[k])
    assert one["counts"] == two["counts"]
    assert one["counts"]["env_received"] > 0 and "env_stale" not in one["counts"]
    # the frames thermal was scored on with the stale temperature are counted apart, as
    # many as a model that reads the temperature runs with (absent before, issue 21)
    assert one["counts"]["env_stale_candidates"] == stale, (one["counts"], stale)
    # every key, string, integer and flag equal, and every float: each score comes from a
    # run of every candidate, and the base run keeps a gyro candidate (the propagation's
    # branch; before, the parts' other consider sets moved the MDBs and biases by up to
    # 1.6e-12 relative)
    assert written[1] == written[2]


@pytest.mark.parametrize("effect", ["time_offset", "pixel_aspect"])
@pytest.mark.parametrize("hook", [True, False])
def test_the_rounds_tail_starts_beside_the_runs_after_the_top_candidate(tmp_path, monkeypatch,
                                                                        effect, hook):
    """Issue 24: a diagnose round's tail starts as soon as its inputs are known.  On a
    cluster the flexure probes (their inputs: the current model's run and the refined run's
    run) and the lines' re-runs (a drift, a rolling shutter: the refined run alone) go
    out as soon as the refined run is in, beside the runs after the top candidate, and the
    round then takes them; before, the probes went after that batch and the drift's re-run
    alone after them (the several round's tail).  A camera effect: no flexure test, no
    probe.  Without the hook (a round that handed out no refined run): the probes, then the
    re-runs beside them, as before this change but the re-runs' place."""
    import contextlib
    from types import SimpleNamespace

    from stellar_cal_ros.diagnosis import flexure
    from stellar_cal_ros.diagnosis import run as run_module
    from stellar_cal_ros.diagnosis.parallel import Task

    calls = []
    runs = SimpleNamespace(description="fake", noise=None, verdict=None)
    base = SimpleNamespace(prior="base prior", effects=(), ok=True, residuals="base res")
    refined = SimpleNamespace(prior="refined prior", effects=(effect,), ok=True,
                              residuals="refined res")
    best = SimpleNamespace(effect=effect, significant_alone=True, refined_run=refined)

    def rank_candidates(*args, on_top=None, **kw):
        if hook:  # as condition_on_top: the refined run and the runs after it handed out
            task = Task("refined " + effect, "refined prior", (effect,))
            then = on_top(base, best, task)
            calls.append(("after-runs",))
            assert then(Task("x after", "p", ()), refined) == []  # (not the refined run)
            assert then(task, refined) == []
        return base, [best]

    @contextlib.contextmanager
    def runner(*args, **kw):
        yield runs

    def probe_later(r, prior, effects):
        calls.append(("probe", prior))
        return lambda: None

    def after_add(r, run, prior, effects, probe=None):
        calls.append(("after_add", prior, probe is not None))

    def start_reruns(run, r):
        calls.append(("reruns", run.residuals))
        return ("drifts", "shutter")

    def finish(*args, started=None, **kw):
        calls.append(("finish", started))
        return {}

    monkeypatch.setattr(run_module, "open_runner", runner)
    monkeypatch.setattr(run_module, "rank_candidates", rank_candidates)
    monkeypatch.setattr(run_module, "start_reruns", start_reruns)
    monkeypatch.setattr(run_module, "finish", finish)
    monkeypatch.setattr(flexure, "probe_later", probe_later)
    monkeypatch.setattr(flexure, "after_add", after_add)
    diagnose("bag.mcap", SimpleNamespace(), "psce", [], tmp_path / "out", plots=False,
             verbose=False, noise="stated", noise_scales="the scales")
    # (the probes' test finds nothing here: the current model's probe is never asked for)
    flexed = effect == "time_offset"  # a flexure may hide behind it: tested
    if hook:
        assert calls == ([("after-runs",)] + [("probe", "base prior")] * flexed
                         + [("reruns", "refined res")]
                         + [("probe", "refined prior"),
                            ("after_add", "refined prior", True)] * flexed
                         + [("finish", ("drifts", "shutter"))]), calls
    elif flexed:
        assert calls == [("probe", "base prior"), ("reruns", "refined res"),
                         ("after_add", "refined prior", False),
                         ("finish", ("drifts", "shutter"))], calls
    else:  # finish starts the re-runs itself
        assert calls == [("finish", None)], calls


def test_a_model_reading_the_temperature_runs_in_memory_as_from_the_file(tmp_path):
    """The diagnosis runs the bag from memory (``BagData``): a model that reads the head
    temperature gets there what a replay of the file gets, float for float.  Before, an
    environment sample came after the whole 4 096-sample IMU block its stamp fell in, so a
    frame in a block's last second waited past ``environment_wait_s`` and went with the
    previous temperature: env_stale 2 on this 100 s bag (12 on a 300 s one, whose thermal
    model's estimates moved by up to 1.3 sigma), none from the file."""
    sim, paths, data = _bag(tmp_path, {"thermal_focal_length": 2e-5}, duration=100.0,
                            seed=21)
    effects = ["thermal_focal_length"]
    from_file = replay_psce(paths["bag"], sim.prior, effects)
    in_memory = replay_psce(data, sim.prior, effects)
    assert from_file.counters.get("env_stale", 0) == 0
    assert in_memory.counters.get("env_stale", 0) == 0
    assert np.array_equal(in_memory.filter.theta, from_file.filter.theta)
    assert np.array_equal(in_memory.filter.P, from_file.filter.P)


@pytest.mark.benchmark
def test_clean_data_false_alarm_rate(tmp_path):
    """Clean data: no candidate significant after correction in >= 95 % of seeds."""
    false = 0
    seeds = range(30, 50)
    for seed in seeds:
        sim, paths, data = _bag(tmp_path / str(seed), {}, duration=200.0, seed=seed)
        base = replay_psce(data, sim.prior)
        s = diagnose(data, base.calibration, "psce", [], tmp_path / str(seed) / "rep",
                     candidates=CANDIDATES, plots=False, verbose=False)
        false += any(c["significant"] for c in s["candidates"])
    assert false <= 0.05 * len(seeds) + 1e-9


def test_builtin_demo_loop_works(tmp_path, capsys):
    """The README's main command in a shorter form: the loop names the effect and fixes it.

    150 s of the README's 600 s: the hidden 20 ms time offset is ~270 x its minimum
    detectable size at 150 s (5.3e-5 s at 300 s, doc/benchmarks.md) and is estimated to
    +-0.009 ms; the RMS after adding it is 1.002 x the noise (the demo's own 1.05 x limit),
    the checks of what else is claimed hold at the diagnosis's stated alpha at any length.
    At 150 s a look-alike (refraction) is listed as implausible, so the last check runs."""
    from stellar_cal_ros.demo import run_demo

    assert run_demo(tmp_path / "demo", duration=150.0) == 0
    out = capsys.readouterr().out
    assert "the diagnosis named time_offset" in out and "the loop worked" in out
    assert (tmp_path / "demo" / "diagnosis" / "report.html").exists()
    summary = json.loads((tmp_path / "demo" / "diagnosis" / "diagnosis.json").read_text())
    # one effect hidden: nothing else claimed, no structure left once it is added
    assert [c["effect"] for c in summary["candidates"] if c["significant"]] == ["time_offset"]
    assert summary["unexplained"] == [], summary["unexplained"]
    # astrometric corrections fitting at the wrong size are look-alikes of the time offset
    assert all(u["after"] and not u["after"]["needed"] for u in summary["implausible"]), \
        summary["implausible"]
