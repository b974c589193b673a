"""``stellar-cal budget``: attitude error budget of a result file or of a spec of σ's.

Kept light at import (the parser is built for every ``stellar-cal`` command); numpy-heavy
modules are imported when the command runs.
"""

from __future__ import annotations

import argparse
from pathlib import Path

#: The replay's default centroid noise (``PsceConfig.centroid_sigma_px``), px.
DEFAULT_CENTROID_SIGMA_PX = 0.05


def add_budget_parser(sub) -> None:
    """Add the ``budget`` subcommand to ``stellar-cal``'s subparsers."""
    b = sub.add_parser(
        "budget", help="attitude error budget: per source, linear, Monte Carlo, max error",
        description="Attitude error of the star tracker and of the IMU-referenced system "
                    "caused by calibration errors (principal point, focal length, distortion, "
                    "image-plane tilt, installation) and centroid noise: per star against "
                    "the incident angle, and per frame (Wahba); see doc/budget.md.")
    b.add_argument("result", type=Path, nargs="?", help="RESULT.yaml (a calibration result)")
    b.add_argument("--spec", type=Path, help="SPEC.yaml: a camera and a sigma per source "
                   "(instead of a result)")
    b.add_argument("--covariance", type=Path, default=None,
                   help="covariance file (names + matrix); default RESULT.covariance.* if "
                        "present, else the diagonal of the result's sigma block")
    b.add_argument("--prior", type=Path, default=None,
                   help="the run's prior: tells which parameters the run did not estimate "
                        "(held at the prior); see --unestimated")
    b.add_argument("--unestimated", choices=["exclude", "include"], default="exclude",
                   help="with --prior: leave the parameters the run did not estimate out "
                        "(default; listed) or include them with the prior's sigma")
    b.add_argument("--exclude", default="", help="comma-separated parameters to leave out "
                   "(e.g. k3 or radial_k3.k3)")
    b.add_argument("--centroid-sigma", type=float, default=None,
                   help=f"centroid noise per axis, px (result default "
                        f"{DEFAULT_CENTROID_SIGMA_PX}; 0: leave it out)")
    b.add_argument("--stars-per-frame", type=int, default=None, help="default 10")
    b.add_argument("--frames", type=int, default=None, help="random frames (default 100)")
    b.add_argument("--draws", type=int, default=None,
                   help="Monte-Carlo draws per source (default 1000; 0: linear only)")
    b.add_argument("--seed", type=int, default=None,
                   help="seed of the Monte-Carlo draws (default: fresh each run)")
    b.add_argument("--reference-angle", type=float, default=None, metavar="DEG",
                   help="incident angle of the per-star table (default: half the field "
                        "along u)")
    b.add_argument("-o", "--output", type=Path, default=None,
                   help="OUT_DIR for budget.json and the plots")
    b.add_argument("--no-plots", action="store_true",
                   help="budget.json only, no PNG figures")
    b.set_defaults(func=run_budget_command)


def _options(args: argparse.Namespace, spec: dict):
    from stellar_cal_ros.budget.analysis import BudgetOptions
    from stellar_cal_ros.errors import StellarCalError

    opt = BudgetOptions()
    for key, attr, kind in (("stars_per_frame", "stars_per_frame", int),
                            ("frames", "frames", int), ("draws", "draws", int),
                            ("seed", "seed", int),
                            ("reference_angle_deg", "reference_angle", float)):
        value = getattr(args, attr)
        if value is None:
            value = spec.get(key)
        if value is not None:
            try:
                setattr(opt, key, kind(value))
            except (TypeError, ValueError):
                raise StellarCalError(f"{key} must be a number, got {value!r}") from None
    return opt


def build_error_model(args: argparse.Namespace):
    """The :class:`ErrorModel` and the spec dict (empty for a result) of the command line."""
    from stellar_cal_ros.budget import sources as src
    from stellar_cal_ros.errors import StellarCalError
    from stellar_cal_ros.io.calibration import load_calibration

    exclude = [e.strip() for e in args.exclude.split(",") if e.strip()]
    if (args.result is None) == (args.spec is None):
        raise StellarCalError("give either RESULT.yaml or --spec SPEC.yaml")
    if args.spec is not None:
        spec = src.read_spec(args.spec)
        camera = src.spec_camera(spec, args.spec.parent)
        from stellar_cal_ros.budget.analysis import default_reference_angle

        ref = args.reference_angle if args.reference_angle is not None else spec.get(
            "reference_angle_deg", default_reference_angle(camera))
        model = src.error_model_from_spec(spec, camera, float(ref))
        if args.centroid_sigma is not None:
            model.centroid_sigma_px = args.centroid_sigma
        return model, spec
    cal = load_calibration(args.result)
    cov_path = args.covariance or src.find_covariance(args.result)
    covariance = src.load_covariance(cov_path) if cov_path is not None else None
    prior = load_calibration(args.prior) if args.prior is not None else None
    centroid = DEFAULT_CENTROID_SIGMA_PX if args.centroid_sigma is None else args.centroid_sigma
    model = src.error_model_from_result(cal, covariance, str(cov_path or ""), prior, exclude,
                                        centroid, args.unestimated)
    if args.centroid_sigma is None:
        model.notes.append(f"centroid noise {centroid} px per axis assumed (--centroid-sigma)")
    if covariance is None and prior is None:
        model.notes.append("the sigma block repeats the prior's sigma for parameters the run "
                           "did not estimate; give --prior or --exclude to leave them out")
    return model, {}


def run_budget_command(args: argparse.Namespace) -> int:
    """Run ``stellar-cal budget``."""
    from stellar_cal_ros.budget.analysis import run_budget
    from stellar_cal_ros.budget.report import format_budget, write_budget

    model, spec = build_error_model(args)
    budget = run_budget(model, _options(args, spec))
    print(format_budget(budget))
    if args.output is not None:
        paths = write_budget(budget, args.output, plots=not args.no_plots)
        print("wrote " + ", ".join(str(p) for p in paths))
    return 0
