"""Online (live) PSCE calibration: messages in any interleaving, same result as the replay.

:class:`OnlineCalibrator` is the estimator of the ``calibrator`` node without any ROS
dependency.  It takes IMU samples, star frames, temperatures, pressure and GNSS fixes one at
a time, in whatever order the transport delivers them, and drives a
:class:`~stellar_cal_ros.methods.psce.PsceFilter` exactly as
:func:`~stellar_cal_ros.methods.replay.replay_psce` does over a whole bag:

* the same relative time origin as :func:`~stellar_cal_ros.methods.replay.read_bag_data`
  (``t0_ns`` = first IMU stamp − median of the first ``t0_imu_samples`` − 1 IMU intervals);
* the same IMU cleaning (stamp order, duplicated stamps and non-finite samples dropped);
* the same frame cleaning (:func:`~stellar_cal_ros.methods.replay.clean_frame`), context
  (:func:`frame_context` interpolation of temperatures and pressure; the site is the median
  of the valid fixes) and counters.

Reorder buffer
--------------
The *data clock* is the latest IMU stamp received, ``T``.  IMU samples are held until
``stamp ≤ T − reorder_window_s`` and then released in stamp order; star frames are held
until ``stamp ≤ T − reorder_window_s`` as well, so messages of any topic that arrive up to
the window late (in data time) are still put in order.  A released frame is handed to the
filter only once the released IMU samples *cover* its exposure time ``t_exp = stamp − t0 +
time_shift`` (an IMU stamp > ``t_exp``) — otherwise the filter would count it as
``skipped_no_imu`` where the replay, which holds all IMU, would not — and, if an effect of
the model needs them (``Effect.requires``: ``site``, ``weather``, ``head_temperature``),
once those inputs have a sample at or after the frame stamp, or ``environment_wait_s`` of
data time has passed (then the last value is used: counted as ``env_stale``).  Messages
older than what was already released are dropped and counted (``imu_late``,
``frames_late``).  :meth:`OnlineCalibrator.finish` releases everything (end of a bag).

Memory stays bounded: the filter's IMU history is trimmed to the samples it still needs,
environment series to the last ``env_history_s`` seconds.

Checkpoints
-----------
:meth:`OnlineCalibrator.save_checkpoint` writes one file (io/checkpoint.py: atomic, checksum)
holding the filter's nominal state (attitude, θ, ω, time), covariance, counters, the
IMU tail it still needs, and every buffered message (reorder buffers, pending frames,
environment series, fixes).  :meth:`OnlineCalibrator.load_checkpoint` into a new instance
built with the same prior, effects and configuration continues exactly where the saved one
stopped: feeding both the same remaining messages gives bit-identical results.
"""

from __future__ import annotations

import copy
import dataclasses
import inspect
import logging
import math
import os
from collections import deque
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from stellar_cal_ros.core.catalog import radec_to_unit
from stellar_cal_ros.core.earth import Site
from stellar_cal_ros.effects.base import FrameContext
from stellar_cal_ros.errors import ModelError
from stellar_cal_ros.io.bag import StarFrame
from stellar_cal_ros.io.calibration import Calibration
from stellar_cal_ros.io.checkpoint import read_checkpoint, write_checkpoint
from stellar_cal_ros.methods.psce import (
    BASELINE_EFFECTS,
    FilterCounters,
    FrameUpdate,
    PsceConfig,
    PsceFilter,
)
from stellar_cal_ros.methods.replay import (
    build_model,
    clean_frame,
    equivalent_principal_point,
    result_calibration,
)

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "stellar_cal_online_checkpoint/1"
ENV_KEYS = ("head", "air", "pressure")


@dataclass
class OnlineConfig:
    """Buffering and convergence settings of :class:`OnlineCalibrator`."""

    reorder_window_s: float = 0.05  #: data-time window within which messages may be reordered
    environment_wait_s: float = 2.0  #: max data time a frame waits for needed temperatures etc.
    t0_imu_samples: int = 1000  #: IMU samples whose median interval sets t0 (read_bag_data)
    max_pending_frames: int = 200  #: held frames beyond this drop the oldest (counted)
    max_pending_imu: int = 100_000  #: held IMU samples beyond this release the oldest
    env_history_s: float = 600.0  #: environment samples older than this before a frame: dropped
    max_fixes: int = 100_000  #: fixes kept for the site median
    imu_batch: int = 512  #: released IMU samples handed to the filter in batches of this size
    converge_window: int = 20  #: updates over which convergence is judged
    converge_sigma_ratio: float = 0.98  #: every σ(now)/σ(window ago) above this: settled
    converge_nis_ratio: float = 2.0  #: mean NIS/dof over the window below this: consistent


