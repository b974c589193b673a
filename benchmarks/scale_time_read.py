"""A scale changing over the run, read on the current model's residuals (issue 21 item 3).

Measures why unseen case ``focal_drift`` (benchmarks/unseen_cases.py: the focal length
drifting linearly, 150 ppm over the run, no temperature topic) has no first line naming
time, and what a scale-vs-time test shaped like the drift would read.  One PSCE run of the
current model (no added effect), the evaluation window (second half), the within-frame
residuals (u and v stacked, each frame's attitude fit taken out, the frames as units of
:func:`~stellar_cal_ros.diagnosis.stats.frame_robust_t`, as ``stats.shaped_tests``):

* ``static scale``: the regressor ``(u - c_x, v - c_y)``, its slope ``b`` a scale (ppm);
* ``scale x time`` given the static scale: ``(u - c_x, v - c_y) (t - t_mid)``, its slope over
  the window (ppm), both the regressor and the residuals without their static-scale part
  (the static scale left in the residuals otherwise swamps the test's variance: the plain
  product read t 1.1-1.3 on the drift, doc/benchmarks.md).

Both are :func:`stellar_cal_ros.diagnosis.stats.shape_change`, the tests of the shape
drift's rule (:mod:`stellar_cal_ros.diagnosis.shape_drift`); the same two tests of the
detector's tilts (tau_x, tau_y: the keystone's pattern, mrad) follow the scale's.

Usage: ``python benchmarks/scale_time_read.py focal_drift|tilt_drift|clean SEED [DURATION_S]``
"""

from __future__ import annotations

import dataclasses
import sys

from stellar_cal_ros.diagnosis import shape_drift
from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
from stellar_cal_ros.diagnosis.runstats import evaluate
from stellar_cal_ros.methods.replay import bag_data_from_simulation
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate


def read(case: str, seed: int, duration: float) -> dict[str, tuple]:
    """``{test: (t, size, unit)}`` of one simulated PSCE bag, and the rule's condition.

    ``case``: ``focal_drift``, ``tilt_drift`` or ``clean``.  For each shape also whether
    the rule's condition holds (:func:`~stellar_cal_ros.diagnosis.shape_drift.lagging`; a
    tilt's pattern counts as followed when psce's camera parameters span more than
    :data:`~stellar_cal_ros.diagnosis.shape_drift.SPANNED` of it: that share printed).
    """
    sc = get_scenario("psce_rotations")
    if case in ("focal_drift", "tilt_drift"):
        import unseen_cases  # (the case's own definition)

        sim = simulate(dataclasses.replace(sc, centroid_noise_px=0.0), duration=duration,
                       seed=seed)
        getattr(unseen_cases, f"_{case}")(sim, seed)
    else:
        sim = simulate(sc, duration=duration, seed=seed)
    run = evaluate(bag_data_from_simulation(sim), method_spec("psce"), rerun_prior(sim.prior),
                   (), 0.5, keep_residuals=True)
    out = {}
    base = method_spec("psce").baseline
    for shape in shape_drift.SHAPES:
        own = shape.effect in base
        fit = shape_drift.of_table(run.residuals, run.calibration, 0.5, shape,
                                   None if own else base)
        estimated = own or fit.get("spanned", 0.0) > shape_drift.SPANNED
        name = shape.name
        out[f"static {name}"] = (fit["static_t"], fit["static"] * shape.per_unit, shape.unit)
        out[f"{name} x time given the static {name}"] = (
            fit["change_t"], fit["change"] * shape.per_unit, shape.unit)
        out[f"{name}: the rule's condition"] = (
            "holds" if estimated and shape_drift.lagging(fit, 0.01) else "does not hold",
            "estimated" if own else f"spanned {fit['spanned']:.3f}")
    return out


if __name__ == "__main__":
    case, seed = sys.argv[1], int(sys.argv[2])
    duration = float(sys.argv[3]) if len(sys.argv) > 3 else 300.0
    for name, got in read(case, seed, duration).items():
        text = ("{} ({})".format(*got) if len(got) == 2
                else f"t {got[0]:+.2f}, {got[1]:+.3g} {got[2]}")
        print(f"{case} seed {seed} {duration:.0f} s  {name}: {text}")
