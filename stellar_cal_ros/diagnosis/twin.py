"""``stellar-cal twin``: the user's own bag as the test bench (issue 21 item 4).

A twin is a synthetic bag with the user's trajectory, stamps, stars and measured noise,
rendered through the effect classes with the calibration the user's run estimated — plus
any effects injected (``--effect ID=VALUE``, the units of ``simulate --effect``).  It
answers "would a 5 arcsec misalignment have been caught on *my* data?": diagnose the twin
with the effect injected, and compare with the twin without it.

How it is made
--------------
* **Trajectory**: the user's gyro samples corrected by the calibration's gyro model,
  ``ω = (I + E)⁻¹ (w − b)``, smoothed (:func:`smooth_samples`: their noise is no motion),
  integrated (coning-compensated) from the attitude the first
  usable frame's stars give (the calibration's camera and installation).  This *is* the
  twin's true attitude; the accelerometer's specific force is corrected the same way.
* **IMU**: at the user's IMU stamps, the true rates and forces rendered through the twin's
  sensor model (the calibration's biases and error matrices plus the injected GYRO /
  ACCEL effects) plus white noise at the method's random walks times the measured noise
  scales (the calibration's ``consistency.noise``).
* **Stars**: per user frame (same stamp), the same identified stars (catalogue id, RA/Dec,
  magnitude), rendered through :meth:`StarModel.predict_frames` at the true attitude (the
  simulator's chain), plus noise at the σ the run measured for them (their message's σ
  times the star scale, or the measured σ of stars whose message says 0); the message
  keeps the σ the user's message stated.  When the run measured the stars' noise
  correlated from frame to frame (``consistency.noise.star_correlated``: the scale it
  applied is the scatter within frames times √((1+ρ)/(1−ρ))), each star's noise is an
  AR(1) along its track with that ρ and the scatter as its marginal σ (the simulator's
  :class:`~stellar_cal_ros.sim.tracker_errors.Ar1Tracks`; white + AR(1) noise, ``ar_share``
  ``w`` < 1: the AR(1) carries ``w`` of the variance, the factor √((1 − w) + w (1+ρ)/(1−ρ))).
  Unidentified stars are left out (counted).
* the site, temperatures and pressure are the user's.

The truth (``TWIN.truth.yaml``) is the calibration with the injected effects added; the
prior (``TWIN.prior.yaml``) is the calibration as given.  The same seed gives the same
noise, so twins with and without an effect form a paired injection.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from stellar_cal_ros.core.attitude import fit_frame_attitude
from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.core.rotation import (
    quat_from_rotvec,
    quat_to_matrix,
    so3_exp,
)
from stellar_cal_ros.core.strapdown import attitude_increments, quat_cumprod
from stellar_cal_ros.core.types import ImuSeries, NavSatSeries, StarFrame
from stellar_cal_ros.effects import registry
from stellar_cal_ros.effects.base import Stage
from stellar_cal_ros.errors import ModelError
from stellar_cal_ros.io.calibration import Calibration, save_calibration
from stellar_cal_ros.methods.frames import (
    BagData,
    InputColumns,
    frame_context,
    frame_inputs,
    frame_inputs_columns,
)
from stellar_cal_ros.methods.star_model import StarModel
from stellar_cal_ros.sim.tracker_errors import Ar1Tracks, frame_shifts, stamp_errors
from stellar_cal_ros.sim.truth_effects import SIM_ONLY, normalize_effect

IMU_FRAME = "imu_link"
STAR_TRACKER_FRAME = "star_tracker_optical_frame"


@dataclass
class Twin:
    """A twin in memory: its bag data, its truth, and what was left out."""

    data: BagData
    truth: Calibration
    prior: Calibration
    injected: dict[str, np.ndarray]
    noise: NoiseScales
    counts: dict[str, int] = field(default_factory=dict)


def twin_model(calibration: Calibration, method: str, injected: dict[str, np.ndarray]
           ) -> tuple[StarModel, np.ndarray]:
    """The twin's StarModel (the calibration's effects + the injected ones) and its θ."""
    from stellar_cal_ros.methods import registry as methods
    from stellar_cal_ros.sim.world import MountFlexure

    ids = list(methods.get(method).baseline)
    for e in list(calibration.estimated) + [e for e in injected if e not in SIM_ONLY]:
        if e in registry.EFFECTS and e not in ids:
            ids.append(e)
    effs = registry.create_many(ids)
    theta = []
    for eff in effs:
        value = np.asarray(eff.initial(calibration)[0], dtype=float)
        if eff.id in injected:
            scale = np.asarray(eff.simulation_scale, dtype=float) \
                if eff.simulation_scale is not None else 1.0
            value = value + np.asarray(injected[eff.id], dtype=float) * scale
        theta.append(value)
    flex = injected.get("mount_flexure")
    if flex is not None and np.any(flex != 0.0):
        effs.append(MountFlexure())
        theta.append(np.asarray(flex, dtype=float))
    return StarModel(effs, calibration), (np.concatenate(theta) if theta else np.zeros(0))


def _truth(calibration: Calibration, model: StarModel, theta: np.ndarray,
           injected: dict[str, np.ndarray]) -> Calibration:
    cal = copy.deepcopy(calibration)
    cal.method = "truth"
    for eff in model.effects:
        if eff.id in SIM_ONLY:
            continue
        eff.store(theta[model.slices[eff.id]], np.zeros(eff.size), cal)
    cal.sigma = {}
    cal.estimated = []
    for key in SIM_ONLY:
        if key in injected and np.any(injected[key] != 0.0):
            cal.effects[key] = {"value": injected[key].tolist()}
    cal.extra = {k: v for k, v in cal.extra.items() if k not in ("consistency", "derived",
                                                                  "covariance_file")}
    return cal


class _Trajectory:
    """The twin's true attitude: integrated corrected rates, anchored on one frame."""

    def __init__(self, t: np.ndarray, w: np.ndarray, R_anchor: np.ndarray, t_anchor: float):
        dt = np.diff(t, prepend=t[0] - (np.median(np.diff(t)) if len(t) > 1 else 0.01))
        # sample k covers (t_start(k), t[k]]: the previous stamp (not held: 6 MB on 2 h)
        self._first = float(t[0] - dt[0])
        self.t, self.w = t, w
        phi = attitude_increments(w, dt, coning=True)
        # laid out as the scan works on it ((4, N) rows): quat_cumprod scans it in place
        # instead of a copy (23 MB on a 2-h bag; the same numbers)
        q = np.empty((4, len(phi) + 1)).T
        q[0] = [0.0, 0.0, 0.0, 1.0]
        q[1:] = quat_from_rotvec(phi)
        del phi  # not held through the scan (17 MB on a 2-h bag)
        # the attitude after each sample, as quaternions (q_rel[0] at t_start[0], q_rel[k+1] at
        # t[k]); turned into matrices only where a frame looks (a matrix per IMU sample of a
        # 2-h bag was 52 MB and 0.3 s; quat_to_matrix is row by row, the same numbers)
        self.q_rel = quat_cumprod(q, overwrite=True)
        del q
        R_a = self._relative(t_anchor)
        self.R0 = R_anchor @ R_a.T

    def t_start(self, k):
        """Start of sample ``k`` (index or array): the stamp before it."""
        k = np.asarray(k)
        return np.where(k > 0, self.t[np.maximum(k - 1, 0)], self._first)

    def _relative(self, t: float) -> np.ndarray:
        k = int(np.clip(np.searchsorted(self.t, t, side="left"), 0, len(self.t) - 1))
        # sample k covers (t_start[k], t[k]]: rotate from its start by its rate
        return quat_to_matrix(self.q_rel[k]) @ so3_exp(self.w[k] * (t - self.t_start(k)))

    def rate(self, t: float) -> np.ndarray:
        return self.w[int(np.clip(np.searchsorted(self.t, t, side="left"), 0, len(self.t) - 1))]

    def R_i_b(self, t: float) -> np.ndarray:
        return self.R0 @ self._relative(t)

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`R_i_b` and :meth:`rate` at many times ``t`` (s): (F, 3, 3), (F, 3)."""
        t = np.asarray(t, dtype=float)
        k = np.clip(np.searchsorted(self.t, t, side="left"), 0, len(self.t) - 1)
        w = self.w[k]
        return self.R0 @ (quat_to_matrix(self.q_rel[k]) @ so3_exp(
            w * (t - self.t_start(k))[:, None])), w

    def near(self, t_rel: float):
        def attitude(shift: float) -> tuple[np.ndarray, np.ndarray]:
            return self.R_i_b(t_rel + shift), self.rate(t_rel + shift)

        return attitude


def _method_noise(method: str) -> tuple[float, float, float]:
    """(star default σ px, gyro ARW rad/√s, accel VRW m/s/√s) of ``method``'s defaults."""
    from stellar_cal_ros.core.units import DEG_PER_SQRT_HOUR
    from stellar_cal_ros.methods import registry as methods
    from stellar_cal_ros.methods.swaying import SwayingConfig

    spec = methods.get(method)
    # a batch method (bundle: camera only) has no filter configuration: its own σ of σ-0
    # stars, the IMU's at the PSCE defaults (no run of it reads an IMU).  Its probe runs
    # failed with "'NoneType' object is not callable" (unseen case bundle_s06)
    cfg = (spec.config_cls or methods.get("psce").config_cls)()
    vrw = getattr(cfg, "accel_vrw_mps_sqrth", SwayingConfig().accel_vrw_mps_sqrth) / 60.0
    if spec.config_cls is None:
        from stellar_cal_ros.methods.bundle import DEFAULT_SIGMA_PX

        return DEFAULT_SIGMA_PX, cfg.gyro_arw_deg_sqrth * DEG_PER_SQRT_HOUR, vrw
    return cfg.centroid_sigma_px, cfg.gyro_arw_deg_sqrth * DEG_PER_SQRT_HOUR, vrw


