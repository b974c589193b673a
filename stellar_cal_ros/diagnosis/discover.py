"""Learn which physical effect the model lacks: augmented runs and a prequential LR test.

Method (issue 5, "likelihood-ratio test from augmented runs")
-------------------------------------------------------------
For every library effect not in the current model, the calibration is re-run with the
effect added, and compared with a re-run of the current model from the same starting
values.  The statistic is twice the difference of the *innovation* log-likelihoods over the
evaluation window (the second half of the frames):

    Λ = 2 (ℓ_augmented − ℓ_current),      p = P(χ²_k > Λ),      p_adj = min(1, m · p)

Innovations are one-step-ahead predictions made before the frame's own update, so ℓ is a
prequential (out-of-sample) likelihood: each frame is held out from the estimate that
predicts it.  A flexible effect cannot win by fitting noise, which is the concern behind
fit-on-half/test-on-half validation, and every frame still serves as test data.  The
``k`` extra parameters get a χ²_k reference distribution; ``m`` candidates are corrected
for by Bonferroni.  ``rms_after_px`` is the innovation RMS of the augmented run in the
same window: what the user will see after adding the effect.

A round (issue 15) is: an optional screening pass that scores every candidate from one run
of the current model (:mod:`~stellar_cal_ros.diagnosis.screening`), the augmented re-runs
of the candidates that pass — concurrently, each reduced to its statistics where it ran
(:mod:`~stellar_cal_ros.diagnosis.parallel`, :mod:`~stellar_cal_ros.diagnosis.runstats`) —
and the decision rules below.

Two statistics decide significance when the screening's score test is local: the score
test ``LM / dispersion ~ χ²_k`` (the locally most powerful test, and the one the minimal
detectable size is stated for) and the augmented run's prequential ratio Λ; a candidate's
p is the smaller of the two, Bonferroni-corrected over the candidates *and* the two
statistics.  Near its MDB an effect the model's own parameters nearly absorb (a thermal
focal drift against the focal length) gains little prequential likelihood while its score
is clear, so Λ alone would find it far less often than the printed 80 % (issue 21).

Every candidate is re-run with its parameters' prior σ at least their plausible physical
size (:func:`candidate_sigma`), so a prior σ set too small cannot hide a large effect.  An
effect is reported *not testable with this motion* (key ``unobservable``) only when its
minimal detectable size on this bag (MDB, from the information its augmented run carries,
:mod:`~stellar_cal_ros.diagnosis.reliability`) exceeds its plausible size in every
direction — e.g. a time offset without rotation.  Effects needing inputs the bag lacks
(site, head temperature) or acting in a stage the method does not model (accelerometer
effects for PSCE) are not applicable.  An effect whose size physics fixes (the astrometric
corrections, ``Effect.physical_value``) is reported as implausible instead of ranked when its
fitted scale is far from the physical one: the data then follow part of its pattern for
another reason.

When the current model misses something, the residuals are over-dispersed and a wrong
candidate that absorbs a sliver of the misfit would still reach a tiny p-value with ten
thousand stars.  Two guards: Λ is divided by the dispersion (quasi-likelihood), and a
significant candidate must remove at least :data:`MIN_EXPLAINED` of the excess residual
variance (residual variance above what the model expects).  Where that gate asks more than
the test, screened round or not, the MDB it states is the size that passes it
(:meth:`Reference.gate_energy`).

One effect missing makes several candidates significant on their own: any that copies part
of its pattern (a time offset under rotation looks partly like an image-plane tilt).  And a
small real effect can hide behind a large one (it removes too little of the excess to
count).  So every other candidate with a small p is tested again *after* the top one — the
same statistic between the run with both and the run with the top one alone, started from
the top one's calibration (Bonferroni over those tested) — and that test decides whether it
is claimed.  The user sees what the next loop iteration would find, without running it
(``diagnose --auto`` runs it: :mod:`~stellar_cal_ros.diagnosis.auto`).
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from stellar_cal_ros.core import distributions as dist
from stellar_cal_ros.diagnosis import reliability, screening
from stellar_cal_ros.diagnosis.parallel import Runs, Task, Then
from stellar_cal_ros.diagnosis.runstats import RunSummary
from stellar_cal_ros.effects import registry
from stellar_cal_ros.effects.base import Stage
from stellar_cal_ros.io.calibration import Calibration
from stellar_cal_ros.methods import registry as methods
from stellar_cal_ros.methods.replay import BagData, ReplayResult, method_runner

log = logging.getLogger(__name__)

Runner = Callable[[BagData, Calibration, list[str]], ReplayResult]

#: a significant candidate must remove at least this fraction of the excess variance
MIN_EXPLAINED = 0.1
#: level of the tests after Bonferroni
ALPHA = 0.01

# Effects whose size physics fixes declare it on their class (``physical_value``:
# astrometric corrections, parameter = scale, 1 = physical).  If one is missing, its
# estimated scale is 1; an estimate far from it means the data follow a *fraction* of the
# correction, i.e. another cause with a similar pattern (measured: an isotropic gyro scale
# factor of 3e-5 fits as aberration × 0.35).
#: a candidate is implausible when its decision finds it significant (family-wise
#: :data:`ALPHA`, :func:`decide`) and its estimate differs from the physical value by more
#: than this many posterior sigmas (two-sided p 6e-7 for a real effect at its physical
#: size) *and* this fraction of the value.  Its distance from zero plays no part: a scale
#: of -0.07 ± 0.022 whose score test is significant is not aberration at -0.07x but a
#: structure with part of its pattern (an aberration twin at -0.1x, 150 s, was added as
#: aberration at -0.068x while the rule also asked for |estimate| > 5 sigma, issue 21)
PHYSICAL_TOL_SIGMA = 5.0
PHYSICAL_TOL_FRACTION = 0.25


@dataclass
class DiagnosisSpec:
    """How the diagnosis runs one estimation method (from its registered spec).

    ``runner`` is the only way the diagnosis calls an estimator; ``screen`` turns its run
    with the candidates as consider parameters into their score tests
    (:func:`~stellar_cal_ros.diagnosis.screening.kernel_scores`; ``None``: no screening,
    every candidate is re-run).
    """

    name: str
    baseline: tuple[str, ...]
    stages: tuple[Stage, ...]
    runner: Runner
    screen: screening.ScreenFn | None = None

    def beyond_baseline(self, effects) -> tuple[str, ...]:
        """The effects of ``effects`` beyond the method's baseline, in their order."""
        return tuple(e for e in effects if e not in self.baseline)


def method_spec(method: str) -> DiagnosisSpec:
    """The :class:`DiagnosisSpec` of a registered method that can be re-run on a bag.

    Every library effect is a candidate, except those acting in a stage the method does not
    model (the accelerometer's for PSCE).
    """
    spec = methods.get(method)
    return DiagnosisSpec(spec.name, spec.baseline, spec.stages, method_runner(method),
                         screening.screen_function(method))


