"""Tests of stellar_cal_ros.core.rotation against scipy and finite differences."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stellar_cal_ros.core import rotation as rot


def _rotvecs(rng: np.random.Generator, n: int) -> np.ndarray:
    """Rotation vectors spanning tiny, small, moderate and near-pi angles."""
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate(
        [
            np.zeros(1),
            10.0 ** rng.uniform(-12, -2, n // 4),
            rng.uniform(1e-2, 1.0, n // 4),
            rng.uniform(1.0, np.pi - 1e-3, n - 1 - 2 * (n // 4) - 3),
            np.pi - np.array([1e-9, 1e-6, 1e-4]),
        ]
    )
    return axes * angles[:, None]


def test_skew() -> None:
    rng = np.random.default_rng(0)
    a = rng.normal(size=(4, 5, 3))
    b = rng.normal(size=(4, 5, 3))
    S = rot.skew(a)
    assert S.shape == (4, 5, 3, 3)
    np.testing.assert_allclose(np.einsum("...ij,...j->...i", S, b), np.cross(a, b), atol=1e-15)
    np.testing.assert_array_equal(S, -np.swapaxes(S, -1, -2))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        rot.skew(np.zeros(4))


def test_exp_matches_scipy() -> None:
    rng = np.random.default_rng(1)
    phi = _rotvecs(rng, 400)
    R = rot.so3_exp(phi)
    np.testing.assert_allclose(R, Rotation.from_rotvec(phi).as_matrix(), atol=2e-15)
    np.testing.assert_allclose(
        R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=2e-15
    )
    np.testing.assert_array_equal(rot.so3_exp(np.zeros(3)), np.eye(3))
    # Tiny angles: first order exact to rounding.
    tiny = np.array([1e-10, -2e-10, 3e-10])
    np.testing.assert_allclose(rot.so3_exp(tiny), np.eye(3) + rot.skew(tiny), atol=1e-19, rtol=0)


def test_exp_batched_shapes() -> None:
    rng = np.random.default_rng(2)
    phi = rng.normal(size=(2, 3, 3))
    assert rot.so3_exp(phi).shape == (2, 3, 3, 3)
    assert rot.so3_log(rot.so3_exp(phi)).shape == (2, 3, 3)
    assert rot.right_jacobian(phi).shape == (2, 3, 3, 3)
    assert rot.so3_exp(np.zeros(3)).shape == (3, 3)


def test_log_inverts_exp() -> None:
    rng = np.random.default_rng(3)
    phi = _rotvecs(rng, 400)
    back = rot.so3_log(rot.so3_exp(phi))
    # Relative accuracy for small angles, absolute for large.
    err = np.linalg.norm(back - phi, axis=1)
    tol = 1e-15 * np.maximum(np.linalg.norm(phi, axis=1), 1e-300) + 4e-15
    assert np.all(err <= np.maximum(tol, 1e-12 * (np.linalg.norm(phi, axis=1) > 3.1)))
    np.testing.assert_allclose(back, Rotation.from_matrix(rot.so3_exp(phi)).as_rotvec(), atol=1e-9)
    tiny = np.array([[1e-14, -3e-14, 2e-15]])
    np.testing.assert_allclose(rot.so3_log(rot.so3_exp(tiny)), tiny, rtol=1e-10, atol=0)
    np.testing.assert_array_equal(rot.so3_log(np.eye(3)), np.zeros(3))


def test_log_at_pi() -> None:
    for axis in np.eye(3):
        R = rot.so3_exp(np.pi * axis)
        phi = rot.so3_log(R)
        assert np.isclose(np.linalg.norm(phi), np.pi)
        np.testing.assert_allclose(rot.so3_exp(phi), R, atol=1e-15)


def test_log_of_random_matrices_matches_scipy() -> None:
    R = Rotation.random(500, random_state=4)
    np.testing.assert_allclose(rot.so3_log(R.as_matrix()), R.as_rotvec(), atol=1e-12)


def test_quaternions_match_scipy() -> None:
    rng = np.random.default_rng(5)
    r1 = Rotation.random(300, random_state=5)
    r2 = Rotation.random(300, random_state=6)
    q1, q2 = r1.as_quat(), r2.as_quat()
    prod = rot.quat_multiply(q1, q2)
    ref = (r1 * r2).as_quat()
    prod *= np.sign(prod[:, 3:]) * np.sign(ref[:, 3:])
    np.testing.assert_allclose(prod, ref, atol=1e-15)
    np.testing.assert_allclose(
        rot.quat_to_matrix(prod), r1.as_matrix() @ r2.as_matrix(), atol=1e-14
    )
    # Broadcasting: one quaternion times many.
    np.testing.assert_allclose(
        rot.quat_multiply(q1[0], q2), rot.quat_multiply(np.broadcast_to(q1[0], q2.shape), q2)
    )
    np.testing.assert_allclose(rot.quat_to_matrix(q1), r1.as_matrix(), atol=1e-15)
    q_from_m = rot.quat_from_matrix(r1.as_matrix())
    assert np.all(q_from_m[:, 3] >= 0.0)
    np.testing.assert_allclose(np.abs(np.sum(q_from_m * q1, axis=1)), 1.0, atol=1e-14)
    # one matrix (the single-frame refits' so3_log): the batched form's floats bit for bit,
    # through each of the four pivots (x, y, z about pi; small angles: w), slightly
    # non-orthonormal matrices too
    mats = np.concatenate([r1.as_matrix(), rot.so3_exp(np.pi * np.eye(3) * 0.999),
                           r1.as_matrix()[:100] + 1e-9 * rng.normal(size=(100, 3, 3))])
    pivots = set()
    for m in mats:
        pivots.add(int(np.argmax([m[0, 0], m[1, 1], m[2, 2], np.trace(m)])))
        assert np.array_equal(rot.quat_from_matrix(m), rot.quat_from_matrix(m[None])[0])
    assert pivots == {0, 1, 2, 3}
    phi = _rotvecs(rng, 100)
    ref_q = Rotation.from_rotvec(phi).as_quat()
    ref_q *= np.sign(ref_q[:, 3:])
    np.testing.assert_allclose(rot.quat_from_rotvec(phi), ref_q, atol=1e-15)
    np.testing.assert_allclose(rot.quat_to_rotvec(rot.quat_from_rotvec(phi)), phi, atol=1e-12)
    v = rng.normal(size=(300, 3))
    np.testing.assert_allclose(rot.quat_rotate(q1, v), r1.apply(v), atol=1e-14)
    np.testing.assert_allclose(
        rot.quat_multiply(q1, rot.quat_conjugate(q1)),
        np.tile([0, 0, 0, 1.0], (300, 1)),
        atol=1e-15,
    )


def test_frame_convention() -> None:
    """R_a_c = R_a_b @ R_b_c and q_a_c = q_a_b * q_b_c."""
    rng = np.random.default_rng(7)
    R_a_b = rot.so3_exp(rng.normal(size=3))
    R_b_c = rot.so3_exp(rng.normal(size=3))
    v_c = rng.normal(size=3)
    v_a = R_a_b @ (R_b_c @ v_c)
    q = rot.quat_multiply(rot.quat_from_matrix(R_a_b), rot.quat_from_matrix(R_b_c))
    np.testing.assert_allclose(rot.quat_rotate(q, v_c), v_a, atol=1e-14)


def test_boxplus_boxminus() -> None:
    rng = np.random.default_rng(8)
    R0 = rot.so3_exp(rng.normal(size=(50, 3)))
    delta = rng.normal(scale=0.3, size=(50, 3))
    R = rot.so3_boxplus(R0, delta)
    np.testing.assert_allclose(R, R0 @ rot.so3_exp(delta), atol=1e-15)
    np.testing.assert_allclose(rot.so3_boxminus(R, R0), delta, atol=1e-13)


def test_orthonormalize() -> None:
    rng = np.random.default_rng(9)
    R = rot.so3_exp(rng.normal(size=(20, 3)))
    noisy = R + rng.normal(scale=1e-6, size=R.shape)
    Q = rot.orthonormalize(noisy)
    np.testing.assert_allclose(
        Q @ np.swapaxes(Q, -1, -2), np.broadcast_to(np.eye(3), Q.shape), atol=1e-14
    )
    assert np.all(np.linalg.det(Q) > 0)
    np.testing.assert_allclose(Q, R, atol=1e-5)


def _numeric_right_jacobian(phi: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """d Log(Exp(phi)^T Exp(phi + delta)) / d delta by central differences."""
    J = np.empty((3, 3))
    R = rot.so3_exp(phi)
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        plus = rot.so3_log(R.T @ rot.so3_exp(phi + e))
        minus = rot.so3_log(R.T @ rot.so3_exp(phi - e))
        J[:, j] = (plus - minus) / (2.0 * h)
    return J


def _numeric_left_jacobian(phi: np.ndarray, h: float = 1e-6) -> np.ndarray:
    J = np.empty((3, 3))
    R = rot.so3_exp(phi)
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        plus = rot.so3_log(rot.so3_exp(phi + e) @ R.T)
        minus = rot.so3_log(rot.so3_exp(phi - e) @ R.T)
        J[:, j] = (plus - minus) / (2.0 * h)
    return J


ANGLES = [0.0, 1e-9, 1e-5, 5e-3, 1e-2, 2e-2, 0.3, 1.5, 3.0]


@pytest.mark.parametrize("angle", ANGLES)
def test_jacobians_finite_differences(angle: float) -> None:
    rng = np.random.default_rng(10)
    axis = rng.normal(size=3)
    phi = angle * axis / np.linalg.norm(axis)
    np.testing.assert_allclose(rot.right_jacobian(phi), _numeric_right_jacobian(phi), atol=1e-8)
    np.testing.assert_allclose(rot.left_jacobian(phi), _numeric_left_jacobian(phi), atol=1e-8)
    # The inverse Jacobians: d Log(Exp(phi) Exp(delta)) / d delta.
    Jr_inv = rot.right_jacobian_inverse(phi)
    Jl_inv = rot.left_jacobian_inverse(phi)
    h = 1e-6
    R = rot.so3_exp(phi)
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        num_r = (rot.so3_log(R @ rot.so3_exp(e)) - rot.so3_log(R @ rot.so3_exp(-e))) / (2 * h)
        num_l = (rot.so3_log(rot.so3_exp(e) @ R) - rot.so3_log(rot.so3_exp(-e) @ R)) / (2 * h)
        np.testing.assert_allclose(Jr_inv[:, j], num_r, atol=1e-8)
        np.testing.assert_allclose(Jl_inv[:, j], num_l, atol=1e-8)


def test_jacobian_identities() -> None:
    rng = np.random.default_rng(11)
    phi = _rotvecs(rng, 200)
    phi = phi[np.linalg.norm(phi, axis=1) < 3.0]
    eye = np.broadcast_to(np.eye(3), (len(phi), 3, 3))
    Jr = rot.right_jacobian(phi)
    Jl = rot.left_jacobian(phi)
    np.testing.assert_allclose(Jr @ rot.right_jacobian_inverse(phi), eye, atol=1e-12)
    np.testing.assert_allclose(Jl @ rot.left_jacobian_inverse(phi), eye, atol=1e-12)
    np.testing.assert_allclose(Jl, np.swapaxes(Jr, -1, -2), atol=1e-15)
    np.testing.assert_allclose(Jl, rot.right_jacobian(-phi), atol=1e-15)
    # Jl = R Jr.
    np.testing.assert_allclose(Jl, rot.so3_exp(phi) @ Jr, atol=1e-14)


def test_jacobian_series_continuity() -> None:
    """No jump where the coefficients switch from their series to the closed forms."""
    axis = np.array([0.6, -0.8, 0.0])
    below = (1e-2 - 1e-16) * axis
    above = (1e-2 + 1e-16) * axis
    for f in (
        rot.right_jacobian,
        rot.left_jacobian,
        rot.right_jacobian_inverse,
        rot.left_jacobian_inverse,
    ):
        np.testing.assert_allclose(f(below), f(above), atol=1e-15, rtol=0)


def test_scipy_floats_without_scipy_are_rotations_bit_for_bit() -> None:
    """``scipy_*`` (what a replay uses instead of importing ``scipy.spatial``, issue 24.1)
    give ``Rotation``'s floats exactly: normalising, to a matrix, from an orthonormal matrix
    (every pivot, ties, few and many matrices), from rotation vectors on both sides of the
    series' 1e-3 rad, and composing stored quaternions."""
    rng = np.random.default_rng(24)
    n = 20_000
    q = rng.normal(size=(n, 4)) * rng.choice([1e-3, 1.0, 1e3], size=(n, 1))
    r = Rotation.from_quat(q)
    assert np.array_equal(rot.scipy_quat(q), r.as_quat())
    assert np.array_equal(rot.scipy_matrix(r.as_quat()), r.as_matrix())
    U, _, Vt = np.linalg.svd(r.as_matrix() + rng.normal(size=(n, 3, 3)) * 1e-9)
    m = U @ Vt
    m[np.linalg.det(m) < 0] *= -1
    m[:6] = [np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1]),
             Rotation.from_rotvec([0, 0, np.pi / 2]).as_matrix(),
             Rotation.from_rotvec([np.pi, 0, 0]).as_matrix()]
    ref = Rotation.from_matrix(m, assume_valid=True)
    assert np.array_equal(rot.scipy_quat_from_matrix(m), ref.as_quat())
    assert np.array_equal(rot.scipy_matrix_roundtrip(m), ref.as_matrix())
    for k in (1, 2, 3, 8):  # the Python-float path of a few matrices
        for a in range(0, 600, k):
            assert np.array_equal(rot.scipy_matrix_roundtrip(m[a:a + k]),
                                  Rotation.from_matrix(m[a:a + k], assume_valid=True).as_matrix())
    v = rng.normal(size=(n, 3)) * rng.choice([0.0, 1e-6, 0.999e-3, 1e-3, 1.001e-3, 1e-2, 3.0],
                                              size=(n, 1))
    assert np.array_equal(rot.scipy_quat_from_rotvec(v), Rotation.from_rotvec(v).as_quat())
    assert np.array_equal(rot.scipy_quat_from_rotvec(v[7]), Rotation.from_rotvec(v[7]).as_quat())
    assert np.array_equal(rot.scipy_compose(r.as_quat(), rot.scipy_quat_from_rotvec(v)),
                          (r * Rotation.from_rotvec(v)).as_quat())
    # (normalising a stored quaternion again moves some by an ulp: the functions take the
    # stored one, never Rotation.from_quat of it)
    assert not np.array_equal(rot.scipy_quat(r.as_quat()), r.as_quat())