class _Stars(NamedTuple):
    """What :func:`frame_context` reads of a frame's inputs."""

    catalog_id: np.ndarray
    magnitude: np.ndarray


@dataclass
class SceneStars:
    """Each user frame's usable stars and context inputs, in arrays over the bag.

    What :func:`frame_inputs` and :func:`frame_context` give per frame, kept as columns
    (a ``(FrameInputs, FrameContext)`` pair per frame cost ≈ 7 kB a frame, ≈ 100 MB of a
    2-h bag's 14 400 frames): star rows are the frames' usable stars in order.
    """

    stamp_ns: np.ndarray  #: (F,) int64, the user frames' stamps
    count: np.ndarray  #: (F,) usable stars per frame
    messages: np.ndarray  #: (F,) stars in each frame's message (usable or not)
    usable: np.ndarray  #: every message star of every frame: usable (frame_inputs' ``ok``)
    u_i: np.ndarray  #: (N, 3) catalogue directions of the usable stars
    catalog_id: np.ndarray  #: (N,) int64
    magnitude: np.ndarray  #: (N,)
    unidentified: np.ndarray  #: (F,) centroids without identity per frame
    head: np.ndarray  #: (F,) head temperature at the stamp, °C (NaN: none)
    air: np.ndarray  #: (F,) air temperature, °C
    pressure: np.ndarray  #: (F,) Pa
    gravity: np.ndarray | None  #: (F, 3) unit gravity in the tracker frame, None: unknown
    #: per frame the context's ``extra`` (the direction effects' caches), shared by the
    #: renders of one scene as the contexts were
    extra: list[dict]
    #: (N,) the usable stars' σ as their messages state it (px; 0 or NaN: none stated)
    stated_sigma: np.ndarray

    def context(self, j: int, site, start: int):
        """Frame ``j``'s context (its stars from row ``start``), as :func:`frame_context`."""
        n = int(self.count[j])
        stars = _Stars(self.catalog_id[start:start + n], self.magnitude[start:start + n])
        ctx = frame_context(int(self.stamp_ns[j]), stars, site, {}, keys=())
        ctx.head_temperature_c = float(self.head[j])
        ctx.air_temperature_c = float(self.air[j])
        ctx.pressure_pa = float(self.pressure[j])
        if self.gravity is not None:
            ctx.gravity_st = self.gravity[j]
        ctx.extra = self.extra[j]
        return ctx


