"""Outside-library leads as nuisance fields: ``discover``'s stand-in rule beside them.

A structure no library effect models can still be taken up, in part, by one: a step of the
centroids on one detector quadrant by an image-plane tilt's second-order field (unseen case
``quadrant``: image_plane_tilt 9.5 mrad added, p 9e-68), a centroid bias that grows with
magnitude by the gyro terms and the pixel aspect through the changing mix of the stars in
view (a twin of the independent 900 s PSCE bag with ``magnitude_bias=0.02,30``: three
library effects added before the right 'unexplained: u residual vs magnitude' line).  The
rule already made for a rolling shutter and a mount flexure
(:func:`~stellar_cal_ros.diagnosis.rolling.stand_in`, :func:`~stellar_cal_ros.diagnosis.
flexure.beyond`) applies to them once their shape is a nuisance regressor of the
innovations: a field of the detector's cells (a per-cell offset, u and v, on the grid of
the noise's cell means, :data:`~stellar_cal_ros.diagnosis.noise_stars.CELL_GRID`) and a
field along magnitude (offsets linear in magnitude, along u, v and the radius).

Each field has many columns; the one displacement pattern fitted is their least-squares
combination on the frames *before* the evaluation window (the direction), tested and sized
in the window (:func:`~stellar_cal_ros.diagnosis.stats.whitened_fit`: the frame-robust
t_ν of every 'unexplained' line, ``chi2_capped`` in the candidates' currency).  A direction
chosen on the data it is tested on would make a χ²_k of a t; chosen on other frames it is a
fixed pattern for the window's test.  A field is a lead when that test is significant on the
current model (Bonferroni over the fields); a candidate is then added only if it explains
the data beyond the field, or the field is no longer significant beside it (the rolling
shutter's rule, :func:`~stellar_cal_ros.diagnosis.rolling.stand_in`).  Nothing runs unless a
candidate is significant alone; on a bag where no field is a lead nothing changes.

A third field is a mount bending with gravity (unseen case ``sway_flex``: 10″/g on the
swaying base was named gyro_scale_factor −46, −43 ppm with nothing unexplained).  Its one
pattern is the flexure probe's response (:mod:`~stellar_cal_ros.diagnosis.flexure`, the
test made after an add, the same functions): one more run of the current model, with the
probe, and one of the candidate's, asked only for a candidate that may stand in for a
flexure (not a camera effect) and before any add found a remainder (after one,
``state.outside`` and :func:`~stellar_cal_ros.diagnosis.flexure.beyond` decide).
"""

from __future__ import annotations

import numpy as np

from stellar_cal_ros.diagnosis import flexure, stats
from stellar_cal_ros.diagnosis.noise_stars import CELL_GRID, detector_cells
from stellar_cal_ros.io.calibration import Calibration

#: what a refused candidate's reason calls each field and the fit beside it
NAMES = {
    "cells": ("the detector-cells-shaped remainder", "a per-cell offset field"),
    "magnitude": ("the magnitude-shaped remainder", "an offset linear in magnitude"),
    "gravity": ("the gravity-shaped remainder", "a mount flexure"),
}
#: the fields made of columns of the residual table (:func:`columns`); the gravity field is
#: the flexure probe's response (:mod:`~stellar_cal_ros.diagnosis.flexure`), one more run
FIELDS = ("cells", "magnitude")


def columns(sub: dict, kind: str, centre: tuple[float, float]) -> np.ndarray | None:
    """The field's displacement columns ``(n, 2, k)`` px per unit coefficient."""
    du = np.asarray(sub["u"], dtype=float) - centre[0]
    dv = np.asarray(sub["v"], dtype=float) - centre[1]
    n = len(du)
    if kind == "magnitude":
        m = np.asarray(sub["magnitude"], dtype=float)
        fin = np.isfinite(m)
        if fin.sum() < 20 or np.ptp(m[fin]) == 0:
            return None
        m = np.where(fin, m - np.median(m[fin]), 0.0)
        r = np.maximum(np.hypot(du, dv), 1e-9)
        x = np.zeros((n, 2, 3))
        x[:, 0, 0] = m
        x[:, 1, 1] = m
        x[:, 0, 2], x[:, 1, 2] = m * du / r, m * dv / r
        return x
    cell, _ = detector_cells(_uv(sub), centre)
    used = np.unique(cell)
    if len(used) < 2:
        return None
    x = np.zeros((n, 2, 2 * len(used)))
    for j, c in enumerate(used):
        on = cell == c
        x[on, 0, 2 * j] = 1.0
        x[on, 1, 2 * j + 1] = 1.0
    return x


