"""Star centroids from an image, each with a σ from its signal-to-noise.

Detection is tetra3rs's (``extract_centroids``: local background, matched filter,
connected components, hot-pixel and elongation rejection).  Its positions are moment /
quadratic-peak centroids without an uncertainty, biased on saturated stars; so every
detection is refined here by a **pixel-integrated Gaussian PSF fit** (position, flux, width,
local background; Gauss-Newton over a window of ±3 PSF σ, all stars at once):

* saturated pixels (at the image's saturation level) get no weight: a saturated star is
  centred on its unsaturated wings, not on its flat top;
* each pixel's variance is the background's ``σ_bg²`` plus ``κ`` × the star's signal there
  (shot noise); both are estimated from the frame (``κ`` = 1 / gain, ADU per electron, may
  be given) from the first, unweighted fit's residuals: ``σ_bg²`` from the pixels where the
  stars' signal is negligible (median), ``κ`` from each unsaturated star's remaining
  residual power per unit signal (median over the stars);
* the centroid's covariance is the weighted fit's ``(JᵀWJ)⁻¹``, scaled by the frame's
  a-posteriori variance factor (χ²/dof over all stars: a PSF that is not Gaussian, JPEG
  artefacts: the median of the stars' χ²/dof, at least 1, or a star's own when larger), and
  σ = √((σ_u² + σ_v²)/2) goes into the message (contract ``sigma``).

``test/test_images.py`` checks bias and σ against rendered images with known truth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from stellar_cal_ros.core.types import StarFrame
from stellar_cal_ros.sky import database

__all__ = ["Centroids", "ExtractConfig", "centroid_frame", "extract_stars"]

_SQRT2PI = math.sqrt(2.0 * math.pi)


@dataclass
class ExtractConfig:
    """Settings of :func:`extract_stars`."""

    sigma_threshold: float = 5.0  #: detection threshold, background σ (tetra3rs)
    max_stars: int = 200  #: brightest detections kept (contract: 0-200 stars a frame)
    saturation_level: float | None = None  #: None: a full-range maximum reached by 2+ pixels
    gain_adu_per_e: float | None = None  #: κ; None: estimated from the frame
    window_sigmas: float = 3.0  #: fit window half-width in PSF σ (at least 3 px)
    iterations: int = 12  #: Gauss-Newton iterations
    min_separation_sigmas: float = 4.0  #: detections closer than this (PSF σ): both dropped
    edge_margin_px: float = 1.0  #: centroids closer to the edge are dropped


@dataclass
class Centroids:
    """Stars of one image, brightest first (n of them)."""

    uv: np.ndarray  #: (n, 2) px, (0, 0) the centre of the top-left pixel
    sigma: np.ndarray  #: (n,) px, 1-σ per axis (contract ``sigma``)
    covariance: np.ndarray  #: (n, 2, 2) px²
    flux: np.ndarray  #: (n,) ADU above background
    snr: np.ndarray  #: (n,) flux / its σ
    saturated: np.ndarray  #: (n,) bool: pixels at the saturation level were left out
    psf_sigma: np.ndarray  #: (n,) fitted PSF σ, px
    background_sigma: float  #: the frame's background noise, ADU
    variance_factor: float  #: a-posteriori variance factor applied to the covariances
    detections: int  #: tetra3rs detections before the fit's checks
    width: int = 0
    height: int = 0

    def __len__(self) -> int:
        return int(self.uv.shape[0])


def _saturation(img: np.ndarray, level: float | None) -> float:
    """The saturation level (inf: none).

    The configured one; else the image's maximum when it is a full ADC range (2^k − 1,
    k = 8..16) reached by at least two pixels, or when at least five pixels share it in the
    upper half of the integer type's range (a 12-bit sensor scaled to 16 bits saturates at
    65520, not 65535).
    """
    if level is not None:
        return float(level)
    top = float(img.max())
    count = int(np.count_nonzero(img >= top))
    full = {float(2 ** k - 1) for k in range(8, 17)}
    if top in full and count >= 2:
        return top
    if img.dtype.kind in "ui" and count >= 5 and top >= 0.5 * np.iinfo(img.dtype).max:
        return top
    return math.inf


def extract_stars(image: np.ndarray, config: ExtractConfig | None = None) -> Centroids:
    """Detect and centroid the stars of a grey image (2-D array of any real dtype)."""
    c = config or ExtractConfig()
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"a grey image is 2-D, got shape {img.shape}")
    h, w = img.shape
    data = img.astype(np.float32)
    sat = _saturation(img, c.saturation_level)
    t3 = database.tetra3rs()
    ex = t3.extract_centroids(data, sigma_threshold=c.sigma_threshold,
                              max_centroids=4 * c.max_stars,
                              saturation_level=None if math.isinf(sat) else sat, threads=1)
    det = ex.centroids
    n0 = len(det)
    bg_sigma = max(float(ex.background_sigma), 1e-3)
    empty = Centroids(np.zeros((0, 2)), np.zeros(0), np.zeros((0, 2, 2)), np.zeros(0),
                      np.zeros(0), np.zeros(0, bool), np.zeros(0), bg_sigma, 1.0, n0, w, h)
    if not n0:
        return empty
    xy = np.array([[d.x + (w - 1) / 2.0, d.y + (h - 1) / 2.0] for d in det])
    covs = [d.cov for d in det]
    sizes = np.array([math.sqrt(max(0.5 * (cv[0, 0] + cv[1, 1]), 0.25)) if cv is not None
                      else 1.0 for cv in covs])
    s0 = float(np.clip(np.median(sizes), 0.5, 8.0))
    half = max(3, int(math.ceil(c.window_sigmas * s0)))
    # crowded detections (another within min_separation) and edge windows are dropped
    keep = (xy[:, 0] >= half) & (xy[:, 0] <= w - 1 - half) & (xy[:, 1] >= half) & \
        (xy[:, 1] <= h - 1 - half)
    if len(xy) > 1:
        from scipy.spatial import cKDTree

        pairs = cKDTree(xy).query_pairs(c.min_separation_sigmas * s0, output_type="ndarray")
        keep[pairs.ravel()] = False
    xy = xy[keep][:c.max_stars]
    if not len(xy):
        return empty
    fit = _fit(data, xy, s0, half, bg_sigma, sat, c)
    ok = fit["ok"] & (fit["uv"][:, 0] >= c.edge_margin_px - 0.5) & \
        (fit["uv"][:, 0] <= w - 0.5 - c.edge_margin_px) & \
        (fit["uv"][:, 1] >= c.edge_margin_px - 0.5) & \
        (fit["uv"][:, 1] <= h - 0.5 - c.edge_margin_px)
    order = np.flatnonzero(ok)[np.argsort(-fit["flux"][ok], kind="stable")]
    cov = fit["cov"][order]
    return Centroids(fit["uv"][order], np.sqrt(0.5 * (cov[:, 0, 0] + cov[:, 1, 1])), cov,
                     fit["flux"][order], fit["snr"][order], fit["saturated"][order],
                     fit["psf"][order], bg_sigma, fit["factor"], n0, w, h)


def centroid_frame(pixels: np.ndarray, stamp_ns: int, frame_id: str,
                   exposure_time: float = 0.0, config: ExtractConfig | None = None
                   ) -> StarFrame:
    """An image's stars as a message of unidentified centroids (contract §2).

    The one step from an image to a star frame: the ``star_extractor`` node and the bag
    data path (:mod:`stellar_cal_ros.methods.frames`) both call it, then identify the frame
    (:meth:`stellar_cal_ros.sky.identify.Identifier.identify_frame`).  Stars brightest
    first, ``catalog_id`` 0, RA/Dec and magnitude NaN, ``sigma`` from the PSF fit.
    """
    c = extract_stars(pixels, config)
    n = len(c)
    return StarFrame(stamp_ns=int(stamp_ns), frame_id=frame_id,
                     exposure_time=float(exposure_time), catalog_id=np.zeros(n, np.uint32),
                     right_ascension=np.full(n, np.nan), declination=np.full(n, np.nan),
                     uv=c.uv, magnitude=np.full(n, np.nan), sigma=c.sigma)


def _model(p: np.ndarray, gx: np.ndarray, gy: np.ndarray, jac: bool):
    """Integrated Gaussian on windows: model (n, k, k) and its Jacobian (n, k, k, 5).

    ``p`` (n, 5) = u0, v0, flux, σ, background; ``gx`` (n, k), ``gy`` (n, k) pixel indices.
    """
    u0, v0, f, s, b = p.T
    s_ = s[:, None]
    ax_hi = (gx + 0.5 - u0[:, None]) / s_
    ax_lo = (gx - 0.5 - u0[:, None]) / s_
    ay_hi = (gy + 0.5 - v0[:, None]) / s_
    ay_lo = (gy - 0.5 - v0[:, None]) / s_
    ex = ndtr(ax_hi) - ndtr(ax_lo)
    ey = ndtr(ay_hi) - ndtr(ay_lo)
    m = b[:, None, None] + f[:, None, None] * ey[:, :, None] * ex[:, None, :]
    if not jac:
        return m, None

    def pdf(a):
        return np.exp(-0.5 * a * a) / _SQRT2PI

    dex_du = -(pdf(ax_hi) - pdf(ax_lo)) / s_
    dey_dv = -(pdf(ay_hi) - pdf(ay_lo)) / s_
    dex_ds = -(ax_hi * pdf(ax_hi) - ax_lo * pdf(ax_lo)) / s_
    dey_ds = -(ay_hi * pdf(ay_hi) - ay_lo * pdf(ay_lo)) / s_
    F = f[:, None, None]
    J = np.empty(m.shape + (5,))
    J[..., 0] = F * ey[:, :, None] * dex_du[:, None, :]
    J[..., 1] = F * dey_dv[:, :, None] * ex[:, None, :]
    J[..., 2] = ey[:, :, None] * ex[:, None, :]
    J[..., 3] = F * (dey_ds[:, :, None] * ex[:, None, :] + ey[:, :, None] * dex_ds[:, None, :])
    J[..., 4] = 1.0
    return m, J


def _gauss_newton(p, pix, wgt, gx, gy, iterations, s_max):
    for _ in range(iterations):
        m, J = _model(p, gx, gy, True)
        r = (pix - m) * wgt
        Jw = J * wgt[..., None]
        n = len(p)
        A = np.einsum("nija,nijb->nab", Jw, Jw) + 1e-9 * np.eye(5)
        g = np.einsum("nija,nij->na", Jw, r)
        try:
            step = np.linalg.solve(A, g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            step = np.zeros((n, 5))
        step = np.where(np.isfinite(step), step, 0.0)
        step[:, :2] = np.clip(step[:, :2], -1.0, 1.0)
        p = p + step
        p[:, 2] = np.maximum(p[:, 2], 1e-6)
        p[:, 3] = np.clip(p[:, 3], 0.3, s_max)
        if np.max(np.abs(step[:, :2])) < 1e-5:
            break
    return p


def _fit(img, xy, s0, half, bg_sigma, sat, c: ExtractConfig) -> dict:
    n = len(xy)
    cu = np.rint(xy[:, 0]).astype(int)
    cv = np.rint(xy[:, 1]).astype(int)
    gx = cu[:, None] + np.arange(-half, half + 1)[None, :]
    gy = cv[:, None] + np.arange(-half, half + 1)[None, :]
    pix = img[gy[:, :, None], gx[:, None, :]].astype(float)  # (n, k, k)
    good = pix < sat
    border = np.concatenate([pix[:, 0, :], pix[:, -1, :], pix[:, :, 0], pix[:, :, -1]], axis=1)
    b0 = np.median(border, axis=1)
    f0 = np.clip((pix - b0[:, None, None]).sum(axis=(1, 2)), 1.0, None)
    p = np.c_[xy, f0, np.full(n, s0), b0]
    var_bg = bg_sigma ** 2 + 1.0 / 12.0  # quantization of one LSB
    s_max = max(3.0 * s0, 2.0)
    # pass 1: background weights only; the residuals give the shot-noise slope κ
    w1 = good / math.sqrt(var_bg)
    p = _gauss_newton(p, pix, w1, gx, gy, c.iterations, s_max)
    m, _ = _model(p, gx, gy, False)
    signal = np.clip(m - p[:, 4, None, None], 0.0, None) * good
    # the noise model from the data (a detector's background σ misjudges quantized 8-bit
    # data): var_bg from the pass-1 residuals where the star's signal is negligible, then
    # κ per star from the rest of its residual power, its median over the stars
    res2 = (pix - m) ** 2
    dark = good & (signal < 0.02 * np.max(signal, axis=(1, 2), keepdims=True))
    if dark.sum() >= 20:
        var_bg = max(float(np.median(res2[dark])) / 0.4549, 1.0 / 12.0)  # median of χ²₁
    N = good.sum(axis=(1, 2)).astype(float)
    R = (res2 * good).sum(axis=(1, 2)) * N / np.maximum(N - 5.0, 1.0)
    S = signal.sum(axis=(1, 2))
    if c.gain_adu_per_e is not None:
        kappa = float(c.gain_adu_per_e)
    else:
        use = (S > 0) & ~(~good).any(axis=(1, 2))
        kappa = max(float(np.median((R[use] - N[use] * var_bg) / S[use])), 0.0) \
            if use.sum() >= 3 else 0.0
    # pass 2: weighted by background + shot noise
    var = var_bg + kappa * signal
    w2 = good / np.sqrt(var)
    p = _gauss_newton(p, pix, w2, gx, gy, c.iterations, s_max)
    m, J = _model(p, gx, gy, True)
    var = var_bg + kappa * np.clip(m - p[:, 4, None, None], 0.0, None) * good
    w2 = good / np.sqrt(var)
    r = (pix - m) * w2
    Jw = J * w2[..., None]
    A = np.einsum("nija,nijb->nab", Jw, Jw)
    dof = good.sum(axis=(1, 2)) - 5
    ok = (dof > 0) & np.all(np.isfinite(p), axis=1) & (p[:, 2] > 0)
    ok &= np.all(np.abs(p[:, :2] - xy) <= 2.0 * half / 3.0, axis=1)
    ok &= np.abs(np.linalg.det(A)) > 0
    cov = np.full((n, 5, 5), np.nan)
    if ok.any():
        cov[ok] = np.linalg.inv(A[ok])
    # a-posteriori variance factor: the frame's (median over stars), or a star's own when
    # its fit is worse (a blend, a cosmic ray, a PSF the Gaussian does not describe)
    chi2_dof = (r ** 2).sum(axis=(1, 2)) / np.maximum(dof, 1)
    factor = max(float(np.median(chi2_dof[ok])), 1.0) if ok.any() else 1.0
    cov *= np.maximum(chi2_dof, factor)[:, None, None]
    ok &= np.isfinite(cov[:, 0, 0]) & (cov[:, 0, 0] > 0) & (cov[:, 1, 1] > 0)
    snr = p[:, 2] / np.sqrt(np.clip(cov[:, 2, 2], 1e-30, None))
    ok &= snr > 3.0
    return {"uv": p[:, :2], "flux": p[:, 2], "psf": p[:, 3], "cov": cov[:, :2, :2],
            "snr": snr, "saturated": (~good).any(axis=(1, 2)), "ok": ok, "factor": factor,
            "kappa": kappa}
