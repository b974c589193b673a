"""Noise as a hypothesis, measured over re-runs (:mod:`~stellar_cal_ros.diagnosis.noise`).

:func:`measure` runs the maximum-likelihood searches of the IMU noise scales over the
runner's re-runs (the stars' scale needs none); :mod:`~stellar_cal_ros.diagnosis.noise`
holds the estimators and the verdict, below the runner (its runs measure the stars).
"""

from __future__ import annotations

import math

from stellar_cal_ros.core import distributions as dist
from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.diagnosis.noise import (
    ALPHA,
    MATERIAL,
    NoiseVerdict,
    default_sigma,
    far_off,
    judge_stars,
    misfit,
    p_two_sided,
    stamp_jitter,
    structured,
)
from stellar_cal_ros.diagnosis.noise_imu import first_points, imu_sample_scale, search_scale
from stellar_cal_ros.diagnosis.parallel import Task


def measure(runs, prior, effects: tuple[str, ...], base, tell=None,
            components: tuple[str, ...] = ("gyro",), rivals=None) -> NoiseVerdict:
    """Measure the noise scales on ``runs``' bag for the model ``effects`` from ``prior``.

    ``base`` is a run of that model with the scales ``runs.noise`` and its stars' noise
    measured (``Task(star_noise=True)``).  First the IMU's own samples (no run: their
    sample-to-sample noise, :func:`~.noise_imu.imu_sample_scale`, which no missing effect
    moves); then the stars (no further run); then each IMU component in ``components`` by
    ML over re-runs with the stars' scale applied.  Where the samples look white they
    measure the sensor's noise and the ML is their check: attitude (velocity) motion the
    stars see beyond the samples' noise is a motion of the tracker against the IMU (or a
    wandering bias), not sensor noise, and is said as such, not applied.  When the model
    is too far off for that, or the gyro's ML goes beyond its samples, a wandering gyro
    bias is searched (:func:`search_walk`); accepted, it must also explain the stars'
    misfit better than the round's best library effect (:func:`beats_rivals`: a missing
    effect the walk would stand in for wins) and its bias estimate must not follow the
    gyro's rate (:func:`walk_motion`, :func:`follows_motion`: a rate-dependent gyro error
    is not a walk) nor come back with a period (:func:`comes_back`: a wobble of the tracker
    the gyro does not see is not a walk), and the noise is judged again on a run with
    it.  ``rivals``: a function of the scales the walk's runs used returning the runs of
    the round's best candidates with those scales, ``[(effect, run, parameters)]`` (None:
    no candidates to compare with).  Returns the verdict; ``verdict.applied`` is what the
    diagnosis should run with.
    """
    stated = runs.noise or NoiseScales()
    v = _judge(runs, prior, effects, base, tell, components, stated)
    v, base = _at_samples(v, runs, prior, effects, base, tell, components, stated)
    v, base = _at_stamps(v, runs, prior, effects, base, tell, components, stated)
    v, base = _at_frames(v, runs, prior, effects, base, tell, components, stated)
    if not walk_asked(v, base, components):
        return v
    walk = search_walk(v, runs, prior, effects, base, tell, 1 + len(components))
    v.walk = walk
    if not walk["accepted"] or not beats_rivals(walk, v.applied, base, rivals, tell):
        return v
    # (after the rivals: a walk a library effect beats costs no run here)
    moved = runs.on_bag(walk_motion, runs.spec.name, prior, tuple(effects),
                        v.applied.replace(gyro_bias_rw=walk["deg_h_sqrth"]))
    if follows_motion(walk, moved, tell) or comes_back(walk, moved, tell):
        return v
    # judged again on the model's run with the walk (the stars' σ measured on it: with the
    # walk the model fits, so the noise tests no longer skip)
    ran = stated.replace(gyro_bias_rw=walk["deg_h_sqrth"])
    key = "noise: the model with the gyro bias walk"
    again = runs.run_all([Task(key, prior, tuple(effects), noise=ran, cost=SEARCH_COST,
                               star_noise=True)])[key]
    w = _judge(runs, prior, effects, again, tell, components, stated, ran) if again.ok else None
    if w is None or w.skipped:
        walk["accepted"] = False
        walk["why"] = ("with it, " + w.skipped.split(":")[0] if w else
                       f"the model's run with it failed: {again.error}")
        if tell:
            tell(f"noise: gyro bias walk not taken: {walk['why']}")
        return v
    w.walk = walk
    w.rejected.append("gyro_bias_rw")
    return w


