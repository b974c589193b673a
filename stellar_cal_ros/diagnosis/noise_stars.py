"""The stars' σ scale measured within frames, and its groups (part of :mod:`.noise`).

From the part of each frame's innovations no attitude error can produce (the frame's
whitened innovations minus their fit by a small rotation of the tracker), with the
structure that is not noise removed first (cell means, pixel locking, a rolling shutter's
shape, per-star errors: :mod:`.noise_structure`): :func:`star_noise` gives the
variance-component estimate :class:`StarNoise`, :func:`star_groups` its magnitude, radius,
column and row groups (Bartlett's test, neighbours that agree merged).  What the estimate
means for the verdict ("noise as stated" or not) is :mod:`.noise`'s.
"""

from __future__ import annotations

import dataclasses
import inspect
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from stellar_cal_ros.core import distributions as dist
from stellar_cal_ros.core.gating import GatePolicy
from stellar_cal_ros.core.memory import trim_freed
from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.diagnosis import noise_structure
from stellar_cal_ros.diagnosis.stats import finite_rows

#: level of the "noise as stated" tests (after Bonferroni over the components), and of the
#: structure fits removed before the stars' σ is taken
ALPHA = 0.01

#: groups of the stars' σ: GROUP_BINS bins of magnitude and radius (quantiles of the stars)
#: and of column and row (equal widths of the detector: a region of the detector whose
#: noise differs), tested fine, then neighbours that agree merged (:func:`_merge`)
GROUP_BINS = 8
#: neighbouring bins whose scales differ by less than this many σ are one group
MERGE_Z = 3.0
#: a scale within this fraction of 1 is "as stated" (a 5 % error changes every σ by 5 %);
#: groups are applied when their scales span more than twice it
MATERIAL = 0.05

Table = dict[str, np.ndarray]


