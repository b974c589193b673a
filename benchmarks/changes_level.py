"""Level of the 'sigma changes over the run' verdict on clean bags (issue 21).

The verdict (:func:`stellar_cal_ros.diagnosis.noise.changes_over_run`) compares the stars'
σ scale measured before the evaluation window with the window's: it fires when the two
differ significantly (two-sided, α = 1 % Bonferroni over the noise components tested) AND
their ratio exceeds :data:`~stellar_cal_ros.diagnosis.noise.CHANGES` (1.2).  On a clean bag
(noise as stated and stationary) it must fire on at most α of the bags.  For each clean
bag (the false-alarm benchmark's, :func:`~stellar_cal_ros.diagnosis.injection.clean_case`)
the current model is run once from the prior, as the diagnosis's first run, and the two
scales, their ratio, z and p are recorded; the table gives how often each condition and
both hold, and the spread of the ratio (how far 1.2 is from what noise does).

Run::

    .venv/bin/python benchmarks/changes_level.py --seeds 50               # 2 cases x 50
    .venv/bin/python benchmarks/changes_level.py --seeds 50 \
        --cases psce,psce+sky,swaying,swaying+sky
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
from scipy import stats as sps

from stellar_cal_ros.diagnosis import noise
from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
from stellar_cal_ros.diagnosis.injection import clean_case
from stellar_cal_ros.diagnosis.runstats import evaluate

#: the false-alarm benchmark's cases (benchmarks/false_alarms.py)
CASES = {"psce": ("psce", False, 300.0), "psce+sky": ("psce", True, 300.0),
         "swaying": ("swaying_base", False, 200.0),
         "swaying+sky": ("swaying_base", True, 200.0)}
#: noise components the diagnosis tests beside the stars (its Bonferroni count - 1)
COMPONENTS = {"psce": 1, "swaying_base": 2}


def measure(name: str, seed: int) -> dict[str, float]:
    """The two scales of one clean bag and the verdict's statistics."""
    method, sky, duration = CASES[name]
    data, prior, effects = clean_case(method, sky, seed, duration)
    spec = method_spec(method)
    run = evaluate(data, spec, rerun_prior(prior), tuple(spec.beyond_baseline(effects)), 0.5,
                   star_noise=True)
    sn = run.star_noise
    known = ~sn.unknown
    s, e, _ = sn.group(known)
    b = sn.before or {}
    n_tests = 1 + COMPONENTS[method]
    out = {"case": name, "seed": seed, "window": s, "sigma_window": e,
           "before": b.get("scale", math.nan), "sigma_before": b.get("sigma", math.nan),
           "structure_p": sn.structure_p, "repeat_removed": bool(sn.repeat_removed)}
    out["ratio"] = s / out["before"] if out["before"] > 0 else math.nan
    z = (s - out["before"]) / math.hypot(e, out["sigma_before"])
    out["p"] = float(2.0 * sps.norm.sf(abs(z))) if np.isfinite(z) else math.nan
    out["z"] = z
    out["significant"] = bool(out["p"] < noise.ALPHA / n_tests)
    out["material"] = bool(max(out["ratio"], 1.0 / out["ratio"]) > noise.CHANGES)
    out["fires"] = noise.changes_over_run(sn, s, e, 1.0, n_tests) is not None
    return out


def upper(k: int, n: int) -> float:
    """One-sided 95 % Clopper–Pearson upper bound of a rate k / n."""
    return 1.0 if k >= n else float(sps.beta.ppf(0.95, k + 1, n - k))


def main() -> int:
    """Run the seeds, print the level table; 0 on success."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--first-seed", type=int, default=2000)
    ap.add_argument("--cases", default="psce,swaying")
    ap.add_argument("-v", "--verbose", action="store_true")
    a = ap.parse_args()
    print(f"'changes over the run' on clean bags, seeds {a.first_seed}-"
          f"{a.first_seed + a.seeds - 1} (alpha {noise.ALPHA:g} / tests, ratio > "
          f"{noise.CHANGES:g}); count, one-sided 95 % upper bound")
    print(f"{'case':12s} {'n':>3s} {'p<a/k':>11s} {'ratio>1.2':>11s} {'fires':>11s} "
          f"{'ratio mean':>10s} {'sd':>6s} {'min':>6s} {'max':>6s} {'z sd':>5s} {'cpu s':>6s}")
    for name in a.cases.split(","):
        recs = []
        t0 = time.process_time()
        for seed in range(a.first_seed, a.first_seed + a.seeds):
            r = measure(name, seed)
            recs.append(r)
            if a.verbose:
                print(f"  {name} {seed}: before {r['before']:.4f} +- {r['sigma_before']:.4f}, "
                      f"window {r['window']:.4f} +- {r['sigma_window']:.4f}, ratio "
                      f"{r['ratio']:.4f}, z {r['z']:.2f}, p {r['p']:.3g}"
                      + (" FIRES" if r["fires"] else ""), flush=True)
        n = len(recs)
        ratio = np.array([r["ratio"] for r in recs])
        z = np.array([r["z"] for r in recs])
        cells = []
        for k in ("significant", "material", "fires"):
            c = sum(r[k] for r in recs)
            cells.append(f"{c:3d} (<{upper(c, n):5.1%})")
        print(f"{name:12s} {n:3d} " + " ".join(f"{c:>11s}" for c in cells)
              + f" {np.nanmean(ratio):10.4f} {np.nanstd(ratio):6.4f} {np.nanmin(ratio):6.3f} "
              f"{np.nanmax(ratio):6.3f} {np.nanstd(z):5.2f} "
              f"{(time.process_time() - t0) / n:6.1f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
