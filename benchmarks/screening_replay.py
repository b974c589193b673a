"""CPU of a diagnosis round's screening replay, in process (issue 24.2).

Usage::

    python benchmarks/screening_replay.py BAG.mcap --calibration R.yaml [--repeat 2]
        [--runs screen,screen_no_dt,estimated_dt,plain] [--consider a,b,...]

Reads the bag once (``read_bag_data``), then replays it with ``replay(data, R, "psce",
...)`` ``--repeat`` times per run kind, ``time.process_time`` around each replay, and prints
a table: ``screen`` the current model with the candidates as consider parameters (the
round's first replay, both tables), ``screen_no_dt`` the same without ``time_offset``,
``estimated_dt`` ``time_offset`` estimated (a candidate's run), ``plain`` the model alone.
The first replay of a process carries first-use costs (numba's cache load, tables).  Run
it with another checkout first on ``PYTHONPATH`` to time that checkout's code.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import stellar_cal_ros
from stellar_cal_ros.io.calibration import load_calibration
from stellar_cal_ros.methods.frames import read_bag_data
from stellar_cal_ros.methods.replay import replay

#: the candidates a psce round screens on a clean bag (diagnosis.json of the 2-h round)
CANDIDATES = ("aberration", "pixel_aspect", "radial_k3", "image_plane_tilt",
              "thermal_focal_length", "gyro_scale_factor", "gyro_misalignment", "time_offset",
              "proper_motion", "refraction")


def main() -> None:
    """Time the replays and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("bag", type=Path)
    ap.add_argument("--calibration", type=Path, required=True)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--runs", default="screen,screen_no_dt,estimated_dt,plain")
    ap.add_argument("--consider", default=",".join(CANDIDATES))
    a = ap.parse_args()
    cands = [c for c in a.consider.split(",") if c]
    kinds = {"screen": {"consider": cands},
             "screen_no_dt": {"consider": [c for c in cands if c != "time_offset"]},
             "estimated_dt": {"effects": ["time_offset"]}, "plain": {}}
    data = read_bag_data(a.bag)
    prior = load_calibration(a.calibration)
    code = os.path.dirname(os.path.dirname(stellar_cal_ros.__file__))
    print(f"code: {code}; load {os.getloadavg()[0]:.2f}")
    print("| run | " + " | ".join(f"replay {i + 1} CPU s" for i in range(a.repeat)) +
          " | updates |")
    print("|---|" + "---|" * (a.repeat + 1))
    for kind in a.runs.split(","):
        cpu, n = [], 0
        for _ in range(a.repeat):
            t = time.process_time()
            r = replay(data, prior, "psce", **kinds[kind])
            cpu.append(time.process_time() - t)
            n = r.counters["updates"]
        print(f"| {kind} | " + " | ".join(f"{c:.2f}" for c in cpu) + f" | {n} |", flush=True)
    print(f"load {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
