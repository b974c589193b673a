"""From the messages of one topic in a chunk to the domain types, for each contract kind.

A kind is what a topic holds: ``imu`` (``sensor_msgs/msg/Imu`` -> :class:`ImuSeries`),
``stars`` (``StarCentroidArray`` -> :class:`StarFrame`), ``fix`` (``NavSatFix`` ->
:class:`NavSatSeries`), ``scalar`` (``Temperature`` / ``FluidPressure`` ->
:class:`ScalarSeries`), ``image`` (``Image`` -> :class:`~stellar_cal_ros.io.image_msgs.
ImageMessage`) and ``camera_info`` (``CameraInfo`` -> :class:`~stellar_cal_ros.io.
image_msgs.CameraInfoMessage`). A :class:`TopicDecoder` decodes a chunk's rows of its topic in bulk
(bad rows reported, not raised) and builds the typed result from decoded rows.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

from stellar_cal_ros.core.types import ImuSeries, NavSatSeries, ScalarSeries, StarFrame
from stellar_cal_ros.io import cdr, image_msgs
from stellar_cal_ros.io.mcap_records import Rows
from stellar_cal_ros.io.merge import Fields
from stellar_cal_ros.io.schemas import (
    CAMERA_INFO,
    FLUID_PRESSURE,
    IMAGE,
    IMU,
    NAVSATFIX,
    STAR_ARRAY,
    TEMPERATURE,
)

EXPECTED: dict[str, tuple[str, ...]] = {
    "imu": (IMU,),
    "stars": (STAR_ARRAY,),
    "fix": (NAVSATFIX,),
    "scalar": (TEMPERATURE, FLUID_PRESSURE),
    "image": (IMAGE,),
    "camera_info": (CAMERA_INFO,),
}
"""Kind -> the message types it decodes."""

#: kinds decoded to one object per message (the others to numpy series)
PER_MESSAGE = ("stars", "image", "camera_info")

Block = (ImuSeries | StarFrame | NavSatSeries | ScalarSeries | image_msgs.ImageMessage
         | image_msgs.CameraInfoMessage)


def kind_of(types: list[str]) -> str | None:
    """The kind of a topic from its channels' message types (None: no channel or unknown)."""
    for kind, expected in EXPECTED.items():
        if any(t in expected for t in types):
            return kind
    return None


def _imu(buf: NDArray[np.uint8], off: NDArray[np.int64], ln: NDArray[np.int64],
         log: NDArray[np.int64]) -> cdr.Decoded:
    dec = cdr.decode_f8_block(buf, off, ln, log, 37, IMU, {"av": (13, 16), "la": (25, 28)})
    # the first row's covariances, not row-aligned: popped by decode()
    dec.fields["first_cov"] = dec.fields.pop("first")[:, 16:37]
    return dec


def _scalar(buf: NDArray[np.uint8], off: NDArray[np.int64], ln: NDArray[np.int64],
            log: NDArray[np.int64]) -> cdr.Decoded:
    dec = cdr.decode_f8_block(buf, off, ln, log, 2, "Temperature/FluidPressure",
                              {"value": (0, 1), "variance": (1, 2)})
    dec.fields.pop("first")
    for k in ("value", "variance"):
        dec.fields[k] = dec.fields[k].reshape(-1)
    return dec


def _fix(buf: NDArray[np.uint8], off: NDArray[np.int64], ln: NDArray[np.int64],
         log: NDArray[np.int64]) -> cdr.Decoded:
    dec = cdr.decode_navsat(buf, off, ln, log)
    f8 = dec.fields.pop("f8")
    for k, col in (("lat", 0), ("lon", 1), ("alt", 2)):
        dec.fields[k] = np.ascontiguousarray(f8[:, col])
    dec.fields["cov"] = np.ascontiguousarray(f8[:, 3:12])
    return dec


_DECODE: dict[str, Callable[..., cdr.Decoded]] = {
    "imu": _imu,
    "stars": cdr.decode_star_frames,
    "fix": _fix,
    "scalar": _scalar,
    "image": image_msgs.decode_images,
    "camera_info": image_msgs.decode_camera_infos,
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
        self._covs: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None

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
        if len(self._good_list) == 1:  # (one channel: a comparison, not isin's sort)
            mine = rows.channel == self._good_list[0]
            sel = np.arange(len(rows)) if not self._other_list and mine.all() else \
                np.flatnonzero(mine)
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
        cov = fields.pop("first_cov", None)
        if self.cov is None and cov is not None and len(cov):
            self.cov = cov[0].copy()
        for f in dec.frame_ids:
            if f not in self.frames:
                self.frames.append(f)
        fields["seq"] = rows.order_key(sel[dec.keep])
        return fields, errors

    def _empty_fields(self) -> Fields:
        z = np.zeros(0, np.int64)
        f = np.zeros(0)
        if self.kind == "imu":
            return {"stamp": z, "log": z, "av": np.zeros((0, 3)), "la": np.zeros((0, 3))}
        if self.kind in PER_MESSAGE:
            return {"obj": np.empty(0, object), "log": z}
        if self.kind == "fix":
            return {"stamp": z, "lat": f, "lon": f, "alt": f, "status": z, "service": z,
                    "cov": np.zeros((0, 9)), "cov_type": z, "log": z}
        return {"stamp": z, "value": f, "variance": f, "log": z}

    def build(self, d: Fields | None) -> Any:
        """The typed result of decoded rows (``None``: no row); arrays are not copied.

        Returns
        -------
        ImuSeries, NavSatSeries, ScalarSeries or list (of StarFrame, ImageMessage or
            CameraInfoMessage)
            By kind.
        """
        if d is None:
            d = self._empty_fields()
        frame = self.frames[0] if self.frames else ""
        if self.kind == "imu":
            if self._covs is None and self.cov is not None:
                self._covs = (self.cov[0:9].copy(), self.cov[12:21].copy())
            covs = self._covs or (None, None)
            return ImuSeries(d["stamp"], d["av"], d["la"], frame, d["log"], *covs)
        if self.kind in PER_MESSAGE:
            return list(d["obj"])
        if self.kind == "fix":
            return NavSatSeries(d["stamp"], d["lat"], d["lon"], d["alt"], d["status"], frame,
                                d["service"], d["cov"], d["cov_type"], d["log"])
        return ScalarSeries(d["stamp"], d["value"], d["variance"], frame, d["log"])

    def blocks(self, d: Fields, imu_block: int) -> Iterator[Block]:
        """Stream blocks of one run of decoded rows (IMU split every ``imu_block`` rows)."""
        if self.kind in PER_MESSAGE:
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
