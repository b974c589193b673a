"""star_extractor node in process: a rendered sky image on /star_tracker/image comes out as
identified centroids on /star_tracker/stars (the true HIP numbers), tracking afterwards."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import pytest

from stellar_cal_ros.core.camera import CameraModel
from stellar_cal_ros.core.catalog import load_catalog, radec_to_unit
from stellar_cal_ros.core.rotation import so3_exp
from stellar_cal_ros.sim.render import SensorConfig, render_image

pytestmark = pytest.mark.ros

try:
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, Image
    from stellar_cal_msgs.msg import StarCentroidArray

    from stellar_cal_ros.io.image_msgs import image_pixels
    from stellar_cal_ros.nodes.star_extractor import StarExtractorNode

    _IMPORT_ERROR = None
except ImportError as exc:
    _IMPORT_ERROR = exc

W, H = 800, 600
F = W / 2 / np.tan(np.radians(11.0) / 2)
CAMERA = CameraModel(W, H, F, F, 401.0, 297.5, [-0.05, 0, 0, 0, 0])


def _frames(n=3):
    rng = np.random.default_rng(4)
    cat = load_catalog(7.0)
    u = radec_to_unit(*cat.message_radec())
    R = so3_exp(rng.normal(size=3))
    out = []
    for k in range(n):
        Rk = R @ so3_exp([0.0, 0.002 * k, 0.0])  # a slow pan: tracking after the first
        d = u @ Rk
        vis = d[:, 2] > 0.97
        uv = CAMERA.project(d[vis])
        ok = CAMERA.in_image(uv, margin=-3)
        r = render_image(uv[ok], cat.magnitude[vis][ok], W, H, SensorConfig(), rng)
        out.append((r, cat.hip[vis][ok]))
    return out


def _image_msg(img: np.ndarray, stamp_s: int) -> Image:
    m = Image()
    m.header.stamp.sec = stamp_s
    m.height, m.width = img.shape
    m.encoding = "mono16"
    m.is_bigendian = 0
    m.step = 2 * img.shape[1]
    m.data = img.astype("<u2").tobytes()
    return m


def test_image_message_decoding():
    if _IMPORT_ERROR is not None:
        pytest.fail(f"rclpy / stellar_cal_msgs not importable ({_IMPORT_ERROR})")
    img = np.arange(12, dtype=np.uint16).reshape(3, 4) * 1000
    m = _image_msg(img, 1)
    assert np.array_equal(image_pixels(m), img)  # the check the bag data path makes too
    m.encoding = "bgr8"
    with pytest.raises(ValueError, match="not mono8 or mono16"):
        image_pixels(m)


def test_images_in_identified_centroids_out(ros_context):
    if _IMPORT_ERROR is not None:
        pytest.fail(f"rclpy / stellar_cal_msgs not importable ({_IMPORT_ERROR})")
    ctx = ros_context
    prefix = f"/sx{os.getpid()}"
    node = StarExtractorNode(
        "star_extractor_test", context=ctx, use_global_arguments=False,
        parameter_overrides=[
            Parameter("image_topic", value=prefix + "/image"),
            Parameter("camera_info_topic", value=prefix + "/camera_info"),
            Parameter("stars_topic", value=prefix + "/stars"),
            Parameter("report_period_s", value=0.0)])
    io = rclpy.create_node("sx_io", context=ctx)
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    got: list = []
    io.create_subscription(StarCentroidArray, prefix + "/stars", got.append, qos)
    pub = io.create_publisher(Image, prefix + "/image", qos)
    info_pub = io.create_publisher(CameraInfo, prefix + "/camera_info", qos)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    ex.add_node(io)
    info = CameraInfo()
    info.width, info.height = W, H
    info.k = [CAMERA.fx, 0.0, CAMERA.cx, 0.0, CAMERA.fy, CAMERA.cy, 0.0, 0.0, 1.0]
    info.d = list(CAMERA.distortion[:5])
    info.distortion_model = "plumb_bob"
    frames = _frames()
    deadline = time.monotonic() + 10
    while pub.get_subscription_count() < 1 and time.monotonic() < deadline:
        ex.spin_once(timeout_sec=0.05)
    info_pub.publish(info)
    for _ in range(20):
        ex.spin_once(timeout_sec=0.02)
    for k, (r, _) in enumerate(frames):
        pub.publish(_image_msg(r.image, 1_800_000_000 + k))
        deadline = time.monotonic() + 20
        while len(got) <= k and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
    assert len(got) == len(frames)
    for msg, (r, hip) in zip(got, frames, strict=True):
        uv = np.array([[s.u, s.v] for s in msg.stars])
        ids = np.array([s.catalog_id for s in msg.stars])
        assert len(ids) >= 10 and np.all(ids > 0)
        d = np.linalg.norm(uv[:, None] - r.uv[None], axis=2)
        j = d.argmin(axis=1)
        assert np.all(d[np.arange(len(j)), j] < 0.5)
        assert np.array_equal(ids, hip[j])  # the true stars
        assert all(s.sigma > 0 for s in msg.stars)
    assert node.identifier.counters.lost_in_space == 1
    assert node.identifier.counters.tracking == len(frames) - 1


def test_help_names_the_parameters():
    out = subprocess.run([sys.executable, "-m", "stellar_cal_ros.nodes.star_extractor", "--help"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.startswith("usage: star_extractor")
    assert "fov_deg" in out.stdout
