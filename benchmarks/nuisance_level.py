r"""The stars' structure fits under AR(1) centroid noise: how often they fire, and their power.

:func:`~stellar_cal_ros.diagnosis.noise_stars.star_noise` removes a bias periodic in the
centroids' sub-pixel phase (:func:`~stellar_cal_ros.diagnosis.noise_structure.minus_subpixel`)
and a rolling shutter's shape
(:func:`~stellar_cal_ros.diagnosis.noise_structure.minus_rolling`) where their χ² is
significant at ``noise_stars.ALPHA`` (1 %), both fitted together and each tested given the
other (:func:`~stellar_cal_ros.diagnosis.noise_structure.minus_fits`). On noise alone each must
fire in ≈ 1 % of the draws. One residual table of a ``psce_rotations`` bag (the current model's
run, its evaluation half), its ``du, dv`` replaced by draws of the centroid noise along each
star's rows (``--rho``: an AR(1) of that coefficient per frame, 0 white, ``RHO:SHARE`` white +
AR(1), marginal σ 0.05 px as stated), then ``star_noise``: the share of draws whose fits fire
(p < 1 %) with its binomial σ (at least the σ of 1 % over the draws), their mean p (0.5 ±
1/√(12 draws) on noise alone), the mean scale ± its SD over the draws, the mean printed σ of
the scale, the SD over it (1 when the printed σ is honest) and the tracks' mean lag-1 ρ.
``--subpixel A`` adds ``A`` px × ``sin 2π u`` (and v) to every draw, ``--readout MS`` a rolling
shutter of that readout: the share then is the fit's power.

Run::

    .venv/bin/python benchmarks/nuisance_level.py --duration 300 --reps 200 --rho 0.81873,0
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from stellar_cal_ros.diagnosis import noise_stars
from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
from stellar_cal_ros.diagnosis.runstats import evaluate
from stellar_cal_ros.diagnosis.stats import evaluation_mask, rolling_columns
from stellar_cal_ros.methods.replay import bag_data_from_simulation
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

SIGMA = 0.05


def table(duration: float, seed: int, path: str | None = None):
    """The residual table of one ``psce_rotations`` bag's run, its camera and installation.

    ``path``: an ``.npz`` the table is kept in (read when it exists: the run takes minutes).
    """
    sim = simulate(get_scenario("psce_rotations"), duration=duration, seed=seed)
    cam, R = sim.prior.camera, sim.prior.R_imu_st
    if path and os.path.exists(path):
        with np.load(path) as z:
            return {k: z[k] for k in z.files}, cam, R
    run = evaluate(bag_data_from_simulation(sim), method_spec("psce"), rerun_prior(sim.prior),
                   (), 0.5, keep_residuals=True)
    res = {k: np.asarray(v) for k, v in run.residuals.items()}
    if path:
        np.savez(path, **res)
    return res, cam, R


def track_noise(res, rng, rho: float, share: float = 1.0) -> np.ndarray:
    """Unit-variance centroid noise ``(n, 2)`` along each star's rows (its frames' gaps kept).

    An AR(1) of coefficient ``rho`` per frame carrying ``share`` of the variance, the rest
    white (``rho`` 0: white).
    """
    star, frame = np.asarray(res["catalog_id"]), np.asarray(res["frame"]).astype(float)
    order = np.lexsort((frame, star))
    e = rng.standard_normal((len(star), 2))
    out = np.empty((len(star), 2))
    prev_s, prev_f, x = None, 0.0, np.zeros(2)
    for i in order:
        if rho > 0.0 and star[i] == prev_s:
            a = rho ** (frame[i] - prev_f)
            x = a * x + np.sqrt(1.0 - a * a) * e[i]
        else:
            x = e[i].copy()
        out[i] = x
        prev_s, prev_f = star[i], frame[i]
    if share != 1.0:
        out = np.sqrt(share) * out + np.sqrt(1.0 - share) * rng.standard_normal(out.shape)
    return out


def one(res, cam, R, noise: np.ndarray, subpixel: float = 0.0, readout_s: float = 0.0):
    """``star_noise`` on the table with ``noise`` (px) as its residuals, plus the structure."""
    r = dict(res)
    d = noise.copy()
    if subpixel:
        d += subpixel * np.sin(2.0 * np.pi * np.stack([res["u_pred"], res["v_pred"]], 1))
    if readout_s:  # row v read (v/H − ½) T after the stamp: (v − c_y) T/H × its velocity
        d += readout_s / cam.height * rolling_columns(res, (cam.fx, cam.fy), (cam.cx, cam.cy),
                                                      R)
    r["du"], r["dv"] = d[:, 0], d[:, 1]
    sig = np.full(len(res["t"]), SIGMA)
    return noise_stars.star_noise(r, sig, sig, evaluation_mask(res, 0.5), cam.fx, cam.fy,
                                  (cam.cx, cam.cy), R)


def main() -> int:
    """Print one row per noise model."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--bag-seed", type=int, default=21)
    ap.add_argument("--reps", type=int, default=200)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--rho", default="0.81873,0", help="RHO or RHO:SHARE, comma-separated")
    ap.add_argument("--subpixel", type=float, default=0.0, help="pixel locking amplitude, px")
    ap.add_argument("--readout", type=float, default=0.0, help="rolling shutter readout, ms")
    ap.add_argument("--table", help="an .npz to keep the run's residual table in")
    ap.add_argument("--white-fits", action="store_true",
                    help="the fits' chi2 taken as white whatever the tracks (before H72)")
    a = ap.parse_args()
    if a.white_fits:
        noise_stars._fit_lags = lambda *args: None
    res, cam, R = table(a.duration, a.bag_seed, a.table)
    print(f"{'rho':>7} {'share':>5} {'subpix':>6} {'readout':>7} {'draws':>5} "
          f"{'sub-pixel fires':>16} {'rolling fires':>14} {'mean p sub':>10} "
          f"{'mean p roll':>11} {'scale':>14} {'sigma':>6} {'SD/sigma':>8} {'rho hat':>7}")
    for item in a.rho.split(","):
        rho_s, _, share_s = item.partition(":")
        rho, share = float(rho_s), float(share_s or 1.0)
        rng = np.random.default_rng(a.seed)
        t0 = time.process_time()
        P, S, RH = [], [], []
        for _ in range(a.reps):
            sn = one(res, cam, R, SIGMA * track_noise(res, rng, rho, share), a.subpixel,
                     a.readout * 1e-3)
            P.append((sn.subpixel_p, sn.rolling_p))
            S.append((sn.scale, sn.sigma))
            RH.append(sn.track_rho)
        P = np.array(P)
        fire = (P < noise_stars.ALPHA).mean(0)
        se = np.sqrt(np.maximum(fire * (1 - fire), noise_stars.ALPHA * (1 - noise_stars.ALPHA))
                     / a.reps)
        S, E = np.array(S).T
        print(f"{rho:7.4g} {share:5.3g} {a.subpixel:6.3g} {a.readout:7.3g} {a.reps:5d} "
              f"{fire[0]:7.3f}+-{se[0]:.3f} {fire[1]:7.3f}+-{se[1]:.3f} "
              f"{P[:, 0].mean():10.3f} {P[:, 1].mean():11.3f} "
              f"{S.mean():7.4f}+-{S.std(ddof=1):.4f} {E.mean():6.4f} "
              f"{S.std(ddof=1) / E.mean():8.3f} {np.mean(RH):7.3f}", flush=True)
        print(f"        ({time.process_time() - t0:.1f} CPU-s)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
