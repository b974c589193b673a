"""A replay's events of the 2-h bag in memory and its environment calls: two checkouts' (issue 24).

``python benchmarks/env_events_ab.py OTHER/stellar_cal_ros/methods/replay.py``: this
checkout's :func:`~stellar_cal_ros.methods.replay._events_from_data` and the one of the
file given (loaded beside it, e.g. main's), interleaved in this process: each generates
every event of the bag of ``psce_speed.py`` (2 h) and hands the environment ones to a
:class:`~stellar_cal_ros.methods.driver.Calibrator` (this checkout's); prints the CPU-s
(``process_time``), the events, and what the driver counted and holds (equal: the same
samples went in).
"""

import importlib.util
import sys
import time
from pathlib import Path

from stellar_cal_ros.io.calibration import load_calibration
from stellar_cal_ros.methods import replay as new
from stellar_cal_ros.methods.driver import Calibrator
from stellar_cal_ros.methods.replay import _handlers, read_bag_data

sys.path.insert(0, str(Path(__file__).resolve().parent))


def one(mod, data, prior):
    """CPU-s, events, the driver's count and the samples it holds."""
    cal = Calibrator(prior, "psce", [])
    h = _handlers(cal)
    c = time.process_time()
    n = 0
    for role, p in mod._events_from_data(data):
        n += 1
        if role in ("head", "air", "pressure", "scalars"):
            h[role](p)
    return (time.process_time() - c, n, cal.counters.env_received,
            [len(s.stamp_ns) for s in cal.env.values()])


def main() -> int:
    """Four interleaved pairs."""
    from psce_speed import ensure_bag

    spec = importlib.util.spec_from_file_location("replay_other", sys.argv[1])
    old = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(old)
    bag = ensure_bag(7200.0)
    data = read_bag_data(bag)
    prior = load_calibration(bag.with_name(bag.name.replace(".mcap", ".prior.yaml")))
    for _ in range(4):
        for name, mod in (("given", old), ("this", new)):
            t, n, r, lens = one(mod, data, prior)
            print(f"{name}: {t:.3f} CPU-s, {n} events, env_received {r}, held {lens}",
                  flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
