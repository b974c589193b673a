"""A noise common to all stars of a frame, white between frames (issue 21, H288).

Unseen case ``frame_jitter``: every star of a frame shifted by one N(0, 0.04 px) per axis,
independently from frame to frame (an attitude or image jitter the gyro does not see),
was "noise as stated" with no line (RMS 0.063 px for 0.050 expected): the stars' σ is
measured within each frame (the jitter fitted out with the frame's rotation) and the
gyro's from its samples.  :func:`~stellar_cal_ros.diagnosis.noise_structure.frame_common`
compares the frames' mean innovations with what the stars' σ and the filter's attitude
covariance predict for them, on consecutive frames' differences.

* read back: on 120-s psce bags with 0.04 px (seeds 31-34) the measured σ_j lies within 3
  of its σ of the truth on each seed and their mean z within 3/√4; named by the verdict,
  its line printed first, "the rest of the noise as stated";
* clean bags (seeds 31, 32): |z| < 3, not named, no key in the verdict's JSON.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.diagnosis.noise import NoiseVerdict, measure_stars, named_common
from stellar_cal_ros.methods.frames import bag_data_from_simulation
from stellar_cal_ros.methods.replay import replay
from stellar_cal_ros.sim import tracker_errors
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

JITTER_PX = 0.04


def _common(seed: int, px: float) -> dict:
    sim = simulate(get_scenario("psce_rotations"), duration=120.0, seed=seed)
    if px:
        tracker_errors.frame_jitter(sim, px, seed)
    data = bag_data_from_simulation(sim)
    result = replay(data, sim.prior, "psce")
    sn = measure_stars(result, data, "psce", 0.5, None)
    assert sn is not None and sn.common is not None
    return sn.common


@pytest.fixture(scope="module")
def jittered() -> list[dict]:
    return [_common(seed, JITTER_PX) for seed in (31, 32, 33, 34)]


def test_the_frame_common_sigma_is_read_back(jittered) -> None:
    z = [(d["sigma_px"] - JITTER_PX) / d["sigma_sigma_px"] for d in jittered]
    for d, zi in zip(jittered, z, strict=True):
        assert d["sigma_sigma_px"] < 0.2 * JITTER_PX, d
        assert abs(zi) < 3.0, (d, zi)
        assert d["z"] > 10.0 and d["slow_z"] > 5.0 and d["median_z"] > 10.0, d
    assert abs(float(np.mean(z))) < 3.0 / math.sqrt(len(z)), z


def test_it_is_named_as_noise(jittered) -> None:
    d = named_common(jittered[0], 2)
    assert d is not None
    v = NoiseVerdict(NoiseScales(), NoiseScales(), star=1.0, star_sigma=0.007,
                     stated_sigma_px=0.05, frame_common=d)
    lines = v.lines()
    assert lines[0].startswith("the frames share a noise: all stars of a frame move by one "
                               f"error of {d['sigma_px']:.3g} +- ")
    assert "not the stamps" in lines[0]
    assert lines[-1].startswith("the rest of the noise as stated (")
    assert v.as_json()["frame_common"]["sigma_px"] == d["sigma_px"]
    # the frames' stamps named: theirs, not this line
    v.stamp_jitter = {"ms": 1.0}
    assert "frame_common" not in v.as_json()
    assert not any(ln.startswith("the frames share a noise") for ln in v.lines())


@pytest.mark.parametrize("seed", [31, 32])
def test_clean_bags_name_no_frame_common_noise(seed) -> None:
    d = _common(seed, 0.0)
    assert abs(d["z"]) < 3.0 and abs(d["median_z"]) < 3.0, d
    assert d["sigma_px"] < 3.0 * d["sigma_sigma_px"] + 0.005, d
    assert named_common(d, 2) is None
    v = NoiseVerdict(NoiseScales(), NoiseScales(), star=1.0, star_sigma=0.007,
                     stated_sigma_px=0.05, frame_common=named_common(d, 2))
    assert "frame_common" not in v.as_json()
    assert v.lines()[-1].startswith("noise as stated (")
