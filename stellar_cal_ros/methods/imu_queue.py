"""The driver's queue of pending IMU samples (:class:`ImuQueue`) and their release.

:class:`~stellar_cal_ros.methods.driver.Calibrator` holds IMU samples here until the
reorder window has passed, then releases them in stamp order (:class:`ImuRelease`, the
driver's IMU path: release, the replay's deferred release, hand-over to the filter).
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
             increasing: bool | None = None, copy: bool = True) -> None:
        """Append a block (``increasing``: known strictly increasing).

        ``copy=False``: the caller hands the arrays over (int64 stamps, float rates and
        forces, never written to afterwards): they are held as they are, not copied.
        """
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
        if copy:
            t, w, f = np.array(t, dtype=np.int64), np.array(w, dtype=float), \
                np.array(f, dtype=float)
        self._blocks.append((t, w, f))
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


class ImuRelease:
    """The driver's IMU release (a mixin of :class:`~stellar_cal_ros.methods.driver.Calibrator`).

    Uses the driver's ``_imu`` (an :class:`ImuQueue`), ``_staged`` / ``_staged_n`` (released,
    not yet handed to the filter), ``_last_imu_ns``, ``_deferred``, ``imu_max_ns``,
    ``window_ns``, ``t0_ns``, ``counters``, ``driver`` (its DriverConfig) and ``filter``.
    """

    def _defer_release(self, t: np.ndarray, w: np.ndarray, f: np.ndarray, t0: int,
                       t1: int, copy: bool = True) -> bool:
        """Queue an in-order block whose release can wait (a replay); False: not taken.

        With ``batch_frames`` and the filter running, a pump after an IMU block only moves
        the samples older than the reorder window to the staged batch, until the batch is
        full and the frames are processed.  For a block strictly after everything pushed,
        within the clock-jump bounds, into a queue in strict order, that move can wait: the
        releases are prefixes of one sorted queue, so releasing later up to the current
        limit (:meth:`_settle_imu`, and every :meth:`_pump`) gives the same staged samples,
        and the batch is handed over at the same block (the caller counts what the pump
        would release).  Frees a replay from a pump per message run; what a checkpoint
        saves and every count stay as without it.  The caller has checked the block strictly
        increasing from ``t0`` to ``t1`` (ns) and within the clock-jump bounds of the newest
        sample pushed; ``copy``: as :meth:`ImuQueue.push`'s.
        """
        q = self._imu
        if not self.driver.batch_frames or self.filter is None or not q.strict:
            return False
        newest = self.imu_max_ns
        after = q.tail if q.n else self._last_imu_ns
        if (after is not None and t0 <= after) or newest is None \
                or q.n + len(t) > self.driver.max_pending_imu:
            return False
        q.push(t, w, f, True, copy)
        if t1 > newest:
            self.imu_max_ns = t1
        self._deferred = True
        return True

    def _settle_imu(self) -> None:
        """Do the IMU release :meth:`_defer_release` left (as the pumps would have)."""
        if self._deferred:
            self._deferred = False
            self._release_imu(False)

    def _release_imu(self, final: bool) -> None:
        self._deferred = False
        limit = None if final else self.imu_max_ns - self.window_ns
        strict = self._imu.strict
        t, w, f = self._imu.pop(limit, self.driver.max_pending_imu)
        if not len(t):
            return
        last = self._last_imu_ns
        if strict and (last is None or t[0] > last):  # the usual case: nothing to check
            self._last_imu_ns = int(t[-1])
            self._staged.append((t, w, f))
            self._staged_n += len(t)
            return
        d = np.diff(t)
        if (last is None or t[0] > last) and (d > 0).all():
            keep = None
        else:
            keep = np.ones(len(t), dtype=bool)
            keep[1:] = d > 0  # duplicated stamps within the released block
            if last is not None:
                keep &= t > last
        if keep is not None and not keep.all():
            bad = ~keep
            same = np.zeros(len(t), dtype=bool)
            same[1:] = d == 0
            if self._last_imu_ns is not None:
                same |= t == self._last_imu_ns
            self.counters.imu_duplicate += int((bad & same).sum())
            self.counters.imu_late += int((bad & ~same).sum())
            t, w, f = t[keep], w[keep], f[keep]
        if not len(t):
            return
        self._last_imu_ns = int(t[-1])
        self._staged.append((t, w, f))
        self._staged_n += len(t)

    def _flush_staged(self) -> None:
        if not self._staged or self.filter is None:
            return
        t = np.concatenate([s[0] for s in self._staged])
        w = np.concatenate([s[1] for s in self._staged])
        f = np.concatenate([s[2] for s in self._staged])
        self._staged, self._staged_n = [], 0
        self.filter.extend_imu((t - self.t0_ns) * 1e-9, w, f)
