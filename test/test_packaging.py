"""Packaging tells the truth (issue 23, item 7): the wheel declares what the code imports, and
installed into a clean venv with just what it declares it calibrates a bag.

* ``install_requires`` (setup.py) covers every third-party module stellar_cal_ros imports,
  and nothing it does not import; requirements.txt's exact pins satisfy its bounds;
* ``python_requires`` matches the code (3.11: ``datetime.UTC``; ruff's target);
* package.xml has a key for every one of them (rosdistro's, or the repository's own in
  ``rosdep/stellar_cal_ros.yaml``) and for every ROS package the nodes import, and no
  ament linter that no test runs;
* the wheel, installed with ``--no-deps`` into a new venv whose site-packages holds only the
  distributions its requirements resolve to (linked from this venv: the files pip would
  install, without downloading them again), passes ``pip check`` and runs ``simulate`` and
  ``replay`` from its console script.
"""

from __future__ import annotations

import ast
import os
import shutil
import subprocess
import sys
import sysconfig
import xml.etree.ElementTree as ET
import zipfile
from importlib.metadata import distributions, packages_distributions
from pathlib import Path

import pytest
import yaml
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "stellar_cal_ros"

#: rosdistro's keys used in package.xml → the PyPI distribution each stands for (looked up in
#: ros/rosdistro rosdep/python.yaml); the repository's own keys are in rosdep/
ROSDISTRO_KEYS = {
    "python3-numpy": "numpy", "python3-scipy": "scipy", "python3-numba": "numba",
    "python3-yaml": "pyyaml", "python3-matplotlib": "matplotlib", "python3-pil": "pillow",
    "python3-tqdm": "tqdm", "python3-rosbags-pip": "rosbags", "python3-psutil": "psutil",
    "mcap-ros2-support": "mcap-ros2-support",
}
#: the ament linters the ros2pkg template lists (no test of this repository runs them)
AMENT_LINTERS = {"ament_copyright", "ament_flake8", "ament_pep257", "ament_lint_auto",
                 "ament_xmllint", "ament_mypy"}


def _setup_kwargs() -> dict:
    """``install_requires`` and ``python_requires`` as setup.py states them (no setuptools run)."""
    tree = ast.parse((ROOT / "setup.py").read_text())
    out = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", "") == \
                "install_requires":
            out["install_requires"] = ast.literal_eval(node.value)
        if isinstance(node, ast.keyword) and node.arg == "python_requires":
            out["python_requires"] = ast.literal_eval(node.value)
    return out


def _requirements() -> dict[str, Requirement]:
    return {canonicalize_name(r.name): r for r in map(
        Requirement, _setup_kwargs()["install_requires"])}


def _third_party_imports() -> dict[str, set[str]]:
    """Top-level module → files of the package importing it (stdlib and own excluded)."""
    out: dict[str, set[str]] = {}
    for path in PKG.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            for n in names:
                top = n.split(".")[0]
                if top not in sys.stdlib_module_names and top != "stellar_cal_ros":
                    out.setdefault(top, set()).add(path.relative_to(ROOT).as_posix())
    return out


def _package_xml() -> dict[str, list[str]]:
    root = ET.parse(ROOT / "package.xml").getroot()
    return {tag: [e.text.strip() for e in root.findall(tag)]
            for tag in ("exec_depend", "depend", "test_depend", "build_depend")}


def _own_rosdep_keys() -> dict[str, set[str]]:
    """The repository's rosdep keys → the distributions (pip) or Debian packages they install."""
    data = yaml.safe_load((ROOT / "rosdep" / "stellar_cal_ros.yaml").read_text())
    out = {}
    for key, rules in data.items():
        names = set()
        for rule in rules.values():
            names |= set(rule["pip"]["packages"]) if isinstance(rule, dict) else set(rule)
        out[key] = names
    return out


