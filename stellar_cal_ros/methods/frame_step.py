"""One compiled call per star frame (numba): propagation, update, statistics.

Propagation, prediction, gate, iterated update, sensitivity, injection and the frame's
terms of the running statistics.

:meth:`~stellar_cal_ros.methods.kernel.StarFilter.update` takes this path when the frame is
an ordinary one — the model has a compiled star chain
(:mod:`~stellar_cal_ros.methods.star_chain`), the method propagates with the kernel's
attitude transition (:meth:`StarFilter._transition`: attitude rows driven by θ, random
walks; PSCE), no IMU sample of the interval is bridged and no re-acquisition is pending —
and :func:`frame_step` computes, in one call, what the numpy path computes in
:class:`~stellar_cal_ros.core.propagation.ImuPropagation`, :class:`~stellar_cal_ros.core.
state.ErrorState`, :class:`~stellar_cal_ros.core.gating.GatePolicy`,
:func:`~stellar_cal_ros.core.covariance.iterated_update` and
:meth:`~stellar_cal_ros.methods.results.RunStats.add`: the same formulas, in loops.  The
numpy path stays the reference (``StarFilter.compiled_step = False``);
``test/test_compiled_step.py`` holds the two to a fraction of the posterior σ.

Whatever needs Python — a reference strapdown to rebuild, too few stars (the re-acquisition
logic), a failed update (its log line) — comes back as a status before or after the
propagation, and the kernel goes on from there with the state as the numpy path leaves it.

The swaying-base filter (velocity and position driven by the accelerometer, its own
transition and position reference) takes no fused step; its parts are compiled one by one
and called from its numpy path: :func:`swaying_propagate` (the interval's strapdown sums
and its transition), :func:`reference_update` (the position reference) and
:func:`star_update` (the star update), each held to the numpy reference by
``test/test_compiled_step.py``.
"""

from __future__ import annotations

import importlib
import json
import math
import sys
from pathlib import Path
from typing import TextIO

import numpy as np

from stellar_cal_ros.core.covariance import augment, common_columns, joint_correction
from stellar_cal_ros.core.imu_prefix import in_sample_rotvec
from stellar_cal_ros.core.jit import (
    HAVE_NUMBA,
    cholesky_solve,
    joseph,
    kalman_gain_factor,
    mat3_mul,
    njit,
    so3_exp1,
    star_blocks,
)
from stellar_cal_ros.methods.star_chain import predict_chain

#: statuses of :func:`frame_step`
UPDATED, REBUILD, FEW_STARS, BAD_GAIN, BAD_RELINEARIZATION, NON_FINITE = 0, 1, 2, 3, 4, 5
#: the numpy path's words for the failures
REASONS = {BAD_GAIN: "innovation covariance not positive definite",
           BAD_RELINEARIZATION: "relinearization left the field of view",
           NON_FINITE: "non-finite update"}
#: median of χ² with 2 degrees of freedom (core.gating.CHI2_2_MEDIAN)
_CHI2_2_MEDIAN = 2.0 * math.log(2.0)
#: config vector of :func:`frame_step` (see StarFilter._frame_config)
CONFIG_FIELDS = ("threshold", "scale_by_frame", "mismatch_factor", "lost_lock_factor",
                 "fov_tan2", "min_stars", "max_iterations", "iteration_tolerance",
                 "relinearize_rad", "relinearize_sigma", "max_correction_rad", "nis_cap",
                 "stamp_sigma", "frame_sigma")


@njit(cache=True)
def _mat3_mul_t(a, b):
    """``a @ bᵀ`` of two (3, 3) matrices."""
    out = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            out[i, j] = a[i, 0] * b[j, 0] + a[i, 1] * b[j, 1] + a[i, 2] * b[j, 2]
    return out


_in_sample_rotvec = njit(cache=True)(in_sample_rotvec)
_augment = njit(cache=True)(augment)
_joint_correction = njit(cache=True)(joint_correction)
_common_columns = njit(cache=True)(common_columns)


@njit(cache=True)
def _at(tp, C, phi, slope, m, t):
    """:meth:`ImuPrefix.at`: ``C(t)`` in row ``m`` (the same in-sample rotation)."""
    a = (t - tp[m]) / (tp[m + 1] - tp[m])
    if a > 0.0:
        return mat3_mul(C[m], so3_exp1(_in_sample_rotvec(a, phi[m], slope[m])))
    return C[m].copy()


@njit(cache=True)
def attitude_interval(tp, C, w_hat, phi, slope, j, mj, ta, tb, R_a, Gamma, delta, max_rad):
    """The attitude-only :meth:`ImuPropagation._interval` (rows ``j..mj`` of the reference).

    Returns ``(ok, R_b (3, 3), F (3, P))``; ``ok`` False when the first-order correction
    exceeds ``max_rad`` (the reference is to be rebuilt; nothing else computed).
    """
    n = mj - j + 1
    Ca = _at(tp, C, phi, slope, j, ta)
    Cb = _at(tp, C, phi, slope, mj, tb)
    Q = _mat3_mul_t(R_a, Ca)
    K = Gamma.shape[0]
    Z = np.zeros((3, K))
    prev = ta
    for i in range(n):
        r = j + i
        end = tb if i == n - 1 else tp[r + 1]
        hw = 0.5 * (end - prev)
        prev = end
        Cs = Ca if i == 0 else C[r]
        Ce = Cb if i == n - 1 else C[r + 1]
        for a in range(3):
            for b in range(3):
                cm = (Cs[a, b] + Ce[a, b]) * hw
                Z[a, b] += cm
                if K > 3:
                    for c in range(3):
                        Z[a, 3 + 3 * b + c] += cm * w_hat[r, c]
    F = Q @ (Z @ Gamma)
    corr = F @ delta
    if corr[0] * corr[0] + corr[1] * corr[1] + corr[2] * corr[2] > max_rad * max_rad:
        return False, np.eye(3), F
    return True, mat3_mul(so3_exp1(corr), mat3_mul(Q, Cb)), F


@njit(cache=True)
def swaying_interval(tp, C, w_hat, phi, slope, f_hat, du, gdt, j, mj, ta, tb, R_a, Gg, Ga,
                     delta, max_rad):
    """:meth:`ImuPropagation._interval` with an accelerometer (rows ``j..mj``), in loops.

    Returns ``(ok, R_b (3, 3), F (3, 3, P), dvr (2, 3), gravity (2, 3))``; ``ok`` False when
    the first-order attitude correction exceeds ``max_rad`` (the reference is to be rebuilt).
    The same sums as the numpy path: ``DG``, the tail sums ``Y``, ``Zg``, ``Za`` and their
    weighted sums, accumulated per sample.
    """
    n = mj - j + 1
    P = Gg.shape[1]
    Kg, Ka = Gg.shape[0], Ga.shape[0]
    Ca = _at(tp, C, phi, slope, j, ta)
    Cb = _at(tp, C, phi, slope, mj, tb)
    Q = _mat3_mul_t(R_a, Ca)
    dts = np.empty(n)
    W1 = np.empty(n)  # trapezoid weight of δv in δr
    frac = np.empty(n)
    prev = ta
    for i in range(n):
        r = j + i
        end = tb if i == n - 1 else tp[r + 1]
        dts[i] = end - prev
        prev = end
        W1[i] = (tb - end) + 0.5 * dts[i]
        frac[i] = dts[i] / (tp[r + 1] - tp[r])
    # specific-force and gravitation increments in the reference frame, their sums
    D = np.empty((n, 3))
    sums = np.zeros((2, 6))
    for i in range(n):
        r = j + i
        Cs = Ca if i == 0 else C[r]
        for a in range(3):
            D[i, a] = (Cs[a, 0] * du[r, 0] + Cs[a, 1] * du[r, 1] + Cs[a, 2] * du[r, 2]) \
                * frac[i]
            g = gdt[r, a] * frac[i]
            sums[0, a] += D[i, a]
            sums[1, a] += W1[i] * D[i, a]
            sums[0, 3 + a] += g
            sums[1, 3 + a] += W1[i] * g
    # tails[w, i] = Σ_{l>i} W_w,l D_l (as total − running sum, the numpy path's form)
    tails = np.empty((2, n, 3))
    for w in range(2):
        for a in range(3):
            tot = 0.0
            for i in range(n):
                tot += (1.0 if w == 0 else W1[i]) * D[i, a]
            run = 0.0
            for i in range(n):
                run += (1.0 if w == 0 else W1[i]) * D[i, a]
                tails[w, i, a] = tot - run
    YZ0 = np.zeros((3, Kg))  # Σ Zg
    Tx = np.zeros((2, 3, 3, Kg))  # Σ tails[w, i, c] Zg_i[a, k]
    Zas = np.zeros((2, 3, Ka))  # Σ W_w Za
    zg = np.empty((3, Kg))
    za = np.empty((3, Ka))
    for i in range(n):
        r = j + i
        Cs = Ca if i == 0 else C[r]
        Ce = Cb if i == n - 1 else C[r + 1]
        hw = 0.5 * dts[i]
        for a in range(3):
            for b in range(3):
                cm = (Ce[a, b] + Cs[a, b]) * hw
                zg[a, b] = cm
                if Kg > 3:
                    for c in range(3):
                        zg[a, 3 + 3 * b + c] = cm * w_hat[r, c]
                cs = Cs[a, b] * dts[i]
                za[a, b] = cs
                if Ka > 3:
                    for c in range(3):
                        za[a, 3 + 3 * b + c] = cs * f_hat[r, c]
        for a in range(3):
            for k in range(Kg):
                z = zg[a, k]
                YZ0[a, k] += z
                for w in range(2):
                    for c in range(3):
                        Tx[w, c, a, k] += tails[w, i, c] * z
            for k in range(Ka):
                Zas[0, a, k] += za[a, k]
                Zas[1, a, k] += W1[i] * za[a, k]
    Xc = np.empty((2, 3, Kg))
    for w in range(2):
        for k in range(Kg):
            Xc[w, 0, k] = Tx[w, 1, 2, k] - Tx[w, 2, 1, k]
            Xc[w, 1, k] = Tx[w, 2, 0, k] - Tx[w, 0, 2, k]
            Xc[w, 2, k] = Tx[w, 0, 1, k] - Tx[w, 1, 0, k]
    F = np.empty((3, 3, P))
    F[0] = Q @ (YZ0 @ Gg)
    for w in range(2):
        F[1 + w] = Q @ (Zas[w] @ Ga - Xc[w] @ Gg)
    corr = np.zeros((3, 3))
    for s in range(3):
        for a in range(3):
            acc = 0.0
            for p in range(P):
                acc += F[s, a, p] * delta[p]
            corr[s, a] = acc
    if corr[0, 0] ** 2 + corr[0, 1] ** 2 + corr[0, 2] ** 2 > max_rad * max_rad:
        return False, np.eye(3), F, np.zeros((2, 3)), np.zeros((2, 3))
    dvr = np.empty((2, 3))
    grav = np.empty((2, 3))
    for w in range(2):
        for a in range(3):
            dvr[w, a] = (Q[a, 0] * sums[w, 0] + Q[a, 1] * sums[w, 1] + Q[a, 2] * sums[w, 2]) \
                + corr[1 + w, a]
            grav[w, a] = sums[w, 3 + a]
    c0 = np.empty(3)
    c0[:] = corr[0]
    R_b = mat3_mul(so3_exp1(c0), mat3_mul(Q, Cb))
    return True, R_b, F, dvr, grav


