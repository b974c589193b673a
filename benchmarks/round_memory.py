"""RSS and CPU-s at the stages of one 2-h ``diagnose`` round in process (issue 24.2).

Wraps ``runstats.load_bag``, ``noise_runs.measure``, ``output.line_tests`` and
``reliability_probe.measure_on_bag``; after each prints the RSS before → after, the peak so
far (``ru_maxrss``), the stage's CPU-s (``process_time``; a stage inside another is counted
in both) and, for the bag, the bytes of the numpy arrays it holds.  ``--probe`` adds the
reliability probe's twin scene, renders and steps.  ``--trim``
calls glibc's ``malloc_trim(0)`` after each stage (what the allocator keeps but does not
use).  ``--sample`` reads the RSS every 5 ms in a thread and, at each new maximum 2 MB above
the last one, the main thread's stack; at the end it prints the highest maxima (MB) with
the package's innermost frames (the sampling's own cost lifts the figures a little).

Run::

    python benchmarks/round_memory.py [--trim] [--probe] [--sample] [--calibration R.yaml]
        [--default-malloc]
"""

from __future__ import annotations

import argparse
import ctypes
import functools
import gc
import resource
import sys
import threading
import time
import traceback
from pathlib import Path

import numpy as np
import psutil

sys.path.insert(0, str(Path(__file__).resolve().parent))
PROC = psutil.Process()


def rss() -> float:
    """RSS of the process, MB."""
    return PROC.memory_info().rss / 2**20


def peak() -> float:
    """Peak RSS of the process so far, MB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def nbytes(obj, seen=None) -> int:
    """Bytes of the numpy arrays reachable through dicts, lists and attributes."""
    seen = seen if seen is not None else set()
    if id(obj) in seen:
        return 0
    seen.add(id(obj))
    if isinstance(obj, np.ndarray):
        return obj.nbytes
    if isinstance(obj, dict):
        return sum(nbytes(v, seen) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return sum(nbytes(v, seen) for v in obj)
    if hasattr(obj, "__dict__"):
        return nbytes(vars(obj), seen)
    return 0


class Sampler(threading.Thread):
    """RSS every ``period`` s; the main thread's stack at each new maximum ``step`` MB above."""

    def __init__(self, period: float = 0.005, step: float = 2.0):
        """Start a daemon thread sampling the RSS of this process."""
        super().__init__(daemon=True)
        self.period, self.step, self.top, self.peaks = period, step, 0.0, []
        self.main_id = threading.main_thread().ident
        self.stop = threading.Event()
        self.start()

    def run(self) -> None:
        """Sample until :meth:`stop` is set."""
        while not self.stop.wait(self.period):
            r = rss()
            if r > self.top + self.step:
                self.top = r
                frame = sys._current_frames().get(self.main_id)
                stack = traceback.extract_stack(frame) if frame is not None else []
                ours = [f"{Path(f.filename).stem}.{f.name}:{f.lineno}" for f in stack
                        if "stellar_cal_ros" in f.filename]
                self.peaks.append((r, ours[-4:]))

    def report(self, n: int = 12) -> None:
        """The ``n`` highest maxima with the package's innermost frames."""
        self.stop.set()
        self.join()
        for r, frames in sorted(self.peaks, reverse=True)[:n]:
            print(f"  {r:.0f} MB  " + " < ".join(reversed(frames)), flush=True)


def main() -> int:
    """Run the round and print the stages."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trim", action="store_true")
    ap.add_argument("--calibration", type=Path, default=None,
                    help="the round's calibration (default: the bag's prior)")
    ap.add_argument("--default-malloc", action="store_true",
                    help="leave glibc's mapping threshold to rise (before core.memory)")
    ap.add_argument("--probe", action="store_true",
                    help="also the reliability probe's parts: its scene, renders and steps")
    ap.add_argument("--sample", action="store_true",
                    help="sample the RSS and print the stacks at its highest maxima")
    args = ap.parse_args()
    libc = ctypes.CDLL("libc.so.6") if args.trim else None
    if not args.default_malloc:  # as the command line's diagnose does
        try:
            from stellar_cal_ros.core.memory import return_freed_arrays
        except ImportError:  # a checkout before it
            pass
        else:
            return_freed_arrays()
    print(f"python: rss {rss():.0f}", flush=True)
    from discovery_speed import ensure_2h_bag

    import stellar_cal_ros.diagnosis.noise_runs as nr
    import stellar_cal_ros.diagnosis.output as out
    import stellar_cal_ros.diagnosis.reliability_probe as rp
    import stellar_cal_ros.diagnosis.run as runmod
    import stellar_cal_ros.diagnosis.runstats as rs
    import stellar_cal_ros.methods.frame_step  # noqa: F401  (numba, as a run imports it)
    from stellar_cal_ros.io.calibration import load_calibration

    print(f"imports: rss {rss():.0f}", flush=True)

    def wrap(mod, name, what=None):
        f = getattr(mod, name)

        @functools.wraps(f)
        def g(*a, **k):
            r0, c0 = rss(), time.process_time()
            res = f(*a, **k)
            c1 = time.process_time() - c0
            if libc is not None:
                gc.collect()
                libc.malloc_trim(0)
            extra = what(res) if what else ""
            print(f"  {name}: rss {r0:.0f}->{rss():.0f} peak {peak():.0f} cpu {c1:.2f} s {extra}",
                  flush=True)
            return res
        setattr(mod, name, g)

    wrap(rs, "load_bag", lambda res: f"bag arrays {nbytes(res) / 2**20:.0f} MB")
    wrap(nr, "measure")
    wrap(rp, "measure_on_bag")
    wrap(out, "line_tests")
    if args.probe:
        import stellar_cal_ros.diagnosis.twin as tw

        wrap(tw, "twin_scene")
        wrap(rp, "rendered_stars")
        wrap(rp, "star_steps")
    bag = ensure_2h_bag()
    cal = load_calibration(args.calibration or bag.with_suffix(".prior.yaml"))
    import tempfile

    sampler = Sampler() if args.sample else None
    with tempfile.TemporaryDirectory() as tmp:
        runmod.diagnose(str(bag), cal, "psce", [], tmp, plots=False, verbose=False, workers=0)
    print(f"end: rss {rss():.0f} peak {peak():.0f} cpu {time.process_time():.1f} s", flush=True)
    if sampler is not None:
        print("highest RSS maxima sampled, innermost frame first:", flush=True)
        sampler.report()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
