"""``sensor_msgs/msg/Image`` and ``CameraInfo`` in bags: CDR decoding and encoding, pixels.

Star images are recorded on ``/star_tracker/image`` (mono8 / mono16, ``header.stamp`` =
mid-exposure) with an optional ``/star_tracker/camera_info`` (contract §2).  A bag's image
message decodes to an :class:`ImageMessage` whose ``data`` is a view of the chunk it came
from (nothing is copied: an image is megabytes, and the readers stream them one chunk at a
time); :func:`image_pixels` turns its bytes into a 2-D array and is the one check of an
image's content (encoding, size, row step), shared by the ``star_extractor`` node (ROS
messages have the same field names) and the bag data path
(:mod:`stellar_cal_ros.methods.frames`).

CDR layout (XCDR1, little endian; alignment relative to the byte after the 4-byte
encapsulation header): ``Header``; ``uint32 height, width``; ``string encoding``;
``uint8 is_bigendian``; ``uint32 step`` (4-aligned); ``uint8[] data`` (uint32 length, bytes).
``CameraInfo``: ``Header``; ``uint32 height, width``; ``string distortion_model``;
``float64[] d`` (uint32 length, doubles 8-aligned); ``float64[9] k, [9] r, [12] p``;
``uint32 binning_x, binning_y``; ``RegionOfInterest roi`` (4 × uint32, bool).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from stellar_cal_ros.core.camera import CameraModel
from stellar_cal_ros.io.cdr import (
    MAX_PAD,
    Decoded,
    align,
    decode_each,
    header_bytes,
    parse_header,
)

__all__ = ["ENCODINGS", "CameraInfoMessage", "ImageMessage", "camera_from_info",
           "decode_camera_infos", "decode_images", "encode_camera_info", "encode_image",
           "encode_image_fields", "image_payload_size", "image_pixels"]

#: image encodings a star image may have -> pixel type (one channel)
ENCODINGS: dict[str, type] = {"mono8": np.uint8, "8UC1": np.uint8,
                              "mono16": np.uint16, "16UC1": np.uint16}


@dataclass
class ImageMessage:
    """One ``sensor_msgs/msg/Image`` as read from a bag (fields as in the message)."""

    stamp_ns: int  #: header.stamp, POSIX ns (mid-exposure, contract §2)
    frame_id: str
    height: int
    width: int
    encoding: str
    is_bigendian: int
    step: int  #: bytes per row
    data: NDArray[np.uint8]  #: the pixel bytes: a view of the chunk (copy what you keep)
    log_time_ns: int | None = None


@dataclass
class CameraInfoMessage:
    """One ``sensor_msgs/msg/CameraInfo`` as read from a bag."""

    stamp_ns: int
    frame_id: str
    height: int
    width: int
    distortion_model: str
    d: NDArray[np.float64]
    k: NDArray[np.float64]  #: (9,) row-major
    r: NDArray[np.float64]
    p: NDArray[np.float64]
    log_time_ns: int | None = None


def image_pixels(msg: Any) -> NDArray[Any]:
    """The pixels of a mono image message as a 2-D native-endian array (height, width).

    ``msg`` has the fields of ``sensor_msgs/msg/Image`` (an :class:`ImageMessage` or a ROS
    message).  Raises ValueError naming what is wrong: an encoding other than
    mono8/mono16 (8UC1/16UC1), a size of zero, a row step shorter than a row, or a data
    length other than ``height × step``.
    """
    dtype = ENCODINGS.get(str(msg.encoding))
    if dtype is None:
        raise ValueError(f"image encoding {msg.encoding!r} is not mono8 or mono16 "
                         "(8UC1/16UC1)")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    size = np.dtype(dtype).itemsize
    if h <= 0 or w <= 0:
        raise ValueError(f"image of {w} x {h} pixels")
    if step < w * size:
        raise ValueError(f"image row step {step} bytes is shorter than a row of {w} "
                         f"{msg.encoding} pixels ({w * size} bytes)")
    data = msg.data if isinstance(msg.data, np.ndarray) else np.frombuffer(msg.data, np.uint8)
    if data.size != h * step:
        raise ValueError(f"image data of {data.size} bytes, expected height {h} x step {step}"
                         f" = {h * step} bytes")
    rows = data.reshape(h, step)[:, :w * size]
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    pixels = np.ascontiguousarray(rows).view(dt).reshape(h, w)
    return pixels if dt.isnative else pixels.astype(dtype)


def camera_from_info(msg: Any) -> CameraModel:
    """The camera of a CameraInfo message (K, D in OpenCV order; ROS or bag message)."""
    k = [float(x) for x in msg.k]
    d = [float(x) for x in msg.d]
    if len(d) not in (0, 4, 5, 8, 12, 14):
        d = (d + [0.0] * 14)[:14]
    return CameraModel(int(msg.width), int(msg.height), k[0], k[4], k[2], k[5],
                       d or np.zeros(14))


# ---------------------------------------------------------------------------- decoding
def _u32(mv: memoryview, pos: int, n: int, what: str) -> tuple[int, int]:
    pos = 4 + align(pos - 4, 4)
    if pos + 4 > n:
        raise ValueError(f"payload of {n} bytes ends inside {what}")
    return struct.unpack_from("<I", mv, pos)[0], pos + 4


def _string(mv: memoryview, pos: int, n: int, what: str) -> tuple[str, int]:
    length, pos = _u32(mv, pos, n, what)
    if length < 1 or pos + length > n:
        raise ValueError(f"{what} length {length} does not fit the payload of {n} bytes")
    if mv[pos + length - 1] != 0:
        raise ValueError(f"{what} is not NUL-terminated")
    return bytes(mv[pos:pos + length - 1]).decode("utf-8", errors="replace"), pos + length


def _head(buf: NDArray[np.uint8], off: int, n: int, what: str
          ) -> tuple[memoryview, int, str, int, int, str, int]:
    """Header, ``uint32 height, width`` and a string (``what``) of an Image / CameraInfo.

    Returns (payload view, stamp ns, frame_id, height, width, the string, position after).
    """
    mv = memoryview(buf)[off:off + n]
    stamp, frame_id, pos = parse_header(mv, n)
    height, pos = _u32(mv, pos, n, "height")
    width, pos = _u32(mv, pos, n, "width")
    text, pos = _string(mv, pos, n, what)
    return mv, stamp, frame_id, int(height), int(width), text, pos


def decode_image(buf: NDArray[np.uint8], off: int, n: int) -> ImageMessage:
    """Decode the ``Image`` payload ``buf[off:off + n]`` (``data`` a view of ``buf``)."""
    mv, stamp, frame_id, height, width, encoding, pos = _head(buf, off, n, "encoding")
    if pos + 1 > n:
        raise ValueError(f"payload of {n} bytes ends inside is_bigendian")
    bigendian = int(mv[pos])
    step, pos = _u32(mv, pos + 1, n, "step")
    length, pos = _u32(mv, pos, n, "the data length")
    if not pos + length <= n <= pos + length + MAX_PAD:
        raise ValueError(f"payload of {n} bytes, expected {pos + length} for an image of "
                         f"{length} data bytes")
    return ImageMessage(stamp, frame_id, height, width, encoding, bigendian, int(step),
                        buf[off + pos:off + pos + length])


def decode_camera_info(buf: NDArray[np.uint8], off: int, n: int) -> CameraInfoMessage:
    """Decode the ``CameraInfo`` payload ``buf[off:off + n]``."""
    mv, stamp, frame_id, height, width, model, pos = _head(buf, off, n, "distortion_model")
    nd, pos = _u32(mv, pos, n, "the length of d")
    pos = 4 + align(pos - 4, 8)  # the doubles (d, then k, r, p) are 8-aligned
    end = pos + 8 * (nd + 30)
    if not end + 25 <= n <= end + 25 + MAX_PAD:  # binning 2 x uint32, roi 4 x uint32 + bool
        raise ValueError(f"payload of {n} bytes, expected {end + 25} for a CameraInfo with "
                         f"{nd} distortion coefficients")
    doubles = np.frombuffer(bytes(mv[pos:end]), "<f8")
    return CameraInfoMessage(stamp, frame_id, height, width, model,
                             doubles[:nd].copy(), doubles[nd:nd + 9].copy(),
                             doubles[nd + 9:nd + 18].copy(), doubles[nd + 18:nd + 30].copy())


def decode_images(buf: NDArray[np.uint8], off: NDArray[np.int64], ln: NDArray[np.int64],
                  log: NDArray[np.int64]) -> Decoded:
    """Decode many ``Image`` payloads of one chunk (fields ``obj``: ImageMessage, ``log``)."""
    return decode_each(decode_image, buf, off, ln, log)


def decode_camera_infos(buf: NDArray[np.uint8], off: NDArray[np.int64],
                        ln: NDArray[np.int64], log: NDArray[np.int64]) -> Decoded:
    """Decode many ``CameraInfo`` payloads (fields ``obj``: CameraInfoMessage, ``log``)."""
    return decode_each(decode_camera_info, buf, off, ln, log)


# ---------------------------------------------------------------------------- encoding
def _pad(out: bytearray, alignment: int) -> None:
    out += b"\x00" * (-(len(out) - 4) % alignment)


def _image_head(stamp_ns: int, frame_id: str, height: int, width: int, encoding: str,
                is_bigendian: int, step: int, length: int) -> bytearray:
    out = header_bytes(stamp_ns, frame_id)
    enc = encoding.encode("utf-8") + b"\x00"
    _pad(out, 4)
    out += struct.pack("<III", height, width, len(enc)) + enc
    out += struct.pack("<B", int(is_bigendian))
    _pad(out, 4)
    out += struct.pack("<II", step, length)
    return out


def image_payload_size(frame_id: str, encoding: str, data_bytes: int) -> int:
    """Bytes of an ``Image`` payload with ``data_bytes`` of pixel data."""
    return len(_image_head(0, frame_id, 0, 0, encoding, 0, 0, 0)) + int(data_bytes)


def encode_image_fields(stamp_ns: int, frame_id: str, height: int, width: int, encoding: str,
                        is_bigendian: int, step: int, data: bytes) -> bytes:
    """CDR payload of an ``Image`` with the given fields (unchecked: tests make bad ones)."""
    return bytes(_image_head(stamp_ns, frame_id, height, width, encoding, is_bigendian, step,
                             len(data))) + bytes(data)


def encode_image(stamp_ns: int, frame_id: str, pixels: NDArray[Any],
                 encoding: str | None = None) -> bytes:
    """CDR payload of a mono image (uint8 -> mono8, uint16 -> mono16, little endian)."""
    px = np.asarray(pixels)
    if encoding is None:
        encoding = {1: "mono8", 2: "mono16"}.get(px.dtype.itemsize, "")
    dtype = ENCODINGS.get(encoding)
    if dtype is None or px.ndim != 2:
        raise ValueError(f"a mono8/mono16 image is a 2-D array, got {px.dtype} {px.shape} as "
                         f"{encoding!r}")
    data = np.ascontiguousarray(px, dtype=np.dtype(dtype).newbyteorder("<"))
    h, w = data.shape
    return encode_image_fields(stamp_ns, frame_id, h, w, encoding, 0, w * data.itemsize,
                               data.tobytes())


def encode_camera_info(stamp_ns: int, frame_id: str, camera: CameraModel) -> bytes:
    """CDR payload of the ``CameraInfo`` of ``camera`` (plumb_bob or rational_polynomial)."""
    d = np.asarray(camera.distortion, dtype=float)
    if np.any(d[8:]):
        model, d = "rational_polynomial", d[:14]
    elif np.any(d[5:8]):
        model, d = "rational_polynomial", d[:8]
    else:
        model, d = "plumb_bob", d[:5]
    k = [camera.fx, 0.0, camera.cx, 0.0, camera.fy, camera.cy, 0.0, 0.0, 1.0]
    p = [camera.fx, 0.0, camera.cx, 0.0, 0.0, camera.fy, camera.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    out = header_bytes(stamp_ns, frame_id)
    name = model.encode() + b"\x00"
    _pad(out, 4)
    out += struct.pack("<III", camera.height, camera.width, len(name)) + name
    _pad(out, 4)
    out += struct.pack("<I", len(d))
    _pad(out, 8)
    out += np.asarray(list(d) + k + [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0] + p, "<f8").tobytes()
    out += struct.pack("<IIIIII", 0, 0, 0, 0, 0, 0) + b"\x00"
    return bytes(out)
