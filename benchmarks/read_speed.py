"""Decode-only reading speed of one bag: this package (read_*, stream) vs rosbags vs mcap_ros2.

Usage::

    python benchmarks/read_speed.py [BAG ...] [--repeat 5] [--rss 600,1800,7200]

Without a bag, the 900 s reference bag ``../shared/data/psce_sky_900s.mcap`` is used if it is
there, else a 900 s ``psce_rotations`` bag is simulated once into ``benchmarks/.cache/``.
Every reader decodes every message of the six contract topics (to numpy arrays for this
package, to message objects for the others); the methods run interleaved in each repetition
so machine load hits them alike. Printed per bag: min and median wall time, the bag's
duration per second of reading, and the median of the per-repetition ratios to rosbags.

``--rss D1,D2,..`` also simulates bags of those durations (cached) and measures, each in a
fresh process, the peak RSS of ``stream()`` and of the ``read_*`` methods (all topics held)
against the bag length. ``--rosbag2`` adds the same bag converted by rosbags to a rosbag2
sqlite3 directory and a ROS 1 bag (read by this package through rosbags).
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = ROOT.parent / "shared" / "data" / "psce_sky_900s.mcap"
CACHE = Path(__file__).parent / ".cache"
SCALARS = ("/star_tracker/temperature", "/environment/temperature", "/environment/pressure")


def ours_read(path: Path) -> int:
    """Every contract topic through the read_* methods; returns the message count."""
    from stellar_cal_ros.io.bag import BagReader

    with BagReader(path) as r:
        n = len(r.read_imu()) + len(r.read_star_frames()) + len(r.read_navsat())
        return n + sum(len(r.read_scalar(t)) for t in SCALARS)


def ours_stream(path: Path) -> int:
    """Every contract topic through one stream() pass; returns the message count."""
    from stellar_cal_ros.io.bag import BagReader

    with BagReader(path) as r:
        return sum(1 if role == "stars" else len(b) for role, b in r.stream())


def rosbags_decode(path: Path) -> int:
    """Decode with rosbags.highlevel.AnyReader: every message deserialised."""
    from rosbags.highlevel import AnyReader

    n = 0
    with AnyReader([path]) as reader:
        for conn, _, raw in reader.messages():
            reader.deserialize(raw, conn.msgtype)
            n += 1
    return n


def mcap_ros2_decode(path: Path) -> int:
    """Decode with mcap and mcap_ros2: every message decoded (file order, as its fastest mode)."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    n = 0
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _ in reader.iter_decoded_messages(log_time_order=False):
            n += 1
    return n


METHODS: dict[str, Callable[[Path], int]] = {
    "stellar_cal read_*": ours_read,
    "stellar_cal stream()": ours_stream,
    "rosbags AnyReader": rosbags_decode,
    "mcap_ros2": mcap_ros2_decode,
}


def simulated(duration: float) -> Path:
    """A ``psce_rotations`` bag of ``duration`` s, simulated once into the cache."""
    sys.path.insert(0, str(Path(__file__).parent))
    from psce_speed import ensure_bag  # the same cached bags as the replay benchmark

    return ensure_bag(duration)


def converted(src: Path) -> list[Path]:
    """``src`` converted by rosbags to a rosbag2 sqlite3 directory and a ROS 1 bag (cached)."""
    from rosbags.convert import convert

    out = []
    for name in (f"{src.stem}_rb2_sqlite3", f"{src.stem}.bag"):  # the suffix picks ROS 1
        dst = CACHE / name
        if not dst.exists():
            CACHE.mkdir(parents=True, exist_ok=True)
            convert([src], dst, "sqlite3", 8, None, "file", None, None, [], [], [], [])
        out.append(dst)
    return out


def duration_s(path: Path) -> float:
    """Log-time span of the bag, s."""
    from stellar_cal_ros.io.bag import BagReader

    with BagReader(path) as r:
        return r.duration_s


