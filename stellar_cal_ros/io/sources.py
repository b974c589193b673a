"""Where a bag's messages come from: one MCAP file, a rosbag2 directory, a rosbags-read bag.

Every source offers the same small interface to :class:`~stellar_cal_ros.io.reader.BagReader`
(:class:`~stellar_cal_ros.io.source_base.SourceBase`): channels and schemas, counts and time
bounds when the index has them, the messages of chosen channels as
:class:`~stellar_cal_ros.io.mcap_records.Rows` batches in chunk-start order, a generic
decoder, and a damage check. :func:`open_source` picks the source
from what the path is:

- a file starting with the MCAP magic: :class:`McapSource` (this package's parser, fast);
- a rosbag2 directory (``metadata.yaml``) stored as uncompressed MCAP files, or a directory
  of ``.mcap`` files: :class:`MergedSource` of one :class:`McapSource` per file;
- any other rosbag2 directory (sqlite3, compressed files), a ``.db3`` file or a ROS 1 ``.bag``:
  :class:`~stellar_cal_ros.io.rosbags_source.RosbagsSource`.
"""

from __future__ import annotations

import heapq
import os
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from stellar_cal_ros.errors import BagError, no_such_bag, yaml_error_text
from stellar_cal_ros.io.mcap_container import McapFile
from stellar_cal_ros.io.mcap_records import MAGIC, BagProblem, Channel, OnDamage, Rows, Schema
from stellar_cal_ros.io.rosbags_source import ROS1_MAGIC, SQLITE_MAGIC, RosbagsSource
from stellar_cal_ros.io.source_base import SourceBase


class McapSource(McapFile, SourceBase):
    """One MCAP file read by this package's parser (see :class:`McapFile`)."""

    storage = "mcap"

    def __init__(self, path: str | os.PathLike[str]) -> None:
        super().__init__(path)
        self._decoders: dict[int, Callable[[bytes], Any]] = {}

    def decoder(self, cid: int) -> Callable[[bytes], Any]:
        """``mcap_ros2`` decoder of channel ``cid`` (payload bytes -> message object)."""
        dec = self._decoders.get(cid)
        if dec is None:
            from mcap.records import Schema as McapSchema
            from mcap_ros2.decoder import DecoderFactory

            ch = self.channels[cid]
            sch = self.schemas.get(ch.schema_id)
            if sch is None:
                raise BagError(f"channel {ch.topic!r} has no schema; cannot decode")
            made = DecoderFactory().decoder_for(
                ch.message_encoding,
                McapSchema(id=sch.id, name=sch.name, encoding=sch.encoding, data=sch.data),
            )
            if made is None:
                raise BagError(
                    f"no decoder for {ch.topic!r} ({ch.message_encoding}, {sch.encoding})"
                )
            dec = self._decoders[cid] = made
        return dec