@dataclass
class TwinScene:
    """What every twin of one bag under one calibration shares (:func:`twin_scene`).

    The true trajectory, rates and forces come from the user's samples through the
    calibration's model, and each frame's usable stars and context from the message: none
    depends on the injected effects, the seed or the noise, so twins of one bag (the
    reliability probe renders five) make them once.
    """

    method: str
    default_sigma: float
    arw: float
    vrw: float
    t: np.ndarray
    w_true: np.ndarray
    #: None in a scene for twins without the IMU (``twin_scene(imu=False)``)
    f_true: np.ndarray | None
    traj: _Trajectory
    #: every user frame's usable stars and context, in arrays (:class:`SceneStars`)
    stars: SceneStars


#: the span (s) of the centred mean that takes the IMU's noise out of the twin's true
#: motion: 11 samples at 100 Hz (:func:`smooth_count`)
SMOOTH_S = 0.1


def smooth_count(t: np.ndarray) -> int:
    """The samples in :func:`smooth_samples`' mean for IMU stamps ``t`` (s): a fixed time.

    The largest odd count whose span ``(n − 1)/rate`` is at most :data:`SMOOTH_S` (to
    0.1 % of a sample, for the stamps' jitter; the rate from the median step), at least
    3: 11 at 100 Hz, 5 at 50 Hz, 21 at 200 Hz.  A count fixed in samples would keep less
    of the motion at a lower rate (11 samples at 50 Hz keep 0.71 of a 2 Hz motion; 5 keep
    0.94, 11 at 100 Hz 0.92).
    """
    dt = np.diff(np.asarray(t, dtype=float))
    step = float(np.median(dt)) if len(dt) else 0.0
    if not np.isfinite(step) or step <= 0.0:
        return 3
    half = int(np.floor(0.5 * SMOOTH_S / step + 1e-3))  # stamps' jitter: 11 at 100 Hz
    return max(3, 2 * half + 1)


