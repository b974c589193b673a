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

Both are :func:`stellar_cal_ros.diagnosis.stats.scale_change`, the tests of the focal
drift's rule (:mod:`stellar_cal_ros.diagnosis.scale_drift`).

Usage: ``python benchmarks/scale_time_read.py focal_drift|clean SEED [DURATION_S]``
"""

from __future__ import annotations

import dataclasses
import sys

from stellar_cal_ros.diagnosis import stats
from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
from stellar_cal_ros.diagnosis.runstats import evaluate
from stellar_cal_ros.methods.replay import bag_data_from_simulation
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate


def read(case: str, seed: int, duration: float) -> dict[str, tuple[float, float]]:
    """``{test: (t, size ppm)}`` of one simulated PSCE bag (``focal_drift`` or ``clean``)."""
    sc = get_scenario("psce_rotations")
    if case == "focal_drift":
        from unseen_cases import _focal_drift  # (the case's own definition)

        sim = simulate(dataclasses.replace(sc, centroid_noise_px=0.0), duration=duration,
                       seed=seed)
        _focal_drift(sim, seed)
    else:
        sim = simulate(sc, duration=duration, seed=seed)
    run = evaluate(bag_data_from_simulation(sim), method_spec("psce"), rerun_prior(sim.prior),
                   (), 0.5, keep_residuals=True)
    cam = sim.prior.camera
    fit = stats.scale_change(run.residuals, stats.evaluation_mask(run.residuals, 0.5),
                             (cam.cx, cam.cy), (cam.fx, cam.fy))
    return {"static scale": (fit["static_t"], fit["static_ppm"]),
            "scale x time given the static scale": (fit["change_t"], fit["change_ppm"])}


if __name__ == "__main__":
    case, seed = sys.argv[1], int(sys.argv[2])
    duration = float(sys.argv[3]) if len(sys.argv) > 3 else 300.0
    for name, (tt, ppm) in read(case, seed, duration).items():
        print(f"{case} seed {seed} {duration:.0f} s  {name}: t {tt:+.2f}, {ppm:+.1f} ppm")
