"""Where a command's CPU goes, sampled on CPU time (issue 24.2): no per-call cost.

cProfile charges every Python call its own bookkeeping (~1 µs), so code of many small
calls (a replay's per-frame Python) reads 3-5x its real share beside numpy and compiled
code.  This samples instead: ``setitimer(ITIMER_PROF)`` interrupts the process every
``--period`` s of its CPU time and the Python stack at that moment is counted.  A sample
taken inside compiled code (numba, numpy's C) is counted at the Python line that made the
call when the call returns (numba's native ``frame_steps`` shows as
``numba/core/serialize.py:_numba_unpickle`` under ``frame_step.py:batch``).  Printed: the
command's ``process_time``, then the CPU-s of each function (inclusive: every sample with
it on the stack, scaled to the process time) and the innermost frames (self).

Run::

    python benchmarks/cpu_samples.py [--top 80] [--period 0.005] -- diagnose BAG.mcap
        --calibration R.yaml --method psce --no-plots --workers 0 -o OUT
"""

from __future__ import annotations

import argparse
import collections
import signal
import time


def main() -> int:
    """Run the command under the sampler; print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--top", type=int, default=80)
    ap.add_argument("--period", type=float, default=0.005)
    ap.add_argument("command", nargs=argparse.REMAINDER)
    args = ap.parse_args()
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    stacks: collections.Counter = collections.Counter()

    def sample(_sig, frame) -> None:
        names = []
        while frame is not None:
            code = frame.f_code
            names.append(f"{code.co_filename.split('stellar_cal_ros/')[-1]}:{code.co_name}")
            frame = frame.f_back
        stacks[tuple(names)] += 1

    from stellar_cal_ros import cli

    signal.signal(signal.SIGPROF, sample)
    signal.setitimer(signal.ITIMER_PROF, args.period, args.period)
    t0 = time.process_time()
    try:
        cli.main(command)
    except SystemExit:
        pass
    signal.setitimer(signal.ITIMER_PROF, 0, 0)
    cpu = time.process_time() - t0
    total = sum(stacks.values()) or 1
    inclusive: collections.Counter = collections.Counter()
    inner: collections.Counter = collections.Counter()
    for names, n in stacks.items():
        for name in set(names):
            inclusive[name] += n
        inner[names[0]] += n
    print(f"process_time {cpu:.2f} CPU-s, {total} samples")
    for name, n in inclusive.most_common(args.top):
        print(f"{n * cpu / total:8.2f}  {name}")
    print("innermost:")
    for name, n in inner.most_common(args.top // 2):
        print(f"{n * cpu / total:8.2f}  {name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
