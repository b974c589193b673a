r"""Whether the gyro scale's log-likelihood is a likelihood over seeds (issue 21).

The IMU noise search (:func:`stellar_cal_ros.diagnosis.noise_imu.search_scale`) takes
σ of ln s from the curvature of the stars' window log-likelihood in ln s.  Per seed a psce
bag (200 s) with ``--gyro`` x the stated gyro random walk (its samples smoothed [1 2 1] / 4
unless ``--white``) is run at ln s = 0.8, 0.9, ..., 2.4 (no search), and printed: the
maximum and curvature of a parabola through the 5 grid points around the best, z of the
maximum against the truth with σ = 1 / sqrt(curvature), and the score and curvature at the
truth.  Over seeds: the SD of the maximum against that σ, and Var(score at the truth)
against the mean curvature there (1 for a likelihood: the information equality).

Run::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/imu_loglik_grid.py --seeds 3-42
"""

from __future__ import annotations

import argparse
import dataclasses
import math

import numpy as np

from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.diagnosis.parallel import Runs, Task
from stellar_cal_ros.diagnosis.run import method_spec
from stellar_cal_ros.methods.replay import bag_data_from_simulation
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate


def main() -> None:
    """Print each seed's grid fit and the over-seeds comparison (the module's doc)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="3-42")
    ap.add_argument("--gyro", type=float, default=5.0, help="true gyro noise / stated")
    ap.add_argument("--white", action="store_true", help="do not smooth the gyro samples")
    args = ap.parse_args()
    a, _, b = args.seeds.partition("-")
    xs = np.round(0.8 + 0.1 * np.arange(17), 3)
    t = math.log(args.gyro)
    kernel = np.array([0.0, 1.0, 0.0]) if args.white else np.array([0.25, 0.5, 0.25])
    mle, curv, score, curv_t = [], [], [], []
    print("seed | max ln s | 1/sqrt(curv) | z | score at truth | curv at truth")
    for seed in range(int(a), int(b or a) + 1):
        sc = get_scenario("psce_rotations")
        sc = dataclasses.replace(sc, gyro_arw_deg_sqrth=sc.gyro_arw_deg_sqrth * args.gyro)
        sim = simulate(sc, duration=200.0, seed=seed)
        data = bag_data_from_simulation(sim)
        data.imu_w = np.stack([np.convolve(data.imu_w[:, i], kernel, "same")
                               for i in range(3)], 1)
        spec = method_spec("psce")
        runs = Runs(data, spec, 0.5)
        runs.noise = NoiseScales()
        tasks = [Task(f"g{x}", sim.prior, spec.beyond_baseline([]),
                      noise=NoiseScales(gyro=math.exp(x)), gyro_check=False) for x in xs]
        out = runs.run_all(tasks, None)
        ll = np.array([out[k.key].window["log_likelihood"] for k in tasks])
        i = int(np.argmax(ll))
        lo = max(0, min(i - 2, len(xs) - 5))
        c = np.polyfit(xs[lo:lo + 5], ll[lo:lo + 5], 2)
        j = np.argsort(abs(xs - t))[:5]
        ct = np.polyfit(xs[j] - t, ll[j], 2)
        mle.append(-c[1] / (2 * c[0]))
        curv.append(-2 * c[0])
        score.append(ct[1])
        curv_t.append(-2 * ct[0])
        print(f"{seed} | {mle[-1]:.3f} | {1 / math.sqrt(curv[-1]):.3f} | "
              f"{(mle[-1] - t) * math.sqrt(curv[-1]):+.2f} | {score[-1]:+.1f} | {curv_t[-1]:.1f}",
              flush=True)
    mle, curv, score, curv_t = (np.array(v) for v in (mle, curv, score, curv_t))
    n = len(mle)
    if n < 2:
        return
    z = (mle - t) * np.sqrt(curv)
    print(f"n {n}: SD of the maximum {mle.std(ddof=1):.3f} +- "
          f"{mle.std(ddof=1) / math.sqrt(2 * (n - 1)):.3f} (mean {mle.mean():.3f}, truth "
          f"{t:.3f}) against rms 1/sqrt(curv) {math.sqrt(np.mean(1 / curv)):.3f}; z mean "
          f"{z.mean():+.2f}, SD {z.std(ddof=1):.2f} +- "
          f"{z.std(ddof=1) / math.sqrt(2 * (n - 1)):.2f}; "
          f"Var(score at truth) / mean curvature {score.var(ddof=1) / curv_t.mean():.2f} "
          f"(mean score {score.mean():+.1f} +- {score.std(ddof=1) / math.sqrt(n):.1f})")


if __name__ == "__main__":
    main()
