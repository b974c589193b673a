"""Log-time ordering of decoded chunk batches, for one topic or for several interleaved.

Chunks come in order of their start time; a chunk's messages are sorted, but chunks may
overlap in time. Both mergers keep a look-behind of the rows not yet final: a row is final
once the next batch's start time is above its log time. Memory is the overlap of the chunks
(a chunk or two), whatever the bag's length. Ties keep file order.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

Fields = dict[str, NDArray[Any]]
"""Row-aligned arrays of decoded messages; ``"log"`` holds the int64 log times, ns."""


def take(data: Fields, idx: NDArray[np.int64] | slice) -> Fields:
    """Rows ``idx`` of every array."""
    return {k: v[idx] for k, v in data.items()}


def concat(parts: list[Fields]) -> Fields:
    """Concatenate row-aligned batches with the same keys."""
    if len(parts) == 1:
        return parts[0]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def time_ordered(batches: Iterable[tuple[int, Fields]]) -> Iterator[Fields]:
    """Merge decoded batches of one topic into log-time order.

    Parameters
    ----------
    batches : iterable of (start_ns, data)
        ``start_ns`` bounds the log times of this and all later batches from below; ``data``
        may carry a ``"seq"`` key (write-order key) that orders equal log times.

    Yields
    ------
    Fields
        Row-aligned arrays (without ``"seq"``), globally sorted by log time, ties in write
        order (in arrival order without ``"seq"``).
    """
    for _, rows in interleaved(((s, [d]) for s, d in batches), 1):
        rows.pop("seq", None)
        yield rows


def interleaved(
    batches: Iterable[tuple[int, list[Fields | None]]], n_roles: int
) -> Iterator[tuple[int, Fields]]:
    """Merge decoded batches of several topics into one log-time ordered sequence of runs.

    Parameters
    ----------
    batches : iterable of (start_ns, per_role)
        ``per_role[r]`` holds the decoded rows of role ``r`` in this chunk (None: none), each
        with ``"log"`` and ``"seq"`` (int64 position of the message in the file's reading
        order, which breaks ties of log time). ``start_ns`` as in :func:`time_ordered`.
    n_roles : int
        Number of roles.

    Yields
    ------
    (int, Fields)
        ``(role, rows)``: runs of consecutive messages of one role, in log-time order (ties in
        file order); each role's rows are in the order :func:`time_ordered` gives. A run may
        be cut where a chunk's rows become final, so two consecutive runs can have the same
        role.
    """
    pending: list[Fields | None] = [None] * n_roles
    for start_ns, per_role in batches:
        yield from _release(pending, start_ns)
        for r, data in enumerate(per_role):
            if data is None or not len(data["log"]):
                continue
            p = pending[r]
            merged = data if p is None or not len(p["log"]) else concat([p, data])
            log = merged["log"]
            if len(log) > 1 and np.any(log[1:] < log[:-1]):
                order = np.lexsort((merged["seq"], log)) if "seq" in merged else \
                    np.argsort(log, kind="stable")
                merged = take(merged, order)
            pending[r] = merged
    yield from _release(pending, None)


def _release(pending: list[Fields | None], bound: int | None) -> Iterator[tuple[int, Fields]]:
    """Yield the runs of the pending rows below ``bound`` (all if None), keep the rest."""
    heads: list[tuple[int, Fields]] = []
    for r, p in enumerate(pending):
        if p is None or not len(p["log"]):
            continue
        k = len(p["log"]) if bound is None else int(np.searchsorted(p["log"], bound, "left"))
        if k == len(p["log"]):
            heads.append((r, p))
            pending[r] = None
        elif k:
            heads.append((r, take(p, slice(0, k))))
            pending[r] = take(p, slice(k, None))
    if not heads:
        return
    if len(heads) == 1:
        yield heads[0]
        return
    log = np.concatenate([h["log"] for _, h in heads])
    seq = np.concatenate([h["seq"] for _, h in heads])
    role = np.concatenate([np.full(len(h["log"]), r, np.int64) for r, h in heads])
    role = role[np.lexsort((seq, log))]
    cuts = np.flatnonzero(role[1:] != role[:-1]) + 1
    starts = np.concatenate([[0], cuts]).tolist()
    stops = np.concatenate([cuts, [len(role)]]).tolist()
    pos = dict.fromkeys((r for r, _ in heads), 0)
    rows = dict(heads)
    for a, b in zip(starts, stops, strict=True):
        r = int(role[a])
        k = pos[r]
        pos[r] = k + (b - a)
        yield r, take(rows[r], slice(k, k + b - a))
