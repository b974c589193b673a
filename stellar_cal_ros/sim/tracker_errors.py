"""Simulator-only star-tracker errors that no library effect models (issue 21, unseen cases).

Each function changes a finished :class:`~stellar_cal_ros.sim.world.SimulationResult` in
place, the way a real tracker's centroiding or readout spoils its messages; none is an
effect of the library (the diagnosis must call them noise or 'unexplained', never a
library name).  The centroids' own noise is expected to be drawn by the caller (a scenario
with ``centroid_noise_px = 0`` and :func:`renoise`) where the error acts on the noise-free
centroid.

==================  ==============================================================================
function            what a tracker does
==================  ==============================================================================
``renoise``         per-star centroid noise ``σ(mag, uv)``; the messages state any σ (0: unknown)
``uv_noise``        centroid noise anisotropic or u-v correlated; the messages state an isotropic σ
``s_curve``         pixel locking: a centroid bias ``A sin(2π u)`` per axis, periodic in the
                    centroid's sub-pixel phase (a PSF sampled by too few pixels)
``rolling_shutter`` rows read out over ``T``: row ``v`` exposed ``(v/H − ½) T`` after the stamp,
                    the star displaced by its image velocity times that
``outliers``        a fraction of centroids off by ``k σ`` (blends, hot pixels, cosmic rays)
``ar1_noise``       centroid noise correlated in time per star (AR(1), ``τ`` frames)
``imu_noise_axis``  extra white noise on one gyro or accelerometer axis, not in the covariance
``heavy_tails``     centroid noise Student-t (``ν`` dof), scaled to a stated RMS
``gyro_bias_walk``  gyro bias instability: a random walk in the bias the model holds constant
``gyro_bias_gauss_markov``  gyro bias instability as a first-order Gauss-Markov process
``gross_outliers``  a fraction of centroids tens of px off (stars misidentified), on the detector
``stamp_jitter``    each frame stamped with a random error (the exposure's true time unknown)
``star_offsets``    each star's centroid off by its own fixed offset in every frame (a catalogue
                    position error, a proper motion the catalogue lacks)
``radial_by_mag``   a centroid bias away from the principal point growing with magnitude, the
                    same length at every radius (no focal length or distortion makes it)
``saturation_pull`` bright stars' centroids pulled toward the detector's centre, more the
                    brighter (a saturated core)
``focal_drift``     the image scale (the focal length) drifting linearly over the run
``lens_zone``       the image scale beyond a radius not the scale within (a lens zone: a step)
``vibration``       an attitude vibration of the tracker against the IMU, sampled by the frames
==================  ==============================================================================
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from stellar_cal_ros.core.rotation import so3_exp


def renoise(sim, true_sigma: Callable, stated: float, seed: int) -> None:
    """Add per-star noise ``true_sigma(mag, uv)`` (px) to the centroids; σ field ``stated``."""
    rng = np.random.default_rng(seed + 7919)
    for f in sim.star_frames:
        mag = np.asarray(f.magnitude, dtype=float)
        s = np.broadcast_to(true_sigma(mag, np.asarray(f.uv, dtype=float)), mag.shape)
        f.uv = np.asarray(f.uv, dtype=float) + s[:, None] * rng.standard_normal(f.uv.shape)
        f.sigma = np.full(len(mag), float(stated))


def uv_noise(sim, sigma_uv: tuple[float, float], rho: float, stated: float, seed: int
             ) -> None:
    """Centroid noise unlike an isotropic σ: ``sigma_uv`` (px) along u and v, correlation ``rho``.

    An elongated PSF or a readout noisier along one axis; the messages state ``stated``
    (isotropic).  The isotropic ML scale of the stated σ is √((σ_u² + σ_v²) / 2) / stated.
    """
    su, sv = sigma_uv
    L = np.linalg.cholesky(np.array([[su * su, rho * su * sv], [rho * su * sv, sv * sv]]))
    rng = np.random.default_rng(seed + 7919)
    for f in sim.star_frames:
        n = len(f.uv)
        f.uv = np.asarray(f.uv, dtype=float) + rng.standard_normal((n, 2)) @ L.T
        f.sigma = np.full(n, float(stated))


def s_curve(sim, amplitude_px: float) -> None:
    """Pixel locking: ``u += A sin(2π u)``, ``v += A sin(2π v)`` (pixel centres at integers).

    The centroid of an under-sampled PSF is pulled toward the pixel centre: an error odd
    about the centre and periodic with one pixel, of amplitude ``A`` (0.05-0.1 px is
    typical of a defocused PSF a few pixels wide).
    """
    for f in sim.star_frames:
        uv = np.asarray(f.uv, dtype=float)
        f.uv = uv + amplitude_px * np.sin(2.0 * np.pi * uv)


def image_velocity(sim) -> list[np.ndarray]:
    """Each star's true image velocity (px/s, ``(n, 2)`` per frame), pinhole at the truth."""
    world = sim.truth_world
    cam = world.camera()
    R_imu_st = world.installation().as_matrix()
    t0 = int(round(world.scenario.start_posix * 1e9))
    out = []
    for f in sim.star_frames:
        uv = np.asarray(f.uv, dtype=float).reshape(-1, 2)
        t = np.array([(f.stamp_ns - t0) * 1e-9])
        w_st = R_imu_st.T @ world.omega_ib_b(t)[0]
        x = (uv[:, 0] - cam.cx) / cam.fx
        y = (uv[:, 1] - cam.cy) / cam.fy
        d = np.stack([x, y, np.ones_like(x)], 1)
        dd = -np.cross(w_st, d)  # a fixed inertial direction seen from the rotating tracker
        out.append(np.stack([cam.fx * (dd[:, 0] - x * dd[:, 2]),
                             cam.fy * (dd[:, 1] - y * dd[:, 2])], 1))
    return out


