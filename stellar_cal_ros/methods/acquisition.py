"""Acquisition and re-acquisition of a star filter's attitude, and the gyro-against-stars watch.

The part of :class:`~stellar_cal_ros.methods.kernel.StarFilter` that sets the state from one
frame (:class:`Acquisition`, a mixin of the kernel's filter):

* :meth:`Acquisition.initialize`: the attitude from one frame by a pixel-space Wahba fit
  under the current model, with the initial attitude error correlated with θ exactly as the
  fit makes it (``φ₀ = −M δθ + r + noise``), and the navigation blocks set by the method;
* :meth:`Acquisition.reacquire` after an IMU gap or a lost lock: the navigation blocks are
  cleared and set again from a frame, θ and its covariance are kept;
* :meth:`Acquisition._watch_gyro`: the gyro's own rotation between frames against the
  stars' (:mod:`~stellar_cal_ros.core.gyro_check`).
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from stellar_cal_ros.core import gyro_check
from stellar_cal_ros.core.attitude import fit_frame_attitude, refine_frame_rotation, wahba
from stellar_cal_ros.core.rotation import so3_log
from stellar_cal_ros.effects.base import FrameContext
from stellar_cal_ros.errors import DataError, ModelError

log = logging.getLogger("stellar_cal_ros.methods.kernel")


class Acquisition:
    """Acquisition, re-acquisition and the gyro watch of a :class:`StarFilter` (mixin)."""

    def initialize(self, uv: np.ndarray, u_i: np.ndarray, ctx: FrameContext,
                   sigma: np.ndarray) -> bool:
        """Acquire the attitude (and navigation) from one frame; False if it cannot.

        The frame fit under the current model gives ``φ₀ = −M δθ`` to first order, with
        ``M = (H_φᵀ H_φ)⁻¹ H_φᵀ H_θ`` (a principal-point offset is indistinguishable from an
        attitude tilt in one frame), plus the centroid noise ``σ² (H_φᵀ H_φ)⁻¹`` and the
        second moment of the second-order remainder in δθ
        (:meth:`_init_second_order`).
        """
        model, theta, c = self.model, self.theta, self.config
        shift, _ = model.time_shift(theta, ctx)
        t_exp = self._stamp_rel + shift
        imu_t = self.imu.t
        if not len(imu_t) or t_exp <= imu_t[0] - self.nominal_dt or t_exp >= imu_t[-1]:
            self.counters.skipped_no_imu += 1
            return False
        if self.t is not None and t_exp < self.t - 1e-9:
            return False
        camera = model.camera_at(theta, ctx)
        R_imu_st, _ = model.installation_at(theta, ctx)
        keep = wahba_inliers(camera, uv, u_i, c.init_outlier_px)
        fit = None
        for _ in range(3):
            if keep.sum() < max(c.min_stars, 3):
                return False
            try:
                R0 = wahba(camera.unproject(uv[keep]), u_i[keep])
                fit = fit_frame_attitude(camera, uv[keep], u_i[keep], R_i_st0=R0)
            except (ModelError, np.linalg.LinAlgError, ValueError) as exc:
                log.warning("attitude fit failed at t=%.3f s: %s", t_exp, exc)
                return False
            err = np.linalg.norm(fit.residuals, axis=1)
            if not np.all(np.isfinite(err)):
                return False
            bad = err > max(c.init_outlier_px, 5 * float(np.median(err)))
            if not np.any(bad):
                break
            idx = np.flatnonzero(keep)
            keep[idx[bad]] = False
        R_i_b = fit.R_i_st @ R_imu_st.T
        self.t = t_exp
        self._k = self.imu.index(t_exp)
        self.R_i_b = R_i_b
        self.omega = self.rate_at(t_exp)
        idx = np.flatnonzero(keep)
        pred = self._predict(theta, u_i[keep], subset_context(ctx, idx))
        Hf = pred.H_attitude.reshape(-1, 3)
        Ht_all = pred.H_parameters.reshape(-1, model.size)
        Ht = Ht_all[:, :self.P_est]
        info = Hf.T @ Hf
        if not np.all(np.isfinite(info)) or np.linalg.cond(info) > 1e12:
            return False
        M = np.linalg.solve(info, Hf.T @ Ht) if self.P_est else np.zeros((3, 0))
        s2 = float(np.mean(sigma[keep] ** 2))
        ia, it = self.ia, self.it
        Ptt = self.P[it, it]
        Q2 = self._init_second_order(uv[keep], u_i[keep], ctx, fit.R_i_st, R_i_b, M, Ht) \
            if self.P_est and c.init_second_order else 0.0
        self.state.assign(ia, ia, M @ Ptt @ M.T + s2 * np.linalg.inv(info) + Q2)
        self.state.assign(ia, it, -M @ Ptt)
        if self.sensitivity is not None:
            self.sensitivity.clear_rows(self.layout.navigation_index)
            self.sensitivity.set_rows(ia, -np.linalg.solve(info, Hf.T @ Ht_all[:, self.P_est:]))
        self._acquire_navigation(t_exp)
        self.counters.init_frames += 1
        self._rejected_in_row = 0
        self._good = self._snapshot()
        log.info("attitude initialized at t=%.3f s from %d stars", t_exp, int(keep.sum()))
        return True

    def _init_second_order(self, uv: np.ndarray, u_i: np.ndarray, ctx: FrameContext,
                           R_i_st: np.ndarray, R_i_b: np.ndarray, M: np.ndarray,
                           Ht: np.ndarray) -> np.ndarray:
        """Second moment of the second-order part of the initial attitude error.

        The frame fit under the current model gives ``φ₀ = −M δθ`` only to first order in
        δθ; with datasheet priors (pixels of principal point, 0.2° of installation) the
        quadratic remainder ``r = ½ yᵀ H y`` (``δθ = L y``, ``L Lᵀ = P_θθ``, y ~ N(0, I))
        is some 10 µrad, far above the centroid-noise term of a 0.005-px tracker; ignoring
        it makes the filter start, and with little process noise stay, overconfident.
        H is measured by refitting the frame under ``θ̂ + δ`` for ``δ = ±L_j`` and
        ``L_j + L_k``: ``e_j = ½ H_jj`` is the even part along ``L_j`` and ``H_jk =
        r(L_j + L_k) − e_j − e_k``.  Then ``E r = Σ e_j`` and
        ``Cov r = 2 Σ e_j e_jᵀ + Σ_{j<k} H_jk H_jkᵀ`` (exact for a quadratic r).
        """
        model, theta, P_est = self.model, self.theta, self.P_est
        Ptt = self.P[self.it, self.it]
        try:
            L = np.linalg.cholesky(Ptt)
        except np.linalg.LinAlgError:
            w, V = np.linalg.eigh(Ptt)
            L = V * np.sqrt(np.clip(w, 0.0, None))
        # columns that do not move the stars of one frame (gyro bias) contribute nothing
        HL = np.linalg.norm(Ht @ L, axis=0)
        cols = np.flatnonzero(HL > 1e-9 * (1.0 + HL.max()))

        def remainder(delta: np.ndarray) -> np.ndarray | None:
            th = theta.copy()
            th[:P_est] += delta
            R_imu_st, _ = model.installation_at(th, ctx)
            try:
                # the rotation only: no residuals or covariance at the refit
                R_fit, _, _ = refine_frame_rotation(model.camera_at(th, ctx), uv, u_i,
                                                    R_i_st, max_iterations=2)
            except (ModelError, np.linalg.LinAlgError, ValueError):
                return None
            phi = so3_log((R_fit @ R_imu_st.T) @ R_i_b.T) + M @ delta
            return phi if np.all(np.isfinite(phi)) else None

        e = {}
        for j in cols:
            rp, rm = remainder(L[:, j]), remainder(-L[:, j])
            if rp is not None and rm is not None:
                e[j] = 0.5 * (rp + rm)
        if not e:
            return np.zeros((3, 3))
        mean = sum(e.values())
        Q = 2.0 * sum(np.outer(v, v) for v in e.values())
        keys = sorted(e)
        for a, j in enumerate(keys):
            for k in keys[a + 1:]:
                r = remainder(L[:, j] + L[:, k])
                if r is not None:
                    h = r - e[j] - e[k]
                    Q = Q + np.outer(h, h)
        return Q + np.outer(mean, mean)

    def reacquire(self, uv: np.ndarray, u_i: np.ndarray, ctx: FrameContext,
                  sigma: np.ndarray) -> bool:
        """Re-acquire the navigation blocks from a frame; keep θ and its covariance.

        After an IMU gap or a lost lock the nominal attitude (and velocity, position) carry
        errors the covariance does not describe; updating them would pull θ.  Their rows and
        columns of P are cleared and :meth:`initialize` sets them as at the start.
        False (state unchanged) if the frame cannot align.
        """
        saved = self._snapshot(full=True)
        self.state.forget(self.layout.navigation_index)
        if not self.initialize(uv, u_i, ctx, sigma):
            self._restore(saved)
            return False
        self.counters.init_frames -= 1
        self.counters.reinitializations += 1
        self._after_reacquire()
        return True

    def _watch_gyro(self, uv: np.ndarray, u_i: np.ndarray,
                    R_prior: np.ndarray | None) -> None:
        """Add the frame to the gyro-against-stars check (:mod:`~stellar_cal_ros.core.gyro_check`).

        ``R_prior``: the attitude propagated to the frame (None: the gyro chain starts again).
        A fault found over the first :data:`~stellar_cal_ros.core.gyro_check.EARLY_FRAMES`
        frames raises :class:`DataError`; later it flags the result (:attr:`data_faults`).
        Deferred (:meth:`defer_gyro_judgement`): only kept here, fitted and judged by
        :meth:`judge_gyro`.
        """
        w = self.gyro_watch
        camera = self.model.prior.camera
        v_st = uv if w.get("defer") else (lambda: camera.unproject(uv))
        cause = gyro_check.watch_frame(w, self.t, v_st, u_i, R_prior, self.R_i_b,
                                       self._R_imu_st_prior)
        self._gyro_verdict(cause)

    def finish_checks(self) -> None:
        """End of the data: judge what the gyro watch recorded since its last judgement."""
        w = self.gyro_watch
        if w is not None:
            self._gyro_verdict(gyro_check.judge_pending(
                w, self._R_imu_st_prior, self.model.prior.camera.unproject))

    def defer_gyro_judgement(self) -> None:
        """Leave the gyro watch's fits and judgements to :meth:`judge_gyro` (the live node).

        A frame's update then only keeps its centroids; the Wahba fit (≈ 0.3 ms a frame over
        the first 200 frames) and the judgement of all frame pairs (up to ≈ 2 ms every 10th)
        run between frames, with the same records and verdicts
        (:func:`~stellar_cal_ros.core.gyro_check.record_pending`); a fault judged within the
        first :data:`~stellar_cal_ros.core.gyro_check.EARLY_FRAMES` frames raises as it
        would have there.
        """
        if self.gyro_watch is not None:
            self.gyro_watch["defer"] = True

    def judge_gyro(self) -> None:
        """Fit and judge what the deferred gyro watch keeps (see :meth:`defer_gyro_judgement`)."""
        w = self.gyro_watch
        if w is not None and w.get("pending"):
            self._gyro_verdict(gyro_check.record_pending(
                w, self.model.prior.camera.unproject, self._R_imu_st_prior))

    def _gyro_verdict(self, cause: str) -> None:
        w = self.gyro_watch
        if w["done"]:
            self.gyro_watch = None
        if not cause:
            return
        self.counters.add("gyro_star_mismatch")
        early = w.get("judged_at", w["frames"]) <= gyro_check.EARLY_FRAMES
        if early and self.config.unit_check_raises:
            raise DataError(cause)
        log.warning("t=%.1f s: %s; the result is degraded", self.t, cause)
        self.data_faults.append(cause)


def wahba_inliers(camera, uv: np.ndarray, u_i: np.ndarray, outlier_px: float) -> np.ndarray:
    """Stars consistent with one rotation (drops misidentified ones before the pixel fit).

    Wahba on the unprojected centroids, then repeatedly drop the worst star while it is
    off by more than ``max(outlier_px / f, 5 × median)`` in angle.
    """
    d = camera.unproject(uv)
    keep = np.all(np.isfinite(d), axis=1) & np.all(np.isfinite(u_i), axis=1)
    floor = outlier_px / max(camera.fx, camera.fy)
    for _ in range(len(uv)):
        if keep.sum() < 3:
            break
        R = wahba(d[keep], u_i[keep])
        ang = np.full(len(uv), np.inf)
        ang[keep] = np.linalg.norm(d[keep] @ R.T - u_i[keep], axis=1)
        worst = int(np.argmax(np.where(keep, ang, -1.0)))
        if ang[worst] <= max(floor, 5.0 * float(np.median(ang[keep]))):
            break
        keep[worst] = False
    return keep


def subset_context(ctx: FrameContext, idx: np.ndarray) -> FrameContext:
    """The context of a subset of the frame's stars (per-star arrays sliced)."""
    return dataclasses.replace(
        ctx,
        catalog_id=np.asarray(ctx.catalog_id)[idx] if len(ctx.catalog_id) else ctx.catalog_id,
        magnitude=np.asarray(ctx.magnitude)[idx] if len(ctx.magnitude) else ctx.magnitude,
        extra={},
    )
