"""Where a replay's CPU goes: exclusive CPU time of the driver's and filter's parts (issue 24.1).

Usage::

    python benchmarks/replay_profile.py BAG.mcap [--prior PRIOR.yaml] [--method psce]

Runs ``stellar-cal replay BAG --method M --prior PRIOR -o TMP -q`` in this process (what the
CLI does: the history CSV is written) with ``time.process_time`` around the functions of
the per-message path, and prints for each its calls, inclusive and exclusive CPU seconds
(exclusive: without the timed functions it calls) and exclusive µs per call — the replay's
reading (its events generator) a row too, a call an event; then the reading alone (every
message as an event, no quiet merge, nothing fed) in the same process.  The timers cost about
1 µs a call (≈ 0.5 CPU-s on the 2-h bag of ``psce_speed.py``).  Use it with
``psce_speed.py``, which times whole processes against rosbags.
"""

from __future__ import annotations

import argparse
import functools
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

from stellar_cal_ros import cli
from stellar_cal_ros.core import gyro_check
from stellar_cal_ros.io.bag import BagReader
from stellar_cal_ros.methods import driver, frame_step, imu_queue, kernel, results, star_chain
from stellar_cal_ros.methods import replay as replay_mod

# (owner, attribute, label): the per-message path of a replay
TIMED = [
    *[(driver.Calibrator, n, "Calibrator." + n) for n in (
        "push_imu_block", "push_stars", "push_stars_many", "push_scalar", "push_fix",
        "push_scalars", "push_fixes",
        "_pump", "_process",
        "_record_history", "_trim", "_flush_staged", "_defer_release", "_release_imu",
        "_process_run", "_commit_batch")],
    (driver, "frame_inputs", "frame_inputs"), (driver, "frame_context", "frame_context"),
    (driver, "frame_inputs_many", "frame_inputs_many"),
    *[(kernel.StarFilter, n, "StarFilter." + n) for n in (
        "process_frame", "update", "_fused_update", "extend_imu", "_watch_gyro", "sigma",
        "_gated", "_updated", "prepare_frames", "commit_batch")],
    (frame_step.FusedStep, "call", "FusedStep.call"),
    (frame_step.FusedStep, "batch", "FusedStep.batch"),
    (frame_step, "frame_steps", "frame_steps (compiled)"),
    (frame_step.FrameBatch, "take", "FrameBatch.take"),
    (frame_step.BatchCommit, "__init__", "BatchCommit"),
    (gyro_check, "watch_frames", "gyro_check.watch_frames"),
    (results.TableSink, "append_rows", "TableSink.append_rows"),
    (results.RunStats, "add_block", "RunStats.add_block"),
    (frame_step, "frame_step", "frame_step (compiled)"),
    (star_chain.CompiledChain, "frame_inputs", "CompiledChain.frame_inputs"),
    (gyro_check, "watch_frame", "gyro_check.watch_frame"),
    (gyro_check, "_record", "gyro_check._record"), (gyro_check, "_judge", "gyro_check._judge"),
    *[(imu_queue.ImuQueue, n, "ImuQueue." + n) for n in ("push", "count_upto", "pop")],
    (results.TableSink, "append_row", "TableSink.append_row"),
    (results.RunStats, "add", "RunStats.add"),
]
# a kernel's first call loads it from numba's cache, and the process's first one also starts
# numba's CPU target (its typing and lowering registries, ~0.2 CPU-s): timed apart, or that
# start is charged to whichever timed function calls a kernel first (on a replay,
# push_imu_block's screen).  numba is imported inside the timed replay, where the replay
# imports it, so that "start and imports" stays the script's own.
NUMBA_FIRST = "numba first calls (cache loads)"
# the replay's reading: the time inside its events generator (decompression, decoding, the
# merge of the chunks and of the IMU runs), a call an event
READING = "reading (the replay's events)"


