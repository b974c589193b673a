"""``stellar-cal batch BAG --method bundle``: the command around :func:`run_bundle`."""

from __future__ import annotations

import argparse

import numpy as np


def cmd_batch_bundle(args: argparse.Namespace, prior) -> int:
    """Run the bundle, write RESULT.yaml (+ covariance, residuals), print the summary."""
    from stellar_cal_ros.io.calibration import save_calibration
    from stellar_cal_ros.io.residuals import write_residuals
    from stellar_cal_ros.methods.bundle import run_bundle
    from stellar_cal_ros.progress import progress

    effects = [e.strip() for e in (args.effects or "").split(",") if e.strip()]
    if args.residuals is not None and args.residuals.suffix.lower() == ".parquet":
        write_residuals(args.residuals, {"probe": np.zeros(0)})  # fail early without pyarrow
    with progress(3, "bundle", unit="stages", enabled=not args.quiet) as p:
        def stage_done(text: str) -> None:
            p.update(1)
            p.note(f"bundle: {text}")

        p.note("bundle: reading the bag", eta=False)
        res = run_bundle(args.bag, prior, effects, loss=args.loss,
                         outlier_probability=args.outlier_probability or None,
                         progress=stage_done)
    save_calibration(res.calibration, args.output,
                     covariance=(res.parameter_names, res.covariance))
    if args.residuals is not None:
        write_residuals(args.residuals, res.residuals)
    print_bundle_summary(res)
    print(f"wrote {args.output}" + (f" and {args.residuals}" if args.residuals else "")
          + f" (covariance: {args.output.with_suffix('').name}.covariance.yaml)")
    return 0


def print_bundle_summary(res) -> None:
    """Human summary of a bundle result: fit, parameters ± σ, the held-out RMS."""
    from stellar_cal_ros.methods.bundle import BASELINE_EFFECTS

    c = res.counts
    n_stars = int((~res.residuals["gated"]).sum())
    print(f"bundle: {len(res.frames)} of {c.frames_read} frames ({c.frames_few_stars} with too "
          f"few stars), {n_stars} stars ({c.stars_misidentified} misidentified, "
          f"{c.stars_outliers} outliers left out; {c.stars_unidentified} unidentified and "
          f"{c.stars_unusable} unusable not fitted), RMS |duv| {res.rms_px:.4f} px, "
          f"sigma-hat {res.sigma_px:.4f} px (variance factor {res.variance_factor:.3g}), "
          f"{res.iterations} iterations, loss {res.loss}")
    extra = [e.id for e in res.model.effects if e.id not in BASELINE_EFFECTS]
    print("model: " + ", ".join(BASELINE_EFFECTS) + (" + " + ", ".join(extra) if extra
                                                     else ""))
    for reason in res.degraded:
        print(f"result degraded: {reason}")
    for name, value, sigma, sp in zip(res.parameter_names, res.theta, res.sigma,
                                      res.sigma_prior, strict=True):
        note = "  (prior-dominated)" if sigma > 0.5 * sp else ""
        print(f"  {name:28s} {value:+.8g} ± {sig(sigma)}{note}")
    cv = res.cross_validation
    if cv:
        per = " ".join(f"{v:.2f}" for v in cv["held_out_rms_arcsec"])
        print(f"held-out RMS (each frame alone, camera from the others): mean "
              f"{cv['mean_arcsec']:.3f} arcsec; per frame: {per}")
        if any(cv["rejected"]):
            print(f"  stars beyond 5x the frame's median left out: {sum(cv['rejected'])} "
                  f"(per frame: {' '.join(map(str, cv['rejected']))})")


def sig(x: float) -> str:
    """A σ with 3 significant digits."""
    return f"{x:.3g}"
