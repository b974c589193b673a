"""Noise as a hypothesis: measure the scales of the stated noise from the run itself.

Users' noise figures are guesses, and a model that is right with a wrong σ looks like a
model that misses an effect (a too-small σ raises every NIS; a too-small gyro noise makes
the filter trust its propagation, so the innovations follow time and anything that drifts
with it).  Before any physical effect is tested, the diagnosis measures

* the **stars' σ scale** ``s`` (globally; per magnitude or image-radius group when the data
  ask for it; the σ of stars whose messages say 0), from the part of each frame's
  innovations that no attitude error can produce: the innovation vector of a frame,
  whitened by the σ the run used, minus its least-squares fit by a small rotation of the
  tracker (3 parameters).  What is left is centroid noise (the common attitude error,
  hence the gyro noise, drops out) and any structure of the camera side; the structure is
  removed as the residuals' mean per detector cell and magnitude class (a field that
  repeats from frame to frame is not noise, and is left to the candidates and the
  structure tests), so ``s² = Σ‖r − r̄_cell‖² / Σ(2n − 3)(1 − 1/n_cell)`` is a
  variance-component estimate (Helmert's, with the rotation and the cell means as
  nuisance) that needs no further run.
  Per star the expectation of ``‖r_i‖²`` is ``s² (2 − h_i)`` (``h_i`` its leverage), which
  gives the group estimates; Bartlett's statistic tests that the groups share one scale.
* the **gyro noise scale** ``g`` (and the accelerometer's ``a``, swaying-base), by maximum
  likelihood on the innovations: the prequential log-likelihood of the evaluation window,
  as a function of ``ln g``, from re-runs of the current model (a parabola through three
  runs, moved until it brackets its maximum, then refined once); σ from its curvature.

Why not an adaptive filter: a Sage–Husa or innovation-matching filter adapts Q and R while
it estimates, so its calibration σ would follow its own noise estimate, and a missing
physical effect would be absorbed into "noise" frame by frame, out of reach of the tests
that name effects.  A variance-component / ML estimate over the run, applied as fixed
scales to a re-run, keeps the filter a plain Kalman filter whose σ mean what they say, and
leaves the physical candidates to be tested on correctly weighted innovations.

"Noise as stated" is rejected for a component when its scale differs from 1 by more than
:data:`MATERIAL` (smaller misstatements change no σ the user reads by more than that) and
its test is significant at :data:`ALPHA` (Bonferroni over the components tested).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats as sps

from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.diagnosis import noise_structure
from stellar_cal_ros.diagnosis.noise_imu import ScaleSearch

#: level of the "noise as stated" tests (after Bonferroni over the components)
ALPHA = 0.01
#: a scale within this fraction of 1 is "as stated" (a 5 % error changes every σ by 5 %)
MATERIAL = 0.05
#: groups of the stars' σ: GROUP_BINS bins of magnitude and radius (quantiles of the stars)
#: and of column and row (equal widths of the detector: a region of the detector whose
#: noise differs), tested fine, then neighbours that agree merged (:func:`_merge`)
GROUP_BINS = 8
#: neighbouring bins whose scales differ by less than this many σ are one group
MERGE_Z = 3.0

Table = dict[str, np.ndarray]


# ----------------------------------------------------------------------------- stars
def used_sigma(residuals: Table, data, scales: NoiseScales, default: float,
               width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """The σ (px) the run used for each row of ``residuals``, and its message's σ.

    Joined on (stamp, catalogue id) with the bag's frames; NaN where a row has no message.
    """
    key: dict[tuple[int, int], tuple[float, float, float, float]] = {}
    for fr in data.frames:
        us = int(round(int(fr.stamp_ns) / 1000))
        mag = np.asarray(fr.magnitude, dtype=float)
        for i, cid in enumerate(np.asarray(fr.catalog_id).tolist()):
            key[(us, int(cid))] = (float(fr.sigma[i]), float(mag[i]), float(fr.uv[i, 0]),
                                   float(fr.uv[i, 1]))
    t_us = np.round(np.asarray(residuals["t"], dtype=float) * 1e6).astype(np.int64)
    rows = [key.get((int(t), int(c))) for t, c in zip(t_us, residuals["catalog_id"],
                                                      strict=True)]
    msg = np.array([np.nan if r is None else r[0] for r in rows])
    mag = np.array([np.nan if r is None else r[1] for r in rows])
    uv = np.array([[np.nan, np.nan] if r is None else r[2:] for r in rows]).reshape(-1, 2)
    s = np.where(np.isfinite(msg) & (msg >= 0), msg, 0.0)
    out = scales.star_sigma(s, default, mag, uv, ((width - 1) / 2.0, (height - 1) / 2.0))
    out[~np.isfinite(msg)] = np.nan
    return out, msg


@dataclass
class StarNoise:
    """Within-frame variance-component estimate of the stars' σ scale."""

    scale: float  #: s: the σ the data show over the σ the run used
    sigma: float  #: σ of s
    dof: float  #: Σ(2n − 3) over the frames used
    frames: int
    q: np.ndarray  #: per star: ‖r_i‖² (whitened, px² / σ²)
    m: np.ndarray  #: per star: 2 − leverage (its share of the dof)
    magnitude: np.ndarray
    radius: np.ndarray
    unknown: np.ndarray  #: per star: its message said σ = 0
    sigma_px: np.ndarray  #: per star: the σ the run used
    #: the cell means' χ² (whitened, in units of the scale found) and its dof: a residual
    #: field that repeats from frame to frame, which no noise makes
    structure: float = 0.0
    structure_dof: int = 0
    uv: np.ndarray | None = None  #: per star: its centroid (px), for the column/row groups
    #: the per-star means' χ² (whitened, in units of the scale found) and its dof: an error
    #: that repeats star by star (a catalogue position), which no centroid noise makes
    repeat: float = 0.0
    repeat_dof: float = 0.0
    #: when significant, the per-star error's RMS (px per axis), removed before the scale
    repeat_removed: float = 0.0
    #: lag-one correlation of a star's consecutive residuals (about its mean), and pairs
    track_rho: float = 0.0
    track_pairs: int = 0

    @property
    def repeat_p(self) -> float:
        """The p-value of "no error that repeats star by star" (χ² of the star means)."""
        if self.repeat_dof <= 0:
            return 1.0
        return float(sps.chi2.sf(self.repeat, self.repeat_dof))

    @property
    def repeat_rms_px(self) -> float:
        """RMS per axis (px) of the per-star errors: the χ²'s excess over its dof."""
        n = max(float(len(self.q)), 1.0)
        px = float(np.median(self.sigma_px)) * self.scale if len(self.sigma_px) else 0.0
        return math.sqrt(max(self.repeat - self.repeat_dof, 0.0) / n / 2.0) * px

    @property
    def structure_p(self) -> float:
        """The p-value of "no repeating field" (χ² of the cell means)."""
        if self.structure_dof <= 0:
            return 1.0
        return float(sps.chi2.sf(self.structure, self.structure_dof))

    def group(self, mask: np.ndarray) -> tuple[float, float, float]:
        """(scale, σ, dof) of the stars in ``mask``."""
        m = float(self.m[mask].sum())
        if m <= 0:
            return math.nan, math.nan, 0.0
        v = float(self.q[mask].sum()) / m
        # sandwich σ of the ratio estimator (robust to a non-Gaussian tail)
        var = float(np.sum((self.q[mask] - v * self.m[mask]) ** 2)) / m**2
        s = math.sqrt(max(v, 0.0))
        return s, math.sqrt(var) / max(2.0 * s, 1e-300), m


