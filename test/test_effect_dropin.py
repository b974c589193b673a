"""A library effect is one file (issue 23, item 4): a new effect file dropped into the effects
package is found by the registry and is simulated, estimated, diagnosed, budgeted and exported
with no other file edited; an installed plugin's entry-point effect is known wherever an
effect id is resolved.

The package's search path is extended by a temporary folder holding the file (what copying it
into ``stellar_cal_ros/effects/`` does), so the installed package is left alone.  The effect
is OpenCV's thin-prism distortion (s1, s3): a lens element or window tilted in its mount.  On
the 15° field of ``psce_rotations`` it is aliased with the image-plane tilt (a 6 mrad tilt fits
0.5 px of thin prism as well, p = 1e-188 both), so the diagnosis is asked about candidates
that are not its alias.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import yaml

import stellar_cal_ros.effects as effects_package
from stellar_cal_ros.budget.sources import (
    error_model_from_result,
    find_covariance,
    load_covariance,
)
from stellar_cal_ros.cli import main
from stellar_cal_ros.diagnosis import reliability
from stellar_cal_ros.effects import registry
from stellar_cal_ros.effects.base import CAMERA_INDEX, Stage, corner_gain
from stellar_cal_ros.io.calibration import load_calibration

EFFECT_FILE = textwrap.dedent('''
    """Thin-prism distortion s1, s3 (OpenCV): a lens element or window tilted in its mount."""

    from stellar_cal_ros.effects.base import CameraSetEffect, Plausible


    class ThinPrism(CameraSetEffect):
        """``x += s1 r^2, y += s3 r^2`` (normalized coordinates)."""

        id = "thin_prism"
        order = 65
        camera_entries = ("s1", "s3")
        parameter_names = ("s1", "s3")
        units = ("1", "1")
        default_sigma = (0.01, 0.01)
        plausible = Plausible(3.0, "px", at="corner")
        budget_source = "distortion"
        explanation = (
            "A lens element or the window is tilted in its mount: stars move along one "
            "fixed direction by s r^2, growing from the centre toward the corners.")
''')
TRUTH = (0.004, -0.004)  # 0.5 px at the detector corner of psce_rotations
MODULE = "stellar_cal_ros.effects.thin_prism"


@pytest.fixture(scope="module")
def dropped(tmp_path_factory):
    """The effect file in a folder on the effects package's path; a 150 s bag with it."""
    folder = tmp_path_factory.mktemp("effects_package")
    (folder / "thin_prism.py").write_text(EFFECT_FILE)
    patch = pytest.MonkeyPatch()
    patch.setattr(effects_package, "__path__", [*effects_package.__path__, str(folder)])
    registry.EFFECTS.reload()
    d = tmp_path_factory.mktemp("dropin")
    bag = d / "sim.mcap"
    assert main(["simulate", "--scenario", "psce_rotations", "--duration", "150", "--seed",
                 "12", "--effect", f"thin_prism={TRUTH[0]},{TRUTH[1]}", "-o", str(bag)]) == 0
    yield d, bag
    registry.EFFECTS.pop("thin_prism", None)
    sys.modules.pop(MODULE, None)
    patch.undo()


def test_found_in_the_package_and_ordered_by_its_class(dropped):
    ids = registry.available()
    assert "thin_prism" in ids and registry.EFFECTS["thin_prism"].__module__ == MODULE
    # order 65: after tangential (60), before the image-plane tilt (70)
    assert ids.index("thin_prism") == ids.index("tangential") + 1
    assert not registry.is_library(registry.EFFECTS["thin_prism"])  # shipped to workers
    # its plausible size, 3 px at the corner, in its parameters for this camera
    d, bag = dropped
    prior = load_calibration(bag.with_suffix(".prior.yaml"))
    eff = registry.create("thin_prism")
    s = reliability.plausible_size("thin_prism", prior)
    np.testing.assert_allclose(s * corner_gain(eff, prior), 3.0, rtol=1e-12)
    # s1 r^2 at the corner of a 1024 px detector, f = 3969 px: r^2 = 2 (512/3969)^2
    assert s == pytest.approx(3.0 / (3969.0 * 2 * (512.0 / 3969.0) ** 2), rel=0.02)
    assert reliability.display_unit("thin_prism.s1") == ("", 1.0)
    assert eff.stage is Stage.CAMERA