def test_install_requires_are_the_imports():
    imports = _third_party_imports()
    xml = _package_xml()
    ros = set(xml["exec_depend"]) | set(xml["depend"])
    dist_of = packages_distributions()
    reqs = _requirements()
    missing, used = [], set()
    for module, files in sorted(imports.items()):
        if module in ros:  # a ROS package: the nodes' client library and messages
            continue
        dists = {canonicalize_name(d) for d in dist_of.get(module, [])}
        assert dists, f"{module} (imported by {sorted(files)}) is not installed here"
        if not dists & set(reqs):
            missing.append(f"{module} ({', '.join(sorted(dists))}) imported by {sorted(files)}")
        used |= dists & set(reqs)
    assert not missing, "not in setup.py's install_requires:\n" + "\n".join(missing)
    assert not set(reqs) - used, f"declared but never imported: {sorted(set(reqs) - used)}"


def test_requirements_pins_satisfy_install_requires():
    pins = {}
    for line in (ROOT / "requirements.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if "==" in line and not line.startswith("-"):
            r = Requirement(line)
            pins[canonicalize_name(r.name)] = next(iter(r.specifier)).version
    for name, req in _requirements().items():
        assert name in pins, f"{name} is required by setup.py but not pinned in requirements.txt"
        assert req.specifier.contains(pins[name]), (name, str(req.specifier), pins[name])


def test_python_requires_matches_the_code():
    assert _setup_kwargs()["python_requires"] == ">=3.11"
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert 'target-version = "py311"' in pyproject
    # the code does use 3.11 (datetime.UTC, the command line's provenance stamp)
    assert "from datetime import UTC" in (PKG / "cli.py").read_text()


def test_package_xml_has_every_runtime_dependency():
    xml = _package_xml()
    keys = xml["exec_depend"] + xml["depend"]
    own = _own_rosdep_keys()
    assert not set(own) & set(ROSDISTRO_KEYS), "a key defined twice"
    stands_for: dict[str, set[str]] = {}
    for key in keys:
        if key in ROSDISTRO_KEYS:
            stands_for[key] = {ROSDISTRO_KEYS[key]}
        elif key in own:
            stands_for[key] = {canonicalize_name(n.removeprefix("python3-")) for n in own[key]}
    covered = set().union(*stands_for.values())
    assert not set(_requirements()) - covered, \
        f"no package.xml key for {sorted(set(_requirements()) - covered)}"
    assert not set(own) - set(keys), f"rosdep keys defined but unused: {set(own) - set(keys)}"
    # the ROS packages the code imports are ROS dependencies (the rest are Python keys)
    ros_imports = {m for m in _third_party_imports()
                   if m == "rclpy" or m.endswith("_msgs") or m.endswith("_srvs")
                   or m == "rcl_interfaces"}
    assert ros_imports <= set(keys), sorted(ros_imports - set(keys))
    python_keys = set(stands_for)
    assert set(keys) - python_keys == ros_imports, sorted(set(keys) - python_keys - ros_imports)
    assert not AMENT_LINTERS & set(xml["test_depend"] + keys)


def _resolve(requirements: list[Requirement], site: Path) -> dict[str, object]:
    """The distributions of ``site`` these requirements need, recursively (markers, extras)."""
    installed = {canonicalize_name(d.metadata["Name"]): d for d in distributions(path=[str(site)])}
    need: dict[str, set[str]] = {}
    todo = [(r, "") for r in requirements]
    while todo:
        req, extra = todo.pop()
        if req.marker is not None and not req.marker.evaluate({"extra": extra}):
            continue
        name = canonicalize_name(req.name)
        dist = installed.get(name)
        assert dist is not None, f"{req} is not installed in {site}"
        assert req.specifier.contains(dist.version, prereleases=True), (str(req), dist.version)
        new = name not in need or bool(set(req.extras) - need[name])
        need.setdefault(name, set()).update(req.extras)
        if new:
            todo += [(Requirement(s), e) for s in dist.requires or []
                     for e in ["", *sorted(req.extras)]]
    return {name: installed[name] for name in need}


def _build_wheel(tmp_path: Path) -> Path:
    """The wheel of a copy of the checkout's package sources (setuptools builds in place)."""
    src = tmp_path / "src"
    for name in ("setup.py", "setup.cfg", "package.xml", "README.md", "resource", "config",
                 "launch", "stellar_cal_ros"):
        if (ROOT / name).is_dir():
            shutil.copytree(ROOT / name, src / name,
                            ignore=shutil.ignore_patterns("__pycache__", "*.nbi", "*.nbc"))
        elif (ROOT / name).exists():
            src.mkdir(exist_ok=True)
            shutil.copy2(ROOT / name, src / name)
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps",
                    "--no-build-isolation", "-w", str(tmp_path / "dist"), str(src)],
                   check=True, capture_output=True, timeout=300)
    return next((tmp_path / "dist").glob("stellar_cal_ros-*.whl"))