def speed_squared_smear(sim, px: float) -> None:
    """A centroid bias along each star's image motion growing as its speed squared.

    ``px`` at the run's 95th-percentile image speed (:func:`image_velocity`, every star of
    every frame): a thresholded centroid of a streak, its faint tail clipped more the
    longer the streak.  A bias *linear* in the image velocity is a time offset (in the
    library); its square is not.  No noise added.
    """
    vel = image_velocity(sim)
    s95 = float(np.percentile(np.concatenate([np.linalg.norm(v, axis=1) for v in vel]), 95))
    for f, v in zip(sim.star_frames, vel, strict=True):
        speed = np.linalg.norm(v, axis=1)
        f.uv = np.asarray(f.uv, dtype=float) + px * (speed / s95)[:, None] * v / s95


def rolling_shutter(sim, readout_s: float, axis: str = "v") -> None:
    """Rows read out over ``readout_s``: row ``v`` seen ``(v/H − ½)·T`` after the stamp.

    The stamp is the middle row's time (so no common time offset); every star moves by its
    image velocity over its row's offset: a displacement ∝ row × rate, zero at rest.
    ``axis`` ``"u"``: the columns read out so (column ``u`` seen ``(u/W − ½)·T`` after the
    stamp: a detector mounted a quarter turn round).
    """
    cam = sim.truth_world.camera()
    k, extent = (0, float(cam.width)) if axis == "u" else (1, float(cam.height))
    for f, vel in zip(sim.star_frames, image_velocity(sim), strict=True):
        uv = np.asarray(f.uv, dtype=float)
        dt = (uv[:, k] / extent - 0.5) * readout_s
        f.uv = uv + dt[:, None] * vel


def outliers(sim, fraction: float, k_sigma: float, seed: int) -> None:
    """A ``fraction`` of the centroids moved by ``k_sigma`` × their stated-or-scenario σ."""
    rng = np.random.default_rng(seed + 15485863)
    s0 = sim.scenario.centroid_noise_px
    for f in sim.star_frames:
        uv = np.asarray(f.uv, dtype=float)
        hit = rng.random(len(uv)) < fraction
        if hit.any():
            uv = uv.copy()
            uv[hit] += k_sigma * s0 * rng.standard_normal((int(hit.sum()), 2))
        f.uv = uv


