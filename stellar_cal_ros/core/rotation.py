"""Rotations: SO(3) exponential / logarithm, their Jacobians and quaternion helpers.

Conventions
-----------
- ``R_a_b`` is the rotation matrix that maps the coordinates of a vector in frame ``b`` to
  its coordinates in frame ``a``: ``v_a = R_a_b @ v_b``. Compositions chain as
  ``R_a_c = R_a_b @ R_b_c``.
- Perturbations are *right* perturbations, expressed in the frame on the right of the
  subscript (the body / sensor frame): ``R = R_nominal @ Exp(delta)``. :func:`so3_boxplus`
  and :func:`so3_boxminus` implement this convention.
- ``Exp`` / ``Log`` are the SO(3) exponential and logarithm, :func:`so3_exp` and
  :func:`so3_log`; rotation vectors are in rad.
- The Jacobians satisfy, for a small ``delta``::

      Exp(phi + delta) ~= Exp(phi) @ Exp(right_jacobian(phi) @ delta)
      Exp(phi + delta) ~= Exp(left_jacobian(phi) @ delta) @ Exp(phi)
      Log(Exp(phi) @ Exp(delta)) ~= phi + right_jacobian_inverse(phi) @ delta
      Log(Exp(delta) @ Exp(phi)) ~= phi + left_jacobian_inverse(phi) @ delta

- Quaternions are stored scalar-last, ``[x, y, z, w]``, as :class:`scipy.spatial.transform.
  Rotation` does, and use the Hamilton product, so that
  ``quat_to_matrix(quat_multiply(q1, q2)) == quat_to_matrix(q1) @ quat_to_matrix(q2)``.

Every function is vectorised over leading axes (``...``) and safe at and near zero angle.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "left_jacobian",
    "left_jacobian_inverse",
    "orthonormalize",
    "quat_conjugate",
    "scipy_compose",
    "scipy_matrix",
    "scipy_matrix_roundtrip",
    "scipy_quat",
    "scipy_quat_from_matrix",
    "scipy_quat_from_rotvec",
    "quat_from_matrix",
    "quat_from_rotvec",
    "quat_multiply",
    "quat_rotate",
    "quat_to_matrix",
    "quat_to_rotvec",
    "right_jacobian",
    "right_jacobian_inverse",
    "skew",
    "so3_boxminus",
    "so3_boxplus",
    "so3_exp",
    "so3_log",
]

FloatArray = NDArray[np.float64]

# Below this angle (rad) the closed forms of the Jacobian coefficients lose accuracy to
# cancellation and their Taylor series (truncated after the theta**6 term, error < 1e-18) are
# used instead.
_SERIES_ANGLE = 1e-2


def _vec3(v: ArrayLike, name: str) -> FloatArray:
    a = np.asarray(v, dtype=np.float64)
    if a.shape[-1:] != (3,):
        raise ValueError(f"{name} must have shape (..., 3), got {a.shape}")
    return a


def _mat3(m: ArrayLike, name: str) -> FloatArray:
    a = np.asarray(m, dtype=np.float64)
    if a.shape[-2:] != (3, 3):
        raise ValueError(f"{name} must have shape (..., 3, 3), got {a.shape}")
    return a


def _quat(q: ArrayLike, name: str) -> FloatArray:
    a = np.asarray(q, dtype=np.float64)
    if a.shape[-1:] != (4,):
        raise ValueError(f"{name} must have shape (..., 4) in xyzw order, got {a.shape}")
    return a


def skew(v: ArrayLike) -> FloatArray:
    """Return the cross-product (hat) matrix of ``v``.

    Parameters
    ----------
    v : array_like, shape (..., 3)
        Vectors.

    Returns
    -------
    numpy.ndarray, shape (..., 3, 3)
        ``S`` with ``S @ w == cross(v, w)`` for every ``w``.
    """
    v = _vec3(v, "v")
    # Filled in place: several times faster than nested np.stack for the small batches of
    # the filters' hot loops.
    S = np.zeros(v.shape + (3,))
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    S[..., 0, 1] = -z
    S[..., 0, 2] = y
    S[..., 1, 0] = z
    S[..., 1, 2] = -x
    S[..., 2, 0] = -y
    S[..., 2, 1] = x
    return S


def _angle_coefficients(phi: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Return ``theta, sin(t)/t, (1-cos t)/t**2, (t-sin t)/t**3`` accurately at every angle."""
    theta = np.linalg.norm(phi, axis=-1)
    a = np.sinc(theta / np.pi)  # sin(t)/t, exact at 0
    half = np.sinc(theta / (2.0 * np.pi))  # sin(t/2)/(t/2)
    b = 0.5 * half * half  # (1-cos t)/t**2 = 2 sin^2(t/2)/t^2
    small = theta < _SERIES_ANGLE
    t2 = theta * theta
    with np.errstate(divide="ignore", invalid="ignore"):
        c_closed = (theta - np.sin(theta)) / (t2 * theta)
    c_series = 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0 - t2 * t2 * t2 / 362880.0
    c = np.where(small, c_series, c_closed)
    return theta, a, b, c


