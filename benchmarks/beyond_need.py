"""The 'beyond' line's "need x N +- e" over seeds (issue 21, H92).

psce 200 s; the gyro's samples carry its stated white noise plus white noise k x the
stated averaged over 10 samples (a drift the samples' second differences barely see, ~
white to the stars): the stars need sqrt(1 + k²) x the stated noise, the samples show
sqrt(1 + 4 k² / 600), and the line prints the first over the second.  Per seed: the
printed need and σ, z = ln(need / truth) / (e / need); then their mean and SD.

Run::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/beyond_need.py --k 3 --seeds 3-22
"""

from __future__ import annotations

import argparse
import re

import numpy as np

from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.core.units import DEG_PER_SQRT_HOUR
from stellar_cal_ros.diagnosis.run import measure_bag
from stellar_cal_ros.methods.replay import bag_data_from_simulation
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate


def with_drift(sim, data, k: float, seed: int, n: int = 10) -> None:
    """Add to ``data``'s gyro samples white noise ``k`` x the stated averaged over ``n``.

    (``sim``: the simulation ``data`` is of; the draws from ``default_rng(100 + seed)``.)
    """
    per_sample = sim.scenario.gyro_arw_deg_sqrth * DEG_PER_SQRT_HOUR / np.sqrt(0.01)
    c = np.cumsum(k * per_sample * np.random.default_rng(100 + seed).standard_normal(
        (len(data.imu_w) + n, 3)), axis=0)
    data.imu_w = data.imu_w + (c[n:] - c[:-n])[:len(data.imu_w)] / n


def main() -> int:
    """One line per seed, then the summary."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--k", type=float, default=3.0)
    ap.add_argument("--seeds", default="3-22")
    args = ap.parse_args()
    a, b = (int(x) for x in args.seeds.split("-"))
    k, n = args.k, 10
    truth = np.sqrt(1 + k**2) / np.sqrt(1 + 4 * k**2 / (6 * n**2))
    z, got = [], []
    for seed in range(a, b + 1):
        sim = simulate(get_scenario("psce_rotations"), duration=200.0, seed=seed)
        data = bag_data_from_simulation(sim)
        with_drift(sim, data, k, seed, n)
        v = measure_bag(data, sim.prior, "psce", [], NoiseScales())
        line = next((x for x in v.lines() if x.startswith("the stars see more")), "")
        m = re.search(r"need x(\S+) \+- (\S+) the noise", line)
        if not m:
            print(f"{seed} | no 'beyond' line")
            continue
        need, e = float(m.group(1)), float(m.group(2))
        got.append(need)
        z.append(np.log(need / truth) / (e / need))
        print(f"{seed} | {need:.3g} +- {e:.2g} | z {z[-1]:+.2f}", flush=True)
    print(f"k {k:g}, truth {truth:.3f}, n {len(z)}: need mean {np.mean(got):.3f}, "
          f"SD {np.std(got, ddof=1):.3f}; z mean {np.mean(z):+.2f}, SD {np.std(z, ddof=1):.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
