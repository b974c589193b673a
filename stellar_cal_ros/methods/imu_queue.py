"""The live driver's queue of pending IMU samples (:class:`ImuQueue`).

:class:`~stellar_cal_ros.methods.driver.Calibrator` holds IMU samples here until the
reorder window has passed, then releases them in stamp order.
"""

from __future__ import annotations

from collections import deque

import numpy as np


class ImuQueue:
    """Pending IMU samples (stamps ns, rates, specific forces), held as the blocks pushed.

    In-order blocks (the usual case, a bag or a transport in order) are released whole or
    split, without copying every pending sample at every release; out-of-order ones are
    sorted once when released.  ``t``, ``w``, ``f`` (all pending samples) and ``sorted`` are
    what a checkpoint saves.
    """

    def __init__(self) -> None:
        self._blocks: deque[tuple[np.ndarray, np.ndarray, np.ndarray]] = deque()
        self.n = 0
        self.sorted = True  #: the blocks in order are sorted by stamp
        #: ... and strictly increasing (no duplicated stamp)
        self.strict = True
        self._tail: int | None = None  # the newest pending stamp

    def _concat(self, i: int) -> np.ndarray:
        if not self._blocks:
            return np.zeros((0,) + ((3,) if i else ()), dtype=np.int64 if i == 0 else float)
        return np.concatenate([b[i] for b in self._blocks])

    @property
    def t(self) -> np.ndarray:
        """Every pending stamp (arrival order unless sorted)."""
        return self._concat(0)

    @property
    def w(self) -> np.ndarray:
        """Every pending rate (rad/s), as :attr:`t`."""
        return self._concat(1)

    @property
    def f(self) -> np.ndarray:
        """Every pending specific force (m/s²), as :attr:`t`."""
        return self._concat(2)

    @property
    def tail(self) -> int | None:
        """The newest pending stamp (None: nothing pending)."""
        return self._tail

    def count_upto(self, limit_ns: int) -> int:
        """Pending samples stamped ≤ ``limit_ns`` (the queue sorted: :attr:`sorted`)."""
        k = self.n
        for b in reversed(self._blocks):
            t = b[0]
            if t[0] > limit_ns:
                k -= len(t)
                continue
            if t[-1] > limit_ns:
                k -= len(t) - int(np.searchsorted(t, limit_ns, side="right"))
            break
        return k

    def push(self, t: np.ndarray, w: np.ndarray, f: np.ndarray,
             increasing: bool | None = None) -> None:
        """Append a block (``increasing``: known strictly increasing)."""
        m = len(t)
        if not m:
            return
        if increasing is None:
            increasing = m < 2 or bool((t[1:] > t[:-1]).all())
        after = self._tail is None or t[0] > self._tail
        if self.strict and not (increasing and after):
            self.strict = False
        if self.sorted and not (increasing and after) and (
                (self._tail is not None and t[0] < self._tail)
                or (m > 1 and np.any(t[1:] < t[:-1]))):
            self.sorted = False
        # the newest pending stamp (the last one while sorted: what the next block is
        # compared with)
        top = int(t[-1]) if increasing else int(t.max())
        self._tail = top if self._tail is None else max(self._tail, top)
        self._blocks.append((np.array(t, dtype=np.int64), np.array(w, dtype=float),
                             np.array(f, dtype=float)))
        self.n += m

    def pop(self, limit_ns: int | None, keep_max: int) -> tuple[np.ndarray, ...]:
        """Samples with stamp ≤ limit (all if None), sorted; at most ``keep_max`` stay held."""
        n = self.n
        if not n:
            return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3))
        blocks = self._blocks
        if not self.sorted:
            t, w, f = self._concat(0), self._concat(1), self._concat(2)
            o = np.argsort(t, kind="stable")
            blocks.clear()
            blocks.append((t[o], w[o], f[o]))
            self.sorted = True
            self.strict = False  # duplicates may be in it: checked when released
        if limit_ns is None:
            k = n
        else:
            k = 0
            for b in blocks:
                if b[0][-1] <= limit_ns:
                    k += len(b[0])
                    continue
                k += int(np.searchsorted(b[0], limit_ns, side="right"))
                break
        k = max(k, n - keep_max)
        out = []
        left = k
        while left:
            b = blocks[0]
            if len(b[0]) <= left:
                out.append(blocks.popleft())
                left -= len(b[0])
            else:
                out.append((b[0][:left], b[1][:left], b[2][:left]))
                blocks[0] = (b[0][left:], b[1][left:], b[2][left:])
                left = 0
        self.n = n - k
        if not blocks:
            self._tail = None
            self.strict = True
        if len(out) == 1:
            return out[0]
        if not out:
            return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3))
        return tuple(np.concatenate([o[i] for o in out]) for i in range(3))
