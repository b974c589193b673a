"""Attitude-correlated-frames (ACF) batch calibration (Liu et al. 2017, eqs. 6-11).

The gyros tie every star frame to the first one: with the IMU propagated once through the
whole bag (prior sensor model),

    R_i_b(t_k) = Exp(φ) · Exp(G_k Δθ_gyro) · R̂_i_b0 · R_b0_b(t_k),

where ``R̂_i_b0`` is the (estimated) IMU attitude at the first selected frame, ``φ`` its
left (inertial) correction, ``R_b0_b(t_k)`` the gyro attitude change to frame ``k``
(interpolated within IMU samples) and ``G_k`` the first-order sensitivity of that change to
gyro bias / scale / misalignment effects if those are estimated.  The unknowns are ``φ`` (3)
and the :class:`~stellar_cal_ros.methods.star_model.StarModel` parameters θ of the effects
(default: installation, focal length, principal point, k1 k2, k3, p1 p2).  All stars of all
frames enter one least-squares problem (``scipy.optimize.least_squares``) with the analytic
Jacobian of the star model, plus prior residuals ``(θ − θ_prior)/σ_prior`` which fix the
directions the data cannot see (see below) and make the problem well posed.

Observability.  Only attitude *changes* come from the gyros, so a rotation ``a`` of the
first attitude is indistinguishable from an installation rotation δ with
``R_imu_st δ = R_b_k_b0 a`` for every frame — possible exactly for ``a`` along the rotation
axis of a single-axis sweep.  The installation component about the sweep axis (expressed in
tracker axes) is therefore unobservable apart from the small part Earth rotation adds, and
stays at its prior.  A principal-point offset and a tracker rotation about x/y both shift
the whole star field; they separate only through the perspective term ``f (1 + x²)`` — weakly
over a 15° field — so ``cx`` and ``ry`` (``cy`` and ``rx``) are strongly correlated.  The
:class:`ObservabilityReport` lists these combinations from the SVD of the star Jacobian.

Solution (Liu's two steps): a joint Wahba fit of all frames gives ``R̂_i_b0`` (from the
frames whose own attitude agrees with the consensus, so a frame of garbage cannot pull it);
step 1 fits a distortion-free pinhole (focal length, principal point, installation) and φ
with a soft-L1 loss; step 2 fits every parameter.  Wrong identities are removed twice: a
catalogue direction far from the measured one (the identification gate, ``gate_deg``), and
— by default — a star whose normalized residual after a robust fit lies beyond a χ²(2) gate
(:mod:`~stellar_cal_ros.methods.acf_robust`: a star labelled as another star of the same
frame passes the first gate and drags a plain least squares by hundreds of arcseconds).
The final fit runs on the inliers with the chosen loss (``linear`` by default: efficient;
``huber`` / ``soft_l1`` / ``cauchy`` with ``f_scale = 3σ`` on the star residuals only — the
prior residuals stay quadratic).  Both rejections are counted in :class:`~stellar_cal_ros.
methods.acf_data.DataQuality`, with the IMU repairs (NaN/lost samples bridged) and the
skipped stars and frames; data that contradict the contract (gyro units or axes, long IMU
gaps, clock jumps or offsets) raise :class:`~stellar_cal_ros.errors.DataError` naming the
cause (:mod:`~stellar_cal_ros.methods.acf_data`).

Bound. :func:`~stellar_cal_ros.methods.acf_bound.crlb_acf` gives the Cramér–Rao bound of this
problem at the truth (φ and the installation as nuisance, with and without the gyro random
walk) and the covariance of the least squares as implemented, which ignores the random-walk
correlation in its weights (in Liu's setting at 0.1 px 1-4 % above the bound on x0 y0 f and 4-8
% on the observable installation axes; at 0.05 px, where the random walk weighs more, up to
12-19 %). In Liu's setting the bound on x0 y0 f is within 3 % of the attitude-free (IAC) bound
(:func:`~stellar_cal_ros.methods.iac.crlb_iac`) — also for a two-axis or a three-axis step
motion: the principal point trades against the installation tilt here as against each frame's
attitude there. The gyros add information on the intrinsics only when the installation is known
(x0: 0.18 vs 1.03 px at 0.1 px). ``benchmarks/acf_vs_paper.py`` prints the bounds.

Times: relative seconds ``(stamp_ns − t0_ns)·1e-9`` with ``t0_ns`` the first IMU stamp; the
star model's ``ctx.stamp`` (POSIX float, needed by astrometric effects) is only used to carry
a time shift back to the exact relative time.
"""

from __future__ import annotations

