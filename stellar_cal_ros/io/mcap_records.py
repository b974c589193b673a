"""MCAP records: opcodes, record layouts, cursors, chunk decompression, batches and damage reports.

The pieces :mod:`stellar_cal_ros.io.mcap_container` parses a file with and the writer writes
one with, plus the two types every bag source shares: :class:`Rows` (the messages of one
chunk, as offsets into its decompressed bytes) and :class:`BagProblem` (a damaged part).
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER = 0x01
OP_FOOTER = 0x02
OP_SCHEMA = 0x03
OP_CHANNEL = 0x04
OP_MESSAGE = 0x05
OP_CHUNK = 0x06
OP_MESSAGE_INDEX = 0x07
OP_CHUNK_INDEX = 0x08
OP_STATISTICS = 0x0B
OP_SUMMARY_OFFSET = 0x0E
OP_DATA_END = 0x0F
DATA_OPS = frozenset({0x02, 0x03, 0x04, 0x05, 0x06, 0x07, 0x09, 0x0C, 0x0F})

REC_HDR = struct.Struct("<BQ")  # opcode, record length
MSG_HDR = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
MSG_PREFIX = REC_HDR.size + MSG_HDR.size  # 31 bytes before a message's payload
CHUNK_HEAD = struct.Struct("<QQQIi")  # start, end, uncompressed size, crc, compression len
FOOTER_LEN = 1 + 8 + 20 + len(MAGIC)  # footer record + trailing magic
MSG_RECORD_DTYPE = np.dtype(
    [("op", "u1"), ("len", "<u8"), ("ch", "<u2"), ("seq", "<u4"), ("log", "<u8"), ("pub", "<u8")]
)
COMPRESSIONS = ("zstd", "lz4", "")
LOOSE_BLOCK = 4 << 20  # un-chunked message records are read in runs of this many bytes


class CorruptError(Exception):
    """The container cannot be parsed at ``offset`` (converted to BagError by the reader)."""

    def __init__(self, offset: int, reason: str) -> None:
        super().__init__(reason)
        self.offset = offset
        self.reason = reason


@dataclass
class BagProblem:
    """One damaged part of a bag.

    Attributes
    ----------
    offset : int
        Byte offset of the damaged record (or of the start of the damaged region).
    reason : str
        What is wrong (e.g. ``chunk CRC mismatch``).
    chunk : int or None
        1-based number of the chunk in file order, when known.
    n_chunks : int or None
        Number of chunks in the file, when known (summary).
    start_ns, end_ns : int or None
        Log-time range whose messages are lost (None: unknown or none lost).
    topics : tuple of str or None
        Topics with messages in the lost part (None: unknown).
    lost : bool
        False when the damage is outside every chunk (no message lost).
    path : str
        File the problem is in.
    """

    offset: int
    reason: str
    chunk: int | None = None
    n_chunks: int | None = None
    start_ns: int | None = None
    end_ns: int | None = None
    topics: tuple[str, ...] | None = None
    lost: bool = True
    path: str = ""

    def describe(self, t0_ns: int | None = None) -> str:
        """One line: where, what, the time range lost and the topics affected.

        Parameters
        ----------
        t0_ns : int, optional
            Bag start (log time, ns); times are printed relative to it when given.
        """
        where = f"chunk {self.chunk}" + (f"/{self.n_chunks}" if self.n_chunks else "") \
            if self.chunk is not None else "data"
        text = f"{Path(self.path).name}: {where} at byte {self.offset}: {self.reason}"
        if not self.lost:
            return text + "; no message lost"
        if self.start_ns is not None and self.end_ns is not None:
            rel = t0_ns if t0_ns is not None else 0
            text += (f"; lost log time {(self.start_ns - rel) * 1e-9:.3f}"
                     f"-{(self.end_ns - rel) * 1e-9:.3f} s"
                     + (" after the bag start" if t0_ns is not None else ""))
        else:
            text += "; time range lost unknown"
        if self.topics is None:
            text += ", topics unknown"
        else:
            text += f" on {', '.join(self.topics) or 'no topic'}"
        return text


class Cursor:
    """Sequential little-endian reader over a bytes-like record body."""

    __slots__ = ("buf", "pos", "end", "base")

    def __init__(self, buf: bytes | memoryview, pos: int, end: int, base: int = 0) -> None:
        self.buf = buf
        self.pos = pos
        self.end = end
        self.base = base

    def _need(self, n: int) -> None:
        if self.pos + n > self.end:
            raise CorruptError(self.base + self.pos, "record shorter than its fields")

    def _unpack(self, fmt: str, n: int) -> int:
        self._need(n)
        (v,) = struct.unpack_from(fmt, self.buf, self.pos)
        self.pos += n
        return int(v)

    def u16(self) -> int:
        """Read a uint16."""
        return self._unpack("<H", 2)

    def u32(self) -> int:
        """Read a uint32."""
        return self._unpack("<I", 4)

    def u64(self) -> int:
        """Read a uint64."""
        return self._unpack("<Q", 8)

    def raw(self, n: int) -> bytes:
        """Read ``n`` bytes."""
        self._need(n)
        v = bytes(self.buf[self.pos : self.pos + n])
        self.pos += n
        return v

    def string(self) -> str:
        """Read a uint32-prefixed UTF-8 string."""
        n = self.u32()
        try:
            return self.raw(n).decode("utf-8")
        except UnicodeDecodeError as exc:
            raise CorruptError(self.base + self.pos, "string is not UTF-8") from exc

    def str_map(self) -> dict[str, str]:
        """Read a uint32-prefixed map of string to string."""
        n = self.u32()
        stop = self.pos + n
        out: dict[str, str] = {}
        while self.pos < stop:
            k = self.string()
            out[k] = self.string()
        return out


def p_string(s: str) -> bytes:
    """Serialise an MCAP string (uint32 length + UTF-8)."""
    b = s.encode("utf-8")
    return struct.pack("<I", len(b)) + b


def p_record(op: int, body: bytes) -> bytes:
    """Serialise a record (opcode, uint64 length, body)."""
    return REC_HDR.pack(op, len(body)) + body


@dataclass
class Schema:
    """An MCAP schema record."""

    id: int
    name: str
    encoding: str
    data: bytes


@dataclass
class Channel:
    """An MCAP channel record."""

    id: int
    schema_id: int
    topic: str
    message_encoding: str
    metadata: dict[str, str]


@dataclass
class ChunkIndex:
    """Where a chunk is and what it holds (from the summary or from a scan of the file).

    ``compression`` is ``"loose"`` for a run of un-chunked message records of the data
    section (read raw); ``number`` is the 1-based position of the chunk among the chunks in
    file order, ``rank`` the position of the entry (chunk or loose run) in file order.
    """

    start: int
    end: int
    offset: int
    length: int
    index_offsets: dict[int, int]
    index_length: int
    compression: str
    compressed_size: int
    uncompressed_size: int
    number: int = 0
    rank: int = 0


@dataclass
class Summary:
    """What the summary section says."""

    chunk_indexes: list[ChunkIndex]
    channel_counts: dict[int, int] | None
    message_count: int | None
    start: int | None
    end: int | None


@dataclass
class Rows:
    """Messages of one chunk on the selected channels, sorted by (log time, position).

    ``buf`` is the decompressed chunk; ``offset``/``length`` locate each payload in it.
    ``start_ns`` is a lower bound of the log times of this and every later batch. ``rank``
    is the batch's position in the order the bag was written (for a file, the chunk's rank in
    file order), so ``rank * 2**32 + row`` orders messages of equal log time as written.
    """

    buf: NDArray[np.uint8]
    channel: NDArray[np.uint16]
    sequence: NDArray[np.uint32]
    log_time: NDArray[np.int64]
    publish_time: NDArray[np.int64]
    offset: NDArray[np.int64]
    length: NDArray[np.int64]
    start_ns: int
    rank: int = 0

    def __len__(self) -> int:
        return len(self.log_time)

    def sorted(self) -> Rows:
        """These rows sorted by (log time, position in the chunk)."""
        log = self.log_time
        if len(log) > 1 and (np.any(log[1:] < log[:-1]) or np.any(np.diff(self.offset) < 0)):
            order = np.lexsort((self.offset, log))
            return Rows(self.buf, self.channel[order], self.sequence[order], log[order],
                        self.publish_time[order], self.offset[order], self.length[order],
                        self.start_ns, self.rank)
        return self

    def order_key(self, rows: NDArray[np.int64]) -> NDArray[np.int64]:
        """Write-order key (``rank * 2**32 + row``) of the given rows, int64."""
        return (self.rank << 32) + rows.astype(np.int64)

    @staticmethod
    def empty(buf: NDArray[np.uint8], start_ns: int) -> Rows:
        """No message."""
        z = np.zeros(0, np.int64)
        return Rows(buf, np.zeros(0, np.uint16), np.zeros(0, np.uint32), z, z, z, z, start_ns)


OnDamage = Callable[[BagProblem], None]
"""Called with each damaged part met while reading; raises to stop, returns to go on."""


def decompress(compression: str, data: bytes, size: int, where: int) -> bytes:
    """Decompress a chunk's records; CorruptError if the codec fails or the size is wrong."""
    try:
        if compression == "":
            out = data
        elif compression == "zstd":
            import zstandard

            out = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
        elif compression == "lz4":
            import lz4.frame

            out = lz4.frame.decompress(data)
        else:
            raise CorruptError(where, f"unsupported chunk compression {compression!r}")
    except CorruptError:
        raise
    except Exception as exc:  # the codecs raise their own error types
        raise CorruptError(where, f"{compression} decompression failed: {exc}") from exc
    if len(out) != size:
        raise CorruptError(where, f"chunk decompressed to {len(out)} bytes, expected {size}")
    return out


