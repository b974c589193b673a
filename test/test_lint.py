"""Style checks with the venv's ruff; pyproject.toml selects the rules (pydocstyle = "D").

ruff runs once (JSON output, every rule of the pyproject selection); the findings are
split into the docstring (pydocstyle, ``D``) rules and the rest, so a failure names its kind.
"""

import functools
import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.linter

ROOT = Path(__file__).resolve().parents[1]
RUFF = Path(sys.prefix) / "bin" / "ruff"
TARGETS = ["stellar_cal_ros", "test", "benchmarks", "setup.py"]


@functools.cache
def findings():
    """All ruff findings (list of dicts) for TARGETS with the pyproject configuration."""
    assert RUFF.exists(), f"{RUFF} missing: run bash scripts/setup.sh"
    proc = subprocess.run(
        [str(RUFF), "check", "--no-cache", "--exit-zero", "--output-format=json", *TARGETS],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 0, f"ruff did not run:\n{proc.stdout}\n{proc.stderr}"
    return json.loads(proc.stdout or "[]")


def report(items):
    lines = []
    for f in items:
        path = Path(f["filename"]).resolve()
        try:
            path = path.relative_to(ROOT)
        except ValueError:
            pass
        loc = f.get("location") or {}
        lines.append(f"{path}:{loc.get('row')}:{loc.get('column')}: {f['code']} {f['message']}")
    return "\n".join(lines)


def test_ruff_check():
    """pycodestyle, pyflakes, isort, bugbear, pep8-naming, pyupgrade (pyproject selection)."""
    bad = [f for f in findings() if not (f["code"] or "").startswith("D")]
    if bad:
        pytest.fail(f"ruff check: {len(bad)} problem(s):\n{report(bad)}", pytrace=False)


def test_docstrings_pydocstyle_rules():
    """The pydocstyle rules (ruff's D), as configured in pyproject.toml."""
    bad = [f for f in findings() if (f["code"] or "").startswith("D")]
    if bad:
        pytest.fail(f"docstrings: {len(bad)} problem(s):\n{report(bad)}", pytrace=False)