def _so3_exp_single(phi: FloatArray) -> FloatArray:
    """Rodrigues' formula for one rotation vector with scalar math (hot path).

    Written so that numba compiles it as it is: the filters' compiled kernels
    (:mod:`stellar_cal_ros.core.jit`) use this one implementation.
    """
    x, y, z = float(phi[0]), float(phi[1]), float(phi[2])
    t2 = x * x + y * y + z * z
    if t2 < 1e-8:  # series: sin t/t and (1-cos t)/t^2 to O(t^4), error < 1e-17
        a = 1.0 - t2 / 6.0 + t2 * t2 / 120.0
        b = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
    else:
        t = math.sqrt(t2)
        a = math.sin(t) / t
        b = (1.0 - math.cos(t)) / t2
    R = np.empty((3, 3))
    R[0, 0], R[0, 1], R[0, 2] = 1.0 - b * (y * y + z * z), -a * z + b * x * y, a * y + b * x * z
    R[1, 0], R[1, 1], R[1, 2] = a * z + b * x * y, 1.0 - b * (x * x + z * z), -a * x + b * y * z
    R[2, 0], R[2, 1], R[2, 2] = -a * y + b * x * z, a * x + b * y * z, 1.0 - b * (x * x + y * y)
    return R


def so3_exp(phi: ArrayLike) -> FloatArray:
    """Return the rotation matrix ``Exp(phi)`` of a rotation vector (Rodrigues' formula).

    Parameters
    ----------
    phi : array_like, shape (..., 3)
        Rotation vectors, rad (axis times angle).

    Returns
    -------
    numpy.ndarray, shape (..., 3, 3)
        Rotation matrices. Exact (to rounding) at every angle, including zero.
    """
    phi = _vec3(phi, "phi")
    if phi.shape == (3,):
        return _so3_exp_single(phi)
    _, a, b, _ = _angle_coefficients(phi)
    S = skew(phi)
    eye = np.broadcast_to(np.eye(3), S.shape)
    return eye + a[..., None, None] * S + b[..., None, None] * (S @ S)


