"""Bundle method (issue 22.3): camera from star frames alone, on simulated frames with truth.

Every number the user reads is checked against simulation: the estimate against the truth
and the Cramér–Rao bound, its σ (NEES over Monte Carlo), the variance factor, the held-out
RMS (against the noise it must equal) and the rule that computes it.
"""

from __future__ import annotations

import copy
import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.errors import ModelError, StellarCalError
from stellar_cal_ros.methods import bundle as bd
from stellar_cal_ros.methods.bundle_bound import crlb_bundle
from stellar_cal_ros.methods.bundle_cv import held_out_frame
from stellar_cal_ros.methods.bundle_runs import run_bundle
from stellar_cal_ros.methods.frames import bag_data_from_simulation

SIGMA_PX = 0.05
BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "bundle_bound.py"


def _bench():
    spec = importlib.util.spec_from_file_location("bundle_bound", BENCH)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def bench():
    return _bench()


@pytest.fixture(scope="module")
def world(bench):
    """Noise-free frames of seven attitudes (Tan et al.'s rotations), their truth."""
    w = bench.world(n_frames=16, noise_px=SIGMA_PX)
    assert w["misfit"] < 1e-12  # the frames are exactly the model at the truth
    return w


def _noisy(frames, rng, sigma=SIGMA_PX):
    return _bench().noisy(frames, rng, sigma)


def test_bundle_at_cramer_rao_bound_with_honest_sigma(world, bench):
    """Monte Carlo (reduced form of benchmarks/bundle_bound.py): errors against the CRLB
    (efficiency) and against the reported σ (NEES), and the variance factor."""
    mc = bench.monte_carlo(world, runs=30, seed=7)
    P, runs = mc["P"], mc["runs"]
    # means of chi2(P)-distributed values: P ± 3 sqrt(2P/runs)
    tol = 3.0 * np.sqrt(2.0 * P / runs)
    assert abs(np.mean(mc["efficiency_chi2"]) - P) < tol  # at the bound
    assert abs(np.mean(mc["nees"]) - P) < tol  # σ honest
    n = sum(len(f.uv) for f in world["frames"])
    dof = 2 * n - 3 * len(world["frames"]) - P
    assert abs(np.mean(mc["variance_factor"]) - 1.0) < 3.0 * np.sqrt(2.0 / dof / runs)


def test_schur_solution_equals_dense_least_squares(world):
    """The block elimination gives scipy's dense solution and the dense covariance."""
    from scipy.optimize import least_squares

    from stellar_cal_ros.core.rotation import so3_exp

    model, theta0, sp = world["model"], world["theta"], world["sigma_prior"]
    frames = _noisy(world["frames"][:4], np.random.default_rng(3))
    Rs = world["attitudes"][:4]
    prob = bd.Bundle(model, frames, theta0, sp)
    th, R_fit, ne, _ = prob.solve(theta0, Rs)
    N = len(frames)

    def fun(x):
        phi, t = x[:3 * N].reshape(N, 3), x[3 * N:]
        r = [prob.residuals(t, so3_exp(p) @ R, f, jacobians=False)[0].ravel()
             for p, R, f in zip(phi, Rs, frames, strict=True)]
        return np.concatenate(r + [(t - theta0) / sp])

    ref = least_squares(fun, np.concatenate([np.zeros(3 * N), theta0]), x_scale="jac",
                        xtol=1e-15, ftol=1e-15, gtol=1e-15)
    sig = np.sqrt(np.diag(crlb_bundle(frames, model, th, R_fit, sp)))
    assert np.all(np.abs(ref.x[3 * N:] - th) < 1e-3 * sig)
    J = ref.jac
    dense = np.linalg.inv(J.T @ J)[3 * N:, 3 * N:]
    assert np.allclose(np.sqrt(np.diag(dense)), sig, rtol=1e-3)


