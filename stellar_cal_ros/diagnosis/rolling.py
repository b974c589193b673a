"""A rolling shutter's shape beside a candidate: ``discover``'s stand-in rule for it.

No library effect models a tracker whose rows are read out one after the other (a row
``v`` read ``(v − c_y)/H · T`` after the stamp moves each star by its image velocity times
that), or its columns (column ``u`` read ``(u − c_x)/W · T`` after it: a detector mounted a
quarter turn round; the same machinery along the other direction, ``axis`` ``"u"``,
:data:`~stellar_cal_ros.diagnosis.stats.READOUT_AXES`).  On a moving base, library
effects take up parts of it: a time offset the frames' mean row offset (stars not
centred on the middle row), a pixel aspect the row-proportional part (measured, unseen
case ``sway_rolling``: 30 ms readout, discover added time_offset and pixel_aspect).
The 'unexplained' test of its shape is
:func:`~stellar_cal_ros.diagnosis.stats.shaped_tests`; here the same shape is fitted to the
innovations as a nuisance regressor (:func:`~stellar_cal_ros.diagnosis.stats.
rolling_remainder`), and a candidate is added, once that fit is significant on the current
model, only if it explains the data beyond it (:func:`~stellar_cal_ros.diagnosis.flexure.
beyond`, the rule built for a mount flexure: the candidate's ratio plus what the fit gains
with it minus what it gains without it, χ² with the candidate's dof).  One run of each
candidate so tested, its residuals kept where the bag is.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from stellar_cal_ros.core import distributions as dist
from stellar_cal_ros.diagnosis import stats
from stellar_cal_ros.io.calibration import Calibration

#: what a refused candidate's reason calls the remainder and the fit beside it
REMAINDER = ("the rolling-shutter-shaped remainder", "a rolling shutter")


def of_table(res, calibration: Calibration, fraction: float, axis: str | None = None
             ) -> dict | None:
    """The rolling-shutter fit of a run's residual table (its evaluation window).

    Along ``axis`` (``"v"`` rows, ``"u"`` columns), or, ``None``, the more significant
    direction, its p × the directions (:func:`~stellar_cal_ros.diagnosis.stats.
    rolling_remainder`).
    """
    if res is None or not len(res.get("t", ())):
        return None
    cam = calibration.camera
    return stats.rolling_remainder(res, stats.evaluation_mask(res, fraction),
                                   (cam.cx, cam.cy), (cam.fx, cam.fy), calibration.R_imu_st,
                                   cam.height, cam.width, axis)


def of_run(run, fraction: float, axis: str | None = None) -> dict | None:
    """:func:`of_table` of a :class:`~stellar_cal_ros.diagnosis.runstats.RunSummary`."""
    if run is None or not run.ok or run.residuals is None:
        return None
    return of_table(run.residuals, run.calibration, fraction, axis)


def along(fit: dict | None, shutter: dict) -> dict | None:
    """``fit`` (a candidate's, :func:`of_run`) along the readout direction of ``shutter``.

    A fit of either direction (``by_axis``) gives that direction's own; a fit of one
    direction is itself.
    """
    if fit is None or "by_axis" not in fit or "axis" not in shutter:
        return fit
    return fit["by_axis"].get(shutter["axis"])


def stand_in(candidate, dispersion: float, with_c: dict | None, shutter: dict,
             alpha: float, remainder: tuple[str, str] = REMAINDER, family: int = 1
             ) -> dict | None:
    """Whether ``candidate`` stands in for the rolling shutter fitted on the current model.

    The beyond test (:func:`~stellar_cal_ros.diagnosis.flexure.beyond`: the candidate's Λ
    plus the fit's χ² beside it (``with_c``, :func:`~stellar_cal_ros.diagnosis.leads.
    candidate_on_bag`'s ``rolling``) minus the fit's χ²
    without it (``shutter``)), when it finds nothing beyond the fit, unless the fit has
    vanished beside the candidate (:func:`vanished`; ``family``: the fit's multiplicity
    there).  A true readout keeps its shape
    beside any one library effect (each takes only a part of it: unseen case
    ``sway_rolling``, 30 ms, the fit's t −657 → −409 beside a time offset); a fit that
    vanishes beside the candidate was the candidate's stand-in, not the reverse (a true 5 ms
    time offset on a swaying bag whose model is far off, NIS/dof 135: the fit's χ² 175 513
    → 3.0, p 0.90; its uncapped χ² against the NIS-capped Λ 288 made the ratio −1013.8,
    and time_offset was refused; since the fit's gain is NIS-capped too the 200 s version
    reads 129.1 beyond it, needed, where it read −231.8).  The beyond result
    (``remainder``: :data:`REMAINDER`, or the other nuisance field's names given) when
    refused, with ``beside`` (:func:`beside`: what the fit reads beside the candidate, the
    refusal's evidence), else ``None``.  The same rule for the outside-library fields of
    :mod:`~stellar_cal_ros.diagnosis.leads` (``shutter`` then a field's fit).
    """
    from stellar_cal_ros.diagnosis import flexure

    with_c = along(with_c, shutter)
    b = flexure.beyond(candidate.statistic, candidate.dof, dispersion, with_c, shutter)
    if b is None or b["needed"] or vanished(with_c, shutter, alpha, candidate.dof, family):
        return None
    return dict(b, remainder=remainder,
                beside=beside(with_c, shutter, alpha, candidate.dof, family))


def ratio_without_on_bag(data, spec, prior: Calibration, effects: tuple[str, ...],
                         fraction: float, noise, classes: tuple[type, ...],
                         calibration: Calibration, coefficient: float, axis: str,
                         candidate_prior: Calibration, effect: str, dof: float
                         ) -> tuple[float, float] | None:
    """A candidate's ratio on the bag with a fitted rolling shutter taken out: ``(Λ, p)``.

    Two runs on :func:`taken_out` (``calibration``, ``coefficient``, ``axis``: the current
    model's fit; for :meth:`~stellar_cal_ros.diagnosis.parallel.Runs.on_bag`): the model
    ``effects`` from ``prior`` and the candidate's model (``effect`` added, from
    ``candidate_prior``), compared as ``discover`` compares a candidate (quasi-likelihood
    ratio, χ² with ``dof``, unadjusted p).  ``None`` when a run fails.
    """
    from stellar_cal_ros.diagnosis.discover import Reference
    from stellar_cal_ros.diagnosis.runstats import evaluate, register_effect_classes

    register_effect_classes(classes)
    less = taken_out(data, calibration, coefficient, axis)
    base = evaluate(less, spec, prior, effects, fraction, False, classes, noise=noise)
    with_c = evaluate(less, spec, candidate_prior, effects + (effect,), fraction, False,
                      classes, candidate=True, noise=noise)
    if not (base.ok and with_c.ok):
        return None
    lam, p, _ = Reference.of(base).compare(with_c, dof)
    return float(lam), float(p)


def needs_without(candidate, dispersion: float, with_c: dict | None, shutter: dict,
                  alpha: float) -> bool:
    """Whether :func:`not_without`'s runs are needed: the fit kept beside the candidate.

    ``stand_in`` let the candidate pass (it explains the data beyond the fit in the
    capped currency) while the fit did not vanish beside it: the candidate may still be
    only what the filter made of the readout (a 30 ms column readout on a PSCE bag, unseen
    case ``rolling_cols`` s22: radial_k3 ratio 237.7 beside the fit, 243.1 beyond it, the
    fit t −20.7 → −22.9 beside it; on the bag without the readout 5.2, p 0.023).
    """
    with_c = along(with_c, shutter)
    if with_c is None or vanished(with_c, shutter, alpha, candidate.dof):
        return False
    from stellar_cal_ros.diagnosis import flexure

    b = flexure.beyond(candidate.statistic, candidate.dof, dispersion, with_c, shutter)
    return b is not None and b["needed"]


def not_without(candidate, got: tuple[float, float] | None, shutter: dict, alpha: float
                ) -> dict | None:
    """The refusal of a candidate not needed once the fitted readout is out of the bag.

    ``got``: :func:`ratio_without_on_bag`'s ``(Λ, p)``.  The evidence :func:`first_if_cause`
    takes for a line (gone in a run with the readout taken out) taken for a candidate: not
    significant there at ``alpha`` (unadjusted, as :func:`~stellar_cal_ros.diagnosis.
    flexure.beyond`'s ``needed``), it is refused as the shutter's stand-in (a dict as
    :func:`stand_in`'s, ``without_readout`` True, with its ``reason``); else ``None``.
    """
    if got is None or not got[1] >= alpha:
        return None
    lam, p = got
    along_ = "columns" if shutter.get("axis") == "u" else "rows"
    return {"statistic": lam, "dof": float(candidate.seen_dof), "p_value": p,
            "needed": False, "negative": not lam >= 0.0, "remainder": REMAINDER,
            "without_readout": True, "readout_ms": float(shutter["readout_ms"]),
            "axis": shutter.get("axis", "v"),
            "reason": f"significant alone (p = {candidate.p_adjusted:.2g}) but not on the bag "
                      f"with the fitted readout ({shutter['readout_ms']:.3g} ms along the "
                      f"{along_}) taken out of the centroids (its ratio there {lam:.1f}, "
                      f"p={p:.2g}): a rolling shutter's stand-in, not added"}


def finding(run, fraction: float, alpha: float) -> stats.RegressorFinding | None:
    """The rolling-shutter fit's 'unexplained' line on ``run``, where significant.

    The line of the fit a candidate was refused beside (:func:`stand_in`,
    :func:`not_without`): the innovations' fit (:func:`of_run`, the more significant
    direction, its p × 2) below ``alpha``, its readout over that direction's extent in the
    regressor's name (:data:`~stellar_cal_ros.diagnosis.stats.ROLLING_NAMES`), its size the
    fitted displacement's 99th percentile over the window's stars (px), ``detail`` the fit
    (``shutter``).  The line tests' own line of the direction, where they find one, is
    printed instead (:func:`~stellar_cal_ros.diagnosis.output.finish`).  A column readout
    on a PSCE bag acts in its slews only: the line tests' frame-robust t (−38, ν ≈ 2, unseen
    case ``rolling_cols`` s21) is not significant among ~90 tests, the innovations' fit is.
    """
    fit = of_run(run, fraction)
    if fit is None or not fit["p_value"] < alpha:
        return None
    detail = {k: v if isinstance(v, str) else float(v) for k, v in fit.items()
              if k != "by_axis"}
    return stats.RegressorFinding(
        f"{stats.ROLLING_NAMES[fit['axis']]}, readout {fit['readout_ms']:.3g} ms)", "u, v",
        float(fit["t"]), float(fit["p_value"]), float(fit["size_px"]),
        detail={"shutter": detail})


def refused_beside(b: dict) -> bool:
    """Whether a refusal (a ``beyond_remainder`` entry) was beside the rolling shutter."""
    return tuple(b.get("remainder") or ()) == REMAINDER


def nested(before: dict, dof: int | None) -> bool:
    """Whether a field is the larger model of a nested comparison with a candidate of ``dof``.

    A field of more free columns (``before["columns"]``: :func:`~stellar_cal_ros.diagnosis.
    leads.field_fit`'s, the cells field's per-cell offsets, the magnitude field's 12 a part
    of the window) than the candidate has parameters: the candidate explains what the field
    explains when the field is no longer significant beside it (:func:`vanished`).  A fit of
    one pattern (a rolling shutter, a flexure's response: no ``columns``) is not.
    """
    return dof is not None and before.get("columns", 0) > dof


def vanished(with_c: dict, before: dict, alpha: float, dof: int | None = None,
             family: int = 1) -> bool:
    """Whether a nuisance field fitted on the current model (``before``) is gone beside one.

    Gone beside the candidate (its fit ``with_c``; ``dof`` its parameters): the field was the
    candidate's stand-in.  A field of many columns beside a candidate of few
    (:func:`nested`): gone when it is no longer significant beside it at the level that made
    it a lead (``p · family`` ≥ ``alpha``, ``family`` its Bonferroni multiplicity, as
    :func:`~stellar_cal_ros.diagnosis.leads.significant`).  The nested question is whether
    the 1-6 parameters of a library effect explain what the field's many columns did; what
    the field's size along its direction did beside it is not that question: a per-cell
    field on a twin with pixel_aspect at its MDB (unseen case ``twin_s07_aspect1`` s22)
    fell from t 3.79 to 1.75 beside the aspect (p 0.088), its size 0.271 → 0.159 ± 0.073
    (1.5 σ, not 'fallen' at 1 %), and the aspect, found alone at p 4e-9, was refused.
    Otherwise (a fit of one pattern: a rolling shutter, a flexure's response; or ``dof``
    not given): not significant at ``alpha`` beside it, **and** its size there (the same
    pattern's, :func:`~stellar_cal_ros.diagnosis.stats.pattern_size`) differs from its size
    before at ``alpha``, toward 0 (:func:`~stellar_cal_ros.diagnosis.stats.size_changed`).
    One pattern can lose its test's power beside a candidate of more parameters without
    going anywhere: an 80″/g
    flexure beside gyro_scale_factor + gyro_misalignment (the pair spans it on steps about
    the IMU axes) read 83.3 ± 3.4″/g before, 57.7 ± 23.2″/g beside (t 2.5, p 0.029): not
    significant, but 1.1 σ from what it was, so not gone, and gyro_misalignment (its ratio
    beyond the field −2.6 for 6 dof) was its stand-in.  A true cause takes the field with it
    (a true 5 ms time offset beside a rolling-shutter fit: χ² 175 513 → 3.0).  A fit without
    a comparable size: not significant is gone.
    """
    if nested(before, dof):
        return not with_c["p_value"] * family < alpha
    if with_c["p_value"] < alpha:
        return False
    changed = stats.size_changed(with_c, before, alpha)
    return changed is None or changed


def beside(with_c: dict, before: dict, alpha: float, dof: int | None, family: int = 1
           ) -> dict:
    """What a field reads beside a candidate it refused (the refusal's evidence, the line's).

    ``t``, ``p_value`` (× ``family`` for a field of many columns, :func:`nested`: the level
    :func:`vanished` compares) and ``kept``: ``"significant"`` where that p is below
    ``alpha`` (a field of many columns that refuses is), else ``"size"`` (one pattern whose
    test lost its power beside the candidate while its size did not fall toward 0).
    """
    p = min(1.0, float(with_c["p_value"]) * (family if nested(before, dof) else 1))
    return {"t": float(with_c["t"]), "p_value": p,
            "kept": "significant" if p < alpha else "size"}


def beside_text(b: dict, fitted: str) -> str:
    """A refusal's words for what the field reads beside the candidate (:func:`beside`)."""
    f = b.get("beside")
    if not f:
        return ""
    if f["kept"] == "significant":
        return (f"; {fitted} still significant beside it (t={f['t']:.2f}, "
                f"p={f['p_value']:.2g})")
    return (f"; {fitted} beside it t={f['t']:.2f}, p={f['p_value']:.2g}: weaker, but its "
            "size has not fallen toward 0")


def taken_out(data, calibration: Calibration, coefficient: float, axis: str = "v"):
    """A copy of the bag with a fitted rolling shutter taken out of its centroids.

    Each centroid moved back by ``coefficient`` × :func:`~stellar_cal_ros.diagnosis.stats.
    rolling_columns` along ``axis`` (the innovations being measured − predicted, the fit says the
    measurement holds that much of the shape); the star's direction from its centroid
    (pinhole of ``calibration``'s camera), the gyro rate interpolated at the frames' stamps
    (3 ``np.interp`` over all stamps at once).
    """
    cam = calibration.camera
    if not len(data.imu_t):
        return dataclasses.replace(data, frames=list(data.frames))
    t = np.array([(f.stamp_ns - data.t0_ns) * 1e-9 for f in data.frames])
    w = np.stack([np.interp(t, data.imu_t, data.imu_w[:, k]) for k in range(3)], 1)
    frames = []
    for f, w_f in zip(data.frames, w, strict=True):
        uv = np.asarray(f.uv, dtype=float).reshape(-1, 2)
        if not len(uv):
            frames.append(f)
            continue
        sub = {"x_st": (uv[:, 0] - cam.cx) / cam.fx, "y_st": (uv[:, 1] - cam.cy) / cam.fy,
               "z_st": np.ones(len(uv)), "u": uv[:, 0], "v": uv[:, 1],
               **{f"omega_{a}": np.full(len(uv), w_f[k]) for k, a in enumerate("xyz")}}
        x = stats.rolling_columns(sub, (cam.fx, cam.fy), (cam.cx, cam.cy),
                                  calibration.R_imu_st, axis)
        frames.append(dataclasses.replace(f, uv=uv - coefficient * x))
    return dataclasses.replace(data, frames=frames)


def lines_without_on_bag(data, spec, prior: Calibration, effects: tuple[str, ...],
                         fraction: float, noise, classes: tuple[type, ...],
                         calibration: Calibration, coefficient: float, tests, axis: str = "v"
                         ) -> tuple[tuple[tuple[str, str], ...], float | None] | None:
    """The 'unexplained' lines of a run on the bag without the shutter, and its remainder.

    One run of the same model on :func:`taken_out` (for :meth:`~stellar_cal_ros.diagnosis.
    parallel.Runs.on_bag`): the lines as (regressor, component), what a line's fit reads
    (a readout, a period) cut from its name, and the rolling-shutter fit's signed
    coefficient on that run (:func:`of_run`; ``None`` without it), both along the readout
    direction ``axis``.  ``tests(residuals,
    calibration, fraction, readout=axis)``: the diagnosis's 'unexplained' tests
    (:func:`~stellar_cal_ros.diagnosis.output.line_tests`), their stars' noise and motion
    tests taking out what is left of the shutter along ``axis`` (a column readout's
    leftover, 1.1 ms of 30 on unseen case ``rolling_cols`` s22, repeats star by star: the
    rows' fit left it to the 'catalogue star' line).
    """
    got = rerun_lines(taken_out(data, calibration, coefficient, axis), spec, prior, effects,
                      fraction, noise, classes, tests, axis)
    if got is None:
        return None
    keys, run = got
    rest = of_run(run, fraction, axis)
    return keys, None if rest is None else float(rest["coefficient"])


def rerun_lines(data, spec, prior: Calibration, effects: tuple[str, ...], fraction: float,
                noise, classes: tuple[type, ...], tests, readout: str | None = None):
    """One run of the model on ``data`` (a bag with a cause taken out) and its lines.

    ``(lines, run)``: ``{key: (size, t)}`` of the 'unexplained' lines ``tests`` gives on
    that run (:func:`line_key`; a key's largest size, px; ``readout``, where given, passed
    to the tests: a rolling shutter's direction), and the run (for the cause's own fit
    there); ``None`` when the run fails.
    The evidence of both causes' rules (:func:`first_if_cause`,
    :func:`~stellar_cal_ros.diagnosis.shape_drift.shape_first`), where the bag is.
    """
    from stellar_cal_ros.diagnosis.runstats import evaluate, register_effect_classes

    register_effect_classes(classes)
    run = evaluate(data, spec, prior, effects, fraction, True, classes, noise=noise)
    if not run.ok or run.residuals is None:
        return None
    kw = {} if readout is None else {"readout": readout}
    lines: dict[tuple[str, str], tuple[float, float]] = {}
    for f in tests(run.residuals, run.calibration, fraction, **kw):
        k = line_key(f)
        if k not in lines or abs(f.slope_px) > abs(lines[k][0]):
            lines[k] = (float(f.slope_px), float(f.statistic))
    return lines, run


def line_key(f) -> tuple[str, str]:
    """A line's (regressor, component) without what its fit reads (a readout, a period)."""
    name = f.regressor
    axis = stats.rolling_axis(name)
    if axis is not None:
        name = stats.ROLLING_NAMES[axis]
    elif "(periodic" in name:
        name = name.split(",")[0]
    return name, f.component


def gone(f, left, keep=frozenset(), alpha: float | None = None) -> bool:
    """Whether the line ``f`` is gone in a re-run whose lines' keys are ``left``.

    Only a line the re-run's tests could give back: a cause's own line (its ``detail``
    holds ``"cause"``: another rule's, which no re-run's tests make) and the lines of
    ``keep`` (their ids: the flexure-shaped findings after an add, not the line tests')
    stay where they are.  ``alpha`` given and ``left`` :func:`rerun_lines`' sizes: a line
    still there counts as gone where it has shrunk there (:func:`shrunk`).
    """
    if id(f) in keep or (getattr(f, "detail", None) or {}).get("cause"):
        return False
    key = line_key(f)
    if key not in left:
        return True
    return alpha is not None and isinstance(left, dict) and shrunk(f, left[key], alpha)


#: the largest share of its size a line may keep in a cause's re-run and follow the cause
#: (:func:`shrunk`)
SHRUNK = 0.1


def shrunk(f, again: tuple[float, float], alpha: float) -> bool:
    """Whether the line ``f`` is left in a cause's re-run as a small share of itself.

    ``again``: its size (px) and t there (:func:`rerun_lines`).  At most :data:`SHRUNK`
    of its size before, and fallen at ``alpha`` (one-sided, each size's σ its size over its
    t): the cause took at least 90 % of it.  A removal that is not exact leaves every
    echo at its share: unseen case ``rolling_cols`` s22 (a 30 ms column readout), with the
    fitted 28.7 ms taken out, kept two radius lines and two ripples at 2-3 % of their size
    (u vs radius −0.47 → −0.012 px) at p 3e-5..2e-4, and with the true 30 ms taken out
    the same lines at t −17 (the removal's own approximation: a pinhole's image velocity),
    so never 'gone'; a line of another cause keeps its size.
    """
    s0, t0 = abs(float(f.slope_px)), abs(float(f.statistic))
    s1, t1 = abs(float(again[0])), abs(float(again[1]))
    if not (s0 > 0 and t0 > 0 and math.isfinite(s1)):
        return False
    sd = math.hypot(s0 / t0, s1 / t1 if t1 > 0 else 0.0)
    return s1 <= SHRUNK * s0 and s0 - s1 > float(dist.norm.isf(alpha)) * sd


#: the level :func:`first_if_cause` asks of a line's fall in its re-run (:func:`shrunk`)
FOLLOWS_ALPHA = 0.01


#: the rolling-shutter fit's p (unadjusted) under which :func:`start_lines_without` starts
#: the re-run before the line tests say whether it is needed (a guess: it decides when the
#: re-run starts, never what it returns)
START_P = 0.05


def start_lines_without(run, runs, tests):
    """:func:`first_if_cause`'s re-run started now, beside the line tests; None: not started.

    On a cluster a worker runs :func:`lines_without_on_bag` while this process computes
    the line tests that decide whether it is needed (its arguments are known before them:
    the run and its rolling-shutter fit); in this process it runs only when asked for.
    Started when the fit's p is under :data:`START_P` (its more significant direction's,
    :func:`of_run`), as a spare piece (:meth:`~stellar_cal_ros.diagnosis.parallel.Runs.
    spare`: after the runs the diagnosis waits for, first once asked for): on the several
    round its p was under :data:`START_P` with no line to explain, and started at a
    statistic's priority it went before the refined model's flexure probe, which then ended
    the round alone (H281).  A run started and not needed (or along the other direction
    than the line's) is dropped by :func:`first_if_cause` (queued: never run; running: a
    worker's time, not a result).  Returns ``(fit, value)`` for :func:`first_if_cause`.
    """
    if runs is None or run is None or not run.ok or run.prior is None:
        return None
    fit = of_run(run, runs.fraction)
    if fit is None or not fit["p_value"] < START_P:
        return None
    return fit, runs.spare(lines_without_on_bag, runs.spec, run.prior, tuple(run.effects),
                           runs.fraction, runs.noise, runs.classes, run.calibration,
                           fit["coefficient"], tests, fit["axis"])


def drop_unasked(found: list, started) -> None:
    """Drop :func:`start_lines_without`'s re-run now where no line of ``found`` asks for it.

    For a caller with work before :func:`first_if_cause` (the drifts' re-runs, waited for):
    while that work runs a queued spare would otherwise go out to a free worker, unused.
    A re-run along the other direction than every shutter line's is not asked for either
    (:func:`first_if_cause` drops it).
    """
    if started is not None and started[0]["axis"] not in {
            stats.rolling_axis(f.regressor) for f in found}:
        started[1].cancel()


def first_if_cause(found: list, run, runs, tests, keep=frozenset(), started=None
                   ) -> tuple[list, set[int]]:
    """``found`` with the rolling-shutter line first when the lines before it are its doing.

    A rolling shutter that acts only while the tracker turns fast (a PSCE bag's slews: ~20
    of its frames) has a t of −52 referred to t_ν with ν ≈ 2-3 (p ~ 1e-3), while the
    calibration those frames pull leaves camera-shaped and per-star lines over every dwell
    frame (t 14-38, p ~ 1e-18): ranked by p, the cause came fifth.  The evidence that they
    are its consequence: one run of the same model on the bag with the fitted readout taken
    out of the centroids (:func:`taken_out`); the lines ranked before the shape that are no
    longer significant there, or left there at a small share of their size
    (:func:`shrunk`), follow it.  Returns the reordered lines and the indices (in
    the returned list) of those that follow the shutter (``tests``: as in
    :func:`lines_without_on_bag`); unchanged without a significant shape line or without
    a runner.  The same re-run, made also when the shape is first already, gives the
    readout the line prints (:func:`~stellar_cal_ros.diagnosis.stats.readout_s`: the
    run's fit alone reads it ~12 % short; without a runner, or when the re-run fails, the
    line keeps the one-pass slope of :func:`~stellar_cal_ros.diagnosis.stats.shaped_tests`,
    over the detector's rows too).  ``started``: :func:`start_lines_without`'s of the same
    ``run``, ``runs`` and ``tests`` (its value taken instead of a run made now).
    """
    at = next((i for i, f in enumerate(found) if stats.rolling_axis(f.regressor)), None)
    usable = at is not None and runs is not None and run is not None and run.ok \
        and run.prior is not None
    axis = stats.rolling_axis(found[at].regressor) if usable else None  # (the first's)
    if started is not None and started[0]["axis"] != axis:
        started[1].cancel()  # not needed (queued: never runs)
    if not usable:
        return found, set()
    if started is not None and started[0]["axis"] == axis:
        fit, again = started[0], started[1]()  # (start_lines_without of the same run)
    else:
        fit = of_run(run, runs.fraction, axis)
        if fit is None:
            return found, set()
        again = runs.on_bag(lines_without_on_bag, runs.spec, run.prior, tuple(run.effects),
                            runs.fraction, runs.noise, runs.classes, run.calibration,
                            fit["coefficient"], tests, axis)
    if again is None:
        return found, set()
    left, rest = again
    found = list(found)
    cam = run.calibration.camera
    ms = stats.readout_s(fit["coefficient"], rest,
                         stats.readout_extent(axis, cam.width, cam.height)) * 1e3
    found[at] = dataclasses.replace(
        found[at], regressor=f"{stats.ROLLING_NAMES[axis]}, readout {ms:.3g} ms)")
    if at == 0:
        return found, set()
    follows = [f for f in found[:at] if gone(f, left, keep, FOLLOWS_ALPHA)]
    if not follows:
        return found, set()
    stays = [f for f in found[:at] if not gone(f, left, keep, FOLLOWS_ALPHA)]
    out = stays + [found[at]] + follows + found[at + 1:]
    first = len(stays) + 1
    return out, set(range(first, first + len(follows)))
