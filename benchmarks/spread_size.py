"""The residual-spread (size) line's size against an injected spread (issue 21, H92).

A clean psce bag's own rows (seed 3, 200 s; frames, stars, the filter's covariances), its
innovations replaced by draws whose σ grows 20 % per magnitude: the size a 'residual
spread (size) vs magnitude' line prints (``stats.size_through_fit``: the innovations' size
read through each frame's attitude fit), the straight line of the within-frame sizes it
replaced, and the raw innovations' straight line, over the truth sqrt(pi/2) x the σ's
change across the magnitudes' 5-95 % range.

Run::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/spread_size.py --draws 100
"""

from __future__ import annotations

import argparse

import numpy as np

from stellar_cal_ros.diagnosis import stats
from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
from stellar_cal_ros.diagnosis.runstats import evaluate
from stellar_cal_ros.methods.replay import bag_data_from_simulation
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate


def main() -> int:
    """Print each reading's mean over the truth, with its standard error."""
    ap = argparse.ArgumentParser()
    ap.add_argument("--draws", type=int, default=100)
    ap.add_argument("--seed", type=int, default=3)
    args = ap.parse_args()
    sim = simulate(get_scenario("psce_rotations"), duration=200.0, seed=args.seed)
    base = evaluate(bag_data_from_simulation(sim), method_spec("psce"), rerun_prior(sim.prior),
                    (), 0.5, keep_residuals=True)
    res0, cam = dict(base.residuals), base.calibration.camera
    mask = stats.evaluation_mask(res0, 0.5) & stats.accepted(res0)
    sub0 = {k: np.asarray(v)[mask] for k, v in res0.items()}
    mag = np.asarray(sub0["magnitude"], dtype=float)
    n = len(mag)
    sig = np.sqrt(0.5 * (sub0["s_uu"] + sub0["s_vv"]))
    lo, hi = np.percentile(mag, [5, 95])
    truth = np.sqrt(np.pi / 2) * 0.05 * 0.2 * (hi - lo)
    print(f"rows {n}, stars a frame {n / len(np.unique(sub0['frame'])):.1f}, "
          f"truth {truth:.5f} px")
    rng = np.random.default_rng(5)
    got: dict[str, list[float]] = {"through the fit": [], "within-frame straight line": [],
                                   "raw innovations' straight line": []}
    for _ in range(args.draws):
        s = 0.05 * (1.0 + 0.2 * (mag - mag.mean()))
        du, dv = s * rng.standard_normal(n), s * rng.standard_normal(n)
        sub = dict(sub0, du=du, dv=dv)
        r, _, _ = stats.within_frame(sub, sig, cam.fx, cam.fy)
        y = np.hypot(r[:, 0] * sig, r[:, 1] * sig)
        ok = np.isfinite(y)
        got["through the fit"].append(stats.size_through_fit(sub, sig, (cam.fx, cam.fy), mag, y))
        got["within-frame straight line"].append(np.polyfit(mag[ok], y[ok], 1)[0] * (hi - lo))
        got["raw innovations' straight line"].append(
            np.polyfit(mag, np.hypot(du, dv), 1)[0] * (hi - lo))
    print("reading | mean / truth | its SE")
    for name, a in got.items():
        a = np.asarray(a) / truth
        print(f"{name} | {a.mean():.3f} | {a.std(ddof=1) / np.sqrt(len(a)):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