@dataclass
class CandidateResult:
    """One candidate effect tried by an augmented run."""

    #: ranked | unobservable (not testable) | implausible | screened_out | not_applicable
    #: | failed
    effect: str
    status: str
    statistic: float = float("nan")
    #: the effect's parameter count (its estimate's size, the parameters an augmented run
    #: adds), whatever decided; each test's own dof is beside its p: ``seen_dof`` (the ratio
    #: test's), ``screen.dof`` (the score test's: its directions that are not blind)
    dof: int = 0
    #: the directions of the effect its run fits (:func:`seen_dof`): the ratio test's dof
    seen_dof: float = float("nan")
    p_value: float = 1.0
    p_adjusted: float = 1.0
    rms_after_px: tuple[float, float] = (float("nan"), float("nan"))
    estimate: dict[str, float] = field(default_factory=dict)
    sigma: dict[str, float] = field(default_factory=dict)
    reason: str = ""
    run: RunSummary | None = None
    #: the top candidate only: re-run from its own calibration (:func:`condition_on_top`),
    #: what the next loop iteration starts from; its residuals carry no start-up transient
    #: of the current model's biased values
    refined_run: RunSummary | None = None
    detect: reliability.Detectability | None = None
    screen: screening.ScreenResult | None = None
    prior_uncertain: bool = False  #: the prior calls it uncertain, the model lacks it

    #: the screening's score-test p (unadjusted) when it took part in the decision
    p_score: float = float("nan")
    explained: float = float("nan")  # fraction of the excess residual variance removed
    #: tested again after the top candidate (:func:`condition_on_top`): its name, the
    #: statistic and Bonferroni p of adding this one to it, the fraction of what the top
    #: one leaves that this one removes
    after: str = ""
    statistic_after: float = float("nan")
    p_after: float = float("nan")
    explained_after: float = float("nan")

    @property
    def significant_alone(self) -> bool:
        """Significant at 1 % after correction, and it removes a real part of the excess."""
        return (self.status == "ranked" and self.p_adjusted < ALPHA
                and not self.explained < MIN_EXPLAINED)

    @property
    def explained_by_top(self) -> bool:
        """Tested after the top candidate and no longer significant."""
        return bool(self.after) and not (self.p_after < ALPHA
                                         and not self.explained_after < MIN_EXPLAINED)

    @property
    def significant(self) -> bool:
        """Significant alone, or once tested after the top candidate: significant then."""
        if self.status != "ranked":
            return False
        if self.after:
            return not self.explained_by_top
        return self.significant_alone


def excess_energy(excess: float, noise: float, stars: int) -> float:
    """``bᵀ I b`` of an effect whose residuals add ``excess`` to the excess variance per star.

    ``I`` whitened by ``noise`` (the variance per star of both axes), over ``stars``: the
    effect's own residuals' mean square is ``bᵀ I b · noise / (2 · stars)``.  The one
    conversion of :meth:`Reference.gate_energy` (the energy the gate asks) and of the
    probe's runs (:func:`~stellar_cal_ros.diagnosis.reliability_probe.start_probes`: the
    energy an injected effect added).
    """
    return float(2.0 * stars * excess / noise)


@dataclass
class Reference:
    """A run the augmented runs are compared with (evaluation window of its residuals)."""

    log_likelihood: float
    dispersion: float  # mean NIS / 2, at least 1 (quasi-likelihood)
    excess: float  # excess residual variance per star
    floor: float  # 5 % of the noise variance: below it there is no excess to explain
    noise: float = float("nan")  # the noise variance per star (both axes) the model states
    stars: int = 0  # the window's accepted stars

    @classmethod
    def of(cls, run: RunSummary) -> Reference:
        """The reference of a run's evaluation window."""
        w = run.window
        return cls(w["log_likelihood"], screening.dispersion(run),
                   w["excess_variance"], 0.05 * w["noise_variance"], w["noise_variance"],
                   int(w.get("n_window", 0)))

    @property
    def has_excess(self) -> bool:
        """Whether there is an excess variance to explain (above :attr:`floor`).

        The decision's excess gate applies then (:func:`_gate_screened_out`, ``excess_gate``).
        """
        return bool(self.excess > self.floor)

    def gate_energy(self, explained: float) -> float:
        """The energy an effect must add for a candidate to remove :data:`MIN_EXPLAINED`.

        ``explained``: the share of the excess the candidate removes without the effect.
        Its augmented run fits the effect away and leaves the excess it leaves now,
        ``E (1 − explained)`` (measured on ``dt_step``: the same to 2e-4 with gyro scale
        factor sx injected from −2863 to +2863 ppm), while the effect ``b`` raises this
        reference's by
        its own residuals' mean square, ``bᵀ I b · noise / (2 · stars)`` (``I`` the window's
        information, whitened by the stated noise, half of ``noise`` an axis).  The gate
        passes once that reaches ``E (MIN_EXPLAINED − explained) / (1 − MIN_EXPLAINED)``;
        returned as ``bᵀ I b`` (:func:`reliability.detectability`'s ``gate``).  0 where no
        gate applies: no excess to explain (``explained`` NaN) or passed already.  What the
        effect's residuals share with the misfit (``2 bᵀ s``, linear in ``b``: it helps one
        sign and hinders the other) is added there (``overlap``; doc/benchmarks.md).
        """
        if not explained < MIN_EXPLAINED or not self.noise > 0 or not self.stars:
            return 0.0
        return excess_energy(self.excess * (MIN_EXPLAINED - explained) / (1.0 - MIN_EXPLAINED),
                             self.noise, self.stars)

    def compare(self, run: RunSummary, dof: float) -> tuple[float, float, float]:
        """Statistic Λ, its unadjusted p (χ²_dof) and the fraction of the excess removed.

        Quasi-likelihood: when the reference misses something, every residual is
        over-dispersed by the same factor, and any extra parameter that absorbs a sliver of
        the misfit gains a log-likelihood proportional to it; dividing by the dispersion
        (mean NIS / 2) restores the χ² reference.  The explained fraction is NaN when the
        reference has no excess to explain.
        """
        w = run.window
        statistic = float(2.0 * (w["log_likelihood"] - self.log_likelihood) / self.dispersion)
        p = float(dist.chi2.sf(max(statistic, 0.0), dof))
        explained = (float(1.0 - w["excess_variance"] / self.excess)
                     if self.has_excess else float("nan"))
        return statistic, p, explained


def seen_dof(run: RunSummary, x: str) -> float:
    """How many directions of ``x`` (in ``run``'s model) the data sees beside the rest of it.

    The run fits ``x`` as a constant with prior σ (``Π = diag σ⁻²``) beside the other
    parameters; with ``I`` the information the data carries about ``x`` once they are
    marginalized (the model's own span projected out), its posterior block is
    ``P = (I + Π)⁻¹``.  The estimate is the prior shrunk by the hat matrix
    ``H = I (I + Π)⁻¹ = 1 − Π P``: along an eigen-direction of ``I`` (in ``Π``'s metric)
    the data fits ``λ / (λ + π)`` of it -- 1 where the data determines it, 0 where only the
    prior does -- and a likelihood ratio of ``x`` gains about one χ²₁ in each direction
    fitted and nothing where it is not.  So the effective dof is the hat's trace,
    ``tr H = k − tr(Π P) = Σ_j (1 − P_jj / σ_j²)`` (each parameter's share of its prior
    variance the data removed; ``Π`` is diagonal).  A gyro misalignment on psce rotations:
    the installation absorbs its three antisymmetric directions (a rotation of the gyro
    axes), the posterior stays near the prior there, and 3.1-3.2 of 6 count (``twin_gm2``
    s21 / s23; the installation's own prior pins a little of the rotation, which counts:
    more dof, a larger p, so the count errs towards a tie).  No run: the model's run has
    ``x``'s block.  At least 1 (an added effect was significant in some direction).
    """
    sl = run.block(x)
    prior_var = np.asarray(run.prior_sigma[sl], dtype=float) ** 2
    fitted = 1.0 - np.diag(np.atleast_2d(run.P[sl, sl])) / np.maximum(prior_var, 1e-300)
    return max(float(np.clip(fitted, 0.0, 1.0).sum()), 1.0)


