"""Zhang et al. (IEEE Access 2018) Table 2 against our inertial-frame and traditional filters.

Five Table 2 groups (true installation errors from the paper), sway of eqs. 18-19 over the
three base orientations of the ``swaying`` scenario, Table 1 sensor errors, 3" star sensor
(0.058 px), calibrated camera (Zhang assume a calibrated star sensor).  Conditions:

* ``sway``        — IMU scale factor / misalignment pre-calibrated (Zhang's filter model,
  "misalignment and scale factor are ignored"); gyro/accel bias and noise of Table 1.
* ``stationary``  — the same with zero sway (angular and linear amplitude 0).
* ``sway+E``      — Table 1 complete (100 ppm, 100" gyro misalignment) with
  ``gyro_scale_factor, gyro_misalignment, accel_scale_factor`` added to the model.

Columns per axis: the paper's proposed (P) and traditional (T) estimates, ours with error and
1σ, the posterior Cramér–Rao bound of the inertial filter's model on that run
(:func:`~stellar_cal_ros.methods.swaying.crlb_swaying`: Jacobians on the true trajectory and
parameters; no bound is given for the traditional filter, whose model is wrong on a swaying
base).  After each group: per axis the RMS error over the seeds, the RMS bound and the
efficiency RMS error / bound (≈ 1 for an efficient estimator; it scatters by ~1/√(2·seeds)),
and the mean NEES (3 dof, consistent = 3).

Run: ``python benchmarks/swaying_vs_paper.py [--groups 1,2,3,4,5] [--seeds N] [--no-crlb]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import time

import numpy as np

from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.methods.replay import BagData
from stellar_cal_ros.methods.swaying import crlb_swaying, replay_swaying
from stellar_cal_ros.methods.traditional import replay_traditional
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

#: Zhang Table 2: true value, proposed method, traditional method (arcsec, x y z)
TABLE2 = {
    1: ((120, 180, -240), (119.27, 180.68, -240.19), (117.72, 178.60, -237.31)),
    2: ((-200, 160, 90), (-198.50, 159.22, 89.49), (-202.45, 165.09, 86.33)),
    3: ((100, 100, 100), (99.83, 100.12, 99.41), (97.55, 98.17, 96.28)),
    4: ((-200, -200, -200), (-200.79, -200.88, -199.37), (-204.21, -203.46, -196.63)),
    5: ((60, -220, 150), (59.78, -219.48, 149.87), (58.48, -223.79, 155.22)),
}
CALIBRATED_CAMERA = {"principal_point": [0.0, 0.0], "radial_k1k2": [0.0, 0.0],
                     "tangential": [0.0, 0.0]}
NO_IMU_MATRIX = {"gyro_scale_factor": [0.0] * 3, "gyro_misalignment": [0.0] * 6,
                 "accel_scale_factor": [0.0] * 3}
E_EFFECTS = ["gyro_scale_factor", "gyro_misalignment", "accel_scale_factor"]


def scenario(stationary: bool = False):
    """The ``swaying`` scenario; ``stationary``: same bases, zero sway."""
    sc = get_scenario("swaying")
    if stationary:
        base = sc.motion_factory

        def factory(dur):
            return dataclasses.replace(base(dur), amplitude_deg=(0.0, 0.0, 0.0),
                                       velocity_amplitude=(0.0, 0.0, 0.0))

        sc.motion_factory = factory
        sc.name = "swaying_stationary"
    return sc


def bag_data(res) -> BagData:
    """BagData straight from a simulation (what read_bag_data gives for its bag)."""
    imu = res.imu
    t0_ns = int(imu.stamp_ns[0]) - int(np.median(np.diff(imu.stamp_ns[:1000])))
    return BagData(t0_ns, (imu.stamp_ns - t0_ns) * 1e-9, imu.angular_velocity,
                   imu.linear_acceleration, res.star_frames, res.scenario.site,
                   res.head_temperature, res.air_temperature, res.pressure)


def run_case(group: int, condition: str = "sway", seed: int = 0, duration=None,
             crlb: bool = True) -> dict:
    """Simulate one case and run both methods; installation in arcsec, errors, sigmas.

    ``crlb``: also the Cramér–Rao bound of the inertial filter's model (``out["crlb"]``,
    arcsec per axis).
    """
    true = np.array(TABLE2[group][0], dtype=float)
    effects = {"installation": list(true), **CALIBRATED_CAMERA}
    if condition != "sway+E":
        effects.update(NO_IMU_MATRIX)
    res = simulate(scenario(condition == "stationary"), seed=seed, duration=duration,
                   effects=effects)
    data = bag_data(res)
    extra = E_EFFECTS if condition == "sway+E" else []
    out = {"group": group, "condition": condition, "seed": seed, "true": true}
    for name, fn in (("inertial", replay_swaying), ("traditional", replay_traditional)):
        t = time.perf_counter()
        r = fn(data, res.prior, extra)
        f = r.filter
        sl = f.model.slices["installation"]
        est = f.theta[sl] / ARCSEC
        sig = f.sigma()[f.it][sl] / ARCSEC
        P = f.P[f.it, f.it][sl, sl] / ARCSEC**2
        err = est - true
        out[name] = {"est": est, "err": err, "sigma": sig,
                     "nees": float(err @ np.linalg.solve(P, err)),
                     "seconds": time.perf_counter() - t, "gated": r.counters["stars_gated"]}
    if crlb:
        b = crlb_swaying(data, res.prior, res.truth, extra).filter
        out["crlb"] = b.sigma()[b.it][b.model.slices["installation"]] / ARCSEC
    return out


def main(argv=None) -> int:
    """Print the table (and mean NEES) for the selected groups and conditions."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--groups", default="1,2,3,4,5")
    ap.add_argument("--conditions", default="sway,stationary,sway+E")
    ap.add_argument("--seeds", type=int, default=1, help="Monte-Carlo runs per case")
    ap.add_argument("--no-crlb", action="store_true", help="skip the Cramér–Rao bound")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    groups = [int(g) for g in args.groups.split(",")]
    crlb = not args.no_crlb
    print(f"{'grp':>3} {'cond':>10} {'axis':>4} {'true':>7} | {'paper P':>8} {'paper T':>8} | "
          f"{'inertial':>9} {'err':>6} {'1σ':>5} {'CRLB':>5} | {'tradit.':>9} {'err':>6} "
          f"{'1σ':>5}")
    nees = {"inertial": [], "traditional": []}
    for cond in args.conditions.split(","):
        for g in groups:
            errs, bounds, nees_case = [], [], []
            for seed in range(args.seeds):
                r = run_case(g, cond, seed, crlb=crlb)
                b = r.get("crlb", np.full(3, np.nan))
                for k, ax in enumerate("xyz"):
                    pP, pT = TABLE2[g][1][k], TABLE2[g][2][k]
                    i, t = r["inertial"], r["traditional"]
                    print(f"{g:>3} {cond:>10} {ax:>4} {r['true'][k]:7.1f} | {pP:8.2f} {pT:8.2f} | "
                          f"{i['est'][k]:9.2f} {i['err'][k]:+6.2f} {i['sigma'][k]:5.2f} "
                          f"{b[k]:5.2f} | "
                          f"{t['est'][k]:9.2f} {t['err'][k]:+6.2f} {t['sigma'][k]:5.2f}")
                for m in nees:
                    nees[m].append(r[m]["nees"])
                errs.append(r["inertial"]["err"])
                bounds.append(b)
                nees_case.append(r["inertial"]["nees"])
                sys.stdout.flush()
            rms = np.sqrt(np.mean(np.square(errs), axis=0))
            bnd = np.sqrt(np.mean(np.square(bounds), axis=0))
            print(f"{g:>3} {cond:>10}  inertial over {args.seeds} seed(s): RMS error "
                  + " ".join(f"{v:.3f}" for v in rms) + "\"; CRLB "
                  + " ".join(f"{v:.3f}" for v in bnd) + "\"; efficiency RMS/CRLB "
                  + " ".join(f"{v:.2f}" for v in rms / bnd)
                  + f"; mean NEES {np.mean(nees_case):.2f}")
    for m, v in nees.items():
        print(f"mean NEES (3 dof, consistent = 3) {m}: {np.mean(v):.2f} over {len(v)} runs")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
