"""Speed and memory of the model discovery (issue 15 targets), measured as the user runs it.

Each measurement is one ``python -m stellar_cal_ros`` process (the command a user types),
watched from outside: wall time, the CPU time of its whole process tree (user + system,
from the reaped children's rusage: on a shared machine, CPU / cores is the wall time an
idle machine would need at best), and the peak over time of the RSS and of the PSS summed
over the tree (the parent, the Dask worker processes).  RSS counts shared library pages
once per process; PSS splits them, so it is the fairer "memory of the tree".

Targets (2 cores):

* ``sky``    the independent sky bag's whole path, ``discover`` from its prior, ≤ 60 s;
* ``round``  one ``diagnose`` round on a 2-h ``psce_rotations`` bag, ≤ 30 s, ≤ 500 MB;
* ``speedup`` the same round with 1 and with 2 workers: ≥ 1.8×;
* ``cases``  each multi-effect acceptance case of ``test/test_discovery_cases.py`` (its bag
  simulated once into ``.cache``) in one ``discover`` command, ≤ 60 s;
* ``small``  a ``diagnose`` of a 150 s bag with the command line's default workers,
  ``--workers 0`` and ``--workers 2``: what a local cluster costs a small command;
* ``several`` one ``diagnose`` round where several candidates pass the screening (the
  acceptance case ``psce_camera_imu_time``'s three hidden effects on a 900 s bag) with 1
  and 2 workers: the round the 1 → 2 worker target is about.

The variants are interleaved (1 worker, 2 workers, 1, 2, …) so that a load change on a
shared machine hits both alike.  The 2-h bag is simulated once into
``benchmarks/.cache/`` (shared with ``psce_speed.py``).

Run::

    python benchmarks/discovery_speed.py                 # everything, 1 repetition
    python benchmarks/discovery_speed.py --only round --repeat 2 --detail
    python benchmarks/discovery_speed.py --only breakdown   # where a 2-h round's time goes
    python benchmarks/discovery_speed.py --only breakdown --duration 1800   # a shorter bag
    python benchmarks/discovery_speed.py --only several --repeat 2 --detail
    python benchmarks/discovery_speed.py --only cases --workers 0,2 --detail   # acceptance
    python benchmarks/discovery_speed.py --only cases --case swaying_sky_mode --workers 2
    python benchmarks/discovery_speed.py --only small --repeat 2   # the CLI's default workers
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import psutil

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's package (the measured commands run in ROOT)
SKY = ROOT.parent / "shared" / "data" / "psce_sky_900s.mcap"


def _tree_memory(proc: psutil.Process) -> tuple[float, float]:
    """(RSS, PSS) summed over ``proc`` and its descendants, bytes."""
    rss = pss = 0.0
    for p in [proc, *proc.children(recursive=True)]:
        try:
            full = p.memory_full_info()
            rss += full.rss
            pss += getattr(full, "pss", full.rss)
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
    return rss, pss


def measure(args: list[str], period: float = 0.5) -> dict[str, float]:
    """Run ``python -m stellar_cal_ros ARGS``; wall time and peak tree memory."""
    cmd = [sys.executable, "-m", "stellar_cal_ros", *args]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    watched = psutil.Process(proc.pid)
    peak = [0.0, 0.0]
    done = threading.Event()

    def watch() -> None:
        while not done.is_set():
            rss, pss = _tree_memory(watched)
            peak[0], peak[1] = max(peak[0], rss), max(peak[1], pss)
            done.wait(period)

    thread = threading.Thread(target=watch, daemon=True)
    thread.start()
    out, err = proc.communicate()
    done.set()
    thread.join()
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)  # the tree, reaped
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{err[-2000:]}")
    return {"wall": wall, "cpu": cpu, "rss_mb": peak[0] / 1e6, "pss_mb": peak[1] / 1e6,
            "stdout": out}


def ensure_2h_bag() -> Path:
    """The 2-h psce_rotations bag (simulated once, as ``psce_speed.py`` does)."""
    sys.path.insert(0, str(Path(__file__).parent))
    from psce_speed import ensure_bag

    return ensure_bag(7200.0)


#: the acceptance case psce_camera_imu_time (test/test_discovery_cases.py) on a longer bag
SEVERAL = {"time_offset": 0.02, "gyro_scale_factor": 1e-4, "pixel_aspect": 1e-4,
           "misidentification": 0.02}


def several_bag(duration: float = 900.0) -> Path:
    """A psce_rotations bag with three hidden effects (simulated once into .cache)."""
    from stellar_cal_ros.sim.scenarios import get_scenario
    from stellar_cal_ros.sim.world import simulate, write_simulation

    path = Path(__file__).parent / ".cache" / f"psce_several_{int(duration)}s.mcap"
    if not path.exists():
        write_simulation(simulate(get_scenario("psce_rotations"), duration=duration, seed=3,
                                  effects=SEVERAL), path)
    return path


def small_bag(duration: float = 150.0) -> Path:
    """A short psce_rotations bag, one small effect (a ``diagnose`` near the model)."""
    from stellar_cal_ros.sim.scenarios import get_scenario
    from stellar_cal_ros.sim.world import simulate, write_simulation

    path = Path(__file__).parent / ".cache" / f"psce_small_aspect_{int(duration)}s.mcap"
    if not path.exists():
        write_simulation(simulate(get_scenario("psce_rotations"), duration=duration, seed=5,
                                  effects={"pixel_aspect": 1e-4}), path)
    return path


def case_bag(name: str) -> tuple[Path, object]:
    """An acceptance case's bag (``test/test_discovery_cases.py`` CASES), simulated once."""
    from stellar_cal_ros.sim.world import write_simulation

    sys.path.insert(0, str(ROOT / "test"))
    from test_discovery_cases import CASES

    case = CASES[name]
    path = Path(__file__).parent / ".cache" / f"case_{name}.mcap"
    if not path.exists():
        write_simulation(case.simulate(), path)
    return path, case


