"""Focal length drift with the optical-head temperature."""

from __future__ import annotations

from typing import Any

import numpy as np

from stellar_cal_ros.effects.base import (
    FX,
    FY,
    BilinearCamera,
    Effect,
    FrameContext,
    Plausible,
    Stage,
)


class ThermalFocalLength(Effect):
    """Focal length drift with the optical-head temperature: ``f(T) = f (1 + c (T − T_ref))``."""

    id = "thermal_focal_length"
    order = 80
    plausible = Plausible(100.0, "ppm/degC")  # lens barrel expansion and dn/dT together
    stage = Stage.CAMERA
    parameter_names = ("coefficient_per_c",)
    units = ("1/degC",)
    default_sigma = (5e-5,)
    requires = ("head_temperature",)
    explanation = (
        "The lens barrel and spacers expand with temperature, changing the focal length by "
        "about 1e-6 to 3e-5 per degC. Residual: a radial scale error that follows the head "
        "temperature (/star_tracker/temperature) in time, not the attitude."
    )

    def __init__(self) -> None:
        self.reference_c = 20.0

    def initial(self, prior: Any) -> tuple[np.ndarray, np.ndarray]:  # noqa: D102
        block = (prior.effects or {}).get(self.id, {})
        self.reference_c = float(block.get("reference_temperature_c", 20.0))
        _, sigma = Effect.initial(self, prior)  # sigma.effects.thermal_focal_length
        return np.array([float(block.get("coefficient_per_c", 0.0))]), sigma

    def store(self, value: np.ndarray, sigma: np.ndarray, cal: Any) -> None:  # noqa: D102
        cal.effects[self.id] = {"coefficient_per_c": float(value[0]),
                                "reference_temperature_c": self.reference_c}
        cal.sigma.setdefault("effects", {})[self.id] = {"coefficient_per_c": float(sigma[0])}

    def _dT(self, ctx: FrameContext) -> float:
        T = ctx.head_temperature_c
        return 0.0 if not np.isfinite(T) else float(T - self.reference_c)

    def camera_parameters(self, value, p, ctx):  # noqa: D102
        out = p.copy()
        s = 1.0 + value[0] * self._dT(ctx)
        out[FX] *= s
        out[FY] *= s
        return out

    def camera_jacobian(self, value, p, ctx):  # noqa: D102
        dT = self._dT(ctx)
        J = np.zeros((18, 1))
        J[FX, 0], J[FY, 0] = p[FX] * dT, p[FY] * dT
        D = np.eye(18)
        D[FX, FX] = D[FY, FY] = 1.0 + value[0] * dT
        return J, D

    def affine_form(self):  # noqa: D102 - f' = f + c ΔT f
        Dv = np.zeros((1, 18, 18))
        Dv[0, FX, FX] = Dv[0, FY, FY] = 1.0
        return BilinearCamera(np.eye(18), Dv, np.zeros((18, 1)))

    def camera_scale(self, ctx):  # noqa: D102
        return np.array([self._dT(ctx)])