def test_simulated_through_the_class(dropped):
    _, bag = dropped
    truth = load_calibration(bag.with_suffix(".truth.yaml"))
    p = truth.camera.parameters()
    assert (p[CAMERA_INDEX["s1"]], p[CAMERA_INDEX["s3"]]) == TRUTH


def test_diagnosed_estimated_budgeted_and_exported(dropped, caplog):
    d, bag = dropped
    prior = bag.with_suffix(".prior.yaml")
    base = d / "base.yaml"
    assert main(["replay", str(bag), "--method", "psce", "--prior", str(prior), "-o",
                 str(base), "-q"]) == 0
    assert load_calibration(base).extra["consistency"]["verdict"] == "model mismatch"
    # diagnosed: named first among the candidates (not given by a file: found in the package)
    out = d / "diag"
    assert main(["diagnose", str(bag), "--calibration", str(base), "--method", "psce",
                 "--candidates", "thin_prism,pixel_aspect,time_offset,thermal_focal_length",
                 "--workers", "0", "--no-plots", "-o", str(out)]) == 0
    summary = json.loads((out / "diagnosis.json").read_text())
    assert summary["recommendation"] == "thin_prism", summary["candidates"][:2]
    # estimated: the model with it is consistent and finds the truth
    fixed = d / "fixed.yaml"
    assert main(["replay", str(bag), "--method", "psce", "--prior", str(prior), "-o",
                 str(fixed), "--effects", "thin_prism", "-q"]) == 0
    cal = load_calibration(fixed)
    assert cal.extra["consistency"]["verdict"] == "consistent"
    p = cal.camera.parameters()
    sigma = cal.sigma["camera"]["distortion_coefficients"]["data"]
    for name, true in zip(("s1", "s3"), TRUTH, strict=True):
        i = CAMERA_INDEX[name]
        assert abs(p[i] - true) < 4.0 * sigma[i - 4], (name, p[i], sigma[i - 4])
    # budgeted: its parameters are part of the distortion source
    model = error_model_from_result(cal, load_covariance(find_covariance(fixed)))
    assert {"thin_prism.s1", "thin_prism.s3"} <= {model.names[i]
                                                  for i in model.groups["distortion"]}
    assert main(["budget", str(fixed), "--no-plots", "--draws", "50", "-o",
                 str(d / "budget")]) == 0
    budget = json.loads((d / "budget" / "budget.json").read_text())
    assert "thin_prism.s1" in json.dumps(budget), "the budget left thin_prism out"
    # exported: Kalibr's radtan cannot hold s1, s3: said, with the pixels it costs
    caplog.clear()
    assert main(["export", str(fixed), "--format", "kalibr", "-o", str(d / "k.yaml")]) == 0
    said = next(r.getMessage() for r in caplog.records if "s1=" in r.getMessage())
    assert "s3=" in said and "cannot express" in said, said
    assert yaml.safe_load((d / "k.yaml").read_text())["cam0"]["distortion_model"] == "radtan"


EP_MODULE = textwrap.dedent('''
    from stellar_cal_ros.effects.base import Effect, Stage


    class EntryPointDelay(Effect):
        id = "test_entry_point_delay"
        stage = Stage.TIME
        parameter_names = ("dt",)
        units = ("s",)
        default_sigma = (0.01,)
''')


def test_entry_point_effects_are_known_where_ids_are_resolved(tmp_path):
    """An installed plugin's effect (entry point group ``stellar_cal_ros.effects``) is known
    to the first look-up of a fresh process, here the method model's ``resolve_effects``."""
    (tmp_path / "my_ep_effects.py").write_text(EP_MODULE)
    info = tmp_path / "my_ep_effects-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: my-ep-effects\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(
        "[stellar_cal_ros.effects]\ndelay = my_ep_effects:EntryPointDelay\n")
    code = ("from stellar_cal_ros.methods.models import resolve_effects\n"
            "print(resolve_effects('psce', ['test_entry_point_delay']))\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(tmp_path), *filter(None, [os.environ.get("PYTHONPATH")])])}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr[-1500:]
    assert proc.stdout.strip() == "['test_entry_point_delay']"
