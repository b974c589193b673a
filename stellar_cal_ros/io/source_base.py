"""The interface every bag source offers :class:`~stellar_cal_ros.io.reader.BagReader`.

The sources themselves: :mod:`~stellar_cal_ros.io.sources` (MCAP files, rosbag2 directories
of them) and :mod:`~stellar_cal_ros.io.rosbags_source` (anything the ``rosbags`` library
reads).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from typing import Any

from stellar_cal_ros.io.mcap_records import BagProblem, Channel, OnDamage, Rows, Schema
from stellar_cal_ros.io.schemas import normalize_type


class SourceBase:
    """What every source has: channel and schema records and the lookups built on them.

    Subclasses fill :attr:`channels` and :attr:`schemas` (a channel's ``schema_id`` keys
    :attr:`schemas`) and implement the reading methods documented on :class:`McapSource`.
    """

    storage = ""
    profile = ""
    library = ""
    has_summary = True
    channels: Mapping[int, Channel]
    schemas: Mapping[int, Schema]

    def schema(self, cid: int) -> tuple[str, str] | None:
        """(schema name, definition text) of channel ``cid``, if it has a schema."""
        ch = self.channels.get(cid)
        sch = self.schemas.get(ch.schema_id) if ch else None
        if sch is None:
            return None
        return sch.name, sch.data.decode("utf-8", errors="replace")

    def schema_name(self, cid: int) -> str:
        """Schema name of channel ``cid`` (``"?"`` if unknown)."""
        found = self.schema(cid)
        return found[0] if found else "?"

    def normalized_type(self, cid: int) -> str:
        """Message type of channel ``cid`` as ``pkg/msg/Type`` (``""`` if unknown)."""
        found = self.schema(cid)
        return normalize_type(found[0]) if found else ""

    def start_hint(self) -> int | None:
        """The first log time if known without reading (for relative times in messages)."""
        bounds = self.time_bounds()
        return bounds[0] if bounds else None

    # the reading interface (implemented by every source)

    def time_bounds(self) -> tuple[int | None, int | None] | None:  # pragma: no cover
        """(first, last) log time, ns, from the index; None if only a full read can tell."""
        raise NotImplementedError

    def channels_known(self) -> bool:  # pragma: no cover
        """Whether :attr:`channels` is complete without reading every message."""
        raise NotImplementedError

    def channel_counts(self) -> dict[int, int] | None:  # pragma: no cover
        """Messages per channel id from the index (None: only a full read can tell)."""
        raise NotImplementedError

    def iter_rows(self, want: set[int] | None, on_damage: OnDamage) -> Iterator[Rows]:
        """Batches of the wanted channels (None: all) in chunk-start order.

        Each batch's ``start_ns`` bounds the log times of it and every later batch from
        below. Damage is passed to ``on_damage``; reading goes on if it returns.
        """
        raise NotImplementedError  # pragma: no cover

    def decoder(self, cid: int) -> Callable[[bytes], Any]:  # pragma: no cover
        """Generic decoder of channel ``cid``: payload bytes -> message object."""
        raise NotImplementedError

    def check(self) -> list[BagProblem]:  # pragma: no cover
        """Validate the whole bag; one problem per damaged part."""
        raise NotImplementedError

    def close(self) -> None:  # pragma: no cover
        """Release the files."""
        raise NotImplementedError
