r"""The printed bias of a hidden effect against its injection, per size, seed and effect.

Measures why image_plane_tilt's printed gyro-bias biases are not what an injection does
(doc/benchmarks.md, "Every printed number checked by injection"): for each seed a clean
``psce_rotations`` bag is replayed with the effects as consider parameters (the printed
bias of parameter j at size b is ``-M[:, j] b``, :mod:`stellar_cal_ros.methods.screening`),
then the effect is injected at ``± size`` into the paired bag and the current model is
re-run; the odd part of the paired shift over the size is the first-order response, which
``-M b`` claims.  Run::

    .venv/bin/python benchmarks/tilt_gyro_bias.py --fractions 1,0.3,0.1          # sizes
    .venv/bin/python benchmarks/tilt_gyro_bias.py --seeds 5,6,7,8,9,10,11,12      # seeds
    .venv/bin/python benchmarks/tilt_gyro_bias.py --parameter best \
        --effects gyro_misalignment,gyro_scale_factor,time_offset,pixel_aspect,image_plane_tilt
    .venv/bin/python benchmarks/tilt_gyro_bias.py --trace gyro_bias.by --size 2.1e-3  # per frame

``--trace Q`` follows quantity Q frame by frame (the numpy reference step, whose
sensitivity is the compiled one's): the filter's odd response against −M's row over time
shows where the two part.
"""

from __future__ import annotations

import argparse

import numpy as np

from stellar_cal_ros.diagnosis import injection
from stellar_cal_ros.diagnosis.discover import rerun_prior
from stellar_cal_ros.methods.replay import bag_data_from_simulation, replay
from stellar_cal_ros.methods.screening import score_tests
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

QUANTITIES = ("gyro_bias.bx", "gyro_bias.by", "gyro_bias.bz", "installation.rx",
              "installation.ry", "principal_point.cy", "radial_k1k2.k2", "tangential.p1")


def _data(duration: float, seed: int, effects=None):
    sim = simulate(get_scenario("psce_rotations"), duration=duration, seed=seed,
                   effects=effects or {}, paired_with={} if effects else None)
    return sim, bag_data_from_simulation(sim)


def measure(duration: float, seed: int, effects: list[str], parameter: str, size: float,
            fractions: list[float], alpha: float) -> list[dict]:
    """Rows ``{effect, parameter, fraction, quantity, printed, odd, sigma}`` of one seed."""
    sim, data = _data(duration, seed)
    prior = rerun_prior(sim.prior)
    base = replay(data, prior, "psce", [], consider=effects, keep_tables=False)
    scores = score_tests(base, effects)
    names = base.filter.model.parameter_names()
    sigma = dict(zip(names, np.sqrt(np.diag(base.filter.P)[base.filter.it]), strict=False))
    before = injection.run_values(base)
    rows = []
    for eid in effects:
        cs = scores[eid]
        mdb = cs.mdb_per_parameter(alpha)
        j = (int(np.argmin(mdb)) if parameter == "best"
             else cs.parameters.index(f"{eid}.{parameter}"))
        b = size if size > 0 else float(mdb[j])
        printed = dict(zip(names, cs.bias_per_unit[:, j] * b, strict=False))
        p = cs.parameters[j].split(".", 1)[1]
        for f in fractions:
            shifts = []
            for sign in (1, -1):
                delta = injection.parameter_delta(eid, p, sign * f * b)
                _, inj = _data(duration, seed, {eid: injection.simulation_value(eid, delta)})
                run = replay(inj, prior, "psce", [], consider=[eid], keep_tables=False)
                shifts.append(injection.paired_shift(before, injection.run_values(run)))
            for q in QUANTITIES:
                if q in printed and q in shifts[0]:
                    rows.append({"seed": seed, "effect": eid, "parameter": p, "size": b,
                                 "fraction": f, "quantity": q, "printed": printed[q],
                                 "odd": 0.5 * (shifts[0][q] - shifts[1][q]) / f,
                                 "sigma": sigma.get(q, np.nan)})
    return rows


