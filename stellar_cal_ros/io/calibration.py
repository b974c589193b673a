"""The calibration YAML file (``doc/interfaces.md`` §3): prior in, result out.

Layout (``format: stellar_cal/1``)::

    format, method, stamp, frames, camera (camera_calibration_parsers layout),
    installation.quaternion_xyzw (R_imu_st), gyro.{bias, error_matrix},
    accelerometer.{bias, error_matrix}, time_offset, effects, sigma,
    estimated (result files: effect ids the run estimated), covariance_file (optional)

``camera``, ``installation`` and ``gyro.bias`` are required; every other block has a
default (zeros, empty). Unknown top-level keys are kept in :attr:`Calibration.extra` and
written back unchanged. Every problem is reported as :class:`CalibrationFileError` naming
the file and the key.

A result lists the effects its run estimated under ``estimated`` and holds the σ of those
only (an entry of a fixed-shape σ array that no estimated effect owns is 0).  The full
covariance of the estimated parameters goes to a sidecar ``RESULT.covariance.yaml``
(:func:`save_calibration` with ``covariance=``; :func:`load_covariance`; the document is
:mod:`~stellar_cal_ros.io.covariance_file`), named by the result's ``covariance_file`` key.
:func:`prior_warnings` lists the problems of a σ block read as a prior.
"""

from __future__ import annotations

import contextlib
import copy
import math
import numbers
import os
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml
from numpy.typing import NDArray

from stellar_cal_ros.core.camera import CameraModel
from stellar_cal_ros.core.rotation import scipy_matrix, scipy_quat
from stellar_cal_ros.errors import CalibrationFileError, StellarCalError, yaml_error_text
from stellar_cal_ros.io.covariance_file import COVARIANCE_FORMAT, Covariance, covariance_path
from stellar_cal_ros.io.yaml_style import Dumper, plain

if TYPE_CHECKING:
    from scipy.spatial.transform import Rotation

