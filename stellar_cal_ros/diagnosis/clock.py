"""A frame clock that steps or drifts against the IMU: the time offset × time test.

The library's time_offset is one constant ``Δt``: the tracker's stamps late or early by a
fixed time.  A clock that steps (a resynchronisation, a driver restart) or drifts (two
free-running oscillators) against the IMU has no library name.  A model with the constant
reads the window's mean of the change (unseen case ``dt_step``, a 4-ms step at 75 % of the
run: −1.33 ms ± 0.0067, the ± that of a constant) and leaves the rest; a model without it
may lose lock (``sky_clock_drift``, 0 → 30 ms).  The remainder's sign follows each star's
motion, so no time line sees it, and the stamp-noise test (:func:`~stellar_cal_ros.
diagnosis.stats.motion_spread`) reads the filter's catch-up after the step as a noise.

A stamp late by ``δ`` moves every star by its image velocity ``u_i = J_i ω`` (px/s) times
``δ``: the offset's pattern, whose per-frame score ``g_k = Σ uᵀ S⁻¹ ν`` and information
``I_k = Σ uᵀ S⁻¹ u`` :func:`~stellar_cal_ros.diagnosis.stats.frame_offsets` gives (the
innovations, not the within-frame residuals: the pattern is a rotation, the attitude error
the frame's stars share). The test (:func:`clock_change`): the window's moving frames
(:data:`MOVING`) in :data:`SEGMENTS` consecutive parts of equal count, the offset each part
says ``d_s = Σ g / Σ I``, their covariance from the frames' scores about it (the frames the
units, neighbouring frames sharing an error: the Newey–West window of
:func:`~stellar_cal_ros.diagnosis.stats.frame_robust_t`, across the parts' borders too; and
:data:`FLOOR_S` for the filter's error along a slew, which lasts longer than that window),
and the Wald χ² of their equality with ``SEGMENTS − 1`` dof. The parts' offsets are
fitted jointly with a mount flexure's turn and the filter's catch-up on it (:data:`GRAVITY`,
one coefficient each for the run): a flexure turns the tracker as the motion turns gravity,
along the motion, and alone the parts' offsets read it as a changing clock (psce 200 s,
40″/g: χ² 142 / 5 dof; with the gravity columns 10.4, p 0.064 unadjusted, no line). A constant
offset, in the model or not, passes it where the filter leaves it alike in every part; a
stepped or drifting clock fails it. Read on the round's residuals whatever the model holds;
it joins the 'unexplained' family (Bonferroni over its tests) and is ranked with the others
by its p (not forced first: a gyro scale factor that differs between the motions reads
alike, unseen case ``gsf_asym``).

A clock that drifts (:func:`drift_fit`) is one rate: the parts' offsets fitted by a
constant, the rate times the parts' time (a model without time_offset: the remainder is
the offset) or their lag behind a constant's estimate (:func:`constant_lag`: a model with
it), and the filter's catch-up along each slew (a nuisance: the remainder shrinks along a
slew as the attitude takes it up, −1.66, −1.25, −0.91 ms on a slew at −1.8 ms).  When the
rate is 3σ from zero and leaves no change the line says the drift (``dt from A ms to B ms
over the run (rate R ± σ ppm)``; clean psce 300 s, 0 → 3 ms late: −9.11 ± 2.8 ppm for a
truth of −10.0, −0.28 → −3.01 ms); a step leaves a change (``dt_step``: 32 χ² / 3 dof).
With time_offset in the model the lag's leverage between the window's slews is small
(−9.2 ± 5.3 ppm on the same bag): the parts' line then.

A clock that steps more than once reads as a drift in the window's few slews (psce 300 s:
two, one offset each, which a ramp fits as well as a staircase; unseen case ``dt_step2``,
two 2-ms steps: −18.6 ppm with time_offset).  Where a drift is said or asked, the run's
every slew is fitted by steps and by a rate (:func:`steps_test`): each slew in
:data:`SLEW_PARTS` parts with its own catch-up, up to :data:`STEPS_MAX` steps scanned at
the borders between parts, the steps tested beside the rate (Bonferroni over the borders
scanned) and the rate beside the steps; a staircase the rate cannot follow is said as
steps (:data:`STEPS`), and no ``clock_drift`` is offered for it.

A gyro whose scale differs between the rate's signs leaves the parts' offsets changing too
(each window slew of psce turns one axis: a per-axis rate error is a per-slew offset), but
its remainder grows along the slew that carries it, where a clock's shrinks as the filter
catches up (:meth:`ClockChange.grows`): the line is then the gyro's (:data:`GROWS`), not
the clock's.

A centroid bias along each star's motion that grows as its image speed squared (a clipped
streak, outside the library) makes each part's offset the bias's share of that part's speed:
where the window's slews differ in speed the parts change slew by slew and the drift's time
column takes them (unseen case ``smear15`` s21: "the frames' clock drifts", 3.78 ± 0.89
ppm).  A time offset's shift grows with the image speed, a smear's faster, a drifting
clock's with time at any speed: where the parts change the test is made again with the
speed-squared column beside them (:data:`SMEAR_P`), and is that one where the smear is
significant there and the parts no longer change (:meth:`ClockChange.by_speed`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from itertools import combinations
from typing import Any

import numpy as np

from stellar_cal_ros.core import distributions as dist
from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.diagnosis import stats

#: consecutive parts of the window whose offsets are compared (equal frame counts)
SEGMENTS = 6
#: the frames tested move at least this share of the window's 95th percentile image speed
MOVING = 0.1
#: the 'unexplained' line's regressor begins with this (its parts' offsets follow)
CLOCK = "the frames' time offset to the IMU changes over the run"
#: the offset's spread a constant leaves between the parts (s, added in quadrature to each
#: part's σ): the filter's along-motion error, shared by a slew's frames beyond the frames'
#: lag window (clean psce 300 s, the moving frames' parts: −0.066 to 0.061 ms, ~0.03 ms
#: rms, over seeds 21-27; doc/benchmarks.md), and what a knock's catch-up leaves along a
#: slew (unseen case ``knock``: 0.1 ms)
FLOOR_S = 0.05e-3
#: a mount that bends with gravity (a turn ``c (z × g_st)``, ``g_st`` the unit gravity in
#: the tracker frame) and the filter's catch-up when gravity turns (its recent change,
#: :func:`~stellar_cal_ros.diagnosis.context.add_gravity_regressors`): fitted with the
#: parts' offsets, one coefficient each for the run. A flexure turns the tracker as the
#: motion turns gravity, so along the motion: alone, the parts' offsets read it as a
#: clock that changes (psce, 40″/g: χ² 142 / 5 dof; test_discovery_effects)
GRAVITY = (("gravity_x_st", "gravity_y_st"), ("gravity_x_st change", "gravity_y_st change"))
#: the gravity direction must change by at least this much over the frames (unit vector;
#: :data:`~stellar_cal_ros.diagnosis.flexure.MIN_GRAVITY_CHANGE`'s value) for its columns
MIN_GRAVITY_CHANGE = 0.01
#: a wobble's regressor (:func:`~stellar_cal_ros.diagnosis.stats.periodic_findings`): the
#: tracker turning against the IMU with a period, which along each star's motion reads as
#: an offset that changes (unseen case ``wobble`` s23, 0.1 px at 45 s: "the frames' clock
#: drifts ... rate 14.5 +- 1.7 ppm", no clock drifting; with it fitted: rate -6.2 +- 3.6
#: ppm, no line), and hides a clock that does drift (the same wobble beside a 0 -> 3 ms
#: drift: +4.0 +- 3.5 ppm read for -10.0; with it fitted -22.8 +- 5.0, said).  When its line
#: is found the clock test is made again with a turn about each tracker axis at its
#: period's sine and cosine fitted beside the parts' offsets, as the flexure's
#: (:func:`flexure_products`), and its line judged in the same family
WOBBLE = "time (periodic, "
#: a wobble is fitted beside the clock only when the window holds this many of its cycles
WOBBLE_CYCLES = 3.0
#: a centroid bias along each star's motion growing as its image speed squared (a clipped
#: streak, unseen cases ``smear2``, ``smear15``): where the window's slews differ in speed
#: the parts read it as offsets that change (the offset a part says is the bias's share of
#: its speed), and the drift's time column takes it (``smear15`` s21, 0.15 px: "the frames'
#: clock drifts ... rate 3.78 +- 0.89 ppm", 19.5 chi2 / 5 dof).  Where the parts change at
#: this level (the parts' or the drift's p, unadjusted) the test is made again with the
#: speed-squared column beside the parts (:func:`flexure_products`' ``smear``), and
#: :meth:`ClockChange.by_speed` decides which is said
SMEAR_P = 0.01
#: the smear's line where the clock's test is the one beside it (:meth:`ClockChange.line`;
#: "image rate", as :data:`~stellar_cal_ros.diagnosis.stats.CURVE`'s, the speed curve's)
SMEAR_LINE = "image rate squared, beside the clock's parts"
#: the drift's line, when one rate explains the parts' change (:meth:`ClockChange.drifts`)
DRIFT = "the frames' clock drifts against the IMU"
#: the drift explains the change when what it leaves of the parts' χ² has at least this p
DRIFT_REST_P = 0.01
#: the rate must be at least this many σ from zero for the drift's line
DRIFT_Z = 3.0
#: frames further apart than this many times their median spacing begin a new run of
#: moving frames (a slew), along which the filter catches up (:func:`drift_fit`)
CATCH_UP_GAP = 5.0
#: the line when the remainder grows along the slew that carries it (:meth:`ClockChange.
#: grows`): a gyro's error, not a clock's
GROWS = "the stars' remainder along their motion grows along a slew"
#: that line's component
GYRO_COMPONENT = "gyro rate"
#: library effects whose attitude error follows the body rate, as a clock's does (a rate
#: error about each axis; on psce each window slew turns one axis, so a per-axis scale is a
#: per-slew offset): a drifting clock's parts are taken up by them (unseen case
#: ``sky_clock_drift3``: gyro_scale_factor added beside time_offset).  Refused while the
#: current model's remainder is a clock's (:meth:`ClockChange.clock_like`)
RATE_ALIASES = ("gyro_scale_factor", "gyro_misalignment")
#: the 'what could still be hiding' row of a candidate :func:`refuses` (``p``: the clock
#: finding's): its MDB is a size the test would find, but this rule decides first
REFUSED_TEXT = ("refused here at any size that leaves the stars' remainder along their motion "
                "a clock's, as it is now: p = {p:.2g}, it shrinks along a slew; a gyro rate "
                "effect is added only if it changes that shape")
#: the test named by an effect offered only where a drifting clock is found
#: (:attr:`~stellar_cal_ros.effects.base.Effect.offered_on`, :meth:`ClockChange.asks_drift`)
OFFERED_ON = "clock drift"
#: the line's component (:func:`~stellar_cal_ros.diagnosis.printing.unexplained_phrase`)
COMPONENT = "time offset"
#: each slew of the whole run is cut into this many parts for the steps test (its early and
#: late frames: the filter's catch-up beside the offsets, :func:`steps_fit`)
SLEW_PARTS = 3
#: the most steps the steps test scans for (:func:`steps_fit`)
STEPS_MAX = 3
#: the line where the clock steps (:func:`steps_said`)
STEPS = "the frames' clock steps against the IMU"


@dataclasses.dataclass
class ClockChange:
    """The parts' offsets and the test of their equality (:func:`clock_change`)."""

    t0: list[float]  #: each part's first frame time (s from the run's first frame)
    t1: list[float]  #: each part's last frame time
    dt: list[float]  #: each part's offset (s, the sign of time_offset's dt: remainder)
    sigma: list[float]  #: its standard deviation from the frames' scores (s, no floor)
    chi2: float  #: Wald statistic of their equality
    dof: int  #: its degrees of freedom (parts − 1)
    p_value: float  #: unadjusted
    size_px: float  #: the change's size: the spans' offsets' range × the image speed
    speed: float  #: 95th percentile of the stars' image speed (px/s)
    #: the drift (:func:`drift_fit`): its rate (s per s, time_offset's sign) and σ, χ² (1
    #: dof) and p, the χ² it leaves (parts − 2 dof) and p, its column (``"time"``: the
    #: remainder is the offset; ``"lag"``: a constant time_offset's estimate follows it)
    drift_rate: float = math.nan
    drift_sigma: float = math.nan
    drift_chi2: float = 0.0
    drift_p: float = 1.0
    rest_chi2: float = math.nan
    rest_p: float = math.nan
    drift_form: str = ""
    drift_start: float = math.nan  #: the offset at the run's start (s; ``"time"`` only)
    #: the remainder's change along a slew (s per s of the slew, the catch-up column's
    #: coefficient in :func:`drift_fit`) and σ
    along: float = math.nan
    along_sigma: float = math.nan
    #: along the slew whose offset departs most from zero (:func:`slew_growth`): its first
    #: and last frame times, mean offset (s) and change along it (s per s) with σ
    slew: list[float] = dataclasses.field(default_factory=list)
    slew_growth: float = math.nan
    slew_growth_sigma: float = math.nan
    duration: float = math.nan  #: the run's span (s, its first to last star)
    #: the wobble's periods (s) fitted as rivals beside the parts (``periods`` of
    #: :func:`clock_change`; in the entry only when there were any)
    periods: list[float] = dataclasses.field(default_factory=list)
    #: the speed-squared smear fitted beside the parts (:data:`SMEAR_P`; in the entry only
    #: where it was): ``offset_s``, its coefficient (the offset it says at the window's 95th
    #: percentile image speed, s, time_offset's sign), ``sigma_s``, and ``fitted``: whether
    #: this test is the one beside it (:meth:`by_speed`)
    smear: dict = dataclasses.field(default_factory=dict)
    #: the steps test over the whole run (:func:`steps_test`; in the entry only where it
    #: was made): :class:`ClockSteps` as a dict
    steps: dict = dataclasses.field(default_factory=dict)

    def as_json(self) -> dict:
        """The summary's entry (``diagnosis.json`` ``clock_change``)."""
        out = dataclasses.asdict(self)
        for key in ("periods", "smear", "steps"):
            if not out[key]:
                del out[key]
        return out

    def changes(self) -> bool:
        """Whether the parts change at :data:`SMEAR_P` (theirs or the drift's p, unadjusted)."""
        return min(self.p_value, self.drift_p) < SMEAR_P

    def by_speed(self) -> bool:
        """Whether this test beside the speed-squared smear is the one said (:data:`SMEAR_P`).

        The smear's coefficient at least :data:`DRIFT_Z` σ from zero beside the parts'
        offsets (a speed dependence within the parts, which a clock does not make: a 0 → 3
        ms drift reads −1.4 to −1.7 σ, seeds 21-23, with time_offset −0.8 to −1.2 σ) and
        the parts no longer changing beside it (:meth:`changes`): a time offset's shift
        grows with the image speed, a smear's faster, a drifting clock's with time at any
        speed; where the parts still change beside it, the clock's own test stays
        (``smear15`` s21: the smear's +0.337 ± 0.076 ms at 202 px/s, 4.4 σ, the parts 2.4
        chi2 / 5 dof beside it; the truth 0.375 ms).
        """
        sm = self.smear
        return bool(sm) and abs(sm["offset_s"]) >= DRIFT_Z * sm["sigma_s"] \
            and not self.changes()

    def spans(self) -> list[tuple[float, float, float]]:
        """``(t0, t1, dt)`` of the runs of parts one offset fits, for the line.

        The parts joined where neighbours agree (their difference within 3σ, the pooled
        offset); a step leaves two runs, a drift its parts.
        """
        out: list[list[float]] = []
        for a, b, d, s in zip(self.t0, self.t1, self.dt, self.sigma, strict=True):
            w = 1.0 / (s**2 + FLOOR_S**2)
            if out:
                p = out[-1]
                if abs(d - p[2]) <= 3.0 * math.sqrt(1.0 / w + 1.0 / p[3]):
                    p[2] = (p[2] * p[3] + d * w) / (p[3] + w)
                    p[1], p[3] = b, p[3] + w
                    continue
            out.append([a, b, d, w])
        return [(a, b, d) for a, b, d, _ in out]

    def drifts(self) -> bool:
        """Whether the drift is the line: it explains the change (its χ² beyond the parts').

        The rate at least :data:`DRIFT_Z` σ from zero, and what it and the catch-up leave of
        the parts' change not significant (:data:`DRIFT_REST_P`); a lag's rate of the sign
        of the parts' mean offset (the remainder behind a constant's estimate is the rate
        times a positive lag: ``sky_clock_drift``, a model without time_offset that lost
        lock, fits the lag at +343 ppm for a truth of −100, its parts −16.8 … +1.1 ms).
        """
        if self.drift_form == "lag" and self.drift_rate * float(np.mean(self.dt)) <= 0:
            return False
        return (abs(self.drift_rate) >= DRIFT_Z * self.drift_sigma
                and np.isfinite(self.rest_p) and self.rest_p >= DRIFT_REST_P)

    def asks_drift(self, alpha: float) -> bool:
        """Whether a drifting clock is worth a candidate (the library's ``clock_drift``).

        The parts' change (or the drift) significant at ``alpha``, and one rate leaving
        nothing significant of it (what it and the catch-up leave at :data:`DRIFT_REST_P`),
        whatever the rate's size or, for a lag, its sign: the candidate's run over the whole
        bag says the rate, the window's moving parts only that one fits.  A model that lost
        lock on a drifting clock fits the lag's rate of the wrong sign (``sky_clock_drift``:
        +343 ppm for a truth of −100, 8.2 chi2 / 3 dof left, p 0.04); a 0 → 3 ms drift
        beside time_offset changes the parts (p 0.0016) with a rate of 1.6 σ only
        (``sky_clock_drift3``: −8.6 ± 5.5 ppm, 1.7 chi2 / 3 dof left).  A clock that steps
        leaves the rate a remainder (``dt_step``: 31.7 chi2 / 3 dof, p 6e-7): the step is
        outside the library, and a rate would only stand in for it.
        """
        return (min(self.p_value, self.drift_p) < alpha
                and np.isfinite(self.rest_p) and self.rest_p >= DRIFT_REST_P)

    def grows(self) -> bool:
        """Whether the remainder grows along the slew that carries it (a gyro's error).

        A clock's remainder shrinks along a slew as the filter catches up (``dt_step``:
        −3.25, −2.26, −1.83 ms); a gyro's rate error turns the attitude by the angle turned,
        and its remainder grows (``gsf_asym``: 0.89, 2.20, 2.68 ms on the z slew, ~0 on the
        y slew).  The change along that slew of the same sign as its mean offset, at least
        :data:`DRIFT_Z` σ.
        """
        if len(self.slew) < 3 or not np.isfinite(self.slew_growth_sigma):
            return False
        return (self.slew_growth * self.slew[2] > 0
                and abs(self.slew_growth) >= DRIFT_Z * self.slew_growth_sigma)

    def shrinks(self) -> bool:
        """Whether the remainder shrinks along the slew that carries it (a clock's catch-up).

        The change along that slew of the sign opposite to its mean offset, at least
        :data:`DRIFT_Z` σ (``dt_step``: +0.58 ± 0.08 ms/s at −2.08 ms; a 0 → 3 ms drift:
        +0.29 ± 0.05 ms/s at −0.71 ms): the filter's attitude takes up a clock's offset
        along a slew, where a gyro's rate error grows with the angle turned.
        """
        if len(self.slew) < 3 or not np.isfinite(self.slew_growth_sigma):
            return False
        return (self.slew_growth * self.slew[2] < 0
                and abs(self.slew_growth) >= DRIFT_Z * self.slew_growth_sigma)

    def clock_like(self, alpha: float) -> bool:
        """Whether the parts' change is a clock's: significant at ``alpha`` and shrinking.

        The finding's p (the parts' or the drift's) below ``alpha``, and the remainder
        shrinking along its slew (:meth:`shrinks`), not growing (:meth:`grows`).
        """
        return self.finding().p_value < alpha and self.shrinks() and not self.grows()

    def steps_line(self) -> bool:
        """Whether the line is the steps' (:func:`steps_test` made and said, not a gyro's)."""
        return bool(self.steps.get("said")) and not self.grows()

    def regressor(self) -> str:
        """The line's regressor: the offsets' spans (ms, s), the drift's rate, or the steps."""
        if self.steps_line():
            st = self.steps
            each = ", ".join(f"by {d * 1e3:.3g} +- {e * 1e3:.2g} ms between {a:.0f} and "
                             f"{b:.0f} s" for d, e, (a, b) in zip(st["size_s"], st["sigma_s"],
                                                                  st["between"], strict=True))
            n = len(st["size_s"])
            return (f"{STEPS}: dt changes {each} ({n} step{'s' if n > 1 else ''} over the "
                    f"run's {len(st['dt'])} parts of its slews' moving frames, "
                    f"{st['rest_chi2']:.1f} chi2 / {st['rest_dof']} dof left; beside one "
                    f"rate the steps take {st['steps_chi2']:.0f} chi2 / {n} dof (p "
                    f"{st['steps_p']:.2g} over the {st['scanned']} borders scanned), the rate "
                    f"beside them {st['rate_chi2']:.1f} chi2 / 1 dof: not a drift; outside the "
                    "library: its time_offset is constant)")
        if self.grows():
            a, b, m = self.slew[:3]
            return (f"{GROWS}: {m * 1e3:.3g} ms over {a:.0f}-{b:.0f} s, changing by "
                    f"{self.slew_growth * 1e3:.3g} +- {self.slew_growth_sigma * 1e3:.2g} ms "
                    "per s along it (a clock's remainder shrinks along a slew as the filter "
                    "catches up; a gyro's rate error grows with the angle turned: e.g. a gyro "
                    "scale that differs between the rate's signs, outside the library; "
                    f"{self.chi2:.0f} chi2 / {self.dof} dof over {len(self.dt)} parts of the "
                    "moving frames)")
        if self.drifts():
            how = ("the stars' remainder along their motion grows with the time since a "
                   "constant time_offset's estimate learned" if self.drift_form == "lag"
                   else "the offset the stars say along their motion changes with time")
            change = self.drift_rate * self.duration
            span = (f"dt from {self.drift_start * 1e3:.3g} ms to "
                    f"{(self.drift_start + change) * 1e3:.3g} ms" if np.isfinite(self.drift_start)
                    else f"dt changes by {change * 1e3:.3g} ms")
            return (f"{DRIFT}: {span} over the run's {self.duration:.0f} s (rate "
                    f"{self.drift_rate * 1e6:.3g} "
                    f"+- {self.drift_sigma * 1e6:.2g} ppm; {how}; {self.drift_chi2:.0f} chi2 / "
                    f"1 dof, {self.rest_chi2:.1f} chi2 / {self.dof - 2} dof left over "
                    f"{len(self.dt)} parts of the moving frames; a constant time_offset "
                    "cannot follow it: the library's clock_drift models it)")
        parts = ", ".join(f"{d * 1e3:.3g} ms over {a:.0f}-{b:.0f} s"
                          for a, b, d in self.spans())
        return (f"{CLOCK}: dt {parts} (outside the library: its time_offset is constant; "
                f"{self.chi2:.0f} chi2 / {self.dof} dof over {len(self.dt)} parts of the "
                "moving frames; a gyro scale error that differs between the motions reads "
                "alike)")

    def finding(self) -> stats.RegressorFinding:
        """The 'unexplained' test (its statistic the one-sided p's normal score).

        Its p: the parts' equality's or the drift's, the smaller, × 2 (both asked; the
        drift's the better of its two columns, × 2 too).
        """
        p = min(1.0, 2.0 * min(self.p_value, 2.0 * self.drift_p))
        size = (abs(self.drift_rate) * (max(self.t1) - min(self.t0)) * self.speed
                if self.drifts() else self.size_px)
        if self.steps_line():
            size = abs(sum(self.steps["size_s"])) * self.speed
        return stats.p_finding(self.regressor(),
                               GYRO_COMPONENT if self.grows() else COMPONENT, p, size,
                               detail={"clock_change": self.as_json()})


    def line(self) -> stats.RegressorFinding:
        """The 'unexplained' line: :meth:`finding`, or the smear's (:meth:`by_speed`).

        Where this test is the one beside the smear the parts no longer change and the
        clock says nothing, but the smear's coefficient is what the window's stars say
        (unseen case ``smear15`` s21: +0.337 ± 0.076 ms at 202 px/s, the truth 0.375; no
        line at all before, the speed curve's own test lacking the power at 300 s):
        :data:`SMEAR_LINE`, its p the coefficient's two-sided normal p × 2 (the parts'
        test asked as well), its size the shift at the window's 95th-percentile image
        speed.
        """
        sm = self.smear
        if not (sm and sm.get("fitted") and self.by_speed()):
            return self.finding()
        off, sig = sm["offset_s"], sm["sigma_s"]
        p = min(1.0, 4.0 * float(dist.norm.sf(abs(off) / sig)))
        where = "ahead of" if off > 0 else "behind"
        text = (f"{SMEAR_LINE}: the centroids sit {abs(off) * 1e3:.3g} +- {sig * 1e3:.2g} ms of "
                f"the image's motion {where} the stamp's position at {self.speed:.0f} px/s (the "
                "95th-percentile image speed), growing with the speed squared: a smear (e.g. "
                "a clipped streak; not in the library), not the clock (beside it the parts' "
                f"offsets are equal: {self.chi2:.1f} chi2 / {self.dof} dof over "
                f"{len(self.dt)} parts of the moving frames)")
        return stats.p_finding(text, stats.CURVE_COMPONENT, p, abs(off) * self.speed,
                               detail={"clock_change": self.as_json()})


