"""Exception hierarchy of stellar_cal_ros.

Every error the package raises on purpose derives from :class:`StellarCalError`, so a
caller (the CLI, a ROS node) can catch one type and print a clear message instead of a
traceback.
"""

from __future__ import annotations


class StellarCalError(Exception):
    """Base class of all errors raised on purpose by stellar_cal_ros."""


class BagError(StellarCalError):
    """A bag cannot be read or written (missing, corrupt, truncated, wrong schema)."""


class CheckpointError(StellarCalError):
    """A checkpoint file is missing, truncated, corrupt (checksum) or of another format."""


class MessageDecodeError(BagError):
    """One message cannot be decoded; the text names the topic and the log time."""

    def __init__(self, topic: str, log_time_ns: int, reason: str) -> None:
        self.topic = topic
        self.log_time_ns = log_time_ns
        self.reason = reason
        super().__init__(
            f"cannot decode message on {topic} at t={log_time_ns * 1e-9:.9f} s: {reason}"
        )


class CalibrationFileError(StellarCalError):
    """A calibration YAML is missing, malformed or of an unknown format."""


class ModelError(StellarCalError):
    """A model is asked for something it cannot do (bad parameter, unknown effect id)."""


class ScenarioError(StellarCalError):
    """A simulation scenario or effect injection is invalid."""


class DataError(StellarCalError):
    """The input data contradict the contract in a way no calibration can absorb.

    E.g. a gyro that reports deg/s where rad/s is expected, or star and IMU clocks an hour
    apart; the text names the likely cause.
    """


def one_line(text: str) -> str:
    """``text`` as one line: its non-blank lines stripped and joined by '; '.

    What a command prints as ``stellar-cal CMD: error: ...`` must be one line whatever a
    library put into the message (yaml's excerpt with a caret, a nested error's lines).
    """
    return "; ".join(ln.strip() for ln in str(text).splitlines() if ln.strip())


def yaml_error_text(exc: Exception) -> str:
    """One line for a YAML parse error: line and column of the problem and what it is.

    ``yaml.MarkedYAMLError`` prints the offending lines with a caret under them; a user
    reads 'line 7, column 15: expected ',' or ']', but got ':' (while parsing a flow
    sequence started at line 5)' instead. Other errors: :func:`one_line` of their text.
    """
    problem = getattr(exc, "problem", None)
    if not problem:
        return one_line(str(exc))
    mark = getattr(exc, "problem_mark", None)
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    context = getattr(exc, "context", None)
    cmark = getattr(exc, "context_mark", None)
    if context:
        started = f" started at line {cmark.line + 1}" if cmark is not None else ""
        return f"{where}{problem} ({context}{started})"
    return f"{where}{problem}"
