"""Replay a bag through a Kalman-filter calibration, as fast as the machine allows.

:func:`replay` reads the bag in one pass in time order and feeds every message to the one
streaming driver (:class:`~stellar_cal_ros.methods.driver.Calibrator`) that the live node
uses too; residual and history tables go to memory or, for long bags, straight to files.
Every skipped frame, star or IMU sample is counted; nothing is dropped silently.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from stellar_cal_ros.errors import BagError, ModelError
from stellar_cal_ros.io.bag import BagReader
from stellar_cal_ros.io.calibration import Calibration
from stellar_cal_ros.io.merge import runs
from stellar_cal_ros.methods import models, registry
from stellar_cal_ros.methods.driver import Calibrator, DriverConfig
from stellar_cal_ros.methods.frames import (  # noqa: F401 (re-exported)
    TOPIC_FIX,
    TOPICS,
    BagData,
    bag_data_from_simulation,
    clean_frame,
    missing_stars_text,
    read_bag_data,
    star_input,
)
from stellar_cal_ros.methods.results import (  # noqa: F401 (re-exported)
    RESIDUAL_COLUMNS,
    NullSink,
    ReplayResult,
    TableSink,
    equivalent_principal_point,
    result_calibration,
    truth_parameters,
)

log = logging.getLogger(__name__)

#: data-time reorder window of a replay (a bag's log order is nearly stamp order)
REPLAY_REORDER_S = 1.0
#: data seconds of IMU a replay holds ahead of the frame being processed
REPLAY_LOOKAHEAD_S = 30.0
#: IMU block handed to the driver at once
IMU_BLOCK = 4096
#: data seconds of a bag's IMU blocks a replay merges across star frames (:func:`_merged_imu`)
IMU_MERGE_S = 1.0
#: the same when the merge also passes over environment and fix messages (nothing the run
#: computes reads them: :func:`_env_unread`); the look-ahead's size, so a frame waits no
#: longer than the filter's look-ahead holds it anyway
IMU_MERGE_QUIET_S = REPLAY_LOOKAHEAD_S
#: the bag roles of environment and fix messages
ENV_ROLES = frozenset({"fix", "head", "air", "pressure"})
#: the event role of consecutive star messages with their filter inputs, ``(frames,
#: inputs)``, computed a chunk a call (:meth:`Calibrator.star_inputs`) and handed on in one
#: (:meth:`Calibrator.push_stars_many`): a replay's frames between two other events
_STARS_MANY = "star messages with inputs"
#: the event roles of star messages
_STAR_ROLES = frozenset({"stars", _STARS_MANY})


def _events_from_data(data: BagData, inputs=None):
    """``(stamp_ns, role, payload)`` of a :class:`BagData` in time order (in memory).

    ``inputs`` (:meth:`Calibrator.star_inputs`): the star frames between two other events go
    as one ``(frames, inputs)`` event (:data:`_STARS_MANY`, :func:`_grouped_frames`), their
    inputs computed :data:`INPUT_FRAMES` frames a call.
    """
    stamps = data.imu_stamp_ns
    out = []
    # blocks keyed by their first stamp: a frame comes after the IMU block it falls in, as
    # from a bag read in log order (never far ahead of the newest IMU sample); cut where the
    # stamps step by more than a second, so that the frames of an IMU gap come before it
    cuts = np.flatnonzero(np.abs(np.diff(np.asarray(stamps, dtype=np.int64))) > 10**9) + 1
    starts = sorted(set(range(0, len(stamps), IMU_BLOCK)) | set(cuts.tolist()))
    for a, b in zip(starts, starts[1:] + [len(stamps)], strict=True):
        out.append((int(stamps[a]), 0, "imu", (stamps[a:b], data.imu_w[a:b],
                                                   data.imu_f[a:b])))
    # frames in list (log) order: each keyed by the latest stamp so far, so a frame logged
    # late comes after its successors, as from a bag
    latest = None
    for i, fr in enumerate(data.frames):
        key = int(fr.stamp_ns) if fr.log_time_ns is None else int(fr.log_time_ns)
        latest = key if latest is None else max(latest, key)
        out.append((latest, 1, "stars", i))
    if data.site is not None:
        s = data.site
        out.append((data.t0_ns, -1, "fix", (data.t0_ns, s.latitude_deg, s.longitude_deg,
                                             s.height_m, 0)))
    # an environment sample goes before the IMU block its stamp falls in: a bag read in log
    # order has it by the time the IMU reaches it, which is when the driver releases a frame
    # (the look-ahead holds frames REPLAY_LOOKAHEAD_S of IMU longer).  Keyed by its own stamp
    # it came after the whole block, and a frame in the block's last second, whose next
    # temperature lies in the next block, went with a stale temperature (env_stale 12 on a
    # 300 s bag; a thermal model's estimates moved by up to 1.3 sigma against the file's)
    block_t0 = np.asarray(stamps, dtype=np.int64)[starts] if len(stamps) else \
        np.zeros(0, np.int64)
    # The samples of one series that share a key go as one bulk event (``scalars``, the
    # driver's :meth:`~.driver.Calibrator.push_scalars`, what a call a sample does): the
    # stable sort keeps them next to each other anyway (a 2-h bag's 21 600 samples, each a
    # driver call of ~11 µs and an event, are ~1 000 events)
    for key, series in (("head", data.head_temperature), ("air", data.air_temperature),
                        ("pressure", data.pressure)):
        if series is not None and len(series.stamp_ns):
            st = np.asarray(series.stamp_ns, dtype=np.int64)
            value = np.asarray(series.value, dtype=float)
            j = np.searchsorted(block_t0, st, side="right") - 1
            keys = np.where(j >= 0, block_t0[np.maximum(j, 0)], st) if len(block_t0) else st
            cuts = (np.flatnonzero(keys[1:] != keys[:-1]) + 1).tolist()
            for a, b in zip([0, *cuts], [*cuts, len(st)], strict=True):
                out.append((int(keys[a]), -1, "scalars", (key, st[a:b], value[a:b])))
    out.sort(key=lambda e: (e[0], e[1]))
    if inputs is None:
        for _, _, role, payload in out:
            yield (role, data.frames[payload]) if role == "stars" else (role, payload)
        return
    yield from _grouped_frames(out, data.frames, inputs)


def _grouped_frames(events: list, frames, inputs):
    """:func:`_events_from_data`'s events, a run of star frames one :data:`_STARS_MANY` event.

    The frames between two other events go as ``(frames, inputs)``
    (:meth:`Calibrator.push_stars_many`).

    ``events``: ``(key, order, role, payload)`` sorted, a star frame's payload its index in
    ``frames`` (they keep their list order: a group is a run of consecutive indices).  The
    inputs are computed :data:`INPUT_FRAMES` frames a call (chunks from frame 0 on; a chunk
    that gave None: None for each of its frames, which then compute their own).
    """
    chunk: list = [-1, None]  # the last chunk's first frame and inputs

    def group_event(a: int, b: int) -> tuple:
        got: list = []
        while a < b:
            start = a - a % INPUT_FRAMES
            if chunk[0] != start:
                chunk[:] = start, inputs(frames[start:start + INPUT_FRAMES])
            e = min(b, start + INPUT_FRAMES)
            got += [None] * (e - a) if chunk[1] is None else chunk[1][a - start:e - start]
            a = e
        return _STARS_MANY, (frames[b - len(got):b], got)

    first = None  # the open group's first frame
    last = 0
    for _, _, role, payload in events:
        if role == "stars":
            if first is not None and payload != last:  # (not the next one: a group of its own)
                yield group_event(first, last)
                first = None
            if first is None:
                first = payload
            last = payload + 1
            continue
        if first is not None:
            yield group_event(first, last)
            first = None
        yield role, payload
    if first is not None:
        yield group_event(first, last)


#: the frames of a :class:`BagData` whose inputs one call computes (:func:`_grouped_frames`)
INPUT_FRAMES = 256


def _events_from_reader(reader: BagReader, topics: dict[str, str],
                        env_unread: bool | Callable[[], bool] = False, inputs=None):
    """``(role, payload)`` in log-time order from a bag reader, one pass when it can.

    ``env_unread``: nothing the run computes reads the environment and fix messages
    (:func:`_env_unread`); the IMU blocks then merge across them too.  A call
    (:func:`_env_quiet`): from when it first says so on.  ``inputs``: the star messages' filter
    inputs of a release in one call (:meth:`Calibrator.star_inputs`; :func:`_release_items`).
    """
    quiet = None if isinstance(env_unread, bool) else env_unread
    across, limit = (_QUIET_ACROSS, IMU_MERGE_QUIET_S) if env_unread is True \
        else (_STAR_ROLES, None)
    releases = getattr(reader, "stream_releases", None)
    if releases is not None:
        yield from _merge_items(_release_items(releases(topics=topics), rows=env_unread,
                                               inputs=inputs), across, limit, quiet)
        return
    stream = getattr(reader, "stream", None)
    if stream is not None:
        yield from _merged_imu(stream(topics=topics, imu_block=IMU_BLOCK), across, limit,
                               quiet)
        return
    # readers without a streaming pass: each topic whole, merged by stamp
    available = reader.topics()
    data: list[tuple[int, int, str, Any]] = []
    for role, topic in topics.items():
        if topic not in available:
            continue
        if role == "imu":
            block = reader.read_imu(topic)
        elif role == "stars":
            block = reader.read_star_frames(topic)
        elif role == "fix":
            block = reader.read_navsat(topic)
        else:
            block = reader.read_scalar(topic)
        if role == "stars":
            data += [(int(f.stamp_ns), 1, role, f) for f in block]
            continue
        st = np.asarray(block.stamp_ns, dtype=np.int64)
        step = IMU_BLOCK if role == "imu" else 1
        for a in range(0, len(st), step):
            data.append((int(st[min(a + step, len(st)) - 1]), 0 if role == "imu" else -1,
                         role, _slice(block, a, a + step)))
    data.sort(key=lambda e: (e[0], e[1]))
    for _, _, role, block in data:
        yield from _block_events(role, block)


def _env_unread(cal: Calibrator, started: bool | None = None) -> bool:
    """Whether nothing a run computes reads the environment and fix messages (now).

    No effect of the model and not the method needs them (``Calibrator.requires`` holds
    none of ``site``, ``head_temperature``, ``weather``), and no residual table keeps the
    head temperature.  Then a frame's context takes no value of them (the pump's
    ``frame_context`` gets no environment key; the site it carries, the median of the
    fixes so far, is read only by effects that require it), no frame waits for them
    (``_env_ready``), and their pushes pump only while the filter has not started — on
    the IMU staged so far, which a site-free method starts from alone — so when they reach
    the driver, before or after the IMU logged around them, changes no float: only the
    counts of messages, which are the same.  A method that needs a site reads the fixes
    until its filter is built (at their median so far), and no more when no effect reads
    the site (``Calibrator.site_read``): true from then on (:func:`_env_quiet`;
    ``started``: whether the filter runs, None: as it is).
    """
    started = cal.filter is not None if started is None else started
    return not cal.scalars_read() and \
        ("site" not in cal.requires or (started and not cal.site_read)) and \
        bool(getattr(cal.residuals, "discard", False))


def _env_quiet(cal: Calibrator) -> bool | Callable[[], bool]:
    """:func:`_env_unread` for a replay: a bool, or a call that says it as the run goes.

    A method that needs a site (``needs_site``: swaying_base) reads the fixes until its
    filter starts — the filter is built at their median so far, and each may start it —
    and, when no effect reads the site (``Calibrator.site_read``), none after: then the
    call, true from the filter's start on (before it, the messages go as they came).
    """
    if _env_unread(cal):
        return True
    if cal.filter is None and _env_unread(cal, started=True):
        return lambda: cal.filter is not None
    return False


def _merged_imu(blocks, across=_STAR_ROLES, limit_s: float | None = None,
                quiet: Callable[[], bool] | None = None):
    """The events of a bag's stream, an IMU block merged with the next ones across star frames.

    A star frame falls between two IMU blocks of a bag read in log order (its stamp is its
    mid-exposure, the IMU covering it comes after); the driver's cost is per IMU block
    (≈ 25 µs: checks, queueing, release), so the blocks between two other messages (the
    environment, a fix) go as one — at most :data:`IMU_MERGE_S` of data, stamps increasing
    across the junction, one frame id — and the star frames they held after it, in their
    order: a frame arrives after the IMU that covers it, as live (the filter steps the same
    frames on the same samples: its IMU chunks and frame runs are cut elsewhere, which
    changes no float; test_replay_golden, the 2-h bag's history CSV byte for byte).

    ``blocks``: ``(role, block)`` as :meth:`BagReader.stream` yields them.  ``across``: the
    roles a merge passes over (held, then handed on after it in their order); ``limit_s``:
    the data seconds of a merge (None: :data:`IMU_MERGE_S`).  A replay whose run reads no
    environment or fix message passes over those too (:func:`_env_unread`;
    :data:`IMU_MERGE_QUIET_S`): the 2-h bag's 7 200 IMU calls become 240; ``quiet``
    (:func:`_env_quiet`'s call): from when it first says so on (:func:`_merge_items`).
    """
    return _merge_items(_block_items(blocks), across, limit_s, quiet)


#: the role of an IMU piece among :func:`_merge_items`' items
_PIECE = "imu piece"


def _block_items(blocks):
    """:func:`_merge_items`' items of a stream's ``(role, block)``."""
    for role, block in blocks:
        if role != "imu":
            yield from _block_events(role, block)
            continue
        t = block.stamp_ns
        if len(t):
            yield _PIECE, (t[0], t[-1], block.frame_id,
                           (t, block.angular_velocity, block.linear_acceleration), 0, len(t))
        else:  # (as it came: cuts a merge)
            yield "imu", _imu_payload(block)


def _release_items(releases, imu_block: int = IMU_BLOCK,
                   rows: bool | Callable[[], bool] = False, inputs=None):
    """:func:`_merge_items`' items of :meth:`BagReader.stream_releases`.

    The same as :func:`_block_items` of :meth:`BagReader.stream`'s blocks (an IMU run cut
    every ``imu_block`` samples), without a block object a run.  ``rows``: the
    environment and fix messages of a release go as one event a role (``scalars``:
    ``(role, stamps, values)``; ``fixes``: ``(stamps, lat, lon, alt, status)``; the
    driver's bulk calls) where the role's last one of the release was — for a run that
    reads none of them (:func:`_env_unread`), whose quiet merge hands them on after the
    IMU logged around them anyway; a call (:func:`_env_quiet`): from the release it first
    says so at on.  ``inputs`` (:meth:`Calibrator.star_inputs`): a release's star messages
    go as ``(frames, inputs)`` events, a run of them one event (:data:`_STARS_MANY`), their
    inputs computed in one call (when it gives None, as they came).
    """
    quiet = rows if callable(rows) else None
    for roles, blocks, order in releases:
        if quiet is not None and quiet():  # (a call: from when it first says so on)
            rows, quiet = True, None
        events: list = [None] * len(roles)
        last: list = [None] * len(roles)  # rows: a role's rows in the release, else None
        names = list(roles)  # each role's events' role
        for r, (role, block) in enumerate(zip(roles, blocks, strict=True)):
            if block is None:
                continue
            if role == "imu":
                t = block.stamp_ns
                st = t.tolist()
                arrays = (t, block.angular_velocity, block.linear_acceleration)
                frame = block.frame_id
            elif rows is True and role in ENV_ROLES:
                last[r] = len(block.stamp_ns)
                events[r] = _rows_event(role, block)
            else:
                events[r] = block if role in _ONE_A_MESSAGE else _row_events(role, block)
                pre = inputs(block) if role == "stars" and inputs is not None else None
                if pre is not None:
                    names[r], events[r] = _STARS_MANY, (block, pre)
        for r, a, b in runs(order):
            role = roles[r]
            if role == "imu":
                for c in range(a, b, imu_block):
                    d = min(c + imu_block, b)
                    yield _PIECE, (st[c], st[d - 1], frame, arrays, c, d)
            elif last[r] is not None:
                if b == last[r]:
                    yield events[r]
            elif names[r] is _STARS_MANY:  # (the run's messages in one call)
                block, pre = events[r]
                yield _STARS_MANY, (block[a:b], pre[a:b])
            else:
                ev, name = events[r], names[r]
                for i in range(a, b):
                    yield name, ev[i]


#: the event roles of a release's environment and fix messages in bulk (:func:`_release_items`)
_ROWS_ROLES = frozenset({"scalars", "fixes"})
#: the roles a quiet merge passes over (:func:`_env_unread`)
_QUIET_ACROSS = ENV_ROLES | _ROWS_ROLES | _STAR_ROLES


def _rows_event(role: str, block) -> tuple:
    """The bulk event of a series block's messages (:func:`_release_items`' ``rows``)."""
    if role == "fix":
        return "fixes", (block.stamp_ns, block.latitude_deg, block.longitude_deg,
                         block.altitude_m, block.status)
    return "scalars", (role, block.stamp_ns, block.value)


def _merge_items(items, across=_STAR_ROLES, limit_s: float | None = None,
                 quiet: Callable[[], bool] | None = None):
    """The driver's events of a bag's items in log order, IMU pieces merged (:func:`_merged_imu`).

    ``items``: ``(role, payload)`` events, and ``(_PIECE, (first stamp, last stamp,
    frame id, (stamps, rates, forces), a, b))`` for IMU samples ``a:b`` of those arrays.
    A piece joins the held ones when it has their frame id, its first stamp is above the
    held last one and its last stamp at most ``limit_s`` after the held first one; pieces
    of one set of arrays that follow each other are handed on as one slice.  ``quiet``
    (:func:`_env_quiet`'s call): from when it first says so on, the merge passes over the
    environment and fix messages too, :data:`IMU_MERGE_QUIET_S` at most.
    """
    held: list[list] = []  # [arrays, a, b] of one merge
    later: list = []  # the events of ``across`` roles logged among them
    limit = int((IMU_MERGE_S if limit_s is None else limit_s) * 1e9)
    frame = first = last = None
    for role, p in items:
        if quiet is not None and quiet():
            across, limit, quiet = _QUIET_ACROSS, int(IMU_MERGE_QUIET_S * 1e9), None
        piece = role is _PIECE
        if held:
            if piece:
                f, g, fid, arrays, a, b = p
                if fid == frame and f > last and g - first <= limit:  # joins the merge
                    h = held[-1]
                    if h[0] is arrays and h[2] == a:
                        h[2] = b
                    else:
                        held.append([arrays, a, b])
                    last = g
                    continue
            elif role in across:
                later.append((role, p))
                continue
            yield "imu", _joined(held, frame)
            held = []
            if later:
                yield from _star_runs(later)
                later = []
        if piece:
            f, g, fid, arrays, a, b = p
            held.append([arrays, a, b])
            frame, first, last = fid, f, g
        else:
            yield role, p
    if held:
        yield "imu", _joined(held, frame)
    yield from _star_runs(later)


def _star_runs(events: list) -> list:
    """``events`` with each run of :data:`_STARS_MANY` events one such event.

    Their frames in order: one :meth:`Calibrator.push_stars_many` call for the frames a
    merge held (:func:`_merge_items`).
    """
    out: list = []
    for role, p in events:
        if role is not _STARS_MANY:
            out.append((role, p))
        elif out and out[-1][0] is _STARS_MANY:
            out[-1][1][0].extend(p[0])
            out[-1][1][1].extend(p[1])
        else:
            out.append((role, (list(p[0]), list(p[1]))))
    return out


def _joined(held: list[list], frame_id: str) -> tuple:
    """``Calibrator.push_imu_block``'s arguments of held IMU pieces (frame id None: any)."""
    if len(held) == 1:
        (t, w, f), a, b = held[0]
        if a == 0 and b == len(t):
            return t, w, f, frame_id or None
        return t[a:b], w[a:b], None if f is None else f[a:b], frame_id or None
    forces = [f for (_, _, f), _, _ in held]
    return (np.concatenate([t[a:b] for (t, _, _), a, b in held]),
            np.concatenate([w[a:b] for (_, w, _), a, b in held]),
            None if any(f is None for f in forces) else
            np.concatenate([f[a:b] for (_, _, f), a, b in held]),
            frame_id or None)


def _slice(block, a: int, b: int):
    """Rows ``a:b`` of a series dataclass (arrays sliced, scalars kept)."""
    n = len(block.stamp_ns)
    kw = {}
    for f in dataclasses.fields(block):
        v = getattr(block, f.name)
        kw[f.name] = v[a:b] if isinstance(v, np.ndarray) and v.ndim and len(v) == n else v
    return type(block)(**kw)


def _imu_payload(block) -> tuple:
    """``Calibrator.push_imu_block``'s arguments of an IMU block (frame id None: any)."""
    return (block.stamp_ns, block.angular_velocity, block.linear_acceleration,
            block.frame_id or None)


#: roles whose reader block is one message (the others: series of messages)
_ONE_A_MESSAGE = ("stars", "image", "camera_info")


def _block_events(role: str, block):
    """Driver calls of one reader block."""
    if role == "imu":
        yield "imu", _imu_payload(block)
    elif role in _ONE_A_MESSAGE:
        yield role, block
    else:
        for p in _row_events(role, block):
            yield role, p


def _row_events(role: str, block) -> list:
    """The driver calls' payloads of a series block, one a message."""
    if role == "fix":
        return list(zip(np.asarray(block.stamp_ns).tolist(),
                        np.asarray(block.latitude_deg).tolist(),
                        np.asarray(block.longitude_deg).tolist(),
                        np.asarray(block.altitude_m).tolist(),
                        np.asarray(block.status).tolist(), strict=True))
    return list(zip(np.asarray(block.stamp_ns).tolist(), np.asarray(block.value).tolist(),
                    strict=True))


def _handlers(cal: Calibrator) -> dict[str, Any]:
    """``role -> call(payload)``: the driver call of each event role of the replay."""
    out: dict[str, Any] = {
        # (stamps, rates, forces[, frame_id]): the frame id (None: any) last, by position
        # a decoded block is the replay's own (never written to): queued without a copy
        "imu": lambda p: cal.push_imu_block(*p, owned=True),
        "stars": cal.push_stars,
        _STARS_MANY: lambda p: cal.push_stars_many(*p),
        "image": cal.push_image,  # star images: made into frames one at a time (frames.py)
        "camera_info": cal.images.camera_info,
        "fix": lambda p: cal.push_fix(*p),
        "scalars": lambda p: cal.push_scalars(*p),
        "fixes": lambda p: cal.push_fixes(*p),
    }
    for key in ("head", "air", "pressure"):
        out[key] = functools.partial(_push_scalar, cal.push_scalar, key)
    return out


def _push_scalar(push, key: str, payload) -> None:
    push(key, *payload)


def replay(bag: str | Path | BagData, prior: Calibration, method: str = "psce",
           effects: list[str] | None = None, config=None, *, consider: list[str] | None = None,
           baseline: tuple[str, ...] | None = None, residuals: str | Path | None = None,
           history: str | Path | None = None, keep_tables: bool = True,
           progress: bool = False, topics: dict[str, str] | None = None,
           on_error: str = "raise", driver: DriverConfig | None = None,
           eval_fraction: float = 0.5, filter_cls=None,
           gyro_fault: str = "raise", noise=None) -> ReplayResult:
    """Run a filter method over a bag (path or :class:`BagData`); return the result.

    Parameters
    ----------
    bag : path or BagData
        A bag file (read in one pass) or data in memory.
    prior : Calibration
        Where the calibration starts (values and σ).
    method : str
        A registered filter method (``psce``, ``swaying_base``, ``traditional``, ...:
        :mod:`~stellar_cal_ros.methods.registry`).
    effects : list of str
        Effects added to the method's baseline (:mod:`stellar_cal_ros.methods.models`).
    config : KernelConfig subclass, optional
        The filter's configuration (default: the method's).
    consider : list of str
        Effects tracked as consider parameters (score tests; not estimated).
    baseline : tuple of str, optional
        Replace the method's baseline (studies of a reduced model).
    residuals, history : path, optional
        Stream these tables to files (CSV / Parquet) instead of keeping them in memory.
    keep_tables : bool
        Keep the tables in memory when not streamed (False: statistics only).
    progress : bool
        Show a progress bar with ETA.
    topics : dict, optional
        Topic of each input role (:data:`~stellar_cal_ros.methods.frames.TOPICS`).
    on_error : str
        ``raise`` (default) or ``skip`` malformed messages of the bag (counted).
    driver : DriverConfig, optional
        Buffering settings (default: a replay's).
    eval_fraction : float
        The statistics' evaluation window is the last ``eval_fraction`` of the bag's span.
    filter_cls : type, optional
        A subclass of the method's filter to run instead (e.g. a bound recursion).
    gyro_fault : str
        ``raise``: a gyro that does not turn as the stars do over the first frames raises
        :class:`~stellar_cal_ros.errors.DataError` (deg/s, dead, swapped axes); ``flag``:
        it is counted and flags the result (a diagnosis's candidate runs); ``off``: the
        check does not run (a re-run of a bag whose gyro a run of the same diagnosis has
        judged, and whose own counters and calibration nobody reads: the reliability
        probe's runs).  The check changes no estimate, only the counters and flags.
    noise : NoiseScales, optional
        Scales of the stated noise (stars' σ, gyro ARW, accelerometer VRW) the run uses
        (:mod:`stellar_cal_ros.core.noise`; measured by :mod:`stellar_cal_ros.diagnosis.
        noise`).
    """
    spec = registry.get(method)
    if gyro_fault not in ("raise", "flag", "off"):
        raise ValueError(f"gyro_fault must be 'raise', 'flag' or 'off', got {gyro_fault!r}")
    names = dict(TOPICS)
    names.update(topics or {})
    cfg = config
    if gyro_fault == "flag" and spec.kind == "filter":
        cfg = dataclasses.replace(cfg or spec.config_cls(), unit_check_raises=False)
    if gyro_fault == "off" and spec.kind == "filter":
        cfg = dataclasses.replace(cfg or spec.config_cls(), unit_check=False)
    if noise is not None and spec.kind == "filter":
        cfg = noise.apply(cfg or spec.config_cls())
    # a replay never drops frames for memory: what is held is bounded by the look-ahead
    drv = driver or DriverConfig(reorder_window_s=REPLAY_REORDER_S,
                                 max_pending_frames=1_000_000, batch_frames=True,
                                 strict_clock=True, frame_updates=False)
    # IMU ahead of the frames: the filter takes it in large vectorized batches, and the
    # swaying strapdown gets full reference windows, as over a whole bag
    drv.imu_lookahead_s = max(drv.imu_lookahead_s, REPLAY_LOOKAHEAD_S)
    if spec.imu_lookahead is not None:
        drv.imu_lookahead_s = max(drv.imu_lookahead_s,
                                  spec.imu_lookahead(cfg or spec.config_cls()))
    res_sink = TableSink(residuals, RESIDUAL_COLUMNS) if residuals is not None or keep_tables \
        else NullSink()
    hist_sink = TableSink(history) if history is not None or keep_tables else NullSink()
    t_read = t_filter = 0.0
    losses: dict[str, Any] = {}
    if isinstance(bag, BagData):
        span = _span_of_data(bag)
        cal = _calibrator(prior, method, effects, cfg, drv, consider, res_sink, hist_sink,
                          span, eval_fraction, baseline, filter_cls)
        if hasattr(cal.model, "prepare_frames"):  # the astrometric corrections, in one call
            cal.model.prepare_frames(bag)
        events = _events_from_data(bag, cal.star_inputs)
        reader = None
    else:
        reader = BagReader(bag, on_error=on_error)
        available = reader.topics()
        # star centroids, or star images made into frames as they stream (frames.py)
        stars = star_input(available, names, str(bag))
        if names["imu"] not in available or stars is None:
            reader.close()
            raise BagError(missing_stars_text(str(bag), names, available) if stars is None
                           else f"{bag}: required topic {names['imu']} is missing "
                           f"(topics: {', '.join(sorted(available)) or 'none'})")
        for role in ("image", "camera_info") if stars == "stars" else ("stars",):
            names.pop(role, None)
        span = (reader.start_ns, reader.end_ns)
        cal = _calibrator(prior, method, effects, cfg, drv, consider, res_sink, hist_sink,
                          span, eval_fraction, baseline, filter_cls)
        events = _events_from_reader(reader, {k: v for k, v in names.items()},
                                     env_unread=_env_quiet(cal), inputs=cal.star_inputs)
    bar = _Progress(span, progress)
    handlers = _handlers(cal)
    clock = time.perf_counter
    try:
        t1 = clock()
        for role, payload in events:
            t2 = clock()
            t_read += t2 - t1
            try:
                call = handlers[role]
            except KeyError:  # a role without a driver call: the scalar call says so
                call = functools.partial(_push_scalar, cal.push_scalar, role)
            call(payload)
            if role == "imu" and bar.enabled:
                bar.update(int(np.asarray(payload[0])[-1]))
            t1 = clock()
            t_filter += t1 - t2
        t2 = time.perf_counter()
        cal.finish()
        t_filter += time.perf_counter() - t2
    finally:
        if reader is not None:
            losses = reader.losses(span[0])
            reader.close()
        cal.close()
        bar.close()
    cal.require_initialized()
    return _result(cal, t_read, t_filter, losses)


def _span_of_data(data: BagData) -> tuple[int | None, int | None]:
    st = data.imu_stamp_ns
    return (int(st[0]), int(st[-1])) if len(st) else (None, None)


def _calibrator(prior, method, effects, cfg, drv, consider, res_sink, hist_sink, span,
                eval_fraction, baseline, filter_cls) -> Calibrator:
    start, end = span
    eval_start = None
    if start is not None and end is not None and 0 < eval_fraction < 1:
        eval_start = (start + (1.0 - eval_fraction) * (end - start)) * 1e-9
    return Calibrator(prior, method, effects, cfg, drv, consider=consider,
                      residuals=res_sink, history=hist_sink, eval_start=eval_start,
                      baseline=baseline, filter_cls=filter_cls)


def _result(cal: Calibrator, t_read: float, t_filter: float,
            losses: dict[str, Any]) -> ReplayResult:
    flt = cal.filter
    calibration = cal.calibration()
    counters = cal.all_counters()
    if losses:  # a bag read past damage: counted, and recorded in the result file
        counters["messages_skipped"] = losses["messages_skipped"]
        counters["bag_parts_lost"] = losses["bag_parts_lost"]
        read = {k[:-len("_received")]: int(v) for k, v in counters.items()
                if k.endswith("_received") and not k.startswith("identify_") and v}
        # seconds_read: the IMU time the filter ran over (the summary's 'replayed N s')
        calibration.extra["data_quality"] = {**calibration.extra.get("data_quality", {}),
                                             **losses, "seconds_read": _duration(flt),
                                             "messages_read": read}
    _log_counters(counters)
    hist = cal.history.table()
    derived = dict(calibration.extra.get("derived", {}))
    if hasattr(flt, "level_check_deg"):
        derived["level_check_deg"] = flt.level_check_deg
    return ReplayResult(
        calibration=calibration, covariance=cal.named_covariance(),
        residuals=cal.residuals.table(), history=hist,
        counters=counters, read_seconds=t_read, filter_seconds=t_filter,
        duration=_duration(flt), filter=flt, derived=derived, stats=cal.stats,
        method=cal.method, effects=list(cal.effects),
        consider_stale_ns=list(cal.consider_stale_ns))


def _duration(flt) -> float:
    """The IMU time a filter ran over, s."""
    return float(flt.imu.t_end - 0.0) if flt is not None else 0.0


def _log_counters(counters: dict[str, int]) -> None:
    skipped = {k: v for k, v in counters.items() if (
        k.startswith("skipped") or k.startswith("imu_") or k in (
            "stars_invalid", "stars_gated", "stars_bad_sigma")) and v and k != "imu_received"}
    if skipped:
        log.info("skipped / counted: %s", ", ".join(f"{k}={v}" for k, v in skipped.items()))


class _Progress:
    """A progress bar over the bag's data time (tqdm; plain lines when not a terminal)."""

    def __init__(self, span: tuple[int | None, int | None], enabled: bool) -> None:
        self.enabled = bool(enabled) and span[0] is not None and span[1] is not None
        self.bar = None
        if self.enabled:
            from stellar_cal_ros.progress import progress

            self.start = span[0]
            self.total = max((span[1] - span[0]) * 1e-9, 1e-9)
            self.bar = progress(total=self.total, desc="replay", unit="s")
            self.done = 0.0

    def update(self, stamp_ns: int) -> None:
        if self.bar is None:
            return
        t = min((stamp_ns - self.start) * 1e-9, self.total)
        if t > self.done:
            self.bar.update(t - self.done)
            self.done = t

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


# ---------------------------------------------------------------------------- entry points
def method_runner(method: str) -> registry.Runner:
    """How the diagnosis, ``report``/``compare`` and campaigns run ``method`` on a bag.

    The method's own :attr:`~stellar_cal_ros.methods.registry.MethodSpec.runner` if it has
    one, else (a filter method) :func:`replay` with it:
    ``runner(data, prior, effects, keep_tables=False, eval_fraction=0.5, consider=None,
    gyro_fault="raise", noise=None) -> ReplayResult`` (``noise``: the measured noise scales,
    :class:`~stellar_cal_ros.core.noise.NoiseScales`; a method's own runner may take it).
    The runner carries the spec, so a worker process
    that does not know a user's method registers it.
    """
    spec = registry.get(method)
    if spec.runner is not None:
        return spec.runner
    if spec.kind != "filter":
        raise ModelError(f"the {method} method cannot be re-run on a bag (it has no runner)")
    return functools.partial(_replay_runner, spec)


def _replay_runner(spec: registry.MethodSpec, data, prior: Calibration, effects: list[str],
                   keep_tables: bool = False, eval_fraction: float = 0.5,
                   consider: list[str] | None = None, gyro_fault: str = "raise",
                   noise=None) -> ReplayResult:
    if registry.find(spec.name) is None:  # a user's method, in a fresh worker process
        registry.register(spec)
    if isinstance(data, BagData) and not len(data.imu_t):
        raise BagError(f"{spec.name} needs /imu/data, absent from the bag (a batch method "
                       "without an IMU, e.g. bundle, calibrates star frames alone)")
    return replay(data, prior, spec.name, effects, keep_tables=keep_tables,
                  eval_fraction=eval_fraction, consider=consider, gyro_fault=gyro_fault,
                  noise=noise)


def replay_psce(bag: str | Path | BagData, prior: Calibration, effects: list[str] | None = None,
                config=None, progress: bool = False,
                baseline: tuple[str, ...] | None = None, **kw) -> ReplayResult:
    """:func:`replay` with the PSCE filter (Tan et al. 2018)."""
    return replay(bag, prior, "psce", effects, config, progress=progress, baseline=baseline, **kw)


def build_model(prior: Calibration, effects: list[str], baseline=None):
    """StarModel of the PSCE baseline (or ``baseline``) plus ``effects``."""
    return models.build_model(prior, "psce", effects, baseline=baseline)
