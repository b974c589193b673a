"""The filters' one IMU propagation (core/propagation.py, core/imu_prefix.py).

Its Jacobians (attitude, velocity, position per sensor parameter) against finite differences
of its own nominal propagation, the first-order (fast) path against the per-sample (exact)
one, and the reference rows independent of how the samples were batched (live use).
"""

from __future__ import annotations

import numpy as np
import pytest

from stellar_cal_ros.core.imu import ImuBuffer
from stellar_cal_ros.core.imu_prefix import ImuPrefix
from stellar_cal_ros.core.propagation import ImuPropagation, SensorModel
from stellar_cal_ros.core.rotation import so3_exp, so3_log

DT = 0.01
G = np.array([0.3, -0.2, -9.8])


def _sensor(offset: int, P: int) -> SensorModel:
    """Bias (3) and a full error matrix (9) at ``offset`` of a P-parameter θ (affine)."""
    Jb = np.zeros((3, P))
    Jb[:, offset:offset + 3] = np.eye(3)
    JE = np.zeros((3, 3, P))
    for i in range(3):
        for j in range(3):
            JE[i, j, offset + 3 + 3 * i + j] = 1.0

    def model(theta):
        return Jb @ theta, JE @ theta, Jb, JE

    return SensorModel(model, np.zeros(P), np.full(P, 1e-3))


def _imu(n: int = 400, seed: int = 2) -> ImuBuffer:
    """A slewing IMU (rates up to ~0.6 rad/s, so a sample turns by up to 6 mrad)."""
    rng = np.random.default_rng(seed)
    t = np.arange(1, n + 1) * DT
    w = np.stack([0.5 * np.sin(2.0 * t), 0.3 * np.cos(1.3 * t), 0.2 + 0.1 * t], axis=1)
    w += rng.normal(0.0, 1e-3, w.shape)
    f = np.stack([0.5 * np.cos(t), 0.4 * np.sin(0.7 * t), 9.8 + 0.2 * np.sin(3 * t)], axis=1)
    buf = ImuBuffer(DT)
    buf.append(t, w, f)
    return buf


def _theta(P: int, seed: int = 4) -> np.ndarray:
    rng = np.random.default_rng(seed)
    th = np.zeros(P)
    th[0:3] = rng.normal(0.0, 1e-3, 3)  # gyro bias, rad/s
    th[3:12] = rng.normal(0.0, 1e-3, 9)  # gyro error matrix
    if P > 12:
        th[12:15] = rng.normal(0.0, 1e-2, 3)  # accel bias, m/s²
        th[15:24] = rng.normal(0.0, 1e-3, 9)
    return th


def _propagation(accel: bool, exact: bool, **kw) -> ImuPropagation:
    P = 24 if accel else 12
    return ImuPropagation(DT, _sensor(0, P), _sensor(12, P) if accel else None,
                          (lambda t: np.broadcast_to(G, (len(t), 3))) if accel else None,
                          exact=exact, **kw)


def _run(prop, imu, theta, ta=0.503, tb=2.4567):
    R_a = so3_exp([0.1, 0.2, -0.3])
    if not prop.exact:
        prop.appended(imu, 0, theta)
    k, m = imu.index(ta), imu.index(tb)
    st = prop.step(imu, k, m, ta, tb, R_a, theta)
    v = r = None
    if st.dvr is not None:
        v = st.dvr[0] + st.gravity[0]
        r = st.dvr[1] + st.gravity[1]
    return st, v, r