def quat_from_matrix(R: ArrayLike) -> FloatArray:
    """Return the unit quaternion of rotation matrices (Shepperd's method).

    Parameters
    ----------
    R : array_like, shape (..., 3, 3)
        Rotation matrices (assumed orthonormal; small errors are tolerated).

    Returns
    -------
    numpy.ndarray, shape (..., 4)
        Unit quaternions ``[x, y, z, w]`` with ``w >= 0``.
    """
    R = _mat3(R, "R")
    if R.shape == (3, 3):
        return _quat_from_matrix_single(R)
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    trace = m00 + m11 + m22
    # Four candidate (unnormalised) quaternions, each well conditioned when its pivot is large.
    cands = np.stack(
        [
            np.stack([1.0 + 2.0 * m00 - trace, m01 + m10, m02 + m20, m21 - m12], axis=-1),
            np.stack([m01 + m10, 1.0 + 2.0 * m11 - trace, m12 + m21, m02 - m20], axis=-1),
            np.stack([m02 + m20, m12 + m21, 1.0 + 2.0 * m22 - trace, m10 - m01], axis=-1),
            np.stack([m21 - m12, m02 - m20, m10 - m01, 1.0 + trace], axis=-1),
        ],
        axis=-2,
    )
    pivots = np.stack([m00, m11, m22, trace], axis=-1)
    choice = np.argmax(pivots, axis=-1)
    q = np.take_along_axis(cands, choice[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0.0, -q, q)


def _quat_from_matrix_single(R: FloatArray) -> FloatArray:
    """:func:`quat_from_matrix` of one (3, 3) matrix: only the chosen candidate is formed.

    The same operations on the same floats as the batched form (bit for bit; a single-frame
    refit's ``so3_log`` is called some 16 000 times in one ``discover``).
    """
    m00, m01, m02 = R[0, 0], R[0, 1], R[0, 2]
    m10, m11, m12 = R[1, 0], R[1, 1], R[1, 2]
    m20, m21, m22 = R[2, 0], R[2, 1], R[2, 2]
    trace = m00 + m11 + m22
    choice = int(np.argmax(np.array([m00, m11, m22, trace])))
    if choice == 0:
        q = np.array([1.0 + 2.0 * m00 - trace, m01 + m10, m02 + m20, m21 - m12])
    elif choice == 1:
        q = np.array([m01 + m10, 1.0 + 2.0 * m11 - trace, m12 + m21, m02 - m20])
    elif choice == 2:
        q = np.array([m02 + m20, m12 + m21, 1.0 + 2.0 * m22 - trace, m10 - m01])
    else:
        q = np.array([m21 - m12, m02 - m20, m10 - m01, 1.0 + trace])
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0.0, -q, q)


def quat_to_rotvec(q: ArrayLike) -> FloatArray:
    """Return the rotation vector of unit quaternions, angle in ``[0, pi]``.

    Parameters
    ----------
    q : array_like, shape (..., 4)
        Quaternions ``[x, y, z, w]`` (normalised internally).

    Returns
    -------
    numpy.ndarray, shape (..., 3)
        Rotation vectors, rad.
    """
    q = _quat(q, "q")
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[..., 3:4] < 0.0, -q, q)
    v = q[..., :3]
    s = np.linalg.norm(v, axis=-1)
    half = np.arctan2(s, q[..., 3])  # theta / 2 in [0, pi/2]
    # theta / s = 2 * half / sin(half) / w-free form; use sinc for the small-angle limit.
    scale = 2.0 / np.sinc(half / np.pi)  # 2 * half / sin(half)
    # s = sin(half) because |q| = 1, so v * 2 * half / s == v * scale.
    return v * scale[..., None]


def so3_log(R: ArrayLike) -> FloatArray:
    """Return the rotation vector ``Log(R)`` of rotation matrices.

    Computed through the quaternion, which keeps full accuracy near 0 and near pi.

    Parameters
    ----------
    R : array_like, shape (..., 3, 3)
        Rotation matrices.

    Returns
    -------
    numpy.ndarray, shape (..., 3)
        Rotation vectors, rad, angle in ``[0, pi]``.
    """
    return quat_to_rotvec(quat_from_matrix(R))


def quat_from_rotvec(phi: ArrayLike) -> FloatArray:
    """Return the unit quaternion of rotation vectors.

    Parameters
    ----------
    phi : array_like, shape (..., 3)
        Rotation vectors, rad.

    Returns
    -------
    numpy.ndarray, shape (..., 4)
        Quaternions ``[x, y, z, w]``.
    """
    phi = _vec3(phi, "phi")
    theta = np.linalg.norm(phi, axis=-1)
    half_sinc = 0.5 * np.sinc(theta / (2.0 * np.pi))  # sin(t/2) / t
    return np.concatenate([phi * half_sinc[..., None], np.cos(0.5 * theta)[..., None]], axis=-1)


