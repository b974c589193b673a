"""The truth world: IMU samples, star centroids and auxiliary topics of a scenario.

Frames and chain (doc/interfaces.md §1): inertial ``i`` (GCRS = ICRS axes), Earth ``e``
(ITRS), local level ``n`` (ENU at the site), IMU ``b`` (``imu_link``), star tracker ``st``.

    R_i_b(t) = R_i_e(t) · R_e_n · R_n_b(t)        R_i_st(t) = R_i_b(t) · R_imu_st

``R_i_e(t) = R_i_e(t0) · Rz(Ω (t − t0))`` with ``R_i_e(t0)`` from ERFA (IAU 2006/2000A,
dut1 = 0, no polar motion) and Ω the Earth rotation angle rate: over a 2 h scenario this
differs from the full ERFA model by precession-nutation rates of < 0.01", and it makes the
gyro truth exactly the derivative of the attitude truth.

Gyro and accelerometer samples are the *mean* body rate and specific force over the
interval ending at the stamp (contract §2), computed by 3-point Gauss-Legendre quadrature of
the closed-form rates; slew corners fall on sample boundaries, so the quadrature error is
far below the sensor noise.  Sensor model: ``w_meas = (I + E) w_true + bias + noise``.

The truth is rendered through the effect classes themselves (one implementation of every
physical effect, shared with the filters and the diagnosis): the ``--effect`` values become
the parameters θ of a :class:`~stellar_cal_ros.methods.star_model.StarModel` over the
scenario's nominal calibration (:meth:`~stellar_cal_ros.effects.base.Effect.from_simulation`),
the IMU error model is its ``sensor_model`` (``w_meas = (I + E) w_true + b + noise``) and every
star frame is its ``predict`` with the true attitude: catalogue directions (Hipparcos 2 J2000.0
places, as the messages carry them) → DIRECTION effects (proper motion to the date,
aberration, refraction) → tracker frame at the true exposure time (TIME effects: stamp +
time_offset) → installation (TRACKER effects) → camera (CAMERA effects: principal point,
focal length, distortion, tilt, thermal drift) → Gaussian noise.  A user's effect file is
simulated the same way (``stellar-cal simulate --effect-module FILE.py --effect ID=V``).
Three simulator-only effects that no library effect models (``mount_flexure``,
``magnitude_bias``, ``misidentification``, :data:`~.truth_effects.SIM_ONLY`) test that the
diagnosis reports what it cannot explain.
"""

from __future__ import annotations

import copy
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from stellar_cal_ros import __version__
from stellar_cal_ros.core import earth
from stellar_cal_ros.core.camera import CameraModel
from stellar_cal_ros.core.catalog import load_catalog, radec_to_unit
from stellar_cal_ros.core.rotation import so3_exp
from stellar_cal_ros.core.types import ImuSeries, NavSatSeries, ScalarSeries, StarFrame
from stellar_cal_ros.core.units import ARCSEC, DEG_PER_HOUR
from stellar_cal_ros.effects import registry
from stellar_cal_ros.effects.base import Effect, FrameContext, Stage
from stellar_cal_ros.errors import ScenarioError
from stellar_cal_ros.io.bag import BagWriter
from stellar_cal_ros.io.calibration import Calibration, save_calibration
from stellar_cal_ros.sim.scenarios import Scenario
from stellar_cal_ros.sim.truth_effects import SIM_ONLY, merged_effects

IMU_FRAME = "imu_link"
STAR_TRACKER_FRAME = "star_tracker_optical_frame"
MAX_STARS_PER_FRAME = 200
_GL_NODES = np.array([-np.sqrt(0.6), 0.0, np.sqrt(0.6)])
_GL_WEIGHTS = np.array([5.0, 8.0, 5.0]) / 18.0  # sum to 1: a mean over the interval


@dataclass
class SimulationResult:
    """Everything a simulation produced (what goes into the bag and the YAML files)."""

    scenario: Scenario
    imu: ImuSeries
    star_frames: list[StarFrame]
    navsat: NavSatSeries
    head_temperature: ScalarSeries
    air_temperature: ScalarSeries
    pressure: ScalarSeries
    truth: Calibration
    prior: Calibration
    effects: dict[str, np.ndarray]
    meta: dict[str, Any] = field(default_factory=dict)
    truth_world: TruthWorld | None = None


