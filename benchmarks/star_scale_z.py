r"""Whether the stars' printed scale ``s +- sigma`` is honest on clean bags (issue 21).

The verdict's "noise as stated" line prints the stars' σ scale ``s ± σ`` measured within
the frames of the evaluation window (:func:`stellar_cal_ros.diagnosis.noise.measure_stars`,
:meth:`~stellar_cal_ros.diagnosis.noise_stars.StarNoise.group` over the stars of known σ);
the 'changes over the run' line adds the same estimate on the stretch before the window.
On a clean bag the truth is 1, so ``z = (s − 1) / σ`` must have mean 0 and SD 1 over
seeds.  Per clean bag (the false-alarm benchmark's,
:func:`~stellar_cal_ros.diagnosis.injection.clean_case`) the current model is run once from
the prior, as the diagnosis's first run, and three estimates are made on its residual
table:

* ``bag``: the run's own innovations (what the verdict prints);
* ``drawn``: the same rows with the simulator's centroid noise alone in place of the
  innovations (the bag simulated again with ``centroid_noise_px`` 0 and the same seed: the
  draws are the same, so their difference is the noise; ``--paired``).  ``bag − drawn``
  is what the filter's own estimation adds (its prediction errors, its gain);
* ``iid``: ``--iid K`` fresh iid draws N(0, σ²) on the same rows (the estimator alone on
  this bag's geometry, no filter, no simulator).

The table gives, per case and estimate, z's mean and SD with their standard errors
(``SD/√n`` and ``SD/√(2(n−1))``), the rms printed σ against the SD of ``s``, and for the
window before (``before``) the same.  The cases with the sky effects are not independent
of those without (same seed, same centroid draws: the window's ``s`` correlates 0.9994),
so they add no seeds.

Run::

    .venv/bin/python benchmarks/star_scale_z.py --seeds 1000-1099 --cases psce,swaying
    .venv/bin/python benchmarks/star_scale_z.py --seeds 2000-2009 --cases psce --paired --iid 100
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time

import numpy as np

from stellar_cal_ros.diagnosis import noise
from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
from stellar_cal_ros.diagnosis.injection import SCENARIO, SKY, SWAY_CLEAN
from stellar_cal_ros.diagnosis.runstats import quiet
from stellar_cal_ros.methods.replay import bag_data_from_simulation
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

#: the false-alarm benchmark's cases (benchmarks/false_alarms.py)
CASES = {"psce": ("psce", False, 300.0), "psce+sky": ("psce", True, 300.0),
         "swaying": ("swaying_base", False, 200.0),
         "swaying+sky": ("swaying_base", True, 200.0)}


def _simulate(method: str, sky: bool, seed: int, duration: float, noise_px: float | None):
    eff = dict(SWAY_CLEAN) if method == "swaying_base" else {}
    if sky:
        eff.update(SKY)
    sc = get_scenario(SCENARIO[method])
    if noise_px is not None:
        sc = dataclasses.replace(sc, centroid_noise_px=noise_px)
    return simulate(sc, duration=duration, seed=seed, effects=eff)


def _drawn_noise(sim, method, sky, seed, duration, res) -> np.ndarray:
    """The simulator's centroid noise of each residual row.

    NaN where the star is not in the noise-free bag (its noise moved it across the
    detector's edge).
    """
    sim0 = _simulate(method, sky, seed, duration, 0.0)
    nz: dict[tuple[int, int], np.ndarray] = {}
    for f, f0 in zip(sim.star_frames, sim0.star_frames, strict=True):
        us = int(round(int(f.stamp_ns) / 1000))
        clean = {int(c): f0.uv[i] for i, c in enumerate(np.asarray(f0.catalog_id).tolist())}
        for i, c in enumerate(np.asarray(f.catalog_id).tolist()):
            nz[(us, int(c))] = f.uv[i] - clean.get(int(c), np.full(2, np.nan))
    t_us = np.round(np.asarray(res["t"], dtype=float) * 1e6).astype(np.int64)
    return np.array([nz[(int(t), int(c))] for t, c in zip(t_us, res["catalog_id"],
                                                          strict=True)]).reshape(-1, 2)


def _estimate(result, data, method: str, res) -> tuple[float, float, float, float]:
    """(window s, σ, before s, σ) of the residual table ``res``."""
    result.residuals = res
    sn = noise.measure_stars(result, data, method, 0.5, None)
    if sn is None:
        return (math.nan,) * 4
    s, e, _ = sn.group(~sn.unknown)
    b = sn.before or {}
    return s, e, b.get("scale", math.nan), b.get("sigma", math.nan)


def measure(name: str, seed: int, paired: bool, iid: int) -> dict[str, list]:
    """The estimates of one clean bag: {estimate: [(s, σ, s_before, σ_before), ...]}."""
    method, sky, duration = CASES[name]
    sim = _simulate(method, sky, seed, duration, None)
    data = bag_data_from_simulation(sim)
    spec = method_spec(method)
    with quiet():
        result = spec.runner(data, rerun_prior(sim.prior),
                             list(spec.beyond_baseline(list(SKY) if sky else [])),
                             keep_tables=True, eval_fraction=0.5)
    res0 = dict(result.residuals)
    out = {"bag": [_estimate(result, data, method, dict(res0))]}
    if paired:
        n = _drawn_noise(sim, method, sky, seed, duration, res0)
        res = dict(res0, du=n[:, 0], dv=n[:, 1],
                   gated=np.asarray(res0["gated"]).astype(bool) | ~np.isfinite(n[:, 0]))
        out["drawn"] = [_estimate(result, data, method, res)]
    if iid:
        rng = np.random.default_rng(seed)
        sig = float(np.median(np.concatenate([f.sigma for f in data.frames])))
        m = len(res0["du"])
        out["iid"] = [_estimate(result, data, method,
                                dict(res0, du=sig * rng.standard_normal(m),
                                     dv=sig * rng.standard_normal(m),
                                     gated=np.zeros(m, dtype=bool))) for _ in range(iid)]
    return out


def _row(label: str, v: np.ndarray) -> str:
    """The table row: z's mean ± SE and SD ± SE, the SD of s and the rms printed σ."""
    ok = np.all(np.isfinite(v), axis=1)
    s, e = v[ok, 0], v[ok, 1]
    n = len(s)
    if n < 3:
        return f"{label:22s} {n:4d}"
    z = (s - 1.0) / e
    sd = float(np.std(z, ddof=1))
    return (f"{label:22s} {n:4d} {np.mean(z):+7.3f} +- {sd / math.sqrt(n):5.3f} "
            f"{sd:6.3f} +- {sd / math.sqrt(2 * (n - 1)):5.3f} {np.mean(s):8.5f} "
            f"{np.std(s, ddof=1):8.5f} {math.sqrt(np.mean(e**2)):8.5f}")


def main() -> int:
    """Measure the cases and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="1000-1049", help="a-b (inclusive)")
    ap.add_argument("--cases", default="psce,swaying")
    ap.add_argument("--paired", action="store_true",
                    help="also the simulator's drawn noise alone (the bag simulated again "
                         "without centroid noise)")
    ap.add_argument("--iid", type=int, default=0, help="fresh iid draws per bag")
    ap.add_argument("-v", "--verbose", action="store_true")
    a = ap.parse_args()
    lo, hi = (int(x) for x in a.seeds.split("-"))
    print(f"the stars' scale s +- sigma on clean bags, seeds {lo}-{hi}: z = (s - 1) / sigma "
          "(mean +- SE, SD +- SE), s mean and SD, rms printed sigma")
    print(f"{'case / estimate':22s} {'n':>4s} {'z mean':>16s} {'z SD':>15s} {'s mean':>8s} "
          f"{'s SD':>8s} {'sigma':>8s}")
    for name in a.cases.split(","):
        got: dict[str, list] = {}
        t0 = time.process_time()
        for seed in range(lo, hi + 1):
            m = measure(name, seed, a.paired, a.iid)
            for k, v in m.items():
                got.setdefault(k, []).extend(v)
            if a.verbose:
                print(f"  {name} {seed}: " + ", ".join(
                    f"{k} {v[0][0]:.5f} +- {v[0][1]:.5f} (before {v[0][2]:.5f} +- "
                    f"{v[0][3]:.5f})" for k, v in m.items()), flush=True)
        for k, v in got.items():
            arr = np.array(v, dtype=float)
            print(_row(f"{name} {k}", arr[:, :2]))
            print(_row(f"{name} {k} before", arr[:, 2:]))
        print(f"  ({(time.process_time() - t0) / (hi - lo + 1):.1f} CPU-s a bag)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
