"""Clock checks of the one driver (:class:`~stellar_cal_ros.methods.driver.Calibrator`).

The driver's data clock is the newest IMU stamp.  Two clocks that disagree show as:

* star frames stamped far after the newest IMU sample (the tracker's clock ahead, or the
  IMU silent): they are refused and counted (``frames_ahead``) — they could only wait in
  the buffer, and enough of them would push the good frames out;
* IMU stamps jumping back by more than the limit (a clock step): :func:`imu_jumps`;
* IMU stamps leaping ahead by more than the limit *while star frames keep arriving stamped
  inside the leap* (:func:`inside_leap`): the IMU clock jumped and the tracker's did not.
  An IMU that is merely silent for a while (a real gap) is not this: the frames of the gap
  arrive before the IMU resumes.

Numbers in, texts out; what to do with them (raise, count, flag) is the driver's.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def imu_jumps(t: np.ndarray, newest_ns: int, jump_ns: int
              ) -> tuple[tuple[int, int] | None, tuple[int, int] | None]:
    """The first leap ahead and the first jump back of an IMU block (arrival order).

    Parameters
    ----------
    t : ndarray of int64 (n,)
        The block's stamps, ns, in arrival order.
    newest_ns : int
        The newest IMU stamp received before the block.
    jump_ns : int
        A step of more than this is a jump.

    Returns
    -------
    leap, back : (int, int) or None
        ``(newest stamp before, the stamp after)`` of the first step ahead by more than
        ``jump_ns``, and of the first sample older than the newest by more than that.
    """
    if len(t) == 1:
        if abs(int(t[0]) - newest_ns) <= jump_ns:
            return None, None  # the live case
    else:
        lo, hi = int(t.min()), int(t.max())
        if lo >= newest_ns - jump_ns and hi <= newest_ns + jump_ns and hi - lo <= jump_ns:
            return None, None  # the replay case
    newest = np.maximum.accumulate(np.concatenate([[newest_ns], t]))[:-1]
    ahead = np.flatnonzero(t > newest + jump_ns)
    back = np.flatnonzero(t < newest - jump_ns)
    leap = (int(newest[ahead[0]]), int(t[ahead[0]])) if ahead.size else None
    return leap, (int(newest[back[0]]), int(t[back[0]])) if back.size else None


def inside_leap(stamp_ns: int, leap: tuple[int, int] | None, window_ns: int) -> bool:
    """True if a star frame arriving now is stamped inside the IMU's last leap ahead."""
    return leap is not None and leap[0] < stamp_ns < leap[1] - window_ns


def back_text(back: tuple[int, int], t0_ns: int | None) -> str:
    """The one line of an IMU clock jumping back."""
    newest, t = back
    return (f"/imu/data stamps jump back by {(newest - t) * 1e-9:.3f} s after "
            f"t={_rel(newest, t0_ns):.3f} s: the IMU clock jumped")


def leap_text(leap: tuple[int, int], stamp_ns: int, t0_ns: int | None) -> str:
    """The one line of an IMU clock leaping ahead past the star frames."""
    return (f"/imu/data stamps leap {(leap[1] - leap[0]) * 1e-9:.3f} s ahead after "
            f"t={_rel(leap[0], t0_ns):.3f} s while star frames go on inside that interval "
            f"(t={_rel(stamp_ns, t0_ns):.3f} s): the IMU clock jumped (or the IMU and star "
            "tracker clocks disagree)")


def ahead_text(counters: Any, lead_s: float, share: float) -> str:
    """The line about frames refused as stamped ahead of the IMU, if more than ``share``."""
    ahead, received = counters.frames_ahead, max(counters.frames_received, 1)
    if ahead <= share * received:
        return ""
    return (f"{ahead} of {counters.frames_received} star frames are stamped more than "
            f"{lead_s:g} s after the newest IMU sample (refused): an IMU outage, or star "
            "tracker and IMU clocks that disagree")


def offset_text(counts: dict[str, int], first_frame_ns: int | None, t0_ns: int | None,
                share: float = 0.5) -> str:
    """The line naming a clock offset when most star frames found no IMU data ('' if not).

    Frames refused as stamped far after the newest IMU sample (``frames_ahead``) and frames
    the filter found no IMU data for (``skipped_no_imu``: stamped before the first sample)
    count; beyond ``share`` of the frames received, the offset is the first star frame's
    stamp minus the IMU's time origin (both streams start together in a recording).

    Parameters
    ----------
    counts : dict
        The driver's and the filter's counters (``Calibrator.all_counters``).
    first_frame_ns, t0_ns : int or None
        Stamp of the first star frame received and the IMU time origin, ns.
    share : float
        Fraction of the frames that must lack IMU data.
    """
    received = max(counts.get("frames_received", 0), 1)
    lacking = counts.get("frames_ahead", 0) + counts.get("skipped_no_imu", 0)
    if lacking <= share * received or first_frame_ns is None or t0_ns is None:
        return ""
    off = (int(first_frame_ns) - int(t0_ns)) * 1e-9
    return (f"{lacking} of {received} star frames found no IMU data at their stamps: the star "
            f"tracker's stamps start {abs(off):.3f} s {'after' if off > 0 else 'before'} the "
            f"IMU's (/imu/data), the clocks are offset by about {off:+.1f} s")


def _rel(stamp_ns: int, t0_ns: int | None) -> float:
    """Seconds after the time origin (POSIX seconds before it is set)."""
    return (int(stamp_ns) - (t0_ns or 0)) * 1e-9
