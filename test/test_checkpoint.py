"""Checkpoint files (io/checkpoint.py): atomic writes, verified reads, and the online resume.

A truncated or corrupt checkpoint must give one CheckpointError naming the damage (it gave
``zipfile.BadZipFile`` before the checksum), a crash while writing must leave the previous
checkpoint intact, and a file of the first format (bare .npz) must still load.
"""

from __future__ import annotations

import io
import json
import os

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


def test_first_format_still_loads(tmp_path):
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
