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


def test_printed_report_lines_close_their_parentheses():
    """The report printers' lines (noise, an installation step's line at rest, over moving
    frames, before the window and fitted, every 'unexplained' size phrase and every cause a
    line follows): parentheses that close, none nested to a '))' (``printed_text``).  On
    main 423125a: "noise as stated (... gyro x1 +- 0.0043 (its samples))", "... the largest
    of 600 frames (the platform never rests))", "... told apart))", "0.029 px at most (99 %
    of the stars; what the fit left of it))", "... from the bands beside it))", "(left by
    the cells))"."""
    from printed_text import parentheses_problems

    from stellar_cal_ros.core.noise import NoiseScales
    from stellar_cal_ros.diagnosis import installation_step as steps
    from stellar_cal_ros.diagnosis import leads, noise, printing
    from stellar_cal_ros.diagnosis.auto import FITTED_STEP

    v = noise.NoiseVerdict(NoiseScales(), NoiseScales(), star=0.979, star_sigma=0.0091)
    v.samples = {"accel": {"scale": 0.991, "sigma": 0.0052, "white": True},
                 "gyro": {"scale": 1.01, "sigma": 0.0043, "white": True}}
    lines = v.lines()
    assert any("its samples" in x for x in lines), lines  # (the clause rendered)
    for at_rest in (True, False):
        step = steps.InstallationStep(59.5, 59.25, [-9.45, 17.3, 0.1], [0.2, 0.2, 5.0], 0.38,
                                      0.005, 29.0, 96.0, 600, 1e-9, at_rest)
        for where in ("", steps.MOVING, steps.BEFORE):
            for sized in ("", FITTED_STEP):
                lines.append(step.regressor(where, sized))
    summary = {"unexplained": [
        {"regressor": "catalogue star", "component": "u, v", "statistic": 29.5,
         "p_value": 1e-60, "change_px": 0.0106},
        {"regressor": "u (column) (fixed pattern, bands of 8 px)", "component": "u",
         "statistic": 7.4, "p_value": 1e-6, "change_px": 0.146},
        {"regressor": leads.REGRESSORS["magnitude"], "component": "u, v", "statistic": 13.5,
         "p_value": 1e-15, "change_px": 0.04, "detail": {"field": "magnitude"}},
        *({"regressor": leads.REGRESSORS["cells"], "component": "u, v", "statistic": 8.7,
           "p_value": 1e-10, "change_px": 0.029, "detail": {"field": "cells"},
           "follows": cause} for cause in printing.CAUSES)]}
    lines += printing.unexplained_lines(summary, n=len(summary["unexplained"]))
    bad = parentheses_problems(lines)
    assert not bad, "\n".join(bad)
