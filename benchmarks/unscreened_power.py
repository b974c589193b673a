"""Power at the MDB an unscreened round prints: the effect injected into a bag that does not fit.

An unseen case whose final model stays far from consistent (``dt_step``: a clock step
outside the library, final NIS/dof ~8) prints the MDBs of a round that is not screened
(issue 21 item 2).  A twin of its calibration is clean and cannot check them: here the
case itself is simulated again with the library effect added (``--effect`` of the
simulation, fresh noise per seed), ``discover --auto`` is run as the user would, and per
seed it counts whether the effect was found (added, or significant in a round).  Run::

    python benchmarks/unscreened_power.py dt_step gyro_scale_factor 1.27e-4,0,0 101-110 OUT

(a negative VALUE after ``--``).  Per seed and round: p, Λ, the explained fraction, reason.

``--paired PARAM`` measures instead the non-centrality of one unscreened round (the
``--model`` effects beside the baseline, the one candidate ``EFFECT``) at its printed MDB
of ``PARAM``: the case simulated with that parameter at 0 and at ± the MDB, same seed,
``(Λ(+b) + Λ(−b) − 2 Λ(0)) / 2`` over λ₀ (1 when the MDB is right; VALUE and OUT unused)::

    python benchmarks/unscreened_power.py dt_step gyro_scale_factor - 23-23 - \
        --paired sx --model time_offset

``--gate PARAM`` checks an MDB the excess gate set (``mdb_set_by`` "explained_gate") at
the sign the misfit works against: per seed the round's own printed MDB, the case simulated
again with ``-sign(mdb_leaning)`` x ``--factor`` x it, and whether that round's decision
passes (p below 1 % and 10 % of the excess removed)::

    python benchmarks/unscreened_power.py dt_step gyro_scale_factor - 101-110 - \
        --gate sx --model time_offset [--secant]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import unseen_cases  # noqa: E402


def main() -> int:
    """Simulate, discover and count one row a seed."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    # the unseen case, the library effect, its parameters (comma-separated), first-last seeds
    for name in ("case", "effect", "value", "seeds"):
        ap.add_argument(name)
    ap.add_argument("out", type=Path)
    ap.add_argument("--paired", default="", help="measure the non-centrality at this "
                    "parameter's printed MDB instead")
    ap.add_argument("--model", default="", help="with --paired/--gate: effects beside the "
                    "baseline")
    ap.add_argument("--gate", default="", help="measure instead the decision at this "
                    "parameter's printed MDB, the sign the misfit works against")
    ap.add_argument("--factor", type=float, default=1.0, help="with --gate: x the MDB")
    ap.add_argument("--secant", action="store_true", help="with --gate: restate the MDB "
                    "from that injection as a diagnosis does, and inject it too")
    a = ap.parse_args()
    if a.gate:
        return gate(a)
    if a.paired:
        return paired(a)
    a.out.mkdir(parents=True, exist_ok=True)
    value = [float(v) for v in a.value.split(",")]
    base = unseen_cases.CASES[a.case]
    name = f"{a.case}_inj"
    unseen_cases.CASES[name] = dataclasses.replace(
        base, sim_effects={**base.sim_effects, a.effect: value})
    first, last = map(int, a.seeds.split("-"))
    found = 0
    for k in range(first, last + 1):
        out = a.out / f"s{k}"
        out.mkdir(exist_ok=True)
        unseen_cases.write_case(name, out, k)
        exe = str(Path(sys.executable).with_name("stellar-cal"))
        d = out / "d"
        subprocess.run([exe, "discover", str(out / f"{name}.mcap"), "--calibration",
                        str(out / f"{name}.prior.yaml"), "--method", base.method, "--auto",
                        "-o", str(d), "--no-plots", "--workers", "0"], capture_output=True)
        s = json.loads((d / "diagnosis.json").read_text())
        added = a.effect in s.get("added", [])
        rows = []
        for i, rnd in enumerate(s["path"]):
            mine = rnd.get("added") or {}
            if mine.get("effect") != a.effect:
                mine = next((x for x in rnd.get("rejected", []) if x.get("effect") == a.effect),
                            {})
            rows.append((i + 1, mine.get("p_value"), mine.get("score"),
                         mine.get("explained_fraction"), (mine.get("reason") or "")[:60]))
        # flagged: significant in a round though refused ('not significant' is not)
        sig = any(r[4].startswith("significant") for r in rows)
        found += added or sig
        print(f"{k:5d} {'added' if added else 'missed':7s} {s.get('added', [])} "
              f"rounds {rows}", flush=True)
        (out / f"{name}.mcap").unlink(missing_ok=True)
    n = last - first + 1
    print(f"{a.case} {a.effect}={a.value}: found {found} of {n}")
    return 0


