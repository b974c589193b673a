"""Reduced PSCE reproduction benchmark (``pytest -m benchmark``): 5 runs × 300 s at the
paper's 0.05 px / 0.001 °/√h setting.  Full form: ``benchmarks/psce_vs_paper.py``."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))


@pytest.mark.benchmark
def test_reduced_monte_carlo_consistent_and_efficient():
    from psce_vs_paper import run_once

    runs = [run_once(300.0, 2000 + r) for r in range(5)]
    dof = len(runs[0].err)
    nees = np.mean([r.nees for r in runs])
    lo, hi = chi2.ppf([0.005, 0.995], dof * len(runs)) / len(runs)
    assert lo <= nees <= hi, (nees, lo, hi)
    nis_dof = sum(r.nis_dof for r in runs)
    nis = sum(r.nis_sum for r in runs) / nis_dof
    lo, hi = chi2.ppf([0.0005, 0.9995], nis_dof) / nis_dof
    assert lo <= nis <= hi, (nis, lo, hi)
    errs = np.array([r.err for r in runs])
    crlb = np.sqrt(np.mean([r.var for r in runs], axis=0))
    ratio = np.sqrt(np.mean(errs**2, axis=0)) / crlb
    # RMS of 5 samples / σ: χ(5)/√5 stays below 2.0 with > 99.9 % probability per parameter
    assert np.all(ratio < 2.2), ratio


@pytest.mark.benchmark
def test_reduced_table3_runs(capsys):
    from psce_vs_paper import table3

    table3(300.0, 1)
    out = capsys.readouterr().out
    assert "Psi_z" in out and "eq. pp" in out
