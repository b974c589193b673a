"""Truth values of physical effects for the simulator (``--effect ID=VALUE``).

Each effect id of doc/interfaces.md §4 (plus a few that no library effect models, used to test
that the diagnosis reports unexplained structure) has a fixed number of values and a unit:

==========================  =====  ==========================================================
id                          size   unit / meaning
==========================  =====  ==========================================================
installation                3      arcsec, rotation δ about the tracker axes,
                                   ``R_imu_st = R_nominal · Exp(δ)``
principal_point             2      px, offset of (cx, cy) from the detector centre
focal_length                1      px, offset of fx and fy from the nominal focal length
pixel_aspect                1      1, ``fy = fx · (1 + value)``
radial_k1k2                 2      OpenCV k1, k2 (normalized coordinates)
radial_k3                   1      OpenCV k3
tangential                  2      OpenCV p1, p2
image_plane_tilt            2      rad, OpenCV tau_x, tau_y
thermal_focal_length        1      1/°C, ``f(T) = f · (1 + value · (T_head − T_ref))``
gyro_bias                   3      deg/h
gyro_scale_factor           3      1 (diagonal of the gyro error matrix E)
gyro_misalignment           6      rad, E01 E02 E10 E12 E20 E21
accel_bias                  3      m/s²
accel_scale_factor          3      1
time_offset                 1      s, true mid-exposure = header.stamp + value
aberration                  1      scale of annual + diurnal aberration (1 = physical)
refraction                  1      scale of atmospheric refraction (1 = physical)
proper_motion               1      scale of proper motion from J2000.0 to the date
mount_flexure               1      arcsec of tracker rotation per unit lateral gravity (not in
                                   the library: gravity-dependent bending of the mount)
magnitude_bias              2      px per magnitude (from mag 4), direction deg in the image
                                   (not in the library: a magnitude-dependent centroid bias)
misidentification           1      fraction of stars given a wrong catalogue identity
==========================  =====  ==========================================================
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from stellar_cal_ros.errors import ScenarioError

EFFECT_SIZES: dict[str, int] = {
    "installation": 3,
    "principal_point": 2,
    "focal_length": 1,
    "pixel_aspect": 1,
    "radial_k1k2": 2,
    "radial_k3": 1,
    "tangential": 2,
    "image_plane_tilt": 2,
    "thermal_focal_length": 1,
    "gyro_bias": 3,
    "gyro_scale_factor": 3,
    "gyro_misalignment": 6,
    "accel_bias": 3,
    "accel_scale_factor": 3,
    "time_offset": 1,
    "aberration": 1,
    "refraction": 1,
    "proper_motion": 1,
    "mount_flexure": 1,
    "magnitude_bias": 2,
    "misidentification": 1,
}

CONTRACT_EFFECTS = tuple(k for k in EFFECT_SIZES if k not in {
    "mount_flexure", "magnitude_bias", "misidentification"})

ARCSEC = np.pi / (180.0 * 3600.0)
DEG_PER_HOUR = np.pi / 180.0 / 3600.0


def normalize_effect(effect_id: str, value: Any) -> np.ndarray:
    """Validate one effect value and return it as a float array of the effect's size.

    A scalar given for a vector effect is broadcast (``gyro_bias=0.01`` sets all axes).
    """
    if effect_id not in EFFECT_SIZES:
        raise ScenarioError(
            f"unknown effect id {effect_id!r}; known: {', '.join(EFFECT_SIZES)}"
        )
    arr = np.atleast_1d(np.asarray(value, dtype=float)).ravel()
    size = EFFECT_SIZES[effect_id]
    if arr.size == 1 and size > 1:
        arr = np.full(size, arr[0])
    if arr.size != size:
        raise ScenarioError(
            f"effect {effect_id!r} takes {size} value(s), got {arr.size}: {value!r}"
        )
    if not np.all(np.isfinite(arr)):
        raise ScenarioError(f"effect {effect_id!r} has a non-finite value: {value!r}")
    return arr


def parse_effect_arguments(items: Iterable[str]) -> dict[str, np.ndarray]:
    """Parse command-line ``ID=V[,V...]`` items into normalized effect values."""
    out: dict[str, np.ndarray] = {}
    for item in items:
        if "=" not in item:
            raise ScenarioError(f"--effect expects ID=VALUE[,VALUE...], got {item!r}")
        key, text = item.split("=", 1)
        try:
            values = [float(x) for x in text.replace(";", ",").split(",") if x.strip()]
        except ValueError:
            raise ScenarioError(f"--effect {key}: cannot parse numbers in {text!r}") from None
        out[key.strip()] = normalize_effect(key.strip(), values)
    return out


def merged_effects(
    defaults: Mapping[str, Any], overrides: Mapping[str, Any] | None = None
) -> dict[str, np.ndarray]:
    """Return every known effect with its value: scenario defaults, then overrides, else 0."""
    out = {k: np.zeros(n) for k, n in EFFECT_SIZES.items()}
    for source in (defaults, overrides or {}):
        for key, value in source.items():
            out[key] = normalize_effect(key, value)
    return out


def error_matrix(scale_factor: np.ndarray, misalignment: np.ndarray | None = None) -> np.ndarray:
    """Sensor error matrix E of ``w_meas = (I + E) w_true + bias`` (diag = scale factors)."""
    E = np.diag(np.asarray(scale_factor, dtype=float))
    if misalignment is not None:
        m = np.asarray(misalignment, dtype=float)
        E[0, 1], E[0, 2], E[1, 0], E[1, 2], E[2, 0], E[2, 1] = m
    return E