class TruthWorld:
    """Closed-form truth of attitude, rates and specific force for one scenario run."""

    def __init__(self, scenario: Scenario, duration: float, effects: dict[str, np.ndarray]):
        self.scenario = scenario
        self.duration = duration
        self.effects = effects
        self.t0 = scenario.start_posix
        self.site = scenario.site
        self.motion = scenario.motion(duration)
        self.omega_earth = earth.ERA_RATE
        self.R_i_e0 = earth.R_itrs_gcrs(self.t0).T
        self.R_e_n = earth.R_itrs_enu(self.site)
        self.gravity_e = earth.gravity_itrs(self.site)
        self.site_e = earth.site_itrs(self.site)
        self.nominal = nominal_calibration(scenario)
        self.model, self.theta = truth_model(self.nominal, effects)

    # --- attitude and rates -------------------------------------------------------------
    def R_i_e(self, t: np.ndarray) -> np.ndarray:
        """Earth attitude in the inertial frame at relative times ``t`` (N, 3, 3)."""
        t = np.atleast_1d(t)
        return self.R_i_e0 @ so3_exp(np.outer(self.omega_earth * t, [0.0, 0.0, 1.0]))

    def R_i_b(self, t: np.ndarray) -> np.ndarray:
        """IMU attitude in the inertial frame at relative times ``t`` (N, 3, 3)."""
        return self.R_i_e(t) @ self.R_e_n @ self.motion.attitude(t)

    def omega_ib_b(self, t: np.ndarray) -> np.ndarray:
        """Body rate w.r.t. inertial space in the body frame (N, 3), rad/s."""
        R_n_b = self.motion.attitude(t)
        w_ie_n = self.R_e_n.T @ np.array([0.0, 0.0, self.omega_earth])
        return np.einsum("nji,j->ni", R_n_b, w_ie_n) + self.motion.rate(t)

    def specific_force_b(self, t: np.ndarray) -> np.ndarray:
        """Specific force in the body frame (N, 3), m/s^2.

        ``f_e = a_e + 2 Ω×v_e + Ω×(Ω×Δp_e) − g_e``: Earth-relative kinematics of the
        displacement ``Δp`` from the site plus the site's gravity (gravitation + centrifugal).
        """
        Om = np.array([0.0, 0.0, self.omega_earth])
        dp = self.motion.position(t) @ self.R_e_n.T
        v = self.motion.velocity(t) @ self.R_e_n.T
        a = self.motion.acceleration(t) @ self.R_e_n.T
        f_e = a + 2 * np.cross(Om, v) + np.cross(Om, np.cross(Om, dp)) - self.gravity_e
        R_n_b = self.motion.attitude(t)
        return np.einsum("nji,nj->ni", R_n_b, f_e @ self.R_e_n)

    def interval_means(self, t_end: np.ndarray, dt: float, fn) -> np.ndarray:
        """Mean of ``fn`` over ``(t_end − dt, t_end]`` by Gauss-Legendre quadrature."""
        mid = t_end - 0.5 * dt
        acc = np.zeros((t_end.size, 3))
        for x, w in zip(_GL_NODES, _GL_WEIGHTS, strict=True):
            acc += w * fn(mid + 0.5 * dt * x)
        return acc

    def installation(self) -> Rotation:
        """True ``R_imu_st`` (without gravity-dependent flexure)."""
        R, _ = self.model.installation_at(self.theta, FrameContext(stamp=self.t0))
        return Rotation.from_matrix(R)

    def head_temperature(self, t: np.ndarray) -> np.ndarray:
        """Optical-head temperature (°C) at relative times ``t``."""
        s = self.scenario
        return s.head_temperature_ambient_c + (
            s.head_temperature_start_c - s.head_temperature_ambient_c
        ) * np.exp(-np.asarray(t) / s.head_temperature_tau_s)

    def camera(self) -> CameraModel:
        """True camera at the thermal reference temperature."""
        ctx = FrameContext(stamp=self.t0,
                           head_temperature_c=self.scenario.head_temperature_ref_c)
        return self.model.camera_at(self.theta, ctx)

    def attitude_near(self, stamp_rel: float):
        """The model's attitude function ``shift -> (R_i_b, ω_b)`` around one frame stamp.

        ``shift`` is seconds after the frame's reported stamp (relative time ``stamp_rel``).
        """

        def attitude(shift: float) -> tuple[np.ndarray, np.ndarray]:
            t = np.array([stamp_rel + shift])
            return self.R_i_b(t)[0], self.omega_ib_b(t)[0]

        return attitude


