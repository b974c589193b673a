"""A method is one file: a toy method written in tmp_path is registered and run by replay,
diagnose, batch and the calibrator node with no other edit (issue 23, item 1)."""

from __future__ import annotations

import json
import textwrap
import uuid

import doc_examples
import numpy as np
import pytest
from sim_bags import psce_bag

# the calibrator node's test harness (the player with flow control; ros_context: conftest)
from test_nodes import (
    BAG,
    PRIOR,
    Spinner,
    make_calibrator,
    make_player,
    wait_for,
)
from test_online import assert_same

from stellar_cal_ros.cli import main
from stellar_cal_ros.diagnosis import screening
from stellar_cal_ros.diagnosis.discover import method_spec
from stellar_cal_ros.effects.base import Stage
from stellar_cal_ros.errors import ModelError
from stellar_cal_ros.io.calibration import load_calibration, load_covariance
from stellar_cal_ros.methods import models, registry
from stellar_cal_ros.methods.replay import replay

#: the method file doc/architecture.md shows ("Adding a method")
TOY_FILTER = doc_examples.example("architecture.md", "toy_method.py")

TOY_BATCH = textwrap.dedent('''
    """A batch method that returns its prior, and remembers how it was called."""
    import numpy as np

    from stellar_cal_ros.methods.registry import BatchOutput, MethodSpec

    CALLS = []


    def batch(bag, prior, effects, options, progress):
        CALLS.append((str(bag), list(effects), dict(options)))
        progress("read")
        progress("fit")
        cal = prior
        cal.method = "toy_batch"
        return BatchOutput(cal, (["installation.rx"], np.eye(1) * 1e-10),
                           {"du": np.zeros(2), "dv": np.ones(2)}, ["toy batch: done"])


    METHOD = MethodSpec(name="toy_batch", kind="batch", summary="returns the prior",
                        baseline=("installation",), batch=batch, steps=("read", "fit"))
''')


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    """The toy filter method's file, registered (as ``--method-module`` does)."""
    path = tmp_path_factory.mktemp("toy") / "toy_method.py"
    path.write_text(TOY_FILTER)
    assert registry.load_method_module(path) == "toy"
    yield path
    registry.METHODS.pop("toy", None)


def test_builtin_methods_are_found_from_their_files():
    assert registry.names("filter")[:3] == ["psce", "swaying_base", "traditional"]
    assert "acf" in registry.names("batch")
    assert "acf" not in registry.names(diagnosable=True)
    psce = registry.get("psce")
    from stellar_cal_ros.methods.psce import BASELINE_EFFECTS, PsceFilter

    # the PSCE baseline is stated once (psce.py) and read by the model rule
    assert psce.baseline is BASELINE_EFFECTS and psce.filter_cls is PsceFilter
    assert Stage.ACCEL not in psce.stages and Stage.ACCEL in registry.get("swaying_base").stages
    assert registry.get("swaying_base").needs_site and not psce.needs_site
    # the screening is the kernel's score test for filters, none for a batch method
    assert screening.screen_function("psce") is screening.kernel_scores
    assert screening.screen_function("acf") is None
    with pytest.raises(ModelError, match="unknown method 'nope'.*psce"):
        registry.get("nope")
    with pytest.raises(ModelError, match="cannot be removed"):
        models.resolve_effects("psce", ["-installation"])
    with pytest.raises(ModelError, match="accel stage, which the psce method does not"):
        models.resolve_effects("psce", ["accel_bias"])


