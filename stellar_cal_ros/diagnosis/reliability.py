"""Detectability and reliability of the model (Teunissen's internal and external reliability).

Internal reliability: the *minimal detectable bias* (MDB) of a candidate effect β (k
parameters) is the size it must have for the round's test to find it with probability
``POWER`` at the test's level α (Bonferroni over the round's candidates).  With ``I`` the
information the evaluation window carries about β (nuisance parameters marginalized), the
test statistic is non-central χ²_k with non-centrality ``λ = bᵀ I b``, so the MDB along a
direction ``d`` is ``sqrt(λ₀ / dᵀ I d)`` with ``λ₀ = λ(α, POWER, k)`` (:func:`lambda0`).
The test and its MDB leave out the directions an effect of plausible size cannot reach λ₀
along (:func:`tested_directions`): k counts the others, and those left out are the blind
directions of the report (:func:`blind_directions`): one rule, :func:`split_directions`.

Where the round divides its statistics by the residuals' dispersion φ (quasi-likelihood:
the ratio statistic, and a screened round's score statistic ``LM / φ``) an effect ``b``
gives the printed test the non-centrality ``bᵀ I b / φ``, so the MDB is stated for φ,
``sqrt(φ λ₀ / dᵀ I d)``: the bias the printed test detects with the printed power
(Teunissen's MDB with the variance factor the test uses).  Not dividing the statistic
instead would keep the MDB of residuals as stated but give the test the level α only
where the noise is as stated: on residuals at φ x their stated variance its false-alarm
rate grows (the score's covariance is φ I).  Until H295 a screened round stated its MDB for
φ = 1 (:func:`~stellar_cal_ros.diagnosis.discover.rank_round`).

``I`` is the information of the evaluation window, where the decision's statistics are
summed: the screening pass's (:mod:`~stellar_cal_ros.diagnosis.screening`) ``Σ Aᵀ S⁻¹ A``
over the window, for a candidate screened out and for one re-run alike
(:func:`~stellar_cal_ros.diagnosis.discover.window_information`; a round that is not
screened scores its candidates on its current model's run for the MDB alone).  Only a
candidate no run scored takes it from its augmented run: ``I_data = (P_post)_ββ⁻¹ −
(P_prior)_ββ⁻¹`` (the marginal posterior block already has the other parameters
marginalized; the screening's sum over every frame, to 1e-4), scaled by the share of the
accepted stars that lie in the window -- an approximation: the information is not spread
over the run as the stars are (the window holds 16-98 % of it for 44-49 % of the stars).

Identification: an alternative that shares an effect's shape on this motion (a candidate
of its stage whose span holds at least :data:`SHARED_SHAPE` of the effect's information
along a parameter) scores it nearly as well, and the selection names the effect as itself
only when its test *beside* the alternative rejects too (otherwise the one added is said
with "or" the other, :func:`~stellar_cal_ros.diagnosis.auto._tie`, or the alternative is
added).  Teunissen's minimal identifiable bias, for that rule: per parameter the size at
which the test of the effect beside each such alternative (its information
``I_cc − I_ca I_aa⁺ I_ac``) rejects at the tie's level with power ``1 − (1 − POWER) / m``
(m alternatives: all of them with power ``POWER`` at least), and never below the MDB
(``mdb_identified``, :func:`identification`).  On the swaying bag where a tangential
distortion shares 0.89 of its information with the principal point and with the tilt, 2 of
16 twins at its MDB named it as itself (6 more "or" one of them): doc/benchmarks.md.

An effect is *not testable with this motion* only when its MDB exceeds its plausible
physical size (stated on its class where it acts and converted to its parameters for the
run's camera, :func:`plausible_size`) in every direction — never because the posterior
stays near a prior σ that may have been set too small.

External reliability: an effect β = b left out of the model shifts the estimated
parameters θ by ``b_θ = −P_θβ P_ββ⁻¹ b`` (the shift of the conditional mean when β is
pinned to zero; P is the augmented run's joint posterior), or ``−M_θ b`` from a screening
pass's sensitivity.  The report states, per parameter of the effect, the shift that
parameter alone at its printed MDB causes — the number an injection of that size
reproduces (``test/test_reliability_injection.py``, ``benchmarks/reliability_injection.py``)
— and, separately, the directions the data cannot see at all with the shift an effect of
plausible size along them leaves undetected (:func:`blind_directions`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np
from scipy import optimize

from stellar_cal_ros.core import distributions as dist
from stellar_cal_ros.effects import registry

#: power at which the minimal detectable bias is defined
POWER = 0.8
#: a parameter is "dominated" when a hidden effect's bias exceeds this many of its sigmas
DOMINATES_SIGMA = 1.0
#: a printed bias is first-order only (``remainders``) below this share of the largest
#: shift, in sigmas, the same injection makes: beside a large shift the filter's response
#: departs from the sensitivity recursion by up to 1.4 % of that shift (doc/benchmarks.md,
#: image_plane_tilt at its MDB, seeds 5-12: gyro_bias.by 1.32 sigma printed, ~0 measured,
#: beside 97.6 sigma), so 30 % needs >= 0.047 of it; 0.15 leaves a factor 3.  A diagnosis
#: measures these rows by probe runs (:mod:`~stellar_cal_ros.diagnosis.reliability_probe`)
FIRST_ORDER_SHARE = 0.15
#: an alternative shares an effect's shape when its span holds at least this share of the
#: effect's information along a parameter (ρ²): its score test then takes at least this
#: share of the effect's non-centrality, as the selection's rival of an added effect does
#: (:data:`~stellar_cal_ros.diagnosis.auto.RIVAL_SCORE`, the same 0.5)
SHARED_SHAPE = 0.5

def plausible_size(effect_id: str, calibration: Any = None) -> np.ndarray:
    """Plausible size per parameter of ``effect_id`` (its units) for ``calibration``'s camera.

    Each effect states its plausible size where it acts on its class (``plausible``: px at
    the detector corner, arcsec, ppm, ms ...); :meth:`Effect.plausible_parameters` converts
    it to the parameters for this camera (a k3 is 5 px at the corner, whatever the lens).
    """
    return registry.create(effect_id).plausible_parameters(calibration)


@lru_cache(maxsize=256)
def lambda0(alpha: float, dof: int, power: float = POWER) -> float:
    """Non-centrality λ₀ at which a χ²_dof test of level ``alpha`` has power ``power``."""
    dof = max(int(dof), 1)
    return noncentrality_beyond(float(dist.chi2.isf(alpha, dof)), dof, power)


def split_directions(effect_id: str, information: np.ndarray, alpha: float,
                     calibration: Any = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The one rule for the directions of an effect a test sees and those it is blind to.

    The eigen-directions ``U`` of the information whitened by the plausible sizes ``D``
    (``D I D = U diag(μ) Uᵀ``) and ``seen``: along them an effect of plausible size reaches
    the test's non-centrality, ``μ ≥ λ₀(α, k)`` with ``k`` the effect's parameter count.
    Judged for residuals as the noise states them (``information`` not divided by a
    dispersion, as :attr:`Detectability.testable` is), so the test's directions and its
    dof do not move with a round's dispersion.  The test sums over the seen directions
    (:func:`tested_directions`); the others are its blind ones (:func:`blind_directions`):
    a direction is one or the other, never both.  (Until H295 the blind ones were read
    from the information divided by the dispersion φ, with λ₀ at the tested dof: above
    φ = 1 a direction the test sums over could be listed as blind too.)

    Returns ``(U, μ, seen)``: ``U`` (k, k) whitened (``b = D U c``), ``μ`` (k,), ``seen``
    (k,) bool.
    """
    info = _sym(np.atleast_2d(np.asarray(information, dtype=float)))
    D = plausible_size(effect_id, calibration)
    mu, U = np.linalg.eigh(_sym(info * np.outer(D, D)))
    return U, mu, mu >= lambda0(alpha, info.shape[0])


