"""The flexure sizes the diagnosis prints, checked by injecting a flexure of that size.

Two printed numbers, each a size the gravity-shaped test (:func:`~stellar_cal_ros.
diagnosis.flexure.remainder_statistics`, t_ν referred, Bonferroni over ``m`` tests at
α = 1 %) claims to see with a stated power:

* ``hiding`` -- "a mount flexure ... up to X arcsec per unit lateral gravity could still
  hide" (:func:`~stellar_cal_ros.diagnosis.flexure.hiding`, power 80 %, ``m`` = 1): the test
  after gyro_scale_factor on a bag with a true 1e-4 gyro scale factor;
* ``alias`` -- "with gyro_misalignment in the model the test sees X arcsec/g with power
  50 %" (:func:`~stellar_cal_ros.diagnosis.flexure.alias_size`, ``m`` = 2, as discover's
  mixed case: a remainder test after each of the two adds): the test after
  gyro_scale_factor + gyro_misalignment on the same bag.

For each seed: the bag (psce_rotations, a true 1e-4 gyro scale factor, no flexure) is
replayed from the simulation's prior with each model and the test made (the model's run and
its run with the probe: :func:`~stellar_cal_ros.diagnosis.flexure.pair_on_bag`, noise as
stated, window 0.5); the printed size X is read; a flexure of exactly X (the simulator's
``mount_flexure``) is injected into the same seed's bag and the same model's test made
again: detected when ``p m < α``.  Prints each seed's X, t and verdict, then for each check
the share detected (binomial σ) against the stated power, the mean t at X (its σ from
the seeds' scatter) against the shift δ X is made of, and what the flexure the test prints
moved by, over the size injected (its mean over the seeds ± its standard error: 1 when the
printed flexure reads the truth).

``--factor F`` injects F X instead of X (F = 0.7: what a wrong MDB factor would print; the
checks must fail).

Run::

    .venv/bin/python benchmarks/flexure_power.py --seeds 20
    .venv/bin/python benchmarks/flexure_power.py --seeds 20 --factor 0.7
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from stellar_cal_ros.diagnosis import flexure
from stellar_cal_ros.diagnosis.discover import method_spec
from stellar_cal_ros.diagnosis.reliability import delta_t
from stellar_cal_ros.methods.replay import bag_data_from_simulation
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

ALPHA = 0.01
TRUTH = {"gyro_scale_factor": 1e-4}
#: check: (model, m, stated power)
CHECKS = {"hiding": (("gyro_scale_factor",), 1, 0.8),
          "alias": (("gyro_scale_factor", "gyro_misalignment"), 2, flexure.ALIAS_POWER)}


def _test(effects: dict, seed: int, duration: float, model: tuple[str, ...]):
    sim = simulate(get_scenario("psce_rotations"), duration=duration, seed=seed,
                   effects=effects)
    return flexure.pair_on_bag(bag_data_from_simulation(sim), method_spec("psce"), sim.prior,
                               model, 0.5)


def printed(check: str, got: dict) -> tuple[float, float, float]:
    """The size the diagnosis prints for ``check`` from the test ``got``, its σ and δ."""
    model, m, power = CHECKS[check]
    if check == "hiding":
        h = flexure.hiding(got, list(model), m, ALPHA)
        return h["arcsec_per_g"], h["sigma_arcsec_per_g"], delta_t(ALPHA / m, got["nu"], power)
    size, se = flexure.alias_size(got, m, ALPHA)
    return size, se, delta_t(ALPHA / m, got["nu"], power)


def seed_rows(seed: int, duration: float, checks: list[str], factor: float = 1.0
              ) -> list[dict]:
    """One seed: each check's printed size on the bag, then that flexure injected."""
    rows = []
    for check in checks:
        model, m, power = CHECKS[check]
        clean = _test(TRUTH, seed, duration, model)
        if clean is None:
            rows.append({"check": check, "seed": seed, "size": None})
            continue
        size, se, shift = printed(check, clean)
        hit = _test({**TRUTH, "mount_flexure": factor * size}, seed, duration, model)
        t = float("nan") if hit is None else float(hit["t"])
        p = 1.0 if hit is None else min(1.0, hit["p_value"] * m)
        robust = clean.get("robust_sigma_arcsec_per_g") or clean["sigma_arcsec_per_g"]
        rows.append({"check": check, "seed": seed, "size": size, "sigma": se,
                     "robust": float(robust),
                     "shift": shift, "nu": clean["nu"], "t_clean": float(clean["t"]),
                     "t": t, "detected": p < ALPHA, "power": power,
                     "estimate_clean": float(clean["arcsec_per_g"]),
                     "estimate": None if hit is None else float(hit["arcsec_per_g"])})
    return rows