def test_one_method_looked_up_imports_only_its_file():
    """``get``/``find``/``in MethodNames`` import only the file declaring the name (a psce
    replay loads neither the ACF, bundle nor swaying-base modules: ~0.05 CPU-s of its
    start-up, issue 24.1); listing them all reads their declarations, in file order as
    before, and imports none (main imported every one: ~0.5 CPU-s of `--help`)."""
    import subprocess
    import sys

    code = textwrap.dedent("""
        import sys
        from stellar_cal_ros.methods import registry
        from stellar_cal_ros.methods.registry import MethodNames
        assert registry.get("traditional").name == "traditional"
        assert "psce" in MethodNames(kind="filter") and "psce" in MethodNames(diagnosable=True)
        assert "psce" not in MethodNames(kind="batch")
        assert registry.find("psce").kind == "filter"
        mods = ("acf", "acf_data", "acf_covariance", "bundle_runs", "bundle", "iac")
        print(sorted(m for m in mods if "stellar_cal_ros.methods." + m in sys.modules))
        print(registry.names("filter"), "acf" in registry.names("batch"))
        print("stellar_cal_ros.methods.acf" in sys.modules)
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = proc.stdout.splitlines()
    assert lines[0] == "[]"
    # traditional was looked up first: the list keeps the files' order all the same
    assert lines[1].startswith("['psce', 'swaying_base', 'traditional']") and \
        lines[1].endswith("True")
    assert lines[2] == "False"


def test_the_declarations_read_from_the_files_are_the_specs():
    """What the registry reads from a method file's source without importing it (the
    ``--method`` choices, ``--help``, a refusal's alternatives) is what the file declares."""
    declared = registry._package_declarations()
    assert [d.name for d in declared] == ["acf", "bundle", "psce", "swaying_base",
                                          "traditional"]
    for d in declared:
        spec = registry.get(d.name)
        assert d.complete and d.module == spec.source, d
        assert (d.kind, d.summary, d.diagnosable) == (spec.kind, spec.summary,
                                                      spec.diagnosable), d
        # traditional's stages come from swaying's spec (a ``**`` expansion): a filter's
        # stages are not needed without import (it reads the IMU whatever they are)
        assert d.stages == spec.stages or (d.stages is None and d.kind == "filter"), d


def test_a_spec_is_checked_when_declared(tmp_path):
    with pytest.raises(ModelError, match="needs filter_cls"):
        registry.MethodSpec(name="x", kind="filter", summary="", baseline=())
    with pytest.raises(ModelError, match="kind"):
        registry.MethodSpec(name="x", kind="smoother", summary="", baseline=())
    bad = tmp_path / "bad.py"
    bad.write_text("X = 1\n")
    with pytest.raises(ModelError, match="declares no METHOD"):
        registry.load_method_module(bad)
    # the same name twice from another file is refused
    clash = tmp_path / "clash.py"
    clash.write_text(TOY_FILTER.replace('name="toy"', 'name="psce"'))
    with pytest.raises(ModelError, match="already registered"):
        registry.load_method_module(clash)


def test_toy_method_replay_and_diagnose_from_the_command_line(toy, tmp_path, capsys):
    """The toy holds the camera at a prior that is off: replay fits only its two effects and
    says the model misses something; diagnose (run on the toy) names a camera effect."""
    bag, prior, truth = psce_bag(120.0, seed=5)
    out = tmp_path / "toy.yaml"
    assert main(["replay", str(bag), "--method-module", str(toy), "--method", "toy",
                 "--prior", str(prior), "-o", str(out), "-q"]) == 0
    text = capsys.readouterr().out
    assert "model: gyro_bias, installation" in text and "MODEL MISMATCH" in text
    cal = load_calibration(out)
    assert cal.method == "toy"
    names = load_covariance(out).names
    assert {n.split(".")[0] for n in names} == {"gyro_bias", "installation"}
    # the camera stayed at the prior's
    p = load_calibration(prior)
    assert cal.camera.cx == p.camera.cx and cal.camera.fx == p.camera.fx
    # the same run through the Python API
    res = replay(bag, p, "toy", keep_tables=False)
    assert res.filter.method == "toy" and res.method == "toy"
    np.testing.assert_allclose(res.calibration.installation.as_quat(),
                               cal.installation.as_quat(), rtol=0, atol=1e-12)

    rep = tmp_path / "rep"
    assert main(["diagnose", str(bag), "--method-module", str(toy), "--method", "toy",
                 "--calibration", str(out), "-o", str(rep), "--no-plots", "--workers", "0",
                 "--candidates", "principal_point,radial_k1k2,time_offset"]) == 0
    summary = json.loads((rep / "diagnosis.json").read_text())
    assert summary["model"]["method"] == "toy"
    assert summary["model"]["effects"] == ["gyro_bias", "installation"]
    top = summary["candidates"][0]
    assert top["effect"] in ("principal_point", "radial_k1k2") and top["p_value"] < 1e-6
    by = {c["effect"]: c for c in summary["candidates"]}
    assert by["time_offset"]["p_value"] > 1e-3  # the truth has no time offset
    spec = method_spec("toy")
    assert spec.baseline == ("gyro_bias", "installation") and spec.screen is not None


def test_unknown_method_and_module_are_one_line_errors(tmp_path, capsys):
    bag, prior, _ = psce_bag(120.0, seed=5)
    with pytest.raises(SystemExit):
        main(["replay", str(bag), "--method", "magic", "--prior", str(prior), "-o",
              str(tmp_path / "x.yaml")])
    assert "invalid choice: 'magic'" in capsys.readouterr().err
    assert main(["replay", str(bag), "--method-module", str(tmp_path / "none.py"),
                 "--method", "psce", "--prior", str(prior), "-o", str(tmp_path / "x.yaml")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not exist" in err[0]
    assert err[0].startswith("stellar-cal replay: error: method module "), err  # as others
    # a batch method is not a filter
    with pytest.raises(ModelError, match="batch method"):
        replay(bag, load_calibration(prior), "acf")


def test_toy_batch_method(tmp_path, capsys):
    path = tmp_path / "toy_batch.py"
    path.write_text(TOY_BATCH)
    bag, prior, _ = psce_bag(120.0, seed=5)
    out = tmp_path / "b.yaml"
    try:
        assert main(["batch", str(bag), "--method-module", str(path), "--method", "toy_batch",
                     "--prior", str(prior), "-o", str(out), "--effects", "focal_length,-x",
                     "--residuals", str(tmp_path / "r.csv"), "-q"]) == 0
        assert "toy batch: done" in capsys.readouterr().out
        module_calls = registry.get("toy_batch").batch.__globals__["CALLS"]
        assert module_calls[-1][1:] == (["focal_length", "-x"],
                                        {"loss": "linear",
                                         "outlier_probability": 1.0 - 1e-6,
                                         "on_error": "raise"})
        assert load_calibration(out).method == "toy_batch"
        assert (tmp_path / "r.csv").read_text().startswith("du,dv")
        assert "toy_batch" not in registry.names(diagnosable=True)
    finally:
        registry.METHODS.pop("toy_batch", None)


@pytest.mark.ros
def test_toy_method_runs_in_the_calibrator_node(toy, ros_context, tmp_path):  # noqa: F811
    """method:=toy: the node builds the toy's filter and configuration from the registry, and
    its result equals the toy's replay of the same bag."""
    from stellar_cal_ros.io.bag import BagReader

    ref = replay(BAG, load_calibration(PRIOR), "toy")
    prefix = "/y" + uuid.uuid4().hex[:8]
    cal = make_calibrator(ros_context, prefix, tmp_path, method="toy")
    assert type(cal.filter_config).__name__ == "ToyConfig"
    player = make_player(ros_context, prefix, BAG)
    with BagReader(BAG) as r:
        n_imu = r.topics()["/imu/data"].message_count
    with Spinner(ros_context, cal, player):
        player.play()
        wait_for(lambda: cal.received["imu"] == n_imu, what="all IMU")
        cal.finish()
    assert type(cal.cal.filter).__name__ == "ToyFilter"
    assert cal.cal.parameter_names() == ref.covariance[0]
    assert_same(cal.cal.calibration(), ref.calibration)
    cal.destroy_node()
    player.destroy_node()
