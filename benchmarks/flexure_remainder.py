"""Mount flexure (outside the library) on psce_rotations: what discover reports, and the null.

A tracker rotation of ``c`` arcsec per unit lateral gravity (``sim.world.MountFlexure``) on
the demo motion (steps of 30 deg about the IMU axes) is ~98 % a gyro scale factor: discover
adds gyro_scale_factor, then tests the model it added for a flexure-shaped remainder
(:mod:`~stellar_cal_ros.diagnosis.flexure`).  For each size this prints what discover adds,
the remainder test after each add (t, p Bonferroni over the adds, its size in px, the
flexure that would leave it; when significant, the added effect's ratio beside a fitted
flexure and the candidates refused as explaining nothing beyond it) and the first
'unexplained' line (with the flexure it reads, ″/g ± its σ, when it is the gravity field
or the remainder).

``--null-seeds N``: the same test on bags with a *true* gyro scale factor (1e-4 per axis,
no flexure) and gyro_scale_factor in the model, over N seeds: the share of p below 5 %,
1 %, 0.1 % (each must be its level: the test's p is from t_nu, frame-robust).

``--with ID=SIZE`` (repeatable): a true library effect in the bag beside the flexure (the
mixed case: is the true effect still added, and the remainder still said?).
``--single``: a single ``diagnose`` round instead of discover (its recommendation and what
it says of the remainder).

``--at-mdb N``: the printed MDB checked by injection (issue 21: power 80 % +- 15 %).  For
each of N seeds (from ``--seed``): the bag without a flexure (``--with`` effects, by default
a true gyro_scale_factor 1e-4, so the test runs after it) is diagnosed, the MDB it prints
("a mount flexure ... up to X arcsec per unit lateral gravity could still hide") read, and
a flexure of exactly X injected into the same seed's bag; detected when the report says the
gravity-shaped remainder.  Prints each seed's MDB, t and verdict, the share detected (with
its binomial sigma) and the mean t at the MDB against the shift the MDB is made of.

Run::

    .venv/bin/python benchmarks/flexure_remainder.py --sizes 10,20,40,80 --null-seeds 20
    .venv/bin/python benchmarks/flexure_remainder.py --sizes 40 --with gyro_misalignment=1e-4
    .venv/bin/python benchmarks/flexure_remainder.py --single --sizes 40 \
        --with gyro_scale_factor=1e-4
    .venv/bin/python benchmarks/flexure_remainder.py --single --at-mdb 20 --seed 300
"""

from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np

from stellar_cal_ros.diagnosis import flexure
from stellar_cal_ros.diagnosis.context import add_gravity_regressors
from stellar_cal_ros.diagnosis.discover import method_spec
from stellar_cal_ros.diagnosis.run import diagnose
from stellar_cal_ros.methods.replay import bag_data_from_simulation, replay_psce
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate


def _bag(effects: dict, seed: int, duration: float):
    sim = simulate(get_scenario("psce_rotations"), duration=duration, seed=seed,
                   effects=effects)
    return sim, bag_data_from_simulation(sim)


