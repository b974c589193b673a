"""Leave-one-frame-out cross-validation of the bundle (the result's ``cross_validation``).

Each frame is held out in turn: the camera is fitted on the other frames (warm-started
from the full solution, the same loss and the same inliers), then only the held-out
frame's attitude is fitted to its identified stars under that camera
(:func:`held_out_frame`), and the frame scores

    RMS = sqrt(mean((Δu/f_x)² + (Δv/f_y)²))    (arcsec: the plate scale at the principal point)

over its identified stars except those beyond 5 × the frame's median residual ``|Δuv|``
(counted in ``rejected``).  The attitude fit uses the same stars: it is repeated until the
rejected set is stable, so a wrong identity neither pulls the attitude nor enters the RMS.
:func:`held_out_frame` takes any projection ``R ↦ uv``, so another solver's camera is
scored by exactly the same rule (``benchmarks/realsky_bundle.py``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from stellar_cal_ros.core.rotation import so3_exp
from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.methods.bundle import Bundle, BundleFrame, BundleResult, _constant

#: a held-out star beyond this many times the frame's median residual is not scored
REJECT_FACTOR = 5.0
#: a frame whose held-out NIS/dof is this many times the other frames' median does not
#: share their camera (another focus or zoom, a different camera, wrong identifications)
INCONSISTENT_FACTOR = 4.0


@dataclass
class FrameScore:
    """The held-out score of one frame."""

    rms_arcsec: float
    rejected: int
    scored: np.ndarray  #: (n,) bool: the stars in the RMS
    residuals: np.ndarray  #: (n, 2) px, measured − predicted
    attitude: np.ndarray  #: the fitted attitude (what ``predict`` takes)
    iterations: int


def fit_attitude(predict: Callable[[np.ndarray], np.ndarray], R0: np.ndarray, uv: np.ndarray,
                 mask: np.ndarray, max_iterations: int = 20, h: float = 1e-6
                 ) -> tuple[np.ndarray, int]:
    """Gauss–Newton on a left rotation ``R ← Exp(φ) R`` of the stars in ``mask``.

    ``predict(R)`` returns the predicted centroids (n, 2); its Jacobian in φ is taken by
    central differences (step ``h`` rad), so any camera model can be scored.
    """
    R = np.asarray(R0, dtype=float)
    it = 0
    for it in range(1, max_iterations + 1):  # noqa: B007 (returned)
        r = (uv - predict(R))[mask].reshape(-1)
        J = np.empty((len(r), 3))
        for a in range(3):
            e = np.zeros(3)
            e[a] = h
            J[:, a] = ((predict(so3_exp(e) @ R) - predict(so3_exp(-e) @ R))[mask]
                       .reshape(-1) / (2 * h))
        ok = np.isfinite(r) & np.all(np.isfinite(J), axis=1)
        step = np.linalg.lstsq(J[ok], r[ok], rcond=None)[0]
        R = so3_exp(step) @ R
        if np.max(np.abs(step)) < 1e-11:
            break
    return R, it


def held_out_frame(predict: Callable[[np.ndarray], np.ndarray], R0: np.ndarray,
                   uv: np.ndarray, plate_scale: tuple[float, float],
                   max_rounds: int = 10) -> FrameScore:
    """Fit only the attitude of one frame and score it (see the module docstring).

    ``plate_scale``: rad per px in u and v at the principal point (``1/f_x``, ``1/f_y``).
    """
    uv = np.asarray(uv, dtype=float)
    finite = np.all(np.isfinite(uv), axis=1)
    scored = finite.copy()
    R, total = np.asarray(R0, dtype=float), 0
    d = np.full(len(uv), np.inf)
    for _ in range(max_rounds):
        if scored.sum() < 2:
            break
        R, it = fit_attitude(predict, R, uv, scored)
        total += it
        res = uv - predict(R)
        d = np.where(finite, np.linalg.norm(res, axis=1), np.inf)
        ok = np.isfinite(d)
        new = ok & (d <= REJECT_FACTOR * float(np.median(d[ok]))) if ok.any() else ok
        if np.array_equal(new, scored):
            break
        scored = new
    res = uv - predict(R)
    a = res[scored] * np.asarray(plate_scale)[None, :]
    rms = float(np.sqrt(np.mean(np.sum(a ** 2, axis=1)))) / ARCSEC if scored.any() else \
        float("nan")
    return FrameScore(rms, int(len(uv) - scored.sum()), scored, res, R, total)


@dataclass
class HeldOut:
    """Every frame's held-out score and what the diagnosis needs of it."""

    frames: list[int]  #: bag index of each held-out frame
    scores: list[FrameScore]
    #: per frame: the fold's variance factor s² (its σ̂ = s · stated σ)
    variance_factor: list[float]
    #: per frame: the stated σ (n,) of the held-out stars
    sigma: list[np.ndarray]
    theta: list[np.ndarray] = field(default_factory=list)  #: the fold's camera θ
    #: per frame: predicted covariance (n, 2, 2) of each held-out residual, px²
    covariance: list[np.ndarray] = field(default_factory=list)
    #: per frame: the predicted centroids (n, 2) and tracker-frame directions (n, 3)
    uv_pred: list[np.ndarray] = field(default_factory=list)
    directions: list[np.ndarray] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        """The result's ``cross_validation`` block (contract §5).

        Plus, per frame, ``frames`` (bag index), ``stars`` scored and ``nis_per_dof``.
        """
        rms = [float(s.rms_arcsec) for s in self.scores]
        finite = [r for r in rms if np.isfinite(r)]
        return {"held_out_rms_arcsec": rms,
                "mean_arcsec": float(np.mean(finite)) if finite else float("nan"),
                "rejected": [int(s.rejected) for s in self.scores],
                "frames": list(self.frames),
                "stars": [int(s.scored.sum()) for s in self.scores],
                "nis_per_dof": [float(x) for x in self.nis_per_dof()]}

    def nis_per_dof(self) -> np.ndarray:
        """Per frame: the scored stars' mean held-out NIS / 2 (1: as predicted).

        Each star's NIS is against its own predicted covariance, which already carries what
        the frame's attitude fit absorbs (:func:`residual_covariance`): 2 on average.
        """
        out = []
        for sc, S in zip(self.scores, self.covariance, strict=True):
            m = sc.scored
            if not m.any():
                out.append(float("nan"))
                continue
            r = sc.residuals[m]
            nis = np.einsum("ni,nij,nj->n", r, np.linalg.inv(S[m]), r)
            out.append(float(nis.mean() / 2.0))
        return np.asarray(out)

    def inconsistent(self, factor: float = INCONSISTENT_FACTOR) -> list[int]:
        """Positions of frames that do not share the others' camera.

        Their held-out NIS/dof exceeds ``factor`` × the other frames' median (and ``factor``).
        """
        nis = self.nis_per_dof()
        out = []
        for k, v in enumerate(nis):
            others = np.delete(nis, k)
            others = others[np.isfinite(others)]
            if len(others) and v > factor * max(float(np.median(others)), 1.0):
                out.append(k)
        return out


