"""Decentering (tangential) distortion p1, p2 (OpenCV)."""

from __future__ import annotations

from stellar_cal_ros.effects.base import CameraSetEffect, Plausible


class Tangential(CameraSetEffect):
    """Decentering (tangential) distortion p1, p2."""

    id = "tangential"
    order = 60
    budget_source = "distortion"
    plausible = Plausible(2.0, "px", at="corner")
    camera_entries = ("p1", "p2")
    parameter_names = ("p1", "p2")
    units = ("1", "1")
    default_sigma = (0.002, 0.002)
    explanation = (
        "Lens elements are decentered, so distortion is not symmetric about the axis. "
        "Residual: a pattern with one preferred direction, growing with r^2, partly "
        "tangential. Typical size: 0.01-1 px at the edge."
    )
