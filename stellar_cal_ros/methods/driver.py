"""One driver for every filter, live and replayed: messages in, calibration out.

:class:`Calibrator` takes IMU samples (one at a time or in blocks), star frames,
temperatures, pressure and GNSS fixes in whatever order a transport or a bag delivers them,
and drives the filter of a registered filter method (:mod:`~stellar_cal_ros.methods.
registry`: PSCE, swaying-base, traditional, a user's).  The ``calibrator`` ROS node feeds it
from callbacks; :func:`stellar_cal_ros.methods.replay.replay` feeds it from a bag
read in one pass — the same code, so a live run and a replay of its recording agree.

Reorder buffer
--------------
The *data clock* is the latest IMU stamp received, ``T``.  IMU samples are released in stamp
order once ``stamp ≤ T − reorder_window_s``; star frames likewise, so messages of any topic
that arrive up to the window late (in data time) are still put in order.  A released frame
goes to the filter once the IMU *covers* its exposure (an IMU stamp later than ``t_exp +
imu_lookahead_s``) and, if an effect needs them (``Effect.requires``), once the environment
inputs have a sample at or after the frame stamp, or ``environment_wait_s`` of data time has
passed (then the last value is used: ``env_stale``).  Older messages than what was released
are dropped and counted (``imu_late``, ``frames_late``).  :meth:`Calibrator.finish`
releases everything (end of a bag).

Star frames stamped over ``max_frame_lead_s`` after the newest IMU sample are refused
(``frames_ahead``); an IMU clock that jumps (:mod:`~stellar_cal_ros.methods.clocks`) is a
:class:`~stellar_cal_ros.errors.DataError` with ``strict_clock`` (a replay); live it is
counted (``imu_clock_jumps``), and a leap past the star frames flags the result.

The relative time origin, the star cleaning, σ rules, the site and the environment are
those of :mod:`stellar_cal_ros.methods.frames`.  Memory stays bounded: the filter's IMU
history is trimmed to what it still needs, environment series to ``env_history_s``, and the
tables go to :class:`~stellar_cal_ros.methods.results.TableSink` (memory or file).
"""

from __future__ import annotations

import logging
import math
from collections import deque
from typing import Any

import numpy as np

from stellar_cal_ros.core.covariance import compiled_kernels
from stellar_cal_ros.core.types import StarFrame
from stellar_cal_ros.errors import DataError, ModelError
from stellar_cal_ros.io.calibration import Calibration
from stellar_cal_ros.methods import clocks, models, registry
from stellar_cal_ros.methods.driver_config import (
    DriverConfig,
    FrameOutcome,
    InputCounters,
)
from stellar_cal_ros.methods.frames import (
    ENV_KEYS,
    EnvSeries,
    FrameInputs,
    ImageFrames,
    SiteEstimator,
    frame_context,
    frame_contexts,
    frame_inputs,
    frame_inputs_many,
    time_origin,
)
from stellar_cal_ros.methods.imu_queue import ImuQueue, ImuRelease
from stellar_cal_ros.methods.kernel import FilterCounters, FrameUpdate
from stellar_cal_ros.methods.results import (
    RESIDUAL_COLUMNS,
    HalfWindowStats,
    RunStats,
    TableSink,
    consistency,
    derived_quantities,
    residual_block,
    residual_rows,
    result_calibration,
)
from stellar_cal_ros.sky.identify import (
    Identifier,
    any_needs_identification,
    needs_identification,
    predicted_attitude,
)

log = logging.getLogger(__name__)

