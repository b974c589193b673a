"""Domain types of the measurements: IMU, star frames, GNSS fixes and scalar sensors.

These containers are what the bag readers return and the writers take, and what the methods
consume; they depend on numpy only, so :mod:`stellar_cal_ros.methods` does not import the I/O
layer to use them.

Times: ``stamp_ns`` fields are ``header.stamp`` (POSIX ns); ``log_time_ns`` fields are the bag's
log times (receive times when recorded by rosbag2). They are the same in bags written by this
package and in the reference bags, but need not be in general.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

__all__ = ["ImuSeries", "NavSatSeries", "ScalarSeries", "StarFrame", "TopicInfo"]

_S = TypeVar("_S", "ImuSeries", "ScalarSeries", "NavSatSeries")


@dataclass
class TopicInfo:
    """What a bag holds on one topic.

    Attributes
    ----------
    schema_name : str
        Message type, e.g. ``sensor_msgs/msg/Imu`` (``A|B`` if channels of one topic differ).
    message_count : int
        Number of messages on the topic.
    """

    schema_name: str
    message_count: int


def _concatenate(cls: type[_S], blocks: Sequence[_S], per_row: frozenset[str]) -> _S:
    """Join series blocks: per-row fields concatenated, the others taken from the first block.

    A per-row field that is None in any block is None in the result.
    """
    if not blocks:
        raise ValueError(f"{cls.__name__}.concatenate needs at least one block")
    if len(blocks) == 1:
        return blocks[0]
    kw: dict[str, Any] = {}
    for f in fields(cls):
        vals = [getattr(b, f.name) for b in blocks]
        if f.name not in per_row:
            kw[f.name] = vals[0]
        elif any(v is None for v in vals):
            kw[f.name] = None
        else:
            kw[f.name] = np.concatenate(vals)
    return cls(**kw)


@dataclass
class ImuSeries:
    """A series of ``sensor_msgs/msg/Imu`` samples.

    Attributes
    ----------
    stamp_ns : ndarray of int64, shape (N,)
        ``header.stamp`` in POSIX ns: end of the sample interval.
    angular_velocity : ndarray of float64, shape (N, 3)
        Mean body rate over the interval, rad/s, IMU frame.
    linear_acceleration : ndarray of float64, shape (N, 3)
        Mean specific force over the interval, m/s^2, IMU frame.
    frame_id : str
        ``header.frame_id`` (of the first message when reading).
    log_time_ns : ndarray of int64, shape (N,), optional
        Bag log times (filled when reading; ignored when writing, where log time = stamp).
    angular_velocity_covariance : ndarray of float64, shape (9,), optional
        Row-major covariance, (rad/s)^2, of the first message read; written to every message
        (zeros if None).
    linear_acceleration_covariance : ndarray of float64, shape (9,), optional
        Same for the specific force, (m/s^2)^2.
    """

    stamp_ns: NDArray[np.int64]
    angular_velocity: NDArray[np.float64]
    linear_acceleration: NDArray[np.float64]
    frame_id: str = "imu_link"
    log_time_ns: NDArray[np.int64] | None = None
    angular_velocity_covariance: NDArray[np.float64] | None = None
    linear_acceleration_covariance: NDArray[np.float64] | None = None

    def __len__(self) -> int:
        return int(np.shape(self.stamp_ns)[0])

    @classmethod
    def concatenate(cls, blocks: Sequence[ImuSeries]) -> ImuSeries:
        """Join consecutive blocks (e.g. from a stream) into one series.

        Parameters
        ----------
        blocks : sequence of ImuSeries
            At least one; ``frame_id`` and the covariances are taken from the first.

        Returns
        -------
        ImuSeries
            The rows of all blocks, in the given order.
        """
        return _concatenate(
            cls, blocks, frozenset({"stamp_ns", "angular_velocity", "linear_acceleration",
                                    "log_time_ns"})
        )


@dataclass
class StarFrame:
    """One ``stellar_cal_msgs/msg/StarCentroidArray`` message (one exposure), n stars.

    Attributes
    ----------
    stamp_ns : int
        ``header.stamp``, POSIX ns: mid-exposure time as the tracker reports it.
    frame_id : str
        ``header.frame_id`` (the star tracker optical frame).
    exposure_time : float
        Exposure time, s (0 if unknown); float32 on the wire.
    catalog_id : ndarray of uint32, shape (n,)
        Hipparcos numbers (0: not identified).
    right_ascension, declination : ndarray of float64, shape (n,)
        ICRS J2000 catalogue direction, rad.
    uv : ndarray of float64, shape (n, 2)
        Centroid (column u, row v), px.
    magnitude : ndarray of float64, shape (n,)
        Catalogue visual magnitude (float32 on the wire).
    sigma : ndarray of float64, shape (n,)
        1-sigma centroid noise, px, 0 if unknown (float32 on the wire).
    log_time_ns : int, optional
        Bag log time (filled when reading; the writer uses ``stamp_ns``).
    """

    stamp_ns: int
    frame_id: str
    exposure_time: float
    catalog_id: NDArray[np.uint32]
    right_ascension: NDArray[np.float64]
    declination: NDArray[np.float64]
    uv: NDArray[np.float64]
    magnitude: NDArray[np.float64]
    sigma: NDArray[np.float64]
    log_time_ns: int | None = None

    def __len__(self) -> int:
        return int(np.shape(self.catalog_id)[0])


@dataclass
class ScalarSeries:
    """A series of ``sensor_msgs/msg/Temperature`` (deg C) or ``FluidPressure`` (Pa) values.

    Attributes
    ----------
    stamp_ns : ndarray of int64, shape (N,)
        ``header.stamp``, POSIX ns.
    value : ndarray of float64, shape (N,)
        Temperature in deg C or pressure in Pa.
    variance : ndarray of float64, shape (N,)
        Variance of ``value`` (0: unknown), unit squared.
    frame_id : str
        ``header.frame_id`` (of the first message when reading).
    log_time_ns : ndarray of int64, shape (N,), optional
        Bag log times (reading only).
    """

    stamp_ns: NDArray[np.int64]
    value: NDArray[np.float64]
    variance: NDArray[np.float64]
    frame_id: str = ""
    log_time_ns: NDArray[np.int64] | None = None

    def __len__(self) -> int:
        return int(np.shape(self.stamp_ns)[0])

    @classmethod
    def concatenate(cls, blocks: Sequence[ScalarSeries]) -> ScalarSeries:
        """Join consecutive blocks into one series (``frame_id`` of the first).

        Parameters
        ----------
        blocks : sequence of ScalarSeries
            At least one.

        Returns
        -------
        ScalarSeries
            The rows of all blocks, in the given order.
        """
        return _concatenate(
            cls, blocks, frozenset({"stamp_ns", "value", "variance", "log_time_ns"})
        )


@dataclass
class NavSatSeries:
    """A series of ``sensor_msgs/msg/NavSatFix`` fixes.

    Attributes
    ----------
    stamp_ns : ndarray of int64, shape (N,)
        ``header.stamp``, POSIX ns.
    latitude_deg, longitude_deg : ndarray of float64, shape (N,)
        WGS84 geodetic latitude / longitude, deg.
    altitude_m : ndarray of float64, shape (N,)
        Height above the WGS84 ellipsoid, m.
    status : ndarray of int, shape (N,)
        ``status.status`` (-1 no fix, 0 fix, 1 SBAS, 2 GBAS).
    frame_id : str
        ``header.frame_id`` (of the first message when reading).
    service : ndarray of int, shape (N,), optional
        ``status.service`` bit mask (0 if None when writing).
    position_covariance : ndarray of float64, shape (N, 9), optional
        Row-major ENU covariance, m^2 (zeros if None when writing).
    position_covariance_type : ndarray of int, shape (N,), optional
        0 unknown .. 3 known (0 if None when writing).
    log_time_ns : ndarray of int64, shape (N,), optional
        Bag log times (reading only).
    """

    stamp_ns: NDArray[np.int64]
    latitude_deg: NDArray[np.float64]
    longitude_deg: NDArray[np.float64]
    altitude_m: NDArray[np.float64]
    status: NDArray[np.int64]
    frame_id: str = "gnss_link"
    service: NDArray[np.int64] | None = None
    position_covariance: NDArray[np.float64] | None = None
    position_covariance_type: NDArray[np.int64] | None = None
    log_time_ns: NDArray[np.int64] | None = None

    def __len__(self) -> int:
        return int(np.shape(self.stamp_ns)[0])

    @classmethod
    def concatenate(cls, blocks: Sequence[NavSatSeries]) -> NavSatSeries:
        """Join consecutive blocks into one series (``frame_id`` of the first).

        Parameters
        ----------
        blocks : sequence of NavSatSeries
            At least one.

        Returns
        -------
        NavSatSeries
            The rows of all blocks, in the given order.
        """
        return _concatenate(cls, blocks, frozenset(f.name for f in fields(cls)) - {"frame_id"})
