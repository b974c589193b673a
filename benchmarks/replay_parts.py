"""Where a replay's CPU goes frame by frame, for any method; a round's share (issue 24.1).

Usage::

    python benchmarks/replay_parts.py BAG.mcap [--method swaying_base] [--prior PRIOR.yaml]
                                      [--fine]
    python benchmarks/replay_parts.py BAG.mcap --method swaying_base --round R.yaml

Replays ``BAG`` in process (``replay(bag, prior, method, keep_tables=False)``) once to warm,
once plain (its CPU seconds), then once with every part below wrapped in a CPU timer
(inclusive; a part called inside another counts in both) and prints each part's seconds,
calls and µs a call: the driver's frame (``Calibrator._process``), the filter's
(``StarFilter.process_frame``), its propagation (the strapdown interval
``ImuPropagation.step`` and the method's ``_transition``), the method's other measurements
(``_before_star_update``: the swaying filter's position reference), the numpy star update
(``_star_update``), the one compiled call (``_fused_update``), the gyro watch, the history
row (``--fine``: finer parts too, the driver's pushes among them).  A method whose frames
take the compiled step shows them under ``_fused_update``; a batched replay's committed
frames pass none of these.

``--round R.yaml``: instead, ``stellar-cal diagnose BAG --calibration R.yaml --method METHOD
--no-plots --workers 0`` in process (output in a temporary directory), and the CPU seconds
inside ``StarFilter.process_frame`` against the whole command's.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

from stellar_cal_ros.core.propagation import ImuPropagation
from stellar_cal_ros.io.calibration import load_calibration
from stellar_cal_ros.methods import registry
from stellar_cal_ros.methods.driver import Calibrator
from stellar_cal_ros.methods.kernel import StarFilter
from stellar_cal_ros.methods.replay import replay


def _wrap(cls, name: str, label: str, tot: dict, cnt: dict, outer: bool = False) -> None:
    """Time ``cls.name`` into ``tot[label]`` (``outer``: the outermost call only)."""
    f = getattr(cls, name)
    depth = [0]

    def timed(*a, **k):
        if outer and depth[0]:
            return f(*a, **k)
        depth[0] += 1
        t = time.process_time()
        try:
            return f(*a, **k)
        finally:
            depth[0] -= 1
            tot[label] += time.process_time() - t
            cnt[label] += 1

    setattr(cls, name, timed)


def main(argv=None) -> int:
    """Command line entry."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("bag", type=Path)
    ap.add_argument("--method", default="psce")
    ap.add_argument("--prior", type=Path)
    ap.add_argument("--round", type=Path, help="a calibration: time a diagnose round")
    ap.add_argument("--fine", action="store_true",
                    help="time finer parts too: the rate at the frame, the compiled calls "
                         "and their Python around them, the reference rows, the driver's "
                         "pushes (a push's frames counted in it)")
    args = ap.parse_args(argv)
    tot: dict[str, float] = defaultdict(float)
    cnt: dict[str, int] = defaultdict(int)
    if args.round:
        from stellar_cal_ros import cli

        _wrap(StarFilter, "process_frame", "process_frame", tot, cnt, outer=True)
        t = time.process_time()
        with tempfile.TemporaryDirectory() as out:
            cli.main(["diagnose", str(args.bag), "--calibration", str(args.round), "--method",
                      args.method, "--no-plots", "--workers", "0", "-o", out])
        whole = time.process_time() - t
        n = max(cnt["process_frame"], 1)
        print(f"diagnose round: {whole:.2f} CPU s, StarFilter.process_frame "
              f"{tot['process_frame']:.2f} s ({tot['process_frame'] / whole:.0%}) over "
              f"{cnt['process_frame']} frames, {tot['process_frame'] / n * 1e6:.0f} us a frame")
        return 0
    prior = load_calibration(args.prior or Path(str(args.bag).removesuffix(".mcap")
                                                + ".prior.yaml"))
    replay(args.bag, prior, args.method, keep_tables=False)
    t = time.process_time()
    res = replay(args.bag, prior, args.method, keep_tables=False)
    plain = time.process_time() - t
    cls = registry.get(args.method).filter_cls
    parts = [(Calibrator, "_process", "driver: a frame (_process)"),
             (StarFilter, "process_frame", " filter: process_frame"),
             (StarFilter, "propagate", "  propagate (strapdown + transition)"),
             (ImuPropagation, "step", "   ImuPropagation.step"),
             (cls, "_transition", "   _transition"),
             (cls, "_before_star_update", "  _before_star_update"),
             (StarFilter, "_star_update", "  _star_update (numpy path)"),
             (StarFilter, "_fused_update", "  _fused_update (compiled call)"),
             (StarFilter, "_watch_gyro", "  gyro watch"),
             (Calibrator, "_record_history", " history row")]
    if args.fine:
        from stellar_cal_ros.core.imu_prefix import ImuPrefix
        from stellar_cal_ros.methods.frame_step import FusedStep

        parts += [(StarFilter, "rate_at", "  (fine) rate at the frame (omega)"),
                  (FusedStep, "update", "  (fine) FusedStep.update (star update call)"),
                  (StarFilter, "_compiled_result", "  (fine) _compiled_result"),
                  (ImuPrefix, "extend", "  (fine) reference rows (ImuPrefix.extend)"),
                  (Calibrator, "push_imu_block", "(fine) push_imu_block (incl. frames)"),
                  (Calibrator, "push_scalars", "(fine) push_scalars (incl. frames)"),
                  (Calibrator, "push_fix", "(fine) push_fix (incl. frames)"),
                  (Calibrator, "push_stars", "(fine) push_stars (incl. frames)"),
                  (Calibrator, "push_stars_many", "(fine) push_stars_many (incl. frames)")]
        for name, label in (("_compiled_interval", "   (fine) _compiled_interval"),
                            ("reference_measurement", "   (fine) reference_measurement"),
                            ("_reference_update", "   (fine) _reference_update")):
            if hasattr(cls, name):
                parts.append((cls, name, label))
    for c, name, label in parts:
        _wrap(c, name, label, tot, cnt)
    t = time.process_time()
    replay(args.bag, prior, args.method, keep_tables=False)
    wrapped = time.process_time() - t
    print(f"bag {args.bag.name}, method {args.method}: replay in process {plain:.2f} CPU s "
          f"({wrapped:.2f} with the timers), {res.counters['frames']} frames, "
          f"{res.counters['updates']} updates")
    print(f"{'':40s} {'CPU s':>7s} {'calls':>7s} {'us/call':>8s}")
    for _, _, label in parts:
        if cnt[label]:
            print(f"{label:40s} {tot[label]:7.3f} {cnt[label]:7d} "
                  f"{tot[label] / cnt[label] * 1e6:8.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