def test_held_out_rule_rejects_beyond_five_medians_and_scores_in_arcsec():
    """The contract's rule on a pinhole with one misidentified star."""
    from stellar_cal_ros.core.rotation import so3_exp

    rng = np.random.default_rng(0)
    f = 2000.0
    d = np.column_stack([rng.uniform(-0.1, 0.1, (30, 2)), np.ones(30)])
    u_i = d / np.linalg.norm(d, axis=1, keepdims=True)
    R_true = so3_exp(np.array([0.3, -0.2, 0.1]))

    def predict(R):
        c = u_i @ R
        return f * c[:, :2] / c[:, 2:] + 500.0

    uv = predict(R_true) + 0.1 * rng.standard_normal((30, 2))
    uv[5] += 40.0  # a wrong identity
    score = held_out_frame(predict, so3_exp(np.array([1e-3, 0, 0])) @ R_true, uv,
                           (1 / f, 1 / f))
    assert score.rejected == 1 and not score.scored[5]
    res = score.residuals[score.scored]
    expect = np.sqrt(np.mean(np.sum((res / f) ** 2, axis=1))) / ARCSEC
    assert score.rms_arcsec == pytest.approx(expect, rel=1e-12)
    # the attitude fit does not see the wrong star: the rest scatter as the noise does
    assert 0.7 < score.rms_arcsec / (np.sqrt(2) * 0.1 / f / ARCSEC) < 1.3


def _with_noise(world, seed, stated=SIGMA_PX):
    """The world's frames with SIGMA_PX noise drawn from ``seed`` and ``stated`` as their σ."""
    data = copy.copy(world["data"])
    rng = np.random.default_rng(seed)
    data.frames = []
    for fr in world["data"].frames:
        g = copy.copy(fr)
        g.uv = fr.uv + SIGMA_PX * rng.standard_normal(fr.uv.shape)
        g.sigma = np.full(len(fr.uv), stated)
        data.frames.append(g)
    return data


def test_bundle_run_recovers_truth_and_held_out_rms_equals_noise(world):
    """One run: estimate within 4σ of the truth, held-out RMS the noise's (arcsec)."""
    data = _with_noise(world, seed=11)
    res = run_bundle(data, world["sim"].prior, ["tangential"])
    z = (res.theta - world["theta"]) / res.sigma
    assert np.all(np.abs(z) < 4.0), dict(zip(res.parameter_names, z, strict=True))
    cv = res.cross_validation
    assert len(cv["held_out_rms_arcsec"]) == len(cv["rejected"]) == len(data.frames)
    # held-out residual: noise of 2 axes, less the 3 attitude dof, plus the fold camera error
    n = np.array(cv["stars"])
    f = res.calibration.camera.fx
    expect = np.sqrt(np.mean(2 * SIGMA_PX ** 2 * (1 - 1.5 / n))) / f / ARCSEC
    assert cv["mean_arcsec"] == pytest.approx(expect, rel=0.12)
    assert sum(cv["rejected"]) <= 2
    assert res.calibration.extra["cross_validation"] == cv
    assert res.variance_factor == pytest.approx(1.0, abs=0.15)


def test_the_diagnosis_noise_scale_reaches_the_bundle(world):
    """A σ stated 0.6x the true noise: the bundle's variance factor is ~1/0.36; with the
    scale the diagnosis measures (star = 1/0.6, ``run_for_diagnosis(noise=)``) it is ~1."""
    from stellar_cal_ros.core.noise import NoiseScales

    data = _with_noise(world, seed=12, stated=0.6 * SIGMA_PX)
    stated = run_bundle(data, world["sim"].prior, [], cross_validate=False)
    scaled = run_bundle(data, world["sim"].prior, [], cross_validate=False,
                        noise=NoiseScales(star=1 / 0.6))
    assert stated.variance_factor == pytest.approx(1 / 0.36, rel=0.15)
    assert scaled.variance_factor == pytest.approx(1.0, abs=0.15)


def test_wrong_identities_are_left_out(world):
    """Stars labelled as another star are gated and counted; the estimate stays unbiased."""
    data = copy.copy(world["data"])
    rng = np.random.default_rng(5)
    data.frames = []
    n_bad = 0
    for fr in world["data"].frames:
        g = copy.copy(fr)
        g.uv = fr.uv + SIGMA_PX * rng.standard_normal(fr.uv.shape)
        g.sigma = np.full(len(fr.uv), SIGMA_PX)
        ra, dec = g.right_ascension.copy(), g.declination.copy()
        k = rng.permutation(len(ra))[:2]  # swap two stars' identities (inside the field)
        ra[k], dec[k] = ra[k[::-1]], dec[k[::-1]]
        g.right_ascension, g.declination = ra, dec
        n_bad += 2
        data.frames.append(g)
    res = run_bundle(data, world["sim"].prior, ["tangential"], cross_validate=False)
    rejected = res.counts.stars_misidentified + res.counts.stars_outliers
    assert n_bad <= rejected <= n_bad + 3
    z = (res.theta - world["theta"]) / res.sigma
    assert np.all(np.abs(z) < 4.0)


