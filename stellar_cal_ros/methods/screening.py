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
  (``bias_per_unit``);
* the information about c left once each other candidate a of the run is fitted beside
  it, ``I_cc − I_ca I_aa⁺ I_ac`` (``beside``): what tells c from a on this motion (the
  identification size, :func:`~stellar_cal_ros.diagnosis.reliability.identification`).
  The minimal detectable size ``b`` (internal reliability) is the diagnosis's, for the
  decision's level and dof (:func:`~stellar_cal_ros.diagnosis.reliability.detectability`):
  none is computed here.

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
    #: per other candidate a of the run: I_cc − I_ca I_aa⁺ I_ac (k, k)
    beside: dict[str, np.ndarray] = field(default_factory=dict)

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
    info = 0.5 * (sens.info + sens.info.T)
    cols = {eff.id: np.arange(model.slices[eff.id].start - P_est,
                              model.slices[eff.id].stop - P_est)
            for eff in model.effects if eff.id in candidates}
    # each candidate's information on the directions the data see, pseudo-inverted
    inverse = {e: _seen_inverse(info[np.ix_(c, c)]) for e, c in cols.items()}
    out: dict[str, CandidateScore] = {}
    for eff in model.effects:
        if eff.id not in candidates:
            continue
        c = cols[eff.id]
        s = sens.score[c]
        I_cc = info[np.ix_(c, c)]
        # the test lives in the identifiable subspace (a direction the data do not see
        # has no score)
        inv, dof = inverse[eff.id]
        lm = float(s @ inv @ s) if dof else 0.0
        beside = {}
        for a, ca in cols.items():
            if a != eff.id:
                I_ca = info[np.ix_(c, ca)]
                beside[a] = I_cc - I_ca @ inverse[a][0] @ I_ca.T
        out[eff.id] = CandidateScore(
            effect=eff.id, parameters=[f"{eff.id}.{n}" for n in eff.parameter_names],
            dof=dof, lm=lm, estimate=inv @ s, info=I_cc,
            bias_per_unit=-M_theta[:, c], beside=beside)
    return out


def _seen_inverse(I_cc: np.ndarray) -> tuple[np.ndarray, int]:
    """The pseudo-inverse of an information block on the directions it sees, and their count."""
    w, V = np.linalg.eigh(I_cc)
    good = w > 1e-12 * max(float(w.max(initial=0.0)), 1e-300)
    if not good.any():
        return np.zeros_like(I_cc), 0
    return (V[:, good] / w[good]) @ V[:, good].T, int(good.sum())
