"""Data of the ACF batch calibration: star frames and IMU samples of one run.

:func:`load_acf_data` reads what the method needs from a contract bag.  Times are relative
seconds ``(stamp_ns − t0_ns)·1e-9`` with ``t0_ns`` the first IMU stamp.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from stellar_cal_ros.core.earth import Site
from stellar_cal_ros.errors import BagError, StellarCalError
from stellar_cal_ros.io.bag import BagReader, ImuSeries, StarFrame


@dataclass
class AcfData:
    """Star frames and IMU samples of one run, with the time origin ``t0_ns``."""

    frames: list[StarFrame]
    imu: ImuSeries
    t0_ns: int
    site: Site | None = None
    scalars: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    def rel(self, stamp_ns: Any) -> Any:
        """Relative seconds of POSIX ns stamps (exact integer difference first)."""
        return (np.asarray(stamp_ns, dtype=np.int64) - self.t0_ns) * 1e-9


def load_acf_data(
    bag_path: str | os.PathLike[str],
    star_topic: str = "/star_tracker/stars",
    imu_topic: str = "/imu/data",
    gnss_topic: str = "/gnss/fix",
) -> AcfData:
    """Read what the ACF method needs from a contract bag.

    Raises
    ------
    StellarCalError
        The bag or one of the two required topics is missing, or holds no data.
    """
    try:
        with BagReader(bag_path) as reader:
            topics = reader.topics()
            for topic, what in ((star_topic, "star centroids"), (imu_topic, "IMU samples")):
                if topic not in topics:
                    raise StellarCalError(
                        f"{bag_path}: the ACF method needs {what} on {topic}, which the bag "
                        f"does not have (topics: {sorted(topics)})")
            imu = reader.read_imu(imu_topic)
            frames = reader.read_star_frames(star_topic)
            site = None
            scalars: dict[str, tuple[np.ndarray, np.ndarray]] = {}
            if gnss_topic in topics:
                fix = reader.read_navsat(gnss_topic)
                if len(fix):
                    site = Site(float(np.median(fix.latitude_deg)),
                                float(np.median(fix.longitude_deg)),
                                float(np.median(fix.altitude_m)))
            for key, topic in (("head_temperature_c", "/star_tracker/temperature"),
                               ("air_temperature_c", "/environment/temperature"),
                               ("pressure_pa", "/environment/pressure")):
                if topic in topics:
                    s = reader.read_scalar(topic)
                    if len(s):
                        scalars[key] = (np.asarray(s.stamp_ns), np.asarray(s.value))
    except FileNotFoundError as exc:
        raise BagError(f"cannot open bag {bag_path}: {exc}") from None
    if len(imu) < 2:
        raise StellarCalError(f"{bag_path}: {imu_topic} holds {len(imu)} IMU samples; "
                              "the ACF method needs the gyro data between the star frames")
    if not frames:
        raise StellarCalError(f"{bag_path}: {star_topic} holds no star frames")
    t0 = int(imu.stamp_ns[0])
    data = AcfData(frames=frames, imu=imu, t0_ns=t0, site=site)
    data.scalars = {k: (data.rel(st), v) for k, (st, v) in scalars.items()}
    return data
