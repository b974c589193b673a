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


def releases(
    batches: Iterable[tuple[int, list[Fields | None]]], n_roles: int
) -> Iterator[tuple[list[Fields | None], NDArray[np.int64]]]:
    """Merge decoded batches of several topics into log-time ordered releases.

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
    (list of Fields or None, ndarray of int64)
        ``(rows, order)``: the rows that became final, per role (None: none), each role's in
        the order :func:`time_ordered` gives; and ``order[i]``, the role of the ``i``-th of
        them in log-time order (ties in file order).  The ``k``-th ``r`` in ``order`` is row
        ``k`` of ``rows[r]``.  A release ends where a chunk's rows become final.
    """
    pending: list[Fields | None] = [None] * n_roles
    for start_ns, per_role in batches:
        out = _release(pending, start_ns)
        if out is not None:
            yield out
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
    out = _release(pending, None)
    if out is not None:
        yield out


def interleaved(
    batches: Iterable[tuple[int, list[Fields | None]]], n_roles: int
) -> Iterator[tuple[int, Fields]]:
    """Merge decoded batches of several topics into one log-time ordered sequence of runs.

    Parameters
    ----------
    batches, n_roles
        As :func:`releases`.

    Yields
    ------
    (int, Fields)
        ``(role, rows)``: runs of consecutive messages of one role, in log-time order (ties in
        file order); each role's rows are in the order :func:`time_ordered` gives. A run may
        be cut where a chunk's rows become final, so two consecutive runs can have the same
        role.
    """
    for rows, order in releases(batches, n_roles):
        present = [r for r, p in enumerate(rows) if p is not None]
        if len(present) == 1:
            yield present[0], rows[present[0]]
            continue
        for r, a, b in runs(order):
            yield r, take(rows[r], slice(a, b))


def runs(order: NDArray[np.int64]) -> Iterator[tuple[int, int, int]]:
    """``(role, a, b)``: the runs of one role in a release's ``order`` (:func:`releases`).

    A run is rows ``a:b`` of that role's rows.
    """
    if not len(order):
        return
    cuts = np.flatnonzero(order[1:] != order[:-1]) + 1
    role = order[np.concatenate([[0], cuts])].tolist()
    size = np.diff(np.concatenate([[0], cuts, [len(order)]])).tolist()
    pos = [0] * (max(role) + 1)
    for r, n in zip(role, size, strict=True):
        k = pos[r]
        pos[r] = k + n
        yield r, k, k + n


def _release(pending: list[Fields | None], bound: int | None
             ) -> tuple[list[Fields | None], NDArray[np.int64]] | None:
    """The pending rows below ``bound`` (all if None) and their roles' order; keep the rest."""
    rows: list[Fields | None] = [None] * len(pending)
    present: list[int] = []
    for r, p in enumerate(pending):
        if p is None or not len(p["log"]):
            continue
        k = len(p["log"]) if bound is None else int(np.searchsorted(p["log"], bound, "left"))
        if k == len(p["log"]):
            rows[r] = p
            pending[r] = None
        elif k:
            rows[r] = take(p, slice(0, k))
            pending[r] = take(p, slice(k, None))
        else:
            continue
        present.append(r)
    if not present:
        return None
    if len(present) == 1:
        r = present[0]
        return rows, np.full(len(rows[r]["log"]), r, np.int64)  # type: ignore[index]
    heads = [(r, rows[r]) for r in present]
    log = np.concatenate([h["log"] for _, h in heads])
    seq = np.concatenate([h["seq"] for _, h in heads])
    role = np.concatenate([np.full(len(h["log"]), r, np.int64) for r, h in heads])
    return rows, role[np.lexsort((seq, log))]
