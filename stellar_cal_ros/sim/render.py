"""Star images rendered from the truth world.

PSF, background, shot and read noise, hot pixels, saturation and (optionally) clouds.
Every star of a simulated frame (:func:`stellar_cal_ros.sim.world.simulate`; run the
scenario with ``centroid_noise_px = 0`` so the frames carry the true centroids) becomes a
pixel-integrated Gaussian PSF centred on its true ``(u, v)`` (pixel-centre convention,
contract §1) holding ``zero_point_e · 10^(−0.4 m)`` photo-electrons.  The electrons of each
pixel (star + sky background) are Poisson, read noise is Gaussian, the result is digitized
(``gain_e_per_adu``, ``bias_adu``) and clipped at the full well and the ADC's range, so bright
stars saturate as on a real sensor.  Hot pixels add a fixed level at random places; clouds
multiply the stars by a smooth random transmission and add the light they scatter.

The truth of each rendered star (its true centroid, electrons, whether it saturated) comes
back with the image, so extraction is tested against it (centroid bias and σ against SNR,
detection and false-detection rates).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from stellar_cal_ros.core.types import StarFrame

__all__ = ["RenderedImage", "SensorConfig", "render_frames", "render_image"]


@dataclass
class SensorConfig:
    """The camera's photometry and detector (defaults: a 12-bit star tracker)."""

    psf_sigma_px: float = 1.0  #: Gaussian PSF σ, px
    zero_point_e: float = 1.5e6  #: electrons of a magnitude-0 star in one exposure
    background_e: float = 40.0  #: sky background per pixel, electrons
    read_noise_e: float = 5.0  #: read noise, electrons rms
    gain_e_per_adu: float = 2.0  #: electrons per digital number
    bias_adu: float = 100.0  #: offset of the digitized values
    full_well_e: float = 15000.0  #: a pixel saturates at this many electrons
    bits: int = 12  #: ADC range 0 .. 2^bits − 1 (8: an 8-bit image)
    hot_pixel_fraction: float = 2e-5  #: fraction of pixels that are hot
    hot_pixel_adu: float = 1500.0  #: digital level a hot pixel adds
    clouds: float = 0.0  #: 0: clear; else the rms optical depth of a smooth cloud layer
    cloud_scale_px: float = 150.0  #: cloud structure size, px
    window_sigmas: float = 5.0  #: PSF rendered within this many σ of the star

    @property
    def saturation_adu(self) -> float:
        """The digital level at which a pixel is saturated."""
        return float(min(2 ** self.bits - 1,
                         self.bias_adu + self.full_well_e / self.gain_e_per_adu))

    @property
    def dtype(self) -> type:
        """uint8 for an 8-bit sensor, else uint16."""
        return np.uint8 if self.bits <= 8 else np.uint16


@dataclass
class RenderedImage:
    """One rendered exposure and its truth."""

    image: np.ndarray  #: (height, width) uint8 / uint16
    uv: np.ndarray  #: (n, 2) true centroids of the rendered stars, px
    electrons: np.ndarray  #: (n,) electrons each star delivered (after clouds)
    saturated: np.ndarray  #: (n,) bool: the star's peak pixel saturated
    hot_pixels: np.ndarray  #: (k, 2) (u, v) of the hot pixels
    transmission: np.ndarray | None = None  #: (height, width) cloud transmission (None: clear)


def _pixel_fraction(centre: np.ndarray, lo: np.ndarray, s: float, k: int) -> np.ndarray:
    """Fraction of a 1-D Gaussian (mean ``centre``, σ ``s``) in each pixel of a window.

    ``centre`` (n,), ``lo`` (n,) first pixel index of each window; returns (n, k) for the
    k = window length pixels ``lo .. lo + k − 1`` (pixel j spans j − ½ .. j + ½).
    """
    j = lo[:, None] + np.arange(k)[None, :]
    return ndtr((j + 0.5 - centre[:, None]) / s) - ndtr((j - 0.5 - centre[:, None]) / s)


