"""Result files other tools load, the report pages, the progress lines and the CLI help.

* the result says which effects it estimated; its sigma block holds those only; the full
  covariance is a sidecar read back exactly;
* Kalibr / OpenVINS / camera_info exports are read back by their documented keys — the
  OpenVINS file with OpenCV's FileStorage (what OpenVINS reads it with), the camera_info
  file with a re-implementation of camera_calibration_parsers' readCalibrationYml — and
  their projection reproduces the calibrated model's;
* report / compare write their figures and one page; progress prints complete lines.
"""

from __future__ import annotations

import copy
import dataclasses
import io
import json
import logging

import numpy as np
import pytest
import yaml

from stellar_cal_ros.cli import build_parser, load_prior, main
from stellar_cal_ros.effects import registry
from stellar_cal_ros.errors import CalibrationFileError, StellarCalError
from stellar_cal_ros.io.calibration import (
    load_calibration,
    load_covariance,
    prior_warnings,
    save_calibration,
    store_estimate,
)
from stellar_cal_ros.io.covariance_file import covariance_path
from stellar_cal_ros.io.export import export_calibration, max_displacement_px
from stellar_cal_ros.methods.star_model import StarModel
from stellar_cal_ros.progress import Progress, format_seconds, progress
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate, write_simulation

ESTIMATED = ["installation", "principal_point", "focal_length", "radial_k1k2", "gyro_bias"]


@pytest.fixture(scope="module")
def sim():
    # 60 s: the report/compare tests check pages, plots and the model diff, no statistic
    return simulate(get_scenario("psce_rotations"), duration=60.0, seed=4,
                    effects={"time_offset": 0.01})


@pytest.fixture(scope="module")
def result(sim):
    """A result in the estimated-only layout, with a distorted, tilted truth camera."""
    prior = copy.deepcopy(sim.prior)
    prior.sigma["camera"]["distortion_coefficients"]["data"][4] = 2.0  # k3 σ (not estimated)
    model = StarModel(registry.create_many(ESTIMATED), prior)
    theta = model.initial_value + 1e-3 * model.initial_sigma
    return store_estimate(prior, model.effects, model.slices, theta, 0.5 * model.initial_sigma,
                          "psce", 1.8e9), model


# ------------------------------------------------------------------------------ result file
def test_sigma_holds_only_estimated_quantities(result, tmp_path):
    cal, model = result
    assert cal.estimated == [e.id for e in model.effects] and set(cal.estimated) == set(ESTIMATED)
    assert "time_offset" not in cal.sigma and "accelerometer" not in cal.sigma
    d = cal.sigma["camera"]["distortion_coefficients"]["data"]
    assert d[4] == 0.0 and d[0] > 0  # k3 not estimated: 0, not the prior's 2.0
    s = cal.sigma["camera"]["camera_matrix"]["data"]
    assert s[2] == pytest.approx(0.5 * model.initial_sigma[model.slices["principal_point"]][0])
    save_calibration(cal, tmp_path / "r.yaml")
    doc = yaml.safe_load((tmp_path / "r.yaml").read_text())
    assert doc["estimated"] == cal.estimated
    assert list(doc).index("estimated") == list(doc).index("sigma") - 1
    assert load_calibration(tmp_path / "r.yaml") == cal
    with pytest.raises(CalibrationFileError, match="estimated"):
        bad = dict(doc, estimated="installation")
        (tmp_path / "bad.yaml").write_text(yaml.safe_dump(bad))
        load_calibration(tmp_path / "bad.yaml")


def test_covariance_sidecar_round_trip(result, tmp_path):
    cal, model = result
    cal = dataclasses.replace(cal, estimated=[])
    rng = np.random.default_rng(1)
    a = rng.normal(size=(model.size, model.size))
    cov = a @ a.T * 1e-6
    out = tmp_path / "res.yaml"
    save_calibration(cal, out, covariance=(model.parameter_names(), cov))
    side = covariance_path(out)
    assert side == tmp_path / "res.covariance.yaml" and side.is_file()
    back = load_calibration(out)
    assert back.extra["covariance_file"] == side.name
    assert back.estimated == [e.id for e in model.effects]  # from the covariance's names
    c = load_covariance(out)
    assert c.names == model.parameter_names()
    np.testing.assert_array_equal(c.matrix, cov)
    assert c.units[:3] == ["rad"] * 3 and c.units[model.parameter_names().index(
        "principal_point.cx")] == "px"
    np.testing.assert_allclose(c.sigma, np.sqrt(np.diag(cov)))
    assert np.allclose(np.diag(c.correlation()), 1.0)
    with pytest.raises(CalibrationFileError, match="shape"):
        save_calibration(cal, out, covariance=(model.parameter_names()[:2], cov))
    save_calibration(cal, tmp_path / "plain.yaml")
    with pytest.raises(CalibrationFileError, match="no covariance_file"):
        load_covariance(tmp_path / "plain.yaml")