@pytest.mark.parametrize("accel", [False, True], ids=["attitude", "velocity"])
def test_jacobians_match_finite_differences(accel):
    """F (attitude, velocity, position errors per parameter) = central differences of the
    per-sample strapdown.  Attitude rows: second order in a sample's rotation (≤ 6 mrad
    here), within 1e-4 of each column, where the samples' end attitude would be off by
    ~ω Δt / 2 ≈ 3e-3.  Velocity and position rows: first order (each sample's start
    attitude, see core/propagation.py), within 3e-2 of the column here (2.1e-2 measured;
    the same as ω Δt on a ship's sway is 1e-4)."""
    imu = _imu()
    P = 24 if accel else 12
    theta = _theta(P)
    st, v0, r0 = _run(_propagation(accel, exact=True), imu, theta)
    h = 1e-6
    for p in range(P):
        e = np.zeros(P)
        e[p] = h
        sp, vp, rp = _run(_propagation(accel, exact=True), imu, theta + e)
        sm, vm, rm = _run(_propagation(accel, exact=True), imu, theta - e)
        fd = [(so3_log(sp.R @ st.R.T) - so3_log(sm.R @ st.R.T)) / (2 * h)]
        if accel:
            fd += [(vp - vm) / (2 * h), (rp - rm) / (2 * h)]
        for q, col in enumerate(fd):
            scale = np.abs(col).max() + 1e-12
            err = np.abs(st.F[q, :, p] - col).max() / scale
            assert err < (1e-4 if q == 0 else 3e-2), (p, q, err)


@pytest.mark.parametrize("accel", [False, True], ids=["attitude", "velocity"])
def test_first_order_path_matches_per_sample(accel):
    """A reference built under θ₀ serves θ₀ + δ with first-order corrections: the nominal
    state differs from the per-sample propagation under θ₀ + δ by second order only."""
    imu = _imu()
    P = 24 if accel else 12
    theta0 = _theta(P)
    delta = _theta(P, seed=9) * 1e-2
    fast = _propagation(accel, exact=False, max_correction_rad=1.0)
    fast.appended(imu, 0, theta0)
    st_f, v_f, r_f = _run(fast, imu, theta0 + delta)
    assert fast.rebuilds == 0 and np.array_equal(fast.theta_ref, theta0)
    st_x, v_x, r_x = _run(_propagation(accel, exact=True), imu, theta0 + delta)
    st_0, v_0, _ = _run(_propagation(accel, exact=True), imu, theta0)
    first = np.linalg.norm(so3_log(st_x.R @ st_0.R.T))
    second = np.linalg.norm(so3_log(st_f.R @ st_x.R.T))
    assert first > 1e-6 and second < 1e-3 * first, (first, second)
    if accel:
        # the velocity's parameter columns are first order in a sample's rotation
        assert np.abs(v_f - v_x).max() < 3e-2 * np.abs(v_x - v_0).max()
    # a correction above the threshold rebuilds the reference under the current θ
    tight = _propagation(accel, exact=False, max_correction_rad=1e-9)
    tight.appended(imu, 0, theta0)
    st_t, _, _ = _run(tight, imu, theta0 + delta)
    assert tight.rebuilds == 1 and np.array_equal(tight.theta_ref, theta0 + delta)
    assert np.linalg.norm(so3_log(st_t.R @ st_x.R.T)) < 1e-12


def test_reference_rows_independent_of_batching_with_accelerometer():
    """The rows (attitude, rate, increments, specific force, sculling, gravitation) are the
    same bit for bit whether the samples come in one batch or one at a time."""
    imu = _imu(600)
    b, A = np.array([1e-3, -2e-3, 5e-4]), np.eye(3) + 1e-3
    accel = (np.array([0.01, 0.0, -0.02]), None)

    def gravity(t):
        return np.stack([np.sin(t), np.cos(t), -9.8 + 0 * t], axis=1)

    one = ImuPrefix(DT, b, A, accel=accel, gravity=gravity)
    one.extend(imu.t, imu.w, imu.f)
    many = ImuPrefix(DT, b, A, accel=accel, gravity=gravity)
    rng = np.random.default_rng(1)
    i = 0
    while i < len(imu):
        k = int(rng.integers(1, 5)) if rng.random() < 0.8 else int(rng.integers(5, 90))
        many.extend(imu.t[i:i + k], imu.w[i:i + k], imu.f[i:i + k])
        i += k
    for key in ("tp", "C", "w_hat", "phi", "slope", "f_hat", "du", "gdt"):
        assert np.array_equal(getattr(one, key), getattr(many, key)), key
    restored = ImuPrefix(DT, np.zeros(3), accel=(np.zeros(3), None), gravity=gravity)
    restored.load_state(many.state())
    for p in (one, restored):
        p.extend(imu.t[-1] + DT * np.arange(1, 4), imu.w[:3], imu.f[:3])
    for key in ("C", "slope", "du", "gdt"):
        assert np.array_equal(getattr(one, key), getattr(restored, key)), key


