"""The ``stellar-cal solve`` command (contract §5): star images → a contract bag + prior."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_solve_parser(sub) -> None:
    """Register ``solve`` on the ``stellar-cal`` sub-parsers."""
    s = sub.add_parser(
        "solve", help="star images -> identified centroids in a contract bag + BAG.prior.yaml")
    s.add_argument("images", nargs="+", metavar="IMAGE",
                   help="8-bit JPEG/PNG, 16-bit PNG/TIFF or FITS frames of one camera")
    s.add_argument("-o", "--output", type=Path, required=True, metavar="BAG.mcap",
                   help="bag to write (BAG.prior.yaml beside it)")
    s.add_argument("--stamps", type=Path, metavar="STAMPS.csv",
                   help="CSV with columns file,utc (ISO 8601 UTC, mid-exposure); default: "
                        "the image's own time (FITS DATE-OBS, EXIF with offset)")
    s.add_argument("--site", metavar="LAT,LON,H",
                   help="observing site (deg, deg, m above WGS84): written as /gnss/fix")
    s.add_argument("--fov", type=float, metavar="DEG",
                   help="horizontal field of view estimate (default: searched over 5-30 deg)")
    s.set_defaults(func=_cmd_solve)


def _cmd_solve(args: argparse.Namespace) -> int:
    from stellar_cal_ros.sky.solve import parse_site, read_stamps, solve_images, write_solve

    site = parse_site(args.site) if args.site else None
    stamps = read_stamps(args.stamps) if args.stamps else None
    res = solve_images([str(p) for p in args.images], args.fov, stamps)
    paths = write_solve(res, args.output, site)
    n_ok = 0
    for s in sorted(res.solved, key=lambda s: s.stamp_ns):
        ident = s.identification
        n_ok += ident.status != "failed"
        flags = ident.ambiguous.sum() + ident.conflicting.sum() + ident.gated.sum()
        print(f"{Path(s.image.path).name}: {len(s.centroids)} stars, {ident.status}, "
              f"{ident.n_identified} identified ({int(flags)} flagged, "
              f"{int(ident.not_hipparcos.sum())} outside Hipparcos), "
              f"RMS {ident.rmse_arcsec:.1f} arcsec")
    cam = res.camera
    print(f"solve: {n_ok} of {len(res.solved)} images identified; focal length "
          f"{cam.fx:.2f} +- {res.sigma_f:.2f} px; wrote {paths['bag']} and {paths['prior']}")
    return 0 if n_ok else 1
