"""Radial distortion k1, k2 (OpenCV, normalized coordinates)."""

from __future__ import annotations

from stellar_cal_ros.effects.base import CameraSetEffect, Plausible


class RadialK1K2(CameraSetEffect):
    """Radial distortion k1, k2 (OpenCV, normalized coordinates)."""

    id = "radial_k1k2"
    order = 40
    budget_source = "distortion"
    #: each term moves a star at the detector corner by up to this many px (k1 = 0.3, k2 = 1
    #: were 7 and 0.8 px on the demo's 15° field, 50 and 39 px on a 38° one)
    plausible = Plausible((10.0, 5.0), "px", at="corner")
    camera_entries = ("k1", "k2")
    parameter_names = ("k1", "k2")
    units = ("1", "1")
    default_sigma = (0.3, 1.0)
    explanation = (
        "Lens radial distortion: image points move along the radius by k1 r^3 + k2 r^5. "
        "Residual: radial vectors, near zero at the centre, growing steeply to the corners "
        "(pincushion or barrel). Typical size: 0.1-5 px at the field edge."
    )
