"""``stellar-cal diagnose``: compare model and measurements, name the missing effect."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

from stellar_cal_ros.diagnosis import report, stats
from stellar_cal_ros.diagnosis.context import add_gravity_regressors
from stellar_cal_ros.diagnosis.discover import method_spec, rank_candidates, summary_dict
from stellar_cal_ros.io.calibration import Calibration
from stellar_cal_ros.methods.replay import BagData, read_bag_data

log = logging.getLogger(__name__)


def diagnose(
    bag: str | Path | BagData,
    calibration: Calibration,
    method: str,
    effects: list[str],
    output_dir: str | Path,
    candidates: list[str] | None = None,
    evaluation_fraction: float = 0.5,
    plots: bool = True,
    verbose: bool = True,
) -> dict[str, Any]:
    """Run the diagnosis; write ``diagnosis.json`` and ``report.html``; return the summary."""
    out = Path(output_dir)
    out.mkdir(parents=True, exist_ok=True)
    data = bag if isinstance(bag, BagData) else read_bag_data(bag)
    spec = method_spec(method)

    def tell(effect_id: str) -> None:
        if verbose:
            print(f"   trying {effect_id} ...", flush=True)

    base, results = rank_candidates(data, calibration, spec, effects, candidates,
                                    evaluation_fraction, progress=tell)
    # the top candidate (a candidate tested after it may be significant too, but it is the
    # one to add first); its re-run from its own calibration is where the next iteration
    # starts
    best = next((c for c in results if c.significant_alone), None)
    best_run = None if best is None else (best.refined_run or best.run)
    final = best_run if best_run is not None else base
    cam = calibration.camera
    centre = (cam.cx, cam.cy)
    mask = stats.evaluation_mask(final.residuals, evaluation_fraction)
    # The residual table lacks the gravity direction that mount flexure follows: add it.
    final_cal = final.calibration
    final_res = add_gravity_regressors(final.residuals, data, final_cal)
    unexplained = stats.regressor_tests(final_res, mask, centre)
    summary = summary_dict(base, results, unexplained, spec, effects, evaluation_fraction)
    summary["recommendation"] = best.effect if best is not None else None
    (out / "diagnosis.json").write_text(json.dumps(summary, indent=1, default=float))
    if plots:
        panels = [("current model", base.residuals)]
        if best is not None:
            panels.append((f"+ {best.effect}", best_run.residuals))
        report.plot_vector_fields(panels, cam.width, cam.height, evaluation_fraction,
                                  out / "vector_field.png")
        report.plot_regressors(panels, centre, evaluation_fraction, out / "regressors.png")
        report.plot_time(panels, out / "time.png")
        images = [("Mean innovation over the detector (regional bins)", "vector_field.png"),
                  ("Innovations against possible causes", "regressors.png"),
                  ("Innovations against time", "time.png")]
        report.write_html(out, summary, images, "stellar_cal diagnosis")
    return summary
