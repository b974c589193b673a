"""A remainder shaped like a mount that bends with gravity, after a library effect is added.

No library effect models a tracker that turns against the IMU with the gravity direction
(mount flexure: a rotation ``ρ = c · (z × g_st)``, ``g_st`` the unit gravity in the tracker
frame, ``c`` in rad per unit lateral gravity).  On a motion of steps about the IMU axes its
increments are rotations about the step axis that a gyro scale factor reproduces to ~98 %
(doc/benchmarks.md): the library effect is then significant and the generic gravity
regressors of the 'unexplained' lines see nothing after it, because the filter absorbs an
attitude offset within a few frames of each step and what is left is a short transient.

The test here is shaped like the flexure *as the filter sees it*.  The model just chosen is
run twice on the bag: as it is, and with every centroid moved as a tracker rotation of
:data:`PROBE` per unit lateral gravity would move it (gravity from the accelerometer,
:func:`~stellar_cal_ros.diagnosis.context.gravity_in_tracker`).  The filter is linear at these
sizes, so the difference of the two runs' innovations per star is the innovation response
``S`` to the flexure, after everything the model's own parameters (the added effect too)
absorb of it — the sensitivity the screening's score test computes for a library effect,
here by finite difference.  The innovations ``ν`` of the model are regressed on ``S``
(both whitened by the innovation covariance, u and v of every star), the frames as the
units: :func:`~stellar_cal_ros.diagnosis.stats.frame_robust_t`, referred to t_ν as every
'unexplained' line.  ``c = Σ Sᵀ C⁻¹ ν / Σ Sᵀ C⁻¹ S`` is the flexure that would leave this
remainder, and the size printed is the remainder's displacement ``|S c|`` (99th percentile
over the stars, px).

Measured (``benchmarks/flexure_remainder.py``, doc/benchmarks.md): 40″ on 300 s of
``psce_rotations`` with gyro_scale_factor added, t = 12.6 (c = 44 ± 3″); the same bag with a
true gyro scale factor instead, t = 1.1.

Once the remainder is significant, which library effects are needed *beside* a flexure is
a nested test (:func:`beyond`): the flexure fitted as a nuisance regressor in the model with
and without the effect (``chi2_capped``: what it removes of the whitened sum of squares
with each star's NIS capped as in Λ) turns the effect's ratio Λ into its ratio given a
flexure, ``Λ + (chi2_with − chi2_without) / dispersion``, χ² with the effect's dof.
``discover`` adds a non-camera candidate then only if that is significant, and flags the
effect the remainder was found after when it is not (40″/g, 200 s, seeds 52-61:
gyro_scale_factor −11.1 to 10.6 for 3 dof, gyro_misalignment after it −29.7 to −62.3 for 6:
a negative ratio, said as such).

A remainder that a later add takes up was that add's only if the test after it could
still see a flexure of that size (:func:`alias`); when the add leaves the test blind to it
(a flexure beside a true gyro scale factor: gyro_misalignment after it, σ 5.5 → 37.9″/g)
the add is marked "could be a mount flexure (outside the library): this motion cannot
separate them" (:data:`ALIAS_TEXT`) and the remainder is still said.
"""

from __future__ import annotations

import copy
import logging
from typing import Any

import numpy as np

from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.diagnosis import stats
from stellar_cal_ros.diagnosis.context import LOAD_WINDOW_S, gravity_in_tracker
from stellar_cal_ros.io.calibration import Calibration

log = logging.getLogger(__name__)

#: the flexure the response is measured with (rad of tracker rotation per unit lateral
#: gravity): far above the filter's numerical noise, far below any non-linearity or gate
PROBE = 5.0 * ARCSEC
#: the gravity direction must change by at least this much (unit vector, x or y in the
#: tracker frame) over the evaluation window, or the test has nothing to go on
MIN_GRAVITY_CHANGE = 0.01
#: the 'unexplained' regressor of the finding (a gravity regressor: the lines rank it by p)
REGRESSOR = "gravity_st (mount-flexure shape)"


