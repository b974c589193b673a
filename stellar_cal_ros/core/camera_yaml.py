"""The ``camera`` block of the calibration YAML (``camera_calibration_parsers`` layout).

:meth:`~stellar_cal_ros.core.camera.CameraModel.from_yaml_dict` and
:meth:`~stellar_cal_ros.core.camera.CameraModel.to_yaml_dict` use these: reading validates
every key with a clear error; writing gives a complete ``camera_calibration_parsers`` file
(rectification and projection matrices included).  Below the camera model (it imports
nothing of it): the distortion models' coefficient counts are defined here.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from typing import Any

import numpy as np

from stellar_cal_ros.errors import ModelError

#: Number of coefficients of each ``camera_calibration_parsers`` distortion model, smallest first.
DISTORTION_MODEL_SIZES: dict[str, int] = {
    "plumb_bob": 5,
    "rational_polynomial": 8,
    "opencv_full": 14,
}


def is_number(value: object) -> bool:
    """A real number that is not a bool (YAML ``true`` is not a size)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _matrix_data(
    block: Mapping[str, Any], key: str, rows: int, cols: int, context: str = ""
) -> list[float]:
    """Read a ``{rows, cols, data}`` matrix of the camera block, with clear errors."""
    where = f"camera.{key}"
    if key not in block:
        raise ModelError(f"{where} is missing")
    mat = block[key]
    if not isinstance(mat, Mapping) or "data" not in mat:
        raise ModelError(f"{where} must be a mapping with 'rows', 'cols' and 'data'")
    data = mat["data"]
    if not isinstance(data, (list, tuple)) or not all(is_number(x) for x in data):
        raise ModelError(f"{where}.data must be a list of numbers, got {data!r}")
    values = [float(x) for x in data]
    if not all(math.isfinite(x) for x in values):
        raise ModelError(f"{where}.data must be finite, got {values}")
    if len(values) != rows * cols:
        raise ModelError(
            f"{where}.data must hold {rows * cols} numbers{context}, got {len(values)}"
        )
    for dim, expected in (("rows", rows), ("cols", cols)):
        if dim in mat and (not is_number(mat[dim]) or mat[dim] != expected):
            raise ModelError(f"{where}.{dim} must be {expected}{context}, got {mat[dim]!r}")
    return values


def _positive_int(block: Mapping[str, Any], key: str) -> int:
    if key not in block:
        raise ModelError(f"camera.{key} is missing")
    value = block[key]
    if not is_number(value) or value != int(value) or int(value) <= 0:
        raise ModelError(f"camera.{key} must be a positive integer, got {value!r}")
    return int(value)


def camera_kwargs(camera_block: Mapping[str, Any]) -> dict[str, Any]:
    """Validated :class:`CameraModel` arguments of a ``camera`` block (see ``from_yaml_dict``)."""
    if not isinstance(camera_block, Mapping):
        raise ModelError(f"camera block must be a mapping, got {type(camera_block).__name__}")
    width = _positive_int(camera_block, "image_width")
    height = _positive_int(camera_block, "image_height")
    name = camera_block.get("camera_name", "star_tracker")
    if not isinstance(name, str):
        raise ModelError(f"camera.camera_name must be a string, got {name!r}")

    k = _matrix_data(camera_block, "camera_matrix", 3, 3)
    fx, skew, cx, k10, fy, cy, k20, k21, k22 = k
    if skew != 0.0:
        raise ModelError(
            f"camera.camera_matrix has a nonzero skew K[0,1] = {skew}; the OpenCV "
            "projection model (cv2.projectPoints) has no skew term"
        )
    if k10 != 0.0 or k20 != 0.0 or k21 != 0.0 or k22 != 1.0:
        raise ModelError(
            f"camera.camera_matrix must be [fx, 0, cx, 0, fy, cy, 0, 0, 1], got {k}"
        )
    if fx <= 0.0 or fy <= 0.0:
        raise ModelError(
            f"camera.camera_matrix focal lengths must be positive, got fx={fx}, fy={fy}"
        )

    if "distortion_model" not in camera_block:
        raise ModelError("camera.distortion_model is missing")
    model = camera_block["distortion_model"]
    if model not in DISTORTION_MODEL_SIZES:
        raise ModelError(
            f"camera.distortion_model {model!r} is not supported; use one of "
            f"{', '.join(DISTORTION_MODEL_SIZES)}"
        )
    size = DISTORTION_MODEL_SIZES[model]
    coeffs = _matrix_data(
        camera_block, "distortion_coefficients", 1, size, f" for distortion_model {model}"
    )
    return {"width": width, "height": height, "fx": fx, "fy": fy, "cx": cx, "cy": cy,
            "distortion": np.asarray(coeffs), "name": name}


def camera_block(cam: Any) -> dict[str, Any]:
    """The ``camera`` block of ``cam`` in plain Python types (see ``to_yaml_dict``)."""
    model = cam.distortion_model()
    n = DISTORTION_MODEL_SIZES[model]
    fx, fy, cx, cy = cam.fx, cam.fy, cam.cx, cam.cy
    return {
        "image_width": int(cam.width),
        "image_height": int(cam.height),
        "camera_name": str(cam.name),
        "camera_matrix": {
            "rows": 3,
            "cols": 3,
            "data": [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
        },
        "distortion_model": model,
        "distortion_coefficients": {
            "rows": 1,
            "cols": n,
            "data": [float(c) for c in cam.distortion[:n]],
        },
        "rectification_matrix": {
            "rows": 3,
            "cols": 3,
            "data": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        },
        "projection_matrix": {
            "rows": 3,
            "cols": 4,
            "data": [fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
        },
    }