def _at_stamps(v: NoiseVerdict, runs, prior, effects: tuple[str, ...], base, tell,
               components: tuple[str, ...], stated: NoiseScales):
    """``(verdict, base run)``: judged again with the frames' stamp noise in the model's R.

    Where the model was too far off for the noise and a noise in the frames' stamps makes
    that misfit (:func:`~.noise.stamp_jitter`, ``v.stamp_jitter``), or where the stars ask
    the attitude for more motion than the gyro's noise (``v.beyond``) and the stamps' test
    on the same run names such a noise (psce's misfit stays within 2 there), the model is
    run once
    more with that noise in each frame's measurement covariance (``NoiseScales.stamp_ms``,
    the rank-one ``σ_t² J_t J_tᵀ``: :func:`~stellar_cal_ros.core.covariance.stamp_column`),
    its stars' noise measured, and the verdict made on that run: the stamps are named as
    the noise they are and applied (``use --noise-scale stamp=X``), the NIS/dof comes back
    to ~1 and the rest of the noise is measured (unseen cases ``sway_jitter``, ``jitter``).
    Where the model is still far off with it, or the stars still ask for more motion,
    ``(v, base)`` (the verdict without it).  Records
    ``nis_before`` / ``nis_after`` (the stars' NIS/dof of the two runs, each at its stars'
    measured σ: :func:`~.noise.misfit`, as :func:`~.noise.far_off` prints it) in the stamps'
    dict.
    """
    got = v.stamp_jitter if v.skipped else None
    if not v.skipped and "gyro" in v.beyond and base.ok and base.window:
        # the stars asking the attitude for more motion than the gyro's noise: a stamp
        # noise does that where the model is not far off (unseen case ``jitter``, psce s22:
        # 'x5.42 the noise its own samples show'), the stamps' test on the same run
        s, nis = misfit(base, base.star_noise)
        got = stamp_jitter(base, base.calibration or prior, runs.fraction, s, nis)
    if not got:
        return v, base
    ms = float(f"{got['ms']:.2g}")  # (the size printed is the size applied)
    w, again = _judged_with(v, runs, prior, effects, base, tell, components, stated,
                            "noise: the model with the frames' stamp noise",
                            v.applied.replace(stamp_ms=ms),
                            f"the frames' stamps jitter {ms:.2g} ms rms",
                            "stamp_jitter", dict(got, applied_ms=ms))
    if w is not v:
        w.rejected.append("stamp")
    return w, again


def _judged_with(v: NoiseVerdict, runs, prior, effects: tuple[str, ...], base, tell,
                 components: tuple[str, ...], stated: NoiseScales, key: str,
                 ran: NoiseScales, said: str, field: str, record: dict):
    """``(verdict, run)`` of the model run again with ``ran``, or ``(v, base)``.

    A frame-common noise named on ``base`` (the stamps', :func:`_at_stamps`; a shift of
    all the frame's stars, :func:`_at_frames`) put in each frame's R: the model's run
    ``key`` with it, its stars' noise measured, the verdict made on it; the stars' NIS/dof
    of ``base`` and of that run.  Where the run failed, the model is still far off with
    it, or the stars ask the gyro for more motion than its noise: ``(v, base)``, the
    verdict without it.  Otherwise the new verdict's ``field`` is ``record`` with
    ``nis_before``, ``nis_after`` and ``tell`` hears ``said`` with them.
    """
    again = runs.run_all([Task(key, prior, tuple(effects), noise=ran, cost=SEARCH_COST,
                               star_noise=True)])[key]
    if not again.ok:
        return v, base
    w = _judge(runs, prior, effects, again, tell, components, stated, ran)
    if w.skipped or "gyro" in w.beyond:
        return v, base
    # each run's NIS/dof at its stars' measured σ (:func:`~.noise.misfit`): the number
    # far_off printed and decided on for ``base``, the one ``nis_share`` is of
    got = dict(record, nis_before=misfit(base, base.star_noise)[1],
               nis_after=misfit(again, again.star_noise)[1])
    setattr(w, field, got)
    if tell:
        tell(f"noise: {said}: applied, NIS/dof {got['nis_before']:.3g} -> "
             f"{got['nis_after']:.3g}")
    return w, again


def _at_frames(v: NoiseVerdict, runs, prior, effects: tuple[str, ...], base, tell,
               components: tuple[str, ...], stated: NoiseScales):
    """``(verdict, base run)``: judged again with the frames' common shift in the model's R.

    Where the verdict named a noise all stars of a frame share (``v.frame_common``,
    :func:`~.noise.named_common`: one shift per frame and axis, white between frames, which
    the stars' σ measured within each frame does not hold), the model is run once more
    with it in each frame's measurement covariance (``NoiseScales.frame_px``, σ_f² I₂
    between every two of its stars: :func:`~stellar_cal_ros.core.covariance.common_columns`)
    at the σ_f measured (the size printed), its stars' noise measured and the verdict made
    on that run: the shift is applied (``use --noise-scale frame=X``), the frames' NIS/dof
    comes back to ~1 and the minimal detectable sizes of the later rounds hold it (unseen
    case ``frame_jitter``).  Where that run fails, is far off or asks the gyro for more
    motion, ``(v, base)`` (named, not applied).  Records ``applied_px``, ``nis_before`` /
    ``nis_after`` (the stars' NIS/dof of the two runs) in the frames' dict.
    """
    got = v.frame_common if v.frame_common and not v.stamp_jitter else None
    if not got or not base.ok or not base.window:
        return v, base
    # (the size printed is the size applied; on a run that held a shift already, the one
    # measured is beyond it: the two add in variance)
    px = float(f"{math.hypot(v.applied.frame_px, got['sigma_px']):.2g}")
    return _judged_with(v, runs, prior, effects, base, tell, components, stated,
                        "noise: the model with the frames' common shift",
                        v.applied.replace(frame_px=px),
                        f"the frames share a shift of {px:.2g} px rms per axis",
                        "frame_common", dict(got, applied_px=px))


