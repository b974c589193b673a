"""MCAP bag I/O: write/read round trip, independent readers, reference bags, error handling."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import refdata

from stellar_cal_ros.core.types import ImuSeries, NavSatSeries, ScalarSeries, StarFrame
from stellar_cal_ros.errors import BagError, MessageDecodeError
from stellar_cal_ros.io.bag import IMU_SCHEMA, SCHEMA_TEXTS, BagReader, BagWriter

DATA = refdata.DATA
BAGS = refdata.files("*.mcap")
needs_data = refdata.needs()

T0 = 1_795_348_800 * 10**9


def _frames(rng: np.random.Generator, n: int, frame_id: str) -> list[StarFrame]:
    out = []
    for k in range(n):
        m = [0, 1, 5, 17][k % 4]
        out.append(
            StarFrame(
                stamp_ns=T0 + k * 500_000_000 + 253_700_001,
                frame_id=frame_id,
                exposure_time=float(np.float32(0.1)),
                catalog_id=rng.integers(0, 120_000, m).astype(np.uint32),
                right_ascension=rng.uniform(0, 2 * np.pi, m),
                declination=rng.uniform(-1.5, 1.5, m),
                uv=rng.uniform(0, 1024, (m, 2)),
                magnitude=rng.uniform(-1, 6, m).astype(np.float32).astype(float),
                sigma=np.full(m, np.float32(0.05), dtype=float),
            )
        )
    return out


@pytest.fixture()
def content():
    rng = np.random.default_rng(7)
    n = 1000
    imu = ImuSeries(
        stamp_ns=T0 + np.arange(1, n + 1, dtype=np.int64) * 10_000_000 + 3,
        angular_velocity=rng.normal(size=(n, 3)) * 1e-2,
        linear_acceleration=rng.normal(size=(n, 3)) + [0, 0, 9.8],
        frame_id="imu_link",
        angular_velocity_covariance=np.eye(3).ravel() * 1e-11,
        linear_acceleration_covariance=np.eye(3).ravel() * 1e-6,
    )
    # a second IMU with a frame_id of another length (other CDR alignment of the doubles)
    imu2 = ImuSeries(
        imu.stamp_ns[:50] + 1, imu.angular_velocity[:50], imu.linear_acceleration[:50], "i"
    )
    ns = 11
    ts = T0 + np.arange(ns, dtype=np.int64) * 10**9
    nav = NavSatSeries(
        ts,
        np.full(ns, 36.07),
        np.full(ns, 120.38),
        np.linspace(10, 11, ns),
        np.zeros(ns, int),
        service=np.ones(ns, int),
        position_covariance=np.tile(np.diag([1.0, 1, 4]).ravel(), (ns, 1)),
        position_covariance_type=np.full(ns, 2),
    )
    temp = ScalarSeries(
        ts, np.linspace(30, 29, ns), np.full(ns, 0.01), "star_tracker_optical_frame"
    )
    air = ScalarSeries(ts, np.linspace(5, 4, ns), np.zeros(ns), "environment")
    pres = ScalarSeries(ts, np.full(ns, 101200.0), np.full(ns, 4.0), "environment")
    stars = _frames(rng, 20, "star_tracker_optical_frame")
    stars_odd = _frames(rng, 8, "cam1")  # first StarCentroid packed (catalog_id at 4 mod 8)
    return {
        "imu": imu,
        "imu2": imu2,
        "nav": nav,
        "temp": temp,
        "air": air,
        "pres": pres,
        "stars": stars,
        "stars_odd": stars_odd,
    }


def _write(path: Path, c: dict, compression: str = "zstd", chunk_size: int = 16 * 1024) -> Path:
    with BagWriter(path, compression=compression, chunk_size=chunk_size) as w:
        w.write_imu(c["imu"])
        w.write_imu(c["imu2"], topic="/imu2")
        for f in c["stars"]:
            w.write_star_frame(f)
        w.write_star_frames(c["stars_odd"], topic="/stars_odd")
        w.write_navsat(c["nav"])
        w.write_scalar(c["temp"], "/star_tracker/temperature")
        w.write_scalar(c["air"], "/environment/temperature")
        w.write_scalar(c["pres"], "/environment/pressure", kind="pressure")
    return path


def _assert_frames_equal(a: StarFrame, b: StarFrame) -> None:
    assert a.stamp_ns == b.stamp_ns and a.frame_id == b.frame_id
    assert a.exposure_time == pytest.approx(b.exposure_time, rel=1e-7)
    for k in ("catalog_id", "right_ascension", "declination", "uv", "magnitude", "sigma"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_round_trip(tmp_path: Path, content, compression: str) -> None:
    path = _write(tmp_path / "t.mcap", content, compression)
    with BagReader(path) as r:
        tops = r.topics()
        assert tops["/imu/data"].schema_name == "sensor_msgs/msg/Imu"
        assert tops["/imu/data"].message_count == 1000
        assert tops["/star_tracker/stars"].message_count == 20
        assert r.start_ns == T0 and r.end_ns == int(content["imu"].stamp_ns[-1])
        imu = r.read_imu()
        src = content["imu"]
        np.testing.assert_array_equal(imu.stamp_ns, src.stamp_ns)
        np.testing.assert_array_equal(imu.log_time_ns, src.stamp_ns)
        np.testing.assert_array_equal(imu.angular_velocity, src.angular_velocity)
        np.testing.assert_array_equal(imu.linear_acceleration, src.linear_acceleration)
        np.testing.assert_array_equal(
            imu.angular_velocity_covariance, src.angular_velocity_covariance
        )
        assert imu.frame_id == "imu_link"
        imu2 = r.read_imu("/imu2")
        assert imu2.frame_id == "i"
        np.testing.assert_array_equal(imu2.angular_velocity, content["imu2"].angular_velocity)
        blocks = list(r.iter_imu_blocks(block_size=333))
        assert [len(b) for b in blocks] == [333, 333, 333, 1]
        np.testing.assert_array_equal(np.concatenate([b.stamp_ns for b in blocks]), src.stamp_ns)
        for got, want in zip(r.read_star_frames(), content["stars"], strict=True):
            _assert_frames_equal(got, want)
        for got, want in zip(r.read_star_frames("/stars_odd"), content["stars_odd"], strict=True):
            _assert_frames_equal(got, want)
        nav = r.read_navsat()
        for k in (
            "stamp_ns",
            "latitude_deg",
            "longitude_deg",
            "altitude_m",
            "status",
            "service",
            "position_covariance",
            "position_covariance_type",
        ):
            np.testing.assert_array_equal(getattr(nav, k), getattr(content["nav"], k), err_msg=k)
        for topic, key in (
            ("/star_tracker/temperature", "temp"),
            ("/environment/temperature", "air"),
            ("/environment/pressure", "pres"),
        ):
            s = r.read_scalar(topic)
            np.testing.assert_array_equal(s.value, content[key].value)
            np.testing.assert_array_equal(s.variance, content[key].variance)
            assert s.frame_id == content[key].frame_id
        # log-time order across topics in the file
        times = [t for _, t, _ in r.iter_messages()]
        assert times == sorted(times) and len(times) == sum(v.message_count for v in tops.values())


def test_mcap_ros2_decodes_written_bag(tmp_path: Path, content) -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path = _write(tmp_path / "t.mcap", content)
    got: dict[str, list] = {}
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        for schema in summary.schemas.values():
            assert schema.encoding == "ros2msg"
            assert schema.data.decode() == SCHEMA_TEXTS[schema.name]
        for _, channel, message, msg in reader.iter_decoded_messages(log_time_order=False):
            assert message.log_time == message.publish_time
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            assert stamp == message.log_time
            got.setdefault(channel.topic, []).append(msg)
    imu = got["/imu/data"]
    np.testing.assert_array_equal(
        [[m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z] for m in imu],
        content["imu"].angular_velocity,
    )
    assert imu[0].orientation_covariance[0] == -1.0 and imu[0].orientation.w == 1.0
    odd = got["/stars_odd"]
    for m, f in zip(odd, content["stars_odd"], strict=True):
        assert [s.catalog_id for s in m.stars] == f.catalog_id.tolist()
        assert [s.u for s in m.stars] == f.uv[:, 0].tolist()
        assert [s.sigma for s in m.stars] == f.sigma.tolist()


def test_rosbags_reads_written_bag(tmp_path: Path, content) -> None:
    from rosbags.highlevel import AnyReader

    path = _write(tmp_path / "t.mcap", content)
    with AnyReader([path]) as reader:  # registers stellar_cal_msgs from the schema texts
        counts = {c.topic: c.msgcount for c in reader.connections}
        assert counts["/imu/data"] == 1000 and counts["/stars_odd"] == 8
        av, stars, nav, pres = [], [], [], []
        for conn, t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == t
            if conn.topic == "/imu/data":
                av.append([msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z])
            elif conn.topic == "/stars_odd":
                stars.append(msg)
            elif conn.topic == "/gnss/fix":
                nav.append((msg.latitude, msg.status.status, msg.status.service))
            elif conn.topic == "/environment/pressure":
                pres.append(msg.fluid_pressure)
    np.testing.assert_array_equal(av, content["imu"].angular_velocity)
    for m, f in zip(stars, content["stars_odd"], strict=True):
        assert m.header.frame_id == "cam1"
        assert [s.catalog_id for s in m.stars] == f.catalog_id.tolist()
        assert [s.declination for s in m.stars] == f.declination.tolist()
        assert [s.v for s in m.stars] == f.uv[:, 1].tolist()
    assert nav[0] == (36.07, 0, 1)
    assert pres == content["pres"].value.tolist()


@needs_data
@pytest.mark.parametrize("path", BAGS, ids=lambda p: p.name)
def test_reference_bag(path: Path) -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    meta = json.loads(path.with_suffix(".meta.json").read_text())
    with BagReader(path) as r:
        tops = r.topics()
        print(path.name, {t: (i.schema_name, i.message_count) for t, i in tops.items()})
        assert {t: i.message_count for t, i in tops.items()} == meta["counts"]
        for topic, info in tops.items():
            name, text = r.raw_schema(topic)
            assert text == SCHEMA_TEXTS[name] and name == info.schema_name
        imu = r.read_imu()
        frames = r.read_star_frames()
        assert len(imu) == meta["counts"]["/imu/data"]
        assert len(frames) == meta["counts"]["/star_tracker/stars"]
    ref_imu, ref_st = [], []
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _, ch, message, msg in reader.iter_decoded_messages(
            topics=["/imu/data", "/star_tracker/stars"]
        ):
            lst = ref_imu if ch.topic == "/imu/data" else ref_st
            if len(lst) < 1000:
                lst.append((message.log_time, msg))
            if len(ref_imu) >= 1000 and len(ref_st) >= min(1000, len(frames)):
                break
    k = len(ref_imu)
    np.testing.assert_array_equal(imu.log_time_ns[:k], [t for t, _ in ref_imu])
    np.testing.assert_array_equal(
        imu.stamp_ns[:k], [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for _, m in ref_imu]
    )
    np.testing.assert_array_equal(
        imu.angular_velocity[:k],
        [[m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z] for _, m in ref_imu],
    )
    np.testing.assert_array_equal(
        imu.linear_acceleration[:k],
        [
            [m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z]
            for _, m in ref_imu
        ],
    )
    assert imu.frame_id == ref_imu[0][1].header.frame_id
    for f, (t, m) in zip(frames, ref_st, strict=False):
        assert f.log_time_ns == t and f.frame_id == m.header.frame_id
        assert f.stamp_ns == m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
        assert f.exposure_time == m.exposure_time
        assert f.catalog_id.tolist() == [s.catalog_id for s in m.stars]
        assert f.right_ascension.tolist() == [s.right_ascension for s in m.stars]
        assert f.declination.tolist() == [s.declination for s in m.stars]
        assert f.uv.tolist() == [[s.u, s.v] for s in m.stars]
        assert f.magnitude.tolist() == [s.magnitude for s in m.stars]
        assert f.sigma.tolist() == [s.sigma for s in m.stars]


@needs_data
def test_schema_constants_match_reference() -> None:
    with BagReader(DATA / "psce_ideal_900s.mcap") as r:
        assert r.profile == "ros2"
        assert r.raw_schema("/imu/data") == ("sensor_msgs/msg/Imu", IMU_SCHEMA)


def _truncated(tmp_path: Path, content, frac: float = 0.6) -> tuple[Path, int]:
    if BAGS:
        src = DATA / "psce_ideal_900s.mcap"
        if not src.exists():
            src = BAGS[0]
    else:
        src = _write(tmp_path / "full.mcap", content)
    data = src.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * frac)])
    with BagReader(src) as r:
        n = r.topics()["/imu/data"].message_count
    return cut, n


def test_truncated_strict_raises_bag_error(tmp_path: Path, content) -> None:
    cut, _ = _truncated(tmp_path, content)
    with BagReader(cut) as r:
        assert not r.has_summary
        with pytest.raises(BagError, match="truncated or corrupt") as exc:
            r.read_imu()
        assert "byte" in str(exc.value) and "chunks read" in str(exc.value)
        with pytest.raises(BagError):
            r.topics()


def test_truncated_lenient_reads_what_is_there(tmp_path: Path, content) -> None:
    cut, n_full = _truncated(tmp_path, content)
    with BagReader(cut, on_error="skip") as r:
        with pytest.warns(UserWarning, match="truncated or corrupt"):
            imu = r.read_imu()
        assert 0 < len(imu) < n_full
        assert np.all(np.diff(imu.log_time_ns) > 0)
        assert r.truncated
        with pytest.warns(UserWarning, match="no summary"):
            tops = r.topics()
        assert tops["/imu/data"].message_count == len(imu)
        with pytest.warns(UserWarning):
            frames = r.read_star_frames()
        assert frames and frames[-1].stamp_ns <= imu.stamp_ns[-1] + 10**9


@pytest.mark.parametrize("frac", [0.0001, 0.01, 0.3, 0.99, 0.9999])
def test_truncated_anywhere_never_leaks_internal_errors(
    tmp_path: Path, content, frac: float
) -> None:
    src = _write(tmp_path / "full.mcap", content)
    data = src.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: max(1, int(len(data) * frac))])
    try:
        with BagReader(cut) as r:
            r.read_imu()
            r.read_star_frames()
    except BagError:
        pass
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with BagReader(cut, on_error="skip") as r:
                r.read_imu()
                list(r.iter_messages())
    except BagError:
        pass


def test_corrupt_chunk_is_bag_error(tmp_path: Path, content) -> None:
    src = _write(tmp_path / "full.mcap", content, compression="none")
    data = bytearray(src.read_bytes())
    data[2000:2016] = b"\xff" * 16  # inside the first chunk
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with BagReader(bad) as r, pytest.raises(BagError, match="CRC"):
        r.read_imu()


def test_missing_and_not_mcap(tmp_path: Path) -> None:
    with pytest.raises(BagError, match="no such bag"):
        BagReader(tmp_path / "nope.mcap")
    p = tmp_path / "x.mcap"
    p.write_text("hello, this is not a bag at all")
    with pytest.raises(BagError, match="not an MCAP"):
        BagReader(p)
    with pytest.raises(BagError, match="cannot open"):
        BagReader(tmp_path)
    (tmp_path / "empty.mcap").write_bytes(b"")
    with pytest.raises(BagError, match="not an MCAP"):
        BagReader(tmp_path / "empty.mcap")


def test_missing_topic(tmp_path: Path, content) -> None:
    path = _write(tmp_path / "t.mcap", content)
    with BagReader(path) as r:
        with pytest.raises(BagError, match="/nope"):
            r.read_imu("/nope")
        with pytest.raises(BagError, match="expected"):
            r.read_imu("/star_tracker/stars")


def _malformed_bag(tmp_path: Path, content) -> tuple[Path, int, int]:
    path = tmp_path / "m.mcap"
    t_short = int(content["imu"].stamp_ns[500]) + 5
    t_wrong = int(content["imu"].stamp_ns[700]) + 5
    with BagWriter(path) as w:
        w.write_imu(content["imu"])
        w.write_raw("/imu/data", "sensor_msgs/msg/Imu", IMU_SCHEMA, t_short, b"\x00\x01\x00\x00abc")
        w.write_raw(
            "/imu/data",
            "std_msgs/msg/String",
            "string data\n",
            t_wrong,
            b"\x00\x01\x00\x00\x03\x00\x00\x00hi\x00",
        )
        for f in content["stars"]:
            w.write_star_frame(f)
        w.write_raw(
            "/star_tracker/stars",
            "stellar_cal_msgs/msg/StarCentroidArray",
            SCHEMA_TEXTS["stellar_cal_msgs/msg/StarCentroidArray"],
            T0 + 7,
            b"\x00\x01\x00\x00" + b"\x01" * 30,
        )
    return path, t_short, t_wrong


def test_malformed_message_strict(tmp_path: Path, content) -> None:
    path, t_short, _ = _malformed_bag(tmp_path, content)
    with BagReader(path) as r:
        with pytest.raises(MessageDecodeError) as exc:
            r.read_imu()
        assert exc.value.topic == "/imu/data" and exc.value.log_time_ns == t_short
        assert "/imu/data" in str(exc.value) and f"{t_short * 1e-9:.9f}" in str(exc.value)
        assert "shorter" in str(exc.value)
        with pytest.raises(MessageDecodeError, match="/star_tracker/stars"):
            r.read_star_frames()


def test_malformed_message_skip(tmp_path: Path, content) -> None:
    path, _, _ = _malformed_bag(tmp_path, content)
    with BagReader(path, on_error="skip") as r:
        with pytest.warns(UserWarning, match="skipped 2 malformed"):
            imu = r.read_imu()
        np.testing.assert_array_equal(imu.angular_velocity, content["imu"].angular_velocity)
        assert r.skipped == {"/imu/data": 2}
        with pytest.warns(UserWarning, match="skipped 1 malformed"):
            frames = r.read_star_frames()
        assert len(frames) == len(content["stars"])
        assert r.skipped == {"/imu/data": 2, "/star_tracker/stars": 1}


def test_iter_messages_decodes_with_mcap_ros2(tmp_path: Path, content) -> None:
    path = _write(tmp_path / "t.mcap", content)
    with BagReader(path) as r:
        msgs = list(r.iter_messages(["/gnss/fix", "/stars_odd"]))
    assert len(msgs) == 11 + 8
    topic, t, msg = msgs[0]
    assert topic == "/gnss/fix" and t == T0 and msg.latitude == 36.07


def test_empty_bag(tmp_path: Path) -> None:
    path = tmp_path / "e.mcap"
    with BagWriter(path) as w:
        w.write_imu(ImuSeries(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3))))
    with BagReader(path) as r:
        assert r.topics()["/imu/data"].message_count == 0
        assert len(r.read_imu()) == 0


def test_cli_replays_a_truncated_bag_when_asked(tmp_path, capsys):
    """A recording cut short (power loss) is calibrated on what it holds with --on-error skip.

    The CLI in-process (no interpreter start-up): a traceback would raise out of main()."""
    from stellar_cal_ros.cli import main
    from stellar_cal_ros.sim.scenarios import get_scenario
    from stellar_cal_ros.sim.world import simulate, write_simulation

    paths = write_simulation(simulate(get_scenario("psce_rotations"), duration=300.0, seed=2),
                             tmp_path / "full.mcap")
    cut = tmp_path / "cut.mcap"
    data = paths["bag"].read_bytes()
    cut.write_bytes(data[: int(0.6 * len(data))])
    exe = ["replay", str(cut), "--method", "psce", "--prior", str(paths["prior"]), "-o",
           str(tmp_path / "r.yaml"), "-q"]
    capsys.readouterr()
    assert main(exe) == 1
    strict = capsys.readouterr().err
    assert "truncated or corrupt bag" in strict and "Traceback" not in strict
    rc = main(exe + ["--on-error", "skip"])
    assert rc == 0, capsys.readouterr().err[-2000:]
    assert (tmp_path / "r.yaml").exists()
