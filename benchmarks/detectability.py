"""Minimum detectable size of every PSCE candidate effect (issue 5).

For each library effect that is a candidate for the PSCE method (not in its baseline, not
an accelerometer effect), the demo scenario (``psce_rotations``, 0.05 px centroid noise) is
simulated with the effect at a ladder of sizes; the baseline model is calibrated and the
diagnosis run over **all** applicable candidates.  The minimum detectable size (MDS) is the
smallest rung at which the effect ranks first *and* is significant (Bonferroni-corrected
p < 0.01, explained-variance floor) in at least ``--need`` of ``--seeds`` seeds.

A seed is first screened with the effect's own augmented run (its p-value corrected for the
number of applicable candidates); only when that is significant is the full ranking run.  A
rung stops as soon as its outcome is decided.

Units are those of ``--effect ID=VALUE`` (``stellar_cal_ros/sim/truth_effects.py``).
Thermal focal drift is detectable only through the head-temperature *change* over the run
(30 °C decaying toward 10 °C with τ = 3600 s: 1.6 °C in 300 s); the constant offset from
the 20 °C reference is absorbed by the focal length.

Last result (2026-11-22, 5 seeds, 4 needed, 300 s; vector effects: every component)::

    effect                 unit       min. detectable size
    pixel_aspect           1                       1.6e-05
    radial_k3              1             > 240 (absorbed by k1, k2 on the 14.7° field)
    image_plane_tilt       rad                       0.004
    thermal_focal_length   1/degC                    1e-05
    gyro_scale_factor      1                       1.1e-05
    gyro_misalignment      rad                     1.3e-05  (symmetric: all six equal)
    time_offset            s                       5.3e-05
    aberration             x phys.                   0.141
    refraction             x phys.                  0.0325
    proper_motion          x phys.                   0.046

Near the threshold the wrong effect sometimes ranks first: pixel_aspect for a small
image_plane_tilt, aberration (as a free scale) for a small isotropic gyro scale factor and
vice versa.  The astrometric scales are ladder-tested as free parameters
(``physical_check=False``); in the diagnosis itself they are claimed only near scale 1.

The diagnosis also predicts these sizes without a ladder: the minimal detectable bias
(MDB, power 0.8 at the round's Bonferroni level) from the information each candidate's
augmented run carries (``stellar_cal_ros/diagnosis/reliability.py``).  ``--mdb`` prints it
for clean bags (one diagnosis per seed, a minute), next to the ladder's result above::

    effect                 MDB (information), seeds 100, 101
    pixel_aspect           1.4e-05
    image_plane_tilt       0.0033 .. 0.0041
    thermal_focal_length   1.3e-05
    gyro_scale_factor      1.1e-05 .. 3.2e-05  (per axis)
    gyro_misalignment      3.1e-05 .. 4.8e-05  (per entry)
    time_offset            4e-05
    aberration             0.092
    refraction             0.023
    proper_motion          0.04
    radial_k3              18 (above its plausible size 2: not testable)

The MDB is a little smaller than the ladder's size, which also requires ranking first.

Run (about 25 minutes on one core)::

    .venv/bin/python benchmarks/detectability.py
    .venv/bin/python benchmarks/detectability.py --effects pixel_aspect,time_offset --seeds 5
    .venv/bin/python benchmarks/detectability.py --mdb --seeds 2
"""

from __future__ import annotations

import argparse
import logging
import sys
import time

import numpy as np

from stellar_cal_ros.diagnosis.discover import _applicable, method_spec, rank_candidates
from stellar_cal_ros.effects import registry
from stellar_cal_ros.methods.replay import bag_data_from_simulation, replay_psce
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

#: first guess of the MDS per effect: the result of the last full run (the bottom of the
#: ladder is half of it; when that is already detected the ladder descends)
GUESS = {
    "pixel_aspect": 1.6e-5,
    "radial_k3": 30.0,
    "image_plane_tilt": 4e-3,
    "thermal_focal_length": 1e-5,
    "gyro_scale_factor": 1.1e-5,
    "gyro_misalignment": 1.3e-5,
    "time_offset": 5.3e-5,
    "aberration": 0.141,
    "refraction": 0.0325,
    "proper_motion": 0.046,
}
#: size ladder relative to the guess (factor √2 between rungs)
LADDER = tuple(2.0 ** (k / 2.0) for k in range(-2, 7))


def psce_candidates(data) -> list[str]:
    """Library effects the PSCE diagnosis ranks on this bag (not baseline, applicable)."""
    spec = method_spec("psce")
    return [e for e in registry.available()
            if e not in spec.baseline and not _applicable(e, spec, data)]