def refuses(effect: str, test: ClockChange | None | bool, alpha: float) -> bool:
    """Whether discover refuses candidate ``effect``, whatever its test says, beside ``test``.

    A rate-shaped candidate (:data:`RATE_ALIASES`) is never added while ``test`` (the
    current model's clock test, or ``None``/``False`` when none was made or could be) says
    the stars' remainder along their motion is a clock's (:meth:`ClockChange.clock_like`):
    it would take the clock's remainder up slew by slew.  The rule of
    :func:`~stellar_cal_ros.diagnosis.auto._top`, and of the hiding rows it marks
    (:func:`refused_entry`, :func:`~stellar_cal_ros.diagnosis.auto._refused_rows`).  It
    holds at any size only while the effect leaves that remainder clock-shaped: on
    ``dt_step`` s23 (model time_offset) gyro_scale_factor sx at +818 to +15000 ppm (+2863:
    its printed MDB, refused 6 of 6 times, doc/benchmarks.md H207) and −818 to −2200 ppm
    leaves it so, −2863 ppm and beyond do not (the remainder moves to another slew and
    stops shrinking; doc/benchmarks.md H217).
    """
    return effect in RATE_ALIASES and bool(test) and test.clock_like(alpha)


def refused_entry(test: ClockChange) -> dict[str, Any]:
    """The ``refused_beside_clock`` entry of a hiding row :func:`refuses` (its line)."""
    p = test.finding().p_value
    return {"by": "clock", "p_value": p, "text": REFUSED_TEXT.format(p=p)}


