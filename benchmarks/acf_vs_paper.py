"""ACF calibration against Liu et al. 2017 (Table 1 setting, Table 2, Figs. 3-5).

For every noise level and run: simulate the ``acf_sweep`` scenario (Liu Table 1: 0.5 °/s,
60 frames at 1 Hz, gyro bias 0.03 °/h, ARW 0.005 °/√h) with noise-free centroids, add
Gaussian centroid noise, then

* ACF on the 30 odd frames (noisy), reprojection RMS on the 30 even frames (noise-free),
  as in Liu §3.1 / Fig. 3 (start: f = 20 mm, everything else zero, wide prior σ);
* ACF and IAC on all 60 noisy frames (Liu §3.2 / Fig. 5): RMS errors of x0, y0, f and the
  maximum residual distortion over the 1024² detector.

Usage::

    .venv/bin/python benchmarks/acf_vs_paper.py --runs 5 --noise 0.05,0.1,0.2,0.3,0.5
"""

from __future__ import annotations

import argparse
import copy
import re
import sys
import time
from pathlib import Path

import numpy as np

from stellar_cal_ros.core.camera import CameraModel
from stellar_cal_ros.methods.acf import (
    ARCSEC,
    AcfData,
    installation_error_arcsec,
    reprojection_rms,
    run_acf,
)
from stellar_cal_ros.methods.iac import run_iac
from stellar_cal_ros.sim.scenarios import FOCAL_LENGTH_MM, PIXEL_PITCH_MM, get_scenario
from stellar_cal_ros.sim.world import simulate

PAPER = Path("/work/shared/papers/001_8d153847d9206e76.txt")
TABLE2_NAMES = ("x0", "y0", "f", "q1", "q2", "q3", "p1", "p2",
                "phi1", "phi2", "phi3", "theta1", "theta2", "theta3")


def paper_table2(path: Path = PAPER) -> dict[str, str]:
    """The 'Error' rows of Liu et al. Table 2, as printed (units: px, mm, mm⁻ⁿ, arcsec)."""
    if not path.exists():
        return {}
    values: list[str] = []
    for line in path.read_text().splitlines():
        if line.startswith("Error"):
            values += [v.strip() for v in line.split("\t")[1:] if v.strip()]
    return dict(zip(TABLE2_NAMES, values, strict=False))


def _clean(text: str) -> str:
    t = text.replace("$", "").replace("\\times 10^{", "e").replace("}", "").replace("''", "\"")
    return re.sub(r"\s+", "", t)


def liu_prior(prior):
    """Liu's start: f = 20 mm, zero principal-point offset / distortion / installation."""
    p = copy.deepcopy(prior)
    f20 = 20.0 / PIXEL_PITCH_MM
    p.camera = p.camera.with_parameters(np.r_[f20, f20, p.camera.parameters()[2:]])
    p.sigma["camera"]["camera_matrix"]["data"] = [1000.0, 0, 50.0, 0, 1000.0, 50.0, 0, 0, 0]
    p.sigma["camera"]["distortion_coefficients"]["data"] = [3.0, 10.0, 0.02, 0.02, 100.0]
    p.sigma["installation"]["rotation_vector"] = [float(np.deg2rad(5.0))] * 3
    return p


def residual_distortion_max(est: CameraModel, truth: CameraModel, n: int = 33) -> float:
    """Max over the detector of |distortion displacement (est) − (truth)|, px."""
    g = np.linspace(0.0, 1.0, n)
    uu, vv = np.meshgrid(g * (truth.width - 1), g * (truth.height - 1))
    xy = truth.pixel_to_normalized(np.column_stack([uu.ravel(), vv.ravel()]))

    def disp(cam: CameraModel) -> np.ndarray:
        lin = np.column_stack([cam.fx * xy[:, 0] + cam.cx, cam.fy * xy[:, 1] + cam.cy])
        return cam.normalized_to_pixel(xy) - lin

    return float(np.max(np.linalg.norm(disp(est) - disp(truth), axis=1)))


def one_run(seed: int, noise: float) -> dict[str, float]:
    """One Monte-Carlo run at centroid noise ``noise`` px."""
    sc = get_scenario("acf_sweep")
    sc.centroid_noise_px = 0.0
    sim = simulate(sc, seed=seed)
    rng = np.random.default_rng(10_000 + seed)
    noisy = copy.deepcopy(sim.star_frames)
    for f in noisy:
        f.uv = f.uv + noise * rng.standard_normal(f.uv.shape)
        f.sigma = np.full(len(f.uv), noise)
    t0 = int(sim.imu.stamp_ns[0])
    data_noisy = AcfData(frames=noisy, imu=sim.imu, t0_ns=t0)
    data_clean = AcfData(frames=sim.star_frames, imu=sim.imu, t0_ns=t0)
    arw = np.deg2rad(sc.gyro_arw_deg_sqrth) / 60.0
    prior = liu_prior(sim.prior)
    truth = sim.truth
    tc = truth.camera
    out: dict[str, float] = {}
    # §3.1: odd frames calibrate, noise-free even frames check
    r = run_acf(data_noisy, prior, frames="odd", gyro_arw=arw)
    out["heldout_rms"] = reprojection_rms(r, "even", data=data_clean)
    out["heldout_u"], out["heldout_v"] = reprojection_rms(r, "even", data=data_clean,
                                                          per_axis=True)
    c = r.calibration.camera
    f_mm = FOCAL_LENGTH_MM
    out.update({
        "x0": c.cx - tc.cx, "y0": c.cy - tc.cy, "f": (c.fx - tc.fx) * PIXEL_PITCH_MM,
        "q1": (c.distortion[0] - tc.distortion[0]) / f_mm**2,
        "q2": (c.distortion[1] - tc.distortion[1]) / f_mm**4,
        "q3": (c.distortion[4] - tc.distortion[4]) / f_mm**6,
        "p1": (c.distortion[2] - tc.distortion[2]) / f_mm,
        "p2": (c.distortion[3] - tc.distortion[3]) / f_mm,
    })
    inst = installation_error_arcsec(r.calibration, truth)
    out.update({"theta1": inst[0], "theta2": inst[1], "theta3": inst[2]})
    out["sigma_x0"], out["sigma_y0"] = r.sigma[7], r.sigma[8]
    out["sigma_theta2"] = r.sigma[4] / ARCSEC
    # §3.2: all 60 noisy frames, ACF vs IAC
    for name, res in (("acf", run_acf(data_noisy, prior, gyro_arw=arw)),
                      ("iac", run_iac(noisy, prior))):
        ce = res.calibration.camera
        out[f"{name}_x0"] = ce.cx - tc.cx
        out[f"{name}_y0"] = ce.cy - tc.cy
        out[f"{name}_f"] = ce.fx - tc.fx
        out[f"{name}_dist"] = residual_distortion_max(ce, tc)
    return out


