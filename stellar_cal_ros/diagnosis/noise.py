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
  (Measured in :mod:`.noise_stars`; this module judges it.)
* the **gyro noise scale** ``g`` (and the accelerometer's ``a``, swaying-base), by maximum
  likelihood on the innovations: the prequential log-likelihood of the evaluation window,
  as a function of ``ln g``, from re-runs of the current model (three runs a factor of 3
  apart, moved until they bracket its maximum, then triples of runs a factor of 1.22
  apart around the vertex until it lies inside one); σ of ln g the sandwich of that
  triple: the variance of the score over the window's frames over the curvature² (the
  log-likelihood is a composite one, each star's own NIS while a frame's stars share one
  attitude error: :meth:`.noise_imu.ScaleSearch.sandwich`; the curvature alone was small).

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

from stellar_cal_ros.core import distributions as dist
from stellar_cal_ros.core.memory import trim_freed
from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.diagnosis import noise_structure
from stellar_cal_ros.diagnosis.noise_imu import FLAT, ScaleSearch
from stellar_cal_ros.diagnosis.noise_stars import (
    ALPHA,
    MATERIAL,
    StarNoise,
    Table,
    detector_patterns,
    group_index,
    group_x,
    grouped_stars,
    known_groups,
    levels_fit,
    significant_grouping,
    speed_variance,
    star_groups,
    star_levels,
    star_noise,
    star_spread,
    used_sigma,
)

#: the frames' fit made again this many times at the measured σ (:func:`measure_stars`)
FIT_PASSES = 2


def default_sigma(method: str) -> float:
    """The configured σ of stars whose message says 0, for ``method``."""
    from stellar_cal_ros.methods import registry as methods

    return float(methods.get(method).config_cls().centroid_sigma_px)


def measure_stars(result, data, method: str, fraction: float,
                  noise: NoiseScales | None, summary=None) -> StarNoise | None:
    """The within-frame estimate on a replay's residual table (where the run executed).

    ``summary``: the run's :class:`~.runstats.RunSummary`; where :func:`far_off` finds the
    run too far from its model (the verdict then skips the noise), the frames' fit is not
    weighted again at the measured σ (:func:`~.noise_stars.star_noise`'s ``weigh``): the
    skip line's NIS/dof is at the one fit's scale (clean swaying 300 s seed 21 diagnosed
    from a replayed result: the passes moved it from 7.82, x3.48, to 9.29, x3.2).  The rows
    the run's gate took are re-admitted at its own gate (``result.filter.gate``, where the
    result has its filter; else the default policy's).
    """
    from stellar_cal_ros.diagnosis.stats import evaluation_mask

    res = result.residuals
    if not res or len(res.get("t", ())) == 0:
        return None
    cam = result.calibration.camera
    sig, msg = used_sigma(res, data, noise or NoiseScales(), default_sigma(method),
                          cam.width, cam.height)
    trim_freed()  # (its freed heap pages, not held beside the estimate's)

    near = []  # (whether the run is near its model: decided on the window's one fit)
    # the detector's pattern tests read the table's last part whatever the mask: made once
    # for the window's estimate and the stretch's before it (≈ 0.25 CPU-s a 2-h run)
    patterns = detector_patterns(res, sig, cam.fx, cam.fy, (cam.cx, cam.cy),
                                 result.calibration.R_imu_st)
    trim_freed()

    def on(mask):
        # (the frames' attitude fit weighted again by the σ measured where the data find the
        # σ used wrong for part of the stars: noise_stars.star_noise's passes)
        return star_noise(res, sig, msg, mask, cam.fx, cam.fy, (cam.cx, cam.cy),
                          result.calibration.R_imu_st, size=(cam.width, cam.height),
                          passes=FIT_PASSES, weigh=weigh, kept=noise or NoiseScales(),
                          gate=getattr(getattr(result, "filter", None), "gate", None),
                          patterns=patterns)

    def weigh(first: StarNoise) -> bool:
        if not near:
            near.append(summary is None or not far_off(summary, first))
        return near[0]

    sn = on(evaluation_mask(res, fraction))
    if sn is not None:
        # (the frames' mean innovations against what the filter predicts for them: a noise
        # every star of a frame shares, which the within-frame estimate fits out)
        sn.common = noise_structure.frame_common(res, evaluation_mask(res, fraction), sig,
                                                 (cam.fx, cam.fy),
                                                 result.calibration.R_imu_st)
        # the stretch before the window, after the filter's first half of it (converging):
        # a noise that changes with time is invisible within the window alone
        t = np.asarray(res["t"], dtype=float)
        t0, span = float(t.min()), float(np.ptp(t))
        a, b = t0 + 0.5 * (1.0 - fraction) * span, t0 + (1.0 - fraction) * span
        early = on((t >= a) & (t < b)) if b > a else None
        known = None if early is None else ~early.unknown
        if known is not None and known.sum() >= 20:
            s, e, _ = early.group(known)
            if np.isfinite(s) and np.isfinite(e):
                sn.before = {"scale": s, "sigma": e, "from_s": a - t0, "to_s": b - t0}
                # (its rows the groups' test reads, not its own levels, speeds, patterns)
                sn.early = dataclasses.replace(early, levels=None, t=None, speed=None,
                                               pattern_px=None, patterns=[], common=None)
    return sn


