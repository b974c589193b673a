"""Residual statistics: RMS against the noise floor, NIS consistency, whiteness, regressors.

All functions take the residual table of a run (:data:`~stellar_cal_ros.methods.replay.
RESIDUAL_COLUMNS`; innovations ``du, dv`` with their 2×2 covariance ``s_uu, s_uv, s_vv``)
and an evaluation mask (by default the second half of the frames, after convergence).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import logsumexp

from stellar_cal_ros.core import distributions as dist
from stellar_cal_ros.core.units import ARCSEC

Table = dict[str, np.ndarray]


def finite_rows(a: np.ndarray) -> np.ndarray:
    """``np.all(np.isfinite(a), axis=1)``, for a 2-d ``a`` of a few columns column by column.

    The same booleans; numpy's reduction over a row of 2-8 values is ~10x slower than the
    columns' ``&`` (6.7 against 0.5 ms on a 2-h table's 457 000 × 2 rows).
    """
    a = np.asarray(a)
    if a.ndim != 2 or not 1 <= a.shape[1] <= 8:
        return np.all(np.isfinite(a), axis=1)
    ok = np.isfinite(a[:, 0])
    for j in range(1, a.shape[1]):
        ok &= np.isfinite(a[:, j])
    return ok


def evaluation_mask(res: Table, fraction: float = 0.5) -> np.ndarray:
    """Stars of the last ``fraction`` of the frames (the filter has converged there)."""
    if len(res["t"]) == 0:
        return np.zeros(0, dtype=bool)
    t = res["t"]
    t_cut = t.min() + (1.0 - fraction) * (t.max() - t.min())
    return t >= t_cut


class Rows(dict):
    """The rows ``mask`` of a residual table, each column taken when first read.

    ``{k: np.asarray(v)[mask] for k, v in res.items()}`` with the same arrays, but only of
    the columns read: a test that reads a dozen of a 2-h run's 30 columns no longer holds
    a copy of the others (the clock test over the whole run: ≈ 20 MB).  ``res`` must not
    change while this is read.
    """

    def __init__(self, res: Table, mask: np.ndarray) -> None:
        super().__init__()
        self._res, self._mask = res, mask

    def __missing__(self, key: str) -> np.ndarray:
        if key not in self._res:
            raise KeyError(key)
        got = self[key] = np.asarray(self._res[key])[self._mask]
        return got

    def __contains__(self, key: object) -> bool:
        return key in self._res or dict.__contains__(self, key)

    def get(self, key: str, default=None):
        """The column ``key`` (taken now), or ``default``."""
        return self[key] if key in self else default

    def keys(self):
        """Every column's name (the table's, then any set here)."""
        return list(dict.fromkeys([*self._res, *dict.keys(self)]))

    def __iter__(self):
        return iter(self.keys())

    def __len__(self) -> int:
        return len(self.keys())

    def items(self):
        """``(name, column)`` of every column (each taken now)."""
        return [(k, self[k]) for k in self.keys()]

    def values(self):
        """Every column (each taken now)."""
        return [self[k] for k in self.keys()]


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
    model is scored alike on the stars it rejects.  Each log-determinant is weighted by
    :func:`~stellar_cal_ros.methods.results.logdet_weight` of ``cap`` (0.992 at 13.8), which
    keeps a noise scale measured on this likelihood from reading low by the cap.
    """
    from stellar_cal_ros.methods.results import logdet_weight

    det = res["s_uu"] * res["s_vv"] - res["s_uv"] ** 2
    nis = np.asarray(res["nis"], dtype=float)
    ok = accepted(res) & np.isfinite(nis) & np.isfinite(det) & (det > 0)
    nis = np.where(ok, np.minimum(nis, cap), cap)
    logdet = logdet_weight(cap) * np.log(np.where(ok, det, 1.0))
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
    lo, hi = dist.chi2.ppf([0.025, 0.975], 2 * n) / n
    return {"mean": mean, "lower": float(lo), "upper": float(hi), "n": n}


def whiteness(res: Table, mask: np.ndarray) -> dict[str, float]:
    """Lag-1 autocorrelation of frame-mean whitened residuals, with its p-value."""
    m = mask & accepted(res)
    frames = res["frame"][m]
    w = whitened({k: v[m] for k, v in res.items()})
    if len(frames) == 0:
        return {"lag1_u": float("nan"), "lag1_v": float("nan"), "p_value": 1.0}
    uniq, inv = frames_of(frames)
    cnt = np.bincount(inv)
    means = np.stack([np.bincount(inv, w[:, k]) / cnt for k in range(2)], 1) * np.sqrt(cnt)[:, None]
    out = {}
    ps = []
    for k, name in enumerate(("u", "v")):
        x = means[:, k] - means[:, k].mean()
        r = float(np.sum(x[1:] * x[:-1]) / max(np.sum(x * x), 1e-300)) if len(x) > 2 else 0.0
        out[f"lag1_{name}"] = r
        z = r * np.sqrt(max(len(x), 1))
        ps.append(2 * dist.norm.sf(abs(z)))
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
    #: what a test shaped like one effect outside the library adds (its fitted size, ...)
    detail: dict | None = None


def p_finding(regressor: str, component: str, p_value: float, size_px: float,
              detail: dict | None = None) -> RegressorFinding:
    """A test's :class:`RegressorFinding` from its unadjusted p (one-sided).

    Its statistic the p's normal score, 37 where the p underflows: the 'unexplained'
    family ranks by p, then by it.
    """
    z = float(dist.norm.isf(p_value)) if p_value > 1e-300 else 37.0
    return RegressorFinding(regressor, component, z, p_value, size_px, detail=detail)


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
    for key in ("elevation", "gravity_x_st", "gravity_y_st", "gravity_x_st change",
                "gravity_y_st change", "rotation_angle"):
        if key in res:
            out[key] = res[key]
    return out


def attitude_columns(res: Table, fx: float, fy: float) -> np.ndarray:
    """∂(u, v)/∂(small tracker rotation) of each star, (n, 2, 3) (pinhole; signs immaterial).

    From the star's direction in the tracker frame (``x_st, y_st, z_st``): the three ways
    a frame's attitude error moves its stars, which every star of the frame shares.
    """
    x, y, z = (np.asarray(res[k], dtype=float) for k in ("x_st", "y_st", "z_st"))
    J = np.zeros((len(x), 2, 3))
    # (u, v) = (fx x/z, fy y/z);  d ← d + δ × d
    J[:, 0, 0] = -fx * x * y / z**2
    J[:, 0, 1] = fx * (1.0 + x**2 / z**2)
    J[:, 0, 2] = -fx * y / z
    J[:, 1, 0] = -fy * (1.0 + y**2 / z**2)
    J[:, 1, 1] = fy * x * y / z**2
    J[:, 1, 2] = fy * x / z
    return J


def within_frame(res: Table, sigma: np.ndarray, fx: float, fy: float
                 ) -> tuple[np.ndarray, np.ndarray, int]:
    """Each frame's innovations (whitened by ``sigma``) minus their fit by an attitude error.

    Per frame of at least 3 stars, ``r = (I − A (AᵀA)⁻¹ Aᵀ) ν/σ`` with ``A`` the stars'
    :func:`attitude_columns` over σ: what no attitude error (hence no gyro noise, no
    installation or timing error that rotates the whole frame) can produce — centroid noise
    and the structure of the camera side.  Returns ``(r (n, 2), leverage (n,), frames)``;
    rows of smaller frames are NaN, leverage 2.  (:class:`FrameFit` of the table applied to
    its ``du, dv``; a caller projecting several columns through the same frames makes the
    :class:`FrameFit` once.)
    """
    fit = FrameFit(res, sigma, fx, fy)
    return fit.residual(res["du"], res["dv"]), fit.leverage, fit.frames


class FrameFit:
    """The frames' attitude fit of :func:`within_frame`, made once for any columns.

    The stars' whitened :func:`attitude_columns` ``A``, frame by frame, and ``(AᵀA)⁻¹``:
    :meth:`residual` gives ``(I − A (AᵀA)⁻¹ Aᵀ) y/σ`` of any ``(du, dv)`` over the same
    rows.  The frames of one star count are stacked and computed in one call each (the same
    per-frame products and inverses as a loop over the frames).
    """

    def __init__(self, res: Table, sigma: np.ndarray, fx: float, fy: float) -> None:
        self.n = n = len(sigma)
        self.sigma = sigma
        A = attitude_columns(res, fx, fy) / sigma[:, None, None]
        frames = np.asarray(res["frame"])
        order = np.argsort(frames, kind="stable")
        starts = np.concatenate([[0], np.flatnonzero(np.diff(frames[order])) + 1])
        sizes = np.diff(np.concatenate([starts, [n]])) if n else np.zeros(0, int)
        self.leverage = np.full(n, 2.0)
        #: per star count: ``(rows (k, s), A (k, 2s, 3), (AᵀA)⁻¹ (k, 3, 3))``
        self.groups: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        used = 0
        for s in np.unique(sizes[sizes >= 3]) if n else ():
            rows = order[starts[sizes == s][:, None] + np.arange(s)]
            Ak = A[rows].reshape(len(rows), 2 * s, 3)
            G = np.matmul(Ak.transpose(0, 2, 1), Ak)
            try:
                Gi = np.linalg.inv(G)
            except np.linalg.LinAlgError:  # the frames one by one: a singular one is left out
                keep = []
                Gi = np.zeros_like(G)
                for i in range(len(rows)):
                    try:
                        Gi[i] = np.linalg.inv(G[i])
                    except np.linalg.LinAlgError:
                        continue
                    keep.append(i)
                rows, Ak, Gi = rows[keep], Ak[keep], Gi[keep]
            if not len(rows):
                continue
            self.leverage[rows] = np.einsum("bij,bjk,bik->bi", Ak, Gi, Ak
                                            ).reshape(len(rows), s, 2).sum(2)
            self.groups.append((rows, Ak, Gi))
            used += len(rows)
        self.frames = used

    def residual(self, du: np.ndarray, dv: np.ndarray) -> np.ndarray:
        """``(n, 2)``: ``(du, dv)/σ`` minus each frame's attitude fit (NaN outside the frames)."""
        y = np.stack([np.asarray(du, dtype=float), np.asarray(dv, dtype=float)], 1) \
            / self.sigma[:, None]
        r = np.full((self.n, 2), np.nan)
        for rows, Ak, Gi in self.groups:
            yk = y[rows].reshape(len(rows), -1)
            b = np.matmul(Gi, np.matmul(Ak.transpose(0, 2, 1), yk[:, :, None]))
            r[rows] = (yk - np.matmul(Ak, b)[:, :, 0]).reshape(len(rows), -1, 2)
        return r


def star_tracks(sub: Table) -> np.ndarray | None:
    """Each row's star (its catalogue id) for :func:`frame_robust_t`'s ``track``, or ``None``."""
    return np.asarray(sub["catalog_id"]) if "catalog_id" in sub else None


def hac_bandwidth(n_frames: int) -> int:
    """Newey–West lag window over frames: ``⌊4 (n / 100)^(2/9)⌋`` (at least 1)."""
    return max(1, int(4.0 * (max(n_frames, 1) / 100.0) ** (2.0 / 9.0)))


def normal_scores(x: np.ndarray) -> np.ndarray:
    """Van der Waerden scores of ``x`` (ties share their mean rank)."""
    return dist.norm.ppf(dist.rankdata(x) / (len(x) + 1.0))


#: :func:`frame_robust_t`'s input is degenerate when the spread of ``x`` is below this share of
#: ``Σ x²`` or ``V`` below this share of ``Σ x_c² Σ y_c²``: far above double rounding (~1e-32,
#: a constant ``x`` minus its computed mean, or an exact fit's residuals), far below any data
DEGENERATE = 1e-24


def plugin_bandwidth(u: np.ndarray) -> int:
    """The lag window over a series of frames' scores ``u`` (the caller caps it).

    Andrews' (1991) AR(1) plug-in for the Bartlett kernel, at least Newey–West's rule
    (:func:`hac_bandwidth`).  A filter whose noise is misstated leaves its innovations
    correlated over many frames, and the window must cover them.
    """
    n = len(u)
    uc = u - u.mean()
    rho = float(np.clip((uc[1:] @ uc[:-1]) / max(uc @ uc, 1e-300), -0.97, 0.97)) \
        if n > 2 else 0.0
    a1 = 4.0 * rho**2 / ((1.0 - rho) ** 2 * (1.0 + rho) ** 2)
    return max(hac_bandwidth(n), int(1.1447 * (a1 * n) ** (1.0 / 3.0)))


def frame_index(cluster: np.ndarray) -> np.ndarray:
    """``np.unique(cluster, return_inverse=True)[1]``: each row's frame as ``0..n−1``.

    Integer frames that do not decrease (a residual table's rows, in time order) are
    counted in one pass instead of sorted: the same indices, without the sort's copies
    (the line tests call it per regressor on the 2-h round's 457 000 rows).

    Integer frames that decrease somewhere but span few values (a table's frame numbers
    stacked twice, u then v: :func:`shaped_tests`' ~35 tests on 914 000 rows) are ranked
    through a table of the values present (their cumulative count): the same dense ranks,
    without the sort.
    """
    c = np.asarray(cluster)
    if c.ndim != 1 or c.dtype.kind not in "iu" or len(c) < 2:
        return np.unique(c, return_inverse=True)[1]
    if np.any(c[1:] < c[:-1]):
        lo, hi = c.min(), c.max()
        if int(hi) - int(lo) >= 2 * len(c):
            return np.unique(c, return_inverse=True)[1]
        at = c - lo
        seen = np.zeros(int(hi - lo) + 1, dtype=bool)
        seen[at] = True
        return (np.cumsum(seen, dtype=np.intp) - 1)[at]
    k = np.empty(len(c), dtype=np.intp)
    k[0] = 0
    np.cumsum(c[1:] != c[:-1], out=k[1:])
    return k


