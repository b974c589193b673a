"""From the messages of one topic in a chunk to the domain types, for each contract kind.

A kind is what a topic holds: ``imu`` (``sensor_msgs/msg/Imu`` -> :class:`ImuSeries`),
``stars`` (``StarCentroidArray`` -> :class:`StarFrame`), ``fix`` (``NavSatFix`` ->
:class:`NavSatSeries`) and ``scalar`` (``Temperature`` / ``FluidPressure`` ->
:class:`ScalarSeries`). A :class:`TopicDecoder` decodes a chunk's rows of its topic in bulk
(bad rows reported, not raised) and builds the typed result from decoded rows.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

from stellar_cal_ros.core.types import ImuSeries, NavSatSeries, ScalarSeries, StarFrame
from stellar_cal_ros.io import cdr
from stellar_cal_ros.io.mcap_records import Rows
from stellar_cal_ros.io.merge import Fields
from stellar_cal_ros.io.schemas import FLUID_PRESSURE, IMU, NAVSATFIX, STAR_ARRAY, TEMPERATURE

EXPECTED: dict[str, tuple[str, ...]] = {
    "imu": (IMU,),
    "stars": (STAR_ARRAY,),
    "fix": (NAVSATFIX,),
    "scalar": (TEMPERATURE, FLUID_PRESSURE),
}
"""Kind -> the message types it decodes."""

Block = ImuSeries | StarFrame | NavSatSeries | ScalarSeries


def kind_of(types: list[str]) -> str | None:
    """The kind of a topic from its channels' message types (None: no channel or unknown)."""
    for kind, expected in EXPECTED.items():
        if any(t in expected for t in types):
            return kind
    return None


def _imu(buf: NDArray[np.uint8], off: NDArray[np.int64], ln: NDArray[np.int64],
         log: NDArray[np.int64]) -> cdr.Decoded:
    dec = cdr.decode_f8_block(buf, off, ln, log, 37, IMU)
    f8 = dec.fields.pop("f8")
    dec.fields["av"] = np.ascontiguousarray(f8[:, 13:16])
    dec.fields["la"] = np.ascontiguousarray(f8[:, 25:28])
    dec.fields["cov"] = f8[:1, 16:37]  # first row only, not row-aligned: popped by decode()
    return dec


def _scalar(buf: NDArray[np.uint8], off: NDArray[np.int64], ln: NDArray[np.int64],
            log: NDArray[np.int64]) -> cdr.Decoded:
    return cdr.decode_f8_block(buf, off, ln, log, 2, "Temperature/FluidPressure")


_DECODE: dict[str, Callable[..., cdr.Decoded]] = {
    "imu": _imu,
    "stars": cdr.decode_star_frames,
    "fix": cdr.decode_navsat,
    "scalar": _scalar,
}


