"""Layering: the numerical core and the methods import without ROS; the core imports no
higher layer.  (A user without ROS can calibrate bags; a fix in a method cannot drag rclpy
into the core.)"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "stellar_cal_ros"


def _modules(sub: str) -> list[str]:
    return sorted(f"stellar_cal_ros.{sub}.{p.stem}" for p in (PKG / sub).glob("*.py")
                  if p.stem != "__init__")


def test_core_and_methods_import_with_rclpy_unavailable():
    mods = _modules("core") + _modules("effects") + _modules("methods") + \
        _modules("diagnosis") + _modules("sim") + _modules("sky")
    code = ("import sys\n"
            "for m in ('rclpy', 'stellar_cal_msgs', 'sensor_msgs'):\n"
            "    sys.modules[m] = None  # any import of them raises ImportError\n"
            f"import importlib\nfor m in {mods!r}:\n    importlib.import_module(m)\n"
            "assert not [m for m in sys.modules if m.startswith('rclpy.')]\n"
            "print(len(" + repr(mods) + "))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert int(proc.stdout.strip()) == len(mods) > 30


def test_core_imports_no_higher_layer():
    bad = []
    for path in (PKG / "core").glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            for n in names:
                if n.startswith("stellar_cal_ros.") and not n.startswith(
                        ("stellar_cal_ros.core", "stellar_cal_ros.errors")):
                    bad.append(f"{path.name}: {n}")
                if n.split(".")[0] in ("rclpy", "mcap", "rosbags"):
                    bad.append(f"{path.name}: {n}")
    assert not bad, bad