def test_the_wheel_in_a_clean_venv_calibrates_a_bag(tmp_path):
    """Build the wheel, install it into a new venv holding only what it requires, replay."""
    site = Path(sysconfig.get_paths()["purelib"])
    wheel = _build_wheel(tmp_path)
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
        meta = z.read(next(n for n in names if n.endswith(".dist-info/METADATA"))).decode()
    assert not [n for n in names if n.startswith(("test/", "benchmarks/"))]
    assert "Requires-Python: >=3.11" in meta
    requires = [Requirement(line.split(":", 1)[1].strip()) for line in meta.splitlines()
                if line.startswith("Requires-Dist:")]
    assert {canonicalize_name(r.name) for r in requires} == set(_requirements())
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True,
                   timeout=120)
    py = venv / "bin" / "python"
    vsite = Path(subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig."
                                 "get_paths()['purelib'])"], capture_output=True, text=True,
                                check=True).stdout.strip())
    linked: set[str] = set()
    for dist in _resolve(requires, site).values():
        for f in dist.files or []:
            top = f.parts[0]
            if top not in linked and top not in ("..", "__pycache__") and \
                    not top.endswith(".pth") and (site / top).exists():
                (vsite / top).symlink_to(site / top)
                linked.add(top)
    assert "rclpy" not in linked  # ROS is not a pip requirement: the CLI runs without it
    # nothing of this checkout or venv on the path (PYTHONPATH would show pip the checkout's
    # own package as installed already)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    pip = [sys.executable, "-m", "pip", "--python", str(py)]
    subprocess.run(pip + ["install", "-q", "--no-deps", "--no-index", str(wheel)], check=True,
                   capture_output=True, timeout=300, env=env, cwd=tmp_path)
    check = subprocess.run(pip + ["check"], capture_output=True, text=True, timeout=120,
                           env=env, cwd=tmp_path)
    assert check.returncode == 0, check.stdout + check.stderr
    # the installed console script; the numba kernels run uncompiled (their compilation,
    # 30 s of CPU, is tested elsewhere)
    env["NUMBA_DISABLE_JIT"] = "1"
    cli = str(venv / "bin" / "stellar-cal")
    for args in (["simulate", "--scenario", "psce_rotations", "--duration", "30", "-o",
                  "sim.mcap"],
                 ["replay", "sim.mcap", "--method", "psce", "--prior", "sim.prior.yaml",
                  "-o", "result.yaml", "-q"]):
        run = subprocess.run([cli, *args], cwd=tmp_path, env=env, capture_output=True,
                             text=True, timeout=600)
        assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    imported = subprocess.run([str(py), "-c", "import stellar_cal_ros; print(stellar_cal_ros."
                               "__file__)"], cwd=tmp_path, env=env, capture_output=True,
                              text=True, check=True).stdout
    assert str(vsite) in imported and str(ROOT) not in imported
    result = yaml.safe_load((tmp_path / "result.yaml").read_text())
    assert result["method"] == "psce" and "installation" in result["estimated"]


@pytest.mark.benchmark
def test_pip_resolves_the_wheel_from_the_index(tmp_path):
    """The same with pip resolving and downloading every requirement (minutes: benchmark)."""
    wheel = _build_wheel(tmp_path)
    subprocess.run([sys.executable, "-m", "venv", str(tmp_path / "venv")], check=True)
    py = tmp_path / "venv" / "bin" / "python"
    subprocess.run([str(py), "-m", "pip", "install", "-q", "-c",
                    str(ROOT / "requirements.lock"), str(wheel)], check=True, timeout=3000)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    out = subprocess.run([str(py), "-c", "import stellar_cal_ros.methods.replay"], env=env,
                         cwd=tmp_path, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