#: the 'unexplained' line of each field (a field a candidate was refused beside)
REGRESSORS = {
    "cells": "the detector's cells (a per-cell offset field, outside the library)",
    "magnitude": "magnitude (an offset field along u, v and the radius, outside the library)",
    "gravity": flexure.REGRESSOR,
}


def findings(run, fraction: float, kinds, alpha: float, known: dict | None = None
             ) -> list[stats.RegressorFinding]:
    """The 'unexplained' lines of the fields ``kinds`` on ``run``, where significant.

    Bonferroni over the fields as :func:`significant`; the size is the fitted field's
    displacement (99th percentile over the window's stars, px).  ``known``: fits of
    ``run`` already made (the gravity field's needs a run: :func:`gravity_of`); a field
    of :data:`FIELDS` not in it is fitted here.
    """
    known = dict(known or {})
    got = {k: known[k] if k in known else field_fit(run.residuals, run.calibration,
                                                    fraction, k)
           for k in kinds if k in known or (k in FIELDS and _has_table(run))}
    out = []
    for kind, f in significant({k: got.get(k) for k in kinds}, alpha).items():
        out.append(stats.RegressorFinding(_regressor(kind, f), "u, v", f["t"],
                                          min(1.0, f["p_value"] * len(NAMES)), f["size_px"],
                                          detail={"field": kind, **f}))
    return out


def _has_table(run) -> bool:
    return run is not None and run.ok and run.residuals is not None


def _regressor(kind: str, f: dict) -> str:
    """The line's regressor; the gravity field's says the flexure that would leave it."""
    if kind != "gravity":
        return REGRESSORS[kind]
    return (f"{flexure.REGRESSOR[:-1]}: {f['arcsec_per_g']:.3g} +- "
            f"{f['sigma_arcsec_per_g']:.2g} arcsec per unit lateral gravity, outside the "
            "library)")


def field_fit(res, calibration: Calibration, fraction: float, kind: str
              ) -> dict[str, float] | None:
    """The innovations' fit by one field (:func:`columns`) in the evaluation window.

    The direction: the whitened least-squares combination of the columns over the accepted
    stars before the window; the window's test of that one pattern
    (:func:`~stellar_cal_ros.diagnosis.stats.whitened_fit`).  ``{t, p_value, chi2,
    chi2_capped, size_px}`` (``size_px``: 99th percentile of the fitted field's
    displacement over the window's stars), or ``None``.
    """
    if res is None or not len(res.get("t", ())):
        return None
    cam = calibration.camera
    centre = (cam.cx, cam.cy)
    acc = stats.accepted(res)
    inside = stats.evaluation_mask(res, fraction)
    before, window = acc & ~inside, acc & inside
    if before.sum() < 50 or window.sum() < 50:
        return None
    sb = {k: np.asarray(v)[before] for k, v in res.items()}
    xb = columns(sb, kind, centre)
    if xb is None:
        return None
    cov = {k: sb[k] for k in ("s_uu", "s_uv", "s_vv")}
    w_nu = stats.whitened(sb)
    w_x = np.stack([stats.whitened({"du": xb[:, 0, j], "dv": xb[:, 1, j], **cov})
                    for j in range(xb.shape[2])], 2)  # (n, 2, k)
    ok = np.all(np.isfinite(w_nu), 1) & np.all(np.isfinite(w_x), (1, 2))
    if ok.sum() < 20:
        return None
    a = w_x[ok].reshape(-1, xb.shape[2])
    coef = np.linalg.lstsq(a, w_nu[ok].ravel(), rcond=None)[0]
    if not np.any(coef):
        return None
    sw = {k: np.asarray(v)[window] for k, v in res.items()}
    if kind == "cells":
        pattern = _align_cells(sb, sw, centre, coef)
    else:
        xw = columns(sw, kind, centre)
        pattern = None if xw is None else xw @ coef
    if pattern is None:
        return None
    fit = stats.whitened_fit(sw, pattern)
    if fit is None:
        return None
    t, p, c, info = fit
    size = np.hypot(*(c * pattern).T)
    return {"t": t, "p_value": p, "chi2": c * c * info,
            "chi2_capped": stats.capped_gain(sw, pattern, c),
            "size_px": float(np.percentile(size, 99)) if len(size) else 0.0}


def _uv(sub: dict) -> np.ndarray:
    """``(n, 2)`` centroids (px) of a residual table's rows."""
    return np.stack([np.asarray(sub["u"], float), np.asarray(sub["v"], float)], 1)