def smooth_samples(x: np.ndarray, n: int, in_place: bool = False) -> np.ndarray:
    """``x`` (rates or forces, a row per IMU sample): its centred mean of ``n`` samples.

    ``n`` odd, from :func:`smooth_count` (a fixed time, 0.1 s); the ends are padded with
    their own sample.  The white noise left in is ~1/n of its variance (the same noise
    density whatever the rate) and, low-passed, barely seen by the samples' own noise
    estimate (150 s psce twin at 100 Hz: the gyro's samples read x1.01 +- 0.006 of the
    noise rendered, x1.41 unsmoothed; swaying accelerometer x1.00, was x1.42).  Kept
    amplitude of a motion at 1 / 2 / 5 Hz: 0.98 / 0.92 / 0.57 at 100 Hz (11 samples),
    0.98 / 0.94 / 0.65 at 50 Hz (5), 0.98 / 0.93 / 0.60 at 200 Hz (21).  The twin's stars
    and IMU both follow the smoothed motion, so the twin is consistent whatever it smooths
    away.

    ``in_place``: the mean is written over ``x`` (a float array of the caller's own that it
    no longer needs; 17 MB less at the twin scene's peak on a 2-h bag).  The same numbers:
    the filter reads each column whole into its line buffer before writing it, and the
    columns do not overlap.
    """
    from scipy.ndimage import uniform_filter1d

    x = np.asarray(x, dtype=float)
    if len(x) < n:
        return x
    return uniform_filter1d(x, n, axis=0, mode="nearest", output=x if in_place else None)


def twin_scene(data: BagData, calibration: Calibration, method: str | None = None,
               imu: bool = True) -> TwinScene:
    """The shared part of every twin of ``data`` under ``calibration`` (see :func:`make_twin`).

    ``imu=False``: for twins made with ``make_twin(imu=False)`` only; the true forces are
    not kept (17 MB on a 2-h bag; the rates are the trajectory's).
    """
    from stellar_cal_ros.diagnosis.context import LOAD_WINDOW_S, gravity_in_tracker

    method = method or (calibration.method if calibration.method in ("psce", "swaying_base")
                        else "psce")
    model_cal, theta_cal = twin_model(calibration, method, {})
    cam = calibration.camera
    default_sigma, arw, vrw = _method_noise(method)
    t = np.asarray(data.imu_t, dtype=float)
    if len(t) < 2 or not data.frames:
        raise ModelError("twin: the bag needs IMU samples and star frames")
    # true rates and forces: the user's samples through the calibration's sensor model,
    # smoothed: the samples' own noise is no motion of the twin (left in, the twin's IMU
    # carried it plus its fresh noise: the gyro's samples read 1.41x the measured noise)
    n = smooth_count(t)
    # (corrected_rates makes a new array: smoothed where it is, not into a second one)
    w_true = smooth_samples(model_cal.corrected_rates(
        theta_cal, np.asarray(data.imu_w, dtype=float)), n, in_place=True)
    f_true = smooth_samples(model_cal.corrected_rates(
        theta_cal, np.asarray(data.imu_f, dtype=float), Stage.ACCEL), n, in_place=True)
    grav = gravity_in_tracker(dataclasses.replace(data, imu_f=f_true), calibration,
                              np.array([f.stamp_ns * 1e-9 for f in data.frames]),
                              LOAD_WINDOW_S)  # the load an injected flexure follows
    if not imu:
        f_true = None  # not held while the trajectory is integrated
    # anchor: the first frame whose identified stars fit an attitude
    env = data.env()
    anchor = None
    for fr in data.frames:
        inp = frame_inputs(fr, cam.width, cam.height, default_sigma)
        if len(inp.uv) < 3:
            continue
        ctx = frame_context(int(fr.stamp_ns), inp, data.site, env)
        t_rel = (int(fr.stamp_ns) - data.t0_ns) * 1e-9 + model_cal.time_shift(theta_cal, ctx)[0]
        if not t[0] <= t_rel <= t[-1]:
            continue
        fit = fit_frame_attitude(cam, inp.uv, inp.u_i)
        anchor = (fit.R_i_st @ calibration.R_imu_st.T, t_rel)
        break
    if anchor is None:
        raise ModelError("twin: no frame with 3 identified stars inside the IMU span")
    traj = _Trajectory(t, w_true, anchor[0], anchor[1])
    return TwinScene(method, default_sigma, arw, vrw, t, w_true, f_true, traj,
                     _scene_stars(data, cam, default_sigma, env, grav))