def test_prior_sigma_problems_are_warned_one_line_each(sim, tmp_path, caplog):
    prior = copy.deepcopy(sim.prior)
    assert prior_warnings(prior) == []
    prior.sigma["camera"]["distortion_coefficients"]["data"][1] = -0.1
    prior.sigma["camera"]["camera_matrix"]["data"][2] = float("nan")
    w = prior_warnings(prior, "p.yaml")
    assert len(w) == 2
    assert any("distortion_coefficients.data[1] = -0.1 is negative" in x for x in w)
    assert any("camera_matrix.data[2] is NaN" in x for x in w)
    save_calibration(prior, tmp_path / "p.yaml")
    with caplog.at_level(logging.WARNING, logger="stellar_cal_ros"):
        load_prior(tmp_path / "p.yaml")
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 3 and "2 problems (above)" in lines[-1]
    prior.sigma = {}
    assert len(prior_warnings(prior)) == 1 and "no 'sigma' block" in prior_warnings(prior)[0]


# ------------------------------------------------------------------------------ exports
def _radtan_project(d_cam, intr, coeffs):
    """Kalibr's pinhole-radtan model, written from its documentation."""
    x, y = d_cam[:, 0] / d_cam[:, 2], d_cam[:, 1] / d_cam[:, 2]
    k1, k2, r1, r2 = coeffs
    r2_ = x * x + y * y
    radial = 1 + k1 * r2_ + k2 * r2_ * r2_
    xd = x * radial + 2 * r1 * x * y + r2 * (r2_ + 2 * x * x)
    yd = y * radial + r1 * (r2_ + 2 * y * y) + 2 * r2 * x * y
    fu, fv, pu, pv = intr
    return np.stack([fu * xd + pu, fv * yd + pv], 1)


def _directions_imu(cal, n=50, seed=0):
    """IMU-frame directions of stars spread over the detector."""
    cam = cal.camera
    rng = np.random.default_rng(seed)
    uv = rng.uniform([20, 20], [cam.width - 20, cam.height - 20], size=(n, 2))
    return (cal.R_imu_st @ cam.unproject(uv).T).T


def test_kalibr_file_by_its_documented_keys(result):
    cal, _ = result
    cal = dataclasses.replace(cal, time_offset=0.0123)
    ex = export_calibration(cal, "kalibr", rostopic="/cam/image")
    doc = yaml.safe_load(ex.text)["cam0"]
    T = np.array(doc["T_cam_imu"])
    assert T.shape == (4, 4) and np.allclose(T[3], [0, 0, 0, 1]) and np.all(T[:3, 3] == 0)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    assert doc["timeshift_cam_imu"] == 0.0123  # t_imu = t_cam + shift
    assert doc["camera_model"] == "pinhole" and doc["distortion_model"] == "radtan"
    assert doc["resolution"] == [cal.camera.width, cal.camera.height]
    assert doc["rostopic"] == "/cam/image" and doc["cam_overlaps"] == []
    # a star seen from the IMU lands where our model puts it
    d_imu = _directions_imu(cal)
    uv_kalibr = _radtan_project((T[:3, :3] @ d_imu.T).T, doc["intrinsics"],
                                doc["distortion_coeffs"])
    uv_ours = cal.camera.project((cal.R_imu_st.T @ d_imu.T).T)
    assert np.max(np.abs(uv_kalibr - uv_ours)) < 1e-6
    assert any("translation set to 0" in w for w in ex.warnings)
    assert any("gyro bias" in w for w in ex.warnings)