# ----------------------------------------------------------------------------- the verdict
def p_two_sided(value: float, sigma: float) -> float:
    """Two-sided p of "the scale is 1" for a measured ``value`` ± ``sigma`` (normal)."""
    if not (np.isfinite(sigma) and sigma > 0):
        return 1.0
    return float(2.0 * dist.norm.sf(abs(value - 1.0) / sigma))


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
    #: 5 % and 95 % points of the σ the stars' messages state (a field that varies star by
    #: star is said as its range, not as its median)
    stated_sigma_range: tuple[float, float] = (math.nan, math.nan)
    unknown: int = 0  #: stars whose message says σ = 0
    unknown_sigma_px: float = math.nan  #: their measured σ
    unknown_sigma_sigma: float = math.nan
    unknown_base_px: float = math.nan  #: the σ the run assumed for them (the default)
    default_px: float = math.nan  #: the configured σ of σ-0 stars (what groups of them are of)
    groups: list[dict[str, Any]] = field(default_factory=list)
    group: dict[str, Any] | None = None  #: the grouping applied (or None)
    #: the groups applied composed with those of earlier rounds, of the messages' σ:
    #: ``{by, edges, scales, sigma}`` (None: this round's are the messages' own)
    composed: dict[str, Any] | None = None
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
    #: the stars' σ scale before the window unlike the window's (a noise that changes with
    #: time): {before, sigma_before, window, sigma_window, from_s, to_s, p_value} or None
    changes: dict[str, float] | None = None
    #: the stars' noise heavier-tailed than Gaussian: {share, expected, p_value} or None
    tails: dict[str, float] | None = None
    #: the stated σ wrong star by star (:func:`star_levels`): {F, p_value, stars, rows,
    #: spread, ...} or None
    per_star: dict[str, float] | None = None
    #: the stars' σ growing with their image's speed (smear, :func:`speed_variance`):
    #: {rest_px, per_deg_s_px, v95_deg_s, at_v95_px, p_value, ...} or None
    speed: dict[str, float] | None = None
    #: the gyro bias walk's search (:func:`~.noise_runs.search_walk`): {deg_h_sqrth, sigma,
    #: p_value, over_white_gyro, accepted, ...} or None (not searched)
    walk: dict[str, Any] | None = None
    #: the frames' stamps' noise that made the model too far off (:func:`stamp_jitter`):
    #: {ms, p_value, nis_share} or None
    stamp_jitter: dict[str, float] | None = None
    #: a noise every star of a frame shares, white from frame to frame, named
    #: (:func:`named_common`): :func:`~.noise_structure.frame_common`'s dict, or None; with
    #: ``applied_px``, ``nis_before``, ``nis_after`` where the model ran again with it in R
    #: (:func:`~.noise_runs._at_frames`)
    frame_common: dict[str, float] | None = None

    @property
    def rescaled(self) -> bool:
        """The diagnosis uses other noise than stated."""
        return not (self.applied.identity or self.applied == self.stated)

    def imu_from_stars(self) -> list[str]:
        """The IMU components applied at a scale the stars' fit measured (not as stated).

        Those whose own samples are not white (they carry the motion: the swaying base's
        gyro), so that only the stars' ML runs measured them, and not read as motion beyond
        the noise (:attr:`beyond`: kept at the samples').  Such a scale holds for the model
        it was measured on: an effect still missing there makes the attitude wander, which
        a larger IMU noise follows (unseen case ``sway_sky_twin_dt1``, the swaying bag with
        the sky and a prior without it, s21: gyro x106 +- 15 measured with aberration
        missing, kept once it was added).
        """
        return [c for c in self.rejected if c in ("gyro", "accel") and c not in self.beyond
                and not (self.samples.get(c) or {}).get("white")]

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

    def following(self, cause: str) -> NoiseVerdict:
        """The verdict with its star-by-star repeat following ``cause`` (its line's).

        The repeat's line and the IMU noise's reason (:func:`repeat_reason`, where the
        repeat is why it was taken as stated) then say the cause, not the catalogue
        positions or the per-star errors (unseen cases ``lens_zone``, ``stray_light``).
        """
        if not self.repeat:
            return self
        skipped = self.imu_skipped
        if skipped == repeat_reason(self.repeat["rms_px"]):
            skipped = repeat_reason(self.repeat["rms_px"], cause)
        return dataclasses.replace(self, repeat=dict(self.repeat, follows=cause),
                                   imu_skipped=skipped)

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
        if self.composed:  # (with the scales of earlier rounds, of the messages' σ)
            out["star_groups_composed"] = self.composed
        if self.repeat:
            out["star_repeat"] = self.repeat
        if self.correlated:
            out["star_correlated"] = self.correlated
        if self.changes:
            out["star_changes"] = self.changes
        if self.tails:
            out["star_tails"] = self.tails
        if self.per_star:
            out["star_per_star"] = self.per_star
        if self.speed:
            out["star_speed"] = self.speed
        if self.walk is not None:
            out["gyro_bias_rw"] = self.walk
        out["verdict"] = self.lines()
        if self.skipped:
            out["skipped"] = self.skipped
        if self.stamp_jitter:
            out["stamp_jitter"] = self.stamp_jitter
        if self._common():
            out["frame_common"] = self.frame_common
        if self.imu_skipped:
            out["imu_skipped"] = self.imu_skipped
        return out

    def _stamp_line(self) -> str:
        """The line of the frames' stamps' noise applied in each frame's R ('' if none).

        :func:`~.noise_runs._at_stamps`'s run with it.
        """
        j = self.stamp_jitter
        if not j or "applied_ms" not in j:
            return ""
        return (f"the frames' stamps jitter {j['applied_ms']:.2g} ms rms (the stars' spread "
                f"along their image motion, p = {j['p_value']:.2g}): a noise in time, not in "
                "the stars' positions, applied in each frame's measurement covariance "
                f"(NIS/dof {j['nis_before']:.3g} -> {j['nis_after']:.3g}): use --noise-scale "
                f"stamp={j['applied_ms']:.2g}")

    def _common(self) -> bool:
        """A frame-common noise is named (not where the frames' stamps are: theirs)."""
        return bool(self.frame_common) and not self.stamp_jitter

    def _common_line(self) -> str:
        """The line of a noise common to each frame's stars ('' if none).

        Unseen case ``frame_jitter`` (one N(0, 0.04 px) shift of all stars of a frame, white
        between frames): RMS 0.063 px for 0.050 expected was "noise as stated" and no line.
        Applied in R (``applied_px``): it says so and what to use (``frame=X``), as the
        stamps' line does.
        """
        if not self._common():
            return ""
        c = self.frame_common
        head = (f"the frames share a noise: all stars of a frame move by one error of "
                f"{c['sigma_px']:.3g} +- {c['sigma_sigma_px']:.2g} px rms per axis, white from "
                "frame to frame (the frames' mean innovations beyond what the stars' sigma "
                f"and the filter's attitude predict, z = {c['z']:.3g}; {c['slow_px']:.3g} px "
                f"in the slower half of the frames, {c['fast_px']:.3g} in the faster: not the "
                "stamps, not a smear): the tracker moving against the IMU faster than the "
                "frames (an attitude or image jitter the gyro does not see), noise, not an "
                "effect. The stars' sigma, measured within each frame, does not hold it")
        if "applied_px" in c:  # (:func:`~.noise_runs._at_frames`'s run with it)
            return (head + ": applied in each frame's measurement covariance, "
                    f"{c['applied_px']:.2g} px shared by its stars (NIS/dof "
                    f"{c['nis_before']:.3g} -> {c['nis_after']:.3g}): use --noise-scale "
                    f"frame={c['applied_px']:.2g}")
        return (head + "; the filter takes it for attitude error, and the minimal detectable "
                f"sizes grow with it: use --noise-scale frame={c['sigma_px']:.2g} to state it")

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
            out.append(f"the {_IMU_WORDS[comp][0]} looks {s:.3g} +- {e:.2g} x {word} than "
                       f"{self._imu_stated(comp)}(the {comp}'s own samples{axes}{check}): use "
                       f"--noise-scale {_IMU_WORDS[comp][2]}={getattr(self.applied, comp):.3g}")
        return out

    def _imu_stated(self, comp: str) -> str:
        """"stated " or, on a later round, the scale applied before (its factor's reference)."""
        k = getattr(self.stated, comp)
        return "stated " if k == 1.0 else f"the x{k:.3g} of the stated applied before "

    def _beyond_lines(self) -> list[str]:
        """Motion the stars see beyond the IMU's own noise (not applied as noise)."""
        out = []
        for comp in self.beyond:
            f, smp = self.imu[comp], self.samples[comp]
            # (the search's scale is of the noise applied, the stated one where the samples
            # are within MATERIAL of it: said over the samples' own, as its words say)
            k = getattr(self.applied, comp) / getattr(self.stated, comp) / smp["scale"]
            out.append(f"the stars see more {_IMU_WORDS[comp][1]} motion than the {comp}'s "
                       f"noise explains: they would need x{f.value * k:.3g} +- "
                       f"{f.sigma * k:.2g} the "
                       f"noise its own samples show (x{smp['scale']:.3g} +- "
                       f"{smp['sigma']:.2g} of the stated): not {comp} noise but an effect "
                       "the model lacks (a candidate below, if one is significant), else the "
                       "tracker moving against the IMU (a wobble, a flexing mount) or a "
                       f"wandering {comp} bias, neither in the library (noise kept at the "
                       "samples')")
        return out

    def _walk_line(self) -> str:
        """The gyro bias's random walk, when the search found it ('' if not).

        The bias walk is a noise the model states none of (a constant bias): said as the
        density to state, not as a physical effect (unseen case ``bias_walk10``: "noise not
        measured (NIS/dof 2.36)" and a gravity lead before).
        """
        w = self.walk
        if not (w and w.get("accepted")):
            return ""
        d = w["deg_h_sqrth"]
        sd = f" +- {w['sigma']:.2g}" if w.get("sigma") is not None else ""
        return (f"the gyro bias wanders: a random walk of ~{d:.2g}{sd} deg/h/sqrt(h) (the "
                f"model states none; p = {w['p_value']:.2g}, and better than more white gyro "
                f"noise by {w['over_white_gyro']:.3g} in log-likelihood): use --noise-scale "
                f"gyro_bias_rw={d:.2g}")

    def _walk_refused_line(self) -> str:
        """The gyro bias walk its own search took but the round did not ('' if none).

        Refused by a rival effect (:func:`~.noise_runs.beats_rivals`), by its estimate
        following the motion (:func:`~.noise_runs.follows_motion`) or by the run with it:
        said with what was searched, its value and why (unseen case ``gsf_asym``: a walk of
        29 deg/h/sqrt(h) refused was told only in ``diagnosis.json``).  A walk the search
        itself did not take is not said: on a far-off first round (the clean swaying bag's
        prior, radial_k1k2 missing) its maximum is more white gyro noise standing in for
        the missing effect (x27 of the stated), which says nothing of a walk.
        """
        w = self.walk
        if not w or w.get("accepted") or not ("rival" in w or "motion_p" in w):
            return ""
        d = w["deg_h_sqrth"]
        sd = f" +- {w['sigma']:.2g}" if w.get("sigma") is not None else ""
        return (f"a gyro bias random walk was searched (the model states none): ~{d:.3g}"
                f"{sd} deg/h/sqrt(h) fits best (p = {w['p_value']:.2g}) but is "
                "not taken: "
                f"{w.get('why', '')} (noise.gyro_bias_rw in diagnosis.json)")

    def _unmeasured_phrase(self, comp: str) -> str:
        """Why the noise of the IMU component ``comp`` was not measured on this bag."""
        search, smp = self.imu[comp], self.samples.get(comp)
        why = []
        if smp is not None:  # (white samples would have measured it)
            why.append("its own samples are not white: they carry the motion")
        pts = list(search.points.values())
        if len(pts) > 1 and np.ptp(pts) < FLAT:
            why.append("the stars' fit does not change between a third and 3x of it: a "
                       "noise below what the stars see on this motion")
        else:
            why.append("the stars' fit has no maximum in its range")
        return (f"the {_IMU_WORDS[comp][0]} cannot be measured on this bag ("
                + "; ".join(why) + "): kept as stated, not confirmed")

    def _star_advice(self) -> str:
        """What to give replay for the stars' σ: one scale, or the groups kept from before.

        An earlier round's groups are multiplied by this round's scale (unseen case
        ``sigma0_faint``, seed 22: "use --noise-scale star=1.56" while the applied σ kept
        the magnitude groups, whose bright stars then read x0.9 of the messages' σ).
        """
        a = self.applied
        if not a.group_by:
            return f"use --noise-scale {a.advice(3)}"
        return (f"with the {a.group_by} groups measured before, now x"
                + _factors_text(a, a.star)
                + f" of the messages' sigma: use --noise-scale {a.advice()}")

    def _stated_varies(self) -> bool:
        lo, hi = self.stated_sigma_range
        return bool(np.isfinite(lo) and np.isfinite(hi) and lo > 0 and hi > STATED_SPREAD * lo)

    def _stated_px(self, scale: float = 1.0) -> str:
        """The σ the messages state, times ``scale``: their median, or their 5-95 % range.

        The range where it varies star by star (unseen case ``mag_faint_over2``: 0.05 px
        for bright stars, 0.1 px for faint ones was said "0.1 px stated").
        """
        if self._stated_varies():
            lo, hi = self.stated_sigma_range
            return f"{lo * scale:.3g}-{hi * scale:.3g}"
        return f"{self.stated_sigma_px * scale:.3g}"

    def lines(self, pending: bool = False) -> list[str]:
        """The terminal's lines, first of the diagnosis (noise is tested before effects).

        ``pending``: the lines a round prints as it goes (discover's progress), before the
        'unexplained' lines are tested: a star-by-star repeat whose cause they have not
        told yet (:meth:`following`) is said with its cause to come, not as the per-star
        errors the report may then contradict (unseen case ``stray_light`` s21: the
        report's first line the rows' field, which the repeat follows).
        """
        out = self._sample_lines()
        refused = self._walk_refused_line()
        if self.skipped:
            return [f"not measured: {self.skipped}"] + ([refused] if refused else []) + out
        stamps = self._stamp_line() or self._common_line()
        out = ([stamps] if stamps else []) + out
        walk = self._walk_line()
        out += ([walk] if walk else []) + ([refused] if refused else []) + self._beyond_lines()
        if self.correlated:
            out.append(noise_structure.correlated_line(self.correlated, self.applied.star))
        # with correlated noise its line names the scatter and the product to use: a line of
        # the scatter alone said 'x1.04 too large: use star=3.08' (unseen case ar1).  The
        # window's scale is advised only when it was applied: a noise that changes over the
        # run rejects "as stated" by itself, and a window not told from the stated (x1.08 +-
        # 0.03 beside x1.45 before it) printed "looks 1.08 x too small: use star=1"
        window_applied = self.applied.star != self.stated.star
        if "star" in self.rejected and self.group is None and not self.correlated and \
                abs(self.star - 1.0) > MATERIAL and window_applied:
            s, e = self.star, self.star_sigma
            word = "too small" if s > 1 else "too large"
            k = s if s > 1 else 1.0 / s
            ke = e / s**2 if s < 1 else e
            # (a later round's scale is of the one applied before: the σ it leads to is the
            # messages' times the composed scale, 0.05 -> 0.0497 px, not x the increment,
            # "0.05 -> 0.0468 px" on unseen case sigma0_faint's second round)
            a = self.applied
            before = "" if self.stated.star == 1.0 or a.group_by else \
                f" for the x{self.stated.star:.3g} applied before"
            out.append(f"the stars' sigma looks {k:.3g} +- {ke:.2g} x {word}{before} "
                       f"({self._stated_px()} -> "
                       f"{self._stated_px(s if a.group_by else a.star)} px): "
                       + self._star_advice())
        if self.group is not None:
            g = self.group
            said = (f"{self._stated_px()} px stated" + (
                ", the factors of each star's own" if self._stated_varies() else "")
                if np.isfinite(self.stated_sigma_px) else
                "0 = unknown in every message: the factors are of "
                f"the {self.default_px:.3g} px default")
            # (on a later round the groups are said composed with the scales applied
            # before, of the messages' σ: this round's alone are of the σ the run used)
            c = self.composed or g
            bins = _bin_text(c["edges"], GROUP_UNITS[c["by"]])
            before = "" if self.composed is None else \
                ", with the scales measured before (this round x" + ", x".join(
                    f"{s:.3g}" for s in g["scales"]) + ")"
            # (no message states a σ: each group's σ in px too, the σ its stars are given)
            px = [f" = {self.default_px * s:.3g} px"
                  if not np.isfinite(self.stated_sigma_px) else "" for s in c["scales"]]
            out.append(f"the stars' sigma ({said}) depends on "
                       + c["by"] + ": " + ", ".join(
                           f"x{s:.3g} +- {e:.2g}{p} ({b})" for s, e, p, b in zip(
                               c["scales"], c["sigma"], px, bins, strict=True))
                       + f"{before} (applied per group: use --noise-scale "
                       f"{self.applied.advice()}; `replay --estimate-noise` measures them)")
        if self.speed:
            d = self.speed
            out.append(f"the stars' sigma grows with their image's speed v (smear: a streak "
                       f"per exposure): sigma ~ sqrt(a^2 + (b v)^2) px, a = "
                       f"{d['rest_px']:.3g} +- {d['rest_sigma_px']:.2g} px at rest, b = "
                       f"{d['per_deg_s_px']:.3g} +- {d['per_deg_s_sigma_px']:.2g} px per "
                       f"deg/s ({d['at_v95_px']:.3g} px at the measured stars' 95th-percentile "
                       f"{d['v95_deg_s']:.3g} deg/s; t = {d['t']:.3g}, p = "
                       f"{d['p_value']:.2g}): noise, not an effect; one --noise-scale states "
                       "its average, the fix is a sigma that grows with the star's speed in "
                       "the tracker's messages. Residual spread that follows the angular "
                       "rate is this")
        if self.per_star:
            out.append(self._per_star_line())
        if self.changes:
            c = self.changes
            of = f"of the {c['by']} groups' sigma" if c.get("by") else "of the stated"
            out.append(f"the stars' sigma changes over the run: x{c['before']:.3g} +- "
                       f"{c['sigma_before']:.2g} {of} at {c['from_s']:.0f}-"
                       f"{c['to_s']:.0f} s, x{c['window']:.3g} +- {c['sigma_window']:.2g} in "
                       f"the window the diagnosis measures ({c['to_s']:.0f} s on; p = "
                       f"{c['p_value']:.2g}): noise that changes with time, which one "
                       "--noise-scale does not describe ("
                       + ("the window's is applied" if window_applied else
                          "the window's is not told from the stated, which is kept")
                       + "; state the messages' sigma per frame if the tracker knows it)")
        if self.tails:
            t = self.tails
            out.append(f"the stars' noise is heavy-tailed: {100 * t['share']:.2g} % of the "
                       f"accepted stars lie beyond the {100 * (1 - t['expected']):.1f} % bound "
                       f"of Gaussian noise of this sigma ({100 * t['expected']:.2g} % expected, "
                       f"p = {t['p_value']:.2g}): the sigma fits the noise's core, not its "
                       "tails, and stars the gate rejects are likely its tails, not "
                       "misidentified stars")
        if self.repeat:
            out.append(f"the stars' residuals repeat star by star (chi2 {self.repeat['chi2']:.0f}"
                       f" / {self.repeat['dof']:.0f} dof, p = {self.repeat['p_value']:.2g}): "
                       f"a per-star position error of at least {self.repeat['rms_px']:.2g} px "
                       "rms per axis (what the detector cells' means leave of it: with few "
                       "stars in view they take most) " + (
                           f"that follows the {self.repeat['follows']} (its 'unexplained' "
                           "line: gone once its fit is taken out of the centroids; a star "
                           "keeps its place on the detector along its track), not the "
                           "catalogue positions" if self.repeat.get("follows") else
                           PENDING_SOURCE if pending else
                           "from the catalogue positions or the identification")
                       + ", not centroid noise; the sigma is measured without it")
        if self.unknown and self.group is not None and not np.isfinite(self.stated_sigma_px):
            # (every message says 0 and the groups are theirs: the one σ measured over all
            # of them is not what they are given; it read "(used for them)")
            out.append(f"{self.unknown} stars carry sigma 0 (unknown) in every message: "
                       f"measured from the run as {self.unknown_sigma_px:.3g} +- "
                       f"{self.unknown_sigma_sigma:.2g} px over all of them, per "
                       f"{self.group['by']} group as above (used for them per group)")
        elif self.unknown:
            out.append(f"{self.unknown} stars carry sigma 0 (unknown): measured from the run "
                       f"as {self.unknown_sigma_px:.3g} +- {self.unknown_sigma_sigma:.2g} px "
                       + (f"(used for them x{self.correlated['sigma_scale']:.3g} for the "
                          "frame-to-frame correlation: "
                          f"{self.unknown_sigma_px * self.correlated['sigma_scale']:.3g} px)"
                          if self.correlated else "(used for them" + (
                              f": use --noise-scale unknown={self.applied.unknown_sigma_px:.3g})"
                              if self.applied.unknown_sigma_px > 0 else ")")))
        units = {"gyro": ("gyro noise (angle random walk)", "gyro"),
                 "accel": ("accelerometer noise (velocity random walk)", "accel")}
        summed = not [c for c in self.rejected if c != "gyro_bias_rw"] and not self.unknown
        for comp, search in self.imu.items():
            if (self.samples.get(comp) or {}).get("white"):
                continue  # said from the samples
            if not summed and comp not in self.rejected and not (search.measurable or
                                                                 search.bound):
                # (beside the lines of the components rejected no summary line follows:
                # the unmeasured one was said nowhere, and read as stated -- unseen case
                # sway_three s22: the stars x0.662 and the accel x3 said, the gyro's third
                # of the stated not)
                out.append(self._unmeasured_phrase(comp))
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
                           f"{self._imu_stated(comp)}".rstrip() + ": use --noise-scale "
                           f"{units[comp][1]}={getattr(self.applied, comp):.3g}")
        if self.imu_skipped:
            skipped = self.imu_skipped
            if pending and self.repeat and not self.repeat.get("follows") and \
                    skipped == repeat_reason(self.repeat["rms_px"]):
                skipped = repeat_reason(self.repeat["rms_px"], pending=True)
            out.append(f"IMU noise taken as stated: {skipped}")
        if summed:
            parts = [f"stars' sigma x{self.star:.3g} +- {self.star_sigma:.2g}"]
            for comp, smp in self.samples.items():
                if smp["white"]:
                    parts.append(f"{comp} x{smp['scale']:.3g} +- {smp['sigma']:.2g} "
                                 "from its samples")
            unmeasured = []
            for comp, search in self.imu.items():
                if (self.samples.get(comp) or {}).get("white"):
                    continue
                if not (search.measurable or search.bound):
                    unmeasured.append(comp)
                    continue
                parts.append(f"{comp} x{search.value:.3g} +- {search.sigma:.2g}"
                             if search.measurable else
                             f"{comp} at {'most' if search.bound == 'upper' else 'least'} "
                             f"x{search.value:.3g}")
            if self.stated.identity and unmeasured:
                # (not "noise as stated (..., gyro not measurable on this bag)": a user reads
                # the unmeasured component as stated too, unseen case sway_gyro_over3)
                out.append(("the rest of the noise" if walk or self._common() else "noise")
                           + " as stated where "
                           "measured (" + ", ".join(parts) + "); " + "; ".join(
                               self._unmeasured_phrase(c) for c in unmeasured))
            elif self.stated.identity:
                out.append(("the rest of the noise as stated (" if walk or self._common()
                            else "noise as stated (") + ", ".join(parts) + ")")
            else:  # measured again on a later round: relative to the scales applied so far
                out.append(self._measured_before_line(
                    parts + [f"{c} not measurable on this bag" for c in unmeasured]))
        elif "star" not in self.rejected and (self.stated.star != 1.0 or self.stated.group_by):
            # (another component rejected: the stars' σ kept from before is still said, with
            # the value to use; it was not said at all)
            out.append(self._measured_before_line(
                [f"stars' sigma x{self.star:.3g} +- {self.star_sigma:.2g}"], stars_only=True))
        return out

    def _per_star_line(self) -> str:
        """The stated σ wrong star by star: what it is, and what to do about it."""
        d = self.per_star
        k = 100.0 * 0.5 * d["spread"]  # a σ factor's spread: half its variance factor's
        within = "" if self.group is None else f" within the {self.group['by']} groups"
        if "star" in self.rejected and self.group is None and \
                abs(self.applied.star / self.stated.star - 1.0) > MATERIAL:
            avg = f"use --noise-scale {self.applied.advice(3)} for their average"
        elif self.group is None and (self.stated.star != 1.0 or self.stated.star_rho
                                     or self.stated.group_by):
            # a later round, measured relative to the scales applied before: "as stated
            # (x0.298)" was printed under a round 1 that said star=3.77 (unseen case
            # ``columns``: the ×3.4 of a correlated noise is not in the frames' scatter);
            # the stars' scales only: a gyro= or unknown= alone left the stars as stated
            avg = (f"their average is as measured before: use --noise-scale "
                   f"{self.applied.advice(3)}")
        elif self.group is None:
            avg = (f"their average is as stated (x{self.star:.3g} +- {self.star_sigma:.2g}), "
                   "no --noise-scale")
        else:
            avg = "the groups' scales above are their averages"
        return (f"the stars' sigma is wrong star by star: each star's own scatter differs "
                f"from its stated sigma by ~{k:.2g} % at random{within} (SD across "
                f"{d['stars']:.0f} stars; F = {d['F']:.3g}, p = {d['p_value']:.2g}; not a "
                f"trend in magnitude, radius or position); {avg}; the fix is in the "
                "tracker's sigma of each star, which one --noise-scale cannot state. Residual "
                "spread that follows which stars are in view is this, not an effect")

    def _measured_before_line(self, parts: list[str], stars_only: bool = False) -> str:
        """A later round that keeps the scales applied before: the σ they lead to, to use.

        Its measurements are of the σ applied so far: said composed with it, of the stated
        σ, with the ``--noise-scale`` to use (the product; the last round's measurement is
        the best one of it).  "noise as measured before (star x1.73 of the stated; now
        stars' sigma x0.97 +- 0.0042 of that)" left the product to the user (unseen case
        ``psce_sky_900s`` with its σ field 0.6x: 1.68, for a true 1.67).
        """
        st = self.stated
        use = []
        said = []
        if st.star != 1.0 or st.group_by:
            k = st.star * self.star
            if st.group_by:
                said.append("stars' sigma x" + _factors_text(st, k)
                            + f" +- {st.star * self.star_sigma:.2g} of the messages' sigma (by "
                    f"{st.group_by})")
            else:
                said.append(f"stars' sigma {self._stated_px()} -> {self._stated_px(k)} px "
                            f"(x{k:.3g} +- {st.star * self.star_sigma:.2g} of the stated)")
            use.append(st.replace(star=k).advice())
        for comp in ("gyro", "accel"):
            before = getattr(st, comp)
            if before == 1.0 or stars_only:
                continue
            v, e = self.scale_of(comp)
            if not np.isfinite(e):
                v, e = 1.0, math.nan
            k = before * v
            said.append(f"{comp} x{k:.3g}" + (f" +- {before * e:.2g}" if np.isfinite(e) else "")
                        + " of the stated")
            use.append(f"{comp}={k:.3g}")
        d = st.as_dict()
        before = [f"{k.split('_')[0]} x{v:.3g}" for k, v in d.items()
                  if k.endswith("_scale") and v != 1.0]
        if st.gyro_bias_rw:  # (a walk measured before: kept, said with the rest)
            said.append(f"gyro bias walk {st.gyro_bias_rw:.2g} deg/h/sqrt(h)")
            use.append(f"gyro_bias_rw={st.gyro_bias_rw:.2g}")
            before.append(f"gyro bias walk {st.gyro_bias_rw:.2g}")
        now = (" (this round: " + ", ".join(parts) + " of the scales applied before, "
               + ", ".join(before) + ")")
        return ("noise as measured before: " + ", ".join(said) + now
                + (": use --noise-scale " + ",".join(use) if use else ""))


