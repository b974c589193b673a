"""The "traditional" installation calibration: zero velocity w.r.t. the Earth as reference.

The comparison method of Zhang et al. (IEEE Access 2018, §III, after Lu et al. 2017 and
Yang et al. 2017): a navigation-frame (local-level) Kalman filter whose velocity reference is
*zero velocity with respect to the Earth*, ``vⁿ = 0``, plus the same star measurements.

Implementation: the same error-state filter, strapdown and star update as
:class:`~stellar_cal_ros.methods.swaying.SwayingFilter`, with Z1 replaced by the zero-velocity
measurement expressed in the local-level frame n (ENU at the site)::

    ν = C_n_i (v_siteⁱ − v̂ⁱ) = C_n_i δvⁱ − v_swayⁿ,   R = σ_zupt² I   (σ_zupt = 0.01 m/s)

``C_n_i δvⁱ`` is exactly the navigation-frame velocity error of a local-level mechanization at
the site (the Earth-relative velocity ``vⁿ = C_n_i (vⁱ − ω_ie × rⁱ)`` with the Coriolis and
transport terms known), so the linearized information is that of the navigation-frame
filter; keeping one mechanization isolates the one thing that differs — the reference.  On a
base at rest the two methods agree (Zhang Table 3, stationary columns).  On a swaying base
the reference is wrong by the sway velocity (up to 1.5 m/s), which a zero-velocity filter
with σ_zupt of cm/s reads as tilt and accelerometer bias; the star updates then split the
resulting attitude disagreement between attitude and installation, which biases the
installation estimate.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stellar_cal_ros.core import earth
from stellar_cal_ros.io.calibration import Calibration
from stellar_cal_ros.methods.replay import BagData, ReplayResult
from stellar_cal_ros.methods.swaying import SwayingConfig, SwayingFilter, run_filter


@dataclass
class TraditionalConfig(SwayingConfig):
    """Swaying-base defaults with the zero-velocity reference."""

    velocity_reference: str = "zero_velocity"
    zero_velocity_sigma_mps: float = 0.01  #: σ of the zero-velocity "measurement"
    position_interval_s: float = 0.5  #: every star frame


class TraditionalFilter(SwayingFilter):
    """Navigation-frame zero-velocity reference (see the module docstring)."""

    method = "traditional"

    def __init__(self, model, imu_t, imu_w, imu_f, t0, site,
                 config: SwayingConfig | None = None) -> None:
        super().__init__(model, imu_t, imu_w, imu_f, t0, site, config or TraditionalConfig())
        self.R_e_n = earth.R_itrs_enu(self.site)
        # C_n_i on the Earth-orientation grid (vectorized once; linear interpolation between
        # 0.25 s nodes: the Earth turns 1.8e-5 rad, interpolation error < 1e-10)
        R_e_i = earth.R_itrs_gcrs(self.t0 + self.grid, self.config.dut1)  # x_itrs = R x_gcrs
        self.grid_C_n_i = np.einsum("ji,njk->nik", self.R_e_n, R_e_i).reshape(-1, 9)

    def reference_measurement(self):  # noqa: D102
        c = self.config
        if c.velocity_reference != "zero_velocity":
            return super().reference_measurement()
        C_n_i = self._interp(self.grid_C_n_i, self.t)[0].reshape(3, 3)
        nu = C_n_i @ (self.site_velocity(self.t) - self.v)
        H = np.zeros((3, self.N))
        H[:, self.iv] = C_n_i
        return nu, H, c.zero_velocity_sigma_mps**2 * np.eye(3)


def replay_traditional(bag: str | Path | BagData, prior: Calibration,
                       effects: list[str] | None = None, config: TraditionalConfig | None = None,
                       progress: bool = False) -> ReplayResult:
    """Run the traditional (zero-velocity, navigation-frame) filter over a bag."""
    return run_filter(TraditionalFilter, bag, prior, effects, config or TraditionalConfig(),
                      progress)
