"""The per-star σ test's level on clean rows (issue 21 item 1, H118).

``noise_stars.star_spread`` (the stated σ wrong star by star) on a psce bag's own rows with
the innovations replaced by white draws at the stated σ (Gaussian, or Student-t of ``--dof``
scaled to that RMS: the F's level under heavy tails): how often its F test is below 1 % /
5 %, the σ factors' spread it reads, and how often ``noise.star_levels`` (significant and
material) accepts it — the gate of the verdict's per-star line and of the size tests' star
levels.  Run::

    OPENBLAS_NUM_THREADS=1 python benchmarks/star_levels_null.py --draws 200 [--dof 4]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from stellar_cal_ros.diagnosis import stats
from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
from stellar_cal_ros.diagnosis.noise import line_noise, star_levels
from stellar_cal_ros.diagnosis.noise_stars import star_spread
from stellar_cal_ros.diagnosis.runstats import evaluate
from stellar_cal_ros.methods.replay import bag_data_from_simulation
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate


def main() -> int:
    """Draw, test, print the level line."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=200)
    ap.add_argument("--seed", type=int, default=3, help="the bag's simulation seed")
    ap.add_argument("--duration", type=float, default=200.0)
    ap.add_argument("--dof", type=float, default=0.0,
                    help="Student-t draws of this many dof (> 2), 0: Gaussian")
    a = ap.parse_args()
    sim = simulate(get_scenario("psce_rotations"), duration=a.duration, seed=a.seed)
    base = evaluate(bag_data_from_simulation(sim), method_spec("psce"),
                    rerun_prior(sim.prior), (), 0.5, keep_residuals=True)
    res0, cam = dict(base.residuals), base.calibration.camera
    mask = stats.evaluation_mask(res0, 0.5)
    n = len(res0["du"])
    rng = np.random.default_rng(11)
    ps, sp, fired, d = [], [], 0, {}
    t0 = time.time()
    for _ in range(a.draws):
        e = rng.standard_normal((2, n)) if not a.dof else \
            rng.standard_t(a.dof, (2, n)) * np.sqrt((a.dof - 2.0) / a.dof)
        res = dict(res0, du=0.05 * e[0], dv=0.05 * e[1], gated=np.zeros(n, bool))
        sn = line_noise(res, mask, cam.fx, cam.fy, (cam.cx, cam.cy), base.calibration.R_imu_st)
        d = star_spread(sn)
        ps.append(d["p_value"])
        sp.append(0.5 * d["spread"])
        fired += star_levels(sn) is not None
    p, s = np.array(ps), np.array(sp)
    print(f"draws {len(p)} ({d['stars']} stars, {d['rows']} rows): p < 1 % in "
          f"{100 * np.mean(p < 0.01):.1f} %, p < 5 % in {100 * np.mean(p < 0.05):.1f} %; the σ "
          f"factors' spread median {np.median(s):.3f}, max {s.max():.3f}; star_levels "
          f"accepted {fired} of {len(p)}  [{time.time() - t0:.0f} s]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
