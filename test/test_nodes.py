"""calibrator + player nodes, in process: bag → topics → calibrator equals the offline replay.

Both nodes share one Context (private domain id, localhost discovery, unique topic names
through remapping) and one executor spinning in a thread; the player publishes from the
test's thread with flow control (``rate: 0``).
"""

from __future__ import annotations

import math
import os
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
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
    from sensor_msgs.msg import CameraInfo, Imu, Temperature
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
DOMAIN_ID = 1 + (os.getpid() + 37) % 100
BAG, PRIOR, _ = psce_bag(EXCERPT_S)


@pytest.fixture
def ros_context(monkeypatch):
    if _IMPORT_ERROR is not None:
        pytest.fail(f"rclpy / stellar_cal_msgs not importable ({_IMPORT_ERROR})")
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=DOMAIN_ID)
    try:
        yield ctx
    finally:
        ctx.try_shutdown()


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
    player = PlayerNode(f"player_{prefix[1:]}", context=ros_context, cli_args=remaps(prefix),
                        use_global_arguments=False, parameter_overrides=[
                            Parameter("bag", value=str(path)), Parameter("rate", value=0.0),
                            Parameter("progress_topic",
                                      value=f"/calibrator_{prefix[1:]}/data_clock"),
                            Parameter("wait_for_subscribers_s", value=5.0)])
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
    assert stats.ack_timeouts == 0
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
    print(f"\n{stats.messages} messages in {wall:.2f} s ({stats.messages / wall:.0f} msg/s)")
    cal.destroy_node()
    player.destroy_node()


def test_swaying_base_live_equals_its_replay(ros_context, tmp_path):
    """method:=swaying_base (a moored ship): the site from /gnss/fix, gravity in the inertial
    frame; the bag played through topics gives the replay's installation to 0.1 σ."""
    from stellar_cal_ros.core.units import ARCSEC
    from stellar_cal_ros.methods.swaying import replay_swaying

    bag, prior_path, _ = swaying_bag(150.0)
    prior = load_calibration(prior_path)
    ref = replay_swaying(bag, prior)
    prefix = "/w" + uuid.uuid4().hex[:8]
    cal = make_calibrator(ros_context, prefix, tmp_path, method="swaying_base",
                          prior_file=str(prior_path))
    player = PlayerNode(f"player_{prefix[1:]}", context=ros_context, cli_args=remaps(prefix),
                        use_global_arguments=False, parameter_overrides=[
                            Parameter("bag", value=str(bag)), Parameter("rate", value=0.0),
                            Parameter("progress_topic",
                                      value=f"/calibrator_{prefix[1:]}/data_clock"),
                            Parameter("wait_for_subscribers_s", value=5.0)])
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
        for k in range(43, 80):
            p_imu.publish(imu(k))
        wait_for(lambda: cal.received["imu"] == 79 and cal.received["stars"] == 4
                 and cal.received["head"] == 1, what="garbage delivered")
        time.sleep(0.6)  # both inputs silent now
        wait_for(lambda: any(d.status[0].level == DiagnosticStatus.WARN and "silent" in
                             d.status[0].message for d in diag.msgs), what="silence warning")
    c = cal.cal.counters
    assert c.imu_wrong_frame == 1 and c.imu_invalid == 1 and c.imu_late == 1
    assert c.frames_wrong_frame == 1 and c.env_invalid == 1
    fc = cal.cal.filter_counters()
    assert fc["skipped_few_stars"] >= 2  # the empty and the all-NaN frame
    assert cal.callback_errors == 0
    keys = {kv.key: kv.value for kv in diag.msgs[-1].status[0].values}
    assert keys["input.imu_wrong_frame"] == "1" and keys["input.frames_wrong_frame"] == "1"
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
    # the launch file is for apt machines (launch_ros): only check it compiles
    src = (root / "launch/calibrate_bag.launch.py").read_text()
    compile(src, "calibrate_bag.launch.py", "exec")
    cal.destroy_node()
    player.destroy_node()


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