class Ar1Tracks:
    """Unit-variance AR(1) noise per star track over frames (lag-one correlation ``rho``).

    :meth:`draw` gives the ``(n, 2)`` draws of frame ``j``'s stars (their catalogue ids);
    a star that leaves and comes back continues its process over the gap (``rho`` to the
    power of the frames missed).  Scaled by each star's σ it is noise of marginal σ whose
    consecutive values correlate by ``rho``: the simulator's :func:`ar1_noise` and the
    twin's rendering of correlated centroid noise (:mod:`stellar_cal_ros.diagnosis.twin`).
    ``share`` below 1: white + AR(1) noise of unit variance, the AR(1) carrying ``share`` of
    it (lags ``share ρ^k``, :func:`~stellar_cal_ros.diagnosis.noise_structure.track_model`),
    a white draw per star after its AR(1)'s (``share`` 1 draws nothing more).
    """

    def __init__(self, rho: float, rng: np.random.Generator, share: float = 1.0):
        self.rho, self.rng, self.share = float(rho), rng, float(share)
        self.last: dict[int, tuple[int, np.ndarray]] = {}

    def draw(self, j: int, catalog_id) -> np.ndarray:
        """The ``(n, 2)`` unit-variance draws of frame ``j``'s stars (``catalog_id``)."""
        ids = np.asarray(catalog_id).tolist()
        out = np.empty((len(ids), 2))
        for i, cid in enumerate(ids):
            n = self.rng.standard_normal(2)
            prev = self.last.get(int(cid))
            if prev is None:
                e = n
            else:
                a = self.rho ** (j - prev[0])
                e = a * prev[1] + np.sqrt(1.0 - a * a) * n
            self.last[int(cid)] = (j, e)
            out[i] = e if self.share == 1.0 else math.sqrt(self.share) * e + math.sqrt(
                1.0 - self.share) * self.rng.standard_normal(2)
        return out


def ar1_noise(sim, sigma_px: float, tau_frames: float, seed: int,
              stated: float | None = None, share: float = 1.0) -> None:
    """Centroid noise of each star an AR(1) over frames (marginal ``σ``, time constant τ).

    A star that leaves and comes back continues its process over the gap.  The σ field
    states ``stated`` (default ``σ``: the marginal noise is stated right, only its
    correlation is not).  ``share`` below 1: white + AR(1) noise, the AR(1) carrying that
    share of the variance (:class:`Ar1Tracks`; unseen case ``ar1_mixed``).
    """
    tracks = Ar1Tracks(float(np.exp(-1.0 / tau_frames)),
                       np.random.default_rng(seed + 6700417), share=share)
    for j, f in enumerate(sim.star_frames):
        uv = np.asarray(f.uv, dtype=float)
        f.uv = uv + sigma_px * tracks.draw(j, f.catalog_id)
        f.sigma = np.full(len(uv), float(sigma_px if stated is None else stated))


def imu_noise_axis(sim, sensor: str, axis: int, factor: float, seed: int) -> None:
    """One gyro (``"gyro"``) or accelerometer axis's white noise made ``factor`` x the stated.

    Extra noise is added; the messages' covariance is unchanged.
    """
    rng = np.random.default_rng(seed + 999331)
    imu = sim.imu
    field = "angular_velocity" if sensor == "gyro" else "linear_acceleration"
    cov = np.asarray(getattr(imu, field + "_covariance"), dtype=float).reshape(3, 3)
    sd = np.sqrt(cov[axis, axis]) * np.sqrt(max(factor**2 - 1.0, 0.0))
    data = np.asarray(getattr(imu, field), dtype=float).copy()
    data[:, axis] += sd * rng.standard_normal(len(data))
    setattr(imu, field, data)


def heavy_tails(sim, sigma_px: float, dof: float, seed: int) -> None:
    """Centroid noise Student-t with ``dof`` (> 2) degrees of freedom, RMS ``sigma_px``.

    Each axis draws ``t_ν · σ √((ν − 2)/ν)`` (variance ``σ²``: the σ field, set to
    ``sigma_px``, is right on average; a few centroids lie far out, as blends and cosmic
    rays make them).
    """
    if not dof > 2:
        raise ValueError(f"Student-t noise needs dof > 2 for a finite RMS, got {dof}")
    rng = np.random.default_rng(seed + 32452843)
    k = sigma_px * np.sqrt((dof - 2.0) / dof)
    for f in sim.star_frames:
        uv = np.asarray(f.uv, dtype=float)
        f.uv = uv + k * rng.standard_t(dof, uv.shape)
        f.sigma = np.full(len(uv), float(sigma_px))


