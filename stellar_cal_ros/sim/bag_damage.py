"""Damage MCAP files at the record and byte level (for the fault campaign and tests).

Records are read and written with the independent ``mcap`` library (not the project's
reader/writer), so a damaged file exercises the project's reader as a foreign recording would:
log times that disagree with header stamps, duplicated records, messages out of log order.
Byte-level helpers cut, zero or flip bytes, or alter a chunk's stored CRC.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path


@dataclass
class RawMessage:
    """One MCAP message as stored: topic, schema, log time and CDR payload."""

    topic: str
    schema_name: str
    schema_text: bytes
    log_time_ns: int
    data: bytes


def read_raw(path: str | Path) -> list[RawMessage]:
    """Every message of a bag in file order (the independent ``mcap`` reader)."""
    from mcap.reader import make_reader

    out = []
    with open(path, "rb") as fh:
        for schema, channel, msg in make_reader(fh).iter_messages(log_time_order=False):
            out.append(RawMessage(channel.topic, schema.name if schema else "",
                                  schema.data if schema else b"", int(msg.log_time),
                                  bytes(msg.data)))
    return out


def write_raw(path: str | Path, messages: Iterable[RawMessage]) -> Path:
    """Write messages in the given order with the independent ``mcap`` writer (ros2 profile)."""
    from mcap.writer import CompressionType, Writer

    path = Path(path)
    with open(path, "wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD, chunk_size=256 * 1024)
        w.start(profile="ros2", library="stellar_cal_ros.sim.faults")
        schemas: dict[tuple[str, bytes], int] = {}
        channels: dict[tuple[str, int], int] = {}
        for m in messages:
            sid = schemas.get((m.schema_name, m.schema_text))
            if sid is None:
                sid = schemas[(m.schema_name, m.schema_text)] = w.register_schema(
                    m.schema_name, "ros2msg", m.schema_text)
            cid = channels.get((m.topic, sid))
            if cid is None:
                cid = channels[(m.topic, sid)] = w.register_channel(m.topic, "cdr", sid)
            w.add_message(cid, log_time=m.log_time_ns, data=m.data,
                          publish_time=m.log_time_ns)
        w.finish()
    return path


def header_stamp_ns(data: bytes) -> int:
    """``header.stamp`` (ns) of a CDR payload that starts with a std_msgs/Header."""
    sec, nsec = struct.unpack_from("<iI" if data[1] == 1 else ">iI", data, 4)
    return sec * 1_000_000_000 + nsec


def with_header_stamp(data: bytes, stamp_ns: int) -> bytes:
    """The payload with its ``header.stamp`` replaced (the log time is not touched)."""
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    head = struct.pack("<iI" if data[1] == 1 else ">iI", sec, nsec)
    return data[:4] + head + data[12:]


# ============================================================================ byte damage
def chunk_spans(path: str | Path) -> list[tuple[int, int, int, int]]:
    """``(offset, length, start_ns, end_ns)`` of every chunk, from the summary."""
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    if summary is None:
        return []
    return sorted((ci.chunk_start_offset, ci.chunk_length, ci.message_start_time,
                   ci.message_end_time) for ci in summary.chunk_indexes)


def truncate(data: bytes, fraction: float) -> bytes:
    """The first ``fraction`` of the bytes."""
    return data[:int(len(data) * fraction)]


def zero_range(data: bytes, offset: int, length: int) -> bytes:
    """``length`` bytes from ``offset`` set to zero (clipped to the file)."""
    b = bytearray(data)
    lo, hi = max(0, offset), min(len(b), offset + length)
    b[lo:hi] = bytes(hi - lo)
    return bytes(b)


def flip_bytes(data: bytes, offsets: Iterable[int], mask: int = 0xFF) -> bytes:
    """XOR the bytes at ``offsets`` with ``mask``."""
    b = bytearray(data)
    for o in offsets:
        if 0 <= o < len(b):
            b[o] ^= mask
    return bytes(b)


_CHUNK_CRC_AT = 1 + 8 + 8 + 8 + 8  # opcode, length, start, end, uncompressed size


def bad_chunk_crc(data: bytes, chunk_offset: int) -> bytes:
    """The chunk at ``chunk_offset`` with its stored uncompressed-data CRC changed."""
    at = chunk_offset + _CHUNK_CRC_AT
    (crc,) = struct.unpack_from("<I", data, at)
    return data[:at] + struct.pack("<I", (crc ^ 0x5A5A5A5A) or 1) + data[at + 4:]
