"""What the 'radial residual vs magnitude' line reads of unseen case ``magbias_radial``.

The case pushes every centroid away from the principal point by 0.03 px per magnitude
fainter than 4 (``tracker_errors.radial_by_mag``).  Per seed, the bag's own run (psce, the
method's baseline model, window 0.5, as ``discover``'s first round) with the stated 0.05
px noise or without it (``--noise-free``; the σ field still 0.05 px), and over the
window's accepted rows, each across the magnitudes' 5-95 % range:

- the truth (the bias's own change) and a straight line in magnitude through it (the hinge);
- what the run took away from the bias (innovations − bias), split into the attitude (each
  frame's least-squares rotation of it), a field smooth over the detector (a degree-5
  polynomial in u, v of the rest: the camera states' kind) and the remainder;
- the innovations' straight line, and the size the line prints (``output.line_tests``).

Run::

    .venv/bin/python benchmarks/magbias_share.py --seeds 21,22
    .venv/bin/python benchmarks/magbias_share.py --seeds 21 --noise-free
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from stellar_cal_ros.diagnosis import stats
from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
from stellar_cal_ros.diagnosis.output import line_tests
from stellar_cal_ros.diagnosis.runstats import quiet
from stellar_cal_ros.methods.replay import bag_data_from_simulation
from stellar_cal_ros.sim import tracker_errors
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

PX_PER_MAG = 0.03  #: the case's bias (unseen_cases._magbias_radial)
FROM_MAG = 4.0
SIGMA = 0.05


def _smooth(u: np.ndarray, v: np.ndarray, y: np.ndarray, degree: int = 5) -> np.ndarray:
    """The least-squares polynomial of ``y`` in ``(u, v)`` (normalised), ``degree`` at most."""
    a, b = (u - 512.0) / 512.0, (v - 512.0) / 512.0
    X = np.stack([a**i * b**j for i in range(degree + 1) for j in range(degree + 1 - i)], 1)
    return X @ np.linalg.lstsq(X, y, rcond=None)[0]


def seed_rows(seed: int, noisy: bool) -> dict[str, float]:
    """One seed's sizes (px across the magnitudes' 5-95 % range)."""
    sc = dataclasses.replace(get_scenario("psce_rotations"), centroid_noise_px=0.0)
    sim = simulate(sc, duration=300.0, seed=seed, effects={})
    centre = np.array([sim.prior.camera.cx, sim.prior.camera.cy])  # the push's centre
    tracker_errors.radial_by_mag(sim, PX_PER_MAG, FROM_MAG)
    tracker_errors.renoise(sim, lambda m, uv: (SIGMA if noisy else 0.0) + 0.0 * m, SIGMA, seed)
    spec = method_spec("psce")
    with quiet():
        run = spec.runner(bag_data_from_simulation(sim), rerun_prior(sim.prior), [],
                          keep_tables=True, eval_fraction=0.5)
    printed = [f.slope_px for f in line_tests(run.residuals, run.calibration, 0.5)
               if f.regressor == "magnitude" and f.component == "radial"]
    res = run.residuals
    win = stats.evaluation_mask(res, 0.5)
    sub = {k: np.asarray(v)[win] for k, v in res.items()}
    ok = stats.accepted(sub) & np.isfinite(np.asarray(sub["magnitude"], dtype=float))
    sub = {k: np.asarray(v)[ok] for k, v in sub.items()}
    m = np.asarray(sub["magnitude"], dtype=float)
    d = np.stack([sub["u"] - centre[0], sub["v"] - centre[1]], 1)
    unit = d / np.linalg.norm(d, axis=1)[:, None]
    bias = PX_PER_MAG * np.maximum(m - FROM_MAG, 0.0)
    nu = np.stack([sub["du"], sub["dv"]], 1)
    taken = nu - bias[:, None] * unit
    J = stats.attitude_columns(sub, run.calibration.camera.fx, run.calibration.camera.fy)
    att = np.zeros_like(taken)
    frame = np.asarray(sub["frame"])
    for f in np.unique(frame):
        i = frame == f
        A = J[i].reshape(-1, 3)
        att[i] = (A @ np.linalg.lstsq(A, taken[i].ravel(), rcond=None)[0]).reshape(-1, 2)
    rest = taken - att
    smooth = np.stack([_smooth(sub["u"], sub["v"], rest[:, k]) for k in (0, 1)], 1)
    lo, hi = np.percentile(m, [5.0, 95.0])

    def line(w):  # a radial displacement's straight line in magnitude, across the range
        return float(np.polyfit(m, (w * unit).sum(1), 1)[0] * (hi - lo))

    return {"lo": lo, "hi": hi, "stars": len(np.unique(sub["catalog_id"])),
            "truth": PX_PER_MAG * (max(hi - FROM_MAG, 0.0) - max(lo - FROM_MAG, 0.0)),
            "straight": float(np.polyfit(m, bias, 1)[0] * (hi - lo)),
            "attitude": -line(att), "smooth": -line(smooth), "other": -line(rest - smooth),
            "innovations": line(nu), "printed": printed[0] if printed else float("nan")}


def main() -> int:
    """Print one row a seed."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="21,22", help="comma-separated")
    ap.add_argument("--noise-free", action="store_true", help="centroids without noise")
    args = ap.parse_args()
    print("| seed | mags 5-95 % | stars | truth | straight line | taken: attitude | smooth "
          "field | other | innovations' line | printed |\n|---|---|---|---|---|---|---|---|"
          "---|---|")
    for seed in (int(s) for s in args.seeds.split(",")):
        r = seed_rows(seed, not args.noise_free)
        print(f"| {seed} | {r['lo']:.2f}-{r['hi']:.2f} | {r['stars']} | {r['truth']:.4f} | "
              f"{r['straight']:.4f} | {r['attitude']:.4f} | {r['smooth']:.4f} | "
              f"{r['other']:.4f} | {r['innovations']:.4f} | {r['printed']:.4f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
