"""The 'unexplained' structure tests on clean bags: does each printed p hold its level.

On a bag the model fits, the diagnosis tests the current model's residuals against every
regressor (:func:`~stellar_cal_ros.diagnosis.stats.regressor_tests`).  This script runs the
current model (stated noise) on clean bags (:func:`~stellar_cal_ros.diagnosis.injection.
clean_case`, the false-alarm benchmark's bags), collects every test's unadjusted p (the
frame-robust t referred to t_ν) and the same t referred to N(0, 1), and prints the share of
tests below 5 %, 1 % and 0.1 % (each must be its level; the ripple tests of
:func:`~stellar_cal_ros.diagnosis.stats.shaped_tests` among them, and on their own row), with
the bags that print a line (Bonferroni at 1 %, the per-star and periodic tests included).
Only the current model's run: a few seconds per bag, against ~10 s for a whole diagnosis
(``benchmarks/false_alarms.py``), whose 'unexplained' column is the same test on the same
run when no candidate is significant and the noise is kept as stated.

Run::

    .venv/bin/python benchmarks/structure_null.py --seeds 50 --cases psce,swaying
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy import stats as sps

from stellar_cal_ros.diagnosis import stats
from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
from stellar_cal_ros.diagnosis.injection import clean_case
from stellar_cal_ros.diagnosis.noise import star_lines
from stellar_cal_ros.diagnosis.runstats import evaluate

CASES = {"psce": ("psce", False, 300.0), "psce+sky": ("psce", True, 300.0),
         "swaying": ("swaying_base", False, 200.0),
         "swaying+sky": ("swaying_base", True, 200.0)}


def bag_tests(name: str, seed: int) -> tuple[list[tuple[float, float]], list[float], list]:
    """One clean bag's structure tests.

    ``([(t, p under t_ν)] of the regressor tests, [p] of the per-star and periodic tests,
    the lines printed)``.
    """
    method, sky, duration = CASES[name]
    data, prior, effects = clean_case(method, sky, seed, duration)
    run = evaluate(data, method_spec(method), rerun_prior(prior), tuple(effects), 0.5,
                   keep_residuals=True)
    res, cam = run.residuals, prior.camera
    mask = stats.evaluation_mask(res, 0.5)
    centre = (cam.cx, cam.cy)
    seen: list[tuple[float, float]] = []
    inner = stats.frame_robust_t

    def record(x, y, cluster, lags=None, **kw):
        out = inner(x, y, cluster, lags, **kw)  # (t, p), or (t, p, ν) with dof=True
        seen.append(out[:2])
        return out

    extra = star_lines(res, mask, cam.fx, cam.fy, centre, prior.R_imu_st)
    extra_p = [f.p_value for f in extra]  # regressor_tests adjusts them in place
    made = stats.RegressorFinding
    ripple: list[float] = []

    class Recorded(made):
        def __init__(self, *args, **kw):  # the ripple tests' unadjusted p, as they are made
            super().__init__(*args, **kw)
            if self.regressor.split(" (")[0] in ("u", "v") and stats.RIPPLE in self.regressor:
                ripple.append(self.p_value)

    stats.frame_robust_t = record
    stats.RegressorFinding = Recorded
    try:
        lines = stats.regressor_tests(res, mask, centre, focal=(cam.fx, cam.fy), extra=extra,
                                      R_imu_st=prior.R_imu_st, height=cam.height,
                                      width=cam.width)
    finally:
        stats.frame_robust_t = inner
        stats.RegressorFinding = made
    return seen, extra_p, lines, ripple


def main() -> int:
    """Print the levels of the tests over the seeds, per reference."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--first-seed", type=int, default=2000)
    ap.add_argument("--cases", default="psce,swaying")
    args = ap.parse_args()
    t0 = time.process_time()
    T, P, E, R, flagged, n = [], [], [], [], [], 0
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        for name in args.cases.split(","):
            seen, extra, lines, ripple = bag_tests(name, seed)
            n += 1
            T += [t for t, _ in seen]
            P += [p for _, p in seen]
            E += extra
            R += ripple
            if lines:
                flagged.append(f"{name} {seed}: " + ", ".join(
                    f"{f.component} vs {f.regressor} (t={f.statistic:.1f})" for f in lines))
    T, P, E, R = np.asarray(T), np.asarray(P), np.asarray(E), np.asarray(R)
    normal = 2.0 * sps.norm.sf(np.abs(T))
    print(f"structure tests on {n} clean bags ({args.cases}, seeds {args.first_seed}-"
          f"{args.first_seed + args.seeds - 1}): {len(T)} regressor tests, {len(E)} per-star "
          f"and periodic tests [{time.process_time() - t0:.0f} CPU-s]")
    print(f"{'share of p below':28s} {'5 %':>7s} {'1 %':>7s} {'0.1 %':>7s}")
    for label, p in (("t_nu (printed)", P), ("same t, N(0,1)", normal),
                     (f"of which ripple ({len(R)})", R), ("per-star + periodic", E)):
        print(f"{label:28s} " + " ".join(f"{np.mean(p < a):7.2%}" for a in (0.05, 0.01, 0.001)))
    print(f"bags with an 'unexplained' line (Bonferroni 1 %): {len(flagged)} of {n}")
    for line in flagged:
        print("  " + line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
