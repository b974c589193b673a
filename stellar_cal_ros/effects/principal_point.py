"""Principal point: where the optical axis meets the detector (OpenCV cx, cy)."""

from __future__ import annotations

from stellar_cal_ros.effects.base import CameraSetEffect, Plausible


class PrincipalPoint(CameraSetEffect):
    """Principal point (cx, cy), px."""

    id = "principal_point"
    order = 30
    budget_source = "principal_point"
    plausible = Plausible(20.0, "px")  # detector placement, ~0.13 mm at 6.45 um pixels
    camera_entries = ("cx", "cy")
    parameter_names = ("cx", "cy")
    units = ("px", "px")
    default_sigma = (20.0, 20.0)
    simulation_units = ("px from nominal", "px from nominal")
    simulation_relative = True
    explanation = (
        "The optical axis meets the detector away from its centre (lens decentering, detector "
        "placement). Alone it shifts every star equally, which a small installation rotation "
        "about x/y mimics; only the combination, the equivalent principal point, is sharply "
        "observable. Residual signature: a uniform offset plus a radial-scale pattern centred "
        "off the image centre. Typical size: 1-20 px."
    )
