"""The user's path (issue 25): every command reads every bag, errors in one line, runs
that do not belong together are refused, provenance names the command that made a result.

Each test reproduces what a user ran into with the command line itself (``cli.main``) on a
short simulated bag and its copies converted with ``rosbags`` (an independent writer).
"""

from __future__ import annotations

import errno
import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from sim_bags import psce_bag

from stellar_cal_ros import cli
from stellar_cal_ros.cli import main
from stellar_cal_ros.effects import registry
from stellar_cal_ros.io.calibration import load_calibration, prior_warnings

DURATION = 60.0


def _convert(src: Path, dst: Path, storage: str = "sqlite3", exclude=()) -> Path:
    from rosbags.convert import convert

    convert([src], dst, storage, 8, None, "file", None, None, list(exclude), [], [], [])
    return dst


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Two bags of one scenario (seeds 7, 8), a rosbag2 sqlite3 copy of the first, and a
    replay of each with its residual table."""
    d = tmp_path_factory.mktemp("userpath")
    out = {}
    for key, seed in (("a", 7), ("b", 8)):
        bag, prior, _ = psce_bag(DURATION, seed=seed)
        out[f"bag_{key}"], out[f"prior_{key}"] = bag, prior
        res, cal = d / f"res_{key}.csv", d / f"run_{key}.yaml"
        assert main(["replay", str(bag), "--method", "psce", "--prior", str(prior), "-o",
                     str(cal), "--residuals", str(res), "-q"]) == 0
        out[f"run_{key}"], out[f"res_{key}"] = cal, res
    out["dir_a"] = _convert(out["bag_a"], d / "a_sqlite3")
    out["d"] = d
    return out


def _one_error_line(err: str, command: str) -> str:
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert "Traceback" not in err, err
    assert lines and lines[-1].startswith(f"stellar-cal {command}: error: "), err
    return lines[-1]


# ------------------------------------------------------------------ 1. every command, every bag
def test_diagnose_and_discover_read_a_rosbag2_directory(runs, tmp_path, capsys):
    args = ["--method", "psce", "--workers", "0", "--no-plots", "--candidates", "time_offset"]
    assert main(["diagnose", str(runs["bag_a"]), "--calibration", str(runs["run_a"]), "-o",
                 str(tmp_path / "mcap"), *args]) == 0
    assert main(["diagnose", str(runs["dir_a"]), "--calibration", str(runs["run_a"]), "-o",
                 str(tmp_path / "dir"), *args]) == 0, capsys.readouterr().err
    a, b = (json.loads((tmp_path / k / "diagnosis.json").read_text()) for k in ("mcap", "dir"))
    assert a["residual_rms_px"] == pytest.approx(b["residual_rms_px"], rel=1e-12)
    assert main(["discover", str(runs["dir_a"]), "--calibration", str(runs["run_a"]), "-o",
                 str(tmp_path / "found"), *args]) == 0
    # 6. the discovered calibration names the command that made it, the replay as its input
    prov = load_calibration(tmp_path / "found" / "calibration.yaml").extra["provenance"]
    assert prov["command"].startswith("stellar-cal discover "), prov
    assert prov["input"]["command"].startswith("stellar-cal replay "), prov
    assert main(["diagnose", str(tmp_path / "nothing"), "--calibration", str(runs["run_a"]),
                 "-o", str(tmp_path / "x"), *args]) == 1
    assert "no such bag" in _one_error_line(capsys.readouterr().err, "diagnose")


def test_a_rosbag2_directory_that_lost_its_metadata_reads_its_one_database(runs, tmp_path,
                                                                           capsys):
    """A rosbag2 sqlite3 directory without metadata.yaml (copied without it) reads as its
    one .db3 (a bare .db3 reads); main handed the directory to rosbags, which said
    'Expected metadata file '<the directory>' does not exist'. Two databases: one line."""
    bare = tmp_path / "no_meta"
    shutil.copytree(runs["dir_a"], bare)
    (bare / "metadata.yaml").unlink()
    assert main(["info", str(runs["dir_a"])]) == 0
    whole = capsys.readouterr().out.splitlines()[1:]
    assert main(["info", str(bare)]) == 0, capsys.readouterr().err
    assert capsys.readouterr().out.splitlines()[1:] == whole
    db = next(bare.glob("*.db3"))
    shutil.copy(db, bare / "second.db3")
    assert main(["info", str(bare)]) == 1
    line = _one_error_line(capsys.readouterr().err, "info")
    assert line.endswith("2 .db3 files and no metadata.yaml to join them: give one .db3 "
                         "file, or restore metadata.yaml"), line


def test_info_fails_on_a_bag_without_star_centroids(runs, tmp_path, capsys):
    bag = _convert(runs["bag_a"], tmp_path / "no_stars", "mcap",
                   exclude=["/star_tracker/stars"])
    assert main(["info", str(bag)]) == 1
    line = _one_error_line(capsys.readouterr().err, "info")
    assert "no /star_tracker/stars topic" in line
    assert main(["info", str(runs["dir_a"])]) == 0


def test_a_truncated_bag_says_what_to_do_in_one_line_per_problem(runs, tmp_path, capsys):
    raw = Path(runs["bag_a"]).read_bytes()
    bag = tmp_path / "cut.mcap"
    bag.write_bytes(raw[: len(raw) // 2])
    base = ["replay", str(bag), "--method", "psce", "--prior", str(runs["prior_a"]), "-q"]
    assert main([*base, "-o", str(tmp_path / "r.yaml")]) == 1
    err = capsys.readouterr().err
    assert "--on-error skip" in _one_error_line(err, "replay")
    assert main([*base, "--on-error", "skip", "-o", str(tmp_path / "r2.yaml")]) == 0
    out, err = capsys.readouterr()
    assert "UserWarning" not in err and ".py:" not in err, err
    # the reader's warnings counted in the one data quality line below (H252: printed)
    assert "warning" not in err, err
    # the part read past is counted and the summary says so (main: 'data quality: no input
    # fault counted' under the warnings: the stdout a user keeps called the input whole)
    lines = out.splitlines()
    assert any(ln.startswith("counts: ") and "bag_parts_lost=1" in ln for ln in lines), out
    assert any(ln.startswith("data quality: 1 damaged or truncated parts of the bag "
                             "(skipped; `stellar-cal info` lists them)") and "the reader's "
               "3 warnings about the damage counted here" in ln for ln in lines), out
    # ... and so does the result file a user keeps (coord: its YAML had no trace of the
    # loss: a calibration from the first third of the bag read as one from the whole bag)
    dq = yaml.safe_load((tmp_path / "r2.yaml").read_text())["data_quality"]
    assert dq["bag_parts_lost"] == 1 and dq["messages_skipped"] == 0, dq
    assert len(dq["parts_lost"]) == 1 and "runs past the end of the file" in dq["parts_lost"][0]
    assert 0.2 * DURATION < dq["seconds_read"] < 0.6 * DURATION, dq  # half the bytes
    # the simulation's rates (IMU 100 Hz, frames 2 Hz) over the span read
    assert abs(dq["messages_read"]["imu"] - 100.0 * dq["seconds_read"]) <= 2, dq
    assert abs(dq["messages_read"]["frames"] - 2.0 * dq["seconds_read"]) <= 1, dq
    assert f"imu_received={dq['messages_read']['imu']}," in out
    # a whole bag's result says nothing of it (no data_quality block: nothing was lost)
    assert "data_quality" not in yaml.safe_load(Path(runs["run_a"]).read_text())


# ------------------------------------------------------------------ 3. unwritable outputs
def _commands(runs, out: str) -> dict[str, list[str]]:
    bag, prior, run, res = (str(runs[k]) for k in ("bag_a", "prior_a", "run_a", "res_a"))
    return {
        "simulate": ["simulate", "--scenario", "psce_rotations", "-o", f"{out}/x.mcap"],
        "replay": ["replay", bag, "--method", "psce", "--prior", prior, "-o", f"{out}/r.yaml"],
        "batch": ["batch", bag, "--method", "acf", "--prior", prior, "-o", f"{out}/r.yaml"],
        "diagnose": ["diagnose", bag, "--calibration", run, "--method", "psce", "-o", out],
        "discover": ["discover", bag, "--calibration", run, "--method", "psce", "-o",
                     f"{out}/d"],
        "report": ["report", run, "--residuals", res, "-o", out],
        "compare": ["compare", run, run, "--residuals", res, res, "-o", f"{out}/c"],
        "budget": ["budget", run, "-o", f"{out}/b"],
        "export": ["export", run, "--format", "kalibr", "-o", f"{out}/k.yaml"],
        "campaign": ["campaign", f"{out}/spec.yaml", "-o", f"{out}/c"],
    }


def test_an_unwritable_output_path_is_one_line_before_any_work(runs, tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("in the way\n")
    for name, argv in _commands(runs, str(blocker)).items():
        assert main(argv) == 1, name
        line = _one_error_line(capsys.readouterr().err, name)
        assert str(blocker) in line, line


def test_any_os_error_of_a_command_is_one_line(monkeypatch, tmp_path, capsys):
    def full_disk(args):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "x.yaml"))

    parser = cli.build_parser()
    monkeypatch.setattr(cli, "build_parser", lambda: parser)
    parser._subparsers._group_actions[0].choices["effects"].set_defaults(func=full_disk)
    assert main(["effects"]) == 1
    line = _one_error_line(capsys.readouterr().err, "effects")
    assert "No space left on device" in line and "x.yaml" in line


def test_a_multi_line_error_is_printed_as_one_line(monkeypatch, capsys):
    """Whatever a library puts into an error's text (an excerpt, a nested error's lines),
    the command prints one line."""
    def nested(args):
        raise cli.StellarCalError("outer problem:\n  inner line one\n\n  inner line two")

    parser = cli.build_parser()
    monkeypatch.setattr(cli, "build_parser", lambda: parser)
    parser._subparsers._group_actions[0].choices["effects"].set_defaults(func=nested)
    assert main(["effects"]) == 1
    err = capsys.readouterr().err
    assert err.strip() == ("stellar-cal effects: error: outer problem:; inner line one; "
                           "inner line two"), err


def test_a_yaml_syntax_error_is_one_line_naming_line_and_column(tmp_path, capsys):
    """A calibration YAML with a syntax error (a '[' typed for a block): yaml's own text is
    five lines with an excerpt and a caret; the user reads one line with where and what.
    (main printed the five lines.)"""
    bad = tmp_path / "prior.yaml"
    bad.write_text("format: stellar_cal/1\nmethod: prior\ncamera: [\n  image_width: 1024\n")
    assert main(["export", str(bad), "--format", "kalibr", "-o", str(tmp_path / "k.yaml")]) == 1
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert lines == [f"stellar-cal export: error: {bad}: YAML syntax error at line 5, column "
                     "1: expected ',' or ']', but got '<stream end>' (while parsing a flow "
                     "sequence started at line 3)"], lines
    meta = tmp_path / "rosbag2" / "metadata.yaml"  # the reader's YAML too
    meta.parent.mkdir()
    meta.write_text("rosbag2_bagfile_information: [\n  version: 8\n")
    assert main(["info", str(meta.parent)]) == 1
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "(line 3, column 1: expected" in lines[0], lines
    binary = tmp_path / "a_bag.mcap"  # a bag given where the calibration goes
    binary.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)))
    assert main(["export", str(binary), "--format", "kalibr", "-o", str(tmp_path / "b")]) == 1
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert lines == [f"stellar-cal export: error: {binary} is not a calibration YAML: binary "
                     "content at byte 0 (a bag or an image given for RESULT.yaml?)"], lines


def test_diagnose_of_a_truncated_bag_says_what_can_be_done_in_one_line(runs, tmp_path,
                                                                        capsys):
    """diagnose without --on-error stops at damage: one error line that names what reads
    past it (its own --on-error skip, H239; before, replay's only), and no warning before it
    that reading 'goes on' (the star-image probe read the bag with skip and printed one)."""
    raw = Path(runs["bag_a"]).read_bytes()
    bag = tmp_path / "cut.mcap"
    bag.write_bytes(raw[: len(raw) // 2])
    assert main(["diagnose", str(bag), "--calibration", str(runs["run_a"]), "--method", "psce",
                 "-o", str(tmp_path / "d"), "--workers", "0", "--no-plots", "--noise",
                 "stated", "--candidates", "time_offset"]) == 1
    err = capsys.readouterr().err
    assert "reading goes on" not in err, err
    line = _one_error_line(err, "diagnose")
    assert "truncated or corrupt bag" in line, line
    assert line.endswith(f"(`--on-error skip` reads on past it, counting what is lost; "
                         f"`stellar-cal info {bag}` lists the damage)"), line


def test_diagnose_refuses_a_bag_without_imu_from_its_summary(runs, tmp_path, capsys):
    """A filter method on a bag without IMU: refused from the bag's summary before any run,
    naming what runs without it.  main refused only once the noise and the current model's
    runs had failed on it (7-17 s under load), saying nothing of what could run."""
    bag = _convert(runs["bag_a"], tmp_path / "no_imu.mcap", "mcap", exclude=["/imu/data"])
    for command in ("diagnose", "discover"):
        assert main([command, str(bag), "--calibration", str(runs["run_a"]), "--method", "psce",
                     "-o", str(tmp_path / command), "--workers", "0", "--no-plots"]) == 1
        out, err = capsys.readouterr()
        assert "re-runs" not in out and "screen" not in out, out  # nothing ran
        line = _one_error_line(err, command)
        assert line == (f"stellar-cal {command}: error: {bag}: psce needs IMU samples on "
                        "/imu/data, which the bag does not have; without it `--method bundle` "
                        "runs on the star frames alone (from `stellar-cal batch --method "
                        "bundle`'s result)"), line


# ------------------------------------------------------------------ 4. misspelled prior keys
def test_misspelled_prior_keys_are_named_with_the_key_meant(runs, tmp_path, caplog):
    doc = yaml.safe_load(Path(runs["prior_a"]).read_text())
    doc["time_ofset"] = doc.pop("time_offset")
    doc["sigma"]["gyro"]["bais"] = doc["sigma"]["gyro"].pop("bias")
    doc["sigma"]["time_ofset"] = doc["sigma"].pop("time_offset")
    doc["effects"] = {"refraction": {"scael": 1.0}, "abberation": {"scale": 1.0}}
    path = tmp_path / "typo.yaml"
    path.write_text(yaml.safe_dump(doc))
    with caplog.at_level(logging.WARNING, logger="stellar_cal_ros"):
        cli.load_prior(path)
    text = caplog.text
    for key, meant in (("time_ofset", "time_offset"), ("sigma.time_ofset", "time_offset"),
                       ("sigma.gyro.bais", "bias"), ("effects.refraction.scael", "scale"),
                       ("effects.abberation", "aberration")):
        assert key in text and f"'{meant}'" in text, (key, text)
    # sound files (a prior, a result used as a prior) give no such warning
    known = {e: c.parameter_names for e, c in registry.EFFECTS.items()}
    for sound in (runs["prior_a"], runs["run_a"]):
        assert prior_warnings(load_calibration(sound), "x", known) == [], sound


# ------------------------------------------------------------------ 5. runs combined
def test_report_refuses_residuals_and_bags_of_another_run(runs, tmp_path, capsys):
    run, other_res = str(runs["run_a"]), str(runs["res_b"])
    assert main(["report", run, "--residuals", other_res, "-o", str(tmp_path / "r1")]) == 1
    assert "is not the residual table" in _one_error_line(capsys.readouterr().err, "report")
    assert main(["report", run, "--residuals", str(runs["res_a"]), "--bag",
                 str(runs["bag_b"]), "-o", str(tmp_path / "r2")]) == 1
    assert "is not the bag" in _one_error_line(capsys.readouterr().err, "report")
    # the same recording in another container is the same bag
    assert main(["report", run, "--residuals", str(runs["res_a"]), "--bag",
                 str(runs["dir_a"]), "-o", str(tmp_path / "r3")]) == 0
    page = (tmp_path / "r3" / "report.html").read_text()
    # 8. one NIS figure: the run's own NIS/dof, over the same window
    nis = load_calibration(run).extra["consistency"]["nis_per_dof"]
    assert f"NIS/dof <b>{nis:.3f}</b>" in page
    assert "per star" not in page


def test_compare_refuses_runs_of_different_bags(runs, tmp_path, capsys):
    assert main(["compare", str(runs["run_a"]), str(runs["run_b"]), "--residuals",
                 str(runs["res_a"]), str(runs["res_b"]), "-o", str(tmp_path / "c")]) == 1
    assert "different bags" in _one_error_line(capsys.readouterr().err, "compare")


def test_a_change_of_method_is_not_an_added_effect():
    from stellar_cal_ros.diagnosis.report_html import model_change

    text = model_change("psce", ["installation", "focal_length", "gyro_bias"],
                        "swaying_base", ["installation", "gyro_bias", "accel_bias"])
    assert "adds" not in text and "different methods" in text
    assert "B estimates accel_bias" in text and "A estimates focal_length" in text
    assert model_change("psce", ["a"], "psce", ["a", "b"]) == "B adds b to A's model."


# ------------------------------------------------------------------ 8. smaller items
def test_first_run_says_it_compiles(monkeypatch, runs, tmp_path, capsys):
    from stellar_cal_ros.methods import frame_step

    monkeypatch.setattr(frame_step, "compiled_kernels_cold", lambda: True)
    assert main(["replay", str(runs["bag_a"]), "--method", "psce", "--prior",
                 str(runs["prior_a"]), "-o", str(tmp_path / "r.yaml"), "-q"]) == 0
    assert "compiling the filter's numba kernels" in capsys.readouterr().err


def test_the_compile_check_sees_an_empty_cache(tmp_path):
    import subprocess
    import sys

    code = "from stellar_cal_ros.methods.frame_step import compiled_kernels_cold as c; print(c())"
    env = {**__import__("os").environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=env, timeout=120)
    assert out.stdout.strip() == "True", out.stderr[-2000:]


_KERNEL_STEP = """
import json, os, sys
sys.path.insert(0, sys.argv[1])
from stellar_cal_ros.methods import frame_step as fs
mods = ("h109k.a", "h109k.b")
before = fs.kernels_cold(mods)
every = any(not o._cache._cache_file._load_index() for _, _, o in fs._kernels(mods))
import h109k.b
assert h109k.b.entry(1.0) == 4.0
fs.record_kernels_used(mods)
print(json.dumps([before, every, fs.kernels_cold(mods)]))
"""


def test_the_compile_check_judges_the_kernels_a_run_uses(tmp_path):
    """A kernel only other kernels call, whose source changed under unchanged callers, is never
    compiled again (numba loads the callers from their cache): its stale index said 'cold' for
    ever (core.jit.skew3 under star_chain.predict_chain).  Each step is a fresh process:
    [cold before the run, cold judged by every kernel's index, cold after the run]."""
    import json
    import os
    import subprocess
    import sys

    pkg = tmp_path / "src" / "h109k"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    helper = "from numba import njit\n\n\n@njit(cache=True)\ndef helper(x):\n    return x + 1.0\n"
    (pkg / "a.py").write_text(helper)
    (pkg / "b.py").write_text("from numba import njit\n\nfrom h109k.a import helper\n\n\n"
                              "@njit(cache=True)\ndef entry(x):\n    return 2.0 * helper(x)\n")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}

    def step():
        out = subprocess.run([sys.executable, "-c", _KERNEL_STEP, str(tmp_path / "src")],
                             capture_output=True, text=True, env=env, timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
        return json.loads(out.stdout.strip().splitlines()[-1])

    def edit(path, comment):  # another source stamp (numba's: mtime and size)
        path.write_text(path.read_text() + f"# {comment}\n")
        st = path.stat()
        os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))

    assert step() == [True, True, False]  # fresh: compiles, then warm
    assert step() == [False, False, False]
    edit(pkg / "a.py", "the helper's file changes, not its caller's")
    assert step() == [True, True, False]  # judged once (the last run compiled it) ...
    # ... then no longer: the caller came from its cache, the helper's index stays stale
    # (judged by every index, as before, it would say 'cold' for ever)
    assert step() == [False, True, False]
    assert step() == [False, True, False]
    edit(pkg / "b.py", "the caller's file changes")
    assert step() == [True, True, False]  # the entry compiles (and the helper into it)


