"""Replay a contract bag through a Kalman-filter calibration, as fast as the machine allows.

Reading and filtering are timed separately.  The IMU topic is decoded in bulk (fixed CDR
layout), star frames one by one (2 Hz); the filter is pure numpy.  Every skipped frame or
star is counted in :class:`~stellar_cal_ros.methods.psce.FilterCounters` and summarized in
the log — nothing is dropped silently.
"""

from __future__ import annotations

import copy
import logging
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from stellar_cal_ros.core.catalog import radec_to_unit
from stellar_cal_ros.core.earth import Site
from stellar_cal_ros.effects import registry
from stellar_cal_ros.effects.base import FrameContext
from stellar_cal_ros.errors import BagError, ModelError
from stellar_cal_ros.io.bag import BagReader, ScalarSeries, StarFrame
from stellar_cal_ros.io.calibration import Calibration
from stellar_cal_ros.methods.psce import BASELINE_EFFECTS, FrameUpdate, PsceConfig, PsceFilter
from stellar_cal_ros.methods.star_model import StarModel

log = logging.getLogger(__name__)

TOPIC_IMU = "/imu/data"
TOPIC_STARS = "/star_tracker/stars"
TOPIC_FIX = "/gnss/fix"
TOPIC_HEAD_TEMPERATURE = "/star_tracker/temperature"
TOPIC_AIR_TEMPERATURE = "/environment/temperature"
TOPIC_PRESSURE = "/environment/pressure"


@dataclass
class BagData:
    """The parts of a contract bag the calibrations use (times relative to ``t0_ns``)."""

    t0_ns: int
    imu_t: np.ndarray
    imu_w: np.ndarray
    imu_f: np.ndarray
    frames: list[StarFrame]
    site: Site | None
    head_temperature: ScalarSeries | None
    air_temperature: ScalarSeries | None
    pressure: ScalarSeries | None
    read_seconds: float = 0.0
    imu_dropped: int = 0  #: duplicated-stamp or non-finite IMU messages not used

    @property
    def t0(self) -> float:
        """POSIX seconds of relative time zero."""
        return self.t0_ns * 1e-9


def read_bag_data(path: str | Path, topics: dict[str, str] | None = None,
                  on_error: str = "raise") -> BagData:
    """Read everything a calibration needs from a contract bag."""
    names = {"imu": TOPIC_IMU, "stars": TOPIC_STARS, "fix": TOPIC_FIX,
             "head": TOPIC_HEAD_TEMPERATURE, "air": TOPIC_AIR_TEMPERATURE,
             "pressure": TOPIC_PRESSURE}
    names.update(topics or {})
    t_start = time.perf_counter()
    # on_error="skip": a truncated recording (power loss at sea) is calibrated on what it
    # holds; bad messages are dropped and counted (BagReader.skipped) with a warning.
    with BagReader(path, on_error=on_error) as reader:
        available = reader.topics()
        for key in ("imu", "stars"):
            if names[key] not in available:
                raise BagError(f"{path}: required topic {names[key]} is missing "
                               f"(topics: {', '.join(sorted(available)) or 'none'})")
        imu = reader.read_imu(names["imu"])
        frames = reader.read_star_frames(names["stars"])
        site = None
        if names["fix"] in available:
            fix = reader.read_navsat(names["fix"])
            ok = np.isfinite(fix.latitude_deg) & np.isfinite(fix.longitude_deg) & \
                np.isfinite(fix.altitude_m) & (fix.status >= 0)
            if np.any(ok):
                site = Site(float(np.median(fix.latitude_deg[ok])),
                            float(np.median(fix.longitude_deg[ok])),
                            float(np.median(fix.altitude_m[ok])))
        scalars = {}
        for key in ("head", "air", "pressure"):
            scalars[key] = reader.read_scalar(names[key]) if names[key] in available else None
    if len(imu.stamp_ns) < 2:
        raise BagError(f"{path}: {names['imu']} has {len(imu.stamp_ns)} messages")
    order = np.argsort(imu.stamp_ns, kind="stable")
    stamps = imu.stamp_ns[order]
    keep = np.concatenate([[True], np.diff(stamps) > 0])  # drop duplicated stamps
    dropped = int(len(stamps) - keep.sum())
    if dropped:
        log.warning("%s: %d IMU messages with duplicated stamps dropped", path, dropped)
    if not np.array_equal(order, np.arange(len(order))):
        log.warning("%s: IMU messages out of stamp order were sorted", path)
    w = imu.angular_velocity[order][keep]
    f = imu.linear_acceleration[order][keep]
    stamps = stamps[keep]
    finite = np.all(np.isfinite(w), axis=1) & np.all(np.isfinite(f), axis=1)
    dropped += int((~finite).sum())
    if not np.all(finite):
        log.warning("%s: %d IMU messages with NaN/inf dropped", path, int((~finite).sum()))
        w, f, stamps = w[finite], f[finite], stamps[finite]
    t0_ns = int(stamps[0]) - int(np.median(np.diff(stamps[:1000])))
    return BagData(
        t0_ns=t0_ns,
        imu_t=(stamps - t0_ns) * 1e-9,
        imu_w=w,
        imu_f=f,
        frames=frames,
        site=site,
        head_temperature=scalars["head"],
        air_temperature=scalars["air"],
        pressure=scalars["pressure"],
        read_seconds=time.perf_counter() - t_start,
        imu_dropped=dropped,
    )