def time_bag(path: Path, repeat: int, methods: dict[str, Callable[[Path], int]]) -> None:
    """Print the interleaved timing table of one bag."""
    times: dict[str, list[float]] = {k: [] for k in methods}
    counts: dict[str, int] = {}
    for _ in range(repeat):
        for name, fn in methods.items():
            t = time.perf_counter()
            counts[name] = fn(path)
            times[name].append(time.perf_counter() - t)
    span = duration_s(path)
    ref = np.array(times.get("rosbags AnyReader") or times[next(iter(times))])
    print(f"\n{path.name}: {span:.0f} s of data, {os.path.getsize(path) / 1e6:.1f} MB"
          if path.is_file() else f"\n{path.name}/: {span:.0f} s of data")
    print(f"{'reader':24s} {'messages':>9s} {'min s':>8s} {'median s':>9s} {'x real':>8s} "
          f"{'/ rosbags':>10s}")
    for name, v in times.items():
        arr = np.array(v)
        print(f"{name:24s} {counts[name]:9d} {arr.min():8.3f} {np.median(arr):9.3f} "
              f"{span / np.median(arr):8.0f} {np.median(arr / ref):10.3f}")


def _hwm_mib() -> float:
    """Peak resident set size of this process, MiB.

    VmHWM is reset at exec, unlike ``ru_maxrss``, which a child inherits from its parent.
    """
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _rss_child(path: str, how: str) -> None:
    """Measure in a fresh process: peak RSS after imports, then after reading."""
    import stellar_cal_ros.io.bag  # noqa: F401 -- imports before the baseline

    base = _hwm_mib()
    if how == "stream":
        ours_stream(Path(path))
    else:
        from stellar_cal_ros.io.bag import BagReader

        with BagReader(path) as r:  # everything held at once, as a whole-bag reader does
            kept = [r.read_imu(), r.read_star_frames(), r.read_navsat(),
                    *(r.read_scalar(t) for t in SCALARS)]
        del kept
    print(base, _hwm_mib())


def rss_table(durations: list[float]) -> None:
    """Print peak RSS of stream() and read_* per bag length (each in a fresh process)."""
    print("\npeak RSS, MiB (fresh process; 'import' = after importing the package)")
    print(f"{'bag s':>7s} {'MB':>7s} {'import':>7s} {'stream()':>9s} {'read_*':>8s}")
    for d in durations:
        path = simulated(d)
        row = []
        for how in ("stream", "read"):
            out = subprocess.run([sys.executable, __file__, "--rss-child", str(path), how],
                                 capture_output=True, text=True, check=True, cwd=ROOT)
            base, peak = (float(x) for x in out.stdout.split())
            row.append((base, peak))
        print(f"{d:7.0f} {path.stat().st_size / 1e6:7.1f} {row[0][0]:7.0f} {row[0][1]:9.0f} "
              f"{row[1][1]:8.0f}")


def main(argv: list[str] | None = None) -> int:
    """Command line entry."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("bags", nargs="*", type=Path, help="bags to read (default: see above)")
    ap.add_argument("--repeat", type=int, default=5, help="interleaved repetitions")
    ap.add_argument("--rss", default="", help="comma-separated bag durations, s")
    ap.add_argument("--rosbag2", action="store_true",
                    help="also read rosbags conversions of the first bag (sqlite3, ROS 1)")
    ap.add_argument("--rss-child", nargs=2, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.rss_child:
        _rss_child(*args.rss_child)
        return 0
    bags = args.bags or [REFERENCE if REFERENCE.exists() else simulated(900.0)]
    print(f"load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} (2 cores, shared)")
    for bag in bags:
        time_bag(bag, args.repeat, METHODS)
    if args.rosbag2:
        ours = {k: METHODS[k] for k in ("stellar_cal read_*", "stellar_cal stream()",
                                        "rosbags AnyReader")}
        for bag in converted(bags[0]):
            time_bag(bag, args.repeat, ours)
    if args.rss:
        rss_table([float(x) for x in args.rss.split(",") if x])
    print(f"load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