def _at_samples(v: NoiseVerdict, runs, prior, effects: tuple[str, ...], base, tell,
                components: tuple[str, ...], stated: NoiseScales):
    """``(verdict, base run)``: judged again with the IMU samples' scales where they mattered.

    The run ``base`` made with the stated scales was too far off for the noise
    (:func:`~.noise.far_off`) while the IMU's own samples measured a scale off the stated
    (``v.applied``): the misfit may be that IMU noise, not a missing effect (unseen case
    ``gyro_x57``: the gyro's ARW 57x the stated, NIS/dof 6.4 with it stated, the stars as
    stated; the verdict said "a missing effect shapes the residuals" beside "noise is the
    cause").  The model is run once more with the samples' scales, its stars' noise
    measured, and the verdict made on that run (which keeps the skip where the model is
    still far off).  Likewise where the IMU noise was not measured for a field the stars
    repeat (:func:`~.noise.structured`) while the stars' σ measured off the stated: a run
    whose stars are weighted wrongly makes its own field (unseen case ``sigma_arcsec``: the
    σ field in arcsec, 52x the truth; with it the filter's camera hardly left the prior and
    the cells read chi2 292 / 112 dof, "a missing effect", beside "noise is the cause";
    at the measured σ the model fits and nothing is added).  Otherwise ``(v, base)``
    unchanged: no run.
    """
    far = bool(v.skipped) or (bool(v.imu_skipped) and "star" in v.rejected)
    if not far or v.applied == stated:
        return v, base
    key = "noise: the model with the IMU samples' noise" if v.skipped else \
        "noise: the model with the stars' measured sigma"
    again = runs.run_all([Task(key, prior, tuple(effects), noise=v.applied, cost=SEARCH_COST,
                               star_noise=True)])[key]
    if not again.ok:
        return v, base
    if v.skipped:
        return _judge(runs, prior, effects, again, tell, components, stated, v.applied), again
    # (the stars' σ the run used is the measured one: judged relative to it, as a later
    # round judges the scales applied before it)
    return _judge(runs, prior, effects, again, tell, components, v.applied), again


#: the blocks (s) the walk's bias estimate is cut into by :func:`walk_motion`, and the
#: start skipped (s, the filter converging)
MOTION_BLOCK = 5.0
MOTION_SKIP = 20.0


def walk_motion(bag, method: str, prior, effects: tuple[str, ...], noise: NoiseScales
                ) -> list[tuple[float, float, int, float, float]]:
    """Whether the walk's bias estimate moves with the gyro's rate, axis by axis (on the bag).

    The model with the walk ``noise`` run over ``bag``; its gyro bias estimate at the ends
    of :data:`MOTION_BLOCK`-s blocks (after :data:`MOTION_SKIP` s), the increments regressed
    on the change of the block's mean rate and mean absolute rate on that axis (with a
    constant).  A walk's increments are independent of the motion; a gyro error that is a
    function of the rate (a scale factor, one by the rate's sign) moves the estimate as the
    rate changes.  The same increments are also tested for one periodic term
    (:func:`~stellar_cal_ros.diagnosis.stats.fisher_g`: a walk's increments are white) and,
    where the bag's head temperature changes, against it (:func:`_temperature_columns`: a
    bias changing with the temperature, a mount turning with it, whose turn δ(T) the
    estimate takes up as its rate and, in the slews, as ``ω × δ(T)``), alone (with a
    constant; ``p_temperature``) and each family beside the other (:func:`_family_p`; the
    rate's family there every axis's block mean rate and this axis's mean absolute rate),
    which says which of the two the estimate follows.  Returns ``[(F, p, blocks,
    p_periodic, period_s, p_temperature, p_rate_beside, p_temperature_beside)]`` per axis
    (nan where too few blocks or no temperature); ``F``, ``p`` (the rate alone) as before.
    """
    import numpy as np

    from stellar_cal_ros.diagnosis.stats import fisher_g
    from stellar_cal_ros.methods.replay import replay

    r = replay(bag, prior, method, effects=list(effects), noise=noise, keep_tables=True)
    h = r.history
    t = np.asarray(h["t"], dtype=float) - bag.t0_ns * 1e-9
    ti, wi = np.asarray(bag.imu_t, dtype=float), np.asarray(bag.imu_w, dtype=float)
    out = []
    names = [k for k in h if k.startswith("gyro_bias.")]
    nan4 = (math.nan,) * 3
    if len(t) < 2 or len(names) != 3:
        return [(math.nan, math.nan, 0, math.nan, math.nan) + nan4] * 3
    edges = np.arange(t[0] + MOTION_SKIP, t[-1], MOTION_BLOCK)
    idx = np.searchsorted(ti, edges)
    heat = _temperature_columns(bag, edges, idx, ti, wi)
    rates = None
    for ax, name in enumerate(names):
        spans = [(a, c) for a, c in zip(idx[:-1], idx[1:], strict=True)]
        if len(spans) < 8 or any(c <= a for a, c in spans):
            out.append((math.nan, math.nan, len(spans), math.nan, math.nan) + nan4)
            continue
        b = np.interp(edges, t, np.asarray(h[name], dtype=float))
        mean = np.array([wi[a:c, ax].mean() for a, c in spans])
        mabs = np.array([np.abs(wi[a:c, ax]).mean() for a, c in spans])
        y = np.diff(b)[1:]
        x = np.column_stack([np.ones(len(y)), np.diff(mean), np.diff(mabs)])
        beta = np.linalg.lstsq(x, y, rcond=None)[0]
        rss1, rss0 = np.sum((y - x @ beta) ** 2), np.sum((y - y.mean()) ** 2)
        dfe = len(y) - 3
        f = (rss0 - rss1) / 2.0 / max(rss1 / dfe, 1e-300)
        p_per, k = fisher_g(np.diff(b))
        if heat is not None and rates is None:  # every axis's block mean rate
            rates = np.diff(np.add.reduceat(wi[idx[0]:idx[-1]], idx[:-1] - idx[0], axis=0)
                            / np.diff(idx)[:, None], axis=0)
        both = None if heat is None else np.column_stack([rates, np.diff(mabs)])
        temp = nan4 if heat is None else (_family_p(y, x[:, :1], heat),
                                          _family_p(y, np.column_stack([x[:, :1], heat]),
                                                    both),
                                          _family_p(y, np.column_stack([x[:, :1], both]),
                                                    heat))
        out.append((float(f), float(dist.f.sf(f, 2, dfe)), len(spans), p_per,
                    MOTION_BLOCK * (len(b) - 1) / k if k else math.nan) + temp)
    return out