def test_effects_the_bundle_cannot_see_are_refused(world):
    prior = world["sim"].prior
    for eid in ("installation", "time_offset", "gyro_bias"):
        with pytest.raises(ModelError, match="cannot see"):
            bd.make_model(prior, [eid])
    data = copy.copy(world["data"])
    data.site = None
    with pytest.raises(ModelError, match="needs the site"):
        run_bundle(data, prior, ["refraction"], cross_validate=False)
    data.frames = data.frames[:1]
    with pytest.raises(StellarCalError, match="at least 2 star frames"):
        run_bundle(data, prior, [], cross_validate=False)


def test_cli_batch_bundle_writes_the_contract_result(tmp_path, capsys):
    """``stellar-cal batch --method bundle`` end to end, and its one-line errors (the CLI
    in-process: no interpreter start-up)."""
    from sim_bags import simulated_bag

    from stellar_cal_ros.cli import main

    bag, prior, _ = simulated_bag("psce_rotations", 8.0)
    out = tmp_path / "bundle.yaml"
    run = ["batch", str(bag), "--method", "bundle", "--prior", str(prior), "-o", str(out), "-q"]
    capsys.readouterr()
    rc = main(run + ["--effects", "tangential"])
    proc = capsys.readouterr()
    assert rc == 0, proc.err[-2000:]
    assert "held-out RMS" in proc.out
    doc = yaml.safe_load(out.read_text())
    assert doc["method"] == "bundle"
    cv = doc["cross_validation"]
    assert set(cv) >= {"held_out_rms_arcsec", "mean_arcsec", "rejected"}
    assert len(cv["held_out_rms_arcsec"]) == len(cv["rejected"]) == 16
    assert cv["mean_arcsec"] == pytest.approx(np.mean(cv["held_out_rms_arcsec"]))
    assert doc["sigma"]["camera"]["camera_matrix"]["data"][0] > 0
    assert (tmp_path / "bundle.covariance.yaml").exists()
    assert main(run + ["--effects", "installation"]) == 1
    bad = capsys.readouterr()
    assert bad.err.strip().count("\n") == 0 and "cannot see" in bad.err


def _every_25th(world, seed, stated=None):
    """The bag's every 25th frame (32 frames, seven attitudes), noise SIGMA_PX drawn with
    ``seed``; ``stated``: the messages' σ is that factor of it (default: as simulated)."""
    data = bag_data_from_simulation(world["sim"])
    rng = np.random.default_rng(seed)
    frames = []
    for fr in data.frames[::25]:
        g = copy.copy(fr)
        g.uv = fr.uv + SIGMA_PX * rng.standard_normal(fr.uv.shape)
        if stated is not None:
            g.sigma = np.full(len(fr.uv), stated * SIGMA_PX)
        frames.append(g)
    data.frames = frames
    return data


def test_diagnose_bundle_names_the_missing_effect(world, tmp_path):
    """The loop on star frames: tangential distortion missing from the model is found from
    held-out residuals, and adding it lowers the held-out RMS; effects the bundle cannot see
    are not applicable."""
    from stellar_cal_ros.diagnosis.run import diagnose

    r = world["sim"]
    data = _every_25th(world, 2)
    start = run_bundle(data, r.prior, [], cross_validate=False).calibration
    summary = diagnose(data, start, "bundle", [], tmp_path, plots=False, verbose=False,
                       candidates=["tangential", "pixel_aspect", "radial_k3", "installation",
                                   "time_offset"])
    assert summary["recommendation"] == "tangential"
    top = summary["candidates"][0]
    assert top["effect"] == "tangential" and top["p_value"] < 1e-3
    assert np.hypot(*top["rms_after_px"]) < np.hypot(*summary["residual_rms_px"])
    na = {c["effect"] for c in summary["not_applicable"]}
    assert {"installation", "time_offset"} <= na
    # held-out residuals at the noise the messages state, once tangential is in
    assert np.hypot(*top["rms_after_px"]) == pytest.approx(np.sqrt(2) * SIGMA_PX, rel=0.1)


