"""The ``stellar-cal twin`` command (contract §5): the user's own bag as the test bench."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_twin_parser(sub) -> None:
    """Register ``twin`` on the ``stellar-cal`` subcommand parser."""
    t = sub.add_parser(
        "twin", help="the user's own trajectory, stamps, stars and measured noise "
                     "re-rendered with effects injected (plus TWIN.truth.yaml)")
    t.add_argument("bag", type=Path, help="the user's contract bag")
    t.add_argument("--calibration", required=True, type=Path,
                   help="RESULT.yaml of a run on the bag (replay, or discover's "
                        "calibration.yaml): the twin's calibration and measured noise")
    t.add_argument("-o", "--output", required=True, type=Path, help="TWIN.mcap to write")
    t.add_argument("--effect", action="append", metavar="ID=VALUE[,VALUE...]",
                   help="inject an effect on top of the calibration (repeatable; the units "
                        "of `simulate --effect`, `stellar-cal effects`); also the "
                        "simulator-only magnitude_bias and mount_flexure")
    t.add_argument("--method", choices=["psce", "swaying_base"], default=None,
                   help="whose baseline model and noise defaults (default: the "
                        "calibration's method)")
    t.add_argument("--seed", type=int, default=0, help="noise seed (same seed: paired twins)")
    t.add_argument("--effect-module", type=Path, action="append",
                   help="Python file defining extra Effect classes (repeatable)")
    from stellar_cal_ros.errors import on_error_argument

    on_error_argument(t, "re-render")
    t.set_defaults(func=_cmd_twin)


def noise_line(noise) -> str:
    """The one line saying which noise a twin renders (its :class:`NoiseScales`)."""
    n = noise.within_frames()
    star = f"stars' sigma x{n.star:.3g} of the messages'"
    if n.unknown_sigma_px:
        star += f" (sigma-0 stars {n.unknown_sigma_px:.3g} px)"
    if n.group_by:
        star += f", per {n.group_by} x" + ", x".join(f"{f:.3g}" for f in n.factors)
    if noise.star_rho and noise.star_ar_share != 1.0:
        star += (f", correlated from frame to frame along each star's track (white + AR(1): "
                 f"an AR(1) of coefficient {noise.star_rho:.2f} carrying "
                 f"{noise.star_ar_share:.2f} of the variance; a white-noise filter needs "
                 f"x{noise.star:.3g})")
    elif noise.star_rho:
        star += (f", correlated from frame to frame along each star's track (AR(1), lag-1 "
                 f"rho {noise.star_rho:.2f}; a white-noise filter needs x{noise.star:.3g})")
    else:
        star += ", white"
    stamps = f"; the frames' stamps off by {noise.stamp_ms:.2g} ms rms" \
        if noise.stamp_ms else ""
    if noise.frame_px:
        stamps += f"; each frame's stars shifted together by {noise.frame_px:.2g} px rms per axis"
    return (f"{star}; gyro x{noise.gyro:.3g}, accelerometer x{noise.accel:.3g} "
            f"(white; 1 = as stated){stamps}")


def _cmd_twin(args: argparse.Namespace) -> int:
    from stellar_cal_ros.diagnosis.twin import make_twin, write_twin
    from stellar_cal_ros.effects import registry
    from stellar_cal_ros.io.calibration import load_calibration
    from stellar_cal_ros.methods.frames import read_bag_data
    from stellar_cal_ros.sim.truth_effects import parse_effect_arguments

    for path in args.effect_module or []:
        registry.load_effect_module(path)
    effects = parse_effect_arguments(args.effect or [])
    cal = load_calibration(args.calibration)
    data = read_bag_data(args.bag, on_error=args.on_error)
    twin = make_twin(data, cal, effects, args.seed, args.method)
    paths = write_twin(twin, args.output)
    print(f"twin of {args.bag}: {len(twin.data.frames)} star frames "
          f"({twin.counts['stars']} stars; {twin.counts['unidentified_left_out']} unidentified "
          f"left out, {twin.counts['off_detector']} moved off the detector), "
          f"{len(twin.data.imu_t)} IMU samples")
    print("noise: " + noise_line(twin.noise))
    print("injected: " + (", ".join(f"{k}={','.join(f'{x:g}' for x in v)}"
                                     for k, v in effects.items()) or "nothing"))
    from stellar_cal_ros.methods.results import loss_line

    lost = loss_line(data.losses_record())
    if lost:  # the twin re-renders what was read: its gaps are the bag's
        print(lost)
    for key in ("bag", "truth", "prior"):
        print(f"  {key:5s} {paths[key]}")
    return 0
