"""The swaying-base filter's compiled star update against its numpy update, on a bag (issue 24.1).

Usage::

    python benchmarks/star_update_equal.py BAG.mcap [--prior PRIOR.yaml] [--consider radial_k3]
        [--switch compiled_propagation|compiled_reference|compiled_frame]

Replays the bag twice in process (``replay(bag, prior, "swaying_base", consider=...)``)
with ``SwayingFilter.compiled_star_update`` False (the numpy update, the reference) then
True (one compiled call a frame after the numpy propagation); ``--switch
compiled_propagation``: the same with ``SwayingFilter.compiled_propagation`` (the
propagation between frames in numpy, the reference, then in one compiled call; the star
update compiled in both), ``--switch compiled_reference`` the same with the position
reference's update (``SwayingFilter.compiled_reference``), ``--switch compiled_frame``
the three calls against one compiled call a frame (``SwayingFilter.compiled_frame``; the
other switches run without it).  Prints the CPU seconds of each, whether the counters
are equal, and the largest differences: θ̂, velocity and position in their σ and
relative, the attitude in its σ, the covariance (against its largest entry; its diagonal
relative), the consider sensitivity M (against its largest entry), the information
(relative) and the score (in its σ).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from stellar_cal_ros.core.rotation import so3_log
from stellar_cal_ros.io.calibration import load_calibration
from stellar_cal_ros.methods.replay import replay
from stellar_cal_ros.methods.swaying import SwayingFilter


def main(argv=None) -> int:
    """Command line entry."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("bag", type=Path)
    ap.add_argument("--prior", type=Path)
    ap.add_argument("--consider", default="radial_k3")
    ap.add_argument("--switch", default="compiled_star_update",
                    choices=("compiled_star_update", "compiled_propagation", "compiled_frame",
                             "compiled_reference"))
    args = ap.parse_args(argv)
    prior = load_calibration(args.prior or Path(str(args.bag).removesuffix(".mcap")
                                                + ".prior.yaml"))
    consider = [e for e in args.consider.split(",") if e]
    runs = {}
    if args.switch != "compiled_frame":  # (the other calls apart)
        SwayingFilter.compiled_frame = False
    for compiled in (False, True):
        setattr(SwayingFilter, args.switch, compiled)
        t = time.process_time()
        runs[compiled] = replay(args.bag, prior, "swaying_base", consider=consider,
                                keep_tables=False)
        print(f"{args.switch}={compiled}: {time.process_time() - t:.2f} CPU s, "
              f"updates {runs[compiled].counters['updates']}")
    a, b = runs[True].filter, runs[False].filter
    print(f"counters equal {runs[True].counters == runs[False].counters}")
    sig = np.sqrt(np.diag(b.P))
    x = np.concatenate([a.theta[:a.P_est], a.velocity, a.position])
    y = np.concatenate([b.theta[:b.P_est], b.velocity, b.position])
    d = np.abs(x - y)
    print(f"theta, velocity, position: max |diff| / sigma {np.max(d / sig[3:]):.2e}, "
          f"max relative {np.max(d / np.maximum(np.abs(y), 1e-300)):.2e}")
    att = float(np.linalg.norm(so3_log(a.R_i_b @ b.R_i_b.T)))
    print(f"attitude: {att:.2e} rad = {att / sig[:3].min():.2e} sigma")
    dP = np.max(np.abs(a.P - b.P)) / np.max(np.abs(b.P))
    dd = np.max(np.abs(np.diag(a.P) - np.diag(b.P)) / np.diag(b.P))
    print(f"P: max |diff| / max |P| {dP:.2e}; diagonal max relative {dd:.2e}")
    sa, sb = a.sensitivity, b.sensitivity
    if sb is not None:
        dM = np.max(np.abs(sa.M - sb.M)) / max(np.max(np.abs(sb.M)), 1e-300)
        di = np.max(np.abs(sa.info - sb.info) / np.maximum(np.abs(sb.info), 1e-300))
        ds = np.max(np.abs(sa.score - sb.score) / np.sqrt(np.diag(sb.info)))
        print(f"sensitivity: M {dM:.2e} of max |M|; information max relative {di:.2e}; "
              f"score max |diff| / sigma {ds:.2e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
