"""The rolling-shutter readout the diagnosis prints, against the simulated truth, over seeds.

A ``psce_rotations`` bag (or ``--scenario swaying``) with rows read out over ``--readout``
ms (``sim/tracker_errors.rolling_shutter``, stamp at the middle row), the current model run
once: the table prints the one-pass readout of the 'unexplained' line
(``stats.shaped_tests``), the whitened fit on the innovations (``rolling.of_run``, as
|coefficient| × rows), its frame-robust σ (|fit| / |t|), the fit of the re-run with that
fit taken out of the centroids (``rolling.lines_without_on_bag``), and the readout printed
(``stats.readout_s``: the two added); ``--truth-out`` also runs the bag with the true
readout taken out (what is left is the estimator's own bias at the truth).

Run::

    .venv/bin/python benchmarks/rolling_readout.py --seeds 21,22,23,24,25
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from stellar_cal_ros.diagnosis import rolling, stats
from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
from stellar_cal_ros.diagnosis.output import line_tests
from stellar_cal_ros.diagnosis.runstats import evaluate
from stellar_cal_ros.methods.replay import bag_data_from_simulation
from stellar_cal_ros.sim import tracker_errors
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate


def one(seed: int, scenario: str, duration: float, readout: float, truth_out: bool
        ) -> dict[str, float]:
    """The readouts (ms) of one seed."""
    sc = dataclasses.replace(get_scenario(scenario), centroid_noise_px=0.0)
    kw = {}
    if scenario == "swaying":
        from stellar_cal_ros.diagnosis.injection import SWAY_CLEAN

        kw = {"effects": dict(SWAY_CLEAN)}
    sim = simulate(sc, duration=duration, seed=seed, **kw)
    tracker_errors.rolling_shutter(sim, readout)
    tracker_errors.renoise(sim, lambda m, uv: 0.05, 0.05, seed)
    data = bag_data_from_simulation(sim)
    spec = method_spec("swaying_base" if scenario == "swaying" else "psce")
    run = evaluate(data, spec, rerun_prior(sim.prior), (), 0.5, keep_residuals=True)
    rows = run.calibration.camera.height
    fit = rolling.of_run(run, 0.5)
    line = [f for f in line_tests(run.residuals, sim.prior, 0.5)
            if f.regressor.startswith(stats.ROLLING)]
    _, rest = rolling.lines_without_on_bag(data, spec, run.prior, tuple(run.effects), 0.5,
                                           None, (), run.calibration, fit["coefficient"],
                                           line_tests)
    c = fit["coefficient"]
    out = {"line": float(line[0].regressor.split("readout ")[1].split(" ms")[0])
           if line else float("nan"),
           "fit": abs(c) * rows * 1e3, "sigma": abs(c) / abs(fit["t"]) * rows * 1e3,
           "rest": (rest or 0.0) * np.sign(c) * rows * 1e3,
           "printed": stats.readout_s(c, rest, rows) * 1e3,
           "cy": run.calibration.camera.cy}
    if truth_out:
        cam = dataclasses.replace(run.calibration.camera, cy=rows / 2.0)
        true_c = np.sign(c) * readout / rows
        again = evaluate(rolling.taken_out(data, dataclasses.replace(run.calibration,
                                                                     camera=cam), true_c),
                         spec, rerun_prior(sim.prior), (), 0.5, keep_residuals=True)
        left = rolling.of_run(again, 0.5)
        out["left"] = left["coefficient"] * np.sign(c) * rows * 1e3
    return out


def main() -> int:
    """Print the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="21,22,23,24,25")
    ap.add_argument("--scenario", default="psce_rotations")
    ap.add_argument("--duration", type=float, default=150.0)
    ap.add_argument("--readout", type=float, default=30.0, help="ms")
    ap.add_argument("--truth-out", action="store_true")
    args = ap.parse_args()
    keys = ("line", "fit", "sigma", "rest", "printed", "cy") + (("left",) if args.truth_out
                                                              else ())
    print(f"{args.scenario}, {args.duration:.0f} s, readout {args.readout:g} ms (ms; cy: the "
          "run's principal point row)")
    print(f"{'seed':>5} " + " ".join(f"{k:>8}" for k in keys) + "   CPU-s")
    rows = []
    for seed in (int(s) for s in args.seeds.split(",")):
        t0 = time.process_time()
        r = one(seed, args.scenario, args.duration, args.readout * 1e-3, args.truth_out)
        rows.append([r[k] for k in keys])
        print(f"{seed:5d} " + " ".join(f"{r[k]:8.2f}" for k in keys)
              + f"   {time.process_time() - t0:.1f}", flush=True)
    a = np.array(rows)
    print(" mean " + " ".join(f"{v:8.2f}" for v in a.mean(0)))
    if len(a) > 1:
        print("   SD " + " ".join(f"{v:8.2f}" for v in a.std(0, ddof=1)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
