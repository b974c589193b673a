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
field along magnitude (offsets piecewise linear in magnitude, knots at the stars' quartiles,
along u, v and the radius: :func:`columns`).

Each field has many columns.  A field is fixed on the detector (:func:`detector_grid`: the
bag's centroids, the same for every model compared).  The lead's test is one displacement
pattern: the columns' least-squares combination on the frames *before* the evaluation
window (the direction), tested and sized in the window (:func:`~stellar_cal_ros.diagnosis.
stats.whitened_fit`: the frame-robust t_ν of every 'unexplained' line).  A direction
chosen on the data it is tested on would make a χ²_k of a t; chosen on other frames it is a
fixed pattern for the window's test.  A field is a lead when that test is significant on the
current model (Bonferroni over the fields); a candidate is then added only if it explains
the data beyond the field, or the field has vanished beside it (the rolling shutter's rule,
:func:`~stellar_cal_ros.diagnosis.rolling.stand_in`; :func:`vanished`): a field of many
columns beside a library effect of few parameters is the larger model of a nested
comparison, gone once no longer significant beside the effect at the fields' level (a cells
lead at t 3.79 read 1.75 beside pixel_aspect injected at its MDB, unseen case
``twin_s07_aspect1`` s22, and refused it while the rule asked its size to have fallen too);
the gravity field, one pattern, also when its size along the current model's direction
(:func:`direction`, the same pattern on the candidate's rows) has not fallen.  "Beyond" is the
nested ratio: the candidate's Λ plus what the field removes of the capped χ² with the
candidate minus without it, each field fitted on the window itself, every column, per
quarter of its time (:func:`window_gain`, ``chi2_capped``: the direction's own noise and a
static field made the ratio's null far from χ²: unseen case ``quadrant`` 300 s seed 22
added the tilt at 26.5).  Nothing runs unless a candidate is significant alone; on a bag
where no field is a lead nothing changes.

A third field is a mount bending with gravity (unseen case ``sway_flex``: 10″/g on the
swaying base was named gyro_scale_factor −46, −43 ppm with nothing unexplained).  Its one
pattern is the flexure probe's response (:mod:`~stellar_cal_ros.diagnosis.flexure`, the
test made after an add, the same functions): one more run of the current model, with the
probe, and one of the candidate's, asked only for a candidate that may stand in for a
flexure (not a camera effect) and before any add found a remainder (after one,
``state.outside`` and :func:`~stellar_cal_ros.diagnosis.flexure.beyond` decide).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from stellar_cal_ros.core import distributions as dist
from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.diagnosis import flexure, noise_structure, stats
from stellar_cal_ros.diagnosis.noise_stars import CELL_GRID, detector_cells
from stellar_cal_ros.io.calibration import Calibration

#: what a refused candidate's reason calls each field and the fit beside it
NAMES = {
    "cells": ("the detector-cells-shaped remainder", "a per-cell offset field"),
    "magnitude": ("the magnitude-shaped remainder", "an offset piecewise linear in magnitude"),
    "gravity": ("the gravity-shaped remainder", "a mount flexure"),
    "temperature": ("the head-temperature-shaped remainder",
                    "a mount turning with the head temperature"),
}
#: the fields made of columns of the residual table (:func:`field_fit`); the gravity field is
#: the flexure probe's response (:mod:`~stellar_cal_ros.diagnosis.flexure`), one more run
FIELDS = ("cells", "magnitude")


#: the magnitude field's knots: these percentiles of the stars' magnitudes (one value a star)
MAGNITUDE_KNOTS = (25.0, 50.0, 75.0)


def magnitude_knots(res) -> np.ndarray:
    """The magnitude field's knots on a residual table: :data:`MAGNITUDE_KNOTS` of its stars.

    Every row (gated or not, every frame), one magnitude a star (its ``catalog_id``'s, where
    the table has it): the same for every model run on one bag, like
    :func:`detector_grid`'s frame.  The median is the middle knot (the field is 0 there).
    Empty without a finite magnitude.
    """
    m = np.asarray(res.get("magnitude", ()), dtype=float)
    ids = res.get("catalog_id")
    if ids is not None and len(ids) == len(m):
        _, first = np.unique(np.asarray(ids), return_index=True)
        m = m[first]
    m = m[np.isfinite(m)]
    return np.percentile(m, MAGNITUDE_KNOTS) if len(m) else np.zeros(0)


def columns(sub: dict, centre: tuple[float, float], knots: np.ndarray) -> np.ndarray | None:
    """The magnitude field's displacement columns ``(n, 2, 3 k)`` px per unit coefficient.

    Offsets piecewise linear in magnitude, along u, v and the radius from ``centre`` (the
    detector's, :func:`detector_grid`): the magnitude and a hinge ``max(knot − m, 0)`` at
    each of ``knots`` (:func:`magnitude_knots`, the stars' quartiles), each made 0 at the
    middle knot (the median star), so ``k`` = 4 functions of magnitude, 12 columns.  A
    straight line could not follow a pull that only the bright stars have (unseen case
    ``saturation``: 0 for magnitude ≥ 4, the 10 % brightest stars): what it missed was
    per star, and a per-cell field (81 stars on 36 cells) took it up as well as the line
    did (300 s seed 22: cells t 8.71, magnitude 8.41, each t 5.3 beyond the other).
    ``None`` without 20 finite magnitudes that vary.  (The cells field's columns, a
    per-cell offset along u and one along v, are solved cell by cell:
    :func:`_cell_offsets`; the one place that tells the two apart: :func:`_pattern`.)
    """
    du = np.asarray(sub["u"], dtype=float) - centre[0]
    dv = np.asarray(sub["v"], dtype=float) - centre[1]
    m = np.asarray(sub["magnitude"], dtype=float)
    fin = np.isfinite(m)
    if fin.sum() < 20 or np.ptp(m[fin]) == 0 or not len(knots):
        return None
    mid = float(np.median(knots))
    m = np.where(fin, m, mid)
    shapes = [m - mid] + [np.maximum(k - m, 0.0) - max(k - mid, 0.0) for k in knots]
    r = np.maximum(np.hypot(du, dv), 1e-9)
    x = np.zeros((len(du), 2, 3 * len(shapes)))
    for j, f in enumerate(shapes):
        x[:, 0, 3 * j] = f
        x[:, 1, 3 * j + 1] = f
        x[:, 0, 3 * j + 2], x[:, 1, 3 * j + 2] = f * du / r, f * dv / r
    return x


