"""The tracker's clock drifting against the IMU's: a time offset growing with time."""

from __future__ import annotations

from typing import Any

import numpy as np

from stellar_cal_ros.effects.base import Effect, ExportRole, FrameContext, Plausible, Stage

#: a prior's ``stamp`` is the reference when at most this many s before the first frame (a
#: bag's start: the simulator's 0.254 s, a recorder started before the tracker); beyond it,
#: or after the first frame, it is another run's time and the first frame is the reference
START_LEAD = 10.0


class ClockDrift(Effect):
    """``t_true = header.stamp + r (header.stamp − t_ref)`` (beside ``time_offset``'s Δt).

    With ``time_offset`` the frames' offset is ``dt(t) = Δt + r (t − t_ref)``: the offset at
    ``t_ref`` and the rate the two clocks drift apart at.  ``t_ref`` (POSIX s) is the
    prior's ``effects.clock_drift.reference_stamp``, else the prior's ``stamp`` where it is
    the run's start (at most :data:`START_LEAD` s before the first frame the model sees: a
    simulated bag's prior, 0.254 s before its first frame), else the first frame's stamp;
    the result stores it.  A prior's stamp after the first frame is a result's (the time of
    its estimate, the end of its run: ``discover``'s second round starts from the first
    round's result) and one long before it an older calibration's: counted from there the
    candidate's rate would sit on a lever of −300 s at the first frames (its prior σ 1e-3:
    0.3 s of exposure time; unseen case ``rolling_cols`` s22, whose round-2 candidate moved
    a frame's exposure behind the one before and its run failed).  Without
    ``time_offset`` the offset at ``t_ref`` is 0 by assumption: an offset c there goes into
    the rate, about 1.5 c / T over a run T s long from ``t_ref`` (H198: 25 us, +0.13 ppm at
    300 s, 3σ).
    """

    id = "clock_drift"
    stage = Stage.TIME
    order = 20
    export_role = ExportRole.EXTRINSIC
    plausible = Plausible(1000.0, "ppm")  # a free-running crystal: 10-100 ppm, at most 1e-3
    parameter_names = ("rate",)
    units = ("1",)  # s per s
    display_units = ("ppm", 1e6)
    default_sigma = (1e-3,)
    requires = ("rate",)
    offered_on = "clock drift"  # a rate stands in for a clock's step: only where one drifts
    explanation = (
        "The tracker's clock runs at another rate than the IMU's (a free-running crystal: "
        "10-100 ppm, 1 ms every 10-100 s): the frames' time offset grows over the run. While "
        "the vehicle turns the residual is a shift along the direction of motion, "
        "proportional to the angular rate and to the time since the reference stamp; a "
        "constant time_offset takes its mean only. Typical: 1e-5 to 1e-4 s/s."
    )

    def __init__(self) -> None:
        self.reference_stamp = 0.0
        #: the reference is the prior's stamp until the first frame says whether it is the
        #: run's start (a result stores only a reference so set)
        self._provisional = False

    def initial(self, prior: Any) -> tuple[np.ndarray, np.ndarray]:  # noqa: D102
        block = (prior.effects or {}).get(self.id, {})
        stored = block.get("reference_stamp")
        self._provisional = stored is None
        self.reference_stamp = float(getattr(prior, "stamp", 0.0) or 0.0) if stored is None \
            else float(stored)
        _, sigma = Effect.initial(self, prior)  # sigma.effects.clock_drift
        return np.array([float(block.get("rate", 0.0))]), sigma

    def store(self, value: np.ndarray, sigma: np.ndarray, cal: Any) -> None:  # noqa: D102
        block = {"rate": float(value[0])}
        if not self._provisional:  # (before any frame: the run that reads it sets it)
            block["reference_stamp"] = self.reference_stamp
        cal.effects[self.id] = block
        cal.sigma.setdefault("effects", {})[self.id] = {"rate": float(sigma[0])}

    def _since(self, ctx: FrameContext) -> float:
        """Seconds from the reference stamp.

        The prior's stamp (not a stored reference) is checked at the first frame: kept where
        it is the run's start (:data:`START_LEAD`), else the frame's own stamp is the
        reference (a prior without a stamp, 0, as well: not the POSIX epoch's lever of
        1.7e9 s).
        """
        if self._provisional:
            self._provisional = False
            if not 0.0 <= ctx.stamp - self.reference_stamp <= START_LEAD:
                self.reference_stamp = float(ctx.stamp)
        return ctx.stamp - self.reference_stamp

    def time_shift(self, value: np.ndarray, ctx: FrameContext) -> float:  # noqa: D102
        return float(value[0]) * self._since(ctx)

    def time_shift_jacobian(self, value: np.ndarray, ctx: FrameContext) -> np.ndarray:  # noqa: D102
        return np.array([self._since(ctx)])
