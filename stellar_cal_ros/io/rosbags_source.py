"""Bags read through the ``rosbags`` library: rosbag2 sqlite3 (or compressed) and ROS 1.

``rosbags`` supplies the raw messages in log-time order; they are gathered into
:class:`~stellar_cal_ros.io.mcap_records.Rows` batches so the same bulk CDR decoders as for
MCAP apply, and the results are identical. ROS 1 payloads are converted to CDR first with the
bag's own definitions (``std_msgs/Header`` without ``seq``, as ``rosbags-convert`` does).
The ``stellar_cal_msgs`` types are registered from this package's schema texts when a bag
carries no definitions.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from stellar_cal_ros.errors import BagError
from stellar_cal_ros.io.mcap_records import BagProblem, Channel, OnDamage, Rows, Schema
from stellar_cal_ros.io.schemas import SCHEMA_TEXTS
from stellar_cal_ros.io.source_base import SourceBase

_BATCH_MESSAGES = 4096
_BATCH_BYTES = 4 << 20

# ROS 1 -> CDR without rosbags' generic converter for the high-rate contract types: a
# std_msgs/Header followed by fixed fields, given as runs of (ROS 1 bytes, CDR alignment of
# the run's first field; the others follow aligned).
_ROS1_TAILS: dict[str, list[tuple[int, int]]] = {
    "sensor_msgs/msg/Imu": [(37 * 8, 8)],
    "sensor_msgs/msg/Temperature": [(2 * 8, 8)],
    "sensor_msgs/msg/FluidPressure": [(2 * 8, 8)],
    "sensor_msgs/msg/NavSatFix": [(1, 1), (2, 2), (12 * 8, 8), (1, 1)],
}


def _ros1_header_to_cdr(raw: bytes, tail: list[tuple[int, int]]) -> bytes | None:
    """CDR of a ROS 1 ``Header`` + fixed-field message, None if ``raw`` does not fit.

    ROS 1: ``uint32 seq, uint32 sec, uint32 nsec, uint32 n, n chars``, then the fields
    packed. CDR: encapsulation, ``sec, nsec, n + 1, chars, NUL``, then each field aligned to
    its alignment relative to the byte after the encapsulation.
    """
    if len(raw) < 16:
        return None
    n = int.from_bytes(raw[12:16], "little")
    if len(raw) != 16 + n + sum(size for size, _ in tail):
        return None
    out = bytearray(b"\x00\x01\x00\x00")
    out += raw[4:12]
    out += (n + 1).to_bytes(4, "little")
    out += raw[16 : 16 + n]
    out += b"\x00"
    pos = 16 + n
    for size, alignment in tail:
        out += bytes(-(len(out) - 4) % alignment)
        out += raw[pos : pos + size]
        pos += size
    return bytes(out)


def contract_types(base: Any = None, ros2_header: bool = False) -> dict[str, Any]:
    """ROS 2 Jazzy's type definitions, the contract types' and ``base``'s (not built).

    Parameters
    ----------
    base : rosbags Typestore, optional
        Types to add (they win over Jazzy's and the contract ones).
    ros2_header : bool
        Use ROS 2's ``std_msgs/Header`` (no ``seq``) even if ``base`` has ROS 1's, so that
        ``ros1_to_cdr`` gives ROS 2 CDR.
    """
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    jazzy = get_typestore(Stores.ROS2_JAZZY).fielddefs
    types: dict[str, Any] = dict(jazzy)
    for name, text in SCHEMA_TEXTS.items():
        for k, v in get_types_from_msg(text, name).items():
            types.setdefault(k, v)
    if base is not None:
        types.update(base.fielddefs)
    if ros2_header:
        types["std_msgs/msg/Header"] = jazzy["std_msgs/msg/Header"]
    return types


def contract_typestore(base: Any = None, ros2_header: bool = False) -> Any:
    """A rosbags typestore built from :func:`contract_types` (its arguments).

    Building one (rosbags generates and compiles a class per type) costs ~0.08 CPU-s.
    """
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.EMPTY)
    store.register(contract_types(base, ros2_header))
    return store


def _unbuilt_contract_typestore() -> Any:
    """A typestore that holds :func:`contract_types` as definitions only, none built.

    ``AnyReader`` reads its default typestore's definitions alone (for a bag that carries
    none) and builds its own store from them: the contract store built for it was built
    again per open (H284: ~0.08 CPU-s an open).
    """
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.EMPTY)
    store.fielddefs.update(contract_types())
    return store


ROS1_MAGIC = b"#ROSBAG V2.0\n"


def ros1_reindex_text(path: Path, why: str) -> str:
    """The one line for a ROS 1 bag whose index cannot be read (``why``: what shows it)."""
    return (f"{path}: a ROS 1 bag without a readable index (cut short or not closed: the "
            f"index is written last; {why}); rebuild it with `rosbag reindex {path}` (ROS 1) "
            "and give the reindexed bag")


def ros1_unindexed_text(path: Path) -> str:
    """:func:`ros1_reindex_text` for a ROS 1 bag whose header shows no index in the file.

    '' if ``path``'s header puts the index inside the file, or is not a ROS 1 bag header
    (rosbags then says what it finds).  The bag header record follows the magic line:
    its length, then ``len name=value`` fields, ``index_pos`` a little-endian uint64, 0
    until the recorder closes the bag; a bag cut short lost the index (written last) with
    its end.  Read before rosbags' imports and typestore (H284: a refusal 0.58 -> 0.32
    CPU-s for info, 0.84 -> 0.57 for replay).
    """
    with path.open("rb") as f:
        head = f.read(4096)
        size = os.fstat(f.fileno()).st_size
    if not head.startswith(ROS1_MAGIC) or len(head) < len(ROS1_MAGIC) + 4:
        return ""
    pos = len(ROS1_MAGIC) + 4
    end = pos + int.from_bytes(head[pos - 4 : pos], "little")
    fields = {}
    while pos + 4 <= min(end, len(head)):
        n = int.from_bytes(head[pos : pos + 4], "little")
        name, _, value = head[pos + 4 : pos + 4 + n].partition(b"=")
        fields[name] = value
        pos += 4 + n
    index = fields.get(b"index_pos", b"")
    if fields.get(b"op") != b"\x03" or len(index) != 8:
        return ""
    index_pos = int.from_bytes(index, "little")
    if index_pos == 0:
        return ros1_reindex_text(path, "its header holds no index position: the recording "
                                       "was not closed")
    if index_pos >= size:
        return ros1_reindex_text(path, f"its header puts the index at byte {index_pos}, "
                                       f"past the file's {size} bytes")
    return ""


SQLITE_MAGIC = b"SQLite format 3\0"


def sqlite_cut_text(path: Path) -> str:
    """The one line for a rosbag2 sqlite3 database cut short ('' if none of ``path``'s is).

    ``path``: a ``.db3`` file or a rosbag2 directory.  A database's header counts its pages
    (bytes 28-31, valid when bytes 92-95 repeat the change counter of bytes 24-27); a file
    shorter than that lost its end: sqlite then refuses even the table list ("database disk
    image is malformed"; its shell's ``.recover`` too), and rosbags opens a database by
    counting every message, so no part is read (``--on-error skip`` neither).  Measured on a
    converted sweep bag cut at half: with the size taken from the file (``writable_schema``)
    none of its 6304 messages could be looked up, the table's inner pages being written late.
    """
    files = [path] if path.is_file() else sorted(path.glob("*.db3"))
    for db in files:
        with db.open("rb") as f:
            head = f.read(100)
        if len(head) < 100 or not head.startswith(SQLITE_MAGIC) or head[24:28] != head[92:96]:
            continue
        page = int.from_bytes(head[16:18], "big")
        need = (65536 if page == 1 else page) * int.from_bytes(head[28:32], "big")
        size = db.stat().st_size
        if size < need:
            return (f"{db}: a rosbag2 sqlite3 database cut short: {size} of the {need} bytes "
                    "its header counts (a copy or download that stopped, a full disk); "
                    "sqlite refuses such a file and nothing here reads a part of it (nor "
                    "`--on-error skip`): copy the whole file again from where it was recorded")
    return ""


class RosbagsSource(SourceBase):
    """A bag read by ``rosbags.highlevel.AnyReader`` (see the module docstring).

    Parameters
    ----------
    path : Path
        A rosbag2 directory, a ``.db3`` file or a ROS 1 ``.bag`` file.
    storage : str
        ``rosbag1`` or ``rosbag2-<storage id>``.

    Raises
    ------
    BagError
        ``rosbags`` cannot open the bag.
    """

    profile = "ros2"
    library = "rosbags"

    def __init__(self, path: Path, storage: str) -> None:
        cut = (sqlite_cut_text(path) if storage == "rosbag2-sqlite3" else
               ros1_unindexed_text(path) if storage == "rosbag1" else "")
        if cut:  # (said from the header, before rosbags' imports)
            raise BagError(cut)
        from rosbags.highlevel import AnyReader, AnyReaderError

        self.path = path
        self.storage = storage
        self.profile = "ros1" if storage == "rosbag1" else "ros2"
        try:
            self._reader = AnyReader([path], default_typestore=_unbuilt_contract_typestore())
            self._reader.open()
        except (AnyReaderError, OSError, ValueError, KeyError) as exc:
            if storage == "rosbag1" and "index" in str(exc).lower():
                # a recording cut short or never closed (``.bag.active``): ROS 1 writes the
                # index last, and rosbags reads indexed bags only (no reindex of its own)
                raise BagError(ros1_reindex_text(path, f"rosbags: {exc}")) from exc
            raise BagError(f"cannot open bag {path} ({storage}) with rosbags: {exc}") from exc
        self._ros1 = not self._reader.is2
        self._types = contract_typestore(self._reader.typestore, ros2_header=self._ros1)
        self._conn: dict[int, Any] = {}
        self._channels: dict[int, Channel] = {}
        self._schemas: dict[int, Schema] = {}
        for cid, conn in enumerate(self._reader.connections, start=1):
            self._conn[cid] = conn
            self._channels[cid] = Channel(cid, cid, conn.topic, "cdr", {})
            fmt = "ros1msg" if self._ros1 else "ros2msg"
            self._schemas[cid] = Schema(cid, conn.msgtype, fmt, conn.msgdef.data.encode())

    @property
    def channels(self) -> Mapping[int, Channel]:  # type: ignore[override]
        """Channel records, one per rosbags connection."""
        return self._channels

    @property
    def schemas(self) -> Mapping[int, Schema]:  # type: ignore[override]
        """Schema records (the connection's type and definition text)."""
        return self._schemas

    def channels_known(self) -> bool:
        """Always True: the bag's index lists its connections."""
        return True

    def channel_counts(self) -> dict[int, int]:
        """Messages per channel from the bag's index."""
        return {cid: int(c.msgcount) for cid, c in self._conn.items()}

    def time_bounds(self) -> tuple[int | None, int | None]:
        """(first, last) log time; rosbags' end time is one past the last message."""
        if not self._reader.message_count:
            return None, None
        return int(self._reader.start_time), int(self._reader.end_time) - 1

    def _to_cdr(self, cid: int) -> Callable[[bytes], bytes | memoryview]:
        if not self._ros1:
            return lambda raw: raw
        msgtype = self._conn[cid].msgtype
        convert = self._types.ros1_to_cdr
        fast = _ROS1_TAILS.get(msgtype)

        def to_cdr(raw: bytes) -> bytes | memoryview:
            if fast is not None:
                out = _ros1_header_to_cdr(raw, fast)
                if out is not None:
                    return out
            try:
                return convert(raw, msgtype)
            except Exception:  # noqa: BLE001 -- reported by the CDR decoder as malformed
                return b""

        return to_cdr

    def iter_rows(self, want: set[int] | None, on_damage: OnDamage) -> Iterator[Rows]:
        """Batches of the wanted channels' messages in log-time order (CDR payloads)."""
        cids = sorted(self._conn if want is None else (c for c in want if c in self._conn))
        if not cids:
            return
        ids = {id(self._conn[c]): c for c in cids}
        conv = {c: self._to_cdr(c) for c in cids}
        parts: list[bytes | memoryview] = []
        chan: list[int] = []
        log: list[int] = []
        size = 0
        last = None
        rank = 0
        try:
            for conn, t, raw in self._reader.messages(connections=[self._conn[c] for c in cids]):
                cid = ids[id(conn)]
                payload = conv[cid](raw)
                parts.append(payload)
                chan.append(cid)
                log.append(t)
                size += len(payload)
                last = t
                if len(chan) >= _BATCH_MESSAGES or size >= _BATCH_BYTES:
                    yield _batch(parts, chan, log, rank := rank + 1)
                    parts, chan, log, size = [], [], [], 0
        except Exception as exc:  # rosbags raises assorted errors on damaged files
            if parts:
                yield _batch(parts, chan, log, rank := rank + 1)
                parts = []
            on_damage(BagProblem(0, f"rosbags cannot read on ({type(exc).__name__}: {exc})",
                                 start_ns=last, path=str(self.path)))
        if parts:
            yield _batch(parts, chan, log, rank := rank + 1)

    def decoder(self, cid: int) -> Callable[[bytes], Any]:
        """The ``rosbags`` decoder of channel ``cid``'s payloads as iter_rows gives them (CDR)."""
        msgtype = self._conn[cid].msgtype
        return lambda raw: self._types.deserialize_cdr(raw, msgtype)

    def check(self) -> list[BagProblem]:
        """Read every message once; a failure is reported as one problem."""
        problems: list[BagProblem] = []
        for _ in self.iter_rows(None, problems.append):
            pass
        return problems

    def close(self) -> None:
        """Close the rosbags reader."""
        self._reader.close()


def _batch(parts: list[bytes | memoryview], chan: list[int], log: list[int], rank: int) -> Rows:
    lengths = np.fromiter((len(p) for p in parts), np.int64, len(parts))
    offsets = np.zeros(len(parts), np.int64)
    np.cumsum(lengths[:-1], out=offsets[1:])
    buf = np.frombuffer(b"".join(parts), np.uint8)
    logs = np.array(log, np.int64)
    n = len(parts)
    return Rows(buf, np.array(chan, np.uint16), np.zeros(n, np.uint32), logs, logs.copy(),
                offsets, lengths, int(logs.min()), rank).sorted()

