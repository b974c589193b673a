"""``stellar-cal replay`` speed against decode-only reading of the same bag (issue 17).

Usage::

    python benchmarks/psce_speed.py [--bag BAG.mcap] [--duration 7200] [--repeat 3]
                                    [--baseline CHECKOUT] [--frames] [--no-mcap-ros2]
                                    [--effects time_offset] [--method swaying_base]

Without ``--bag`` a 2 h ``psce_rotations`` bag (Tan et al. setting) is simulated once and
cached under ``benchmarks/.cache/``.  Each repetition runs, interleaved (machine load hits
them alike), each in a fresh process so that everything is counted the same way (interpreter
start and imports included):

* ``replay``: ``python -m stellar_cal_ros replay BAG --method psce --prior PRIOR -o OUT -q``
  (what ``stellar-cal replay`` does: the history CSV is written, the residuals are not);
* ``replay (baseline)``: the same command run from another checkout (``--baseline``), for
  before/after comparisons;
* ``rosbags``: every message decoded by ``rosbags.highlevel.AnyReader``;
* ``mcap_ros2``: every message decoded by ``mcap_ros2`` (file order, its fastest mode;
  ``--no-mcap-ros2`` leaves it out: ~23 CPU-s a repetition on the 2-h bag, not in the ratio),

as in ``read_speed.py``.  ``--method`` replays with another method (``swaying_base`` on a
``swaying`` bag: ``stellar-cal simulate --scenario swaying``); the bag's prior is
``BAG.prior.yaml`` either way.  Printed: median wall and CPU (user + system) seconds, the speed
(bag seconds per wall second) and the median of the per-repetition ratios to rosbags' time —
wall and CPU: on a shared machine the CPU ratio is the steadier one.  Each checkout's
bytecode is written first (``compileall``), as an install writes it — rosbags' is: with
``PYTHONDONTWRITEBYTECODE`` set and no ``__pycache__``, every replay compiled the package's
modules from source (≈ 0.3–0.45 CPU-s a process at load 15, 2026-11-29).  ``--frames`` adds
the per-frame latency of the filter step (``process_frame``, p50 / p99, µs) from one
in-process replay.  The issue's target: replay ≤ 0.6 × rosbags' decode-only time.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
TARGET = 0.6


def ensure_bag(duration: float) -> Path:
    """Simulate (once) the psce_rotations bag of ``duration`` seconds."""
    from stellar_cal_ros.sim.scenarios import get_scenario
    from stellar_cal_ros.sim.world import simulate, write_simulation

    path = Path(__file__).parent / ".cache" / f"psce_rotations_{int(duration)}s.mcap"
    if not path.exists():
        t = time.perf_counter()
        write_simulation(simulate(get_scenario("psce_rotations"), duration=duration, seed=1),
                         path)
        print(f"simulated {path} in {time.perf_counter() - t:.1f} s", file=sys.stderr)
    return path


def _decode_cmd(bag: Path, how: str) -> list[str]:
    code = (f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); "
            f"import read_speed; read_speed.{how}(__import__('pathlib').Path({str(bag)!r}))")
    return [sys.executable, "-c", code]


def compile_checkout(checkout: Path) -> None:
    """Write the bytecode of ``checkout``'s package (``compileall``), as an install does."""
    subprocess.run([sys.executable, "-m", "compileall", "-q", str(checkout / "stellar_cal_ros")],
                   capture_output=True, check=False)