def rerun_prior(calibration: Calibration, model_effects: list[str] | None = None) -> Calibration:
    """Start values from ``calibration``, datasheet-level sigmas for every estimated effect.

    Both the current model and each augmented one are re-run from this prior, so their
    likelihoods are comparable and every parameter can re-adjust to the candidate.
    """
    prior = copy.deepcopy(calibration)
    prior.sigma = {}
    prior.method = "prior"
    return prior


def candidate_sigma(effect_id: str, user_prior: Calibration | None,
                    calibration: Calibration | None = None) -> np.ndarray:
    """Prior σ of a candidate in its augmented run: never below its plausible size.

    The largest of the user's prior σ (``user_prior``'s sigma block), the effect's default
    σ and its plausible physical size for ``calibration``'s camera (default: the user's):
    a prior σ set too small must not keep a large effect from being fitted and tested.
    """
    eff = registry.create(effect_id)
    sig = np.maximum(np.asarray(eff.default_sigma, dtype=float),
                     reliability.plausible_size(effect_id, calibration or user_prior))
    if user_prior is not None:
        sig = np.maximum(sig, eff.initial(user_prior)[1])
    return sig


def candidate_prior(prior: Calibration, effect_id: str,
                    user_prior: Calibration | None) -> Calibration:
    """``prior`` with the candidate's σ set by :func:`candidate_sigma`."""
    out = copy.deepcopy(prior)
    eff = registry.create(effect_id)
    value, _ = eff.initial(out)
    eff.store(value, candidate_sigma(effect_id, user_prior, prior), out)
    return out


def prior_uncertain(calibration: Calibration, in_model: set[str]) -> list[str]:
    """Effects the calibration's sigma block calls uncertain that the model lacks.

    The rule for both methods: the model is the method's baseline plus the user's
    ``--effects``; these effects are not added silently but listed first among the
    candidates and tested like any other.
    """
    from stellar_cal_ros.diagnosis.runstats import quiet
    from stellar_cal_ros.methods.models import prior_uncertain_effects

    with quiet("stellar_cal_ros.methods.models", level=logging.WARNING):
        found = prior_uncertain_effects(calibration)
    return [e for e in found if e not in in_model]


def _applicable(effect_id: str, spec: DiagnosisSpec, facts: dict[str, Any] | BagData) -> str:
    if isinstance(facts, BagData):
        facts = {"site": facts.site is not None,
                 "head_temperature": facts.head_temperature is not None}
    eff = registry.create(effect_id)
    if eff.stage not in spec.stages:
        return f"acts on the {eff.stage.value} stage, which {spec.name} does not model"
    if "site" in eff.requires and not facts["site"]:
        return "needs the site position (/gnss/fix), absent from the bag"
    if "head_temperature" in eff.requires and not facts["head_temperature"]:
        return "needs /star_tracker/temperature, absent from the bag"
    return ""


#: relative run time of an augmented run by stage (longest first keeps workers busy)
_COST = {Stage.DIRECTION: 2.0, Stage.GYRO: 1.5, Stage.ACCEL: 1.5}


def _cost(effect_id: str) -> float:
    return _COST.get(registry.create(effect_id).stage, 1.0)


@dataclass
class Round:
    """What every round of one diagnosis shares."""

    runs: Runs
    spec: DiagnosisSpec
    facts: dict[str, Any]
    fraction: float = 0.5
    user_prior: Calibration | None = None  #: the calibration the user gave (its sigmas)
    uncertain: tuple[str, ...] = ()  #: effects the user's prior calls uncertain
    physical_check: bool = True
    progress: Callable[[str], None] | None = None
    #: the latest noise verdict (:class:`~stellar_cal_ros.diagnosis.noise.NoiseVerdict`)
    noise: Any = None
    #: the stars' σ scale of the latest round's run differs from the one applied, or an IMU
    #: scale the stars measured (:meth:`~.noise.NoiseVerdict.imu_from_stars`) was measured
    #: on another model than the round's
    noise_stale: bool = False
    #: the model (``extra``) the latest noise verdict was measured on
    noise_extra: tuple[str, ...] | None = None
    #: the IMU components of :attr:`noise_stale` (measured by the stars on another model)
    imu_stale: list[str] = field(default_factory=list)
    #: candidates' runs the noise's walk search compared with (:func:`measure_round_noise`):
    #: {key: (the scales they ran with, run)}, taken by the round when its scales are those
    rival_runs: dict[str, Any] = field(default_factory=dict)
    #: ``on_top(base, top, refined)``, called by :func:`condition_on_top` as it hands out
    #: the top candidate's refined run (the :class:`Task` ``refined``) and the runs after
    #: it: the caller's runs that need only these start beside them; returns a
    #: :meth:`~.parallel.Runs.run_ahead` ``then`` (or None) for that batch
    on_top: Callable[[RunSummary, Any, Task], Then | None] | None = None
    #: ``beside(base, candidates)``, called by :func:`rank_round` of a screened round once
    #: its current model's run (``base``, with the round's noise) is in and the candidates
    #: it passes are out, before it waits for them (``candidates``: the round's
    #: :class:`CandidateResult` with their screening): the caller's runs that need only
    #: ``base`` may start beside them
    beside: Callable[[RunSummary, list[CandidateResult]], None] | None = None

    def measured_elsewhere(self, extra) -> list[str]:
        """The IMU components the stars measured on another model than ``extra``.

        Of the latest noise verdict (:meth:`~.noise.NoiseVerdict.imu_from_stars`).
        """
        if self.noise is None or self.noise_extra == tuple(extra):
            return []
        return self.noise.imu_from_stars()

    def tell(self, text: str) -> None:
        """Report progress."""
        if self.progress:
            self.progress(text)

    def done(self, task: Task, out: RunSummary, where: str = "") -> None:
        """Progress line of one finished run (``where``: ``run 4/11, ETA 20 s``)."""
        # (a private nuisance's id is never named: :func:`~stellar_cal_ros.effects.
        # registry.available`)
        shown = [e for e in task.effects if not registry.is_private(e)]
        what = "+".join(shown[-2:]) if shown else "current model"
        name = what if task.key == what else f"{task.key}: {what}"
        self.tell(f"{name} ({out.seconds:.1f} s)"
                  + (f" failed: {out.error}" if out.error else "")
                  + (f"; {where}" if where else ""))


def _untestable(cand: CandidateResult) -> bool:
    """Mark ``cand`` not testable with this motion when its detectability says so."""
    det = cand.detect
    if det is None or det.testable:
        return False
    cand.status = "unobservable"
    mdb = ", ".join(reliability.shown(f"{cand.effect}.{n}", v) for n, v in det.mdb.items())
    where = det.where_text()
    cand.reason = (f"not testable with this motion: its minimal detectable size ({mdb}"
                   + (f"; {where}" if where else "") + f") is {det.ratio:.3g} x its plausible "
                   "size even along its best-determined direction")
    return True