def discover_row(size: float, seed: int, duration: float, also: dict | None = None) -> str:
    """One size: what discover adds and says (``also``: true library effects beside it)."""
    sim, data = _bag({"mount_flexure": size, **(also or {})}, seed, duration)
    base = replay_psce(data, sim.prior)
    t0 = time.process_time()
    with tempfile.TemporaryDirectory() as tmp:
        s = diagnose(data, base.calibration, "psce", [], tmp, plots=False, verbose=False,
                     auto=True)
    cpu = time.process_time() - t0
    tests = []
    for step in s["path"]:
        if "remainder" in step:
            r = step["remainder"]
            b = (r or {}).get("beyond")
            tests.append(f"after {step['added']['effect']}: " + (
                "not run" if r is None else
                f"t={r['t']:.1f} p={r['p_value']:.2g} {r['change_px']:.3f} px "
                f"({r['arcsec_per_g']:.1f}+-{r['sigma_arcsec_per_g']:.1f}\")")
                + ("" if not b else f", {step['added']['effect']} beyond it "
                   f"{b['statistic']:.1f} ({b['dof']} dof): "
                   + ("needed" if b["needed"] else "stand-in")))
        a = step.get("could_be_flexure")
        if a:
            tests.append(f"{step['added']['effect']} marked: could be a mount flexure "
                         f"({a['arcsec_per_g']:.1f}\"/g before it; seen with power 50 % "
                         f"from {a['mdb_after_arcsec_per_g']:.0f}\"/g after it)")
        for e, b in (step.get("beyond_remainder") or {}).items():
            tests.append(f"{e} beyond it {b['statistic']:.1f} ({b['dof']} dof): not added")
    first = s["unexplained"][0] if s["unexplained"] else None
    said = ("remainder said" if s.get("remainder") else "no remainder said")
    h = s.get("flexure_hiding")
    if h:
        said += (f"; a flexure up to {h['arcsec_per_g']:.3g}\"/g could still hide (MDB; after "
                 f"{'+'.join(h['after'])}, sigma {h['sigma_arcsec_per_g']:.2g}\"/g)")
    d = (first or {}).get("detail") or {}
    size_read = (f", {d['arcsec_per_g']:.1f}+-{d['sigma_arcsec_per_g']:.1f}\"/g"
                 if "arcsec_per_g" in d else "")
    return (f"| {size:g}\u2033 | {', '.join(s['added']) or '-'} | {'; '.join(tests) or '-'} | "
            + (f"{first['regressor']} (p={first['p_value']:.2g}, {first['change_px']:.3f} px"
               f"{size_read})" if first else "-") + f" | {said} | {cpu:.0f} |")


def single_row(size: float, seed: int, duration: float, also: dict | None = None) -> str:
    """One size, a single ``diagnose`` round: what it recommends and says of the remainder."""
    sim, data = _bag({"mount_flexure": size, **(also or {})}, seed, duration)
    base = replay_psce(data, sim.prior)
    t0 = time.process_time()
    with tempfile.TemporaryDirectory() as tmp:
        s = diagnose(data, base.calibration, "psce", [], tmp, plots=False, verbose=False)
    cpu = time.process_time() - t0
    rem = s.get("remainder")
    said = "no remainder said" if not rem else rem["text"].split(" -- ")[0] + " ... " + (
        rem["text"].split(" would leave it; ")[-1])
    return f"| {size:g}\u2033 | {s['recommendation'] or '-'} | {said} | {cpu:.0f} |"


def _report(effects: dict, seed: int, duration: float, single: bool) -> tuple[dict, float]:
    """The summary of one ``diagnose`` round (``single``) or of discover, and its CPU-s."""
    sim, data = _bag(effects, seed, duration)
    base = replay_psce(data, sim.prior)
    t0 = time.process_time()
    with tempfile.TemporaryDirectory() as tmp:
        s = diagnose(data, base.calibration, "psce", [], tmp, plots=False, verbose=False,
                     auto=not single)
    return s, time.process_time() - t0


def mdb_row(seed: int, duration: float, also: dict, single: bool) -> dict:
    """One seed: the MDB printed on the bag without a flexure, then that flexure injected."""
    clean, cpu = _report(also, seed, duration, single)
    h = clean.get("flexure_hiding")
    if not h:
        return {"seed": seed, "mdb": None, "cpu": cpu,
                "why": "remainder said" if clean.get("remainder") else "no test"}
    mdb = float(h["arcsec_per_g"])
    hit, cpu2 = _report({"mount_flexure": mdb, **also}, seed, duration, single)
    rem = hit.get("remainder")
    again = hit.get("flexure_hiding") or {}
    t = rem["statistic"] if rem else again.get("t", float("nan"))
    return {"seed": seed, "mdb": mdb, "sigma": float(h["sigma_arcsec_per_g"]),
            "nu": h.get("nu"), "shift": mdb / float(h["sigma_arcsec_per_g"]),
            "t": float(t), "detected": bool(rem), "cpu": cpu + cpu2,
            "after": "+".join(h["after"]),
            "injected_after": (rem or {}).get("detail", {}).get("after")
            or again.get("after")}