#: frames of :func:`_scene_stars`' compiled calls (:func:`frame_inputs_columns`), one at a time:
#: its concatenated columns a few MB, not the 2-h bag's 460 000 stars at once
SCENE_CHUNK = 1000


def _scene_stars(data: BagData, cam, default_sigma: float, env, grav) -> SceneStars:
    """The frames' usable stars (:func:`frame_inputs`, per frame) and context inputs.

    The columns of :data:`SCENE_CHUNK` frames from one compiled call where it applies
    (:func:`frame_inputs_columns`: bit for bit :func:`frame_inputs`' usable stars,
    directions, identities and magnitudes, not cut into messages and stacked again: ≈ 0.3
    CPU-s less a 2-h bag's scene), else a frame at a time.
    """
    names = ("usable", "u_i", "catalog_id", "magnitude", "stated_sigma")
    parts: dict[str, list] = {k: [] for k in names}
    count, messages, unidentified = [], [], []
    for lo in range(0, len(data.frames), SCENE_CHUNK):
        part = data.frames[lo:lo + SCENE_CHUNK]
        got = frame_inputs_columns(part, cam.width, cam.height, default_sigma, compiled=True)
        if got is None:
            got = _columns_one_by_one(part, cam, default_sigma)
        ok = np.asarray(got.ok, dtype=bool).reshape(-1)
        # each message's centroids with catalogue id 0, from the rows' running count
        zero = np.zeros(len(ok) + 1, dtype=np.intp)
        np.cumsum(np.asarray(got.message_ids).reshape(-1) == 0, out=zero[1:])
        unidentified.append(zero[got.bounds[1:]] - zero[got.bounds[:-1]])
        count.append(got.counts[:, 0])
        messages.append(np.diff(got.bounds))
        parts["usable"].append(ok)
        parts["u_i"].append(np.asarray(got.u_i, dtype=float).reshape(-1, 3))
        parts["catalog_id"].append(np.asarray(got.catalog_id, dtype=np.int64).reshape(-1))
        parts["magnitude"].append(np.asarray(got.magnitude, dtype=float).reshape(-1))
        parts["stated_sigma"].append(np.asarray(got.message_sigma, dtype=float)[ok])
    empty = {"usable": np.zeros(0, bool), "u_i": np.zeros((0, 3)),
             "catalog_id": np.zeros(0, np.int64), "magnitude": np.zeros(0),
             "stated_sigma": np.zeros(0)}
    cols = {k: np.concatenate([empty[k]] + v) for k, v in parts.items()}
    del parts
    count, messages, unidentified = (np.concatenate([np.zeros(0, np.intp)] + x).astype(np.intp)
                                     for x in (count, messages, unidentified))
    stamps = np.array([int(fr.stamp_ns) for fr in data.frames], dtype=np.int64)
    # the environment at each stamp (frame_context's interpolation, all stamps in one call:
    # np.interp's value at each abscissa does not depend on the others, the same floats)
    at = {k: np.asarray(env[k].interp(stamps), dtype=float) for k in ("head", "air", "pressure")}
    return SceneStars(stamps, count, messages, cols["usable"], cols["u_i"], cols["catalog_id"],
                      cols["magnitude"], unidentified, at["head"], at["air"],
                      at["pressure"], grav, [{} for _ in stamps], cols["stated_sigma"])


