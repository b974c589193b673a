"""Checkpoint files (io/checkpoint.py): atomic writes, verified reads, and the online resume.

A truncated or corrupt checkpoint must give one CheckpointError naming the damage (it gave
``zipfile.BadZipFile`` before the checksum), a crash while writing must leave the previous
checkpoint intact, and a file of the first format (bare .npz) must still load.
"""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from stellar_cal_ros.errors import CheckpointError
from stellar_cal_ros.io.checkpoint import MAGIC, read_checkpoint, write_checkpoint


def _arrays():
    rng = np.random.default_rng(0)
    return {"P": rng.standard_normal((5, 5)), "ns": np.arange(7, dtype=np.int64) * 10**18,
            "mask": np.array([True, False]), "empty": np.zeros((0, 3))}


def test_roundtrip(tmp_path):
    meta = {"format": "x/1", "n": 3, "nested": {"a": [1, 2.5, None]}}
    p = write_checkpoint(tmp_path / "sub" / "ck.bin", _arrays(), meta)
    assert p.read_bytes()[:len(MAGIC)] == MAGIC
    arrays, back = read_checkpoint(p)
    assert back == meta
    for k, v in _arrays().items():
        np.testing.assert_array_equal(arrays[k], v)
        assert arrays[k].dtype == v.dtype
    assert [f.name for f in p.parent.iterdir()] == ["ck.bin"]  # no temporary left


