"""The shared estimation kernel's pieces: state blocks, covariance helper, gate, IMU buffer,
sensitivity (consider parameters) — each against an independent computation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from stellar_cal_ros.core import covariance as cov
from stellar_cal_ros.core.gating import GatePolicy, block_nis, chi2_2_quantile
from stellar_cal_ros.core.imu import ImuBuffer
from stellar_cal_ros.core.rotation import so3_exp, so3_log
from stellar_cal_ros.core.state import Block, ErrorState, StateLayout
from stellar_cal_ros.errors import ModelError


def _spd(n, rng):
    A = rng.normal(size=(n, n))
    return A @ A.T + n * np.eye(n)


def test_layout_offsets_assemble_and_boxplus():
    lay = StateLayout([("attitude", 3, "rotation", True), ("theta", 4),
                       ("velocity", 3, "vector", True)])
    assert lay.size == 10 and lay.sl("theta") == slice(3, 7)
    assert list(lay.navigation_index) == [0, 1, 2, 7, 8, 9]
    H = lay.assemble({"theta": np.ones((2, 4)), "velocity": 2 * np.ones((2, 3))}, 2)
    assert H.shape == (2, 10) and H[:, :3].sum() == 0 and H[:, 7:].sum() == 12
    R = so3_exp([0.1, -0.2, 0.3])
    d = np.array([1e-3, 2e-3, -3e-3])
    assert np.allclose(lay["attitude"].boxplus(R, d), so3_exp(d) @ R)
    assert np.allclose(lay["velocity"].boxplus(np.ones(3), d), 1 + d)
    with pytest.raises(ValueError):
        StateLayout([("a", 1), ("a", 2)])


def test_error_state_owns_injection_reset_and_snapshots():
    """ErrorState: box-plus per block into its nominal value (θ blocks are slices of one
    vector whose consider tail no block touches), the rotation reset G P Gᵀ with the
    sensitivity's rows alike, the noise of bridged IMU intervals on the driven blocks, and
    snapshots that give back P, the nominal values and M."""
    rng = np.random.default_rng(7)
    lay = StateLayout([Block("attitude", 3, kind="rotation", navigation=True, driven_by="gyro"),
                       Block("a", 2, nominal="theta", index=slice(0, 2)),
                       Block("b", 1, nominal="theta", index=slice(2, 3)),
                       Block("velocity", 3, navigation=True, driven_by="accel")])
    R0, th0, v0 = so3_exp([0.1, -0.2, 0.3]), np.array([1.0, 2.0, 3.0, 9.0]), np.ones(3)
    st = ErrorState(lay, {"attitude": R0, "theta": th0.copy(), "velocity": v0}, n_consider=1)
    P0 = _spd(9, rng)
    st.P = P0.copy()
    st.sensitivity.M = rng.normal(size=(9, 1))
    M0 = st.sensitivity.M.copy()
    snap = st.snapshot(sensitivity=True)
    dx = rng.normal(scale=1e-2, size=9)
    st.inject(dx)
    np.testing.assert_allclose(st.nominal["attitude"], so3_exp(dx[:3]) @ R0, atol=1e-15)
    np.testing.assert_array_equal(st.nominal["theta"], np.append(th0[:3] + dx[3:6], 9.0))
    np.testing.assert_array_equal(st.nominal["velocity"], v0 + dx[6:])
    G = np.eye(9)
    G[:3, :3] += 0.5 * np.array([[0, -dx[2], dx[1]], [dx[2], 0, -dx[0]],
                                 [-dx[1], dx[0], 0]])
    np.testing.assert_allclose(st.P, G @ P0 @ G.T, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(st.sensitivity.M, G @ M0, rtol=1e-13, atol=1e-15)
    st.restore(snap)
    assert np.array_equal(st.P, P0) and np.array_equal(st.sensitivity.M, M0)
    assert np.array_equal(st.nominal["attitude"], R0)
    assert np.array_equal(st.nominal["theta"], th0)
    st.add_noise({"gyro": 2.0, "accel": 3.0})
    d = np.diag(st.P - P0)
    np.testing.assert_allclose(d, [2, 2, 2, 0, 0, 0, 3, 3, 3], atol=1e-12)
    st.forget(lay.navigation_index)
    assert not st.P[:, :3].any() and not st.P[6:].any() and st.P[3:6, 3:6].all()
    with pytest.raises(ValueError):
        ErrorState(lay, {"attitude": R0, "theta": th0})


def test_propagate_coupled_equals_dense():
    rng = np.random.default_rng(1)
    P = _spd(9, rng)
    F = rng.normal(size=(3, 4))
    q = rng.uniform(0, 1, 9)
    Phi = np.eye(9)
    Phi[0:3, 3:7] = F
    dense = cov.propagate(P, Phi, np.diag(q))
    P2 = P.copy()
    cov.propagate_coupled(P2, slice(0, 3), slice(3, 7), F, q)
    np.testing.assert_allclose(P2, dense, rtol=1e-12, atol=1e-12)


def test_iterated_update_linear_is_the_kalman_update():
    rng = np.random.default_rng(2)
    N, m = 6, 4
    P = _spd(N, rng)
    H = rng.normal(size=(m, N))
    r = rng.uniform(0.5, 2.0, m)
    z = rng.normal(size=m)
    h = np.zeros(m)
    res = cov.iterated_update(P, H, h, z, r, None, cov.UpdatePolicy())
    S = H @ P @ H.T + np.diag(r)
    K = P @ H.T @ np.linalg.inv(S)
    np.testing.assert_allclose(res.dx, K @ z, rtol=1e-10)
    np.testing.assert_allclose(res.P, (np.eye(N) - K @ H) @ P, rtol=1e-9, atol=1e-12)
    assert res.nis == pytest.approx(z @ np.linalg.solve(S, z), rel=1e-10)
    # a non-positive-definite innovation covariance is refused, not used
    bad = cov.iterated_update(P, H, h, z, -10 * np.abs(r) - 1e3, None, cov.UpdatePolicy())
    assert not bad.ok and not bad.dx.any()


def test_iterated_update_converges_on_a_nonlinear_measurement():
    """z = |x|² with a prior far off: the iterations reach the MAP estimate."""
    x_true = np.array([1.0, 2.0])
    P = np.diag([4.0, 4.0])
    x0 = np.array([2.0, 1.0])
    r = np.array([1e-6, 1e-6])
    z = np.array([x_true @ x_true, x_true[0]])

    def meas(x):
        return np.array([[2 * x[0], 2 * x[1]], [1.0, 0.0]]), np.array([x @ x, x[0]])

    H, h = meas(x0)
    res = cov.iterated_update(P, H, h, z, r, lambda dx: meas(x0 + dx),
                              cov.UpdatePolicy(max_iterations=20, iteration_tolerance=1e-10),
                              rotation=slice(0, 0), others=slice(0, 2))
    assert res.iterations > 2
    np.testing.assert_allclose(x0 + res.dx, x_true, atol=1e-5)


def test_reset_rotation_is_the_derivative_of_the_new_error():
    """φ' = Log(Exp(φ) Exp(−δ)); ∂φ'/∂φ at φ = δ is I + ½[δ]× to second order in δ."""
    delta = np.array([2e-3, -1e-3, 3e-3])
    J = np.zeros((3, 3))
    h = 1e-7
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        plus = so3_log(so3_exp(delta + e) @ so3_exp(-delta))
        minus = so3_log(so3_exp(delta - e) @ so3_exp(-delta))
        J[:, j] = (plus - minus) / (2 * h)
    P = np.block([[np.zeros((3, 3)), np.eye(3)], [np.eye(3), np.zeros((3, 3))]])
    cov.reset_rotation(P, slice(0, 3), delta)
    G = P[0:3, 3:6]  # the cross block picks up G once
    assert np.abs(G - np.eye(3)).max() > 1e-3  # the first-order term is there ...
    np.testing.assert_allclose(G, J, atol=5e-6)  # ... and equals the derivative


def test_repair_clips_to_positive_definite():
    rng = np.random.default_rng(3)
    P = _spd(5, rng)
    w, V = np.linalg.eigh(P)
    bad = (V * np.r_[-1.0, w[1:]]) @ V.T
    with pytest.raises(ModelError):
        cov.check(bad)
    cov.check(cov.repair(bad))
    assert cov.repair(np.full((2, 2), np.nan)) is None


def test_gate_chi2_scaling_lost_lock_and_fov():
    assert chi2_2_quantile(0.9999) == pytest.approx(chi2.ppf(0.9999, 2), rel=1e-12)
    rng = np.random.default_rng(4)
    S = np.tile(np.eye(2), (20, 1, 1))
    nu = rng.normal(size=(20, 2))
    nis = block_nis(nu, S)
    np.testing.assert_allclose(nis, np.sum(nu**2, axis=1))
    d = np.tile([0.0, 0.0, 1.0], (20, 1))
    gate = GatePolicy(fov_tan2=0.01)
    nis[3] = 1e3  # one misidentified star
    dec = gate.decide(nis, d)
    assert not dec.accepted[3] and dec.accepted.sum() == 19 and not dec.mismatch
    # every star 10x: a missing effect, not 20 outliers — scaled, all kept, flagged
    dec = gate.decide(np.sum(nu**2, axis=1) * 10 + 1.0, d)
    assert dec.mismatch and dec.accepted.sum() >= 18
    dec = gate.decide(np.full(20, 1e6), d)
    assert dec.lost_lock and not dec.accepted.any()
    d2 = d.copy()
    d2[5] = [0.5, 0.0, 1.0]  # 26.6° off axis
    d2[6] = [0.0, 0.0, -1.0]  # behind
    dec = gate.decide(np.ones(20), d2)
    assert dec.outside_fov == 2 and not dec.accepted[5] and not dec.accepted[6]


def test_imu_buffer_bridges_a_missing_sample():
    dt = 0.01
    t = np.arange(1, 101) * dt
    w = np.zeros((100, 3))
    w[50:, 0] = 1.0  # a rate step between samples 49 and 50 (a slew's corner)
    keep = np.ones(100, dtype=bool)
    keep[50] = False  # the sample right at the corner is lost
    buf = ImuBuffer(dt, gap_rate_sigma=1e-3)
    assert buf.append(t[keep][:70], w[keep][:70]) == 71  # one bridged sample inserted
    buf.append(t[keep][70:], w[keep][70:])
    assert len(buf) == 100 and np.allclose(buf.t, t)
    k = 50
    # the rate left its trend by 1 rad/s: the bridged rate may be off by half of that
    assert buf.w[k, 0] == pytest.approx(0.5) and buf.bvar_w[k] == pytest.approx(0.25)
    assert buf.counters["imu_bridged"] == 1 and not buf.long_gap.any()
    # over the bridged interval the attitude error is bounded by its σ: |0.5 − 1| dt ≤ 1σ·dt
    var_w, _, long, entered = buf.bridged_variance(t[45], t[55], 45, 55)
    assert var_w == pytest.approx(0.25 * dt**2) and entered == 1 and not long
    # on a smooth ramp the linear bridge is exact and claims (almost) nothing: the noise
    ramp = ImuBuffer(dt, rate_noise_sigma=1e-6)
    w_ramp = np.zeros((100, 3))
    w_ramp[:, 2] = 0.01 * np.arange(100)
    ramp.append(t[keep], w_ramp[keep])
    assert ramp.w[50, 2] == pytest.approx(0.5) and ramp.bvar_w[50] == pytest.approx(2e-12)
    # a long gap: flagged for re-acquisition once the interval is inside it
    buf2 = ImuBuffer(dt, reacquire_s=0.1)
    buf2.append(t[:20], w[:20])
    buf2.append(np.array([0.5, 0.51]), np.zeros((2, 3)))
    assert buf2.counters["imu_long_gaps"] == 1
    m = buf2.index(0.45)
    assert buf2.bridged_variance(0.2, 0.45, buf2.index(0.2), m)[2]
    assert not buf2.bridged_variance(0.2, 0.25, buf2.index(0.2), buf2.index(0.25))[2]
    # round trip and drop
    other = ImuBuffer(dt)
    other.load_state(buf.state())
    assert np.array_equal(other.w, buf.w) and np.array_equal(other.cum_bridged, buf.cum_bridged)
    buf.drop(30)
    assert buf.base == 30 and np.allclose(buf.t[0], t[30])
    with pytest.raises(ValueError):
        buf.append(np.array([0.0]), np.zeros((1, 3)))


def test_sensitivity_is_the_exact_response_of_a_linear_filter():
    """A linear KF that ignores a constant β: its estimate moves by −M b when the data hold
    b; the score and information recover b exactly from noise-free data."""
    rng = np.random.default_rng(6)
    n, m, steps = 3, 2, 60
    Phi = np.eye(n) + 0.05 * rng.normal(size=(n, n))
    Phi_b = 0.1 * rng.normal(size=(n, m))
    Q = 0.01 * np.eye(n)
    R = 0.04 * np.eye(2)
    Hs = [rng.normal(size=(2, n)) for _ in range(steps)]
    Hbs = [rng.normal(size=(2, m)) for _ in range(steps)]
    b = np.array([0.3, -0.2])
    noise = [rng.normal(size=2) * 0.2 for _ in range(steps)]

    def run(with_b: bool, noisy: bool):
        x = np.zeros(n)
        xh = np.zeros(n)
        P = np.eye(n)
        sens = cov.Sensitivity(n, m)
        for k in range(steps):
            x = Phi @ x + (Phi_b @ b if with_b else 0)
            xh = Phi @ xh
            P = cov.propagate(P, Phi, Q)
            sens.propagate(Phi, Phi_b)
            z = Hs[k] @ x + (Hbs[k] @ b if with_b else 0) + (noise[k] if noisy else 0)
            nu = z - Hs[k] @ xh
            S = Hs[k] @ P @ Hs[k].T + R
            K = P @ Hs[k].T @ np.linalg.inv(S)
            sens.update(Hs[k], Hbs[k], K, nu, S)
            xh = xh + K @ nu
            P = (np.eye(n) - K @ Hs[k]) @ P
        return x, xh, sens

    x0, xh0, _ = run(False, True)
    x1, xh1, sens = run(True, True)
    # e = x − x̂ has mean M b: the difference of the two runs' errors is exactly M b
    np.testing.assert_allclose((x1 - xh1) - (x0 - xh0), sens.M @ b, rtol=1e-9, atol=1e-12)
    _, _, clean = run(True, False)
    np.testing.assert_allclose(np.linalg.solve(clean.info, clean.score), b, rtol=1e-8)
    # with noise and b = 0 the score statistic is χ²_m: moderate
    _, _, null = run(False, True)
    lm = null.score @ np.linalg.solve(null.info, null.score)
    assert lm < chi2.ppf(0.999, m)
    assert math.isfinite(lm)
