"""Layering: every package of stellar_cal_ros sits in one layer and imports only lower layers
(and itself); no module imports another that imports it back, counting every import —
function-level and ``TYPE_CHECKING`` ones too; and everything but the ROS nodes imports
without ROS.  (A user without ROS can calibrate bags; a fix in a method cannot drag rclpy
into the core; a new package must be given its layer here.)"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "stellar_cal_ros"

#: layer of each package / top-level module, lowest first (core < effects < io < sky < methods <
#: sim < diagnosis < viz < apps < cli); within a layer a package imports only itself
LAYERS: dict[str, int] = {
    "__init__": 0, "errors": 0, "progress": 0,  # the package's version, errors, progress
    "core": 1,  # pure numpy: rotations, camera, IMU, covariance, state blocks, catalogue
    "effects": 2,  # the library of physical effects, one file each
    "io": 3,  # bags, calibration files, residual tables, checkpoints
    "sky": 4,  # star images: extraction and identification
    "methods": 5, "budget": 5,  # the estimation methods; the error budget
    "sim": 6,  # the simulator (renders through the effects and the star model)
    "diagnosis": 7,  # model discovery, reports
    "viz": 8,  # the view's channels and pictures (replay --viz and the node's live view)
    # applications: the ROS nodes, the demo, campaigns, result commands ...
    "nodes": 9, "demo": 9, "campaign": 9, "results_cli": 9,
    "cli": 10, "__main__": 11,  # ... and the command line that dispatches to them
}
#: the only packages that may import rclpy / ROS message packages
ROS_PACKAGES = {"nodes"}
#: third-party libraries the core must not import (it is pure numpy/scipy)
NOT_IN_CORE = ("rclpy", "mcap", "rosbags", "mcap_ros2", "dask", "distributed", "matplotlib")


def _modules() -> dict[str, Path]:
    out = {}
    for path in PKG.rglob("*.py"):
        parts = path.relative_to(PKG.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def _package(module: str) -> str:
    parts = module.split(".")
    return "__init__" if len(parts) == 1 else parts[1]


def _imports(path: Path) -> list[str]:
    """Every module name an import statement of the file names (anywhere in it)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append(node.module)
            out += [f"{node.module}.{a.name}" for a in node.names]
    return out


def _graph() -> dict[str, set[str]]:
    mods = _modules()
    edges: dict[str, set[str]] = defaultdict(set)
    for name, path in mods.items():
        for target in _imports(path):
            if target in mods and target != name:
                edges[name].add(target)
    return edges


def test_every_package_has_a_layer():
    packages = {_package(m) for m in _modules()}
    assert not packages - set(LAYERS), f"give these a layer in LAYERS: {packages - set(LAYERS)}"


def test_packages_import_only_lower_layers():
    bad = []
    for module, targets in _graph().items():
        src = _package(module)
        for target in targets:
            dst = _package(target)
            if dst != src and LAYERS[dst] >= LAYERS[src] and dst != "__init__":
                bad.append(f"{module} ({src}, layer {LAYERS[src]}) imports {target} "
                           f"({dst}, layer {LAYERS[dst]})")
    assert not bad, "\n".join(sorted(bad))


def test_no_import_cycles():
    """No strongly connected component of more than one module (Tarjan)."""
    edges = _graph()
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    cycles: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))
    for v in _modules():
        if v not in index:
            visit(v)
    assert not cycles, cycles


def test_core_imports_no_io_or_ros_library():
    bad = [f"{m}: {t}" for m, p in _modules().items() if _package(m) == "core"
           for t in _imports(p) if t.split(".")[0] in NOT_IN_CORE]
    assert not bad, bad


def test_everything_but_the_nodes_imports_with_rclpy_unavailable():
    mods = sorted(m for m in _modules() if _package(m) not in ROS_PACKAGES
                  and not m.endswith("__main__"))
    code = ("import sys\n"
            "for m in ('rclpy', 'stellar_cal_msgs', 'sensor_msgs', 'tf2_msgs'):\n"
            "    sys.modules[m] = None  # any import of them raises ImportError\n"
            f"import importlib\nfor m in {mods!r}:\n    importlib.import_module(m)\n"
            "assert not [m for m in sys.modules if m.startswith('rclpy.')]\n"
            "print(len(" + repr(mods) + "))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert int(proc.stdout.strip()) == len(mods) > 100


def test_the_architecture_page_draws_these_layers():
    """doc/architecture.md's layer diagram names every package with its layer here."""
    text = (PKG.parent / "doc" / "architecture.md").read_text(encoding="utf-8")
    diagram = text.split("## Layers", 1)[1].split("```")[1]
    drawn: dict[str, int] = {}
    number = None
    for line in reversed(diagram.splitlines()):  # a package's number ends its last line
        m = re.search(r"\s(\d+)$", line)
        number = int(m.group(1)) if m else number
        for name in re.findall(r"([a-z_]+)(?:/|\.py)", line):
            drawn.setdefault(name, number)
    expected = {k: v for k, v in LAYERS.items() if k not in ("__init__", "__main__")}
    assert {k: drawn.get(k) for k in expected} == expected
