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
    .venv/bin/python benchmarks/tilt_gyro_bias.py --reseed 0,60,119,120,121,200 \
        --trace gyro_bias.by --size 2e-4 [--noise 0]

``--trace Q`` follows quantity Q frame by frame (the numpy reference step, whose
sensitivity is the compiled one's): the filter's odd response against −M's row over time
shows where the two part.  ``--reseed K,…`` sets the recursion's column to the measured odd
response right after update K (0: the acquisition) and prints its end value for Q: where
re-seeding stops mattering, the updates that follow are linearized right and the
discrepancy was made before; it also lists the updates with the largest attitude
corrections.  ``--noise 0`` draws no centroid or IMU noise (the stated σ unchanged).
``--acquisition`` compares the acquisition's rows (−M of the attitude right after it) with
the acquired attitude's measured odd response, the filter started from the prior and from
the truth (the linearization point of the effect's Jacobian)::

    .venv/bin/python benchmarks/tilt_gyro_bias.py --acquisition --size 2e-4 --duration 5
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from stellar_cal_ros.diagnosis import injection, reliability
from stellar_cal_ros.diagnosis.discover import rerun_prior
from stellar_cal_ros.methods.replay import bag_data_from_simulation, replay
from stellar_cal_ros.methods.screening import score_tests
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

QUANTITIES = ("gyro_bias.bx", "gyro_bias.by", "gyro_bias.bz", "installation.rx",
              "installation.ry", "principal_point.cy", "radial_k1k2.k2", "tangential.p1")


def _data(duration: float, seed: int, effects=None, noise: float = 1.0):
    scenario = get_scenario("psce_rotations")
    quiet = dataclasses.replace(scenario, centroid_noise_px=noise * scenario.centroid_noise_px,
                                gyro_arw_deg_sqrth=noise * scenario.gyro_arw_deg_sqrth,
                                accel_vrw_mps_sqrth=noise * scenario.accel_vrw_mps_sqrth)
    sim = simulate(quiet, duration=duration, seed=seed,
                   effects=effects or {}, paired_with={} if effects else None)
    if noise != 1.0:  # the noise the messages state stays the scenario's
        stated = simulate(scenario, duration=duration, seed=seed)
        sim = dataclasses.replace(sim, imu=stated.imu.__class__(
            **{**vars(sim.imu), "angular_velocity_covariance":
               stated.imu.angular_velocity_covariance, "linear_acceleration_covariance":
               stated.imu.linear_acceleration_covariance}), star_frames=[
            dataclasses.replace(f, sigma=np.full(len(f.sigma), scenario.centroid_noise_px))
            for f in sim.star_frames], prior=stated.prior)
    return sim, bag_data_from_simulation(sim)


def measure(duration: float, seed: int, effects: list[str], parameter: str, size: float,
            fractions: list[float], alpha: float, quantities=QUANTITIES) -> list[dict]:
    """Rows ``{effect, parameter, fraction, quantity, printed, odd, sigma, share}``, one seed.

    ``share``: the row's |printed| / σ over the largest of the injection's rows (what
    :data:`~stellar_cal_ros.diagnosis.reliability.FIRST_ORDER_SHARE` bounds);
    ``quantities`` None: every estimated parameter.
    """
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
        # each parameter alone at its MDB (the diagnosis's, at this level)
        mdb = np.array(list(reliability.detectability(eid, cs.info, alpha).mdb.values()))
        j = (int(np.argmin(mdb)) if parameter == "best"
             else cs.parameters.index(f"{eid}.{parameter}"))
        b = size if size > 0 else float(mdb[j])
        printed = dict(zip(names, cs.bias_per_unit[:, j] * b, strict=False))
        p = cs.parameters[j].split(".", 1)[1]
        largest = max(abs(v) / sigma[q] for q, v in printed.items() if sigma.get(q, 0) > 0)
        for f in fractions:
            shifts = []
            for sign in (1, -1):
                delta = injection.parameter_delta(eid, p, sign * f * b)
                _, inj = _data(duration, seed, {eid: injection.simulation_value(eid, delta)})
                run = replay(inj, prior, "psce", [], consider=[eid], keep_tables=False)
                shifts.append(injection.paired_shift(before, injection.run_values(run)))
            for q in names if quantities is None else quantities:
                if q in printed and q in shifts[0]:
                    rows.append({"seed": seed, "effect": eid, "parameter": p, "size": b,
                                 "fraction": f, "quantity": q, "printed": printed[q],
                                 "odd": 0.5 * (shifts[0][q] - shifts[1][q]) / f,
                                 "sigma": sigma.get(q, np.nan),
                                 "share": abs(printed[q]) / sigma.get(q, np.nan) / largest})
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


def reseed(duration: float, seed: int, effect: str, parameter: str, size: float,
           quantity: str, ks: list[int], noise: float) -> None:
    """End value of −M's row for ``quantity`` with the column re-seeded after update K."""
    from stellar_cal_ros.core.rotation import so3_log
    from stellar_cal_ros.methods import kernel

    update, initialize = kernel.StarFilter.update, kernel.StarFilter.initialize
    inject = kernel.StarFilter.inject
    mode: dict = {}
    states: dict[int, list] = {1: [], -1: []}
    steps: list[tuple] = []

    def after(self, n: int) -> None:
        self._n = n
        col = self.model.parameter_names().index(f"{effect}.{parameter}") - self.P_est
        if mode["sign"]:
            states[mode["sign"]].append((self.R_i_b.copy(), self.theta[:self.P_est].copy()))
        elif n == mode["k"]:
            self.sensitivity.M[:, col] = -measured[n]

    def upd(self, *args, **kwargs):
        out = update(self, *args, **kwargs)
        after(self, self._n + 1)
        return out

    def corrected(self, dx):
        if mode["sign"] == 0 and mode["k"] == ks[0]:
            steps.append((self._n + 1, self.t, float(np.linalg.norm(dx[self.ia]))))
        return inject(self, dx)

    def init(self, *args, **kwargs):
        ok = initialize(self, *args, **kwargs)
        if ok:
            after(self, 0)
        return ok

    kernel.StarFilter.compiled_step = False
    kernel.StarFilter.update, kernel.StarFilter.initialize = upd, init
    kernel.StarFilter.inject = corrected
    try:
        sim, data = _data(duration, seed, noise=noise)
        prior = rerun_prior(sim.prior)
        for sign in (1, -1):
            mode.update(sign=sign, k=-1)
            replay(_data(duration, seed, {effect: injection.simulation_value(
                effect, injection.parameter_delta(effect, parameter, sign * size))}, noise)[1],
                prior, "psce", [], consider=[effect], keep_tables=False)
        measured = [np.concatenate([so3_log(a[0] @ b[0].T), a[1] - b[1]]) / (2 * size)
                    for a, b in zip(states[1], states[-1], strict=True)]
        names = None
        print(f"{quantity} per unit {effect}.{parameter} (size {size:g}), seed {seed}, "
              f"noise x{noise:g}: measured end value, then −M's end value re-seeded after "
              "update K")
        for k in ks:
            mode.update(sign=0, k=k)
            flt = replay(data, prior, "psce", [], consider=[effect], keep_tables=False).filter
            names = ["attitude.x", "attitude.y", "attitude.z"] + \
                flt.model.parameter_names()[:flt.P_est]
            col = flt.model.parameter_names().index(f"{effect}.{parameter}") - flt.P_est
            i = names.index(quantity)
            if k == ks[0]:
                print(f"  measured {measured[-1][i]:11.3e}")
            print(f"  K {k:4d}  {-flt.sensitivity.M[i, col]:11.3e}")
        print("largest attitude corrections (update, t s, |correction| rad):")
        for n, t, a in sorted(steps, key=lambda r: -r[2])[:5]:
            print(f"  {n:4d} {t:8.2f} {a:9.2e}")
    finally:
        kernel.StarFilter.compiled_step = True
        kernel.StarFilter.update, kernel.StarFilter.initialize = update, initialize
        kernel.StarFilter.inject = inject


def _by_share(rows: list[dict], floor: float = 0.3) -> None:
    """Per effect: measured/printed of the rows above ``floor`` σ, by share."""
    from stellar_cal_ros.diagnosis.reliability import FIRST_ORDER_SHARE

    print(f"\nrows above {floor} σ: measured/printed (min-max) at share >= "
          f"{FIRST_ORDER_SHARE} and below it")
    for eid in dict.fromkeys(r["effect"] for r in rows):
        sel = [r for r in rows if r["effect"] == eid and abs(r["printed"]) > floor * r["sigma"]]
        line = f"  {eid:22s}"
        for part in ([r for r in sel if r["share"] >= FIRST_ORDER_SHARE],
                     [r for r in sel if r["share"] < FIRST_ORDER_SHARE]):
            ratio = [r["odd"] / r["printed"] for r in part]
            line += (f"  {len(part):2d} rows {min(ratio):6.3f}-{max(ratio):6.3f}" if part
                     else f"  {0:2d} rows {'':13s}")
        print(line)


def acquisition(duration: float, seed: int, effect: str, parameter: str, size: float) -> None:
    """The acquisition's attitude rows against the acquired attitude's odd response."""
    from stellar_cal_ros.core.rotation import so3_log
    from stellar_cal_ros.methods import kernel

    initialize = kernel.StarFilter.initialize
    got: list[tuple] = []

    def init(self, *args, **kwargs):
        ok = initialize(self, *args, **kwargs)
        if ok:
            col = self.model.parameter_names().index(f"{effect}.{parameter}") - self.P_est
            got.append((self.R_i_b.copy(), -self.sensitivity.M[self.ia, col].copy()))
        return ok

    bags = [_data(duration, seed, {effect: injection.simulation_value(
        effect, injection.parameter_delta(effect, parameter, sign * size))} if sign else None)
        for sign in (0, 1, -1)]
    print(f"attitude per unit {effect}.{parameter} after the acquisition (size {size:g}, "
          f"seed {seed}): the recursion's rows, the measured odd response, their ratio")
    kernel.StarFilter.initialize = init
    try:
        for start in ("prior", "truth"):
            got.clear()
            cal = rerun_prior(getattr(bags[0][0], start))
            for _, data in bags:
                replay(data, cal, "psce", [], consider=[effect], keep_tables=False)
            measured = so3_log(got[1][0] @ got[2][0].T) / (2 * size)
            print(f"  from the {start:5s}  rows {np.array2string(got[0][1], precision=4)}  "
                  f"measured {np.array2string(measured, precision=4)}  ratio "
                  f"{np.array2string(got[0][1] / measured, precision=4)}")
    finally:
        kernel.StarFilter.initialize = initialize


def probe_check(duration: float, seed: int, effects: list[str]) -> list[dict]:
    """Every row the report prints, after the probe runs, against the simulator's injection.

    The clean bag is diagnosed as a user's would be (noise measured, every candidate; the
    rows the first order does not hold are measured by probe runs on the bag,
    :mod:`stellar_cal_ros.diagnosis.reliability_probe`); each effect's parameters that
    carry a listed or probed row are injected with the simulator (same seed) at ± their
    printed size and the current model re-run.  Rows ``{seed, effect, parameter, sign,
    quantity, printed, measured, sigma, listed, probed}``: ``listed`` — the report lists the
    row at that sign (:func:`~stellar_cal_ros.diagnosis.injection.claims`); ``probed`` — a
    probe replaced its first-order value (``first_order`` then holds that value).  The
    equivalent principal point's shift is measured less what the effect does to its true
    value (:func:`~stellar_cal_ros.diagnosis.reliability_probe.own_shift`), as printed.
    """
    import tempfile

    from stellar_cal_ros.core.noise import NoiseScales
    from stellar_cal_ros.diagnosis import reliability_probe
    from stellar_cal_ros.diagnosis.run import diagnose

    sim, data = _data(duration, seed)
    with tempfile.TemporaryDirectory() as tmp:
        summary = diagnose(data, sim.prior, "psce", [], tmp, plots=False, verbose=False)
    noise = NoiseScales.from_dict(summary["noise"]["applied"])
    prior = rerun_prior(sim.prior)
    clean = replay(data, prior, "psce", [], keep_tables=False, noise=noise)
    before = injection.run_values(clean)
    sigma = dict(zip(clean.filter.model.parameter_names(),
                     np.sqrt(np.diag(clean.filter.P)[clean.filter.it]), strict=False))
    sigma.update(zip(("equivalent_principal_point.u", "equivalent_principal_point.v"),
                     (clean.derived or {}).get("equivalent_principal_point_sigma_px",
                                               (np.nan, np.nan)), strict=True))
    rows = []
    for entry in summary.get("reliability", []):
        eid = entry["effect"]
        if eid not in effects:
            continue
        first = {q: v for p in entry.get("probe", {}).values()
                 for q, v in p["first_order"].items()}
        shown = set(entry["dominates"]) | set(first) | set(entry.get("remainders", []))
        for parameter in dict.fromkeys(entry["bias_parameter"][q] for q in sorted(shown)):
            for sign in (1, -1):
                delta = injection.parameter_delta(eid, parameter,
                                                  sign * entry["hidden_size"][parameter])
                _, inj = _data(duration, seed, {eid: injection.simulation_value(eid, delta)})
                shift = injection.paired_shift(before, injection.run_values(replay(
                    inj, prior, "psce", [], keep_tables=False, noise=noise)),
                    reliability_probe.own_shift(sim.truth, "psce", eid, delta))
                listed = injection.claims(entry, sign).get(parameter, [])
                for q in sorted(shown):
                    if entry["bias_parameter"][q] != parameter:
                        continue
                    rows.append({"seed": seed, "effect": eid, "parameter": parameter,
                                 "sign": sign, "quantity": q,
                                 "printed": injection.printed_shift(entry, q, sign),
                                 "measured": shift[q], "first_order": sign * first.get(
                                     q, entry["biases_signed"][q]),
                                 "sigma": sigma.get(q, float("nan")),
                                 "listed": q in listed, "probed": q in first,
                                 "remainder": q in entry.get("remainders", [])})
    return rows


def _print_rows(rows: list[dict]) -> None:
    for r in rows:
        status = ("listed" if r["listed"] else "not listed") + (
            ", probed" if r["probed"] else "") + (", remainder" if r["remainder"] else "")
        print(f"{r['seed']:4d} {r['effect']:20s} {r['parameter']:7s} {r['sign']:+2d} "
              f"{r['quantity']:30s} {r['printed']:10.3e} {r['measured']:10.3e} "
              f"{r['measured'] / r['printed']:6.3f} {r['first_order']:11.3e} "
              f"{r['measured'] / r['first_order']:6.3f} "
              f"{abs(r['measured']) / r['sigma']:6.2f} {status}", flush=True)


def _print_probe(rows: list[dict]) -> None:
    listed = [r for r in rows if r["listed"]]
    held = [r for r in listed if 0.7 <= r["measured"] / r["printed"] <= 1.3]
    probed = [r for r in rows if r["probed"]]
    print(f"\nlisted rows within 0.7-1.3 of the printed shift: {len(held)} of {len(listed)}"
          f" (probed: {sum(r['listed'] for r in probed)} listed, "
          f"{sum(not r['listed'] for r in probed)} measured below σ at that sign)")
    for eid in dict.fromkeys(r["effect"] for r in rows):
        sel = [r for r in listed if r["effect"] == eid]
        ratio = [r["measured"] / r["printed"] for r in sel]
        pr = [r for r in rows if r["effect"] == eid and r["probed"]]
        print(f"  {eid:22s} {len(sel):3d} listed rows, measured/printed "
              + (f"{min(ratio):.3f}-{max(ratio):.3f}" if ratio else "-")
              + (f"; {len(pr)} probed rows: first-order ratio "
                 f"{min(r['measured'] / r['first_order'] for r in pr):.3f}-"
                 f"{max(r['measured'] / r['first_order'] for r in pr):.3f}" if pr else ""))


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
    ap.add_argument("--reseed", default="", help="--trace Q: re-seed −M after these updates")
    ap.add_argument("--noise", type=float, default=1.0, help="--reseed: noise drawn (x)")
    ap.add_argument("--acquisition", action="store_true",
                    help="the acquisition's rows against the measured response")
    ap.add_argument("--quantities", default="",
                    help="'all': every estimated parameter (default: the gyro-bias rows "
                         "and the tilt's), with a summary by share")
    ap.add_argument("--probe", action="store_true",
                    help="every printed row after the probe runs against the simulator's "
                         "injection at ± its size (--effects all: every library effect)")
    args = ap.parse_args()
    if args.probe:
        from stellar_cal_ros.effects import registry

        effects = list(registry.available()) if args.effects == "all" else \
            args.effects.split(",")
        rows = []
        print(f"{'seed':>4s} {'effect':20s} {'param':7s} {'±':>2s} {'quantity':30s} "
              f"{'printed':>10s} {'measured':>10s} {'ratio':>6s} {'first-order':>11s} "
              f"{'ratio':>6s} {'|m|/σ':>6s} status")
        for seed in (int(s) for s in args.seeds.split(",")):
            rows += probe_check(args.duration, seed, effects)
            _print_rows([r for r in rows if r["seed"] == seed])
        _print_probe(rows)
        return 0
    if args.acquisition:
        acquisition(args.duration, int(args.seeds.split(",")[0]), args.effects.split(",")[0],
                    args.parameter, args.size)
        return 0
    if args.reseed:
        reseed(args.duration, int(args.seeds.split(",")[0]), args.effects.split(",")[0],
               args.parameter, args.size, args.trace or "gyro_bias.by",
               [int(k) for k in args.reseed.split(",")], args.noise)
        return 0
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
          f"{'printed':>11s} {'odd/size':>11s} {'ratio':>7s} {'|printed|/σ':>11s} "
          f"{'share':>6s}")
    quantities = None if args.quantities == "all" else QUANTITIES
    for seed in seeds:
        for r in measure(args.duration, seed, effects, args.parameter, size, fractions,
                         args.alpha, quantities):
            rows.append(r)
            print(f"{r['seed']:4d} {r['effect']:20s} {r['parameter']:8s} {r['fraction']:6.2g} "
                  f"{r['quantity']:20s} {r['printed']:11.3e} {r['odd']:11.3e} "
                  f"{r['odd'] / r['printed']:7.3f} {abs(r['printed']) / r['sigma']:11.2f} "
                  f"{r['share']:6.3f}", flush=True)
    if quantities is None:
        _by_share(rows)
    if len(seeds) > 1:
        print("\nover seeds (mean printed, mean odd ± its standard error, ratio of means)")
        for eid in effects:
            for f in fractions:
                for q in dict.fromkeys(r["quantity"] for r in rows):
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