def at_mdb(entry: dict[str, Any], effect: str, sizes: dict[str, float],
           shown: dict[str, str], tests: dict[str, dict[str, ClockChange | None]],
           alpha: float) -> None:
    """Whether the rule still refuses ``effect`` at each sign of its printed MDB (in place).

    ``entry``: the row's :func:`refused_entry`; ``tests[parameter]``: the clock test of
    the current model's run on the bag with that parameter alone injected at ``+size`` and
    ``−size`` (``sizes``: the printed MDB, ``shown`` as printed; keys ``"+"``, ``"-"``;
    ``None`` where the run or its test could not be made).  The rule holds at a size only
    while the effect leaves the remainder a clock's (:func:`refuses`): on ``dt_step`` s23 a
    gyro scale sx of −2.86e-3 moves it to another slew where it no longer shrinks
    (doc/benchmarks.md H217).  Adds, per parameter, ``at_mdb`` ({sign: refused; ``None``:
    not checked}), ``at_mdb_size``, ``at_mdb_p_value`` (the clock finding's p) and
    ``at_mdb_shape`` (what the remainder does along its slew: ``"shrinks"``, ``"grows"``,
    ``"neither"``), and the line's clause (``text``, :func:`at_mdb_clause`).
    """
    def each(f) -> dict[str, dict[str, Any]]:
        return {q: {k: None if t is None else f(t) for k, t in by.items()}
                for q, by in tests.items()}

    entry.update(at_mdb=each(lambda t: refuses(effect, t, alpha)),
                 at_mdb_size={q: float(sizes[q]) for q in tests},
                 at_mdb_p_value=each(lambda t: t.finding().p_value),
                 at_mdb_shape=each(_shape))
    entry["text"] += "; " + at_mdb_clause(entry, shown)


