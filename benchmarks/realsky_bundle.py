"""Held-out RMS on real night-sky frames: the bundle after ``discover`` against tetra3rs.

Both pipelines start from the same JPEGs and are scored by the same rule (the contract's
``cross_validation``, :func:`~stellar_cal_ros.methods.bundle_cv.held_out_frame`): each
frame held out in turn, the camera from the other frames, only the held-out frame's
attitude fitted, ``sqrt(mean(du² + dv²))`` in arcsec at the principal point's plate scale
over its identified stars except those beyond 5 × the frame's median residual.

* **ours** — centroids (``psf``: the project's pixel-integrated Gaussian fit with a σ per
  star, :mod:`stellar_cal_ros.sky.extract`; and, to separate the two gains, ``tetra3rs``'s
  moment centroids), identification through :mod:`stellar_cal_ros.sky.identify` (Hipparcos
  stars), then ``discover --method bundle`` from the baseline, and the final model's
  cross-validation;
* **tetra3rs** — its own extraction and lost-in-space solve, ``calibrate_camera`` on the
  other frames (``radial``: Brown–Conrady k1 k2 k3; ``polynomial``: SIP-like, order 2-4),
  the held-out frame re-solved with that camera.  Two numbers per frame: the rule above
  applied to its camera and its own matches (``same rule``) and the RMSE its re-solve
  reports (``own``; the number the issue quotes).  And tetra3rs's ``calibrate_camera`` on
  *our* centroids: what the centroids alone are worth.

Usage::

    .venv/bin/python benchmarks/realsky_bundle.py      # the 4 frames of one camera
    .venv/bin/python benchmarks/realsky_bundle.py --frames FRAMES   # e.g. the 3 of one state
    .venv/bin/python benchmarks/realsky_bundle.py --images DIR --frames FILES --fov DEG ...

(FRAMES: ``jan1_g90_e100ms,jan1_g90_e50ms,test_5mp_g100_e50ms``; a name without a suffix is
a ``.jpg``.)  Your own frames: ``--images DIR --frames a.tif,b.tif,c.tif --fov 22 --stamps
STAMPS.csv --site LAT,LON,H`` (``stellar-cal solve``'s stamps CSV and site: our pipeline
then has the times and place, so refraction and aberration are candidates).
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stellar_cal_ros.core.camera import CameraModel
from stellar_cal_ros.core.catalog import radec_to_unit
from stellar_cal_ros.core.types import StarFrame
from stellar_cal_ros.io.calibration import Calibration
from stellar_cal_ros.methods.bundle_cv import held_out_frame
from stellar_cal_ros.methods.frames import BagData

ONE_CAMERA = ("jan1_g90_e100ms", "jan1_g90_e50ms", "test2_g100_e50ms", "test_5mp_g100_e50ms")
FOV_DEG = 10.9  #: the README's field of the one-camera frames
J2000_POSIX = 946728000.0  #: stamps of frames without a time (proper motion then zero)


def default_images() -> Path:
    """``../shared/realsky`` beside the repository."""
    return Path(__file__).resolve().parents[2] / "shared" / "realsky"


def load_grey(path: Path) -> np.ndarray:
    """An image as a 2-D grey array (JPEG/PNG/TIFF, 8 or 16 bit, FITS: sky/images.py)."""
    from stellar_cal_ros.sky.images import read_image

    return np.asarray(read_image(path).pixels)


def image_path(images_dir: Path, name: str) -> Path:
    """``name`` in ``images_dir`` (``.jpg`` when it has no suffix)."""
    return images_dir / (name if Path(name).suffix else f"{name}.jpg")


# ----------------------------------------------------------------------------- ours
@dataclass
class Centroids:
    """One image's detections: centroids (n, 2) px, brightness (n,), σ (n,) px (0: unknown)."""

    uv: np.ndarray
    brightness: np.ndarray
    sigma: np.ndarray


def extract(img: np.ndarray, method: str) -> Centroids:
    """Centroids of an image: the project's PSF fit (``psf``) or tetra3rs's moments."""
    if method == "psf":
        from stellar_cal_ros.sky.extract import extract_stars

        c = extract_stars(img)
        return Centroids(c.uv, c.flux, c.sigma)
    import tetra3rs

    h, w = img.shape
    det = tetra3rs.extract_centroids(img.astype(np.float32)).centroids
    uv = np.array([[d.x + (w - 1) / 2.0, d.y + (h - 1) / 2.0] for d in det])
    return Centroids(uv, np.array([d.brightness for d in det]), np.zeros(len(det)))


