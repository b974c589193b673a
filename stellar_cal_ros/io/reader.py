"""Reading the contract topics of a bag: bulk numpy decoding, one pass, log-time order.

:class:`BagReader` opens a single ``.mcap`` file (its own container parser, the fast path), a
rosbag2 directory (``metadata.yaml``; MCAP files through the same fast path, sqlite3 storage
through ``rosbags``) or a ROS 1 ``.bag`` (through ``rosbags``), and offers the same API for all:
:meth:`~BagReader.topics`, the time bounds, ``read_*`` per topic, :meth:`~BagReader.stream`
(every topic interleaved in one pass; star images too, a chunk at a time),
:meth:`~BagReader.iter_messages` (any type, decoded
generically) and :meth:`~BagReader.check` (damage report).
"""

from __future__ import annotations

import os
import struct
import warnings
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from stellar_cal_ros.core.types import (
    ImuSeries,
    NavSatSeries,
    ScalarSeries,
    StarFrame,
    TopicInfo,
)
from stellar_cal_ros.errors import BagDamageWarning, BagError, MessageDecodeError
from stellar_cal_ros.io import kinds
from stellar_cal_ros.io.image_msgs import CameraInfoMessage, ImageMessage
from stellar_cal_ros.io.mcap_records import BagProblem, CorruptError, Rows
from stellar_cal_ros.io.merge import Fields, concat, interleaved, releases, time_ordered
from stellar_cal_ros.io.source_base import SourceBase
from stellar_cal_ros.io.sources import open_source

__all__ = ["DEFAULT_TOPICS", "BagReader", "OnError"]

OnError = Literal["raise", "skip"]

DEFAULT_TOPICS: dict[str, str] = {
    "imu": "/imu/data",
    "stars": "/star_tracker/stars",
    "fix": "/gnss/fix",
    "head": "/star_tracker/temperature",
    "air": "/environment/temperature",
    "pressure": "/environment/pressure",
}
"""Role -> topic of the contract bag, the default of :meth:`BagReader.stream`."""


class _DamageError(CorruptError):
    """A damaged part met while reading in strict mode."""

    def __init__(self, problem: BagProblem) -> None:
        super().__init__(problem.offset, problem.reason)
        self.problem = problem


