"""BagReader.stream(): one pass, log-time order, blocks equal to the read_* results."""

from __future__ import annotations

import dataclasses
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest
import refdata
from bag_checks import (
    SCALARS,
    assert_same_content,
    block_times,
    join_stream,
    read_all,
    simulated_bag,
)

from stellar_cal_ros.core.types import ImuSeries, ScalarSeries, StarFrame
from stellar_cal_ros.errors import BagError, MessageDecodeError
from stellar_cal_ros.io import cdr
from stellar_cal_ros.io.bag import IMU_SCHEMA, SCHEMA_TEXTS, BagReader, BagWriter
from stellar_cal_ros.io.mcap_container import McapFile

BAGS = refdata.files("*.mcap")
T0 = 1_795_348_800 * 10**9


def _stream(path: Path, **kw) -> list:
    with BagReader(path) as r:
        return list(r.stream(**kw))


def _assert_ordered(blocks: list) -> None:
    last = -1
    for _, b in blocks:
        t = block_times(b)
        assert np.all(np.diff(t) >= 0) and t[0] >= last
        last = int(t[-1])


@pytest.fixture(scope="module")
def sim_bag(tmp_path_factory) -> Path:
    return simulated_bag(tmp_path_factory.mktemp("stream") / "sim.mcap", duration=40.0,
                         chunk_size=64 * 1024)


def test_stream_equals_read_and_is_time_ordered(sim_bag: Path) -> None:
    blocks = _stream(sim_bag, imu_block=7)
    _assert_ordered(blocks)
    assert {r for r, _ in blocks} == {"imu", "stars", "fix", *SCALARS}
    assert max(len(b) for r, b in blocks if r == "imu") == 7
    assert all(isinstance(b, StarFrame) for r, b in blocks if r == "stars")
    assert all(isinstance(b, ScalarSeries) for r, b in blocks if r in SCALARS)
    # consecutive messages: no message of another role between a block's first and last
    spans = [(int(block_times(b)[0]), int(block_times(b)[-1])) for _, b in blocks]
    assert all(a[1] <= b[0] for a, b in zip(spans, spans[1:], strict=False))
    assert_same_content(join_stream(blocks), read_all(BagReader(sim_bag)))


def test_stream_reads_each_chunk_once(sim_bag: Path, monkeypatch) -> None:
    calls: list[int] = []
    original = McapFile.read_chunk

    def counting(self, offset, length):
        calls.append(offset)
        return original(self, offset, length)

    monkeypatch.setattr(McapFile, "read_chunk", counting)
    with BagReader(sim_bag) as r:
        n_chunks = len(r._src.plan())
        n_blocks = sum(1 for _ in r.stream())
    assert n_blocks > 0 and n_chunks > 10
    assert sorted(calls) == sorted(set(calls)) and len(calls) == n_chunks


def test_stream_roles_topics_and_absent_topics(sim_bag: Path) -> None:
    blocks = _stream(sim_bag, topics={"gyro": "/imu/data", "gps": "/gnss/fix",
                                      "nothing": "/not/recorded"})
    assert {r for r, _ in blocks} == {"gyro", "gps"}
    ref = read_all(BagReader(sim_bag))
    got = join_stream(blocks)
    np.testing.assert_array_equal(got["gyro"].angular_velocity, ref["imu"].angular_velocity)
    np.testing.assert_array_equal(got["gps"].latitude_deg, ref["fix"].latitude_deg)
    assert _stream(sim_bag, topics={}) == []
    with pytest.raises(ValueError, match="imu_block"):
        _stream(sim_bag, imu_block=0)


def _imu(n: int, t0: int, step: int = 10_000_000) -> ImuSeries:
    rng = np.random.default_rng(n)
    return ImuSeries(t0 + np.arange(n, dtype=np.int64) * step, rng.normal(size=(n, 3)),
                     rng.normal(size=(n, 3)), "imu_link",
                     angular_velocity_covariance=np.arange(9.0))


