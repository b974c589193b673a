r"""Where the gyro scale's log-likelihood gets its extra score variance (issue 21).

The stars' window log-likelihood the IMU noise search maximises
(:func:`stellar_cal_ros.diagnosis.noise_imu.search_scale`) varies over seeds more than its
curvature says.  Per seed a psce bag (200 s) with ``--gyro`` x the stated gyro random walk
(its samples smoothed [1 2 1] / 4 unless ``--white``) is run at the truth ln s and ± ``--h``;
each window frame's terms (:meth:`~stellar_cal_ros.methods.results.RunStats.
frame_log_likelihood`, the runs in :func:`~stellar_cal_ros.methods.results.keeping_frames`)
give its score (central difference) and the sum's curvature J.
Printed per seed: the score U at the truth, J, and Var(U) / J estimated within the run
four ways — the stars as independent (each star's own score), the frames as independent,
Newey-West over 20 frames, batch means over 10 blocks — then over seeds the mean of each
against Var(U) over seeds / mean J (the truth of what the within-run estimates estimate),
and the frames' scores' mean autocorrelation at lags 1-10 and its sum over lags 1-30.

Run::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/imu_score_frames.py --seeds 3-42
"""

from __future__ import annotations

import argparse
import math

import numpy as np
from imu_search_spread import gyro_bag  # this directory: the benchmark's bag

from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.diagnosis.discover import method_spec
from stellar_cal_ros.methods.results import LOGDET_WEIGHT, NIS_CAP, keeping_frames

LAGS = 30


def _stars(r) -> np.ndarray:
    """Each window star's log-likelihood term (a gated star: at the cap, its own det 1).

    log det S weighted as the run's (:data:`~stellar_cal_ros.methods.results.LOGDET_WEIGHT`).
    """
    res = r.residuals
    win = res["t"] >= r.stats.eval_start
    ok = ~res["gated"].astype(bool)[win]
    a, b, d = (res[k][win] for k in ("s_uu", "s_uv", "s_vv"))
    nis = np.where(ok, np.minimum(res["nis"][win], NIS_CAP), NIS_CAP)
    return -0.5 * (nis + LOGDET_WEIGHT * np.log(np.where(ok, a * d - b * b, 1.0)))


def _newey_west(s: np.ndarray, lags: int) -> float:
    c = s - s.mean()
    v = float(c @ c)
    for k in range(1, lags + 1):
        v += 2 * (1 - k / (lags + 1)) * float(c[k:] @ c[:-k])
    return v


def _batch_means(s: np.ndarray, blocks: int) -> float:
    edges = np.linspace(0, len(s), blocks + 1).astype(int)
    sums = np.array([s[a:b].sum() for a, b in zip(edges[:-1], edges[1:], strict=True)])
    return float(blocks / (blocks - 1) * np.sum((sums - sums.mean()) ** 2))


def main() -> None:
    """Print each seed's score and the within-run estimates of its variance (the doc)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="3-42")
    ap.add_argument("--gyro", type=float, default=5.0, help="true gyro noise / stated")
    ap.add_argument("--h", type=float, default=0.2, help="ln s step of the differences")
    ap.add_argument("--white", action="store_true", help="do not smooth the gyro samples")
    args = ap.parse_args()
    a, _, b = args.seeds.partition("-")
    t = math.log(args.gyro)
    spec = method_spec("psce")
    names = ("star-iid", "frame-iid", "NW 20", "BM 10")
    rows, acf = [], np.zeros(LAGS + 1)
    print("seed | U at truth | J | " + " | ".join(f"{n} / J" for n in names))
    for seed in range(int(a), int(b or a) + 1):
        sim, data = gyro_bag(seed, args.gyro, white=args.white)
        with keeping_frames():
            runs = [spec.runner(data, sim.prior, [], keep_tables=True, eval_fraction=0.5,
                                noise=NoiseScales(gyro=math.exp(x)), gyro_fault="off")
                    for x in (t - args.h, t, t + args.h)]
        fl = [r.stats.frame_log_likelihood() for r in runs]
        if not all(np.array_equal(f[0], fl[0][0]) for f in fl):
            print(f"{seed} | the runs' window frames differ: skipped")
            continue
        score = (fl[2][1] - fl[0][1]) / (2 * args.h)
        curv = float(-np.sum(fl[2][1] - 2 * fl[1][1] + fl[0][1]) / args.h**2)
        lo, hi = _stars(runs[0]), _stars(runs[2])
        star = (hi - lo) / (2 * args.h) if len(hi) == len(lo) else np.full(1, np.nan)
        c = score - score.mean()
        acf += np.array([float(c[k:] @ c[:len(c) - k]) / float(c @ c) for k in range(LAGS + 1)])
        est = (float(np.sum((star - star.mean()) ** 2)), float(c @ c),
               _newey_west(score, 20), _batch_means(score, 10))
        rows.append((float(score.sum()), curv, *(e / curv for e in est)))
        print(f"{seed} | {rows[-1][0]:+.2f} | {curv:.1f} | "
              + " | ".join(f"{e:.2f}" for e in rows[-1][2:]), flush=True)
    n = len(rows)
    if n < 2:
        return
    v = np.array(rows)
    ratio = v[:, 0].var(ddof=1) / v[:, 1].mean()
    print(f"n {n}: Var(U) over seeds / mean J {ratio:.2f} +- {ratio * math.sqrt(2 / (n - 1)):.2f}"
          f" (mean U {v[:, 0].mean():+.2f} +- {v[:, 0].std(ddof=1) / math.sqrt(n):.2f}); "
          "within the run, mean (SD over seeds): "
          + ", ".join(f"{nm} {v[:, 2 + i].mean():.2f} ({v[:, 2 + i].std(ddof=1):.2f})"
                      for i, nm in enumerate(names)))
    acf /= n
    print("frames' scores, mean autocorrelation at lags 1-10: "
          + " ".join(f"{x:+.3f}" for x in acf[1:11])
          + f"; sum over lags 1-{LAGS} {acf[1:].sum():+.3f} (1 / sqrt(frames) "
          f"{1 / math.sqrt(len(score)):.3f})")


if __name__ == "__main__":
    main()