import copy
import logging
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from stellar_cal_ros.core.attitude import wahba
from stellar_cal_ros.core.rotation import left_jacobian, so3_exp
from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.effects.base import FrameContext
from stellar_cal_ros.effects.registry import create_many
from stellar_cal_ros.errors import ModelError, StellarCalError
from stellar_cal_ros.io.calibration import Calibration, store_estimate
from stellar_cal_ros.methods.acf_covariance import (
    ObservabilityReport,
    _arw_density,
    _covariance,
    _observability,
    _random_walk_term,
)
from stellar_cal_ros.methods.acf_data import (
    AcfData,
    DataQuality,
    GyroChain,
    check_gyro_against_stars,
    check_overlap,
    load_acf_data,
    report_quality,
    select_frames,
    unit_vectors,
)
from stellar_cal_ros.methods.acf_robust import (
    _gate_outliers,
    _robust_weights,
    _solve,
    _solve_scaled,
    _used,
    beyond_gate,
)
from stellar_cal_ros.methods.frames import losses_record, star_masks, star_sigma
from stellar_cal_ros.methods.init_from import prior_from_result  # noqa: F401 (re-exported)
from stellar_cal_ros.methods.registry import STAGES_WITHOUT_ACCEL, BatchOutput, MethodSpec
from stellar_cal_ros.methods.star_model import StarModel
from stellar_cal_ros.sky.identify import identify_frames, needs_identification

log = logging.getLogger(__name__)

ACF_EFFECTS: tuple[str, ...] = ("installation", "focal_length", "principal_point",
                                "radial_k1k2", "radial_k3", "tangential")
"""Default effect set of the ACF method (Liu et al. eq. 9: x0 y0 f q1 q2 q3 p1 p2 θ1-3)."""

PINHOLE_EFFECTS: tuple[str, ...] = ("installation", "focal_length", "principal_point",
                                    "pixel_aspect")
"""Effects kept in step 1 (distortion-free pinhole)."""

MIN_FRAMES = 2
MIN_STARS_PER_FRAME = 2
OUTLIER_PROBABILITY = 1.0 - 1e-6
"""Default outlier gate: a star's normalized residual beyond the χ²(2) quantile (5.3 σ).

A wrong identity is off by degrees (thousands of σ); the gate's false alarms (10⁻⁶ a star)
leave clean runs of up to ~10⁵ stars untouched in practice."""


# ============================================================================ results

@dataclass
class AcfResult:
    """Result of :func:`run_acf`."""

    calibration: Calibration
    residuals: dict[str, np.ndarray]
    cost: float
    iterations: int
    observability: ObservabilityReport
    theta: np.ndarray
    covariance: np.ndarray  # (3 + P, 3 + P): [φ, θ]
    parameter_names: list[str]
    sigma_px: float  # a-posteriori centroid σ (σ̂), px
    rms_px: float  # RMS of |Δuv| over the fitted frames (inliers), px
    R_i_b0: np.ndarray  # IMU attitude at the reference frame
    reference_time: float  # relative s of the reference frame
    frames: np.ndarray  # indices of the fitted frames
    model: StarModel
    chain: GyroChain
    data: AcfData
    loss: str
    step1_theta: np.ndarray | None = None
    quality: DataQuality | None = None  # what was repaired, skipped, rejected (= data.quality)
    degraded: list[str] = field(default_factory=list)  # why the result is not to be trusted
    derived: dict[str, Any] = field(default_factory=dict)  # equivalent principal point ± σ

    @property
    def sigma(self) -> np.ndarray:
        """1-σ of ``[φ, θ]``."""
        return np.sqrt(np.diag(self.covariance))


# ============================================================================ helpers
@dataclass
class _Frame:
    index: int
    t_rel: float
    stamp: float  # POSIX float for the star model's ctx
    u_i: np.ndarray
    uv: np.ndarray
    sigma: np.ndarray
    catalog_id: np.ndarray
    magnitude: np.ndarray
    ctx: FrameContext
    C: np.ndarray | None = None
    use: np.ndarray | None = None  # stars that passed the identification gate

    def subset(self) -> _Frame:
        """The frame restricted to the stars in ``use``."""
        if self.use is None or self.use.all():
            return self
        m = self.use
        ctx = copy.copy(self.ctx)
        ctx.catalog_id, ctx.magnitude = self.ctx.catalog_id[m], self.ctx.magnitude[m]
        return _Frame(self.index, self.t_rel, self.stamp, self.u_i[m], self.uv[m],
                      self.sigma[m], self.catalog_id[m], self.magnitude[m], ctx)


