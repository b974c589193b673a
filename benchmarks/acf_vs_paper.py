"""ACF calibration against Liu et al. 2017 (Table 1 setting, Table 2, Figs. 3-5).

For every noise level and run: simulate the ``acf_sweep`` scenario (Liu Table 1: 0.5 °/s,
60 frames at 1 Hz, gyro bias 0.03 °/h, ARW 0.005 °/√h) with noise-free centroids, add
Gaussian centroid noise, then

* ACF on the 30 odd frames (noisy), reprojection RMS on the 30 even frames (noise-free),
  as in Liu §3.1 / Fig. 3 (start: f = 20 mm, everything else zero, wide prior σ);
* ACF and IAC on all 60 noisy frames (Liu §3.2 / Fig. 5): RMS errors of x0, y0, f and the
  maximum residual distortion over the 1024² detector.

Against the Cramér–Rao bound (:func:`~stellar_cal_ros.methods.acf_bound.crlb_acf`,
:func:`~stellar_cal_ros.methods.iac.crlb_iac`; the star geometry is the same for every seed,
so one bound per noise level): per parameter the bound, the efficiency RMS/CRLB (1 for an
efficient unbiased estimator; with N runs an efficient one lies in
``√(χ²_N(2.5 %, 97.5 %)/N)``, printed), and the σ predicted for the estimator as
implemented (``LS``: ACF's least squares ignores the gyro random walk in its weights, IAC
treats the pair angles of a frame as independent).  Liu's Table 2 "Error" row is the error
of the 100-run *mean* (§3.1 "100 次平均标定结果"); the table prints ours with its standard
error CRLB/√N next to it.

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
from typing import Any

import numpy as np
from scipy.stats import chi2

from stellar_cal_ros.core.camera import CameraModel
from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.methods.acf import AcfData, reprojection_rms, run_acf
from stellar_cal_ros.methods.acf_bound import (
    crlb_acf,
    installation_error_arcsec,
    installation_error_covariance,
)
from stellar_cal_ros.methods.iac import crlb_iac, run_iac
from stellar_cal_ros.sim.scenarios import FOCAL_LENGTH_MM, PIXEL_PITCH_MM, get_scenario
from stellar_cal_ros.sim.world import simulate

# Liu et al. 2017 as text, beside the repository (the table is left out when it is absent)
PAPER = Path(__file__).resolve().parents[2] / "shared" / "papers" / "001_8d153847d9206e76.txt"
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
    t = text.replace("$", "").replace("\\times 10^{", "e").replace("×10^{", "e")
    t = t.replace("}", "").replace("''", "\"")
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
        if name == "acf":
            inst = installation_error_arcsec(res.calibration, truth)
            out.update({f"acf_theta{k + 1}": inst[k] for k in range(3)})
    return out


def bounds(noise: float, seed: int = 100) -> dict[str, Any]:
    """Cramér–Rao bounds (and the σ of the estimators as implemented) at ``noise`` px.

    Keys ``crlb_<key>`` / ``ls_<key>`` with the run keys of :func:`one_run`: Table 2 (odd
    frames: x0 y0 px, f mm, theta1-3 arcsec) and ``acf_`` / ``iac_`` (all frames, px).  The
    installation also along the principal axes of its bound (``thetaA`` the largest: the
    rotation about the sweep axis, bounded by the prior only; ``thetaB``, ``thetaC``), whose
    unit vectors (tracker axes) are ``axes`` / ``acf_axes`` (rows A, B, C).
    """
    sc = get_scenario("acf_sweep")
    sc.centroid_noise_px = 0.0
    sim = simulate(sc, seed=seed)
    data = AcfData(frames=sim.star_frames, imu=sim.imu, t0_ns=int(sim.imu.stamp_ns[0]))
    arw = np.deg2rad(sc.gyro_arw_deg_sqrth) / 60.0
    prior, truth = liu_prior(sim.prior), sim.truth
    out: dict[str, Any] = {}
    for prefix, frames in (("", "odd"), ("acf_", None)):
        b = crlb_acf(data, prior, truth, frames=frames, sigma_px=noise, gyro_arw=arw)
        names = b.parameter_names
        scale_f = PIXEL_PITCH_MM if prefix == "" else 1.0
        ev, V = np.linalg.eigh(installation_error_covariance(b.crlb, b.model, b.theta_true))
        V = V[:, np.argsort(-ev)]
        V *= np.sign(V[np.argmax(np.abs(V), axis=0), np.arange(3)])
        out[f"{prefix}axes"] = V.T
        for tag, which in (("crlb", "crlb"), ("ls", "estimator")):
            sig = b.sigma(which)
            out[f"{tag}_{prefix}x0"] = sig[names.index("principal_point.cx")]
            out[f"{tag}_{prefix}y0"] = sig[names.index("principal_point.cy")]
            out[f"{tag}_{prefix}f"] = sig[names.index("focal_length.f")] * scale_f
            C = installation_error_covariance(getattr(b, which), b.model, b.theta_true)
            for k in range(3):
                out[f"{tag}_{prefix}theta{k + 1}"] = float(np.sqrt(C[k, k]))
                out[f"{tag}_{prefix}theta{'ABC'[k]}"] = float(np.sqrt(V[:, k] @ C @ V[:, k]))
    bi = crlb_iac(sim.star_frames, prior, truth, sigma_px=noise)
    for tag, which in (("crlb", "crlb"), ("ls", "estimator")):
        sig = bi.sigma(which)
        for key, name in (("x0", "principal_point.cx"), ("y0", "principal_point.cy"),
                          ("f", "focal_length.f")):
            out[f"{tag}_iac_{key}"] = sig[bi.parameter_names.index(name)]
    return out


def run_benchmark(runs: int, noises: list[float], seed0: int = 100) -> list[dict[str, float]]:
    """Rows of aggregated results, one per noise level."""
    rows = []
    for noise in noises:
        res = [one_run(seed0 + k, noise) for k in range(runs)]
        b = bounds(noise, seed0)
        for r in res:  # installation errors along the principal axes of the bound
            for prefix in ("", "acf_"):
                e = np.array([r[f"{prefix}theta{k}"] for k in (1, 2, 3)])
                for k, v in enumerate(b[f"{prefix}axes"] @ e):
                    r[f"{prefix}theta{'ABC'[k]}"] = float(v)

        def rms(key: str, res=res) -> float:
            return float(np.sqrt(np.mean([r[key] ** 2 for r in res])))

        row = {"noise": noise, "runs": runs,
               "heldout_rms": float(np.mean([r["heldout_rms"] for r in res])),
               "heldout_u": float(np.mean([r["heldout_u"] for r in res])),
               "heldout_v": float(np.mean([r["heldout_v"] for r in res]))}
        for key in ("x0", "y0", "f", "q1", "q2", "q3", "p1", "p2", "theta1", "theta2",
                    "theta3", "sigma_x0", "sigma_y0", "sigma_theta2"):
            row[key] = rms(key)
        for key in BOUND_KEYS:
            row[f"mean_{key}"] = float(np.mean([r[key] for r in res]))
        for m in ("acf", "iac"):
            for key in ("x0", "y0", "f"):
                row[f"{m}_{key}"] = rms(f"{m}_{key}")
            row[f"{m}_dist"] = float(np.mean([r[f"{m}_dist"] for r in res]))
        for k in "ABC":
            row[f"acf_theta{k}"] = rms(f"acf_theta{k}")
        for k in "ABC":
            row[f"theta{k}"] = rms(f"theta{k}")
        row.update(b)
        for key in BOUND_KEYS:
            row[f"eff_{key}"] = row[key] / b[f"crlb_{key}"]
        rows.append(row)
    return rows


#: run keys with a bound: Table 2 (odd frames) and Fig. 5 (all frames, ACF and IAC)
BOUND_KEYS = ("x0", "y0", "f", "theta1", "theta2", "theta3", "thetaA", "thetaB", "thetaC",
              "acf_x0", "acf_y0", "acf_f", "acf_thetaA", "acf_thetaB", "acf_thetaC",
              "iac_x0", "iac_y0", "iac_f")


def efficiency_range(runs: int, level: float = 0.95) -> tuple[float, float]:
    """Range of RMS/σ over ``runs`` runs of an efficient unbiased estimator (χ²_N)."""
    a = (1.0 - level) / 2.0
    return (float(np.sqrt(chi2.ppf(a, runs) / runs)),
            float(np.sqrt(chi2.ppf(1.0 - a, runs) / runs)))


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
    print_bounds(rows)


def print_bounds(rows: list[dict[str, float]]) -> None:
    """Bound tables: Fig. 5 setting (ACF vs IAC) and Table 2 setting (odd frames)."""
    lo, hi = efficiency_range(rows[0]["runs"])
    print(f"\nCramér–Rao bound, all 60 frames (Fig. 5 setting): RMS, CRLB, eff = RMS/CRLB, "
          f"LS = σ of the estimator as implemented\n(efficient over {rows[0]['runs']} runs: "
          f"eff in [{lo:.2f}, {hi:.2f}] with 95 %; x0 y0 f in px, θ in arcsec)")
    print(f"{'noise':>6} {'param':>6} | {'ACF RMS':>8} {'CRLB':>8} {'eff':>5} {'LS':>8} | "
          f"{'IAC RMS':>8} {'CRLB':>8} {'eff':>5} {'LS':>8} | {'CRLB IAC/ACF':>12}")
    for r in rows:
        for key in ("x0", "y0", "f", "thetaA", "thetaB", "thetaC"):
            a = f"acf_{key}"
            line = (f"{r['noise']:6.3f} {key:>6} | {r[a]:8.4g} {r['crlb_' + a]:8.4g} "
                    f"{r['eff_' + a]:5.2f} {r['ls_' + a]:8.4g} | ")
            i = f"iac_{key}"
            if i in r:
                line += (f"{r[i]:8.4g} {r['crlb_' + i]:8.4g} {r['eff_' + i]:5.2f} "
                         f"{r['ls_' + i]:8.4g} | {r['crlb_' + i] / r['crlb_' + a]:12.3f}")
            else:
                line += f"{'(IAC estimates no installation)':>35} |"
            print(line)
    print("  θA θB θC: installation error along the principal axes of its bound, in tracker "
          "axes: " + ", ".join(f"{n} = [{v[0]:+.3f} {v[1]:+.3f} {v[2]:+.3f}]"
                               for n, v in zip("ABC", rows[0]["acf_axes"], strict=True))
          + "; θA is the rotation about the sweep axis (bounded by the 5° prior only)")
    paper = paper_table2()
    print(f"\nLiu Table 2 setting (30 odd frames): error of the {rows[0]['runs']}-run mean "
          "(Liu's metric, ± its standard error CRLB/√N) vs RMS and CRLB")
    units = {"x0": "px", "y0": "px", "f": "mm", "theta1": "arcsec", "theta2": "arcsec",
             "theta3": "arcsec", "thetaB": "arcsec", "thetaC": "arcsec"}
    print(f"{'noise':>6} {'param':>6} {'unit':>6} | {'Liu Error':>9} | {'mean err':>9} "
          f"{'± CRLB/√N':>9} | {'RMS':>9} {'CRLB':>9} {'eff':>5} {'LS':>9}")
    for r in rows:
        n = r["runs"]
        for key, unit in units.items():
            liu = _clean(paper.get(key, "-")) if abs(r["noise"] - 0.1) < 1e-9 else ""
            print(f"{r['noise']:6.3f} {key:>6} {unit:>6} | {liu:>9} | {r['mean_' + key]:9.3g} "
                  f"{r['crlb_' + key] / np.sqrt(n):9.3g} | {r[key]:9.3g} "
                  f"{r['crlb_' + key]:9.3g} {r['eff_' + key]:5.2f} {r['ls_' + key]:9.3g}")
    print("  θ1-3: installation error about the tracker axes (Liu's layout; θ1 and θ3 "
          "hold the unobservable rotation about the sweep axis and rest on the 5° prior); "
          "θB θC: the observable principal axes of the bound, "
          + ", ".join(f"{n} = [{v[0]:+.3f} {v[1]:+.3f} {v[2]:+.3f}]"
                      for n, v in zip("BC", rows[0]["axes"][1:], strict=True)))


def motion_bounds(noise: float = 0.1, seed: int = 100) -> list[dict[str, Any]]:
    """ACF and IAC bounds for other motions / knowledge (``--motions``, a few seconds).

    * ``acf_sweep``: Liu's single-axis sweep (as above);
    * ``installation known``: the same with the true installation and a 1" prior σ;
    * ``two-axis``: 60 s as well, 14° about IMU x at 0.5 °/s, then 14° about IMU y;
    * ``psce_rotations``: Tan et al.'s ±30° steps about each IMU axis, first 360 s at 1 Hz
      (its own camera, 0.001 °/√h ARW), prior widened as Liu's.
    """
    from stellar_cal_ros.sim.motion import StepRotations

    def two_axis():
        sc = get_scenario("acf_sweep")
        sc.motion_factory = lambda dur: StepRotations(
            np.eye(3), [("x", np.deg2rad(14.0)), ("y", np.deg2rad(14.0))], step_s=30.0,
            slew_rate=np.deg2rad(0.5), ramp_s=1.0, duration=dur)
        return sc

    def psce():
        sc = get_scenario("psce_rotations")
        sc.star_rate = 1.0
        return sc

    cases = [("acf_sweep (Liu)", get_scenario("acf_sweep"), None, False),
             ("acf_sweep, installation known", get_scenario("acf_sweep"), None, True),
             ("two-axis 14° x then y", two_axis(), None, False),
             ("psce_rotations 360 s", psce(), 360.0, False)]
    out = []
    for name, sc, duration, known in cases:
        sc.centroid_noise_px = 0.0
        sim = simulate(sc, seed=seed, duration=duration)
        prior = liu_prior(sim.prior)
        if known:
            prior.installation = sim.truth.installation
            prior.sigma["installation"]["rotation_vector"] = [float(np.deg2rad(1 / 3600))] * 3
        data = AcfData(frames=sim.star_frames, imu=sim.imu, t0_ns=int(sim.imu.stamp_ns[0]))
        arw = np.deg2rad(sc.gyro_arw_deg_sqrth) / 60.0
        b = crlb_acf(data, prior, sim.truth, sigma_px=noise, gyro_arw=arw)
        bi = crlb_iac(sim.star_frames, prior, sim.truth, sigma_px=noise)
        row: dict[str, Any] = {"case": name, "frames": b.n_frames, "stars": b.n_stars,
                               "inst": b.installation_sigma_arcsec()}
        for key, n in (("x0", "principal_point.cx"), ("y0", "principal_point.cy"),
                       ("f", "focal_length.f")):
            row[f"acf_{key}"] = b.sigma()[b.parameter_names.index(n)]
            row[f"iac_{key}"] = bi.sigma()[bi.parameter_names.index(n)]
        out.append(row)
    return out


def print_motion_bounds(rows: list[dict[str, Any]], noise: float) -> None:
    """Table of :func:`motion_bounds`."""
    print(f"\nBounds by motion at {noise:g} px (CRLB, px; installation bound in arcsec about "
          "the tracker axes)")
    print(f"{'case':>30} {'frames':>6} {'stars':>6} | {'x0 ACF':>7} {'IAC':>7} | "
          f"{'y0 ACF':>7} {'IAC':>7} | {'f ACF':>7} {'IAC':>7} | ACF installation")
    for r in rows:
        print(f"{r['case']:>30} {r['frames']:6d} {r['stars']:6d} | "
              + " | ".join(f"{r['acf_' + k]:7.3f} {r['iac_' + k]:7.3f}" for k in ("x0", "y0", "f"))
              + " | " + " ".join(f"{v:7.1f}" for v in r["inst"]))


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--noise", default="0.05,0.1,0.2,0.3,0.5",
                   help="comma-separated centroid noise levels, px")
    p.add_argument("--seed", type=int, default=100)
    p.add_argument("--motions", action="store_true",
                   help="also print the ACF / IAC bounds for other motions (0.1 px)")
    args = p.parse_args(argv)
    noises = [float(x) for x in args.noise.split(",") if x.strip()]
    t = time.perf_counter()
    rows = run_benchmark(args.runs, noises, args.seed)
    print_tables(rows)
    if args.motions:
        print_motion_bounds(motion_bounds(0.1, args.seed), 0.1)
    print(f"\n{time.perf_counter() - t:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
