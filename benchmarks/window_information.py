"""Where a candidate's information lies: the evaluation window's against the whole run's.

The decision's statistics (the screening's score test and the augmented run's likelihood
ratio) are sums over the evaluation window, so the MDB is stated for the window's
information ``I_W = Σ_window Aᵀ S⁻¹ A`` (:func:`stellar_cal_ros.diagnosis.discover.
window_information`).  Per effect this prints, on one bag, the screening run's information
over the window and over every frame, the augmented run's (``P_post⁻¹ − P_prior⁻¹``, which
should equal the second), the window's share of the information against its share of the
accepted stars, and the MDB per parameter both ways: the window's (printed since
2026-11-28 for a candidate re-run as for one screened out) and the whole run's times the
stars' share (what a re-run candidate printed before).  Run::

    python benchmarks/window_information.py BAG.mcap BAG.prior.yaml swaying_base \
        gyro_scale_factor,accel_scale_factor
"""

from __future__ import annotations

import argparse

import numpy as np

from stellar_cal_ros.diagnosis import reliability, runstats
from stellar_cal_ros.diagnosis.discover import ALPHA, method_spec, rerun_prior
from stellar_cal_ros.effects import registry
from stellar_cal_ros.io.calibration import load_calibration


def main() -> int:
    """Print the table for the bag, prior, method and effects of the command line."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("bag")
    ap.add_argument("prior")
    ap.add_argument("method")
    ap.add_argument("effects", help="comma-separated effect ids")
    ap.add_argument("--candidates", type=int, default=15,
                    help="the round's testable candidates (the MDB's Bonferroni level)")
    a = ap.parse_args()
    spec = method_spec(a.method)
    prior = rerun_prior(load_calibration(a.prior))
    effects = a.effects.split(",")
    alpha = ALPHA / (2 * a.candidates)  # score and ratio: two statistics
    window = runstats.evaluate(a.bag, spec, prior, (), 0.5, screen=tuple(effects))
    every = runstats.evaluate(a.bag, spec, prior, (), 1.0, screen=tuple(effects))
    print(f"{'effect.parameter':28s} {'I window':>10s} {'I all':>10s} {'I augmented':>11s} "
          f"{'window/all':>10s} {'stars':>6s} {'MDB window':>11s} {'MDB all x share':>15s}")
    for eid in effects:
        names = registry.create(eid).parameter_names
        iw = np.atleast_2d(window.scores[eid][2])
        ia = np.atleast_2d(every.scores[eid][2])
        run = runstats.evaluate(a.bag, spec, prior, (eid,), 0.5, candidate=True)
        sl = run.block(eid)
        post = reliability.data_information(run.P[sl, sl], run.prior_sigma[sl], 1.0)
        share = run.window["n_window"] / max(run.window["n_accepted"], 1)
        lam = reliability.lambda0(alpha, len(names))
        for j, n in enumerate(names):
            print(f"{eid + '.' + n:28s} {iw[j, j]:10.4g} {ia[j, j]:10.4g} {post[j, j]:11.4g} "
                  f"{iw[j, j] / ia[j, j]:10.3f} {share:6.3f} "
                  f"{np.sqrt(lam / iw[j, j]):11.4g} {np.sqrt(lam / (post[j, j] * share)):15.4g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
