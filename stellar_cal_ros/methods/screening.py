"""Score tests of many candidate effects in one filter run (and what could still hide).

The current model is run once with every candidate effect as a *consider* parameter: kept at
its prior value, predicted through, and tracked by the sensitivity recursion of
:class:`~stellar_cal_ros.core.covariance.Sensitivity` (Willsky & Jones 1976).  Over the
evaluation window that gives, for all candidates jointly, the score ``s = Σ Aᵀ S⁻¹ ν`` and
the Fisher information ``I = Σ Aᵀ S⁻¹ A`` of the innovations with respect to the candidates'
parameters.  For each candidate c (its block of parameters, the others at their prior):

* the Lagrange-multiplier (score) statistic ``LM_c = s_cᵀ I_cc⁻¹ s_c``, χ² with ``k_c`` dof
  when the candidate is absent — the full augmented re-run is needed only for candidates
  this flags, instead of every candidate (one run instead of 11–19);
* the one-step estimate ``b̂_c = I_cc⁻¹ s_c`` and its covariance ``I_cc⁻¹``;
* the bias an undetected effect ``b`` leaves in the estimated parameters (external
  reliability): ``−M_θ b`` with ``M`` the state's sensitivity at the end of the run
  (``bias_per_unit``).  The minimal detectable size ``b`` (internal reliability) is the
  diagnosis's, for the decision's level and dof
  (:func:`~stellar_cal_ros.diagnosis.reliability.detectability`): none is computed here.

Innovations a wrong model over-disperses (NIS/dof > 1) inflate every LM; the caller divides
by the dispersion (quasi-score), as the likelihood-ratio test does.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from stellar_cal_ros.methods.results import ReplayResult


@dataclass
class CandidateScore:
    """One candidate's score test and reliability numbers (its parameters' units)."""

    effect: str
    parameters: list[str]
    dof: int
    lm: float  #: s_cᵀ I_cc⁻¹ s_c (not yet divided by any dispersion)
    estimate: np.ndarray  #: b̂ = I_cc⁻¹ s_c (k,)
    info: np.ndarray  #: I_cc (k, k)
    #: bias of the estimated parameters per unit of each candidate parameter (P_est, k)
    bias_per_unit: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    def p_value(self, dispersion: float = 1.0) -> float:
        """P(χ²_k > LM / dispersion)."""
        from stellar_cal_ros.core.distributions import chi2

        return float(chi2.sf(self.lm / max(dispersion, 1e-300), self.dof))


def score_tests(result: ReplayResult, candidates: list[str]) -> dict[str, CandidateScore]:
    """Per-candidate score tests from a run made with ``consider=candidates``.

    ``result`` is :func:`~stellar_cal_ros.methods.replay.replay` of the current model with
    the candidates as consider effects (their order in the run's model is the registry's).
    """
    flt = result.filter
    sens = flt.sensitivity
    if sens is None:
        raise ValueError("the run has no consider parameters (replay(..., consider=...))")
    model, P_est = flt.model, flt.P_est
    M_theta = sens.M[flt.it]
    out: dict[str, CandidateScore] = {}
    for eff in model.effects:
        if eff.id not in candidates:
            continue
        sl = model.slices[eff.id]
        cols = np.arange(sl.start - P_est, sl.stop - P_est)
        s = sens.score[cols]
        I_cc = sens.info[np.ix_(cols, cols)]
        I_cc = 0.5 * (I_cc + I_cc.T)
        w, V = np.linalg.eigh(I_cc)
        good = w > 1e-12 * max(float(w.max(initial=0.0)), 1e-300)
        # the test lives in the identifiable subspace (a direction the data do not see
        # has no score)
        inv = (V[:, good] / w[good]) @ V[:, good].T if good.any() else np.zeros_like(I_cc)
        lm = float(s @ inv @ s) if good.any() else 0.0
        out[eff.id] = CandidateScore(
            effect=eff.id, parameters=[f"{eff.id}.{n}" for n in eff.parameter_names],
            dof=int(good.sum()), lm=lm, estimate=inv @ s, info=I_cc,
            bias_per_unit=-M_theta[:, cols])
    return out