__all__ = [
    "FORMAT",
    "Calibration",
    "calibration_from_dict",
    "calibration_to_dict",
    "load_calibration",
    "load_covariance",
    "prior_warnings",
    "save_calibration",
    "note_provenance",
    "provenance_record",
    "run_provenance",
    "set_provenance",
    "store_estimate",
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
    "estimated",
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
        Made from its unit quaternion when first read: a file's calibration holds the
        quaternion (:attr:`installation_quat`, :attr:`R_imu_st` read it without importing
        ``scipy.spatial``, ~0.1 CPU-s of a replay's start-up); assigning a ``Rotation``
        works as always.
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
    estimated : list of str
        Effect ids the run that wrote this result estimated (empty for a prior / truth);
        :attr:`sigma` holds the σ of these only.
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
    estimated: list[str] = field(default_factory=list)
    extra: dict[str, Any] = field(default_factory=dict)
    #: keys of the file this calibration was read from that no reader uses (misspellings
    #: among them: ``time_ofset``, ``sigma.gyro.bais``), for :func:`prior_warnings`
    unused_keys: list[str] = field(default_factory=list, repr=False)

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
        """Installation rotation matrix, shape (3, 3) (``installation.as_matrix()``)."""
        return scipy_matrix(self._installation_quat())

    @property
    def installation_quat(self) -> NDArray[np.float64]:
        """The installation's unit quaternion ``[x, y, z, w]`` (``installation.as_quat()``)."""
        return self._installation_quat().copy()

    def set_installation_quat(self, q: NDArray[np.float64]) -> None:
        """The installation from the unit quaternion a ``Rotation`` would store.

        Not normalised again: e.g. a :mod:`~stellar_cal_ros.core.rotation` ``scipy_*`` result.
        """
        self.installation = _UnitQuat(q)

    def _installation_quat(self) -> NDArray[np.float64]:
        q = self.__dict__.get("_inst_q")
        if q is None:
            q = self.__dict__["_inst_q"] = np.asarray(self.installation.as_quat(),
                                                      dtype=np.float64)
        return q

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Calibration):
            return NotImplemented
        q1 = self._installation_quat()
        q2 = other._installation_quat()
        same_rot = bool(np.allclose(q1, q2, rtol=0, atol=1e-15) or np.allclose(q1, -q2, atol=1e-15))
        arrays = ("gyro_bias", "gyro_error_matrix", "accel_bias", "accel_error_matrix")
        scalars = ("time_offset", "effects", "sigma", "method", "stamp", "frames", "estimated",
                   "extra")
        return (
            same_rot
            and self.camera == other.camera
            and all(np.array_equal(getattr(self, k), getattr(other, k)) for k in arrays)
            and all(getattr(self, k) == getattr(other, k) for k in scalars)
        )

    __hash__ = None  # type: ignore[assignment]


class _UnitQuat:
    """An installation given as a stored unit quaternion (``set_installation_quat``)."""

    __slots__ = ("q",)

    def __init__(self, q) -> None:
        self.q = np.array(q, dtype=np.float64).reshape(4)


def _get_installation(self: Calibration) -> Rotation:
    rot = self.__dict__.get("_inst_rot")
    if rot is None:  # the Rotation that stores this quaternion, as Rotation.from_quat made it
        from scipy.spatial.transform import Rotation

        rot = self.__dict__["_inst_rot"] = Rotation(self.__dict__["_inst_q"], normalize=False)
    return rot


def _set_installation(self: Calibration, value: Any) -> None:
    if isinstance(value, _UnitQuat):
        self.__dict__["_inst_q"], self.__dict__["_inst_rot"] = value.q, None
    else:
        self.__dict__["_inst_q"], self.__dict__["_inst_rot"] = None, value


# set after the dataclass is made: its __init__ (and dataclasses.replace, copy) go through it
Calibration.installation = property(  # type: ignore[assignment]
    _get_installation, _set_installation,
    doc="R_imu_st as a scipy Rotation (made from the unit quaternion when first read).")


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
        effects[str(k)] = plain(v)
    sigma = plain(_mapping(d, "sigma", source, required=False))
    _check_sigma(sigma, source)
    frames_raw = _mapping(d, "frames", source, required=False)
    frames = dict(DEFAULT_FRAMES)
    frames.update({str(k): str(v) for k, v in frames_raw.items()})
    method = d.get("method", "prior")
    if not isinstance(method, str):
        raise CalibrationFileError(f"{source}: 'method' must be a string, got {method!r}")
    stamp = 0.0 if d.get("stamp") is None else _number(d["stamp"], "stamp", source)
    estimated = d.get("estimated") or []
    if not isinstance(estimated, (list, tuple)) or not all(isinstance(e, str) for e in estimated):
        raise CalibrationFileError(
            f"{source}: 'estimated' must be a list of effect ids, got {estimated!r}")
    extra = {k: plain(v) for k, v in d.items() if k not in _KNOWN_KEYS}
    cal = Calibration(
        camera=camera,
        installation=_UnitQuat(scipy_quat(q)),  # Rotation.from_quat(q)'s quaternion
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
        estimated=list(estimated),
        extra=extra,
    )
    cal.unused_keys = unused_keys(d)
    return cal


#: the keys each block of the file may hold (doc/interfaces.md §3); ``None``: any key
_BLOCK_KEYS: dict[str, tuple[str, ...] | None] = {
    "installation": ("quaternion_xyzw",),
    "gyro": ("bias", "error_matrix"),
    "accelerometer": ("bias", "error_matrix"),
    "frames": ("imu", "star_tracker"),
    "sigma": ("camera", "installation", "gyro", "accelerometer", "time_offset", "effects"),
    "sigma.camera": ("camera_matrix", "distortion_coefficients"),
    "sigma.installation": ("rotation_vector",),
    "sigma.gyro": ("bias", "error_matrix"),
    "sigma.accelerometer": ("bias", "error_matrix"),
}
#: top-level keys results carry besides the contract's (written by this package)
_RESULT_KEYS = ("provenance", "consistency", "derived", "data_quality", "covariance_file",
                "cross_validation", "noise")


def _suggest(key: str, known: Any) -> str:
    import difflib

    close = difflib.get_close_matches(str(key), list(known), n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


def unused_keys(d: Mapping[str, Any]) -> list[str]:
    """Keys of a calibration document no reader uses, each ``path (did you mean ...?)``.

    Unknown top-level keys are allowed (a newer version's, a result's own); only those
    close to a contract key (``time_ofset``) are listed there.  Inside the blocks whose keys
    the contract fixes (``gyro``, ``installation``, ``sigma`` ...) every unknown key is.
    """
    import difflib

    out = []
    for key in d:
        if key not in _KNOWN_KEYS and key not in _RESULT_KEYS and difflib.get_close_matches(
                str(key), _KNOWN_KEYS, n=1, cutoff=0.8):
            out.append(f"{key}{_suggest(key, _KNOWN_KEYS)}")
    for path, allowed in _BLOCK_KEYS.items():
        block: Any = d
        for part in path.split("."):
            block = block.get(part) if isinstance(block, Mapping) else None
        if isinstance(block, Mapping) and allowed is not None:
            out += [f"{path}.{k}{_suggest(k, allowed)}" for k in block if k not in allowed]
    return out


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
        time_offset, effects, [estimated,] sigma`` followed by :attr:`Calibration.extra`.
    """
    d: dict[str, Any] = {
        "format": FORMAT,
        "method": str(cal.method),
        "stamp": float(cal.stamp),
        "frames": {str(k): str(v) for k, v in cal.frames.items()},
        "camera": plain(cal.camera.to_yaml_dict()),
        "installation": {"quaternion_xyzw": plain(cal.installation_quat)},
        "gyro": {
            "bias": plain(np.asarray(cal.gyro_bias, float).reshape(3)),
            "error_matrix": plain(np.asarray(cal.gyro_error_matrix, float).reshape(9)),
        },
        "accelerometer": {
            "bias": plain(np.asarray(cal.accel_bias, float).reshape(3)),
            "error_matrix": plain(np.asarray(cal.accel_error_matrix, float).reshape(9)),
        },
        "time_offset": float(cal.time_offset),
        "effects": plain(cal.effects),
    }
    if cal.estimated:
        d["estimated"] = [str(e) for e in cal.estimated]
    d["sigma"] = plain(cal.sigma)
    for k, v in cal.extra.items():
        if k not in d:
            d[k] = plain(v)
    return d


# --------------------------------------------------------------------------------------------
# files
# --------------------------------------------------------------------------------------------


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
        Dumper=Dumper,
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
    except UnicodeDecodeError as exc:
        raise CalibrationFileError(f"{p} is not a calibration YAML: binary content at byte "
                                   f"{exc.start} (a bag or an image given for RESULT.yaml?)"
                                   ) from exc
    except OSError as exc:
        raise CalibrationFileError(f"cannot read calibration file {p}: {exc}") from exc
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise CalibrationFileError(f"{p}: YAML syntax error at {yaml_error_text(exc)}") from exc
    if doc is None:
        raise CalibrationFileError(f"{p}: the file is empty")
    return calibration_from_dict(doc, str(p))


def save_calibration(cal: Calibration, path: str | os.PathLike[str],
                     covariance: Covariance | tuple | None = None,
                     provenance: Mapping[str, Any] | None = None) -> None:
    """Write a calibration YAML file atomically (and its covariance sidecar).

    The document is validated (converted back to a :class:`Calibration`) first, written to a
    temporary file in the target directory, flushed and fsynced, then renamed over the
    target: an existing file is replaced only by a complete new one.

    Parameters
    ----------
    cal : Calibration
        The calibration.
    path : str or Path
        Output ``.yaml`` file.
    covariance : Covariance or (names, matrix) or (names, matrix, units), optional
        Full covariance of the estimated parameters (names ``effect.parameter``, matrix
        (n, n) in the effects' units).  Written to :func:`covariance_path` of ``path``
        and named in the result's ``covariance_file`` key; when ``cal.estimated`` is empty
        it is filled from the names' effect ids.
    provenance : mapping, optional
        The record of the run that computed ``cal`` (a node passes its own: several nodes
        may share a process); default the process's record (:func:`set_provenance`).

    Raises
    ------
    CalibrationFileError
        The calibration cannot be represented, or the file cannot be written (the previous
        file, if any, is left untouched).
    """
    p = Path(path)
    record = _RUN_PROVENANCE if provenance is None else provenance
    if record and cal.method not in ("prior", "truth"):
        cal = copy.copy(cal)
        cal.extra = {**cal.extra, "provenance": run_provenance(cal.extra.get("provenance"),
                                                               record)}
    if covariance is not None:
        cov = covariance if isinstance(covariance, Covariance) else Covariance.from_tuple(
            covariance)
        cal = copy.copy(cal)
        cal.extra = dict(cal.extra)
        side = covariance_path(p)
        cal.extra["covariance_file"] = side.name
        if not cal.estimated:
            cal.estimated = list(dict.fromkeys(n.split(".", 1)[0] for n in cov.names))
        _write_atomically(side, cov.dump_yaml(p.name))
    text = dump_calibration_yaml(cal)
    calibration_from_dict(yaml.safe_load(text), f"{p} (to be written)")
    _write_atomically(p, text)


def _write_atomically(p: Path, text: str) -> None:
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


_RUN_PROVENANCE: dict[str, Any] = {}


def set_provenance(**items: Any) -> None:
    """Record how this process runs (command line, version, date, bag, prior).

    Every result (a calibration whose ``method`` is not ``prior`` / ``truth``) that
    :func:`save_calibration` writes afterwards carries these items under ``provenance``
    (the record of the run it was computed from, if any, moves to ``provenance.input``,
    :func:`run_provenance`).  Called once by the command line; ``None`` values are
    left out; a callable is evaluated when the first result is written (e.g. the bag's
    identity, :func:`stellar_cal_ros.io.identity.bag_identity`); no items clears the
    record.
    """
    _RUN_PROVENANCE.clear()
    _RUN_PROVENANCE.update(provenance_record(**items))


def note_provenance(**items: Any) -> None:
    """Add items to this process's record (e.g. the residual file a run wrote)."""
    _RUN_PROVENANCE.update({k: plain(v) for k, v in items.items() if v is not None})


def provenance_record(**items: Any) -> dict[str, Any]:
    """A provenance record as :func:`set_provenance` keeps it (``None`` values left out)."""
    return {k: plain(v) if not isinstance(v, os.PathLike) else str(v)
            for k, v in items.items() if v is not None}


def run_provenance(earlier: Any = None,
                   record: dict[str, Any] | None = None) -> dict[str, Any]:
    """Return the provenance record (default this process's) for a result it writes.

    A result computed from another one (``discover`` from a replay's result) names the
    command that made it; the earlier record, if different, is kept under ``input``
    (its command, version and date only: one step back, not a growing chain).
    """
    record = _RUN_PROVENANCE if record is None else record
    out = {k: v() if callable(v) else v for k, v in record.items()}
    if isinstance(record, dict):
        record.update(out)  # evaluated once (a bag identity reads the bag)
    out = {k: v for k, v in out.items() if v is not None}
    if isinstance(earlier, Mapping) and earlier.get("command") and \
            earlier.get("command") != out.get("command"):
        out["input"] = {k: earlier[k] for k in ("command", "version", "date") if k in earlier}
    return out


# --------------------------------------------------------------------------------------------
# results: estimated effects; reading the covariance sidecar (io/covariance_file.py)
# --------------------------------------------------------------------------------------------


def store_estimate(prior: Calibration, effects: Any, slices: Mapping[str, slice],
                   theta: NDArray[np.float64], sigma: NDArray[np.float64], method: str,
                   stamp: float) -> Calibration:
    """The result of a run: the prior with every estimated effect's value and σ stored.

    The σ block starts empty, so it holds the estimated quantities only (the prior's σ of a
    quantity the run did not estimate is not repeated), and ``estimated`` lists the effects.

    Parameters
    ----------
    prior : Calibration
        The prior the run started from (not modified).
    effects : sequence of Effect
        The model's effects (objects with ``id`` and ``store(value, sigma, cal)``).
    slices : mapping of str to slice
        Each effect's slice of ``theta``.
    theta, sigma : ndarray of float64, shape (n,)
        Estimate and 1-σ in the effects' units.
    method : str
        ``psce``, ``swaying_base``, ``acf``, ...
    stamp : float
        POSIX s of the estimate.

    Returns
    -------
    Calibration
    """
    cal = copy.deepcopy(prior)
    cal.sigma = {}
    cal.method = method
    cal.stamp = float(stamp)
    cal.extra.pop("covariance_file", None)  # a prior that was a result: not this run's
    for eff in effects:
        sl = slices[eff.id]
        eff.store(theta[sl], sigma[sl], cal)
    cal.estimated = [str(eff.id) for eff in effects]
    return cal


def load_covariance(path: str | os.PathLike[str]) -> Covariance:
    """Read a covariance sidecar, given it or the result YAML that names it.

    Raises
    ------
    CalibrationFileError
        Missing / malformed file, or a result without ``covariance_file``.
    """
    p = Path(path)
    try:
        doc = yaml.safe_load(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise CalibrationFileError(f"cannot read {p}: {yaml_error_text(exc)}") from exc
    if isinstance(doc, Mapping) and doc.get("format") == FORMAT:
        side = doc.get("covariance_file")
        if not side:
            raise CalibrationFileError(f"{p}: no covariance_file (written without covariance)")
        return load_covariance(p.parent / str(side))
    if not isinstance(doc, Mapping) or doc.get("format") != COVARIANCE_FORMAT:
        raise CalibrationFileError(f"{p}: 'format' is not {COVARIANCE_FORMAT!r}")
    try:
        return Covariance(doc["parameters"], doc.get("units") or [], doc["matrix"])
    except (KeyError, TypeError, ValueError) as exc:
        raise CalibrationFileError(f"{p}: malformed covariance file: {exc}") from exc


# --------------------------------------------------------------------------------------------
# prior checks
# --------------------------------------------------------------------------------------------


def _walk_numbers(x: Any, where: str):
    """Yield (path, number) of every number in a nested σ block."""
    if isinstance(x, Mapping):
        for k, v in x.items():
            if k in ("rows", "cols"):
                continue
            yield from _walk_numbers(v, f"{where}.{k}")
    elif isinstance(x, (list, tuple)):
        for i, v in enumerate(x):
            yield from _walk_numbers(v, f"{where}[{i}]")
    elif _is_number(x):
        yield where, float(x)


def prior_warnings(cal: Calibration, source: str = "prior",
                   effects: Mapping[str, Any] | None = None) -> list[str]:
    """Problems of a calibration when it is used as a prior (one line each).

    Keys no reader uses (:attr:`Calibration.unused_keys`: a misspelled ``time_ofset`` or
    ``sigma.gyro.bais`` would otherwise be silently ignored); with ``effects`` (effect id →
    its parameter names) ids and parameters under ``effects`` and ``sigma.effects`` that no
    effect has.

    A prior without a ``sigma`` block gives every estimated quantity its effect's default σ;
    a negative or NaN σ is not an uncertainty (the estimators treat such an entry as
    missing or by its magnitude, depending on the quantity).

    Parameters
    ----------
    cal : Calibration
        The loaded prior.
    source : str
        File name for the messages.
    effects : mapping, optional
        Known effect ids and their parameter names (the effect registry's).

    Returns
    -------
    list of str
        One warning per problem (empty when the file is sound).
    """
    out = [f"{source}: unknown key {k}: ignored (doc/interfaces.md lists the keys)"
           for k in cal.unused_keys]
    for block, where in ((cal.effects, "effects"),
                         ((cal.sigma or {}).get("effects") or {}, "sigma.effects")):
        if effects is None or not isinstance(block, Mapping):
            continue
        for eid, params in block.items():
            if eid not in effects:
                out.append(f"{source}: {where}.{eid}: no effect of that id{_suggest(eid, effects)}:"
                           " ignored (`stellar-cal effects` lists them)")
                continue
            for name in params if isinstance(params, Mapping) else ():
                if name not in effects[eid]:
                    out.append(f"{source}: {where}.{eid}.{name}: not a parameter of {eid}"
                               f"{_suggest(name, effects[eid])}: ignored (its parameters: "
                               f"{', '.join(effects[eid])})")
    if not cal.sigma:
        return out + [f"{source}: no 'sigma' block: every estimated quantity starts from its "
                      "effect's default σ (see doc/interfaces.md)"]
    for where, v in _walk_numbers(cal.sigma, "sigma"):
        if math.isnan(v):
            out.append(f"{source}: {where} is NaN (not an uncertainty)")
        elif v < 0:
            out.append(f"{source}: {where} = {v:g} is negative (a σ must be ≥ 0)")
    return out
