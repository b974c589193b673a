"""The "traditional" installation calibration: zero velocity w.r.t. the Earth as reference.

The comparison method of Zhang et al. (IEEE Access 2018, §III, after Lu et al. 2017 and
Yang et al. 2017): a navigation-frame (local-level) Kalman filter whose velocity reference is
*zero velocity with respect to the Earth*, ``vⁿ = 0``, plus the same star measurements.

Implementation: the swaying-base filter (:class:`~stellar_cal_ros.methods.swaying.
SwayingFilter`, itself the shared kernel plus an inertial strapdown) with Z1 replaced by the
zero-velocity measurement expressed in the local-level frame n (ENU at the site)::

    ν = C_n_i (v_siteⁱ − v̂ⁱ) = C_n_i δvⁱ − v_swayⁿ,   R = σ_zupt² I   (σ_zupt = 0.01 m/s)

``C_n_i δvⁱ`` is exactly the navigation-frame velocity error of a local-level mechanization at
the site, so the linearized information is that of the navigation-frame filter; keeping one
mechanization isolates the one thing that differs — the reference.  On a swaying base the
reference is wrong by the sway velocity (up to 1.5 m/s), which a zero-velocity filter reads
as tilt and accelerometer bias, and that biases the installation estimate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stellar_cal_ros.core import earth
from stellar_cal_ros.methods import swaying
from stellar_cal_ros.methods.registry import MethodSpec
from stellar_cal_ros.methods.swaying import SwayingConfig, SwayingFilter


@dataclass
class TraditionalConfig(SwayingConfig):
    """Swaying-base defaults with the zero-velocity reference."""

    velocity_reference: str = "zero_velocity"
    zero_velocity_sigma_mps: float = 0.01  #: σ of the zero-velocity "measurement"
    position_interval_s: float = 0.5  #: every star frame


class TraditionalFilter(SwayingFilter):
    """Navigation-frame zero-velocity reference (see the module docstring)."""

    method = "traditional"

    def __init__(self, model, t0, site, config: SwayingConfig | None = None, *,
                 nominal_dt: float, consider: int = 0) -> None:
        super().__init__(model, t0, site, config or TraditionalConfig(),
                         nominal_dt=nominal_dt, consider=consider)

    def _grid_functions(self) -> dict:
        out = super()._grid_functions()
        R_e_n = earth.R_itrs_enu(self.site)
        dut1 = self.config.dut1
        # C_n_i = R_e_nᵀ R_e_i with x_itrs = R_itrs_gcrs x_gcrs
        out["C_n_i"] = lambda t: np.einsum(
            "ji,njk->nik", R_e_n, earth.R_itrs_gcrs(t, dut1)).reshape(len(t), 9)
        return out

    def reference_measurement(self):  # noqa: D102
        c = self.config
        if c.velocity_reference != "zero_velocity":
            return super().reference_measurement()
        C_n_i = self.grid.interp("C_n_i", self.t)[0].reshape(3, 3)
        nu = C_n_i @ (self.site_velocity(self.t) - self.velocity)
        H = np.zeros((3, self.N))
        H[:, self.iv] = C_n_i
        return nu, H, c.zero_velocity_sigma_mps**2 * np.eye(3)


def replay_traditional(bag, prior, effects: list[str] | None = None,
                       config: TraditionalConfig | None = None, progress: bool = False, **kw):
    """Run the traditional (zero-velocity, navigation-frame) filter over a bag."""
    from stellar_cal_ros.methods.replay import replay

    return replay(bag, prior, "traditional", effects, config or TraditionalConfig(),
                  progress=progress, **kw)


METHOD = MethodSpec(
    name="traditional", kind="filter",
    summary="zero velocity w.r.t. the Earth as the reference (the comparison method of "
            "Zhang et al.); needs /gnss/fix",
    # the swaying-base filter with another reference: its model, site and IMU look-ahead
    **{key: getattr(swaying.METHOD, key)
       for key in ("baseline", "stages", "needs_site", "imu_lookahead")},
    filter_cls=TraditionalFilter, config_cls=TraditionalConfig)
