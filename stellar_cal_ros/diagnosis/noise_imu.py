"""The IMU's noise scales: maximum likelihood over re-runs, and the IMU's own samples.

Part of noise as a hypothesis (:mod:`~stellar_cal_ros.diagnosis.noise`, whose doc says
why): the gyro (accelerometer) noise scale by maximum likelihood on the stars'
innovations over re-runs of the model (:func:`search_scale`), and the white noise of the
IMU's own samples (:func:`imu_sample_scale`: second differences, a robust scale), which no
missing effect of the stars' model moves and which is therefore the check of the first.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from stellar_cal_ros.core import distributions as dist
from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.diagnosis.stats import finite_rows

#: the gyro / accelerometer scale search range (ln of the scale)
LN_RANGE = math.log(300.0)
#: log-likelihood change below which a scale search sees nothing (a third of the χ²₁ 5 %
#: half-width: over a factor of 9 of the scale the data would have moved it far more)
FLAT = 0.5


# ----------------------------------------------------------------------------- IMU (ML)
@dataclass
class ScaleSearch:
    """Maximum-likelihood search of one noise scale over re-runs."""

    name: str  #: "gyro" or "accel"
    points: dict[float, float] = field(default_factory=dict)  #: ln scale → log-likelihood
    value: float = 1.0
    sigma: float = math.nan  #: σ of the scale (delta method from σ of its log)
    statistic: float = 0.0  #: 2 (ℓ(ŝ) − ℓ(1))
    p_value: float = 1.0  #: of "as stated": the statistic over the dispersion (adjusted_p)
    measurable: bool = True  #: the likelihood has a maximum in range
    #: when it has none: "upper" (the scale is at most :attr:`value`, 95 %) or "lower"
    bound: str = ""
    #: the variance of the log-likelihood's score over its curvature, from its frames (the
    #: sandwich's factor on σ²; 1 for a likelihood whose runs gave no frames)
    dispersion: float = 1.0
    #: ln scale → the runs' log-likelihood frame by frame ``(2, frames)``, while searching
    frames: dict[float, np.ndarray] = field(default_factory=dict, repr=False)
    #: a check stopped at its first runs: the scale above fits no better than as stated
    #: (:func:`search_scale`'s ``check``; not measurable, statistic 0, p 1)
    checked: bool = False

    def fit(self) -> tuple[float, float]:
        """Vertex and curvature of the parabola through the three points nearest the best."""
        x3 = self.fit_points()
        l3 = np.array([self.points[x] for x in x3])
        xs = np.array(sorted(self.points))
        best = int(np.argmax([self.points[x] for x in xs]))
        if len(x3) < 3:
            return float(xs[best]), 0.0
        a, b, _ = np.polyfit(x3, l3, 2)
        if a >= 0:  # no interior maximum here
            return float(xs[best]), 0.0
        return float(-b / (2 * a)), float(-2 * a)

    def fit_points(self) -> list[float]:
        """The (up to) three points :meth:`fit` takes: those nearest the best, in order."""
        xs = sorted(self.points)
        best = int(np.argmax([self.points[x] for x in xs]))
        lo = min(max(best - 1, 0), max(len(xs) - 3, 0))
        return xs[lo:lo + 3]

    def sandwich(self, xs: list[float], curv: float, at: float) -> float:
        """Var(score) / curvature of the log-likelihood at ``at``, from its frames at ``xs``.

        Each frame's score at ``at`` is the slope there of the parabola through its terms at
        the three points ``xs`` (at the outermost two that ran with frames, their difference
        quotient); their variance over the frames (centred), summed, is the score's variance
        when the frames' scores are uncorrelated (measured: their lag 1-30
        autocorrelations sum to -0.04, and batch means over 10-20 blocks of the run agree,
        doc/benchmarks.md).  1 without frames (a likelihood, not a composite one).
        """
        have = [x for x in sorted(xs) if x in self.frames]
        if len(have) < 2 or not curv > 0:
            return 1.0
        if len(have) > 2:  # Lagrange: the derivative at ``at`` of the parabola through 3
            x0, x1, x2 = have[0], have[len(have) // 2], have[-1]
            have = [x0, x1, x2]
            w = [(2 * at - x1 - x2) / ((x0 - x1) * (x0 - x2)),
                 (2 * at - x0 - x2) / ((x1 - x0) * (x1 - x2)),
                 (2 * at - x0 - x1) / ((x2 - x0) * (x2 - x1))]
        else:
            w = [-1.0 / (have[1] - have[0]), 1.0 / (have[1] - have[0])]
        common = self.frames[have[0]][0]
        for x in have[1:]:
            common = np.intersect1d(common, self.frames[x][0])
        if len(common) < MIN_FRAMES:
            return 1.0
        d = np.zeros(len(common))
        for wj, x in zip(w, have, strict=True):
            f = self.frames[x]
            d += wj * f[1, np.searchsorted(f[0], common)]
        return float(len(d) * np.var(d) / curv)


def adjusted_p(statistic: float, dispersion: float) -> float:
    """The p of "as stated": the composite likelihood's ratio over its dispersion, on χ²₁.

    The stars' window log-likelihood is a composite one (:meth:`ScaleSearch.sandwich`):
    under "as stated" its ratio 2 Δℓ is ~ dispersion × χ²₁, not χ²₁ (the adjusted
    likelihood ratio of composite likelihoods, one parameter).  The dispersion divided by
    is clipped to :data:`DISPERSION_RANGE`.
    """
    lo, hi = DISPERSION_RANGE
    return float(dist.chi2.sf(statistic / min(max(dispersion, lo), hi), 1))


#: the dispersion :func:`adjusted_p` divides by is clipped to this range.  At least 1: a
#: frame's stars share one attitude error, so their score cannot vary less than their
#: curvature says (each star's own: 0.94, doc/benchmarks.md); the estimates below 1 come
#: from triples that do not straddle a maximum (an "at most" plateau: 0.00-0.06 on clean
#: 100 s bags), and dividing by them would make the p smaller than the plain ratio's (with
#: the floor the p is never below it).  At most 3: the factor's truth over seeds is 1.43 ±
#: 0.32 (psce 200 s, gyro 5x), while single 100 s bags' estimates at a maximum reach 3.3-4.0
#: (a variance over ~100 frames); a guard, which changed no decision on the measured bags
#: (doc/benchmarks.md, issue 21, H95)
DISPERSION_RANGE = (1.0, 3.0)

#: ln-scale step of :func:`search_scale` (a factor of 3)
STEP = math.log(3.0)
#: half-width (ln scale) of the runs either side of the maximum that give its curvature (a
#: factor of 1.22: about 2 of σ(ln s) where the gyro is measured well)
REFINE = 0.2
#: fewest frames two runs share for :meth:`ScaleSearch.sandwich` (below: the curvature's σ)
MIN_FRAMES = 20


def first_points(start: float = 0.0, step: float = STEP, ln_range: float = LN_RANGE
                 ) -> list[float]:
    """The ln scales :func:`search_scale` runs first (its first batch, clipped)."""
    xs = [0.0, start - step, start + step] if start else [-step, 0.0, step]
    return [float(np.clip(x, -ln_range, ln_range)) for x in xs]


def search_scale(name: str, loglik, start: float = 0.0, step: float = STEP,
                 max_runs: int = 14, known: dict[float, float] | None = None,
                 ln_range: float = LN_RANGE, lowest: float | None = None,
                 bound: bool = True, check: bool = False) -> ScaleSearch:
    """ML scale of one noise component: ``loglik([ln s, ...]) -> [ℓ, ...]`` runs a batch.

    Three points around ``start`` (ln of the scale), moved by whole steps until the best
    point is inside, then triples of runs :data:`REFINE` apart around the parabola's vertex
    until the vertex of the triple's own parabola lies inside it, and one triple a few σ
    wide around it where σ is small (:func:`_narrowed`; at most ``max_runs`` runs); σ of
    ln s from that curvature, the test of "as stated" is the likelihood ratio
    of the best point against ln s = 0 over its dispersion (:func:`adjusted_p`).  The
    scale is measured (``x s +- e``) only where the likelihood's 95 % interval closes on
    both sides of the maximum among the points (:func:`closed`; an open side is searched
    once further), else a one-sided 95 % bound is, when one side closes.
    ``known``: points already run; ``ln_range``: the search's range of ln s (either side);
    ``lowest``: the least ln s searched, if not ``-ln_range`` (a floor standing for 0: when
    it is the best of the first runs, the search stops there, not measurable).
    ``bound``: False spends no run on a bound (its crossing, an open side searched
    further): a check whose value is used only where measured (the IMU's white samples
    measured the noise; the best white scale beside a walk).
    ``check`` (with ``start`` 0): a check read only where it measures a scale above 1 (the
    IMU's white samples measured the noise and kept it: the stars asking for more is motion
    beyond it, :func:`~.noise_runs._judge`): the first batch's point above runs first (with
    ln s = 0 if not known), and where it fits no better than ln s = 0 the search stops
    there (:attr:`ScaleSearch.checked`): with the point below no better either, ln s = 0 is
    the best point, the statistic 0 and p 1; with it better, the maximum is below 1 (a
    likelihood with one maximum in ln s).  Otherwise the point below runs and the search
    goes on as without ``check``, its points the same (ties between points are resolved in
    the same order).
    """
    out = ScaleSearch(name, dict(known or {}))
    low = -ln_range if lowest is None else lowest

    def fresh(xs: list[float]) -> list[float]:
        xs = [float(np.clip(x, low, ln_range)) for x in xs]
        return [x for x in dict.fromkeys(xs) if not any(abs(x - y) < 1e-3 for y in out.points)]

    def keep(x: float, v) -> None:
        if isinstance(v, tuple):  # (ℓ, its frames)
            v, f = v
            if f is not None:
                out.frames[x] = f
        out.points[x] = float(v)

    def run(xs: list[float]) -> None:
        new = fresh(xs)
        for x, v in zip(new, loglik(new) if new else [], strict=True):
            keep(x, v)

    new = fresh(first_points(start, step, ln_range))
    if check and not start and new and max(new) > 0.0:
        # (the runs above first, in a batch of their own; kept in the first batch's order)
        up = [x for x in new if x >= 0.0]
        got = dict(zip(up, loglik(up), strict=True))
        ell = {**out.points, **{x: v[0] if isinstance(v, tuple) else v for x, v in got.items()}}
        if 0.0 in ell and not float(ell[max(up)]) > float(ell[0.0]):
            for x in up:
                keep(x, got[x])
            out.checked, out.measurable, out.sigma, out.frames = True, False, math.inf, {}
            return out
        rest = [x for x in new if x not in got]
        got.update(zip(rest, loglik(rest) if rest else [], strict=True))
        for x in new:
            keep(x, got[x])
    else:
        run(new)
    first = np.array(list(out.points.values()))
    if np.ptp(first) < FLAT:
        # the likelihood does not move over a factor of 9 of the scale: nothing to measure
        out.measurable = False
        out.sigma = math.inf
        out.frames = {}
        return out
    if lowest is not None and max(out.points, key=out.points.get) == low:
        # the least scale searched (a floor standing for 0) is the best of the first runs:
        # no maximum above it to refine (runs below it would say nothing)
        out.measurable = False
        out.value, out.sigma = float(math.exp(low)), math.inf
        out.frames = {}
        return out
    while len(out.points) < max_runs:
        xs = sorted(out.points)
        best = max(xs, key=out.points.get)
        if best == xs[0] and best > low + 1e-6:
            run([best - 2 * step])
        elif best == xs[-1] and best < ln_range - 1e-6:
            run([best + 2 * step])
        else:
            break
    x_hat, curv = out.fit()
    used = out.fit_points()
    # refine at the vertex.  The log-likelihood is far from a parabola in ln s over the
    # search's factor-of-3 steps (flat toward small scales, steep toward large): a parabola
    # through the coarse points and one run at its vertex missed the maximum by several of
    # its σ (a noise-free χ² likelihood with its maximum at x4: x2.88 +- 0.10; 5x on psce
    # seeds 3-9: 2.95-5.48 against σ ~0.45).  So a triple of runs ``REFINE`` apart is run
    # around the vertex (one batch) and its own parabola's vertex taken; outside the
    # triple, the next triple is centred there (moved at most 3 ``REFINE``); inside, that
    # parabola gives the maximum and its curvature, σ.  Where "as stated" is the best of the
    # first runs and their vertex within half a step of it, the first triple is centred on
    # it (its run is one of them: two runs).  The coarse vertex was taken there unrefined
    # (H209's "settled"), far below the maximum on a likelihood flat toward small scales: a
    # variance component 4 + s² at x1 read x0.62 +- 0.05 (test_imu_search_at_the_stated_
    # scale_...); the stars' check of a gyro whose samples measured x57 of the stated
    # (unseen case ``gyro_x57``, the model run at the samples' x57.1) printed "the stars
    # see: x0.734 +- 0.021 of it" where the likelihood's maximum is x1.015 (the vertex of
    # x1/3, x1, x3 on a likelihood steep toward large scales; doc/benchmarks.md, H248, H221)
    if max(out.points, key=out.points.get) == 0.0 and abs(x_hat) < 0.5 * step:
        x_hat = 0.0
    while len(out.points) + 3 <= max_runs and curv > 0 and \
            min(out.points) < x_hat < max(out.points):
        before = len(out.points)
        run([x_hat - REFINE, x_hat, x_hat + REFINE])
        lo, hi = x_hat - REFINE - 1e-3, x_hat + REFINE + 1e-3
        near = {x: v for x, v in out.points.items() if lo <= x <= hi}
        x_new, c_new = ScaleSearch(name, near).fit()
        if c_new > 0 and lo < x_new < hi:  # the maximum is inside: its parabola is local
            x_hat, curv, used = _narrowed(out, run, x_new, c_new,
                                          ScaleSearch(name, near).fit_points(), max_runs)
            break
        if len(out.points) == before:  # a triple run before: no progress (no cycling)
            x_hat, curv = out.fit()
            used = out.fit_points()
            break
        if c_new <= 0:  # not concave there (far from the maximum): toward its best end
            x_new = x_hat + math.copysign(3 * REFINE, max(near, key=near.get) - x_hat)
        x_hat = float(np.clip(x_new, x_hat - 3 * REFINE, x_hat + 3 * REFINE))
    else:
        x_hat, curv = out.fit()
        used = out.fit_points()
    sig_ln = 1.0 / math.sqrt(curv) if curv > 0 else math.inf
    if bound and curv > 0 and sig_ln <= math.log(3.0):
        # a side of the maximum no searched point closes (95 %) is searched once further
        for side in (-1.0, 1.0):
            if not closed(out.points, x_hat, side):
                beyond = [x for x in out.points if (x - x_hat) * side > 0]
                if beyond:
                    run([(min(beyond) if side < 0 else max(beyond)) + side * 2 * step])
    xs = sorted(out.points)
    ls = np.array([out.points[x] for x in xs])
    l_max = float(ls.max())
    out.statistic = float(max(2.0 * (l_max - out.points[0.0]), 0.0))
    # σ of ln s: the sandwich Var(score) / curvature², not 1 / curvature.  The stars'
    # log-likelihood is a composite one (each star's own NIS, while a frame's stars share
    # one attitude error): its score varies more than its curvature says, by the stars'
    # correlation within a frame (psce 200 s, gyro 5x, seeds 3-42, at the truth: Var of
    # the score over seeds / curvature 1.43 +- 0.32; per frame 1.31, per star 0.94; no
    # correlation between frames; doc/benchmarks.md, issue 21)
    # (whether there is a maximum to speak of is the likelihood's own width, as before)
    out.dispersion = out.sandwich(used, curv, x_hat)
    out.frames = {}
    out.p_value = adjusted_p(out.statistic, out.dispersion)
    inside = xs[0] < x_hat < xs[-1]
    # "x s +- e" only where the likelihood's 95 % interval closes on both sides of the
    # maximum: its parabola is the vertex's, and a likelihood flat toward small scales (a
    # gyro noise below what the stars see) that rises by a little to a maximum read "gyro
    # x5.96 +- 1.7" for a gyro as stated, the lower side open down to x0.04 (unseen case
    # sway_knock_gsf_early, seed 21: 1.15 below the maximum there, 1.04 at x1, p 0.15;
    # doc/benchmarks.md, H209): it is then a one-sided bound, below
    if curv > 0 and inside and sig_ln <= math.log(3.0) and all(
            closed(out.points, x_hat, side) for side in (-1.0, 1.0)):
        out.value = float(math.exp(x_hat))
        # (the dispersion at least 1, as the p's: a frame's stars share one attitude error,
        # so their score cannot vary less than its curvature says; one below 1 made the
        # white samples' check "x0.72 +- 0.22" narrow.  Not at most 3 as the p's: a larger
        # sandwich is the σ's, test_imu_search_sigma_is_the_sandwich_of_a_composite_...)
        out.sigma = out.value * sig_ln * math.sqrt(max(out.dispersion, DISPERSION_RANGE[0]))
        return out
    # no interior maximum closed on both sides: the likelihood rises to a plateau at one
    # end, or stays within the 95 % cut of its maximum there (e.g. a gyro noise far below
    # what the stars can see): only a one-sided 95 % bound is measurable
    out.measurable = False
    out.sigma = math.inf
    cut = l_max - CUT
    low, high = ls[0] >= cut, ls[-1] >= cut  # an end the 95 % interval reaches
    if bound and 0.0 < out.statistic and low != high:
        best = 0 if low else len(xs) - 1
        out.bound = "upper" if low else "lower"
        order = range(best, len(xs)) if best == 0 else range(best, -1, -1)
        prev = None
        for i in order:
            if ls[i] < cut and prev is not None:  # the crossing, bisected, interpolated
                a, b = _bisect_crossing(out, run, xs[prev], xs[i], cut)
                la, lb = out.points[a], out.points[b]
                f = (la - cut) / max(la - lb, 1e-300)
                out.value = float(math.exp(a + f * (b - a)))
                break
            prev = i
        else:
            out.bound = ""
    out.frames = {}  # the bisection's runs'
    return out


#: half-width of :func:`_narrowed`'s triple, in σ of ln s
NARROW = 2.0


def _narrowed(out: ScaleSearch, run, x_hat: float, curv: float, used: list[float],
              max_runs: int) -> tuple[float, float, list[float]]:
    """``(x_hat, curv, used)``: the maximum from a triple :data:`NARROW` σ apart around it.

    Where the :data:`REFINE` triple's vertex ``x_hat`` (curvature ``curv``, its points
    ``used``) has σ(ln s) below ``REFINE`` / (2 ``NARROW``): that triple spans many σ, and
    the likelihood's skew in ln s (steep toward large scales) moves its parabola's vertex
    by a part of σ.  Unseen case ``gyro_x57`` s21 (the stars' check of the samples' x57.1,
    σ(ln s) 0.015 from the curvature): the ±0.2 triple's vertex ln s 0.002, the ±0.05
    triple's 0.018 (the likelihood's maximum; the truth 0.0035); over 300-s bags seeds
    2000-2011 the check read ln s −0.025 ± 0.009 below the truth (doc/benchmarks.md, H248).
    Unchanged where the triple is no wider than that, where the runs are spent, or where
    the narrow triple's own vertex falls outside it.
    """
    h = NARROW / math.sqrt(curv)
    if not h < 0.5 * REFINE or len(out.points) + 3 > max_runs:
        return x_hat, curv, used
    run([x_hat - h, x_hat, x_hat + h])
    near = {x: v for x, v in out.points.items() if abs(x - x_hat) <= h + 1e-3}
    x_new, c_new = ScaleSearch(out.name, near).fit()
    if c_new > 0 and abs(x_new - x_hat) < h:
        return x_new, c_new, ScaleSearch(out.name, near).fit_points()
    return x_hat, curv, used


#: the log-likelihood's drop from its maximum to the edge of its 95 % interval (½ χ²₁ 95 %)
CUT = 0.5 * float(dist.chi2.isf(0.05, 1))


def closed(points: dict[float, float], x_hat: float, side: float) -> bool:
    """Whether the 95 % interval of ``points`` (ln scale → ℓ) closes on ``side`` of ``x_hat``.

    ``side``: −1 below, +1 above; closed when a point there lies :data:`CUT` below their best.
    """
    cut = max(points.values()) - CUT
    return any(v < cut for x, v in points.items() if (x - x_hat) * side > 0)


#: the bound's crossing is bisected until its bracket is this narrow (ln scale: 5 %)
CROSSING = 0.05


def _bisect_crossing(out: ScaleSearch, run, a: float, b: float, cut: float,
                     max_runs: int = 6) -> tuple[float, float]:
    """Narrow ``[a, b]`` (``ℓ(a) ≥ cut > ℓ(b)``) by runs at its midpoint; the final bracket.

    The likelihood bends sharply where it leaves its plateau, so a straight line between
    points a factor of 3-9 apart put the crossing far from it: on a likelihood flat from
    x4 up, "at least x13" for a truth of x10 (the 95 % bound held the truth in 14 % of
    draws).  Bisection brings the bracket to :data:`CROSSING`, where a line is fair.
    """
    for _ in range(max_runs):
        if abs(b - a) <= CROSSING:
            break
        mid = 0.5 * (a + b)
        run([mid])
        if mid not in out.points:
            break
        if out.points[mid] >= cut:
            a = mid
        else:
            b = mid
    return a, b


# ----------------------------------------------------------------------------- IMU (samples)
#: the samples' second differences look white when their lag-1 correlation is within this
#: of white noise's −2/3 (an IMU that low-pass filters its output has far stronger
#: correlation, and its sample-to-sample noise says nothing about its random walk)
WHITE_TOLERANCE = 0.08


#: the axes' white noise differs when the noisiest axis is this many times the quietest: the
#: estimate is then their RMS (the one scale a filter with one random walk for all axes
#: should take: it keeps the attitude's total noise), not their median (which would keep
#: the quiet axes' value and miss one axis 4x noisier: measured, unseen case ``gyro_z4``)
AXES_DIFFER = 1.25


def sample_noise(samples: np.ndarray, axes: bool = False):
    """The white noise σ of an IMU's own samples (per sample), its σ, whether they look white.

    Second differences cancel any motion smooth over two sample intervals and leave
    ``6 σ²`` of white noise; a robust scale (MAD) per axis ignores the few samples at a
    slew's corners; the axes' median is the estimate, or their RMS when they differ
    (:data:`AXES_DIFFER`).  The samples look white when the second differences' lag-1
    correlation is −2/3 ± :data:`WHITE_TOLERANCE`.  ``axes``: also return the per-axis σ.
    """
    x = np.asarray(samples, dtype=float)
    ok = finite_rows(x)
    n = int(ok.sum())
    if n < 100:
        return (math.nan, math.nan, False) + ((np.full(3, math.nan),) if axes else ())
    # axis by axis, each axis' second differences dropped before the next (a 2-h bag's
    # samples are 17 MB, an axis' temporaries 6 MB each): the numbers are the whole
    # block's, since every median and correlation is per axis
    mad, rhos = np.zeros(x.shape[1]), []
    every = bool(ok.all())
    for k in range(x.shape[1]):
        d = np.diff(x[:, k] if every else x[ok, k], n=2)
        dev = d - np.median(d)
        mad[k] = np.median(np.abs(dev)) * 1.4826 / math.sqrt(6.0)
        dc = np.clip(dev, -4 * mad[k] * math.sqrt(6), 4 * mad[k] * math.sqrt(6))
        del d, dev
        rhos.append(np.corrcoef(dc[1:], dc[:-1])[0, 1])
        del dc
    sigma = float(np.median(mad))
    if np.min(mad) > 0 and np.max(mad) > AXES_DIFFER * np.min(mad):
        sigma = float(np.sqrt(np.mean(mad**2)))
    # the MAD's relative σ for a normal sample is ~1.17/√(2N); the second differences are
    # correlated (their effective count is ~N/2.4)
    err = sigma * 1.17 / math.sqrt(2.0 * (n - 2) / 2.4 * 3)
    rho = float(np.median(rhos))
    out = (sigma, err, abs(rho + 2.0 / 3.0) < WHITE_TOLERANCE)
    return out + (mad,) if axes else out


def imu_sample_scale(data, method: str, comp: str, stated: NoiseScales
                     ) -> tuple[float, float, bool, tuple[float, ...]]:
    """(scale, σ, white, per-axis scales) of ``comp`` ("gyro" / "accel") from its samples.

    The scale is the samples' white noise over the per-sample σ the run assumes (the
    method's random walk times ``stated``'s scale, at the bag's IMU rate).  The per-axis
    scales are ``()`` unless the axes differ (:data:`AXES_DIFFER`).
    """
    from stellar_cal_ros.core.units import DEG_PER_SQRT_HOUR
    from stellar_cal_ros.methods import registry as methods

    cfg = methods.get(method).config_cls()
    dt = float(np.median(np.diff(data.imu_t))) if len(data.imu_t) > 2 else math.nan
    if comp == "gyro":
        per_sample = cfg.gyro_arw_deg_sqrth * DEG_PER_SQRT_HOUR * stated.gyro
        samples = data.imu_w
    else:
        per_sample = getattr(cfg, "accel_vrw_mps_sqrth", math.nan) / 60.0 * stated.accel
        samples = data.imu_f
    if not (dt > 0 and per_sample > 0):
        return math.nan, math.nan, False, ()
    per_sample /= math.sqrt(dt)
    sigma, err, white, mad = sample_noise(samples, axes=True)
    differ = bool(np.min(mad) > 0 and np.max(mad) > AXES_DIFFER * np.min(mad))
    return (sigma / per_sample, err / per_sample, white,
            tuple(float(m / per_sample) for m in mad) if differ else ())