def _shape(test: ClockChange) -> str:
    """What the remainder does along the slew that carries it (:meth:`ClockChange.shrinks`)."""
    return "shrinks" if test.shrinks() else "grows" if test.grows() else "neither"


def p_text(p: float, rel: str = "=") -> str:
    """``p = 0.0012`` (one below the smallest double: ``p < 1e-300``)."""
    return f"p {rel} {p:.2g}" if p > 0.0 else "p < 1e-300"


def at_mdb_clause(entry: dict[str, Any], shown: dict[str, str]) -> str:
    """The line's per-sign clause of :func:`at_mdb` (``shown``: each MDB as printed)."""
    at, p, shape = entry["at_mdb"], entry["at_mdb_p_value"], entry["at_mdb_shape"]
    signs = ("+", "-")
    held = [f"{k}MDB of " + ", ".join(q for q in at if at[q][k]) for k in signs
            if any(at[q][k] for q in at)]
    both = [q for q in at if all(at[q][k] for k in signs)]
    if len(both) == len(at):
        low = max(p[q][k] for q in at for k in signs)
        return (f"checked at +-MDB of {', '.join(at)}: the remainder still a clock's at each, "
                f"{p_text(low, '<=')}: refused there")
    out = ["refused at " + " and at ".join(held)] if held else []
    for q in at:
        for k in signs:
            if at[q][k]:
                continue
            if at[q][k] is None:
                out.append(f"at {q} {k}{shown[q]} not checked: its run could not be made")
                continue
            why = {"grows": "it grows along a slew, as a gyro's error does",
                   "neither": "it no longer shrinks along a slew"}.get(
                       shape[q][k], "its change is no longer significant")
            # (no parentheses: the clause is printed inside the row's flag's, H221)
            out.append(f"at {q} {k}{shown[q]}, the {k}MDB, the remainder is no longer a "
                       f"clock's: {why}, {p_text(p[q][k])}; this sign can be added, its "
                       "test decides")
    return "; ".join(out)


def clock_test(res: stats.Table, calibration, fraction: float,
               periods: tuple[float, ...] = (), shared: dict | None = None
               ) -> ClockChange | None:
    """The test (:func:`clock_change`) of a residual table on ``fraction``'s window.

    ``calibration``: the run's (its camera and installation); ``periods``: a wobble's,
    fitted as rivals (:func:`wobble_periods`); ``shared``: the frames' offsets made once
    for the table's tests (:func:`~stellar_cal_ros.diagnosis.stats.accepted_offsets`).
    """
    cam = calibration.camera
    return clock_change(res, stats.evaluation_mask(res, fraction), (cam.fx, cam.fy),
                        (cam.cx, cam.cy), calibration.R_imu_st, periods=periods,
                        shared=shared)