def gyro_bias_walk(sim, density_deg_h_sqrth: float, seed: int) -> np.ndarray:
    """The gyro bias wanders: a random walk of ``density`` deg/h/√h on each axis.

    Added to the gyro samples (the bias at the first sample is the scenario's); the model's
    gyro bias is a constant, so this is gyro bias instability no library effect states.
    Returns the walk added (rad/s, ``(N, 3)``).
    """
    rng = np.random.default_rng(seed + 86028121)
    imu = sim.imu
    t = np.asarray(imu.stamp_ns, dtype=np.int64)
    dt = np.diff(t, prepend=t[0]).astype(float) * 1e-9
    q = np.deg2rad(density_deg_h_sqrth) / 3600.0 / 60.0  # rad/s per √s
    walk = np.cumsum(q * np.sqrt(dt)[:, None] * rng.standard_normal((len(t), 3)), axis=0)
    imu.angular_velocity = np.asarray(imu.angular_velocity, dtype=float) + walk
    return walk


def gyro_bias_gauss_markov(sim, sigma_deg_h: float, tau_s: float, seed: int) -> np.ndarray:
    """The gyro bias wanders as a first-order Gauss-Markov process (σ, correlation time τ).

    Stationary, of standard deviation ``sigma_deg_h`` deg/h per axis (its first value a
    draw of that law), added to the gyro samples: a datasheet's "bias instability" that a
    user states as white noise (the model's gyro bias is a constant).  Returns the bias
    added (rad/s, ``(N, 3)``).
    """
    rng = np.random.default_rng(seed + 67867967)
    imu = sim.imu
    t = np.asarray(imu.stamp_ns, dtype=np.int64)
    dt = np.diff(t, prepend=t[0]).astype(float) * 1e-9
    s = np.deg2rad(sigma_deg_h) / 3600.0
    a = np.exp(-dt / tau_s)
    n = rng.standard_normal((len(t), 3))
    b = np.empty((len(t), 3))
    prev = s * n[0]
    for k in range(len(t)):  # b_k = a b_(k-1) + s sqrt(1 - a^2) n_k
        prev = prev if k == 0 else a[k] * prev + s * math.sqrt(1.0 - a[k] * a[k]) * n[k]
        b[k] = prev
    imu.angular_velocity = np.asarray(imu.angular_velocity, dtype=float) + b
    return b


def gross_outliers(sim, fraction: float, lo_px: float, hi_px: float, seed: int) -> int:
    """A ``fraction`` of the centroids moved ``lo_px``..``hi_px`` (uniform) in a random direction.

    What a tracker's misidentified stars look like in its messages: the identity (catalogue
    id, RA/Dec) of one star, the centroid tens of px away; the moved centroid stays on the
    detector (the direction turned by half a turn where it would leave it).  The σ field
    is left as it is.  Returns how many centroids were moved.
    """
    rng = np.random.default_rng(seed + 179424673)
    cam = sim.truth_world.camera()
    size = np.array([float(cam.width), float(cam.height)])
    moved = 0
    for f in sim.star_frames:
        uv = np.asarray(f.uv, dtype=float)
        hit = np.flatnonzero(rng.random(len(uv)) < fraction)
        if not len(hit):
            continue
        uv = uv.copy()
        ang = rng.uniform(0.0, 2.0 * np.pi, len(hit))
        r = rng.uniform(lo_px, hi_px, len(hit))
        d = r[:, None] * np.stack([np.cos(ang), np.sin(ang)], 1)
        out = ((uv[hit] + d < 0.0) | (uv[hit] + d >= size)).any(axis=1)
        d[out] *= -1.0
        uv[hit] += d
        f.uv = uv
        moved += len(hit)
    return moved


def stamp_jitter(sim, sigma_s: float, seed: int) -> np.ndarray:
    """Each frame's stamp off its exposure's true time by N(0, ``sigma_s``), independently.

    What a tracker whose clock is read with a jitter sends: the stars are where they were
    at the exposure, the stamp is not.  Returns the errors (s, one per frame:
    :func:`stamp_errors`).
    """
    err = stamp_errors(len(sim.star_frames), sigma_s, seed)
    for f, e in zip(sim.star_frames, err, strict=True):
        f.stamp_ns = int(f.stamp_ns + round(float(e) * 1e9))
    return err


def stamp_errors(n: int, sigma_s: float, seed: int) -> np.ndarray:
    """``n`` frames' stamp errors, N(0, ``sigma_s``) each (s).

    The stamp is the exposure's true time plus its error (:func:`stamp_jitter`; a twin
    renders the stars of a frame at its stamp less it,
    :func:`~stellar_cal_ros.diagnosis.twin.render`).
    """
    return sigma_s * np.random.default_rng(seed + 49979687).standard_normal(n)


