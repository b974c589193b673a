r"""The temperature field's MDB checked by injection (issue 21: every printed number).

For each seed: the psce 300 s bag with its head cooling (``--tau`` s, from ``--start`` °C),
the baseline's temperature field and its MDB (``leads.temperature_mdb``) on the clean bag;
then a turn of ``--factor`` × that MDB about an axis at random (``flexure.with_turn``,
``(T − T̄)`` per °C) injected into the same bag and the field fitted again: detected where
its p × 4 (the fields' Bonferroni) < 0.01.  At factor 1 about 80 % should be detected.
One JSON line per seed::

    PYTHONPATH=$PWD python benchmarks/temperature_power.py --seeds 21,22,23 --factor 1
"""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np

from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.diagnosis import flexure, leads
from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
from stellar_cal_ros.diagnosis.runstats import evaluate
from stellar_cal_ros.methods.replay import bag_data_from_simulation
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate


def field(data, spec, prior):
    """The baseline's temperature field on ``data``, its MDB (″/°C)."""
    base = evaluate(data, spec, prior, (), 0.5, keep_residuals=True)
    moved = [flexure.measure_on_bag(data, spec, prior, (), 0.5, None, (), False, ax)
             for ax in range(3)]
    f = leads.temperature_fit(base.residuals, moved, 0.5)
    return f, leads.temperature_mdb(base.residuals, moved, 0.5, f, 0.01)


def main() -> None:
    """Run the seeds (one JSON line each)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="21,22,23")
    ap.add_argument("--tau", type=float, default=100.0)
    ap.add_argument("--start", type=float, default=30.0)
    ap.add_argument("--factor", type=float, default=1.0)
    a = ap.parse_args()
    sc = dataclasses.replace(get_scenario("psce_rotations"), head_temperature_tau_s=a.tau,
                             head_temperature_start_c=a.start)
    for seed in (int(s) for s in a.seeds.split(",")):
        sim = simulate(sc, duration=300.0, seed=seed)
        data, spec, prior = bag_data_from_simulation(sim), method_spec("psce"), \
            rerun_prior(sim.prior)
        f0, mdb = field(data, spec, prior)
        e = np.random.default_rng(seed + 7).standard_normal(3)
        e /= np.linalg.norm(e)
        temp = flexure.head_temperatures(data)
        rate = a.factor * mdb
        turned = flexure.with_turn(data, sim.prior,
                                   np.outer(rate * ARCSEC * (temp - temp.mean()), e))
        f1, _ = field(turned, spec, prior)
        print(json.dumps({"seed": seed, "change_c": f0["temperature_change_c"], "mdb": mdb,
                          "injected": rate, "axis": e.tolist(), "t": f1["t"],
                          "p_value": f1["p_value"], "arcsec_per_c": f1["arcsec_per_c"],
                          "detected": f1["p_value"] * len(leads.NAMES) < 0.01}), flush=True)


if __name__ == "__main__":
    main()
