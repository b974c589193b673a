"""The MCAP container: records, chunks, chunk and message indexes, summary, CRCs, damage.

:class:`McapFile` parses an MCAP file itself (magic, header, footer, summary, chunk indexes,
chunks and message indexes) and yields the messages of the wanted channels chunk by chunk as
:class:`Rows` (offsets into the decompressed chunk, no per-message object). It never holds
more than one chunk. Damage is reported, not hidden: every chunk whose CRC, decompression or
record structure fails is described by a :class:`BagProblem`, and reading goes on with the
next valid chunk (through the summary's chunk index when there is one, else by scanning
forward for the next chunk record whose CRC validates), so the caller decides whether a
problem is fatal.
"""

from __future__ import annotations

import logging
import os
import struct
import warnings
import zlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from stellar_cal_ros.errors import BagDamageWarning, BagError, no_such_bag
from stellar_cal_ros.io.cdr import windows
from stellar_cal_ros.io.mcap_records import (
    DATA_OPS,
    FOOTER_LEN,
    LOOSE_BLOCK,
    MAGIC,
    MSG_HDR,
    MSG_PREFIX,
    MSG_RECORD_DTYPE,
    OP_CHANNEL,
    OP_CHUNK,
    OP_CHUNK_INDEX,
    OP_DATA_END,
    OP_FOOTER,
    OP_HEADER,
    OP_MESSAGE,
    OP_MESSAGE_INDEX,
    OP_SCHEMA,
    OP_STATISTICS,
    REC_HDR,
    BagProblem,
    Channel,
    ChunkIndex,
    CorruptError,
    Cursor,
    OnDamage,
    Rows,
    Schema,
    Summary,
    chunk_head,
    decompress,
    parse_chunk_index,
)

_log = logging.getLogger(__name__)
#: the files whose missing footer was said (the commands open a bag more than once)
_NO_FOOTER_SAID: set[str] = set()