@pytest.mark.parametrize("accel", [False, True])
def test_compiled_prefix_rows_are_the_numpy_rows(monkeypatch, accel):
    """The per-sample rows (``core.jit.prefix_sample_rows``: rates, coning, slopes, and the
    accelerometer's corrected force and sculled increments), the block scan and the
    attitude matrices compiled (``quat_block_scan``, ``anchored_matrices``) store the numpy
    path's rows bit for bit, whatever the pieces; with an accelerometer also a sample that
    turns by more than 1e-2 rad (``du`` from the closed forms), a reference that starts
    after a sample (``start``) and no accelerometer matrix."""
    from stellar_cal_ros.core import imu_prefix

    if not imu_prefix.HAVE_NUMBA:
        pytest.skip("numba not importable: the numpy path is the only one")
    imu = _imu(6000, seed=7)
    w = imu.w.copy()
    w[3000] = [2.0, -1.5, 0.5]  # 2.5 rad/s: a 0.025 rad increment
    b, A = np.array([1e-3, -2e-3, 5e-4]), np.eye(3) + 1e-3
    rng = np.random.default_rng(3)
    cuts = np.cumsum(rng.integers(1, 700, 40))
    cuts = [0, *cuts[cuts < len(imu)].tolist(), len(imu)]
    opts = {}
    if accel:
        def gravity(t):
            return np.stack([1e-3 * np.sin(t), 2e-3 * np.cos(t), -9.8 + 0 * t], axis=1)

        start = (0.0, np.array([1e-4, -2e-4, 3e-4]), np.array([1e-3, 2e-3, 0.098]),
                 np.array([0.01, -0.02, 0.03]), DT)
        opts = {"accel": (np.array([0.01, -0.02, 0.03]), None), "gravity": gravity,
                "start": start}

    def rows(compiled: bool) -> ImuPrefix:
        monkeypatch.setattr(imu_prefix, "HAVE_NUMBA", compiled)
        pre = ImuPrefix(DT, b, A, **opts)
        for a, e in zip(cuts[:-1], cuts[1:], strict=True):
            pre.extend(imu.t[a:e], w[a:e], imu.f[a:e] if accel else None)
        return pre

    one, ref = rows(True), rows(False)
    keys = ["tp", "C", "w_hat", "phi", "slope", "anchor", "block_dq", "dtheta_last",
            "w_last", "dt_last"]
    if accel:
        keys += ["f_hat", "du", "gdt", "dv_last"]
        assert np.linalg.norm(ref.phi, axis=1).max() > 1e-2  # the closed forms are taken
    for key in keys:
        assert np.array_equal(getattr(one, key), getattr(ref, key)), key
    assert one._lv == ref._lv


def test_in_sample_attitude_matches_the_truth_to_second_order():
    """A star stamp falls inside an IMU sample (the swaying scenario's 37 % into a 100 Hz
    sample).  From noise-free samples (the simulator's interval means of the true rate),
    :meth:`ImuPrefix.at` gives the rotation from the sample's start to the stamp within
    0.002" of the simulator's truth; the sample's increment split linearly in time (the held
    mean rate) errs by ω̇ Δt² a (1 − a) / 2, ~0.1" RMS here.  The compiled frame step's
    ``_at`` computes the same attitude."""
    from stellar_cal_ros.core.units import ARCSEC
    from stellar_cal_ros.methods.frame_step import _at
    from stellar_cal_ros.sim.scenarios import get_scenario
    from stellar_cal_ros.sim.truth_effects import merged_effects
    from stellar_cal_ros.sim.world import TruthWorld

    sc = get_scenario("swaying")
    world = TruthWorld(sc, 12.0, merged_effects(sc.effects, None))
    t_end = np.arange(1, 1201) * DT
    pre = ImuPrefix(DT, np.zeros(3))
    pre.extend(t_end, world.interval_means(t_end, DT, world.omega_ib_b))
    stamps = sc.star_phase_s + np.arange(1.0, 11.0, 0.25)
    rows = np.searchsorted(pre.tp, stamps) - 1
    a = (stamps - pre.tp[rows]) / DT
    assert np.all((a > 0.3) & (a < 0.7))
    R_start, R_true = world.R_i_b(pre.tp[rows]), world.R_i_b(stamps)
    err_at, err_linear = [], []
    for i, (m, t) in enumerate(zip(rows.tolist(), stamps.tolist(), strict=True)):
        truth = R_start[i].T @ R_true[i]
        C = pre.at(m, t)
        np.testing.assert_allclose(_at(pre.tp, pre.C, pre.phi, pre.slope, m, t), C,
                                   rtol=0, atol=1e-14)
        err_at.append(so3_log((pre.C[m].T @ C).T @ truth))
        err_linear.append(so3_log(so3_exp(a[i] * pre.phi[m]).T @ truth))
    err_at = np.linalg.norm(err_at, axis=1) / ARCSEC
    err_linear = np.linalg.norm(err_linear, axis=1) / ARCSEC
    assert np.sqrt(np.mean(err_linear ** 2)) > 0.05, err_linear
    assert err_at.max() < 0.002, err_at