def used_sigma(residuals: Table, data, scales: NoiseScales, default: float,
               width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """The σ (px) the run used for each row of ``residuals``, and its message's σ.

    Joined on (stamp, catalogue id) with the bag's frames; NaN where a row has no message
    (a key twice in the bag: its last star, :func:`_last_match`).
    """
    frames = data.frames
    counts = np.array([len(fr.catalog_id) for fr in frames], dtype=np.int64)
    # (the stamp in µs as Python rounds the exact quotient, frame by frame)
    us = np.repeat(np.array([int(round(int(fr.stamp_ns) / 1000)) for fr in frames],
                            dtype=np.int64), counts)

    def column(k: str, shape: tuple[int, ...]) -> np.ndarray:
        return np.concatenate([np.asarray(getattr(fr, k), dtype=float).reshape(shape)
                               for fr in frames]) if len(frames) else np.zeros((0, *shape[1:]))

    m_sigma, m_mag, m_uv = column("sigma", (-1,)), column("magnitude", (-1,)), \
        column("uv", (-1, 2))
    cid = np.concatenate([np.asarray(fr.catalog_id, dtype=np.int64) for fr in frames]) \
        if len(frames) else np.zeros(0, np.int64)
    t_us = np.round(np.asarray(residuals["t"], dtype=float) * 1e6).astype(np.int64)
    at = _last_match(us, cid, t_us, np.asarray(residuals["catalog_id"]).astype(np.int64))
    hit = at >= 0
    msg, mag, uv = np.full(len(at), np.nan), np.full(len(at), np.nan), \
        np.full((len(at), 2), np.nan)
    msg[hit], mag[hit], uv[hit] = m_sigma[at[hit]], m_mag[at[hit]], m_uv[at[hit]]
    s = np.where(np.isfinite(msg) & (msg >= 0), msg, 0.0)
    out = scales.star_sigma(s, default, mag, uv, ((width - 1) / 2.0, (height - 1) / 2.0))
    out[~np.isfinite(msg)] = np.nan
    return out, msg


def _last_match(a_t: np.ndarray, a_id: np.ndarray, b_t: np.ndarray, b_id: np.ndarray
                ) -> np.ndarray:
    """For each ``(b_t, b_id)``, the row of ``(a_t, a_id)`` with that key, or −1.

    The last such row, as a dict filled in order keeps it.  Both keys are coded densely
    over the two sides and sorted once: no Python object per row (a 2-h bag has 228 000
    stars, and a dict of them held ≈ 100 MB at once).
    """
    n = len(a_t)
    if n == 0 or len(b_t) == 0:
        return np.full(len(b_t), -1, dtype=np.int64)
    _, ti = np.unique(np.concatenate([a_t, b_t]), return_inverse=True)
    ids, ii = np.unique(np.concatenate([a_id, b_id]), return_inverse=True)
    code = ti.reshape(-1).astype(np.int64) * len(ids) + ii.reshape(-1)
    order = np.argsort(code[:n], kind="stable")
    sa, b = code[:n][order], code[n:]
    pos = np.searchsorted(sa, b, side="right") - 1
    found = (pos >= 0) & (sa[np.maximum(pos, 0)] == b)
    return np.where(found, order[np.maximum(pos, 0)], -1)


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
    #: lag-one correlation of a star's consecutive residuals (about its mean) as a pure
    #: AR(1) reads it, and pairs (its σ ≈ 1/√pairs): the test of white noise
    track_rho: float = 0.0
    track_pairs: int = 0
    star: np.ndarray | None = None  #: per star: its catalogue id (its track)
    #: the tracks' lag-1 ρ the scale is counted with (0: white, or not significant): the
    #: cells' means' share of the dof (:func:`cell_shares`) and the σ and dof of
    #: :meth:`group` (consecutive ‖r‖² of a track correlate by ρ²); white + AR(1) noise:
    #: the AR(1)'s coefficient, ``scatter_share`` its share of the variance (1: pure AR(1))
    scatter_rho: float = 0.0
    #: the same estimate on the stretch before the window (stars of known σ): ``{scale,
    #: sigma, from_s, to_s}`` (seconds from the run's first frame), or None
    before: dict[str, float] | None = None
    #: that stretch's own estimate (its rows: the stars' σ groups are judged on it too)
    early: StarNoise | None = field(default=None, repr=False, compare=False)
    scatter_share: float = 1.0
    #: the tracks' noise model (:func:`~.noise_structure.track_model`): white plus an AR(1)
    #: of coefficient ``track_phi`` (None: ``track_rho``) carrying ``track_share`` of the
    #: variance (1: pure AR(1)), and the σ of its long-run factor
    track_phi: float | None = None
    track_share: float = 1.0
    track_factor_sigma: float = math.nan
    #: per star: its frame (the scale's σ sums each frame's stars first: :meth:`group`)
    frame: np.ndarray | None = None
    #: p-values of the sub-pixel (pixel locking) and rolling-shutter fits' χ² (removed
    #: below :data:`ALPHA`; referred to the tracks' correlation where it is significant)
    subpixel_p: float = 1.0
    rolling_p: float = 1.0
    #: the fixed-pattern tests of the columns (u) and rows (v), :func:`detector_patterns`:
    #: ``{axis, z, p, at_px, size_px, removed}`` each
    patterns: list = field(default_factory=list)
    #: per row of the table measured, the offsets (px, columns u and v) of the patterns
    #: :func:`detector_patterns` removed (0 on rows and axes with none); None: none removed
    pattern_px: np.ndarray | None = None
    #: the p of the cell means' χ² against its sign flips of whole tracks
    #: (:func:`~.noise_structure.flip_p`): whether the field is one the stars' tracks
    #: share; drawn where :attr:`structure_p` is below :data:`ALPHA` (None: not drawn)
    structure_flip_p: float | None = None
    #: tracks correlated (:attr:`scatter_rho` > 0): the variance of ``log s²`` over all the
    #: rows, exact through the steps (:func:`_correlated_variance`), the σ and dof of the
    #: scale over all the rows (:meth:`group`); None: white tracks (the sandwich alone)
    log_variance: float | None = None
    #: per star: the σ its message states (px; 0: unknown), or None
    stated_px: np.ndarray | None = None
    #: ``(size, groups)``: :func:`star_groups` of the stars of stated σ with the detector
    #: ``size``, as :func:`fit_weights` made them on these rows (the verdict's own groups,
    #: :func:`known_groups`: not made twice); None: not made
    groups_made: tuple | None = field(default=None, repr=False, compare=False)
    #: :func:`fit_weights` weighted the next pass by the stars' own scales (:func:`own_scales`)
    own_weighted: bool = field(default=False, repr=False, compare=False)
    #: the fit the star-by-star test reads (:func:`levels_fit`) where a pass was weighted by
    #: the stars' own scales: the last one that was not; None: this one
    levels: StarNoise | None = field(default=None, repr=False, compare=False)
    #: per star: its frame's time (s; the groups tested beside the noise's time trend,
    #: :func:`beside_time`), or None
    t: np.ndarray | None = field(default=None, repr=False, compare=False)
    #: per star: its image's speed (deg/s, the gyro rate through its attitude columns over
    #: the focal length: :func:`speed_variance`), or None (no rate columns)
    speed: np.ndarray | None = field(default=None, repr=False, compare=False)
    #: a noise common to each frame's stars, white between frames, measured on the same
    #: rows (:func:`~.noise_structure.frame_common`; set by :func:`~.noise.measure_stars`),
    #: or None (not measured)
    common: dict[str, float] | None = field(default=None, repr=False, compare=False)

    @property
    def repeat_p(self) -> float:
        """The p-value of "no error that repeats star by star" (χ² of the star means)."""
        if self.repeat_dof <= 0:
            return 1.0
        return float(dist.chi2.sf(self.repeat, self.repeat_dof))

    @property
    def repeat_rms_px(self) -> float:
        """RMS per axis (px) of the per-star errors: the χ²'s excess over its dof."""
        n = max(float(len(self.q)), 1.0)
        px = float(np.median(self.sigma_px)) * self.scale if len(self.sigma_px) else 0.0
        return math.sqrt(max(self.repeat - self.repeat_dof, 0.0) / n / 2.0) * px

    @property
    def structure_p(self) -> float:
        """The p-value of "no repeating field" (χ² of the cell means).

        Not exact (H76): the χ² of ``2 × cells`` dof takes each row's variance as 1 where
        the frames' fit leaves ``1 − lev/2`` (conservative), and the tracks' correlation
        as modelled.  The exact reference, sign flips of whole tracks
        (:attr:`structure_flip_p`), is not the decision: where a cell holds the tracks of
        one or two stars it cannot tell a field from per-star errors, and it lost the
        power to find one (a field 0.5 σ at the detector's edge on a psce bag's rows: χ²
        p below 1e-18 in 10 of 10 draws, flips 0.0005-0.07).
        """
        if self.structure_dof <= 0:
            return 1.0
        return float(dist.chi2.sf(self.structure, self.structure_dof))

    def group(self, mask: np.ndarray, stars: bool = False) -> tuple[float, float, float]:
        """(scale, σ, dof) of the stars in ``mask``.

        ``stars``: the σ with the stars as the units (the stated σ wrong star by star,
        :func:`star_spread`: each star's level is a draw of its own, which its rows share
        along its whole track): the sandwich's scores summed per star and per frame, two-way
        (:meth:`_star_units`); its dof the stars'.
        """
        m = float(self.m[mask].sum())
        if m <= 0:
            return math.nan, math.nan, 0.0
        v = float(self.q[mask].sum()) / m
        if stars and self.star is not None and self.frame is not None:
            s = math.sqrt(max(v, 0.0))
            var, n = self._star_units(mask, v)
            return s, math.sqrt(var) / m / max(2.0 * s, 1e-300), n
        # sandwich σ of the ratio estimator (robust to a non-Gaussian tail), its scores
        # summed per frame first: a frame's stars share its attitude fit (3 dof taken
        # from a few stars' residuals make their ‖r‖² covary: row by row the σ read 0.86x
        # the scatter on white noise in frames of 4-7 stars, 0.96x in a psce bag's ~20)
        s = math.sqrt(max(v, 0.0))
        if self.log_variance is not None and self.scatter_rho > 0.0 and bool(np.all(mask)):
            # all the rows, tracks correlated: the variance through every step under the
            # tracks' model (:func:`_correlated_variance`); its dof as a χ²'s (2 / Var log)
            return s, 0.5 * s * math.sqrt(self.log_variance), 2.0 / self.log_variance
        e = self.q[mask] - v * self.m[mask]
        if self.frame is not None:
            e = np.bincount(np.unique(self.frame[mask], return_inverse=True)[1].reshape(-1), e)
        var = float(np.sum(e**2)) / m**2
        f = self.inflation(mask)
        return s, math.sqrt(var * f) / max(2.0 * s, 1e-300), m / f

    def _star_units(self, mask: np.ndarray, v: float) -> tuple[float, float]:
        """The variance of ``Σ (q − v m)`` over ``mask`` with the stars as units, and their number.

        Scores summed per star (a star's level is shared by its rows at every lag, and a
        correlated track's rows too), each star's square over ``1 − h`` (``h`` its share of
        ``Σ m``: a star of many rows pulls the mean its score is taken about), and per frame
        (a frame's stars share its attitude fit): ``V_star + V_frame − V_row`` (two-way
        clustering; at least ``V_star``); infinite for one star.
        """
        e = self.q[mask] - v * self.m[mask]
        _, sk = np.unique(self.star[mask], return_inverse=True)
        sk = sk.reshape(-1)
        n = int(sk.max()) + 1 if len(sk) else 0
        if n < 2:  # (one star's level is no sample of levels: no σ)
            return math.inf, float(n)
        h = np.bincount(sk, self.m[mask]) / float(self.m[mask].sum())
        by_star = float(np.sum(np.bincount(sk, e) ** 2 / np.maximum(1.0 - h, 1e-3)))
        _, fk = np.unique(self.frame[mask], return_inverse=True)
        var = by_star + float(np.sum(np.bincount(fk.reshape(-1), e) ** 2)) - float(np.sum(e**2))
        return max(var, by_star), float(n)

    def inflation(self, mask: np.ndarray) -> float:
        """How much more the sum of ``q`` over ``mask`` varies than for independent stars.

        Noise correlated along the tracks (lag-1 :attr:`scatter_rho`) correlates a track's
        consecutive ``‖r‖²`` by ρ² (Gaussian), so their sum over a track's ``n`` rows varies
        ``f(n; ρ²)`` times more (:func:`~.noise_structure.mean_factor`): the σ of the scale
        is the sandwich's times the square root of the rows' mean factor, and the dof the
        groups are compared with (Bartlett's) are divided by it.  1 for white noise.
        (Measured, 'ar1' case 300 s, seeds 21-50: the scale's seed-to-seed SD 0.019, the
        sandwich's 0.0064, now 0.0146; Bartlett on the plain dof named a row group
        x0.32-0.36 on seed 25.)
        """
        if not self.scatter_rho > 0.0 or self.star is None:
            return 1.0
        _, k = np.unique(self.star[mask], return_inverse=True)
        n = np.bincount(k).astype(float)
        # (white + AR(1): the squares' lags (w φ^k)², an AR of φ² carrying w²)
        return float(np.sum(n * noise_structure.mean_factor(n, self.scatter_rho**2,
                                                             self.scatter_share**2))
                     / max(n.sum(), 1.0))


def star_noise(res: Table, sigma_px: np.ndarray, msg_sigma: np.ndarray, mask: np.ndarray,
               fx: float, fy: float, centre: tuple[float, float],
               R_imu_st: np.ndarray | None = None, flips: bool = False,
               size: tuple[int, int] | None = None, passes: int = 0,
               weigh=None, kept: NoiseScales | None = None,
               gate: GatePolicy | None = None,
               patterns: list | None = None, readout: str = "v") -> StarNoise | None:
    """The within-frame estimate over the accepted stars of ``mask`` (see the module doc).

    With the installation ``R_imu_st``, a rolling shutter's shape is removed first where
    it is significant (:func:`~.noise_structure.minus_rolling`), along ``readout`` (the
    rows ``"v"`` or the columns ``"u"``: :func:`~.stats.readout_axis`).  The cells' sign-flip p
    (:attr:`StarNoise.structure_flip_p`) is drawn where their χ²'s p is below
    :data:`ALPHA`, or always with ``flips``.

    ``passes``: where the estimate finds the σ the run used wrong for part of the stars
    (σ groups significant as the verdict applies them, :func:`significant_grouping`, with
    ``size`` the detector's; or the σ-0 stars' scale unlike the others'), the frames'
    attitude fit is made again up to ``passes`` times with each star weighted by its
    measured σ (:func:`fit_weights`).  Helmert's estimate is unbiased at the right weights
    only: a frame's attitude fit weighted by the σ being measured takes from each star's
    residual a share of the others' noise at the wrong weight (unseen case
    ``mag_faint_over2``, faint stars stated 2x: the bright group read x0.949 +- 0.016 for a
    true 1.0).  Where the σ is wrong star by star (:func:`star_levels`) each star is
    weighted by its own scale (:func:`own_scales`), and a pass counts the rows the filter's
    gate took at the σ it used that pass it at the σ measured (:func:`readmitted`).  The
    scales stay of the σ the run used (``sigma_px``); where nothing is significant no pass
    is made and the estimate is the one fit's, bit for bit.

    ``weigh``: a test of the one fit's estimate (True: the passes may be made); a run too
    far from its model (:func:`~.noise.far_off`) keeps the one fit's weights: the groups a
    pass would weight by are measured through residuals a missing effect shapes more than
    the noise does, and the noise is not judged on such a run anyway.  ``kept``: the
    scales the run used (:func:`fit_weights`).  ``gate``: the run's χ² gate (its filter's
    policy, :func:`readmitted`; None: the default policy's).  ``patterns``: the
    detector's fixed-pattern tests of the same ``res``, ``sigma_px``, ``fx``, ``fy``,
    ``centre`` and ``R_imu_st`` if already made (:func:`detector_patterns` reads every row
    of the run's last part, not ``mask``'s: estimates of one table on other masks share
    them; read, never changed).
    """
    # after each part its freed heap pages (blocks below the mapping threshold) go back,
    # not held beside the next part's: a 2-h round's screening run peaks in these parts
    if patterns is None:
        patterns = detector_patterns(res, sigma_px, fx, fy, centre, R_imu_st, readout)
        trim_freed()
    out = _star_noise_once(res, sigma_px, msg_sigma, mask, fx, fy, centre, R_imu_st, flips,
                           patterns=patterns, readout=readout)
    trim_freed()
    if weigh is not None and out is not None and passes and not weigh(out):
        return out
    last = plain = None
    for _ in range(passes):
        w = fit_weights(out, res, sigma_px, msg_sigma, centre, size, kept)
        if w is None or (last is not None and np.nanmax(np.abs(w / last - 1.0)) < WEIGHTS_TOL):
            break
        if out.own_weighted and plain is None:
            plain = out
        admit = readmitted(res, w * out.group(grouped_stars(out))[0], gate)
        out, last = _star_noise_once(res, sigma_px, msg_sigma, mask, fx, fy, centre,
                                     R_imu_st, flips, w, patterns, admit, readout), w
        trim_freed()
    if out is not None and plain is not None:
        out.levels = plain
    return out


def levels_fit(sn: StarNoise | None) -> StarNoise | None:
    """The fit the star-by-star test (:func:`star_levels`, :func:`star_spread`) reads.

    A pass weighted by the stars' own scales (:func:`own_scales`, measured on the same
    rows) leans each frame's fit on the stars that read small, which then read smaller,
    and off those that read large: the stars' spread grows with the weights it made, and
    the F test's reference no longer holds (clean swaying bag, false-alarm seed 2047: F
    1.39, p 0.0051 on the fit before those weights, 1.57, p 0.00016 after).  The scale is
    the weighted fit's (:func:`star_noise`); the test is the last fit's before them.
    """
    return sn if sn is None or sn.levels is None else sn.levels


def readmitted(res: Table, scale: np.ndarray, gate: GatePolicy | None = None
               ) -> np.ndarray | None:
    """The rows the run's χ² gate rejected at the σ it used that pass it at ``scale`` × that σ.

    The filter gates each star at the σ it was given, by its policy ``gate``
    (:class:`~stellar_cal_ros.core.gating.GatePolicy`; None: the default one): a star
    whose σ is stated too small loses the tail of its own noise there, and a scale
    measured without those rows reads low (unseen case ``sigma_per_star`` s21: x1.035 on
    the accepted rows, 1.057 with every row, the rows' ML 1.062).  The gate's threshold
    is scaled by its frame's median NIS (:meth:`~.GatePolicy.frame_scales`), at the σ
    used and again at the σ measured (each row's NIS over its ``scale``²): a row above
    its frame's threshold at the σ used (``nis``) and below it at the σ measured is noise,
    counted; a row gated below its frame's threshold (out of the field of view) or in a
    frame whose median NIS lost the lock stays out.  None without a NIS column.
    """
    if "nis" not in res:
        return None
    # (the run's own threshold: a gate set in the driver's config, e.g. gate_probability
    # 0.999, rejects rows the default's would pass, which were then never counted)
    policy = gate or GatePolicy()
    t = policy.threshold
    nis = np.asarray(res["nis"], dtype=float)
    frames = np.asarray(res["frame"])
    used = policy.frame_scales(nis, frames)
    with np.errstate(invalid="ignore", divide="ignore"):
        at = nis / np.asarray(scale, dtype=float) ** 2
        measured = policy.frame_scales(at, frames)
        return (np.asarray(res["gated"]).astype(bool) & (nis > t * used)
                & (used <= policy.lost_lock_factor) & (at <= t * measured))


#: the fixed-pattern test reads the run's last this share of the time (the filter's first
#: tenth converging): a pattern on the detector does not change with time, and its test,
#: a coincidence across the stars crossing the same bands, gains with every star (unseen
#: case ``columns``, seed 21: p 2.9e-4 on the evaluation window's half, 2.2e-8 on 0.9)
PATTERN_FRACTION = 0.9
#: the fixed-pattern test's level over its two axes (Bonferroni): the family's, not
#: :data:`ALPHA`: its removal changes the noise measured, and its line is judged among the
#: ~100 'unexplained' tests at 1 % (at ALPHA it fired on 1 of 98 clean psce / swaying 300 s
#: bags, swaying seed 2030, p 8.3e-4; the ``columns`` case's 300 s seeds 21-26 read
#: 7.6e-10 .. 1.6e-7)
PATTERN_ALPHA = 1e-4


#: the part of :data:`PATTERN_ALPHA` the fixed pattern's Gaussian null takes, the flips the
#: rest (Bonferroni over the two: the family's level is ``PATTERN_ALPHA``).  Small, as its
#: null is a model (Gaussian rows, AR(1) tracks) where the flips' is exact and it is only
#: needed where the flips are blind (stars dwelling in a band): it fires at p < 2.5e-6 an
#: axis (the ``rows`` case end to end, seeds 21-23: 1.7e-9, 6.0e-7, 3.5e-9; clean psce
#: 300 s, 50 draws: >= 0.0058), the flips at p < 4.75e-5 (``columns`` 200 s seed 8 read
#: through ``measure_bag``: 4.6e-5; at a share of 0.2 it was no longer removed)
PATTERN_MODEL_SHARE = 0.05


def detector_patterns(res: Table, sigma_px: np.ndarray, fx: float, fy: float,
                      centre: tuple[float, float] | None = None,
                      R_imu_st: np.ndarray | None = None, readout: str = "v") -> list:
    """The fixed-pattern tests of the detector's columns (u) and rows (v) on the run.

    The accepted stars of the run's last :data:`PATTERN_FRACTION` (σ ``sigma_px`` finite,
    at a predicted position), whitened and less each frame's attitude fit, each axis
    against its own predicted position: :func:`~.noise_structure.fixed_pattern`,
    Bonferroni over the two at :data:`PATTERN_ALPHA`, each axis's flips' p and its
    Gaussian null's (:attr:`~.noise_structure.FixedPattern.model_p`) over their shares of
    that level (:data:`PATTERN_MODEL_SHARE`), the smaller of the two said.  ``[(axis,
    FixedPattern, removed, offset, share, seen)]`` (empty without the predictions, or too
    few rows); where ``removed``, ``offset`` and ``share`` (per row of ``res``, 0 off the
    rows tested; else None) are the rows' pixels' offsets in px and each row's share of
    its pixel's offset (:func:`~.noise_structure.pixel_means`), which
    :func:`_star_noise_once` takes out of that axis before the stars' noise is read; and
    ``seen`` (per row, px; else None) the rows' pixels' means without the stars' means:
    what the residuals hold of the pattern, which the other 'unexplained' lines are read
    without (:func:`~.noise.without_patterns`).

    With the installation ``R_imu_st``, no pattern is removed where a rolling shutter's
    fit (:func:`~.noise_structure.minus_fits`, as :func:`_star_noise_once` tests it) is
    significant on the same rows: a shutter moves the stars in the slews by their row
    times their image velocity, and their means per band of columns then read as a
    'pattern' (unseen case ``rolling``, 30 ms, seeds 21-24: u p 2e-5 .. 3.5e-5, 1.06 px),
    whose removal took the shutter's own line from t −49 to −11 (not significant among the
    ~86 line tests) and left 'catalogue star' first.  ``readout``: the shutter's direction
    (the rows ``"v"``, the columns ``"u"``).
    """
    from stellar_cal_ros.diagnosis.stats import (
        POSITION_PERIODS,
        ROLLING_KEYS,
        FrameFit,
        evaluation_mask,
        rolling_columns,
    )

    if "u_pred" not in res or len(res["t"]) == 0:
        return []
    sig = np.asarray(sigma_px, dtype=float)
    ok = evaluation_mask(res, PATTERN_FRACTION) & ~np.asarray(res["gated"]).astype(bool) \
        & np.isfinite(sig) & (sig > 0) & np.isfinite(np.asarray(res["du"], dtype=float))
    idx = np.flatnonzero(ok)
    if len(idx) < noise_structure.MIN_ROWS:
        return []
    sub = {k: np.asarray(res[k])[idx] for k in ("frame", "du", "dv", "x_st", "y_st", "z_st")}
    fit = FrameFit(sub, sig[idx], fx, fy)
    r = fit.residual(sub["du"], sub["dv"])
    stars = np.asarray(res["catalog_id"])[idx]
    shutter: list[float] = []  # the shutter fit's p, made once a pattern would be removed

    def shutter_p() -> float:
        if not shutter:
            x = rolling_columns({k: np.asarray(res[k])[idx] for k in ROLLING_KEYS if k in res},
                                (fx, fy), centre, R_imu_st, readout) \
                if centre is not None else None
            p = 1.0
            if x is not None:
                blocks = [None, noise_structure.rolling_block(fit.residual(x[:, 0], x[:, 1]))]
                p = noise_structure.minus_fits(r, np.ones(len(idx)), blocks, ALPHA, stars,
                                               _fit_lags(r, np.ones(len(idx)), blocks,
                                                         stars))[2][1]
            shutter.append(p)
        return shutter[0]

    # (the frames' own noise where it differs: smear in the slews, noise_structure's
    # frame_variances; None, one variance, on a bag whose frames' noise is alike)
    row_var = noise_structure.frame_variances(0.5 * np.sum(r**2, axis=1), sub["frame"])
    out = []
    for axis, key in enumerate(("u_pred", "v_pred")):
        # (tested less a smooth function of the position, whose part the ripple lines
        # test; once found, the pixels' offsets are read and removed whole: a pattern of
        # bands has a smooth part of its own, which echoes as a ripple left in)
        at = np.asarray(res[key], dtype=float)[idx]
        fp = noise_structure.fixed_pattern(
            noise_structure.less_smooth(r[:, axis], at, None if centre is None
                                        else 2.0 * centre[axis], POSITION_PERIODS),
            np.ones(len(idx)), at, stars, scale=sig[idx], row_var=row_var)
        if fp is None:
            continue
        # the flips' p or the model's, each over its share of the level
        flips = fp.p / (1.0 - PATTERN_MODEL_SHARE) <= fp.model_p / PATTERN_MODEL_SHARE
        fp = dataclasses.replace(fp, p=min(1.0, fp.p / (1.0 - PATTERN_MODEL_SHARE))) \
            if flips else dataclasses.replace(fp, z=fp.model_z,
                                              p=min(1.0, fp.model_p / PATTERN_MODEL_SHARE))
        removed = fp.p * 2.0 < PATTERN_ALPHA and not shutter_p() < ALPHA
        offset = share = seen = None
        if removed:
            # found by the model (between the stars too): the stars' means hold the
            # pattern, not fitted beside it (rows seeds 21-30: 0.147 +- 0.014 px for 0.15;
            # fitted, 0.160 +- 0.022)
            offset, share = np.zeros(len(sig)), np.zeros(len(sig))
            offset[idx], share[idx] = noise_structure.pixel_means(
                r[:, axis], np.asarray(res[key], dtype=float)[idx], stars, scale=sig[idx],
                star_means=flips)
            # the size from the rows with a share of a pixel's offset only: a row whose
            # residual is not finite has offset 0 and would dilute the window's mean;
            # through the frames' fit either way (which takes ~1/N of a band's offset into
            # the attitude: unseen case ``rows`` end to end, seeds 21-23, 0.129 / 0.116 /
            # 0.137 px read directly, 0.136 / 0.125 / 0.144 through it, for 0.15)
            pos = np.where(share[idx] > 0, np.asarray(res[key], dtype=float)[idx], np.nan)
            fp = dataclasses.replace(fp, size_px=_pattern_size(
                fit, axis, offset[idx], pos, stars, sig[idx], fp.at_px, star_means=flips))
            # (what the residuals hold of it, for the other lines: the pixels' means
            # without the stars', whose fit leaves the offsets' smooth part undetermined)
            seen = offset
            if flips:
                seen = np.zeros(len(sig))
                seen[idx], _ = noise_structure.pixel_means(
                    r[:, axis], np.asarray(res[key], dtype=float)[idx], stars,
                    scale=sig[idx], star_means=False)
        out.append(("uv"[axis], fp, removed, offset, share, seen))
    return out


#: the most passes of :func:`_pattern_size`'s fit of the pixels' offsets through the
#: frames' fit (unseen case ``columns`` seed 21: 0.1376 px after none, 0.1466 after 6,
#: 0.1467 after 8)
PATTERN_SIZE_PASSES = 10

#: :func:`_pattern_size`'s fit has settled once the size changes by less than this part
#: of itself between two passes (unseen case ``columns`` seed 21: 0.146 px as after 10
#: passes; at 1 % it stopped early at 0.145, and a slow inflation of ~1 % a pass on sparse
#: data passed for settled)
PATTERN_SIZE_TOL = 0.001


def _pattern_size(fit, axis: int, offset: np.ndarray, pos: np.ndarray, stars: np.ndarray,
                  sig: np.ndarray, at_px: float, star_means: bool = True) -> float:
    """The size (px) of the fixed pattern at ``at_px``, through the frames' fit.

    :func:`~.noise_structure.band_offset_size` of the pixels' offsets ``c`` that give the
    measured ones ``offset``.  The residuals the pattern is measured in are less each
    frame's attitude fit (``fit``, the :class:`~.stats.FrameFit` of the rows), which takes
    a share of a star's offset on a defective band into its frame's attitude (~1/N of it
    with N stars a frame), and the pixels' offsets are fitted beside the stars' means
    (:func:`~.noise_structure.pixel_means`; ``star_means`` False: not, as where the
    Gaussian null found the pattern): together a linear map ``A`` of the true
    offsets, ``offset = A c``.  ``c`` is found by passes of ``c ← c + (offset − A c)``
    until the size changes by less than :data:`PATTERN_SIZE_TOL` of itself between two
    passes (unseen case ``columns``, 0.15 px: 0.134-0.145 px over seeds 21-30 with
    ``offset``'s own size, 0.143-0.156 with ``c``'s).  Where it has not settled after
    :data:`PATTERN_SIZE_PASSES` passes (sparse data, where ``A`` is near singular and the
    passes inflate the size: 300 frames of 20-40 stars read 0.147, 0.187, 0.226 px after
    0, 10, 100 passes for 0.15) the size is ``offset``'s own, the direct one.  The removal
    of the pattern keeps ``offset``: it is what the residuals hold.  Rows with ``pos`` not
    finite take no part.
    """
    direct = noise_structure.band_offset_size(offset, pos, at_px)
    c, size = offset.copy(), direct
    d = np.zeros((len(c), 2))
    for _ in range(PATTERN_SIZE_PASSES):
        d[:, axis] = c
        ac, _ = noise_structure.pixel_means(fit.residual(d[:, 0], d[:, 1])[:, axis], pos,
                                            stars, scale=sig, star_means=star_means)
        c = c + (offset - ac)
        last, size = size, noise_structure.band_offset_size(c, pos, at_px)
        if abs(size - last) < PATTERN_SIZE_TOL * abs(size):
            return size
    return direct


#: the fit's weights are iterated no further once no star's moves by more than this
WEIGHTS_TOL = 1e-3


def significant_grouping(groups: list[dict[str, Any]], n_tests: int) -> dict[str, Any] | None:
    """The grouping of the stars' σ the verdict applies, or None.

    The one of :func:`star_groups` with the smallest Bartlett p, when that p is below
    :data:`ALPHA` over ``n_tests`` components and the groupings (Bonferroni) and its
    groups' scales span more than ``1 + 2`` :data:`MATERIAL`.  The groupings are ranked
    of one σ: the kept variable's by its p of the σ before the kept factors
    (``p_before``, what the others are measured of); chosen, its own p (of the σ used)
    decides, and not significant it is none (the kept groups stay).
    """
    best = min(groups, key=lambda g: g.get("p_before", g["p_value"]), default=None)
    if best is None or not best["p_value"] < ALPHA / (n_tests * len(groups)):
        return None
    sc = np.asarray(best["scales"], dtype=float)
    if not (np.all(np.isfinite(sc)) and sc.max() / sc.min() > 1.0 + 2 * MATERIAL):
        return None
    return best


def fit_weights(sn: StarNoise | None, res: Table, sigma_px: np.ndarray,
                msg_sigma: np.ndarray, centre: tuple[float, float],
                size: tuple[int, int] | None, kept: NoiseScales | None = None
                ) -> np.ndarray | None:
    """Each row's measured σ over the σ the run used, for :func:`star_noise`'s fit; or None.

    The stars of stated σ: their group's scale (the grouping :func:`significant_grouping`
    would apply with one component tested); σ-0 stars: their own scale where it differs
    from the stated stars' by more than :data:`MATERIAL` and 3 of its σ.  Where no message
    states a σ, every star is grouped (the verdict's groups then are of every star,
    :func:`known_groups`): a bag whose σ-0 stars are noisier when faint had its groups
    measured through a fit that weighted them all alike.  None where nothing applies (the
    fit's weights are then right as far as the data tell).

    ``kept``: the scales the run used; groups of another variable than theirs are of the σ
    before the kept factors (:func:`star_groups`), and a star is weighted by its group's
    scale over its own kept factor (the σ the verdict then gives it).
    """
    if sn is None:
        return None
    known = ~sn.unknown
    grouped = grouped_stars(sn)
    w = np.ones(len(sigma_px))
    msg = np.asarray(msg_sigma, dtype=float)
    moved = False
    s, e, _ = sn.group(grouped)
    if not (math.isfinite(s) and s > 0):
        return None
    sn.groups_made = ((size, kept), star_groups(sn, size, grouped, kept))
    best = significant_grouping(sn.groups_made[1], 1)
    if best is not None:
        uv = np.stack([np.asarray(res["u"], dtype=float), np.asarray(res["v"], dtype=float)],
                      1)
        mag = np.asarray(res["magnitude"], dtype=float)
        x = {"magnitude": lambda: np.nan_to_num(
                mag, nan=float(np.median(sn.magnitude[np.isfinite(sn.magnitude)]))
                if np.isfinite(sn.magnitude).any() else 0.0),
             "radius": lambda: np.hypot(uv[:, 0] - centre[0], uv[:, 1] - centre[1]),
             "column": lambda: uv[:, 0], "row": lambda: uv[:, 1]}[best["by"]]()
        g = np.searchsorted(np.asarray(best["edges"], dtype=float), x, side="right")
        scales = np.asarray(best["scales"], dtype=float)
        w = scales[g] / s
        if kept is not None and kept.group_by and kept.group_by != best["by"]:
            # (another variable's groups are of the σ before the kept factors,
            # :func:`star_groups`: each star's σ is its group's scale of that, the kept
            # factor it was used with taken off)
            f = np.asarray(kept.factors, dtype=float)[kept.group_of(mag, uv, centre)]
            w = w / np.where((msg > 0) | (kept.unknown_sigma_px <= 0), f, 1.0)
        moved = True
    own = own_scales(sn, res, grouped, None if best is None else group_index(sn, best))
    sn.own_weighted = own is not None
    if own is not None:
        # the stated σ wrong star by star (beyond the groups): each star weighted by its own
        # scale, measured on these rows (its group's where it has none here).  Weighted by
        # the stated σ, a frame's fit leans on the stars stated too small, whose leverage
        # then takes more of their own (larger) variance: the scale read the (2 − h)-weighted
        # mean of s², x1.02 +- 0.0095 for the rows' 1.06 (unseen case sigma_per_star s21)
        w = np.where(np.isfinite(own), own / s, w)
        moved = True
    if known.any() and sn.unknown.any():
        su, esu, _ = sn.group(sn.unknown)
        if math.isfinite(su) and su > 0 and abs(su / s - 1.0) > MATERIAL and \
                abs(su - s) > 3.0 * math.hypot(esu, e):
            w = np.where(msg == 0, su / s, w)
            moved = True
    return np.where(np.isfinite(w) & (w > 0), w, 1.0) if moved else None


def star_levels(sn: StarNoise | None, use: np.ndarray | None = None,
                gidx: np.ndarray | None = None) -> dict[str, float] | None:
    """The stated σ wrong star by star (:func:`star_spread`), when it is.

    Significant at :data:`ALPHA` and material (the stars' σ factors spread by more than
    :data:`MATERIAL`, half their variance factors' spread), where no field or per-star
    position error is left (those make a star's residuals large too: said as themselves).
    ``use``/``gidx``: the stars tested and their groups (about each group's own level).
    Only stars whose message states a σ are tested, among themselves: σ-0 stars are their
    own group, measured as one σ (before, any σ-0 star skipped the test, and a bag of
    stated stars wrong star by star beside them read random groups and tails), and a bag
    whose every message says 0 states no σ to be wrong.
    """
    if sn is None or sn.repeat_removed or sn.structure_p < ALPHA:
        return None
    use = ~sn.unknown if use is None else np.asarray(use, dtype=bool) & ~sn.unknown
    if not use.any():
        return None
    d = star_spread(sn, use, gidx)
    if d is None or not (d["p_value"] < ALPHA and 0.5 * d["spread"] > MATERIAL):
        return None
    return d


def own_scales(sn: StarNoise, res: Table, use: np.ndarray, gidx: np.ndarray | None
               ) -> np.ndarray | None:
    """Each row of ``res``: its star's own σ scale on ``sn``'s rows, or None.

    None where the σ is not wrong star by star (:func:`star_levels` on the stars ``use``,
    about their groups ``gidx``).  ``sqrt(Σ q / Σ m)`` over the star's rows of ``sn`` (its
    catalogue id); NaN for a row whose star is not among them, or σ-0.
    """
    if star_levels(sn, use, gidx) is None:
        return None
    ok = np.asarray(use, dtype=bool) & ~sn.unknown & (sn.m > 0) & np.isfinite(sn.q)
    ids, k = np.unique(np.asarray(sn.star)[ok], return_inverse=True)
    k = k.reshape(-1)
    own = np.sqrt(np.bincount(k, sn.q[ok]) / np.bincount(k, sn.m[ok]))
    rows = np.asarray(res["catalog_id"])
    at = np.clip(np.searchsorted(ids, rows), 0, max(len(ids) - 1, 0))
    found = (ids[at] == rows) if len(ids) else np.zeros(len(rows), dtype=bool)
    return np.where(found, own[at] if len(ids) else np.nan, np.nan)


def _star_noise_once(res: Table, sigma_px: np.ndarray, msg_sigma: np.ndarray,
                     mask: np.ndarray, fx: float, fy: float, centre: tuple[float, float],
                     R_imu_st: np.ndarray | None = None, flips: bool = False,
                     weights: np.ndarray | None = None,
                     patterns: list | None = None,
                     admit: np.ndarray | None = None, readout: str = "v"
                     ) -> StarNoise | None:
    """:func:`star_noise` with the frames' fit weighted by ``sigma_px × weights`` (None: 1).

    The residuals and the columns projected through the fit are then brought back to the
    units of ``sigma_px`` (× ``weights``): ``E‖r_i‖² = s_i² (2 − h_i)`` with ``h_i`` the
    weighted fit's leverage and ``s_i`` star ``i``'s σ over ``sigma_px``.
    """
    from stellar_cal_ros.diagnosis.stats import (
        ROLLING_KEYS,
        FrameFit,
        image_velocity,
        rolling_columns,
    )

    gated = np.asarray(res["gated"]).astype(bool)
    if admit is not None:  # (rows the gate took at the wrong σ: :func:`readmitted`)
        gated = gated & ~admit
    ok = mask & ~gated & np.isfinite(sigma_px) \
        & (sigma_px > 0) & np.isfinite(np.asarray(res["du"], dtype=float))
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return None
    sub = {k: np.asarray(res[k])[idx] for k in ("frame", "du", "dv", "x_st", "y_st", "z_st")}
    w = None if weights is None else np.asarray(weights, dtype=float)[idx]
    fit_sigma = sigma_px[idx] if w is None else sigma_px[idx] * w
    fit = FrameFit(sub, fit_sigma, fx, fy)  # (the frames' fit, for every column below)

    def back(x: np.ndarray) -> np.ndarray:
        """Whitened by the fit's σ -> by ``sigma_px`` (the weights' units: identity if none)."""
        return x if w is None else x * w.reshape((-1,) + (1,) * (x.ndim - 1))

    r, lev, n_frames = back(fit.residual(sub["du"], sub["dv"])), fit.leverage, fit.frames
    uv = np.stack([np.asarray(res["u"], dtype=float)[idx], np.asarray(res["v"],
                                                                    dtype=float)[idx]], 1)
    # structure is not noise: a residual field that repeats from frame to frame (a missing
    # distortion term, a magnitude-dependent bias) is removed as its mean per detector cell
    # and magnitude class before the variance is taken (the dof it uses are not counted)
    cell, keep_cell = _cells(uv, np.asarray(res["magnitude"], dtype=float)[idx], centre)
    # (a bias periodic in the centroid's sub-pixel phase, pixel locking, first: the cells'
    # means would take part of it and leave the rest to look like a per-star error)
    sub_share = np.ones(len(idx))
    stars = np.asarray(res["catalog_id"])[idx]
    uv_pred = np.stack([np.asarray(res["u_pred"], dtype=float)[idx],
                        np.asarray(res["v_pred"], dtype=float)[idx]], 1) \
        if "u_pred" in res else None
    # (and a rolling shutter's shape: the row (``readout`` "u": the column) times the
    # image velocity; its readout is structure, not a σ growing with the row nor noise
    # correlated along the tracks; a star keeps its column along its track too, so a
    # column readout left in repeats star by star: unseen case ``rolling_cols``)
    def projected(c: np.ndarray) -> np.ndarray:
        """Columns ``c`` (n, 2) in px through the frames' attitude fit, whitened as ``r``."""
        return back(fit.residual(c[:, 0], c[:, 1]))

    # (only the columns it reads: the whole table's rows were a ≈ 30 MB copy on a 2-h bag)
    rows = {k: np.asarray(res[k])[idx] for k in ROLLING_KEYS if k in res}
    x = rolling_columns(rows, (fx, fy), centre, R_imu_st, readout)
    vel = image_velocity(rows, (fx, fy), R_imu_st)
    speed = None if vel is None else np.degrees(np.hypot(vel[:, 0] / fx, vel[:, 1] / fy))
    del rows, vel
    if x is not None:
        x = projected(x)
    # (the sub-pixel regressors too: fitted raw, 0.08 px of locking left the scale at 1.04)
    X_sub = None if uv_pred is None else np.stack(
        [projected(c) for c in np.moveaxis(noise_structure.subpixel_columns(uv_pred), 2, 0)],
        2)
    # both fits' χ² referred to the tracks' correlation where it is significant, as the
    # cells' (:func:`_fit_lags`; white tracks: the white fits, as before)
    # (fitted together, each tested given the other, noise_structure.minus_fits: run first,
    # the sub-pixel fit took part of a 3 ms readout's shape and fired in 6 of 100 white
    # draws at 1 %)
    blocks = _structure_blocks(uv_pred, X_sub, x)
    # (the block is a masked copy: the regressors and the predictions it was made of are
    # not held through the fits below, ≈ 10 MB on a 2-h bag)
    del X_sub, uv_pred
    lags = _fit_lags(r, sub_share, blocks, stars)
    r, sub_share, (p_sub, p_roll) = noise_structure.minus_fits(r, sub_share, blocks, ALPHA,
                                                               stars, lags)
    # ... and a centroid offset fixed to the detector's columns (rows), a CCD's fixed
    # pattern: a star's residual jumps for the frames it sits on a defective band, which
    # the tracks' model read as AR(1) noise and the star spread as σ wrong star by star
    # (unseen case ``columns``): removed where significant before either is read
    r, sub_share = _minus_patterns(r, sub_share, patterns or [], idx, sigma_px[idx])
    r_cells = r  # (the cells' χ² is referred to the tracks' lag below)
    # (the tracks' lag-1 ρ read about the star means before the cells' means, which bias
    # it low: pure AR(1) tracks of 0.819 read 0.809 after them, and the repeat's p mean
    # 0.33; white + AR(1) along the tracks: :func:`~.noise_structure.track_model`, a pure
    # AR(1) unless the lags ask for white noise beside it)
    rep_track = noise_structure.track_model(star_means(r_cells, sub_share, stars)[2], stars)
    rho_tracks, pairs_tracks = rep_track.rho, rep_track.pairs
    # noise correlated along the tracks makes a cell's mean vary more than 1/n_c (a track
    # crosses a cell in a few dozen correlated frames): the dof the cells' means take is
    # counted for it where the correlation is significant (:func:`cell_shares`; counted as
    # 1/n_c, the scale read 0.969 +- 0.006 on the 'ar1' case's 300 s bags, seeds 21-32)
    significant = noise_structure.correlated(rho_tracks, pairs_tracks, 0.0) is not None
    scatter_rho, scatter_share = (rep_track.phi, rep_track.share) if significant else (0.0, 1.0)
    r, share, chi2, dof = _minus_cell_means(r, cell, keep_cell)
    if scatter_rho > 0.0:
        cells_at_rho = cell_shares(cell, keep_cell, stars, scatter_rho, scatter_share)
        share = np.where(share > 0, cells_at_rho, share)
    share = share * sub_share
    # ... and so is an error that repeats star by star (a catalogue position error): its
    # per-star means are tested, and removed when significant
    _, _, r_star, share_star = star_means(r, share, stars)
    # (the star means of residuals the cells' means have already left take less than 1/n_s
    # a row: a track that stays in its cell has had its mean taken by the cell; counted as
    # 1/n_s, the scale read 1.0055, z +0.50 +- 0.07, on 200 iid draws on a 150 s psce bag
    # with the removal forced; now 0.9993, z -0.08, as without the removal)
    share_star = star_shares_after_cells(share, sub_share, stars, cell)
    # noise correlated over a few frames makes each star's mean vary more than 1/n: the χ²
    # is referred to that (the lag correlation of the residuals about their star's mean,
    # which a fixed per-star error does not raise)
    track = noise_structure.track_model(r_star, stars, cell=cell)
    # (tested after the cells' means: χ² and dof of the stars' means beyond them, the χ²
    # referred to the exact trace of the tracks' covariance through its projection, the
    # model read about the star means before the cells' means: ``rep_track`` above)
    rep, rep_dof = star_after_cells(r_cells, cell, keep_cell, stars, sub_share, rep_track.phi,
                                    rep_track.share)
    # (where the frames' noise differs, the same χ² with each row in its frame's own σ
    # (noise_structure.frame_variances), the smaller of the two said: a noise that grows in
    # the slews' frames made the star means of the stars seen there read as a per-star
    # error at one σ, unseen case ``rate_noise`` s21 χ² 535 / 156)
    row_var = noise_structure.frame_variances(0.5 * np.sum(r_cells**2, axis=1), sub["frame"])
    rep_frames = None if row_var is None else star_after_cells(
        r_cells / np.sqrt(row_var)[:, None], cell, keep_cell, stars, sub_share,
        rep_track.phi, rep_track.share)[0]

    def repeat(scale: float) -> float:
        """The repeat's χ² in the units of the stars' noise ``scale``."""
        at_one = rep / max(scale, 1e-300) ** 2
        return at_one if rep_frames is None else min(at_one, rep_frames)
    # each cell's mean referred to the variance of a mean of its tracks' frames (with the
    # tracks' model read before the cells' means, as the repeat's: read after them ρ is
    # biased low, 0.809 for 0.819, and the cells' χ² high: 'ar1' 300 s seed 30 called a
    # repeating field, p 0.0016; the larger factor of the two readings)
    cells_track = max(track, rep_track, key=lambda t: t.factor)
    cells_lag = (cells_track.phi, cells_track.share) if track.phi > 0 else (0.0, 1.0)
    if track.phi > 0:
        chi2 = noise_structure.lagged_chi2(r_cells, cell, stars, cells_track.phi, keep_cell,
                                           share=cells_track.share)
    # (and where it reads a field: the same statistic against sign flips of whole tracks,
    # :func:`~.noise_structure.flip_p`, whether the stars' tracks share it)
    flip = (lambda: noise_structure.flip_p(r_cells, cell, stars, cells_lag[0], keep_cell,
                                           share=cells_lag[1])) if dof > 0 else None

    def estimate(r, share):
        q = (r**2).sum(1)
        m = (2.0 - lev) * share
        use = np.isfinite(q) & (m > 0)
        if not use.any():
            return None
        out = StarNoise(0.0, 0.0, float(m[use].sum()), n_frames, q[use], m[use],
                        np.asarray(res["magnitude"], dtype=float)[idx][use],
                        np.hypot(uv[use, 0] - centre[0], uv[use, 1] - centre[1]),
                        (msg_sigma[idx] == 0)[use], sigma_px[idx][use], uv=uv[use],
                        star=stars[use], scatter_rho=scatter_rho,
                        frame=np.asarray(res["frame"])[idx][use],
                        scatter_share=scatter_share, stated_px=msg_sigma[idx][use],
                        t=np.asarray(res["t"], dtype=float)[idx][use],
                        speed=None if speed is None else speed[use])
        out.scale, out.sigma, _ = out.group(np.ones(len(out.q), dtype=bool))
        return out

    out = estimate(r, share)
    if out is None:
        return None
    final = (r, share)
    out.repeat, out.repeat_dof = repeat(out.scale), rep_dof
    if out.repeat_p < ALPHA:
        rms = out.repeat_rms_px
        star_out = estimate(r_star, share_star)
        if star_out is not None:
            out, final = star_out, (r_star, share_star)
        out.repeat, out.repeat_dof, out.repeat_removed = repeat(out.scale), rep_dof, rms
    if scatter_rho > 0.0:
        # tracks correlated: the σ of the scale from the variance of Σ q through the
        # frames' attitude fit, the cells' means and the stars' (when removed), and of the
        # dof it is divided by, which the cells' shares take from ρ̂ (:func:`cell_shares`),
        # read from the same residuals: not the sandwich times a per-track factor
        dm = 0.0
        if scatter_share == 1.0:  # (white + AR(1): (w, φ) fitted jointly, not counted)
            step = 1e-4
            d_cells = (cell_shares(cell, keep_cell, stars, scatter_rho + step)
                       - cells_at_rho) / step
            r_f, share_f = final
            use = np.isfinite((r_f**2).sum(1)) & ((2.0 - lev) * share_f > 0)
            dm = float(np.sum(((2.0 - lev) * sub_share * d_cells)[use]))
        out.log_variance = _correlated_variance(
            sub, fit_sigma, fx, fy, r_cells, cell, keep_cell, stars, final,
            out.repeat_removed > 0, lev, (scatter_share, scatter_rho), out, dm, w)
        if not (math.isfinite(out.log_variance) and out.log_variance > 0.0):
            # (a stochastic trace of a few probes on a tiny table can come out <= 0: the
            # sandwich times the tracks' factor then, never a sqrt of a negative)
            out.log_variance = None
        out.scale, out.sigma, _ = out.group(np.ones(len(out.q), dtype=bool))
    out.structure, out.structure_dof = chi2 / max(out.scale, 1e-300) ** 2, dof
    if flip is not None and (flips or out.structure_p < ALPHA):
        out.structure_flip_p = flip()
    out.track_rho, out.track_pairs = track.rho, track.pairs
    out.track_phi, out.track_share = track.phi, track.share
    out.track_factor_sigma = track.factor_sigma
    out.subpixel_p, out.rolling_p = p_sub, p_roll
    out.patterns = [{"axis": a, "z": fp.z, "p": fp.p, "at_px": fp.at_px,
                     "size_px": fp.size_px if math.isfinite(fp.size_px) else abs(fp.top),
                     "removed": removed}
                    for a, fp, removed, *_ in patterns or []]
    out.pattern_px = pattern_offsets(patterns or [], len(sigma_px))
    return out


def pattern_offsets(patterns: list, rows: int) -> np.ndarray | None:
    """The offsets (px, ``(rows, 2)``: u, v) the residuals hold of the patterns removed.

    Those :func:`detector_patterns` removed (its ``seen``), per row of its table (0 where it
    read none); None where none was removed.
    """
    out = None
    for axis, _, removed, _, _, seen in patterns:
        if removed:
            out = np.zeros((rows, 2)) if out is None else out
            out[:, "uv".index(axis)] = seen
    return out


def _minus_patterns(r: np.ndarray, share: np.ndarray, patterns: list, idx: np.ndarray,
                    sigma_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``r`` (rows ``idx`` of the table) without the patterns :func:`detector_patterns` removed.

    Each removed axis less its rows' pixels' means (px, over ``sigma_px``: ``r``'s units);
    each row's share of its 2 dof reduced by half its share of its pixel's mean.  ``(r,
    share)`` as given where none is removed.
    """
    out_r, out_share = r, share
    for axis, _, removed, offset, lev, _ in patterns:
        if not removed:
            continue
        if out_r is r:
            out_r, out_share = r.copy(), share.copy()
        ax = "uv".index(axis)
        out_r[:, ax] -= offset[idx] / sigma_px
        out_share = out_share * np.clip(1.0 - 0.5 * lev[idx], 0.0, 1.0)
    return out_r, out_share


#: Rademacher probes of :func:`quadratic_variance`'s traces (fixed seed): enough for
#: TRACE_ROWS probe-rows, at most TRACE_PROBES.  One probe on a 300 s psce table (5 700
#: rows) put the scale's σ within ~2 % of 256 probes' (16: 0.4 %); the spread falls as
#: 1/√(rows × probes), so a 2-h bag's 140 000 rows take one (the cost is linear in both)
TRACE_PROBES = 16
TRACE_ROWS = 100_000


def _indicator(label: np.ndarray):
    """The sparse ``(groups, rows)`` indicator of ``label`` and each group's row count."""
    from scipy.sparse import csr_matrix

    _, k = np.unique(label, return_inverse=True)
    k = np.asarray(k).reshape(-1)
    ind = csr_matrix((np.ones(len(k)), (k, np.arange(len(k)))), shape=(int(k.max()) + 1, len(k)))
    return ind, np.bincount(k).astype(float)


def _minus_means(label: np.ndarray, rows: np.ndarray):
    """``z ↦ z`` minus its mean per ``label`` over ``rows``, 0 elsewhere (a projection)."""
    ind, n = _indicator(np.asarray(label)[rows])

    def step(z: np.ndarray) -> np.ndarray:
        out = np.zeros_like(z)
        zr = z[rows].reshape(int(rows.sum()), -1)
        out[rows] = (zr - ind.T @ ((ind @ zr) / n[:, None])).reshape(z[rows].shape)
        return out
    return step


def _minus_frame_fit(A: np.ndarray, frame: np.ndarray):
    """``z ↦ (I − P_W) z``: :func:`~.stats.within_frame`'s attitude fit as a projection.

    ``A``: the whitened attitude columns ``(n, 2, 3)`` of rows whose frames it fitted.
    """
    ind, _ = _indicator(frame)
    Gi = np.linalg.inv((ind @ np.einsum("iak,ial->ikl", A, A).reshape(len(A), 9)
                        ).reshape(-1, 3, 3))
    Af = A.reshape(len(A), 2, 3)

    def step(z: np.ndarray) -> np.ndarray:
        K = z.shape[2]
        b = (ind @ np.einsum("iak,iaj->ikj", Af, z).reshape(len(A), 3 * K)).reshape(-1, 3, K)
        c = Gi @ b
        return z - np.einsum("iak,ikj->iaj", Af, (ind.T @ c.reshape(len(c), 3 * K)
                                                  ).reshape(len(A), 3, K))
    return step


def quadratic_variance(forms: list, track: np.ndarray, lags: tuple[float, float],
                       probes: int | None = None) -> tuple[float, ...]:
    """``tr(X Σ Y Σ)`` over the pairs of ``forms`` (``z ~ N(0, Σ)``): ``Cov(zᵀXz, zᵀYz) / 2``.

    Each form ``X = Mᵀ M`` (or ``Mᵀ K M`` when its last step ``K`` is symmetric but no
    projection): its steps ``M`` applied in order, each symmetric (a fit's or a group's means
    removed, rows left out set to 0), then back (``X = P_1 … P_k … P_1``).  ``Σ``: the tracks'
    unit-variance noise (:func:`~.noise_structure.along_tracks` with ``lags``, rows of each
    ``track`` in time order, the axes independent).  For a Gaussian ``z``, ``Var zᵀXz = 2
    tr((XΣ)²)``.  By Hutchinson's estimator over ``probes`` Rademacher vectors ``u`` of a
    fixed seed, ``uᵀ X Σ Y Σ u`` (O(n) a probe: no n × n matrix; ``probes`` None: as
    :data:`TRACE_ROWS` asks).  Returns the pairs ``(0, 0), (0, 1), (1, 1), …`` in that
    order (one form: one trace).
    """
    n = len(track)
    if probes is None:
        probes = int(min(TRACE_PROBES, max(1, math.ceil(TRACE_ROWS / max(n, 1)))))
    u = np.random.default_rng(0).choice([-1.0, 1.0], size=(n, 2, probes))

    def apply(steps, z):
        for st in steps:
            z = st(z)
        for st in steps[-2::-1]:
            z = st(z)
        return z

    Su = noise_structure.along_tracks(u, track, lags)
    Xu = [apply(f, u) for f in forms]
    SXSu = [noise_structure.along_tracks(apply(f, Su), track, lags) for f in forms]
    return tuple(float(np.sum(Xu[a] * SXSu[b])) / probes
                 for a in range(len(forms)) for b in range(a, len(forms)))


def _correlated_variance(sub: Table, sigma: np.ndarray, fx: float, fy: float,
                         r_cells: np.ndarray, cell: np.ndarray, keep_cell: np.ndarray,
                         stars: np.ndarray, final: tuple[np.ndarray, np.ndarray],
                         star_removed: bool, lev: np.ndarray, lags: tuple[float, float],
                         out: StarNoise, dm_drho: float = 0.0,
                         weights: np.ndarray | None = None) -> float:
    """:attr:`StarNoise.log_variance`: the variance of ``log s² = log Σ q − log m``.

    ``Σ q = zᵀ A z``: the steps of :func:`star_noise` as projections of the rows its
    frames' attitude fit kept (its fit, the cells' means over the ``keep_cell`` rows, the
    stars' means when removed, the rows summed; :func:`quadratic_variance`), ``z`` the
    whitened noise of covariance ``s² Σ`` (the tracks' model ``lags``).  ``m``: the dof,
    the cells' shares of it counted with the tracks' ρ̂ (``dm_drho`` its slope; 0: not
    counted), read from the same residuals by :func:`~.noise_structure.track_inflation`
    (the lag-1 ratio ``L / √(S_a S_b)`` of the rows about their star means, before the
    cells'): linearized, ``d raw = zᵀ E z``, a quadratic form too.  Hence ``Var log Σ q =
    2 tr((AΣ)²)/m²``, ``Var ρ̂ = 2 tr((EΣ)²)/slope²`` and their covariance ``2 tr(AΣEΣ)/(m
    slope)``.  A realization with more long-run power reads both more ``Σ q`` and a higher ρ̂
    (whose cells' means then take more dof): the two add.  Measured, 100 pure AR(1) draws
    in one 300 s table: ``Σ q`` and ``m`` correlate −0.72; the scale's SD 0.0173 for 0.0159
    with ``m`` held (the sandwich times the tracks' factor printed 0.0150).
    """
    from stellar_cal_ros.diagnosis.stats import attitude_columns

    rows = finite_rows(r_cells)  # the frames the attitude fit took
    sel = {k: np.asarray(v)[rows] for k, v in sub.items()}
    A = attitude_columns(sel, fx, fy) / sigma[rows, None, None]
    keep = np.asarray(keep_cell)[rows]
    track = stars[rows]
    r_f, share_f = final
    used = np.isfinite((r_f[rows] ** 2).sum(1)) & ((2.0 - lev[rows]) * share_f[rows] > 0)
    fit = _minus_frame_fit(A, sel["frame"])
    steps = [fit, _minus_means(cell[rows], keep)]
    if weights is not None:  # (the fit's whitening back to the run's σ: a diagonal step)
        wr = np.asarray(weights, dtype=float)[rows][:, None, None]
        steps.insert(1, lambda z: z * wr)
    if star_removed:
        steps.append(_minus_means(track, keep & (share_f[rows] > 0)))
    steps.append(lambda z: np.where(used[:, None, None], z, 0.0))
    m = float(out.m.sum())
    forms = [steps]
    form = _lag1_form(r_cells[rows] / max(out.scale, 1e-300), track, lags[1]) \
        if dm_drho != 0.0 else None
    g = 0.0
    if form is not None:
        lag1, g = form
        g *= dm_drho / m
        forms.append([fit, _minus_means(track, np.ones(len(track), dtype=bool)), lag1])
    t = quadratic_variance(forms, track, lags)
    if len(t) == 1:
        return 2.0 * t[0] / m**2
    t_aa, t_ae, t_ee = t
    return 2.0 * t_aa / m**2 - 4.0 * g * t_ae / m + 2.0 * g * g * t_ee


def _lag1_form(x: np.ndarray, track: np.ndarray, rho: float) -> tuple[Any, float] | None:
    """The lag-1 ratio's linearization: the step ``z ↦ K z`` and ``dρ̂/d raw``.

    ``x``: whitened residuals at unit scale ``(n, 2)`` (rows of each ``track`` in time
    order) before their star means; :func:`~.noise_structure.track_inflation` reads ``raw
    = L / √(S_a S_b)`` of them about their star means (``L = Σ x_t·x_(t+1)`` over a
    track's consecutive rows, ``S_a``, ``S_b`` the squares of the pairs' later and
    earlier members) and solves it for ρ̂.  ``d raw = raw (dL/L − dS_a/(2 S_a) − dS_b/(2
    S_b))`` is the quadratic form ``xᵀ K x`` (``K`` symmetric, applied here to rows about
    their star means; its value at ``x`` is 0).  ``rho``: the ρ̂ read.  Returns ``(K as a
    step, 1/slope)``, the slope :func:`~.noise_structure.rho_slope`'s, or None (no lag-1
    correlation to linearize).
    """
    order, ts = noise_structure.in_track_order(track)
    _, k = np.unique(ts, return_inverse=True)
    xs = x[order]
    xs = xs - (np.stack([np.bincount(k, xs[:, c]) for c in range(2)], 1)
               / np.bincount(k)[:, None])[k]
    a, b, same = noise_structure.lag_pairs(xs, ts)
    L, Sa, Sb = float(np.sum(a * b)), float(np.sum(a * a)), float(np.sum(b * b))
    raw = L / math.sqrt(Sa * Sb)
    n = np.bincount(k).astype(float)
    slope = noise_structure.rho_slope(n[n >= 2], rho)
    if not (L > 0.0 and slope > 0.0):
        return None
    later = np.r_[False, same]  # rows that are a pair's later member
    earlier = np.r_[same, False]
    wd = (later / (2.0 * Sa) + earlier / (2.0 * Sb))[:, None, None]

    def step(z: np.ndarray) -> np.ndarray:
        zs = z[order]
        nb = np.zeros_like(zs)  # ½ the neighbours in the track: (B z)
        nb[1:][same] += 0.5 * zs[:-1][same]
        nb[:-1][same] += 0.5 * zs[1:][same]
        out = np.empty_like(z)
        out[order] = raw * (nb / L - wd * zs)
        return out
    return step, 1.0 / slope


def _structure_blocks(uv: np.ndarray | None, X_sub: np.ndarray | None, x: np.ndarray | None
                      ) -> list[np.ndarray | None]:
    """The sub-pixel and rolling-shutter fits' blocks of :func:`~.noise_structure.minus_fits`.

    None where a fit has no regressors (no predicted centroids, no installation).
    """
    return [None if uv is None else noise_structure.subpixel_block(uv, X_sub),
            noise_structure.rolling_block(x)]


def _fit_lags(r: np.ndarray, share: np.ndarray, blocks: list[np.ndarray | None],
              stars: np.ndarray) -> tuple[float, float] | None:
    """The tracks' ``(w, φ)`` the structure fits' χ² are referred to, or None (white).

    Read by :func:`~.noise_structure.track_model` about the star means, as the cells'
    test reads it, on the residuals with the fits of ``blocks`` (:func:`_structure_blocks`,
    :func:`~.noise_structure.minus_fits`) taken out whatever their χ² (a real pixel locking
    or readout, correlated along a track as the star crosses pixels, would otherwise be
    read as correlated noise and discount its own test); significant as :func:`star_noise`
    counts it (:func:`~.noise_structure.correlated` without its materiality,
    :func:`~.noise.track_lags`' rule).  Pure AR(1) noise of τ 5 frames, taken as white,
    fired the sub-pixel fit in 41.5 % of 200 draws and the rolling fit in 8 % at 1 %
    (``benchmarks/nuisance_level.py``; referred: 1.5 % and 0 %).
    """
    rr = noise_structure.minus_fits(r, share, blocks, 1.0)[0]
    model = noise_structure.track_model(star_means(rr, share, stars)[2], stars)
    if noise_structure.correlated(model.rho, model.pairs, 0.0) is None:
        return None
    return float(model.share), float(model.phi)


def cell_shares(cell: np.ndarray, keep: np.ndarray, star: np.ndarray, rho: float,
                ar_share: float = 1.0) -> np.ndarray:
    """Each row's share of its dof left by its cell's mean, for noise correlated along tracks.

    A cell's mean of ``n_c`` rows takes ``1ᵀ Σ_cc 1 / n_c`` of their expected sum of
    squares (``Σ``: unit-variance AR(1) of lag-1 ``rho`` along each ``star``'s rows, in
    time order; stars independent), not 1 as for white noise: each row of a ``keep`` cell
    keeps ``1 − 1ᵀ Σ_cc 1 / n_c²`` (:func:`_run_sums` sums ``Σ`` over the runs of a
    track's rows in one cell).  Rows outside the ``keep`` cells: 0.  White + AR(1) noise
    (``ar_share`` the AR's part of the variance): ``1ᵀ Σ_cc 1`` is linear in ``Σ``, ``(1 −
    w) n_c`` plus ``w`` the AR's.
    """
    out = np.zeros(len(cell))
    ok = np.asarray(keep, dtype=bool)
    if not ok.any():
        return out
    _, si = np.unique(np.asarray(star)[ok], return_inverse=True)
    ci = np.asarray(cell)[ok]
    G = np.zeros(int(ci.max()) + 1)
    order = np.argsort(si, kind="stable")
    ends = np.cumsum(np.bincount(si))
    for s in range(len(ends)):
        cu, M, run_cell = _run_sums(ci[order[(ends[s - 1] if s else 0):ends[s]]], rho)
        same = run_cell[:, None] == run_cell[None, :]  # pairs of runs in one cell
        G[cu] += np.bincount(run_cell, (M * same).sum(1), minlength=len(cu))
    n = np.bincount(ci, minlength=len(G)).astype(float)
    if ar_share != 1.0:
        G = (1.0 - ar_share) * n + ar_share * G
    out[ok] = 1.0 - G[ci] / n[ci] ** 2
    return out


def star_means(r: np.ndarray, share: np.ndarray, star: np.ndarray
               ) -> tuple[float, float, np.ndarray, np.ndarray]:
    """The per-star means of the whitened residuals ``r``: their χ², its dof, ``r`` without them.

    Stars seen in at least two frames count; the χ² is ``Σ_s n_s ‖r̄_s‖²`` and its
    expectation for noise alone ``Σ_s 2 mean(share)`` (``share``: each residual's share of
    its dof left by earlier fits).  Returns ``(χ², dof, r − r̄_star, share (1 − 1/n_s))``.
    """
    ok = finite_rows(r) & (share > 0)
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


def star_shares_after_cells(share: np.ndarray, sub_share: np.ndarray, star: np.ndarray,
                            cell: np.ndarray) -> np.ndarray:
    """Each row's share of its dof left after its cell's mean, then its star's mean.

    ``share``: the shares after the cells' means (:func:`_minus_cell_means`; rows of share 0
    count for neither mean), ``sub_share``: the part of it earlier fits left.  The star
    means of residuals without their cells' means (``r_c = (I − P_C) r``, then ``r'' = (I −
    P_S) r_c``) take ``h_i = (I − P_C)_ii − ((I − P_S)(I − P_C)(I − P_S))_ii`` of row
    ``i``'s expected square, not ``1/n_s``: ``h_i = 1/n_s − 2 n_sc/(n_c n_s) + Σ_c'
    n_sc'² / (n_c' n_s²)`` (``n_sc``: the star's rows in the row's cell ``c``), summing to
    ``S − tr(P_S P_C)``.  A star whose track stays in one cell keeps ``1 − 1/n_s`` (the
    cell's mean leaves its star mean's residuals alone; ``h = 1/n_s − 1/n_c``).  Returns
    ``share − sub_share · h`` (≥ 0).
    """
    ok = share > 0
    out = np.zeros(len(share))
    if not ok.any():
        return out
    _, si = np.unique(np.asarray(star)[ok], return_inverse=True)
    _, ci = np.unique(np.asarray(cell)[ok], return_inverse=True)
    ns = np.bincount(si).astype(float)
    nc = np.bincount(ci).astype(float)
    pair, k = np.unique(si.astype(np.int64) * (int(ci.max()) + 1) + ci, return_inverse=True)
    nsc = np.bincount(k).astype(float)
    p_s, p_c = pair // (int(ci.max()) + 1), pair % (int(ci.max()) + 1)
    g = np.bincount(p_s, nsc**2 / nc[p_c], minlength=len(ns))  # per star: Σ_c n_sc²/n_c
    h = 1.0 / ns[si] - 2.0 * nsc[k] / (nc[ci] * ns[si]) + g[si] / ns[si] ** 2
    out[ok] = np.clip(share[ok] - sub_share[ok] * h, 0.0, None)
    return out


def star_after_cells(r: np.ndarray, cell: np.ndarray, keep: np.ndarray, star: np.ndarray,
                     share: np.ndarray | None = None, rho: float = 0.0,
                     ar_share: float = 1.0) -> tuple[float, float]:
    """The χ² of the per-star means beyond the detector cells' means, and its exact dof.

    ``r``: whitened residuals ``(n, 2)`` before the cells' means, rows of the cells ``keep``
    counting.  The cells' means take most of a star's mean when its track stays in few
    cells (one star a cell: all of it), so the star means of ``r`` minus the cells' means
    (:func:`star_means`) sit far below ``Σ 2 (1 − 1/n_s)`` (white bag: 10.4 for 68.8).  The
    statistic is the stars' sum of squares after the cells' (``SS(S) + SS(C|S) − SS(C)``,
    per axis, ``SS(C|S)`` solved in the cells), a χ² of ``2 (stars − groups)`` dof for
    noise alone (``groups``: stars and cells connected through shared rows; the rank the
    stars add to the cells), times the mean ``share`` left by earlier fits.  Noise
    correlated along the tracks (an AR(1) of lag-1 ``rho`` over each star's rows in time
    order, :func:`~.noise_structure.track_inflation`) raises the expectation of each axis's
    sum of squares from ``stars − groups`` to the trace of its covariance through the
    projection (:func:`_trace_after_cells`); the χ² is referred to that (mean exact; the
    ratio of the star means' lagged and plain χ² made it ~13 % conservative at ρ 0.82,
    because the cells take the long parts of a track's mean).  ``ar_share``: white + AR(1)
    noise, the AR's share of the variance (:func:`~.noise_structure.track_model`).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    ok = np.asarray(keep, dtype=bool) & finite_rows(r)
    if share is not None:
        ok &= share > 0
    if ok.sum() < 2:
        return 0.0, 0.0
    x = r[ok]
    _, si = np.unique(np.asarray(star)[ok], return_inverse=True)
    _, ci = np.unique(np.asarray(cell)[ok], return_inverse=True)
    S, C = int(si.max()) + 1, int(ci.max()) + 1
    ns, nc = np.bincount(si).astype(float), np.bincount(ci).astype(float)
    N = coo_matrix((np.ones(len(si)), (si, ci)), shape=(S, C)).tocsr()
    groups = connected_components(coo_matrix((np.ones(len(si)), (si, S + ci)),
                                             shape=(S + C, S + C)), directed=False)[0]
    A = np.diag(nc) - (N.T.multiply(1.0 / ns) @ N).toarray()  # cells' normal matrix | stars
    Ap = np.linalg.pinv(A, rcond=1e-10, hermitian=True)
    chi2 = 0.0
    for k in range(2):
        ms = np.bincount(si, x[:, k]) / ns
        mc = np.bincount(ci, x[:, k]) / nc
        z = np.bincount(ci, x[:, k] - ms[si], minlength=C)
        chi2 += float(ns @ ms**2 + z @ Ap @ z - nc @ mc**2)
    if rho > 0.0 and S > groups:
        chi2 *= (S - groups) / _trace_after_cells(si, ci, ns, nc, Ap, rho, ar_share)
    dof = 2.0 * (S - groups) * (float(np.mean(share[ok])) if share is not None else 1.0)
    return max(chi2, 0.0), dof


def _trace_after_cells(si: np.ndarray, ci: np.ndarray, ns: np.ndarray, nc: np.ndarray,
                       Ap: np.ndarray, rho: float, share: float = 1.0) -> float:
    """``tr((P_{S+C} − P_C) Σ)``: what one axis of :func:`star_after_cells` expects under AR(1).

    ``Σ``: unit-variance AR(1) of lag-1 ``rho`` along each star's rows (``si``, in time
    order; stars independent); ``P``: the projections on the star and cell indicators
    (``ci``), ``Ap`` the pseudo-inverse of the cells' normal matrix given the stars.  The
    trace is ``tr(P_S Σ) + tr(A⁺ Cᵀ M Σ M C) − tr(P_C Σ)`` (``M``: minus the star means):
    ``Σ_s f(n_s)`` (:func:`~.noise_structure.mean_factor`), the cells' term summed star by
    star, and ``Σ_c 1ᵀ Σ_cc 1 / n_c``; white noise (``rho`` 0) gives ``stars − groups``.
    White + AR(1) noise (``share`` the AR's part of the variance, ``Σ = (1 − w) I + w
    Σ_AR``): the trace is linear in ``Σ``, ``(1 − w)`` the white trace plus ``w`` the AR's.
    """
    if share != 1.0:
        return (1.0 - share) * _trace_after_cells(si, ci, ns, nc, Ap, 0.0) \
            + share * _trace_after_cells(si, ci, ns, nc, Ap, rho)
    C = len(nc)
    B, within = np.zeros((C, C)), np.zeros(C)
    # each star's rows in time order (a stable sort by star) and Σ's sums over the runs of
    # its cells (:func:`_run_sums`): no dense n × n Σ a star (it grew as n²: a track of
    # 4 000 rows, 1.6 CPU-s and 0.46 GB; a star held for hours on a still base has more)
    order = np.argsort(si, kind="stable")
    ends = np.cumsum(np.bincount(si, minlength=len(ns)))
    for s in range(len(ns)):
        c = ci[order[(ends[s - 1] if s else 0):ends[s]]]
        cu, M, run_cell = _run_sums(c, rho)
        U = np.zeros((len(run_cell), len(cu)))
        U[np.arange(len(run_cell)), run_cell] = 1.0
        K = U.T @ M @ U  # Eᵀ Σ E (E: the star's rows × its cells)
        v, e = K.sum(1), np.bincount(np.searchsorted(cu, c), minlength=len(cu)) / len(c)
        within[cu] += np.diag(K)
        # (E − 1 eᵀ)ᵀ Σ (E − 1 eᵀ): the rows about the star's mean
        B[np.ix_(cu, cu)] += K - np.outer(v, e) - np.outer(e, v) + v.sum() * np.outer(e, e)
    return float(np.sum(noise_structure.mean_factor(ns, rho)) + np.sum(Ap * B.T)
                 - np.sum(within / nc))


def _run_sums(c: np.ndarray, rho: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A track's cells ``c`` (its rows in time order) as runs: ``(cells, M, run_cell)``.

    ``M[a, b] = Σ_(i ∈ a, j ∈ b) ρ^|i − j|`` over the runs ``a``, ``b`` of consecutive rows
    in one cell (a unit-variance AR(1) of lag-1 ``rho`` along the rows): ``L f(L)`` within a
    run of ``L`` rows (:func:`~.noise_structure.mean_factor`), ``ρ^(gap + 1) G(L_a) G(L_b)``
    between two (``G(L) = (1 − ρ^L)/(1 − ρ)``, ``gap`` the rows between them); ``cells``
    the distinct cells, ``run_cell`` each run's place in them.
    """
    start = np.r_[0, np.flatnonzero(c[1:] != c[:-1]) + 1]
    stop = np.r_[start[1:], len(c)]
    L = (stop - start).astype(float)
    G = (1.0 - rho**L) / (1.0 - rho)
    gap = np.abs(start[None, :] - stop[:, None] + 1)  # a < b: rows from a's last to b's first
    M = np.triu(rho ** gap.astype(float) * np.outer(G, G), 1)
    M = M + M.T + np.diag(L * noise_structure.mean_factor(L, rho))
    cells, run_cell = np.unique(c[start], return_inverse=True)
    return cells, M, np.asarray(run_cell).reshape(-1)


#: the cells whose mean residual is structure, not noise: a grid over the detector times
#: magnitude classes, cells of at least CELL_MIN stars
CELL_GRID = 6
MAGNITUDE_CLASSES = 3
CELL_MIN = 8


def detector_cells(uv: np.ndarray, centre: tuple[float, float],
                   ext: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Each star's cell of the :data:`CELL_GRID` × :data:`CELL_GRID` detector grid, and its extent.

    The cell is a flat index; the extent is px along u and v: twice the largest offset from
    ``centre`` plus 1, unless ``ext`` gives another's (:func:`~stellar_cal_ros.diagnosis.
    leads.detector_grid`: one grid fixed on the detector for every model of a bag).
    """
    d = uv - np.asarray(centre)
    if ext is None:
        ext = 2.0 * np.nanmax(np.abs(d), axis=0) + 1.0
    ij = np.clip((d / ext + 0.5) * CELL_GRID, 0, CELL_GRID - 1e-9).astype(int)
    return ij[:, 0] * CELL_GRID + ij[:, 1], ext


def _cells(uv: np.ndarray, magnitude: np.ndarray, centre: tuple[float, float]
           ) -> tuple[np.ndarray, np.ndarray]:
    """Cell index of each star (detector grid × magnitude class) and which cells count."""
    grid, _ = detector_cells(uv, centre)
    fin = np.isfinite(magnitude)
    mclass = np.zeros(len(uv), dtype=int)
    if fin.sum() > MAGNITUDE_CLASSES * CELL_MIN:
        edges = np.quantile(magnitude[fin], np.linspace(0, 1, MAGNITUDE_CLASSES + 1)[1:-1])
        mclass = np.searchsorted(edges, np.nan_to_num(magnitude, nan=float(np.median(
            magnitude[fin]))), side="right")
    cell = grid * MAGNITUDE_CLASSES + mclass
    counts = np.bincount(cell, minlength=CELL_GRID**2 * MAGNITUDE_CLASSES)
    return cell, counts[cell] >= CELL_MIN


def _minus_cell_means(r: np.ndarray, cell: np.ndarray, keep: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, float, int]:
    """``r`` minus its mean per cell, each star's share of its dof, the cell means' χ².

    The χ² is ``Σ n_c ‖r̄_c‖²`` (whitened r, scale 1), its dof 2 per cell.
    """
    out = np.full_like(r, np.nan)
    share = np.zeros(len(r))
    ok = keep & finite_rows(r)
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
    return stat, float(dist.chi2.sf(stat, len(parts) - 1))


def _bins(sn: StarNoise, gidx: np.ndarray, n: int) -> list[tuple[float, float, float]]:
    """Bartlett's parts of the bins ``0 .. n − 1`` of ``gidx``: ``(scale, σ, dof)`` each.

    The dof the rows' (:meth:`StarNoise.group`) where a star's rows are independent; where
    they are not, the scale's effective dof with the stars as units, ``s² / (2 σ²)`` (``σ``
    of the scale from the scores summed per star and per frame,
    :meth:`StarNoise._star_units`).  Not independent: the σ with the stars as units over
    the rows' beyond :data:`DEPENDENT` and significant (its square ~ ``χ²_{n−1} / (n − 1)``
    for ``n`` stars of independent rows, p below :data:`ALPHA`).  A star whose error holds
    still while the tracker rests (a centroid quantised to a 0.5 px grid, unseen case
    ``bright_quant``: its sub-pixel phase does not change) put its excess in the bin of the
    column it dwelt at as if each of its rows were a draw: a column grouping x1.46 at p
    3e-28 beside the magnitude one (200 s seed 8, one bright star; H274: its bin's
    variance ratio 77, clean bins of the same bag at most 3.4).
    """
    out = []
    for g in range(n):
        s, e, d = sn.group(gidx == g)
        if sn.star is not None and sn.frame is not None and d > 0 and e > 0:
            _, es, k = sn.group(gidx == g, stars=True)
            ratio = (es / e) ** 2
            if k > 1 and ratio > DEPENDENT and \
                    float(dist.chi2.sf(ratio * (k - 1), k - 1)) < ALPHA:
                d = min(d, s * s / (2.0 * es * es))
        out.append((s, e, d))
    return out


#: a σ group's rows are not independent (:func:`_bins`) where its scale's variance with the
#: stars as units is more than this many times the rows' (and significantly): the stars' own
#: levels then count, not each row (a quantised star at rest: 36-78 in ``bright_quant``'s
#: bins of the bright stars; a clean psce run's bins 0.03-3.4, 200 s seed 8)
DEPENDENT = 4.0


def _merge(sn: StarNoise, gidx: np.ndarray, edges: np.ndarray, use: np.ndarray,
           steps: np.ndarray | None = None, stars: bool = False
           ) -> tuple[np.ndarray, np.ndarray, list[tuple[float, float, float]]]:
    """Merge neighbouring bins whose scales agree (within :data:`MERGE_Z` σ).

    Bins are tested fine (a step in the noise at 4.5 mag or at column 683 falls inside one
    bin, whose mixed scale is then a small share of the stars) and reported coarse: the
    pair of neighbours closest in scale is merged until every neighbour differs.  Returns
    the remaining edges, the group index of each star and the groups' (scale, σ, dof).
    ``stars``: the σ with the stars as units (:meth:`StarNoise.group`).
    """
    edges = np.asarray(edges, dtype=float)
    while len(edges):
        parts = [sn.group(gidx == g, stars) for g in range(len(edges) + 1)]
        z = [abs(a[0] - b[0]) / math.hypot(a[1], b[1]) if all(
            math.isfinite(x) and x > 0 for x in (a[0], b[0], a[1], b[1])) else 0.0
            for a, b in zip(parts, parts[1:], strict=False)]
        # (an edge at a step of the messages' σ, ``steps``, goes last: a small bin between
        # it and a quantile edge beside it merged across the step, mag_faint_over2 seed 4)
        last = np.isin(edges, steps) if steps is not None and len(steps) else \
            np.zeros(len(z), dtype=bool)
        k = int(np.argmin(np.where(last & (np.asarray(z) < MERGE_Z), math.inf, z))) \
            if np.any(~last & (np.asarray(z) < MERGE_Z)) else int(np.argmin(z))
        if z[k] >= MERGE_Z:
            return edges, gidx, parts
        edges = np.delete(edges, k)
        gidx = np.where(gidx > k, gidx - 1, gidx)
    return edges, gidx, [sn.group(use, stars)]


def known_groups(sn: StarNoise, size: tuple[int, int] | None,
                 kept: NoiseScales | None = None) -> list[dict[str, Any]]:
    """:func:`star_groups` of the stars grouped (:func:`grouped_stars`), made once per rows.

    :func:`fit_weights` made them already where :func:`star_noise` stopped on these rows;
    the scale, σ and dof of a :class:`StarNoise` (what a verdict replaces) do not enter
    them.
    """
    made = sn.groups_made
    if made is not None and made[0] == (size, kept):
        return made[1]
    return star_groups(sn, size, grouped_stars(sn), kept)


def grouped_stars(sn: StarNoise) -> np.ndarray:
    """The stars the σ groups are of: those of stated σ, or every star where none states one.

    A σ-0 star beside stated ones keeps its own measured σ (:func:`~.noise.judge_stars`);
    where no message states a σ, the groups are of every star, factors of the default σ.
    """
    known = ~sn.unknown
    return known if known.any() else np.ones(len(known), dtype=bool)


def group_x(sn: StarNoise, kind: str) -> np.ndarray:
    """Each star's value of the grouping variable ``kind`` (magnitude: NaN at the median)."""
    if kind == "magnitude":
        mag = sn.magnitude
        fin = np.isfinite(mag)
        return np.nan_to_num(mag, nan=float(np.median(mag[fin])) if fin.any() else 0.0)
    if kind == "radius":
        return sn.radius
    return sn.uv[:, ("column", "row").index(kind)]


def group_index(sn: StarNoise, group: dict[str, Any]) -> np.ndarray:
    """Each star's index in the grouping ``group`` (a :func:`star_groups` entry)."""
    return np.searchsorted(np.asarray(group["edges"], dtype=float), group_x(sn, group["by"]),
                           side="right")


#: the messages' σ is a step function of a grouping's variable when, in its order, it
#: changes at most this many times (more: it varies star by star, no edge of its own)
STATED_STEPS = GROUP_BINS - 1
#: a σ field that varies along the variable steps where ``ln σ`` between neighbouring
#: values jumps by more than this beyond the field's local slope (:func:`_trend_steps`;
#: a tracker's noise table 2x off from 5 mag on: 0.69) ...
JUMP_LN = 0.2
#: ... in a field that follows its trend: the robust SD of those residuals below
#: ``JUMP_LN / JUMP_Z`` (above, the σ varies star by star along the variable and has no
#: edge of its own: a per-star random ±20 % in the messages' σ, robust SD 0.16; a σ per
#: magnitude seen along a column, 0.67, where a slope of a few random neighbours times a
#: wide gap read 3-4)
JUMP_Z = 5.0
#: the local slope of ``ln σ`` at a gap: the median over this many gaps each side
JUMP_HALF = 5


def _stated_steps(sn: StarNoise, x: np.ndarray, use: np.ndarray) -> np.ndarray:
    """Where the messages' σ steps along ``x`` (midpoints), if it is a few steps of it."""
    if sn.stated_px is None:
        return np.empty(0)
    # (and of the σ the run used: the messages' times the scales applied, whose groups kept
    # from an earlier round step too; where the messages' σ is 0 it is not a step of theirs)
    used = np.where(sn.stated_px > 0, sn.sigma_px, sn.stated_px)
    ok = use & np.isfinite(x) & np.isfinite(used) & (used > 0)
    if ok.sum() < 2:
        return np.empty(0)
    order = np.argsort(x[ok], kind="stable")
    xs, ss, ms = x[ok][order], used[ok][order], sn.stated_px[ok][order]

    def changes(a: np.ndarray) -> np.ndarray:
        return np.abs(np.diff(a)) > 0.01 * np.minimum(a[1:], a[:-1])

    def steps(change: np.ndarray) -> np.ndarray:
        if not 0 < len(change) <= STATED_STEPS or np.any(xs[change + 1] <= xs[change]):
            return np.empty(0)  # constant, star by star, or two σ at one value of x
        return 0.5 * (xs[change] + xs[change + 1])

    both = steps(np.flatnonzero(changes(ss) | changes(ms)))
    own = np.flatnonzero(changes(ms))
    if len(both) or not len(own):  # (a few steps, or the messages' σ constant along x)
        return both
    # (the σ used varies star by star along x where it holds another variable's groups,
    # kept from an earlier round: the messages' own steps are still edges; their loss
    # put the faint stars of 4.5-4.56 mag, stated 2x, in the bright group of a magnitude
    # grouping under kept column groups)
    if not np.all(ss == ms) and len(steps(own)):
        return steps(own)
    # (a field that varies along x, a σ per magnitude, and jumps where its table is
    # wrong: the jumps of the messages' σ from its own trend; unseen case magfield_faint,
    # right below 5 mag and half the truth from 5 on: the edge was a quantile's, 5.18,
    # and the 5.0-5.18 stars' true x2 was read as per-star spread)
    return _trend_steps(xs, ms)


def _trend_steps(x: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Where a σ field that varies along sorted ``x`` jumps from its own trend (midpoints).

    At each distinct ``x`` the mean ``ln σ``; between neighbours its change ``d`` less
    the local slope's ``b Δx`` (``b`` = the median ``d`` over the median ``Δx`` of the
    :data:`JUMP_HALF` gaps each side: a smooth field's change, which a jump beside it does
    not move).  Where the residuals' robust SD (over the gaps where ``ln σ`` moves by
    over 1 % and less than a jump) is below ``JUMP_LN / JUMP_Z`` the field follows its
    trend, and a jump is a residual above :data:`JUMP_LN` whose level holds on (the
    medians of up to three values each side, taken along the slope, differ by half of it
    the same way: one star's outlying σ is no edge); at most :data:`STATED_STEPS` of
    them, else none (the σ varies star by star).
    """
    ux, k = np.unique(x, return_inverse=True)
    if len(ux) < 4:
        return np.empty(0)
    k = k.reshape(-1)
    y = np.bincount(k, np.log(sigma)) / np.bincount(k)
    d, dx = np.diff(y), np.diff(ux)
    n, h = len(d), JUMP_HALF
    win = np.lib.stride_tricks.sliding_window_view(
        np.pad(np.arange(n), h, constant_values=-1), 2 * h + 1)
    have = win >= 0
    b = (np.nanmedian(np.where(have, d[win], np.nan), axis=1)
         / np.nanmedian(np.where(have, dx[win], np.nan), axis=1))
    r = d - b * dx
    # (the residuals' scatter where ln σ moves: rows of one star side by side along a
    # column repeat its σ, and their zeros made any two stars' difference a jump; and
    # without the candidate jumps themselves: on a dense gentle field the trend moves ln σ
    # by under 1 % a gap, so only the jumps were left, and two opposite ones read as a
    # field without trend, one or two alike as one of no scatter, reviewer RE)
    moving = r[(np.abs(d) > 0.01) & (np.abs(r) <= JUMP_LN)]
    if not np.any(np.abs(d) > 0.01):
        return np.empty(0)  # (ln σ constant)
    if len(moving) and 1.4826 * float(np.median(np.abs(moving - np.median(moving)))) \
            > JUMP_LN / JUMP_Z:
        return np.empty(0)  # (no trend: star by star)
    jump = np.flatnonzero(np.abs(r) > JUMP_LN)
    mid = 0.5 * (ux[:-1] + ux[1:])

    def level(i: int) -> float:  # the medians each side of gap i, along its slope
        at = y + b[i] * (mid[i] - ux)
        return float(np.median(at[i + 1:i + 4]) - np.median(at[max(i - 2, 0):i + 1]))

    held = [i for i in jump if level(i) * np.sign(r[i]) >= 0.5 * abs(r[i])]
    if not 0 < len(held) <= STATED_STEPS:
        return np.empty(0)
    return mid[np.asarray(held)]


def star_groups(sn: StarNoise, size: tuple[int, int] | None = None,
                use: np.ndarray | None = None, kept: NoiseScales | None = None,
                stars: bool = False) -> list[dict[str, Any]]:
    """The magnitude, radius, column and row groupings: per group scale ± σ, Bartlett's p.

    ``size``: the detector's (width, height) px (no column / row groups without it).  The
    test is Bartlett's over :data:`GROUP_BINS` fine bins; the groups reported (and applied)
    are those bins with agreeing neighbours merged.  ``use``: the stars grouped (default
    all; the diagnosis passes the stars of stated σ, :func:`~.noise.judge_stars`).

    ``kept``: the scales the run used.  Where they hold groups, a grouping of another
    variable is measured of the σ before the kept factors (each star's ``q`` times its
    kept factor squared: its scale of the messages' σ times ``kept.star``), since it
    replaces them (one variable at a time); measured of the σ used, its bins each mixed
    stars the kept factors set apart and had to be folded (a column grouping x1 / x0.6 kept
    under a magnitude one: faint bins split by their stars' columns, x0.458-0.542 for 0.5,
    the z of 66 bins over seeds 4-15 of SD 1.29).  The kept variable's own grouping stays
    of the σ used (its factors compose, :meth:`NoiseScales.times_groups`).

    ``stars``: the groups merged and their σ with the stars as units (the stated σ wrong
    star by star, :func:`~.noise.judge_stars`; Bartlett's p stays the rows').
    """
    use = np.ones(len(sn.q), dtype=bool) if use is None else np.asarray(use, dtype=bool)
    if kept is not None and kept.group_by:
        f = np.asarray(kept.factors, dtype=float)[np.searchsorted(
            np.asarray(kept.edges, dtype=float), group_x(sn, kept.group_by), side="right")]
        f = np.where(~sn.unknown | (kept.unknown_sigma_px <= 0), f, 1.0)
        before = dataclasses.replace(sn, q=sn.q * f**2, log_variance=None, groups_made=None)
    else:
        before = sn
    out = []
    q = np.linspace(0, 1, GROUP_BINS + 1)[1:-1]
    mag = sn.magnitude
    fin = np.isfinite(mag) & use
    if fin.sum() > 40 and np.ptp(mag[fin]) > 0:
        out.append(("magnitude", np.unique(np.quantile(mag[fin], q)), group_x(sn, "magnitude")))
    rad = sn.radius[use]
    if len(rad) > 40 and np.ptp(rad) > 0:  # quantiles: the corners are sparse
        out.append(("radius", np.unique(np.quantile(rad, q)), sn.radius))
    if size is not None and sn.uv is not None:
        for k, kind in enumerate(("column", "row")):
            out.append((kind, q * size[k], sn.uv[:, k]))
    # where the messages' σ steps along a grouping's variable (a tracker that states one σ
    # for bright stars and another for faint ones), its step is an edge too: a bin across
    # it mixed right and wrong messages under one factor (unseen case mag_faint_over2:
    # stated 0.05 px below 4.5 mag, 0.1 above, edges 4.02 and 4.8, the middle group
    # x0.732 for stars truly x1 and x0.5, and a false "heavy-tailed" line)
    out = [(kind, edges, x, _stated_steps(sn, x, use)) for kind, edges, x in out]
    result = []
    for kind, edges, x, steps in out:
        edges = np.unique(np.concatenate([edges, steps]))
        # (stars outside ``use`` in no group: index -1)
        gidx = np.where(use, np.searchsorted(edges, x, side="right"), -1)
        # (the kept variable's own grouping of the σ used, another's of the σ before)
        src = sn if kept is None or kind == kept.group_by else before
        # (beside the noise's time trend within the bins, where it has one)
        src = beside_time(src, use, gidx)
        stat, p = _bartlett(_bins(src, gidx, len(edges) + 1))
        fine = edges
        entry: dict[str, Any] = {}
        if kept is not None and kept.group_by and kind == kept.group_by:
            # the kept variable's grouping of the σ before the kept factors too: what the
            # other groupings are measured of, the rank :func:`significant_grouping` takes
            # (of the σ used, the kept factors right, it is flat: unseen case bright_quant,
            # magnitude groups kept x3.1 / x1.0, their p 0.12 beside the rows' 1e-161 of
            # the σ before, which held the bright stars' excess wherever they sat: "the
            # stars' sigma depends on row" replaced the magnitude groups)
            b_src = beside_time(before, use, gidx)
            entry["p_before"] = _bartlett(_bins(b_src, gidx, len(edges) + 1))[1]
        edges, gidx, parts = _merge(src, gidx, edges, use, steps, stars)
        # (a grouping that may be applied: its edges placed; not the kept variable's own,
        # of the σ used, whose factors already split it: test_noise_unknown's kept columns;
        # nor one beside a per-star verdict, measured with the stars as units: the rows'
        # likelihood reads each star's own level as a step there, a region's 640 px edge
        # moved to 524-638 px: test_noise's per-star groups)
        if p < ALPHA and len(edges) and (kept is None or kind != kept.group_by) and not stars:
            moved = _placed(src, x, use, edges, fine, steps)
            if not np.array_equal(moved, edges):  # (and groups now alike merged)
                gidx = np.where(use, np.searchsorted(moved, x, side="right"), -1)
                edges, gidx, parts = _merge(src, gidx, moved, use, steps, stars)
        result.append({"by": kind, "edges": [float(e) for e in edges],
                       "scales": [s for s, _, _ in parts], "sigma": [e for _, e, _ in parts],
                       "dof": [d for _, _, d in parts], "statistic": stat, "p_value": p,
                       **entry})
    return result


def _placed(sn: StarNoise, x: np.ndarray, use: np.ndarray, edges: np.ndarray,
            fine: np.ndarray, steps: np.ndarray | None = None) -> np.ndarray:
    """``edges`` each moved to where the σ steps within the fine bins beside it.

    The bins are quantiles (:data:`GROUP_BINS`): a step of the noise inside a bin is merged
    to one side at a quantile's edge (unseen case ``mag2x``: faint stars from 4.5 mag 2x,
    grouped at 4.02 mag, its 4.0-4.5 stars x1 in the x1.96 group, read as "wrong star by
    star ~10 % at random within the magnitude groups").  Each edge (not a step of the
    messages' σ, ``steps``) is moved to the split within the two ``fine`` bins beside it
    (the test's) where the two groups it parts (between the edges beside it) fit best
    (Gaussian likelihood: the least ``Σ m ln(Σ q / Σ m)`` over both), each at least half a
    bin of the rows' ``m``.  (Between the edges beside it, a region's second
    edge went to the split chance made most different, 3.4σ, and was not merged.)  The test's
    bins and p are unchanged: the edges are where its groups are reported and applied.
    """
    x = np.asarray(x, dtype=float)
    ok = np.asarray(use, dtype=bool) & np.isfinite(x) & (sn.m > 0) & np.isfinite(sn.q)
    least = 0.5 * float(sn.m[ok].sum()) / GROUP_BINS
    out = np.array(edges, dtype=float)
    for k in range(len(out)):
        if steps is not None and np.isin(out[k], steps):
            continue
        below, above = fine[fine < out[k]], fine[fine > out[k]]
        lo = out[k - 1] if k else -math.inf
        hi = out[k + 1] if k + 1 < len(out) else math.inf
        inside = ok & (x >= lo) & (x < hi)  # (the two groups it parts: their likelihood)
        order = np.argsort(x[inside], kind="stable")
        xs = x[inside][order]
        if len(xs) < 2:
            continue
        cq, cm = np.cumsum(sn.q[inside][order]), np.cumsum(sn.m[inside][order])
        i = np.flatnonzero(np.diff(xs) > 0)
        # (a split within the test's two bins beside the edge)
        i = i[(xs[i] >= (below[-1] if len(below) else -math.inf))
              & (xs[i + 1] <= (above[0] if len(above) else math.inf))]
        qa, ma = cq[i], cm[i]
        qb, mb = cq[-1] - qa, cm[-1] - ma
        fit = (ma >= least) & (mb >= least) & (qa > 0) & (qb > 0)
        if not fit.any():
            continue
        with np.errstate(divide="ignore", invalid="ignore"):
            cost = np.where(fit, ma * np.log(qa / ma) + mb * np.log(qb / mb), np.inf)
        j = i[int(np.argmin(cost))]
        out[k] = 0.5 * (xs[j] + xs[j + 1])
    return out


#: :func:`beside_time`'s passes between the bins' levels and the time trend (a joint fit,
#: alternating), at most; done when the trend moves by less than :data:`TREND_TOL`.  Slow
#: where the bins follow time (columns drifting 600 px over the run, ±150 about it: 8
#: passes left column groups x1.50 / x1.58 at p 2e-7, ~30 converge)
TREND_PASSES = 60
TREND_TOL = 1e-4


def beside_time(sn: StarNoise, use: np.ndarray | None = None,
                gidx: np.ndarray | None = None) -> StarNoise:
    """``sn`` with each row's ``q`` over the stars' noise's time trend beside the bins ``gidx``.

    A noise that grows over the run (a detector warming, unseen case ``noise_ramp``: σ
    x1.5 -> x2 across the evaluation window) reads as groups of whatever the stars in view
    share as the attitude changes with time: column groups x1.59-1.82 at p 4e-7 (seed
    22), radius ones (seed 24), applied.  The rows' ``z = q / m`` over their bin's level
    (``gidx``, each row's bin, -1 outside; default one bin) change with time by a material
    ratio (:func:`~.stats.time_trend`, on the rows ``use``) and significantly
    (:func:`~.stats.frame_robust_t` against the time's normal scores, clustered by frame,
    below :data:`ALPHA`): the bins' levels and the trend are then fitted jointly
    (alternating, :data:`TREND_PASSES`) and the grouping is tested on ``q`` over the trend
    (the overall scale kept).  Beside the bins, not before them: a real grouping whose
    stars' share changes with time (unseen case ``magfield_faint``, faint stars 2x) makes
    a trend of the rows alone, which divided out moved its edge (an extra group 5-5.18 mag
    x1.78).  ``sn`` itself where there is no such trend (the same numbers bit for bit).
    What changes over the run is said by :func:`~.noise.changes_over_run`.
    """
    from stellar_cal_ros.diagnosis.stats import frame_robust_t, normal_scores, time_trend

    if sn.t is None or sn.frame is None:
        return sn
    ok = (sn.m > 0) & np.isfinite(sn.q) & np.isfinite(sn.t)
    if use is not None:
        ok &= np.asarray(use, dtype=bool)
    g = np.zeros(len(sn.q), dtype=np.int64) if gidx is None else np.asarray(gidx)
    ok &= g >= 0
    if ok.sum() < 20 or np.ptp(sn.t[ok]) == 0:
        return sn
    gk = np.where(ok, g, 0)
    z = sn.q / np.where(sn.m > 0, sn.m, 1.0)

    def levels(f: np.ndarray) -> np.ndarray:
        lv = np.bincount(gk[ok], (sn.q / f)[ok]) / np.maximum(np.bincount(gk[ok], sn.m[ok]),
                                                              1e-300)
        return np.where(lv > 0, lv, 1.0)[gk]

    within = z / levels(np.ones(len(z)))
    f = time_trend(sn.t, within, sn.m, ok)
    if f is None or not frame_robust_t(normal_scores(sn.t[ok]), within[ok],
                                       sn.frame[ok])[1] < ALPHA:
        return sn
    for _ in range(TREND_PASSES):
        last, f = f, time_trend(sn.t, z / levels(f), sn.m, ok)
        if f is None:  # (no material trend beside the bins' levels)
            return sn
        if float(np.max(np.abs(f[ok] / last[ok] - 1.0))) < TREND_TOL:
            break
    f = f * float(np.sum((sn.q / f)[ok])) / float(np.sum(sn.q[ok]))  # (Σ q kept)
    return dataclasses.replace(sn, q=sn.q / f, log_variance=None, groups_made=None)


# ----------------------------------------------------------------------------- a run's stars


# ----------------------------------------------------------------------------- star by star
def star_spread(sn: StarNoise, use: np.ndarray | None = None,
                gidx: np.ndarray | None = None) -> dict[str, float] | None:
    """Whether the σ the run used is wrong star by star: each star's own variance.

    A tracker whose σ field is off by a factor of each star's own (a per-star PSF or
    background estimate, right on average) makes every star's whitened residual variance
    its own factor², around the one scale.  The stars' tracks then carry that variance
    wherever they are seen, and a test that takes the rows (or the frames) as independent
    reads it as groups (unseen case ``sigma_per_star``, 30 % lognormal factors: "x0.889 ..
    x1.2 by magnitude", at random) and as a spread that changes with whatever the stars in
    view share (time, temperature, gravity: 'unexplained' lines at t ~ 6).

    The test: one-way ANOVA of the rows' ``z = q / m`` (each ``E z = s²``) on the stars,
    about their frame's mean (a variance that changes with time, temperature or anything
    else a frame carries is no per-star one: unseen case ``step2x``) and, with ``gidx``
    (each row's group), about its group's mean of the stars (the groups' own steps are
    theirs).  The frames and the stars are a two-way layout: ``B`` the stars' mean square
    adjusted for the frames (beyond the groups': :func:`_adjusted_ss`), ``W`` the rows'
    residual one (times :meth:`StarNoise.inflation` where the tracks are correlated), ``F
    = B / W`` on their ranks' dof.  Returns ``{F, p_value, stars, rows, spread, tau2,
    mean}``: ``spread`` the SD across the stars of their variance factor over its mean
    beyond the rows' noise (method of moments, ``τ² = (B − W) / n₀``, ``n₀`` the stars'
    information per dof), or None where there is nothing to test.
    """
    if sn.star is None or sn.frame is None:
        return None
    use = np.ones(len(sn.q), dtype=bool) if use is None else np.asarray(use, dtype=bool)
    ok = use & (sn.m > 0) & np.isfinite(sn.q)
    if gidx is not None:
        ok &= np.asarray(gidx) >= 0
    z = sn.q[ok] / sn.m[ok]
    _, fk = np.unique(sn.frame[ok], return_inverse=True)
    nf = np.bincount(fk)
    keep = nf[fk] > 1  # a frame of one star has no within-frame variance to tell
    # (a star whose track crosses groups, radius or position ones, is one unit per group)
    gr = np.zeros(int(keep.sum()), dtype=np.int64) if gidx is None else \
        np.unique(np.asarray(gidx)[ok][keep], return_inverse=True)[1]
    z = z[keep]
    if not len(z):  # no frame with two tested stars (one stated star beside σ-0 ones)
        return None
    fk = np.unique(fk[keep], return_inverse=True)[1].reshape(-1)
    nf = np.bincount(fk)
    # (where the stars' σ grows with their image's speed, each row over the variance its
    # speed gives first, :func:`speed_variance`: within a frame in a roll the stars far
    # from its axis move faster, which no frame's level takes; unseen case ``rate_noise``
    # s21 read "wrong star by star ~6 %, F 1.77, p 0.0021" after the frames' levels)
    sp = speed_variance(sn, ok)
    if sp is not None:
        z = z / speed_levels(sp, sn.speed[ok][keep]) * float(np.mean(z))
    # (where the frames' noise differs, each row over its frame's level first,
    # noise_structure.frame_variances: a σ that grows in the slews' frames made the stars
    # seen there read as wrong star by star, unseen case ``rate_noise`` s21 ~24 %, F 10.1)
    at_frames = noise_structure.frame_variances(z, fk)
    if at_frames is not None:
        z = z / at_frames * float(np.mean(z))

    def about_frames(y: np.ndarray) -> np.ndarray:
        return y - (np.bincount(fk, y) / nf)[fk]

    # a trend of the stars' levels in magnitude (within their groups) divided out first:
    # it is the σ's magnitude dependence the groups step through, not a per-star error
    # (unseen case mag_inverted: "wrong star by star ~11 % at random ... not a trend in
    # magnitude" for a σ field whose magnitude dependence is upside down)
    z_raw = z
    trend = _magnitude_trend(z, fk, gr, np.asarray(sn.star)[ok][keep],
                             group_x(sn, "magnitude")[ok][keep])
    if trend is not None:
        z = z / trend[0]
    # each group's level divided out before the frames' means (a frame's mean of bright
    # stars at x1 and faint ones at x0.25 lent each star its frames' mix: unseen case
    # mag_faint_over2 read "wrong star by star" within its two groups)
    lvl = np.bincount(gr, z) / np.bincount(gr)
    r = about_frames(z / lvl[gr]) * float(np.mean(z))
    N = len(r)
    _, sk = np.unique(np.stack([gr, np.asarray(sn.star)[ok][keep]]), axis=1,
                      return_inverse=True)
    sk = sk.reshape(-1)
    ns = np.bincount(sk).astype(float)
    S = len(ns)
    g = gr[np.unique(sk, return_index=True)[1]]
    G = int(g.max()) + 1 if S else 0
    if S - G < 2:
        return None
    # the stars' effects beyond the frames' (and the groups'): a two-way layout, frames x
    # stars, whose stars' sum of squares is adjusted for the frames (each star's rows
    # about their frames' means share those means with the other stars in view: with few
    # stars a frame, the stated stars beside σ-0 ones, their means covary and the one-way
    # F on them fired in 7.5 % of white draws at 1 %, 4 stars in 2-4 a frame)
    ss_s, rank_s, tr_s = _adjusted_ss(r, fk, sk)
    ss_g, rank_g, _ = _adjusted_ss(r, fk, gr) if G > 1 else (0.0, 0, 0.0)
    df1, df2 = rank_s - rank_g, N - len(nf) - rank_s
    if df1 < 2 or df2 < 2:
        return None
    B = max(ss_s - ss_g, 0.0) / df1
    W = max(float(r @ r) - ss_s, 0.0) / df2 * sn.inflation(ok)
    if not W > 0:
        return None
    F = B / W
    # (τ² by the method of moments: E[B] = W + τ² tr(C) / rank, C the stars' information
    # matrix after the frames, :func:`_adjusted_ss`)
    n0 = tr_s / max(rank_s, 1)
    tau2 = max(B - W, 0.0) / n0
    mean = float(np.mean(z))
    # (the mean squares' dof over the rows' heavy tails, :func:`tail_factor`)
    k1, k2 = tail_factor(r, ns)
    out = {"F": F, "p_value": float(dist.f.sf(F, df1 / k1, df2 / k2)), "stars": S, "rows": N,
           "spread": math.sqrt(tau2) / mean if mean > 0 else math.nan, "tau2": tau2,
           "mean": mean, "groups_p": 1.0,
           "magnitude_trend": 0.0 if trend is None else trend[1]}
    z = z_raw  # (the groups' levels below: of the σ as the rows show it)
    if G > 1 and B > 0 and S > G:
        # the groups' levels against the stars' own: a one-way ANOVA of the stars' means
        # (each star once: the stars, not the rows, are the units a per-star σ error leaves
        # independent; weighted by rows, a star of many rows carried its group, column
        # groups x1.03-1.57 at p 1.8e-10 on sigma_per_star seed 22), of the rows about
        # their frames' means (not divided by their groups' levels), F(G − 1, S − G)
        raw = np.bincount(sk, about_frames(z)) / ns
        kg = np.bincount(g, minlength=G).astype(float)
        rg = np.bincount(g, raw, minlength=G) / np.maximum(kg, 1.0)
        within = float(np.sum((raw - rg[g]) ** 2)) / (S - G)
        MG = float(np.sum(kg * (rg - float(np.mean(raw))) ** 2)) / (G - 1)
        if within > 0:
            out["groups_p"] = float(dist.f.sf(MG / within, G - 1, S - G))
    return out


#: the stars' σ at the run's 95th-percentile image speed over their σ at rest that is
#: material (:func:`speed_variance`)
SPEED_RATIO = 1.0 + 2 * MATERIAL


def speed_levels(d: dict[str, float], speed: np.ndarray) -> np.ndarray:
    """The variance (of the σ used) :func:`speed_variance`'s fit ``d`` gives at ``speed``."""
    return d["alpha"] + d["beta"] * (np.asarray(speed, dtype=float) / d["v95_deg_s"]) ** 2


def speed_variance(sn: StarNoise, use: np.ndarray | None = None) -> dict[str, float] | None:
    """The stars' variance as it grows with their image's speed (smear), when it does.

    A centroid of a star that moves across the detector during the exposure is a streak's:
    its noise grows with the image's speed ``v`` (each star's own: in a roll the stars far
    from its axis move faster than those near it, so no frame's level takes it; unseen
    case ``rate_noise``, σ 0.05 √(1 + (2 v / v95)²) px, read "wrong star by star ~6 %").
    The rows' ``q`` (``E q = m σ²``, whitened by the σ used) by least squares on ``m`` and
    ``m (v / v95)²`` (``v95`` the rows' 95th-percentile speed): ``σ² = α + β (v / v95)²``
    of the σ used.  Said where the rows' ``z = q / m`` grow with ``v²``
    (:func:`~.stats.frame_robust_t`, clustered by frame, two-sided p from its Student
    reference below :data:`ALPHA`, t > 0: on the speed's normal scores the ~90 % of rows
    at rest, ranked at random, left p 0.018 where this reads t 11.7, ν 8, p 2e-6), both
    coefficients are positive and the σ at ``v95`` over the σ at rest exceeds
    :data:`SPEED_RATIO`; not where a field or a per-star error is left (as
    :func:`star_levels`).  Returns ``{alpha, beta, v95_deg_s, rest_px, rest_sigma_px,
    per_deg_s_px, per_deg_s_sigma_px, at_v95_px, ratio, t, p_value, rows}`` (px: times the
    rows' median σ used; ``σ ≈ √(rest² + (per_deg_s v)²)``; the coefficients' σ by the
    frames' sandwich times :meth:`StarNoise.inflation`), or None.
    """
    from stellar_cal_ros.diagnosis.stats import frame_robust_t

    if sn.speed is None or sn.frame is None or sn.repeat_removed or sn.structure_p < ALPHA:
        return None
    ok = (sn.m > 0) & np.isfinite(sn.q) & np.isfinite(sn.speed)
    if use is not None:
        ok &= np.asarray(use, dtype=bool)
    if ok.sum() < 40:
        return None
    v, q, m = sn.speed[ok], sn.q[ok], sn.m[ok]
    v95 = float(np.percentile(v, 95))
    if not v95 > 0:
        return None
    X = np.stack([m, m * (v / v95) ** 2], 1)
    xtx = X.T @ X
    if not abs(np.linalg.det(xtx)) > 0:
        return None
    inv = np.linalg.inv(xtx)
    alpha, beta = inv @ (X.T @ q)
    if not (alpha > 0 and beta > 0 and math.sqrt(1.0 + beta / alpha) > SPEED_RATIO):
        return None
    t, p = frame_robust_t(v**2, q / m, sn.frame[ok])[:2]
    if t is None or not (t > 0 and p < ALPHA):
        return None
    e = q - X @ np.array([alpha, beta])
    fk = np.unique(sn.frame[ok], return_inverse=True)[1].reshape(-1)
    U = np.stack([np.bincount(fk, X[:, j] * e) for j in range(2)], 1)
    cov = inv @ (U.T @ U) @ inv * sn.inflation(ok)
    px = float(np.median(sn.sigma_px[ok]))
    sa, sb = (math.sqrt(max(float(cov[j, j]), 0.0)) for j in range(2))
    return {"alpha": float(alpha), "beta": float(beta), "v95_deg_s": v95,
            "rest_px": px * math.sqrt(alpha), "rest_sigma_px": px * sa / (2 * math.sqrt(alpha)),
            "per_deg_s_px": px * math.sqrt(beta) / v95,
            "per_deg_s_sigma_px": px * sb / (2 * math.sqrt(beta)) / v95,
            "at_v95_px": px * math.sqrt(alpha + beta), "ratio": math.sqrt(1 + beta / alpha),
            "t": float(t), "p_value": float(p), "rows": int(ok.sum())}


def _magnitude_trend(z: np.ndarray, fk: np.ndarray, gr: np.ndarray, star: np.ndarray,
                     mag: np.ndarray) -> tuple[np.ndarray, float] | None:
    """A trend of the stars' variance levels in magnitude within their groups, or None.

    ``z``: the rows' ``q / m``; ``fk``, ``gr``, ``star``, ``mag``: each row's frame, group,
    star and magnitude.  Each star's level is the mean of its rows' ``z`` over their group's
    level, about their frames' means; ``ln`` of it is fitted on the star's magnitude with an
    intercept per group (weighted by the star's rows; the stars the units of its t, ``S −
    G − 1`` dof).  Where the slope is significant at :data:`ALPHA`: ``(exp(b (mag −
    mean)), b)`` per row (``b`` per magnitude, of the variance), the σ's magnitude
    dependence beyond the groups' steps that :func:`star_spread` divides out before it
    reads a per-star error (a σ stated flat or with the wrong slope in magnitude is no σ
    wrong star by star at random).
    """
    nf = np.bincount(fk)
    lvl = np.bincount(gr, z) / np.bincount(gr)
    rel = z / lvl[gr]
    rel = rel - (np.bincount(fk, rel) / nf)[fk] + 1.0
    _, sk = np.unique(np.stack([gr, star]), axis=1, return_inverse=True)
    sk = sk.reshape(-1)
    ns = np.bincount(sk).astype(float)
    lev, ms = np.bincount(sk, rel) / ns, np.bincount(sk, mag) / ns
    g = gr[np.unique(sk, return_index=True)[1]]
    ok = lev > 0
    gg = np.unique(g[ok], return_inverse=True)[1].reshape(-1)
    S, G = int(ok.sum()), int(gg.max()) + 1 if ok.any() else 0
    if S - G < 3:
        return None
    y, x, w = np.log(lev[ok]), ms[ok], ns[ok]
    sw = np.bincount(gg, w)
    xc = x - (np.bincount(gg, w * x) / sw)[gg]
    yc = y - (np.bincount(gg, w * y) / sw)[gg]
    sxx = float(np.sum(w * xc * xc))
    if not sxx > 0:
        return None
    b = float(np.sum(w * xc * yc)) / sxx
    s2 = float(np.sum(w * (yc - b * xc) ** 2)) / (S - G - 1)
    if not s2 > 0 or not 2.0 * float(dist.t.sf(abs(b) / math.sqrt(s2 / sxx), S - G - 1)) \
            < ALPHA:
        return None
    return np.exp(b * (mag - float(np.mean(mag)))), b


#: excess kurtosis of Gaussian noise's rows ``z`` (``‖r‖²`` of two axes: exponential's)
GAUSS_KURTOSIS = 6.0


def tail_factor(r: np.ndarray, ns: np.ndarray) -> tuple[float, float]:
    """How much more heavy tails make the F's two mean squares vary than Gaussian noise's.

    ``r``: the rows' ``z`` about their frames' means; ``ns``: each star's rows.  A star's
    term of the F's numerator, ``n (z̄ − μ)² / σ²`` over its ``n`` rows, has mean 1 and
    variance ``2 + κ / n``, and a row's term of the denominator ``2 + κ``, ``κ`` the rows'
    excess kurtosis (of ``z``, the squared residuals: 6, exponential's, for Gaussian
    noise; the F's reference as it stood is held for it).  Under heavy-tailed noise ``κ``
    is much larger (``z`` of Student-t noise of 4 dof has no fourth moment): the mean
    squares vary more than the χ²s of the F's reference, and the test was liberal (rows of
    a psce bag, Student-t of 4 / 3 dof: 15 / 17 of 600 draws below 1 %; unseen case
    ``sway_t4`` seed 23, "wrong star by star ~7.6 %, p = 0.0045").  Returns the ratios of
    their variances at the ``κ`` measured on ``r`` to Gaussian noise's, ``(2 + κ h) / (2 +
    6 h)`` (``h`` the stars' mean ``1 / n``) and ``(2 + κ) / 8``, at least 1 each: the
    F's numerator and denominator dof are divided by them (Satterthwaite).
    """
    c = r - float(np.mean(r))
    v = float(np.mean(c**2))
    if not v > 0:
        return 1.0, 1.0
    k = float(np.mean(c**4)) / v**2 - 3.0
    h = float(np.mean(1.0 / ns))
    return (max(1.0, (2.0 + k * h) / (2.0 + GAUSS_KURTOSIS * h)),
            max(1.0, (2.0 + k) / (2.0 + GAUSS_KURTOSIS)))


#: stars beyond this many: :func:`_adjusted_ss` solves by conjugate gradients (dense below;
#: 1 500 stars of 36 000 frames: dense 2.2 s, CG 0.19 s, the same sum of squares to 2e-16)
DENSE_STARS = 300


def _adjusted_ss(r: np.ndarray, frame: np.ndarray, label: np.ndarray
                 ) -> tuple[float, int, float]:
    """The sum of squares of ``label``'s effects after the frames', its rank and trace.

    ``r``: the rows about their frame's mean (``frame`` dense 0..F−1, ``label`` dense
    0..L−1).  The reduced normal equations of the two-way layout, ``C α = Q`` with ``C =
    diag(n_l) − N diag(1/n_f) Nᵀ`` (``N`` the label × frame counts) and ``Q`` the labels'
    sums of ``r``; the sum of squares is ``αᵀ Q`` on ``rank C = L −`` (labels' connected
    components through shared frames) dof.  Returns ``(ss, rank, trace C)``.
    """
    from scipy import sparse
    from scipy.sparse.csgraph import connected_components
    from scipy.sparse.linalg import cg

    if not len(r):
        return 0.0, 0, 0.0
    L, nF = int(label.max()) + 1, int(frame.max()) + 1
    inc = sparse.csr_matrix((np.ones(len(r)), (label, frame)), shape=(L, nF))
    nf = np.asarray(inc.sum(0)).reshape(-1)
    nl = np.asarray(inc.sum(1)).reshape(-1)
    C = sparse.diags(nl) - inc @ sparse.diags(1.0 / nf) @ inc.T
    Q = np.bincount(label, r, minlength=L)
    comps = connected_components(inc @ inc.T, directed=False)[0]
    rank = L - int(comps)
    trace = float(C.diagonal().sum())
    if rank <= 0:
        return 0.0, 0, trace
    if L <= DENSE_STARS:
        a = np.linalg.lstsq(C.toarray(), Q, rcond=None)[0]
    else:  # (C is positive semi-definite and Q in its range: CG stays in it)
        # (``rtol`` from SciPy 1.12 on, ``tol`` before: apt Jazzy's is 1.11)
        tol = "rtol" if "rtol" in inspect.signature(cg).parameters else "tol"
        a = cg(C.tocsr(), Q, atol=0.0, maxiter=10 * L, **{tol: 1e-10})[0]
    return float(a @ Q), rank, trace
