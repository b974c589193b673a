"""The streaming driver's settings and records.

:class:`DriverConfig` (buffering, memory, convergence), :class:`InputCounters` (what came in
and what was refused, counted) and :class:`FrameOutcome` (what happened to one star frame).

Split from :mod:`stellar_cal_ros.methods.driver`, which re-exports them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from stellar_cal_ros.methods.frames import T0_IMU_SAMPLES
from stellar_cal_ros.methods.kernel import FrameUpdate

__all__ = ["DriverConfig", "FrameOutcome", "InputCounters"]


@dataclass
class DriverConfig:
    """Buffering, memory and convergence settings of :class:`Calibrator`."""

    reorder_window_s: float = 0.05  #: data-time window within which messages may be reordered
    environment_wait_s: float = 2.0  #: max data time a frame waits for needed temperatures etc.
    imu_lookahead_s: float = 0.0  #: IMU held beyond a frame before it is processed
    t0_imu_samples: int = T0_IMU_SAMPLES  #: IMU samples whose median interval sets t0
    max_pending_frames: int = 200  #: held frames beyond this drop the oldest (counted)
    max_pending_imu: int = 100_000  #: held IMU samples beyond this release the oldest
    env_history_s: float = 600.0  #: environment samples older than this before a frame: dropped
    max_fixes: int = 100_000  #: fixes kept for the site median
    imu_batch: int = 4096  #: released IMU samples handed to the filter in batches of this size
    #: process frames only when a batch of IMU is handed over (replay: throughput); False:
    #: as soon as the IMU covers them (live: latency)
    batch_frames: bool = False
    #: live (``batch_frames`` False): staged IMU goes to the filter once this many samples
    #: are held, so a frame finds its IMU already integrated (the per-sample work stays in
    #: the IMU callbacks, off the frame's path; the result does not depend on the split)
    imu_flush_live: int = 8
    max_frame_lead_s: float = 10.0  #: frames stamped this far after the newest IMU: refused
    clock_jump_s: float = 10.0  #: IMU stamps jumping back (or leaping ahead) by more: a clock
    strict_clock: bool = False  #: a clock jump raises DataError (replay) instead of a flag
    converge_window: int = 20  #: updates over which convergence is judged
    converge_sigma_ratio: float = 0.98  #: every σ(now)/σ(window ago) above this: settled
    converge_nis_ratio: float = 2.0  #: mean NIS/dof over the window below this: consistent
    #: judge consistency on the second half of the data seen so far (the live node: no end
    #: is known; :class:`~.results.HalfWindowStats`) instead of a window fixed in advance
    live_window: bool = False
    #: the filter's gyro-against-stars judgement waits for :meth:`Calibrator.run_checks`
    #: (the live node calls it between frames) instead of running in a frame's update
    defer_checks: bool = False
    #: the outcomes of frames a replay's batch committed at once carry their
    #: :class:`~stellar_cal_ros.methods.kernel.FrameUpdate` (False: None there, and none is
    #: made unless the residual table or the statistics need it; ``Calibrator.last_update``
    #: is kept either way)
    frame_updates: bool = True


@dataclass
class InputCounters:
    """Input-level counts (the filter's own are in :class:`FilterCounters`)."""

    imu_received: int = 0
    imu_invalid: int = 0  # non-finite values or stamps (their intervals are bridged)
    imu_late: int = 0  # older than the released IMU (beyond the reorder window)
    imu_duplicate: int = 0  # same stamp as an already released sample
    imu_wrong_frame: int = 0
    imu_clock_jumps: int = 0  # IMU stamps jumping back, or leaping ahead past star frames
    frames_received: int = 0
    frames_reordered: int = 0  # arrived after a frame with a later stamp (put in order)
    frames_late: int = 0
    frames_duplicate: int = 0
    frames_overflow: int = 0
    frames_wrong_frame: int = 0
    frames_no_site: int = 0
    frames_ahead: int = 0  # stamped more than max_frame_lead_s after the newest IMU sample
    frames_replaced: int = 0  # a pending frame with the same stamp and fewer usable stars
    stars_bad_sigma: int = 0  # negative or NaN σ in the message: the default σ was used
    stars_sigma_unknown: int = 0  # σ = 0 ("unknown") in the message: default or measured σ
    env_received: int = 0
    env_invalid: int = 0
    env_stale: int = 0
    fixes_received: int = 0
    fixes_invalid: int = 0
    images_received: int = 0  # star images (a bag of images): made into frames
    images_bad: int = 0  # images whose content is unusable (encoding, size): skipped


@dataclass
class FrameOutcome:
    """What happened to one star frame."""

    stamp_ns: int
    frame_id: str
    status: str  # updated | initialized | skipped_<reason> | dropped_<reason>
    update: FrameUpdate | None = None
    catalog_id: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    magnitude: np.ndarray = field(default_factory=lambda: np.zeros(0))
    head_temperature: float = float("nan")
