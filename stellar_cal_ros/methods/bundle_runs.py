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

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from stellar_cal_ros.io.calibration import Calibration
from stellar_cal_ros.methods.bundle import (
    BASELINE_EFFECTS,
    STAGES,
    BundleResult,
    run_bundle,
)
from stellar_cal_ros.methods.bundle_cv import HeldOut
from stellar_cal_ros.methods.kernel import FrameUpdate
from stellar_cal_ros.methods.registry import BatchOutput, MethodSpec
from stellar_cal_ros.methods.results import RunStats
from stellar_cal_ros.methods.star_model import StarModel


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
        from stellar_cal_ros.methods.bundle_cv import cross_validate

        held = result.held_out = cross_validate(result)
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
                      ) -> BundleRun:
    """The diagnosis' runner for the bundle (the filters' runner signature).

    ``eval_fraction`` is unused (every frame is held out); ``consider`` is not supported
    (the bundle has no screening pass: every candidate is re-run); ``gyro_fault`` does not
    apply (no IMU).
    """
    if consider:
        from stellar_cal_ros.errors import ModelError

        raise ModelError("the bundle method has no consider parameters (no screening)")
    return as_run(run_bundle(data, prior, effects), keep_tables)


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
    res = run_bundle(bag, prior, effects, loss=options.get("loss", "linear"),
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
