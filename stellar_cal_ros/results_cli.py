"""``stellar-cal export``, ``report`` and ``compare``: what a user does with a result file.

``export RESULT.yaml --format kalibr|openvins|camera_info [-o OUT]``
    the calibration in another tool's format (:mod:`stellar_cal_ros.io.export`); every
    quantity the format cannot hold is printed as a warning.
``report RESULT.yaml [--bag BAG] [--residuals RES] [--history HIST] [--diagnosis JSON] -o DIR``
    PNGs and one HTML page of one run
    (:func:`stellar_cal_ros.diagnosis.report_html.write_run_report`).
``compare A.yaml B.yaml [--bag BAG] [--residuals RES_A RES_B] -o DIR``
    two runs of the model-discovery loop side by side
    (:func:`stellar_cal_ros.diagnosis.report_html.write_compare_report`).

Without residual files, ``report`` and ``compare`` re-run each calibration's method on the
bag from the calibration's values, as ``diagnose`` does (``--bag`` is needed then).
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import Any

from stellar_cal_ros.errors import StellarCalError

log = logging.getLogger("stellar_cal_ros")


def _cmd_export(args: argparse.Namespace) -> int:
    from stellar_cal_ros.io.calibration import load_calibration
    from stellar_cal_ros.io.export import default_output, write_export

    cal = load_calibration(args.result)
    out = args.output or default_output(args.result, args.format)
    ex = write_export(cal, args.format, out, rostopic=args.rostopic)
    for w in ex.warnings:
        log.warning("%s", w)
    print(f"wrote {out} ({args.format}; {len(ex.warnings)} warning"
          f"{'' if len(ex.warnings) == 1 else 's'})")
    return 0


def _history_for(result: Path, given: Path | None) -> dict | None:
    from stellar_cal_ros.io.residuals import read_residuals

    path = given or result.with_suffix(".history.csv")
    if path.is_file():
        return read_residuals(path)
    if given is not None:
        raise StellarCalError(f"history file {given} does not exist")
    log.info("no history file %s: the parameter-over-time plots are left out", path)
    return None


def _truth_for(bag: Path | None):
    from stellar_cal_ros.io.calibration import load_calibration

    if bag is None:
        return None
    truth = bag.with_suffix("").with_name(bag.with_suffix("").name + ".truth.yaml")
    return load_calibration(truth) if truth.is_file() else None


def check_run_files(cal, result: Path, residuals: Path | None, bag: Path | None,
                    bag_ids: dict[str, str | None] | None = None) -> None:
    """Refuse a residual table or a bag that is not the one ``result``'s run used.

    The result's ``provenance`` records the SHA-256 of the residual table its run wrote and
    the bag's content identity (:mod:`stellar_cal_ros.io.identity`); a result without them
    (older, or from the live node) cannot be checked, which is said once.
    """
    from stellar_cal_ros.io.identity import bag_identity, file_digest

    prov = cal.extra.get("provenance") or {}
    if residuals is not None:
        rec = prov.get("residuals") if isinstance(prov.get("residuals"), dict) else {}
        if rec.get("sha256"):
            if file_digest(residuals) != rec["sha256"]:
                raise StellarCalError(
                    f"{residuals} is not the residual table of the run that wrote {result} "
                    f"(that run wrote {rec.get('file', '?')}, whose content differs): give "
                    "that file, or --bag to re-run the result on its bag")
        else:
            log.warning("%s records no residual table of its run: cannot check that %s "
                        "belongs to it", result, residuals)
    if bag is not None:
        if prov.get("bag_id"):
            if bag_ids is None:
                bag_ids = {}
            if str(bag) not in bag_ids:
                bag_ids[str(bag)] = bag_identity(bag)
            if bag_ids[str(bag)] != prov["bag_id"]:
                raise StellarCalError(
                    f"{bag} is not the bag {result} was computed from ({prov.get('bag', '?')};"
                    " their content differs): give that bag")
        else:
            log.warning("%s records no bag identity: cannot check that it was computed from "
                        "%s", result, bag)
def _rerun_method(cal) -> str:
    """The method a result is re-run with: its own if it can be, else PSCE."""
    from stellar_cal_ros.methods import registry

    spec = registry.find(cal.method)
    return spec.name if spec is not None and spec.diagnosable else "psce"


def _settled_fraction(cal, given: Path | None) -> float:
    """The part of the residuals that is settled (the report's evaluation window).

    A filter's innovations after convergence (the second half); a batch fit's residuals are
    all final (and so are given files of results that are not a filter's).
    """
    from stellar_cal_ros.methods import registry

    spec = registry.get(_rerun_method(cal)) if given is None else registry.find(cal.method)
    return 0.5 if spec is not None and spec.kind == "filter" else 1.0


def _residuals_for(cal, result: Path, given: Path | None, bag: Path | None,
                   data_cache: dict[str, Any]) -> tuple[dict, dict | None, str]:
    """The run's residual table: the given file, or a re-run on the bag (with its history).

    The re-run uses the noise scales the result's run applied (its consistency block's
    ``noise``: ``replay --noise-scale`` or ``--estimate-noise``), so its residuals, NIS and
    verdict are those of that run, not of the noise as the bag states it.
    """
    from stellar_cal_ros.io.residuals import read_residuals

    check_run_files(cal, result, given, bag, data_cache.setdefault("bag_ids", {}))
    if given is not None:
        return read_residuals(given), None, f"residuals from {given}"
    if bag is None:
        raise StellarCalError(f"{result}: give its residual file (--residuals, written by "
                              "'replay --residuals') or the bag (--bag) to re-run it on")
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.noise import stated_scales
    from stellar_cal_ros.methods.replay import read_bag_data

    if "data" not in data_cache:
        data_cache["data"] = read_bag_data(bag, require_imu=False)  # star-only: bundle
    method = _rerun_method(cal)
    spec = method_spec(method)
    effects = list(spec.beyond_baseline(cal.estimated))
    noise = stated_scales(cal)
    log.info("re-running %s on %s from %s (effects: %s; noise %s)", method, bag, result,
             ", ".join(effects) or "baseline",
             "as stated" if noise.identity else f"as the run rescaled it: {noise.as_dict()}")
    run = spec.runner(data_cache["data"], rerun_prior(cal, effects), effects, keep_tables=True,
                      noise=None if noise.identity else noise)
    return run.residuals, run.history, (
        f"residuals from a re-run of {method} on the bag, starting at the values of "
        f"{result.name}" + ("" if noise.identity else ", with the noise scales its run "
                            "applied"))


def _cmd_report(args: argparse.Namespace) -> int:
    from stellar_cal_ros.diagnosis.report_html import write_run_report
    from stellar_cal_ros.io.calibration import load_calibration

    cal = load_calibration(args.result)
    cache: dict[str, Any] = {}
    res, rerun_hist, source = _residuals_for(cal, args.result, args.residuals, args.bag, cache)
    hist = _history_for(args.result, args.history) or rerun_hist
    summary = json.loads(args.diagnosis.read_text()) if args.diagnosis else None
    fraction = _settled_fraction(cal, args.residuals)
    path = write_run_report(args.output, cal, res, history=hist, summary=summary,
                            truth=_truth_for(args.bag), result_path=args.result,
                            bag=args.bag, residual_source=source, fraction=fraction)
    print(f"wrote {path}")
    return 0


def _cmd_compare(args: argparse.Namespace) -> int:
    from stellar_cal_ros.diagnosis.report_html import RunData, write_compare_report
    from stellar_cal_ros.io.calibration import load_calibration

    cache: dict[str, Any] = {}
    runs = []
    given = args.residuals or [None, None]
    cals = [load_calibration(args.a), load_calibration(args.b)]
    ids = [(c.extra.get("provenance") or {}).get("bag_id") for c in cals]
    if ids[0] and ids[1] and ids[0] != ids[1]:
        bags = [(c.extra.get("provenance") or {}).get("bag", "?") for c in cals]
        raise StellarCalError(f"{args.a} and {args.b} were computed from different bags "
                              f"({bags[0]} and {bags[1]}): compare puts two runs on one bag "
                              "side by side")
    for path, res_path, cal in zip((args.a, args.b), given, cals, strict=True):
        res, rerun_hist, source = _residuals_for(cal, path, res_path, args.bag, cache)
        hist = _history_for(path, None) or rerun_hist
        runs.append(RunData(path.stem, cal, res, hist, path, source))
    out = write_compare_report(args.output, runs[0], runs[1], truth=_truth_for(args.bag),
                               bag=args.bag)
    print(f"wrote {out}")
    return 0


def add_result_commands(sub: argparse._SubParsersAction) -> None:
    """Register ``export``, ``report`` and ``compare`` on the ``stellar-cal`` parser."""
    from stellar_cal_ros.io.export import DEFAULT_ROSTOPIC, FORMATS

    e = sub.add_parser("export", help="write a result in Kalibr, OpenVINS or ROS "
                       "camera_info format")
    e.add_argument("result", type=Path, help="RESULT.yaml (any calibration file)")
    e.add_argument("--format", required=True, choices=FORMATS,
                   help="kalibr: camchain-imucam.yaml; openvins: kalibr_imucam_chain.yaml; "
                        "camera_info: camera_calibration_parsers YAML")
    e.add_argument("-o", "--output", type=Path, default=None,
                   help="file to write (default: RESULT-<format file name>.yaml beside it)")
    e.add_argument("--rostopic", default=DEFAULT_ROSTOPIC,
                   help=f"image topic named in the kalibr/openvins file (default "
                        f"{DEFAULT_ROSTOPIC})")
    e.set_defaults(func=_cmd_export)

    r = sub.add_parser("report", help="plots and an HTML page of one calibration run")
    r.add_argument("result", type=Path, help="RESULT.yaml of a replay or batch run")
    r.add_argument("--bag", type=Path, default=None,
                   help="the bag the run used (provenance; BAG.truth.yaml beside it is "
                        "plotted; re-run source when --residuals is not given)")
    r.add_argument("--residuals", type=Path, default=None,
                   help="RES.csv/.parquet written by the run's --residuals")
    r.add_argument("--history", type=Path, default=None,
                   help="state history CSV (default: RESULT.history.csv if it exists)")
    r.add_argument("--diagnosis", type=Path, default=None,
                   help="diagnosis.json of 'diagnose' on this result: adds its candidates "
                        "and a plot behind every unexplained line")
    r.add_argument("-o", "--output", required=True, type=Path, help="REPORT_DIR to write")
    r.set_defaults(func=_cmd_report)

    c = sub.add_parser("compare", help="two runs of the model-discovery loop side by side")
    c.add_argument("a", type=Path, help="A.yaml: the earlier run (e.g. the baseline model)")
    c.add_argument("b", type=Path, help="B.yaml: the later run (e.g. with an added effect)")
    c.add_argument("--bag", type=Path, default=None,
                   help="the bag both runs used (truth beside it; re-run source)")
    c.add_argument("--residuals", type=Path, nargs=2, default=None, metavar=("RES_A", "RES_B"),
                   help="the two runs' residual files (default: re-run both on --bag)")
    c.add_argument("-o", "--output", required=True, type=Path, help="REPORT_DIR to write")
    c.set_defaults(func=_cmd_compare)