def window_information(cand: CandidateResult, run: RunSummary | None = None) -> np.ndarray:
    """The information about ``cand``'s effect its decision's window carries, ``(k, k)``.

    Both of the candidate's statistics (the score test and the augmented run's likelihood
    ratio) are sums over the evaluation window: under an effect ``b`` their non-centrality
    is ``bᵀ I_W b`` with ``I_W = Σ_window Aᵀ S⁻¹ A`` (``A``: the innovations' response to
    the effect through the current model's filter), the information the MDB is stated for.
    The screening run measures ``I_W`` itself (:attr:`ScreenResult.information`), so a
    re-run candidate prints the MDB a screened-out one does.  The augmented run's posterior
    holds the whole run's information (``P_post⁻¹ − P_prior⁻¹``: the screening's sum over
    every frame, to 1e-4 on ``sway_twin_gsf1`` s23), and the information is not spread
    over the run as the stars are: the window holds 98 % of gyro_scale_factor sz's on that
    swaying bag (44 % of the stars: 20.9 ppm printed re-run, 14.0 screened out; twins at
    14.0 found 18 of 20), 21 % of accel_scale_factor sz's there, and 16-18 % of
    gyro_misalignment e02's and gsf sx's on a clean 300-s PSCE bag (49 % of the stars;
    twins at sx's window MDB significant 15 of 20).  A round that is not screened (its
    current model far from consistent, ``screen=False``: the final round of unseen cases
    ``dt_step``, ``sky_clock_drift3``, ``sway_knock``, whose 'what could still be hiding' the
    user reads) scores its candidates on the current model's run for this alone
    (:func:`rank_round`; not local: no score test decides).  The stars' share scales the
    augmented run's information only where no run scored the candidate (a current-model
    run that failed to score).
    """
    if cand.screen is not None:
        return np.atleast_2d(np.asarray(cand.screen.information, dtype=float))
    sl = run.block(cand.effect)
    share = run.window["n_window"] / max(run.window["n_accepted"], 1)
    return reliability.data_information(run.P[sl, sl], run.prior_sigma[sl], share)


def _alternatives(cand: CandidateResult) -> dict[str, Any]:
    """:func:`reliability.detectability`'s ``beside`` and ``tie_alpha`` for ``cand``.

    The information its screening left with each alternative of its stage fitted beside it
    (:func:`screening.alternatives`), and the level at which the selection tells an added
    effect from its rival (:data:`ALPHA`, :func:`~stellar_cal_ros.diagnosis.auto._tie`);
    none for a candidate no run scored.
    """
    if cand.screen is None:
        return {}
    return {"beside": cand.screen.beside, "tie_alpha": ALPHA}


def _fill_candidate(r: Round, cand: CandidateResult, run: RunSummary, reference: Reference,
                    alpha_mdb: float, dispersion: float = 1.0) -> None:
    """Decision inputs of one augmented run: detectability, Λ, p, physical size.

    ``dispersion``: the one the MDB is stated for (:func:`reliability.detectability`).
    The MDB is also the excess gate's where that asks more (:func:`_gated`).  The gate decides
    in every round, screened or not, so the MDB printed is its size wherever it binds: a
    screened round's MDB was the test's alone (unseen case ``sway_jitter`` s22, 1 ms stamp
    jitter, NIS/dof 5.86: time_offset 'MDB dt 0.0194 ms' printed while 0.087 ms, p 2.4e-9,
    was refused for removing 1 % of the excess; the gate's MDB is 0.449 ms, and an offset
    injected at it is added: test_discovery_auto).  Checked by injection there only: a
    far-off model's first round (the swaying 300-s diagnose, NIS/dof 95 without the lens'
    radial terms) now prints the gate's MDB too (time_offset 1.46 ms, 74x the test's alone),
    not checked by injection.
    """
    cand.run = run
    sl = run.block(cand.effect)
    eff = registry.create(cand.effect)
    cand.dof = eff.size
    value, sig_post = run.theta[sl], run.sigma[sl]
    cand.estimate = dict(zip(eff.parameter_names, map(float, value), strict=True))
    cand.sigma = dict(zip(eff.parameter_names, map(float, sig_post), strict=True))
    cand.rms_after_px = tuple(run.window["rms"])
    info = window_information(cand, run)
    cand.detect = reliability.detectability(cand.effect, info, alpha_mdb, r.user_prior,
                                            dispersion, **_alternatives(cand))
    if _untestable(cand):
        return
    cand.seen_dof = seen_dof(run, cand.effect)
    cand.statistic, cand.p_value, cand.explained = reference.compare(run, cand.seen_dof)
    # the MDB is the size the decision finds: its excess gate too
    _gated(r, cand, info, alpha_mdb, dispersion, reference.gate_energy(cand.explained))
    phys = eff.physical_value
    if r.physical_check and phys is not None:
        est, sig = float(value[0]), float(sig_post[0])
        # clearly not at its physical size; whether it is there at all is the decision's
        # (:func:`decide` undoes the status when the candidate is not significant)
        if (abs(est - phys) > PHYSICAL_TOL_SIGMA * sig
                and abs(est - phys) > PHYSICAL_TOL_FRACTION * abs(phys)):
            cand.status = "implausible"
            reading = eff.fraction_reading(est / phys, run.calibration.stamp) \
                if run.calibration is not None else ""
            cand.reason = (
                f"the data fit {est:.3g} ± {sig:.2g} of the physical {cand.effect}, whose "
                f"size is known ({phys:g}): the structure follows part of its pattern but "
                "has another cause" + (f", {reading}" if reading else "") + "; if several "
                "effects are missing, add the top candidate and diagnose again")
    beyond = beyond_limit(eff, value, sig_post) if r.physical_check else ""
    if beyond:
        cand.status, cand.reason = "implausible", beyond


def beyond_limit(eff, value, sigma) -> str:
    """Why an estimate ``value`` (σ ``sigma``) of ``eff`` is beyond what an instrument reaches.

    Its size (the parameters' norm) above ``eff.physical_limit`` by more than
    :data:`PHYSICAL_TOL_SIGMA` of its largest σ: the effect's pattern standing in for another
    cause, not the effect (a rolling shutter fitted as a 122 mrad detector tilt, unseen case
    ``rolling`` seed 23).  '' when within, or when the effect has no such limit.
    """
    limit = eff.physical_limit
    if limit is None:
        return ""
    size = float(np.linalg.norm(np.asarray(value, dtype=float)))
    if not size - limit > PHYSICAL_TOL_SIGMA * float(np.max(np.asarray(sigma, dtype=float))):
        return ""
    shown, factor = eff.display_units or ("", 1.0)
    return (f"the data fit {eff.id} of {size * factor:.3g} {shown}, beyond what a working "
            f"instrument reaches ({limit * factor:g} {shown}): the structure follows part of "
            "its pattern but has another cause, outside the library; if several effects are "
            "missing, add the top candidate and diagnose again")


#: a screening run goes first (the round's re-runs wait for it)
_SCREEN_COST = 10.0


def _candidate_task(r: Round, prior: Calibration, extra: list[str], effect_id: str) -> Task:
    return Task(effect_id, candidate_prior(prior, effect_id, r.user_prior),
                tuple(extra) + (effect_id,), cost=_cost(effect_id), candidate=True)


