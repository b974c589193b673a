r"""z of the clock test's speed-squared smear coefficient over seeds (issue 21, H292).

The clock test (:mod:`~stellar_cal_ros.diagnosis.clock`) fits the speed-squared smear
beside the parts only where they change (``clock.SMEAR_P``); here it is fitted on every
bag, so that its σ (``clock_change.smear.sigma_s``) can be checked where the truth is
known: clean psce bags (truth 0) and bags with ``smear15``'s bias (``--px``, truth
``px · speed / s95²``).  Each bag is replayed with the model (``--effects``: none, or
time_offset as discover adds on a smear bag) on ``evaluate``'s residuals (the window of
``clock_test``).  One JSON line per seed and model: the coefficient, σ, truth,
``z = (offset − truth) / σ`` (``clock.smear_beside``), whether the clock's own parts
change and whether its test is the one beside the smear (``clock.ClockChange.by_speed``).

    PYTHONPATH=$PWD python benchmarks/smear_z.py --seeds 21-40 --px 0 \
        --effects none,time_offset
"""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np


def seeds_of(text: str) -> list[int]:
    """``21-40`` or ``21,22``."""
    if "-" in text:
        a, b = text.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(s) for s in text.split(",")]


def main() -> None:  # noqa: D103
    from stellar_cal_ros.diagnosis import clock
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.runstats import evaluate
    from stellar_cal_ros.methods.replay import bag_data_from_simulation
    from stellar_cal_ros.sim import tracker_errors
    from stellar_cal_ros.sim.scenarios import get_scenario
    from stellar_cal_ros.sim.world import simulate

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="21-40")
    ap.add_argument("--px", type=float, default=0.0, help="smear at the 95th pct speed")
    ap.add_argument("--effects", default="none,time_offset")
    ap.add_argument("--duration", type=float, default=300.0)
    args = ap.parse_args()
    models = [() if m == "none" else tuple(m.split("+")) for m in args.effects.split(",")]
    for seed in seeds_of(args.seeds):
        sc = get_scenario("psce_rotations")
        if args.px:
            sc = dataclasses.replace(sc, centroid_noise_px=0.0)
        sim = simulate(sc, duration=args.duration, seed=seed)
        s95 = float(np.percentile(np.concatenate(
            [np.linalg.norm(v, axis=1) for v in tracker_errors.image_velocity(sim)]), 95))
        if args.px:
            tracker_errors.speed_squared_smear(sim, args.px)
            tracker_errors.renoise(sim, lambda m, uv: 0.05, 0.05, seed)
        data = bag_data_from_simulation(sim)
        for eff in models:
            run = evaluate(data, method_spec("psce"), rerun_prior(sim.prior), eff, 0.5,
                           keep_residuals=True)
            res, cal = run.residuals, run.calibration
            sm = clock.smear_beside(res, cal, 0.5)
            own = clock.clock_test(res, cal, 0.5)
            truth = args.px * sm["speed"] / s95**2
            print(json.dumps({"seed": seed, "px": args.px, "effects": list(eff),
                              "offset_ms": sm["offset_s"] * 1e3,
                              "sigma_ms": sm["sigma_s"] * 1e3, "truth_ms": truth * 1e3,
                              "z": (sm["offset_s"] - truth) / sm["sigma_s"],
                              "changes": own.changes(), "by_speed": bool(
                                  own.smear and own.smear["fitted"])}), flush=True)


if __name__ == "__main__":
    main()
