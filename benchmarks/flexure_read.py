"""What the printed mount flexure reads against the truth, over seeds (issue 21 items 2-3).

The flexure the gravity field / remainder test prints is the least-squares fit ``c`` of the
innovations on the probe's response ``S`` (:func:`~stellar_cal_ros.diagnosis.flexure.
remainder_statistics`).  For each seed: the bag with a flexure of ``--size`` ″/g and the
same seed's bag without it (paired: the same noise, ``injection.clean_simulation``), the
model (``--effects``, from the simulation's prior) run on both and on the flexed bag with
the probe.  Prints ``c`` ± its printed σ (the frame-robust σ ``t`` is made of; the
whitened ``1/√info`` printed until 2026-11-28 beside it), t, ν, the **response**
(the two bags' innovation difference -- the flexure's own response, noise-free -- fitted
on ``S``: the truth when the probe reads the flexure right) and the **noise part** (the
clean bag's innovations fitted on the same ``S``; ``c`` = response + noise part, the fit
being linear).  The **non-linear rest**: the response's whitened sum of squares off
``S`` (what the probe's linear pattern does not hold; its share of the response's), which a
library effect can take up beyond the gravity field.  The summary: mean ``c``/truth ± its
standard error over the seeds, the mean response/truth, the noise parts' mean ± SE and
their SD against the printed and the whitened σ, and the **frames' variance factors**: the
clean bag's innovations' scores on ``S`` summed per frame, ``U_k = Σ x_i ν_i`` (whitened),
``Σ_k U_k² / info`` (1 for stars independent within a frame: the share the stars' shared
error adds) and ``Σ_{|k−j| ≤ 14} U_k U_j / info`` (the frames' covariance up to the sway's
~14-frame period), means ± SE over the seeds: the estimate's variance over ``1/info``.
``--size 0``: the null alone (the clean bag and its probe run; ``c`` is the noise part;
also the SD of t with a HAC window of 14 frames).

Run::

    .venv/bin/python benchmarks/flexure_read.py --method swaying_base --size 10 \
        --duration 200 --seeds 21-30
    .venv/bin/python benchmarks/flexure_read.py --method swaying_base --size 0 \
        --duration 200 --seeds 1-30
    .venv/bin/python benchmarks/flexure_read.py --method psce --size 40 --duration 200 \
        --seeds 52-55
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.diagnosis import flexure, stats
from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
from stellar_cal_ros.diagnosis.injection import clean_simulation
from stellar_cal_ros.diagnosis.runstats import evaluate
from stellar_cal_ros.methods.replay import bag_data_from_simulation

FRACTION = 0.5


def _window(res: dict) -> dict:
    keep = stats.evaluation_mask(res, FRACTION)
    return {k: np.asarray(v)[keep] for k, v in res.items()}


#: the frames' covariance window of the variance factor (the sway's period, frames at 2 Hz)
SWAY_FRAMES = 14


def _whitened_scores(own: dict, du: np.ndarray, dv: np.ndarray, S: np.ndarray):
    """``(x, y, frame)``: the response ``S`` and the innovations ``du, dv``, whitened."""
    cov = {k: own[k] for k in ("s_uu", "s_uv", "s_vv")}
    y = stats.whitened(dict(cov, du=du, dv=dv))
    x = stats.whitened(dict(cov, du=S[:, 0], dv=S[:, 1]))
    ok = np.all(np.isfinite(x), 1) & np.all(np.isfinite(y), 1)
    return x[ok].ravel(), y[ok].ravel(), np.repeat(np.asarray(own["frame"])[ok], 2)


def variance_factors(x: np.ndarray, y: np.ndarray, frame: np.ndarray) -> tuple[float, float]:
    """``Σ_k U_k² / info`` and ``Σ_{|k−j| ≤ SWAY_FRAMES} U_k U_j / info`` at the truth 0."""
    _, k = np.unique(frame, return_inverse=True)
    U = np.bincount(k, x * y)
    info = float(x @ x)
    near = float(U @ U) + 2.0 * sum(float(U[lag:] @ U[:-lag])
                                    for lag in range(1, min(SWAY_FRAMES, len(U) - 1) + 1))
    return float(U @ U) / info, near / info


def seed_row(method: str, seed: int, duration: float, size: float,
             effects: tuple[str, ...]) -> dict:
    """One seed: the printed fit on the flexed bag, its response part and noise part."""
    spec = method_spec(method)
    bags = {}
    for s in ((0.0, size) if size else (0.0,)):
        sim, _ = clean_simulation(method, False, seed, duration,
                                  {"mount_flexure": s} if s else None)
        data, prior = bag_data_from_simulation(sim), rerun_prior(sim.prior, list(effects))
        bags[s] = (data, prior, evaluate(data, spec, prior, effects, FRACTION,
                                         keep_residuals=True).residuals)
    data, prior, res = bags[size]
    moved = flexure.measure_on_bag(data, spec, prior, effects, FRACTION)
    got = flexure.remainder_statistics(res, moved, FRACTION)
    row = {"seed": seed, "c": got["arcsec_per_g"], "sigma": got["sigma_arcsec_per_g"],
           "whitened": got["whitened_sigma_arcsec_per_g"], "t": got["t"], "nu": got["nu"],
           "response": 0.0, "noise": got["arcsec_per_g"], "rest": 0.0, "rest_share": 0.0}
    if not size:
        own, probe = flexure._aligned(_window(res), moved)
        m = stats.accepted(own) & stats.accepted(probe)
        own = {k: v[m] for k, v in own.items()}
        S = np.stack([probe[k][m] - own[k] for k in ("du", "dv")], 1) / (
            flexure.PROBE / ARCSEC)
        x, y, frame = _whitened_scores(own, own["du"], own["dv"], S)
        row["t_window"] = stats.frame_robust_t(x, y, frame, lags=SWAY_FRAMES)[0]
    if size:
        flexed, clean = flexure._aligned(_window(res), _window(bags[0.0][2]))
        flexed, probe = flexure._aligned(flexed, moved)
        clean, _ = flexure._aligned(clean, probe)
        m = stats.accepted(flexed) & stats.accepted(probe) & stats.accepted(clean)
        S = np.stack([probe[k][m] - flexed[k][m] for k in ("du", "dv")], 1) / (
            flexure.PROBE / ARCSEC)
        own = {k: v[m] for k, v in flexed.items()}
        D = np.stack([flexed[k][m] - clean[k][m] for k in ("du", "dv")], 1)
        row["response"] = stats.whitened_fit(dict(own, du=D[:, 0], dv=D[:, 1]), S)[2]
        # the response's part the probe's linear pattern does not hold (second order in
        # the size when the filter is not linear at it): its whitened sum of squares
        rest = D - row["response"] * S
        w_d = stats.whitened(dict(own, du=D[:, 0], dv=D[:, 1]))
        w_r = stats.whitened(dict(own, du=rest[:, 0], dv=rest[:, 1]))
        ok = np.all(np.isfinite(w_r), 1) & np.all(np.isfinite(w_d), 1)
        row["rest"], row["rest_share"] = (float(np.sum(w_r[ok] ** 2)),
                                          float(np.sum(w_r[ok] ** 2) / np.sum(w_d[ok] ** 2)))
        row["noise"] = stats.whitened_fit(dict(own, du=clean["du"][m], dv=clean["dv"][m]),
                                          S)[2]
        x, y, frame = _whitened_scores(own, clean["du"][m], clean["dv"][m], S)
    row["frame_factor"], row["sway_factor"] = variance_factors(x, y, frame)
    return row


def _seeds(text: str) -> list[int]:
    lo, _, hi = text.partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


def main() -> int:
    """Print the per-seed table and the summary."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--method", default="swaying_base", choices=("psce", "swaying_base"))
    ap.add_argument("--size", type=float, default=10.0, help="flexure, arcsec/g (0: null)")
    ap.add_argument("--duration", type=float, default=200.0)
    ap.add_argument("--seeds", default="21-30", help="FIRST-LAST")
    ap.add_argument("--effects", default="", help="the model's extra effects, comma-separated")
    args = ap.parse_args()
    effects = tuple(e for e in args.effects.split(",") if e)
    print(f"{args.method} {args.duration:g} s, mount_flexure {args.size:g}\"/g, model "
          f"{'+'.join(effects) or 'baseline'}, seeds {args.seeds}")
    print("| seed | c \"/g | printed sigma | whitened sigma | t | nu | response | noise part "
          "| non-linear rest (share) | CPU-s |\n|---|---|---|---|---|---|---|---|---|---|")
    rows = []
    for seed in _seeds(args.seeds):
        t0 = time.process_time()
        r = seed_row(args.method, seed, args.duration, args.size, effects)
        rows.append(r)
        print(f"| {seed} | {r['c']:.3f} | {r['sigma']:.3f} | {r['whitened']:.3f} | "
              f"{r['t']:.2f} | {r['nu']:.0f} | {r['response']:.3f} | {r['noise']:.3f} | "
              f"{r['rest']:.1f} ({r['rest_share']:.2e}) | {time.process_time() - t0:.0f} |",
              flush=True)
    n = len(rows)
    c, noise = np.array([r["c"] for r in rows]), np.array([r["noise"] for r in rows])
    se = (lambda x: x.std(ddof=1) / np.sqrt(n)) if n > 1 else (lambda x: np.nan)
    if args.size:
        resp = np.array([r["response"] for r in rows])
        print(f"mean c / truth {c.mean() / args.size:.3f} +- {se(c) / args.size:.3f} "
              f"(SE over {n} seeds); response / truth {resp.mean() / args.size:.4f} "
              f"({resp.min() / args.size:.4f}..{resp.max() / args.size:.4f})")
    sd = noise.std(ddof=1) if n > 1 else np.nan
    print(f"noise part: mean {noise.mean():.3f} +- {se(noise):.3f}\"/g, SD over the seeds "
          f"{sd:.3f} +- {sd / np.sqrt(2 * max(n - 1, 1)):.3f} against the printed sigma "
          f"{np.mean([r['sigma'] for r in rows]):.3f} (mean; the whitened "
          f"{np.mean([r['whitened'] for r in rows]):.3f})"
          + ("" if args.size or n < 2 else
             f"; SD of t {np.std([r['t'] for r in rows], ddof=1):.3f} (t_nu's "
             f"{np.sqrt(np.mean([r['nu'] / (r['nu'] - 2) for r in rows])):.3f}), |t| > 3 on "
             f"{sum(abs(r['t']) > 3 for r in rows)}; with a HAC window of {SWAY_FRAMES} "
             f"frames {np.std([r['t_window'] for r in rows], ddof=1):.3f}"))
    for key, what in (("frame_factor", "within a frame"),
                      ("sway_factor", f"frames up to {SWAY_FRAMES} apart")):
        v = np.array([r[key] for r in rows])
        print(f"variance factor, {what}: {v.mean():.3f} +- {se(v):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
