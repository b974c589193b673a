"""Tests of stellar_cal_ros.core.strapdown (inertial-frame strapdown integration)."""

from __future__ import annotations

import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stellar_cal_ros.core import earth
from stellar_cal_ros.core.strapdown import (
    attitude_increments,
    propagate_attitude,
    propagate_velocity_position_inertial,
    quat_cumprod,
    quat_multiply,
    velocity_increments,
)

SITE = earth.Site(36.07, 120.38, 10.0)
T0 = 1795348800.0  # 2026-11-22T12:00:00 UTC, as the reference bags


def _angle(a: Rotation, b: Rotation) -> np.ndarray:
    return (a.inv() * b).magnitude()


# --- (a) prefix scan -------------------------------------------------------------------------
def test_quat_multiply_matches_scipy():
    rng = np.random.default_rng(1)
    p = Rotation.random(50, random_state=rng)
    q = Rotation.random(50, random_state=rng)
    pq = quat_multiply(p.as_quat(), q.as_quat())
    assert np.max(_angle(Rotation.from_quat(pq), p * q)) < 1e-14


@pytest.mark.parametrize("n", [1, 2, 3, 5, 8, 17, 1000, 4097])
def test_quat_cumprod_equals_sequential_loop(n):
    rng = np.random.default_rng(n)
    q = Rotation.from_rotvec(rng.normal(size=(n, 3)) * 0.3).as_quat()
    P = quat_cumprod(q)
    r = Rotation.identity()
    seq = []
    for k in range(n):
        r = r * Rotation.from_quat(q[k])
        seq.append(r.as_quat())
    err = _angle(Rotation.from_quat(np.array(seq)), Rotation.from_quat(P))
    assert np.max(err) < 1e-12
    assert np.allclose(np.linalg.norm(P, axis=1), 1.0, atol=1e-15)


def test_quat_cumprod_speed_720k():
    rng = np.random.default_rng(0)
    q = Rotation.from_rotvec(rng.normal(size=(720_000, 3)) * 0.01).as_quat()
    quat_cumprod(q[:1000])  # warm up
    times = []
    for _ in range(3):  # best of 3 in CPU time: robust against a busy CI machine
        t = time.process_time()
        P = quat_cumprod(q)
        times.append(time.process_time() - t)
    elapsed = min(times)
    print(f"quat_cumprod 720000 samples: {elapsed:.3f} s (best of 3)")
    assert P.shape == (720_000, 4)
    assert elapsed < 1.0


# --- (b) coning ------------------------------------------------------------------------------
def _coning_truth(t: np.ndarray, beta: float, Om: float) -> Rotation:
    """R(t) = Rz(Om t) Rx(beta) Rz(-Om t): rotation by beta about an axis circling in xy."""
    return (
        Rotation.from_rotvec(np.outer(Om * t, [0, 0, 1]))
        * Rotation.from_rotvec([beta, 0, 0])
        * Rotation.from_rotvec(np.outer(-Om * t, [0, 0, 1]))
    )


def _coning_rate(t: np.ndarray, beta: float, Om: float) -> np.ndarray:
    """Body rate w = Om (R^T e_z - e_z)."""
    return Om * np.stack(
        [-np.sin(beta) * np.sin(Om * t), np.sin(beta) * np.cos(Om * t), np.cos(beta) - 1 + 0 * t],
        axis=-1,
    )


def _coning_increments(ta: np.ndarray, tb: np.ndarray, beta: float, Om: float) -> np.ndarray:
    """Exact interval integrals of the coning body rate over (ta, tb]."""
    sb = np.sin(beta)
    return np.stack(
        [
            -sb * (np.cos(Om * ta) - np.cos(Om * tb)),
            sb * (np.sin(Om * tb) - np.sin(Om * ta)),
            (np.cos(beta) - 1.0) * Om * (tb - ta),
        ],
        axis=-1,
    )


