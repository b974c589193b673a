"""Sixth-order radial distortion k3 (OpenCV, normalized coordinates)."""

from __future__ import annotations

from stellar_cal_ros.effects.base import CameraSetEffect, Plausible


class RadialK3(CameraSetEffect):
    """Sixth-order radial distortion k3."""

    id = "radial_k3"
    order = 50
    budget_source = "distortion"
    #: a coefficient means nothing without the lens: k3 = 2 moves a corner star by 0.05 px
    #: on the demo's 15° field and by 18 px on a 38° one; the plausible size is the
    #: displacement, converted through the run's camera
    plausible = Plausible(5.0, "px", at="corner")
    camera_entries = ("k3",)
    parameter_names = ("k3",)
    units = ("1",)
    default_sigma = (2.0,)
    explanation = (
        "Higher-order radial distortion (r^7 term) of fast or wide lenses. Residual: radial "
        "vectors confined to the outer field after k1, k2 are fitted; a change of sign between "
        "mid-field and corners. Typical size: 0.01-0.5 px at the corners."
    )
