"""Campaign speed-up: the same campaign on 1 and on 2 (or more) local Dask workers.

Usage::

    python benchmarks/campaign_speed.py                          # 40 runs of 600 s, 1 vs 2
    python benchmarks/campaign_speed.py --runs 10 --duration 120 # a small version
    python benchmarks/campaign_speed.py --workers 1,2 --repeat 2 # interleaved, twice

Each measurement starts its own LocalCluster (single-threaded worker processes) in a fresh
output folder and times the whole campaign (cluster start, every run, the Parquet table) and,
separately, the cluster start.  The worker counts are interleaved (1, 2, 1, 2, …) so that a
change of the machine's load hits both.  The estimates of every run must be identical
whatever the number of workers (checked).  Acceptance (issue 16): 40 runs, 2 workers ≥ 1.8×
faster than 1, on a quiet machine with at least 2 free cores.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

from stellar_cal_ros.campaign.runner import dask_client, run_campaign
from stellar_cal_ros.campaign.spec import runs_from_spec


def measure(runs_spec: dict, workers: int, folder: Path) -> tuple[float, float, list[dict]]:
    """(campaign wall time, cluster start time, rows) of one measurement."""
    t0 = time.perf_counter()
    with dask_client(workers=workers) as client:
        client.wait_for_workers(workers)
        start = time.perf_counter() - t0
        runs = runs_from_spec(runs_spec, folder, folder)
        res = run_campaign(runs, folder, client=client, progress=False)
    total = time.perf_counter() - t0
    if res.failed:
        raise SystemExit(f"{res.failed} runs failed: {res.rows[0].get('error')}")
    return total, start, res.rows


def main(argv=None) -> int:
    """Print the timings and the speed-up."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=40)
    ap.add_argument("--duration", type=float, default=600.0, help="seconds per simulated run")
    ap.add_argument("--workers", default="1,2", help="comma-separated worker counts")
    ap.add_argument("--repeat", type=int, default=1, help="measurements per worker count")
    args = ap.parse_args(argv)
    counts = [int(w) for w in args.workers.split(",")]
    spec = {"run": {"scenario": "psce_rotations", "duration": args.duration, "method": "psce",
                    "steps": ["simulate", "replay"]},
            "seeds": args.runs}
    print(f"== campaign of {args.runs} PSCE runs of {args.duration:.0f} s (simulate + replay) "
          f"on {os.cpu_count()} cores; load average before: "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())} ==")
    print(f"{'workers':>7s} {'wall s':>8s} {'start s':>8s} {'runs s':>8s} {'mean run s':>10s}")
    times: dict[int, list[float]] = {w: [] for w in counts}
    reference = None
    for _ in range(args.repeat):
        for w in counts:
            with tempfile.TemporaryDirectory() as tmp:
                total, start, rows = measure(spec, w, Path(tmp))
            est = [{k: v for k, v in r.items() if k.startswith("est.")} for r in rows]
            if reference is None:
                reference = est
            elif est != reference:
                raise SystemExit("estimates differ between worker counts")
            times[w].append(total)
            mean_run = sum(r["t.total"] for r in rows) / len(rows)
            print(f"{w:7d} {total:8.1f} {start:8.1f} {total - start:8.1f} {mean_run:10.2f}",
                  flush=True)
    base = min(times[counts[0]])
    for w in counts[1:]:
        print(f"speed-up {counts[0]} -> {w} workers (best of {args.repeat}, wall): "
              f"{base / min(times[w]):.2f}x")
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())} "
          "(a shared machine: the ratio is only meaningful with free cores)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
