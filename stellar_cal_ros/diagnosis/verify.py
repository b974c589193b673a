"""``discover --verify``: the printed MDBs and biases checked on twins of the user's bag.

For every effect the report lists under "what could still be hiding", a twin of the bag
(:mod:`stellar_cal_ros.diagnosis.twin`: the user's trajectory, stamps, stars and measured noise,
rendered with the final calibration) is made with the effect injected at its printed MDB —
the parameter the report names for its largest bias, else its best determined one — and a
twin with the same seed without it.  Then, per effect:

* **detection**: one diagnosis round on the injected twin (the final model, every
  candidate): is the effect a significant candidate?  One twin is one draw; the *power* is
  read from the measured non-centrality: the paired difference of the effect's score
  between the two twins, ``λ = Δsᵀ I⁻¹ Δs``, gives ``P(χ²_k(λ) > crit)`` — 80 % when the
  printed MDB is right;
* **bias**: the current model's estimates on the two twins: the shift of every listed
  quantity against the printed bias (within ± 30 %: holds).

"Would a 5 arcsec misalignment have been caught on my data?" is then answered on the
user's own motion, star field and noise.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy import stats as sps

from stellar_cal_ros.diagnosis import injection
from stellar_cal_ros.diagnosis.runstats import EPP_NAMES
from stellar_cal_ros.effects import registry
from stellar_cal_ros.effects.base import Stage

#: the printed numbers hold when the implied power is within these bounds and every
#: listed shift within this ratio of its printed bias
POWER_RANGE = (0.65, 0.95)
RATIO_RANGE = (0.7, 1.3)


def _values(run) -> dict[str, float]:
    out = run.value_by_name()
    epp = run.derived.get("equivalent_principal_point_px")
    if epp is not None:
        out.update(zip(EPP_NAMES, map(float, epp), strict=True))
    return out


def injected_parameter(entry: dict[str, Any]) -> tuple[str, list[str]]:
    """The parameter to inject for an entry, and the quantities whose bias it carries."""
    groups = injection.claims(entry)
    if groups:
        best = max(groups, key=lambda p: max(
            entry["biases"][q] / max(entry["sigma"].get(q, 1e-300), 1e-300) for q in groups[p]))
        return best, groups[best]
    plaus = entry["plausible_size"]
    return min(entry["hidden_size"], key=lambda p: entry["hidden_size"][p]
               / max(float(plaus.get(p, 1.0)), 1e-300)), []


def verify(data, calibration, method: str, effects: list[str], entries: list[dict],
           seed: int = 1, tell=None, fraction: float = 0.5) -> list[dict[str, Any]]:
    """Check ``entries`` (the report's reliability list) on twins of ``data``.

    ``calibration``: the final model's calibration (its ``consistency.noise`` is the
    measured noise the twins get); ``effects``: the final model's effects.
    """
    from stellar_cal_ros.diagnosis.noise import stated_scales
    from stellar_cal_ros.diagnosis.twin import make_twin

    noise = stated_scales(calibration)

    def make(injected: dict[str, np.ndarray]):
        twin = make_twin(data, calibration, injected, seed, method, noise)
        return twin.data, twin.counts

    return check_claims(make, calibration, method, effects, entries, noise, seed, tell,
                        fraction)


def check_claims(make, calibration, method: str, effects: list[str], entries: list[dict],
                 noise=None, seed: int = 1, tell=None, fraction: float = 0.5
                 ) -> list[dict[str, Any]]:
    """Inject each testable entry at its printed MDB into ``make(injected)`` bags and check.

    ``make({effect: simulate-units value}) -> (BagData, counts)`` makes the paired bags (the
    same noise for every call: a twin of the same seed, or the simulator with one seed);
    ``calibration`` is where the diagnosis starts; ``noise`` the scales its runs use.
    """
    from stellar_cal_ros.diagnosis.discover import Round, method_spec, rank_round
    from stellar_cal_ros.diagnosis.parallel import Runs

    spec = method_spec(method)
    extra = [e for e in effects if e not in spec.baseline]
    pool = [e["effect"] for e in entries]

    def round_on(data):
        runs = Runs(data, spec, fraction)
        runs.noise = noise
        r = Round(runs, spec, runs.facts(), fraction, calibration, (), True, None)
        base, results, _ = rank_round(r, calibration, extra, pool, condition=False,
                                      keep_residuals=False)
        return base, {c.effect: c for c in results}

    data0, _ = make({})
    base0, _ = round_on(data0)
    before = _values(base0)
    out = []
    for entry in entries:
        if not entry.get("testable"):
            continue
        eid = entry["effect"]
        eff = registry.create(eid)
        param, listed = injected_parameter(entry)
        size = entry["hidden_size"][param]
        delta = injection.parameter_delta(eid, param, size)
        data1, counts = make({eid: injection.simulation_value(eid, delta)})
        base, cands = round_on(data1)
        c = cands.get(eid)
        found = bool(c is not None and c.significant)
        lam = power = float("nan")
        s0 = (base0.scores or {}).get(eid)
        s1 = (base.scores or {}).get(eid)
        if s0 is not None and s1 is not None and len(s0) > 5 and len(s1) > 5:
            d = np.asarray(s1[5]) - np.asarray(s0[5])
            info = np.atleast_2d(np.asarray(s0[2], dtype=float))
            lam = float(d @ np.linalg.pinv(info) @ d)
            k = int(entry.get("dof", eff.size))
            crit = sps.chi2.isf(entry["alpha"], k)
            power = float(sps.ncx2.sf(crit, k, lam))
        shift = injection.paired_shift(before, _values(base))
        checks = []
        for q in listed:
            if q.startswith("equivalent_principal_point") and eff.stage in (Stage.CAMERA,
                                                                             Stage.TRACKER):
                continue  # the effect moves the true value itself
            printed = entry["biases_signed"][q]
            checks.append({"quantity": q, "printed": printed, "measured": shift.get(q),
                           "ratio": shift.get(q, np.nan) / printed if printed else np.nan})
        ratios = [c["ratio"] for c in checks]
        holds_bias = all(RATIO_RANGE[0] <= r <= RATIO_RANGE[1] for r in ratios)
        holds_power = bool(np.isfinite(power) and POWER_RANGE[0] <= power <= POWER_RANGE[1])
        rec = {"effect": eid, "parameter": param, "size": size,
               "size_shown": _shown(eid, param, size), "found": found,
               "noncentrality": lam, "expected_noncentrality": entry.get("lam0"),
               "implied_power": power, "biases": checks,
               "holds": bool(holds_bias and holds_power), "seed": seed,
               "twin_counts": counts}
        out.append(rec)
        if tell:
            tell(describe(rec))
    return out


def _shown(eid: str, param: str, value: float) -> str:
    from stellar_cal_ros.diagnosis.reliability import shown

    return shown(f"{eid}.{param}", value)


def describe(rec: dict[str, Any]) -> str:
    """One line of the verification."""
    from stellar_cal_ros.diagnosis.reliability import shown

    parts = [f"{rec['effect']} {rec['parameter']} = {rec['size_shown']}: "
             f"{'found' if rec['found'] else 'missed'} on the twin"]
    if np.isfinite(rec["noncentrality"]):
        parts.append(f"non-centrality {rec['noncentrality']:.3g} (MDB claims "
                     f"{rec['expected_noncentrality']:.3g}: power {rec['implied_power']:.0%})")
    for c in rec["biases"]:
        parts.append(f"{c['quantity']} moved {shown(c['quantity'], c['measured'])} "
                     f"(printed {shown(c['quantity'], c['printed'])})")
    return "; ".join(parts) + (" -> holds" if rec["holds"] else " -> DOES NOT HOLD")