def test_coning_rate_formula_is_the_derivative_of_the_truth():
    beta, Om, h = 0.3, 2.0, 1e-5
    t = np.array([0.1, 0.7, 2.3])
    Rm, Rp = _coning_truth(t - h, beta, Om), _coning_truth(t + h, beta, Om)
    w_fd = (Rm.inv() * Rp).as_rotvec() / (2 * h)
    assert np.allclose(w_fd, _coning_rate(t, beta, Om), atol=1e-8)


def test_coning_correction():
    beta, Om, rate, duration = np.radians(1.0), 2 * np.pi * 1.0, 100.0, 60.0
    T = 1.0 / rate
    n = int(round(duration * rate))
    tb = np.arange(1, n + 1) * T
    ta = tb - T
    dth = _coning_increments(ta, tb, beta, Om)
    w = dth / T  # mean rate over the interval ending at the stamp
    truth = _coning_truth(tb, beta, Om)
    R0 = _coning_truth(np.array([0.0]), beta, Om)[0]
    err_c = _angle(truth, propagate_attitude(R0, w, T, coning=True))
    err_n = _angle(truth, propagate_attitude(R0, w, T, coning=False))
    # fourth-order residual of the two-sample algorithm: W sin^2(beta) (W T)^4 / 60 rad/s
    bound = Om * np.sin(beta) ** 2 * (Om * T) ** 4 / 60.0 * duration
    print(
        f"coning 60 s: error with correction {err_c.max():.3e} rad, without {err_n.max():.3e} "
        f"rad, ratio {err_n.max() / err_c.max():.3g}, 4th-order bound {bound:.3e} rad"
    )
    assert err_c.max() < 2.0 * bound + 1e-12
    assert err_n.max() > 100.0 * err_c.max()


def test_attitude_increments_first_sample_uncorrected_and_bias():
    rng = np.random.default_rng(3)
    w = rng.normal(size=(10, 3))
    phi = attitude_increments(w, 0.01)
    assert np.allclose(phi[0], w[0] * 0.01)
    assert np.allclose(phi[1], w[1] * 0.01 + np.cross(w[0], w[1]) * 1e-4 / 12)
    b = np.array([0.01, -0.02, 0.03])
    R1 = propagate_attitude(Rotation.identity(), w + b, 0.01, gyro_bias=b)
    R2 = propagate_attitude(Rotation.identity(), w, 0.01)
    assert np.max(_angle(R1, R2)) < 1e-14


# --- (c) rotation / sculling compensation -----------------------------------------------------
def test_constant_rotation_and_specific_force():
    rate, duration = 100.0, 60.0
    T = 1.0 / rate
    n = int(duration * rate)
    w = np.array([0.3, -0.2, 0.5])
    f = np.array([1.0, 2.0, 9.8])
    W = np.linalg.norm(w)
    nax = w / W
    tk = np.arange(1, n + 1) * T
    f_par = nax * (nax @ f)
    f_perp = f - f_par
    v_true = (
        np.outer(tk, f_par)
        + np.outer(np.sin(W * tk) / W, f_perp)
        + np.outer((1 - np.cos(W * tk)) / W, np.cross(nax, f))
    )
    ws = np.tile(w, (n, 1))
    fs = np.tile(f, (n, 1))
    R0 = Rotation.identity()
    Rk = propagate_attitude(R0, ws, T)
    Rall = np.concatenate([R0.as_matrix()[None], Rk.as_matrix()])
    errs = {}
    for scul in (True, False):
        du = velocity_increments(ws, fs, T, sculling=scul)
        v, p = propagate_velocity_position_inertial(
            Rall, du, T, np.zeros(3), np.zeros(3), np.zeros(3)
        )
        errs[scul] = np.max(np.linalg.norm(v - v_true, axis=1))
    print(
        f"constant rotation 60 s: |dv| error {errs[True]:.3e} m/s (uncompensated {errs[False]:.3e})"
    )
    assert errs[True] < 1e-9
    assert errs[False] > 1e3 * errs[True]


