"""Replay speed on a bag of star images (frames/s), beside the equivalent centroid bag.

Usage::

    python benchmarks/image_bag_replay.py [--duration 60] [--encoding mono16] [--repeat 3]

One ``psce_rotations`` world (seed 3) is written twice, as ``stellar-cal simulate`` and
``stellar-cal simulate --images ENCODING`` write it (1024 x 1024 images at 2 Hz): a bag of
identified centroids and a bag of star images.  Each bag is replayed (``--method psce``,
what ``stellar-cal replay`` runs) ``--repeat`` times, interleaved, after one warm-up run;
times are this process's CPU time (the machine is shared), medians.  For the image bag the
time is split into reading + extraction (``read_bag_data``: every image decoded and made
into centroids, the step of ``methods.frames.ImageFrames``) and identification (the
driver's tetra3rs calls, ``identify_solve_ms``); the rest is the filter.  The last lines
give the peak traced memory (``tracemalloc``) of ``read_bag_data`` on the image bag
against the pixel bytes that went through it.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
import tracemalloc
from pathlib import Path

from stellar_cal_ros.io.bag import BagReader
from stellar_cal_ros.io.calibration import load_calibration
from stellar_cal_ros.methods.frames import TOPIC_IMAGE, read_bag_data
from stellar_cal_ros.methods.replay import replay
from stellar_cal_ros.sim.image_bag import write_image_simulation
from stellar_cal_ros.sim.render import without_noise
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate, write_simulation

SEED = 3


def _cpu(fn):
    t = time.process_time()
    out = fn()
    return time.process_time() - t, out


def main() -> None:
    """Print the table (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0, help="seconds of data (2 Hz)")
    ap.add_argument("--encoding", choices=["mono16", "mono8"], default="mono16")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    sc = get_scenario("psce_rotations")
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        cen = write_simulation(simulate(sc, duration=args.duration, seed=SEED), d / "c.mcap")
        t_write, img = _cpu(lambda: write_image_simulation(
            simulate(without_noise(sc), duration=args.duration, seed=SEED), d / "i.mcap",
            args.encoding, seed=SEED))
        prior = load_calibration(cen["prior"])
        with BagReader(img["bag"]) as r:
            n = r.topics()[TOPIC_IMAGE].message_count
        size_mb = img["bag"].stat().st_size / 1e6
        print(f"psce_rotations {args.duration:.0f} s, {n} frames; image bag {args.encoding} "
              f"1024x1024 {size_mb:.1f} MB (rendered and written in {t_write:.1f} s CPU), "
              f"centroid bag {cen['bag'].stat().st_size / 1e6:.2f} MB")
        replay(cen["bag"], prior, keep_tables=False)  # warm-up (compiled kernels, caches)
        times: dict[str, list[float]] = {"centroids": [], "images": [], "read": []}
        ident_ms = []
        for _ in range(args.repeat):
            times["centroids"].append(_cpu(lambda: replay(cen["bag"], prior,
                                                          keep_tables=False))[0])
            t, res = _cpu(lambda: replay(img["bag"], prior, keep_tables=False))
            times["images"].append(t)
            ident_ms.append(res.counters["identify_solve_ms"])
            times["read"].append(_cpu(lambda: read_bag_data(img["bag"]))[0])
        med = {k: statistics.median(v) for k, v in times.items()}
        ident = statistics.median(ident_ms) / 1e3
        print(f"{'bag':<28}{'CPU s':>8}{'frames/s':>10}{'ms/frame':>10}")
        for name, t in (("centroids (replay)", med["centroids"]),
                        (f"images {args.encoding} (replay)", med["images"])):
            print(f"{name:<28}{t:8.2f}{n / t:10.1f}{1e3 * t / n:10.1f}")
        print(f"  of which read + extraction{med['read']:8.2f}{n / med['read']:10.1f}"
              f"{1e3 * med['read'] / n:10.1f}")
        print(f"  of which identification   {ident:8.2f}{n / ident:10.1f}{1e3 * ident / n:10.1f}")
        tracemalloc.start()
        data = read_bag_data(img["bag"])
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        pixels = n * 1024 * 1024 * (1 if args.encoding == "mono8" else 2)
        print(f"read_bag_data peak traced memory {peak / 2**20:.1f} MiB for {pixels / 2**20:.0f} "
              f"MiB of pixels ({len(data.frames)} frames)")


if __name__ == "__main__":
    main()