def _run(cmd: list[str], cwd: Path) -> tuple[float, float]:
    """Wall and CPU (user + sys) seconds of a child process."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    p = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - t
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode:
        raise RuntimeError(f"{' '.join(cmd[:4])} ... failed: {p.stderr[-1500:]}")
    return wall, (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)


def frame_latency(bag: Path, prior: Path, method: str = "psce") -> tuple[float, float, int]:
    """p50, p99 (µs) of ``process_frame`` in one in-process replay, and the updates."""
    from stellar_cal_ros.io.calibration import load_calibration
    from stellar_cal_ros.methods.kernel import StarFilter
    from stellar_cal_ros.methods.replay import replay

    latencies: list[int] = []
    original = StarFilter.process_frame

    def timed(self, *a, **k):
        t = time.perf_counter_ns()
        out = original(self, *a, **k)
        latencies.append(time.perf_counter_ns() - t)
        return out

    StarFilter.process_frame = timed
    try:
        res = replay(bag, load_calibration(prior), method, keep_tables=False)
    finally:
        StarFilter.process_frame = original
    lat = np.array(latencies) * 1e-3
    return float(np.percentile(lat, 50)), float(np.percentile(lat, 99)), res.counters["updates"]


def main(argv=None) -> int:
    """Command line entry."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bag", type=Path)
    ap.add_argument("--duration", type=float, default=7200.0)
    ap.add_argument("--repeat", type=int, default=3, help="interleaved repetitions")
    ap.add_argument("--baseline", type=Path, help="another checkout to time the same way")
    ap.add_argument("--frames", action="store_true", help="also the per-frame latency")
    ap.add_argument("--effects", default="",
                    help="replay's --effects (e.g. time_offset: an estimated offset)")
    ap.add_argument("--method", default="psce", help="replay's --method")
    ap.add_argument("--no-mcap-ros2", action="store_true",
                    help="leave out mcap_ros2's decode (not in the ratio; the slowest run)")
    args = ap.parse_args(argv)
    bag = Path(args.bag).resolve() if args.bag else ensure_bag(args.duration)
    prior = Path(str(bag).removesuffix(".mcap") + ".prior.yaml")
    tmp = Path(tempfile.mkdtemp(prefix="psce_speed_"))
    runs: dict[str, tuple[list[str], Path]] = {}

    def replay_cmd(tag: str) -> list[str]:
        return [sys.executable, "-m", "stellar_cal_ros", "replay", str(bag), "--method",
                args.method, "--prior", str(prior), "-o", str(tmp / f"{tag}.yaml"), "-q"] + \
            (["--effects", args.effects] if args.effects else [])

    runs["replay"] = (replay_cmd("new"), ROOT)
    compile_checkout(ROOT)
    if args.baseline:
        runs["replay (baseline)"] = (replay_cmd("base"), args.baseline.resolve())
        compile_checkout(args.baseline.resolve())
    runs["rosbags"] = (_decode_cmd(bag, "rosbags_decode"), ROOT)
    if not args.no_mcap_ros2:
        runs["mcap_ros2"] = (_decode_cmd(bag, "mcap_ros2_decode"), ROOT)
    times: dict[str, list[tuple[float, float]]] = {k: [] for k in runs}
    load0 = os.getloadavg()[0]
    for _ in range(args.repeat):
        for name, (cmd, cwd) in runs.items():
            times[name].append(_run(cmd, cwd))
    from stellar_cal_ros.io.bag import BagReader

    with BagReader(bag) as r:
        span = r.duration_s
    ref = np.array(times["rosbags"])
    print(f"bag: {bag.name} ({span:.0f} s, {bag.stat().st_size / 1e6:.1f} MB), "
          f"{os.cpu_count()} cpus, {args.repeat} interleaved repetitions, load average "
          f"{load0:.1f} -> {os.getloadavg()[0]:.1f}")
    print(f"{'':20s} {'wall s':>7s} {'cpu s':>7s} {'x real':>7s} {'wall/rosbags':>13s} "
          f"{'cpu/rosbags':>12s}")
    for name, v in times.items():
        a = np.array(v)
        print(f"{name:20s} {np.median(a[:, 0]):7.2f} {np.median(a[:, 1]):7.2f} "
              f"{span / np.median(a[:, 0]):7.0f} {np.median(a[:, 0] / ref[:, 0]):13.2f} "
              f"{np.median(a[:, 1] / ref[:, 1]):12.2f}")
    print(f"target: replay <= {TARGET} x rosbags' decode-only time")
    if args.frames:
        p50, p99, updates = frame_latency(bag, prior, args.method)
        print(f"process_frame over {updates} updates: p50 {p50:.0f} us, p99 {p99:.0f} us")
    return 0


if __name__ == "__main__":
    sys.exit(main())
