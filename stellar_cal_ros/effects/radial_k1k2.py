"""Radial distortion k1, k2 (OpenCV, normalized coordinates)."""

from __future__ import annotations

from stellar_cal_ros.effects.base import CameraSetEffect, Plausible


class RadialK1K2(CameraSetEffect):
    """Radial distortion k1, k2 (OpenCV, normalized coordinates)."""

    id = "radial_k1k2"
    order = 40
    budget_source = "distortion"
    plausible = Plausible((0.3, 1.0), "1")
    camera_entries = ("k1", "k2")
    parameter_names = ("k1", "k2")
    units = ("1", "1")
    default_sigma = (0.3, 1.0)
    explanation = (
        "Lens radial distortion: image points move along the radius by k1 r^3 + k2 r^5. "
        "Residual: radial vectors, near zero at the centre, growing steeply to the corners "
        "(pincushion or barrel). Typical size: 0.1-5 px at the field edge."
    )
