"""``stellar-cal solve IMAGE... -o BAG.mcap``: star images → a contract bag + ``BAG.prior.yaml``.

Per image: read (:mod:`.images`), centroids with σ from their SNR (:mod:`.extract`),
lost-in-space identification (:mod:`.identify`; field from ``--fov`` or searched over
5-30 deg).  The images are taken to come from one camera: its focal length is the median of
the solved fields, and the images are identified a second time through that camera (the
solver then sees the same pinhole in every frame).  The bag holds one
``StarCentroidArray`` per image on ``/star_tracker/stars`` (stamped from ``--stamps`` or the
image's own time) with its identified stars — an image that could not be identified keeps
all its centroids unidentified (``catalog_id`` 0, RA/Dec NaN) for the calibration methods
to try again — and, with ``--site``, one ``/gnss/fix`` per frame.

``BAG.prior.yaml``: the camera of the solve and its σ: the focal length's from the scatter of
the solved fields (at least 0.2 %), the principal point at the image centre with σ 2 % of
the width (a plate solve cannot see it), no distortion with σ (k1 0.5, k2 1.0, p1/p2 0.005)
a star camera of 5-30 deg may have; identity installation with σ 1 rad (no IMU).
"""

from __future__ import annotations

import csv
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from stellar_cal_ros.core.camera import CameraModel
from stellar_cal_ros.core.types import NavSatSeries, StarFrame
from stellar_cal_ros.errors import StellarCalError
from stellar_cal_ros.sky.extract import Centroids, ExtractConfig, extract_stars
from stellar_cal_ros.sky.identify import Identification, Identifier, IdentifyConfig
from stellar_cal_ros.sky.images import StarImage, parse_utc, read_image

log = logging.getLogger(__name__)

STAR_TRACKER_FRAME = "star_tracker_optical_frame"
DEFAULT_FOV = (17.5, 12.5)  #: field estimate, search half-range without --fov: 5-30 deg


@dataclass
class SolvedImage:
    """One image through extraction and identification."""

    image: StarImage
    centroids: Centroids
    identification: Identification
    stamp_ns: int = 0


@dataclass
class SolveResult:
    """What ``solve`` made of the images."""

    solved: list[SolvedImage] = field(default_factory=list)
    camera: CameraModel | None = None
    sigma_f: float = float("nan")

    @property
    def frames(self) -> list[StarFrame]:
        """One contract message per image (stamp order)."""
        return [star_frame(s) for s in sorted(self.solved, key=lambda s: s.stamp_ns)]


def read_stamps(path: str | Path) -> dict[str, float]:
    """``file,utc`` CSV → {file name: POSIX s} (keys: the names as written and base names)."""
    out: dict[str, float] = {}
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except OSError as exc:
        raise StellarCalError(f"cannot read stamps {path}: {exc}") from None
    if not rows or not {"file", "utc"} <= set(rows[0]):
        raise StellarCalError(f"{path}: a stamps CSV needs the columns file,utc")
    for i, row in enumerate(rows, start=2):
        try:
            t = parse_utc(row["utc"])
        except StellarCalError as exc:
            raise StellarCalError(f"{path} line {i}: {exc}") from None
        out[row["file"]] = t
        out[Path(row["file"]).name] = t
    return out


def star_frame(s: SolvedImage) -> StarFrame:
    """The contract message of a solved image.

    Its identified stars, or, when the image could not be identified, all its centroids
    unidentified (for a method to try again).
    """
    c, ident = s.centroids, s.identification
    keep = ident.identified if ident.status != "failed" else np.ones(len(c), bool)
    return StarFrame(stamp_ns=int(s.stamp_ns), frame_id=STAR_TRACKER_FRAME,
                     exposure_time=float(s.image.exposure_s),
                     catalog_id=ident.catalog_id[keep].astype(np.uint32),
                     right_ascension=ident.right_ascension[keep],
                     declination=ident.declination[keep], uv=c.uv[keep],
                     magnitude=ident.magnitude[keep], sigma=c.sigma[keep])