def quat_to_matrix(q: ArrayLike) -> FloatArray:
    """Return the rotation matrices of quaternions.

    Parameters
    ----------
    q : array_like, shape (..., 4)
        Quaternions ``[x, y, z, w]`` (normalised internally).

    Returns
    -------
    numpy.ndarray, shape (..., 3, 3)
        Rotation matrices.
    """
    q = _quat(q, "q")
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return np.stack(
        [
            np.stack([1.0 - 2.0 * (yy + zz), 2.0 * (xy - wz), 2.0 * (xz + wy)], axis=-1),
            np.stack([2.0 * (xy + wz), 1.0 - 2.0 * (xx + zz), 2.0 * (yz - wx)], axis=-1),
            np.stack([2.0 * (xz - wy), 2.0 * (yz + wx), 1.0 - 2.0 * (xx + yy)], axis=-1),
        ],
        axis=-2,
    )


def quat_multiply(q1: ArrayLike, q2: ArrayLike) -> FloatArray:
    """Return the Hamilton product ``q1 * q2`` of quaternions in xyzw order.

    The product represents "first ``q2``, then ``q1``": its matrix is ``R(q1) @ R(q2)``, as
    ``scipy.spatial.transform.Rotation`` composes ``r1 * r2``. With the frame convention of
    this module, ``q_a_c = quat_multiply(q_a_b, q_b_c)``.

    Parameters
    ----------
    q1, q2 : array_like, shape (..., 4)
        Quaternions ``[x, y, z, w]``; leading axes broadcast.

    Returns
    -------
    numpy.ndarray, shape (..., 4)
        The product (not renormalised).
    """
    q1 = _quat(q1, "q1")
    q2 = _quat(q2, "q2")
    x1, y1, z1, w1 = q1[..., 0], q1[..., 1], q1[..., 2], q1[..., 3]
    x2, y2, z2, w2 = q2[..., 0], q2[..., 1], q2[..., 2], q2[..., 3]
    return np.stack(
        [
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        ],
        axis=-1,
    )


def quat_conjugate(q: ArrayLike) -> FloatArray:
    """Return the conjugate (the inverse for unit quaternions) of quaternions.

    Parameters
    ----------
    q : array_like, shape (..., 4)
        Quaternions ``[x, y, z, w]``.

    Returns
    -------
    numpy.ndarray, shape (..., 4)
        ``[-x, -y, -z, w]``.
    """
    q = _quat(q, "q")
    return np.concatenate([-q[..., :3], q[..., 3:]], axis=-1)


def quat_rotate(q: ArrayLike, v: ArrayLike) -> FloatArray:
    """Rotate vectors by unit quaternions: ``R(q) @ v``.

    Parameters
    ----------
    q : array_like, shape (..., 4)
        Unit quaternions ``[x, y, z, w]``.
    v : array_like, shape (..., 3)
        Vectors; leading axes broadcast with ``q``.

    Returns
    -------
    numpy.ndarray, shape (..., 3)
        Rotated vectors.
    """
    q = _quat(q, "q")
    v = _vec3(v, "v")
    u = q[..., :3]
    w = q[..., 3:4]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def so3_boxplus(R: ArrayLike, delta: ArrayLike) -> FloatArray:
    """Apply a right perturbation: ``R @ Exp(delta)``.

    Parameters
    ----------
    R : array_like, shape (..., 3, 3)
        Nominal rotations.
    delta : array_like, shape (..., 3)
        Perturbations, rad, in the frame on the right of ``R``'s subscript.

    Returns
    -------
    numpy.ndarray, shape (..., 3, 3)
        Perturbed rotations.
    """
    return _mat3(R, "R") @ so3_exp(delta)


def so3_boxminus(R: ArrayLike, R_nominal: ArrayLike) -> FloatArray:
    """Return the right perturbation ``delta = Log(R_nominal.T @ R)``, the inverse of boxplus.

    Parameters
    ----------
    R : array_like, shape (..., 3, 3)
        Rotations.
    R_nominal : array_like, shape (..., 3, 3)
        Nominal rotations.

    Returns
    -------
    numpy.ndarray, shape (..., 3)
        ``delta`` with ``R == R_nominal @ Exp(delta)``, rad.
    """
    R = _mat3(R, "R")
    R_nominal = _mat3(R_nominal, "R_nominal")
    return so3_log(np.swapaxes(R_nominal, -1, -2) @ R)


