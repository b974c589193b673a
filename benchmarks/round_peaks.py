"""Where a command's RSS peaks, stage by stage: the command in process, sampled (issue 24.2).

Runs ``python -m stellar_cal_ros ARGS`` in this process (no wrapped functions, no other
imports than the command's: its RSS is the command's within a few MB) while a thread reads
the RSS (``/proc/self/statm``) and the main thread's stack (the package's frames, walked
without reading their source) every ``--period`` s.  At the end: ``ru_maxrss``, then each
stretch of samples with the same package frames ``--from``..``--to`` (outermost first) whose
highest RSS is at least ``--above`` MiB: its start and end (s), the RSS at its start, end
and highest.  A peak shorter than the period, or inside a call that holds the GIL, can be
missed (``ru_maxrss`` above every sample says so).

Run::

    python benchmarks/round_peaks.py [--from 4] [--to 7] [--above 400] -- diagnose BAG.mcap
        --calibration R.yaml --method psce --no-plots --workers 0 -o OUT
"""

from __future__ import annotations

import argparse
import os
import resource
import runpy
import sys
import threading
import time

PAGE = os.sysconf("SC_PAGE_SIZE")


def rss() -> float:
    """RSS of this process, MiB."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * PAGE / 2**20


def package_frames(frame) -> list[str]:
    """``module.function`` of the package's frames of ``frame``'s stack, outermost first."""
    out = []
    while frame is not None:
        code = frame.f_code
        if "stellar_cal_ros" in code.co_filename:
            out.append(f"{os.path.basename(code.co_filename)[:-3]}.{code.co_name}")
        frame = frame.f_back
    return out[::-1]


def stretches(rows: list[tuple[float, float, list[str]]], lo: int, hi: int
              ) -> list[tuple[float, float, float, float, float, str]]:
    """Consecutive samples with the same frames ``lo:hi``: ``(t0, t1, rss0, rss1, top, key)``."""
    out: list = []
    for t, r, frames in rows:
        key = " > ".join(frames[lo:hi])
        # (a sample between the package's calls, or in a compiled one, continues its stretch)
        if out and (out[-1][5] == key or (not key and len(frames) <= lo)):
            key = out[-1][5]
            t0, _, r0, _, top, _ = out[-1]
            out[-1] = (t0, t, r0, r, max(top, r), key)
        else:
            out.append((t, t, r, r, r, key))
    return out


def main() -> int:
    """Run the command, then print its stretches."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--period", type=float, default=0.005)
    ap.add_argument("--from", dest="lo", type=int, default=4,
                    help="first package frame of a stretch's key (0: the outermost)")
    ap.add_argument("--to", dest="hi", type=int, default=7)
    ap.add_argument("--above", type=float, default=400.0, help="MiB")
    ap.add_argument("command", nargs=argparse.REMAINDER)
    args = ap.parse_args()
    command = [a for a in args.command if a != "--"]
    rows: list[tuple[float, float, list[str]]] = []
    main_id = threading.main_thread().ident
    stop = threading.Event()
    start = time.perf_counter()

    def sample() -> None:
        while not stop.wait(args.period):
            frame = sys._current_frames().get(main_id)
            rows.append((time.perf_counter() - start, rss(), package_frames(frame)))

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    sys.argv = ["stellar_cal_ros", *command]
    try:
        runpy.run_module("stellar_cal_ros", run_name="__main__")
    except SystemExit:
        pass
    finally:
        stop.set()
        thread.join()
    top = max((r for _, r, _ in rows), default=0.0)
    print(f"ru_maxrss {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.1f} MiB, "
          f"highest sample {top:.1f} MiB ({len(rows)} samples)")
    for t0, t1, r0, r1, hi, key in stretches(rows, args.lo, args.hi):
        if hi >= args.above:
            print(f"{t0:7.1f}-{t1:7.1f} s  rss {r0:6.1f} -> {r1:6.1f}  max {hi:6.1f}  {key}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