class McapFile:
    """Reader of one MCAP file's container (see the module docstring).

    Parameters
    ----------
    path : str or Path
        The ``.mcap`` file.

    Attributes
    ----------
    schemas, channels : dict of int
        Schema and channel records seen so far (all of them once the summary or a full
        read has been parsed).
    has_summary : bool
        Whether the file has a usable summary section (False for a truncated file).
    profile, library : str
        From the MCAP header record.
    summary_problem : BagProblem or None
        Why the summary is not used (CRC mismatch, unreadable), if it is not.

    Raises
    ------
    BagError
        The file is missing, not an MCAP file, or its header cannot be read.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.summary_problem: BagProblem | None = None
        self._plan: list[ChunkIndex | BagProblem] | None = None
        try:
            self._fh = open(self.path, "rb")  # noqa: SIM115 -- closed in close()
        except FileNotFoundError as exc:
            raise no_such_bag(self.path) from exc
        except OSError as exc:
            raise BagError(f"cannot open bag {self.path}: {exc}") from exc
        try:
            self.size = os.fstat(self._fh.fileno()).st_size
            self._read_header()
            self.summary = self._read_summary()
        except BaseException:
            self._fh.close()
            raise
        self.has_summary = self.summary is not None

    def close(self) -> None:
        """Close the file."""
        self._fh.close()

    def where(self, offset: int) -> str:
        """``PATH at byte N of SIZE`` for messages."""
        return f"{self.path} at byte {offset} of {self.size}"

    def _read(self, offset: int, n: int) -> bytes:
        self._fh.seek(offset)
        return self._fh.read(n)

    # -- header and summary ----------------------------------------------------------------

    def _read_header(self) -> None:
        head = self._fh.read(len(MAGIC) + 9)
        if len(head) < len(MAGIC) or head[: len(MAGIC)] != MAGIC:
            raise BagError(f"{self.path} is not an MCAP file (bad magic bytes)")
        if len(head) < len(MAGIC) + 9:
            raise BagError(f"{self.path}: truncated after the magic bytes ({self.size} bytes)")
        op, length = REC_HDR.unpack_from(head, len(MAGIC))
        body = self._fh.read(length) if length < 1 << 20 else b""
        if op != OP_HEADER or len(body) != length:
            raise BagError(f"{self.path}: unreadable MCAP header record")
        try:
            cur = Cursor(body, 0, len(body))
            self.profile = cur.string()
            self.library = cur.string()
        except CorruptError as exc:
            raise BagError(f"{self.path}: unreadable MCAP header record: {exc.reason}") from exc
        self.data_start = len(MAGIC) + 9 + length

    def _read_summary(self) -> Summary | None:
        """Parse footer + summary section; None (and a log line) if absent or unusable."""
        if self.size < self.data_start + FOOTER_LEN:
            return None
        tail = self._read(self.size - FOOTER_LEN, FOOTER_LEN)
        if tail[-len(MAGIC) :] != MAGIC or tail[0] != OP_FOOTER:
            if str(self.path) not in _NO_FOOTER_SAID:  # once a process (each open asked)
                _NO_FOOTER_SAID.add(str(self.path))
                # (debug: a command's error or data quality line says the truncation, a
                # scan's warning that the index is missing)
                _log.debug("%s: no footer (truncated or still being written)", self.path)
            return None
        _, length, summary_start, summary_offset_start, crc = struct.unpack_from("<BQQQI", tail, 0)
        if length != 20 or summary_start == 0:
            return None
        footer_pos = self.size - FOOTER_LEN
        if not self.data_start <= summary_start <= footer_pos:
            return None
        section = self._read(summary_start, footer_pos - summary_start)
        if crc and zlib.crc32(tail[:25], zlib.crc32(section)) != crc:
            self.summary_problem = BagProblem(summary_start, "summary CRC mismatch", lost=False,
                                              path=str(self.path))
            warnings.warn(
                f"{self.path}: summary CRC mismatch; ignoring the summary and scanning the file",
                BagDamageWarning, stacklevel=3,
            )
            return None
        end = (summary_offset_start - summary_start) if summary_offset_start else len(section)
        chunk_indexes: list[ChunkIndex] = []
        counts: dict[int, int] | None = None
        msg_count = start = stop = None
        try:
            pos = 0
            while pos < end:
                op, ln = REC_HDR.unpack_from(section, pos)
                cur = Cursor(section, pos + 9, pos + 9 + ln, summary_start)
                if op == OP_SCHEMA:
                    self._add_schema(cur)
                elif op == OP_CHANNEL:
                    self._add_channel(cur)
                elif op == OP_CHUNK_INDEX:
                    chunk_indexes.append(parse_chunk_index(cur))
                elif op == OP_STATISTICS:
                    msg_count = cur.u64()
                    cur.u16()
                    for _ in range(4):
                        cur.u32()
                    start, stop = cur.u64(), cur.u64()
                    n = cur.u32()
                    counts = {}
                    for _ in range(n // 10):
                        cid = cur.u16()
                        counts[cid] = cur.u64()
                pos += 9 + ln
        except (CorruptError, struct.error) as exc:
            self.summary_problem = BagProblem(summary_start, f"unreadable summary ({exc})",
                                              lost=False, path=str(self.path))
            warnings.warn(f"{self.path}: unreadable summary ({exc}); scanning",
                          BagDamageWarning, stacklevel=3)
            return None
        if msg_count == 0:
            start = stop = None
        for k, ci in enumerate(sorted(chunk_indexes, key=lambda c: c.offset)):
            ci.number = ci.rank = k + 1
        return Summary(chunk_indexes, counts, msg_count, start, stop)

    def _add_schema(self, cur: Cursor) -> None:
        sid = cur.u16()
        name = cur.string()
        enc = cur.string()
        data = cur.raw(cur.u32())
        if sid:
            self.schemas[sid] = Schema(sid, name, enc, data)

    def _add_channel(self, cur: Cursor) -> None:
        cid = cur.u16()
        sid = cur.u16()
        topic = cur.string()
        enc = cur.string()
        meta = cur.str_map()
        self.channels[cid] = Channel(cid, sid, topic, enc, meta)

    # -- what the summary says -------------------------------------------------------------

    def channels_known(self) -> bool:
        """Whether :attr:`channels` is complete without reading every chunk."""
        return self.summary is not None

    def channel_counts(self) -> dict[int, int] | None:
        """Messages per channel id from the statistics (None: no statistics)."""
        return self.summary.channel_counts if self.summary is not None else None

    def time_bounds(self) -> tuple[int | None, int | None] | None:
        """(first, last) log time from the summary; None if it must be found by reading."""
        s = self.summary
        if s is not None and s.start is not None:
            return s.start, s.end
        if s is not None and s.chunk_indexes:
            return min(c.start for c in s.chunk_indexes), max(c.end for c in s.chunk_indexes)
        if s is not None and s.message_count == 0:
            return None, None
        return None

    # -- chunks ----------------------------------------------------------------------------

    def _parse_records(
        self, buf: bytes, base: int, want: set[int] | None
    ) -> tuple[list[int], list[int], list[int], list[int], list[int], list[int]]:
        """Walk the records of a decompressed chunk (no index): register schemas/channels."""
        chs: list[int] = []
        seqs: list[int] = []
        logs: list[int] = []
        pubs: list[int] = []
        offs: list[int] = []
        lens: list[int] = []
        unpack_rec = REC_HDR.unpack_from
        unpack_msg = MSG_HDR.unpack_from
        pos, n = 0, len(buf)
        while pos < n:
            if pos + 9 > n:
                raise CorruptError(base, f"record header cut at byte {pos} of a chunk")
            op, length = unpack_rec(buf, pos)
            end = pos + 9 + length
            if end > n:
                raise CorruptError(base, f"record at byte {pos} of a chunk runs past its end")
            if op == OP_MESSAGE:
                if length < 22:
                    raise CorruptError(base, f"message record at byte {pos} of a chunk too short")
                ch, seq, lt, pt = unpack_msg(buf, pos + 9)
                if want is None or ch in want:
                    chs.append(ch)
                    seqs.append(seq)
                    logs.append(lt)
                    pubs.append(pt)
                    offs.append(pos + MSG_PREFIX)
                    lens.append(length - 22)
            elif op == OP_SCHEMA:
                self._add_schema(Cursor(buf, pos + 9, end, base))
            elif op == OP_CHANNEL:
                self._add_channel(Cursor(buf, pos + 9, end, base))
            pos = end
        return chs, seqs, logs, pubs, offs, lens

    def _rows_from_records(self, buf: bytes, base: int, want: set[int] | None,
                           start_ns: int) -> Rows:
        chs, seqs, logs, pubs, offs, lens = self._parse_records(buf, base, want)
        return Rows(
            np.frombuffer(buf, np.uint8),
            np.array(chs, np.uint16),
            np.array(seqs, np.uint32),
            np.array(logs, np.uint64).astype(np.int64),
            np.array(pubs, np.uint64).astype(np.int64),
            np.array(offs, np.int64),
            np.array(lens, np.int64),
            start_ns,
        ).sorted()

    def _rows_from_index(self, buf: bytes, ci: ChunkIndex, want: set[int] | None) -> Rows | None:
        """Locate the wanted messages of a chunk through its message index records."""
        chans = [c for c in ci.index_offsets if want is None or c in want]
        arr = np.frombuffer(buf, np.uint8)
        if not chans:
            return Rows.empty(arr, ci.start)
        raw = self._read(ci.offset + ci.length, ci.index_length)
        if len(raw) != ci.index_length:
            return None
        pairs = []
        for c in chans:
            rel = ci.index_offsets[c] - (ci.offset + ci.length)
            if rel < 0 or rel + 15 > len(raw):
                return None
            op, _, cid, n = struct.unpack_from("<BQHI", raw, rel)
            if op != OP_MESSAGE_INDEX or cid != c or rel + 15 + n > len(raw) or n % 16:
                return None
            pairs.append(np.frombuffer(raw, "<u8", n // 8, rel + 15).reshape(-1, 2))
        both = np.concatenate(pairs)
        pos = both[:, 1].astype(np.int64)
        if len(pos) and (pos.min() < 0 or pos.max() + MSG_PREFIX > len(arr)):
            return None
        hdr = windows(arr, pos, MSG_PREFIX).copy().view(MSG_RECORD_DTYPE)[:, 0]
        length = hdr["len"].astype(np.int64) - 22
        # a damaged index (e.g. zeroed entries) must not pass: every entry must name a message
        # record of its channel with the log time indexed
        channel = np.repeat(np.array(chans, np.uint16), [len(p) for p in pairs])
        if np.any(hdr["op"] != OP_MESSAGE) or np.any(length < 0) or \
                np.any(hdr["ch"] != channel) or np.any(hdr["log"] != both[:, 0]):
            return None
        if np.any(pos + MSG_PREFIX + length > len(arr)):
            return None
        return Rows(
            arr,
            hdr["ch"].astype(np.uint16),
            hdr["seq"].astype(np.uint32),
            hdr["log"].astype(np.int64),
            hdr["pub"].astype(np.int64),
            pos + MSG_PREFIX,
            length,
            ci.start,
        ).sorted()

    def read_chunk(self, offset: int, length: int) -> tuple[int, bytes]:
        """Read, decompress and CRC-check the chunk record at ``offset``.

        Returns
        -------
        (int, bytes)
            The chunk's start log time (ns) and its decompressed records.

        Raises
        ------
        CorruptError
            Truncated, not a chunk, decompression or CRC failure.
        """
        raw = self._read(offset, length)
        if len(raw) < length:
            raise CorruptError(offset, f"file ends inside a chunk ({len(raw)} of {length} bytes)")
        if raw[0] != OP_CHUNK:
            raise CorruptError(offset, f"expected a chunk record, found opcode 0x{raw[0]:02x}")
        cur = Cursor(raw, 9, length, offset)
        start, _end, usize, crc = cur.u64(), cur.u64(), cur.u64(), cur.u32()
        compression = cur.string()
        n = cur.u64()
        if cur.pos + n > length:
            raise CorruptError(offset, "chunk records run past the chunk record")
        buf = decompress(compression, raw[cur.pos : cur.pos + n], usize, offset)
        if crc and zlib.crc32(buf) != crc:
            raise CorruptError(offset, "chunk CRC mismatch (corrupt data)")
        return start, buf

    def _chunk_rows(self, ci: ChunkIndex, want: set[int] | None) -> Rows:
        if ci.compression == "loose":
            buf = self._read(ci.offset, ci.length)
            if len(buf) < ci.length:
                raise CorruptError(ci.offset, "file ends inside a message record")
            rows = self._rows_from_records(buf, ci.offset, want, ci.start)
        else:
            _, buf = self.read_chunk(ci.offset, ci.length)
            rows = self._rows_from_index(buf, ci, want) if ci.index_offsets else None
            if rows is None:  # no or inconsistent message index: walk the records
                rows = self._rows_from_records(buf, ci.offset, want, ci.start)
        rows.rank = ci.rank
        return rows

    def _problem(self, ci: ChunkIndex, exc: CorruptError) -> BagProblem:
        topics = None
        if ci.index_offsets:
            topics = tuple(sorted({self.channels[c].topic for c in ci.index_offsets
                                   if c in self.channels}))
        n = len(self.summary.chunk_indexes) if self.summary is not None else None
        return BagProblem(exc.offset, exc.reason, ci.number or None, n, ci.start, ci.end,
                          topics, path=str(self.path))

    def iter_rows(self, want: set[int] | None, on_damage: OnDamage) -> Iterator[Rows]:
        """Yield the messages of the wanted channels chunk by chunk (see :class:`Rows`).

        Chunks come in order of their start time (ties: file order), so every batch's
        ``start_ns`` bounds the log times of the later ones. Each damaged chunk or region is
        passed to ``on_damage``; if it returns, reading goes on with the next valid chunk.

        Parameters
        ----------
        want : set of int or None
            Channel ids to return (None: all).
        on_damage : callable
            See :data:`OnDamage`.
        """
        for ci in self.plan():
            if isinstance(ci, BagProblem):
                on_damage(ci)
                continue
            if want is not None and ci.index_offsets and not (set(ci.index_offsets) & want):
                continue
            try:
                rows = self._chunk_rows(ci, want)
            except CorruptError as exc:
                on_damage(self._problem(ci, exc))
                continue
            yield rows

    def plan(self) -> list[ChunkIndex | BagProblem]:
        """Chunks in reading order (start time, then offset), with the damaged regions.

        From the summary's chunk index when there is one, else from a scan of the record
        headers of the data section (which resynchronises on the next valid chunk after
        damage).
        """
        if self._plan is None:
            s = self.summary
            if s is not None and (s.chunk_indexes or s.message_count == 0):
                entries: list[ChunkIndex | BagProblem] = list(s.chunk_indexes)
            else:
                entries = self._scan_plan()

            def key(e: ChunkIndex | BagProblem) -> tuple[int, int]:
                if isinstance(e, BagProblem):
                    return (e.start_ns if e.start_ns is not None else -1, e.offset)
                return (e.start, e.offset)

            self._plan = sorted(entries, key=key)
        return self._plan

    # -- scanning (no summary) -------------------------------------------------------------

    def _scan_plan(self) -> list[ChunkIndex | BagProblem]:
        """Walk the record headers of the data section; find chunks, loose runs, damage."""
        out: list[ChunkIndex | BagProblem] = []
        pos = self.data_start
        number = 0
        last_end: int | None = None
        loose: ChunkIndex | None = None

        def flush_loose() -> None:
            nonlocal loose
            if loose is not None:
                out.append(loose)
                loose = None

        while True:
            head = self._read(pos, 9)
            reason = None
            if len(head) == 0:
                reason = "file ends without a data-end / footer record (truncated)"
            elif len(head) < 9:
                reason = "file ends inside a record header (truncated)"
            else:
                op, length = REC_HDR.unpack_from(head, 0)
                if op not in DATA_OPS and op < 0x80:
                    reason = f"invalid record opcode 0x{op:02x}"
                elif pos + 9 + length > self.size:
                    reason = f"record (opcode 0x{op:02x}) runs past the end of the file"
            if reason is not None:
                flush_loose()
                nxt = self._resync(pos + 1)
                lost_to = nxt.start if nxt is not None else None
                out.append(BagProblem(pos, reason, None, None, last_end, lost_to, None,
                                      path=str(self.path)))
                if nxt is None:
                    return out
                pos = nxt.offset
                continue
            if op in (OP_DATA_END, OP_FOOTER):
                flush_loose()
                return out
            if op == OP_CHUNK:
                flush_loose()
                ci = chunk_head(self._read(pos, 64), 0, self.size - pos)
                number += 1
                if ci is None:
                    out.append(BagProblem(pos, "unreadable chunk record header", number, None,
                                          last_end, None, None, path=str(self.path)))
                else:
                    ci.offset, ci.number, ci.rank = pos, number, len(out) + 1
                    out.append(ci)
                    last_end = ci.end if last_end is None else max(last_end, ci.end)
            elif op in (OP_SCHEMA, OP_CHANNEL):
                cur = Cursor(self._read(pos + 9, length), 0, length, pos + 9)
                self._add_schema(cur) if op == OP_SCHEMA else self._add_channel(cur)
            elif op == OP_MESSAGE and length >= 22:
                lt = MSG_HDR.unpack_from(self._read(pos + 9, 22), 0)[2]
                if loose is None or loose.length >= LOOSE_BLOCK:
                    flush_loose()
                    loose = ChunkIndex(lt, lt, pos, 0, {}, 0, "loose", 0, 0, 0, len(out) + 1)
                loose.length = pos + 9 + length - loose.offset
                loose.start, loose.end = min(loose.start, lt), max(loose.end, lt)
                last_end = lt if last_end is None else max(last_end, lt)
            elif op != OP_MESSAGE_INDEX:
                flush_loose()
            pos += 9 + length

    def _resync(self, pos: int) -> ChunkIndex | None:
        """The next chunk at or after ``pos`` whose header is sane and whose data validate."""
        step = 1 << 22
        while pos < self.size:
            window = self._read(pos, step + 64)
            k = window.find(bytes([OP_CHUNK]))
            while 0 <= k < step:
                ci = chunk_head(window, k, self.size - pos - k)
                if ci is not None:
                    try:
                        _, buf = self.read_chunk(pos + k, ci.length)
                        self._parse_records(buf, pos + k, set())
                    except (CorruptError, struct.error):
                        pass
                    else:
                        ci.offset = pos + k
                        return ci
                k = window.find(bytes([OP_CHUNK]), k + 1)
            pos += step
        return None

    # -- validation ------------------------------------------------------------------------

    def check(self) -> list[BagProblem]:
        """Validate every chunk (decompression and CRC) and the data section CRC.

        Returns
        -------
        list of BagProblem
            Empty for a healthy file. Damage outside the chunks (message indexes, metadata)
            found by the record walk is reported with ``lost=False`` when a summary says no
            chunk lies there.
        """
        problems: list[BagProblem] = []
        if self.summary_problem is not None:
            problems.append(self.summary_problem)
        chunks: list[ChunkIndex] = []
        for entry in self.plan():
            if isinstance(entry, BagProblem):
                problems.append(entry)
                continue
            try:
                if entry.compression == "loose":
                    self._chunk_rows(entry, set())
                else:
                    self.read_chunk(entry.offset, entry.length)
            except CorruptError as exc:
                problems.append(self._problem(entry, exc))
            else:
                chunks.append(entry)
        if self.summary is not None:
            problems += self._walk_problems(chunks)
        return problems

    def _walk_problems(self, chunks: list[ChunkIndex]) -> list[BagProblem]:
        """Record walk of the data section of a file with a summary; data CRC if present.

        ``chunks`` are the valid chunks; damage inside a damaged chunk or its message
        indexes is not reported again.
        """
        problems: list[BagProblem] = []
        everything = self.summary.chunk_indexes if self.summary is not None else chunks
        damaged = [c for c in everything if c not in chunks]
        pos = self.data_start
        while pos < self.size:
            head = self._read(pos, 9)
            if len(head) < 9:
                break
            op, length = REC_HDR.unpack_from(head, 0)
            if op in DATA_OPS and pos + 9 + length <= self.size:
                if op == OP_DATA_END:
                    problems += self._data_crc_problem(pos, length)
                if op in (OP_DATA_END, OP_FOOTER):
                    return problems
                pos += 9 + length
                continue
            nxt = min((c.offset for c in everything if c.offset > pos), default=None)
            if not any(c.offset <= pos < c.offset + c.length + c.index_length for c in damaged) \
                    and not any(c.offset <= pos < c.offset + c.length for c in chunks):
                problems.append(BagProblem(pos, f"invalid record (opcode 0x{op:02x}) outside the "
                                           "chunks (message index or metadata)", lost=False,
                                           path=str(self.path)))
            if nxt is None:
                break
            pos = nxt
        return problems

    def _data_crc_problem(self, pos: int, length: int) -> list[BagProblem]:
        if length < 4:
            return []
        (crc,) = struct.unpack("<I", self._read(pos + 9, 4))
        if not crc:
            return []
        got = 0
        at = 0
        while at < pos:
            block = self._read(at, min(1 << 24, pos - at))
            got = zlib.crc32(block, got)
            at += len(block)
        if got == crc:
            return []
        return [BagProblem(pos, "data section CRC mismatch", lost=False, path=str(self.path))]

