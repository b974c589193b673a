"""The filters' star step in compiled form (numba): every star of a frame in one call.

When every effect of a :class:`~stellar_cal_ros.methods.star_model.StarModel` is a constant
affine map of its value (:meth:`~stellar_cal_ros.effects.base.Effect.affine_form`: the
library's installation, time offset and camera effects), the model's chain folds into a few
constant arrays (:class:`CompiledChain`) and :func:`predict_chain` computes the centroids
and Jacobians of :meth:`StarModel.predict` with the kernels of
:mod:`stellar_cal_ros.core.jit`.  Any other effect (a user's ``--effect-module`` without an
affine form, a DIRECTION effect) or a missing numba: :func:`compile_chain` returns None and
the model predicts through the effects' Python methods — the reference path.

Both paths compute the same quantities with the same formulas, in a different order of a
few floating-point operations, so they agree to rounding (~1e-16 relative) per call.  Over
a replay the difference grows during the ill-conditioned start-up (one frame cannot tell a
principal-point offset from an attitude tilt, so the first updates amplify a last-bit
difference by up to the condition number of the innovation covariance) and then stays
bounded: after a 300 s replay the estimates of both paths differ by far less than their
posterior σ (``test/test_compiled_step.py`` states the bound).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from stellar_cal_ros.core.jit import (
    HAVE_NUMBA,
    jacobian1,
    mat3_mul,
    njit,
    project_points,
    skew3,
    so3_exp1,
    tilt_kernel,
)
from stellar_cal_ros.effects.base import Stage

_NO_SCALE = np.zeros(0)


@dataclass
class CompiledChain:
    """The star chain of a model whose effects all have an affine form (compiled step).

    With every TIME, TRACKER and CAMERA effect a constant affine map of its value
    (:meth:`Effect.affine_form`) and every DIRECTION effect affine in its value with
    columns ``C`` that come with the frame, the chain is::

        u' = u + Σ v C(u, ctx)     (DIRECTION; C from :meth:`direction_columns`)
        Δt = s0 + g·θ              (s0: the prior's time offset when no TIME effect)
        δ  = T θ,  R_imu_st = R_prior Exp(δ)
        p  = c + B θ               (the camera chain folded: c from the prior, B = ∂p/∂θ)

    and :func:`predict_chain` computes the centroids and Jacobians of every star of a frame
    in one compiled call — the quantities of :meth:`StarModel.predict`, to rounding.
    """

    s0: float
    g: np.ndarray  #: (P,) ∂Δt/∂θ, s per unit
    timed: bool  #: the time shift depends on θ (a TIME effect with a nonzero gradient)
    R_prior: np.ndarray  #: (3, 3) prior installation R_imu_st
    T: np.ndarray  #: (3, P) ∂δ/∂θ
    tracked: bool  #: TRACKER effects present
    c: np.ndarray  #: (18,) camera parameters at θ = 0
    B: np.ndarray  #: (18, P) ∂p/∂θ
    need: np.ndarray  #: (k,) intp, rows of B that are not zero
    #: DIRECTION effects in chain order: (effect, slice of θ or None, fixed value or None);
    #: each maps ``u' = u + Σ_j v_j C_j(u, ctx)`` (:func:`direction_columns` gives ``C``)
    directions: list = None  # type: ignore[assignment]
    dcol: np.ndarray = None  # type: ignore[assignment]  #: (kd,) intp θ index, -1: fixed
    dfix: np.ndarray = None  # type: ignore[assignment]  #: (kd,) value of a fixed column
    dgrp: np.ndarray = None  # type: ignore[assignment]  #: (effects + 1,) column offsets
    #: the camera chain's bilinear steps (:func:`_camera_at`; empty: ``p = c + B θ``)
    cam: tuple = ()
    bilinear: list = None  # type: ignore[assignment]  #: their effects (camera_scale)

    def frame_inputs(self, u: np.ndarray, ctx: Any) -> tuple[np.ndarray, np.ndarray]:
        """``(du, bscale)`` of one frame.

        :meth:`direction_columns` and the bilinear camera steps' scales
        (:meth:`Effect.camera_scale`).
        """
        return self.direction_columns(u, ctx), self._scales(ctx)

    def _scales(self, ctx: Any) -> np.ndarray:
        """The bilinear camera steps' scales of a frame (:meth:`Effect.camera_scale`)."""
        if not self.bilinear:
            return _NO_SCALE
        return np.concatenate([np.asarray(e.camera_scale(ctx), dtype=float)
                               for e in self.bilinear])

    def frames_inputs(self, us: list, u: np.ndarray, offs: np.ndarray, ctxs: list
                      ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`frame_inputs` of several frames: ``du`` stacked (N, 3, kd), ``bscale`` (K, kb).

        ``us``: each frame's directions, its rows ``offs[i]:offs[i + 1]`` of ``u`` (N, 3);
        ``ctxs``: their contexts.  An effect with ``directions_jacobian_frames`` (the
        astrometric ones: :meth:`~stellar_cal_ros.effects._direction.ScaledDirection.
        delta_frames`) gives all the frames' columns in one call; any other, a frame at a
        time — the same floats as :meth:`frame_inputs` of each frame.
        """
        K, N = len(ctxs), len(u)
        if not self.directions:
            du = np.zeros((N, 3, 0))
        else:
            du = np.empty((N, 3, len(self.dcol)))
            for k, (eff, sl, fixed) in enumerate(self.directions):
                v = fixed if sl is None else np.zeros(eff.size)
                cols = slice(self.dgrp[k], self.dgrp[k + 1])
                many = getattr(eff, "directions_jacobian_frames", None)
                got = many(v, us, u, offs, ctxs) if many is not None else None
                if got is not None:
                    du[:, :, cols] = got
                    continue
                for i in range(K):
                    du[offs[i]:offs[i + 1], :, cols] = eff.directions_jacobian(v, us[i], ctxs[i])
        return du, np.array([self._scales(c) for c in ctxs], dtype=float).reshape(
            K, -1 if self.bilinear else 0)

    def direction_columns(self, u: np.ndarray, ctx: Any) -> np.ndarray:
        """The frame's DIRECTION columns ``C`` (n, 3, kd) of :func:`predict_chain`.

        Column j of effect e is ``∂u'/∂v_j`` (:meth:`Effect.directions_jacobian`, which an
        effect with an affine DIRECTION form returns for any value); (n, 3, 0) without
        DIRECTION effects.
        """
        n = len(u)
        if not self.directions:
            return np.zeros((n, 3, 0))
        out = np.empty((n, 3, len(self.dcol)))
        for k, (eff, sl, fixed) in enumerate(self.directions):
            v = fixed if sl is None else np.zeros(eff.size)
            out[:, :, self.dgrp[k]:self.dgrp[k + 1]] = eff.directions_jacobian(v, u, ctx)
        return out


def compile_chain(model: Any) -> CompiledChain | None:
    """The :class:`CompiledChain` of ``model`` (a :class:`~.star_model.StarModel`), or None.

    None without numba or when an effect has no affine form: the model then predicts
    through the effects' methods.
    """
    if not HAVE_NUMBA:
        return None
    directions, dcol, dfix, dgrp = [], [], [], [0]
    for eff, sl, fixed in model._chain[Stage.DIRECTION]:
        if not eff.affine_form():
            return None
        directions.append((eff, sl, fixed))
        for j in range(eff.size):
            dcol.append(-1 if sl is None else sl.start + j)
            dfix.append(float(fixed[j]) if sl is None else 0.0)
        dgrp.append(len(dcol))
    P = model.size
    g, T = np.zeros(P), np.zeros((3, P))
    for stage, target in ((Stage.TIME, g), (Stage.TRACKER, T)):
        for eff in model._by_stage[stage]:
            form = eff.affine_form()
            if form is None:
                return None
            target[..., model.slices[eff.id]] = form
    camera = _camera_chain(model, P)
    if camera is None:
        return None
    c, B, cam, bilinear = camera
    timed = bool(model.has_time_effect and np.any(g))
    s0 = 0.0 if model.has_time_effect else float(model.prior.time_offset)
    return CompiledChain(s0, g, timed, np.array(model._R_imu_st_prior, dtype=float), T,
                         bool(model._by_stage[Stage.TRACKER]), c, B,
                         _camera_rows(B, cam), directions, np.array(dcol, dtype=np.intp),
                         np.array(dfix, dtype=float), np.array(dgrp, dtype=np.intp), cam,
                         bilinear)


def _camera_chain(model: Any, P: int) -> tuple | None:
    """The camera chain folded: ``(c, B, cam, bilinear)``, or None (an effect without form).

    Affine steps fold into ``p = c + B θ``; each :class:`~stellar_cal_ros.effects.base.
    BilinearCamera` step is kept (``cam``: see :func:`_camera_at`), followed by the fold of
    the affine steps after it.
    """
    from stellar_cal_ros.effects.base import BilinearCamera

    c, B = np.array(model._camera_prior, dtype=float), np.zeros((18, P))
    steps: list = []  # (D0, Dv, J0, cols, fixed) and the fold (A, Bb, cb) after each
    bilinear: list = []  # (effect, k) of each step (its camera_scale per frame)
    for eff, sl, fixed in model._chain[Stage.CAMERA]:
        form = eff.affine_form()
        if form is None:
            return None
        if isinstance(form, BilinearCamera):
            cols = np.full(eff.size, -1) if sl is None else np.arange(sl.start, sl.stop)
            fix = np.asarray(fixed, dtype=float) if sl is None else np.zeros(eff.size)
            steps.append([form, cols, fix, np.eye(18), np.zeros((18, P)), np.zeros(18)])
            bilinear.append(eff)
            continue
        J, D = (np.asarray(f, dtype=float) for f in form)
        if steps:  # after a bilinear step: fold into its (A, Bb, cb)
            st = steps[-1]
            st[3], st[4], st[5] = D @ st[3], D @ st[4], D @ st[5]
            if sl is None:
                st[5] = st[5] + J @ fixed
            else:
                st[4][:, sl] += J
            continue
        c, B = D @ c, D @ B
        if sl is None:
            c = c + J @ fixed
        else:
            B[:, sl] += J
    k = sum(len(st[1]) for st in steps)
    grp = np.zeros(len(steps) + 1, dtype=np.intp)
    D0s, As = np.zeros((len(steps), 18, 18)), np.zeros((len(steps), 18, 18))
    Dvs, J0s = np.zeros((k, 18, 18)), np.zeros((18, k))
    bcol, bfix = np.zeros(k, dtype=np.intp), np.zeros(k)
    Bbs, cbs = np.zeros((len(steps), 18, P)), np.zeros((len(steps), 18))
    for b, (form, cols, fix, A, Bb, cb) in enumerate(steps):
        grp[b + 1] = grp[b] + len(cols)
        sl = slice(grp[b], grp[b + 1])
        D0s[b], As[b], Bbs[b], cbs[b] = form.D0, A, Bb, cb
        Dvs[sl], J0s[:, sl], bcol[sl], bfix[sl] = form.Dv, form.J0, cols, fix
    return c, B, (D0s, Dvs, J0s, bcol, bfix, grp, As, Bbs, cbs), bilinear


def _camera_rows(B: np.ndarray, cam: tuple) -> np.ndarray:
    """Rows of ``∂p/∂θ`` that can be nonzero (the projection's Jacobian columns needed)."""
    D0s, Dvs, J0s, bcol, _, grp, As, Bbs, _ = cam
    pat = np.abs(B)
    for b in range(len(D0s)):
        Mabs = np.abs(D0s[b]) + np.abs(Dvs[grp[b]:grp[b + 1]]).sum(axis=0)
        pat = Mabs @ pat
        for j in range(grp[b], grp[b + 1]):
            if bcol[j] >= 0:
                pat[:, bcol[j]] += np.abs(Dvs[j]).sum(axis=1) + np.abs(J0s[:, j])
        pat = np.abs(As[b]) @ pat + np.abs(Bbs[b])
    return np.flatnonzero(np.any(pat != 0.0, axis=1)).astype(np.intp)


@njit(cache=True)
def _camera_at(theta, c, B, need, cam, bscale):
    """Camera vector ``p`` (18,) and ``∂p/∂θ`` (18, P) of ``theta``.

    ``p = c + B θ`` without bilinear steps (``B`` itself returned); with them, each step
    ``p ← (D0 + Σ v s Dv) p + J0 v`` and the fold after it, ``p ← A p + Bb θ + cb``, in
    forward mode.
    """
    D0s, Dvs, J0s, bcol, bfix, grp, As, Bbs, cbs = cam
    P = theta.shape[0]
    p = c.copy()
    if D0s.shape[0] == 0:
        for k in need:
            acc = 0.0
            for j in range(P):
                acc += B[k, j] * theta[j]
            p[k] = c[k] + acc
        return p, B
    p = c + B @ theta
    dp = B.copy()
    for b in range(D0s.shape[0]):
        M = D0s[b].copy()
        for j in range(grp[b], grp[b + 1]):
            v = bfix[j] if bcol[j] < 0 else theta[bcol[j]]
            M += (v * bscale[j]) * Dvs[j]
        pn = M @ p
        for j in range(grp[b], grp[b + 1]):
            v = bfix[j] if bcol[j] < 0 else theta[bcol[j]]
            pn += J0s[:, j] * v
        dpn = M @ dp
        for j in range(grp[b], grp[b + 1]):
            if bcol[j] >= 0:
                dpn[:, bcol[j]] += bscale[j] * (Dvs[j] @ p) + J0s[:, j]
        p = As[b] @ pn + Bbs[b] @ theta + cbs[b]
        dp = As[b] @ dpn + Bbs[b]
    return p, dp


@njit(cache=True)
def _apply_directions(u, du, theta, dcol, dfix, dgrp):
    """``u' = u + Σ_e ((u + Σ_j v_j C_j) − u)`` (:meth:`StarModel.predict`'s order)."""
    if dcol.shape[0] == 0:
        return u
    out = u.copy()
    for e in range(dgrp.shape[0] - 1):
        for i in range(u.shape[0]):
            for a in range(3):
                s = u[i, a]
                for j in range(dgrp[e], dgrp[e + 1]):
                    v = dfix[j] if dcol[j] < 0 else theta[dcol[j]]
                    s += v * du[i, a, j]
                out[i, a] += s - u[i, a]
    return out


@njit(cache=True, error_model="numpy")
def predict_chain(theta, u_cat, R_b, phi, use_phi, w, base, s0, g, timed, R_prior, T, tracked,
                  c, B, need, dcol, dfix, dgrp, cam, du, bscale, jac, uv, d, H_att, H_par,
                  R_out):
    """:meth:`StarModel.predict` of a :class:`CompiledChain` (compiled).

    Parameters
    ----------
    theta : ndarray (P,)
        The model's parameters (estimated and consider).
    u_cat : ndarray (n, 3)
        Catalogue unit vectors.
    R_b, phi, use_phi, w, base
        The filter's attitude function (:func:`~stellar_cal_ros.methods.star_model.
        state_attitude`): ``R(s) = Exp(φ) R_b Exp(ω (s + base))`` (φ only if ``use_phi``;
        no rotation when ``|s + base| < 1e-12``).
    s0, g, timed, R_prior, T, tracked, c, B, need, dcol, dfix, dgrp, cam
        The :class:`CompiledChain`.
    du, bscale : ndarray (n, 3, kd), (kb,)
        The frame's DIRECTION columns and bilinear camera scales
        (:meth:`CompiledChain.frame_inputs`).
    jac : int
        1: also the Jacobians.
    uv, d : ndarray (n, 2), (n, 3)
        Outputs: centroids, px; directions in the tracker frame.
    H_att, H_par : ndarray (n, 2, 3), (n, 2, P)
        Outputs ``∂uv/∂φ``, ``∂uv/∂θ`` (with ``jac``).
    R_out : ndarray (2, 3, 3)
        Outputs ``R_i_b`` at the exposure and ``R_i_st``.
    """
    n, P = u_cat.shape[0], theta.shape[0]
    u = _apply_directions(u_cat, du, theta, dcol, dfix, dgrp)
    R_now = mat3_mul(so3_exp1(phi), R_b) if use_phi else R_b
    shift = s0
    if timed:
        acc = 0.0
        for j in range(P):
            acc += g[j] * theta[j]
        shift = s0 + acc
    dt = shift + base
    R = R_now if abs(dt) < 1e-12 else mat3_mul(R_now, so3_exp1(w * dt))
    delta = np.zeros(3)
    for a in range(3):
        acc = 0.0
        for j in range(P):
            acc += T[a, j] * theta[j]
        delta[a] = acc
    R_imu_st = mat3_mul(R_prior, so3_exp1(delta))
    R_i_st = mat3_mul(R, R_imu_st)
    R_out[0], R_out[1] = R, R_i_st
    for i in range(n):
        for j in range(3):
            d[i, j] = u[i, 0] * R_i_st[0, j] + u[i, 1] * R_i_st[1, j] + u[i, 2] * R_i_st[2, j]
    p, Bx = _camera_at(theta, c, B, need, cam, bscale)
    J_d = np.empty((n if jac else 0, 2, 3))
    J_p = np.empty((n if jac else 0, 2, 18))
    project_points(d, p, tilt_kernel(p[16], p[17]), jac, uv, J_d, J_p)
    if not jac:
        return
    Jr = jacobian1(delta, -1.0)
    for i in range(n):
        # attitude: J_d (R_st_i [u]×)
        S = skew3(u[i])
        A = np.empty((3, 3))
        for a in range(3):
            for b in range(3):
                A[a, b] = (R_i_st[0, a] * S[0, b] + R_i_st[1, a] * S[1, b]
                           + R_i_st[2, a] * S[2, b])
        for r in range(2):
            for b in range(3):
                H_att[i, r, b] = (J_d[i, r, 0] * A[0, b] + J_d[i, r, 1] * A[1, b]
                                  + J_d[i, r, 2] * A[2, b])
        # camera columns: J_p ∂p/∂θ
        for r in range(2):
            for j in range(P):
                acc = 0.0
                for k in need:
                    acc += J_p[i, r, k] * Bx[k, j]
                H_par[i, r, j] = acc
        # ∂uv/∂t ∂Δt/∂θ: ∂uv/∂t as J_d R_st_b [d_b]× ω, the same derivative as
        # covariance.stamp_column's H_att R_i_b ω (StarModel.predict's, the stamp column's) to
        # rounding; kept in this order: through it the last bits of every timed run
        # change (clean psce 300 s: time_offset's p 0.09522136181956352 -> ...262, H294)
        if timed:
            db = np.empty(3)
            for a in range(3):
                db[a] = u[i, 0] * R[0, a] + u[i, 1] * R[1, a] + u[i, 2] * R[2, a]
            cr = np.array([db[1] * w[2] - db[2] * w[1], db[2] * w[0] - db[0] * w[2],
                           db[0] * w[1] - db[1] * w[0]])
            for r in range(2):
                s = 0.0
                for a in range(3):
                    dd = (cr[0] * R_imu_st[0, a] + cr[1] * R_imu_st[1, a]
                          + cr[2] * R_imu_st[2, a])
                    s += J_d[i, r, a] * dd
                for j in range(P):
                    H_par[i, r, j] += s * g[j]
        if tracked:  # (J_d [d]×) Jr(δ) ∂δ/∂θ
            Sd = skew3(d[i])
            for r in range(2):
                e = np.empty(3)
                for b in range(3):
                    e[b] = (J_d[i, r, 0] * Sd[0, b] + J_d[i, r, 1] * Sd[1, b]
                            + J_d[i, r, 2] * Sd[2, b])
                f = np.empty(3)
                for b in range(3):
                    f[b] = e[0] * Jr[0, b] + e[1] * Jr[1, b] + e[2] * Jr[2, b]
                for j in range(P):
                    H_par[i, r, j] += f[0] * T[0, j] + f[1] * T[1, j] + f[2] * T[2, j]
        # DIRECTION columns of θ: J_d R_st_i ∂u/∂v
        for j in range(dcol.shape[0]):
            col = dcol[j]
            if col < 0:
                continue
            e = np.empty(3)
            for a in range(3):
                e[a] = (du[i, 0, j] * R_i_st[0, a] + du[i, 1, j] * R_i_st[1, a]
                        + du[i, 2, j] * R_i_st[2, a])
            for r in range(2):
                H_par[i, r, col] += (J_d[i, r, 0] * e[0] + J_d[i, r, 1] * e[1]
                                     + J_d[i, r, 2] * e[2])
