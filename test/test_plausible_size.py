"""Every effect states its plausible size where it acts, converted for this camera (issue 21).

A distortion coefficient means nothing without the lens: k3 = 2 moves a star at the corner of
the demo's 15° field by 0.05 px and at the corner of a 60° field by 60 px.  The library states
the distortion terms' plausible sizes in px at the detector corner and converts them through
the run's camera, so a real effect is never skipped because of how its coefficient happens to
be scaled.  The issue's case: k3 = 100 (2.65 px at the corner of ``psce_rotations``) was
called "not testable with this motion: its minimal detectable size (7.35) is 3.67 x its
plausible size" (2, a coefficient).
"""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from stellar_cal_ros.core.camera import CameraModel
from stellar_cal_ros.diagnosis import reliability
from stellar_cal_ros.diagnosis.run import diagnose
from stellar_cal_ros.effects import registry
from stellar_cal_ros.effects.base import corner_gain
from stellar_cal_ros.methods.replay import bag_data_from_simulation, replay_psce
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate


@pytest.fixture(scope="module")
def prior():
    return simulate(get_scenario("psce_rotations"), duration=2.0, seed=1).prior


def _with_focal_length(prior, f: float):
    out = copy.deepcopy(prior)
    p = out.camera.parameters()
    p[0] = p[1] = f
    out.camera = out.camera.with_parameters(p)
    return out


def test_k3_plausible_size_is_pixels_at_the_corner_of_this_camera(prior):
    cam = prior.camera
    # the corner of the detector in normalized coordinates, through the prior's distortion
    corner = cam.pixel_to_normalized(np.array([[0.0, 0.0], [cam.width - 1.0, 0.0],
                                               [0.0, cam.height - 1.0],
                                               [cam.width - 1.0, cam.height - 1.0]]))
    r = np.linalg.norm(corner, axis=1).max()
    k3 = reliability.plausible_size("radial_k3", prior)[0]
    # ∂u/∂k3 = fx x r^6: 5 px at the corner
    assert k3 == pytest.approx(5.0 / (cam.fx * r ** 7), rel=0.01)
    assert 150.0 < k3 < 250.0
    # the k3 = 100 is 2.65 px at the corner: real, large, and plausible
    px = registry.create("radial_k3").where_it_acts(np.array([100.0]), prior)[0]
    assert px == pytest.approx(100.0 * cam.fx * r ** 7, rel=0.01)
    assert 2.4 < px < 2.9
    # the MDB (7.35) is far below it: testable
    lam = reliability.lambda0(1e-3, 1)
    det = reliability.detectability("radial_k3", np.array([[lam / 7.35 ** 2]]), 1e-3, prior)
    assert det.mdb["k3"] == pytest.approx(7.35, rel=1e-9)
    assert det.testable and det.ratio == pytest.approx(7.35 / k3, rel=1e-9)
    assert det.plausible_text == {"k3": "5 px at the detector corner"}
    assert det.mdb_where_it_acts["k3"] == pytest.approx(7.35 * px / 100.0, rel=1e-9)


def test_the_same_statement_gives_each_lens_its_own_coefficients(prior):
    """A 38° field (fx = 1500 px): the same 5 px at the corner is a k3 ~ 1000 x smaller."""
    wide = _with_focal_length(prior, 1500.0)
    narrow_k3 = reliability.plausible_size("radial_k3", prior)[0]
    wide_k3 = reliability.plausible_size("radial_k3", wide)[0]
    eff = registry.create("radial_k3")
    assert wide_k3 * corner_gain(eff, wide)[0] == pytest.approx(5.0, rel=1e-12)
    assert narrow_k3 / wide_k3 == pytest.approx((3968.99 / 1500.0) ** 6, rel=0.05)
    # every distortion term, and the focal length (0.5 % of f), follows the camera
    for eid in ("radial_k1k2", "tangential", "focal_length"):
        a = reliability.plausible_size(eid, prior)
        b = reliability.plausible_size(eid, wide)
        assert np.all(a != b), eid
    assert reliability.plausible_size("focal_length", wide)[0] == pytest.approx(7.5)
    # a size stated in the parameters' own physical units does not depend on the lens
    for eid in ("installation", "time_offset", "image_plane_tilt", "gyro_scale_factor"):
        np.testing.assert_array_equal(reliability.plausible_size(eid, prior),
                                      reliability.plausible_size(eid, wide))


def test_corner_gain_against_finite_differences(prior):
    """The generic conversion (camera Jacobian × effect Jacobian) against moving the star."""
    cam: CameraModel = prior.camera
    corner = np.array([[cam.width - 1.0, cam.height - 1.0]])
    d = cam.unproject(corner)
    for eid, h in (("radial_k3", 1.0), ("radial_k1k2", 1e-3), ("tangential", 1e-5)):
        eff = registry.create(eid)
        value, _ = eff.initial(prior)
        gains = corner_gain(eff, prior)
        for j in range(eff.size):
            v = value.copy()
            v[j] += h
            p = eff.camera_parameters(v, cam.parameters(), None)
            moved = cam.with_parameters(p).project(d)
            fd = np.linalg.norm(moved - corner) / h
            # the largest displacement over the detector is at a corner (within 1 %)
            assert gains[j] == pytest.approx(fd, rel=0.01), (eid, j)


def test_a_large_k3_on_the_narrow_field_is_tested_and_found(tmp_path):
    """The issue's case, reduced (300 s, no thermal drift): k3 = 100 is ranked, not skipped."""
    sim = simulate(get_scenario("psce_rotations"), duration=300.0, seed=21,
                   effects={"radial_k3": 100.0})
    data = bag_data_from_simulation(sim)
    base = replay_psce(data, sim.prior).calibration
    summary = diagnose(data, base, "psce", [], tmp_path, plots=False, verbose=False,
                       candidates=["radial_k3", "pixel_aspect", "thermal_focal_length"],
                       workers=0)
    text = json.dumps(summary["unobservable"])
    assert "radial_k3" not in text, text
    assert summary["recommendation"] == "radial_k3", summary["candidates"]
