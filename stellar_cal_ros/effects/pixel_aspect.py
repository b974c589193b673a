"""Pixel aspect: non-square pixels, ``fy = fx · (1 + a)``."""

from __future__ import annotations

from typing import Any

import numpy as np

from stellar_cal_ros.effects.base import (
    FX,
    FY,
    BilinearCamera,
    Effect,
    ExportRole,
    Plausible,
    Stage,
)


class PixelAspect(Effect):
    """Pixel aspect a: ``fy = fx · (1 + a)``."""

    id = "pixel_aspect"
    order = 20
    budget_source = "pixel_aspect"
    export_role = ExportRole.CAMERA
    display_units = ("ppm", 1e6)
    plausible = Plausible(1000.0, "ppm")  # non-square pixels or a skewed readout
    stage = Stage.CAMERA
    parameter_names = ("aspect",)
    units = ("1",)
    default_sigma = (1e-3,)
    explanation = (
        "Pixels are not square (detector pitch differs along rows and columns) so the focal "
        "length in px differs between u and v. Residual: radial scale error of opposite sign "
        "along u and v, growing with distance from the centre. Typical size: 1e-5-1e-3."
    )

    def initial(self, prior: Any) -> tuple[np.ndarray, np.ndarray]:  # noqa: D102
        cam = prior.camera
        _, sigma = Effect.initial(self, prior)  # sigma.effects.pixel_aspect if present
        return np.array([cam.fy / cam.fx - 1.0]), sigma

    def store(self, value: np.ndarray, sigma: np.ndarray, cal: Any) -> None:  # noqa: D102
        # The value lives in the camera block only (OpenCV expresses it, contract §3): a
        # copy under ``effects`` would be a second, possibly stale, source of fy.
        p = cal.camera.parameters()
        p[FY] = p[FX] * (1.0 + value[0])
        cal.camera = cal.camera.with_parameters(p)
        cal.sigma.setdefault("effects", {})[self.id] = {"aspect": float(sigma[0])}

    def camera_parameters(self, value, p, ctx):  # noqa: D102
        out = p.copy()
        out[FY] = p[FX] * (1.0 + value[0])
        return out

    def camera_jacobian(self, value, p, ctx):  # noqa: D102
        J = np.zeros((18, 1))
        J[FY, 0] = p[FX]
        D = np.eye(18)
        D[FY, FY] = 0.0
        D[FY, FX] = 1.0 + value[0]
        return J, D

    def affine_form(self):  # noqa: D102 - fy = fx + a fx
        D0 = np.eye(18)
        D0[FY, FY], D0[FY, FX] = 0.0, 1.0
        Dv = np.zeros((1, 18, 18))
        Dv[0, FY, FX] = 1.0
        return BilinearCamera(D0, Dv, np.zeros((18, 1)))