def identified_frames(images: list[np.ndarray], centroids: str, fov_deg: float = FOV_DEG,
                      stamps: list[float] | None = None
                      ) -> tuple[list[StarFrame], list[float], list[int], list[Centroids]]:
    """Our identification of every image (``stamps``: POSIX s of each, else J2000.0 + k s).

    Returns the frames (identified stars only), the solved fields, the number of centroids
    detected and the detections.
    """
    from stellar_cal_ros.sky.identify import Identifier, IdentifyConfig

    h, w = images[0].shape
    ident = Identifier(None, IdentifyConfig(fov_deg=fov_deg,
                                            fov_max_error_deg=0.15 * fov_deg), (w, h))
    frames, fovs, detected, cents = [], [], [], []
    for k, img in enumerate(images):
        c = extract(img, centroids)
        cents.append(c)
        res = ident.identify(c.uv, brightness=c.brightness)
        ok = res.identified
        frames.append(StarFrame(
            stamp_ns=int(round(((stamps[k] if stamps else J2000_POSIX + k)) * 1e9)),
            frame_id="star_tracker_optical_frame",
            exposure_time=0.0, catalog_id=res.catalog_id[ok].astype(np.uint32),
            right_ascension=res.right_ascension[ok], declination=res.declination[ok],
            uv=c.uv[ok], magnitude=res.magnitude[ok], sigma=c.sigma[ok]))
        fovs.append(res.fov_deg)
        detected.append(len(c.uv))
    return frames, fovs, detected, cents