#: the messages' σ (5-95 % points) vary beyond this ratio: said as a range, not a median
STATED_SPREAD = 1.1

#: how a grouping's bins are printed
GROUP_UNITS = {"magnitude": "mag", "radius": "px from the centre", "column": "px column",
               "row": "px row"}


def _bin_text(edges: list[float], unit: str) -> list[str]:
    e = [f"{x:.3g}" for x in edges]
    if not e:
        return ["all"]
    return ([f"< {e[0]} {unit}"] + [f"{a}-{b} {unit}" for a, b in zip(e, e[1:], strict=False)]
            + [f">= {e[-1]} {unit}"])


def _factors_text(scales: NoiseScales, k: float) -> str:
    """``F0 (bin 0), xF1 (bin 1), ...``: the groups of ``scales``, each factor times ``k``."""
    bins = _bin_text(list(scales.edges), GROUP_UNITS.get(scales.group_by, ""))
    return ", x".join(f"{k * f:.3g} ({b})" for f, b in zip(scales.factors, bins, strict=True))


def short_edges(edges: list[float], x: np.ndarray) -> list[float]:
    """``edges`` each moved to the shortest decimal that splits the stars ``x`` as it does.

    A quantile edge lies on a star's own value (a star's many rows repeat it), and the
    advice printed it to 4 digits: the star went to the other bin in a replay given the
    advice (an all-σ-0 bag, edge 4.5578 printed 4.558: NIS/dof 1.076 where the measured
    scales gave 1.006).  Each edge becomes a short decimal strictly above the largest star
    below it and at most the smallest star at or above it (the bins keep every star).
    """
    x = np.sort(np.asarray(x, dtype=float)[np.isfinite(x)])
    out = []
    for e in edges:
        i = int(np.searchsorted(x, e, side="left"))
        lo = x[i - 1] if i > 0 else -math.inf
        hi = x[i] if i < len(x) else math.inf
        mid = e if not (math.isfinite(lo) and math.isfinite(hi)) else 0.5 * (lo + hi)
        d = e
        for k in range(1, 16):
            c = float(f"{mid:.{k}g}")
            if lo < c <= hi:
                d = c
                break
        out.append(d)
    return out


