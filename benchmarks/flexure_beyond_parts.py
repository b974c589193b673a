"""The parts of flexure.beyond on two bags: an effect's ratio beside a flexure's in-sample fit.

``flexure.beyond`` adds to an effect's ratio Λ (twice the innovation log-likelihood gain,
which pays the log-determinant of the effect's parameter uncertainty) what a flexure fitted
to the innovations (in-sample whitened sum of squares, no such cost) removes with the
effect minus without it.  This prints, for the model ``M`` and ``M + Y`` replayed from the
simulation's prior (noise as stated, evaluation window 0.5): the whitened sum of squares,
the log-likelihood, the flexure's χ² and t, then 2ΔLL, the whitened-sum-of-squares
reduction ΔSS (the like-with-like counterpart of the flexure's χ²) and the flexure's χ²
without minus with Y; the two 'beyond' values ``2ΔLL − Δflex`` and ``ΔSS − Δflex`` (before
the dispersion).

Cases: ``to`` = test_discovery_auto's bag (psce_rotations 120 s, seed 21, a 10 ms time
offset and a true 1e-4 gyro scale factor; M = time_offset, Y = gyro_scale_factor);
``flexure`` = a 40"/g mount flexure alone (200 s, seed 52; M = gyro_scale_factor,
Y = gyro_misalignment, the stand-in that must be refused).

Run::

    .venv/bin/python benchmarks/flexure_beyond_parts.py to
    .venv/bin/python benchmarks/flexure_beyond_parts.py flexure
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy import stats as sps

from stellar_cal_ros.diagnosis import flexure, stats
from stellar_cal_ros.diagnosis.context import add_gravity_regressors
from stellar_cal_ros.diagnosis.discover import method_spec
from stellar_cal_ros.effects import registry
from stellar_cal_ros.methods.replay import bag_data_from_simulation, replay_psce
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

CASES = {
    "to": ({"time_offset": 0.01, "gyro_scale_factor": 1e-4}, 21, 120.0, ["time_offset"],
           "gyro_scale_factor"),
    "flexure": ({"mount_flexure": 40.0}, 52, 200.0, ["gyro_scale_factor"],
                "gyro_misalignment"),
}


def parts(effects: list[str], data, sim, spec) -> tuple[float, float, float]:
    """Whitened sum of squares, log-likelihood and flexure χ² of one model's window."""
    run = replay_psce(data, sim.prior, effects, keep_tables=True)
    res = add_gravity_regressors(run.residuals, data, run.calibration)
    moved = flexure.measure_on_bag(data, spec, sim.prior, tuple(effects), 0.5)
    got = flexure.remainder_statistics(res, moved, 0.5)
    win = stats.evaluation_mask(res, 0.5) & stats.accepted(res)
    w = stats.whitened({k: np.asarray(v)[win] for k, v in res.items()})
    ss = float(np.sum(w * w))
    det = (np.asarray(res["s_uu"]) * np.asarray(res["s_vv"]) - np.asarray(res["s_uv"]) ** 2)
    ll = -0.5 * (ss + float(np.sum(np.log(det[win]))))
    print(f"{'+'.join(effects)}: whitened SS {ss:.1f}, loglik {ll:.1f}, flexure chi2 "
          f"{got['chi2']:.1f} (t={got['t']:.1f}), {int(win.sum())} stars")
    return ss, ll, got["chi2"]


def main() -> int:
    """Print the parts for one case."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("case", choices=list(CASES))
    args = ap.parse_args()
    truth, seed, duration, model, y = CASES[args.case]
    sim = simulate(get_scenario("psce_rotations"), duration=duration, seed=seed,
                   effects=truth)
    data = bag_data_from_simulation(sim)
    spec = method_spec("psce")
    ss0, ll0, f0 = parts(model, data, sim, spec)
    ss1, ll1, f1 = parts(model + [y], data, sim, spec)
    dof = registry.create(y).size
    lam, dss, dflex = 2.0 * (ll1 - ll0), ss0 - ss1, f0 - f1
    print(f"{y} ({dof} dof): 2dLL {lam:.1f}, dSS {dss:.1f}, flexure chi2 without - with "
          f"{dflex:.1f}; beyond: 2dLL - dflex {lam - dflex:.1f} "
          f"(p={sps.chi2.sf(max(lam - dflex, 0.0), dof):.2g}), dSS - dflex {dss - dflex:.1f} "
          f"(p={sps.chi2.sf(max(dss - dflex, 0.0), dof):.2g})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