def one_seed(effect: str, size: float, seed: int, duration: float,
             scenario: str = "psce_rotations") -> dict:
    """Simulate, calibrate the baseline, diagnose: did ``effect`` rank first, significant."""
    spec = method_spec("psce")
    sim = simulate(get_scenario(scenario), duration=duration, seed=seed,
                   effects={effect: size})
    data = bag_data_from_simulation(sim)
    cal = replay_psce(data, sim.prior).calibration
    pool = psce_candidates(data)
    # Screen: the effect's own augmented run, corrected for the whole pool.
    # The astrometric scales are measured as free parameters (their physical-size check
    # would reject any non-physical scale by design): the MDS is their detectability.
    free = registry.effect_class(effect).physical_value is None
    _, own = rank_candidates(data, cal, spec, [], [effect], physical_check=free)
    c = own[0]
    p_adj = min(1.0, c.p_value * len(pool))
    screen = (c.status == "ranked" and p_adj < 0.01
              and not c.explained < 0.1)  # same floor as discover.MIN_EXPLAINED
    out = {"detected": False, "first": None, "statistic": c.statistic, "status": c.status}
    if not screen:
        return out
    _, results = rank_candidates(data, cal, spec, [], pool, physical_check=free)
    ranked = [r for r in results if r.status == "ranked"]
    first = ranked[0] if ranked else None
    out["first"] = first.effect if first else None
    out["detected"] = bool(first is not None and first.effect == effect and first.significant)
    return out


def mds(effect: str, seeds: int, need: int, duration: float, ladder=LADDER,
        verbose: bool = True) -> tuple[float, list[str]]:
    """Smallest ladder size detected in ``need`` of ``seeds`` seeds (nan if none).

    The ladder is climbed from its bottom; if the bottom rung is already detected, it is
    descended instead (factor √2) until a rung is missed.
    """
    notes: list[str] = []
    first = _rung(effect, GUESS[effect] * ladder[0], seeds, need, duration, notes, verbose)
    if first:
        size = GUESS[effect] * ladder[0]
        for k in range(1, 9):
            lower = GUESS[effect] * ladder[0] * 2.0 ** (-k / 2.0)
            if not _rung(effect, lower, seeds, need, duration, notes, verbose):
                break
            size = lower
        return size, notes
    for factor in ladder[1:]:
        size = GUESS[effect] * factor
        if _rung(effect, size, seeds, need, duration, notes, verbose):
            return size, notes
    return float("nan"), notes


def _rung(effect: str, size: float, seeds: int, need: int, duration: float,
          notes: list[str], verbose: bool) -> bool:
    """Is ``effect`` at ``size`` detected in ``need`` of ``seeds`` seeds."""
    hits = misses = 0
    wrong = set()
    for seed in range(seeds):
        r = one_seed(effect, size, 100 + seed, duration)
        hits += r["detected"]
        misses += not r["detected"]
        if r["first"] not in (None, effect):
            wrong.add(r["first"])
        if hits >= need or misses > seeds - need:
            break
    line = f"{effect:22s} size {size:10.3g}: {hits} detected, {misses} missed" + (
        f" (ranked first instead: {', '.join(sorted(wrong))})" if wrong else "")
    notes.append(line)
    if verbose:
        print("   " + line, flush=True)
    return hits >= need


def information_mdb(seeds: int, duration: float) -> dict[str, list[dict[str, float]]]:
    """MDB per candidate and parameter from one clean diagnosis per seed."""
    spec = method_spec("psce")
    out: dict[str, list[dict[str, float]]] = {}
    for seed in range(seeds):
        sim = simulate(get_scenario("psce_rotations"), duration=duration, seed=100 + seed)
        data = bag_data_from_simulation(sim)
        _, results = rank_candidates(data, sim.prior, spec, [], psce_candidates(data))
        for c in results:
            if c.detect is not None:
                out.setdefault(c.effect, []).append(c.detect.mdb)
    return out


def main(argv: list[str] | None = None) -> int:
    """Print the minimum-detectable-size table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--effects", default=",".join(GUESS))
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--need", type=int, default=4)
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--mdb", action="store_true",
                    help="only the MDB from the information of clean bags (fast)")
    args = ap.parse_args(argv)
    logging.disable(logging.WARNING)
    print("command: " + " ".join([sys.executable, *sys.argv]))
    if args.mdb:
        print(f"{'effect':22s} MDB (information) per parameter, seeds 100..{99 + args.seeds}")
        for effect, rows in information_mdb(args.seeds, args.duration).items():
            lo = min(min(r.values()) for r in rows)
            hi = max(max(r.values()) for r in rows)
            print(f"{effect:22s} {lo:.2g}" + (f" .. {hi:.2g}" if hi > 1.05 * lo else ""))
        return 0
    print(f"scenario psce_rotations, 0.05 px, {args.duration:.0f} s; detected = ranked first "
          f"among all PSCE candidates and significant in >= {args.need}/{args.seeds} seeds")
    rows = []
    t0 = time.perf_counter()
    for effect in args.effects.split(","):
        size, _ = mds(effect, args.seeds, args.need, args.duration)
        rows.append((effect, size))
    print()
    print(f"{'effect':22s} {'unit':8s} {'min. detectable size':>22s}")
    for effect, size in rows:
        unit = registry.create(effect).units[0]
        if effect in ("aberration", "refraction", "proper_motion"):
            unit = "x phys."
        text = f"{size:.3g}" if np.isfinite(size) else \
            f"> {GUESS[effect] * LADDER[-1]:.3g} (not found)"
        print(f"{effect:22s} {unit:8s} {text:>22s}")
    print(f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