class BagReader:
    """Reader of a bag: one ``.mcap``, a rosbag2 directory or a ROS 1 ``.bag``.

    An MCAP file is read chunk by chunk (memory stays at a few chunks whatever the file
    size) and the IMU, GNSS and scalar topics are decoded a whole chunk at a time with numpy.

    Parameters
    ----------
    path : str or Path
        A ``.mcap`` file, a rosbag2 directory (MCAP or sqlite3 storage, split files), a
        rosbag2 ``.db3`` file or a ROS 1 ``.bag`` file.
    on_error : {"raise", "skip"}
        ``"raise"``: a malformed message raises :class:`MessageDecodeError`, a truncated or
        corrupt container raises :class:`BagError`. ``"skip"``: malformed messages are
        dropped and counted in :attr:`skipped`; a damaged chunk is skipped with a
        :class:`UserWarning` naming the time range and topics lost, and reading goes on with
        the next valid chunk (listed in :attr:`problems`).

    Attributes
    ----------
    skipped : dict of str to int
        Malformed messages dropped per topic (skip mode), cumulative over calls.
    truncated : bool
        True once a read ran into a truncated or corrupt part of the file (skip mode).
    problems : list of BagProblem
        The damaged parts met while reading (skip mode), each once.
    has_summary : bool
        Whether the bag has a usable index (MCAP summary; always True for rosbags formats).
    profile, library : str
        From the MCAP header record (``ros2`` / ``rosbags`` for the other formats).
    storage : str
        ``mcap``, ``rosbag2-mcap``, ``rosbag2-sqlite3`` or ``rosbag1``.

    Raises
    ------
    BagError
        The bag is missing, of an unknown format, or its header cannot be read.

    Examples
    --------
    >>> with BagReader("run.mcap") as bag:  # doctest: +SKIP
    ...     imu = bag.read_imu()
    ...     frames = bag.read_star_frames()
    """

    def __init__(self, path: str | os.PathLike[str], on_error: OnError = "raise") -> None:
        if on_error not in ("raise", "skip"):
            raise ValueError(f"on_error must be 'raise' or 'skip', got {on_error!r}")
        self.path = Path(path)
        self.on_error: OnError = on_error
        self.skipped: dict[str, int] = {}
        self.truncated = False
        self.problems: list[BagProblem] = []
        self._scan_cache: tuple[dict[int, int], int | None, int | None] | None = None
        self._src: SourceBase = open_source(self.path)
        self.storage: str = self._src.storage
        self.profile: str = self._src.profile
        self.library: str = self._src.library
        self.has_summary: bool = self._src.has_summary

    def __enter__(self) -> BagReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the bag."""
        self._src.close()

    # -- error policy ----------------------------------------------------------------------

    def _rows(self, want: set[int] | None, what: str) -> Iterator[Rows]:
        """The source's batches, damage handled by ``on_error`` (see the class docstring)."""
        n = 0
        last: int | None = None
        again: list[BagProblem] = []

        def on_damage(problem: BagProblem) -> None:
            if self.on_error == "raise":
                raise _DamageError(problem)
            self.truncated = True
            if problem in self.problems:
                again.append(problem)  # described once per reader, counted at each read
                return
            self.problems.append(problem)
            warnings.warn(
                f"truncated or corrupt bag {problem.path} at byte {problem.offset} "
                f"(while reading {what}): {problem.describe(self._src.start_hint())}; "
                "skipped, reading goes on with the next valid chunk",
                BagDamageWarning, stacklevel=5,
            )

        try:
            for rows in self._src.iter_rows(want, on_damage):
                n += 1
                if len(rows):
                    last = int(rows.log_time.max()) if last is None else \
                        max(last, int(rows.log_time.max()))
                yield rows
            if again:
                warnings.warn(f"truncated or corrupt bag {self.path}: {len(again)} damaged "
                              f"part(s) skipped again while reading {what} (described above)",
                              BagDamageWarning, stacklevel=4)
        except (CorruptError, struct.error, OSError) as exc:
            off = getattr(exc, "offset", None)
            where = f"{self.path} at byte {off}" if off is not None else str(self.path)
            reason = getattr(exc, "reason", str(exc))
            if isinstance(exc, _DamageError):
                where = f"{exc.problem.path} at byte {exc.offset}"
                reason = exc.problem.describe(self._src.start_hint())
            t = f", last message log time {last * 1e-9:.9f} s" if last is not None else ""
            msg = (f"truncated or corrupt bag {where}: {reason} "
                   f"(while reading {what}; {n} chunks read before{t})")
            if self.on_error == "raise":
                raise BagError(msg) from exc
            self.truncated = True
            warnings.warn(msg + "; returning what could be read", BagDamageWarning,
                          stacklevel=4)

    def _bad(self, topic: str, log_time: int, reason: str, counter: dict[str, list[Any]]) -> None:
        """Handle one malformed message according to ``on_error``."""
        if self.on_error == "raise":
            raise MessageDecodeError(topic, int(log_time), reason)
        self.skipped[topic] = self.skipped.get(topic, 0) + 1
        entry = counter.setdefault(topic, [0, int(log_time), reason])
        entry[0] += 1

    @staticmethod
    def _report_skipped(counter: dict[str, list[Any]]) -> None:
        for topic, (n, t, reason) in counter.items():
            warnings.warn(
                f"skipped {n} malformed message(s) on {topic} (first at t={t * 1e-9:.9f} s: "
                f"{reason})",
                BagDamageWarning, stacklevel=4,
            )

    # -- topics and times ------------------------------------------------------------------

    def _scan_counts(self) -> tuple[dict[int, int], int | None, int | None]:
        if self._scan_cache is None:
            counts: dict[int, int] = {}
            lo: int | None = None
            hi: int | None = None
            for rows in self._rows(None, "the whole file (scan)"):
                ch, c = np.unique(rows.channel, return_counts=True)
                for a, b in zip(ch.tolist(), c.tolist(), strict=True):
                    counts[a] = counts.get(a, 0) + b
                if len(rows):
                    lo = min(lo, int(rows.log_time[0])) if lo is not None else int(rows.log_time[0])
                    hi = max(hi or 0, int(rows.log_time.max()))
            self._scan_cache = (counts, lo, hi)
        return self._scan_cache

    def _channels(self) -> Mapping[int, Any]:
        if not self._src.channels_known():
            self._scan_counts()  # channels only appear while reading the chunks
        return self._src.channels

    def topics(self) -> dict[str, TopicInfo]:
        """Topics with their message type and count.

        Returns
        -------
        dict of str to TopicInfo
            From the bag's index; for an MCAP file without summary (truncated), from a scan
            of the readable part, with a :class:`UserWarning`.
        """
        counts = self._src.channel_counts()
        if counts is None:
            # scan first: where the scan itself stops at the damage (on_error="raise"), the
            # error is the one line the user reads, not a warning and then the error
            counts = self._scan_counts()[0]
            warnings.warn(
                f"{self.path} has no summary/statistics (truncated or not closed?); counted "
                "the messages with a full scan",
                BagDamageWarning, stacklevel=2,
            )
        out: dict[str, TopicInfo] = {}
        for cid, ch in sorted(self._channels().items()):
            name = self._src.schema_name(cid)
            n = int(counts.get(cid, 0))
            if ch.topic in out:
                prev = out[ch.topic]
                names = prev.schema_name.split("|")
                if name not in names:
                    names.append(name)
                out[ch.topic] = TopicInfo("|".join(names), prev.message_count + n)
            else:
                out[ch.topic] = TopicInfo(name, n)
        return out

    def _time_bounds(self) -> tuple[int | None, int | None]:
        bounds = self._src.time_bounds()
        if bounds is not None:
            return bounds
        _, lo, hi = self._scan_counts()
        return lo, hi

    @property
    def start_ns(self) -> int | None:
        """Earliest message log time, ns (None for an empty bag)."""
        return self._time_bounds()[0]

    @property
    def end_ns(self) -> int | None:
        """Latest message log time, ns (None for an empty bag)."""
        return self._time_bounds()[1]

    @property
    def duration_s(self) -> float:
        """``end_ns - start_ns`` in s (0 for an empty bag)."""
        lo, hi = self._time_bounds()
        return 0.0 if lo is None or hi is None else (hi - lo) * 1e-9

    def losses(self, start_ns: int | None = None) -> dict[str, Any]:
        """What the reads so far passed over (skip mode; empty: nothing was lost).

        The one record of a read past damage that every command writes (a result file's,
        a diagnosis's ``data_quality`` block, doc/interfaces.md §3): ``bag_parts_lost``
        (damaged or truncated parts read past), ``messages_skipped`` (malformed messages
        dropped) and ``parts_lost``, each part's one line (where, the log time lost after
        ``start_ns`` when known, the topics).
        """
        skipped = int(sum(self.skipped.values()))
        lost = len(self.problems) or int(self.truncated)
        if not skipped and not lost:
            return {}
        return {"bag_parts_lost": int(lost), "messages_skipped": skipped,
                "parts_lost": [p.describe(start_ns) for p in self.problems]}

    def check(self) -> list[BagProblem]:
        """Validate the whole bag (every chunk's decompression and CRC, data CRC).

        Returns
        -------
        list of BagProblem
            One per damaged part (empty for a healthy bag); ``describe()`` gives one line.
        """
        return self._src.check()

    # -- channel selection and decoding ----------------------------------------------------

    def _topic_channels(self, topic: str, expected: Sequence[str],
                        missing_ok: bool = False) -> tuple[set[int], set[int]]:
        """Channel ids of ``topic``: (with an expected schema, with another schema)."""
        channels = self._channels()
        good: set[int] = set()
        other: set[int] = set()
        for cid, ch in channels.items():
            if ch.topic != topic:
                continue
            if self._src.normalized_type(cid) in expected and ch.message_encoding == "cdr":
                good.add(cid)
            else:
                other.add(cid)
        if not good and not other and not missing_ok:
            names = sorted({c.topic for c in channels.values()})
            raise BagError(f"topic {topic!r} not in {self.path}; topics: {names}")
        if not good and other and self.on_error == "raise":
            found = {self._src.schema_name(c) for c in other}
            raise BagError(
                f"topic {topic!r} in {self.path} has type {sorted(found)}, expected "
                f"{' or '.join(expected)}"
            )
        return good, other

    def _decoder(self, topic: str, kind: str, missing_ok: bool = False) -> kinds.TopicDecoder:
        good, other = self._topic_channels(topic, kinds.EXPECTED[kind], missing_ok)
        return kinds.TopicDecoder(topic, kind, good, other, self._src.schema_name)

    def _decoded(
        self, decoders: Sequence[kinds.TopicDecoder], counter: dict[str, list[Any]], what: str
    ) -> Iterator[tuple[int, list[Fields | None]]]:
        """One pass: per chunk, the decoded rows of every decoder (bad rows handled)."""
        want: set[int] = set()
        for d in decoders:
            want |= d.good | d.other
        for rows in self._rows(want, what):
            out: list[Fields | None] = []
            for d in decoders:
                fields, errors = d.decode(rows)
                for t, reason in errors:
                    self._bad(d.topic, t, reason, counter)
                out.append(fields)
            yield rows.start_ns, out

    def _read_topic(self, topic: str, kind: str) -> tuple[list[Fields], kinds.TopicDecoder]:
        counter: dict[str, list[Any]] = {}
        dec = self._decoder(topic, kind)
        batches = ((s, f[0]) for s, f in self._decoded([dec], counter, topic) if f[0] is not None)
        parts = list(time_ordered(batches))
        self._report_skipped(counter)
        return parts, dec

    # -- typed reads -----------------------------------------------------------------------

    def iter_imu_blocks(
        self, topic: str = "/imu/data", block_size: int = 100_000
    ) -> Iterator[ImuSeries]:
        """Stream ``sensor_msgs/msg/Imu`` in blocks of ``block_size`` samples, log-time order.

        Parameters
        ----------
        topic : str
            IMU topic.
        block_size : int
            Samples per yielded block (the last one may be shorter).

        Yields
        ------
        ImuSeries
            Consecutive blocks; together they equal :meth:`read_imu`.

        Raises
        ------
        BagError
            Topic missing / of another type, or truncated file (strict mode).
        MessageDecodeError
            A malformed IMU message (strict mode).
        """
        if block_size < 1:
            raise ValueError("block_size must be >= 1")
        counter: dict[str, list[Any]] = {}
        dec = self._decoder(topic, "imu")
        batches = ((s, f[0]) for s, f in self._decoded([dec], counter, topic) if f[0] is not None)
        buf: list[Fields] = []
        n_buf = 0
        yielded = False
        for d in time_ordered(batches):
            buf.append(d)
            n_buf += len(d["log"])
            while n_buf >= block_size:
                cat = concat(buf)
                yield dec.build({k: v[:block_size] for k, v in cat.items()})
                yielded = True
                buf = [{k: v[block_size:] for k, v in cat.items()}]
                n_buf -= block_size
        if n_buf or not yielded:
            yield dec.build(concat(buf) if buf else None)
        dec.warn_frames()
        self._report_skipped(counter)

    def read_imu(self, topic: str = "/imu/data") -> ImuSeries:
        """Read all ``sensor_msgs/msg/Imu`` messages of ``topic`` (bulk numpy decode).

        Parameters
        ----------
        topic : str
            IMU topic.

        Returns
        -------
        ImuSeries
            All samples in log-time order; ``angular_velocity`` rad/s (N, 3),
            ``linear_acceleration`` m/s^2 (N, 3), ``stamp_ns`` from ``header.stamp``.

        Raises
        ------
        BagError
            Topic missing / of another type, or truncated file (strict mode).
        MessageDecodeError
            A malformed IMU message (strict mode).
        """
        parts, dec = self._read_topic(topic, "imu")
        dec.warn_frames()
        return dec.build(concat(parts) if parts else None)

    def iter_star_frames(self, topic: str = "/star_tracker/stars") -> Iterator[StarFrame]:
        """Stream ``stellar_cal_msgs/msg/StarCentroidArray`` messages in log-time order.

        Parameters
        ----------
        topic : str
            Star centroid topic.

        Yields
        ------
        StarFrame
            One per message, ``log_time_ns`` filled.

        Raises
        ------
        BagError
            Topic missing / of another type, or truncated file (strict mode).
        MessageDecodeError
            A malformed message (strict mode).
        """
        yield from self._iter_objects(topic, "stars")

    def _iter_objects(self, topic: str, kind: str) -> Iterator[Any]:
        """The messages of a per-message kind (:data:`kinds.PER_MESSAGE`), log-time order."""
        counter: dict[str, list[Any]] = {}
        dec = self._decoder(topic, kind)
        batches = ((s, f[0]) for s, f in self._decoded([dec], counter, topic) if f[0] is not None)
        for d in time_ordered(batches):
            yield from d["obj"]
        self._report_skipped(counter)

    def iter_images(self, topic: str = "/star_tracker/image") -> Iterator[ImageMessage]:
        """Stream ``sensor_msgs/msg/Image`` messages in log-time order, a chunk at a time.

        Parameters
        ----------
        topic : str
            Image topic.

        Yields
        ------
        ImageMessage
            One per message, ``log_time_ns`` filled; ``data`` is a view of the chunk's
            bytes (copy what you keep: the reader holds a chunk or two, never the bag).
            The content (encoding, size) is checked by
            :func:`~stellar_cal_ros.io.image_msgs.image_pixels`, not here.

        Raises
        ------
        BagError
            Topic missing / of another type, or truncated file (strict mode).
        MessageDecodeError
            A message whose CDR is malformed (strict mode).
        """
        yield from self._iter_objects(topic, "image")

    def iter_camera_info(self, topic: str = "/star_tracker/camera_info"
                         ) -> Iterator[CameraInfoMessage]:
        """Stream ``sensor_msgs/msg/CameraInfo`` messages of ``topic`` (log-time order)."""
        yield from self._iter_objects(topic, "camera_info")

    def read_star_frames(self, topic: str = "/star_tracker/stars") -> list[StarFrame]:
        """Read all star frames of ``topic``; see :meth:`iter_star_frames`.

        Parameters
        ----------
        topic : str
            Star centroid topic.

        Returns
        -------
        list of StarFrame
            In log-time order.
        """
        return list(self.iter_star_frames(topic))

    def read_navsat(self, topic: str = "/gnss/fix") -> NavSatSeries:
        """Read all ``sensor_msgs/msg/NavSatFix`` messages of ``topic``.

        Parameters
        ----------
        topic : str
            GNSS fix topic.

        Returns
        -------
        NavSatSeries
            Latitude/longitude in deg, altitude in m, in log-time order.
        """
        parts, dec = self._read_topic(topic, "fix")
        return dec.build(concat(parts) if parts else None)

    def read_scalar(self, topic: str) -> ScalarSeries:
        """Read a ``sensor_msgs/msg/Temperature`` (deg C) or ``FluidPressure`` (Pa) topic.

        Parameters
        ----------
        topic : str
            E.g. ``/star_tracker/temperature``, ``/environment/pressure``.

        Returns
        -------
        ScalarSeries
            ``value`` is ``temperature`` or ``fluid_pressure``; log-time order.
        """
        parts, dec = self._read_topic(topic, "scalar")
        return dec.build(concat(parts) if parts else None)

    def read_whole(self, topics: Mapping[str, tuple[str, str]],
                   convert: Mapping[str, Callable[[Any], Any]] | None = None
                   ) -> dict[str, Any]:
        """Several topics read whole in one pass over the bag (each chunk read once).

        What one ``read_*`` call a topic gives, without decompressing and checking every
        chunk once per topic.

        Parameters
        ----------
        topics : mapping of str to (str, str)
            Role -> ``(topic, kind)``, the kind a key of :data:`kinds.EXPECTED` (``imu``,
            ``stars``, ``fix``, ``scalar``, ``image``, ``camera_info``).  A topic missing
            or of another type raises :class:`BagError` as the ``read_*`` of its kind does
            (checked in the mapping's order, before anything is read).
        convert : mapping of str to callable, optional
            Role -> a function applied to each message of a per-message kind as it is read
            (a None result is left out): memory then holds a chunk of those messages, not
            the topic's (star images made into frames).

        Returns
        -------
        dict of str to object
            Role -> what :meth:`read_imu`, :meth:`read_star_frames`, :meth:`read_navsat`,
            :meth:`read_scalar`, ``list(iter_images(...))`` or ``list(iter_camera_info(...))``
            return for its topic (each message converted when ``convert`` says so).

        Raises
        ------
        BagError, MessageDecodeError
            As those methods (``on_error="raise"``).
        """
        roles = list(topics)
        decoders = [self._decoder(topic, kind) for topic, kind in topics.values()]
        if not decoders:
            return {}
        convert = convert or {}
        counter: dict[str, list[Any]] = {}
        parts: dict[str, list[Any]] = {role: [] for role in roles}
        what = ", ".join(dict.fromkeys(topic for topic, _ in topics.values()))
        for rows, _ in releases(self._decoded(decoders, counter, what), len(decoders)):
            for role, dec, d in zip(roles, decoders, rows, strict=True):
                if d is None:
                    continue
                if dec.kind not in kinds.PER_MESSAGE:
                    d.pop("seq", None)
                    parts[role].append(d)
                elif role in convert:
                    parts[role].extend(o for o in map(convert[role], d["obj"]) if o is not None)
                else:
                    parts[role].extend(d["obj"])
        out: dict[str, Any] = {}
        for role, dec in zip(roles, decoders, strict=True):
            got = parts[role]
            out[role] = got if dec.kind in kinds.PER_MESSAGE else \
                dec.build(concat(got) if got else None)
            dec.warn_frames()
        self._report_skipped(counter)
        return out

    # -- one pass over every topic ---------------------------------------------------------

    def stream(
        self, topics: Mapping[str, str] | None = None, imu_block: int = 4096
    ) -> Iterator[tuple[str, kinds.Block]]:
        """Read several topics interleaved in log-time order, in one pass over the bag.

        Every chunk is decompressed and CRC-checked once and decoded in bulk; memory is a
        chunk or two (the overlap of consecutive chunks), not the bag.

        Parameters
        ----------
        topics : mapping of str to str, optional
            Role -> topic. Default :data:`DEFAULT_TOPICS` (``imu``, ``stars``, ``fix``,
            ``head``, ``air``, ``pressure``). A topic the bag does not have is left out. The
            block type follows the topic's message type: ``Imu`` -> :class:`ImuSeries`,
            ``StarCentroidArray`` -> :class:`StarFrame`, ``NavSatFix`` ->
            :class:`NavSatSeries`, ``Temperature`` / ``FluidPressure`` ->
            :class:`ScalarSeries`, ``Image`` -> :class:`ImageMessage`, ``CameraInfo`` ->
            :class:`CameraInfoMessage`; a topic of another type raises :class:`BagError`
            (``on_error="skip"``: it is left out with a warning).
        imu_block : int
            Most samples in one :class:`ImuSeries` block.

        Yields
        ------
        (str, block)
            ``(role, block)`` in log-time order, ``role`` a key of ``topics``: a block holds
            consecutive messages of one topic (no message of another streamed topic falls
            between its first and last). Equal log times keep the order the messages were
            written (chunks in file order, then position in the chunk; files in
            ``metadata.yaml`` order), which can differ between two formats of one
            recording. Series blocks hold one or more messages (an IMU block at most
            ``imu_block``; blocks are not necessarily maximal: they are also cut where a
            chunk ends); a star, image or camera-info block is one message. Concatenating
            one role's blocks gives exactly what ``read_imu`` / ``read_star_frames`` /
            ``read_navsat`` / ``read_scalar`` / ``iter_images`` return for its topic. Block
            arrays are views of the chunk's decoded arrays (the IMU covariances are shared
            by all blocks; an image's data is a view of its chunk): copy what you keep for
            long if memory matters.

        Raises
        ------
        BagError
            Damaged bag or a topic of another type (``on_error="raise"``).
        MessageDecodeError
            A malformed message (``on_error="raise"``); with ``"skip"`` it is dropped and
            counted in :attr:`skipped` and damaged chunks are skipped (see the class).
        """
        if imu_block < 1:
            raise ValueError("imu_block must be >= 1")
        roles, decoders = self._stream_decoders(topics)
        counter: dict[str, list[Any]] = {}
        if decoders:
            batches = self._decoded(decoders, counter, "the stream")
            for r, fields in interleaved(batches, len(decoders)):
                yield from ((roles[r], b) for b in decoders[r].blocks(fields, imu_block))
        for d in decoders:
            d.warn_frames()
        self._report_skipped(counter)

    def stream_releases(
        self, topics: Mapping[str, str] | None = None
    ) -> Iterator[tuple[list[str], list[kinds.Block | list[Any] | None], NDArray[np.int64]]]:
        """What :meth:`stream` yields, a release of rows at a time (no Python object a run).

        Parameters
        ----------
        topics : mapping of str to str, optional
            As :meth:`stream`.

        Yields
        ------
        (roles, blocks, order)
            ``roles``: the streamed roles (the same list every time); ``blocks[r]``: the
            rows of ``roles[r]`` that became final, one series (a list of messages for a
            star, image or camera-info topic; None: no row); ``order[i]``: the index in
            ``roles`` of the ``i``-th of these messages in log-time order (ties in file
            order), the ``k``-th ``r`` being row ``k`` of ``blocks[r]``.  Cutting each
            release's blocks at the role changes of ``order`` (and an IMU run every
            ``imu_block`` rows) gives :meth:`stream`'s blocks, in its order.

        Raises
        ------
        BagError, MessageDecodeError
            As :meth:`stream`.
        """
        roles, decoders = self._stream_decoders(topics)
        counter: dict[str, list[Any]] = {}
        if decoders:
            batches = self._decoded(decoders, counter, "the stream")
            for rows, order in releases(batches, len(decoders)):
                yield roles, [None if d is None else dec.build(d)
                              for dec, d in zip(decoders, rows, strict=True)], order
        for dec in decoders:
            dec.warn_frames()
        self._report_skipped(counter)

    def _stream_decoders(self, topics: Mapping[str, str] | None
                         ) -> tuple[list[str], list[kinds.TopicDecoder]]:
        """The roles a stream reads and their decoders (unknown types raised or left out)."""
        topics = dict(DEFAULT_TOPICS if topics is None else topics)
        roles: list[str] = []
        decoders: list[kinds.TopicDecoder] = []
        for role, topic in topics.items():
            types = self._topic_types(topic)
            kind = kinds.kind_of(types)
            if kind is None and types:
                msg = (f"topic {topic!r} in {self.path} has type {sorted(set(types))}; stream "
                       f"reads {', '.join(t for e in kinds.EXPECTED.values() for t in e)}")
                if self.on_error == "raise":
                    raise BagError(msg)
                warnings.warn(msg + "; left out", stacklevel=3)
            if kind is None:
                continue
            roles.append(role)
            decoders.append(self._decoder(topic, kind, missing_ok=True))
        return roles, decoders

    def _topic_types(self, topic: str) -> list[str]:
        return [self._src.normalized_type(c) for c, ch in self._channels().items()
                if ch.topic == topic]

    # -- generic ---------------------------------------------------------------------------

    def iter_raw(
        self, topics: Iterable[str] | None = None
    ) -> Iterator[tuple[str, int, bytes]]:
        """Yield every message of ``topics`` (all if None) as its CDR payload.

        Parameters
        ----------
        topics : iterable of str, optional
            Topics to read; None reads all.

        Yields
        ------
        (topic, log_time_ns, payload)
            In log-time order (ties in file order); ``payload`` is the serialized message
            as ROS 2 publishes it (a ROS 1 bag's messages converted to CDR).
        """
        for _, topic, log_time, raw in self._raw(topics):
            yield topic, log_time, raw

    def _raw(self, topics: Iterable[str] | None) -> Iterator[tuple[int, str, int, bytes]]:
        """(channel id, topic, log time, payload) of ``topics`` in log-time order."""
        channels = self._channels()
        want = None
        if topics is not None:
            tset = set(topics)
            want = {c for c, ch in channels.items() if ch.topic in tset}

        def batches() -> Iterator[tuple[int, Fields]]:
            for rows in self._rows(want, "messages"):
                n = len(rows)
                objs = np.empty(n, dtype=object)
                mv = memoryview(rows.buf)
                for i in range(n):
                    cid = int(rows.channel[i])
                    o, ln = int(rows.offset[i]), int(rows.length[i])
                    objs[i] = (cid, channels[cid].topic if cid in channels else f"#{cid}",
                               int(rows.log_time[i]), bytes(mv[o : o + ln]))
                yield rows.start_ns, {"obj": objs, "log": rows.log_time,
                                      "seq": rows.order_key(np.arange(n))}

        for d in time_ordered(batches()):
            yield from d["obj"]

    def iter_messages(
        self, topics: Iterable[str] | None = None
    ) -> Iterator[tuple[str, int, object]]:
        """Yield every message of ``topics`` (all if None), decoded generically.

        Parameters
        ----------
        topics : iterable of str, optional
            Topics to read; None reads all.

        Yields
        ------
        (topic, log_time_ns, message)
            In log-time order (ties in file order); ``message`` is an object with the ROS
            field names (``mcap_ros2`` dynamic object for MCAP, ``rosbags`` message else).
        """
        counter: dict[str, list[Any]] = {}
        for cid, topic, log_time, raw in self._raw(topics):
            try:
                msg = self._src.decoder(cid)(raw)
            except Exception as exc:  # the generic decoders raise assorted errors
                reason = str(exc) if isinstance(exc, BagError) else \
                    f"{type(exc).__name__}: {exc}"
                self._bad(topic, log_time, reason, counter)
                continue
            yield topic, log_time, msg
        self._report_skipped(counter)

    def raw_schema(self, topic: str) -> tuple[str, str]:
        """Return the schema (name, text) of the first channel of ``topic``.

        Parameters
        ----------
        topic : str
            Topic name.

        Returns
        -------
        (str, str)
            Schema name and its definition text (ros2msg for MCAP).
        """
        for cid, ch in self._channels().items():
            if ch.topic == topic:
                found = self._src.schema(cid)
                if found is not None:
                    return found
        raise BagError(f"topic {topic!r} not in {self.path}")
