"""Star centroids from an image, each with a σ from its signal-to-noise.

Detection is tetra3rs's (``extract_centroids``: local background, matched filter,
connected components, hot-pixel and elongation rejection).  Its positions are moment /
quadratic-peak centroids without an uncertainty, biased on saturated stars; so every
detection is refined here by a **pixel-integrated Gaussian PSF fit** (position, flux, width,
local background; Gauss-Newton over a window of ±3 PSF σ, all stars at once):

* saturated pixels (at the image's saturation level, or within 6 background σ of a plateau
  where a full well is reached below the ADC's range) get no weight: a saturated star is
  centred on its unsaturated wings, not on its flat top;
* each pixel's variance is the background's ``σ_bg²`` plus ``κ`` × the star's signal there
  (shot noise; ``κ`` = 1 / gain, ADU per electron, may be given), both estimated from the
  frame as variance components of the weighted fit's residuals, each divided by ``1 − h``
  (``h`` the pixel's leverage: a fit absorbs most of the noise where the star's signal, and
  so its shot noise, is), the fit repeated with them (:func:`_noise_model`);
* each star's width has a prior, the frame's PSF width from its well-measured stars with
  their spread: a faint star's free width comes out narrow and with it its σ too small;
* the centroid's covariance is the weighted fit's ``(JᵀWJ)⁻¹``, scaled by the frame's
  a-posteriori variance factor (χ²/dof pooled over the stars, at least 1), or a star's own
  χ²/dof where its fit is significantly worse (p < 0.001: a blend, a hot pixel, a PSF the
  Gaussian does not describe), and σ = √((σ_u² + σ_v²)/2) goes into the message (contract
  ``sigma``).

The earlier noise model (κ from an unweighted fit's residual power, corrected for 5 of N
parameters) left the shot-noise share of the pixels the fit absorbs uncounted: κ came out
0.6-0.7 × the truth and the stars at SNR ≥ 50 stated a σ 7-21 % too small (49 % with a
0.7 px PSF).  ``test/test_images.py`` checks bias and σ against rendered images with known
truth (8-, 12- and 16-bit, SNR 5 to saturation; ``doc/benchmarks.md``, real sky in).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from stellar_cal_ros.core.distributions import chi2 as chi2_dist
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
    65520, not 65535); else a plateau: a detector whose full well is reached below the ADC's
    range reads its saturated pixels as the full well plus read noise, so five or more
    pixels within 6 background σ of the maximum, far (50 σ) above the background, saturate
    from 6 σ below the maximum.
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
    flat = img.reshape(-1)
    sample = flat[::max(1, flat.size // 16384)].astype(float)
    med = float(np.median(sample))
    sigma = max(1.4826 * float(np.median(np.abs(sample - med))), math.sqrt(1.0 / 12.0))
    if top - 6.0 * sigma >= med + 50.0 * sigma and \
            np.count_nonzero(img >= top - 6.0 * sigma) >= 5:
        return top - 6.0 * sigma
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


def _gauss_newton(p, pix, wgt, gx, gy, iterations, s_max, width=None):
    """Fit ``p`` (n, 5) to the windows ``pix`` with pixel weights ``wgt`` (1/σ, 0: left out).

    ``width``: ``(σ_psf, τ)``, the frame's PSF width and its spread over the stars, a prior
    on each star's width (see :func:`_fit`).  A star stops when its position steps below 1 %
    of its σ (or 1e-5 px); the others go on.
    """
    p = p.copy()
    prior = _width_information(width, 1)[0]
    active = np.arange(len(p))
    for _ in range(iterations):
        if not len(active):
            break
        q, w = p[active], wgt[active]
        m, J = _model(q, gx[active], gy[active], True)
        r = (pix[active] - m) * w
        Jf = (J * w[..., None]).reshape(len(active), -1, 5)
        Jt = Jf.transpose(0, 2, 1)
        A = np.matmul(Jt, Jf) + 1e-9 * np.eye(5) + prior
        g = np.matmul(Jt, r.reshape(len(active), -1, 1))[..., 0]
        if width is not None:
            g[:, 3] += (width[0] - q[:, 3]) / width[1] ** 2
        try:
            Ainv = np.linalg.inv(A)
        except np.linalg.LinAlgError:
            break
        step = np.matmul(Ainv, g[..., None])[..., 0]
        step = np.where(np.isfinite(step), step, 0.0)
        step[:, :2] = np.clip(step[:, :2], -1.0, 1.0)
        q = q + step
        q[:, 2] = np.maximum(q[:, 2], 1e-6)
        q[:, 3] = np.clip(q[:, 3], 0.3, s_max)
        p[active] = q
        sig = np.sqrt(np.abs(np.stack([Ainv[:, 0, 0], Ainv[:, 1, 1]], axis=1)))
        small = np.abs(step[:, :2]) < np.maximum(1e-2 * sig, 1e-5)
        active = active[~small.all(axis=1)]
    return p


def _width_information(width, n: int) -> np.ndarray:
    """The information (n, 5, 5) a width prior ``(σ_psf, τ)`` adds (zeros: no prior)."""
    out = np.zeros((n, 5, 5))
    if width is not None:
        out[:, 3, 3] = 1.0 / width[1] ** 2
    return out


def _frame_width(p, A, use) -> tuple[float, float] | None:
    """The frame's PSF width and its spread, from the stars whose width is measured to 3 %.

    ``(median, max(1.4826·MAD, 2 % of it))`` over those of ``use`` (at least 5), else None.
    A faint star's own width is poorly determined and, free, biased narrow by the noise
    (most of all on quantized data), which makes its stated σ too small: the PSF is the
    optics', shared by the stars of a frame, so each star's width gets this prior.
    """
    var_s = np.full(len(p), np.inf)
    good = use & (np.abs(np.linalg.det(A)) > 0)
    if good.any():
        var_s[good] = np.linalg.inv(A[good])[:, 3, 3]
    sharp = good & (np.sqrt(var_s) < 0.03 * p[:, 3])
    if sharp.sum() < 5:
        return None
    s = p[sharp, 3]
    med = float(np.median(s))
    return med, max(1.4826 * float(np.median(np.abs(s - med))), 0.02 * med)


def _leverage(Jw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel leverage ``h`` (n, k, k) of each star's weighted fit, and ``JᵀWJ`` (n, 5, 5).

    A fitted residual keeps ``(1 − h)`` of its pixel's variance: the fit absorbs the rest,
    most of it where the star's signal (and so its shot noise) is.
    """
    Jf = Jw.reshape(len(Jw), -1, 5)
    A = np.matmul(Jf.transpose(0, 2, 1), Jf)
    Ainv = np.linalg.pinv(A + 1e-12 * np.eye(5))
    h = np.einsum("npa,npa->np", np.matmul(Jf, Ainv), Jf).reshape(Jw.shape[:-1])
    return np.clip(h, 0.0, 1.0), A


