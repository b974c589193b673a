"""``stellar-cal diagnose``: compare model and measurements, name the missing effect."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.diagnosis import flexure
from stellar_cal_ros.diagnosis.auto import discover
from stellar_cal_ros.diagnosis.discover import (
    ALPHA,
    Reference,
    method_spec,
    rank_candidates,
    rerun_prior,
)
from stellar_cal_ros.diagnosis.noise import NoiseVerdict, check_noise, stated_scales
from stellar_cal_ros.diagnosis.output import finish, progress_printer
from stellar_cal_ros.diagnosis.parallel import open_runner
from stellar_cal_ros.io.calibration import Calibration
from stellar_cal_ros.methods.replay import BagData

log = logging.getLogger(__name__)


def diagnose(
    bag: str | Path | BagData,
    calibration: Calibration,
    method: str,
    effects: list[str],
    output_dir: str | Path,
    candidates: list[str] | None = None,
    evaluation_fraction: float = 0.5,
    plots: bool = True,
    verbose: bool = True,
    workers: int | None = 0,
    scheduler: str | None = None,
    auto: bool = False,
    max_rounds: int = 8,
    noise: str = "estimate",
    verify: bool = False,
    verify_seed: int = 1,
    noise_scales: NoiseScales | None = None,
) -> dict[str, Any]:
    """Run one diagnosis round; write ``diagnosis.json`` and ``report.html``; return the summary.

    ``workers``: 0 runs the re-runs in this process, N on a local Dask cluster of N
    processes, ``None`` automatic (in this process until a batch of runs pays for a
    cluster of one worker per core); ``scheduler``: the address of an existing Dask
    cluster (:mod:`~stellar_cal_ros.diagnosis.parallel`).  ``auto``: add the recommended
    effect and test again, up to ``max_rounds`` rounds
    (:func:`~stellar_cal_ros.diagnosis.auto.discover`).  ``noise``: ``estimate`` (measure
    the noise scales first and test every effect with them, :mod:`~stellar_cal_ros.
    diagnosis.noise`) or ``stated`` (use the noise the messages, the prior and the
    calibration's run state).  ``verify`` (with ``auto``): check the printed MDBs and
    biases on twins of the bag (:mod:`~stellar_cal_ros.diagnosis.verify`).
    ``noise_scales``: the noise the runs start from (``--noise-scale``) instead of the
    calibration's run's (its consistency block).
    """
    if auto:
        return discover(bag, calibration, method, effects, output_dir, max_rounds,
                        candidates=candidates, evaluation_fraction=evaluation_fraction,
                        plots=plots, verbose=verbose, workers=workers, scheduler=scheduler,
                        noise=noise, verify=verify, verify_seed=verify_seed,
                        noise_scales=noise_scales)
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    spec = method_spec(method)
    tell = progress_printer(verbose)
    with open_runner(bag, spec, evaluation_fraction, workers, scheduler) as runs:
        tell(f"re-runs {runs.description}")
        runs.noise = noise_scales or stated_scales(calibration)
        base, results = rank_candidates(bag, calibration, spec, effects, candidates,
                                        evaluation_fraction, progress=tell, runs=runs,
                                        measure_noise=check_noise(noise))
        # the top candidate (a candidate tested after it may be significant too, but it is
        # the one to add first); its re-run from its own calibration is where the next
        # iteration starts, and the structure left is tested on it -- and for a remainder
        # shaped like a mount bending with gravity, which it may stand in for
        best = next((c for c in results if c.significant_alone), None)
        outside, hidden = [], None
        if best is not None and best.refined_run is not None and \
                flexure.may_stand_in(best.effect):
            tell(f"after {best.effect}: testing for a gravity-shaped remainder (mount flexure)")
            # the refined run's own start and model (discover.condition_on_top)
            refined = best.refined_run
            # the second test's probe run, if it may be needed, beside the first's on a
            # cluster (in this process it runs only when needed)
            second = (flexure.probe_later(runs, base.prior, base.effects)
                      if base.prior is not None and base.ok and base.residuals is not None
                      and refined.ok and refined.residuals is not None else None)
            got = flexure.after_add(runs, refined, refined.prior, refined.effects)
            if flexure.significant([flexure.finding(got, [best.effect])], ALPHA) and \
                    base.prior is not None:
                # whether it explains anything beyond a flexure (as discover tests it):
                # one more run, the current model with the probe
                got["beyond"] = flexure.beyond(
                    best.statistic, best.dof, Reference.of(base).dispersion, got,
                    flexure.after_add(runs, base, base.prior, base.effects, second))
            outside = flexure.significant([flexure.finding(got, [best.effect])], ALPHA)
            # no remainder: what a flexure could still be beside the recommendation
            hidden = None if outside else flexure.hiding(got, [best.effect], 1, ALPHA)
        final = base
        panels = [("current model", base.residuals)]
        if best is not None and best.refined_run is not None:
            final = best.refined_run
            panels.append((f"+ {best.effect}", final.residuals))
        # with the runner open: the printed biases the first order does not hold are
        # measured by probe runs on the bag
        summary = finish(out, calibration, base, final, results, spec, effects,
                         evaluation_fraction, panels, plots, verdict=runs.verdict,
                         outside=outside, runs=runs, hiding=hidden, drop_tables=True)
    (out / "diagnosis.json").write_text(json.dumps(summary, indent=1, default=float))
    return summary


def measure_bag(bag, prior, method: str, effects: list[str], scales: NoiseScales,
                components: tuple[str, ...] | None = None, tell=None,
                fraction: float = 0.5) -> NoiseVerdict:
    """Measure the noise scales of ``method`` + ``effects`` on ``bag`` from ``prior``.

    For ``replay --estimate-noise`` (and a bag whose stars say σ = 0): one run in this
    process with the scales ``scales``, the stars' scale from it, then the IMU components
    by ML over re-runs (default: the gyro's, and the accelerometer's for swaying_base).
    """
    from stellar_cal_ros.diagnosis.noise_runs import measure
    from stellar_cal_ros.diagnosis.parallel import Runs, Task

    spec = method_spec(method)
    if components is None:
        components = ("gyro", "accel") if method == "swaying_base" else ("gyro",)
    runs = Runs(bag, spec, fraction)
    runs.noise = scales
    start = rerun_prior(prior) if prior.method != "prior" else prior
    extra = spec.beyond_baseline(effects)
    base = runs.run_all([Task("noise: the model", start, extra, star_noise=True)])[
        "noise: the model"]
    if not base.ok:
        from stellar_cal_ros.errors import ModelError

        raise ModelError(f"noise not measured: the run failed: {base.error}")
    return measure(runs, start, extra, base, tell, components)
