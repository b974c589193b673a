"""Why the `region` case's noise group reads 1.84 for a true 2.0 (issue 21, unseen cases).

`benchmarks/unseen_cases.py`'s `region` bag: the right third of the detector (u > 683 px)
has twice the stated 0.05 px centroid noise.  The stars' σ scale per column group
(:func:`~stellar_cal_ros.diagnosis.noise_stars.star_noise`, one Helmert step on the run with the
stated σ) is printed three ways on the same run, to split the bias between its causes:

1. as the diagnosis computes it (accepted stars, the rotation fit weighted by the stated σ);
2. with the stars the filter's gate rejected put back (the gate, at the stated σ, cuts the
   far tail of the 2x stars: their scale is taken from a truncated distribution);
3. as 2., plus one more Helmert step: the rotation fit weighted by each group's scale (the
   first step weights every star alike, so the common rotation takes a share of the noisy
   stars' variance to the quiet ones).

Run::

    .venv/bin/python benchmarks/region_scale.py --seeds 21
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.diagnosis import noise as nz
from stellar_cal_ros.diagnosis import noise_stars
from stellar_cal_ros.diagnosis.stats import evaluation_mask
from stellar_cal_ros.methods.replay import bag_data_from_simulation, replay_psce
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

sys.path.insert(0, str(Path(__file__).resolve().parent))
from unseen_cases import CASES  # noqa: E402  (the case as the unseen-cases table runs it)


def row(seed: int) -> str:
    """The three estimates of the right third's and the rest's scale on one seed."""
    case = CASES["region"]
    sc = get_scenario("psce_rotations")
    sc = dataclasses.replace(sc, **{k: getattr(sc, k) * v if v else 0.0
                                    for k, v in case.scenario_changes.items()})
    sim = simulate(sc, duration=case.duration, seed=seed, effects=case.sim_effects)
    case.post(sim, seed)
    data = bag_data_from_simulation(sim)
    run = replay_psce(data, sim.prior, keep_tables=True)
    res, cam = run.residuals, run.calibration.camera
    sig, msg = noise_stars.used_sigma(res, data, NoiseScales(), nz.default_sigma("psce"), cam.width,
                             cam.height)
    mask = evaluation_mask(res, 0.5)
    u = np.asarray(res["u"], dtype=float)
    edge = 2.0 * cam.width / 3.0
    gated = np.asarray(res["gated"]).astype(bool)
    share = float(gated[mask & (u > edge)].mean())
    every = dict(res, gated=np.zeros_like(gated))

    def scales(table, sigma):
        sn = noise_stars.star_noise(table, sigma, msg, mask, cam.fx, cam.fy, (cam.cx, cam.cy))
        right = sn.uv[:, 0] > edge
        return sn.group(right)[:2], sn.group(~right)[0]

    (a, sa), la = scales(res, sig)
    (b, sb), lb = scales(every, sig)
    (c, sc_), lc = scales(every, sig * np.where(u > edge, b, lb))
    return (f"| {seed} | {share:.1%} | {a:.3f} ± {sa:.3f} ({la:.3f}) | {b:.3f} ± {sb:.3f} "
            f"({lb:.3f}) | {c * b:.3f} ± {sc_ * b:.3f} ({lc * lb:.3f}) |")


def main() -> int:
    """Print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="21")
    args = ap.parse_args()
    print("right third (true 2.0) and, in brackets, the rest (true 1.0); psce_rotations 300 s")
    print("| seed | right-third stars gated | as diagnosed | gated stars back | + one more "
          "Helmert step |")
    print("|---|---|---|---|---|")
    for s in (int(x) for x in args.seeds.split(",") if x):
        print(row(s), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