def _bag(duration: float) -> Path:
    sys.path.insert(0, str(Path(__file__).parent))
    from psce_speed import ensure_bag

    return ensure_bag(duration)


def _row(name: str, workers: int, m: dict[str, float], target: str) -> str:
    return (f"{name:8s} {workers:7d} {m['wall']:9.1f} {m['cpu']:8.1f} {m['rss_mb']:10.0f} "
            f"{m['pss_mb']:10.0f}   {target}")


def where_the_time_goes(stdout: str, runs: bool) -> None:
    """Print where a command's time went.

    Its path lines (runs and seconds per round) and, with ``runs``, its per-run progress
    lines (each run's own wall time in its worker).
    """
    for line in stdout.splitlines():
        if re.match(r"\s+round \d+:", line) or (
                runs and re.search(r"\(\d+\.\d s\)(; run \d+/\d+.*)?$", line)):
            print(f"    {line.strip()}")


def breakdown(bag: Path) -> None:
    """Where a 2-h round's time goes, in this process (one core).

    Read the bag, the current model's run alone, the screening run scoring every candidate,
    and each half of the candidates (what one of two workers runs).
    """
    from stellar_cal_ros.diagnosis import screening
    from stellar_cal_ros.diagnosis.discover import _applicable, method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.runstats import bag_facts, quiet
    from stellar_cal_ros.effects import registry
    from stellar_cal_ros.io.calibration import load_calibration
    from stellar_cal_ros.methods.replay import read_bag_data

    spec = method_spec("psce")
    prior = rerun_prior(load_calibration(bag.with_suffix(".prior.yaml")))
    t0 = time.process_time()
    data = read_bag_data(bag)
    facts = bag_facts(data)
    rows = [("read the bag", time.process_time() - t0)]
    cands = [e for e in registry.available()
             if e not in spec.baseline and not _applicable(e, spec, facts)]

    def run(label: str, consider: list[str]) -> None:
        t = time.process_time()
        with quiet():
            result = spec.runner(data, prior, [], consider=consider or None)
            if consider:
                spec.screen(result, consider)
        rows.append((label, time.process_time() - t))

    run("current model alone", [])
    run(f"screening run, all {len(cands)} candidates", cands)
    for i, part in enumerate(screening.parts(cands, 2)):
        run(f"screening part {i + 1}/2 ({len(part)}: {','.join(part)[:40]})", part)
    print("breakdown (CPU s of this process, one core):")
    for label, sec in rows:
        print(f"    {label:62s} {sec:7.1f}")