def star_noise(res: Table, sigma_px: np.ndarray, msg_sigma: np.ndarray, mask: np.ndarray,
               fx: float, fy: float, centre: tuple[float, float],
               R_imu_st: np.ndarray | None = None) -> StarNoise | None:
    """The within-frame estimate over the accepted stars of ``mask`` (see the module doc).

    With the installation ``R_imu_st``, a rolling shutter's shape is removed first where
    it is significant (:func:`~.noise_structure.minus_rolling`).
    """
    from stellar_cal_ros.diagnosis.stats import rolling_columns, within_frame

    ok = mask & ~np.asarray(res["gated"]).astype(bool) & np.isfinite(sigma_px) \
        & (sigma_px > 0) & np.isfinite(np.asarray(res["du"], dtype=float))
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return None
    sub = {k: np.asarray(res[k])[idx] for k in ("frame", "du", "dv", "x_st", "y_st", "z_st")}
    r, lev, n_frames = within_frame(sub, sigma_px[idx], fx, fy)
    uv = np.stack([np.asarray(res["u"], dtype=float)[idx], np.asarray(res["v"],
                                                                    dtype=float)[idx]], 1)
    # structure is not noise: a residual field that repeats from frame to frame (a missing
    # distortion term, a magnitude-dependent bias) is removed as its mean per detector cell
    # and magnitude class before the variance is taken (the dof it uses are not counted)
    cell, keep_cell = _cells(uv, np.asarray(res["magnitude"], dtype=float)[idx], centre)
    # (a bias periodic in the centroid's sub-pixel phase, pixel locking, first: the cells'
    # means would take part of it and leave the rest to look like a per-star error)
    sub_share = np.ones(len(idx))
    if "u_pred" in res:
        r, sub_share = noise_structure.minus_subpixel(r, sub_share, np.stack(
            [np.asarray(res["u_pred"], dtype=float)[idx],
             np.asarray(res["v_pred"], dtype=float)[idx]], 1), ALPHA)
    # (and a rolling shutter's shape: the row times the image velocity; its readout is
    # structure, not a σ growing with the row nor noise correlated along the tracks)
    x = rolling_columns({k: np.asarray(res[k])[idx] for k in res}, (fx, fy), centre, R_imu_st)
    if x is not None:
        x = within_frame(dict(sub, du=x[:, 0], dv=x[:, 1]), sigma_px[idx], fx, fy)[0]
    r, sub_share = noise_structure.minus_rolling(r, sub_share, x, ALPHA)
    r, share, chi2, dof = _minus_cell_means(r, cell, keep_cell)
    share = share * sub_share
    # ... and so is an error that repeats star by star (a catalogue position error): its
    # per-star means are tested, and removed when significant
    stars = np.asarray(res["catalog_id"])[idx]
    rep, rep_dof, r_star, share_star = star_means(r, share, stars)
    # noise correlated over a few frames makes each star's mean vary more than 1/n: the χ²
    # is referred to that (the lag correlation of the residuals about their star's mean,
    # which a fixed per-star error does not raise)
    infl, rho, pairs = noise_structure.track_inflation(r_star, stars)
    rep /= infl
    chi2 /= infl  # the cells' means too (with few stars in view a cell is a star or two)

    def estimate(r, share):
        q = (r**2).sum(1)
        m = (2.0 - lev) * share
        use = np.isfinite(q) & (m > 0)
        if not use.any():
            return None
        out = StarNoise(0.0, 0.0, float(m[use].sum()), n_frames, q[use], m[use],
                        np.asarray(res["magnitude"], dtype=float)[idx][use],
                        np.hypot(uv[use, 0] - centre[0], uv[use, 1] - centre[1]),
                        (msg_sigma[idx] == 0)[use], sigma_px[idx][use], uv=uv[use])
        out.scale, out.sigma, _ = out.group(np.ones(len(out.q), dtype=bool))
        return out

    out = estimate(r, share)
    if out is None:
        return None
    out.repeat, out.repeat_dof = rep / max(out.scale, 1e-300) ** 2, rep_dof
    if out.repeat_p < ALPHA:
        rms = out.repeat_rms_px
        out = estimate(r_star, share_star) or out
        out.repeat, out.repeat_dof, out.repeat_removed = rep / max(out.scale, 1e-300) ** 2, \
            rep_dof, rms
    out.structure, out.structure_dof = chi2 / max(out.scale, 1e-300) ** 2, dof
    out.track_rho, out.track_pairs = rho, pairs
    return out


