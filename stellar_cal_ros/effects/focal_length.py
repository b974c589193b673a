"""Focal length f in px (``fx = f``, ``fy = f · fy/fx`` of the prior)."""

from __future__ import annotations

from typing import Any

import numpy as np

from stellar_cal_ros.effects.base import (
    FX,
    FY,
    Effect,
    ExportRole,
    Plausible,
    Stage,
    _camera_sigma,
    _store_camera_sigma,
)


class FocalLength(Effect):
    """Focal length f, px (``fx = f``, ``fy = f · fy/fx`` of the prior)."""

    id = "focal_length"
    order = 10
    budget_source = "focal_length"
    export_role = ExportRole.CAMERA
    #: a share of the focal length (manufacturing tolerance, focus): 20 px of the demo's f
    plausible = Plausible(0.5, "% of f")
    stage = Stage.CAMERA
    parameter_names = ("f",)
    units = ("px",)
    default_sigma = (20.0,)
    simulation_units = ("px from nominal",)
    simulation_relative = True
    explanation = (
        "The effective focal length differs from the datasheet (manufacturing, focus, "
        "temperature). Star separations on the detector scale by f: the residual is radial, "
        "growing linearly with distance from the principal point. Typical size: 0.01-1 %."
    )

    def __init__(self) -> None:
        self.ratio = 1.0

    def initial(self, prior: Any) -> tuple[np.ndarray, np.ndarray]:  # noqa: D102
        cam = prior.camera
        self.ratio = cam.fy / cam.fx
        return np.array([cam.fx]), _camera_sigma(prior, ("fx",), self.default_sigma)

    def store(self, value: np.ndarray, sigma: np.ndarray, cal: Any) -> None:  # noqa: D102
        p = cal.camera.parameters()
        p[FX], p[FY] = value[0], value[0] * self.ratio
        cal.camera = cal.camera.with_parameters(p)
        _store_camera_sigma(cal, ("fx", "fy"), np.array([sigma[0], sigma[0] * self.ratio]))

    def plausible_gain(self, calibration: Any) -> np.ndarray:
        """Percent of the camera's focal length per px (NaN without a camera)."""
        cam = getattr(calibration, "camera", None)
        return np.array([100.0 / cam.fx if cam is not None else np.nan])

    def camera_parameters(self, value, p, ctx):  # noqa: D102
        out = p.copy()
        out[FX], out[FY] = value[0], value[0] * self.ratio
        return out

    def camera_jacobian(self, value, p, ctx):  # noqa: D102
        # depends on the prior's ratio only: built once per ratio, read-only
        cached = self.__dict__.get("_camera_jacobian")
        if cached is None or cached[0] != self.ratio:
            J = np.zeros((18, 1))
            J[FX, 0], J[FY, 0] = 1.0, self.ratio
            D = np.eye(18)
            D[FX, FX] = D[FY, FY] = 0.0
            J.setflags(write=False)
            D.setflags(write=False)
            cached = self._camera_jacobian = (self.ratio, J, D)
        return cached[1], cached[2]

    def affine_form(self):  # noqa: D102
        return self.camera_jacobian(None, None, None)
