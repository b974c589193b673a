"""IMU faults are handled once, in the shared kernel (issue 12, item 7).

A lost or NaN IMU sample leaves a known interval that the buffer bridges; the result must not
be biased by it.  A gyro that reports deg/s is refused with an error naming the unit.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from stellar_cal_ros.errors import DataError
from stellar_cal_ros.methods.frames import bag_data_from_simulation
from stellar_cal_ros.methods.models import build_model
from stellar_cal_ros.methods.replay import replay
from stellar_cal_ros.methods.results import equivalent_principal_point, truth_parameters
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate


@pytest.fixture(scope="module")
def psce300():
    sim = simulate(get_scenario("psce_rotations"), duration=300, seed=21)
    model = build_model(sim.prior, "psce")
    th = truth_parameters(model, sim.truth)
    truth = np.array(equivalent_principal_point(model, th, np.eye(model.size))[
        "equivalent_principal_point_px"])
    data = bag_data_from_simulation(sim)
    clean = replay(data, sim.prior, "psce")
    return sim, data, truth, _eqpp_error(clean, truth)


def _eqpp_error(result, truth):
    eq = result.calibration.extra["derived"]["equivalent_principal_point_px"]
    return float(np.linalg.norm(np.asarray(eq) - truth))


@pytest.mark.parametrize("kind", ["missing", "nan"])
def test_one_percent_bad_imu_samples_do_not_bias(psce300, kind):
    """Before the bridge: 1 % missing gave 0.035–0.048 px (clean 0.0017), 1 % NaN 0.049 px.

    Measured now with seeds 1-3 (test/test_imu_faults.py's draw is seed 1): 0.96–1.18 × the
    clean equivalent-principal-point error, every run 'consistent'.
    """
    sim, data, truth, e_clean = psce300
    rng = np.random.default_rng(1)
    bad = rng.random(len(data.imu_t)) < 0.01
    d = copy.copy(data)
    if kind == "missing":
        d.imu_t, d.imu_w, d.imu_f = d.imu_t[~bad], d.imu_w[~bad], d.imu_f[~bad]
    else:
        d.imu_w = d.imu_w.copy()
        d.imu_w[bad] = np.nan
    r = replay(d, sim.prior, "psce")
    assert r.counters["imu_bridged"] >= 0.9 * bad.sum()
    if kind == "nan":
        assert r.counters["imu_invalid"] == bad.sum()
    assert _eqpp_error(r, truth) <= 1.2 * e_clean
    assert r.calibration.extra["consistency"]["verdict"] == "consistent"


@pytest.mark.parametrize("scenario,method", [("psce_rotations", "psce"),
                                             ("swaying", "swaying_base")])
def test_gyro_in_degrees_per_second_is_refused(scenario, method):
    sim = simulate(get_scenario(scenario), duration=60, seed=5)
    d = bag_data_from_simulation(sim)
    d.imu_w = np.degrees(d.imu_w)
    with pytest.raises(DataError, match="deg/s"):
        replay(d, sim.prior, method)


def test_data_quality_names_input_faults_not_model_mismatch():
    """The 'data quality first' phrases: input counters always, gated stars only when the
    accepted stars fit (a model far off gates stars by itself)."""
    from stellar_cal_ros.methods.results import data_quality

    clean = {"imu_received": 30000, "stars_gated": 2, "reinitializations": 0}
    assert data_quality(clean, 30000, 1.0) == []
    faults = data_quality({**clean, "imu_invalid": 3, "imu_gaps": 3}, 30000, 1.0)
    assert faults == ["3 IMU samples with non-finite values or stamps (bridged)",
                      "3 gaps in the IMU stream (bridged)"]
    misid = {"stars_gated": 300, "reinitializations": 2}
    assert "misidentified" in data_quality(misid, 30000, 1.02)[0]
    assert data_quality(misid, 30000, 9.9) == []  # a wrong model: the diagnosis's business
    assert data_quality({"stars_gated": 8}, 30000, 1.0) == []  # within the gate's false alarms