_AFTER_WARM_UP = """
import json, sys
from stellar_cal_ros.diagnosis import warm_up
from stellar_cal_ros.methods import frame_step as fs
if sys.argv[1] == "warm":
    warm_up.WARM_UPS.clear()  # (the replays' kernels: ~100 CPU-s; the rest of main as it is)
    sys.exit(warm_up.main([]))
from stellar_cal_ros.core.float_text import _table_text
from stellar_cal_ros.core.jit import kernel_cache_dir
text = fs._marker("stellar_cal_ros.core.float_text", _table_text)
print(json.dumps([fs.kernels_cold(("stellar_cal_ros.core.float_text",)),
                  json.loads(text.read_text())["used"] if text.exists() else None,
                  (kernel_cache_dir() / warm_up.DONE_MARKER).is_file()]))
"""


def test_the_compile_check_after_warm_up_finds_nothing_to_compile(tmp_path):
    """setup.sh's warm-up (python -m stellar_cal_ros.diagnosis.warm_up) leaves what a first
    command leaves: the CSV writer's kernel compiled and the kernels-used markers written.  It
    did neither, and the first command after it said 'first run here: compiling' (and compiled
    float_text._table_text).  Each step a fresh process: [cold, the writer's marker, done]."""
    import json
    import os
    import subprocess
    import sys

    from stellar_cal_ros.core import jit

    if not jit.HAVE_NUMBA:
        pytest.skip("numba is not installed")
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env[jit.KERNEL_CACHE_ENV] = str(tmp_path)

    def step(what):
        out = subprocess.run([sys.executable, "-c", _AFTER_WARM_UP, what], capture_output=True,
                             text=True, env=env, timeout=600)
        assert out.returncode == 0, out.stderr[-2000:]
        return out.stdout.strip().splitlines()

    assert step("check") == [json.dumps([True, None, False])]  # a fresh cache: cold
    warm = step("warm")
    assert step("check") == [json.dumps([False, ["_table_text"], True])]
    assert warm == ["tables: kernel ready" + warm[-1].partition("ready")[2]], warm


