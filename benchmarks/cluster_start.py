"""What starting the diagnosis' local Dask cluster costs: spawned, forked, fork server (24.2).

The automatic executor (``workers=None``, :mod:`stellar_cal_ros.diagnosis.parallel`)
starts a ``LocalCluster`` once a batch of runs would take :data:`~stellar_cal_ros.
diagnosis.parallel.CLUSTER_PAYS_S` CPU seconds in the parent.  By then the parent has
imported the package, loaded the compiled kernels and read the bag.  This measures, in
one process as the automatic executor has it (the bag read and one run made here first):

* ``ready``: wall seconds from asking for the cluster until each worker has returned a
  first statistic of the bag (its start, imports, kernel loads and bag read);
* ``first run``: wall seconds of the same short run then on each worker, against the
  parent's (a worker's first run pays what is left of its kernel loads);
* ``CPU``: CPU seconds of the parent and its children over the start (psutil, children
  read before the cluster closes).

Worker processes are spawned (Dask's default: fresh interpreters), forked from the parent
(``fork``: the imports, the loaded kernels and the bag read are inherited, but the parent
runs threads), or forked from multiprocessing's fork server (``forkserver``, the package's
default on Linux: a fresh single-threaded process that imports the package and reads the
bag once, :func:`~stellar_cal_ros.diagnosis.parallel.local_cluster`).  The fork server
starts with the first such cluster of a process and serves the later ones: a repeat's
``forkserver`` row after the first is a warm server (as a later round's cluster).

Run::

    python benchmarks/cluster_start.py --bag benchmarks/.cache/psce_rotations_600s.mcap
    python benchmarks/cluster_start.py --bag BAG.mcap --method spawn,fork,forkserver --repeat 2
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from pathlib import Path


def _tree_cpu() -> float:
    from stellar_cal_ros.diagnosis.parallel import tree_cpu

    return sum(tree_cpu().values())


def _run_seconds(bag, spec, prior) -> tuple[float, float]:
    """Wall and CPU seconds of the current model's run where this runs."""
    from stellar_cal_ros.diagnosis.runstats import evaluate

    t, c = time.perf_counter(), time.process_time()
    out = evaluate(bag, spec, prior, (), 0.5)
    assert out.ok, out.error
    return time.perf_counter() - t, time.process_time() - c


def start(bag: str, method: str, spec, prior) -> dict[str, float]:
    """One cluster of two workers started the way ``method`` says; its costs."""
    from distributed import Client

    from stellar_cal_ros.diagnosis.parallel import local_cluster
    from stellar_cal_ros.diagnosis.runstats import bag_facts, load_bag

    logging.getLogger("distributed").setLevel(logging.ERROR)
    cpu0, t0 = _tree_cpu(), time.perf_counter()
    cluster = local_cluster(2, bag, method)  # the diagnosis' own start
    client = Client(cluster)
    up = time.perf_counter() - t0
    workers = list(client.scheduler_info()["workers"])
    facts = [client.submit(lambda b: bag_facts(load_bag(b)), bag, workers=[w], pure=False)
             for w in workers]
    client.gather(facts)
    ready = time.perf_counter() - t0
    cpu_ready = _tree_cpu() - cpu0
    runs = [client.submit(_run_seconds, bag, spec, prior, workers=[w], pure=False)
            for w in workers]
    first = client.gather(runs)
    cpu = _tree_cpu() - cpu0
    client.close()
    cluster.close()
    return {"up": up, "ready": ready, "cpu_ready": cpu_ready,
            "first": max(f[0] for f in first), "first_cpu": max(f[1] for f in first),
            "cpu": cpu}


def main(argv: list[str] | None = None) -> int:
    """Print one line per cluster start: its wall seconds and CPU."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bag", type=Path, required=True, help="BAG.mcap, BAG.prior.yaml beside")
    ap.add_argument("--method", default="spawn,fork,forkserver")
    ap.add_argument("--repeat", type=int, default=1)
    args = ap.parse_args(argv)
    from stellar_cal_ros.diagnosis.discover import method_spec
    from stellar_cal_ros.diagnosis.runstats import load_bag
    from stellar_cal_ros.io.calibration import load_calibration

    bag = str(args.bag.resolve())
    prior = load_calibration(args.bag.with_suffix(".prior.yaml"))
    spec = method_spec("psce")
    t = time.perf_counter()
    load_bag(bag)
    read = time.perf_counter() - t
    here = [_run_seconds(bag, spec, prior) for _ in range(2)]
    print(f"load average {os.getloadavg()[0]:.1f}; {args.bag.name}: bag read here {read:.2f} s, "
          f"the run here {here[0][0]:.2f} s wall {here[0][1]:.2f} CPU-s (first), "
          f"{here[1][0]:.2f} s wall {here[1][1]:.2f} CPU-s (second)")
    print(f"{'start':>10} {'up s':>6} {'ready s':>8} {'CPU s':>6} {'1st run s':>10} "
          f"{'its CPU':>8} {'CPU s':>6}")
    for _ in range(args.repeat):
        for method in args.method.split(","):
            m = start(bag, method, spec, prior)
            print(f"{method:>10} {m['up']:6.2f} {m['ready']:8.2f} {m['cpu_ready']:6.2f} "
                  f"{m['first']:10.2f} {m['first_cpu']:8.2f} {m['cpu']:6.2f}")
    print(f"load average {os.getloadavg()[0]:.1f} at the end.  up: LocalCluster and Client "
          "made; ready: every worker has read the bag (a statistic of it back); CPU s: the "
          "process tree's over the start to ready, then to the first run's end on both "
          "workers (beside each other); 1st run s, its CPU: the longer of the two workers' "
          "first run (wall; CPU seconds of its process)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