#: the 'unexplained' line of each field (a field a candidate was refused beside)
REGRESSORS = {
    "cells": "the detector's cells (a per-cell offset field, outside the library)",
    "magnitude": "magnitude (an offset field along u, v and the radius, outside the library)",
    "gravity": flexure.REGRESSOR,
    "temperature": "head temperature (the mount turning with it, outside the library)",
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
    got = {k: known[k] if k in known else field_fit(run.residuals, fraction, k)
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
    """The line's regressor; the gravity and temperature fields' say the turn leaving it."""
    if kind == "temperature":
        return (f"{REGRESSORS[kind][:-1]}: {f['arcsec_per_c']:.3g} +- "
                f"{f['sigma_arcsec_per_c']:.2g} arcsec per deg C, {f['turn_arcsec']:.3g} "
                f"arcsec = {f['turn_px']:.3g} px over the window's "
                f"{f['temperature_change_c']:.3g} deg C)")
    if kind != "gravity":
        return REGRESSORS[kind]
    return (f"{flexure.REGRESSOR[:-1]}: {f['arcsec_per_g']:.3g} +- "
            f"{f['sigma_arcsec_per_g']:.2g} arcsec per unit lateral gravity, outside the "
            "library)")


def field_fit(res, fraction: float, kind: str, along=None) -> dict[str, float] | None:
    """The innovations' fit by one field in the evaluation window.

    The field is fixed on the detector (:func:`detector_grid`: the centre and extent of the
    bag's centroids), not on a model's principal point, so that every model compared on a
    bag is given the same columns.  The lead's test: the whitened least-squares
    combination of the columns over the accepted stars before the window (the direction,
    :func:`direction`), tested in the window as one pattern (:func:`~stellar_cal_ros.
    diagnosis.stats.whitened_fit`): ``t``, ``p_value``, ``chi2`` (its ``c² info``) and
    ``size_px`` (99th percentile of the fitted pattern's displacement over the window's
    stars).  ``chi2_capped``, what the field removes of the window's NIS-capped χ² for a
    candidate's ratio beyond it (:func:`~stellar_cal_ros.diagnosis.flexure.beyond`), is
    the field fitted on the window itself, every column (``columns``: how many;
    :func:`window_gain`).  ``coef`` (:func:`~stellar_cal_ros.diagnosis.stats.pattern_size`:
    with its robust σ and ν) is the window's size along the direction ``along`` (another
    model's, :func:`direction`: a candidate's run is measured along the current model's
    pattern, on its own rows, so that the two sizes are of one pattern and comparable;
    ``None``: this fit's own).  ``None`` when no test.
    """
    got = _window_pattern(res, fraction, kind)
    if got is None:
        return None
    grid, _, sw, pattern = got
    # (with ν where a test can be made: the same t, p, c, info, and the size's own fit)
    fit = stats.whitened_fit(sw, pattern, dof=True) or stats.whitened_fit(sw, pattern)
    if fit is None:
        return None
    t, p, c, info = fit[:4]
    size = np.hypot(*(c * pattern).T)
    gain, k = window_gain(sw, kind, grid)
    if along is None:
        same, made = pattern, fit if len(fit) == 5 else None
    else:
        got = _displace(sw, kind, grid, along)
        same, made = None if got is None or not np.any(got[0]) else got[0], None
    return {"t": t, "p_value": p, "chi2": c * c * info, "chi2_capped": gain, "columns": k,
            "size_px": float(np.percentile(size, 99)) if len(size) else 0.0,
            **((None if same is None else stats.pattern_size(sw, same, made)) or {})}


def _window_pattern(res, fraction: float, kind: str):
    """The lead's one pattern: ``(grid, window, sw, pattern)``, or ``None``.

    The field ``kind`` fitted on the accepted stars before the evaluation window
    (:func:`direction`) as displacements ``pattern`` ``(n, 2)`` px of the window's accepted
    stars ``sw`` (``window``: their rows of ``res``), on :func:`detector_grid`'s ``grid``:
    what :func:`field_fit` tests and :func:`without` takes out.
    """
    if res is None or not len(res.get("t", ())):
        return None
    grid = detector_grid(res)
    acc = stats.accepted(res)
    inside = stats.evaluation_mask(res, fraction)
    before, window = acc & ~inside, acc & inside
    if grid is None or before.sum() < 50 or window.sum() < 50:
        return None
    sb = {k: np.asarray(v)[before] for k, v in res.items()}
    sw = {k: np.asarray(v)[window] for k, v in res.items()}
    got = _pattern(sb, kind, grid, sw)
    if got is None or not np.any(got[0]):
        return None
    return grid, window, sw, got[0]


def without(res, fraction: float, kind: str):
    """``res`` with the lead ``kind``'s fit taken out of the window's innovations.

    The lead's pattern (:func:`_window_pattern`: fitted before the window) times its size
    fitted in the window (:func:`~stellar_cal_ros.diagnosis.stats.whitened_fit`'s ``c``):
    the very fit the field's line tests and sizes (:func:`field_fit`), so that what is
    left is what that line does not explain.  Rows outside the window unchanged; ``None``
    when the field cannot be fitted.
    """
    got = _window_pattern(res, fraction, kind)
    fit = None if got is None else stats.whitened_fit(got[2], got[3])
    if fit is None:
        return None
    return _taken_out(res, got[1], fit[2] * got[3])


def _taken_out(res, window: np.ndarray, fitted: np.ndarray) -> dict:
    """``res`` with the displacements ``fitted`` ``(n, 2)`` px taken from its rows ``window``."""
    du = np.array(res["du"], dtype=float)
    dv = np.array(res["dv"], dtype=float)
    du[window] -= fitted[:, 0]
    dv[window] -= fitted[:, 1]
    return dict(res, du=du, dv=dv)


#: the cause an 'unexplained' line follows when a printed field's fit explains it
#: (:func:`fields_first`; ``printing.CAUSES`` words it)
CAUSES = {"cells": "detector's cells field", "magnitude": "magnitude field",
          "temperature": "mount turning with the head temperature",
          "zone": "radial step of the image scale",
          "rows": "smooth structure over the detector's rows (v)",
          "columns": "smooth structure over the detector's columns (u)"}
CELLS_CAUSE = CAUSES["cells"]
#: the regressors of the lines a field on the detector makes: a position's, straight or
#: periodic (:data:`~stellar_cal_ros.diagnosis.stats.RIPPLE`)
POSITIONS = ("u (column)", "v (row)", "radius")
#: the lines of the line tests each field's fit may explain (:func:`fields_first`): the
#: cells field's, those against a detector position: with a few stars a cell (81 stars on 36
#: cells on the PSCE sky, 72 columns) it takes up a per-star error too, a magnitude's
#: (unseen case ``saturation`` s22: the 'radial vs magnitude' line is gone beside it), and
#: such a line is not the field's doing; the magnitude field's (12 columns, each a function of
#: the star's magnitude alone), any line: what it takes is what varies with magnitude
#: (``saturation`` s22's 'radial residual vs gravity_x_st' t 4.8: the stars in view change
#: with the attitude)
#: the radial step's (a line of :func:`~stellar_cal_ros.diagnosis.stats.shaped_tests`,
#: :data:`~stellar_cal_ros.diagnosis.stats.ZONE`): the repeat of a star's residual (a star
#: keeps its radius along its track: unseen case ``lens_zone`` s21, 'residual repeating vs
#: catalogue star' t 11.8 ranked before the step's line t 11.2), a line against a detector
#: position, straight or a ripple (a step on the detector, as the cells field's), and
#: another radius's step
#: a smooth structure over the detector's rows or columns' (:data:`POSITION_LEADS`): the
#: repeat of a star's residual
ECHOES = {"cells": POSITIONS, "magnitude": None, "temperature": None,
          "zone": ("catalogue star", *POSITIONS), "rows": ("catalogue star",),
          "columns": ("catalogue star",)}
#: the lines that lead a smooth structure over one detector axis (:func:`position_lead`):
#: a residual (u or v) against the detector's column or row, straight or a ripple, not a
#: fixed pattern's bands (their pixels' means are taken out of the lines already:
#: :func:`~stellar_cal_ros.diagnosis.noise.without_patterns`).  A bias that fades over a
#: few dozen rows from one edge (unseen case ``stray_light``, 0.15 exp(−v / 40 px) px
#: toward the first rows) is finer than the detector cells the per-star repeat test takes
#: out first, so the stars that dwell near the edge repeat: s21 'residual repeating vs
#: catalogue star' t 8.3 (χ² 328 / 156) ranked before the 'v (row)' lines (t −8.0, 7.6);
#: without a smooth function of the row (:func:`position_without`) 148 / 156, where a
#: catalogue error's repeat stays (``catalogue`` s21: 1563 → 1284; ``lateral_colour`` s21:
#: 418 → 469)
POSITION_LEADS = {"u (column)": "columns", "v (row)": "rows"}


def echoes(kind: str, f) -> bool:
    """Whether the line ``f`` may be field ``kind``'s echo (:data:`ECHOES`)."""
    family = ECHOES[kind]
    if kind == "zone" and stats.zone_radius(f) is not None:
        return True
    return family is None or f.regressor.split(f" ({stats.RIPPLE} ")[0] in family


def position_lead(f) -> str | None:
    """``"rows"`` or ``"columns"`` where the line ``f`` may lead a smooth structure over them.

    :data:`POSITION_LEADS`: a u or v residual against the detector's row (column),
    straight or a ripple over it; ``None`` for any other line.
    """
    name = f.regressor
    if f.component not in ("u", "v") or " (fixed pattern" in name:
        return None
    return POSITION_LEADS.get(name.split(f" ({stats.RIPPLE} ")[0])


def position_without(res, fraction: float, kind: str, camera):
    """``res`` with a smooth function of the detector's rows (``kind`` ``"rows"``) taken out.

    On the window's accepted stars, each residual axis (u, v) less its least-squares fit
    by the ripple lines' own functions of the predicted row (``"columns"``: column): a
    straight line and the sines and cosines of :data:`~stellar_cal_ros.diagnosis.stats.
    POSITION_PERIODS` periods over the detector's height (width; without it twice the
    centre) (:func:`~stellar_cal_ros.diagnosis.noise_structure.less_smooth`).  Rows outside
    the window unchanged; ``None`` with fewer than 50 rows.  What it leaves of a per-star
    repeat is what no smooth structure over that axis explains (:data:`POSITION_LEADS`).
    """
    if res is None or not len(res.get("t", ())):
        return None
    window = stats.accepted(res) & stats.evaluation_mask(res, fraction)
    if window.sum() < 50:
        return None
    axis = "v" if kind == "rows" else "u"
    extent = (camera.height if axis == "v" else camera.width) or \
        2.0 * (camera.cy if axis == "v" else camera.cx)
    sw = {k: np.asarray(v)[window] for k, v in res.items()}
    at = stats.predicted_position(sw, axis)
    fitted = np.stack([sw[k] - noise_structure.less_smooth(sw[k], at, extent,
                                                           stats.POSITION_PERIODS)
                       for k in ("du", "dv")], 1)
    return _taken_out(res, window, np.nan_to_num(fitted))


def on_the_detector(f) -> bool:
    """Whether the line ``f`` is against a detector position (straight, or a ripple over it)."""
    return echoes("cells", f)


def _field(f) -> str | None:
    """The field of :data:`FIELDS` (or the temperature field) whose line ``f`` is, or ``None``."""
    kind = (getattr(f, "detail", None) or {}).get("field")
    return kind if kind in FIELDS or kind == "temperature" else None


#: :func:`zone_without`'s radii: this many, evenly from the 5th to the 95th percentile of the
#: window's stars' distances from the centre (~5 px apart on the PSCE detector)
ZONE_RADII = 91


def zone_without(res, fraction: float, centre: tuple[float, float]):
    """``res`` with a radial step fitted out of the window, and the step's radius (px).

    The step less the camera's radial polynomial (:func:`~stellar_cal_ros.diagnosis.stats.
    zone_step`, on the window's accepted stars' predicted centroids: the rows its line
    test takes) at the radius from ``centre`` that takes most of their whitened χ² (one
    of :data:`ZONE_RADII`: the line tests' quartiles miss the step's radius, and a step
    fitted at a quartile leaves a step's structure that the other lines read, unseen case
    ``lens_zone`` s21: at 424 px, for 400, the 508 px step line and the catalogue-star
    repeat stay), times its size fitted there (:func:`~stellar_cal_ros.diagnosis.stats.
    whitened_fit`'s ``c``); rows outside the window unchanged.  The step is of the image
    scale (:func:`~stellar_cal_ros.diagnosis.stats.zone_step`'s ``scale``: a unit step left
    the scale's growth beyond the radius, which the 338 px step line of unseen case
    ``lens_zone`` s21 read).  Returns ``(residuals, radius, c)``: ``c`` the step's fitted
    size at the radius (px); ``(None, nan, nan)`` when it cannot be fitted.  The radius is
    an estimate for the removal, not a test: the lines re-tested on what it leaves decide.
    """
    if res is None or not len(res.get("t", ())):
        return None, math.nan, math.nan
    window = stats.accepted(res) & stats.evaluation_mask(res, fraction)
    if window.sum() < 50:
        return None, math.nan, math.nan
    sw = {k: np.asarray(v)[window] for k, v in res.items()}
    r_vec = np.stack([stats.predicted_position(sw, "u") - centre[0],
                      stats.predicted_position(sw, "v") - centre[1]], 1)
    r = np.hypot(r_vec[:, 0], r_vec[:, 1])
    if not np.isfinite(r).sum() >= 50:
        return None, math.nan, math.nan
    cov = {k: sw[k] for k in ("s_uu", "s_uv", "s_vv")}
    w_nu = stats.whitened(sw)
    best, radius, pattern = -1.0, math.nan, None
    for q in np.linspace(*np.nanpercentile(r, [5.0, 95.0]), ZONE_RADII):
        x = np.nan_to_num(stats.zone_step(r_vec, q, scale=True))
        w_x = stats.whitened({"du": x[:, 0], "dv": x[:, 1], **cov})
        ok = stats.finite_rows(w_x) & stats.finite_rows(w_nu)
        info = float(np.sum(w_x[ok] ** 2))
        gain = float(np.sum(w_x[ok] * w_nu[ok])) ** 2 / info if info > 0 else -1.0
        if gain > best:
            best, radius, pattern = gain, float(q), x
    fit = None if pattern is None else stats.whitened_fit(sw, pattern)
    if fit is None:
        return None, math.nan, math.nan
    return _taken_out(res, window, fit[2] * pattern), radius, float(fit[2])


def fields_first(found: list, run, fraction: float, tests, alpha: float, keep=frozenset(),
                 calibration: Calibration | None = None, taken=frozenset(), runs=None
                 ) -> tuple[list, dict[int, str]]:
    """``found`` with the lines a printed field's line explains last, as its consequence.

    A printed field (the line of one of :data:`FIELDS`: a candidate was refused beside it)
    explains the lines the residuals without its fit (:func:`without`) no longer give:

    - lines of the line tests ``tests(residuals, calibration, fraction)`` (:func:`~stellar_
      cal_ros.diagnosis.output.line_tests`; ``calibration``: the one ``found`` was tested
      with, default ``run``'s) that may be the field's (:func:`echoes`) and that those
      tests no longer find (:func:`~stellar_cal_ros.diagnosis.rolling.gone`; ``keep``:
      ids that stay);
    - the line of a weaker field (ranked after it in ``found``) that is no longer
      significant at ``alpha`` beside it (:func:`field_fit` of the residuals without it,
      :func:`significant`), whichever field is first.

    A step of the centroids on one detector quadrant (unseen case ``quadrant``, 0.05 px,
    300 s seed 22) is the cells field's line (t 27) and, ranked as leads of their own, its
    echoes on the detector's positions: a ripple one period across the rows (``u residual
    vs v (row) (periodic 1024 px, sin)`` t 17, the step's fundamental) and straight lines
    (``v residual vs u (column)`` t −14).  A saturation (unseen case ``saturation`` 300 s
    s22: bright stars pulled toward the centre) is the magnitude field's line (t 13.5) and
    the cells field's (t 8.7), whose per-cell offsets took the pull's per-star part: beside
    the magnitude field the cells field keeps t 2.4.  The fields are taken strongest first;
    a line follows the first that explains it (a field that follows another still has its
    own echoes).  Returns the lines and ``{index: cause}``
    (:data:`CAUSES`) of those that follow: the others keep their order, those that follow
    come last, in theirs; unchanged without a field's line or a residual table.  ``taken``:
    ids of lines that already follow another cause (they stay where they are).

    The temperature field's line (:func:`temperature_fit`; a mount turning with the head
    temperature) explains the lines gone from the residuals without its fit
    (:func:`temperature_without`: its probes run again on ``run``'s model with ``runs``,
    three runs, only where the line is printed and others rank with it): any line may be
    its echo (a turn of the whole tracker that changes over the run moves every star;
    unseen case ``thermal_mount`` s21: the clock line 'dt from −1.03 ms to 0.40 ms', t 4.9,
    ranked before it).

    The strongest radial step's line (:data:`~stellar_cal_ros.diagnosis.stats.ZONE`, a lens
    zone; the others are the same step's lines at other radii) explains the lines gone from
    the residuals without a step fitted at the radius that fits best (:func:`zone_without`;
    the lines' radii are the stars' quartiles): the repeat of a star's residual, a line
    against a detector position, another radius's step (:data:`ECHOES`; unseen case ``lens_zone``
    s21: 'residual repeating vs catalogue star' t 11.8 ranked before the step's line t 11.2,
    the 508 px step line t −10.6 after it).

    The strongest line against a detector row or column (:func:`position_lead`) explains
    the repeat of a star's residual gone from the residuals without a smooth function of
    that position (:func:`position_without`; unseen case ``stray_light`` s21: the repeat
    t 8.3 ranked before the 'v (row)' lines, a bias that fades over 40 px from the first
    rows, finer than the detector cells).
    """
    from stellar_cal_ros.diagnosis import rolling

    if not _has_table(run):
        return found, {}
    cause: dict[int, str] = {}
    fitted: dict[int, dict] = {}  # (the step's fit, for its line: ``detail``)
    cal = calibration or run.calibration
    step = next((f for f in found if stats.zone_radius(f) is not None), None)
    position = next((f for f in found if position_lead(f)), None)
    for i, lead in enumerate(found):
        kind = "zone" if lead is step else position_lead(lead) if lead is position \
            else _field(lead)
        if kind is None or id(lead) in taken:  # (one that follows a field still has echoes)
            continue
        lines = [f for j, f in enumerate(found) if j != i and id(f) not in cause
                 and id(f) not in taken
                 and (j > i if _field(f) else echoes(kind, f))]
        if not lines:
            continue
        if kind in FIELDS:
            less = without(run.residuals, fraction, kind)
        elif kind in ("rows", "columns"):
            less = position_without(run.residuals, fraction, kind, cal.camera)
        elif kind == "zone":
            less, radius, size = zone_without(run.residuals, fraction,
                                              (cal.camera.cx, cal.camera.cy))
            if less is not None:  # (the step line is printed at the fitted radius too)
                fitted[id(lead)] = {"cause": CAUSES["zone"], "radius_px": radius,
                                    "step_px": size, "scale_ppm": 1e6 * size / radius}
        else:  # the temperature field's pattern: its probes run again (where ``runs``)
            less = None if runs is None else temperature_without(runs, run)
        if less is None:
            continue
        left = None
        for f in lines:
            other = _field(f)
            if other is not None:  # (one that cannot be fitted beside it stays)
                fit = field_fit(less, fraction, other) if other in FIELDS else None
                gone = fit is not None and not significant({other: fit}, alpha)
            else:
                if left is None:  # (the line tests once a field, only where asked)
                    left = {rolling.line_key(g) for g in tests(less, cal, fraction)}
                gone = rolling.gone(f, left, keep | taken)
            if gone:
                cause[id(f)] = CAUSES[kind]
    if not cause:
        return found, {}
    out = [f for f in found if id(f) not in cause] + [f for f in found if id(f) in cause]
    follows = {i: cause[id(f)] for i, f in enumerate(out) if id(f) in cause}
    return [dataclasses.replace(f, detail=fitted[id(f)]) if id(f) in fitted else f
            for f in out], follows


def direction(res, fraction: float, kind: str):
    """The field's direction fitted on ``res``'s accepted stars before the window.

    The cells field's table of offsets (:func:`_cell_offsets`) or the magnitude field's
    column coefficients (:func:`_direction`); what :func:`field_fit` tests in the window,
    and what a candidate's fit is measured along (its ``along``).  ``None`` when it cannot
    be fitted.
    """
    if res is None or not len(res.get("t", ())):
        return None
    grid = detector_grid(res)
    before = stats.accepted(res) & ~stats.evaluation_mask(res, fraction)
    if grid is None or before.sum() < 50:
        return None
    return _direction({k: np.asarray(v)[before] for k, v in res.items()}, kind, grid)


def detector_grid(res) -> tuple[tuple[float, float], np.ndarray, np.ndarray] | None:
    """The fields' frame: the centre (px) and extent of the centroids, the magnitude knots.

    Every row (gated or not, every frame): the same for every model run on one bag.  The
    midpoint of the centroids' range and that range + 1 px, so that the grid of
    :func:`~stellar_cal_ros.diagnosis.noise_stars.detector_cells` spans the detector's
    stars.  (On the model's estimated principal point a tilt's run moved the grid by 20-40
    px from the baseline's, and 26-29 % of a 150 s quadrant bag's window stars changed
    cell between the two models.)  The third item: the magnitude field's knots
    (:func:`magnitude_knots`).  ``None`` without a finite centroid.
    """
    uv = _uv(res)
    uv = uv[stats.finite_rows(uv)]
    if not len(uv):
        return None
    lo, hi = uv.min(0), uv.max(0)
    return ((float((lo[0] + hi[0]) / 2), float((lo[1] + hi[1]) / 2)), hi - lo + 1.0,
            magnitude_knots(res))


def _cells(sub: dict, grid) -> np.ndarray:
    return detector_cells(_uv(sub), *grid[:2])[0]


#: the window's parts (equal spans of time) each given its own field for the nuisance gain
#: (:func:`window_gain`)
WINDOW_PARTS = 4


def window_gain(sw: dict, kind: str, grid) -> tuple[float, int]:
    """What the field fitted on the window's stars ``sw`` removes of their capped χ².

    Every column fitted (whitened least squares on the detector's ``grid``,
    :func:`detector_grid`), in each of :data:`WINDOW_PARTS` equal spans of the window's
    time on its own; the gain with each star's NIS capped (:func:`~stellar_cal_ros.
    diagnosis.stats.capped_gain` along the fitted displacement), and the number of
    columns.  Fitted on the sample it removes, the same columns on the same stars for a
    model with a candidate and without it, so that the difference of the two gains is the
    nested ratio's: what each takes of the noise (~``columns``) is the same noise's.

    Why not the lead's direction (fitted before the window): it carries noise of its own
    (72 cell coefficients on the frames before the window) that does not cancel between
    the two models (unseen case ``quadrant`` 300 s seed 22: image_plane_tilt's ratio
    beyond it 26.5 for 2 dof, added; −37.9 on the same bag with noise-free centroids).  Why
    the parts: a step a field fits in the filter, the run takes up in part into its
    camera states and keeps doing so through the window, so the cells' offsets drift;
    a candidate with states of its own follows part of the drift that one static field
    cannot (noise-free centroids, 300 s seeds 21 / 22: the tilt's ratio 9.5 / 7.1
    beyond one field, −5.3 / −8.6 beyond halves, −7.0 / −8.6 beyond quarters).
    ``(0, 0)`` when the field cannot be fitted.
    """
    t = np.asarray(sw["t"], dtype=float)
    if not len(t):
        return 0.0, 0
    edges = np.linspace(t.min(), t.max(), WINDOW_PARTS + 1)[1:-1]
    part = np.searchsorted(edges, t, side="right")
    own, k = np.zeros((len(t), 2)), 0
    for j in range(WINDOW_PARTS):
        on = part == j
        got = _pattern({key: np.asarray(v)[on] for key, v in sw.items()}, kind, grid)
        if got is not None:
            own[on], k = got[0], k + got[1]
    if not np.any(own):
        return 0.0, 0
    return stats.capped_gain(sw, own, 1.0), k


def _pattern(fit: dict, kind: str, grid, on: dict | None = None
             ) -> tuple[np.ndarray, int] | None:
    """The field ``kind`` fitted to the innovations of ``fit``, as displacements of ``on``.

    ``(pattern, k)``: the fitted field's displacement ``(n, 2)`` px on the stars of ``on``
    (default: ``fit``'s own) and its columns there (2 per cell holding a star, or the
    magnitude field's 3): :func:`_displace` of :func:`_direction`.  ``None`` when the field
    cannot be fitted, or ``on`` holds no two cells or no magnitude columns.
    """
    return _displace(fit if on is None else on, kind, grid, _direction(fit, kind, grid))


def _direction(fit: dict, kind: str, grid):
    """The field ``kind`` fitted to the innovations of ``fit`` (its direction).

    The one place that tells the fields apart: the cells field's table of offsets
    (:func:`_cell_offsets`) or the magnitude field's :func:`columns`' coefficients
    (:func:`_lstsq`), on :func:`detector_grid`'s ``grid``; ``None`` when it cannot be
    fitted.
    """
    if kind == "cells":
        return _cell_offsets(fit, _cells(fit, grid))
    if kind != "magnitude":
        raise ValueError(f"no {kind!r} field of the residual table's columns")
    x = columns(fit, grid[0], grid[2])
    return None if x is None else _lstsq(fit, x)


def _displace(on: dict, kind: str, grid, d) -> tuple[np.ndarray, int] | None:
    """The direction ``d`` (:func:`_direction`) as displacements ``(n, 2)`` of ``on``.

    With its columns there; ``None`` without ``d``, two cells or magnitude columns.
    """
    if d is None:
        return None
    if kind == "cells":
        cell = _cells(on, grid)
        cells = len(np.unique(cell))
        return None if cells < 2 else (d[cell], 2 * cells)
    x = columns(on, grid[0], grid[2])
    return None if x is None else (x @ d, x.shape[2])


def _lstsq(sub: dict, x: np.ndarray) -> np.ndarray | None:
    """The columns ``x`` ``(n, 2, k)`` fitted to the innovations, whitened; ``None`` if 0."""
    cov = {k: sub[k] for k in ("s_uu", "s_uv", "s_vv")}
    w_nu = stats.whitened(sub)
    w_x = np.stack([stats.whitened({"du": x[:, 0, j], "dv": x[:, 1, j], **cov})
                    for j in range(x.shape[2])], 2)  # (n, 2, k)
    ok = stats.finite_rows(w_nu) & np.all(np.isfinite(w_x), (1, 2))
    if ok.sum() < 20:
        return None
    coef = np.linalg.lstsq(w_x[ok].reshape(-1, x.shape[2]), w_nu[ok].ravel(), rcond=None)[0]
    return coef if np.any(coef) else None


def _uv(sub: dict) -> np.ndarray:
    """``(n, 2)`` centroids (px) of a residual table's rows."""
    return np.stack([np.asarray(sub["u"], float), np.asarray(sub["v"], float)], 1)


def _cell_offsets(sub: dict, cell: np.ndarray) -> np.ndarray | None:
    """Each cell's offset (u, v) fitted to the innovations of ``sub`` (``(CELL_GRID², 2)`` px).

    The whitened least squares of the cells field's columns (an offset along u and one along
    v per cell of :func:`~stellar_cal_ros.diagnosis.noise_stars.detector_cells`) solved
    cell by cell: the normal equations are block-diagonal, ``Σ S⁻¹`` and ``Σ S⁻¹ ν`` over
    each cell's stars (``S`` each star's innovation covariance).  0 where a cell holds no
    star; ``None`` with fewer than 20 stars or two cells, or an offset field of 0.
    """
    a, b, d = (np.asarray(sub[k], dtype=float) for k in ("s_uu", "s_uv", "s_vv"))
    du, dv = np.asarray(sub["du"], dtype=float), np.asarray(sub["dv"], dtype=float)
    det = a * d - b * b
    ok = np.isfinite(du) & np.isfinite(dv) & np.isfinite(det) & (det > 0) & (a > 0)
    if ok.sum() < 20 or len(np.unique(cell)) < 2:
        return None
    cell, a, b, d, det, du, dv = (x[ok] for x in (cell, a, b, d, det, du, dv))
    m = CELL_GRID * CELL_GRID

    def total(x):
        return np.bincount(cell, x, minlength=m)

    # S⁻¹ = [[d, −b], [−b, a]] / det summed per cell, and S⁻¹ ν
    auu, auv, avv = total(d / det), total(-b / det), total(a / det)
    ru, rv = total((d * du - b * dv) / det), total((a * dv - b * du) / det)
    n = auu * avv - auv * auv
    has = n > 0
    table = np.zeros((m, 2))
    table[has, 0] = (avv * ru - auv * rv)[has] / n[has]
    table[has, 1] = (auu * rv - auv * ru)[has] / n[has]
    return table if np.any(table) else None


def fits(res, fraction: float, along: dict | None = None) -> dict[str, dict | None]:
    """Every column field's fit (:func:`field_fit`) of a residual table (:data:`FIELDS`).

    ``along``: each field's direction to measure its size along (:func:`direction`).
    """
    along = along or {}
    return {kind: field_fit(res, fraction, kind, along.get(kind)) for kind in FIELDS}


def of_run(run, fraction: float, along: dict | None = None) -> dict[str, dict | None]:
    """:func:`fits` of a :class:`~stellar_cal_ros.diagnosis.runstats.RunSummary`."""
    if not _has_table(run):
        return {}
    return fits(run.residuals, fraction, along)


def directions(run, fraction: float, kinds) -> dict:
    """The current model's :func:`direction` of each field of ``kinds`` in :data:`FIELDS`."""
    if not _has_table(run):
        return {}
    return {k: direction(run.residuals, fraction, k) for k in kinds if k in FIELDS}


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


#: a plausible mount coefficient (″/°C): the turn with the head temperature the
#: temperature field must be able to see (its MDB at most this) to be worth running.  Liu
#: et al., "Method and Implementation of Improving the Pointing Accuracy of an Optical
#: Remote Sensor Using a Star Sensor", Traitement du Signal 36(4) 311-317 (2019): a star
#: sensor bracket designed and thermally controlled for it turns < 5″ over its ±1 °C,
#: 2.5″/°C; a mount not designed for it turns more (unseen case ``thermal_mount``: 2″/°C)
PLAUSIBLE_MOUNT_ARCSEC_PER_C = 2.5


#: the draws (turn axis, direction fitted before the window) of :func:`temperature_mdb`'s
#: power, and its seed (fixed: the MDB is a number of the bag, the same on every call)
MDB_DRAWS = 2000
MDB_SEED = 20261129


def temperature_mdb(res, moved: list[dict], fraction: float, fit: dict, alpha: float
                    ) -> float:
    """The temperature field's MDB (″/°C): the turn its test sees with power 80 %.

    The field's test is made in two steps (:func:`temperature_fit`): the turn's axis fitted
    before the evaluation window, the window's innovations then fitted along it; a small
    turn's axis is mostly noise, and the window's test along a wrong axis sees little of
    it (the window's σ alone, ``σ δ`` as :func:`~stellar_cal_ros.diagnosis.flexure.hiding`
    says for the gravity field, was seen in 1 bag of 8 at that size, doc/benchmarks.md).
    So its power at a rate ``r`` about an axis ``e`` is computed from the probes' whitened
    responses ``X_b`` before the window and ``X_w`` in it (the filter is linear at these
    sizes): the axis fitted ``â ~ N(r e, k² (X_bᵀX_b)⁻¹)``, the window's t along it
    ``âᵀ I_w r e / (k √(âᵀ I_w â))`` (``I_w = X_wᵀX_w``, ``X_w``'s columns centred as the
    t's slope is: 7 of 12 injections at the MDB seen without, 10 of 12 with) referred to
    t_ν two-sided at the
    level that makes it a lead (``α`` over the fields, :func:`significant`; ν the fit's),
    ``k`` the fit's frame-robust σ over its whitened one (at least 1), averaged over
    :data:`MDB_DRAWS` draws of ``â`` and of ``e`` uniform over the directions (a mount
    turning about any axis); the MDB is the ``r`` where it reaches
    :data:`~stellar_cal_ros.diagnosis.reliability.POWER`.  NaN where it cannot be made.
    """
    from stellar_cal_ros.diagnosis.reliability import POWER

    S, ok = _responses(res, moved)
    inside = stats.evaluation_mask(res, fraction)
    a = np.asarray(fit["direction"], dtype=float)
    (Xb, kb), (Xw, k) = (_whitened_columns({c: np.asarray(v)[m] for c, v in res.items()},
                                           S[m], a, centred)
                         for m, centred in ((ok & ~inside, False), (ok & inside, True)))
    Ib, Iw = Xb.T @ Xb, Xw.T @ Xw
    nu = fit.get("coef_nu")
    if not (nu and k and kb) or np.linalg.matrix_rank(Ib) < 3:
        return math.nan
    rng = np.random.default_rng(MDB_SEED)
    e = rng.standard_normal((MDB_DRAWS, 3))
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    z = rng.standard_normal((MDB_DRAWS, 3)) @ np.linalg.cholesky(kb * kb * np.linalg.inv(Ib)).T
    crit = float(dist.t.isf(alpha / len(NAMES) / 2.0, nu))

    def power(r: float) -> float:
        a = r * e + z
        m = np.sum(a * (r * e @ Iw), 1) / (k * np.sqrt(np.sum(a * (a @ Iw), 1)))
        return float(np.mean(dist.nct.sf(crit, nu, m)
                             + np.nan_to_num(dist.nct.sf(crit, nu, -m))))

    lo, hi = 0.0, float(np.sqrt(np.trace(k * k * np.linalg.inv(Iw))))
    while power(hi) < POWER:
        lo, hi = hi, 2.0 * hi
        if hi > 1e6:
            return math.inf
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if power(mid) < POWER else (lo, mid)
        if hi - lo < 1e-3 * hi:
            break
    return float(hi)


def _whitened_columns(sub: dict, x: np.ndarray, a: np.ndarray, centred: bool = False
                      ) -> tuple[np.ndarray, float | None]:
    """The columns ``x`` ``(n, 2, k)`` whitened by ``sub``'s innovation covariance, ``(m, k)``.

    The rows where every column and the innovations are finite, as :func:`_lstsq` fits
    (``centred``: each column less its mean, as the window's t is a slope with an
    intercept, :func:`~stellar_cal_ros.diagnosis.stats.frame_robust_t`: a turn's mean
    shift over the window's stars is not its evidence); with the frame-robust σ of the
    pattern ``x a``'s fit over its whitened ``1/√info``
    (:func:`~stellar_cal_ros.diagnosis.stats.pattern_size`, at least 1; ``None`` where no
    test can be made): how much more the stars of a frame share than the whitening says.
    """
    cov = {k: sub[k] for k in ("s_uu", "s_uv", "s_vv")}
    w_x = np.stack([stats.whitened({"du": x[:, 0, j], "dv": x[:, 1, j], **cov})
                    for j in range(x.shape[2])], 2)
    ok = stats.finite_rows(stats.whitened(sub)) & np.all(np.isfinite(w_x), (1, 2))
    cols = w_x[ok].reshape(-1, x.shape[2])
    cols = cols - cols.mean(axis=0) if centred else cols
    info = float(np.sum((cols @ a) ** 2))
    sized = stats.pattern_size(sub, x @ a) if info > 0 else None
    return cols, (None if sized is None else max(1.0, sized["coef_sigma"] * math.sqrt(info)))


def temperature_bound(res, fraction: float, alpha: float) -> dict[str, float] | None:
    """What the temperature field could see at best, before any run: ``{change_c, mdb}``.

    ``change_c`` the head temperature's range over the evaluation window (°C); ``mdb`` a
    lower bound of the field's MDB (″/°C): a turn ``(T − T̄) e`` about the tracker axis
    ``e`` the window's stars see best (:func:`~stellar_cal_ros.diagnosis.stats.
    attitude_columns`), whitened by the innovations' covariance, the stars independent and
    nothing of it taken up by the model's states (a filter takes some up: the field's own
    MDB, from its probes, is 3-7x this on the 300 s bags measured, doc/benchmarks.md), at
    the field's level and power for the normal (:func:`temperature_mdb`).  ``None``
    without a finite head temperature in the window; ``mdb`` inf where it does not change.
    """
    from stellar_cal_ros.diagnosis.reliability import delta_t

    if res is None or "head_temperature" not in res or not len(res["head_temperature"]):
        return None
    temp = np.asarray(res["head_temperature"], dtype=float)
    w = stats.evaluation_mask(res, fraction) & stats.accepted(res) & np.isfinite(temp)
    if w.sum() < 2:
        return None
    sub = {k: np.asarray(v)[w] for k, v in res.items()}
    g = temp[w] - float(np.mean(temp[w]))
    A = stats.attitude_columns(sub, *_focal(sub)) * ARCSEC  # px per ″
    cols = [stats.whitened({"du": A[:, 0, j] * g, "dv": A[:, 1, j] * g, "s_uu": sub["s_uu"],
                            "s_uv": sub["s_uv"], "s_vv": sub["s_vv"]}) for j in range(3)]
    ok = np.all([stats.finite_rows(c) for c in cols], axis=0)
    X = np.stack([c[ok].ravel() for c in cols], axis=1)
    top = float(np.linalg.eigvalsh(X.T @ X)[-1]) if ok.any() else 0.0
    mdb = delta_t(alpha / len(NAMES), 1e4) / np.sqrt(top) if top > 0 else math.inf
    return {"change_c": float(np.ptp(temp[w])), "mdb": float(mdb)}


def not_testable(change_c: float, mdb: float, bound: bool) -> str:
    """The line said where the temperature field is not worth running (its MDB too large)."""
    what = ("even a model that takes none of the turn up would see at best" if bound else
            "its field would see")
    axis = "about the axis seen best" if bound else "about an axis at random"
    return (f"a mount turning with the head temperature is not testable: temperature "
            f"changed {change_c:.2g} deg C over the window ({what} {mdb:.3g} arcsec per deg C "
            f"with power 80 %, a turn {axis}, above a plausible mount's "
            f"{PLAUSIBLE_MOUNT_ARCSEC_PER_C:g})")


def temperature_probes(runs, prior: Calibration, effects: tuple[str, ...]):
    """The model's runs with a turn with the head temperature about each tracker axis.

    :func:`~stellar_cal_ros.diagnosis.flexure.measure_on_bag` with ``axis`` 0, 1, 2 (three
    runs where the bag is, started together on a cluster); ``None`` when any failed.
    """
    args = (runs.spec, prior, tuple(effects), runs.fraction, runs.noise, runs.classes)
    got = [runs.later(flexure.measure_on_bag, *args, False, axis) for axis in range(3)]
    moved = [g() for g in got]
    return None if any(m is None for m in moved) else moved


def _responses(res, moved: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """Each row's innovation response to the probes ``moved`` ``(n, 2, k)`` px per ″/°C.

    The rows of ``res`` that are the same star of the same frame in every probe run and
    accepted in all (``ok``, ``(n,)``); the response of the others NaN.
    """
    k0 = flexure.row_key(res)
    ok = stats.accepted(res).copy()
    S = np.full((len(k0), 2, len(moved)), np.nan)
    per = flexure.PROBE / ARCSEC
    for j, m in enumerate(moved):
        _, i0, im = np.intersect1d(k0, flexure.row_key(m), return_indices=True)
        S[i0, 0, j] = (np.asarray(m["du"])[im] - np.asarray(res["du"])[i0]) / per
        S[i0, 1, j] = (np.asarray(m["dv"])[im] - np.asarray(res["dv"])[i0]) / per
        hit = np.zeros(len(k0), dtype=bool)
        hit[i0[stats.accepted({"gated": np.asarray(m["gated"])[im]})]] = True
        ok &= hit
    return S, ok & np.all(np.isfinite(S), (1, 2))


def _temperature_pattern(res, moved: list[dict] | None, fraction: float):
    """The temperature field's one pattern: ``(window, sw, Sw, a, pattern)``, or ``None``.

    The probes' responses (:func:`_responses`) fitted on the accepted stars before the
    evaluation window (``a``: the turn's axis, ″/°C a unit), as displacements ``pattern``
    ``(n, 2)`` px of the window's accepted stars ``sw`` (``window``: their rows of ``res``;
    ``Sw`` their responses): what :func:`temperature_fit` tests and
    :func:`temperature_without` takes out.
    """
    if moved is None or res is None or not len(res.get("t", ())):
        return None
    S, ok = _responses(res, moved)
    inside = stats.evaluation_mask(res, fraction)
    before, window = ok & ~inside, ok & inside
    if before.sum() < 50 or window.sum() < 50:
        return None
    a = _lstsq({k: np.asarray(v)[before] for k, v in res.items()}, S[before])
    if a is None:
        return None
    sw = {k: np.asarray(v)[window] for k, v in res.items()}
    return window, sw, S[window], a, S[window] @ a


def temperature_without(runs, run) -> dict | None:
    """``run``'s residuals with the temperature field's fit taken out of the window.

    The field's pattern (:func:`_temperature_pattern`, the probes run again on ``run``'s
    model: three runs) times its size fitted in the window, the fit the field's line tests
    and sizes (:func:`temperature_fit`), as :func:`without` for the column fields; ``None``
    when it cannot be made.
    """
    if not _has_table(run) or run.prior is None:
        return None
    res = run.residuals
    got = _temperature_pattern(res, temperature_probes(runs, run.prior, run.effects),
                               runs.fraction)
    fit = None if got is None else stats.whitened_fit(got[1], got[4])
    if fit is None:
        return None
    return _taken_out(res, got[0], fit[2] * got[4])


def temperature_fit(res, moved: list[dict] | None, fraction: float, along=None
                    ) -> dict | None:
    """The temperature field's fit: the innovations against a mount turning with temperature.

    The field's columns are the filter's response to a tracker turn of 1″/°C with the head
    temperature about each tracker axis (:func:`temperature_probes`: the model run with
    each probe, the difference of the innovations; the filter is linear at these sizes),
    what the model's own states (the gyro bias, the installation) leave of such a turn.
    As the column fields: their combination fitted before the evaluation window is the
    direction (the turn's axis), tested and sized in the window as one pattern
    (:func:`~stellar_cal_ros.diagnosis.stats.whitened_fit`, the frame-robust t_ν);
    ``chi2_capped`` the three columns fitted on the window itself (a candidate's ratio
    beyond the field, :func:`~stellar_cal_ros.diagnosis.flexure.beyond`).  ``along``: the
    current model's direction (its fit's ``direction``) to size this run's pattern along.
    Beside :func:`field_fit`'s keys: ``arcsec_per_c`` (the fitted turn's rate, ″/°C, and
    ``sigma_arcsec_per_c``), ``temperature_change_c`` (the window's range), ``turn_arcsec``
    and ``turn_px`` (the turn over the window: rate × range, and its 99th-percentile
    displacement of the window's stars).  ``None`` when no test can be made.
    """
    got = _temperature_pattern(res, moved, fraction)
    if got is None:
        return None
    _, sw, Sw, a, pattern = got
    fit = stats.whitened_fit(sw, pattern, dof=True)
    if fit is None:
        return None
    t, p, c, info, _ = fit
    own = _lstsq(sw, Sw)
    gain = 0.0 if own is None else stats.capped_gain(sw, Sw @ own, 1.0)
    same = pattern if along is None else Sw @ np.asarray(along, dtype=float)
    sized = stats.pattern_size(sw, same, fit if along is None else None) or {}
    rate = c * a  # ″/°C about the tracker axes
    sigma = float(sized.get("coef_sigma", 1.0 / np.sqrt(info))) * float(np.linalg.norm(a)) \
        if along is None else float("nan")
    temp = np.asarray(sw["head_temperature"], dtype=float)
    change = float(np.ptp(temp[np.isfinite(temp)])) if np.isfinite(temp).any() else 0.0
    return {"t": t, "p_value": p, "chi2": c * c * info, "chi2_capped": gain, "columns": 3,
            "size_px": float(np.percentile(np.hypot(*(c * pattern).T), 99)),
            "direction": [float(x) for x in a],
            "arcsec_per_c": float(np.linalg.norm(rate)), "sigma_arcsec_per_c": sigma,
            "rate_arcsec_per_c": [float(x) for x in rate],
            "temperature_change_c": change,
            "turn_arcsec": float(np.linalg.norm(rate)) * change,
            "turn_px": _turn_px(sw, rate * change * ARCSEC), **sized}


def _turn_px(sub: dict, rho: np.ndarray) -> float:
    """99th percentile of the displacement (px) a tracker turn ``rho`` (rad) gives ``sub``'s stars.

    The pinhole's focal lengths from the table itself (``u`` against ``x/z``, ``v`` against
    ``y/z``, a straight-line fit).
    """
    d = stats.attitude_columns(sub, *_focal(sub)) @ rho
    return float(np.percentile(np.hypot(d[:, 0], d[:, 1]), 99))


def _focal(sub: dict) -> tuple[float, float]:
    """The pinhole's focal lengths (px) of a residual table: ``u`` on ``x/z``, ``v`` on ``y/z``."""
    x, y, z = (np.asarray(sub[k], dtype=float) for k in ("x_st", "y_st", "z_st"))
    return (float(np.polyfit(x / z, np.asarray(sub["u"], dtype=float), 1)[0]),
            float(np.polyfit(y / z, np.asarray(sub["v"], dtype=float), 1)[0]))


def temperature_of(runs, run, prior: Calibration, effects: tuple[str, ...], alpha: float,
                   tell=None, what: str = "", said: dict | None = None) -> dict | None:
    """The temperature field's fit on the current model ``run`` (its residuals kept).

    Run only where it is worth running: where its MDB (:func:`temperature_mdb`, with
    ``mdb_arcsec_per_c`` in the fit) is at most :data:`PLAUSIBLE_MOUNT_ARCSEC_PER_C`,
    first bounded without a run (:func:`temperature_bound`: above it, no probe runs), then
    measured on its probes (three runs).  Where it is not, :func:`not_testable`'s line is
    told and ``None`` returned, as where the bag has no head temperature (nothing told) or
    the test cannot be made.  ``tell``, ``what``: the progress line (``what`` the model).
    ``said``: filled with the numbers of the not-testable line where it is told
    (``temperature_change_c``, ``mdb_arcsec_per_c``, ``from_bound``: the bound decided, no
    probe run; diagnosis.json's ``path[].temperature_not_testable``).
    """
    say = tell or (lambda _: None)

    def untestable(change_c: float, mdb: float, from_bound: bool) -> None:
        say(not_testable(change_c, mdb, from_bound))
        if said is not None:
            said.update(temperature_change_c=change_c, mdb_arcsec_per_c=mdb,
                        from_bound=from_bound)

    bound = temperature_bound(run.residuals, runs.fraction, alpha) if _has_table(run) \
        else None
    if bound is None:
        return None
    if not bound["mdb"] <= PLAUSIBLE_MOUNT_ARCSEC_PER_C:
        untestable(bound["change_c"], bound["mdb"], True)
        return None
    say("testing for a head-temperature-shaped remainder (a mount turning with it) on "
        f"{what or 'the model'}")
    moved = temperature_probes(runs, prior, effects)
    fit = temperature_fit(run.residuals, moved, runs.fraction)
    if fit is None:
        return None
    fit["mdb_arcsec_per_c"] = temperature_mdb(run.residuals, moved, runs.fraction, fit, alpha)
    if not fit["mdb_arcsec_per_c"] <= PLAUSIBLE_MOUNT_ARCSEC_PER_C:
        untestable(fit["temperature_change_c"], fit["mdb_arcsec_per_c"], False)
        return None
    return fit


def significant(found: dict[str, dict | None], alpha: float) -> dict[str, dict]:
    """The fields that are leads: significant at ``alpha`` (Bonferroni over the fields)."""
    return {k: f for k, f in found.items()
            if f is not None and f["p_value"] * len(NAMES) < alpha}


def candidate_on_bag(data, spec, prior: Calibration, effects: tuple[str, ...],
                     fraction: float, noise=None, classes: tuple[type, ...] = (),
                     gravity: bool = False, along: dict | None = None,
                     temperature: bool = False) -> dict[str, dict | None]:
    """The rolling-shutter fit and every field's fit of a candidate model's run.

    For :meth:`~stellar_cal_ros.diagnosis.parallel.Runs.on_bag` (one run where the bag is;
    only the statistics travel): ``{"rolling": ..., "cells": ..., "magnitude": ...}``,
    with ``"gravity"`` (:func:`gravity_fit`: one more run, the model with the probe) when
    ``gravity``.  ``along``: the current model's field directions (:func:`directions`),
    along which each field's size is measured (:func:`field_fit`); with ``temperature``
    also ``"temperature"`` (:func:`temperature_fit` along ``along["temperature"]``: three
    more runs, the model with each of its probes).
    """
    from stellar_cal_ros.diagnosis import rolling
    from stellar_cal_ros.diagnosis.runstats import evaluate, register_effect_classes

    register_effect_classes(classes)
    run = evaluate(data, spec, prior, effects, fraction, True, classes, candidate=True,
                   noise=noise)
    out = {"rolling": rolling.of_run(run, fraction)}
    out.update(of_run(run, fraction, along))
    if gravity and _has_table(run):
        out["gravity"] = gravity_fit(run.residuals, flexure.measure_on_bag(
            data, spec, prior, effects, fraction, noise, classes, True), fraction)
    if temperature and _has_table(run):
        moved = [flexure.measure_on_bag(data, spec, prior, effects, fraction, noise, classes,
                                        True, axis) for axis in range(3)]
        out["temperature"] = temperature_fit(
            run.residuals, None if any(m is None for m in moved) else moved, fraction,
            (along or {}).get("temperature"))
    return out


def stand_in(candidate, dispersion: float, with_c: dict | None, lead: dict, kind: str,
             alpha: float) -> dict | None:
    """Whether ``candidate`` stands in for the field ``kind`` fitted on the current model.

    :func:`~stellar_cal_ros.diagnosis.rolling.stand_in`'s rule with this field, gone beside
    the candidate as :func:`vanished` says: the beyond result (``remainder``: :data:`NAMES`;
    ``lead``: ``kind``; ``lead_size_px``: the field's size on the current model) when
    refused, else ``None``.
    """
    from stellar_cal_ros.diagnosis import rolling

    b = rolling.stand_in(candidate, dispersion, with_c, lead, alpha, NAMES[kind], len(NAMES))
    return None if b is None else dict(b, lead=kind, lead_size_px=lead["size_px"])


def vanished(with_c: dict, lead: dict, dof: int, alpha: float) -> bool:
    """Whether a field (``lead``) is gone beside a candidate of ``dof`` (its fit ``with_c``).

    :func:`~stellar_cal_ros.diagnosis.rolling.vanished` at the fields' level: a field of
    :data:`FIELDS` (many columns) is gone when no longer significant beside the candidate
    as :func:`significant` tests it (Bonferroni over the fields); the gravity field (one
    pattern) when not significant and its size fell.
    """
    from stellar_cal_ros.diagnosis import rolling

    return rolling.vanished(with_c, lead, alpha, dof, len(NAMES))