_MISS = """
import sys
import numpy as np
from stellar_cal_ros.progress import compile_notice_armed
compile_notice_armed(sys.stdout)
from stellar_cal_ros.core.jit import mat3_mul, skew3
mat3_mul(np.eye(3), np.eye(3))
skew3(np.ones(3))
print("done")
"""


def test_a_kernel_the_check_ahead_does_not_judge_is_said_as_it_compiles(tmp_path):
    """The check ahead judges the kernels a run here used (the kernels-used markers): a kernel
    of another method compiled without a word (fresh cache: replay psce, then a first replay
    of swaying_base compiled its 5 kernels, 58 CPU-s, silently).  Armed
    (every CLI command), the first cache miss says the notice, once per process; a warm
    cache says nothing."""
    import os
    import subprocess
    import sys

    from stellar_cal_ros.core import jit
    from stellar_cal_ros.progress import COMPILE_NOTICE

    if not jit.HAVE_NUMBA:
        pytest.skip("numba is not installed")
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env[jit.KERNEL_CACHE_ENV] = str(tmp_path)

    def step():
        out = subprocess.run([sys.executable, "-c", _MISS], capture_output=True, text=True,
                             env=env, timeout=600)
        assert out.returncode == 0, out.stderr[-2000:]
        return out.stdout.splitlines()

    assert step() == [COMPILE_NOTICE, "done"]  # two kernels compiled: said once
    assert step() == ["done"]  # loaded from the cache