def rank_round(r: Round, start: Calibration, extra: list[str], pool: list[str],
               condition: bool = True, keep_residuals: bool = True,
               more: list[Task] | None = None, screen: bool = True,
               measure_noise: bool = False,
               ) -> tuple[RunSummary, list[CandidateResult], dict[str, RunSummary]]:
    """One round: (the noise,) screen, re-run the candidates that pass, decide.

    With ``measure_noise`` the round first measures the noise scales of the current model
    (:func:`~stellar_cal_ros.diagnosis.noise_runs.measure`: "noise as stated" is tested before
    any physical effect) and runs everything else with the scales it finds (``r.noise``).

    ``start`` gives the start values (:func:`rerun_prior`); ``extra`` are the model's
    effects beyond the baseline.  The screening run (scoring every candidate; on several
    workers the candidates' runs go ahead beside it, those it does not pass cancelled) is
    the current model's re-run; with ``screen=False`` (the caller
    expects the current model far from consistent, where a local test says nothing) the
    current model and every candidate are re-run at once.  With ``condition`` the strong
    candidates are tested again after the top one (:func:`condition_on_top`).  ``more``:
    further runs to execute with the first batch (their statistics are returned by key,
    undecided).
    """
    prior = rerun_prior(start)
    in_model = set(r.spec.baseline) | set(extra)
    results: list[CandidateResult] = []
    testable: list[str] = []
    for effect_id in dict.fromkeys(e for e in pool if e not in in_model):
        reason = _applicable(effect_id, r.spec, r.facts)
        if reason:
            results.append(CandidateResult(effect_id, "not_applicable", reason=reason))
        else:
            testable.append(effect_id)
    # two statistics decide when a local score test is available (the score test the MDB
    # is computed for, and the augmented run's likelihood ratio): Bonferroni over both
    use_score = bool(screen and r.spec.screen is not None and testable)
    n_stats = 2 if use_score else 1
    # the noise's base run is the current model's run: when the noise it ran with is kept,
    # it is the round's screening run (its candidates as consider parameters) or reference
    more = list(more or [])
    # the candidates' runs, built once (a run made ahead is taken by the same Task): not
    # screened, all of them; screened, on several workers those the screening passes go
    # beside the noise's base run (:func:`measure_round_noise`)
    early = measure_noise and r.runs.workers > 1
    cand_tasks = ([_candidate_task(r, prior, extra, e) for e in testable]
                  if not use_score or early else [])
    # not screened: the current model's run scores them for their MDB alone, where the
    # method has consider parameters (the bundle has none)
    for_mdb = () if use_score or r.spec.screen is None else tuple(testable)
    measured = (measure_round_noise(r, prior, extra, tuple(testable) if use_score else (),
                                    keep_residuals, cand_tasks + ([] if use_score else more),
                                    rivals=tuple(testable), score=for_mdb)
                if measure_noise else None)
    base = measured[0] if measured else None
    alpha_mdb = round_alpha(n_stats, len(testable))
    cands = {e: CandidateResult(e, "ranked", prior_uncertain=e in r.uncertain)
             for e in testable}
    current = Task("current model", prior, tuple(extra), keep_residuals, cost=1.0,
                   star_noise=r.noise is not None)
    late = list(more)  # run with the re-runs unless they can go with a screening run
    if use_score:
        if base is not None:  # the noise's base run (and its parts) scored the candidates
            screens, out = measured, {}
        else:
            # one run scores every candidate (the one-worker run, bit for bit); on several
            # workers every candidate's run goes ahead beside it and those its screening
            # does not pass are cancelled as soon as it is in (as beside the noise's base
            # run, :func:`measure_round_noise`; until H273 a second worker ran a second
            # screening run of the same model, scoring half of the candidates)
            first = [Task("screen 1/1", prior, tuple(extra), keep_residuals,
                          cost=_SCREEN_COST, screen=tuple(testable),
                          star_noise=r.noise is not None)]
            if r.runs.workers > 1 and not cand_tasks:
                cand_tasks = [_candidate_task(r, prior, extra, e) for e in testable]
            out = r.runs.run_ahead(first + more, cand_tasks, r.done)
            screens = [out.pop(t.key) for t in first]
            late = []  # ran with the screening
        # motion beyond the IMU's noise correlates the innovations: no local score test
        scores = screening.collect(screens, white=not (r.noise and r.noise.beyond),
                                   alpha=alpha_mdb, calibration=r.user_prior)
        if base is None and cand_tasks:
            _forget_screened_out(r, cand_tasks, scores)
        rerun = []
        for e, c in cands.items():
            c.screen = scores.get(e)
            if c.screen is None or c.screen.passes:
                rerun.append(e)
                continue
            c.status, c.p_value = "screened_out", c.screen.p_value
            c.dof = registry.create(e).size
            c.detect = reliability.detectability(e, window_information(c), alpha_mdb,
                                                 r.user_prior, c.screen.dispersion,
                                                 **_alternatives(c))
            if not _untestable(c):
                c.reason = f"score test p = {c.p_value:.2g}: not re-run"
        # every screening run is the current model's run (consider parameters leave the
        # filter alone): the first that finished is the reference
        base = next((s for s in screens if s.ok), None)
        if base is not None:
            _count_stale_candidates(base, screens)
        built = {t.key: t for t in cand_tasks}
        tasks, made = _take_rivals(r, [built.get(e) or _candidate_task(r, prior, extra, e)
                                       for e in rerun])
        out.update(made)
        if base is not None and r.beside is not None:
            r.beside(base, list(cands.values()))
        out.update(r.runs.run_all((tasks if base is not None else [current] + tasks) + late,
                                  r.done))
    else:
        cand_tasks, out = _take_rivals(r, cand_tasks)
        if base is None and for_mdb:
            # its run scores the candidates for their MDB only (the window's information,
            # :func:`window_information`): no local test decides here
            current = replace(current, screen=tuple(testable), cost=_SCREEN_COST)
        out.update(r.runs.run_all(([current] if base is None else []) + cand_tasks + more,
                                  r.done))
    extras = {t.key: out.pop(t.key) for t in more}
    if base is None:
        base = out.pop("current model")
        if not base.ok:
            from stellar_cal_ros.errors import ModelError

            raise ModelError(f"the current model's re-run failed: {base.error}")
    if r.noise is not None:
        from stellar_cal_ros.diagnosis.noise import stale

        # the stars' noise checked again on this model's run (free): a model that changed
        # since the noise was measured may show another scale (a missing effect inflates it);
        # an IMU scale only the stars measured is not checked by a run: stale once the model
        # is not the one it was measured on
        r.imu_stale = [] if r.noise.skipped else r.measured_elsewhere(extra)
        r.noise_stale = not r.noise.skipped and (stale(base.star_noise) or bool(r.imu_stale))
    reference = Reference.of(base)
    if not use_score:
        for e, scr in screening.collect([base], alpha=alpha_mdb,
                                        calibration=r.user_prior).items():
            if e in cands:
                cands[e].screen = replace(scr, local=False)
    for e, run in out.items():
        c = cands[e]
        if not run.ok:
            log.warning("candidate %s failed: %s", e, run.error)
            c.status, c.reason = "failed", run.error
            continue
        # the ratio statistic is divided by the reference's dispersion, and so is the
        # score statistic of a screened round (the same run's, :func:`screening.dispersion`):
        # the MDB is stated for it (Teunissen: the bias the printed test finds with the
        # printed power), screened or not
        _fill_candidate(r, c, run, reference, alpha_mdb, reference.dispersion)
    for c in cands.values():
        if c.status == "screened_out" and c.screen is not None:
            _gate_screened_out(r, c, reference, alpha_mdb)
    results = list(cands.values()) + results
    tested = [c for c in results if c.status in ("ranked", "implausible", "screened_out")]
    m = max(len(tested), 1)
    for c in tested:
        decide(c, m, n_stats)
    order = {"ranked": 0, "implausible": 1, "screened_out": 2, "unobservable": 3,
             "failed": 4, "not_applicable": 5}
    results.sort(key=lambda c: (order[c.status], -np.nan_to_num(c.statistic, nan=-np.inf)))
    if condition:
        condition_on_top(r, extra, results, keep_residuals=keep_residuals, base=base)
    return base, results, extras


