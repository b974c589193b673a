"""calibrator + player nodes, in process: bag → topics → calibrator equals the offline replay.

Both nodes share one Context (private domain id, localhost discovery, unique topic names
through remapping) and one executor spinning in a thread; the player publishes from the
test's thread with flow control (``rate: 0``).
"""

from __future__ import annotations

import math
import re
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
from ros_env import node_env, own_shm_segments, remove_shm_segments
from sim_bags import psce_bag, swaying_bag
from test_online import assert_same, bag_events, feed, live_psce

from stellar_cal_ros.io.bag import BagReader
from stellar_cal_ros.io.calibration import load_calibration
from stellar_cal_ros.methods.replay import replay_psce

pytestmark = pytest.mark.ros

try:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import CameraInfo, Imu, NavSatFix, Temperature
    from std_srvs.srv import Trigger
    from stellar_cal_msgs.msg import (
        CalibrationEstimate,
        StarCentroid,
        StarCentroidArray,
        StarResidualArray,
    )

    from stellar_cal_ros.nodes.calibrator import INPUTS, CalibratorNode
    from stellar_cal_ros.nodes.player import PlayerNode

    _IMPORT_ERROR = None
except ImportError as exc:
    _IMPORT_ERROR = exc

EXCERPT_S = 60.0
# the ros_context fixture (conftest.py) and the node processes' environment (ros_env):
# this process's private domain, localhost discovery, Fast DDS asked for UDP
BAG, PRIOR, _ = psce_bag(EXCERPT_S)


@pytest.fixture(scope="module")
def excerpt():
    path = BAG
    prior = load_calibration(PRIOR)
    with BagReader(path) as r:
        counts = {t: i.message_count for t, i in r.topics().items()}
    return path, prior, replay_psce(path, prior, config=live_psce()), counts


class Spinner:
    """An executor spinning the given nodes in a background thread."""

    def __init__(self, ctx, *nodes):
        self.ex = SingleThreadedExecutor(context=ctx)
        for n in nodes:
            self.ex.add_node(n)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        while not self.stop.is_set():
            self.ex.spin_once(timeout_sec=0.05)

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join(5)
        self.ex.shutdown()


def remaps(prefix: str) -> list[str]:
    args = ["--ros-args"]
    for topic, _ in INPUTS.values():
        args += ["-r", f"{topic}:={prefix}{topic}"]
    args += ["-r", f"/clock:={prefix}/clock", "-r", f"/diagnostics:={prefix}/diagnostics"]
    return args


def make_calibrator(ctx, prefix, tmp_path, **params):
    values = {"prior_file": str(PRIOR), "reorder_window_s": 0.05,
              "estimate_rate_hz": 20.0, "diagnostics_rate_hz": 10.0,
              "output_file": str(tmp_path / "result.yaml"),
              "checkpoint_file": str(tmp_path / "calibrator.npz"),
              "checkpoint_period_s": 0.0}
    values.update(params)
    return CalibratorNode(
        f"calibrator_{prefix[1:]}", context=ctx, cli_args=remaps(prefix),
        use_global_arguments=False,
        parameter_overrides=[Parameter(k, value=v) for k, v in values.items()])


def make_player(ctx, prefix, bag, **params):
    """A player of ``bag`` into ``make_calibrator(ctx, prefix, ...)``'s node: as fast as the
    node takes the messages in (``rate`` 0: flow control on its ``~/data_clock``), after the
    handshake (its latched ``~/inputs_matched``: the node's subscriptions have matched every
    played topic's publishers, so no message is lost before the node is listening)."""
    ns = f"/calibrator_{prefix[1:]}"
    values = {"bag": str(bag), "rate": 0.0, "progress_topic": ns + "/data_clock",
              "match_topic": ns + "/inputs_matched", "wait_for_subscribers_s": 20.0}
    values.update(params)
    return PlayerNode(f"player_{prefix[1:]}_{uuid.uuid4().hex[:4]}", context=ctx,
                      cli_args=remaps(prefix), use_global_arguments=False,
                      parameter_overrides=[Parameter(k, value=v) for k, v in values.items()])


def wait_for(pred, timeout=20.0, what="condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return
        time.sleep(0.01)
    raise AssertionError(f"timed out waiting for {what}")


class Collector:
    def __init__(self, node, typ, topic):
        self.msgs = []
        node.create_subscription(typ, topic, self.msgs.append,
                                 QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))


def test_bag_through_topics_equals_offline_replay(ros_context, excerpt, tmp_path):
    path, prior, ref, counts = excerpt
    prefix = "/t" + uuid.uuid4().hex[:8]
    cal = make_calibrator(ros_context, prefix, tmp_path)
    player = make_player(ros_context, prefix, path)
    ns = f"/calibrator_{prefix[1:]}"
    est = Collector(player, CalibrationEstimate, ns + "/estimate")
    info = Collector(player, CameraInfo, ns + "/camera_info")
    res = Collector(player, StarResidualArray, ns + "/residuals")
    diag = Collector(player, DiagnosticArray, prefix + "/diagnostics")
    with Spinner(ros_context, cal, player):
        t0 = time.perf_counter()
        stats = player.play()
        wall = time.perf_counter() - t0
        assert stats.messages == sum(counts.values())
        n_imu = counts["/imu/data"]
        wait_for(lambda: cal.received["imu"] == n_imu
                 and cal.received["stars"] == counts["/star_tracker/stars"], what="all input")
        cal.finish()
        wait_for(lambda: len(res.msgs) == counts["/star_tracker/stars"], what="residuals")
        wait_for(lambda: est.msgs and info.msgs and any(
            kv.key == "received.imu" and kv.value == str(n_imu)
            for kv in diag.msgs[-1].status[0].values), what="estimate + diagnostics")
    assert stats.ack_timeouts == 0 and stats.unmatched_topics == 0
    # the handshake: the node's report of its subscriptions' publishers (the player's)
    assert player.consumer_matched == cal.inputs_matched() == {
        **{prefix + t: 1 for t, _ in INPUTS.values()}, ns + "/data_clock": 1}
    assert cal.received == {k: counts[t] for k, (t, _) in INPUTS.items()}
    # every message arrived unchanged and in the replay's order: the same calibration
    online = cal.cal.calibration()
    assert_same(online, ref.calibration)
    assert cal.cal.filter_counters()["updates"] == ref.counters["updates"]
    saved = load_calibration(tmp_path / "result.yaml")
    assert_same(saved, ref.calibration)
    assert (tmp_path / "calibrator.npz").exists()
    # outputs
    updated = [m for m in res.msgs if m.dof > 0]
    assert len(updated) == ref.counters["updates"]
    assert sum(len(m.residuals) for m in updated) == len(ref.residuals["u"])
    # ~/residuals are serialized from the arrays (residual_cdr): the replay's values
    got = {k: np.array([getattr(r, k) for m in updated for r in m.residuals])
           for k in ("catalog_id", "u", "v", "predicted_u", "predicted_v", "cov_uu", "cov_uv",
                     "cov_vv", "magnitude", "gated")}
    rr = ref.residuals
    for k, kr in (("catalog_id", "catalog_id"), ("u", "u"), ("v", "v"),
                  ("predicted_u", "u_pred"), ("predicted_v", "v_pred"), ("cov_uu", "s_uu"),
                  ("cov_uv", "s_uv"), ("cov_vv", "s_vv"), ("gated", "gated")):
        np.testing.assert_allclose(got[k].astype(float), rr[kr].astype(float), rtol=1e-9,
                                   atol=1e-12, err_msg=k)
    np.testing.assert_array_equal(got["magnitude"], rr["magnitude"].astype(np.float32))
    e = est.msgs[-1]
    assert list(e.names) == cal.cal.parameter_names()
    assert len(e.values) == len(e.sigmas) == len(e.names)
    assert e.header.frame_id == "imu_link"
    ci = info.msgs[-1]
    assert ci.width == 1024 and ci.distortion_model == "plumb_bob" and len(ci.d) == 5
    st = diag.msgs[-1].status[0]
    keys = {kv.key: kv.value for kv in st.values}
    assert keys["received.imu"] == str(n_imu) and "latency_p99_ms" in keys
    # the verdict it publishes is the replay's (the second half of the data so far)
    ref_cons = ref.calibration.extra["consistency"]
    assert st.level == DiagnosticStatus.OK, st.message
    assert keys["consistency.verdict"] == ref_cons["verdict"] == "consistent"
    assert float(keys["consistency.nis_per_dof"]) == pytest.approx(ref_cons["nis_per_dof"],
                                                                   rel=0.03)
    print(f"\n{stats.messages} messages in {wall:.2f} s ({stats.messages / wall:.0f} msg/s)")
    cal.destroy_node()
    player.destroy_node()