def _interp(series: ScalarSeries | None, t_ns: int) -> float:
    if series is None or len(series.stamp_ns) == 0:
        return float("nan")
    ok = np.isfinite(series.value)
    if not np.any(ok):
        return float("nan")
    return float(np.interp(t_ns, series.stamp_ns[ok], series.value[ok]))


def _interp_many(series: ScalarSeries | None, t_ns: np.ndarray) -> np.ndarray:
    """:func:`_interp` for many stamps at once."""
    if series is None or len(series.stamp_ns) == 0 or not np.any(np.isfinite(series.value)):
        return np.full(len(t_ns), np.nan)
    ok = np.isfinite(series.value)
    t0 = int(series.stamp_ns[ok][0])
    return np.interp((t_ns - t0) * 1e-9, (series.stamp_ns[ok] - t0) * 1e-9, series.value[ok])


def frame_context(data: BagData, frame: StarFrame, catalog_id: np.ndarray,
                  magnitude: np.ndarray) -> FrameContext:
    """The context effects may use for one frame."""
    return FrameContext(
        stamp=frame.stamp_ns * 1e-9,
        catalog_id=catalog_id,
        magnitude=magnitude,
        site=data.site,
        head_temperature_c=_interp(data.head_temperature, frame.stamp_ns),
        air_temperature_c=_interp(data.air_temperature, frame.stamp_ns),
        pressure_pa=_interp(data.pressure, frame.stamp_ns),
    )


def clean_frame(frame: StarFrame, width: int, height: int) -> np.ndarray:
    """Mask of usable stars: identified, finite, on the detector."""
    uv = frame.uv
    ok = (frame.catalog_id != 0) & np.isfinite(frame.right_ascension) & \
        np.isfinite(frame.declination) & np.all(np.isfinite(uv), axis=1)
    ok &= (uv[:, 0] >= -0.5) & (uv[:, 0] < width - 0.5) & (uv[:, 1] >= -0.5) & \
        (uv[:, 1] < height - 0.5)
    return ok


@dataclass
class ReplayResult:
    """Outputs of a replay."""

    calibration: Calibration
    residuals: dict[str, np.ndarray]
    history: dict[str, np.ndarray]
    counters: dict[str, int]
    read_seconds: float
    filter_seconds: float
    duration: float
    filter: Any = None
    derived: dict[str, Any] = field(default_factory=dict)

    @property
    def speed(self) -> float:
        """Bag seconds per wall-clock second (reading + filtering)."""
        return self.duration / max(self.read_seconds + self.filter_seconds, 1e-9)


