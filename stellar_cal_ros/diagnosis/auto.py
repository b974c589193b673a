"""``stellar-cal diagnose --auto`` (``stellar-cal discover``): stepwise selection of effects.

Each round is a diagnosis round (:func:`~stellar_cal_ros.diagnosis.discover.rank_round`):
the current model and every candidate re-run from the same start values, concurrently, and
in the same batch the runs that check what was added before.  One change per round, in
this order:

1. **drop** — an effect added in an earlier round that is no longer needed: the model
   without it, tested against the model with it by the same quasi-likelihood ratio, is not
   significantly worse (Bonferroni over the effects checked).  A look-alike added before
   the real cause was found (an aberration scale fitted to a gyro scale factor's pattern)
   goes here.  A dropped effect is not added again.
2. **exchange** — an added effect ``x`` replaced by a *rival*: a candidate that was
   significant alone in the round ``x`` was added, with a score at least
   :data:`RIVAL_SCORE` of ``x``'s (a near tie).  The model with the rival instead of ``x``
   (and of the effect added with it, :data:`ADDED_WITH`) is kept when it predicts the
   evaluation window better (higher prequential log-likelihood: held-out predictions, so
   the extra parameters of a flexible effect are no advantage) and the two are nested
   alike (:func:`_refused`): the rival no longer significant once ``x`` is in (this round's
   candidate), and ``x`` not significant beside the rival.  A rival still significant
   beside ``x`` is a candidate of its own (the add rule, then ``x``'s drop check); an ``x``
   significant beside the rival explains what the rival does not.  Each pair is tried once
   per model (again after the model has changed: a rival can lose while a third effect is
   still missing).  Neither significant beside the other (:func:`_tie`) means this motion
   cannot tell them apart: the one kept is named with the other (``ties`` in
   ``diagnosis.json``).
3. **add** — the top candidate: significant after Bonferroni and removing a real part of
   the excess variance, the rule of a single ``diagnose``.  Every other candidate is tested
   again in the next round, so an effect that only copied part of the real cause's pattern
   is not added once the cause is in the model.
   When a remainder shaped like a mount bending with gravity (outside the library) is
   significant after an add (:mod:`~stellar_cal_ros.diagnosis.flexure`), the effect just
   added is tested beyond a flexure: its ratio with a flexure fitted beside it in both
   models (:func:`~stellar_cal_ros.diagnosis.flexure.beyond`; one run: the model before it
   with the probe).  If it explains the data beyond the flexure, the remainder may be a
   library effect still missing (a gyro scale factor is ~98 % a flexure on steps about the
   IMU axes) and the next round goes on as usual.  If not, it is flagged as standing in for
   the flexure, and from then on a candidate that may stand in for one (not a camera
   effect) is added only if it explains the data beyond the flexure (two runs of its
   model).  (A mount flexure: gyro_scale_factor is added, flagged, and gyro_misalignment,
   which would absorb the remainder next, is not.)  A remainder that a later add leaves
   insignificant is not reported (it was that effect's) unless the test with that add in
   the model could not have seen a flexure of the size the remainder was (its MDB above
   it, :func:`~stellar_cal_ros.diagnosis.flexure.alias`; no run): then the two are not
   told apart by this motion, the add is marked "could be a mount flexure (outside the
   library): this motion cannot separate them" (a mount flexure beside a true gyro scale
   factor: gyro_misalignment) and the remainder stays the first 'unexplained' line.
4. **stop** when none of these applies (or after ``max_rounds`` rounds).

The next round starts the effects the discovery added from the chosen run's estimates and
everything else from the user's calibration (:func:`restart`); its re-run of the new model
is its reference.  Only statistics are kept per run; the residual tables kept are those of
the first and the newest model (the report's panels and the structure tests).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from stellar_cal_ros.core import distributions as dist
from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.diagnosis import (
    clock,
    flexure,
    installation_step,
    leads,
    rolling,
    screening,
    slew_steps,
)
from stellar_cal_ros.diagnosis.discover import (
    ALPHA,
    MIN_EXPLAINED,
    PHYSICAL_TOL_FRACTION,
    CandidateResult,
    Reference,
    Round,
    candidate_prior,
    method_spec,
    prior_uncertain,
    rank_round,
    rerun_prior,
    seen_dof,
)
from stellar_cal_ros.diagnosis.noise import check_noise, stated_scales
from stellar_cal_ros.diagnosis.output import finish, progress_printer, write_report
from stellar_cal_ros.diagnosis.parallel import Task, open_runner
from stellar_cal_ros.diagnosis.printing import describe
from stellar_cal_ros.diagnosis.runstats import RunSummary
from stellar_cal_ros.effects import registry
from stellar_cal_ros.io.calibration import Calibration, save_calibration
from stellar_cal_ros.methods.replay import BagData

#: at most this many rivals of an added effect are tried in its place: candidates
#: significant alone in its round whose score was at least RIVAL_SCORE of its score
MAX_RIVALS = 2
RIVAL_SCORE = 0.5
#: an effect added together with another the model lacks, estimated beside it and never
#: dropped while it is in: clock_drift's rate counts from its reference stamp, where
#: without time_offset the clocks' offset is 0 by assumption.  A real offset c there goes
#: into the rate (about 1.5 c / T over T s: +25 us, +0.13 ppm at 300 s, 3σ of the rate
#: alone) and the rate's σ alone (0.042 ppm on sky_clock_drift) is the σ given that
#: assumption; with the offset free it is 0.072 ppm (correlation 0.81), the rate unbiased
#: whatever the offset (H208, doc/benchmarks.md).  ``path[].added.with`` names it.
ADDED_WITH = {"clock_drift": "time_offset"}
#: what a stop names when a rate-shaped candidate was refused beside a clock's remainder
CLOCK_REMAINDER = ("the clock-shaped remainder along the stars' motion", "a drifting clock")
#: ... and beside an attitude step (a knock) it explains nothing before
STEP_REMAINDER = ("what the attitude step leaves", "an attitude step")
#: the level of the step test over the frames before the window (:func:`_step_before`): on
#: psce its moving frames hold the slews' ends, where the rate steps, and 4 of 23 bags
#: without a knock fired at 1 % there (unseen cases rows, columns, flex20 s22 and
#: mag_faint_over2 s21: p 7.2e-4 to 7.2e-3, chi2_3 at most 28.7, at the slew ending near
#: 60 s); knock_gsf_run20's 20-arcsec knock: chi2_3 2204-3730 (s21-s24)
STEP_BEFORE_ALPHA = 1e-6


def _verdict(c: CandidateResult, top: CandidateResult | None) -> str:
    """Why a candidate was not added this round."""
    if c.status == "ranked":
        if c.significant_alone:
            return (f"significant alone (p = {c.p_adjusted:.2g}) but behind "
                    f"{top.effect if top else 'a change of the model'}: tested again next round")
        if c.p_adjusted < ALPHA and c.explained < 0:  # it fits worse: "removes only -21%"
            worse = f"{-c.explained:.0%}" if -c.explained >= 0.005 else f"{-c.explained:.2%}"
            return (f"leaves {worse} more excess variance than the model without "
                    f"it (it must remove >= {MIN_EXPLAINED:.0%}; p = {c.p_adjusted:.2g})")
        if c.p_adjusted < ALPHA:
            return (f"removes only {c.explained:.0%} of the excess variance "
                    f"(< {MIN_EXPLAINED:.0%}; p = {c.p_adjusted:.2g})")
        return f"not significant (p = {c.p_adjusted:.2g})"
    return c.reason or c.status


def _estimates(run: RunSummary, effect_id: str) -> dict[str, list[float]]:
    """``{param: [value, sigma]}`` of one effect in a run."""
    sl = run.block(effect_id)
    names = registry.create(effect_id).parameter_names
    return {n: [float(v), float(s)] for n, v, s in zip(names, run.theta[sl], run.sigma[sl],
                                                        strict=True)}


def without(prior: Calibration, effects: list[str], original: Calibration) -> Calibration:
    """``prior`` with ``effects`` back at their values in ``original`` (removed, not fixed).

    An effect left out of a model keeps whatever value its start calibration holds (a
    camera entry, an ``effects`` block the star model applies as fixed): removing one means
    restoring the value it had before the discovery estimated it.
    """
    out = copy.deepcopy(prior)
    for effect_id in effects:
        eff = registry.create(effect_id)
        value, sigma = eff.initial(original)
        eff.store(value, sigma, out)
        if effect_id not in (original.effects or {}):
            out.effects.pop(effect_id, None)
    return out


def restart(chosen: Calibration, users: tuple[str, ...], original: Calibration
            ) -> Calibration:
    """The next round's start: the chosen run's added effects, the user's values otherwise.

    ``users``: the method's baseline and the user's ``--effects`` (installation, principal
    point, focal length, ...): they start again from the user's calibration; only the
    effects the discovery added keep the values the chosen run estimated (a large time
    offset must not be lost again).  Restarting them from the chosen run instead would let
    a round's re-runs forget the user's prior: an effect missing so far is absorbed by a
    combination of the user's parameters
    (an image-plane tilt τ by a principal-point shift f·τ and an installation rotation τ,
    exact to first order), and from those absorbed values the augmented run cannot tell the
    tilt apart (measured: Λ = −1.3 and τ = (1.2, 0.3) mrad against a true (10, −8) mrad;
    from the user's values Λ = +78 and τ = (10.4, −8.2) ± 0.6 mrad, doc/benchmarks.md).
    """
    return without(chosen, list(users), original)


@dataclass
class _State:
    """The model as the stepwise selection changes it."""

    extra: list[str]  #: effects beyond the baseline, in the order added
    user: tuple[str, ...]  #: the user's --effects (never dropped)
    start: Calibration
    rivals: dict[str, list[str]] = field(default_factory=dict)
    #: an added effect → the one added with it (:data:`ADDED_WITH`), which an exchange
    #: takes out with it
    partners: dict[str, str] = field(default_factory=dict)
    dropped: dict[str, str] = field(default_factory=dict)  #: effect → why
    #: exchanges tried: (out, in, the model then); retried once the model has changed
    tried: set[tuple[str, str, frozenset]] = field(default_factory=set)
    last: str = ""  #: the effect changed last (not checked again at once)
    #: the flexure-shaped test after each add: (its result, the effects added by then)
    remainders: list[tuple[dict | None, list[str]]] = field(default_factory=list)
    #: a flexure-shaped remainder was significant after an add: from then on a non-camera
    #: candidate is added only if it explains the data beyond the flexure direction
    outside: bool = False
    #: the prior of the latest round's runs (the flexure test of the model before an add)
    prior: Calibration | None = None
    #: indexes into ``remainders`` of the tests after an add that took up a significant
    #: remainder but explains nothing beyond a flexure either (the two not told apart)
    aliased: set[int] = field(default_factory=set)
    #: the latest round's outside-library fits made by :func:`_top` (``gravity``: one run)
    lead: dict[str, dict | None] = field(default_factory=dict)
    #: the latest round's temperature field where it was not testable (its MDB above a
    #: plausible mount's): the numbers of its line (:func:`~.leads.temperature_of`)
    untestable: dict[str, Any] = field(default_factory=dict)
    #: the latest round's candidates tested beside a lead: effect → lead → its beyond test
    beside: dict[str, dict[str, dict | None]] = field(default_factory=dict)
    #: effects added at their physical size beside a clock's remainder (:func:`_at_size`):
    #: the excess they are measured against is the clock's, so no explained floor keeps or
    #: drops them; effect → the estimate's fraction of its physical value
    at_size: dict[str, float] = field(default_factory=dict)
    #: effects added beside an attitude step that hid them (:func:`_by_step`): the excess
    #: is the step's, so no explained floor keeps or drops them; effect → the ratio on the
    #: window's frames before the step and after it
    before_step: dict[str, dict] = field(default_factory=dict)
    #: the latest :func:`_top`'s candidates a step hid that explain the frames before it
    by_step: dict[str, dict] = field(default_factory=dict)
    #: ... and the gyro rate candidates significant alone that explain them too
    passed_step: dict[str, dict] = field(default_factory=dict)
    #: the latest round's clock test (:func:`_clock_of`; ``False``: none could be made),
    #: ``None`` until made: the rule that refuses a rate candidate beside a clock's
    #: remainder (:func:`~stellar_cal_ros.diagnosis.clock.refuses`) marks the final hiding rows
    ticks: Any = None
    #: an effect in the model → the rival this motion does not tell from it (:func:`_tie`)
    ties: dict[str, dict] = field(default_factory=dict)
    #: the latest :func:`_top`'s candidates judged beside the step fitted as a nuisance
    #: (:func:`_beside_knock`) and found needed: effect → (the test, its run with the step)
    with_step: dict[str, tuple[dict, RunSummary]] = field(default_factory=dict)
    #: the latest :func:`_top`'s runs of the model with the step alone (made once a round)
    step_alone: dict[str, Any] = field(default_factory=dict)
    #: the step's line from the round its nuisance entered the model (:func:`_write` says
    #: it: the final model's own test no longer sees the step it fits)
    step_line: dict[str, Any] | None = None
    #: the latest :func:`_top`'s slews and the model with their steps alone
    #: (:func:`_beside_slews`, made once a round)
    slews: dict[str, Any] = field(default_factory=dict)

    def checkable(self) -> list[str]:
        """Added effects whose need is tested this round.

        Not one added with another that is still in the model (:data:`ADDED_WITH`).
        """
        return [e for e in self.shown() if e not in self.user and e != self.last
                and not any(ADDED_WITH.get(x) == e for x in self.extra)]

    def with_partner(self, x: str) -> list[str]:
        """``x`` and the effect added with it, if that one came in with it (:data:`ADDED_WITH`).

        What a rival replaces: the partner is in the model for ``x``'s sake, and a rival
        compared with ``x`` while the partner stays is compared with ``x``'s remainder
        beside it (unseen case ``sky_clock_drift3`` s21: time_offset kept the drift's mean
        −1.3 ms, and refraction, significant beside clock_drift at p 0, took its place).
        """
        return [x] + ([self.partners[x]] if x in self.partners else [])

    def shown(self) -> list[str]:
        """The effects beyond the baseline but the step's nuisance (never in an output)."""
        return [e for e in self.extra if e != installation_step.STEP_ID]


def _checks(state: _State, prior: Calibration, original: Calibration,
            pool: list[str]) -> list[Task]:
    """Runs without each added effect, and with each untried rival in its place."""
    tasks = []
    for x in state.checkable():
        rest = tuple(e for e in state.extra if e != x)
        tasks.append(Task(f"without {x}", without(prior, [x], original), rest, cost=1.0))
    for x in [e for e in state.extra if e not in state.user]:
        out = state.with_partner(x)
        rest = tuple(e for e in state.extra if e not in out)
        for y in state.rivals.get(x, []):
            if (x, y, frozenset(state.extra)) in state.tried or y in state.extra \
                    or y not in pool:
                continue
            tasks.append(Task(f"{y} for {x}", candidate_prior(
                without(prior, out, original), y, original), rest + (y,), cost=1.5,
                candidate=True))
    return tasks


def _decide_checks(state: _State, base: RunSummary, extras: dict[str, RunSummary],
                   results: list[CandidateResult] = ()
                   ) -> tuple[str, str, str, RunSummary | None, dict[str, Any]]:
    """(action, removed, added, run to continue from, details) from the check runs.

    ``results``: this round's candidates (a rival tested beside the effect it was tried
    in place of: whether the two are told apart, :func:`_tie`).
    """
    checks = {k[len("without "):]: v for k, v in extras.items()
              if k.startswith("without ") and v.ok}
    worst, details = None, {}
    for x, run in checks.items():
        stat, p, expl = Reference.of(run).compare(base, seen_dof(base, x))
        p_adj = min(1.0, p * len(checks))
        needed = p_adj < ALPHA and (not expl < MIN_EXPLAINED or x in state.at_size
                                    or x in state.before_step)
        details[x] = {"score": stat, "p_value": p_adj, "explained_fraction": expl,
                      "needed": needed}
        if not needed and (worst is None or p_adj > details[worst]["p_value"]):
            worst = x
    if worst is not None:
        return "drop", worst, "", checks[worst], details
    ref = Reference.of(base)
    best, best_gain = None, 0.0
    for key, run in extras.items():
        if " for " not in key or not run.ok:
            continue
        y, x = key.split(" for ")
        state.tried.add((x, y, frozenset(state.extra)))
        gain = 2.0 * (run.window["log_likelihood"] - ref.log_likelihood) / ref.dispersion
        details[key] = {"score": gain}
        c = next((c for c in results if c.effect == y), None)
        # (x beside the rival: x and the partner its run was made without)
        dof = sum(seen_dof(base, e) for e in state.with_partner(x))
        tie = _tie(x, gain, c, dof)
        if tie is not None:
            details[key]["tie"] = tie
        refused = _refused(x, gain, c, dof) if gain > 0.0 and tie is None else ""
        if refused:
            details[key]["refused"] = refused
        elif gain > best_gain:
            best, best_gain = key, gain
    for key in (k for k in details if " for " in k and "tie" in details[k]):
        y, x = key.split(" for ")
        kept, other = (y, x) if key == best else (x, y)
        state.ties[kept] = {"with": other, **details[key]["tie"]}
    if best is not None:
        y, x = best.split(" for ")
        return "exchange", x, y, extras[best], details
    return "", "", "", None, details


def _refused(x: str, gain: float, c: CandidateResult | None, dof: float) -> str:
    """Why the rival ``c`` that predicts better than ``x`` (``gain`` > 0) does not replace it.

    An exchange puts the rival in ``x``'s place without the add's tests and drops ``x`` for
    good, so it is made only where the two explain the same part of the data: the rival no
    longer significant once ``x`` is in (the add rule's own test, this round's candidate
    ``c``), and ``x`` not significant beside the rival (:func:`_beside_rival`).  A rival
    significant beside ``x`` explains more than ``x``'s part: it is a candidate of its own,
    added by the add rule and its gates, after which ``x`` is checked beside it (unseen case
    ``sky_clock_drift3`` s21 on 8075edd: refraction, p 0 beside clock_drift, was exchanged
    for it, and the drift was missed).  ``x`` significant beside the rival explains what the
    rival does not: dropping it loses that.  Empty (the gain decides) where neither holds,
    or where ``c`` is not a ranked or screened-out candidate beside ``x`` (not testable,
    implausible, failed: no test of its own there).
    """
    if c is None:
        return ""
    if c.significant_alone:
        return (f"significant beside {x} (p = {c.p_adjusted:.2g}): a candidate of its own, "
                f"not {x}'s stand-in")
    nested = _beside_rival(gain, c, dof)
    if nested is None or not nested["p_value"] < ALPHA:
        return ""
    return (f"{x} is significant beside it ({nested['beside_rival']:.3g} on {dof:.3g} dof, "
            f"p = {nested['p_value']:.2g}): {x} explains what it does not")


def _beside_rival(gain: float, c: CandidateResult, dof: float) -> dict[str, Any] | None:
    """``x`` beside its rival ``c``: Λ_{y|x} − ``gain`` on ``dof`` (:func:`_tie`).

    Λ_{y|x}: the rival's statistic beside the model that holds ``x`` (this round's
    candidate: its ratio, or its score where it was screened out); None where it has none.
    """
    if c.status not in ("ranked", "screened_out"):
        return None
    beside = c.statistic if c.status == "ranked" or c.screen is None else c.screen.statistic
    if not math.isfinite(beside):
        return None
    stat = max(beside, 0.0) - gain
    return {"rival_beside": beside, "beside_rival": stat,
            "p_value": float(dist.chi2.sf(max(stat, 0.0), dof)), "dof": dof}


def _tie(x: str, gain: float, c: CandidateResult | None, dof: float
         ) -> dict[str, Any] | None:
    """Whether this motion cannot tell ``x`` (in the model) from its rival ``c``.

    ``gain``: the rival's ratio in place of ``x`` (Λ_y − Λ_x, the exchange's run).  The
    rival beside ``x`` is this round's candidate ``c``; ``x`` beside the rival is then
    Λ_{y|x} − gain (the union model's ratio against the rival's, no run).  When neither is
    significant the two explain the same part of the data: the one kept is named with the
    other (a gyro scale factor sx 47.8 ppm on psce rotations: gyro_misalignment's span
    holds 99.7 % of its information, and 5 of 15 twins added gyro_misalignment, silently).

    ``dof``: the directions of ``x`` the data sees beside the model (:func:`seen_dof`), not
    its parameter count: x beside the rival is χ² on those (those the rival also spans
    count too, so the test errs towards a tie).  On the nominal count a gyro misalignment
    (3 of 6 directions absorbed by the installation) was called a tie at p 0.038 / 0.050
    (``twin_gm2`` s23 / s21, misalignment injected): 0.0051 / 0.0062 on its 3.24 / 3.10.
    """
    if c is None or c.significant_alone:
        return None
    nested = _beside_rival(gain, c, dof)
    if nested is None or nested["p_value"] < ALPHA:
        return None  # (below ALPHA: x explains what the rival does not)
    return nested


def _early_probe(early: dict[str, Any], runs) -> Any:
    """The probe run a round's ``beside`` started for its flexure test, else None.

    (None also when it ran with other noise scales than the runs' now.)
    """
    return early.get("probe") if early.get("noise") is runs.noise else None


def discover(bag: str | Path | BagData, calibration: Calibration, method: str,
             effects: list[str], output_dir: str | Path, max_rounds: int = 8,
             **options: Any) -> dict[str, Any]:
    """Change the model one effect at a time until nothing is significant.

    Writes ``diagnosis.json`` (the last round's diagnosis plus ``path``, ``added``,
    ``final_estimates``, ``rejected`` and ``reliability``), ``calibration.yaml`` (the final
    model's calibration) and the report to ``output_dir``; returns the summary.
    ``options``: ``candidates``, ``evaluation_fraction``, ``plots``, ``verbose``,
    ``workers``, ``scheduler``, ``noise``, ``noise_scales``, ``on_error`` as for
    :func:`~stellar_cal_ros.diagnosis.run.diagnose`.
    """
    candidates = options.get("candidates")
    evaluation_fraction = options.get("evaluation_fraction", 0.5)
    plots = options.get("plots", True)
    t_start = time.perf_counter()
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    spec = method_spec(method)
    tell = progress_printer(options.get("verbose", True))
    user = spec.beyond_baseline(effects)
    state = _State(list(user), user, calibration)
    path: list[dict[str, Any]] = []
    history: dict[str, list[tuple[int, CandidateResult]]] = {}
    first: RunSummary | None = None
    current: RunSummary | None = None
    stopped = ""
    local = True
    estimate = check_noise(options.get("noise", "estimate"))
    with open_runner(bag, spec, evaluation_fraction, options.get("workers", 0),
                     options.get("scheduler"), options.get("on_error", "raise")) as runs:
        runs.noise = options.get("noise_scales") or stated_scales(calibration)
        uncertain = prior_uncertain(calibration, set(spec.baseline) | set(user))
        r = Round(runs, spec, runs.facts(), evaluation_fraction, calibration,
                  tuple(uncertain), progress=tell)
        every = registry.available() if candidates is not None else registry.candidates()
        pool = uncertain + [e for e in every if e not in uncertain]
        if candidates is not None:
            pool = [e for e in pool if e in candidates]
        # offered once the clock test asks (:func:`_drift_asked`); a user's list holds them
        gated = [] if candidates is not None else [
            e for e in registry.offered_on(clock.OFFERED_ON) if e not in pool]
        for k in range(1, max_rounds + 1):
            t0 = time.perf_counter()
            model = list(spec.baseline) + state.shown()
            tell(f"round {k}: {', '.join(model)}; re-runs {runs.description}")
            prior = rerun_prior(state.start)
            state.lead, state.beside, state.untestable = {}, {}, {}
            # the flexure-shaped test of this round's model (below) needs one probe run of
            # it with the round's noise, not the candidates: it starts beside their runs
            # (Round.beside; in this process it runs when asked for, H273)
            flexed = bool(path and path[-1]["action"] == "add"
                          and flexure.may_stand_in(state.last)) or state.outside
            early: dict[str, Any] = {}

            def beside(base, candidates, prior=prior, extra=tuple(state.extra),
                       flexed=flexed, early=early):
                if flexed and early.get("noise") is not runs.noise:
                    early.update(noise=runs.noise,
                                 probe=flexure.probe_later(runs, prior, extra))

            r.beside = beside

            def ranked(measure_noise: bool, prior=prior, local=local):
                # (this round's model; made again with the gated effects: below)
                return rank_round(
                    r, state.start, state.extra, [e for e in pool if e not in state.dropped],
                    condition=False, more=_checks(state, prior, calibration, pool),
                    screen=local, measure_noise=measure_noise)

            base, results, extras = ranked(estimate and (
                r.noise is None or bool(r.noise.skipped or r.noise.imu_skipped
                                        or r.noise.beyond) or r.noise_stale))
            ticks, timing = _drift_asked(base, base.calibration or prior, runs.fraction) \
                if gated else (None, None)
            if ticks is not None:
                # the frames' clock drifts on this model: its rate is a candidate from now
                # on, and this round is made again with it (its noise as measured)
                tell(f"round {k}: the frames' clock drifts against the IMU (one rate fits "
                     f"{ticks.drift_rate * 1e6:.3g} +- {ticks.drift_sigma * 1e6:.2g} ppm, "
                     f"{ticks.rest_chi2:.1f} chi2 / {ticks.dof - 2} dof left): "
                     f"{', '.join(gated)} a candidate; the round again")
                pool.extend(gated)
                gated = []
                base, results, extras = ranked(False)
                timing = None  # (another run's)
            state.ticks = timing  # (:func:`_top` makes it if a rate candidate asks)
            here = None  # the flexure-shaped test of this round's model, when it ran
            if path and path[-1]["action"] == "add" and flexure.may_stand_in(state.last):
                # the effect just added may stand in for a mount bending with gravity
                # (outside the library): the remainder on this round's model (its run)
                tell(f"after {state.last}: testing for a gravity-shaped remainder (mount "
                     "flexure)")
                here = got = flexure.after_add(runs, base, prior, tuple(state.extra),
                                               _early_probe(early, runs))
                path[-1]["remainder"] = got
                state.remainders.append((got, [e for e in state.shown() if e not in state.user]))
                if flexure.significant([flexure.finding(got, [], len(state.remainders))],
                                       ALPHA):
                    # a flexure, or a library effect still missing (a gyro scale factor is
                    # ~98 % one on steps about the IMU axes): the effect just added decides.
                    # If it explains the data beyond a flexure, the remainder may be the
                    # next candidate; if not, it stands in for one, and so would the next
                    got["beyond"] = b = _stand_in(runs, state, path[-1], current, got)
                    state.outside = state.outside or bool(b and not b["needed"])
                else:
                    _alias(state, path)
            elif state.outside:
                here = flexure.after_add(runs, base, prior, tuple(state.extra),
                                         _early_probe(early, runs))
            r.beside = None
            state.prior = prior
            if current is not None and current is not first:
                current.residuals = None  # keep the first and the newest table only
            current = base
            first = first or base
            for c in results:
                history.setdefault(c.effect, []).append((k, c))
            action, removed, added, follow, checks = _decide_checks(state, base, extras,
                                                                    results)
            shutter = rolling.of_run(base, runs.fraction) if not action else None
            if shutter is not None and not shutter["p_value"] < ALPHA:
                shutter = None
            top, refused = (_top(runs, state, base, here, prior, calibration, results, tell,
                                 shutter, timing) if not action else (None, []))
            if not action and top is not None:
                action, added, follow = "add", top.effect, top.run
            knocked = None
            if not action and not refused and k < max_rounds:
                # nothing to add: a knock before the evaluation window, which no window
                # test sees, spoils every candidate's run (unseen case knock_gsf_run20)
                knocked = _step_before(runs, state, base, prior, tell, timing)
                if knocked is not None:
                    action, follow = "step", knocked.pop("run")
            step = _step(k, model, base, results, top if action == "add" else None,
                         time.perf_counter() - t0, 1 + len(extras) + sum(
                             c.run is not None for c in results))
            for c, b in refused:
                # significant alone, but only along the flexure (rolling shutter, outside-
                # library field, clock) the remainder showed
                step["beyond_remainder"] = {**step.get("beyond_remainder", {}), c.effect: b}
                what, fitted = b.get("remainder", ("the gravity-shaped remainder",
                                                   "a mount flexure"))
                if b.get("lead_size_px") is not None:
                    what = f"{what} ({b['lead_size_px']:.3g} px at most)"
                why = b.get("reason") or (
                    f"significant alone (p = {c.p_adjusted:.2g}) but explains nothing "
                    f"beyond {what} ({flexure.ratio_text(b, fitted)}"
                    f"{rolling.beside_text(b, fitted)}): not added")
                for rj in step["rejected"]:
                    if rj["effect"] == c.effect:
                        rj["reason"] = why
            if state.beside:
                # every candidate tested beside a lead: its ratio beyond it, added or not
                step["beside_leads"] = state.beside
            if state.untestable:  # (its progress line's numbers)
                step["temperature_not_testable"] = dict(state.untestable)
            if knocked is not None:
                step["step_before_window"] = knocked
            step.update({"action": action or "stop", "removed": removed or None,
                         "exchanged_for": added if action == "exchange" else None,
                         "checks": checks,
                         "noise": None if runs.noise is None else runs.noise.as_dict()})
            if not action and r.noise_stale and k < max_rounds and not (
                    len(path) > 1 and path[-2]["action"] == "noise"):
                # nothing significant, but the stars' σ scale of this model is not the one
                # applied, or an IMU scale the stars measured was measured on another model:
                # measure the noise again and test once more with it
                step["action"] = action = "noise"
                if r.imu_stale:
                    step["imu_again"] = list(r.imu_stale)
            path.append(step)
            rms = base.window["rms"]
            tell(f"round {k}: RMS u={rms[0]:.4f} v={rms[1]:.4f} px, loglik "
                 f"{base.window['log_likelihood']:.1f} -> {describe(step)} "
                 f"[{step['seconds']:.1f} s]")
            if not action:
                if refused:
                    what = refused[0][1].get("remainder", ("the gravity-shaped remainder",))
                    stopped = (f"stopped: nothing significant beyond {what[0]} ("
                               + ", ".join(c.effect for c, _ in refused)
                               + " only along it: not added; see 'unexplained')")
                break
            if k == max_rounds:
                stopped = (f"stopped after --max-rounds {max_rounds} before: "
                           f"{describe(step)}")
                step.update(action="stop", added=None, removed=None, exchanged_for=None)
                break
            if action == "noise":
                continue
            if action == "step":
                # the step stays in the model (hidden) from now on; its line is said at the end
                state.extra.append(installation_step.STEP_ID)
                state.step_line = knocked
            elif action == "drop":
                state.extra.remove(removed)
                state.dropped[removed] = (
                    f"added earlier, dropped in round {k}: the model without it is not "
                    f"significantly worse (p = {checks[removed]['p_value']:.2g})")
            elif action == "exchange":
                state.extra[state.extra.index(removed)] = added
                for e in state.with_partner(removed)[1:]:  # (its run was made without it)
                    state.extra.remove(e)
                state.partners.pop(removed, None)
                state.dropped[removed] = f"exchanged for {added} in round {k}"
            else:
                if added in state.with_step and installation_step.STEP_ID not in state.extra:
                    # judged beside the step fitted as a nuisance: the step stays in the
                    # model (hidden) from now on, and the added effect's estimate beside it
                    state.extra.append(installation_step.STEP_ID)
                    state.step_line = state.with_step[added][0]
                state.extra.append(added)
                partner = ADDED_WITH.get(added)
                if partner and partner not in state.extra and partner not in spec.baseline:
                    # estimated beside it from the next round on (not a candidate then)
                    state.extra.append(partner)
                    state.partners[added] = partner
                    step["added"]["with"] = partner
                if top.effect in state.passed_step:  # tested before a step (its line)
                    step["added"]["before_step"] = state.passed_step[added]
                if top.effect in state.with_step:  # the excess is the step's: no floor
                    state.before_step[added] = state.with_step[added][0]
                    step["added"]["beside_step"] = state.with_step[added][0]
                elif top.effect in state.by_step:  # one a step's remainder hid (:func:`_by_step`)
                    state.before_step[added] = state.by_step[added]
                    step["added"]["before_step"] = state.by_step[added]
                elif not top.significant_alone:  # one a clock's remainder hid (:func:`_at_size`)
                    eff = registry.create(added)
                    state.at_size[added] = next(iter(top.estimate.values())) / eff.physical_value
                    step["added"]["at_physical_size"] = state.at_size[added]
                # not those refused as a field's stand-in this round: the exchange
                # (prequential log-likelihood) does not ask the stand-in rule, and brought
                # one back (a 40″/g flexure: gyro_misalignment exchanged for the
                # gyro_scale_factor refused beside it)
                stand_ins = {c.effect for c, _ in refused}
                state.rivals[added] = [
                    c.effect for c in results if c is not top and c.significant_alone
                    and c.effect not in stand_ins
                    and c.statistic >= RIVAL_SCORE * top.statistic][:MAX_RIVALS]
            state.start = restart(follow.calibration, spec.baseline + state.user, calibration)
            # (an effect exchanged in is checked next round: the exchange compared it
            # with the effect it replaced, not with the model without either)
            state.last = added if action == "add" else removed
            # the run of the next model tells whether a local (score) test can screen
            # its candidates; if not, the next round re-runs them all at once
            local = screening.is_local(follow)
        check = None
        if options.get("verify"):
            def check(final_cal, entries):
                from stellar_cal_ros.diagnosis.runstats import load_bag
                from stellar_cal_ros.diagnosis.verify import TWINS, TWINS_MAX, verify

                tell("verify: the printed MDBs and biases on twins of this bag")
                model = list(spec.baseline) + state.shown()

                def clock_check(effect, delta):  # the clock rule at a twin's size, on the bag
                    return _clock_runs(runs, current, ((effect, tuple(delta.tolist())),))[0]

                return verify(load_bag(runs.bag), final_cal, method, model, entries,
                              options.get("verify_seed", 1), tell, evaluation_fraction,
                              clock_check, options.get("verify_signs", (1, -1)),
                              options.get("verify_twins") or 0,
                              options.get("verify_twins_max") or (
                                  TWINS_MAX if options.get("verify_twins") is None
                                  else max(options["verify_twins"], TWINS)))
        return _write(out, calibration, spec, state, path, history, first, current, results,
                      evaluation_fraction, plots, runs, stopped,
                      time.perf_counter() - t_start, r.noise, check)


def _stand_in(runs, state: _State, step: dict[str, Any], before: RunSummary | None,
              after: dict[str, float]) -> dict[str, Any] | None:
    """Whether the effect ``step`` added explains anything beyond a flexure.

    ``before``: the run of the model it was added to (its residuals kept: the previous
    round's base); ``after``: the flexure-shaped test of the model with it.  One run (the
    model before, with the probe).
    """
    if before is None or before.residuals is None or state.prior is None:
        return None
    x = step["added"]["effect"]
    without = flexure.after_add(runs, before, state.prior,
                                tuple(e for e in state.extra if e != x))
    return flexure.beyond(step["added"]["score"], registry.create(x).size,
                          Reference.of(before).dispersion, after, without)


def _alias(state: _State, path: list[dict[str, Any]]) -> None:
    """Mark the add that took up a significant gravity-shaped remainder if a flexure could too.

    ``path[-1]`` added the effect; the test after it (``state.remainders[-1]``) found
    nothing, the one after the add before it (``path[-2]``) a remainder.  When the test
    with the effect could not see a flexure of the size that remainder was
    (:func:`~stellar_cal_ros.diagnosis.flexure.alias`: its MDB above it; no run) the step
    gains ``could_be_flexure`` and the remainder is not taken as the effect's
    (``state.aliased``).
    """
    prev = path[-2].get("remainder") if len(path) > 1 and path[-2]["action"] == "add" else None
    got = state.remainders[-1][0]
    if not prev or "beyond" not in prev or got is None:
        return  # the remainder before this add was not significant (or not tested)
    a = flexure.alias(prev, got, len(state.remainders), ALPHA)
    if a is None:
        return
    a["text"] = flexure.alias_text(path[-1]["added"]["effect"], a)
    path[-1]["could_be_flexure"] = a
    state.aliased.add(len(state.remainders) - 1)


def _top(runs, state: _State, base: RunSummary, here: dict | None, prior: Calibration,
         calibration: Calibration, results: list[CandidateResult], tell,
         shutter: dict | None = None, timing=None
         ) -> tuple[CandidateResult | None, list[tuple[CandidateResult, dict]]]:
    """The candidate to add, and those refused as a flexure's (a rolling shutter's) stand-ins.

    The first candidate significant alone, except that once a flexure-shaped remainder
    was found (``state.outside``) a candidate that may stand in for a flexure is added only
    if it explains the data beyond it (:func:`~stellar_cal_ros.diagnosis.flexure.beyond`:
    its ratio beside a fitted flexure, two runs of its model); camera effects as always.
    ``shutter``: the current model's rolling-shutter fit when significant
    (:mod:`~stellar_cal_ros.diagnosis.rolling`): then every candidate is added only if it
    explains the data beyond that fit or the fit has vanished beside it
    (:func:`~stellar_cal_ros.diagnosis.rolling.stand_in`, one run of its model).
    ``timing``: ``base``'s clock test (:func:`_clock_of`) when the round made it already
    (:func:`_drift_asked`), else ``None``.
    """
    refused = []
    fields, along = None, {}  # the outside-library leads of the current model (and their
    # directions), once a candidate asks
    ticks = timing  # the current model's clock test, once a rate-shaped candidate asks
    knock, where = None, ""  # its installation step test, likewise (and its frames)
    frames = None  # its run's log-likelihood frame by frame, once a step's test asks
    order, hidden = [c for c in results if c.significant_alone], []
    state.by_step, state.passed_step, stepped = {}, {}, set()
    state.with_step, state.step_alone, state.slews = {}, {}, {}
    small = _by_step(results)  # significant, but removing little of the excess
    if small:
        knock, where = _knock_of(base, base.calibration or prior, runs.fraction)
        knock = knock or False
        if knock and knock.p_value < ALPHA and not where:
            # the excess is a step's the line says: those explaining the frames before it
            # are tested after those significant alone
            order.extend(small)
            stepped = {c.effect for c in small}
    for c in order:  # (grows once, by the candidates a clock's remainder hides: below)
        if c.effect in clock.RATE_ALIASES and ticks is None:
            # (kept for the hiding rows of the final model: :func:`_write`)
            ticks = state.ticks = _clock_of(base, base.calibration or prior,
                                            runs.fraction) or False
        if clock.refuses(c.effect, ticks, ALPHA):
            tell(f"{c.effect}: not added: the stars' remainder along their motion is a "
                 "clock's (it shrinks along a slew)")
            refused.append((c, {"clock": ticks.as_json(), "reason": _clock_reason(
                c, ticks), "remainder": CLOCK_REMAINDER}))
            if not hidden:
                # the excess is the clock's: an effect at its physical size, significant
                # but removing little of it, is tested after those significant alone
                hidden = _at_size(results)
                order.extend(hidden)
            continue
        if c.effect in clock.RATE_ALIASES or c.effect in stepped:
            if knock is None:
                knock, where = _knock_of(base, base.calibration or prior, runs.fraction)
                knock = knock or False
            if knock and knock.p_value < ALPHA:
                # the step fitted beside it (Bonferroni over the candidates judged so)
                tests = len(stepped | {x.effect for x in order
                                       if x.effect in clock.RATE_ALIASES})
                tell(f"{c.effect}: testing it beside the attitude step at t~{knock.t:.1f} s "
                     "(fitted)")
                b = _beside_knock(runs, state, base, prior, calibration, c, knock, where,
                                  tests)
                if b is None:  # the step is not the rival (a clock's step): before it
                    tell(f"{c.effect}: testing it before the attitude step at "
                         f"t~{knock.t:.1f} s")
                    b, frames = _after_knock(runs, state, base, prior, calibration, c,
                                             knock, frames,
                                             len(stepped) if c.effect in stepped else 0)
                elif not b:
                    b = None  # needed beside the step: on to the other tests
                if b is not None:
                    refused.append((c, b))
                    continue
        if c.effect in slew_steps.RIVALS and c.effect not in state.with_step:
            # (after the knock's rules: a knock during a slew is theirs, unseen case
            # knock_slew; one needed beside the knock fitted stays so)
            b = _beside_slews(runs, state, base, prior, calibration, c, len(
                {x.effect for x in order if x.effect in slew_steps.RIVALS}))
            if b is not None:
                tell(f"{c.effect}: not added: it explains nothing beside the attitude "
                     "steps fitted at each slew's start")
                refused.append((c, b))
                continue
        if fields is None:
            fields = leads.significant(leads.of_run(base, runs.fraction), ALPHA)
            # a candidate's fields are sized along this model's (one pattern, two runs)
            along = leads.directions(base, runs.fraction, fields)
        # a mount bending with gravity: a lead for a candidate that may stand in for one
        # (before an add: after one, the flexure-shaped test and ``state.outside`` decide)
        gravity = not state.outside and flexure.may_stand_in(c.effect)
        if gravity and "gravity" not in state.lead:
            if here is None:  # else the test after the add just made is this model's
                tell("testing for a gravity-shaped remainder (mount flexure) on "
                     f"{'+'.join(state.shown()) or 'the baseline'}")
            state.lead["gravity"] = leads.as_lead(here) if here is not None else \
                leads.gravity_of(runs, base, prior, tuple(state.extra))
        beside = dict(fields)
        if gravity:
            beside.update(leads.significant({"gravity": state.lead["gravity"]}, ALPHA))
        # a mount turning with the head temperature: a lead for the same candidates (a
        # slowly turning installation a gyro term or a bias walk may stand in for; unseen
        # case thermal_mount), where the temperature changes over the window
        if flexure.may_stand_in(c.effect):
            if "temperature" not in state.lead:  # (where its MDB is a plausible mount's)
                state.lead["temperature"] = leads.temperature_of(
                    runs, base, prior, tuple(state.extra), ALPHA, tell,
                    '+'.join(state.shown()) or 'the baseline', state.untestable)
            beside.update(leads.significant({"temperature": state.lead["temperature"]},
                                            ALPHA))
            if "temperature" in beside:  # a candidate's size along this model's axis
                along = dict(along, temperature=beside["temperature"]["direction"])
        if shutter is not None or beside:
            what = ", ".join(([rolling.REMAINDER[0]] if shutter is not None else [])
                             + [leads.NAMES[k][0] for k in beside])
            tell(f"{c.effect}: testing it beyond {what}")
            with_c = runs.on_bag(leads.candidate_on_bag, runs.spec,
                                 candidate_prior(prior, c.effect, calibration),
                                 tuple(state.extra) + (c.effect,), runs.fraction, runs.noise,
                                 runs.classes, "gravity" in beside, along,
                                 "temperature" in beside) or {}
            dispersion = Reference.of(base).dispersion
            b = None if shutter is None else rolling.stand_in(
                c, dispersion, with_c.get("rolling"), shutter, ALPHA)
            if shutter is not None and b is None and rolling.needs_without(
                    c, dispersion, with_c.get("rolling"), shutter, ALPHA):
                # kept beside it: is it needed once the fitted readout is out of the bag?
                tell(f"{c.effect}: testing it on the bag without the fitted readout")
                b = rolling.not_without(c, runs.on_bag(
                    rolling.ratio_without_on_bag, runs.spec, prior, tuple(state.extra),
                    runs.fraction, runs.noise, runs.classes, base.calibration,
                    shutter["coefficient"], shutter["axis"],
                    candidate_prior(prior, c.effect, calibration), c.effect,
                    c.seen_dof), shutter, ALPHA)
            # every lead it stands in for, not only the first (unseen case saturation s22:
            # image_plane_tilt refused beside the cells and the magnitude fields; the path
            # kept 'cells' alone, so the magnitude field's line was never printed)
            by = {}
            for kind, lead in beside.items():
                state.beside.setdefault(c.effect, {})[kind] = _beyond_lead(
                    c, dispersion, with_c.get(kind), lead)
                got = leads.stand_in(c, dispersion, with_c.get(kind), lead, kind, ALPHA)
                if got is not None:
                    by[kind] = got
            b = b or next(iter(by.values()), None)
            if by and list(by) != [b.get("lead")]:
                b = dict(b, leads=list(by))  # (absent where it would repeat ``lead``)
            if b is not None:
                refused.append((c, b))
                continue
        if c.effect in state.with_step:  # the estimate beside the step (its run)
            c = dataclasses.replace(c, run=state.with_step[c.effect][1])
        if not (state.outside and here is not None and flexure.may_stand_in(c.effect)):
            return c, refused
        tell(f"{c.effect}: testing it beyond the gravity-shaped remainder")
        effects = tuple(state.extra) + (c.effect,)
        with_c = runs.on_bag(flexure.pair_on_bag, runs.spec,
                             candidate_prior(prior, c.effect, calibration), effects,
                             runs.fraction, runs.noise, runs.classes)
        b = flexure.beyond(c.statistic, c.dof, Reference.of(base).dispersion, with_c, here)
        if b is None or b["needed"]:
            return c, refused
        refused.append((c, b))
    return None, refused


def _at_size(results: list[CandidateResult]) -> list[CandidateResult]:
    """Candidates significant at their physical size that remove too little of the excess.

    Asked once a clock's remainder (outside the library) was found on the current model
    (:func:`_top`): the excess residual variance is then mostly the clock's, and an effect
    whose size physics fixes (``Effect.physical_value``) can remove only a sliver of it
    however real it is (unseen case ``sky_clock_drift3``: aberration at 0.989x of its
    physical size, p 6.6e-34, removes 2 % of an excess the 0 -> 3 ms drift makes).  Its
    estimate within :data:`~stellar_cal_ros.diagnosis.discover.PHYSICAL_TOL_FRACTION` of
    the physical value is the evidence the explained floor stands for: a stand-in absorbing
    a sliver of another cause fits at a size of its own.
    """
    out = []
    for c in results:
        if c.significant_alone or c.status != "ranked" or not c.p_adjusted < ALPHA:
            continue
        phys = registry.create(c.effect).physical_value
        est = next(iter(c.estimate.values()), math.nan)
        if phys is not None and abs(est - phys) <= PHYSICAL_TOL_FRACTION * abs(phys):
            out.append(c)
    return out


def _by_step(results: list[CandidateResult]) -> list[CandidateResult]:
    """Candidates significant that remove too little of the excess: a step's, if one fires.

    Asked when the current model's attitude step test fires (:func:`_top`, the line's own
    test: at rest, or over all frames of a platform that never rests): the excess residual
    variance is then mostly the step's, and a library effect, however real, removes only a
    sliver of it (unseen case ``knock_gsf``: a 100-ppm gyro scale beside ``knock``'s 20″
    step, p 5.4e-50, removes 6 % of the excess).  Such a candidate is added if it explains
    the window's frames before the step (:func:`_after_knock`, Bonferroni over them), where
    the step leaves nothing; a stand-in for the step explains nothing there.
    """
    return [c for c in results if not c.significant_alone and c.status == "ranked"
            and c.p_adjusted < ALPHA and c.explained < MIN_EXPLAINED]


def _clock_of(base: RunSummary, calibration: Calibration, fraction: float):
    """The clock test (:func:`~stellar_cal_ros.diagnosis.clock.clock_change`) of ``base``."""
    if base.residuals is None:
        return None
    return clock.clock_test(base.residuals, calibration, fraction)


def _drift_asked(base: RunSummary, calibration: Calibration, fraction: float):
    """``(the clock test if it asks for a drifting clock's candidate else None, the test)``.

    :meth:`~stellar_cal_ros.diagnosis.clock.ClockChange.asks_drift` on the clock test, and
    again on the one the 'unexplained' lines judge (:func:`~.output.line_tests`: beside a
    wobble's periods where one is found, a wobble's turns read as a drift otherwise:
    unseen case ``wobble`` s23, 14.5 ppm).  Where ``base`` lost lock, the parts' change
    alone.  Not where the clock steps (:func:`~stellar_cal_ros.diagnosis.clock.steps_test`
    over the whole run: unseen case ``dt_step2``, two 2-ms steps that the window's two
    slews read as −18.6 ppm).  Asked each round until it asks: a model that fits costs the
    one clock test, returned second (:func:`_clock_of`'s: :func:`_top` asks it of the same run).
    """
    ticks = _clock_of(base, calibration, fraction)
    if ticks is None:
        return None, None
    if base.lost_lock and min(ticks.p_value, ticks.drift_p) < ALPHA:
        # lost on the way, the parts' offsets are the filter's catch-up as much as the
        # clock's (a 0 -> 30 ms drift: one rate leaves 12.7 chi2 / 3 dof, p 0.005): the
        # candidate's run says whether a rate holds
        return ticks, ticks
    if not ticks.asks_drift(ALPHA):
        return None, ticks
    # a clock that steps, more than once, reads as a drift in the window's few slews: the
    # run's every slew tells a staircase from a ramp (unseen case dt_step2)
    ticks.steps = clock.steps_test(base.residuals, calibration, ALPHA,
                                   "time_offset" in base.effects)
    if ticks.steps_line():
        return None, ticks
    from stellar_cal_ros.diagnosis.output import line_tests

    parts: dict[str, Any] = {}
    line_tests(base.residuals, calibration, fraction, parts, ticks,
               offset="time_offset" in base.effects)
    lines = parts.get("clock")
    return (lines if lines is not None and lines.asks_drift(ALPHA) else None), ticks


def _knock_of(base: RunSummary, calibration: Calibration, fraction: float):
    """The attitude step test of ``base`` (:func:`~.output.step_test`), a gyro rate rival.

    The line's test (at rest, or over all frames of a platform that never rests) when it
    fires or cannot rest; else over all frames, moving too, with the line's words for them
    (:data:`~.installation_step.MOVING`; else ``""``).  Where a platform slews, a knock and
    a clock's step are not told apart (the line is said at rest only), but both are
    outside the library, and a gyro rate candidate that only takes up what either leaves
    is refused alike (unseen cases ``knock_slew`` χ²₃ 1021 at 241.0 s, ``dt_step`` 6229; a
    true 300 ppm scale, ``gyro3_gsf``, 17.9, p 0.13; seed 21).  ``(None, "")`` without the
    residuals.
    """
    if base.residuals is None:
        return None, ""
    from stellar_cal_ros.diagnosis.output import step_test

    shared: dict[str, Any] = {}  # (the window's frame offsets: both tests')
    rest = step_test(base.residuals, calibration, fraction, shared=shared)
    if rest is None or not rest.at_rest or rest.p_value < ALPHA:
        return rest, ""  # (all its frames tested: the platform never rests; or the line's)
    return (step_test(base.residuals, calibration, fraction, everywhere=True, shared=shared),
            installation_step.MOVING)


def _step_before(runs, state: _State, base: RunSummary, prior: Calibration, tell,
                 timing=None) -> dict[str, Any] | None:
    """A knock before the evaluation window, fitted; ``None`` where there is none to fit.

    Asked where nothing else changes the model.  A knock before the window (unseen case
    ``knock_gsf_run20``: 20″ at 60 s of 300) leaves the window no step to test -- the
    filter took it into its attitude and installation before -- but every candidate's run
    takes part of it in its first half and carries that into the window (a true 100-ppm
    gyro scale 2 Δℓ −939 on seed 21, every candidate negative: nothing is significant).
    The step test over the frames before the window, moving or not
    (:func:`~.output.step_test`, ``before``; at :data:`STEP_BEFORE_ALPHA`: its null is
    heavier there than the line's), says when; the step is then fitted from
    that time on (:class:`~.installation_step.StepNuisance`, one run) and kept, hidden, in
    the model when it explains the window: its ratio ``2 Δℓ / dispersion`` against the
    current model, χ²₃ at ``ALPHA``.  Returned then: the test (``installation_step``,
    ``where``, ``statistic``, ``p_value``, ``dof``, ``step_fitted_arcsec``, ``step_time``)
    and its ``run``.  One step is fitted at most.

    Over moving frames the test's largest step may be the filter's answer to the knock,
    one frame after it, and its own rotation is not the knock's (``knock_gsf_run20`` seed
    21: the knock's first frame 59.5 s, where a slew starts, says the knock's −9.6, 17.4″;
    the filter over-answers, and the test's largest step is at 60.0 s: x 43.7, y 4.2,
    z 79.5 ± 0.8 / 5.9″).  So the step is fitted from zero (± 100″,
    :func:`~.installation_step.with_step` without the test) at the test's time and one frame
    before it, and the better window kept (``step_time``: the frames either side of it, s
    from the run's first frame): there −9.45, 17.3 ± 0.24″ from 59.25 s (2 Δℓ +32.6 over
    60.0 s's −8.4, 15.8; from the test's rotation ± 3σ, −7.8, 15.6).

    Not where the frames' clock steps there (``timing``: ``base``'s clock test; where it
    says the clock changes, its steps test over the run, :func:`~.clock.clock_steps_at`):
    a clock's step where a slew starts reads as an attitude step (unseen case ``dt_step2``
    s21, a 2-ms step at 119.8 s: "the tracker's installation steps at t~120.0 s by 6.32″",
    336 χ² / 3 dof, said first and fitted).
    """
    if base.residuals is None or installation_step.STEP_ID in state.extra:
        return None
    from stellar_cal_ros.diagnosis.output import step_test

    knock = step_test(base.residuals, base.calibration or prior, runs.fraction,
                      everywhere=True, before=True)
    if knock is None or not knock.p_value < STEP_BEFORE_ALPHA:
        return None
    said = clock.clock_steps_at(timing, base.residuals, base.calibration or prior, ALPHA,
                                "time_offset" in base.effects, knock.t_before, knock.t)
    if said is not None:
        tell(f"an attitude step before the evaluation window at t~{knock.t:.1f} s "
             f"({knock.chi2:.0f} chi2 / 3 dof) is the frames' clock's step "
             f"({said * 1e3:.3g} ms): not fitted")
        return None
    tell(f"an attitude step before the evaluation window at t~{knock.t:.1f} s "
         f"({knock.chi2:.0f} chi2 / 3 dof): fitting it")
    installation_step.register_step(runs)
    first = float(np.min(base.residuals["t"]))
    frame = knock.t - knock.t_before
    times = {"the step before the window": (knock.t_before, knock.t),
             "the step before the window, a frame earlier": (knock.t_before - frame,
                                                             knock.t_before)}
    got = runs.run_all([Task(key, installation_step.with_step(prior, first + 0.5 * sum(t)),
                             tuple(state.extra) + (installation_step.STEP_ID,))
                        for key, t in times.items()], None)
    fitted = [k for k in times if got[k].ok]
    if not fitted:
        return None
    key = max(fitted, key=lambda k: got[k].window["log_likelihood"])
    run = got[key]
    stat, p, _ = Reference.of(base).compare(run, 3)
    if not p < ALPHA:
        return None
    return {"installation_step": knock.as_json(), "where": installation_step.BEFORE,
            "statistic": stat, "p_value": p, "dof": 3,
            "step_fitted_arcsec": [float(x) for x in _step_fitted(run)[0]],
            "step_time": [float(x) for x in times[key]], "run": run}


def _after_knock(runs, state: _State, base: RunSummary, prior: Calibration,
                 calibration: Calibration, c: CandidateResult, knock, frames,
                 tests: int = 0):
    """Whether a rate-shaped candidate only takes up what an installation step leaves.

    The step (:mod:`~stellar_cal_ros.diagnosis.installation_step`, outside the library)
    fires on the current model ``base``.  The filter takes the jump into its attitude; as
    the platform turns, the attitude error that leaves grows with the angle turned, as a
    gyro rate error's does, so a gyro scale factor takes part of it (unseen case
    ``sway_knock``).  A gyro's error acts before the step as after it: the candidate's
    ratio on the window's frames before the step
    (:func:`~stellar_cal_ros.diagnosis.installation_step.before_and_after`: its run and
    the current model's with their frames' log-likelihood, two runs; ``frames``: the
    current model's, once made) must be significant at ``ALPHA``, else it is refused with
    its reason.  ``(refusal or None, frames)``; no refusal where the test cannot be made
    (fewer than :data:`~stellar_cal_ros.diagnosis.installation_step.MIN_BEFORE` window
    frames before the step).

    ``tests``: ``c`` is one of that many candidates the step hid (:func:`_by_step`): it is
    refused unless its ratio before the step is significant at ``ALPHA`` / ``tests``, also
    where that cannot be tested; if it is, ``state.by_step`` holds the ratios.
    """
    key = f"{c.effect}: its frames"
    tasks = [Task(key, candidate_prior(prior, c.effect, calibration),
                  tuple(state.extra) + (c.effect,), cost=1.5, candidate=True,
                  frame_loglik=True)]
    if frames is None:
        tasks.append(Task("current model: its frames", prior, tuple(state.extra),
                          frame_loglik=True))
    got = runs.run_all(tasks, None)
    if frames is None:
        done = got["current model: its frames"]
        frames = done.frame_loglik if done.ok else False
    run = got[key]
    stamp = float(min(base.residuals["t"])) + knock.t
    split = installation_step.before_and_after(
        frames if frames is not False else None, run.frame_loglik if run.ok else None,
        stamp, Reference.of(base).dispersion, c.dof)
    if tests:
        return _beside_step(state, c, knock, split, tests), frames
    if split is None or split["before"]["p_value"] < ALPHA:
        if split is not None:
            state.passed_step[c.effect] = split
        return None, frames
    a, b = split["before"], split["after"]
    reason = (f"significant alone (p = {c.p_adjusted:.2g}) but explains nothing before the "
              f"stars' attitude step at t~{knock.t:.1f} s on this model ({knock.chi2:.0f} "
              f"chi2 / 3 dof, the largest of {knock.candidates} frames): its ratio "
              f"{a['statistic']:.3g} for {c.dof} dof on the window's {a['frames']} frames "
              f"before it (p = {a['p_value']:.2g}), {b['statistic']:.3g} on the "
              f"{b['frames']} after; the filter takes the jump into its attitude and the "
              "error left grows with the angle turned, as a gyro rate error's would, but a "
              "gyro's error acts before the step as after it: a knock on the mount (or a "
              "clock that steps), outside the library; not added")
    return {"installation_step": knock.as_json(), **split, "reason": reason,
            "remainder": STEP_REMAINDER}, frames


def _beside_knock(runs, state: _State, base: RunSummary, prior: Calibration,
                  calibration: Calibration, c: CandidateResult, knock, where: str,
                  tests: int) -> dict | None:
    """A rate-shaped candidate judged beside the attitude step, the step fitted.

    The step (a knock, outside the library) fires on the current model ``base``: the
    installation rotated by a free ``δ`` from the step's time on
    (:class:`~stellar_cal_ros.diagnosis.installation_step.StepNuisance`, started at the
    step test's rotation ± 3 σ, :func:`~.installation_step.with_step`) is the
    rival of a candidate that may take up what the filter's catch-up leaves (a gyro
    scale factor on a swaying base, unseen case ``sway_knock``), and a candidate the step
    hid (:func:`_by_step`) is measured against the excess the step leaves.  Two runs
    (the step alone, made once a round, and the step with ``c``); ``c``'s ratio
    ``2 Δℓ / dispersion`` beside the step (the current model's dispersion), its χ²_dof
    tail × ``tests`` (Bonferroni over the candidates judged so).

    Returns ``None`` where the fitted step is not the rival: the step test said over all
    frames, moving or not (:data:`~.installation_step.MOVING`), still fires on the model
    with the step (unseen case ``dt_step``: a clock's step, χ²₃ 3598 after ``δ``; the
    caller then tests ``c`` before the step); ``{}`` where ``c`` is needed beside the step
    (``state.with_step`` holds its test and run: the discovery adds it and keeps the
    step, hidden, in the model); else the refusal with its reason.  One step is fitted
    at most: where the model holds it already, ``None`` (the test before the step).
    """
    if installation_step.STEP_ID in state.extra:
        return None
    at = state.step_alone.get("prior")
    if at is None:
        installation_step.register_step(runs)
        first = float(np.min(base.residuals["t"]))
        at = installation_step.with_step(prior, first + 0.5 * (knock.t + knock.t_before),
                                         knock)
        state.step_alone["prior"] = at
    key = f"{c.effect} beside the step"
    tasks = [Task(key, candidate_prior(at, c.effect, calibration),
                  tuple(state.extra) + (installation_step.STEP_ID, c.effect), cost=1.5,
                  candidate=True)]
    if "run" not in state.step_alone:
        tasks.append(Task("the step alone", at, tuple(state.extra)
                          + (installation_step.STEP_ID,), keep_residuals=bool(where)))
    got = runs.run_all(tasks, None)
    if "run" not in state.step_alone:
        alone = got["the step alone"]
        state.step_alone["run"] = alone if alone.ok else None
        after = None
        if alone.ok and where:
            after = _knock_of(alone, alone.calibration or prior, runs.fraction)[0]
            alone.residuals = None
        state.step_alone["still"] = after is not None and after.p_value < ALPHA
    alone, run = state.step_alone["run"], got[key]
    if alone is None or not run.ok or state.step_alone["still"]:
        return None
    d = np.array(_step_fitted(alone)[0])
    stat = 2.0 * (run.window["log_likelihood"] - alone.window["log_likelihood"]) \
        / Reference.of(base).dispersion
    p = min(1.0, float(dist.chi2.sf(max(stat, 0.0), c.dof)) * max(tests, 1))
    test = {"installation_step": knock.as_json(), "where": where, "statistic": stat,
            "p_value": p,
            "dof": c.dof, "tests": max(tests, 1),
            "step_fitted_arcsec": [float(x) for x in d]}
    if p < ALPHA:
        state.with_step[c.effect] = (test, run)
        return {}
    reason = (f"significant alone (p = {c.p_adjusted:.2g}) but explains nothing beside the "
              f"stars' attitude step at t~{knock.t:.1f} s on this model ({knock.chi2:.0f} "
              f"chi2 / 3 dof, the largest of {knock.candidates} frames), fitted as a "
              f"rotation of the installation from then on ({np.linalg.norm(d):.3g}\"): its "
              f"ratio {stat:.3g} for {c.dof} dof beside it (p = {p:.2g} over the "
              f"{max(tests, 1)} candidates judged so); it took up what the filter's catch-up "
              "on the step leaves: a knock on the mount, outside the library; not added")
    return {**test, "reason": reason, "remainder": STEP_REMAINDER}


def _beside_slews(runs, state: _State, base: RunSummary, prior: Calibration,
                  calibration: Calibration, c: CandidateResult, tests: int) -> dict | None:
    """A rate-shaped candidate refused where steps at each slew's start take all it explains.

    A mount that lags each slew and stays there (outside the library,
    :mod:`~stellar_cal_ros.diagnosis.slew_steps`): the installation rotated by a free step
    from each slew's start on (:class:`~.slew_steps.SlewSteps`, the window's slews and the
    last before it) is the rival of a candidate :data:`~.slew_steps.RIVALS`.  Two runs
    (the steps alone, made once a round, and the steps with ``c``).  Where the steps alone
    explain the window (their ratio against ``base``, χ² with 3 × slews dof, at ``ALPHA``)
    and ``c``'s ratio beside them (χ²_dof tail × ``tests``, Bonferroni over the candidates
    judged so) is not significant, the refusal with its reason; else ``None`` (no slews to
    fit: a platform that never rests; any number of slews: the steps are 3 states, their
    variance grown at each slew's start, :class:`~.slew_steps.SlewSteps`).
    A gyro scale error grows through a slew and a time offset vanishes at rest: steps held
    from a slew's start take neither (unseen cases ``gsf100``, ``twin_dt1``).
    """
    if base.residuals is None or slew_steps.STEPS_ID in state.extra:
        return None
    if "slews" not in state.slews:
        state.slews["slews"] = slew_steps.slew_starts(
            base.residuals, (base.calibration or prior).R_imu_st, runs.fraction)
        state.slews["first_t"] = float(np.min(base.residuals["t"]))
    slews = state.slews["slews"]
    if slews is None:
        return None
    installation_step.register_step(runs, slew_steps.SlewSteps)
    at = slew_steps.with_steps(prior, slews)
    extra = tuple(state.extra) + (slew_steps.STEPS_ID,)
    key = f"{c.effect} beside the slews' steps"
    tasks = [Task(key, candidate_prior(at, c.effect, calibration), extra + (c.effect,),
                  cost=1.5, candidate=True)]
    if "run" not in state.slews:
        # (and one lag at every slew: whether it differs from slew to slew)
        installation_step.register_step(runs, slew_steps.SlewLag)
        tasks += [Task("the slews' steps alone", at, extra),
                  Task("one lag at the slews", slew_steps.with_lag(prior, slews),
                       tuple(state.extra) + (slew_steps.LAG_ID,))]
    got = runs.run_all(tasks, None)
    if "run" not in state.slews:
        alone = got["the slews' steps alone"]
        state.slews["run"] = alone if alone.ok else None
        steps = slew_steps.fitted(alone.calibration.effects.get(slew_steps.STEPS_ID) or {},
                                  slews) if alone.ok and alone.calibration else None
        if steps is None:  # (a run that failed, or ended before the last slew)
            state.slews["run"] = None
        else:
            dof = 3 * len(slews)
            stat, p, _ = Reference.of(base).compare(alone, dof)
            state.slews["test"] = {
                "steps": steps, **slew_steps.lag(steps, slews),
                "steps_statistic": float(stat), "steps_dof": dof, "steps_p_value": float(p),
                "first_t": state.slews["first_t"],
                "focal_px": float((base.calibration or prior).camera.fx),
                **_one_lag(got["one lag at the slews"], alone, base, dof - 1)}
    alone, run = state.slews["run"], got[key]
    if alone is None or not run.ok or not state.slews["test"]["steps_p_value"] < ALPHA:
        return None
    stat = 2.0 * (run.window["log_likelihood"] - alone.window["log_likelihood"]) \
        / Reference.of(base).dispersion
    p = min(1.0, float(dist.chi2.sf(max(stat, 0.0), c.dof)) * max(tests, 1))
    if p < ALPHA:
        return None
    test = state.slews["test"]
    reason = (f"significant alone (p = {c.p_adjusted:.2g}) but explains nothing beside the "
              f"installation's steps fitted at the {len(slews)} slews' starts "
              f"({test['steps_statistic']:.0f} chi2 / {test['steps_dof']} dof): its ratio "
              f"{stat:.3g} for {c.dof} dof beside them (p = {p:.2g} over the "
              f"{max(tests, 1)} candidates judged so); the tracker jumps at each slew and "
              "stays (a lag), which a gyro rate error or a time offset only mimics here: "
              "outside the library; not added")
    return {"slew_steps": test, "statistic": float(stat), "p_value": p, "dof": c.dof,
            "tests": max(tests, 1), "reason": reason, "remainder": slew_steps.REMAINDER}


def _one_lag(one: RunSummary, steps: RunSummary, base: RunSummary, dof: int) -> dict:
    """One lag at every slew (:class:`~.slew_steps.SlewLag`) against the slews' steps.

    ``lag_arcsec`` / ``lag_sigma_arcsec``: the filter's λ (where its run is ok; else
    :func:`~.slew_steps.lag`'s from the offsets stays); ``lags_statistic``: the steps'
    2Δℓ/dispersion over it, χ² with ``dof`` (3 × slews − 1) where the lag is the same at
    every slew; ``lags_p_value`` its tail (NaN without the run).
    """
    if not one.ok:
        return {"lags_statistic": math.nan, "lags_dof": dof, "lags_p_value": math.nan}
    stat = 2.0 * (steps.window["log_likelihood"] - one.window["log_likelihood"]) \
        / Reference.of(base).dispersion
    (lam, sig), = _estimates(one, slew_steps.LAG_ID).values()
    return {"lag_arcsec": lam / ARCSEC, "lag_sigma_arcsec": sig / ARCSEC,
            "lags_statistic": float(stat), "lags_dof": dof,
            "lags_p_value": float(dist.chi2.sf(max(stat, 0.0), dof))}


def _step_fitted(run: RunSummary) -> tuple[list[float], list[float]]:
    """The step nuisance's rotation in ``run`` and its σ (arcsec, x y z).

    In the step line's sign: the stars', the installation rotation's opposite.
    """
    est = _estimates(run, installation_step.STEP_ID).values()
    return [-v[0] / ARCSEC for v in est], [v[1] / ARCSEC for v in est]


def _step_finding(test: dict, final: RunSummary):
    """The step's 'unexplained' line, carried from the round its nuisance entered the model.

    ``test``: :func:`_beside_knock`'s or :func:`_step_before`'s; the line's time and test
    as the step test said them then, its size (rotation, the stars' shift and their σ) the
    step's rotation as the final model fits it
    (:meth:`~.installation_step.InstallationStep.fitted`; ``detail["step_fitted_arcsec"]``,
    ``detail["installation_step"]`` the test's own).  The test's own step over moving
    frames holds the motion's error there too (``knock_gsf_run20`` s21: 90.8″, 0.844 px
    printed on coord 4c5e68b against the true 20″, 0.385 px).
    """
    knock = installation_step.InstallationStep(**test["installation_step"])
    d, s = _step_fitted(final)
    cam = final.calibration.camera
    fitted = knock.fitted(d, s, (cam.fx, cam.fy))
    if test.get("step_time"):  # (:func:`_step_before`: the time the step is fitted from)
        fitted.t_before, fitted.t = test["step_time"]
    f = fitted.finding(test.get("where", ""), FITTED_STEP)
    f.detail = {"installation_step": knock.as_json(), "step_fitted_arcsec": d,
                "step_fitted_sigma_arcsec": s, "step_fitted_px": fitted.shift_px,
                "step_fitted_sigma_px": fitted.sigma_px}
    return f


#: where the step's line takes its size from once its nuisance is in the final model
FITTED_STEP = "fitted beside the final model: the installation turned from then on"


def _beside_step(state: _State, c: CandidateResult, knock, split: dict | None,
                 tests: int) -> dict | None:
    """The refusal of a candidate a step hid (:func:`_by_step`), or ``None`` to add it."""
    p = math.inf if split is None else min(1.0, split["before"]["p_value"] * tests)
    if p < ALPHA:
        state.by_step[c.effect] = split
        return None
    said = (f"its ratio {split['before']['statistic']:.3g} for {c.dof} dof on the window's "
            f"{split['before']['frames']} frames before it (p = {p:.2g} over the {tests} "
            "candidates it hid)" if split is not None else "too few of the window's frames "
            "before it to tell")
    reason = (f"significant (p = {c.p_adjusted:.2g}) but removes only "
              f"{100 * c.explained:.0f}% of the excess variance, which the stars' attitude "
              f"step at t~{knock.t:.1f} s makes on this model ({knock.chi2:.0f} chi2 / 3 dof)"
              f"; {said}: a stand-in for the step's remainder (a knock on the mount, "
              "outside the library); not added")
    return {"installation_step": knock.as_json(), **(split or {}), "reason": reason,
            "remainder": STEP_REMAINDER}


def _clock_reason(c: CandidateResult, ticks) -> str:
    """Why a rate-shaped candidate is refused beside a clock's remainder (the user's line)."""
    a, b, m = ticks.slew[:3]
    drift = (f"; one drift rate fits {ticks.drift_rate * 1e6:.3g} +- "
             f"{ticks.drift_sigma * 1e6:.2g} ppm, {ticks.rest_chi2:.1f} chi2 / {ticks.dof - 2} "
             "dof left" if math.isfinite(ticks.drift_rate) else "")
    return (f"significant alone (p = {c.p_adjusted:.2g}) but the stars' remainder along "
            f"their motion on this model is a clock's, not a gyro rate error's: its parts "
            f"change ({ticks.chi2:.0f} chi2 / {ticks.dof} dof; dt "
            + ", ".join(f"{d * 1e3:.3g}" for d in ticks.dt)
            + f" ms) and it shrinks along a slew as the filter catches up ({m * 1e3:.3g} ms "
            f"over {a:.0f}-{b:.0f} s, changing by {ticks.slew_growth * 1e3:.3g} +- "
            f"{ticks.slew_growth_sigma * 1e3:.2g} ms per s; a gyro's error grows with the "
            f"angle turned){drift}: a frame clock that drifts or steps against the IMU, "
            "outside the library, which a per-axis gyro rate error takes up slew by slew; not "
            "added")


def _beyond_lead(c: CandidateResult, dispersion: float, with_c: dict | None, lead: dict
                 ) -> dict[str, Any] | None:
    """A candidate's beyond test beside a lead and the lead's test beside it (for the JSON)."""
    b = flexure.beyond(c.statistic, c.dof, dispersion, with_c, lead)
    if b is None:
        return None
    sizes = {k: float(f[key]) for k, f, key in (
        ("lead_coef", lead, "coef"), ("beside_coef", with_c, "coef"),
        ("beside_coef_sigma", with_c, "coef_sigma"), ("beside_coef_nu", with_c, "coef_nu"))
        if f.get(key) is not None}
    return dict(b, lead_t=float(lead["t"]), lead_p_value=float(lead["p_value"]),
                lead_size_px=float(lead["size_px"]), beside_t=float(with_c["t"]),
                beside_p_value=float(with_c["p_value"]), **sizes,
                vanished=leads.vanished(with_c, lead, c.dof, ALPHA))


def _step(k: int, model: list[str], base: RunSummary, results: list[CandidateResult],
          top: CandidateResult | None, seconds: float, reruns: int) -> dict[str, Any]:
    w = base.window
    return {
        "round": k, "model": list(model), "rms_px": list(w["rms"]),
        "expected_rms_px": list(w["expected_rms"]), "log_likelihood": w["log_likelihood"],
        "nis_mean": w["nis"]["mean"], "reruns": reruns, "seconds": seconds,
        "added": None if top is None else {
            "effect": top.effect, "score": top.statistic, "p_value": top.p_adjusted,
            "explained_fraction": top.explained, "rms_after_px": list(top.rms_after_px),
            "estimate": _estimates(top.run, top.effect)},
        "rejected": [{"effect": c.effect, "status": c.status, "score": c.statistic,
                      "p_value": c.p_adjusted, "explained_fraction": c.explained,
                      "estimate": c.estimate, "reason": _verdict(c, top)}
                     for c in results if c is not top],
    }


def _write(out: Path, calibration: Calibration, spec, state: _State, path, history, first,
           final: RunSummary, results, fraction: float, plots: bool, runs, stopped: str,
           seconds: float, verdict=None, verify=None) -> dict[str, Any]:
    """The final diagnosis, the report, ``calibration.yaml`` and ``diagnosis.json``.

    ``verify(calibration, reliability entries) -> rows``: ``--verify``'s check of the
    printed MDBs and biases on twins of the bag, run before the report is written.
    """
    panels = [("initial model", first.residuals)]
    if final is not first:
        panels.append(("final model", final.residuals))
    images = []
    if plots:
        from stellar_cal_ros.diagnosis.plots_discovery import plot_path

        plot_path(path, out / "path.png")
        images.append(("The path: innovation RMS at each round", "path.png"))
    added = [e for e in state.shown() if e not in state.user]
    # the flexure-shaped tests after the adds: Bonferroni over those made; a remainder
    # that a later add left insignificant was that effect's (a library effect still
    # missing then), not a flexure's
    found = [flexure.finding(got, after, len(state.remainders))
             for got, after in state.remainders]
    cleared = [i for i, f in enumerate(found) if f is not None and i not in state.aliased
               and not flexure.significant([f], ALPHA)]
    outside = flexure.significant(found[cleared[-1] + 1 if cleared else 0:], ALPHA)
    like = outside[0].detail["after"] if outside else None
    # no remainder said: the flexure the last test would have seen (its MDB, ″/g)
    hidden = (flexure.hiding(*state.remainders[-1], len(state.remainders), ALPHA)
              if state.remainders and not outside else None)
    # the outside-library fields a candidate was refused beside: their lines, if still there
    kinds = sorted({k for s in path for b in (s.get("beyond_remainder") or {}).values()
                    for k in b.get("leads") or ([b["lead"]] if b.get("lead") else [])})
    known = dict(state.lead)
    if "gravity" in kinds and "gravity" not in known:
        known["gravity"] = leads.gravity_of(runs, final, state.prior, tuple(state.extra))
    if "temperature" in kinds and "temperature" not in known:
        known["temperature"] = leads.temperature_of(runs, final, state.prior,
                                                    tuple(state.extra), ALPHA)
    fields = leads.findings(final, fraction, kinds, ALPHA, known) if kinds else []
    if any("clock" in b for s in path for b in (s.get("beyond_remainder") or {}).values()):
        # a rate-shaped candidate refused beside a clock's remainder: the clock's line, if
        # still there on the final model (the reason the user reads for the refusal)
        # (the user's calibration, as the lines of :func:`finish`: the same text is one line)
        ticks = _clock_of(final, calibration, fraction)
        if ticks is not None and ticks.finding().p_value < ALPHA:
            fields.append(ticks.finding())
    if any(rolling.refused_beside(b) for s in path
           for b in (s.get("beyond_remainder") or {}).values()):
        # one refused beside the rolling shutter's fit: the fit's line, if still there
        line = rolling.finding(final, fraction, ALPHA)
        if line is not None:
            fields.append(line)
    slewed = next((b["slew_steps"] for s in path for b in (s.get("beyond_remainder")
                                                            or {}).values()
                   if "slew_steps" in b), None)
    if slewed is not None:
        # one refused beside the slews' steps: their line (the round's fit), said first
        fields.append(slew_steps.finding(slewed))
    if installation_step.STEP_ID in state.extra and state.step_line is not None:
        # the step is fitted (hidden) in the final model, so its test there sees none: the
        # line of the round it entered, with its size fitted on the final model
        fields.append(_step_finding(state.step_line, final))
    elif any("installation_step" in b for s in path
             for b in (s.get("beyond_remainder") or {}).values()) or any(
               (s.get("added") or {}).get("before_step") for s in path):
        # one refused beside an attitude step where the platform moves, or added for what
        # it explains before it: its line, if still there (the line tests say a step at
        # rest or on a platform that never rests; unseen case knock_slew_gsf)
        knock, where = _knock_of(final, calibration, fraction)
        if where and knock is not None and knock.p_value < ALPHA:
            fields.append(knock.finding(where))
    summary = finish(out, calibration, final, final, results, spec, state.shown(), fraction,
                     panels, plots, "stellar_cal discovery", images, verdict, write=False,
                     outside=outside + fields, like=like, runs=runs, hiding=hidden,
                     refused=tuple(path[-1].get("beyond_remainder") or ()) if path else ())
    if path and any("clock" in b for b in (path[-1].get("beyond_remainder") or {}).values()):
        _clock_first(summary["unexplained"])
    if slewed is not None:
        _first(summary["unexplained"], slew_steps.COMPONENT)
    summary.update({
        "path": path,
        "added": added,
        "stopped": stopped or "nothing more is significant",
        "final_estimates": {e: _estimates(final, e) for e in added},
        "rejected": _rejected(history, state, path),
        "workers": runs.workers, "executor": runs.description,
        "seconds": seconds,
    })
    summary.setdefault("reliability", [])
    _refused_rows(summary["reliability"], state, final, fraction, runs)
    ties = {e: t for e, t in state.ties.items() if e in added and t["with"] not in added}
    if ties:
        summary["ties"] = ties  # (absent otherwise: a diagnosis without one is unchanged)
    if summary.get("remainder"):
        # effects added after the remainder was found (they may absorb it in turn)
        summary["remainder"]["later"] = added[len(summary["remainder"]["like"]):]
        # the later adds a flexure explains as well (not told apart by this motion)
        summary["remainder"]["could_be_flexure"] = {
            s["added"]["effect"]: s["could_be_flexure"] for s in path
            if s.get("could_be_flexure") and s["added"]["effect"] in added}
    cal_path = out / "calibration.yaml"
    written = final.calibration
    if installation_step.STEP_ID in state.extra:  # (the nuisance is not the user's)
        written = copy.deepcopy(written)
        written.effects.pop(installation_step.STEP_ID, None)
        (written.sigma.get("effects") or {}).pop(installation_step.STEP_ID, None)
        written.estimated = [e for e in written.estimated if e != installation_step.STEP_ID]
    save_calibration(written, cal_path)
    summary["calibration_file"] = str(cal_path)
    if verify is not None:
        summary["verify"] = verify(written, summary["reliability"])
    from stellar_cal_ros.diagnosis.printing import discovery_lines

    summary["terminal"] = discovery_lines(summary)
    if plots:
        write_report(out, summary, "stellar_cal discovery")
    (out / "diagnosis.json").write_text(json.dumps(summary, indent=1, default=float))
    return summary


def _refused_rows(entries: list[dict[str, Any]], state: _State, final: RunSummary,
                  fraction: float, runs=None) -> None:
    """Mark the hiding rows of effects the final model's clock rule refuses (in place).

    The final round's rule (:func:`~stellar_cal_ros.diagnosis.clock.refuses`, as
    :func:`_top` asks it): while the stars' remainder along their motion is a clock's, a
    rate-shaped candidate is not added whatever its test says, so its MDB is not a size
    the round adds it at (``dt_step`` s23: gyro_scale_factor at its printed +2.86e-3,
    refused 6 of 6 times).  Each such row gains ``refused_beside_clock``
    (:func:`~stellar_cal_ros.diagnosis.clock.refused_entry`).  The clock test is the
    round's (made again, as :func:`_top` makes it, only if no candidate asked for it).

    The rule holds only at sizes that leave the remainder a clock's (H217: not at sx
    −2.86e-3 on ``dt_step`` s23).  With ``runs`` (the round's, open) each marked row is
    checked at both signs of each parameter's printed MDB: the final model's run on the
    bag with that parameter alone injected there (:func:`~.reliability_probe.
    clock_on_bag`: the probe's injection, its run keeping the residual table the clock
    test reads; the probe's own runs keep none, and are made for some rows only);
    :func:`~.clock.at_mdb` says per parameter and sign.  Two runs a parameter of a marked
    row (gyro_scale_factor 6, gyro_misalignment 12), none on a bag without one.
    """
    ticks = state.ticks
    if ticks is None and any(e["effect"] in clock.RATE_ALIASES for e in entries):
        ticks = _clock_of(final, final.calibration or state.prior, fraction) or False
    marked = [e for e in entries if clock.refuses(e["effect"], ticks, ALPHA)]
    for e in marked:
        e["refused_beside_clock"] = clock.refused_entry(ticks)
    if not marked or runs is None:
        return
    from stellar_cal_ros.diagnosis import injection
    from stellar_cal_ros.diagnosis.reliability import shown

    at = [(e, p) for e in marked for p in e["mdb"]]
    probes = tuple((e["effect"], tuple(injection.parameter_delta(
        e["effect"], p, sign * float(e["mdb"][p])).tolist()))
        for e, p in at for sign in (1.0, -1.0))
    got = iter(_clock_runs(runs, final, probes))
    tests: dict[int, dict[str, dict]] = {}
    for e, p in at:
        tests.setdefault(id(e), {})[p] = {"+": next(got), "-": next(got)}
    for e in marked:
        clock.at_mdb(e["refused_beside_clock"], e["effect"], e["mdb"],
                     {p: shown(f"{e['effect']}.{p}", v) for p, v in e["mdb"].items()},
                     tests[id(e)], ALPHA)


def _clock_runs(runs, final: RunSummary, probes: tuple) -> list:
    """The clock test of ``final``'s model on the bag with each ``(effect, delta)`` injected.

    (:func:`~.reliability_probe.clock_runs`.)  ``None`` for each where the final run
    cannot be repeated.
    """
    if not final.ok or final.calibration is None or final.prior is None:
        return [None] * len(probes)
    from stellar_cal_ros.diagnosis.reliability_probe import clock_runs

    return clock_runs(runs, final.prior, final.effects, final.calibration, probes)


def _clock_first(lines: list[dict[str, Any]]) -> None:
    """The clock's line first (after an installation step's), when the stop names the clock.

    The discovery stopped on "nothing significant beyond the clock-shaped remainder": the
    line that remainder is (:data:`~stellar_cal_ros.diagnosis.clock.CLOCK`) is what the
    user is sent to, and the lines that rank above it by p are read on the same remainder
    (unseen case ``sky_clock_drift3`` s21: the stars' spread along their motion read as a
    0.46-ms stamp noise, p 4.4e-4, above the clock's p 3.1e-3; no stamp noise is in the
    bag).  In place; the order of the others kept.
    """
    at = next((i for i, u in enumerate(lines) if u.get("component") == clock.COMPONENT
               and str(u.get("regressor", "")).startswith(clock.CLOCK)), None)
    if at is None:
        return
    k = 0
    while k < at and lines[k].get("component") == installation_step.COMPONENT:
        k += 1
    lines.insert(k, lines.pop(at))


def _first(lines: list[dict[str, Any]], component: str) -> None:
    """The first line of ``component`` made the first of all (in place)."""
    at = next((i for i, u in enumerate(lines) if u.get("component") == component), None)
    if at is not None:
        lines.insert(0, lines.pop(at))


def _rejected(history: dict[str, list[tuple[int, CandidateResult]]], state: _State,
              path: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Every candidate not in the final model, with the reason; copycats named as such."""
    out = []
    for effect, seen in history.items():
        if effect in state.extra:
            continue
        k_last, last = seen[-1]
        step = path[k_last - 1]
        reason = next((x["reason"] for x in step["rejected"] if x["effect"] == effect),
                      last.reason or last.status)
        alone = [k for k, c in seen if c.significant_alone]
        if effect in state.dropped:
            reason = state.dropped[effect]
        elif alone and not last.significant_alone and last.status == "ranked":
            then = set(path[alone[-1] - 1]["model"])
            new = [e for e in path[k_last - 1]["model"] if e not in then]
            reason = (f"significant alone in round {alone[-1]}, not in round {k_last} once "
                      f"{', '.join(new) or 'the model changed'} (p = {last.p_adjusted:.2g}): "
                      "it copied part of their pattern")
        out.append({"effect": effect, "status": last.status, "reason": reason})
    return out
