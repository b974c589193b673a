"""The ``stellar-cal`` command line (doc/interfaces.md §5).

Commands
--------
simulate   write a synthetic contract bag + ``*.truth.yaml`` + ``*.prior.yaml``
info       list the topics, message counts and time span of a bag
replay     Kalman-filter calibration over a bag (the filter methods: psce, swaying_base ...)
batch      batch calibration over a whole bag (the batch methods: acf ...)
diagnose   compare model and measurements, rank missing effects (--auto: add them)
discover   diagnose --auto
report     plots and an HTML page of one calibration run
compare    two runs of the model-discovery loop side by side
export     a result in Kalibr, OpenVINS or ROS camera_info format
demo       the built-in end-to-end demonstration
budget     attitude error budget of a result or a spec (stellar_cal_ros.budget)
campaign   many simulate/replay/diagnose/budget runs on Dask (stellar_cal_ros.campaign)
solve      star images -> identified centroids in a contract bag + prior (stellar_cal_ros.sky)

The ``--method`` choices are the registered methods (:mod:`stellar_cal_ros.methods.registry`);
``--method-module FILE.py`` adds a user's method file.

Every error raised on purpose (:class:`stellar_cal_ros.errors.StellarCalError`) and every
operating-system error (an output path that cannot be written: a file in the way of a
directory, no permission, a full disk) is printed as one clear line and gives exit status 1
(``-v`` logs the traceback too); a usage error gives 2.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
import warnings
from collections.abc import Sequence
from pathlib import Path

from stellar_cal_ros import __version__
from stellar_cal_ros.errors import (
    BagDamageWarning,
    StellarCalError,
    held_damage_warning,
    hold_damage_warnings,
    no_such_bag,
    one_line,
    unsaid_damage_warnings,
)

log = logging.getLogger("stellar_cal_ros")


def _cmd_simulate(args: argparse.Namespace) -> int:
    from stellar_cal_ros.sim.scenarios import get_scenario
    from stellar_cal_ros.sim.truth_effects import parse_effect_arguments
    from stellar_cal_ros.sim.world import simulate, write_simulation

    _load_effect_modules(args.effect_module)
    scenario = get_scenario(args.scenario)
    effects = parse_effect_arguments(args.effect or [])
    t_start = time.perf_counter()
    if args.images:  # the truth world's stars rendered into images (sim/image_bag.py)
        from stellar_cal_ros.sim.image_bag import write_image_simulation
        from stellar_cal_ros.sim.render import without_noise

        scenario = without_noise(scenario)
    result = simulate(scenario, duration=args.duration, seed=args.seed, effects=effects)
    t_sim = time.perf_counter() - t_start
    paths = (write_image_simulation(result, args.output, args.images, seed=args.seed)
             if args.images else write_simulation(result, args.output))
    t_all = time.perf_counter() - t_start
    m = result.meta
    n_frames = len(result.star_frames)
    what = (f"{n_frames} {args.images} images {scenario.width}x{scenario.height}"
            if args.images else f"{n_frames} star frames")
    print(
        f"simulated {m['scenario']}: {m['duration_s']:.0f} s, "
        f"{m['counts']['/imu/data']} IMU samples, {what} "
        f"({m['stars_per_frame']['mean']:.1f} stars/frame) in {t_sim:.1f} s "
        f"(+{t_all - t_sim:.1f} s {'rendering and ' if args.images else ''}writing)"
    )
    for key in ("bag", "truth", "prior", "meta"):
        print(f"  {key:5s} {paths[key]}")
    return 0


def _cmd_effects(args: argparse.Namespace) -> int:
    from stellar_cal_ros.effects import registry
    from stellar_cal_ros.sim.truth_effects import SIM_ONLY, effect_table

    _load_effect_modules(args.effect_module)
    table = effect_table()
    for eid in registry.available():
        cls = registry.EFFECTS[eid]
        size, sim_units = table[eid]
        print(f"{eid}  [{cls.stage.value}]  parameters: " + ", ".join(
            f"{n} ({u})" for n, u in zip(cls.parameter_names, cls.units or ("",) * size,
                                        strict=False)))
        print(f"    simulate --effect {eid}=" + ",".join(["V"] * size) + "  in "
              + ", ".join(sim_units))
        if cls.plausible is not None:
            print("    plausible size (largest seen in practice): "
                  + ", ".join(dict.fromkeys(cls.plausible.text(i) for i in range(size))))
        if args.verbose_text and cls.explanation:
            print("    " + cls.explanation)
    print("simulator only (no library effect models them): "
          + ", ".join(f"{k} ({u})" for k, (_, u) in SIM_ONLY.items()))
    return 0


def _cmd_info(args: argparse.Namespace) -> int:
    from stellar_cal_ros.io.bag import BagReader

    with warnings.catch_warnings(record=True), BagReader(args.bag, on_error="skip") as reader:
        warnings.simplefilter("always")
        topics = reader.topics()
        start, end = reader.start_ns, reader.end_ns
        span = (end - start) * 1e-9 if start is not None and end is not None else 0.0
        print(f"{args.bag}: {span:.3f} s, {len(topics)} topics ({reader.storage})")
        for name, info in sorted(topics.items()):
            print(f"  {name:32s} {info.schema_name:40s} {info.message_count:8d}")
        problems = reader.check()
        if not problems:
            from stellar_cal_ros.methods.frames import star_images_text

            images, images_used = star_images_text(reader, topics, str(args.bag))
    if not problems:
        what = "every chunk decompresses and matches its CRC" if "mcap" in reader.storage \
            else "every message could be read"
        print(f"integrity: {what}")
        if images:
            print(images)
        missing = "" if images_used else _no_stars_text(topics)
        if missing and "extract them" in missing:  # star images: data, in another form
            print(f"note: {missing}")
        elif missing:
            print(f"stellar-cal info: error: {args.bag}: {missing}", file=sys.stderr)
            return 1
        return 0
    print(f"integrity: {len(problems)} damaged part(s)")
    for p in problems:
        print(f"DAMAGED {p.describe(start)}")
    more = f" (and {len(problems) - 1} more damaged part(s))" if len(problems) > 1 else ""
    print(f"stellar-cal info: error: damaged bag: {problems[0].describe(start)}{more}",
          file=sys.stderr)
    return 1


def _no_stars_text(topics: dict) -> str:
    """Why no command can calibrate on a bag with these topics ('' if it can)."""
    from stellar_cal_ros.io.bag import DEFAULT_TOPICS

    stars = DEFAULT_TOPICS["stars"]
    info = topics.get(stars)
    if info is not None and info.message_count > 0 and \
            "StarCentroidArray" in info.schema_name:
        return ""
    if info is None:
        what = f"no {stars} topic"
    elif info.message_count == 0:
        what = f"{stars} holds no message"
    else:
        what = f"{stars} is {info.schema_name}, not stellar_cal_msgs/msg/StarCentroidArray"
    images = [t for t, i in topics.items() if i.schema_name.endswith("/Image")]
    if images:
        return (f"{what}; extract them from {', '.join(sorted(images))} first (the "
                "star_extractor node, doc/ros_nodes.md)")
    return f"{what}: nothing to calibrate on (the contract's star centroids, doc/interfaces.md)"


def _effect_list(text: str) -> list[str]:
    return [e.strip() for e in (text or "").split(",") if e.strip()]


def load_prior(path: Path):
    """Load a prior calibration; warn (one line each, then a count) about its keys and σ."""
    from stellar_cal_ros.effects import registry
    from stellar_cal_ros.io.calibration import load_calibration, prior_warnings

    prior = load_calibration(path)
    problems = prior_warnings(prior, str(path), {e: cls.parameter_names for e, cls in
                                                 registry.EFFECTS.items()})
    for w in problems:
        log.warning("%s", w)
    if len(problems) > 1:
        log.warning("%s: %d problems (above): the run uses the defaults in their place",
                    path, len(problems))
    return prior


def note_residual_file(path: Path | None) -> None:
    """Record the residual table a run wrote in its result's provenance.

    Its name and SHA-256: ``report`` and ``compare`` refuse another run's table.
    """
    if path is not None:
        from stellar_cal_ros.io.calibration import note_provenance
        from stellar_cal_ros.io.identity import file_digest

        note_provenance(residuals={"file": str(path), "sha256": file_digest(path)})


def _load_effect_modules(paths: list[Path] | None) -> None:
    from stellar_cal_ros.effects import registry

    for path in paths or []:
        ids = registry.load_effect_module(path)
        log.info("loaded effects %s from %s", ", ".join(ids), path)


def _load_method_modules(argv: Sequence[str]) -> None:
    """Register the ``--method-module`` files before the parser checks ``--method``."""
    pre = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    pre.add_argument("--method-module", type=Path, action="append", default=[])
    known, _ = pre.parse_known_args(list(argv))
    if known.method_module:
        from stellar_cal_ros.methods import registry

        for path in known.method_module:
            name = registry.load_method_module(path)
            log.info("loaded method %s from %s", name, path)


def _check_replay(args: argparse.Namespace) -> None:
    """Refuse a replay's inputs before the filter's imports and the kernels' compile notice.

    The prior (and ``--init-from``'s result), the effect ids, ``--noise-scale``, then the
    bag: it exists, opens, and holds the star frames and the IMU the method needs (from its
    summary, as diagnose's check).  A refusal costs the reader's imports, not the filter's
    (measured: 0.9 -> ~0.5 CPU-s).  The prior loaded is the run's
    (``args.replay_prior``: its warnings are said once).
    """
    from stellar_cal_ros.effects import registry
    from stellar_cal_ros.methods.frames import method_reads_images

    _load_effect_modules(args.effect_module)
    prior = load_prior(args.prior)
    if args.init_from is not None:
        from stellar_cal_ros.io.calibration import load_calibration
        from stellar_cal_ros.methods.init_from import prior_from_result

        prior = prior_from_result(prior, load_calibration(args.init_from), args.init_from)
    for eid in _effect_list(args.effects):
        if not eid.startswith("-"):
            registry.effect_class(eid)
    _noise_scales(args.noise_scale)
    method_reads_images(args.bag, args.method, command="replay")
    args.replay_prior = prior


def _cmd_replay(args: argparse.Namespace) -> int:
    from stellar_cal_ros.io.calibration import save_calibration
    from stellar_cal_ros.methods import registry
    from stellar_cal_ros.methods.replay import replay

    prior = args.replay_prior  # (_check_replay: loaded before the filter's imports)
    effects = _effect_list(args.effects)
    config = registry.get(args.method).config_cls()
    if args.centroid_sigma is not None:
        config.centroid_sigma_px = args.centroid_sigma
    if args.gyro_arw is not None:
        config.gyro_arw_deg_sqrth = args.gyro_arw
    noise = _replay_noise(args, prior, effects, config)
    history_path = args.history or args.output.with_suffix(".history.csv")
    result = replay(args.bag, prior, args.method, effects, config, residuals=args.residuals,
                    history=history_path, keep_tables=args.viz is not None and
                    args.residuals is None, progress=not args.quiet, on_error=args.on_error,
                    noise=noise)
    unknown = result.counters.get("stars_sigma_unknown", 0)
    if unknown and not (noise and (noise.unknown_sigma_px or noise.group_by)) and \
            args.centroid_sigma is None:
        # a σ of 0 says "unknown": measured from the run, never used as a guess (unless the
        # scales given say it: unknown=PX, or groups, which a σ-0 star takes on the default
        # when no unknown= is given: the advice of a bag where no message states a σ)
        verdict = _measure_noise(args, prior, effects, noise, ())
        noise = verdict.applied
        result = replay(args.bag, prior, args.method, effects, config,
                        residuals=args.residuals, history=history_path,
                        keep_tables=args.viz is not None and args.residuals is None,
                        progress=not args.quiet, on_error=args.on_error, noise=noise)
    note_residual_file(args.residuals)
    save_calibration(result.calibration, args.output, covariance=result.covariance)
    print_replay_summary(result, prior)
    print(f"wrote {args.output}, {history_path}"
          + (f" and {args.residuals}" if args.residuals else ""))
    if args.viz is not None:
        _write_viz(args.viz, result, history_path, args.residuals, noise)
    return 0


def _write_viz(path: Path, result, history_path: Path, residuals_path: Path | None,
               noise=None) -> None:
    """``replay --viz``: the run as a Foxglove view (MCAP + the layout beside it)."""
    from stellar_cal_ros.io.residuals import read_residuals
    from stellar_cal_ros.viz import layout_json, write_viz

    res = read_residuals(residuals_path) if residuals_path else result.residuals
    t0 = time.perf_counter()
    counts = write_viz(path, read_residuals(history_path), res, result.calibration,
                       result.method, noise=noise)
    lay = path.with_suffix(".layout.json")
    lay.write_text(layout_json())
    print(f"wrote {path} ({', '.join(f'{v} {k}' for k, v in counts.items())} messages, "
          f"{time.perf_counter() - t0:.1f} s): open it in Foxglove with the layout {lay}")


def _measure_noise(args: argparse.Namespace, prior, effects, scales, components):
    from stellar_cal_ros.core.noise import NoiseScales
    from stellar_cal_ros.diagnosis.run import measure_bag

    print("measuring the noise scales from the run ...", flush=True)
    verdict = measure_bag(args.bag, prior, args.method, effects, scales or NoiseScales(),
                          components)
    for line in verdict.lines():
        print(f"noise: {line}")
    return verdict


#: the items of ``--noise-scale`` (replay, diagnose and discover take the same)
NOISE_SCALE_ITEMS = ("star=S scales the stars' sigma "
                     "(messages, or --centroid-sigma for sigma 0) by S, gyro=G the gyro "
                     "ARW, accel=A the accelerometer VRW; gyro_bias_rw=D gives the gyro "
                     "bias a random walk of D deg/h/sqrt(h) (0, the default: a constant "
                     "bias); stamp=MS states a noise of MS ms rms in the frames' stamps "
                     "(one error per frame, its stars' common motion in each frame's "
                     "covariance; 0, the default: exact stamps); frame=PX states a shift of "
                     "PX px rms per axis all stars of a frame share, white between frames "
                     "(sigma_f^2 between every two of its stars in each frame's covariance; "
                     "0, the default: none); unknown=PX sets the sigma of "
                     "stars whose message says 0; rho=R[,share=W] declares the stars' "
                     "noise correlated from frame to frame (lag-1 R; S then the whole "
                     "scale a white-noise filter needs): the consistency is judged "
                     "against it.  The stars' sigma per group: "
                     "by=magnitude|radius|column|row,edges=E1/E2,factors=F0/F1/F2 (edges "
                     "increasing, in mag or px; one factor more than edges, each of the "
                     "messages' sigma; '/' between numbers), e.g. "
                     "by=magnitude,edges=4.5,factors=1/0.5; a group spec needs no "
                     "unknown=: without it stars whose message says 0 take "
                     "--centroid-sigma times their group's factor, with it PX alone")


def _verify_twins(twins: str, most: int | None) -> tuple[int, int]:
    """``--verify-twins K|auto`` and ``--verify-twins-max M``: the first twins and the most.

    The noisy twins every row gets beside its noise-free twin pair (auto: none) and the
    most a row gets (a row whose noise-free run failed is judged on noisy twins: at least
    :data:`~.verify.TWINS`; auto: more, up to ``M``).
    """
    from stellar_cal_ros.diagnosis.verify import TWINS, TWINS_MAX

    if twins == "auto":
        first = 0
    elif twins.isdigit():
        first = int(twins)
    else:
        raise StellarCalError(f"--verify-twins must be a count >= 0 or auto, not {twins!r}")
    last = most if most is not None else (TWINS_MAX if twins == "auto" else max(first, TWINS))
    if last < first:
        raise StellarCalError(f"--verify-twins-max {last} is below the first twins ({first})")
    return first, last


def _noise_scales(text: str | None):
    """``--noise-scale``'s scales (replay, diagnose, discover), or None when not given."""
    from stellar_cal_ros.core.noise import NoiseScales

    if not text:
        return None
    try:
        return NoiseScales.parse(text)
    except ValueError as exc:
        raise StellarCalError(str(exc)) from None


def _replay_noise(args: argparse.Namespace, prior, effects, config):
    """The noise scales of a replay: given (--noise-scale), measured (--estimate-noise)."""
    noise = _noise_scales(args.noise_scale)
    if args.estimate_noise:
        noise = _measure_noise(args, prior, effects, noise, None).applied
    return noise


def print_replay_summary(result, prior) -> None:
    """Human summary of a filter run (accuracy-relevant numbers first, mismatch loudly)."""
    import numpy as np

    from stellar_cal_ros.core.units import ARCSEC, DEG_PER_HOUR, MICRO_G
    from stellar_cal_ros.effects.base import Stage
    from stellar_cal_ros.methods import models, registry
    from stellar_cal_ros.methods.results import (
        counts_line,
        data_quality,
        mismatch_text,
        quality_line,
    )

    spec = registry.get(result.method)
    st = result.stats.summary()
    cons = result.calibration.extra.get("consistency", {})
    print(f"replayed {result.duration:.0f} s in {result.read_seconds:.2f} s reading + "
          f"{result.filter_seconds:.2f} s filtering = {result.speed:.0f}x real time")
    rms, exp = st["rms_px"], st["expected_rms_px"]
    print(f"innovation RMS (second half, accepted stars): u={rms[0]:.4f} v={rms[1]:.4f} px "
          f"(model expects {exp[0]:.4f} {exp[1]:.4f}); NIS/dof {st['nis_per_dof']:.3f}"
          + (" (x{:.3g} for the stars' noise declared correlated from frame to frame, rho "
             "{:.2f}: {:.3f})".format(cons["correlated"]["inflation"],
                                      cons["correlated"]["star_rho"], cons["nis_per_dof"])
             if cons.get("correlated") else "") + "; "
          f"verdict: {cons.get('verdict', '?')}")
    if cons.get("noise_rescaled"):
        n = cons.get("noise", {})
        print("noise rescaled: stars' sigma x{:.3g}, gyro noise x{:.3g}, accelerometer noise "
              "x{:.3g}{}".format(n.get("star_sigma_scale", 1.0), n.get("gyro_noise_scale", 1.0),
                                 n.get("accel_noise_scale", 1.0),
                                 ", stars with sigma 0 (unknown): measured "
                                 f"{n['unknown_star_sigma_px']:.3g} px"
                                 if n.get("unknown_star_sigma_px") else "")
              + (", gyro bias random walk {:.3g} deg/h/sqrt(h)".format(
                  n["gyro_bias_rw_deg_h_sqrth"]) if n.get("gyro_bias_rw_deg_h_sqrth") else ""))
    loud = mismatch_text(cons)
    if loud:
        print("*" * 78 + "\n" + loud + "\n" + "*" * 78)
    print(counts_line(result.counters))
    # what the counters say about the input, as the diagnosis says it (one line)
    print(quality_line(data_quality(result.counters, result.stats.accepted_total,
                                    st["nis_per_dof"]), lead="data quality")
          or "data quality: no input fault counted")
    extra = list(result.effects)
    print("model: " + ", ".join(spec.baseline)
          + (" + " + ", ".join(extra) if extra else ""))
    hint = models.uncertain_not_in_model(prior, result.method,
                                         [e.id for e in result.filter.model.effects])
    if hint:
        print("the prior calls uncertain but the model keeps fixed: " + ", ".join(hint)
              + " (add with --effects, or let `stellar-cal diagnose` test them)")
    cal = result.calibration
    cam = cal.camera
    print(f"camera: fx={cam.fx:.3f} fy={cam.fy:.3f} cx={cam.cx:.3f} cy={cam.cy:.3f} px, "
          f"distortion {cam.distortion_model()} "
          + " ".join(f"{v:.4g}" for v in cam.to_yaml_dict()["distortion_coefficients"]["data"]))
    d = result.derived
    if "equivalent_principal_point_px" in d:
        print("equivalent principal point: ({:.3f}, {:.3f}) +- ({:.3f}, {:.3f}) px".format(
            *d["equivalent_principal_point_px"], *d["equivalent_principal_point_sigma_px"]))
    flt = result.filter
    if "installation" in flt.model.slices:
        sl = flt.model.slices["installation"]
        print("installation delta (tracker axes): " + "  ".join(
            f'{v:+.3f}"+-{s:.3f}' for v, s in zip(flt.theta[sl] / ARCSEC,
                                                   flt.sigma()[flt.it][sl] / ARCSEC,
                                                   strict=True)))
    print(f"installation quaternion_xyzw: {np.round(cal.installation_quat, 9).tolist()}")
    print(f"gyro bias: {np.round(np.asarray(cal.gyro_bias) / DEG_PER_HOUR, 5).tolist()} deg/h"
          + ("" if Stage.ACCEL not in spec.stages else "; accelerometer bias: "
             f"{np.round(np.asarray(cal.accel_bias) / MICRO_G, 2).tolist()} ug"))


def _check_diagnose(args: argparse.Namespace) -> None:
    """Refuse a missing bag, or one without what the method needs, from its summary.

    Before the kernels' compile notice and before the diagnosis's modules are imported
    (a refusal costs a fraction of a CPU-second, not the filter's imports).
    """
    from stellar_cal_ros.methods.frames import method_reads_images

    method_reads_images(args.bag, args.method)


def _cmd_diagnose(args: argparse.Namespace) -> int:
    _load_effect_modules(args.effect_module)
    cal = load_prior(args.calibration)
    candidates = _effect_list(args.candidates) or None
    if args.workers is not None and args.workers < 0:
        raise StellarCalError("--workers must be >= 0 (0: no worker processes)")
    auto = args.auto or args.command == "discover"
    if auto and args.max_rounds < 1:
        raise StellarCalError("--max-rounds must be >= 1")
    twins, twins_max = _verify_twins(args.verify_twins, args.verify_twins_max)
    from stellar_cal_ros.diagnosis.run import diagnose

    summary = diagnose(args.bag, cal, args.method, _effect_list(args.effects), args.output,
                       candidates=candidates, plots=not args.no_plots, workers=args.workers,
                       scheduler=args.scheduler, auto=auto, max_rounds=args.max_rounds,
                       noise=args.noise, verify=args.verify and auto,
                       verify_seed=args.verify_seed,
                       verify_signs={"both": (1, -1), "+": (1,), "-": (-1,)}[args.verify_signs],
                       verify_twins=twins, verify_twins_max=twins_max,
                       noise_scales=_noise_scales(args.noise_scale),
                       on_error=args.on_error)
    if auto:
        from stellar_cal_ros.diagnosis.printing import print_discovery

        print_discovery(summary)
        print(f"wrote {summary['calibration_file']}, {args.output / 'diagnosis.json'}"
              + ("" if args.no_plots else f" and {args.output / 'report.html'}"))
        return 0
    from stellar_cal_ros.diagnosis.printing import print_diagnosis

    print_diagnosis(summary, cal)
    print(f"wrote {args.output / 'diagnosis.json'}"
          + ("" if args.no_plots else f" and {args.output / 'report.html'}"))
    return 0


def _cmd_batch(args: argparse.Namespace) -> int:
    import numpy as np

    from stellar_cal_ros.io.calibration import save_calibration
    from stellar_cal_ros.io.residuals import write_residuals
    from stellar_cal_ros.methods import registry
    from stellar_cal_ros.progress import progress

    spec = registry.get(args.method)
    prior = load_prior(args.prior)
    if args.residuals is not None and args.residuals.suffix.lower() == ".parquet":
        write_residuals(args.residuals, {"probe": np.zeros(0)})  # fail early without pyarrow
    steps = spec.steps
    options = {"loss": args.loss, "outlier_probability": args.outlier_probability or None,
               "on_error": args.on_error}
    with progress(max(len(steps), 1), args.method, unit="stages",
                  enabled=not args.quiet) as p:
        def step_done(name: str) -> None:
            p.update(1)
            if p.n < len(steps):
                p.note(f"{args.method} stage {p.n + 1}/{len(steps)}: {steps[p.n]}")

        if steps:
            p.note(f"{args.method} stage 1/{len(steps)}: {steps[0]}", eta=False)
        res = spec.batch(args.bag, prior, _effect_list(args.effects), options, step_done)
    if args.residuals is not None:
        write_residuals(args.residuals, res.residuals)
        note_residual_file(args.residuals)
    save_calibration(res.calibration, args.output, covariance=res.covariance)
    for line in res.lines:
        print(line)
    from stellar_cal_ros.methods.results import loss_line

    lost = loss_line(res.calibration.extra.get("data_quality") or {})
    if lost:
        print(lost)
    print(f"wrote {args.output}" + (f" and {args.residuals}" if args.residuals else "")
          + f" (covariance: {args.output.with_suffix('').name}.covariance.yaml)")
    return 0


def _not_yet(issue: int, what: str):
    def run(args: argparse.Namespace) -> int:
        raise StellarCalError(f"{what} is not implemented yet (tracked in issue {issue})")

    return run


class _HelpFormatter(argparse.HelpFormatter):
    """Help that lists the registered methods (read only when help is printed)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        from stellar_cal_ros.methods.registry import MethodNames

        text = super()._get_help_string(action)
        if isinstance(action.choices, MethodNames):
            text = f"{text}: {action.choices.describe().replace('%', '%%')}"
        return text


def _method_arguments(p: argparse.ArgumentParser, what: str, **select) -> None:
    """``--method`` (choices: the registered methods of ``select``) and ``--method-module``."""
    from stellar_cal_ros.methods.registry import MethodNames

    p.add_argument("--method", required=True, choices=MethodNames(**select), metavar="METHOD",
                   help=what)
    p.add_argument("--method-module", type=Path, action="append", metavar="FILE.py",
                   help="Python file declaring a method (METHOD = MethodSpec(...), "
                        "doc/workflow.md); repeatable")


def _run_arguments(p: argparse.ArgumentParser, bag: str, kind: str, method: str,
                   output: str, effects: str) -> None:
    """The arguments every calibration command has: bag, method, prior, output, effects."""
    p.add_argument("bag", type=Path, help=bag)
    _method_arguments(p, method, kind=kind)
    p.add_argument("--prior", required=True, type=Path,
                   help="PRIOR.yaml: nominal values and their sigmas (doc/interfaces.md)")
    p.add_argument("-o", "--output", required=True, type=Path, help=output)
    p.add_argument("--effects", default="", help=effects)


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``stellar-cal``."""
    p = argparse.ArgumentParser(
        prog="stellar-cal",
        description="Star tracker + IMU calibration: simulate, calibrate, diagnose.",
    )
    p.add_argument("--version", action="version", version=f"stellar-cal {__version__}")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    p.epilog = ("File formats, topics and frames: doc/interfaces.md. Run "
                "'stellar-cal COMMAND -h' for a command's options.")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = sub.add_parser("simulate", help="write a synthetic contract bag with known truth")
    s.add_argument("--scenario", required=True, choices=["psce_rotations", "swaying", "acf_sweep"],
                   help="the papers' motion scenario (Tan et al. rotations, Zhang et al. "
                        "swaying base, Liu et al. turntable sweep)")
    s.add_argument("-o", "--output", required=True, type=Path, help="BAG.mcap to write")
    s.add_argument("--duration", type=float, default=None, help="seconds (default: scenario's)")
    s.add_argument("--seed", type=int, default=0, help="random seed (deterministic output)")
    s.add_argument("--effect", action="append", metavar="ID=VALUE[,VALUE...]",
                   help="inject or override a physical effect (repeatable); units: "
                        "`stellar-cal effects` or doc/interfaces.md")
    s.add_argument("--effect-module", type=Path, action="append",
                   help="Python file defining extra Effect classes (repeatable): simulated "
                        "through the class itself")
    s.add_argument("--images", nargs="?", const="mono16", choices=["mono16", "mono8"],
                   default=None, metavar="ENCODING",
                   help="write star images instead of centroids: the truth world's stars "
                        "rendered (PSF, sky, shot/read noise, hot pixels, saturation) on "
                        "/star_tracker/image (mono16: 12-bit sensor, default; mono8) plus "
                        "/star_tracker/camera_info; about 0.75 MB per frame at 1024x1024")
    s.set_defaults(func=_cmd_simulate)

    e = sub.add_parser("effects", help="list the effect library: ids, stages, parameters, "
                       "units, simulate units")
    e.add_argument("--effect-module", type=Path, action="append",
                   help="Python file defining extra Effect classes (repeatable)")
    e.add_argument("--explain", dest="verbose_text", action="store_true",
                   help="print each effect's explanation (cause, size, residual signature)")
    e.set_defaults(func=_cmd_effects)

    i = sub.add_parser("info", help="topics, counts and time span of a bag; checks every chunk's "
                                    "CRC (exit 1 and one line per damaged part if any, or "
                                    "when it holds no star centroids)")
    i.add_argument("bag", type=Path, help="a .mcap file, a rosbag2 directory or a ROS 1 .bag")
    i.set_defaults(func=_cmd_info)

    from stellar_cal_ros.errors import on_error_argument

    r = sub.add_parser("replay", help="Kalman-filter calibration over a bag",
                       formatter_class=_HelpFormatter)
    _run_arguments(r, "contract bag to calibrate on", "filter",
                   "the filter method", "RESULT.yaml to write (plus "
                   "RESULT.history.csv)", "comma-separated effect ids to add to the "
                   "method's baseline model")
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
    r.add_argument("--noise-scale", default=None, metavar="KEY=VALUE,...",
                   help="scale the stated noise (comma-separated items; what `diagnose` "
                        "prints as 'use --noise-scale'): " + NOISE_SCALE_ITEMS)
    r.add_argument("--estimate-noise", action="store_true",
                   help="measure the noise scales from the run first (stars' sigma: "
                        "within-frame variance components; gyro/accelerometer: maximum "
                        "likelihood over re-runs), then replay with them")
    r.add_argument("--effect-module", type=Path, action="append",
                   help="Python file defining extra Effect classes (repeatable)")
    on_error_argument(r, "calibrate")
    r.add_argument("--viz", type=Path, default=None, metavar="VIZ.mcap",
                   help="also write the run as a Foxglove view: estimates with their sigma, "
                        "NIS, /diagnostics and the residual field over time, plus the layout "
                        "VIZ.layout.json (doc/visualization.md)")
    r.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    r.set_defaults(func=_cmd_replay, check=_check_replay)

    b = sub.add_parser("batch", help="batch least squares over a whole bag (acf, bundle ...)",
                       formatter_class=_HelpFormatter)
    _run_arguments(b, "contract bag (e.g. a turntable or slew sequence)", "batch",
                   "the batch method", "RESULT.yaml to write (plus "
                   "RESULT.covariance.yaml)", "comma-separated effect ids to add to the "
                   "method's set (-id removes one)")
    b.add_argument("--residuals", type=Path, default=None,
                   help="RES.csv (or .parquet): per-star residuals of the fit")
    b.add_argument("--loss", default="linear", choices=["linear", "huber", "soft_l1", "cauchy"],
                   help="loss of the final fit (default linear: efficient on the inliers; "
                        "robust ones bound outliers' pull)")
    b.add_argument("--outlier-probability", type=float, default=1.0 - 1e-6, metavar="P",
                   help="outlier gate: after a robust fit, stars beyond the chi2(2) quantile "
                        "P of their normalized residual are left out and counted (0: off)")
    on_error_argument(b, "fit")
    b.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    b.set_defaults(func=_cmd_batch)

    for name, text in (("diagnose", "compare model and measurements (--auto: add effects "
                                    "until nothing is significant)"),
                       ("discover", "diagnose --auto: forward selection of missing effects")):
        d = sub.add_parser(name, help=text, formatter_class=_HelpFormatter)
        d.add_argument("bag", type=Path, help="contract bag to diagnose on")
        d.add_argument("--calibration", required=True, type=Path,
                       help="RESULT.yaml (or a prior) the diagnosis starts from")
        _method_arguments(d, "the method whose model is diagnosed", diagnosable=True)
        d.add_argument("--effects", default="",
                       help="comma-separated effect ids already in the model (as for replay)")
        d.add_argument("-o", "--output", required=True, type=Path, help="REPORT_DIR")
        d.add_argument("--candidates", default="",
                       help="comma-separated effect ids to try (default: every library effect)")
        d.add_argument("--effect-module", type=Path, action="append",
                       help="Python file defining extra Effect classes (repeatable)")
        d.add_argument("--no-plots", action="store_true", help="diagnosis.json only")
        d.add_argument("--auto", action="store_true", default=name == "discover",
                       help="add the recommended effect, re-run and test again until nothing "
                            "is significant; writes REPORT_DIR/calibration.yaml")
        d.add_argument("--max-rounds", type=int, default=8,
                       help="--auto: at most this many test rounds (default 8)")
        d.add_argument("--workers", type=int, default=None,
                       help="worker processes for the re-runs (default: automatic, in this "
                            "process until a batch of re-runs would take >= 20 CPU-s, then "
                            "one per core; in this process on 1-2 cores; 0 or 1: none, "
                            "everything in this process)")
        d.add_argument("--scheduler", default=None, metavar="ADDRESS",
                       help="run the re-runs on an existing Dask cluster (tcp://host:8786)")
        d.add_argument("--verify", action="store_true",
                       help="--auto: check every printed MDB and bias on twins of this bag "
                            "(the effect injected at its MDB, `stellar-cal twin`; the biases "
                            "on its noise-free twin, exactly)")
        d.add_argument("--verify-seed", type=int, default=1,
                       help="noise seed of the first --verify twins (default 1; the next "
                            "twins take the next seeds)")
        d.add_argument("--verify-signs", choices=["both", "+", "-"], default="both",
                       help="--verify: inject each row at both signs of its MDB (default: an "
                            "MDB is a size of either sign) or at one")
        d.add_argument("--verify-twins", default="auto", metavar="K|auto",
                       help="--verify: noisy twins of different noise seeds per row and "
                            "sign beside its noise-free twin pair, which judges the "
                            "detection (its exact score response's power) and the biases "
                            "(K: that many, listed; auto, the default: none, and one noisy "
                            "clean twin's run checks the noise model; a row whose "
                            "noise-free twin did not run gets 2, and more, one seed at a "
                            "time, where they cannot judge its biases or leave them at the "
                            "band's edge, up to --verify-twins-max)")
        d.add_argument("--verify-twins-max", type=int, default=None, metavar="M",
                       help="--verify: the most noisy twins a row gets (default 6 with "
                            "--verify-twins auto; with K: K, at least 2)")
        on_error_argument(d, "diagnose")
        d.add_argument("--noise", choices=["estimate", "stated"], default="estimate",
                       help="estimate (default): measure the stars' sigma and the IMU noise "
                            "scales first and test every effect with them; stated: use the "
                            "noise the messages and the calibration's run state")
        d.add_argument("--noise-scale", default=None, metavar="KEY=VALUE,...",
                       help="the noise to start from instead of the calibration's run's "
                            "(its consistency block; as for replay, what the diagnosis "
                            "prints as 'use --noise-scale'; with --noise estimate measured "
                            "again relative to it): " + NOISE_SCALE_ITEMS)
        d.set_defaults(func=_cmd_diagnose, check=_check_diagnose)

    m = sub.add_parser("demo", help="run the built-in demonstration")
    m.add_argument("-o", "--output", type=Path, default=Path("demo_out"),
                   help="folder for the demo's bag, results and report (default demo_out)")
    m.add_argument("--duration", type=float, default=600.0,
                   help="seconds of simulated data (default 600)")
    m.set_defaults(func=_cmd_demo)

    from stellar_cal_ros.budget.command import add_budget_parser
    from stellar_cal_ros.campaign.command import add_campaign_parser
    from stellar_cal_ros.diagnosis.twin_command import add_twin_parser
    from stellar_cal_ros.results_cli import add_result_commands
    from stellar_cal_ros.sky.command import add_solve_parser

    add_result_commands(sub)
    add_solve_parser(sub)
    add_budget_parser(sub)
    add_twin_parser(sub)
    add_campaign_parser(sub)
    return p


def _cmd_demo(args: argparse.Namespace) -> int:
    from stellar_cal_ros.demo import run_demo

    if not args.verbose:  # the demo narrates; the library's own log lines would drown it
        logging.getLogger("stellar_cal_ros").setLevel(logging.ERROR)
    return run_demo(args.output, duration=args.duration)


#: the output paths of each command: (argument, is a directory), checked before it runs
OUTPUTS: dict[str, tuple[tuple[str, bool], ...]] = {
    "simulate": (("output", False),), "replay": (("output", False), ("residuals", False),
                                                 ("history", False), ("viz", False)),
    "batch": (("output", False), ("residuals", False)), "export": (("output", False),),
    **{c: (("output", True),) for c in ("diagnose", "discover", "report", "compare",
                                         "budget", "campaign", "demo")},
}


#: commands whose first run on a machine compiles the filter kernels (a notice says so)
COMPILES = ("replay", "diagnose", "discover", "demo", "campaign")
#: commands of diagnosis rounds: glibc's mapping threshold fixed (core.memory)
ROUNDS = ("diagnose", "discover")


def _one_line_warning(command: str):
    """Return a ``warnings.showwarning`` printing ``stellar-cal CMD: warning: TEXT``.

    No source line: the text names the file and what was lost.
    """

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        if issubclass(category, BagDamageWarning) and held_damage_warning(one_line(message)):
            return  # (--on-error skip: counted in the command's data quality line)
        print(f"stellar-cal {command}: warning: {one_line(message)}", file=file or sys.stderr)

    return show


def _say_unsaid(command: str) -> None:
    """The held damage warnings no data quality line counted: printed, one line each."""
    for text in unsaid_damage_warnings():
        print(f"stellar-cal {command}: warning: {text}", file=sys.stderr)
    hold_damage_warnings(False)


def _unsaid_note(args: argparse.Namespace) -> str:
    """An error's words for the held damage warnings no data quality line counted."""
    n = len(unsaid_damage_warnings())
    hold_damage_warnings(False)
    if not n:
        return ""
    return (f" (read past damage in {args.bag}: the reader's {n} warning{'s' * (n != 1)} "
            f"about it not printed, `stellar-cal -v` prints them; `stellar-cal info "
            f"{args.bag}` lists the damage)")


def _hint(args: argparse.Namespace, exc: StellarCalError) -> str:
    """What to do about a damaged bag (read past it, or what else reads it)."""
    from stellar_cal_ros.errors import BagError, MessageDecodeError

    damaged = isinstance(exc, MessageDecodeError) or (
        isinstance(exc, BagError) and "truncated or corrupt" in str(exc))
    bag = getattr(args, "bag", None)
    if not damaged or bag is None:
        return ""
    if getattr(args, "on_error", None) == "raise":
        return (f" (`--on-error skip` reads on past it, counting what is lost; "
                f"`stellar-cal info {bag}` lists the damage)")
    return f" (`stellar-cal info {bag}` lists the damage)"


def check_output(path: Path, directory: bool) -> None:
    """Raise a one-line error now if ``path`` cannot be written (not after the work)."""
    import os

    kind = "directory" if directory else "file"
    if path.exists():
        if directory != path.is_dir():
            raise StellarCalError(f"{path} exists and is a {'file' if directory else 'directory'}"
                                  f"; the output is a {kind}: choose another path")
        where = path if directory else path.parent
    else:
        where = path.parent
        while not where.exists() and where != where.parent:
            where = where.parent
        if not where.is_dir():
            raise StellarCalError(f"cannot write {path}: {where} is a file, not a directory: "
                                  "choose another path")
    if not os.access(where, os.W_OK | os.X_OK):
        raise StellarCalError(f"cannot write {path}: {where or Path('.')} is not writable")


def os_error_text(exc: OSError) -> str:
    """One line for an operating-system error: the path, what is wrong, what to do."""
    where = exc.filename if exc.filename is not None else ""
    what = exc.strerror or str(exc)
    if isinstance(exc, (FileExistsError, NotADirectoryError)):
        what += " (a file stands where the output needs a directory: choose another -o path)"
    elif isinstance(exc, IsADirectoryError):
        what += " (a directory stands where a file is needed)"
    elif isinstance(exc, PermissionError):
        what += " (no permission: choose a writable path)"
    return f"{where}: {what}" if where else what


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``stellar-cal`` and ``python -m stellar_cal_ros``."""
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        _load_method_modules(argv)
    except StellarCalError as exc:  # before parsing: the command is the first word
        name = f" {argv[0]}" if argv and not argv[0].startswith("-") else ""
        print(f"stellar-cal{name}: error: {one_line(exc)}", file=sys.stderr)
        return 1
    parser = build_parser()
    args = parser.parse_args(argv)
    from datetime import UTC, datetime

    from stellar_cal_ros.io.calibration import set_provenance
    from stellar_cal_ros.io.identity import deferred_bag_identity

    bag = getattr(args, "bag", None)
    set_provenance(command="stellar-cal " + " ".join(argv),
                   version=__version__, date=datetime.now(UTC).isoformat(
                       timespec="seconds"), bag=bag, bag_id=deferred_bag_identity(bag),
                   prior=getattr(args, "prior", None))
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    if not args.verbose:  # the package's own INFO lines; third-party ones only with -v
        logging.getLogger("stellar_cal_ros").setLevel(logging.INFO)
    try:
        for name, directory in OUTPUTS.get(args.command, ()):
            if getattr(args, name, None) is not None:
                check_output(Path(getattr(args, name)), directory)
        if bag is not None and not Path(bag).exists():  # every command's line, at once
            raise no_such_bag(bag)  # (batch said it after its first stage's note)
        if getattr(args, "check", None) is not None:  # what refuses the input at once
            args.check(args)
        if args.command in ROUNDS:  # the arrays a stage drops go back to the system
            from stellar_cal_ros.core.memory import return_freed_arrays

            return_freed_arrays()
        from stellar_cal_ros.progress import compile_notice_armed

        # a kernel compiled where the check ahead did not see it coming: said as it compiles
        compile_notice_armed(sys.stderr)
        if args.command in COMPILES:
            from stellar_cal_ros.methods.frame_step import compile_notice

            if compile_notice():
                compile_notice_armed(None)  # (said once)
        # a read past damage: the reader's warnings counted in the one data quality line
        hold_damage_warnings(getattr(args, "on_error", None) == "skip" and not args.verbose)
        with warnings.catch_warnings():
            warnings.showwarning = _one_line_warning(args.command)
            code = int(args.func(args) or 0)
        _say_unsaid(args.command)
        if args.command in COMPILES:  # the kernels it compiled or loaded: the next notice's
            from stellar_cal_ros.methods.frame_step import record_kernels_used

            record_kernels_used()
        return code
    except StellarCalError as exc:
        print(f"stellar-cal {args.command}: error: {one_line(exc)}{_hint(args, exc)}"
              f"{_unsaid_note(args)}", file=sys.stderr)
        return 1
    except OSError as exc:  # an output path that cannot be written, a vanished input
        log.debug("traceback", exc_info=True)
        print(f"stellar-cal {args.command}: error: {one_line(os_error_text(exc))}"
              f"{_unsaid_note(args)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    finally:
        set_provenance()  # this command's record ends with it (a caller may run another)
        hold_damage_warnings(False)
        from stellar_cal_ros.progress import compile_notice_armed

        compile_notice_armed(None)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
