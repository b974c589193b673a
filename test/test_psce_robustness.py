"""PSCE robustness: corrupted bags are counted, logged and skipped — never a crash or a
corrupted estimate (final parameters within 4σ of the truth, covariance SPD)."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest

from stellar_cal_ros.core.covariance import check as check_covariance
from stellar_cal_ros.errors import ModelError
from stellar_cal_ros.io.bag import BagWriter
from stellar_cal_ros.methods.psce import PsceConfig, PsceFilter
from stellar_cal_ros.methods.replay import (
    bag_data_from_simulation,
    build_model,
    read_bag_data,
    replay_psce,
    truth_parameters,
)
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

DURATION = 300.0


@pytest.fixture(scope="module")
def sim():
    return simulate(get_scenario("psce_rotations"), duration=DURATION, seed=7,
                    effects={"misidentification": 0.05})


def _write(sim, path, imu, frames):
    with BagWriter(path) as w:
        w.write_imu(imu, "/imu/data")
        for f in frames:
            w.write_star_frame(f, "/star_tracker/stars")
        w.write_navsat(sim.navsat, "/gnss/fix")
    return path


def _subset(frame, idx):
    return dataclasses.replace(
        frame, catalog_id=frame.catalog_id[idx], right_ascension=frame.right_ascension[idx],
        declination=frame.declination[idx], uv=frame.uv[idx], magnitude=frame.magnitude[idx],
        sigma=frame.sigma[idx])


def _assert_healthy(res, truth):
    flt = res.filter
    check_covariance(flt.P, "final covariance")
    err = flt.theta - truth_parameters(flt.model, truth)
    z = err / flt.sigma()[3:]
    names = flt.model.parameter_names()
    bad = {n: round(float(v), 2) for n, v in zip(names, z, strict=True) if abs(v) > 4.0}
    assert not bad, f"parameters outside 4σ: {bad}"
    assert res.counters["covariance_checks"] > 0


def test_corrupted_bag(sim, tmp_path):
    frames = [copy.deepcopy(f) for f in sim.star_frames]
    # 0, 1 and 2 stars
    frames[10] = _subset(frames[10], np.arange(0))
    frames[11] = _subset(frames[11], np.arange(1))
    frames[12] = _subset(frames[12], np.arange(2))
    # NaN centroids and a star far off the image
    frames[20].uv[:2] = np.nan
    frames[21].uv[0] = [5000.0, -300.0]
    # a duplicated frame (same stamp)
    frames.insert(41, copy.deepcopy(frames[40]))
    # IMU: 2 s gap at 100 s, and the IMU ends 20 s before the stars
    imu = sim.imu
    t = (imu.stamp_ns - imu.stamp_ns[0]) * 1e-9
    keep = ~((t > 100.0) & (t < 102.0)) & (t < DURATION - 20.0)
    imu = dataclasses.replace(imu, stamp_ns=imu.stamp_ns[keep],
                              angular_velocity=imu.angular_velocity[keep],
                              linear_acceleration=imu.linear_acceleration[keep])
    path = _write(sim, tmp_path / "corrupt.mcap", imu, frames)
    res = replay_psce(read_bag_data(path), sim.prior)
    c = res.counters
    n_total = len(frames)
    # the duplicate stops at the input; so do frames stamped too far after the IMU's end
    assert c["frames"] + c["frames_duplicate"] + c["frames_ahead"] == n_total
    assert c["skipped_few_stars"] >= 3
    assert c["stars_invalid"] >= 3  # two NaN + one off the image
    assert c["frames_duplicate"] == 1
    assert c["imu_gaps"] == 1
    # the last 20 s of 2 Hz frames: waited for in vain, or refused as ahead of the IMU
    assert 35 <= c["skipped_no_imu"] + c["frames_ahead"] <= 42
    assert c["stars_gated"] > 50  # misidentified stars (5 %)
    assert c["updates"] + c["init_frames"] + c["skipped_few_stars"] + c["frames_duplicate"] + \
        c["skipped_no_imu"] + c["skipped_out_of_order"] + c["reinitializations"] + \
        c.get("update_failed", 0) + c["frames_ahead"] == n_total
    assert c["reacquired_after_gap"] >= 1
    _assert_healthy(res, sim.truth)


def test_misidentification_only(sim):
    res = replay_psce(bag_data_from_simulation(sim), sim.prior)
    assert res.counters["stars_gated"] > 0.03 * sum(len(f.uv) for f in sim.star_frames)
    _assert_healthy(res, sim.truth)


def test_out_of_order_frames_are_replayed_in_stamp_order(sim):
    data = bag_data_from_simulation(sim)
    data.frames[30], data.frames[31] = data.frames[31], data.frames[30]
    res = replay_psce(data, sim.prior)
    assert res.counters["frames_reordered"] == 1  # frame 30 arrives after frame 31
    assert res.counters["skipped_out_of_order"] == 0
    _assert_healthy(res, sim.truth)


def _filter(sim):
    data = bag_data_from_simulation(sim)
    model = build_model(sim.prior, [])
    flt = PsceFilter(model, data.t0, PsceConfig(), nominal_dt=data.nominal_dt)
    flt.extend_imu(data.imu_t, data.imu_w)
    return data, flt


def _feed(flt, data, frame):
    from stellar_cal_ros.core.catalog import radec_to_unit
    from stellar_cal_ros.effects.base import FrameContext

    ctx = FrameContext(stamp=frame.stamp_ns * 1e-9, catalog_id=frame.catalog_id.astype(np.int64),
                       magnitude=frame.magnitude)
    u_i = radec_to_unit(frame.right_ascension, frame.declination)
    return flt.process_frame(frame.uv, u_i, ctx, frame.sigma.astype(float),
                             t_rel=(frame.stamp_ns - data.t0_ns) * 1e-9)


def test_live_out_of_order_and_duplicate_are_skipped(sim):
    data, flt = _filter(sim)
    for f in data.frames[:20]:
        _feed(flt, data, f)
    assert _feed(flt, data, data.frames[19]) is None  # duplicate
    assert _feed(flt, data, data.frames[5]) is None  # older
    assert flt.counters.skipped_duplicate == 1
    assert flt.counters.skipped_out_of_order == 1
    assert _feed(flt, data, data.frames[20]) is not None


def test_lost_lock_reacquires(sim):
    """A wrong attitude (as after a gap during a slew) is re-acquired, not kept forever."""
    data, flt = _filter(sim)
    for f in data.frames[:40]:
        _feed(flt, data, f)
    from stellar_cal_ros.core.rotation import so3_exp

    flt.R_i_b = so3_exp(np.array([0.0, 0.05, 0.0])) @ flt.R_i_b  # 3° off
    # the jump is not the gyro's: its check's chain starts again, as after a long gap
    flt.gyro_watch["R_post"] = None
    for f in data.frames[40:80]:
        _feed(flt, data, f)
    assert flt.counters.reinitializations == 1
    assert flt.counters.updates > 70


def test_failed_reacquisitions_back_off(sim):
    """Re-acquisitions that fail (or are lost again before any accepted update: a model far
    from the data) are spaced out -- after 3 rejected frames, then 6, 12, 24, ... (at most
    48), not at every frame (each is a full second-order initialisation); a re-acquisition
    that holds resets the wait."""
    from stellar_cal_ros.core.rotation import so3_exp

    data, flt = _filter(sim)
    for f in data.frames[:40]:
        _feed(flt, data, f)
    flt.R_i_b = so3_exp(np.array([0.0, 0.05, 0.0])) @ flt.R_i_b  # 3° off
    flt.gyro_watch["R_post"] = None
    waited = []
    flt.reacquire = lambda *a: waited.append(flt._rejected_in_row) or False  # cannot align
    for f in data.frames[40:100]:
        _feed(flt, data, f)
    assert waited == [3, 6, 12, 24]  # before: an attempt at each of the 58 frames after 3
    del flt.reacquire  # the filter's own again: the next attempt (48 frames on) holds
    for f in data.frames[100:200]:
        _feed(flt, data, f)
    assert flt.counters.reinitializations == 1 and flt._reacquire_streak == 0
    assert flt.counters.updates > 40 + 40


def test_covariance_check_repairs(sim):
    data, flt = _filter(sim)
    for f in data.frames[:30]:
        _feed(flt, data, f)
    good = flt.P.copy()
    flt._check_covariance()
    w, V = np.linalg.eigh(flt.P)
    flt.P = (V * np.where(np.arange(len(w)) == 0, -abs(w[-1]), w)) @ V.T  # indefinite
    with pytest.raises(ModelError):
        check_covariance(flt.P)
    flt._check_covariance()
    check_covariance(flt.P)
    assert flt.counters.covariance_repairs == 1
    flt.P[0, 0] = np.nan
    flt._check_covariance()  # non-finite: rolled back to the last healthy state
    np.testing.assert_array_equal(flt.P, good)
    assert flt.counters.covariance_repairs == 2
