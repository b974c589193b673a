"""The one place that changes an error-state covariance (after OpenVINS's ``StateHelper``).

Functional, numpy + LAPACK only: every function takes and returns arrays; shapes are in the
docstrings.  Used by every Kalman filter of the package (PSCE, swaying-base, traditional):

* :func:`propagate` / :func:`propagate_coupled` — ``P ← Φ P Φᵀ + Q_d``, the second for the
  common ``Φ = I + F`` with ``F`` in one off-diagonal block (cheaper, same values);
* :func:`iterated_update` — an iterated EKF update of a stacked measurement with the
  Joseph-form covariance (stays symmetric positive definite with the iterated, not exactly
  optimal gain);
* :func:`reset_rotation` — the covariance reset after injecting a left rotation correction;
* :func:`repair` — check (finite, symmetric, positive definite) and repair;
* :class:`Sensitivity` — the mean response of the error state to unmodelled constant
  parameters (Willsky & Jones 1976): score tests for many candidate effects in one run,
  minimal detectable sizes and the bias an undetected effect would cause.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.linalg.lapack import dpotrf as _potrf
from scipy.linalg.lapack import dpotrs as _potrs
from scipy.linalg.lapack import dtrtrs as _trtrs

from stellar_cal_ros.errors import ModelError


# ---------------------------------------------------------------------------- propagation
def propagate(P: np.ndarray, Phi: np.ndarray, Q: np.ndarray | None = None) -> np.ndarray:
    """``Φ P Φᵀ + Q`` symmetrized.  P, Φ, Q (N, N); Q may be None."""
    Pn = Phi @ P @ Phi.T
    if Q is not None:
        Pn += Q
    return 0.5 * (Pn + Pn.T)


def propagate_coupled(P: np.ndarray, rows: slice, cols: slice, F: np.ndarray,
                      q_diag: np.ndarray | None = None) -> None:
    """In place: ``P ← Φ P Φᵀ + diag(q)`` for ``Φ = I + F`` with F only in ``[rows, cols]``.

    ``rows`` and ``cols`` must not overlap (e.g. attitude rows driven by gyro-parameter
    columns).  With ``A = P[rows, :]`` the result is ``P[rows, :] = A + F P[cols, :]`` and
    its transpose, and ``P[rows, rows] += F P[cols, rows] + P[rows, cols] Fᵀ + F P[cols,
    cols] Fᵀ`` — no N×N products.  ``q_diag`` (N,) is added on the diagonal.
    """
    if F.size:
        FP = F @ P[cols, cols]
        cross = P[rows, cols] + FP
        P[rows, rows] += F @ P[cols, rows] + P[rows, cols] @ F.T + FP @ F.T
        P[rows, cols] = cross
        P[cols, rows] = cross.T
        # other columns of the driven rows: P[rows, k] += F P[cols, k]
        n = len(P)
        other = np.ones(n, dtype=bool)
        other[rows] = False
        other[cols] = False
        if other.any():
            add = F @ P[cols][:, other]
            P[rows, other] += add
            P[other, rows] += add.T
    if q_diag is not None:
        P.flat[::len(P) + 1] += q_diag


# ---------------------------------------------------------------------------- update
@dataclass
class UpdatePolicy:
    """When an iterated update relinearizes, and when it stops."""

    max_iterations: int = 5  #: relinearizations per update
    iteration_tolerance: float = 1e-3  #: stop when the correction changes < tol · σ
    relinearize_rad: float = 2e-4  #: iterate only if the rotation correction exceeds this
    relinearize_sigma: float = 0.5  #: ... or another part moves by more than this × σ


@dataclass
class UpdateResult:
    """Outcome of :func:`iterated_update`."""

    ok: bool
    dx: np.ndarray  #: (N,) correction (zeros when not ok)
    #: (N, N) Joseph-form posterior, before the reset and not yet symmetrized; the prior
    #: when not ok
    P: np.ndarray
    K: np.ndarray  #: (N, m) final gain
    H: np.ndarray  #: (m, N) final Jacobian
    nis: float  #: νᵀ S⁻¹ ν at the first linearization
    iterations: int
    reason: str = ""


def iterated_update(P: np.ndarray, H: np.ndarray, h: np.ndarray, z: np.ndarray,
                    r_diag: np.ndarray,
                    relinearize: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None,
                    policy: UpdatePolicy, rotation: slice = slice(0, 3),
                    others: slice | None = None, compiled: bool = False,
                    common: np.ndarray | None = None) -> UpdateResult:
    """Iterated EKF update with the Joseph-form covariance.

    Parameters
    ----------
    P : ndarray (N, N)
        Prior covariance.
    H : ndarray (m, N)
        Jacobian at the prior.
    h : ndarray (m,)
        Prediction at the prior.
    z : ndarray (m,)
        Measurement.
    r_diag : ndarray (m,)
        Measurement variances (uncorrelated).
    relinearize : callable or None
        ``dx -> (H, h)`` at ``x̂ ⊞ dx``; None: a linear update.
    policy : UpdatePolicy
        When to relinearize and stop.
    rotation : slice
        The rotation correction that decides relinearization.
    others : slice, optional
        The rest whose motion (in σ) decides it too (default: after ``rotation``).
    compiled : bool
        Gain and Joseph step in compiled kernels (:func:`stellar_cal_ros.core.jit.
        kalman_gain`, :func:`~stellar_cal_ros.core.jit.joseph`; ignored without numba):
        the same formulas, Cholesky by hand instead of LAPACK — equal to rounding.
    common : ndarray (m,) or (m, k), optional
        Noises every row shares: ``R = diag(r) + C Cᵀ`` (a frame's stamp error moves all its
        stars at once, ``c = σ_t ∂h/∂t``: :func:`stamp_column`; a shift common to the
        frame's stars, ``σ_f`` on each u and each v row: :func:`common_columns`).  Taken as
        ``k`` more error states of unit variance seen through ``C`` (:func:`augment`), whose
        gain rows are dropped: the same S, gain and Joseph covariance as the full R.  None:
        diagonal R.

    The first pass gives the gain, the frame NIS and, when the correction is small (a
    rotation below ``relinearize_rad`` and every other part below ``relinearize_sigma`` σ),
    the update.  Otherwise the measurement is relinearized at ``x̂ ⊞ dx`` and
    ``dx ← K (z − h(dx) + H(dx) dx)`` repeated until it changes by less than
    ``iteration_tolerance`` σ (Gauss–Newton on the MAP cost).
    """
    N = len(P)
    others = slice(rotation.stop, N) if others is None else others
    sig_floor = np.maximum(np.sqrt(np.clip(np.diag(P), 0.0, None)), 1e-300)
    nu = z - h
    dx = np.zeros(N)
    nis = math.nan
    K = np.zeros((N, len(z)))
    it = 0
    jit = compiled_kernels() if compiled else None
    if jit is not None:
        P = np.ascontiguousarray(P, dtype=float)
        r_diag = np.ascontiguousarray(r_diag, dtype=float)
    if common is not None and common.ndim == 2 and common.shape[1] == 1:
        common = common[:, 0]  # (one column: the stamp's, as a vector)
    P_g = P if common is None else augment(P, 1 if common.ndim == 1 else common.shape[1])
    for it in range(1, policy.max_iterations + 1):
        H_g = H if common is None else np.column_stack([H, common])
        if jit is not None:
            ok, K, nis_it = jit.kalman_gain(P_g, np.ascontiguousarray(H_g, dtype=float),
                                            r_diag, np.ascontiguousarray(nu, dtype=float))
            if not ok:
                return UpdateResult(False, np.zeros(N), P, K[:N], H, nis, it,
                                    "innovation covariance not positive definite")
            if it == 1:
                nis = nis_it
        else:
            K_it, nis = _gain(P_g, H_g, r_diag, nu, nis, it)
            if K_it is None:
                return UpdateResult(False, np.zeros(N), P, K, H, nis, it,
                                    "innovation covariance not positive definite")
            K = K_it
        if common is not None:
            K = np.ascontiguousarray(K[:N])
        dx_new = K @ (z - h + H @ dx)
        dx_prev, dx = dx, dx_new
        if it == policy.max_iterations or relinearize is None:
            break
        if it == 1:
            dphi = dx[rotation]
            if math.sqrt(float(dphi @ dphi)) < policy.relinearize_rad and (
                    np.abs(dx[others]) < policy.relinearize_sigma * sig_floor[others]).all():
                break
        elif (float(np.max(np.abs(dx - dx_prev) / sig_floor)) if N else 0.0) \
                < policy.iteration_tolerance:
            break
        if not np.isfinite(dx).all():
            break  # reported below
        try:
            H, h = relinearize(dx)
        except (ModelError, np.linalg.LinAlgError, ValueError) as exc:
            return UpdateResult(False, np.zeros(N), P, K, H, nis, it,
                                f"relinearization failed ({exc})")
        if not (np.isfinite(H).all() and np.isfinite(h).all()):
            return UpdateResult(False, np.zeros(N), P, K, H, nis, it,
                                "relinearization left the field of view")
    if not (np.isfinite(dx).all() and np.isfinite(K).all()):
        return UpdateResult(False, np.zeros(N), P, K, H, nis, it, "non-finite update")
    # not symmetrized here: the caller resets the rotation blocks, then symmetrizes
    if jit is not None:
        Pn = jit.joseph(P, K, np.ascontiguousarray(H, dtype=float), r_diag)
    else:
        A = np.eye(N) - K @ H
        Pn = A @ P @ A.T + (K * r_diag) @ K.T
    if common is not None:
        kc = K @ common
        Pn += np.outer(kc, kc) if kc.ndim == 1 else kc @ kc.T
    return UpdateResult(True, dx, Pn, K, H, nis, it)


def augment(P: np.ndarray, k: int = 1) -> np.ndarray:
    """``blkdiag(P, I_k)`` (N + k, N + k): ``P`` with ``k`` frame-common noises of unit variance.

    With ``H`` given the columns ``C`` it adds ``C Cᵀ`` to ``H P Hᵀ`` (``iterated_update``'s
    ``common``, each star's block ``S_i`` of the gate).
    """
    N = len(P)
    out = np.zeros((N + k, N + k))
    out[:N, :N] = P
    for i in range(N, N + k):
        out[i, i] = 1.0
    return out


def common_columns(H_attitude: np.ndarray, R_i_b: np.ndarray, omega: np.ndarray,
                   sigma_t: float, sigma_f: float) -> np.ndarray:
    """The frame's common noises' columns (n, 2, k): its stars' motion in each, σ-scaled.

    ``σ_t > 0``: the stamp's column (:func:`stamp_column`) first; ``σ_f > 0`` (px): a shift
    of all the frame's stars by one error per axis (an attitude or image jitter the gyro
    does not see, :func:`~stellar_cal_ros.diagnosis.noise_structure.frame_common`), two
    columns ``σ_f (1, 0)`` and ``σ_f (0, 1)`` on every star: the frame's R gains
    ``σ_f² I₂`` in every 2 × 2 block, its own and between stars.  ``k`` = 0–3; a caller
    with both σ zero takes none (the diagonal R).  Arrays in, written for numba as well
    (the compiled star update's, ``frame_step``).
    """
    n = H_attitude.shape[0]
    k = (1 if sigma_t > 0.0 else 0) + (2 if sigma_f > 0.0 else 0)
    out = np.zeros((n, 2, k))
    j = 0
    if sigma_t > 0.0:
        w = R_i_b @ omega
        out[:, :, 0] = sigma_t * (H_attitude[:, :, 0] * w[0] + H_attitude[:, :, 1] * w[1]
                                  + H_attitude[:, :, 2] * w[2])
        j = 1
    if sigma_f > 0.0:
        out[:, 0, j] = sigma_f
        out[:, 1, j + 1] = sigma_f
    return out


def stamp_column(H_attitude: np.ndarray, R_i_b: np.ndarray, omega: np.ndarray,
                 sigma_t: float) -> np.ndarray:
    """``σ_t ∂uv/∂t`` (n, 2) of each star of a frame: its image's motion in a stamp error.

    An error ``δt`` in the frame's stamp turns the attitude at exposure by ``R_i_b ω δt``
    (a left rotation: ``R Exp(ω δt) = Exp(R ω δt) R``), so ``∂uv/∂t = H_attitude R_i_b ω``
    (``H_attitude`` (n, 2, 3) the prediction's ∂uv/∂φ, ``R_i_b`` the attitude at exposure,
    ``omega`` the body rate, rad/s).  One δt for all the frame's stars: the frame's R gains
    the rank-one ``c cᵀ`` (``iterated_update``'s ``common``, flattened), not a per-star term.
    The first of :func:`common_columns`.
    """
    return common_columns(H_attitude, R_i_b, omega, sigma_t, 0.0)[:, :, 0]


def joint_correction(nis: float, logdet: float, S: np.ndarray, nis_stars: np.ndarray,
                     accepted: np.ndarray) -> float:
    """The frame's ``−2 log`` likelihood less the sum of its accepted stars' own.

    ``nis``, ``logdet``: the frame's ``νᵀ S⁻¹ ν`` and ``log det S`` over its accepted stars
    with the full ``S = H P Hᵀ + R + c cᵀ`` (the update's first pass); ``S`` (n, 2, 2) and
    ``nis_stars`` (n,) each star's own block and NIS (the gate's).  A frame-common noise
    (the stamps', :func:`stamp_column`) moves all the frame's stars at once: summed star by
    star it counts once per star, as would an effect whose columns are ``c``'s, a time
    offset (its estimate's uncertainty too: ``H P Hᵀ`` between the stars).  Unseen case
    ``sway_jitter`` s22: 2Δℓ 23.3 for a time offset estimated at 1.6σ, whose score test
    read 4.2.  Added to the stars' own terms where the run states a stamp noise or a
    frame-common shift (:func:`common_columns`; the likelihood is then the frame's):
    ``frame_sums``.  Scalar loops: compiled as well.
    """
    out = nis + logdet
    for i in range(S.shape[0]):
        if accepted[i]:
            out -= nis_stars[i] + math.log(S[i, 0, 0] * S[i, 1, 1] - S[i, 0, 1] * S[i, 0, 1])
    return out


def frame_logdet(P: np.ndarray, H: np.ndarray, r_diag: np.ndarray, common: np.ndarray
                 ) -> float:
    """``log det (H P Hᵀ + diag(r) + C Cᵀ)``: the frame's (numpy; :func:`joint_correction`).

    ``common`` (m,) or (m, k): the frame's common columns (:func:`common_columns`).
    """
    C = common.reshape(len(common), -1)
    S = H @ P @ H.T + C @ C.T
    S.ravel()[::len(S) + 1] += r_diag
    return float(np.linalg.slogdet(S)[1])


def _gain(P: np.ndarray, H: np.ndarray, r_diag: np.ndarray, nu: np.ndarray, nis: float,
          it: int) -> tuple[np.ndarray | None, float]:
    """The gain ``K`` (N, m) of one pass (None: S not positive definite) and the NIS.

    The NIS is computed on the first pass (``it == 1``); later passes return ``nis``.
    """
    PHt = P @ H.T
    S = H @ PHt
    S.ravel()[::len(S) + 1] += r_diag
    # LAPACK directly (Cholesky, then triangular solves): the numpy.linalg wrappers cost
    # more than the factorization of a frame's 2n × 2n innovation covariance
    c, info = _potrf(S, lower=1, clean=1, overwrite_a=1)
    if info != 0:
        return None, nis
    if it == 1:
        y, _ = _trtrs(c, nu, lower=1)
        nis = float(y @ y)
    Kt, _ = _potrs(c, PHt.T, lower=1)  # S⁻¹ H P = Kᵀ
    return Kt.T, nis


_JIT: list = []  # [module or None] once looked up (compiled_kernels)


def compiled_kernels():
    """:mod:`stellar_cal_ros.core.jit` when numba is importable, else None.

    Imported on first use (importing numba takes ~0.3 s), then remembered.
    """
    if not _JIT:
        from stellar_cal_ros.core import jit

        _JIT.append(jit if jit.HAVE_NUMBA else None)
    return _JIT[0]


def linear_update(P: np.ndarray, H: np.ndarray, nu: np.ndarray, R: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """One linear update with a full R: ``(dx, P⁺ (Joseph), K, NIS)``.

    ``P`` (N, N), ``H`` (m, N), ``nu`` (m,) innovation, ``R`` (m, m).
    """
    HP = H @ P
    S = HP @ H.T + R
    X = np.linalg.solve(S, np.column_stack([HP, nu]))
    K = X[:, :-1].T
    nis = float(nu @ X[:, -1])
    A = np.eye(len(P)) - K @ H
    Pn = A @ P @ A.T + K @ R @ K.T
    return K @ nu, 0.5 * (Pn + Pn.T), K, nis


def reset_rotation(P: np.ndarray, sl: slice, dphi: np.ndarray) -> None:
    """In place: the covariance reset ``G P Gᵀ`` after injecting a left rotation ``δφ``.

    With ``R = Exp(δφ_true) R̂`` and the nominal moved to ``Exp(δφ) R̂``, the new error is
    ``Log(Exp(δφ_true) Exp(−δφ)) ≈ (I + ½[δφ]×)(δφ_true − δφ)`` to first order in the
    error: ``G = I + ½[δφ]×`` on the block's rows and columns (OpenVINS / Solà §7.2).
    """
    x, y, z = 0.5 * np.asarray(dphi, dtype=float)
    G = np.array([[1.0, -z, y], [z, 1.0, -x], [-y, x, 1.0]])
    P[sl, :] = G @ P[sl, :]
    P[:, sl] = P[:, sl] @ G.T


# ---------------------------------------------------------------------------- health
def check(P: np.ndarray, name: str = "covariance") -> None:
    """Raise :class:`ModelError` unless P is finite, symmetric and positive definite."""
    if not np.all(np.isfinite(P)):
        raise ModelError(f"{name} has non-finite entries")
    if np.max(np.abs(P - P.T)) > 1e-9 * max(1.0, float(np.max(np.abs(P)))):
        raise ModelError(f"{name} is not symmetric")
    try:
        np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        raise ModelError(f"{name} is not positive definite") from None


def repair(P: np.ndarray) -> np.ndarray | None:
    """Nearest symmetric positive definite matrix by eigenvalue clipping; None if not finite."""
    S = 0.5 * (P + P.T)
    if not np.all(np.isfinite(S)):
        return None
    w, V = np.linalg.eigh(S)
    w = np.maximum(w, 1e-12 * max(float(w.max()), 1e-300))
    return (V * w) @ V.T


# ---------------------------------------------------------------------------- sensitivity
class Sensitivity:
    """Mean error-state response to unmodelled constant parameters (Willsky & Jones 1976).

    If the truth holds parameters β = β₀ + b that the filter keeps at β₀, the filter's error
    ``e = x − x̂`` has mean ``M b`` and the innovations have mean ``A b``::

        propagation   M ← Φ M + Φ_β
        update        A = H M + H_β,   M ← M − K A
        reset         M ← G M  (rows of a rotation block)

    Accumulated over the evaluation frames: the score ``s = Σ Aᵀ S⁻¹ ν`` and the Fisher
    information ``I = Σ Aᵀ S⁻¹ A``.  Then, per group of columns (a candidate effect):
    the Lagrange-multiplier (score) statistic ``sᵀ I⁻¹ s ~ χ²_k`` under "no effect", the
    one-step estimate ``b̂ = I⁻¹ s``, the minimal detectable size along a direction ``d``,
    ``√(λ₀ / dᵀ I d)``, and the bias ``−M_θ b`` an undetected ``b`` leaves in the
    estimated parameters (external reliability).

    Parameters
    ----------
    n_state : int
        Error-state size N.
    n_params : int
        Number of unmodelled parameters m.
    """

    def __init__(self, n_state: int, n_params: int) -> None:
        self.M = np.zeros((n_state, n_params))
        self.score = np.zeros(n_params)
        self.info = np.zeros((n_params, n_params))
        self.frames = 0
        self.accumulate = True  #: add the frame's terms to score / info

    @property
    def size(self) -> int:
        """Number of unmodelled parameters."""
        return self.M.shape[1]

    def propagate(self, Phi: np.ndarray, Phi_b: np.ndarray | None = None) -> None:
        """``M ← Φ M + Φ_β`` (Φ (N, N); Φ_β (N, m) or None)."""
        self.M = Phi @ self.M
        if Phi_b is not None:
            self.M += Phi_b

    def propagate_coupled(self, rows: slice, cols: slice, F: np.ndarray,
                          F_b: np.ndarray | None = None) -> None:
        """:meth:`propagate` for ``Φ = I + F`` with F in ``[rows, cols]`` (in place)."""
        if F.size:
            self.M[rows] += F @ self.M[cols]
        if F_b is not None:
            self.M[rows] += F_b

    def update(self, H: np.ndarray, H_b: np.ndarray, K: np.ndarray, nu: np.ndarray,
               S: np.ndarray) -> None:
        """Apply one update (and accumulate its score and information).

        ``H`` (k, N), ``H_b`` (k, m), gain ``K`` (N, k), innovation ``nu`` (k,) and its
        covariance ``S`` (k, k).
        """
        A = H @ self.M + H_b
        if self.accumulate:
            X = np.linalg.solve(S, np.column_stack([A, nu]))
            self.score += A.T @ X[:, -1]
            self.info += A.T @ X[:, :-1]
            self.frames += 1
        self.M -= K @ A

    def reset_rotation(self, sl: slice, dphi: np.ndarray) -> None:
        """Rows of a rotation block after its reset (``G = I + ½[δφ]×``)."""
        x, y, z = 0.5 * np.asarray(dphi, dtype=float)
        G = np.array([[1.0, -z, y], [z, 1.0, -x], [-y, x, 1.0]])
        self.M[sl] = G @ self.M[sl]

    def set_rows(self, rows: slice, value: np.ndarray) -> None:
        """The response of re-initialized states ``rows`` (e.g. the attitude at acquisition)."""
        self.M[rows] = value

    def clear_rows(self, index: np.ndarray) -> None:
        """Forget the response of re-acquired (re-initialized) states."""
        self.M[index] = 0.0
