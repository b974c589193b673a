"""RSS of what a ``diagnose`` round imports, library by library (issue 24.2).

Runs ``stellar-cal diagnose BAG ...`` (the arguments after ``--``) in this process, keeps the
names in ``sys.modules`` at its end, then in a fresh process imports them again in groups
(the interpreter, numpy, numba with llvmlite, scipy without ``scipy.signal`` /
``scipy.stats``, those two, the other third-party modules, the package's own) and prints the
RSS each group adds.  A group's figure depends on what came before it (shared libraries,
numpy pulled by the first user), so the order is fixed.  ``--modules FILE`` skips the round
and reads the names a former run wrote.

Run::

    python benchmarks/round_imports.py --save MODS.json -- diagnose BAG --calibration R.yaml \
        --method psce --no-plots --workers 0 -o OUT
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

GROUPS = (
    ("numpy", ("numpy",)),
    ("numba + llvmlite", ("numba", "llvmlite")),
    ("scipy (no signal, stats)", ("scipy",)),
    ("scipy.signal + scipy.stats", ("scipy.signal", "scipy.stats")),
    ("coverage (numba's coverage_support)", ("coverage",)),
    ("other third-party", None),
    ("stellar_cal_ros", ("stellar_cal_ros",)),
)

_CHILD = r"""
import importlib, json, sys
import psutil
proc = psutil.Process()
rss = lambda: proc.memory_info().rss / 2**20
groups = json.loads(sys.argv[1])
print(f"{'interpreter (+ psutil)':40s} {rss():7.1f} {rss():7.1f}")
for label, names in groups:
    before = rss()
    for name in names:
        try:
            importlib.import_module(name)
        except Exception:  # a module only importable in its parent's context
            pass
    print(f"{label:40s} {rss() - before:7.1f} {rss():7.1f}")
"""


def _group(name: str) -> str:
    """The label of ``GROUPS`` a module name falls in."""
    for label, prefixes in GROUPS:
        if prefixes and any(name == p or name.startswith(p + ".") for p in prefixes):
            if label.startswith("scipy (") and name.startswith(("scipy.signal", "scipy.stats")):
                continue
            return label
    return "other third-party"


def main() -> int:
    """Run the round (or read its modules), then measure the groups in a fresh process."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--modules", help="the module names of a former run (JSON)")
    parser.add_argument("--save", help="write the round's module names here (JSON)")
    parser.add_argument("command", nargs=argparse.REMAINDER)
    args = parser.parse_args()
    if args.modules:
        with open(args.modules, encoding="utf-8") as f:
            names = json.load(f)
    else:
        from stellar_cal_ros.cli import main as cli_main

        command = [a for a in args.command if a != "--"]
        cli_main(command)
        names = sorted(n for n in sys.modules if not n.startswith(("__main__", "__mp_main__")))
        if args.save:
            with open(args.save, "w", encoding="utf-8") as f:
                json.dump(names, f)
    names = [n for n in names if not n.startswith(("_", "encodings"))]
    order = [label for label, _ in GROUPS]
    grouped = {label: [] for label in order}
    for name in names:
        grouped[_group(name)].append(name)
    print(f"{len(names)} modules imported by the round")
    print(f"{'group':40s} {'+MiB':>7s} {'RSS MiB':>7s}")
    payload = json.dumps([(label, grouped[label]) for label in order])
    return subprocess.call([sys.executable, "-c", _CHILD, payload])


if __name__ == "__main__":
    sys.exit(main())