def summary(rows: list[dict]) -> dict:
    """What the injections say of the printed size (rows of one check).

    ``share`` detected against the stated ``power`` (``binomial_sigma`` at that power);
    ``mean_t`` (|t| at the size) against ``expected_t``, the mean of the non-central t_ν
    with the shift δ each size is made of, ``z`` the difference over its σ (the nct's
    variances: the claim includes that t has the t_ν scale); ``response``: the mean of
    ``(t at the size − t before) / δ``, what the injected flexure moved t by (1 when the
    flexure moves the innovations as the probe's response says and the size is σ δ).
    """
    from scipy import stats as sps

    got = [r for r in rows if r["size"] is not None and np.isfinite(r["t"])]
    n = len(got)
    power = got[0]["power"]
    k = sum(r["detected"] for r in got)
    t = np.array([abs(r["t"]) for r in got])
    mean, var = zip(*(sps.nct.stats(r["nu"], r["shift"], moments="mv") for r in got),
                    strict=True)
    response, expected = responses(got)
    read = np.array([(r["estimate"] - r["estimate_clean"]) / r["size"] for r in got
                     if r["estimate"] is not None])
    sigma_read = float(read.std(ddof=1) / np.sqrt(len(read))) if len(read) > 1 else np.nan
    return {"read": float(read.mean()), "sigma_read": sigma_read,
            "n": n, "k": k, "share": k / n, "binomial_sigma": np.sqrt(power * (1 - power) / n),
            "power": power, "mean_t": float(t.mean()), "expected_t": float(np.mean(mean)),
            "z": float((t.sum() - np.sum(mean)) / np.sqrt(np.sum(var))),
            "shift": float(np.mean([r["shift"] for r in got])),
            "response": float(response.mean()), "response_min": float(response.min()),
            "response_max": float(response.max()), "expected_response": float(expected.mean()),
            "response_gap": float(np.mean(response - expected)),
            "sigma_response_gap": float(np.std(response - expected, ddof=1) / np.sqrt(n))}


def responses(rows: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """What the injected flexure moved t by, in δ, and what the printed size says it should.

    ``(t at the size − t before) / δ`` (signed as t at the size), and ``σ / σ_robust``: the
    size is ``σ δ`` with ``σ`` the standard error the line prints (for the MDB the larger of
    the frame-robust and the whitened one), and moving the innovations by ``k S`` moves t by
    ``k / σ_robust`` -- so the two agree when the real flexure moves the innovations as the
    probe's response says and the size is made with the right factor (a size made ×0.7
    moves t by 0.7 of what is expected).
    """
    r = np.array([(np.sign(x["t"]) or 1.0) * (x["t"] - x["t_clean"]) / x["shift"]
                  for x in rows])
    e = np.array([x["sigma"] / x["robust"] for x in rows])
    return r, e


def main() -> int:
    """Print the per-seed table and each check's summary."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=600)
    ap.add_argument("--duration", type=float, default=200.0)
    ap.add_argument("--checks", default="hiding,alias")
    ap.add_argument("--factor", type=float, default=1.0)
    args = ap.parse_args()
    checks = [c for c in args.checks.split(",") if c]
    print(f"psce_rotations {args.duration:g} s, true gyro_scale_factor 1e-4, seeds "
          f"{args.first_seed}..{args.first_seed + args.seeds - 1}, injected "
          f"{args.factor:g} x the printed size")
    print("| check | seed | printed \"/g | sigma \"/g | nu | delta | t before | t at the size "
          "| estimate before / at the size \"/g | detected | CPU-s |\n"
          "|---|---|---|---|---|---|---|---|---|---|---|")
    rows = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        t0 = time.process_time()
        got = seed_rows(seed, args.duration, checks, args.factor)
        cpu = time.process_time() - t0
        for r in got:
            if r["size"] is None:
                print(f"| {r['check']} | {seed} | no test | | | | | | | | {cpu:.0f} |")
                continue
            print(f"| {r['check']} | {seed} | {r['size']:.1f} | {r['sigma']:.2f} | "
                  f"{r['nu']:.0f} | {r['shift']:.2f} | {r['t_clean']:.2f} | {r['t']:.2f} | "
                  f"{r['estimate_clean']:.1f} / {r['estimate']:.1f} | "
                  f"{'yes' if r['detected'] else 'no'} | {cpu:.0f} |",
                  flush=True)
        rows += got
    for check in checks:
        s = summary([r for r in rows if r["check"] == check])
        print(f"{check}: detected {s['k']}/{s['n']} = {s['share']:.0%} against the stated "
              f"{s['power']:.0%} +- {s['binomial_sigma']:.0%} (binomial sigma); mean |t| at "
              f"the size {s['mean_t']:.2f} against {s['expected_t']:.2f} (nct at delta "
              f"{s['shift']:.2f}; z = {s['z']:.2f}); t moved by {s['response']:.3f} delta "
              f"({s['response_min']:.3f}..{s['response_max']:.3f}) where the size says "
              f"{s['expected_response']:.3f}: gap {s['response_gap']:.3f} +- "
              f"{s['sigma_response_gap']:.3f}; the estimate moved by {s['read']:.3f} +- "
              f"{s['sigma_read']:.3f} of the size injected (1: it reads the truth)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