@dataclass
class OnlineCounters:
    """Input-level counts (the filter's own are in :class:`FilterCounters`)."""

    imu_received: int = 0
    imu_invalid: int = 0  # non-finite values or stamps
    imu_late: int = 0  # older than the released IMU (beyond the reorder window)
    imu_duplicate: int = 0  # same stamp as an already released sample
    imu_wrong_frame: int = 0
    frames_received: int = 0
    frames_late: int = 0
    frames_duplicate: int = 0
    frames_overflow: int = 0
    frames_wrong_frame: int = 0
    frames_no_site: int = 0
    env_received: int = 0
    env_invalid: int = 0
    env_stale: int = 0
    fixes_received: int = 0
    fixes_invalid: int = 0


@dataclass
class FrameOutcome:
    """What happened to one star frame handed to the filter."""

    stamp_ns: int
    frame_id: str
    status: str  # updated | initialized | skipped_<reason> | dropped_<reason>
    update: FrameUpdate | None = None
    catalog_id: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    magnitude: np.ndarray = field(default_factory=lambda: np.zeros(0))


class _Series:
    """A scalar time series kept sorted by stamp (temperatures, pressure)."""

    def __init__(self) -> None:
        self.stamp_ns: list[int] = []
        self.value: list[float] = []
        self.ref_ns: int | None = None  # earliest finite sample ever: interpolation origin
        self._version = 0  # bumped on every change (add, trim, restore): the caches' key
        self._cache: tuple[Any, np.ndarray, np.ndarray] | None = None  # interp abscissae

    def add(self, stamp_ns: int, value: float) -> None:
        self._version += 1
        if np.isfinite(value) and (self.ref_ns is None or stamp_ns < self.ref_ns):
            self.ref_ns = stamp_ns
        if not self.stamp_ns or stamp_ns >= self.stamp_ns[-1]:
            self.stamp_ns.append(stamp_ns)
            self.value.append(value)
            return
        i = int(np.searchsorted(np.asarray(self.stamp_ns), stamp_ns, side="right"))
        self.stamp_ns.insert(i, stamp_ns)
        self.value.insert(i, value)

    def restore(self, stamp_ns: list[int], value: list[float], ref_ns: int | None) -> None:
        """Replace the samples (checkpoint load)."""
        self._version += 1
        self.stamp_ns, self.value, self.ref_ns = stamp_ns, value, ref_ns

    def interp(self, t_ns: int) -> float:
        """``np.interp`` over the finite samples, in s from the earliest one (as the replay)."""
        if not self.stamp_ns or self.ref_ns is None:
            return float("nan")
        ref = self.ref_ns
        # the arrays change at the inputs' rate (~1 Hz), frames ask more often: cache them
        key = self._version
        if self._cache is None or self._cache[0] != key:
            s = np.asarray(self.stamp_ns, dtype=np.int64)
            v = np.asarray(self.value, dtype=float)
            ok = np.isfinite(v)
            self._cache = (key, (s[ok] - ref) * 1e-9, v[ok])
        _, x, y = self._cache
        if not len(x):
            return float("nan")
        return float(np.interp((t_ns - ref) * 1e-9, x, y))

    def covers(self, t_ns: int) -> bool:
        return bool(self.stamp_ns) and self.stamp_ns[-1] >= t_ns

    def trim(self, before_ns: int) -> None:
        """Drop samples older than ``before_ns`` but keep the one just before it."""
        if len(self.stamp_ns) < 3 or self.stamp_ns[1] >= before_ns:
            return  # nothing to drop (the search below would give i <= 0)
        i = int(np.searchsorted(np.asarray(self.stamp_ns), before_ns, side="left")) - 1
        if i > 0:
            self._version += 1
            del self.stamp_ns[:i]
            del self.value[:i]