class MergedSource(SourceBase):
    """Several sources read as one bag (a split rosbag2 recording).

    Channels of the parts are mapped to common ids by (topic, type, encoding, definition);
    batches are merged by chunk start time (parts whose time ranges do not overlap are read
    one after the other, so only one chunk is held).

    Parameters
    ----------
    parts : list of SourceBase
        The files, e.g. in ``metadata.yaml`` order.
    path : Path
        The directory (for messages).
    storage : str
        Storage label.
    """

    def __init__(self, parts: list[Any], path: Path, storage: str) -> None:
        self.parts = parts
        self.path = path
        self.storage = storage
        self.profile = parts[0].profile
        self.library = parts[0].library
        self.has_summary = all(p.has_summary for p in parts)
        self._ids: dict[tuple[str, str, str, bytes], int] = {}
        self._luts: list[dict[int, int]] = [{} for _ in parts]
        self._channels: dict[int, Channel] = {}
        self._schemas: dict[int, Schema] = {}

    def _refresh(self) -> None:
        for k, part in enumerate(self.parts):
            lut = self._luts[k]
            for cid, ch in part.channels.items():
                if cid in lut:
                    continue
                sch = part.schemas.get(ch.schema_id)
                key = (ch.topic, sch.name if sch else "", ch.message_encoding,
                       sch.data if sch else b"")
                gid = self._ids.setdefault(key, len(self._ids) + 1)
                lut[cid] = gid
                if gid not in self._channels:
                    self._channels[gid] = Channel(gid, gid if sch else 0, ch.topic,
                                                  ch.message_encoding, ch.metadata)
                    if sch is not None:
                        self._schemas[gid] = Schema(gid, sch.name, sch.encoding, sch.data)

    @property
    def channels(self) -> Mapping[int, Channel]:  # type: ignore[override]
        """Common channel ids -> channel records."""
        self._refresh()
        return self._channels

    @property
    def schemas(self) -> Mapping[int, Schema]:  # type: ignore[override]
        """Schemas keyed like the channels' ``schema_id``."""
        self._refresh()
        return self._schemas

    def channels_known(self) -> bool:
        """Whether every part knows its channels without a full read."""
        return all(p.channels_known() for p in self.parts)

    def channel_counts(self) -> dict[int, int] | None:
        """Messages per common channel id (None if a part has no statistics)."""
        self._refresh()
        out: dict[int, int] = {}
        for k, part in enumerate(self.parts):
            counts = part.channel_counts()
            if counts is None:
                return None
            for cid, n in counts.items():
                gid = self._luts[k].get(cid)
                if gid is not None:
                    out[gid] = out.get(gid, 0) + n
        return out

    def time_bounds(self) -> tuple[int | None, int | None] | None:
        """(first, last) log time over the parts (None if a part cannot tell)."""
        bounds = [p.time_bounds() for p in self.parts]
        if any(b is None for b in bounds):
            return None
        lo = [b[0] for b in bounds if b is not None and b[0] is not None]
        hi = [b[1] for b in bounds if b is not None and b[1] is not None]
        return (min(lo) if lo else None, max(hi) if hi else None)

    def _part_rows(self, k: int, want: set[int] | None, on_damage: OnDamage) -> Iterator[Rows]:
        part = self.parts[k]
        local = None
        if want is not None:
            self._refresh()
            local = {c for c, g in self._luts[k].items() if g in want}
            if part.channels_known() and not local:
                return
        for rows in part.iter_rows(local, on_damage):
            self._refresh()
            lut = self._luts[k]
            if len(rows):
                table = np.zeros(int(rows.channel.max()) + 1, np.uint16)
                for c, g in lut.items():
                    if c < len(table):
                        table[c] = g
                rows.channel = table[rows.channel]
            rows.rank = (k << 20) + rows.rank  # file order first (< 2048 files, 2**20 chunks)
            yield rows

    def iter_rows(self, want: set[int] | None, on_damage: OnDamage) -> Iterator[Rows]:
        """Batches of all parts in chunk-start order, channel ids mapped to the common ones."""
        bounds = [p.time_bounds() for p in self.parts]
        order = sorted(range(len(self.parts)),
                       key=lambda k: (bounds[k][0] if bounds[k] and bounds[k][0] is not None
                                      else -1, k))
        group: list[int] = []
        group_end: int | None = None  # None: unknown, every later part may overlap
        for k in order:
            lo, hi = bounds[k] if bounds[k] is not None else (None, None)
            if group and (lo is None or group_end is None or lo <= group_end):
                group.append(k)
                group_end = None if hi is None or group_end is None else max(group_end, hi)
            else:
                yield from self._group_rows(group, want, on_damage)
                group, group_end = [k], hi
        yield from self._group_rows(group, want, on_damage)

    def _group_rows(self, group: list[int], want: set[int] | None,
                    on_damage: OnDamage) -> Iterator[Rows]:
        if len(group) == 1:
            yield from self._part_rows(group[0], want, on_damage)
        elif group:
            its = [self._part_rows(k, want, on_damage) for k in group]
            yield from heapq.merge(*its, key=lambda r: r.start_ns)

    def decoder(self, cid: int) -> Callable[[bytes], Any]:
        """Generic decoder of common channel ``cid`` (that of the first part having it)."""
        self._refresh()
        for k, part in enumerate(self.parts):
            for c, g in self._luts[k].items():
                if g == cid:
                    return part.decoder(c)
        raise BagError(f"no channel {cid} in {self.path}")

    def check(self) -> list[BagProblem]:
        """Problems of every part."""
        return [p for part in self.parts for p in part.check()]

    def close(self) -> None:
        """Close every part."""
        for p in self.parts:
            p.close()