def with_flexure(data, calibration: Calibration, rate: float):
    """A copy of the bag whose centroids carry a flexure of ``rate`` rad per unit gravity.

    Each star's direction in the tracker frame (pinhole through ``calibration``'s camera)
    is turned by ``−ρ``, ``ρ = rate · (z × g_st)`` (the tracker turned by ``ρ``), ``g_st``
    the specific force's direction over :data:`~.context.LOAD_WINDOW_S` (the load, as the
    simulator's mount bends under it); ``None`` when the bag has no usable accelerometer.
    """
    t = np.array([f.stamp_ns * 1e-9 for f in data.frames])
    g = gravity_in_tracker(data, calibration, t, LOAD_WINDOW_S) if len(t) else None
    if g is None:
        return None
    return with_turn(data, calibration, rate * np.cross([0.0, 0.0, 1.0], g))


def head_temperatures(data) -> np.ndarray | None:
    """The head temperature at each frame's stamp (°C), or ``None`` without a finite one."""
    series = data.head_temperature
    if series is None or not len(series.stamp_ns) or not len(data.frames):
        return None
    s = np.asarray(series.stamp_ns, dtype=np.int64)
    v = np.asarray(series.value, dtype=float)
    order = np.argsort(s, kind="stable")
    s, v = s[order], v[order]
    fin = np.isfinite(v)
    if not fin.any():
        return None
    ref = int(s[fin][0])
    return np.interp([(f.stamp_ns - ref) * 1e-9 for f in data.frames],
                     (s[fin] - ref) * 1e-9, v[fin])


def with_thermal_turn(data, calibration: Calibration, rate: float, axis: int):
    """A copy of the bag whose tracker turns about its ``axis`` with the head temperature.

    ``ρ = rate · (T − T̄) e_axis`` (rad; ``T̄`` the frames' mean head temperature: a constant
    turn is the installation's), the probe of a mount that turns as the head warms or
    cools (outside the library; unseen case ``thermal_mount``).  ``None`` without a head
    temperature.
    """
    temp = head_temperatures(data)
    if temp is None:
        return None
    turns = np.zeros((len(temp), 3))
    turns[:, axis] = rate * (temp - float(np.mean(temp)))
    return with_turn(data, calibration, turns)