def solve_images(paths: list[str], fov_deg: float | None = None,
                 stamps: dict[str, float] | None = None,
                 extract: ExtractConfig | None = None) -> SolveResult:
    """Extract and identify every image (see the module docstring)."""
    if not paths:
        raise StellarCalError("no images given")
    images = [read_image(p) for p in paths]
    sizes = {(im.width, im.height) for im in images}
    if len(sizes) > 1:
        raise StellarCalError(f"the images are of different sizes {sorted(sizes)}: one "
                              "camera per solve")
    width, height = sizes.pop()
    stamp_of = {}
    for im in images:
        t = None
        if stamps is not None:
            t = stamps.get(im.path, stamps.get(Path(im.path).name))
        if t is None:
            t = im.time_posix
        if t is None:
            raise StellarCalError(f"{im.path}: no time (the file has none and --stamps does "
                                  "not list it): give --stamps STAMPS.csv with file,utc")
        stamp_of[im.path] = int(round(t * 1e9))
    cents = [extract_stars(im.pixels, extract) for im in images]
    fov, err = (fov_deg, 0.25 * fov_deg) if fov_deg else DEFAULT_FOV
    first = Identifier(None, IdentifyConfig(fov_deg=fov, fov_max_error_deg=err),
                       image_size=(width, height))
    fovs = []
    for im, c in zip(images, cents, strict=True):
        ident = first.identify(c.uv, brightness=c.flux)
        log.debug("%s: %d stars, %s (%d identified, field %.3f deg)", im.path, len(c),
                 ident.status, ident.n_identified, ident.fov_deg)
        if ident.status != "failed":
            fovs.append(ident.fov_deg)
    if not fovs:
        raise StellarCalError("no image could be identified (lost-in-space failed on all; "
                              "check --fov)")
    f_all = (width / 2.0) / np.tan(np.radians(np.asarray(fovs)) / 2.0)
    f = float(np.median(f_all))
    spread = 1.4826 * float(np.median(np.abs(f_all - f))) if len(f_all) > 2 else 0.0
    sigma_f = max(spread, 0.002 * f)
    camera = CameraModel.pinhole(width, height, f)
    second = Identifier(camera)
    out = SolveResult(camera=camera, sigma_f=sigma_f)
    for im, c in zip(images, cents, strict=True):
        ident = second.identify(c.uv, brightness=c.flux)
        out.solved.append(SolvedImage(im, c, ident, stamp_of[im.path]))
    return out


def prior_calibration(result: SolveResult):
    """``BAG.prior.yaml``: the camera of the solve with σ (see the module docstring)."""
    from stellar_cal_ros.io.calibration import Calibration

    cam = result.camera
    sp = 0.02 * cam.width
    stamps = [s.stamp_ns for s in result.solved]
    return Calibration(
        camera=cam, installation=Rotation.identity(), method="prior",
        stamp=float(min(stamps)) * 1e-9 if stamps else 0.0,
        sigma={"camera": {
            "camera_matrix": {"rows": 3, "cols": 3,
                              "data": [result.sigma_f, 0.0, sp, 0.0, result.sigma_f, sp,
                                       0.0, 0.0, 0.0]},
            "distortion_coefficients": {"rows": 1, "cols": 5,
                                        "data": [0.5, 1.0, 0.005, 0.005, 0.0]}},
            "installation": {"rotation_vector": [1.0, 1.0, 1.0]}, "time_offset": 0.0})


def parse_site(text: str) -> tuple[float, float, float]:
    """``LAT,LON,H`` (deg, deg, m) → a tuple; a one-line error otherwise."""
    try:
        lat, lon, h = (float(x) for x in str(text).split(","))
    except ValueError:
        raise StellarCalError(f"--site wants LAT,LON,H (deg, deg, m), got {text!r}") from None
    if not (abs(lat) <= 90 and abs(lon) <= 360 and math.isfinite(h)):
        raise StellarCalError(f"--site {text!r}: latitude within ±90 deg, longitude within "
                              "±360 deg, finite height")
    return lat, lon, h


def write_solve(result: SolveResult, bag: str | Path,
                site: tuple[float, float, float] | None = None) -> dict[str, Path]:
    """Write the bag and ``BAG.prior.yaml``; returns their paths."""
    from stellar_cal_ros.io.bag import BagWriter
    from stellar_cal_ros.io.calibration import save_calibration

    bag = Path(bag)
    bag.parent.mkdir(parents=True, exist_ok=True)
    prior = Path(f"{bag.with_suffix('')}.prior.yaml")
    frames = result.frames
    with BagWriter(bag) as w:
        for fr in frames:
            w.write_star_frame(fr, "/star_tracker/stars")
        if site is not None and frames:
            n = len(frames)
            w.write_navsat(NavSatSeries(
                stamp_ns=np.array([f.stamp_ns for f in frames], dtype=np.int64),
                latitude_deg=np.full(n, site[0]), longitude_deg=np.full(n, site[1]),
                altitude_m=np.full(n, site[2]), status=np.zeros(n, dtype=np.int64)),
                "/gnss/fix")
    save_calibration(prior_calibration(result), prior)
    return {"bag": bag, "prior": prior}
