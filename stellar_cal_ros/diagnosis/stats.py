"""Residual statistics: RMS against the noise floor, NIS consistency, whiteness, regressors.

All functions take the residual table of a run (:data:`~stellar_cal_ros.methods.replay.
RESIDUAL_COLUMNS`; innovations ``du, dv`` with their 2×2 covariance ``s_uu, s_uv, s_vv``)
and an evaluation mask (by default the second half of the frames, after convergence).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

Table = dict[str, np.ndarray]


def evaluation_mask(res: Table, fraction: float = 0.5) -> np.ndarray:
    """Stars of the last ``fraction`` of the frames (the filter has converged there)."""
    if len(res["t"]) == 0:
        return np.zeros(0, dtype=bool)
    t = res["t"]
    t_cut = t.min() + (1.0 - fraction) * (t.max() - t.min())
    return t >= t_cut


def accepted(res: Table) -> np.ndarray:
    """Stars not rejected by the gate."""
    return ~np.asarray(res["gated"]).astype(bool)


def rms(res: Table, mask: np.ndarray) -> tuple[float, float]:
    """Innovation RMS (u, v) over ``mask`` ∧ accepted, px."""
    m = mask & accepted(res)
    if not np.any(m):
        return float("nan"), float("nan")
    return float(np.sqrt(np.mean(res["du"][m] ** 2))), float(np.sqrt(np.mean(res["dv"][m] ** 2)))


def expected_rms(res: Table, mask: np.ndarray) -> tuple[float, float]:
    """RMS the model predicts: sqrt of the mean innovation variance (u, v), px."""
    m = mask & accepted(res)
    if not np.any(m):
        return float("nan"), float("nan")
    return float(np.sqrt(np.mean(res["s_uu"][m]))), float(np.sqrt(np.mean(res["s_vv"][m])))


def noise_variance(res: Table, mask: np.ndarray) -> float:
    """Mean predicted innovation variance per star (u + v), px²."""
    m = mask & accepted(res)
    return float(np.mean(res["s_uu"][m] + res["s_vv"][m])) if np.any(m) else float("nan")


def excess_variance(res: Table, mask: np.ndarray) -> float:
    """Mean squared innovation minus its predicted variance per star (u + v), px².

    Positive when the residuals are larger than the model's noise accounts for.
    """
    m = mask & accepted(res)
    if not np.any(m):
        return float("nan")
    return float(np.mean(res["du"][m] ** 2 + res["dv"][m] ** 2)
                 - np.mean(res["s_uu"][m] + res["s_vv"][m]))


def whitened(res: Table) -> np.ndarray:
    """Innovations whitened by their 2×2 covariance (n, 2): Cholesky ``L⁻¹ ν``."""
    a, b, d = res["s_uu"], res["s_uv"], res["s_vv"]
    l11 = np.sqrt(a)
    l21 = b / l11
    l22 = np.sqrt(np.maximum(d - l21**2, 1e-300))
    w1 = res["du"] / l11
    w2 = (res["dv"] - l21 * w1) / l22
    return np.stack([w1, w2], axis=1)


def log_likelihood(res: Table, mask: np.ndarray, cap: float = 13.8) -> float:
    """Gaussian log-likelihood of the innovations, each star's NIS capped at ``cap``.

    Innovations are one-step-ahead predictions, so this is a prequential (out-of-sample)
    likelihood: a model cannot raise it by fitting noise.  Capping the per-star NIS at the
    gate keeps a few misidentified stars from dominating the comparison of two models.  A
    gated star counts as capped *with the window's median accepted covariance*: its own
    covariance is that of a wrong identity predicted far across (or off) the detector,
    whose log-determinant varies between models by more than the effects compared
    (measured: 250 of the 2Δℓ between two models with 2 % misidentified stars), so every
    model is scored alike on the stars it rejects.
    """
    det = res["s_uu"] * res["s_vv"] - res["s_uv"] ** 2
    nis = np.asarray(res["nis"], dtype=float)
    ok = accepted(res) & np.isfinite(nis) & np.isfinite(det) & (det > 0)
    nis = np.where(ok, np.minimum(nis, cap), cap)
    logdet = np.log(np.where(ok, det, 1.0))
    fill = float(np.median(logdet[mask & ok])) if np.any(mask & ok) else 0.0
    logdet = np.where(ok, logdet, fill)
    terms = -0.5 * (nis + logdet + 2 * np.log(2 * np.pi))
    return float(np.sum(terms[mask]))


def nis_consistency(res: Table, mask: np.ndarray) -> dict[str, float]:
    """Mean per-star NIS (2 dof) over accepted stars and its two-sided 95 % χ² bounds."""
    m = mask & accepted(res)
    n = int(m.sum())
    if n == 0:
        return {"mean": float("nan"), "lower": float("nan"), "upper": float("nan"), "n": 0}
    mean = float(np.mean(res["nis"][m]))
    lo, hi = stats.chi2.ppf([0.025, 0.975], 2 * n) / n
    return {"mean": mean, "lower": float(lo), "upper": float(hi), "n": n}


def whiteness(res: Table, mask: np.ndarray) -> dict[str, float]:
    """Lag-1 autocorrelation of frame-mean whitened residuals, with its p-value."""
    m = mask & accepted(res)
    frames = res["frame"][m]
    w = whitened({k: v[m] for k, v in res.items()})
    if len(frames) == 0:
        return {"lag1_u": float("nan"), "lag1_v": float("nan"), "p_value": 1.0}
    uniq, inv = np.unique(frames, return_inverse=True)
    cnt = np.bincount(inv)
    means = np.stack([np.bincount(inv, w[:, k]) / cnt for k in range(2)], 1) * np.sqrt(cnt)[:, None]
    out = {}
    ps = []
    for k, name in enumerate(("u", "v")):
        x = means[:, k] - means[:, k].mean()
        r = float(np.sum(x[1:] * x[:-1]) / max(np.sum(x * x), 1e-300)) if len(x) > 2 else 0.0
        out[f"lag1_{name}"] = r
        z = r * np.sqrt(max(len(x), 1))
        ps.append(2 * stats.norm.sf(abs(z)))
    out["p_value"] = float(min(1.0, 2 * min(ps)))
    return out


@dataclass
class RegressorFinding:
    """A residual component correlated with a regressor."""

    regressor: str
    component: str
    statistic: float
    p_value: float
    slope_px: float  # residual change across the regressor's 5-95 % range, px


def regressors(res: Table, camera_centre: tuple[float, float]) -> dict[str, np.ndarray]:
    """Candidate explanatory variables of residual structure, one value per star."""
    cx, cy = camera_centre
    du_ = res["u"] - cx
    dv_ = res["v"] - cy
    out = {
        "time": res["t"] - res["t"].min() if len(res["t"]) else res["t"],
        "magnitude": res["magnitude"],
        "u (column)": res["u"],
        "v (row)": res["v"],
        "radius": np.hypot(du_, dv_),
        "angular rate": np.linalg.norm(
            np.stack([res["omega_x"], res["omega_y"], res["omega_z"]], 1), axis=1),
        "head temperature": res["head_temperature"],
    }
    for key in ("elevation", "gravity_x_st", "gravity_y_st", "rotation_angle"):
        if key in res:
            out[key] = res[key]
    return out


def regressor_tests(res: Table, mask: np.ndarray, camera_centre: tuple[float, float],
                    alpha: float = 0.01) -> list[RegressorFinding]:
    """Correlation of whitened residuals (u, v, radial) with each regressor.

    A Pearson correlation test per pair; p-values are Bonferroni-corrected over all pairs.
    Only pairs significant at ``alpha`` after correction are returned, strongest first.
    """
    m = mask & accepted(res)
    if m.sum() < 20:
        return []
    sub = {k: v[m] for k, v in res.items()}
    w = whitened(sub)
    cx, cy = camera_centre
    du_, dv_ = sub["u"] - cx, sub["v"] - cy
    r = np.hypot(du_, dv_)
    radial = (sub["du"] * du_ + sub["dv"] * dv_) / np.maximum(r, 1e-9)
    sigma_r = np.sqrt(np.maximum((sub["s_uu"] * du_**2 + 2 * sub["s_uv"] * du_ * dv_
                                  + sub["s_vv"] * dv_**2) / np.maximum(r, 1e-9) ** 2, 1e-300))
    # Signed components find biases (e.g. a radial error growing with radius); the squared
    # whitened norm finds residuals whose *size* follows a regressor (e.g. the angular rate
    # for a timing error, whose direction follows the motion and averages out when signed).
    components = {"u": (w[:, 0], sub["du"]), "v": (w[:, 1], sub["dv"]),
                  "radial": (radial / sigma_r, radial),
                  "size": (w[:, 0] ** 2 + w[:, 1] ** 2, np.hypot(sub["du"], sub["dv"]))}
    regs = regressors(sub, camera_centre)
    tests = []
    for rname, x in regs.items():
        x = np.asarray(x, dtype=float)
        ok = np.isfinite(x)
        if ok.sum() < 20 or np.ptp(x[ok]) == 0:
            continue
        for cname, (y, y_px) in components.items():
            ok2 = ok & np.isfinite(y)
            rho, _ = stats.pearsonr(x[ok2], y[ok2])
            n = ok2.sum()
            tstat = rho * np.sqrt((n - 2) / max(1 - rho**2, 1e-300))
            p = 2 * stats.t.sf(abs(tstat), n - 2)
            lo, hi = np.percentile(x[ok2], [5, 95])
            slope = np.polyfit(x[ok2], y_px[ok2], 1)[0] * (hi - lo)
            tests.append(RegressorFinding(rname, cname, float(tstat), float(p), float(slope)))
    m_tests = max(len(tests), 1)
    found = []
    for tst in tests:
        tst.p_value = min(1.0, tst.p_value * m_tests)
        if tst.p_value < alpha:
            found.append(tst)
    found.sort(key=lambda f: f.p_value)
    return found