def _temperature_columns(bag, edges, idx, ti, wi):
    """The temperature's columns of :func:`walk_motion` (``(blocks − 1, 5)``), or ``None``.

    The head temperature ``T`` (s from the bag's start; ``T'`` about its mean) at the
    blocks' ``edges`` and at the IMU's samples ``ti`` (the blocks' ``idx``): each block's
    change of ``T`` (a bias changing with it), the change of that change (a mount turning
    with it: the bias takes up the turn's rate) and, per gyro axis, the change of the
    block's mean ``ω T'`` (the turn ``δ(T)`` seen in the slews as ``ω × δ``, the block
    means differenced from block to block as the rate's are); ``None`` without a head
    temperature or where it does not change over the blocks.
    """
    import numpy as np

    series = getattr(bag, "head_temperature", None)
    if series is None or len(series.stamp_ns) < 2 or len(edges) < 3 or \
            np.any(np.diff(idx) <= 0):
        return None
    s = (np.asarray(series.stamp_ns, dtype=np.int64) - bag.t0_ns) * 1e-9
    v = np.asarray(series.value, dtype=float)
    fin = np.isfinite(v)
    if fin.sum() < 2:
        return None
    order = np.argsort(s[fin], kind="stable")
    s, v = s[fin][order], v[fin][order]
    temp = np.interp(edges, s, v)
    if not np.ptp(temp) > 0:
        return None
    step = np.diff(temp)  # each block's change
    at = np.interp(ti[idx[0]:idx[-1]], s, v)
    wt = wi[idx[0]:idx[-1]] * (at - at.mean())[:, None]
    turn = np.add.reduceat(wt, idx[:-1] - idx[0], axis=0) / np.diff(idx)[:, None]
    return np.column_stack([step[1:], np.diff(step), np.diff(turn, axis=0)])


def _family_p(y, base, extra) -> float:
    """The p of the columns ``extra`` beside ``base`` fitting ``y`` (partial F, their rank)."""
    import numpy as np

    full = np.column_stack([base, extra])
    r0, r1 = np.linalg.matrix_rank(base), np.linalg.matrix_rank(full)
    dfe = len(y) - r1
    if r1 <= r0 or dfe < 1:
        return math.nan
    rss0 = np.sum((y - base @ np.linalg.lstsq(base, y, rcond=None)[0]) ** 2)
    rss1 = np.sum((y - full @ np.linalg.lstsq(full, y, rcond=None)[0]) ** 2)
    f = (rss0 - rss1) / (r1 - r0) / max(rss1 / dfe, 1e-300)
    return float(dist.f.sf(f, r1 - r0, dfe))


def _axis_below(ps: list[float]) -> tuple[int, float] | None:
    """The axis (0-2) whose p is smallest among those below α over the axes, or None."""
    alpha = ALPHA / len(ps)
    hit = [(i, p) for i, p in enumerate(ps) if p < alpha]
    return min(hit, key=lambda a: a[1]) if hit else None