def _star(t: int, n: int = 3) -> StarFrame:
    return StarFrame(t, "st", 0.1, np.arange(n, dtype=np.uint32), np.full(n, 0.5),
                     np.full(n, 0.1), np.full((n, 2), 100.0), np.ones(n), np.full(n, 0.05))


def _mcap_in_call_order(path: Path, messages: list[tuple[str, str, int, bytes]],
                        chunk_size: int, **options) -> Path:
    """Write with the ``mcap`` library, messages in the given order (chunks may overlap)."""
    from mcap.writer import CompressionType, Writer

    with open(path, "wb") as fh:
        w = Writer(fh, chunk_size=chunk_size, compression=CompressionType.NONE, **options)
        w.start(profile="ros2", library="test")
        channels: dict[str, int] = {}
        for topic, schema, t, data in messages:
            if topic not in channels:
                sid = w.register_schema(schema, "ros2msg", SCHEMA_TEXTS[schema].encode())
                channels[topic] = w.register_channel(topic, "cdr", sid)
            w.add_message(channels[topic], log_time=t, data=data, publish_time=t)
        w.finish()
    return path


def _imu_payloads(series: ImuSeries) -> list[bytes]:
    _, size, encode = cdr.imu_encoder(series)
    raw = encode(np.arange(len(series))).tobytes()
    return [raw[k * size:(k + 1) * size] for k in range(len(series))]


def test_overlapping_chunks_and_ties(tmp_path: Path) -> None:
    imu = _imu(2000, T0)
    stars = [_star(T0 + k * 500_000_000) for k in range(40)]  # ties with IMU stamps
    temp = ScalarSeries(T0 + np.arange(20, dtype=np.int64) * 10**9 + 3, np.arange(20.0),
                        np.zeros(20), "env")
    _, size, enc = cdr.scalar_encoder(temp)
    temp_raw = enc(np.arange(20)).tobytes()
    msgs = [("/imu/data", "sensor_msgs/msg/Imu", int(t), p)
            for t, p in zip(imu.stamp_ns, _imu_payloads(imu), strict=True)]
    # stars after every IMU message: the last chunks start at T0 and overlap all others;
    # temperatures in reverse order: sorted inside their chunk
    msgs += [("/star_tracker/stars", "stellar_cal_msgs/msg/StarCentroidArray", f.stamp_ns,
              cdr.encode_star_frame(f)) for f in stars]
    msgs += [("/star_tracker/temperature", "sensor_msgs/msg/Temperature", int(temp.stamp_ns[k]),
              temp_raw[k * size:(k + 1) * size]) for k in reversed(range(20))]
    path = _mcap_in_call_order(tmp_path / "overlap.mcap", msgs, chunk_size=8192)
    with BagReader(path) as r:
        starts = sorted(c.start for c in r._src.plan())
        assert starts.count(T0) >= 2  # overlapping chunks indeed
        blocks = list(r.stream(imu_block=1000))
        _assert_same_blocks(_cut_releases(r.stream_releases(), 1000), blocks)
    _assert_ordered(blocks)
    got = join_stream(blocks)
    np.testing.assert_array_equal(got["imu"].stamp_ns, imu.stamp_ns)
    np.testing.assert_array_equal(got["imu"].angular_velocity, imu.angular_velocity)
    assert [f.stamp_ns for f in got["stars"]] == [f.stamp_ns for f in stars]
    np.testing.assert_array_equal(got["head"].value, temp.value)
    # ties: at T0 + k*0.5 s the IMU message comes first (earlier chunk in file order)
    order = [(int(t), role) for role, b in blocks for t in block_times(b)]
    k = order.index((T0 + 500_000_000, "stars"))
    assert order[k - 1] == (T0 + 500_000_000, "imu")
    assert_same_content_subset(got, BagReader(path))


