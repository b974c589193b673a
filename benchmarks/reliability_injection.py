"""Every number of "what could still be hiding" checked by injection (issue 21 item 2).

Per seed: a clean bag is diagnosed (noise measured first, every candidate); for each
library effect the report prints its MDB and, per listed parameter, the bias an effect of
that size leaves.  The effect is then injected with the simulator into the same bag (same
seed, same noise) at its printed MDB — the parameter the report names for its largest
bias, else its best determined one — and one diagnosis round is run on it
(:func:`stellar_cal_ros.diagnosis.verify.check_claims`, what ``discover --verify`` does on
twins of a user's bag):

* **power**: the share of seeds where the round's decision flags the effect (significant,
  or significant but 'implausible': an astrometric scale at a few % of its physical size)
  — target 80 % ± 15 % — and, from the same injected runs, the non-centrality of the
  decision's score statistic measured over seeds (``mean − k``: it is χ²_k(λ)) against
  the λ₀ the MDB is stated for, with the power that λ implies.  The paired score
  difference (``paired``: λ/λ₀, 1 when the score is linear in the effect up to its MDB)
  and the clean bags' mean statistic over its dof (``null``: 1) are shown apart;
* **bias**: the paired shift of every listed quantity over the printed bias (target
  within 0.7–1.3);
* **RMS after**: on the bag with the effect at 4× its MDB, the RMS the diagnosis prints
  after adding it against the RMS of a replay that has it.

The size's sign alternates with the seed (an MDB is a size).  Run::

    .venv/bin/python benchmarks/reliability_injection.py --seeds 10
    .venv/bin/python benchmarks/reliability_injection.py --seeds 2 --effects gyro_misalignment
    # split by seed over processes, then one table:
    .venv/bin/python benchmarks/reliability_injection.py --seeds 5 --records a.jsonl
    .venv/bin/python benchmarks/reliability_injection.py --seeds 5 --first-seed 305 \
        --records b.jsonl
    .venv/bin/python benchmarks/reliability_injection.py --table-from a.jsonl b.jsonl

The reduced form in the default suite is ``test/test_reliability_injection.py``.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time

import numpy as np
from scipy import stats as sps

from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.diagnosis import injection
from stellar_cal_ros.diagnosis.discover import rerun_prior
from stellar_cal_ros.diagnosis.run import diagnose
from stellar_cal_ros.diagnosis.verify import check_claims
from stellar_cal_ros.methods.replay import bag_data_from_simulation, replay


def run(method: str, seeds: range, duration: float, only: list[str] | None,
        verbose: bool, rms_seeds: int = 2, records: str = "",
        stated_star: float = 0.0) -> dict[str, dict]:
    """Per effect over the seeds: injection records (:func:`check_claims`), RMS pairs.

    The size's sign alternates with the seed (+ on even seeds: an MDB is a size, either
    sign); the RMS after is measured on the first ``rms_seeds`` seeds only (a diagnosis
    per effect).  ``stated_star`` (> 0): the noise is not measured, every run states the
    stars' σ at that many times the bag's (a wrong stated σ: below 1 the residuals scatter
    1/stated_star² x the stated variance, a round's dispersion φ ≠ 1).
    """
    out: dict[str, dict] = {}
    for i, seed in enumerate(seeds):
        t0 = time.process_time()
        sim0, model = injection.clean_simulation(method, False, seed, duration)
        stated = ({"noise": "stated", "noise_scales": NoiseScales(star=stated_star)}
                  if stated_star > 0 else {})
        with tempfile.TemporaryDirectory() as tmp:
            clean = diagnose(bag_data_from_simulation(sim0), sim0.prior, method, model, tmp,
                             plots=False, verbose=False, **stated)
        noise = (NoiseScales(star=stated_star) if stated_star > 0
                 else NoiseScales.from_dict(clean["noise"]["applied"]))
        entries = clean.get("reliability", [])

        def make(injected, seed=seed):
            sim, _ = injection.clean_simulation(method, False, seed, duration, injected)
            return bag_data_from_simulation(sim), {}

        sign = 1 if seed % 2 == 0 else -1
        # the simulator's bag of the same seed and noise scatters as the diagnosed one
        # did: its rounds have the printed MDB's dispersion (``own``)
        rows = check_claims(make, sim0.prior, method, model, entries, noise, seed,
                            only=only, signs=(sign,), own=True)
        for rec in rows:
            r = out.setdefault(rec["effect"], {"records": [], "rms": [],
                                               "param": rec["parameter"]})
            r["records"].append(rec)
            eid = rec["effect"]
            if i < rms_seeds:  # RMS after: the effect at 4x its MDB
                delta = 4 * injection.parameter_delta(eid, rec["parameter"], rec["size"])
                data4, _ = make({eid: injection.simulation_value(eid, delta)})
                with tempfile.TemporaryDirectory() as tmp:
                    s4 = diagnose(data4, sim0.prior, method, model, tmp, plots=False,
                                  verbose=False, candidates=[e["effect"] for e in entries])
                c4 = next((c for c in s4["candidates"] if c["effect"] == eid), None)
                if c4 is not None:
                    r4 = replay(data4, rerun_prior(sim0.prior), method, model + [eid],
                                keep_tables=False, noise=noise)
                    rec["rms_after"] = (max(c4["rms_after_px"]),
                                        max(r4.stats.window(0.5)["rms"]))
                    r["rms"].append(rec["rms_after"])
            if records:
                with open(records, "a") as f:
                    f.write(json.dumps({k: v for k, v in rec.items() if k != "twin_counts"},
                                       default=float) + "\n")
            if verbose:
                print(f"seed {seed} {eid} {rec['parameter']} = {rec['size_shown']}: "
                      f"{'found' if rec['found'] else 'missed'} ({rec['status']}, p_adj "
                      f"{rec['p_adjusted']:.2g}), score statistic "
                      f"{rec['score_statistic']:.3g}, paired λ "
                      f"{rec['noncentrality']:.3g} "
                      f"(λ0 {rec['expected_noncentrality']:.3g}), "
                      f"ratios {[round(c['ratio'], 2) for c in rec['biases']]}", flush=True)
        if verbose:
            print(f"seed {seed}: {time.process_time() - t0:.0f} s CPU", flush=True)
    return out


def summarize(recs: list[dict]) -> dict[str, float]:
    """Power over seeds and the non-centrality measured from the injected runs' statistic.

    ``found``: share of seeds the decision flags the effect, with its binomial σ;
    ``lam``: mean score statistic on the injected bags minus its dof (the statistic is
    non-central χ²_k(λ): E = k + λ) and its standard error; ``implied``: the power of the
    score test at the MDB's level with that λ; ``paired``: the median paired score
    response over λ₀ (1 when the score is linear up to the MDB); ``null``: the mean score
    statistic on the clean bags over its dof (1: the statistic is χ²_k without the effect).
    """
    found = np.array([r["found"] for r in recs], dtype=float)
    stat = np.array([r["score_statistic"] for r in recs], dtype=float)
    stat = stat[np.isfinite(stat)]
    k, alpha, lam0 = recs[0]["dof"], recs[0]["alpha"], recs[0]["expected_noncentrality"]
    lam = float(np.mean(stat) - k) if stat.size else float("nan")
    lam_se = float(np.std(stat, ddof=1) / np.sqrt(stat.size)) if stat.size > 1 else float("nan")
    crit = sps.chi2.isf(alpha, k)
    implied = float(sps.ncx2.sf(crit, k, max(lam, 1e-9))) if np.isfinite(lam) else float("nan")
    paired = np.array([r.get("noncentrality", r.get("paired_noncentrality", np.nan)) / lam0
                       for r in recs], dtype=float)
    null = np.array([r["clean_score_statistic"] for r in recs], dtype=float)
    return {"n": len(recs), "found": float(found.mean()),
            "found_se": float(np.sqrt(found.mean() * (1 - found.mean()) / len(recs))),
            "named": float(np.mean([r["named"] for r in recs])),
            "lam": lam, "lam_se": lam_se, "lam0": lam0, "implied": implied,
            "paired": float(np.nanmedian(paired)) if np.isfinite(paired).any() else np.nan,
            "null": float(np.nanmean(null) / k) if np.isfinite(null).any() else np.nan}


def main() -> int:
    """Run and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--first-seed", type=int, default=300)
    ap.add_argument("--method", default="psce", choices=["psce", "swaying_base"])
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--effects", default="", help="inject only these (comma separated); "
                    "every round still tests all candidates")
    ap.add_argument("--rms-seeds", type=int, default=2,
                    help="seeds on which 'RMS after' is checked (a diagnosis per effect)")
    ap.add_argument("--records", default="", help="append every injection as JSON lines")
    ap.add_argument("--table-from", nargs="*", default=[],
                    help="print the table of earlier --records files (runs split by seed)")
    ap.add_argument("--stated-star", type=float, default=0.0,
                    help="state the stars' sigma at this many times the bag's, noise not "
                    "measured (below 1: residuals over-dispersed, a round's dispersion "
                    "1/x^2); 0: measure the noise")
    ap.add_argument("-v", "--verbose", action="store_true")
    args = ap.parse_args()
    only = [e for e in args.effects.split(",") if e] or None
    if args.table_from:
        res: dict[str, dict] = {}
        for path in args.table_from:
            with open(path) as f:
                for line in f:
                    rec = json.loads(line)
                    r = res.setdefault(rec["effect"], {"records": [], "rms": [],
                                                       "param": rec["parameter"]})
                    r["records"].append(rec)
                    if rec.get("rms_after"):
                        r["rms"].append(rec["rms_after"])
        seeds = sorted({rec["seed"] for r in res.values() for rec in r["records"]})
        n_seeds = len(seeds)
    else:
        res = run(args.method, range(args.first_seed, args.first_seed + args.seeds),
                  args.duration, only, args.verbose, args.rms_seeds, args.records,
                  args.stated_star)
        n_seeds = args.seeds
    print_table(res, f"{args.method}, {args.duration:.0f} s, {n_seeds} seeds")
    return 0