def frames_of(cluster: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(cluster, return_inverse=True)`` by :func:`frame_index`: frames, row ranks.

    :func:`frame_index` ranks the values densely in ascending order: the frames are the
    value each rank's rows hold (one sort less on the clock test's 457 000 rows).
    """
    c = np.asarray(cluster)
    if len(c) == 0 or c.ndim != 1:
        return np.unique(c, return_inverse=True)
    k = frame_index(c)
    frames = np.empty(int(k.max()) + 1, dtype=c.dtype)
    frames[k] = c
    return frames, k


def frame_robust_t(x: np.ndarray, y: np.ndarray, cluster: np.ndarray,
                   lags: int | None = None, dof: bool = False,
                   track: np.ndarray | None = None,
                   track_lags: tuple[float, float] | None = None,
                   track_level: bool = False, index: np.ndarray | None = None
                   ) -> tuple[float | None, ...]:
    """The slope's t of ``y`` on ``x``, robust to correlation within and across frames.

    The slope ``b`` by least squares; its variance from the scores ``U_k = Σ (x − x̄)(y −
    ȳ − b (x − x̄))`` summed per frame (``cluster``: frame index, in time order), as the
    frames' Newey–West sum ``V = Σ_k U_k² + 2 Σ_l (1 − l/(L+1)) Σ_k U_k U_{k+l}`` (``L``
    from the frame sums' own lag-1 correlation, Andrews' plug-in).  The stars of a frame
    share the attitude error (one error seen by all, not ``n`` independent ones) and an
    imperfect filter leaves its innovations correlated from frame to frame: an i.i.d. test
    over the stars counts both as evidence (measured: the 'unexplained' lines of the demo
    and of a bag with understated gyro noise).

    The reference is Student's t, not N(0, 1): ``V`` is itself estimated from the frames'
    scores, and the lag window and the frames' unequal weight (a regressor's extreme
    frames carry most of ``Σ U_k²``) leave it few effective degrees of freedom (measured on
    clean bags' windows of 200-300 frames, ``L`` = 4-5: ν = 21-72, median 28-38; at ν = 25,
    |t| = 3.9 is p = 6.4e-4, not the normal's 1.0e-4: the 3 % 'unexplained' lines on clean
    bags were these tails).  :func:`hac_reference`
    gives ν and the small-sample factor of ``V`` (Satterthwaite, Bell–McCaffrey) under the
    null of frames independent with stars exchangeable within a frame.  Returns ``(t,
    two-sided p from t_ν)``, ``(t, p, ν)`` with ``dof`` (an MDB on the same reference).
    Degenerate input (no spread of ``x``, or ``V`` zero: ``y`` exactly ``b x``, see
    :data:`DEGENERATE`) makes no test: ``(0, 1)``, and with ``dof`` ``ν = None`` (no
    reference, so no MDB either).  ``index``: :func:`frame_index` of ``cluster`` when the
    caller has it (several tests over the same rows: the line tests).

    ``track`` (each row's star, e.g. its catalogue id) with ``track_lags = (w, φ)``: the
    stars' centroid noise is correlated along each star's track as ``w φ^l`` at lag ``l``
    frames (:func:`~stellar_cal_ros.diagnosis.noise_structure.track_model`, fitted on
    thousands of pairs about the stars' means), and ``V`` gains the part of that covariance
    the frames' window leaves out (:func:`track_covariance`).  White + AR(1) noise (lag-1
    ~0.2, φ 0.82) stays correlated for ~20 frames, where a window read from one test's
    150-300 frame scores is 4-5 frames long, and those scores read their own lags too
    noisily to size a longer one (doc/benchmarks.md "The stars' track model in the
    structure tests").  The model, not the residuals: clustering by star (two-way) also
    took a structure's per-star lack of fit for noise (magnitude bias, t 36.5 -> 9.3).

    ``track_level`` (with ``track``): each star's rows share a level of their own, ``y``'s
    mean differs star by star (a σ stated wrong by each star's own factor: its whitened
    size is that factor², :func:`~.noise_stars.star_spread`), a covariance ``τ²`` between a
    star's rows at every lag, which the frames' window holds only up to ``L``: ``V`` gains
    ``τ² Σ_s Σ_{k≠j} (1 − b_|k−j|) a_sk a_sj`` (:func:`track_level_covariance`), ``τ²`` the
    stars' means' variance beyond their rows' (about their frame's mean, at the fitted
    slope: a real change along ``x`` is no star's level).  The stars in view when ``x`` is
    high are then a sample of stars, not of noise (unseen case ``sigma_per_star``: 'spread
    vs time, head temperature, gravity' at t ~ 6-8, measured).
    """
    xc = x - x.mean()
    yc = y - y.mean()
    sxx = float(xc @ xc)
    if not sxx > DEGENERATE * float(x @ x):  # a constant x leaves its mean's rounding
        return (0.0, 1.0, None) if dof else (0.0, 1.0)
    b = float(xc @ yc) / sxx
    k = frame_index(cluster) if index is None else index
    # the frames' scores at the fitted slope (a Wald t: a real structure must not count as
    # its own noise)
    e = yc - b * xc
    U = np.bincount(k, xc * e)
    n = len(U)
    if lags is None:
        L = min(plugin_bandwidth(U), max(n // 4, 1))
    else:
        L = lags
    L = min(L, n - 1)
    V = float(U @ U)
    for lag in range(1, L + 1):
        V += 2.0 * (1.0 - lag / (L + 1.0)) * float(U[lag:] @ U[:-lag])
    if not V > DEGENERATE * sxx * float(yc @ yc):  # y exactly b x: rounding is all e is
        return (0.0, 1.0, None) if dof else (0.0, 1.0)
    nu, factor = hac_reference(xc, e, k, L)
    if track is not None and (track_lags is not None or track_level):
        # the rows' residuals about their frame's mean (an error the frame's stars share
        # is no part of a star's track): the tracks' variance and their levels' ANOVA
        cnt = np.bincount(k, minlength=n)
        r = e - (np.bincount(k, e, minlength=n) / np.maximum(cnt, 1))[k]
        # each row's star as an index 0..S−1, once for both terms
        s = np.unique(np.asarray(track), return_inverse=True)[1].reshape(-1)
        if track_lags is not None:
            var = float(r @ r) / max(len(e) - int(np.sum(cnt > 0)), 1)
            V += var * track_covariance(xc, k, s, L, *track_lags)
        if track_level:
            V += track_level_covariance(xc, r, k, s, L)
    t = float(b * sxx / np.sqrt(V / factor))
    p = float(2.0 * dist.t.sf(abs(t), nu))
    return (t, p, nu) if dof else (t, p)


def track_covariance(xc: np.ndarray, k: np.ndarray, s: np.ndarray, L: int, w: float,
                     phi: float) -> float:
    """What the frames' lag window misses of a score sum's variance under correlated tracks.

    Rows' noise of one variance, correlated ``w φ^l`` between a star's rows ``l`` frames
    apart (``k`` the frame index in time order, ``s`` the star's index ``0..S−1``): with
    ``a_sk`` the sum of ``xc`` over star ``s``'s rows in frame ``k``, ``Σ_s Σ_{l ≥ 1} 2 (1
    − b_l) w φ^l Σ_k a_sk a_s,k+l``, ``b_l`` the Bartlett weight :func:`frame_robust_t`'s
    window gives lag ``l`` (``1 − l/(L+1)`` up to ``L``, 0 beyond), in units of the rows'
    variance.  Lags until ``w φ^l`` falls below 1e-4.  Each star's frames from its first to
    its last laid end to end, ``last`` zeros after each, so that no lag reaches the next
    star (H70's layout: a 2-h window's call 0.02 CPU-s, a stars × frames table's 0.7-2).
    """
    if not (w > 1e-4 and 0.0 < phi < 1.0):
        return 0.0
    n = int(k.max()) + 1
    last = min(n - 1, int(math.ceil(math.log(1e-4 / w) / math.log(phi))))
    if last < 1:
        return 0.0
    A = track_sums(xc, k, s, n, last)
    tot = 0.0
    for lag in range(1, last + 1):
        kept = 1.0 - lag / (L + 1.0) if lag <= L else 0.0
        tot += 2.0 * (1.0 - kept) * w * phi**lag * float(A[lag:] @ A[:-lag])
    return tot


def track_sums(xc: np.ndarray, k: np.ndarray, s: np.ndarray, n: int, gap: int) -> np.ndarray:
    """``xc`` summed per star ``s`` and frame ``k`` (of ``n``), the stars laid end to end.

    Each star's frames from its first to its last, ``gap`` zeros after each, so that no lag
    up to ``gap`` reaches the next star (H70's layout: a 2-h window's call 0.02 CPU-s, a
    stars × frames table's 0.7-2).
    """
    ns = int(s.max()) + 1
    lo = np.full(ns, n, dtype=np.int64)
    np.minimum.at(lo, s, k)
    hi = np.zeros(ns, dtype=np.int64)
    np.maximum.at(hi, s, k)
    start = np.concatenate([[0], np.cumsum(hi - lo + 1 + gap)])
    return np.bincount(start[s] + k - lo[s], xc, minlength=int(start[-1]))


def track_level_covariance(xc: np.ndarray, r: np.ndarray, k: np.ndarray, s: np.ndarray,
                           L: int) -> float:
    """What the frames' lag window misses of a score sum's variance when tracks have levels.

    :func:`frame_robust_t`'s ``track_level``: ``r`` the rows' residuals at the fitted slope
    about their frame's mean, ``k`` their frame (time order), ``s`` their star's index
    ``0..S−1``.  ``τ²`` by the method of moments from the one-way ANOVA of ``r`` on the
    stars (``(B − W) / n₀``, 0 when below), times ``Σ_s [(Σ_k a_sk)² − Σ_k a_sk² − 2
    Σ_{l=1..L} b_l Σ_k a_sk a_s,k+l]`` (``a_sk`` the sum of ``xc`` over star ``s``'s rows
    in frame ``k``, ``b_l`` the window's Bartlett weights): the pairs of a star's rows
    beyond the window and the part of those inside it the weights leave out.
    """
    n = int(k.max()) + 1
    ns = np.bincount(s).astype(float)
    S, N = len(ns), len(r)
    if S < 3 or N - S < 2:
        return 0.0
    ms = np.bincount(s, r) / ns
    B = float(np.sum(ns * ms**2)) / (S - 1)
    W = float(np.sum((r - ms[s]) ** 2)) / (N - S)
    n0 = (N - float(np.sum(ns**2)) / N) / (S - 1)
    tau2 = max(B - W, 0.0) / n0
    if not tau2 > 0.0:
        return 0.0
    A = track_sums(xc, k, s, n, L)
    tot = float(np.sum(np.bincount(s, xc, minlength=S) ** 2)) - float(A @ A)
    for lag in range(1, L + 1):
        tot -= 2.0 * (1.0 - lag / (L + 1.0)) * float(A[lag:] @ A[:-lag])
    return tau2 * max(tot, 0.0)


def hac_reference(xc: np.ndarray, e: np.ndarray, k: np.ndarray, L: int
                  ) -> tuple[float, float]:
    """Degrees of freedom and bias factor of :func:`frame_robust_t`'s variance ``V``.

    Under the null (frames independent; within a frame, residuals ``e`` exchangeable with
    intra-frame correlation ρ estimated from ``e``), the frame score ``g_k = Σ x_c y``
    has variance ``d_k ∝ (1 − ρ) Σ x_c² + ρ (Σ x_c)²``.  ``V = Uᵀ W U`` (``W`` the Bartlett
    weights, ``U = P g`` the scores at the fitted slope, ``P = I − h 1ᵀ / Σh``, ``h_k =
    Σ x_c²``) then has mean ``tr(W P D Pᵀ)`` (``factor`` = that over the numerator's
    variance ``Σ d_k``: the fitted slope and the negative autocovariances its residuals
    leave bias ``V`` low) and, Gaussian, variance ``2 tr((W D)²)``: Satterthwaite's ``ν =
    (Σ d)² / Σ_{k,j} W_kj² d_k d_j``.
    """
    n = int(k.max()) + 1
    h = np.bincount(k, xc * xc, minlength=n)
    sx = np.bincount(k, xc, minlength=n)
    cnt = np.bincount(k, minlength=n).astype(float)
    se = np.bincount(k, e, minlength=n)
    ss = float(e @ e)
    pairs = float(np.sum(cnt * (cnt - 1.0)))
    rho = 0.0
    if pairs > 0 and ss > 0:
        rho = float(np.clip((float(se @ se) - ss) / pairs / (ss / len(e)), 0.0, 1.0))
    d = (1.0 - rho) * h + rho * sx * sx
    S = float(d.sum())
    H = float(h.sum())
    if not (S > 0 and H > 0):
        return float(max(n - 1, 1)), 1.0

    def wdot(a: np.ndarray, c: np.ndarray, square: bool = False) -> float:
        """``aᵀ W c`` (or with the squared weights ``W_kj²``)."""
        tot = float(a @ c)
        for lag in range(1, L + 1):
            w = 1.0 - lag / (L + 1.0)
            w = w * w if square else w
            tot += w * float(a[lag:] @ c[:-lag] + a[:-lag] @ c[lag:])
        return tot

    mean_v = S - 2.0 * wdot(h, d) / H + S * wdot(h, h) / H**2
    dof = S * S / wdot(d, d, square=True)
    return float(max(dof, 1.0)), float(max(mean_v / S, 0.05))


#: ordinates on each side of a periodogram peak that are its reference (beyond the main lobe
#: of the Hann taper, ±2 ordinates, which a peak between ordinates fills)
PERIODIC_NEIGHBOURS = 16
#: the reference's effective dof per ordinate it averages (the taper correlates neighbours;
#: simulated on white noise: 32 ordinates act as ~19-22 independent ones; 0.6 keeps the
#: tail's p at or above the simulated rate)
PERIODIC_DOF_SHARE = 0.6


_GH_X, _GH_W = np.polynomial.hermite_e.hermegauss(24)  # standard-normal nodes, weights
_GH_LOGW = np.log(_GH_W / _GH_W.sum())


def fisher_g(y: np.ndarray) -> tuple[float, int]:
    """Fisher's g test of a white series ``y`` for one hidden periodic term.

    The periodogram's largest ordinate over their sum (mean removed; the m ordinates
    between the mean's and the Nyquist rate's), its exact tail under white Gaussian ``y``
    (Fisher 1929: ``p = Σ_{j=1}^{⌊1/g⌋} (-1)^{j-1} C(m, j) (1 - j g)^{m-1}``).  For a
    series that is white when no period is there (the increments of a random walk's
    estimate, :func:`~stellar_cal_ros.diagnosis.noise_runs.walk_motion`); red series need
    :func:`_local_peak`.  Returns ``(p, k)``: the tail and the ordinate's index (the
    period is ``len(y) / k`` samples); ``(nan, 0)`` below 8 samples.
    """
    y = np.asarray(y, dtype=float)
    n = len(y)
    if n < 8:
        return math.nan, 0
    spec = np.abs(np.fft.rfft(y - y.mean())) ** 2
    spec = spec[1:(n - 1) // 2 + 1]
    m = len(spec)
    total = float(spec.sum())
    if not total > 0.0:
        return 1.0, 0
    k = int(np.argmax(spec))
    g = float(spec[k]) / total
    p = sum((-1) ** (j - 1) * math.comb(m, j) * (1.0 - j * g) ** (m - 1)
            for j in range(1, int(1.0 / g) + 1))
    return float(min(max(p, 0.0), 1.0)), k + 1


def _local_peak(spec: np.ndarray, red: bool = False) -> tuple[int, float, float]:
    """The periodogram ordinate highest over its neighbours' level: ``(index, ratio, tail)``.

    Each ordinate of the tapered periodogram is referred to the ``2 N`` ordinates nearest
    to it beyond its main lobe (:data:`PERIODIC_NEIGHBOURS` on each side, more on one side
    at the ends of the range).  By default to their mean: under a spectrum flat on that
    scale the ratio is about ``F(2, 2J)``, ``J`` the reference's effective count
    (:data:`PERIODIC_DOF_SHARE`), so ``P(ratio > g) = (1 + g/J)^(−J)``.

    ``red`` (the stars' noise is correlated from frame to frame along their tracks, which
    makes the frame means red): to the level a straight line through the log of the same
    ordinates gives at it, ``exp(a + γ)`` (``γ`` Euler's: the log of an exponential ordinate
    reads ``γ`` low on average).  At the low end of the range every neighbour lies above in
    frequency and a red spectrum's mean of them falls below the ordinate's own level:
    ``benchmarks/periodic_red_level.py`` (AR(1) tracks, ρ 0.82) read 61 % / 22 % of the
    tests below 1 % at 150 / 300 frames with the mean, 1.3 % / 0.8 % with the line
    (white: 1.25 % / 1.15 %, the mean 1.05 % / 1.20 %).  The line's error at the ordinate,
    ``e ~ N(0, v)``, ``v = (π²/6) × leverage / share`` (the log of an exponential has
    variance ``π²/6``; :data:`PERIODIC_DOF_SHARE` for the taper's correlation), makes the
    tail ``E[exp(−g e^e)]`` (Gauss–Hermite).  The line is not the default: extrapolated to
    the low end it has ~5x the mean's variance, and a real wobble there loses that power
    (unseen case ``wobble``: p 1.6e-30 with the mean, 1.1e-6 with the line, ranked third).

    Returns the ordinate with the smallest tail, its ratio and that tail.
    """
    n = len(spec)
    best = (0, 0.0, 1.0)
    c = np.concatenate([[0.0], np.cumsum(spec)])
    lg = np.log(np.maximum(spec, 1e-300)) if red else None
    want = 2 * PERIODIC_NEIGHBOURS
    for k in range(n):
        a, b = max(k - 2, 0), min(k + 3, n)  # the main lobe, not the reference
        # the 2N ordinates nearest outside it (one side longer at the ends of the range)
        left = min(PERIODIC_NEIGHBOURS, a)
        right = min(want - left, n - b)
        left = min(want - right, a)
        lo, hi = a - left, b + right
        cnt = left + right
        if cnt < 4:
            continue
        if lg is None:
            tot = c[hi] - c[lo] - (c[b] - c[a])
            if not tot > 0:
                continue
            g = float(spec[k] / (tot / cnt))
            dof = PERIODIC_DOF_SHARE * cnt
            tail = (1.0 + g / dof) ** (-dof)
        else:
            x = np.r_[np.arange(lo, a), np.arange(b, hi)]
            y = lg[x]
            x = (x - k).astype(float)
            xm, ym = x.mean(), y.mean()
            sxx = float(((x - xm) ** 2).sum())
            slope = float(((x - xm) * (y - ym)).sum() / sxx)
            at_k = ym - slope * xm  # the line at the ordinate (x = 0)
            sd = math.sqrt(math.pi**2 / 6.0 / PERIODIC_DOF_SHARE * (1.0 / cnt + xm * xm / sxx))
            g = float(spec[k] / math.exp(at_k + np.euler_gamma))
            # in logs: a wobble's ratio of ~1e5 leaves every node's exp(-g e^e) below 1e-300
            tail = math.exp(max(float(logsumexp(_GH_LOGW - g * np.exp(sd * _GH_X))), -690.0))
        if tail < best[2]:
            best = (k, g, tail)
    return best


#: ordinates below the frames' Nyquist rate within which a peak's lobe is searched up to it
NYQUIST_REACH = 5
#: frequencies tried between the peak ordinate's two neighbours (:func:`_fitted_sinusoid`)
SINUSOID_STEPS = 33


def _fitted_sinusoid(t: np.ndarray, y: np.ndarray, f_lo: float, f_hi: float
                     ) -> tuple[float, float]:
    """``(period, amplitude)`` of the least-squares sinusoid in ``y(t)`` explaining most of it.

    Frequencies from ``f_lo`` to ``f_hi`` (:data:`SINUSOID_STEPS`, the peak ordinate's
    neighbours: its main lobe): a period between ordinates, or at the frames' Nyquist rate
    (an ordinate the periodogram leaves out; its taper's lobe finds it), fitted at an
    ordinate's frequency reads a fraction of its amplitude (unseen case ``arm_1hz``: a
    1-Hz vibration of the tracker, 2-Hz frames, read 9e-5 and 0.0015 px for frame means
    alternating by 0.066 and 0.051 px).  At the Nyquist rate the sine and cosine are one
    column: the minimum-norm fit's amplitude is the alternation's.
    """
    best = (-1.0, 1.0 / max(f_hi, 1e-300), 0.0)
    t = t - t[0]  # POSIX seconds would round the phase
    for f in np.linspace(max(f_lo, 0.5 * (f_hi - f_lo) / (SINUSOID_STEPS - 1)), f_hi,
                         SINUSOID_STEPS):
        w = 2.0 * np.pi * f
        X = np.stack([np.sin(w * t), np.cos(w * t)], 1)
        c = np.linalg.lstsq(X, y, rcond=1e-6)[0]  # one column at the Nyquist rate
        ss = float(np.sum((X @ c) ** 2))
        if ss > best[0]:
            best = (ss, 1.0 / f, float(np.hypot(*c)))
    return best[1], best[2]


def periodic_findings(res: Table, mask: np.ndarray, red: bool = False
                      ) -> list[RegressorFinding]:
    """A periodic residual every star of a frame shares (u and v): Fisher's g test.

    A motion of the tracker against the IMU that the gyro does not see (a wobble) moves
    every star of a frame alike and comes back with its period: no star regressor follows
    it and a straight line in time averages it out.  Per component, the frames' mean
    innovation (px, the evaluation window, frames in time order) is tested for one periodic
    term: the (tapered) periodogram's ordinate highest over its neighbours
    (:func:`_local_peak`, their mean, or with ``red`` — the stars' noise found correlated
    along their tracks — their log-linear level; Bonferroni over the m ordinates).  Not
    Fisher's g (the largest ordinate over all of them), which assumes white frame means:
    centroid noise correlated over a few frames makes them red, and the low ordinates then
    beat the sum without any period (measured: unseen case ``ar1``, p = 2.5e-5 and 1.6e-3);
    the neighbours' mean is not enough for that either at the low end of the range
    (:func:`_local_peak`'s ``red``).  The size is the amplitude (px) of the sinusoid fitted
    within the peak's lobe (:func:`_fitted_sinusoid`), its period in the name.  Returns
    unadjusted findings (regressor ``time (periodic, P s)``), for :func:`regressor_tests`'
    ``extra``.
    """
    m = mask & accepted(res)
    out: list[RegressorFinding] = []
    if m.sum() < 20:
        return out
    frame = np.asarray(res["frame"])[m]
    uniq, inv = frames_of(frame)
    if len(uniq) < 32:
        return out
    cnt = np.bincount(inv).astype(float)
    t = np.bincount(inv, np.asarray(res["t"], dtype=float)[m]) / cnt
    order = np.argsort(t)
    t = t[order]
    for comp, key in (("frame mean u", "du"), ("frame mean v", "dv")):
        y = (np.bincount(inv, np.asarray(res[key], dtype=float)[m]) / cnt)[order]
        y = y - y.mean()
        # Hann-tapered: a period between ordinates stays within ±2 of them
        spec = np.abs(np.fft.rfft(y * np.hanning(len(y)))[1:-1]) ** 2  # no mean, no Nyquist
        n_ord = len(spec)
        if n_ord < 2 * PERIODIC_NEIGHBOURS or not spec.sum() > 0:
            continue
        k, _, tail = _local_peak(spec, red)
        p = float(min(1.0, n_ord * tail))
        span = (t[-1] - t[0]) * len(y) / (len(y) - 1)  # the ordinates' 1 / spacing
        # the frames' Nyquist rate from their own spacing (an odd count's last ordinate
        # lies half a spacing below it; gated frames' gaps flip the alternation's phase
        # and spread its peak a few ordinates below): reached when the lobe comes within
        # NYQUIST_REACH ordinates of it; at least one cycle in the window (below, a
        # sinusoid fits any trend and reads more than the frame means' range)
        nyquist = 0.5 / float(np.median(np.diff(t)))
        hi = (k + 2) / span
        period, amp = _fitted_sinusoid(
            t, y, max(k, 1) / span, nyquist if hi >= nyquist - NYQUIST_REACH / span else hi)
        z = float(dist.norm.isf(max(p, 1e-300) / 2.0))
        out.append(RegressorFinding(f"time (periodic, {period:.3g} s)", comp, z, p, amp))
    return out


#: regressors that vary from star to star within a frame (tested on the within-frame
#: residuals); the others are properties of the frame (tested on the innovations)
STAR_REGRESSORS = ("magnitude", "u (column)", "v (row)", "radius")


def _components(sub: Table, du: np.ndarray, dv: np.ndarray, su: np.ndarray,
                sv: np.ndarray, suv: np.ndarray, centre: tuple[float, float]) -> dict:
    """Whitened u, v, radial and size components, and the same in px (for the size)."""
    cx, cy = centre
    du_, dv_ = sub["u"] - cx, sub["v"] - cy
    r = np.hypot(du_, dv_)
    radial = (du * du_ + dv * dv_) / np.maximum(r, 1e-9)
    sigma_r = np.sqrt(np.maximum((su * du_**2 + 2 * suv * du_ * dv_ + sv * dv_**2)
                                 / np.maximum(r, 1e-9) ** 2, 1e-300))
    w = whitened({"du": du, "dv": dv, "s_uu": su, "s_uv": suv, "s_vv": sv})
    return {"u": (w[:, 0], du), "v": (w[:, 1], dv), "radial": (radial / sigma_r, radial),
            "size": (w[:, 0] ** 2 + w[:, 1] ** 2, np.hypot(du, dv))}


#: regressor names of the tests shaped like a tracker's readout and centroiding
#: (:func:`shaped_tests`)
SUBPIXEL = "sub-pixel phase"
ROLLING = "v (row) x image velocity (rolling-shutter shape"
#: the rolling-shutter regressor's name by readout direction (:data:`READOUT_AXES`): rows
#: read one after the other (``v``, :data:`ROLLING`) or columns (``u``: a detector mounted
#: a quarter turn round, or one read column by column)
ROLLING_NAMES = {"v": ROLLING, "u": "u (column) x image velocity (rolling-shutter shape"}
#: the readout directions a rolling shutter is tested along, rows first (each one test of
#: the family, :func:`shaped_tests`; the nuisance fit's Bonferroni factor,
#: :func:`rolling_remainder`)
READOUT_AXES = ("v", "u")


def rolling_axis(regressor: str) -> str | None:
    """The readout direction (``"v"`` rows, ``"u"`` columns) of a rolling-shutter line."""
    return next((a for a, n in ROLLING_NAMES.items() if regressor.startswith(n)), None)


def readout_extent(axis: str, width: float | None, height: float | None) -> float | None:
    """The detector's extent (px) along a readout direction: its rows ``height`` for ``v``."""
    return height if axis == "v" else width

#: the word of a ripple's regressor name (:func:`shaped_tests`: ``u (column) (periodic
#: 455 px, sin)``), and its periods across the detector: a few, each period well above a
#: cell of the noise's grid and the stars' spacing (the ``unseen_cases`` ripple has 3)
RIPPLE = "periodic"
POSITION_PERIODS = (1, 2, 3, 4)
#: regressor name of the radial step tests (:func:`shaped_tests`: the step's radius follows)
ZONE = "radius (a radial step at"
#: the radial step tests' radii: these percentiles of the stars' distances from the centre
ZONE_PERCENTILES = (25.0, 50.0, 75.0)


def zone_step(r_vec: np.ndarray, radius: float, scale: bool = False) -> np.ndarray:
    """The radial step at ``radius`` (px) as displacements ``(n, 2)`` of the stars ``r_vec``.

    ``r_vec``: the stars' positions less the centre (px).  The step (1 beyond ``radius``,
    0 within, along each star's radius) less what the camera's radial polynomial (r, r³,
    r⁵ on these stars: the focal length and radial distortion the model fits) takes of
    it; NaN where a position is not finite.  What :func:`shaped_tests` tests.  ``scale``:
    the step of the image scale itself, ``r / radius`` beyond it (1 at the radius, growing
    outward as a zone's second focal length moves the stars), what :func:`~stellar_cal_ros.
    diagnosis.leads.zone_without` takes out (the unit step left the growth beyond it: the
    lines of the steps at the other radii, unseen case ``lens_zone`` s21's 338 px line).
    """
    r = np.hypot(r_vec[:, 0], r_vec[:, 1])
    fin = np.isfinite(r)
    unit = r_vec / np.maximum(r, 1e-9)[:, None]
    rn = r / np.max(r[fin])
    poly = np.stack([(rn ** k)[fin] for k in (1, 3, 5)], 1)
    step = (r[fin] > radius) * (r[fin] / radius if scale else 1.0)
    left = np.full(len(r), np.nan)
    left[fin] = step - poly @ np.linalg.lstsq(poly, step, rcond=None)[0]
    return unit * left[:, None]


def zone_radius(f) -> float | None:
    """The radius (px) of a radial step's line ``f`` (:data:`ZONE`), ``None`` for another line."""
    if not f.regressor.startswith(ZONE):
        return None
    return float(f.regressor[len(ZONE):].split("px")[0])


def shaped_tests(sub: Table, inside: dict, sigma: np.ndarray, focal: tuple[float, float],
                 centre: tuple[float, float], R_imu_st: np.ndarray | None = None,
                 height: float | None = None,
                 track_lags: tuple[float, float] | None = None,
                 width: float | None = None) -> list[RegressorFinding]:
    """Tests of two tracker errors no straight line in one regressor follows (unadjusted).

    **Sub-pixel phase** (pixel locking, an S-curve): a centroid of an under-sampled PSF is
    pulled toward the pixel centre by ``A sin(2π u)`` in u and ``A sin(2π v)`` in v
    (pixel centres on integers; the cosines are the second test, for a phase a quarter
    pixel off): the within-frame residuals (u and v stacked, the frames as units,
    :func:`frame_robust_t`) regressed on ``sin(2π u)``, ``sin(2π v)`` of the *predicted*
    centroid (its phase has no noise of the star's own measurement in it), projected like
    the residuals.  The size is about ``2 A`` (the change across the regressor's 5–95 %
    range).

    **Rolling shutter**: a row ``v`` read out ``(v − c_y)/H · T`` after the stamp moves
    each star by its image velocity times that; the image velocity is ``J ω`` (the star's
    :func:`attitude_columns`, the gyro rate in the tracker frame: ``R_imu_st`` the
    installation; without it or the detector's rows ``height`` the test is not made).
    Regressor ``(v − c_y) J ω``, projected like the residuals on what no frame attitude
    explains; the readout time ``|T|`` (ms, :func:`readout_s` of the slope: over the
    detector's rows; its sign, the readout's direction, is the slope's) is in the
    regressor's name, as the period is in :func:`periodic_findings`'.

    **A ripple over the detector** (a structure periodic in position, which no straight line
    in u or v follows and no polynomial distortion of the library makes: a stitched
    detector's or a flat-field's periodic centroid error): for each axis ``a`` (u over the
    detector's ``width``, v over its ``height``, without them ``2 c``), each of
    :data:`POSITION_PERIODS` ``k`` periods across it, each displaced axis (u, v) and each
    phase, the pattern ``sin`` (or ``cos``) ``(2π k a / extent)`` along that axis, projected
    like the residuals and tested as the others (``8 k_max`` tests, each counted in the
    family).  The size is the amplitude of the sine and cosine fitted together (px; the
    same on both findings of a pair), the period (px) in the regressor's name
    (:data:`RIPPLE`).
    """
    out: list[RegressorFinding] = []
    frame = np.asarray(sub["frame"])
    (yu, yu_px), (yv, yv_px) = inside["u"], inside["v"]
    y = np.concatenate([yu, yv])
    y_px = np.concatenate([yu_px, yv_px])
    cl = np.concatenate([frame, frame])
    star = star_tracks(sub)
    tr = None if star is None else np.concatenate([star, star])
    u, v = predicted_position(sub, "u"), predicted_position(sub, "v")

    fits: list[FrameFit] = []  # (the frames' fit, made once for every regressor)
    # (the rows a test takes, with their frames' index: the same for every regressor
    # projected through the frames' fit, NaN outside it; taken once while they stay)
    rows: list[tuple] = []
    ripple: list[tuple] = []

    def taken(ok: np.ndarray) -> tuple:
        """``(cl, tr, y, y_px, frame index)`` of the rows ``ok``."""
        if not rows or not np.array_equal(ok, rows[0][0]):
            c = cl[ok]
            rows[:] = [(ok, c, None if tr is None else tr[ok], y[ok], y_px[ok],
                        frame_index(c))]
        return rows[0][1:]

    def centred(ok: np.ndarray) -> np.ndarray:
        """``y_px`` of the rows ``ok`` less their mean (the ripples' rows: taken once)."""
        if not ripple or not np.array_equal(ok, ripple[0][0]):
            ripple[:] = [(ok, y_px[ok] - y_px[ok].mean())]
        return ripple[0][1]

    def project(xy: np.ndarray) -> np.ndarray:
        """``(n, 2)`` regressor → its part no frame attitude explains, u and v stacked."""
        if not fits:
            fits.append(FrameFit(sub, sigma, *focal))
        r = fits[0].residual(xy[:, 0] * sigma, xy[:, 1] * sigma)
        return np.concatenate([r[:, 0], r[:, 1]])

    def one(name, x: np.ndarray, component: str = "u, v",
            size: float | None = None) -> None:
        """One test of ``x``; ``name``: the regressor's name, or a function of the slope.

        ``size``: the finding's size (default: the slope's change over ``x``'s 5–95 %).
        """
        ok = np.isfinite(x) & np.isfinite(y)
        if ok.sum() < 40:
            return
        c, t_ok, y_ok, px_ok, k = taken(ok)
        x = x[ok]
        if int(k.max()) < 9 or not np.ptp(x) > 0:
            return
        t, p = frame_robust_t(x, y_ok, c, track=t_ok, track_lags=track_lags, index=k)
        xc = x - x.mean()
        b = float(xc @ px_ok) / float(xc @ xc)
        lo, hi = np.percentile(x, [5, 95])
        out.append(RegressorFinding(name if isinstance(name, str) else name(b), component,
                                    float(t), float(p), b * (hi - lo) if size is None
                                    else size))

    for fn, label in ((np.sin, "sin"), (np.cos, "cos")):
        one(f"{SUBPIXEL} ({label} 2 pi u, {label} 2 pi v)",
            project(np.stack([fn(2.0 * np.pi * u), fn(2.0 * np.pi * v)], 1)))
    extents = (width if width else 2.0 * centre[0], height if height else 2.0 * centre[1])
    for axis, pos, extent in (("u (column)", u, extents[0]), ("v (row)", v, extents[1])):
        for k in POSITION_PERIODS:
            ph = 2.0 * np.pi * k * pos / extent
            for d, comp in enumerate(("u", "v")):
                cols = []
                for fn in (np.sin, np.cos):
                    xy = np.zeros((len(pos), 2))
                    xy[:, d] = fn(ph)
                    cols.append(project(xy))
                X = np.stack(cols, 1)
                # (column by column: np.all over a row of 2 is a slow reduction)
                ok = np.isfinite(cols[0]) & np.isfinite(cols[1]) & np.isfinite(y_px)
                amp = float(np.hypot(*np.linalg.lstsq(X[ok], centred(ok), rcond=None)[0])) \
                    if ok.sum() >= 40 else math.nan
                for x, label in zip(cols, ("sin", "cos"), strict=True):
                    one(f"{axis} ({RIPPLE} {extent / k:.0f} px, {label})", x, comp, amp)
    r_vec = np.stack([u - centre[0], v - centre[1]], 1)
    r = np.hypot(r_vec[:, 0], r_vec[:, 1])
    fin = np.isfinite(r)
    if fin.sum() >= 40:
        for q in np.percentile(r[fin], ZONE_PERCENTILES):
            one(f"{ZONE} {q:.0f} px: the image scale beyond it not the scale within)",
                project(zone_step(r_vec, q)))
    for axis in READOUT_AXES:
        extent = readout_extent(axis, width, height)
        x = rolling_columns(sub, focal, centre, R_imu_st, axis) if extent else None
        if x is not None:
            one(lambda b, a=axis, e=extent:
                f"{ROLLING_NAMES[a]}, readout {readout_s(b, None, e) * 1e3:.3g} ms)",
                project(x))
    return out


#: regressor name of :func:`motion_spread` (the stamp noise's size follows in the name)
MOTION = "image rate, frame to frame (a noise in the frames' stamps"


def motion_spread(sub: Table, focal: tuple[float, float], centre: tuple[float, float],
                  R_imu_st: np.ndarray | None, columns: tuple | None = None,
                  stamp: float = 0.0) -> RegressorFinding | None:
    """A noise in the frames' stamps: spread along each star's image motion, frame to frame.

    A frame stamped ``δ_k`` off its exposure (a clock read with a jitter) moves every star
    of it by its image velocity ``u_i = J_i ω`` (:func:`attitude_columns`, the gyro rate
    in the tracker frame) times ``δ_k``: a rotation, which :func:`within_frame` takes out,
    and a spread of the innovations *along* the motion, large where the image moves fast
    (the slews) and independent from frame to frame.  The frame-robust tests
    (:func:`frame_robust_t`) join a slew's frames into a unit or two: the 'size' test
    against the rate reached t 2.0-2.6 on 1 ms (unseen case ``jitter``).

    ``sub``: the accepted stars tested (:func:`regressor_tests`' table, pixel locking
    already taken out where it is significant).  A rolling shutter's shape moves stars
    along their motion too, by their row, which changes from frame to frame in a slew: its
    fit over the run (:func:`rolling_columns`, one coefficient, :func:`whitened_fit`) is
    taken out first.  Per frame (:func:`frame_offsets`), the stamp offset its stars say,
    ``d_k = Σ uᵀ S⁻¹ ν / I_k``, ``I_k = Σ uᵀ S⁻¹ u`` (``S`` each star's innovation
    covariance), and the same across the motion (``u`` turned by 90° in the image: no
    stamp moves a star that way); then :func:`motion_test` on their differences between
    consecutive frames (an error that lasts longer than a frame interval, as the filter's
    along a slew or a constant time offset, cancels).  ``None`` without the installation,
    the rate columns or 10 pairs of frames.  ``columns``: :func:`motion_columns` of ``sub``
    when the caller has them (:func:`regressor_tests`: :func:`speed_curve` reads them too;
    made with ``stamp``).  ``stamp`` (s rms): the stamp noise the run stated in each
    frame's R: the test is of a spread beyond it (:func:`stamp_noise`'s ``sigma_t``).
    """
    got = frame_offsets(sub, focal, centre, R_imu_st, columns, stamp=stamp)
    return None if got is None else motion_test(*got, sigma_t=stamp)


def image_speed(vel: np.ndarray) -> np.ndarray:
    """Each star's image speed ``|u|`` (px/s) of its image velocity ``vel`` (n, 2)."""
    return np.hypot(vel[:, 0], vel[:, 1])


def speed_squared(vel: np.ndarray, scale: float = 1.0, speed: np.ndarray | None = None
                  ) -> np.ndarray:
    """The speed-squared column ``u |u| / scale`` (n, 2) of image velocities ``vel`` (n, 2).

    A bias along the motion that grows as the speed squared (a streak's clipped tail):
    :func:`speed_curve`'s regressor, the clock's smear part
    (:func:`~stellar_cal_ros.diagnosis.clock.flexure_products`' ``smear``) and the
    frame-common noise's motion fit (:mod:`~stellar_cal_ros.diagnosis.noise_structure`).
    ``speed``: :func:`image_speed` of ``vel`` where the caller has it.
    """
    if speed is None:
        speed = image_speed(vel)
    return vel * (speed / scale)[:, None]


#: regressor name of :func:`speed_curve` (its component :data:`CURVE_COMPONENT`)
CURVE = "image rate squared, beyond a time offset (a centroid bias along the motion that " \
    "grows faster than the speed: not in the library)"
#: :func:`speed_curve`'s component
CURVE_COMPONENT = "along-motion"


def speed_curve(sub: Table, columns: tuple | None) -> RegressorFinding | None:
    """A centroid bias along each star's image motion that grows as its speed squared.

    A bias along the motion *linear* in the image velocity ``u = J ω`` (px/s) is a time
    offset (in the library); one that grows faster (a streak's clipped tail: unseen case
    ``smear2``, 0.1 px at the 95th percentile speed ∝ speed²) leaves, beside the offset the
    model fits (its least-squares projection, 0.383 ms there), a remainder no other test
    reads: the frames' attitude fit takes it out of the within-frame residuals (a shift
    alike on a frame's stars), :func:`motion_spread` cancels it between consecutive frames,
    the clock's parts (:mod:`~stellar_cal_ros.diagnosis.clock`) see a constant.  The
    innovations (without a rolling shutter's fit, :func:`motion_columns`), the velocity
    ``u`` and ``u |u|``, each whitened by the innovation covariance (u and v of every
    star): ``u |u|`` and the innovations less their least-squares fit by ``u`` (any time
    offset the model leaves, Frisch–Waugh), then :func:`frame_robust_t` of one on the
    other, the frames the units.  The size: the fitted ``c (s² − k s)`` (``k s`` the
    offset's share of ``s²``) at its largest over speeds ``s`` up to the 95th percentile of
    the stars' image speed, px.  ``columns``: :func:`motion_columns` of ``sub``; ``None``
    without them (no rate columns), or with fewer than 10 frames.
    """
    if columns is None:
        return None
    ok, vel, nu, _ = columns
    cov = {k: np.asarray(sub[k], dtype=float)[ok] for k in ("s_uu", "s_uv", "s_vv")}
    speed = image_speed(vel)
    a, b, y = (whitened({"du": x[:, 0], "dv": x[:, 1], **cov}).ravel()
               for x in (vel, speed_squared(vel, speed=speed), nu))
    aa = float(a @ a)
    if not aa > 0:
        return None
    k = float(a @ b) / aa  # px/s: the offset's share of the speed squared
    b = b - k * a
    y = y - (float(a @ y) / aa) * a
    frame = np.repeat(np.asarray(sub["frame"])[ok], 2)
    if len(np.unique(frame)) < 10:
        return None
    t, p = frame_robust_t(b, y, frame)
    bb = float(b @ b)
    c = float(b @ y) / bb if bb > 0 else 0.0
    s95 = float(np.percentile(speed, 95))
    # c (s² − k s) over 0 ≤ s ≤ s95: at s95, or at its turning point k / 2
    size = abs(c) * max(abs(s95 * (s95 - k)), 0.25 * k * k if 0.0 < k < 2.0 * s95 else 0.0)
    return RegressorFinding(CURVE, CURVE_COMPONENT, float(t), float(p), size)


def accepted_offsets(res: Table, mask: np.ndarray, focal: tuple[float, float],
                     centre: tuple[float, float], R_imu_st: np.ndarray | None,
                     shared: dict | None = None
                     ) -> tuple[Table, tuple[np.ndarray, ...]] | None:
    """``mask``'s accepted stars and their :func:`frame_offsets` (``None``: too few, no columns).

    ``shared``: a dict its caller keeps for one ``(res, mask, focal, centre, R_imu_st)``:
    made on the first call, then read from it (the clock and step tests of one residual
    table take the same offsets: 2-h round, 457 000 rows); its ``"readout"``, where given,
    the rolling shutter's direction :func:`motion_columns` takes out (default the rows).
    """
    if shared is not None and "offsets" in shared:
        return shared["offsets"]
    m = np.asarray(mask, dtype=bool) & accepted(res)
    got = None
    if m.sum() >= 20:
        sub = Rows(res, m)
        got = frame_offsets(sub, focal, centre, R_imu_st,
                            readout=(shared or {}).get("readout", "v"))
        got = None if got is None else (sub, got)
    if shared is not None:
        shared["offsets"] = got
    return got


def frame_offsets(sub: Table, focal: tuple[float, float], centre: tuple[float, float],
                  R_imu_st: np.ndarray | None, columns: tuple | None = None,
                  readout: str = "v", stamp: float = 0.0) -> tuple[np.ndarray, ...] | None:
    """``(frames, g, I, g⊥, I⊥, speed)`` of :func:`motion_spread` (``None``: no columns).

    Per frame of ``sub`` (frame indices in time order): the scores ``g = Σ uᵀ S⁻¹ ν`` and
    information ``I = Σ uᵀ S⁻¹ u`` of a stamp offset along each star's image velocity
    ``u`` (px/s), the same across it; ``ν`` the innovations without their fit by a
    rolling shutter's shape; ``speed``: the 95th percentile of the stars' image speed
    (px/s).  ``columns``: :func:`motion_columns` of ``sub`` already made (not made again);
    ``readout``, ``stamp``: its rolling shutter's direction, the run's stated stamp noise.
    """
    got = motion_columns(sub, focal, centre, R_imu_st, readout, stamp) if columns is None \
        else columns
    if got is None:
        return None
    ok, vel, nu, Si = got
    perp = np.stack([-vel[:, 1], vel[:, 0]], 1)
    frames, k = frames_of(np.asarray(sub["frame"])[ok])
    g, info, gp, infop = (np.bincount(k, np.einsum("ni,nij,nj->n", x, Si, y),
                                      minlength=len(frames))
                          for x, y in ((vel, nu), (vel, vel), (perp, nu), (perp, perp)))
    speed = float(np.percentile(image_speed(vel), 95))
    return frames, g, info, gp, infop, speed


def frame_attitudes(sub: Table, focal: tuple[float, float]
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame of ``sub`` the rotation its stars say: ``(frames, g (n, 3), I (n, 3, 3))``.

    The scores ``g = Σ Jᵀ S⁻¹ ν`` and information ``I = Σ Jᵀ S⁻¹ J`` of a small rotation of
    the tracker (arcsec about its x, y, z), ``J`` the stars' :func:`attitude_columns`, ``S``
    each star's innovation covariance; ``I⁻¹ g`` the frame's rotation.  Frames in index
    order; those whose ``I`` is singular (fewer than two stars) are left out.
    """
    J = attitude_columns(sub, *focal) * ARCSEC  # px per arcsec
    a, b, c = (np.asarray(sub[k], dtype=float) for k in ("s_uu", "s_uv", "s_vv"))
    det = a * c - b * b
    nu = np.stack([np.asarray(sub["du"], dtype=float), np.asarray(sub["dv"], dtype=float)], 1)
    ok = (det > 0) & finite_rows(J.reshape(len(J), -1)) & finite_rows(nu)
    Si = np.stack([np.stack([c, -b], 1), np.stack([-b, a], 1)], 1)[ok] / det[ok, None, None]
    SJ = np.einsum("nij,njk->nik", Si, J[ok])
    frames, k = frames_of(np.asarray(sub["frame"])[ok])
    n = len(frames)
    gs = np.einsum("nik,ni->nk", SJ, nu[ok])
    Is = np.einsum("nij,nik->njk", J[ok], SJ)
    g = np.stack([np.bincount(k, gs[:, i], minlength=n) for i in range(3)], 1)
    info = np.stack([np.stack([np.bincount(k, Is[:, i, j], minlength=n) for j in range(3)], 1)
                     for i in range(3)], 1)
    good = np.linalg.cond(info) < 1e12 if n else np.zeros(0, dtype=bool)
    return frames[good], g[good], info[good]


def moving_frames(sub: Table, frames: np.ndarray, info: np.ndarray, share: float
                  ) -> np.ndarray:
    """Which of :func:`frame_offsets`' ``frames`` move: ``(len(frames),)`` bool.

    Each frame's image speed, the information-weighted rms of its stars' (px/s,
    ``√(I / Σ ½ tr S⁻¹)``, ``I`` its :func:`frame_offsets` information ``info``), at least
    ``share`` of the frames' 95th percentile (and ``info > 0``).  The frames at rest are the
    others: there a stamp offset moves no star, and any attitude error the model leaves
    reads as seconds of one (:mod:`~stellar_cal_ros.diagnosis.clock`,
    :mod:`~stellar_cal_ros.diagnosis.installation_step`).
    """
    a, b, c = (np.asarray(sub[k], dtype=float) for k in ("s_uu", "s_uv", "s_vv"))
    det = a * c - b * b
    tr = np.where(det > 0, 0.5 * (a + c) / np.where(det > 0, det, 1.0), 0.0)
    fr_all, k_all = frames_of(np.asarray(sub["frame"]))
    per = np.bincount(k_all, tr)[np.searchsorted(fr_all, frames)]
    speed = np.sqrt(np.where(per > 0, info / np.where(per > 0, per, 1.0), 0.0))
    return (info > 0) & (speed >= share * np.percentile(speed, 95))


def frame_times(sub: Table, frames: np.ndarray) -> np.ndarray:
    """The time ``t`` of each of ``frames`` (frame indices of ``sub``, sorted)."""
    fr_all, first = np.unique(np.asarray(sub["frame"]), return_index=True)
    return np.asarray(sub["t"], dtype=float)[first][np.searchsorted(fr_all, frames)]


def image_velocity(sub: Table, focal: tuple[float, float], R_imu_st: np.ndarray | None
                   ) -> np.ndarray | None:
    """Each star's image velocity (px/s, ``(n, 2)``), or None.

    Its :func:`attitude_columns` times the gyro rate in the tracker frame; None without the
    installation or the rate columns.
    """
    if R_imu_st is None or not all(k in sub for k in ("omega_x", "x_st")):
        return None
    w_st = np.stack([np.asarray(sub[k], dtype=float) for k in ("omega_x", "omega_y",
                                                              "omega_z")], 1) \
        @ np.asarray(R_imu_st, dtype=float)
    return np.einsum("nij,nj->ni", attitude_columns(sub, *focal), w_st)


def motion_columns(sub: Table, focal: tuple[float, float], centre: tuple[float, float],
                   R_imu_st: np.ndarray | None, readout: str = "v", stamp: float = 0.0
                   ) -> tuple[np.ndarray, ...] | None:
    """``(ok, u, ν, S⁻¹)`` of :func:`frame_offsets` (``None``: no columns).

    Its stars (a mask of ``sub``), their image velocity (px/s), innovations without the
    rolling shutter's fit along ``readout`` (:data:`READOUT_AXES`; :func:`readout_axis`)
    and inverse covariances.  ``stamp`` (s rms): the frames' stamp noise the run stated in
    each frame's R (``NoiseScales.stamp_ms``): each star's covariance is taken without its
    share ``stamp² u uᵀ`` (:func:`~stellar_cal_ros.core.covariance.stamp_column`, the same
    motion the stars' image velocity ``u`` is): one error per frame, common to its stars,
    which the per-star blocks cannot carry (:func:`stamp_noise` holds it in its null).
    """
    if len(sub.get("du", ())) < 20:
        return None
    vel = image_velocity(sub, focal, R_imu_st)
    if vel is None:
        return None
    nu = np.stack([np.asarray(sub["du"], dtype=float), np.asarray(sub["dv"], dtype=float)], 1)
    x = rolling_columns(sub, focal, centre, R_imu_st, readout)
    fit = whitened_fit(sub, x) if x is not None else None
    if fit is not None and np.isfinite(fit[2]):
        nu = nu - fit[2] * x
    a, b, c = (np.asarray(sub[k], dtype=float) for k in ("s_uu", "s_uv", "s_vv"))
    if stamp > 0:
        a, b, c = (a - stamp**2 * vel[:, 0] ** 2, b - stamp**2 * vel[:, 0] * vel[:, 1],
                   c - stamp**2 * vel[:, 1] ** 2)
    det = a * c - b * b
    ok = finite_rows(vel) & finite_rows(nu) & (det > 0) & (a > 0)
    if ok.sum() < 20:
        return None
    vel, nu, a, b, c, det = vel[ok], nu[ok], a[ok], b[ok], c[ok], det[ok]
    Si = np.stack([np.stack([c, -b], 1), np.stack([-b, a], 1)], 1) / det[:, None, None]
    return ok, vel, nu, Si


def motion_test(frames: np.ndarray, g: np.ndarray, info: np.ndarray, gp: np.ndarray,
                infop: np.ndarray, speed: float, sigma_t: float = 0.0
                ) -> RegressorFinding | None:
    """:func:`motion_spread`'s test on :func:`frame_offsets`' per-frame sums.

    ``d = g / I`` along, ``d⊥`` across; over consecutive frames ``j``, ``j + 1`` (both with
    stars) their differences ``Δa_j``, ``Δc_j``, each over its variance as stated, ``V_j
    = 1/I_j + 1/I_{j+1}``: ``A_j = Δa_j² / V_j``, ``C_j`` the same across.  Under the null
    both are ``κ χ²₁`` whatever the stated noise's scale ``κ``; a stamp noise of variance
    ``σ_t²`` adds ``2 σ_t² / V_j`` to ``A_j`` only.  Statistic: the ratio ``F = Σ h A / Σ h
    C`` (``h = 1/V``: the pairs a stamp noise moves most count most), referred to ``F(ν,
    ν)`` with Satterthwaite's ``ν = (Σ h)² / (Σ h² + 2 Σ h_j h_{j+1} ρ_j²)`` (``ρ_j = −(1/I_{j+1})
    / √(V_j V_{j+1})``: consecutive differences share a frame); one-sided.  (A Student t of
    ``Σ h (A − C)`` over ``κ`` read from the ``C`` alone was liberal: 32 % below 5 % on
    synthetic slews, the ratio of two χ² of ~15 dof.)  The size: ``σ̂_t² = Σ w (Δa² − Δc²) /
    (2 Σ w)`` with ``w = 1 / (2 σ̂₀² + V)²`` (``σ̂₀`` that with ``w = h²``: the pairs where
    the stamp noise dominates count alike), times ``speed``.  Returns a
    :class:`RegressorFinding` (regressor :data:`MOTION` with ``σ̂_t`` in ms, component
    ``along motion``, statistic the normal score of the one-sided p, unadjusted p, size px
    rms at ``speed``) or ``None`` (fewer than 10 pairs).  ``sigma_t`` (s rms): the stamp
    noise the run stated (:func:`stamp_noise`'s null): the line is of a spread beyond it,
    and says so.
    """
    got = stamp_noise(frames, g, info, gp, infop, sigma_t)
    if got is None:
        return None
    p, sig_t = got
    z = float(dist.norm.isf(p)) if p > 1e-300 else 37.0
    stated = f", {sigma_t * 1e3:.2g} ms stated" if sigma_t > 0 else ""
    return RegressorFinding(f"{MOTION}: {sig_t * 1e3:.2g} ms rms{stated}, {speed:.0f} px/s "
                            "at the 95th percentile of image speed)", "along motion", z, p,
                            sig_t * speed)


def stamp_noise(frames: np.ndarray, g: np.ndarray, info: np.ndarray, gp: np.ndarray,
                infop: np.ndarray, sigma_t: float = 0.0, beside: np.ndarray | None = None,
                beside_p: float = 0.01) -> tuple[float, float] | None:
    """:func:`motion_test`'s one-sided p and stamp noise ``σ̂_t`` (s rms): ``(p, σ̂_t)``.

    ``None`` with fewer than 10 pairs of consecutive frames (or no spread across the
    motion).  The one estimate of a noise in the frames' stamps: the line's
    (:func:`motion_test`) and the attitude step test's expected spread of a frame
    (:func:`~stellar_cal_ros.diagnosis.installation_step.installation_step`).
    ``sigma_t`` (s rms): a stamp noise the null holds (the one the run stated in each
    frame's R, ``NoiseScales.stamp_ms``; the offsets made without its share of the stars'
    covariance, :func:`motion_columns`): ``Δa`` then has the variance ``V_j + 2 σ_t²`` (and
    consecutive ones the covariance ``−(1/I_{j+1} + σ_t²)``), the p is of a noise beyond it;
    ``σ̂_t`` stays the whole stamp noise.  60 s of the swaying base, 1 ms stamps stated
    1 ms (seed 22): p 3.8e-8 without it, 0.86 with it; 2 ms stated 1 ms: 0.0079, 2.1 ms.
    ``beside``: per frame the along-motion offset (s per unit coefficient) of a
    deterministic column of the frames' motion
    (:func:`~stellar_cal_ros.diagnosis.clock.stamp_share`: a speed-squared smear's).  Its
    coefficient is fitted on the pairs' ``Δa`` with the variances ``V_a + 2 σ̂_t²`` (the
    stamp noise this test measured: a random stamp noise does not follow the speed, a smear
    does); where it is significant (two-sided ``beside_p``) it is taken out of the ``Δa``
    (weights ``1 / V_n``, the null's: ``V_a`` where no stamp noise is stated) and the test
    made again on what is left (one dof of some hundreds of pairs).  Not significant: the
    test without it, bit for bit.
    """
    use = (info > 0) & (infop > 0)
    j = np.flatnonzero(use[1:] & use[:-1] & (np.diff(frames) == 1))
    if len(j) < 10:
        return None
    safe = np.where(use, info, 1.0), np.where(use, infop, 1.0)
    d, dp = g / safe[0], gp / safe[1]
    da = d[j + 1] - d[j]
    Va = 1.0 / info[j] + 1.0 / info[j + 1]
    # (the null's stamp noise: along the motion only)
    Vn = Va + 2.0 * sigma_t**2 if sigma_t > 0 else Va
    got = _stamp_ratio(j, da**2, (dp[j + 1] - dp[j]) ** 2, info, infop, Va, Vn, sigma_t)
    if beside is None or got is None:
        return got
    dx = beside[j + 1] - beside[j]
    # (the column beside the stamp noise measured: its coefficient's z)
    Vs = Va + 2.0 * max(got[1], sigma_t) ** 2
    xx = float(np.sum(dx * dx / Vs))
    if not (xx > 0 and abs(float(np.sum(dx * da / Vs))) / math.sqrt(xx)
            > float(dist.norm.isf(beside_p / 2.0))):
        return got
    da = da - dx * (float(np.sum(dx * da / Vn)) / float(np.sum(dx * dx / Vn)))
    return _stamp_ratio(j, da**2, (dp[j + 1] - dp[j]) ** 2, info, infop, Va, Vn, sigma_t)


def _stamp_ratio(j: np.ndarray, da2: np.ndarray, dc2: np.ndarray, info: np.ndarray,
                 infop: np.ndarray, Va: np.ndarray, Vn: np.ndarray, sigma_t: float
                 ) -> tuple[float, float] | None:
    """:func:`stamp_noise`'s ratio test and ``σ̂_t`` on the pairs ``j``' squared differences."""
    Vc = 1.0 / infop[j] + 1.0 / infop[j + 1]
    V = 0.5 * (Va + Vc)
    h = 1.0 / V
    x, y = float(np.sum(h * da2 / Vn)), float(np.sum(h * dc2 / Vc))
    if not (y > 0 and np.isfinite(x)):
        return None
    # consecutive pairs share a frame: their squares correlate as 2 ρ²
    nxt = np.flatnonzero(j[1:] == j[:-1] + 1)
    # (with a stamp noise stated, the along pairs' own: they share its frame's σ_t² too)
    rho2 = 1.0 / (info[j[nxt] + 1] ** 2 * V[nxt] * V[nxt + 1]) if not sigma_t > 0 else \
        (1.0 / info[j[nxt] + 1] + sigma_t**2) ** 2 / (Vn[nxt] * Vn[nxt + 1])
    nu = float(np.sum(h) ** 2 / (np.sum(h * h) + 2.0 * np.sum(h[nxt] * h[nxt + 1] * rho2)))
    p = float(dist.f.sf(x / y, nu, nu))
    diff = da2 - dc2
    s2 = max(float(np.sum(h * h * diff) / (2.0 * np.sum(h * h))), 0.0)
    w = 1.0 / (2.0 * s2 + V) ** 2
    return p, float(np.sqrt(max(float(np.sum(w * diff) / (2.0 * np.sum(w))), 0.0)))


def stamp_line(res: Table, mask: np.ndarray, focal: tuple[float, float],
               centre: tuple[float, float], R_imu_st: np.ndarray | None, stamp: float = 0.0
               ) -> RegressorFinding | None:
    """:func:`motion_spread` on ``mask``'s accepted stars, its null's stamp noise ``stamp`` (s).

    The stamps' line as :func:`regressor_tests` makes it (unadjusted p), for a caller that
    wants that line alone (``benchmarks/stamp_noise_nis.py --motion``).
    """
    m = np.asarray(mask, dtype=bool) & accepted(res)
    sub = {k: v[m] for k, v in res.items()}
    cols = motion_columns(sub, focal, centre, R_imu_st, "v", stamp)
    return None if cols is None else motion_spread(sub, focal, centre, R_imu_st, cols, stamp)


def readout_s(first: float, rest: float | None, height: float) -> float:
    """The readout time (s) from the fit of a run and of its re-run with that fit taken out.

    The filter the innovations come from takes up part of the shutter's shape in its
    calibration (measured, 150 s PSCE bag, 30 ms: the principal point's row pulled by
    27 px), so one run's fit reads ``a`` × the truth, ``a`` ≈ 0.88 there (26.4 ms), while
    with the true readout taken out nothing is left (0.1-0.3 ms): attenuation by the
    fitted terms, not by an error in the regressor.  The re-run's fit of what is left,
    ``rest`` ≈ ``a (c − first)``, added: one fixed-point step (``(1 − a)² c`` short, 29.8
    ms measured; the two-run extrapolation ``first / (1 − rest/first)`` read 30.3 ms, the
    response not quite linear).  ``|c|`` × the detector's rows ``height`` (the simulator's
    ``(v/H − ½) T``; ``2 c_y`` would put the pulled principal point in it: 27.7 ms).  The
    one formula of every readout the diagnosis gives: the line's (this, from
    :func:`~stellar_cal_ros.diagnosis.rolling.first_if_cause`), the one-pass line's it
    falls back to (:func:`shaped_tests`, ``rest`` None) and :func:`rolling_remainder`'s
    ``readout_ms``.
    """
    return abs(first + (rest or 0.0)) * height


def predicted_position(sub: Table, axis: str) -> np.ndarray:
    """Column ``axis`` (``"u"`` or ``"v"``) of the predicted centroid, else the measured one.

    The predicted centroid carries no noise of its own frame, so a regressor of position
    (a sub-pixel phase, a rolling shutter's row) is not correlated with that frame's noise;
    tables without ``u_pred``/``v_pred`` fall back to the measured centroid.
    """
    key = f"{axis}_pred"
    return np.asarray(sub[key] if key in sub else sub[axis], dtype=float)


#: the residual table's columns :func:`rolling_columns` reads
ROLLING_KEYS = ("omega_x", "omega_y", "omega_z", "x_st", "y_st", "z_st", "v_pred", "v",
                "u_pred", "u")


def rolling_columns(sub: Table, focal: tuple[float, float], centre: tuple[float, float],
                    R_imu_st: np.ndarray | None, axis: str = "v") -> np.ndarray | None:
    """A rolling shutter's displacement per second of readout offset, ``(n, 2)`` px · px/s.

    ``(v − c_y) J ω``: the row's offset from the middle row times the star's image velocity
    (its :func:`attitude_columns` times the gyro rate in the tracker frame, ``R_imu_st`` the
    installation; ``v`` of the predicted centroid where there is one).  ``axis`` ``"u"``:
    a readout along the columns, ``(u − c_x) J ω``.  ``None`` without the installation or
    the rate columns.
    """
    if R_imu_st is None or not all(k in sub for k in ("omega_x", "x_st")):
        return None
    pos = predicted_position(sub, axis)
    w_b = np.stack([np.asarray(sub[k], dtype=float) for k in ("omega_x", "omega_y",
                                                              "omega_z")], 1)
    w_st = w_b @ np.asarray(R_imu_st, dtype=float)  # R^T ω per row
    vel = np.einsum("nij,nj->ni", attitude_columns(sub, *focal), w_st)
    return (pos - centre[0 if axis == "u" else 1])[:, None] * vel


def readout_axis(fit: dict | None, alpha: float = 0.01) -> str:
    """The rolling shutter's direction the noise's nuisance fits take out, from a table's fit.

    ``fit``: :func:`rolling_remainder` of both directions (its ``p_value`` × 2).  The
    columns (``"u"``) where the more significant direction is theirs and significant at
    ``alpha``; else the rows (``"v"``, what those fits took before a readout could be
    either's: a bag without a significant column readout keeps them bit for bit).  Read
    by the stars' noise (:func:`~stellar_cal_ros.diagnosis.noise_stars.star_noise`: a
    star keeps its column along its track, so a column readout repeats star by star) and
    the motion tests (:func:`motion_columns`).
    """
    return "u" if fit is not None and fit.get("axis") == "u" and fit["p_value"] < alpha \
        else "v"


def rolling_remainder(res: Table, mask: np.ndarray, centre: tuple[float, float],
                      focal: tuple[float, float], R_imu_st: np.ndarray | None,
                      height: float, width: float | None = None, axis: str | None = None
                      ) -> dict | None:
    """The innovations' fit by a rolling shutter's shape (a nuisance regressor).

    The innovations of ``mask``'s accepted stars and :func:`rolling_columns` along
    ``axis``, both whitened by the innovation covariance, u and v of every star; the frames
    as the units (:func:`frame_robust_t`).  ``{t, p_value, chi2 (the whitened sum of
    squares the fit removes), readout_ms (:func:`readout_s` over the detector's extent
    along the readout, :func:`readout_extent`), coefficient, axis}`` (``coefficient``: the
    fitted size, s per px of offset along the readout, signed: the innovations ≈ it × the
    columns; with its σ and ν as :func:`pattern_size`'s ``coef``; ``size_px`` the fitted
    displacement's 99th percentile over the stars), or ``None`` without the
    columns.  ``axis`` given: that direction's fit, ``p_value`` unadjusted.  ``axis``
    None: each direction of :data:`READOUT_AXES` the detector's extent allows (the
    columns need ``width``) fitted alone, the more significant one returned with its
    ``p_value`` × the directions fitted (Bonferroni: a readout of unknown direction is
    two tests, as in :func:`shaped_tests`' family) and ``by_axis``: every direction's own
    fit (``axis`` given), for a fit beside a candidate along the same direction
    (:func:`~stellar_cal_ros.diagnosis.rolling.along`).  What
    :func:`~stellar_cal_ros.diagnosis.flexure.beyond` takes beside a candidate: whether it
    explains the data beyond a rolling shutter (``discover``'s stand-in rule).
    """
    m = mask & accepted(res)
    if m.sum() < 20:
        return None
    sub = Rows(res, m)
    if axis is not None:
        return _rolling_fit(sub, focal, centre, R_imu_st, axis, width, height)
    fits = {a: _rolling_fit(sub, focal, centre, R_imu_st, a, width, height)
            for a in READOUT_AXES if readout_extent(a, width, height)}
    fits = {a: f for a, f in fits.items() if f is not None}
    if not fits:
        return None
    best = min(fits.values(), key=lambda f: (f["p_value"], -abs(f["t"])))
    return dict(best, p_value=min(1.0, best["p_value"] * len(fits)), by_axis=fits)


def _rolling_fit(sub: Table, focal: tuple[float, float], centre: tuple[float, float],
                 R_imu_st: np.ndarray | None, axis: str, width: float | None,
                 height: float | None) -> dict | None:
    """:func:`rolling_remainder` along one readout direction ``axis`` (``sub``: its stars)."""
    x = rolling_columns(sub, focal, centre, R_imu_st, axis)
    if x is None:
        return None
    fit = whitened_fit(sub, x, dof=True) or whitened_fit(sub, x)
    if fit is None:
        return None
    t, p, c, info = fit[:4]
    moved = np.hypot(x[:, 0], x[:, 1]) * abs(c)
    moved = moved[np.isfinite(moved)]
    return {"t": t, "p_value": p, "chi2": c * c * info,
            "chi2_capped": capped_gain(sub, x, c),
            "readout_ms": readout_s(c, None, readout_extent(axis, width, height)) * 1e3,
            "coefficient": c, "axis": axis,
            # (the fitted readout's displacement, 99th percentile over the stars, px)
            "size_px": float(np.percentile(moved, 99)) if moved.size else math.nan,
            **(pattern_size(sub, x, fit) or {})}


def whitened_fit(sub: Table, x: np.ndarray, dof: bool = False
                 ) -> tuple[float, ...] | None:
    """The innovations of ``sub`` fitted by one displacement pattern ``x`` (``(n, 2)`` px).

    Both whitened by the innovation covariance (:func:`whitened`), u and v of every star
    where both are finite; the frames as the units (:func:`frame_robust_t`).  ``(t, p
    (unadjusted), c, info)``: ``c`` the pattern's fitted size, ``info`` the whitened
    ``xᵀx`` (the fit removes ``c² info`` of χ²; ``1/√info`` is ``σ(c)`` only for stars
    independent within a frame: a pattern alike on a frame's stars sees the error they
    share, which the frame-robust σ ``t`` is made of holds; ``dof``: ν of the t_ν
    reference appended); ``None`` with fewer than 20 stars or no information, and with
    ``dof`` also when no test can be made (:func:`frame_robust_t` degenerate: the whitened
    pattern does not vary, or the innovations are exactly the fit; without ``dof`` ``t =
    0, p = 1`` then, and ``c``, ``info`` still hold).  The nuisance fits of ``discover``'s
    stand-in rules (a rolling shutter here, a mount flexure in
    :mod:`~stellar_cal_ros.diagnosis.flexure`).
    """
    cov = {k: sub[k] for k in ("s_uu", "s_uv", "s_vv")}
    w_nu = whitened(sub)
    w_x = whitened({"du": x[:, 0], "dv": x[:, 1], **cov})
    ok = finite_rows(w_x) & finite_rows(w_nu)
    # the rows ``ok`` taken once, the whole columns not held beside the test (the clock
    # test's fit over a 2-h run's every star is one of its round's peaks)
    w_x, w_nu = w_x[ok], w_nu[ok]
    info = float(np.sum(w_x**2))
    if ok.sum() < 20 or not info > 0:
        return None
    frame = np.repeat(np.asarray(sub["frame"])[ok], 2)
    t, p, nu = frame_robust_t(w_x.ravel(), w_nu.ravel(), frame, dof=True)
    if dof and nu is None:
        return None
    c = float(np.sum(w_x * w_nu)) / info
    return (float(t), float(p), c, info) + ((float(nu),) if dof else ())


def robust_sigma(sub: Table, x: np.ndarray, t: float, info: float) -> float | None:
    """The frame-robust standard error of the slope a pattern's ``t`` is of (its units).

    ``t``, ``info``: :func:`whitened_fit`'s for the pattern ``x`` (``(n, 2)``).  ``t`` is a
    centred slope over its frame-robust σ (:func:`frame_robust_t`), ``c`` the fit through
    the origin: ``|c / t|`` is that σ only when the two slopes agree, and blows up when
    ``t`` is near 0 (a flexure's test, seed 317: c = −0.74″/g, t = −0.027: "σ" 27.7″/g, MDB
    112″/g, against 2.5″/g whitened).  Moving the innovations by ``k x`` moves the slope by
    ``k`` and leaves its residuals, so its σ, unchanged: ``σ = k / (t(ν + k x) − t(ν))``,
    the same reference exactly.  ``None`` when the second fit fails.
    """
    k = 1.0 / np.sqrt(info)
    shifted = dict(sub, du=sub["du"] + k * x[:, 0], dv=sub["dv"] + k * x[:, 1])
    fit = whitened_fit(shifted, x)
    if fit is None or not fit[0] != t:
        return None
    return float(abs(k / (fit[0] - t)))


def pattern_size(sub: Table, x: np.ndarray, fit: tuple[float, ...] | None = None
                 ) -> dict[str, float] | None:
    """A pattern's fitted size with its frame-robust σ and ν, comparable between models.

    ``{coef, coef_sigma, coef_nu}``: :func:`whitened_fit`'s ``c`` of the pattern ``x`` (the
    fit given as ``fit``, with ν, when made already), its :func:`robust_sigma` (the
    whitened ``1/√info`` where that fails) and the ν of its t_ν reference.  What a nuisance
    field's fit on one model and on another (a candidate's) are compared by, the pattern
    being the same thing on both (:func:`size_changed`).  ``None`` when no test can be made.
    """
    fit = fit if fit is not None else whitened_fit(sub, x, dof=True)
    if fit is None or len(fit) < 5:
        return None
    t, _, c, info, nu = fit[:5]
    sigma = robust_sigma(sub, x, t, info)
    sigma = sigma if sigma and np.isfinite(sigma) else 1.0 / np.sqrt(info)
    return {"coef": float(c), "coef_sigma": float(sigma), "coef_nu": float(nu)}


def size_changed(beside: dict, before: dict, alpha: float) -> bool | None:
    """Whether a field's size beside a candidate has fallen from its size before, at ``alpha``.

    ``d = (coef_beside − coef_before) · sign(coef_before) / coef_sigma_beside`` referred to
    t_ν (ν beside's), one-sided: the size the current model's fit found taken as the value
    tested, against the field having moved toward 0 (a candidate taking it up; a field that
    grows beside it has not gone).  Measured on the cases it separates (300 s / 120 s
    psce_rotations): a true gyro scale factor after a time offset, −26.5 → −6.0 ± 5.8″/g on
    ν 6.4, p 0.0053 (fallen: the true effect added); gyro_misalignment beside a 40″/g
    flexure, 40.0 → 18.9 ± 4.4″/g on ν 2.6, p 0.012 (not: refused); beside an 80″/g one,
    83.3 → 57.7 ± 23.2″/g, p 0.15.  ``None`` when either fit carries no comparable size
    (:func:`pattern_size`'s keys).
    """
    keys = ("coef", "coef_sigma", "coef_nu")
    if not all(beside.get(k) is not None for k in keys) or before.get("coef") is None:
        return None
    d = (beside["coef"] - before["coef"]) * np.sign(before["coef"]) / beside["coef_sigma"]
    return bool(dist.t.cdf(d, beside["coef_nu"]) < alpha)


def capped_gain(sub: Table, x: np.ndarray, c: float, cap: float | None = None) -> float:
    """What a nuisance fit of the pattern ``x`` removes of the χ², each star's NIS capped.

    ``max over k of Σ min(q, cap) − Σ min(q_k, cap)`` over the stars of ``sub`` where both
    whitened vectors are finite (as :func:`whitened_fit`), ``q`` each star's NIS (whitened
    u² + v²) of the innovations and ``q_k`` of the innovations minus ``k x``; ``k`` searched
    between 0 and ``2 c`` (``c`` the least-squares size) and never worse than 0 or ``c``,
    so the gain is ≥ 0.  The currency of a candidate's ratio Λ (twice its gain in the
    log-likelihood whose per-star NIS is capped at ``cap``, by default the run's own
    :data:`stellar_cal_ros.methods.results.NIS_CAP`, :func:`log_likelihood`), so that the
    two can be added (:func:`~stellar_cal_ros.diagnosis.flexure.beyond`).  ``c² info`` is
    the uncapped gain, which on a far-off model is dominated by the stars Λ caps (a swaying
    bag at NIS/dof 135: 175 513 uncapped); the least-squares ``c`` itself can lose in the
    capped sum (a 10 ms time offset's baseline: −551.5 at ``c``), hence the search.
    """
    from scipy import optimize

    from stellar_cal_ros.methods import results

    cap = results.NIS_CAP if cap is None else cap
    cov = {k: sub[k] for k in ("s_uu", "s_uv", "s_vv")}
    w_nu = whitened(sub)
    w_x = whitened({"du": x[:, 0], "dv": x[:, 1], **cov})
    ok = finite_rows(w_x) & finite_rows(w_nu)
    w_nu, w_x = w_nu[ok], w_x[ok]
    base = float(np.sum(np.minimum(np.sum(w_nu**2, 1), cap)))

    def gain(k: float) -> float:
        return base - float(np.sum(np.minimum(np.sum((w_nu - k * w_x) ** 2, 1), cap)))

    best = max(0.0, gain(c))
    if c != 0.0 and np.isfinite(c):
        got = optimize.minimize_scalar(lambda k: -gain(k), bounds=sorted((0.0, 2.0 * c)),
                                       method="bounded", options={"xatol": 1e-6 * abs(c)})
        best = max(best, -float(got.fun))
    return best


def subpixel_removed(sub: Table) -> dict[str, np.ndarray]:
    """``du``, ``dv`` without their fit by ``sin, cos 2π u`` (``v`` for ``dv``).

    Of the predicted centroid: what is left of the innovations once pixel locking is taken
    out.
    """
    out = {}
    for key, axis in (("du", "u"), ("dv", "v")):
        ph = 2.0 * np.pi * predicted_position(sub, axis)
        X = np.stack([np.sin(ph), np.cos(ph), np.ones_like(ph)], 1)
        y = np.asarray(sub[key], dtype=float)
        ok = finite_rows(X) & np.isfinite(y)
        b = np.linalg.lstsq(X[ok], y[ok], rcond=None)[0]
        b[2] = 0.0  # the mean stays
        out[key] = y - X @ b
    return out


class LineSlope:
    """``np.polyfit(x, y, 1)[0]`` of one ``x`` and several ``y``: its scaled design made once.

    The same operations as ``np.polyfit`` (the same floats); where the design's rank falls
    short, ``np.polyfit`` itself (its warning).
    """

    def __init__(self, x: np.ndarray) -> None:
        self.x = np.asarray(x) + 0.0
        self.lhs = np.vander(self.x, 2)
        self.scale = np.sqrt((self.lhs * self.lhs).sum(axis=0))
        self.lhs /= self.scale
        self.rcond = len(self.x) * np.finfo(self.x.dtype).eps

    def slope(self, y: np.ndarray) -> float:
        """The slope of ``y`` (over the rows of ``x``) on ``x``."""
        c, _, rank, _ = np.linalg.lstsq(self.lhs, np.asarray(y) + 0.0, self.rcond)
        if rank != 2:
            return float(np.polyfit(self.x, y, 1)[0])
        return float((c.T / self.scale).T[0])


class _RegressorRows:
    """The rows ``ok`` of a regressor ``x`` as :func:`regressor_tests` tests them.

    Their frames (``cluster``, its :func:`frame_index` ``index``, the number ``frames``), stars,
    and where there are 10 frames or more the regressor's normal scores, 5-95 % range and
    :class:`LineSlope`: the same for each residual component finite on the same rows.
    """

    def __init__(self, x: np.ndarray, ok: np.ndarray, frame: np.ndarray,
                 star: np.ndarray | None) -> None:
        self.ok = ok
        self.cluster = frame[ok]
        self.index = frame_index(self.cluster)
        self.frames = int(self.index.max()) + 1 if len(self.index) else 0
        self.star = None if star is None else star[ok]
        if self.frames >= 10:
            xo = x[ok]
            self.scores = normal_scores(xo)
            self.range = np.percentile(xo, [5, 95])
            self.line = LineSlope(xo)


#: a noise's time trend (:func:`time_trend`): the means of this many stretches of the rows
#: (equal counts, in time order), joined by straight lines (a ramp or a step alike)
TREND_BINS = 8
#: ... taken out only where its stretches' means span more than this ratio (the variance's:
#: σ 5 %, the noise verdict's materiality; a stretch's mean of ~3 700 rows of a 300 s
#: window varies ~1.6 %, the ratio of 8 of them on white noise ~1.06)
TREND_SPAN = 1.1


def time_trend(t: np.ndarray, y: np.ndarray, weights: np.ndarray | None = None,
               use: np.ndarray | None = None) -> np.ndarray | None:
    """Each row's factor of ``y``'s mean as it changes with time ``t`` (a noise that grows).

    The mean of ``y`` (``Σ w y / Σ w`` with ``weights``) over :data:`TREND_BINS` stretches of
    the rows ``use`` (default all) in time order, linear between the stretches' mean times
    (and beyond, along the end segments; at least half the lowest mean): ``y / f`` is then
    the noise with its time trend taken out, and the factors are scaled so that ``Σ w y / f
    = Σ w y`` (the mean over the rows kept).  None where the stretches' means span at most
    :data:`TREND_SPAN` (or too few rows): no trend worth taking out.  The caller decides
    that the trend is significant (the noise whose σ grows over the run, unseen case
    ``noise_ramp``: a spread or a grouping tested against the stars in view, or the gravity
    direction, which change with time too, reads the time trend as theirs).
    """
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    w = np.ones(len(y)) if weights is None else np.asarray(weights, dtype=float)
    ok = np.isfinite(t) & np.isfinite(y) & np.isfinite(w) & (w > 0)
    if use is not None:
        ok &= np.asarray(use, dtype=bool)
    idx = np.flatnonzero(ok)
    if len(idx) < 20 * TREND_BINS:
        return None
    parts = _trend_parts(t, idx)
    sw = np.array([w[p].sum() for p in parts])
    at = np.array([w[p] @ t[p] for p in parts]) / sw
    level = np.array([w[p] @ y[p] for p in parts]) / sw
    if not (np.all(level > 0) and level.max() / level.min() > TREND_SPAN) or \
            np.any(np.diff(at) <= 0):
        return None
    f = np.maximum(_trend_line(t, at, level), 0.5 * level.min())
    return f * float((w[ok] * y[ok]) @ (1.0 / f[ok])) / float(w[ok] @ y[ok])


def _trend_parts(t: np.ndarray, idx: np.ndarray) -> list[np.ndarray]:
    """The rows ``idx`` in :data:`TREND_BINS` stretches of equal counts, in time order."""
    ti = t[idx]
    # (a residual table's rows are in time order: sorted only where they are not)
    return np.array_split(idx if np.all(ti[1:] >= ti[:-1]) else
                          idx[np.argsort(ti, kind="stable")], TREND_BINS)


def _trend_line(t: np.ndarray, at: np.ndarray, level: np.ndarray) -> np.ndarray:
    """The trend through ``level`` at the stretches' mean times ``at``, at each time ``t``.

    Linear between them, and beyond the end stretches too, along their segments (flat,
    the rows before the first stretch's mean time and after the last one's read a ramp's
    variance 13 % off, and the stars in view then, at the detector's edge as it drifts,
    read as a column group); linear in ``level``.
    """
    x = np.where(np.isfinite(t), t, at[0])
    f = np.interp(x, at, level)
    lo, hi = x < at[0], x > at[-1]
    f[lo] = level[0] + (x[lo] - at[0]) * (level[1] - level[0]) / (at[1] - at[0])
    f[hi] = level[-1] + (x[hi] - at[-1]) * (level[-1] - level[-2]) / (at[-1] - at[-2])
    return f


def regressor_tests(res: Table, mask: np.ndarray, camera_centre: tuple[float, float],
                    alpha: float = 0.01, focal: tuple[float, float] | None = None,
                    extra: list[RegressorFinding] | None = None,
                    R_imu_st: np.ndarray | None = None, height: float | None = None,
                    track_lags: tuple[float, float] | None = None,
                    width: float | None = None,
                    star_levels: bool = False,
                    family: dict | None = None, readout: str = "v", stamp: float = 0.0
                    ) -> list[RegressorFinding]:
    """Correlation of residual components (u, v, radial, size) with each regressor.

    One frame-robust score test per pair (:func:`frame_robust_t`: the frames, not the
    stars, are the independent units, and neighbouring frames may share an error);
    p-values Bonferroni-corrected over all pairs: at most ``alpha`` family-wise on a bag
    the model fits (``benchmarks/false_alarms.py``).  A regressor that varies within a
    frame (:data:`STAR_REGRESSORS`) is tested on the within-frame residuals
    (:func:`within_frame`, with ``focal`` = (fx, fy)): the attitude error every star of a
    frame shares is no evidence about magnitude or position, only noise for that test.  A
    property of the frame (time, rate, temperature, gravity) is tested on the innovations.
    Only pairs significant at ``alpha`` after correction are returned, most significant
    first (adjusted p, then ``|t|``), each with the size of the structure (the residual's
    change across the regressor's 5–95 % range, px).  ``extra``: further tests (unadjusted
    p) in the same family, e.g. the per-star repeat of
    :func:`~stellar_cal_ros.diagnosis.noise.repeat_finding`; one of :data:`CURVE_COMPONENT`
    (the clock's test's speed-squared smear) stands for :func:`speed_curve`'s.  With
    ``focal``, the within-frame residuals are also tested against the sub-pixel phase and
    (with the installation ``R_imu_st`` and the detector's rows ``height``) a rolling
    shutter's shape (:func:`shaped_tests`), and the innovations for a noise in the frames'
    stamps, their spread along each star's motion from frame to frame (:func:`motion_spread`,
    with the installation).  ``track_lags = (w, φ)``: the stars' noise
    correlated ``w φ^l`` along their tracks (:func:`frame_robust_t`; the size's as its
    squares, ``w² φ^(2l)``), ``None`` where the tracks are white.  ``star_levels``: the
    stated σ is wrong star by star (:func:`~.noise_stars.star_spread`, significant): the
    size is tested against each star's own level (:func:`frame_robust_t`'s ``track_level``).
    ``family``: a dict given gets the family's size (``"size"``: the Bonferroni factor).
    ``readout``: the direction of the rolling shutter the motion tests' innovations are
    read without (:func:`motion_columns`, :func:`readout_axis`).  ``stamp`` (s rms): the
    frames' stamp noise the run stated in each frame's R: the stamps' test is of a spread
    beyond it (:func:`motion_spread`).
    """
    m = mask & accepted(res)
    if m.sum() < 20:
        return []
    sub = {k: v[m] for k, v in res.items()}
    su, sv, suv = sub["s_uu"], sub["s_vv"], sub["s_uv"]
    sig = np.sqrt(np.maximum(0.5 * (su + sv), 1e-300))

    def components(sub):
        plain = _components(sub, sub["du"], sub["dv"], su, sv, suv, camera_centre)
        if focal is None:
            return plain, None
        r, lev, _ = within_frame(sub, sig, focal[0], focal[1])
        keep = np.clip(1.0 - 0.5 * lev, 1e-3, 1.0)  # each star's share of its 2 dof
        var = sig**2 * keep
        return plain, _components(sub, r[:, 0] * sig, r[:, 1] * sig, var, var,
                                  np.zeros_like(var), camera_centre)

    plain, inside = components(sub)
    regs = regressors(sub, camera_centre)
    shaped = shaped_tests(sub, inside, sig, focal, camera_centre, R_imu_st, height,
                          track_lags, width) if inside is not None else []
    # the family's size, at most (motion_spread's and speed_curve's tests among them)
    bound = 4 * len(regs) + len(shaped) + len(extra or []) + 2
    if any(f.regressor.startswith(SUBPIXEL) and f.p_value * bound < alpha for f in shaped):
        # the other regressors are tested on the residuals without the pixel locking (it
        # would lend them its per-dwell means: a 'radial vs gravity' lead, measured)
        sub = dict(sub, **subpixel_removed(sub))
        plain, inside = components(sub)
    frame = np.asarray(sub["frame"])
    star = star_tracks(sub)
    # a Gaussian's squares correlate as its correlation squared: the size's lags
    squared = None if track_lags is None else (track_lags[0] ** 2, track_lags[1] ** 2)
    tests = []
    # the spread's time trend, where its line against time is found: the other regressors'
    # spread tested beside it (their y over it), each kind of residual's own ({id: factor})
    trend: dict[int, np.ndarray | None] | None = None
    # (time first: the regressors' own order, in which it is already first)
    for rname, x in sorted(regs.items(), key=lambda kv: kv[0] != "time"):
        x = np.asarray(x, dtype=float)
        ok = np.isfinite(x)
        if ok.sum() < 20 or np.ptp(x[ok]) == 0:
            continue
        comps = inside if (inside is not None and rname in STAR_REGRESSORS) else plain
        on = None  # (the rows of x the components finite on the same rows share: made once)
        for cname, (y, y_px) in comps.items():
            if cname == "size" and trend and trend.get(id(comps)) is not None:
                f = trend[id(comps)]
                y, y_px = y / f, y_px / np.sqrt(f)
            ok2 = ok & np.isfinite(y)
            if on is None or not np.array_equal(ok2, on.ok):
                on = _RegressorRows(x, ok2, frame, star)
            if on.frames < 10:
                continue
            # on the regressor's normal scores: a skewed regressor (the angular rate, high
            # in a few frames only) must not let a handful of frames decide the test
            tstat, p = frame_robust_t(on.scores, y[ok2], on.cluster, track=on.star,
                                      track_lags=squared if cname == "size" else track_lags,
                                      track_level=star_levels and cname == "size",
                                      index=on.index)
            lo, hi = on.range
            slope = on.line.slope(y_px[ok2]) * (hi - lo)
            tests.append(RegressorFinding(rname, cname, float(tstat), float(p), float(slope)))
            if rname == "time" and cname == "size" and p * bound < alpha:
                # the stars' noise changes over the window (the line a noise that grows with
                # time makes, unseen case noise_ramp: its spread read against gravity_y_st
                # first, t 10.0, as the stars' attitude changes with time too)
                trend = {id(c): time_trend(sub["t"], c["size"][0]) for c in (plain, inside)
                         if c is not None}
    tests += shaped
    if focal is not None:
        # a noise in the frames' stamps: along each star's motion, frame to frame
        # (the stars' image velocity and innovations along it: made once for both)
        cols = motion_columns(sub, focal, camera_centre, R_imu_st, readout, stamp)
        moving = motion_spread(sub, focal, camera_centre, R_imu_st, cols, stamp) \
            if cols is not None else None
        # a bias along the motion that grows faster than a time offset's, unless the clock's
        # test fitted it beside its parts (its line among ``extra``, of the same component,
        # :data:`~stellar_cal_ros.diagnosis.clock.SMEAR_LINE`): one bias, one test and one
        # line (unseen case smear15 s22 printed both, the curve's at t -7.9)
        curve = None if any(t is not None and t.component == CURVE_COMPONENT
                            for t in extra or []) else speed_curve(sub, cols)
        tests += [t for t in (moving, curve) if t is not None]
    tests += [t for t in (extra or []) if t is not None]
    m_tests = max(len(tests), 1)
    if family is not None:
        family["size"] = m_tests
    found = []
    for tst in tests:
        tst.p_value = min(1.0, tst.p_value * m_tests)
        if tst.p_value < alpha:
            found.append(tst)
    found.sort(key=lambda f: (f.p_value, -abs(f.statistic)))
    for f in found:
        if inside is not None and f.component == "size" and f.regressor in STAR_REGRESSORS:
            # (the size the line prints: the innovations', read through the frames' fit;
            # only for a line found, its per-frame hat matrices are not free)
            # (over the noise's time trend where one was found, as its test was made)
            f.slope_px = size_through_fit(sub, sig, focal, np.asarray(regs[f.regressor],
                                                                      dtype=float),
                                          inside["size"][1],
                                          sub["t"] if trend and trend.get(id(inside))
                                          is not None else None)
    return found


def size_through_fit(sub: Table, sigma: np.ndarray, focal: tuple[float, float], x: np.ndarray,
                     size_px: np.ndarray, times: np.ndarray | None = None) -> float:
    """The innovations' size ``|ν|``'s change across ``x``'s 5–95 % range, from within-frame sizes.

    ``size_px``: ``σ_i ‖r_i‖`` of :func:`within_frame`'s residuals ``r = M ν/σ`` (``M = I −
    H``, each frame's attitude fit).  A straight line of those sizes in ``x`` reads the
    spread's change short: each star's own noise enters ``r_i`` as ``M_ii``, and the fit
    spreads a fraction of every star's noise over its frame (measured, a σ growing 20 % per
    magnitude on a psce bag's rows: 0.0181 px read for 0.0226 px, ~16 stars a frame).  With
    each star's per-axis variance ``v_j = α + β x_j``, ``E σ_i² ‖r_i‖² = Σ_j K_ij v_j`` exactly,
    ``K_ij = (σ_i/σ_j)² Σ_ab M_(ia,jb)²``: least squares of the squared sizes on ``(Σ_j K_ij,
    Σ_j K_ij x_j)`` gives ``α, β``, and the size is ``√(π/2) (√v(x95) − √v(x5))`` (a 2-D
    Gaussian's mean length), what a straight line of ``|ν|`` would read with no fit.

    ``times``: the rows' times, where the spread's line against time is found (the noise
    grows over the window, :func:`time_trend`): the sizes are read as ``v_j = h(t_j) (α + β
    x_j)``, ``h`` the time trend through :data:`TREND_BINS` stretches (:func:`_trend_line`)
    fitted jointly with ``α, β`` (alternating least squares; a frame's rows share a time,
    so ``E σ_i² ‖r_i‖² = h(t_i) Σ_j K_ij (α + β x_j)``), ``h``'s mean over the rows 1: the
    structure at the window's mean level.  Read without it, a regressor that changes with
    time (the stars in view as the attitude turns) takes the noise's growth as its own;
    read over :func:`time_trend`'s factors, those take the share of the structure the
    stars in view bring over time.
    """
    n = len(sigma)
    A = attitude_columns(sub, focal[0], focal[1]) / sigma[:, None, None]
    c = np.full((n, 2), np.nan)
    frames = np.asarray(sub["frame"])
    order = np.argsort(frames, kind="stable")
    for part in np.split(order, np.flatnonzero(np.diff(frames[order])) + 1):
        k = len(part)
        if k < 3:
            continue
        Ak = A[part].reshape(-1, 3)
        try:
            Gi = np.linalg.inv(Ak.T @ Ak)
        except np.linalg.LinAlgError:
            continue
        M = np.eye(2 * k) - Ak @ Gi @ Ak.T
        K = (M**2).reshape(k, 2, k, 2).sum(axis=(1, 3)) \
            * (sigma[part][:, None] / sigma[part][None, :]) ** 2
        c[part, 0] = K.sum(1)
        c[part, 1] = K @ x[part]
    ok = finite_rows(c) & np.isfinite(size_px) & np.isfinite(x)
    if ok.sum() < 3:
        return math.nan
    if times is None:
        (a, b), *_ = np.linalg.lstsq(c[ok], size_px[ok] ** 2, rcond=None)
    else:
        a, b = _through_time_trend(c[ok], size_px[ok] ** 2, np.asarray(times, float)[ok])
    lo, hi = np.percentile(x[ok], [5, 95])
    return float(math.sqrt(math.pi / 2) * (math.sqrt(max(a + b * hi, 0.0))
                                           - math.sqrt(max(a + b * lo, 0.0))))


def _through_time_trend(c: np.ndarray, y: np.ndarray, t: np.ndarray,
                        iterations: int = 50, tol: float = 1e-6) -> tuple[float, float]:
    """``α, β`` of ``y ≈ h(t) (c @ (α, β))``, ``h`` a :func:`_trend_line` of mean 1.

    Alternating least squares: ``α, β`` with ``h`` fixed, then the trend's levels at the
    :data:`TREND_BINS` stretches' mean times with ``α, β`` fixed, until ``h`` moves less
    than ``tol`` (:func:`size_through_fit`).  ``h`` starts flat (the plain fit).
    """
    t = np.where(np.isfinite(t), t, np.nanmedian(t))
    parts = _trend_parts(t, np.arange(len(t)))
    at = np.array([t[p].mean() if len(p) else np.nan for p in parts])
    h = np.ones(len(y))
    if len(y) < 20 * TREND_BINS or not np.all(np.diff(at) > 0):
        (a, b), *_ = np.linalg.lstsq(c, y, rcond=None)
        return float(a), float(b)
    basis = np.stack([_trend_line(t, at, e) for e in np.eye(TREND_BINS)], 1)
    for _ in range(iterations):
        (a, b), *_ = np.linalg.lstsq(c * h[:, None], y, rcond=None)
        p = c @ np.array([a, b])
        g, *_ = np.linalg.lstsq(basis * p[:, None], y, rcond=None)
        new = basis @ g
        new = np.maximum(new / new.mean(), 0.05)
        new /= new.mean()
        done = np.max(np.abs(new - h)) < tol
        h = new
        if done:
            break
    (a, b), *_ = np.linalg.lstsq(c * h[:, None], y, rcond=None)
    return float(a), float(b)


#: the camera's shape parameters :func:`shape_change` tests: the image scale (the focal
#: length, relative) and the detector's two tilts (OpenCV tau_x, tau_y, rad; to first order
#: a keystone ``(u − c_x, v − c_y) (1 + tau_x y − tau_y x)``, ``x, y`` normalised)
SHAPES = ("scale", "tau_x", "tau_y")


def shape_weight(shape: str, du, dv, focal: tuple[float, float]):
    """A shape parameter's radial factor at offsets ``(du, dv)`` from the principal point.

    The displacement per unit is the offset times it (:func:`shape_pattern`): ``scale`` 1
    (px per relative scale); ``tau_x`` ``dv / f_y``, ``tau_y`` ``−du / f_x`` (per rad:
    OpenCV's tilt matrix to first order, :func:`~stellar_cal_ros.core.camera.tilt_matrix`).
    Arrays or floats; the one place each shape's form is written (the rule's drift taken out
    and its corner size, :mod:`~stellar_cal_ros.diagnosis.shape_drift`, use it too).
    """
    if shape == "scale":
        return 1.0
    if shape == "tau_x":
        return dv / focal[1]
    if shape == "tau_y":
        return -du / focal[0]
    raise ValueError(f"unknown shape {shape!r} (one of {SHAPES})")


def shape_pattern(shape: str, u: np.ndarray, v: np.ndarray, centre: tuple[float, float],
                  focal: tuple[float, float]) -> np.ndarray:
    """A shape parameter's displacement per unit (px, ``(N, 2)``) at the points ``(u, v)``.

    The offset ``(u − c_x, v − c_y)`` times :func:`shape_weight`.
    """
    d = np.stack([u - centre[0], v - centre[1]], 1)
    w = shape_weight(shape, d[:, 0], d[:, 1], focal)
    return d if shape == "scale" else d * w[:, None]


def shape_change(res: Table, mask: np.ndarray, centre: tuple[float, float],
                 focal: tuple[float, float], shape: str = "scale", against=None
                 ) -> dict[str, float] | None:
    """A static camera shape left in the residuals, and its change over the window given it.

    The within-frame residuals of ``mask``'s accepted stars (u and v stacked, each frame's
    attitude fit taken out, the frames as the units of :func:`frame_robust_t`, as
    :func:`shaped_tests`) regressed on the shape's pattern (:func:`shape_pattern`: the
    image scale ``(u − c_x, v − c_y)``, or a detector tilt's keystone) (the *static* test:
    its slope the shape parameter, relative scale or rad) and on the pattern times
    ``(t − t_mid)``, both the regressor and the residuals taken without their static part
    (the *change* test: its slope the parameter per second; without the conditioning the
    static part left in the residuals swamps its frame-robust variance: unseen case
    ``focal_drift``, t 1.1-1.3 plain, 5.8-7.2 given the static scale;
    benchmarks/scale_time_read.py).  ``{static_t, static_p, static, change_t, change_p,
    change (over the window), rate_per_s (the change's slope, per s), window_s}`` (p
    unadjusted); ``None`` with fewer than 40 stars or 10 frames.  ``against(u, v)``: the
    displacement patterns ``(N, 2, k)`` of the camera parameters a model estimates; with it
    also ``spanned``, the share of the static pattern's sum of squares they span (a model
    that spans a shape follows it, late, as it follows its own parameters: unseen case
    ``tilt_drift``, the keystone of tau_x 0.99 spanned by psce's principal point and
    tangential p1).
    """
    m = mask & accepted(res)
    if m.sum() < 40:
        return None
    sub = Rows(res, m)
    sig = np.sqrt(np.maximum(0.5 * (sub["s_uu"] + sub["s_vv"]), 1e-300))
    fit = FrameFit(sub, sig, *focal)
    r = fit.residual(sub["du"], sub["dv"])
    var = sig**2 * np.clip(1.0 - 0.5 * fit.leverage, 1e-3, 1.0)
    inside = _components(sub, r[:, 0] * sig, r[:, 1] * sig, var, var, np.zeros_like(var),
                         centre)
    y = np.concatenate([inside["u"][0], inside["v"][0]])
    y_px = np.concatenate([inside["u"][1], inside["v"][1]])
    frame = np.asarray(sub["frame"])
    cl = np.concatenate([frame, frame])
    star = star_tracks(sub)
    tr = None if star is None else np.concatenate([star, star])
    u, v = predicted_position(sub, "u"), predicted_position(sub, "v")

    def project(xy: np.ndarray) -> np.ndarray:
        p = fit.residual(xy[:, 0] * sig, xy[:, 1] * sig)
        return np.concatenate([p[:, 0], p[:, 1]])

    t = np.asarray(sub["t"], dtype=float)
    tc = t - 0.5 * (t.min() + t.max())
    pattern = shape_pattern(shape, u, v, centre, focal)
    s = project(pattern)
    ok = np.isfinite(s) & np.isfinite(y) & np.isfinite(y_px)
    if len(np.unique(cl[ok])) < 10 or not np.ptp(t) > 0:
        return None
    x = project(pattern * tc[:, None])
    ok &= np.isfinite(x)

    def without_static(z: np.ndarray) -> np.ndarray:
        return z - s * (s[ok] @ z[ok]) / (s[ok] @ s[ok])

    def test(x: np.ndarray, y: np.ndarray, y_px: np.ndarray) -> tuple[float, float, float]:
        tt, p = frame_robust_t(x[ok], y[ok], cl[ok], track=None if tr is None else tr[ok])
        xc = x[ok] - x[ok].mean()
        return float(tt), float(p), float(xc @ y_px[ok]) / float(xc @ xc)

    st, sp, sb = test(s, y, y_px)
    ct, cp, cb = test(without_static(x), without_static(y), without_static(y_px))
    out = {"static_t": st, "static_p": sp, "static": sb, "change_t": ct, "change_p": cp,
           "change": cb * float(np.ptp(t)), "rate_per_s": cb, "window_s": float(np.ptp(t))}
    if against is not None:
        out["spanned"] = _spanned(s[ok], np.asarray(against(u, v), dtype=float), project, ok)
    return out


def _spanned(s: np.ndarray, cols: np.ndarray, project, ok: np.ndarray) -> float:
    """The share of ``s``'s sum of squares the projected columns ``cols`` ``(N, 2, k)`` span."""
    k = cols.shape[2]
    if not k:
        return 0.0
    # the projected columns made into one array of the rows ``ok`` (not stacked, then
    # taken, then taken again for each use: a 2-h window's peak in the line tests)
    a = np.empty((int(np.count_nonzero(ok)), k))
    for j in range(k):
        a[:, j] = project(cols[:, :, j])[ok]
    use = np.isfinite(a).all(1)
    if use.sum() <= k:
        return 0.0
    if not use.all():
        a = a[use]
    su = s[use]
    left = su - a @ np.linalg.lstsq(a, su, rcond=None)[0]
    return float(1.0 - (left @ left) / (su @ su))
