"""The live view (issue 25): ``replay --viz`` writes the run as Foxglove shows it, the
``calibrator`` node publishes the same messages live (and serves them over a Foxglove
WebSocket with ``foxglove_port``), and the shipped layout reads exactly those topics.

The MCAP is read back with the ``mcap`` library and ``mcap-ros2-support``, independently of
the Foxglove SDK that wrote it; the WebSocket with tornado's client (a dask dependency).
"""

from __future__ import annotations

import io
import json
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
from ros_env import node_env
from sim_bags import simulated_bag

from stellar_cal_ros.cli import main
from stellar_cal_ros.io.calibration import load_calibration
from stellar_cal_ros.io.residuals import read_residuals

ROOT = Path(__file__).resolve().parents[1]


def _bag():
    """A 120-s bag whose frames are stamped 3 ms early, and a prior without time_offset."""
    return simulated_bag("psce_rotations", 120.0, 7, {"time_offset": 0.003})[:2]


@pytest.fixture(scope="module")
def viz(tmp_path_factory):
    """``replay --viz`` of :func:`_bag`."""
    d = tmp_path_factory.mktemp("viz")
    bag, prior = _bag()
    assert main(["replay", str(bag), "--method", "psce", "--prior", str(prior), "-o",
                 str(d / "r.yaml"), "--viz", str(d / "v.mcap"), "-q"]) == 0
    return d