def test_the_compile_check_looks_at_every_kernel_module():
    """A module with cached numba kernels left out of KERNEL_MODULES compiles without the notice
    (frame_step's kernels were missed that way: warm star_chain/jit caches said 'warm')."""
    from pathlib import Path

    import stellar_cal_ros
    from stellar_cal_ros.methods.frame_step import KERNEL_MODULES

    root = Path(stellar_cal_ros.__file__).parent
    kernels = {"stellar_cal_ros." + ".".join(p.relative_to(root).with_suffix("").parts)
               for p in root.rglob("*.py") if "njit(cache=True" in p.read_text()}
    assert kernels and kernels == set(KERNEL_MODULES)


def test_budget_plot_says_why_the_total_is_below_its_components():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from stellar_cal_ros.budget.report import _mark_correlation

    lin = {"centroid": {"cross": 0.84, "roll": 8.46}, "principal_point": {"cross": 6.1,
           "roll": 0.15}, "installation": {"cross": 6.2, "roll": 0.2},
           "total": {"cross": 0.88, "roll": 8.46}}
    fig, ax = plt.subplots()
    _mark_correlation(ax, lin, list(lin))
    notes = [t.get_text() for t in ax.texts]
    plt.close(fig)
    indep = np.sqrt(0.84**2 + 6.1**2 + 6.2**2)
    assert len(notes) == 1 and "correlated" in notes[0]
    assert f"independent: {indep:.3g}" in notes[0]


