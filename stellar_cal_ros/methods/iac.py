"""Interstar-angle calibration (IAC): the attitude-free baseline Liu et al. compare with.

The angle between two stars is invariant under rotation, so the camera intrinsics can be
fitted without any attitude or IMU: for every pair (i, j) of identified stars in a frame,

    r_ij = ∠(unproject(uv_i; θ), unproject(uv_j; θ)) − ∠(u_i, u_j)

with ``u`` the catalogue directions, minimised over θ (principal point, focal length, k1 k2,
(k3), p1 p2) by ``scipy.optimize.least_squares`` with an analytic Jacobian (implicit
differentiation of the undistortion: ``∂xy/∂p = −(∂uv/∂xy)⁻¹ ∂uv/∂p``) plus the prior
residuals ``(θ − θ_prior)/σ_prior``.  The principal point enters the angles only through
the perspective (second-order) terms, hence it is poorly determined — the weakness Liu et
al. (Fig. 5) show.  Pair residuals of one frame are correlated (each star is in n−1 pairs);
the fit treats them as independent with ``σ_angle = √2 σ_px / f`` (the usual IAC practice),
so the returned σ are indicative only.  The installation (and all else) stays at the prior.
"""

from __future__ import annotations

import copy
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import least_squares

from stellar_cal_ros.effects.base import FrameContext, Stage
from stellar_cal_ros.effects.registry import create_many
from stellar_cal_ros.errors import StellarCalError
from stellar_cal_ros.io.bag import BagReader, StarFrame
from stellar_cal_ros.io.calibration import Calibration
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
    from stellar_cal_ros.methods.acf import _select_frames, _unit_vectors

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
    ctx = FrameContext(stamp=0.0)
    # pairs
    pi, pj, ang_cat, uv_all, sig_all = [], [], [], [], []
    base = 0
    for k in _select_frames(len(all_frames), frames):
        fr = all_frames[int(k)]
        ok = (fr.catalog_id != 0) & np.isfinite(fr.right_ascension) & \
            np.all(np.isfinite(fr.uv), axis=1)
        n = int(ok.sum())
        if n < 2:
            continue
        u = _unit_vectors(fr.right_ascension[ok], fr.declination[ok])
        i, j = np.triu_indices(n, 1)
        pi.append(base + i)
        pj.append(base + j)
        ang_cat.append(_pair_angles(u[i], u[j]))
        uv_all.append(np.asarray(fr.uv, dtype=float)[ok])
        s = np.asarray(fr.sigma, dtype=float)[ok]
        s = np.full(n, sigma_px) if sigma_px is not None else np.where(s > 0, s, 1.0)
        sig_all.append(s)
        base += n
    if not pi or sum(len(p) for p in pi) < model.size:
        raise StellarCalError("too few star pairs for the interstar-angle calibration")
    Ia, Ib = np.concatenate(pi), np.concatenate(pj)
    A_cat = np.concatenate(ang_cat)
    uv = np.vstack(uv_all)
    sig = np.concatenate(sig_all)
    th0, sp = model.initial_value.copy(), model.initial_sigma.copy()
    f0 = prior.camera.fx
    w_pair = f0 / np.sqrt(sig[Ia] ** 2 + sig[Ib] ** 2)  # 1/σ_angle

    cache: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    def evaluate(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = theta.tobytes()
        if key in cache:
            return cache[key]
        cam = model.camera_at(theta, ctx)
        xy = cam.pixel_to_normalized(uv)
        _, J_xy, J_p = cam.normalized_to_pixel(np.nan_to_num(xy), jacobians=True)
        dxy_dp = -np.linalg.solve(J_xy, J_p)  # (n, 2, 18)
        dxy = dxy_dp @ _camera_jacobian(model, theta, ctx)  # (n, 2, P)
        a = np.column_stack([xy, np.ones(len(xy))])
        va, vb = a[Ia], a[Ib]
        cr = np.cross(va, vb)
        ncr = np.linalg.norm(cr, axis=1)
        dot = np.einsum("ij,ij->i", va, vb)
        ang = np.arctan2(ncr, dot)
        ga = (dot / np.einsum("ij,ij->i", va, va))[:, None] * va - vb
        gb = (dot / np.einsum("ij,ij->i", vb, vb))[:, None] * vb - va
        ga /= ncr[:, None]
        gb /= ncr[:, None]
        Jang = np.einsum("ni,nip->np", ga[:, :2], dxy[Ia]) + \
            np.einsum("ni,nip->np", gb[:, :2], dxy[Ib])
        r = np.concatenate([(ang - A_cat) * w_pair, (theta - th0) / sp])
        J = np.vstack([Jang * w_pair[:, None], np.diag(1.0 / sp)])
        bad = ~np.isfinite(r)
        if bad.any():
            r[bad] = 1e6
            J[bad] = 0.0
        cache.clear()
        cache[key] = (r, J)
        return r, J

    if loss not in ("linear", "huber", "soft_l1", "cauchy"):
        raise StellarCalError(f"loss must be linear, huber, soft_l1 or cauchy, got {loss!r}")
    res = least_squares(lambda t: evaluate(t)[0], th0, jac=lambda t: evaluate(t)[1],
                        loss=loss, f_scale=3.0, x_scale="jac", max_nfev=max_nfev,
                        xtol=1e-12, ftol=1e-12, gtol=1e-10)
    r, J = evaluate(res.x)
    npair = len(Ia)
    s2 = float(np.sum(r[:npair] ** 2) / max(npair - model.size, 1))
    info = J[:npair].T @ J[:npair] / s2 + J[npair:].T @ J[npair:]
    d = 1.0 / np.sqrt(np.diag(info))
    cov = np.linalg.pinv(info * np.outer(d, d), hermitian=True) * np.outer(d, d)
    cal = copy.deepcopy(prior)
    cal.sigma = copy.deepcopy(prior.sigma or {})
    cal.method = "iac"
    sig_th = np.sqrt(np.diag(cov))
    for e in model.effects:
        sl = model.slices[e.id]
        e.store(res.x[sl], sig_th[sl], cal)
    rms = float(np.sqrt(np.mean((r[:npair] / w_pair) ** 2)) * 180 / np.pi * 3600)
    return IacResult(cal, res.x, cov, model.parameter_names(), rms, npair, float(res.cost),
                     int(res.nfev))
