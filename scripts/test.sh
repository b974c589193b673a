#!/usr/bin/env bash
# Run the test suite: bring the environment up to date (scripts/setup.sh, quiet and
# idempotent), then pytest in the project's venv. Arguments go to pytest, e.g.
#   bash scripts/test.sh -m ros          bash scripts/test.sh -m benchmark test/test_x.py
# The default selection (pyproject addopts) leaves out the benchmarks.
# Without arguments the suite runs on every logical core (pytest-xdist, one file per worker
# at a time: a module's fixtures are built once, its tests run in order in one process);
# with arguments it runs in one process unless they say -n (benchmarks time themselves).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
VENV="${VENV:-$ROOT/.venv}"
export VENV

bash "$ROOT/scripts/setup.sh" --quiet

ARGS=("$@")
if [ "$#" -eq 0 ]; then
    ARGS=(-n logical --dist loadfile)
fi

rc=0
"$VENV/bin/python" -m pytest -q "${ARGS[@]}" || rc=$?
if [ "$rc" -eq 5 ]; then
    # pytest: "no tests were collected". With the default selection this is a broken suite,
    # not a success; with an explicit selection (-m/-k/paths) it is a selection that matched nothing.
    echo "test.sh: pytest collected no tests (exit 5) -- treating as failure" >&2
fi
exit "$rc"