def star_means(r: np.ndarray, share: np.ndarray, star: np.ndarray
               ) -> tuple[float, float, np.ndarray, np.ndarray]:
    """The per-star means of the whitened residuals ``r``: their χ², its dof, ``r`` without them.

    Stars seen in at least two frames count; the χ² is ``Σ_s n_s ‖r̄_s‖²`` and its
    expectation for noise alone ``Σ_s 2 mean(share)`` (``share``: each residual's share of
    its dof left by earlier fits).  Returns ``(χ², dof, r − r̄_star, share (1 − 1/n_s))``.
    """
    ok = np.all(np.isfinite(r), axis=1) & (share > 0)
    out, share_out = r.copy(), share.copy()
    if not ok.any():
        return 0.0, 0.0, out, share_out
    _, k = np.unique(np.asarray(star)[ok], return_inverse=True)
    n = np.bincount(k).astype(float)
    means = np.stack([np.bincount(k, r[ok, c]) / n for c in range(2)], 1)
    multi = n >= 2
    chi2 = float(np.sum(n[multi] * (means[multi] ** 2).sum(1)))
    dof = float(2.0 * np.sum((np.bincount(k, share[ok]) / n)[multi]))
    out[ok] = r[ok] - means[k]
    share_out[ok] = share[ok] * (1.0 - 1.0 / n[k])
    return chi2, dof, out, share_out


#: the cells whose mean residual is structure, not noise: a grid over the detector times
#: magnitude classes, cells of at least CELL_MIN stars
CELL_GRID = 6
MAGNITUDE_CLASSES = 3
CELL_MIN = 8


def _cells(uv: np.ndarray, magnitude: np.ndarray, centre: tuple[float, float]
           ) -> tuple[np.ndarray, np.ndarray]:
    """Cell index of each star (detector grid × magnitude class) and which cells count."""
    ext = 2.0 * np.nanmax(np.abs(uv - np.asarray(centre)), axis=0) + 1.0
    ij = np.clip(((uv - np.asarray(centre)) / ext + 0.5) * CELL_GRID, 0,
                 CELL_GRID - 1e-9).astype(int)
    fin = np.isfinite(magnitude)
    mclass = np.zeros(len(uv), dtype=int)
    if fin.sum() > MAGNITUDE_CLASSES * CELL_MIN:
        edges = np.quantile(magnitude[fin], np.linspace(0, 1, MAGNITUDE_CLASSES + 1)[1:-1])
        mclass = np.searchsorted(edges, np.nan_to_num(magnitude, nan=float(np.median(
            magnitude[fin]))), side="right")
    cell = (ij[:, 0] * CELL_GRID + ij[:, 1]) * MAGNITUDE_CLASSES + mclass
    counts = np.bincount(cell, minlength=CELL_GRID**2 * MAGNITUDE_CLASSES)
    return cell, counts[cell] >= CELL_MIN


def _minus_cell_means(r: np.ndarray, cell: np.ndarray, keep: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, float, int]:
    """``r`` minus its mean per cell, each star's share of its dof, the cell means' χ².

    The χ² is ``Σ n_c ‖r̄_c‖²`` (whitened r, scale 1), its dof 2 per cell.
    """
    out = np.full_like(r, np.nan)
    share = np.zeros(len(r))
    ok = keep & np.all(np.isfinite(r), axis=1)
    if not ok.any():
        return out, share, 0.0, 0
    n = np.bincount(cell[ok], minlength=int(cell.max()) + 1).astype(float)
    chi2 = 0.0
    for k in range(2):
        mean = np.bincount(cell[ok], r[ok, k], minlength=len(n)) / np.maximum(n, 1.0)
        out[ok, k] = r[ok, k] - mean[cell[ok]]
        chi2 += float(np.sum(n * mean**2))
    share[ok] = 1.0 - 1.0 / n[cell[ok]]
    return out, share, chi2, 2 * int(np.count_nonzero(n))