def residual_covariance(b: Bundle, theta: np.ndarray, R: np.ndarray, f: BundleFrame,
                        scored: np.ndarray, P_theta: np.ndarray, s2: float) -> np.ndarray:
    """Predicted covariance (n, 2, 2) px² of the held-out residuals of frame ``f``.

    The residual of a held-out star is ``Π (ε − B δθ)``: its noise and the fold camera's
    error ``δθ`` (covariance ``P_theta``), less what the frame's own attitude fit (on the
    ``scored`` stars) absorbs (``Π``, whitened).  Stars not scored keep their noise alone.
    """
    _, A, B = b.residuals(theta, R, f)
    var = (f.sigma * b.sigma_scale) ** 2 * (s2 if np.isfinite(s2) else 1.0)
    out = var[:, None, None] * np.eye(2)[None]
    m = scored & np.all(np.isfinite(A), axis=(1, 2)) & np.all(np.isfinite(B), axis=(1, 2))
    if m.sum() < 2:
        return out
    scale = np.sqrt(var[m] / (f.sigma[m] * b.sigma_scale) ** 2)[:, None, None]
    A2 = (A[m] / scale).reshape(-1, 3)  # whitened by the fold's σ̂
    B2 = (B[m] / scale).reshape(-1, B.shape[2])
    C = np.eye(len(A2)) + B2 @ P_theta @ B2.T
    Pi = np.eye(len(A2)) - A2 @ np.linalg.pinv(A2.T @ A2) @ A2.T
    C = Pi @ C @ Pi
    idx = np.flatnonzero(m)
    for k, j in enumerate(idx):
        out[j] = var[j] * C[2 * k:2 * k + 2, 2 * k:2 * k + 2]
    return out


def cross_validate(result: BundleResult) -> HeldOut:
    """Hold out each fitted frame of ``result`` in turn (module docstring).

    Each fold's camera is one Gauss–Newton step from the full solution on the normal
    equations without the frame (:meth:`~stellar_cal_ros.methods.bundle.Bundle.
    without_frame`): the fold's own solution to second order, at the cost of one
    evaluation of the model for all folds.
    """
    model = result.model
    frames, Rs = result.frames, result.attitudes
    out = HeldOut([], [], [], [])
    full = Bundle(model, frames, result.theta_prior, result.sigma_prior, result.loss)
    ne_full = full.normal(result.theta, Rs)
    schur_full = Bundle.schur(ne_full, 0.0)
    for k, f in enumerate(frames):
        dtheta, P_theta, s2 = full.without_frame(ne_full, schur_full, k)
        theta = result.theta + dtheta
        cam = model.camera_at(theta, f.ctx)

        def predict(R: np.ndarray, theta=theta, f=f) -> np.ndarray:
            with np.errstate(all="ignore"):
                return model.predict(theta, f.u_i, f.ctx, _constant(R), jacobians=False).uv

        score = held_out_frame(predict, Rs[k], f.uv, (1.0 / cam.fx, 1.0 / cam.fy))
        out.frames.append(f.index)
        out.scores.append(score)
        out.variance_factor.append(float(s2))
        out.sigma.append(f.sigma)
        out.theta.append(theta)
        out.covariance.append(residual_covariance(full, theta, score.attitude, f,
                                                  score.scored, P_theta, s2))
        with np.errstate(all="ignore"):
            pred = model.predict(theta, f.u_i, f.ctx, _constant(score.attitude),
                                 jacobians=False)
        out.uv_pred.append(pred.uv)
        out.directions.append(pred.directions_st)
    return out