def _align_cells(sb: dict, sw: dict, centre: tuple[float, float], coef: np.ndarray
                 ) -> np.ndarray | None:
    """The window's stars' offsets of the cell field fitted before it (``(n, 2)`` px).

    On the grid of the frames before the window (:func:`columns`' cells, their extent);
    the window's cells that those frames held no star of add nothing (coefficient 0).
    ``None`` when the window's stars lie in fewer than two cells or the field is 0 on them.
    """
    if len(np.unique(detector_cells(_uv(sw), centre)[0])) < 2:  # on the window's own grid
        return None
    before, ext = detector_cells(_uv(sb), centre)
    window, _ = detector_cells(_uv(sw), centre, ext)
    table = np.zeros((CELL_GRID * CELL_GRID, 2))
    used = np.unique(before)
    table[used, 0], table[used, 1] = coef[0::2], coef[1::2]
    out = table[window]
    return out if np.any(out) else None


def fits(res, calibration: Calibration, fraction: float) -> dict[str, dict | None]:
    """Every column field's fit (:func:`field_fit`) of a residual table (:data:`FIELDS`)."""
    return {kind: field_fit(res, calibration, fraction, kind) for kind in FIELDS}


def of_run(run, fraction: float) -> dict[str, dict | None]:
    """:func:`fits` of a :class:`~stellar_cal_ros.diagnosis.runstats.RunSummary`."""
    if not _has_table(run):
        return {}
    return fits(run.residuals, run.calibration, fraction)


def gravity_fit(res: dict, moved: dict | None, fraction: float) -> dict[str, float] | None:
    """The gravity field's fit: the flexure-shaped test of the innovations ``res``.

    :func:`~stellar_cal_ros.diagnosis.flexure.remainder_statistics` (the probe's response
    as the one pattern) given the model's run with the probe ``moved``; ``size_px`` its
    remainder's displacement (99th percentile, px) as the other fields'.  ``None`` where
    the test cannot be made.
    """
    return as_lead(None if moved is None else flexure.remainder_statistics(res, moved,
                                                                            fraction))


def as_lead(f: dict[str, float] | None) -> dict[str, float] | None:
    """A flexure-shaped test's result as the gravity field's fit (``size_px``: its size)."""
    return None if f is None else dict(f, size_px=f["change_px"])


def gravity_of(runs, run, prior: Calibration, effects: tuple[str, ...]
               ) -> dict[str, float] | None:
    """The gravity field's fit on the current model ``run`` (its residuals kept).

    The flexure-shaped test after an add
    (:func:`~stellar_cal_ros.diagnosis.flexure.after_add`: one run where the bag is, the
    model ``effects`` from ``prior`` with the probe) as a lead: the two are one test.
    """
    return as_lead(flexure.after_add(runs, run, prior, tuple(effects)))


def significant(found: dict[str, dict | None], alpha: float) -> dict[str, dict]:
    """The fields that are leads: significant at ``alpha`` (Bonferroni over the fields)."""
    return {k: f for k, f in found.items()
            if f is not None and f["p_value"] * len(NAMES) < alpha}


def candidate_on_bag(data, spec, prior: Calibration, effects: tuple[str, ...],
                     fraction: float, noise=None, classes: tuple[type, ...] = (),
                     gravity: bool = False) -> dict[str, dict | None]:
    """The rolling-shutter fit and every field's fit of a candidate model's run.

    For :meth:`~stellar_cal_ros.diagnosis.parallel.Runs.on_bag` (one run where the bag is;
    only the statistics travel): ``{"rolling": ..., "cells": ..., "magnitude": ...}``,
    with ``"gravity"`` (:func:`gravity_fit`: one more run, the model with the probe) when
    ``gravity``.
    """
    from stellar_cal_ros.diagnosis import rolling
    from stellar_cal_ros.diagnosis.runstats import evaluate, register_effect_classes

    register_effect_classes(classes)
    run = evaluate(data, spec, prior, effects, fraction, True, classes, candidate=True,
                   noise=noise)
    out = {"rolling": rolling.of_run(run, fraction)}
    out.update(of_run(run, fraction))
    if gravity and _has_table(run):
        out["gravity"] = gravity_fit(run.residuals, flexure.measure_on_bag(
            data, spec, prior, effects, fraction, noise, classes, True), fraction)
    return out


def stand_in(candidate, dispersion: float, with_c: dict | None, lead: dict, kind: str,
             alpha: float) -> dict | None:
    """Whether ``candidate`` stands in for the field ``kind`` fitted on the current model.

    :func:`~stellar_cal_ros.diagnosis.rolling.stand_in`'s rule with this field: the beyond
    result (``remainder``: :data:`NAMES`; ``lead``: ``kind``; ``lead_size_px``: the field's
    size on the current model) when refused, else ``None``.
    """
    from stellar_cal_ros.diagnosis import rolling

    b = rolling.stand_in(candidate, dispersion, with_c, lead, alpha, NAMES[kind])
    return None if b is None else dict(b, lead=kind, lead_size_px=lead["size_px"])
