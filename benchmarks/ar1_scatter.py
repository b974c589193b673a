r"""The stars' scatter within frames under AR(1) centroid noise, over seeds (issue 21.2).

Each seed: the unseen case ``ar1`` (``psce_rotations``, each star's centroid noise an AR(1)
over frames, τ = 5 frames, marginal σ 0.05 px as stated), the current model's run, and
:func:`~stellar_cal_ros.diagnosis.noise_stars.star_noise` on its evaluation window at the
stated σ: the printed scale (truth 1) with its printed σ, the ρ it was counted with and the
cells' and the repeat's p.  The last line: the mean scale, the seed-to-seed SD against the
mean printed σ, and how often the printed σ holds the truth.

Run::

    .venv/bin/python benchmarks/ar1_scatter.py --duration 300 --seeds 21-50
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from stellar_cal_ros.diagnosis import noise_stars
from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
from stellar_cal_ros.diagnosis.runstats import evaluate
from stellar_cal_ros.diagnosis.stats import evaluation_mask
from stellar_cal_ros.methods.replay import bag_data_from_simulation
from stellar_cal_ros.sim import tracker_errors
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

SIGMA = 0.05


def one(duration: float, seed: int):
    """The ``ar1`` bag of ``seed``: its stars' noise estimate at the stated σ."""
    sc = dataclasses.replace(get_scenario("psce_rotations"), centroid_noise_px=0.0)
    sim = simulate(sc, duration=duration, seed=seed)
    tracker_errors.ar1_noise(sim, SIGMA, 5.0, seed)
    run = evaluate(bag_data_from_simulation(sim), method_spec("psce"), rerun_prior(sim.prior),
                   (), 0.5, keep_residuals=True)
    res, cam = run.residuals, sim.prior.camera
    sig = np.full(len(res["t"]), SIGMA)
    return noise_stars.star_noise(res, sig, sig, evaluation_mask(res, 0.5), cam.fx, cam.fy,
                                  (cam.cx, cam.cy), sim.prior.R_imu_st)


def main() -> int:
    """Print one row per seed and the summary."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--seeds", default="21-50", help="a-b or a,b,c")
    a = ap.parse_args()
    if "-" in a.seeds:
        lo, hi = (int(x) for x in a.seeds.split("-"))
        seeds = list(range(lo, hi + 1))
    else:
        seeds = [int(x) for x in a.seeds.split(",")]
    print(f"{'seed':>4} {'scale':>7} {'sigma':>7} {'rho':>6} {'cells p':>8} {'repeat p':>8}")
    rows = []
    for seed in seeds:
        sn = one(a.duration, seed)
        rows.append((sn.scale, sn.sigma))
        print(f"{seed:4d} {sn.scale:7.4f} {sn.sigma:7.4f} {sn.scatter_rho:6.3f} "
              f"{sn.structure_p:8.3g} {sn.repeat_p:8.3g}", flush=True)
    s, e = np.array(rows).T
    z = (s - 1.0) / e
    print(f"{len(s)} seeds: scale {s.mean():.4f} +- {s.std(ddof=1) / np.sqrt(len(s)):.4f} "
          f"(truth 1), seed SD {s.std(ddof=1):.4f}, mean printed sigma {e.mean():.4f}; "
          f"|z| < 1: {np.mean(abs(z) < 1):.0%}, < 2: {np.mean(abs(z) < 2):.0%}, "
          f"mean z^2 {np.mean(z**2):.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
