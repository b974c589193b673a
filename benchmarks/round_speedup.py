"""1 -> 2 workers on a diagnosis round, from CPU accounting: what limits the speedup.

The wall time of a round on a shared machine says the load, not the code.  This reads the
timelines :mod:`benchmarks.round_timeline` records (every run's CPU seconds, the batches the
parent hands out, the parent's CPU between them) and prints, per timeline:

* ``serial``: the parent's CPU outside runs (imports, reading, screening, line tests,
  ranking); ``dask`` (with workers): their starts and Dask's CPU in the parent while it
  waits (beside the runs: counted in ``work``, not on the paths);
* ``tasks``: the runs' CPU seconds (the part two workers can split), their number, the
  largest, and whether the largest of a batch was handed out last;
* ``work``: everything (serial + tasks);
* ``path inf``: the critical path on endless workers -- the serial part plus, for each
  batch, its longest run (the batches as the parent waits for them; batches it had out
  at once count as one);
* ``path 2``: the same on two workers, each batch's runs placed largest first on the
  less busy worker (LPT);
* ``ideal``: work of the one-worker timeline / ``path 2`` -- the 1 -> 2 speedup the round's
  batches allow when every run costs on two workers what it costs alone;
* ``replay``: ``round_timeline``'s replay of the recorded schedule (two-worker timelines:
  the runs where and when they ran, with their measured CPU), and the 1 -> 2 ratio of the
  one-worker work over it;
* ``wall``: the measured wall seconds (the load's, on a shared machine).

Run::

    python benchmarks/round_speedup.py --workers 1,2 --keep DIR      # measure, then print
    python benchmarks/round_speedup.py --show DIR                    # print what DIR holds
    python benchmarks/round_speedup.py --bag BAG.mcap --workers 1,2  # another round
    python benchmarks/round_speedup.py --parts          # the base run's pieces, in process

``--parts``: the current model's base run (the round's largest serial piece) taken apart in
this process, CPU seconds: the filter alone, with the screening of all candidates and of
half of them, with its residuals kept, and the base run as the round makes it (half the
screening, residuals, the stars' noise: the window's estimate and the early stretch's).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
import round_timeline  # noqa: E402


def lpt(cpus: list[float], n: int) -> float:
    """Makespan of ``cpus`` on ``n`` workers, largest first on the least busy one."""
    loads = [0.0] * n
    for c in sorted(cpus, reverse=True):
        loads[loads.index(min(loads))] += c
    return max(loads)


def as_alone(events: list[dict], one: list[dict]) -> float:
    """The replay of a two-worker timeline with each run at its one-worker CPU seconds.

    Separates the schedule (the code's) from the runs' CPU beside each other (the load's,
    the shared cores'): a run whose key is once in each timeline takes the one-worker
    timeline's CPU; the others (the screening part, the probes' ``measure_on_bag``) are
    scaled by the matched runs' one-worker / two-worker CPU.  The parent's serial CPU and
    the workers' starts stay as measured.
    """
    def by_key(evs):
        out: dict[str, list[float]] = defaultdict(list)
        for e in evs:
            if e["kind"] == "task":
                out[e["key"]].append(e["cpu"])
        return out

    two, alone = by_key(events), by_key(one)
    same = [k for k in two if len(two[k]) == 1 and len(alone.get(k, ())) == 1]
    k = (sum(alone[key][0] for key in same) / sum(two[key][0] for key in same)
         if same else 1.0)
    scaled = []
    for e in events:
        e = dict(e)
        if e["kind"] == "task":
            e["cpu"] = alone[e["key"]][0] if e["key"] in same else e["cpu"] * k
        scaled.append(e)
    return round_timeline.replay(scaled)["idle"]


def analyse(events: list[dict]) -> dict:
    """Serial and parallel CPU, the batches' critical paths, of one timeline."""
    r = round_timeline.replay([dict(e) for e in events])
    tasks = r["tasks"]
    # batches the parent had out at once (a run started ahead, ``Runs.later``) are one
    group, top, last = {}, -1.0, 0
    for b in sorted((e for e in events if e["kind"] == "batch"), key=lambda e: e["submit"]):
        last = last if b["submit"] < top else b["batch"]
        group[b["batch"]], top = last, max(top, b["done"])
    by_batch: dict[int, list[dict]] = defaultdict(list)
    for t in tasks:
        by_batch[group.get(t["batch"], t["batch"])].append(t)
    end = next(e for e in events if e["kind"] == "end")
    parent_runs = sum(t["cpu"] for t in tasks if t["pid"] == r["parent"])
    # in process the parent's CPU holds its runs; with workers the replay split it into
    # its serial work and Dask's CPU while it waits (beside the runs, as the workers' starts)
    serial = end["cpu"] - parent_runs if not r["starts"] else r["serial"]
    dask = r["beside"] + sum(r["starts"].values())
    cpus = [t["cpu"] for t in tasks]
    batches = [sorted(by_batch[b], key=lambda t: t["start"]) for b in sorted(by_batch)]
    last_largest = sum(1 for b in batches if len(b) > 1
                       and b[-1]["cpu"] == max(t["cpu"] for t in b))
    return {"serial": serial, "tasks": sum(cpus), "n": len(cpus), "largest": max(cpus),
            "work": serial + dask + sum(cpus), "dask": dask,
            "multi": sum(len(b) > 1 for b in batches),
            "last_largest": last_largest,
            "inf": serial + sum(max(t["cpu"] for t in b) for b in batches),
            "two": serial + sum(lpt([t["cpu"] for t in b], 2) for b in batches),
            "replay": r["idle"], "batches": batches}


HEADER = (f"{'timeline':>14s} {'wall':>6s} {'serial':>6s} {'dask':>5s} {'tasks':>6s} "
          f"{'n':>3s} {'max':>5s} "
          f"{'work':>6s} {'path inf':>8s} {'path 2':>6s} {'ideal':>6s} {'replay':>6s} "
          f"{'1->2':>5s}  multi-run batches (largest handed out last)")


def show(folder: Path, detail: bool) -> None:
    """One row per kept timeline; ideal and 1 -> 2 against the folder's one-worker work."""
    rows = []
    for path in sorted(folder.glob("timeline_w*.jsonl")):
        m = json.loads(path.with_suffix(".json").read_text())
        events = [json.loads(line) for line in path.read_text().splitlines()]
        rows.append((path.stem.removeprefix("timeline_"), m, analyse(events)))
    ones = [a["work"] for name, m, a in rows if m["workers"] in ("0", "1")]
    one = min(ones) if ones else float("nan")
    print(HEADER)
    for name, m, a in rows:
        print(f"{name:>14s} {m['wall']:6.1f} {a['serial']:6.1f} {a['dask']:5.1f} "
              f"{a['tasks']:6.1f} {a['n']:3d} "
              f"{a['largest']:5.1f} {a['work']:6.1f} {a['inf']:8.1f} {a['two']:6.1f} "
              f"{one / a['two']:5.2f}x {a['replay']:6.1f} {one / a['replay']:4.2f}x  "
              f"{a['multi']} ({a['last_largest']})")
        if detail:
            for b in a["batches"]:
                runs = ", ".join(f"{t['key'][:28]} {t['cpu']:.2f}" for t in b)
                print(f"{'':16s}b{b[0]['batch']:<3d} {runs}")
    print("CPU seconds.  ideal = the one-worker work / path 2 (every run as cheap on two "
          "workers as alone); 1->2 = the one-worker work / the two-worker schedule replayed")
    # each two-worker timeline replayed with its runs at the one-worker CPU (same repeat)
    for path in sorted(folder.glob("timeline_w2_*.jsonl")):
        rep = path.stem.rsplit("_", 1)[1]
        one = [folder / f"timeline_w{w}_{rep}.jsonl" for w in ("1", "0")]
        one = next((p for p in one if p.exists()), None)
        if one is None:
            continue
        read = [[json.loads(line) for line in p.read_text().splitlines()] for p in (path, one)]
        work = analyse(read[1])["work"]
        idle = as_alone(*read)
        print(f"{path.stem.removeprefix('timeline_')} with its runs at {one.stem[9:]}'s CPU: "
              f"replay {idle:.1f}, 1->2 {work / idle:.2f}x (work {work:.1f})")


#: the several round's candidates (``discovery_speed.several_bag``, round 1)
CANDIDATES = ("proper_motion", "aberration", "refraction", "gyro_scale_factor",
              "gyro_misalignment", "radial_k3", "time_offset", "pixel_aspect",
              "image_plane_tilt", "thermal_focal_length")


def parts(bag: Path, candidates: tuple[str, ...], repeat: int) -> None:
    """CPU seconds of the base run's pieces (in this process, after one warm-up run)."""
    import time

    from stellar_cal_ros.diagnosis import noise, runstats
    from stellar_cal_ros.diagnosis.discover import method_spec
    from stellar_cal_ros.io.calibration import load_calibration

    prior = load_calibration(bag.with_suffix(".prior.yaml"))
    spec = method_spec("psce")
    runstats.load_bag(str(bag))
    calls: list[float] = []
    inner = noise.star_noise

    def timed(*a, **k):
        t = time.process_time()
        try:
            return inner(*a, **k)
        finally:
            calls.append(time.process_time() - t)

    noise.star_noise = timed
    half = candidates[: len(candidates) // 2]
    variants = [("warm-up", {}), ("filter alone", {}),
                (f"screening {len(candidates)}", {"screen": candidates}),
                (f"screening {len(half)}", {"screen": half}),
                ("residuals kept", {"keep_residuals": True}),
                ("base run", {"screen": half, "keep_residuals": True, "star_noise": True})]
    for _ in range(repeat):
        for label, kw in variants:
            calls.clear()
            t = time.process_time()
            out = runstats.evaluate(str(bag), spec, prior, (), 0.5, **kw)
            stars = " + ".join(f"{c:.2f}" for c in calls)
            print(f"{label:>16s} {time.process_time() - t:6.2f} CPU-s"
                  + (f"  (stars' noise: window + early {stars})" if calls else "")
                  + (f"  error {out.error}" if out.error else ""), flush=True)
    noise.star_noise = inner


def main(argv: list[str] | None = None) -> int:
    """Measure with round_timeline (or read --show DIR) and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bag", type=Path, help="default: the 'several' round's 900 s bag")
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--keep", type=Path, help="keep the timelines here")
    ap.add_argument("--show", type=Path, help="only print the timelines kept there")
    ap.add_argument("--detail", action="store_true", help="every batch's runs")
    ap.add_argument("--parts", action="store_true", help="the base run's pieces, in process")
    args = ap.parse_args(argv)
    if args.parts:
        from discovery_speed import several_bag

        parts(args.bag or several_bag(), CANDIDATES, args.repeat)
        return 0
    if args.show:
        show(args.show, args.detail)
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        keep = args.keep or Path(tmp)
        extra = ["--bag", str(args.bag)] if args.bag else []
        round_timeline.main([*extra, "--workers", args.workers, "--repeat",
                             str(args.repeat), "--keep", str(keep)])
        show(keep, args.detail)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
