"""Helpers shared by the bag tests: bags with known content and exact comparisons."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stellar_cal_ros.core.types import ImuSeries, NavSatSeries, ScalarSeries, StarFrame
from stellar_cal_ros.io.bag import BagReader, BagWriter

SCALARS = {"head": "/star_tracker/temperature", "air": "/environment/temperature",
           "pressure": "/environment/pressure"}
IMU_FIELDS = ("stamp_ns", "angular_velocity", "linear_acceleration", "log_time_ns",
              "angular_velocity_covariance", "linear_acceleration_covariance", "frame_id")
NAV_FIELDS = ("stamp_ns", "latitude_deg", "longitude_deg", "altitude_m", "status", "service",
              "position_covariance", "position_covariance_type", "log_time_ns", "frame_id")
SCALAR_FIELDS = ("stamp_ns", "value", "variance", "log_time_ns", "frame_id")
STAR_FIELDS = ("stamp_ns", "log_time_ns", "frame_id", "exposure_time", "catalog_id",
               "right_ascension", "declination", "uv", "magnitude", "sigma")


def simulated_bag(path: Path, duration: float = 60.0, seed: int = 1,
                  chunk_size: int | None = None) -> Path:
    """A PSCE contract bag from the simulator (``chunk_size``: rewrite with that chunk size)."""
    from stellar_cal_ros.sim.scenarios import get_scenario
    from stellar_cal_ros.sim.world import simulate, write_simulation

    paths = write_simulation(simulate(get_scenario("psce_rotations"), duration=duration,
                                      seed=seed), path)
    if chunk_size is None:
        return paths["bag"]
    content = read_all(BagReader(path))
    tmp = path.with_suffix(".tmp.mcap")
    with BagWriter(tmp, chunk_size=chunk_size) as w:
        w.write_imu(content["imu"])
        w.write_star_frames(content["stars"])
        w.write_navsat(content["fix"])
        for role, topic in SCALARS.items():
            kind = "pressure" if role == "pressure" else "temperature"
            w.write_scalar(content[role], topic, kind=kind)
    tmp.replace(path)
    return path


def read_all(reader: BagReader) -> dict:
    """Every contract topic through the ``read_*`` methods (closes the reader)."""
    with reader as r:
        out = {"imu": r.read_imu(), "stars": r.read_star_frames(), "fix": r.read_navsat()}
        out.update({role: r.read_scalar(topic) for role, topic in SCALARS.items()})
    return out


def assert_same(a, b, fields, what: str = "") -> None:
    """Exact equality of the named fields of two objects (arrays or scalars)."""
    for f in fields:
        x, y = getattr(a, f), getattr(b, f)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            np.testing.assert_array_equal(x, y, err_msg=f"{what}.{f}")
        else:
            assert x == y, f"{what}.{f}: {x!r} != {y!r}"


def assert_same_content(a: dict, b: dict) -> None:
    """Two :func:`read_all` results hold exactly the same messages."""
    assert_same(a["imu"], b["imu"], IMU_FIELDS, "imu")
    assert len(a["stars"]) == len(b["stars"])
    for k, (x, y) in enumerate(zip(a["stars"], b["stars"], strict=True)):
        assert_same(x, y, STAR_FIELDS, f"stars[{k}]")
    assert_same(a["fix"], b["fix"], NAV_FIELDS, "fix")
    for role in SCALARS:
        assert_same(a[role], b[role], SCALAR_FIELDS, role)


def join_stream(blocks: list[tuple[str, object]]) -> dict:
    """Concatenate the blocks of each role of a ``stream()`` into ``read_*``-like results."""
    by_role: dict[str, list] = {}
    for role, block in blocks:
        by_role.setdefault(role, []).append(block)
    out: dict = {}
    for role, items in by_role.items():
        first = items[0]
        if isinstance(first, StarFrame):
            out[role] = items
        else:
            out[role] = type(first).concatenate(items)
            assert isinstance(out[role], ImuSeries | NavSatSeries | ScalarSeries)
    return out


def block_times(block) -> np.ndarray:
    """Log times of a stream block, ns."""
    t = block.log_time_ns
    return np.atleast_1d(np.asarray(t, np.int64))
