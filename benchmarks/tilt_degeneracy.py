"""How much of an image-plane tilt the principal point and the installation copy.

The exact pixel pattern of a tilt ``tau`` (the camera model with ``tau`` minus without)
at 400 random pixels of the psce_rotations camera is least-squares fitted by the
Jacobian columns of other parameters (finite differences): the principal point, a small
installation rotation, the focal length, tangential and radial distortion.  What is left
is the part of the tilt no combination of them can copy: what a filter can see of a tilt
once the others have absorbed its first-order pattern (doc/benchmarks.md, issue 15,
"Why the tilt was missed").

Run::

    python benchmarks/tilt_degeneracy.py
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate


def main() -> None:
    """Print, per tilt, the pattern's RMS and what each set of parameters leaves of it."""
    cam = simulate(get_scenario("psce_rotations"), duration=5.0, seed=4).prior.camera
    names = list(cam.PARAMETER_NAMES)
    p0 = cam.parameters()
    rng = np.random.default_rng(0)
    d = cam.unproject(np.c_[rng.uniform(0, cam.width, 400), rng.uniform(0, cam.height, 400)])

    def project(p: np.ndarray, rotvec=(0.0, 0.0, 0.0)) -> np.ndarray:
        return cam.with_parameters(p).project(Rotation.from_rotvec(rotvec).apply(d)).ravel()

    base = project(p0)

    def column(name: str, h: float) -> np.ndarray:
        p = p0.copy()
        p[names.index(name)] += h
        return (project(p) - base) / h

    rot = [(project(p0, np.eye(3)[k] * 1e-6) - base) / 1e-6 for k in range(3)]
    sets = {"pp+rot": [column("cx", 1e-3), column("cy", 1e-3)] + rot}
    sets["+f"] = sets["pp+rot"] + [column("fx", 1e-3) + column("fy", 1e-3)]
    sets["+p1p2"] = sets["+f"] + [column("p1", 1e-6), column("p2", 1e-6)]
    sets["+k1k2"] = sets["+p1p2"] + [column("k1", 1e-6), column("k2", 1e-6)]
    print(f"camera f = {cam.fx:.1f} px, {cam.width} x {cam.height} px; RMS in px over u and v")
    print(f"{'tilt':>16} {'pattern':>8} " + " ".join(f"{k:>8}" for k in sets)
          + "   absorbed by (cx, cy px; rotation mrad; f px)")
    for tau in (1e-3, 3e-3, 1e-2):
        for comp in ("tau_x", "tau_y"):
            p = p0.copy()
            p[names.index(comp)] += tau
            pattern = project(p) - base
            left = []
            for cols in sets.values():
                a = np.array(cols).T
                x, *_ = np.linalg.lstsq(a, pattern, rcond=None)
                left.append(np.sqrt(np.mean((pattern - a @ x) ** 2)))
            x, *_ = np.linalg.lstsq(np.array(sets["+f"]).T, pattern, rcond=None)
            print(f"{comp} = {tau * 1e3:4.0f} mrad {np.sqrt(np.mean(pattern ** 2)):8.4f} "
                  + " ".join(f"{v:8.4f}" for v in left)
                  + f"   {x[0]:6.2f} {x[1]:6.2f}; {x[2] * 1e3:5.2f} {x[3] * 1e3:5.2f}"
                  f" {x[4] * 1e3:5.2f}; {x[5]:5.3f}")


if __name__ == "__main__":
    main()
