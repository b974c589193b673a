"""Tests of stellar_cal_ros.core.camera (cv2 is a test-only dependency)."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest

from stellar_cal_ros.core.camera import OPENCV_DISTORTION_NAMES, CameraModel, tilt_matrix
from stellar_cal_ros.errors import ModelError

WIDTH, HEIGHT = 1024, 1024
FX = FY = 3968.99
CX, CY = 516.5, 521.5
PLUMB_BOB = [0.131072, -0.4294967296, 0.000512, 0.000512, 0.0]


def _random_coefficients(rng: np.random.Generator, model: str) -> np.ndarray:
    """Random coefficient sets of realistic size for a narrow-field star tracker."""
    d = np.zeros(14)
    d[:5] = PLUMB_BOB
    d[:5] += rng.normal(0.0, [0.02, 0.05, 2e-4, 2e-4, 0.5])
    if model in ("rational_polynomial", "opencv_full"):
        d[5:8] = rng.normal(0.0, [0.05, 0.3, 2.0])
    if model == "opencv_full":
        d[8:12] = rng.normal(0.0, 5e-4, 4)
        d[12:14] = rng.normal(0.0, 1e-3, 2)
    return d


def _camera(rng: np.random.Generator, model: str) -> CameraModel:
    d = _random_coefficients(rng, model)
    fx = FX * (1.0 + rng.normal(0.0, 1e-3))
    fy = FY * (1.0 + rng.normal(0.0, 1e-3))
    return CameraModel(
        WIDTH, HEIGHT, fx, fy, CX + rng.normal(0.0, 3.0), CY + rng.normal(0.0, 3.0), d
    )


def _directions(rng: np.random.Generator, n: int, half_angle_deg: float = 9.0) -> np.ndarray:
    """Random unit vectors uniformly distributed in a cone about +z."""
    cos_max = np.cos(np.deg2rad(half_angle_deg))
    cos_t = 1.0 - rng.random(n) * (1.0 - cos_max)
    sin_t = np.sqrt(1.0 - cos_t**2)
    phi = rng.random(n) * 2.0 * np.pi
    return np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=1)


MODELS = ["plumb_bob", "rational_polynomial", "opencv_full"]
CASES = [(model, seed) for model in MODELS for seed in range(3)]


def _cv2_project(cam: CameraModel, directions: np.ndarray) -> np.ndarray:
    cv2 = pytest.importorskip("cv2")
    K = np.array([[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]])
    uv, _ = cv2.projectPoints(
        directions.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, np.array(cam.distortion)
    )
    return uv.reshape(-1, 2)


# ---------------------------------------------------------------------- (a) OpenCV equality


@pytest.mark.parametrize(("model", "seed"), CASES)
def test_project_matches_opencv(model: str, seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    cam = _camera(rng, model)
    assert cam.distortion_model() == model
    d = _directions(rng, 2000)
    # Non-unit directions must give the same pixels.
    d_scaled = d * rng.uniform(0.1, 10.0, size=(d.shape[0], 1))
    ref = _cv2_project(cam, d)
    np.testing.assert_allclose(cam.project(d), ref, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(cam.project(d_scaled), ref, rtol=0.0, atol=1e-9)
    uv, _, _ = cam.project(d, jacobians=True)
    np.testing.assert_allclose(uv, ref, rtol=0.0, atol=1e-9)


def test_project_matches_opencv_realistic_plumb_bob() -> None:
    rng = np.random.default_rng(7)
    cam = CameraModel(WIDTH, HEIGHT, FX, FY, CX, CY, np.array(PLUMB_BOB))
    d = _directions(rng, 5000)
    np.testing.assert_allclose(cam.project(d), _cv2_project(cam, d), rtol=0.0, atol=1e-9)


@pytest.mark.parametrize("single", range(14))
def test_project_matches_opencv_single_coefficient(single: int) -> None:
    """Each coefficient alone (exercises every fast path), with a large value."""
    rng = np.random.default_rng(200 + single)
    d = np.zeros(14)
    d[single] = [0.3, -0.5, 2e-3, -2e-3, 1.5, 0.2, -0.6, 1.8, 3e-3, -4e-3, 2e-3, 5e-3, 0.02, -0.03][
        single
    ]
    cam = CameraModel(WIDTH, HEIGHT, FX, FY, CX, CY, d)
    dirs = _directions(rng, 500)
    np.testing.assert_allclose(cam.project(dirs), _cv2_project(cam, dirs), rtol=0.0, atol=1e-9)


def test_tilt_matrix_matches_opencv_semantics() -> None:
    """Tilt alone: cv2 result equals K * (M (x, y, 1) / third component)."""
    rng = np.random.default_rng(3)
    d = np.zeros(14)
    d[12:] = [1e-3, -2e-3]
    cam = CameraModel(WIDTH, HEIGHT, FX, FY, CX, CY, d)
    dirs = _directions(rng, 100)
    M, _, _ = tilt_matrix(1e-3, -2e-3)
    w = (M @ (dirs / dirs[:, 2:]).T).T
    uv = np.stack([FX * w[:, 0] / w[:, 2] + CX, FY * w[:, 1] / w[:, 2] + CY], axis=1)
    np.testing.assert_allclose(_cv2_project(cam, dirs), uv, rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(cam.project(dirs), uv, rtol=0.0, atol=1e-9)


def test_tilt_matrix_derivatives() -> None:
    for tx, ty in [(0.0, 0.0), (1e-3, -2e-3), (0.3, 0.2)]:
        _, dx, dy = tilt_matrix(tx, ty)
        h = 1e-6
        fdx = (tilt_matrix(tx + h, ty)[0] - tilt_matrix(tx - h, ty)[0]) / (2 * h)
        fdy = (tilt_matrix(tx, ty + h)[0] - tilt_matrix(tx, ty - h)[0]) / (2 * h)
        np.testing.assert_allclose(dx, fdx, atol=1e-9)
        np.testing.assert_allclose(dy, fdy, atol=1e-9)
    np.testing.assert_array_equal(tilt_matrix(0.0, 0.0)[0], np.eye(3))


# ---------------------------------------------------------------------- (b) Jacobians


def _check_columns(analytic: np.ndarray, numeric: np.ndarray, label: str) -> None:
    scale = np.max(np.abs(numeric))
    err = np.max(np.abs(analytic - numeric))
    assert err <= 1e-6 * scale + 1e-12, f"{label}: max error {err:.3e}, scale {scale:.3e}"


@pytest.mark.parametrize(("model", "seed"), CASES)
def test_parameter_jacobian_finite_differences(model: str, seed: int) -> None:
    rng = np.random.default_rng(300 + seed)
    cam = _camera(rng, model)
    d = _directions(rng, 200)
    _, _, J_p = cam.project(d, jacobians=True)
    assert J_p.shape == (200, 2, 18)
    p = cam.parameters()
    for i, name in enumerate(CameraModel.PARAMETER_NAMES):
        # Step giving ~1e-2 px of image motion: truncation and rounding both << 1e-6.
        step = 1e-2 / max(np.max(np.abs(J_p[:, :, i])), 1e-9)
        e = np.zeros(18)
        e[i] = step
        numeric = (
            cam.with_parameters(p + e).project(d) - cam.with_parameters(p - e).project(d)
        ) / (2.0 * step)
        _check_columns(J_p[:, :, i], numeric, name)


@pytest.mark.parametrize(("model", "seed"), CASES)
def test_parameter_jacobian_subset_of_columns(model: str, seed: int) -> None:
    """``project(parameters=mask)``: the wanted columns bit for bit, the others zero."""
    rng = np.random.default_rng(500 + seed)
    cam = _camera(rng, model)
    d = _directions(rng, 50)
    uv, J_d, J_p = cam.project(d, jacobians=True)
    masks = [np.arange(18) < 8, np.isin(np.arange(18), [2, 3, 16]),
             np.isin(np.arange(18), [4, 9, 13]), rng.random(18) < 0.5, np.zeros(18, bool)]
    for want in masks:
        uv2, J_d2, J_p2 = cam.project(d, jacobians=True, parameters=want)
        assert np.array_equal(uv2, uv) and np.array_equal(J_d2, J_d)
        assert np.array_equal(J_p2[:, :, want], J_p[:, :, want])
        # columns computed anyway are exact; the skipped ones are zero
        assert np.all((J_p2[:, :, ~want] == 0) | (J_p2[:, :, ~want] == J_p[:, :, ~want]))


@pytest.mark.parametrize(("model", "seed"), CASES)
def test_direction_jacobian_finite_differences(model: str, seed: int) -> None:
    rng = np.random.default_rng(400 + seed)
    cam = _camera(rng, model)
    d = _directions(rng, 200) * rng.uniform(0.5, 2.0, size=(200, 1))
    _, J_d, _ = cam.project(d, jacobians=True)
    assert J_d.shape == (200, 2, 3)
    for j in range(3):
        step = 1e-6
        e = np.zeros(3)
        e[j] = step
        numeric = (cam.project(d + e) - cam.project(d - e)) / (2.0 * step)
        _check_columns(J_d[:, :, j], numeric, f"direction[{j}]")
    # The Jacobian of a direction is orthogonal to it (projection is scale invariant).
    np.testing.assert_allclose(np.einsum("nij,nj->ni", J_d, d), 0.0, atol=1e-7)


def test_normalized_to_pixel_jacobian() -> None:
    rng = np.random.default_rng(5)
    cam = _camera(rng, "opencv_full")
    d = _directions(rng, 100)
    xy = d[:, :2] / d[:, 2:]
    uv, J_xy, J_p = cam.normalized_to_pixel(xy, jacobians=True)
    uv2, _, J_p2 = cam.project(d, jacobians=True)
    np.testing.assert_allclose(uv, uv2, atol=1e-9)
    np.testing.assert_allclose(J_p, J_p2, rtol=1e-12, atol=1e-9)
    for j in range(2):
        e = np.zeros(2)
        e[j] = 1e-7
        numeric = (cam.normalized_to_pixel(xy + e) - cam.normalized_to_pixel(xy - e)) / 2e-7
        _check_columns(J_xy[:, :, j], numeric, f"xy[{j}]")


def test_behind_camera_is_nan() -> None:
    cam = CameraModel.pinhole(WIDTH, HEIGHT, FX)
    uv, J_d, J_p = cam.project(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]), jacobians=True)
    assert np.all(np.isfinite(uv[0])) and np.all(np.isnan(uv[1]))
    assert np.all(np.isnan(J_d[1])) and np.all(np.isfinite(J_p[0]))


def test_project_shape_errors() -> None:
    cam = CameraModel.pinhole(WIDTH, HEIGHT, FX)
    with pytest.raises(ValueError, match="shape"):
        cam.project(np.zeros(3))
    assert cam.project(np.zeros((0, 3))).shape == (0, 2)


@pytest.mark.parametrize(("model", "seed"), CASES)
def test_project_direction_is_project_without_parameter_jacobian(model: str, seed: int) -> None:
    """The attitude fits' projection: bit for bit :meth:`project`'s pixels and ``J_d``."""
    rng = np.random.default_rng(700 + seed)
    cam = _camera(rng, model)
    d = _directions(rng, 300)
    d[7] = [0.0, 0.1, -1.0]  # behind the camera: NaN in both
    uv, J_d, _ = cam.project(d, jacobians=True)
    uv1, J_d1 = cam.project_direction(d)
    assert np.array_equal(uv1, uv, equal_nan=True)
    assert np.array_equal(J_d1, J_d, equal_nan=True)
    assert np.isnan(uv1[7]).all() and np.isfinite(uv1[8]).all()


# ---------------------------------------------------------------------- (c) unproject


@pytest.mark.parametrize(("model", "seed"), CASES)
def test_unproject_inverts_project(model: str, seed: int) -> None:
    rng = np.random.default_rng(500 + seed)
    cam = _camera(rng, model)
    d = _directions(rng, 5000)
    uv = cam.project(d)
    back = cam.unproject(uv)
    angle = np.linalg.norm(np.cross(back, d), axis=1)
    assert np.max(angle) < 1e-12
    np.testing.assert_allclose(np.linalg.norm(back, axis=1), 1.0, atol=1e-15)
    assert np.max(np.abs(cam.project(back) - uv)) < 1e-9


def test_unproject_whole_image() -> None:
    """Every pixel of the sensor (corners included) inverts to < 1e-9 px."""
    rng = np.random.default_rng(9)
    cam = _camera(rng, "opencv_full")
    u, v = np.meshgrid(np.linspace(-0.5, WIDTH - 0.5, 65), np.linspace(-0.5, HEIGHT - 0.5, 65))
    uv = np.stack([u.ravel(), v.ravel()], axis=1)
    back = cam.unproject(uv)
    assert np.all(np.isfinite(back))
    assert np.max(np.abs(cam.project(back) - uv)) < 1e-9


def test_unproject_nan_input() -> None:
    cam = CameraModel.pinhole(WIDTH, HEIGHT, FX)
    out = cam.unproject(np.array([[np.nan, 3.0], [cam.cx, cam.cy]]))
    assert np.all(np.isnan(out[0]))
    np.testing.assert_allclose(out[1], [0.0, 0.0, 1.0], atol=1e-15)


# ---------------------------------------------------------------------- (d) YAML


def _block(model: str = "plumb_bob") -> dict:
    n = {"plumb_bob": 5, "rational_polynomial": 8, "opencv_full": 14}[model]
    return {
        "image_width": WIDTH,
        "image_height": HEIGHT,
        "camera_name": "star_tracker",
        "camera_matrix": {"rows": 3, "cols": 3, "data": [FX, 0, CX, 0, FY, CY, 0, 0, 1]},
        "distortion_model": model,
        "distortion_coefficients": {"rows": 1, "cols": n, "data": (PLUMB_BOB + [0.0] * 9)[:n]},
    }


@pytest.mark.parametrize(("model", "seed"), CASES)
def test_yaml_round_trip(model: str, seed: int) -> None:
    cam = _camera(np.random.default_rng(600 + seed), model)
    block = cam.to_yaml_dict()
    assert block["distortion_model"] == model
    n = len(block["distortion_coefficients"]["data"])
    assert (
        n
        == block["distortion_coefficients"]["cols"]
        == {"plumb_bob": 5, "rational_polynomial": 8, "opencv_full": 14}[model]
    )
    # Plain Python types only (safe for yaml.safe_dump).
    for key in ("camera_matrix", "distortion_coefficients"):
        assert all(type(x) is float for x in block[key]["data"])
    assert type(block["image_width"]) is int
    again = CameraModel.from_yaml_dict(copy.deepcopy(block))
    assert again == cam
    np.testing.assert_array_equal(again.parameters(), cam.parameters())


def test_yaml_through_pyyaml() -> None:
    yaml = pytest.importorskip("yaml")
    cam = _camera(np.random.default_rng(1), "opencv_full")
    text = yaml.safe_dump({"camera": cam.to_yaml_dict()})
    assert CameraModel.from_yaml_dict(yaml.safe_load(text)["camera"]) == cam


def test_yaml_reads_contract_example() -> None:
    cam = CameraModel.from_yaml_dict(_block())
    assert (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy) == (
        WIDTH,
        HEIGHT,
        FX,
        FY,
        CX,
        CY,
    )
    np.testing.assert_array_equal(cam.distortion, PLUMB_BOB + [0.0] * 9)
    assert cam.name == "star_tracker"
    assert cam.distortion_model() == "plumb_bob"
    # Unknown keys are ignored; rows/cols are optional; camera_name is optional.
    block = _block()
    block["projection_matrix"] = {"rows": 3, "cols": 4, "data": [0] * 12}
    del block["camera_name"]
    del block["camera_matrix"]["rows"]
    assert CameraModel.from_yaml_dict(block) == cam


def test_yaml_wider_model_with_zero_tail_is_accepted() -> None:
    block = _block("opencv_full")
    cam = CameraModel.from_yaml_dict(block)
    assert cam.distortion_model() == "plumb_bob"
    assert cam.to_yaml_dict()["distortion_coefficients"]["cols"] == 5


def _mutate(path: tuple, value: object) -> dict:
    block = copy.deepcopy(_block())
    target = block
    for key in path[:-1]:
        target = target[key]
    if value is KeyError:
        del target[path[-1]]
    else:
        target[path[-1]] = value
    return block


@pytest.mark.parametrize(
    ("path", "value", "message"),
    [
        (("camera_matrix", "data"), [FX, 1.5, CX, 0, FY, CY, 0, 0, 1], "nonzero skew"),
        (("camera_matrix", "data"), [FX, 0, CX, 0, FY, CY, 0, 0], "must hold 9 numbers"),
        (("camera_matrix", "data"), [FX, 0, CX, 0, FY, CY, 0, 0, 2], r"\[fx, 0, cx"),
        (("camera_matrix", "data"), [-FX, 0, CX, 0, FY, CY, 0, 0, 1], "positive"),
        (("camera_matrix", "data"), [FX, 0, "a", 0, FY, CY, 0, 0, 1], "list of numbers"),
        (("camera_matrix", "data"), [FX, 0, float("nan"), 0, FY, CY, 0, 0, 1], "finite"),
        (("camera_matrix", "rows"), 4, "rows must be 3"),
        (("camera_matrix",), KeyError, "camera_matrix is missing"),
        (("camera_matrix",), [1, 2, 3], "mapping"),
        (("distortion_model",), "equidistant", "'equidistant' is not supported"),
        (("distortion_model",), KeyError, "distortion_model is missing"),
        (("distortion_coefficients", "data"), [0.1, 0.2, 0.0, 0.0], "must hold 5 numbers"),
        (("distortion_coefficients", "cols"), 8, "cols must be 5"),
        (("distortion_coefficients", "rows"), 2, "rows must be 1"),
        (("distortion_coefficients",), KeyError, "distortion_coefficients is missing"),
        (("image_width",), 0, "image_width must be a positive integer"),
        (("image_height",), 10.5, "image_height must be a positive integer"),
        (("image_height",), KeyError, "image_height is missing"),
        (("camera_name",), 5, "camera_name must be a string"),
    ],
)
def test_yaml_errors(path: tuple, value: object, message: str) -> None:
    with pytest.raises(ModelError, match=message):
        CameraModel.from_yaml_dict(_mutate(path, value))


def test_yaml_not_a_mapping() -> None:
    with pytest.raises(ModelError, match="mapping"):
        CameraModel.from_yaml_dict([1, 2])  # type: ignore[arg-type]


def test_rational_model_count_mismatch() -> None:
    block = _block("rational_polynomial")
    block["distortion_coefficients"]["data"] = [0.0] * 5
    block["distortion_coefficients"]["cols"] = 5
    with pytest.raises(
        ModelError, match="must hold 8 numbers for distortion_model rational_polynomial, got 5"
    ):
        CameraModel.from_yaml_dict(block)


# ---------------------------------------------------------------------- (e) in_image


def test_in_image_edges() -> None:
    cam = CameraModel.pinhole(4, 3, 100.0)
    uv = np.array(
        [
            [-0.5, -0.5],  # top-left corner of the top-left pixel: inside
            [-0.5 - 1e-9, 0.0],
            [3.5 - 1e-9, 2.5 - 1e-9],  # just inside the bottom-right corner
            [3.5, 0.0],  # right edge is exclusive
            [0.0, 2.5],  # bottom edge is exclusive
            [1.0, 1.0],
            [np.nan, 1.0],
        ]
    )
    np.testing.assert_array_equal(cam.in_image(uv), [True, False, True, False, False, True, False])
    np.testing.assert_array_equal(
        cam.in_image(np.array([[0.5, 0.5], [0.49, 1.0], [2.5, 1.5], [2.49, 1.49]]), margin=1.0),
        [True, False, False, True],
    )


def test_pinhole_defaults() -> None:
    cam = CameraModel.pinhole(1024, 768, 4000.0)
    assert (cam.cx, cam.cy) == (511.5, 383.5)
    np.testing.assert_allclose(cam.project(np.array([[0.0, 0.0, 1.0]])), [[511.5, 383.5]])
    assert cam.distortion_model() == "plumb_bob"
    assert CameraModel.pinhole(10, 10, 5.0, cx=1.0, cy=2.0).cx == 1.0


# ---------------------------------------------------------------------- model object


def test_parameters_round_trip_and_names() -> None:
    cam = _camera(np.random.default_rng(11), "opencv_full")
    assert CameraModel.PARAMETER_NAMES == ("fx", "fy", "cx", "cy") + OPENCV_DISTORTION_NAMES
    assert len(CameraModel.PARAMETER_NAMES) == 18
    p = cam.parameters()
    assert p.shape == (18,)
    assert cam.with_parameters(p) == cam
    p2 = p.copy()
    p2[17] = 0.5
    cam2 = cam.with_parameters(p2)
    assert cam2.distortion[13] == 0.5 and cam.distortion[13] != 0.5
    with pytest.raises(ModelError, match=r"shape \(18,\)"):
        cam.with_parameters(p[:17])


def test_model_is_immutable_and_validated() -> None:
    cam = CameraModel.pinhole(WIDTH, HEIGHT, FX)
    with pytest.raises(dataclasses.FrozenInstanceError):
        cam.fx = 1.0  # type: ignore[misc]
    with pytest.raises(ValueError):
        cam.distortion[0] = 1.0
    # OpenCV-style short vectors are zero-padded.
    assert CameraModel(WIDTH, HEIGHT, FX, FY, CX, CY, np.array(PLUMB_BOB)).distortion.shape == (14,)
    with pytest.raises(ModelError, match="coefficients"):
        CameraModel(WIDTH, HEIGHT, FX, FY, CX, CY, np.zeros(6))
    with pytest.raises(ModelError, match="positive"):
        CameraModel(WIDTH, HEIGHT, 0.0, FY, CX, CY)
    replaced = dataclasses.replace(cam, distortion=np.r_[np.zeros(12), 1e-3, 0.0])
    assert replaced.distortion_model() == "opencv_full"
    assert not np.allclose(
        replaced.project(np.array([[0.1, 0.1, 1.0]])), cam.project(np.array([[0.1, 0.1, 1.0]]))
    )


@pytest.mark.parametrize(
    ("index", "model"),
    [
        (None, "plumb_bob"),
        (0, "plumb_bob"),
        (4, "plumb_bob"),
        (5, "rational_polynomial"),
        (7, "rational_polynomial"),
        (8, "opencv_full"),
        (13, "opencv_full"),
    ],
)
def test_distortion_model_selection(index: int | None, model: str) -> None:
    d = np.zeros(14)
    if index is not None:
        d[index] = 1e-4
    assert CameraModel(WIDTH, HEIGHT, FX, FY, CX, CY, d).distortion_model() == model
