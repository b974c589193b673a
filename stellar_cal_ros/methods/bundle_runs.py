"""The bundle method's spec: its batch command and its runs as the diagnosis sees them.

``METHOD`` registers ``bundle`` (:mod:`~stellar_cal_ros.methods.registry`):
``stellar-cal batch --method bundle`` runs :func:`batch` (the solver:
:mod:`~stellar_cal_ros.methods.bundle`), ``diagnose``/``discover --method bundle`` run
:func:`run_for_diagnosis`, in which held-out residuals take the innovations' place.

The diagnosis (``diagnose`` / ``discover``) compares models by a *prequential* likelihood:
each measurement predicted by an estimate that has not seen it.  For the Kalman filters
those are the innovations; for the bundle they are the leave-one-frame-out residuals of
:mod:`~stellar_cal_ros.methods.bundle_cv` (the camera from the other frames, only the
held-out frame's attitude fitted), each with its predicted covariance (noise at the fold's
σ̂, the fold camera's uncertainty, less what the frame's attitude fit absorbs).  So a
flexible effect cannot win by fitting noise, and ``rms_after_px`` is the held-out RMS the
user will see after adding the effect.  Every frame is held out, so the evaluation window
is all frames.

:func:`run_for_diagnosis` returns a :class:`BundleRun`, which holds what
:func:`~stellar_cal_ros.diagnosis.runstats.run_statistics` reads of a filter run: the model,
θ and its covariance, the running statistics (:class:`~stellar_cal_ros.methods.results.
RunStats` over the held-out residuals), the result calibration, counters and the residual
table.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from stellar_cal_ros.errors import StellarCalError
from stellar_cal_ros.io.calibration import Calibration, store_estimate
from stellar_cal_ros.methods.bundle import (
    BASELINE_EFFECTS,
    GATE_DEG,
    MIN_STARS_PER_FRAME,
    OUTLIER_PROBABILITY,
    STAGES,
    BundleCounts,
    BundleResult,
    bundle_frames,
    check_context,
    fit_bundle,
    initial_attitudes,
    make_model,
    residual_table,
)
from stellar_cal_ros.methods.bundle_cv import HeldOut
from stellar_cal_ros.methods.bundle_cv import cross_validate as held_out_folds
from stellar_cal_ros.methods.frames import BagData, read_bag_data
from stellar_cal_ros.methods.kernel import FrameUpdate
from stellar_cal_ros.methods.registry import BatchOutput, MethodSpec
from stellar_cal_ros.methods.results import RunStats
from stellar_cal_ros.methods.star_model import StarModel
from stellar_cal_ros.sky.identify import identify_frames, needs_identification

log = logging.getLogger(__name__)


# ============================================================================ a bag
def _bag_data(source: Any, on_error: str = "raise") -> BagData:
    return source if isinstance(source, BagData) else read_bag_data(
        source, require_imu=False, on_error=on_error)


def identify(data: BagData, prior: Calibration) -> dict[str, float]:
    """Identify unidentified centroids (contract §2) in place; their counts ({} if none).

    Lost-in-space per frame under the prior camera (tracking with the gyro rates when the
    bag has an IMU): :func:`~stellar_cal_ros.sky.identify.identify_frames`.
    """
    if not any(needs_identification(f) for f in data.frames):
        return {}
    data.frames, counters = identify_frames(data.frames, prior.camera,
                                            prior.installation.as_matrix(),
                                            data.imu_stamp_ns, data.imu_w)
    out = counters.as_dict()
    log.info("identification of unidentified centroids: %s", out)
    return out


def run_bundle(
    source: Any,
    prior: Calibration,
    effects: Sequence[str] | None = None,
    *,
    loss: str = "linear",
    outlier_probability: float | None = OUTLIER_PROBABILITY,
    min_stars_per_frame: int = MIN_STARS_PER_FRAME,
    gate_deg: float | None = GATE_DEG,
    cross_validate: bool = True,
    progress: Callable[[str], None] | None = None,
    noise=None,
) -> BundleResult:
    """Calibrate the camera from star frames with a free attitude per frame.

    Parameters
    ----------
    source : path or BagData
        A contract bag (IMU not needed) or its data.
    prior : Calibration
        Starting values and prior σ of the estimated parameters; all else stays fixed
        (including a DIRECTION or CAMERA effect under the prior's ``effects``, applied at
        its value: e.g. ``refraction: {scale: 1.0}`` applies the physical refraction).
    effects : list of str
        Effects added to :data:`BASELINE_EFFECTS` (``-id`` removes an added one).
    loss : {'linear', 'huber', 'soft_l1', 'cauchy'}
        Loss of the final fit on the inliers.
    outlier_probability : float or None
        The outlier gate (None: off).
    min_stars_per_frame : int
        Frames with fewer usable stars are skipped (counted).
    gate_deg : float or None
        Identification gate, deg (None: off).
    cross_validate : bool
        Hold out each frame in turn (:func:`~stellar_cal_ros.methods.bundle_cv.
        cross_validate`) and store ``cross_validation`` in the result.
    progress : callable, optional
        Called with a short text as each stage ends.
    noise : NoiseScales, optional
        Scales of the stars' stated σ (the diagnosis' measured noise).

    Raises
    ------
    StellarCalError
        Too few frames or stars, effects the data cannot see or lack inputs for.
    """
    tell = progress or (lambda text: None)
    data = _bag_data(source)
    model, theta_prior, sigma_prior = make_model(prior, effects)
    identified = identify(data, prior)
    counts = BundleCounts()
    frames = bundle_frames(data, prior, counts, min_stars_per_frame, noise=noise)
    if len(frames) < 2:
        raise StellarCalError(
            f"the bundle method needs at least 2 star frames with >= {min_stars_per_frame} "
            f"identified stars; the bag has {len(frames)} of {counts.frames_read} "
            f"({counts.stars_unidentified} stars unidentified, {counts.stars_unusable} "
            "non-finite or off the detector)")
    check_context(model, frames)
    Rs, counts.stars_misidentified = initial_attitudes(model, theta_prior, frames, gate_deg)
    n_used = sum(int(f.use.sum()) for f in frames)
    if 2 * n_used < 3 * len(frames) + model.size + 1:
        raise StellarCalError(f"too few stars ({n_used}) for {3 * len(frames)} attitude and "
                              f"{model.size} camera unknowns")
    tell("initial attitudes")
    fit, counts.stars_outliers = fit_bundle(model, frames, theta_prior, Rs, theta_prior,
                                            sigma_prior, loss, outlier_probability)
    tell(f"fit ({fit.iterations} iterations)")
    cov, s2 = fit.covariance()
    sig_stated = float(np.median(np.concatenate([f.sigma[f.use] for f in frames])))
    theta = fit.theta
    cal = store_estimate(prior, model.effects, model.slices, theta, np.sqrt(np.diag(cov)),
                         "bundle", float(frames[-1].stamp_ns * 1e-9))
    table = residual_table(fit, frames, np.sqrt(s2) if np.isfinite(s2) else 1.0)
    inl = ~table["gated"]
    rms = float(np.sqrt(np.mean(table["du"][inl] ** 2 + table["dv"][inl] ** 2)))
    result = BundleResult(
        calibration=cal, model=model, theta=theta, covariance=cov,
        parameter_names=model.parameter_names(), variance_factor=s2,
        sigma_px=sig_stated * float(np.sqrt(s2)), rms_px=rms, frames=frames,
        attitudes=fit.attitudes, counts=counts, residuals=table, iterations=fit.iterations,
        loss=loss, theta_prior=theta_prior, sigma_prior=sigma_prior,
        outlier_probability=outlier_probability)
    n_ident = sum(len(f.uv) for f in frames)
    rejected = counts.stars_misidentified + counts.stars_outliers
    if rejected > 0.1 * n_ident:
        result.degraded.append(f"{rejected} of {n_ident} identified stars rejected as "
                               "misidentified or outliers")
    if cross_validate:
        cv = held_out_folds(result)
        result.cross_validation, result.held_out = cv.summary(), cv
        nis = result.cross_validation["nis_per_dof"]
        for k in cv.inconsistent():
            result.degraded.append(
                f"frame {cv.frames[k]} does not share the other frames' camera: held-out "
                f"RMS {cv.scores[k].rms_arcsec:.3g} arcsec, NIS/dof {nis[k]:.3g} against a "
                f"median {float(np.median(np.delete(nis, k))):.3g} of the others (another "
                "focus or zoom, another camera, or wrong identifications): calibrate "
                "without it")
        tell("cross-validation")
    cal.extra = dict(cal.extra)
    cal.extra["data_quality"] = {**{k: v for k, v in counts.as_dict().items() if v},
                                 "degraded": bool(result.degraded),
                                 "reasons": list(result.degraded),
                                 **data.losses_record()}  # (a read past damage)
    if identified:
        cal.extra["identification"] = identified
    cal.extra["fit"] = {"frames": len(frames), "stars": int(inl.sum()),
                        "rms_px": rms, "sigma_px": result.sigma_px,
                        "variance_factor": s2, "loss": loss}
    if result.cross_validation is not None:
        cal.extra["cross_validation"] = result.cross_validation
    return result


# ============================================================================ diagnosis
@dataclass
class EstimateView:
    """The parts of a filter the diagnosis reads: model, θ, covariance, estimated count."""

    model: StarModel
    theta: np.ndarray
    P: np.ndarray
    it: slice
    P_est: int


@dataclass
class BundleRun:
    """A bundle run in the shape of a filter run (see the module docstring)."""

    result: BundleResult
    calibration: Calibration
    filter: EstimateView
    stats: RunStats
    counters: dict[str, int]
    residuals: dict[str, np.ndarray] | None
    derived: dict[str, Any] = field(default_factory=dict)
    history: dict[str, np.ndarray] | None = None  #: a batch fit has no state history


def frame_updates(result: BundleResult, held: HeldOut) -> list[FrameUpdate]:
    """One :class:`FrameUpdate` per held-out frame: its stars' held-out residuals."""
    out = []
    for f, score, S, uv_pred, d in zip(result.frames, held.scores, held.covariance,
                                       held.uv_pred, held.directions, strict=True):
        nu = f.uv - uv_pred
        acc = score.scored & np.all(np.isfinite(nu), axis=1)
        nu0 = np.where(acc[:, None], nu, 0.0)
        Sinv = np.linalg.inv(S)
        nis = np.einsum("ni,nij,nj->n", nu0, Sinv, nu0)
        out.append(FrameUpdate(
            stamp=f.stamp_ns * 1e-9, t_exposure=f.stamp_ns * 1e-9, accepted=acc, uv=f.uv,
            uv_pred=uv_pred, S=S, nis_stars=nis, nis=float(nis[acc].sum()) if acc.any()
            else float("nan"), dof=int(2 * acc.sum()), directions_st=d,
            omega_b=np.zeros(3), iterations=score.iterations))
    return out


