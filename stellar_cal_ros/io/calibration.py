"""The calibration YAML file (``INTERFACES.md`` section 3): prior in, result out.

Layout (``format: stellar_cal/1``)::

    format, method, stamp, frames, camera (camera_calibration_parsers layout),
    installation.quaternion_xyzw (R_imu_st), gyro.{bias, error_matrix},
    accelerometer.{bias, error_matrix}, time_offset, effects, sigma

``camera``, ``installation`` and ``gyro.bias`` are required; every other block has a
default (zeros, empty). Unknown top-level keys are kept in :attr:`Calibration.extra` and
written back unchanged. Every problem is reported as :class:`CalibrationFileError` naming
the file and the key.
"""

from __future__ import annotations

import contextlib
import math
import numbers
import os
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from stellar_cal_ros.core.camera import CameraModel
from stellar_cal_ros.errors import CalibrationFileError, StellarCalError

__all__ = [
    "FORMAT",
    "Calibration",
    "calibration_from_dict",
    "calibration_to_dict",
    "load_calibration",
    "save_calibration",
]

FORMAT = "stellar_cal/1"
"""Value of the ``format`` key this module reads and writes."""

DEFAULT_FRAMES = {"imu": "imu_link", "star_tracker": "star_tracker_optical_frame"}

_KNOWN_KEYS = (
    "format",
    "method",
    "stamp",
    "frames",
    "camera",
    "installation",
    "gyro",
    "accelerometer",
    "time_offset",
    "effects",
    "sigma",
)


def _zeros3() -> NDArray[np.float64]:
    return np.zeros(3)


def _zeros33() -> NDArray[np.float64]:
    return np.zeros((3, 3))


@dataclass(eq=False)
class Calibration:
    """Everything a calibration file holds.

    Attributes
    ----------
    camera : CameraModel
        Projection model (pinhole + OpenCV distortion, 14 coefficients).
    installation : scipy.spatial.transform.Rotation
        ``R_imu_st``: star tracker frame in the IMU frame, ``v_imu = R_imu_st v_st``.
    gyro_bias : ndarray of float64, shape (3,)
        rad/s, IMU frame.
    gyro_error_matrix : ndarray of float64, shape (3, 3)
        ``E`` in ``w_meas = (I + E) w_true + bias + noise`` (dimensionless).
    accel_bias : ndarray of float64, shape (3,)
        m/s^2, IMU frame.
    accel_error_matrix : ndarray of float64, shape (3, 3)
        Same form as the gyro's.
    time_offset : float
        s; true mid-exposure time = star frame ``header.stamp`` + ``time_offset``.
    effects : dict of str to dict
        Further estimated effects, ``{effect_id: {parameter: value}}``.
    sigma : dict
        1-sigma of the estimated quantities, nested exactly as in the YAML (e.g.
        ``sigma["installation"]["rotation_vector"]``, rad; ``sigma["time_offset"]``, s).
    method : str
        ``psce``, ``swaying_base``, ``acf``, ``prior`` or ``truth``.
    stamp : float
        POSIX time of the estimate, s.
    frames : dict of str to str
        ``{"imu": ..., "star_tracker": ...}`` frame ids.
    extra : dict
        Unknown top-level keys, written back unchanged.
    """

    camera: CameraModel
    installation: Rotation
    gyro_bias: NDArray[np.float64] = field(default_factory=_zeros3)
    gyro_error_matrix: NDArray[np.float64] = field(default_factory=_zeros33)
    accel_bias: NDArray[np.float64] = field(default_factory=_zeros3)
    accel_error_matrix: NDArray[np.float64] = field(default_factory=_zeros33)
    time_offset: float = 0.0
    effects: dict[str, dict[str, Any]] = field(default_factory=dict)
    sigma: dict[str, Any] = field(default_factory=dict)
    method: str = "prior"
    stamp: float = 0.0
    frames: dict[str, str] = field(default_factory=lambda: dict(DEFAULT_FRAMES))
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.gyro_bias = np.asarray(self.gyro_bias, dtype=np.float64).reshape(3)
        self.gyro_error_matrix = np.asarray(self.gyro_error_matrix, dtype=np.float64).reshape(3, 3)
        self.accel_bias = np.asarray(self.accel_bias, dtype=np.float64).reshape(3)
        self.accel_error_matrix = np.asarray(self.accel_error_matrix, dtype=np.float64).reshape(
            3, 3
        )
        self.time_offset = float(self.time_offset)
        self.stamp = float(self.stamp)

    @property
    def R_imu_st(self) -> NDArray[np.float64]:
        """Installation rotation matrix, shape (3, 3)."""
        return np.asarray(self.installation.as_matrix(), dtype=np.float64)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Calibration):
            return NotImplemented
        q1 = self.installation.as_quat()
        q2 = other.installation.as_quat()
        same_rot = bool(np.allclose(q1, q2, rtol=0, atol=1e-15) or np.allclose(q1, -q2, atol=1e-15))
        arrays = ("gyro_bias", "gyro_error_matrix", "accel_bias", "accel_error_matrix")
        scalars = ("time_offset", "effects", "sigma", "method", "stamp", "frames", "extra")
        return (
            same_rot
            and self.camera == other.camera
            and all(np.array_equal(getattr(self, k), getattr(other, k)) for k in arrays)
            and all(getattr(self, k) == getattr(other, k) for k in scalars)
        )

    __hash__ = None  # type: ignore[assignment]