def test_classic_sculling():
    """theta = th0 sin(W t) about x, f = A sin(W t) e_y: rectified acceleration A th0 / 2 on z."""
    th0, A, Om = 0.01, 1.0, 2 * np.pi * 2.0
    rate, duration = 100.0, 20.0
    T = 1.0 / rate
    n = int(duration * rate)
    tb = np.arange(1, n + 1) * T
    ta = tb - T
    ws = np.zeros((n, 3))
    fs = np.zeros((n, 3))
    ws[:, 0] = th0 * (np.sin(Om * tb) - np.sin(Om * ta)) / T  # int th0 W cos(W t)
    fs[:, 1] = A * (np.cos(Om * ta) - np.cos(Om * tb)) / Om / T  # int A sin(W t)
    # truth: attitude Rx(theta); velocity int Rx(theta) f dt by Gauss-Legendre quadrature
    x, wq = np.polynomial.legendre.leggauss(12)
    sub = 10
    edges = np.linspace(0.0, duration, n * sub + 1)
    h = np.diff(edges)[:, None]
    s = 0.5 * (edges[:-1, None] + edges[1:, None]) + 0.5 * h * x[None, :]
    th = th0 * np.sin(Om * s)
    a_y = (A * np.sin(Om * s) * np.cos(th) * wq * 0.5 * h).sum(axis=1)
    a_z = (A * np.sin(Om * s) * np.sin(th) * wq * 0.5 * h).sum(axis=1)
    v_true = np.stack(
        [np.zeros(n), np.cumsum(a_y)[sub - 1 :: sub], np.cumsum(a_z)[sub - 1 :: sub]], 1
    )
    R0 = Rotation.identity()
    Rk = propagate_attitude(R0, ws, T)
    th_true = th0 * np.sin(Om * tb)
    assert np.max(np.abs(Rk.as_rotvec()[:, 0] - th_true)) < 1e-12
    Rall = np.concatenate([R0.as_matrix()[None], Rk.as_matrix()])
    errs = {}
    for scul in (True, False):
        du = velocity_increments(ws, fs, T, sculling=scul)
        v, _ = propagate_velocity_position_inertial(
            Rall, du, T, np.zeros(3), np.zeros(3), np.zeros(3)
        )
        errs[scul] = np.max(np.linalg.norm(v - v_true, axis=1))
    print(
        f"classic sculling 20 s: |dv| error {errs[True]:.3e} m/s "
        f"(uncompensated {errs[False]:.3e}); rectified z velocity {v_true[-1, 2]:.4f} m/s"
    )
    assert abs(v_true[-1, 2] - A * th0 / 2 * duration) < 1e-3 * A * th0 * duration
    # fourth-order residual (the sculling analogue of the coning one): (A th0 / 2) (W T)^4 / 30
    bound = A * th0 / 2 * (Om * T) ** 4 / 30 * duration
    print(f"classic sculling 4th-order bound {bound:.3e} m/s")
    assert errs[True] < 2 * bound
    assert errs[False] > 100 * errs[True]


def test_position_integration_and_callable_gravity():
    n, T = 500, 0.01
    g = np.array([0.0, 0.0, -9.8])
    Rall = np.tile(np.eye(3), (n + 1, 1, 1))
    du = np.zeros((n, 3))
    v0 = np.array([1.0, 2.0, 3.0])
    p0 = np.array([10.0, 20.0, 30.0])
    v, p = propagate_velocity_position_inertial(Rall, du, T, g, v0, p0)
    t = np.arange(1, n + 1) * T
    assert np.allclose(v, v0 + np.outer(t, g), atol=1e-12)
    assert np.allclose(p, p0 + np.outer(t, v0) + 0.5 * np.outer(t**2, g), atol=1e-9)
    v2, p2 = propagate_velocity_position_inertial(Rall, du, T, lambda k, pm: g, v0, p0)
    assert np.allclose(v2, v, atol=1e-12) and np.allclose(p2, p, atol=1e-9)


