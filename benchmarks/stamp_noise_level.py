"""The stamp-noise test and the repeating-field test on clean bags: their level (issue 21).

On each clean bag (:func:`~stellar_cal_ros.diagnosis.injection.clean_case`, the false-alarm
benchmark's bags: both methods, with and without the sky) the current model is run once
with the stated noise (as the diagnosis's noise measurement runs it), and two tests are
read from it:

* the stamp-noise test (:func:`~stellar_cal_ros.diagnosis.stats.motion_spread`): the
  stars' spread along their image motion from frame to frame against the same across it,
  its unadjusted one-sided p (an 'unexplained' line needs it below ~α / 45, Bonferroni
  over the family);
* the noise verdict's repeating field (the detector cells' means, ``StarNoise.structure``
  against its χ², :func:`~stellar_cal_ros.diagnosis.noise.structured`), printed at p < 1 %.

Each is printed with its count below 5 % and 1 % per case, the z of the cells' χ² ((χ² −
dof) / √(2 dof)), and with ``--jitter S`` the stamp noise (s) the test reads on bags with
that jitter (``sim.tracker_errors.stamp_jitter``; then the bags are not clean).

Run::

    .venv/bin/python benchmarks/stamp_noise_level.py --seeds 50 --records lvl.jsonl
    .venv/bin/python benchmarks/stamp_noise_level.py --seeds 5 --first-seed 21 --cases psce \
        --jitter 1e-3
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from stellar_cal_ros.diagnosis import stats
from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
from stellar_cal_ros.diagnosis.injection import clean_simulation
from stellar_cal_ros.diagnosis.runstats import evaluate
from stellar_cal_ros.methods.replay import bag_data_from_simulation
from stellar_cal_ros.sim import tracker_errors

CASES = {"psce": ("psce", False, 300.0), "psce+sky": ("psce", True, 300.0),
         "swaying": ("swaying_base", False, 200.0),
         "swaying+sky": ("swaying_base", True, 200.0)}


def one_bag(name: str, seed: int, jitter: float = 0.0) -> dict:
    """The two tests on one bag's current-model run (the record written per seed)."""
    method, sky, duration = CASES[name]
    t0 = time.process_time()
    sim, effects = clean_simulation(method, sky, seed, duration)
    if jitter:
        tracker_errors.stamp_jitter(sim, jitter, seed)
    data = bag_data_from_simulation(sim)
    spec = method_spec(method)
    start = rerun_prior(sim.prior) if sim.prior.method != "prior" else sim.prior
    run = evaluate(data, spec, start, tuple(spec.beyond_baseline(effects)), 0.5,
                   keep_residuals=True, star_noise=True)
    res, cam = run.residuals, start.camera
    m = stats.evaluation_mask(res, 0.5) & stats.accepted(res)
    sub = {k: np.asarray(v)[m] for k, v in res.items()}
    f = stats.motion_spread(sub, (cam.fx, cam.fy), (cam.cx, cam.cy), start.R_imu_st)
    sn = run.star_noise
    rec = {"case": name, "seed": seed, "jitter": jitter}
    if f is not None:
        rec.update(p_motion=f.p_value, motion=f.regressor, motion_px=f.slope_px)
    if sn is not None:
        rec.update(cells_chi2=sn.structure, cells_dof=sn.structure_dof, p_cells=sn.structure_p)
    rec["cpu"] = time.process_time() - t0
    return rec


def table(records: list[dict]) -> list[str]:
    """Per case: the bags, each test's count below 5 % and 1 %, the cells' z."""
    out = ["| case | bags | stamp noise p < 5 % | < 1 % | < 2e-4 | min p | cells p < 5 % "
           "| < 1 % | cells z mean | z sd | z max |", "|---" * 11 + "|"]
    for name in CASES:
        rs = [r for r in records if r["case"] == name and "p_motion" in r]
        if not rs:
            continue
        p = np.array([r["p_motion"] for r in rs])
        pc = np.array([r["p_cells"] for r in rs])
        z = np.array([(r["cells_chi2"] - r["cells_dof"]) / np.sqrt(2.0 * r["cells_dof"])
                      for r in rs])
        out.append(f"| {name} | {len(rs)} | {(p < 0.05).sum()} | {(p < 0.01).sum()} | "
                   f"{(p < 2e-4).sum()} | {p.min():.3g} | {(pc < 0.05).sum()} | "
                   f"{(pc < 0.01).sum()} | {z.mean():.2f} | {z.std():.2f} | {z.max():.2f} |")
    return out


def main() -> int:
    """Run the bags (resumable with ``--records``) and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--first-seed", type=int, default=2000)
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--jitter", type=float, default=0.0, help="stamp noise, s (0: clean)")
    ap.add_argument("--records", type=Path, default=None, help="JSON lines, one per bag")
    args = ap.parse_args()
    done = {}
    if args.records is not None and args.records.exists():
        for line in args.records.read_text().splitlines():
            if line.strip():
                r = json.loads(line)
                done[(r["case"], r["seed"], r.get("jitter", 0.0))] = r
    records = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        for name in args.cases.split(","):
            key = (name, seed, args.jitter)
            if key not in done:
                done[key] = one_bag(name, seed, args.jitter)
                print(json.dumps(done[key], default=float), flush=True)
                if args.records is not None:
                    with args.records.open("a") as fh:
                        fh.write(json.dumps(done[key], default=float) + "\n")
            records.append(done[key])
    print("\n".join(table(records)))
    if args.jitter:
        for r in records:
            print(f"{r['case']} seed {r['seed']}: {r.get('motion', '-')} p {r.get('p_motion')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