def tested_directions(effect_id: str, information: np.ndarray, alpha: float,
                      calibration: Any = None) -> tuple[np.ndarray, np.ndarray] | None:
    """The directions of an effect its tests sum over, where some of them are blind.

    The eigen-directions ``u`` of the information whitened by the plausible sizes ``D``
    along which an effect of plausible size reaches the test's non-centrality
    (:func:`split_directions`, the rule :func:`blind_directions` reads too).  A blind
    direction adds a χ²₁ of no power to the score statistic at best, and where the
    information there comes from a measurement whose error is not the noise it is stated
    as, not even that: on the swaying base the installation absorbs a gyro
    misalignment's rotation of the gyro axes from the stars, what is left of it (1.7e-5 to
    7.9e-5 of the largest eigenvalue, μ 1.7-8.2 for λ₀ 28) is seen through the position
    reference, whose error is the base's sway (a motion, stated as ±2 m of white noise),
    and the score there scatters 0.04-0.24 instead of 1 (doc/benchmarks.md, H278): the
    statistic counted 6 dof and held about 3.  The test (:meth:`~stellar_cal_ros.diagnosis.
    screening.ScreenResult.tested`) and its MDB (:func:`detectability`) are both stated on
    the directions returned, with their count as the dof.

    Returns ``(B, μ)``: ``B`` (k, r) the directions in whitened units (``b = D B c``),
    ``μ`` (r,) their information; None where every direction is seen or none is (an
    untestable effect keeps its whole test).
    """
    return _tested(split_directions(effect_id, information, alpha, calibration))


