r"""Where the gyro noise scale's likelihood reads low on clean psce bags (issue 21 item 1).

The stars' check of the gyro noise (:func:`stellar_cal_ros.diagnosis.noise_imu.search_scale`)
maximises the window log-likelihood of re-runs over ln g.  Per seed a psce bag is simulated
and run at ln g = ln truth + (−0.8, −0.6, ..., 0.6) (no search: the same runs for every
variant), and printed: the maximum of the parabola through the best grid point and its
neighbours (minus ln truth), its curvature, z = maximum · sqrt(curvature), and the **score
at the truth** (the slope there of the parabola through the 5 grid points around it).  For a
likelihood that is the data's, the score at the truth has mean 0 whatever the bag's length;
a maximum that is low because the likelihood is flat on one side has a score of mean 0 and
a bias that shrinks as 1 / curvature.  Over seeds: means ± standard errors.

Variants (each changes one thing; the same seeds pair them): ``--at-truth`` starts from the
true calibration, ``--prior-scale K`` multiplies every prior σ (``--at-truth --prior-scale
0.01``: the calibration fixed at the truth), ``--static`` holds the pointing (no 30° steps),
``--gyro F`` simulates F x the stated gyro noise, ``--star-scale S`` runs with S x the
stars' stated σ, ``--cap C`` scores with the per-star NIS capped at C (default the
likelihood's own), ``--fractions`` the windows (the last fraction of the frames) scored from
the same runs, ``--duration`` the bag's length.

Run::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/imu_scale_bias.py --seeds 2000-2023
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time

import numpy as np

from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.diagnosis import stats
from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
from stellar_cal_ros.methods import star_model
from stellar_cal_ros.methods.replay import bag_data_from_simulation, method_runner
from stellar_cal_ros.methods.results import NIS_CAP
from stellar_cal_ros.sim.motion import StepRotations
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

#: the grid of ln g around ln truth
GRID = np.round(np.arange(-0.8, 0.61, 0.2), 3)


def _seeds(text: str) -> list[int]:
    a, _, b = text.partition("-")
    return list(range(int(a), int(b or a) + 1))


def bag(seed: int, duration: float, gyro: float, static: bool):
    """The simulation and its bag data (``static``: the pointing held, no steps)."""
    sc = get_scenario("psce_rotations")
    sc = dataclasses.replace(sc, gyro_arw_deg_sqrth=sc.gyro_arw_deg_sqrth * gyro)
    if static:  # (steps of 2″ there and back: the motion's slews need an angle)
        sc = dataclasses.replace(sc, motion_factory=lambda d: StepRotations(
            np.eye(3), [("x", 1e-5), ("x", -1e-5)], step_s=60.0, duration=d))
    sim = simulate(sc, duration=duration, seed=seed)
    return sim, bag_data_from_simulation(sim)


def start(sim, at_truth: bool):
    """The re-runs' prior: the bag's prior, or its values replaced by the truth."""
    prior = rerun_prior(sim.prior)
    if at_truth:
        prior._inst_q, prior._inst_rot = sim.truth._inst_q, None
        prior.gyro_bias = sim.truth.gyro_bias.copy()
        prior.camera = sim.truth.camera
    return prior


def scale_prior_sigma(k: float) -> None:
    """Every model's prior σ times ``k`` from now on (``--prior-scale``)."""
    if k == 1.0:
        return
    init = star_model.StarModel.__init__

    def scaled(self, *a, **kw):
        init(self, *a, **kw)
        self.initial_sigma = self.initial_sigma * k

    star_model.StarModel.__init__ = scaled


def fit(xs: np.ndarray, ll: np.ndarray, at: float) -> tuple[float, float, float]:
    """(maximum, curvature, score at ``at``) of ``ll`` over the grid ``xs``."""
    i = int(np.argmax(ll))
    lo = max(0, min(i - 1, len(xs) - 3))
    c = np.polyfit(xs[lo:lo + 3], ll[lo:lo + 3], 2)
    near = np.argsort(abs(xs - at))[:5]
    d = np.polyfit(xs[near] - at, ll[near], 2)
    return float(-c[1] / (2 * c[0])), float(-2 * c[0]), float(d[1])


def main() -> None:
    """Print each seed's maximum and score, then their means (the module's doc)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="2000-2023")
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--gyro", type=float, default=1.0, help="true gyro noise / stated")
    ap.add_argument("--star-scale", type=float, default=1.0)
    ap.add_argument("--prior-scale", type=float, default=1.0)
    ap.add_argument("--at-truth", action="store_true")
    ap.add_argument("--static", action="store_true")
    ap.add_argument("--cap", type=float, default=NIS_CAP)
    ap.add_argument("--fractions", default="0.5")
    args = ap.parse_args()
    fractions = [float(f) for f in args.fractions.split(",")]
    scale_prior_sigma(args.prior_scale)
    truth = math.log(args.gyro)
    xs = GRID + truth
    runner, spec = method_runner("psce"), method_spec("psce")
    rows: dict[float, list] = {f: [] for f in fractions}
    print("seed | fraction: max ln g − ln truth, curvature, z, score at truth")
    for seed in _seeds(args.seeds):
        t0 = time.process_time()
        sim, data = bag(seed, args.duration, args.gyro, args.static)
        prior = start(sim, args.at_truth)
        ll = np.zeros((len(fractions), len(xs)))
        for j, x in enumerate(xs):
            r = runner(data, prior, list(spec.beyond_baseline([])), keep_tables=True,
                       noise=NoiseScales(gyro=math.exp(x), star=args.star_scale))
            for i, f in enumerate(fractions):
                ll[i, j] = stats.log_likelihood(
                    r.residuals, stats.evaluation_mask(r.residuals, f), cap=args.cap)
        out = []
        for i, f in enumerate(fractions):
            m, c, s = fit(xs, ll[i], truth)
            rows[f].append((m - truth, c, s))
            out.append(f"{f}: {m - truth:+.3f}, {c:.1f}, {(m - truth) * math.sqrt(c):+.2f}, "
                       f"{s:+.2f}")
        print(f"{seed} | " + " | ".join(out) + f" ({time.process_time() - t0:.0f} CPU-s)",
              flush=True)
    for f, got in rows.items():
        if len(got) < 2:
            continue
        m, c, s = (np.array(v) for v in zip(*got, strict=True))
        z = m * np.sqrt(c)
        n = len(m)

        def se(v: np.ndarray, k: int = n) -> float:
            return float(v.std(ddof=1) / math.sqrt(k))

        print(f"fraction {f}, n {n}: ln g − ln truth {m.mean():+.3f} +- {se(m):.3f} "
              f"(median {np.median(m):+.3f}, g mean {np.exp(m).mean():.3f}); z {z.mean():+.2f}"
              f" +- {se(z):.2f}, SD {z.std(ddof=1):.2f}; score at truth {s.mean():+.2f} +- "
              f"{se(s):.2f} (Var / mean curvature {s.var(ddof=1) / c.mean():.2f})")


if __name__ == "__main__":
    main()
