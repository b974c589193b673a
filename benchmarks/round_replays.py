"""Every filter replay of one ``diagnose`` round, and whether one repeats another (issue 24).

Runs ``python -m stellar_cal_ros diagnose BAG ...`` in this process (the arguments after
``--`` are the command line's; default: the 2-h psce round with ``--workers 0``) with
:func:`stellar_cal_ros.methods.replay.replay` wrapped: per replay its CPU-s
(``process_time``), the diagnosis function that asked for it, the bag (``user`` for the
bag object the first replay read, else ``other #k``: the reliability probe's injected
bags), the effects, the consider parameters, the noise scales that differ from 1 and the
run's options.  A replay whose inputs (the same bag object, start calibration, effects,
consider parameters, noise, options) equal an earlier one's is marked ``repeats #k``: its
result could be reused.  At the end the round's CPU-s in process and the replays' share.

Run::

    python benchmarks/round_replays.py [-- diagnose-arguments ...]
"""

from __future__ import annotations

import dataclasses
import runpy
import sys
import time
import traceback
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def _caller() -> str:
    """The innermost diagnosis function on the stack (who asked for the replay)."""
    names = [f.name for f in traceback.extract_stack()[:-2]
             if "diagnosis" in f.filename and f.name not in
             ("_run", "traced", "_evaluate", "evaluate", "map", "run_all", "_on_bag",
              "on_bag_each", "<listcomp>", "run_ahead", "on_bag")]
    return names[-1] if names else "?"


def _noise(noise) -> str:
    """The scales of ``noise`` that differ from the stated ones."""
    if noise is None:
        return "stated"
    moved = [f"{f.name}={getattr(noise, f.name):.3g}" for f in dataclasses.fields(noise)
             if isinstance(getattr(noise, f.name), float)
             and getattr(noise, f.name) != (1.0 if f.name in ("star", "gyro", "accel",
                                                              "star_ar_share") else 0.0)]
    return ",".join(moved) or "stated"


def main() -> int:
    """Run the round with the replays traced; print one row per replay and the totals."""
    args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else None
    if args is None:
        from discovery_speed import ensure_2h_bag

        bag = Path(ensure_2h_bag())
        cal = bag.with_name(bag.name.replace(".mcap", ".prior.yaml"))
        args = ["diagnose", str(bag), "--calibration", str(cal), "--method", "psce",
                "--no-plots", "--workers", "0", "-o", str(Path("round_replays_out"))]
    import stellar_cal_ros.methods.replay as rp

    original = rp.replay
    rows: list[dict] = []
    bags: list[int] = []
    keep: list[object] = []  # (the bags, so that their ids stay theirs)

    def traced(bag, prior, method="psce", effects=None, config=None, **kw):
        if id(bag) not in bags:
            bags.append(id(bag))
            keep.append(bag)
        where = bags.index(id(bag))
        key = (id(bag), id(prior), repr(prior), method, tuple(effects or ()), repr(config),
               repr(sorted((k, repr(v)) for k, v in kw.items())))
        c0 = time.process_time()
        result = original(bag, prior, method, effects, config, **kw)
        first = next((i for i, r in enumerate(rows) if r["key"] == key), None)
        rows.append({"cpu": time.process_time() - c0, "by": _caller(),
                     "bag": "user" if where == 0 else f"other #{where}",
                     "effects": ",".join(effects or ()) or "-",
                     "consider": len(kw.get("consider") or ()),
                     "noise": _noise(kw.get("noise")),
                     "opts": f"tables={kw.get('keep_tables', True)} "
                             f"gyro={kw.get('gyro_fault', 'raise')}",
                     "repeats": "-" if first is None else f"#{first + 1}", "key": key})
        return result

    rp.replay = traced
    sys.argv = ["stellar_cal_ros", *args]
    c0 = time.process_time()
    try:
        runpy.run_module("stellar_cal_ros", run_name="__main__")
    except SystemExit:
        pass
    total = time.process_time() - c0
    print("\n| # | CPU s | asked by | bag | effects | consider | noise | options | repeats |")
    print("|---|---|---|---|---|---|---|---|---|")
    for i, r in enumerate(rows):
        print(f"| {i + 1} | {r['cpu']:.2f} | {r['by']} | {r['bag']} | {r['effects']} | "
              f"{r['consider']} | {r['noise']} | {r['opts']} | {r['repeats']} |")
    spent = sum(r["cpu"] for r in rows)
    print(f"\nround in process: {total:.1f} CPU-s; {len(rows)} replays {spent:.1f} CPU-s; "
          f"repeated: {sum(1 for r in rows if r['repeats'] != '-')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