class TopicDecoder:
    """Decoder of one topic of one kind.

    Parameters
    ----------
    topic : str
        Topic name.
    kind : str
        Key of :data:`EXPECTED`.
    good, other : set of int
        Channel ids of the topic with an expected type / with another type (whose messages
        are reported as bad).
    schema_name : callable
        Channel id -> schema name, for messages.
    """

    def __init__(self, topic: str, kind: str, good: set[int], other: set[int],
                 schema_name: Callable[[int], str]) -> None:
        self.topic = topic
        self.kind = kind
        self.good = good
        self.other = other
        self._schema_name = schema_name
        self._good_list = sorted(good)
        self._other_list = sorted(other)
        self.frames: list[str] = []
        self.cov: NDArray[np.float64] | None = None

    def decode(self, rows: Rows) -> tuple[Fields | None, list[tuple[int, str]]]:
        """Decode this topic's messages of one chunk.

        Parameters
        ----------
        rows : Rows
            The chunk's messages.

        Returns
        -------
        fields : Fields or None
            Decoded rows with their ``"log"`` time and ``"seq"`` (write-order key, see
            :meth:`Rows.order_key`); None if the chunk has no message of the topic.
        errors : list of (int, str)
            Log time and reason of every message not decoded, in time order.
        """
        if not self._other_list and len(self._good_list) == 1 and rows.channel.size and \
                np.all(rows.channel == self._good_list[0]):
            sel = np.arange(len(rows))
        else:
            sel = np.flatnonzero(np.isin(rows.channel, self._good_list))
        errors: list[tuple[int, str]] = []
        if self._other_list:
            for i in np.flatnonzero(np.isin(rows.channel, self._other_list)):
                name = self._schema_name(int(rows.channel[i]))
                errors.append((int(rows.log_time[i]),
                               f"schema {name} on this channel, expected {EXPECTED[self.kind][0]}"))
        if not len(sel):
            return None, errors
        log = rows.log_time[sel]
        dec = _DECODE[self.kind](rows.buf, rows.offset[sel], rows.length[sel], log)
        errors += [(int(log[i]), reason) for i, reason in dec.bad]
        errors.sort(key=lambda e: e[0])
        fields = dec.fields
        cov = fields.pop("cov", None)
        if self.cov is None and cov is not None and len(cov):
            self.cov = cov[0].copy()
        for f in dec.frame_ids:
            if f not in self.frames:
                self.frames.append(f)
        fields["seq"] = rows.order_key(sel[dec.keep])
        return fields, errors

    def _empty_fields(self) -> Fields:
        z = np.zeros(0, np.int64)
        if self.kind == "imu":
            return {"stamp": z, "log": z, "av": np.zeros((0, 3)), "la": np.zeros((0, 3))}
        if self.kind == "stars":
            return {"obj": np.empty(0, object), "log": z}
        if self.kind == "fix":
            return {"stamp": z, "f8": np.zeros((0, 12)), "status": z, "service": z,
                    "cov_type": z, "log": z}
        return {"stamp": z, "f8": np.zeros((0, 2)), "log": z}

    def build(self, d: Fields | None) -> Any:
        """The typed result of decoded rows (``None``: no row).

        Returns
        -------
        ImuSeries, NavSatSeries, ScalarSeries or list of StarFrame
            By kind.
        """
        if d is None:
            d = self._empty_fields()
        frame = self.frames[0] if self.frames else ""
        if self.kind == "imu":
            cov = self.cov
            return ImuSeries(
                stamp_ns=np.ascontiguousarray(d["stamp"], np.int64),
                angular_velocity=np.ascontiguousarray(d["av"]),
                linear_acceleration=np.ascontiguousarray(d["la"]),
                frame_id=frame,
                log_time_ns=np.ascontiguousarray(d["log"], np.int64),
                angular_velocity_covariance=cov[0:9].copy() if cov is not None else None,
                linear_acceleration_covariance=cov[12:21].copy() if cov is not None else None,
            )
        if self.kind == "stars":
            return list(d["obj"])
        if self.kind == "fix":
            f8 = d["f8"]
            return NavSatSeries(
                stamp_ns=d["stamp"],
                latitude_deg=np.ascontiguousarray(f8[:, 0]),
                longitude_deg=np.ascontiguousarray(f8[:, 1]),
                altitude_m=np.ascontiguousarray(f8[:, 2]),
                status=d["status"],
                frame_id=frame,
                service=d["service"],
                position_covariance=np.ascontiguousarray(f8[:, 3:12]),
                position_covariance_type=d["cov_type"],
                log_time_ns=d["log"],
            )
        return ScalarSeries(
            stamp_ns=d["stamp"],
            value=np.ascontiguousarray(d["f8"][:, 0]),
            variance=np.ascontiguousarray(d["f8"][:, 1]),
            frame_id=frame,
            log_time_ns=d["log"],
        )

    def blocks(self, d: Fields, imu_block: int) -> Iterator[Block]:
        """Stream blocks of one run of decoded rows (IMU split every ``imu_block`` rows)."""
        if self.kind == "stars":
            yield from d["obj"]
        elif self.kind == "imu" and len(d["log"]) > imu_block:
            for a in range(0, len(d["log"]), imu_block):
                yield self.build({k: v[a : a + imu_block] for k, v in d.items()})
        else:
            yield self.build(d)

    def warn_frames(self) -> None:
        """Warn if an IMU topic had several frame_ids (the first is used)."""
        if self.kind == "imu" and len(self.frames) > 1:
            warnings.warn(f"{self.topic}: several frame_ids {self.frames}; using "
                          f"{self.frames[0]!r}", stacklevel=3)
