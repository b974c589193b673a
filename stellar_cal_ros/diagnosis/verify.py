"""``discover --verify``: the printed MDBs and biases checked on twins of the user's bag.

For every effect the report lists under "what could still be hiding", a twin of the bag
(:mod:`stellar_cal_ros.diagnosis.twin`: the user's trajectory, stamps, stars and measured noise,
rendered with the final calibration) is made with the effect injected at its printed MDB —
the parameter the report names for its largest bias, else its best determined one — and a
twin without it; at both signs of the MDB (an MDB is a size of either sign: the
image-plane tilt's response is 0.55x its first order at +MDB, 1.47x at −MDB).  Per effect
and sign:

* **detection**: the row's score test on the bag's twin rendered without noise, with and
  without the effect (:func:`noise_free_pairs`): the paired difference of the effect's
  score, ``λ = Δsᵀ I⁻¹ Δs`` on the directions its test sums over (:func:`paired_response`),
  is, with no noise, the whole response: the non-centrality of the test on this bag at that
  size, and ``P(χ²_k(λ) > crit)`` (:func:`power_at`) the power the MDB claims 80 % of
  (holds within :data:`POWER_RANGE`, above it conservatively; below, the line gives the
  power this bag gives).  An effect the model absorbs to first order (an image-plane tilt)
  responds non-linearly (0.55x at +MDB, 1.47x at -MDB), which λ measures at each sign.
  The power holds where the score's noise is what ``I`` states: one screening run on a
  noisy clean twin checks that once (:func:`noise_check`), and the noise-free λ is the
  noisy twins' over seeds (their score statistic's mean less its dof,
  ``test_verify::test_the_noise_free_power_is_the_noisy_twins_detection_rate``).  Noisy
  twins of different seeds (``--verify-twins N``: a diagnosis round each, the decision's
  draw) are listed beside it where asked for, not judged;
* **bias**: the current model's estimates on the same noise-free twin pair: the shift of
  every listed quantity exactly, against the printed bias (within ± 30 %: holds; beyond,
  the line says the first order misses and gives the measured shift:
  :func:`noise_free_record`; H268 measured that it is the noisy twins' mean, radial_k3
  epp.u 1.17x against 1.18x, refraction cx 1.75x against 1.77x on ``dt_step`` s23, where
  six twins could not judge cx, at one run per row and sign); a twin below the printed size
  checks a row a probe measured at it against its first order plus the probe's departure
  as of second order (:func:`~.injection.claimed_shift`, :func:`bias_checks`).

A row whose noise-free run fails is judged on noisy twins as before (:data:`TWINS` of
different noise seeds, judged on their mean, :func:`pooled`: a row whose shift varies from
twin to twin as much as ± 30 % of its claim cannot be judged by them, and says so;
``--verify-twins auto`` gives a row they leave :func:`undecided` the twins of further
seeds, up to :data:`TWINS_MAX`): its detection on the twins' mean paired response.

A claim is one-sided where it errs on the safe side (:func:`claim_verdict`): a score
response *above* the power band (the effect is seen more easily than printed: the MDB
overstates what could hide) and a shift *smaller* than printed (the printed bias overstates
what the effect does) are conservative: the claim holds, and the record says so
(``verdict`` "conservative").  A response below the band, a shift larger than printed or
in the other direction at its size, fails.

A row discover marks refused by its clock rule (``refused_beside_clock``,
:func:`~stellar_cal_ros.diagnosis.clock.refuses`: a gyro rate effect is not added while the
stars' remainder along their motion on the user's bag is a clock's) is not added at that
size whatever its test says.  A twin holds no such remainder (it is rendered from the
library), so its round says what the test sees, not what discover does on the bag: where the
rule refuses the effect at the twin's sign and size on the user's bag (:func:`clock_rule`),
the record says "refused by the clock rule (not a miss)", its detection is no claim (the
verdict judges its biases only) and the count of detections leaves it out.

"Would a 5 arcsec misalignment have been caught on my data?" is then answered on the
user's own motion, star field and noise.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from stellar_cal_ros.core import distributions as dist
from stellar_cal_ros.diagnosis import injection
from stellar_cal_ros.diagnosis.reliability import score_response
from stellar_cal_ros.diagnosis.reliability_probe import own_shift, stated_size
from stellar_cal_ros.effects import registry

log = logging.getLogger(__name__)

#: the printed numbers hold when the paired score response's power is within these bounds
#: and every listed shift within this ratio of its printed bias
POWER_RANGE = (0.65, 0.95)
RATIO_RANGE = (0.7, 1.3)
#: noisy twins of different noise seeds a row whose noise-free run failed gets: two measure
#: the twin-to-twin spread of a row's shift (:func:`pooled`)
TWINS = 2
#: ``--verify-twins auto`` (the default): such a row, whose quantity the first
#: :data:`TWINS` twins cannot judge, or whose verdict they leave undecided at the band's edge
#: (:func:`undecided`), gets twins of further seeds, one at a time, up to this many
TWINS_MAX = 6
#: a quantity is judged where the ratio band's half-width holds the two-sided 95 % interval
#: of the twins' mean shift (:func:`judge_z`)
JUDGE_LEVEL = 0.95


def judge_z(twins: int) -> float:
    """The half-width, in σ of the twins' mean shift, of its two-sided 95 % interval.

    The mean's σ is the twins' spread (their SD, estimated from the same ``twins`` shifts)
    / √twins, so the interval is Student's t of ``twins − 1`` dof, not the normal's 1.96:
    12.7 on 2 twins, 4.30 on 3, 2.57 on 6 (1.96 there covers the true mean in 70 % of
    2-twin draws, 81 % of 3, 89 % of 6: ``test_verify``'s simulation).
    """
    return float(dist.t.isf((1.0 - JUDGE_LEVEL) / 2.0, max(int(twins), 2) - 1))


def twin_scale(entry: dict[str, Any], param: str, own: bool = False) -> float:
    """The share of the printed hidden size a twin is injected at (1 on a fitting round).

    A round states its MDB for the dispersion ``d`` its statistics are divided by (a
    screened round too, H295; ``dispersion``: √d × the MDB of residuals as stated,
    :func:`~.reliability.detectability`).  A twin holds the user's motion, stars and
    measured noise but not the misfit, so its rounds fit (d ≈ 1): there the printed size
    would be seen with a non-centrality d·λ₀, always "conservative", and the check would
    say nothing.  The twin is injected at the MDB for residuals as stated instead
    (``mdb / √d``, at most the plausible size the printed hidden size is capped at), and
    every printed bias is scaled alike (they are linear in the size).  Where the round's
    excess gate set the printed MDB (``mdb_set_by``), the twin, without the misfit's excess,
    has no such gate: it gets the test's MDB (``mdb_test``) for residuals as stated, and
    likewise on a round that fits.  Where the probe's runs restated the MDB at both signs
    (``mdb_set_by`` "probe", :func:`~.reliability_probe.both_signs`: an image-plane tilt's
    weaker sign), the twin, which responds as the user's bag does, gets the printed MDB
    (for residuals as stated): the share is then above 1 (the biases, printed at the
    first-order size, scaled alike).  (:func:`~.reliability_probe.stated_size`: the size
    the probe's runs check the test's MDB at, at both signs.)

    ``own``: the bag injected is not a twin but one whose residuals scatter as the round's
    did (the simulator's bag of the same seed and noise, ``benchmarks/reliability_
    injection.py``): its rounds divide by the same dispersion, so the printed MDB is the
    size to inject (the rules above with ``dispersion`` 1).
    """
    d = float(entry.get("dispersion", 1.0))
    root = 1.0 if own else np.sqrt(d)  # the injected bag's residuals' over the stated
    hidden = float(entry["hidden_size"][param])
    if entry.get("mdb_set_by") == "probe" and hidden > 0.0:
        return float(entry["mdb"][param]) / root / hidden
    if (root == 1.0 and not entry.get("mdb_set_by")) or not hidden > 0.0:
        return 1.0
    return min(stated_size(entry, param) * np.sqrt(d) / root / hidden, 1.0)


def verify(data, calibration, method: str, effects: list[str], entries: list[dict],
           seed: int = 1, tell=None, fraction: float = 0.5, clock_check=None,
           signs: tuple[int, ...] = (1, -1), twins: int = 0,
           twins_max: int | None = None, exact: bool = True) -> list[dict[str, Any]]:
    """Check ``entries`` (the report's reliability list) on twins of ``data``.

    ``calibration``: the final model's calibration (its ``consistency.noise`` is the
    measured noise the twins get); ``effects``: the final model's effects.
    ``clock_check(effect, delta)``: the clock test of the final model's run on ``data``
    with the effect injected (:func:`clock_rule`), or ``None``.  Every row is injected at
    each of ``signs`` (an MDB is a size of either sign).

    ``exact`` (the default): each row is judged on the bag's noise-free twin pair
    (:func:`noise_free_pairs`, :func:`noise_free_record`: one screening run a row and
    sign): its biases on the exact shift, its detection on the exact score response λ,
    whose power at the test's level is the MDB's claim (:func:`power_at`).  ``twins``
    (``--verify-twins``, 0 by default) noisy twins of seeds ``seed``, ``seed + 1``, ... are
    made for every row beside it (their detections and mean shifts are listed, not judged);
    one screening run on the clean noisy twin of ``seed`` checks the noise model the power
    is computed with (:func:`noise_check`, the first record's ``noise_check``).  A row whose
    noise-free run fails, and every row with ``exact=False``, is judged on noisy twins
    (:func:`pooled`): at least :data:`TWINS`; ``twins_max`` above that
    (``--verify-twins auto``): a row and sign these twins leave :func:`undecided` is injected
    into the twin of the next seed too, one seed at a time, until decided or on
    ``twins_max`` twins; the clean twin of a seed is rendered and run once for every row
    still open.  Each record says its own ``twins``.
    """
    from stellar_cal_ros.diagnosis.noise import stated_scales
    from stellar_cal_ros.diagnosis.twin import make_twin

    noise = stated_scales(calibration)
    asked: dict[tuple, Any] = {}

    def clock_once(effect, delta):  # a run on the user's bag: the same for every twin seed
        key = (effect, tuple(np.asarray(delta, dtype=float).tolist()))
        if key not in asked:
            asked[key] = clock_check(effect, delta)
        return asked[key]

    checker = clock_once if clock_check else None
    twins = max(int(twins), 0)
    by_effect = {e["effect"]: e for e in entries}
    keys = [(e["effect"], int(s)) for e in entries if e.get("testable") for s in signs]
    # the noise-free twin pair: exact shifts and score responses, one run a row and sign
    free = noise_free_pairs(data, calibration, method, effects, entries, noise, fraction,
                            signs) if exact else {}
    lacking = [key for key in keys if key not in free]
    first = {key: twins if key in free else max(twins, TWINS) for key in keys}
    cap = max([int(twins_max or 0), *first.values()]) if keys else 0

    rows: dict[tuple[str, int], list[dict[str, Any]]] = {}  # (effect, sign) -> its twins' records
    for k in range(cap):
        need = {key for key in keys if k < first[key] or (
            key in lacking and key in rows and undecided(pooled(by_effect[key[0]], rows[key])))}
        if not need:
            break

        def make(injected: dict[str, np.ndarray], s: int = seed + k):
            twin = make_twin(data, calibration, injected, s, method, noise)
            return twin.data, twin.counts

        # one twin of this seed (its clean round rendered once) serves every row still open
        for rec in check_claims(make, calibration, method, effects, entries, noise,
                                seed + k, None, fraction, signs=signs, clock_check=checker,
                                rows=None if k < min(first.values()) else need):
            rows.setdefault((rec["effect"], rec["sign"]), []).append(rec)
        if tell:
            tell(f"verify: noisy twins of seed {seed + k} done ({len(need)} rows and signs)")
    out = []
    for key in keys:
        entry = by_effect[key[0]]
        if key in free:
            out.append(noise_free_record(entry, key[1], free[key], calibration, method,
                                         checker, rows.get(key)))
        elif key in rows:
            out.append(pooled(entry, rows[key]))
    if lacking and cap > TWINS:  # the first twins' count, the most a row could get, and
        # what they left at the band's edge (judged; a quantity not judged says so already)
        out = [rec if rec.get("biases_on") == "noise-free twin" else
               {**rec, "twins_first": TWINS, "twins_max": cap,
                "at_edge": [q for q in undecided(rec) if q not in rec.get("unjudged", [])]}
               for rec in out]
    if exact and out and data is not None:
        out[0] = {**out[0], "noise_check": noise_check(data, calibration, method, effects,
                                                       entries, noise, fraction, seed)}
    if tell:
        for rec in out:
            tell(describe(rec))
    return out


def noise_free_pairs(data, calibration, method: str, effects: list[str],
                     entries: list[dict], noise=None, fraction: float = 0.5,
                     signs: tuple[int, ...] = (1, -1),
                     parameters: dict[str, str] | None = None
                     ) -> dict[tuple[str, int], dict[str, Any]]:
    """Each row on the bag's noise-free twin: ``{(effect, sign): record}``.

    A record holds ``parameter`` (the one injected, :func:`injected`), ``shift`` and
    ``noncentrality``.  The current model's screening run (``effects`` from
    :func:`~.discover.rerun_prior` of ``calibration``, with ``noise``'s scales, as the
    twins' rounds run it; the rows' effects its consider parameters, which leave the
    filter's estimate alone and score each the same alone or beside the others) on the twin
    rendered without noise (:func:`~.reliability_probe.rendered`: the bag's motion, stamps
    and stars, no noise, no misfit) with each testable row injected at ``sign`` x its size
    (:func:`injected`: what the noisy twins get), against its run on the twin alone:

    * ``shift``: every quantity's shift at that size exactly, with no twin-to-twin spread
      to average out.  H268 measured that it is the noisy twins' mean (radial_k3 epp.u
      1.17x against 1.18x on 6 twins, refraction cx 1.75x against 1.77x, e02
      installation.ry 1.23x against 1.29x ± 0.06);
    * ``noncentrality``: the row's paired score response λ (:func:`paired_response`):
      without noise, the score's whole change is the effect's, so λ is the non-centrality
      of the test on this bag at that size, and ``P(χ²_k(λ) > crit)`` its power
      (:func:`power_at`; the noisy twins' detection rate over seeds,
      ``test_verify::test_the_noise_free_power_is_the_noisy_twins_detection_rate``).

    A row whose run fails (or all, where the clean run fails) is left out: noisy twins
    judge it (:func:`verify`).
    """
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.reliability_probe import rendered
    from stellar_cal_ros.diagnosis.runstats import evaluate
    from stellar_cal_ros.diagnosis.twin import twin_scene

    spec = method_spec(method)
    extra = tuple(spec.beyond_baseline(effects))
    prior = rerun_prior(calibration)
    scene = twin_scene(data, calibration, method)
    rows = [e for e in entries if e.get("testable")]
    screen = tuple(dict.fromkeys(e["effect"] for e in rows if e["effect"] not in effects))

    def run(inject: dict[str, Any], scored: tuple[str, ...]):
        twin = rendered(data, calibration, method, inject, scene)
        got = evaluate(twin, spec, prior, extra, fraction, screen=scored, noise=noise,
                       gyro_check=False)
        if not got.ok:
            log.warning("verify: the noise-free twin's run failed (%s): noisy twins "
                        "judge it", got.error)
            return None
        return got

    out: dict[tuple[str, int], dict[str, Any]] = {}
    base = run({}, screen)
    if base is None:
        return out
    before = injection.summary_values(base)
    for entry in rows:
        eid, alpha = entry["effect"], float(entry.get("alpha", 0.0))
        for sign in signs:
            param, _, _, delta = injected(entry, int(sign), (parameters or {}).get(eid))
            after = run({eid: injection.simulation_value(eid, delta)},
                        (eid,) if eid in screen else ())
            if after is not None:
                out[(eid, int(sign))] = {
                    "parameter": param, "shift": injection.paired_shift(
                        before, injection.summary_values(after),
                        own_shift(calibration, method, eid, delta)),
                    "noncentrality": paired_response(eid, base, after, alpha, calibration)}
    return out


def paired_response(effect_id: str, before, after, alpha: float = 0.0,
                    calibration: Any = None) -> float:
    """The paired score response λ of ``effect_id`` from run ``before`` to run ``after``.

    ``Δsᵀ I⁻¹ Δs`` (:func:`~.reliability.score_response`) of the screening runs' raw
    scores (:attr:`~.runstats.RunSummary.scores`), ``I`` ``before``'s; with ``alpha`` (the
    row's level) on the directions its test sums over (:meth:`~.screening.ScreenResult.
    tested`: the blind ones left out, as the MDB's λ₀ is stated: a gyro misalignment's
    three blind directions gave 85 on clean psce's noise-free twin at the 6-direction MDB
    and 29-33 on its noisy twins).  NaN where either run did not score the effect.  A
    noisy twin pair's (:func:`check_claims`) and the noise-free pair's
    (:func:`noise_free_pairs`) alike.
    """
    from stellar_cal_ros.diagnosis.screening import ScreenResult

    s0 = (before.scores or {}).get(effect_id)
    s1 = (after.scores or {}).get(effect_id)
    if s0 is None or s1 is None or len(s0) <= 5 or len(s1) <= 5:
        return float("nan")
    d = np.asarray(s1[5], dtype=float) - np.asarray(s0[5], dtype=float)
    info = np.atleast_2d(np.asarray(s0[2], dtype=float))
    full = ScreenResult(score_response(d, info), d.size, info, score=d)
    return float(full.tested(effect_id, alpha, calibration).lm if alpha > 0 else full.lm)


def power_at(lam: float, alpha: float, dof: int) -> float:
    """``P(χ²_dof(λ) > crit)`` at level ``alpha``: a score test's power at response ``λ``."""
    if not np.isfinite(lam):
        return float("nan")
    return float(dist.ncx2.sf(dist.chi2.isf(alpha, dof), dof, max(lam, 0.0)))


def noise_free_record(entry: dict[str, Any], sign: int, pair: dict[str, Any],
                      calibration, method: str, clock_check=None,
                      recs: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """One row at one sign judged on the noise-free twin pair (:func:`noise_free_pairs`).

    ``noncentrality`` is the pair's exact λ, ``paired_power`` its power at the test's
    level and dof (:func:`power_at`): the detection claim ("found with 80 % power at its
    MDB") holds where it is in :data:`POWER_RANGE` or above (seen more easily: conservative);
    below, the line gives the power this bag gives (:func:`describe`).  Each listed
    quantity's ``measured`` is its exact shift (``exact`` true).  A shift beyond ± 30 % of
    its printed first-order bias (:data:`RATIO_RANGE`'s width about 1, either side) is
    listed in ``first_order_misses`` with its measured bias (``noise_free``, at the twin's
    size; ``at_printed_size``: at the size the biases are printed at, the twin's /
    ``size_scale`` — the shift is linear in the size, H268).  The verdict is
    :func:`claim_verdict` of the two; the clock rule as :func:`clock_rule`.

    ``recs``: the row's noisy twins' records (``--verify-twins N``), listed beside it and
    not judged: ``found_on`` of ``twins``, ``twins_noncentrality`` (their mean λ),
    ``noncentrality_by_twin``; each quantity's ``twins_mean`` and ``by_twin``.
    """
    eid = entry["effect"]
    param, scale, size, delta = injected(entry, sign, pair.get("parameter"))
    k = int(entry.get("dof", registry.create(eid).size))
    lam = float(pair["noncentrality"])
    power = power_at(lam, entry["alpha"], k)
    rule = clock_rule(entry, param, size, delta, clock_check)
    refused = bool(rule and rule["refuses"])
    checks = bias_checks(entry, param, sign, scale, pair["shift"])
    for c in checks:
        c["exact"] = True
    verdict, conservative = claim_verdict(power, [c["ratio"] for c in checks],
                                          detection=not refused)
    misses = [{"quantity": c["quantity"], "printed": c["printed"], "noise_free": c["measured"],
               "ratio": c["ratio"], "at_printed_size": c["measured"] / scale}
              for c in checks if misses_first_order(c["ratio"])]
    rec = {"effect": eid, "parameter": param, "size": size, "sign": sign,
           "size_shown": _shown(eid, param, size), "refused_by_clock": refused,
           **({"clock_rule": rule} if rule else {}),
           "noncentrality": lam, "expected_noncentrality": entry.get("lam0"),
           "paired_power": power, "dof": k, "alpha": entry["alpha"],
           "detection_on": "noise-free twin", "biases_on": "noise-free twin",
           "biases": checks, "holds": verdict in ("holds", "conservative"),
           "verdict": verdict, "conservative": conservative, "unjudged": [],
           "first_order_misses": misses, "size_scale": scale, "twins": 0}
    if not recs:
        return rec
    noisy = pooled(entry, recs)
    for c, n in zip(checks, noisy["biases"], strict=True):
        c["twins_mean"] = n["measured"]
        c["by_twin"] = n.get("by_twin", [n["measured"]])
    return {**rec, "twins": len(recs), "seeds": [r["seed"] for r in recs],
            "found_on": sum(bool(r["found"]) for r in recs),
            "named_on": sum(bool(r["named"]) for r in recs),
            "twins_noncentrality": noisy["noncentrality"],
            "noncentrality_by_twin": [r["noncentrality"] for r in recs],
            "twin_counts": recs[0].get("twin_counts")}


def noise_check(data, calibration, method: str, effects: list[str], entries: list[dict],
                noise=None, fraction: float = 0.5, seed: int = 1) -> dict[str, Any] | None:
    """The noise model the powers are computed with, checked once on a noisy clean twin.

    A power ``P(χ²_k(λ) > crit)`` (:func:`power_at`) holds where the score's noise on
    this bag is what its information ``I`` states (the twin's rendered noise is the
    measured noise the runs state): the current model's screening run on the clean twin
    of ``seed`` (:func:`~.twin.make_twin`), every row's effect scored on its tested
    directions (:func:`~.screening.collect`), gives each a central χ²_k draw.  Returns
    ``{"seed", "statistic", "dof", "ratio", "p_value", "smallest_p", "effects",
    "holds"}``: ``statistic`` the sum of the candidates' statistics over ``dof`` their
    dof (``ratio``; a sum of χ²'s, not independent where their signatures overlap, so
    its ``p_value`` χ²_dof's upper tail is a guide), ``smallest_p`` the smallest test's p x
    the candidates' count (Bonferroni) and ``holds``: no candidate false-alarms at the
    rows' level (``smallest_p`` ≥ their α).  None where the run fails.
    """
    from stellar_cal_ros.diagnosis import screening
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.runstats import evaluate
    from stellar_cal_ros.diagnosis.twin import make_twin

    rows = [e for e in entries if e.get("testable") and e["effect"] not in effects]
    screen = tuple(dict.fromkeys(e["effect"] for e in rows))
    if not screen:
        return None
    spec = method_spec(method)
    alpha = min(float(e["alpha"]) for e in rows)
    twin = make_twin(data, calibration, {}, seed, method, noise)
    run = evaluate(twin.data, spec, rerun_prior(calibration),
                   tuple(spec.beyond_baseline(effects)), fraction, screen=screen,
                   noise=noise, gyro_check=False)
    if not run.ok:
        log.warning("verify: the noise check's run failed (%s)", run.error)
        return None
    got = screening.collect([run], alpha=alpha, calibration=calibration)
    by = {e: [float(got[e].statistic), int(got[e].dof), float(got[e].p_value)]
          for e in screen if e in got}
    if not by:
        return None
    stat = float(sum(v[0] for v in by.values()))
    dof = int(sum(v[1] for v in by.values()))
    smallest = min(1.0, min(v[2] for v in by.values()) * len(by))
    return {"seed": seed, "statistic": stat, "dof": dof, "ratio": stat / max(dof, 1),
            "p_value": float(dist.chi2.sf(stat, max(dof, 1))), "smallest_p": smallest,
            "effects": by, "holds": smallest >= alpha}


def misses_first_order(ratio: float) -> bool:
    """A measured shift beyond ± 30 % of its printed bias (or not measured)."""
    half = RATIO_RANGE[1] - 1.0
    return not (np.isfinite(ratio) and abs(ratio - 1.0) <= half)


def undecided(rec: dict[str, Any]) -> list[str]:
    """The quantities of a pooled record that more twins could decide (``--verify-twins auto``).

    One not judged (:func:`pooled`: the twins' spread too wide for the ± 30 % band), and one
    judged whose mean ratio's 95 % interval (:func:`judge_z` x the mean's σ, the twins'
    spread / √twins) holds an edge between holding and failing (a ratio of 1.3, or −0.7):
    its verdict on these twins is a draw (dt_step s23, seed 1: radial_k3's epp.u 1.32x on two
    twins, spread 0.015 σ against a claim of 0.12 σ — holds on three).  One twin: nothing
    (no spread known).
    """
    out = []
    for c in rec["biases"]:
        if "judged" not in c:
            continue
        if not c["judged"]:
            out.append(c["quantity"])
            continue
        n = rec["twins"]
        half = judge_z(n) * c["spread"] / np.sqrt(n) / abs(c["printed"])
        if any(abs(c["ratio"] - edge) < half for edge in (RATIO_RANGE[1], -RATIO_RANGE[0])):
            out.append(c["quantity"])
    return out


def pooled(entry: dict[str, Any], recs: list[dict[str, Any]]) -> dict[str, Any]:
    """One row at one sign judged on ``recs``, its checks on twins of different seeds.

    A row's paired shift varies from twin to twin where the model's answer to the effect
    depends on the noise (a row a probe replaced, a second-order one: on ``dt_step`` s23
    up to 0.3 σ, 0.06-0.24 σ against claims of 0.08-0.25 σ, H229; the median row 0.01 σ,
    2 % of its claim, doc/benchmarks.md H234).  The
    claim is judged on the twins' mean shift, whose σ is the twins' spread (their SD)
    / √twins; a quantity is judged where the ± 30 % band (:data:`RATIO_RANGE`) holds
    :func:`judge_z` of those σ (Student's t: a true claim then lands in it at 95 %) — else
    "cannot be judged with N twins (spread X σ against a claim of Y σ)": its ratio is left
    out of the verdict, and a claim whose judged parts hold is ``verdict`` "cannot be
    judged" (``holds`` false, counted apart).  The detection is judged on the mean paired score
    response.  One twin (``recs`` of one seed): its record as it is (no spread known).
    """
    first = recs[0]
    if len(recs) == 1:
        return first
    n = len(recs)
    lams = [r["noncentrality"] for r in recs if np.isfinite(r["noncentrality"])]
    lam = float(np.mean(lams)) if lams else float("nan")
    crit = dist.chi2.isf(first["alpha"], first["dof"])
    response = (float(dist.ncx2.sf(crit, first["dof"], lam)) if np.isfinite(lam)
                else float("nan"))
    mean = {}
    for i, c in enumerate(first["biases"]):
        got = np.array([r["biases"][i]["measured"] for r in recs], dtype=float)
        mean[c["quantity"]] = float(np.mean(got))
    checks = bias_checks(entry, first["parameter"], first["sign"], first["size_scale"], mean)
    for i, c in enumerate(checks):
        got = np.array([r["biases"][i]["measured"] for r in recs], dtype=float)
        spread = float(np.std(got, ddof=1))
        c["by_twin"] = got.tolist()
        c["spread"] = spread
        c["judged"] = bool(judge_z(n) * spread / np.sqrt(n)
                           <= (RATIO_RANGE[1] - 1.0) * abs(c["printed"]))
    refused = first["refused_by_clock"]
    verdict, conservative = claim_verdict(
        response, [c["ratio"] for c in checks if c["judged"]], detection=not refused)
    unjudged = [c["quantity"] for c in checks if not c["judged"]]
    if unjudged and verdict != "fails":
        verdict, conservative = "cannot be judged", []
    return {**first, "seeds": [r["seed"] for r in recs], "twins": n,
            "found_on": sum(bool(r["found"]) for r in recs),
            "named_on": sum(bool(r["named"]) for r in recs),
            "noncentrality": lam, "paired_power": response,
            "noncentrality_by_twin": [r["noncentrality"] for r in recs],
            "biases": checks, "holds": verdict in ("holds", "conservative"),
            "verdict": verdict, "conservative": conservative, "unjudged": unjudged}


def check_claims(make, calibration, method: str, effects: list[str], entries: list[dict],
                 noise=None, seed: int = 1, tell=None, fraction: float = 0.5,
                 only: list[str] | None = None, signs: tuple[int, ...] = (1,),
                 parameters: dict[str, str] | None = None,
                 clock_check=None, rows=None, own: bool = False) -> list[dict[str, Any]]:
    """Inject each testable entry at its printed MDB into ``make(injected)`` bags and check.

    ``make({effect: simulate-units value}) -> (BagData, counts)`` makes the paired bags (the
    same noise for every call: a twin of the same seed, or the simulator with one seed);
    ``calibration`` is where the diagnosis starts; ``noise`` the scales its runs use.
    ``own``: ``make``'s bags scatter as the diagnosed bag's residuals did (the simulator's
    bag of the same seed and noise, not a twin that fits): the printed MDB is injected
    where it is stated for a dispersion (:func:`twin_scale`).

    Every round tests all of ``entries``' effects (the report's candidates: the same
    family-wise correction as the report's decision); ``only`` restricts which are
    injected, ``signs`` the signs of the injected size (an MDB is a size: either sign),
    ``parameters`` (``{effect: parameter}``) the parameter injected where it is not the
    report's (:func:`injection.injected_parameter`): a probe-restated MDB per parameter;
    ``rows`` (a set of ``(effect, sign)``) the rows injected, where not all.

    Per injection: ``found`` — the round's decision flags it (significant, or significant
    but at a size its physics rules out, 'implausible': the report says a structure with
    its pattern is there); ``named`` — significant as itself; ``score_statistic`` — the
    decision's score statistic on the injected bag (over seeds its mean minus the dof is
    the measured non-centrality, ``benchmarks/reliability_injection.py``);
    ``noncentrality`` — ``Δsᵀ I⁻¹ Δs`` of the paired score difference, the
    noise-free response of the score (λ₀ when the score is linear in the effect up to its
    MDB); ``clock_rule``/``refused_by_clock`` for a row discover's clock rule marks
    (:func:`clock_rule`, ``clock_check`` as there).
    """
    from stellar_cal_ros.diagnosis.discover import Round, method_spec, rank_round
    from stellar_cal_ros.diagnosis.parallel import Runs

    spec = method_spec(method)
    extra = spec.beyond_baseline(effects)
    pool = [e["effect"] for e in entries]

    def round_on(data):
        runs = Runs(data, spec, fraction)
        runs.noise = noise
        r = Round(runs, spec, runs.facts(), fraction, calibration, (), True, None)
        base, results, _ = rank_round(r, calibration, extra, pool, condition=False,
                                      keep_residuals=False)
        return base, {c.effect: c for c in results}

    data0, _ = make({})
    base0, cands0 = round_on(data0)
    before = injection.summary_values(base0)
    out = []
    for entry in entries:
        if not entry.get("testable") or (only is not None and entry["effect"] not in only):
            continue
        for sign in signs:
            if rows is not None and (entry["effect"], int(sign)) not in rows:
                continue
            rec = _inject(make, round_on, entry, base0, cands0, before, int(sign),
                          calibration, method, (parameters or {}).get(entry["effect"]),
                          clock_check, own)
            rec["seed"] = seed
            out.append(rec)
            if tell:
                tell(describe(rec))
    return out


def injected(entry: dict[str, Any], sign: int, param: str | None = None, own: bool = False
             ) -> tuple[str, float, float, np.ndarray]:
    """``(parameter, share, size, delta)`` of one row's twin injection at ``sign``.

    The parameter the report names (:func:`~.injection.injected_parameter`) unless
    ``param``; its share of the printed hidden size (:func:`twin_scale`; ``own``: a bag
    whose residuals scatter as the round's did, not a twin), the signed size and the
    effect's parameter vector (:func:`~.injection.parameter_delta`).
    """
    param = param or injection.injected_parameter(entry)[0]
    scale = twin_scale(entry, param, own)
    size = sign * entry["hidden_size"][param] * scale
    return param, scale, size, injection.parameter_delta(entry["effect"], param, size)


def _inject(make, round_on, entry, base0, cands0, before, sign: int, calibration,
            method: str, param: str | None = None, clock_check=None,
            own: bool = False) -> dict[str, Any]:
    """One entry injected at ``sign`` x its printed MDB: the check's record.

    The measured shift of a derived quantity is the estimate's shift less what the effect
    itself does to it (:func:`~.reliability_probe.own_shift`: the equivalent principal
    point of an effect that moves the principal point or the installation), as the printed
    bias is (:func:`~.reliability.bias_rows`); so its rows are checked for every effect.
    """
    eid = entry["effect"]
    eff = registry.create(eid)
    param, scale, size, delta = injected(entry, sign, param, own)
    data1, counts = make({eid: injection.simulation_value(eid, delta)})
    base, cands = round_on(data1)
    c = cands.get(eid)
    lam = paired_response(eid, base0, base, entry["alpha"], calibration)
    if own:  # its test's statistic is divided by the bag's dispersion (a twin fits: 1)
        lam /= float(entry.get("dispersion", 1.0))
    k = int(entry.get("dof", eff.size))
    shift = injection.paired_shift(before, injection.summary_values(base),
                                   own_shift(calibration, method, eid, delta))
    checks = bias_checks(entry, param, sign, scale, shift)
    ratios = [c["ratio"] for c in checks]
    response = power_at(lam, entry["alpha"], k)
    rule = clock_rule(entry, param, size, delta, clock_check)
    refused = bool(rule and rule["refuses"])
    verdict, conservative = claim_verdict(response, ratios, detection=not refused)
    c0 = cands0.get(eid)
    return {"effect": eid, "parameter": param, "size": size, "sign": sign,
            "size_shown": _shown(eid, param, size),
            "found": flagged(c), "refused_by_clock": refused,
            **({"clock_rule": rule} if rule else {}),
            "named": bool(c is not None and c.significant),
            "noncentrality": lam, "expected_noncentrality": entry.get("lam0"),
            "paired_power": response, "dof": k, "alpha": entry["alpha"],
            "biases": checks, "holds": verdict != "fails", "verdict": verdict,
            "conservative": conservative,
            "twin_counts": counts, "size_scale": scale, **_decision(c),
            "clean_score_statistic": (c0.screen.statistic if c0 is not None
                                      and c0.screen is not None else float("nan"))}


def bias_checks(entry: dict[str, Any], param: str, sign: int, scale: float,
                shift: dict[str, float]) -> list[dict[str, Any]]:
    """Each listed quantity's measured ``shift`` against its claim at ``scale`` x the size.

    The claim (:func:`~.injection.claimed_shift`) is a range for a row a probe measured
    at the printed size, checked at a smaller share: ``printed`` is then its point
    nearest the measured shift (the measured one where it lies within: ratio 1) and
    ``claimed`` the range; elsewhere the printed bias x ``scale``.
    """
    checks = []
    for q in injection.claims(entry, sign, scale).get(param, []):
        ends = injection.claimed_shift(entry, q, sign, scale)
        measured = shift.get(q, np.nan)
        printed = float(np.clip(measured, min(ends), max(ends))) if np.isfinite(
            measured) else ends[0]
        checks.append({"quantity": q, "printed": printed, "measured": shift.get(q),
                       "ratio": measured / printed if printed else np.nan,
                       "sigma": float(entry["sigma"][q]),
                       **({"claimed": list(ends)} if ends[0] != ends[1] else {})})
    return checks


def claim_verdict(power: float, ratios: list[float], detection: bool = True
                  ) -> tuple[str, list[str]]:
    """``("holds" | "conservative" | "fails", what errs on the safe side)`` of one claim.

    ``power``: the paired score response's power at the test's level (the MDB claims
    :data:`POWER_RANGE`); ``ratios``: each listed quantity's measured shift / printed bias
    (:data:`RATIO_RANGE` holds).  A power above the band (seen more easily than printed) and
    a shift smaller than printed, of either sign, err on the safe side: the claim holds,
    conservatively.  A power below the band or not measured, a shift larger than printed,
    in the other direction at its size, or not measured, fails.  ``detection=False``: the
    MDB claims no detection there (discover's clock rule refuses the effect at that size,
    :func:`clock_rule`): the biases alone are judged.
    """
    safe = []
    if detection and not (np.isfinite(power) and power >= POWER_RANGE[0]):
        return "fails", []
    if detection and power > POWER_RANGE[1]:
        safe.append("seen more easily than printed")
    small = False
    for r in ratios:
        if not np.isfinite(r) or r > RATIO_RANGE[1] or r <= -RATIO_RANGE[0]:
            return "fails", []
        small = small or r < RATIO_RANGE[0]
    if small:
        safe.append("moved less than printed")
    return ("conservative" if safe else "holds"), safe


def clock_rule(entry: dict[str, Any], param: str, size: float, delta: np.ndarray,
               clock_check=None) -> dict[str, Any] | None:
    """Whether discover's clock rule refuses the twin's injection on the user's bag.

    ``None`` for a row the rule does not mark (``refused_beside_clock``,
    :func:`~stellar_cal_ros.diagnosis.auto._refused_rows`).  Else ``{"refuses": bool or
    None, "size", "from", "p_value"}``: at the size the row was checked at
    (``at_mdb``: its printed MDB, that sign) its answer (``from`` "at_mdb"); at another
    size (a twin of a round that did not fit is injected at the MDB for residuals as
    stated, :func:`twin_scale`) the rule asked again of ``clock_check(effect, delta)`` (the
    clock test of the final model's run on the user's bag with the effect at the twin's
    size; ``from`` "twin's size"), else not known (``refuses`` ``None``, ``from`` "not
    checked": the answer at the MDB is not the one at another size -- dt_step s23:
    gyro_misalignment e02 refused at -16.5 arcsec, not at -999 arcsec).
    """
    mark = entry.get("refused_beside_clock")
    if not mark:
        return None
    from stellar_cal_ros.diagnosis import clock
    from stellar_cal_ros.diagnosis.discover import ALPHA

    key = "+" if size > 0 else "-"
    at = (mark.get("at_mdb") or {}).get(param) or {}
    p_at = ((mark.get("at_mdb_p_value") or {}).get(param) or {}).get(key)
    mdb = (mark.get("at_mdb_size") or {}).get(param)
    same = mdb is not None and np.isclose(abs(size), float(mdb), rtol=1e-9)
    if not same and clock_check is not None:
        ticks = clock_check(entry["effect"], delta)
        if ticks is not None:
            return {"refuses": clock.refuses(entry["effect"], ticks, ALPHA),
                    "size": size, "from": "twin's size", "p_value": ticks.finding().p_value}
    if same:
        return {"refuses": at.get(key), "size": size, "from": "at_mdb", "p_value": p_at}
    return {"refuses": None, "size": size, "from": "not checked", "p_value": None}


def flagged(c) -> bool:
    """The round's decision flags candidate ``c``: significant, or 'implausible'.

    An implausible candidate is significant (:func:`~stellar_cal_ros.diagnosis.discover.
    decide`) at a size its physics rules out: the report says a structure with its
    pattern is there, from another cause -- the right call for an astrometric scale
    injected at a fraction of its physical size, and a detection all the same.
    """
    return bool(c is not None and (c.significant or c.status == "implausible"))


def _decision(c) -> dict[str, Any]:
    """What the round's decision saw on the injected bag (for the power benchmark)."""
    if c is None:
        return {"status": "absent", "reason": "", "p_adjusted": float("nan"),
                "lr_statistic": float("nan"), "lr_p": float("nan"),
                "score_statistic": float("nan"), "score_p": float("nan"),
                "score_local": False, "estimate": {}, "sigma_post": {},
                "explained": float("nan")}
    scr = c.screen
    return {"status": c.status, "reason": c.reason, "p_adjusted": c.p_adjusted,
            "lr_statistic": c.statistic, "lr_p": c.p_value,
            "score_statistic": scr.statistic if scr is not None else float("nan"),
            "score_p": scr.p_value if scr is not None else float("nan"),
            "score_local": bool(scr is not None and scr.local),
            "estimate": dict(c.estimate), "sigma_post": dict(c.sigma),
            "explained": c.explained}


def _shown(eid: str, param: str, value: float) -> str:
    from stellar_cal_ros.diagnosis.reliability import shown

    return shown(f"{eid}.{param}", value)


def describe(rec: dict[str, Any]) -> str:
    """One line of the verification."""
    from stellar_cal_ros.diagnosis.reliability import shown

    scale = rec.get("size_scale", 1.0)
    stated = ("" if scale == 1.0 else
              f" (the MDB restated at both signs by the probe runs, x{scale:.3g} the "
              "first-order size the biases are printed at)" if scale > 1.0 else
              f" (the MDB for residuals as stated, x{scale:.3g} the printed one: the twin "
              "fits, this round did not)")
    parts = [f"{rec['effect']} {rec['parameter']} = {rec['size_shown']}{stated}: "
             + _detection(rec)]
    twins = rec.get("twins", 1)
    free = rec.get("detection_on") == "noise-free twin"
    if np.isfinite(rec["noncentrality"]) and not free:
        parts.append(f"score response (paired{', mean' if twins > 1 else ''}) "
                     f"{rec['noncentrality']:.3g} (MDB claims "
                     f"{rec['expected_noncentrality']:.3g}: {rec['paired_power']:.0%} at the "
                     "test's level)")
    for c in rec["biases"]:
        q = c["quantity"]
        claim = (f"printed {shown(q, c['printed'])}" if "claimed" not in c else
                 "claimed at this size {} to {}: the first order and the probe's departure "
                 "as of second order".format(*(shown(q, v) for v in c["claimed"][::-1])))
        if c.get("judged") is False:
            claim += "; " + _unjudged(c, twins)
        if c.get("exact"):
            if misses_first_order(c["ratio"]):
                claim += (f": {c['ratio']:.2f}x, the printed first-order bias misses by more "
                          "than 30 %, the shift measured here is this bag's" + (
                              "" if scale == 1.0 else
                              f"; at the size it is printed for {shown(q, c['measured'] / scale)}"))
            parts.append(f"{q} moved {shown(q, c['measured'])} on the noise-free twin "
                         f"({claim})")
            continue
        parts.append(f"{q} moved {shown(q, c['measured'])}"
                     f"{' (mean)' if twins > 1 else ''} ({claim})")
    if rec.get("verdict") == "cannot be judged":
        return "; ".join(parts) + (f" -> cannot be judged with {_twins(twins)} "
                                   f"({', '.join(rec['unjudged'])}); the rest holds"
                                   + _edge(rec))
    if not rec["holds"]:
        weak = (free and not rec.get("refused_by_clock")
                and not rec["paired_power"] >= POWER_RANGE[0])
        return "; ".join(parts) + " -> DOES NOT HOLD" + (
            f": at its printed MDB this bag gives the test {rec['paired_power']:.0%} power "
            "(the MDB claims 80 %)" if weak and np.isfinite(rec["paired_power"]) else
            ": the noise-free twin gave no score response" if weak else "") + _edge(rec)
    if rec.get("refused_by_clock"):
        return "; ".join(parts) + (" -> the biases hold" + _edge(rec) if rec["biases"]
                                   else "")
    safe = rec.get("conservative") or []
    return "; ".join(parts) + (f" -> holds (conservative: {', '.join(safe)})" if safe
                               else " -> holds") + _edge(rec)


def _edge(rec: dict[str, Any]) -> str:
    """The clause of a verdict its twins leave at the band's edge (:func:`undecided`)."""
    edge = rec.get("at_edge")
    if not edge:
        return ""
    return (f" (at the band's edge on {_twins(rec['twins'])}, the most: the 95 % interval of "
            f"{', '.join(edge)}'s mean ratio holds 1.3 or -0.7)")


def _twins(n: int) -> str:
    return "one twin" if n == 1 else f"{n} twins"


def _unjudged(c: dict[str, Any], twins: int) -> str:
    """The clause of a quantity whose twin-to-twin spread the ± 30 % band cannot judge."""
    return (f"cannot be judged with {_twins(twins)}: spread {c['spread'] / c['sigma']:.2g} σ "
            f"against a claim of {abs(c['printed']) / c['sigma']:.2g} σ")


def _detection(rec: dict[str, Any]) -> str:
    """What the twins' rounds did with the effect, and discover's clock rule on the bag."""
    from stellar_cal_ros.diagnosis.clock import p_text

    twins = rec.get("twins", 1)
    if rec.get("detection_on") == "noise-free twin":
        where = holder = _free_detection(rec)
    else:
        seen = ("found" if rec["found"] else "missed") if twins == 1 else (
            f"found on {rec['found_on']} of {twins} twins" if rec["found_on"] else
            f"missed on {twins} twins")
        where = f"{seen} on the twin" if twins == 1 else seen
        holder = ("the twin, which holds no clock, " + ("found" if rec["found"] else "missed")
                  + " it" if twins == 1 else f"the twins, which hold no clock: {seen}")
    rule = rec.get("clock_rule")
    if not rule:
        return where
    at = "at its MDB" if rule["from"] == "at_mdb" else "at this size"
    p = "" if rule.get("p_value") is None else ", " + p_text(rule["p_value"])
    if rule["refuses"]:
        return (f"refused by the clock rule (not a miss): on this bag the stars' remainder "
                f"along their motion stays a clock's {at}{p}, and discover adds no gyro rate "
                f"effect beside it; {holder} (not counted as a detection)")
    if rule["refuses"] is None:
        return f"{where} (the clock rule {at}: not checked)"
    return (f"{where} (the clock rule lets this sign through {at}{p}: the "
            "remainder is no longer a clock's)")


def _free_detection(rec: dict[str, Any]) -> str:
    """The detection clause of a row judged on the noise-free twin pair (its exact λ)."""
    lam, lam0 = rec["noncentrality"], rec.get("expected_noncentrality")
    out = (f"score response {lam:.3g} on the noise-free twin" + (
        f" (the MDB claims {lam0:.3g})" if lam0 is not None else "")
           + (f": {rec['paired_power']:.0%} power at the test's level"
              if np.isfinite(rec["paired_power"]) else ": not measured"))
    twins = rec.get("twins", 0)
    if twins:
        out += (f"; found on {rec['found_on']} of {_twins(twins)}" if rec["found_on"] else
                f"; missed on {_twins(twins)}") + (
            f" (noisy, their mean response {rec['twins_noncentrality']:.3g})"
            if np.isfinite(rec.get("twins_noncentrality", np.nan)) else " (noisy)")
    return out


def noise_check_line(check: dict[str, Any] | None) -> str | None:
    """The printed line of :func:`noise_check`."""
    if not check:
        return None
    return (f"verify: noise check on the clean noisy twin (seed {check['seed']}): the "
            f"candidates' score statistics sum to {check['statistic']:.1f} for "
            f"{check['dof']} dof (x{check['ratio']:.2f}), the smallest test's p x "
            f"{len(check['effects'])} = {check['smallest_p']:.2g}: "
            + ("the noise the powers are computed with holds on this bag's twin"
               if check["holds"] else
               "a candidate false-alarms on the clean twin: the powers printed assume a "
               "noise this bag's twin does not hold"))