def _rosbag2_files(path: Path) -> tuple[str, list[Path], bool]:
    """(storage id, files, compressed) of a rosbag2 directory."""
    meta = path / "metadata.yaml"
    if not meta.exists():
        files = sorted(path.glob("*.mcap"))
        if files:
            return "mcap", files, False
        dbs = sorted(path.glob("*.db3"))
        if len(dbs) == 1:  # metadata.yaml lost: its one database reads as a bare .db3
            return "sqlite3", dbs, False
        if dbs:
            raise BagError(f"cannot open bag {path}: {len(dbs)} .db3 files and no "
                           "metadata.yaml to join them: give one .db3 file, or restore "
                           "metadata.yaml")
        raise BagError(f"cannot open bag {path}: a directory without metadata.yaml, .mcap or "
                       ".db3 files (not a rosbag2 bag)")
    import yaml

    try:
        info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
        storage = str(info.get("storage_identifier", ""))
        files = [path / f for f in info.get("relative_file_paths", [])]
        mode = str(info.get("compression_mode") or "").lower()
        compressed = bool(info.get("compression_format")) or mode not in ("", "none")
    except (OSError, yaml.YAMLError, KeyError, TypeError) as exc:
        raise BagError(f"{meta}: not a rosbag2 metadata file ({yaml_error_text(exc)})") from exc
    return storage, files, compressed


def open_source(path: Path) -> SourceBase:
    """Open the right source for ``path`` (see the module docstring).

    Raises
    ------
    BagError
        Missing path, unknown format, or an unreadable header / metadata.
    """
    if path.is_dir():
        storage, files, compressed = _rosbag2_files(path)
        if storage == "mcap" and not compressed and files and all(f.exists() for f in files):
            parts: list[Any] = []
            try:
                for f in files:
                    parts.append(McapSource(f))
            except BaseException as exc:
                for p in parts:
                    p.close()
                if isinstance(exc, BagError):
                    raise BagError(f"cannot open bag {path}: {exc}") from exc
                raise
            if len(parts) == 1:
                parts[0].storage = "rosbag2-mcap"
                return parts[0]
            return MergedSource(parts, path, "rosbag2-mcap")
        if storage == "sqlite3" and files and not (path / "metadata.yaml").exists():
            return RosbagsSource(files[0], "rosbag2-sqlite3")
        return RosbagsSource(path, f"rosbag2-{storage or 'unknown'}")
    try:
        with open(path, "rb") as fh:
            head = fh.read(16)
    except FileNotFoundError as exc:
        raise no_such_bag(path) from exc
    except OSError as exc:
        raise BagError(f"cannot open bag {path}: {exc}") from exc
    if head.startswith(ROS1_MAGIC) or head.startswith(SQLITE_MAGIC):
        kind = "rosbag1" if head.startswith(ROS1_MAGIC) else "rosbag2-sqlite3"
        return RosbagsSource(path, kind)
    if path.suffix == ".bag" and not head.startswith(MAGIC):
        raise BagError(f"{path} is not a ROS 1 bag (no '#ROSBAG V2.0' magic)")
    return McapSource(path)