def _cut_releases(releases, imu_block: int) -> list:
    """``stream_releases`` cut as its docstring says.

    At the role changes of each release's order, an IMU run every ``imu_block`` rows, a list
    of messages one a block.
    """
    from stellar_cal_ros.io.merge import runs

    def rows(block, a, b):
        n = len(block.stamp_ns)
        return dataclasses.replace(block, **{
            f.name: getattr(block, f.name)[a:b] for f in dataclasses.fields(block)
            if isinstance(getattr(block, f.name), np.ndarray) and
            getattr(block, f.name).ndim and len(getattr(block, f.name)) == n})

    out = []
    for roles, blocks, order in releases:
        assert len(order) == sum(len(b) for b in blocks if b is not None)
        for r, a, b in runs(order):
            block = blocks[r]
            if isinstance(block, list):
                out += [(roles[r], m) for m in block[a:b]]
            else:
                step = imu_block if roles[r] == "imu" else b - a
                out += [(roles[r], rows(block, c, min(c + step, b))) for c in range(a, b, step)]
    return out


def _assert_same_blocks(got: list, want: list) -> None:
    assert [r for r, _ in got] == [r for r, _ in want]
    for (_, g), (_, w) in zip(got, want, strict=True):
        assert type(g) is type(w)
        for k, v in vars(w).items():
            if isinstance(v, np.ndarray):
                assert v.dtype == getattr(g, k).dtype
                np.testing.assert_array_equal(getattr(g, k), v)
            else:
                assert getattr(g, k) == v


def assert_same_content_subset(got: dict, reader: BagReader) -> None:
    with reader as r:
        np.testing.assert_array_equal(got["imu"].log_time_ns, r.read_imu().log_time_ns)
        assert [f.log_time_ns for f in got["stars"]] == \
            [f.log_time_ns for f in r.read_star_frames()]
        np.testing.assert_array_equal(got["head"].stamp_ns,
                                      r.read_scalar("/star_tracker/temperature").stamp_ns)


def test_ties_keep_file_order_within_a_chunk(tmp_path: Path) -> None:
    imu = _imu(3, T0)
    star = _star(T0 + 10_000_000)
    msgs = [("/imu/data", "sensor_msgs/msg/Imu", int(imu.stamp_ns[0]), _imu_payloads(imu)[0]),
            ("/star_tracker/stars", "stellar_cal_msgs/msg/StarCentroidArray", star.stamp_ns,
             cdr.encode_star_frame(star))]
    msgs += [("/imu/data", "sensor_msgs/msg/Imu", int(t), p)
             for t, p in zip(imu.stamp_ns[1:], _imu_payloads(imu)[1:], strict=True)]
    path = _mcap_in_call_order(tmp_path / "ties.mcap", msgs, chunk_size=1 << 20)
    roles = [(r, len(b) if r == "imu" else 1) for r, b in _stream(path)]
    assert roles == [("imu", 1), ("stars", 1), ("imu", 2)]
    with BagReader(path) as r:
        _assert_same_blocks(_cut_releases(r.stream_releases(), 4096), _stream(path))


def test_unchunked_file(tmp_path: Path) -> None:
    """Message records outside chunks (no chunk index): read through the record scan."""
    imu = _imu(3000, T0)
    stars = [_star(T0 + k * 500_000_000 + 1) for k in range(60)]
    msgs = sorted([("/imu/data", "sensor_msgs/msg/Imu", int(t), p)
                   for t, p in zip(imu.stamp_ns, _imu_payloads(imu), strict=True)]
                  + [("/star_tracker/stars", "stellar_cal_msgs/msg/StarCentroidArray",
                      f.stamp_ns, cdr.encode_star_frame(f)) for f in stars],
                  key=lambda m: m[2])
    path = _mcap_in_call_order(tmp_path / "loose.mcap", msgs, 1 << 20, use_chunking=False)
    blocks = _stream(path)
    _assert_ordered(blocks)
    got = join_stream(blocks)
    np.testing.assert_array_equal(got["imu"].angular_velocity, imu.angular_velocity)
    assert [f.stamp_ns for f in got["stars"]] == [f.stamp_ns for f in stars]
    with BagReader(path) as r:
        np.testing.assert_array_equal(r.read_imu().stamp_ns, imu.stamp_ns)
        assert r.check() == []