def test_every_truncation_and_a_flipped_byte_are_named(tmp_path):
    p = write_checkpoint(tmp_path / "ck", _arrays(), {"k": 1})
    data = p.read_bytes()
    for cut in sorted({0, 5, 16, 30, 56, 57, len(data) // 2, len(data) - 1}):
        p.write_bytes(data[:cut])
        with pytest.raises(CheckpointError, match="truncated|empty"):
            read_checkpoint(p)
    for at in (60, len(data) // 2, len(data) - 1):
        b = bytearray(data)
        b[at] ^= 0x01
        p.write_bytes(bytes(b))
        with pytest.raises(CheckpointError, match="checksum"):
            read_checkpoint(p)
    p.write_bytes(b"hello")
    with pytest.raises(CheckpointError, match="not a checkpoint"):
        read_checkpoint(p)
    with pytest.raises(CheckpointError, match="not found"):
        read_checkpoint(tmp_path / "absent")


def test_a_failed_write_keeps_the_old_checkpoint(tmp_path, monkeypatch):
    p = write_checkpoint(tmp_path / "ck", _arrays(), {"generation": 1})

    def boom(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError, match="disk full"):
        write_checkpoint(p, _arrays(), {"generation": 2})
    monkeypatch.undo()
    assert read_checkpoint(p)[1] == {"generation": 1}
    assert [f.name for f in tmp_path.iterdir()] == ["ck"]
    with pytest.raises(CheckpointError, match="reserved"):
        write_checkpoint(p, {"__meta__": np.zeros(1)}, {})
    with pytest.raises(CheckpointError, match="objects"):
        write_checkpoint(p, {"o": np.array([{}], dtype=object)}, {})


def test_the_writer_writes_the_newest_state_one_at_a_time(tmp_path, monkeypatch):
    """The live node's background writer: submit returns at once, one write in flight, the
    states submitted meanwhile are replaced by the newest (written next, the others never),
    flush waits for it; a failed write is raised by flush (or taken once by take_error) and
    leaves the last good file."""
    from stellar_cal_ros.io import checkpoint as io_ck

    real, gate, started, order = io_ck.write_checkpoint, threading.Event(), threading.Event(), []

    def slow(path, arrays, meta):
        order.append(meta["generation"])
        started.set()
        assert gate.wait(30)
        return real(path, arrays, meta)

    monkeypatch.setattr(io_ck, "write_checkpoint", slow)
    w = io_ck.CheckpointWriter(tmp_path / "ck")
    w.submit(_arrays(), {"generation": 1})
    assert started.wait(30)
    for g in (2, 3, 4):
        w.submit(_arrays(), {"generation": g})
    assert not (tmp_path / "ck").exists()  # the first one still in flight
    gate.set()
    w.flush(30)
    assert order == [1, 4] and w.written == 2
    assert read_checkpoint(tmp_path / "ck")[1] == {"generation": 4}

    def boom(path, arrays, meta):
        raise OSError("disk full")

    monkeypatch.setattr(io_ck, "write_checkpoint", boom)
    w.submit(_arrays(), {"generation": 5})
    with pytest.raises(OSError, match="disk full"):
        w.flush(30)
    assert w.take_error() is None  # flush took it
    w.submit(_arrays(), {"generation": 6})
    with pytest.raises(OSError, match="disk full"):
        w.close(30)  # close flushes (the failure comes with it), then the thread ends
    assert w._thread is None
    assert read_checkpoint(tmp_path / "ck")[1] == {"generation": 4}
    monkeypatch.undo()
    w.submit(_arrays(), {"generation": 7})  # after close: another thread
    w.close(30)
    assert read_checkpoint(tmp_path / "ck")[1] == {"generation": 7} and w.written == 3


#: a process writing checkpoints through the background writer as fast as it can (16 MB:
#: each write lasts tens of ms), the generation in the metadata and in the array
_WRITER = """
import sys
import numpy as np
from stellar_cal_ros.io.checkpoint import CheckpointWriter
w = CheckpointWriter(sys.argv[1])
x = np.zeros(2_000_000)
g = 0
while True:
    g += 1
    x[:] = g
    w.submit({"x": x.copy()}, {"generation": g})
    w.flush()
"""


def test_a_kill_during_a_write_leaves_the_last_checkpoint_whole(tmp_path):
    """kill -9 at any moment of the writer's loop (mostly inside a write: serialising,
    writing, fsync): the file is always the whole of one generation."""
    ck = tmp_path / "ck"
    killed_in_write = 0
    for i in range(5):
        proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(ck)])
        try:
            t_end = time.monotonic() + 120
            while not ck.exists() and time.monotonic() < t_end and proc.poll() is None:
                time.sleep(0.02)
            time.sleep(0.05 + 0.11 * i)
        finally:
            proc.kill()
            proc.wait(30)
        killed_in_write += bool(list(tmp_path.glob("ck.*.tmp")))
        arrays, meta = read_checkpoint(ck)
        assert meta["generation"] >= 1
        np.testing.assert_array_equal(arrays["x"], np.full(2_000_000, meta["generation"]))
        for tmp in tmp_path.glob("ck.*.tmp"):
            tmp.unlink()
    print(f"{killed_in_write} of 5 kills left a temporary file (killed writing it)")

    buf = io.BytesIO()
    np.savez(buf, x=np.arange(3.0), meta=np.frombuffer(json.dumps({"v": 1}).encode(),
                                                         dtype=np.uint8))
    p = tmp_path / "old.npz"
    p.write_bytes(buf.getvalue())
    arrays, meta = read_checkpoint(p)
    assert meta == {"v": 1} and list(arrays) == ["x"]
    p.write_bytes(buf.getvalue()[:100])  # truncated zip: no BadZipFile escapes
    with pytest.raises(CheckpointError, match="unreadable"):
        read_checkpoint(p)


def test_calibrator_truncated_checkpoint(tmp_path):
    """Calibrator checkpoints: a resumed copy has the same pending state; damage is named."""
    from stellar_cal_ros.methods.checkpoint import load_checkpoint, save_checkpoint
    from stellar_cal_ros.methods.driver import Calibrator
    from stellar_cal_ros.sim.scenarios import get_scenario
    from stellar_cal_ros.sim.world import simulate

    sim = simulate(get_scenario("psce_rotations"), duration=5.0, seed=2)
    cal = Calibrator(sim.prior)
    imu = sim.imu
    for t, w in zip(imu.stamp_ns[:300], imu.angular_velocity[:300], strict=True):
        cal.push_imu(int(t), w)
    for f in sim.star_frames[:4]:
        cal.push_stars(f)
    ck = tmp_path / "calibrator.ckpt"
    save_checkpoint(cal, ck)
    again = Calibrator(sim.prior)
    load_checkpoint(again, ck)
    assert [f.stamp_ns for f in again._frames_pending] == [
        f.stamp_ns for f in cal._frames_pending]
    assert again._imu.n == cal._imu.n
    ck.write_bytes(ck.read_bytes()[: ck.stat().st_size * 2 // 3])
    with pytest.raises(CheckpointError, match="truncated"):
        load_checkpoint(Calibrator(sim.prior), ck)


# ---------------------------------------------------------------------------- the schema
#: objects the filter's constructor builds from the prior, model and configuration, and
#: workspaces every step overwrites (the swaying transition matrix) or builds on first use
#: (the fused compiled frame step, the compiled star update alone)
_BUILT = {"model", "config", "layout", "gate", "update_policy", "grid", "site", "_Phi",
          "_frame_step", "_update_step", "_frame_one"}


def _differences(a, b, where=""):
    """Where two values differ (arrays exactly, NaN = NaN; objects by ``state()``)."""
    if hasattr(a, "state") and callable(a.state):
        return _differences(a.state(), b.state(), where)
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        same = a.shape == b.shape and a.dtype == b.dtype and np.array_equal(
            a, b, equal_nan=a.dtype.kind in "fc")
        return [] if same else [where]
    if isinstance(a, float) and isinstance(b, float):
        return [] if a == b or (a != a and b != b) else [where]
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if len(a) != len(b) or type(a) is not type(b):
            return [where]
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True))
                for d in _differences(x, y, f"{where}[{i}]")]
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            return [where]
        return [d for k in a for d in _differences(a[k], b[k], f"{where}.{k}")]
    if hasattr(a, "__dict__") and type(a) is type(b):
        return _differences(vars(a), vars(b), where)
    return [] if a == b else [where]


