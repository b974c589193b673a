"""Interstar-angle calibration (IAC): the attitude-free baseline Liu et al. compare with.

The angle between two stars is invariant under rotation, so the camera intrinsics can be
fitted without any attitude or IMU: for every pair (i, j) of identified stars in a frame,

    r_ij = ∠(unproject(uv_i; θ), unproject(uv_j; θ)) − ∠(u_i, u_j)

with ``u`` the catalogue directions, minimised over θ (principal point, focal length, k1 k2,
(k3), p1 p2) by ``scipy.optimize.least_squares`` with an analytic Jacobian (implicit
differentiation of the undistortion: ``∂xy/∂p = −(∂uv/∂xy)⁻¹ ∂uv/∂p``) plus the prior
residuals ``(θ − θ_prior)/σ_prior``.  The principal point enters the angles only through
the perspective (second-order) terms, hence it is poorly determined — but no better in ACF,
where it trades against the installation tilt: in Liu's setting the attitude-free bound
(:func:`crlb_iac`) on x0 y0 f is within 3 % of ACF's, so the gap Liu et al. show in Fig. 5 is
not an information limit.  Pair residuals of one frame are correlated (each star is in n−1
pairs); the fit treats them as independent with ``σ_angle = √2 σ_px / f`` (the usual IAC
practice), which costs ~15 % in σ(x0, y0) over the bound and makes the returned σ optimistic
(about half the actual σ in Liu's setting; :class:`IacBound` has both).  The installation
(and all else) stays at the prior.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from stellar_cal_ros.core.attitude import wahba
from stellar_cal_ros.core.types import StarFrame
from stellar_cal_ros.effects.base import FrameContext, Stage
from stellar_cal_ros.effects.registry import create_many
from stellar_cal_ros.errors import StellarCalError
from stellar_cal_ros.io.bag import BagReader
from stellar_cal_ros.io.calibration import Calibration, store_estimate
from stellar_cal_ros.methods.acf_covariance import _inverse
from stellar_cal_ros.methods.acf_data import select_frames, unit_vectors
from stellar_cal_ros.methods.frames import clean_frame, star_sigma
from stellar_cal_ros.methods.results import truth_parameters
from stellar_cal_ros.methods.star_model import StarModel

IAC_EFFECTS: tuple[str, ...] = ("focal_length", "principal_point", "radial_k1k2",
                                "radial_k3", "tangential")


@dataclass
class IacResult:
    """Result of :func:`run_iac`."""

    calibration: Calibration
    theta: np.ndarray
    covariance: np.ndarray
    parameter_names: list[str]
    rms_angle_arcsec: float
    pairs: int
    cost: float
    iterations: int

    @property
    def sigma(self) -> np.ndarray:
        """1-σ of θ (indicative: pair residuals are treated as independent)."""
        return np.sqrt(np.diag(self.covariance))


def _camera_jacobian(model: StarModel, theta: np.ndarray, ctx: FrameContext) -> np.ndarray:
    """``∂p/∂θ`` (18, P) of the camera chain (as composed in StarModel.predict)."""
    p = model._camera_prior
    steps = []
    for eff in model.effects:
        if eff.stage is not Stage.CAMERA:
            continue
        v = theta[model.slices[eff.id]]
        J, D = eff.camera_jacobian(v, p, ctx)
        steps.append((model.slices[eff.id], J, D))
        p = eff.camera_parameters(v, p, ctx)
    out = np.zeros((18, model.size))
    A = np.eye(18)
    for sl, J, D in reversed(steps):
        out[:, sl] += A @ J
        A = A @ D
    return out


def _pair_angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ij,ij->i", a, b))


class _Pairs:
    """Interstar-angle residuals of all star pairs within each frame, and their Jacobians.

    ``uvs``, ``us``, ``sigs``: per frame the centroids (n, 2), catalogue directions (n, 3)
    and centroid σ (n,).  Residuals are whitened with ``w_pair = f0 / √(σ_i² + σ_j²)``
    (pairs treated as independent); the prior rows ``(θ − th0)/sp`` follow them.
    """

    def __init__(self, model: StarModel, uvs: list[np.ndarray], us: list[np.ndarray],
                 sigs: list[np.ndarray], f0: float, th0: np.ndarray, sp: np.ndarray) -> None:
        self.model, self.th0, self.sp = model, th0, sp
        self.ctx = FrameContext(stamp=0.0)
        pi, pj, ang_cat, pair_frame = [], [], [], []
        base = 0
        for k, (uv, u) in enumerate(zip(uvs, us, strict=True)):
            n = len(uv)
            i, j = np.triu_indices(n, 1)
            pi.append(base + i)
            pj.append(base + j)
            ang_cat.append(_pair_angles(u[i], u[j]))
            pair_frame.append(np.full(len(i), k))
            base += n
        self.Ia = np.concatenate(pi) if pi else np.zeros(0, dtype=np.int64)
        self.Ib = np.concatenate(pj) if pj else np.zeros(0, dtype=np.int64)
        self.A_cat = np.concatenate(ang_cat) if ang_cat else np.zeros(0)
        self.pair_frame = np.concatenate(pair_frame) if pair_frame else np.zeros(0, dtype=int)
        self.star_start = np.cumsum([0] + [len(uv) for uv in uvs])
        self.uv = np.vstack(uvs) if uvs else np.zeros((0, 2))
        self.sig = np.concatenate(sigs) if sigs else np.zeros(0)
        self.n_pairs = len(self.Ia)
        self.w_pair = f0 / np.sqrt(self.sig[self.Ia] ** 2 + self.sig[self.Ib] ** 2)  # 1/σ
        self._cache: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    def _geometry(self, theta: np.ndarray):
        cam = self.model.camera_at(theta, self.ctx)
        xy = cam.pixel_to_normalized(self.uv)
        _, J_xy, J_p = cam.normalized_to_pixel(np.nan_to_num(xy), jacobians=True)
        a = np.column_stack([xy, np.ones(len(xy))])
        va, vb = a[self.Ia], a[self.Ib]
        cr = np.cross(va, vb)
        ncr = np.linalg.norm(cr, axis=1)
        dot = np.einsum("ij,ij->i", va, vb)
        ang = np.arctan2(ncr, dot)
        ga = (dot / np.einsum("ij,ij->i", va, va))[:, None] * va - vb
        gb = (dot / np.einsum("ij,ij->i", vb, vb))[:, None] * vb - va
        ga /= ncr[:, None]
        gb /= ncr[:, None]
        return ang, ga[:, :2], gb[:, :2], J_xy, J_p

    def evaluate(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Whitened residuals (pairs, then prior rows) and their Jacobian."""
        key = theta.tobytes()
        if key in self._cache:
            return self._cache[key]
        ang, ga, gb, J_xy, J_p = self._geometry(theta)
        dxy_dp = -np.linalg.solve(J_xy, J_p)  # (n, 2, 18)
        dxy = dxy_dp @ _camera_jacobian(self.model, theta, self.ctx)  # (n, 2, P)
        Jang = np.einsum("ni,nip->np", ga, dxy[self.Ia]) + \
            np.einsum("ni,nip->np", gb, dxy[self.Ib])
        w = self.w_pair
        r = np.concatenate([(ang - self.A_cat) * w, (theta - self.th0) / self.sp])
        J = np.vstack([Jang * w[:, None], np.diag(1.0 / self.sp)])
        bad = ~np.isfinite(r)
        if bad.any():
            r[bad] = 1e6
            J[bad] = 0.0
        self._cache.clear()
        self._cache[key] = (r, J)
        return r, J

    def covariance(self, theta: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
        """Covariance of the estimate at ``theta`` with the pair correlations.

        The angles of a frame share centroid errors, so the weighted least squares (pairs
        treated as independent) has the sandwich covariance ``N⁻¹ (JᵀWΣWJ + prior) N⁻¹``
        with ``Σ = G diag(σ²) Gᵀ``, ``G = ∂angle/∂uv``.  Returns it, the expected sum of
        squared whitened pair residuals at the solution (``tr WΣW − tr H WΣW``, H the hat
        matrix: the σ̂² denominator that the correlations make differ from pairs − P), and
        the naive ``(JᵀWJ / σ̂²_expected + prior)⁻¹`` that treats the pairs as independent.
        """
        _, J = self.evaluate(theta)
        npair, P = self.n_pairs, J.shape[1]
        Jw, Jp = J[:npair], J[npair:]  # pairs already × w_pair; prior rows
        N = Jw.T @ Jw + Jp.T @ Jp
        ga, gb = self.centroid_jacobian(theta)
        # JᵀWΣWJ = Σ_stars (Σ_{pairs ∋ star} Jw w g)(…)ᵀ σ²
        T = np.zeros((len(self.uv), 2, P))
        w = self.w_pair
        np.add.at(T, self.Ia, (w[:, None] * ga)[:, :, None] * Jw[:, None, :])
        np.add.at(T, self.Ib, (w[:, None] * gb)[:, :, None] * Jw[:, None, :])
        T *= self.sig[:, None, None]
        T = T.reshape(-1, P)
        Ninv = _inverse(N)
        cov = Ninv @ (T.T @ T + Jp.T @ Jp) @ Ninv
        diag = w ** 2 * (self.sig[self.Ia] ** 2 * np.sum(ga ** 2, axis=1)
                         + self.sig[self.Ib] ** 2 * np.sum(gb ** 2, axis=1))
        expected_ss = float(diag.sum()) - float(np.trace(Ninv @ T.T @ T))
        s2 = expected_ss / max(npair - P, 1)
        naive = _inverse(Jw.T @ Jw / s2 + Jp.T @ Jp)
        return 0.5 * (cov + cov.T), expected_ss, naive

    def centroid_jacobian(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``∂angle/∂uv`` of each pair's first and second star, (pairs, 2) each (rad/px)."""
        _, ga, gb, J_xy, _ = self._geometry(theta)
        dxy_duv = np.linalg.inv(J_xy)  # (n, 2, 2)
        return (np.einsum("ni,nij->nj", ga, dxy_duv[self.Ia]),
                np.einsum("ni,nij->nj", gb, dxy_duv[self.Ib]))


def run_iac(
    source: str | os.PathLike[str] | list[StarFrame],
    prior: Calibration,
    effects: Sequence[str] | None = None,
    *,
    frames: Any = None,
    loss: str = "linear",
    sigma_px: float | None = None,
    max_nfev: int = 100,
    star_topic: str = "/star_tracker/stars",
) -> IacResult:
    """Calibrate the camera intrinsics from interstar angles (no IMU, no attitude).

    Parameters
    ----------
    source : path or list of StarFrame
        A contract bag or its star frames.
    prior : Calibration
        Start and prior σ; the result keeps everything else (installation, gyro) from it.
    effects : list of str, optional
        Camera effects to estimate (default :data:`IAC_EFFECTS`); non-camera ids are refused.
    frames : None, 'all', 'odd', 'even', indices, slice or bool mask
        Frames to use (as in :func:`stellar_cal_ros.methods.acf.run_acf`).
    loss : {'linear', 'huber', 'soft_l1', 'cauchy'}
        scipy loss with ``f_scale = 3`` (residuals are whitened).
    sigma_px : float, optional
        Centroid σ (default: the messages' ``sigma``, else 1 px).
    max_nfev : int
        Function evaluations of the least squares.
    star_topic : str
        Star centroid topic when reading a bag.
    """
    if isinstance(source, list):
        all_frames = source
    else:
        with BagReader(source) as reader:
            if star_topic not in reader.topics():
                raise StellarCalError(f"{source}: no star centroids on {star_topic}")
            all_frames = reader.read_star_frames(star_topic)
    eff = create_many(list(IAC_EFFECTS if effects is None else effects))
    bad = [e.id for e in eff if e.stage is not Stage.CAMERA]
    if bad:
        raise StellarCalError(f"the interstar-angle method estimates camera effects only, "
                              f"not {bad}")
    model = StarModel(eff, prior)
    idx = select_frames(len(all_frames), frames)
    uvs, us, sigs = [], [], []
    for k in idx:
        fr = all_frames[int(k)]
        ok = clean_frame(fr, prior.camera.width, prior.camera.height)
        n = int(ok.sum())
        if n < 2:
            continue
        uvs.append(np.asarray(fr.uv, dtype=float)[ok])
        us.append(unit_vectors(fr.right_ascension[ok], fr.declination[ok]))
        sigs.append(np.full(n, sigma_px) if sigma_px is not None
                    else star_sigma(np.asarray(fr.sigma, dtype=float)[ok], 1.0)[0])
    th0, sp = model.initial_value.copy(), model.initial_sigma.copy()
    pairs = _Pairs(model, uvs, us, sigs, prior.camera.fx, th0, sp)
    if pairs.n_pairs < model.size:
        raise StellarCalError("too few star pairs for the interstar-angle calibration")
    evaluate = pairs.evaluate
    if loss not in ("linear", "huber", "soft_l1", "cauchy"):
        raise StellarCalError(f"loss must be linear, huber, soft_l1 or cauchy, got {loss!r}")
    from scipy.optimize import least_squares  # (on first use: a replay never needs it)

    res = least_squares(lambda t: evaluate(t)[0], th0, jac=lambda t: evaluate(t)[1],
                        loss=loss, f_scale=3.0, x_scale="jac", max_nfev=max_nfev,
                        xtol=1e-12, ftol=1e-12, gtol=1e-10)
    r, J = evaluate(res.x)
    npair = pairs.n_pairs
    # Sandwich covariance (the pairs of a frame are correlated: the independent-pair
    # formula was 2x optimistic in Liu's setting), scaled by the observed over the
    # expected residual sum of squares so that a wrong message σ is corrected for.
    cov, expected_ss, _ = pairs.covariance(res.x)
    scale = float(np.sum(r[:npair] ** 2)) / expected_ss if expected_ss > 0 else 1.0
    cov = cov * max(scale, 1e-12)
    sig_th = np.sqrt(np.diag(cov))
    cal = store_estimate(prior, model.effects, model.slices, res.x, sig_th, "iac", prior.stamp)
    rms = float(np.sqrt(np.mean((r[:npair] / pairs.w_pair) ** 2)) * 180 / np.pi * 3600)
    return IacResult(cal, res.x, cov, model.parameter_names(), rms, npair, float(res.cost),
                     int(res.nfev))


@dataclass
class IacBound:
    """Cramér–Rao bound of the attitude-free (interstar-angle) problem (:func:`crlb_iac`).

    Covariances of the camera θ (the model's units), prior information included:

    * ``crlb`` — every frame's attitude is an unknown nuisance (3 per frame, marginalised):
      the information the centroids hold on θ without any attitude knowledge.  The interstar
      angles of a frame are its rotation-invariant part, so this is also the bound of any
      method using the angles (optimally weighted);
    * ``estimator`` — the covariance of :func:`run_iac` in the same linearisation: least
      squares with pair weights ``f0/√(σ_i² + σ_j²)`` and pairs treated as independent,
      while the angles of a frame share centroid errors (sandwich ``N⁻¹ (JᵀWΣWJ + prior)
      N⁻¹`` with ``Σ = G σ² Gᵀ``, ``G`` = ∂angle/∂uv);
    * ``reported`` — what run_iac reports for it on average: the same sandwich (scaled by
      observed / expected residual sum of squares, 1 on average);
    * ``naive`` — what the independent-pair formula ``(JᵀWJ / σ̂² + prior)⁻¹`` would report
      (σ̂² its residual variance factor's expectation, which the pair correlations bias):
      about 2× too small a σ in Liu's setting, the reason run_iac reports the sandwich.
    """

    parameter_names: list[str]
    model: StarModel
    theta_true: np.ndarray
    crlb: np.ndarray
    estimator: np.ndarray
    reported: np.ndarray
    naive: np.ndarray
    n_frames: int
    n_stars: int
    n_pairs: int

    def sigma(self, which: str = "crlb") -> np.ndarray:
        """1-σ of θ from ``crlb``, ``estimator``, ``reported`` or ``naive``."""
        return np.sqrt(np.diag(getattr(self, which)))


def crlb_iac(
    source: list[StarFrame],
    prior: Calibration,
    truth: Calibration,
    effects: Sequence[str] | None = None,
    *,
    frames: Any = None,
    sigma_px: float | None = None,
) -> IacBound:
    """Cramér–Rao bound of the intrinsics without attitude knowledge (the IAC setting).

    For every frame with ≥ 3 identified stars: the attitude from a Wahba fit under the true
    camera (error ~1", immaterial for the Jacobian), the star model's analytic Jacobians
    ``∂uv/∂θ`` and ``∂uv/∂φ_k`` at the truth (:func:`~stellar_cal_ros.methods.replay.
    truth_parameters`), and the frame's information on θ with its attitude φ_k marginalised
    (Schur complement).  Prior rows ``(θ − θ_prior)/σ_prior`` as in :func:`run_iac`.  Also
    evaluates run_iac's own estimator covariance at the noise-free predicted centroids (see
    :class:`IacBound`).
    """
    eff = create_many(list(IAC_EFFECTS if effects is None else effects))
    model = StarModel(eff, prior)
    theta = truth_parameters(model, truth)
    th0, sp = model.initial_value.copy(), model.initial_sigma.copy()
    cam_true = model.camera_at(theta, FrameContext(stamp=0.0))
    R_imu_st = prior.installation.as_matrix()
    P = model.size
    info = np.diag(1.0 / sp ** 2)
    uvs, us, sigs = [], [], []
    for k in select_frames(len(source), frames):
        fr = source[int(k)]
        ok = clean_frame(fr, prior.camera.width, prior.camera.height)
        if ok.sum() < 3:
            continue
        u = unit_vectors(fr.right_ascension[ok], fr.declination[ok])
        uv = np.asarray(fr.uv, dtype=float)[ok]
        s = np.full(len(uv), sigma_px) if sigma_px is not None \
            else star_sigma(np.asarray(fr.sigma, dtype=float)[ok], 1.0)[0]
        R_i_st = wahba(cam_true.unproject(uv), u)
        R_i_b = R_i_st @ R_imu_st.T

        def attitude(t: float, R=R_i_b) -> tuple[np.ndarray, np.ndarray]:
            return R, np.zeros(3)

        pred = model.predict(theta, u, FrameContext(stamp=0.0), attitude)
        Ht = (pred.H_parameters / s[:, None, None]).reshape(-1, P)
        Ha = (pred.H_attitude / s[:, None, None]).reshape(-1, 3)
        HtHa = Ht.T @ Ha
        info += Ht.T @ Ht - HtHa @ np.linalg.solve(Ha.T @ Ha, HtHa.T)
        uvs.append(pred.uv)
        us.append(u)
        sigs.append(s)
    if not uvs:
        raise StellarCalError("no frame with 3 identified stars")
    cov = _inverse(info)
    # run_iac's estimator at the noise-free centroids: pair-correlation sandwich
    pairs = _Pairs(model, uvs, us, sigs, prior.camera.fx, th0, sp)
    est, _, naive = pairs.covariance(theta)
    return IacBound(model.parameter_names(), model, theta, cov, est, est, naive, len(uvs),
                    len(pairs.uv), pairs.n_pairs)