class MountFlexure(Effect):
    """Simulator-only: tracker rotation ∝ lateral gravity in the tracker frame.

    ``ctx.gravity_st``: the direction of the load the mount carries, minus the specific
    force (gravity on a still base; gravity and the base's acceleration on a moving one).
    Not in the library: the diagnosis must report it as unexplained structure.
    """

    id = "mount_flexure"
    stage = Stage.TRACKER
    parameter_names = ("arcsec_per_g",)
    units = ("arcsec",)
    default_sigma = (1.0,)

    def tracker_rotation(self, value, ctx):  # noqa: D102
        return value[0] * ARCSEC * np.cross([0.0, 0.0, 1.0], ctx.gravity_st)


def nominal_calibration(scenario: Scenario) -> Calibration:
    """The scenario's nominal (datasheet) values: what the truth is a deviation from."""
    cal = _prior_calibration_of(scenario)
    cal.sigma = {}
    cal.effects = {"thermal_focal_length": {
        "coefficient_per_c": 0.0,
        "reference_temperature_c": scenario.head_temperature_ref_c}}
    return cal


def truth_model(nominal: Calibration, effects: dict[str, np.ndarray]):
    """``(StarModel, θ_true)`` of the non-zero effects over the nominal calibration.

    Library (and registered user) effects take their parameters from
    :meth:`Effect.from_simulation`; the simulator-only ``mount_flexure`` is a TRACKER effect
    of this module; ``magnitude_bias`` and ``misidentification`` act on the rendered
    centroids and identities (:func:`_simulate_stars`).
    """
    from stellar_cal_ros.methods.star_model import StarModel

    ids = [e for e in registry.available() if e in effects and np.any(effects[e] != 0.0)]
    effs = registry.create_many(ids) if ids else []
    flex = effects.get("mount_flexure")
    if flex is not None and np.any(flex != 0.0):
        effs.append(MountFlexure())
    theta = []
    for eff in effs:
        if eff.id == "mount_flexure":
            theta.append(np.asarray(flex, dtype=float))
        else:
            theta.append(eff.from_simulation(effects[eff.id], nominal))
    model = StarModel(effs, nominal)
    return model, (np.concatenate(theta) if theta else np.zeros(0))


def simulate(
    scenario: Scenario,
    *,
    duration: float | None = None,
    seed: int = 0,
    effects: dict[str, Any] | None = None,
    paired_with: dict[str, Any] | None = None,
) -> SimulationResult:
    """Run the truth world of ``scenario`` and return the sensor data and calibrations.

    Parameters
    ----------
    scenario : Scenario
        The scenario (see :func:`stellar_cal_ros.sim.scenarios.get_scenario`).
    duration : float, optional
        Seconds to simulate (default: the scenario's).
    seed : int
        Seed of every random draw: the same seed gives byte-identical data.
    effects : dict, optional
        Effect values overriding the scenario's (units in :mod:`.truth_effects`).
    paired_with : dict, optional
        The effects of a bag this one is *paired* with (an injection: the same seed and
        these effects, plus what ``effects`` adds).  The stars whose centroid noise is
        drawn, and their order in the random stream, are then that bag's, so every star
        both bags hold gets the same noise, whatever the added effects do to the camera,
        the exposure time or the installation (a wider cone would shift every later
        draw); stars only this bag's cone holds get noise from a separate stream.  Without
        it (the default) the bag is exactly what the seed and ``effects`` give.
    """
    duration = float(scenario.duration if duration is None else duration)
    if not duration > 0:
        raise ScenarioError(f"duration must be positive, got {duration}")
    eff = merged_effects(scenario.effects, effects)
    rng = np.random.default_rng(seed)
    world = TruthWorld(scenario, duration, eff)
    t0 = scenario.start_posix

    imu = _simulate_imu(world, rng)
    reference = None
    if paired_with is not None:
        ref_eff = merged_effects(scenario.effects, paired_with)
        if set(ref_eff) != set(eff) or any(
                not np.array_equal(ref_eff[k], eff[k]) for k in eff):
            reference = TruthWorld(scenario, duration, ref_eff)
    frames, star_stats = _simulate_stars(world, rng, reference)
    aux = _simulate_aux(world)
    truth = _truth_calibration(world)
    prior = _prior_calibration(world)
    meta = {
        "generator": f"stellar_cal_ros {__version__}",
        "scenario": scenario.name,
        "seed": seed,
        "duration_s": duration,
        "t0_posix_ns": int(round(t0 * 1e9)),
        "imu_rate_hz": scenario.imu_rate,
        "star_rate_hz": scenario.star_rate,
        "centroid_noise_px": scenario.centroid_noise_px,
        "gyro_arw_deg_sqrth": scenario.gyro_arw_deg_sqrth,
        "accel_vrw_mps_sqrth": scenario.accel_vrw_mps_sqrth,
        "site": [scenario.site.latitude_deg, scenario.site.longitude_deg, scenario.site.height_m],
        "effects": {k: v.tolist() for k, v in eff.items()},
        "counts": {"/imu/data": int(imu.stamp_ns.size), "/star_tracker/stars": len(frames)},
        "stars_per_frame": star_stats,
    }
    return SimulationResult(
        scenario=scenario,
        imu=imu,
        star_frames=frames,
        navsat=aux["navsat"],
        head_temperature=aux["head"],
        air_temperature=aux["air"],
        pressure=aux["pressure"],
        truth=truth,
        prior=prior,
        effects=eff,
        meta=meta,
        truth_world=world,
    )