def test_campaign_tables_carry_units_and_histograms_keep_every_value(tmp_path):
    from stellar_cal_ros.campaign import summary

    stats = [{"group": g, "runs": 3, "failed": 0, "mean_run_seconds": 1.0, "parameters": {
        "gyro_bias.bx": {"n": 3, "rms_error": 4.8e-8, "mean_sigma": 4.8e-8, "ratio": 1.0,
                         "ratio_interval": [0.5, 1.5], "normalized": z}}}
        for g, z in (("a", [0.1, -0.5, 6.5]), ("b", [0.2, 1.0, -1.0]))]
    text = summary.format_summary(stats)
    assert "deg/h" in text and "0.0099" in text  # 4.8e-8 rad/s in deg/h
    zs, lim = summary.histogram_groups(stats, "gyro_bias.bx")
    assert [label for label, _ in zs] == ["a", "b"]  # not pooled
    assert lim >= 6.5


def test_runs_can_be_copied_away_and_still_checked(runs, tmp_path):
    """The check compares content, not paths: a moved result and residual table pass."""
    for k in ("run_a", "res_a"):
        shutil.copy(runs[k], tmp_path / Path(runs[k]).name)
    assert main(["report", str(tmp_path / "run_a.yaml"), "--residuals",
                 str(tmp_path / "res_a.csv"), "-o", str(tmp_path / "rep")]) == 0


# ------------------------------------------------------------------ 2. the live window
def test_statistics_blocks_merge_exactly(runs):
    """The live node's blocks (HalfWindowStats) merge into what one RunStats over the same
    frames holds, whiteness lag across the seams included; a checkpoint keeps them."""
    from test_online import bag_events, feed

    from stellar_cal_ros.methods.driver import Calibrator
    from stellar_cal_ros.methods.results import (
        HalfWindowStats,
        RunStats,
        stats_from_dict,
        stats_state,
    )

    cal = Calibrator(load_calibration(runs["prior_a"]), "psce")
    updates = [o.update for o in feed(cal, bag_events(runs["bag_a"])) + cal.finish()
               if o.update is not None]
    whole, blocks = RunStats(), HalfWindowStats(max_blocks=4)
    for u in updates:
        whole.add(u)
        blocks.add(u)
    assert len(blocks.blocks) <= 4 and blocks.block_s >= 8.0  # coarsened as it grew
    merged = RunStats()
    for b in blocks.blocks:
        merged.merge(b)
    a, b = whole.summary(), merged.summary()
    for key in ("frames", "stars", "nis_per_dof", "loglik", "rms_px"):
        assert a[key] == pytest.approx(b[key], rel=1e-12), key
    assert a["whiteness"]["p_value"] == pytest.approx(b["whiteness"]["p_value"], rel=1e-9)
    again = stats_from_dict(stats_state(blocks))  # the checkpoint's: blocks as one array
    assert again.blocks == blocks.blocks and again.starts == blocks.starts  # field for field
    assert all(type(getattr(x, n)) is type(getattr(y, n)) for x, y in zip(
        again.blocks, blocks.blocks, strict=True) for n in ("frames", "sum_nis", "eval_start"))
    assert again.current().summary()["nis_per_dof"] == blocks.current().summary()["nis_per_dof"]
    half = blocks.current()
    assert half.eval_start >= blocks.t_first + 0.5 * (blocks.t_last - blocks.t_first)
    assert 0 < half.stars < whole.stars


def test_third_party_info_lines_only_with_verbose():
    """Coordinator's first-user run of `solve`: tetra3's INFO lines drowned the summary."""
    import subprocess
    import sys

    code = ("import logging, sys\nfrom stellar_cal_ros import cli\n"
            "def run(args):\n"
            "    logging.getLogger('tetra3.solver.database').info('THIRD PARTY')\n"
            "    logging.getLogger('stellar_cal_ros.sky').info('OURS')\n    return 0\n"
            "parser = cli.build_parser()\ncli.build_parser = lambda: parser\n"
            "parser._subparsers._group_actions[0].choices['effects'].set_defaults(func=run)\n"
            "sys.exit(cli.main(sys.argv[1:]))\n")
    for argv, third in ((["effects"], False), (["-v", "effects"], True)):
        p = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True,
                           timeout=120)
        assert p.returncode == 0, p.stderr
        assert "OURS" in p.stderr and ("THIRD PARTY" in p.stderr) == third, p.stderr


# ------------------------------------------------------------- replay's data-quality line
def test_replay_says_the_data_quality_in_one_line(runs, tmp_path, capsys):
    """Replay's end-of-run summary says what its counters say about the input, in the one
    phrasing the diagnosis prints (``results.quality_line`` of ``results.data_quality``; led
    "data quality", not the diagnosis's "data quality first", which the fault campaign reads
    as a flag: a counted skip is none): 1 % of the gyro samples NaN is named with its count,
    a clean bag says so (main: no line)."""
    from stellar_cal_ros.methods.results import data_quality, quality_line
    from stellar_cal_ros.sim.scenarios import get_scenario
    from stellar_cal_ros.sim.world import simulate, write_simulation

    sim = simulate(get_scenario("psce_rotations"), duration=DURATION, seed=7)
    bad = np.random.default_rng(3).random(len(sim.imu.stamp_ns)) < 0.01
    sim.imu.angular_velocity[bad] = np.nan
    paths = write_simulation(sim, tmp_path / "nan_gyro.mcap")
    out = {}
    for key, bag, prior in (("clean", runs["bag_a"], runs["prior_a"]),
                            ("nan", paths["bag"], paths["prior"])):
        capsys.readouterr()
        assert main(["replay", str(bag), "--method", "psce", "--prior", str(prior), "-o",
                     str(tmp_path / f"{key}.yaml"), "-q"]) == 0
        out[key] = [ln for ln in capsys.readouterr().out.splitlines()
                    if ln.startswith("data quality")]
    assert out["clean"] == ["data quality: no input fault counted"], out
    assert len(out["nan"]) == 1, out
    assert out["nan"][0].startswith(f"data quality: {int(bad.sum())} IMU samples with "
                                    "non-finite values or stamps (bridged); "), out
    # the diagnosis's phrasing, from the same function
    n = int(bad.sum())
    faults = data_quality({"imu_invalid": n, "imu_gaps": n, "imu_bridged": n}, 1000)
    assert out["nan"][0] == quality_line(faults, lead="data quality"), out


