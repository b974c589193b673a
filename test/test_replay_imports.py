"""What a replay process imports (issue 24.1: its fixed start-up cost).

A psce replay does not import ``scipy.spatial`` (with it ``scipy.sparse`` and
``scipy.special``: ~0.1 CPU-s; the calibration's installation is kept as its quaternion,
:mod:`~stellar_cal_ros.core.rotation`'s ``scipy_*`` give ``Rotation``'s floats), nor the
other methods' modules (the ACF, bundle and IAC files: the registry imports only the file
declaring ``psce``), nor ``scipy.optimize``, nor ``coverage`` (numba reads it when installed:
:func:`stellar_cal_ros.core.jit._import_numba`).
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

from sim_bags import psce_bag


def test_a_psce_replay_imports_neither_scipy_spatial_nor_other_methods(tmp_path) -> None:
    bag, prior, _ = psce_bag(30.0)
    out = tmp_path / "r.yaml"
    code = textwrap.dedent(f"""
        import sys
        covered = "coverage" in sys.modules  # (a coverage run of this process: it stays)
        from stellar_cal_ros.cli import main
        assert main(["replay", {str(bag)!r}, "--method", "psce", "--prior", {str(prior)!r},
                     "-o", {str(out)!r}, "-q"]) == 0
        bad = ("scipy.spatial", "scipy.sparse", "scipy.special", "scipy.optimize",
               "stellar_cal_ros.methods.acf", "stellar_cal_ros.methods.bundle",
               "stellar_cal_ros.methods.iac")
        print(sorted(m for m in sys.modules if m.startswith(bad)))
        print("stellar_cal_ros.methods.psce" in sys.modules, "numba" in sys.modules)
        print(covered or "coverage" not in sys.modules)
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=600, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = proc.stdout.splitlines()
    assert lines[-3] == "[]", lines[-3][:2000]
    assert lines[-2] == "True True"  # (the check sees the replay's own modules)
    assert lines[-1] == "True"  # numba's import does not read coverage (core.jit)
    assert "installation:" in out.read_text()