def _bartlett(parts: list[tuple[float, float, float]]) -> tuple[float, float]:
    """Bartlett's statistic that the groups' variances are equal, and its p (χ²_{G−1})."""
    parts = [(s, d) for s, _, d in parts if d > 1 and math.isfinite(s) and s > 0]
    if len(parts) < 2:
        return 0.0, 1.0
    v = np.array([s * s for s, _ in parts])
    d = np.array([d for _, d in parts])
    pooled = float(np.sum(d * v) / np.sum(d))
    stat = float(np.sum(d) * math.log(pooled) - np.sum(d * np.log(v)))
    c = 1.0 + (np.sum(1.0 / d) - 1.0 / np.sum(d)) / (3.0 * (len(parts) - 1))
    stat /= c
    return stat, float(sps.chi2.sf(stat, len(parts) - 1))


def _merge(sn: StarNoise, gidx: np.ndarray, edges: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, list[tuple[float, float, float]]]:
    """Merge neighbouring bins whose scales agree (within :data:`MERGE_Z` σ).

    Bins are tested fine (a step in the noise at 4.5 mag or at column 683 falls inside one
    bin, whose mixed scale is then a small share of the stars) and reported coarse: the
    pair of neighbours closest in scale is merged until every neighbour differs.  Returns
    the remaining edges, the group index of each star and the groups' (scale, σ, dof).
    """
    edges = np.asarray(edges, dtype=float)
    while len(edges):
        parts = [sn.group(gidx == g) for g in range(len(edges) + 1)]
        z = [abs(a[0] - b[0]) / math.hypot(a[1], b[1]) if all(
            math.isfinite(x) and x > 0 for x in (a[0], b[0], a[1], b[1])) else 0.0
            for a, b in zip(parts, parts[1:], strict=False)]
        k = int(np.argmin(z))
        if z[k] >= MERGE_Z:
            return edges, gidx, parts
        edges = np.delete(edges, k)
        gidx = np.where(gidx > k, gidx - 1, gidx)
    return edges, gidx, [sn.group(np.ones(len(gidx), dtype=bool))]


def star_groups(sn: StarNoise, size: tuple[int, int] | None = None) -> list[dict[str, Any]]:
    """The magnitude, radius, column and row groupings: per group scale ± σ, Bartlett's p.

    ``size``: the detector's (width, height) px (no column / row groups without it).  The
    test is Bartlett's over :data:`GROUP_BINS` fine bins; the groups reported (and applied)
    are those bins with agreeing neighbours merged.
    """
    out = []
    q = np.linspace(0, 1, GROUP_BINS + 1)[1:-1]
    mag = sn.magnitude
    fin = np.isfinite(mag)
    if fin.sum() > 40 and np.ptp(mag[fin]) > 0:
        out.append(("magnitude", np.unique(np.quantile(mag[fin], q)),
                    np.nan_to_num(mag, nan=float(np.median(mag[fin])))))
    if len(sn.radius) > 40 and np.ptp(sn.radius) > 0:  # quantiles: the corners are sparse
        out.append(("radius", np.unique(np.quantile(sn.radius, q)), sn.radius))
    if size is not None and sn.uv is not None:
        for k, kind in enumerate(("column", "row")):
            out.append((kind, q * size[k], sn.uv[:, k]))
    result = []
    for kind, edges, x in out:
        gidx = np.searchsorted(edges, x, side="right")
        stat, p = _bartlett([sn.group(gidx == g) for g in range(len(edges) + 1)])
        edges, gidx, parts = _merge(sn, gidx, edges)
        result.append({"by": kind, "edges": [float(e) for e in edges],
                       "scales": [s for s, _, _ in parts], "sigma": [e for _, e, _ in parts],
                       "dof": [d for _, _, d in parts], "statistic": stat, "p_value": p})
    return result


# ----------------------------------------------------------------------------- a run's stars
def default_sigma(method: str) -> float:
    """The configured σ of stars whose message says 0, for ``method``."""
    from stellar_cal_ros.methods import registry as methods

    return float(methods.get(method).config_cls().centroid_sigma_px)


def measure_stars(result, data, method: str, fraction: float,
                  noise: NoiseScales | None) -> StarNoise | None:
    """The within-frame estimate on a replay's residual table (where the run executed)."""
    from stellar_cal_ros.diagnosis.stats import evaluation_mask

    res = result.residuals
    if not res or len(res.get("t", ())) == 0:
        return None
    cam = result.calibration.camera
    sig, msg = used_sigma(res, data, noise or NoiseScales(), default_sigma(method),
                          cam.width, cam.height)
    return star_noise(res, sig, msg, evaluation_mask(res, fraction), cam.fx, cam.fy,
                      (cam.cx, cam.cy), result.calibration.R_imu_st)


# ----------------------------------------------------------------------------- the verdict
def p_two_sided(value: float, sigma: float) -> float:
    """Two-sided p of "the scale is 1" for a measured ``value`` ± ``sigma`` (normal)."""
    if not (np.isfinite(sigma) and sigma > 0):
        return 1.0
    return float(2.0 * sps.norm.sf(abs(value - 1.0) / sigma))


_IMU_WORDS = {"gyro": ("gyro noise (angle random walk)", "attitude", "gyro"),
              "accel": ("accelerometer noise (velocity random walk)", "velocity", "accel")}



