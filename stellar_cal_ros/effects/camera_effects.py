"""Camera (intrinsic) effects: each sets or scales some OpenCV camera parameters.

One class per contract effect id; they are small enough to share a module, and each still
declares its own parameters, prior sigma and explanation.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from stellar_cal_ros.effects.base import CAMERA_INDEX, CameraSetEffect, Effect, FrameContext, Stage

FX, FY = CAMERA_INDEX["fx"], CAMERA_INDEX["fy"]


class PrincipalPoint(CameraSetEffect):
    """Principal point (cx, cy), px."""

    id = "principal_point"
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


class FocalLength(Effect):
    """Focal length f, px (``fx = f``, ``fy = f · fy/fx`` of the prior)."""

    id = "focal_length"
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
        from stellar_cal_ros.effects.base import _camera_sigma

        cam = prior.camera
        self.ratio = cam.fy / cam.fx
        return np.array([cam.fx]), _camera_sigma(prior, ("fx",), self.default_sigma)

    def store(self, value: np.ndarray, sigma: np.ndarray, cal: Any) -> None:  # noqa: D102
        from stellar_cal_ros.effects.base import _store_camera_sigma

        p = cal.camera.parameters()
        p[FX], p[FY] = value[0], value[0] * self.ratio
        cal.camera = cal.camera.with_parameters(p)
        _store_camera_sigma(cal, ("fx", "fy"), np.array([sigma[0], sigma[0] * self.ratio]))

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


class PixelAspect(Effect):
    """Pixel aspect a: ``fy = fx · (1 + a)``."""

    id = "pixel_aspect"
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


class RadialK1K2(CameraSetEffect):
    """Radial distortion k1, k2 (OpenCV, normalized coordinates)."""

    id = "radial_k1k2"
    camera_entries = ("k1", "k2")
    parameter_names = ("k1", "k2")
    units = ("1", "1")
    default_sigma = (0.3, 1.0)
    explanation = (
        "Lens radial distortion: image points move along the radius by k1 r^3 + k2 r^5. "
        "Residual: radial vectors, near zero at the centre, growing steeply to the corners "
        "(pincushion or barrel). Typical size: 0.1-5 px at the field edge."
    )


class RadialK3(CameraSetEffect):
    """Sixth-order radial distortion k3."""

    id = "radial_k3"
    camera_entries = ("k3",)
    parameter_names = ("k3",)
    units = ("1",)
    default_sigma = (2.0,)
    explanation = (
        "Higher-order radial distortion (r^7 term) of fast or wide lenses. Residual: radial "
        "vectors confined to the outer field after k1, k2 are fitted; a change of sign between "
        "mid-field and corners. Typical size: 0.01-0.5 px at the corners."
    )


class Tangential(CameraSetEffect):
    """Decentering (tangential) distortion p1, p2."""

    id = "tangential"
    camera_entries = ("p1", "p2")
    parameter_names = ("p1", "p2")
    units = ("1", "1")
    default_sigma = (0.002, 0.002)
    explanation = (
        "Lens elements are decentered, so distortion is not symmetric about the axis. "
        "Residual: a pattern with one preferred direction, growing with r^2, partly "
        "tangential. Typical size: 0.01-1 px at the edge."
    )


class ImagePlaneTilt(CameraSetEffect):
    """Detector tilt against the optical axis (OpenCV tau_x, tau_y)."""

    id = "image_plane_tilt"
    camera_entries = ("tau_x", "tau_y")
    parameter_names = ("tau_x", "tau_y")
    units = ("rad", "rad")
    default_sigma = (5e-3, 5e-3)
    explanation = (
        "The detector is not perpendicular to the optical axis (Scheimpflug-like tilt). One "
        "side of the image is farther from the lens: a keystone pattern whose scale changes "
        "linearly across the image (Sun et al. 2013). Typical size: 0.1-10 mrad."
    )


class ThermalFocalLength(Effect):
    """Focal length drift with the optical-head temperature: ``f(T) = f (1 + c (T − T_ref))``."""

    id = "thermal_focal_length"
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

