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

DOMAIN_ID = 1 + (os.getpid() + 53) % 100


def test_help_prints_usage_and_exits_0():
    out = subprocess.run([sys.executable, "-m", "stellar_cal_ros.nodes.calibrator", "--help"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("usage: calibrator") and "prior_file" in out.stdout
    assert "/tf_static" in out.stdout


def test_camera_info_and_installation_are_latched(tmp_path, monkeypatch):
    if _IMPORT_ERROR is not None:
        pytest.fail(f"rclpy / stellar_cal_msgs not importable ({_IMPORT_ERROR})")
    prior = simulate(get_scenario("psce_rotations"), duration=5.0, seed=1).prior
    save_calibration(prior, tmp_path / "prior.yaml")
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=DOMAIN_ID)
    try:
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
    finally:
        ctx.try_shutdown()
