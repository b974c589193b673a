"""A camera shape that changes over the run: ``discover``'s rule for the lines it leaves.

No library effect lets the focal length or the detector's tilt change with time alone
(thermal_focal_length needs the tracker's temperature; image_plane_tilt is static). Such a
drift leaves, in the evaluation window (the run's second half), mostly a *static* shape and
only a smaller part that changes over it, and ranked by p the static shape's lines come
first with no line on time. A model that follows the shape (estimates it, or spans it with
its other camera parameters: psce's principal point spans the keystone of a tilt about u to
1.0 once each frame's attitude takes up the rotation, so a principal point that drifts reads
as a tilt that drifts, and the line says both) follows the drift's running mean: on a linear
drift ``k t`` its estimate lags ``k t / 2`` behind, and the window holds the mean lag
(unseen case ``focal_drift``, 150 ppm over 300 s: ``u vs u``, ``v vs v`` and their
one-period sines at t 20-23, p ~ 1e-30, the only time line ``radial vs time``, 12th; unseen
case ``tilt_drift``, the tilt about u −1.5 → +1.5 mrad: ``v vs v (row)``, ``radial vs v
(row)`` at t ~ 24, the keystone's lag +1.2 mrad). A shape the filter could follow and does
not hold is itself the sign of a lag.

The rule (:func:`first_if_cause`), for each of the camera's shapes (:data:`SHAPES`: the
image scale, the two tilts; their patterns :func:`~stellar_cal_ros.diagnosis.stats.
shape_pattern`) a model follows: when the window's static shape and its change over the
window given it are both significant (:func:`~stellar_cal_ros.diagnosis.stats.
shape_change`) and of one sign (a lag behind a drift leaves both of the drift's sign), one
run of the same model on the bag with the drift the change says taken out of the centroids
(:func:`taken_out`).  The lines that are gone there follow the drift: a line naming it goes
before them, its size the drift over the run (ppm or mrad, and px at the detector's
corner).  The same evidence as the rolling shutter's (:func:`~stellar_cal_ros.diagnosis.
rolling.first_if_cause`).  Nothing runs unless both tests are significant: on a bag without
a drift nothing changes; on a model with no camera parameter (swaying's) nothing is tested.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from stellar_cal_ros.diagnosis import rolling, stats
from stellar_cal_ros.io.calibration import Calibration


@dataclasses.dataclass(frozen=True)
class Shape:
    """One shape parameter of the camera the rule reads a drift of.

    ``name``: :data:`~stellar_cal_ros.diagnosis.stats.SHAPES`' entry; ``effect``: the
    library effect that estimates it (constant); ``unit``, ``per_unit``: how its size is
    printed (the parameter × ``per_unit``); ``regressor``: the line's regressor (its size
    and rate follow in the name); ``cause``: what the lines that follow it say they follow
    (``summary["unexplained"][i]["follows"]``); ``lags``: the line's words when the model
    estimates it.
    """

    name: str
    effect: str
    unit: str
    per_unit: float
    regressor: str
    cause: str
    lags: str


#: the image scale, a focal length that drifts
SCALE = Shape("scale", "focal_length", "ppm", 1e6,
              "time x radius (the focal length changes over the run", "focal length drift",
              "a constant f lags it")
#: the camera's shapes the rule tests, in this order (the scale's first)
SHAPES = (SCALE,
          Shape("tau_x", "image_plane_tilt", "mrad", 1e3,
                "time x keystone along v (the image-plane tilt tau_x changes over the run",
                "image-plane tilt drift", "a constant tilt lags it"),
          Shape("tau_y", "image_plane_tilt", "mrad", 1e3,
                "time x keystone along u (the image-plane tilt tau_y changes over the run",
                "image-plane tilt drift", "a constant tilt lags it"))
#: the scale's line's regressor (``SCALE.regressor``)
REGRESSOR = SCALE.regressor
#: what the lines that follow the scale's drift say they follow (``SCALE.cause``)
CAUSE = SCALE.cause
#: each shape's two tests (the static part, its change)
TESTS = 2
#: the rule's family: every shape's two tests, Bonferroni (the condition and the line's p)
FAMILY = TESTS * len(SHAPES)
#: a model whose camera parameters span more than this share of a shape's pattern follows
#: it as if it estimated it (psce's principal point alone spans a tilt's keystone to 1.0
#: once each frame's attitude takes up the rotation, tangential p1 0.89: unseen case
#: ``tilt_drift``'s filter lags the tilt; the pixel aspect spans the scale 0.50, kept out)
SPANNED = 0.8
#: :func:`patterns` computes the camera's Jacobian in blocks of this many rows
PATTERN_ROWS = 16384
#: the principal point's coordinate whose drift reads as each tilt's (the same keystone
#: once the attitude takes up its rotation): its axis, name and focal length
TWIN_POINT = {"tau_x": ("v", "c_y", "fy"), "tau_y": ("u", "c_x", "fx")}


def of_table(res, calibration: Calibration, fraction: float, shape: Shape = SCALE,
             model: tuple[str, ...] | None = None) -> dict[str, float] | None:
    """:func:`~stellar_cal_ros.diagnosis.stats.shape_change` of a residual table's window.

    ``model``: the effects of a model that does not estimate ``shape``: the share of its
    pattern the model's camera parameters span (:func:`patterns`) is read too.
    """
    if res is None or not len(res.get("t", ())):
        return None
    cam = calibration.camera
    return stats.shape_change(res, stats.evaluation_mask(res, fraction), (cam.cx, cam.cy),
                              (cam.fx, cam.fy), shape.name,
                              None if model is None else patterns(calibration, model))


def camera_columns(effects: tuple[str, ...]) -> tuple[tuple[str, ...], ...]:
    """The camera parameters the effects estimate, one tuple a pattern.

    Names of :attr:`~stellar_cal_ros.core.camera.CameraModel.PARAMETER_NAMES`, summed within
    a tuple: ``fx`` and ``fy`` move together for the focal length, ``fy`` alone for the
    pixel aspect.
    """
    from stellar_cal_ros.effects.registry import available, effect_class

    known = set(available())
    out: list[tuple[str, ...]] = []
    for e in dict.fromkeys(effects):
        if e == "focal_length":
            out.append(("fx", "fy"))
        elif e == "pixel_aspect":
            out.append(("fy",))
        elif e in known:
            out += [(n,) for n in getattr(effect_class(e), "camera_entries", ())]
    return tuple(out)


def patterns(calibration: Calibration, effects: tuple[str, ...]):
    """``(u, v) -> (N, 2, k)``: the displacement per unit of the camera parameters estimated.

    Those ``effects`` estimate (:func:`camera_columns`; the camera's Jacobian at the points,
    ``fx``, ``fy`` per relative change), for :func:`~stellar_cal_ros.diagnosis.stats.
    shape_change`'s ``against``; ``None`` when they estimate none.
    """
    cam = calibration.camera
    cols = camera_columns(effects)
    if not cols:
        return None
    names = list(cam.PARAMETER_NAMES)
    scale = np.ones(len(names))
    scale[:2] = (cam.fx, cam.fy)

    def at(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        xy = cam.pixel_to_normalized(np.stack([u, v], 1))
        d = np.concatenate([xy, np.ones((len(xy), 1))], 1)
        out = np.empty((len(d), 2, len(cols)))
        # the Jacobian (N, 2, 18) in blocks of rows (each row's the same floats): a 2-h
        # run's window made it and its scaled copy at once, ≈ 60 MB
        for a in range(0, len(d), PATTERN_ROWS):
            _, _, jp = cam.project(d[a:a + PATTERN_ROWS], jacobians=True)
            jp = np.asarray(jp) * scale
            out[a:a + PATTERN_ROWS] = np.stack(
                [jp[:, :, [names.index(n) for n in c]].sum(2) for c in cols], 2)
        return out

    return at


def lagging(fit: dict[str, float] | None, alpha: float) -> bool:
    """Whether ``fit`` reads a filter lagging a drift: both tests significant, one sign."""
    return (fit is not None and fit["static_p"] * FAMILY < alpha
            and fit["change_p"] * FAMILY < alpha
            and np.sign(fit["static"]) == np.sign(fit["change"]))


def taken_out(data, calibration: Calibration, rate_per_s: float, shape: Shape = SCALE,
              middle: bool = False):
    """A copy of the bag with a linear drift of ``shape`` taken out of its centroids.

    Each centroid's offset ``d`` from ``calibration``'s principal point divided by ``1 +
    a w``, ``a = k (t − t_ref)`` (``k`` = ``rate_per_s``, the parameter per second, ``t``
    the frame's stamp), ``w`` the shape's pattern per unit along ``d``: 1 for the scale,
    ``d_v / f_y`` for tau_x, ``−d_u / f_x`` for tau_y (first order).  ``t_ref``, where the
    shape stays: the first frame's stamp (a model that estimates the shape takes up any
    constant), or with ``middle`` the run's middle (the drift's mean over the run stays).
    """
    cam = calibration.camera
    c = np.array([cam.cx, cam.cy])
    if not data.frames:
        return dataclasses.replace(data, frames=[])
    first = min(f.stamp_ns for f in data.frames)
    if middle:
        first = (first + max(f.stamp_ns for f in data.frames)) // 2
    frames = []
    for f in data.frames:
        uv = np.asarray(f.uv, dtype=float).reshape(-1, 2)
        a = rate_per_s * (f.stamp_ns - first) * 1e-9
        d = uv - c
        scale = 1.0 + a * stats.shape_weight(shape.name, d[:, 0:1], d[:, 1:2],
                                             (cam.fx, cam.fy))
        frames.append(dataclasses.replace(f, uv=c + (uv - c) / scale) if len(uv) else f)
    return dataclasses.replace(data, frames=frames)


def lines_without_on_bag(data, spec, prior: Calibration, effects: tuple[str, ...],
                         fraction: float, noise, classes: tuple[type, ...],
                         calibration: Calibration, rate_per_s: float, tests,
                         shape: Shape = SCALE, middle: bool = False
                         ) -> tuple[tuple[tuple[str, str], ...], dict | None] | None:
    """The 'unexplained' lines of a run on the bag without the drift, and its shape tests.

    One run of the same model on :func:`taken_out` (for :meth:`~stellar_cal_ros.diagnosis.
    parallel.Runs.on_bag`): the lines as (regressor, component)
    (:func:`~stellar_cal_ros.diagnosis.rolling.line_key`) and :func:`of_table` of that run.
    ``tests``: as :func:`~stellar_cal_ros.diagnosis.rolling.lines_without_on_bag`'s.
    """
    got = rolling.rerun_lines(taken_out(data, calibration, rate_per_s, shape, middle), spec,
                              prior, effects, fraction, noise, classes, tests)
    if got is None:
        return None
    keys, run = got
    return keys, of_table(run.residuals, run.calibration, fraction, shape)


def corner_px(calibration: Calibration, shape: Shape = SCALE) -> float:
    """The shape's displacement per unit at the detector's corner (px).

    The corner farthest from the principal point; for the scale its distance.
    """
    cam = calibration.camera
    du, dv = max(cam.cx, cam.width - cam.cx), max(cam.cy, cam.height - cam.cy)
    r = float(np.hypot(du, dv))
    return r * abs(stats.shape_weight(shape.name, du, dv, (cam.fx, cam.fy)))


def first_if_cause(found: list, run, runs, tests, alpha: float = 0.01, keep=frozenset(),
                   started: dict | None = None) -> tuple[list, dict[int, str]]:
    """``found`` with a line naming each drifting camera shape first, when the lines are its.

    For each of :data:`SHAPES` in turn (:func:`shape_first`); a line that follows one
    shape's drift stays behind it.  Returns the lines and ``{index: cause}`` (in the
    returned list) of those that follow a drift.  ``started``: :func:`start_first_runs`'s
    of the same ``run``, ``runs``, ``tests`` and ``alpha``.
    """
    follows: dict[int, str] = {}
    for shape in SHAPES:
        found, after = shape_first(found, run, runs, tests, shape, alpha,
                                   frozenset(keep) | frozenset(follows),
                                   (started or {}).get(shape.name))
        follows.update((id(found[i]), shape.cause) for i in after)
    return found, {i: follows[id(f)] for i, f in enumerate(found) if id(f) in follows}


def _first_run(run, runs, shape: Shape, alpha: float) -> tuple[bool, dict, float] | None:
    """:func:`shape_first`'s conditions on ``run``: (own, the window's fit, the rate) or None."""
    if (runs is None or run is None or not run.ok or run.prior is None
            or run.calibration is None or run.residuals is None):
        return None
    model = (*runs.spec.baseline, *run.effects)
    own = shape.effect in model
    if not own and not camera_columns(model):
        return None
    fit = of_table(run.residuals, run.calibration, runs.fraction, shape, None if own else model)
    if not (own or (fit is not None and fit["spanned"] > SPANNED)) or not lagging(fit, alpha):
        return None
    return own, fit, 2.0 * fit["rate_per_s"]


def _without(run, runs, tests, shape: Shape, own: bool, k: float, soon: bool = False):
    """The run on the bag without the drift at ``k`` (``soon``: started, a function of it)."""
    call = runs.later if soon else runs.on_bag
    return call(lines_without_on_bag, runs.spec, run.prior, tuple(run.effects), runs.fraction,
                runs.noise, runs.classes, run.calibration, k, tests, shape, not own)


def start_first_runs(run, runs, tests, alpha: float = 0.01) -> dict[str, tuple]:
    """:func:`first_if_cause`'s first run of each shape, started now, beside the line tests.

    Every argument of a shape's first run is known from ``run`` alone (its lines only
    decide whether it is needed: some line to explain), so on a cluster
    (:meth:`~stellar_cal_ros.diagnosis.parallel.Runs.later`) a worker makes it while this
    process computes the line tests; in this process it runs only when asked for.  Returns
    ``{shape name: (own, fit, rate, value)}`` of the shapes whose run starts.
    """
    out = {}
    for shape in SHAPES:
        first = _first_run(run, runs, shape, alpha)
        if first is not None:
            out[shape.name] = (*first, _without(run, runs, tests, shape, first[0], first[2],
                                                soon=True))
    return out


def shape_first(found: list, run, runs, tests, shape: Shape = SCALE, alpha: float = 0.01,
                keep=frozenset(), started: tuple | None = None) -> tuple[list, set[int]]:
    """``found`` with a line naming a drift of ``shape`` first, when the lines are its.

    On a model that estimates the shape (its ``effect`` in the method's baseline or the
    run's effects) or whose camera parameters span more than :data:`SPANNED` of its
    pattern (psce's principal point and tangential distortion: a tilt's keystone), when
    :func:`lagging` holds on ``run``'s window: one run on the bag with the drift taken out
    (:func:`taken_out`, at twice the window's rate of change: a constant filter follows a
    linear drift's running mean, half its rate; unseen case ``focal_drift`` seeds 21 / 22
    read 144 / 147 ppm over the run for 150; about the first frame for its own parameter,
    about the run's middle for a spanned one, whose mean over the run, a static shape, the
    other parameters take up only in part).  When lines are left there and so is a
    significant static part, one more run at the rate a secant step puts (:func:`_secant`).
    Fires only if some line of ``found`` is gone there (the evidence);
    then the line (the shape's ``regressor``: the drift over the run ± its σ from the
    change test's t, its size the px at the detector's corner; t and p of the change test,
    p × :data:`FAMILY`) goes before the first line that is gone, the lines that are gone
    after it (they follow it: their indices in the returned list returned), the others
    after them.  Unchanged otherwise, and without a runner.  ``started``:
    :func:`start_first_runs`'s entry of ``shape`` (its first run's value taken from it).
    """
    if not found:
        return found, set()
    first = started[:3] if started is not None else _first_run(run, runs, shape, alpha)
    if first is None:
        return found, set()
    own, fit, rate = first
    t = np.asarray(run.residuals["t"], dtype=float)

    def without(k: float):
        return _without(run, runs, tests, shape, own, k)

    again = started[3]() if started is not None else without(rate)
    if again is None or again[1] is None:
        return found, set()
    left, rest = set(again[0]), again[1]
    better = _secant(rate, fit, rest, alpha) if any(
        not rolling.gone(f, left, keep) for f in found) else None
    if better is not None:
        twice = without(better)
        # kept only if it leaves no more of the lines than the first run did
        if (twice is not None and twice[1] is not None
                and sum(not rolling.gone(f, set(twice[0]), keep) for f in found)
                <= sum(not rolling.gone(f, left, keep) for f in found)):
            rate, left, rest = better, set(twice[0]), twice[1]
    follows = [f for f in found if rolling.gone(f, left, keep)]
    if not follows:
        return found, set()
    span = float(np.ptp(t)) if len(t) else 0.0
    u = shape.unit
    size = rate * span * shape.per_unit
    sd = abs(size / fit["change_t"])
    edge = corner_px(run.calibration, shape)
    detail = {"cause": shape.cause, f"{u}_over_run": size, f"sigma_{u}": sd,
              f"{u}_per_s": rate * shape.per_unit, "run_s": span, "corner_px": edge,
              f"static_{u}": fit["static"] * shape.per_unit, "static_t": fit["static_t"],
              f"window_change_{u}": fit["change"] * shape.per_unit,
              "static_t_without": rest["static_t"],
              f"static_{u}_without": rest["static"] * shape.per_unit}
    if own:
        how = shape.lags
    else:
        detail.update(shape=shape.name, spanned=fit["spanned"])
        how = (f"the model's other camera parameters span {100 * fit['spanned']:.3g} % of it "
               "and follow it late")
        if shape.name in TWIN_POINT:  # the principal point drifting reads the same
            axis, name, f_name = TWIN_POINT[shape.name]
            px = size / shape.per_unit * float(getattr(run.calibration.camera, f_name))
            detail[f"{name}_px_over_run"] = px
            how += (f"; or equally the principal point's {axis} ({name}) drifting by "
                    f"about {abs(px):.2g} px (first order), which the same lines cannot "
                    "tell apart")
    line = stats.RegressorFinding(
        f"{shape.regressor}: {size:+.3g} +- {sd:.2g} {u} over {span:.0f} s; {how}; "
        "outside the library)", "radial", fit["change_t"],
        min(1.0, fit["change_p"] * FAMILY), abs(size / shape.per_unit * edge), detail=detail)
    at = found.index(follows[0])
    stays = [f for f in found[at:] if not rolling.gone(f, left, keep)]
    out = found[:at] + [line] + follows + stays
    return out, set(range(at + 1, at + 1 + len(follows)))


def _secant(rate: float, fit: dict[str, float], rest: dict[str, float], alpha: float
            ) -> float | None:
    """A better rate to take out when the run without ``rate`` still holds a static part.

    The lag a drift leaves is linear in the drift: the window's static part ``fit`` read
    with nothing taken out and ``rest`` with ``rate`` taken out put the rate that leaves
    none on their line (a secant step).  ``None`` when ``rest``'s static part is not
    significant (p × :data:`FAMILY` ≥ ``alpha``) or the step is not between half and twice
    ``rate`` (unseen case ``tilt_drift`` seed 21: 3.33 mrad over the run taken out left
    −0.17 mrad, t −7.9, and the static keystone's lines; the step reads 2.9 for 3.0).
    """
    if rest["static_p"] * FAMILY >= alpha or fit["static"] == rest["static"]:
        return None
    step = fit["static"] / (fit["static"] - rest["static"])
    return rate * step if 0.5 < step < 2.0 else None