def round_alpha(n_stats: int, n: int) -> float:
    """The level of one test of a round of ``n`` candidates and ``n_stats`` statistics each.

    Bonferroni (:func:`decide`): the level the MDB is stated for, and the one a score
    test's blind directions are judged at (:func:`screening.collect`).
    """
    return ALPHA / (n_stats * max(n, 1))


def _gate_screened_out(r: Round, cand: CandidateResult, reference: Reference,
                       alpha_mdb: float) -> None:
    """A screened-out candidate's MDB, the excess gate's where that asks more.

    Not re-run, it removes nothing of the excess (``explained`` 0, its score test not
    significant); an effect large enough to pass the score test is re-run and must then
    remove :data:`MIN_EXPLAINED` as a re-run candidate must (:func:`_fill_candidate`).
    No gate where the reference has no excess to explain (:meth:`Reference.compare`).
    """
    if cand.detect is None or not cand.detect.testable or not reference.has_excess:
        return
    _gated(r, cand, window_information(cand), alpha_mdb, cand.screen.dispersion,
           reference.gate_energy(0.0))


def _forget_screened_out(r: Round, tasks: list[Task], scores: dict[str, Any]) -> list[Task]:
    """Cancel the runs made ahead of the candidates the screening does not pass.

    ``tasks``: the candidates' runs made ahead; ``scores``: the screening's
    (:func:`screening.collect`).  Returns the ones cancelled
    (:meth:`~.parallel.Runs.forget_ahead`).
    """
    out = [t for t in tasks if t.key in scores and not scores[t.key].passes]
    r.runs.forget_ahead(out)
    return out


def _gated(r: Round, cand: CandidateResult, info: np.ndarray, alpha_mdb: float,
           dispersion: float, gate: float) -> None:
    """``cand``'s MDB the excess gate's (``gate``: :meth:`Reference.gate_energy`) where > 0."""
    if gate > 0.0:
        cand.detect = reliability.detectability(
            cand.effect, info, alpha_mdb, r.user_prior, dispersion, gate,
            cand.screen.score if cand.screen is not None else None, **_alternatives(cand))


def _take_rivals(r: Round, tasks: list[Task]) -> tuple[list[Task], dict[str, RunSummary]]:
    """The candidates' runs ``tasks`` still to make, and those the noise's walk search made.

    A run of :attr:`Round.rival_runs` is taken when it ran with the scales the round uses
    (the walk was not taken); the rest are dropped.
    """
    made = {k: run for k, (noise, run) in r.rival_runs.items() if noise == r.runs.noise}
    r.rival_runs = {}
    return [t for t in tasks if t.key not in made], {t.key: made[t.key] for t in tasks
                                                    if t.key in made}


def _count_stale_candidates(base: RunSummary, screens: list[RunSummary]) -> None:
    """Count the frames a candidate was scored on with a stale input only it needs.

    ``env_stale_candidates`` in ``base``'s counters (e.g. a thermal candidate's head
    temperature).

    ``env_stale`` counts the frames the *model* ran with a stale input (what a replay of it
    counts); the screening's frames are joined over its runs by stamp, so that the count is
    the same however the candidates are split among them (a frame's wait for an input ends
    at the same timeout whichever other inputs its run waits for).
    """
    stale = set().union(*(s.consider_stale_ns for s in screens if s.ok))
    if stale:
        base.counters = {**base.counters, "env_stale_candidates": len(stale)}


def decide(c: CandidateResult, m: int, n_stats: int) -> None:
    """Set the decision's p of a tested candidate, ``p_adjusted``.

    Bonferroni over ``m`` candidates and ``n_stats`` statistics; 'implausible' is undone
    when the candidate is not significant.

    The p is the smaller of the augmented run's ratio test and the screening's score test
    (the test the MDB is stated for) when that is local: the prequential ratio alone has
    less power near the MDB for effects the model's own parameters nearly absorb
    (measured: a thermal focal drift at its MDB, score p = 0.013, ratio -2.9).  An
    implausible candidate is decided by the same two tests: refraction injected at its MDB
    (``benchmarks/reliability_injection.py``, seed 305) had score p 7e-5 but ratio p 6e-4,
    and the ratio alone (x20) called it not significant -- the sky effects were 'missed' at
    their MDB (issue 21).
    """
    p = c.p_value
    if c.status in ("ranked", "implausible") and c.screen is not None and c.screen.local:
        c.p_score = c.screen.p_value
        p = min(p, c.screen.p_value)
    c.p_adjusted = min(1.0, p * m * n_stats)
    if c.status == "implausible" and not c.p_adjusted < ALPHA:
        # its fit at the wrong size explains nothing significant: an ordinary
        # non-significant candidate, not a sign of another cause
        c.status, c.reason = "ranked", ""