def follows_motion(walk: dict, moved: list[tuple], tell=None) -> bool:
    """Whether the walk's estimate follows the motion (:func:`walk_motion`'s ``moved``).

    At p below α over the axes on any axis, the walk is not taken (``walk['why']``): a
    random walk absorbs any slowly varying gyro error, and one that is a function of the
    rate is a missing effect, not a wandering bias (the z gyro 500 ppm high for positive
    rates and low for negative on the clean 300-s psce bag: a walk of 29 deg/h/√h was
    accepted, doc/benchmarks.md, H160).  Records the axes' p in ``walk['motion_p']``.

    Where the bag's head temperature changes, the estimate following it (``walk
    ['temperature_p']``, at the same level) is not a walk either, and the reason names the
    regressor the estimate follows (``walk['follows']``: ``"rate"`` or ``"head
    temperature"``, whichever explains it beside the other: the smaller p of the two
    families each beside the other) with the other's p beside it; ``"rate and head
    temperature"`` where the rate wins and the temperature is significant beside it too.
    A rate it follows there is not said to be a gyro error: unseen case ``thermal_mount``
    s21 (the mount turning 2″/°C with the head temperature, no gyro error), the walk's x
    estimate follows the rate (p 7.8e-5; beside the temperature's columns 3.7e-6) and not
    the temperature (0.22; beside the rate 0.30): the turn is seen in the slews, which the
    rate's changes mark.  A gyro x bias changing 2 deg/h per °C with the same cooling (no
    rate error): the rate beside the temperature p 3.5e-8, the temperature beside the rate
    2.9e-4, both said (the estimate moves when the slews make the bias seen).
    """
    walk["motion_p"] = [m[1] for m in moved]
    walk["temperature_p"] = [m[5] if len(m) > 5 else math.nan for m in moved]
    hit = _axis_below(walk["motion_p"])
    heat = _axis_below(walk["temperature_p"])
    if hit is None and heat is None:
        return False
    i, p = min((h for h in (hit, heat) if h is not None), key=lambda h: h[1])
    m = moved[i]
    beside = (m[6], m[7]) if len(m) > 7 else (math.nan, math.nan)
    hot = heat is not None and (hit is None or beside[1] < beside[0]
                                or (math.isnan(beside[0]) and not math.isnan(beside[1])))
    also = not hot and beside[1] < ALPHA / len(moved)  # the temperature beside the rate too
    walk["follows"] = "head temperature" if hot else "rate and head temperature" if also \
        else "rate"
    if hot:
        p = m[5]
        why = (f"its {'xyz'[i]} bias estimate follows the head temperature (p = {p:.2g}; "
               f"beside the gyro's rate p = {beside[1]:.2g}, the rate beside it p = "
               f"{beside[0]:.2g}): a mount turning with the temperature or a gyro bias "
               "changing with it, not a wandering bias")
    elif math.isnan(beside[1]):  # (no head temperature that changes)
        p = m[1]
        why = (f"its {'xyz'[i]} bias estimate follows the gyro's rate (p = {p:.2g}): a gyro "
               "error that is a function of the motion, not a wandering bias")
    elif also:
        p = m[1]
        why = (f"its {'xyz'[i]} bias estimate follows the gyro's rate (p = {p:.2g}; beside "
               f"the head temperature p = {beside[0]:.2g}) and the head temperature beside "
               f"the rate (p = {beside[1]:.2g}): it moves as the motion and the temperature "
               "change (a gyro error, or the tracker turning against the IMU), not a "
               "wandering bias")
    else:  # the rate, and not the temperature beside it: the motion shows it, whatever it is
        p = m[1]
        why = (f"its {'xyz'[i]} bias estimate follows the gyro's rate (p = {p:.2g}; beside "
               f"it the head temperature p = {beside[1]:.2g}, the rate beside that p = "
               f"{beside[0]:.2g}): it moves as the motion changes (a gyro error of the "
               "rate, or the tracker turning against the IMU in the slews), not a wandering "
               "bias")
    _not_taken(walk, why, tell)
    return True


def comes_back(walk: dict, moved: list[tuple], tell=None) -> bool:
    """Whether the walk's estimate comes back with a period (:func:`walk_motion`'s ``moved``).

    A random walk's bias increments are white; a motion of the tracker against the IMU that
    the gyro does not see (a wobble, an effect outside the library) is followed by a walk's
    bias estimate as the wobble's rate, and comes back with its period.  At Fisher's g
    p below α over the axes on any axis the walk is not taken (``walk['why']``), so the
    round's periodic 'unexplained' line is said instead.  Measured (doc/benchmarks.md,
    "a wobble is not a walk"): unseen case ``wobble`` (5 arcsec, 45 s) s21 walk ~10
    deg/h/√h, g p 8.5e-7 / 2.8e-14 / 1.6e-3 at 45.8 s; true walks (``bias_walk10`` s21-23,
    ``bias_walk`` s21/s22) p >= 0.065 on 21 axes.  Records ``walk['periodic_p']``.
    """
    walk["periodic_p"] = [m[3] for m in moved]
    hit = _axis_below(walk["periodic_p"])
    if hit is None:
        return False
    i, p = hit
    _not_taken(walk, f"its {'xyz'[i]} bias estimate comes back every {moved[i][4]:.3g} s "
               f"(p = {p:.2g}): a periodic motion of the tracker the gyro does not see, not "
               "a wandering bias", tell)
    return True


