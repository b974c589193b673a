"""A candidate's score test on clean bags: is its statistic centred where its chi2 says.

The screening's score test of a candidate (``LM = sᵀ I⁻¹ s``) is χ²_k on a bag the model
fits, and each component of ``s`` along an eigendirection of ``I`` (``z = vᵀ s / √λ``) is
N(0, 1).  On clean swaying bags ``gyro_scale_factor`` was 'significant' on 2 of 50
(``benchmarks/false_alarms.py``); this script measures why: per seed, the current model's
run with the candidate as a consider parameter, then ``z`` per eigendirection and LM.  A
mean of ``z`` away from 0 over the seeds is a deterministic signal in the bag that the
filter does not model (not a wrong reference); ``--imu-rate`` and ``--star-phase`` change
the scenario's IMU rate and the first frame's offset from the start (2 Hz frames: on the
IMU grid when the phase is a multiple of the IMU period).

Run::

    .venv/bin/python benchmarks/score_null.py --seeds 20
    .venv/bin/python benchmarks/score_null.py --seeds 10 --imu-rate 400
    .venv/bin/python benchmarks/score_null.py --seeds 10 --star-phase 0.25
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
from stellar_cal_ros.diagnosis.injection import SCENARIO, SWAY_CLEAN
from stellar_cal_ros.methods.replay import bag_data_from_simulation
from stellar_cal_ros.methods.screening import score_tests
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate


def seed_scores(method: str, candidate: str, seed: int, duration: float,
                imu_rate: float | None, star_phase: float | None
                ) -> tuple[float, np.ndarray, np.ndarray]:
    """``(LM, z per eigendirection of I, its eigenvalues over the largest)`` of one clean bag.

    Both in ascending eigenvalue order.
    """
    sc = get_scenario(SCENARIO[method])
    if imu_rate is not None:
        sc.imu_rate = imu_rate
    if star_phase is not None:
        sc.star_phase_s = star_phase
    clean = dict(SWAY_CLEAN) if method == "swaying_base" else {}
    sim = simulate(sc, duration=duration, seed=seed, effects=clean)
    run = method_spec(method).runner(bag_data_from_simulation(sim), rerun_prior(sim.prior), [],
                                     keep_tables=False, eval_fraction=0.5,
                                     consider=[candidate])
    c = score_tests(run, [candidate])[candidate]
    w, V = np.linalg.eigh(c.info)
    V = V * np.sign(V[np.argmax(np.abs(V), axis=0), np.arange(len(w))])  # a fixed sign
    return c.lm, (V.T @ (c.info @ c.estimate)) / np.sqrt(w), w / w.max()


def main() -> int:
    """Print LM and z per seed, then their means against the χ² reference."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--method", default="swaying_base", choices=sorted(SCENARIO))
    ap.add_argument("--candidate", default="gyro_scale_factor")
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=2000)
    ap.add_argument("--duration", type=float, default=200.0)
    ap.add_argument("--imu-rate", type=float, default=None)
    ap.add_argument("--star-phase", type=float, default=None)
    args = ap.parse_args()
    lms, zs, ws = [], [], []
    t0 = time.process_time()
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        lm, z, w = seed_scores(args.method, args.candidate, seed, args.duration, args.imu_rate,
                               args.star_phase)
        lms.append(lm)
        zs.append(z)
        ws.append(w)
        print(f"seed {seed}: LM {lm:6.2f}  z {np.array2string(z, precision=2)}  eigenvalue / "
              f"largest {np.array2string(w, precision=1)}", flush=True)
    Z = np.asarray(zs)
    se = Z.std(0, ddof=1) / np.sqrt(len(Z))
    print(f"\n{args.candidate} on {len(Z)} clean {args.method} bags ({args.duration:.0f} s, "
          f"IMU {args.imu_rate or 'scenario'} Hz, star phase {args.star_phase or 'scenario'}):"
          f" mean LM {np.mean(lms):.2f} (chi2_{Z.shape[1]}: {Z.shape[1]}), mean z "
          f"{np.array2string(Z.mean(0), precision=2)} +- {np.array2string(se, precision=2)}"
          f" (N(0,1): 0), sd z {np.array2string(Z.std(0, ddof=1), precision=2)}, mean z²"
          f" {np.array2string((Z ** 2).mean(0), precision=2)} (χ²₁: 1), eigenvalue / largest"
          f" (geometric mean) {np.array2string(np.exp(np.log(ws).mean(0)), precision=1)}"
          f" [{time.process_time() - t0:.0f} CPU-s]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
