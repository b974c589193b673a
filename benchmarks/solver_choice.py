"""Which maintained plate solver identifies the stars: tetra3rs against cedar-solve.

Runs one library on every image of a folder (default ``../shared/realsky``): its own
centroid extraction and solve, and (``--centroids FILE``) a solve of the other library's
centroids, so the two identifications can be compared star by star.  cedar-solve pins
numpy < 2 and Pillow < 9, which clash with this project's venv: run it from a separate venv.

    python benchmarks/solver_choice.py --library tetra3rs -o t3.json
    OTHER_VENV/bin/python benchmarks/solver_choice.py --library cedar-solve \
        --centroids t3.json -o cs.json
    python benchmarks/solver_choice.py --compare t3.json cs.json

Times are process CPU time (one thread), per frame.  The image is read as 8-bit grey.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import time
from pathlib import Path

import numpy as np

FOV_DEG, FOV_ERR_DEG = 15.0, 10.0  # the folder's fields are 10-20 deg


def _grey(path: str) -> np.ndarray:
    from PIL import Image
    return np.asarray(Image.open(path).convert("L"))


def run_tetra3rs(images: list[str], db_path: str) -> dict:
    """tetra3rs on every image: its extraction, then lost-in-space."""
    import tetra3rs
    if os.path.exists(db_path):
        db = tetra3rs.SolverDatabase.load_from_file(db_path)
    else:
        c = time.process_time()
        db = tetra3rs.SolverDatabase.generate_from_gaia(max_fov_deg=30.0, min_fov_deg=5.0)
        print(f"database 5-30 deg generated in {time.process_time() - c:.1f} s CPU "
              f"({db.num_stars} stars, {db.num_patterns} patterns)")
        db.save_to_file(db_path)
    out = {}
    for f in images:
        img = _grey(f).astype(np.float32)
        h, w = img.shape
        c0 = time.process_time()
        cents = tetra3rs.extract_centroids(img, threads=1).centroids
        c1 = time.process_time()
        r = db.solve_from_centroids(cents, fov_estimate_deg=FOV_DEG,
                                    fov_max_error_deg=FOV_ERR_DEG, image_width=w,
                                    image_height=h)
        c2 = time.process_time()
        rec = {"shape": [h, w], "n_centroids": len(cents), "extract_ms": 1e3 * (c1 - c0),
               "solve_ms": 1e3 * (c2 - c1), "solved": bool(r),
               "xy": [[c.x + w / 2.0, c.y + h / 2.0] for c in cents]}  # top-left origin
        if r:
            stars = [db.get_star_by_id(int(i)) for i in r.matched_catalog_ids]
            rec.update(fov=r.fov_deg, matches=r.num_matches, rmse_arcsec=r.rmse_arcsec,
                       matched=[int(i) for i in r.matched_centroids],
                       radec=[[s.ra_deg, s.dec_deg] for s in stars])
        out[os.path.basename(f)] = rec
    return out


def run_cedar(images: list[str], centroids: dict | None) -> dict:
    """cedar-solve on every image, and on the other library's centroids."""
    import tetra3  # cedar-solve's module name
    t3 = tetra3.Tetra3()
    out = {}
    for f in images:
        name = os.path.basename(f)
        img = _grey(f)
        h, w = img.shape
        c0 = time.process_time()
        cents = tetra3.get_centroids_from_image(img)
        c1 = time.process_time()
        r = t3.solve_from_centroids(cents, (h, w), fov_estimate=FOV_DEG,
                                    fov_max_error=FOV_ERR_DEG)
        c2 = time.process_time()
        rec = {"shape": [h, w], "n_centroids": len(cents), "extract_ms": 1e3 * (c1 - c0),
               "solve_ms": 1e3 * (c2 - c1), "solved": r.get("RA") is not None}
        if rec["solved"]:
            rec.update(fov=r["FOV"], matches=r["Matches"], rmse_arcsec=r["RMSE"])
        if centroids and name in centroids:  # the other library's centroids, (y, x)
            xy = np.asarray(centroids[name]["xy"], dtype=float).reshape(-1, 2)
            c3 = time.process_time()
            r2 = t3.solve_from_centroids(xy[:, ::-1], (h, w), fov_estimate=FOV_DEG,
                                         fov_max_error=FOV_ERR_DEG, return_matches=True)
            other = {"solve_ms": 1e3 * (time.process_time() - c3),
                     "solved": r2.get("RA") is not None}
            if other["solved"]:
                yx = np.asarray(r2["matched_centroids"], dtype=float).reshape(-1, 2)
                idx = [int(np.argmin(np.hypot(*(xy[:, ::-1] - p).T))) for p in yx]
                other.update(fov=r2["FOV"], matches=r2["Matches"], rmse_arcsec=r2["RMSE"],
                             matched=idx,
                             radec=[[float(s[0]), float(s[1])] for s in r2["matched_stars"]])
            rec["other_centroids"] = other
        out[name] = rec
    return out