def _columns_one_by_one(frames: list, cam, default_sigma: float) -> InputColumns:
    """:func:`frame_inputs_columns`' columns from :func:`frame_inputs`, a frame at a time.

    Where the compiled call does not apply (no numba, messages whose arrays differ in
    length): the same columns but the usable stars' ``uv`` and ``sigma`` (None: the scene
    does not keep them).
    """
    got = [frame_inputs(fr, cam.width, cam.height, default_sigma) for fr in frames]
    bounds = np.zeros(len(got) + 1, dtype=np.int64)
    np.cumsum([len(inp.ok) for inp in got], out=bounds[1:])
    counts = np.zeros((len(got), 4), dtype=np.int64)
    counts[:, 0] = [len(inp.uv) for inp in got]

    def stacked(rows, empty):
        return np.concatenate([empty] + [np.asarray(r).reshape((-1,) + empty.shape[1:])
                                         for r in rows])

    return InputColumns(
        stacked((inp.ok for inp in got), np.zeros(0, bool)), None,
        stacked((inp.u_i for inp in got), np.zeros((0, 3))), None,
        stacked((inp.catalog_id for inp in got), np.zeros(0, np.int64)),
        stacked((inp.magnitude for inp in got), np.zeros(0)), counts, bounds,
        stacked((fr.catalog_id for fr in frames), np.zeros(0, np.int64)),
        stacked((np.asarray(fr.sigma, dtype=float) for fr in frames), np.zeros(0)))