def pinhole_prior(width: int, height: int, fov_deg: float) -> Calibration:
    """A datasheet-level prior: pinhole of the solved field, centred, no distortion."""
    from scipy.spatial.transform import Rotation

    f = (width / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    return Calibration(
        camera=CameraModel.pinhole(width, height, f), installation=Rotation.identity(),
        gyro_bias=np.zeros(3), gyro_error_matrix=np.zeros((3, 3)), accel_bias=np.zeros(3),
        accel_error_matrix=np.zeros((3, 3)), time_offset=0.0, effects={},
        sigma={"camera": {
            "camera_matrix": {"rows": 3, "cols": 3,
                              "data": [0.02 * f, 0, 0.05 * width, 0, 0.02 * f,
                                       0.05 * width, 0, 0, 0]},
            "distortion_coefficients": {"rows": 1, "cols": 5,
                                        "data": [0.5, 2.0, 0.01, 0.01, 5.0]}}},
        method="prior", stamp=J2000_POSIX)


@dataclass
class Ours:
    """Our result: the discovered model and its cross-validation."""

    added: list[str]
    held_out: list[float]
    rejected: list[int]
    stars: list[int]
    seconds: float
    path: list[str] = field(default_factory=list)


def ours(frames: list[StarFrame], prior: Calibration, discover: bool = True,
         site: tuple[float, float, float] | None = None) -> Ours:
    """``discover --method bundle`` from the baseline, then the final model's CV.

    ``site`` (lat, lon deg, height m) makes refraction and aberration candidates.
    """
    from stellar_cal_ros.core.earth import Site
    from stellar_cal_ros.diagnosis.run import diagnose
    from stellar_cal_ros.methods.bundle_runs import run_bundle

    data = BagData(t0_ns=frames[0].stamp_ns, imu_t=np.zeros(0), imu_w=np.zeros((0, 3)),
                   imu_f=np.zeros((0, 3)), frames=frames,
                   site=Site(*site) if site else None, head_temperature=None,
                   air_temperature=None, pressure=None)
    t0 = time.process_time()
    start = run_bundle(data, prior, [], cross_validate=False).calibration
    added, path = [], []
    if discover:
        with tempfile.TemporaryDirectory() as tmp:
            summary = diagnose(data, start, "bundle", [], tmp, plots=False, verbose=False,
                               auto=True, workers=0)
        added = list(summary["added"])
        path = [f"round {s['round']}: {s['action']}"
                + (f" {s['added']['effect']}" if s.get("added") else "")
                for s in summary["path"]]
    res = run_bundle(data, prior, added)
    cv = res.cross_validation
    return Ours(added, cv["held_out_rms_arcsec"], cv["rejected"], cv["stars"],
                time.process_time() - t0, path)


# ----------------------------------------------------------------------------- tetra3rs
def _t3_predict(camera, u_i: np.ndarray, width: int, height: int):
    """``R_i_st ↦ uv`` through a tetra3rs CameraModel (its camera axes are the contract's)."""
    def predict(R: np.ndarray) -> np.ndarray:
        d = u_i @ R
        with np.errstate(all="ignore"):
            xy = [camera.tanplane_to_pixel(a[0] / a[2], a[1] / a[2]) if a[2] > 0
                  else (np.nan, np.nan) for a in d]
        return np.asarray(xy, dtype=float) + [(width - 1) / 2.0, (height - 1) / 2.0]

    return predict


@dataclass
class Row:
    """One pipeline's held-out numbers per frame."""

    name: str
    held_out: list[float]
    rejected: list[int] = field(default_factory=list)
    stars: list[int] = field(default_factory=list)
    own: list[float] | None = None  #: tetra3rs: the RMSE its re-solve reports


def tetra3rs_loo(images: list[np.ndarray], models: list[tuple[str, int]],
                 centroids: list[Centroids] | None = None, label: str = "",
                 fov_deg: float = FOV_DEG) -> list[Row]:
    """tetra3rs alone: solve, ``calibrate_camera`` on the others, re-solve each frame.

    ``centroids``: the detections to use (default: tetra3rs's own extraction).
    """
    import tetra3rs

    from stellar_cal_ros.sky import database

    h, w = images[0].shape
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    db = database.solver_database(*database.band_for(fov_deg))
    cents, sols = [], []
    for k, img in enumerate(images):
        if centroids is None:
            cs = tetra3rs.extract_centroids(img.astype(np.float32)).centroids
            xy = np.array([[d.x, d.y, d.brightness] for d in cs])
        else:
            c = centroids[k]
            order = np.argsort(-c.brightness, kind="stable")
            xy = np.column_stack([c.uv[order] - centre, c.brightness[order]])
        cents.append(xy)
        sols.append(db.solve_from_centroids(xy, fov_estimate_deg=fov_deg,
                                            fov_max_error_deg=0.15 * fov_deg,
                                            image_shape=(h, w)))
    out = []
    for model, order in models:
        name = f"tetra3rs {model}" + (f" {order}" if model == "polynomial" else "") + label
        row = Row(name, [], [], [], [])
        for k in range(len(images)):
            train = [j for j in range(len(images)) if j != k and sols[j]]
            cal = db.calibrate_camera([sols[j] for j in train], [cents[j] for j in train],
                                      image_shape=(h, w), model=model, order=order)
            cam = cal.camera_model
            again = db.solve_from_centroids(cents[k], camera_model=cam, image_shape=(h, w))
            row.own.append(float(again.rmse_arcsec) if again else float("nan"))
            ref = again if again else sols[k]
            idx = np.asarray(ref.matched_centroids, dtype=np.int64)
            stars = [db.get_star_by_id(int(i)) for i in ref.matched_catalog_ids]
            u_i = radec_to_unit(np.radians([s.ra_deg for s in stars]),
                                np.radians([s.dec_deg for s in stars]))
            score = held_out_frame(_t3_predict(cam, u_i, w, h),
                                   np.asarray(ref.rotation_matrix_icrs_to_camera).T,
                                   cents[k][idx, :2] + centre,
                                   (1.0 / cam.focal_length_px, 1.0 / cam.focal_length_px))
            row.held_out.append(score.rms_arcsec)
            row.rejected.append(score.rejected)
            row.stars.append(int(score.scored.sum()))
        out.append(row)
    return out


# ----------------------------------------------------------------------------- table
T3_MODELS = (("radial", 4), ("polynomial", 2), ("polynomial", 4))


def compare(names: list[str], images_dir: Path, discover: bool = True,
            t3_models: tuple[tuple[str, int], ...] = T3_MODELS, fov_deg: float = FOV_DEG,
            stamps: dict[str, float] | None = None,
            site: tuple[float, float, float] | None = None) -> dict:
    """Every pipeline on the frames ``names`` (see the module docstring).

    ``stamps`` ({file name: POSIX s}, ``stellar-cal solve``'s ``--stamps`` CSV) and ``site``
    give our pipeline the times and place (refraction, aberration); tetra3rs uses neither.
    """
    paths = [image_path(images_dir, n) for n in names]
    images = [load_grey(p) for p in paths]
    times = [stamps[p.name] for p in paths] if stamps else None
    h, w = images[0].shape
    rows, extra = [], {}
    for centroids in ("psf", "tetra3rs"):
        frames, fovs, detected, cents = identified_frames(images, centroids, fov_deg, times)
        fov_deg = float(np.nanmedian(fovs))
        prior = pinhole_prior(w, h, fov_deg)
        mine = ours(frames, prior, discover, site)
        rows.append(Row(f"ours: {centroids} centroids, bundle" + (" after discover" if discover
                                                                    else ""),
                        mine.held_out, mine.rejected, mine.stars))
        extra[centroids] = {"added": mine.added, "path": mine.path, "seconds": mine.seconds,
                            "identified": [len(f.uv) for f in frames], "detected": detected}
        if centroids == "psf":
            rows += tetra3rs_loo(images, [t3_models[0]], cents, " on our psf centroids",
                                 fov_deg)
    rows += tetra3rs_loo(images, list(t3_models), fov_deg=fov_deg)
    return {"names": names, "rows": rows, "ours": extra}


def print_table(out: dict) -> None:
    """The side-by-side table (rows: pipelines; columns: frames, mean, ratio)."""
    names, rows = out["names"], out["rows"]
    t3 = [r for r in rows if r.name.startswith("tetra3rs") and "our" not in r.name]
    ref = min(t3, key=lambda r: np.nanmean(r.held_out))
    ref_own = min(t3, key=lambda r: np.nanmean(r.own))
    print("held-out RMS, arcsec (each frame held out: camera from the others, its attitude "
          "alone fitted; the contract's rule)")
    width = max(len(r.name) for r in rows) + 2
    print(f"{'pipeline':{width}s}" + "".join(f"{n[:16]:>17s}" for n in names)
          + f"{'mean':>8s}{'ratio':>7s}")
    for r in rows:
        m = float(np.nanmean(r.held_out))
        print(f"{r.name:{width}s}" + "".join(f"{v:10.2f} ({s:3d})" for v, s in
                                             zip(r.held_out, r.stars, strict=True))
              + f"{m:8.2f}{m / np.nanmean(ref.held_out):7.3f}")
    for r in t3:
        m = float(np.nanmean(r.own))
        print(f"{r.name + ' (own re-solve RMSE)':{width}s}" + "".join(
            f"{v:16.2f} " for v in r.own) + f"{m:8.2f}{m / np.nanmean(ref_own.own):7.3f}")
    print(f"(stars scored in brackets; ratio: to {ref.name} by the same rule, and for the "
          f"re-solve RMSEs to {ref_own.name}'s)")
    for key, e in out["ours"].items():
        print(f"ours, {key} centroids: identified {e['identified']} of {e['detected']} "
              f"detected; discover added {', '.join(e['added']) or 'nothing'} "
              f"({'; '.join(e['path'])}); {e['seconds']:.1f} s CPU")


def main(argv: list[str] | None = None) -> int:
    """Print the table for ``--frames`` of ``--images``."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--images", type=Path, default=default_images())
    p.add_argument("--frames", default=",".join(ONE_CAMERA))
    p.add_argument("--no-discover", action="store_true", help="the baseline model only")
    p.add_argument("--fov", type=float, default=FOV_DEG, help="horizontal field, deg")
    p.add_argument("--stamps", type=Path, default=None,
                   help="file,utc CSV (as for stellar-cal solve): our pipeline gets the times")
    p.add_argument("--site", default=None, metavar="LAT,LON,H",
                   help="the site (deg, deg, m): refraction and aberration become candidates")
    args = p.parse_args(argv)
    if not args.images.is_dir():
        print(f"no real-sky images at {args.images}", file=sys.stderr)
        return 1
    logging.basicConfig(level=logging.WARNING)
    from stellar_cal_ros.sky.solve import parse_site, read_stamps

    out = compare(args.frames.split(","), args.images, not args.no_discover,
                  fov_deg=args.fov,
                  stamps=read_stamps(args.stamps) if args.stamps else None,
                  site=parse_site(args.site) if args.site else None)
    print_table(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