def _clipped_mean(y: np.ndarray, k2: float = 25.0, rounds: int = 6) -> float:
    """The mean of squared residuals ``y`` without those beyond ``k2`` × it (iterated).

    A mean, not a median: on quantized data (a background σ near one ADU) most residuals
    share a few values and a median of them is no scale.
    """
    v = float(np.mean(y))
    for _ in range(rounds):
        keep = y < k2 * v
        if not keep.any():
            break
        v_new = float(np.mean(y[keep]))
        if v_new == v:
            break
        v = v_new
    return v


def _noise_model(res2, lev, signal, good, clean, var, var_bg, kappa, fixed):
    """``(σ_bg², κ)`` of ``var = σ_bg² + κ · signal`` from fitted residuals (variance components).

    A fitted residual keeps ``(1 − h)`` of its pixel's variance (``h`` the pixel's leverage in
    the fit weighted by ``var``, the current model, which the caller iterates), so
    ``y = r²/(1 − h)`` has the pixel's variance as its mean.  ``σ_bg²``: the clipped mean of
    ``y`` over the dark ``good`` (unsaturated) pixels of the windows, at least the
    quantization's 1/12; ``κ``: the weighted least-squares
    slope of ``y − σ_bg²`` against the signal over the pixels of ``clean`` windows (no
    saturated pixel: a pixel near the level is truncated) where shot noise dominates
    (``κ·signal ≥ σ_bg²``: in between, on an 8-bit detector whose background σ is below one
    ADU, a star's faint wings are not dithered and their rounding is not noise), weights
    ``1/var²``, pixels beyond 25 × their variance (a hot pixel, a cosmic ray) left out.
    ``fixed``: κ is known (``ExtractConfig.gain_adu_per_e``).
    """
    y = res2 / np.maximum(1.0 - lev, 1e-3)
    use = good & (lev < 0.95)
    dark = use & (signal * max(kappa, 0.0) < 0.05 * var_bg) & \
        (signal < 0.02 * np.max(signal, axis=(1, 2), keepdims=True))
    if dark.sum() >= 20:
        var_bg = max(_clipped_mean(y[dark]), 1.0 / 12.0)
    if fixed is not None:
        return var_bg, fixed
    shot = use & clean[:, None, None] & (y < 25.0 * var) & \
        (signal >= (var_bg / kappa if kappa > 0 else 5.0 * math.sqrt(var_bg)))
    if shot.sum() < 10:
        return var_bg, kappa
    y, s, wt = y[shot], signal[shot], 1.0 / var[shot] ** 2
    return var_bg, max(float(np.sum(wt * s * (y - var_bg)) / np.sum(wt * s * s)), 0.0)


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
    # pass 1: background weights only
    w1 = good / math.sqrt(var_bg)
    p = _gauss_newton(p, pix, w1, gx, gy, c.iterations, s_max)
    m, J = _model(p, gx, gy, True)
    signal = np.clip(m - p[:, 4, None, None], 0.0, None) * good
    res2 = (pix - m) ** 2
    # a first noise model (a detector's background σ misjudges quantized 8-bit data): σ_bg²
    # from the residuals where the star's signal is negligible, κ per star from the rest of
    # its residual power (leverage-corrected), their median; _noise_model refines both
    dark = good & (signal < 0.02 * np.max(signal, axis=(1, 2), keepdims=True))
    if dark.sum() >= 20:
        var_bg = max(_clipped_mean(res2[dark]), 1.0 / 12.0)
    lev, _ = _leverage(J * w1[..., None])
    keep = good * (1.0 - lev)
    R = (res2 * good).sum(axis=(1, 2))
    S = (signal * keep).sum(axis=(1, 2))
    clean = ~(~good).any(axis=(1, 2))  # no saturated pixel in the window
    if c.gain_adu_per_e is not None:
        kappa = float(c.gain_adu_per_e)
    else:
        use = (S > 0) & clean
        kappa = max(float(np.median((R[use] - var_bg * keep[use].sum(axis=(1, 2))) / S[use])),
                    0.0) if use.sum() >= 3 else 0.0
    # pass 2: weighted by background + shot noise; twice the noise model re-estimated from
    # the weighted fit's residuals (variance components), the width prior set, and the fit
    # repeated with them
    fixed = None if c.gain_adu_per_e is None else kappa
    width = None
    for it in range(3):
        var = var_bg + kappa * signal
        w2 = good / np.sqrt(var)
        p = _gauss_newton(p, pix, w2, gx, gy, c.iterations, s_max, width)
        m, J = _model(p, gx, gy, True)
        signal = np.clip(m - p[:, 4, None, None], 0.0, None) * good
        if it == 2:
            break
        var = var_bg + kappa * signal
        lev, A = _leverage(J * (good / np.sqrt(var))[..., None])
        if it == 0:
            width = _frame_width(p, A, clean)
        var_bg, kappa = _noise_model((pix - m) ** 2, lev, signal, good, clean, var, var_bg,
                                     kappa, fixed)
    var = var_bg + kappa * signal
    w2 = good / np.sqrt(var)
    r = (pix - m) * w2
    Jw = J * w2[..., None]
    Jf = Jw.reshape(n, -1, 5)
    A = np.matmul(Jf.transpose(0, 2, 1), Jf) + _width_information(width, n)
    dof = good.sum(axis=(1, 2)) - 5
    ok = (dof > 0) & np.all(np.isfinite(p), axis=1) & (p[:, 2] > 0)
    ok &= np.all(np.abs(p[:, :2] - xy) <= 2.0 * half / 3.0, axis=1)
    ok &= np.abs(np.linalg.det(A)) > 0
    cov = np.full((n, 5, 5), np.nan)
    if ok.any():
        cov[ok] = np.linalg.inv(A[ok])
    # a-posteriori variance factor: the frame's (pooled over the stars whose fit agrees with
    # the noise model), or a star's own when its fit is significantly worse (p < 0.001: a
    # blend, a hot pixel, a PSF the Gaussian does not describe); dof less what the width
    # prior holds of the width
    chi2 = (r ** 2).sum(axis=(1, 2))
    if width is not None:
        dof = dof + np.nan_to_num(cov[:, 3, 3]) / width[1] ** 2
    dof1 = np.maximum(dof, 1)
    bad = chi2_dist.sf(chi2, dof1) < 1e-3
    pool = ok & ~bad
    factor = max(float(chi2[pool].sum() / dof1[pool].sum()), 1.0) if pool.any() else 1.0
    own = chi2_dist.sf(chi2 / factor, dof1) < 1e-3
    cov *= np.where(own, np.maximum(chi2 / dof1, factor), factor)[:, None, None]
    ok &= np.isfinite(cov[:, 0, 0]) & (cov[:, 0, 0] > 0) & (cov[:, 1, 1] > 0)
    snr = p[:, 2] / np.sqrt(np.clip(cov[:, 2, 2], 1e-30, None))
    ok &= snr > 3.0
    return {"uv": p[:, :2], "flux": p[:, 2], "psf": p[:, 3], "cov": cov[:, :2, :2],
            "snr": snr, "saturated": (~good).any(axis=(1, 2)), "ok": ok, "factor": factor,
            "kappa": kappa, "var_bg": var_bg}