def _row(name: str, r: dict) -> str:
    if not r["solved"]:
        return (f"{name:26s} {r['n_centroids']:5d} {r['extract_ms']:8.1f} "
                f"{r['solve_ms']:9.1f}   fail")
    return (f"{name:26s} {r['n_centroids']:5d} {r['extract_ms']:8.1f} {r['solve_ms']:9.1f} "
            f"{r['fov']:6.2f} {r['matches']:5d} {r['rmse_arcsec']:7.1f}")


def table(res: dict, title: str) -> None:
    """Print one library's run."""
    print(f"== {title}: own extraction and solve (CPU ms per frame) ==")
    print(f"{'image':26s} {'cents':>5s} {'extract':>8s} {'solve':>9s} {'fov':>6s} "
          f"{'match':>5s} {'rms_as':>7s}")
    for name in sorted(res):
        print(_row(name, res[name]))
    n = sum(r["solved"] for r in res.values())
    ext = np.median([r["extract_ms"] for r in res.values()])
    sol = np.median([r["solve_ms"] for r in res.values() if r["solved"]] or [np.nan])
    print(f"solved {n} of {len(res)}; median extract {ext:.1f} ms, median solve {sol:.1f} ms")


def compare(a_path: str, b_path: str) -> None:
    """Star-by-star agreement of library B on library A's centroids with library A."""
    a, b = json.load(open(a_path)), json.load(open(b_path))

    def unit(rd):
        ra, dec = np.radians(np.asarray(rd, dtype=float)).T
        return np.c_[np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)]

    print("== agreement on the same centroids (same star: < 3 arcsec apart) ==")
    print(f"{'image':26s} {'A':>4s} {'B':>4s} {'both':>5s} {'same':>5s} {'differ':>6s}")
    tot = [0, 0]
    for name in sorted(a):
        ra, rb = a[name], b.get(name, {}).get("other_centroids", {"solved": False})
        if not (ra["solved"] and rb["solved"]):
            print(f"{name:26s} A {'ok' if ra['solved'] else 'fail'}, B "
                  f"{'ok' if rb['solved'] else 'fail'}")
            continue
        da = dict(zip(ra["matched"], unit(ra["radec"]), strict=True))
        db_ = dict(zip(rb["matched"], unit(rb["radec"]), strict=True))
        both = sorted(set(da) & set(db_))
        sep = np.degrees(np.arccos(np.clip([da[i] @ db_[i] for i in both], -1, 1))) * 3600
        same = int(np.sum(sep < 3.0))
        tot[0] += same
        tot[1] += len(both)
        print(f"{name:26s} {len(da):4d} {len(db_):4d} {len(both):5d} {same:5d} "
              f"{len(both) - same:6d}")
    print(f"same star on {tot[0]} of {tot[1]} centroids both matched")


def main() -> None:
    """Command line."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--library", choices=["tetra3rs", "cedar-solve"])
    ap.add_argument("--images", default=str(Path(__file__).resolve().parents[1].parent /
                                            "shared" / "realsky"))
    ap.add_argument("--database", default="tetra3rs_5_30.bin",
                    help="tetra3rs database file (generated once if absent)")
    ap.add_argument("--centroids", help="JSON of the other library's run (its centroids)")
    ap.add_argument("--compare", nargs=2, metavar=("A.json", "B.json"))
    ap.add_argument("-o", "--output")
    args = ap.parse_args()
    if args.compare:
        compare(*args.compare)
        return
    images = sorted(glob.glob(os.path.join(args.images, "*.jpg")))
    if not images:
        raise SystemExit(f"no images in {args.images}")
    if args.library == "tetra3rs":
        res = run_tetra3rs(images, args.database)
    else:
        cents = json.load(open(args.centroids)) if args.centroids else None
        res = run_cedar(images, cents)
    table(res, args.library)
    if args.output:
        json.dump(res, open(args.output, "w"))


if __name__ == "__main__":
    main()
