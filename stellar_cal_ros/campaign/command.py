"""``stellar-cal campaign SPEC.yaml -o OUT_DIR``: many runs on Dask, one Parquet table.

Kept light at import (the parser is built for every ``stellar-cal`` command).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_campaign_parser(sub) -> None:
    """Add the ``campaign`` subcommand to ``stellar-cal``'s subparsers."""
    c = sub.add_parser(
        "campaign", help="many simulate/replay/diagnose/budget runs on Dask",
        description="Expand SPEC.yaml into runs (scenarios x effects x seeds, or a fleet of "
                    "bags), execute those not done yet on a Dask cluster, write "
                    "OUT_DIR/results.parquet (one row per run) and a summary report. "
                    "See doc/budget.md.")
    c.add_argument("spec", type=Path, help="SPEC.yaml")
    c.add_argument("-o", "--output", required=True, type=Path, help="OUT_DIR")
    c.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="an existing Dask scheduler (default: start a local cluster)")
    c.add_argument("--workers", type=int, default=None,
                   help="local cluster: worker processes (default: one per core)")
    c.add_argument("--dry-run", action="store_true",
                   help="list the runs and which are done, run nothing")
    c.add_argument("-q", "--quiet", action="store_true", help="no progress")
    c.set_defaults(func=run_campaign_command)


def run_campaign_command(args: argparse.Namespace) -> int:
    """Run ``stellar-cal campaign``."""
    from stellar_cal_ros.campaign.runner import _done, run_campaign
    from stellar_cal_ros.campaign.spec import read_campaign_spec, runs_from_spec
    from stellar_cal_ros.campaign.summary import format_summary, summarize, write_summary
    from stellar_cal_ros.errors import StellarCalError

    if args.workers is not None and args.workers < 1:
        raise StellarCalError("--workers must be at least 1")
    spec = read_campaign_spec(args.spec)
    runs = runs_from_spec(spec, args.spec.resolve().parent, args.output)
    args.output.mkdir(parents=True, exist_ok=True)
    (args.output / "spec.yaml").write_text(args.spec.read_text())
    done = sum(_done(args.output, r["key"]) for r in runs)
    print(f"campaign {spec.get('name', args.spec.stem)}: {len(runs)} runs, {done} already "
          f"done, {len(runs) - done} to run"
          + ("" if args.scheduler else f" on {args.workers or 'one per core'} local workers"))
    if args.dry_run:
        for r in runs:
            state = "done" if _done(args.output, r["key"]) else "todo"
            print(f"  {r['key']} {state} " + ", ".join(
                f"{k}={r[k]}" for k in ("label", "scenario", "duration", "seed", "bag",
                                        "method") if k in r))
        return 0
    res = run_campaign(runs, args.output, args.scheduler, args.workers, not args.quiet)
    print(f"ran {res.ran} runs in {res.seconds:.1f} s ({res.skipped} skipped as done, "
          f"{res.failed} failed)")
    for r in res.rows:
        if r.get("status") != "ok":
            print(f"  FAILED {r['key']}: {r.get('error')}")
    print(format_summary(summarize(res.rows)))
    html = write_summary(res.rows, args.output)
    print(f"wrote {res.parquet} and {html}")
    return 1 if res.failed else 0
