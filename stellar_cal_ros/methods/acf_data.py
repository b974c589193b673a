"""Data of the ACF batch calibration: star frames and IMU samples of one run, checked.

Also the gyro chain (:class:`GyroChain`: one propagation of the IMU, interpolated to any
frame) and the frame selection shared with the interstar-angle baseline.

:func:`load_acf_data` reads what the method needs from a contract bag.  Times are relative
seconds ``(stamp_ns − t0_ns)·1e-9`` with ``t0_ns`` the first IMU stamp.

The ACF gyro chain ties every star frame to the first one, so one bad IMU sample would
tilt every later frame.  :meth:`AcfData.gyro` therefore prepares the IMU once, counting
every repair in :class:`DataQuality`:

* messages out of stamp order are sorted, repeated stamps dropped;
* a sample with NaN/inf, or a lost one, leaves a *known* interval without data (each
  message holds the mean rate over the interval that ends at its stamp): it is bridged as
  the filters bridge it (:class:`~stellar_cal_ros.core.imu.ImuBuffer`: one sample with the
  neighbours' mean rate, i.e. the rate interpolated linearly);
* a gap longer than the star frame interval cannot be bridged (the attitude over it is
  unknown), and a stamp jumping backwards is a clock jump: both raise
  :class:`~stellar_cal_ros.errors.DataError` naming the time and size.

:func:`check_gyro_against_stars` (:mod:`stellar_cal_ros.core.gyro_check`, the check the
filters run too) compares the gyro's rotation between star frames with the stars' own: a
ratio of 57.3 is a gyro in deg/s, ~0 a dead gyro, and rotation axes that no fixed rotation
maps onto each other are swapped or mirrored axes.
"""

from __future__ import annotations

import logging
import os
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from stellar_cal_ros.core.earth import Site
from stellar_cal_ros.core.gyro_check import check_gyro_against_stars  # noqa: F401 (re-exported)
from stellar_cal_ros.core.imu import ImuBuffer
from stellar_cal_ros.core.imu_prefix import in_sample_rotvec, sample_slopes
from stellar_cal_ros.core.rotation import so3_exp
from stellar_cal_ros.core.strapdown import attitude_increments, propagate_attitude
from stellar_cal_ros.effects.base import Stage
from stellar_cal_ros.errors import BagError, DataError, StellarCalError
from stellar_cal_ros.io.bag import BagReader, ImuSeries, StarFrame
from stellar_cal_ros.methods.frames import TOPIC_IMAGE, TOPICS, read_inputs, star_input
from stellar_cal_ros.methods.star_model import StarModel

log = logging.getLogger(__name__)

BRIDGE_FACTOR = 1.5
"""An IMU interval longer than this × the nominal one is a gap to bridge."""


@dataclass
class DataQuality:
    """What the ACF method repaired, skipped or rejected (counts; ``_s``: seconds)."""

    imu_unsorted: int = 0  # messages whose stamp is earlier than their predecessor's
    imu_duplicates: int = 0  # repeated stamps dropped
    imu_nonfinite: int = 0  # NaN/inf samples, their intervals bridged
    imu_bridged: int = 0  # intervals without data, bridged by interpolation
    imu_bridged_s: float = 0.0
    frames_unsorted: int = 0
    frames_duplicates: int = 0
    frames_outside_imu: int = 0
    frames_few_stars: int = 0
    stars_unidentified: int = 0  # catalog_id 0 / direction unknown
    stars_invalid: int = 0  # NaN/inf centroid or direction
    stars_outside_image: int = 0  # centroid off the detector
    stars_bad_sigma: int = 0  # σ ≤ 0 or NaN in the message (1 px used, rescaled by σ̂)
    stars_misidentified: int = 0  # catalogue direction far from the measured one
    stars_outliers: int = 0  # normalized residual beyond the outlier gate

    def counts(self) -> dict[str, float]:
        """The nonzero counts."""
        return {k: v for k, v in asdict(self).items() if v}

    def summary(self) -> str:
        """``name=value`` of the nonzero counts ('' if none)."""
        return ", ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}"
                         for k, v in self.counts().items())


