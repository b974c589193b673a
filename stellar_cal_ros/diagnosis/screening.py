"""Screening: one run of the current model that scores every candidate at once.

A round of the diagnosis is

1. **screening** — a score (Lagrange-multiplier) test of every candidate from one run of
   the *current* model: with the sensitivity of the filter's state to the candidates'
   parameters (Willsky–Jones recursion), the score ``s`` and Fisher information ``I`` of
   each candidate over the evaluation window give ``LM = sᵀ I⁻¹ s ~ χ²_k`` under "not
   missing".  The sensitivity does not feed back into the filter, so this run *is* the
   current model's re-run (its statistics are the round's reference: no separate run);
2. **full augmented re-runs**, in parallel, of the candidates whose screening p-value is
   below :data:`SCREEN_P` (a loose threshold: the decision is the augmented run's);
3. the decision rules of :mod:`~stellar_cal_ros.diagnosis.discover`.

With several workers the candidates are split into parts (:func:`parts`), one screening
run per part, concurrently: each part repeats the filter (cheap) and carries the
sensitivity of its own candidates only (the expensive part); the score test of a candidate
uses its own block of ``s`` and ``I`` only, so the split changes no number.

The score function is pluggable: :attr:`~stellar_cal_ros.diagnosis.discover.DiagnosisSpec.
screen` is called where the run executes, on the run made with the candidates as consider
parameters::

    screen(result, candidates) -> {effect_id: (LM, dof, I)}  or (LM, dof, I, M[, derived,
                                                                   score, beside])

``I`` is (k, k) in the effect's units⁻² over the evaluation window; the optional ``M``
(n_θ, k) is the sensitivity of the current model's final θ to the candidate (consider
analysis), which gives the reliability report for candidates that are not re-run; the
optional ``beside`` ``{other candidate: (k, k)}`` its information once the other is fitted
beside it (what tells them apart, :func:`alternatives`).  A
method without one (``screen=None``) re-runs every candidate.

When is the score test trusted?  It is a local test: its LM equals the likelihood-ratio
statistic to first order around the current model.  Far from consistency (NIS/dof above
:data:`SCREEN_MAX_DISPERSION`, or the filter lost lock) the innovations are not the small
perturbations the sensitivity describes, and every candidate is re-run.  Close to it, the
test uses the same quasi-likelihood correction as the re-runs' ratio test (LM divided by
the dispersion), at the loose level :data:`SCREEN_P` — measured against the full re-runs in
``benchmarks/discovery_screening.py`` (doc/benchmarks.md).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from stellar_cal_ros.core import distributions as dist
from stellar_cal_ros.diagnosis import reliability
from stellar_cal_ros.effects import registry
from stellar_cal_ros.methods import registry as methods

#: a candidate is re-run when its score test's unadjusted p-value is below this
SCREEN_P = 0.05

#: the score test is local: when the current model is this far off (NIS/dof), or lost lock
#: and re-acquired, its linearization no longer predicts what an added effect would do, and
#: every candidate is re-run
SCREEN_MAX_DISPERSION = 2.0

ScreenFn = Callable[..., dict[str, tuple]]


@dataclass
class ScreenResult:
    """The score test of one candidate."""

    lm: float  #: sᵀ I⁻¹ s, not divided by the dispersion
    dof: int
    information: np.ndarray  #: (k, k) over the evaluation window
    sensitivity: np.ndarray | None = None  #: (n_θ, k): ∂θ̂/∂β of the current model
    dispersion: float = 1.0  #: of the screening run (mean NIS/dof, at least 1)
    local: bool = True  #: the current model is close enough for a local test
    #: bias rows of derived quantities per unit of β: ``{name: (k,)}`` (the equivalent
    #: principal point)
    derived: dict[str, np.ndarray] = field(default_factory=dict)
    score: np.ndarray | None = None  #: s = Σ Aᵀ S⁻¹ ν (k,)
    #: per alternative of the same stage scored by the same run: the information left
    #: once it is fitted beside this candidate (:func:`alternatives`)
    beside: dict[str, np.ndarray] = field(default_factory=dict)
    #: (k, r) the directions the test sums over where some are blind (:meth:`tested`):
    #: ``D B``, the score seen along its columns; None: every direction
    basis: np.ndarray | None = None

    @property
    def statistic(self) -> float:
        """The quasi-score statistic LM / dispersion (as the re-runs' Λ is divided)."""
        return self.lm / self.dispersion

    @property
    def p_value(self) -> float:
        """P(χ²_dof > LM / dispersion)."""
        return float(dist.chi2.sf(max(self.statistic, 0.0), max(self.dof, 1)))

    def tested(self, effect_id: str, alpha: float, calibration: Any = None) -> ScreenResult:
        """The test on the directions that are not blind, at the round's level ``alpha``.

        (:func:`~stellar_cal_ros.diagnosis.reliability.tested_directions`.)
        ``LM = Σ (uᵢᵀ D s)² / μᵢ`` over those directions, their count the dof, the
        information without the blind ones (the MDB's, :func:`~stellar_cal_ros.diagnosis.
        reliability.detectability`) and the directions (``basis``: what :meth:`response`
        weighs a paired score difference along); itself where every direction is seen (or
        none is).
        """
        tested = reliability.tested_directions(effect_id, self.information, alpha,
                                               calibration)
        if tested is None or self.score is None:
            return self
        B, mu = tested
        z = B.T @ (reliability.plausible_size(effect_id, calibration) * self.score)
        return replace(self, lm=float(np.sum(z * z / mu)), dof=int(mu.size),
                       information=reliability.tested_information(effect_id, tested,
                                                                  calibration),
                       basis=reliability.tested_basis(effect_id, tested, calibration))

    def response(self, d: np.ndarray, information: np.ndarray | None = None,
                 dispersion: float | None = None) -> float:
        """The non-centrality of this test's statistic whose score moved by ``d``.

        :func:`~stellar_cal_ros.diagnosis.reliability.score_response` on the test's
        directions (``basis``): the paired response of an injection, λ₀ at the MDB where the
        score is linear in the effect.  ``information``: another run's (a twin's), where not
        the test's own; ``dispersion``: the test's where not given (a twin that fits: 1).
        """
        return reliability.score_response(
            d, self.information if information is None else information,
            self.dispersion if dispersion is None else dispersion, basis=self.basis)

    @property
    def passes(self) -> bool:
        """Worth a full augmented re-run (always, when the test is not local)."""
        return not self.local or self.p_value < SCREEN_P


def kernel_scores(result, candidates: list[str]) -> dict[str, tuple]:
    """The kernel's score tests of a run made with ``consider=candidates``.

    ``{effect: (LM, dof, I, bias_per_unit, derived, score, beside)}``; ``derived`` holds the
    bias rows of the equivalent principal point, ``J_θ (−M_θ) − J_β`` (its error in the
    current model minus the shift the effect itself makes); ``score`` is ``s`` (the
    injection checks compare it between paired bags); ``beside`` the information left with
    each alternative fitted beside it (:func:`alternatives`: those of its stage).
    """
    from stellar_cal_ros.diagnosis.runstats import EPP_NAMES
    from stellar_cal_ros.methods.results import epp_jacobian
    from stellar_cal_ros.methods.screening import score_tests

    flt = result.filter
    n = flt.P_est
    try:
        J = epp_jacobian(flt.model, np.asarray(flt.theta, dtype=float), flt.model.size)[1]
    except Exception:  # a model without a camera chain: no derived rows
        J = None
    out = {}
    for eid, c in score_tests(result, list(candidates)).items():
        derived = {}
        if J is not None:
            sl = flt.model.slices[eid]
            rows = J[:, :n] @ c.bias_per_unit - J[:, sl]
            derived = dict(zip(EPP_NAMES, rows, strict=True))
        out[eid] = (c.lm, c.dof, c.info, c.bias_per_unit, derived, c.info @ c.estimate,
                    alternatives(eid, c.beside))
    return out


def alternatives(effect_id: str, beside: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The entries of ``beside`` (other candidate → information left) of ``effect_id``'s stage.

    An effect shares its shape with effects acting where it acts (a tangential distortion
    with the principal point and the detector tilt, a gyro scale factor with a
    misalignment); :func:`parts` keeps a stage's candidates in one screening run, so the
    set is the same on any number of workers.
    """
    stage = registry.create(effect_id).stage
    return {a: np.asarray(v, dtype=float) for a, v in beside.items()
            if registry.create(a).stage == stage}


def screen_function(method: str) -> ScreenFn | None:
    """The screening of ``method``: the kernel's one-pass score test, or None.

    The score test needs runs that carry consider parameters
    (:attr:`~stellar_cal_ros.methods.registry.MethodSpec.consider`: the filter methods); for
    any other method every candidate is re-run.
    """
    return kernel_scores if methods.get(method).consider else None


def is_local(run) -> bool:
    """Whether a run is close enough to consistent for the score test.

    ``run`` is a :class:`~stellar_cal_ros.diagnosis.runstats.RunSummary`: NIS/dof at most
    :data:`SCREEN_MAX_DISPERSION`, and it never lost lock.
    """
    if not run.ok or not run.window:
        return False
    nis = run.window["nis"]["mean"] / 2.0
    return bool(np.isfinite(nis) and nis <= SCREEN_MAX_DISPERSION and not run.lost_lock)


def dispersion(run) -> float:
    """Mean NIS/dof of a run's window, at least 1 (the quasi-likelihood factor)."""
    return max(1.0, run.window["nis"]["mean"] / 2.0)


def _screen_cost(effect_id: str) -> float:
    """Relative cost of an effect's sensitivity: its columns.

    Every candidate's columns go through the same compiled frame step (an astrometric
    correction's per-frame pyerfa call, once 4x a column, is computed for the whole bag
    before the run: ``ScaledDirection.prepare``).
    """
    return float(registry.create(effect_id).size)


def parts(candidates: list[str], n: int) -> list[list[str]]:
    """Split ``candidates`` into at most ``n`` parts of similar screening cost.

    A stage's candidates stay together (a candidate is told from its alternatives by their
    joint information, which only a run scoring both has: :func:`alternatives`); the
    stages' groups longest first, each to the cheapest part so far (the order within a part
    keeps the candidates' order).
    """
    groups: dict[Any, list[str]] = {}
    for e in candidates:
        groups.setdefault(registry.create(e).stage, []).append(e)
    n = max(1, min(n, len(groups)))
    loads = [0.0] * n
    out: list[list[str]] = [[] for _ in range(n)]
    for g in sorted(groups.values(), key=lambda g: sum(map(_screen_cost, g)), reverse=True):
        k = int(np.argmin(loads))
        out[k].extend(g)
        loads[k] += sum(map(_screen_cost, g))
    order = {e: i for i, e in enumerate(candidates)}
    return [sorted(p, key=order.__getitem__) for p in out if p]


def collect(runs: list[Any], white: bool = True, alpha: float = 0.0,
            calibration: Any = None) -> dict[str, ScreenResult]:
    """The :class:`ScreenResult` of every candidate scored by the screening ``runs``.

    Each run is a :class:`~stellar_cal_ros.diagnosis.runstats.RunSummary` whose ``scores``
    holds its part's raw score tests; all parts ran the same current model.

    ``white=False``: the noise verdict found motion the stars see beyond the IMU's own
    noise (:attr:`~stellar_cal_ros.diagnosis.noise.NoiseVerdict.beyond`: a wandering gyro
    bias, a wobble), which the run's noise does not carry.  Its innovations then drift
    together from frame to frame, while the score test's information ``I`` is that of white
    innovations: ``LM`` overstates the evidence of any candidate whose columns follow the
    drift, and no test is local (every candidate is re-run and decided by the prequential
    ratio alone).  Measured (unseen case ``bias_walk``, 300 s, a gyro bias random walk of
    0.3 deg/h/√h): gyro_misalignment's score p 1.5e-14 while its re-run gained 4 of
    log-likelihood for 6 parameters (ratio p 0.24), added with every angle ±71 arcsec.

    ``alpha`` (> 0): the round's level for the MDB; each test is then the one on the
    directions that are not blind for ``calibration``'s camera (:meth:`ScreenResult.tested`).
    """
    out: dict[str, ScreenResult] = {}
    for run in runs:
        if not run.ok or run.scores is None:
            continue
        local, disp = is_local(run) and white, dispersion(run)
        for eid, item in run.scores.items():
            lm, dof, info = item[:3]
            sens = item[3] if len(item) > 3 else None
            derived = {k: np.asarray(v, dtype=float)
                       for k, v in (item[4] if len(item) > 4 else {}).items()}
            out[eid] = ScreenResult(float(lm), int(dof),
                                    np.atleast_2d(np.asarray(info, dtype=float)),
                                    None if sens is None else np.asarray(sens, dtype=float),
                                    disp, local, derived,
                                    np.asarray(item[5], dtype=float) if len(item) > 5
                                    else None,
                                    dict(item[6]) if len(item) > 6 else {})
            if alpha > 0:
                out[eid] = out[eid].tested(eid, alpha, calibration)
    return out