def test_the_kernel_cache_is_one_per_kernel_version_shared_by_checkouts(tmp_path, monkeypatch):
    """The kernels' numba cache is named by the contents of every file holding compiled code
    (a helper's change is a new version), not by the checkout's path: a fresh clone loads what
    another checkout of the same sources compiled.  Every package file with a cached kernel,
    and every file a kernel module compiles a function of, is one of KERNEL_SOURCES."""
    import inspect
    from pathlib import Path

    import stellar_cal_ros
    from stellar_cal_ros.core import jit
    from stellar_cal_ros.methods.frame_step import KERNEL_MODULES, _kernels

    if not jit.HAVE_NUMBA:
        pytest.skip("numba is not installed")
    root = Path(stellar_cal_ros.__file__).parent
    sources = {root / rel for rel in jit.KERNEL_SOURCES}
    assert {p for p in root.rglob("*.py") if "njit(" in p.read_text()} <= sources
    for _, name, obj in _kernels(KERNEL_MODULES):
        assert Path(inspect.getfile(obj.py_func)).resolve() in sources, name
    # (and a function of another module a kernel module compiles, frame_step's
    # covariance.common_columns: its file's change is a new version too)
    import importlib

    for mod in KERNEL_MODULES:
        for name, obj in vars(importlib.import_module(mod)).items():
            if hasattr(obj, "py_func") and hasattr(obj, "_cache"):
                assert Path(inspect.getfile(obj.py_func)).resolve() in sources, name
    monkeypatch.setenv(jit.KERNEL_CACHE_ENV, str(tmp_path))
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    where = jit.kernel_cache_dir()
    assert where == tmp_path / f"kernels-{jit.kernel_version()}"
    kernel = jit.njit(cache=True)(jit.skew3.py_func)
    assert Path(kernel._cache.cache_path) == where  # not the checkout's __pycache__
    assert kernel._cache._cache_file._source_stamp == jit.kernel_version()
    monkeypatch.setenv(jit.KERNEL_CACHE_ENV, "tree")
    assert jit.kernel_cache_dir() is None


def test_the_kernel_cache_prunes_other_versions_unused_for_days(tmp_path, monkeypatch):
    """A process using the kernel cache stamps its version and removes other versions'
    directories not used for KERNEL_CACHE_KEEP_DAYS (by their stamp, or the directory's
    time before stamps); never the current one, nothing of another name."""
    import os
    import time

    from stellar_cal_ros.core import jit

    if not jit.HAVE_NUMBA:
        pytest.skip("numba is not installed")
    monkeypatch.setenv(jit.KERNEL_CACHE_ENV, str(tmp_path))
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    current = jit.kernel_cache_dir()
    day = 86400.0
    now = time.time()
    keep = jit.KERNEL_CACHE_KEEP_DAYS

    def version_dir(name, days_ago, stamp=True):
        d = tmp_path / name
        d.mkdir()
        (d / "kernel.nbi").write_bytes(b"x")
        t = now - days_ago * day
        if stamp:
            (d / jit.KERNEL_CACHE_STAMP).touch()
            os.utime(d / jit.KERNEL_CACHE_STAMP, (t, t))
        os.utime(d, (t, t))
        return d

    current.mkdir()
    os.utime(current, (now - 400 * day,) * 2)  # old but current: kept, stamped now
    old = version_dir("kernels-" + "a" * 16, keep + 1)
    recent = version_dir("kernels-" + "b" * 16, keep - 1)
    old_unstamped = version_dir("kernels-" + "c" * 16, keep + 5, stamp=False)
    stamped_recently = version_dir("kernels-" + "d" * 16, 0.5)
    os.utime(stamped_recently, (now - 400 * day,) * 2)  # the stamp, not the directory, says
    other_name = version_dir("kernels-old", keep + 100, stamp=False)
    (tmp_path / "tetra3rs.bin").write_bytes(b"x")
    os.utime(tmp_path / "tetra3rs.bin", (now - 400 * day,) * 2)

    jit.kernel_cache_used.cache_clear()
    kernel = jit.njit(cache=True)(jit.skew3.py_func)  # numba's locator: the first cached kernel
    assert Path(kernel._cache.cache_path) == current
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [current.name, recent.name, stamped_recently.name, other_name.name, "tetra3rs.bin"])
    assert not old.exists() and not old_unstamped.exists()
    assert now - (current / jit.KERNEL_CACHE_STAMP).stat().st_mtime < 60.0
    assert (recent / "kernel.nbi").exists()
    # once per process and directory; the direct call with a later clock prunes the recent one
    assert set(jit.kernel_cache_used(current)) == {old, old_unstamped}
    removed = jit.prune_kernel_caches(current, now=now + 2 * day)
    assert removed == [recent]
    assert current.is_dir() and stamped_recently.is_dir()
    jit.kernel_cache_used.cache_clear()


# ------------------------------------------------------------------ a refusal costs no filter
#: what a refusal imports none of: the methods' modules and kernels, numba, scipy beyond the
#: LAPACK of the bag reading's covariance module
HEAVY = ("numba", "scipy.spatial", "scipy.optimize", "scipy.stats", "scipy.sparse",
         "stellar_cal_ros.methods.psce", "stellar_cal_ros.methods.acf",
         "stellar_cal_ros.methods.bundle_runs", "stellar_cal_ros.methods.swaying",
         "stellar_cal_ros.methods.kernel", "stellar_cal_ros.methods.frame_step",
         "stellar_cal_ros.methods.replay", "stellar_cal_ros.diagnosis.run")