def timed_replay(argv: list[str]) -> tuple[dict, dict, dict, float]:
    """Run ``cli.main(argv)`` with the TIMED functions wrapped; (calls, incl, excl, cpu s)."""
    incl: dict[str, float] = defaultdict(float)
    excl: dict[str, float] = defaultdict(float)
    calls: dict[str, int] = defaultdict(int)
    stack: list[float] = []

    def wrap(owner, name: str, label: str) -> None:
        f = getattr(owner, name)

        @functools.wraps(f)
        def w(*a, **k):
            t = time.process_time()
            stack.append(0.0)
            try:
                return f(*a, **k)
            finally:
                d = time.process_time() - t
                inner = stack.pop()
                incl[label] += d
                excl[label] += d - inner
                calls[label] += 1
                if stack:
                    stack[-1] += d

        setattr(owner, name, w)

    def wrap_events(f):
        @functools.wraps(f)
        def events(*a, **k):
            it = f(*a, **k)
            while True:
                t = time.process_time()
                try:
                    item = next(it)
                except StopIteration:
                    return
                finally:
                    d = time.process_time() - t
                    incl[READING] += d
                    excl[READING] += d
                    calls[READING] += 1
                yield item

        return events

    t = time.process_time()
    from numba.core.dispatcher import Dispatcher

    # (a checkout without one of them, e.g. an older one timed with this script: left out)
    timed = [t for t in [*TIMED, (Dispatcher, "_compile_for_args", NUMBA_FIRST)]
             if hasattr(t[0], t[1])]
    originals = [(owner, name, getattr(owner, name)) for owner, name, _ in timed]
    for owner, name, label in timed:
        wrap(owner, name, label)
    events = replay_mod._events_from_reader
    replay_mod._events_from_reader = wrap_events(events)
    try:
        cli.main(argv)
    finally:
        for owner, name, f in originals:
            setattr(owner, name, f)
        replay_mod._events_from_reader = events
    return calls, incl, excl, time.process_time() - t


def main(argv=None) -> int:
    """Command line entry."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("bag", type=Path)
    ap.add_argument("--prior", type=Path, help="default: BAG's .prior.yaml beside it")
    ap.add_argument("--method", default="psce")
    args = ap.parse_args(argv)
    prior = args.prior or Path(str(args.bag).removesuffix(".mcap") + ".prior.yaml")
    start = time.process_time()  # interpreter start and the imports above
    if frame_step.compiled_kernels_cold():
        # compiled with the timers in place, frame_steps would hold the timed wrapper of
        # frame_step (a Python function): its compilation fails, every batch falls back
        # to one call a frame, and the table times that instead
        print("the numba kernels are not compiled yet: run one replay first (e.g. "
              "benchmarks/psce_speed.py, or stellar-cal replay), then this", file=sys.stderr)
        return 2
    out = Path(tempfile.mkdtemp(prefix="replay_profile_")) / "result.yaml"
    calls, incl, excl, total = timed_replay(
        ["replay", str(args.bag), "--method", args.method, "--prior", str(prior), "-o",
         str(out), "-q"])
    t = time.process_time()
    n = 0
    with BagReader(args.bag) as reader:  # (every message to the driver: no quiet merge)
        for _ in replay_mod._events_from_reader(reader, dict(replay_mod.TOPICS)):
            n += 1
    reading = time.process_time() - t
    print(f"bag: {args.bag.name}; start and imports {start:.2f} CPU-s, replay (cli.main) "
          f"{total:.2f} CPU-s with the timers; reading alone {reading:.2f} CPU-s ({n} events)")
    print(f"{'':32s} {'calls':>8s} {'incl s':>8s} {'excl s':>8s} {'excl us/call':>13s}")
    for k in sorted(excl, key=lambda k: -excl[k]):
        print(f"{k:32s} {calls[k]:8d} {incl[k]:8.2f} {excl[k]:8.2f} "
              f"{1e6 * excl[k] / max(calls[k], 1):13.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
