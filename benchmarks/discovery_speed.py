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
* ``profile`` where an acceptance case's CPU goes in one process, by kind of run;
* ``cluster`` what a local cluster costs, step by step (start, first runs, warm runs);
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
    python benchmarks/discovery_speed.py --only profile --case swaying_sky_mode  # run kinds
    python benchmarks/discovery_speed.py --only cluster --workers 0,2 --repeat 2  # its cost
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
    try:
        children = proc.children(recursive=True)
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        # a process of the tree ended while psutil walked it (seen: the watch thread
        # died of it, the peak RSS then stopped there); the next read takes the tree again
        children = []
    for p in [proc, *children]:
        try:
            full = p.memory_full_info()
            rss += full.rss
            pss += getattr(full, "pss", full.rss)
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
    return rss, pss


def measure(args: list[str], period: float = 0.5) -> dict[str, float]:
    """Run ``python -m stellar_cal_ros ARGS``; wall time, CPU and peak memory of its tree.

    CPU: the command's reaped rusage plus its descendants read with psutil while they run
    (:class:`stellar_cal_ros.diagnosis.parallel.TreeCPU`): the fork server's worker
    processes are its children, never reaped into the command's rusage (before H238 the
    CPU column of a run with workers was the parent's alone).
    """
    from stellar_cal_ros.diagnosis.parallel import TreeCPU

    cmd = [sys.executable, "-m", "stellar_cal_ros", *args]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    tree = TreeCPU(period, root=proc.pid, descendants_only=True).__enter__()
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
    tree.__exit__(None, None, None)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)  # the command, reaped
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime) + tree.cpu
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


def _kind(key: str) -> str:
    """The kind of a run, from its task key (diagnosis/discover.py, auto.py, noise_runs.py)."""
    if key.startswith("noise: current"):
        return "noise base runs (= screening runs when kept)"
    if key.startswith("noise "):
        return "ML noise-scale runs"
    if key.startswith("without ") or " for " in key:
        return "checks (without x, rival for x)"
    if key.startswith("screen") or key == "current model":
        return "current-model / screening re-runs"
    return "candidate re-runs"


def profile_case(name: str) -> None:
    """Where one acceptance case's ``discover`` goes, in this process: CPU s per run kind."""
    import collections

    from stellar_cal_ros.diagnosis import parallel
    from stellar_cal_ros.diagnosis.run import diagnose
    from stellar_cal_ros.io.calibration import load_calibration

    bag, case = case_bag(name)
    rows: dict[str, list[float]] = collections.defaultdict(lambda: [0, 0.0])
    evaluate, on_bag = parallel.Runs._evaluate, parallel.Runs._compute_on_bag

    def timed(label: str, fn, *args):
        t = time.process_time()
        out = fn(*args)
        rows[label][0] += 1
        rows[label][1] += time.process_time() - t
        return out

    parallel.Runs._evaluate = lambda self, task: timed(_kind(task.key), evaluate, self, task)
    parallel.Runs._compute_on_bag = lambda self, fn, *a: timed(
        f"on the bag: {fn.__module__.split('.')[-1]}.{fn.__name__}", on_bag, self, fn, *a)
    t0, w0 = time.process_time(), time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        s = diagnose(str(bag), load_calibration(bag.with_suffix(".prior.yaml")), case.method,
                     list(case.user), tmp, plots=False, verbose=False, auto=True, workers=0)
    total = time.process_time() - t0
    print(f"{name} in this process: added {', '.join(s['added'])}; "
          f"{sum(p['reruns'] for p in s['path'])} runs in the path; "
          f"{total:.1f} CPU-s, {time.perf_counter() - w0:.1f} s wall")
    for label, (n, sec) in sorted(rows.items(), key=lambda kv: -kv[1][1]):
        print(f"    {label:52s} {n:4d} {sec:7.1f}")
    print(f"    {'the rest (statistics, decisions, report)':52s}      "
          f"{total - sum(sec for _, sec in rows.values()):7.1f}")


def cluster_cost(workers: int) -> None:
    """CPU s of the process tree per step: runner start, 2 runs (cold), 2 runs (warm), close.

    Of the small bag's ``time_offset`` candidate run, in this process (``workers=0``) or on
    a local cluster of ``workers`` processes (psutil: the parent and its live children).
    """
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.parallel import Task, open_runner, tree_cpu
    from stellar_cal_ros.io.calibration import load_calibration

    def tree() -> float:
        return sum(tree_cpu(reaped=True).values())

    bag = small_bag()
    prior = rerun_prior(load_calibration(bag.with_suffix(".prior.yaml")))
    steps, last = [], tree()

    def step(label: str) -> None:
        nonlocal last
        now = tree()
        steps.append((label, now - last))
        last = now

    with open_runner(str(bag), method_spec("psce"), 0.5, workers) as runs:
        step(f"start ({runs.description})")
        for label in ("2 runs, first (import, kernels, bag)", "the same 2 runs, warm"):
            runs.run_all([Task(f"{label}{i}", prior, ("time_offset",), candidate=True)
                          for i in range(2)])
            step(label)
    step("close")
    print(f"cluster cost, workers={workers} (CPU s of the tree):")
    for label, sec in steps:
        print(f"    {label:52s} {sec:6.1f}")
    print(f"    {'total':52s} {sum(sec for _, sec in steps):6.1f}")


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


def cases_table(rows: list[tuple[str, str, dict[str, float], float]]) -> None:
    """Every acceptance case's ``discover`` in one table against the 60 s target.

    ``rows``: (case, workers, :func:`measure`'s result, the 1-min load average after it).
    """
    print("\none discover per acceptance case (target: <= 60 s wall on 2 cores; CPU s of "
          "the process tree: the wall an idle 2-core machine needs is at least CPU / 2)")
    print("| case | workers | wall s | CPU s | CPU / 2 | peak PSS MB | load after | "
          "<= 60 s |\n|---|---|---:|---:|---:|---:|---:|---|")
    for name, w, m, load in rows:
        print(f"| {name} | {w} | {m['wall']:.1f} | {m['cpu']:.1f} | {m['cpu'] / 2:.1f} | "
              f"{m['pss_mb']:.0f} | {load:.1f} | {'yes' if m['wall'] <= 60 else 'no'} |")


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
                                       "small", "profile", "cluster"], default=None)
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

            table = []
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
                        table.append((name, w, m, os.getloadavg()[0]))
                        if args.detail:
                            where_the_time_goes(m["stdout"], runs=True)
            cases_table(table)
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
    if args.only == "profile":
        for name in args.case or ["swaying_time_tilt_misalignment"]:
            profile_case(name)
    if args.only == "cluster":
        for _ in range(args.repeat):
            for w in counts:
                cluster_cost(w)
    if args.only == "breakdown":
        breakdown(ensure_2h_bag() if args.duration == 7200.0 else _bag(args.duration))
    print(f"load average {os.getloadavg()[0]:.1f} at the end (shared machine: other jobs "
          "slow every row alike)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
