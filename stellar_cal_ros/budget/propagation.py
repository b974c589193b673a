"""How camera, installation and centroid errors become attitude errors (first principles).

Sun et al. (Sensors 2013) give the idea, not the equations in our copy; this is our
derivation.  Everything is in the *true* star-tracker optical frame (+z the boresight,
``INTERFACES.md`` §1), which we take as the inertial frame of one frame (``R_i_st = I``
without loss of generality).

Parameter error ``δx`` (21,): the 18 OpenCV camera parameters (order of
:attr:`~stellar_cal_ros.core.camera.CameraModel.PARAMETER_NAMES`, estimate − truth) and the
installation error ψ (rad, tracker axes, ``R̂_imu_st = R_imu_st · Exp(ψ)``).

Star ``k`` with true unit direction ``d_k`` has centroid ``z_k = h(p, d_k) + n_k``; the tracker
interprets it with its model, ``d̂_k = h⁻¹(p + δp, z_k)``.  Because ``h(λ d) = h(d)``,
``J_d d = 0`` and the pseudo-inverse ``J_d⁺ = J_dᵀ (J_d J_dᵀ)⁻¹`` maps pixels into the tangent
plane, so to first order::

    e_k = d̂_k − d_k = J_d⁺ (n_k − J_p δp)                       (3,)

A least-squares (Wahba / QUEST, equal weights) attitude ``R̂ = Exp(δθ)`` minimises
``Σ |d_k − Exp(δθ) d̂_k|² ≈ Σ |e_k + δθ × d_k|²``, whence::

    δθ = A⁻¹ Σ_k e_k × d_k,      A = Σ_k (I − d_k d_kᵀ)

The three references an attitude can have (the "conventions" of the budget):

``mounting``
    the tracker's mechanical frame: the frame the model defines, as built.  A principal-
    point error δc is then an attitude error of ≈ δc / f (a rotation of every star).
``axis``
    the tracker's optical axis: the reference is the true ray through the model's own
    principal point ĉ, ``b = h⁻¹(p, ĉ) ≈ z + e₀``, ``e₀ = J_d⁺(z) δc``, reached by the
    minimal rotation ``α = z × e₀``: ``δθ_axis = δθ − α``, and per star ``e_axis = e + α × d``.
    Only the second-order part of a principal-point error is left (≈ δc sin²θ / f at
    incident angle θ): this is Sun et al.'s convention (their table needs it).
``system``
    the IMU-referenced attitude ``R̂_i_imu = R̂_i_st R̂_imu_stᵀ``: in tracker axes
    ``δθ_sys = δθ_mounting − ψ``.  A principal-point error and an installation error that
    rotate the same way cancel (Tan et al. §3.4's equivalent principal point).

The incident-angle error of one star (Sun et al.'s "angle measurement error") is the
change of its angle from the axis, ``Δθ = −zᵀ e_ref / sin θ`` (radial component).

:func:`linear_star_jacobians` and :func:`frame_attitude_jacobians` are the linear model (the
camera's analytic Jacobians); :func:`frame_attitude_errors` and :func:`star_angle_errors`
evaluate the same quantities exactly (project, unproject, SVD Wahba) for Monte Carlo.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from stellar_cal_ros.core.attitude import batched_wahba
from stellar_cal_ros.core.camera import CameraModel
from stellar_cal_ros.core.rotation import skew, so3_exp

__all__ = [
    "CONVENTIONS",
    "N_PARAMETERS",
    "StarField",
    "axis_jacobian",
    "batched_wahba",
    "boresight_rotation",
    "frame_attitude_errors",
    "frame_attitude_jacobians",
    "linear_star_jacobians",
    "perturbed_camera",
    "random_frames",
    "ring_directions",
    "star_angle_errors",
]

#: 18 camera parameters + 3 installation angles.
N_PARAMETERS = 21
#: Attitude references (see the module docstring).
CONVENTIONS = ("axis", "mounting", "system")
_Z = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class StarField:
    """Star frames over the detector: true pixels and directions.

    Attributes
    ----------
    uv : numpy.ndarray, shape (F, n, 2)
        Error-free centroids, px.
    directions : numpy.ndarray, shape (F, n, 3)
        True unit directions in the tracker frame.
    """

    uv: np.ndarray
    directions: np.ndarray

    @property
    def frames(self) -> int:
        """Number of frames F."""
        return self.uv.shape[0]

    @property
    def stars_per_frame(self) -> int:
        """Stars per frame n."""
        return self.uv.shape[1]


def random_frames(camera: CameraModel, frames: int, stars_per_frame: int,
                  rng: np.random.Generator) -> StarField:
    """Frames of stars uniformly distributed over the detector.

    Uniform on the sky is uniform on the detector to within ``cos³θ`` (< 4 % over a 17°
    field); the star count is fixed per frame.

    Parameters
    ----------
    camera : CameraModel
        The true camera.
    frames, stars_per_frame : int
        F and n (n ≥ 3 keeps the roll well determined).
    rng : numpy.random.Generator
        Source of the positions.

    Returns
    -------
    StarField
    """
    uv = rng.uniform([-0.5, -0.5], [camera.width - 0.5, camera.height - 0.5],
                     size=(frames, stars_per_frame, 2))
    d = camera.unproject(uv.reshape(-1, 2)).reshape(frames, stars_per_frame, 3)
    return StarField(uv=uv, directions=d)


def ring_directions(theta: np.ndarray, azimuth: np.ndarray) -> np.ndarray:
    """Unit directions at incident angles ``theta`` and azimuths ``azimuth`` (rad, broadcast).

    Returns
    -------
    numpy.ndarray, shape (..., 3)
        ``(sin θ cos φ, sin θ sin φ, cos θ)``.
    """
    theta, azimuth = np.broadcast_arrays(theta, azimuth)
    s = np.sin(theta)
    return np.stack([s * np.cos(azimuth), s * np.sin(azimuth), np.cos(theta)], axis=-1)


def perturbed_camera(camera: CameraModel, dx: np.ndarray) -> CameraModel:
    """The tracker's model: ``camera`` with the first 18 entries of ``dx`` added."""
    return camera.with_parameters(camera.parameters() + np.asarray(dx, dtype=float)[:18])