class OnlineCalibrator:
    """Live PSCE calibration fed one message at a time (see the module docstring).

    Parameters
    ----------
    prior : Calibration
        Prior calibration (nominal values and their sigmas).
    effects : list of str
        Effects estimated on top of the PSCE baseline.
    psce : PsceConfig
        Filter noise levels and decisions.
    config : OnlineConfig
        Buffering and convergence settings.
    frames : dict, optional
        Expected ``header.frame_id`` of the IMU (``imu``) and star (``star_tracker``)
        messages; ``None`` or an empty id accepts any.  Default: the prior's frames.
    """

    def __init__(self, prior: Calibration, effects: list[str] | None = None,
                 psce: PsceConfig | None = None, config: OnlineConfig | None = None,
                 frames: dict[str, str] | None = None) -> None:
        self.prior = prior
        self.effects = list(effects or [])
        self.psce = _live_config(psce or PsceConfig())
        self.config = config or OnlineConfig()
        self.frames = dict(prior.frames if frames is None else frames)
        self.model = build_model(prior, self.effects)
        self.requires = {r for e in self.model.effects for r in e.requires}
        self.window_ns = int(round(self.config.reorder_window_s * 1e9))
        self.env_wait_ns = int(round(self.config.environment_wait_s * 1e9))
        self._takes_t_rel = "t_rel" in inspect.signature(PsceFilter.process_frame).parameters
        self._reset_state()

    # ------------------------------------------------------------------ state
    def _reset_state(self) -> None:
        self.counters = OnlineCounters()
        self.filter: PsceFilter | None = None
        self.t0_ns: int | None = None
        self.imu_max_ns: int | None = None  # data clock
        self._imu_pending: list[tuple[int, float, float, float]] = []
        self._imu_pending_sorted = True
        self._last_imu_ns: int | None = None  # last released IMU stamp
        self._staged_t: list[int] = []  # released, not yet in the filter (ns)
        self._staged_w: list[tuple[float, float, float]] = []
        self._frames_pending: list[StarFrame] = []  # sorted by stamp
        self._last_frame_ns: int | None = None  # last frame handed on
        self._frame_stamps_seen: set[int] = set()
        self.env = {k: _Series() for k in ENV_KEYS}
        # valid fixes kept for the site median: stamps, and lat, lon, alt as rows of an array
        # with spare capacity (the median is taken at every fix, over up to max_fixes)
        self._fix_ns: list[int] = []
        self._fix_values = np.zeros((0, 3))
        self._fix_count = 0  # fixes ever added: the caches' key
        self._site_cache: tuple[Any, Site] | None = None
        self._clean: dict[int, np.ndarray] = {}  # clean_frame of the pending frames by stamp
        # filter inputs (centroids, catalogue directions, sigmas) of the pending frames
        self._inputs: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._ctx_cache: tuple[Any, FrameContext | None, dict[bytes, float]] | None = None
        self._conv: deque[tuple[np.ndarray, float, int]] = deque(
            maxlen=max(self.config.converge_window, 1) + 1)
        self.last_update: FrameUpdate | None = None

    def reset(self) -> None:
        """Forget everything (the prior, effects and configuration stay)."""
        self._reset_state()

    # ------------------------------------------------------------------ inputs
    def push_imu(self, stamp_ns: int, angular_velocity, frame_id: str | None = None
                 ) -> list[FrameOutcome]:
        """One ``sensor_msgs/Imu`` sample; returns the frames this made processable."""
        c = self.counters
        c.imu_received += 1
        expected = self.frames.get("imu")
        if frame_id is not None and expected and frame_id != expected:
            c.imu_wrong_frame += 1
            return []
        wx, wy, wz = (float(x) for x in angular_velocity)
        if not (np.isfinite(wx) and np.isfinite(wy) and np.isfinite(wz)) or stamp_ns <= 0:
            c.imu_invalid += 1
            return []
        stamp_ns = int(stamp_ns)
        if self._last_imu_ns is not None and stamp_ns <= self._last_imu_ns:
            if stamp_ns == self._last_imu_ns:
                c.imu_duplicate += 1
            else:
                c.imu_late += 1
            return []
        if self._imu_pending and stamp_ns < self._imu_pending[-1][0]:
            self._imu_pending_sorted = False
        self._imu_pending.append((stamp_ns, wx, wy, wz))
        if self.imu_max_ns is None or stamp_ns > self.imu_max_ns:
            self.imu_max_ns = stamp_ns
        return self._pump()

    def push_imu_batch(self, stamp_ns, angular_velocity, frame_id: str | None = None
                       ) -> list[FrameOutcome]:
        """Several IMU samples (arrival order); same as calling :meth:`push_imu` for each."""
        out: list[FrameOutcome] = []
        w = np.asarray(angular_velocity, dtype=float).reshape(-1, 3)
        for s, wi in zip(np.asarray(stamp_ns, dtype=np.int64).tolist(), w.tolist(), strict=True):
            out.extend(self.push_imu(s, wi, frame_id))
        return out

    def push_stars(self, frame: StarFrame) -> list[FrameOutcome]:
        """One ``StarCentroidArray`` (as a :class:`StarFrame`); returns processed frames.

        A frame refused on input (wrong frame id, late, duplicate) comes back at once as a
        ``dropped_<reason>`` outcome; accepted ones come back when processed.
        """
        c = self.counters
        c.frames_received += 1
        stamp = int(frame.stamp_ns)

        def dropped(reason: str) -> list[FrameOutcome]:
            setattr(c, "frames_" + reason, getattr(c, "frames_" + reason) + 1)
            return [FrameOutcome(stamp, frame.frame_id, "dropped_" + reason)]

        expected = self.frames.get("star_tracker")
        if expected and frame.frame_id and frame.frame_id != expected:
            return dropped("wrong_frame")
        if stamp <= 0:
            return dropped("late")
        if self._last_frame_ns is not None and stamp <= self._last_frame_ns:
            return dropped("duplicate" if stamp == self._last_frame_ns else "late")
        stamps = [f.stamp_ns for f in self._frames_pending]
        if stamp in stamps:
            return dropped("duplicate")
        i = int(np.searchsorted(np.asarray(stamps, dtype=np.int64), stamp)) if stamps else 0
        self._frames_pending.insert(i, frame)
        # input check and the filter's inputs on arrival, not when the IMU releases it
        self._frame_inputs(frame, self._clean_mask(frame))
        out: list[FrameOutcome] = []
        while len(self._frames_pending) > self.config.max_pending_frames:
            old = self._frames_pending.pop(0)
            self._clean.pop(int(old.stamp_ns), None)
            self._inputs.pop(int(old.stamp_ns), None)
            c.frames_overflow += 1
            self._last_frame_ns = int(old.stamp_ns)
            out.append(FrameOutcome(int(old.stamp_ns), old.frame_id, "dropped_overflow"))
        return out + self._pump()

    def push_scalar(self, kind: str, stamp_ns: int, value: float) -> list[FrameOutcome]:
        """A temperature (°C) or pressure (Pa): ``kind`` in ``head``, ``air``, ``pressure``."""
        if kind not in self.env:
            raise ValueError(f"unknown scalar input {kind!r} (one of {ENV_KEYS})")
        self.counters.env_received += 1
        value = float(value)
        if stamp_ns <= 0 or not np.isfinite(value):
            self.counters.env_invalid += 1
            return []
        self.env[kind].add(int(stamp_ns), value)
        return self._pump()

    def push_fix(self, stamp_ns: int, latitude_deg: float, longitude_deg: float,
                 altitude_m: float, status: int = 0) -> list[FrameOutcome]:
        """A ``NavSatFix``; valid ones (finite, status ≥ 0) enter the site median."""
        self.counters.fixes_received += 1
        vals = (float(latitude_deg), float(longitude_deg), float(altitude_m))
        if not all(np.isfinite(vals)) or status < 0 or abs(vals[0]) > 90:
            self.counters.fixes_invalid += 1
            return []
        n = len(self._fix_ns)
        if n == len(self._fix_values):  # grow (amortized)
            grown = np.zeros((max(2 * n, 64), 3))
            grown[:n] = self._fix_values[:n]
            self._fix_values = grown
        self._fix_values[n] = vals
        self._fix_ns.append(int(stamp_ns))
        self._fix_count += 1
        k = len(self._fix_ns) - self.config.max_fixes
        if k > 0:
            del self._fix_ns[:k]
            self._fix_values[:n + 1 - k] = self._fix_values[k:n + 1].copy()
        _ = self.site  # the median now, not in the next frame's update
        return self._pump()

    def finish(self) -> list[FrameOutcome]:
        """End of input: release and process everything still held."""
        return self._pump(final=True)

    # ------------------------------------------------------------------ pumping
    @property
    def site(self) -> Site | None:
        """Median of the valid fixes so far (as the replay's over the bag)."""
        if not self._fix_ns:
            return None
        key = self._fix_count
        if self._site_cache is None or self._site_cache[0] != key:
            a = self._fix_values[:len(self._fix_ns)]
            site = Site(float(np.median(a[:, 0])), float(np.median(a[:, 1])),
                        float(np.median(a[:, 2])))
            self._site_cache = (key, site)
        return self._site_cache[1]

    def _release_imu(self, final: bool) -> None:
        pend = self._imu_pending
        if not pend:
            return
        if not self._imu_pending_sorted:
            pend.sort(key=lambda s: s[0])
            self._imu_pending_sorted = True
        limit = None if final else self.imu_max_ns - self.window_ns
        n = len(pend)
        if limit is not None:
            n = 0
            while n < len(pend) and pend[n][0] <= limit:
                n += 1
            n = max(n, len(pend) - self.config.max_pending_imu)
        if n == 0:
            return
        last = self._last_imu_ns
        for s, wx, wy, wz in pend[:n]:
            if last is not None and s <= last:
                if s == last:
                    self.counters.imu_duplicate += 1
                else:
                    self.counters.imu_late += 1
                continue
            self._staged_t.append(s)
            self._staged_w.append((wx, wy, wz))
            last = s
        self._last_imu_ns = last
        del pend[:n]

    def _clean_mask(self, frame: StarFrame) -> np.ndarray:
        """:func:`clean_frame` of a pending frame (computed once)."""
        key = int(frame.stamp_ns)
        ok = self._clean.get(key)
        if ok is None:
            ok = clean_frame(frame, self.prior.camera.width, self.prior.camera.height)
            self._clean[key] = ok
        return ok

    def _frame_inputs(self, frame: StarFrame, ok: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Valid centroids, catalogue unit vectors and sigmas of a pending frame (once)."""
        key = int(frame.stamp_ns)
        v = self._inputs.get(key)
        if v is None:
            s = frame.sigma[ok]
            v = (frame.uv[ok], radec_to_unit(frame.right_ascension[ok], frame.declination[ok]),
                 np.where(s > 0, s, self.psce.centroid_sigma_px))
            self._inputs[key] = v
        return v

    def _start_filter(self) -> None:
        k = self.config.t0_imu_samples
        stamps = np.asarray(self._staged_t[:k], dtype=np.int64)
        self.t0_ns = int(stamps[0]) - int(np.median(np.diff(stamps)))
        t = (np.asarray(self._staged_t, dtype=np.int64) - self.t0_ns) * 1e-9
        w = np.asarray(self._staged_w, dtype=float).reshape(-1, 3)
        self.filter = PsceFilter(self.model, t, w, self.t0_ns * 1e-9, self.psce,
                                 nominal_dt=float(np.median(np.diff(t[:k]))))
        self._staged_t, self._staged_w = [], []

    def _flush_staged(self) -> None:
        if self._staged_t and self.filter is not None:
            t = (np.asarray(self._staged_t, dtype=np.int64) - self.t0_ns) * 1e-9
            self.filter.extend_imu(t, np.asarray(self._staged_w, dtype=float))
            self._staged_t, self._staged_w = [], []

    def _imu_last_rel(self) -> float:
        if self._staged_t:
            return (self._staged_t[-1] - self.t0_ns) * 1e-9
        flt = self.filter
        return float(flt.imu_t[-1]) if flt is not None and len(flt.imu_t) else -np.inf

    def _env_ready(self, stamp_ns: int, final: bool) -> tuple[bool, bool]:
        """(ready, stale) of the environment inputs the model needs for a frame."""
        need = []
        if "head_temperature" in self.requires:
            need.append(self.env["head"])
        if "weather" in self.requires:
            need += [self.env["air"], self.env["pressure"]]
        waiting = [s for s in need if not s.covers(stamp_ns)]
        site_missing = "site" in self.requires and not self._fix_ns
        if not waiting and not site_missing:
            return True, False
        if final or self.imu_max_ns - self.window_ns >= stamp_ns + self.env_wait_ns:
            return True, True
        return False, False

    def _context(self, frame: StarFrame, ok: np.ndarray) -> FrameContext:
        return FrameContext(
            stamp=frame.stamp_ns * 1e-9,
            catalog_id=frame.catalog_id[ok].astype(np.int64),
            magnitude=frame.magnitude[ok],
            site=self.site,
            head_temperature_c=self.env["head"].interp(frame.stamp_ns),
            air_temperature_c=self.env["air"].interp(frame.stamp_ns),
            pressure_pa=self.env["pressure"].interp(frame.stamp_ns),
        )

    def _frame_context(self, frame: StarFrame, ok: np.ndarray) -> FrameContext | None:
        """:meth:`_context` of the head frame, reused while its inputs are unchanged.

        A frame waiting for the IMU is looked at on every IMU sample; its context only
        changes with the environment series and the fixes.
        """
        if not np.any(ok):
            return None
        key = (int(frame.stamp_ns), id(frame),
               tuple(s._version for s in self.env.values()),
               self._fix_count)
        c = self._ctx_cache
        if c is None or c[0] != key:
            c = self._ctx_cache = (key, self._context(frame, ok), {})
        return c[1]

    def _exposure_time(self, frame: StarFrame, ctx: FrameContext) -> float:
        """Relative exposure time of a frame under the current θ (cached with the context)."""
        theta = self.filter.theta
        c = self._ctx_cache
        memo = c[2] if c is not None and c[1] is ctx else {}
        key = theta.tobytes()
        t_exp = memo.get(key)
        if t_exp is None:
            shift, _ = self.model.time_shift(theta, ctx)
            t_exp = memo[key] = (frame.stamp_ns - self.t0_ns) * 1e-9 + shift
        return t_exp

    def _pump(self, final: bool = False) -> list[FrameOutcome]:
        if self.imu_max_ns is None:
            return []
        self._release_imu(final)
        if self.filter is None:
            if len(self._staged_t) >= max(self.config.t0_imu_samples, 2) or (
                    final and len(self._staged_t) >= 2):
                self._start_filter()
            else:
                return []
        elif len(self._staged_t) >= self.config.imu_batch or (
                self._frames_pending and self._frames_pending[0].stamp_ns <= self.imu_max_ns):
            # a frame is waiting for the IMU to cover it: integrate the samples as they come
            # (same values for any batching) so its update only adds the last ones
            self._flush_staged()
        out: list[FrameOutcome] = []
        watermark = self.imu_max_ns - self.window_ns
        while self._frames_pending:
            frame = self._frames_pending[0]
            if not final and frame.stamp_ns > watermark:
                if frame.stamp_ns <= self.imu_max_ns:
                    # inside the reorder window: prepare its context now (reused when the
                    # frame is released unless an environment input or fix arrives first)
                    ctx = self._frame_context(frame, self._clean_mask(frame))
                    if ctx is not None:
                        self._exposure_time(frame, ctx)
                break
            ready, stale = self._env_ready(frame.stamp_ns, final)
            if not ready:
                break
            ok = self._clean_mask(frame)
            ctx = self._frame_context(frame, ok)
            if ctx is not None and not final:
                if not self._imu_last_rel() > self._exposure_time(frame, ctx):
                    break  # wait for the IMU to cover the exposure
            self._frames_pending.pop(0)
            self._clean.pop(int(frame.stamp_ns), None)
            inputs = self._inputs.pop(int(frame.stamp_ns), None)
            self._last_frame_ns = int(frame.stamp_ns)
            if stale:
                self.counters.env_stale += 1
            if "site" in self.requires and not self._fix_ns:
                self.counters.frames_no_site += 1
                out.append(FrameOutcome(int(frame.stamp_ns), frame.frame_id, "dropped_no_site"))
                continue
            self._flush_staged()
            out.append(self._process(frame, ok, ctx, inputs))
        if final:
            self._flush_staged()
        if out:
            self._trim()
        return out

    def _process(self, frame: StarFrame, ok: np.ndarray, ctx: FrameContext | None,
                 inputs: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
                 ) -> FrameOutcome:
        flt = self.filter
        fc = flt.counters
        flt.counters.stars_invalid += int((~ok).sum())
        if ctx is None:
            fc.frames += 1
            fc.skipped_few_stars += 1
            return FrameOutcome(int(frame.stamp_ns), frame.frame_id, "skipped_few_stars")
        before = _counter_values(fc)
        uv, u_i, sigma = inputs if inputs is not None else self._frame_inputs(frame, ok)
        if self._takes_t_rel:  # exact relative stamp from integer ns, as the replay does
            upd = flt.process_frame(uv, u_i, ctx, sigma,
                                    t_rel=(frame.stamp_ns - self.t0_ns) * 1e-9)
        else:
            upd = flt.process_frame(uv, u_i, ctx, sigma)
        if upd is not None and math.isfinite(upd.nis):
            status = "updated"
            self._conv.append((flt.sigma()[3:], float(upd.nis), int(upd.dof)))
        else:
            after = _counter_values(fc)
            changed = [k for k in after if after[k] != before.get(k, 0)
                       and k not in ("frames", "stars_invalid", "stars_gated")]
            if "init_frames" in changed:
                status = "initialized"
            else:
                status = next((k for k in changed if k.startswith("skipped")), "skipped")
        if upd is not None:
            self.last_update = upd
        return FrameOutcome(int(frame.stamp_ns), frame.frame_id, status, upd,
                            ctx.catalog_id, ctx.magnitude)

    def _trim(self) -> None:
        """Drop IMU samples and environment data the filter can no longer need."""
        flt = self.filter
        if flt is None:
            return
        if flt.initialized:
            cut = flt._k - 2  # _segments reads imu_t[_k:], imu_w[_k:]; keep a margin
        elif self._last_frame_ns is not None:
            # before initialization the next frame is not older than the last one handed on
            # (up to the largest time shift it could have): keep 1 s more than that
            t_keep = (self._last_frame_ns - self.t0_ns) * 1e-9 - 1.0
            cut = int(np.searchsorted(flt.imu_t, t_keep)) - 2
        else:
            cut = 0
        if cut > 4096:  # amortize the copy
            flt.drop_imu(cut)
        if self._last_frame_ns is not None:
            before = self._last_frame_ns - int(self.config.env_history_s * 1e9)
            for s in self.env.values():
                s.trim(before)

    # ------------------------------------------------------------------ outputs
    @property
    def initialized(self) -> bool:
        """True once a star frame has initialized the attitude."""
        return self.filter is not None and self.filter.initialized

    def parameter_names(self) -> list[str]:
        """``effect.parameter`` names of θ."""
        return self.model.parameter_names()

    def state(self) -> tuple[np.ndarray, np.ndarray]:
        """Current θ and its 1-sigma."""
        if self.filter is None:
            return self.model.initial_value.copy(), self.model.initial_sigma.copy()
        return self.filter.theta.copy(), self.filter.sigma()[3:]

    def stamp(self) -> float:
        """POSIX time of the current estimate (the filter's time, else the prior's)."""
        if self.filter is not None and self.filter.t is not None:
            return self.filter.t0 + self.filter.t
        return self.prior.stamp

    def calibration(self) -> Calibration:
        """Current calibration (as :func:`~stellar_cal_ros.methods.replay.replay_psce`)."""
        theta, sigma = self.state()
        cal = result_calibration(self.prior, self.model, theta, sigma, "psce", self.stamp())
        P = self.filter.P[3:, 3:] if self.filter is not None else np.diag(sigma**2)
        cal.extra["derived"] = equivalent_principal_point(self.model, theta, P)
        return cal

    def filter_counters(self) -> dict[str, int]:
        """Counters of the filter (zeros before it starts), ``extra`` flattened."""
        fc = self.filter.counters if self.filter is not None else FilterCounters()
        return _counter_values(fc)

    def convergence(self) -> dict[str, Any]:
        """The convergence test: enough updates, σ settled, NIS consistent."""
        hist = list(self._conv)
        n = self.config.converge_window
        res = {"converged": False, "updates": self.filter.counters.updates if self.filter else 0,
               "sigma_ratio_min": float("nan"), "nis_ratio": float("nan")}
        if len(hist) < n + 1 or n < 1:
            return res
        s_old, s_new = hist[0][0], hist[-1][0]
        ratio = float(np.min(s_new / np.maximum(s_old, 1e-300)))
        nis = sum(h[1] for h in hist[1:]) / max(sum(h[2] for h in hist[1:]), 1)
        res.update(sigma_ratio_min=ratio, nis_ratio=float(nis),
                   converged=bool(ratio >= self.config.converge_sigma_ratio
                                  and nis <= self.config.converge_nis_ratio))
        return res

    def pending(self) -> dict[str, int]:
        """Messages held in the buffers."""
        return {"imu": len(self._imu_pending) + len(self._staged_t),
                "frames": len(self._frames_pending)}

    # ------------------------------------------------------------------ checkpoints
    def _identity(self) -> dict[str, Any]:
        return {"method": "psce", "baseline": list(BASELINE_EFFECTS), "effects": self.effects,
                "parameters": self.parameter_names()}

    def save_checkpoint(self, path: str | os.PathLike[str]) -> None:
        """Write everything needed to continue to ``path`` (atomic, with a checksum)."""
        flt = self.filter
        meta: dict[str, Any] = {
            "format": CHECKPOINT_FORMAT,
            "identity": self._identity(),
            "psce": asdict(self.psce),
            "online": asdict(self.config),
            "counters": asdict(self.counters),
            "t0_ns": self.t0_ns,
            "imu_max_ns": self.imu_max_ns,
            "last_imu_ns": self._last_imu_ns,
            "last_frame_ns": self._last_frame_ns,
            "imu_pending_sorted": self._imu_pending_sorted,
            "frames": [{"stamp_ns": int(f.stamp_ns), "frame_id": f.frame_id,
                        "exposure_time": float(f.exposure_time), "n": len(f.catalog_id)}
                       for f in self._frames_pending],
            "filter": None,
            "env_ref_ns": {k: s.ref_ns for k, s in self.env.items()},
        }
        arrays: dict[str, np.ndarray] = {
            "imu_pending": np.asarray(self._imu_pending, dtype=float).reshape(-1, 4),
            "imu_pending_ns": np.asarray([p[0] for p in self._imu_pending], dtype=np.int64),
            "staged_ns": np.asarray(self._staged_t, dtype=np.int64),
            "staged_w": np.asarray(self._staged_w, dtype=float).reshape(-1, 3),
            "fixes": self._fix_values[:len(self._fix_ns)].copy(),
            "fixes_ns": np.asarray(self._fix_ns, dtype=np.int64),
            "conv_sigma": np.asarray([h[0] for h in self._conv], dtype=float).reshape(
                len(self._conv), self.model.size),
            "conv_nis": np.asarray([h[1] for h in self._conv], dtype=float),
            "conv_dof": np.asarray([h[2] for h in self._conv], dtype=np.int64),
        }
        for k, s in self.env.items():
            arrays[f"env_{k}_ns"] = np.asarray(s.stamp_ns, dtype=np.int64)
            arrays[f"env_{k}"] = np.asarray(s.value, dtype=float)
        fr = self._frames_pending
        arrays["frames_catalog_id"] = np.concatenate(
            [f.catalog_id for f in fr]).astype(np.uint32) if fr else np.zeros(0, np.uint32)
        for name in ("right_ascension", "declination", "magnitude", "sigma"):
            arrays["frames_" + name] = np.concatenate(
                [np.asarray(getattr(f, name), float) for f in fr]) if fr else np.zeros(0)
        arrays["frames_uv"] = np.concatenate([f.uv for f in fr]) if fr else np.zeros((0, 2))
        if flt is not None:
            fstate, farrays = _filter_state(flt)
            meta["filter"] = fstate
            arrays.update({"filter." + k: v for k, v in farrays.items()})
        write_checkpoint(path, arrays, meta)

    def load_checkpoint(self, path: str | os.PathLike[str]) -> None:
        """Restore the state saved by :meth:`save_checkpoint` (same prior/effects/config).

        Raises
        ------
        CheckpointError
            The file is missing, truncated, corrupt (checksum) or unreadable.
        ModelError
            The checkpoint belongs to another model (effects, parameters).
        """
        a, meta = read_checkpoint(path)
        if meta.get("format") != CHECKPOINT_FORMAT:
            raise ModelError(f"{path}: unknown checkpoint format {meta.get('format')!r}")
        if meta["identity"] != self._identity():
            raise ModelError(f"{path}: checkpoint of another model {meta['identity']} "
                             f"(this one: {self._identity()})")
        if meta["psce"] != asdict(self.psce):
            log.warning("%s: filter settings differ from the checkpoint's; using the new ones",
                        path)
        self._reset_state()
        self.counters = OnlineCounters(**meta["counters"])
        self.t0_ns = meta["t0_ns"]
        self.imu_max_ns = meta["imu_max_ns"]
        self._last_imu_ns = meta["last_imu_ns"]
        self._last_frame_ns = meta["last_frame_ns"]
        self._imu_pending_sorted = meta["imu_pending_sorted"]
        ip = a["imu_pending"]
        self._imu_pending = [(int(s), *map(float, row[1:]))
                             for s, row in zip(a["imu_pending_ns"].tolist(), ip, strict=True)]
        self._staged_t = a["staged_ns"].tolist()
        self._staged_w = [tuple(r) for r in a["staged_w"].tolist()]
        self._fix_ns = [int(x) for x in a["fixes_ns"].tolist()]
        self._fix_values = np.asarray(a["fixes"], dtype=float).reshape(-1, 3).copy()
        if len(self._fix_values) != len(self._fix_ns):
            raise ValueError("checkpoint: fixes and fixes_ns differ in length")
        self._fix_count += 1  # the caches' key changes with the restored fixes
        for s, nis, dof in zip(a["conv_sigma"], a["conv_nis"].tolist(), a["conv_dof"].tolist(),
                               strict=True):
            self._conv.append((s.copy(), nis, dof))
        for k, s in self.env.items():
            s.restore(a[f"env_{k}_ns"].tolist(), a[f"env_{k}"].tolist(), meta["env_ref_ns"][k])
        pos = 0
        for f in meta["frames"]:
            sl = slice(pos, pos + f["n"])
            pos += f["n"]
            self._frames_pending.append(StarFrame(
                stamp_ns=f["stamp_ns"], frame_id=f["frame_id"],
                exposure_time=f["exposure_time"],
                catalog_id=a["frames_catalog_id"][sl].copy(),
                right_ascension=a["frames_right_ascension"][sl].copy(),
                declination=a["frames_declination"][sl].copy(),
                uv=a["frames_uv"][sl].copy(), magnitude=a["frames_magnitude"][sl].copy(),
                sigma=a["frames_sigma"][sl].copy()))
        fm = meta["filter"]
        if fm is not None:
            farrays = {k[7:]: v for k, v in a.items() if k.startswith("filter.")}
            self.filter = _restore_filter(self.model, self.psce, fm, farrays)

def _counter_values(c: FilterCounters) -> dict[str, int]:
    d = {k: v for k, v in vars(c).items() if k != "extra"}
    d.update(copy.copy(c.extra))
    return d


def _live_config(cfg: PsceConfig) -> PsceConfig:
    """The filter settings for live use: the same as the replay's.

    The prefix-integrated fast propagation follows appended IMU samples
    (:meth:`PsceFilter.extend_imu`) with values independent of how the samples were
    batched, so the live filter uses it too and reproduces the replay with the same
    configuration.
    """
    return cfg


_FILTER_SKIP = ("model", "config", "counters", "_prefix", "_imu_cap")  # _imu_cap: buffers
_PREFIX_KEY = "prefix:"  # checkpoint arrays of the fast-propagation prefix


def _filter_state(flt: PsceFilter) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Every attribute of the filter that defines its state (JSON part, array part).

    Generic over the attributes so that state the filter gains later is saved too;
    an attribute of a type this cannot store is reported.
    """
    scalars: dict[str, Any] = {}
    arrays: dict[str, np.ndarray] = {}
    pre = getattr(flt, "_prefix", None)
    if pre is not None:
        for k, v in pre.state().items():
            arrays[_PREFIX_KEY + k] = v
    for k, v in vars(flt).items():
        if k in _FILTER_SKIP:
            continue
        if isinstance(v, np.ndarray):
            arrays[k] = v
        elif v is None or isinstance(v, (bool, str)):
            scalars[k] = v
        elif isinstance(v, (int, np.integer)):
            scalars[k] = int(v)
        elif isinstance(v, (float, np.floating)):
            scalars[k] = float(v)
        elif isinstance(v, tuple) and all(isinstance(x, np.ndarray) for x in v):
            scalars[k] = {"__tuple__": len(v)}
            for i, x in enumerate(v):
                arrays[f"{k}#{i}"] = x
        else:
            log.warning("checkpoint: filter attribute %s (%s) not saved", k, type(v).__name__)
    c = flt.counters
    scalars["__counters__"] = {k: v for k, v in vars(c).items() if k != "extra"}
    scalars["__counters_extra__"] = dict(c.extra)
    return scalars, arrays


def _restore_filter(model, psce: PsceConfig, state: dict[str, Any],
                    arrays: dict[str, np.ndarray]) -> PsceFilter:
    flt = PsceFilter(model, arrays["imu_t"], arrays["imu_w"], state["t0"], psce,
                     nominal_dt=state.get("nominal_dt"))
    prefix = {k[len(_PREFIX_KEY):]: v for k, v in arrays.items() if k.startswith(_PREFIX_KEY)}
    arrays = {k: v for k, v in arrays.items() if not k.startswith(_PREFIX_KEY)}
    if prefix and flt._prefix is not None:
        flt._prefix.load_state(prefix)
    # else: a checkpoint without the prefix (exact propagation, or an older checkpoint):
    # the filter built its prefix from the saved IMU tail, or has none if configured so
    for k, v in state.items():
        if k.startswith("__"):
            continue
        if isinstance(v, dict) and "__tuple__" in v:
            v = tuple(arrays[f"{k}#{i}"].copy() for i in range(v["__tuple__"]))
        setattr(flt, k, v)
    for k, v in arrays.items():
        if "#" not in k:
            setattr(flt, k, v.copy())
    known = {f.name for f in dataclasses.fields(FilterCounters)}
    flt.counters = FilterCounters(**{k: v for k, v in state["__counters__"].items()
                                     if k in known})
    flt.counters.extra = dict(state["__counters_extra__"])
    return flt