def test_openvins_file_reads_with_opencv_filestorage(result, tmp_path):
    cv2 = pytest.importorskip("cv2")
    cal, _ = result
    ex = export_calibration(cal, "openvins")
    path = tmp_path / "kalibr_imucam_chain.yaml"
    path.write_text(ex.text)
    assert ex.text.startswith("%YAML:1.0\n")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    node = fs.getNode("cam0")
    T = np.array([[node.getNode("T_imu_cam").at(i).at(j).real() for j in range(4)]
                  for i in range(4)])
    np.testing.assert_allclose(T[:3, :3], cal.R_imu_st, atol=1e-15)  # camera → IMU
    intr = [node.getNode("intrinsics").at(i).real() for i in range(4)]
    assert intr == [cal.camera.fx, cal.camera.fy, cal.camera.cx, cal.camera.cy]
    assert node.getNode("distortion_model").string() == "radtan"
    assert node.getNode("timeshift_cam_imu").real() == cal.time_offset
    assert [node.getNode("resolution").at(i).real() for i in range(2)] == [1024, 1024]
    fs.release()


def read_calibration_yml(text: str) -> dict:
    """camera_calibration_parsers' readCalibrationYml (ROS 2 image_common), in Python.

    camera_name optional ("unknown"); image_width / image_height; camera_matrix,
    rectification_matrix, projection_matrix as {rows, cols, data} of fixed sizes (3×3, 3×3,
    3×4: the C++ asserts them); distortion_model (absent: plumb_bob); distortion_coefficients
    of rows × cols values.
    """
    doc = yaml.safe_load(text)

    def matrix(key, rows, cols):
        m = doc[key]
        assert (int(m["rows"]), int(m["cols"])) == (rows, cols), key
        return [float(m["data"][i]) for i in range(rows * cols)]

    d = doc["distortion_coefficients"]
    n = int(d["rows"]) * int(d["cols"])
    return {"camera_name": doc.get("camera_name", "unknown"),
            "width": int(doc["image_width"]), "height": int(doc["image_height"]),
            "k": matrix("camera_matrix", 3, 3), "r": matrix("rectification_matrix", 3, 3),
            "p": matrix("projection_matrix", 3, 4),
            "distortion_model": doc.get("distortion_model", "plumb_bob"),
            "d": [float(d["data"][i]) for i in range(n)]}


def test_camera_info_reads_as_camera_calibration_parsers_does(result):
    cal, _ = result
    info = read_calibration_yml(export_calibration(cal, "camera_info").text)
    cam = cal.camera
    assert info["width"] == cam.width and info["camera_name"] == cam.name
    assert info["k"] == [cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1]
    assert info["p"] == [cam.fx, 0, cam.cx, 0, 0, cam.fy, cam.cy, 0, 0, 0, 1, 0]
    assert info["distortion_model"] == "plumb_bob"
    assert info["d"] == list(cam.distortion[:5])
    # k4..k6 → rational_polynomial (8); s1 and the tilt cannot go: warned with their size
    d = np.array(cam.distortion)
    d[5], d[8], d[12] = 1e-3, 1e-4, 2e-3
    wide = dataclasses.replace(cal, camera=dataclasses.replace(cam, distortion=d),
                               effects={"thermal_focal_length": {"coefficient_per_c": 1e-5}})
    ex = export_calibration(wide, "camera_info")
    info = read_calibration_yml(ex.text)
    assert info["distortion_model"] == "rational_polynomial" and len(info["d"]) == 8
    assert info["d"][5] == 1e-3
    text = "\n".join(ex.warnings)
    assert "s1=0.0001" in text and "tau_x=0.002 rad" in text
    assert "thermal_focal_length" in text and "installation R_imu_st" in text
    px = max_displacement_px(wide.camera, dataclasses.replace(
        cam, distortion=np.r_[d[:8], np.zeros(6)]))
    # a 2 mrad tilt moves the corners by about τ·r²/f = 2e-3 · 724² / 3969 ≈ 0.26 px
    assert 0.1 < px < 0.5 and f"{px:.3f} px" in text


def test_kalibr_warns_about_the_tilt_it_cannot_hold(result):
    cal, _ = result
    d = np.array(cal.camera.distortion)
    d[12] = 1e-3
    tilted = dataclasses.replace(cal, camera=dataclasses.replace(cal.camera, distortion=d))
    ex = export_calibration(tilted, "kalibr")
    assert any("image_plane_tilt tau_x=0.001 rad" in w for w in ex.warnings)
    assert any("differs from the calibrated one by up to" in w for w in ex.warnings)
    with pytest.raises(StellarCalError, match="unknown export format"):
        export_calibration(cal, "colmap")


