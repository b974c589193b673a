"""The ``stellar-cal`` command line (INTERFACES.md §5).

Commands
--------
simulate   write a synthetic contract bag + ``*.truth.yaml`` + ``*.prior.yaml``
info       list the topics, message counts and time span of a bag
replay     Kalman-filter calibration over a bag (psce, swaying_base)
batch      attitude-correlated-frames batch calibration
diagnose   compare model and measurements, rank missing effects
demo       the built-in end-to-end demonstration

Every error raised on purpose (:class:`stellar_cal_ros.errors.StellarCalError`) is printed as
one clear line and gives exit status 1; a usage error gives 2.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from stellar_cal_ros import __version__
from stellar_cal_ros.errors import StellarCalError

log = logging.getLogger("stellar_cal_ros")


def _cmd_simulate(args: argparse.Namespace) -> int:
    from stellar_cal_ros.sim.scenarios import get_scenario
    from stellar_cal_ros.sim.truth_effects import parse_effect_arguments
    from stellar_cal_ros.sim.world import simulate, write_simulation

    scenario = get_scenario(args.scenario)
    effects = parse_effect_arguments(args.effect or [])
    t_start = time.perf_counter()
    result = simulate(scenario, duration=args.duration, seed=args.seed, effects=effects)
    t_sim = time.perf_counter() - t_start
    paths = write_simulation(result, args.output)
    t_all = time.perf_counter() - t_start
    m = result.meta
    print(
        f"simulated {m['scenario']}: {m['duration_s']:.0f} s, "
        f"{m['counts']['/imu/data']} IMU samples, {m['counts']['/star_tracker/stars']} star "
        f"frames ({m['stars_per_frame']['mean']:.1f} stars/frame) in {t_sim:.1f} s "
        f"(+{t_all - t_sim:.1f} s writing)"
    )
    for key in ("bag", "truth", "prior", "meta"):
        print(f"  {key:5s} {paths[key]}")
    return 0


def _cmd_info(args: argparse.Namespace) -> int:
    from stellar_cal_ros.io.bag import BagReader

    with BagReader(args.bag) as reader:
        topics = reader.topics()
        span = (reader.end_ns - reader.start_ns) * 1e-9
        print(f"{args.bag}: {span:.3f} s, {len(topics)} topics")
        for name, info in sorted(topics.items()):
            print(f"  {name:32s} {info.schema_name:40s} {info.message_count:8d}")
    return 0


def _effect_list(text: str) -> list[str]:
    return [e.strip() for e in (text or "").split(",") if e.strip()]


def _load_effect_modules(paths: list[Path] | None) -> None:
    from stellar_cal_ros.effects import registry

    for path in paths or []:
        ids = registry.load_effect_module(path)
        log.info("loaded effects %s from %s", ", ".join(ids), path)


def _cmd_replay(args: argparse.Namespace) -> int:
    from stellar_cal_ros.io.calibration import load_calibration, save_calibration
    from stellar_cal_ros.io.residuals import write_residuals
    from stellar_cal_ros.methods.psce import PsceConfig
    from stellar_cal_ros.methods.replay import replay_psce

    _load_effect_modules(args.effect_module)
    prior = load_calibration(args.prior)
    if args.init_from is not None:
        from stellar_cal_ros.methods.acf import prior_from_result

        prior = prior_from_result(prior, load_calibration(args.init_from), args.init_from)
    effects = _effect_list(args.effects)
    if args.method == "swaying_base":
        from stellar_cal_ros.methods.swaying import cli_replay

        return cli_replay(args, prior, effects)
    if args.method != "psce":
        raise StellarCalError(f"replay --method {args.method} is not implemented")
    config = PsceConfig()
    if args.centroid_sigma is not None:
        config.centroid_sigma_px = args.centroid_sigma
    if args.gyro_arw is not None:
        config.gyro_arw_deg_sqrth = args.gyro_arw
    from stellar_cal_ros.methods.replay import read_bag_data

    data = read_bag_data(args.bag, on_error=args.on_error)
    result = replay_psce(data, prior, effects, config, progress=not args.quiet)
    save_calibration(result.calibration, args.output)
    if args.residuals:
        write_residuals(args.residuals, result.residuals)
    history_path = args.history or args.output.with_suffix(".history.csv")
    write_residuals(history_path, result.history)
    _print_replay_summary(result, args)
    return 0


def _print_replay_summary(result, args: argparse.Namespace) -> None:
    import numpy as np

    res = result.residuals
    ok = ~res["gated"].astype(bool) if len(res["gated"]) else np.zeros(0, bool)
    half = len(ok) // 2
    du, dv = res["du"][half:][ok[half:]], res["dv"][half:][ok[half:]]
    rms = (float(np.sqrt(np.mean(du**2))), float(np.sqrt(np.mean(dv**2)))) if du.size else (
        float("nan"),) * 2
    hist = result.history
    nis = float(np.sum(hist["nis"]) / max(np.sum(hist["dof"]), 1)) if len(hist["nis"]) else \
        float("nan")
    print(f"replayed {result.duration:.0f} s in {result.read_seconds:.2f} s reading + "
          f"{result.filter_seconds:.2f} s filtering = {result.speed:.0f}x real time")
    print(f"innovation RMS (second half, accepted stars): u={rms[0]:.4f} v={rms[1]:.4f} px; "
          f"NIS/dof {nis:.3f}")
    counts = ", ".join(f"{k}={v}" for k, v in result.counters.items() if v)
    print(f"counts: {counts}")
    cal = result.calibration
    cam = cal.camera
    print(f"camera: fx={cam.fx:.3f} fy={cam.fy:.3f} cx={cam.cx:.3f} cy={cam.cy:.3f} px, "
          f"distortion {cam.distortion_model()} "
          + " ".join(f"{v:.4g}" for v in cam.to_yaml_dict()["distortion_coefficients"]["data"]))
    eq = result.derived
    print("equivalent principal point: ({:.3f}, {:.3f}) +- ({:.3f}, {:.3f}) px".format(
        *eq["equivalent_principal_point_px"], *eq["equivalent_principal_point_sigma_px"]))
    print(f"installation quaternion_xyzw: {np.round(cal.installation.as_quat(), 9).tolist()}")
    print(f"gyro bias: {np.round(np.rad2deg(cal.gyro_bias) * 3600, 5).tolist()} deg/h")
    print(f"wrote {args.output}" + (f" and {args.residuals}" if args.residuals else ""))


def _cmd_diagnose(args: argparse.Namespace) -> int:
    from stellar_cal_ros.diagnosis.run import diagnose
    from stellar_cal_ros.io.calibration import load_calibration

    _load_effect_modules(args.effect_module)
    cal = load_calibration(args.calibration)
    candidates = _effect_list(args.candidates) or None
    summary = diagnose(args.bag, cal, args.method, _effect_list(args.effects), args.output,
                       candidates=candidates, plots=not args.no_plots)
    print_diagnosis(summary)
    print(f"wrote {args.output / 'diagnosis.json'}"
          + ("" if args.no_plots else f" and {args.output / 'report.html'}"))
    return 0


def print_diagnosis(summary: dict) -> None:
    """Print the key lines of a diagnosis summary."""
    rms, exp = summary["residual_rms_px"], summary["expected_rms_px"]
    print(f"innovation RMS u={rms[0]:.4f} v={rms[1]:.4f} px; the model expects "
          f"u={exp[0]:.4f} v={exp[1]:.4f} px")
    print("candidates (best first):")
    for c in summary["candidates"][:6]:
        flag = "SIGNIFICANT" if c["significant"] else "           "
        after = c.get("after")
        note = (f"  (not needed once {after['effect']} is added: p={after['p_value']:.2g})"
                if after and not c["significant"] else
                f"  (after {after['effect']}: p={after['p_value']:.2g})" if after else "")
        print(f"  {flag} {c['effect']:22s} score {c['score']:10.1f}  p={c['p_value']:.2g}  "
              f"RMS after u={c['rms_after_px'][0]:.4f} v={c['rms_after_px'][1]:.4f} px{note}")
    also = [c["effect"] for c in sorted(summary["candidates"][1:],
                                        key=lambda c: -(c.get("after") or {}).get("score", 0))
            if c["significant"] and c.get("after")]
    if also:
        top = next(c["after"]["effect"] for c in summary["candidates"] if c.get("after"))
        print(f"  still significant after adding {top}: "
              f"{', '.join(also)} (add them one at a time)")
    implausible = summary.get("implausible", [])
    for u in implausible:
        est, sig = next(iter(u["estimate"].values())), next(iter(u["sigma"].values()))
        after = u.get("after")
        note = (f"; not needed once {after['effect']} is added" if after and not after["needed"]
                else "")
        print(f"  implausible: {u['effect']} (fits {est:.3g} +- {sig:.2g} x its physical "
              f"size{note})")
    if any(not (u.get("after") and not u["after"]["needed"]) for u in implausible):
        print("    (a physical effect at the wrong size: the structure has another cause, or "
              "several effects are missing; add the top candidate and diagnose again)")
    for u in summary["unobservable"]:
        print(f"  unobservable: {u['effect']} ({u['reason']})")
    for u in summary["unexplained"][:5]:
        print(f"  unexplained: {u['component']} residual vs {u['regressor']} "
              f"(t={u['statistic']:.1f}, p={u['p_value']:.2g})")
    rec = summary.get("recommendation")
    print(f"recommendation: add --effects {rec}" if rec else
          "recommendation: no library effect explains the residuals better")


def _cmd_batch(args: argparse.Namespace) -> int:
    import numpy as np

    from stellar_cal_ros.io.calibration import load_calibration, save_calibration
    from stellar_cal_ros.io.residuals import write_residuals
    from stellar_cal_ros.methods.acf import ARCSEC, parse_effects, run_acf

    prior = load_calibration(args.prior)
    if args.residuals is not None and args.residuals.suffix.lower() == ".parquet":
        write_residuals(args.residuals, {"probe": np.zeros(0)})  # fail early without pyarrow
    res = run_acf(args.bag, prior, parse_effects(args.effects), loss=args.loss,
                  outlier_probability=args.outlier_probability or None)
    save_calibration(res.calibration, args.output)
    if args.residuals is not None:
        write_residuals(args.residuals, res.residuals)
    gated = int(np.sum(res.residuals["gated"]))
    q = res.quality
    print(f"acf: {len(res.frames)} frames, {len(res.residuals['du']) - gated} stars "
          f"({gated} gated: {q.stars_misidentified} misidentified, {q.stars_outliers} "
          f"outliers), RMS |Δuv| {res.rms_px:.4f} px, σ̂ {res.sigma_px:.4f} px, "
          f"{res.iterations} evaluations, loss {res.loss}")
    if q.counts():
        print(f"data: {q.summary()}")
    for reason in res.degraded:
        print(f"result degraded: {reason}")
    for name, value, sigma in zip(res.parameter_names[3:], res.theta, res.sigma[3:],
                                  strict=True):
        unit = ""
        if name.startswith("installation."):
            value, sigma, unit = value / ARCSEC, sigma / ARCSEC, " arcsec (vs prior)"
        print(f"  {name:28s} {value:+.8g} ± {sigma:.3g}{unit}")
    eq = res.derived
    if eq:
        print("equivalent principal point: ({:.3f}, {:.3f}) +- ({:.3f}, {:.3f}) px".format(
            *eq["equivalent_principal_point_px"], *eq["equivalent_principal_point_sigma_px"]))
    print(res.observability.summary())
    print(f"wrote {args.output}" + (f" and {args.residuals}" if args.residuals else ""))
    return 0


def _not_yet(issue: int, what: str):
    def run(args: argparse.Namespace) -> int:
        raise StellarCalError(f"{what} is not implemented yet (tracked in issue {issue})")

    return run


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``stellar-cal``."""
    p = argparse.ArgumentParser(
        prog="stellar-cal",
        description="Star tracker + IMU calibration: simulate, calibrate, diagnose.",
    )
    p.add_argument("--version", action="version", version=f"stellar-cal {__version__}")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = sub.add_parser("simulate", help="write a synthetic contract bag with known truth")
    s.add_argument("--scenario", required=True,
                   help="psce_rotations | swaying | acf_sweep")
    s.add_argument("-o", "--output", required=True, type=Path, help="BAG.mcap to write")
    s.add_argument("--duration", type=float, default=None, help="seconds (default: scenario's)")
    s.add_argument("--seed", type=int, default=0, help="random seed (deterministic output)")
    s.add_argument("--effect", action="append", metavar="ID=VALUE[,VALUE...]",
                   help="inject or override a physical effect (repeatable); units in "
                        "stellar_cal_ros.sim.truth_effects")
    s.set_defaults(func=_cmd_simulate)

    i = sub.add_parser("info", help="topics, counts and time span of a bag")
    i.add_argument("bag", type=Path)
    i.set_defaults(func=_cmd_info)

    r = sub.add_parser("replay", help="Kalman-filter calibration over a bag")
    r.add_argument("bag", type=Path)
    r.add_argument("--method", required=True, choices=["psce", "swaying_base"])
    r.add_argument("--prior", required=True, type=Path)
    r.add_argument("-o", "--output", required=True, type=Path)
    r.add_argument("--effects", default="", help="comma-separated effect ids to add")
    r.add_argument("--init-from", type=Path, default=None, metavar="RESULT.yaml",
                   help="start from an earlier solution (e.g. 'batch --method acf'): values "
                        "from RESULT.yaml, sigmas from its sigma block (the prior's where "
                        "it has none)")
    r.add_argument("--residuals", type=Path, default=None, help="RES.parquet or RES.csv")
    r.add_argument("--history", type=Path, default=None,
                   help="state history CSV (default: RESULT.history.csv)")
    r.add_argument("--centroid-sigma", type=float, default=None,
                   help="px, for stars whose message sigma is 0 (default 0.05)")
    r.add_argument("--gyro-arw", type=float, default=None,
                   help="gyro angle random walk, deg/sqrt(h) (default 0.001)")
    r.add_argument("--effect-module", type=Path, action="append",
                   help="Python file defining extra Effect classes (repeatable)")
    r.add_argument("--on-error", choices=["raise", "skip"], default="raise",
                   help="skip: calibrate a truncated bag on what it holds, dropping and "
                        "counting malformed messages (default: stop with an error)")
    r.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    r.set_defaults(func=_cmd_replay)

    b = sub.add_parser("batch", help="attitude-correlated-frames batch least squares")
    b.add_argument("bag", type=Path)
    b.add_argument("--method", required=True, choices=["acf"])
    b.add_argument("--prior", required=True, type=Path)
    b.add_argument("-o", "--output", required=True, type=Path)
    b.add_argument("--effects", default="")
    b.add_argument("--residuals", type=Path, default=None, help="RES.csv (or .parquet)")
    b.add_argument("--loss", default="linear", choices=["linear", "huber", "soft_l1", "cauchy"],
                   help="loss of the final fit (default linear: efficient on the inliers)")
    b.add_argument("--outlier-probability", type=float, default=1.0 - 1e-6, metavar="P",
                   help="outlier gate: after a robust fit, stars beyond the chi2(2) quantile "
                        "P of their normalized residual are left out and counted (0: off)")
    b.set_defaults(func=_cmd_batch)

    d = sub.add_parser("diagnose", help="compare model and measurements")
    d.add_argument("bag", type=Path)
    d.add_argument("--calibration", required=True, type=Path)
    d.add_argument("--method", required=True)
    d.add_argument("--effects", default="")
    d.add_argument("-o", "--output", required=True, type=Path, help="REPORT_DIR")
    d.add_argument("--candidates", default="",
                   help="comma-separated effect ids to try (default: every library effect)")
    d.add_argument("--effect-module", type=Path, action="append",
                   help="Python file defining extra Effect classes (repeatable)")
    d.add_argument("--no-plots", action="store_true", help="diagnosis.json only")
    d.set_defaults(func=_cmd_diagnose)

    m = sub.add_parser("demo", help="run the built-in demonstration")
    m.add_argument("-o", "--output", type=Path, default=Path("demo_out"))
    m.add_argument("--duration", type=float, default=600.0)
    m.set_defaults(func=_cmd_demo)
    return p


def _cmd_demo(args: argparse.Namespace) -> int:
    from stellar_cal_ros.sim.demo import run_demo

    if not args.verbose:  # the demo narrates; the library's own log lines would drown it
        logging.getLogger("stellar_cal_ros").setLevel(logging.ERROR)
    return run_demo(args.output, duration=args.duration)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``stellar-cal`` and ``python -m stellar_cal_ros``."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    try:
        return int(args.func(args) or 0)
    except StellarCalError as exc:
        print(f"stellar-cal {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