def _simulate_imu(world: TruthWorld, rng: np.random.Generator) -> ImuSeries:
    s = world.scenario
    dt = 1.0 / s.imu_rate
    n = int(np.floor(world.duration * s.imu_rate + 1e-9))
    k = np.arange(1, n + 1)
    t_end = k * dt
    w = world.interval_means(t_end, dt, world.omega_ib_b)
    f = world.interval_means(t_end, dt, world.specific_force_b)
    # the sensor error model of the effects: w_meas = (I + E) w_true + b
    bg, Eg, _, _ = world.model.sensor_model(world.theta, Stage.GYRO)
    ba, Ea, _, _ = world.model.sensor_model(world.theta, Stage.ACCEL)
    gyro_sigma = np.deg2rad(s.gyro_arw_deg_sqrth) / 60.0 / np.sqrt(dt)
    accel_sigma = s.accel_vrw_mps_sqrth / 60.0 / np.sqrt(dt)
    w_meas = w + w @ Eg.T + bg + gyro_sigma * rng.standard_normal((n, 3))
    f_meas = f + f @ Ea.T + ba + accel_sigma * rng.standard_normal((n, 3))
    stamp_ns = int(round(s.start_posix * 1e9)) + np.round(t_end * 1e9).astype(np.int64)
    # Covariances as a strapdown IMU driver reports them: white-noise variance per sample.
    return ImuSeries(stamp_ns=stamp_ns, angular_velocity=w_meas, linear_acceleration=f_meas,
                     frame_id=IMU_FRAME,
                     angular_velocity_covariance=np.diag([gyro_sigma**2] * 3).ravel(),
                     linear_acceleration_covariance=np.diag([accel_sigma**2] * 3).ravel())


def _frame_contexts(world: TruthWorld) -> tuple[np.ndarray, int, list[FrameContext]]:
    """Relative frame stamps, the first stamp (ns) and each frame's context."""
    s = world.scenario
    stamps_rel = s.star_phase_s + np.arange(0.0, world.duration, 1.0 / s.star_rate)
    stamps_rel = stamps_rel[stamps_rel <= world.duration - 1e-9]
    stamp0 = int(round(s.start_posix * 1e9))
    head = world.head_temperature(stamps_rel)
    air = _air_temperature(s, stamps_rel)
    contexts = [FrameContext(stamp=(stamp0 + int(round(t * 1e9))) * 1e-9, site=world.site,
                             head_temperature_c=float(h), air_temperature_c=float(a),
                             pressure_pa=s.pressure_hpa * 100.0)
                for t, h, a in zip(stamps_rel.tolist(), head.tolist(), air.tolist(),
                                   strict=True)]
    return stamps_rel, stamp0, contexts


