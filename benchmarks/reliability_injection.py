"""Every number of "what could still be hiding" checked by injection (issue 21 item 2).

Per seed: a clean bag is diagnosed (noise measured first, every candidate); for each
library effect the report prints its MDB and, per listed parameter, the bias an effect of
that size leaves.  The effect is then injected with the simulator into the same bag (same
seed, same noise) at its printed MDB — the parameter the report names for its largest
bias, else its best determined one — and one diagnosis round is run on it
(:func:`stellar_cal_ros.diagnosis.verify.check_claims`, what ``discover --verify`` does on
twins of a user's bag):

* **power**: the share of seeds where the effect is a significant candidate (target
  80 % ± 15 %), and the power implied by the non-centrality measured from the paired score
  difference (``P(χ²_k(λ) > crit)``, the same in expectation, far less noisy);
* **bias**: the paired shift of every listed quantity over the printed bias (target
  within 0.7–1.3);
* **RMS after**: on the bag with the effect at 4× its MDB, the RMS the diagnosis prints
  after adding it against the RMS of a replay that has it.

Run::

    .venv/bin/python benchmarks/reliability_injection.py --seeds 10
    .venv/bin/python benchmarks/reliability_injection.py --seeds 2 --effects gyro_misalignment

The reduced form in the default suite is ``test/test_reliability_injection.py``.
"""

from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np

from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.diagnosis import injection
from stellar_cal_ros.diagnosis.discover import rerun_prior
from stellar_cal_ros.diagnosis.run import diagnose
from stellar_cal_ros.diagnosis.verify import check_claims
from stellar_cal_ros.methods.replay import bag_data_from_simulation, replay


def run(method: str, seeds: range, duration: float, only: list[str] | None,
        verbose: bool) -> dict[str, dict]:
    """Per effect over the seeds: detections, implied powers, shift ratios, RMS pairs."""
    out: dict[str, dict] = {}
    for seed in seeds:
        t0 = time.process_time()
        sim0, model = injection.clean_simulation(method, False, seed, duration)
        with tempfile.TemporaryDirectory() as tmp:
            clean = diagnose(bag_data_from_simulation(sim0), sim0.prior, method, model, tmp,
                             plots=False, verbose=False)
        noise = NoiseScales.from_dict(clean["noise"]["applied"])
        entries = [e for e in clean.get("reliability", [])
                   if only is None or e["effect"] in only]

        def make(injected, seed=seed):
            sim, _ = injection.clean_simulation(method, False, seed, duration, injected)
            return bag_data_from_simulation(sim), {}

        rows = check_claims(make, sim0.prior, method, model, entries, noise, seed)
        for rec in rows:
            r = out.setdefault(rec["effect"], {"found": [], "power": [], "ratios": [],
                                               "rms": [], "param": rec["parameter"]})
            r["found"].append(rec["found"])
            r["power"].append(rec["implied_power"])
            r["ratios"] += [c["ratio"] for c in rec["biases"]]
            # RMS after: the effect at 4x its MDB
            eid = rec["effect"]
            delta = 4 * injection.parameter_delta(eid, rec["parameter"], rec["size"])
            data4, _ = make({eid: injection.simulation_value(eid, delta)})
            with tempfile.TemporaryDirectory() as tmp:
                s4 = diagnose(data4, sim0.prior, method, model, tmp, plots=False,
                              verbose=False, candidates=[e["effect"] for e in entries])
            c4 = next((c for c in s4["candidates"] if c["effect"] == eid), None)
            if c4 is not None:
                r4 = replay(data4, rerun_prior(sim0.prior), method, model + [eid],
                            keep_tables=False, noise=noise)
                r["rms"].append((max(c4["rms_after_px"]), max(r4.stats.window(0.5)["rms"])))
            if verbose:
                print(f"seed {seed} {eid} {rec['parameter']} = {rec['size_shown']}: "
                      f"{'found' if rec['found'] else 'missed'}, power "
                      f"{rec['implied_power']:.0%}, ratios "
                      f"{[round(c['ratio'], 2) for c in rec['biases']]}", flush=True)
        if verbose:
            print(f"seed {seed}: {time.process_time() - t0:.0f} s CPU", flush=True)
    return out


def main() -> int:
    """Run and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--first-seed", type=int, default=300)
    ap.add_argument("--method", default="psce", choices=["psce", "swaying_base"])
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--effects", default="")
    ap.add_argument("-v", "--verbose", action="store_true")
    args = ap.parse_args()
    only = [e for e in args.effects.split(",") if e] or None
    res = run(args.method, range(args.first_seed, args.first_seed + args.seeds),
              args.duration, only, args.verbose)
    print(f"\n{args.method}, {args.duration:.0f} s, {args.seeds} seeds: each effect injected "
          "at its printed MDB (targets: power 80 % +- 15 %, shift/printed 0.7-1.3)")
    print(f"{'effect':22s} {'injected':18s} {'found':>7s} {'implied power':>14s} "
          f"{'shift/printed (median, n)':>26s} {'in 0.7-1.3':>10s} "
          f"{'RMS after printed/replay':>25s}")
    for eid, r in res.items():
        ratios = np.asarray(r["ratios"], dtype=float)
        inside = f"{np.mean((ratios > 0.7) & (ratios < 1.3)):.0%}" if ratios.size else "-"
        med = f"{np.median(ratios):.3f} ({ratios.size})" if ratios.size else "-"
        rms = np.asarray(r["rms"])
        rms_txt = (f"{np.median(rms[:, 0] / rms[:, 1]):.4f} (n={len(rms)})" if rms.size
                   else "-")
        print(f"{eid:22s} {r['param']:18s} {np.mean(r['found']):7.0%} "
              f"{np.nanmedian(r['power']):14.0%} {med:>26s} {inside:>10s} {rms_txt:>25s}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