# --------------------------------------------------------------------------------------------
# dict <-> Calibration
# --------------------------------------------------------------------------------------------


def _is_number(x: object) -> bool:
    return isinstance(x, numbers.Real) and not isinstance(x, bool)


def _numbers(value: Any, n: int, where: str, src: str) -> NDArray[np.float64]:
    """Parse a flat list of ``n`` finite numbers (a 3x3 nested list is accepted for n == 9)."""
    if n == 9 and isinstance(value, (list, tuple)) and len(value) == 3:
        if all(isinstance(r, (list, tuple)) for r in value):
            value = [x for r in value for x in r]
    if not isinstance(value, (list, tuple)) or not all(_is_number(x) for x in value):
        raise CalibrationFileError(f"{src}: {where} must be a list of {n} numbers, got {value!r}")
    if len(value) != n:
        raise CalibrationFileError(f"{src}: {where} must have {n} values, got {len(value)}")
    arr = np.array([float(x) for x in value])
    if not np.all(np.isfinite(arr)):
        raise CalibrationFileError(f"{src}: {where} must be finite, got {arr.tolist()}")
    return arr


def _number(value: Any, where: str, src: str) -> float:
    if not _is_number(value) or not math.isfinite(float(value)):
        raise CalibrationFileError(f"{src}: {where} must be a finite number, got {value!r}")
    return float(value)


def _mapping(d: Mapping[str, Any], key: str, src: str, required: bool) -> Mapping[str, Any]:
    if key not in d or d[key] is None:
        if required:
            raise CalibrationFileError(f"{src}: required block '{key}' is missing")
        return {}
    block = d[key]
    if not isinstance(block, Mapping):
        raise CalibrationFileError(f"{src}: '{key}' must be a mapping, got {type(block).__name__}")
    return block


def _plain(x: Any) -> Any:
    """Convert numpy scalars / arrays and tuples into plain Python (YAML-safe) values."""
    if isinstance(x, Mapping):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, np.ndarray):
        return [_plain(v) for v in x.reshape(-1).tolist()] if x.ndim else _plain(x.item())
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, numbers.Integral):
        return int(x)
    if isinstance(x, numbers.Real):
        return float(x)
    return x