def _compose_groups(applied: NoiseScales, stated: NoiseScales, best: dict[str, Any],
                    overall: float, sn: StarNoise, grouped: np.ndarray
                    ) -> tuple[NoiseScales, dict[str, Any] | None]:
    """``applied`` with the groups ``best`` measured on top of the groups ``stated`` kept.

    The scales ``best`` found are of the σ ``stated`` gave, which held an earlier round's
    groups: the applied factors are the products (:meth:`NoiseScales.times_groups`), not this
    round's alone, which replaced them.  Groups of another variable were measured of the σ
    before the kept factors (:func:`~.noise_stars.star_groups`) and replace them (one
    variable at a time: the earlier variable's steps are then lost; before, they were
    folded into this round's bins, ``1 / √(mean of m / f²)`` of the kept factors over a
    bin's stars, from bins measured of the σ used).  Returns the scales and, where an
    earlier grouping or scale was composed, the composed groups ``{by, edges, scales,
    sigma}`` of the messages' σ (else None).
    """
    f_new = np.asarray(best["scales"], dtype=float) / overall
    sig_new = np.asarray(best["sigma"], dtype=float)
    if stated.group_by and stated.group_by != best["by"]:
        # (measured of the σ before the kept factors, noise_stars.star_groups: they replace
        # the kept groups, nothing to fold)
        applied = applied.replace(group_by="", edges=(), factors=())
    out = applied.times_groups(best["by"], tuple(best["edges"]), tuple(f_new))
    # (a bin of the union no star lies in, between an edge kept and a step of this round's
    # beside it: left out, its edge dropped; no star's σ changes)
    e, f = list(out.edges), list(out.factors)
    filled = np.bincount(np.searchsorted(np.asarray(e, dtype=float), group_x(sn, best["by"])[
        grouped], side="right"), minlength=len(f)) > 0
    for k in range(len(f) - 1, -1, -1):
        if not filled[k] and len(f) > 1:
            del f[k], e[min(k, len(e) - 1)]
    out = out.replace(edges=tuple(short_edges(e, group_x(sn, best["by"])[grouped])),
                      factors=tuple(f))
    if not (stated.group_by or stated.star != 1.0):
        return out, None
    # each composed bin's σ: its scale's σ of this round times the factor it multiplied
    e_new = np.asarray(best["edges"], dtype=float)
    x = np.concatenate([[out.edges[0] - 1.0], out.edges]) if out.edges else np.zeros(1)
    j = np.searchsorted(e_new, x, side="right")
    before = np.asarray(out.factors) / f_new[j] * out.star / overall
    composed = np.asarray(out.factors) * out.star
    return out, {"by": best["by"], "edges": list(out.edges), "scales": composed.tolist(),
                 "sigma": (sig_new[j] * before).tolist()}