def at_mdb(seeds: range, duration: float, also: dict, single: bool) -> None:
    """The table of :func:`mdb_row` over ``seeds`` and the power at the printed MDB."""
    print("| seed | after | printed MDB \"/g | sigma \"/g | nu | MDB/sigma | t at the MDB | "
          "remainder said | CPU-s |\n|---|---|---|---|---|---|---|---|---|")
    rows = []
    for seed in seeds:
        r = mdb_row(seed, duration, also, single)
        rows.append(r)
        if r["mdb"] is None:
            print(f"| {seed} | - | none printed ({r['why']}) | | | | | | {r['cpu']:.0f} |",
                  flush=True)
            continue
        nu = f"{r['nu']:.0f}" if r["nu"] else "-"
        print(f"| {seed} | {r['after']} | {r['mdb']:.2f} | {r['sigma']:.2f} | {nu} | "
              f"{r['shift']:.2f} | {r['t']:.2f} | {'yes' if r['detected'] else 'no'} | "
              f"{r['cpu']:.0f} |", flush=True)
    got = [r for r in rows if r["mdb"] is not None]
    if not got:
        print("no MDB printed on any seed")
        return
    k, n = sum(r["detected"] for r in got), len(got)
    share = k / n
    ts = np.abs([r["t"] for r in got])
    print(f"power at the printed MDB: {k}/{n} = {share:.0%} +- "
          f"{np.sqrt(share * (1 - share) / n):.0%}"
          f" (binomial; target 80 % +- 15 %); |t| at the MDB {ts.mean():.2f} +- "
          f"{ts.std(ddof=1) / np.sqrt(n) if n > 1 else float('nan'):.2f} (mean +- its sigma) "
          f"against the shift the MDB is made of {np.mean([r['shift'] for r in got]):.2f}; "
          f"{len(rows) - n} seed(s) printed no MDB")


def null_p(seed: int, duration: float) -> float:
    """The remainder test's p on a bag with a true gyro scale factor, gsf in the model."""
    sim, data = _bag({"gyro_scale_factor": 1e-4}, seed, duration)
    spec = method_spec("psce")
    effects = ("gyro_scale_factor",)
    run = replay_psce(data, sim.prior, list(effects), keep_tables=True)
    res = add_gravity_regressors(run.residuals, data, run.calibration)
    moved = flexure.measure_on_bag(data, spec, sim.prior, effects, 0.5)
    got = flexure.remainder_statistics(res, moved, 0.5)
    return float("nan") if got is None else got["p_value"]


def main() -> int:
    """Print the table and the null level."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="10,20,40,80")
    ap.add_argument("--seed", type=int, default=52)
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--null-seeds", type=int, default=0)
    ap.add_argument("--single", action="store_true",
                    help="a single diagnose round instead of discover")
    ap.add_argument("--with", dest="also", action="append", default=[], metavar="ID=SIZE",
                    help="a true library effect in the bag beside the flexure (repeatable)")
    ap.add_argument("--first-null-seed", type=int, default=2000)
    ap.add_argument("--at-mdb", type=int, default=0, metavar="N",
                    help="inject a flexure at the MDB each of N seeds prints (from --seed)")
    args = ap.parse_args()
    also = {k: float(v) for k, v in (a.split("=", 1) for a in args.also)}
    print(f"psce_rotations, {args.duration:g} s, seed {args.seed}; discover (noise estimated)"
          + "".join(f"; true {k} {v:g}" for k, v in also.items()))
    sizes = [float(x) for x in args.sizes.split(",") if x]
    if args.at_mdb:
        also = also or {"gyro_scale_factor": 1e-4}
        print(("a single diagnose round" if args.single else "discover")
              + f", power at the printed flexure MDB; bag: {also}")
        at_mdb(range(args.seed, args.seed + args.at_mdb), args.duration, also, args.single)
        return 0
    if args.single:
        print("| flexure | recommendation | remainder | CPU-s |\n|---|---|---|---|")
        for size in sizes:
            print(single_row(size, args.seed, args.duration, also), flush=True)
        sizes = []
    else:
        print("| flexure | added | remainder test after each add | first 'unexplained' | "
              "report | CPU-s |")
        print("|---|---|---|---|---|---|")
    for size in sizes:
        print(discover_row(size, args.seed, args.duration, also), flush=True)
    if args.null_seeds:
        ps = np.array([null_p(s, args.duration) for s in range(
            args.first_null_seed, args.first_null_seed + args.null_seeds)])
        ok = ps[np.isfinite(ps)]
        print(f"null (true gyro_scale_factor 1e-4, gsf in the model), {len(ok)} seeds: "
              + ", ".join(f"p<{a:g}: {np.mean(ok < a):.0%}" for a in (0.05, 0.01, 0.001))
              + f"; smallest p {ok.min():.2g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