def _main_in_a_fresh_process(argvs: list[list[str]], heavy: tuple[str, ...] = HEAVY
                             ) -> tuple[list, list[str]]:
    """``cli.main(argv)`` of each argv in one new process: [(exit status, stderr lines,
    stdout)], and the ``heavy`` modules the process had imported at the end."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent(f"""
        import contextlib, io, sys
        from stellar_cal_ros.cli import main
        out = []
        for argv in {argvs!r}:
            err, text = io.StringIO(), io.StringIO()
            with contextlib.redirect_stderr(err), contextlib.redirect_stdout(text):
                try:
                    code = main(argv)
                except SystemExit as exc:
                    code = exc.code
            out.append((code, err.getvalue().strip().splitlines(), text.getvalue()))
        print(repr(out))
        print(repr(sorted(m for m in sys.modules if m.startswith({heavy!r}))))
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    *_, said, imported = proc.stdout.splitlines()
    return eval(said), eval(imported)  # noqa: S307
def test_a_refusal_a_bad_path_and_help_import_no_method_nor_numba(tmp_path):
    """``diagnose`` of a bag without IMU (refused from its summary), of a path that does not
    exist, ``--method`` of an unknown name and ``diagnose --help`` (which lists every
    diagnosable method with its summary) import no method module, numba nor scipy beyond
    its LAPACK (the bag reading's): the registry reads the methods' declarations from their
    files (H252).  main imported psce
    (numba, scipy) through the ``--method`` choices and every method for the help and the
    refusal's alternatives, and the compile check imported the kernels: 1.0-1.3 CPU-s (8-14 s
    wall under load) for a refusal, now ~0.5."""
    bag, prior, _ = psce_bag(DURATION, seed=7)
    no_imu = _convert(bag, tmp_path / "no_imu.mcap", "mcap", exclude=["/imu/data"])
    said, imported = _main_in_a_fresh_process([
        ["diagnose", str(no_imu), "--calibration", str(prior), "--method", "psce", "-o",
         str(tmp_path / "d")],
        ["diagnose", str(tmp_path / "nope.mcap"), "--calibration", str(prior), "--method",
         "psce", "-o", str(tmp_path / "e")],
        ["diagnose", str(no_imu), "--calibration", str(prior), "--method", "nope", "-o",
         str(tmp_path / "f")],
        ["diagnose", "--help"]])
    assert imported == [], imported
    said = [(code, err[-1:], out) for code, err, out in said]
    (r1, e1, _), (r2, e2, _), (r3, e3, _), (r4, _, helped) = said
    assert r1 == 1 and "psce needs IMU samples on /imu/data" in e1[0], e1
    assert "`--method bundle` runs on the star frames alone" in e1[0], e1
    assert r2 == 1 and e2 == [f"stellar-cal diagnose: error: {tmp_path / 'nope.mcap'}: no "
                              "such bag (a .mcap or ROS 1 .bag file, or a rosbag2 directory)"], e2
    assert r3 == 2 and "invalid choice: 'nope'" in e3[0], e3
    helped = " ".join(helped.split())
    assert r4 == 0 and all(f"{name}: " in helped for name in
                           ("psce", "swaying_base", "traditional", "bundle")), helped
    assert "acf: " not in helped  # (not diagnosable)
    assert "psce: Tan et al. 2018: a rotating vehicle" in helped


