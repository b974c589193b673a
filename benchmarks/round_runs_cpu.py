"""CPU-s of the 2-h round's replays of the user's bag, each re-run in this process (issue 24).

Starts the ``diagnose`` round of ``round_replays.py`` (the 2-h psce bag, ``--workers 0``)
with :func:`stellar_cal_ros.methods.replay.replay` wrapped, keeps the arguments of its
first ``--runs`` replays (all of the user's bag: the noise's base run, the IMU search's
two, the screening's aberration) and stops the round there; then replays each of them
``--repeat`` times on the bag read once, printing each replay's ``process_time`` and a
digest of its result (covariance, counters, statistics: equal digests, equal results).
The first repetition pays what a round pays once (the direction effects' tables, numba's
first calls): compare the later ones.  Run it on two checkouts one after the other, and
again, to compare them on a loaded machine::

    PYTHONPATH=CHECKOUT python benchmarks/round_runs_cpu.py [--runs 4] [--repeat 2]
"""

from __future__ import annotations

import argparse
import hashlib
import runpy
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


class _EnoughError(Exception):
    """Raised by the wrapped replay once the round's first runs are kept."""


def round_runs(count: int, bag: Path) -> list[tuple]:
    """``(prior, method, effects, config, keywords)`` of the round's first ``count`` replays."""
    import stellar_cal_ros.methods.replay as rp

    cal = bag.with_name(bag.name.replace(".mcap", ".prior.yaml"))
    kept: list[tuple] = []
    original = rp.replay

    def kept_replay(data, prior, method="psce", effects=None, config=None, **kw):
        kept.append((prior, method, effects, config, kw))
        if len(kept) >= count:
            raise _EnoughError
        return original(data, prior, method, effects, config, **kw)

    rp.replay = kept_replay
    argv = sys.argv
    sys.argv = ["stellar_cal_ros", "diagnose", str(bag), "--calibration", str(cal),
                "--method", "psce", "--no-plots", "--workers", "0", "-o",
                str(Path("round_runs_out"))]
    try:
        runpy.run_module("stellar_cal_ros", run_name="__main__")
    except (_EnoughError, SystemExit):
        pass
    finally:
        rp.replay, sys.argv = original, argv
    return kept[:count]


def digest(result) -> str:
    """A short hash of a replay's covariance, counters and statistics."""
    h = hashlib.sha1()
    h.update(np.ascontiguousarray(result.covariance[1]).tobytes())
    h.update(repr(sorted(result.counters.items())).encode())
    h.update(repr(getattr(result.stats, "__dict__", result.stats)).encode())
    return h.hexdigest()[:12]


def main() -> int:
    """Keep the round's runs, then time each ``--repeat`` times."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()
    from discovery_speed import ensure_2h_bag

    from stellar_cal_ros.methods.replay import read_bag_data, replay

    bag = Path(ensure_2h_bag())
    runs = round_runs(args.runs, bag)
    data = read_bag_data(bag)
    for rep in range(args.repeat):
        for i, (prior, method, effects, config, kw) in enumerate(runs):
            c = time.process_time()
            result = replay(data, prior, method, effects, config, **kw)
            c = time.process_time() - c
            print(f"run {i + 1} repetition {rep + 1}: {c:.2f} CPU-s  {digest(result)}  "
                  f"effects={','.join(effects or ()) or '-'} "
                  f"consider={len(kw.get('consider') or ())}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