def orthonormalize(R: ArrayLike) -> FloatArray:
    """Return the nearest rotation matrices (in the Frobenius norm) of near-rotations.

    Parameters
    ----------
    R : array_like, shape (..., 3, 3)
        Nearly orthonormal matrices with positive determinant.

    Returns
    -------
    numpy.ndarray, shape (..., 3, 3)
        Rotation matrices (polar decomposition via SVD).
    """
    R = _mat3(R, "R")
    U, _, Vt = np.linalg.svd(R)
    d = np.sign(np.linalg.det(U @ Vt))
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt


def _jacobian_single(phi: FloatArray, sign: float) -> FloatArray:
    """``I + sign·b [φ]× + c [φ]×²`` for one vector with scalar math (hot path).

    Compiled as it is by :mod:`stellar_cal_ros.core.jit`.
    """
    x, y, z = float(phi[0]), float(phi[1]), float(phi[2])
    t2 = x * x + y * y + z * z
    if t2 < _SERIES_ANGLE**2:  # series to O(t^4), error < 3e-17
        b = 0.5 - t2 / 24.0 + t2 * t2 / 720.0
        c = 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0
    else:
        t = math.sqrt(t2)
        half = math.sin(0.5 * t) / (0.5 * t)
        b = 0.5 * half * half  # (1 - cos t)/t^2 without cancellation
        c = (t - math.sin(t)) / (t2 * t)
    sb = sign * b
    J = np.empty((3, 3))
    J[0, 0], J[0, 1], J[0, 2] = 1.0 - c * (y * y + z * z), -sb * z + c * x * y, sb * y + c * x * z
    J[1, 0], J[1, 1], J[1, 2] = sb * z + c * x * y, 1.0 - c * (x * x + z * z), -sb * x + c * y * z
    J[2, 0], J[2, 1], J[2, 2] = -sb * y + c * x * z, sb * x + c * y * z, 1.0 - c * (x * x + y * y)
    return J


def _jacobian(phi: ArrayLike, sign: float) -> FloatArray:
    phi = _vec3(phi, "phi")
    if phi.shape == (3,):
        return _jacobian_single(phi, sign)
    _, _, b, c = _angle_coefficients(phi)
    S = skew(phi)
    eye = np.broadcast_to(np.eye(3), S.shape)
    return eye + sign * b[..., None, None] * S + c[..., None, None] * (S @ S)


def _jacobian_inverse(phi: ArrayLike, sign: float) -> FloatArray:
    phi = _vec3(phi, "phi")
    theta = np.linalg.norm(phi, axis=-1)
    t2 = theta * theta
    with np.errstate(divide="ignore", invalid="ignore"):
        d_closed = 1.0 / t2 - (1.0 + np.cos(theta)) / (2.0 * theta * np.sin(theta))
    d_series = 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0 + t2 * t2 * t2 / 1209600.0
    d = np.where(theta < _SERIES_ANGLE, d_series, d_closed)
    S = skew(phi)
    eye = np.broadcast_to(np.eye(3), S.shape)
    return eye + sign * 0.5 * S + d[..., None, None] * (S @ S)


def right_jacobian(phi: ArrayLike) -> FloatArray:
    """Return the right Jacobian of SO(3), ``Jr(phi)``.

    ``Exp(phi + delta) ~= Exp(phi) @ Exp(Jr(phi) @ delta)``;
    ``Jr = I - (1 - cos t)/t**2 [phi]x + (t - sin t)/t**3 [phi]x**2`` with ``t = |phi|``.

    Parameters
    ----------
    phi : array_like, shape (..., 3)
        Rotation vectors, rad.

    Returns
    -------
    numpy.ndarray, shape (..., 3, 3)
        Right Jacobians (dimensionless).
    """
    return _jacobian(phi, -1.0)


def left_jacobian(phi: ArrayLike) -> FloatArray:
    """Return the left Jacobian of SO(3), ``Jl(phi) = Jr(-phi) = Jr(phi).T``.

    ``Exp(phi + delta) ~= Exp(Jl(phi) @ delta) @ Exp(phi)``.

    Parameters
    ----------
    phi : array_like, shape (..., 3)
        Rotation vectors, rad.

    Returns
    -------
    numpy.ndarray, shape (..., 3, 3)
        Left Jacobians (dimensionless).
    """
    return _jacobian(phi, 1.0)