@dataclass
class NoiseVerdict:
    """What the data say about the stated noise, and the scales the diagnosis then uses."""

    stated: NoiseScales  #: the scales the measurement started from (as stated: identity)
    applied: NoiseScales  #: the scales the diagnosis uses from now on
    star: float = 1.0  #: measured (relative to ``stated``)
    star_sigma: float = math.nan
    star_p: float = 1.0
    star_dof: float = 0.0
    stated_sigma_px: float = math.nan  #: median σ the stars' messages state
    unknown: int = 0  #: stars whose message says σ = 0
    unknown_sigma_px: float = math.nan  #: their measured σ
    unknown_sigma_sigma: float = math.nan
    unknown_base_px: float = math.nan  #: the σ the run assumed for them (the default)
    groups: list[dict[str, Any]] = field(default_factory=list)
    group: dict[str, Any] | None = None  #: the grouping applied (or None)
    imu: dict[str, ScaleSearch] = field(default_factory=dict)  #: gyro / accel searches
    rejected: list[str] = field(default_factory=list)  #: components not as stated
    method: str = "psce"
    #: why the noise was not measured (the model too far off), else ""
    skipped: str = ""
    #: why the IMU noise was not measured although the stars' was (a repeating field), or ""
    imu_skipped: str = ""
    #: an error that repeats star by star, removed before the stars' scale (or None)
    repeat: dict[str, float] | None = None
    #: the IMU's own samples: component -> {scale, sigma, white}
    samples: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: components whose ML scale (the stars) exceeds what the samples show: motion, not noise
    beyond: list[str] = field(default_factory=list)
    #: the stars' noise correlated from frame to frame: {rho, inflation, sigma_scale} or None
    correlated: dict[str, float] | None = None

    @property
    def rescaled(self) -> bool:
        """The diagnosis uses other noise than stated."""
        return not (self.applied.identity or self.applied == self.stated)

    def scale_of(self, name: str) -> tuple[float, float]:
        """(measured scale, σ) of ``star`` / ``gyro`` / ``accel`` (1, NaN: not measured)."""
        if name == "star":
            return self.star, self.star_sigma
        smp = self.samples.get(name)
        if smp and smp["white"]:
            return smp["scale"], smp["sigma"]
        s = self.imu.get(name)
        if s is None:
            return 1.0, math.nan
        return (s.value, s.sigma) if s.measurable else (1.0, math.inf)

    def as_json(self) -> dict[str, Any]:
        """``diagnosis.json``'s ``noise`` block (contract §5, plus what was applied)."""
        names = {"star": "star_sigma_scale", "gyro": "gyro_noise_scale",
                 "accel": "accel_noise_scale"}
        out: dict[str, Any] = {}
        sig: dict[str, Any] = {}
        p: dict[str, Any] = {}
        for comp, key in names.items():
            v, s = self.scale_of(comp)
            out[key] = float(v) * getattr(self.stated, comp)
            sig[key] = None if not np.isfinite(s) else float(s) * getattr(self.stated, comp)
            smp = self.samples.get(comp) or {}
            p[key] = (self.star_p if comp == "star" else
                      p_two_sided(smp["scale"], smp["sigma"]) if smp.get("white") else
                      (self.imu[comp].p_value if comp in self.imu else None))
        out["sigma"] = sig
        out["p_value"] = p
        out["as_stated"] = {names[c]: c not in self.rejected for c in names}
        out["measured"] = {"star_sigma_scale": True,
                           **{names[c]: bool(c in self.imu and self.imu[c].measurable or
                                             (self.samples.get(c) or {}).get("white"))
                              for c in ("gyro", "accel")}}
        if self.samples:
            out["imu_samples"] = {names[c]: d for c, d in self.samples.items()}
        if self.beyond:
            out["motion_beyond_noise"] = {
                names[c]: {"stars_scale": self.imu[c].value, "sigma": self.imu[c].sigma,
                           "samples_scale": self.samples[c]["scale"]} for c in self.beyond}
        out["rescaled"] = self.rescaled
        out["applied"] = self.applied.as_dict()
        if self.unknown:
            out["unknown_sigma"] = {"stars": self.unknown, "sigma_px": self.unknown_sigma_px,
                                    "sigma_of_sigma_px": self.unknown_sigma_sigma}
        if self.groups:
            out["star_groups"] = self.groups
        if self.repeat:
            out["star_repeat"] = self.repeat
        if self.correlated:
            out["star_correlated"] = self.correlated
        out["verdict"] = self.lines()
        if self.skipped:
            out["skipped"] = self.skipped
        if self.imu_skipped:
            out["imu_skipped"] = self.imu_skipped
        return out

    def _sample_lines(self) -> list[str]:
        """The IMU noise measured from its own samples, where it is not as stated."""
        out = []
        for comp, smp in self.samples.items():
            if comp not in self.rejected or not smp["white"]:
                continue
            s, e = smp["scale"], smp["sigma"]
            word = "larger" if s > 1 else "smaller"
            check = ""
            if comp in self.imu and self.imu[comp].measurable and comp not in self.beyond:
                f = self.imu[comp]
                verb = "agree" if abs(f.value - 1.0) <= 3.0 * f.sigma else "see"
                check = f"; the stars {verb}: x{f.value:.3g} +- {f.sigma:.2g} of it"
            axes = ""
            if smp.get("axes"):
                axes = ("; per axis x" + ", x".join(f"{a:.3g}" for a in smp["axes"])
                        + " (x, y, z): one scale for all axes, their RMS")
            out.append(f"the {_IMU_WORDS[comp][0]} looks {s:.3g} +- {e:.2g} x {word} than stated "
                       f"(the {comp}'s own samples{axes}{check}): use --noise-scale "
                       f"{_IMU_WORDS[comp][2]}={getattr(self.applied, comp):.3g}")
        return out

    def _beyond_lines(self) -> list[str]:
        """Motion the stars see beyond the IMU's own noise (not applied as noise)."""
        out = []
        for comp in self.beyond:
            f, smp = self.imu[comp], self.samples[comp]
            out.append(f"the stars see more {_IMU_WORDS[comp][1]} motion than the {comp}'s "
                       f"noise explains: they would need x{f.value:.3g} +- {f.sigma:.2g} the "
                       f"noise its own samples show (x{smp['scale']:.3g} +- "
                       f"{smp['sigma']:.2g} of the stated): not {comp} noise but an effect "
                       "the model lacks (a candidate below, if one is significant), else the "
                       "tracker moving against the IMU (a wobble, a flexing mount) or a "
                       f"wandering {comp} bias, neither in the library (noise kept at the "
                       "samples')")
        return out

    def lines(self) -> list[str]:
        """The terminal's lines, first of the diagnosis (noise is tested before effects)."""
        out = self._sample_lines()
        if self.skipped:
            return [f"not measured: {self.skipped}"] + out
        out += self._beyond_lines()
        if self.correlated:
            out.append(noise_structure.correlated_line(self.correlated, self.applied.star))
        white = self.star * (self.correlated or {}).get("sigma_scale", 1.0)
        if "star" in self.rejected and self.group is None and abs(white - 1.0) > MATERIAL:
            s, e = self.star, self.star_sigma
            word = "too small" if s > 1 else "too large"
            k = s if s > 1 else 1.0 / s
            ke = e / s**2 if s < 1 else e
            old = self.stated_sigma_px
            out.append(f"the stars' sigma looks {k:.3g} +- {ke:.2g} x {word} "
                       f"({old:.3g} -> {old * s:.3g} px): use --noise-scale "
                       f"star={self.applied.star:.3g}")
        if self.group is not None:
            g = self.group
            bins = _bin_text(g["edges"], GROUP_UNITS[g["by"]])
            said = (f"{self.stated_sigma_px:.3g} px stated" if np.isfinite(
                self.stated_sigma_px) else "0 = unknown in every message: the factors are of "
                f"the {self.unknown_base_px:.3g} px default")
            out.append(f"the stars' sigma ({said}) depends on "
                       + g["by"] + ": " + ", ".join(
                           f"x{s:.3g} +- {e:.2g} ({b})" for s, e, b in zip(
                               g["scales"], g["sigma"], bins, strict=True))
                       + " (applied per group; `replay --estimate-noise` measures them)")
        if self.repeat:
            out.append(f"the stars' residuals repeat star by star (chi2 {self.repeat['chi2']:.0f}"
                       f" / {self.repeat['dof']:.0f} dof, p = {self.repeat['p_value']:.2g}): "
                       f"a per-star position error of at least {self.repeat['rms_px']:.2g} px "
                       "rms per axis (what the detector cells' means leave of it: with few "
                       "stars in view they take most) from the catalogue positions or the "
                       "identification, not centroid noise; the sigma is measured without it")
        if self.unknown:
            out.append(f"{self.unknown} stars carry sigma 0 (unknown): measured from the run "
                       f"as {self.unknown_sigma_px:.3g} +- {self.unknown_sigma_sigma:.2g} px "
                       "(used for them)")
        units = {"gyro": ("gyro noise (angle random walk)", "gyro"),
                 "accel": ("accelerometer noise (velocity random walk)", "accel")}
        for comp, search in self.imu.items():
            if (self.samples.get(comp) or {}).get("white"):
                continue  # said from the samples
            if comp in self.rejected and search.bound:
                word = "smaller" if search.bound == "upper" else "larger"
                out.append(f"the {units[comp][0]} looks {word} than stated: at "
                           f"{'most' if search.bound == 'upper' else 'least'} x"
                           f"{search.value:.3g} (95 %; beyond it the stars cannot tell): "
                           f"use --noise-scale {units[comp][1]}="
                           f"{getattr(self.applied, comp):.3g}")
            elif comp in self.rejected:
                s, e = search.value, search.sigma
                word = "larger" if s > 1 else "smaller"
                out.append(f"the {units[comp][0]} looks {s:.3g} +- {e:.2g} x {word} than "
                           f"stated: use --noise-scale {units[comp][1]}="
                           f"{getattr(self.applied, comp):.3g}")
        if self.imu_skipped:
            out.append(f"IMU noise taken as stated: {self.imu_skipped}")
        if not self.rejected and not self.unknown:
            parts = [f"stars' sigma x{self.star:.3g} +- {self.star_sigma:.2g}"]
            for comp, smp in self.samples.items():
                if smp["white"]:
                    parts.append(f"{comp} x{smp['scale']:.3g} +- {smp['sigma']:.2g} "
                                 "(its samples)")
            for comp, search in self.imu.items():
                if (self.samples.get(comp) or {}).get("white"):
                    continue
                parts.append(f"{comp} x{search.value:.3g} +- {search.sigma:.2g}"
                             if search.measurable else
                             f"{comp} at {'most' if search.bound == 'upper' else 'least'} "
                             f"x{search.value:.3g}" if search.bound else
                             f"{comp} not measurable on this bag")
            if self.stated.identity:
                out.append("noise as stated (" + ", ".join(parts) + ")")
            else:  # measured again on a later round: relative to the scales applied so far
                d = self.stated.as_dict()
                out.append("noise as measured before (" + ", ".join(
                    f"{k.split('_')[0]} x{v:.3g}" for k, v in d.items()
                    if k.endswith("_scale") and v != 1.0) + " of the stated; now "
                    + ", ".join(parts) + " of that)")
        return out


