"""Where discover's 'beyond a flexure' statistic loses its currency, measured inside discover.

``flexure.beyond`` adds to a candidate's Λ (2ΔLL of discover's capped prequential
log-likelihood, over the dispersion) what a flexure fitted to the innovations removes with
it minus without it (an in-sample, *uncapped* whitened sum of squares, which pays no
log-determinant).  This runs discover with every non-camera candidate tested beyond a
significant remainder (the one-line rule H34 tried: ``--rule every``; default: main's rule)
and prints, at each call of ``beyond``, the parts in one currency over the same stars of the
evaluation window (both runs' accepted, aligned stars):

* ``dSS``: the candidate's reduction of the uncapped whitened sum of squares;
* ``dSS capped``: the same with each star's NIS capped at 13.8, as the log-likelihood does;
* ``dlogdet``: what the candidate's parameter uncertainty adds to Σ log det S;
* ``flex chi2`` without / with: the flexure's in-sample χ², uncapped, NIS-capped at the
  least-squares size, and the capped gain ``flexure.beyond`` adds (``stats.capped_gain``:
  the best size for the capped sum, ≥ 0; since 2026-11-27).

Cases: ``to`` = test_discovery_auto's bag (psce_rotations 120 s, seed 21, 10 ms time offset +
a true 1e-4 gyro scale factor, four candidates); ``flexure`` = test_discovery_effects'
flexure bag (40"/g, 200 s, seed 52, the two gyro candidates, noise as stated); ``mixed`` =
that bag with a true 1e-4 gyro scale factor too.  At the end: what was added, each
remainder test, and the adds marked as not told apart from a flexure
(``flexure.alias``: the test after
the add could not see a flexure of the size found before it).

Run::

    .venv/bin/python benchmarks/flexure_beyond_discover.py to --rule every
    .venv/bin/python benchmarks/flexure_beyond_discover.py flexure
    .venv/bin/python benchmarks/flexure_beyond_discover.py mixed
    .venv/bin/python benchmarks/flexure_beyond_discover.py flexure --seed 53
"""

from __future__ import annotations

import argparse
import tempfile

import numpy as np

from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.diagnosis import auto, flexure, stats
from stellar_cal_ros.diagnosis.run import diagnose
from stellar_cal_ros.methods.replay import bag_data_from_simulation, replay_psce
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

CAP = 13.8  # results.NIS_CAP

CASES = {
    "to": ({"time_offset": 0.01, "gyro_scale_factor": 1e-4}, 21, 120.0,
           ["time_offset", "pixel_aspect", "gyro_scale_factor", "image_plane_tilt"], "estimate",
           False),
    "flexure": ({"mount_flexure": 40.0}, 52, 200.0,
                ["gyro_scale_factor", "gyro_misalignment"], "stated", True),
    "mixed": ({"mount_flexure": 40.0, "gyro_scale_factor": 1e-4}, 52, 200.0,
              ["gyro_scale_factor", "gyro_misalignment"], "stated", True),
}

_orig_stats = flexure.remainder_statistics
_orig_beyond = flexure.beyond


def _parts(res, moved, fraction):
    """remainder_statistics plus the sums of its stars (uncapped, capped, log-det)."""
    got = _orig_stats(res, moved, fraction)
    if got is None:
        return None
    win = stats.evaluation_mask(res, fraction)
    a, b = flexure._aligned({k: np.asarray(v)[win] for k, v in res.items()}, moved)
    m = stats.accepted(a) & stats.accepted(b)
    sub = {k: v[m] for k, v in a.items()}
    S = np.stack([b["du"][m] - a["du"][m], b["dv"][m] - a["dv"][m]], 1) / (flexure.PROBE
                                                                            / ARCSEC)
    c = got["arcsec_per_g"]
    cov = {k: sub[k] for k in ("s_uu", "s_uv", "s_vv")}
    w = stats.whitened(sub)
    wx = stats.whitened({"du": S[:, 0] * c, "dv": S[:, 1] * c, **cov})
    ok = np.all(np.isfinite(w), 1) & np.all(np.isfinite(wx), 1)
    q, qf = np.sum(w[ok] ** 2, 1), np.sum((w[ok] - wx[ok]) ** 2, 1)
    det = sub["s_uu"] * sub["s_vv"] - sub["s_uv"] ** 2
    got.update(ss=float(q.sum()), ss_capped=float(np.minimum(q, CAP).sum()),
               logdet=float(np.log(det[ok]).sum()), n=int(ok.sum()),
               chi2_capped_ls=float(np.minimum(q, CAP).sum() - np.minimum(qf, CAP).sum()))
    return got


