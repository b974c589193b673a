r"""A true gyro scale beside a knock, with the knock fitted as a nuisance (issue 21 items 2-3).

The five unseen cases ``knock_gsf_early``, ``knock_gsf_run20``, ``knock_slew_gsf``,
``sway_knock_gsf`` and ``sway_knock_gsf_early`` fail on main: the installation step is found
and said, but the gyro scale factor is judged by rules beside it (``auto._by_step``,
``_after_knock``: its ratio on the frames before the step) and its estimate comes from a
model without the step.  This measures what fitting the step would give: the step's time
from the current model's own step test (:func:`~stellar_cal_ros.diagnosis.auto._knock_of`:
the line's test, else over all frames), then a private tracker-stage effect, the
installation rotated by a free 3-parameter ``δ`` for frames stamped after the step and by
nothing before it, run beside the candidate.

Per case (the bag ``unseen_cases.py`` writes, simulated here when absent), four runs of
the method's baseline model from the re-run prior: without and with the step, each without
and with ``gyro_scale_factor``.  Printed: the step (its time, χ²₃, p and where it was
tested); the candidate's ``2 Δℓ`` over the evaluation window and its estimate ± σ
without the step and beside it; the step's fitted ``δ`` (arcsec) and the step test on the
model with the step (p).  The ratio is raw ``2 Δℓ`` (dispersion 1; the diagnosis divides by
the current model's dispersion) and the noise is as stated.  δ is fitted at the largest
step even where the test does not fire (its p is printed; the fix would not fit it there).

Run::

    PYTHONPATH=$PWD .venv/bin/python benchmarks/knock_beside.py OUT \
        --cases knock_gsf_early,sway_knock_gsf --seed 21
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from pathlib import Path

import numpy as np

from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.diagnosis import auto
from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
from stellar_cal_ros.diagnosis.installation_step import StepNuisance
from stellar_cal_ros.diagnosis.runstats import evaluate
from stellar_cal_ros.effects import registry
from stellar_cal_ros.io.calibration import load_calibration

sys.path.insert(0, str(Path(__file__).resolve().parent))
import unseen_cases  # noqa: E402

FRACTION = 0.5
GSF = "gyro_scale_factor"


def _gsf(run) -> tuple[np.ndarray, np.ndarray]:
    v, s = registry.create(GSF).initial(run.calibration)
    return np.asarray(v) * 1e6, np.asarray(s) * 1e6


def one(name: str, out: Path, seed: int, test_fraction: float = FRACTION) -> None:
    """The four runs of case ``name`` and its printed rows.

    ``test_fraction``: the last share of the run the step test looks at (1: every frame,
    those before the evaluation window too; the runs are still scored on the window).
    """
    bag, prior_path = out / f"{name}.mcap", out / f"{name}.prior.yaml"
    if not bag.exists():
        unseen_cases.write_case(name, out, seed)
    case = unseen_cases.CASES[name]
    spec = method_spec(case.method)
    prior = rerun_prior(load_calibration(prior_path))
    t0 = time.perf_counter()
    base = evaluate(str(bag), spec, prior, (), FRACTION, keep_residuals=True)
    knock, where = auto._knock_of(base, base.calibration or prior, test_fraction)
    if knock is None:
        print(f"{name}: no step test")
        return
    first = float(np.min(base.residuals["t"]))
    at = copy.deepcopy(prior)  # the step's time: between the frames either side of it
    at.effects[StepNuisance.id] = {"t_posix": first + 0.5 * (knock.t + knock.t_before)}
    classes = (StepNuisance,)
    step = evaluate(str(bag), spec, at, (StepNuisance.id,), FRACTION, True, classes)
    runs = {k: evaluate(str(bag), spec, at, e, FRACTION, False, classes, candidate=True)
            for k, e in (("gsf", (GSF,)), ("step+gsf", (StepNuisance.id, GSF)))}
    after, _ = auto._knock_of(step, step.calibration or prior, test_fraction)
    d = np.asarray(StepNuisance().initial(step.calibration)[0]) / ARCSEC
    ll = {k: r.window["log_likelihood"] for k, r in
          (("base", base), ("step", step), *runs.items())}
    print(f"{name} (seed {seed}; {time.perf_counter() - t0:.0f} s): the step at t~{knock.t:.1f}"
          f" s, chi2 {knock.chi2:.0f}, p {knock.p_value:.2g} "
          f"({where or ('at rest' if knock.at_rest else 'never rests')}); fitted "
          f"delta x {d[0]:.3g}, y {d[1]:.3g}, z {d[2]:.3g}\" (|{np.linalg.norm(d):.3g}|); step"
          f" test on the model with it: chi2 {after.chi2:.1f}, p {after.p_value:.2g}"
          if after is not None else "; no step test after it")
    print(f"  2 dl(step) {2 * (ll['step'] - ll['base']):.1f}")
    for label, a, b in (("without the step", "base", "gsf"), ("beside the step", "step",
                                                              "step+gsf")):
        v, s = _gsf(runs[b])
        print(f"  gsf {label:>17}: 2 dl {2 * (ll[b] - ll[a]):8.1f}; sx/sy/sz "
              + "/".join(f"{x:.1f}" for x in v) + " +- " + "/".join(f"{x:.1f}" for x in s)
              + " ppm")


def main() -> int:
    """One block per case."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--cases", default="knock_gsf_early,knock_gsf_run20,knock_slew_gsf,"
                    "sway_knock_gsf,sway_knock_gsf_early")
    ap.add_argument("--seed", type=int, default=21)
    ap.add_argument("--test-fraction", type=float, default=FRACTION,
                    help="the last share of the run the step test looks at (1: every frame)")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    for name in a.cases.split(","):
        one(name, a.out, a.seed, a.test_fraction)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
