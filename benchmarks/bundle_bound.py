"""The bundle method at its Cramér–Rao bound, with honest σ (Monte Carlo on simulated frames).

Frames: Tan et al.'s rotation sequence (``psce_rotations``: seven attitudes over 400 s),
``--frames`` of them evenly spaced, centroids exactly the true model (pinhole + principal
point offset + k1 k2 + tangential) plus Gaussian noise of ``--noise`` px, the message σ
stating it.  Each run draws new noise and a new prior centre from the prior
(``θ_prior ~ N(θ_true, σ_prior²)``: the bound is then the Bayesian one, prior included) and
fits the camera (focal length, principal point, k1 k2, p1 p2) and one attitude per frame.

Per parameter: the bound ``σ_CRLB`` (inverse Fisher information at the truth, attitudes
marginalised), the RMS error over the runs, the efficiency ``σ_CRLB² / MSE`` (1: at the
bound) and the mean reported σ; over all parameters the mean of ``eᵀ CRLB⁻¹ e`` and the NEES
``eᵀ P̂⁻¹ e`` (both P on average: at the bound, σ honest) with their 95 % intervals, and the
mean variance factor s² (1: the stated noise is the noise).

With ``--images`` each run renders the frames as 12-bit images (PSF, sky background, shot
and read noise, hot pixels, saturation: :mod:`stellar_cal_ros.sim.render`) and centroids
them with the project's extractor; the bound is then the one of the σ the extractor
states, and the variance factor says how honest those σ are.

Usage::

    .venv/bin/python benchmarks/bundle_bound.py --runs 400 --frames 30
    .venv/bin/python benchmarks/bundle_bound.py --runs 100 --frames 30 --images
"""

from __future__ import annotations

import argparse
import copy
import sys
import time

import numpy as np