def _beyond(statistic, dof, dispersion, w, wo):
    out = _orig_beyond(statistic, dof, dispersion, w, wo)
    if w and wo and "ss" in w and "ss" in wo:
        lam = statistic * dispersion
        print(f"beyond ({dof} dof, dispersion {dispersion:.3f}): discover {out['statistic']:.1f}"
              f" | raw: 2dLL (Lambda) {lam:.1f}, dSS {wo['ss'] - w['ss']:.1f}, dSS capped "
              f"{wo['ss_capped'] - w['ss_capped']:.1f}, dlogdet {w['logdet'] - wo['logdet']:.1f}"
              f"; flex chi2 without/with {wo['chi2']:.1f}/{w['chi2']:.1f}, capped at the "
              f"least-squares c {wo['chi2_capped_ls']:.1f}/{w['chi2_capped_ls']:.1f}, capped "
              f"gain (what beyond adds) {wo['chi2_capped']:.1f}/{w['chi2_capped']:.1f}; "
              f"stars {wo['n']}/{w['n']}",
              flush=True)
    return out


def main() -> None:
    """Run one case's discover and print the parts at each beyond test."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", choices=sorted(CASES))
    ap.add_argument("--rule", choices=("main", "every"), default="main",
                    help="every: test each later non-camera candidate beyond a significant "
                         "remainder (H34's trial), not only after a stand-in")
    ap.add_argument("--seed", type=int, default=None, help="another seed of the case's bag")
    a = ap.parse_args()
    effects, seed, duration, cands, noise, refit = CASES[a.case]
    seed = seed if a.seed is None else a.seed
    flexure.remainder_statistics = _parts
    flexure.beyond = _beyond
    if a.rule == "every":
        real = auto._stand_in

        def stand_in(runs, state, *rest):
            b = real(runs, state, *rest)
            state.outside = state.outside or b is not None
            return b
        auto._stand_in = stand_in
    sim = simulate(get_scenario("psce_rotations"), duration=duration, seed=seed,
                   effects=effects)
    data = bag_data_from_simulation(sim)
    cal = replay_psce(data, sim.prior).calibration if refit else sim.prior
    with tempfile.TemporaryDirectory() as out:
        s = diagnose(data, cal, "psce", [], out, candidates=cands, plots=False,
                     verbose=False, auto=True, workers=0, noise=noise)
    print("added:", ", ".join(s["added"]))
    for step in s["path"]:
        got = step.get("remainder")
        if got:
            h = flexure.hiding(got, [], 1, 0.01)
            print(f"after round {step['round']}'s add {step['added']['effect']}: remainder t="
                  f"{got['t']:.1f} p={got['p_value']:.2g} {got['arcsec_per_g']:.1f}+-"
                  f"{got['sigma_arcsec_per_g']:.1f} arcsec/g (robust sigma "
                  f"{got.get('robust_sigma_arcsec_per_g') or float('nan'):.1f}; its MDB at "
                  f"1 %, one test: {h['arcsec_per_g']:.1f})")
        b = step.get("could_be_flexure")
        if b:
            print(f"  marked: {b['text']}")
    rem = s.get("remainder")
    print("remainder said:", "no" if not rem else
          f"after {'+'.join(rem['like'])}, later {rem.get('later')}, could be a flexure: "
          f"{sorted(rem.get('could_be_flexure') or {})}")
    print("\n".join(line for line in s["terminal"] if "added " in line or "residuals after"
                     in line or "unexplained:" in line))


if __name__ == "__main__":
    main()