def _not_taken(walk: dict, why: str, tell=None) -> None:
    """The walk not taken, for the reason ``why`` (recorded in ``walk`` and told)."""
    walk["accepted"] = False
    walk["why"] = why
    if tell:
        tell(f"noise: gyro bias walk not taken: {why}")


def beats_rivals(walk: dict, at: NoiseScales, base, rivals, tell=None) -> bool:
    """Whether the walk explains the stars' misfit better than each of the round's rivals.

    Quasi-AIC over the model's run ``base`` (its dispersion, mean NIS / 2 at least 1, as
    the candidates' ratio test): the walk's gain ``2 Δℓ / c − 2`` (one parameter) against
    each rival's ``2 Δℓ / c − 2 k`` (its ``k`` parameters), both with the scales ``at``.
    A walk that loses is not taken (``walk['why']`` names the effect): on a 60-s psce bag
    whose model misses a 0.5 ms time offset the walk alone was accepted at 0.87
    deg/h/√h in its place (doc/benchmarks.md, H151).  Records the best rival in ``walk``.
    """
    if rivals is None:
        return True
    c = max(1.0, base.window["nis"]["mean"] / 2.0)
    l0 = base.window["log_likelihood"]
    walk_q = 2.0 * (walk["loglik"] - l0) / c - 2.0
    best = None
    for effect, run, k in rivals(at):
        if not run.ok:
            continue
        q = 2.0 * (run.window["log_likelihood"] - l0) / c - 2.0 * k
        if best is None or q > best[1]:
            best = (effect, q, k)
    if best is None:
        return True
    walk["rival"] = {"effect": best[0], "parameters": int(best[2]), "qaic_gain": float(best[1]),
                     "walk_qaic_gain": float(walk_q)}
    if walk_q > best[1]:
        return True
    _not_taken(walk, f"{best[0]} explains more ({best[1]:.4g} against {walk_q:.4g} in "
               "penalised likelihood)", tell)
    return False


def _judge(runs, prior, effects: tuple[str, ...], base, tell, components: tuple[str, ...],
           stated: NoiseScales, ran: NoiseScales | None = None) -> NoiseVerdict:
    """:func:`measure`'s verdict from the run ``base``, made with the scales ``ran``.

    ``ran``: ``stated`` unless the run held a gyro bias walk (:func:`measure`'s second
    judgement), which every scale applied then keeps.
    """
    ran = ran or stated
    v = NoiseVerdict(stated, stated, method=runs.spec.name)
    n_tests = 1 + len(components)
    cam = prior.camera
    sn = base.star_noise
    applied = _from_samples(v, runs, components, n_tests).replace(
        gyro_bias_rw=ran.gyro_bias_rw, stamp_ms=ran.stamp_ms, frame_px=ran.frame_px)
    v.skipped = far_off(base, sn, base.calibration or prior, runs.fraction, v)
    if v.skipped:
        if tell:
            tell(f"noise: {v.skipped}")
        v.applied = applied
        return v
    if sn is not None:
        applied = judge_stars(v, sn, default_sigma(runs.spec.name), (cam.width, cam.height),
                              n_tests, applied)
        v.imu_skipped = structured(sn) if components else ""
        if v.imu_skipped:
            components = ()  # said once, in the verdict's lines
    for comp in components:
        cur = getattr(applied, comp)

        def loglik(xs: list[float], comp=comp, at=applied) -> list:
            tasks = [scale_task(comp, x, prior, effects, at) for x in xs]
            return _logliks(runs, tasks)

        known = {0.0: base.window["log_likelihood"]} if applied == ran and base.ok else {}
        # (white samples measured the sensor: the stars' search is their check, no bound;
        # where they keep the scale it is read only above 1, below)
        found = search_scale(comp, loglik, known=known, bound=not (
            comp in v.samples and v.samples[comp]["white"]), check=checks_only(v, comp))
        v.imu[comp] = found
        if tell:
            tell(f"noise: {comp} scale {found.value:.3g} +- {found.sigma:.2g} "
                 f"({len(found.points)} runs)" if found.measurable else
                 f"noise: {comp}: the stars ask no more than its samples (x3 fits no better "
                 f"than x1; {len(found.points)} runs)" if found.checked else
                 f"noise: {comp} scale at {'most' if found.bound == 'upper' else 'least'} "
                 f"{found.value:.3g} ({len(found.points)} runs)" if found.bound else
                 f"noise: {comp} scale not measurable on this bag")
        significant = (found.measurable or found.bound) and found.p_value < ALPHA / n_tests \
            and abs(found.value - 1.0) > MATERIAL
        if comp in v.samples and v.samples[comp]["white"]:
            # the samples measured the sensor; the stars asking for more is motion, not noise
            if significant and found.measurable and found.value > 1.0 + BEYOND:
                v.beyond.append(comp)
            continue
        if significant:
            v.rejected.append(comp)
            applied = applied.replace(**{comp: cur * found.value})
    if v.frame_common and ({"gyro", "accel"} & set(v.rejected) or v.beyond):
        # (the frames' mean innovations were judged on the run at the IMU noise it used: an
        # IMU noise not as stated moves them too, each frame's attitude error with it)
        v.frame_common = None
    v.applied = applied
    return v


