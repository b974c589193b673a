"""A replay's batched compiled steps against one call a frame, on a bag (issue 24.1).

Usage::

    python benchmarks/batched_equal.py BAG.mcap [--prior PRIOR.yaml] [--time-offset 0.003]
        [--effects time_offset] [--consider radial_k3] [--method swaying_base]

Replays the bag twice in process (``replay(bag, prior, METHOD, effects, consider)``, METHOD
``psce`` unless ``--method`` says) with
``StarFilter.batched_step`` False (one compiled call a frame) then True (a run of frames in
one call), and prints the CPU seconds of each, how many updates came from a batch (frames
taken one by one from it; frames committed a batch at once), and the largest difference of
θ, P, R and the consider sensitivity (M, score, information), whether the counters, the
statistics and the history rows are equal.  ``--time-offset``: the prior's offset replaced
(an offset the estimate moves away from).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from stellar_cal_ros.io.calibration import load_calibration
from stellar_cal_ros.methods import frame_step
from stellar_cal_ros.methods.kernel import StarFilter
from stellar_cal_ros.methods.replay import replay


def _counting() -> dict[str, int]:
    """Count the frames taken from batches and committed a batch at once (patched in)."""
    count = {"taken": 0, "committed": 0}
    take, commit = frame_step.FrameBatch.take, StarFilter.commit_batch

    def taken(self, *a, **k):
        out = take(self, *a, **k)
        count["taken"] += out is not None
        return out

    def committed(self, *a, **k):
        out = commit(self, *a, **k)
        count["committed"] += 0 if out is None else out.count
        return out

    frame_step.FrameBatch.take = taken
    StarFilter.commit_batch = committed
    return count


def main(argv=None) -> int:
    """Command line entry."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("bag", type=Path)
    ap.add_argument("--prior", type=Path)
    ap.add_argument("--time-offset", type=float)
    ap.add_argument("--effects", default="time_offset")
    ap.add_argument("--consider", default="radial_k3")
    ap.add_argument("--method", default="psce")
    args = ap.parse_args(argv)
    prior = load_calibration(args.prior or Path(str(args.bag).removesuffix(".mcap")
                                                + ".prior.yaml"))
    if args.time_offset is not None:
        prior.time_offset = args.time_offset
    effects = [e for e in args.effects.split(",") if e]
    consider = [e for e in args.consider.split(",") if e]
    count = _counting()
    runs = {}
    for batched in (False, True):
        StarFilter.batched_step = batched
        count.update(taken=0, committed=0)
        t = time.process_time()
        runs[batched] = replay(args.bag, prior, args.method, effects=effects,
                               consider=consider)
        print(f"batched_step={batched}: {time.process_time() - t:.2f} CPU s, updates "
              f"{runs[batched].counters['updates']}, taken from a batch {count['taken']}, "
              f"committed a batch at once {count['committed']}")
    one, batch = runs[False], runs[True]
    fa, fb = one.filter, batch.filter
    for name in ("theta", "P", "R_i_b"):
        print(f"{name}: max |diff| {np.max(np.abs(getattr(fa, name) - getattr(fb, name))):.3g}")
    if fa.sensitivity is not None:
        for name in ("M", "score", "info"):
            d = np.max(np.abs(getattr(fa.sensitivity, name) - getattr(fb.sensitivity, name)))
            print(f"sensitivity {name}: max |diff| {d:.3g}")
    ha, hb = one.history, batch.history
    same = list(ha) == list(hb) and all(np.array_equal(ha[k], hb[k]) for k in ha)
    print(f"counters equal {one.counters == batch.counters}, statistics equal "
          f"{vars(one.stats) == vars(batch.stats)}, history ({len(ha['t'])} rows) equal {same}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