def _tested(split: tuple[np.ndarray, np.ndarray, np.ndarray]
            ) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`tested_directions` of a :func:`split_directions`."""
    U, mu, seen = split
    if seen.all() or not seen.any():
        return None
    return U[:, seen], mu[seen]


def tested_information(effect_id: str, directions: tuple[np.ndarray, np.ndarray],
                       calibration: Any = None, block: np.ndarray | None = None) -> np.ndarray:
    """The information on the tested ``directions`` (:func:`tested_directions`), (k, k).

    ``D⁻¹ B diag(μ) Bᵀ D⁻¹``: the whole information with its blind directions left out.
    ``block``: another information of the effect (one left beside an alternative,
    :func:`identification`'s ``beside``) seen on the same directions, ``D⁻¹ Π D block D Π
    D⁻¹`` with ``Π = B Bᵀ``.
    """
    B, mu = directions
    D = plausible_size(effect_id, calibration)
    if block is not None:
        Pi = B @ B.T
        DD = np.outer(D, D)
        return _sym(Pi @ (np.atleast_2d(np.asarray(block, dtype=float)) * DD) @ Pi / DD)
    W = B / D[:, None]
    return _sym((W * mu) @ W.T)


def tested_basis(effect_id: str, directions: tuple[np.ndarray, np.ndarray],
                 calibration: Any = None) -> np.ndarray:
    """``D B`` (k, r): the tested ``directions`` (:func:`tested_directions`) as the score's.

    The test's statistic is ``Σ (uᵢᵀ D s)² / μᵢ``: the score ``s`` seen along the columns
    of ``D B`` (:func:`score_response`'s ``basis``).
    """
    return plausible_size(effect_id, calibration)[:, None] * directions[0]


def score_response(d: np.ndarray, information: np.ndarray, dispersion: float = 1.0,
                   basis: np.ndarray | None = None) -> float:
    """``Δsᵀ I⁻¹ Δs / φ``: the non-centrality of a score test whose score moved by ``d``.

    ``information``: the score's ``I``; ``dispersion`` φ the round's, which the decision's
    statistic ``LM / φ`` is divided by (the innovations scatter φ x their stated S: the
    score's covariance is φ I, its response to an effect ``b`` ``Δs = I b``, so the
    non-centrality is ``bᵀ I b / φ``).  Until H285 ``φ Δsᵀ I⁻¹ Δs``: the information was
    divided by φ and the score was not, a response φ² too large (the bag probe's, on a bag
    of dispersion up to :data:`~.reliability_probe.FITS`: up to 1.44x; clean psce 300 s
    s21, φ 1.021: 1.04x, which hid a gyro misalignment's response 0.96 λ₀ and a tilt's).
    The paired response of an injection (:mod:`~.verify`'s twins, :mod:`~.reliability_probe`'s
    runs on the user's bag), λ₀ at the MDB where the score is linear in the effect.

    ``basis`` (k, r): the test's directions where some are blind (``D B``,
    :func:`tested_directions`, kept by :meth:`~stellar_cal_ros.diagnosis.screening.
    ScreenResult.tested`): the response of the test on them, ``vᵀ (Wᵀ I W)⁻¹ v`` with
    ``v = Wᵀ Δs`` — ``Σ (uᵢᵀ D Δs)² / μᵢ`` for the information the directions were found
    in (``Wᵀ I W = diag(μ)``, whole or without its blind directions alike), and the same
    directions weighed by another run's information (a twin's) elsewhere.  (``Δsᵀ I_t⁺ Δs``
    of the information without the blind directions, :func:`tested_information`, is the
    same only where the plausible sizes are alike — a gyro misalignment's — as ``D⁻¹ B``'s
    columns are then orthogonal.)  The whole information's ``Δsᵀ I⁻¹ Δs`` adds the blind
    directions' response: 1.03-1.28 λ₀ for a gyro misalignment at ± its MDB on a clean
    300-s psce bag, where the test's is λ₀ within 0.2 % (doc/benchmarks.md, H285).
    """
    info = np.atleast_2d(np.asarray(information, dtype=float))
    d = np.asarray(d, dtype=float)
    if basis is not None:
        v = basis.T @ d
        return float(v @ np.linalg.pinv(basis.T @ info @ basis) @ v) / float(dispersion)
    return float(d @ np.linalg.pinv(info) @ d) / float(dispersion)


def noncentrality_beyond(crit: float, dof: int, power: float = POWER) -> float:
    """Non-centrality λ at which a non-central χ²_dof(λ) exceeds ``crit`` with ``power``.

    0 when a central χ²_dof does already.
    """
    dof = max(int(dof), 1)
    if dist.chi2.sf(crit, dof) >= power:
        return 0.0

    def gap(lam: float) -> float:
        return float(dist.ncx2.sf(crit, dof, lam) - power)

    hi = max(crit, 1.0)
    while gap(hi) < 0:
        hi *= 2.0
    return float(optimize.brentq(gap, 1e-9, hi, xtol=1e-6))


def delta_t(alpha: float, nu: float, power: float = POWER) -> float:
    """Shift δ (in σ) at which a two-sided t_ν test of level ``alpha`` has power ``power``.

    The t_ν counterpart of ``√λ₀(alpha, 1)`` (:func:`lambda0`), for a test referred to
    Student's t (the frame-robust tests, :func:`~stellar_cal_ros.diagnosis.stats.
    frame_robust_t`): ``P(|T| > t_ν,1−α/2) = power``, ``T`` non-central t with ``δ``.
    """
    nu = min(max(float(nu), 1.0), 1e4)  # scipy's nct is NaN far out; t_1e4 is the normal
    crit = dist.t.isf(alpha / 2.0, nu)

    def gap(d: float) -> float:
        # the far tail by symmetry (scipy's nct.cdf is NaN there for small ν)
        return float(dist.nct.sf(crit, nu, d) + np.nan_to_num(dist.nct.sf(crit, nu, -d))
                     - power)

    hi = crit + 4.0
    while gap(hi) < 0:
        hi *= 2.0
    return float(optimize.brentq(gap, 0.0, hi, xtol=1e-6))


def _sym(A: np.ndarray) -> np.ndarray:
    return 0.5 * (A + A.T)


def _inverse(A: np.ndarray) -> np.ndarray:
    A = _sym(np.atleast_2d(A))
    try:
        return np.linalg.inv(A)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(A)


def data_information(P_post: np.ndarray, sigma_prior: np.ndarray,
                     window_share: float = 1.0) -> np.ndarray:
    """Information about an effect from its augmented run, ``(k, k)`` in its units⁻².

    ``(P_post⁻¹ − diag(σ_prior)⁻²) × window_share``, clipped to positive semi-definite
    (process noise and round-off can make the difference slightly indefinite).
    """
    P_post = np.atleast_2d(np.asarray(P_post, dtype=float))
    prior_info = np.diag(1.0 / np.maximum(np.asarray(sigma_prior, dtype=float), 1e-300) ** 2)
    I_data = _sym(_inverse(P_post) - prior_info)
    w, V = np.linalg.eigh(I_data)
    return (V * np.clip(w, 0.0, None)) @ V.T * float(window_share)


@dataclass
class Detectability:
    """MDB of one candidate effect on this bag."""

    effect: str
    dof: int
    alpha: float
    lam0: float
    information: np.ndarray  # (k, k) in the effect's units⁻²
    plausible: np.ndarray  # (k,)
    mdb: dict[str, float] = field(default_factory=dict)  # per parameter, effect units
    #: MDB / plausible size along the best-determined direction (≤ 1: testable)
    ratio: float = float("inf")
    #: the plausible size as the class states it, per parameter (e.g. '5 px at the
    #: detector corner'), and each MDB in that statement's unit where the camera converts it
    plausible_text: dict[str, str] = field(default_factory=dict)
    mdb_where_it_acts: dict[str, float] = field(default_factory=dict)
    #: the decision statistic's dispersion the MDB is stated for (``information`` is the
    #: window's divided by it): 1 where the residuals are as the stated noise says
    dispersion: float = 1.0
    #: where the excess gate binds (a candidate must remove MIN_EXPLAINED of the excess
    #: variance, :func:`detectability`'s ``gate``): the test's MDB per parameter (``mdb``
    #: is then the gate's, larger) and the non-centrality the gate asks, in the units of
    #: ``lam0``; empty and 0 where the test sets the MDB
    mdb_test: dict[str, float] = field(default_factory=dict)
    lam_gate: float = 0.0
    #: where the gate binds: per parameter the signed size at which an effect of the sign
    #: the misfit already leans to passes it (sooner than ``mdb``, the other sign's)
    mdb_leaning: dict[str, float] = field(default_factory=dict)
    #: where alternatives share its shape (:func:`identification`): per parameter the size
    #: from which it is named as itself, and per alternative its share ρ² per parameter
    mdb_identified: dict[str, float] = field(default_factory=dict)
    shares_shape_with: dict[str, dict[str, float]] = field(default_factory=dict)
    #: (k, n) the directions the test does not sum over (:func:`split_directions`), each
    #: scaled to the plausible ellipsoid (:func:`blind_directions`); None: not found (a
    #: Detectability made without :func:`detectability`): none
    blind: np.ndarray | None = None

    @property
    def testable(self) -> bool:
        """The MDB is below the plausible size in at least one direction.

        Judged for residuals as the noise states them (``ratio / √dispersion``): whether
        this motion can test the effect; a model that does not fit yet does not make it
        untestable (its round still tests it, and its decisions stay those of a round
        whose MDB ignored the dispersion).
        """
        return bool(self.ratio / np.sqrt(self.dispersion) <= 1.0)

    def as_dict(self) -> dict[str, Any]:
        """JSON form: MDB per parameter, plausible size, ratio, testable."""
        names = list(self.mdb)
        return {"mdb": dict(self.mdb),
                "plausible_size": {n: float(p) for n, p in zip(names, self.plausible,
                                                                strict=True)},
                "mdb_over_plausible": self.ratio, "testable": self.testable,
                "plausible_statement": dict(self.plausible_text),
                "mdb_where_it_acts": dict(self.mdb_where_it_acts),
                "alpha": self.alpha, "power": POWER, "lam0": self.lam0, "dof": self.dof,
                **({"dispersion": self.dispersion} if self.dispersion != 1.0 else {}),
                **({"mdb_set_by": "explained_gate", "mdb_test": dict(self.mdb_test),
                    "mdb_leaning": dict(self.mdb_leaning), "lam_gate": self.lam_gate}
                   if self.mdb_test else {}),
                **({"mdb_identified": dict(self.mdb_identified),
                    "shares_shape_with": {a: dict(r) for a, r
                                          in self.shares_shape_with.items()}}
                   if self.mdb_identified else {})}

    def where_text(self) -> str:
        """MDB and plausible size where the effect acts, when the camera converts them.

        E.g. ``k3 0.19 px at the detector corner (plausible 5 px at the detector corner)``;
        '' for a size stated in the parameters' own units (arcsec, ms, ppm).
        """
        out = []
        for n, v in self.mdb_where_it_acts.items():
            statement = self.plausible_text.get(n, "")
            unit = statement.split(" ", 1)[1] if " " in statement else ""
            if np.isfinite(v):
                out.append(f"{n} {v:.3g} {unit} (plausible {statement})")
        return ", ".join(out)


def detectability(effect_id: str, information: np.ndarray, alpha: float,
                  calibration: Any = None, dispersion: float = 1.0,
                  gate: float = 0.0, overlap: np.ndarray | None = None,
                  beside: dict[str, np.ndarray] | None = None,
                  tie_alpha: float = 0.0) -> Detectability:
    """MDB per parameter and the testability of ``effect_id`` given its information.

    ``calibration``: the run's calibration, whose camera converts a plausible size stated
    in px at the detector corner to the parameters (:func:`plausible_size`).
    ``dispersion``: what the decision's statistics are divided by (the round's reference
    run's mean NIS / dof, at least 1, :class:`~stellar_cal_ros.diagnosis.discover.
    Reference`: the quasi-likelihood ratio's, and a screened round's score statistic's,
    :attr:`~stellar_cal_ros.diagnosis.screening.ScreenResult.statistic`): the statistic's
    non-centrality is then ``bᵀ I b / dispersion``, so the information is divided by it and
    the MDB grows by its square root.  The test's directions and the blind ones are judged
    before (:func:`split_directions`).

    ``gate``: the whitened energy ``bᵀ I b`` (``information`` as given, not divided) an
    effect must add to the window's residuals for the candidate to pass the decision's
    excess gate (:meth:`~stellar_cal_ros.diagnosis.discover.Reference.gate_energy`); 0:
    none.  ``overlap``: the score ``s = Σ Aᵀ S⁻¹ ν`` of the current model's residuals
    along the effect (its screening, ``(k,)``): what the misfit shares with the effect's
    pattern.  The effect ``b`` adds ``bᵀ I b + 2 bᵀ s`` to the residuals' whitened energy
    (a non-central χ²_k in the first term: the gate passes with the test's power once the
    sum reaches :func:`noncentrality_beyond` ``(gate)`` = ``q``), so along parameter n
    the sign of ``s_n`` passes at ``(√(s_n² + I_nn q) − |s_n|) / I_nn``
    (``mdb_leaning``, signed) and the other at ``(√(s_n² + I_nn q) + |s_n|) / I_nn``.  An
    MDB is a size of either sign: where the latter exceeds the test's MDB, it is the MDB
    and ``mdb_test`` keeps the test's.  The ratio to the plausible size (``testable``, a
    decision) stays the test's.

    Where some of its directions are blind (:func:`tested_directions`) the MDB is the
    test's on the others: ``information`` without the blind ones, their count the dof.

    ``beside``: per alternative (a candidate of the effect's stage) the effect's
    information left once the alternative is fitted beside it (the screening's,
    :func:`~stellar_cal_ros.diagnosis.screening.alternatives`), in ``information``'s units;
    ``tie_alpha``: the level of the test that tells the two apart
    (:func:`~stellar_cal_ros.diagnosis.auto._tie`).  Gives ``mdb_identified`` and
    ``shares_shape_with`` where an alternative shares the shape (:func:`identification`).
    """
    eff = registry.create(effect_id)
    info = np.atleast_2d(np.asarray(information, dtype=float))
    k = info.shape[0]
    split = split_directions(effect_id, info, alpha, calibration)
    tested = _tested(split)
    if tested is not None:  # the test's directions and count (its blind ones left out)
        info, k = tested_information(effect_id, tested, calibration), tested[1].size
        beside = {a: tested_information(effect_id, tested, calibration, b)
                  for a, b in (beside or {}).items()}  # (the alternatives' on the same)
    info = info / float(dispersion)
    lam = lambda0(alpha, k)
    D = plausible_size(effect_id, calibration)
    diag = np.diag(info)
    mdb = {n: float(np.sqrt(lam / d)) if d > 0 else float("inf")
           for n, d in zip(eff.parameter_names, diag, strict=True)}
    mdb_test: dict[str, float] = {}
    leaning: dict[str, float] = {}
    q = noncentrality_beyond(gate, k) if gate > 0 else 0.0
    if q > 0:
        s = np.zeros(k) if overlap is None else np.asarray(overlap, dtype=float).ravel()
        I_nn = diag * float(dispersion)  # the information as the residuals' energy counts it
        root = np.sqrt(s * s + I_nn * q)
        hard = {n: float((r + abs(x)) / i) if i > 0 else float("inf")
                for n, x, i, r in zip(eff.parameter_names, s, I_nn, root, strict=True)}
        if any(hard[n] > mdb[n] for n in mdb):
            mdb_test = mdb
            mdb = {n: max(hard[n], mdb_test[n]) for n in mdb}
            leaning = {n: float(np.copysign((r - abs(x)) / i, x)) if i > 0 else float("inf")
                       for n, x, i, r in zip(eff.parameter_names, s, I_nn, root,
                                             strict=True)}
    mu = np.linalg.eigvalsh(_sym(info * np.outer(D, D)))
    top = float(mu.max()) if mu.size else 0.0
    ratio = float(np.sqrt(lam / top)) if top > 0 else float("inf")
    text, where = {}, {}
    if eff.plausible is not None:
        text = {n: eff.plausible.text(i) for i, n in enumerate(eff.parameter_names)}
        if eff.plausible_depends_on_camera():
            acts = eff.where_it_acts(np.array(list(mdb.values())), calibration)
            where = {n: float(a) for n, a in zip(eff.parameter_names, acts, strict=True)}
    ident, shared = identification(eff.parameter_names, np.diag(info), beside or {},
                                   tie_alpha, k, float(dispersion), mdb)
    return Detectability(effect_id, k, alpha, lam, info, D, mdb, ratio, text, where,
                         float(dispersion), mdb_test,
                         q / float(dispersion) if mdb_test else 0.0, leaning, ident, shared,
                         D[:, None] * _sparse_basis(split[0][:, ~split[2]]))


def identification(names: list[str], diag: np.ndarray, beside: dict[str, np.ndarray],
                   alpha: float, dof: int, dispersion: float, mdb: dict[str, float]
                   ) -> tuple[dict[str, float], dict[str, dict[str, float]]]:
    """The size from which an effect is named as itself, and who shares its shape.

    ``diag``: the diagonal of the effect's information (divided by ``dispersion``);
    ``beside``: per alternative the information left with it fitted beside (not divided).
    An alternative shares the shape when it holds at least :data:`SHARED_SHAPE` of the
    information along some parameter (``ρ² = 1 − I_{c|a,nn} / I_nn``).  With m such
    alternatives each test beside one, χ²_dof at level ``alpha``, must reject with power
    ``1 − (1 − POWER) / m`` (all of them at ``POWER`` at least): along parameter n beside
    alternative a that is ``sqrt(λ / I_{c|a,nn})``; the identification size is the largest
    over the alternatives, and not below the MDB ``mdb`` (the effect must be found first).
    ``({}, {})`` where none shares it (or ``alpha`` is 0).
    """
    shared: dict[str, dict[str, float]] = {}
    left: dict[str, np.ndarray] = {}
    for a, block in sorted(beside.items()):
        d = np.diag(np.atleast_2d(np.asarray(block, dtype=float))) / dispersion
        rho2 = np.where(diag > 0, 1.0 - np.clip(d, 0.0, None) / np.where(diag > 0, diag, 1.0),
                        0.0)
        if alpha > 0 and np.any(rho2 >= SHARED_SHAPE):
            shared[a] = {n: float(r) for n, r in zip(names, rho2, strict=True)}
            left[a] = d
    if not shared:
        return {}, {}
    lam = lambda0(alpha, dof, 1.0 - (1.0 - POWER) / len(shared))
    out = {}
    for i, n in enumerate(names):
        size = max((float(np.sqrt(lam / d[i])) if d[i] > 0 else float("inf")
                    for d in left.values()), default=0.0)
        out[n] = max(size, mdb[n])
    return out, shared


# ----------------------------------------------------------------------------- display units
def display_unit(parameter: str) -> tuple[str, float]:
    """(unit, factor) the user reads a parameter ``effect.name`` in: px, arcsec, ppm, ms.

    Declared on the effect's class (:meth:`Effect.display`); an unknown name is shown raw.
    """
    effect_id, _, name = parameter.partition(".")
    if effect_id == "equivalent_principal_point":
        return "px", 1.0
    try:
        return registry.effect_class(effect_id).display(name)
    except Exception:  # an unknown effect or unit: show it raw
        return "", 1.0


def shown(parameter: str, value: float) -> str:
    """``value`` of ``parameter`` in its display unit, e.g. ``'312 arcsec'``."""
    unit, factor = display_unit(parameter)
    return f"{value * factor:.3g} {unit}".strip()


# ----------------------------------------------------------------------------- external
def bias_rows(names_aug: list[str], P_aug: np.ndarray, beta: slice, model_names: list[str],
              derived: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """Bias of each estimated quantity per unit of a hidden effect, from a joint posterior.

    Parameters
    ----------
    names_aug, P_aug : list of str, ndarray (n, n)
        Parameter names and joint posterior covariance of the augmented run.
    beta : slice
        The effect's block in ``names_aug``.
    model_names : list of str
        The current model's parameters (a subset of ``names_aug``).
    derived : dict, optional
        Derived quantities ``name → J (n,)``: their gradient with respect to the augmented
        run's θ (e.g. the equivalent principal point).

    Returns
    -------
    dict
        ``name → h (k,)``: leaving out β = b shifts the quantity by ``h · b``
        (``−P_θβ P_ββ⁻¹ b`` for a parameter).
    """
    P = _sym(np.asarray(P_aug, dtype=float))
    idx = [names_aug.index(n) for n in model_names if n in names_aug]
    kept = [n for n in model_names if n in names_aug]
    bidx = np.arange(beta.start, beta.stop)
    G = -P[np.ix_(idx, bidx)] @ _inverse(P[np.ix_(bidx, bidx)])  # (n_θ, k): b_θ = G b_β
    rows = {name: G[j] for j, name in enumerate(kept)}
    for name, J in (derived or {}).items():
        J = np.asarray(J, dtype=float)
        rows[name] = J[idx] @ G - J[bidx]  # reduced model's error minus the true shift
    return rows


def blind_directions(det: Detectability) -> np.ndarray:
    """Directions of ``det.effect`` the data cannot see, ``(k, n_blind)`` at plausible size.

    The eigen-directions of the information whitened by the plausible sizes along which an
    effect as large as plausible stays below the test's non-centrality λ₀: an effect there,
    up to its plausible size, leaves no detectable trace (e.g. the antisymmetric part of a
    gyro misalignment, a rotation of the gyro axes that the installation absorbs one to
    one).  Each column is the effect vector (its units) of one such direction, scaled to
    the plausible ellipsoid.  Exactly the directions the test leaves out
    (:func:`split_directions`, found by :func:`detectability`): none of them is one the
    test sums over, whatever the round's dispersion.
    """
    if det.blind is None:
        return np.zeros((det.plausible.size, 0))
    return det.blind


def _sparse_basis(B: np.ndarray) -> np.ndarray:
    """An orthonormal basis of span(B) that is as sparse as the space allows.

    Eigenvectors of a (near-)degenerate block are arbitrary mixtures; the reduced row
    echelon form of ``Bᵀ`` names the space by its simplest vectors (e01 − e10, e02 − e20,
    … for a rotation of the gyro axes), orthonormalized in that order.
    """
    if B.shape[1] < 2:
        return B
    R = B.T.copy()
    rows, cols = R.shape
    r = 0
    for c in range(cols):
        if r == rows:
            break
        p = r + int(np.argmax(np.abs(R[r:, c])))
        if abs(R[p, c]) < 1e-9:
            continue
        R[[r, p]] = R[[p, r]]
        R[r] /= R[r, c]
        for i in range(rows):
            if i != r:
                R[i] -= R[i, c] * R[r]
        r += 1
    Q, _ = np.linalg.qr(R.T)
    return Q[:, :B.shape[1]]


def _direction_text(effect_id: str, v: np.ndarray) -> str:
    """A direction of an effect in words: ``'0.71 e01 - 0.71 e10'``."""
    names = registry.create(effect_id).parameter_names
    u = np.asarray(v, dtype=float) / max(float(np.abs(v).max()), 1e-300)
    u = u / np.linalg.norm(u)
    lead = np.flatnonzero(np.abs(u) >= 0.2)
    if lead.size:
        u = u * np.sign(u[lead[0]])  # the direction's sign is immaterial: lead with +
    terms = [(c, n) for c, n in zip(u, names, strict=True) if abs(c) >= 0.2]
    text = " ".join(f"{'-' if c < 0 else '+'} {abs(c):.2g} {n}" for c, n in terms)
    return text[2:] if text.startswith("+ ") else text


def external_reliability(det: Detectability, rows: dict[str, np.ndarray],
                         model_sigma: dict[str, float]) -> dict[str, Any]:
    """The bias an undetected ``det.effect`` of its printed MDB puts into each quantity.

    ``rows`` from :func:`bias_rows` (or a screening pass's sensitivity): leaving out the
    effect at ``b`` shifts quantity q by ``h_q · b``; ``model_sigma`` the posterior σ of
    each quantity in the current model (same units).

    Every number is the shift an injection of the printed size reproduces (issue 21): for
    each parameter j of the effect, the effect with that parameter alone at its printed MDB
    (``sqrt(λ₀ / I_jj)``, or the excess gate's where it binds, :func:`detectability`; at most
    its plausible size when the MDB exceeds it) shifts q by
    ``h_qj · size_j``; ``biases[q]`` is the largest of these over j (signed, in
    ``biases_signed``), ``bias_parameter[q]`` the j that gives it.  Directions the data
    cannot see at all (:func:`blind_directions`) are a separate statement, ``blind``: up to
    its plausible size an effect there moves q by up to ``|h_q D V_b|`` and no test can
    tell.  (The worst bias over the whole undetectable set mixed the two: for a gyro
    misalignment it printed the plausible-size rotation of the gyro axes — 150 arcsec of
    installation — beside a 3 arcsec MDB, ~60x what that MDB does.)

    A bias above the parameter's σ is listed in ``dominates`` unless it is below
    :data:`FIRST_ORDER_SHARE` of the largest shift (in σ) the same parameter of the effect
    makes (``largest_shift_sigma``): then it is a first-order remainder (``remainders``)
    that an injection need not reproduce (an image-plane tilt moves the installation by
    ~100 σ and the gyro bias by a printed 1.2 σ that the filter's response does not have);
    a diagnosis measures those rows by probe runs on the bag
    (:func:`~stellar_cal_ros.diagnosis.reliability_probe.probe_entries`).

    Returns ``{"effect", "mdb", ..., "hidden_size", "biases", "biases_signed",
    "bias_parameter", "biases_shown", "dominates", "sigma", "sigma_shown", "blind",
    "remainders", "largest_shift_sigma"}``.
    """
    names = list(det.mdb)
    size = np.array([min(det.mdb[n], p) for n, p in zip(names, det.plausible, strict=True)])
    biases, signed, source, col = {}, {}, {}, {}
    largest = np.zeros(len(names))  # each parameter's largest shift, in sigmas
    for q, h in rows.items():
        shifts = np.asarray(h, dtype=float) * size
        j = int(np.argmax(np.abs(shifts))) if shifts.size else 0
        signed[q] = float(shifts[j]) if shifts.size else 0.0
        biases[q], source[q], col[q] = abs(signed[q]), names[j] if names else "", j
        if shifts.size and model_sigma.get(q, 0.0) > 0:
            largest = np.fmax(largest, np.abs(shifts) / model_sigma[q])
    listed = [name for name, b in biases.items()
              if model_sigma.get(name, 0.0) > 0
              and b > DOMINATES_SIGMA * model_sigma[name]]
    # beside a much larger shift of the same injection a bias is a remainder the
    # first-order recursion does not hold to 30 % (doc/benchmarks.md): said apart
    remainders = [n for n in listed
                  if biases[n] < FIRST_ORDER_SHARE * largest[col[n]] * model_sigma[n]]
    dominates = [n for n in listed if n not in remainders]
    B = blind_directions(det) if det.testable else np.zeros((len(names), 0))
    blind: dict[str, Any] = {}
    if B.shape[1]:
        worst = {q: float(np.linalg.norm(np.asarray(h, dtype=float) @ B))
                 for q, h in rows.items()}
        blind = {"directions": [_direction_text(det.effect, B[:, i])
                                for i in range(B.shape[1])],
                 "biases": worst, "biases_shown": {n: shown(n, b) for n, b in worst.items()},
                 "dominates": [n for n, b in worst.items() if model_sigma.get(n, 0.0) > 0
                               and b > DOMINATES_SIGMA * model_sigma[n]]}
    # in the rows' order (a set's order varies with the interpreter's string hashing:
    # diagnosis.json's sigma blocks came out in another order each run)
    shown_also = set(listed) | set(blind.get("dominates", []))
    sig_names = [q for q in rows if q in shown_also]
    return {"effect": det.effect, **det.as_dict(),
            "hidden_size": dict(zip(names, map(float, size), strict=True)),
            "biases": biases, "biases_signed": signed, "bias_parameter": source,
            "biases_shown": {n: shown(n, b) for n, b in biases.items()},
            "sigma": {n: model_sigma[n] for n in sig_names},
            "sigma_shown": {n: shown(n, model_sigma[n]) for n in sig_names},
            "dominates": dominates, "blind": blind, "remainders": remainders,
            "largest_shift_sigma": {n: float(v) for n, v in zip(names, largest, strict=True)}}