def test_a_ros1_bag_cut_short_names_rosbag_reindex(tmp_path, capsys):
    """A ROS 1 bag cut short (no index: ROS 1 writes it last) or never closed (its header's
    index position still 0) cannot be read by rosbags (no reindex of its own): one error
    line that says what rebuilds it, from the bag's header, before rosbags is imported
    (H284: coord 0e2fd9e built rosbags' typestore first and quoted its "Bag index looks
    damaged: ('Header could not be read from file.',)": 0.78 CPU-s a refusal); an index
    cut within (the header's position inside the file) is rosbags' to say, in the same
    line.  main before H252: rosbags' words alone."""
    bag, prior, _ = psce_bag(DURATION, seed=7)
    ros1 = _convert(bag, tmp_path / "whole.bag")
    raw = ros1.read_bytes()
    at = raw.index(b"index_pos=") + len(b"index_pos=")
    index_pos = int.from_bytes(raw[at : at + 8], "little")
    cut, open_, cut_in = tmp_path / "cut.bag", tmp_path / "open.bag", tmp_path / "cut_in.bag"
    cut.write_bytes(raw[: len(raw) // 2])
    open_.write_bytes(raw[:at] + bytes(8) + raw[at + 8:])
    cut_in.write_bytes(raw[: index_pos + 20])
    argvs = [["info", str(cut)],
             ["replay", str(cut), "--method", "psce", "--prior", str(prior), "-o",
              str(tmp_path / "r.yaml"), "-q", "--on-error", "skip"],
             ["info", str(open_)]]
    said, imported = _main_in_a_fresh_process(argvs, HEAVY + ("rosbags",))
    assert imported == [], imported  # (refused from the header)
    whys = {cut: f"its header puts the index at byte {index_pos}, past the file's "
                 f"{len(raw) // 2} bytes",
            open_: "its header holds no index position: the recording was not closed",
            cut_in: "rosbags: Bag index looks damaged: ('Header could not be read from "
                    "file.',)"}
    assert main(["info", str(cut_in)]) == 1
    said.append((1, capsys.readouterr().err.strip().splitlines(), ""))
    for argv, (code, err, _) in zip([*argvs, ["info", str(cut_in)]], said, strict=True):
        path = Path(argv[1])
        assert code == 1 and err == [
            f"stellar-cal {argv[0]}: error: {path}: a ROS 1 bag without a readable index (cut "
            f"short or not closed: the index is written last; {whys[path]}); rebuild it with "
            f"`rosbag reindex {path}` (ROS 1) and give the reindexed bag"], (argv, err)
    assert main(["info", str(ros1)]) == 0, capsys.readouterr().err  # (the whole bag reads)


def test_a_bag_that_does_not_exist_is_one_line_alike_for_every_command(tmp_path, capsys):
    """A bag path that does not exist (a file or a rosbag2 directory): every command that
    reads a bag, and the player node's check, say "PATH: no such bag (a .mcap or ROS 1
    .bag file, or a rosbag2 directory)" (errors.no_such_bag).  coord 0e2fd9e: ``info``,
    ``batch``, ``twin`` and the player said "bag not found: PATH" (the reader's words),
    ``replay``, ``diagnose`` and ``discover`` the line above (their summary check's)."""
    from stellar_cal_ros.errors import BagError
    from stellar_cal_ros.nodes.player import check_bag

    _, prior, _ = psce_bag(DURATION, seed=7)
    for missing in (tmp_path / "nope.mcap", tmp_path / "nope_dir", tmp_path / "nope.bag"):
        want = f"{missing}: no such bag (a .mcap or ROS 1 .bag file, or a rosbag2 directory)"
        for argv in (["info", str(missing)],
                     ["replay", str(missing), "--method", "psce", "--prior", str(prior), "-o",
                      str(tmp_path / "r.yaml"), "-q"],
                     ["batch", str(missing), "--method", "acf", "--prior", str(prior), "-o",
                      str(tmp_path / "b.yaml")],
                     ["diagnose", str(missing), "--calibration", str(prior), "--method",
                      "psce", "-o", str(tmp_path / "d")],
                     ["discover", str(missing), "--calibration", str(prior), "--method",
                      "psce", "-o", str(tmp_path / "f")],
                     ["twin", str(missing), "--calibration", str(prior), "-o",
                      str(tmp_path / "t")]):
            assert main(argv) == 1, argv
            err = capsys.readouterr().err
            assert err.strip().splitlines() == [f"stellar-cal {argv[0]}: error: {want}"], err
        with pytest.raises(BagError) as got:
            check_bag(str(missing))
        assert str(got.value) == want


def test_a_rosbag2_database_cut_short_says_what_to_do_in_one_line(runs, tmp_path, capsys):
    """A rosbag2 sqlite3 database cut short (a copy that stopped): its header counts more
    pages than the file holds, sqlite refuses it whole and rosbags (which opens a database by
    counting every message) reads no part: one line that says so and what to do, for
    ``info``, ``replay`` (``--on-error skip`` too: nothing to skip to) and ``diagnose``.
    main printed rosbags' text: "cannot open bag DIR (rosbag2-sqlite3) with rosbags: Cannot
    open database DB: database disk image is malformed"."""
    cut = tmp_path / "cut_db3"
    shutil.copytree(runs["dir_a"], cut)
    db = next(cut.glob("*.db3"))
    raw = db.read_bytes()
    page = int.from_bytes(raw[16:18], "big")
    assert int.from_bytes(raw[28:32], "big") * page == len(raw)  # (the header's size)
    for keep in (len(raw) // 2, len(raw) // 2 // page * page, 10 * page):
        db.write_bytes(raw[:keep])
        want = (f"{db}: a rosbag2 sqlite3 database cut short: {keep} of the {len(raw)} bytes "
                "its header counts (a copy or download that stopped, a full disk); sqlite "
                "refuses such a file and nothing here reads a part of it (nor `--on-error "
                "skip`): copy the whole file again from where it was recorded")
        for argv in (["info", str(cut)], ["info", str(db)],
                     ["replay", str(cut), "--method", "psce", "--prior", str(runs["prior_a"]),
                      "-o", str(tmp_path / "r.yaml"), "-q"],
                     ["replay", str(cut), "--method", "psce", "--prior", str(runs["prior_a"]),
                      "-o", str(tmp_path / "r.yaml"), "-q", "--on-error", "skip"],
                     ["diagnose", str(cut), "--calibration", str(runs["run_a"]), "--method",
                      "psce", "-o", str(tmp_path / "d"), "--workers", "0", "--no-plots"]):
            assert main(argv) == 1, argv
            line = _one_error_line(capsys.readouterr().err, argv[0])
            assert line == f"stellar-cal {argv[0]}: error: {want}", line
    db.write_bytes(raw)  # (whole again: it reads)
    assert main(["info", str(cut)]) == 0, capsys.readouterr().err


def test_replay_refusals_come_before_the_filter_imports(runs, tmp_path):
    """``replay``'s refusals (no such bag, no IMU, an unknown ``--effects`` id, a prior that
    does not load, a bad ``--noise-scale``) are decided before the filter's imports and the
    kernels' compile check, as diagnose's (H252): one line each, no method module, numba
    nor scipy beyond its LAPACK imported.  main judged them inside ``replay()`` after its
    imports: 0.85-1.0 CPU-s a refusal, now ~0.55 (benchmarks.md, H267).  A bag without IMU
    names the batch command that calibrates on the star frames alone."""
    bag, prior = runs["bag_a"], runs["prior_a"]
    no_imu = _convert(bag, tmp_path / "no_imu.mcap", "mcap", exclude=["/imu/data"])
    bad_prior = tmp_path / "bad_prior.yaml"
    bad_prior.write_text("- 1\n- 2\n")
    cases = [[str(no_imu), "--prior", str(prior)],
             [str(tmp_path / "nope.mcap"), "--prior", str(prior)],
             [str(bag), "--prior", str(prior), "--effects", "radial_k3,nope"],
             [str(bag), "--prior", str(bad_prior)],
             [str(bag), "--prior", str(prior), "--noise-scale", "star=x"]]
    said, imported = _main_in_a_fresh_process(
        [["replay", bag_, "--method", "psce", "-o", str(tmp_path / "r.yaml"), "-q", *more]
         for bag_, *more in cases])
    assert imported == [], imported
    lines = []
    for code, err, _ in said:
        assert code == 1 and len(err) == 1 and err[0].startswith("stellar-cal replay: error: "), err
        lines.append(err[0][len("stellar-cal replay: error: "):])
    assert lines[0] == (f"{no_imu}: psce needs IMU samples on /imu/data, which the bag does "
                        "not have; without it `stellar-cal batch --method bundle` calibrates "
                        "on the star frames alone"), lines[0]
    assert lines[1] == (f"{tmp_path / 'nope.mcap'}: no such bag (a .mcap or ROS 1 .bag file, "
                        "or a rosbag2 directory)"), lines[1]
    assert lines[2].startswith("unknown effect 'nope'; known: installation, "), lines[2]
    assert str(bad_prior) in lines[3], lines[3]
    assert lines[4] == "--noise-scale star: not a number: 'x'", lines[4]