def print_table(res: dict[str, dict], title: str) -> None:
    """The table of :func:`run`'s results."""
    print(f"\n{title} (sign alternating): each effect injected at its printed MDB "
          "(targets: found 80 % +- 15 %, shift/printed 0.7-1.3)")
    print(f"{'effect':22s} {'injected':10s} {'found':>10s} {'as itself':>9s} "
          f"{'λ measured / λ0':>18s} {'implied':>8s} {'paired':>7s} {'null':>5s} "
          f"{'shift/printed (median, n)':>26s} {'in 0.7-1.3':>10s} "
          f"{'RMS after printed/replay':>25s}")
    for eid, r in res.items():
        sm = summarize(r["records"])
        ratios = np.asarray([c["ratio"] for rec in r["records"] for c in rec["biases"]],
                            dtype=float)
        inside = f"{np.mean((ratios > 0.7) & (ratios < 1.3)):.0%}" if ratios.size else "-"
        med = f"{np.median(ratios):.3f} ({ratios.size})" if ratios.size else "-"
        rms = np.asarray(r["rms"])
        rms_txt = (f"{np.median(rms[:, 0] / rms[:, 1]):.4f} (n={len(rms)})" if rms.size
                   else "-")
        found = f"{sm['found']:.0%}±{sm['found_se']:.0%}"
        lam = f"{sm['lam']:.1f}±{sm['lam_se']:.1f}/{sm['lam0']:.1f}"
        print(f"{eid:22s} {r['param']:10s} {found:>10s} {sm['named']:9.0%} {lam:>18s} "
              f"{sm['implied']:8.0%} {sm['paired']:7.2f} {sm['null']:5.2f} {med:>26s} "
              f"{inside:>10s} "
              f"{rms_txt:>25s}")


if __name__ == "__main__":
    raise SystemExit(main())
