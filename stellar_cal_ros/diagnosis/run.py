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
from stellar_cal_ros.diagnosis.output import finish, lines_run, progress_printer, start_reruns
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
    verify_signs: tuple[int, ...] = (1, -1),
    verify_twins: int | None = None,
    verify_twins_max: int | None = None,
    noise_scales: NoiseScales | None = None,
    on_error: str = "raise",
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
    biases on twins of the bag (:mod:`~stellar_cal_ros.diagnosis.verify`), each row at
    ``verify_signs`` x its MDB on its noise-free twin pair and on ``verify_twins`` noisy
    twins of seeds ``verify_seed``, ... (``None``: none; a row whose noise-free run
    failed gets :data:`~.verify.TWINS`, and more, up to ``verify_twins_max`` —
    ``None``: :data:`~.verify.TWINS_MAX` —, where they leave it undecided; a count:
    that many, up to ``verify_twins_max``, ``None``: no more).
    ``noise_scales``: the noise the runs start from (``--noise-scale``) instead of the
    calibration's run's (its consistency block).  ``on_error``: ``skip`` diagnoses a
    damaged bag on what it holds (read once, past the damage; ``diagnosis.json``'s
    ``bag_losses`` and first ``data_quality`` line say what was lost).
    """
    if auto:
        return discover(bag, calibration, method, effects, output_dir, max_rounds,
                        candidates=candidates, evaluation_fraction=evaluation_fraction,
                        plots=plots, verbose=verbose, workers=workers, scheduler=scheduler,
                        noise=noise, verify=verify, verify_seed=verify_seed,
                        verify_signs=verify_signs, verify_twins=verify_twins,
                        verify_twins_max=verify_twins_max,
                        noise_scales=noise_scales, on_error=on_error)
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    spec = method_spec(method)
    tell = progress_printer(verbose)
    with open_runner(bag, spec, evaluation_fraction, workers, scheduler, on_error) as runs:
        tell(f"re-runs {runs.description}")
        runs.noise = noise_scales or stated_scales(calibration)
        tail = _Tail(runs)
        base, results = rank_candidates(bag, calibration, spec, effects, candidates,
                                        evaluation_fraction, progress=tell, runs=runs,
                                        measure_noise=check_noise(noise), on_top=tail,
                                        beside=tail.beside)
        tail.forget()  # (a spare probe no top asked for)
        # the top candidate (a candidate tested after it may be significant too, but it is
        # the one to add first); its re-run from its own calibration is where the next
        # iteration starts, and the structure left is tested on it -- and for a remainder
        # shaped like a mount bending with gravity, which it may stand in for
        best = next((c for c in results if c.significant_alone), None)
        final = base
        panels = [("current model", base.residuals)]
        if best is not None and best.refined_run is not None:
            final = best.refined_run
            panels.append((f"+ {best.effect}", final.residuals))
        outside, hidden = [], None
        # the lines' re-runs (a drifting shape, a rolling shutter), started beside the
        # runs after the top candidate as soon as its refined run was in (else by finish)
        started = tail.started[1] if tail.started and tail.started[0] is final else None
        if best is not None and best.refined_run is not None and \
                flexure.may_stand_in(best.effect):
            tell(f"after {best.effect}: testing for a gravity-shaped remainder (mount flexure)")
            # the refined run's own start and model (discover.condition_on_top)
            refined = best.refined_run
            # the probes started as the refined run came in (on a cluster; in this process
            # each runs only when asked for)
            probes = tail.probes if tail.started and tail.started[0] is refined else None
            probes = probes or (None, None)
            # the second test's probe run, if it may be needed, beside the first's on a
            # cluster (in this process it runs only when needed)
            second = ((probes[0] or flexure.probe_later(runs, base.prior, base.effects))
                      if base.prior is not None and base.ok and base.residuals is not None
                      and refined.ok and refined.residuals is not None else None)
            if started is None:  # (beside the probes, not alone after them)
                started = start_reruns(lines_run(base, final), runs)
            got = flexure.after_add(runs, refined, refined.prior, refined.effects, probes[1])
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
        # with the runner open: the printed biases the first order does not hold are
        # measured by probe runs on the bag
        summary = finish(out, calibration, base, final, results, spec, effects,
                         evaluation_fraction, panels, plots, verdict=runs.verdict,
                         outside=outside, runs=runs, hiding=hidden, drop_tables=True,
                         started=started)
    (out / "diagnosis.json").write_text(json.dumps(summary, indent=1, default=float))
    return summary


class _Tail:
    """A diagnose round's tail, started as soon as the top candidate's refined run is in.

    :attr:`~stellar_cal_ros.diagnosis.discover.Round.on_top`: while the candidates after
    the top one still run, the refined run's result is all the tail needs: the two flexure
    probes (the current model's, then the refined model's) and the lines' re-runs of it
    (:func:`~stellar_cal_ros.diagnosis.output.start_reruns`, between the two: two workers
    take the larger first) go out then, ahead of the runs queued.  On the several round
    they went after that batch, the drift's re-run alone after the probes (H212: the
    round's tail, 4.4 CPU-s one after the other); handed out before the refined run, the
    probes held it up (measured: the refined run last on its worker).  In this process
    nothing runs before it is asked for (:meth:`~stellar_cal_ros.diagnosis.parallel.
    Runs.later`).

    The current model's probe needs only the round's base run: :meth:`beside`
    (:attr:`~stellar_cal_ros.diagnosis.discover.Round.beside`) starts it beside the
    candidates' runs as a spare piece (:meth:`~stellar_cal_ros.diagnosis.parallel.Runs.
    spare`: a worker that would idle at the candidates' end takes it) when the screening's
    most significant candidate may stand in for a flexure and is significant by its score
    test alone, local or not (then probably the top one, H273).
    """

    def __init__(self, runs) -> None:
        self.runs = runs
        #: (the current model's probe, the refined model's), when a flexure is tested
        self.probes: tuple | None = None
        #: (the refined run, its :func:`start_reruns`)
        self.started: tuple | None = None
        #: (base run, noise scales, the current model's probe started by :meth:`beside`)
        self.early: tuple | None = None

    def beside(self, base, candidates) -> None:
        """Start the current model's probe as a spare piece when the top may stand in."""
        if self.runs.workers < 2 or not (base.ok and base.prior is not None
                                         and base.residuals is not None):
            return
        # the screening's most significant candidate (its score test local or not: a base
        # run that lost lock still ranks them; the several round's top, time_offset)
        scored = [c for c in candidates if c.screen is not None]
        best = min(scored, key=lambda c: c.screen.p_value, default=None)
        if best is None or best.status != "ranked" or not flexure.may_stand_in(best.effect) \
                or not best.screen.p_value * 2 * len(scored) < ALPHA:
            return
        self.early = (base, self.runs.noise,
                      flexure.probe_later(self.runs, base.prior, base.effects, spare=True))

    def forget(self) -> None:
        """Drop the spare probe :meth:`beside` started if nothing took it."""
        if self.early is not None:
            self.early[2].cancel()
            self.early = None

    def _current(self, base):
        """The current model's probe: :meth:`beside`'s for ``base``, else started now."""
        early, self.early = self.early, None
        if early is not None and early[0] is base and early[1] is self.runs.noise \
                and not early[2].cancel():
            return early[2]  # running or ran (in hand when asked for)
        # (still queued at the lowest priority: again at a statistic's, first to go out)
        return flexure.probe_later(self.runs, base.prior, base.effects)

    def __call__(self, base, top, refined):
        def then(task, stats):
            if task.key != refined.key or not stats.ok or stats.residuals is None:
                return []
            flexed = (base is not None and base.ok and base.prior is not None
                      and base.residuals is not None and flexure.may_stand_in(top.effect))
            current = self._current(base) if flexed else None
            self.started = (stats, start_reruns(stats, self.runs))
            if flexed:
                self.probes = (current,
                               flexure.probe_later(self.runs, stats.prior, stats.effects))
            return []

        return then


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