class Calibrator(ImuRelease):
    """Streaming calibration with one filter method (see the module docstring).

    Parameters
    ----------
    prior : Calibration
        Prior calibration (nominal values and their sigmas).
    method : str
        A registered filter method (``psce``, ``swaying_base``, ``traditional``, ...).
    effects : list of str
        Effects estimated on top of the method's baseline (``-id`` removes an added one).
    config : KernelConfig subclass, optional
        The filter's configuration (default: the method's).
    driver : DriverConfig, optional
    frames : dict, optional
        Expected ``header.frame_id`` of the IMU (``imu``) and star (``star_tracker``)
        messages; None or an empty id accepts any.  Default: the prior's frames.
    consider : list of str
        Effects tracked as consider parameters (the diagnosis' score tests).
    residuals, history : TableSink, optional
        Where the per-star residual rows and the per-update parameter history go (default:
        in memory).
    eval_start : float, optional
        POSIX start of the evaluation window of :attr:`stats` (default: every frame).
    baseline : tuple of str, optional
        Replace the method's baseline (studies of a reduced model).
    filter_cls : type, optional
        A subclass of the method's filter to run instead.
    """

    def __init__(self, prior: Calibration, method: str = "psce",
                 effects: list[str] | None = None, config=None,
                 driver: DriverConfig | None = None, frames: dict[str, str] | None = None,
                 consider: list[str] | None = None, residuals: TableSink | None = None,
                 history: TableSink | None = None, eval_start: float | None = None,
                 baseline: tuple[str, ...] | None = None, filter_cls=None) -> None:
        self.spec = spec = registry.get(method)
        if spec.kind != "filter":
            raise ModelError(f"{method} is a {spec.kind} method, not a filter: "
                             "stellar-cal batch runs it")
        self.prior = prior
        self.method = method
        self.baseline = spec.baseline if baseline is None else tuple(baseline)
        self.effects = models.resolve_effects(method, effects, self.baseline)
        self.consider = [e for e in (consider or [])
                         if e not in self.effects and e not in self.baseline]
        # filter_cls: a variant of the method's filter (e.g. the Cramér–Rao bound recursion)
        self.filter_cls = filter_cls or spec.filter_cls
        self.config = config or spec.config_cls()
        self.driver = driver or DriverConfig()
        self.frames = dict(prior.frames if frames is None else frames)
        self.model = models.build_model(prior, method, self.effects, self.consider,
                                        self.baseline)
        self.n_consider = sum(e.size for e in self.model.effects if e.id in self.consider)
        self.requires = {r for e in self.model.effects for r in e.requires}
        #: what the estimated model itself needs (``requires`` without the consider
        #: parameters'): ``env_stale`` counts the frames released without these; a frame
        #: also waits for what the consider parameters need (their sensitivities read it),
        #: which a replay of the model would not, so that count would describe how a
        #: diagnosis groups its candidates, not the bag and the model
        self.model_requires = {r for e in self.model.effects if e.id not in self.consider
                               for r in e.requires}
        #: an effect reads the frames' site (the fixes' median so far); a method that needs a
        #: site (``needs_site``) takes it once, when its filter is built (:meth:`_start_filter`)
        self.site_read = "site" in self.requires
        if spec.needs_site:
            self.requires.add("site")
            self.model_requires.add("site")
        #: what only the consider parameters need: a frame released without it has their
        #: sensitivities computed on a stale value (:attr:`consider_stale_ns`)
        self._consider_requires = self.requires - self.model_requires
        self.window_ns = int(round(self.driver.reorder_window_s * 1e9))
        self._jump_ns = int(self.driver.clock_jump_s * 1e9)  # a jump of the IMU clock
        self.env_wait_ns = int(round(self.driver.environment_wait_s * 1e9))
        self.residuals = residuals if residuals is not None else TableSink(
            columns=RESIDUAL_COLUMNS)
        self.history = history if history is not None else TableSink()
        self.eval_start = eval_start
        # the compiled IMU block screen (core.jit.imu_block_screen), False: numpy (on first use)
        self._imu_screen: Any = None
        self._reset_state()

    # ------------------------------------------------------------------ state
    def _reset_state(self) -> None:
        self.counters = InputCounters()
        #: stamps of the frames released while an input only the consider parameters need
        #: (:attr:`_consider_requires`) did not cover them (not counted in ``env_stale``):
        #: a stamp list, so that the runs of a split screening can be joined
        self.consider_stale_ns: list[int] = []
        self.filter = None
        self.t0_ns: int | None = None
        self.nominal_dt: float | None = None
        self.imu_max_ns: int | None = None  # data clock
        self._imu = ImuQueue()
        self._last_imu_ns: int | None = None  # last released IMU stamp
        self._staged: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._staged_n = 0
        self._deferred = False  # IMU blocks queued whose release is due (_defer_release)
        self._frames_pending: list[StarFrame] = []  # sorted by stamp
        self._last_frame_ns: int | None = None  # last frame handed on
        self.env = {k: EnvSeries() for k in ENV_KEYS}
        self.faults: list[str] = []  #: why the result is degraded (clocks; one line each)
        self._imu_leap: tuple[int, int] | None = None  # (last stamp before, first after), ns
        self._first_frame_ns: int | None = None  # stamp of the first star frame received
        self.sites = SiteEstimator(self.driver.max_fixes)
        self._inputs: dict[int, Any] = {}
        self._conv: deque[tuple[np.ndarray, float, int]] = deque(
            maxlen=max(self.driver.converge_window, 1) + 1)
        self.last_update: FrameUpdate | None = None
        self.stats = HalfWindowStats() if self.driver.live_window else \
            RunStats(self.eval_start)
        self._frame_index = 0
        self._history_keys: tuple[str, ...] | None = None  # see _record_history
        self._history_sigma_index: np.ndarray | None = None
        self.identifier = None  # the star identification of unidentified frames (lazy)
        cam = self.prior.camera
        self.images = ImageFrames(size=(cam.width, cam.height))  # star images -> frames
        self._to_identify: set[int] = set()  # stamps of pending frames to identify

    def reset(self) -> None:
        """Forget everything (the prior, effects and configuration stay)."""
        self._reset_state()

    # ------------------------------------------------------------------ inputs
    def push_imu(self, stamp_ns: int, angular_velocity, linear_acceleration=None,
                 frame_id: str | None = None) -> list[FrameOutcome]:
        """One ``sensor_msgs/Imu`` sample; returns the frames this made processable."""
        return self.push_imu_block(np.array([stamp_ns], dtype=np.int64),
                                   np.array(angular_velocity, dtype=float).reshape(1, 3),
                                   None if linear_acceleration is None
                                   else np.array(linear_acceleration, dtype=float).reshape(1, 3),
                                   frame_id, owned=True)

    def push_imu_block(self, stamp_ns, angular_velocity, linear_acceleration=None,
                       frame_id: str | None = None, owned: bool = False) -> list[FrameOutcome]:
        """Several IMU samples (arrival order; stamps ns, rad/s, m/s²).

        ``owned``: the caller hands the arrays over (it never writes to them afterwards, as
        a replay's decoded blocks): the pending queue holds them without a copy.
        """
        c = self.counters
        t = np.asarray(stamp_ns, dtype=np.int64).reshape(-1)
        w = np.asarray(angular_velocity, dtype=float).reshape(-1, 3)
        f = np.zeros_like(w) if linear_acceleration is None else \
            np.asarray(linear_acceleration, dtype=float).reshape(-1, 3)
        copy = not owned
        c.imu_received += len(t)
        expected = self.frames.get("imu")
        if frame_id is not None and expected and frame_id != expected:
            c.imu_wrong_frame += len(t)
            return []
        # the checks on the whole block first (the usual case: nothing to remove), in one
        # compiled pass when the filter's kernels are compiled; else a sum is finite only
        # if every term is (one that overflows takes the exact path below), and strictly
        # increasing stamps are all positive when the first is
        m = len(t)
        screen = self._imu_screen
        if screen is None:
            jit = compiled_kernels() if self.filter_cls.compiled_step else None
            screen = self._imu_screen = jit.imu_block_screen if jit is not None else False
        if screen and m:
            inc, clean = screen(t, w, f)
        else:
            inc = m < 2 or bool((t[1:] > t[:-1]).all())
            clean = math.isfinite(w.sum() + f.sum()) and (t[0] > 0 if inc and m
                                                           else (t > 0).all())
        if not clean:
            ok = (t > 0) & np.all(np.isfinite(w), axis=1) & np.all(np.isfinite(f), axis=1)
            if not ok.all():
                c.imu_invalid += int((~ok).sum())
                t, w, f = t[ok], w[ok], f[ok]
                m = len(t)
                # strictly increasing (the usual case): first and last are the extremes
                inc = m < 2 or bool((t[1:] > t[:-1]).all())
        if m and self.imu_max_ns is not None:
            jump = self._jump_ns
            newest = self.imu_max_ns
            t_first, t_last = int(t[0]), int(t[-1])
            if not (inc and t_first >= newest - jump and t_last <= newest + jump
                    and t_last - t_first <= jump):
                leap, back = clocks.imu_jumps(t, newest, jump)
                self._imu_leap = leap or self._imu_leap
                if back:
                    c.imu_clock_jumps += 1
                    self._clock_fault(clocks.back_text(back, self.t0_ns), flag=False)
            elif self._defer_release(t, w, f, t_first, t_last, copy):
                return [] if self._staged_n + self._imu.count_upto(
                    self.imu_max_ns - self.window_ns) < self.driver.imu_batch else self._pump()
        self._settle_imu()
        last = self._last_imu_ns
        if last is not None and m and not (inc and t[0] > last):
            old = t <= last
            if old.any():
                dup = t[old] == self._last_imu_ns
                c.imu_duplicate += int(dup.sum())
                c.imu_late += int((~dup).sum())
                t, w, f = t[~old], w[~old], f[~old]
        if not len(t):
            return []
        self._imu.push(t, w, f, inc, copy)
        tmax = int(t[-1]) if inc else int(t.max())
        if self.imu_max_ns is None or tmax > self.imu_max_ns:
            self.imu_max_ns = tmax
        return self._pump()

    def _clock_fault(self, text: str, flag: bool = True) -> None:
        """DataError if ``strict_clock``, else flagged, or (stamps back: data resent?) warned."""
        if self.driver.strict_clock:
            raise DataError(text)
        if not flag:
            if self.counters.imu_clock_jumps == 1:
                log.warning("%s, or data sent again (older samples dropped as imu_late)", text)
            return
        if text not in self.faults and len(self.faults) < 20:
            log.warning("%s; the result is degraded", text)
            self.faults.append(text)

    def star_inputs(self, frames) -> list | None:
        """The filter inputs of several star messages in one call, for :meth:`push_stars`.

        What :meth:`push_stars` would compute for each (:func:`~.frames.frame_inputs`, the
        same arguments), through :func:`~.frames.frame_inputs_many`; None when that does not
        apply (each message then computes its own as it comes).
        """
        return frame_inputs_many(frames, *self._input_args(),
                                 compiled=self.filter_cls.compiled_step)

    def _input_args(self) -> tuple:
        """:func:`~.frames.frame_inputs`' ``width, height, default_sigma, noise`` of a message."""
        cam = self.prior.camera
        return cam.width, cam.height, self.config.centroid_sigma_px, self.config.noise

    def push_stars(self, frame: StarFrame, inputs: FrameInputs | None = None
                   ) -> list[FrameOutcome]:
        """One ``StarCentroidArray`` (as a :class:`StarFrame`); returns processed frames.

        A frame refused on input (wrong frame id, late, duplicate) comes back at once as a
        ``dropped_<reason>`` outcome; accepted ones come back when processed.  ``inputs``:
        the frame's filter inputs from :meth:`star_inputs` (a replay's, a batch at once);
        None: computed here.  :meth:`push_stars_many` of the one message.
        """
        return self.push_stars_many([frame], None if inputs is None else [inputs])

    def push_stars_many(self, frames: list[StarFrame], inputs: list | None = None
                        ) -> list[FrameOutcome]:
        """Several star messages in arrival order: :meth:`push_stars` of each, in turn.

        ``inputs``: their filter inputs (:meth:`star_inputs`; None, or a None in it: computed
        here).  A group whose messages need nothing but queueing (:meth:`_plain`, the one
        admission test of every path) is queued in one pass, the counters a message at a
        time gives; a group of several goes so only where a star message pumps nothing
        (:attr:`DriverConfig.batch_frames`: a replay).  Any other group goes a message at a
        time, through the special cases of the one-message group.
        """
        n = len(frames)
        inputs = [None] * n if inputs is None else list(inputs)
        c = self.counters
        stamps = [int(f.stamp_ns) for f in frames]
        refused = self._refused(stamps, [f.frame_id for f in frames])
        if n == 1 and inputs[0] is None and refused[0] is None:
            inputs[0] = frame_inputs(frames[0], *self._input_args(),
                                     compiled=self.filter_cls.compiled_step)
        pending = self._frames_pending
        if n and (n == 1 or self.driver.batch_frames) and \
                self._plain(frames, inputs, stamps, refused):
            c.frames_received += n
            self._first_frame_ns = self._first_frame_ns or stamps[0]
            pending.extend(frames)
            c.stars_sigma_unknown += sum(inp.unknown_sigma for inp in inputs)
            self._inputs.update(zip(stamps, inputs, strict=True))
            # a replay processes frames when IMU is handed over: a star message changes
            # nothing the pump would act on (what it releases depends on the IMU only)
            return [] if self.driver.batch_frames else self._pump()
        if n != 1:
            out: list[FrameOutcome] = []
            for frame, inp in zip(frames, inputs, strict=True):
                out += self.push_stars_many([frame], [inp])
            return out
        # the special cases (each one excluded by _plain)
        frame, inp, stamp, reason = frames[0], inputs[0], stamps[0], refused[0]
        c.frames_received += 1
        self._first_frame_ns = self._first_frame_ns or stamp

        def dropped(reason: str) -> list[FrameOutcome]:
            setattr(c, "frames_" + reason, getattr(c, "frames_" + reason) + 1)
            return [FrameOutcome(stamp, frame.frame_id, "dropped_" + reason)]

        if reason == "ahead" and not c.frames_ahead:
            log.warning("star frame stamped %.3f s after the newest IMU sample: refused "
                        "(counted as frames_ahead; clocks that disagree?)",
                        (stamp - self.imu_max_ns) * 1e-9)
        if reason:
            return dropped(reason)
        if self.imu_max_ns is not None and clocks.inside_leap(stamp, self._imu_leap,
                                                              self.window_ns):
            c.imu_clock_jumps += 1
            self._clock_fault(clocks.leap_text(self._imu_leap, stamp, self.t0_ns))
        if needs_identification(frame):  # identified when processed, with the IMU's hint
            self._to_identify.add(stamp)
        if self._in_order(stamps):  # the usual case
            pending.append(frame)
        else:
            stamps = np.asarray([f.stamp_ns for f in pending], dtype=np.int64)
            i = int(np.searchsorted(stamps, stamp))
            if i < len(pending) and stamps[i] == stamp:
                # the same stamp twice: keep the one with more usable stars (a garbage
                # message carrying a good frame's stamp must not shadow it)
                if len(inp.uv) <= len(self._inputs[stamp].uv):
                    return dropped("duplicate")
                c.frames_duplicate += 1
                c.frames_replaced += 1
                pending[i] = frame
                self._inputs[stamp] = inp
                return self._pump()
            c.frames_reordered += 1
            pending.insert(i, frame)
        c.stars_sigma_unknown += inp.unknown_sigma
        if inp.bad_sigma:
            if not c.stars_bad_sigma:
                log.warning("star message at %.3f: %d stars with negative or NaN sigma; the "
                            "default %.3g px is used (counted as stars_bad_sigma)",
                            stamp * 1e-9, inp.bad_sigma, self.config.centroid_sigma_px)
            c.stars_bad_sigma += inp.bad_sigma
        self._inputs[stamp] = inp
        out = []
        while len(self._frames_pending) > self.driver.max_pending_frames:
            old = self._frames_pending.pop(0)
            self._inputs.pop(int(old.stamp_ns), None)
            c.frames_overflow += 1
            self._last_frame_ns = int(old.stamp_ns)
            out.append(FrameOutcome(int(old.stamp_ns), old.frame_id, "dropped_overflow"))
        return out + ([] if self.driver.batch_frames else self._pump())

    def _plain(self, frames: list[StarFrame], inputs: list, stamps: list[int],
               refused: list[str | None]) -> bool:
        """Whether these messages, in turn, need nothing but queueing (:meth:`push_stars_many`).

        Each accepted (:meth:`_refused`), its inputs there and no σ bad, nothing to identify,
        not stamped inside an IMU clock leap; in increasing order after the frames held; and
        the frames held not overflowing.  Every path admits a message through this one test:
        a special case added to :meth:`push_stars_many` is excluded here, for a live message
        and for a replay's group alike.
        """
        leap = self._imu_leap
        return not any(refused) and self._in_order(stamps) and \
            len(self._frames_pending) + len(frames) <= self.driver.max_pending_frames and \
            all(inp is not None and not inp.bad_sigma for inp in inputs) and \
            not any_needs_identification(frames) and \
            (self.imu_max_ns is None or leap is None or
             not any(clocks.inside_leap(s, leap, self.window_ns) for s in stamps))

    def _refused(self, stamps: list[int], frame_ids: list) -> list[str | None]:
        """Why each of several star messages would be refused on input; None: accepted.

        ``wrong_frame`` (not the star tracker's frame id), ``late`` (stamp ≤ 0, or before the
        last frame handed on), ``duplicate`` (that one's stamp), ``ahead`` (after the newest
        IMU sample by more than ``max_frame_lead_s``).  Each message on its own (what the
        messages before it in a group change is placement: :meth:`_in_order`).
        """
        expected = self.frames.get("star_tracker")
        last = self._last_frame_ns
        lead = None if self.imu_max_ns is None else \
            self.imu_max_ns + int(self.driver.max_frame_lead_s * 1e9)
        out: list[str | None] = []
        for stamp, fid in zip(stamps, frame_ids, strict=True):
            if expected and fid and fid != expected:
                out.append("wrong_frame")
            elif stamp <= 0:
                out.append("late")
            elif last is not None and stamp <= last:
                out.append("duplicate" if stamp == last else "late")
            elif lead is not None and stamp > lead:
                out.append("ahead")
            else:
                out.append(None)
        return out

    def _in_order(self, stamps: list[int]) -> bool:
        """Whether messages of these stamps go, in turn, after every frame held (appended)."""
        pending = self._frames_pending
        before = int(pending[-1].stamp_ns) if pending else None
        for stamp in stamps:
            if before is not None and stamp <= before:
                return False
            before = stamp
        return True

    def push_image(self, image) -> list[FrameOutcome]:
        """One star image (:class:`~stellar_cal_ros.io.image_msgs.ImageMessage`).

        Its centroids (:class:`~stellar_cal_ros.methods.frames.ImageFrames`) go on as
        :meth:`push_stars` does, identified when processed; an unusable image comes back
        as ``dropped_bad_image`` (counted ``images_bad``).
        """
        frame = self.images(image)
        self.counters.images_received += 1
        if frame is None:
            self.counters.images_bad += 1
            return [FrameOutcome(int(image.stamp_ns), str(image.frame_id), "dropped_bad_image")]
        return self.push_stars(frame)

    def push_scalar(self, kind: str, stamp_ns: int, value: float) -> list[FrameOutcome]:
        """A temperature (°C) or pressure (Pa): ``kind`` in ``head``, ``air``, ``pressure``."""
        return self.push_scalars(kind, (stamp_ns,), (value,))

    def push_fix(self, stamp_ns: int, latitude_deg: float, longitude_deg: float,
                 altitude_m: float, status: int = 0) -> list[FrameOutcome]:
        """A ``NavSatFix``; valid ones (finite, status ≥ 0) enter the site median."""
        self.counters.fixes_received += 1
        if not self.sites.add(stamp_ns, latitude_deg, longitude_deg, altitude_m, status):
            self.counters.fixes_invalid += 1
            return []
        if self.filter is None or (self._frames_pending and self.site_read):
            return self._pump()
        return []

    def push_scalars(self, kind: str, stamp_ns, values) -> list[FrameOutcome]:
        """Several temperatures or pressures of one ``kind`` (:meth:`push_scalar`), in order.

        A sample with a stamp ≤ 0 or a non-finite value is counted (``env_invalid``) and
        dropped.  When the model needs an input, a frame may have been waiting for each
        sample (the data clock did not move): the frames are pumped after each; otherwise
        the samples go into the series at once.
        """
        if kind not in self.env:
            raise ValueError(f"unknown scalar input {kind!r} (one of {ENV_KEYS})")
        s = np.asarray(stamp_ns, dtype=np.int64).reshape(-1)
        v = np.asarray(values, dtype=float).reshape(-1)
        if len(s) != len(v):
            raise ValueError(f"{len(s)} stamps and {len(v)} values")
        ok = (s > 0) & np.isfinite(v)
        c = self.counters
        c.env_received += len(s)
        c.env_invalid += int(len(s) - np.count_nonzero(ok))
        series = self.env[kind]
        out: list[FrameOutcome] = []
        for i, (t, x, good) in enumerate(zip(s.tolist(), v.tolist(), ok.tolist(),
                                             strict=True)):
            # no frame waits for them (and, a method that needs a site, its filter runs:
            # before, each pumps as it may start it): the rest at once
            if not self.requires or (self.filter is not None and not self.scalars_read()):
                series.extend(s[i:][ok[i:]], v[i:][ok[i:]])
                break
            if good:
                series.add(t, x)
                if self._frames_pending:
                    out += self._pump()
        return out

    def push_fixes(self, stamp_ns, latitude_deg, longitude_deg, altitude_m, status
                   ) -> list[FrameOutcome]:
        """Several ``NavSatFix`` in their order: what :meth:`push_fix` does for each.

        In bulk once the filter runs and no effect reads the site (then none of them pumps;
        a method that needs a site took it when its filter was built).
        """
        if self.filter is None or self.site_read:
            out: list[FrameOutcome] = []
            for row in zip(np.asarray(stamp_ns).tolist(), np.asarray(latitude_deg).tolist(),
                           np.asarray(longitude_deg).tolist(), np.asarray(altitude_m).tolist(),
                           np.asarray(status).tolist(), strict=True):
                out += self.push_fix(*row)
            return out
        n = len(stamp_ns)
        self.counters.fixes_received += n
        self.counters.fixes_invalid += self.sites.add_many(stamp_ns, latitude_deg,
                                                           longitude_deg, altitude_m, status)
        return []

    def run_checks(self) -> None:
        """Run the checks :attr:`DriverConfig.defer_checks` left due.

        The gyro judgement and the filter's covariance health check
        (``StarFilter.run_checks``).  May raise :class:`~stellar_cal_ros.errors.DataError`
        as a frame's update would have.
        """
        if self.filter is not None:
            self.filter.run_checks()

    def finish(self) -> list[FrameOutcome]:
        """End of input: release and process everything still held; close the tables."""
        out = self._pump(final=True)
        if self.filter is not None:
            self.filter.check_covariance_due()  # deferred (defer_checks): as a replay's
            self.filter.finish_checks()  # the gyro watch's last judgement
        return out

    def close(self) -> None:
        """Close the table sinks (files)."""
        self.residuals.close()
        self.history.close()

    @property
    def site(self):
        """Median of the valid fixes so far."""
        return self.sites.site

    # ------------------------------------------------------------------ pumping
    def _start_filter(self, final: bool) -> bool:
        if self.filter is not None:
            return True
        if not self._staged_n or (self._staged_n < self.driver.t0_imu_samples and not final):
            return False
        if self.spec.needs_site and self.site is None:
            return False
        t = np.concatenate([s[0] for s in self._staged])
        if len(t) < 2:
            return False
        self.t0_ns, self.nominal_dt = time_origin(t, self.driver.t0_imu_samples)
        self._build_filter()
        return True

    def _build_filter(self) -> None:
        """The filter for the known time origin (and site)."""
        if self.spec.needs_site:
            self.filter = self.filter_cls(self.model, self.t0_ns * 1e-9, self.site, self.config,
                                          nominal_dt=self.nominal_dt, consider=self.n_consider)
        else:
            self.filter = self.filter_cls(self.model, self.t0_ns * 1e-9, self.config,
                                          nominal_dt=self.nominal_dt, consider=self.n_consider)
        if self.driver.defer_checks:
            self.filter.defer_checks()

    def _env_ready(self, stamp_ns: int, final: bool) -> tuple[bool, bool]:
        """(ready, stale) of the environment inputs the model needs for a frame.

        Ready once every input of :attr:`requires` (the consider parameters' too) covers
        the frame, or after ``environment_wait_s``; stale when one of the *model's*
        (:attr:`model_requires`) still does not then.  A frame that waits longer for a
        consider parameter's input is released no earlier than without it, and only ever
        by the same timeout when the model's input is missing: the count is the one a
        run of the model alone makes.
        """
        if not self.requires:
            return True, False
        if not self._env_missing(stamp_ns, self.requires):
            return True, False
        if final or self.imu_max_ns - self.window_ns >= stamp_ns + self.env_wait_ns:
            return True, self._env_missing(stamp_ns, self.model_requires)
        return False, False

    def _env_missing(self, stamp_ns: int, requires: set[str]) -> bool:
        """Whether an input of ``requires`` does not cover ``stamp_ns`` yet."""
        need = []
        if "head_temperature" in requires:
            need.append(self.env["head"])
        if "weather" in requires:
            need += [self.env["air"], self.env["pressure"]]
        return any(not s.covers(stamp_ns) for s in need) or \
            ("site" in requires and self.site is None)

    def _pump(self, final: bool = False) -> list[FrameOutcome]:
        """Release what the data clock allows and process the frames that are ready."""
        out: list[FrameOutcome] = []
        if self.imu_max_ns is None:
            if final:
                for fr in self._frames_pending:
                    out.append(FrameOutcome(int(fr.stamp_ns), fr.frame_id, "skipped_no_imu"))
                self._frames_pending.clear()
            return out
        self._release_imu(final)
        if not self._start_filter(final):
            if final:
                reason = "no_site" if self._staged_n >= 2 else "no_imu"
                for fr in self._frames_pending:
                    if reason == "no_site":
                        self.counters.frames_no_site += 1
                    out.append(FrameOutcome(int(fr.stamp_ns), fr.frame_id, "skipped_" + reason))
                self._frames_pending.clear()
            return out
        # IMU goes to the filter in batches (one vectorized extension instead of one per
        # message), and at once when a frame is ready to be processed
        if final or self._staged_n >= self.driver.imu_batch:
            self._flush_staged()
        elif self.driver.batch_frames:
            return out
        elif self._staged_n >= self.driver.imu_flush_live:
            self._flush_staged()
        limit = None if final else self.imu_max_ns - self.window_ns
        lookahead = self.driver.imu_lookahead_s
        imu_end = self._imu_end_rel()
        n_pending = len(self._frames_pending)
        # a frame's exposure shift when every frame has the same (no time effect: the prior's;
        # a time effect held as a consider parameter: its value; no context needed)
        flt = self.filter
        fixed_shift = self.model.fixed_exposure_shift(flt.theta, flt.P_est)
        moving = fixed_shift is None
        # a replay's ready frames go to the filter together (one compiled call steps a run of
        # them: StarFilter.prepare_frames), also when the shift moves with the estimate (an
        # estimated time offset) and the filter's call follows it: a frame is then ready by
        # the state its turn finds, which the run checks (_process_run), and those the run
        # leaves stay pending; identification needs the filter's attitude: the frames before
        # it go first
        run: list | None = [] if self.driver.batch_frames and (
            not moving or flt.batches_moving_shift()) else None
        ready = (imu_end, lookahead) if moving and not final else None
        env_keys = self._env_keys()
        pending = self._frames_pending
        i = 0  # the frames pending[:i] are in run (popped as they are processed)
        if run is not None and not moving and not final and not self.requires and \
                not self._to_identify:
            # a replay's usual pump (one shift, nothing to wait for but the IMU, nothing to
            # identify): the loop below on every frame at once, up to the first that waits
            i = len(pending)
            stamps = np.fromiter((f.stamp_ns for f in pending), dtype=np.int64, count=i)
            inps = [self._inputs[s] for s in stamps.tolist()]
            stars = np.fromiter((len(inp.uv) for inp in inps), dtype=np.int64, count=i)
            wait = (stamps > limit) | ((stars > 0) & self._uncovered(
                stamps, fixed_shift, imu_end, lookahead))
            if wait.any():
                i = int(np.argmax(wait))
            if i and self._staged:
                self._flush_staged()
            use = np.flatnonzero(stars[:i]).tolist()  # (a frame without stars: None)
            ctxs = dict(zip(use, frame_contexts(stamps[use].tolist(), [inps[j] for j in use],
                                                self.site, self.env, env_keys), strict=True))
            run += [(fr, inp, ctxs.get(j), False)
                    for j, (fr, inp) in enumerate(zip(pending[:i], inps[:i], strict=True))]
            i = len(pending)  # (the loop below would stop at the frame that waits)
        while i < len(pending):
            fr = pending[i]
            stamp = int(fr.stamp_ns)
            if limit is not None and stamp > limit:
                break
            inp = self._inputs[stamp]
            ok, stale = self._env_ready(stamp, final)
            if not ok:
                break
            ctx = False  # (the frame's context, once: a moving shift reads it too)
            if not final and (len(inp.uv) or stamp in self._to_identify):
                # (a moving shift by the state before the run: the run checks it again)
                if moving and stamp not in self._to_identify:
                    ctx = frame_context(stamp, inp, self.site, self.env, env_keys)
                shift = self._time_shift(stamp, inp, ctx) if moving else fixed_shift
                if self._uncovered(stamp, shift, imu_end, lookahead):
                    if run and moving and self._run_out(run, out, fixed_shift, ready):
                        i = 0  # the run's updates moved the shift: this frame again
                        continue
                    break  # the IMU does not cover the exposure yet
            if self._staged:
                self._flush_staged()
            if stamp in self._to_identify:
                if run:  # the frames before it first, then this one again
                    i = 0
                    if self._run_out(run, out, fixed_shift, ready):
                        continue
                    break
                self._to_identify.discard(stamp)
                fr, inp = self._identify(fr, inp, stamp)
            if ctx is False:
                ctx = frame_context(stamp, inp, self.site, self.env, env_keys) \
                    if len(inp.uv) else None
            if run is None:
                self._released([stale])
                out.append(self._process(fr, inp, ctx))
            else:
                run.append((fr, inp, ctx, stale))
                i += 1
        if run:
            self._run_out(run, out, fixed_shift, ready)
        if len(pending) < n_pending:
            self._trim()
        return out

    def _uncovered(self, stamp, shift: float, imu_end: float, lookahead: float):
        """Whether the IMU released does not cover a frame's exposure yet (waits).

        ``stamp``: its stamp, ns (an int64 array: each frame's); ``shift``: its exposure
        shift (:meth:`_time_shift`), ``imu_end`` (:meth:`_imu_end_rel`) and ``lookahead``
        (s): the IMU must reach ``lookahead`` past the exposure.
        """
        return imu_end <= (stamp - self.t0_ns) * 1e-9 + shift + lookahead

    def _released(self, stale: list[bool]) -> None:
        """The first ``len(stale)`` pending frames go to the filter: popped, their inputs count.

        ``stale``: each one's (:meth:`_env_ready`).
        """
        k = len(stale)
        gone = self._frames_pending[:k]
        del self._frames_pending[:k]
        inputs = self._inputs
        consider = self._consider_requires
        for fr, old in zip(gone, stale, strict=True):
            stamp = int(fr.stamp_ns)
            inputs.pop(stamp, None)
            if old:
                self.counters.env_stale += 1
            elif consider and self._env_missing(stamp, consider):
                self.consider_stale_ns.append(stamp)
        if k:
            self._last_frame_ns = int(gone[-1].stamp_ns)

    def _run_out(self, run: list, out: list, shift: float | None,
                 ready: tuple[float, float] | None) -> bool:
        """Process ``run``, the leading pending frames, and release those processed.

        :meth:`_process_run`; ``run`` is emptied.  False when frames of it were left pending
        (not ready under the state their turn found).
        """
        k = self._process_run(run, out, shift, ready)
        self._released([stale for _, _, _, stale in run[:k]])
        left = k < len(run)
        run.clear()
        return not left

    def _process_run(self, run: list, out: list, shift: float | None,
                     ready: tuple[float, float] | None) -> int:
        """:meth:`_process` of the leading ready frames of ``run``; returns how many.

        ``run``: a replay's (frame, inputs, context, stale) in order; the outcomes are
        appended to ``out``.
        The filter first steps the frames it can in one compiled call
        (:meth:`~stellar_cal_ros.methods.kernel.StarFilter.prepare_frames`, given the fixed
        exposure ``shift``, None: it moves).  ``ready = (imu_end, lookahead)``: a frame is
        ready only when its exposure time under the state its turn finds is covered
        (``imu_end > t_exp + lookahead``: the driver's test for one frame); the run stops
        before the first frame that is not.  None: every frame of the run is ready.
        """
        flt = self.filter
        frames = [(inp.uv, inp.u_i, ctx, inp.sigma, (fr.stamp_ns - self.t0_ns) * 1e-9,
                   self._accumulates(fr.stamp_ns)) for fr, inp, ctx, _ in run]
        i = 0
        while i < len(run):  # a run ends at a covariance check, a reference rebuild, ...
            if ready is not None and i and len(run[i][1].uv):
                fr, inp = run[i][:2]
                t_exp = frames[i][4] + self._time_shift(int(fr.stamp_ns), inp, run[i][2])
                if ready[0] <= t_exp + ready[1]:
                    break
            # (a method's batch may hold one frame: SwayingFilter.prepare_frames)
            stepped = flt.prepare_frames(frames[i:], shift, ready)
            done = self._commit_batch(run[i:i + stepped], out) if stepped else 0
            for fr, inp, ctx, _ in run[i + done:i + max(stepped, 1)]:
                out.append(self._process(fr, inp, ctx))
            i += max(stepped, 1)
        flt.prepare_frames([])  # (what is left of a batch, dropped: a workspace)
        return i

    def _commit_batch(self, part: list, out: list) -> int:
        """The leading frames of ``part`` (a batch the filter stepped) committed at once.

        What :meth:`_process` does frame by frame — the filter's bookkeeping
        (:meth:`~stellar_cal_ros.methods.kernel.StarFilter.commit_batch`), convergence
        window, residual rows, statistics (:meth:`~.results.RunStats.add_block`), history rows
        (:meth:`~.results.TableSink.append_rows`) and outcomes — for the leading frames whose
        stars are all valid and which updated; ``FrameUpdate`` objects only for a consumer
        (the residual table, statistics other than :class:`~.results.RunStats`, outcomes with
        :attr:`DriverConfig.frame_updates`; the last frame's is :attr:`last_update`).
        Returns the frames done (appended to ``out``); the rest go frame by frame.
        """
        flt = self.filter
        ref = getattr(flt, "reference_history", None)
        if ref is not None and type(self.stats) is not RunStats:
            return 0  # (a method's other measurements go into the statistics frame by frame)
        q = 0
        for _, inp, _, _ in part:  # (process_frame re-checks a frame's stars otherwise)
            if not inp.valid:
                break
            q += 1
        b = flt.commit_batch(q) if q else None
        if b is None:
            return 0
        k = b.count
        part = part[:k]
        if ref and ref["t"]:  # the method's other measurements (sums of their own, in order)
            for t, nis in zip(ref["t"], ref["nis"], strict=True):
                self.stats.add_reference(t, nis, 3)
            for v in ref.values():
                v.clear()
        fc = flt.counters
        fc.stars_invalid += sum(len(inp.ok) - len(inp.uv) for _, inp, _, _ in part)
        index0 = self._frame_index
        self._frame_index += k
        nis = b.nis.tolist()
        sig_t = b.sigma[:, flt.it]
        for i in range(max(0, k - (self._conv.maxlen or k)), k):
            self._conv.append((sig_t[i], nis[i], b.dof[i]))
        keep = self.driver.frame_updates
        stats = self.stats if type(self.stats) is RunStats else None
        upds = [b.update(i) for i in range(k)] if keep or stats is None else None
        self.last_update = upds[-1] if upds else b.update(k - 1)
        if not self.residuals.discard:  # (the frames' rows in one chunk, cut as a frame each)
            uv, accepted, uv_pred, S, nis_stars, dirs, omega = b.star_rows(k)
            self.residuals.append(residual_block(
                b.stamps, b.n, index0, uv, uv_pred, S, nis_stars, accepted, dirs, omega,
                np.concatenate([inp.catalog_id for _, inp, _, _ in part]),
                np.concatenate([inp.magnitude for _, inp, _, _ in part]),
                [ctx.head_temperature_c for _, _, ctx, _ in part]), np.cumsum(b.n).tolist())
        if stats is None:
            for u in upds:
                self.stats.add(u)
        else:
            stats.add_block(b.stamps, b.n, b.nis, b.dof, b.sums)
        if not self.history.discard:
            keys = self._history_layout(b.sigma[0])
            heads = [[float(t), x, d, a, m - a, int(it)] for t, x, d, a, m, it in zip(
                b.stamps, nis, b.dof, b.n_acc, b.n, b.iterations.tolist(), strict=True)]
            self.history.append_rows(keys, heads, (b.theta, b.sigma),
                                     self._history_sigma_index)
        for i, (fr, inp, ctx, _) in enumerate(part):
            out.append(FrameOutcome(int(fr.stamp_ns), fr.frame_id, "updated",
                                    upds[i] if keep else None, inp.catalog_id, inp.magnitude,
                                    ctx.head_temperature_c))
        return k

    def _accumulates(self, stamp_ns: int) -> bool:
        """Whether a frame's score and information enter the sensitivity (evaluation window)."""
        return self.eval_start is None or stamp_ns * 1e-9 >= self.eval_start

    def scalars_read(self) -> bool:
        """Whether the model or the method reads the temperature or pressure messages.

        :attr:`requires` holds ``head_temperature`` or ``weather``: a frame waits for them
        (:meth:`push_scalars`; a replay's :func:`~.replay._env_unread` asks it too).
        """
        return bool(self.requires & {"head_temperature", "weather"})

    def _env_keys(self) -> tuple[str, ...]:
        """The environment inputs a frame's context needs.

        The model's, and the head temperature of the residual table when it is kept.
        """
        keys = ("head",) if "head_temperature" in self.requires or \
            not self.residuals.discard else ()
        return keys + (("air", "pressure") if "weather" in self.requires else ())

    def _identify(self, frame: StarFrame, inp, stamp: int):
        """Identify a frame's unidentified centroids (:mod:`stellar_cal_ros.sky.identify`).

        Lost-in-space until the filter has an attitude; then tracking with the attitude the
        filter predicts for the exposure (its last attitude carried by the IMU rates held), and
        lost-in-space again when tracking fails.
        """
        flt = self.filter
        hint, unc = None, None
        ctx = frame_context(stamp, inp, self.site, self.env)
        theta = flt.theta if flt is not None else self.model.initial_value
        camera = self.model.camera_at(theta, ctx)
        if self.identifier is None:
            self.identifier = Identifier(camera)
        self.identifier.set_camera(camera)
        if flt is not None and flt.initialized:
            t_exp = (stamp - self.t0_ns) * 1e-9 + self._time_shift(stamp, inp)
            R_imu_st, _ = self.model.installation_at(theta, ctx)
            hint = predicted_attitude(flt.R_i_b, flt.t, t_exp, flt.imu.t, flt.imu.w) @ R_imu_st
            var = np.linalg.eigvalsh(flt.P[flt.ia, flt.ia]).max()
            unc = float(np.clip(np.degrees(5.0 * math.sqrt(max(var, 0.0))), 0.05, 2.0))
        frame, _ = self.identifier.identify_frame(frame, hint, hint_uncertainty_deg=unc)
        return frame, frame_inputs(frame, *self._input_args())

    def _time_shift(self, stamp: int, inp, ctx=False) -> float:
        """Seconds from a frame's stamp to its modelled exposure (current θ).

        ``ctx``: the frame's context when the caller has built it (the one its update
        gets); otherwise (False) it is built here if a time effect reads it.
        """
        return self.model.exposure_shift(
            self.filter.theta, lambda: frame_context(stamp, inp, self.site, self.env)
            if ctx is False else ctx)

    def _imu_end_rel(self) -> float:
        """Relative stamp of the newest IMU sample released (staged or in the filter)."""
        if self._staged:
            return (int(self._staged[-1][0][-1]) - self.t0_ns) * 1e-9
        return self.filter.imu.t_end

    def _process(self, frame: StarFrame, inp, ctx) -> FrameOutcome:
        flt = self.filter
        fc = flt.counters
        before = (dict(vars(fc)), dict(fc.extra))  # what changes names a skip
        if ctx is None:  # no usable star: counted as the replay always did
            fc.frames += 1
            fc.skipped_few_stars += 1
            fc.stars_invalid += len(inp.ok)
            return FrameOutcome(int(frame.stamp_ns), frame.frame_id, "skipped_few_stars")
        fc.stars_invalid += len(inp.ok) - len(inp.uv)
        if flt.sensitivity is not None:  # score and information over the evaluation window
            flt.sensitivity.accumulate = self._accumulates(frame.stamp_ns)
        upd = flt.process_frame(inp.uv, inp.u_i, ctx, inp.sigma,
                                t_rel=(frame.stamp_ns - self.t0_ns) * 1e-9, valid=inp.valid)
        ref = getattr(flt, "reference_history", None)
        if ref and ref["t"]:  # the method's other measurements: into the statistics, then gone
            for t, nis in zip(ref["t"], ref["nis"], strict=True):
                self.stats.add_reference(t, nis, 3)
            for v in ref.values():
                v.clear()
        index = self._frame_index
        self._frame_index += 1
        sigma = None
        if upd is not None and math.isfinite(upd.nis):
            status = "updated"
            sigma = flt.sigma()
            self._conv.append((sigma[flt.it], float(upd.nis), int(upd.dof)))
        else:
            after = fc.as_dict()
            old = dict(before[0], **before[1])
            changed = [k for k in after if after[k] != old.get(k, 0)
                       and k not in ("frames", "stars_invalid", "stars_gated", "extra")]
            if "init_frames" in changed:
                status = "initialized"
            elif "reinitializations" in changed:
                status = "reacquired"
            else:
                status = next((k for k in changed if k.startswith("skipped")), "skipped")
        if upd is not None:
            self.last_update = upd
            if not self.residuals.discard:
                self.residuals.append(residual_rows(upd, index, inp.catalog_id,
                                                    inp.magnitude, ctx.head_temperature_c))
            self.stats.add(upd)
            if sigma is not None and not self.history.discard:
                self._record_history(upd, sigma)
        return FrameOutcome(int(frame.stamp_ns), frame.frame_id, status, upd,
                            inp.catalog_id, inp.magnitude, ctx.head_temperature_c)

    def _record_history(self, upd: FrameUpdate, s: np.ndarray) -> None:
        """One history row: the update and the state after it (``s``: its 1-σ)."""
        n_acc = int(np.count_nonzero(upd.accepted))
        keys = self._history_layout(s)
        # the parameters and σ gathered by the sink for a block of rows at once
        self.history.append_row(keys, [float(upd.stamp), float(upd.nis), int(upd.dof), n_acc,
                                       len(upd.accepted) - n_acc, int(upd.iterations)],
                                (self.filter.theta_estimated(), s), self._history_sigma_index)

    def _history_layout(self, s: np.ndarray) -> tuple[str, ...]:
        """The history's columns (and, once, the index of their θ and σ cells)."""
        flt = self.filter
        keys = self._history_keys
        if keys is None:
            keys = ["t", "nis", "dof", "stars", "gated", "iterations"]
            for name in self.parameter_names():
                keys += [name, "sigma." + name]
            keys += [f"sigma.attitude.{ax}" for ax in "xyz"]
            for name in flt._nav_blocks:
                keys += [f"sigma.{name}.{ax}" for ax in "xyz"]
            self._history_keys = keys = tuple(keys)
            # the row's values from [θ_estimated, σ]: each parameter then its σ, then the σ
            # of attitude and navigation blocks
            n_th = len(flt.theta_estimated())
            index = np.arange(len(s))
            nav = [index[flt.layout.sl(name)] for name in flt._nav_blocks]
            pairs = np.empty(2 * n_th, dtype=np.intp)
            pairs[0::2] = np.arange(n_th)
            pairs[1::2] = n_th + index[flt.it]
            self._history_sigma_index = np.concatenate(
                [pairs, n_th + index[flt.ia]] + [n_th + i for i in nav]).astype(np.intp)
        return keys

    def _trim(self, least: int = 4096) -> None:
        """Drop IMU samples and environment data the filter can no longer need.

        The samples go once more than ``least`` of them are not needed (amortizes the copy;
        a checkpoint drops them all, ``least=0``: dropping changes no float).
        """
        flt = self.filter
        if flt is None:
            return
        if flt.initialized:
            cut = flt._k - 2
        elif self._last_frame_ns is not None:
            # before initialization the next frame is not older than the last one handed on
            # (up to the largest time shift it could have): keep 1 s more than that
            t_keep = (self._last_frame_ns - self.t0_ns) * 1e-9 - 1.0
            cut = flt.imu.index(t_keep) - 2
        else:
            cut = 0
        if cut > least:
            flt.drop_imu(cut)
        if self._last_frame_ns is not None:
            before = self._last_frame_ns - int(self.driver.env_history_s * 1e9)
            for s in self.env.values():
                s.trim(before)

    # ------------------------------------------------------------------ outputs
    @property
    def initialized(self) -> bool:
        """True once a star frame has initialized the attitude."""
        return self.filter is not None and self.filter.initialized

    def parameter_names(self) -> list[str]:
        """``effect.parameter`` names of the estimated θ."""
        n = self.model.size - self.n_consider
        return self.model.parameter_names()[:n]

    def state(self) -> tuple[np.ndarray, np.ndarray]:
        """Current estimated θ and its 1-sigma."""
        n = self.model.size - self.n_consider
        if self.filter is None:
            return self.model.initial_value[:n].copy(), self.model.initial_sigma[:n].copy()
        return self.filter.theta_estimated().copy(), self.filter.sigma()[self.filter.it]

    def covariance(self) -> np.ndarray:
        """Covariance of the estimated θ."""
        if self.filter is None:
            return np.diag(self.state()[1] ** 2)
        return self.filter.P[self.filter.it, self.filter.it].copy()

    def named_covariance(self) -> tuple[list[str], np.ndarray]:
        """``(names, P_θθ)`` of the estimated parameters (the result's covariance sidecar)."""
        return self.parameter_names(), self.covariance()

    def stamp(self) -> float:
        """POSIX time of the current estimate (the filter's time, else the prior's)."""
        if self.filter is not None and self.filter.t is not None:
            return self.filter.t0 + self.filter.t
        return self.prior.stamp

    def calibration(self) -> Calibration:
        """Current calibration: estimates, σ, derived quantities, consistency."""
        theta, sigma = self.state()
        full = self.model.initial_value.copy()
        full[:len(theta)] = theta
        sig_full = np.concatenate([sigma, np.zeros(self.n_consider)])
        cal = result_calibration(self.prior, self.model, full, sig_full, self.method,
                                 self.stamp(), estimated=len(theta))
        cal.extra["derived"] = derived_quantities(self.model, full, self.covariance())
        noise = getattr(self.config, "noise", None)
        cal.extra["consistency"] = consistency(self.stats.current(), noise)
        # whether the run used the stated noise or measured scales of it (issue 21)
        cal.extra["consistency"]["noise_rescaled"] = bool(noise is not None
                                                          and not noise.identity)
        if noise is not None and not noise.identity:
            cal.extra["consistency"]["noise"] = noise.as_dict()
        reasons = self.degraded()
        if reasons:
            cal.extra["data_quality"] = {"degraded": True, "reasons": reasons}
        if self.identifier is not None:  # the result says how its stars were identified
            cal.extra["identification"] = self.identifier.counters.as_dict()
        return cal

    def degraded(self) -> list[str]:
        """Why the result is not to be trusted (one line each; empty: nothing known).

        Clock faults (:attr:`faults`), the filter's (a gyro that disagrees with the stars,
        found late), and more than 10 % of the star frames refused as stamped far ahead of
        the IMU.
        """
        out = list(self.faults) + (list(self.filter.data_faults) if self.filter else [])
        ahead = clocks.ahead_text(self.counters, self.driver.max_frame_lead_s, 0.1)
        return out + [ahead] if ahead else out

    def filter_counters(self) -> dict[str, int]:
        """Counters of the filter (zeros before it starts), ``extra`` flattened."""
        fc = self.filter.counters if self.filter is not None else FilterCounters()
        out = fc.as_dict()
        if self.filter is not None:
            out.update({k: v for k, v in self.filter.imu.counters.items()})
        return out

    def all_counters(self) -> dict[str, Any]:
        """Input and filter counters together (and the identification's, if it ran)."""
        out = dict(vars(self.counters))
        out.update(self.filter_counters())
        if self.identifier is not None:
            out.update({"identify_" + k: v
                        for k, v in self.identifier.counters.as_dict().items()})
        return out

    def convergence(self) -> dict[str, Any]:
        """The convergence test: enough updates, σ settled, NIS consistent."""
        hist = list(self._conv)
        n = self.driver.converge_window
        res = {"converged": False, "updates": self.filter.counters.updates if self.filter else 0,
               "sigma_ratio_min": float("nan"), "nis_ratio": float("nan")}
        if len(hist) < n + 1 or n < 1:
            return res
        s_old, s_new = hist[0][0], hist[-1][0]
        ratio = float(np.min(s_new / np.maximum(s_old, 1e-300)))
        nis = sum(h[1] for h in hist[1:]) / max(sum(h[2] for h in hist[1:]), 1)
        res.update(sigma_ratio_min=ratio, nis_ratio=float(nis),
                   converged=bool(ratio >= self.driver.converge_sigma_ratio
                                  and nis <= self.driver.converge_nis_ratio))
        return res

    def pending(self) -> dict[str, int]:
        """Messages held in the buffers."""
        return {"imu": self._imu.n + self._staged_n, "frames": len(self._frames_pending)}

    def require_initialized(self) -> None:
        """Raise why no frame could start the filter (DataError: offset clocks)."""
        if self.initialized:
            return
        counts = {k: v for k, v in self.all_counters().items() if v}
        why = clocks.offset_text(counts, self._first_frame_ns, self.t0_ns)
        raise (DataError if why else ModelError)(
            f"no star frame could initialize the attitude{': ' + why if why else ''}"
            f" (counters: {counts})")
