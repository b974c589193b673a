"""Detector tilt against the optical axis (OpenCV tau_x, tau_y; Sun et al. 2013)."""

from __future__ import annotations

from stellar_cal_ros.effects.base import CameraSetEffect, Plausible


class ImagePlaneTilt(CameraSetEffect):
    """Detector tilt against the optical axis (OpenCV tau_x, tau_y)."""

    id = "image_plane_tilt"
    order = 70
    budget_source = "image_plane_tilt"
    display_units = ("mrad", 1e3)
    plausible = Plausible(10.0, "mrad")  # detector mounting tolerance, up to ~0.6 deg
    # 50 mrad (2.9 deg): across a 6.6 mm detector the focus moves by 0.33 mm, some 10x a
    # fast star-tracker lens's depth of focus: no focused tracker is tilted that far (the
    # unseen case 'rolling', seed 23, fitted 122 mrad standing in for a rolling shutter)
    physical_limit = 0.05
    camera_entries = ("tau_x", "tau_y")
    parameter_names = ("tau_x", "tau_y")
    units = ("rad", "rad")
    default_sigma = (5e-3, 5e-3)
    explanation = (
        "The detector is not perpendicular to the optical axis (Scheimpflug-like tilt). One "
        "side of the image is farther from the lens: a keystone pattern whose scale changes "
        "linearly across the image (Sun et al. 2013). Typical size: 0.1-10 mrad."
    )