def checks_only(v: NoiseVerdict, comp: str) -> bool:
    """Whether the stars' search of ``comp`` is read only where it measures above 1.

    Where the IMU's own samples look white and keep the stated scale: the verdict then
    reads the search only for motion beyond the samples' noise (a measured scale above
    1 + :data:`BEYOND`); nothing of it is printed or kept otherwise
    (:func:`~.noise_imu.search_scale`'s ``check`` stops it once x3 fits no better than x1).
    """
    return bool((v.samples.get(comp) or {}).get("white")) and comp not in v.rejected


def _logliks(runs, tasks: list[Task]) -> list:
    """The runs' window log-likelihoods with their frames (-inf where a run failed)."""
    out = runs.run_all(tasks, None)
    return [(out[t.key].window["log_likelihood"], out[t.key].frame_loglik)
            if out[t.key].ok else -math.inf for t in tasks]


#: the gyro bias walk's floor, deg/h/√h: the walk's search is over ln(D / floor), and the
#: model's own run (a constant bias, D = 0) stands for the floor (on the clean 600-s psce
#: bag 0.03 costs Δℓ = −1.2 against 0: 0.01 is 0 for the likelihood, doc/benchmarks.md)
WALK_FLOOR = 0.01
#: the walk's search starts at 1 deg/h/√h (its first runs 1/3 and 3) ...
WALK_START = math.log(1.0 / WALK_FLOOR)
#: ... and reaches at most 100 deg/h/√h
WALK_LN_RANGE = math.log(100.0 / WALK_FLOOR)


def walk_asked(v: NoiseVerdict, base, components: tuple[str, ...]) -> bool:
    """Whether :func:`measure` searches a wandering gyro bias after the verdict ``v``.

    When the model states no walk and the gyro is measured, and either the model's run is
    too far off for the noise (by its NIS: not a failed run nor a lost lock, where the
    likelihood says nothing) or the stars ask the gyro for more than its samples' noise
    (``v.beyond``): both are what a bias walk far above the stated does (unseen cases
    ``bias_walk10``, ``bias_walk``).  A clean bag does neither, and is not searched.
    """
    if "gyro" not in components or v.stated.gyro_bias_rw or not base.ok or not base.window:
        return False
    if "gyro" in v.beyond:
        return True
    return bool(v.skipped) and not base.lost_lock


def walk_task(x: float, prior, effects: tuple[str, ...], at: NoiseScales) -> Task:
    """The run of the gyro bias walk's search at ln(D / :data:`WALK_FLOOR`) = ``x``."""
    d = WALK_FLOOR * math.exp(x)
    return Task(f"noise gyro_bias_rw {d:.3g}", prior, tuple(effects),
                noise=at.replace(gyro_bias_rw=d), cost=SEARCH_COST, gyro_check=False,
                frame_loglik=True)


def search_walk(v: NoiseVerdict, runs, prior, effects: tuple[str, ...], base, tell,
                n_tests: int) -> dict:
    """ML density of a gyro bias random walk, against the best white gyro scale.

    :func:`~.noise_imu.search_scale` over ln(D / :data:`WALK_FLOOR`), around the scales
    ``v`` applies (the model's run ``base`` is the floor's point when it ran with them).
    The walk is accepted when its adjusted p is below α over the tests (``n_tests`` and
    itself) and its best likelihood beats the best white gyro scale's (the gyro's search
    in ``v``, else one run here): one parameter each, the walk must explain the stars'
    misfit better than more white gyro noise (H130: Δℓ = 262 on ``bias_walk10``).
    Returns the record ``diagnosis.json`` keeps (``noise.gyro_bias_rw``).
    """
    at = v.applied
    known = {0.0: base.window["log_likelihood"]} if at == v.stated else {}
    found = search_scale("gyro_bias_rw", lambda xs: _logliks(
        runs, [walk_task(x, prior, effects, at) for x in xs]), start=WALK_START,
        known=known, ln_range=WALK_LN_RANGE, lowest=0.0)
    d, sd = WALK_FLOOR * found.value, WALK_FLOOR * found.sigma
    alpha = ALPHA / (n_tests + 1)
    l_walk = max(found.points.values())
    out = {"deg_h_sqrth": float(d), "sigma": float(sd) if math.isfinite(sd) else None,
           "p_value": float(found.p_value), "alpha": float(alpha),
           "statistic": float(found.statistic), "dispersion": float(found.dispersion),
           "loglik_gain": float(l_walk - found.points.get(0.0, math.nan)),
           "loglik": float(l_walk),
           "runs": len(found.points) - len(known), "accepted": False}
    white = v.imu.get("gyro")
    # (a check stopped at x3 holds no maximum: searched here as if not made)
    white = None if white is not None and white.checked else white
    if white is None and found.measurable and found.p_value < alpha:
        # (searched only when the walk could be taken: a far-off model's walk usually has
        # no maximum in range, and the white search's runs would decide nothing)
        white = search_scale("gyro", lambda xs: _logliks(
            runs, [scale_task("gyro", x, prior, effects, at) for x in xs]), known=known,
            bound=False)
        out["runs"] += len(white.points) - len(known)
    l_white = max(white.points.values()) if white is not None else math.nan
    if white is not None:
        out["over_white_gyro"] = float(l_walk - l_white)
        out["white_gyro_scale"] = float(math.exp(max(white.points, key=white.points.get)))
    if not found.measurable:
        # (a maximum whose 95 % interval reaches the floor, a constant bias, is no
        # measured walk either: :func:`~.noise_imu.search_scale`)
        out["why"] = ("a constant bias fits best" if max(found.points, key=found.points.get)
                      == 0.0 else f"not significant (p = {found.p_value:.2g})"
                      if not found.p_value < alpha else "no maximum in range")
    elif not found.p_value < alpha:
        out["why"] = f"not significant (p = {found.p_value:.2g})"
    elif not l_walk > l_white:
        out["why"] = (f"white gyro noise x{out['white_gyro_scale']:.3g} fits as well "
                      f"(by {l_white - l_walk:.3g} in log-likelihood)")
    else:
        out["accepted"] = True
    if tell:
        over = (f", {out['over_white_gyro']:+.4g} over white gyro noise"
                if "over_white_gyro" in out else "")
        tell(f"noise: gyro bias walk {d:.3g} +- {sd:.2g} deg/h/sqrt(h) "
             f"(p = {found.p_value:.2g}{over}; {out['runs']} runs)"
             + ("" if out["accepted"] else f": not taken, {out['why']}"))
    return out


