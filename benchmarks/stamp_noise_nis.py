"""The stars' NIS/dof of a replay whose frames' stamps jitter, with and without ``stamp=``.

``--kind frame`` (H296): the frames' stars shifted together instead, one N(0, ``--jitter``
px) per frame and axis (:func:`~stellar_cal_ros.sim.tracker_errors.frame_jitter`, unseen
case ``frame_jitter``), replayed without and with ``NoiseScales(frame_px=...)`` (σ_f² I₂
between every two stars of a frame in its R).  ``--jitter`` is the size in the kind's unit
(ms for the stamps, px for the frames' shift; ``--jitter-ms`` its old name).

Each bag: ``--scenario`` (psce_rotations through :func:`simulate`, swaying_base through
:func:`~stellar_cal_ros.diagnosis.injection.clean_simulation`: the model's own effects),
frames stamped N(0, ``--jitter-ms``) off their exposures
(:func:`~stellar_cal_ros.sim.tracker_errors.stamp_jitter`), replayed with the stated noise
and with ``NoiseScales(stamp_ms=--jitter-ms)`` (the stamps' noise in each frame's R).  One
line a seed: the two NIS/dof; then their mean and sd (issue 21, H277).

``--motion`` (H286): the stamps' line's test (:func:`~stellar_cal_ros.diagnosis.stats.
motion_spread`) on the window of the replay with ``stamp=--stated-ms`` in R (default the
jitter), its null without the stamps (as before H286) and with the stated ones: p, σ̂_t.
``--twin-seeds``: twins of each bag (:func:`~stellar_cal_ros.diagnosis.twin.make_twin`, the
calibration of its ``stamp=`` replay: they render the stamps) replayed without and with it.

Run::

    .venv/bin/python benchmarks/stamp_noise_nis.py --scenario psce_rotations --duration 120 \
        --seeds 21,22,23,24,25,26
    .venv/bin/python benchmarks/stamp_noise_nis.py --scenario swaying_base --duration 60 \
        --seeds 21,22,23,24
    .venv/bin/python benchmarks/stamp_noise_nis.py --scenario swaying_base --duration 60 \
        --seeds 22,23 --motion            # and --jitter-ms 2 --stated-ms 1
    .venv/bin/python benchmarks/stamp_noise_nis.py --seeds 21 --twin-seeds 3,4,5
    .venv/bin/python benchmarks/stamp_noise_nis.py --kind frame --jitter 0.04 \
        --seeds 21,22,23,24,25,26
"""

from __future__ import annotations

import argparse

import numpy as np

from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.diagnosis.injection import clean_simulation
from stellar_cal_ros.methods.frames import bag_data_from_simulation
from stellar_cal_ros.methods.replay import replay
from stellar_cal_ros.sim import tracker_errors
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate


def nis_dof(res) -> float:
    """The stars' NIS per degree of freedom of the replay's window (``RunStats.nis_per_dof``)."""
    return res.stats.current().nis_per_dof()[0]


def _motion(r, stamp: float):
    """The stamps' line's test on ``r``'s window, its null's stamp noise ``stamp`` (s)."""
    from stellar_cal_ros.diagnosis import stats

    cam = r.calibration.camera
    return stats.stamp_line(r.residuals, stats.evaluation_mask(r.residuals, 0.5),
                            (cam.fx, cam.fy), (cam.cx, cam.cy), r.calibration.R_imu_st, stamp)


#: per kind: (its --noise-scale item, the scales with size x, the bag's jitter of size x)
KINDS = {"stamp": ("stamp", lambda x: NoiseScales(stamp_ms=x),
                   lambda sim, x, seed: tracker_errors.stamp_jitter(sim, x * 1e-3, seed)),
         "frame": ("frame", lambda x: NoiseScales(frame_px=x), tracker_errors.frame_jitter)}


def main() -> None:
    """The command line (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default="psce_rotations",
                    choices=("psce_rotations", "swaying_base"))
    ap.add_argument("--duration", type=float, default=120.0)
    ap.add_argument("--seeds", default="21,22,23,24,25,26")
    ap.add_argument("--kind", default="stamp", choices=tuple(KINDS),
                    help="the frames' stamps jitter (ms), or their stars shift together (px)")
    ap.add_argument("--jitter", "--jitter-ms", dest="jitter_ms", type=float, default=1.0)
    ap.add_argument("--stated-ms", type=float, default=None,
                    help="the noise in R (default: --jitter; the kind's unit)")
    ap.add_argument("--motion", action="store_true", help="the stamps' line's test only")
    ap.add_argument("--twin-seeds", default="", help="twins of each bag, these noise seeds")
    a = ap.parse_args()
    stated = a.jitter_ms if a.stated_ms is None else a.stated_ms
    method = "psce" if a.scenario == "psce_rotations" else "swaying_base"
    item, scales, jitter = KINDS[a.kind]
    got = []
    for seed in (int(s) for s in a.seeds.split(",")):
        if method == "psce":
            sim = simulate(get_scenario(a.scenario), duration=a.duration, seed=seed)
        else:
            sim, _ = clean_simulation("swaying_base", False, seed, a.duration)
        jitter(sim, a.jitter_ms, seed)
        data = bag_data_from_simulation(sim)
        if a.motion and a.kind == "stamp":
            r = replay(data, sim.prior, method, noise=NoiseScales(stamp_ms=stated))
            got_m = [_motion(r, st) for st in (0.0, stated * 1e-3)]
            print(f"seed {seed}: stamps {a.jitter_ms:g} ms, stamp={stated:g} in R: p "
                  f"{got_m[0].p_value:.2g} (null without), {got_m[1].p_value:.2g} (with); "
                  f"{got_m[1].regressor.split(': ')[1].split(',')[0]}", flush=True)
            continue
        if a.twin_seeds:
            from stellar_cal_ros.diagnosis.twin import make_twin

            cal = replay(data, sim.prior, method, noise=scales(stated),
                         keep_tables=False).calibration
            for ts in (int(x) for x in a.twin_seeds.split(",")):
                tw = make_twin(data, cal, {}, seed=ts, method=method)
                two = [nis_dof(replay(tw.data, tw.prior, method, noise=scales(st),
                                      keep_tables=False)) for st in (0.0, stated)]
                print(f"seed {seed} twin {ts}: NIS/dof {two[0]:.4f} without, {two[1]:.4f} "
                      f"with {item}={stated:g}", flush=True)
            continue
        row = [nis_dof(replay(data, sim.prior, method, noise=scales(st),
                              keep_tables=False)) for st in (0.0, a.jitter_ms)]
        got.append(row)
        print(f"seed {seed}: NIS/dof {row[0]:.4f} without, {row[1]:.4f} with {item}="
              f"{a.jitter_ms:g}", flush=True)
    if not got:
        return
    x = np.array(got)[:, 1]
    print(f"with {item}={a.jitter_ms:g}: mean {x.mean():.4f} sd {x.std(ddof=1):.4f} "
          f"(the mean's sigma {x.std(ddof=1) / np.sqrt(len(x)):.4f})")


if __name__ == "__main__":
    main()