def run_benchmark(runs: int, noises: list[float], seed0: int = 100) -> list[dict[str, float]]:
    """Rows of aggregated results, one per noise level."""
    rows = []
    for noise in noises:
        res = [one_run(seed0 + k, noise) for k in range(runs)]

        def rms(key: str, res=res) -> float:
            return float(np.sqrt(np.mean([r[key] ** 2 for r in res])))

        row = {"noise": noise, "runs": runs,
               "heldout_rms": float(np.mean([r["heldout_rms"] for r in res])),
               "heldout_u": float(np.mean([r["heldout_u"] for r in res])),
               "heldout_v": float(np.mean([r["heldout_v"] for r in res]))}
        for key in ("x0", "y0", "f", "q1", "q2", "q3", "p1", "p2", "theta1", "theta2",
                    "theta3", "sigma_x0", "sigma_y0", "sigma_theta2"):
            row[key] = rms(key)
        for m in ("acf", "iac"):
            for key in ("x0", "y0", "f"):
                row[f"{m}_{key}"] = rms(f"{m}_{key}")
            row[f"{m}_dist"] = float(np.mean([r[f"{m}_dist"] for r in res]))
        rows.append(row)
    return rows


def print_tables(rows: list[dict[str, float]]) -> None:
    """Print the three tables (Fig. 3, Table 2, Fig. 5)."""
    print("\nHeld-out reprojection (odd frames calibrate, noise-free even frames check; "
          "Liu Fig. 3/4: 0.0132 / 0.0123 px per axis at 0.1 px)")
    print(f"{'noise px':>8} {'runs':>4} {'RMS|Δ| px':>10} {'RMS u':>8} {'RMS v':>8}")
    for r in rows:
        print(f"{r['noise']:8.3f} {r['runs']:4d} {r['heldout_rms']:10.4f} "
              f"{r['heldout_u']:8.4f} {r['heldout_v']:8.4f}")
    paper = paper_table2()
    print("\nParameter RMS errors (odd frames) vs Liu Table 2 'Error' row (100-run mean, 0.1 px)")
    keys = ("x0", "y0", "f", "q1", "q2", "q3", "p1", "p2", "theta1", "theta2", "theta3")
    units = ("px", "px", "mm", "mm^-2", "mm^-4", "mm^-6", "mm^-1", "mm^-1", "arcsec",
             "arcsec", "arcsec")
    head = f"{'param':>7} {'unit':>7} {'Liu':>10} " + " ".join(
        f"{'σ=' + format(r['noise'], 'g'):>10}" for r in rows)
    print(head)
    for k, u in zip(keys, units, strict=True):
        print(f"{k:>7} {u:>7} {_clean(paper.get(k, '-')):>10} "
              + " ".join(f"{r[k]:10.3g}" for r in rows))
    print("  (installation errors are rotation-vector components about the tracker axes; the "
          "component about the sweep axis is unobservable and rests on the prior)")
    print("\nACF vs IAC, all 60 frames (Liu Fig. 5): RMS errors and mean max residual "
          "distortion")
    print(f"{'noise':>6} | {'x0 ACF':>7} {'x0 IAC':>7} | {'y0 ACF':>7} {'y0 IAC':>7} | "
          f"{'f ACF':>7} {'f IAC':>7} px | {'dist ACF':>8} {'dist IAC':>8} px")
    for r in rows:
        print(f"{r['noise']:6.3f} | {r['acf_x0']:7.3f} {r['iac_x0']:7.3f} | "
              f"{r['acf_y0']:7.3f} {r['iac_y0']:7.3f} | {r['acf_f']:7.3f} {r['iac_f']:7.3f}"
              f"    | {r['acf_dist']:8.3f} {r['iac_dist']:8.3f}")


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--noise", default="0.05,0.1,0.2,0.3,0.5",
                   help="comma-separated centroid noise levels, px")
    p.add_argument("--seed", type=int, default=100)
    args = p.parse_args(argv)
    noises = [float(x) for x in args.noise.split(",") if x.strip()]
    t = time.perf_counter()
    rows = run_benchmark(args.runs, noises, args.seed)
    print_tables(rows)
    print(f"\n{time.perf_counter() - t:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
