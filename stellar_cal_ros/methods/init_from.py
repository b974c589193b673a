"""A Kalman-filter prior that starts from an earlier solution (``replay --init-from``).

The batch method (:mod:`~stellar_cal_ros.methods.acf`) gives a first solution; the filters
start from it with its σ for what it estimated and the datasheet σ for the rest.
"""

from __future__ import annotations

import copy
import logging
import os
from typing import Any

from stellar_cal_ros.errors import ModelError
from stellar_cal_ros.io.calibration import Calibration

log = logging.getLogger(__name__)


def _merge_sigma(base: Any, over: Any) -> Any:
    """``over`` on top of ``base`` (dicts merged recursively, other leaves replaced).

    In σ arrays of one length, an entry ``over`` leaves at 0 (a result's "not estimated")
    keeps ``base``'s value.
    """
    if isinstance(base, dict) and isinstance(over, dict):
        out = copy.deepcopy(base)
        for k, v in over.items():
            out[k] = _merge_sigma(base.get(k), v) if k in base else copy.deepcopy(v)
        return out
    if isinstance(base, list) and isinstance(over, list) and len(base) == len(over):
        return [b if isinstance(o, (int, float)) and o == 0 else copy.deepcopy(o)
                for b, o in zip(base, over, strict=True)]
    return copy.deepcopy(over)


def prior_from_result(prior: Calibration, result: Calibration,
                      source: str | os.PathLike[str] | None = None) -> Calibration:
    """A Kalman-filter prior that starts from an earlier solution (``replay --init-from``).

    Values: every value of ``result`` (camera, installation, sensor blocks, time offset,
    effects).  Sigmas: the result's sigma block, with ``prior``'s sigma for any key the
    result does not carry (and for the 0 entries of its σ arrays).  A result stores the σ
    of what it estimated only, so the filter starts at the batch estimate with the batch
    uncertainty and the datasheet uncertainty of what the batch did not estimate.

    Only marginal σ are carried (the file has no covariance): the strong principal-point /
    installation-tilt correlation of a batch solution is dropped, so the filter starts wider
    than the batch along that combination — conservative, and the stars re-determine the
    combination within a few frames.
    """
    if (result.camera.width, result.camera.height) != (prior.camera.width,
                                                       prior.camera.height):
        raise ModelError(
            f"--init-from: the result's image size {result.camera.width}x"
            f"{result.camera.height} differs from the prior's {prior.camera.width}x"
            f"{prior.camera.height}")
    if result.frames != prior.frames:
        log.warning("--init-from: frame ids %s differ from the prior's %s", result.frames,
                    prior.frames)
    if not result.sigma:
        log.warning("--init-from: the result has no sigma block; the prior's sigmas are used")
    init = copy.deepcopy(result)
    init.sigma = _merge_sigma(prior.sigma or {}, result.sigma or {})
    init.method = "prior"
    init.estimated = []
    init.extra = {"init_from": {"file": str(source) if source is not None else "",
                                "method": result.method, "stamp": float(result.stamp)}}
    log.info("starting from the %s solution%s (values and sigmas)", result.method,
             f" in {source}" if source is not None else "")
    return init