class _Progress:
    def __init__(self, total: int, enabled: bool) -> None:
        self.total, self.enabled = max(total, 1), enabled
        self.next = 0.0
        self.start = time.perf_counter()

    def __call__(self, i: int) -> None:
        if not self.enabled:
            return
        frac = (i + 1) / self.total
        if frac >= self.next or i + 1 == self.total:
            self.next = frac + 0.05
            el = time.perf_counter() - self.start
            bar = "#" * int(30 * frac)
            sys.stderr.write(f"\r[{bar:30s}] {100 * frac:5.1f}%  {el:6.1f} s")
            if i + 1 == self.total:
                sys.stderr.write("\n")
            sys.stderr.flush()


def build_model(prior: Calibration, effects: list[str], baseline=BASELINE_EFFECTS) -> StarModel:
    """StarModel of the method's baseline plus ``effects``."""
    return StarModel(registry.create_many(list(baseline) + list(effects)), prior)


def replay_psce(
    bag: str | Path | BagData,
    prior: Calibration,
    effects: list[str] | None = None,
    config: PsceConfig | None = None,
    progress: bool = False,
    baseline: tuple[str, ...] = BASELINE_EFFECTS,
) -> ReplayResult:
    """Run the PSCE filter over a bag and return the calibration and the residuals.

    ``baseline`` is the model's fixed part (default: Tan et al.'s); a reduced one shows
    what the diagnosis says when a baseline effect is missing.
    """
    data = bag if isinstance(bag, BagData) else read_bag_data(bag)
    config = config or PsceConfig()
    model = build_model(prior, effects or [], baseline)
    for eff in model.effects:
        if "site" in eff.requires and data.site is None:
            raise ModelError(f"effect {eff.id} needs the site position ({TOPIC_FIX})")
    flt = PsceFilter(model, data.imu_t, data.imu_w, data.t0, config)
    width, height = prior.camera.width, prior.camera.height
    rows: dict[str, list] = {k: [] for k in RESIDUAL_COLUMNS}
    hist: dict[str, list] = {"t": [], "nis": [], "dof": [], "stars": [], "gated": [],
                             "iterations": []}
    theta_hist, sigma_hist, att_sigma = [], [], []
    prog = _Progress(len(data.frames), progress)
    t_start = time.perf_counter()
    # A recorded bag is replayed in stamp order (a late-logged frame is still good data);
    # equal stamps stay in log order and the filter skips the duplicates.
    stamps = np.array([f.stamp_ns for f in data.frames], dtype=np.int64)
    order = np.argsort(stamps, kind="stable")
    reordered = int(np.sum(order != np.arange(len(order))))
    if reordered:
        log.warning("%d star frames out of stamp order in the bag: replayed in stamp order",
                    reordered)
    weather = {key: _interp_many(series, stamps) for key, series in (
        ("head", data.head_temperature), ("air", data.air_temperature),
        ("pressure", data.pressure))}
    frames_done = 0
    for i in order:
        frame = data.frames[i]
        prog(frames_done)
        frames_done += 1
        ok = clean_frame(frame, width, height)
        flt.counters.stars_invalid += int((~ok).sum())
        if not np.any(ok):
            flt.counters.frames += 1
            flt.counters.skipped_few_stars += 1
            continue
        ids = frame.catalog_id[ok].astype(np.int64)
        mag = frame.magnitude[ok]
        ctx = FrameContext(stamp=frame.stamp_ns * 1e-9, catalog_id=ids, magnitude=mag,
                           site=data.site, head_temperature_c=weather["head"][i],
                           air_temperature_c=weather["air"][i],
                           pressure_pa=weather["pressure"][i])
        u_i = radec_to_unit(frame.right_ascension[ok], frame.declination[ok])
        sigma = frame.sigma[ok].astype(float)
        sigma = np.where(sigma > 0, sigma, config.centroid_sigma_px)
        upd = flt.process_frame(frame.uv[ok], u_i, ctx, sigma,
                                t_rel=(frame.stamp_ns - data.t0_ns) * 1e-9)
        if upd is None:
            continue
        _append_residuals(rows, upd, int(i), ids, mag, ctx)
        if np.isfinite(upd.nis):
            hist["t"].append(upd.stamp)
            hist["nis"].append(upd.nis)
            hist["dof"].append(upd.dof)
            hist["stars"].append(int(upd.accepted.sum()))
            hist["gated"].append(int((~upd.accepted).sum()))
            hist["iterations"].append(upd.iterations)
            theta_hist.append(flt.theta.copy())
            s = flt.sigma()
            sigma_hist.append(s[3:])
            att_sigma.append(s[:3])
    filter_seconds = time.perf_counter() - t_start
    if not flt.initialized:
        raise ModelError("no star frame could initialize the attitude "
                         f"(counters: {vars(flt.counters)})")
    cal = result_calibration(prior, model, flt.theta, flt.sigma()[3:], "psce",
                             data.t0 + flt.t)
    derived = equivalent_principal_point(model, flt.theta, flt.P[3:, 3:])
    cal.extra["derived"] = derived
    history = {k: np.asarray(v) for k, v in hist.items()}
    names = model.parameter_names()
    th = np.asarray(theta_hist).reshape(-1, model.size)
    sg = np.asarray(sigma_hist).reshape(-1, model.size)
    for j, name in enumerate(names):
        history[name] = th[:, j]
        history["sigma." + name] = sg[:, j]
    att = np.asarray(att_sigma).reshape(-1, 3)
    for j, ax in enumerate("xyz"):
        history[f"sigma.attitude.{ax}"] = att[:, j]
    counters = {k: v for k, v in vars(flt.counters).items() if k != "extra"}
    counters.update(flt.counters.extra)
    counters["frames_reordered"] = reordered
    counters["imu_messages_dropped"] = data.imu_dropped
    _log_counters(counters)
    return ReplayResult(
        calibration=cal,
        residuals={k: np.concatenate(v) if v else np.zeros(0) for k, v in rows.items()},
        history=history,
        counters=counters,
        read_seconds=data.read_seconds,
        filter_seconds=filter_seconds,
        duration=float(data.imu_t[-1]),
        filter=flt,
        derived=derived,
    )


