"""Bundle adjustment of a star camera: one free attitude per frame, one camera, no IMU.

Every identified star ``j`` of frame ``k`` is predicted by the shared
:class:`~stellar_cal_ros.methods.star_model.StarModel` with the frame's own attitude::

    uv_kj = h(θ, R_k, u_kj)          R_k ← Exp(φ_k) · R_k   (left, inertial, as the filters)

The unknowns are the N attitudes ``φ_k`` and the camera (and apparent-place) parameters θ of
the effects: the baseline :data:`BASELINE_EFFECTS` plus ``--effects``; every library effect
of the CAMERA stage (pixel aspect, k3, tangential, tilt, thermal focal length, …) and of
the DIRECTION stage (``aberration``, ``refraction``, ``proper_motion``: computed from the
frame's site, stamp and weather, the scale estimated) is available.  An installation, a
time offset or a gyro error is invisible to a free attitude per frame and is refused.

Solution: Levenberg–Marquardt on the whitened residuals ``(uv − h)/σ`` plus the prior rows
``(θ − θ_prior)/σ_prior``, with the attitudes eliminated by the Schur complement in every
step (the normal matrix is block-arrow: 3×3 per frame plus the P×P camera block), so a step
costs O(N P²).  The start is each frame's Wahba attitude under the prior camera.  Wrong
identities are removed twice, as in the ACF method: a catalogue direction far off the
measured one (the identification gate), then — after a robust fit — stars whose normalized
residual lies beyond a χ²(2) gate (:func:`~stellar_cal_ros.methods.acf_robust.beyond_gate`);
the final fit runs on the inliers with the chosen loss.

Covariance: ``(S / s² + Λ_prior)⁻¹`` with ``S`` the camera block of the star information
with the attitudes marginalised (Schur complement) and ``s²`` the variance factor of the
star rows (σ̂ = s · the stated σ): honest when the stated centroid σ is wrong by a factor.
:func:`~stellar_cal_ros.methods.bundle_bound.information_at` gives the same matrix at given
parameters without ``s²`` — at the truth, the Cramér–Rao bound (``bundle_bound.crlb_bundle``).

Cross-validation (:mod:`~stellar_cal_ros.methods.bundle_cv`): each frame held out in turn.
The whole run on a bag (identification, the fit, the cross-validation) is
:func:`~stellar_cal_ros.methods.bundle_runs.run_bundle`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from stellar_cal_ros.core.attitude import wahba
from stellar_cal_ros.core.rotation import so3_exp
from stellar_cal_ros.effects import registry
from stellar_cal_ros.effects.base import FrameContext, Stage
from stellar_cal_ros.errors import ModelError, StellarCalError
from stellar_cal_ros.io.calibration import Calibration
from stellar_cal_ros.methods.acf_covariance import _equilibrated_inverse
from stellar_cal_ros.methods.acf_robust import _make_loss, beyond_gate
from stellar_cal_ros.methods.frames import BagData, EnvSeries, frame_context, frame_inputs
from stellar_cal_ros.methods.star_model import StarModel

log = logging.getLogger(__name__)

#: the bundle's baseline model: a pinhole and the first two radial terms
BASELINE_EFFECTS: tuple[str, ...] = ("focal_length", "principal_point", "radial_k1k2")
#: the stages a free attitude per frame can see
STAGES: tuple[Stage, ...] = (Stage.DIRECTION, Stage.CAMERA)
#: a frame needs this many identified stars (3 for its attitude, more to check it)
MIN_STARS_PER_FRAME = 4
#: px: the σ of a star whose message says 0 ("unknown"); only the ratio between stars
#: matters, the fit's variance factor gives the scale
DEFAULT_SIGMA_PX = 1.0
#: outlier gate probability (χ²(2) of the normalized residual, as the ACF method)
OUTLIER_PROBABILITY = 1.0 - 1e-6
#: identification gate: a star this far (deg) from its catalogue direction is not fitted
GATE_DEG = 0.5
_ZERO3 = np.zeros(3)


# ============================================================================ data
@dataclass
class BundleFrame:
    """The identified stars of one frame, as the bundle fits them."""

    index: int  #: position of the message in the bag's star frames
    stamp_ns: int
    uv: np.ndarray  #: (n, 2) px
    u_i: np.ndarray  #: (n, 3) catalogue unit vectors (ICRS)
    sigma: np.ndarray  #: (n,) px, stated
    catalog_id: np.ndarray
    magnitude: np.ndarray
    ctx: FrameContext
    use: np.ndarray = field(default=None)  # type: ignore[assignment]  # inliers (bool)

    def __post_init__(self) -> None:
        if self.use is None:
            self.use = np.ones(len(self.uv), dtype=bool)

    def subset(self, mask: np.ndarray | None = None) -> BundleFrame:
        """The frame restricted to ``mask`` (default: its inliers); itself when all are.

        The context's ``extra`` (the apparent-place corrections' cache, keyed by content)
        is shared, so a subset fitted again and again (the cross-validation's folds) does
        not compute them again.
        """
        m = self.use if mask is None else mask
        if np.all(m):
            return self
        ctx = FrameContext(stamp=self.ctx.stamp, catalog_id=self.ctx.catalog_id[m],
                           magnitude=self.ctx.magnitude[m], site=self.ctx.site,
                           head_temperature_c=self.ctx.head_temperature_c,
                           air_temperature_c=self.ctx.air_temperature_c,
                           pressure_pa=self.ctx.pressure_pa, extra=self.ctx.extra)
        return BundleFrame(self.index, self.stamp_ns, self.uv[m], self.u_i[m], self.sigma[m],
                           self.catalog_id[m], self.magnitude[m], ctx)


@dataclass
class BundleCounts:
    """What the bundle skipped or rejected (counted, reported in the result)."""

    frames_read: int = 0
    frames_few_stars: int = 0
    stars_unidentified: int = 0  #: catalog_id 0 and no direction (not identified)
    stars_unusable: int = 0  #: non-finite or off the detector
    stars_bad_sigma: int = 0  #: message σ negative or NaN (default used)
    stars_misidentified: int = 0  #: catalogue direction far off the measured one
    stars_outliers: int = 0  #: beyond the outlier gate after a robust fit

    def as_dict(self) -> dict[str, int]:
        """Every count."""
        return dict(vars(self))


def bundle_frames(data: BagData, prior: Calibration, counts: BundleCounts | None = None,
                  min_stars: int = MIN_STARS_PER_FRAME,
                  default_sigma: float = DEFAULT_SIGMA_PX, noise=None) -> list[BundleFrame]:
    """The frames of ``data`` with at least ``min_stars`` usable stars (the filters' rules).

    ``noise`` (:class:`~stellar_cal_ros.core.noise.NoiseScales`) scales the stars' stated σ
    as it does in the filters (the diagnosis' measured noise).

    A star is used as every method uses it (:func:`~stellar_cal_ros.methods.frames.
    frame_inputs`); its context (site, stamp, weather) as the filters build it.
    """
    c = counts if counts is not None else BundleCounts()
    env = data.env() if hasattr(data, "env") else {k: EnvSeries() for k in
                                                    ("head", "air", "pressure")}
    w, h = prior.camera.width, prior.camera.height
    out = []
    for k, fr in enumerate(data.frames):
        c.frames_read += 1
        inp = frame_inputs(fr, w, h, default_sigma, noise)
        c.stars_unidentified += inp.unidentified
        c.stars_unusable += int((~inp.ok).sum()) - inp.unidentified
        c.stars_bad_sigma += inp.bad_sigma
        if len(inp.uv) < min_stars:
            c.frames_few_stars += 1
            continue
        ctx = frame_context(fr.stamp_ns, inp, data.site, env)
        out.append(BundleFrame(k, int(fr.stamp_ns), np.asarray(inp.uv, dtype=float),
                               inp.u_i, inp.sigma, inp.catalog_id, inp.magnitude, ctx))
    return out


def check_effects(effects: Sequence[str]) -> list[str]:
    """The baseline plus ``effects`` (``-id`` removes an added one), checked for the bundle.

    Raises
    ------
    ModelError
        An unknown effect, or one acting where a free attitude per frame cannot see it.
    """
    out = list(BASELINE_EFFECTS)
    for item in effects or ():
        item = item.strip()
        if not item:
            continue
        if item.startswith("-"):
            if item[1:] in BASELINE_EFFECTS:
                raise ModelError(f"{item[1:]} is in the bundle baseline and cannot be removed")
            out = [e for e in out if e != item[1:]]
            continue
        if item not in registry.available():
            raise ModelError(f"unknown effect {item!r}; known: {', '.join(registry.available())}")
        stage = registry.EFFECTS[item].stage
        if stage not in STAGES:
            raise ModelError(
                f"effect {item} acts on the {stage.value} stage, which the bundle method "
                "cannot see (a free attitude per frame absorbs it; it needs an IMU: use "
                "replay or batch --method acf)")
        if item not in out:
            out.append(item)
    return out


def check_context(model: StarModel, frames: list[BundleFrame]) -> None:
    """Refuse effects whose inputs the frames lack (a site for refraction, …)."""
    for eff in model.effects:
        if "site" in eff.requires and frames and frames[0].ctx.site is None:
            raise ModelError(f"effect {eff.id} needs the site (/gnss/fix), absent from the "
                             "bag (stellar-cal solve --site LAT,LON,H writes it)")
        if "head_temperature" in eff.requires and frames and \
                not np.isfinite(frames[0].ctx.head_temperature_c):
            raise ModelError(f"effect {eff.id} needs /star_tracker/temperature, absent from "
                             "the bag")


# ============================================================================ solver
def _constant(R: np.ndarray) -> Callable[[float], tuple[np.ndarray, np.ndarray]]:
    return lambda shift: (R, _ZERO3)


@dataclass
class _Normal:
    """Normal equations at one point: per-frame blocks and the camera block."""

    cost: float
    V: np.ndarray  # (P, P) camera block, prior included
    g: np.ndarray  # (P,)
    U: list[np.ndarray]  # (3, 3) per frame
    W: list[np.ndarray]  # (3, P) per frame
    gk: list[np.ndarray]  # (3,) per frame
    V_stars: np.ndarray  # (P, P) stars only
    sum_wz: float  # Σ w·|e|² over the stars
    n_stars: int
    Vk: list[np.ndarray] = field(default_factory=list)  # (P, P) per frame
    gthk: list[np.ndarray] = field(default_factory=list)  # (P,) per frame
    zk: list[float] = field(default_factory=list)  # Σ w·|e|² per frame
    nk: list[int] = field(default_factory=list)  # stars per frame


class Bundle:
    """Residuals, normal equations and Levenberg–Marquardt steps of one bundle problem.

    ``frames`` are fitted with their ``use`` stars; ``sigma_scale`` multiplies every stated
    σ (the robust stages rescale it); ``loss`` acts on each star's squared normalized
    residual ``z = |e|²`` with threshold ``f_scale`` (σ units).
    """

    def __init__(self, model: StarModel, frames: list[BundleFrame], theta_prior: np.ndarray,
                 sigma_prior: np.ndarray, loss: str = "linear", f_scale: float = 3.0,
                 sigma_scale: float = 1.0, masks: list[np.ndarray] | None = None) -> None:
        self.model = model
        self.frames = ([f.subset() for f in frames] if masks is None else
                       [f.subset(m) for f, m in zip(frames, masks, strict=True)])
        self.theta_prior = np.asarray(theta_prior, dtype=float)
        self.sigma_prior = np.asarray(sigma_prior, dtype=float)
        self.loss, self.f_scale, self.sigma_scale = loss, f_scale, sigma_scale
        self.P = model.size
        self.n_stars = sum(len(f.uv) for f in self.frames)

    # ------------------------------------------------------------------ residuals
    def residuals(self, theta: np.ndarray, R: np.ndarray, f: BundleFrame,
                  jacobians: bool = True) -> tuple[np.ndarray, Any, Any]:
        """Whitened residuals ``(uv − h)/σ`` (n, 2) and ``∂h/∂φ``, ``∂h/∂θ`` whitened."""
        with np.errstate(all="ignore"):
            pred = self.model.predict(theta, f.u_i, f.ctx, _constant(R), jacobians=jacobians)
        s = (f.sigma * self.sigma_scale)[:, None]
        e = (f.uv - pred.uv) / s
        if not jacobians:
            return e, None, None
        return e, pred.H_attitude / s[:, :, None], pred.H_parameters / s[:, :, None]

    def _rho(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Loss ρ(z) and weight ρ'(z) of squared normalized residuals."""
        if self.loss == "linear":
            return z, np.ones_like(z)
        out = _make_loss(self.loss, len(z), self.f_scale)(z)
        return out[0], out[1]

    def _prior_cost(self, theta: np.ndarray) -> float:
        d = (theta - self.theta_prior) / self.sigma_prior
        return float(d @ d)

    def cost(self, theta: np.ndarray, Rs: list[np.ndarray]) -> float:
        """Σ ρ(|e|²) over the stars + the prior term (non-finite predictions: a large z)."""
        total = self._prior_cost(theta)
        for R, f in zip(Rs, self.frames, strict=True):
            e, _, _ = self.residuals(theta, R, f, jacobians=False)
            z = np.sum(e ** 2, axis=1)
            z = np.where(np.isfinite(z), z, 1e12)
            total += float(np.sum(self._rho(z)[0]))
        return total

    def normal(self, theta: np.ndarray, Rs: list[np.ndarray],
               with_theta: bool = True) -> _Normal:
        """Normal equations (Gauss–Newton, IRLS weights) at ``(θ, R)``."""
        P = self.P if with_theta else 0
        V = np.zeros((P, P))
        g = np.zeros(P)
        U, W, gk, Vk, gthk, zk, nk = [], [], [], [], [], [], []
        cost, sum_wz, n = 0.0, 0.0, 0
        for R, f in zip(Rs, self.frames, strict=True):
            e, A, B = self.residuals(theta, R, f)
            z = np.sum(e ** 2, axis=1)
            bad = ~np.isfinite(z) | np.any(~np.isfinite(A), axis=(1, 2))
            if with_theta:
                bad |= np.any(~np.isfinite(B), axis=(1, 2))
            rho, w = self._rho(np.where(bad, 0.0, z))
            w = np.where(bad, 0.0, w)
            cost += float(np.sum(np.where(bad, 1e12, rho)))
            zk.append(float(np.sum(w * np.where(bad, 0.0, z))))
            nk.append(int((~bad).sum()))
            sum_wz += zk[-1]
            n += nk[-1]
            ww = np.repeat(w, 2)
            e2 = np.where(bad[:, None], 0.0, e).reshape(-1)
            A2 = np.where(bad[:, None, None], 0.0, A).reshape(-1, 3)
            Aw = A2 * ww[:, None]
            U.append(A2.T @ Aw)
            gk.append(Aw.T @ e2)
            if with_theta:
                B2 = np.where(bad[:, None, None], 0.0, B).reshape(-1, P)
                W.append(Aw.T @ B2)
                Bw = B2 * ww[:, None]
                Vk.append(B2.T @ Bw)
                gthk.append(Bw.T @ e2)
                V += Vk[-1]
                g += gthk[-1]
            else:
                W.append(np.zeros((3, 0)))
        V_stars = V.copy()
        if with_theta:
            d = (theta - self.theta_prior) / self.sigma_prior
            cost += float(d @ d)
            V += np.diag(1.0 / self.sigma_prior ** 2)
            g -= d / self.sigma_prior
        else:
            cost += self._prior_cost(theta)
        return _Normal(cost, V, g, U, W, gk, V_stars, sum_wz, n, Vk, gthk, zk, nk)

    def without_frame(self, ne: _Normal, schur_full: tuple[np.ndarray, np.ndarray, list],
                      k: int) -> tuple[np.ndarray, np.ndarray, float]:
        """The camera of the problem without frame ``k``: ``(Δθ, covariance, s²)``.

        One Gauss–Newton step from the full problem's solution, on its normal equations with
        frame ``k``'s terms taken out (the Schur complement ``schur_full`` of :meth:`schur`
        at λ = 0, so no evaluation of the model): at the full solution the fold's gradient
        is frame ``k``'s alone, and the step lands on the fold's own solution to second
        order (measured: within 0.007 σ of a converged refit, ``test/test_bundle.py``).
        The covariance is the fold's ``(S_k / s_k² + Λ_prior)⁻¹``, ``s_k²`` the variance
        factor of the other frames' stars.
        """
        S, b, Uinv = schur_full
        W, Ui, gk = ne.W[k], Uinv[k], ne.gk[k]
        S_k = S + W.T @ Ui @ W - ne.Vk[k]
        S_k = 0.5 * (S_k + S_k.T)
        b_k = b + W.T @ (Ui @ gk) - ne.gthk[k]
        dtheta = _solve_equilibrated(S_k, b_k)
        dof = 2 * (ne.n_stars - ne.nk[k]) - 3 * (len(ne.U) - 1) - self.P
        s2 = (ne.sum_wz - ne.zk[k]) / dof if dof > 0 else float("nan")
        prior = np.diag(1.0 / self.sigma_prior ** 2)
        info = (S_k - prior) / s2 + prior if np.isfinite(s2) else S_k
        cov = _equilibrated_inverse(info)
        return dtheta, 0.5 * (cov + cov.T), float(s2)

    @staticmethod
    def schur(ne: _Normal, lam: float = 0.0, stars_only: bool = False
              ) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
        """Camera block with the attitudes eliminated: ``(S, b, [U_k⁻¹])``."""
        V = ne.V_stars if stars_only else ne.V
        S = V + lam * np.diag(np.diag(V))
        b = ne.g.copy()
        Uinv = []
        for U, W, gk in zip(ne.U, ne.W, ne.gk, strict=True):
            Ud = U + lam * np.diag(np.diag(U))
            Ui = _inv3(Ud)
            Uinv.append(Ui)
            if W.shape[1]:
                UW = Ui @ W
                S -= W.T @ UW
                b -= UW.T @ gk
        return 0.5 * (S + S.T), b, Uinv

    def step(self, ne: _Normal, lam: float) -> tuple[np.ndarray, list[np.ndarray]]:
        """One damped Gauss–Newton step ``(Δθ, [Δφ_k])``."""
        S, b, Uinv = self.schur(ne, lam)
        dtheta = _solve_equilibrated(S, b) if len(b) else np.zeros(0)
        dphi = [Ui @ (gk - W @ dtheta) for Ui, W, gk in zip(Uinv, ne.W, ne.gk, strict=True)]
        return dtheta, dphi

    def solve(self, theta: np.ndarray, Rs: list[np.ndarray], with_theta: bool = True,
              max_iterations: int = 60, tol: float = 1e-6
              ) -> tuple[np.ndarray, list[np.ndarray], _Normal, int]:
        """Levenberg–Marquardt from ``(θ, R)`` (``with_theta=False``: attitudes only).

        Returns the solution, its normal equations and the number of linearizations.
        Converged when a step lowers the cost (a χ² in stated-σ units) by less than ``tol``:
        the step left is then ~10⁻³ of the parameters' σ.
        """
        theta = np.asarray(theta, dtype=float).copy()
        Rs = [np.asarray(R, dtype=float).copy() for R in Rs]
        ne = self.normal(theta, Rs, with_theta)
        lam, it = 1e-8, 0
        for it in range(1, max_iterations + 1):  # noqa: B007 (returned)
            dtheta, dphi = self.step(ne, lam)
            # the decrease the linear model predicts (cost = Σ z: 2 δᵀg − δᵀHδ ≈ δᵀg)
            predicted = float(dtheta @ ne.g) if with_theta else 0.0
            predicted += sum(float(d @ gk) for d, gk in zip(dphi, ne.gk, strict=True))
            if predicted < 0.1 * tol:
                break
            accepted = False
            while lam < 1e12:
                th_new = theta + dtheta if with_theta else theta
                R_new = [so3_exp(p) @ R for p, R in zip(dphi, Rs, strict=True)]
                c_new = self.cost(th_new, R_new)
                if c_new <= ne.cost:
                    accepted = True
                    break
                lam *= 10.0
                dtheta, dphi = self.step(ne, lam)
            if not accepted:
                break
            decrease = ne.cost - c_new
            theta, Rs = th_new, R_new
            ne = self.normal(theta, Rs, with_theta)
            lam = max(lam / 10.0, 1e-12)
            if decrease <= tol:
                break
        return theta, Rs, ne, it


def _inv3(U: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.inv(U)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(U)


def _solve_equilibrated(S: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = 1.0 / np.sqrt(np.maximum(np.diag(S), 1e-300))
    A = S * np.outer(d, d)
    try:
        y = np.linalg.solve(A, b * d)
    except np.linalg.LinAlgError:
        y = np.linalg.lstsq(A, b * d, rcond=None)[0]
    return y * d


def initial_attitudes(model: StarModel, theta: np.ndarray, frames: list[BundleFrame],
                      gate_deg: float | None = GATE_DEG) -> tuple[list[np.ndarray], int]:
    """Each frame's ``R_i_b`` from a Wahba fit under the camera of ``θ``; the gate.

    Two passes per frame: stars more than 5 × the median angle off are left out of the
    second; then stars farther than ``max(gate_deg, 5 × median)`` from their catalogue
    direction are marked not used (wrong identities).  Returns the attitudes and the number
    of stars gated.
    """
    R_imu_st = model.installation_at(theta, frames[0].ctx)[0] if frames else np.eye(3)
    gated = 0
    Rs = []
    for f in frames:
        cam = model.camera_at(theta, f.ctx)
        v = cam.unproject(f.uv)
        ok = np.all(np.isfinite(v), axis=1)
        if ok.sum() < 2:
            raise StellarCalError(f"frame {f.index}: fewer than two stars unproject under "
                                  "the prior camera (is the prior's image size right?)")
        R = wahba(v[ok], f.u_i[ok])
        err = np.full(len(v), np.pi)
        for _ in range(2):
            err[ok] = np.arccos(np.clip(np.einsum("ij,ij->i", v[ok] @ R.T, f.u_i[ok]), -1, 1))
            keep = ok & (err <= max(5.0 * float(np.median(err[ok])), 1e-6))
            if keep.sum() >= 3:
                R = wahba(v[keep], f.u_i[keep])
        err[ok] = np.arccos(np.clip(np.einsum("ij,ij->i", v[ok] @ R.T, f.u_i[ok]), -1, 1))
        if gate_deg is not None:
            lim = max(np.deg2rad(gate_deg), 5.0 * float(np.median(err[ok])))
            use = ok & (err < lim)
        else:
            use = ok
        gated += int((~use).sum())
        f.use = use
        Rs.append(R @ R_imu_st.T)  # R_i_b = R_i_st R_imu_stᵀ
    return Rs, gated


def _robust_scale(z: np.ndarray) -> float:
    """σ of 2-D residuals from the median of their squared norms (χ²(2) median 2 ln 2)."""
    z = z[np.isfinite(z)]
    return float(np.sqrt(np.median(z) / (2.0 * np.log(2.0)))) if len(z) else 1.0


def star_residuals(b: Bundle, theta: np.ndarray, Rs: list[np.ndarray],
                   frames: list[BundleFrame]) -> list[np.ndarray]:
    """Whitened residuals (n, 2) of every identified star of ``frames`` (not only inliers)."""
    out = []
    for R, f in zip(Rs, frames, strict=True):
        e, _, _ = b.residuals(theta, R, f, jacobians=False)
        out.append(e)
    return out


@dataclass
class Fit:
    """A converged bundle: θ, the attitudes ``R_i_b`` and the normal equations there."""

    theta: np.ndarray
    attitudes: list[np.ndarray]
    normal: _Normal
    problem: Bundle
    iterations: int

    def covariance(self) -> tuple[np.ndarray, float]:
        """``(S / s² + Λ_prior)⁻¹`` and the variance factor ``s²`` of the star rows."""
        b = self.problem
        S, _, _ = Bundle.schur(self.normal, 0.0, stars_only=True)
        dof = 2 * self.normal.n_stars - 3 * len(b.frames) - b.P
        s2 = self.normal.sum_wz / dof if dof > 0 else float("nan")
        info = S / s2 + np.diag(1.0 / b.sigma_prior ** 2) if np.isfinite(s2) else \
            S + np.diag(1.0 / b.sigma_prior ** 2)
        cov = _equilibrated_inverse(info)
        return 0.5 * (cov + cov.T), float(s2)


def fit_bundle(model: StarModel, frames: list[BundleFrame], theta0: np.ndarray,
               attitudes: list[np.ndarray], theta_prior: np.ndarray, sigma_prior: np.ndarray,
               loss: str = "linear", outlier_probability: float | None = OUTLIER_PROBABILITY,
               max_iterations: int = 60) -> tuple[Fit, int]:
    """Fit θ and the attitudes; stars beyond the outlier gate are left out (``f.use``).

    The plain fit with ``loss`` first; if a star lies beyond the χ²(2) gate of
    ``outlier_probability`` (robust scale), the fit starts again robustly (soft-L1, σ
    rescaled to the data), leaves such stars out until the set is stable, and ends with
    ``loss`` on the inliers.  Clean data end after the plain fit.  Returns the fit and the
    number of outliers.
    """
    ident = [f.use.copy() for f in frames]

    def solve(loss_: str, theta, Rs, scale: float = 1.0) -> Fit:
        b = Bundle(model, frames, theta_prior, sigma_prior, loss_, 3.0, scale)
        th, R, ne, it = b.solve(theta, Rs, max_iterations=max_iterations)
        return Fit(th, R, ne, b, it)

    fit = solve(loss, theta0, attitudes)
    if not outlier_probability:
        return fit, 0

    def beyond(f_: Fit, scale: float) -> list[np.ndarray]:
        probe = Bundle(model, frames, theta_prior, sigma_prior, sigma_scale=scale,
                       masks=ident)
        es = star_residuals(probe, f_.theta, f_.attitudes, probe.frames)
        flat = np.concatenate([e.reshape(-1) for e in es])
        out = beyond_gate(np.nan_to_num(flat, nan=1e6), outlier_probability)
        return np.split(out, np.cumsum([len(e) for e in es])[:-1])

    if not any(x.any() for x in beyond(fit, 1.0)):
        return fit, 0
    # robust: soft-L1 with the σ scale of the data, gate until stable
    scale = 1.0
    robust = fit
    for _ in range(6):
        for _ in range(3):
            robust = solve("soft_l1", robust.theta, robust.attitudes, scale)
            es = star_residuals(robust.problem, robust.theta, robust.attitudes,
                                robust.problem.frames)
            ratio = _robust_scale(np.concatenate([np.sum(e ** 2, axis=1) for e in es]))
            if 0.7 < ratio < 1.4:
                break
            scale *= ratio
        out = beyond(robust, scale)
        changed = False
        for f, m, o in zip(frames, ident, out, strict=True):
            use = m.copy()
            use[np.flatnonzero(m)] = ~o
            changed |= not np.array_equal(use, f.use)
            f.use = use
        if not changed:
            break
    n_out = int(sum(int(m.sum() - f.use.sum()) for f, m in zip(frames, ident, strict=True)))
    log.info("bundle: %d stars beyond the outlier gate (p = %g) left out", n_out,
             outlier_probability)
    fit = solve(loss, robust.theta, robust.attitudes)
    return fit, n_out


# ============================================================================ the method
@dataclass
class BundleResult:
    """Result of :func:`~stellar_cal_ros.methods.bundle_runs.run_bundle`."""

    calibration: Calibration
    model: StarModel
    theta: np.ndarray
    covariance: np.ndarray  #: (P, P) of θ
    parameter_names: list[str]
    variance_factor: float  #: s²: (σ̂ / stated σ)²
    sigma_px: float  #: σ̂ of a star of median stated σ, px
    rms_px: float  #: RMS of |Δuv| of the inliers, px
    frames: list[BundleFrame]  #: the fitted frames (``use``: inliers)
    attitudes: list[np.ndarray]  #: R_i_b of each fitted frame
    counts: BundleCounts
    residuals: dict[str, np.ndarray]
    iterations: int
    loss: str
    theta_prior: np.ndarray
    sigma_prior: np.ndarray
    outlier_probability: float | None
    cross_validation: dict[str, Any] | None = None
    held_out: Any = None  #: :class:`~stellar_cal_ros.methods.bundle_cv.HeldOut` (if run)
    degraded: list[str] = field(default_factory=list)

    @property
    def sigma(self) -> np.ndarray:
        """1-σ of θ."""
        return np.sqrt(np.diag(self.covariance))


def make_model(prior: Calibration, effects: Sequence[str] | None
               ) -> tuple[StarModel, np.ndarray, np.ndarray]:
    """The bundle's star model for ``effects`` (added to the baseline), its prior θ and σ."""
    model = StarModel(registry.create_many(check_effects(effects or [])), prior)
    sp = model.initial_sigma.copy()
    if np.any(~np.isfinite(sp)) or np.any(sp <= 0):
        raise ModelError("every estimated parameter needs a positive prior σ")
    return model, model.initial_value.copy(), sp


def residual_table(fit: Fit, frames: list[BundleFrame], s: float) -> dict[str, np.ndarray]:
    """Per-star residuals of every identified star of the fitted frames (gated: not used)."""
    model = fit.problem.model
    cols: dict[str, list[np.ndarray]] = {}

    def put(key: str, value: np.ndarray) -> None:
        cols.setdefault(key, []).append(np.asarray(value))

    for R, f in zip(fit.attitudes, frames, strict=True):
        with np.errstate(all="ignore"):
            pred = model.predict(fit.theta, f.u_i, f.ctx, _constant(R), jacobians=False)
        n = len(f.uv)
        d = f.uv - pred.uv
        var = (f.sigma * s) ** 2
        put("t", np.full(n, f.stamp_ns * 1e-9))
        put("frame", np.full(n, f.index, dtype=np.int64))
        put("catalog_id", f.catalog_id)
        put("u", f.uv[:, 0])
        put("v", f.uv[:, 1])
        put("u_pred", pred.uv[:, 0])
        put("v_pred", pred.uv[:, 1])
        put("du", d[:, 0])
        put("dv", d[:, 1])
        put("s_uu", var)
        put("s_uv", np.zeros(n))
        put("s_vv", var)
        put("nis", np.sum(d ** 2, axis=1) / var)
        put("magnitude", f.magnitude)
        put("gated", ~f.use)
        for k, name in enumerate(("x_st", "y_st", "z_st")):
            put(name, pred.directions_st[:, k])
        for name in ("omega_x", "omega_y", "omega_z"):
            put(name, np.zeros(n))
        put("head_temperature", np.full(n, f.ctx.head_temperature_c))
    return {k: np.concatenate(v) for k, v in cols.items()}
