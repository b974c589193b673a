"""The user's path: every ``stellar-cal`` command on every input a user may hand it.

Usage::

    python benchmarks/user_paths.py [--work DIR] [--only CMD,...] [--inputs KEY,...]
                                    [--unwritable DIR] [--timeout 900] [--json OUT.json]

Each case runs ``python -m stellar_cal_ros COMMAND ...`` in a fresh process (as a user
would) and the table prints, per command x input: ``ok`` (exit 0; ``ok, N warning lines``
when it warned), or the last line of stderr for a refusal, the wall seconds and the CPU
seconds (the process and its children). A case
is a BUG when its stderr holds a traceback, when a refusal is not one
``stellar-cal CMD: error: ...`` line (argparse's usage + one line counts as one), or when
it exits 0 where it must refuse (or refuses where it must run).

Inputs: the four reference bags of ``--data`` (default ``../shared/data`` beside the
checkout) with their ``.prior.yaml``, a rosbag2 sqlite3 directory and a ROS 1 ``.bag``
converted from the acf sweep bag by ``rosbags`` (an independent writer), the real-sky JPEGs
of ``--realsky``, and bad ones made in ``--work``: an empty file, the psce bag cut at half,
the acf bag without its IMU topic and cut at half, a prior without its ``camera`` block and
one with a word in a number, a path that does not exist and an output directory that cannot
be written (``--unwritable``: default a mode-555 directory, which blocks only a non-root user; as
root pass a read-only mount). Short options throughout (``--workers 0``, ``--no-plots``,
few candidates, short durations) so the matrix runs in minutes under load.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import shutil
import stat
import subprocess
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
BAGS = {"psce_ideal": "psce_ideal_900s", "psce_sky": "psce_sky_900s",
        "swaying": "swaying_ideal", "acf": "acf_sweep_ideal"}
METHOD = {"psce_ideal": "psce", "psce_sky": "psce", "swaying": "swaying_base",
          "acf": "psce", "rosbag2": "psce", "ros1": "psce", "cut": "psce",
          "no_imu": "psce", "empty": "psce", "missing": "psce"}
IMU_TOPIC = "/imu/data"
FOUR_FRAMES = ("jan1_g90_e100ms.jpg", "jan1_g90_e50ms.jpg", "test2_g100_e50ms.jpg",
               "test_5mp_g100_e50ms.jpg")
QUICK = ["--workers", "0", "--no-plots", "--noise", "stated", "--candidates",
         "time_offset,radial_k3"]


def _convert(src: Path, dst: Path, storage: str, exclude=()) -> Path:
    from rosbags.convert import convert

    if dst.exists():
        shutil.rmtree(dst) if dst.is_dir() else dst.unlink()
    convert([src], dst, storage, 8, None, "file", None, None, list(exclude), [], [], [])
    return dst


def _rechunked(src: Path, dst: Path, chunk_size: int = 16 * 1024) -> Path:
    """``src``'s contract topics written again in chunks of ``chunk_size`` bytes."""
    from stellar_cal_ros.io.bag import BagReader, BagWriter

    scalars = {"/star_tracker/temperature": "temperature",
               "/environment/temperature": "temperature", "/environment/pressure": "pressure"}
    with BagReader(src) as r, BagWriter(dst, chunk_size=chunk_size) as w:
        topics = r.topics()
        w.write_imu(r.read_imu())
        w.write_star_frames(r.read_star_frames())
        if "/gnss/fix" in topics:
            w.write_navsat(r.read_navsat())
        for topic, kind in scalars.items():
            if topic in topics:
                w.write_scalar(r.read_scalar(topic), topic, kind=kind)
    return dst


