"""Family-wise false-alarm rate of the diagnosis on clean bags (issue 21 item 2).

A clean bag holds only what the model holds.  On each, one ``diagnose`` round (noise
measured first, every library candidate, the structure tests) is run from the prior; a
false alarm is a bag with

* any *significant* candidate (Bonferroni at α = 1 % over the candidates),
* any *unexplained* line (Bonferroni at α = 1 % over the regressor × component pairs),
* the noise found not as stated (α = 1 % over the components, and more than 5 % off).

Each rate must be at most α = 1 %; the table gives the count, the rate and its one-sided
95 % upper bound (Clopper–Pearson).  Cases: both methods, with and without the
astrometric (sky) effects in the bag and the model.

Run::

    .venv/bin/python benchmarks/false_alarms.py --seeds 50
    .venv/bin/python benchmarks/false_alarms.py --seeds 10 --cases psce
    .venv/bin/python benchmarks/false_alarms.py --seeds 50 --records fa.jsonl  # resumable
    .venv/bin/python benchmarks/false_alarms.py --seeds 50 --records fa.jsonl --recorded-only \
        --score-levels  # + each candidate's unadjusted score p below 5 % / 1 %: its level

The reduced form in the default suite is ``test/test_false_alarms.py``.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from scipy import stats as sps

from stellar_cal_ros.diagnosis.injection import clean_case
from stellar_cal_ros.diagnosis.run import diagnose

CASES = {"psce": ("psce", False, 300.0), "psce+sky": ("psce", True, 300.0),
         "swaying": ("swaying_base", False, 200.0),
         "swaying+sky": ("swaying_base", True, 200.0)}


def upper(k: int, n: int) -> float:
    """One-sided 95 % Clopper–Pearson upper bound of a rate k / n."""
    return 1.0 if k >= n else float(sps.beta.ppf(0.95, k + 1, n - k))


def diagnose_seed(name: str, seed: int) -> dict[str, object]:
    """Diagnose one clean bag; the record written per seed (so a partial run is kept)."""
    method, sky, duration = CASES[name]
    t0 = time.process_time()
    data, prior, effects = clean_case(method, sky, seed, duration)
    with tempfile.TemporaryDirectory() as tmp:
        s = diagnose(data, prior, method, effects, tmp, plots=False, verbose=False)
    return {"case": name, "seed": seed,
            "candidates": [c["effect"] for c in s["candidates"] if c["significant"]],
            "unexplained": [f"{u['component']} vs {u['regressor']} (t={u['statistic']:.1f})"
                            for u in s["unexplained"]],
            "noise": bool(s["noise"]["rescaled"]), "verdict": s["noise"]["verdict"],
            # every re-run candidate's tests (their null distribution over the seeds)
            "tests": {c["effect"]: {"p_ratio": c["p_value_unadjusted"],
                                    "p_score": c["p_value_score"], "p_adjusted": c["p_value"],
                                    "statistic": c["score"], "dof": c["dof"],
                                    "seen_dof": c.get("seen_dof")}
                      for c in s["candidates"]},
            "cpu": time.process_time() - t0}


def load_records(path: Path | None) -> dict[tuple[str, int], dict]:
    """Per-seed records already written by an earlier (partial) run."""
    done: dict[tuple[str, int], dict] = {}
    if path is not None and path.exists():
        for line in path.read_text().splitlines():
            if line.strip():
                r = json.loads(line)
                done[(r["case"], int(r["seed"]))] = r
    return done


def run_case(name: str, seeds: range, done: dict | None = None,
             recorded_only: bool = False) -> dict[str, object]:
    """Count the alarms of one case.

    The seeds not already in ``done`` are diagnosed, unless ``recorded_only``: then only
    those in ``done`` are counted.
    """
    done = {} if done is None else done
    out = {"candidates": 0, "unexplained": 0, "noise": 0, "n": 0, "lines": [], "cpu": 0.0}
    for seed in seeds:
        r = done.get((name, seed))
        if r is None and recorded_only:
            continue
        if r is None:
            r = done[(name, seed)] = diagnose_seed(name, seed)
        cand, une, noise = r["candidates"], r["unexplained"], r["noise"]
        out["n"] += 1
        out["candidates"] += bool(cand)
        out["unexplained"] += bool(une)
        out["noise"] += bool(noise)
        out["cpu"] += r["cpu"]
        if cand or une or noise:
            out["lines"].append(f"  {name} seed {seed}: candidates {cand}, unexplained {une}, "
                                f"noise {r['verdict']}")
    return out


def main() -> int:
    """Run the cases and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--first-seed", type=int, default=1000)
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--records", type=Path, default=None,
                    help="JSON-lines file: one record per diagnosed seed is appended; seeds "
                         "already in it are not run again (resume a partial run)")
    ap.add_argument("--recorded-only", action="store_true",
                    help="run nothing: the table of the seeds already in --records (a partial run; "
                         "the files of several processes concatenated)")
    ap.add_argument("--score-levels", action="store_true",
                    help="also count, per case and candidate, the bags whose unadjusted score "
                         "p is below 5 %% and 1 %% (the screening re-runs those below 5 %%: "
                         "a candidate's test at its level gives ~5 %% and ~1 %% of the bags)")
    ap.add_argument("-v", "--verbose", action="store_true")
    args = ap.parse_args()
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    done = load_records(args.records)
    cases = args.cases.split(",")
    for seed in [] if args.recorded_only else seeds:  # seed-major: a partial run covers
        for name in cases:                             # every case
            if (name, seed) not in done:
                done[(name, seed)] = r = diagnose_seed(name, seed)
                if args.records is not None:
                    with args.records.open("a") as fh:
                        fh.write(json.dumps(r) + "\n")
                if args.verbose:
                    print(f"{name} seed {seed}: {len(r['candidates'])} candidates, "
                          f"{len(r['unexplained'])} unexplained, noise "
                          f"{'rescaled' if r['noise'] else 'as stated'} [{r['cpu']:.0f} s]",
                          flush=True)
    rows = []
    for name in cases:
        rows.append((name, run_case(name, seeds, done, args.recorded_only)))
    n_seeds = ", ".join(f"{r['n']}" for _, r in rows)
    print(f"\nfalse alarms on clean bags, seeds {seeds.start}-{seeds.stop - 1}: {n_seeds} bags "
          "per case (alpha = 1 %; count, rate, one-sided 95 % upper bound)")
    print(f"{'case':14s} {'candidates':>22s} {'unexplained':>22s} {'noise rescaled':>22s} "
          f"{'cpu s/bag':>9s}")
    for name, r in rows:
        n = max(r["n"], 1)
        cells = [f"{r[k]:3d} {r[k] / n:6.1%} (<{upper(r[k], n):5.1%})"
                 for k in ("candidates", "unexplained", "noise")]
        print(f"{name:14s} " + " ".join(f"{c:>22s}" for c in cells) + f" {r['cpu'] / n:9.0f}")
    for _, r in rows:
        for line in r["lines"]:
            print(line)
    if args.score_levels:
        print_score_levels(cases, seeds, done)
    return 0


def print_score_levels(cases: list[str], seeds: range, done: dict) -> None:
    """Per case and candidate: recorded bags with score p below 5 % and 1 %."""
    print("\nunadjusted score p of each candidate (bags below 5 % / below 1 %, of n bags)")
    for name in cases:
        recs = [done[(name, s)] for s in seeds if (name, s) in done]
        low: dict[str, list[int]] = {}
        for r in recs:
            for effect, t in r["tests"].items():
                p = t["p_score"]
                if p is not None:
                    c = low.setdefault(effect, [0, 0])
                    c[0] += p < 0.05
                    c[1] += p < 0.01
        cells = ", ".join(f"{e} {a}/{b}" for e, (a, b) in
                          sorted(low.items(), key=lambda kv: (-kv[1][0], kv[0])))
        print(f"  {name} (n = {len(recs)}): {cells or 'none below 5 %'}")


if __name__ == "__main__":
    raise SystemExit(main())