@dataclass
class GyroSamples:
    """IMU rates ready for the gyro chain: strictly increasing stamps, no gaps left.

    Attributes
    ----------
    t : ndarray (N,)
        Relative time (s) of the end of each interval.
    w : ndarray (N, 3)
        Mean body rate over the interval, rad/s.
    dt : ndarray (N,)
        Interval lengths, s (the first one: the nominal interval).
    """

    t: np.ndarray
    w: np.ndarray
    dt: np.ndarray


@dataclass
class AcfData:
    """Star frames and IMU samples of one run, with the time origin ``t0_ns``.

    Star frames are put in stamp order and repeated stamps dropped on construction (both
    counted in :attr:`quality`).
    """

    frames: list[StarFrame]
    imu: ImuSeries
    t0_ns: int
    site: Site | None = None
    scalars: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    quality: DataQuality = field(default_factory=DataQuality)
    #: what a read with ``on_error="skip"`` passed over (:meth:`BagReader.losses`)
    losses: dict = field(default_factory=dict)
    _gyro: GyroSamples | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        stamps = np.array([f.stamp_ns for f in self.frames], dtype=np.int64)
        if len(stamps) > 1 and np.any(np.diff(stamps) <= 0):
            self.quality.frames_unsorted += int(np.sum(np.diff(stamps) < 0))
            order = np.argsort(stamps, kind="stable")
            keep = np.concatenate([[True], np.diff(stamps[order]) > 0])
            self.quality.frames_duplicates += int(np.sum(~keep))
            self.frames = [self.frames[i] for i in order[keep]]

    def rel(self, stamp_ns: Any) -> Any:
        """Relative seconds of POSIX ns stamps (exact integer difference first)."""
        return (np.asarray(stamp_ns, dtype=np.int64) - self.t0_ns) * 1e-9

    def frame_interval(self) -> float:
        """Median interval between star frames, s (inf with fewer than two frames)."""
        if len(self.frames) < 2:
            return float("inf")
        return float(np.median(np.diff([f.stamp_ns for f in self.frames]))) * 1e-9

    def gyro(self) -> GyroSamples:
        """The IMU prepared for the gyro chain (:func:`prepare_gyro`, computed once)."""
        if self._gyro is None:
            self._gyro = prepare_gyro(self)
        return self._gyro


