"""A rolling shutter's shape beside a candidate: ``discover``'s stand-in rule for it.

No library effect models a tracker whose rows are read out one after the other (a row
``v`` read ``(v − c_y)/H · T`` after the stamp moves each star by its image velocity times
that).  On a moving base, library effects take up parts of it: a time offset the frames'
mean row offset (stars not centred on the middle row), a pixel aspect the row-proportional
part (measured, unseen case ``sway_rolling``: 30 ms readout, discover added time_offset and
pixel_aspect).  The 'unexplained' test of its shape is
:func:`~stellar_cal_ros.diagnosis.stats.shaped_tests`; here the same shape is fitted to the
innovations as a nuisance regressor (:func:`~stellar_cal_ros.diagnosis.stats.
rolling_remainder`), and a candidate is added, once that fit is significant on the current
model, only if it explains the data beyond it (:func:`~stellar_cal_ros.diagnosis.flexure.
beyond`, the rule built for a mount flexure: the candidate's ratio plus what the fit gains
with it minus what it gains without it, χ² with the candidate's dof).  One run of each
candidate so tested, its residuals kept where the bag is.
"""

from __future__ import annotations

from stellar_cal_ros.diagnosis import stats
from stellar_cal_ros.io.calibration import Calibration

#: what a refused candidate's reason calls the remainder and the fit beside it
REMAINDER = ("the rolling-shutter-shaped remainder", "a rolling shutter")


def of_table(res, calibration: Calibration, fraction: float) -> dict[str, float] | None:
    """The rolling-shutter fit of a run's residual table (its evaluation window)."""
    if res is None or not len(res.get("t", ())):
        return None
    cam = calibration.camera
    return stats.rolling_remainder(res, stats.evaluation_mask(res, fraction),
                                   (cam.cx, cam.cy), (cam.fx, cam.fy), calibration.R_imu_st)


def of_run(run, fraction: float) -> dict[str, float] | None:
    """:func:`of_table` of a :class:`~stellar_cal_ros.diagnosis.runstats.RunSummary`."""
    if run is None or not run.ok or run.residuals is None:
        return None
    return of_table(run.residuals, run.calibration, fraction)


def candidate_on_bag(data, spec, prior: Calibration, effects: tuple[str, ...],
                     fraction: float, noise=None, classes: tuple[type, ...] = ()
                     ) -> dict[str, float] | None:
    """The rolling-shutter fit of a candidate model's run, where the bag is.

    For :meth:`~stellar_cal_ros.diagnosis.parallel.Runs.on_bag` (only the statistics
    travel): a candidate's own run keeps no residual table.
    """
    from stellar_cal_ros.diagnosis.runstats import evaluate, register_effect_classes

    register_effect_classes(classes)
    run = evaluate(data, spec, prior, effects, fraction, True, classes, candidate=True,
                   noise=noise)
    return of_run(run, fraction)
