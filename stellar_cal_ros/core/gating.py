"""One gate policy for star measurements: per-star χ², scaled by the frame, FOV, lost lock.

A misidentified star stands out from the other stars of its frame, while a model that
misses an effect raises every star's normalized innovation squared (NIS).  Gating each star
against the absolute χ² threshold would then reject whole frames and leave nothing to
diagnose; scaling the threshold by the frame's median NIS over the χ² median keeps rejecting
outliers and keeps the honest innovations.  A frame whose typical star is a hundred sigma off
is not a missing effect but a lost attitude (e.g. after an IMU gap in a slew): it is rejected
whole, and a few such frames in a row make the filter re-acquire.  A star whose catalogue
direction falls outside the field of view is misidentified whatever its NIS (far outside the
detector the distortion polynomial folds back and its huge Jacobian would let it pass).

numpy and math only (no scipy: the χ² quantile of 2 degrees of freedom has a closed form).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: median of χ² with 2 degrees of freedom
CHI2_2_MEDIAN = 2.0 * math.log(2.0)


def chi2_2_quantile(probability: float) -> float:
    """Quantile of χ² with 2 dof: ``−2 ln(1 − p)`` (exact; p = 1 gives ∞)."""
    if probability >= 1.0:
        return math.inf
    return -2.0 * math.log1p(-probability)


def block_nis(nu: np.ndarray, S_blocks: np.ndarray) -> np.ndarray:
    """Per-measurement normalized innovation squared for 2×2 blocks.

    ``nu`` (n, 2), ``S_blocks`` (n, 2, 2) → (n,) values ``νᵀ S⁻¹ ν`` (χ² with 2 dof).
    """
    a, b, d = S_blocks[:, 0, 0], S_blocks[:, 0, 1], S_blocks[:, 1, 1]
    det = a * d - b * b
    x, y = nu[:, 0], nu[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        return (d * x * x - 2 * b * x * y + a * y * y) / det


@dataclass
class GateDecision:
    """The gate's verdict on one frame."""

    accepted: np.ndarray  #: (n,) bool
    scale: float  #: frame median NIS / χ² median, at least 1
    mismatch: bool  #: the frame's stars are more off than the model expects (scale large)
    lost_lock: bool  #: so far off that the attitude is lost: nothing accepted
    outside_fov: int  #: stars whose predicted direction is outside the field of view


@dataclass
class GatePolicy:
    """Per-star χ² gate scaled by the frame's median NIS, field of view and lost lock.

    Parameters
    ----------
    probability : float
        Per-star acceptance probability of a consistent star (2 dof).
    mismatch_factor, lost_lock_factor : float
        Frame median NIS this many times the χ² median: a model mismatch (counted), resp.
        a lost attitude (frame rejected).
    fov_tan2 : float
        Squared tangent of the largest accepted off-axis angle (∞: no FOV test).
    scale_by_frame : bool
        False: the plain χ² gate (no scaling; used to compute Cramér–Rao bounds).
    """

    probability: float = 0.9999
    mismatch_factor: float = 3.0
    lost_lock_factor: float = 1e4
    fov_tan2: float = math.inf
    scale_by_frame: bool = True

    def __post_init__(self) -> None:
        self.threshold = chi2_2_quantile(self.probability)

    def frame_scales(self, nis_stars: np.ndarray, frames: np.ndarray) -> np.ndarray:
        """Each row's frame's threshold scale, as :meth:`decide` sets it, for many frames.

        ``nis_stars`` (n,) the rows' NIS (NaN: not counted), ``frames`` (n,) their frame
        ids: ``max(1, median / χ² median)`` of each frame's finite NIS where it has at least
        3 (else, and without ``scale_by_frame``, 1), per row.  (A residual table read
        again at another σ: which rows the gate would take there, ``noise_stars.readmitted``.)
        """
        nis = np.asarray(nis_stars, dtype=float)
        out = np.ones(len(nis))
        if not self.scale_by_frame or not len(nis):
            return out
        frames = np.asarray(frames)
        fin = np.isfinite(nis)
        order = np.lexsort((np.where(fin, nis, np.inf), frames))
        f_sorted = frames[order]
        starts = np.flatnonzero(np.r_[True, f_sorted[1:] != f_sorted[:-1]])
        k = np.add.reduceat(fin[order].astype(np.int64), starts)  # finite rows a frame
        v = nis[order]
        half = k // 2
        hi = v[starts + np.minimum(half, np.maximum(k - 1, 0))]
        lo = v[starts + np.maximum(half - 1, 0)]
        with np.errstate(invalid="ignore"):
            med = np.where(k % 2 == 1, hi, (lo + hi) / 2.0)
            scale = np.where(k >= 3, np.maximum(1.0, med / CHI2_2_MEDIAN), 1.0)
        per_row = np.repeat(scale, np.diff(np.r_[starts, len(v)]))
        out[order] = per_row
        return out

    def decide(self, nis_stars: np.ndarray, directions_st: np.ndarray) -> GateDecision:
        """Accept or reject each star of a frame.

        ``nis_stars`` (n,) per-star NIS (NaN for a star behind the tracker);
        ``directions_st`` (n, 3) predicted unit directions in the tracker frame.
        """
        finite = [v for v in nis_stars.tolist() if math.isfinite(v)]
        scale = 1.0
        if self.scale_by_frame and len(finite) >= 3:
            scale = max(1.0, _median(finite) / CHI2_2_MEDIAN)
        with np.errstate(invalid="ignore"):
            accepted = nis_stars <= self.threshold * scale  # NaN is rejected
        lost = scale > self.lost_lock_factor
        if lost:
            accepted[:] = False
        outside = 0
        if math.isfinite(self.fov_tan2):
            d = directions_st
            front = d[:, 2] > 0
            if front.all():
                in_fov = (d[:, 0] ** 2 + d[:, 1] ** 2) / d[:, 2] ** 2 <= self.fov_tan2
            else:
                with np.errstate(divide="ignore", invalid="ignore"):
                    r2 = (d[:, 0] ** 2 + d[:, 1] ** 2) / d[:, 2] ** 2
                in_fov = front & (r2 <= self.fov_tan2)
            if not in_fov.all():
                outside = int((~in_fov).sum())
                accepted &= in_fov
        return GateDecision(accepted, scale, scale > self.mismatch_factor, lost, outside)


def fov_tan2(camera, margin: float) -> float:
    """Squared tangent of ``margin`` × the detector's half-diagonal angle (pinhole)."""
    half_diag = math.hypot(max(camera.cx, camera.width - camera.cx),
                           max(camera.cy, camera.height - camera.cy))
    return (margin * half_diag / min(camera.fx, camera.fy)) ** 2


def _median(values: list[float]) -> float:
    """``np.median`` of a short list of finite floats (the same value, less overhead)."""
    s = sorted(values)
    k = len(s) // 2
    return s[k] if len(s) % 2 else (s[k - 1] + s[k]) / 2.0
