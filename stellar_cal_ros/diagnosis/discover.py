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

An effect whose parameters the data leave at their prior uncertainty (posterior σ above
``unobservable_ratio`` × prior σ for every combination of its parameters, see
:func:`observability_ratio`) is reported as unobservable with
this motion instead of ranked — e.g. a time offset without rotation.  Effects acting in a
stage the method does not model (accelerometer effects for PSCE) or needing inputs the bag
lacks (site, head temperature) are reported as not applicable.  An effect whose size
physics fixes (the astrometric corrections, :data:`PHYSICAL_VALUE`) is reported as
implausible instead of ranked when its fitted scale is far from the physical one: the data
then follow part of its pattern for another reason.

When the current model misses something, the residuals are over-dispersed and a wrong
candidate that absorbs a sliver of the misfit would still reach a tiny p-value with ten
thousand stars.  Two guards: Λ is divided by the dispersion (quasi-likelihood), and a
significant candidate must remove at least :data:`MIN_EXPLAINED` of the excess residual
variance (residual variance above what the model expects).

One effect missing makes several candidates significant on their own: any that copies part
of its pattern (a time offset under rotation looks partly like an image-plane tilt).  And a
small real effect can hide behind a large one (it removes too little of the excess to
count).  So every other candidate with a small p is tested again *after* the top one — the
same statistic between the run with both and the run with the top one alone, started from
the top one's calibration (Bonferroni over those tested) — and that test decides whether it
is claimed.  The user sees what the next loop iteration would find, without running it.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats as sps

from stellar_cal_ros.diagnosis import stats
from stellar_cal_ros.effects import registry
from stellar_cal_ros.effects.base import Stage
from stellar_cal_ros.io.calibration import Calibration
from stellar_cal_ros.methods.replay import BagData, ReplayResult

log = logging.getLogger(__name__)

Runner = Callable[[BagData, Calibration, list[str]], ReplayResult]

#: a significant candidate must remove at least this fraction of the excess variance
MIN_EXPLAINED = 0.1

#: Effects whose size physics fixes (astrometric corrections, parameter = scale, 1 =
#: physical).  If one is missing, its estimated scale is 1; an estimate far from it means
#: the data follow a *fraction* of the correction, i.e. another cause with a similar
#: pattern (measured: an isotropic gyro scale factor of 3e-5 fits as aberration × 0.35).
PHYSICAL_VALUE: dict[str, float] = {"aberration": 1.0, "refraction": 1.0,
                                    "proper_motion": 1.0}
#: an estimate is implausible when it is clearly non-zero and differs from the physical
#: value by more than this many posterior sigmas *and* this fraction of the value
PHYSICAL_TOL_SIGMA = 5.0
PHYSICAL_TOL_FRACTION = 0.25


@dataclass
class MethodSpec:
    """How the diagnosis runs one estimation method."""

    name: str
    baseline: tuple[str, ...]
    stages: tuple[Stage, ...]
    runner: Runner


def _psce_runner(data: BagData, prior: Calibration, effects: list[str]) -> ReplayResult:
    from stellar_cal_ros.methods.replay import replay_psce

    return replay_psce(data, prior, effects)


def method_spec(method: str) -> MethodSpec:
    """The :class:`MethodSpec` of ``psce`` or ``swaying_base``."""
    from stellar_cal_ros.errors import ModelError
    from stellar_cal_ros.methods.psce import BASELINE_EFFECTS

    if method == "psce":
        return MethodSpec("psce", BASELINE_EFFECTS,
                          (Stage.GYRO, Stage.DIRECTION, Stage.TIME, Stage.TRACKER, Stage.CAMERA),
                          _psce_runner)
    if method == "swaying_base":
        try:
            from stellar_cal_ros.methods import swaying
        except ImportError as exc:  # pragma: no cover - until issue 4 lands
            raise ModelError("the swaying_base method is not available") from exc
        return MethodSpec("swaying_base", tuple(swaying.BASELINE_EFFECTS),
                          (Stage.GYRO, Stage.ACCEL, Stage.DIRECTION, Stage.TIME, Stage.TRACKER),
                          lambda d, p, e: swaying.replay_swaying(d, p, e))
    raise ModelError(f"diagnose: unknown method {method!r} (psce | swaying_base)")