def _filter_differences(first, second) -> list[str]:
    """Attributes of two filters that differ, the constructor-built objects left out; the
    error state by what it holds (covariance, nominal values, sensitivity)."""
    out = []
    for k in vars(first):
        if k in _BUILT:
            continue
        a, b = getattr(first, k), getattr(second, k)
        if k == "state":
            a = {"P": a.P, "nominal": a.nominal, "sensitivity": a.sensitivity}
            b = {"P": b.P, "nominal": b.nominal, "sensitivity": b.sensitivity}
        out += _differences(a, b, k)
    return out


def _half_way(method, scenario, consider):
    from stellar_cal_ros.methods.driver import Calibrator, DriverConfig
    from stellar_cal_ros.sim.scenarios import get_scenario
    from stellar_cal_ros.sim.world import simulate

    sim = simulate(get_scenario(scenario), duration=60.0, seed=4)

    def make():
        return Calibrator(sim.prior, method, None, consider=consider,
                          driver=DriverConfig(reorder_window_s=0.05))

    events = []
    for t, w, f in zip(sim.imu.stamp_ns, sim.imu.angular_velocity,
                       sim.imu.linear_acceleration, strict=True):
        events.append((int(t), 0, ("imu", int(t), w, f)))
    for fr in sim.star_frames:
        events.append((int(fr.stamp_ns), 1, ("stars", fr)))
    n = sim.navsat
    for row in zip(n.stamp_ns.tolist(), n.latitude_deg.tolist(), n.longitude_deg.tolist(),
                   n.altitude_m.tolist(), strict=True):
        events.append((int(row[0]), -1, ("fix", *row)))
    events.sort(key=lambda e: (e[0], e[1]))

    def feed(cal, part):
        for _, _, ev in part:
            if ev[0] == "imu":
                cal.push_imu(ev[1], ev[2], ev[3])
            elif ev[0] == "stars":
                cal.push_stars(ev[1])
            else:
                cal.push_fix(*ev[1:])

    return make, events, feed


@pytest.mark.parametrize("method,scenario", [("psce", "psce_rotations"),
                                             ("swaying_base", "swaying")])
def test_restored_filter_is_the_saved_one_attribute_for_attribute(method, scenario, tmp_path):
    """The schema holds every part of the filter's state: after load, the filter (error
    state, sensitivity, IMU buffer, propagation, the declared fields) equals the saved one
    attribute for attribute, and both continue bit for bit."""
    from stellar_cal_ros.methods.checkpoint import load_checkpoint, save_checkpoint

    make, events, feed = _half_way(method, scenario, ["time_offset"])
    first = make()
    half = int(0.6 * len(events))
    feed(first, events[:half])
    assert first.filter.initialized and first.filter.counters.updates > 10
    ck = tmp_path / "c.ckpt"
    save_checkpoint(first, ck)
    # only the IMU samples the filter still reads, from the one before its current sample
    # (not the up to 4 096 more its trim leaves until it copies: 3 592 held here, 0.9-1.2 MB
    # files, before)
    rows = len(read_checkpoint(ck)[0]["filter.imu.t"])
    assert rows <= 2 + round(1.0 / first.nominal_dt), rows
    assert ck.stat().st_size < 100_000
    second = make()
    load_checkpoint(second, ck)
    diff = _filter_differences(first.filter, second.filter)
    assert not diff, f"state not in the checkpoint schema: {diff}"
    assert second.pending() == first.pending()
    for cal in (first, second):
        feed(cal, events[half:])
        cal.finish()
    np.testing.assert_array_equal(second.filter.theta, first.filter.theta)
    np.testing.assert_array_equal(second.filter.P, first.filter.P)
    np.testing.assert_array_equal(second.filter.sensitivity.M, first.filter.sensitivity.M)
    assert second.all_counters() == first.all_counters()


