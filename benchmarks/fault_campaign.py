"""Fault campaign: every variant of stellar_cal_ros.sim.faults through the CLI, judged.

Builds a clean simulated run (``psce_rotations``, 300 s by default), derives every faulty
variant from it (damaged bytes, messages, times, topics, units, priors), runs each command
the variant names (``replay``, ``replay --on-error skip``, ``batch --method acf``,
``diagnose``, ``info``) in a subprocess with a timeout, and prints one line per run:
variant, command, expected outcome class(es), the outcome seen, the key number (equivalent
principal point error against the truth, px) next to the clean run's on the same data, the
run time and the verdict (see stellar_cal_ros.sim.fault_campaign).

Usage::

    .venv/bin/python benchmarks/fault_campaign.py               # the full table
    .venv/bin/python benchmarks/fault_campaign.py --reduced     # the default-suite set
    .venv/bin/python benchmarks/fault_campaign.py --only imu_ --commands batch
    .venv/bin/python benchmarks/fault_campaign.py --code ../other_checkout   # judge another

Exit status 1 if any run crashed, hung or was silently wrong.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from stellar_cal_ros.sim.fault_campaign import Campaign, format_rows, format_table  # noqa: E402
from stellar_cal_ros.sim.faults import catalogue, make_base  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    """Run the campaign and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=300.0, help="clean run length, s")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--reduced", action="store_true", help="only the default-suite variants")
    ap.add_argument("--only", default="", help="comma-separated variant name prefixes")
    ap.add_argument("--commands", default="", help="comma-separated commands to run")
    ap.add_argument("--timeout", type=float, default=300.0, help="per run, s (hang)")
    ap.add_argument("--workdir", type=Path, default=None, help="keep the files here")
    ap.add_argument("--code", type=Path, default=None,
                    help="root of another checkout whose CLI to judge (default: this one)")
    args = ap.parse_args(argv)
    variants = [v for v in catalogue() if not args.reduced or v.reduced]
    if args.only:
        pre = [p.strip() for p in args.only.split(",") if p.strip()]
        variants = [v for v in variants if any(v.name.startswith(p) for p in pre)]
    commands = {c.strip() for c in args.commands.split(",") if c.strip()} or None
    with tempfile.TemporaryDirectory(prefix="fault_campaign_") as tmp:
        work = args.workdir or Path(tmp)
        t0 = time.perf_counter()
        base = make_base(work / "base", duration=args.duration, seed=args.seed)
        camp = Campaign(base, work, timeout=args.timeout, code=args.code)
        rows = []
        for v in variants:
            new = camp.run(v, commands)
            rows += new
            print("\n".join(format_rows(new)), file=sys.stderr, flush=True)
        clean = ", ".join(f"{c} {r.key:.4f} px / {r.installation:.1f}\" in {r.seconds:.1f} s"
                          for (c, _), r in camp._clean.items()
                          if r.key is not None and _ == str(base.bag))
        print(f"== fault campaign: {len(variants)} variants, {len(rows)} runs, clean "
              f"psce_rotations {args.duration:.0f} s seed {args.seed} "
              f"({time.perf_counter() - t0:.0f} s) ==")
        print(f"clean runs (eq. principal point error / installation error): {clean}")
        print(format_table(rows))
    bad = [r for r in rows if r.verdict in ("CRASH", "HANG", "SILENT")]
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