def trace(duration: float, seed: int, effect: str, parameter: str, size: float,
          quantity: str, every: int) -> None:
    """Print the filter's odd response of ``quantity`` and −M's row, frame by frame."""
    from stellar_cal_ros.methods import kernel

    records: list[list] = []
    update = kernel.StarFilter.update

    def recorded(self, *args, **kwargs):
        out = update(self, *args, **kwargs)
        names = self.model.parameter_names()
        i, col = names.index(quantity), names.index(f"{effect}.{parameter}") - self.P_est
        records[-1].append((self.t, float(self.theta[i]),
                            float(self.sensitivity.M[self.it][i, col])))
        return out

    kernel.StarFilter.compiled_step, kernel.StarFilter.update = False, recorded
    try:
        sim, data = _data(duration, seed)
        prior = rerun_prior(sim.prior)
        for sign in (0, 1, -1):
            records.append([])
            d = data if sign == 0 else _data(duration, seed, {effect: injection.simulation_value(
                effect, injection.parameter_delta(effect, parameter, sign * size))})[1]
            replay(d, prior, "psce", [], consider=[effect], keep_tables=False)
    finally:
        kernel.StarFilter.compiled_step, kernel.StarFilter.update = True, update
    clean, plus, minus = records
    print(f"{quantity} per unit {effect}.{parameter} (size {size:g}), seed {seed}")
    print(f"{'frame':>5s} {'t s':>8s} {'-M row':>11s} {'odd response':>13s}")
    n = min(map(len, records))
    for k in sorted(set(range(0, n, every)) | {n - 1}):
        odd = 0.5 * (plus[k][1] - minus[k][1]) / size
        print(f"{k:5d} {clean[k][0]:8.2f} {-clean[k][2]:11.3e} {odd:13.3e}")


def main() -> int:
    """Measure and print one line per (seed, effect, size, quantity), then per-seed means."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=150.0)
    ap.add_argument("--seeds", default="5")
    ap.add_argument("--effects", default="image_plane_tilt")
    ap.add_argument("--parameter", default="tau_x", help="injected parameter, or 'best'")
    ap.add_argument("--size", type=float, default=7e-3,
                    help="injected size (the parameter's units); 0: its MDB")
    ap.add_argument("--fractions", default="1")
    ap.add_argument("--alpha", type=float, default=0.01 / 20)
    ap.add_argument("--trace", default="", help="a quantity to follow frame by frame")
    ap.add_argument("--every", type=int, default=9, help="--trace: print every n-th frame")
    args = ap.parse_args()
    if args.trace:
        trace(args.duration, int(args.seeds.split(",")[0]), args.effects.split(",")[0],
              args.parameter, args.size, args.trace, args.every)
        return 0
    seeds = [int(s) for s in args.seeds.split(",")]
    effects = args.effects.split(",")
    fractions = [float(f) for f in args.fractions.split(",")]
    size = args.size if args.parameter != "best" else 0.0
    rows = []
    print(f"{'seed':>4s} {'effect':20s} {'param':8s} {'x size':>6s} {'quantity':20s} "
          f"{'printed':>11s} {'odd/size':>11s} {'ratio':>7s} {'|printed|/σ':>11s}")
    for seed in seeds:
        for r in measure(args.duration, seed, effects, args.parameter, size, fractions,
                         args.alpha):
            rows.append(r)
            print(f"{r['seed']:4d} {r['effect']:20s} {r['parameter']:8s} {r['fraction']:6.2g} "
                  f"{r['quantity']:20s} {r['printed']:11.3e} {r['odd']:11.3e} "
                  f"{r['odd'] / r['printed']:7.3f} {abs(r['printed']) / r['sigma']:11.2f}",
                  flush=True)
    if len(seeds) > 1:
        print("\nover seeds (mean printed, mean odd ± its standard error, ratio of means)")
        for eid in effects:
            for f in fractions:
                for q in QUANTITIES:
                    sel = [r for r in rows if r["effect"] == eid and r["quantity"] == q
                           and r["fraction"] == f]
                    if not sel:
                        continue
                    pr = np.array([r["printed"] for r in sel])
                    od = np.array([r["odd"] for r in sel])
                    print(f"{eid:20s} x{f:<4g} {q:20s} printed {pr.mean():11.3e} "
                          f"(sd {pr.std(ddof=1):.2e})  odd {od.mean():11.3e} ± "
                          f"{od.std(ddof=1) / np.sqrt(len(od)):.2e}  ratio "
                          f"{od.mean() / pr.mean():7.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
