"""The parent's CPU per second of wall that an idle local Dask cluster takes (issue 24 item 2).

The diagnosis' scheduler and one nanny per worker run in the parent's event loop, woken by
Dask's timers whatever the work: that CPU grows with a round's wall time, on the cores the
workers share.  This starts the diagnosis' own cluster
(:func:`stellar_cal_ros.diagnosis.parallel.local_cluster`, its settings
:data:`~stellar_cal_ros.diagnosis.parallel.LOCAL_DASK_CONFIG`) and, with ``--defaults``,
the same cluster at Dask's defaults (the profiler off as before), lets each idle for
``--seconds`` and prints the parent's CPU per second of wall and the parent's timers
(scheduler and nannies) per second.  Interleaved, ``--repeat`` times::

    python benchmarks/dask_idle.py --defaults --repeat 2
"""

from __future__ import annotations

import argparse
import os
import time
from unittest import mock

from stellar_cal_ros.diagnosis import parallel


def idle(seconds: float) -> tuple[float, float]:
    """Parent CPU ms per wall second and timer calls per second of an idle 2-worker cluster."""
    from distributed import Client

    with parallel.local_cluster(2, None) as cluster, Client(cluster):
        time.sleep(2.0)  # past the start
        servers = [cluster.scheduler, *cluster.workers.values()]
        timers = sum(1000 / pc.callback_time for s in servers
                     for pc in s.periodic_callbacks.values() if pc.is_running())
        c0, w0 = time.process_time(), time.perf_counter()
        time.sleep(seconds)
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    return 1000 * cpu / wall, timers


def main(argv: list[str] | None = None) -> int:
    """Print one row per idle cluster."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--defaults", action="store_true",
                    help="also Dask's defaults (the workers' profiler off, as before)")
    args = ap.parse_args(argv)
    before = {"distributed.worker.profile.enabled": False}
    settings = [("LOCAL_DASK_CONFIG", parallel.LOCAL_DASK_CONFIG)]
    if args.defaults:
        settings.insert(0, ("Dask's defaults", before))
    print(f"load average {os.getloadavg()[0]:.1f} at the start")
    for _ in range(args.repeat):
        for name, config in settings:
            with mock.patch.object(parallel, "LOCAL_DASK_CONFIG", config):
                ms, timers = idle(args.seconds)
            print(f"{name:>18s}: parent {ms:5.1f} ms CPU per s of wall, "
                  f"its timers {timers:5.1f} calls per s", flush=True)
    print(f"load average {os.getloadavg()[0]:.1f} at the end")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