def parse_chunk_index(cur: Cursor) -> ChunkIndex:
    """Parse the body of a chunk index record."""
    start, end, offset, length = cur.u64(), cur.u64(), cur.u64(), cur.u64()
    n = cur.u32()
    offsets = {}
    for _ in range(n // 10):
        cid = cur.u16()
        offsets[cid] = cur.u64()
    index_length = cur.u64()
    compression = cur.string()
    return ChunkIndex(
        start, end, offset, length, offsets, index_length, compression, cur.u64(), cur.u64()
    )


def chunk_head(raw: bytes | memoryview, pos: int, size: int) -> ChunkIndex | None:
    """The chunk record header at ``raw[pos]`` if it is plausible, else None.

    ``size`` is the number of bytes of the file from ``pos`` on. The record body is
    ``start, end, uncompressed size, crc, compression (string), records (uint64 + bytes)``;
    the returned entry has ``offset = -1`` (the caller knows where it is).
    """
    if pos + 9 + CHUNK_HEAD.size > len(raw) or raw[pos] != OP_CHUNK:
        return None
    (length,) = struct.unpack_from("<Q", raw, pos + 1)
    start, end, usize, _crc, clen = CHUNK_HEAD.unpack_from(raw, pos + 9)
    at = pos + 9 + CHUNK_HEAD.size
    if clen not in (0, 3, 4) or at + clen + 8 > len(raw) or start > end:
        return None
    comp = bytes(raw[at : at + clen])
    if comp not in (b"", b"lz4", b"zstd"):
        return None
    (rlen,) = struct.unpack_from("<Q", raw, at + clen)
    if length != CHUNK_HEAD.size + clen + 8 + rlen or 9 + length > size or usize > 1 << 36:
        return None
    return ChunkIndex(start, end, -1, 9 + length, {}, 0, comp.decode(), rlen, usize)