#: how a grouping's bins are printed
GROUP_UNITS = {"magnitude": "mag", "radius": "px from the centre", "column": "px column",
               "row": "px row"}


def _bin_text(edges: list[float], unit: str) -> list[str]:
    e = [f"{x:.3g}" for x in edges]
    if not e:
        return ["all"]
    return ([f"< {e[0]} {unit}"] + [f"{a}-{b} {unit}" for a, b in zip(e, e[1:], strict=False)]
            + [f">= {e[-1]} {unit}"])


def judge_stars(v: NoiseVerdict, sn: StarNoise, default: float, size: tuple[int, int],
                n_tests: int, applied: NoiseScales | None = None) -> NoiseScales:
    """Fill the stars' part of ``v`` from ``sn``; return the scales to use for the stars.

    ``size``: the detector's (width, height), px (the column / row groups); ``applied``:
    the scales so far (default: as stated).
    """
    applied = v.stated if applied is None else applied
    known = ~sn.unknown
    v.unknown = int(sn.unknown.sum())
    if v.unknown:
        su, esu, _ = sn.group(sn.unknown)
        base = float(np.median(sn.sigma_px[sn.unknown]))
        v.unknown_sigma_px, v.unknown_sigma_sigma = base * su, base * esu
        v.unknown_base_px = base
        applied = applied.replace(unknown_sigma_px=v.unknown_sigma_px)
    if sn.repeat_removed:
        v.repeat = {"chi2": sn.repeat, "dof": sn.repeat_dof, "p_value": sn.repeat_p,
                    "rms_px": sn.repeat_removed}
    if known.any():
        v.star, v.star_sigma, v.star_dof = sn.group(known)
        v.stated_sigma_px = float(np.median(sn.sigma_px[known])) / v.stated.star
        v.star_p = p_two_sided(v.star, v.star_sigma)
        if v.star_p < ALPHA / n_tests and abs(v.star - 1.0) > MATERIAL:
            v.rejected.append("star")
            applied = applied.replace(star=v.stated.star * v.star)
    sub = dataclasses.replace(sn, scale=v.star, sigma=v.star_sigma, dof=v.star_dof)
    v.groups = star_groups(sub, size)
    best = min(v.groups, key=lambda g: g["p_value"], default=None)
    if best is not None and best["p_value"] < ALPHA / (n_tests * len(v.groups)):
        sc = np.asarray(best["scales"], dtype=float)
        if np.all(np.isfinite(sc)) and sc.max() / sc.min() > 1.0 + 2 * MATERIAL:
            overall = sub.group(np.ones(len(sub.q), dtype=bool))[0]
            v.group = best
            applied = applied.replace(
                star=v.stated.star * overall, group_by=best["by"],
                edges=tuple(best["edges"]), factors=tuple(float(x) for x in sc / overall))
            if "star" not in v.rejected:
                v.rejected.append("star")
    # only where no field or per-star error is left: a missing effect that varies along a
    # star's track correlates its residuals too, and is no noise to inflate (measured: a
    # 30 ms rolling shutter on a swaying base read rho 0.57)
    v.correlated = noise_structure.correlated(sn.track_rho, sn.track_pairs, 2 * MATERIAL) \
        if sn.structure_p >= ALPHA and not sn.repeat_removed else None
    if v.correlated:
        applied = applied.replace(star=applied.star * v.correlated["sigma_scale"])
        if "star" not in v.rejected:
            v.rejected.append("star")
    return applied