RESIDUAL_COLUMNS = (
    "t", "frame", "catalog_id", "u", "v", "u_pred", "v_pred", "du", "dv",
    "s_uu", "s_uv", "s_vv", "nis", "magnitude", "gated",
    "x_st", "y_st", "z_st", "omega_x", "omega_y", "omega_z", "head_temperature",
)


def _append_residuals(rows, upd: FrameUpdate, frame_index: int, ids, mag, ctx) -> None:
    n = len(upd.uv)
    nu = upd.uv - upd.uv_pred
    cols = {
        "t": np.full(n, upd.stamp), "frame": np.full(n, frame_index), "catalog_id": ids,
        "u": upd.uv[:, 0], "v": upd.uv[:, 1], "u_pred": upd.uv_pred[:, 0],
        "v_pred": upd.uv_pred[:, 1], "du": nu[:, 0], "dv": nu[:, 1],
        "s_uu": upd.S[:, 0, 0], "s_uv": upd.S[:, 0, 1], "s_vv": upd.S[:, 1, 1],
        "nis": upd.nis_stars, "magnitude": mag, "gated": ~upd.accepted,
        "x_st": upd.directions_st[:, 0], "y_st": upd.directions_st[:, 1],
        "z_st": upd.directions_st[:, 2],
        "omega_x": np.full(n, upd.omega_b[0]), "omega_y": np.full(n, upd.omega_b[1]),
        "omega_z": np.full(n, upd.omega_b[2]),
        "head_temperature": np.full(n, ctx.head_temperature_c),
    }
    for k, v in cols.items():
        rows[k].append(np.asarray(v))


def _log_counters(counters: dict[str, int]) -> None:
    skipped = {k: v for k, v in counters.items() if (k.startswith("skipped") or k in (
        "stars_invalid", "stars_gated", "imu_gaps")) and v}
    if skipped:
        log.info("skipped / counted: %s", ", ".join(f"{k}={v}" for k, v in skipped.items()))