def frame_jitter(sim, rms_px: float, seed: int) -> np.ndarray:
    """Every star of a frame shifted by one N(0, ``rms_px``²) per axis, independently by frame.

    An attitude (or image) jitter faster than the frames that the gyro does not see: one
    error common to the frame's stars, white from frame to frame, not each star's noise
    (unseen case ``frame_jitter``).  Returns the shifts (px, one ``(u, v)`` per frame).
    """
    out = frame_shifts(len(sim.star_frames), rms_px, seed)
    for i, f in enumerate(sim.star_frames):
        f.uv = np.asarray(f.uv, dtype=float) + out[i]
    return out


def frame_shifts(n: int, rms_px: float, seed: int) -> np.ndarray:
    """``n`` frames' common shifts (n, 2), N(0, ``rms_px``²) per axis each (px).

    :func:`frame_jitter`'s; a twin renders a frame-common noise it is given with them
    (:func:`~stellar_cal_ros.diagnosis.twin.render`).
    """
    return rms_px * np.random.default_rng(seed + 5381).standard_normal((n, 2))


def star_offsets(sim, rms_px: float, seed: int) -> dict[int, np.ndarray]:
    """Each star off by its own fixed offset, N(0, ``rms_px``²) per axis, in every frame.

    What a catalogue position error (or a proper motion the catalogue lacks) does to the
    centroids over a short run: an error that repeats star by star, not noise.  Returns
    the offsets (px) by catalogue id.
    """
    rng = np.random.default_rng(seed + 67867967)
    ids = sorted({int(c) for f in sim.star_frames for c in np.asarray(f.catalog_id).tolist()})
    off = dict(zip(ids, rms_px * rng.standard_normal((len(ids), 2)), strict=True))
    for f in sim.star_frames:
        cid = np.asarray(f.catalog_id).tolist()
        if cid:
            f.uv = np.asarray(f.uv, dtype=float) + np.array([off[int(c)] for c in cid])
    return off


def quadrant_step(sim, shift_px: float = 0.05) -> None:
    """Stars in the detector's upper-left quadrant moved by ``shift_px`` along u and v.

    (u, v below the centre.)  A detector defect or a stitched sensor: a step that no
    library effect (a polynomial of the detector) makes.
    """
    w, h = sim.prior.camera.width, sim.prior.camera.height
    for f in sim.star_frames:
        uv = np.asarray(f.uv, dtype=float)
        inside = (uv[:, 0] < w / 2.0) & (uv[:, 1] < h / 2.0)
        f.uv = uv + shift_px * inside[:, None]


def radial_by_mag(sim, px_per_mag: float, from_mag: float = 4.0) -> None:
    """Each centroid pushed away from the principal point, more for fainter stars.

    By ``px_per_mag`` per magnitude fainter than ``from_mag`` (0 for brighter stars), the
    same length at every radius.  A centroider that clips faint stars' wings unevenly
    about the optical axis: no focal length (∝ radius) or radial distortion (∝ radius³)
    makes it.
    """
    cam = sim.prior.camera
    _radial_shift(sim, (cam.cx, cam.cy), from_mag,
                  lambda m: px_per_mag * np.maximum(m - from_mag, 0.0))


def _radial_shift(sim, centre: tuple[float, float], from_mag: float, shift_of_mag) -> None:
    """Each centroid moved away from ``centre`` by ``shift_of_mag(magnitude)`` px (< 0: toward).

    (A star without a magnitude takes ``from_mag``'s.)
    """
    for f in sim.star_frames:
        uv = np.asarray(f.uv, dtype=float)
        d = uv - np.asarray(centre, dtype=float)
        unit = d / np.maximum(np.linalg.norm(d, axis=1), 1e-9)[:, None]
        m = np.nan_to_num(np.asarray(f.magnitude, dtype=float), nan=from_mag)
        f.uv = uv + shift_of_mag(m)[:, None] * unit


