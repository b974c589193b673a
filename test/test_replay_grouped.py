"""A replay's star frames handed to the driver a group at a time (issue 24).

``Calibrator.push_stars_many`` takes the frames between two other events of a replay in one
call (``replay._grouped_frames``, ``replay._release_items``); the reference is
``Calibrator.push_stars`` a message at a time (the group of one: the same checks), which it
must equal in every float, counter and table, also where a group holds frames its one-pass
path leaves to a message at a time (duplicates, frames out of order, a wrong frame id,
unidentified stars, bad σ, a frame ahead of the IMU, an overflow, frames inside an IMU clock
leap): ``Calibrator._plain``, the one admission test of both.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from sim_bags import psce_bag

from stellar_cal_ros.io.calibration import load_calibration
from stellar_cal_ros.methods import driver
from stellar_cal_ros.methods import replay as replay_mod
from stellar_cal_ros.methods.driver import Calibrator, DriverConfig


@pytest.fixture(scope="module")
def bag():
    path, prior_path, _ = psce_bag(120.0)
    return path, load_calibration(prior_path)


_MANY = Calibrator.push_stars_many


def _one_at_a_time(self, frames, inputs=None):
    """The reference: a message at a time (:meth:`Calibrator.push_stars`, the group of one)."""
    out = []
    for i, frame in enumerate(frames):
        out += _MANY(self, [frame], None if inputs is None else [inputs[i]])
    return out


def _digest(res) -> tuple:
    tables = [np.asarray(t[k]).tobytes() for t in (res.history, res.residuals) for k in t]
    return (res.filter.theta.tobytes(), res.filter.P.tobytes(), res.counters, tables,
            res.calibration.extra.get("derived"))


@pytest.mark.parametrize("source", ["data", "file"])
def test_grouped_replay_equals_a_message_at_a_time(bag, source, monkeypatch) -> None:
    """θ, P, the counters and both tables bit for bit as with ``push_stars`` a message at a
    time, on the bag in memory (the diagnosis's runs) and read from the file; the groups hold
    several frames each (the 120 s bag's 240 frames in at most half as many calls: from the
    file, the frames a 1-s IMU merge held; in memory, those between two IMU blocks)."""
    path, prior = bag
    data = replay_mod.read_bag_data(path) if source == "data" else path
    calls: list[int] = []
    many = driver.Calibrator.push_stars_many

    def counted(self, frames, inputs=None):
        calls.append(len(frames))
        return many(self, frames, inputs)

    monkeypatch.setattr(driver.Calibrator, "push_stars_many", counted)
    grouped = _digest(replay_mod.replay(data, prior, "psce"))
    assert sum(calls) == 240 and len(calls) <= (120 if source == "file" else 20), calls
    monkeypatch.setattr(driver.Calibrator, "push_stars_many", _one_at_a_time)
    reference = _digest(replay_mod.replay(data, prior, "psce"))
    assert grouped[:3] == reference[:3] and grouped[4] == reference[4]
    assert grouped[3] == reference[3] and len(grouped[3]) > 10
    assert grouped[2]["frames_received"] == 240 and grouped[2]["updates"] > 200


def _replay_calibrator(prior, bulk: bool, max_pending_frames: int = 1_000_000,
                       strict_clock: bool = True):
    """A replay's :class:`Calibrator` and its group push: ``push_stars_many`` (``bulk``), or
    the reference, ``push_stars`` a message at a time."""
    drv = DriverConfig(reorder_window_s=replay_mod.REPLAY_REORDER_S,
                       max_pending_frames=max_pending_frames, batch_frames=True,
                       strict_clock=strict_clock, frame_updates=False)
    cal = Calibrator(prior, "psce", driver=drv)
    push = cal.push_stars_many if bulk else (
        lambda fr, inp, cal=cal: _one_at_a_time(cal, fr, inp))
    return cal, push


def _state(cal: Calibrator) -> tuple:
    c = dataclasses.asdict(cal.counters)
    return (c, [int(f.stamp_ns) for f in cal._frames_pending], sorted(cal._inputs),
            sorted(cal._to_identify), cal._first_frame_ns)


def test_push_stars_many_equals_push_stars_on_odd_groups(bag) -> None:
    """Groups with a duplicate, a frame out of order, a wrong frame id, unidentified stars,
    a bad σ, a frame ahead of the IMU, and a group before the pending frame's stamp: the
    counters, the pending queue, the inputs held and the frames to identify as
    ``push_stars`` a message at a time gives; then both runs end with the same θ and P."""
    path, prior = bag
    data = replay_mod.read_bag_data(path)
    frames = list(data.frames)
    f0 = frames[100]
    odd = {
        103: dataclasses.replace(frames[103], stamp_ns=frames[102].stamp_ns),  # duplicate
        106: frames[104],  # late (already pushed)
        109: dataclasses.replace(frames[109], frame_id="camera"),  # wrong frame id
        112: dataclasses.replace(  # unidentified stars: identified when processed
            frames[112], catalog_id=np.zeros_like(frames[112].catalog_id),
            right_ascension=np.full(len(frames[112].uv), np.nan),
            declination=np.full(len(frames[112].uv), np.nan)),
        115: dataclasses.replace(frames[115], sigma=-np.ones(len(frames[115].uv))),  # bad σ
    }
    ahead = dataclasses.replace(f0, stamp_ns=int(data.imu_stamp_ns[-1]) + 10**12)
    # before the IMU covers them (nothing released): then after it (released, one late)
    first = [frames[:100], frames[100:102], [frames[102], odd[103]],
             [frames[104], frames[105], odd[106]], [frames[107], frames[108], odd[109]],
             [frames[110], frames[111], odd[112]], [frames[113], frames[114], odd[115]],
             [frames[117], frames[116]], frames[118:140], [frames[140], ahead]]
    then = [frames[141:], [frames[50]]]
    cut = np.searchsorted(data.imu_stamp_ns, frames[145].stamp_ns)
    states = []
    results = []
    for bulk in (True, False):
        cal, push = _replay_calibrator(prior, bulk)
        cal.push_imu_block(data.imu_stamp_ns[:cut], data.imu_w[:cut], data.imu_f[:cut])
        seen = []
        for g in first:
            push(g, cal.star_inputs(g))
            seen.append(_state(cal))
        cal.push_imu_block(data.imu_stamp_ns[cut:], data.imu_w[cut:], data.imu_f[cut:])
        for g in then:
            push(g, cal.star_inputs(g))
            seen.append(_state(cal))
        cal.finish()
        seen.append(_state(cal))
        states.append(seen)
        results.append((cal.filter.theta.tobytes(), cal.filter.P.tobytes(),
                        cal.filter_counters()["updates"]))
    assert states[0] == states[1]
    assert results[0] == results[1]
    c = states[0][-1][0]
    assert c["frames_duplicate"] == 2 and c["frames_late"] == 1 and c["frames_reordered"] == 1
    assert c["frames_wrong_frame"] == 1 and c["frames_ahead"] == 1 and c["stars_bad_sigma"] > 0
    assert c["frames_received"] == len(frames) + 2 and results[0][2] > 200
    assert int(odd[112].stamp_ns) in states[0][5][3]  # unidentified: held to identify


def test_push_stars_many_overflows_as_push_stars(bag) -> None:
    """A group that would overflow the frames held (``max_pending_frames``) is not queued in
    one pass: the oldest dropped as ``overflow``, a message at a time's counts and outcomes
    (the one-pass path's overflow condition; the test above holds a million frames)."""
    path, prior = bag
    frames = list(replay_mod.read_bag_data(path).frames)
    states = []
    for bulk in (True, False):
        cal, push = _replay_calibrator(prior, bulk, max_pending_frames=50)
        out = [[o.status for o in push(g, cal.star_inputs(g))]
               for g in (frames[:30], frames[30:80])]
        states.append((_state(cal), out))
    assert states[0] == states[1]
    assert states[0][0][0]["frames_overflow"] == 30 and states[0][1][1] == ["dropped_overflow"] * 30


def test_push_stars_many_inside_a_clock_leap_as_push_stars(bag) -> None:
    """Groups of frames around an IMU clock leap ahead (``strict_clock`` off): a group held
    wholly before the leap, one across its start and one inside it give the counters (each
    frame inside counted as ``imu_clock_jumps``), the faults, the pending queue, θ and P of
    ``push_stars`` a message at a time (the one-pass path's leap condition; the tests above
    hold no leap)."""
    path, prior = bag
    data = replay_mod.read_bag_data(path)
    frames = list(data.frames)
    cut = int(np.searchsorted(data.imu_stamp_ns, frames[60].stamp_ns))
    shifted = data.imu_stamp_ns[cut:] + 50 * 10**9  # the IMU clock leaps 50 s ahead
    groups = [frames[:40], frames[40:55], frames[55:75], frames[75:100]]
    states = []
    for bulk in (True, False):
        cal, push = _replay_calibrator(prior, bulk, strict_clock=False)
        cal.push_imu_block(data.imu_stamp_ns[:cut], data.imu_w[:cut], data.imu_f[:cut])
        push(groups[0], cal.star_inputs(groups[0]))
        cal.push_imu_block(shifted, data.imu_w[cut:], data.imu_f[cut:])
        seen = []
        for g in groups[1:]:
            push(g, cal.star_inputs(g))
            seen.append((_state(cal), list(cal.faults)))
        cal.finish()
        seen.append((_state(cal), list(cal.faults)))
        states.append((seen, cal.filter.theta.tobytes(), cal.filter.P.tobytes()))
    assert states[0] == states[1]
    inside = sum(int(data.imu_stamp_ns[cut - 1]) < int(f.stamp_ns) < int(shifted[0])
                 - cal.window_ns for f in frames[:100])
    (first, _), *_, (last, faults) = states[0][0]
    assert first[0]["imu_clock_jumps"] == 0 and 30 < inside < 45
    assert last[0]["imu_clock_jumps"] == inside and last[0]["frames_received"] == 100
    assert any("IMU clock jumped" in text for text in faults)
