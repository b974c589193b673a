"""What the live calibrator tells its operator.

The model verdict, the library's warnings on ``/rosout``, and the provenance of the result
it writes:

* :func:`verdict_status` turns the consistency of the second half of the data seen so far
  (:class:`~stellar_cal_ros.methods.results.HalfWindowStats`, the replay's statistics) into
  a ``/diagnostics`` level and a message whose text changes only when the state does (the
  numbers go to the status' values);
* :class:`RosoutBridge` forwards the package's Python log records (e.g. the filter's "the
  model misses an effect") to the node's rclpy logger, hence to ``/rosout``, instead of the
  process' stderr;
* :func:`node_provenance` records how the node runs for the result YAML it writes.
"""

from __future__ import annotations

import logging
import sys
from datetime import UTC, datetime
from typing import Any

from diagnostic_msgs.msg import DiagnosticStatus

from stellar_cal_ros import __version__
from stellar_cal_ros.io.calibration import provenance_record
from stellar_cal_ros.methods.results import VERDICT_MESSAGES


def verdict_status(cons: dict[str, Any], converged: bool,
                   degraded: list[str] | tuple[str, ...] = ()) -> tuple[bytes, str]:
    """``(level, message)`` of an initialized filter from its consistency block.

    ``degraded``: why the result is not to be trusted (``Calibrator.degraded()``: a gyro
    that disagrees with the stars, clock faults); any reason makes the level ERROR, whatever
    the residuals say (a gyro in deg/s can leave them consistent).
    """
    if degraded:
        more = f" (and {len(degraded) - 1} more)" if len(degraded) > 1 else ""
        return DiagnosticStatus.ERROR, f"result degraded: {degraded[0]}{more}"
    verdict = cons.get("verdict", "no data")
    if verdict == "model mismatch":
        return DiagnosticStatus.WARN, VERDICT_MESSAGES[verdict]
    state = "converged" if converged else "estimating (not converged yet)"
    if verdict == "conservative":
        return DiagnosticStatus.OK, f"{state}; {VERDICT_MESSAGES[verdict]}"
    return DiagnosticStatus.OK, state


def verdict_values(cons: dict[str, Any]) -> dict[str, str]:
    """The consistency numbers as ``/diagnostics`` values."""
    out = {"consistency.verdict": str(cons.get("verdict", "no data"))}
    for key, fmt in (("nis_per_dof", "{:.3f}"), ("whiteness_p", "{:.3g}"), ("stars", "{}"),
                     ("window_start", "{:.3f}")):
        if cons.get(key) is not None:
            out[f"consistency.{key}"] = fmt.format(cons[key])
    if cons.get("interval"):
        out["consistency.interval"] = "{:.3f}..{:.3f}".format(*cons["interval"])
    for key in ("rms_px", "expected_rms_px"):
        if cons.get(key):
            out[f"consistency.{key}"] = "{:.4f} {:.4f}".format(*cons[key])
    return out


class RosoutBridge(logging.Handler):
    """Forward the package's log records to an rclpy logger (hence ``/rosout``)."""

    def __init__(self, ros_logger: Any) -> None:
        super().__init__(logging.INFO)
        self.ros_logger = ros_logger

    def emit(self, record: logging.LogRecord) -> None:  # noqa: D102
        try:
            text = self.format(record)
            if record.levelno >= logging.ERROR:
                self.ros_logger.error(text)
            elif record.levelno >= logging.WARNING:
                self.ros_logger.warning(text)
            else:
                self.ros_logger.info(text)
        except Exception:  # noqa: BLE001 - logging must never raise into the filter
            self.handleError(record)

    def install(self, name: str = "stellar_cal_ros") -> None:
        """Route logger ``name`` (and its children) here only, not to stderr."""
        logger = logging.getLogger(name)
        logger.addHandler(self)
        logger.propagate = False
        if logger.level == logging.NOTSET:
            logger.setLevel(logging.INFO)

    def remove(self, name: str = "stellar_cal_ros") -> None:
        """Undo :meth:`install`."""
        logger = logging.getLogger(name)
        logger.removeHandler(self)
        if not any(isinstance(h, RosoutBridge) for h in logger.handlers):
            logger.propagate = True


def node_provenance(node_name: str, params: dict[str, Any],
                    defaults: dict[str, Any]) -> dict[str, Any]:
    """How the node runs, for the result it writes (``save_calibration(provenance=)``).

    Its parameters that differ from the defaults, version, start date, prior.  The node
    keeps its own record: a process-wide one would stamp another node's (or, after the
    node is gone, a later command's) result with this node's prior and date.
    """
    given = " ".join(f"-p {k}:={v}" for k, v in params.items()
                     if k in defaults and v != defaults[k] and v not in (None, [], ""))
    exe = sys.argv[0].rsplit("/", 1)[-1].removesuffix(".py") if sys.argv and sys.argv[0] \
        else node_name
    return provenance_record(command=f"{exe} --ros-args {given}".strip(), node=node_name,
                             version=__version__,
                             date=datetime.now(UTC).isoformat(timespec="seconds"),
                             prior=params.get("prior_file") or None,
                             method=params.get("method"),
                             effects=list(params.get("effects") or []) or None)