def _sensor_block(
    d: Mapping[str, Any], key: str, src: str, required: bool
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    block = _mapping(d, key, src, required)
    if required and "bias" not in block:
        raise CalibrationFileError(f"{src}: '{key}.bias' is missing")
    bias = _numbers(block["bias"], 3, f"{key}.bias", src) if "bias" in block else np.zeros(3)
    em = block.get("error_matrix")
    err = np.zeros((3, 3)) if em is None else _numbers(em, 9, f"{key}.error_matrix", src)
    return bias, err.reshape(3, 3)


def calibration_from_dict(d: Mapping[str, Any], source: str = "<dict>") -> Calibration:
    """Build a :class:`Calibration` from the parsed YAML mapping.

    Parameters
    ----------
    d : mapping
        The whole document (``format`` ... ``sigma``).
    source : str
        Name used in error messages (the file path).

    Returns
    -------
    Calibration

    Raises
    ------
    CalibrationFileError
        Wrong ``format``, a missing required block (``camera``, ``installation``,
        ``gyro``), values of the wrong shape or type.
    """
    if not isinstance(d, Mapping):
        raise CalibrationFileError(
            f"{source}: a calibration file must be a YAML mapping, got {type(d).__name__}"
        )
    fmt = d.get("format")
    if fmt != FORMAT:
        raise CalibrationFileError(
            f"{source}: 'format' is {fmt!r}; expected {FORMAT!r}"
            + (" (missing)" if fmt is None else "")
        )
    cam_block = _mapping(d, "camera", source, required=True)
    try:
        camera = CameraModel.from_yaml_dict(cam_block)
    except StellarCalError as exc:
        raise CalibrationFileError(f"{source}: invalid camera block: {exc}") from exc
    inst = _mapping(d, "installation", source, required=True)
    if "quaternion_xyzw" not in inst:
        raise CalibrationFileError(f"{source}: 'installation.quaternion_xyzw' is missing")
    q = _numbers(inst["quaternion_xyzw"], 4, "installation.quaternion_xyzw", source)
    norm = float(np.linalg.norm(q))
    if not 0.5 < norm < 2.0:
        raise CalibrationFileError(
            f"{source}: installation.quaternion_xyzw has norm {norm}; expected a unit quaternion"
        )
    gyro_bias, gyro_err = _sensor_block(d, "gyro", source, required=True)
    acc_bias, acc_err = _sensor_block(d, "accelerometer", source, required=False)
    time_offset = (
        0.0 if d.get("time_offset") is None else _number(d["time_offset"], "time_offset", source)
    )
    effects_raw = _mapping(d, "effects", source, required=False)
    effects: dict[str, dict[str, Any]] = {}
    for k, v in effects_raw.items():
        if v is None:
            v = {}
        if not isinstance(v, Mapping):
            raise CalibrationFileError(
                f"{source}: effects.{k} must be a mapping {{parameter: value}}, got {v!r}"
            )
        effects[str(k)] = _plain(v)
    sigma = _plain(_mapping(d, "sigma", source, required=False))
    _check_sigma(sigma, source)
    frames_raw = _mapping(d, "frames", source, required=False)
    frames = dict(DEFAULT_FRAMES)
    frames.update({str(k): str(v) for k, v in frames_raw.items()})
    method = d.get("method", "prior")
    if not isinstance(method, str):
        raise CalibrationFileError(f"{source}: 'method' must be a string, got {method!r}")
    stamp = 0.0 if d.get("stamp") is None else _number(d["stamp"], "stamp", source)
    extra = {k: _plain(v) for k, v in d.items() if k not in _KNOWN_KEYS}
    return Calibration(
        camera=camera,
        installation=Rotation.from_quat(q),
        gyro_bias=gyro_bias,
        gyro_error_matrix=gyro_err,
        accel_bias=acc_bias,
        accel_error_matrix=acc_err,
        time_offset=time_offset,
        effects=effects,
        sigma=sigma,
        method=method,
        stamp=stamp,
        frames=frames,
        extra=extra,
    )


def _check_sigma(sigma: Mapping[str, Any], src: str) -> None:
    """Check the shapes of the sigma entries the contract fixes (others pass through)."""
    shapes = {
        ("installation", "rotation_vector"): 3,
        ("gyro", "bias"): 3,
        ("gyro", "error_matrix"): 9,
        ("accelerometer", "bias"): 3,
        ("accelerometer", "error_matrix"): 9,
    }
    for (blk, key), n in shapes.items():
        b = sigma.get(blk)
        if isinstance(b, Mapping) and key in b:
            _numbers(b[key], n, f"sigma.{blk}.{key}", src)
    if "time_offset" in sigma:
        _number(sigma["time_offset"], "sigma.time_offset", src)


def calibration_to_dict(cal: Calibration) -> dict[str, Any]:
    """Return the YAML document of a calibration (plain Python types, contract key order).

    Parameters
    ----------
    cal : Calibration
        The calibration.

    Returns
    -------
    dict
        ``format, method, stamp, frames, camera, installation, gyro, accelerometer,
        time_offset, effects, sigma`` followed by :attr:`Calibration.extra`.
    """
    d: dict[str, Any] = {
        "format": FORMAT,
        "method": str(cal.method),
        "stamp": float(cal.stamp),
        "frames": {str(k): str(v) for k, v in cal.frames.items()},
        "camera": _plain(cal.camera.to_yaml_dict()),
        "installation": {"quaternion_xyzw": _plain(np.asarray(cal.installation.as_quat()))},
        "gyro": {
            "bias": _plain(np.asarray(cal.gyro_bias, float).reshape(3)),
            "error_matrix": _plain(np.asarray(cal.gyro_error_matrix, float).reshape(9)),
        },
        "accelerometer": {
            "bias": _plain(np.asarray(cal.accel_bias, float).reshape(3)),
            "error_matrix": _plain(np.asarray(cal.accel_error_matrix, float).reshape(9)),
        },
        "time_offset": float(cal.time_offset),
        "effects": _plain(cal.effects),
        "sigma": _plain(cal.sigma),
    }
    for k, v in cal.extra.items():
        if k not in d:
            d[k] = _plain(v)
    return d


# --------------------------------------------------------------------------------------------
# files
# --------------------------------------------------------------------------------------------


class _Dumper(yaml.SafeDumper):
    """Block style, except flow style for lists and for mappings of scalars only."""


def _represent_list(dumper: yaml.SafeDumper, data: list[Any]) -> yaml.Node:
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=True)