@dataclass
class CandidateResult:
    """One candidate effect tried by an augmented run."""

    effect: str
    status: str  # ranked | unobservable | implausible | not_applicable | failed
    statistic: float = float("nan")
    dof: int = 0
    p_value: float = 1.0
    p_adjusted: float = 1.0
    rms_after_px: tuple[float, float] = (float("nan"), float("nan"))
    estimate: dict[str, float] = field(default_factory=dict)
    sigma: dict[str, float] = field(default_factory=dict)
    sigma_ratio: float = float("nan")
    reason: str = ""
    run: ReplayResult | None = None
    #: the top candidate only: re-run from its own calibration (:func:`refine_top`), what
    #: the next loop iteration starts from; its residuals carry no start-up transient of
    #: the current model's biased values
    refined_run: ReplayResult | None = None

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
        return (self.status == "ranked" and self.p_adjusted < 0.01
                and not self.explained < MIN_EXPLAINED)

    @property
    def explained_by_top(self) -> bool:
        """Tested after the top candidate and no longer significant."""
        return bool(self.after) and not (self.p_after < 0.01
                                         and not self.explained_after < MIN_EXPLAINED)

    @property
    def significant(self) -> bool:
        """Significant alone, or once tested after the top candidate: significant then."""
        if self.status != "ranked":
            return False
        if self.after:
            return not self.explained_by_top
        return self.significant_alone


def observability_ratio(P_post: np.ndarray, sigma_prior: np.ndarray) -> float:
    """Smallest posterior/prior sigma ratio over every *combination* of the parameters.

    ``sqrt(λ_min)`` of the prior-whitened posterior covariance ``D⁻¹ P D⁻¹`` (D = prior
    sigmas).  Per-parameter marginal ratios are not enough: a gyro misalignment's
    antisymmetric part is a rotation of the gyro triad, which the installation absorbs, so
    every marginal sigma stays at 1/√2 of the prior while the symmetric part is determined
    to a few percent.  The effect is observable as soon as one direction is.
    """
    d = 1.0 / np.maximum(np.asarray(sigma_prior, dtype=float), 1e-300)
    W = np.atleast_2d(P_post) * np.outer(d, d)
    lam = np.linalg.eigvalsh(0.5 * (W + W.T))
    return float(np.sqrt(max(lam.min(), 0.0)))


@dataclass
class _Reference:
    """A run the augmented runs are compared with (evaluation window of its residuals)."""

    log_likelihood: float
    dispersion: float  # mean NIS / 2, at least 1 (quasi-likelihood)
    excess: float  # excess residual variance per star
    floor: float  # 5 % of the noise variance: below it there is no excess to explain

    @classmethod
    def of(cls, res: stats.Table, fraction: float) -> _Reference:
        mask = stats.evaluation_mask(res, fraction)
        return cls(stats.log_likelihood(res, mask),
                   max(1.0, stats.nis_consistency(res, mask)["mean"] / 2.0),
                   stats.excess_variance(res, mask), 0.05 * stats.noise_variance(res, mask))

    def compare(self, res: stats.Table, mask: np.ndarray,
                dof: int) -> tuple[float, float, float]:
        """Statistic Λ, its unadjusted p (χ²_dof) and the fraction of the excess removed.

        Quasi-likelihood: when the reference misses something, every residual is
        over-dispersed by the same factor, and any extra parameter that absorbs a sliver of
        the misfit gains a log-likelihood proportional to it; dividing by the dispersion
        (mean NIS / 2) restores the χ² reference.  The explained fraction is NaN when the
        reference has no excess to explain.
        """
        statistic = float(2.0 * (stats.log_likelihood(res, mask) - self.log_likelihood)
                          / self.dispersion)
        p = float(sps.chi2.sf(max(statistic, 0.0), dof))
        explained = (float(1.0 - stats.excess_variance(res, mask) / self.excess)
                     if self.excess > self.floor else float("nan"))
        return statistic, p, explained


def rerun_prior(calibration: Calibration, model_effects: list[str]) -> Calibration:
    """Start values from ``calibration``, datasheet-level sigmas for every estimated effect.

    Both the current model and each augmented one are re-run from this prior, so their
    likelihoods are comparable and every parameter can re-adjust to the candidate.
    """
    prior = copy.deepcopy(calibration)
    prior.sigma = {}
    prior.method = "prior"
    return prior


def _applicable(effect_id: str, spec: MethodSpec, data: BagData) -> str:
    eff = registry.create(effect_id)
    if eff.stage not in spec.stages:
        return f"acts on the {eff.stage.value} stage, which {spec.name} does not model"
    if "site" in eff.requires and data.site is None:
        return "needs the site position (/gnss/fix), absent from the bag"
    if "head_temperature" in eff.requires and data.head_temperature is None:
        return "needs /star_tracker/temperature, absent from the bag"
    return ""