#: a frame-common noise whose estimate in the faster half of the frames exceeds the slower
#: half's by this many σ grows with the motion: not named (:func:`~.noise_structure.frame_common`)
COMMON_GROWTH_Z = 3.0


def named_common(d: dict[str, float] | None, n_tests: int) -> dict[str, float] | None:
    """``d`` (:func:`~.noise_structure.frame_common`) where it names a frame-common noise.

    Significant at :data:`~.noise_structure.COMMON_ALPHA` over the frames (Bonferroni over
    the noise's ``n_tests``), on the slower half of them alone and by the median of the
    frames' pairs (not a few frames far off: a step, a misidentified frame), material
    (:data:`~.noise_structure.COMMON_SHARE` of the frames' mean innovations' predicted
    variance), and not growing with the motion (the faster half's σ_j² within
    :data:`COMMON_GROWTH_Z` σ of the slower's): the frames' stamps' noise moves the stars
    with their image's speed (unseen cases ``jitter``: nothing in the slower half;
    ``sway_jitter``: 5.3 σ more in the faster), and is said as that
    (:func:`stamp_jitter`).  Otherwise None.
    """
    if not d:
        return None
    level = float(dist.norm.isf(noise_structure.COMMON_ALPHA / n_tests))
    named = (d["z"] > level and d["slow_z"] > level and d.get("median_z", math.inf) > level
             and d["share"] >= noise_structure.COMMON_SHARE
             and d["growth_z"] < COMMON_GROWTH_Z)
    return dict(d) if named else None


def judge_stars(v: NoiseVerdict, sn: StarNoise, default: float, size: tuple[int, int],
                n_tests: int, applied: NoiseScales | None = None) -> NoiseScales:
    """Fill the stars' part of ``v`` from ``sn``; return the scales to use for the stars.

    ``size``: the detector's (width, height), px (the column / row groups); ``applied``:
    the scales so far (default: as stated).
    """
    applied = v.stated if applied is None else applied
    known = ~sn.unknown
    v.unknown = int(sn.unknown.sum())
    v.default_px = default
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
        # (the messages' own σ: the σ used holds the groups kept from an earlier round too)
        said, k = (sn.sigma_px[known], v.stated.star) if sn.stated_px is None or \
            v.stated.group_by == "" else (sn.stated_px[known], 1.0)
        v.stated_sigma_px = float(np.median(said)) / k
        v.stated_sigma_range = tuple(float(x) / k for x in np.percentile(said, [5.0, 95.0]))
        v.star_p = p_two_sided(v.star, v.star_sigma)
        if v.star_p < ALPHA / n_tests and abs(v.star - 1.0) > MATERIAL:
            v.rejected.append("star")
            applied = applied.replace(star=v.stated.star * v.star, star_rho=0.0,
                                      star_ar_share=1.0)
        v.changes = changes_over_run(sn, v.star, v.star_sigma, v.stated.star, n_tests)
        if v.changes and "star" not in v.rejected:  # not as stated, whatever the window says
            v.rejected.append("star")
    sub = dataclasses.replace(sn, scale=v.star, sigma=v.star_sigma, dof=v.star_dof)
    # the groups are of the stars whose messages state a σ: a σ-0 star keeps its own
    # measured σ (above), which a group's factor would multiply (unseen case sigma0_faint:
    # faint σ-0 stars at 0.1 px in the groups of stated bright ones, the faint group's x1.98
    # applied on top of their measured 0.1 px, and rounds that compounded to "x0.582
    # (< 4.02 mag)" for bright stars stated right)
    # (no message states one: the groups are of every star, factors of the default σ,
    # which the σ-0 stars then take with the groups' factors instead of one measured σ)
    grouped = grouped_stars(sn)
    v.groups = known_groups(sub, size, v.stated)
    best = significant_grouping(v.groups, n_tests)
    # the stated σ wrong star by star (beyond the groups' steps): the groupings are then
    # judged with the stars as their units (a random factor per star made the rows' groups
    # "x0.889 .. x1.2 by magnitude", unseen case sigma_per_star)
    # (the test on the fit before the stars' own weights, :func:`levels_fit`)
    lv = levels_fit(sn)
    lgrouped = grouped_stars(lv)
    lev = star_levels(lv, lgrouped, None if best is None else group_index(lv, best))
    if lev is not None:
        # (merged and their σ with the stars as units too: the rows' σ of a group's scale
        # holds none of its stars' own levels, 0.08-0.19 x its scatter over draws of the
        # stars' factors, and merged by it the bins kept steps of random stars, 4.9 column
        # groups a draw for the truth's 2; the stars' σ 0.85-0.9 x, test_noise)
        v.groups = [dict(g, p_rows=g["p_value"], p_value=max(g["p_value"], (star_spread(
            lv, lgrouped, group_index(lv, g)) or {"groups_p": 1.0})["groups_p"]))
            for g in star_groups(sub, size, grouped, v.stated, stars=True)]
        best = significant_grouping(v.groups, n_tests)
        v.per_star = star_levels(lv, lgrouped,
                                 None if best is None else group_index(lv, best))
        if v.per_star is not None and "star" not in v.rejected:
            v.rejected.append("star")
    # (the σ growing with each star's image speed: said as itself, and the star-by-star
    # test above reads the rows over it, noise_stars.star_spread)
    v.speed = speed_variance(sn, grouped)
    v.frame_common = named_common(sn.common, n_tests) if v.speed is None else None
    if v.speed is not None and "star" not in v.rejected:
        v.rejected.append("star")
    if best is not None:
        overall = sub.group(grouped)[0]
        v.group = best
        ref = v.stated
        if not known.any() and ref.unknown_sigma_px > 0:
            # (every message says 0 and an earlier round gave them one measured σ: that is
            # the σ these groups are of, the default times its ratio; composed with the
            # stated scale, they gave the σ-0 stars the default times the groups' factors)
            ref = ref.replace(star=ref.unknown_sigma_px / default, unknown_sigma_px=0.0)
        applied, v.composed = _compose_groups(applied.replace(
            star=ref.star * overall, star_rho=0.0, star_ar_share=1.0), ref, best,
            overall, sub, grouped)
        if "star" not in v.rejected:
            v.rejected.append("star")
        # (a change over the run judged at each star's group's σ: the pooled scale moves
        # with the groups' shares of the stars, :func:`changes_over_run`)
        v.changes = changes_over_run(sn, v.star, v.star_sigma, v.stated.star, n_tests,
                                     group=best) if known.any() else None
    if known.any():
        # judged at each star's own group's scale when groups are applied: at the one
        # scale, the stars of a group above it are its "tails" (mag_faint_over2: "1 %
        # beyond the 99.9 % bound, p = 1e-37" for Gaussian noise)
        # (and against the share the stars' own σ have beyond it where the σ is wrong star
        # by star: a mixture of the stars' σ is heavy-tailed at any one, "0.82 % beyond",
        # sigma_per_star; judged at each star's own scale instead, a star's wide residuals
        # were its scale's, and true tails beside a per-star verdict went unsaid)
        v.tails = heavy_tails(sn, known, v.star if v.group is None else np.asarray(
            v.group["scales"], dtype=float)[group_index(sn, v.group)],
            v.per_star["spread"] if v.per_star else 0.0)
    if not known.any() and applied.group_by:
        # every σ-0 star in the groups (this round's or kept from before): the default σ
        # times the scale and its group's factor, not one measured σ
        if v.group is None:
            applied = applied.replace(star=v.stated.star * su)
        applied = applied.replace(unknown_sigma_px=0.0)
    # only where no field or per-star error is left: a missing effect that varies along a
    # star's track correlates its residuals too, and is no noise to inflate (measured: a
    # 30 ms rolling shutter on a swaying base read rho 0.57)
    v.correlated = noise_structure.correlated(
        sn.track_rho, sn.track_pairs, 2 * MATERIAL, sn.track_phi, sn.track_share,
        sn.track_factor_sigma) if sn.structure_p >= ALPHA and not sn.repeat_removed else None
    if v.correlated:
        # the scale a filter needs, and the correlation it stands for (a twin renders it)
        # σ-0 stars' noise is the same process: their measured scatter takes the factor too
        # (before, they kept the white scatter: ~1/3 of what the filter needs at ρ 0.81)
        k = v.correlated["sigma_scale"]
        c = v.correlated
        applied = applied.replace(star=applied.star * k, star_rho=c.get("phi", c["rho"]),
                                  star_ar_share=c.get("ar_share", 1.0),
                                  unknown_sigma_px=applied.unknown_sigma_px * k)
        if "star" not in v.rejected:
            v.rejected.append("star")
    return applied