def _represent_dict(dumper: yaml.SafeDumper, data: dict[str, Any]) -> yaml.Node:
    flow = all(not isinstance(v, (dict, list)) for v in data.values())
    return dumper.represent_mapping("tag:yaml.org,2002:map", data, flow_style=flow)


_Dumper.add_representer(list, _represent_list)
_Dumper.add_representer(dict, _represent_dict)


def dump_calibration_yaml(cal: Calibration) -> str:
    """Return the YAML text :func:`save_calibration` writes.

    Parameters
    ----------
    cal : Calibration
        The calibration.

    Returns
    -------
    str
        YAML document.
    """
    return yaml.dump(
        calibration_to_dict(cal),
        Dumper=_Dumper,
        sort_keys=False,
        default_flow_style=False,
        width=120,
        allow_unicode=True,
    )


def load_calibration(path: str | os.PathLike[str]) -> Calibration:
    """Read a calibration YAML file.

    Parameters
    ----------
    path : str or Path
        The ``.yaml`` file.

    Returns
    -------
    Calibration

    Raises
    ------
    CalibrationFileError
        Missing / unreadable file, YAML syntax error, wrong ``format``, missing required
        block, wrong shapes (the message names the file, and the line for syntax errors).
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError as exc:
        raise CalibrationFileError(f"calibration file not found: {p}") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise CalibrationFileError(f"cannot read calibration file {p}: {exc}") from exc
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise CalibrationFileError(f"{p}: YAML syntax error: {exc}") from exc
    if doc is None:
        raise CalibrationFileError(f"{p}: the file is empty")
    return calibration_from_dict(doc, str(p))


def save_calibration(cal: Calibration, path: str | os.PathLike[str]) -> None:
    """Write a calibration YAML file atomically.

    The document is validated (converted back to a :class:`Calibration`) first, written to a
    temporary file in the target directory, flushed and fsynced, then renamed over the
    target: an existing file is replaced only by a complete new one.

    Parameters
    ----------
    cal : Calibration
        The calibration.
    path : str or Path
        Output ``.yaml`` file.

    Raises
    ------
    CalibrationFileError
        The calibration cannot be represented, or the file cannot be written (the previous
        file, if any, is left untouched).
    """
    p = Path(path)
    text = dump_calibration_yaml(cal)
    calibration_from_dict(yaml.safe_load(text), f"{p} (to be written)")
    tmp_name = None
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        if p.exists():
            with contextlib.suppress(OSError):
                os.chmod(tmp_name, p.stat().st_mode & 0o777)
        else:
            with contextlib.suppress(OSError):
                os.chmod(tmp_name, 0o644)
        os.replace(tmp_name, p)
        tmp_name = None
    except OSError as exc:
        raise CalibrationFileError(f"cannot write calibration file {p}: {exc}") from exc
    finally:
        if tmp_name is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp_name)