@pytest.mark.parametrize("stated", [0.6, 1.0])
def test_discover_bundle_says_the_stars_sigma_its_fit_measured(world, tmp_path, stated):
    """A camera-only diagnosis says the σ its batch fit measured (the variance factor's
    root, with its σ), not "noise not measured (--noise stated)" (unseen case
    ``bundle_s06``): the messages' σ 0.6x the true noise reads x1/0.6 within 3σ, right σ
    reads "noise as stated"."""
    from stellar_cal_ros.diagnosis.run import diagnose

    r = world["sim"]
    data = _every_25th(world, 3, stated)
    start = run_bundle(data, r.prior, ["tangential"], cross_validate=False).calibration
    s = diagnose(data, start, "bundle", ["tangential"], tmp_path, plots=False, verbose=False,
                 candidates=["pixel_aspect"])
    noise = s["noise"]
    k, sk = noise["star_sigma_scale"], noise["sigma"]["star_sigma_scale"]
    assert noise["measured"]["star_sigma_scale"] and 0 < sk < 0.05 * k
    assert abs(k - 1.0 / stated) < 3 * sk, (k, sk)
    assert noise["applied"]["star_sigma_scale"] == k
    line = " ".join(noise["verdict"])
    assert "--noise stated" not in line
    assert ("too small" in line and noise["rescaled"]) if stated < 1 else \
        ("noise as stated" in line and not noise["rescaled"]), line


def test_frame_of_another_focus_is_named(world):
    """A frame taken at another focal length (0.2 % here) is named, the others are not."""
    data = copy.copy(world["data"])
    rng = np.random.default_rng(4)
    data.frames = []
    for k, fr in enumerate(world["data"].frames[:8]):
        g = copy.copy(fr)
        g.uv = fr.uv + SIGMA_PX * rng.standard_normal(fr.uv.shape)
        if k == 5:
            g.uv = 511.5 + 1.002 * (g.uv - 511.5)
        g.sigma = np.full(len(fr.uv), SIGMA_PX)
        data.frames.append(g)
    res = run_bundle(data, world["sim"].prior, ["tangential"])
    nis = res.cross_validation["nis_per_dof"]
    assert [r.split(" does not")[0] for r in res.degraded] == ["frame 5"], res.degraded
    assert max(np.delete(nis, 5)) < 2.0 < 10.0 < nis[5]


def test_bundle_from_rendered_images(world, bench):
    """Frames rendered as 12-bit images and centroided by the project's extractor: the
    camera within 4 σ of the truth, and the extractor's σ honest to a factor 1.5 (the fit's
    variance factor; benchmarks/bundle_bound.py --images: 1.006 over 40 runs)."""
    model, theta, sp = world["model"], world["theta"], world["sigma_prior"]
    cam = world["sim"].prior.camera
    frames = bench.rendered(world["frames"][:8], np.random.default_rng(3),
                            (cam.width, cam.height))
    assert sum(len(f.uv) for f in frames) >= 0.9 * sum(len(f.uv) for f in
                                                       world["frames"][:8])
    fit, n_out = bd.fit_bundle(model, frames, theta, world["attitudes"][:8], theta, sp)
    cov, s2 = fit.covariance()
    z = (fit.theta - theta) / np.sqrt(np.diag(cov))
    assert np.all(np.abs(z) < 4.0), z
    assert 1 / 1.5 ** 2 < s2 < 1.5 ** 2 and n_out <= 2


@pytest.fixture(scope="module")
def sky():
    """32 frames of a sky with refraction and aberration (site, stamps and weather in the
    bag) and the rotation sequence's tangential distortion, 0.05 px noise."""
    from stellar_cal_ros.methods.frames import bag_data_from_simulation
    from stellar_cal_ros.sim.scenarios import get_scenario
    from stellar_cal_ros.sim.world import simulate

    r = simulate(get_scenario("psce_rotations"), duration=400, seed=2,
                 effects={"refraction": [1.0], "aberration": [1.0]})
    data = bag_data_from_simulation(r)
    data.frames = data.frames[::25]
    return r, data


