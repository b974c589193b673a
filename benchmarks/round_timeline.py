"""A diagnosis round's schedule, measured so that the machine's load does not decide it.

Runs ``stellar-cal diagnose BAG --workers W`` (the 'several' round of
``discovery_speed.py`` by default) with a timeline (:mod:`stellar_cal_ros.diagnosis.timeline`):
every run and statistic of the bag, where it ran, its wall span and its CPU seconds; every
batch the parent hands out and its CPU between them.  Then it replays the schedule with
each piece of work lasting its CPU seconds -- the same runs on the same processes in the
same order, each batch handed out when the parent's serial work before it is done, a worker
free once its start (imports, kernels) is done -- which is the command's time on idle cores
(``idle s``).  Also printed: the parent's serial CPU, each process's start, the sum of the
CPU of every piece (``CPU s``: the command's work), and the measured wall and CPU of the
whole process tree (the latter includes Dask's scheduler and nannies).

The replay leaves out: the CPU of Dask's scheduler, the nannies and the workers' idle
loops (they share the cores with the runs: a lower bound on a 2-core machine where the
parent and the two workers are three processes), the pickling of the results, the load's
effect on each run's CPU (cache sharing).  It is checked against a wall measurement on a
quiet machine (doc/benchmarks.md).

Run::

    python benchmarks/round_timeline.py --workers 1,2          # the several round
    python benchmarks/round_timeline.py --workers 0,1,2 --repeat 2 --tasks
    python benchmarks/round_timeline.py --bag BAG.mcap --workers 1,2 --keep DIR
    python benchmarks/round_timeline.py --show DIR --tasks   # print what --keep kept
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from discovery_speed import measure, several_bag  # noqa: E402

from stellar_cal_ros.diagnosis import timeline  # noqa: E402


def replay(events: list[dict]) -> dict:
    """The recorded schedule replayed with every piece lasting its CPU seconds.

    The parent's events (a batch handed out, a batch's results in hand) in their order;
    between two of them the parent's CPU beyond its own runs is serial work.  A batch's
    runs start when it is handed out and their process is free (each process runs its
    runs in the recorded order); the parent goes on when the runs it waits for are done.
    """
    batches = {e["batch"]: e for e in events if e["kind"] == "batch"}
    if not batches:
        raise ValueError("no batch on the timeline")
    parent = next(iter(batches.values()))["pid"]
    tasks = sorted((e for e in events if e["kind"] == "task"), key=lambda e: e["start"])
    for t in tasks:  # started and never asked for (its batch was never closed): handed
        if t["batch"] not in batches:  # out with the last batch before it started
            t["batch"] = max((b["batch"] for b in batches.values()
                              if b["submit"] <= t["start"]), default=min(batches))
    starts = {e["pid"]: e for e in events if e["kind"] == "process"}
    cluster = next((e for e in events if e["kind"] == "cluster"), None)
    end = next((e for e in events if e["kind"] == "end"), None)
    by_pid: dict[int, list[dict]] = defaultdict(list)
    for t in tasks:
        by_pid[t["pid"]].append(t)
    by_pid = dict(by_pid)
    # a worker is free once the cluster was asked for (the parent's CPU then) and its own
    # start is done; the parent runs its in-process runs when it hands them out
    free = {pid: (cluster["cpu"] if cluster else 0.0) + starts[pid]["cpu"]
            for pid in by_pid if pid != parent}
    free[parent] = 0.0
    nxt = dict.fromkeys(by_pid, 0)
    marks = sorted([(b["submit"], "open", b) for b in batches.values()]
                   + [(b["done"], "close", b) for b in batches.values()],
                   key=lambda m: (m[0], m[1] == "open"))
    if end is not None:
        marks.append((end["time"], "end", end))
    clock = serial = beside = 0.0
    cpu_prev, t_prev = 0.0, None
    submit: dict[int, float] = {}
    waiting = 0  # batches handed out and not yet in hand
    for when, what, b in marks:
        cpu_now = b["cpu0"] if what == "open" else b["cpu1"] if what == "close" else b["cpu"]
        own = sum(t["cpu"] for t in by_pid.get(parent, ())
                  if t_prev is not None and t_prev <= t["start"] < when)
        gap = max(cpu_now - cpu_prev - own, 0.0)
        if waiting:  # the parent waits: its CPU is Dask's (scheduler, client), beside runs
            beside += gap
        else:  # the parent works: serial
            clock += gap
            serial += gap
        cpu_prev, t_prev = cpu_now, when
        waiting += (what == "open") - (what == "close")
        if what == "open":
            submit[b["batch"]] = clock
        elif what == "close":
            for pid, lst in by_pid.items():
                while nxt[pid] < len(lst) and lst[nxt[pid]]["batch"] in submit:
                    t = lst[nxt[pid]]
                    t["sim_start"] = max(free[pid], submit[t["batch"]])
                    free[pid] = t["sim_end"] = t["sim_start"] + t["cpu"]
                    nxt[pid] += 1
            waited = [t for t in tasks if t["batch"] == b["batch"] and t["key"] in b["wait"]]
            for key in set(b["wait"]) - {t["key"] for t in waited}:
                # a run made ahead in an earlier batch, taken (and waited for) with this one
                earlier = [t for t in tasks if t["key"] == key and t["batch"] < b["batch"]]
                if earlier:
                    waited.append(max(earlier, key=lambda t: t["batch"]))
            clock = max([clock] + [t["sim_end"] for t in waited])
    for t in tasks:  # never waited for (runs ahead nobody took)
        t.setdefault("sim_start", float("nan"))
        t.setdefault("sim_end", float("nan"))
    work = sum(t["cpu"] for t in tasks) + serial + beside + sum(
        s["cpu"] for pid, s in starts.items() if pid != parent)
    return {"idle": clock, "serial": serial, "beside": beside, "work": work, "tasks": tasks,
            "parent": parent,
            "starts": {pid: s["cpu"] for pid, s in starts.items() if pid != parent},
            "batches": len(batches)}


def show(r: dict, workers: str, m: dict, with_tasks: bool, cores: int) -> None:
    """One row (and the tasks with ``with_tasks``)."""
    starts = " ".join(f"{c:.1f}" for c in r["starts"].values()) or "-"
    bound = m["cpu"] / cores
    print(f"{workers:>7s} {m['wall']:7.1f} {m['cpu']:7.1f} {m['rss_mb']:6.0f} {r['work']:7.1f} "
          f"{r['idle']:7.1f} {bound:7.1f} {max(r['idle'], bound):7.1f} {r['serial']:7.1f} "
          f"{r['beside']:7.1f}   {starts}", flush=True)
    if with_tasks:
        t0 = min(t["start"] for t in r["tasks"])
        for t in r["tasks"]:
            where = "parent" if t["pid"] == r["parent"] else f"pid {t['pid']}"
            print(f"          b{t['batch']:<3d} {t['key'][:40]:40s} {where:10s} "
                  f"wall {t['start'] - t0:6.1f}-{t['end'] - t0:6.1f}  CPU {t['cpu']:5.1f} "
                  f"(bag {t['read']:.1f})  idle {t['sim_start']:6.1f}-{t['sim_end']:6.1f}")


HEADER = (f"{'workers':>7s} {'wall s':>7s} {'CPU s':>7s} {'RSS MB':>6s} {'work s':>7s} "
          f"{'path s':>7s} {'CPU/n':>7s} {'idle s':>7s} {'serial':>7s} {'dask':>7s}   "
          "worker starts (CPU s)")
LEGEND = ("wall, CPU, RSS: measured (CPU of the process tree, peak RSS of the tree); work: "
          "the timeline's CPU (runs, parent, worker starts); path: the schedule replayed "
          "with CPU durations; CPU/n: the tree's CPU over the cores; idle: the larger of "
          "the two (the time on idle cores); serial: the parent's CPU outside runs; dask: "
          "the parent's CPU while it waits (Dask's scheduler and client)")


def main(argv: list[str] | None = None) -> int:
    """Print, per command: measured wall, CPU and RSS; the timeline's work, path, serial."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bag", type=Path, help="a bag with BAG.prior.yaml beside it "
                    "(default: the 'several' round's 900 s bag)")
    ap.add_argument("--workers", default="1,2", help="worker counts, interleaved ('default': "
                    "no --workers, the command line's automatic choice)")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--cores", type=int, default=2, help="cores of the idle machine")
    ap.add_argument("--tasks", action="store_true", help="every task of each command")
    ap.add_argument("--keep", type=Path, help="copy each timeline and diagnosis.json into "
                    "this folder")
    ap.add_argument("--show", type=Path, help="only print the timelines --keep kept there")
    args = ap.parse_args(argv)
    if args.show:
        print(HEADER)
        for path in sorted(args.show.glob("timeline_w*.jsonl")):
            m = json.loads(path.with_suffix(".json").read_text())
            events = [json.loads(line) for line in path.read_text().splitlines()]
            show(replay(events), m["workers"], m, args.tasks, args.cores)
        print(LEGEND)
        return 0
    bag = args.bag or several_bag()
    prior = bag.with_suffix(".prior.yaml")
    print(f"load average {os.getloadavg()[0]:.1f} at the start; {bag.name}")
    print(HEADER)
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(args.repeat):
            for w in args.workers.split(","):
                path = Path(tmp) / f"timeline{w}_{rep}.jsonl"
                os.environ[timeline.ENV] = str(path)
                out = Path(tmp) / f"out{w}_{rep}"
                flag = [] if w == "default" else ["--workers", w]
                m = measure(["diagnose", str(bag), "--calibration", str(prior), "--method",
                             "psce", "--no-plots", *flag, "-o", str(out)])
                del os.environ[timeline.ENV]
                m["workers"] = w
                del m["stdout"]
                events = [json.loads(line) for line in path.read_text().splitlines()]
                show(replay(events), w, m, args.tasks, args.cores)
                if args.keep:
                    args.keep.mkdir(parents=True, exist_ok=True)
                    name = f"timeline_w{w}_{rep}"
                    (args.keep / f"{name}.jsonl").write_text(path.read_text())
                    (args.keep / f"{name}.json").write_text(json.dumps(m))
                    (args.keep / f"diagnosis_w{w}_{rep}.json").write_text(
                        (out / "diagnosis.json").read_text())
    print(f"load average {os.getloadavg()[0]:.1f} at the end.  {LEGEND}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
