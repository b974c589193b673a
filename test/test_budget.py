"""Attitude error budget: Jacobians against finite differences, closed forms, Sun et al.'s
table (reduced), correlated sources, the command line."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stellar_cal_ros.budget.analysis import BudgetOptions, run_budget
from stellar_cal_ros.budget.propagation import (
    CONVENTIONS,
    N_PARAMETERS,
    batched_wahba,
    frame_attitude_errors,
    frame_attitude_jacobians,
    linear_star_jacobians,
    random_frames,
    ring_directions,
    star_angle_errors,
)
from stellar_cal_ros.budget.sources import (
    ARCSEC,
    error_model_from_result,
    error_model_from_spec,
    load_covariance,
    spec_camera,
)
from stellar_cal_ros.budget.truth import actual_attitude_errors, parameter_error
from stellar_cal_ros.cli import main
from stellar_cal_ros.core.attitude import wahba
from stellar_cal_ros.core.camera import CameraModel
from stellar_cal_ros.errors import ModelError
from stellar_cal_ros.io.calibration import Calibration, save_calibration

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

# A camera with every kind of term, so that no Jacobian column is trivially zero.
CAM = CameraModel(1024, 1024, 3969.0, 3970.2, 516.0, 509.0,
                  distortion=[0.13, -0.43, 5e-4, -3e-4, 0.2, 0, 0, 0, 0, 0, 0, 0, 1e-3, -2e-3])
# step per parameter for central differences (units of each parameter): large enough that
# the unprojection's 1e-10 px convergence is negligible, small enough for O(h²) truncation
STEP = np.r_[[1e-2] * 4, [1e-3] * 2, [1e-4] * 2, [1e-3] * 8, [1e-4] * 2, [1e-6] * 3]


def test_the_wahba_solver_finds_the_rotation_and_matches_scipy():
    rng = np.random.default_rng(3)
    d = rng.normal(size=(4, 6, 3))
    d /= np.linalg.norm(d, axis=2, keepdims=True)
    R_true = Rotation.random(4, random_state=4).as_matrix()
    exact = np.einsum("fij,fkj->fki", R_true, d)
    np.testing.assert_allclose(batched_wahba(d, exact), R_true, atol=1e-12)
    ref = exact + rng.normal(0, 1e-3, (4, 6, 3))
    w = rng.uniform(0.5, 2.0, (4, 6))
    R = batched_wahba(d, ref, w)
    for f in range(4):  # scipy's SVD solution is the independent reference
        scipy_R = Rotation.align_vectors(ref[f], d[f], weights=w[f])[0].as_matrix()
        np.testing.assert_allclose(R[f], scipy_R, atol=1e-12)
        np.testing.assert_array_equal(wahba(d[f], ref[f], w[f]), R[f])
    assert np.abs(batched_wahba(d, ref) - R).max() > 1e-6  # the weights changed the fit
    with pytest.raises(ModelError):
        wahba(d[0, :1], ref[0, :1])


@pytest.mark.parametrize("convention", CONVENTIONS)
def test_frame_jacobians_match_finite_differences(convention):
    rng = np.random.default_rng(5)
    field = random_frames(CAM, 3, 7, rng)
    T, W = frame_attitude_jacobians(field, CAM, convention)
    for j in range(N_PARAMETERS):
        dx = np.zeros(N_PARAMETERS)
        dx[j] = STEP[j]
        num = (frame_attitude_errors(CAM, field, dx)[convention]
               - frame_attitude_errors(CAM, field, -dx)[convention]) / (2 * STEP[j])
        scale = max(np.max(np.abs(T[:, :, j])), 1e-12)
        np.testing.assert_allclose(T[:, :, j], num, atol=1e-4 * scale, err_msg=f"column {j}")
    noise = np.zeros((3, 7, 2))
    noise[1, 4, 0] = 1e-3
    num = (frame_attitude_errors(CAM, field, np.zeros(21), noise)[convention]
           - frame_attitude_errors(CAM, field, np.zeros(21), -noise)[convention]) / 2e-3
    np.testing.assert_allclose(W[1, 4, :, 0], num[1], atol=1e-4 * np.max(np.abs(num)))
    np.testing.assert_allclose(num[[0, 2]], 0.0, atol=1e-12)


@pytest.mark.parametrize("convention", ["axis", "mounting"])
def test_star_jacobians_match_finite_differences(convention):
    d = ring_directions(np.deg2rad([1.0, 4.0, 7.0, 9.5]), np.array([0.2, 2.0, 3.5, 5.5]))
    from stellar_cal_ros.budget.propagation import radial_rows

    E, G = linear_star_jacobians(CAM, d, convention)
    R = radial_rows(d, E)
    for j in range(18):
        dx = np.zeros(N_PARAMETERS)
        dx[j] = STEP[j]
        num = (star_angle_errors(CAM, d, dx, None, convention)
               - star_angle_errors(CAM, d, -dx, None, convention)) / (2 * STEP[j])
        np.testing.assert_allclose(R[:, j], num, atol=1e-4 * max(np.max(np.abs(R[:, j])), 1e-12),
                                   err_msg=f"column {j}")


def test_closed_forms_of_each_source():
    """First principles at several incident angles: centroid σcos²θ/f, principal point
    (optical-axis reference) σsin²θ/f and (mounting) σcos²θ/f, focal length σ sin2θ/(2f),
    tilt σ sin²θ (pinhole camera, linear, averaged over the azimuth)."""
    from sun_table import linear_sigma

    spec = {"camera": {"focal_length_px": 3316.0, "width": 1024, "height": 1024},
            "sources": {"centroid": {"sigma_px": 0.05}, "principal_point": {"sigma_px": 1.5},
                        "focal_length": {"sigma_px": 0.2},
                        "image_plane_tilt": {"sigma_rad": 4e-4}}}
    model = error_model_from_spec(spec, spec_camera(spec), 8.5)
    f = 3316.0
    for deg in (2.0, 5.0, 8.5, 11.0):
        t = math.radians(deg)
        expect = {"centroid": 0.05 * math.cos(t) ** 2 / f,
                  "principal_point": 1.5 * math.sin(t) ** 2 / f,
                  "focal_length": 0.2 * math.sin(2 * t) / (2 * f),
                  "image_plane_tilt": 4e-4 * math.sin(t) ** 2}
        for src, value in expect.items():
            assert linear_sigma(model, src, deg) == pytest.approx(value / ARCSEC, rel=1e-3), \
                (src, deg)
        assert linear_sigma(model, "principal_point", deg, "mounting") == pytest.approx(
            1.5 * math.cos(t) ** 2 / f / ARCSEC, rel=1e-3)


def test_sun_table_reduced():
    """Sun et al.'s single-source table: the linear values within 0.3 % (their own Monte-Carlo
    noise is ~0.7 %), our Monte Carlo within 4 standard errors of the paper."""
    from sun_table import table

    for row in table(draws=400, seed=11):
        assert row["linear"] == pytest.approx(row["paper_sigma"], rel=3e-3), row
        assert abs(row["mc_sigma"] - row["paper_sigma"]) < 4 * row["mc_se"], row
        assert abs(row["mc_mean"]) < 4 * row["mean_se"], row


def test_monte_carlo_matches_linear_frame_budget():
    spec = {"camera": {"focal_length_px": 3316.0, "width": 1024, "height": 1024},
            "sources": {"centroid": {"sigma_px": 0.05}, "principal_point": {"sigma_px": 1.5},
                        "distortion": {"k1": 0.01, "p1": 1e-4},
                        "installation": {"sigma_arcsec": [3, 4, 5]}}}
    model = error_model_from_spec(spec, spec_camera(spec), 8.5)
    b = run_budget(model, BudgetOptions(frames=20, stars_per_frame=8, draws=300, mc_frames=20,
                                        seed=2))
    for conv in CONVENTIONS:
        for s in b["sources"]:
            lin, mc = b["frame"][conv]["linear"][s], b["frame"][conv]["mc"][s]
            # MC over 300 draws x 20 frames of a variance: a few % at most; the draws of one
            # frame share the parameter error, so allow 15 %
            assert mc["total"] == pytest.approx(lin["total"], rel=0.15, abs=1e-6), (conv, s)
    assert b["frame"]["system"]["linear"]["installation"]["roll"] == pytest.approx(5.0)
    assert b["frame"]["axis"]["linear"]["installation"]["total"] == 0.0


def _result(sigma_pp: float, rho: float) -> tuple[Calibration, tuple[list[str], np.ndarray]]:
    """A result whose principal point cx and installation ry errors have correlation rho."""
    cam = CameraModel.pinhole(1024, 1024, 3969.0)
    s_ry = sigma_pp / cam.fx  # the rotation a cx error mimics
    names = ["principal_point.cx", "installation.ry", "gyro_bias.bx"]
    C = np.array([[sigma_pp**2, rho * sigma_pp * s_ry, 0.0],
                  [rho * sigma_pp * s_ry, s_ry**2, 0.0], [0.0, 0.0, 1e-12]])
    cal = Calibration(camera=cam, installation=Rotation.identity(),
                      sigma={"camera": {"camera_matrix": {"data": [0, 0, sigma_pp, 0, 0, 0, 0,
                                                                   0, 0]}},
                             "installation": {"rotation_vector": [0.0, s_ry, 0.0]}})
    return cal, (names, C)


def test_correlated_principal_point_and_installation_cancel_in_the_system():
    cal, cov = _result(0.2, 1.0)
    full = run_budget(error_model_from_result(cal, cov), BudgetOptions(draws=0, frames=50))
    diag = run_budget(error_model_from_result(cal, None), BudgetOptions(draws=0, frames=50))
    one_axis = 0.2 / 3969.0 / ARCSEC
    # diagonal: the two add (√2 × the rotation); full covariance with ρ = 1: they cancel
    assert diag["frame"]["system"]["linear"]["total"]["y"] == pytest.approx(
        math.sqrt(2) * one_axis, rel=0.02)
    assert full["frame"]["system"]["linear"]["total"]["y"] < 0.02 * one_axis
    assert "diagonal" in diag["origin"] and "full covariance" in full["origin"]
    assert any("gyro_bias.bx" in n for n in full["notes"])


def test_parameters_held_at_the_prior_are_listed_or_included():
    cal, cov = _result(0.2, 0.5)
    prior = Calibration(camera=cal.camera, installation=Rotation.identity(),
                        sigma={"camera": {"camera_matrix": {"data": [20, 0, 20, 0, 20, 20, 0, 0,
                                                                     0]},
                                          "distortion_coefficients": {"data": [0.3, 0, 0, 0,
                                                                               2.0]}},
                               "installation": {"rotation_vector": [1e-3] * 3}})
    out = error_model_from_result(cal, cov, prior=prior)
    assert out.names == ["principal_point.cx", "installation.ry"]
    held = next(n for n in out.notes if n.startswith("not estimated"))
    assert "left out" in held and "k3 (σ 2)" in held and "cy (σ 20)" in held
    inc = error_model_from_result(cal, cov, prior=prior, unestimated="include")
    # cy, f, k1, k3, rx, rz were not estimated: added with the prior's sigma, uncorrelated
    assert set(inc.names) == {"principal_point.cx", "installation.ry", "focal_length.f", "cy",
                              "k1", "k3", "installation.rx", "installation.rz"}
    j = inc.names.index("k3")
    assert inc.covariance[j, j] == 4.0 and np.count_nonzero(inc.covariance[j]) == 1
    with pytest.raises(ModelError, match="unestimated"):
        error_model_from_result(cal, cov, prior=prior, unestimated="maybe")


def test_actual_errors_are_zero_for_a_perfect_calibration_and_follow_the_installation():
    cal, _ = _result(0.2, 0.0)
    est = Calibration(camera=cal.camera, installation=Rotation.from_rotvec([0, 0, 5 * ARCSEC]))
    np.testing.assert_allclose(parameter_error(cal, est)[18:], [0, 0, 5 * ARCSEC])
    same = actual_attitude_errors(cal, cal, 10, 6, 0)
    assert same["system"]["total"] == pytest.approx(0.0, abs=1e-6)
    act = actual_attitude_errors(cal, est, 10, 6, 0)
    assert act["system"]["roll"] == pytest.approx(5.0, rel=1e-6)
    assert act["axis"]["total"] == pytest.approx(0.0, abs=1e-6)


def test_covariance_file_errors(tmp_path):
    bad = tmp_path / "c.yaml"
    bad.write_text(json.dumps({"names": ["a", "b"], "matrix": [[1, 2], [0, 1]]}))
    with pytest.raises(ModelError, match="symmetric"):
        load_covariance(bad)
    bad.write_text(json.dumps({"names": ["a", "b"], "matrix": [1, 0, 0]}))
    with pytest.raises(ModelError, match="2x2"):
        load_covariance(bad)
    bad.write_text("names: [a]\n")
    with pytest.raises(ModelError, match="'names' and 'matrix'"):
        load_covariance(bad)


def test_cli_spec_and_result(tmp_path, capsys):
    spec = tmp_path / "spec.yaml"
    spec.write_text("camera: {focal_length_mm: 49.74, pixel_size_mm: 0.015, width: 1024, "
                    "height: 1024}\nreference_angle_deg: 8.5\nsources:\n"
                    "  centroid: {sigma_px: 0.0333333}\n  principal_point: {sigma_px: 1.5}\n")
    out = tmp_path / "b"
    assert main(["budget", "--spec", str(spec), "--draws", "20", "--frames", "10",
                 "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "principal_point" in text and "IMU-referenced system" in text
    b = json.loads((out / "budget.json").read_text())
    assert b["star"]["linear"]["centroid"] == pytest.approx(2.028, abs=1e-3)
    assert {p.name for p in out.glob("*.png")} == {"incident_angle.png", "attitude.png",
                                                    "fov_map.png"}
    # a result with its covariance sidecar, found next to it
    cal, (names, C) = _result(0.2, 0.5)
    save_calibration(cal, tmp_path / "r.yaml")
    (tmp_path / "r.covariance.yaml").write_text(json.dumps({"names": names,
                                                            "matrix": C.tolist()}))
    assert main(["budget", str(tmp_path / "r.yaml"), "--draws", "0", "--frames", "10",
                 "--no-plots"]) == 0
    assert "full covariance" in capsys.readouterr().out
    # bad input: one clear line, status 1
    spec.write_text("camera: {focal_length_px: 3000, width: 1024, height: 1024}\n"
                    "sources: {centroid: {sigma_mm: 1}}\n")
    assert main(["budget", "--spec", str(spec)]) == 1
    assert "needs exactly one of sigma_px" in capsys.readouterr().err