def test_refraction_and_aberration_from_site_and_time(sky):
    """Apparent place from the bag's site, stamps and weather: with refraction in the sky,
    its scale is estimated at 1 (physics), aberration's too, and the held-out RMS falls."""
    r, data = sky
    without = run_bundle(data, r.prior, ["tangential"])
    res = run_bundle(data, r.prior, ["tangential", "refraction", "aberration"])
    for eid in ("refraction", "aberration"):
        k = res.parameter_names.index(f"{eid}.scale")
        assert abs(res.theta[k] - 1.0) < 3.0 * res.sigma[k], (eid, res.theta[k], res.sigma[k])
    k = res.parameter_names.index("refraction.scale")
    assert res.sigma[k] < 0.1
    assert res.cross_validation["mean_arcsec"] < 0.95 * without.cross_validation["mean_arcsec"]
    assert without.variance_factor > 1.15 > 1.1 > res.variance_factor


def test_discover_bundle_adds_the_missing_effects_and_the_error_falls(sky, tmp_path):
    """The whole loop on star frames (discover --method bundle from the baseline): it adds
    refraction and tangential distortion — what the sky and the camera have beyond the
    baseline and the data can detect (aberration's scale has σ 0.45 here) — and stops, the
    held-out RMS falling round by round to the noise."""
    from stellar_cal_ros.diagnosis.run import diagnose

    r, data = sky
    start = run_bundle(data, r.prior, [], cross_validate=False).calibration
    s = diagnose(data, start, "bundle", [], tmp_path, plots=False, verbose=False, auto=True,
                 workers=0)
    assert s["added"] == ["refraction", "tangential"], s["added"]
    rms = [np.hypot(*step["rms_px"]) for step in s["path"]]
    assert rms[0] > rms[1] > rms[2]
    assert rms[2] == pytest.approx(np.sqrt(2) * SIGMA_PX, rel=0.05)
    scale = s["final_estimates"]["refraction"]["scale"]
    assert abs(scale[0] - 1.0) < 3 * scale[1]
    cv = yaml.safe_load((tmp_path / "calibration.yaml").read_text())["cross_validation"]
    assert cv["mean_arcsec"] < 3.8


def test_fold_camera_is_the_refit_without_the_frame(world):
    """The cross-validation's camera of each fold (one Gauss–Newton step on the normal
    equations without the frame) is the converged fit of the other frames, to 0.01 σ."""
    model, sp = world["model"], world["sigma_prior"]
    frames = _noisy(world["frames"][:10], np.random.default_rng(1))
    fit, _ = bd.fit_bundle(model, frames, world["theta"], world["attitudes"][:10],
                           world["theta"], sp)
    sig = np.sqrt(np.diag(fit.covariance()[0]))
    full = bd.Bundle(model, frames, world["theta"], sp)
    ne = full.normal(fit.theta, fit.attitudes)
    schur = bd.Bundle.schur(ne, 0.0)
    for k in (0, 4, 9):
        dtheta, cov, s2 = full.without_frame(ne, schur, k)
        others = [f for j, f in enumerate(frames) if j != k]
        b = bd.Bundle(model, others, world["theta"], sp)
        th, R, ne_k, it = b.solve(fit.theta, [R for j, R in enumerate(fit.attitudes)
                                              if j != k], tol=1e-10)
        assert np.all(np.abs(fit.theta + dtheta - th) < 0.01 * sig)
        ref_cov, ref_s2 = bd.Fit(th, R, ne_k, b, it).covariance()
        assert s2 == pytest.approx(ref_s2, rel=0.02)
        assert np.allclose(np.sqrt(np.diag(cov)), np.sqrt(np.diag(ref_cov)), rtol=0.02)