def test_swaying_base_live_equals_its_replay(ros_context, tmp_path):
    """method:=swaying_base (a moored ship): the site from /gnss/fix, gravity in the inertial
    frame; the bag played through topics gives the replay's installation to 0.1 σ."""
    from stellar_cal_ros.core.units import ARCSEC
    from stellar_cal_ros.methods.swaying import replay_swaying

    bag, prior_path, _ = swaying_bag(60.0)
    prior = load_calibration(prior_path)
    ref = replay_swaying(bag, prior)
    prefix = "/w" + uuid.uuid4().hex[:8]
    cal = make_calibrator(ros_context, prefix, tmp_path, method="swaying_base",
                          prior_file=str(prior_path))
    player = make_player(ros_context, prefix, bag)
    ns = f"/calibrator_{prefix[1:]}"
    est = Collector(player, CalibrationEstimate, ns + "/estimate")
    diag = Collector(player, DiagnosticArray, prefix + "/diagnostics")
    with BagReader(bag) as r:
        n_imu = r.topics()["/imu/data"].message_count
    with Spinner(ros_context, cal, player):
        player.play()
        wait_for(lambda: cal.received["imu"] == n_imu, what="all IMU")
        cal.finish()
        wait_for(lambda: est.msgs and diag.msgs, what="estimate + diagnostics")
    assert cal.cal.method == "swaying_base" and est.msgs[-1].method == "swaying_base"
    live, rf = cal.cal.filter, ref.filter
    sl = live.model.slices["installation"]
    d = (live.theta[sl] - rf.theta[sl]) / rf.sigma()[rf.it][sl]
    assert np.all(np.abs(d) <= 0.1), d
    assert live.counters.updates >= ref.counters["updates"] - 2
    assert (tmp_path / "calibrator.npz").exists()
    keys = {kv.key: kv.value for kv in diag.msgs[-1].status[0].values}
    assert "filter.position_updates" in keys
    print(f"\nlive - replay installation: {np.round(d, 4)} sigma "
          f"({np.round(live.theta[sl] / ARCSEC, 3)} arcsec)")
    cal.destroy_node()
    player.destroy_node()


def test_garbage_input_is_counted_and_survived(ros_context, tmp_path):
    prefix = "/g" + uuid.uuid4().hex[:8]
    cal = make_calibrator(ros_context, prefix, tmp_path, t0_imu_samples=10,
                          silence_timeout_s=0.3, warn_throttle_s=0.0,
                          checkpoint_file="", output_file="")
    src = rclpy.create_node(f"garbage_{prefix[1:]}", context=ros_context)
    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    p_imu = src.create_publisher(Imu, prefix + "/imu/data", qos)
    p_st = src.create_publisher(StarCentroidArray, prefix + "/star_tracker/stars", qos)
    p_t = src.create_publisher(Temperature, prefix + "/star_tracker/temperature", qos)
    p_fix = src.create_publisher(NavSatFix, prefix + "/gnss/fix", qos)
    diag = Collector(src, DiagnosticArray, prefix + "/diagnostics")
    stamp0 = 1_795_348_800 * 10**9

    def imu(k, frame="imu_link", w=(0.0, 0.0, 0.0)):
        m = Imu()
        t = stamp0 + k * 10_000_000
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(t, 10**9)
        m.header.frame_id = frame
        m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z = w
        return m

    def stars(k, frame="star_tracker_optical_frame", n=5, value=1.0):
        m = StarCentroidArray()
        t = stamp0 + k * 10_000_000 + 1
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(t, 10**9)
        m.header.frame_id = frame
        m.stars = [StarCentroid(catalog_id=i + 1, right_ascension=value, declination=value,
                                u=value, v=value, magnitude=value, sigma=0.0)
                   for i in range(n)]
        return m

    with Spinner(ros_context, cal, src):
        wait_for(lambda: p_imu.get_subscription_count() > 0 and p_st.get_subscription_count()
                 > 0, what="discovery")
        for k in range(1, 40):
            p_imu.publish(imu(k))
        p_imu.publish(imu(41, frame="somewhere_else"))
        p_imu.publish(imu(42, w=(math.nan, 0.0, 0.0)))
        p_imu.publish(imu(5))  # late
        p_st.publish(stars(10, n=0))  # empty
        p_st.publish(stars(12, value=math.nan))  # NaN everywhere
        p_st.publish(stars(14, frame="camera"))  # wrong frame
        p_st.publish(stars(16, value=1e300))  # absurd but finite
        t = Temperature()
        t.temperature = math.nan
        p_t.publish(t)
        fix = NavSatFix()
        fix.latitude = math.nan
        p_fix.publish(fix)
        # bytes that are no StarCentroidArray (a truncated one, another type's): the
        # decoder refuses them, the node counts a rejected message and goes on
        good = serialize_message(stars(60))
        p_st.publish(good[:30])
        p_st.publish(serialize_message(t))
        for k in range(43, 80):
            p_imu.publish(imu(k))
        p_st.publish(good)  # and still decodes the next good frame
        wait_for(lambda: cal.received["imu"] == 79 and cal.received["stars"] == 7
                 and cal.received["head"] == 1 and cal.received["fix"] == 1,
                 what="garbage delivered")
        time.sleep(0.6)  # both inputs silent now
        wait_for(lambda: any(d.status[0].level == DiagnosticStatus.WARN and "silent" in
                             d.status[0].message for d in diag.msgs), what="silence warning")
    c = cal.cal.counters
    assert c.imu_wrong_frame == 1 and c.imu_invalid == 1 and c.imu_late == 1
    assert c.frames_wrong_frame == 1 and c.env_invalid == 1 and c.fixes_invalid == 1
    assert c.frames_received == 5  # 4 decodable garbage frames + the good one
    fc = cal.cal.filter_counters()
    assert fc["skipped_few_stars"] >= 2  # the empty and the all-NaN frame
    assert cal.callback_errors == 2  # the two undecodable payloads, and nothing else
    keys = {kv.key: kv.value for kv in diag.msgs[-1].status[0].values}
    assert keys["input.imu_wrong_frame"] == "1" and keys["input.frames_wrong_frame"] == "1"
    assert keys["input.fixes_invalid"] == "1" and keys["callback_errors"] == "2"
    assert np.isfinite(cal.cal.state()[0]).all()
    cal.destroy_node()
    src.destroy_node()


