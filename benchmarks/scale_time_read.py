"""A scale changing over the run, read on the current model's residuals (issue 21 item 3).

Measures why unseen case ``focal_drift`` (benchmarks/unseen_cases.py: the focal length
drifting linearly, 150 ppm over the run, no temperature topic) has no first line naming
time, and what a scale-vs-time test shaped like the drift would read.  One PSCE run of the
current model (no added effect), the evaluation window (second half), the within-frame
residuals (u and v stacked, each frame's attitude fit taken out, the frames as units of
:func:`~stellar_cal_ros.diagnosis.stats.frame_robust_t`, as ``stats.shaped_tests``):

* ``static scale``: the regressor ``(u - c_x, v - c_y)``, its slope ``b`` a scale (ppm);
* ``scale x time``: ``(u - c_x, v - c_y) (t - t_mid)``, its slope over the window (ppm);
* the same given the static scale: both the regressor and the residuals without their
  static-scale part (the static scale left in the residuals otherwise swamps the test's
  variance).

Nothing here is a test of the diagnosis's family (the lines' p are not changed).

Usage: ``python benchmarks/scale_time_read.py focal_drift|clean SEED [DURATION_S]``
"""

from __future__ import annotations

import dataclasses
import sys

import numpy as np

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
    res, cam = run.residuals, sim.prior.camera
    centre, focal = (cam.cx, cam.cy), (cam.fx, cam.fy)
    m = stats.evaluation_mask(res, 0.5) & stats.accepted(res)
    sub = {k: np.asarray(v)[m] for k, v in res.items()}
    sig = np.sqrt(np.maximum(0.5 * (sub["s_uu"] + sub["s_vv"]), 1e-300))
    r, lev, _ = stats.within_frame(sub, sig, *focal)
    var = sig**2 * np.clip(1.0 - 0.5 * lev, 1e-3, 1.0)
    inside = stats._components(sub, r[:, 0] * sig, r[:, 1] * sig, var, var, np.zeros_like(var),
                           centre)
    y = np.concatenate([inside["u"][0], inside["v"][0]])
    y_px = np.concatenate([inside["u"][1], inside["v"][1]])
    frame = np.asarray(sub["frame"])
    cl = np.concatenate([frame, frame])
    star = stats.star_tracks(sub)
    tr = None if star is None else np.concatenate([star, star])
    u, v = stats.predicted_position(sub, "u"), stats.predicted_position(sub, "v")
    fit = stats.FrameFit(sub, sig, *focal)

    def project(xy):
        p = fit.residual(xy[:, 0] * sig, xy[:, 1] * sig)
        return np.concatenate([p[:, 0], p[:, 1]])

    t = np.asarray(sub["t"], dtype=float)
    tc = t - 0.5 * (t.min() + t.max())
    s = project(np.stack([u - centre[0], v - centre[1]], 1))
    x = project(np.stack([(u - centre[0]) * tc, (v - centre[1]) * tc], 1))
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(s)

    def test(x, y, y_px):
        tt, _ = stats.frame_robust_t(x[ok], y[ok], cl[ok], track=None if tr is None else tr[ok])
        xc = x[ok] - x[ok].mean()
        return float(tt), float(xc @ y_px[ok]) / float(xc @ xc)

    def without_static(z):
        return z - s * (s[ok] @ z[ok]) / (s[ok] @ s[ok])

    out = {}
    tt, b = test(s, y, y_px)
    out["static scale"] = (tt, b * 1e6)
    tt, b = test(x, y, y_px)
    out["scale x time"] = (tt, b * np.ptp(t) * 1e6)
    tt, b = test(without_static(x), without_static(y), without_static(y_px))
    out["scale x time given the static scale"] = (tt, b * np.ptp(t) * 1e6)
    return out


if __name__ == "__main__":
    case, seed = sys.argv[1], int(sys.argv[2])
    duration = float(sys.argv[3]) if len(sys.argv) > 3 else 300.0
    for name, (tt, ppm) in read(case, seed, duration).items():
        print(f"{case} seed {seed} {duration:.0f} s  {name}: t {tt:+.2f}, {ppm:+.1f} ppm")
