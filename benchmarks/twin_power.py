"""Power at a printed MDB on the user's own bag: twins with the effect, each discovered.

A user's calibrated bag (``stellar-cal discover --auto`` gave ``RESULT/calibration.yaml``
and printed the MDBs) is rendered again by ``stellar-cal twin`` with one effect at a given
value, with fresh noise per twin seed, and each twin is diagnosed as the user would
(``stellar-cal discover --auto``).  Per seed: whether the effect was added, and round 1's
score, p and reason, and the ties said (an added effect named with one this motion does not
tell from it); then the counts (issue 21 item 2: 80 % +- 15 % at the printed MDB).
Run::

    python benchmarks/twin_power.py BASE.mcap RESULT/calibration.yaml swaying_base \
        gyro_scale_factor 0,0,1.40171e-05 101-120 OUT
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path


def main() -> int:
    """Make and discover the twins of the command line; print one row a twin and the count."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("bag")
    ap.add_argument("calibration")
    ap.add_argument("method")
    ap.add_argument("effect")
    ap.add_argument("value", help="the effect's parameters, comma-separated (--effect's)")
    ap.add_argument("seeds", help="first-last twin seeds")
    ap.add_argument("out", type=Path)
    ap.add_argument("--keep", action="store_true", help="keep the twins' bags (OUT/tK.mcap)")
    a = ap.parse_args()
    exe = str(Path(sys.executable).with_name("stellar-cal"))
    a.out.mkdir(parents=True, exist_ok=True)
    first, last = map(int, a.seeds.split("-"))
    found = flagged = told = 0
    for k in range(first, last + 1):
        twin = a.out / f"t{k}.mcap"
        subprocess.run([exe, "twin", a.bag, "--calibration", a.calibration, "-o", str(twin),
                        "--effect", f"{a.effect}={a.value}", "--seed", str(k)], check=True,
                       capture_output=True)
        d = a.out / f"t{k}.d"
        subprocess.run([exe, "discover", str(twin), "--calibration",
                        str(a.out / f"t{k}.prior.yaml"), "--method", a.method, "--auto", "-o",
                        str(d), "--no-plots", "--workers", "0"], capture_output=True)
        s = json.loads((d / "diagnosis.json").read_text())
        added = a.effect in s.get("added", [])
        first_round = s["path"][0]
        mine = first_round.get("added") or {}
        if mine.get("effect") != a.effect:
            mine = next((x for x in first_round.get("rejected", [])
                         if x.get("effect") == a.effect), {})
        # significant in round 1 though another effect went first ("behind X")
        behind = "significant alone" in (mine.get("reason") or "")
        found += added
        flagged += added or behind
        # an added effect named with the one this motion does not tell from it
        ties = {e: t["with"] for e, t in (s.get("ties") or {}).items()}
        told += any(a.effect in (e, w) for e, w in ties.items())
        # each tie's p on the dof its test counted (the seen directions; before: nominal)
        said = {e: f"{t['with']} p {t['p_value']:.2g} dof "
                   + (f"{t['dof']:.2f}" if "dof" in t else "nominal")
                for e, t in (s.get("ties") or {}).items()}
        print(f"{k:5d} {'added' if added else 'missed':7s} {s.get('added', [])} score "
              f"{mine.get('score', float('nan')):.3g} p {mine.get('p_value', float('nan')):.2g} "
              f"{mine.get('reason') or ''}{f' tie {said}' if said else ''}", flush=True)
        if not a.keep:
            twin.unlink(missing_ok=True)
    n = last - first + 1
    print(f"{a.effect}={a.value}: added {found} of {n}, significant in round 1 {flagged} of {n}"
          f", named in a tie {told} of {n}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