def test_services_and_resume(ros_context, excerpt, tmp_path):
    path, prior, ref, counts = excerpt
    prefix = "/s" + uuid.uuid4().hex[:8]
    cal = make_calibrator(ros_context, prefix, tmp_path)
    # feed the first half of the excerpt directly (the node's callbacks)
    events = bag_events(path)
    half = events[: len(events) // 2]
    for _, _, kind, p in half:
        with cal._lock:
            if kind == "imu":
                cal.cal.push_imu(p[0], p[1], frame_id=p[2])
            elif kind == "stars":
                cal.cal.push_stars(p)
    client_node = rclpy.create_node(f"client_{prefix[1:]}", context=ros_context)
    ns = f"/calibrator_{prefix[1:]}"
    with Spinner(ros_context, cal, client_node):
        results = {}
        for name in ("checkpoint", "save_calibration", "reset"):
            cli = client_node.create_client(Trigger, f"{ns}/{name}")
            assert cli.wait_for_service(timeout_sec=5.0)
            fut = cli.call_async(Trigger.Request())
            wait_for(fut.done, what=name)
            results[name] = fut.result()
    assert all(r.success for r in results.values()), results
    assert (tmp_path / "result.yaml").exists() and (tmp_path / "calibrator.npz").exists()
    assert cal.cal.filter is None  # reset
    cal.destroy_node()
    resumed = make_calibrator(ros_context, prefix, tmp_path)
    updates_half = resumed.cal.filter_counters()["updates"]
    assert updates_half > 0
    bad = make_calibrator(ros_context, "/b" + prefix[2:], tmp_path, effects=["radial_k3"])
    assert bad.cal.filter is None  # another model's checkpoint is refused, not fatal
    with pytest.raises(ValueError, match="method"):
        make_calibrator(ros_context, "/v" + prefix[2:], tmp_path, method="magic")
    with pytest.raises(ValueError, match="gate_probability"):
        make_calibrator(ros_context, "/w" + prefix[2:], tmp_path, gate_probability=2.0)
    for n in (resumed, bad, client_node):
        n.destroy_node()


def test_config_files_load_into_the_nodes(ros_context, tmp_path):
    root = Path(__file__).resolve().parents[1]
    cal = CalibratorNode("calibrator_cfg" + uuid.uuid4().hex[:6], context=ros_context,
                         use_global_arguments=False, cli_args=[
                             "--ros-args", "--params-file", str(root / "config/calibrator.yaml"),
                             "-p", f"prior_file:={PRIOR}"])
    assert cal.p["reorder_window_s"] == 0.05 and cal.p["qos_reliability"] == "reliable"
    assert cal.p["effects"] == [] and cal.p["prior_file"] == str(PRIOR)
    player = PlayerNode("player_cfg" + uuid.uuid4().hex[:6], context=ros_context,
                        use_global_arguments=False, cli_args=[
                            "--ros-args", "--params-file", str(root / "config/player.yaml"),
                            "-p", f"bag:={BAG}"])
    assert player.p["rate"] == 1.0 and player.p["topics"] == []
    assert player.p["match_topic"] == "/calibrator/inputs_matched"
    # the launch file is for apt machines (launch_ros): only check it compiles
    src = (root / "launch/calibrate_bag.launch.py").read_text()
    compile(src, "calibrate_bag.launch.py", "exec")
    cal.destroy_node()
    player.destroy_node()


def test_node_provenance_stays_with_the_node(ros_context, excerpt, tmp_path):
    """A node's record (command, prior, date) goes into its own result only: it was
    process-wide, so a result saved later in the same process carried the node's prior
    (seen in the suite: test_results' round trip read a node test's prior path)."""
    from stellar_cal_ros.io.calibration import save_calibration

    path, prior, ref, counts = excerpt
    cal = make_calibrator(ros_context, "/v" + uuid.uuid4().hex[:8], tmp_path)
    cal.destroy_node()
    save_calibration(ref.calibration, tmp_path / "other.yaml")
    assert "provenance" not in load_calibration(tmp_path / "other.yaml").extra


def test_star_bytes_read_as_the_star_message():
    """The calibrator's raw star subscription reads what rclpy's deserializer reads, >= 20x
    faster on a 5 000-star message (measured: 0.08 vs 30 ms); undecodable bytes are one
    ValueError (the node counts the message as rejected)."""
    from rclpy.serialization import deserialize_message, serialize_message

    from stellar_cal_ros.nodes.residual_cdr import (
        star_decoder_matches_rmw,
        star_frame_from_cdr,
        star_frame_from_message,
    )

    assert star_decoder_matches_rmw()
    rng = np.random.default_rng(3)
    data = serialize_message(_star_msg(rng, 1_795_000_000_123_456_789, n=5000))
    got = star_frame_from_cdr(data)
    t0 = time.thread_time()
    want = star_frame_from_message(deserialize_message(data, StarCentroidArray))
    t1 = time.thread_time()
    star_frame_from_cdr(data)
    t2 = time.thread_time()
    assert (got.stamp_ns, got.frame_id) == (want.stamp_ns, want.frame_id)
    for name in ("catalog_id", "right_ascension", "declination", "uv", "magnitude", "sigma"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    assert (t2 - t1) * 20 < (t1 - t0), (t2 - t1, t1 - t0)
    with pytest.raises(ValueError, match="undecodable StarCentroidArray"):
        star_frame_from_cdr(data[:100])


def test_residual_bytes_are_the_residual_message(excerpt):
    """The vectorized CDR of ~/residuals deserializes to what _residual_msg builds."""
    from rclpy.serialization import deserialize_message

    from stellar_cal_ros.methods.driver import Calibrator, DriverConfig, FrameOutcome
    from stellar_cal_ros.methods.psce import PsceConfig
    from stellar_cal_ros.nodes.residual_cdr import encoder_matches_rmw

    assert encoder_matches_rmw()
    path, prior, _, _ = excerpt
    cal = Calibrator(prior, "psce", None, PsceConfig(), DriverConfig(reorder_window_s=0.05))
    events = bag_events(path)
    outcomes = feed(cal, events[: len(events) // 3])
    outcomes.append(FrameOutcome(123_000_000_456, "star_tracker_optical_frame", "dropped_late"))
    assert any(o.status == "updated" for o in outcomes)

    class Shell:  # the two methods only read the outcome
        pass

    fields = ("catalog_id", "u", "v", "predicted_u", "predicted_v", "cov_uu", "cov_uv",
              "cov_vv", "magnitude", "gated")
    for o in outcomes:
        a = CalibratorNode._residual_msg(Shell(), o)
        b = deserialize_message(CalibratorNode._residual_bytes(Shell(), o), StarResidualArray)
        assert (a.header.stamp.sec, a.header.stamp.nanosec, a.header.frame_id, a.dof) == (
            b.header.stamp.sec, b.header.stamp.nanosec, b.header.frame_id, b.dof)
        assert a.nis == b.nis or (math.isnan(a.nis) and math.isnan(b.nis))
        ra = np.array([[float(getattr(r, k)) for k in fields] for r in a.residuals])
        rb = np.array([[float(getattr(r, k)) for k in fields] for r in b.residuals])
        if len(ra):
            ra[:, 8] = ra[:, 8].astype(np.float32)  # float32 on the wire
        np.testing.assert_array_equal(ra.reshape(-1, 10), rb.reshape(-1, 10))


# ---------------------------------------------------------------------------- live faults
def test_player_refuses_damaged_bags(tmp_path):
    """Missing, not MCAP, truncated, corrupt chunk: one line, exit 1, nothing else."""
    import subprocess
    import sys

    from stellar_cal_ros.sim.bag_damage import bad_chunk_crc, chunk_spans
    from stellar_cal_ros.sim.scenarios import get_scenario
    from stellar_cal_ros.sim.world import simulate, write_simulation

    good = write_simulation(simulate(get_scenario("psce_rotations"), duration=5.0, seed=1),
                            tmp_path / "good.mcap")["bag"]
    data = good.read_bytes()
    cases = {"missing": (tmp_path / "absent.mcap", r"absent.mcap: no such bag \(a \.mcap "),
             "text": (tmp_path / "text.mcap", r"is not an MCAP file"),
             "truncated": (tmp_path / "cut.mcap", r"truncated or not closed"),
             "crc": (tmp_path / "crc.mcap", r"playback stopped after 0 messages: .*"
                                            r"chunk CRC mismatch")}
    cases["text"][0].write_text("hello\n")
    cases["truncated"][0].write_bytes(data[: len(data) // 2])
    cases["crc"][0].write_bytes(bad_chunk_crc(data, chunk_spans(good)[0][0]))
    for name, (bag, cause) in cases.items():
        p = subprocess.run([sys.executable, "-m", "stellar_cal_ros.nodes.player", "--ros-args",
                            "-p", f"bag:={bag}", "-p", "rate:=1000.0", "-p",
                            "wait_for_subscribers_s:=0.0", "-r", "__node:=player_" + name],
                           env=node_env(), capture_output=True, text=True, timeout=60)
        lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
        assert p.returncode == 1, (name, p.returncode, p.stderr)
        assert "Traceback" not in p.stderr, (name, p.stderr)
        assert len(lines) == 1 and lines[0].startswith("player: error: "), (name, lines)
        assert re.search(cause, lines[0]), (name, lines[0])


def test_player_warns_and_counts_an_unmet_wait(ros_context):
    """Nobody listens and no handshake comes: the player waits wait_for_subscribers_s, then
    warns (the topics, why) and counts them in its stats before playing (it used to play
    silently)."""
    from types import SimpleNamespace

    prefix = "/u" + uuid.uuid4().hex[:8]
    player = make_player(ros_context, prefix, BAG, duration_s=0.2, ack_timeout_s=0.01,
                         progress_topic=prefix + "/data_clock",
                         match_topic=prefix + "/inputs_matched", wait_for_subscribers_s=0.3)
    warned = []
    logger = player.get_logger()
    player.get_logger = lambda: SimpleNamespace(warning=warned.append, info=logger.info)
    with Spinner(ros_context, player):
        stats = player.play()
    # 6 played topics without a subscriber, no report, no progress publisher
    assert stats.unmatched_topics == 8, player.unmatched()
    (text,) = [w for w in warned if "still unmatched" in w]
    assert f"{prefix}/imu/data (no subscriber)" in text
    assert f"{prefix}/inputs_matched (no report from the consumer)" in text
    assert stats.messages > 0
    player.destroy_node()


def test_truncated_checkpoint_starts_from_the_prior(ros_context, excerpt, tmp_path):
    path, prior, ref, counts = excerpt
    prefix = "/k" + uuid.uuid4().hex[:8]
    cal = make_calibrator(ros_context, prefix, tmp_path)
    for _, _, kind, p in bag_events(path)[:4000]:
        if kind == "imu":
            cal.cal.push_imu(p[0], p[1], frame_id=p[2])
        elif kind == "stars":
            cal.cal.push_stars(p)
    assert cal.cal.filter_counters()["updates"] > 0
    ck = Path(cal.save_checkpoint())
    cal.destroy_node()
    ck.write_bytes(ck.read_bytes()[: ck.stat().st_size // 2])
    fresh = make_calibrator(ros_context, prefix, tmp_path)  # BadZipFile before the fix
    assert fresh.cal.filter is None and fresh.cal.filter_counters()["updates"] == 0
    fresh.destroy_node()


def test_checkpoint_of_another_version_starts_from_the_prior(ros_context, tmp_path):
    """A checkpoint of an unknown schema version: one warning line, the run from the prior."""
    from stellar_cal_ros.io.checkpoint import write_checkpoint

    write_checkpoint(tmp_path / "calibrator.npz", {"x": np.zeros(2)},
                     {"schema": "stellar_cal_checkpoint", "version": 99})
    prefix = "/u" + uuid.uuid4().hex[:8]
    cal = make_calibrator(ros_context, prefix, tmp_path)
    assert cal.cal.filter is None and cal.cal.counters.imu_received == 0
    cal.destroy_node()



def test_a_frame_does_not_wait_behind_a_checkpoint_write(ros_context, excerpt, tmp_path,
                                                         monkeypatch):
    """The periodic checkpoint (a timer in the node's executor) hands the state to the
    writer's thread (H253: io.checkpoint.CheckpointWriter): a write that takes as long as a
    slow disk likes does not hold the frames.  The first fsync of the process (the first
    checkpoint's) is held until the test lets it go; meanwhile 20 s of the excerpt play
    through the topics (flow control: the player waits for the node's acknowledgements and
    counts 10 s without one) and every message is taken in, each frame's callback within a
    bound, before the write is let go.  A write in the executor's thread (submit writing in
    the caller's thread) fails this test: nothing is processed while the fsync is held."""
    import os

    from stellar_cal_ros.io import checkpoint as io_ck

    path, prior, ref, counts = excerpt
    real_fsync, in_write, release, calls = os.fsync, threading.Event(), threading.Event(), []
    let_go = []  # (the held fsync's end: perf_counter, whether the test let it go)

    def slow_fsync(fd):
        calls.append(threading.current_thread().name)
        if len(calls) == 1:  # the first checkpoint's data: a disk that takes its time
            in_write.set()
            let_go.append(release.wait(600))
            let_go.append(time.perf_counter())
        return real_fsync(fd)

    monkeypatch.setattr(io_ck.os, "fsync", slow_fsync)
    prefix = "/w" + uuid.uuid4().hex[:8]
    cal = make_calibrator(ros_context, prefix, tmp_path, checkpoint_period_s=0.2,
                          output_file="")
    player = make_player(ros_context, prefix, path, ack_timeout_s=10.0, duration_s=20.0)
    try:
        with Spinner(ros_context, cal, player):
            assert in_write.wait(30), "no periodic checkpoint"
            t0 = time.perf_counter()
            stats = player.play()
            wait_for(lambda: sum(cal.received.values()) == stats.messages, timeout=30,
                     what="every message played")
            t_all = time.perf_counter()
            updates = cal.cal.filter_counters()["updates"]
            latency = np.asarray(cal.latency_s)
            release.set()
            cal.finish()
    finally:
        release.set()
    print(f"\n{stats.messages} messages in {t_all - t0:.2f} s while the first checkpoint's "
          f"fsync was held; {updates} updates; frame callbacks: {latency.size}, max "
          f"{latency.max() * 1e3:.1f} ms, p99 {np.percentile(latency, 99) * 1e3:.1f} ms")
    assert calls[0] == "checkpoint-writer", calls
    assert let_go[0] and let_go[1] > t_all, let_go  # every message taken in while it was held
    assert stats.ack_timeouts == 0 and cal.received["stars"] == 40, cal.received
    assert updates >= 35 and latency.size >= 15 and latency.max() < 1.0, latency.max()
    assert io_ck.read_checkpoint(tmp_path / "calibrator.npz")[1]["filter"] is not None
    cal.destroy_node()
    player.destroy_node()


FLOOD_HZ = 400.0  # malformed star messages per second: 200 x the tracker's 2 Hz


def _flood_setup(ros_context, excerpt, tmp_path, prefix, rate_hz):
    path, prior, ref, counts = excerpt
    ns = f"/calibrator_{prefix[1:]}"
    cal = make_calibrator(ros_context, prefix, tmp_path, estimate_rate_hz=rate_hz,
                          diagnostics_rate_hz=5.0, checkpoint_file="", output_file="",
                          warn_throttle_s=1.0)
    src = rclpy.create_node(f"flood_{prefix[1:]}", context=ros_context)
    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    pub = src.create_publisher(StarCentroidArray, prefix + "/star_tracker/stars", qos)
    est = Collector(src, CalibrationEstimate, ns + "/estimate")
    diag = Collector(src, DiagnosticArray, prefix + "/diagnostics")
    # after the flood's publisher: the handshake waits for the node to match it too
    player = make_player(ros_context, prefix, path)
    return cal, player, src, pub, est, diag


def _star_msg(rng, t_ns, frame="star_tracker_optical_frame", n=20, value=None):
    m = StarCentroidArray()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(int(t_ns), 10**9)
    m.header.frame_id = frame
    vals = rng.uniform(-1e4, 1e4, (n, 5)) if value is None else np.full((n, 5), value)
    m.stars = [StarCentroid(catalog_id=int(i) + 1, right_ascension=float(a),
                            declination=float(b), u=float(c), v=float(d), magnitude=float(e),
                            sigma=0.05) for i, (a, b, c, d, e) in enumerate(vals)]
    return m


def _flood(cal, player, src, pub, est, messages, rate_hz, flood_hz, in_flight=200):
    """Play the bag while ``messages(k)`` are published at ``flood_hz``; returns
    (played stats, estimate rate during the playback, malformed messages sent).

    At most ``in_flight`` messages are sent and not yet taken in by the node: beyond the
    subscription's depth (KEEP_LAST) DDS drops the oldest, good frames among them, and no
    node can count what it never receives (measured in CI: 3 900 of 11 000 dropped when the
    machine's share gave the node ~270 messages/s).  So the flood runs at ``flood_hz`` or
    as fast as the node takes messages in, whichever is slower.
    """
    sent = [0]
    done = threading.Event()

    def run():
        t0 = time.perf_counter()
        k = 0
        while not done.is_set():
            # received['stars'] counts the player's frames too: in flight <= this + 120
            while sent[0] - cal.received["stars"] > in_flight and not done.is_set():
                time.sleep(0.001)
            for m in messages(k):
                pub.publish(m)
                sent[0] += 1
            k += 1
            delay = t0 + sent[0] / flood_hz - time.perf_counter()
            if delay > 0:
                time.sleep(delay)

    with Spinner(cal.context, cal, player, src):
        wait_for(lambda: pub.get_subscription_count() > 0, what="discovery")
        flooder = threading.Thread(target=run, daemon=True)
        flooder.start()
        time.sleep(0.5)
        n0, t0 = len(est.msgs), time.perf_counter()
        stats = player.play()
        time.sleep(1.0)
        n1, t1 = len(est.msgs), time.perf_counter()
        done.set()
        flooder.join(5)
        deadline = time.monotonic() + 20  # until the node has taken in what is in flight
        last = -1
        while time.monotonic() < deadline and cal.received["stars"] != last:
            last = cal.received["stars"]
            time.sleep(0.5)
        cal.finish()
        time.sleep(0.3)
    got = (n1 - n0) / (t1 - t0)
    print(f"\nflood: {sent[0]} malformed star messages in {t1 - t0:.1f} s "
          f"({sent[0] / (t1 - t0):.0f}/s); ~/estimate {got:.1f} Hz (expected {rate_hz}); "
          f"counters {cal.cal.counters}; filter {cal.cal.filter_counters()}")
    return stats, got, sent[0]


def test_flood_of_malformed_messages_does_not_stall_the_node(ros_context, excerpt, tmp_path):
    """While the bag plays, a publisher floods the star topic (200 x its rate) with NaN,
    wrong-frame, unstamped and absurdly large (5000 stars) messages: ~/estimate keeps its
    rate, every message is taken in and counted, no good frame is lost (the replay's
    calibration) and /diagnostics shows every counter.

    The garbage carries no stamp inside the run (garbage that does: the two tests below),
    and a flood that backs up the star queue delays good frames
    beyond the reorder window (dropped as late, counted) — measured with NaN frames stamped
    between the tracker's: 39–96 of 119 updates.
    """
    path, prior, ref, counts = excerpt
    prefix = "/f" + uuid.uuid4().hex[:8]
    rate_hz = 10.0
    cal, player, src, pub, est, diag = _flood_setup(ros_context, excerpt, tmp_path, prefix,
                                                    rate_hz)
    from rclpy.serialization import serialize_message

    rng = np.random.default_rng(5)
    # serialized once: building a 5 000-star message object per publish costs the test's
    # own process ~30 ms of GIL each (measured), which starved the nodes it shares it with
    big = serialize_message(_star_msg(rng, 10**9, n=5000))  # absurd size
    garbage = [serialize_message(m) for m in (
        _star_msg(rng, 0, value=math.nan), _star_msg(rng, 0, frame="camera"),
        _star_msg(rng, 0, n=3))]
    stamped = [serialize_message(_star_msg(rng, 2 * 10**9 + k, value=math.inf))
               for k in range(500)]

    def messages(k):
        out = [*garbage, stamped[k % len(stamped)]]
        return out + [big] if k % 25 == 0 else out

    stats, got, sent = _flood(cal, player, src, pub, est, messages, rate_hz, FLOOD_HZ)
    assert sent > 1000 and got > 0.8 * rate_hz, (sent, got)
    assert stats.ack_timeouts == 0
    c, fc = cal.cal.counters, cal.cal.filter_counters()
    assert c.frames_wrong_frame > 100 and c.frames_late > 100 and cal.callback_errors == 0
    assert cal.received["stars"] == counts["/star_tracker/stars"] + sent  # none lost
    assert fc["updates"] == ref.counters["updates"]
    assert_same(cal.cal.calibration(), ref.calibration)
    # /diagnostics shows every counter of the node, the estimator and the filter
    keys = {kv.key: kv.value for kv in diag.msgs[-1].status[0].values}
    from dataclasses import asdict

    want = ([f"input.{k}" for k in asdict(c)] + [f"filter.{k}" for k in fc]
            + [f"received.{k}" for k in INPUTS] + ["callback_errors", "backlog_updates"])
    assert not [k for k in want if k not in keys], [k for k in want if k not in keys]
    assert int(keys["input.frames_wrong_frame"]) > 100
    for n in (cal, player, src):
        n.destroy_node()


def _garbage_frame(stamp_ns: int, n: int = 20, value: float = math.nan):
    from stellar_cal_ros.io.bag import StarFrame

    return StarFrame(stamp_ns=int(stamp_ns), frame_id="star_tracker_optical_frame",
                     exposure_time=0.0, catalog_id=np.arange(1, n + 1, dtype=np.uint32),
                     right_ascension=np.full(n, value), declination=np.full(n, value),
                     uv=np.full((n, 2), value), magnitude=np.full(n, value),
                     sigma=np.full(n, 0.05))


def _stream_with(excerpt, garbage):
    """The excerpt through the live driver, ``garbage(stamp)`` frames pushed before each
    real frame; returns the driver."""
    from test_online import feed, make

    path, prior, ref, counts = excerpt
    cal = make(prior)
    for e in bag_events(path):
        if e[2] == "stars":
            for g in garbage(int(e[3].stamp_ns)):
                cal.push_stars(g)
        feed(cal, [e])
    cal.finish()
    return cal


def test_same_stamp_garbage_does_not_shadow_the_good_frame(excerpt):
    """A NaN frame carrying a good frame's stamp arrives first: the good one replaces it
    (before: it was dropped as a duplicate, first wins)."""
    path, prior, ref, counts = excerpt
    cal = _stream_with(excerpt, lambda t: [_garbage_frame(t)])
    assert cal.filter_counters()["updates"] == ref.counters["updates"]
    assert cal.counters.frames_replaced == counts["/star_tracker/stars"]


def test_future_stamped_frames_do_not_evict_good_ones(excerpt):
    """Frames stamped a day ahead are refused and counted (before: they filled the pending
    buffer, whose overflow evicted the good frames: 0 of 119 updates)."""
    path, prior, ref, counts = excerpt
    day = 86_400 * 10**9
    cal = _stream_with(excerpt, lambda t: [_garbage_frame(t + day + k, value=1.0)
                                           for k in range(3)])
    assert cal.filter_counters()["updates"] == ref.counters["updates"]
    assert cal.counters.frames_ahead == 3 * counts["/star_tracker/stars"]
    assert cal.counters.frames_overflow == 0


def _received(path) -> int:
    """Input messages a calibrator's checkpoint has counted (every kind the bag holds)."""
    from stellar_cal_ros.io.checkpoint import read_checkpoint

    c = read_checkpoint(path)[1]["driver"]["counters"]
    return c["imu_received"] + c["frames_received"] + c["env_received"] + c["fixes_received"]


def _wait_received(path, n: int, timeout: float = 60.0) -> int:
    """Poll a calibrator's periodic checkpoint until it counts ``n`` input messages (or the
    timeout); returns its last count (-1: no checkpoint yet)."""
    deadline = time.monotonic() + timeout
    got = -1
    while time.monotonic() < deadline and got < n:
        time.sleep(0.2)
        got = _received(path) if Path(path).exists() else -1
    return got


def test_kill_9_and_restart_resumes_from_the_checkpoint(ros_context, excerpt, tmp_path):
    """The calibrator process is SIGKILLed mid-bag; restarted, it resumes from its periodic
    checkpoint, the whole bag is played again (what it already has is dropped, counted)
    and the result is the uninterrupted replay's.

    Each process must have received every message played to it: a message lost on the way
    (the player publishing before the process's subscriptions have matched its publishers)
    is never in the checkpoint, and replayed later it is older than what the process has:
    dropped as late. The player waits for the process's ~/inputs_matched handshake (every
    played topic's publisher matched by the process's subscription; this covers the
    process's start-up), and after the first playback the test waits for the checkpoint to
    count every message played, then kills it (the cut points between checkpoints are
    test_online's test_resumed_driver_drops_what_it_has)."""
    import signal
    import subprocess
    import sys

    path, prior, ref, counts = excerpt
    prefix = "/r" + uuid.uuid4().hex[:8]
    name = f"calibrator_{prefix[1:]}"
    ck, out = tmp_path / "ck.npz", tmp_path / "out.yaml"
    # a checkpoint a second (the node's default is one a minute): the first process's last
    # one holds every message played at most ~1 s after the playback.  Each is 0.4-1.1 MB
    # (the filter's IMU tail; doc/interfaces.md §6) and takes 60-90 ms of wall time to write
    # (fsync): at the 0.2 s used before, a third to a half of the executor's time
    argv = [sys.executable, "-m", "stellar_cal_ros.nodes.calibrator", *remaps(prefix),
            "-r", f"__node:={name}", "-p", f"prior_file:={PRIOR}", "-p",
            f"checkpoint_file:={ck}", "-p", "checkpoint_period_s:=1.0", "-p",
            f"output_file:={out}", "-p", "reorder_window_s:=0.05"]

    def play(duration_s):
        # a restarted process may report no progress for over the default ack_timeout_s
        # (5 s) on a loaded machine; the player would then carry on, the node's queue
        # overflow and the result differ (load ~20); the handshake of a process starting at
        # load ~20 took > 20 s
        player = make_player(ros_context, prefix, path, duration_s=duration_s,
                             ack_timeout_s=60.0, wait_for_subscribers_s=120.0)
        with Spinner(ros_context, player):
            stats = player.play()
        player.destroy_node()
        assert stats.unmatched_topics == 0
        return stats

    first = subprocess.Popen(argv, env=node_env(), stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True)
    shm: list = []  # the killed process's shared-memory segments (ros_env): removed after
    try:
        played = play(EXCERPT_S / 2).messages
        n1 = _wait_received(ck, played)  # until the checkpoint holds every message played
        shm = own_shm_segments(first.pid)
        first.send_signal(signal.SIGKILL)
        first.wait(10)
    finally:
        if first.poll() is None:
            shm = own_shm_segments(first.pid)
            first.kill()
            first.wait(10)
        remove_shm_segments(shm)
    assert first.returncode == -signal.SIGKILL and ck.exists() and not out.exists()
    assert n1 == played, f"the first process received {n1} of {played} messages played"
    second = subprocess.Popen(argv, env=node_env(), stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True)
    try:
        stats = play(0.0)
        # the last messages may still be on their way when play() returns (a fixed 1 s wait
        # lost 2 of 6 364 beside 2 CPU hogs): stop the process once it has them
        _wait_received(ck, n1 + stats.messages)
        second.send_signal(signal.SIGINT)
        log_text = second.communicate(timeout=30)[0]
    finally:
        if second.poll() is None:
            shm = own_shm_segments(second.pid)
            second.kill()
            second.wait(10)
            remove_shm_segments(shm)
    assert "resumed from" in log_text, log_text
    assert stats.messages == sum(counts.values())
    # the checkpoint written at shutdown: the second process received the whole bag
    assert _received(ck) - n1 == stats.messages, log_text
    assert_same(load_calibration(out), ref.calibration)


# ---------------------------------------------------------------------- the node's verdict
def test_the_node_tells_a_wrong_model(ros_context, tmp_path):
    """Issue 25.2: frames stamped 3 ms early and no time_offset in the model.  The replay
    says MODEL MISMATCH; the node must say so on /diagnostics (WARN, a constant message),
    on /rosout, and in its result (the replay's consistency block, with provenance)."""
    from rcl_interfaces.msg import Log
    from sim_bags import simulated_bag

    from stellar_cal_ros.methods.results import consistency

    bag, prior_path, _ = simulated_bag("psce_rotations", 120.0, 7, {"time_offset": 0.003})
    prior = load_calibration(prior_path)
    ref = replay_psce(bag, prior, config=live_psce()).calibration.extra["consistency"]
    assert ref["verdict"] == "model mismatch"
    prefix = "/v" + uuid.uuid4().hex[:8]
    cal = make_calibrator(ros_context, prefix, tmp_path, prior_file=str(prior_path))
    logs = Collector(cal, Log, "/rosout")
    with Spinner(ros_context, cal):
        feed(cal.cal, bag_events(bag))
        cal.received.update(imu=1, stars=1)
        cal._rx_last_wall.update(imu=time.monotonic(), stars=time.monotonic())
        st = cal.diagnostics()
        wait_for(lambda: any("MODEL MISMATCH" in m.msg or "misses an effect" in m.msg
                             for m in logs.msgs if m.name.endswith(prefix[1:])),
                 what="the mismatch on /rosout")
        cal.finish()
    assert st.level == DiagnosticStatus.WARN and st.message.startswith("model mismatch")
    values = {kv.key: kv.value for kv in st.values}
    assert values["consistency.verdict"] == "model mismatch"
    live = load_calibration(tmp_path / "result.yaml").extra
    # the same statistics as the replay's: the second half, up to one block of the window
    assert live["consistency"]["nis_per_dof"] == pytest.approx(ref["nis_per_dof"], rel=0.03)
    assert live["consistency"]["whiteness_p"] < 1e-3 and ref["whiteness_p"] < 1e-3
    assert live["consistency"]["verdict"] == ref["verdict"]
    assert live["consistency"]["rms_px"] == pytest.approx(ref["rms_px"], rel=0.02)
    assert live["consistency"]["window_start"] == pytest.approx(ref["window_start"], abs=2.0)
    assert live["provenance"]["command"].split()[1:3] == ["--ros-args", "-p"], live
    assert live["provenance"]["prior"] == str(prior_path)
    # and a model that fits is not flagged
    ok = make_calibrator(ros_context, prefix + "ok", tmp_path / "ok")
    feed(ok.cal, bag_events(BAG))
    ok.received.update(imu=1, stars=1)
    ok._rx_last_wall.update(imu=time.monotonic(), stars=time.monotonic())
    st = ok.diagnostics()
    assert consistency(ok.cal.stats.current())["verdict"] == "consistent"
    assert st.level == DiagnosticStatus.OK and "mismatch" not in st.message
    for n in (cal, ok):
        n.destroy_node()


def test_diagnostics_text_is_constant_while_the_state_is(ros_context, tmp_path):
    prefix = "/s" + uuid.uuid4().hex[:8]
    cal = make_calibrator(ros_context, prefix, tmp_path, silence_timeout_s=0.1)
    cal.received.update(imu=1, stars=1)
    cal._rx_last_wall.update(imu=time.monotonic() - 6.0, stars=time.monotonic() - 6.0)
    first = cal.diagnostics()
    cal._rx_last_wall.update(imu=time.monotonic() - 7.0, stars=time.monotonic() - 7.0)
    second = cal.diagnostics()
    assert first.level == second.level == DiagnosticStatus.WARN
    assert first.message == second.message and "silent" in first.message
    assert {kv.key: kv.value for kv in second.values}["silent.imu_s"] == "7"
    cal.destroy_node()


def test_a_misspelled_parameter_stops_the_node(ros_context, tmp_path):
    with pytest.raises(ValueError, match="'outptu_file' \\(did you mean 'output_file'\\?\\)"):
        make_calibrator(ros_context, "/p" + uuid.uuid4().hex[:8], tmp_path,
                        outptu_file=str(tmp_path / "r.yaml"))
    with pytest.raises(ValueError, match="'bg' \\(did you mean 'bag'\\?\\)"):
        PlayerNode("player_p" + uuid.uuid4().hex[:6], context=ros_context,
                   use_global_arguments=False, parameter_overrides=[
                       Parameter("bg", value=str(BAG))])


def test_player_help_and_every_bag_format(tmp_path):
    """Issue 25.1/25.8: `player --help` prints its parameters (exit 0); a rosbag2 sqlite3
    directory and a ROS 1 bag play every message, as the MCAP does."""
    import subprocess
    import sys

    from rosbags.convert import convert

    p = subprocess.run([sys.executable, "-m", "stellar_cal_ros.nodes.player", "--help"],
                       env=node_env(), capture_output=True, text=True, timeout=60)
    assert p.returncode == 0 and "bag" in p.stdout and "rate" in p.stdout, p.stderr
    with BagReader(BAG) as r:
        total = sum(i.message_count for i in r.topics().values())
    sqlite = tmp_path / "sqlite"
    convert([BAG], sqlite, "sqlite3", 8, None, "file", None, None, [], [], [], [])
    ros1 = tmp_path / "run.bag"
    convert([BAG], ros1, "sqlite3", 8, None, "file", None, None, [], [], [], [])
    for bag in (BAG, sqlite, ros1):
        p = subprocess.run([sys.executable, "-m", "stellar_cal_ros.nodes.player", "--ros-args",
                            "-p", f"bag:={bag}", "-p", "rate:=0.0", "-p",
                            "wait_for_subscribers_s:=0.0", "-p", "ack_timeout_s:=0.01",
                            "-p", "publish_clock:=false",
                            "-r", "__node:=player_fmt" + uuid.uuid4().hex[:6]],
                           env=node_env(), capture_output=True, text=True, timeout=120)
        assert p.returncode == 0, (bag, p.stderr)
        assert f"played {total} messages" in p.stdout + p.stderr, (bag, p.stderr)


# ------------------------------------------------------------------------- TF out of the box
def test_tf_static_carries_the_calibrated_installation(ros_context, excerpt, tmp_path):
    """Issue 25.7: the set-up builds tf2_msgs where the wheels have none, so /tf_static
    carries imu_link -> star_tracker_optical_frame: a subscriber's transform is the result
    YAML's installation."""
    from rclpy.qos import DurabilityPolicy
    from tf2_msgs.msg import TFMessage

    path, prior, ref, counts = excerpt
    prefix = "/tf" + uuid.uuid4().hex[:8]
    cal = make_calibrator(ros_context, prefix, tmp_path, estimate_rate_hz=0.0)
    assert cal.pub_tf_static is not None
    listener = rclpy.create_node("tf_listener_" + prefix[1:], context=ros_context)
    got = []
    listener.create_subscription(TFMessage, "/tf_static", got.append, QoSProfile(
        depth=10, reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL))
    with Spinner(ros_context, cal, listener):
        feed(cal.cal, bag_events(path))
        cal.finish()  # writes result.yaml
        cal._publish_estimate()
        saved = load_calibration(tmp_path / "result.yaml")
        q_want = saved.installation.as_quat()

        def latest_matches():
            if not got:
                return False
            r = got[-1].transforms[0].transform.rotation
            return abs(abs(np.dot([r.x, r.y, r.z, r.w], q_want)) - 1.0) < 1e-12

        wait_for(latest_matches, what="/tf_static with the result's installation")
    tf = got[-1].transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ("imu_link", "star_tracker_optical_frame")
    t = tf.transform.translation
    assert (t.x, t.y, t.z) == (0.0, 0.0, 0.0)
    assert saved.installation.as_quat() == pytest.approx(ref.calibration.installation.as_quat(),
                                                         abs=1e-9)
    cal.destroy_node()
    listener.destroy_node()


def test_the_built_tf2_msgs_is_jazzys_on_the_wire():
    """The TFMessage type hash (RIHS01) of the installed tf2_msgs is ROS 2 Jazzy's (the one
    rosbags computes from its own Jazzy definitions): tf2 listeners, RViz and Foxglove on
    another machine read our /tf_static."""
    import json
    import sys

    from rosbags.typesys import Stores, get_typestore

    try:  # an apt install (sourced); the PyPI venv sets no AMENT_PREFIX_PATH
        from ament_index_python.packages import get_package_share_directory

        share = Path(get_package_share_directory("tf2_msgs"))
    except (OSError, LookupError):
        share = Path(sys.prefix) / "share" / "tf2_msgs"
    store = get_typestore(Stores.ROS2_JAZZY)
    for name in ("TFMessage", "TF2Error"):
        doc = json.loads((share / "msg" / f"{name}.json").read_text())
        ours = {h["type_name"]: h["hash_string"] for h in doc["type_hashes"]}
        assert ours[f"tf2_msgs/msg/{name}"] == store.hash_rihs01(f"tf2_msgs/msg/{name}")