def test_cli_export(result, tmp_path, capsys, caplog):
    cal, _ = result
    save_calibration(cal, tmp_path / "r.yaml")
    with caplog.at_level(logging.WARNING, logger="stellar_cal_ros"):
        assert main(["export", str(tmp_path / "r.yaml"), "--format", "kalibr"]) == 0
    out = tmp_path / "r-camchain-imucam.yaml"
    assert out.is_file() and f"wrote {out}" in capsys.readouterr().out
    assert any("translation set to 0" in r.getMessage() for r in caplog.records)
    assert main(["export", str(tmp_path / "r.yaml"), "--format", "camera_info", "-o",
                 str(tmp_path / "ci.yaml")]) == 0
    read_calibration_yml((tmp_path / "ci.yaml").read_text())


# ------------------------------------------------------------------------------ progress
class _Pipe(io.StringIO):
    def isatty(self):
        return False


def test_progress_prints_complete_lines_off_a_terminal():
    s = _Pipe()
    with progress(50, "replay", unit="frames", stream=s) as p:
        for k in range(50):
            if k == 20:
                p.note("candidate 21/50: time_offset")
            p.update(1)
    text = s.getvalue()
    assert "\r" not in text and text.endswith("\n")
    lines = text.splitlines()
    assert [ln.split(":")[1].split("%")[0].strip() for ln in lines if "%" in ln] == [
        str(x) for x in range(10, 100, 10)]
    note = next(ln for ln in lines if ln.startswith("candidate"))
    assert note.startswith("candidate 21/50: time_offset, ETA ")
    assert lines[-1].startswith("replay: done (50/50 frames) in ")
    quiet = _Pipe()
    with progress(10, "x", stream=quiet, enabled=False) as p:
        p.update(10)
        p.note("hidden")
    assert quiet.getvalue() == ""
    assert Progress(0, "x", stream=_Pipe(), mode="off").eta() != Progress(0, "x").eta()
    assert format_seconds(75) == "1 min 15 s" and format_seconds(float("nan")) == "?"
    # work that stopped on an error is not "done": the command says the error in one line
    # (coord 0e2fd9e: `batch` of a bag it could not read printed "acf: done (0/5 stages)")
    failed = _Pipe()
    with pytest.raises(ValueError), progress(5, "acf", unit="stages", stream=failed) as p:
        p.note("acf stage 1/5: read the bag", eta=False)
        raise ValueError("the bag")
    assert failed.getvalue() == "acf stage 1/5: read the bag\n"


# ------------------------------------------------------------------------------ CLI help
def test_every_argument_has_help_and_methods_are_validated(capsys):
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    for name, p in sub.choices.items():
        for a in p._actions:
            if a.dest != "help":
                assert a.help, f"{name} {a.option_strings or a.dest} has no help"
    with pytest.raises(SystemExit) as e:
        main(["diagnose", "x.mcap", "--calibration", "c.yaml", "--method", "kalman", "-o", "d"])
    assert e.value.code == 2 and "invalid choice: 'kalman'" in capsys.readouterr().err


# ------------------------------------------------------------------------------ reports
@pytest.fixture(scope="module")
def two_runs(sim, tmp_path_factory):
    d = tmp_path_factory.mktemp("runs")
    paths = write_simulation(sim, d / "sim.mcap")
    bag, prior = str(paths["bag"]), str(paths["prior"])
    assert main(["replay", bag, "--method", "psce", "--prior", prior, "-o", str(d / "a.yaml"),
                 "--residuals", str(d / "a.csv"), "-q"]) == 0
    assert main(["replay", bag, "--method", "psce", "--prior", prior, "--effects",
                 "time_offset", "-o", str(d / "b.yaml"), "--residuals", str(d / "b.csv"),
                 "-q"]) == 0
    return d


def test_report_of_one_run(two_runs, tmp_path):
    d = two_runs
    summary = {"candidates": [], "unexplained": [
        {"regressor": "angular rate", "component": "size", "statistic": 12.0,
         "p_value": 1e-9, "change_px": 0.3},
        {"regressor": "radius", "component": "radial", "statistic": -4.0, "p_value": 1e-3,
         "change_px": 0.01}]}
    (tmp_path / "diagnosis.json").write_text(json.dumps(summary))
    out = tmp_path / "rep"
    assert main(["report", str(d / "a.yaml"), "--bag", str(d / "sim.mcap"), "--residuals",
                 str(d / "a.csv"), "--diagnosis", str(tmp_path / "diagnosis.json"), "-o",
                 str(out)]) == 0
    page = (out / "report.html").read_text()
    for png in ("histogram", "star_vectors", "vector_field", "parameters", "nis",
                "regressors", "time", "unexplained"):
        assert (out / f"{png}.png").stat().st_size > 5000, png
        assert f"{png}.png" in page
    for text in ("Calibrated values ± σ", "truth", "Provenance", "stellar-cal replay",
                 "principal_point.cx", "plot 2"):
        assert text in page, text
    # neither residuals nor a bag to re-run on: one clear error line
    assert main(["report", str(d / "b.yaml"), "-o", str(tmp_path / "x")]) == 1