def main(argv: list[str] | None = None) -> int:
    """Print the table (and the ratio 1 worker / 2 workers of each repetition)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", choices=["sky", "round", "several", "breakdown", "cases",
                                       "small"], default=None)
    ap.add_argument("--case", action="append", default=None,
                    help="--only cases: this acceptance case (repeatable; default: all)")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--workers", default="1,2",
                    help="worker counts to interleave (cases: also 'default', no --workers)")
    ap.add_argument("--duration", type=float, default=7200.0,
                    help="bag length of the breakdown, s (the round is always 2 h)")
    ap.add_argument("--detail", action="store_true",
                    help="print each round's runs and seconds, and each run's wall time")
    args = ap.parse_args(argv)
    counts = [int(w) for w in args.workers.split(",") if w != "default"]
    print("command: " + " ".join([sys.executable, *sys.argv]))
    print(f"cpu count {os.cpu_count()}, load average {os.getloadavg()[0]:.1f} at start")
    print(f"{'case':8s} {'workers':>7s} {'wall s':>9s} {'CPU s':>8s} {'peak RSS':>10s} "
          f"{'peak PSS':>10s}   target  (MB; CPU s: user+system of the whole tree)")
    with tempfile.TemporaryDirectory() as tmp:
        if args.only in (None, "sky"):
            if not SKY.exists():
                print(f"sky      skipped: {SKY} not available")
            else:
                for _ in range(args.repeat):
                    m = measure(["discover", str(SKY), "--calibration",
                                 str(SKY.with_suffix(".prior.yaml")), "--method", "psce",
                                 "--no-plots", "--workers", "2", "-o", f"{tmp}/sky"])
                    added = next((line for line in m["stdout"].splitlines()
                                  if line.startswith("final model")), "")
                    print(_row("sky", 2, m, "whole path <= 60 s") + f"  ({added[:60]}...)")
                    if args.detail:
                        where_the_time_goes(m["stdout"], runs=False)
        if args.only == "cases":
            sys.path.insert(0, str(ROOT / "test"))
            from test_discovery_cases import CASES

            for name in args.case or list(CASES):
                bag, case = case_bag(name)
                for _ in range(args.repeat):
                    for w in args.workers.split(","):
                        flag = [] if w == "default" else ["--workers", w]
                        m = measure(["discover", str(bag), "--calibration",
                                     str(bag.with_suffix(".prior.yaml")), "--method",
                                     case.method, "--effects", ",".join(case.user),
                                     "--no-plots", "-o", f"{tmp}/{name}{w}", *flag])
                        added = ", ".join(re.findall(r"^\s+added (\w+):", m["stdout"],
                                                     re.MULTILINE))
                        added += "; " + next((line.split("; ")[-1] for line in
                                              m["stdout"].splitlines()
                                              if line.startswith("final model")), "")
                        print(f"{name}\n         {w:>7s} {m['wall']:9.1f} {m['cpu']:8.1f} "
                              f"{m['rss_mb']:10.0f} {m['pss_mb']:10.0f}   <= 60 s  "
                              f"({added})", flush=True)
                        if args.detail:
                            where_the_time_goes(m["stdout"], runs=True)
        if args.only == "small":
            # the command line's default (automatic) against --workers 0 and 2 (the old
            # default on two cores): what a cluster costs a small diagnose
            bag = small_bag()
            for _ in range(args.repeat):
                for w in ("0", "2", "default"):
                    flag = [] if w == "default" else ["--workers", w]
                    m = measure(["diagnose", str(bag), "--calibration",
                                 str(bag.with_suffix(".prior.yaml")), "--method", "psce",
                                 "--no-plots", "-o", f"{tmp}/small{w}", *flag])
                    print(f"small    {w:>7s} {m['wall']:9.1f} {m['cpu']:8.1f} "
                          f"{m['rss_mb']:10.0f} {m['pss_mb']:10.0f}", flush=True)
                    if args.detail:
                        where_the_time_goes(m["stdout"], runs=True)
        rounds = [("round", ensure_2h_bag, "<= 30 s, <= 500 MB"),
                  ("several", several_bag, "1 -> 2 workers >= 1.8x")]
        for case, make_bag, target in rounds:
            if args.only not in (None, case):
                continue
            bag = make_bag()
            prior = bag.with_suffix(".prior.yaml")
            for _ in range(args.repeat):
                walls = {}
                for w in counts:
                    m = measure(["diagnose", str(bag), "--calibration", str(prior), "--method",
                                 "psce", "--no-plots", "--workers", str(w), "-o",
                                 f"{tmp}/{case}{w}"])
                    walls[w] = m["wall"]
                    print(_row(case, w, m, target), flush=True)
                    if args.detail:
                        where_the_time_goes(m["stdout"], runs=True)
                if 1 in walls and 2 in walls:
                    print(f"speed-up 1 -> 2 workers: {walls[1] / walls[2]:.2f}x (target >= 1.8)",
                          flush=True)
    if args.only == "breakdown":
        breakdown(ensure_2h_bag() if args.duration == 7200.0 else _bag(args.duration))
    print(f"load average {os.getloadavg()[0]:.1f} at the end (shared machine: other jobs "
          "slow every row alike)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
