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