def saturation_pull(sim, px_per_mag: float, from_mag: float = 4.0) -> None:
    """Each centroid of a bright star pulled toward the detector's centre.

    By ``px_per_mag`` per magnitude brighter than ``from_mag`` (0 for fainter stars): a
    saturated PSF's clipped core, whose centroid a centroider biases toward the middle of
    the detector (unseen case ``saturation``); the mirror of :func:`radial_by_mag`, about
    the detector's centre rather than the principal point.
    """
    cam = sim.prior.camera
    _radial_shift(sim, (cam.width / 2.0, cam.height / 2.0), from_mag,
                  lambda m: -px_per_mag * np.maximum(from_mag - m, 0.0))


def column_ripple(sim, amplitude_px: float, periods: float = 3.0) -> None:
    """A centroid ripple along the columns: ``u += A sin(2π periods u / width)``.

    A stitched detector's or a flat field's periodic error (``periods`` across the
    detector's width): no polynomial distortion of the library makes it (unseen case
    ``ripple``).
    """
    w = sim.prior.camera.width
    for f in sim.star_frames:
        uv = np.asarray(f.uv, dtype=float).copy()
        uv[:, 0] += amplitude_px * np.sin(2.0 * np.pi * periods * uv[:, 0] / w)
        f.uv = uv


def focal_drift(sim, ppm: float) -> None:
    """The image scale drifting linearly over the run by ``ppm`` (of the focal length).

    ``−ppm/2`` at the first frame, ``+ppm/2`` at the last, about the prior's principal
    point.  A focal length that follows a temperature no topic carries (unseen case
    ``focal_drift``): no library effect lets f change with time alone.
    """
    cam = sim.prior.camera
    c = np.array([cam.cx, cam.cy])
    t0, t1 = sim.star_frames[0].stamp_ns, sim.star_frames[-1].stamp_ns
    for f in sim.star_frames:
        x = (f.stamp_ns - t0) / max(t1 - t0, 1) - 0.5
        f.uv = c + (np.asarray(f.uv, dtype=float) - c) * (1.0 + ppm * 1e-6 * x)


def tilt_drift(sim, mrad: float) -> None:
    """The detector's tilt about u drifting linearly over the run, ``±mrad`` at either end.

    ``−mrad`` at the first frame, ``+mrad`` at the last (0 on average): each centroid's
    offset ``d`` from the prior's principal point scaled by ``1 + tau d_v / f_y`` (OpenCV's
    tau_x keystone to first order).  A detector mount that creeps (unseen case
    ``tilt_drift``): the library's image_plane_tilt is static.
    """
    cam = sim.prior.camera
    c = np.array([cam.cx, cam.cy])
    f_px = float(cam.fy)
    t0, t1 = sim.star_frames[0].stamp_ns, sim.star_frames[-1].stamp_ns
    for f in sim.star_frames:
        x = (f.stamp_ns - t0) / max(t1 - t0, 1) - 0.5
        d = np.asarray(f.uv, dtype=float) - c
        f.uv = c + d * (1.0 + 2.0 * mrad * 1e-3 * x * d[:, 1:2] / f_px)


#: the PSCE tracker's nominal plate scale (25.6 mm focal length, 6.45 µm pixels), ″/px
ARCSEC_PER_PX = 206264.806 / (25.6 / 0.00645)


def turn_frame(f, cam, arcsec: float, angle_deg: float) -> None:
    """Every star of frame ``f`` turned by a small tracker rotation about its x and y axes.

    The rotation that shifts the detector's centre by ``arcsec`` along ``angle_deg`` (at
    :data:`ARCSEC_PER_PX`); the pinhole's rays of ``cam`` turned, not a uniform shift.
    """
    shift = arcsec / ARCSEC_PER_PX * np.array([np.cos(np.deg2rad(angle_deg)),
                                               np.sin(np.deg2rad(angle_deg))])
    rotate_frame(f, cam, so3_exp([-shift[1] / cam.fy, shift[0] / cam.fx, 0.0]))