def prepare_gyro(data: AcfData, max_gap_s: float | None = None) -> GyroSamples:
    """Sorted, de-duplicated, finite IMU rates with every missing interval bridged.

    Parameters
    ----------
    data : AcfData
        Counts go to ``data.quality``.
    max_gap_s : float, optional
        Longest interval without data that is bridged (default: the star frame interval,
        at least 5 nominal IMU intervals).

    Raises
    ------
    DataError
        A stamp jumps backwards by more than a second (a clock jump), or a gap longer
        than ``max_gap_s`` lies inside the data; fewer than two usable samples.
    """
    q = data.quality
    imu = data.imu
    stamps = np.asarray(imu.stamp_ns, dtype=np.int64).reshape(-1)
    w = np.asarray(imu.angular_velocity, dtype=float).reshape(-1, 3)
    d = np.diff(stamps)
    jumps = np.flatnonzero(d < -1_000_000_000)
    if jumps.size:
        k = int(jumps[0])
        raise DataError(
            f"/imu/data stamps jump back by {-d[k] * 1e-9:.3f} s after t="
            f"{data.rel(stamps[k]):.3f} s (message {k + 1} of {len(stamps)}): a clock jump "
            "in the IMU time stamps; the ACF method needs one continuous IMU clock")
    q.imu_unsorted += int(np.sum(d < 0))
    order = np.argsort(stamps, kind="stable")
    stamps, w = stamps[order], w[order]
    keep = np.concatenate([[True], np.diff(stamps) > 0])
    q.imu_duplicates += int(np.sum(~keep))
    finite = np.all(np.isfinite(w), axis=1)
    q.imu_nonfinite += int(np.sum(keep & ~finite))
    keep &= finite
    stamps, w = stamps[keep], w[keep]
    if len(stamps) < 2:
        raise DataError(f"/imu/data holds {len(stamps)} usable samples (of {len(imu)}); the "
                        "ACF method needs the gyro rates between the star frames")
    t = data.rel(stamps)
    dt = np.diff(t)
    nominal = float(np.median(dt))
    limit = max(data.frame_interval(), 5.0 * nominal) if max_gap_s is None else max_gap_s
    gaps = np.flatnonzero(dt > BRIDGE_FACTOR * nominal)
    if gaps.size:
        big = gaps[dt[gaps] > limit]
        if big.size:
            k = int(big[np.argmax(dt[big])])
            raise DataError(
                f"/imu/data has a {dt[k]:.3f} s gap after t={t[k]:.3f} s ({big.size} gap(s) "
                f"longer than {limit:.3f} s): the IMU was silent or its clock jumped, and the "
                "ACF gyro chain cannot bridge more than the star frame interval")
        buf = ImuBuffer(nominal, BRIDGE_FACTOR)  # the filters' bridge: one rule
        buf.append(t, w)
        t, w = buf.t.copy(), buf.w.copy()
        q.imu_bridged += int(gaps.size)
        q.imu_bridged_s += float(np.sum(dt[gaps] - nominal))
    dts = np.concatenate([[nominal], np.diff(t)])
    return GyroSamples(t=t, w=w, dt=dts)


def check_overlap(data: AcfData, span: tuple[float, float], idx: np.ndarray) -> None:
    """Refuse star frames that mostly lie outside the IMU data (a clock offset).

    ``span``: first and last time the IMU covers (relative s); ``idx``: the selected frames,
    of which ``data.quality.frames_outside_imu`` were found outside.

    Raises
    ------
    DataError
        More than half of the selected frames lie outside the IMU data.
    """
    q = data.quality
    if q.frames_outside_imu <= 0.5 * len(idx):
        return
    t = data.rel(np.array([data.frames[int(k)].stamp_ns for k in idx]))
    lo, hi = span
    off = float(np.median(t)) - 0.5 * (lo + hi)
    raise DataError(
        f"{q.frames_outside_imu} of {len(idx)} star frames lie outside the IMU data: the "
        f"stars cover {t.min():.3f} .. {t.max():.3f} s, the IMU {lo:.3f} .. {hi:.3f} s "
        f"(relative to the first IMU stamp): the star tracker and IMU clocks disagree "
        f"(by about {off:.0f} s)")


def report_quality(data: AcfData, span: tuple[float, float], n_stars: int, n_frames: int,
                   outlier_probability: float | None) -> list[str]:
    """Log what was counted; return the reasons the result is degraded (may be empty).

    Degraded: more than 10 % of the identified stars rejected (wrong identities or
    outliers), IMU bridged over more than 1 % of its span, or more than 10 % of the frames
    outside the IMU data.
    """
    q = data.quality
    counts = q.counts()
    if not counts:
        return []
    false_alarms = n_stars * (1.0 - (outlier_probability or 1.0))
    only_gate_noise = set(counts) == {"stars_outliers"} and q.stars_outliers <= \
        false_alarms + 3.0 * np.sqrt(false_alarms) + 1.0
    (log.info if only_gate_noise else log.warning)("ACF data: %s", q.summary())
    reasons = []
    rejected = q.stars_misidentified + q.stars_outliers
    if rejected > 0.1 * n_stars:
        reasons.append(f"{rejected} of {n_stars} stars rejected as misidentified or "
                       "outliers")
    lo, hi = span
    if q.imu_bridged_s > 0.05 * (hi - lo):
        reasons.append(f"IMU bridged over {q.imu_bridged_s:.3g} s of {hi - lo:.3g} s")
    if q.frames_outside_imu > 0.1 * n_frames:
        reasons.append(f"{q.frames_outside_imu} of {n_frames} star frames outside the IMU "
                       "data")
    for r in reasons:
        log.warning("ACF result degraded: %s", r)
    return reasons