def _malformed(tmp_path: Path) -> Path:
    imu = _imu(500, T0)
    path = tmp_path / "m.mcap"
    with BagWriter(path) as w:
        w.write_imu(imu)
        w.write_raw("/imu/data", "sensor_msgs/msg/Imu", IMU_SCHEMA, T0 + 5, b"\x00\x01\x00\x00a")
        w.write_raw("/imu/data", "std_msgs/msg/String", "string data\n", T0 + 7,
                    b"\x00\x01\x00\x00\x03\x00\x00\x00hi\x00")
        w.write_star_frames([_star(T0 + k * 500_000_000) for k in range(10)])
        w.write_raw("/star_tracker/stars", "stellar_cal_msgs/msg/StarCentroidArray",
                    SCHEMA_TEXTS["stellar_cal_msgs/msg/StarCentroidArray"], T0 + 9,
                    b"\x00\x01\x00\x00" + b"\x01" * 30)
        w.write_raw("/chatter", "std_msgs/msg/String", "string data\n", T0 + 11,
                    b"\x00\x01\x00\x00\x03\x00\x00\x00hi\x00")
    return path


def test_stream_on_error(tmp_path: Path) -> None:
    path = _malformed(tmp_path)
    with BagReader(path) as r, pytest.raises(MessageDecodeError, match="/imu/data"):
        list(r.stream())
    with BagReader(path, on_error="skip") as r:
        with pytest.warns(UserWarning, match="skipped 2 malformed"):
            got = join_stream(list(r.stream()))
        assert r.skipped == {"/imu/data": 2, "/star_tracker/stars": 1}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            np.testing.assert_array_equal(got["imu"].stamp_ns, r.read_imu().stamp_ns)
        assert len(got["stars"]) == 10
    with BagReader(path) as r, pytest.raises(BagError, match="/chatter.*String"):
        list(r.stream({"imu": "/imu/data", "talk": "/chatter"}))
    with BagReader(path, on_error="skip") as r, pytest.warns(UserWarning, match="left out"):
        assert {role for role, _ in r.stream({"talk": "/chatter"})} == set()


def _stream_peak(path: Path) -> tuple[int, int]:
    """(peak traced bytes while streaming, number of chunks)."""
    tracemalloc.start()
    try:
        with BagReader(path) as r:
            for _ in r.stream():
                pass
            n_chunks = len(r._src.plan())
        return tracemalloc.get_traced_memory()[1], n_chunks
    finally:
        tracemalloc.stop()


def test_stream_memory_does_not_grow_with_the_bag(tmp_path: Path) -> None:
    short = simulated_bag(tmp_path / "short.mcap", duration=30.0, chunk_size=64 * 1024)
    long = simulated_bag(tmp_path / "long.mcap", duration=240.0, chunk_size=64 * 1024)
    _stream_peak(short)  # lazy imports out of the way
    (peak_short, _), (peak_long, n_long) = _stream_peak(short), _stream_peak(long)
    imu_bytes = 24_000 * 64  # what the long bag's IMU alone takes decoded (stamps, log, w, f)
    print(f"stream peak traced memory: 30 s {peak_short / 1e6:.2f} MB, 240 s "
          f"{peak_long / 1e6:.2f} MB ({n_long} chunks, decoded IMU {imu_bytes / 1e6:.1f} MB)")
    # what grows is the chunk index (about 1.4 kB a chunk), not the data
    assert peak_long < 1.2 * peak_short + 2000 * n_long
    assert peak_long < imu_bytes / 3


@refdata.needs()
@pytest.mark.parametrize("path", BAGS, ids=lambda p: p.name)
def test_stream_on_reference_bags(path: Path) -> None:
    blocks = _stream(path)
    _assert_ordered(blocks)
    assert_same_content(join_stream(blocks), read_all(BagReader(path)))


