"""The benchmark scripts import only what the package has (a script doc/benchmarks.md quotes
must run: swaying_bound.py had imported a function moved out of methods/swaying.py)."""

from __future__ import annotations

import ast
import importlib
import importlib.util
from pathlib import Path

import pytest

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


def test_node_latency_split_adds_up_to_the_end_to_end_latency():
    """benchmarks/node_latency.py's end-to-end split: for a frame released by an IMU sample
    and one released by its own arrival, wait + publish + queue + compute + deliver is the
    end-to-end time, the node's busy callbacks count only inside the queue, and frames of
    the start-up or without a receipt are left out."""
    spec = importlib.util.spec_from_file_location("node_latency", BENCHMARKS / "node_latency.py")
    nl = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(nl)
    s = 10**9
    # frame A (stamp 20 s) published at 1.000, released by IMU stamp 20.05 s published at
    # 1.050 (publish() returned 1.052); callback 1.055 (the view tick ran 1.053-1.054);
    # residuals out 1.057, received 1.060.  Frame B (21 s) released by its own arrival.
    pub_t = {20 * s: 1.000, 20 * s + 5 * 10**7: 1.050, 21 * s: 2.000, 5 * s: 0.1}
    pub_done = {20 * s: 1.0005, 20 * s + 5 * 10**7: 1.052, 21 * s: 2.001, 5 * s: 0.1}
    rx = {20 * s: 1.060, 21 * s: 2.010, 5 * s: 0.2}
    res = {"frames": [[20 * s, 1.001, 1.055, 0, 20 * s + 5 * 10**7, 1.057],
                      [21 * s, 2.003, 2.003, 1, 0, 2.006],
                      [22 * s, 3.0, 3.0, 1, 0, 3.0],  # no receipt: left out
                      [5 * s, 0.1, 0.1, 1, 0, 0.15]],  # before the settle time: left out
           "busy": [["view", 1.053, 1.054], ["diagnostics", 1.0, 1.01]]}
    out = nl._split_report(res, pub_t, pub_done, rx, settle_ns=10 * s)
    assert out["frames"] == 2
    a = max(out["tail"], key=lambda r: r["e2e"])
    assert [a[k] for k in ("e2e", "wait", "publish", "queue", "compute", "deliver",
                           "busy_ms")] == pytest.approx([60.0, 50.0, 2.0, 3.0, 2.0, 3.0, 1.0])
    assert a["busy"] == ["view"]
    b = {k: out[k]["p50"] * 2 - a[k] for k in ("e2e", "wait", "queue", "compute")}
    assert [b[k] for k in ("e2e", "wait", "queue", "compute")] == pytest.approx(
        [10.0, 0.0, 2.0, 3.0])  # frame B: 2.000 -> 2.010, released on arrival
