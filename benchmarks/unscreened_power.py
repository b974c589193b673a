"""Power at the MDB an unscreened round prints: the effect injected into a bag that does not fit.

An unseen case whose final model stays far from consistent (``dt_step``: a clock step
outside the library, final NIS/dof ~8) prints the MDBs of a round that is not screened
(issue 21 item 2).  A twin of its calibration is clean and cannot check them: here the
case itself is simulated again with the library effect added (``--effect`` of the
simulation, fresh noise per seed), ``discover --auto`` is run as the user would, and per
seed it counts whether the effect was found (added, or significant in a round).  Run::

    python benchmarks/unscreened_power.py dt_step gyro_scale_factor 1.27e-4,0,0 101-110 OUT
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import unseen_cases  # noqa: E402


def main() -> int:
    """Simulate, discover and count one row a seed."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    # the unseen case, the library effect, its parameters (comma-separated), first-last seeds
    for name in ("case", "effect", "value", "seeds"):
        ap.add_argument(name)
    ap.add_argument("out", type=Path)
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    value = [float(v) for v in a.value.split(",")]
    base = unseen_cases.CASES[a.case]
    name = f"{a.case}_inj"
    unseen_cases.CASES[name] = dataclasses.replace(
        base, sim_effects={**base.sim_effects, a.effect: value})
    first, last = map(int, a.seeds.split("-"))
    found = 0
    for k in range(first, last + 1):
        out = a.out / f"s{k}"
        out.mkdir(exist_ok=True)
        unseen_cases.write_case(name, out, k)
        exe = str(Path(sys.executable).with_name("stellar-cal"))
        d = out / "d"
        subprocess.run([exe, "discover", str(out / f"{name}.mcap"), "--calibration",
                        str(out / f"{name}.prior.yaml"), "--method", base.method, "--auto",
                        "-o", str(d), "--no-plots", "--workers", "0"], capture_output=True)
        s = json.loads((d / "diagnosis.json").read_text())
        added = a.effect in s.get("added", [])
        rows = []
        for i, rnd in enumerate(s["path"]):
            mine = rnd.get("added") or {}
            if mine.get("effect") != a.effect:
                mine = next((x for x in rnd.get("rejected", []) if x.get("effect") == a.effect),
                            {})
            rows.append((i + 1, mine.get("p_value"), mine.get("score"),
                         (mine.get("reason") or "")[:60]))
        sig = any("significant" in (r[3] or "") for r in rows)
        found += added or sig
        print(f"{k:5d} {'added' if added else 'missed':7s} {s.get('added', [])} "
              f"rounds {rows}", flush=True)
        (out / f"{name}.mcap").unlink(missing_ok=True)
    n = last - first + 1
    print(f"{a.case} {a.effect}={a.value}: found {found} of {n}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
