"""Installation (mounting) rotation between the IMU and the star tracker."""

from __future__ import annotations

from typing import Any

import numpy as np

from stellar_cal_ros.core.rotation import scipy_compose, scipy_quat_from_rotvec
from stellar_cal_ros.effects.base import Effect, ExportRole, FrameContext, Plausible, Stage

_IDENTITY_Q = np.array([0.0, 0.0, 0.0, 1.0])


class Installation(Effect):
    """Small rotation δ of the tracker about its own axes: ``R_imu_st = R_prior · Exp(δ)``."""

    id = "installation"
    stage = Stage.TRACKER
    order = 10
    budget_source = "installation"
    export_role = ExportRole.EXTRINSIC
    plausible = Plausible(0.2, "deg")
    parameter_names = ("rx", "ry", "rz")
    units = ("rad", "rad", "rad")
    default_sigma = (np.deg2rad(0.2),) * 3
    simulation_units = ("arcsec", "arcsec", "arcsec")
    simulation_scale = (np.pi / 180.0 / 3600.0,) * 3
    explanation = (
        "The star tracker is not mounted exactly as drawn: its frame is rotated by a few "
        "arc-minutes against the IMU. Every star moves the same way, so the residual is a "
        "uniform shift (rotation about x or y) or a rotation of the whole field about the "
        "boresight (z) that follows the tracker, not the sky; it is observable from the "
        "attitude changes the gyros measure. Typical size: 10-1000 arcsec."
    )

    def __init__(self) -> None:
        #: the prior's installation as its unit quaternion (``Rotation.as_quat()``): the
        #: result is composed with the floats of ``nominal * Rotation.from_rotvec(δ)``
        #: without importing ``scipy.spatial`` (:mod:`~stellar_cal_ros.core.rotation`)
        self.nominal_quat = _IDENTITY_Q

    @property
    def nominal(self):
        """The prior's installation, a ``scipy`` ``Rotation``."""
        from scipy.spatial.transform import Rotation

        return Rotation(self.nominal_quat, normalize=False)

    @nominal.setter
    def nominal(self, value) -> None:
        self.nominal_quat = np.asarray(value.as_quat(), dtype=float)

    def initial(self, prior: Any) -> tuple[np.ndarray, np.ndarray]:  # noqa: D102
        self.nominal_quat = prior.installation_quat
        sig = (prior.sigma or {}).get("installation", {}).get("rotation_vector")
        sigma = np.asarray(sig, dtype=float) if sig else np.asarray(self.default_sigma)
        return np.zeros(3), sigma

    def store(self, value: np.ndarray, sigma: np.ndarray, cal: Any) -> None:  # noqa: D102
        cal.set_installation_quat(scipy_compose(self.nominal_quat,
                                                scipy_quat_from_rotvec(value)))
        cal.sigma["installation"] = {"rotation_vector": [float(s) for s in sigma]}

    def tracker_rotation(self, value: np.ndarray, ctx: FrameContext) -> np.ndarray:  # noqa: D102
        return np.asarray(value, dtype=float)

    def tracker_rotation_jacobian(self, value: np.ndarray, ctx: FrameContext) -> np.ndarray:  # noqa: D102
        return np.eye(3)

    def affine_form(self) -> np.ndarray:  # noqa: D102
        return np.eye(3)
