r"""Power at the printed MDB on twins of the user's bag, per sign, with the tests' own numbers.

``discover --verify`` makes one twin per effect; ``benchmarks/twin_power.py`` runs the
whole ``discover --auto`` on each twin but keeps only the verdict.  This one runs, per twin
seed and per sign of the size (an MDB is a size: either sign), what ``--verify`` runs
(:func:`~stellar_cal_ros.diagnosis.verify.check_claims`: one diagnosis round on the twin
with the effect at its printed MDB, every candidate of the report's family, and the twin of
the same seed without it), and keeps what the decision saw: flagged or not, the score
statistic and its dof, the ratio statistic, the paired score response ``λ`` against the
``λ₀`` the MDB is stated for.  The table: per effect and sign, the share flagged (target
80 % ± 15 %), the score statistic's mean minus its dof (its non-centrality measured over
the seeds: χ²_k(λ)) over λ₀, the paired response over λ₀, and the power that the measured
non-centrality implies at the test's level.  Run::

    python benchmarks/twin_mdb_power.py BASE.mcap RESULT.d psce --seeds 101-110
    python benchmarks/twin_mdb_power.py BASE.mcap RESULT.d psce --effects image_plane_tilt \
        --signs 1 --factor 2 --records OUT.jsonl  # 2x the printed MDB, + only
    python benchmarks/twin_mdb_power.py BASE.mcap RESULT.d psce --effects image_plane_tilt \
        --parameter tau_y  # tau_y instead of the report's parameter (tau_x)
    python benchmarks/twin_mdb_power.py --table-from OUT.jsonl

``RESULT.d`` is ``discover --auto``'s output on ``BASE.mcap`` (its ``calibration.yaml`` and
``diagnosis.json``'s ``reliability`` list: the printed MDBs).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from stellar_cal_ros.core import distributions as dist
from stellar_cal_ros.diagnosis.discover import method_spec
from stellar_cal_ros.diagnosis.noise import stated_scales
from stellar_cal_ros.diagnosis.parallel import Runs
from stellar_cal_ros.diagnosis.reliability_probe import clock_runs
from stellar_cal_ros.diagnosis.twin import make_twin, twin_scene
from stellar_cal_ros.diagnosis.verify import check_claims
from stellar_cal_ros.io.calibration import load_calibration
from stellar_cal_ros.methods.frames import read_bag_data


def records(bag: str, result: Path, method: str, only: list[str], seeds: range,
            signs: tuple[int, ...], sink=None, factor: float = 1.0,
            parameter: str = "") -> list[dict]:
    """:func:`check_claims`'s records of ``only`` on twins of ``bag``, one seed at a time.

    ``factor``: the twins get ``factor`` x the printed size (the bias checks, scaled with
    it, are dropped from the records); ``parameter``: the one injected in the effects that
    have it (else the report's, as ``--verify``: the largest bias's).
    """
    data = read_bag_data(bag)
    calibration = load_calibration(result / "calibration.yaml")
    summary = json.loads((result / "diagnosis.json").read_text())
    entries = [{**e, "hidden_size": {p: v * factor for p, v in e["hidden_size"].items()}}
               if "hidden_size" in e else e for e in summary["reliability"]]
    effects = list(method_spec(method).baseline) + list(summary.get("added", []))
    noise = stated_scales(calibration)
    scene = twin_scene(data, calibration, method)
    chosen = {e["effect"]: parameter for e in entries if parameter in e.get("hidden_size", {})}
    # a row discover's clock rule marks (refused_beside_clock): the rule asked at each twin's
    # size on the bag (verify.clock_rule), the final model run from its calibration (as the
    # twins' rounds start), with the stated noise
    runs = Runs(data, method_spec(method), 0.5)
    runs.noise = noise
    extra = tuple(method_spec(method).beyond_baseline(effects))

    def clock_check(effect, delta):
        return clock_runs(runs, calibration, extra, calibration,
                          ((effect, tuple(np.asarray(delta).tolist())),))[0]

    out = []
    for seed in seeds:
        t0 = time.process_time()

        def make(injected, seed=seed):
            twin = make_twin(data, calibration, injected, seed, method, noise, scene)
            return twin.data, twin.counts

        rows = check_claims(make, calibration, method, effects, entries, noise, seed,
                            only=only, signs=signs, parameters=chosen,
                            clock_check=clock_check)
        for rec in rows:
            rec = {k: v for k, v in rec.items() if k not in ("twin_counts", "biases")}
            rec["cpu_s"] = time.process_time() - t0
            rec["factor"] = factor
            out.append(rec)
            if sink is not None:
                sink.write(json.dumps(rec, default=float) + "\n")
                sink.flush()
            print(f"seed {seed} {rec['effect']} {rec['parameter']} {rec['sign']:+d}: "
                  f"{'found' if rec['found'] else 'missed'}, score {rec['score_statistic']:.3g}"
                  f" (p {rec['score_p']:.2g}), ratio {rec['lr_statistic']:.3g}, p_adjusted "
                  f"{rec['p_adjusted']:.2g}, paired response {rec['noncentrality']:.3g} "
                  f"(lam0 {rec['expected_noncentrality']:.3g})", flush=True)
    return out


def table(recs: list[dict]) -> list[str]:
    """One row per effect and sign: flagged share, measured and paired non-centrality."""
    lines = ["| effect | size (x MDB) | twins | flagged | score stat. mean − dof (λ) | λ / λ₀ | "
             "power at that λ | paired λ / λ₀ (median) |",
             "|---|---|---|---|---|---|---|---|"]
    keys = sorted({(r["effect"], r["parameter"], r.get("factor", 1.0), r["sign"])
                   for r in recs})
    for eid, param, factor, sign in keys:
        rs = [r for r in recs if r["effect"] == eid and r["parameter"] == param
              and r["sign"] == sign and r.get("factor", 1.0) == factor]
        k, lam0, alpha = rs[0]["dof"], rs[0]["expected_noncentrality"], rs[0]["alpha"]
        stat = np.array([r["score_statistic"] for r in rs], dtype=float)
        lam = float(np.nanmean(stat)) - k
        err = float(np.nanstd(stat, ddof=1) / np.sqrt(np.isfinite(stat).sum())) \
            if np.isfinite(stat).sum() > 1 else float("nan")
        implied = float(dist.ncx2.sf(dist.chi2.isf(alpha, k), k, max(lam, 1e-9)))
        paired = np.nanmedian([r["noncentrality"] for r in rs]) / lam0
        # a twin discover's clock rule refuses at that sign on the bag is not a miss: out
        # of the flagged share (verify.clock_rule)
        counted = [r for r in rs if not r.get("refused_by_clock")]
        n_found = sum(bool(r["found"]) for r in counted)
        share = f"{n_found / len(counted):.0%}" if counted else "-"
        refused = len(rs) - len(counted)
        flagged = (f"{n_found} of {len(counted)} ({share}), {refused} refused by the clock "
                   "rule" if refused else f"{n_found} ({share})")
        lines.append(f"| {eid} {rs[0]['parameter']} | {sign * factor:+g} | {len(rs)} | {flagged}"
                     f" | {lam:.1f} ± {err:.1f} (λ₀ {lam0:.1f}, "
                     f"dof {k}) | {lam / lam0:.2f} | {implied:.0%} | {paired:.2f} |")
    return lines


def main() -> int:
    """Run the twins of the command line (or read records) and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("bag", nargs="?")
    ap.add_argument("result", nargs="?", type=Path)
    ap.add_argument("method", nargs="?", default="psce")
    ap.add_argument("--effects", default="image_plane_tilt,gyro_misalignment")
    ap.add_argument("--seeds", default="101-110", help="first-last twin seeds")
    ap.add_argument("--signs", default="1,-1")
    ap.add_argument("--factor", type=float, default=1.0, help="x the printed MDB")
    ap.add_argument("--parameter", default="",
                    help="inject this parameter (default: the report's, as --verify)")
    ap.add_argument("--records", default="", help="append every record as JSON lines")
    ap.add_argument("--table-from", nargs="*", default=[], help="only the table of records")
    a = ap.parse_args()
    if a.table_from:
        recs = [json.loads(line) for f in a.table_from for line in open(f) if line.strip()]
    else:
        first, last = map(int, a.seeds.split("-"))
        sink = open(a.records, "a") if a.records else None
        try:
            recs = records(a.bag, a.result, a.method, a.effects.split(","),
                           range(first, last + 1), tuple(int(s) for s in a.signs.split(",")),
                           sink, a.factor, a.parameter)
        finally:
            if sink is not None:
                sink.close()
    print("\n".join(table(recs)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
