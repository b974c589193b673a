"""Centroid scatter on rendered frames: the project's PSF fit against tetra3rs's moments.

What the bundle's held-out RMS on real frames rests on (doc/benchmarks.md, real sky).  The
frames of ``benchmarks/bundle_bound.py`` (stars to magnitude 6 on a 1024 × 1024 detector)
rendered by :mod:`stellar_cal_ros.sim.render` for several sensors, centroided by
:func:`stellar_cal_ros.sky.extract.extract_stars` (pixel-integrated Gaussian fit) and by
``tetra3rs.extract_centroids`` (moments with peak refinement); each detection within 1 px of
a true star is compared with it.

Usage::

    .venv/bin/python benchmarks/bundle_centroids.py --frames 12
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path

import numpy as np

SENSORS = {
    "8-bit, PSF 1.0 px": {"bits": 8, "gain_e_per_adu": 60.0, "bias_adu": 5.0},
    "12-bit, PSF 1.0 px": {},
    "16-bit, PSF 1.2 px": {"bits": 16, "full_well_e": 60000.0, "gain_e_per_adu": 1.0,
                           "psf_sigma_px": 1.2},
    "16-bit, PSF 0.7 px": {"bits": 16, "full_well_e": 60000.0, "gain_e_per_adu": 1.0,
                           "psf_sigma_px": 0.7},
}


def _world(n_frames: int) -> dict:
    path = Path(__file__).resolve().parent / "bundle_bound.py"
    spec = importlib.util.spec_from_file_location("bundle_bound", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod.world(n_frames=n_frames)


def main(argv: list[str] | None = None) -> int:
    """Print the RMS centroid error of both extractors per sensor."""
    import tetra3rs
    from scipy.spatial import cKDTree

    from stellar_cal_ros.sim.render import SensorConfig, render_image
    from stellar_cal_ros.sky.extract import extract_stars

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--frames", type=int, default=12)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    w = _world(args.frames)
    cam = w["sim"].prior.camera
    rng = np.random.default_rng(args.seed)
    centre = np.array([(cam.width - 1) / 2.0, (cam.height - 1) / 2.0])
    print(f"{'sensor':20s} {'PSF fit RMS |err| px':>21s} {'stars':>6s} "
          f"{'tetra3rs moments':>17s} {'stars':>6s} {'ratio':>6s}")
    for name, kw in SENSORS.items():
        sensor = SensorConfig(**kw)
        errs: dict[str, list[np.ndarray]] = {"psf": [], "moments": []}
        for f in w["frames"]:
            img = render_image(f.uv, f.magnitude, cam.width, cam.height, sensor, rng).image
            found = {"psf": extract_stars(img).uv,
                     "moments": np.array([[d.x, d.y] for d in tetra3rs.extract_centroids(
                         img.astype(np.float32)).centroids]).reshape(-1, 2) + centre}
            for key, uv in found.items():
                d, j = cKDTree(uv).query(f.uv)
                errs[key].append(uv[j[d < 1.0]] - f.uv[d < 1.0])
        e = {k: np.vstack(v) for k, v in errs.items()}
        r = {k: float(np.sqrt(np.mean(np.sum(v ** 2, axis=1)))) for k, v in e.items()}
        print(f"{name:20s} {r['psf']:21.4f} {len(e['psf']):6d} {r['moments']:17.4f} "
              f"{len(e['moments']):6d} {r['psf'] / r['moments']:6.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