#: the model is too far off for the noise to be measured when its innovations, with the
#: stars' measured σ, are still this over-dispersed (NIS/dof), or the filter lost lock
MAX_DISPERSION = 2.0


def far_off(base, sn: StarNoise | None) -> str:
    """Why a run is too far from its model for the noise to be measured on it ('' if not).

    A missing effect that moves the stars far from their predictions (a 20 ms time offset
    under rotation: NIS/dof in the hundreds, lost lock) also bends the within-frame
    residuals and the likelihood the scales are measured from: the noise is then measured
    once the model is closer (the next round of ``discover``), not guessed from a broken run.
    """
    if not base.ok or not base.window:
        return "the model's run failed"
    lost = base.counters.get("reinitializations", 0) or base.counters.get("frames_lost_lock", 0)
    s = 1.0
    if sn is not None and sn.scale > 0:
        s = sn.scale
    nis = base.window["nis"]["mean"] / 2.0 / s**2
    if lost or not np.isfinite(nis) or nis > MAX_DISPERSION:
        return (f"the model is too far off (NIS/dof {base.window['nis']['mean'] / 2.0:.3g}"
                + (", the filter lost lock" if lost else "") + "): a missing effect shapes "
                "the residuals more than the noise does; taken as stated until it is added")
    return ""