def test_compare_two_runs(two_runs, tmp_path):
    d = two_runs
    out = tmp_path / "cmp"
    # without residual files: both runs are re-run on the bag from their values
    assert main(["compare", str(d / "a.yaml"), str(d / "b.yaml"), "--bag", str(d / "sim.mcap"),
                 "-o", str(out)]) == 0
    page = (out / "report.html").read_text()
    assert page.count("re-run of psce on the bag") == 2
    assert "B adds time_offset to A" in page
    assert "time_offset.dt (only in B)" in page
    assert "(B − A) / σ_B" in page and "Residuals before / after" in page
    for png in ("histogram", "star_vectors", "vector_field", "parameters_a", "parameters_b"):
        assert (out / f"{png}.png").is_file(), png


def test_unexplained_sizes_read_the_same_in_the_terminal_and_the_report():
    from stellar_cal_ros.diagnosis import printing
    from stellar_cal_ros.diagnosis.report_html import _unexplained_html

    summary = {"unexplained": [
        {"regressor": "angular rate", "component": "size", "statistic": 12.0,
         "p_value": 1e-9, "change_px": 0.3},
        {"regressor": "catalogue star", "component": "u, v", "statistic": 5.0,
         "p_value": 1e-4, "change_px": 0.02},
        {"regressor": "time (periodic 12 s)", "component": "u", "statistic": 5.0,
         "p_value": 1e-4, "change_px": -0.02},
        {"regressor": "gravity_st (mount-flexure shape, after gyro_scale_factor)",
         "component": "u, v", "statistic": 7.9, "p_value": 3e-5, "change_px": 0.043,
         "detail": {"arcsec_per_g": 40.0}},
        {"regressor": "magnitude", "component": "v", "statistic": 3.9, "p_value": 3e-3}]}
    text = "\n".join(printing.unexplained_lines(summary))
    page = _unexplained_html(summary)
    for u, size in zip(summary["unexplained"],
                       ["0.3 px across its 5-95 % range", "0.02 px rms per axis at least",
                        "0.02 px amplitude",
                        "0.043 px at most over 99 % of the stars, what the fit left of it", ""],
                       strict=True):
        what, said = printing.unexplained_phrase(u)
        assert said.startswith(size) and (size == "") == (said == "")
        assert f"{what} vs {u['regressor']}" in text
        assert f"{what} vs <b>{u['regressor']}</b>" in page and said in text and said in page
    assert "0.000 px" not in page  # no size is not a size of 0
    # 'follows' is said only of a line the rolling shutter explains (below), not of the
    # regressor a line is against (was: 'the regressor it follows is listed first')
    assert "follow" not in text and "varies with" in text, text


def test_regressor_plots_of_a_batch_table(tmp_path):
    """An ACF residual table has no body rate or temperature: those panels are left out."""
    from stellar_cal_ros.diagnosis import report

    rng = np.random.default_rng(2)
    n = 400
    res = {"t": 1.8e9 + np.repeat(np.arange(40.0), 10), "frame": np.repeat(np.arange(40), 10),
           "u": rng.uniform(0, 1024, n), "v": rng.uniform(0, 1024, n),
           "du": rng.normal(0, 0.1, n), "dv": rng.normal(0, 0.1, n), "s_uu": np.full(n, 0.01),
           "s_uv": np.zeros(n), "s_vv": np.full(n, 0.01), "gated": np.zeros(n, bool),
           "magnitude": rng.uniform(2, 6, n)}
    path = report.plot_regressors([("acf", res)], (512.0, 512.0), 0.5, tmp_path / "r.png")
    assert path.stat().st_size > 5000
    finding = [{"regressor": "angular rate", "component": "size", "statistic": 5.0,
                "p_value": 1e-3}]
    assert report.plot_unexplained(res, finding, (512.0, 512.0), 0.5,
                                   tmp_path / "u.png").is_file()
    # a flexure-shaped remainder has no residual-table column: its panel states the test
    flex = {"regressor": "gravity_st (mount-flexure shape, after gyro_scale_factor)",
            "component": "u, v", "statistic": 7.9, "p_value": 3e-5, "change_px": 0.043,
            "detail": {"arcsec_per_g": 43.8, "sigma_arcsec_per_g": 2.6}}
    text = report._finding_text(flex)
    assert "t = 7.9" in text and "0.043 px" in text and "43.8 +- 2.6 arcsec" in text
    assert "not in the residual table" not in text
    assert report.plot_unexplained(res, [flex], (512.0, 512.0), 0.5,
                                   tmp_path / "f.png").is_file()
    assert report.plot_histograms([("acf", res)], 0.5, tmp_path / "h.png").is_file()


