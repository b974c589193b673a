"""A focal length that changes over the run: ``discover``'s rule for the lines it leaves.

No library effect lets the focal length change with time alone (thermal_focal_length needs
the tracker's temperature).  A model that estimates a constant f follows the drift's
running mean: on a linear drift ``k t`` its estimate lags ``k t / 2`` behind, so the
evaluation window (the run's second half) holds mostly a *static* image scale (the window's
mean lag) and only a smaller part that changes over it.  Ranked by p, the static scale's
lines come first (unseen case ``focal_drift``, 150 ppm over 300 s: ``u vs u``, ``v vs v``
and their one-period sines at t 20-23, p ~ 1e-30) and the only time line is
``radial vs time``, 12th.  A scale the filter could estimate and does not hold is itself
the sign of a lag.

The rule (:func:`first_if_cause`): on a model that estimates f, when the window's static
scale is significant and so is its change over the window given it
(:func:`~stellar_cal_ros.diagnosis.stats.scale_change`, the same sign: a lag behind a drift
leaves both of the drift's sign), one run of the same model on the bag with the drift the
change says taken out of the centroids (:func:`taken_out`).  The lines that are gone there
follow the drift: a line naming it goes before them, its size the drift over the run (ppm,
and px at the detector's corner).  The same evidence as the rolling shutter's
(:func:`~stellar_cal_ros.diagnosis.rolling.first_if_cause`).  Nothing runs unless both
tests are significant: on a bag without a drift nothing changes.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from stellar_cal_ros.diagnosis import rolling, stats
from stellar_cal_ros.io.calibration import Calibration

#: the line's regressor (its size and rate follow in the name)
REGRESSOR = "time x radius (the focal length changes over the run"
#: what the lines that follow it say they follow (``summary["unexplained"][i]["follows"]``)
CAUSE = "focal length drift"
#: the rule's two tests (the static scale, its change), Bonferroni
TESTS = 2


def of_table(res, calibration: Calibration, fraction: float) -> dict[str, float] | None:
    """:func:`~stellar_cal_ros.diagnosis.stats.scale_change` of a residual table's window."""
    if res is None or not len(res.get("t", ())):
        return None
    cam = calibration.camera
    return stats.scale_change(res, stats.evaluation_mask(res, fraction), (cam.cx, cam.cy),
                              (cam.fx, cam.fy))


def lagging(fit: dict[str, float] | None, alpha: float) -> bool:
    """Whether ``fit`` reads a filter lagging a drift: both tests significant, one sign."""
    return (fit is not None and fit["static_p"] * TESTS < alpha
            and fit["change_p"] * TESTS < alpha
            and np.sign(fit["static_ppm"]) == np.sign(fit["change_ppm"]))


def taken_out(data, calibration: Calibration, rate_per_s: float):
    """A copy of the bag with a linear focal drift taken out of its centroids.

    Each centroid scaled about ``calibration``'s principal point by ``1 / (1 + k (t −
    t_first))`` (``k`` = ``rate_per_s``, relative scale per second, ``t`` the frame's stamp;
    the scale at the first frame stays, the model's f takes up any constant).
    """
    cam = calibration.camera
    c = np.array([cam.cx, cam.cy])
    if not data.frames:
        return dataclasses.replace(data, frames=[])
    first = min(f.stamp_ns for f in data.frames)
    frames = []
    for f in data.frames:
        uv = np.asarray(f.uv, dtype=float).reshape(-1, 2)
        scale = 1.0 + rate_per_s * (f.stamp_ns - first) * 1e-9
        frames.append(dataclasses.replace(f, uv=c + (uv - c) / scale) if len(uv) else f)
    return dataclasses.replace(data, frames=frames)


