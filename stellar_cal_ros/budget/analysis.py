"""Run an attitude error budget: linear propagation, Monte Carlo and the maximum-error method.

Three views of the same :class:`~stellar_cal_ros.budget.sources.ErrorModel`:

* **star** — the incident-angle error of one star against its incident angle θ (Sun et al.'s
  metric and plots), per source and in total, optical-axis reference (and mounting);
* **frame** — the attitude error of a frame of stars (Wahba, equal weights): cross-boresight
  x, y, roll and total, for the star tracker (optical-axis reference), the tracker's
  mounting, and the IMU-referenced system (installation added);
* **field of view** — the direction error of one star over the detector.

Each by linear propagation (analytic Jacobians), by Monte Carlo (exact projection and
Wahba, parameter errors drawn from the covariance) and by the maximum-error method (the
parameter error on its k-σ ellipsoid, the worst direction; Sun et al. §3.3.2).  All angles
in the returned dictionary are arcsec.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from stellar_cal_ros.budget.propagation import (
    CONVENTIONS,
    StarField,
    frame_attitude_errors,
    frame_attitude_jacobians,
    linear_star_jacobians,
    radial_rows,
    random_frames,
    ring_directions,
    star_angle_errors,
)
from stellar_cal_ros.budget.sources import CENTROID, ErrorModel
from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.errors import ModelError

__all__ = ["TOTAL", "BudgetOptions", "axes_rms", "default_reference_angle", "run_budget"]

TOTAL = "total"


@dataclass
class BudgetOptions:
    """Settings of a budget run.

    Attributes
    ----------
    frames : int
        Random frames for the linear frame statistics.
    stars_per_frame : int
        Stars per frame, uniformly over the detector.
    draws : int
        Monte-Carlo draws per source (0: no Monte Carlo).
    mc_frames : int or None
        Frames evaluated per Monte-Carlo draw (the first ones of the linear set; None: all,
        so that Monte Carlo and linear average over the same geometries).
    seed : int
        Seed of every random draw.
    reference_angle_deg : float or None
        Incident angle of the per-star table (default: the half field along u).
    max_angle_deg : float or None
        Largest incident angle of the curves (default: the detector's corner).
    angles : int
        Incident angles on the curves.
    azimuths : int
        Azimuths per incident angle (linear and max-error).
    max_error_k : float
        The maximum-error method puts each source on its ``k``-σ ellipsoid.
    max_error_directions : int
        Directions tried on that ellipsoid (2-parameter sources: a circle).
    """

    frames: int = 100
    stars_per_frame: int = 10
    draws: int = 1000
    mc_frames: int | None = None
    seed: int = 0
    reference_angle_deg: float | None = None
    max_angle_deg: float | None = None
    angles: int = 24
    azimuths: int = 36
    max_error_k: float = 3.0
    max_error_directions: int = 36


def default_reference_angle(camera) -> float:
    """Half the field of view along u, deg (the edge of the detector's width)."""
    return math.degrees(math.atan(0.5 * camera.width / camera.fx))


def _corner_angle(camera) -> float:
    return math.degrees(math.atan(math.hypot(0.5 * camera.width / camera.fx,
                                             0.5 * camera.height / camera.fy)))


def axes_rms(var: np.ndarray) -> dict[str, float]:
    """x, y, cross-boresight (per axis), roll and total RMS (arcsec) from mean variances."""
    vx, vy, vz = (float(v) for v in var)
    return {k: math.sqrt(max(v, 0.0)) / ARCSEC for k, v in (
        ("x", vx), ("y", vy), ("cross", 0.5 * (vx + vy)), ("roll", vz),
        ("total", vx + vy + vz))}


def _covariances(model: ErrorModel, sources: list[str]) -> dict[str, np.ndarray | None]:
    return {s: model.parameter_covariance(None if s == TOTAL else s) for s in sources}


def _uses_centroid(model: ErrorModel, source: str) -> bool:
    return model.centroid_sigma_px > 0 and source in (CENTROID, TOTAL)


def _frame_linear(model, field, sources, covs, k):
    out = {}
    for conv in CONVENTIONS:
        T, W = frame_attitude_jacobians(field, model.camera, conv)
        noise = model.centroid_sigma_px**2 * np.einsum("fkil,fkjl->fij", W, W)
        lin, worst = {}, {}
        for s in sources:
            P = T @ covs[s] @ T.transpose(0, 2, 1)
            if _uses_centroid(model, s):
                P = P + noise
            lin[s] = axes_rms(np.mean(np.diagonal(P, axis1=1, axis2=2), axis=0))
            top = k * np.sqrt(np.clip(np.linalg.eigvalsh(P)[:, -1], 0.0, None)) / ARCSEC
            worst[s] = {"mean": float(np.mean(top)), "max": float(np.max(top))}
        out[conv] = {"linear": lin, "max_error": worst}
    return out


def _star_linear(model, theta, azimuths, sources, covs):
    """σ of the incident-angle error per θ (rows) for each convention and source."""
    d = ring_directions(theta[:, None], azimuths[None, :]).reshape(-1, 3)
    out = {}
    for conv in ("axis", "mounting"):
        E, G = linear_star_jacobians(model.camera, d, conv)
        R, Rn = radial_rows(d, E), radial_rows(d, G)
        noise = model.centroid_sigma_px**2 * np.sum(Rn * Rn, axis=1)
        per = {}
        for s in sources:
            v = np.einsum("ni,ij,nj->n", R, covs[s], R)
            if _uses_centroid(model, s):
                v = v + noise
            per[s] = np.sqrt(v.reshape(len(theta), -1).mean(axis=1)) / ARCSEC
        out[conv] = per
    return out


def _monte_carlo(model, field, theta, sources, opt, rng):
    """Exact errors for ``opt.draws`` parameter draws per source."""
    n_mc = field.frames if opt.mc_frames is None else opt.mc_frames
    mc_field = StarField(field.uv[:n_mc], field.directions[:n_mc])
    F, n = mc_field.frames, mc_field.stars_per_frame
    sc = model.centroid_sigma_px
    frame, star = {}, {}
    for s in sources:
        draw = model.sampler(None if s == TOTAL else s)
        sq = {conv: np.zeros(3) for conv in CONVENTIONS}
        errs = np.empty((opt.draws, len(theta)))
        for i in range(opt.draws):
            dx, centroid = draw(rng)
            noise = rng.normal(0.0, sc, (F, n, 2)) if centroid else None
            e = frame_attitude_errors(model.camera, mc_field, dx, noise)
            for conv in CONVENTIONS:
                sq[conv] += np.sum(e[conv] ** 2, axis=0)
            dirs = ring_directions(theta, rng.uniform(0.0, 2.0 * np.pi, len(theta)))
            star_noise = rng.normal(0.0, sc, (len(theta), 2)) if centroid else None
            errs[i] = star_angle_errors(model.camera, dirs, dx, star_noise, "axis")
        frame[s] = {conv: axes_rms(sq[conv] / (opt.draws * F)) for conv in CONVENTIONS}
        star[s] = {"mean": np.mean(errs, axis=0) / ARCSEC,
                   "sigma": np.std(errs, axis=0, ddof=1) / ARCSEC}
    return frame, star


def _unit_directions(k: int, count: int, worst: np.ndarray, rng) -> np.ndarray:
    """Directions on the unit sphere of R^k to try for the maximum error."""
    if k == 1:
        return np.array([[1.0], [-1.0]])
    if k == 2:
        a = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
        return np.stack([np.cos(a), np.sin(a)], axis=1)
    r = rng.standard_normal((count, k))
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    return np.vstack([worst, -worst, r])


def _max_error(model, theta, azimuths, sources, opt, rng):
    """Largest |incident-angle error| over the k-σ ellipsoid and the azimuth, per θ."""
    d = ring_directions(theta[:, None], azimuths[None, :]).reshape(-1, 3)
    E, _ = linear_star_jacobians(model.camera, d, "axis")
    R = radial_rows(d, E)
    out = {}
    for s in sources:
        if s == TOTAL:
            continue
        best = np.zeros(len(theta))
        if s == CENTROID:
            a = np.linspace(0.0, 2.0 * np.pi, opt.max_error_directions, endpoint=False)
            for ang in a:
                noise = np.tile(opt.max_error_k * model.centroid_sigma_px
                                * np.array([np.cos(ang), np.sin(ang)]), (len(d), 1))
                err = star_angle_errors(model.camera, d, np.zeros(21), noise, "axis")
                best = np.maximum(best, np.abs(err).reshape(len(theta), -1).max(axis=1))
        else:
            D, C = model.block(s)
            w, V = np.linalg.eigh(C)
            L = V * np.sqrt(np.clip(w, 0.0, None))
            # worst direction of the linear model at the reference angle row
            M = (R @ D @ L)
            worst = np.linalg.svd(M, full_matrices=False)[2][0]
            for u in _unit_directions(D.shape[1], opt.max_error_directions, worst, rng):
                dx = D @ (opt.max_error_k * (L @ u))
                err = star_angle_errors(model.camera, d, dx, None, "axis")
                best = np.maximum(best, np.abs(err).reshape(len(theta), -1).max(axis=1))
        out[s] = best / ARCSEC
    return out


def _fov_map(model, covs, steps: int = 24):
    """RMS direction error of one star over the detector from the calibration errors.

    The centroid noise, the same everywhere, is left out so that their pattern shows.
    """
    cam = model.camera
    u = np.linspace(0.0, cam.width - 1.0, steps)
    v = np.linspace(0.0, cam.height - 1.0, steps)
    uv = np.stack(np.meshgrid(u, v), axis=-1).reshape(-1, 2)
    d = cam.unproject(uv)
    out = {"u": u.tolist(), "v": v.tolist()}
    for conv in ("axis", "system"):
        E, G = linear_star_jacobians(cam, d, conv)
        var = np.einsum("nip,pq,niq->n", E, covs[TOTAL], E)  # calibration errors only
        out[conv] = (np.sqrt(var) / ARCSEC).reshape(steps, steps).tolist()
    return out


def run_budget(model: ErrorModel, options: BudgetOptions | None = None) -> dict:
    """Compute the budget (see the module docstring); angles in arcsec.

    Parameters
    ----------
    model : ErrorModel
        The error sources.
    options : BudgetOptions, optional
        Settings (default: :class:`BudgetOptions`).

    Returns
    -------
    dict
        JSON-serialisable: ``camera``, ``origin``, ``notes``, ``parameters``, ``sources``,
        ``star`` (the table at the reference angle), ``frame`` (per convention),
        ``curves`` (against the incident angle) and ``fov_map``.
    """
    opt = options or BudgetOptions()
    if opt.stars_per_frame < 3 or opt.frames < 1:
        raise ModelError("a budget needs frames >= 1 and stars_per_frame >= 3 (the roll)")
    cam = model.camera
    rng = np.random.default_rng(opt.seed)
    ref = opt.reference_angle_deg if opt.reference_angle_deg is not None else \
        default_reference_angle(cam)
    top = opt.max_angle_deg if opt.max_angle_deg is not None else _corner_angle(cam)
    grid = np.linspace(top / opt.angles, top, opt.angles)
    theta = np.deg2rad(np.concatenate([grid, [ref]]))
    azimuths = (np.arange(opt.azimuths) + 0.5) * 2.0 * np.pi / opt.azimuths
    sources = model.sources() + [TOTAL]
    covs = _covariances(model, sources)
    field = random_frames(cam, opt.frames, opt.stars_per_frame, rng)

    frame = _frame_linear(model, field, sources, covs, opt.max_error_k)
    star_lin = _star_linear(model, theta, azimuths, sources, covs)
    worst = _max_error(model, theta, azimuths, sources, opt, rng)
    mc_frame, mc_star = ({}, {}) if opt.draws <= 0 else _monte_carlo(
        model, field, theta, sources, opt, rng)
    for conv in CONVENTIONS:
        frame[conv]["mc"] = {s: mc_frame[s][conv] for s in mc_frame}

    def at_ref(a: np.ndarray) -> float:
        return float(a[-1])

    sig = np.sqrt(np.diag(model.covariance))
    return {
        "format": "stellar_cal_budget/1",
        "origin": model.origin,
        "notes": list(model.notes),
        "camera": {"width": cam.width, "height": cam.height, "fx": cam.fx, "fy": cam.fy,
                   "cx": cam.cx, "cy": cam.cy,
                   "field_of_view_deg": [2 * default_reference_angle(cam),
                                         2 * math.degrees(math.atan(0.5 * cam.height
                                                                    / cam.fy))]},
        "options": asdict(opt) | {"reference_angle_deg": ref, "max_angle_deg": top},
        "parameters": [{"name": n, "sigma": float(s), "source": g}
                       for g, cols in model.groups.items()
                       for n, s in ((model.names[c], sig[c]) for c in cols)],
        "centroid_sigma_px": model.centroid_sigma_px,
        "sources": sources,
        "star": {
            "reference_angle_deg": ref,
            "linear": {s: at_ref(star_lin["axis"][s]) for s in sources},
            "linear_mounting": {s: at_ref(star_lin["mounting"][s]) for s in sources},
            "mc": {s: {"mean": at_ref(v["mean"]), "sigma": at_ref(v["sigma"]),
                       "standard_error": at_ref(v["sigma"]) / math.sqrt(2 * (opt.draws - 1))}
                   for s, v in mc_star.items()},
            "max_error": {s: at_ref(v) for s, v in worst.items()},
        },
        "frame": frame,
        "curves": {
            "angles_deg": grid.tolist(),
            "linear": {conv: {s: v[:-1].tolist() for s, v in per.items()}
                       for conv, per in star_lin.items()},
            "mc": {s: v["sigma"][:-1].tolist() for s, v in mc_star.items()},
            "max_error": {s: v[:-1].tolist() for s, v in worst.items()},
        },
        "fov_map": _fov_map(model, covs),
    }