def test_the_live_nodes_statistics_resume_field_for_field(tmp_path):
    """The node's driver (live_window: the statistics in data-time blocks): the blocks go
    into the file as one array (a list of dicts took ~7 ms and 90 kB at 120 blocks) and come
    back field for field; both runs go on to the same statistics and estimates."""
    from stellar_cal_ros.methods.checkpoint import load_checkpoint, save_checkpoint
    from stellar_cal_ros.methods.driver import Calibrator, DriverConfig

    made, events, feed = _half_way("psce", "psce_rotations", None)
    prior = made().prior

    def make():
        return Calibrator(prior, "psce", None, driver=DriverConfig(
            reorder_window_s=0.05, live_window=True, defer_checks=True))

    first = make()
    half = int(0.6 * len(events))
    feed(first, events[:half])
    assert len(first.stats.blocks) > 20
    save_checkpoint(first, tmp_path / "c.ckpt")
    arrays, meta = read_checkpoint(tmp_path / "c.ckpt")
    assert arrays["driver.stats.blocks"].shape[0] == len(first.stats.blocks)
    assert len(json.dumps(meta["driver"]["stats"])) < 1000
    second = make()
    load_checkpoint(second, tmp_path / "c.ckpt")
    assert second.stats == first.stats and second.stats.blocks == first.stats.blocks
    for cal in (first, second):
        feed(cal, events[half:])
        cal.finish()
    assert second.stats.current().summary() == first.stats.current().summary()
    np.testing.assert_array_equal(second.filter.theta, first.filter.theta)


def test_unknown_schema_version_is_refused_in_one_line(tmp_path):
    """Another version (a newer file, or one of the formats before the schema) is one line,
    and the calibrator it was to be loaded into is untouched (it starts from the prior)."""
    from stellar_cal_ros.methods.checkpoint import VERSION, load_checkpoint, save_checkpoint

    make, events, feed = _half_way("psce", "psce_rotations", None)
    cal = make()
    feed(cal, events[:3000])
    ck = tmp_path / "c.ckpt"
    save_checkpoint(cal, ck)
    arrays, meta = read_checkpoint(ck)
    assert meta["schema"] == "stellar_cal_checkpoint" and meta["version"] == VERSION
    assert {"blocks", "covariance", "nominal", "sensitivity", "counters", "imu",
            "propagation", "fields"} == set(meta["filter"])
    assert meta["filter"]["blocks"][0] == ["attitude", 3, "rotation", True]
    for bad, says in (({**meta, "version": VERSION + 1}, f"version {VERSION + 1}"),
                      ({k: v for k, v in meta.items() if k not in ("schema", "version")}
                       | {"format": "stellar_cal_checkpoint/4"}, "stellar_cal_checkpoint/4")):
        write_checkpoint(tmp_path / "other.ckpt", arrays, bad)
        fresh = make()
        with pytest.raises(CheckpointError) as err:
            load_checkpoint(fresh, tmp_path / "other.ckpt")
        text = str(err.value)
        assert "\n" not in text and says in text and f"version {VERSION} only" in text
        assert fresh.filter is None and fresh.counters.imu_received == 0
    # a file of this version whose contents do not fit it: one line, and a fresh start
    broken = {**meta, "filter": {**meta["filter"], "blocks": [["attitude", 3, "rotation",
                                                               True]]}}
    write_checkpoint(tmp_path / "broken.ckpt", arrays, broken)
    fresh = make()
    with pytest.raises(CheckpointError, match="state blocks"):
        load_checkpoint(fresh, tmp_path / "broken.ckpt")
    assert fresh.filter is None and fresh.counters.imu_received == 0