def _exposure_attitudes(world: TruthWorld, stamps_rel, contexts):
    """True exposure times (TIME effects, e.g. the time offset) and ``R_i_st`` at them."""
    model, theta = world.model, world.theta
    t_true = stamps_rel + np.array([model.time_shift(theta, c)[0] for c in contexts])
    if np.any(t_true < 0) or np.any(t_true > world.duration + 1.0):
        raise ScenarioError("time_offset moves exposures outside the simulated span")
    return t_true, world.R_i_b(t_true) @ world.installation().as_matrix()


def _star_cone(world: TruthWorld, R_i_st: np.ndarray,
               u_j2000: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Candidate ``(frame, star)`` pairs by J2000 direction: 1 deg beyond the half-diagonal.

    Frame-major, stars in catalogue order within a frame: the order the noise is drawn in.
    """
    s, cam = world.scenario, world.camera()
    half_diag = np.arctan(np.hypot(s.width, s.height) / 2 / min(cam.fx, cam.fy))
    cos_lim = np.cos(half_diag + np.deg2rad(1.0))
    boresight_i = R_i_st[:, :, 2]
    frame_idx, star_idx = [], []
    for a in range(0, len(R_i_st), 512):
        cosang = boresight_i[a:a + 512] @ u_j2000.T
        fi, si = np.nonzero(cosang > cos_lim)
        frame_idx.append(fi + a)
        star_idx.append(si)
    return np.concatenate(frame_idx), np.concatenate(star_idx)


def _simulate_stars(
    world: TruthWorld, rng: np.random.Generator, reference: TruthWorld | None = None
) -> tuple[list[StarFrame], dict[str, float]]:
    s, e = world.scenario, world.effects
    cat = load_catalog(mag_limit=s.mag_limit)
    radec_msg = cat.message_radec()  # what a tracker message carries (J2000.0 place)
    u_j2000 = radec_to_unit(*radec_msg)  # ... and the unit vectors a filter makes of it

    stamps_rel, stamp0, contexts = _frame_contexts(world)
    model, theta = world.model, world.theta
    t_true, R_i_st = _exposure_attitudes(world, stamps_rel, contexts)

    # Pass 1: candidate stars by direction.  A paired bag (an injection) takes the
    # reference bag's candidates, in its order, and appends those only its own cone holds.
    frame_idx, star_idx = _star_cone(world, R_i_st, u_j2000)
    n_paired = len(star_idx)
    if reference is not None:
        _, R_ref = _exposure_attitudes(reference, stamps_rel, _frame_contexts(reference)[2])
        f_ref, s_ref = _star_cone(reference, R_ref, u_j2000)
        n_cat = len(u_j2000)
        extra = ~np.isin(frame_idx * n_cat + star_idx, f_ref * n_cat + s_ref)
        frame_idx = np.concatenate([f_ref, frame_idx[extra]])
        star_idx = np.concatenate([s_ref, star_idx[extra]])
        n_paired = len(s_ref)

    # Pass 2: each frame rendered through the effects with the true attitude (the filters'
    # measurement function, StarModel.predict, at the true parameters)
    # the load a mount bends under (MountFlexure): the specific force's direction, gravity
    # and the base's acceleration alike (a mount cannot tell them apart; what the
    # accelerometer measures, the diagnosis's flexure probe and the twins use).  On a still
    # base it is the gravity direction; on the swaying base the sway's acceleration turns it
    # by ~0.05 rad RMS, as much as the sway turns gravity (until 2026-11-27: gravity alone)
    g_st = -world.specific_force_b(t_true) @ world.installation().as_matrix()
    g_st /= np.linalg.norm(g_st, axis=1, keepdims=True)
    uv = np.full((len(star_idx), 2), np.nan)
    d_z = np.full(len(star_idx), -1.0)
    by_frame = np.argsort(frame_idx, kind="stable")
    bounds = np.searchsorted(frame_idx[by_frame], np.arange(len(stamps_rel) + 1))
    for j, ctx in enumerate(contexts):
        if bounds[j] == bounds[j + 1]:
            continue
        sel = by_frame[bounds[j]:bounds[j + 1]]
        ctx.catalog_id = cat.hip[star_idx[sel]].astype(np.int64)
        ctx.gravity_st = g_st[j]
        pred = model.predict(theta, u_j2000[star_idx[sel]], ctx,
                             world.attitude_near(stamps_rel[j]), jacobians=False)
        uv[sel] = pred.uv
        d_z[sel] = pred.directions_st[:, 2]
    ok = (d_z > 0) & np.all(np.isfinite(uv), axis=1)

    mag = cat.magnitude[star_idx]
    mb = e["magnitude_bias"]
    if mb[0] != 0.0:
        direction = np.array([np.cos(np.deg2rad(mb[1])), np.sin(np.deg2rad(mb[1]))])
        uv = uv + (mb[0] * (mag - 4.0))[:, None] * direction
    noise = rng.standard_normal(uv.shape) if reference is None else np.concatenate(
        [rng.standard_normal((n_paired, 2)),  # the reference bag's draws, star by star
         rng.spawn(1)[0].standard_normal((len(uv) - n_paired, 2))])
    uv = uv + s.centroid_noise_px * noise
    keep = ok & world.camera().in_image(np.nan_to_num(uv, nan=-1e9))
    frame_idx, star_idx, uv, mag = frame_idx[keep], star_idx[keep], uv[keep], mag[keep]

    ids = cat.hip[star_idx].astype(np.uint32)
    ra, dec = radec_msg[0][star_idx], radec_msg[1][star_idx]
    mis = e["misidentification"][0]
    if mis > 0.0:
        wrong = rng.random(len(ids)) < mis
        other = rng.integers(0, len(cat.hip), int(wrong.sum()))
        ids[wrong] = cat.hip[other].astype(np.uint32)
        ra, dec = ra.copy(), dec.copy()
        ra[wrong], dec[wrong] = radec_msg[0][other], radec_msg[1][other]

    frames: list[StarFrame] = []
    order = np.argsort(frame_idx, kind="stable")
    bounds = np.searchsorted(frame_idx[order], np.arange(len(stamps_rel) + 1))
    counts = []
    for j in range(len(stamps_rel)):
        sel = order[bounds[j]:bounds[j + 1]]
        sel = sel[np.argsort(mag[sel], kind="stable")][:MAX_STARS_PER_FRAME]
        counts.append(len(sel))
        frames.append(
            StarFrame(
                stamp_ns=stamp0 + int(round(stamps_rel[j] * 1e9)),
                frame_id=STAR_TRACKER_FRAME,
                exposure_time=s.exposure_time,
                catalog_id=ids[sel],
                right_ascension=ra[sel],
                declination=dec[sel],
                uv=uv[sel],
                magnitude=mag[sel],
                sigma=np.full(len(sel), s.centroid_noise_px),
            )
        )
    counts_arr = np.array(counts) if counts else np.zeros(1)
    stats = {"mean": float(counts_arr.mean()), "min": int(counts_arr.min()),
             "max": int(counts_arr.max())}
    return frames, stats


def _air_temperature(s: Scenario, t_rel: np.ndarray) -> np.ndarray:
    return s.air_temperature_c + s.air_temperature_rate_c_per_h * np.asarray(t_rel) / 3600.0


def _simulate_aux(world: TruthWorld) -> dict[str, Any]:
    s = world.scenario
    t_rel = np.arange(0.0, world.duration + 1e-9, 1.0 / s.aux_rate)
    stamp_ns = int(round(s.start_posix * 1e9)) + np.round(t_rel * 1e9).astype(np.int64)
    n = t_rel.size
    navsat = NavSatSeries(
        stamp_ns=stamp_ns,
        latitude_deg=np.full(n, s.site.latitude_deg),
        longitude_deg=np.full(n, s.site.longitude_deg),
        altitude_m=np.full(n, s.site.height_m),
        status=np.zeros(n, dtype=int),
    )
    head = ScalarSeries(stamp_ns, world.head_temperature(t_rel), np.full(n, 0.01),
                        STAR_TRACKER_FRAME)
    air = ScalarSeries(stamp_ns, _air_temperature(s, t_rel), np.full(n, 0.25), "environment")
    pressure = ScalarSeries(stamp_ns, np.full(n, s.pressure_hpa * 100.0), np.full(n, 100.0),
                            "environment")
    return {"navsat": navsat, "head": head, "air": air, "pressure": pressure}


def _truth_calibration(world: TruthWorld) -> Calibration:
    """The true values: the nominal calibration with every effect's truth stored by itself."""
    cal = copy.deepcopy(world.nominal)
    cal.effects = {}
    cal.method = "truth"
    model, theta = world.model, world.theta
    for eff in model.effects:
        if eff.id in SIM_ONLY:
            continue
        sl = model.slices[eff.id]
        eff.store(theta[sl], np.zeros(eff.size), cal)
    cal.sigma = {}
    for key in SIM_ONLY:  # not in the library: recorded for the tests that use them
        if np.any(world.effects[key] != 0.0):
            cal.effects[key] = {"value": world.effects[key].tolist()}
    return cal


def default_prior_sigma() -> dict[str, Any]:
    """Datasheet-level 1-sigma uncertainties of a prior (contract §3 layout)."""
    return {
        "camera": {
            "camera_matrix": {"rows": 3, "cols": 3,
                              "data": [20.0, 0.0, 20.0, 0.0, 20.0, 20.0, 0.0, 0.0, 0.0]},
            "distortion_coefficients": {"rows": 1, "cols": 5,
                                        "data": [0.3, 1.0, 0.002, 0.002, 2.0]},
        },
        "installation": {"rotation_vector": [float(np.deg2rad(0.2))] * 3},
        "gyro": {"bias": [float(0.05 * DEG_PER_HOUR)] * 3, "error_matrix": [1e-4] * 9},
        "accelerometer": {"bias": [1e-3] * 3, "error_matrix": [1e-4] * 9},
        "time_offset": 0.05,
    }


def _prior_calibration(world: TruthWorld) -> Calibration:
    return _prior_calibration_of(world.scenario)


def _prior_calibration_of(s: Scenario) -> Calibration:
    cam = CameraModel.pinhole(s.width, s.height, s.focal_length_px)
    sigma = default_prior_sigma()
    sigma.update(s.prior_sigma)
    return Calibration(
        camera=cam,
        installation=s.installation_nominal,
        gyro_bias=np.zeros(3),
        gyro_error_matrix=np.zeros((3, 3)),
        accel_bias=np.zeros(3),
        accel_error_matrix=np.zeros((3, 3)),
        time_offset=0.0,
        effects={},
        sigma=sigma,
        method="prior",
        stamp=s.start_posix,
    )


def write_simulation(result: SimulationResult, bag_path: str | Path,
                     write_frames: Callable[[BagWriter], None] | None = None
                     ) -> dict[str, Path]:
    """Write the bag, ``BAG.truth.yaml``, ``BAG.prior.yaml`` and ``BAG.meta.json``.

    ``write_frames(writer)`` writes the star data instead of the centroid messages (the
    images of :func:`stellar_cal_ros.sim.image_bag.write_image_simulation`).
    """
    bag_path = Path(bag_path)
    bag_path.parent.mkdir(parents=True, exist_ok=True)
    stem = bag_path.with_suffix("")
    paths = {
        "bag": bag_path,
        "truth": Path(f"{stem}.truth.yaml"),
        "prior": Path(f"{stem}.prior.yaml"),
        "meta": Path(f"{stem}.meta.json"),
    }
    with BagWriter(bag_path) as w:
        w.write_imu(result.imu, "/imu/data")
        if write_frames is not None:
            write_frames(w)
        else:
            w.write_star_frames(result.star_frames, "/star_tracker/stars")
        w.write_navsat(result.navsat, "/gnss/fix")
        w.write_scalar(result.head_temperature, "/star_tracker/temperature", kind="temperature")
        w.write_scalar(result.air_temperature, "/environment/temperature", kind="temperature")
        w.write_scalar(result.pressure, "/environment/pressure", kind="pressure")
    save_calibration(result.truth, paths["truth"])
    save_calibration(result.prior, paths["prior"])
    meta = dict(result.meta)
    meta["files"] = {k: p.name for k, p in paths.items() if k != "meta"}
    paths["meta"].write_text(json.dumps(meta, indent=1))
    return paths


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


__all__ = [
    "SimulationResult",
    "TruthWorld",
    "default_prior_sigma",
    "simulate",
    "write_simulation",
]
