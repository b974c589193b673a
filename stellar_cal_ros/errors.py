"""Exception hierarchy of stellar_cal_ros.

Every error the package raises on purpose derives from :class:`StellarCalError`, so a
caller (the CLI, a ROS node) can catch one type and print a clear message instead of a
traceback.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import argparse


class StellarCalError(Exception):
    """Base class of all errors raised on purpose by stellar_cal_ros."""


class BagError(StellarCalError):
    """A bag cannot be read or written (missing, corrupt, truncated, wrong schema)."""


def no_such_bag(path: object) -> BagError:
    """The error for a bag path that does not exist: one wording for every command and node.

    (``info`` and the player said "bag not found: PATH", ``replay``/``diagnose`` "PATH: no
    such bag ...".)
    """
    return BagError(f"{path}: no such bag (a .mcap or ROS 1 .bag file, or a rosbag2 directory)")


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


class BagDamageWarning(UserWarning):
    """What a read of a damaged bag met (a part skipped, met again; a scan for want of an index).

    A part skipped (``on_error="skip"``), a part met again, a bag scanned for want of its
    index or summary.
    A library caller sees each; the command line under ``--on-error skip`` holds them
    (:func:`hold_damage_warnings`) and counts them in its one ``data quality`` line, which
    says what was lost (``-v`` prints them as they come).
    """


class _Held:
    """The damage warnings the command line holds, and whether a data quality line said them.

    ``lines`` None: not holding.
    """

    lines: list[str] | None = None
    said = False


_HELD = _Held()


def hold_damage_warnings(hold: bool) -> None:
    """Hold the :class:`BagDamageWarning` texts from now on (False: stop, forget them)."""
    _HELD.lines = [] if hold else None
    _HELD.said = False


def held_damage_warning(text: str) -> bool:
    """Hold one warning's text when holding (True); False: the caller prints it."""
    if _HELD.lines is None:
        return False
    _HELD.lines.append(text)
    return True


def held_damage_note() -> str:
    """The held warnings counted for a data quality line ('' when none are held)."""
    if not _HELD.lines:
        return ""
    _HELD.said = True
    n = len(_HELD.lines)
    return (f"the reader's {n} warning{'s' * (n != 1)} about the damage counted here, not "
            "printed (`stellar-cal -v ...` prints them)")


def unsaid_damage_warnings() -> list[str]:
    """The held warnings no data quality line has counted (the command printed none)."""
    return [] if _HELD.said or _HELD.lines is None else list(_HELD.lines)


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


def on_error_argument(p: argparse.ArgumentParser, what: str) -> None:
    """``--on-error``: the bag reader's skip mode (replay, batch, diagnose, discover, twin)."""
    p.add_argument("--on-error", choices=["raise", "skip"], default="raise",
                   help=f"skip: {what} a truncated or damaged bag on what it holds, dropping "
                        "and counting malformed messages; what was lost is printed in one "
                        "line and recorded (data_quality, doc/interfaces.md) (default: stop "
                        "with an error)")