def result_calibration(prior: Calibration, model: StarModel, theta: np.ndarray,
                       sigma: np.ndarray, method: str, stamp: float) -> Calibration:
    """The prior with every estimated effect stored (values and sigmas)."""
    cal = copy.deepcopy(prior)
    cal.sigma = copy.deepcopy(prior.sigma) if prior.sigma else {}
    cal.method = method
    cal.stamp = float(stamp)
    for eff in model.effects:
        sl = model.slices[eff.id]
        eff.store(theta[sl], sigma[sl], cal)
    return cal


def equivalent_principal_point(model: StarModel, theta: np.ndarray,
                               P_theta: np.ndarray) -> dict[str, Any]:
    """Image position of the IMU-fixed nominal boresight (Tan et al. §3.4), with sigma.

    ``(cx − fx·δ_y, cy + fy·δ_x)`` to first order: the combination of principal point and
    installation tilt that a star tracker observes directly; it converges long before its
    two parts separate.
    """
    ctx = FrameContext(stamp=0.0)

    def value(th: np.ndarray) -> np.ndarray:
        cam = model.camera_at(th, ctx)
        R_imu_st, _ = model.installation_at(th, ctx)
        b = model.prior.installation.as_matrix()[:, 2]  # nominal boresight in the IMU frame
        d = R_imu_st.T @ b
        return np.array([cam.cx + cam.fx * d[0] / d[2], cam.cy + cam.fy * d[1] / d[2]])

    v0 = value(theta)
    J = np.zeros((2, model.size))
    for j in range(model.size):
        h = 1e-6 * max(1.0, abs(theta[j]))
        tp, tm = theta.copy(), theta.copy()
        tp[j] += h
        tm[j] -= h
        J[:, j] = (value(tp) - value(tm)) / (2 * h)
    cov = J @ P_theta @ J.T
    return {"equivalent_principal_point_px": [float(v0[0]), float(v0[1])],
            "equivalent_principal_point_sigma_px": [float(np.sqrt(cov[0, 0])),
                                                    float(np.sqrt(cov[1, 1]))]}


def bag_data_from_simulation(result: Any) -> BagData:
    """The :class:`BagData` a bag written from a simulation result would read as.

    For Monte-Carlo benchmarks and tests that do not need to exercise the MCAP layer
    (:func:`read_bag_data` of the written bag gives the same arrays).
    """
    imu = result.imu
    stamps = np.asarray(imu.stamp_ns, dtype=np.int64)
    t0_ns = int(stamps[0]) - int(np.median(np.diff(stamps[:1000])))
    nav = result.navsat
    site = Site(float(np.median(nav.latitude_deg)), float(np.median(nav.longitude_deg)),
                float(np.median(nav.altitude_m))) if len(nav.stamp_ns) else None
    return BagData(
        t0_ns=t0_ns,
        imu_t=(stamps - t0_ns) * 1e-9,
        imu_w=np.asarray(imu.angular_velocity, dtype=float),
        imu_f=np.asarray(imu.linear_acceleration, dtype=float),
        frames=list(result.star_frames),
        site=site,
        head_temperature=result.head_temperature,
        air_temperature=result.air_temperature,
        pressure=result.pressure,
    )


def truth_parameters(model: StarModel, truth: Calibration) -> np.ndarray:
    """θ of a true calibration in the model's layout (for tests and benchmarks only).

    Every effect reads its value from ``truth`` as it would from a prior, except the
    installation, whose parameter is the rotation from the *prior's* nominal mounting:
    ``δ = Log(R_priorᵀ R_truth)``.
    """
    out = np.empty(model.size)
    for eff in model.effects:
        sl = model.slices[eff.id]
        if eff.id == "installation":
            out[sl] = (model.prior.installation.inv() * truth.installation).as_rotvec()
        else:
            value, _ = copy.deepcopy(eff).initial(truth)  # a copy: initial() may keep state
            out[sl] = value
    return out
