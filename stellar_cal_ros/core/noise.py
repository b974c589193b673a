"""Noise scales: the noise a run uses, as multiples of the noise the data and the prior state.

Users' noise figures are guesses (the stars' ``sigma`` field, the gyro's angle random walk
of a datasheet), and a tracker may send ``sigma = 0`` for "unknown".  A run applies
:class:`NoiseScales` to what is stated:

* every star's σ: the message's σ times :attr:`NoiseScales.star`, times the factor of its
  group (magnitude, image-radius, column or row bins) when the data asked for groups; when
  the message's σ is 0, :attr:`NoiseScales.unknown_sigma_px` if measured (its own: no group
  factor), else the configured default times :attr:`NoiseScales.star` and its group's factor;
* the gyro's angle random walk times :attr:`NoiseScales.gyro`, the accelerometer's velocity
  random walk times :attr:`NoiseScales.accel`;
* the gyro bias's random walk :attr:`NoiseScales.gyro_bias_rw` (deg/h/√h; 0: the constant
  bias the model states), the process noise of the ``gyro_bias`` block;
* a noise in the frames' stamps :attr:`NoiseScales.stamp_ms` (ms rms; 0: exact stamps): one
  error per frame, shared by its stars, which the frame's measurement covariance carries
  (:func:`~stellar_cal_ros.core.covariance.stamp_column`);
* a shift common to all stars of a frame :attr:`NoiseScales.frame_px` (px rms per axis; 0:
  none): one error per frame and axis, white between frames, which the frame's measurement
  covariance carries as ``σ_f² I₂`` in every pair of its stars
  (:func:`~stellar_cal_ros.core.covariance.common_columns`).

1.0 everywhere is "as stated".  The diagnosis measures the scales from the run itself
(:mod:`stellar_cal_ros.diagnosis.noise`); ``replay --noise-scale`` applies them.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

import numpy as np


def long_run(rho: float, share: float = 1.0) -> float:
    """The long-run factor ``(1 − w) + w (1 + ρ)/(1 − ρ)`` of white + AR(1) noise.

    Lags ``ρ_k = w ρ^k``: what a track's mean varies more than ``1/n`` as ``n`` grows, and
    the variance a filter that takes the noise as white must take (``share`` 1:
    ``(1 + ρ)/(1 − ρ)``, a pure AR(1)).  The one formula of :attr:`NoiseScales.star_inflation`
    and of the diagnosis (:mod:`~stellar_cal_ros.diagnosis.noise_structure`).
    """
    ar = (1.0 + rho) / (1.0 - rho)
    return ar if share == 1.0 else (1.0 - share) + share * ar

#: star groups a scale may depend on
GROUP_KINDS = ("magnitude", "radius", "column", "row")

#: what a group spec of ``--noise-scale`` looks like (:meth:`NoiseScales.parse`'s errors, the
#: CLI's help): the groups stand alone, ``unknown=`` is not part of them
GROUP_SPEC = ("a group spec is by=magnitude|radius|column|row,edges=E1/E2,factors=F0/F1/F2 "
              "(edges increasing, in mag or px; one factor more than edges, each of the "
              "messages' sigma; '/' between numbers), e.g. "
              "by=magnitude,edges=4.5,factors=1/0.5")
#: the items ``--noise-scale`` takes
SCALE_SPEC = ("star=S, gyro=G, accel=A, unknown=PX, rho=R, share=W, gyro_bias_rw=D "
              "(deg/h/sqrt(h)), stamp=MS (the frames' stamps' noise, ms rms), frame=PX (a "
              "shift all stars of a frame share, px rms per axis), or a group spec "
              "by=magnitude|radius|column|row,edges=E1/E2,factors=F0/F1/F2")


def _check_groups(values: dict[str, Any]) -> None:
    """A group spec of :meth:`NoiseScales.parse` whole: ``by=``, ``edges=``, ``factors=``.

    One line saying what is missing or wrong and what a group spec looks like
    (:data:`GROUP_SPEC`); the values themselves are checked by the class.
    """
    by = values.get("group_by", "")
    edges, factors = values.get("edges"), values.get("factors")
    if by not in GROUP_KINDS:
        why = "by= is missing" if not by else f"by={by!r} is not a grouping"
    elif factors is None:
        why = "factors= is missing"
    elif edges is None and len(factors) != 1:
        why = "edges= is missing"
    elif len(factors) != len(edges or ()) + 1:
        why = f"{len(edges or ())} edges need {len(edges or ()) + 1} factors, got {len(factors)}"
    else:
        return
    raise ValueError(f"--noise-scale: {why}; {GROUP_SPEC}")


@dataclass(frozen=True)
class NoiseScales:
    """Multipliers of the stated noise (1.0: as stated)."""

    star: float = 1.0  #: every star's σ
    gyro: float = 1.0  #: the gyro's angle random walk
    accel: float = 1.0  #: the accelerometer's velocity random walk
    #: σ (px) of stars whose message says 0 ("unknown"); 0: the configured default × star
    unknown_sigma_px: float = 0.0
    #: "", "magnitude", "radius" (px from the image centre), "column" or "row" (px)
    group_by: str = ""
    edges: tuple[float, ...] = ()  #: bin edges of the groups (ascending)
    factors: tuple[float, ...] = ()  #: one factor per group, len(edges) + 1
    #: lag-one correlation of each star's centroid noise from frame to frame, as measured
    #: (0: white); ``star`` then holds √((1 + ρ)/(1 − ρ)) on top of the stars' scatter
    #: within frames, the white stand-in a filter needs (:meth:`within_frames` undoes it).
    #: With :attr:`star_ar_share` below 1: the coefficient of the AR(1) part of white +
    #: AR(1) noise (lags ``w ρ^k``), the factor √((1 − w) + w (1 + ρ)/(1 − ρ))
    star_rho: float = 0.0
    #: the AR(1)'s share ``w`` of the stars' noise variance, the rest white (1: pure AR(1))
    star_ar_share: float = 1.0
    #: the gyro bias's random walk, deg/h/√h per axis (0: a constant bias, as the model
    #: states): the process noise of the ``gyro_bias`` block where it is estimated
    gyro_bias_rw: float = 0.0
    #: σ of the noise in the frames' stamps, ms (0: exact stamps): one error per frame, the
    #: same for all its stars, in each frame's R as ``σ_t² J_t J_tᵀ``
    #: (:func:`~stellar_cal_ros.core.covariance.stamp_column`)
    stamp_ms: float = 0.0
    #: σ of a shift all stars of a frame share, px per axis (0: none): one error per frame
    #: and axis, white between frames, in each frame's R as ``σ_f² I₂`` between every two
    #: of its stars and on each (:func:`~stellar_cal_ros.core.covariance.common_columns`)
    frame_px: float = 0.0

    def __post_init__(self) -> None:
        for name in ("star", "gyro", "accel"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"noise scale {name} must be a positive number, got {v!r}")
        if not (math.isfinite(self.unknown_sigma_px) and self.unknown_sigma_px >= 0):
            raise ValueError(f"unknown star sigma must be >= 0 px, got {self.unknown_sigma_px!r}")
        if self.group_by and self.group_by not in GROUP_KINDS:
            raise ValueError(f"star groups by {self.group_by!r}: use one of {GROUP_KINDS}")
        if self.group_by and len(self.factors) != len(self.edges) + 1:
            raise ValueError("star groups need one factor per bin (len(edges) + 1)")
        if any(not math.isfinite(e) for e in self.edges) \
                or any(b < a for a, b in zip(self.edges[:-1], self.edges[1:], strict=True)):
            # a bin is found by a sorted search: unsorted edges would give stars another
            # bin's factor, silently
            raise ValueError(f"star group edges must be finite and increasing, got {self.edges!r}")
        if any(not (math.isfinite(f) and f > 0) for f in self.factors):
            raise ValueError(f"star group factors must be positive, got {self.factors!r}")
        if not (math.isfinite(self.star_rho) and 0.0 <= self.star_rho < 1.0):
            raise ValueError(f"star noise correlation must be in [0, 1), got {self.star_rho!r}")
        if not (math.isfinite(self.star_ar_share) and 0.0 <= self.star_ar_share <= 1.0):
            raise ValueError(f"star noise AR(1) share must be in [0, 1], got "
                             f"{self.star_ar_share!r}")
        if not (math.isfinite(self.gyro_bias_rw) and self.gyro_bias_rw >= 0.0):
            raise ValueError(f"gyro bias random walk must be >= 0 deg/h/sqrt(h), got "
                             f"{self.gyro_bias_rw!r}")
        if not (math.isfinite(self.stamp_ms) and self.stamp_ms >= 0.0):
            raise ValueError(f"stamp noise must be >= 0 ms, got {self.stamp_ms!r}")
        if not (math.isfinite(self.frame_px) and self.frame_px >= 0.0):
            raise ValueError(f"frame-common noise must be >= 0 px, got {self.frame_px!r}")

    @property
    def identity(self) -> bool:
        """Nothing rescaled."""
        return (self.star == 1.0 and self.gyro == 1.0 and self.accel == 1.0
                and not self.unknown_sigma_px and not self.group_by and not self.star_rho
                and not self.gyro_bias_rw and not self.stamp_ms and not self.frame_px)

    @property
    def stars_as_stated(self) -> bool:
        """The stars' σ as their messages state it (:meth:`star_sigma` changes none).

        The IMU's scales, a gyro bias walk and the stars' correlation may differ: they act
        in the filter, not on a frame's σ (the IMU noise search's runs, H192).
        """
        return self.star == 1.0 and not self.unknown_sigma_px and not self.group_by

    def replace(self, **changes: Any) -> NoiseScales:
        """A copy with ``changes``."""
        return dataclasses.replace(self, **changes)

    @property
    def star_inflation(self) -> float:
        """√((1 + ρ)/(1 − ρ)): the factor ``star`` holds for the stars' correlated noise.

        White + AR(1) (:attr:`star_ar_share` ``w`` < 1): √((1 − w) + w (1 + ρ)/(1 − ρ)), the
        long-run factor (:func:`long_run`).
        """
        return math.sqrt(long_run(self.star_rho, self.star_ar_share))

    def star_lags(self) -> tuple[float, float, float]:
        """``(ρ₁, n·var(r₁), 1 + 2 Σ ρ_k²)`` of the stars' declared noise over frames.

        ρ_k = w ρ^k (``w`` = :attr:`star_ar_share`, ρ = :attr:`star_rho`; w = 1: a pure AR(1),
        w = 0 or ρ = 0: white).  ρ₁ = w ρ is the lag-1 correlation the frames' mean
        innovations keep; n·var(r₁) is Bartlett's variance of its estimate from n frames,
        Σ_{k≥1} (ρ_{k+1} + ρ_{k−1} − 2 ρ₁ ρ_k)² = (1 + w ρ² − 2 w² ρ²)²
        + w² ρ² (1 + ρ² − 2 w ρ²)² / (1 − ρ²) (1 − ρ² for a pure AR(1)); the last is the
        factor on the variance of a mean of squares (a Gaussian's squares correlate by ρ_k²,
        lags w² ρ^(2k)): :func:`long_run` (ρ², w²), (1 + ρ²)/(1 − ρ²) for a pure AR(1).
        """
        rho, w = self.star_rho, self.star_ar_share
        r2 = rho * rho
        bartlett = ((1.0 + w * r2 - 2.0 * w * w * r2) ** 2
                    + w * w * r2 * (1.0 + r2 - 2.0 * w * r2) ** 2 / (1.0 - r2))
        return w * rho, bartlett, long_run(r2, w * w)

    def within_frames(self) -> NoiseScales:
        """The scales of the stars' noise within one frame (its marginal σ), white.

        ``star`` and the σ of stars whose message says 0 without :attr:`star_inflation`
        (both carry it under correlated noise).  What a bag with this noise has in each
        frame (the twin renders it, correlated by :attr:`star_rho` along each star's track).
        """
        k = self.star_inflation
        return self.replace(star=self.star / k, unknown_sigma_px=self.unknown_sigma_px / k,
                            star_rho=0.0, star_ar_share=1.0)

    def group_of(self, magnitude: np.ndarray, uv: np.ndarray,
                 centre: tuple[float, float]) -> np.ndarray:
        """Group index of each star (0 when there are no groups)."""
        n = len(uv)
        if not self.group_by:
            return np.zeros(n, dtype=int)
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        x = {"magnitude": lambda: np.asarray(magnitude, dtype=float),
             "radius": lambda: np.hypot(uv[:, 0] - centre[0], uv[:, 1] - centre[1]),
             "column": lambda: uv[:, 0], "row": lambda: uv[:, 1]}[self.group_by]()
        # a star of unknown magnitude goes to the middle group
        idx = np.searchsorted(np.asarray(self.edges, dtype=float), np.nan_to_num(
            x, nan=float(np.median(self.edges)) if self.edges else 0.0), side="right")
        return idx

    def times_groups(self, by: str, edges: tuple[float, ...], factors: tuple[float, ...]
                     ) -> NoiseScales:
        """These scales with every star's group factor multiplied by ``factors`` of ``by``.

        A later measurement of the stars' σ is relative to the σ these scales give: groups it
        finds compose with the groups kept (the bins of both, each the product of its two
        factors), they do not replace them.  Groups of another variable than :attr:`group_by`
        cannot be one grouping: ValueError (the caller folds them, :func:`~stellar_cal_ros.
        diagnosis.noise.judge_stars`).
        """
        if self.group_by and self.group_by != by:
            raise ValueError(f"star groups by {by!r} on groups by {self.group_by!r}")
        old_e = np.asarray(self.edges if self.group_by else (), dtype=float)
        old_f = np.asarray(self.factors if self.group_by else (1.0,), dtype=float)
        new_e, new_f = np.asarray(edges, dtype=float), np.asarray(factors, dtype=float)
        e = np.unique(np.concatenate([old_e, new_e]))
        # each bin of the union lies inside one bin of each: its lower edge (or below the
        # first) finds both
        x = np.concatenate([[e[0] - 1.0], e]) if len(e) else np.zeros(1)
        f = old_f[np.searchsorted(old_e, x, side="right")] \
            * new_f[np.searchsorted(new_e, x, side="right")]
        return self.replace(group_by=by, edges=tuple(float(v) for v in e),
                            factors=tuple(float(v) for v in f))

    def star_sigma(self, sigma: np.ndarray, default: float, magnitude: np.ndarray,
                   uv: np.ndarray, centre: tuple[float, float]) -> np.ndarray:
        """σ (px) a run uses for stars whose messages state ``sigma`` (0: unknown)."""
        s = np.asarray(sigma, dtype=float)
        unknown = self.unknown_sigma_px if self.unknown_sigma_px > 0 else default * self.star
        out = np.where(s > 0, s * self.star, unknown)
        if self.group_by:
            f = np.asarray(self.factors, dtype=float)[self.group_of(magnitude, uv, centre)]
            # (a σ-0 star's measured σ is its own, measured beside the groups, not in them)
            out = out * np.where((s > 0) | (self.unknown_sigma_px <= 0), f, 1.0)
        return out

    def apply(self, config: Any) -> Any:
        """``config`` (a filter configuration) with these scales: ARW, VRW, star σ."""
        changes: dict[str, Any] = {"noise": self}
        if hasattr(config, "gyro_arw_deg_sqrth"):
            changes["gyro_arw_deg_sqrth"] = config.gyro_arw_deg_sqrth * self.gyro
        if hasattr(config, "accel_vrw_mps_sqrth"):
            changes["accel_vrw_mps_sqrth"] = config.accel_vrw_mps_sqrth * self.accel
        return dataclasses.replace(config, **changes)

    # ------------------------------------------------------------------ files
    def as_dict(self) -> dict[str, Any]:
        """The calibration file's / diagnosis.json's form (contract §5 names)."""
        out: dict[str, Any] = {"star_sigma_scale": float(self.star),
                               "gyro_noise_scale": float(self.gyro),
                               "accel_noise_scale": float(self.accel)}
        if self.unknown_sigma_px:
            out["unknown_star_sigma_px"] = float(self.unknown_sigma_px)
        if self.group_by:
            out["star_sigma_groups"] = {"by": self.group_by,
                                        "edges": [float(e) for e in self.edges],
                                        "scales": [float(f) for f in self.factors]}
        if self.star_rho:
            out["star_correlated"] = {"rho": float(self.star_rho),
                                      "sigma_scale": float(self.star_inflation)}
            if self.star_ar_share != 1.0:
                out["star_correlated"]["ar_share"] = float(self.star_ar_share)
        if self.gyro_bias_rw:
            out["gyro_bias_rw_deg_h_sqrth"] = float(self.gyro_bias_rw)
        if self.stamp_ms:
            out["stamp_sigma_ms"] = float(self.stamp_ms)
        if self.frame_px:
            out["frame_sigma_px"] = float(self.frame_px)
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> NoiseScales:
        """Inverse of :meth:`as_dict` (missing keys: 1.0 / none)."""
        d = d or {}
        groups = d.get("star_sigma_groups") or {}
        rho = float((d.get("star_correlated") or {}).get("rho", 0.0) or 0.0)
        share = float((d.get("star_correlated") or {}).get("ar_share", 1.0))
        return cls(float(d.get("star_sigma_scale", 1.0)), float(d.get("gyro_noise_scale", 1.0)),
                   float(d.get("accel_noise_scale", 1.0)),
                   float(d.get("unknown_star_sigma_px", 0.0) or 0.0),
                   str(groups.get("by", "")), tuple(float(e) for e in groups.get("edges", ())),
                   tuple(float(f) for f in groups.get("scales", ())), rho, share,
                   float(d.get("gyro_bias_rw_deg_h_sqrth", 0.0) or 0.0),
                   float(d.get("stamp_sigma_ms", 0.0) or 0.0),
                   float(d.get("frame_sigma_px", 0.0) or 0.0))

    @classmethod
    def parse(cls, text: str) -> NoiseScales:
        """``star=1.67,gyro=5,accel=1,unknown=0.05,rho=0.81`` (the command line's form).

        ``by=magnitude,edges=4.51,factors=1/0.5``: the stars' σ groups (:attr:`group_by`,
        :attr:`edges`, :attr:`factors`), as the diagnosis advises them (:meth:`advice`).

        ``rho``: the stars' noise correlated from frame to frame (lag-1 ρ of each star's
        track, :attr:`star_rho`), ``star`` then the whole scale a white-noise filter needs
        (the diagnosis's advice for correlated noise, ``star=K,rho=R``): the run's
        consistency judges its NIS and whiteness against that correlation.  ``share``:
        white + AR(1) noise, ``rho`` then the AR(1)'s coefficient and ``share`` its part of
        the variance (:attr:`star_ar_share`; the advice prints ``star=K,rho=R,share=W``).
        ``gyro_bias_rw``: the gyro bias's random walk, deg/h/√h (:attr:`gyro_bias_rw`).
        ``stamp``: the frames' stamps' noise, ms rms (:attr:`stamp_ms`).  ``frame``: a
        shift all stars of a frame share, px rms per axis (:attr:`frame_px`).
        """
        keys = {"star": "star", "gyro": "gyro", "accel": "accel",
                "unknown": "unknown_sigma_px", "rho": "star_rho", "share": "star_ar_share",
                "gyro_bias_rw": "gyro_bias_rw", "stamp": "stamp_ms", "frame": "frame_px"}
        values: dict[str, Any] = {}
        last = ""
        for item in text.replace(";", ",").split(","):
            if not item.strip():
                continue
            key, sep, val = item.partition("=")
            key = key.strip()
            if not sep and last in ("edges", "factors"):
                raise ValueError(f"--noise-scale {last}: numbers separated by '/', not ',' "
                                 f"(got {item!r} after it); {GROUP_SPEC}")
            last = key if sep else ""
            if sep and key == "by":
                values["group_by"] = val.strip()
                continue
            if sep and key in ("edges", "factors"):
                try:
                    values[key] = tuple(float(x) for x in val.split("/") if x.strip())
                except ValueError:
                    raise ValueError(f"--noise-scale {key}: numbers separated by '/', got "
                                     f"{val!r}; {GROUP_SPEC}") from None
                continue
            if not sep or key not in keys:
                raise ValueError(f"--noise-scale takes comma-separated KEY=VALUE items, "
                                 f"{SCALE_SPEC}; got {item!r}")
            try:
                values[keys[key]] = float(val)
            except ValueError:
                raise ValueError(f"--noise-scale {key}: not a number: {val!r}") from None
        if "group_by" in values or "edges" in values or "factors" in values:
            _check_groups(values)
        try:
            return cls(**values)
        except ValueError as exc:
            raise ValueError(f"--noise-scale: {exc}" + (f"; {GROUP_SPEC}" if values.get(
                "group_by") else "")) from None

    def advice(self, digits: int = 4) -> str:
        """The ``--noise-scale`` text of these scales' stars' part (:meth:`parse` reads it).

        ``star=S``, or with groups ``by=B,edges=E1/E2,factors=F0/F1/F2`` (each group's
        factor of the messages' σ: ``S`` times its own, the σ :meth:`star_sigma` gives),
        and ``unknown=PX`` where the σ of σ-0 stars was measured, ``rho=R[,share=W]`` where
        the stars' noise is declared correlated.
        """
        if self.group_by:
            # (edges exact, shortest round trip: a star on a rounded edge changed bins)
            out = (f"by={self.group_by},edges="
                   + "/".join(repr(float(e)) for e in self.edges)
                   + ",factors=" + "/".join(f"{self.star * f:.{digits}g}" for f in self.factors))
        else:
            out = f"star={self.star:.{digits}g}"
        if self.unknown_sigma_px > 0:
            out += f",unknown={self.unknown_sigma_px:.{digits}g}"
        if self.star_rho:  # (the correlation the scale stands for: its consistency's reference)
            out += f",rho={self.star_rho:.{digits}g}" + (
                f",share={self.star_ar_share:.{digits}g}" if self.star_ar_share != 1.0 else "")
        return out