#: the stars' ML scale over the samples' above which the excess is motion, not noise
BEYOND = 0.5
#: the search's runs go before runs queued ahead of need (a round's candidates beside its
#: base run, :func:`~stellar_cal_ros.diagnosis.discover.measure_round_noise`): the search
#: waits for them, and the candidates' runs wait for the verdict
SEARCH_COST = 10.0


def scale_task(comp: str, x: float, prior, effects: tuple[str, ...], at: NoiseScales) -> Task:
    """The run of the ML search of ``comp`` at ln scale ``x`` around the scales ``at``.

    Without the gyro-against-stars check: the search reads the run's log-likelihood alone
    (the check changes no estimate), and :func:`measure` runs only after the current
    model's run on the bag, which judged the gyro, succeeded (≈ 1 CPU-s a run on a 2-h bag).
    With the log-likelihood frame by frame (the search's sandwich σ).
    """
    return Task(f"noise {comp} x{math.exp(x):.3g}", prior, tuple(effects),
                noise=at.replace(**{comp: getattr(at, comp) * math.exp(x)}),
                cost=SEARCH_COST, gyro_check=False, frame_loglik=True)


def first_runs(runs, prior, effects: tuple[str, ...],
               components: tuple[str, ...] = ("gyro",)) -> list[Task]:
    """The runs :func:`measure` starts its first ML search with, if the stars keep the scales.

    Known before the base run (the usual case): run beside it on an idle worker
    (:meth:`~stellar_cal_ros.diagnosis.parallel.Runs.run_ahead`); any other case simply
    does not use them.
    """
    if not components:
        return []
    stated = runs.noise or NoiseScales()
    v = NoiseVerdict(stated, stated, method=runs.spec.name)
    at = _from_samples(v, runs, components, 1 + len(components))
    # ln s = 0 is the base run itself when the samples keep the stated scales; a check
    # runs the point below only when the one above fits better (search_scale's ``check``)
    low = checks_only(v, components[0])
    return [scale_task(components[0], x, prior, effects, at) for x in first_points()
            if (x != 0.0 or at != stated) and not (low and x < 0.0)]


def start_samples(runs, components: tuple[str, ...] = ("gyro",)) -> None:
    """Start the IMU samples' scales (:func:`_from_samples`) on a free worker, if any.

    So that :func:`first_runs` and :func:`measure` find them computed beside the base run
    instead of waiting for them (:meth:`~stellar_cal_ros.diagnosis.parallel.Runs.on_bag_soon`).
    """
    stated = runs.noise or NoiseScales()
    for comp in components:
        runs.on_bag_soon(imu_sample_scale, runs.spec.name, comp, stated)


def _from_samples(v: NoiseVerdict, runs, components: tuple[str, ...], n_tests: int
                  ) -> NoiseScales:
    """The IMU components' scales from their own samples (where they look white)."""
    applied = v.stated
    for comp in components:  # computed where the bag is: the parent does not read it
        s, e, white, axes = runs.on_bag(imu_sample_scale, runs.spec.name, comp, v.stated)
        if not math.isfinite(s):
            continue
        v.samples[comp] = {"scale": float(s), "sigma": float(e), "white": bool(white)}
        if axes:  # one axis unlike the others: said per axis, the scale is their RMS
            v.samples[comp]["axes"] = [float(a) for a in axes]
        if white and p_two_sided(s, e) < ALPHA / n_tests and abs(s - 1.0) > MATERIAL:
            v.rejected.append(comp)
            applied = applied.replace(**{comp: getattr(v.stated, comp) * s})
    return applied