def rank_candidates(
    data: BagData,
    calibration: Calibration,
    spec: MethodSpec,
    model_effects: list[str],
    candidates: list[str] | None = None,
    evaluation_fraction: float = 0.5,
    unobservable_ratio: float = 0.5,
    progress: Callable[[str], None] | None = None,
    physical_check: bool = True,
) -> tuple[ReplayResult, list[CandidateResult]]:
    """Re-run the current model and every candidate; return the base run and the ranking.

    ``physical_check=False`` ranks the astrometric scales as free parameters (for measuring
    their detectability at non-physical sizes, ``benchmarks/detectability.py``).
    """
    extra = [e for e in model_effects if e not in spec.baseline]
    prior = rerun_prior(calibration, list(spec.baseline) + extra)
    base = spec.runner(data, prior, extra)
    reference = _Reference.of(base.residuals, evaluation_fraction)
    in_model = set(spec.baseline) | set(extra)
    pool = [e for e in (candidates or registry.available()) if e not in in_model]
    results: list[CandidateResult] = []
    for effect_id in pool:
        reason = _applicable(effect_id, spec, data)
        if reason:
            results.append(CandidateResult(effect_id, "not_applicable", reason=reason))
            continue
        if progress:
            progress(effect_id)
        try:
            run = spec.runner(data, prior, extra + [effect_id])
        except Exception as exc:  # a candidate failing must not stop the diagnosis
            log.warning("candidate %s failed: %s", effect_id, exc)
            results.append(CandidateResult(effect_id, "failed", reason=str(exc)))
            continue
        flt = run.filter
        model = flt.model
        sl = model.slices[effect_id]
        value = flt.theta[sl]
        sig_post = flt.sigma()[3:][sl]
        sig_prior = model.initial_sigma[sl]
        ratio = observability_ratio(flt.P[3:, 3:][sl, sl], sig_prior)
        eff = model.effects[[e.id for e in model.effects].index(effect_id)]
        cand = CandidateResult(
            effect_id, "ranked", dof=eff.size, sigma_ratio=ratio,
            estimate={n: float(v) for n, v in zip(eff.parameter_names, value, strict=True)},
            sigma={n: float(s) for n, s in zip(eff.parameter_names, sig_post, strict=True)},
            run=run,
        )
        mask_c = stats.evaluation_mask(run.residuals, evaluation_fraction)
        cand.rms_after_px = stats.rms(run.residuals, mask_c)
        if ratio > unobservable_ratio:
            cand.status = "unobservable"
            cand.reason = (f"the data leave its uncertainty at {ratio:.0%} of the prior: "
                           "not observable with this motion and these inputs")
        else:
            cand.statistic, cand.p_value, cand.explained = reference.compare(
                run.residuals, mask_c, eff.size)
            phys = PHYSICAL_VALUE.get(effect_id)
            if physical_check and phys is not None:
                est, sig = float(value[0]), float(sig_post[0])
                # clearly present, yet clearly not at its physical size
                if (abs(est) > PHYSICAL_TOL_SIGMA * sig
                        and abs(est - phys) > PHYSICAL_TOL_SIGMA * sig
                        and abs(est - phys) > PHYSICAL_TOL_FRACTION * abs(phys)):
                    cand.status = "implausible"
                    cand.reason = (
                        f"the data fit {est:.3g} ± {sig:.2g} of the physical {effect_id}, "
                        f"whose size is known ({phys:g}): the structure follows part of its "
                        "pattern but has another cause; if several effects are missing, "
                        "add the top candidate and diagnose again")
        results.append(cand)
    tested = [c for c in results if c.status in ("ranked", "implausible")]
    m = max(len(tested), 1)
    for c in tested:
        c.p_adjusted = min(1.0, c.p_value * m)
        if c.status == "implausible" and not c.p_adjusted < 0.01:
            # its fit at the wrong size explains nothing significant: an ordinary
            # non-significant candidate, not a sign of another cause
            c.status, c.reason = "ranked", ""
    order = {"ranked": 0, "implausible": 1, "unobservable": 2, "failed": 3,
             "not_applicable": 4}
    results.sort(key=lambda c: (order[c.status], -np.nan_to_num(c.statistic, nan=-np.inf)))
    condition_on_top(data, spec, extra, results, evaluation_fraction, progress)
    return base, results


def refine_top(data: BagData, spec: MethodSpec, extra: list[str], top: CandidateResult,
               prior: Calibration) -> None:
    """Re-run the model with the top candidate from that candidate's calibration.

    The augmented run started from the current model's values, which the missing effect
    biased; parameters that converge slowly (distortion) can still carry that start in the
    evaluation window and show as residual structure.  The re-run is where the next loop
    iteration starts: the residual-structure tests and the "+ effect" panels use it.
    ``prior``: :func:`rerun_prior` of the candidate's calibration.
    """
    try:
        top.refined_run = spec.runner(data, prior, extra + [top.effect])
    except Exception as exc:  # keep the augmented run
        log.warning("re-run with %s failed: %s", top.effect, exc)