def rotate_frame(f, cam, R: np.ndarray) -> None:
    """Every star of frame ``f`` seen through the tracker turned by ``R`` (its own frame).

    The pinhole's rays of ``cam`` turned by the rotation matrix ``R`` and projected again.
    """
    uv = np.asarray(f.uv, dtype=float)
    d = np.stack([(uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy,
                  np.ones(len(uv))], 1) @ R.T  # (the pinhole's rays, turned)
    f.uv = np.stack([cam.cx + cam.fx * d[:, 0] / d[:, 2],
                     cam.cy + cam.fy * d[:, 1] / d[:, 2]], 1)


def backlash(sim, arcsec) -> None:
    """A mount with backlash: the tracker lags each slew by ``arcsec`` about the slew's axis.

    From a slew on (a fast IMU sample: its rate above half its 95th percentile) the
    tracker sits turned by ``-arcsec`` along the rate direction of the latest fast sample
    before the frame (IMU frame,
    turned into the tracker's by the true installation) and stays there until the next
    slew: psce's six ±30° steps leave it in a different place after each, so the
    installation steps at every slew (the library's is one constant); nothing before the
    first slew; no gyro sees it.  ``arcsec``: one lag, or each slew's in turn (a sequence,
    repeated: a lag that differs from slew to slew).
    """
    imu = sim.imu
    t = np.asarray(imu.stamp_ns, dtype=np.int64)
    w = np.asarray(imu.angular_velocity, dtype=float)
    speed = np.linalg.norm(w, axis=1)
    fast = speed > 0.5 * np.percentile(speed, 95)
    last = np.maximum.accumulate(np.where(fast, np.arange(len(t)), -1))
    slew = np.cumsum(fast & ~np.concatenate([[False], fast[:-1]])) - 1  # each sample's slew
    lags = np.atleast_1d(np.asarray(arcsec, dtype=float))
    R = sim.truth_world.installation().as_matrix()  # R_imu_st
    for f in sim.star_frames:
        k = last[int(np.clip(np.searchsorted(t, f.stamp_ns) - 1, 0, len(t) - 1))]
        if k >= 0:  # the lag, in the tracker's frame
            theta = np.deg2rad(lags[slew[k] % len(lags)] / 3600.0)
            rotate_frame(f, sim.prior.camera, so3_exp(R.T @ (-theta * w[k] / speed[k])))


def thermal_mount(sim, arcsec_per_c: float, angle_deg: float = 30.0) -> None:
    """The mount turning with the tracker head's temperature (not with gravity).

    Every star of a frame turned (:func:`turn_frame`) by ``arcsec_per_c`` per °C of the
    head's temperature off the scenario's reference, along ``angle_deg``; no gyro sees it.
    With the head cooling 30 -> 11 °C (τ 100 s) and 2″/°C: +20″ at the start, −18″ at the
    end; a 300 s run's evaluation window (150-300 s) holds 14.5 -> 11.0 °C: 7″ (0.13 px).
    The library's thermal effect is the focal length's (radial); none turns the mount.
    """
    ht = sim.head_temperature
    ref = sim.truth_world.scenario.head_temperature_ref_c
    for f in sim.star_frames:
        temp = float(np.interp(f.stamp_ns, ht.stamp_ns, ht.value))
        turn_frame(f, sim.prior.camera, arcsec_per_c * (temp - ref), angle_deg)


def lens_zone(sim, radius_px: float, ppm: float) -> None:
    """Beyond ``radius_px`` from the prior's principal point the image scale ``ppm`` larger.

    A lens with a zone (a second focal length for its outer part): a radial step of
    ``ppm·radius`` px at the radius, growing outward; no polynomial distortion of the
    library has a step (unseen case ``lens_zone``).
    """
    cam = sim.prior.camera
    c = np.array([cam.cx, cam.cy])
    for f in sim.star_frames:
        d = np.asarray(f.uv, dtype=float) - c
        out = np.hypot(d[:, 0], d[:, 1]) > radius_px
        f.uv = c + d * (1.0 + ppm * 1e-6 * out)[:, None]


def vibration(sim, amplitude_px: float, hz: float, phase: float) -> None:
    """The tracker's attitude vibrating against the IMU at ``hz`` (no gyro sees it).

    Every star of a frame shifted by ``amplitude_px`` along a circle, u and v a quarter
    period apart (``A (sin φ, cos φ)``, ``φ = 2π hz t + phase``, ``t`` from the first
    frame): a resonance of the mount, which the frames sample (aliased where ``hz`` is
    above half their rate).
    """
    t0 = sim.star_frames[0].stamp_ns
    for f in sim.star_frames:
        ph = 2.0 * np.pi * hz * (f.stamp_ns - t0) * 1e-9 + phase
        f.uv = np.asarray(f.uv, dtype=float) + amplitude_px * np.array([np.sin(ph),
                                                                        np.cos(ph)])