#: the stars' σ before the window and in it differ materially beyond this ratio (measured on
#: the 26 unseen-case bags: 0.86-1.06 where the noise is stationary, the lowest a 30 ms
#: rolling shutter's motion-dependent shape; 2.00 for a noise that doubles mid-run)
CHANGES = 1.0 + 4 * MATERIAL


def changes_over_run(sn: StarNoise, window: float, sigma: float, stated: float,
                     n_tests: int, group: dict | None = None) -> dict[str, float] | None:
    """The stars' σ scale before the window against the window's, when it differs.

    The noise is measured in the evaluation window (the filter has converged there); a
    tracker whose noise changes with time (an exposure or a temperature changing mid-run)
    then reads as the window's scale alone, applied to the whole run (unseen case
    ``step2x``: 0.05 px as stated for the first half, 2x in the second: "looks 2.02 x too
    small", nothing said of the first half).  The same estimate on the stretch before the
    window (:func:`measure_stars`) is compared: different beyond :data:`CHANGES` and
    significant (two-sided, Bonferroni over ``n_tests``) where no field or per-star error
    is left (structure makes the within-frame scale depend on the motion), it is said.
    Scales are of the stated σ (× ``stated``).

    ``group``: the stars' σ groups applied (a :func:`star_groups` entry): both stretches
    are then judged at each star's group's σ, scales of the groups' σ (``by`` its
    variable).  The one pooled scale mixes the groups in the stars' shares, which change
    as the sky does (unseen case ``mag_inverted_bright``, the bright stars 4x the faint
    ones' σ: x0.502 at 75-150 s and x0.691 in the window, 0.489 and 0.693 the mixes'
    truth, "noise that changes with time" for a noise that does not).
    """
    b = sn.before
    if not b or not (np.isfinite(window) and window > 0) or sn.repeat_removed or \
            sn.structure_p < ALPHA:
        return None
    if group is not None:
        if sn.early is None:
            return None
        (window, sigma), (s, e) = (_at_groups(x, group) for x in (sn, sn.early))
        if not (np.isfinite(window) and window > 0 and np.isfinite(s) and np.isfinite(e)):
            return None
        b, stated = dict(b, scale=s, sigma=e), 1.0
    ratio = window / b["scale"] if b["scale"] > 0 else math.inf
    z = (window - b["scale"]) / math.hypot(sigma, b["sigma"])
    p = float(2.0 * dist.norm.sf(abs(z)))
    if not (p < ALPHA / n_tests and max(ratio, 1.0 / ratio) > CHANGES):
        return None
    out = {"before": b["scale"] * stated, "sigma_before": b["sigma"] * stated,
           "window": window * stated, "sigma_window": sigma * stated,
           "from_s": b["from_s"], "to_s": b["to_s"], "p_value": p}
    return out if group is None else dict(out, by=group["by"])


def _at_groups(sn: StarNoise, group: dict) -> tuple[float, float]:
    """(scale, σ) of ``sn``'s stars of known σ, each at its group's σ (``group``'s scales)."""
    known = ~sn.unknown
    f = np.asarray(group["scales"], dtype=float)[group_index(sn, group)]
    if known.sum() < 20 or not np.all(np.isfinite(f[known]) & (f[known] > 0)):
        return math.nan, math.nan
    at = dataclasses.replace(sn, q=np.where(known, sn.q / np.where(known, f, 1.0)**2, sn.q),
                             log_variance=None, groups_made=None)
    return at.group(known)[:2]


#: a star's within-frame residual (whitened, at the measured scale, ~χ²₂) beyond this is a
#: tail: χ²₂'s 99.9 % point, the log-likelihood's NIS cap
TAIL_BOUND = -2.0 * math.log(1e-3)
#: the tail share that is heavy: this many times Gaussian noise's 0.1 % (measured on the
#: 26 unseen-case bags' windows: 0.00-0.25 % where the noise is Gaussian at one σ, with or
#: without 3 % of 10-sigma outliers; 0.53 % where one third of the detector is 2x noisier,
#: a mixture; 1.31 % with a rolling shutter's structure left, which is not tested; 1.41 %
#: for Student-t noise of 3 dof)
TAILS = 8.0


def mixture_share(spread: float) -> float:
    """The share beyond :data:`TAIL_BOUND` of Gaussian noise whose variance is each star's.

    Each star's variance a factor ``f`` of the one scale's, lognormal of mean 1 and SD
    ``spread``: ``E[exp(−bound / 2f)]`` (Gauss–Hermite, 40 nodes): 0.1 % at 0, 0.14 % at
    0.15, 0.73 % at 0.6 (a σ wrong star by star by 30 %).
    """
    x, w = np.polynomial.hermite_e.hermegauss(40)
    s = math.sqrt(math.log1p(spread**2))
    f = np.exp(s * x - 0.5 * s**2)
    return float(np.sum(w * np.exp(-0.5 * TAIL_BOUND / f)) / np.sum(w))


