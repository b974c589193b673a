"""Write a calibration in the formats other tools load: Kalibr, OpenVINS, ROS camera_info.

``stellar-cal export RESULT.yaml --format kalibr|openvins|camera_info [-o OUT]``

* ``kalibr`` — Kalibr's ``camchain-imucam.yaml``: ``cam0`` with ``T_cam_imu`` (4×4, IMU →
  camera: rotation ``R_imu_stᵀ``), ``timeshift_cam_imu`` (Kalibr: ``t_imu = t_cam + shift``,
  which is this project's ``time_offset``: true exposure time = stamp + time_offset),
  ``camera_model: pinhole``, ``intrinsics: [fu, fv, pu, pv]``, ``distortion_model: radtan``,
  ``distortion_coeffs: [k1, k2, r1, r2]`` (OpenCV's k1 k2 p1 p2), ``resolution``,
  ``rostopic``, ``cam_overlaps``.
* ``openvins`` — OpenVINS's ``kalibr_imucam_chain.yaml``: the same keys with ``T_imu_cam``
  (camera → IMU, rotation ``R_imu_st``) instead of ``T_cam_imu``; OpenVINS reads
  ``timeshift_cam_imu`` with the same sign into its camera–IMU time offset.  The file starts
  with ``%YAML:1.0`` as OpenVINS's own configuration files (read with OpenCV's FileStorage).
* ``camera_info`` — the YAML ``camera_calibration_parsers`` / ``camera_info_manager`` read:
  ``image_width``, ``image_height``, ``camera_name``, ``camera_matrix``,
  ``distortion_model`` (``plumb_bob`` or ``rational_polynomial``),
  ``distortion_coefficients``, ``rectification_matrix`` (I), ``projection_matrix`` ([K|0]).

Nothing is dropped silently: every quantity of the calibration that the target format
cannot hold (distortion terms beyond radtan, the image-plane tilt, thermal and other
``effects``, IMU errors, the lever arm, the time offset in camera_info) is listed in the
returned warnings, with the largest pixel displacement the omitted camera terms cause over
the detector where that applies.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from stellar_cal_ros.core.camera import OPENCV_DISTORTION_NAMES, CameraModel
from stellar_cal_ros.effects import registry
from stellar_cal_ros.effects.base import ExportRole
from stellar_cal_ros.errors import StellarCalError
from stellar_cal_ros.io.calibration import Calibration

__all__ = ["FORMATS", "Export", "default_output", "export_calibration", "write_export"]

FORMATS = ("kalibr", "openvins", "camera_info")
DEFAULT_ROSTOPIC = "/star_tracker/image_raw"


@dataclass
class Export:
    """One exported document.

    Attributes
    ----------
    format : str
        One of :data:`FORMATS`.
    document : dict
        The YAML mapping.
    text : str
        The file's text.
    warnings : list of str
        What the format cannot hold (one line each).
    """

    format: str
    document: dict[str, Any]
    text: str
    warnings: list[str] = field(default_factory=list)


class _ExportDumper(yaml.SafeDumper):
    """Block style, except flow style for lists of scalars (matrix rows, vectors).

    Block sequences are indented below their key: OpenCV's FileStorage (which OpenVINS
    reads its files with) rejects them at the key's indentation.
    """

    def increase_indent(self, flow: bool = False, indentless: bool = False) -> None:  # noqa: D102
        return super().increase_indent(flow, False)


def _represent_list(dumper: yaml.SafeDumper, data: list[Any]) -> yaml.Node:
    flow = all(not isinstance(v, (list, dict)) for v in data)
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flow)


_ExportDumper.add_representer(list, _represent_list)


def _dump(doc: dict[str, Any]) -> str:
    return yaml.dump(doc, Dumper=_ExportDumper, sort_keys=False, default_flow_style=False,
                     width=120)


def max_displacement_px(full: CameraModel, reduced: CameraModel, n: int = 21) -> float:
    """Largest pixel distance between two camera models over an n×n grid of the detector.

    The grid's pixels are unprojected with ``full`` and projected with ``reduced``.
    """
    u = np.linspace(0.0, full.width - 1.0, n)
    v = np.linspace(0.0, full.height - 1.0, n)
    uv = np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)
    d = full.unproject(uv)
    uv2 = reduced.project(d)
    return float(np.nanmax(np.linalg.norm(uv2 - uv, axis=1)))


def _reduced_camera(cam: CameraModel, keep: int, what: str) -> tuple[CameraModel, list[str]]:
    """The camera with only the first ``keep`` OpenCV coefficients, and what was dropped."""
    dist = np.array(cam.distortion, dtype=float)
    dropped = {OPENCV_DISTORTION_NAMES[i]: float(dist[i]) for i in range(keep, 14)
               if dist[i] != 0.0}
    if not dropped:
        return cam, []
    dist[keep:] = 0.0
    reduced = CameraModel(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, dist,
                          cam.name)
    px = max_displacement_px(cam, reduced)
    tilt = {k: v for k, v in dropped.items() if k.startswith("tau")}
    other = {k: v for k, v in dropped.items() if not k.startswith("tau")}
    out = []
    if other:
        values = ", ".join(f"{k}={v:.6g}" for k, v in other.items())
        out.append(f"not exported: distortion {values} ({what} cannot express them)")
    if tilt:
        values = ", ".join(f"{k}={v:.6g} rad" for k, v in tilt.items())
        out.append(f"not exported: image_plane_tilt {values} ({what} has no tilted image "
                   "plane)")
    out.append(f"the exported camera model differs from the calibrated one by up to {px:.3f} px "
               "over the detector")
    return reduced, out


def _common_warnings(cal: Calibration, fmt: str, holds: str) -> list[str]:
    out = []
    for eff, params in cal.effects.items():
        values = ", ".join(f"{k}={v:.6g}" if isinstance(v, (int, float)) else f"{k}={v}"
                           for k, v in (params or {}).items())
        # the class says what its value is (an effect not loaded here: a sensor effect)
        role = registry.EFFECTS[eff].export() if eff in registry.EFFECTS else None
        if role is ExportRole.STAR_DIRECTIONS:
            out.append(f"not exported: {eff} ({values}): a correction of the star directions, "
                       "not of the sensor")
        elif role is ExportRole.IMU:
            out.append(f"not exported: effect {eff} ({values}): an inertial-sensor error (the "
                       f"{fmt} file holds {holds} only)")
        elif role is ExportRole.EXTRINSIC:
            out.append(f"not exported: effect {eff} ({values}): the {fmt} format's camera–IMU "
                       "transform and time shift cannot express it")
        else:
            out.append(f"not exported: effect {eff} ({values}): OpenCV's camera model and the "
                       f"{fmt} format cannot express it")
    if np.any(cal.gyro_bias != 0) or np.any(cal.gyro_error_matrix != 0):
        out.append("not exported: gyro bias "
                   f"{np.round(cal.gyro_bias, 12).tolist()} rad/s and error matrix (the "
                   f"{fmt} file holds {holds} only)")
    if np.any(cal.accel_bias != 0) or np.any(cal.accel_error_matrix != 0):
        out.append("not exported: accelerometer bias / error matrix (the "
                   f"{fmt} file holds {holds} only)")
    return out


def _transform(R: np.ndarray) -> list[list[float]]:
    T = np.eye(4)
    T[:3, :3] = R
    return [[float(x) for x in row] for row in T]


def _chain_document(cal: Calibration, fmt: str, rostopic: str) -> tuple[dict, list[str]]:
    cam, warn = _reduced_camera(cal.camera, 4, f"{fmt}'s radtan model (k1 k2 r1 r2)")
    d = cam.distortion
    R_imu_st = cal.R_imu_st
    key, R = ("T_cam_imu", R_imu_st.T) if fmt == "kalibr" else ("T_imu_cam", R_imu_st)
    cam0 = {
        key: _transform(R),
        "cam_overlaps": [],
        "camera_model": "pinhole",
        "distortion_coeffs": [float(d[0]), float(d[1]), float(d[2]), float(d[3])],
        "distortion_model": "radtan",
        "intrinsics": [cam.fx, cam.fy, cam.cx, cam.cy],
        "resolution": [int(cam.width), int(cam.height)],
        "rostopic": rostopic,
        "timeshift_cam_imu": float(cal.time_offset),
    }
    warn = warn + _common_warnings(cal, fmt, "the camera and the camera–IMU transform")
    warn.append(f"{key} translation set to 0: the lever arm is not estimated (stars are at "
                "infinity); enter it by hand if your tool needs it")
    return {"cam0": cam0}, warn


def _camera_info_document(cal: Calibration) -> tuple[dict, list[str]]:
    cam0 = cal.camera
    dist = cam0.distortion
    keep = 8 if np.any(dist[5:8] != 0) else 5
    model = "rational_polynomial" if keep == 8 else "plumb_bob"
    cam, warn = _reduced_camera(cam0, keep, f"camera_info's {model} model")
    doc = cam.to_yaml_dict()
    doc["distortion_model"] = model
    doc["distortion_coefficients"] = {"rows": 1, "cols": keep,
                                      "data": [float(x) for x in cam.distortion[:keep]]}
    warn += _common_warnings(cal, "camera_info", "the camera intrinsics")
    warn.append("not exported: installation R_imu_st (camera_info has no extrinsics; use "
                "--format kalibr or the calibrator's /tf_static)")
    if cal.time_offset != 0:
        warn.append(f"not exported: time_offset {cal.time_offset:.6g} s (camera_info has no "
                    "time offset)")
    return doc, warn


def export_calibration(cal: Calibration, fmt: str,
                       rostopic: str = DEFAULT_ROSTOPIC) -> Export:
    """Convert a calibration into one of :data:`FORMATS`.

    Parameters
    ----------
    cal : Calibration
        The calibration (a result, or any calibration file).
    fmt : str
        ``kalibr``, ``openvins`` or ``camera_info``.
    rostopic : str
        The ``rostopic`` entry of the Kalibr / OpenVINS file (the camera's image topic).

    Returns
    -------
    Export

    Raises
    ------
    StellarCalError
        Unknown format.
    """
    if fmt == "camera_info":
        doc, warn = _camera_info_document(cal)
        text = _dump(doc)
    elif fmt in ("kalibr", "openvins"):
        doc, warn = _chain_document(cal, fmt, rostopic)
        head = (f"# {'camchain-imucam' if fmt == 'kalibr' else 'kalibr_imucam_chain'} written "
                f"by stellar-cal export from a {cal.method} calibration\n")
        text = ("%YAML:1.0\n" if fmt == "openvins" else "") + head + _dump(doc)
    else:
        raise StellarCalError(f"unknown export format {fmt!r}; use one of {', '.join(FORMATS)}")
    return Export(fmt, doc, text, warn)


def default_output(result_path: str | os.PathLike[str], fmt: str) -> Path:
    """The default output file beside the result.

    ``RESULT-camchain-imucam.yaml`` (kalibr), ``RESULT-kalibr_imucam_chain.yaml`` (openvins)
    or ``RESULT-camera_info.yaml``.
    """
    p = Path(result_path)
    suffix = {"kalibr": "camchain-imucam", "openvins": "kalibr_imucam_chain",
              "camera_info": "camera_info"}[fmt]
    return p.with_name(f"{p.stem}-{suffix}.yaml")


def write_export(cal: Calibration, fmt: str, path: str | os.PathLike[str],
                 rostopic: str = DEFAULT_ROSTOPIC) -> Export:
    """:func:`export_calibration` and write the text to ``path``."""
    ex = export_calibration(cal, fmt, rostopic)
    p = Path(path)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(ex.text, encoding="utf-8")
    except OSError as exc:
        raise StellarCalError(f"cannot write {p}: {exc}") from exc
    return ex