def clock_change(res: stats.Table, mask: np.ndarray, focal: tuple[float, float],
                 centre: tuple[float, float], R_imu_st: np.ndarray | None,
                 parts: int = SEGMENTS, periods: tuple[float, ...] = (),
                 shared: dict | None = None) -> ClockChange | None:
    """The time offset × time test on ``mask``'s accepted stars (module docstring).

    ``periods`` (s): a wobble's periods the 'unexplained' lines found (:data:`WOBBLE`),
    fitted as rivals beside the flexure's.  ``None`` without the installation or the rate
    columns, or with fewer than 10 frames with motion a part.  ``shared``: as
    :func:`~stellar_cal_ros.diagnosis.stats.accepted_offsets`'.  Where the parts change
    (:meth:`ClockChange.changes`) the test is made again with the speed-squared smear
    beside them (:data:`SMEAR_P`), and that one is returned where
    :meth:`ClockChange.by_speed` (else the first, with the smear's coefficient).
    """
    found = stats.accepted_offsets(res, mask, focal, centre, R_imu_st, shared)
    if found is None:
        return None
    out = _parts_test(res, *found, focal, centre, R_imu_st, parts, periods, False)
    if out is None or not out.changes():
        return out
    rival = _parts_test(res, *found, focal, centre, R_imu_st, parts, periods, True)
    if rival is None:
        return out
    if rival.by_speed():
        return rival
    out.smear = dict(rival.smear, fitted=False)
    return out


