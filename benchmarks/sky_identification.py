"""Identification from images against tetra3rs used independently, and against truth.

Part 1 (``--realsky DIR``, default ``../shared/realsky``): every JPEG through the
project's pipeline (``sky.solve.solve_images``, one image = one camera, field searched
over 5-30 deg) and through tetra3rs alone (its own extraction and lost-in-space, 5-30 deg
database).  For each star the project identified, the independent solve's match at the
same centroid (within 1.5 px) must be the same star: < 2″ apart at the solver catalogue's
epoch.  Part 2 (``--rendered N``): N images of the real sky (Hipparcos, random attitudes)
rendered through a distorted 12-deg camera with hot pixels and clouds; identification and
false-identification rates against the truth, and the same agreement check.

    python benchmarks/sky_identification.py                 # both parts
    python benchmarks/sky_identification.py --rendered 0    # real frames only

Times are process CPU time per frame on one thread (the machine is shared), medians.
"""

from __future__ import annotations

import argparse
import glob
import os
import time
from pathlib import Path

import numpy as np

from stellar_cal_ros.core.camera import CameraModel
from stellar_cal_ros.core.catalog import load_catalog, radec_to_unit
from stellar_cal_ros.core.rotation import so3_exp
from stellar_cal_ros.sim.render import SensorConfig, render_image
from stellar_cal_ros.sky.database import solver_database, tetra3rs
from stellar_cal_ros.sky.extract import extract_stars
from stellar_cal_ros.sky.identify import GAIA_EPOCH_JYEAR, Identifier

REALSKY = Path(__file__).resolve().parents[2] / "shared" / "realsky"


def independent(pixels: np.ndarray, fov: float, fov_err: float, db) -> dict[int, np.ndarray]:
    """tetra3rs alone: {centroid index: catalogue unit vector}, and its centroids (u, v)."""
    t3 = tetra3rs()
    img = pixels.astype(np.float32)
    h, w = img.shape
    cents = t3.extract_centroids(img, threads=1).centroids
    r = db.solve_from_centroids(cents, fov_estimate_deg=fov, fov_max_error_deg=fov_err,
                                image_width=w, image_height=h)
    xy = np.array([[c.x + (w - 1) / 2, c.y + (h - 1) / 2] for c in cents]).reshape(-1, 2)
    if not r:
        return {}, xy
    out = {}
    for i, cid in zip(r.matched_centroids, r.matched_catalog_ids, strict=True):
        s = db.get_star_by_id(int(cid))
        out[int(i)] = radec_to_unit(np.radians(s.ra_deg), np.radians(s.dec_deg))
    return out, xy


def agreement(uv: np.ndarray, hip: np.ndarray, ref: dict, ref_xy: np.ndarray, cat,
              sky: np.ndarray | None = None) -> tuple:
    """(compared, same, ours nearer) for the project's identified stars (``hip`` at ``uv``).

    ``sky`` (n, 3): the centroids' directions under the project's solved attitude; where the
    two differ, the star nearer to it is counted (the project's when it is nearer).
    """
    if not len(hip) or not len(ref_xy):
        return 0, 0, 0
    u = radec_to_unit(*cat.subset(cat.index_of(hip)).radec(GAIA_EPOCH_JYEAR))
    n = same = nearer = 0
    for k in range(len(hip)):
        d = np.linalg.norm(ref_xy - uv[k], axis=1)
        i = int(d.argmin())
        if d[i] < 1.5 and i in ref:
            n += 1
            ok = np.degrees(np.arccos(min(1.0, float(u[k] @ ref[i])))) * 3600 < 2.0
            same += ok
            if not ok and sky is not None:
                nearer += float(sky[k] @ u[k]) > float(sky[k] @ ref[i])
    return n, same, nearer


def ok_ident(ident) -> bool:
    """The identification has an attitude."""
    return ident.R_i_st is not None