def load_acf_data(
    bag_path: str | os.PathLike[str],
    star_topic: str = "/star_tracker/stars",
    imu_topic: str = "/imu/data",
    gnss_topic: str = "/gnss/fix",
    on_error: str = "raise",
) -> AcfData:
    """Read what the ACF method needs from a contract bag.

    ``on_error="skip"``: a damaged bag is read past its damage (the reader's skip mode);
    :attr:`AcfData.losses` says what was lost.

    Raises
    ------
    StellarCalError
        The bag or one of the two required topics is missing, or holds no data.
    """
    env = {"head_temperature_c": "head", "air_temperature_c": "air", "pressure_pa": "pressure"}
    names = dict(TOPICS, stars=star_topic, imu=imu_topic, fix=gnss_topic)
    try:
        with BagReader(bag_path, on_error=on_error) as reader:
            topics = reader.topics()
            if star_input(topics, names, str(bag_path)) is None:
                raise StellarCalError(
                    f"{bag_path}: the ACF method needs star centroids on {star_topic} (or "
                    f"star images on {TOPIC_IMAGE}), which the bag does not have (topics: "
                    f"{sorted(topics)})")
            if imu_topic not in topics:
                raise StellarCalError(
                    f"{bag_path}: the ACF method needs IMU samples on {imu_topic}, which the "
                    f"bag does not have (topics: {sorted(topics)})")
            # centroids, or star images made into frames (one pass; methods/frames.py)
            whole, frames, _ = read_inputs(reader, names, ["imu", "fix", *env.values()],
                                           str(bag_path), topics)
            imu = whole["imu"]
            site = None
            fix = whole.get("fix")
            if fix is not None and len(fix):
                site = Site(float(np.median(fix.latitude_deg)),
                            float(np.median(fix.longitude_deg)),
                            float(np.median(fix.altitude_m)))
            scalars = {key: (np.asarray(s.stamp_ns), np.asarray(s.value))
                       for key, role in env.items()
                       if (s := whole.get(role)) is not None and len(s)}
            losses = reader.losses(reader.start_ns)
    except FileNotFoundError as exc:
        raise BagError(f"cannot open bag {bag_path}: {exc}") from None
    if len(imu) < 2:
        raise DataError(f"{bag_path}: {imu_topic} holds {len(imu)} IMU samples; "
                              "the ACF method needs the gyro data between the star frames")
    if not frames:
        raise StellarCalError(f"{bag_path}: {star_topic} holds no star frames")
    t0 = int(imu.stamp_ns[0])
    data = AcfData(frames=frames, imu=imu, t0_ns=t0, site=site, losses=losses)
    data.scalars = {k: (data.rel(st), v) for k, (st, v) in scalars.items()}
    return data


