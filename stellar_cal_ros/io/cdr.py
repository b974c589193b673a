"""CDR decoding and encoding of the contract message types, in bulk with numpy.

Decoding works on many payloads of one decompressed chunk at once (``buf`` plus the offset and
length of each payload): no Python object is created per IMU message.
``stellar_cal_msgs/msg/StarCentroidArray`` (a few Hz) is parsed per message with :mod:`struct`
and one :func:`numpy.frombuffer` for the star array. Encoding builds structured numpy arrays
whose bytes are the payloads.

Layout notes (XCDR1, little endian, as ROS 2 serialises): the payload starts with a 4-byte
encapsulation header (``00 01 00 00``); every primitive is aligned to its size *relative to
the byte after that header*. ``std_msgs/Header`` is ``int32 sec, uint32 nanosec, uint32 n,
n bytes frame_id incl. NUL``, so everything after the header sits at an offset that depends on
the length of ``frame_id`` only. Serializers may append up to 3 bytes of padding to the end of
a payload; they are accepted.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stellar_cal_ros.core.types import ImuSeries, NavSatSeries, ScalarSeries, StarFrame
from stellar_cal_ros.io.schemas import NAVSATFIX, STAR_ARRAY

MAX_PAD = 3  # serializers may pad a payload to a multiple of 4 bytes

Encoder = Callable[[NDArray[np.int64]], NDArray[np.uint8]]
"""Row indices (ascending) -> concatenated payload bytes of those rows."""


def align(x: NDArray[np.int64] | int, a: int) -> Any:
    """Round ``x`` up to a multiple of ``a``."""
    return (x + (a - 1)) // a * a


def windows(buf: NDArray[np.uint8], offsets: NDArray[np.int64], width: int) -> NDArray[np.uint8]:
    """Copy ``buf[o:o + width]`` for every ``o`` in ``offsets``; shape (n, width).

    ``buf`` is a contiguous 1-D uint8 array and every window must lie inside it.
    """
    if len(offsets) == 0 or width == 0 or width > buf.size:
        return np.zeros((len(offsets), width), np.uint8)
    # overlapping rows of ``width`` bytes starting at every byte (what sliding_window_view
    # gives, without its per-call checks, which cost more than the copy for small batches)
    win = np.ndarray((buf.size - width + 1, width), np.uint8, buffer=buf, strides=(1, 1))
    return win[offsets]


def stamp_ns(sec: NDArray[Any], nsec: NDArray[Any]) -> NDArray[np.int64]:
    """``builtin_interfaces/Time`` fields -> int64 ns."""
    return sec.astype(np.int64) * 1_000_000_000 + nsec.astype(np.int64)


def split_stamp(stamp: NDArray[np.int64]) -> tuple[NDArray[np.int32], NDArray[np.uint32]]:
    """int64 ns -> (sec, nanosec); ValueError outside the int32 seconds range."""
    sec, nsec = np.divmod(np.asarray(stamp, dtype=np.int64), 1_000_000_000)
    if np.any(sec > np.iinfo(np.int32).max) or np.any(sec < np.iinfo(np.int32).min):
        raise ValueError("stamp out of the int32 seconds range of builtin_interfaces/Time")
    return sec.astype(np.int32), nsec.astype(np.uint32)


# --------------------------------------------------------------------------------------------
# Decoding
# --------------------------------------------------------------------------------------------


@dataclass
class Decoded:
    """Bulk decode result of one batch: good rows' fields plus (index, reason) of bad rows.

    Attributes
    ----------
    keep : ndarray of bool, shape (n,)
        Rows decoded.
    fields : dict of str to ndarray
        Row-aligned arrays of the kept rows; always has ``"log"`` (log times, ns).
    frame_ids : list of str
        Distinct ``header.frame_id`` values of the kept rows.
    bad : list of (int, str)
        Index (into the batch) and reason of every row not decoded.
    """

    keep: NDArray[np.bool_]
    fields: dict[str, NDArray[Any]]
    frame_ids: list[str]
    bad: list[tuple[int, str]]


def _header_bulk(
    buf: NDArray[np.uint8], off: NDArray[np.int64], ln: NDArray[np.int64], type_name: str
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.bool_], list[tuple[int, str]]]:
    """Decode encapsulation + ``std_msgs/Header`` of many payloads.

    Returns
    -------
    stamp : ndarray of int64, shape (n,)
        header.stamp, ns.
    strlen : ndarray of int64, shape (n,)
        CDR string length of frame_id (incl. NUL).
    ok : ndarray of bool, shape (n,)
        Rows whose header could be decoded.
    bad : list of (row, reason)
    """
    n = len(off)
    bad: list[tuple[int, str]] = []
    ok = ln >= 16
    for i in np.flatnonzero(~ok):
        bad.append((int(i), f"payload of {ln[i]} bytes is shorter than a CDR header (16 bytes)"))
    safe_off = np.where(ok, off, 0)
    head = windows(buf, safe_off, 16) if n else np.zeros((0, 16), np.uint8)
    enc_ok = (head[:, 0] == 0) & (head[:, 1] == 1)
    for i in np.flatnonzero(ok & ~enc_ok):
        bad.append(
            (int(i), f"encapsulation {head[i, 0]:02x}{head[i, 1]:02x} is not CDR little-endian")
        )
    ok &= enc_ok
    words = np.ascontiguousarray(head[:, 4:16]).view("<u4")
    sec = words[:, 0].view("<i4")
    stamp = stamp_ns(sec, words[:, 1])
    strlen = words[:, 2].astype(np.int64)
    str_ok = (strlen >= 1) & (16 + strlen <= ln)
    for i in np.flatnonzero(ok & ~str_ok):
        bad.append((int(i), f"{type_name}: frame_id length {strlen[i]} does not fit the payload"))
    ok &= str_ok
    nul_pos = np.where(ok, off + 16 + strlen - 1, 0)
    nul_ok = buf[nul_pos] == 0 if n else np.zeros(0, bool)
    for i in np.flatnonzero(ok & ~nul_ok):
        bad.append((int(i), f"{type_name}: frame_id is not NUL-terminated"))
    ok &= nul_ok
    return stamp, strlen, ok, bad


def _frame_ids(
    buf: NDArray[np.uint8], off: NDArray[np.int64], strlen: NDArray[np.int64]
) -> list[str]:
    """Distinct frame_ids of the rows."""
    out: list[str] = []
    one = bool((strlen == strlen[0]).all())  # (a topic's rows: one length, no unique's sort)
    for L in strlen[:1] if one else np.unique(strlen):
        rows = off if one else off[strlen == L]
        chars = windows(buf, rows + 16, int(L) - 1)
        if len(rows) > 1 and not np.all(chars == chars[0]):
            uniq = np.unique(chars, axis=0)
        else:
            uniq = chars[:1]
        for u in uniq:
            s = bytes(u).decode("utf-8", errors="replace")
            if s not in out:
                out.append(s)
    return out


def _check_len(
    ln: NDArray[np.int64],
    expected: NDArray[np.int64],
    ok: NDArray[np.bool_],
    strlen: NDArray[np.int64],
    type_name: str,
    bad: list[tuple[int, str]],
) -> NDArray[np.bool_]:
    len_ok = (ln >= expected) & (ln <= expected + MAX_PAD)
    for i in np.flatnonzero(ok & ~len_ok):
        bad.append(
            (
                int(i),
                f"payload of {ln[i]} bytes, expected {expected[i]} for {type_name} "
                f"with a frame_id of {strlen[i] - 1} chars",
            )
        )
    return ok & len_ok


def decode_f8_block(
    buf: NDArray[np.uint8],
    off: NDArray[np.int64],
    ln: NDArray[np.int64],
    log: NDArray[np.int64],
    n_doubles: int,
    type_name: str,
    picks: dict[str, tuple[int, int]] | None = None,
) -> Decoded:
    """Decode types laid out as ``Header`` followed by ``n_doubles`` float64 only.

    This covers ``Imu`` (37 doubles), ``Temperature`` and ``FluidPressure`` (2 doubles).
    The doubles start at ``4 + align8(12 + strlen)``.

    Parameters
    ----------
    buf : ndarray of uint8
        Decompressed chunk.
    off, ln, log : ndarray of int64, shape (n,)
        Payload offset in ``buf``, payload length (bytes) and log time (ns) of each message.
    n_doubles : int
        Number of float64 after the header.
    type_name : str
        For error messages.
    picks : dict of str to (int, int), optional
        Copy only these ranges of doubles, each to a field of shape (n, stop - start), plus
        all the doubles of the first kept row as ``"first"`` (1, n_doubles). Default: every
        double to ``"f8"``.

    Returns
    -------
    Decoded
        Fields ``stamp`` (n,), ``log`` (n,) and the doubles of the kept rows.
    """
    stamp, strlen, ok, bad = _header_bulk(buf, off, ln, type_name)
    start = 4 + align(12 + strlen, 8)
    ok = _check_len(ln, start + 8 * n_doubles, ok, strlen, type_name, bad)
    good = np.flatnonzero(ok)
    at = off[good] + start[good]
    fields = {"stamp": stamp[good], "log": log[good]}
    for name, (a, b) in (picks or {"f8": (0, n_doubles)}).items():
        block = windows(buf, at + 8 * a, 8 * (b - a))
        fields[name] = np.ascontiguousarray(block).view("<f8").reshape(len(good), b - a)
    if picks is not None:
        fields["first"] = windows(buf, at[:1], 8 * n_doubles).copy().view("<f8")
    frames = _frame_ids(buf, off[good], strlen[good]) if len(good) else []
    return Decoded(keep=ok, fields=fields, frame_ids=frames, bad=bad)


def decode_navsat(
    buf: NDArray[np.uint8], off: NDArray[np.int64], ln: NDArray[np.int64], log: NDArray[np.int64]
) -> Decoded:
    """Bulk-decode ``sensor_msgs/msg/NavSatFix`` (arguments as :func:`decode_f8_block`).

    Layout after the header: int8 status at ``12+s``, uint16 service at ``align2(13+s)``,
    12 float64 (lat, lon, alt, covariance[9]) at ``align8(service+2)``, uint8 covariance type.
    """
    stamp, strlen, ok, bad = _header_bulk(buf, off, ln, NAVSATFIX)
    st_pos = 4 + 12 + strlen
    sv_pos = 4 + align(13 + strlen, 2)
    d_pos = 4 + align(sv_pos - 4 + 2, 8)
    ok = _check_len(ln, d_pos + 97, ok, strlen, NAVSATFIX, bad)
    good = np.flatnonzero(ok)
    o = off[good]
    status = buf[o + st_pos[good]].view(np.int8).astype(np.int64)
    service = windows(buf, o + sv_pos[good], 2).copy().view("<u2")[:, 0].astype(np.int64)
    block = windows(buf, o + d_pos[good], 97)
    doubles = np.ascontiguousarray(block[:, :96]).view("<f8").reshape(len(good), 12)
    cov_type = block[:, 96].astype(np.int64)
    frames = _frame_ids(buf, o, strlen[good]) if len(good) else []
    return Decoded(
        keep=ok,
        fields={
            "stamp": stamp[good],
            "f8": doubles,
            "status": status,
            "service": service,
            "cov_type": cov_type,
            "log": log[good],
        },
        frame_ids=frames,
        bad=bad,
    )


_STAR_NAMES = ["catalog_id", "ra", "dec", "u", "v", "mag", "sigma"]
_STAR_FORMATS = ["<u4", "<f8", "<f8", "<f8", "<f8", "<f4", "<f4"]
STAR_DT_ALIGNED = np.dtype(
    {
        "names": _STAR_NAMES,
        "formats": _STAR_FORMATS,
        "offsets": [0, 8, 16, 24, 32, 40, 44],
        "itemsize": 48,
    }
)
STAR_DT_PACKED = np.dtype(
    {
        "names": _STAR_NAMES,
        "formats": _STAR_FORMATS,
        "offsets": [0, 4, 12, 20, 28, 36, 40],
        "itemsize": 44,
    }
)


def parse_header(data: bytes | memoryview, n: int) -> tuple[int, str, int]:
    """Encapsulation + ``std_msgs/Header`` of one payload of ``n`` bytes; ValueError(reason).

    Returns
    -------
    (stamp ns, frame_id, position after the header)
    """
    if n < 16:
        raise ValueError(f"payload of {n} bytes is shorter than a CDR header (16 bytes)")
    if data[0] != 0 or data[1] != 1:
        raise ValueError(f"encapsulation {data[0]:02x}{data[1]:02x} is not CDR little-endian")
    sec, nsec, slen = struct.unpack_from("<iII", data, 4)
    if slen < 1 or 16 + slen > n:
        raise ValueError(f"frame_id length {slen} does not fit the payload of {n} bytes")
    raw = bytes(data[16 : 16 + slen])
    if raw[-1] != 0:
        raise ValueError("frame_id is not NUL-terminated")
    return int(sec) * 1_000_000_000 + int(nsec), raw[:-1].decode("utf-8", errors="replace"), \
        16 + slen


def header_bytes(stamp_ns: int, frame_id: str) -> bytearray:
    """Encapsulation + ``std_msgs/Header`` (no padding after the frame_id)."""
    fid = frame_id.encode("utf-8") + b"\x00"
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return bytearray(struct.pack("<4siII", b"\x00\x01\x00\x00", sec, nsec, len(fid)) + fid)


def decode_star_array(data: bytes | memoryview) -> StarFrame:
    """Decode one ``StarCentroidArray`` CDR payload; ValueError(reason) if malformed.

    A ``StarCentroid`` element is 48 bytes when it starts 8-aligned (4 bytes of padding after
    ``catalog_id``) and 44 bytes when ``catalog_id`` sits at 4 mod 8; after an element the
    position is always 8-aligned, so only the first element can be the 44-byte form.
    """
    n = len(data)
    stamp, frame_id, pos = parse_header(data, n)
    pos = 4 + align(pos - 4, 4)
    if pos + 8 > n:
        raise ValueError(f"payload of {n} bytes ends inside exposure_time / stars length")
    exposure, count = struct.unpack_from("<fI", data, pos)
    pos += 8
    if count == 0:
        expected = pos
    elif (pos - 4) % 8 == 0:
        expected = pos + 48 * count
    else:
        expected = pos + 44 + 48 * (count - 1)
    if not expected <= n <= expected + MAX_PAD:
        raise ValueError(
            f"payload of {n} bytes, expected {expected} for {STAR_ARRAY} with {count} stars"
        )
    if count == 0:
        arr = np.zeros(0, STAR_DT_ALIGNED)
    elif (pos - 4) % 8 == 0:
        arr = np.frombuffer(data, STAR_DT_ALIGNED, count, pos)
    else:
        first = np.frombuffer(data, STAR_DT_PACKED, 1, pos)
        rest = np.frombuffer(data, STAR_DT_ALIGNED, count - 1, pos + 44)
        arr = np.zeros(count, STAR_DT_ALIGNED)
        for name in _STAR_NAMES:
            arr[name][0] = first[name][0]
            arr[name][1:] = rest[name]
    uv = np.empty((count, 2))  # (u, v) side by side, one copy
    uv[:, 0] = arr["u"]
    uv[:, 1] = arr["v"]
    return StarFrame(
        stamp_ns=stamp,
        frame_id=frame_id,
        exposure_time=float(exposure),
        catalog_id=arr["catalog_id"].astype(np.uint32),
        right_ascension=arr["ra"].astype(np.float64),
        declination=arr["dec"].astype(np.float64),
        uv=uv,
        magnitude=arr["mag"].astype(np.float64),
        sigma=arr["sigma"].astype(np.float64),
    )


def decode_star_frames(
    buf: NDArray[np.uint8], off: NDArray[np.int64], ln: NDArray[np.int64], log: NDArray[np.int64]
) -> Decoded:
    """Decode many ``StarCentroidArray`` payloads (arguments as :func:`decode_f8_block`).

    Returns
    -------
    Decoded
        Fields ``obj`` (object array of :class:`StarFrame`, ``log_time_ns`` filled) and ``log``.
    """
    bulk = _star_frames_bulk(buf, off, ln, log)
    if bulk is not None:
        return bulk
    mv = memoryview(buf)
    return decode_each(lambda _, o, n: decode_star_array(mv[o : o + n]), buf, off, ln, log)


def _star_frames_bulk(
    buf: NDArray[np.uint8], off: NDArray[np.int64], ln: NDArray[np.int64], log: NDArray[np.int64]
) -> Decoded | None:
    """:func:`decode_star_frames` of a well-formed batch in one numpy pass (None: not one).

    Every payload well formed, one frame_id, every star array 8-aligned (what a tracker
    writes); otherwise None, and the batch is decoded one payload at a time, each error
    said as :func:`decode_star_array` says it.  The frames are :func:`decode_star_array`'s,
    value for value and dtype for dtype (their arrays are slices of the batch's).
    """
    n = len(off)
    if n < 2:
        return None
    stamp, strlen, ok, bad = _header_bulk(buf, off, ln, STAR_ARRAY)
    if bad or not ok.all() or np.any(strlen != strlen[0]):
        return None
    pos = 4 + align(16 + strlen - 4, 4)
    if np.any(pos + 8 > ln):
        return None
    head = windows(buf, off + pos, 8)
    exposure = np.ascontiguousarray(head[:, :4]).view("<f4")[:, 0]
    count = np.ascontiguousarray(head[:, 4:]).view("<u4")[:, 0].astype(np.int64)
    pos = pos + 8
    expected = pos + 48 * count
    if np.any((pos - 4) % 8 != 0) or np.any(ln < expected) or np.any(ln > expected + MAX_PAD):
        return None
    chars = windows(buf, off + 16, int(strlen[0]) - 1)
    if not np.all(chars == chars[0]):
        return None
    frame_id = bytes(chars[0]).decode("utf-8", errors="replace")
    total = int(count.sum())
    first = np.cumsum(count) - count
    at = np.repeat(off + pos, count) + 48 * (np.arange(total) - np.repeat(first, count))
    arr = windows(buf, at, 48).view(STAR_DT_ALIGNED)[:, 0] if total else \
        np.zeros(0, STAR_DT_ALIGNED)
    catalog = arr["catalog_id"].astype(np.uint32)
    ra = arr["ra"].astype(np.float64)
    dec = arr["dec"].astype(np.float64)
    mag = arr["mag"].astype(np.float64)
    sigma = arr["sigma"].astype(np.float64)
    uv = np.empty((total, 2))
    uv[:, 0] = arr["u"]
    uv[:, 1] = arr["v"]
    objs = np.empty(n, dtype=object)
    bounds = np.concatenate([first, [total]]).tolist()
    for j, (t, e, lt) in enumerate(zip(stamp.tolist(), exposure.astype(np.float64).tolist(),
                                       log.tolist(), strict=True)):
        a, b = bounds[j], bounds[j + 1]
        objs[j] = StarFrame(t, frame_id, e, catalog[a:b], ra[a:b], dec[a:b], uv[a:b],
                            mag[a:b], sigma[a:b], lt)
    return Decoded(np.ones(n, bool), {"obj": objs, "log": log}, [], [])


def decode_each(
    decode: Callable[[NDArray[np.uint8], int, int], Any],
    buf: NDArray[np.uint8],
    off: NDArray[np.int64],
    ln: NDArray[np.int64],
    log: NDArray[np.int64],
) -> Decoded:
    """Decode payloads one at a time: ``decode(buf, offset, length)`` -> a message object.

    The object gets its ``log_time_ns``; a ValueError marks the row bad with its text.

    Returns
    -------
    Decoded
        Fields ``obj`` (object array of the messages) and ``log``.
    """
    objs = np.empty(len(off), dtype=object)
    keep = np.ones(len(off), bool)
    bad: list[tuple[int, str]] = []
    for j, (o, n, t) in enumerate(zip(off.tolist(), ln.tolist(), log.tolist(), strict=True)):
        try:
            msg = decode(buf, o, n)
        except ValueError as exc:
            keep[j] = False
            bad.append((j, str(exc)))
            continue
        msg.log_time_ns = t
        objs[j] = msg
    return Decoded(keep, {"obj": objs[keep], "log": log[keep]}, [], bad)


# --------------------------------------------------------------------------------------------
# Encoding
# --------------------------------------------------------------------------------------------


def _header_dtype(frame_id: str, fields: list[tuple[str, Any, int]]) -> np.dtype:
    """Structured dtype of a CDR message: encapsulation + Header + fields after it.

    ``fields`` is a list of (name, numpy format, alignment); each is placed at the next
    offset aligned (relative to byte 4) to its alignment.
    """
    fid = frame_id.encode("utf-8") + b"\x00"
    names = ["enc", "sec", "nsec", "slen", "fid"]
    formats: list[Any] = [("u1", 4), "<i4", "<u4", "<u4", f"S{len(fid)}"]
    offsets = [0, 4, 8, 12, 16]
    pos = 16 + len(fid)
    for name, fmt, alignment in fields:
        pos = 4 + align(pos - 4, alignment)
        names.append(name)
        formats.append(fmt)
        offsets.append(pos)
        pos += np.dtype(fmt).itemsize
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": pos})


def _header_array(n: int, dt: np.dtype, stamp: NDArray[np.int64], frame_id: str) -> NDArray[Any]:
    arr = np.zeros(n, dt)
    sec, nsec = split_stamp(stamp)
    fid = frame_id.encode("utf-8") + b"\x00"
    arr["enc"] = (0, 1, 0, 0)
    arr["sec"] = sec
    arr["nsec"] = nsec
    arr["slen"] = len(fid)
    arr["fid"] = fid
    return arr


def _encoder(
    stamp: NDArray[np.int64],
    frame_id: str,
    fields: list[tuple[str, Any, int]],
    columns: dict[str, Callable[[NDArray[np.int64]], NDArray[Any]]],
) -> tuple[int, Encoder]:
    """(payload size, encoder) of a Header + fixed fields message series.

    ``columns`` maps each field name to a function of the row indices giving its values.
    """
    split_stamp(stamp)  # validate the range now, not when encoding
    dt = _header_dtype(frame_id, fields)

    def encode(idx: NDArray[np.int64]) -> NDArray[np.uint8]:
        arr = _header_array(len(idx), dt, stamp[idx], frame_id)
        for name, col in columns.items():
            arr[name] = col(idx)
        return arr.view(np.uint8).reshape(-1)

    return dt.itemsize, encode


def _rows_of(values: NDArray[Any]) -> Callable[[NDArray[np.int64]], NDArray[Any]]:
    return values.__getitem__


def imu_encoder(series: ImuSeries) -> tuple[NDArray[np.int64], int, Encoder]:
    """Encoder of ``sensor_msgs/msg/Imu`` messages for a series.

    Orientation is identity with ``orientation_covariance[0] = -1`` (unknown); the rate /
    specific-force covariances are ``series.*_covariance`` or zeros.

    Returns
    -------
    stamp : ndarray of int64, shape (N,)
        The stamps (copied), used as log times.
    size : int
        Payload size, bytes (the same for every message).
    encode : Encoder
    """
    stamp = np.array(series.stamp_ns, dtype=np.int64, copy=True).reshape(-1)
    n = len(stamp)
    av = np.array(series.angular_velocity, dtype=np.float64, copy=True).reshape(n, 3)
    la = np.array(series.linear_acceleration, dtype=np.float64, copy=True).reshape(n, 3)
    const = np.zeros(37)
    const[3] = 1.0  # quaternion w
    const[4] = -1.0  # orientation_covariance[0]
    if series.angular_velocity_covariance is not None:
        const[16:25] = np.asarray(series.angular_velocity_covariance, float).reshape(9)
    if series.linear_acceleration_covariance is not None:
        const[28:37] = np.asarray(series.linear_acceleration_covariance, float).reshape(9)

    def f8(idx: NDArray[np.int64]) -> NDArray[np.float64]:
        block = np.empty((len(idx), 37))
        block[:] = const
        block[:, 13:16] = av[idx]
        block[:, 25:28] = la[idx]
        return block

    size, enc = _encoder(stamp, series.frame_id, [("f8", ("<f8", 37), 8)], {"f8": f8})
    return stamp, size, enc


def scalar_encoder(series: ScalarSeries) -> tuple[NDArray[np.int64], int, Encoder]:
    """Encoder of ``Temperature`` / ``FluidPressure`` messages (same layout); see imu_encoder."""
    stamp = np.array(series.stamp_ns, dtype=np.int64, copy=True).reshape(-1)
    n = len(stamp)
    cols = {
        "value": _rows_of(np.array(series.value, dtype=np.float64, copy=True).reshape(n)),
        "var": _rows_of(np.broadcast_to(np.asarray(series.variance, np.float64), (n,)).copy()),
    }
    size, enc = _encoder(
        stamp, series.frame_id, [("value", "<f8", 8), ("var", "<f8", 8)], cols
    )
    return stamp, size, enc


def navsat_encoder(series: NavSatSeries) -> tuple[NDArray[np.int64], int, Encoder]:
    """Encoder of ``sensor_msgs/msg/NavSatFix`` messages; see :func:`imu_encoder`.

    Optional ``service``, ``position_covariance`` (N, 9) m^2 and ``position_covariance_type``
    default to 0.
    """
    stamp = np.array(series.stamp_ns, dtype=np.int64, copy=True).reshape(-1)
    n = len(stamp)
    f8 = np.zeros((n, 12))
    f8[:, 0] = series.latitude_deg
    f8[:, 1] = series.longitude_deg
    f8[:, 2] = series.altitude_m
    if series.position_covariance is not None:
        f8[:, 3:] = np.asarray(series.position_covariance, float).reshape(n, 9)

    def column(v: object, dtype: Any) -> NDArray[Any]:
        return np.broadcast_to(np.asarray(0 if v is None else v), (n,)).astype(dtype)

    cols = {
        "status": _rows_of(column(series.status, np.int8)),
        "service": _rows_of(column(series.service, np.uint16)),
        "f8": _rows_of(f8),
        "ct": _rows_of(column(series.position_covariance_type, np.uint8)),
    }
    fields = [("status", "i1", 1), ("service", "<u2", 2), ("f8", ("<f8", 12), 8), ("ct", "u1", 1)]
    size, enc = _encoder(stamp, series.frame_id, fields, cols)
    return stamp, size, enc


def _star_columns(frame: StarFrame, uv: NDArray[np.float64]) -> list[tuple[str, ArrayLike]]:
    return [
        ("catalog_id", np.asarray(frame.catalog_id, np.uint32)),
        ("ra", np.asarray(frame.right_ascension, np.float64)),
        ("dec", np.asarray(frame.declination, np.float64)),
        ("u", uv[:, 0]),
        ("v", uv[:, 1]),
        ("mag", np.asarray(frame.magnitude, np.float32)),
        ("sigma", np.asarray(frame.sigma, np.float32)),
    ]


def encode_star_frame(frame: StarFrame) -> bytes:
    """CDR payload of one ``StarCentroidArray`` message.

    Parameters
    ----------
    frame : StarFrame
        The exposure.

    Returns
    -------
    bytes
        Encapsulated little-endian CDR.
    """
    n = len(frame.catalog_id)
    head = header_bytes(frame.stamp_ns, frame.frame_id)
    head += b"\x00" * ((4 - (len(head) - 4) % 4) % 4)
    head += struct.pack("<fI", frame.exposure_time, n)
    if n == 0:
        return head
    uv = np.asarray(frame.uv, np.float64).reshape(n, 2)
    if (len(head) - 4) % 8 == 0:
        arr = np.zeros(n, STAR_DT_ALIGNED)
        first = b""
        rest_slice = slice(0, n)
    else:
        arr = np.zeros(n - 1, STAR_DT_ALIGNED)
        one = np.zeros(1, STAR_DT_PACKED)
        for name, src in _star_columns(frame, uv):
            one[name] = src[:1]
        first = one.tobytes()
        rest_slice = slice(1, n)
    for name, src in _star_columns(frame, uv):
        arr[name] = src[rest_slice]
    return head + first + arr.tobytes()
