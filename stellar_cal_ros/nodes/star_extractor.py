"""``star_extractor`` node: star images in, identified centroids out.

``ros2 run stellar_cal_ros star_extractor``.  Subscribed: ``/star_tracker/image``
(sensor_msgs/Image, mono8 / mono16 / 8UC1 / 16UC1,
stamp = mid-exposure) and, optionally, ``/star_tracker/camera_info`` (sensor_msgs/CameraInfo).
Published: ``/star_tracker/stars`` (stellar_cal_msgs/StarCentroidArray), one per image, with
the image's stamp; each centroid carries its σ from its signal-to-noise
(:mod:`stellar_cal_ros.sky.extract`).

Identification (:mod:`stellar_cal_ros.sky.identify`) through the camera of ``prior_file``
(a calibration YAML), else of the latest CameraInfo, else a pinhole of ``fov_deg``:
lost-in-space on the first image, then tracking with the last identified attitude as the
hint (the node has no IMU; the calibrator, which has, re-identifies a frame sent
unidentified), lost-in-space again when tracking fails.  Only identified stars are
published; an image that cannot be identified goes out with all its centroids unidentified
(``catalog_id`` 0, RA/Dec NaN), for the calibrator to identify with its IMU's attitude.
Counters are logged every ``report_period_s``.
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any

import numpy as np
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image
from stellar_cal_msgs.msg import StarCentroid, StarCentroidArray

from stellar_cal_ros.core.camera import CameraModel
from stellar_cal_ros.errors import StellarCalError
from stellar_cal_ros.io.image_msgs import camera_from_info, image_pixels
from stellar_cal_ros.nodes.runner import check_parameter_names, declare
from stellar_cal_ros.sky.extract import ExtractConfig, centroid_frame
from stellar_cal_ros.sky.identify import Identifier, IdentifyConfig

PARAMETERS: dict[str, tuple[Any, str]] = {
    "prior_file": ("", "calibration YAML whose camera the centroids come from (optional)"),
    "fov_deg": (0.0, "horizontal field of view, deg, when neither prior nor CameraInfo"),
    "image_topic": ("/star_tracker/image", "sensor_msgs/Image input"),
    "camera_info_topic": ("/star_tracker/camera_info", "sensor_msgs/CameraInfo input"),
    "stars_topic": ("/star_tracker/stars", "StarCentroidArray output"),
    "frame_id": ("star_tracker_optical_frame", "header.frame_id of the output"),
    "sigma_threshold": (5.0, "detection threshold, background sigma"),
    "max_stars": (200, "brightest stars kept per image"),
    "hint_uncertainty_deg": (1.0, "tracking: how far the last attitude may be off, deg"),
    "report_period_s": (30.0, "log the counters this often (wall time), s; 0: never"),
}

def usage() -> str:
    """``--help`` text."""
    lines = ["usage: star_extractor [--ros-args -p NAME:=VALUE ...]", "", __doc__.strip(), "",
             "parameters:"]
    lines += [f"  {k} (default {v[0]!r}): {v[1]}" for k, v in PARAMETERS.items()]
    return "\n".join(lines)


class StarExtractorNode(Node):
    """The node (see the module docstring)."""

    def __init__(self, name: str = "star_extractor", **kw) -> None:
        super().__init__(name, **kw)
        from rcl_interfaces.msg import ParameterDescriptor

        for key, (default, text) in PARAMETERS.items():
            declare(self, key, default, ParameterDescriptor(description=text))
        check_parameter_names(self)  # a typo is an error, as in the other nodes
        p = {k: self.get_parameter(k).value for k in PARAMETERS}
        self.p = p
        self.extract = ExtractConfig(sigma_threshold=float(p["sigma_threshold"]),
                                     max_stars=int(p["max_stars"]))
        self.camera: CameraModel | None = None
        if p["prior_file"]:
            from stellar_cal_ros.io.calibration import load_calibration

            self.camera = load_calibration(p["prior_file"]).camera
        self.identifier: Identifier | None = None
        self.counters = {"images": 0, "bad_images": 0, "identified": 0, "failed": 0,
                         "stars": 0, "stars_identified": 0}
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.pub = self.create_publisher(StarCentroidArray, p["stars_topic"], qos)
        self.create_subscription(Image, p["image_topic"], self._on_image, qos)
        self.create_subscription(CameraInfo, p["camera_info_topic"], self._on_info, qos)
        self._warned: set[str] = set()
        period = float(p["report_period_s"])
        if period > 0:
            self.create_timer(period, self._report)

    def _warn_once(self, key: str, text: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            self.get_logger().warning(text)

    def _on_info(self, msg: CameraInfo) -> None:
        if self.p["prior_file"] or not msg.k[0]:
            return
        try:
            self.camera = camera_from_info(msg)
        except StellarCalError as exc:
            self._warn_once("info", f"camera_info not usable: {exc}")

    def _identifier(self, width: int, height: int) -> Identifier | None:
        cam = self.camera
        if cam is None:
            fov = float(self.p["fov_deg"])
            if fov <= 0:
                self._warn_once("camera", "no camera (prior_file, camera_info or fov_deg): "
                                "centroids are published unidentified")
                return None
            cam = CameraModel.pinhole(width, height,
                                      (width / 2) / math.tan(math.radians(fov) / 2))
        old = self.identifier
        if old is None or (old.camera.width, old.camera.height) != (cam.width, cam.height):
            self.identifier = Identifier(cam, IdentifyConfig(
                hint_uncertainty_deg=float(self.p["hint_uncertainty_deg"])))
        else:
            self.identifier.set_camera(cam)
        return self.identifier

    def process(self, msg: Image) -> StarCentroidArray | None:
        """Centroids and identification of one image (None: the image is not usable)."""
        c = self.counters
        c["images"] += 1
        try:
            pixels = image_pixels(msg)
        except ValueError as exc:
            c["bad_images"] += 1
            self._warn_once("encoding", f"{exc}: images skipped (counted as bad_images)")
            return None
        stamp_ns = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
        # the same two steps as a bag's images in replay/batch (methods/frames.py)
        frame = centroid_frame(pixels, stamp_ns, self.p["frame_id"], 0.0, self.extract)
        ident_obj = self._identifier(pixels.shape[1], pixels.shape[0])
        n = len(frame)
        keep = np.ones(n, bool)
        if ident_obj is not None and n:
            identified, res = ident_obj.identify_frame(frame, ident_obj.last_R_i_st)
            if res.status != "failed":
                c["identified"] += 1
                keep = res.identified
                frame = identified
            else:
                c["failed"] += 1
                ident_obj.last_R_i_st = None
        c["stars"] += n
        c["stars_identified"] += int(np.count_nonzero(frame.catalog_id[keep]))
        out = StarCentroidArray()
        out.header.stamp = msg.header.stamp
        out.header.frame_id = self.p["frame_id"]
        out.exposure_time = 0.0
        for i in np.flatnonzero(keep):
            s = StarCentroid()
            s.catalog_id = int(frame.catalog_id[i])
            s.right_ascension = float(frame.right_ascension[i])
            s.declination = float(frame.declination[i])
            s.u = float(frame.uv[i, 0])
            s.v = float(frame.uv[i, 1])
            s.magnitude = float(frame.magnitude[i])
            s.sigma = float(frame.sigma[i])
            out.stars.append(s)
        return out

    def _on_image(self, msg: Image) -> None:
        t = time.process_time()
        try:
            out = self.process(msg)
        except StellarCalError as exc:
            self._warn_once("error", f"image not processed: {exc}")
            return
        if out is not None:
            self.pub.publish(out)
        self.get_logger().debug(f"image processed in {1e3 * (time.process_time() - t):.1f} ms")

    def _report(self) -> None:
        self.get_logger().info("star_extractor: " + ", ".join(
            f"{k}={v}" for k, v in self.counters.items()))


def main(argv: list[str] | None = None) -> int:
    """Run the node until shutdown."""
    from stellar_cal_ros.nodes.runner import run_node

    return run_node("star_extractor", StarExtractorNode, usage, argv,
                    finish=lambda node: node._report())

if __name__ == "__main__":
    sys.exit(main())