@njit(cache=True)
def swaying_propagate(tp, C, w_hat, phi, slope, f_hat, du, gdt, j, mj, ta, tb, R_a, Gg, Ga,
                      delta, max_rad, P, M, Pe, inv_tau, qd_index, qd, vel, pos):
    """The swaying-base filter's propagation over one interval in one call.

    :func:`swaying_interval`, then :meth:`SwayingFilter._transition`: Φ (the parameter
    columns of the attitude, velocity and position rows, ``−[Δv]×``, ``T I``, the
    Gauss–Markov decay), ``P ← Φ P Φᵀ + Q_d`` symmetrized (``qd`` (5, q): ``q1, q2, q3,
    gm2, itau2`` on the flat entries ``qd_index``), ``M ← Φ M + F_β`` and the nominal
    velocity and position.  Returns ``(ok, R_b, P, M, vel, pos)``; with ``ok`` False
    nothing is computed beyond the interval (the reference is to be rebuilt).
    """
    ok, R_b, F, dvr, grav = swaying_interval(tp, C, w_hat, phi, slope, f_hat, du, gdt, j,
                                             mj, ta, tb, R_a, Gg, Ga, delta, max_rad)
    if not ok:
        return False, R_b, P, M, vel, pos
    T = tb - ta
    N = P.shape[0]
    iv = 3 + Pe
    ir = iv + 3
    Phi = np.eye(N)
    nc = F.shape[2] - Pe
    for s in range(3):
        for a in range(3):
            row = a if s == 0 else iv + 3 * (s - 1) + a
            for p in range(Pe):
                Phi[row, 3 + p] = F[s, a, p]
    for p in range(Pe):
        Phi[3 + p, 3 + p] = math.exp(-T * inv_tau[p])
    for w in range(2):
        x, y, z = dvr[w, 0], dvr[w, 1], dvr[w, 2]
        r0 = iv + 3 * w
        Phi[r0, 0], Phi[r0, 1], Phi[r0, 2] = -0.0, z, -y
        Phi[r0 + 1, 0], Phi[r0 + 1, 1], Phi[r0 + 1, 2] = -z, -0.0, x
        Phi[r0 + 2, 0], Phi[r0 + 2, 1], Phi[r0 + 2, 2] = y, -x, -0.0
    for a in range(3):
        Phi[ir + a, iv + a] = T
    pos_n = pos + vel * T + dvr[1] + grav[1]
    vel_n = vel + dvr[0] + grav[0]
    Pn = Phi @ P @ Phi.T
    for e in range(len(qd_index)):
        i = qd_index[e]
        q = (qd[0, e] + (qd[1, e] + qd[2, e] * T) * T) * T \
            + qd[3, e] * -math.expm1(-T * qd[4, e])
        Pn[i // N, i % N] += q
    Ps = 0.5 * (Pn + Pn.T)
    if M.shape[1] == 0:
        return True, R_b, Ps, M, vel_n, pos_n
    Mn = Phi @ M
    if nc:
        for s in range(3):
            for a in range(3):
                row = a if s == 0 else iv + 3 * (s - 1) + a
                for c in range(nc):
                    Mn[row, c] += F[s, a, Pe + c]
    return True, R_b, Ps, Mn, vel_n, pos_n


@njit(cache=True)
def reference_update(P, M, score, info, accumulate, H, nu, R):
    """A linear update with a full R and the attitude's reset, in one call.

    :meth:`~stellar_cal_ros.core.state.ErrorState.linear_update` (``dx``, Joseph ``P``, the
    NIS; the sensitivity's update with no consider column in ``H``, its score and
    information when ``accumulate``) followed by the covariance part of
    :meth:`~stellar_cal_ros.core.state.ErrorState.inject` for an attitude block in rows
    0:3 (``G = I + ½[δφ]×`` on P's rows and columns and M's rows, P symmetrized).  The
    same formulas as the numpy path (the swaying filter's position reference).  Returns
    ``(dx, nis, P, M)``; ``score`` and ``info`` are changed in place.
    """
    N = P.shape[0]
    m = H.shape[0]
    HP = H @ P
    S = HP @ H.T + R
    rhs = np.empty((m, N + 1))
    rhs[:, :N] = HP
    rhs[:, N] = nu
    X = np.linalg.solve(S, rhs)
    K = np.ascontiguousarray(X[:, :N].T)
    nis = 0.0
    for a in range(m):
        nis += nu[a] * X[a, N]
    A = np.eye(N) - K @ H
    Pn = A @ P @ A.T + K @ R @ K.T
    Pn = 0.5 * (Pn + Pn.T)
    dx = K @ nu
    nc = M.shape[1]
    if nc:
        Am = H @ M
        if accumulate:
            rhs2 = np.empty((m, nc + 1))
            rhs2[:, :nc] = Am
            rhs2[:, nc] = nu
            X2 = np.linalg.solve(S, rhs2)
            AT = np.ascontiguousarray(Am.T)
            score += AT @ np.ascontiguousarray(X2[:, nc])
            info += AT @ np.ascontiguousarray(X2[:, :nc])
        M = M - K @ Am
    x, y, z = 0.5 * dx[0], 0.5 * dx[1], 0.5 * dx[2]
    G = np.array([[1.0, -z, y], [z, 1.0, -x], [-y, x, 1.0]])
    Pn[0:3, :] = G @ np.ascontiguousarray(Pn[0:3, :])
    Pn[:, 0:3] = np.ascontiguousarray(Pn[:, 0:3]) @ G.T
    Pn = 0.5 * (Pn + Pn.T)
    if nc:
        M[0:3] = G @ np.ascontiguousarray(M[0:3])
    return dx, nis, Pn, M


@njit(cache=True)
def swaying_frame(tp, C, w_hat, phi, slope, f_hat, du_a, gdt, j, mj, ta, tb, R_a, Gg, Ga,
                  delta, max_rad, P, M, Pe, inv_tau, qd_index, qd, vel, pos,
                  due, site_pos, R_ref, score, info, accumulate,
                  gyro_b0, gyro_Jb, gyro_theta0, w_raw, theta,
                  uv, u, sigma, base, s0, g, timed, R_prior, T, tracked, c, B, need, dcol,
                  dfix, dgrp, cam, du, bscale, cfg):
    """A swaying-base frame in one call: propagation, position reference when due, star update.

    :func:`swaying_propagate` from ``ta`` to ``tb``; with ``due`` the position reference
    (``nu = site_pos − pos``, ``H`` the position rows, ``R_ref``) by :func:`reference_update`
    and its nominal box-plus (the attitude ``Exp(δφ) R``, θ̂'s first ``Pe`` entries, the
    velocity and position: ``ErrorState.boxplus``); the corrected rate of the sample at
    ``tb`` (the gyro's affine bias at θ̂, no error matrix: ``SensorModel._no_E``); then
    :func:`star_update` in place.  The navigation blocks' part of the star update's ``dx``
    is the caller's (as :func:`star_update`'s).  ``theta``, ``score``, ``info`` are changed
    in place (not after ``REBUILD``, when nothing is).

    Returns ``(status, ints, floats, accepted, uv_pred, S, nis_stars, directions, omega,
    R_prior, R, P, M, vel, pos, nu, nis_ref, dx)`` (``R_prior`` the propagated attitude
    before the reference; ``nu``, ``nis_ref`` the reference's, NaN when not due).
    """
    ints = np.zeros(6, dtype=np.int64)
    floats = np.zeros(13)
    floats[0] = np.nan
    nu = np.full(3, np.nan)
    nis_ref = np.nan
    ok, R_b, P, M, vel, pos = swaying_propagate(tp, C, w_hat, phi, slope, f_hat, du_a, gdt,
                                                j, mj, ta, tb, R_a, Gg, Ga, delta, max_rad,
                                                P, M, Pe, inv_tau, qd_index, qd, vel, pos)
    if not ok:
        return (REBUILD, ints, floats, np.zeros(0, dtype=np.bool_), np.zeros((0, 2)),
                np.zeros((0, 2, 2)), np.zeros(0), np.zeros((0, 3)), np.zeros(3), R_b,
                R_b, P, M, vel, pos, nu, nis_ref, np.zeros(P.shape[0]))
    R_prior_out = R_b.copy()
    R = R_b.copy()
    N = P.shape[0]
    if due:
        ir = 6 + Pe
        H = np.zeros((3, N))
        for a in range(3):
            H[a, ir + a] = 1.0
            nu[a] = site_pos[a] - pos[a]
        dxr, nis_ref, P, M = reference_update(P, M, score, info, accumulate, H, nu, R_ref)
        R = mat3_mul(so3_exp1(dxr[0:3]), R_b)
        for p in range(Pe):
            theta[p] += dxr[3 + p]
        iv = 3 + Pe
        vel = vel + dxr[iv:iv + 3]
        pos = pos + dxr[ir:ir + 3]
    P = np.ascontiguousarray(P)
    M = np.ascontiguousarray(M)
    omega = w_raw - (gyro_b0 + gyro_Jb @ (theta - gyro_theta0))
    status, accepted, uv_pred, S_blocks, nis_stars, dirs, dx = star_update(
        P, theta, R, M, score, info, accumulate, omega, uv, u, sigma, base, s0, g, timed,
        R_prior, T, tracked, c, B, need, dcol, dfix, dgrp, cam, du, bscale, Pe, cfg, ints,
        floats)
    return (status, ints, floats, accepted, uv_pred, S_blocks, nis_stars, dirs, omega,
            R_prior_out, R, P, M, vel, pos, nu, nis_ref, dx)


@njit(cache=True)
def _batch_outputs(K, n_all, P, theta, M):
    """The outputs a batch of ``K`` frames fills (:func:`frame_steps`, :func:`swaying_frames`).

    Status, ints, floats; the stars rows' accepted, uv_pred, S, nis, directions; per frame
    omega, R_prior, P, theta, R, M, score, info.
    """
    N = P.shape[0]
    mc = M.shape[1]
    return (np.full(K, -1, dtype=np.int64), np.zeros((K, 6), dtype=np.int64),
            np.zeros((K, 13)), np.zeros(n_all, dtype=np.bool_), np.zeros((n_all, 2)),
            np.zeros((n_all, 2, 2)), np.zeros(n_all), np.zeros((n_all, 3)), np.zeros((K, 3)),
            np.zeros((K, 3, 3)), np.empty((K, N, N)), np.empty((K, theta.shape[0])),
            np.empty((K, 3, 3)), np.empty((K, N, mc)), np.empty((K, mc)),
            np.empty((K, mc, mc)))


@njit(cache=True)
def _keep_frame(out, i, a, b, st, it_, fl, ac, up, Sb, ns, dr, om, rp, P_, th_, R_, M_, sc_,
                in_):
    """Frame ``i``'s results into :func:`_batch_outputs`' arrays ``out``.

    Its stars rows ``a:b`` only when the frame returned one value a row.
    """
    (status, ints, floats, accepted, uv_pred, S, nis, dirs, omega, R_pr, Ps, ths, Rs, Ms, scs,
     ins) = out
    status[i] = st
    ints[i] = it_
    floats[i] = fl
    if ac.shape[0] == b - a:
        accepted[a:b] = ac
        uv_pred[a:b] = up
        S[a:b] = Sb
        nis[a:b] = ns
        dirs[a:b] = dr
    omega[i] = om
    R_pr[i] = rp
    Ps[i] = P_
    ths[i] = th_
    Rs[i] = R_
    Ms[i] = M_
    scs[i] = sc_
    ins[i] = in_


@njit(cache=True)
def swaying_frames(tp, C, w_hat, phi, slope, f_hat, du_a, gdt, js, mjs, tas, tbs, R_a, Gg,
                   Ga, theta_ref, max_rad, P, M, Pe, inv_tau, qd_index, qd, vel, pos,
                   due, site_pos, R_ref, score, info, acc,
                   gyro_b0, gyro_Jb, gyro_theta0, imu_w, ms, theta,
                   uv, u, sigma, offs, base, s0, g, timed, R_prior, T, tracked, c, B, need,
                   dcol, dfix, dgrp, cam, du, bscale, cfg):
    """:func:`swaying_frame` over ``K`` frames in a row, on copies of the state (a batch).

    Frame ``i``'s inputs: rows ``js[i]..mjs[i]``, ``tas[i]``, ``tbs[i]``, ``due[i]`` and
    ``site_pos[i]`` (the position reference), ``acc[i]``, the raw rate ``imu_w[ms[i]]``,
    ``base[i]``, ``bscale[i]``, its stars rows ``offs[i]:offs[i + 1]`` of ``uv, u,
    sigma, du``; ``delta`` is ``θ̂ − theta_ref`` at each frame; the rest as
    :func:`swaying_frame`.  After an ``UPDATED`` frame the
    navigation blocks' part of its ``dx`` is added to the velocity and position (what
    ``StarFilter._compiled_result`` does).  The state arguments are not changed: each
    frame's state after it is returned (as :func:`frame_steps`).  Stops after the first
    frame not ``UPDATED`` and before a ``REBUILD`` (not done).

    Returns ``(done, status, ints, floats, accepted, uv_pred, S, nis_stars, directions,
    omega, R_prior, P, theta, R, M, score, info, vel (K, 3), pos (K, 3), nu (K, 3),
    nis_ref (K,))`` (the first 17 as :func:`frame_steps`'; ``nu``, ``nis_ref`` NaN where
    no reference was due).
    """
    K = js.shape[0]
    n_all = uv.shape[0]
    P_ = P.copy()
    th_ = theta.copy()
    R_ = R_a.copy()
    M_ = M.copy()
    sc_ = score.copy()
    in_ = info.copy()
    v_ = vel.copy()
    r_ = pos.copy()
    out = _batch_outputs(K, n_all, P, theta, M)
    vs = np.empty((K, 3))
    rs = np.empty((K, 3))
    nus = np.full((K, 3), np.nan)
    nis_ref = np.full(K, np.nan)
    done = 0
    iv = 3 + Pe
    ir = iv + 3
    for i in range(K):
        a, b = offs[i], offs[i + 1]
        (st, it_, fl, ac, up, Sb, ns, dr, om, rp, R_n, P_n, M_n, v_n, r_n, nu, nr,
         dx) = swaying_frame(tp, C, w_hat, phi, slope, f_hat, du_a, gdt, js[i], mjs[i],
                             tas[i], tbs[i], R_, Gg, Ga, th_ - theta_ref, max_rad, P_, M_, Pe,
                             inv_tau, qd_index, qd, v_, r_, due[i], site_pos[i], R_ref, sc_,
                             in_, acc[i], gyro_b0, gyro_Jb, gyro_theta0, imu_w[ms[i]], th_,
                             uv[a:b], u[a:b], sigma[a:b], base[i], s0, g, timed, R_prior, T,
                             tracked, c, B, need, dcol, dfix, dgrp, cam, du[a:b], bscale[i],
                             cfg)
        if st == REBUILD:
            break
        P_, M_, R_ = P_n, M_n, R_n
        if st == UPDATED:
            v_ = v_n + dx[iv:iv + 3]
            r_ = r_n + dx[ir:ir + 3]
        else:
            v_, r_ = v_n, r_n
        _keep_frame(out, i, a, b, st, it_, fl, ac, up, Sb, ns, dr, om, rp, P_, th_, R_, M_,
                    sc_, in_)
        vs[i] = v_
        rs[i] = r_
        nus[i] = nu
        nis_ref[i] = nr
        done = i + 1
        if st != UPDATED:
            break
    return (done,) + out + (vs, rs, nus, nis_ref)


@njit(cache=True)
def propagate_coupled(P, M, Pe, F, q_diag):
    """:func:`~stellar_cal_ros.core.covariance.propagate_coupled` of the attitude rows.

    Rows 0:3 (attitude) driven by columns 3:3+Pe (θ), and the sensitivity
    ``M[0:3] += F M[3:3+Pe] + F_β``.
    """
    N = P.shape[0]
    rows, c0, c1 = 3, 3, 3 + Pe
    Fe = np.ascontiguousarray(F[:, :Pe])
    if Pe:
        Pcc = np.ascontiguousarray(P[c0:c1, c0:c1])
        FP = Fe @ Pcc
        Prc = np.ascontiguousarray(P[0:rows, c0:c1])
        Pcr = np.ascontiguousarray(P[c0:c1, 0:rows])
        add = Fe @ Pcr + Prc @ Fe.T + FP @ Fe.T
        cross = Prc + FP
        for a in range(3):
            for b in range(3):
                P[a, b] += add[a, b]
        for a in range(3):
            for k in range(Pe):
                P[a, c0 + k] = cross[a, k]
                P[c0 + k, a] = cross[a, k]
        if c1 < N:  # other columns of the driven rows
            Po = np.ascontiguousarray(P[c0:c1, c1:N])
            addo = Fe @ Po
            for a in range(3):
                for k in range(N - c1):
                    P[a, c1 + k] += addo[a, k]
                    P[c1 + k, a] += addo[a, k]
    for i in range(N):
        P[i, i] += q_diag[i]
    if M.shape[1]:
        Madd = Fe @ np.ascontiguousarray(M[c0:c1]) if Pe else np.zeros((3, M.shape[1]))
        for a in range(3):
            for k in range(M.shape[1]):
                M[a, k] += Madd[a, k] + F[a, Pe + k]


@njit(cache=True)
def gate(nis, d, cfg, accepted):
    """:meth:`~stellar_cal_ros.core.gating.GatePolicy.decide` (fills ``accepted``).

    Returns ``(scale, mismatch, lost_lock, outside)``.
    """
    n = nis.shape[0]
    fin = np.empty(n)
    k = 0
    for i in range(n):
        if math.isfinite(nis[i]):
            fin[k] = nis[i]
            k += 1
    scale = 1.0
    if cfg[1] != 0.0 and k >= 3:
        s = np.sort(fin[:k])
        h = k // 2
        med = s[h] if k % 2 else (s[h - 1] + s[h]) / 2.0
        scale = max(1.0, med / _CHI2_2_MEDIAN)
    thr = cfg[0] * scale
    for i in range(n):
        accepted[i] = nis[i] <= thr
    lost = scale > cfg[3]
    if lost:
        for i in range(n):
            accepted[i] = False
    outside = 0
    fov = cfg[4]
    if math.isfinite(fov):
        for i in range(n):
            z = d[i, 2]
            ok = z > 0 and (d[i, 0] ** 2 + d[i, 1] ** 2) / z ** 2 <= fov
            if not ok:
                outside += 1
                accepted[i] = False
    return scale, scale > cfg[2], lost, outside


@njit(cache=True)
def frame_sums(nu, S, nis, accepted, nis_cap, joint):
    """The frame's terms of :meth:`~stellar_cal_ros.methods.results.RunStats.add` (10,).

    ``[n, Σ log det S, Σ min(NIS, cap), Σ du², Σ dv², Σ S_uu, Σ S_vv, Σ NIS, whitened
    u mean · √n, whitened v mean · √n]`` over the accepted stars; the third plus ``joint``
    (the frame's :func:`~stellar_cal_ros.core.covariance.joint_correction`, 0 without a
    stamp noise).
    """
    out = np.zeros(10)
    n = 0
    w1s = 0.0
    w2s = 0.0
    for i in range(nu.shape[0]):
        if not accepted[i]:
            continue
        n += 1
        a, b, c = S[i, 0, 0], S[i, 0, 1], S[i, 1, 1]
        out[1] += math.log(max(a * c - b * b, 1e-300))
        out[2] += min(nis[i], nis_cap)
        out[3] += nu[i, 0] * nu[i, 0]
        out[4] += nu[i, 1] * nu[i, 1]
        out[5] += a
        out[6] += c
        out[7] += nis[i]
        l11 = math.sqrt(a)
        l21 = b / l11
        l22 = math.sqrt(max(c - l21 * l21, 1e-300))
        w1 = nu[i, 0] / l11
        w1s += w1
        w2s += (nu[i, 1] - l21 * w1) / l22
    out[0] = n
    if n:
        out[8] = w1s / n * math.sqrt(n)
        out[9] = w2s / n * math.sqrt(n)
        out[2] += joint
    return out


@njit(cache=True)
def _assemble(H_att, H_par, Pe, N, rows):
    """``H`` (2·len(rows), N) of the stars ``rows`` ([φ, θ_estimated, 0...])."""
    H = np.zeros((2 * rows.shape[0], N))
    for q in range(rows.shape[0]):
        i = rows[q]
        for r in range(2):
            for b in range(3):
                H[2 * q + r, b] = H_att[i, r, b]
            for k in range(Pe):
                H[2 * q + r, 3 + k] = H_par[i, r, k]
    return H


@njit(cache=True)
def frame_step(P, theta, R_a, M, score, info, accumulate,
               tp, C, w_hat, phi, slope, j, mj, ta, tb, Gamma, theta_ref, q_diag,
               gyro_b0, gyro_E0, gyro_Jb, gyro_JE, gyro_theta0, w_raw,
               uv, u, sigma, base,
               s0, g, timed, R_prior, T, tracked, c, B, need, dcol, dfix, dgrp, cam, du, bscale,
               Pe, cfg):
    """Propagate from ``ta`` to ``tb`` and update with one frame's stars, in place.

    State (changed in place): ``P`` (N, N), ``theta`` (P_all,), ``R_a`` (3, 3) the attitude
    (at ``ta`` on entry, at ``tb`` after), the sensitivity ``M`` (N, m), ``score`` (m,),
    ``info`` (m, m) (``accumulate``: add this frame's terms).  Propagation: the reference
    rows (:class:`~stellar_cal_ros.core.imu_prefix.ImuPrefix` ``tp, C, w_hat, phi, slope``),
    rows ``j..mj``, ``Gamma`` (3 or 12, P_all) and ``theta_ref`` of the reference, ``q_diag``
    (N,) noise per second; ``gyro_*`` the gyro's affine correction and ``w_raw`` (3,) the
    raw rate of the sample covering ``tb``.  Frame: ``uv`` (n, 2), ``u`` (n, 3), ``sigma``
    (n,), ``base`` = stamp − ``tb``.  Chain: the :class:`CompiledChain`, with the frame's
    ``du, bscale`` (:meth:`CompiledChain.frame_inputs`).  ``cfg``:
    :data:`CONFIG_FIELDS`.

    Returns ``(status, ints (6,) [n_acc, iterations, mismatch, lost, outside, 0],
    floats (13,) [nis, scale, frame sums (10), 0], accepted, uv_pred, S, nis_stars,
    directions, omega, R_prior)``; after ``REBUILD`` nothing was changed.
    """
    ints = np.zeros(6, dtype=np.int64)
    floats = np.zeros(13)
    floats[0] = np.nan
    empty_b = np.zeros(0, dtype=np.bool_)
    empty2 = np.zeros((0, 2))
    # ---- propagation
    ok, R_b, F = attitude_interval(tp, C, w_hat, phi, slope, j, mj, ta, tb, R_a, Gamma,
                                   theta - theta_ref, cfg[10])
    if not ok:
        return (REBUILD, ints, floats, empty_b, empty2, np.zeros((0, 2, 2)), np.zeros(0),
                np.zeros((0, 3)), np.zeros(3), np.eye(3))
    propagate_coupled(P, M, Pe, F, q_diag * (tb - ta))
    for a in range(3):
        for b in range(3):
            R_a[a, b] = R_b[a, b]
    R_prior_out = R_b.copy()
    # the corrected rate of the sample at tb (the gyro's affine model at θ)
    d = theta - gyro_theta0
    bg = gyro_b0 + gyro_Jb @ d
    E = gyro_E0 + (gyro_JE @ d).reshape(3, 3)
    x = w_raw - bg
    omega = x.copy()
    if np.any(E != 0.0):
        A = np.linalg.inv(np.eye(3) + E)
        omega = A @ x
    status, accepted, uv_pred, S_blocks, nis_stars, dirs, _ = star_update(
        P, theta, R_a, M, score, info, accumulate, omega, uv, u, sigma, base, s0, g, timed,
        R_prior, T, tracked, c, B, need, dcol, dfix, dgrp, cam, du, bscale, Pe, cfg, ints,
        floats)
    return (status, ints, floats, accepted, uv_pred, S_blocks, nis_stars, dirs, omega,
            R_prior_out)


@njit(cache=True)
def star_update(P, theta, R_a, M, score, info, accumulate, omega, uv, u, sigma, base,
                s0, g, timed, R_prior, T, tracked, c, B, need, dcol, dfix, dgrp, cam, du,
                bscale, Pe, cfg, ints, floats):
    """The star update of :func:`frame_step` at a propagated state, in place.

    ``R_a`` the attitude at the exposure (after the propagation), ``omega`` the corrected
    body rate there; the rest as :func:`frame_step`, whose ``ints`` (6,) and ``floats`` (13,)
    this fills.  Prediction, gate, iterated update of the accepted stars, sensitivity,
    Joseph covariance, injection of the attitude and θ̂ (the first ``Pe`` entries) and the
    attitude's covariance reset; a navigation block's correction is the caller's to inject
    (``dx``, returned: zeros unless ``UPDATED``).  The star update a method with its own
    propagation and measurements (the swaying-base filter) takes after them
    (``StarFilter.compiled_star_update``).

    Returns ``(status, accepted, uv_pred, S, nis_stars, directions, dx)``.
    """
    N = P.shape[0]
    n = uv.shape[0]
    R_b = R_a.copy()
    dx = np.zeros(N)
    # ---- prediction at the prior state
    P_all = theta.shape[0]
    theta0 = theta.copy()
    uv_pred = np.empty((n, 2))
    dirs = np.empty((n, 3))
    H_att = np.empty((n, 2, 3))
    H_par = np.empty((n, 2, P_all))
    R_out = np.empty((2, 3, 3))
    zero3 = np.zeros(3)
    # flags as typed values, not literals: numba would compile predict_chain (and its
    # projection) once more for each literal signature; typed, the caller's one serves
    no, yes, jac = np.bool_(False), np.bool_(True), np.int64(1)
    predict_chain(theta0, u, R_b, zero3, no, omega, base, s0, g, timed, R_prior, T, tracked,
                  c, B, need, dcol, dfix, dgrp, cam, du, bscale, jac, uv_pred, dirs, H_att,
                  H_par, R_out)
    H0 = np.zeros((n, 2, N))
    for i in range(n):
        for r in range(2):
            for b in range(3):
                H0[i, r, b] = H_att[i, r, b]
            for k in range(Pe):
                H0[i, r, 3 + k] = H_par[i, r, k]
    nu0 = uv - uv_pred
    r_meas = sigma * sigma
    # the frame's common noises, error states of unit variance seen through their columns
    # (covariance.iterated_update's common): the stamp's σ_t (cfg[12], s), one δt moving
    # every star by σ_t ∂uv/∂t; a shift σ_f (cfg[13], px per axis) of all its stars
    timing = cfg[12] > 0.0 or cfg[13] > 0.0
    ct = _common_columns(H_att, R_out[0], omega, cfg[12], cfg[13]) if timing else \
        np.zeros((n, 2, 0))
    kc = ct.shape[2]
    if timing:
        H0g = np.zeros((n, 2, N + kc))
        H0g[:, :, :N] = H0
        H0g[:, :, N:] = ct
        S_blocks, nis_stars = star_blocks(H0g, _augment(P, kc), r_meas, nu0)
    else:
        S_blocks, nis_stars = star_blocks(H0, P, r_meas, nu0)
    accepted = np.zeros(n, dtype=np.bool_)
    scale, mismatch, lost, outside = gate(nis_stars, dirs, cfg, accepted)
    floats[1] = scale
    ints[2], ints[3], ints[4] = mismatch, lost, outside
    idx = np.flatnonzero(accepted)
    n_acc = idx.shape[0]
    ints[0] = n_acc
    if n_acc < cfg[5]:
        return FEW_STARS, accepted, uv_pred, S_blocks, nis_stars, dirs, dx
    # ---- iterated update of the accepted stars
    m2 = 2 * n_acc
    z = np.empty(m2)
    h = np.empty(m2)
    rr = np.empty(m2)
    for q in range(n_acc):
        i = idx[q]
        z[2 * q], z[2 * q + 1] = uv[i, 0], uv[i, 1]
        h[2 * q], h[2 * q + 1] = uv_pred[i, 0], uv_pred[i, 1]
        rr[2 * q] = rr[2 * q + 1] = r_meas[i]
    H = _assemble(H_att, H_par, Pe, N, idx)
    cc = np.zeros((m2, kc))
    for q in range(n_acc):
        for j in range(kc):
            cc[2 * q, j], cc[2 * q + 1, j] = ct[idx[q], 0, j], ct[idx[q], 1, j]
    Pg = _augment(P, kc) if timing else P
    u_acc = np.ascontiguousarray(u[idx])
    du_acc = np.ascontiguousarray(du[idx])
    sig_floor = np.empty(N)
    for i in range(N):
        sig_floor[i] = max(math.sqrt(max(P[i, i], 0.0)), 1e-300)
    nu = z - h
    dx = np.zeros(N)
    nis = np.nan
    K = np.zeros((N, m2))
    max_it = int(cfg[6])
    it = 0
    uv_r = np.empty((n_acc, 2))
    d_r = np.empty((n_acc, 3))
    Ha_r = np.empty((n_acc, 2, 3))
    Hp_r = np.empty((n_acc, 2, P_all))
    all_rows = np.arange(n_acc)
    Lf = np.zeros((m2, m2))  # the last gain's Cholesky factor of S (the sensitivity's)
    joint = 0.0  # (frame_sums': the frame's likelihood less its stars', with common noises)
    for it in range(1, max_it + 1):
        if timing:
            Hg = np.empty((m2, N + kc))
            Hg[:, :N] = H
            Hg[:, N:] = cc
            okg, Kg, nis_it, Lf = kalman_gain_factor(Pg, Hg, rr, nu)
            K = np.ascontiguousarray(Kg[:N])
        else:
            okg, K, nis_it, Lf = kalman_gain_factor(P, H, rr, nu)
        if not okg:
            ints[1] = it
            return BAD_GAIN, accepted, uv_pred, S_blocks, nis_stars, dirs, np.zeros(N)
        if it == 1:
            nis = nis_it
            if timing:  # the frame's likelihood (the stars share the stamp's error, the shift)
                ld = 0.0
                for k in range(m2):
                    ld += 2.0 * math.log(Lf[k, k])
                joint = _joint_correction(nis, ld, S_blocks, nis_stars, accepted)
        dx_prev = dx
        dx = K @ (z - h + H @ dx)
        if it == max_it:
            break
        if it == 1:
            small = math.sqrt(dx[0] ** 2 + dx[1] ** 2 + dx[2] ** 2) < cfg[8]
            if small:
                for k in range(3, 3 + Pe):
                    if not abs(dx[k]) < cfg[9] * sig_floor[k]:
                        small = False
                        break
            if small:
                break
        else:
            worst = 0.0
            for k in range(N):
                worst = max(worst, abs(dx[k] - dx_prev[k]) / sig_floor[k])
            if worst < cfg[7]:
                break
        if not np.all(np.isfinite(dx)):
            break
        th = theta0.copy()
        for k in range(Pe):
            th[k] += dx[3 + k]
        predict_chain(th, u_acc, R_b, dx[0:3].copy(), yes, omega, base, s0, g, timed,
                      R_prior, T, tracked, c, B, need, dcol, dfix, dgrp, cam, du_acc, bscale,
                      jac, uv_r, d_r, Ha_r, Hp_r, R_out)
        H = _assemble(Ha_r, Hp_r, Pe, N, all_rows)
        for q in range(n_acc):
            h[2 * q], h[2 * q + 1] = uv_r[q, 0], uv_r[q, 1]
        if not (np.all(np.isfinite(H)) and np.all(np.isfinite(h))):
            ints[1] = it
            return (BAD_RELINEARIZATION, accepted, uv_pred, S_blocks, nis_stars, dirs,
                    np.zeros(N))
    ints[1] = it
    if not (np.all(np.isfinite(dx)) and np.all(np.isfinite(K))):
        return NON_FINITE, accepted, uv_pred, S_blocks, nis_stars, dirs, np.zeros(N)
    # ---- sensitivity (prior P, final H, the consider columns at the prior state); H is the
    # last gain's (every exit of the loop above comes before H is relinearized), so its
    # S = H P Hᵀ + R is factorized already: Lf
    mc = M.shape[1]
    if mc:
        Hb = np.empty((m2, mc))
        for q in range(n_acc):
            for r in range(2):
                for k in range(mc):
                    Hb[2 * q + r, k] = H_par[idx[q], r, Pe + k]
        A = H @ M + Hb
        if accumulate:
            X = cholesky_solve(Lf, np.hstack((A, nu.reshape(m2, 1))))
            score += A.T @ np.ascontiguousarray(X[:, mc])
            info += A.T @ np.ascontiguousarray(X[:, :mc])
        Mn = M - K @ A
        for i in range(N):
            for k in range(mc):
                M[i, k] = Mn[i, k]
    # ---- covariance, injection, reset
    Pn = joseph(P, K, H, rr)
    if timing:
        KC = K @ cc
        for a in range(N):
            for b in range(N):
                for j in range(kc):
                    Pn[a, b] += KC[a, j] * KC[b, j]
    for k in range(Pe):
        theta[k] += dx[3 + k]
    R_new = mat3_mul(so3_exp1(dx[0:3].copy()), R_b)
    for a in range(3):
        for b in range(3):
            R_a[a, b] = R_new[a, b]
    hx, hy, hz = 0.5 * dx[0], 0.5 * dx[1], 0.5 * dx[2]
    G = np.array([[1.0, -hz, hy], [hz, 1.0, -hx], [-hy, hx, 1.0]])
    top = G @ np.ascontiguousarray(Pn[0:3])
    for a in range(3):
        for k in range(N):
            Pn[a, k] = top[a, k]
    left = np.ascontiguousarray(Pn[:, 0:3]) @ G.T
    for k in range(N):
        for a in range(3):
            Pn[k, a] = left[k, a]
    for a in range(N):
        for b in range(N):
            P[a, b] = 0.5 * (Pn[a, b] + Pn[b, a])
    if mc:
        topm = G @ np.ascontiguousarray(M[0:3])
        for a in range(3):
            for k in range(mc):
                M[a, k] = topm[a, k]
    floats[0] = nis
    floats[2:12] = frame_sums(nu0, S_blocks, nis_stars, accepted, cfg[11], joint)
    return UPDATED, accepted, uv_pred, S_blocks, nis_stars, dirs, dx


@njit(cache=True)
def fused_sample(imu_t, cumb, k, tb, ib, pb, pe, rs, window):
    """The IMU sample covering ``tb`` for the fused step from sample ``k``, or −1.

    The sample: the first stamp of ``imu_t`` ≥ ``tb``.  −1 (the numpy path) when none
    covers it, when the rows ``k..m`` leave the reference prefix (``ib`` the buffer's
    base, ``pb..pe`` the prefix's rows, ``rs`` the reference's start, ``window`` its
    length) or hold a bridged sample (``cumb``, the buffer's running count of them).  The
    one check of ``StarFilter._fused_rows`` and of :func:`frame_steps`.
    """
    m = np.searchsorted(imu_t, tb)
    if m >= imu_t.shape[0] or ib + k < pb or pe <= ib + m or ib + m - rs >= window or \
            cumb[m + 1] != cumb[k]:
        return -1
    return m


@njit(cache=True)
def frame_steps(P, theta, R_a, M, score, info, acc,
                tp, C, w_hat, phi, slope, js, mjs, tas, tbs, Gamma, theta_ref, q_diag,
                gyro_b0, gyro_E0, gyro_Jb, gyro_JE, gyro_theta0, imu_w, ms,
                uv, u, sigma, offs, base,
                s0, g, timed, R_prior, T, tracked, c, B, need, dcol, dfix, dgrp, cam, du, bscale,
                Pe, cfg, t_rel, tix, tg, imu_t, cumb, lim):
    """:func:`frame_step` over ``K`` frames in a row, on copies of the state (a pump's batch).

    Frame ``i``'s inputs: ``acc[i]``, rows ``js[i]..mjs[i]``, ``tas[i]``, ``tbs[i]``, the
    raw rate ``imu_w[ms[i]]``, ``base[i]``, ``bscale[i]``, its stars rows
    ``offs[i]:offs[i + 1]`` of ``uv, u, sigma, du``; the rest as :func:`frame_step`.  The
    state arguments are not changed: each frame's state after it is returned, so that the
    caller commits them one frame at a time (the same floats as ``K`` calls of
    :func:`frame_step`).  Stops after the first frame not ``UPDATED`` and before a
    ``REBUILD`` (not done).

    ``lim[0]`` ≠ 0: the exposure times move with the estimate (an estimated time offset):
    frame ``i``'s ``tbs, base, ms, js, mjs`` and (``i`` > 0) ``tas`` are computed here, in
    place, from the state after frame ``i − 1`` as the kernel computes them for its frame
    (``StarFilter.update``, ``_fused_rows``): exposure shift ``Σ tg[q] θ[tix[q]]`` (the
    TIME effects' affine forms), ``tb = t_rel[i] + shift``, the IMU sample covering it in
    ``imu_t`` (first stamp ≥ tb), rows offset by ``lim[2] − lim[3]``.  The batch stops
    before a frame the driver would not hand on yet (``lim[7] > tb + lim[8]`` fails: the
    IMU received does not cover its exposure), whose time is not after the one before, or
    whose rows leave the reference or contain a bridged sample (``cumb``).  ``lim``:
    ``[vary, k0, imu base, prefix base, prefix end, reference start, window, IMU end,
    look-ahead]``.

    Returns ``(done, status (K,), ints (K, 6), floats (K, 13), accepted, uv_pred, S,
    nis_stars, directions (stars rows), omega (K, 3), R_prior (K, 3, 3), P (K, N, N),
    theta (K, P_all), R (K, 3, 3), M (K, N, m), score (K, m), info (K, m, m))``.
    """
    K = js.shape[0]
    n_all = uv.shape[0]
    P_ = P.copy()
    th_ = theta.copy()
    R_ = R_a.copy()
    M_ = M.copy()
    sc_ = score.copy()
    in_ = info.copy()
    out = _batch_outputs(K, n_all, P, theta, M)
    done = 0
    vary = lim[0] != 0.0
    k = int(lim[1])
    ib, pb, pe, rs = int(lim[2]), int(lim[3]), int(lim[4]), int(lim[5])
    for i in range(K):
        if vary:  # this frame's exposure time under the state after the frame before
            if i > 0:
                tas[i] = tbs[i - 1]
                k = ms[i - 1]
            shift = 0.0
            for q in range(tix.shape[0]):
                shift += tg[q] * th_[tix[q]]
            tb = t_rel[i] + shift
            if not (lim[7] > tb + lim[8]) or not (tb > tas[i]):
                break
            m = fused_sample(imu_t, cumb, k, tb, ib, pb, pe, rs, lim[6])
            if m < 0:
                break
            tbs[i] = tb
            base[i] = t_rel[i] - tb
            ms[i] = m
            js[i] = k + ib - pb
            mjs[i] = m + ib - pb
        a, b = offs[i], offs[i + 1]
        st, it_, fl, ac, up, Sb, ns, dr, om, rp = frame_step(
            P_, th_, R_, M_, sc_, in_, acc[i], tp, C, w_hat, phi, slope, js[i], mjs[i],
            tas[i], tbs[i], Gamma, theta_ref, q_diag, gyro_b0, gyro_E0, gyro_Jb, gyro_JE,
            gyro_theta0, imu_w[ms[i]], uv[a:b], u[a:b], sigma[a:b], base[i], s0, g, timed,
            R_prior, T, tracked, c, B, need, dcol, dfix, dgrp, cam, du[a:b], bscale[i], Pe,
            cfg)
        if st == REBUILD:
            break
        _keep_frame(out, i, a, b, st, it_, fl, ac, up, Sb, ns, dr, om, rp, P_, th_, R_, M_,
                    sc_, in_)
        done = i + 1
        if st != UPDATED:
            break
    return (done,) + out


class FusedStep:
    """The constant inputs of :func:`frame_step` for one filter (see the module docstring).

    :meth:`build` returns None when the filter's frames cannot take the fused path: no
    compiled star chain, a gyro model that is not affine in θ, a method with velocity
    blocks, its own transition, measurements, injection or prediction, or the per-sample
    propagation (``exact_propagation``).
    """

    _HOOKS = ("_transition", "_propagate_interval", "_before_star_update", "inject",
              "_star_update", "propagate", "_predict", "rate_at", "update")

    def __init__(self, flt, chain, gyro_affine) -> None:
        c = flt.config
        P_all = flt.model.size
        self.gyro = None  # (:meth:`build_update`'s step takes the rate from the filter)
        if gyro_affine is not None:
            b0, E0, Jb, JE = gyro_affine
            self.gyro = (np.ascontiguousarray(b0, dtype=float),
                         np.ascontiguousarray(E0, dtype=float),
                         np.ascontiguousarray(Jb, dtype=float),
                         np.ascontiguousarray(JE.reshape(9, P_all), dtype=float),
                         np.ascontiguousarray(flt.propagation.gyro.theta0, dtype=float))
        self.compiled_chain = chain
        self.chain = (float(chain.s0), chain.g, bool(chain.timed), chain.R_prior, chain.T,
                      bool(chain.tracked), chain.c, chain.B, chain.need)
        self.directions = (chain.dcol, chain.dfix, chain.dgrp, chain.cam)
        from stellar_cal_ros.methods.results import NIS_CAP

        values = {"threshold": flt.gate.threshold, "scale_by_frame": float(c.scale_gate_by_frame),
                  "mismatch_factor": c.mismatch_factor, "lost_lock_factor": c.lost_lock_factor,
                  "fov_tan2": flt.gate.fov_tan2, "min_stars": c.min_stars,
                  "max_iterations": c.max_iterations,
                  "iteration_tolerance": c.iteration_tolerance,
                  "relinearize_rad": c.relinearize_rad, "relinearize_sigma": c.relinearize_sigma,
                  "max_correction_rad": flt.propagation.max_correction_rad, "nis_cap": NIS_CAP,
                  "stamp_sigma": flt.stamp_sigma, "frame_sigma": flt.frame_sigma}
        self.cfg = np.array([float(values[k]) for k in CONFIG_FIELDS])
        self.q_diag = np.ascontiguousarray(flt._q_diag, dtype=float)
        self.Pe = int(flt.P_est)
        N = flt.N
        self.none = (np.zeros((N, 0)), np.zeros(0), np.zeros((0, 0)))
        # the reference's Γ (``prop._gamma``, a tuple replaced at each rebuild) as a C array:
        # a column slice would take numba's non-contiguous matrix product (a copy per call)
        self._gamma_of: tuple | None = None
        self._gamma = np.zeros((3, 0))
        #: :meth:`batch`'s ``vary`` of exposure times fixed before the call (none moves)
        self._fixed = (np.zeros(0, dtype=np.int64), np.zeros(0),
                       np.array([0.0, 0, 0, 0, 0, 0, 0, math.inf, 0.0]))

    @classmethod
    def build(cls, flt, kernel_cls: type) -> FusedStep | None:
        """The fused step of ``flt``, or None (see the class docstring).

        ``kernel_cls``: the kernel's filter class (its hooks are the ones this step fuses).
        """
        prop = flt.propagation
        if prop.accel is not None or prop.exact or prop.gyro._affine is None or any(
                getattr(type(flt), h) is not getattr(kernel_cls, h) for h in cls._HOOKS):
            return None
        chain = flt.model.compiled_chain()
        return None if chain is None else cls(flt, chain, prop.gyro._affine)

    #: what the numpy star update calls that :meth:`update` does in the compiled call
    _UPDATE_HOOKS = ("inject", "_predict", "_star_jacobian", "_gated")

    @classmethod
    def build_update(cls, flt, kernel_cls: type) -> FusedStep | None:
        """The star update alone of ``flt`` (:meth:`update`), or None.

        None: no compiled chain, a navigation block that is not a whole vector (its
        correction is injected by the caller: an addition to all of it), or a filter with
        its own injection, prediction, Jacobian or gating judgement (the Cramér–Rao
        bound's, which keeps the nominal state: ``bounds``).

        For a method whose propagation and measurements stay its own (the swaying-base
        filter: ``StarFilter.compiled_star_update``).
        """
        if any(b.kind != "vector" or b.index is not None for b in flt.navigation_blocks) or any(
                getattr(type(flt), h) is not getattr(kernel_cls, h) for h in cls._UPDATE_HOOKS):
            return None
        chain = flt.model.compiled_chain()
        return None if chain is None else cls(flt, chain, None)

    def update(self, P, theta, R, sens, omega, uv, u, sigma, base, ctx):
        """:func:`star_update` of the filter's propagated state (arrays changed in place).

        Returns ``(status, ints, floats, accepted, uv_pred, S, nis_stars, directions, dx)``
        (``ints``, ``floats`` as :func:`frame_step`'s).
        """
        M, score, info, acc = self._sensitivity(sens)
        u, uv, sigma = self._frame(u, uv, sigma)
        du, bscale = self.compiled_chain.frame_inputs(u, ctx)
        ints = np.zeros(6, dtype=np.int64)
        floats = np.zeros(13)
        floats[0] = np.nan
        out = star_update(P, theta, R, M, score, info, acc,
                          np.ascontiguousarray(omega, dtype=float), uv, u, sigma, float(base),
                          *self.chain, *self.directions, du, bscale, self.Pe, self.cfg, ints,
                          floats)
        return (out[0], ints, floats) + out[1:]

    def _sensitivity(self, sens) -> tuple:
        """``(M, score, info, accumulate)`` of the call (the empty ones without consider)."""
        if sens is None:
            return (*self.none, False)
        if not sens.M.flags.c_contiguous:
            sens.M = np.ascontiguousarray(sens.M)
        return sens.M, sens.score, sens.info, bool(sens.accumulate)

    @staticmethod
    def _frame(u, uv, sigma) -> tuple:
        """The frame's ``u, uv, sigma`` as C arrays of floats (copies only when needed)."""
        if not u.flags.c_contiguous:
            u = np.ascontiguousarray(u)
        if not uv.flags.c_contiguous:
            uv = np.ascontiguousarray(uv)
        if not (sigma.flags.c_contiguous and sigma.dtype == float):
            sigma = np.ascontiguousarray(sigma, dtype=float)
        return u, uv, sigma

    def call(self, P, theta, R, sens, pre, j, mj, ta, tb, prop, w_raw, uv, u, sigma, base,
             ctx):
        """:func:`frame_step` of the filter's current state (arrays changed in place)."""
        M, score, info, acc = self._sensitivity(sens)
        u, uv, sigma = self._frame(u, uv, sigma)
        gamma = prop._gamma
        if gamma is not self._gamma_of:  # a new reference: its Γ as a C array, once
            self._gamma_of, self._gamma = gamma, np.ascontiguousarray(gamma[0])
        du, bscale = self.compiled_chain.frame_inputs(u, ctx)
        return frame_step(P, theta, R, M, score, info, acc, pre.tp, pre.C, pre.w_hat, pre.phi,
                          pre.slope, j, mj, float(ta), float(tb), self._gamma, prop.theta_ref,
                          self.q_diag, *self.gyro, w_raw, uv, u, sigma, float(base),
                          *self.chain, *self.directions, du, bscale, self.Pe, self.cfg)


    def stack(self, frames: list) -> tuple:
        """A batch's frames (:meth:`batch`'s tuples) as the compiled loops take them.

        ``(offs, col, uv, u, sigma, du, bscale, base)``: the frames' star rows
        ``offs[i]:offs[i + 1]`` of the stacked ``uv, u, sigma`` and the chain's ``du``, a
        row a frame of ``bscale``, ``base`` and ``col`` (``j, mj, ta, tb, m, accumulate,
        t_rel``).
        """
        K = len(frames)
        offs = np.zeros(K + 1, dtype=np.int64)
        offs[1:] = np.cumsum([len(f[0]) for f in frames])
        col = np.array([f[5:12] for f in frames], dtype=float)
        uv = np.concatenate([f[0] for f in frames]).reshape(-1, 2)
        us = [f[1] for f in frames]
        u = np.concatenate(us).reshape(-1, 3)
        sigma = np.concatenate([f[2] for f in frames]).astype(float, copy=False)
        du, bscale = self.compiled_chain.frames_inputs(us, u, offs, [f[4] for f in frames])
        base = np.array([f[3] for f in frames], dtype=float)
        return offs, col, uv, u, sigma, du, bscale, base

    def batch(self, P, theta, R, sens, pre, prop, imu, frames, vary=None
              ) -> FrameBatch | None:
        """:func:`frame_steps` over ``frames`` from the filter's current state.

        ``frames``: ``(uv, u, sigma, base, ctx, j, mj, ta, tb, m, accumulate, t_rel)`` of
        each frame in order, as :meth:`call` would take them (``m``: the IMU row of the raw
        rate; ``imu``: the filter's :class:`~stellar_cal_ros.core.imu.ImuBuffer`).
        ``vary``: None, or ``(tix, tg, lim)`` of exposure times that move with the estimate
        (:func:`frame_steps`): the frames' ``base, j, mj, tb, m`` (and ``ta`` after the
        first) are then found by the call, and the batch's frames carry them.  The state is
        not changed: :meth:`FrameBatch.take` commits each frame's.  None: no frame.
        """
        if not frames:
            return None
        if sens is None:
            M, score, info = self.none
        else:
            if not sens.M.flags.c_contiguous:
                sens.M = np.ascontiguousarray(sens.M)
            M, score, info = sens.M, sens.score, sens.info
        gamma = prop._gamma
        if gamma is not self._gamma_of:
            self._gamma_of, self._gamma = gamma, np.ascontiguousarray(gamma[0])
        offs, col, uv, u, sigma, du, bscale, base = self.stack(frames)
        js, mjs = col[:, 0].astype(np.int64), col[:, 1].astype(np.int64)
        ms = col[:, 4].astype(np.int64)
        tas, tbs = np.ascontiguousarray(col[:, 2]), np.ascontiguousarray(col[:, 3])
        tix, tg, lim = vary if vary is not None else self._fixed
        try:
            out = frame_steps(P, theta, R, M, score, info, col[:, 5] != 0.0, pre.tp, pre.C,
                              pre.w_hat, pre.phi, pre.slope, js, mjs, tas, tbs,
                              self._gamma, prop.theta_ref, self.q_diag, *self.gyro, imu.w, ms,
                              uv, u, sigma, offs, base, *self.chain, *self.directions, du,
                              bscale, self.Pe, self.cfg, np.ascontiguousarray(col[:, 6]), tix,
                              tg, imu.t, imu.cum_bridged, lim)
        except Exception:  # noqa: BLE001 - the frame's own call raises it, in its turn
            return None
        loaded = len(getattr(frame_steps, "overloads", ()))  # (none: NUMBA_DISABLE_JIT)
        if loaded != _LOADED[0]:  # loaded (or compiled) by this call
            _LOADED[0] = loaded
            release_linking_ir()  # the run's peak comes later: its tables, their statistics
        done = int(out[0])
        if not done:
            return None
        if vary is not None:  # the frames as the call found them (FrameBatch.take's check)
            rows = zip(base[:done].tolist(), js[:done].tolist(), mjs[:done].tolist(),
                       tas[:done].tolist(), tbs[:done].tolist(), ms[:done].tolist(),
                       strict=True)
            frames = [f[:3] + (b, f[4], j, mj, ta, tb, m) + f[10:]
                      for f, (b, j, mj, ta, tb, m) in zip(frames, rows, strict=False)] + \
                frames[done:]
        return FrameBatch(out, frames, offs, gamma, pre, P, theta, R, M)


class FrameBatch:
    """The results of :meth:`FusedStep.batch`, handed out frame by frame (:meth:`take`)."""

    def __init__(self, out, frames, offs, gamma, pre, P, theta, R, M) -> None:
        self.out = out
        self.done = int(out[0])
        self.frames = frames
        self.offs = offs.tolist()
        self.key = (gamma, pre, P, theta, R, M)
        self.i = 0

    def take(self, P, theta, R, sens, uv, j, mj, ta, tb, gamma, pre):
        """Frame ``i``'s :func:`frame_step` result, its state committed; None: not the frame.

        The frame must be the next one of the batch with the same rows, times, stars array,
        accumulation flag and state arrays; otherwise nothing is changed (the caller then
        drops the batch and calls :func:`frame_step`).
        """
        i = self.i
        if i >= self.done:
            return None
        f = self.frames[i]
        M = sens.M if sens is not None else self.key[5]
        acc = bool(sens.accumulate) if sens is not None else f[10]
        if not (uv is f[0] and j == f[5] and mj == f[6] and ta == f[7] and tb == f[8]
                and acc == f[10] and all(a is b for a, b in zip(
                    self.key, (gamma, pre, P, theta, R, M), strict=True))):
            return None
        (_, status, ints, floats, accepted, uv_pred, S, nis, dirs, omega, R_prior, Ps, ths,
         Rs, Ms, scs, ins) = self.out
        P[...] = Ps[i]
        theta[...] = ths[i]
        R[...] = Rs[i]
        if sens is not None:
            M[...] = Ms[i]
            sens.score[...] = scs[i]
            sens.info[...] = ins[i]
        self.i = i + 1
        a, b = self.offs[i], self.offs[i + 1]
        return (int(status[i]), ints[i], floats[i], accepted[a:b], uv_pred[a:b], S[a:b],
                nis[a:b], dirs[a:b], omega[i].copy(), R_prior[i])


class BatchCommit:
    """The frames :meth:`~stellar_cal_ros.methods.kernel.StarFilter.commit_batch` committed.

    Their values as arrays, a row a frame, for the run's statistics and history:
    ``stamps`` (POSIX s), ``nis``, ``dof``, ``iterations``, ``n`` (stars), ``n_acc``
    (accepted), ``sums`` (the statistics' terms, (count, 10)), ``sigma`` (1-σ of the state
    after each, (count, N)) and ``theta`` (the estimated θ after each); :meth:`update` makes a
    frame's :class:`~stellar_cal_ros.methods.kernel.FrameUpdate` (the one the frame-by-frame
    path makes) for a caller that keeps them.  ``update_cls``: that class, handed in by the
    kernel (this module does not import the kernel, which imports it: as
    :meth:`FusedStep.build`'s ``kernel_cls``).
    """

    def __init__(self, batch: FrameBatch, count: int, n: list, n_acc: list,
                 sigma_last: np.ndarray, theta_last: np.ndarray, p_est: int,
                 update_cls: type) -> None:
        self._update_cls = update_cls
        out = batch.out
        self._out = out
        self._frames = batch.frames
        self._offs = batch.offs
        self.count = q = int(count)
        ints, floats, Ps, ths = out[2], out[3], out[11], out[12]
        self.stamps = [f[4].stamp for f in self._frames[:q]]
        self.nis = floats[:q, 0]
        self.n = n
        self.n_acc = n_acc
        self.dof = [2 * a for a in n_acc]
        self.iterations = ints[:q, 1]
        self.sums = floats[:q, 2:12]
        # the state after each frame (the last: the filter's own, after a covariance check)
        sigma = np.sqrt(np.maximum(np.diagonal(Ps[:q], axis1=1, axis2=2), 0.0))
        sigma[q - 1] = sigma_last
        theta = ths[:q, :p_est].copy()
        theta[q - 1] = theta_last
        self.sigma, self.theta = sigma, theta

    def star_rows(self, k: int) -> tuple[np.ndarray, ...]:
        """The first ``k`` frames' stars, stacked, a row a star.

        ``(uv, accepted, uv_pred, S, nis, directions)`` (what :meth:`update` holds of each)
        and the frames' ``omega`` (k, 3): the residual table's rows
        (:func:`~.results.residual_block`).
        """
        accepted, uv_pred, S, nis, dirs, omega = self._out[4:10]
        r = self._offs[k]
        return (np.concatenate([f[0] for f in self._frames[:k]]), accepted[:r], uv_pred[:r],
                S[:r], nis[:r], dirs[:r], omega[:k])

    def update(self, i: int):
        """Frame ``i``'s :class:`~stellar_cal_ros.methods.kernel.FrameUpdate`."""
        (_, _, ints, floats, accepted, uv_pred, S, nis, dirs, omega) = self._out[:10]
        f = self._frames[i]
        a, b = self._offs[i], self._offs[i + 1]
        return self._update_cls(f[4].stamp, f[8], accepted[a:b], f[0], uv_pred[a:b],
                                S[a:b], nis[a:b], float(floats[i, 0]), self.dof[i],
                                dirs[a:b], omega[i].copy(), int(ints[i, 1]),
                                floats[i, 2:12])


# Every module holding cached numba kernels (test_user_path checks the list is complete).
KERNEL_MODULES = ("stellar_cal_ros.core.jit", "stellar_cal_ros.methods.star_chain",
                  "stellar_cal_ros.methods.frame_step", "stellar_cal_ros.core.float_text")


def _kernels(modules: tuple[str, ...]) -> list[tuple[str, str, object]]:
    """``(module, name, dispatcher)`` of each cached, not inlined numba kernel of ``modules``."""
    out = []
    for name in modules:
        mod = importlib.import_module(name)
        for key, obj in vars(mod).items():
            cache = getattr(obj, "_cache", None)
            if getattr(getattr(cache, "_cache_file", None), "_load_index", None) is None or \
                    getattr(obj, "__module__", None) != mod.__name__ or \
                    getattr(obj, "targetoptions", {}).get("inline") == "always":
                continue  # (an inlined kernel is compiled into its callers only)
            out.append((name, key, obj))
    return out


#: overloads of :func:`frame_steps` when :func:`release_linking_ir` last ran here
_LOADED = [0]

#: beside a module's numba cache index files: the module's kernels the last run compiled or
#: loaded (:func:`record_kernels_used`)
USED_MARKER = "{module}.kernels-used.json"


def _marker(module: str, obj) -> Path:
    return Path(obj._cache._cache_path) / USED_MARKER.format(module=module)


def _used(module: str, obj) -> set[str] | None:
    """The kernels of ``module`` a run used (its marker), None where no run has said."""
    try:
        return set(json.loads(_marker(module, obj).read_text())["used"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def kernels_cold(modules: tuple[str, ...]) -> bool:
    """True when a kernel of ``modules`` that a run calls has no usable compiled cache.

    A kernel's cache is numba's index file; it is empty (a fresh install) or stale (another
    source stamp) until the kernel is compiled again.  Judged are the kernels the last run
    compiled or loaded (:func:`record_kernels_used`), every kernel where no run has said:
    a kernel that only other kernels call is compiled into *their* cache files, so when its
    own source changes but theirs does not, numba loads the callers as they are and never
    rewrites the callee's index (``core.jit.skew3`` under ``star_chain.predict_chain``):
    judged by its index, every run said "compiling" and compiled nothing.
    """
    by_module: dict[str, set[str] | None] = {}
    for module, name, obj in _kernels(modules):
        if module not in by_module:
            by_module[module] = _used(module, obj)
        used = by_module[module]
        if used is not None and name not in used:
            continue
        if not obj._cache._cache_file._load_index():
            return True
    return False


def record_kernels_used(modules: tuple[str, ...] = ()) -> None:
    """Write each module's marker (:data:`USED_MARKER`): its kernels this process used.

    Used: compiled or loaded from the cache here (the dispatcher holds an overload), or
    used by an earlier run and still cached (a kernel of the other method).  A kernel
    whose callers came from the cache is neither, and :func:`kernels_cold` stops judging
    it.  Nothing is written where the cache directory cannot be (the check then judges
    every kernel, as before).
    """
    if not HAVE_NUMBA:
        return
    kernels = _kernels(modules or KERNEL_MODULES)
    for module in dict.fromkeys(m for m, _, _ in kernels):
        mine = [(name, obj) for m, name, obj in kernels if m == module]
        before = _used(module, mine[0][1]) or set()
        try:
            used = sorted(name for name, obj in mine if obj.overloads or (
                name in before and obj._cache._cache_file._load_index()))
            _marker(module, mine[0][1]).write_text(json.dumps({"used": used}))
        except Exception:  # noqa: BLE001 - a read-only cache, numba internals: no marker
            continue


def _relinkable(library, bitcode: bytes) -> None:
    """Give ``library`` its linking module back from ``bitcode`` when a compile asks for it."""
    def module_for_linking():
        if library._shared_module is None:
            from numba.core.codegen import ll  # (llvmlite's binding, as numba loads it)

            library._shared_module = ll.parse_bitcode(bitcode)
        return library._shared_module

    library._get_module_for_linking = module_for_linking  # shadows the class's method


def release_linking_ir(modules: tuple[str, ...] = ()) -> int:
    """Free the LLVM modules numba keeps of the loaded kernels for later links; how many.

    numba keeps, beside each kernel's machine code, its whole LLVM module (every kernel it
    calls inlined into it) in case a kernel compiled later calls it: ≈ 21 MB of the ≈ 77 MB
    the four kernels of a 2-h round take when loaded, held all the round.  Kept instead:
    the module's bitcode (≈ 4.5 MB), parsed again only if such a compile comes (the
    library's ``_get_module_for_linking``).  Called by the filter's first batched call
    and after each diagnosis run (``runstats.evaluate``).  A kernel compiled here (not loaded
    from the cache) keeps its module, which numba's engine owns; only the copy made for
    linking is dropped (numba makes it again).  The machine code, and so every number
    computed, is untouched.  Nothing without numba, or where its internals differ.
    """
    if not HAVE_NUMBA:
        return 0
    freed = 0
    try:
        for _, _, obj in _kernels(modules or KERNEL_MODULES):
            for cres in list(obj.overloads.values()):
                library = cres.library
                shared = getattr(library, "_shared_module", None)
                if shared is None or "_get_module_for_linking" in vars(library):
                    continue
                if any(True for _ in library._final_module.functions):
                    library._shared_module = None  # compiled here: made again from its own
                else:  # loaded from the cache: its only copy of the module
                    _relinkable(library, shared.as_bitcode())
                    library._shared_module = None
                freed += 1
    except Exception:  # noqa: BLE001 - numba internals: keep what numba keeps
        return freed
    return freed


def compiled_kernels_cold() -> bool:
    """True when the numba kernels of KERNEL_MODULES a run calls have no usable cache yet.

    The first run after an install or a change of the kernels' source compiles them (≈30 s
    on 2 cores): :func:`kernels_cold`.  False without numba or when the cache cannot be
    inspected.
    """
    if not HAVE_NUMBA:
        return False
    try:
        return kernels_cold(KERNEL_MODULES)
    except Exception:  # noqa: BLE001 - numba internals: say nothing rather than fail
        return False


def compile_notice(stream: TextIO | None = None) -> bool:
    """Say (one line) that the first run compiles the filter kernels, when it will."""
    if not compiled_kernels_cold():
        return False
    from stellar_cal_ros.progress import COMPILE_NOTICE

    print(COMPILE_NOTICE, file=stream or sys.stderr, flush=True)
    return True
