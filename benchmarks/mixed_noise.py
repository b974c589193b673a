"""White + AR(1) centroid noise (a realistic tracker): do the stars' noise tests hold the level.

A tracker's centroid noise is rarely one AR(1): photon noise is white from frame to frame,
the PSF's and background's errors drift over a few frames.  Here ``psce_rotations`` bags
carry white noise of σ ``--white`` px plus an AR(1) of marginal σ ``--ar`` px and time
constant ``--tau`` frames (:func:`~stellar_cal_ros.sim.tracker_errors.ar1_noise`; the
messages state the total σ, the hypotenuse).  The AR(1) carries ``w = ar² / (white² +
ar²)`` of the variance: lags ``w φ^k``, ``φ = e^(−1/τ)``, the long-run factor a filter that
takes the noise as white needs ``K² = (1 − w) + w (1 + φ)/(1 − φ)`` (0.05 + 0.03 px, τ 5:
``w`` 0.265, ``K²`` 3.39).

Per bag, the run's evaluation window as the diagnosis reads it
(:func:`~stellar_cal_ros.diagnosis.noise_stars.star_noise` at the run's own σ): the tracks'
model (:func:`~stellar_cal_ros.diagnosis.noise_structure.track_model`: lag-1 ρ, the
AR(1)'s coefficient φ and share ``w``), the correlated verdict's ``K = √K²`` with its σ
(:func:`~stellar_cal_ros.diagnosis.noise_structure.correlated`, what the noise line prints
and applies) against the truth above (``z``), the per-star repeat's and the detector cells'
p, and the 'unexplained' lines at p < 1 % family-wise
(:func:`~stellar_cal_ros.diagnosis.output.line_tests`).  ``--pure`` reads the tracks as
one AR(1) of their lag-1 ρ, as before the white + AR(1) model (``SHARE_Z`` infinite:
main's numbers).

Run::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/mixed_noise.py --seeds 21-30
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time

import numpy as np

from stellar_cal_ros.diagnosis import noise_stars, noise_structure, stats
from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
from stellar_cal_ros.diagnosis.output import line_tests
from stellar_cal_ros.diagnosis.runstats import evaluate
from stellar_cal_ros.methods.replay import bag_data_from_simulation
from stellar_cal_ros.sim import tracker_errors
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate


def true_factor(white: float, ar: float, tau: float) -> float:
    """``K²`` of the injected noise: the long-run factor of white + AR(1)."""
    if ar <= 0:
        return 1.0
    w = ar * ar / (white * white + ar * ar)
    return noise_structure.long_run(math.exp(-1.0 / tau), w)


def mixed_bag(white: float, ar: float, tau: float, duration: float, seed: int):
    """``(residual table, prior)`` of a psce run on a white + AR(1) bag."""
    sc = dataclasses.replace(get_scenario("psce_rotations"), centroid_noise_px=white)
    sim = simulate(sc, duration=duration, seed=seed)
    if ar > 0:
        tracker_errors.ar1_noise(sim, ar, tau, seed, stated=float(np.hypot(white, ar)))
    prior = sim.prior
    run = evaluate(bag_data_from_simulation(sim), method_spec("psce"), rerun_prior(prior), (),
                   0.5, keep_residuals=True)
    return run.residuals, prior


def star_noise_of(res, prior) -> noise_stars.StarNoise | None:
    """:func:`~.noise_stars.star_noise` of the evaluation window at the run's own σ."""
    cam = prior.camera
    ok = stats.evaluation_mask(res, 0.5) & ~np.asarray(res["gated"]).astype(bool)
    sig = np.sqrt(0.5 * (np.asarray(res["s_uu"]) + np.asarray(res["s_vv"])))
    return noise_stars.star_noise(res, np.where(ok, sig, np.nan), np.ones(len(sig)), ok,
                                  cam.fx, cam.fy, (cam.cx, cam.cy), prior.R_imu_st)


def verdict(sn: noise_stars.StarNoise) -> dict[str, float] | None:
    """The correlated verdict as the noise line makes it (materiality 0.1, as ``noise``)."""
    return noise_structure.correlated(sn.track_rho, sn.track_pairs, 0.1, sn.track_phi,
                                      sn.track_share, sn.track_factor_sigma)


def main() -> int:
    """Print the per-bag table and the counts."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--white", type=float, default=0.05)
    ap.add_argument("--ar", type=float, default=0.03)
    ap.add_argument("--tau", type=float, default=5.0)
    ap.add_argument("--durations", default="150,300")
    ap.add_argument("--seeds", default="21-30")
    ap.add_argument("--pure", action="store_true", help="one AR(1) of lag-1 rho (main's)")
    ap.add_argument("--no-lines", action="store_true", help="skip the 'unexplained' tests")
    args = ap.parse_args()
    if args.pure:
        noise_structure.SHARE_Z = math.inf
    lo, _, hi = args.seeds.partition("-")
    seeds = range(int(lo), int(hi or lo) + 1)
    K_true = math.sqrt(true_factor(args.white, args.ar, args.tau))
    print(f"white {args.white} px + AR(1) {args.ar} px, tau {args.tau} frames: true K "
          f"{K_true:.3f} (K^2 {K_true**2:.3f}){'; --pure' if args.pure else ''}")
    print(f"{'dur':>4} {'seed':>4} {'rho1':>6} {'phi':>6} {'w':>6} {'K':>14} {'z':>6} "
          f"{'repeat p':>9} {'cells p':>9}  lines p<1%")
    for dur in (float(d) for d in args.durations.split(",")):
        rows = []
        for seed in seeds:
            t0 = time.process_time()
            res, prior = mixed_bag(args.white, args.ar, args.tau, dur, seed)
            sn = star_noise_of(res, prior)
            c = verdict(sn)
            K = c["sigma_scale"] if c else 1.0
            sK = c.get("sigma_scale_sigma", math.nan) if c else math.nan
            z = (K - K_true) / sK if sK > 0 else math.nan
            lines = [] if args.no_lines else [
                f"{f.regressor}/{f.component} {f.p_value:.2g}"
                for f in line_tests(res, prior, 0.5) if f.p_value < 0.01]
            share = sn.track_share
            phi = sn.track_rho if sn.track_phi is None else sn.track_phi
            rows.append((sn.repeat_p, sn.structure_p, z, bool(lines)))
            print(f"{dur:4.0f} {seed:4d} {sn.track_rho:6.3f} {phi:6.3f} {share:6.3f} "
                  f"{K:6.3f}+-{sK:5.3f} {z:6.2f} {sn.repeat_p:9.2g} {sn.structure_p:9.2g}  "
                  f"{'; '.join(lines) or '-'}  ({time.process_time() - t0:.0f} CPU-s)",
                  flush=True)
        R = np.array(rows, dtype=float)
        zf = R[np.isfinite(R[:, 2]), 2]
        print(f"{dur:4.0f} s, {len(R)} bags: repeat p<1% {int(np.sum(R[:, 0] < 0.01))}, "
              f"cells p<1% {int(np.sum(R[:, 1] < 0.01))}, bags with lines "
              f"{int(R[:, 3].sum())}; K within 1 sigma {int(np.sum(np.abs(zf) <= 1))}/{len(zf)}"
              f", 2 sigma {int(np.sum(np.abs(zf) <= 2))}/{len(zf)}, rms z "
              f"{math.sqrt(float(np.mean(zf**2))) if len(zf) else math.nan:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