def world(n_frames: int = 30, noise_px: float = 0.05, seed: int = 1) -> dict:
    """Noise-free frames of the rotation sequence, the bundle model and its truth."""
    from stellar_cal_ros.methods import bundle as bd
    from stellar_cal_ros.methods.frames import bag_data_from_simulation
    from stellar_cal_ros.methods.replay import truth_parameters
    from stellar_cal_ros.sim.scenarios import get_scenario
    from stellar_cal_ros.sim.world import simulate

    sc = get_scenario("psce_rotations")
    sc.centroid_noise_px = 0.0
    sim = simulate(sc, duration=400, seed=seed)
    data = bag_data_from_simulation(sim)
    data.frames = data.frames[::max(len(data.frames) // n_frames, 1)][:n_frames]
    model, _, sigma_prior = bd.make_model(sim.prior, ["tangential"])
    frames = bd.bundle_frames(data, sim.prior)
    for f in frames:
        f.sigma = np.full(len(f.uv), noise_px)
    theta = truth_parameters(model, sim.truth)
    R0, _ = bd.initial_attitudes(model, theta, frames)
    _, R_true, ne, _ = bd.Bundle(model, frames, theta, sigma_prior).solve(theta, R0,
                                                                          with_theta=False)
    return {"sim": sim, "data": data, "model": model, "frames": frames, "theta": theta,
            "attitudes": R_true, "sigma_prior": sigma_prior, "noise_px": noise_px,
            "misfit": float(ne.sum_wz)}


def noisy(frames: list, rng: np.random.Generator, sigma: float) -> list:
    """Copies of ``frames`` with Gaussian centroid noise of ``sigma`` px added."""
    out = []
    for f in frames:
        g = copy.copy(f)
        g.uv = f.uv + sigma * rng.standard_normal(f.uv.shape)
        g.use = np.ones(len(f.uv), dtype=bool)
        out.append(g)
    return out


def rendered(frames: list, rng: np.random.Generator, size: tuple[int, int],
             sensor=None) -> list:
    """The frames as images of ``size`` (width, height), their stars extracted again.

    Rendered by :mod:`stellar_cal_ros.sim.render`, centroided by
    :func:`stellar_cal_ros.sky.extract.extract_stars` (PSF fit, σ per star); each
    extracted star takes the identity of the true star within 1 px (identification is
    tested on its own, test/test_identification.py).
    """
    from scipy.spatial import cKDTree

    from stellar_cal_ros.sim.render import render_image
    from stellar_cal_ros.sky.extract import extract_stars

    out = []
    for f in frames:
        c = extract_stars(render_image(f.uv, f.magnitude, *size, sensor, rng).image)
        d, j = cKDTree(c.uv).query(f.uv)
        ok = d < 1.0
        g = copy.copy(f.subset(ok))  # a copy even when every star was found
        g.uv, g.sigma = c.uv[j[ok]], c.sigma[j[ok]]
        out.append(g)
    return out


def monte_carlo(w: dict, runs: int, seed: int = 7, images: bool = False) -> dict:
    """``runs`` fits; the errors, reported σ, CRLB, efficiency and NEES statistics.

    ``images``: each run renders and extracts the frames (:func:`rendered`) instead of
    adding Gaussian noise; the bound is then that of the extractor's stated σ, run by run.
    """
    from stellar_cal_ros.methods import bundle as bd
    from stellar_cal_ros.methods.bundle_bound import crlb_bundle

    model, theta, sp = w["model"], w["theta"], w["sigma_prior"]
    crlb = crlb_bundle(w["frames"], model, theta, w["attitudes"], sp)
    rng = np.random.default_rng(seed)
    P = model.size
    err, sig, eff, nees, s2s, bounds = [], [], [], [], [], []
    c0 = time.process_time()
    for _ in range(runs):
        th_prior = theta + sp * rng.standard_normal(P)
        cam = w["sim"].prior.camera
        frames = (rendered(w["frames"], rng, (cam.width, cam.height)) if images
                  else noisy(w["frames"], rng, w["noise_px"]))
        bound = crlb_bundle(frames, model, theta, w["attitudes"], sp) if images else crlb
        fit, _ = bd.fit_bundle(model, frames, th_prior, w["attitudes"], th_prior, sp)
        cov, s2 = fit.covariance()
        e = fit.theta - theta
        err.append(e)
        sig.append(np.sqrt(np.diag(cov)))
        eff.append(e @ np.linalg.solve(bound, e))
        nees.append(e @ np.linalg.solve(cov, e))
        s2s.append(s2)
        bounds.append(np.diag(bound))
    err = np.array(err)
    return {"names": model.parameter_names(), "crlb": np.sqrt(np.mean(bounds, axis=0)),
            "rms": np.sqrt(np.mean(err ** 2, axis=0)), "mean": err.mean(axis=0),
            "sigma": np.mean(sig, axis=0), "efficiency_chi2": np.array(eff),
            "nees": np.array(nees), "variance_factor": np.array(s2s), "P": P, "runs": runs,
            "cpu_per_run": (time.process_time() - c0) / runs, "images": images}


def print_table(w: dict, mc: dict) -> None:
    """The per-parameter table and the summary lines."""
    n = sum(len(f.uv) for f in w["frames"])
    what = ("rendered 12-bit images, PSF-fit centroids" if mc.get("images")
            else f"noise {w['noise_px']} px")
    print(f"bundle, {len(w['frames'])} frames, {n} stars, {what}, {mc['runs']} runs "
          f"({mc['cpu_per_run']:.2f} s CPU each)")
    print(f"{'parameter':24s} {'sigma CRLB':>12s} {'RMS error':>12s} {'efficiency':>11s} "
          f"{'mean sigma':>12s} {'bias/CRLB':>10s}")
    for k, name in enumerate(mc["names"]):
        c, r = mc["crlb"][k], mc["rms"][k]
        print(f"{name:24s} {c:12.4g} {r:12.4g} {c * c / (r * r):11.3f} {mc['sigma'][k]:12.4g} "
              f"{mc['mean'][k] / c:+10.2f}")
    P, runs = mc["P"], mc["runs"]
    half = 1.96 * np.sqrt(2.0 * P / runs)
    print(f"mean e' CRLB^-1 e = {np.mean(mc['efficiency_chi2']):.3f} and NEES e' P^-1 e = "
          f"{np.mean(mc['nees']):.3f} (both {P} at the bound / when sigma is honest; 95 % "
          f"interval {P - half:.2f}..{P + half:.2f}); mean variance factor "
          f"{np.mean(mc['variance_factor']):.4f}")


def main(argv: list[str] | None = None) -> int:
    """Run the Monte Carlo and print the table."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--runs", type=int, default=400)
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--noise", type=float, default=0.05, help="centroid noise, px")
    p.add_argument("--seed", type=int, default=7)
    p.add_argument("--images", action="store_true",
                   help="render each run's frames as images and extract their centroids")
    args = p.parse_args(argv)
    w = world(args.frames, args.noise)
    print_table(w, monte_carlo(w, args.runs, args.seed, args.images))
    return 0


if __name__ == "__main__":
    sys.exit(main())