def _clouds(width: int, height: int, sensor: SensorConfig, rng) -> np.ndarray:
    """A smooth random transmission map exp(−τ), τ ≥ 0 with rms ``sensor.clouds``.

    Smoothed noise on a grid 16× coarser than the pixels, interpolated up (cheap at any
    cloud size).
    """
    from scipy.ndimage import gaussian_filter, zoom

    cell = 16
    shape = (height // cell + 2, width // cell + 2)
    field = gaussian_filter(rng.standard_normal(shape), sensor.cloud_scale_px / cell,
                            mode="wrap")
    field = zoom(field, cell, order=1)[:height, :width]
    field = (field - field.mean()) / max(float(field.std()), 1e-12)
    tau = np.clip(sensor.clouds * (field + 0.5), 0.0, None)
    return np.exp(-tau)


def render_image(uv: np.ndarray, magnitude: np.ndarray, width: int, height: int,
                 sensor: SensorConfig | None = None,
                 rng: np.random.Generator | None = None) -> RenderedImage:
    """Render stars at true centroids ``uv`` (n, 2) px of magnitudes ``magnitude`` (n,)."""
    sensor = sensor or SensorConfig()
    rng = rng if rng is not None else np.random.default_rng(0)
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    mag = np.asarray(magnitude, dtype=float).reshape(-1)
    electrons = sensor.zero_point_e * 10.0 ** (-0.4 * mag)
    trans = None
    sky = np.full((height, width), float(sensor.background_e))
    if sensor.clouds > 0:
        trans = _clouds(width, height, sensor, rng)
        iu = np.clip(np.rint(uv[:, 0]).astype(int), 0, width - 1)
        iv = np.clip(np.rint(uv[:, 1]).astype(int), 0, height - 1)
        electrons = electrons * trans[iv, iu]
        sky = sky + 3.0 * sensor.background_e * (1.0 - trans)  # moonlit cloud glow
    expected = sky.copy()
    s = float(sensor.psf_sigma_px)
    half = int(np.ceil(sensor.window_sigmas * s))
    lo_u = np.floor(uv[:, 0]).astype(int) - half
    lo_v = np.floor(uv[:, 1]).astype(int) - half
    k = 2 * half + 2
    fx = _pixel_fraction(uv[:, 0], lo_u, s, k)
    fy = _pixel_fraction(uv[:, 1], lo_v, s, k)
    for i in range(len(uv)):  # stars are few; each adds an outer product in its window
        u0, v0 = lo_u[i], lo_v[i]
        a, b = max(u0, 0), min(u0 + k, width)
        c, d = max(v0, 0), min(v0 + k, height)
        if a >= b or c >= d:
            continue
        expected[c:d, a:b] += electrons[i] * np.outer(fy[i, c - v0:d - v0], fx[i, a - u0:b - u0])
    # in place on one buffer: electrons (Poisson, full well) -> ADU + read noise -> ADC
    adu = rng.poisson(expected).astype(np.float64)
    np.minimum(adu, sensor.full_well_e, out=adu)
    adu *= 1.0 / sensor.gain_e_per_adu
    adu += rng.standard_normal(adu.shape) * (sensor.read_noise_e / sensor.gain_e_per_adu) \
        + sensor.bias_adu
    n_hot = rng.binomial(width * height, sensor.hot_pixel_fraction)
    hot = np.c_[rng.integers(0, width, n_hot), rng.integers(0, height, n_hot)]
    adu[hot[:, 1], hot[:, 0]] += sensor.hot_pixel_adu
    top = float(2 ** sensor.bits - 1)
    sat_level = sensor.saturation_adu
    np.rint(adu, out=adu)
    np.maximum(adu, 0.0, out=adu)
    np.minimum(adu, top, out=adu)
    iu = np.clip(np.rint(uv[:, 0]).astype(int), 0, width - 1)
    iv = np.clip(np.rint(uv[:, 1]).astype(int), 0, height - 1)
    peak_e = expected[iv, iu]
    saturated = (peak_e >= sensor.full_well_e) | \
        (peak_e / sensor.gain_e_per_adu + sensor.bias_adu >= sat_level)
    return RenderedImage(adu.astype(sensor.dtype), uv.copy(), electrons, saturated,
                         hot.astype(float), trans)


def render_frames(frames: list[StarFrame], width: int, height: int,
                  sensor: SensorConfig | None = None, seed: int = 0) -> list[RenderedImage]:
    """Render each simulated frame (its centroids taken as the truth; see the module doc)."""
    rng = np.random.default_rng(seed)
    return [render_image(f.uv, f.magnitude, width, height, sensor, rng) for f in frames]


def without_noise(scenario):
    """The scenario with noise-free centroids (the truth a renderer needs)."""
    return dataclasses.replace(scenario, centroid_noise_px=0.0)