def measure_round_noise(r: Round, prior: Calibration, extra: list[str],
                        screen: tuple[str, ...] = (), keep_residuals: bool = False,
                        beside: list[Task] = (), rivals: tuple[str, ...] = (),
                        score: tuple[str, ...] = ()) -> list[RunSummary] | None:
    """Measure the noise of the current model; every later run of ``r`` uses its scales.

    The measurement's base run is the current model's run with the stated scales: it
    scores the candidates ``screen`` (consider parameters leave the filter alone) and keeps
    its residuals with ``keep_residuals``.  Returned when the verdict keeps the scales it
    ran with -- it then *is* the round's screening run (or its current-model run), the same
    filter pass, so the round runs it once; ``None`` when the noise changed (or was not
    measured) and the round runs its current model again with the new scales.  Returned:
    ``[base run]``.  It scores every candidate on any number of workers (the one-worker
    base run, bit for bit).

    ``beside``: the runs the round makes next (its candidates'), sent ahead beside the base
    run on several workers, so that no worker idles through it (the noise's first ML runs
    follow the base run, ahead of those still queued, where its result asks for them):
    all of them, screened or not (a screened round's candidates are not known before the
    base run's scores: those the screening does not pass are cancelled as soon as it is
    in, :meth:`~.parallel.Runs.forget_ahead`; one already running finishes, its result
    unused); kept for the round when the verdict keeps the scales they ran with (the usual
    case), else dropped.  The round must ask for the same :class:`Task` objects.  (Until
    H265 a second run of the current model scored the candidates beside a base run scoring
    few, and its passing candidates followed it: a second filter pass, ≈ 2 CPU-s of the
    several round's ≈ 23.)

    ``rivals``: the round's candidates, which a gyro bias walk the verdict would take must
    beat (:func:`~stellar_cal_ros.diagnosis.noise_runs.beats_rivals`): the one the
    screening scores best, or every one in a round not screened (``beside``'s runs), run
    with the walk's scales; kept for the round (:attr:`Round.rival_runs`).

    ``score``: the candidates a round that is not screened scores on the base run for their
    MDB alone (:func:`window_information`; the runs go as without them).
    """
    from stellar_cal_ros.diagnosis.noise_runs import first_runs, measure, start_samples

    if methods.get(r.spec.name).kind != "filter":
        return None  # a batch method's runner takes no noise scales (its σ: its own fit)
    r.tell("noise: measuring the stars' sigma and the IMU noise from the run")
    back = r.measured_elsewhere(extra)
    if back:
        # an IMU scale the stars measured on another model (an effect then missing, which
        # it followed): measured again from the scale it was measured from, not relative to
        # itself (its search reads within a factor of its start: sway_sky_twin_dt1 s21's
        # gyro x106 then read "at most x0.0524" of it and kept x5.56 for a stated x1)
        r.runs.noise = r.runs.noise.replace(**{c: getattr(r.noise.stated, c) for c in back})
    ran_with = r.runs.noise
    comps = ("gyro", "accel") if Stage.ACCEL in r.spec.stages else ("gyro",)

    def ahead() -> list[Task]:
        # called once the base run is handed out: the IMU samples' scales (the verdict's,
        # and the first ML runs' start) go to the first free worker, not before the base run
        start_samples(r.runs, comps)
        return beside

    def then(task: Task, run: RunSummary) -> list[Task]:
        # with several workers the first ML runs go out as soon as the base run is in, ahead
        # of the candidates still queued (its result decides whether they are used); none
        # in a round that is not screened (its model far off: the verdict skips the ML
        # search) nor when the base run lost lock (the verdict is then far off: a run it
        # does not use would hold a worker up by its length)
        if r.runs.workers < 2 or not screen or not run.ok or run.lost_lock:
            return []
        return first_runs(r.runs, prior, tuple(extra), comps)[:r.runs.workers]

    alpha = round_alpha(2, len(screen))  # the screened round's (:func:`rank_round`)
    # the candidates' runs beside the base run (they wait for nothing it finds unless the
    # noise changes)
    beside = list(beside) if r.runs.workers > 1 else []
    kept: list[Task] = []
    try:
        # the base run first: everything after it waits for it
        done = r.runs.run_ahead([Task("noise: current model", prior, tuple(extra),
                                      keep_residuals,
                                      cost=_SCREEN_COST if screen or beside else 1.0,
                                      screen=tuple(screen) or tuple(score),
                                      star_noise=True)],
                                ahead, r.done, then)
        base = done["noise: current model"]
        if not base.ok:
            log.warning("noise not measured: the current model's run failed: %s", base.error)
            return None
        if screen and beside:
            # the candidates its screening does not pass are not run (the white test
            # unless the latest verdict found motion beyond the IMU's noise; a verdict
            # that finds otherwise re-runs what is missing: the round decides on its own)
            out = _forget_screened_out(
                r, beside, screening.collect([base], white=not (r.noise and r.noise.beyond),
                                             alpha=alpha, calibration=r.user_prior))
            beside = [t for t in beside if all(t is not o for o in out)]

        def rival_runs(at: Any) -> list[tuple[str, RunSummary, int]]:
            # the screening's best candidate (its smallest p), or every one when not screened
            names = list(rivals)
            if screen:
                scores = screening.collect([base], alpha=alpha, calibration=r.user_prior)
                ranked = sorted((s.p_value, e) for e, s in scores.items() if e in rivals)
                names = [e for _, e in ranked[:1]]
            ahead = {t.key: t for t in beside} if at == ran_with else {}
            tasks = [ahead.get(e) or replace(_candidate_task(r, prior, extra, e), noise=at)
                     for e in names]
            out = r.runs.run_all(tasks, r.done) if tasks else {}
            r.rival_runs = {t.key: (at, out[t.key]) for t in tasks}
            return [(t.key, out[t.key], registry.create(t.key).size) for t in tasks]

        r.noise = measure(r.runs, prior, tuple(extra), base, r.tell, comps,
                          rivals=rival_runs if rivals else None)
        r.noise_extra = tuple(extra)
        if r.noise.applied == ran_with:
            kept = beside
    finally:
        r.runs.drop_ahead(keep=kept)
    r.runs.noise = r.noise.applied
    r.runs.verdict = r.noise
    # (the 'unexplained' lines, which may name the star-by-star repeat's cause, come later)
    for line in r.noise.lines(pending=True):
        r.tell("noise: " + line)
    return [base] if ran_with is not None and r.runs.noise == ran_with else None


def rank_candidates(
    data: BagData,
    calibration: Calibration,
    spec: DiagnosisSpec,
    model_effects: list[str],
    candidates: list[str] | None = None,
    evaluation_fraction: float = 0.5,
    progress: Callable[[str], None] | None = None,
    physical_check: bool = True,
    runs: Runs | None = None,
    measure_noise: bool = False,
    on_top: Callable[[RunSummary, Any, Task], Then | None] | None = None,
    beside: Callable[[RunSummary, list[CandidateResult]], None] | None = None,
) -> tuple[RunSummary, list[CandidateResult]]:
    """Re-run the current model and every candidate; return the base run and the ranking.

    ``measure_noise``: measure the noise scales first (the verdict is ``runs.verdict``).
    ``on_top``: :attr:`Round.on_top` (the caller's runs beside the top candidate's);
    ``beside``: :attr:`Round.beside` (the caller's runs beside the candidates').

    ``physical_check=False`` ranks the astrometric scales as free parameters (for measuring
    their detectability at non-physical sizes, ``benchmarks/detectability.py``).  Runs in
    this process unless ``runs`` (:func:`~stellar_cal_ros.diagnosis.parallel.open_runner`)
    is given.
    """
    extra = spec.beyond_baseline(model_effects)
    runs = runs or Runs(data, spec, evaluation_fraction)
    in_model = set(spec.baseline) | set(extra)
    uncertain = prior_uncertain(calibration, in_model)
    r = Round(runs, spec, runs.facts(), evaluation_fraction, calibration, tuple(uncertain),
              physical_check, progress, on_top=on_top, beside=beside)
    pool = uncertain + [e for e in (candidates or registry.candidates()) if e not in uncertain]
    if candidates is not None:
        pool = [e for e in pool if e in candidates]
    base, results, _ = rank_round(r, calibration, extra, pool, measure_noise=measure_noise)
    return base, results


def condition_on_top(r: Round, extra: list[str], results: list[CandidateResult],
                     max_after: int = 4, max_implausible: int = 3,
                     keep_residuals: bool = True, base: RunSummary | None = None) -> None:
    """Test the other significant candidates again with the top one in the model.

    This is the next iteration of the loop, run ahead: start values from the top
    candidate's calibration (as ``stellar-cal diagnose`` would take them after the user
    added it), a reference run with the top one (:attr:`CandidateResult.refined_run`, its
    residuals kept: the final model's structure is tested on it), and the other candidates
    with p < 0.01 (the ``max_after`` strongest; the rest keep their marginal verdict)
    re-run together with it — all concurrently.  The same quasi-likelihood ratio
    (dispersion of the reference run), Bonferroni over the candidates tested, and
    explained-variance floor (of the excess the reference leaves) decide.  Implausible
    candidates with p < 0.01 (up to ``max_implausible``) are tested the same way: an
    astrometric correction that fits at the wrong size because of the top effect is then
    shown as not needed once it is added.  Fills the ``after`` fields in place.
    ``base``: the round's current-model run, for :attr:`Round.on_top`.
    """
    top = next((c for c in results if c.significant_alone), None)
    if top is None or top.run is None:
        return
    # every other candidate with a small p, even one that explains too little of the
    # excess alone: a real effect can hide behind a large one and show once it is gone
    rest = [c for c in results if c is not top and c.status == "ranked"
            and c.p_adjusted < ALPHA][:max_after]  # results are sorted: the strongest ones
    rest += [c for c in results if c.status == "implausible"
             and c.p_adjusted < ALPHA][:max_implausible]
    prior = rerun_prior(top.run.calibration)
    with_top = tuple(extra) + (top.effect,)
    # the refined run first (the tail's lines and probes wait for it, :attr:`Round.on_top`;
    # at cost 1 a direction or gyro run after it went out before it)
    tasks = [Task("refined " + top.effect, prior, with_top, keep_residuals,
                  cost=_SCREEN_COST)]
    tasks += [Task(c.effect + " after", candidate_prior(prior, c.effect, r.user_prior),
                   with_top + (c.effect,), cost=_cost(c.effect), candidate=True) for c in rest]
    then = r.on_top(base, top, tasks[0]) if r.on_top is not None else None
    out = r.runs.run_all(tasks, r.done, then=then)
    refined = out.pop("refined " + top.effect)
    if not refined.ok:
        log.warning("re-run with %s failed: %s", top.effect, refined.error)
        return
    top.refined_run = refined
    reference = Reference.of(refined)
    for c in rest:
        run = out[c.effect + " after"]
        if not run.ok:  # keep the marginal result
            log.warning("candidate %s after %s failed: %s", c.effect, top.effect, run.error)
            continue
        c.after = top.effect
        c.statistic_after, p, c.explained_after = reference.compare(
            run, seen_dof(run, c.effect))
        c.p_after = min(1.0, p * len(rest))