def held_out_table(result: BundleResult, updates: list[FrameUpdate]) -> dict[str, np.ndarray]:
    """The residual table of the held-out residuals (the filters' columns).

    :data:`~stellar_cal_ros.methods.results.RESIDUAL_COLUMNS`; ``gated``: not scored (beyond
    5 × the frame's median).
    """
    from stellar_cal_ros.methods.results import residual_rows

    rows = [residual_rows(u, f.index, f.catalog_id, f.magnitude, f.ctx.head_temperature_c)
            for f, u in zip(result.frames, updates, strict=True)]
    return {k: np.concatenate([r[k] for r in rows]) for k in rows[0]} if rows else {}


def held_out_stats(updates: list[FrameUpdate]) -> RunStats:
    """Running statistics over every held-out frame (the whole bag is the window)."""
    stats = RunStats(eval_start=None)
    for u in updates:
        stats.add(u)
    return stats


def as_run(result: BundleResult, keep_tables: bool = True) -> BundleRun:
    """The :class:`BundleRun` of a cross-validated result."""
    held = result.held_out
    if held is None:
        held = result.held_out = held_out_folds(result)
        result.cross_validation = held.summary()
    updates = frame_updates(result, held)
    stats = held_out_stats(updates)
    n = result.model.size
    c = result.counts
    counters = {"frames": c.frames_read, "updates": len(result.frames),
                "skipped_few_stars": c.frames_few_stars, "stars_invalid": c.stars_unusable,
                "stars_bad_sigma": c.stars_bad_sigma,
                "stars_gated": c.stars_misidentified + c.stars_outliers}
    from stellar_cal_ros.methods.results import equivalent_principal_point

    derived = equivalent_principal_point(result.model, result.theta, result.covariance)
    return BundleRun(result, result.calibration,
                     EstimateView(result.model, result.theta, result.covariance,
                                  slice(0, n), n),
                     stats, counters, held_out_table(result, updates) if keep_tables else None,
                     derived)