def realsky(folder: Path) -> None:
    """Part 1."""
    from stellar_cal_ros.sky.solve import solve_images

    images = sorted(glob.glob(str(folder / "*.jpg")))
    if not images:
        print(f"(no images in {folder}: part 1 skipped)")
        return
    db = solver_database(5.0, 30.0)
    cat = load_catalog(None)
    print("== real night-sky frames: the project's pipeline vs tetra3rs alone ==")
    print(f"{'image':26s} {'stars':>5s} {'status':>13s} {'ident':>5s} {'flag':>4s} "
          f"{'t3rs':>4s} {'cmp':>4s} {'same':>4s} {'extr_ms':>7s} {'id_ms':>6s}")
    tot = [0, 0, 0, 0, 0]
    ext, idt = [], []
    for path in images:
        name = os.path.basename(path)
        c0 = time.process_time()
        res = solve_images([path], None, {name: 0.0})
        s = res.solved[0]
        ident = s.identification
        c1 = time.process_time()
        e0 = time.process_time()
        extract_stars(s.image.pixels)
        e_ms = 1e3 * (time.process_time() - e0)
        ref, ref_xy = independent(s.image.pixels, 15.0, 10.0, db)
        mine = np.flatnonzero(ident.identified)
        sky = res.camera.unproject(s.centroids.uv[mine]) @ ident.R_i_st.T if ok_ident(ident) \
            else None
        n, same, nearer = agreement(s.centroids.uv[mine], ident.catalog_id[mine], ref, ref_xy,
                                    cat, sky)
        flags = int(ident.ambiguous.sum() + ident.conflicting.sum() + ident.gated.sum())
        ok = ident.status != "failed"
        tot[0] += ok
        tot[1] += bool(ref)
        tot[2] += n
        tot[3] += same
        tot[4] += nearer
        ext.append(e_ms)
        idt.append(1e3 * (c1 - c0) - e_ms)
        print(f"{name:26s} {len(s.centroids):5d} {ident.status:>13s} {ident.n_identified:5d} "
              f"{flags:4d} {'ok' if ref else 'fail':>4s} {n:4d} {same:4d} {e_ms:7.1f} "
              f"{idt[-1]:6.1f}")
    print(f"identified {tot[0]} of {len(images)} frames (tetra3rs alone: {tot[1]}); same star "
          f"as tetra3rs alone for {tot[3]} of {tot[2]} stars both identified (of the "
          f"{tot[2] - tot[3]} others, the project's star is the nearer to the centroid under "
          f"the solved attitude for {tot[4]}); median CPU "
          f"extraction {np.median(ext):.1f} ms, identification (two solves) "
          f"{np.median(idt):.1f} ms per frame (a frame's first use of a field band builds "
          "its database once: seconds, cached)")


def rendered(n_frames: int, seed: int = 1) -> None:
    """Part 2."""
    if n_frames <= 0:
        return
    rng = np.random.default_rng(seed)
    w = h = 1024
    f = w / 2 / np.tan(np.radians(12.0) / 2)
    cam = CameraModel(w, h, f, f, 515.0, 508.0, [-0.08, 0.02, 1e-4, -1e-4, 0])
    cat = load_catalog(7.5)
    u_all = radec_to_unit(*cat.message_radec())
    full = load_catalog(None)
    sensor = SensorConfig(hot_pixel_fraction=5e-5, clouds=0.3)
    ident = Identifier(cam)
    db = solver_database(5.0, 30.0)
    stars = detected = identified = wrong = cmp_n = cmp_same = frames_ok = t3_ok = 0
    ext, idt = [], []
    for _ in range(n_frames):
        R = so3_exp(rng.normal(size=3))
        d = u_all @ R
        vis = d[:, 2] > 0.97
        uv = cam.project(d[vis])
        ok = cam.in_image(uv, margin=-3)
        r = render_image(uv[ok], cat.magnitude[vis][ok], w, h, sensor, rng)
        hip = cat.hip[vis][ok]
        c0 = time.process_time()
        c = extract_stars(r.image)
        c1 = time.process_time()
        res = ident.identify(c.uv, brightness=c.flux)
        c2 = time.process_time()
        ext.append(1e3 * (c1 - c0))
        idt.append(1e3 * (c2 - c1))
        dd = np.linalg.norm(c.uv[:, None] - r.uv[None], axis=2)
        j = dd.argmin(axis=1)
        near = dd[np.arange(len(j)), j] < 1.0
        stars += len(r.uv)
        detected += int(near.sum())
        idn = res.identified
        identified += int((idn & near).sum())
        wrong += int((idn & ~near).sum() + (res.catalog_id[idn & near] != hip[j[idn & near]]).sum())
        frames_ok += res.status != "failed"
        ref, ref_xy = independent(r.image, 12.0, 3.0, db)
        t3_ok += bool(ref)
        mine = np.flatnonzero(idn)
        n, same, _ = agreement(c.uv[mine], res.catalog_id[mine], ref, ref_xy, full)
        cmp_n += n
        cmp_same += same
    print(f"== rendered images: {n_frames} frames, 1024 x 1024, 12 deg, k1 -0.08, hot pixels, "
          "clouds 0.3 ==")
    print(f"frames identified {frames_ok} of {n_frames} (tetra3rs alone: {t3_ok}); stars "
          f"rendered {stars}, detected {detected}, identified {identified} "
          f"({100.0 * identified / max(detected, 1):.1f} % of detected), false "
          f"identifications {wrong}; same star as tetra3rs alone for {cmp_same} of {cmp_n}; "
          f"median CPU extraction {np.median(ext):.1f} ms, identification "
          f"{np.median(idt):.1f} ms per frame")


def main() -> None:
    """Command line."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--realsky", type=Path, default=REALSKY)
    ap.add_argument("--rendered", type=int, default=20, help="rendered frames (0: none)")
    args = ap.parse_args()
    realsky(args.realsky)
    rendered(args.rendered)


if __name__ == "__main__":
    main()
