"""CPU-s of the reliability probe's renders on the 2-h psce bag, and a digest of them (issue 24).

What one probe call of the 2-h ``diagnose`` round makes before its runs
(:func:`stellar_cal_ros.diagnosis.reliability_probe._rendered_injections`): the bag's twin
scene, the plain twin, the user's star columns, four image-plane-tilt injections at ±1 mrad
and the moved bags the runs replay — under the bag's prior (the round renders under the
current model's estimate: the same work).  Each step's ``process_time`` per repetition, then
a digest of the scene's columns, the renders' stars, the injections' steps and the moved
frames' centroids (equal digests: the same arrays, bit for bit).  It measures its own
checkout's package (``discovery_speed`` puts it first on the path): run each checkout's copy,
the two started together::

    python CHECKOUT/benchmarks/probe_renders.py [--repeat 3]
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

#: the probe's four tilt injections (mrad-sized: the 2-h bag's MDB is ~1.1 mrad)
PROBES = (("image_plane_tilt", (1e-3, 0.0)), ("image_plane_tilt", (-1e-3, 0.0)),
          ("image_plane_tilt", (0.0, 1e-3)), ("image_plane_tilt", (0.0, -1e-3)))


def _renders(data, cal, rp, twin_scene) -> str:
    """One probe call's renders, each step's CPU-s printed; the digest of what they made."""
    clock = [time.process_time()]
    first = clock[0]

    def lap(name: str) -> None:
        now = time.process_time()
        print(f"  {name}: {now - clock[0]:.3f} CPU-s", flush=True)
        clock[0] = now

    scene = twin_scene(data, cal, "psce", imu=False)
    lap("scene")
    plain = rp.rendered_stars(data, cal, "psce", scene=scene, imu=False)
    lap("plain render")
    user = rp.star_columns(data.frames)
    lap("star columns")
    injections = [rp.injection_of(data, cal, "psce", e, np.asarray(d), plain, scene,
                                  imu=False, user=user) for e, d in PROBES]
    lap("4 injections")
    moved = [i.on(data) for i in injections]
    lap("4 moved bags")
    print(f"  all: {time.process_time() - first:.3f} CPU-s", flush=True)
    h = hashlib.sha1()
    sc = scene.stars
    for a in (sc.count, sc.messages, sc.usable, sc.u_i, sc.catalog_id, sc.magnitude,
              sc.unidentified, sc.head, sc.air, sc.pressure, plain.stars.uv, plain.stars.keep,
              *[x for i in injections for x in i.stars]):
        h.update(np.ascontiguousarray(a).tobytes())
    for m in moved:
        for f in m.frames[::97]:
            h.update(np.ascontiguousarray(f.uv).tobytes())
    return h.hexdigest()[:16]


def main() -> int:
    """Time the render path ``--repeat`` times; print the digest of the first."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    from discovery_speed import ensure_2h_bag

    from stellar_cal_ros.diagnosis import reliability_probe as rp
    from stellar_cal_ros.diagnosis.twin import twin_scene
    from stellar_cal_ros.io.calibration import load_calibration
    from stellar_cal_ros.methods.replay import read_bag_data

    bag = Path(ensure_2h_bag())
    cal = load_calibration(bag.with_name(bag.name.replace(".mcap", ".prior.yaml")))
    data = read_bag_data(bag)

    for rep in range(args.repeat):
        print(f"repetition {rep + 1}", flush=True)
        digest = _renders(data, cal, rp, twin_scene)
        if rep == 0:
            print("digest", digest, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