class _Uncapped(ImuPropagation):
    """The propagation as it was: each reference extended over every sample held."""

    def _extend(self, imu, a: int, b: int) -> None:
        if b > a:
            self.prefix.extend(imu.t[a:b], imu.w[a:b],
                               imu.f[a:b] if self.accel is not None else None)


@pytest.mark.parametrize("window_s", [2.0, 1.51])
@pytest.mark.parametrize("accel", [False, True], ids=["attitude", "velocity"])
def test_reference_rows_stop_at_the_window_and_the_steps_are_unchanged(accel, window_s):
    """A reference's rows stop at the end of its window (a later sample is computed by the
    next reference, not twice), and every step is the same floats as with the rows of every
    sample held: IMU 1.5 s ahead of the frames, 2-s windows (each rebuild by the window) and
    a θ̂ changing at every frame with a tight bound (rebuilds by the correction too); and
    1.51-s windows, where a step reaches the window's last sample (reviewer RF)."""
    src = _imu(1200)
    P = 24 if accel else 12
    theta = _theta(P)
    bufs = {c: ImuBuffer(DT) for c in (ImuPropagation, _Uncapped)}
    props = {c: c(DT, _sensor(0, P), _sensor(12, P) if accel else None,
                  (lambda t: np.broadcast_to(G, (len(t), 3))) if accel else None,
                  max_correction_rad=2e-6, window_s=window_s) for c in bufs}
    rows = dict.fromkeys(bufs, 0)
    R = dict.fromkeys(bufs, so3_exp([0.1, 0.2, -0.3]))
    held, ta = 0, 0.013
    for q in range(18):
        tb = 0.5 * (q + 1) + 0.0037
        upto = min(int(round((tb + 1.5) / DT)), len(src))
        for c, buf in bufs.items():
            if upto > held:
                n0 = len(buf)
                buf.append(src.t[held:upto], src.w[held:upto], src.f[held:upto])
                before = props[c].prefix.n if props[c].prefix is not None else 0
                props[c].appended(buf, n0, theta)
                rows[c] += props[c].prefix.n - before
        held = max(held, upto)
        steps = []
        for c, buf in bufs.items():
            prop = props[c]
            start = prop.prefix
            st = prop.step(buf, buf.index(ta), buf.index(tb), ta, tb, R[c], theta)
            if prop.prefix is not start:  # rebuilt: its rows counted from its start
                rows[c] += prop.prefix.n
            R[c] = st.R
            steps.append(st)
        a, b = steps
        for key in ("R", "F", "dvr", "gravity"):
            assert np.array_equal(getattr(a, key), getattr(b, key)), (q, key)
        capped = props[ImuPropagation]
        assert capped.prefix.end <= capped.ref_start + capped.window
        ta = tb
        theta = theta + 1e-3 * _theta(P, seed=q)
    assert props[ImuPropagation].rebuilds > 0 and \
        props[ImuPropagation].rebuilds == props[_Uncapped].rebuilds
    assert rows[ImuPropagation] < rows[_Uncapped]