# ============================================================================ gyro chain
class GyroChain:
    """Attitude changes from one propagation of the IMU, interpolated to any time.

    ``R(t)`` is the body attitude in the frame of the body at the start of the first IMU
    interval ("n0"); ``C(t)`` (3, P) is the first-order left perturbation of ``R(t)`` per
    unit change of θ through the gyro sensor model (zero unless gyro effects are estimated).
    Inside an IMU interval the attitude is the filters' second-order one
    (:func:`~stellar_cal_ros.core.imu_prefix.in_sample_rotvec`: the rate linear through the
    interval's and the previous interval's mean rates).
    """

    def __init__(self, data: AcfData, model: StarModel, theta0: np.ndarray) -> None:
        g = data.gyro()  # sorted, finite, gaps bridged (counted in data.quality)
        t, dt = g.t, g.dt
        self.nodes = np.concatenate([[t[0] - dt[0]], t])  # interval k: nodes[k] .. nodes[k+1]
        self.dt = dt
        w = model.corrected_rates(theta0, g.w)
        self.rates = w
        self.phi = attitude_increments(w, dt)
        self.slope = sample_slopes(w, dt, np.concatenate([np.zeros((1, 3)), w[:-1]]),
                                   np.concatenate([[0.0], dt[:-1]]))  # first: none
        R = propagate_attitude(Rotation.identity(), w, dt).as_matrix()
        self.R = np.concatenate([np.eye(3)[None], R])  # at nodes
        # sensitivity to θ: δw = −(Jb + JE·w) Δθ
        P = model.size
        self.C = np.zeros((len(self.nodes), 3, P))
        _, _, Jb, JE = model.sensor_model(theta0, Stage.GYRO)
        if P and (np.any(Jb) or np.any(JE)):
            B = -(Jb[None] + np.einsum("ijp,nj->nip", JE, w))  # (N, 3, P)
            R_mid = 0.5 * (self.R[:-1] + self.R[1:])
            self.C[1:] = np.cumsum(np.einsum("nij,njp->nip", R_mid, B) * dt[:, None, None],
                                   axis=0)

    @property
    def span(self) -> tuple[float, float]:
        """First and last time covered by the IMU (relative s)."""
        return float(self.nodes[0]), float(self.nodes[-1])

    def _locate(self, t: float) -> tuple[int, float]:
        j = int(np.searchsorted(self.nodes, t, side="right")) - 1
        j = min(max(j, 0), len(self.dt) - 1)
        s = (t - self.nodes[j]) / self.dt[j]
        return j, s

    def attitude(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """``R_n0_b(t)`` (3, 3) and the body rate ω (3,) at relative time ``t``."""
        j, s = self._locate(t)
        return self.R[j] @ so3_exp(in_sample_rotvec(s, self.phi[j], self.slope[j])), self.rates[j]

    def sensitivity(self, t: float) -> np.ndarray:
        """``C(t)`` (3, P), linear interpolation between IMU nodes."""
        j, s = self._locate(t)
        return (1.0 - s) * self.C[j] + s * self.C[min(j + 1, len(self.C) - 1)]


# ============================================================================ frames
def select_frames(n: int, frames: Any) -> np.ndarray:
    """Indices from None / 'all' / 'odd' / 'even' (1-based, as Liu counts) / ints / mask."""
    if frames is None or (isinstance(frames, str) and frames == "all"):
        return np.arange(n)
    if isinstance(frames, str):
        if frames == "odd":
            return np.arange(0, n, 2)
        if frames == "even":
            return np.arange(1, n, 2)
        raise StellarCalError(f"frames must be 'all', 'odd', 'even' or indices, got {frames!r}")
    if isinstance(frames, slice):
        return np.arange(n)[frames]
    idx = np.asarray(frames)
    if idx.dtype == bool:
        if idx.shape != (n,):
            raise StellarCalError(f"frame mask must have {n} entries, got {idx.shape}")
        return np.flatnonzero(idx)
    idx = np.asarray(idx, dtype=np.int64).ravel()
    if idx.size and (idx.min() < -n or idx.max() >= n):
        raise StellarCalError(f"frame index out of range 0..{n - 1}")
    return np.unique(np.where(idx < 0, idx + n, idx))


def unit_vectors(ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
    """Inertial unit vectors of right ascensions and declinations (rad), (n, 3)."""
    cd = np.cos(dec)
    return np.stack([np.cos(ra) * cd, np.sin(ra) * cd, np.sin(dec)], axis=1)
