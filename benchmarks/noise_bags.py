r"""The bags of issue 21's noise table: a right model with its noise stated wrongly.

One clean PSCE bag (``psce_rotations``, seed 11, true centroid noise 0.05 px) written five
ways: the stars' ``sigma`` field as simulated (``clean``), 0.6x (``s06``), 1.6x (``s16``),
0 = "unknown" (``s0``), and a bag whose gyro angle random walk is 5x the scenario's while
the filter keeps its stated (default) gyro noise (``g5``).  Each bag comes with its
``.prior.yaml``; the diagnosis is then run with the CLI (doc/benchmarks.md, "Noise as a
hypothesis")::

    .venv/bin/python benchmarks/noise_bags.py OUT --duration 900
    .venv/bin/stellar-cal discover OUT/s06.mcap --calibration OUT/s06.prior.yaml \
        --method psce --auto -o OUT/d06
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate, write_simulation


def main() -> None:
    """Write the five bags into OUT."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--duration", type=float, default=900.0)
    ap.add_argument("--seed", type=int, default=11)
    a = ap.parse_args()
    sc = get_scenario("psce_rotations")
    for name, factor in (("clean", 1.0), ("s06", 0.6), ("s16", 1.6), ("s0", 0.0)):
        sim = simulate(sc, duration=a.duration, seed=a.seed)
        for f in sim.star_frames:
            f.sigma = np.asarray(f.sigma, dtype=float) * factor
        write_simulation(sim, a.out / f"{name}.mcap")
        print(f"{name}: stars' sigma field x{factor:g}")
    g5 = dataclasses.replace(sc, gyro_arw_deg_sqrth=5.0 * sc.gyro_arw_deg_sqrth)
    write_simulation(simulate(g5, duration=a.duration, seed=a.seed), a.out / "g5.mcap")
    print("g5: gyro angle random walk x5, the stated gyro noise unchanged")


if __name__ == "__main__":
    main()