def lines_without_on_bag(data, spec, prior: Calibration, effects: tuple[str, ...],
                         fraction: float, noise, classes: tuple[type, ...],
                         calibration: Calibration, rate_per_s: float, tests
                         ) -> tuple[tuple[tuple[str, str], ...], dict | None] | None:
    """The 'unexplained' lines of a run on the bag without the drift, and its scale tests.

    One run of the same model on :func:`taken_out` (for :meth:`~stellar_cal_ros.diagnosis.
    parallel.Runs.on_bag`): the lines as (regressor, component)
    (:func:`~stellar_cal_ros.diagnosis.rolling.line_key`) and :func:`of_table` of that run.
    ``tests``: as :func:`~stellar_cal_ros.diagnosis.rolling.lines_without_on_bag`'s.
    """
    got = rolling.rerun_lines(taken_out(data, calibration, rate_per_s), spec, prior, effects,
                              fraction, noise, classes, tests)
    if got is None:
        return None
    keys, run = got
    return keys, of_table(run.residuals, run.calibration, fraction)


def corner_px(calibration: Calibration) -> float:
    """The detector's farthest corner from the principal point (px)."""
    cam = calibration.camera
    return float(np.hypot(max(cam.cx, cam.width - cam.cx), max(cam.cy, cam.height - cam.cy)))


def first_if_cause(found: list, run, runs, tests, alpha: float = 0.01, keep=frozenset()
                   ) -> tuple[list, set[int]]:
    """``found`` with a line naming a drifting focal length first, when the lines are its.

    On a model that estimates the focal length (``focal_length`` in the method's baseline
    or the run's effects), when :func:`lagging` holds on ``run``'s window: one run on the
    bag with the drift taken out (:func:`taken_out`, at twice the window's rate of change:
    a constant-f filter follows a linear drift's running mean, half its rate; unseen case
    ``focal_drift`` seeds 21 / 22 read 144 / 147 ppm over the run for 150).  Fires only if
    some line of ``found`` is gone there (the evidence); then the line
    (:data:`REGRESSOR`: the drift over the run, ppm ± its σ from the change test's t,
    its size the px at the detector's corner; t and p of the change test, p ×
    :data:`TESTS`) goes before the first line that is gone, the lines that are gone
    after it (they follow it: their indices in the returned list returned), the others
    after them.  Unchanged otherwise, and without a runner.
    """
    if (not found or runs is None or run is None or not run.ok or run.prior is None
            or run.calibration is None or run.residuals is None):
        return found, set()
    if "focal_length" not in (*runs.spec.baseline, *run.effects):
        return found, set()
    fit = of_table(run.residuals, run.calibration, runs.fraction)
    if not lagging(fit, alpha):
        return found, set()
    rate = 2.0 * fit["rate_per_s"]
    again = runs.on_bag(lines_without_on_bag, runs.spec, run.prior, tuple(run.effects),
                        runs.fraction, runs.noise, runs.classes, run.calibration, rate, tests)
    if again is None or again[1] is None:
        return found, set()
    left, rest = set(again[0]), again[1]
    follows = [f for f in found if rolling.gone(f, left, keep)]
    if not follows:
        return found, set()
    t = np.asarray(run.residuals["t"], dtype=float)
    span = float(np.ptp(t)) if len(t) else 0.0
    ppm = rate * span * 1e6
    sd = abs(ppm / fit["change_t"])
    edge = corner_px(run.calibration)
    line = stats.RegressorFinding(
        f"{REGRESSOR}: {ppm:+.3g} +- {sd:.2g} ppm over {span:.0f} s; a constant f lags it; "
        "outside the library)", "radial", fit["change_t"],
        min(1.0, fit["change_p"] * TESTS), abs(ppm * 1e-6 * edge),
        detail={"cause": CAUSE, "ppm_over_run": ppm, "sigma_ppm": sd,
                "ppm_per_s": rate * 1e6, "run_s": span, "corner_px": edge,
                "static_ppm": fit["static_ppm"], "static_t": fit["static_t"],
                "window_change_ppm": fit["change_ppm"], "static_t_without": rest["static_t"],
                "static_ppm_without": rest["static_ppm"]})
    at = found.index(follows[0])
    stays = [f for f in found[at:] if not rolling.gone(f, left, keep)]
    out = found[:at] + [line] + follows + stays
    return out, set(range(at + 1, at + 1 + len(follows)))