def _messages(path: Path):
    """Every message of the file, decoded from its ros2msg schema by mcap_ros2."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    out: dict[str, list] = {}
    with open(path, "rb") as fh:
        for _schema, channel, message, decoded in make_reader(
                fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            out.setdefault(channel.topic, []).append((message.log_time, decoded))
    return out


def _param(view, name: str):
    (p,) = [p for p in view.parameters if p.name == name]
    return p


def test_replay_viz_holds_the_run_over_time(viz):
    msgs = _messages(viz / "v.mcap")
    hist = read_residuals(viz / "r.history.csv")
    cal = load_calibration(viz / "r.yaml")
    # one view message per update, at the update's time, estimates in display units
    view = msgs["/calibrator/view"]
    assert len(view) == len(hist["t"])
    assert [t for t, _ in view] == [int(round(t * 1e9)) for t in hist["t"]]
    last = view[-1][1]
    assert last.header.frame_id == "imu_link" and last.updates == len(hist["t"])
    assert _param(last, "principal_point.cx").value == pytest.approx(
        hist["principal_point.cx"][-1])
    arcsec = np.degrees(1.0) * 3600.0
    ry = _param(last, "installation.ry")
    assert ry.unit == "arcsec" and ry.value == pytest.approx(hist["installation.ry"][-1] * arcsec)
    assert ry.hi - ry.lo == pytest.approx(2 * hist["sigma.installation.ry"][-1] * arcsec)
    # NIS: the update's, the mean of the last 20 against its band
    assert last.nis_frame == pytest.approx(hist["nis"][-1] / hist["dof"][-1])
    assert last.nis_moving == pytest.approx(hist["nis"][-20:].sum() / hist["dof"][-20:].sum())
    assert last.nis_band_lo < 1 < last.nis_band_hi
    # /diagnostics: what the node would say; at the end the run's own verdict
    diag = msgs["/diagnostics"]
    assert len(diag) >= 100  # 1 Hz of data time
    final = diag[-1][1].status[0]
    values = {kv.key: kv.value for kv in final.values}
    assert cal.extra["consistency"]["verdict"] == "model mismatch"
    assert values["consistency.verdict"] == "model mismatch" and final.level == 1
    assert float(values["consistency.nis_per_dof"]) == pytest.approx(
        cal.extra["consistency"]["nis_per_dof"], rel=0.03)
    assert last.nis_window == pytest.approx(float(values["consistency.nis_per_dof"]), rel=1e-3)
    assert last.verdict == "model mismatch"
    # the residual field: PNG images of the detector through the run
    from PIL import Image

    field = msgs["/calibrator/residual_field"]
    assert len(field) >= 4
    assert field[-1][1].format == "png"
    img = Image.open(io.BytesIO(bytes(field[-1][1].data)))
    assert img.size == (640, 680)
    pixels = np.asarray(img.convert("RGB")).reshape(-1, 3)
    red = np.sum((pixels[:, 0] > 200) & (pixels[:, 1] < 90))
    assert red > 50  # significant mean residuals drawn (the model misses the offset)


def test_the_shipped_layout_is_the_viz_layout_and_reads_its_topics(viz):
    from stellar_cal_ros.viz import TOPICS, layout_json

    text = (ROOT / "config" / "foxglove_layout.json").read_text()
    assert text == layout_json(), "regenerate config/foxglove_layout.json (viz.layout_json)"
    assert (viz / "v.layout.json").read_text() == text
    doc = json.loads(text)
    flat = json.dumps(doc)
    for topic in TOPICS.values():
        assert topic in flat, topic
    msgs = _messages(viz / "v.mcap")
    view = msgs["/calibrator/view"][-1][1]
    # every parameter and field the plots name exists in the messages
    import re

    paths = re.findall(r'"/calibrator/view\.([^"]+)"', flat.replace('\\"', "'"))
    assert len(paths) == 3 * 9 + 5  # 9 estimates with their band, 5 NIS series
    for path in paths:
        m = re.fullmatch(r"parameters\[:\]\{name=='([\w.]+)'\}\.(value|lo|hi)", path)
        node = getattr(_param(view, m[1]), m[2]) if m else getattr(view, path)
        assert isinstance(node, float), path


def test_view_schema_is_the_message_definition():
    """The ros2msg text the replay writes and the node's server advertises is msg_defs/'s."""
    from stellar_cal_ros.io.schemas import CALIBRATION_VIEW_SCHEMA

    def fields(text: str) -> list[str]:
        return [line.split("#")[0].strip() for line in text.splitlines()
                if line.split("#")[0].strip()]

    main, *deps = CALIBRATION_VIEW_SCHEMA.split("=" * 80)
    assert fields(main) == fields((ROOT / "msg_defs/msg/CalibrationView.msg").read_text())
    (elem,) = [d for d in deps if "MSG: stellar_cal_msgs/ParameterEstimate" in d]
    assert fields(elem)[1:] == fields(
        (ROOT / "msg_defs/msg/ParameterEstimate.msg").read_text())


# ---------------------------------------------------------------------------- the live node
def _node(ctx, tmp_path, **params):
    from rclpy.parameter import Parameter

    from stellar_cal_ros.nodes.calibrator import CalibratorNode

    name = "calibrator_" + uuid.uuid4().hex[:8]
    values = {"prior_file": str(_bag()[1]), "estimate_rate_hz": 1.0,
              "output_file": str(tmp_path / "result.yaml"), **params}
    return CalibratorNode(name, context=ctx, use_global_arguments=False,
                          cli_args=["--ros-args", "-r", f"/diagnostics:=/{name}/diagnostics"],
                          parameter_overrides=[Parameter(k, value=v) for k, v in values.items()])


def _play(node, events, every_window=True) -> None:
    """Push the events into the node's driver and publish as its callbacks do; tick the
    view whenever a residual-field window has ended (as its timer would at real time)."""
    import time

    for _, _, kind, p in events:
        cal = node.cal
        out = (cal.push_imu(p[0], p[1], frame_id=p[2]) if kind == "imu" else
               cal.push_stars(p) if kind == "stars" else cal.push_fix(*p) if kind == "fix"
               else cal.push_scalar(kind, *p))
        if out:
            node._handle(out, time.perf_counter())
        if every_window and node.view.field_end is not None:
            node.view.tick()


@pytest.mark.ros
def test_the_node_publishes_the_replays_view_and_residual_field(viz, ros_context, tmp_path):
    """The node's ~/residual_field images are byte for byte the ones replay --viz writes for
    the same windows of the same bag, and its ~/view carries the replay's numbers."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import CompressedImage
    from stellar_cal_msgs.msg import CalibrationView
    from test_online import bag_events

    node = _node(ros_context, tmp_path)
    got: dict[str, list] = {"field": [], "view": []}
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
    ns = node.get_fully_qualified_name()
    node.create_subscription(CompressedImage, ns + "/residual_field", got["field"].append, qos)
    node.create_subscription(CalibrationView, ns + "/view", got["view"].append, qos)
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(node)
    _play(node, bag_events(_bag()[0]))
    node.finish()
    node.view.tick()
    deadline = time.monotonic() + 10
    while (len(got["field"]), len(got["view"])) != (node.view.counts["fields"],
                                                     node.view.counts["views"]) \
            and time.monotonic() < deadline:
        ex.spin_once(timeout_sec=0.05)
    msgs = _messages(viz / "v.mcap")
    replay_fields = {m.header.stamp.sec * 10**9 + m.header.stamp.nanosec: bytes(m.data)
                     for _, m in msgs["/calibrator/residual_field"]}
    assert node.view.counts == {"views": 4, "fields": 3, "fields_skipped": 0}
    assert len(got["field"]) == 3
    for m in got["field"]:
        stamp = m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
        assert m.format == "png" and m.header.frame_id == "star_tracker_optical_frame"
        assert bytes(m.data) == replay_fields[stamp], stamp  # the same picture
    # the view: the replay's message for the same update, field by field
    replay_views = {m.header.stamp.sec * 10**9 + m.header.stamp.nanosec: m
                    for _, m in msgs["/calibrator/view"]}
    live = got["view"][-1]
    ref = replay_views[live.header.stamp.sec * 10**9 + live.header.stamp.nanosec]
    assert live.updates == ref.updates == node.cal.filter_counters()["updates"]
    assert [p.name for p in live.parameters] == [p.name for p in ref.parameters] == \
        node.cal.parameter_names()
    for a, b in zip(live.parameters, ref.parameters, strict=True):
        assert a.unit == b.unit
        np.testing.assert_allclose([a.value, a.sigma, a.lo, a.hi],
                                   [b.value, b.sigma, b.lo, b.hi], rtol=1e-9, atol=1e-12)
    for f in ("nis_frame", "nis_moving", "nis_band_lo", "nis_band_hi"):
        assert getattr(live, f) == pytest.approx(getattr(ref, f), rel=1e-9), f
    assert live.verdict == ref.verdict == "model mismatch"
    # what was published is what the node's driver says now, in display units
    theta, sigma = node.cal.state()
    cx = node.cal.parameter_names().index("principal_point.cx")
    assert live.parameters[cx].value == theta[cx] and live.parameters[cx].unit == "px"
    assert serialize_message(live)  # an ordinary ROS message
    ex.shutdown()
    node.destroy_node()