def one_round(a, seed: int, b: float):
    """One unscreened round of the case at ``seed`` with ``a.paired`` = ``b``.

    The ``--model`` effects beside the baseline, the one candidate ``a.effect``:
    ``(reference, candidate)``.
    """
    from stellar_cal_ros.core.noise import NoiseScales
    from stellar_cal_ros.diagnosis import discover
    from stellar_cal_ros.diagnosis.parallel import Runs
    from stellar_cal_ros.effects import registry
    from stellar_cal_ros.methods.replay import bag_data_from_simulation
    from stellar_cal_ros.sim.scenarios import get_scenario
    from stellar_cal_ros.sim.world import simulate

    case = unseen_cases.CASES[a.case]
    spec = discover.method_spec(case.method)
    sc = get_scenario({"psce": "psce_rotations", "swaying_base": "swaying"}[case.method])
    names = registry.create(a.effect).parameter_names
    extra = [e for e in a.model.split(",") if e]
    vec = [b if n == a.paired else 0.0 for n in names]
    sim = simulate(sc, duration=case.duration, seed=seed,
                   effects={**case.sim_effects, **({a.effect: vec} if b else {})})
    if case.post is not None:
        case.post(sim, seed)
    runs = Runs(bag_data_from_simulation(sim), spec, 0.5)
    runs.noise = NoiseScales()
    r = discover.Round(runs, spec, runs.facts(), 0.5, sim.prior)
    base, (c,), _ = discover.rank_round(r, sim.prior, extra, [a.effect], condition=False,
                                        screen=False, measure_noise=False)
    return discover.Reference.of(base), c


def paired(a) -> int:
    """One row a seed: dispersion, printed MDB, Λ(0), Λ(±MDB) and the non-centrality / λ₀."""
    first, last = map(int, a.seeds.split("-"))
    for seed in range(first, last + 1):
        ref, c0 = one_round(a, seed, 0.0)
        d, b = ref.dispersion, c0.detect.mdb[a.paired]
        up, down = one_round(a, seed, b)[1].statistic, one_round(a, seed, -b)[1].statistic
        lam = (up + down - 2.0 * c0.statistic) / 2.0
        print(f"{seed:5d} dispersion {d:.3g} MDB {a.paired} {b:.4g} lam0 {c0.detect.lam0:.4g} "
              f"L(0) {c0.statistic:.4g} L(+b) {up:.4g} L(-b) {down:.4g} "
              f"lam/lam0 {lam / c0.detect.lam0:.3g}", flush=True)
    return 0


def gate(a) -> int:
    """One row a seed: the decision at the sign the misfit works against, at the printed MDB.

    Per seed the round's own printed MDB of ``a.gate``; injected at that sign (``--factor``
    x the MDB): the share removed and the decision.

    ``--secant``: then also the MDB a diagnosis restates from that injection
    (:func:`~stellar_cal_ros.diagnosis.reliability_probe.gate_secant`: the energy measured
    as its probe runs do, at the printed size and at the one step's, here on the case
    simulated again with the same seed: the same noise), injected in its turn.
    """
    from stellar_cal_ros.diagnosis.discover import ALPHA, MIN_EXPLAINED
    from stellar_cal_ros.diagnosis.reliability_probe import gate_secant

    a.paired = a.gate
    first, last = map(int, a.seeds.split("-"))
    found = {"printed": 0, "restated": 0}
    for seed in range(first, last + 1):
        ref0, c0 = one_round(a, seed, 0.0)
        entry = c0.detect.as_dict()
        mdb, lean = entry["mdb"][a.gate], entry.get("mdb_leaning", {}).get(a.gate, np.nan)
        sign = -float(np.sign(lean))
        rec = {"seed": seed, "parameter": a.gate, "mdb": mdb, "mdb_test": entry.get(
            "mdb_test", {}).get(a.gate), "mdb_leaning": lean, "factor": a.factor,
            "set_by": entry.get("mdb_set_by", ""), "explained0": c0.explained}

        def run(kind, size, seed=seed, rec=rec, ref0=ref0):
            ref, c = one_round(a, seed, size)
            hit = bool(c.p_adjusted < ALPHA and not c.explained < MIN_EXPLAINED)
            rec[kind] = {"injected": size, "explained": c.explained,
                         "p_adjusted": c.p_adjusted, "statistic": c.statistic,
                         "excess": ref.excess, "excess_candidate":
                         c.run.window["excess_variance"], "passes": hit}
            return hit, (ref.excess - ref0.excess) * 2.0 * ref0.stars / ref0.noise

        hit, energy = run("printed", sign * mdb * a.factor)
        found["printed"] += hit
        if a.secant and a.factor == 1.0:  # the diagnosis's probe runs: one step, a secant
            step = gate_secant(entry, a.gate, energy)
            if step is not None:
                gate_secant(entry, a.gate, run("step", sign * step)[1])
            rec["gate_probe"] = entry.get("gate_probe", {}).get(a.gate)
            found["restated"] += run("restated", sign * entry["mdb"][a.gate])[0]
        print(json.dumps(rec), flush=True)
    n = last - first + 1
    print(f"{a.case} {a.effect} {a.gate} the hard sign: passes at {a.factor:g} x the printed "
          f"MDB {found['printed']} of {n}"
          + (f", at the restated MDB {found['restated']} of {n}" if a.secant else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
