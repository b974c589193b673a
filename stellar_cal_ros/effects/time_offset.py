"""Time offset between the star tracker's reported stamp and the true mid-exposure."""

from __future__ import annotations

from typing import Any

import numpy as np

from stellar_cal_ros.effects.base import Effect, ExportRole, FrameContext, Plausible, Stage


class TimeOffset(Effect):
    """``t_true = header.stamp + Δt`` (contract §3 ``time_offset``)."""

    id = "time_offset"
    stage = Stage.TIME
    order = 10
    export_role = ExportRole.EXTRINSIC
    plausible = Plausible(50.0, "ms")  # readout, transport, clock offsets
    parameter_names = ("dt",)
    units = ("s",)
    default_sigma = (0.05,)
    requires = ("rate",)
    explanation = (
        "The tracker stamps its frames late or early (readout, transport, clock offset). While "
        "the vehicle turns, the attitude at the stamp differs from the one at exposure by "
        "rate x offset: the residual is a shift along the direction of motion, proportional "
        "to the angular rate, and zero at rest. Typical: 1-100 ms."
    )

    def initial(self, prior: Any) -> tuple[np.ndarray, np.ndarray]:  # noqa: D102
        sig = (prior.sigma or {}).get("time_offset")
        sigma = float(sig) if isinstance(sig, (int, float)) and sig > 0 else self.default_sigma[0]
        return np.array([float(prior.time_offset)]), np.array([sigma])

    def store(self, value: np.ndarray, sigma: np.ndarray, cal: Any) -> None:  # noqa: D102
        cal.time_offset = float(value[0])
        cal.sigma["time_offset"] = float(sigma[0])

    def time_shift(self, value: np.ndarray, ctx: FrameContext) -> float:  # noqa: D102
        return float(value[0])

    def time_shift_jacobian(self, value: np.ndarray, ctx: FrameContext) -> np.ndarray:  # noqa: D102
        return np.ones(1)

    def affine_form(self) -> np.ndarray:  # noqa: D102
        return np.ones(1)