def condition_on_top(data: BagData, spec: MethodSpec, extra: list[str],
                     results: list[CandidateResult], evaluation_fraction: float = 0.5,
                     progress: Callable[[str], None] | None = None,
                     max_after: int = 4, max_implausible: int = 3) -> None:
    """Test the other significant candidates again with the top one in the model.

    This is the next iteration of the loop, run ahead: start values from the top
    candidate's calibration (as ``stellar-cal diagnose`` would take them after the user
    added it), a reference run with the top one, and the other candidates with p < 0.01
    (the ``max_after`` strongest; the rest keep their marginal verdict) re-run together with
    it.  The same quasi-likelihood ratio (dispersion of the reference run), Bonferroni over
    the candidates tested, and explained-variance floor (of the excess the reference
    leaves) decide.  Implausible candidates with p < 0.01 (up to ``max_implausible``) are
    tested the same way: an astrometric correction that fits at the wrong size because of
    the top effect is then shown as not needed once it is added.  Fills the ``after``
    fields in place.
    """
    top = next((c for c in results if c.significant_alone), None)
    # every other candidate with a small p, even one that explains too little of the
    # excess alone: a real effect can hide behind a large one and show once it is gone
    rest = [c for c in results if c is not top and c.status == "ranked"
            and c.p_adjusted < 0.01][:max_after]  # results are sorted: the strongest ones
    if top is None or top.run is None:
        return
    prior = rerun_prior(top.run.calibration, list(spec.baseline) + extra + [top.effect])
    refine_top(data, spec, extra, top, prior)
    rest += [c for c in results if c.status == "implausible"
             and c.p_adjusted < 0.01][:max_implausible]
    if not rest or top.refined_run is None:
        return
    reference = _Reference.of(top.refined_run.residuals, evaluation_fraction)
    for c in rest:
        if progress:
            progress(f"{c.effect} after {top.effect}")
        try:
            run = spec.runner(data, prior, extra + [top.effect, c.effect])
        except Exception as exc:  # keep the marginal result
            log.warning("candidate %s after %s failed: %s", c.effect, top.effect, exc)
            continue
        c.after = top.effect
        c.statistic_after, p, c.explained_after = reference.compare(
            run.residuals, stats.evaluation_mask(run.residuals, evaluation_fraction), c.dof)
        c.p_after = min(1.0, p * len(rest))


def summary_dict(base: ReplayResult, results: list[CandidateResult],
                 unexplained: list[stats.RegressorFinding], spec: MethodSpec,
                 model_effects: list[str], evaluation_fraction: float) -> dict[str, Any]:
    """``diagnosis.json`` (contract §5), plus extra keys readers may ignore."""
    res = base.residuals
    mask = stats.evaluation_mask(res, evaluation_fraction)
    ranked = [c for c in results if c.status == "ranked"]
    return {
        "format": "stellar_cal_diagnosis/1",
        "residual_rms_px": list(stats.rms(res, mask)),
        "expected_rms_px": list(stats.expected_rms(res, mask)),
        "candidates": [
            {"effect": c.effect, "score": c.statistic, "rms_after_px": list(c.rms_after_px),
             "p_value": c.p_adjusted, "p_value_unadjusted": c.p_value,
             "explained_fraction": c.explained,
             "significant": c.significant, "significant_alone": c.significant_alone,
             "after": ({"effect": c.after, "score": c.statistic_after,
                        "p_value": c.p_after, "explained_fraction": c.explained_after}
                       if c.after else None),
             "dof": c.dof, "estimate": c.estimate, "sigma": c.sigma}
            for c in ranked
        ],
        "unexplained": [
            {"regressor": f.regressor, "component": f.component, "statistic": f.statistic,
             "p_value": f.p_value, "change_px": f.slope_px}
            for f in unexplained
        ],
        "unobservable": [{"effect": c.effect, "reason": c.reason}
                         for c in results if c.status == "unobservable"],
        "implausible": [{"effect": c.effect, "reason": c.reason, "score": c.statistic,
                         "p_value": c.p_adjusted, "estimate": c.estimate, "sigma": c.sigma,
                         "after": ({"effect": c.after, "score": c.statistic_after,
                                    "p_value": c.p_after, "needed": not c.explained_by_top}
                                   if c.after else None)}
                        for c in results if c.status == "implausible"],
        "not_applicable": [{"effect": c.effect, "reason": c.reason}
                           for c in results if c.status in ("not_applicable", "failed")],
        "nis": stats.nis_consistency(res, mask),
        "whiteness": stats.whiteness(res, mask),
        "model": {"method": spec.name, "effects": list(spec.baseline) + [
            e for e in model_effects if e not in spec.baseline]},
        "evaluation": f"innovations of the last {evaluation_fraction:.0%} of the frames",
    }
