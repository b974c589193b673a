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
* the minimal detectable size (Teunissen's internal reliability): along each eigenvector
  ``d`` of ``I_cc`` (eigenvalue ``ι``), an effect of size ``√(λ₀ / ι)`` is found with power
  ``power`` by a test of size ``alpha`` (``λ₀`` the non-centrality of χ²_k that reaches it);
* the bias an undetected effect of that size leaves in the estimated parameters (external
  reliability): ``−M_θ b`` with ``M`` the state's sensitivity at the end of the run — per
  parameter of the candidate at its own MDB (:meth:`CandidateScore.bias_of_mdb`), the
  shift an injection of that size reproduces.

Innovations a wrong model over-disperses (NIS/dof > 1) inflate every LM; the caller divides
by the dispersion (quasi-score), as the likelihood-ratio test does.
"""

from __future__ import annotations

import math
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
    mdb: np.ndarray  #: minimal detectable size along each eigenvector of I_cc (k,)
    mdb_directions: np.ndarray  #: eigenvectors (k, k), columns
    #: bias of the estimated parameters per unit of each candidate parameter (P_est, k)
    bias_per_unit: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    def p_value(self, dispersion: float = 1.0) -> float:
        """P(χ²_k > LM / dispersion)."""
        from stellar_cal_ros.core.distributions import chi2

        return float(chi2.sf(self.lm / max(dispersion, 1e-300), self.dof))

    def mdb_per_parameter(self, alpha: float = 0.001, power: float = 0.8) -> np.ndarray:
        """MDB of each parameter alone, ``sqrt(λ₀ / I_jj)`` (k,), inf where I_jj = 0."""
        lam = noncentrality(max(self.dof, 1), alpha, power)
        d = np.diag(self.info)
        return np.where(d > 0, np.sqrt(lam / np.where(d > 0, d, 1.0)), math.inf)

    def bias_of_mdb(self, alpha: float = 0.001, power: float = 0.8) -> np.ndarray:
        """Shift of the estimated parameters from each candidate parameter alone at its MDB.

        (P_est, k): column j is ``bias_per_unit[:, j] · MDB_j`` — what injecting parameter
        j at its MDB does to the current model's estimate (a direction the data do not see
        has an infinite MDB and no column worth printing: NaN).  Not along the eigenvectors
        of ``info``: an eigen-direction with almost no information (a gyro misalignment's
        antisymmetric part, which the installation absorbs) has an MDB of thousands of
        arcsec and would print a bias of the same size beside a few-arcsec MDB.
        """
        mdb = self.mdb_per_parameter(alpha, power)
        with np.errstate(invalid="ignore"):
            return np.where(np.isfinite(mdb)[None, :], self.bias_per_unit * mdb[None, :],
                            np.nan)


def noncentrality(dof: int, alpha: float = 0.001, power: float = 0.8) -> float:
    """λ₀: the non-centrality at which a χ²_dof test of size ``alpha`` has ``power``."""
    from scipy.optimize import brentq

    from stellar_cal_ros.core.distributions import chi2, ncx2

    crit = chi2.isf(alpha, dof)
    return float(brentq(lambda lam: ncx2.sf(crit, dof, lam) - power, 1e-6, 1e4))


def score_tests(result: ReplayResult, candidates: list[str], alpha: float = 0.001,
                power: float = 0.8) -> dict[str, CandidateScore]:
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
        # has no score and an infinite minimal detectable size)
        inv = (V[:, good] / w[good]) @ V[:, good].T if good.any() else np.zeros_like(I_cc)
        lm = float(s @ inv @ s) if good.any() else 0.0
        k = int(good.sum())
        lam = noncentrality(max(k, 1), alpha, power)
        mdb = np.where(good, np.sqrt(lam / np.where(good, w, 1.0)), math.inf)
        out[eff.id] = CandidateScore(
            effect=eff.id, parameters=[f"{eff.id}.{n}" for n in eff.parameter_names],
            dof=k, lm=lm, estimate=inv @ s, info=I_cc, mdb=mdb, mdb_directions=V,
            bias_per_unit=-M_theta[:, cols])
    return out
