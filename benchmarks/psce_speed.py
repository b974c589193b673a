"""PSCE replay speed on a 2-h psce_rotations bag (Tan et al. setting), one core.

Usage::

    python benchmarks/psce_speed.py [--bag BAG.mcap] [--duration 7200] [--repeat 2]

Without ``--bag`` the bag is simulated once and cached under ``benchmarks/.cache/``.  Prints
reading and replay time separately (replay: the whole ``replay_psce`` call, filter
construction with its IMU prefix included; "frames s": the frame loop alone), the speed (bag
seconds per wall-clock second, reading + replay), the latency of one star-frame update (p50 /
p99, µs) and the load average (the machine is shared: a loaded one runs slower).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from stellar_cal_ros.io.calibration import load_calibration
from stellar_cal_ros.methods import psce
from stellar_cal_ros.methods.replay import read_bag_data, replay_psce


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


def main(argv=None) -> int:
    """Command line entry."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bag", type=Path)
    ap.add_argument("--duration", type=float, default=7200.0)
    ap.add_argument("--repeat", type=int, default=2, help="best of N")
    args = ap.parse_args(argv)
    bag = args.bag or ensure_bag(args.duration)
    prior = load_calibration(str(bag).replace(".mcap", ".prior.yaml"))
    latencies: list[int] = []
    original = psce.PsceFilter.process_frame

    def timed(self, *a, **k):
        t = time.perf_counter_ns()
        out = original(self, *a, **k)
        latencies.append(time.perf_counter_ns() - t)
        return out

    rows = []
    for _ in range(args.repeat):
        t = time.perf_counter()
        data = read_bag_data(bag)
        read_s = time.perf_counter() - t
        latencies.clear()
        psce.PsceFilter.process_frame = timed
        t = time.perf_counter()
        try:
            res = replay_psce(data, prior)
        finally:
            psce.PsceFilter.process_frame = original
        replay_s = time.perf_counter() - t  # filter construction (IMU prefix) included
        lat = np.array(latencies) * 1e-3
        rows.append((read_s, replay_s, res.filter_seconds, res.duration,
                     np.percentile(lat, 50), np.percentile(lat, 99), res.counters["updates"]))
    best = min(rows, key=lambda r: r[0] + r[1])
    read_s, replay_s, filt_s, dur, p50, p99, updates = best
    load = os.getloadavg()[0]
    print(f"bag: {bag} ({dur:.0f} s, {updates} updates), {os.cpu_count()} cpus, best of "
          f"{args.repeat}, load average {load:.1f}")
    print(f"{'read s':>8s} {'replay s':>9s} {'(frames s)':>10s} {'speed x':>8s} "
          f"{'replay-only x':>14s} {'p50 us':>8s} {'p99 us':>8s}")
    print(f"{read_s:8.2f} {replay_s:9.2f} {filt_s:10.2f} {dur / (read_s + replay_s):8.0f} "
          f"{dur / replay_s:14.0f} {p50:8.0f} {p99:8.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