def heavy_tails(sn: StarNoise, known: np.ndarray, scale: float | np.ndarray,
                spread: float = 0.0) -> dict[str, float] | None:
    """The share of stars beyond :data:`TAIL_BOUND` when it is heavy (else None).

    ``scale``: the measured scale, one or each star's (its group's).  ``spread``: where
    the σ is wrong star by star, the SD over their mean of the stars' variance factors
    (:func:`star_levels`): the share expected is then their mixture's
    (:func:`mixture_share`), and the tails must exceed it by what :data:`TAILS` asks
    beyond Gaussian noise's (``(TAILS − 1)`` x 0.1 %: unseen case ``sway_t4`` seed 23,
    Student-t of 4 dof beside a per-star verdict of chance, F 1.39, p 0.0045, spread
    0.15: 0.92 % beyond, 0.14 % expected of the mixture; ``sigma_per_star``, 30 %
    factors: 0.82 % beyond, 0.73 % expected).  Judged at each star's own scale instead,
    the row's own star's scale takes its wide residuals in: none was beyond there.

    Noise with heavy tails (Student-t: blends, cosmic rays, a PSF with wings) looks like
    Gaussian noise of a smaller σ plus "misidentified stars" the gate rejects (unseen case
    ``t3``: Student-t of 3 dof at the stated RMS read "sigma 1.19 x too large" and "218
    stars gated: misidentified stars").  The stars' within-frame residuals ``q / (m/2)``,
    at the measured scale, are χ²₂ under Gaussian noise: their share beyond its 99.9 %
    point is tested (binomial, one-sided) and must exceed :data:`TAILS` x the 0.1 %, where
    no field or per-star error is left (as for :func:`changes_over_run`).
    """
    scale = np.broadcast_to(np.asarray(scale, dtype=float), sn.q.shape)[known]
    if not np.all(np.isfinite(scale) & (scale > 0)) or sn.repeat_removed or \
            sn.structure_p < ALPHA:
        return None  # structure left in the residuals is no tail of the noise
    q, m = sn.q[known], sn.m[known]
    ok = m > 0
    n = int(ok.sum())
    if n < 200:
        return None
    x = q[ok] / (0.5 * m[ok] * scale[ok]**2)
    k = int(np.sum(x > TAIL_BOUND))
    expected = math.exp(-0.5 * TAIL_BOUND)
    heavy = TAILS * expected
    if spread > 0:
        expected = mixture_share(spread)
        heavy = expected + (TAILS - 1.0) * math.exp(-0.5 * TAIL_BOUND)
    p = float(dist.binom.sf(k - 1, n, expected))
    if not (k > heavy * n and p < ALPHA):
        return None
    return {"share": k / n, "expected": expected, "p_value": p}


#: the model is too far off for the noise to be measured when its innovations, with the
#: stars' measured σ, are still this over-dispersed (NIS/dof), or the filter lost lock
MAX_DISPERSION = 2.0


def far_off(base, sn: StarNoise | None, calibration=None, fraction: float = 0.5,
            verdict: NoiseVerdict | None = None) -> str:
    """Why a run is too far from its model for the noise to be measured on it ('' if not).

    A missing effect that moves the stars far from their predictions (a 20 ms time offset
    under rotation: NIS/dof in the hundreds, lost lock) also bends the within-frame
    residuals and the likelihood the scales are measured from: the noise is then measured
    once the model is closer (the next round of ``discover``), not guessed from a broken run.

    Where a noise in the frames' stamps makes that misfit (:func:`stamp_jitter`: ``base``'s
    residuals, ``calibration``'s camera, the last ``fraction`` of the run), the reason names
    it, a noise, not a missing effect; the scales are still not measured (a larger gyro
    noise would let the attitude follow the stamps' errors); ``verdict`` given keeps it
    (:attr:`NoiseVerdict.stamp_jitter`).
    """
    if not base.ok or not base.window:
        return "the model's run failed"
    lost = base.lost_lock
    s, nis = misfit(base, sn)
    if lost or not np.isfinite(nis) or nis > MAX_DISPERSION:
        at = "" if abs(s - 1.0) <= MATERIAL else f" at the stars' measured sigma, x{s:.3g}"
        jitter = None if lost or not np.isfinite(nis) else \
            stamp_jitter(base, calibration, fraction, s, nis)
        if jitter is not None:
            if verdict is not None:
                verdict.stamp_jitter = jitter
            return (f"the frames' stamps jitter {jitter['ms']:.2g} ms rms (the stars' spread "
                    f"along their image motion, p = {jitter['p_value']:.2g}): a noise in "
                    "time, not in the stars' positions, that the model does not state "
                    f"(outside the library); it makes NIS/dof {nis:.3g}{at}, "
                    f"{nis - jitter['nis_share']:.3g} without it; taken as stated (use "
                    f"--noise-scale stamp={jitter['ms']:.2g} to state it)")
        return (f"the model is too far off (NIS/dof {nis:.3g}{at}"
                + (", the filter lost lock" if lost else "") + "): a missing effect shapes "
                "the residuals more than the noise does; taken as stated until it is added")
    return ""


def misfit(base, sn: StarNoise | None) -> tuple[float, float]:
    """``(s, NIS/dof)``: the stars' measured σ scale and ``base``'s misfit at it.

    The number decided on is the one printed (the run's own NIS/dof also held the stated
    σ's error: stars stated at half their σ and a 100x gyro noise printed 44.5 where the
    NIS/dof at the true σ is 11.2).
    """
    s = sn.scale if sn is not None and sn.scale > 0 else 1.0
    return s, base.window["nis"]["mean"] / 2.0 / s**2


#: a noise in the frames' stamps is named (:func:`stamp_jitter`) at this one-sided p, where
#: the model's NIS/dof less its share is within :data:`MAX_DISPERSION`
STAMP_ALPHA = ALPHA


def stamp_jitter(base, calibration, fraction: float, scale: float, nis: float
                 ) -> dict[str, float] | None:
    """The frames' stamps' noise that makes ``base``'s misfit, or None.

    ``{ms, p_value, nis_share}``: :func:`~stellar_cal_ros.diagnosis.clock.stamp_share` on
    the window's accepted stars (``nis_share`` at the stars' measured σ ``scale``, as
    ``nis``).  Named where it is significant (one-sided p < :data:`STAMP_ALPHA`) and the
    NIS/dof ``nis`` less its share is within :data:`MAX_DISPERSION`: the misfit is that
    noise (unseen case ``sway_jitter`` s22: 0.97 ms, NIS/dof 5.86, 1.00 without it).  None
    without ``base``'s residuals or ``calibration``.
    """
    from stellar_cal_ros.diagnosis.clock import stamp_share
    from stellar_cal_ros.diagnosis.stats import evaluation_mask

    res = getattr(base, "residuals", None)
    if res is None or calibration is None:
        return None
    cam = calibration.camera
    got = stamp_share(res, evaluation_mask(res, fraction), (cam.fx, cam.fy), (cam.cx, cam.cy),
                      calibration.R_imu_st)
    if got is None or not got[0] < STAMP_ALPHA:
        return None
    share = got[2] / scale**2
    if not nis - share <= MAX_DISPERSION:
        return None
    return {"ms": got[1] * 1e3, "p_value": got[0], "nis_share": share}


#: the star-by-star repeat's source in a round's progress lines (:meth:`NoiseVerdict.lines`'s
#: ``pending``), before the 'unexplained' lines have told whether it follows one of them
PENDING_SOURCE = ("whose source the 'unexplained' lines tell at the end (a field on the "
                  "detector they find, which a star keeps along its track; else the "
                  "catalogue positions or the identification)")


def repeat_reason(rms_px: float, follows: str = "", pending: bool = False) -> str:
    """:func:`structured`'s reason where the stars' residuals repeat star by star.

    ``follows``: the cause the repeat follows (its 'unexplained' line, ``output``'s
    ``causes_first``: a star keeps its place on the detector along its track), said
    instead of the per-star errors (unseen case ``stray_light`` s21: the repeat follows
    the smooth structure over the detector's rows, and the line blamed the per-star errors).
    ``pending``: before the 'unexplained' lines are tested (a round's progress,
    :meth:`NoiseVerdict.lines`): neither said.
    """
    what = (f"the displacement the {follows} makes of the stars in view (its 'unexplained' "
            "line)" if follows else
            "that repeating displacement of the stars in view (its source: with the "
            "'unexplained' lines at the end)" if pending else
            "the per-star errors of the stars in view")
    return (f"the stars' residuals repeat star by star ({rms_px:.2g} px rms): the attitude "
            f"follows {what}, which a larger gyro noise would absorb")


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
        return repeat_reason(sn.repeat_removed)
    if p >= ALPHA:
        return ""
    # the field's rms per axis over the noise's: the χ²'s excess over its dof (the cells'
    # means of noise alone make the dof; counted in, a 0.12 σ checkerboard read 0.19)
    rms = math.sqrt(max(sn.structure - sn.structure_dof, 0.0) / max(float(sn.m.sum()), 1.0))
    # (whether the stars' tracks share it: the same χ² against sign flips of whole tracks,
    # exact but blind where a cell holds one star's track, noise_stars.StarNoise.structure_p)
    shared = "" if sn.structure_flip_p is None else \
        f"; across the stars' tracks p = {sn.structure_flip_p:.2g}"
    return (f"the stars show a repeating field (cell means chi2 {sn.structure:.0f} / "
            f"{sn.structure_dof} dof, p = {p:.2g}{shared}, {rms:.2g} x the noise rms): a "
            "missing effect, measured again once it is added")