def test_star_only_bag_batch_and_report(world, tmp_path, capsys):
    """A bag of star frames alone (no IMU, as ``solve`` writes): batch and report run on it
    (the report re-runs the bundle: held-out residuals); replay refuses it in one line."""
    from stellar_cal_ros.cli import main
    from stellar_cal_ros.io.bag import BagWriter
    from stellar_cal_ros.io.calibration import save_calibration

    bag, prior = tmp_path / "stars.mcap", tmp_path / "prior.yaml"
    rng = np.random.default_rng(8)
    with BagWriter(bag) as w:
        for fr in world["data"].frames[:6]:
            g = copy.copy(fr)
            g.uv = fr.uv + SIGMA_PX * rng.standard_normal(fr.uv.shape)
            w.write_star_frame(g, "/star_tracker/stars")
    save_calibration(world["sim"].prior, prior)

    def run(*args) -> int:
        return main([str(a) for a in args])

    assert run("batch", bag, "--method", "bundle", "--prior", prior, "-q", "-o",
               tmp_path / "a.yaml") == 0
    # the report re-runs the result's method on the bag (compare reads the bag the same way)
    assert run("report", tmp_path / "a.yaml", "--bag", bag, "-o", tmp_path / "rep") == 0
    assert (tmp_path / "rep" / "report.html").exists()
    capsys.readouterr()
    assert run("replay", bag, "--method", "psce", "--prior", prior, "-o",
               tmp_path / "c.yaml") == 1
    # (the one-line notice that a first run compiles the kernels is not the error)
    err = "\n".join(x for x in capsys.readouterr().err.strip().splitlines()
                    if not x.startswith("first run here:"))
    assert err.count("\n") == 0 and "/imu/data" in err, err


def test_every_camera_and_direction_effect_runs(world):
    """Every library effect of the stages a free attitude per frame sees is estimable at
    once (finite σ, no more than its prior's), the others refused."""
    from stellar_cal_ros.effects import registry

    seen = [e for e in registry.available()
            if registry.EFFECTS[e].stage in bd.STAGES and e not in bd.BASELINE_EFFECTS]
    assert {"pixel_aspect", "radial_k3", "tangential", "image_plane_tilt",
            "thermal_focal_length", "aberration", "refraction", "proper_motion"} <= set(seen)
    data = copy.copy(world["data"])
    rng = np.random.default_rng(6)
    data.frames = []
    for fr in world["data"].frames[:8]:
        g = copy.copy(fr)
        g.uv = fr.uv + SIGMA_PX * rng.standard_normal(fr.uv.shape)
        data.frames.append(g)
    res = run_bundle(data, world["sim"].prior, seen, cross_validate=False)
    assert [e.id for e in res.model.effects if e.id in seen] == [
        e for e in registry.available() if e in seen]
    assert np.all(np.isfinite(res.sigma)) and np.all(res.sigma <= 1.0001 * res.sigma_prior)


def test_a_twin_of_a_camera_only_bag_is_rendered_for_the_bundle(world):
    """The probe's twin of a bundle bag (discover's printed biases are measured on it): the
    bundle has no filter configuration; the twin took it from there and failed ("'NoneType'
    object is not callable", unseen case ``bundle_s06``).  Its stars are the bag's."""
    from stellar_cal_ros.diagnosis.reliability_probe import rendered_stars
    from stellar_cal_ros.diagnosis.twin import twin_scene

    data = _every_25th(world, 4)
    cal = run_bundle(data, world["sim"].prior, ["tangential"], cross_validate=False).calibration
    scene = twin_scene(data, cal, "bundle", imu=False)
    twin = rendered_stars(data, cal, "bundle", scene=scene, imu=False).stars
    assert len(twin.live) == len(data.frames) and twin.keep.mean() > 0.95
    assert np.isfinite(twin.uv).all()
    # noiseless at the bundle's camera; the attitude from the IMU and the installation the
    # bundle does not estimate (the prior's): each frame's stars one shift from the bag's
    uv = np.concatenate([f.uv for f in data.frames])[scene.stars.usable]
    frame = np.repeat(np.arange(len(twin.count)), twin.count)
    d = twin.uv - uv
    for k in np.unique(frame[twin.keep]):
        rows = twin.keep & (frame == k)
        d[rows] -= np.median(d[rows], axis=0)
    assert np.sqrt(np.mean(d[twin.keep] ** 2)) < 3 * SIGMA_PX
