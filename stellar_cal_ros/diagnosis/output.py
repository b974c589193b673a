"""What a diagnosis round leaves: its summary, the report files, the progress lines.

Shared by one round (:func:`~stellar_cal_ros.diagnosis.run.diagnose`) and the forward
selection (:func:`~stellar_cal_ros.diagnosis.auto.discover`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from stellar_cal_ros.core.memory import trim_freed
from stellar_cal_ros.diagnosis import (
    clock,
    installation_step,
    leads,
    rolling,
    shape_drift,
    stats,
)
from stellar_cal_ros.diagnosis.discover import (
    ALPHA,
    CandidateResult,
    hidden_effects,
    summary_dict,
)
from stellar_cal_ros.diagnosis.noise import (
    levels_fit,
    line_noise,
    not_measured,
    star_levels,
    star_lines,
    stated_scales,
    track_lags,
    within_groups,
    without_patterns,
)
from stellar_cal_ros.diagnosis.runstats import RunSummary
from stellar_cal_ros.io.calibration import Calibration


def progress_printer(verbose: bool):
    """A progress callback that prints indented lines (or nothing)."""
    def tell(text: str) -> None:
        if verbose:
            print(f"   {text}", flush=True)

    return tell


def finish(out: Path, calibration: Calibration, base: RunSummary, final: RunSummary,
           results: list[CandidateResult], spec, effects: list[str], fraction: float,
           panels: list[tuple[str, Any]], plots: bool, title: str = "stellar_cal diagnosis",
           extra_images: list[tuple[str, str]] | None = None,
           verdict=None, write: bool = True, outside: list | None = None,
           like: list[str] | None = None, runs=None, refused: tuple[str, ...] = (),
           hiding: dict[str, Any] | None = None, drop_tables: bool = False,
           started: tuple | None = None) -> dict[str, Any]:
    """Unexplained structure on ``final``'s residuals, the summary, the report files.

    ``base`` is the run the candidates were compared with (the summary's RMS); ``final``
    the run whose residual structure is tested (the model with the top candidate when
    there is one).  Returns the summary (without writing ``diagnosis.json``); with
    ``write=False`` the figures are made but ``report.html`` is left to the caller
    (:func:`write_report`, once the summary is complete).  ``verdict``: the noise verdict
    (:class:`~stellar_cal_ros.diagnosis.noise.NoiseVerdict`), the summary's ``noise``.
    ``outside``: significant findings of the flexure-shaped test after an added effect
    (:mod:`~stellar_cal_ros.diagnosis.flexure`, adjusted over their own tests), listed among
    the 'unexplained' lines; with them ``summary["remainder"]`` says that the added effects
    ``like`` (default: the recommendation) explain the structure only in part.  ``runs``:
    the round's :class:`~stellar_cal_ros.diagnosis.parallel.Runs` (open): the printed biases
    the first order does not hold are measured by probe runs on the bag
    (:mod:`~stellar_cal_ros.diagnosis.reliability_probe`).  ``refused``: candidates
    significant alone that are not recommended (discover's stand-ins for a flexure).
    ``drop_tables``: the caller reads no table after this (a round of
    :func:`~stellar_cal_ros.diagnosis.run.diagnose`): the bag's direction tables
    (:func:`~stellar_cal_ros.diagnosis.runstats.forget_prepared`, 37 MB on a 2-h bag) are
    dropped before the lines are tested, and without plots ``base``'s and ``final``'s
    residual tables (44 MB) once they are, before the probe runs render their twins.
    ``started``: :func:`start_reruns` of :func:`lines_run`'s run, made by the caller before
    this (beside its own runs on a cluster); else they start here, beside the line tests.
    """
    cam = calibration.camera
    centre = (cam.cx, cam.cy)
    if drop_tables and runs is not None:
        # the round's runs that share the direction tables are done (the lines re-run
        # a model only for a rolling shutter or a focal drift, the probe replays its twins)
        runs.forget_tables()
    shown = lines_run(base, final)
    if started is None:
        started = start_reruns(shown, runs)
    # no recommendation: the probe runs of the hidden effects' rows need the candidates
    # only, not the lines: on workers they start here too, beside the line tests (the
    # parent's line tests take 5-6 CPU-s of a 2-h round; in this process: when asked for)
    best = next((c for c in results if c.significant_alone and c.effect not in refused),
                None)
    reliability = hidden_effects(base, results) if best is None else None
    probing = None
    if reliability is not None and runs is not None:
        from stellar_cal_ros.diagnosis.reliability_probe import start_probes

        probing = start_probes(reliability, base, runs,
                               {c.effect: c.screen for c in results if c.screen is not None})
    lock = base.lock_losses()  # (before the tables go: its spans are the table's frames)
    # (the clock and step tests' results kept from the lines': not computed twice)
    parts: dict[str, Any] = {}
    # (the shutter's direction from the fit its re-run started with, of the same table: no
    # fit made again, a 2-h table's ~0.5 CPU-s; not started, its p is above START_P: rows)
    shutter = started[1]
    readout = stats.readout_axis(shutter[0], ALPHA) if shutter is not None else \
        "v" if runs is not None and shown.ok and shown.prior is not None else None
    # (the stamps' noise the tested run stated: its result's, not the prior's)
    unexplained = line_tests(shown.residuals, calibration, fraction, parts, readout=readout,
                             stamp=1e-3 * stated_scales(shown.calibration or calibration
                                                        ).stamp_ms,
                             offset="time_offset" in shown.effects)
    unexplained, spread = within_groups(unexplained, verdict)
    # (a rolling shutter's fit's line where the line tests have none of its direction)
    have = {rolling.line_key(f) for f in unexplained}
    outside = [f for f in outside or [] if not (stats.rolling_axis(f.regressor)
                                                and rolling.line_key(f) in have)]
    if outside:  # into the ranking of the lines (regressor_tests' order: p, then |t|)
        told = {f.regressor for f in outside}  # (a clock's line may be among both)
        unexplained = sorted(outside + [f for f in unexplained if f.regressor not in told],
                             key=lambda f: (f.p_value, -abs(f.statistic)))
    unexplained, follows = causes_first(unexplained, shown, runs,
                                        frozenset(id(f) for f in outside), started,
                                        calibration)
    # the time offset × time test, whether it fires or not (its parts' offsets)
    clock_entry = parts["clock"].as_json() if parts["clock"] is not None else None
    # the attitude step test at rest, whether it fires or not (its largest step)
    step_entry = parts["step"].as_json() if parts["step"] is not None else None
    if drop_tables and not plots:
        base.residuals = final.residuals = None
        panels.clear()
        # the heap's pages the line tests freed (blocks below the mapping threshold) go
        # back before the probe renders its twins beside them
        trim_freed()
    summary = summary_dict(base, results, unexplained, spec, effects, fraction,
                           # (a σ wrong star by star: the gate's rejects are the tails of
                           # the stars stated too small, not misidentified stars)
                           heavy_tails=bool(getattr(verdict, "tails", None)
                                            or getattr(verdict, "per_star", None)))
    for i, u in enumerate(summary["unexplained"]):
        if i in follows:
            u["follows"] = follows[i]
    losses = getattr(runs, "losses", None)
    if losses:  # a bag read past damage (``--on-error skip``): said first, and recorded
        from stellar_cal_ros.methods.results import data_quality

        summary["bag_losses"] = runs.bag.losses_record()
        summary["data_quality"] = data_quality(losses, 0) + summary["data_quality"]
    if lock is not None:  # (absent where the filter kept lock)
        summary["lost_lock"] = lock
    # (not measured: the scales the runs used, ``--noise-scale``'s or the calibration's run's)
    summary["clock_change"] = clock_entry
    summary["installation_step"] = step_entry
    # the stars' repeat the noise verdict measured, where its line follows a cause (a lens
    # zone's step: a star keeps its radius along its track) says that cause, not the
    # catalogue (unseen case lens_zone)
    echo = next((follows[i] for i, f in enumerate(unexplained)
                 if f.regressor == "catalogue star" and i in follows), None)
    if echo is not None and verdict is not None and verdict.repeat:
        verdict = verdict.following(echo)
    summary["noise"] = (verdict.as_json() if verdict is not None else
                        not_measured(getattr(runs, "noise", None) or stated_scales(calibration),
                                     _batch_fit(base, spec)))
    if spread:
        summary["noise"]["residual_spread"] = [
            {"regressor": f.regressor, "statistic": f.statistic, "p_value": f.p_value,
             "change_px": f.slope_px} for f in spread]
        summary["noise"]["verdict"] = list(summary["noise"]["verdict"]) + [
            f"the residuals' spread still varies with {f.regressor} (t={f.statistic:.1f}, "
            f"p={f.p_value:.2g}): the noise varies within the {verdict.group['by']} groups "
            "applied (a per-star sigma in the messages would track it), not an effect"
            for f in spread]
    summary["recommendation"] = best.effect if best is not None else None
    like = like if like is not None else ([best.effect] if best is not None else [])
    # (the flexure's line: an outside-library field's line has no 'after')
    top = next((u for u in summary["unexplained"] if "after" in (u.get("detail") or {})), None)
    if outside and like and top is not None:
        from stellar_cal_ros.diagnosis.flexure import remainder_text

        summary["remainder"] = dict(top, like=list(like), text=remainder_text(like, top))
    # an added camera shape with a one-axis position shape left beside it: it may be that
    # shape's linear part (a u-only or v-only distortion outside the library)
    axis = axis_remainder(summary["unexplained"],
                          [e for e in list(effects) + like if e not in spec.baseline])
    if axis is not None:
        summary["axis_remainder"] = axis
    # the flexure's MDB (flexure.hiding); null when its test found a remainder or did not run
    summary["flexure_hiding"] = hiding or None
    if best is None:
        summary["reliability"] = reliability
        if probing is not None:
            probing()
    if plots:
        from stellar_cal_ros.diagnosis import report  # matplotlib: only when plotting

        report.plot_vector_fields(panels, cam.width, cam.height, fraction,
                                  out / "vector_field.png")
        report.plot_regressors(panels, centre, fraction, out / "regressors.png")
        report.plot_time(panels, out / "time.png")
        summary["figures"] = list(extra_images or []) + [
            ("Mean innovation over the detector (regional bins)", "vector_field.png"),
            ("Innovations against possible causes", "regressors.png"),
            ("Innovations against time", "time.png")]
    if write:
        from stellar_cal_ros.diagnosis.printing import diagnosis_lines

        summary["terminal"] = diagnosis_lines(summary, calibration)
        if plots:
            write_report(out, summary, title)
    return summary


def lines_run(base: RunSummary, final: RunSummary) -> RunSummary:
    """The run :func:`finish` tests the lines of: ``final``, unless it kept no residuals."""
    return final if final.residuals is not None else base


def start_reruns(run: RunSummary, runs) -> tuple:
    """The re-runs without a drifting shape or a rolling shutter of ``run``, started now.

    Every argument is known from ``run`` alone (the line tests only decide whether a value
    is asked for), so on a cluster a worker makes them beside what the parent does next:
    the line tests, or in a diagnose round the runs after the top candidate and the
    flexure probes, from the moment the refined run is in (:func:`~stellar_cal_ros.
    diagnosis.run.diagnose`; the drift's 1.1 CPU-s on the several round went alone after
    the probes); in this process each runs when asked for.  ``(drifts, shutter)`` for
    :func:`causes_first`'s ``started``.
    """
    return (shape_drift.start_first_runs(run, runs, line_tests),
            rolling.start_lines_without(run, runs, line_tests))


#: the 'unexplained' lines an axis remainder is read from (those the terminal shows)
AXIS_LINES = 5
#: each detector axis's position regressor (:data:`~stellar_cal_ros.diagnosis.stats.
#: STAR_REGRESSORS`), the residual component along it first
AXES = (("u", "u (column)"), ("v", "v (row)"))


def axis_remainder(found: list[dict[str, Any]], effects: list[str]) -> dict[str, Any] | None:
    """An added camera shape that may stand in for a one-axis distortion outside the library.

    A centroid bias along u only that grows with the column (an odd u-only distortion) has
    a linear part that is a pixel aspect to first order: the library takes it, and the
    rest shows as 'u residual vs u (column)' lines (case ``u_cubic`` of
    ``benchmarks/unseen_cases.py``: aspect −141 ppm, 3/5 of a 0.12-px cubic over its
    half width).  ``found``: the summary's 'unexplained' lines (ranked); ``effects``: the
    effects added to the baseline.  When one of them is a camera effect and the shown
    lines (:data:`AXIS_LINES`) hold a residual along one axis against that axis' position
    with no line of the other axis against its own, returns the first such line's fields
    with ``effects`` (the camera effects), ``axis``, ``lines`` (how many) and ``text``;
    else ``None``.  Text only: the added effect is kept.
    """
    from stellar_cal_ros.effects import registry
    from stellar_cal_ros.effects.base import Stage

    camera = [e for e in dict.fromkeys(effects) if registry.create(e).stage is Stage.CAMERA]
    if not camera:
        return None

    def along(lines, axis, regressor):
        return [u for u in lines if u["component"] == axis
                and u["regressor"].split(" (periodic")[0] == regressor]

    for (axis, regressor), (other, theirs) in ((AXES[0], AXES[1]), (AXES[1], AXES[0])):
        own = along(found[:AXIS_LINES], axis, regressor)
        if own and not along(found, other, theirs):
            top = own[0]
            name = "+".join(camera)
            text = (f"{name} may stand in for a {axis}-only distortion outside the library: "
                    f"a shape along {axis} alone is left after it ({len(own)} '{axis} "
                    f"residual vs {regressor}' line{'s' if len(own) > 1 else ''}, the first "
                    f"{abs(top['change_px']):.3g} px, t={top['statistic']:.1f}), and the "
                    f"linear part of such a shape is what {name} fits; its estimate is not a "
                    "calibration to use until that shape is explained")
            return dict(top, effects=camera, axis=axis, lines=len(own), text=text)
    return None


def causes_first(found: list, run: RunSummary, runs, keep=frozenset(), started=None,
                 calibration: Calibration | None = None) -> tuple[list, dict[int, str]]:
    """The 'unexplained' lines ``found`` of ``run`` with a cause before the lines it makes.

    A drifting camera shape (the focal length, the detector's tilt) whose static part
    ranks first is named before its lines (:func:`~stellar_cal_ros.diagnosis.shape_drift.
    first_if_cause`), and a rolling
    shutter whose consequences rank before it goes first (:func:`~stellar_cal_ros.
    diagnosis.rolling.first_if_cause`): one run on the bag without each, only where its
    own tests are significant.  The lines a printed field's line (outside the library: a
    candidate was refused beside it) explains come last: its echoes, and a weaker field's
    line no longer significant beside it (:func:`~stellar_cal_ros.diagnosis.leads.
    fields_first`: the residuals without the field's fit; no run).  Returns the lines and
    ``{index: cause}`` of those that follow a cause (``summary["unexplained"][i]
    ["follows"]``).  None moves a cause's own line nor the lines of ``keep`` (the ids of
    the findings outside the line tests, a field's and the flexure-shaped after an add: no
    re-run's line tests make them, :func:`~stellar_cal_ros.diagnosis.rolling.gone`) but a
    weaker field's line beside a stronger field.
    ``started``: the drifting shapes' and the rolling shutter's re-runs started beside the
    line tests (:func:`~stellar_cal_ros.diagnosis.shape_drift.start_first_runs`,
    :func:`~stellar_cal_ros.diagnosis.rolling.start_lines_without`).  ``calibration``:
    the one ``found`` was tested with (default: ``run``'s), for the fields' re-tests.
    """
    drifts, shutter = started if started is not None else (None, None)
    rolling.drop_unasked(found, shutter)  # (not out while the drifts' re-runs are waited for)
    found, after = shape_drift.first_if_cause(found, run, runs, line_tests, keep=keep,
                                              started=drifts)
    follows = {id(found[i]): cause for i, cause in after.items()}
    found, after = rolling.first_if_cause(found, run, runs, line_tests, keep, shutter)
    follows.update((id(found[i]), "rolling shutter") for i in after)
    if runs is not None:
        # (a line that follows a cause already stays where that rule put it)
        found, after = leads.fields_first(found, run, runs.fraction, line_tests, ALPHA,
                                          keep, calibration, frozenset(follows), runs)
        follows.update((id(found[i]), cause) for i, cause in after.items())
    return found, {i: follows[id(f)] for i, f in enumerate(found) if id(f) in follows}


def step_test(res, calibration: Calibration, fraction: float, everywhere: bool = False,
              before: bool = False, shared: dict | None = None
              ) -> installation_step.InstallationStep | None:
    """The attitude step test at rest (:func:`~.installation_step.installation_step`).

    ``everywhere``: over all frames, moving or not (a gyro rate candidate's rival).
    ``before``: over the frames before the evaluation window instead of the window's.
    ``shared``: the window's frame offsets, made once for the table's tests
    (:func:`~.stats.accepted_offsets`; not with ``before``).
    """
    cam = calibration.camera
    mask = stats.evaluation_mask(res, fraction)
    return installation_step.installation_step(res, ~mask if before else mask,
                                               (cam.fx, cam.fy), (cam.cx, cam.cy),
                                               calibration.R_imu_st, everywhere,
                                               None if before else shared)


def line_tests(res, calibration: Calibration, fraction: float,
               parts: dict[str, Any] | None = None,
               timing: clock.ClockChange | None = None, readout: str | None = None,
               stamp: float | None = None, offset: bool | None = None) -> list:
    """The 'unexplained' tests of a residual table (significant, strongest first).

    An installation step's line (:mod:`~.installation_step`) goes first when it fires: the
    filter's catch-up on it makes the others.  ``parts``: a dict given gets the
    :func:`~.clock.clock_test` and :func:`step_test` made on the way (``"clock"``, ``"step"``),
    for :func:`finish`'s entries (the clock test holds one of the round's memory peaks on a
    2-h bag: made once).  ``timing``: :func:`~.clock.clock_test` of ``res`` already made by the
    caller with the same ``calibration`` and ``fraction`` (not made again).  ``readout``:
    the direction of the rolling shutter the stars' noise and the motion tests take out
    (``"v"`` rows, ``"u"`` columns); None: the table's own (:func:`~.stats.readout_axis`
    of its fit, :func:`~.rolling.of_table`; the columns only where theirs is significant).
    ``stamp`` (s rms): the frames' stamp noise the run of ``res`` stated in each frame's R
    (the stamps' line tests a spread beyond it); None: ``calibration``'s
    (:func:`~.noise.stated_scales`, its consistency block).  ``offset``: whether the model
    of ``res`` holds time_offset (the clock's steps test's form, :func:`~.clock.
    steps_test`; ``None``: not known).
    """
    cam = calibration.camera
    centre = (cam.cx, cam.cy)
    mask = stats.evaluation_mask(res, fraction)
    if readout is None:
        readout = stats.readout_axis(rolling.of_table(res, calibration, fraction), ALPHA)
    # after each part its freed heap pages (blocks below the mapping threshold) go back,
    # not held beside the next part's: the 2-h round's peak is in these tests (the clock
    # test's offsets, the step test's)
    sn = line_noise(res, mask, cam.fx, cam.fy, centre, calibration.R_imu_st, readout)
    trim_freed()
    # the window's frame offsets: the clock's and step's (without the shutter along readout)
    shared: dict[str, Any] = {"readout": readout}
    if timing is None:
        timing = clock.clock_test(res, calibration, fraction, shared=shared)
        trim_freed()
    step = step_test(res, calibration, fraction, shared=shared)
    shared.clear()
    trim_freed()
    if timing is not None and not timing.steps and timing.finding().p_value < clock.SMEAR_P \
            and (timing.drifts() or timing.asks_drift(ALPHA)):
        # a drift said or asked of the window's few slews: a staircase over the run's?
        timing.steps = clock.steps_test(res, calibration, ALPHA, offset)
        trim_freed()
    timing_line = timing.line() if timing is not None else None
    family: dict[str, int] = {}
    # (the other lines read the residuals less a detector pattern found: its echoes are not
    # lines of their own)
    tested = without_patterns(res, sn)
    found = stats.regressor_tests(
        tested, mask, centre, focal=(cam.fx, cam.fy),
        extra=star_lines(tested, mask, cam.fx, cam.fy, centre, calibration.R_imu_st, sn)
        + ([timing_line] if timing_line is not None else [])
        + ([step.finding()] if step is not None else []),
        R_imu_st=calibration.R_imu_st,
        height=cam.height, track_lags=track_lags(sn), width=cam.width,
        star_levels=star_levels(levels_fit(sn)) is not None, family=family,
        readout=readout, stamp=1e-3 * stated_scales(calibration).stamp_ms if stamp is None
        else stamp)
    periods = clock.wobble_periods(found, _span(res, mask))
    if periods and timing is not None:
        # a wobble found: the clock judged against it, as against a flexure
        # (:data:`~.clock.WOBBLE`), in the same family
        timing, found = _clock_beside_wobble(res, calibration, fraction, periods, timing,
                                             timing_line, found, family["size"])
    if parts is not None:
        parts.update(clock=timing, step=step)
    first = [f for f in found if f.component == installation_step.COMPONENT]
    return first + [f for f in found if f.component != installation_step.COMPONENT]


def _span(res, mask) -> float:
    """The time (s) ``mask``'s rows of the residual table span."""
    t = np.asarray(res["t"], dtype=float)[mask]
    return float(np.ptp(t)) if t.size else 0.0


def _clock_beside_wobble(res, calibration: Calibration, fraction: float,
                         periods: tuple[float, ...], timing: clock.ClockChange,
                         line, found: list, family_size: int, alpha: float = 0.01
                         ) -> tuple[clock.ClockChange, list]:
    """The clock's test made again with the wobble's ``periods`` as rivals.

    Its line ``line`` (found, Bonferroni over ``family_size``) is replaced by the new test's
    at the same factor, kept only when still significant at ``alpha``; ``(the test, the
    lines)``.
    """
    again = clock.clock_test(res, calibration, fraction, periods)
    rest = [f for f in found if f is not line]
    if again is None:
        return timing, found
    new = again.line()
    new.p_value = min(1.0, new.p_value * family_size)
    if new.p_value < alpha:
        rest.append(new)
        rest.sort(key=lambda f: (f.p_value, -abs(f.statistic)))
    return again, rest


def write_report(out: Path, summary: dict[str, Any], title: str) -> None:
    """``report.html`` of a complete summary (its ``figures`` and ``terminal`` lines)."""
    from stellar_cal_ros.diagnosis import report_html

    report_html.write_html(out, summary, [tuple(f) for f in summary.get("figures", [])],
                           title)


def _batch_fit(run: RunSummary, spec) -> dict[str, Any] | None:
    """A batch method's fit block (``calibration.extra["fit"]``: its variance factor), or None.

    None for a filter (its noise is measured by the verdict, or stated), even when it
    started from a batch result that carries such a block.
    """
    from stellar_cal_ros.methods import registry as methods

    if methods.get(spec.name).kind == "filter":
        return None
    cal = getattr(run, "calibration", None)
    fit = (getattr(cal, "extra", None) or {}).get("fit")
    return fit if isinstance(fit, dict) and "variance_factor" in fit else None