def _prepare_frames(data: AcfData, idx: np.ndarray, chain: GyroChain, time_offset: float,
                    sigma_px: float | None, min_stars: int,
                    image_size: tuple[int, int] | None = None,
                    quality: DataQuality | None = None) -> list[_Frame]:
    """The selected frames' usable stars, with their attitude-chain time.

    The stars every method uses (:func:`~stellar_cal_ros.methods.frames.star_masks`;
    without ``image_size`` the detector check is left out); a message σ of 0 ("unknown"),
    negative or NaN becomes 1 px (the fit rescales by σ̂).  Frames with fewer than
    ``min_stars`` such stars or outside the IMU span are skipped.  Everything left out is
    counted in ``quality`` (if given).
    """
    lo, hi = chain.span
    q = quality if quality is not None else DataQuality()
    big = np.iinfo(np.int32).max
    width, height = image_size if image_size is not None else (big, big)
    out = []
    for k in idx:
        fr = data.frames[int(k)]
        uv = np.asarray(fr.uv, dtype=float).reshape(-1, 2)
        m = star_masks(fr, width, height)
        ok = m.usable
        q.stars_unidentified += int(np.sum(m.unidentified))
        q.stars_invalid += int(np.sum(m.invalid))
        q.stars_outside_image += int(np.sum(m.off_detector))
        if ok.sum() < min_stars:
            q.frames_few_stars += 1
            continue
        t_rel = float(data.rel(fr.stamp_ns))
        if not (lo <= t_rel + time_offset <= hi):
            q.frames_outside_imu += 1
            continue
        if sigma_px is not None:
            sig = np.full(ok.sum(), float(sigma_px))
        else:
            sig, bad = star_sigma(np.asarray(fr.sigma, dtype=float)[ok], 1.0)
            q.stars_bad_sigma += bad
        ctx = FrameContext(stamp=fr.stamp_ns * 1e-9, catalog_id=fr.catalog_id[ok].astype(np.int64),
                           magnitude=np.asarray(fr.magnitude, dtype=float)[ok], site=data.site)
        for key, (ts, vs) in data.scalars.items():
            setattr(ctx, key, float(np.interp(t_rel, ts, vs)))
        out.append(_Frame(int(k), t_rel, fr.stamp_ns * 1e-9,
                          unit_vectors(fr.right_ascension[ok], fr.declination[ok]),
                          uv[ok], sig, fr.catalog_id[ok].astype(np.int64),
                          np.asarray(fr.magnitude, dtype=float)[ok], ctx))
    return out