def run_for_diagnosis(data: Any, prior: Calibration, effects: list[str],
                      keep_tables: bool = False, eval_fraction: float = 0.5,
                      consider: list[str] | None = None, gyro_fault: str = "raise",
                      noise=None) -> BundleRun:
    """The diagnosis' runner for the bundle (the filters' runner signature).

    ``eval_fraction`` is unused (every frame is held out); ``consider`` is not supported
    (the bundle has no screening pass: every candidate is re-run); ``gyro_fault`` does not
    apply (no IMU); ``noise`` scales the stars' σ (its gyro/accelerometer scales do not
    apply).
    """
    if consider:
        from stellar_cal_ros.errors import ModelError

        raise ModelError("the bundle method has no consider parameters (no screening)")
    return as_run(run_bundle(data, prior, effects, noise=noise), keep_tables)


def summary_lines(res: BundleResult) -> list[str]:
    """What ``stellar-cal batch --method bundle`` prints: fit, parameters ± σ, held-out RMS."""
    c = res.counts
    n_stars = int((~res.residuals["gated"]).sum())
    out = [f"bundle: {len(res.frames)} of {c.frames_read} frames ({c.frames_few_stars} with "
           f"too few stars), {n_stars} stars ({c.stars_misidentified} misidentified, "
           f"{c.stars_outliers} outliers left out; {c.stars_unidentified} unidentified and "
           f"{c.stars_unusable} unusable not fitted), RMS |duv| {res.rms_px:.4f} px, "
           f"sigma-hat {res.sigma_px:.4f} px (variance factor {res.variance_factor:.3g}), "
           f"{res.iterations} iterations, loss {res.loss}"]
    extra = [e.id for e in res.model.effects if e.id not in BASELINE_EFFECTS]
    out.append("model: " + ", ".join(BASELINE_EFFECTS)
               + (" + " + ", ".join(extra) if extra else ""))
    out += [f"result degraded: {reason}" for reason in res.degraded]
    for name, value, sigma, sp in zip(res.parameter_names, res.theta, res.sigma,
                                      res.sigma_prior, strict=True):
        note = "  (prior-dominated)" if sigma > 0.5 * sp else ""
        out.append(f"  {name:28s} {value:+.8g} ± {sigma:.3g}{note}")
    cv = res.cross_validation
    if cv:
        per = " ".join(f"{v:.2f}" for v in cv["held_out_rms_arcsec"])
        out.append(f"held-out RMS (each frame alone, camera from the others): mean "
                   f"{cv['mean_arcsec']:.3f} arcsec; per frame: {per}")
        if any(cv["rejected"]):
            out.append(f"  stars beyond 5x the frame's median left out: {sum(cv['rejected'])}"
                       f" (per frame: {' '.join(map(str, cv['rejected']))})")
    return out


def batch(bag: Any, prior: Calibration, effects: list[str], options: dict[str, Any],
          progress: Any) -> BatchOutput:
    """``stellar-cal batch --method bundle``: :func:`run_bundle` with the command's options."""
    res = run_bundle(_bag_data(bag, options.get("on_error", "raise")), prior, effects,
                     loss=options.get("loss", "linear"),
                     outlier_probability=options.get("outlier_probability"),
                     progress=progress)
    return BatchOutput(res.calibration, (res.parameter_names, res.covariance), res.residuals,
                       summary_lines(res), res)


METHOD = MethodSpec(
    name="bundle", kind="batch",
    summary="star frames alone (no IMU): one free attitude per frame and one camera, with "
            "leave-one-frame-out cross-validation",
    baseline=BASELINE_EFFECTS, stages=STAGES, batch=batch,
    steps=("initial attitudes", "fit", "cross-validation"), runner=run_for_diagnosis)