def right_jacobian_inverse(phi: ArrayLike) -> FloatArray:
    """Return the inverse right Jacobian of SO(3).

    ``Log(Exp(phi) @ Exp(delta)) ~= phi + Jr^-1(phi) @ delta``;
    ``Jr^-1 = I + [phi]x / 2 + (1/t**2 - (1 + cos t)/(2 t sin t)) [phi]x**2``.
    Singular at ``|phi| = 2 pi``; rotation vectors from :func:`so3_log` have ``|phi| <= pi``.

    Parameters
    ----------
    phi : array_like, shape (..., 3)
        Rotation vectors, rad.

    Returns
    -------
    numpy.ndarray, shape (..., 3, 3)
        Inverse right Jacobians (dimensionless).
    """
    return _jacobian_inverse(phi, 1.0)


def left_jacobian_inverse(phi: ArrayLike) -> FloatArray:
    """Return the inverse left Jacobian of SO(3), ``Jl^-1(phi) = Jr^-1(phi).T``.

    ``Log(Exp(delta) @ Exp(phi)) ~= phi + Jl^-1(phi) @ delta``.

    Parameters
    ----------
    phi : array_like, shape (..., 3)
        Rotation vectors, rad.

    Returns
    -------
    numpy.ndarray, shape (..., 3, 3)
        Inverse left Jacobians (dimensionless).
    """
    return _jacobian_inverse(phi, -1.0)


# ------------------------------------------------------------------------------------------
# The floats of scipy's ``Rotation`` without importing it (issue 24.1: ``scipy.spatial``
# costs a replay ~0.1 CPU-s of start-up).  Each function below performs the operations of
# scipy's compiled conversion in the same order (IEEE double, no fused multiply-add), so its
# result is bit for bit ``Rotation``'s — held by test_rotation.py on random inputs.  Quaternions
# are scalar-last and *stored* (what ``Rotation.as_quat()`` returns); the functions above
# (Shepperd's method, sinc forms) are this package's own and round differently.
# ------------------------------------------------------------------------------------------


def _sum_squares(x, y, z, w):
    """``x² + y² + z² + w²`` in scipy's order (Python floats or arrays alike)."""
    return ((x * x + y * y) + z * z) + w * w


def _norm4(q: FloatArray) -> FloatArray:
    return np.sqrt(_sum_squares(q[..., 0], q[..., 1], q[..., 2], q[..., 3]))


def _matrix_rows(x, y, z, w) -> tuple:
    """The rows of the matrix of the unit quaternion ``(x, y, z, w)``, as scipy forms them.

    Python floats or arrays alike (the same IEEE operations in the same order).
    """
    xx, yy, zz, ww = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return ((((xx - yy) - zz) + ww, 2 * (xy - zw), 2 * (xz + yw)),
            (2 * (xy + zw), ((-xx + yy) - zz) + ww, 2 * (yz - xw)),
            (2 * (xz - yw), 2 * (yz + xw), ((-xx - yy) + zz) + ww))


def _pivot_quat(m, tr, piv: int) -> tuple:
    """The (unnormalised) quaternion scipy forms of the matrix ``m`` (nested 3 × 3), pivot ``piv``.

    ``piv`` 0-2: the diagonal entry, 3: the trace ``tr``.  Python floats or arrays alike.
    """
    one = 1 - tr
    if piv == 0:
        return one + 2 * m[0][0], m[1][0] + m[0][1], m[2][0] + m[0][2], m[2][1] - m[1][2]
    if piv == 1:
        return m[0][1] + m[1][0], one + 2 * m[1][1], m[2][1] + m[1][2], m[0][2] - m[2][0]
    if piv == 2:
        return m[0][2] + m[2][0], m[1][2] + m[2][1], one + 2 * m[2][2], m[1][0] - m[0][1]
    return m[2][1] - m[1][2], m[0][2] - m[2][0], m[1][0] - m[0][1], 1 + tr


def scipy_quat(q: ArrayLike) -> FloatArray:
    """``Rotation.from_quat(q).as_quat()``: ``q`` over its norm, shape (..., 4)."""
    q = np.array(q, dtype=np.float64)
    return q / _norm4(q)[..., None]


