"""Robust fitting of the ACF least squares: losses, σ rescaling and the outlier gate.

The star residuals may hold wrong identities that the identification gate cannot see (a
star labelled as another star of the same frame points inside the field).  A robust loss
bounds their pull but does not remove it; :func:`_gate_outliers` therefore fits with a
robust loss, leaves out the stars whose normalized residual lies beyond a χ²(2) gate, and
repeats until the set is stable — after which the caller's final fit runs on the inliers
with the loss it wants (linear: efficient).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from stellar_cal_ros.errors import StellarCalError

log = logging.getLogger("stellar_cal_ros.methods.acf")


def _used(frames: list[Any]) -> list[Any]:
    """The frames restricted to their used stars (frames left without any dropped)."""
    return [f.subset() for f in frames if f.use is None or f.use.any()]


def _make_loss(kind: str, n_star: int, c: float):
    """A least_squares loss ρ(z) (z = r²) robust on the first ``n_star`` residuals only."""
    if kind == "linear":
        return "linear"
    if kind not in ("huber", "soft_l1", "cauchy"):
        raise StellarCalError(f"loss must be linear, huber, soft_l1 or cauchy, got {kind!r}")
    c2 = c * c

    def rho(z: np.ndarray) -> np.ndarray:
        out = np.empty((3, z.size))
        out[0], out[1], out[2] = z, 1.0, 0.0
        zs = z[:n_star] / c2
        if kind == "huber":
            big = zs > 1.0
            sq = np.sqrt(np.where(big, zs, 1.0))
            r0 = np.where(big, 2.0 * sq - 1.0, zs)
            r1 = np.where(big, 1.0 / sq, 1.0)
            r2 = np.where(big, -0.5 / (sq * np.where(big, zs, 1.0)), 0.0)
        elif kind == "soft_l1":
            t = 1.0 + zs
            r0, r1, r2 = 2.0 * (np.sqrt(t) - 1.0), t ** -0.5, -0.5 * t ** -1.5
        else:
            r0, r1, r2 = np.log1p(zs), 1.0 / (1.0 + zs), -1.0 / (1.0 + zs) ** 2
        out[0, :n_star] = c2 * r0
        out[1, :n_star] = r1
        out[2, :n_star] = r2 / c2
        return out

    return rho


def _robust_weights(kind: str, r: np.ndarray, c: float) -> np.ndarray:
    """IRLS weights ρ'(r²) of whitened residuals."""
    if kind == "linear":
        return np.ones_like(r)
    zs = (r / c) ** 2
    if kind == "huber":
        return np.where(zs > 1.0, 1.0 / np.sqrt(np.maximum(zs, 1.0)), 1.0)
    if kind == "soft_l1":
        return (1.0 + zs) ** -0.5
    return 1.0 / (1.0 + zs)


def _solve(problem: Any, x0: np.ndarray, loss: str, f_scale: float, max_nfev: int):
    from scipy.optimize import least_squares  # (on first use: a replay never needs it)

    rho = _make_loss(loss, problem.n_star, f_scale)
    res = least_squares(problem.fun, x0, jac=problem.jac, loss=rho, f_scale=1.0,
                        method="trf", x_scale="jac", max_nfev=max_nfev,
                        xtol=1e-12, ftol=1e-12, gtol=1e-10)
    return res


def _solve_scaled(problem: Any, x: np.ndarray, loss: str, max_nfev: int):
    """Solve; for a robust loss, rescale σ until ``f_scale = 3σ`` means 3 σ (≤ 3 times)."""
    res, nfev = None, 0
    for _ in range(3):
        res = _solve(problem, x, loss, 3.0, max_nfev)
        nfev += res.nfev
        x = res.x
        robust_scale = 1.4826 * float(np.median(np.abs(res.fun[:problem.n_star])))
        if loss == "linear" or 0.5 < robust_scale < 2.0:
            break
        problem.sigma_scale *= robust_scale
        problem._cache = None
    assert res is not None
    return res, nfev


def beyond_gate(residuals: np.ndarray, probability: float,
                excluded: np.ndarray | None = None) -> np.ndarray:
    """Stars (bool per star) whose normalized residual lies beyond the χ²(2) gate.

    ``residuals``: the whitened star residuals ``(r_u, r_v)`` of every star, flat (2n,).
    ``(r_u² + r_v²) / s²``, ``s`` = 1.4826 × the median absolute whitened residual of the
    stars not ``excluded`` (a robust scale: the outliers do not inflate it), against the
    χ²(2) quantile of ``probability``.
    """
    from stellar_cal_ros.core.distributions import chi2

    r = np.asarray(residuals).reshape(-1, 2)
    keep = ~excluded if excluded is not None and np.any(~excluded) else np.ones(len(r), bool)
    s = 1.4826 * float(np.median(np.abs(r[keep])))
    return np.sum(r ** 2, axis=1) > float(chi2.ppf(probability, 2)) * max(s, 1e-12) ** 2


def _gate_outliers(make: Callable[..., Any], fr_all: list[Any], x: np.ndarray, loss: str,
                   probability: float, max_nfev: int,
                   max_rounds: int = 5) -> tuple[np.ndarray, float, int, int]:
    """Robust fit, then leave out stars beyond the χ²(2) gate until the set is stable.

    ``make(frames, scale)`` builds the problem.  Every identified star (``use`` after the
    identification gate) is tested in every round, so a star wrongly left out returns.
    Sets each frame's ``use``; returns x, the σ scale, evaluations and the outlier count.
    """
    robust = loss if loss != "linear" else "soft_l1"
    ident = [f.use.copy() for f in fr_all]
    candidates = make(_used(fr_all))
    out = np.zeros(candidates.n_star // 2, dtype=bool)
    nfev, scale = 0, 1.0
    for _ in range(max_rounds):
        problem = make(_used(fr_all), scale)
        res, n = _solve_scaled(problem, x, robust, max_nfev)
        nfev += n
        x, scale = res.x, problem.sigma_scale
        candidates.sigma_scale = scale
        candidates._cache = None
        new = beyond_gate(candidates.fun(x)[:candidates.n_star], probability, out)
        if np.array_equal(new, out):
            break
        out = new
        start = 0
        for f, m in zip(fr_all, ident, strict=True):
            k = int(m.sum())
            use = m.copy()
            use[np.flatnonzero(m)] = ~out[start:start + k]
            f.use = use
            start += k
    if out.any():
        log.info("ACF: %d of %d stars beyond the outlier gate (p = %g) left out",
                 int(out.sum()), len(out), probability)
    return x, scale, nfev, int(out.sum())
