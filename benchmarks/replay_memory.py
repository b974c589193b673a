"""Peak RSS of ``stellar-cal replay`` against the bag's length (bounded memory, issue 17).

Usage::

    python benchmarks/replay_memory.py [--durations 600,1800,7200] [--day] [--residuals]

For each duration a ``psce_rotations`` bag is simulated once (cached in
``benchmarks/.cache/``, shared with ``psce_speed.py``) and replayed in a fresh process::

    python -m stellar_cal_ros replay BAG --method psce --prior PRIOR -o OUT \
        [--residuals OUT.csv] -q

under ``/usr/bin/time -v`` (its "Maximum resident set size"; without it, psutil-free polling
of ``/proc/PID/status`` VmHWM).  ``--day`` adds a 24 h bag: simulating 24 h at once would
hold the whole day in memory, so it is built as twelve 2 h simulations whose scenario start
times follow each other (``start_posix`` shifted by 2 h: the sky and the stamps continue),
written as twelve MCAP files of one directory, which the reader replays as one split bag.
The simulated motion restarts at every junction, so the attitude jumps there and the filter
re-acquires it from the stars (counted as ``reinitializations``); the memory, not the
estimate, is what this run measures.

Printed per bag: data hours, messages, peak RSS (MiB), wall and CPU time, and the ratio to
the shortest bag's RSS.  Targets (issue 17): RSS(24 h) ≤ 250 MiB, RSS(7200 s)/RSS(600 s)
≤ 1.2.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CACHE = Path(__file__).parent / ".cache"
SEGMENT_S = 7200.0
DAY_SEGMENTS = 12


def simulated(duration: float) -> Path:
    """A cached ``psce_rotations`` bag of ``duration`` s (see psce_speed.ensure_bag)."""
    sys.path.insert(0, str(Path(__file__).parent))
    from psce_speed import ensure_bag

    return ensure_bag(duration)


def day_bag(segments: int = DAY_SEGMENTS) -> Path:
    """A directory of ``segments`` consecutive 2 h simulations (cached): one split bag."""
    from stellar_cal_ros.sim.scenarios import get_scenario
    from stellar_cal_ros.sim.world import simulate, write_simulation

    hours = int(segments * SEGMENT_S / 3600)
    out = CACHE / f"psce_rotations_{hours}h"
    done = out / "complete"
    if done.exists():
        return out
    out.mkdir(parents=True, exist_ok=True)
    base = get_scenario("psce_rotations")
    for k in range(segments):
        path = out / f"part_{k:02d}.mcap"
        if path.exists():
            continue
        t = time.perf_counter()
        sc = dataclasses.replace(base, start_posix=base.start_posix + k * SEGMENT_S)
        paths = write_simulation(simulate(sc, duration=SEGMENT_S, seed=100 + k), path)
        # only the first segment's calibration files are kept (one prior for the day)
        for key in ("truth", "prior", "meta"):
            if k == 0:
                paths[key].rename(out.parent / f"{out.name}.{paths[key].name.split('.', 1)[1]}")
            else:
                paths[key].unlink()
        print(f"segment {k + 1}/{segments} simulated in {time.perf_counter() - t:.0f} s",
              file=sys.stderr, flush=True)
    done.touch()
    return out


def prior_of(bag: Path) -> Path:
    """The ``.prior.yaml`` beside a bag file or directory."""
    return bag.parent / (bag.name.removesuffix(".mcap") + ".prior.yaml")


def peak_rss(bag: Path, residuals: bool) -> dict:
    """Run one replay in a fresh process; its peak RSS (MiB), wall and CPU seconds."""
    tmp = Path(tempfile.mkdtemp(prefix="replay_memory_"))
    cmd = [sys.executable, "-m", "stellar_cal_ros", "replay", str(bag), "--method", "psce",
           "--prior", str(prior_of(bag)), "-o", str(tmp / "out.yaml"), "-q"]
    if residuals:
        cmd += ["--residuals", str(tmp / "out.csv")]
    timer = shutil.which("time") or ("/usr/bin/time" if os.path.exists("/usr/bin/time")
                                      else None)
    t = time.perf_counter()
    try:
        if timer:
            p = subprocess.run([timer, "-v"] + cmd, cwd=ROOT, capture_output=True, text=True,
                               check=False)
            m = re.search(r"Maximum resident set size \(kbytes\): (\d+)", p.stderr)
            rss = int(m.group(1)) / 1024 if m else float("nan")
            mu = re.search(r"User time \(seconds\): ([\d.]+)", p.stderr)
            ms = re.search(r"System time \(seconds\): ([\d.]+)", p.stderr)
            cpu = float(mu.group(1)) + float(ms.group(1)) if mu and ms else float("nan")
        else:
            rss, cpu, p = _poll(cmd)
        wall = time.perf_counter() - t
        if p.returncode != 0:
            raise RuntimeError(f"replay failed ({p.returncode}): {p.stderr[-2000:]}")
        text = p.stdout
        m = re.search(r"reinitializations\D+(\d+)", text)
        return {"rss_mib": rss, "wall_s": wall, "cpu_s": cpu,
                "reacquired": int(m.group(1)) if m else None}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _poll(cmd: list[str]):
    """Run ``cmd`` polling VmHWM (no /usr/bin/time)."""
    import resource

    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    hwm = 0.0
    status = Path(f"/proc/{proc.pid}/status")
    while proc.poll() is None:
        try:
            for line in status.read_text().splitlines():
                if line.startswith("VmHWM:"):
                    hwm = max(hwm, int(line.split()[1]) / 1024)
        except OSError:
            pass
        time.sleep(0.05)
    out, err = proc.communicate()
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    return hwm, cpu, subprocess.CompletedProcess(cmd, proc.returncode, out, err)


def bag_info(bag: Path) -> tuple[float, int]:
    """(data seconds, messages) of a bag."""
    from stellar_cal_ros.io.bag import BagReader

    with BagReader(bag) as r:
        return r.duration_s, sum(t.message_count for t in r.topics().values())


def main(argv=None) -> int:
    """Command line entry."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--durations", default="600,1800,7200",
                    help="comma-separated bag lengths, s")
    ap.add_argument("--day", action="store_true", help="add the 24 h split bag")
    ap.add_argument("--residuals", action="store_true", default=True,
                    help="stream the residual table too (default on)")
    ap.add_argument("--no-residuals", dest="residuals", action="store_false")
    args = ap.parse_args(argv)
    bags = [simulated(float(d)) for d in args.durations.split(",") if d]
    if args.day:
        bags.append(day_bag())
    rows = []
    for bag in bags:
        span, n = bag_info(bag)
        r = peak_rss(bag, args.residuals)
        rows.append((bag, span, n, r))
        print(f"{bag.name}: {span / 3600:.2f} h, peak RSS {r['rss_mib']:.0f} MiB",
              file=sys.stderr, flush=True)
    base = rows[0][3]["rss_mib"]
    print(f"replay --method psce{' --residuals' if args.residuals else ''} -q, "
          f"{os.cpu_count()} cpus, load average {os.getloadavg()[0]:.1f}")
    print(f"{'bag':28s} {'hours':>6s} {'messages':>9s} {'peak RSS MiB':>13s} "
          f"{'/ first':>8s} {'wall s':>7s} {'cpu s':>7s} {'x real':>7s}")
    for bag, span, n, r in rows:
        print(f"{bag.name:28s} {span / 3600:6.2f} {n:9d} {r['rss_mib']:13.1f} "
              f"{r['rss_mib'] / base:8.2f} {r['wall_s']:7.1f} {r['cpu_s']:7.1f} "
              f"{span / r['wall_s']:7.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
