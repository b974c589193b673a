"""Star measurement model composed from effects: catalogue star → predicted centroid.

Shared by the PSCE Kalman filter, the batch (ACF) solver and the diagnosis tools.  The
chain, with the stage of each effect (see :mod:`stellar_cal_ros.effects.base`)::

    u_i'  = DIRECTION effects (u_i)                      inertial unit directions
    t_exp = stamp + Σ TIME effects                        (or the prior's time_offset)
    R_i_b = attitude(t_exp)                               from gyro propagation
    R_imu_st = R_prior · Exp(Σ TRACKER effects)
    d_st  = (R_i_b R_imu_st)ᵀ u_i'
    p     = CAMERA effects (prior camera parameters)
    uv    = camera(p).project(d_st)

Attitude error convention: a *left* perturbation in the inertial frame,
``R_i_b = Exp(φ) · R̂_i_b`` (Tan et al. eq. 7), so ``∂d_st/∂φ = R_st_i [u_i']×``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from stellar_cal_ros.core.camera import CameraModel
from stellar_cal_ros.core.rotation import right_jacobian, skew, so3_exp
from stellar_cal_ros.effects.base import CameraSetEffect, Effect, FrameContext, Stage
from stellar_cal_ros.errors import ModelError

AttitudeFunction = Callable[[float], tuple[np.ndarray, np.ndarray]]
"""``s -> (R_i_b (3, 3), omega_b (3,))``: nominal attitude and body rate ``s`` seconds after the
frame's reported stamp (``ctx.stamp``).  Relative, because float POSIX seconds resolve only
0.24 µs: ``(stamp + 0.02) − stamp`` is 0.02 ± 1e-7 s, 4e-5 px during a 5 °/s slew."""

_ZERO3 = np.zeros(3)


def state_attitude(R_i_b: np.ndarray, omega: np.ndarray, base: float,
                   phi: np.ndarray | None = None) -> AttitudeFunction:
    """The attitude function of a filter state: ``s -> (Exp(φ) R_i_b Exp(ω (s + base)), ω)``.

    ``R_i_b`` (3, 3) and the body rate ``omega`` (3,), rad/s, hold at the filter's time;
    ``base`` = frame stamp − filter time, s, so the attitude ``s`` seconds after the stamp
    is ``s + base`` after the state's (no rotation when ``|s + base| < 1e-12``); ``phi``
    (3,), optional, is a left attitude correction (relinearization).
    :func:`predict_chain` computes the same.
    """
    R_now = R_i_b if phi is None else so3_exp(phi) @ R_i_b

    def attitude(shift: float) -> tuple[np.ndarray, np.ndarray]:
        dt = shift + base
        R = R_now if abs(dt) < 1e-12 else R_now @ so3_exp(omega * dt)
        return R, omega

    return attitude


@dataclass
class Prediction:
    """Predicted centroids of one frame and their Jacobians."""

    uv: np.ndarray  # (n, 2) px
    H_attitude: np.ndarray | None  # (n, 2, 3) ∂uv/∂φ (None: not computed)
    H_parameters: np.ndarray | None  # (n, 2, P) ∂uv/∂θ
    directions_st: np.ndarray  # (n, 3)
    R_i_st: np.ndarray  # (3, 3)
    t_exposure: float
    camera: CameraModel | None  # None from the compiled chain (StarModel.predict_state)


class StarModel:
    """Parameter layout and measurement function of a set of effects.

    Parameters
    ----------
    effects : list of Effect
        In application order (:func:`stellar_cal_ros.effects.registry.create_many`).
    prior : Calibration
        Fixed values of everything not estimated, and starting values of what is.  This
        includes the prior's ``effects`` block: a registered DIRECTION or CAMERA effect
        found there (e.g. ``thermal_focal_length`` of an earlier result) and not estimated
        is applied with its prior value (:attr:`fixed_effects`), not dropped.
    """

    def __init__(self, effects: list[Effect], prior) -> None:
        self.effects = list(effects)
        self.prior = prior
        self.slices: dict[str, slice] = {}
        start = 0
        values, sigmas = [], []
        for eff in self.effects:
            v, s = eff.initial(prior)
            v, s = np.asarray(v, dtype=float), np.asarray(s, dtype=float)
            if v.shape != (eff.size,) or s.shape != (eff.size,):
                raise ModelError(f"effect {eff.id}: initial value/sigma must have {eff.size} "
                                 f"entries, got {v.shape} and {s.shape}")
            self.slices[eff.id] = slice(start, start + eff.size)
            start += eff.size
            values.append(v)
            sigmas.append(s)
        self.size = start
        self.initial_value = np.concatenate(values) if values else np.zeros(0)
        self.initial_sigma = np.concatenate(sigmas) if sigmas else np.zeros(0)
        self._camera_prior = prior.camera.parameters()
        self._camera_cols_cache: tuple[Any, Any, Any] | None = None  # see _camera_columns
        self._R_imu_st_prior = prior.R_imu_st  # cached: scipy is slow per call
        self._by_stage = {st: [e for e in self.effects if e.stage is st] for st in Stage}
        self.fixed_effects: list[tuple[Effect, np.ndarray]] = self._fixed_effects(prior)
        # DIRECTION and CAMERA chains: (effect, slice of θ or None, fixed value or None)
        self._chain = {st: self._stage_chain(st) for st in (Stage.DIRECTION, Stage.CAMERA)}
        self._camera_copy = self._camera_copy_plan()
        #: (∂p/∂θ, column mask, focal-length ratios) of that plan, from the general chain
        self._camera_copy_cols: tuple[Any, Any, list] | None = None
        self.has_time_effect = bool(self._by_stage[Stage.TIME])
        self._gyro_fixed = self._fixed_sensor(Stage.GYRO, prior.gyro_bias,
                                              prior.gyro_error_matrix)
        self._accel_fixed = self._fixed_sensor(Stage.ACCEL, prior.accel_bias,
                                               prior.accel_error_matrix)
        self._compiled: Any = False  # see compiled_chain (False: not built yet)

    def _fixed_effects(self, prior) -> list[tuple[Effect, np.ndarray]]:
        from stellar_cal_ros.effects import registry

        estimated = {e.id for e in self.effects}
        out = []
        for eid in (getattr(prior, "effects", None) or {}):
            if eid in estimated or eid not in registry.EFFECTS:
                continue
            eff = registry.create(eid)
            if eff.stage not in (Stage.DIRECTION, Stage.CAMERA):
                continue  # other stages have their own blocks in the calibration
            value, _ = eff.initial(prior)
            out.append((eff, np.asarray(value, dtype=float)))
        return out

    def _stage_chain(self, stage: Stage) -> list[tuple[Effect, slice | None, np.ndarray | None]]:
        chain = [(e, self.slices[e.id], None) for e in self._by_stage[stage]]
        fixed = [(e, None, v) for e, v in self.fixed_effects if e.stage is stage]
        if not fixed:
            return chain
        from stellar_cal_ros.effects.registry import order_key

        return sorted(chain + fixed, key=lambda c: order_key(type(c[0])))

    def _camera_copy_plan(self) -> tuple[np.ndarray, np.ndarray, list] | None:
        """The camera chain as one copy ``p[dst] = θ[src] · scale``, when it is one.

        True when every camera effect is estimated and either sets OpenCV entries from θ
        (:class:`CameraSetEffect` as is) or is the focal length (``fx = f``, ``fy = f ·
        ratio``), each entry written once: the chain then does exactly these assignments
        (a product by 1.0 is exact), without an 18-vector copy and two Jacobian look-ups
        per effect per frame.  None otherwise (the general chain).
        """
        from stellar_cal_ros.effects.base import FX, FY
        from stellar_cal_ros.effects.focal_length import FocalLength

        dst, src, scale = [], [], []
        for eff, sl, fixed in self._chain[Stage.CAMERA]:
            if sl is None or fixed is not None:
                return None
            if type(eff).camera_parameters is CameraSetEffect.camera_parameters:
                idx = eff._index()
                dst += idx
                src += list(range(sl.start, sl.start + len(idx)))
                scale += [None] * len(idx)
            elif type(eff) is FocalLength:
                dst += [FX, FY]
                src += [sl.start, sl.start]
                scale += [None, eff]  # eff.ratio, read at each call
            else:
                return None
        if not dst or len(set(dst)) != len(dst):
            return None
        return np.array(dst, dtype=np.intp), np.array(src, dtype=np.intp), scale

    def _camera_vector(self, theta: np.ndarray) -> np.ndarray:
        """Camera parameters of ``theta`` by :attr:`_camera_copy` (see there)."""
        dst, src, scale = self._camera_copy
        v = theta[src]
        for j, eff in enumerate(scale):
            if eff is not None:
                v[j] = v[j] * eff.ratio
        p = self._camera_prior.copy()
        p[dst] = v
        return p

    @staticmethod
    def _value(theta: np.ndarray, sl: slice | None, fixed: np.ndarray | None) -> np.ndarray:
        return fixed if sl is None else theta[sl]

    # ------------------------------------------------------------------ names
    def parameter_names(self) -> list[str]:
        """``effect.parameter`` names of θ, in order."""
        return [f"{e.id}.{n}" for e in self.effects for n in e.parameter_names]

    def value_of(self, theta: np.ndarray, effect_id: str) -> np.ndarray:
        """The slice of ``theta`` owned by ``effect_id``."""
        return theta[self.slices[effect_id]]

    # ------------------------------------------------------------------ sensors
    def _fixed_sensor(self, stage: Stage, bias, matrix) -> tuple[np.ndarray, np.ndarray]:
        """Prior bias / matrix entries that no estimated effect of ``stage`` owns."""
        b = np.array(bias, dtype=float)
        E = np.array(matrix, dtype=float)
        for eff in self._by_stage[stage]:
            zero = np.zeros(eff.size)
            if np.any(eff.sensor_bias_jacobian(zero)):
                b[:] = 0.0
            owned = np.any(eff.sensor_matrix_jacobian(zero) != 0, axis=2)
            E[owned] = 0.0
        return b, E

    def sensor_model(
        self, theta: np.ndarray, stage: Stage = Stage.GYRO
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Bias b, matrix E and their Jacobians (3, P), (3, 3, P) for a sensor stage."""
        b, E = (self._gyro_fixed if stage is Stage.GYRO else self._accel_fixed)
        b, E = b.copy(), E.copy()
        Jb = np.zeros((3, self.size))
        JE = np.zeros((3, 3, self.size))
        for eff in self._by_stage[stage]:
            sl = self.slices[eff.id]
            v = theta[sl]
            b += eff.sensor_bias(v)
            E += eff.sensor_matrix(v)
            Jb[:, sl] = eff.sensor_bias_jacobian(v)
            JE[:, :, sl] = eff.sensor_matrix_jacobian(v)
        return b, E, Jb, JE

    def corrected_rates(self, theta: np.ndarray, measured: np.ndarray,
                        stage: Stage = Stage.GYRO) -> np.ndarray:
        """``(I + E)⁻¹ (w_meas − b)`` for samples (N, 3)."""
        b, E, _, _ = self.sensor_model(theta, stage)
        if not np.any(E):
            return measured - b
        return np.linalg.solve(np.eye(3) + E, (measured - b).T).T

    # ------------------------------------------------------------------ stars
    def exposure_shift(self, theta: np.ndarray,
                       ctx: FrameContext | Callable[[], FrameContext]) -> float:
        """:meth:`time_shift`'s value alone (a frame's update needs no gradient).

        ``ctx`` may be a function that builds the frame's context: it is called only when a
        time effect needs it (the driver's look-ahead builds none without one).
        """
        if not self.has_time_effect:
            return float(self.prior.time_offset)
        return self.time_shift(theta, ctx() if callable(ctx) else ctx)[0]

    def fixed_exposure_shift(self, theta: np.ndarray, n_estimated: int) -> float | None:
        """The exposure shift of every frame of a filter that estimates ``θ[:n_estimated]``.

        A filter keeps its consider parameters (the trailing entries) at their values: with
        no TIME effect (the prior's offset), or TIME effects whose shift is a constant map of
        their value (:meth:`Effect.affine_form`: no frame dependence) and whose parameters
        are all consider, every frame's :meth:`exposure_shift` is this same float (from
        ``theta``, the filter's nominal θ).  None when the shift can change between frames
        (an estimated or frame-dependent TIME effect).
        """
        if not self.has_time_effect:
            return float(self.prior.time_offset)
        for eff in self._by_stage[Stage.TIME]:
            if eff.affine_form() is None or self.slices[eff.id].start < n_estimated:
                return None
        return self.exposure_shift(theta, None)

    def affine_exposure_shift(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(index, gain)`` with :meth:`exposure_shift` ``= Σ_q gain[q] θ[index[q]]``, or None.

        For TIME effects that are all constant affine maps of their values
        (:meth:`Effect.affine_form`: no frame dependence), summed from 0.0 in the model's
        order, as :meth:`time_shift` sums them; None without a TIME effect (the prior's
        offset) or with one that is not such a map.  The compiled batch computes an
        estimated offset's exposure times with it (``frame_step.frame_steps``).
        """
        if not self.has_time_effect:
            return None
        index: list[int] = []
        gain: list[float] = []
        for eff in self._by_stage[Stage.TIME]:
            g = eff.affine_form()
            if g is None:
                return None
            start = self.slices[eff.id].start
            for q, v in enumerate(np.asarray(g, dtype=float).reshape(-1).tolist()):
                if v != 0.0:
                    index.append(start + q)
                    gain.append(v)
        return np.array(index, dtype=np.int64), np.array(gain, dtype=float)

    def time_shift(self, theta: np.ndarray, ctx: FrameContext) -> tuple[float, np.ndarray]:
        """Seconds from the stamp to the modelled exposure, and its gradient (P,)."""
        if not self.has_time_effect:
            return float(self.prior.time_offset), np.zeros(self.size)
        dt, grad = 0.0, np.zeros(self.size)
        for eff in self._by_stage[Stage.TIME]:
            sl = self.slices[eff.id]
            dt += eff.time_shift(theta[sl], ctx)
            grad[sl] = eff.time_shift_jacobian(theta[sl], ctx)
        return dt, grad

    def camera_parameters_at(self, theta: np.ndarray, ctx: FrameContext) -> np.ndarray:
        """The camera's parameter vector in the frame's context (the CAMERA stage's chain)."""
        p = self._camera_prior
        for eff, sl, fixed in self._chain[Stage.CAMERA]:
            p = eff.camera_parameters(self._value(theta, sl, fixed), p, ctx)
        return p

    def camera_at(self, theta: np.ndarray, ctx: FrameContext) -> CameraModel:
        """Camera model of the current parameters in the frame's context."""
        return self.prior.camera.with_parameters(self.camera_parameters_at(theta, ctx))

    def tracker_delta(self, theta: np.ndarray, ctx: FrameContext) -> np.ndarray:
        """The TRACKER stage's rotation δ (3,) in the frame's context, summed over its effects."""
        delta = np.zeros(3)
        for eff in self._by_stage[Stage.TRACKER]:
            delta = delta + eff.tracker_rotation(theta[self.slices[eff.id]], ctx)
        return delta

    def installation_at(
        self, theta: np.ndarray, ctx: FrameContext
    ) -> tuple[np.ndarray, np.ndarray]:
        """``R_imu_st`` and the summed tracker rotation δ."""
        delta = self.tracker_delta(theta, ctx)
        return self._R_imu_st_prior @ so3_exp(delta), delta

    def predict(
        self,
        theta: np.ndarray,
        u_i: np.ndarray,
        ctx: FrameContext,
        attitude: AttitudeFunction,
        jacobians: bool = True,
    ) -> Prediction:
        """Predicted centroids and Jacobians for catalogue directions ``u_i`` (n, 3).

        ``jacobians=False`` computes the centroids only (the simulator renders the truth
        through this same chain); the Jacobian fields are then None.
        """
        P = self.size
        n = len(u_i)
        # DIRECTION stage
        u = np.asarray(u_i, dtype=float)
        dir_jac: list[tuple[slice, np.ndarray]] = []
        for eff, sl, fixed in self._chain[Stage.DIRECTION]:
            v = self._value(theta, sl, fixed)
            if sl is not None and jacobians:
                dir_jac.append((sl, eff.directions_jacobian(v, u_i, ctx)))
            # corrections are computed on the catalogue direction and add up
            u = u + (eff.directions(v, u_i, ctx) - u_i)
        # TIME stage and attitude
        shift, shift_grad = self.time_shift(theta, ctx)
        t_exp = ctx.stamp + shift
        R_i_b, omega_b = attitude(shift)
        ctx.R_i_b, ctx.omega_b = R_i_b, omega_b
        # TRACKER stage
        R_imu_st, delta = self.installation_at(theta, ctx)
        R_i_st = R_i_b @ R_imu_st
        ctx.R_i_st = R_i_st
        d = u @ R_i_st  # rows R_st_i u
        # CAMERA stage
        p = self._camera_prior
        fast = self._camera_copy is not None
        if not jacobians:
            p = self._camera_vector(theta) if fast else self.camera_parameters_at(theta, ctx)
            camera = self.prior.camera.with_parameters(p)
            return Prediction(camera.project(d), None, None, d, R_i_st, t_exp, camera)
        cols = self._camera_copy_cols if fast else None
        if cols is not None and cols[2] == [e.ratio for e in self._camera_copy[2] if e]:
            p = self._camera_vector(theta)
            cam_M, need = cols[0], cols[1]
        else:
            cam_steps = []
            for eff, sl, fixed in self._chain[Stage.CAMERA]:
                v = self._value(theta, sl, fixed)
                J, D = eff.camera_jacobian(v, p, ctx)
                cam_steps.append((sl, J, D))
                p = eff.camera_parameters(v, p, ctx)
            cam_M, need = self._camera_columns(cam_steps)
            if fast:  # constant Jacobians of the copy plan (for this focal-length ratio)
                self._camera_copy_cols = (cam_M, need,
                                          [e.ratio for e in self._camera_copy[2] if e])
        camera = self.prior.camera.with_parameters(p)
        uv, J_d, J_p = camera.project(d, jacobians=True, parameters=need)

        # Jacobians
        R_st_i = R_i_st.T
        H_att = J_d @ (R_st_i @ skew(u))  # (n,2,3)
        # camera columns first (one product for all camera effects), then the others add
        H = J_p @ cam_M if cam_M is not None else np.zeros((n, 2, P))
        for sl, Ju in dir_jac:  # ∂d/∂θ = R_st_i ∂u/∂θ
            H[:, :, sl] += np.einsum("nij,jk,nkl->nil", J_d, R_st_i, Ju)
        if self.has_time_effect and np.any(shift_grad):
            d_b = u @ R_i_b
            # ∂uv/∂t = J_d R_st_b [d_b]× ω: covariance.stamp_column's H_att R_i_b ω to rounding,
            # kept in this order (through it the last bits of every run through here
            # change: unseen smear15 s21's diagnosis.json, H294)
            dd_dt = (np.cross(d_b, omega_b)) @ R_imu_st  # R_st_b [d_b]× ω
            H += np.einsum("nij,nj->ni", J_d, dd_dt)[:, :, None] * shift_grad[None, None, :]
        if self._by_stage[Stage.TRACKER]:
            Jr = right_jacobian(delta)
            Jd_skew = (J_d @ skew(d)) @ Jr  # (n,2,3)
            for eff in self._by_stage[Stage.TRACKER]:
                sl = self.slices[eff.id]
                H[:, :, sl] += Jd_skew @ eff.tracker_rotation_jacobian(theta[sl], ctx)
        return Prediction(uv, H_att, H, d, R_i_st, t_exp, camera)

    def predict_frames(
        self,
        theta: np.ndarray,
        u_i: list[np.ndarray] | np.ndarray,
        ctxs: list[FrameContext] | Callable[[], list[FrameContext]],
        attitudes: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
        counts: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`predict`'s centroids (``jacobians=False``) of many frames at once.

        ``u_i``: each frame's catalogue directions (n_j, 3), or with ``counts`` (F,) every
        frame's stacked (N, 3), ``counts[j]`` rows each; ``ctxs``: their contexts, or a
        function that makes that list, asked only where a stage reads the frames' contexts
        (a DIRECTION or TIME stage, a TRACKER effect without a constant affine form, a
        camera chain that is not a plain copy; the psce twin's reads none: ~0.2 CPU-s a
        2-h bag's render for 14 400 contexts); ``attitudes``: ``shifts (F,) -> (R_i_b (F,
        3, 3), ω_b (F, 3))``, each frame's attitude function (:data:`AttitudeFunction`)
        evaluated at its own shift.  Returns ``uv`` (N, 2) and ``directions_st`` (N, 3) of
        every star, frame after frame.

        The same chain as :meth:`predict` in array operations over all frames (the twin's
        render, :func:`~stellar_cal_ros.diagnosis.twin.make_twin`: ~0.2 ms of Python per
        frame per call before); a stage whose effects take the frame's context (DIRECTION,
        TIME, TRACKER, a camera chain that is not a plain copy) still calls them per frame,
        and the projection groups the frames by camera.  A TRACKER stage whose effects all
        have a constant affine form (:meth:`~stellar_cal_ros.effects.base.Effect.
        affine_form`: the same δ in every context, the installation's) is asked once, with
        no context (``ctx`` None).  The same numbers to rounding (``test_star_model``).
        Like :meth:`predict` it sets each context's motion (``R_i_b``, ``omega_b`` before
        the TRACKER stage, ``R_i_st`` before the CAMERA stage): of every context, made.
        """
        if counts is None:
            F = len(u_i)
            counts = np.array([len(u) for u in u_i], dtype=np.intp)
            u0 = np.concatenate([np.asarray(u, dtype=float).reshape(-1, 3) for u in u_i]) \
                if F else np.zeros((0, 3))
        else:
            counts = np.asarray(counts, dtype=np.intp)
            F = len(counts)
            u0 = np.asarray(u_i, dtype=float).reshape(-1, 3)
            ends = np.cumsum(counts).tolist()
            u_i = [u0[e - k:e] for e, k in zip(ends, counts.tolist(), strict=True)]
        if F == 0:
            return np.zeros((0, 2)), np.zeros((0, 3))
        made: list[FrameContext] | None = None if callable(ctxs) else ctxs

        def contexts() -> list[FrameContext]:
            nonlocal made
            if made is None:
                made = list(ctxs())
            return made

        rows = np.repeat(np.arange(F), counts)
        # DIRECTION stage (per frame: the corrections take the frame's context)
        if self._chain[Stage.DIRECTION]:
            parts = []
            for uj, ctx in zip(u_i, contexts(), strict=True):
                uj = np.asarray(uj, dtype=float)
                u = uj
                for eff, sl, fixed in self._chain[Stage.DIRECTION]:
                    u = u + (eff.directions(self._value(theta, sl, fixed), uj, ctx) - uj)
                parts.append(u.reshape(-1, 3))
            u = np.concatenate(parts)
        else:
            u = u0
        # TIME stage and attitude
        if self.has_time_effect:
            shifts = np.array([self.time_shift(theta, ctx)[0] for ctx in contexts()])
        else:
            shifts = np.full(F, float(self.prior.time_offset))
        R_i_b, omega_b = attitudes(shifts)
        # the contexts' motion, as :meth:`predict` sets it before the TRACKER stage (an
        # effect there, or in the CAMERA stage, may read it: a plugin's rate-dependent
        # mount; left unset, the twin's frames gave it the identity and zero rate)
        tracker = self._by_stage[Stage.TRACKER]
        constant = all(eff.affine_form() is not None for eff in tracker)
        if not constant or self._camera_copy is None:
            contexts()
        for j, ctx in enumerate(made or ()):
            ctx.R_i_b, ctx.omega_b = R_i_b[j], omega_b[j]
        # TRACKER stage
        if tracker and constant:  # the same δ in every context
            R_imu_st = self._R_imu_st_prior @ so3_exp(
                np.array(self.tracker_delta(theta, None), dtype=float).reshape(3))
        elif tracker:
            deltas = np.array([self.tracker_delta(theta, ctx) for ctx in made],
                              dtype=float).reshape(F, 3)
            if np.all(deltas == deltas[0]):
                R_imu_st = self._R_imu_st_prior @ so3_exp(deltas[0])
            else:
                R_imu_st = self._R_imu_st_prior @ so3_exp(deltas)
        else:
            R_imu_st = self._R_imu_st_prior @ so3_exp(np.zeros(3))
        R_i_st = R_i_b @ R_imu_st
        for j, ctx in enumerate(made or ()):
            ctx.R_i_st = R_i_st[j]
        d = np.matmul(u[:, None, :], R_i_st[rows])[:, 0, :]  # rows R_st_i u
        # CAMERA stage: one projection per distinct camera
        if self._camera_copy is not None:
            return self.prior.camera.with_parameters(self._camera_vector(theta)).project(d), d
        ps = np.array([self.camera_parameters_at(theta, ctx) for ctx in made])
        cams, which = np.unique(ps, axis=0, return_inverse=True)
        which = np.asarray(which).reshape(-1)[rows]
        uv = np.empty((len(d), 2))
        for c, p in enumerate(cams):
            at = which == c
            uv[at] = self.prior.camera.with_parameters(p).project(d[at])
        return uv, d

    def prepare_frames(self, data: Any) -> None:
        """Let the DIRECTION effects compute their corrections for a whole bag at once.

        ``data``: a :class:`~stellar_cal_ros.methods.frames.BagData` about to be replayed.
        An effect with a ``prepare`` method (the astrometric ones,
        :meth:`~stellar_cal_ros.effects._direction.ScaledDirection.prepare`) computes every
        identified star's correction in one call; each frame then looks its stars up
        instead of calling pyerfa (frames whose context differs are computed as before).
        """
        effs = [e for e, _, _ in self._chain[Stage.DIRECTION] if hasattr(e, "prepare")]
        if not effs or not data.frames:
            return
        # made once per bag in memory and effect class (:attr:`BagData.prepared`): a
        # diagnosis round replays the same bag with the same direction effects several
        # times (the screening run, the candidate's re-run; ≈ 2 CPU-s each on a 2-h bag)
        made = data.prepared_for((id(data.frames), len(data.frames), data.site,
                                  id(data.pressure), id(data.air_temperature)))
        todo = []
        for eff in effs:
            if hasattr(eff, "use_prepared") and type(eff) in made:
                eff.use_prepared(made[type(eff)])
            else:
                todo.append(eff)
        if not todo:
            return
        if "inputs" not in made:
            from stellar_cal_ros.core.catalog import radec_to_unit
            from stellar_cal_ros.effects._direction import Stacked

            env = data.env()
            frames = data.frames
            stamps = np.array([f.stamp_ns for f in frames], dtype=np.int64)
            # every frame's stars in columns (one conversion to directions for the bag; the
            # same floats as frame by frame: elementwise), those with finite RA and Dec
            n = np.array([len(f.catalog_id) for f in frames], dtype=np.int64)
            ra, dec = (np.concatenate([np.zeros(0)] + [np.asarray(getattr(f, name),
                                                                  dtype=float).reshape(-1)
                                                       for f in frames])
                       for name in ("right_ascension", "declination"))
            if len(ra) != n.sum() or len(dec) != n.sum():
                raise IndexError("a star message's right ascension, declination and ids "
                                 "differ in length")
            ok = np.isfinite(ra) & np.isfinite(dec)
            ids = np.concatenate([np.zeros(0, np.int64)] + [
                np.asarray(f.catalog_id, dtype=np.int64).reshape(-1) for f in frames])[ok]
            seen = np.zeros(len(ok) + 1, dtype=np.int64)  # the finite stars before each row
            np.cumsum(ok, out=seen[1:])
            ends = np.cumsum(n)
            counts = seen[ends] - seen[ends - n]
            # the stars stacked once, shared by every effect's table (not a copy each)
            made["inputs"] = (Stacked(stamps * 1e-9, ids, radec_to_unit(ra[ok], dec[ok]),
                                      env["pressure"].interp(stamps), env["air"].interp(stamps),
                                      counts=counts), data.site)
            del ids, ra, dec, ok
        for eff in todo:
            eff.prepare_stacked(*made["inputs"])
            if hasattr(eff, "prepared_table"):
                made[type(eff)] = eff.prepared_table()

    def compiled_chain(self) -> Any:
        """The star chain in compiled form (:mod:`~stellar_cal_ros.methods.star_chain`).

        Built on first use (it imports numba); None without numba or when an effect has no
        affine form.
        """
        if self._compiled is False:
            from stellar_cal_ros.methods.star_chain import compile_chain

            self._compiled = compile_chain(self)
        return self._compiled

    def predict_state(self, theta: np.ndarray, u_i: np.ndarray, ctx: FrameContext,
                      R_i_b: np.ndarray, omega: np.ndarray, base: float,
                      phi: np.ndarray | None = None, jacobians: bool = True,
                      compiled: bool = True) -> Prediction:
        """:meth:`predict` with a filter state's attitude (:func:`state_attitude`).

        Through :func:`~stellar_cal_ros.methods.star_chain.predict_chain` (one compiled
        call) when the model has a :meth:`compiled_chain` and ``compiled`` is True; through
        the effects' methods otherwise — the same numbers to rounding
        (``Prediction.camera`` is None from the compiled chain).
        """
        ch = self.compiled_chain() if compiled else None
        if ch is None:
            return self.predict(theta, u_i, ctx, state_attitude(R_i_b, omega, base, phi),
                                jacobians)
        from stellar_cal_ros.methods.star_chain import predict_chain
        u = np.ascontiguousarray(u_i, dtype=float)
        n, P = len(u), self.size
        uv, d, R_out = np.empty((n, 2)), np.empty((n, 3)), np.empty((2, 3, 3))
        jac = 1 if jacobians else 0
        H_att, H_par = np.empty((n * jac, 2, 3)), np.empty((n * jac, 2, P))
        predict_chain(np.ascontiguousarray(theta, dtype=float), u,
                      np.ascontiguousarray(R_i_b, dtype=float),
                      _ZERO3 if phi is None else np.ascontiguousarray(phi, dtype=float),
                      phi is not None, np.ascontiguousarray(omega, dtype=float), float(base),
                      ch.s0, ch.g, ch.timed, ch.R_prior, ch.T, ch.tracked, ch.c, ch.B, ch.need,
                      ch.dcol, ch.dfix, ch.dgrp, ch.cam, *ch.frame_inputs(u, ctx),
                      jac, uv, d, H_att, H_par, R_out)
        ctx.R_i_b, ctx.omega_b, ctx.R_i_st = R_out[0], omega, R_out[1]
        shift = ch.s0 + float(ch.g @ theta) if ch.timed else ch.s0
        return Prediction(uv, H_att if jacobians else None, H_par if jacobians else None, d,
                          R_out[1], ctx.stamp + shift, None)

    def _camera_columns(self, steps: list[tuple[slice | None, np.ndarray, np.ndarray]]
                        ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """``∂p/∂θ`` (18, P) of the camera chain, and the camera parameters it uses.

        Column block of each estimated camera effect: ``A J`` with ``A`` the product of
        the later steps' ``D`` (None without camera effects); the mask of the parameters
        with a nonzero row (the projection computes only those Jacobian columns; None:
        all).  Effects with constant Jacobians (the parameter-setting ones) return the
        same arrays every call: the result is reused while every step's arrays are the
        same objects.
        """
        c = self._camera_cols_cache
        if c is not None and len(c[0]) == len(steps) and all(
                a[0] == b[0] and a[1] is b[1] and a[2] is b[2]
                for a, b in zip(c[0], steps, strict=True)):
            return c[1], c[2]
        A = np.eye(18)
        cols = []
        for sl, J, D in reversed(steps):
            if sl is not None:  # a fixed effect has no column but passes p on (D)
                cols.append((sl, A @ J))
            A = A @ D
        M_all = np.zeros((18, self.size)) if cols else None
        for sl, M in cols:
            M_all[:, sl] = M
        need = np.any(M_all != 0.0, axis=1) if cols else np.ones(18, dtype=bool)
        mask = None if need.all() else need
        self._camera_cols_cache = (list(steps), M_all, mask)  # holds the arrays compared
        return M_all, mask
