"""Any ROS bag in: rosbag2 sqlite3, split rosbag2 MCAP and ROS 1 give the MCAP's data exactly.

A simulated bag is converted with ``rosbags`` (an independent implementation) to a rosbag2
sqlite3 directory, a rosbag2 MCAP directory split in three files and a ROS 1 ``.bag``; the
reader must return identical arrays, and ``replay`` the same calibration.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from bag_checks import assert_same_content, join_stream, read_all, simulated_bag

from stellar_cal_ros.cli import main
from stellar_cal_ros.errors import BagError
from stellar_cal_ros.io.bag import BagReader


def _convert(src: Path, dst: Path, storage: str) -> Path:
    from rosbags.convert import convert

    convert([src], dst, storage, 8, None, "file", None, None, [], [], [], [])
    return dst


def _split_mcap(src: Path, dst: Path, parts: int = 3) -> Path:
    """A rosbag2 MCAP directory of ``parts`` files split by time, written by rosbags."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer

    dst.mkdir()
    infos = []
    with AnyReader([src]) as reader:
        edges = np.linspace(reader.start_time, reader.end_time, parts + 1).astype(np.int64)
        for k in range(parts):
            sub = dst / f"part{k}"
            with Writer(sub, version=8, storage_plugin=StoragePlugin.MCAP) as w:
                conns = {}
                stop = int(edges[k + 1]) if k < parts - 1 else None
                for c, t, raw in reader.messages(start=int(edges[k]), stop=stop):
                    if c.id not in conns:
                        conns[c.id] = w.add_connection(c.topic, c.msgtype,
                                                       typestore=reader.typestore)
                    w.write(conns[c.id], t, raw)
            next(sub.glob("*.mcap")).rename(dst / f"split_{k}.mcap")
            infos.append(yaml.safe_load((sub / "metadata.yaml").read_text())
                         ["rosbag2_bagfile_information"])
            shutil.rmtree(sub)
    info = infos[0]
    info["relative_file_paths"] = [f"split_{k}.mcap" for k in range(parts)]
    info["files"] = [dict(m["files"][0], path=f"split_{k}.mcap") for k, m in enumerate(infos)]
    info["message_count"] = sum(m["message_count"] for m in infos)
    (dst / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information": info}))
    return dst


@pytest.fixture(scope="module")
def bags(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("formats")
    mcap = simulated_bag(d / "sim.mcap", duration=120.0, seed=5)
    return {
        "mcap": mcap,
        "rosbag2_sqlite3": _convert(mcap, d / "rb2_sqlite3", "sqlite3"),
        "rosbag2_mcap_split": _split_mcap(mcap, d / "rb2_split"),
        "ros1": _convert(mcap, d / "ros1.bag", "sqlite3"),
    }


FORMATS = ["rosbag2_sqlite3", "rosbag2_mcap_split", "ros1"]


@pytest.mark.parametrize("fmt", FORMATS)
def test_converted_bag_reads_identically(bags: dict[str, Path], fmt: str) -> None:
    with BagReader(bags["mcap"]) as ref, BagReader(bags[fmt]) as r:
        assert r.storage == {"rosbag2_sqlite3": "rosbag2-sqlite3", "ros1": "rosbag1",
                             "rosbag2_mcap_split": "rosbag2-mcap"}[fmt]
        assert r.topics() == ref.topics()
        assert (r.start_ns, r.end_ns) == (ref.start_ns, ref.end_ns)
        assert r.check() == []
        blocks = list(r.stream())
    want = read_all(BagReader(bags["mcap"]))
    assert_same_content(read_all(BagReader(bags[fmt])), want)
    assert_same_content(join_stream(blocks), want)


@pytest.mark.parametrize("fmt", ["rosbag2_sqlite3", "ros1"])
def test_a_rosbags_open_builds_the_contract_typestore_once(bags: dict[str, Path], fmt: str,
                                                           monkeypatch) -> None:
    """One open of a bag through rosbags builds one typestore of Jazzy's and the contract
    types (rosbags compiles a class per type: ~0.08 CPU-s a build): the one that decodes
    (H284).  coord 0e2fd9e built one more for ``AnyReader``'s default, which reads only its
    definitions (for a bag that carries none).  The reads stay the MCAP's
    (test_converted_bag_reads_identically, test_other_entry_points' ROS 1 decoding)."""
    from rosbags.typesys.store import Typestore

    sizes: list[int] = []
    register = Typestore.register

    def counted(self, typs):
        sizes.append(len(typs))
        return register(self, typs)

    monkeypatch.setattr(Typestore, "register", counted)
    with BagReader(bags[fmt]) as r:
        assert r.check() == []
    # (AnyReader's own store holds the bag's definitions: a few types)
    assert len([n for n in sizes if n > 100]) == 1, sizes


def test_other_entry_points(bags: dict[str, Path], tmp_path: Path) -> None:
    want = read_all(BagReader(bags["mcap"]))
    db3 = next(bags["rosbag2_sqlite3"].glob("*.db3"))  # the storage file alone
    assert_same_content(read_all(BagReader(db3)), want)
    crashed = tmp_path / "crashed"  # a recording killed before writing metadata.yaml
    crashed.mkdir()
    for f in bags["rosbag2_mcap_split"].glob("*.mcap"):
        shutil.copy(f, crashed / f.name)
    assert_same_content(read_all(BagReader(crashed)), want)
    with BagReader(bags["ros1"]) as r:  # generic decoding of a ROS 1 bag
        topic, t, msg = next(r.iter_messages(["/gnss/fix"]))
    assert topic == "/gnss/fix" and t == int(want["fix"].log_time_ns[0])
    assert msg.latitude == want["fix"].latitude_deg[0]
    assert msg.header.frame_id == want["fix"].frame_id
    fake = tmp_path / "fake.bag"
    fake.write_bytes(b"not a bag")
    with pytest.raises(BagError, match="not a ROS 1 bag"):
        BagReader(fake)


def _numbers(node, prefix=""):
    """Flatten the numbers of a YAML tree: {path: float}."""
    if isinstance(node, dict):
        out = {}
        for k, v in node.items():
            out.update(_numbers(v, f"{prefix}/{k}"))
        return out
    if isinstance(node, list):
        out = {}
        for k, v in enumerate(node):
            out.update(_numbers(v, f"{prefix}[{k}]"))
        return out
    return {prefix: float(node)} if isinstance(node, int | float) else {}


def _replay(bag: Path, out: Path) -> dict[str, float]:
    # the command in this process (a subprocess each cost ~3 CPU-s of start-up: imports and
    # loading the compiled kernels; replay in its own process: test_faults.py's campaign)
    prior = bag.parent / "sim.prior.yaml"
    assert main(["replay", str(bag), "--method", "psce", "--prior", str(prior), "-o", str(out),
                 "-q"]) == 0
    return _numbers(yaml.safe_load(out.read_text()))


def test_replay_gives_the_same_calibration_on_every_format(bags, tmp_path: Path) -> None:
    ref = _replay(bags["mcap"], tmp_path / "mcap.yaml")
    assert len(ref) > 50
    for fmt in FORMATS:
        got = _replay(bags[fmt], tmp_path / f"{fmt}.yaml")
        assert got.keys() == ref.keys()
        for k, v in ref.items():
            assert got[k] == pytest.approx(v, rel=1e-9, abs=1e-300), f"{fmt}: {k}"


def test_replay_merges_imu_blocks_without_changing_a_float(bags, tmp_path: Path,
                                                           monkeypatch) -> None:
    """A bag's IMU blocks merged across star frames (``replay._merged_imu``) reach the
    driver in fewer calls; where the filter's IMU chunks and frame runs split changes, not
    a float: the history CSV byte for byte and every number of the result as with the
    blocks as read (``IMU_MERGE_S`` 0: no merge).  A run that reads no environment or fix
    message (``_env_unread``: this psce replay) merges across those too, fewer calls still,
    and hands them on a release's rows a call (``push_scalars``, ``push_fixes``): the same
    bytes."""
    from stellar_cal_ros.methods import driver
    from stellar_cal_ros.methods import replay as replay_mod

    calls: list[int] = []
    each: list[dict[str, int]] = []

    def counted(name):
        original = getattr(driver.Calibrator, name)

        def call(self, *a, **k):
            if name == "push_imu_block":
                calls[-1] += 1
            each[-1][name] = each[-1].get(name, 0) + 1
            return original(self, *a, **k)
        return call

    for name in ("push_imu_block", "push_scalar", "push_fix", "push_scalars", "push_fixes"):
        monkeypatch.setattr(driver.Calibrator, name, counted(name))
    merge, quiet = replay_mod.IMU_MERGE_S, replay_mod.IMU_MERGE_QUIET_S
    unread = replay_mod._env_quiet
    out = []
    # as read; across star frames only (cut at each environment or fix message); across all
    for s, q, across_env in ((0.0, 0.0, False), (merge, quiet, False), (merge, quiet, True)):
        monkeypatch.setattr(replay_mod, "IMU_MERGE_S", s)
        monkeypatch.setattr(replay_mod, "IMU_MERGE_QUIET_S", q)
        monkeypatch.setattr(replay_mod, "_env_quiet",
                            unread if across_env else lambda cal: False)
        calls.append(0)
        each.append({})
        numbers = _replay(bags["mcap"], tmp_path / f"merge{len(calls)}.yaml")
        out.append((numbers, (tmp_path / f"merge{len(calls)}.history.csv").read_bytes()))
    assert 0 < calls[2] < 0.2 * calls[1] and 0 < calls[1] < 0.5 * calls[0], calls
    scalars, fixes = each[0]["push_scalar"], each[0]["push_fix"]
    assert scalars > 300 and fixes > 100 and each[1] == each[0] | {"push_imu_block": calls[1]}
    # the bulk calls: a release's rows of a role (the first fixes before the filter starts
    # go one at a time: each may start it)
    assert "push_scalar" not in each[2] and each[2].get("push_fix", 0) < 0.2 * fixes, each
    assert 0 < each[2]["push_scalars"] < 0.2 * scalars and 0 < each[2]["push_fixes"], each
    assert out[1][0] == out[0][0] == out[2][0] and len(out[0][0]) > 50
    assert out[1][1] == out[0][1] == out[2][1] and out[0][1].count(b"\n") > 100


def _count_star_inputs(monkeypatch) -> list[list[int]]:
    """The star messages a replay hands the driver, counted: a ``[with inputs, without]``
    list appended per run (``Calibrator.push_stars`` and ``Calibrator.push_stars_many`` as
    the replay calls them; the calls they make of each other inside: not again)."""
    from stellar_cal_ros.methods import driver

    given: list[list[int]] = []
    one, many = driver.Calibrator.push_stars, driver.Calibrator.push_stars_many
    inside = [False]

    def counted(call, self, frames, inputs):
        if inside[0]:
            return call(self, frames, inputs)
        for inp in inputs or [None] * len(frames):
            given[-1][inp is None] += 1
        inside[0] = True
        try:
            return call(self, frames, inputs)
        finally:
            inside[0] = False

    def push(self, frame, inputs=None):
        return counted(lambda s, f, i: one(s, f[0], None if i is None else i[0]), self,
                       [frame], None if inputs is None else [inputs])

    def push_many(self, frames, inputs=None):
        return counted(many, self, frames, inputs)

    monkeypatch.setattr(driver.Calibrator, "push_stars", push)
    monkeypatch.setattr(driver.Calibrator, "push_stars_many", push_many)
    return given


def test_replay_takes_a_releases_star_inputs_in_one_call(bags, tmp_path: Path,
                                                          monkeypatch) -> None:
    """A replay computes the filter inputs of a release's star messages in one call
    (``Calibrator.star_inputs``, ``replay._release_items``) and hands each message its own
    (``push_stars(frame, inputs)``): the history CSV byte for byte and every number of the
    result as when each message computes its own (``star_inputs`` None), and nearly every
    message takes the batch's."""
    from stellar_cal_ros.methods import driver

    given = _count_star_inputs(monkeypatch)
    original_inputs = driver.Calibrator.star_inputs
    out = []
    for batch in (False, True):
        monkeypatch.setattr(driver.Calibrator, "star_inputs",
                            original_inputs if batch else lambda self, frames: None)
        given.append([0, 0])
        numbers = _replay(bags["mcap"], tmp_path / f"inputs{batch}.yaml")
        out.append((numbers, (tmp_path / f"inputs{batch}.history.csv").read_bytes()))
    (each_with, each_own), (batch_with, batch_own) = given
    assert each_with == 0 and each_own > 200 and batch_own == 0, given
    assert batch_with == each_own, given
    assert out[0][0] == out[1][0] and len(out[0][0]) > 50
    assert out[0][1] == out[1][1] and out[0][1].count(b"\n") > 100


def test_replay_of_bag_data_takes_star_inputs_a_chunk_at_once(bags, monkeypatch) -> None:
    """A replay of data in memory (:class:`BagData`: the diagnosis's runs) computes its
    frames' filter inputs ``INPUT_FRAMES`` frames a call (``replay._grouped_frames``):
    θ, P, the counters and the tables bit for bit as when each frame computes its own, with
    chunks of 256 frames and of 7 (frames across a chunk's edge)."""
    from stellar_cal_ros.io.calibration import load_calibration
    from stellar_cal_ros.methods import driver
    from stellar_cal_ros.methods import replay as replay_mod

    data = replay_mod.read_bag_data(bags["mcap"])
    prior = load_calibration(bags["mcap"].parent / "sim.prior.yaml")
    given = _count_star_inputs(monkeypatch)
    original_inputs = driver.Calibrator.star_inputs
    out = []
    for batch, chunk in ((False, 256), (True, 256), (True, 7)):
        monkeypatch.setattr(driver.Calibrator, "star_inputs",
                            original_inputs if batch else lambda self, frames: None)
        monkeypatch.setattr(replay_mod, "INPUT_FRAMES", chunk)
        given.append([0, 0])
        res = replay_mod.replay(data, prior, "psce")
        tables = [np.asarray(t[k]).tobytes() for t in (res.history, res.residuals) for k in t]
        out.append((res.filter.theta.tobytes(), res.filter.P.tobytes(), res.counters, tables))
    assert given[0] == [0, len(data.frames)] and len(data.frames) > 200, given
    assert given[1] == given[2] == [len(data.frames), 0], given
    assert out[0] == out[1] == out[2] and len(out[0][3]) > 10


def test_a_swaying_replay_merges_across_the_fixes_once_its_filter_runs(tmp_path: Path,
                                                                        monkeypatch) -> None:
    """A method that needs a site (swaying_base) reads the fixes until its filter is built
    (at their median so far; each may start it), then no more when no effect reads the
    site (``Calibrator.site_read``; ``replay._env_quiet``): from the filter's start on,
    its IMU blocks merge across the environment and fix messages too, which reach the
    driver a release's rows a call (``push_scalars``, ``push_fixes``: in bulk, no pump).
    The history CSV byte for byte and every number of the result as with the messages
    as they came (``_env_quiet`` False: the IMU cut at each of them, each pushed alone)."""
    from sim_bags import swaying_bag

    from stellar_cal_ros.io.calibration import load_calibration
    from stellar_cal_ros.methods import driver
    from stellar_cal_ros.methods import replay as replay_mod
    from stellar_cal_ros.methods.results import NullSink, TableSink

    bag, prior, _ = swaying_bag(60.0, seed=4)
    cal = driver.Calibrator(load_calibration(prior), "swaying_base", residuals=NullSink())
    assert cal.site_read is False and "site" in cal.requires
    assert not replay_mod._env_unread(cal) and callable(replay_mod._env_quiet(cal))
    assert replay_mod._env_unread(cal, started=True)
    assert replay_mod._env_quiet(driver.Calibrator(load_calibration(prior), "swaying_base",
                                                   residuals=TableSink())) is False
    each: list[dict[str, int]] = []

    def counted(name):
        original = getattr(driver.Calibrator, name)

        def call(self, *a, **k):
            each[-1][name] = each[-1].get(name, 0) + 1
            return original(self, *a, **k)
        return call

    for name in ("push_imu_block", "push_scalar", "push_fix", "push_scalars", "push_fixes"):
        monkeypatch.setattr(driver.Calibrator, name, counted(name))
    quiet = replay_mod._env_quiet
    out = []
    for k, q in enumerate((lambda c: False, quiet)):
        monkeypatch.setattr(replay_mod, "_env_quiet", q)
        each.append({})
        res = tmp_path / f"sway{k}.yaml"
        assert main(["replay", str(bag), "--method", "swaying_base", "--prior", str(prior),
                     "-o", str(res), "-q"]) == 0
        out.append((_numbers(yaml.safe_load(res.read_text())),
                    res.with_suffix(".history.csv").read_bytes()))
    before, after = each
    assert before["push_imu_block"] >= 55 and after["push_imu_block"] < 0.3 * 60, each
    assert before["push_scalar"] >= 150 and before["push_fix"] >= 55, each
    # (one at a time over the first release of rows: the filter did not run at its start)
    assert after["push_scalar"] < 0.4 * 183 and after["push_fix"] < 0.4 * 61, each
    assert after["push_scalars"] >= 1 and after["push_fixes"] >= 1, each
    assert out[0][0] == out[1][0] and len(out[0][0]) > 50
    assert out[0][1] == out[1][1] and out[0][1].count(b"\n") > 100


def _same(a, b) -> bool:
    """Equal values, types and array dtypes/shapes, through tuples, lists and dataclasses."""
    import dataclasses

    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and \
            a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b, equal_nan=True)
    if dataclasses.is_dataclass(a):
        return type(a) is type(b) and all(_same(getattr(a, f.name), getattr(b, f.name))
                                          for f in dataclasses.fields(a))
    if isinstance(a, tuple | list):
        return type(a) is type(b) and len(a) == len(b) and all(map(_same, a, b))
    return type(a) is type(b) and a == b


@pytest.mark.parametrize("fmt", ["mcap", *FORMATS])
def test_replay_events_from_releases_are_those_of_the_stream(bags, fmt: str) -> None:
    """A replay reads a bag a release of rows at a time (``BagReader.stream_releases``,
    ``replay._release_items``): the driver gets the same calls, in the same order, with the
    same arrays as from the stream's blocks (``replay._merged_imu``) — as read (no merge),
    across star frames, across all; IMU runs cut every 4096 samples and every 7."""
    from stellar_cal_ros.methods import replay as replay_mod

    settings = [(frozenset({"stars"}), 0.0), (frozenset({"stars"}), None),
                (replay_mod.ENV_ROLES | {"stars"}, 30.0)]
    for across, limit in settings:
        for imu_block in (replay_mod.IMU_BLOCK, 7):
            with BagReader(bags[fmt]) as r:
                want = list(replay_mod._merged_imu(r.stream(imu_block=imu_block), across,
                                                   limit))
            with BagReader(bags[fmt]) as r:
                got = list(replay_mod._merge_items(
                    replay_mod._release_items(r.stream_releases(), imu_block), across, limit))
            assert len(got) == len(want) > 300
            roles = {role for role, _ in got}
            assert roles >= {"imu", "stars", "fix", "head", "air", "pressure"}
            bad = [k for k, (g, w) in enumerate(zip(got, want, strict=True)) if not _same(g, w)]
            assert not bad, (fmt, across, limit, imu_block, bad[:3])


def test_imu_merges_across_environment_messages_only_when_nothing_reads_them(bags) -> None:
    """``_env_unread``: a psce replay without a residual table reads no environment or fix
    message; a residual table (the head temperature column), a thermal effect (the head
    temperature) or a site-bound method (the fixes' median) does, and its IMU blocks are
    cut at those messages as before.  The merge hands the messages on in their order."""
    from types import SimpleNamespace

    from stellar_cal_ros.io.calibration import load_calibration
    from stellar_cal_ros.methods import replay as replay_mod
    from stellar_cal_ros.methods.driver import Calibrator
    from stellar_cal_ros.methods.results import NullSink, TableSink

    prior = load_calibration(bags["mcap"].parent / "sim.prior.yaml")
    assert replay_mod._env_unread(Calibrator(prior, "psce", residuals=NullSink()))
    assert not replay_mod._env_unread(Calibrator(prior, "psce", residuals=TableSink()))
    assert not replay_mod._env_unread(Calibrator(prior, "psce", ["thermal_focal_length"],
                                                 residuals=NullSink()))
    assert not replay_mod._env_unread(Calibrator(prior, "swaying_base", residuals=NullSink()))

    def imu(t0):
        t = np.arange(t0, t0 + 3, dtype=np.int64) * 10**7
        return "imu", SimpleNamespace(stamp_ns=t, angular_velocity=np.zeros((3, 3)),
                                      linear_acceleration=None, frame_id="imu")

    head = SimpleNamespace(stamp_ns=np.array([5]), value=np.array([20.0]))
    fix = SimpleNamespace(stamp_ns=np.array([6]), latitude_deg=np.array([1.0]),
                          longitude_deg=np.array([2.0]), altitude_m=np.array([3.0]),
                          status=np.array([0]))
    stream = [imu(0), ("stars", "F1"), ("head", head), imu(3), ("fix", fix), ("stars", "F2"),
              imu(6)]
    cut = [(r, p if r != "imu" else len(p[0])) for r, p in replay_mod._merged_imu(stream)]
    assert cut == [("imu", 3), ("stars", "F1"), ("head", (5, 20.0)), ("imu", 3),
                   ("fix", (6, 1.0, 2.0, 3.0, 0)), ("stars", "F2"), ("imu", 3)]
    across = replay_mod.ENV_ROLES | {"stars"}
    merged = [(r, p if r != "imu" else len(p[0]))
              for r, p in replay_mod._merged_imu(stream, across, 30.0)]
    assert merged == [("imu", 9), ("stars", "F1"), ("head", (5, 20.0)),
                      ("fix", (6, 1.0, 2.0, 3.0, 0)), ("stars", "F2")]


@pytest.mark.parametrize("fmt", ["mcap", *FORMATS])
def test_read_whole_is_each_topics_read_in_one_pass(bags, fmt: str) -> None:
    """``BagReader.read_whole`` (what ``read_bag_data`` reads through) gives what the
    ``read_*`` methods give topic by topic — values, dtypes, frame ids — reading the bag's
    chunks once, not once a topic; a conversion of the star messages sees them in order
    and drops its None; a topic of another type is refused as ``read_imu`` refuses it."""
    from bag_checks import SCALARS

    topics = {"stars": ("/star_tracker/stars", "stars"), "imu": ("/imu/data", "imu"),
              "fix": ("/gnss/fix", "fix"), **{k: (t, "scalar") for k, t in SCALARS.items()}}
    want = read_all(BagReader(bags[fmt]))
    with BagReader(bags[fmt]) as r:
        passes = []
        rows = r._rows
        r._rows = lambda want_, what: passes.append(what) or rows(want_, what)
        got = r.read_whole(topics)
        seen: list = []
        half = r.read_whole({"stars": topics["stars"]},  # every other frame, in order
                            convert={"stars": lambda f: seen.append(f) or
                                     (f if len(seen) % 2 else None)})
    assert len(passes) == 2
    assert list(got) == list(topics)
    bad = [k for k in topics if not _same(got[k], want[k])]
    assert not bad and len(got["stars"]) > 100 and len(got["imu"].stamp_ns) > 10_000, bad
    assert _same(seen, want["stars"]) and _same(half["stars"], want["stars"][0::2])
    with BagReader(bags[fmt]) as r, pytest.raises(BagError, match="expected sensor_msgs/msg/Imu"):
        r.read_whole({"imu": ("/gnss/fix", "imu")})