def structured(sn: StarNoise) -> str:
    """Why the IMU noise cannot be measured on this run's stars ('' if it can).

    A residual field that repeats from frame to frame (the cell means, significant at
    :data:`ALPHA`) is a missing camera-side effect.  The IMU noise scales are measured by
    the likelihood of the whole innovations, which a larger gyro noise raises by letting the
    attitude follow any unmodelled displacement: measured, they would absorb the effect
    (measured: with refraction and a pixel aspect missing, a "gyro noise x16.7" that then
    hid a gyro scale factor of 100 ppm).  The IMU noise is measured once the field is
    explained (the next round of ``discover``).
    """
    p = sn.structure_p
    if sn.repeat_removed:
        return (f"the stars' residuals repeat star by star ({sn.repeat_removed:.2g} px rms): "
                "the attitude follows the per-star errors of the stars in view, which a "
                "larger gyro noise would absorb")
    if p >= ALPHA:
        return ""
    rms = math.sqrt(max(sn.structure / max(float(sn.m.sum()), 1.0), 0.0))
    return (f"the stars show a repeating field (cell means chi2 {sn.structure:.0f} / "
            f"{sn.structure_dof} dof, p = {p:.2g}, {rms:.2g} x the noise rms): a missing effect, "
            "measured again once it is added")


def repeat_finding(res: Table, mask: np.ndarray, fx: float, fy: float,
                   centre: tuple[float, float]):
    """The 'unexplained' test of an error that repeats star by star, on a run's residuals.

    The innovations of ``mask``'s accepted stars, whitened by their predicted σ, minus the
    frame's attitude fit and the detector cells' means (:func:`star_noise`'s steps), then
    the χ² of the per-star means against its dof (:func:`star_means`).  Returns a
    :class:`~stellar_cal_ros.diagnosis.stats.RegressorFinding` (regressor ``catalogue
    star``, statistic ``(χ² − dof) / √(2 dof)``, unadjusted one-sided p, size = the per-star
    error's RMS per axis, px), or None when there is nothing to test.
    """
    from stellar_cal_ros.diagnosis.stats import RegressorFinding

    ok = mask & ~np.asarray(res["gated"]).astype(bool)
    if ok.sum() < 20:
        return None
    sig = np.sqrt(np.maximum(0.5 * (np.asarray(res["s_uu"], dtype=float)
                                    + np.asarray(res["s_vv"], dtype=float)), 1e-300))
    sn = star_noise(res, np.where(ok, sig, np.nan), np.ones(len(sig)), ok, fx, fy, centre)
    if sn is None or sn.repeat_dof <= 0:
        return None
    z = (sn.repeat - sn.repeat_dof) / math.sqrt(2.0 * sn.repeat_dof)
    rms = sn.repeat_removed or sn.repeat_rms_px
    return RegressorFinding("catalogue star", "u, v", float(z), float(sn.repeat_p), float(rms))


#: the residual regressor of each grouping of the stars' σ
GROUP_REGRESSOR = {"magnitude": "magnitude", "radius": "radius", "column": "u (column)",
                   "row": "v (row)"}


def within_groups(findings: list, verdict: NoiseVerdict | None) -> tuple[list, list]:
    """Split 'unexplained' findings: ``(kept, spread the noise groups leave)``.

    When the stars' σ was applied per group of a regressor (magnitude, radius, column, row),
    a residual *spread* (the ``size`` component) that still follows that regressor is the
    noise varying within the groups (a step at 4.5 mag falls inside one bin), not an effect
    outside the library: it is said with the noise, not as an 'unexplained' lead.
    """
    group = getattr(verdict, "group", None)
    if not group:
        return list(findings), []
    reg = GROUP_REGRESSOR.get(group["by"])
    spread = [f for f in findings if f.component == "size" and f.regressor == reg]
    return [f for f in findings if f not in spread], spread


def stated_scales(calibration) -> NoiseScales:
    """The scales a calibration's run used (its consistency block), identity if none."""
    cons = (getattr(calibration, "extra", None) or {}).get("consistency") or {}
    try:
        return NoiseScales.from_dict(cons.get("noise"))
    except (TypeError, ValueError):
        return NoiseScales()


#: what ``--noise`` takes
NOISE_MODES = ("estimate", "stated")


def check_noise(mode: str) -> bool:
    """Whether ``mode`` (``estimate`` / ``stated``) measures the noise."""
    if mode not in NOISE_MODES:
        from stellar_cal_ros.errors import ModelError

        raise ModelError(f"--noise must be one of {', '.join(NOISE_MODES)}, got {mode!r}")
    return mode == "estimate"


def not_measured(scales: NoiseScales) -> dict[str, Any]:
    """The ``noise`` block of a diagnosis that used the stated noise (``--noise stated``)."""
    d = scales.as_dict()
    return {"star_sigma_scale": d["star_sigma_scale"], "gyro_noise_scale": d["gyro_noise_scale"],
            "accel_noise_scale": d["accel_noise_scale"],
            "sigma": {k: None for k in ("star_sigma_scale", "gyro_noise_scale",
                                        "accel_noise_scale")},
            "measured": {k: False for k in ("star_sigma_scale", "gyro_noise_scale",
                                            "accel_noise_scale")},
            "rescaled": not scales.identity, "applied": d,
            "verdict": ["noise not measured (--noise stated)"]}


def stale(sn: StarNoise | None) -> bool:
    """Whether a run's stars show a σ scale clearly other than the one it applied."""
    if sn is None:
        return False
    known = ~sn.unknown
    if not known.any():
        return False
    s, e, _ = sn.group(known)
    return bool(p_two_sided(s, e) < ALPHA and abs(s - 1.0) > MATERIAL)