def _parts_test(res: stats.Table, sub: stats.Table, got: tuple, focal: tuple[float, float],
                centre: tuple[float, float], R_imu_st: np.ndarray | None, parts: int,
                periods: tuple[float, ...], smear: bool, by_slew: bool = False,
                offset: bool | None = None) -> ClockChange | None:
    """:func:`clock_change`'s test of ``sub``'s frame offsets ``got``; ``smear``: beside it.

    ``by_slew``: the parts are each slew's :data:`SLEW_PARTS` (``parts`` ignored; the
    steps test's, :func:`steps_test`, ``offset`` its form), not ``parts`` of equal count.
    """
    frames, g, info, _, _, speed = got
    # a frame at rest says an offset only through its tiny rate, where any attitude error
    # the model leaves reads as seconds (unseen case ``knock``: 23-34 ms in the dwells
    # after the jump)
    use = stats.moving_frames(sub, frames, info, MOVING)
    frames, g, info = frames[use], g[use], info[use]
    t = stats.frame_times(sub, frames) - float(np.min(res["t"]))
    seg = _slew_parts(t) if by_slew else np.zeros(len(frames), dtype=int)
    parts = int(seg.max()) + 1 if by_slew and len(seg) else parts
    if len(frames) < 3 * parts or (by_slew and parts < 2 * SLEW_PARTS):
        return None
    if not by_slew:
        for s, idx in enumerate(np.array_split(np.arange(len(frames)), parts)):
            seg[idx] = s
    # the parts' offsets fitted jointly with a mount flexure's (GRAVITY): per frame its
    # scores h (q) and information with the offset (c, q) and with itself (F, q × q)
    h, cross, F = flexure_products(sub, frames, focal, centre, R_imu_st, periods,
                                   float(np.min(res["t"])), float(speed) if smear else 0.0)
    q = h.shape[1]
    P = parts + q
    H = np.zeros((P, P))
    H[np.arange(parts), np.arange(parts)] = np.bincount(seg, info, minlength=parts)
    for j in range(q):
        H[:parts, parts + j] = H[parts + j, :parts] = np.bincount(seg, cross[:, j],
                                                                  minlength=parts)
    H[parts:, parts:] = F.sum(0)
    S = np.zeros((len(frames), P))  # each frame's scores
    S[np.arange(len(frames)), seg] = g
    S[:, parts:] = h
    try:
        Hi = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return None
    beta = Hi @ S.sum(0)
    # each frame's scores about the fit
    E = S.copy()
    E[np.arange(len(frames)), seg] -= info * beta[seg] + cross @ beta[parts:]
    E[:, parts:] -= cross * beta[seg][:, None] + F @ beta[parts:]
    d = beta[:parts]
    e = E[np.arange(len(frames)), seg]  # the offset's (the lag window's autocorrelation)
    L = min(stats.plugin_bandwidth(e), max(len(e) // (4 * parts), 1))
    omega = E.T @ E
    for lag in range(1, L + 1):
        c = E[lag:].T @ E[:-lag]
        omega += (1.0 - lag / (L + 1.0)) * (c + c.T)
    full = Hi @ omega @ Hi
    hac = full[:parts, :parts]
    # a constant offset's parts differ by the filter's lag along each slew as well
    cov = hac + np.eye(parts) * FLOOR_S**2
    try:
        ci = np.linalg.inv(cov)
    except np.linalg.LinAlgError:
        return None
    one = np.ones(parts)
    mean = float(one @ ci @ d) / float(one @ ci @ one)
    r = d - mean
    chi2 = float(r @ ci @ r)
    dof = parts - 1
    p = float(dist.chi2.sf(chi2, dof))
    t0 = [float(t[seg == s].min()) for s in range(parts)]
    t1 = [float(t[seg == s].max()) for s in range(parts)]
    sig = np.sqrt(np.maximum(np.diag(hac), 0.0))
    # (the innovation is the image velocity × the offset the model lacks: its sign is the
    # opposite of time_offset's dt, t_true = stamp + dt)
    out = ClockChange(t0, t1, [-float(x) for x in d], [float(x) for x in sig], chi2, dof,
                      p, math.nan, float(speed))
    out.duration = float(np.ptp(res["t"]))
    out.periods = [float(x) for x in periods]
    if smear:  # (its column the last: time_offset's sign, as the parts')
        out.smear = {"offset_s": -float(beta[-1]), "sigma_s": smear_sigma(full, Hi, len(frames)),
                     "fitted": True}
    slew_growth(out, g, info, t)
    lag = constant_lag(res, focal, centre, R_imu_st, frames)
    if lag is not None:
        drift_fit(out, -d, ci, seg, info, t, lag)
        if by_slew:
            def behind(of, frames=frames):
                return constant_lag(res, focal, centre, R_imu_st, frames, of)

            out.steps = steps_fit(-d, ci, seg, info, t, behind, offset)
    # (the spans', not the parts': a part without a slew says little, at a large σ)
    out.size_px = float(np.ptp([s[2] for s in out.spans()])) * float(speed)
    return out


def smear_sigma(sandwich: np.ndarray, inverse: np.ndarray, frames: int) -> float:
    """The speed-squared smear's σ (s; its column the last): :data:`SMEAR_P`'s test.

    The larger of the frames' sandwich (the lag window's, × ``n / (n − P)`` for the ``P``
    coefficients fitted to its ``n`` frames' scores) and the stated noise's (the inverse
    information ``inverse``).  The smear's scores sit in the few fast frames of a window
    (28 moving frames in psce's 300 s, the sandwich's Satterthwaite dof 2.5-10, median
    5.6): the sandwich alone is about right on average (rms 0.048 ms, 0.059 with the
    factor, against the coefficient's SD 0.055 ms over 40 clean seeds) but so noisy that
    offset / σ was no N(0, 1): SD 1.25, mean square 1.72, 15 % beyond 2 (clean s23 −3.4).
    The stated noise's (0.059 ms) holds where the model does, the sandwich where a misfit
    makes the scores larger (a smear bag without time_offset: 0.18-0.26 ms).  Beside it,
    over the same 40 seeds: SD 0.87, mean square 0.83, 2.5 % beyond 2 (doc/benchmarks.md
    H292, ``benchmarks/smear_z.py``).
    """
    P = sandwich.shape[0]
    wide = float(sandwich[-1, -1]) * frames / max(frames - P, 1)
    return float(math.sqrt(max(wide, float(inverse[-1, -1]), 0.0)))


def smear_beside(res: stats.Table, calibration, fraction: float) -> dict | None:
    """The speed-squared smear fitted beside the parts whether they change or not.

    :func:`clock_test`'s rival (:data:`SMEAR_P`; it fits it only where the parts change):
    ``clock_change.smear``'s ``offset_s`` and ``sigma_s`` with ``speed`` (px/s, the speed
    its offset is said at), to check its σ where the truth is known (clean bags: 0).
    ``None`` where the test cannot be made.
    """
    cam = calibration.camera
    focal, centre = (cam.fx, cam.fy), (cam.cx, cam.cy)
    found = stats.accepted_offsets(res, stats.evaluation_mask(res, fraction), focal, centre,
                                   calibration.R_imu_st, None)
    if found is None:
        return None
    rival = _parts_test(res, *found, focal, centre, calibration.R_imu_st, SEGMENTS, (), True)
    if rival is None or not rival.smear:
        return None
    return dict(rival.smear, speed=rival.speed)


def wobble_periods(found: list, span: float) -> tuple[float, ...]:
    """The periods (s) of the :data:`WOBBLE` lines among ``found``, one per wobble.

    A wobble about two axes is found on u and on v at periods a frequency ordinate apart
    (unseen case ``wobble`` s23: 45.3 s and 44.4 s): a period within 10 % of one kept
    (the more significant, ``found`` ranked first) is the same wobble; two such columns
    would be nearly collinear over the window.  Only periods the window (``span`` s) holds
    :data:`WOBBLE_CYCLES` times: a longer one is a trend over the window, which the clock's
    own parts and drift read (a flexure bag, psce 200 s: a 'periodic, 100 s' line over its
    100-s window; fitted as a wobble it left a false clock line, p 7.7e-6 unadjusted).
    """
    out: list[float] = []
    for f in found:
        if not f.regressor.startswith(WOBBLE):
            continue
        try:
            period = float(f.regressor[len(WOBBLE):].split(" s)")[0])
        except ValueError:
            continue
        if 0 < period <= span / WOBBLE_CYCLES and all(abs(period - q) > 0.1 * q
                                                       for q in out):
            out.append(period)
    return tuple(out)


def flexure_products(sub: stats.Table, frames: np.ndarray, focal: tuple[float, float],
                     centre: tuple[float, float], R_imu_st: np.ndarray | None,
                     periods: tuple[float, ...] = (), t0: float = 0.0,
                     smear: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame of ``frames`` the rivals' columns' products (``q`` of them).

    The :data:`GRAVITY` columns (none without the gravity columns or with gravity (nearly)
    still over the frames), then per period of ``periods`` :data:`WOBBLE`'s (a turn about
    each tracker axis at the sine and the cosine of ``t − t0``), then with ``smear`` (px/s,
    the window's 95th percentile image speed; 0: none) the speed-squared smear's
    (:data:`SMEAR_P`), last: each star shifted along its image velocity ``u`` by ``u |u| /
    smear`` (px per s of coefficient: the offset it says at that speed).  ``(h (n, q), c
    (n, q), F (n, q, q))``: ``Σ xᵀ S⁻¹ ν``, ``Σ xᵀ S⁻¹ u`` (``u`` the image velocity of
    :func:`~stellar_cal_ros.diagnosis.stats.frame_offsets`) and ``Σ xᵀ S⁻¹ x``, ``x`` each
    column's image shift (px per arcsec of turn).
    """
    n = len(frames)
    none = np.zeros((n, 0)), np.zeros((n, 0)), np.zeros((n, 0, 0))
    gravity = all(k in sub for pair in GRAVITY for k in pair)
    if not (gravity or periods or smear):
        return none
    got = stats.motion_columns(sub, focal, centre, R_imu_st)
    if got is None:
        return none
    ok, vel, nu, Si = got
    fr = np.asarray(sub["frame"])[ok]
    on = np.isin(fr, frames)
    if not on.any():
        return none
    J = stats.attitude_columns({k: np.asarray(sub[k])[ok] for k in ("x_st", "y_st", "z_st")},
                               *focal) * ARCSEC
    turns = []
    if gravity:
        gx, gy = (np.asarray(sub[k], dtype=float)[ok] for k in GRAVITY[0])
        if max(float(np.ptp(gx[on])), float(np.ptp(gy[on]))) > MIN_GRAVITY_CHANGE:
            for kx, ky in GRAVITY:
                x, y = (np.asarray(sub[k], dtype=float)[ok] for k in (kx, ky))
                turns.append(np.stack([-y, x, np.zeros_like(x)], 1))  # z × g
    if periods:
        t = np.asarray(sub["t"], dtype=float)[ok] - t0
        for period in periods:
            ph = 2.0 * np.pi * t / period
            for wave in (np.sin(ph), np.cos(ph)):
                for axis in np.eye(3):
                    turns.append(wave[:, None] * axis)
    shifts = [np.einsum("nij,nj->ni", J, turn) for turn in turns]
    if smear:
        shifts.append(stats.speed_squared(vel, smear))
    if not shifts:
        return none
    X = np.stack(shifts, 2)[on]  # (stars, 2, q)
    k = np.searchsorted(frames, fr[on])
    Si, vel, nu = Si[on], vel[on], nu[on]
    SX = np.einsum("nij,njq->niq", Si, X)
    q = X.shape[2]
    h = np.stack([np.bincount(k, np.einsum("ni,ni->n", SX[:, :, j], nu), minlength=n)
                  for j in range(q)], 1)
    c = np.stack([np.bincount(k, np.einsum("ni,ni->n", SX[:, :, j], vel), minlength=n)
                  for j in range(q)], 1)
    F = np.zeros((n, q, q))
    for i in range(q):
        for j in range(q):
            F[:, i, j] = np.bincount(k, np.einsum("ni,ni->n", X[:, :, i], SX[:, :, j]),
                                     minlength=n)
    return h, c, F


def constant_lag(res: stats.Table, focal: tuple[float, float], centre: tuple[float, float],
                 R_imu_st: np.ndarray | None, frames: np.ndarray,
                 of: Callable[[np.ndarray], np.ndarray] | None = None) -> np.ndarray | None:
    """Per frame of ``frames`` the time since a constant offset's estimate learned (s).

    A model with time_offset holds one constant: its estimate at frame ``k`` is the
    recursive least squares of the offsets the frames so far said, their information-
    weighted mean.  A clock that drifts at rate ``r`` leaves ``r (t_k − t̄_k)``, ``t̄_k =
    Σ_{j≤k} I_j t_j / Σ_{j≤k} I_j`` over every frame of the run (not only the window's):
    largest when a slew begins after a long dwell, shrinking along it as the estimate
    catches up.  ``None`` without the rate columns.  ``of``: the offset's shape as a
    function of the frames' times (s from the run's first row; ``(n,)`` → ``(n, m)``), its
    lag behind the constant's estimate returned ``(len(frames), m)`` instead (a step's:
    :func:`steps_fit`).
    """
    m = stats.accepted(res)
    sub = stats.Rows(res, m)
    got = stats.frame_offsets(sub, focal, centre, R_imu_st)
    if got is None:
        return None
    fr, _, info = got[:3]
    f_all, first = np.unique(np.asarray(sub["frame"]), return_index=True)
    t = np.asarray(sub["t"], dtype=float)[first][np.searchsorted(f_all, fr)]
    x = t if of is None else of(t - float(np.min(res["t"])))
    info = np.maximum(info, 0.0)
    w = info if of is None else info[:, None]
    cum = np.cumsum(w, axis=0)
    xbar = np.cumsum(w * x, axis=0) / np.where(cum > 0, cum, 1.0)
    lag = np.where(cum > 0, x - xbar, 0.0)
    k = np.searchsorted(fr, frames)
    if np.any(k >= len(fr)) or np.any(fr[np.minimum(k, len(fr) - 1)] != frames):
        return None
    return lag[k]


def drift_fit(out: ClockChange, dt: np.ndarray, ci: np.ndarray, seg: np.ndarray,
              info: np.ndarray, t: np.ndarray, lag: np.ndarray) -> None:
    """The parts' offsets ``dt`` (time_offset's sign) fitted by a constant and one rate.

    Two columns, the better kept (the smaller χ² left): the parts' information-weighted
    time (a model without time_offset: the remainder is the offset, ``a + r t``) and their
    lag behind a constant's estimate (:func:`constant_lag`: a model with it).  Generalised
    least squares with the parts' covariance's inverse ``ci``; fills ``out``'s drift fields.
    """
    parts = len(dt)
    w = np.bincount(seg, info, minlength=parts)
    if np.any(w <= 0):
        return
    best = None
    # the filter's catch-up along each run of moving frames (a shared shape: the time since
    # the run began), a nuisance beside the rate
    tau = np.bincount(seg, info * since_slew(t), minlength=parts) / w
    for form, x in (("time", t), ("lag", lag)):
        xs = np.bincount(seg, info * x, minlength=parts) / w
        X = np.stack([np.ones(parts), xs, tau], 1)
        A = X.T @ ci @ X
        try:
            cov = np.linalg.inv(A)
        except np.linalg.LinAlgError:
            continue
        beta = cov @ X.T @ ci @ dt
        r = dt - X @ beta
        rest = float(r @ ci @ r)
        if cov[1, 1] > 0 and (best is None or rest < best[0]):
            best = (rest, form, float(beta[1]), float(math.sqrt(cov[1, 1])),
                    float(beta[0]) if form == "time" else math.nan, float(beta[2]),
                    float(math.sqrt(max(cov[2, 2], 0.0))))
    if best is None:
        return
    rest, form, rate, sigma, out.drift_start, out.along, out.along_sigma = best
    out.drift_rate, out.drift_sigma, out.drift_form = rate, sigma, form
    out.drift_chi2 = (rate / sigma) ** 2
    out.drift_p = float(dist.chi2.sf(out.drift_chi2, 1))
    out.rest_chi2, out.rest_p = rest, float(dist.chi2.sf(rest, parts - 3))


def since_slew(t: np.ndarray) -> np.ndarray:
    """Each frame's time since its run of moving frames (its slew) began (s).

    A run ends where consecutive frames are more than :data:`CATCH_UP_GAP` × their median
    spacing apart.
    """
    if len(t) < 2:
        return np.zeros(len(t))
    gap = np.diff(t) > CATCH_UP_GAP * float(np.median(np.diff(t)))
    start = np.maximum.accumulate(np.where(np.r_[True, gap], np.arange(len(t)), 0))
    return t - t[start]


def slew_growth(out: ClockChange, g: np.ndarray, info: np.ndarray, t: np.ndarray) -> None:
    """The change along the slew whose offset departs most from zero (:meth:`ClockChange.grows`).

    Per slew (:func:`since_slew`) of at least 5 frames the frames' offsets ``g / I``
    (time_offset's sign) fitted by ``a + c τ`` (weights ``I``, the covariance scaled by the
    fit's dispersion when above one: neighbouring frames share errors); the slew kept is
    the one whose mean offset is most significant.  Fills ``out.slew`` (first, last frame
    time, mean offset) and ``slew_growth(_sigma)``.
    """
    tau = since_slew(t)
    run = np.cumsum(tau == 0.0) - 1
    best = None
    for r in range(int(run.max()) + 1 if len(run) else 0):
        k = (run == r) & (info > 0)
        if k.sum() < 5:
            continue
        y, w, x = -g[k] / info[k], info[k], tau[k]
        X = np.stack([np.ones(len(y)), x], 1)
        A = X.T @ (w[:, None] * X)
        try:
            cov = np.linalg.inv(A)
        except np.linalg.LinAlgError:
            continue
        beta = cov @ X.T @ (w * y)
        e = y - X @ beta
        cov = cov * max(1.0, float(np.sum(w * e * e)) / (len(y) - 2))
        m = float(np.sum(w * y) / np.sum(w))
        z = abs(m) * math.sqrt(float(np.sum(w)))
        if best is None or z > best[0]:
            best = (z, [float(t[k].min()), float(t[k].max()), m], float(beta[1]),
                    float(math.sqrt(max(cov[1, 1], 0.0))))
    if best is not None:
        _, out.slew, out.slew_growth, out.slew_growth_sigma = best


def _slew_parts(t: np.ndarray) -> np.ndarray:
    """Each moving frame's part: its slew's (:func:`since_slew`) :data:`SLEW_PARTS` parts.

    A slew of fewer than :data:`SLEW_PARTS` frames is one part (the catch-up beside the
    offsets needs a slew's early and late parts apart: :func:`steps_fit`).
    """
    run = np.cumsum(since_slew(t) == 0.0) - 1 if len(t) else np.zeros(0, dtype=int)
    seg = np.zeros(len(t), dtype=int)
    n = 0
    for r in range(int(run.max()) + 1 if len(run) else 0):
        idx = np.flatnonzero(run == r)
        for chunk in np.array_split(idx, min(SLEW_PARTS, len(idx))):
            seg[chunk] = n
            n += 1
    return seg


def _gls(X: np.ndarray, ci: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """``(χ² left, β, cov β)`` of ``y`` fitted by the columns ``X`` (weights ``ci``)."""
    A = X.T @ ci @ X
    cov = np.linalg.pinv(A)
    beta = cov @ X.T @ ci @ y
    r = y - X @ beta
    return float(r @ ci @ r), beta, cov


def steps_fit(dt: np.ndarray, ci: np.ndarray, seg: np.ndarray, info: np.ndarray,
              t: np.ndarray, behind: Callable, offset: bool | None = None) -> dict:
    """The parts' offsets ``dt`` as ``k`` steps against one rate (:func:`steps_test`).

    Each slew's catch-up its own (the remainder shrinks along a slew in proportion to the
    offset it carries: ``dt_step2`` s21, −1.85 → +0.11 ms on the slew after a 2-ms step,
    −3.58 → −1.76 ms after the second; one shared catch-up leaves a rate 159 χ² / 12 dof on
    it, a 0 → 3 ms drift's 81): a column per slew, its time since the slew began.  Both
    forms of :func:`drift_fit` (the offset itself, ``"time"``: a model without time_offset;
    its lag behind a constant's estimate, ``"lag"``, ``behind``'s columns), the one kept
    that fits better.  For ``k`` = 1 … :data:`STEPS_MAX` the ``k`` borders between parts
    (``offset``: whether the model holds time_offset, the form then ``"lag"``, else
    ``"time"``; ``None``: not known) (a scan over every choice) whose steps, with a
    constant and the catch-up, leave the
    least χ²; ``k`` the least whose steps leave nothing significant (p ≥
    :data:`DRIFT_REST_P`).  The steps beside the rate tested as the nested alternative: the
    χ² they remove from the rate's fit, ``k`` dof, its p × the choices scanned
    (Bonferroni); the rate beside the steps likewise, 1 dof.  ``{}`` where no ``k`` fits.
    The dict: ``at`` (each step's border, s from the run's first row: the middle between
    the parts), ``between`` (the parts' last and first frame times), ``size_s`` /
    ``sigma_s`` (each step, time_offset's sign), ``rest_chi2``, ``rest_dof``, ``rest_p``
    (the steps' fit), ``steps_chi2``, ``steps_p`` (beside the rate, adjusted),
    ``rate_chi2``, ``rate_p`` (the rate beside the steps), ``drift_rate`` /
    ``drift_sigma`` / ``drift_rest_chi2`` / ``drift_rest_p`` (the rate's fit), ``scanned``,
    ``form``.
    """
    parts = len(dt)
    w = np.bincount(seg, info, minlength=parts)
    if np.any(w <= 0):
        return {}
    t0 = np.array([t[seg == s].min() for s in range(parts)])
    t1 = np.array([t[seg == s].max() for s in range(parts)])
    at = 0.5 * (t1[:-1] + t0[1:])  # (parts - 1,) the borders

    def mean(x):
        return np.bincount(seg, info * x, minlength=parts) / w

    tau = since_slew(t)
    run = np.cumsum(tau == 0.0) - 1
    catch = [mean(np.where(run == r, tau, 0.0)) for r in range(int(run.max()) + 1)]
    catch = np.stack([c for c in catch if np.any(c > 0)], 1)
    one = np.ones(parts)
    forms = {"time": ((np.arange(parts)[:, None] >= np.arange(1, parts)[None, :]).astype(float),
                      mean(t))}
    cols = behind(lambda tt: np.column_stack([tt, tt[:, None] >= at[None, :]]))
    if cols is not None:
        forms["lag"] = (np.stack([mean(cols[:, j]) for j in range(1, parts)], 1),
                        mean(cols[:, 0]))
    if offset is not None:
        forms = {k: v for k, v in forms.items() if (k == "lag") is offset}
    best = None
    for form, (H, rate) in forms.items():
        got = _steps_in(dt, ci, one, H, rate, catch, at, t0, t1)
        if got and (best is None or min(got["rest_chi2"], got["drift_rest_chi2"])
                    < min(best["rest_chi2"], best["drift_rest_chi2"])):
            best = dict(got, form=form)
    return best or {}


def _steps_in(dt, ci, one, H, rate, catch, at, t0, t1) -> dict:
    """:func:`steps_fit` in one form (``H``: the steps' columns, ``rate``: the rate's)."""
    parts = len(dt)
    free = catch.shape[1]
    drift, beta_d, cov_d = _gls(np.column_stack([one, rate, catch]), ci, dt)
    scanned = 0
    for k in range(1, STEPS_MAX + 1):
        dof = parts - 1 - k - free
        if dof < 1:
            return {}
        best = None
        for b in combinations(range(parts - 1), k):
            scanned += 1
            rest, beta, cov = _gls(np.column_stack([one, H[:, list(b)], catch]), ci, dt)
            if best is None or rest < best[0]:
                best = (rest, b, beta, cov)
        rest, b, beta, cov = best
        rest_p = float(dist.chi2.sf(rest, dof))
        if rest_p < DRIFT_REST_P:
            continue
        full, _, _ = _gls(np.column_stack([one, rate, H[:, list(b)], catch]), ci, dt)
        steps_chi2 = max(drift - full, 0.0)
        rate_chi2 = max(rest - full, 0.0)
        return {"at": [float(at[j]) for j in b],
                "between": [[float(t1[j]), float(t0[j + 1])] for j in b],
                "size_s": [float(x) for x in beta[1:1 + k]],
                "sigma_s": [float(math.sqrt(max(cov[i, i], 0.0))) for i in range(1, 1 + k)],
                "rest_chi2": rest, "rest_dof": dof, "rest_p": rest_p,
                "steps_chi2": steps_chi2,
                "steps_p": min(1.0, scanned * float(dist.chi2.sf(steps_chi2, k))),
                "rate_chi2": rate_chi2, "rate_p": float(dist.chi2.sf(rate_chi2, 1)),
                "drift_rate": float(beta_d[1]),
                "drift_sigma": float(math.sqrt(max(cov_d[1, 1], 0.0))),
                "drift_rest_chi2": drift,
                "drift_rest_p": float(dist.chi2.sf(drift, parts - 2 - free)),
                "scanned": scanned}
    return {}


def steps_said(steps: dict, alpha: float) -> bool:
    """Whether the clock steps rather than drifts (:func:`steps_fit`'s nested tests).

    The steps beside the rate significant at ``alpha`` (adjusted for the scan) and the
    rate beside the steps not (p ≥ ``alpha``): a staircase the rate cannot follow, where a
    drifting clock's parts leave the steps nothing the rate did not take.
    """
    return bool(steps) and steps["steps_p"] < alpha and steps["rate_p"] >= alpha


def steps_test(res: stats.Table, calibration, alpha: float, offset: bool | None = None
               ) -> dict:
    """The steps test (:func:`steps_fit`) over the whole run's moving frames, by slew.

    The window's parts hold few slews (psce 300 s: two, where a staircase and a ramp both
    fit two offsets; unseen case ``dt_step2``); the run's every slew, each in
    :data:`SLEW_PARTS` parts, tells them apart.  ``offset``: whether the model of ``res``
    holds time_offset (:func:`steps_fit`).  ``{}`` where it cannot be made; else the
    :func:`steps_fit` dict with ``said`` (:func:`steps_said` at ``alpha``) and the parts'
    ``t0``, ``t1``, ``dt``, ``sigma``.
    """
    cam = calibration.camera
    focal, centre = (cam.fx, cam.fy), (cam.cx, cam.cy)
    mask = np.ones(len(res["t"]), dtype=bool)
    found = stats.accepted_offsets(res, mask, focal, centre, calibration.R_imu_st, None)
    if found is None:
        return {}
    whole = _parts_test(res, *found, focal, centre, calibration.R_imu_st, SEGMENTS, (), False,
                        by_slew=True, offset=offset)
    if whole is None or not whole.steps:
        return {}
    return dict(whole.steps, said=steps_said(whole.steps, alpha), t0=whole.t0, t1=whole.t1,
                dt=whole.dt, sigma=whole.sigma)


def clock_steps_at(timing: ClockChange | None, res: stats.Table, calibration, alpha: float,
                   offset: bool, t_before: float, t: float) -> float | None:
    """The clock's step (s) said where an attitude step lies, or ``None``.

    ``timing``: the window's clock test of ``res``; only where its finding says the clock
    changes (unadjusted p below :data:`SMEAR_P`) its steps test (:func:`steps_test`, made
    here where ``timing`` holds none) is read: a step said whose parts either side of its
    border (its time is within them) hold ``t_before`` to ``t`` (s from the run's first
    row: the attitude step's last frame before and first after).
    """
    if timing is None or not timing.finding().p_value < SMEAR_P:
        return None
    if not timing.steps:
        timing.steps = steps_test(res, calibration, alpha, offset)
    st = timing.steps
    if not steps_said(st, alpha):
        return None
    for j, (a, b) in enumerate(st["between"]):
        k = st["t1"].index(a) if a in st["t1"] else None
        lo = st["t0"][k] if k is not None else a
        hi = st["t1"][k + 1] if k is not None and k + 1 < len(st["t1"]) else b
        if lo <= t and t_before <= hi:
            return float(st["size_s"][j])
    return None


def stamp_share(res: stats.Table, mask: np.ndarray, focal: tuple[float, float],
                centre: tuple[float, float], R_imu_st: np.ndarray | None
                ) -> tuple[float, float, float] | None:
    """A noise in the frames' stamps on ``mask``'s accepted stars and the NIS/dof it makes.

    ``(p, σ̂_t (s rms), share)``: :func:`~stellar_cal_ros.diagnosis.stats.stamp_noise`'s
    one-sided p and estimate on the frames' offsets along the stars' motion
    (:func:`~stellar_cal_ros.diagnosis.stats.accepted_offsets`), and the mean NIS per star's
    dof such a noise adds, ``σ̂_t² Σ uᵀ S⁻¹ u / (2 n)`` over the ``n`` accepted stars (``u``
    each star's image velocity: a frame stamped ``δ`` off its exposure moves its stars by
    ``u δ``).  On the 300-s swaying bag with its frames stamped N(0, 1 ms) off (unseen case
    ``sway_jitter`` s22) 0.97 ms and 4.86 of the window's NIS/dof 5.86.  Beside the
    speed-squared smear's column where that is significant (the last of
    :func:`flexure_products`, the clock's smear line's, at its :data:`SMEAR_P`;
    ``stamp_noise``'s ``beside``): a smear moves the frames' offsets with their speed, a
    stamp noise at random (unseen case ``smear15`` s22, 0.15 px at 202 px/s, the model
    without its time offset: p 0.0041, 0.14 ms alone, 0.040 beside it).  Here, not in
    :mod:`~stellar_cal_ros.diagnosis.stats`, which the clock imports.  ``None``: too few
    stars or pairs of frames.
    """
    m = np.asarray(mask, dtype=bool) & stats.accepted(res)
    found = stats.accepted_offsets(res, m, focal, centre, R_imu_st)
    if found is None:
        return None
    frames, info = found[1][0], found[1][2]
    smear = flexure_products(found[0], frames, focal, centre, R_imu_st, smear=found[1][5])[1]
    beside = None if smear.shape[1] == 0 else \
        np.where(info > 0, smear[:, -1], 0.0) / np.where(info > 0, info, 1.0)
    got = stats.stamp_noise(*found[1][:5], beside=beside, beside_p=SMEAR_P)
    if got is None:
        return None
    p, sig_t = got
    return p, sig_t, float(sig_t**2 * np.sum(found[1][2]) / (2.0 * max(int(m.sum()), 1)))
