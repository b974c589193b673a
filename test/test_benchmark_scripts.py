"""The benchmark scripts import only what the package has (a script doc/benchmarks.md quotes
must run: swaying_bound.py had imported a function moved out of methods/swaying.py)."""

from __future__ import annotations

import ast
import importlib
import importlib.util
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def test_every_package_name_a_benchmark_imports_exists():
    missing = []
    scripts = sorted(BENCHMARKS.glob("*.py"))
    for path in scripts:
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith(
                    "stellar_cal_ros"):
                module = importlib.import_module(node.module)
                missing += [f"{path.name}:{node.lineno}: {node.module}.{a.name}"
                            for a in node.names if not hasattr(module, a.name) and not (
                                hasattr(module, "__path__")  # a submodule of a package
                                and importlib.util.find_spec(f"{node.module}.{a.name}"))]
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.startswith("stellar_cal_ros"):
                        importlib.import_module(a.name)
    assert len(scripts) > 20 and not missing, missing
