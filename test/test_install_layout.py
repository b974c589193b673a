"""Install layouts: the venv made by scripts/setup.sh and a colcon (ament_python) build.

- ``pip install -e .`` (setup.sh) must put the console scripts in the venv's ``bin``
  (pip builds a wheel and ignores setup.cfg's ``[install] install_scripts``).
- ``colcon build`` of the root package must give the layout ``ros2 run`` needs:
  ``lib/stellar_cal_ros/<exe>`` and the ament index marker (see doc/ros_build.md).
- colcon stops descending at the repo root (a package), so ``msg_defs/`` is only found
  when named explicitly.
"""

import os
import subprocess
import sys
from importlib.metadata import distribution
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
VENV_BIN = Path(sys.prefix) / "bin"
EXECUTABLES = ("stellar-cal", "calibrator", "player")


def colcon_env(tmp_path):
    """Environment for colcon: this venv first on PATH, no user colcon defaults."""
    env = dict(os.environ)
    env["PATH"] = f"{VENV_BIN}{os.pathsep}{env.get('PATH', '')}"
    env["COLCON_HOME"] = str(tmp_path / "colcon_home")
    env.pop("COLCON_DEFAULTS_FILE", None)
    return env


def run_colcon(args, tmp_path, timeout):
    colcon = VENV_BIN / "colcon"
    assert colcon.exists(), f"{colcon} missing: run bash scripts/setup.sh"
    proc = subprocess.run(
        [str(colcon), "--log-base", str(tmp_path / "log"), *args],
        cwd=tmp_path, env=colcon_env(tmp_path), capture_output=True, text=True, timeout=timeout,
    )
    assert proc.returncode == 0, f"colcon {' '.join(args)} failed:\n{proc.stdout}\n{proc.stderr}"
    return proc.stdout


def test_venv_console_scripts_exist():
    assert sys.prefix != sys.base_prefix, "tests must run in the project venv (.venv/bin/python)"
    for name in EXECUTABLES:
        script = VENV_BIN / name
        assert script.is_file(), f"{script} missing: run bash scripts/setup.sh"
        assert os.access(script, os.X_OK)
        shebang = script.read_text().splitlines()[0]
        assert shebang.startswith("#!") and str(VENV_BIN) in shebang, shebang


def test_entry_points_declared():
    eps = {ep.name: ep.value for ep in distribution("stellar_cal_ros").entry_points
           if ep.group == "console_scripts"}
    expected = {
        "stellar-cal": "stellar_cal_ros.cli:main",
        "calibrator": "stellar_cal_ros.nodes.calibrator:main",
        "player": "stellar_cal_ros.nodes.player:main",
    }
    assert {name: eps.get(name) for name in expected} == expected


def test_colcon_discovers_msg_defs_only_when_named(tmp_path):
    # The root is an ament_python package, so colcon does not crawl below it ...
    out = run_colcon(["list", "--names-only", "--base-paths", str(ROOT)], tmp_path, 60)
    assert out.split() == ["stellar_cal_ros"]
    # ... and msg_defs/ must be given explicitly (as doc/ros_build.md says).
    out = run_colcon(["list", "--names-only", "--paths", str(ROOT), str(ROOT / "msg_defs")],
                     tmp_path, 60)
    assert sorted(out.split()) == ["stellar_cal_msgs", "stellar_cal_ros"]


def test_colcon_build_gives_ros2_run_layout(tmp_path):
    run_colcon(
        ["build", "--paths", str(ROOT),
         "--build-base", str(tmp_path / "build"), "--install-base", str(tmp_path / "install")],
        tmp_path, 120,
    )
    prefix = tmp_path / "install" / "stellar_cal_ros"
    for name in EXECUTABLES:
        exe = prefix / "lib" / "stellar_cal_ros" / name
        installed = sorted(str(p.relative_to(prefix)) for p in prefix.rglob("*"))
        assert exe.is_file(), f"{exe} missing; installed: {installed}"
        assert os.access(exe, os.X_OK)
    marker = prefix / "share" / "ament_index" / "resource_index" / "packages" / "stellar_cal_ros"
    assert marker.is_file()
    assert (prefix / "share" / "stellar_cal_ros" / "package.xml").is_file()
    pyver = f"python{sys.version_info.major}.{sys.version_info.minor}"
    site = prefix / "lib" / pyver / "site-packages"
    assert (site / "stellar_cal_ros" / "__init__.py").is_file()
    assert not (site / "test").exists(), "the test directory must not be installed as a package"


@pytest.mark.parametrize("name", ["calibrator", "player", "star_extractor"])
def test_node_modules_have_main(name):
    module = __import__(f"stellar_cal_ros.nodes.{name}", fromlist=["main"])
    assert callable(module.main)
