"""Simulation scenarios of the papers and the truth effects they carry.

A :class:`Scenario` holds everything the truth world needs: site and start time, sensor
rates and noise, the motion profile, the nominal (datasheet) model that goes into the prior,
and the default truth effects.  Effect values use the units of :mod:`stellar_cal_ros.sim.effects`.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from stellar_cal_ros.core.earth import Site
from stellar_cal_ros.errors import ScenarioError
from stellar_cal_ros.sim.motion import ConstantRateSweep, Motion, StepRotations, Sway

# 2026-11-22T12:00:00 UTC: night at the default site (20:00 local time).
DEFAULT_START_POSIX = 1795348800.0
DEFAULT_SITE = Site(latitude_deg=36.07, longitude_deg=120.38, height_m=10.0)

PIXEL_PITCH_MM = 0.00645
FOCAL_LENGTH_MM = 25.6


def tan_distortion_opencv(
    k1_mm: float, k2_mm: float, p1_mm: float, p2_mm: float, focal_mm: float
) -> list[float]:
    """Convert focal-plane distortion coefficients (mm units) to OpenCV's normalized ones.

    With focal-plane coordinates ``x = f x_n`` the radial term ``x (k1 r^2 + k2 r^4)`` becomes
    ``x_n (k1 f^2 r_n^2 + k2 f^4 r_n^4)`` and the tangential ``p (r^2 + 2x^2)`` becomes
    ``p f (r_n^2 + 2 x_n^2)``.
    """
    return [k1_mm * focal_mm**2, k2_mm * focal_mm**4, p1_mm * focal_mm, p2_mm * focal_mm]


@dataclass
class Scenario:
    """A complete truth-world configuration."""

    name: str
    description: str
    duration: float
    motion_factory: Callable[[float], Motion]
    imu_rate: float = 100.0
    star_rate: float = 2.0
    star_phase_s: float = 0.2537  # first frame stamp after the start (not on the IMU grid)
    exposure_time: float = 0.1
    mag_limit: float = 6.0
    width: int = 1024
    height: int = 1024
    focal_length_px: float = FOCAL_LENGTH_MM / PIXEL_PITCH_MM
    centroid_noise_px: float = 0.05
    gyro_arw_deg_sqrth: float = 0.001
    accel_vrw_mps_sqrth: float = 0.01
    start_posix: float = DEFAULT_START_POSIX
    site: Site = DEFAULT_SITE
    installation_nominal: Rotation = field(
        default_factory=lambda: Rotation.from_euler("y", -30.0, degrees=True)
    )
    effects: dict[str, Any] = field(default_factory=dict)
    pressure_hpa: float = 1012.0
    air_temperature_c: float = 5.0
    air_temperature_rate_c_per_h: float = -0.5
    head_temperature_start_c: float = 30.0
    head_temperature_ambient_c: float = 10.0
    head_temperature_tau_s: float = 3600.0
    head_temperature_ref_c: float = 20.0
    aux_rate: float = 1.0
    prior_sigma: dict[str, Any] = field(default_factory=dict)

    def motion(self, duration: float | None = None) -> Motion:
        """Build the motion profile for ``duration`` seconds (default: the scenario's)."""
        return self.motion_factory(self.duration if duration is None else duration)


_TAN_DISTORTION = tan_distortion_opencv(2e-4, -1e-6, 2e-5, 2e-5, FOCAL_LENGTH_MM)


def _psce_rotations() -> Scenario:
    d30 = np.deg2rad(30.0)
    steps = [("x", d30), ("y", d30), ("z", d30), ("z", -d30), ("y", -d30), ("x", -d30)]
    return Scenario(
        name="psce_rotations",
        description="Tan et al. 2018 Tables 1-2: +-30 deg steps about each IMU axis, 60 s each",
        duration=7200.0,
        motion_factory=lambda dur: StepRotations(np.eye(3), steps, step_s=60.0, duration=dur),
        star_rate=2.0,
        centroid_noise_px=0.05,
        gyro_arw_deg_sqrth=0.001,
        effects={
            "installation": [100.0, 200.0, 300.0],
            "principal_point": [5.0, 10.0],
            "radial_k1k2": _TAN_DISTORTION[:2],
            "tangential": _TAN_DISTORTION[2:],
            "gyro_bias": [0.01, 0.01, 0.01],
        },
    )


def _swaying() -> Scenario:
    bases = [
        np.eye(3),
        Rotation.from_euler("z", 90.0, degrees=True).as_matrix(),
        Rotation.from_euler("zx", [90.0, 25.0], degrees=True).as_matrix(),
    ]
    sf = [1e-4, -6e-5, 4e-5]
    arcsec = np.deg2rad(1.0 / 3600.0)
    mis = list(np.array([100.0, -50.0, 70.0, 30.0, -80.0, 60.0]) * arcsec)
    return Scenario(
        name="swaying",
        description=(
            "Zhang et al. 2018: sway of eqs. 18-19 over three base orientations, "
            "Table 1 error sources"
        ),
        duration=386.0,
        motion_factory=lambda dur: Sway(bases, hold_s=120.0, transition_s=13.0, duration=dur),
        star_rate=2.0,
        centroid_noise_px=0.058,
        gyro_arw_deg_sqrth=0.003 / 60.0,  # 0.003 deg/h/sqrt(Hz)
        accel_vrw_mps_sqrth=5e-6 * 9.80665 * 60.0,  # 5 ug/sqrt(Hz)
        effects={
            "installation": [120.0, 180.0, -240.0],  # Table 2, group 1
            "principal_point": [5.0, 10.0],
            "radial_k1k2": _TAN_DISTORTION[:2],
            "tangential": _TAN_DISTORTION[2:],
            "gyro_bias": [0.01, 0.01, 0.01],
            "gyro_scale_factor": sf,
            "gyro_misalignment": mis,
            "accel_bias": list(np.array([10.0, -6.0, 4.0]) * 1e-6 * 9.80665),
            "accel_scale_factor": sf,
        },
    )


def _acf_sweep() -> Scenario:
    liu = tan_distortion_opencv(2e-4, -4e-7, 2e-4, 2e-4, FOCAL_LENGTH_MM)
    k3 = 1e-8 * FOCAL_LENGTH_MM**6
    # Sweep axis 45 deg above the IMU x axis, 15 deg from the tracker x axis, as in the
    # reference generator (acf_axis_tilt_deg = 45): the star field sweeps across the detector.
    axis = Rotation.from_euler("y", -45.0, degrees=True).apply([1.0, 0.0, 0.0])
    return Scenario(
        name="acf_sweep",
        description="Liu et al. 2017 Table 1: 0.5 deg/s sweep, 60 frames at 1 Hz",
        duration=60.0,
        motion_factory=lambda dur: ConstantRateSweep(np.eye(3), axis, np.deg2rad(0.5), dur),
        star_rate=1.0,
        centroid_noise_px=0.1,
        gyro_arw_deg_sqrth=0.005,
        effects={
            "installation": [2.0 * 3600.0, 2.0 * 3600.0, 2.0 * 3600.0],
            "principal_point": [10.0, -10.0],
            "radial_k1k2": liu[:2],
            "radial_k3": k3,
            "tangential": liu[2:],
            "gyro_bias": [0.03, 0.03, 0.03],
        },
    )


SCENARIOS: dict[str, Callable[[], Scenario]] = {
    "psce_rotations": _psce_rotations,
    "swaying": _swaying,
    "acf_sweep": _acf_sweep,
}


def get_scenario(name: str) -> Scenario:
    """Return a fresh copy of the named scenario."""
    try:
        return copy.deepcopy(SCENARIOS[name]())
    except KeyError:
        raise ScenarioError(
            f"unknown scenario {name!r}; known: {', '.join(sorted(SCENARIOS))}"
        ) from None