def make_inputs(data: Path, realsky: Path, work: Path, unwritable: Path | None) -> dict:
    """Every input of the matrix: {key: bag path} and {key: prior path}, made in ``work``."""
    work.mkdir(parents=True, exist_ok=True)
    bags = {k: data / f"{v}.mcap" for k, v in BAGS.items()}
    priors = {k: data / f"{v}.prior.yaml" for k, v in BAGS.items()}
    acf = bags["acf"]
    bags["rosbag2"] = _convert(acf, work / "acf_sqlite3", "sqlite3")
    bags["ros1"] = _convert(acf, work / "acf_ros1.bag", "sqlite3")
    bags["no_imu"] = _convert(acf, work / "acf_no_imu.mcap", "mcap", exclude=[IMU_TOPIC])
    for key in ("rosbag2", "ros1", "no_imu"):
        priors[key] = priors["acf"]
    (work / "empty.mcap").write_bytes(b"")
    bags["empty"] = work / "empty.mcap"
    raw = bags["psce_ideal"].read_bytes()
    (work / "cut.mcap").write_bytes(raw[: len(raw) // 2])
    bags["cut"], priors["cut"] = work / "cut.mcap", priors["psce_ideal"]
    bags["missing"] = work / "no_such_bag.mcap"
    # the sweep's one chunk rewritten in 16 KiB chunks, then cut at half (power lost)
    raw_acf = _rechunked(acf, work / "acf_chunked.mcap").read_bytes()
    (work / "acf_cut.mcap").write_bytes(raw_acf[: len(raw_acf) // 2])
    bags["acf_cut"], priors["acf_cut"] = work / "acf_cut.mcap", priors["acf"]
    from stellar_cal_ros.io.mcap_container import McapFile

    chunks = [e for e in McapFile(bags["psce_ideal"]).plan() if hasattr(e, "length")]
    (work / "cut_at_chunk.mcap").write_bytes(raw[: chunks[len(chunks) // 2].offset])
    bags["cut_at_chunk"] = work / "cut_at_chunk.mcap"
    no_meta = work / "rosbag2_no_metadata"
    shutil.rmtree(no_meta, ignore_errors=True)
    shutil.copytree(bags["rosbag2"], no_meta)
    (no_meta / "metadata.yaml").unlink()
    bags["rosbag2_no_metadata"] = no_meta
    cut_db = work / "rosbag2_cut_db3"
    shutil.rmtree(cut_db, ignore_errors=True)
    shutil.copytree(bags["rosbag2"], cut_db)
    db = next(cut_db.glob("*.db3"))
    db.write_bytes(db.read_bytes()[: db.stat().st_size // 2])
    bags["rosbag2_cut_db3"] = cut_db
    b1 = bags["ros1"].read_bytes()
    (work / "ros1_cut.bag").write_bytes(b1[: len(b1) // 2])
    bags["ros1_cut"] = work / "ros1_cut.bag"
    (work / "text.bag").write_text("not a bag\n")
    bags["text_bag"] = work / "text.bag"
    bags["image_folder"] = realsky
    prior = yaml.safe_load(priors["acf"].read_text())
    no_camera = {k: v for k, v in prior.items() if k != "camera"}
    (work / "prior_no_camera.yaml").write_text(yaml.safe_dump(no_camera))
    garbage = json.loads(json.dumps(prior))
    garbage["camera"]["camera_matrix"]["data"][0] = "four thousand"
    (work / "prior_garbage.yaml").write_text(yaml.safe_dump(garbage))
    priors["no_camera"] = work / "prior_no_camera.yaml"
    text = priors["acf"].read_text()
    (work / "prior_yaml_syntax.yaml").write_text(text.replace("camera:\n", "camera: [\n", 1))
    (work / "prior_a_list.yaml").write_text("- 1\n- 2\n")
    priors["yaml_syntax"] = work / "prior_yaml_syntax.yaml"
    priors["a_list"] = work / "prior_a_list.yaml"
    (work / "broken_module.py").write_text("def broken(:\n")
    priors["garbage"] = work / "prior_garbage.yaml"
    priors["empty"] = bags["empty"]
    if unwritable is None:
        unwritable = work / "readonly"
        unwritable.mkdir(exist_ok=True)
        unwritable.chmod(stat.S_IRUSR | stat.S_IXUSR | stat.S_IRGRP | stat.S_IXGRP
                         | stat.S_IROTH | stat.S_IXOTH)
    stamps = work / "stamps.csv"
    stamps.write_text("file,utc\n" + "".join(
        f"{f.name},2026-01-0{1 + k // 60}T20:{k % 60:02d}:00Z\n"
        for k, f in enumerate(sorted(realsky.glob("*.jpg")))))
    images = {"four_frames": [realsky / f for f in FOUR_FRAMES],
              "one_image": [realsky / "pleiades.jpg"],
              "tree": [realsky / "tree.jpg"],
              "all_13": sorted(realsky.glob("*.jpg")),
              "not_an_image": [realsky / "README.md"]}
    return {"bags": bags, "priors": priors, "images": images, "work": work,
            "unwritable": unwritable, "stamps": stamps}


def cases(inp: dict) -> list[tuple[str, str, list[str], bool]]:
    """(command, input, argv, must_succeed) in dependency order (results before their users)."""
    b, p, w = inp["bags"], inp["priors"], inp["work"]
    out = lambda *parts: str(w.joinpath("out", *parts))  # noqa: E731
    ro = str(inp["unwritable"] / "x")
    good = ["psce_ideal", "psce_sky", "swaying", "acf", "rosbag2", "ros1"]
    bad = ["cut", "no_imu", "empty", "missing"]
    c: list[tuple[str, str, list[str], bool]] = []
    c += [("effects", "-", ["effects"], True)]
    c += [("simulate", "psce 20 s", ["simulate", "--scenario", "psce_rotations", "--duration",
                                     "20", "-o", out("sim.mcap")], True),
          ("simulate", "bad --effect", ["simulate", "--scenario", "psce_rotations",
                                        "--duration", "20", "--effect", "no_such=1", "-o",
                                        out("sim_bad.mcap")], False),
          ("simulate", "unwritable -o", ["simulate", "--scenario", "psce_rotations",
                                         "--duration", "20", "-o", ro], False)]
    damaged = ["cut_at_chunk", "rosbag2_no_metadata", "rosbag2_cut_db3", "ros1_cut",
               "text_bag", "image_folder"]
    c += [("info", k, ["info", str(b[k])], k in good + ["no_imu", "rosbag2_no_metadata"])
          for k in good + bad + damaged]
    for k in good + ["cut", "no_imu", "empty", "missing"]:
        c.append(("replay", k, ["replay", str(b[k]), "--method", METHOD[k], "--prior",
                                str(p.get(k, p["acf"])), "-o", out(f"replay_{k}.yaml"),
                                "-q"], k in good))
    for k in damaged:
        c.append(("replay", k, ["replay", str(b[k]), "--method", "psce", "--prior",
                                str(p["acf"]), "-o", out(f"replay_{k}.yaml"), "-q"],
                  k == "rosbag2_no_metadata"))  # its one .db3 reads
    c += [("replay", "cut_at_chunk --on-error skip",
           ["replay", str(b["cut_at_chunk"]), "--method", "psce", "--prior", str(p["cut"]),
            "--on-error", "skip", "-o", out("replay_cut_at_chunk_skip.yaml"), "-q"], True),
          ("replay", "broken --method-module",
           ["replay", str(b["acf"]), "--method", "psce", "--method-module",
            str(w / "broken_module.py"), "--prior", str(p["acf"]), "-o", out("r_mm.yaml")],
           False)]
    c += [("replay", "ros1_cut --on-error skip",  # (rosbags reads indexed bags only)
           ["replay", str(b["ros1_cut"]), "--method", "psce", "--prior", str(p["acf"]),
            "--on-error", "skip", "-o", out("replay_ros1_cut_skip.yaml"), "-q"], False)]
    c += [("replay", "cut --on-error skip",
           ["replay", str(b["cut"]), "--method", "psce", "--prior", str(p["cut"]),
            "--on-error", "skip", "-o", out("replay_cut_skip.yaml"), "-q"], True)]
    for k in ("no_camera", "garbage", "empty", "yaml_syntax", "a_list"):
        c.append(("replay", f"prior {k}", ["replay", str(b["acf"]), "--method", "psce",
                                           "--prior", str(p[k]), "-o",
                                           out(f"replay_prior_{k}.yaml"), "-q"], False))
    c += [("replay", "unwritable -o", ["replay", str(b["acf"]), "--method", "psce", "--prior",
                                       str(p["acf"]), "-o", ro, "-q"], False)]
    for k in ("acf", "rosbag2", "ros1", "no_imu", "cut", "empty"):
        c.append(("batch acf", k, ["batch", str(b[k]), "--method", "acf", "--prior",
                                   str(p.get(k, p["acf"])), "-o", out(f"acf_{k}.yaml"), "-q"],
                  k in ("acf", "rosbag2", "ros1")))
    c += [("batch bundle", k, ["batch", str(b[k]), "--method", "bundle", "--prior",
                               str(p[k]), "-o", out(f"bundle_{k}.yaml"), "-q"], True)
          for k in ("acf", "no_imu")]
    c += [("batch acf", "prior garbage", ["batch", str(b["acf"]), "--method", "acf",
                                          "--prior", str(p["garbage"]), "-o",
                                          out("acf_garbage.yaml"), "-q"], False)]
    for k in good:
        run = out(f"replay_{k}.yaml")
        c.append(("diagnose", k, ["diagnose", str(b[k]), "--calibration", run, "--method",
                                  METHOD[k], "-o", out(f"diag_{k}"), *QUICK], True))
    for k in ("cut", "no_imu", "empty", "missing"):
        c.append(("diagnose", k, ["diagnose", str(b[k]), "--calibration",
                                  out("replay_acf.yaml"), "--method", "psce", "-o",
                                  out(f"diag_{k}"), *QUICK], False))
    c += [("diagnose", "calibration = YAML syntax",
           ["diagnose", str(b["acf"]), "--calibration", str(p["yaml_syntax"]), "--method",
            "psce", "-o", out("diag_syntax"), *QUICK], False),
          ("effects", "broken --effect-module",
           ["effects", "--effect-module", str(w / "broken_module.py")], False)]
    c += [("diagnose", "calibration = bad prior",
           ["diagnose", str(b["acf"]), "--calibration", str(p["garbage"]), "--method", "psce",
            "-o", out("diag_garbage"), *QUICK], False),
          ("diagnose", "calibration missing",
           ["diagnose", str(b["acf"]), "--calibration", out("no_such.yaml"), "--method",
            "psce", "-o", out("diag_nocal"), *QUICK], False),
          ("diagnose", "unwritable -o",
           ["diagnose", str(b["acf"]), "--calibration", out("replay_acf.yaml"), "--method",
            "psce", "-o", ro, *QUICK], False),
          ("diagnose bundle", "acf",
           ["diagnose", str(b["acf"]), "--calibration", out("bundle_acf.yaml"), "--method",
            "bundle", "-o", out("diag_bundle"), *QUICK], True)]
    # --on-error skip past damage (diagnose, discover, twin, batch: the reader's skip mode)
    skip = ["--on-error", "skip"]
    c += [("diagnose", "cut_at_chunk --on-error skip",
           ["diagnose", str(b["cut_at_chunk"]), "--calibration", str(p["cut"]), "--method",
            "psce", "-o", out("diag_cut_skip"), *QUICK, *skip], True),
          ("discover", "cut --on-error skip",
           ["discover", str(b["cut"]), "--calibration", str(p["cut"]), "--method", "psce",
            "-o", out("disc_cut_skip"), "--max-rounds", "2", *QUICK, *skip], True),
          ("twin", "cut --on-error skip",
           ["twin", str(b["cut"]), "--calibration", str(p["cut"]), "-o",
            out("twin_cut_skip.mcap"), *skip], True),
          ("batch acf", "acf_cut --on-error skip",
           ["batch", str(b["acf_cut"]), "--method", "acf", "--prior", str(p["acf"]), "-o",
            out("acf_cut_skip.yaml"), "-q", *skip], True),
          ("batch bundle", "acf_cut --on-error skip",
           ["batch", str(b["acf_cut"]), "--method", "bundle", "--prior", str(p["acf"]), "-o",
            out("bundle_cut_skip.yaml"), "-q", *skip], True),
          ("batch acf", "acf_cut", ["batch", str(b["acf_cut"]), "--method", "acf", "--prior",
                                    str(p["acf"]), "-o", out("acf_cut.yaml"), "-q"], False),
          ("diagnose bundle", "no_imu",
           ["diagnose", str(b["no_imu"]), "--calibration", out("bundle_no_imu.yaml"),
            "--method", "bundle", "-o", out("diag_bundle_no_imu"), *QUICK], True)]
    for k in ("acf", "rosbag2", "ros1"):
        c.append(("discover", k, ["discover", str(b[k]), "--calibration",
                                  out(f"replay_{k}.yaml"), "--method", "psce", "-o",
                                  out(f"disc_{k}"), "--max-rounds", "2", *QUICK], True))
    for k in ("acf", "rosbag2", "ros1", "swaying"):
        c.append(("twin", k, ["twin", str(b[k]), "--calibration", out(f"replay_{k}.yaml"),
                              "--effect", "time_offset=0.002", "-o", out(f"twin_{k}.mcap")],
                  True))
    c += [("twin", "cut", ["twin", str(b["cut"]), "--calibration", out("replay_acf.yaml"),
                           "-o", out("twin_cut.mcap")], False),
          ("twin", "calibration = bad prior",
           ["twin", str(b["acf"]), "--calibration", str(p["garbage"]), "-o",
            out("twin_garbage.mcap")], False)]
    for fmt in ("kalibr", "openvins", "camera_info"):
        c.append((f"export {fmt}", "replay acf", ["export", out("replay_acf.yaml"),
                                                  "--format", fmt, "-o",
                                                  out(f"export_{fmt}.yaml")], True))
    c += [("export kalibr", "prior garbage", ["export", str(p["garbage"]), "--format",
                                              "kalibr", "-o", out("export_g.yaml")], False),
          ("export kalibr", "empty", ["export", str(b["empty"]), "--format", "kalibr", "-o",
                                      out("export_e.yaml")], False),
          ("export kalibr", "unwritable -o", ["export", out("replay_acf.yaml"), "--format",
                                              "kalibr", "-o", ro], False)]
    c += [("report", k, ["report", out(f"replay_{k}.yaml"), "--bag", str(b[k]), "-o",
                         out(f"report_{k}")], True) for k in ("acf", "ros1")]
    c += [("report", "bag of another run", ["report", out("replay_acf.yaml"), "--bag",
                                            str(b["psce_ideal"]), "-o", out("report_x")],
           False),
          ("compare", "acf vs ros1", ["compare", out("replay_acf.yaml"),
                                      out("replay_ros1.yaml"), "--bag", str(b["acf"]), "-o",
                                      out("compare")], True),
          ("compare", "acf vs psce", ["compare", out("replay_acf.yaml"),
                                      out("replay_psce_ideal.yaml"), "--bag", str(b["acf"]),
                                      "-o", out("compare_x")], False)]
    c += [("budget", "replay acf", ["budget", out("replay_acf.yaml"), "--draws", "50",
                                    "--frames", "20", "--no-plots", "-o", out("budget")], True),
          ("budget", "prior garbage", ["budget", str(p["garbage"]), "--no-plots", "-o",
                                       out("budget_g")], False),
          ("budget", "missing", ["budget", out("no_such.yaml"), "--no-plots", "-o",
                                 out("budget_m")], False)]
    for k, files in inp["images"].items():
        fov = ["--fov", "11"] if k == "four_frames" else []  # one camera, 10.9 deg
        c.append(("solve", k, ["solve", *map(str, files), "--stamps", str(inp["stamps"]),
                               *fov, "-o",
                               out(f"solve_{k}.mcap")],
                  k in ("four_frames", "one_image", "tree")))  # trees, and 25 stars
    c += [("solve", "missing image", ["solve", out("no_such.jpg"), "-o", out("solve_m.mcap")],
           False)]
    c += [("batch bundle", "solved four_frames",
           ["batch", out("solve_four_frames.mcap"), "--method", "bundle", "--prior",
            out("solve_four_frames.prior.yaml"), "-o", out("bundle_solved.yaml"), "-q"], True)]
    spec = w / "campaign.yaml"
    spec.write_text(yaml.safe_dump({"name": "user_paths", "seeds": 1, "run": {
        "scenario": "psce_rotations", "duration": 20, "method": "psce",
        "steps": ["simulate", "replay"]}}))
    c += [("campaign --dry-run", "spec", ["campaign", str(spec), "-o", out("campaign"),
                                          "--dry-run"], True),
          ("campaign", "empty spec", ["campaign", str(b["empty"]), "-o", out("campaign_e"),
                                      "--dry-run"], False)]
    c += [("demo", "30 s", ["demo", "--duration", "30", "-o", out("demo")], True),
          ("demo", "unwritable -o", ["demo", "--duration", "30", "-o", ro], False)]
    return c


def judge(rc: int | None, err: str, command: str, must_succeed: bool) -> tuple[str, str]:
    """(text, verdict): verdict '' when the case behaves, else what is wrong."""
    lines = [ln for ln in err.splitlines() if ln.strip()]
    if rc is None:
        return "timeout", "timeout"
    if "Traceback" in err:
        last = lines[-1] if lines else ""
        return last[:120], "BUG: traceback"
    name = command.split()[0]
    if rc == 0:
        warns = sum(1 for ln in lines if "warning" in ln.lower())
        text = "ok" + (f", {warns} warning line{'s' * (warns != 1)}" if warns else "")
        return text, "" if must_succeed else "BUG: ran on a bad input"
    last = lines[-1] if lines else f"(exit {rc}, nothing on stderr)"
    errors = [ln for ln in lines if ": error: " in ln]
    if not last.startswith(f"stellar-cal {name}: error: ") or len(errors) != 1:
        return last[:160], "BUG: not one error line"
    return last[len(f"stellar-cal {name}: error: "):][:160], (
        "" if not must_succeed else "BUG: refused a good input")


def _children_cpu() -> float:
    use = resource.getrusage(resource.RUSAGE_CHILDREN)
    return use.ru_utime + use.ru_stime


def run_case(argv: list[str], timeout: float) -> tuple[int | None, str, float, float]:
    """(exit status or None on timeout, stderr, wall s, CPU s) of one command, fresh process.

    The CPU is the process's with its children's (worker processes too; NaN on timeout).
    """
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    t0, c0 = time.perf_counter(), _children_cpu()
    try:
        proc = subprocess.run([sys.executable, "-m", "stellar_cal_ros", *argv], env=env,
                              capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired as exc:
        return None, (exc.stderr or b"").decode(errors="replace") if isinstance(
            exc.stderr, bytes) else (exc.stderr or ""), time.perf_counter() - t0, math.nan
    return proc.returncode, proc.stderr, time.perf_counter() - t0, _children_cpu() - c0


def main() -> int:
    """Build the inputs, run the cases, print the table; exit 1 if any case is a bug."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=SHARED / "data")
    ap.add_argument("--realsky", type=Path, default=SHARED / "realsky")
    ap.add_argument("--work", type=Path, default=Path("user_paths_work"))
    ap.add_argument("--unwritable", type=Path, default=None,
                    help="a directory no output can be written in (default: mode 555)")
    ap.add_argument("--only", default="", help="comma-separated commands to run")
    ap.add_argument("--inputs", default="", help="comma-separated inputs to run")
    ap.add_argument("--timeout", type=float, default=900.0)
    ap.add_argument("--json", type=Path, default=None, help="write the rows as JSON")
    args = ap.parse_args()
    inp = make_inputs(args.data, args.realsky, args.work.resolve(), args.unwritable)
    (inp["work"] / "out").mkdir(exist_ok=True)
    only = {s for s in args.only.split(",") if s}
    inputs = {s for s in args.inputs.split(",") if s}
    rows = []
    print(f"{'command':<20} {'input':<24} {'s':>6} {'cpu':>6}  result")
    for command, key, argv, must in cases(inp):
        if (only and command.split()[0] not in only and command not in only) or (
                inputs and key not in inputs):
            continue
        rc, err, sec, cpu = run_case(argv, args.timeout)
        text, verdict = judge(rc, err, command, must)
        rows.append({"command": command, "input": key, "seconds": round(sec, 1),
                     "cpu_seconds": round(cpu, 2), "exit": rc, "result": text,
                     "verdict": verdict, "argv": argv, "stderr": err[-4000:]})
        flag = f"  <- {verdict}" if verdict else ""
        print(f"{command:<20} {key:<24} {sec:6.1f} {cpu:6.2f}  {text}{flag}", flush=True)
    bugs = [r for r in rows if r["verdict"]]
    print(f"{len(rows)} cases, {len(bugs)} bugs")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 1 if bugs else 0


if __name__ == "__main__":
    sys.exit(main())