def scipy_matrix(q: ArrayLike) -> FloatArray:
    """``as_matrix()`` of a ``Rotation`` that stores the unit quaternion ``q`` (..., 4)."""
    q = np.asarray(q, dtype=np.float64)
    rows = _matrix_rows(q[..., 0], q[..., 1], q[..., 2], q[..., 3])
    m = np.empty(q.shape[:-1] + (3, 3))
    for a in range(3):
        for b in range(3):
            m[..., a, b] = rows[a][b]
    return m


def scipy_quat_from_matrix(R: ArrayLike) -> FloatArray:
    """``Rotation.from_matrix(R, assume_valid=True).as_quat()`` (R orthonormal, (..., 3, 3)).

    The pivot is the largest of the diagonal and the trace (the first one on a tie); the
    quaternion is not made canonical (w may be negative).
    """
    R = np.asarray(R, dtype=np.float64)
    m = [[R[..., a, b] for b in range(3)] for a in range(3)]
    tr = (m[0][0] + m[1][1]) + m[2][2]
    cands = np.stack([np.stack(_pivot_quat(m, tr, piv), axis=-1) for piv in range(4)],
                     axis=-2)
    pick = np.argmax(np.stack([m[0][0], m[1][1], m[2][2], tr], axis=-1), axis=-1)
    q = np.take_along_axis(cands, pick[..., None, None], axis=-2)[..., 0, :]
    return q / _norm4(q)[..., None]


def _roundtrip_one(R: list) -> list:
    """:func:`scipy_matrix_roundtrip` of one matrix (nested lists of Python floats)."""
    tr = (R[0][0] + R[1][1]) + R[2][2]
    piv = max(range(4), key=(R[0][0], R[1][1], R[2][2], tr).__getitem__)  # (the first largest)
    x, y, z, w = _pivot_quat(R, tr, piv)
    n = math.sqrt(_sum_squares(x, y, z, w))
    return [list(row) for row in _matrix_rows(x / n, y / n, z / n, w / n)]


def scipy_matrix_roundtrip(R: ArrayLike) -> FloatArray:
    """``Rotation.from_matrix(R, assume_valid=True).as_matrix()`` of matrices (F, 3, 3).

    A few matrices go through Python floats (a few µs each), many through numpy.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.ndim == 3 and len(R) <= 8:
        return np.array([_roundtrip_one(r) for r in R.tolist()]).reshape(R.shape)
    return scipy_matrix(scipy_quat_from_matrix(R))


def scipy_quat_from_rotvec(phi: ArrayLike) -> FloatArray:
    """``Rotation.from_rotvec(phi).as_quat()`` (..., 3) → (..., 4); not normalised again.

    Row by row with :mod:`math`'s ``sin``/``cos`` (the C library's, as scipy's; numpy's own
    vectorised ones may round differently on some CPUs).
    """
    phi = np.asarray(phi, dtype=np.float64)
    out = []
    for x, y, z in phi.reshape(-1, 3).tolist():
        angle = math.sqrt((x * x + y * y) + z * z)
        if angle <= 1e-3:
            a2 = angle * angle
            scale = (0.5 - a2 / 48) + a2 * a2 / 3840
        else:
            scale = math.sin(angle / 2) / angle
        out.append((scale * x, scale * y, scale * z, math.cos(angle / 2)))
    return np.array(out, dtype=np.float64).reshape(phi.shape[:-1] + (4,))


def scipy_compose(p: ArrayLike, q: ArrayLike) -> FloatArray:
    """``(Rotation(p) * Rotation(q)).as_quat()`` of stored quaternions (..., 4), normalised."""
    p = np.asarray(p, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    px, py, pz, pw = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    qx, qy, qz, qw = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    r = np.stack([(pw * qx + qw * px) + (py * qz - pz * qy),
                  (pw * qy + qw * py) + (pz * qx - px * qz),
                  (pw * qz + qw * pz) + (px * qy - py * qx),
                  ((pw * qw - px * qx) - py * qy) - pz * qz], axis=-1)
    return r / _norm4(r)[..., None]
