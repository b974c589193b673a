"""The attitude at a star stamp inside an IMU sample, against the simulator's truth.

A star frame's stamp falls inside an IMU sample interval (the swaying scenario's frames
37 % into a 100 Hz sample); the filters take the attitude there from
:meth:`~stellar_cal_ros.core.imu_prefix.ImuPrefix.at`.  This script builds the prefix from
noise-free samples of a scenario (the simulator's own interval means of the true body
rate, no sensor errors) and compares, at every star stamp, the rotation from the sample's
start to the stamp with the truth's:

* ``linear``: the sample's increment split linearly in time (the held mean rate);
* ``ImuPrefix.at``: what the filters use.

and the same for the rotation between consecutive frames (the propagation's increment,
which also carries the strapdown's whole-sample errors).  Errors in arcsec: RMS and the
largest of the rotation vector's norm, and the RMS of its component along the angular
acceleration at the stamp (frame to frame: along its change between the frames).

Run::

    .venv/bin/python benchmarks/insample_attitude.py
    .venv/bin/python benchmarks/insample_attitude.py --imu-rate 400
    .venv/bin/python benchmarks/insample_attitude.py --scenario psce_rotations
"""

from __future__ import annotations

import argparse

import numpy as np

from stellar_cal_ros.core.imu_prefix import ImuPrefix
from stellar_cal_ros.core.rotation import so3_exp, so3_log
from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.truth_effects import merged_effects
from stellar_cal_ros.sim.world import TruthWorld


def _log(R: np.ndarray) -> np.ndarray:
    return np.array([so3_log(r) for r in R])


def measure(scenario: str, duration: float, imu_rate: float | None,
            star_phase: float | None) -> dict[str, np.ndarray]:
    """Per-frame in-sample and frame-to-frame errors (rad, (n, 3)) of both interpolations."""
    sc = get_scenario(scenario)
    if imu_rate is not None:
        sc.imu_rate = imu_rate
    if star_phase is not None:
        sc.star_phase_s = star_phase
    world = TruthWorld(sc, duration, merged_effects(sc.effects, None))
    dt = 1.0 / sc.imu_rate
    n = int(np.floor(duration * sc.imu_rate + 1e-9))
    t_end = np.arange(1, n + 1) * dt
    w = world.interval_means(t_end, dt, world.omega_ib_b)  # what the gyro measures, noise-free
    pre = ImuPrefix(dt, np.zeros(3))
    pre.extend(t_end, w)
    stamps = sc.star_phase_s + np.arange(0.0, duration, 1.0 / sc.star_rate)
    stamps = stamps[(stamps > 2 * dt) & (stamps < duration - 2 * dt)]
    rows = np.searchsorted(pre.tp, stamps, side="left") - 1  # tp[m] < t <= tp[m+1]
    R_true = world.R_i_b(stamps)
    R_start = world.R_i_b(pre.tp[rows])
    truth_in = np.einsum("nji,njk->nik", R_start, R_true)  # R(tp_m)ᵀ R(t)
    a = (stamps - pre.tp[rows]) / (pre.tp[rows + 1] - pre.tp[rows])
    lin_in = so3_exp(a[:, None] * pre.phi[rows])
    at = np.array([pre.at(m, t) for m, t in zip(rows.tolist(), stamps.tolist(), strict=True)])
    at_in = np.einsum("nji,njk->nik", pre.C[rows], at)
    out = {"linear": _log(np.einsum("nji,njk->nik", lin_in, truth_in)),
           "ImuPrefix.at": _log(np.einsum("nji,njk->nik", at_in, truth_in))}
    # frame to frame: C(ta)ᵀ C(tb) against R(ta)ᵀ R(tb)
    lin_abs = pre.C[rows] @ lin_in
    truth_inc = np.einsum("nji,njk->nik", R_true[:-1], R_true[1:])
    for name, C in (("linear", lin_abs), ("ImuPrefix.at", at)):
        inc = np.einsum("nji,njk->nik", C[:-1], C[1:])
        out[name + " frame-to-frame"] = _log(np.einsum("nji,njk->nik", inc, truth_inc))
    # the angular acceleration at the stamps (for the systematic part)
    h = 1e-3
    out["accel"] = (world.omega_ib_b(stamps + h) - world.omega_ib_b(stamps - h)) / (2 * h)
    out["a"] = a
    return out


def main() -> int:
    """Print the error table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default="swaying")
    ap.add_argument("--duration", type=float, default=200.0)
    ap.add_argument("--imu-rate", type=float, default=None)
    ap.add_argument("--star-phase", type=float, default=None)
    args = ap.parse_args()
    r = measure(args.scenario, args.duration, args.imu_rate, args.star_phase)
    acc = r.pop("accel")
    a = r.pop("a")
    print(f"{args.scenario}, {args.duration:.0f} s, IMU {args.imu_rate or 'scenario'} Hz, "
          f"frames at sample fraction {np.mean(a):.3f} (min {a.min():.3f}, max {a.max():.3f}); "
          f"|angular acceleration| RMS {np.sqrt(np.mean(np.sum(acc**2, 1))):.4f} rad/s^2")
    print(f"{'attitude error (arcsec)':38s} {'RMS':>8s} {'max':>8s} {'along dw/dt RMS':>16s}")
    for name, e in r.items():
        nrm = np.linalg.norm(e, axis=1) / ARCSEC
        d = acc if len(e) == len(acc) else acc[1:] - acc[:-1]  # frame to frame: its change
        ua = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-30)
        along = np.sum(e * ua, axis=1) / ARCSEC
        print(f"{name:38s} {np.sqrt(np.mean(nrm**2)):8.4f} {nrm.max():8.4f} "
              f"{np.sqrt(np.mean(along**2)):16.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