def _random_frame(rng, t: int, n: int, frame_id: str = "st") -> StarFrame:
    uv = rng.uniform(0, 1024, (n, 2))
    return StarFrame(t, frame_id, float(np.float32(rng.uniform(0, 0.2))),
                     rng.integers(0, 2**32, n, dtype=np.uint64).astype(np.uint32),
                     rng.uniform(0, 6.3, n), rng.uniform(-1.5, 1.5, n), uv,
                     rng.normal(5, 2, n).astype(np.float32).astype(float),
                     np.where(rng.random(n) < 0.1, np.nan,
                              rng.uniform(0, 0.1, n)).astype(np.float32).astype(float))


def _batch(payloads: list[bytes]) -> tuple:
    """One buffer holding ``payloads`` (1-byte gaps), their offsets, lengths, log times."""
    off, buf = [], b""
    for p in payloads:
        buf += b"\xee"
        off.append(len(buf))
        buf += p
    ln = [len(p) for p in payloads]
    return (np.frombuffer(buf, np.uint8), np.array(off, np.int64), np.array(ln, np.int64),
            T0 + 7 * np.arange(len(payloads), dtype=np.int64))


def _assert_frames_equal(got: StarFrame, want: StarFrame) -> None:
    for k, v in vars(want).items():
        g = getattr(got, k)
        if isinstance(v, np.ndarray):
            assert g.dtype == v.dtype and g.shape == v.shape, k
            np.testing.assert_array_equal(g, v)
        else:
            assert type(g) is type(v) and g == v, k


def test_star_frames_in_bulk_are_decode_star_array_s() -> None:
    """A batch of well-formed star payloads of one frame_id (8-aligned star arrays: what a
    tracker writes) is decoded in one numpy pass; each frame is ``decode_star_array``'s,
    value for value and dtype for dtype: empty frames, NaN sigmas, trailing padding.  A
    batch with a second frame_id (of another length, of the same), a packed first star
    (frame_id "cam1") or a malformed
    payload is decoded one payload at a time (the errors said as before)."""
    rng = np.random.default_rng(3)
    frames = [_random_frame(rng, T0 + k * 10**8 + k, n) for k, n in
              enumerate([25, 0, 1, 40, 17, 0, 3])]
    payloads = [cdr.encode_star_frame(f) + b"\x00" * (k % 4) for k, f in enumerate(frames)]
    buf, off, ln, log = _batch(payloads)
    assert cdr._star_frames_bulk(buf, off, ln, log) is not None
    dec = cdr.decode_star_frames(buf, off, ln, log)
    assert dec.keep.all() and not dec.bad and len(dec.fields["obj"]) == len(frames)
    np.testing.assert_array_equal(dec.fields["log"], log)
    for k, got in enumerate(dec.fields["obj"]):
        want = cdr.decode_star_array(payloads[k])
        want.log_time_ns = int(log[k])
        _assert_frames_equal(got, want)
        _assert_frames_equal(got, dataclasses.replace(frames[k], log_time_ns=int(log[k])))
    other = cdr.encode_star_frame(_random_frame(rng, T0, 4, "other"))
    same_size = cdr.encode_star_frame(_random_frame(rng, T0, 4, "su"))
    packed = cdr.encode_star_frame(_random_frame(rng, T0, 4, "cam1"))
    short = payloads[0][:-9]
    for odd, bad in ((other, 0), (same_size, 0), (packed, 0), (short, 1)):
        batch = _batch([*payloads[:3], odd, *payloads[3:]])
        assert cdr._star_frames_bulk(*batch) is None
        dec = cdr.decode_star_frames(*batch)
        assert len(dec.bad) == bad and len(dec.fields["obj"]) == len(frames) + 1 - bad
        if not bad:
            want = cdr.decode_star_array(odd)
            want.log_time_ns = int(batch[3][3])
            _assert_frames_equal(dec.fields["obj"][3], want)