class _Problem:
    """Residuals and analytic Jacobian of the ACF least squares for one effect set."""

    def __init__(self, model: StarModel, chain: GyroChain, frames: list[_Frame],
                 R_i_b0: np.ndarray, t_ref: float, theta_prior: np.ndarray,
                 sigma_prior: np.ndarray, sigma_scale: float = 1.0) -> None:
        self.model, self.chain, self.frames = model, chain, frames
        self.R_i_b0 = R_i_b0
        self.t_ref = t_ref
        self.theta_prior = theta_prior
        self.sigma_prior = sigma_prior
        self.sigma_scale = sigma_scale
        self.theta_lin = theta_prior.copy()  # gyro linearization point (the chain's θ0)
        R_ref, _ = chain.attitude(t_ref)
        self.R_ref = R_ref
        C_ref = chain.sensitivity(t_ref)
        self.gyro_used = bool(np.any(chain.C))
        for f in frames:
            f.C = R_i_b0 @ R_ref.T @ (chain.sensitivity(f.t_rel) - C_ref)
        self.n_star = int(sum(2 * len(f.uv) for f in frames))
        self.n_x = 3 + model.size
        self._cache: tuple[bytes, np.ndarray, np.ndarray] | None = None

    def attitude_fn(self, f: _Frame, phi: np.ndarray, dtheta: np.ndarray):
        R_phi = so3_exp(phi)
        R_g = so3_exp(f.C @ dtheta) if self.gyro_used else np.eye(3)
        base = R_phi @ R_g @ self.R_i_b0 @ self.R_ref.T

        def attitude(shift: float) -> tuple[np.ndarray, np.ndarray]:
            R_n0_b, w = self.chain.attitude(f.t_rel + shift)
            return base @ R_n0_b, w

        return attitude

    def predict(self, x: np.ndarray, f: _Frame, jac: bool = True):
        phi, theta = x[:3], x[3:]
        att = self.attitude_fn(f, phi, theta - self.theta_lin)
        pred = self.model.predict(theta, f.u_i, f.ctx, att)
        if not jac:
            return pred.uv, None
        n = len(f.uv)
        J = np.zeros((n, 2, self.n_x))
        J[:, :, :3] = pred.H_attitude @ left_jacobian(phi)
        J[:, :, 3:] = pred.H_parameters
        if self.gyro_used:
            J[:, :, 3:] += pred.H_attitude @ (so3_exp(phi) @ f.C)
        return pred.uv, J

    def evaluate(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = x.tobytes()
        if self._cache is not None and self._cache[0] == key:
            return self._cache[1], self._cache[2]
        rs, Js = [], []
        for f in self.frames:
            uv, J = self.predict(x, f)
            w = 1.0 / (f.sigma * self.sigma_scale)
            rs.append(((f.uv - uv) * w[:, None]).ravel())
            Js.append((-J * w[:, None, None]).reshape(-1, self.n_x))
        P = self.model.size
        rp = (x[3:] - self.theta_prior) / self.sigma_prior
        Jp = np.zeros((P, self.n_x))
        Jp[:, 3:] = np.diag(1.0 / self.sigma_prior)
        r = np.concatenate(rs + [rp])
        J = np.vstack(Js + [Jp])
        if not np.all(np.isfinite(r)):
            bad = ~np.isfinite(r)
            r = np.where(bad, 1e6, r)  # star behind the camera: push back hard
            J[bad] = 0.0
        self._cache = (key, r, J)
        return r, J

    def fun(self, x: np.ndarray) -> np.ndarray:
        return self.evaluate(x)[0]

    def jac(self, x: np.ndarray) -> np.ndarray:
        return self.evaluate(x)[1]


def _initial_attitude(frames: list[_Frame], chain: GyroChain, model: StarModel,
                      theta: np.ndarray, t_ref: float,
                      gate_deg: float | None) -> np.ndarray:
    """Joint Wahba fit of ``R_i_b0`` over all frames; sets each frame's ``use`` mask.

    Each frame alone implies an ``R_i_b0`` (its own Wahba fit carried back along the gyro
    chain); the joint fit uses the frames that agree within 1° with the candidate most
    frames agree with, so a frame of garbage (or many wrong identities) cannot pull it.
    Two passes: the second drops stars more than ``5 × median`` off.  Then stars whose
    catalogue direction is more than ``max(gate_deg, 5 × median)`` from the measured one are
    marked as misidentified (``use = False``): a random wrong identity points far outside
    the field, where the projection is singular and no loss function copes.
    """
    cam = model.camera_at(theta, frames[0].ctx)
    R_imu_st, _ = model.installation_at(theta, frames[0].ctx)
    R_ref, _ = chain.attitude(t_ref)
    v_b0, u_i = [], []
    for f in frames:
        d = cam.unproject(f.uv)
        R_b0_b = R_ref.T @ chain.attitude(f.t_rel + model.prior.time_offset)[0]
        v_b0.append(d @ (R_b0_b @ R_imu_st).T)
        u_i.append(f.u_i)
    v, u = np.vstack(v_b0), np.vstack(u_i)
    ok = np.all(np.isfinite(v), axis=1)
    sel = ok & _consensus_frames(frames, v, u, ok)
    R = wahba(v[sel], u[sel])

    def angles(R: np.ndarray) -> np.ndarray:
        a = np.full(len(v), np.pi)
        a[ok] = np.arccos(np.clip(np.einsum("ij,ij->i", v[ok] @ R.T, u[ok]), -1, 1))
        return a

    err = angles(R)
    keep = sel & (err < max(5.0 * np.median(err[sel]), 20 * ARCSEC))
    if keep.sum() >= 3:
        R = wahba(v[keep], u[keep])
        err = angles(R)
    if gate_deg is None:
        use = ok
    else:
        use = ok & (err < max(np.deg2rad(gate_deg), 5.0 * float(np.median(err[ok]))))
    start = 0
    for f in frames:
        f.use = use[start:start + len(f.uv)]
        start += len(f.uv)
    return R


def _consensus_frames(frames: list[_Frame], v: np.ndarray, u: np.ndarray, ok: np.ndarray,
                      tol_deg: float = 1.0, sample: int = 300) -> np.ndarray:
    """Star mask of the frames whose own ``R_i_b0`` agrees with the consensus.

    ``v`` (body-at-reference directions), ``u`` (catalogue) and ``ok`` are stacked over the
    frames.  The consensus is the candidate with the most others within ``tol_deg`` among
    at most ``sample`` evenly spaced frames.
    """
    starts = np.cumsum([0] + [len(f.uv) for f in frames])
    idx, cands = [], []
    for k in range(len(frames)):
        sl = slice(starts[k], starts[k + 1])
        m = ok[sl]
        if m.sum() >= 2:
            idx.append(k)
            cands.append(wahba(v[sl][m], u[sl][m]))
    if len(cands) < 3:
        return np.ones(len(v), dtype=bool)
    q = Rotation.from_matrix(np.asarray(cands)).as_quat()
    sub = np.unique(np.linspace(0, len(q) - 1, min(len(q), sample)).astype(int))
    cos_half = np.cos(np.deg2rad(tol_deg) / 2.0)
    best = sub[int(np.argmax(np.sum(np.abs(q[sub] @ q[sub].T) > cos_half, axis=1)))]
    agree = np.abs(q @ q[best]) > cos_half
    mask = np.zeros(len(v), dtype=bool)
    for k in np.asarray(idx)[agree].tolist():
        mask[starts[k]:starts[k + 1]] = True
    return mask


# ============================================================================ main entry
#: the stages :func:`run_acf` reports to its ``progress`` callback, in order
ACF_STAGES = ("read the bag", "initial attitude", "pinhole fit (step 1)",
              "full fit (step 2)", "covariance and observability")


def run_acf(
    source: str | os.PathLike[str] | AcfData,
    prior: Calibration,
    effects: Sequence[str] | None = None,
    *,
    frames: Any = None,
    loss: str = "linear",
    sigma_px: float | None = None,
    two_step: bool = True,
    reference_frame: int = 0,
    max_nfev: int = 100,
    min_stars_per_frame: int = MIN_STARS_PER_FRAME,
    gyro_arw: float | None = None,
    gate_deg: float | None = 2.0,
    outlier_probability: float | None = OUTLIER_PROBABILITY,
    check_gyro: bool = True,
    star_topic: str = "/star_tracker/stars",
    imu_topic: str = "/imu/data",
    progress: Callable[[str], None] | None = None,
    on_error: str = "raise",
) -> AcfResult:
    """Calibrate the star tracker (and its installation) from attitude-correlated frames.

    Parameters
    ----------
    source : path or AcfData
        A contract bag, or data loaded by :func:`load_acf_data`.
    prior : Calibration
        Starting values and prior σ; everything not estimated is taken from it.
    effects : list of str, optional
        Effect ids to estimate (default :data:`ACF_EFFECTS`).  Gyro effects
        (``gyro_bias``, ``gyro_scale_factor``, ``gyro_misalignment``) enter through the
        first-order sensitivity of the gyro attitude changes; ``time_offset`` through the
        body rate.
    frames : None, 'all', 'odd', 'even', indices, slice or bool mask
        Frames to fit ('odd' = 1st, 3rd, … as Liu et al. count them = indices 0, 2, …).
    loss : {'linear', 'huber', 'soft_l1', 'cauchy'}
        Loss on the star residuals of the final fit (``f_scale = 3σ``); prior residuals
        stay quadratic.  With the outlier gate on, the final fit runs on the gated inliers,
        so ``linear`` (the default) is the efficient choice.
    sigma_px : float, optional
        Centroid σ, px (default: the messages' ``sigma``, else 1 px).  The covariance is
        scaled by the a-posteriori variance factor in any case.
    two_step : bool
        Liu's two steps (pinhole first).  Without it, the full model starts from the prior.
    reference_frame : int
        Position within the selected frames of the frame whose attitude is estimated.
    max_nfev : int
        Function evaluations per least-squares step.
    gyro_arw : float, optional
        Gyro angle random walk, rad/√s, for the covariance (default: from the IMU messages'
        ``angular_velocity_covariance`` × sample interval; 0 if they carry none).  The
        random walk correlates the attitudes of all frames; it does not change the fit.
    gate_deg : float or None
        Identification gate: after the initial attitude fit, stars whose catalogue direction
        is more than ``max(gate_deg, 5 × median error)`` off are not fitted (``gated`` in
        the residual table).  None disables it.
    outlier_probability : float or None
        Outlier gate (default on): if after the fit any star's normalized residual
        ``(Δu² + Δv²)/s²`` (``s`` the robust scale of the whitened residuals) exceeds the
        χ²(2) quantile of this probability, the fit starts again robustly (soft-L1) and
        such stars are left out until the set is stable; the final fit with ``loss`` runs
        on the rest (clean data: the plain fit, unchanged).  Catches wrong
        identities inside the field (another star of the same frame) that pass the
        identification gate.  None: no gate (the plain least squares of ``loss``).
    check_gyro : bool
        Compare the gyro's rotation between frames with the stars' first
        (:func:`~stellar_cal_ros.methods.acf_data.check_gyro_against_stars`).
    min_stars_per_frame : int
        Frames with fewer identified stars are skipped.
    star_topic, imu_topic : str
        Topics when reading a bag.
    progress : callable, optional
        Called with the name of each of the :data:`ACF_STAGES` stages as it ends.
    on_error : {'raise', 'skip'}
        Reading a bag: ``skip`` reads past damage (:func:`load_acf_data`); the result's
        ``data_quality`` records what was lost.

    Returns
    -------
    AcfResult
        With :attr:`AcfResult.quality` (everything repaired, skipped or rejected) and
        :attr:`AcfResult.degraded` (reasons not to trust the result; empty if none).

    Raises
    ------
    DataError
        The data contradict the contract: gyro units or axes, an IMU gap longer than the
        star frame interval, a clock jump, star and IMU clocks that do not overlap.
    StellarCalError
        Missing topics, too few frames or stars, or a failed fit.
    """
    tell = progress or (lambda stage: None)
    data = source if isinstance(source, AcfData) else load_acf_data(
        source, star_topic, imu_topic, on_error=on_error)
    ident = None
    if any(needs_identification(f) for f in data.frames):  # unidentified centroids
        data.frames, ident = identify_frames(
            data.frames, prior.camera, prior.installation.as_matrix(), data.imu.stamp_ns,
            data.imu.angular_velocity)
        log.info("identification of unidentified centroids: %s", ident.as_dict())
    tell(ACF_STAGES[0])
    ids = list(ACF_EFFECTS if effects is None else effects)
    if not ids:
        raise StellarCalError("no effects to estimate")
    eff = create_many(ids)
    model = StarModel(eff, prior)
    theta_prior = model.initial_value.copy()
    sigma_prior = model.initial_sigma.copy()
    if np.any(~np.isfinite(sigma_prior)) or np.any(sigma_prior <= 0):
        raise ModelError("every estimated parameter needs a positive prior σ")
    chain = GyroChain(data, model, theta_prior)
    idx = select_frames(len(data.frames), frames)
    quality = data.quality
    fr = _prepare_frames(data, idx, chain, prior.time_offset, sigma_px, min_stars_per_frame,
                         (prior.camera.width, prior.camera.height), quality)
    check_overlap(data, chain.span, idx)
    n_stars = sum(len(f.uv) for f in fr)
    if len(fr) < MIN_FRAMES:
        raise StellarCalError(
            f"the ACF method needs at least {MIN_FRAMES} star frames with "
            f">= {min_stars_per_frame} identified stars inside the IMU span; got {len(fr)} "
            f"of {len(idx)} selected")
    if 2 * n_stars < 2 * (3 + model.size):
        raise StellarCalError(f"too few stars ({n_stars}) for {3 + model.size} unknowns")
    if check_gyro:
        cam = model.camera_at(theta_prior, fr[0].ctx)
        check_gyro_against_stars([f.t_rel + prior.time_offset for f in fr],
                                 [cam.unproject(f.uv) for f in fr], [f.u_i for f in fr],
                                 lambda t: chain.attitude(t)[0], prior.installation.as_matrix())
    ref = fr[min(max(reference_frame, 0), len(fr) - 1)]
    t_ref = ref.t_rel + prior.time_offset
    names = ["attitude.phi_x", "attitude.phi_y", "attitude.phi_z"] + model.parameter_names()

    # -- start: joint Wahba of all frames with the prior camera
    R_i_b0 = _initial_attitude(fr, chain, model, theta_prior, t_ref, gate_deg)
    fr_all = fr
    quality.stars_misidentified += int(sum((~f.use).sum() for f in fr_all))
    tell(ACF_STAGES[1])
    if quality.stars_misidentified:
        log.info("ACF: %d of %d stars fail the identification gate",
                 quality.stars_misidentified, n_stars)
    theta = theta_prior.copy()
    nfev = 0
    step1_theta = None
    if two_step:
        R_i_b0, theta, step1_theta, n1 = _step1(data, prior, model, eff, fr_all, R_i_b0,
                                                t_ref, theta, max_nfev)
        nfev += n1

    tell(ACF_STAGES[2])
    # -- step 2: everything; outliers gated after a robust fit, then the final fit
    def make(frames_used: list[_Frame], scale: float = 1.0) -> _Problem:
        return _Problem(model, chain, frames_used, R_i_b0, t_ref, theta_prior, sigma_prior,
                        scale)

    x0 = np.concatenate([np.zeros(3), theta])
    fr = _used(fr_all)
    problem = make(fr)
    res, n2 = _solve_scaled(problem, x0, loss, max_nfev)
    nfev += n2
    # clean data end here; with stars beyond the gate, start again robustly from x0
    if outlier_probability and beyond_gate(res.fun[:problem.n_star],
                                           outlier_probability).any():
        x, scale, n_gate, n_out = _gate_outliers(make, fr_all, x0, loss, outlier_probability,
                                                 max_nfev)
        quality.stars_outliers += n_out
        fr = _used(fr_all)
        problem = make(fr, scale)
        res, n2 = _solve_scaled(problem, x, loss, max_nfev)
        nfev += n_gate + n2
    if res.status < 0:
        raise StellarCalError(f"ACF least squares failed: {res.message}")
    if res.status == 0:
        log.warning("ACF least squares stopped after %d evaluations without converging",
                    res.nfev)

    tell(ACF_STAGES[3])
    # -- covariance (with the gyro random walk between frames), σ̂, observability
    theta_hat = res.x[3:]
    R_i_b0_hat = so3_exp(res.x[:3]) @ R_i_b0  # rebase: φ = 0 at the solution
    problem_final = _Problem(model, chain, fr, R_i_b0_hat, t_ref, theta_prior, sigma_prior,
                             problem.sigma_scale)
    x_hat = np.concatenate([np.zeros(3), theta_hat])
    r, J = problem_final.evaluate(x_hat)
    n_star = problem.n_star
    w = _robust_weights(loss, r[:n_star], 3.0)
    cov, s2 = _covariance(J, r, n_star, w, problem.n_x)
    q = _arw_density(data.imu, gyro_arw)
    if q > 0:
        cov = cov + _random_walk_term(cov, J, w, s2, fr, t_ref, q)
    sig_assumed = float(np.median(np.concatenate([f.sigma for f in fr]))) * problem.sigma_scale
    sigma_hat = sig_assumed * np.sqrt(s2)
    col_scale = np.concatenate([np.full(3, float(np.max(sigma_prior[model.slices[
        "installation"]])) if "installation" in model.slices else np.deg2rad(0.2)),
        sigma_prior])
    prior_sig_all = np.concatenate([np.full(3, np.inf), sigma_prior])
    obs = _observability(J, n_star, w, col_scale, names, cov, prior_sig_all, s2)

    tell(ACF_STAGES[4])
    cal = _store(model, prior, theta_hat, np.sqrt(np.diag(cov))[3:])
    cal.stamp = float(data.frames[fr[-1].index].stamp_ns * 1e-9)
    table = _residual_table(problem_final, x_hat, data, loss, sigma_hat, fr_all)
    inl = ~table["gated"]
    rms = float(np.sqrt(np.mean(table["du"][inl] ** 2 + table["dv"][inl] ** 2)))
    degraded = report_quality(data, chain.span, n_stars, len(idx), outlier_probability)
    cal.extra = dict(cal.extra)
    cal.extra["data_quality"] = {**quality.counts(), "degraded": bool(degraded),
                                 "reasons": degraded,  # (and what a read past damage lost)
                                 **losses_record(data.losses, data.imu.stamp_ns,
                                                 len(data.imu), data.frames)}
    if ident is not None:  # the result says how its stars were identified
        cal.extra["identification"] = ident.as_dict()
    derived = {}
    if "installation" in model.slices:
        from stellar_cal_ros.methods.results import equivalent_principal_point

        derived = equivalent_principal_point(model, theta_hat, cov[3:, 3:])
    return AcfResult(
        calibration=cal, residuals=table, cost=float(res.cost), iterations=int(nfev),
        observability=obs, theta=theta_hat, covariance=cov, parameter_names=names,
        sigma_px=float(sigma_hat), rms_px=rms, R_i_b0=R_i_b0_hat, reference_time=t_ref,
        frames=np.array([f.index for f in fr]), model=model, chain=chain, data=data,
        loss=loss, step1_theta=step1_theta, quality=quality, degraded=degraded,
        derived=derived)


def _step1(data: AcfData, prior: Calibration, model: StarModel, eff: list[Any],
           fr_all: list[_Frame], R_i_b0: np.ndarray, t_ref: float, theta: np.ndarray,
           max_nfev: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, int]:
    """Liu's step 1: a distortion-free pinhole and the first attitude, soft-L1 loss.

    Returns the refined ``R_i_b0``, θ with the pinhole parameters replaced, that θ (None if
    the model has no pinhole parameter) and the evaluations used.
    """
    ids1 = [e.id for e in eff if e.id in PINHOLE_EFFECTS]
    if not ids1:
        return R_i_b0, theta, None, 0
    fr = _used(fr_all)
    m1 = StarModel(create_many(ids1), prior)
    c1 = GyroChain(data, m1, m1.initial_value)
    p1 = _Problem(m1, c1, fr, R_i_b0, t_ref, m1.initial_value, m1.initial_sigma)
    r0 = p1.fun(np.concatenate([np.zeros(3), m1.initial_value]))[:p1.n_star]
    scale = max(1.4826 * float(np.median(np.abs(r0))), 1.0)
    p1.sigma_scale = scale
    p1._cache = None
    res1 = _solve(p1, np.concatenate([np.zeros(3), m1.initial_value]), "soft_l1", 3.0,
                  max_nfev)
    theta = theta.copy()
    for e in m1.effects:
        theta[model.slices[e.id]] = res1.x[3:][m1.slices[e.id]]
    log.info("ACF step 1 (pinhole): %d evaluations, scale %.3g px", res1.nfev, scale)
    return so3_exp(res1.x[:3]) @ R_i_b0, theta, theta.copy(), int(res1.nfev)


def _store(model: StarModel, prior: Calibration, theta: np.ndarray,
           sigma: np.ndarray) -> Calibration:
    return store_estimate(prior, model.effects, model.slices, theta, sigma, "acf", prior.stamp)


def _residual_table(problem: _Problem, x: np.ndarray, data: AcfData, loss: str,
                    sigma_hat: float, frames: list[_Frame],
                    gate_sigma: float = 6.0) -> dict[str, np.ndarray]:
    """Per-star residuals of every star of the fitted frames.

    ``gated``: the star failed the identification gate (not fitted), or a robust loss gave it
    little weight (``|Δ| > 6 σ̂`` on an axis).  With the linear loss only the former.
    """
    cols: dict[str, list[np.ndarray]] = {k: [] for k in (
        "t", "frame", "catalog_id", "u", "v", "u_pred", "v_pred", "du", "dv", "s_uu", "s_uv",
        "s_vv", "magnitude", "gated", "stamp_ns")}
    for f in frames:
        with np.errstate(all="ignore"):
            uv, _ = problem.predict(x, f, jac=False)
        n = len(f.uv)
        d = f.uv - uv
        s2 = np.full(n, sigma_hat ** 2)
        cols["t"].append(np.full(n, f.stamp))  # POSIX s, as the Kalman filters
        cols["frame"].append(np.full(n, f.index, dtype=np.int64))
        cols["catalog_id"].append(f.catalog_id)
        cols["u"].append(f.uv[:, 0])
        cols["v"].append(f.uv[:, 1])
        cols["u_pred"].append(uv[:, 0])
        cols["v_pred"].append(uv[:, 1])
        cols["du"].append(d[:, 0])
        cols["dv"].append(d[:, 1])
        cols["s_uu"].append(s2)
        cols["s_uv"].append(np.zeros(n))
        cols["s_vv"].append(s2)
        cols["magnitude"].append(f.magnitude)
        gated = ~f.use if f.use is not None else np.zeros(n, dtype=bool)
        if loss != "linear":
            with np.errstate(invalid="ignore"):
                gated = gated | ~(np.max(np.abs(d), axis=1) <= gate_sigma * sigma_hat)
        cols["gated"].append(gated)
        cols["stamp_ns"].append(np.full(n, data.frames[f.index].stamp_ns, dtype=np.int64))
    return {k: np.concatenate(v) if v else np.zeros(0) for k, v in cols.items()}


def reprojection_rms(result: AcfResult, frames: Any = None, data: AcfData | None = None,
                     per_axis: bool = False) -> Any:
    """RMS of ``|Δuv|`` (px) of ``frames`` predicted with the calibrated model.

    The attitude of every frame comes from the estimated reference attitude and the gyro
    chain, as in the fit (Liu et al. §3.1: calibrate on odd frames, check on even ones).
    ``data`` may hold other measurements of the same run (e.g. noise-free centroids).
    ``per_axis`` returns ``(rms_u, rms_v)`` instead.
    """
    data = result.data if data is None else data
    idx = select_frames(len(data.frames), frames)
    fr = _prepare_frames(data, idx, result.chain, result.model.prior.time_offset, None, 1)
    if not fr:
        raise StellarCalError("no frames with stars to evaluate")
    model = result.model
    p = _Problem(model, result.chain, fr, result.R_i_b0, result.reference_time,
                 model.initial_value, model.initial_sigma)
    x = np.concatenate([np.zeros(3), result.theta])
    d = np.vstack([f.uv - p.predict(x, f, jac=False)[0] for f in fr])
    if per_axis:
        return float(np.sqrt(np.mean(d[:, 0] ** 2))), float(np.sqrt(np.mean(d[:, 1] ** 2)))
    return float(np.sqrt(np.mean(np.sum(d ** 2, axis=1))))


def parse_effects(text: str | Sequence[str] | None,
                  baseline: Sequence[str] = ACF_EFFECTS) -> list[str]:
    """``--effects`` value → effect ids: entries are added to ``baseline``; ``-id`` removes."""
    items = [s.strip() for s in (text.split(",") if isinstance(text, str) else (text or []))]
    out = list(baseline)
    for it in items:
        if not it:
            continue
        if it.startswith("-"):
            out = [e for e in out if e != it[1:]]
        elif it not in out:
            out.append(it)
    return out


def summary_lines(res: AcfResult) -> list[str]:
    """What ``stellar-cal batch --method acf`` prints about a fit."""
    gated = int(np.sum(res.residuals["gated"]))
    q = res.quality
    out = [f"acf: {len(res.frames)} frames, {len(res.residuals['du']) - gated} stars "
           f"({gated} gated: {q.stars_misidentified} misidentified, {q.stars_outliers} "
           f"outliers), RMS |Δuv| {res.rms_px:.4f} px, σ̂ {res.sigma_px:.4f} px, "
           f"{res.iterations} evaluations, loss {res.loss}"]
    if q.counts():
        out.append(f"data: {q.summary()}")
    out += [f"result degraded: {reason}" for reason in res.degraded]
    for name, value, sigma in zip(res.parameter_names[3:], res.theta, res.sigma[3:],
                                  strict=True):
        unit = ""
        if name.startswith("installation."):
            value, sigma, unit = value / ARCSEC, sigma / ARCSEC, " arcsec (vs prior)"
        out.append(f"  {name:28s} {value:+.8g} ± {sigma:.3g}{unit}")
    eq = res.derived
    if eq:
        out.append("equivalent principal point: ({:.3f}, {:.3f}) +- ({:.3f}, {:.3f}) px".format(
            *eq["equivalent_principal_point_px"], *eq["equivalent_principal_point_sigma_px"]))
    out.append(res.observability.summary())
    return out


def batch(bag: str | os.PathLike[str], prior: Calibration, effects: Sequence[str],
          options: dict[str, Any], progress: Callable[[str], None] | None) -> BatchOutput:
    """``stellar-cal batch --method acf``: :func:`run_acf` with the command's options."""
    res = run_acf(bag, prior, parse_effects(effects), loss=options.get("loss", "linear"),
                  on_error=options.get("on_error", "raise"),
                  outlier_probability=options.get("outlier_probability", OUTLIER_PROBABILITY),
                  progress=progress)
    return BatchOutput(res.calibration, (res.parameter_names[3:], res.covariance[3:, 3:]),
                       res.residuals, summary_lines(res), res)


METHOD = MethodSpec(
    name="acf", kind="batch",
    summary="attitude-correlated frames, Liu et al. 2017: the gyros tie every frame to the "
            "first (a turntable or slew sequence)",
    baseline=ACF_EFFECTS,
    stages=STAGES_WITHOUT_ACCEL,
    batch=batch, steps=ACF_STAGES)