# --- (d) stationary IMU on the Earth ------------------------------------------------------------
def test_stationary_imu_on_earth_keeps_site_inertial_velocity():
    rate, duration = 100.0, 600.0
    T = 1.0 / rate
    n = int(duration * rate)
    tk = T0 + np.arange(1, n + 1) * T
    R_enu_b = Rotation.from_euler("zyx", [30.0, -10.0, 5.0], degrees=True).as_matrix()
    R_itrs_b = earth.R_itrs_enu(SITE) @ R_enu_b

    def R_i_b(t):
        return np.swapaxes(earth.R_itrs_gcrs(t), -1, -2) @ R_itrs_b

    # gyros: Earth rate; accelerometers: f = a_site - G (inertial), constant in the body
    w_b = R_itrs_b.T @ earth.earth_rotation_itrs()
    tc = np.array([T0, T0 + 300.0, T0 + 600.0])
    f_i = earth.site_acceleration_gcrs(SITE, tc) - earth.gravitation_gcrs(SITE, tc)
    f_b = np.einsum("kji,kj->ki", R_i_b(tc), f_i)
    assert np.max(np.abs(f_b - f_b[0])) < 1e-9
    # f = -(gravitation - centripetal) = -gravity
    assert np.allclose(f_b[0], -R_itrs_b.T @ earth.gravity_itrs(SITE), atol=1e-9)
    ws = np.tile(w_b, (n, 1))
    fs = np.tile(f_b[0], (n, 1))

    R0 = Rotation.from_matrix(R_i_b(T0))
    Rk = propagate_attitude(R0, ws, T)
    att_err = _angle(Rotation.from_matrix(R_i_b(tk)), Rk)
    Rall = np.concatenate([R0.as_matrix()[None], Rk.as_matrix()])
    du = velocity_increments(ws, fs, T)
    G = earth.gravitation_gcrs(SITE, tk - 0.5 * T)
    v0 = earth.site_velocity_gcrs(SITE, T0)
    p0 = earth.site_position_gcrs(SITE, T0)
    v, p = propagate_velocity_position_inertial(Rall, du, T, G, v0, p0)
    v_true = earth.site_velocity_gcrs(SITE, tk)
    p_true = earth.site_position_gcrs(SITE, tk)
    dv = np.linalg.norm(v - v_true, axis=1)
    dp = np.linalg.norm(p - p_true, axis=1)
    print(
        f"stationary 600 s: attitude error {att_err.max():.2e} rad, velocity error "
        f"{dv.max() * 1e3:.4f} mm/s, position error {dp.max() * 1e3:.3f} mm"
    )
    assert att_err.max() < 1e-8
    assert dv.max() < 1e-3
    assert dp.max() < 0.3


def test_quat_cumprod_in_place_is_the_copying_scan_bit_for_bit():
    """``overwrite=True`` on a (4, N) layout scans the caller's array (the twin's trajectory,
    23 MB on a 2-h bag): the same numbers as the scan of a copy; other layouts are copied."""
    from stellar_cal_ros.core.rotation import quat_from_rotvec

    rng = np.random.default_rng(3)
    q = quat_from_rotvec(rng.normal(size=(4097, 3)) * 1e-2)
    want = quat_cumprod(q)
    soa = np.empty((4, len(q))).T
    soa[:] = q
    assert np.array_equal(quat_cumprod(soa, overwrite=True), want)
    assert not np.array_equal(soa, q)  # scanned in place
    kept = q.copy()
    assert np.array_equal(quat_cumprod(kept, overwrite=True), want)
    assert np.array_equal(kept, q)  # an (N, 4) array is copied, as without overwrite