def star_lines(res: Table, mask: np.ndarray, fx: float, fy: float,
               centre: tuple[float, float], R_imu_st: np.ndarray | None = None,
               sn: StarNoise | None = None) -> list:
    """The 'unexplained' tests that rest on the stars' noise, from one estimate of it.

    :func:`repeat_finding`'s test (if any) and the periodic frame-mean tests
    (:func:`~stellar_cal_ros.diagnosis.stats.periodic_findings`), these referred to a red
    spectrum when the stars' residuals are correlated from frame to frame along their
    tracks (lag-1 ρ above 3 of its σ, :func:`~.noise_structure.correlated` without its
    materiality): such noise makes the frame means red, and their flat reference called
    that a period (unseen case ``ar1``, 150 s, seeds 25, 28, 30, 35: Bonferroni p 8.6e-6,
    7.7e-5, 1.2e-6, 1.0e-6).  White noise keeps the flat reference, and a wobble its power.
    ``sn``: that estimate (:func:`line_noise`) when the caller has it.
    """
    from stellar_cal_ros.diagnosis.stats import periodic_findings

    sn = line_noise(res, mask, fx, fy, centre, R_imu_st) if sn is None else sn
    red = track_lags(sn) is not None
    rep = repeat_finding(sn)
    return ([rep] if rep is not None else []) + pattern_findings(sn) \
        + periodic_findings(res, mask, red)


#: the 'unexplained' regressor of a fixed pattern on each axis (:func:`pattern_findings`)
PATTERN_REGRESSOR = {"u": "u (column) (fixed pattern, bands of {band} px)",
                     "v": "v (row) (fixed pattern, bands of {band} px)"}


def pattern_findings(sn: StarNoise | None) -> list:
    """The 'unexplained' tests of a centroid offset fixed to detector columns (rows).

    Those of :func:`~.noise_stars.detector_patterns` that fired (removed before the stars'
    noise was measured: a structure, not noise; the tests that did not fire are not added to
    the family, whose other lines then keep their adjusted p).  Each a
    :class:`~stellar_cal_ros.diagnosis.stats.RegressorFinding` (regressor ``u (column)
    (fixed pattern, ...)`` on u, ``v (row) ...`` on v, statistic the flips' z, p unadjusted,
    size the offset in px from its neighbours of a band's window slid to the pattern's
    phase, the pixels' offsets fitted through the frames' attitude fit:
    :func:`~.noise_stars._pattern_size`).
    """
    from stellar_cal_ros.diagnosis.stats import RegressorFinding

    if sn is None:
        return []
    band = noise_structure.PATTERN_BAND_PX
    return [RegressorFinding(PATTERN_REGRESSOR[t["axis"]].format(band=band), t["axis"],
                             float(t["z"]), float(t["p"]), float(t["size_px"]))
            for t in sn.patterns if t["removed"]]


def without_patterns(res: Table, sn: StarNoise | None) -> Table:
    """``res`` with the detector's fixed patterns ``sn`` removed taken out of its residuals.

    The 'unexplained' regressor tests read what is left of a pattern that was found
    (:func:`pattern_findings`' line says it): left in, a pattern of bands echoes as ripples
    over the same axis (unseen case ``rows``, seed 21: ``v vs v (row) (periodic 512 px)``
    t −7.1 ranked before the pattern's own line).  ``res`` itself where none was removed.
    """
    if sn is None or sn.pattern_px is None:
        return res
    return dict(res, du=np.asarray(res["du"], dtype=float) - sn.pattern_px[:, 0],
                dv=np.asarray(res["dv"], dtype=float) - sn.pattern_px[:, 1])


def track_lags(sn: StarNoise | None) -> tuple[float, float] | None:
    """``(w, φ)``: the stars' noise correlated ``w φ^l`` at lag ``l`` along their tracks.

    Where the tracks' lag-1 ρ is above 3 of its σ (:func:`~.noise_structure.correlated`
    without its materiality, as :func:`star_lines`' red reference); ``None`` for white
    tracks.  A pure AR(1) is ``(1, ρ)``, white + AR(1) its share and coefficient
    (:func:`~.noise_structure.track_model`).  What the structure tests take
    (:func:`~stellar_cal_ros.diagnosis.stats.frame_robust_t`'s ``track_lags``).
    """
    if sn is None or noise_structure.correlated(sn.track_rho, sn.track_pairs, 0.0) is None:
        return None
    return (float(sn.track_share),
            float(sn.track_rho if sn.track_phi is None else sn.track_phi))


def line_noise(res: Table, mask: np.ndarray, fx: float, fy: float,
                centre: tuple[float, float], R_imu_st: np.ndarray | None,
                readout: str = "v"):
    """:func:`~.noise_stars.star_noise` of ``mask``'s accepted stars at the run's own σ.

    ``readout``: the rolling shutter's direction it takes out where significant
    (:func:`~stellar_cal_ros.diagnosis.stats.readout_axis`).
    """
    ok = mask & ~np.asarray(res["gated"]).astype(bool)
    if ok.sum() < 20:
        return None
    sig = np.sqrt(np.maximum(0.5 * (np.asarray(res["s_uu"], dtype=float)
                                    + np.asarray(res["s_vv"], dtype=float)), 1e-300))
    # (σ on every row: the detector's fixed-pattern test reads the run beyond the window,
    # noise_stars.detector_patterns; the noise itself the window's ``ok`` rows)
    return star_noise(res, sig, np.ones(len(sig)), ok, fx, fy, centre, R_imu_st,
                      readout=readout)


def repeat_finding(sn: StarNoise | None):
    """The 'unexplained' test of an error that repeats star by star.

    ``sn``: :func:`star_lines`' estimate of the stars' noise: the run's innovations of the
    evaluation window's accepted stars, whitened by their predicted σ, minus the frame's
    attitude fit, a rolling shutter's shape where it is significant (with the installation:
    the shutter repeats star by star, a star's row and image velocity repeating along its
    track; without it, 30 ms read as 'catalogue star' p 9e-93 ranked before the shutter's
    own line) and the detector cells' means (the steps of :func:`~.noise_stars.star_noise`),
    then the χ² of the per-star means beyond the cells' against its exact dof
    (:func:`~.noise_stars.star_after_cells`).  Returns a
    :class:`~stellar_cal_ros.diagnosis.stats.RegressorFinding` (regressor ``catalogue
    star``, statistic ``(χ² − dof) / √(2 dof)``, unadjusted one-sided p, size = the per-star
    error's RMS per axis, px), or None when there is nothing to test.
    """
    from stellar_cal_ros.diagnosis.stats import RegressorFinding

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
    a residual *spread* (the ``size`` component) that still varies with that regressor is the
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


def not_measured(scales: NoiseScales, fit: dict[str, Any] | None = None) -> dict[str, Any]:
    """The ``noise`` block of a diagnosis that measured no noise scale itself.

    With ``--noise stated``, or with a batch method (``bundle``: no noise verdict is measured
    for it; its fit scales the stars' σ by its own variance factor).  ``fit``: that
    fit's block of the run's calibration (``extra["fit"]``: ``variance_factor``, ``stars``,
    ``sigma_px``); with it the stars' scale is the factor's root, said with its σ (a χ² of
    2 × stars dof).  "noise not measured (--noise stated)" was printed for a camera-only
    ``discover --method bundle`` whose messages stated 0.6x the true σ, without the option
    (unseen case ``bundle_s06``; the fit's own factor read x1.68).
    """
    d = scales.as_dict()
    names = ("star_sigma_scale", "gyro_noise_scale", "accel_noise_scale")
    out = {**{k: d[k] for k in names}, "sigma": {k: None for k in names},
           "measured": {k: False for k in names}, "rescaled": not scales.identity, "applied": d,
           "verdict": ["noise not measured (--noise stated)"]}
    vf = float((fit or {}).get("variance_factor") or math.nan)
    if not (math.isfinite(vf) and vf > 0):
        return out
    k = scales.star * math.sqrt(vf)
    sk = k / math.sqrt(2.0 * max(2.0 * float(fit.get("stars") or 0), 1.0))
    fitted = float(fit.get("sigma_px") or math.nan)
    px = (f" ({fitted / k:.3g} -> {fitted:.3g} px)" if math.isfinite(fitted) else "")
    line = ("the stars' sigma is the batch fit's own (its variance factor; a batch method "
            "measures no IMU noise): ")
    if abs(k - 1.0) > MATERIAL:
        line += (f"it looks {k:.3g} +- {sk:.2g} x too {'small' if k > 1 else 'large'}{px}; "
                 "the fit's sigma already carry it")
    else:
        line += f"noise as stated (stars' sigma x{k:.3g} +- {sk:.2g})"
    applied = {**d, "star_sigma_scale": k}
    out.update(star_sigma_scale=k, applied=applied, verdict=[line],
               rescaled=bool(out["rescaled"] or abs(k - 1.0) > MATERIAL))
    out["sigma"]["star_sigma_scale"] = sk
    out["measured"]["star_sigma_scale"] = True
    return out


def stale(sn: StarNoise | None) -> bool:
    """Whether a run's stars show a σ scale clearly other than the one it applied."""
    if sn is None:
        return False
    known = ~sn.unknown
    if not known.any():
        return False
    s, e, _ = sn.group(known)
    return bool(p_two_sided(s, e) < ALPHA and abs(s - 1.0) > MATERIAL)