@pytest.mark.ros
def test_foxglove_port_serves_the_view_over_a_websocket(ros_context, tmp_path):
    """-p foxglove_port: a Foxglove client gets the channel list (the node's topics with
    their ROS schemas) and, once subscribed, the view the node publishes on ROS."""
    import asyncio
    import socket
    import struct

    from rclpy.serialization import deserialize_message
    from stellar_cal_msgs.msg import CalibrationView
    from test_online import bag_events
    from tornado.httpclient import HTTPRequest
    from tornado.websocket import websocket_connect

    with socket.socket() as s:  # a free port
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    node = _node(ros_context, tmp_path, foxglove_port=port, foxglove_address="127.0.0.1",
                 field_period_s=20.0)
    events = bag_events(_bag()[0])
    half = len(events) // 2
    _play(node, events[:half // 2])
    ns = node.get_fully_qualified_name()

    async def client():
        ws = await websocket_connect(HTTPRequest(f"ws://127.0.0.1:{port}", headers={
            "Sec-WebSocket-Protocol": "foxglove.sdk.v1"}), subprotocols=["foxglove.sdk.v1"])
        channels = {}
        while len(channels) < 3:
            msg = await asyncio.wait_for(ws.read_message(), 10)
            assert isinstance(msg, str), "text (JSON) control messages first"
            op = json.loads(msg)
            if op["op"] == "advertise":
                channels.update({c["topic"]: c for c in op["channels"]})
        subs = {k: c["id"] for k, c in channels.items()}
        ws.write_message(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": i, "channelId": cid} for i, cid in enumerate(subs.values())]}))
        await asyncio.sleep(0.3)  # the server takes the subscription
        _play(node, events[half // 2:half])  # more data: a new update, a new window
        node.view.tick()
        node._publish_diagnostics()
        got: dict[str, bytes] = {}
        topic_of = dict(enumerate(subs))
        while len(got) < 3:
            msg = await asyncio.wait_for(ws.read_message(), 10)
            if isinstance(msg, bytes) and msg[0] == 1:  # MessageData
                sub, _log_time = struct.unpack_from("<IQ", msg, 1)
                got[topic_of[sub]] = msg[13:]
        ws.close()
        return channels, got

    channels, got = asyncio.run(client())
    assert set(channels) == {ns + "/view", ns + "/residual_field", ns + "/diagnostics"}
    view_ch = channels[ns + "/view"]
    assert view_ch["encoding"] == "cdr" and view_ch["schemaEncoding"] == "ros2msg"
    assert view_ch["schemaName"] == "stellar_cal_msgs/msg/CalibrationView"
    view = deserialize_message(got[ns + "/view"], CalibrationView)
    theta, _ = node.cal.state()
    assert view.updates == node.cal.filter_counters()["updates"] > 50
    assert [p.name for p in view.parameters] == node.cal.parameter_names()
    f = node.cal.parameter_names().index("focal_length.f")
    assert view.parameters[f].value == theta[f]
    assert got[ns + "/residual_field"][4:].find(b"\x89PNG") > 0
    node.finish()  # stops the server
    node.destroy_node()


@pytest.mark.ros
def test_view_parameters_are_checked(ros_context, tmp_path):
    import socket

    for bad, match in (({"foxglove_port": 70000}, "foxglove_port"),
                       ({"foxglove_port": -1}, "foxglove_port"),
                       ({"foxglove_port": 8765, "view_rate_hz": 0.0},
                        "foxglove_port needs view_rate_hz > 0"),
                       ({"field_period_s": 0.0}, "field_period_s")):
        with pytest.raises(ValueError, match=match) as err:
            _node(ros_context, tmp_path, **bad)
        assert "\n" not in str(err.value)
    # a whole number for a float parameter is that float (rclpy alone refuses it), in every
    # node: -p field_period_s:=10, the player's documented -p rate:=0
    from rclpy.parameter import Parameter

    from stellar_cal_ros.nodes.player import PlayerNode

    node = _node(ros_context, tmp_path, field_period_s=10)
    assert node.p["field_period_s"] == 10.0 and node.view.period == 10.0
    node.destroy_node()
    player = PlayerNode("player_" + uuid.uuid4().hex[:8], context=ros_context,
                        use_global_arguments=False, parameter_overrides=[
                            Parameter("bag", value=str(_bag()[0])), Parameter("rate", value=0)])
    assert player.p["rate"] == 0.0 and isinstance(player.p["rate"], float)
    player.destroy_node()
    with socket.socket() as s:  # a port in use
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(ValueError, match=f"cannot serve Foxglove on 127.0.0.1:{port}"):
            _node(ros_context, tmp_path, foxglove_port=port, foxglove_address="127.0.0.1")
    # the executable: one line, exit 2 (a malformed -p too, which rcl itself refuses)
    import subprocess
    import sys

    env = node_env()
    for arg, said in (("foxglove_port:=70000", "out of range"),
                      ("foxglove_port:=", "parameter override rule")):
        proc = subprocess.run([sys.executable, "-m", "stellar_cal_ros.nodes.calibrator",
                               "--ros-args", "-p", f"prior_file:={_bag()[1]}", "-p", arg],
                              capture_output=True, text=True, timeout=120, env=env)
        ours = [line for line in proc.stderr.splitlines() if not line.startswith("[")]
        assert proc.returncode == 2 and len(ours) == 1, proc.stderr
        assert ours[0].startswith("calibrator: ") and said in ours[0], ours