def with_turn(data, calibration: Calibration, turns: np.ndarray):
    """A copy of the bag whose tracker is turned by ``turns[k]`` (rad, tracker frame) at frame k.

    Each star's direction in the tracker frame (pinhole through ``calibration``'s camera)
    is turned by ``−ρ_k`` (the tracker turned by ``ρ_k``).
    """
    cam = calibration.camera
    frames = []
    for f, rho in zip(data.frames, turns, strict=True):
        uv = np.asarray(f.uv, dtype=float)
        if len(uv) == 0:
            frames.append(f)
            continue
        d = np.stack([(uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy,
                      np.ones(len(uv))], 1)
        d = d - np.cross(rho, d)
        moved = copy.copy(f)
        moved.uv = np.stack([cam.cx + cam.fx * d[:, 0] / d[:, 2],
                             cam.cy + cam.fy * d[:, 1] / d[:, 2]], 1)
        frames.append(moved)
    out = copy.copy(data)
    out.frames = frames
    return out


def row_key(t: dict) -> np.ndarray:
    """Each row's (frame, catalogue star) as one int64: the same star of the same frame."""
    return (np.asarray(t["frame"], dtype=np.int64) * (1 << 32)
            + np.asarray(t["catalog_id"], dtype=np.int64))


def _aligned(a: dict, b: dict) -> tuple[dict, dict]:
    """The rows of two residual tables that are the same star of the same frame."""
    _, ia, ib = np.intersect1d(row_key(a), row_key(b), return_indices=True)
    return ({k: np.asarray(v)[ia] for k, v in a.items()},
            {k: np.asarray(v)[ib] for k, v in b.items()})


def remainder_statistics(res: dict, moved: dict, fraction: float) -> dict[str, float] | None:
    """The flexure-shaped test of the innovations ``res`` given the run with the probe.

    ``res``: the model's residual table with the gravity columns; ``moved``: the same
    model's run on the bag with the probe (at least its evaluation window).

    ``{t, p_value, nu, arcsec_per_g, sigma_arcsec_per_g, change_px, rms_px, frames}``
    (``p_value`` unadjusted, from t_ν, ``nu`` its degrees of freedom) and the flexure as
    :func:`~stellar_cal_ros.diagnosis.stats.pattern_size`'s ``coef`` (″/g, its robust σ,
    ν: what the stand-in rule compares between two models); ``None`` without
    enough stars or gravity change, or when no t can be made (the response the same for
    every star, or the innovations exactly its fit: :func:`~.stats.whitened_fit`).

    ``sigma_arcsec_per_g``, the σ printed beside ``c``, is the frame-robust one ``t`` is
    made of (:func:`~stellar_cal_ros.diagnosis.stats.robust_sigma`; also
    ``robust_sigma_arcsec_per_g``, ``None`` where it failed and the whitened one is
    printed).  ``whitened_sigma_arcsec_per_g`` is ``1/√info``
    (the σ printed until 2026-11-28): right only for stars independent within a frame.  The
    response is a turn of the whole tracker, alike on every star of a frame, and the stars
    of a frame share part of their innovation (the predicted attitude error; each star's
    covariance holds it, the whitening star by star does not see it shared), so the
    estimate's variance is the frames' sum ``Σ_k (Σ_i x_i ν_i)² / info²``: 1.08 times
    ``1/info`` on swaying 200 s, 1.18 on psce (189 and 140 null seeds, doc/benchmarks.md;
    the whitened σ 4 and 9 % small), and the frames are white beyond that.
    """
    win = stats.evaluation_mask(res, fraction)
    a, b = _aligned({k: np.asarray(v)[win] for k, v in res.items()}, moved)
    m = stats.accepted(a) & stats.accepted(b)
    if m.sum() < 20:
        return None
    moves = [float(np.ptp(np.asarray(a[k])[m])) for k in ("gravity_x_st", "gravity_y_st")
             if k in a]
    if not moves or not max(moves) > MIN_GRAVITY_CHANGE:
        return None
    sub = {k: v[m] for k, v in a.items()}
    per = PROBE / ARCSEC
    S = np.stack([b["du"][m] - a["du"][m], b["dv"][m] - a["dv"][m]], 1) / per  # px/arcsec
    fit = stats.whitened_fit(sub, S, dof=True)
    if fit is None:
        return None
    t, p, c, info, nu = fit
    frame = np.asarray(sub["frame"])
    shown = np.hypot(*(S * c).T)
    whitened = float(1.0 / np.sqrt(info))
    robust = stats.robust_sigma(sub, S, t, info)
    sigma = robust if robust is not None and np.isfinite(robust) else whitened
    return {"t": t, "p_value": p, "nu": nu, "arcsec_per_g": c,
            "chi2": c * c * info, "chi2_capped": stats.capped_gain(sub, S, c),
            "sigma_arcsec_per_g": sigma,
            "whitened_sigma_arcsec_per_g": whitened, "robust_sigma_arcsec_per_g": robust,
            # the flexure itself: the same size on every model, whatever its response
            "coef": c, "coef_sigma": sigma, "coef_nu": nu,
            "change_px": float(np.percentile(shown, 99)),
            "rms_px": float(np.sqrt(np.mean(shown**2))),
            "frames": int(len(np.unique(frame)))}


#: the columns of the probe's run the test needs (the rest stays where the bag is)
_MOVED_COLUMNS = ("t", "frame", "catalog_id", "du", "dv", "gated")


def measure_on_bag(data, spec, prior: Calibration, effects: tuple[str, ...], fraction: float,
                   noise=None, classes: tuple[type, ...] = (), candidate: bool = False,
                   axis: int | None = None) -> dict[str, np.ndarray] | None:
    """The model's run on the bag with the probe added, where the bag is.

    For :meth:`~stellar_cal_ros.diagnosis.parallel.Runs.on_bag`: the same call as the
    diagnosis's run of ``effects`` from ``prior`` with ``noise`` (so the two differ by the
    probe only), the probe's pattern from ``prior``'s installation and camera.  Returns the
    run's evaluation window (:data:`_MOVED_COLUMNS`); ``None`` when the bag has no usable
    accelerometer or the run fails (the test is an addition: it never stops a diagnosis).
    ``classes``: user effect classes a fresh worker process does not know; ``candidate``:
    an augmented run (a gyro fault is flagged, not raised, as in its own run).
    ``axis`` (0, 1, 2): the probe a turn about that tracker axis with the head temperature
    instead (:func:`with_thermal_turn`, :data:`PROBE` per °C), every row of the run kept
    (the temperature field's direction is fitted before the window).
    """
    from stellar_cal_ros.diagnosis.runstats import quiet, register_effect_classes

    register_effect_classes(classes)

    moved_bag = with_flexure(data, prior, PROBE) if axis is None else \
        with_thermal_turn(data, prior, PROBE, axis)
    if moved_bag is None:
        return None
    kw: dict[str, Any] = {"noise": noise} if noise is not None else {}
    if candidate:
        kw["gyro_fault"] = "flag"
    try:
        with quiet():
            moved = spec.runner(moved_bag, prior, list(effects), keep_tables=True,
                                eval_fraction=fraction, **kw)
    except Exception as exc:
        log.warning("the flexure-shaped test did not run: %s: %s", type(exc).__name__, exc)
        return None
    res = moved.residuals
    if res is None or not len(res.get("t", ())):
        return None
    keep = stats.evaluation_mask(res, fraction) if axis is None else slice(None)
    return {k: np.asarray(res[k])[keep] for k in _MOVED_COLUMNS}


def probe_later(runs, prior: Calibration, effects: tuple[str, ...], spare: bool = False):
    """The probe run :func:`after_add` makes, as a function to call for its result.

    On a cluster it starts now (:meth:`~stellar_cal_ros.diagnosis.parallel.Runs.later`):
    a caller that may need a second test starts it beside the first.  ``spare``: a probe
    the caller may not need, started once a worker has nothing else to do
    (:meth:`~stellar_cal_ros.diagnosis.parallel.Runs.spare`; its ``cancel()`` drops it).
    """
    start = runs.spare if spare else runs.later
    return start(measure_on_bag, runs.spec, prior, tuple(effects), runs.fraction, runs.noise,
                 runs.classes)


def after_add(runs, run, prior: Calibration, effects: tuple[str, ...], probe=None
              ) -> dict[str, float] | None:
    """The flexure-shaped test of ``run`` (the model ``effects`` from ``prior``).

    ``run``: the diagnosis's :class:`~stellar_cal_ros.diagnosis.runstats.RunSummary` of
    that model, with its residuals; ``runs``: its :class:`~stellar_cal_ros.diagnosis.
    parallel.Runs` (method, window and the noise scales ``run`` ran with).  One more run of
    the model, with the probe, where the bag is (``probe``: that run, started already by
    :func:`probe_later` with the same arguments).
    """
    if run is None or not run.ok or run.residuals is None:
        return None
    moved = (probe or probe_later(runs, prior, effects))()
    if moved is None:
        return None
    return remainder_statistics(run.residuals, moved, runs.fraction)


def pair_on_bag(data, spec, prior: Calibration, effects: tuple[str, ...], fraction: float,
                noise=None, classes: tuple[type, ...] = ()) -> dict[str, float] | None:
    """The flexure-shaped test of a candidate model: its run and its run with the probe.

    For :meth:`~stellar_cal_ros.diagnosis.parallel.Runs.on_bag` (both runs where the bag
    is; only the statistics travel): a candidate's own run keeps no residual table.
    """
    from stellar_cal_ros.diagnosis.runstats import evaluate, register_effect_classes

    register_effect_classes(classes)
    run = evaluate(data, spec, prior, effects, fraction, True, classes, candidate=True,
                   noise=noise)
    if not run.ok or run.residuals is None:
        return None
    moved = measure_on_bag(data, spec, prior, effects, fraction, noise, classes, True)
    return None if moved is None else remainder_statistics(run.residuals, moved, fraction)


def beyond(statistic: float, dof: int, dispersion: float, with_effect: dict | None,
           without: dict | None) -> dict[str, Any] | None:
    """Whether an effect explains the data beyond the flexure direction.

    The two models, each with a flexure fitted beside it (the probe's response ``S`` as a
    nuisance regressor of the innovations, :func:`remainder_statistics`): the effect's
    ratio ``statistic`` (Λ against the model without it, quasi-likelihood with
    ``dispersion``) plus what the fitted flexure gains with the effect (``with_effect``'s
    ``chi2_capped``) minus what it gains without it (``without``'s): the nested test of
    the effect given a flexure, χ² with ``dof``.  ``None`` when either test did not run.

    One currency.  Λ is twice the gain in a log-likelihood whose per-star NIS is capped at
    13.8 (:data:`~stellar_cal_ros.methods.results.NIS_CAP`), so the fitted flexure's gain
    is taken with each star's NIS capped alike (:func:`~stellar_cal_ros.diagnosis.stats.
    capped_gain`).  Until 2026-11-27 its uncapped ``c² info`` was added: on a model far
    from the data the stars Λ caps dominate that sum, and the ratio went far negative
    (the 200 s 40″/g flexure bag: gyro_scale_factor −314.7 for 3 dof, of which 494 was
    the cap; a swaying bag's time offset beside a rolling shutter −1013.8: χ² 175 513
    uncapped).  What stays in Λ and not in the flexure's gain is the prequential price of
    the effect's own parameters (Δ Σ log det S, 13-67 on these bags): the price the same Λ
    paid to be significant alone, so not a second currency.

    A ratio below 0 is not a χ² statistic: the model with the effect predicts the data
    worse, once a flexure is fitted beside both, than the model without it (its
    parameters cost more than what it explains beyond the flexure).  Its p-value is then
    not a χ² tail: ``p_value`` is 1, ``negative`` True and the verdict says so
    (:func:`ratio_text`); the effect is not needed beyond the flexure either way.

    ``{statistic, dof, p_value, needed, negative}``: ``needed`` at the diagnosis's α.
    """
    from stellar_cal_ros.core import distributions as dist
    from stellar_cal_ros.diagnosis.discover import ALPHA

    if with_effect is None or without is None:
        return None
    lam = float(statistic + (with_effect["chi2_capped"] - without["chi2_capped"])
                / dispersion)
    negative = not lam >= 0.0
    p = 1.0 if negative else float(dist.chi2.sf(lam, dof))
    return {"statistic": lam, "dof": int(dof), "p_value": p, "needed": p < ALPHA,
            "negative": negative}


def ratio_text(b: dict[str, Any], fitted: str = "a flexure") -> str:
    """The beyond test's result in words (terminal, report, a refused candidate's reason).

    A ratio below 0 is said as what it is (the model predicts worse with the effect once
    ``fitted`` is fitted beside both), not as a χ² tail.
    """
    head = f"its ratio with {fitted} fitted beside it {b['statistic']:.1f}"
    if b.get("negative"):
        return (f"{head} < 0 for {b['dof']} dof: with {fitted} fitted the model predicts "
                "worse with it than without it, no chi2 test")
    return f"{head}, chi2 with {b['dof']}, p={b['p_value']:.2g}"


#: the power with which the test after an add must see the flexure found before it for
#: the add to count as the remainder's explanation (else it is marked, :func:`alias`)
ALIAS_POWER = 0.5


def alias(before: dict | None, after: dict | None, m: int, alpha: float
          ) -> dict[str, Any] | None:
    """Whether an add that took up a gravity-shaped remainder could be that flexure.

    ``before``: the flexure-shaped test (:func:`remainder_statistics`) after the add before
    it, which found the remainder (``c`` ″/g); ``after``: the test with the effect in the
    model (Bonferroni over ``m`` tests at ``alpha``), which found nothing.
    That is the effect's remainder only if the test after it would more likely than not
    have seen a flexure of ``c`` (:data:`ALIAS_POWER`): ``|c|`` at least ``σ δ``, ``σ`` the
    frame-robust standard error its ``t`` is made of (:func:`~stellar_cal_ros.diagnosis.
    stats.robust_sigma`; the whitened one where that failed) and ``δ`` the shift at which
    its two-sided t_ν test at
    ``α/m`` has that power.  When the effect and a flexure are nearly the same pattern on
    this motion the effect takes the test's power with it (a flexure beside a true gyro
    scale factor, 200 s: 40.9 ± 4.3″/g before gyro_misalignment, robust σ 37.9″/g after
    it), and then the data cannot say which of the two it is: the consider bound of the
    claim, made from the two tests (no run).  A true library effect whose pattern is as
    close to a flexure's but larger keeps the claim (a true gyro scale factor after a time
    offset, 120 s: the remainder −26.5 ± 0.6″/g, robust σ 5.9″/g after it: 19.8″/g seen
    with power 50 %).  ``{arcsec_per_g, sigma_arcsec_per_g, mdb_after_arcsec_per_g,
    sigma_after_arcsec_per_g, t_after, power}`` when the flexure would likely go unseen
    (the add is marked), else ``None``.
    """
    if before is None or after is None or not after.get("nu"):
        return None
    seen, se = alias_size(after, m, alpha)
    if not abs(before["arcsec_per_g"]) < seen:
        return None
    return {"arcsec_per_g": float(before["arcsec_per_g"]),
            "sigma_arcsec_per_g": float(before["sigma_arcsec_per_g"]),
            "mdb_after_arcsec_per_g": seen, "sigma_after_arcsec_per_g": float(se),
            "t_after": float(after["t"]), "power": ALIAS_POWER}


def alias_size(after: dict, m: int, alpha: float) -> tuple[float, float]:
    """The flexure (″/g) the test ``after`` sees with :data:`ALIAS_POWER`, and its σ.

    ``σ δ``: ``σ`` the frame-robust standard error of the slope its ``t`` is of (the
    whitened one where that failed), ``δ`` the shift at which its two-sided t_ν test at
    ``α/m`` has that power.  What :func:`alias` prints; checked by injection
    (``benchmarks/flexure_power.py``: a flexure of this size injected into the bag,
    detected by the test of the same model in about half of the seeds).
    """
    from stellar_cal_ros.diagnosis.reliability import delta_t

    se = float(after.get("robust_sigma_arcsec_per_g") or after["sigma_arcsec_per_g"])
    return se * delta_t(alpha / max(m, 1), after["nu"], ALIAS_POWER), se


#: what an added effect that a flexure explains as well is marked with (terminal, JSON,
#: report: the one phrasing)
ALIAS_TEXT = ("could be a mount flexure (outside the library): this motion cannot separate "
              "them")


def alias_text(effect: str, a: dict[str, Any]) -> str:
    """Why ``effect``, added after a gravity-shaped remainder it then took up, is marked."""
    return (f"{effect} {ALIAS_TEXT} (the remainder before it was a flexure of "
            f"{a['arcsec_per_g']:.3g} +- {a['sigma_arcsec_per_g']:.2g} arcsec/g; with "
            f"{effect} in the model the test sees {a['mdb_after_arcsec_per_g']:.3g} "
            f"arcsec/g with power {a['power']:.0%} (t={a['t_after']:.1f} now), so "
            f"{effect} taking it up says nothing of which it is); its estimate is not a "
            "calibration to use until a motion that turns gravity without turning about "
            "the gyro axes (a swaying base) tells them apart")


def may_stand_in(effect_id: str) -> bool:
    """Whether an added library effect can take up a flexure (and hide it), so is tested.

    A flexure turns every star of a frame alike, by an angle that follows the attitude: a
    gyro, time, installation or direction effect can reproduce part of that; a camera
    effect is a map of the detector, fixed whatever the attitude, and cannot.
    """
    from stellar_cal_ros.effects import registry
    from stellar_cal_ros.effects.base import Stage

    return registry.create(effect_id).stage is not Stage.CAMERA


def finding(result: dict[str, float] | None, after: list[str], m: int = 1
            ) -> stats.RegressorFinding | None:
    """The 'unexplained' line of a test result, Bonferroni over ``m`` such tests."""
    if result is None:
        return None
    what = f"{REGRESSOR[:-1]}, after {'+'.join(after)})" if after else REGRESSOR
    return stats.RegressorFinding(what, "u, v", result["t"],
                                  min(1.0, result["p_value"] * max(m, 1)),
                                  result["change_px"], detail=dict(result, after=list(after)))


def remainder_text(like: list[str], f: dict[str, Any]) -> str:
    """What the report says when a library effect is significant and the remainder too."""
    d = f.get("detail") or {}
    name = "+".join(like)
    return (f"mostly {name}-like, with a gravity-shaped remainder ({abs(f['change_px']):.3g} px "
            f"at most, t={f['statistic']:.1f}, p={f['p_value']:.2g}): an effect outside the "
            f"library may be acting -- a mount bending with gravity by "
            f"{d.get('arcsec_per_g', float('nan')):.3g} +- "
            f"{d.get('sigma_arcsec_per_g', float('nan')):.2g} arcsec per unit lateral gravity "
            f"would leave it; {name} " + _stand_in(d.get("beyond")))


def _stand_in(b: dict[str, Any] | None) -> str:
    """What the report says of the effect the remainder was found after."""
    if not b:
        return "improves the fit but may stand in for it"
    test = ratio_text(b)
    if b["needed"]:
        return f"improves the fit beyond such a flexure too ({test})"
    return (f"explains nothing beyond such a flexure ({test}): it stands in for it, and its "
            "estimate is not a gyro calibration to use")


def hiding(result: dict[str, float] | None, after: list[str], m: int, alpha: float
           ) -> dict[str, Any] | None:
    """What a flexure-shaped test that found nothing still lets hide: its MDB in ″/g.

    The flexure the test (:func:`remainder_statistics` of the model ``after``, Bonferroni
    over ``m`` such tests at ``alpha``) detects with power
    :data:`~stellar_cal_ros.diagnosis.reliability.POWER`: ``σ δ``, ``δ`` the shift at
    which the test's own t_ν reference (two-sided, level ``α/m``) has that power
    (:func:`~stellar_cal_ros.diagnosis.reliability.delta_t`; ν ≈ 30 makes it ~6 % above
    the normal's ``√λ₀(α/m, 1)``), ``σ`` the larger of the frame-robust standard error
    of the slope ``t`` is of (:func:`~stellar_cal_ros.diagnosis.stats.robust_sigma`;
    ``|c / t|`` until 2026-11-26, which blew up where t ≈ 0) and the whitened
    ``1/√info``.  Measured against injections at the printed MDB
    (``benchmarks/flexure_remainder.py --at-mdb``, doc/benchmarks.md).
    A motion whose steps about the gyro axes alias a flexure with the gyro terms in the
    model makes it large (40″/g + a true gyro misalignment: ~25″/g σ after both).
    ``None`` when the test did not run or could not be made (``result`` None).
    """
    from stellar_cal_ros.diagnosis.reliability import POWER, delta_t

    if result is None:
        return None
    t, c = result["t"], result["arcsec_per_g"]
    se = float(result.get("whitened_sigma_arcsec_per_g", result["sigma_arcsec_per_g"]))
    robust = result.get("robust_sigma_arcsec_per_g")
    if robust is not None and np.isfinite(robust):
        se = max(se, robust)
    level = alpha / max(m, 1)
    nu = result["nu"]  # remainder_statistics gives a result only where t_nu is made
    shift = delta_t(level, nu)
    return {"arcsec_per_g": se * shift, "nu": nu,
            "sigma_arcsec_per_g": se, "estimate_arcsec_per_g": c, "t": t,
            "p_value": min(1.0, result["p_value"] * max(m, 1)), "after": list(after),
            "power": POWER}


#: what the hiding line and the report's row call the flexure
HIDING_NAME = "mount flexure (outside the library)"


def hiding_phrases(h: dict[str, Any], pm: str = "+-") -> tuple[str, str]:
    """``(MDB, the test)`` of :func:`hiding`'s result, in words.

    The terminal line's and the HTML report's row's one phrasing (``pm``: the plus-minus
    sign, ``"±"`` in HTML).
    """
    after = "+".join(h["after"]) or "the model"
    return (f"{h['arcsec_per_g']:.3g} arcsec per unit lateral gravity",
            f"the gravity-shaped test after {after}: {h['estimate_arcsec_per_g']:.3g} {pm} "
            f"{h['sigma_arcsec_per_g']:.2g} arcsec/g, p={h['p_value']:.2g}")


def hiding_text(h: dict[str, Any]) -> str:
    """The 'what could still be hiding' line of a mount flexure (outside the library)."""
    mdb, test = hiding_phrases(h)
    return (f"a {HIDING_NAME} up to {mdb} could still hide with this motion (its MDB: seen "
            f"with power {h['power']:.0%} at that size; {test})")


def significant(findings: list[stats.RegressorFinding | None], alpha: float
                ) -> list[stats.RegressorFinding]:
    """The findings (Bonferroni-adjusted over their own tests) below ``alpha``."""
    return [f for f in findings if f is not None and f.p_value < alpha]