# ---------------------------------------------------------------------------- linear model


def _tangent_pinv(J_d: np.ndarray) -> np.ndarray:
    """``J_dᵀ (J_d J_dᵀ)⁻¹`` for (N, 2, 3) Jacobians (maps px into the tangent plane)."""
    JJt = J_d @ J_d.transpose(0, 2, 1)
    return J_d.transpose(0, 2, 1) @ np.linalg.inv(JJt)


def axis_jacobian(camera: CameraModel) -> np.ndarray:
    """``∂α/∂δx`` (3, 21): rotation from the model's axis to the true ray through ĉ.

    ``α = z × J_d⁺(z) δc`` with ``δc = (δcx, δcy)``: only the principal-point columns are
    nonzero (pixel ĉ is the model's boresight whatever its distortion or tilt).
    """
    _, J_d, _ = camera.project(_Z[None], jacobians=True)
    pinv = _tangent_pinv(np.ascontiguousarray(J_d))[0]  # (3, 2)
    out = np.zeros((3, N_PARAMETERS))
    out[:, 2:4] = skew(_Z) @ pinv
    return out


def linear_star_jacobians(camera: CameraModel, directions: np.ndarray,
                          convention: str = "mounting") -> tuple[np.ndarray, np.ndarray]:
    """Direction error of each star, linear in ``δx`` and in its centroid noise.

    Parameters
    ----------
    camera : CameraModel
        The true camera.
    directions : numpy.ndarray, shape (N, 3)
        True unit directions.
    convention : str
        ``"mounting"``, ``"axis"`` or ``"system"`` (the direction in IMU axes, expressed in
        tracker axes: ``e + ψ × d``); see the module docstring.

    Returns
    -------
    E : numpy.ndarray, shape (N, 3, 21)
        ``∂e/∂δx``, rad per unit of each parameter.
    G : numpy.ndarray, shape (N, 3, 2)
        ``∂e/∂n``, rad/px.
    """
    d = np.asarray(directions, dtype=float)
    _, J_d, J_p = camera.project(d, jacobians=True)
    G = _tangent_pinv(np.ascontiguousarray(J_d))
    E = np.zeros((len(d), 3, N_PARAMETERS))
    E[:, :, :18] = -G @ J_p
    if convention == "axis":
        E += -skew(d) @ axis_jacobian(camera)  # + α × d = −[d]× α
    elif convention == "system":
        E[:, :, 18:21] = -skew(d)  # + ψ × d
    return E, G


def radial_rows(directions: np.ndarray, E: np.ndarray) -> np.ndarray:
    """Incident-angle error rows ``−zᵀ E / sin θ`` (N, k) from direction rows (N, 3, k)."""
    sin_t = np.linalg.norm(directions[:, :2], axis=1)
    return -E[:, 2, :] / sin_t[:, None]


