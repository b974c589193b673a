"""The tilt's augmented run from absorbed start values, from the user's, and on clean data.

Case ``psce_time_tilt_gyro`` of ``test/test_discovery_cases.py`` (time offset, gyro scale
factors and a (10, −8) mrad image-plane tilt; 300 s, seed 4).  The model holds the time
offset and the gyro scale factors; the tilt is added (prior σ 10 mrad, its plausible
size, as the discovery does) and compared with the model without it (Λ = 2 Δℓ over the
second half of the frames), both started

* from a calibration whose principal point and installation absorbed the tilt (what a
  round of ``--auto`` started from before it restarted from the user's values): the
  given ``--absorbed`` calibration YAML, e.g. the ``calibration.yaml`` of an old
  ``--auto`` run of the case; skipped without it;
* from the user's calibration (the simulation's prior).

Then on the same scenario without hidden effects (2 % misidentified stars only): the
tilt's Λ at prior σ 10, 5 and 1 mrad, and 2Δℓ per quarter of the bag (a start-up cost
would sit in the first quarters).  Run::

    python benchmarks/tilt_restart.py [--absorbed old/calibration.yaml]
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "test"))

from test_discovery_cases import CASES  # noqa: E402

from stellar_cal_ros.diagnosis.discover import rerun_prior  # noqa: E402
from stellar_cal_ros.effects import registry  # noqa: E402
from stellar_cal_ros.io.calibration import load_calibration  # noqa: E402
from stellar_cal_ros.methods.replay import bag_data_from_simulation, replay  # noqa: E402
from stellar_cal_ros.methods.results import LOGDET_WEIGHT, NIS_CAP  # noqa: E402
from stellar_cal_ros.sim.scenarios import get_scenario  # noqa: E402
from stellar_cal_ros.sim.world import simulate  # noqa: E402

TILT = registry.create("image_plane_tilt")


def frame_loglik(res):
    """(frame, per-star log-likelihood) of the accepted stars of a run with tables."""
    r = res.residuals
    ok = ~np.asarray(r["gated"], bool)
    det = r["s_uu"] * r["s_vv"] - r["s_uv"] ** 2
    ll = -0.5 * (np.minimum(r["nis"], NIS_CAP) + LOGDET_WEIGHT * np.log(det)
                 + 2 * np.log(2 * np.pi))
    return np.asarray(r["frame"])[ok], ll[ok]


def with_tilt(prior, start, sigma):
    """``prior`` with the tilt at ``start`` (rad), prior σ ``sigma`` (rad)."""
    out = copy.deepcopy(prior)
    TILT.store(np.asarray(start, float), np.array([sigma, sigma]), out)
    return out


def describe(run, base, label):
    """One table row: Λ, the tilt ± σ, principal point and focal length."""
    names, cov = run.covariance
    i = [k for k, n in enumerate(names) if n.startswith("image_plane_tilt")]
    p = dict(zip(run.calibration.camera.PARAMETER_NAMES, run.calibration.camera.parameters(),
                 strict=True))
    lam = 2 * (run.stats.window(0.5)["log_likelihood"] - base.stats.window(0.5)["log_likelihood"])
    sig = np.sqrt(np.diag(cov)[i]) * 1e3
    print(f"{label:44s} {lam:7.1f}  ({p['tau_x'] * 1e3:6.2f}, {p['tau_y'] * 1e3:6.2f}) ± "
          f"({sig[0]:.2f}, {sig[1]:.2f})  {p['cx']:7.1f} {p['cy']:7.1f}  {p['fx']:9.3f}")
    return lam


def main() -> None:
    """Print both tables."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--absorbed", type=Path, help="calibration YAML with the tilt absorbed")
    args = ap.parse_args()
    sim = CASES["psce_time_tilt_gyro"].simulate()
    data = bag_data_from_simulation(sim)
    model = ["time_offset", "gyro_scale_factor"]
    t = dict(zip(sim.truth.camera.PARAMETER_NAMES, sim.truth.camera.parameters(), strict=True))
    print(f"{'start of the other parameters, tilt start':44s} {'Λ':>7}  tilt estimate (mrad)"
          f"            cx      cy   f (px)")
    starts = [("user's calibration", sim.prior)]
    if args.absorbed:
        starts.insert(0, ("absorbed", load_calibration(args.absorbed)))
    for label, cal in starts:
        prior = rerun_prior(cal)
        base = replay(data, prior, "psce", model, keep_tables=False)
        for tilt in ((0.0, 0.0), (0.01, -0.008)):
            run = replay(data, with_tilt(prior, tilt, 0.01), "psce", model + ["image_plane_tilt"],
                         keep_tables=False)
            describe(run, base, f"{label}, ({tilt[0] * 1e3:.0f}, {tilt[1] * 1e3:.0f}) mrad")
    print(f"{'truth':44s} {'':7}  ({t['tau_x'] * 1e3:6.2f}, {t['tau_y'] * 1e3:6.2f})"
          f"{'':17}{t['cx']:7.1f} {t['cy']:7.1f}  {t['fx']:9.3f}")

    print("\nclean data (seed 4, 2 % misidentified stars), user's calibration, tilt from 0:")
    clean = simulate(get_scenario("psce_rotations"), duration=300.0, seed=4,
                     effects={"misidentification": 0.02})
    data = bag_data_from_simulation(clean)
    prior = rerun_prior(clean.prior)
    base = replay(data, prior, "psce", [], keep_tables=True)
    fb, lb = frame_loglik(base)
    edges = np.quantile(fb, [0, 0.25, 0.5, 0.75, 1.0])
    edges[-1] += 1
    for sigma in (0.01, 0.005, 0.001):
        run = replay(data, with_tilt(prior, (0.0, 0.0), sigma), "psce", ["image_plane_tilt"],
                     keep_tables=True)
        describe(run, base, f"prior σ {sigma * 1e3:.0f} mrad")
        fa, la = frame_loglik(run)
        q = [2 * (la[(fa >= a) & (fa < b)].sum() - lb[(fb >= a) & (fb < b)].sum())
             for a, b in zip(edges[:-1], edges[1:], strict=True)]
        print(f"{'':44s} 2Δℓ per quarter of the bag: " + ", ".join(f"{v:+.1f}" for v in q))


if __name__ == "__main__":
    main()