def hidden_effects(base: RunSummary, results: list[CandidateResult]) -> list[dict[str, Any]]:
    """What could still hide in the model: every candidate's MDB and the biases it allows.

    For each applicable library effect not in the model (ranked, implausible, not testable
    or screened out) with an augmented run or a screening sensitivity: its minimal
    detectable size and the bias each of its parameters at that size (at most its plausible
    size) puts into each estimated parameter and into the equivalent principal point, and
    what its blind directions could shift (:func:`~stellar_cal_ros.diagnosis.reliability.
    external_reliability`); ``dominates`` lists those where the bias exceeds their σ in
    the current model.
    """
    from stellar_cal_ros.diagnosis.runstats import EPP_NAMES

    sigma = base.sigma_by_name()
    out = []
    for c in results:
        if c.detect is None:
            continue
        if c.run is not None and c.run.ok:
            derived = ({} if c.run.epp_jacobian is None else
                       dict(zip(EPP_NAMES, c.run.epp_jacobian, strict=True)))
            rows = reliability.bias_rows(c.run.names, c.run.P, c.run.block(c.effect),
                                         base.names, derived)
        elif c.screen is not None and c.screen.sensitivity is not None:
            rows = dict(zip(base.names, c.screen.sensitivity, strict=False))
            rows.update(c.screen.derived)
        else:
            rows = {}
        # a private nuisance's parameters (the knock's fitted step) are never printed
        rows = {q: h for q, h in rows.items() if not registry.is_private(q)}
        entry = reliability.external_reliability(c.detect, rows, sigma)
        if "dispersion" in entry:
            # whether the round's excess gate applies (its reference has an excess to
            # explain): a round that fits but for a dispersion of a few % has none, and
            # its MDB is the test's alone (:func:`~.printing.dispersion_note`)
            entry["excess_gate"] = Reference.of(base).has_excess
        phys = registry.create(c.effect).physical_value
        if phys is not None:
            # the decision flags a structure with its pattern at the MDB, and names it
            # 'implausible' (not the effect itself) below this size: the MDB is a
            # detection size (benchmarks/reliability_injection.py counts both as found)
            entry["physical_value"] = float(phys)
            entry["implausible_below"] = float(phys * (1.0 - PHYSICAL_TOL_FRACTION))
        out.append(entry)
    return out


def summary_dict(base: RunSummary, results: list[CandidateResult],
                 unexplained: list, spec: DiagnosisSpec,
                 model_effects: list[str], evaluation_fraction: float,
                 heavy_tails: bool = False) -> dict[str, Any]:
    """``diagnosis.json`` (contract §5), plus extra keys readers may ignore.

    ``heavy_tails``: the noise verdict names the stars' noise heavy-tailed (its data quality
    then does not call the gated stars misidentified, :func:`~stellar_cal_ros.methods.
    results.data_quality`).
    """
    from stellar_cal_ros.methods.results import data_quality

    w = base.window
    ranked = [c for c in results if c.status == "ranked"]
    return {
        "format": "stellar_cal_diagnosis/1",
        "counts": {k: v for k, v in base.counters.items() if v},
        "data_quality": data_quality(base.counters, int(w["n_accepted"]),
                                     w["nis"]["mean"] / 2.0, heavy_tails=heavy_tails),
        "residual_rms_px": list(w["rms"]),
        "expected_rms_px": list(w["expected_rms"]),
        "log_likelihood": w["log_likelihood"],
        "candidates": [
            {"effect": c.effect, "score": c.statistic, "rms_after_px": list(c.rms_after_px),
             "p_value": c.p_adjusted, "p_value_unadjusted": c.p_value,
             "p_value_score": None if np.isnan(c.p_score) else c.p_score,
             "dof_score": None if np.isnan(c.p_score) else c.screen.dof,
             "explained_fraction": c.explained,
             "significant": c.significant, "significant_alone": c.significant_alone,
             "after": ({"effect": c.after, "score": c.statistic_after,
                        "p_value": c.p_after, "explained_fraction": c.explained_after}
                       if c.after else None),
             "dof": c.dof, "seen_dof": None if np.isnan(c.seen_dof) else c.seen_dof,
             "estimate": c.estimate, "sigma": c.sigma,
             "prior_uncertain": c.prior_uncertain,
             "detectability": c.detect.as_dict() if c.detect else None}
            for c in ranked
        ],
        "unexplained": [
            {"regressor": f.regressor, "component": f.component, "statistic": f.statistic,
             "p_value": f.p_value, "change_px": f.slope_px,
             **({"detail": f.detail} if f.detail else {})}
            for f in unexplained
        ],
        "prior_uncertain": [
            {"effect": c.effect, "note": f"the prior says {c.effect} is uncertain; not in "
             "the model (tested like any candidate)"}
            for c in results if c.prior_uncertain],
        "unobservable": [{"effect": c.effect, "reason": c.reason,
                          "detectability": c.detect.as_dict() if c.detect else None}
                         for c in results if c.status == "unobservable"],
        "screened_out": [{"effect": c.effect, "reason": c.reason,
                          "p_value_score": c.screen.p_value, "dof_score": c.screen.dof,
                          "detectability": c.detect.as_dict() if c.detect else None}
                         for c in results if c.status == "screened_out"],
        "implausible": [{"effect": c.effect, "reason": c.reason, "score": c.statistic,
                         "p_value": c.p_adjusted, "estimate": c.estimate, "sigma": c.sigma,
                         "after": ({"effect": c.after, "score": c.statistic_after,
                                    "p_value": c.p_after, "needed": not c.explained_by_top}
                                   if c.after else None)}
                        for c in results if c.status == "implausible"],
        "not_applicable": [{"effect": c.effect, "reason": c.reason}
                           for c in results if c.status in ("not_applicable", "failed")],
        "nis": w["nis"],
        "whiteness": w["whiteness"],
        "model": {"method": spec.name,
                  "effects": [*spec.baseline, *spec.beyond_baseline(model_effects)]},
        "evaluation": f"innovations of the last {evaluation_fraction:.0%} of the frames",
    }