def frame_attitude_jacobians(field: StarField, camera: CameraModel,
                             convention: str = "mounting") -> tuple[np.ndarray, np.ndarray]:
    """Linear attitude error of every frame (Wahba with equal weights).

    Returns
    -------
    T : numpy.ndarray, shape (F, 3, 21)
        ``∂δθ/∂δx``, rad per unit of each parameter; ``convention="system"`` includes ``−ψ``.
    W : numpy.ndarray, shape (F, n, 3, 2)
        ``∂δθ/∂n_k``, rad/px, for the centroid noise of each star.
    """
    F, n = field.frames, field.stars_per_frame
    d = field.directions.reshape(-1, 3)
    E, G = linear_star_jacobians(camera, d, convention)
    S = skew(d)  # e × d = −[d]× e
    A = (n * np.eye(3) - np.einsum("fki,fkj->fij", field.directions, field.directions))
    Ainv = np.linalg.inv(A)  # (F, 3, 3)
    SE = -(S @ E).reshape(F, n, 3, N_PARAMETERS).sum(axis=1)
    T = Ainv @ SE  # "system": the per-star ψ × d terms sum to −ψ
    W = np.einsum("fij,fkjl->fkil", Ainv, -(S @ G).reshape(F, n, 3, 2))
    return T, W


# ---------------------------------------------------------------------------- exact model


def boresight_rotation(camera: CameraModel, model: CameraModel) -> np.ndarray:
    """Minimal rotation (3, 3) taking +z to the true ray through the model's principal point."""
    b = camera.unproject(np.array([[model.cx, model.cy]]))[0]
    axis = np.cross(_Z, b)
    s = np.linalg.norm(axis)
    if s < 1e-15:
        return np.eye(3)
    return so3_exp(axis / s * np.arctan2(s, b[2]))


def frame_attitude_errors(camera: CameraModel, field: StarField, dx: np.ndarray,
                          noise_px: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Exact attitude errors of every frame for one parameter error (Monte Carlo).

    Projects with the true camera, adds the centroid noise, unprojects with the model
    ``camera + δp``, solves Wahba, and reads the error in each convention.

    Parameters
    ----------
    camera : CameraModel
        The true camera.
    field : StarField
        The frames.
    dx : numpy.ndarray, shape (21,)
        Parameter error (model − truth).
    noise_px : numpy.ndarray, shape (F, n, 2), optional
        Centroid noise, px.

    Returns
    -------
    dict of str to numpy.ndarray, shape (F, 3)
        ``δθ`` (rad, tracker axes) per convention of :data:`CONVENTIONS`.
    """
    dx = np.asarray(dx, dtype=float)
    model = perturbed_camera(camera, dx)
    uv = field.uv if noise_px is None else field.uv + noise_px
    d_hat = model.unproject(uv.reshape(-1, 2)).reshape(field.directions.shape)
    R = batched_wahba(d_hat, field.directions)
    mounting = Rotation.from_matrix(R)
    R_axis = Rotation.from_matrix(boresight_rotation(camera, model))
    return {
        "mounting": mounting.as_rotvec(),
        "axis": (R_axis.inv() * mounting).as_rotvec(),
        "system": (mounting * Rotation.from_rotvec(-dx[18:21])).as_rotvec(),
    }


def star_angle_errors(camera: CameraModel, directions: np.ndarray, dx: np.ndarray,
                      noise_px: np.ndarray | None = None,
                      convention: str = "axis") -> np.ndarray:
    """Exact incident-angle error of single stars (Sun et al.'s metric), rad.

    Parameters
    ----------
    camera : CameraModel
        The true camera.
    directions : numpy.ndarray, shape (N, 3)
        True unit directions.
    dx : numpy.ndarray, shape (21,)
        Parameter error (the installation part is ignored).
    noise_px : numpy.ndarray, shape (N, 2), optional
        Centroid noise, px.
    convention : str
        ``"axis"``: angles from the model's own axis, truth measured from the true ray
        through the model's principal point; ``"mounting"``: both from +z.

    Returns
    -------
    numpy.ndarray, shape (N,)
        ``θ̂ − θ``, rad.
    """
    d = np.asarray(directions, dtype=float)
    model = perturbed_camera(camera, dx)
    uv = camera.project(d)
    if noise_px is not None:
        uv = uv + noise_px
    d_hat = model.unproject(uv)
    theta_hat = np.arctan2(np.linalg.norm(d_hat[:, :2], axis=1), d_hat[:, 2])
    ref = _Z if convention != "axis" else camera.unproject(np.array([[model.cx, model.cy]]))[0]
    theta = np.arctan2(np.linalg.norm(np.cross(d, ref), axis=1), d @ ref)
    return theta_hat - theta
