r"""Which part of the PSCE filter's likelihood reads the gyro scale low after the slews.

Follows :mod:`imu_scale_bias` (issue 21 item 1): per seed a clean psce bag is run on the
numpy path at ln g = −0.1, 0, +0.1 (the stated gyro ARW times g), every star update
recorded: the frame's innovations ``ν``, Jacobian ``H``, prior covariance ``P`` and σ.  Per
frame, per tracker axis (x, y cross-boresight, z roll):

* the stars' generalized-least-squares pointing ``d = L ν``, ``L = (Hₐᵀ R⁻¹ Hₐ)⁻¹ Hₐᵀ R⁻¹``
  (``Hₐ`` the attitude columns), its measurement share ``M = (Hₐᵀ R⁻¹ Hₐ)⁻¹`` and the state's
  share ``C = L H P Hᵀ Lᵀ`` (diagonals in the tracker axes);
* the same ``L`` applied to the noise-free innovation (the simulator's stars at the truth
  minus the filter's prediction): the pointing error against the truth, whose NEES on ``C``
  is 1 for a filter whose covariance is right;
* the frame's joint log-likelihood ``−½ (νᵀ S⁻¹ ν + ln |S|)``, ``S = H P Hᵀ + R``.

The score at the truth (central difference over the three runs) is split per axis into the
covariance term ``½ ∂C/S (d²/S − 1)`` and the innovation term ``−d ∂d / S`` (``S = C + M``):
both have mean 0 when the model is the data's.  Per window: means ± standard errors over
seeds.  ``--at-truth --prior-scale K`` as in :mod:`imu_scale_bias`; ``--quiet`` simulates
1e-3 x the gyro and centroid noise (stars keep their stated σ): the filter's deterministic
error.

Run::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/imu_scale_nees.py --seeds 2000-2023
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import runpy
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.diagnosis.discover import method_spec
from stellar_cal_ros.methods import kernel
from stellar_cal_ros.methods.replay import bag_data_from_simulation, replay
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

#: the bags, the prior at the truth and the prior σ scale of :mod:`imu_scale_bias`
BIAS = SimpleNamespace(**runpy.run_path(str(Path(__file__).resolve().parent
                                         / "imu_scale_bias.py")))
#: ln g of the three runs
STEPS = (-0.1, 0.0, 0.1)
WINDOWS = ((10, 60), (70, 240), (150, 300), (250, 300))


def frame_row(flt, uv, u_i, ctx, sigma, world) -> list[float]:
    """(d, C, M, pointing error against the truth) per tracker axis and the joint ℓ."""
    pred = flt._predict(flt.theta.copy(), u_i, ctx)
    H0, _ = flt._star_jacobian(pred)
    nu, H = (uv - pred.uv).reshape(-1), H0.reshape(-1, flt.N)
    r = np.repeat(sigma ** 2, 2)
    Ha = H[:, :3]
    M = np.linalg.inv(Ha.T @ (Ha / r[:, None]))
    L = M @ (Ha.T / r)
    HPH = H @ flt.P @ H.T
    A = flt.R_i_b @ flt.model.prior.R_imu_st  # tracker axes (columns), inertial
    true = world.model.predict(world.theta, u_i, ctx, world.attitude_near(flt._stamp_rel),
                               jacobians=False)
    S = HPH + np.diag(r)
    logdet = np.linalg.slogdet(S)[1]
    joint = -0.5 * (nu @ np.linalg.solve(S, nu) + logdet + len(nu) * math.log(2 * math.pi))
    return [*(A.T @ (L @ nu)), *np.diag(A.T @ L @ HPH @ L.T @ A), *np.diag(A.T @ M @ A),
            *(A.T @ (L @ (true.uv - pred.uv).reshape(-1))), joint]


def runs(seed: int, args) -> np.ndarray:
    """(3 runs, frames, 1 + 13): t and :func:`frame_row` of every star update."""
    if args.quiet:
        sc = get_scenario("psce_rotations")
        stated = sc.centroid_noise_px
        sc = dataclasses.replace(sc, gyro_arw_deg_sqrth=sc.gyro_arw_deg_sqrth * 1e-3,
                                 centroid_noise_px=stated * 1e-3)
        sim = simulate(sc, duration=args.duration, seed=seed)
        for fr in sim.star_frames:
            fr.sigma[:] = stated
        data = bag_data_from_simulation(sim)
    else:
        sim, data = BIAS.bag(seed, args.duration, 1.0, False)
    prior = BIAS.start(sim, args.at_truth)
    rec: list[list[float]] = []
    star_update = kernel.StarFilter._star_update

    def recording(self, uv, u_i, ctx, sigma, t_exp):
        rec.append([t_exp, *frame_row(self, uv, u_i, ctx, sigma, sim.truth_world)])
        return star_update(self, uv, u_i, ctx, sigma, t_exp)

    effects = list(method_spec("psce").beyond_baseline([]))
    out = []
    kernel.StarFilter._star_update = recording
    kernel.StarFilter.compiled_step = False  # (the numpy update: the method above)
    try:
        for x in STEPS:
            rec.clear()
            replay(data, prior, "psce", effects, noise=NoiseScales(gyro=math.exp(x)))
            out.append(np.array(rec))
    finally:
        kernel.StarFilter._star_update = star_update
        kernel.StarFilter.compiled_step = True
    if len({len(o) for o in out}) != 1:
        raise SystemExit(f"seed {seed}: the runs updated different frames")
    return np.stack(out)


def per_window(r: np.ndarray) -> dict:
    """Per window: joint score, covariance and innovation terms per axis, NEES per axis."""
    h = STEPS[2] - STEPS[1]
    t = r[1, :, 0]
    d, C, M, e = r[1, :, 1:4], r[1, :, 4:7], r[1, :, 7:10], r[1, :, 10:13]
    dd = (r[2, :, 1:4] - r[0, :, 1:4]) / (2 * h)
    dC = (r[2, :, 4:7] - r[0, :, 4:7]) / (2 * h)
    S = C + M
    cov_term = 0.5 * dC / S * (d ** 2 / S - 1.0)
    inn_term = -d * dd / S
    out = {}
    for lo, hi in WINDOWS:
        k = (t >= lo) & (t < hi)
        out[(lo, hi)] = np.concatenate([
            [(r[2, k, 13].sum() - r[0, k, 13].sum()) / (2 * h)],
            cov_term[k].sum(0), inn_term[k].sum(0), (e[k] ** 2 / C[k]).mean(0),
            np.sqrt(C[k].mean(0)) * 1e6, np.sqrt(np.mean(e[k] ** 2, axis=0)) * 1e6])
    return out


def main() -> None:
    """Print each seed's joint score per window, then the means (the module's doc)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="2000-2023")
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--prior-scale", type=float, default=1.0)
    ap.add_argument("--at-truth", action="store_true")
    ap.add_argument("--quiet", action="store_true")
    ap.add_argument("--save", help="write the seeds' window values here (.npy)")
    ap.add_argument("--load", nargs="*", default=[],
                    help="summarise these --save files (no runs)")
    args = ap.parse_args()
    BIAS.scale_prior_sigma(args.prior_scale)
    first, _, last = args.seeds.partition("-")
    got = [dict(zip(WINDOWS, v, strict=True)) for f in args.load for v in np.load(f)]
    for seed in range(int(first), int(last or first) + 1) if not args.load else ():
        w = per_window(runs(seed, args))
        got.append(w)
        print(seed, " | ".join(f"{lo}-{hi}: {v[0]:+.2f}" for (lo, hi), v in w.items()),
              flush=True)
    if args.save:
        np.save(args.save, np.array([[g[w] for w in WINDOWS] for g in got]))
    names = ("joint score", "covariance term x y z", "innovation term x y z",
             "pointing NEES against the truth x y z", "predicted pointing σ µrad x y z",
             "pointing error RMS µrad x y z")
    sizes = (1, 3, 3, 3, 3, 3)
    for win in WINDOWS:
        v = np.array([g[win] for g in got])
        mean, se = v.mean(0), v.std(0, ddof=1) / math.sqrt(len(v)) if len(v) > 1 else 0 * v[0]
        print(f"window {win[0]}-{win[1]} s, {len(v)} seeds:")
        i = 0
        for name, n in zip(names, sizes, strict=True):
            print(f"  {name}: " + " ".join(f"{m:+.3f} ± {s:.3f}" for m, s in
                                          zip(mean[i:i + n], se[i:i + n], strict=True)))
            i += n


if __name__ == "__main__":
    main()