@dataclass
class TwinStars:
    """A twin's stars in arrays over its frames, before they are made into messages.

    The twin's frames are the user's frames with usable stars (``live``, in order); row
    by row the usable stars of those frames (:class:`SceneStars`), rendered (``uv``) and
    whether the twin keeps them (in front of the camera and on the detector).
    """

    live: np.ndarray  #: (K,) the user frame of each twin frame
    stamp_ns: np.ndarray  #: (K,) int64, their stamps
    count: np.ndarray  #: (K,) rendered stars per twin frame (kept or not)
    keep: np.ndarray  #: (N,) bool
    uv: np.ndarray  #: (N, 2) px
    catalog_id: np.ndarray  #: (N,) int64

    def kept(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The kept stars as the twin's frames hold them: ``(stamps, counts, ids, uv)``."""
        ends = np.cumsum(self.count)
        before = np.concatenate([[0], np.cumsum(self.keep)])
        counts = before[ends] - before[ends - self.count]
        return self.stamp_ns, counts, self.catalog_id[self.keep], self.uv[self.keep]


@dataclass
class Rendered:
    """What :func:`render` makes: the twin's IMU samples and stars, and its model."""

    imu_w: np.ndarray
    imu_f: np.ndarray
    stars: TwinStars
    counts: dict[str, int]
    model: StarModel
    theta: np.ndarray
    injected: dict[str, np.ndarray]
    noise: NoiseScales


def make_twin(data: BagData, calibration: Calibration, effects: dict[str, Any] | None = None,
              seed: int = 0, method: str | None = None,
              noise: NoiseScales | None = None, scene: TwinScene | None = None,
              imu: bool = True) -> Twin:
    """The twin of ``data`` under ``calibration`` with ``effects`` injected (see the module).

    ``effects``: ``{id: value}`` in the units of ``simulate --effect``; ``method``: whose
    baseline and noise defaults apply (default: the calibration's, else psce); ``noise``:
    the measured noise scales (default: the calibration's ``consistency.noise``);
    ``scene``: :func:`twin_scene` of the same ``data``, ``calibration`` and ``method``,
    made once for several twins (the same twin as without it).  ``imu=False``: the IMU is
    not rendered (the twin holds the user's samples); its noise is still drawn, so the
    stars are the same numbers (for the reliability probe, whose camera effects leave the
    IMU alone: 2 x 17 MB and their temporaries a render on a 2-h bag).
    """
    scene = scene if scene is not None else twin_scene(data, calibration, method)
    r = render(data, calibration, effects, seed, method, noise, scene, imu)
    stars, sc = r.stars, scene.stars
    # the message rows of each frame's usable stars, and the frames' first message rows
    where = np.flatnonzero(sc.usable)
    first = np.cumsum(sc.messages) - sc.messages
    frames = []
    for j, stop, size in zip(stars.live.tolist(), np.cumsum(stars.count).tolist(),
                             stars.count.tolist(), strict=True):
        fr = data.frames[j]
        rows = slice(stop - size, stop)
        k = stars.keep[rows]
        idx = where[rows][k] - first[j]
        frames.append(StarFrame(
            stamp_ns=int(fr.stamp_ns), frame_id=fr.frame_id or STAR_TRACKER_FRAME,
            exposure_time=fr.exposure_time,
            catalog_id=np.asarray(fr.catalog_id)[idx],
            right_ascension=np.asarray(fr.right_ascension, dtype=float)[idx],
            declination=np.asarray(fr.declination, dtype=float)[idx],
            uv=stars.uv[rows][k], magnitude=np.asarray(fr.magnitude)[idx],
            sigma=np.asarray(fr.sigma)[idx]))
    twin_data = dataclasses.replace(data, imu_w=r.imu_w, imu_f=r.imu_f, frames=frames,
                                    source="")
    prior = copy.deepcopy(calibration)
    return Twin(twin_data, _truth(calibration, r.model, r.theta, r.injected), prior,
                r.injected, r.noise, r.counts)


def render(data: BagData, calibration: Calibration, effects: dict[str, Any] | None = None,
           seed: int = 0, method: str | None = None, noise: NoiseScales | None = None,
           scene: TwinScene | None = None, imu: bool = True) -> Rendered:
    """:func:`make_twin`'s IMU samples and stars, in arrays (the same arguments).

    The twin's frames are not made: the reliability probe needs only the stars' steps
    (a 2-h bag's 14 400 messages ≈ 10 MB and 0.2 CPU-s a render).
    """
    from stellar_cal_ros.diagnosis.noise import stated_scales

    scene = scene if scene is not None else twin_scene(data, calibration, method)
    method = scene.method
    injected = {k: normalize_effect(k, v) for k, v in (effects or {}).items()}
    noise = noise or stated_scales(calibration)
    rng = np.random.default_rng(seed)
    model, theta = twin_model(calibration, method, injected)
    cam = calibration.camera
    default_sigma, t, w_true, f_true = scene.default_sigma, scene.t, scene.w_true, scene.f_true
    traj = scene.traj
    # the IMU
    b_g, E_g, _, _ = model.sensor_model(theta, Stage.GYRO)
    b_a, E_a, _, _ = model.sensor_model(theta, Stage.ACCEL)
    dt = data.nominal_dt or float(np.median(np.diff(t)))
    g_sig = scene.arw * noise.gyro / np.sqrt(dt)
    a_sig = scene.vrw * noise.accel / np.sqrt(dt)
    if imu and f_true is None:
        raise ValueError("make_twin: this scene was made without the IMU (imu=False)")
    if imu:
        w_twin = w_true @ (np.eye(3) + E_g).T + b_g + g_sig * rng.standard_normal(w_true.shape)
        f_twin = f_true @ (np.eye(3) + E_a).T + b_a + a_sig * rng.standard_normal(f_true.shape)
    else:
        w_twin, f_twin = data.imu_w, data.imu_f
        _skip_normals(rng, 2 * w_true.size, seed)  # the rates' and the forces' noise
    # the stars
    sc = scene.stars
    mb = injected.get("magnitude_bias", np.zeros(2))
    direction = np.array([np.cos(np.deg2rad(mb[1])), np.sin(np.deg2rad(mb[1]))])
    counts = {"stars": 0, "unidentified_left_out": 0, "off_detector": 0}
    centre = ((cam.width - 1) / 2.0, (cam.height - 1) / 2.0)
    # the stars' noise as measured: each frame's scatter, correlated along each star's track
    # when the run measured that (the simulator's AR(1), sim.tracker_errors.ar1_noise)
    marginal = noise.within_frames()
    tracks = Ar1Tracks(noise.star_rho, rng, noise.star_ar_share) if noise.star_rho > 0 else None
    counts["unidentified_left_out"] = int(sc.unidentified.sum())
    # the centroids of every frame with stars in one call (StarModel.predict_frames); the
    # frames' contexts made for this render only (columns of the scene), and only where the
    # model's chain reads them (the stars' rows are the scene's, frame after frame)
    live = np.flatnonzero(sc.count > 0)
    n = sc.count[live]
    starts = (np.cumsum(sc.count) - sc.count)[live].tolist()

    def contexts() -> list:
        return [sc.context(j, data.site, a) for j, a in zip(live.tolist(), starts, strict=True)]

    t_rel = (sc.stamp_ns[live] - data.t0_ns) * 1e-9
    if noise.stamp_ms > 0:
        # the frames' stamps off their exposures by the noise the run stated or measured
        # (``--noise-scale stamp=``): each frame's stars where they were at its exposure,
        # its stamp less its error, as the bag's own (the twin's stamps are the bag's)
        t_rel = t_rel - stamp_errors(len(data.frames), 1e-3 * noise.stamp_ms, seed)[live]
    uv, d = model.predict_frames(theta, sc.u_i, contexts,
                                 lambda shifts: traj.at(t_rel + shifts), counts=n)
    magnitude = sc.magnitude
    if mb[0] != 0.0:
        uv = uv + (mb[0] * (np.nan_to_num(magnitude, nan=4.0) - 4.0))[:, None] * direction
    stated = sc.stated_sigma
    sig = marginal.star_sigma(np.where(stated > 0, stated, 0.0), default_sigma, magnitude,
                              uv, centre)
    # one draw for every star is the per-frame draws in a row (the same generator stream)
    z = rng.standard_normal(uv.shape) if tracks is None else np.concatenate(
        [np.zeros((0, 2))] + [tracks.draw(j, sc.catalog_id[a:a + k]) for j, a, k in
                              zip(live.tolist(), starts, n.tolist(), strict=True)])
    uv = uv + sig[:, None] * z
    if noise.frame_px > 0:
        # a shift all stars of a frame share (``--noise-scale frame=``), one draw per frame
        uv = uv + np.repeat(frame_shifts(len(data.frames), noise.frame_px, seed)[live], n,
                            axis=0)
    keep = (d[:, 2] > 0) & cam.in_image(np.nan_to_num(uv, nan=-1e9))
    counts["off_detector"] = int((~keep).sum())
    counts["stars"] = int(keep.sum())
    return Rendered(w_twin, f_twin, TwinStars(live, sc.stamp_ns[live], n, keep, uv,
                                              sc.catalog_id), counts,
                    model, theta, injected, noise)


#: :func:`_skip_normals`' generator state after ``n`` normals from ``default_rng(seed)``,
#: by ``(seed, n)`` (the last few: a few hundred bytes each)
_SKIPPED: dict[tuple[int, int], dict] = {}


def _skip_normals(rng: np.random.Generator, n: int, seed: int | None = None,
                  chunk: int = 1 << 16) -> None:
    """Draw ``n`` standard normals from ``rng`` and drop them, ``chunk`` at a time.

    The generator is then where one ``standard_normal`` of ``n`` values leaves it (its
    draws are sequential), without holding them.  ``seed``: an integer ``rng`` is a fresh
    ``default_rng`` of, not drawn from yet: its state after them is kept and set directly
    the next time (the same state; a 2-h bag's ~4.3 M normals ≈ 0.05 CPU-s a render, the
    reliability probe renders six).
    """
    key = (int(seed), int(n)) if isinstance(seed, (int, np.integer)) else None
    if key is not None and key in _SKIPPED:
        rng.bit_generator.state = _SKIPPED[key]
        return
    left = n
    while left > 0:
        rng.standard_normal(min(left, chunk))
        left -= chunk
    if key is not None:
        if len(_SKIPPED) >= 8:
            _SKIPPED.pop(next(iter(_SKIPPED)))
        _SKIPPED[key] = rng.bit_generator.state


def write_twin(twin: Twin, path: str | Path) -> dict[str, Path]:
    """Write the twin bag, ``TWIN.truth.yaml`` and ``TWIN.prior.yaml``."""
    from stellar_cal_ros.io.writer import BagWriter

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    stem = path.with_suffix("")
    paths = {"bag": path, "truth": Path(f"{stem}.truth.yaml"),
             "prior": Path(f"{stem}.prior.yaml")}
    d = twin.data
    stamps = d.imu_stamp_ns
    zero9 = np.zeros(9)
    with BagWriter(path) as w:
        w.write_imu(ImuSeries(stamp_ns=stamps, angular_velocity=d.imu_w,
                              linear_acceleration=d.imu_f, frame_id=IMU_FRAME,
                              angular_velocity_covariance=zero9,
                              linear_acceleration_covariance=zero9), "/imu/data")
        for frame in d.frames:
            w.write_star_frame(frame, "/star_tracker/stars")
        if d.site is not None:
            t_fix = np.arange(int(stamps[0]), int(stamps[-1]) + 1, 10**9, dtype=np.int64)
            n = len(t_fix)
            w.write_navsat(NavSatSeries(t_fix, np.full(n, d.site.latitude_deg),
                                        np.full(n, d.site.longitude_deg),
                                        np.full(n, d.site.height_m),
                                        np.zeros(n, dtype=int)), "/gnss/fix")
        for series, topic, kind in ((d.head_temperature, "/star_tracker/temperature",
                                     "temperature"),
                                    (d.air_temperature, "/environment/temperature",
                                     "temperature"),
                                    (d.pressure, "/environment/pressure", "pressure")):
            if series is not None and len(series.stamp_ns):
                w.write_scalar(series, topic, kind=kind)
    save_calibration(twin.truth, paths["truth"])
    save_calibration(twin.prior, paths["prior"])
    return paths