def test_estimates_read_the_same_in_the_terminal_and_the_report():
    """An added effect's and a candidate's ``value ± σ`` come from one phrase
    (printing.estimate_phrase), in the parameter's display unit."""
    from stellar_cal_ros.diagnosis import printing
    from stellar_cal_ros.diagnosis.report_html import _candidates_html

    said = printing.estimate_phrase("time_offset", "dt", 0.0123, 1e-4)
    assert said == "dt = 12.3 ms +- 0.1 ms"
    page = _candidates_html({"candidates": [
        {"effect": "time_offset", "score": 40.0, "p_value": 1e-8, "significant": True,
         "rms_after_px": [0.05, 0.05], "estimate": {"dt": 0.0123}, "sigma": {"dt": 1e-4}}]})
    assert said.replace("+-", "±") in page


def test_a_line_that_follows_the_rolling_shutter_says_so_in_the_terminal_and_the_report():
    """An 'unexplained' line ranked after the rolling shutter's (``follows`` in
    diagnosis.json) is marked alike on the terminal and in report.html."""
    from stellar_cal_ros.diagnosis import printing
    from stellar_cal_ros.diagnosis.report_html import _unexplained_html

    line = {"regressor": "radius", "component": "u", "statistic": -12.6, "p_value": 1.6e-6,
            "change_px": 0.05}
    summary = {"unexplained": [dict(line, follows="rolling shutter"), line]}
    said = printing.follows_phrase(summary["unexplained"][0])
    assert said.startswith("follows the rolling shutter") and not printing.follows_phrase(line)
    terminal = printing.unexplained_lines(summary)
    assert said in terminal[0] and said not in terminal[1], terminal
    assert terminal[2].count("follow") == 1 and "follows the rolling shutter comes after the " \
        "shutter's" in terminal[2], terminal
    assert _unexplained_html(summary).count(said) == 1


def test_run_stats_add_block_is_add_a_frame_at_a_time_bit_for_bit() -> None:
    """``RunStats.add_block`` (a replay's batch) leaves every sum as one ``add`` a frame
    does, to the bit: blocks across the evaluation window's start, a frame without accepted
    stars, a NaN NIS, a first block that starts the whiteness sums and later ones that
    continue them."""
    from types import SimpleNamespace

    from stellar_cal_ros.methods.results import RunStats

    rng = np.random.default_rng(3)
    K = 40
    stamps = (1000.0 + np.arange(K) * 0.5).tolist()
    n_stars = rng.integers(3, 20, size=K).tolist()
    sums = rng.normal(size=(K, 10)) * rng.uniform(0.1, 1e3, size=10)
    sums[:, 0] = [rng.integers(0, n + 1) for n in n_stars]
    sums[7, 0] = 0  # no accepted star
    nis = rng.chisquare(20, size=K)
    nis[11] = np.nan
    dof = [2 * int(a) for a in sums[:, 0]]
    for eval_start in (None, stamps[13] - 0.1, stamps[0] - 1.0, stamps[-1] + 1.0):
        one, block = RunStats(eval_start), RunStats(eval_start)
        for i in range(K):
            one.add(SimpleNamespace(stamp=stamps[i], uv=np.zeros((n_stars[i], 2)),
                                    nis=float(nis[i]), dof=dof[i], sums=sums[i],
                                    accepted=None))
        for a, b in ((0, 5), (5, 6), (6, 25), (25, K)):
            block.add_block(stamps[a:b], n_stars[a:b], nis[a:b], dof[a:b], sums[a:b])
        assert vars(one) == vars(block), eval_start
    assert one.frames == 0 and block.accepted_total == int(sums[:, 0].sum())
