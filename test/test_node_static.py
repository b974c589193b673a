"""calibrator node outputs that need no data: latched camera_info, /tf_static, --help."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import pytest

from stellar_cal_ros.io.calibration import save_calibration
from stellar_cal_ros.sim.scenarios import get_scenario
from stellar_cal_ros.sim.world import simulate

pytestmark = pytest.mark.ros

try:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo

    from stellar_cal_ros.nodes import calibrator as node_module

    _IMPORT_ERROR = None
except ImportError as exc:
    _IMPORT_ERROR = exc


def test_help_prints_usage_and_exits_0():
    out = subprocess.run([sys.executable, "-m", "stellar_cal_ros.nodes.calibrator", "--help"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("usage: calibrator") and "prior_file" in out.stdout
    assert "/tf_static" in out.stdout


def test_camera_info_and_installation_are_latched(tmp_path, ros_context):
    if _IMPORT_ERROR is not None:
        pytest.fail(f"rclpy / stellar_cal_msgs not importable ({_IMPORT_ERROR})")
    prior = simulate(get_scenario("psce_rotations"), duration=5.0, seed=1).prior
    save_calibration(prior, tmp_path / "prior.yaml")
    ctx = ros_context
    ns = f"/static_{os.getpid()}"
    node = node_module.CalibratorNode(
        f"calibrator_{os.getpid()}", context=ctx, use_global_arguments=False,
        cli_args=["--ros-args", "-r", f"/tf_static:={ns}/tf_static"],
        parameter_overrides=[Parameter("prior_file", value=str(tmp_path / "prior.yaml"))])
    listener = rclpy.create_node(f"listener_{os.getpid()}", context=ctx)
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    got: dict[str, list] = {"info": [], "tf": []}
    # subscribed only after the node published: a latched topic still delivers
    listener.create_subscription(CameraInfo, f"/calibrator_{os.getpid()}/camera_info",
                                 got["info"].append, latched)
    if node_module.TFMessage is not None:
        listener.create_subscription(node_module.TFMessage, f"{ns}/tf_static",
                                     got["tf"].append, latched)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    ex.add_node(listener)
    deadline = time.monotonic() + 20
    want_tf = node_module.TFMessage is not None
    while time.monotonic() < deadline and not (got["info"] and (got["tf"] or not want_tf)):
        ex.spin_once(timeout_sec=0.05)
    assert got["info"], "no latched camera_info"
    info = got["info"][0]
    cam = prior.camera
    assert list(info.k) == [cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1]
    assert info.header.frame_id == prior.frames["star_tracker"]
    if want_tf:
        (tf,) = got["tf"][0].transforms
        assert tf.header.frame_id == "imu_link"
        assert tf.child_frame_id == "star_tracker_optical_frame"
        r = tf.transform.rotation
        np.testing.assert_allclose([r.x, r.y, r.z, r.w], prior.installation.as_quat())
    else:  # no tf2_msgs here (PyPI wheels): said once, no publisher
        assert node.pub_tf_static is None
    ex.shutdown()
    node.destroy_node()
    listener.destroy_node()



def test_launch_file_declares_and_passes_effects(monkeypatch):
    """launch/calibrate_bag.launch.py with launch / launch_ros stubbed (apt-only packages).

    The stubs record what the file declares and builds; ``LaunchConfiguration.perform``
    reads the launch arguments given below.
    """
    import importlib.util
    import types
    from pathlib import Path

    def record(kind):
        class Action:
            def __init__(self, *args, **kw):
                self.kind, self.args, self.kw = kind, args, kw
        return Action

    class LaunchConfiguration:
        def __init__(self, name):
            self.name = name

        def perform(self, context):
            return context[self.name]

    mods = {
        "launch": types.SimpleNamespace(LaunchDescription=list),
        "launch.actions": types.SimpleNamespace(
            DeclareLaunchArgument=record("declare"), OpaqueFunction=record("opaque"),
            RegisterEventHandler=record("handler"), Shutdown=record("shutdown")),
        "launch.event_handlers": types.SimpleNamespace(OnProcessExit=record("on_exit")),
        "launch.substitutions": types.SimpleNamespace(LaunchConfiguration=LaunchConfiguration,
                                                      PathJoinSubstitution=list),
        "launch_ros": types.SimpleNamespace(),
        "launch_ros.actions": types.SimpleNamespace(Node=record("node")),
        "launch_ros.substitutions": types.SimpleNamespace(FindPackageShare=str),
    }
    for name, mod in mods.items():
        monkeypatch.setitem(sys.modules, name, mod)
    path = Path(__file__).resolve().parents[1] / "launch" / "calibrate_bag.launch.py"
    spec = importlib.util.spec_from_file_location("calibrate_bag_launch", path)
    launch_file = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(launch_file)
    entities = launch_file.generate_launch_description()
    declared = {a.args[0] for a in entities if a.kind == "declare"}
    assert {"bag", "prior", "output", "effects", "checkpoint", "rate"} <= declared
    (opaque,) = [a for a in entities if a.kind == "opaque"]
    for text, want in (("radial_k3, time_offset", ["radial_k3", "time_offset"]),
                       ("[radial_k3]", ["radial_k3"]), ("", None)):
        (node,) = opaque.kw["function"]({"effects": text}, *opaque.kw["args"])
        assert node.kw["executable"] == "calibrator"
        (params,) = [p for p in node.kw["parameters"] if isinstance(p, dict)]
        assert params.get("effects") == want, text
