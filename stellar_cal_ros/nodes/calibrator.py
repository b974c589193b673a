"""``calibrator`` node: live calibration (``ros2 run stellar_cal_ros calibrator``).

``method:=psce`` (Tan et al. 2018, default), ``method:=swaying_base`` (Zhang et al. 2018:
a ship at its mooring; needs ``/gnss/fix`` for the site and gravity in the inertial frame), or
any other registered filter method (:mod:`~stellar_cal_ros.methods.registry`).
A thin rclpy shell around :class:`~stellar_cal_ros.methods.driver.Calibrator`, the same
driver ``stellar-cal replay`` uses: callbacks convert messages to numbers and push them; the
driver decides when a star frame can be processed (reorder window, IMU coverage) and the
node publishes what came out.

Subscribed (contract topics, doc/interfaces.md §2; remap with ``--ros-args -r``):
``/imu/data`` (sensor_msgs/Imu), ``/star_tracker/stars`` (stellar_cal_msgs/StarCentroidArray),
``/gnss/fix`` (sensor_msgs/NavSatFix), ``/star_tracker/temperature``,
``/environment/temperature`` (sensor_msgs/Temperature), ``/environment/pressure``
(sensor_msgs/FluidPressure).

Published (node-relative names, i.e. ``/calibrator/...`` by default):

* ``~/estimate`` (stellar_cal_msgs/CalibrationEstimate) at ``estimate_rate_hz``;
* ``~/camera_info`` (sensor_msgs/CameraInfo, latched: transient local): current K, D,
  distortion model;
* ``~/installation`` (geometry_msgs/TransformStamped): ``imu_link → star_tracker_optical_frame``;
* ``/tf_static`` (tf2_msgs/TFMessage, transient local, as a static transform broadcaster):
  the same transform, re-sent when it changes (needs the tf2_msgs package: every ROS 2
  install has it, ``scripts/setup.sh`` builds it for the PyPI wheels; without it the node
  warns once and publishes ``~/installation`` only);
* ``~/residuals`` (stellar_cal_msgs/StarResidualArray): one per star frame received — empty
  with ``nis`` NaN when the frame was skipped or dropped (so it doubles as the
  acknowledgement the ``player`` uses for flow control);
* ``/diagnostics`` (diagnostic_msgs/DiagnosticArray) at ``diagnostics_rate_hz``;
* ``~/data_clock`` (rosgraph_msgs/Clock): the newest IMU stamp consumed, every
  ``progress_period_s`` of IMU time (flow control of the ``player``; monitoring);
* ``~/inputs_matched`` (diagnostic_msgs/DiagnosticStatus, latched): per input topic
  (``values``: resolved topic name → count) how many publishers its subscription has
  matched, and for ``~/data_clock`` how many subscribers its publisher has matched; sent at
  start and whenever a count changes (checked every
  :data:`MATCH_PERIOD_S` of steady time); the ``player``'s ``match_topic`` handshake waits
  for it so that no message goes out before this node can receive it;
* ``~/view`` (stellar_cal_msgs/CalibrationView) and ``~/residual_field``
  (sensor_msgs/CompressedImage): the live view (:mod:`~stellar_cal_ros.nodes.live_view`,
  the layout ``config/foxglove_layout.json``); ``foxglove_port`` also serves it over a
  Foxglove WebSocket.

Services (std_srvs/Trigger): ``~/save_calibration`` (write ``output_file`` now),
``~/checkpoint`` (write ``checkpoint_file`` now), ``~/reset`` (restart from the prior).

Parameters: see :data:`PARAMETERS` (also ``config/calibrator.yaml`` and doc/ros_nodes.md).
"""

from __future__ import annotations

import gc
import math
import sys
import threading
import time
from collections import deque
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import TransformStamped
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rclpy.exceptions import (
    ParameterUninitializedException,
)
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, FluidPressure, Imu, NavSatFix, Temperature
from std_srvs.srv import Trigger
from stellar_cal_msgs.msg import (
    CalibrationEstimate,
    StarCentroidArray,
    StarResidual,
    StarResidualArray,
)

from stellar_cal_ros.effects import registry
from stellar_cal_ros.errors import CheckpointError
from stellar_cal_ros.io.calibration import load_calibration, prior_warnings, save_calibration
from stellar_cal_ros.io.checkpoint import CheckpointWriter
from stellar_cal_ros.methods import registry as methods
from stellar_cal_ros.methods.checkpoint import checkpoint_contents, load_checkpoint
from stellar_cal_ros.methods.driver import Calibrator, DriverConfig, FrameOutcome
from stellar_cal_ros.methods.results import NullSink, consistency, mismatch_text
from stellar_cal_ros.nodes import live_view
from stellar_cal_ros.nodes.health import (
    RosoutBridge,
    node_provenance,
    verdict_status,
    verdict_values,
)
from stellar_cal_ros.nodes.residual_cdr import (
    encode_residual_array,
    encoder_matches_rmw,
    star_decoder_matches_rmw,
    star_frame_from_cdr,
    star_frame_from_message,
)
from stellar_cal_ros.nodes.runner import check_parameter_names, declare

try:  # /tf_static: tf2_msgs comes with every ROS 2 install; on the PyPI wheels (which have
    # none) scripts/setup.sh builds it from vendor/tf2_msgs
    from tf2_msgs.msg import TFMessage
except ImportError:  # pragma: no cover - depends on the installation
    TFMessage = None

#: name: (default, description, range (lo, hi) or choices or None)
PARAMETERS: dict[str, tuple[Any, str, Any]] = {
    "prior_file": ("", "calibration YAML the filter starts from (required)", None),
    "method": ("psce", "estimation method: a registered filter method", None),
    "effects": (Parameter.Type.STRING_ARRAY,
                "effect ids estimated on top of the method's baseline (doc/interfaces.md)", None),
    "centroid_sigma_px": (0.0, "centroid 1-sigma used when a star's sigma is 0, px (0: the "
                          "method's default, 0.05 psce, 0.058 swaying_base)", (0.0, 100.0)),
    "gyro_arw_deg_sqrth": (0.0, "gyro angle random walk, deg/sqrt(h) (0: the method's "
                           "default, 0.001 psce, 5e-5 swaying_base)", (0.0, 100.0)),
    "gate_probability": (0.9999, "per-star chi2 (2 dof) acceptance probability",
                         (0.5, 0.999999999)),
    "reorder_window_s": (0.05, "data-time window within which messages are put back in "
                         "order (adds this much latency)", (0.0, 10.0)),
    "environment_wait_s": (2.0, "max data time a frame waits for temperatures/pressure an "
                           "effect needs", (0.0, 60.0)),
    "t0_imu_samples": (1000, "IMU samples whose median interval fixes the time origin "
                       "(as the replay)", (2, 100000)),
    "qos_depth": (1000, "subscription queue depth (KEEP_LAST)", (1, 100000)),
    "qos_reliability": ("reliable", "subscription reliability", ("reliable", "best_effort")),
    "estimate_rate_hz": (1.0, "rate of ~/estimate, ~/camera_info, ~/installation (0: after "
                         "every update)", (0.0, 1000.0)),
    "diagnostics_rate_hz": (1.0, "rate of /diagnostics", (0.01, 100.0)),
    "progress_period_s": (0.1, "IMU time between ~/data_clock messages, s (0: off)",
                          (0.0, 1e6)),
    "publish_residuals": (True, "publish ~/residuals per star frame", None),
    "checkpoint_file": ("", "filter checkpoint (.npz); '' disables checkpoints", None),
    "checkpoint_period_s": (60.0, "periodic checkpoint, s (0: only on service/shutdown)",
                            (0.0, 1e6)),
    "resume": (True, "resume from checkpoint_file at start if it exists", None),
    "output_file": ("", "calibration YAML written on ~/save_calibration and at shutdown",
                    None),
    "imu_frame_id": ("", "expected IMU header.frame_id ('' = the prior's frames.imu)", None),
    "star_frame_id": ("", "expected star header.frame_id ('' = the prior's "
                      "frames.star_tracker)", None),
    "silence_timeout_s": (5.0, "an input silent for longer is reported (IMU, stars)",
                          (0.1, 1e6)),
    "warn_throttle_s": (10.0, "min interval between warnings of one kind, s", (0.0, 1e6)),
    "converge_window": (20, "updates over which convergence is judged", (1, 100000)),
    "converge_sigma_ratio": (0.98, "converged: every sigma(now)/sigma(window ago) above this",
                             (0.0, 1.0)),
    "converge_nis_ratio": (2.0, "converged: mean NIS/dof over the window below this",
                           (0.0, 1e6)),
    **live_view.PARAMETERS,
}

INPUTS = {  # key: (default topic, type)
    "imu": ("/imu/data", Imu),
    "stars": ("/star_tracker/stars", StarCentroidArray),
    "fix": ("/gnss/fix", NavSatFix),
    "head": ("/star_tracker/temperature", Temperature),
    "air": ("/environment/temperature", Temperature),
    "pressure": ("/environment/pressure", FluidPressure),
}

#: period of the timer that runs the judgements the frames' updates leave due (the gyro
#: check's: about every 10th frame over the first 200, then every ~50 s of data), s
CHECKS_PERIOD_S = 0.2

#: period (steady time, also under use_sim_time) of the check of the input subscriptions'
#: matched publishers (``~/inputs_matched``), s
MATCH_PERIOD_S = 0.05

#: counters whose growth is warned about (throttled)
_WARN_COUNTERS = ("imu_invalid", "imu_late", "imu_duplicate", "imu_wrong_frame", "frames_late",
                  "frames_duplicate", "frames_overflow", "frames_wrong_frame", "frames_no_site",
                  "env_invalid", "env_stale", "fixes_invalid", "callback_errors",
                  "skipped_no_imu", "skipped_few_stars", "skipped_out_of_order", "imu_gaps",
                  "update_failed", "covariance_repairs", "reinitializations")


def live_configs(p: dict[str, Any]) -> tuple[Any, DriverConfig]:
    """The filter's and the driver's configuration of a live node from its parameters ``p``.

    Live, a gyro that disagrees with the stars flags the result as degraded (saved in its
    ``data_quality`` block, ERROR on ``/diagnostics``) rather than raising: a replay refuses
    such data, a node cannot refuse the data still to come, and an exception in its timer
    was only counted as a callback error while the calibration went on unflagged.
    """
    cfg = methods.get(p["method"]).config_cls(gate_probability=p["gate_probability"],
                                              unit_check_raises=False)
    if p["centroid_sigma_px"] > 0:
        cfg.centroid_sigma_px = p["centroid_sigma_px"]
    if p["gyro_arw_deg_sqrth"] > 0:
        cfg.gyro_arw_deg_sqrth = p["gyro_arw_deg_sqrth"]
    drv = DriverConfig(
        reorder_window_s=p["reorder_window_s"], environment_wait_s=p["environment_wait_s"],
        t0_imu_samples=p["t0_imu_samples"], converge_window=p["converge_window"],
        converge_sigma_ratio=p["converge_sigma_ratio"],
        converge_nis_ratio=p["converge_nis_ratio"], live_window=True, defer_checks=True)
    return cfg, drv


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _time_msg(ns: int):
    return rclpy.time.Time(nanoseconds=int(ns)).to_msg()


def _value(node: Node, name: str) -> Any:
    """A declared parameter's value; None for a typed one left unset (e.g. an empty list)."""
    try:
        return node.get_parameter(name).value
    except ParameterUninitializedException:
        return None


class CalibratorNode(Node):
    """The ``calibrator`` node (see the module docstring)."""

    def __init__(self, node_name: str = "calibrator", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self._lock = threading.RLock()
        self._declare_parameters()
        check_parameter_names(self)  # a typo (outptu_file) is an error, not ignored
        p = self._read_parameters()  # raises ValueError on invalid values
        self.p = p
        # checkpoints are written in a thread: the executor goes on with the frames
        self._checkpoints = CheckpointWriter(p["checkpoint_file"]) \
            if p["checkpoint_file"] else None
        # first: a Foxglove port in use stops the node before it does anything
        self.view = live_view.LiveView(self, p) if p["view_rate_hz"] > 0 else None
        self._bridge = RosoutBridge(self.get_logger())
        self._bridge.install()  # the library's warnings (model mismatch ...) go to /rosout
        prior = load_calibration(p["prior_file"])
        for w in prior_warnings(prior, p["prior_file"], {
                e: c.parameter_names for e, c in registry.EFFECTS.items()}):
            self.get_logger().warning(w)
        self._provenance = node_provenance(self.get_fully_qualified_name(), p,
                                           {k: v[0] for k, v in PARAMETERS.items()})
        frames = dict(prior.frames)
        if p["imu_frame_id"]:
            frames["imu"] = p["imu_frame_id"]
        if p["star_frame_id"]:
            frames["star_tracker"] = p["star_frame_id"]
        self.frame_ids = frames
        self.filter_config, self.driver_config = live_configs(p)
        # the residuals are published, not kept: a node runs for days (bounded memory)
        self.cal = Calibrator(prior, p["method"], p["effects"], self.filter_config,
                              self.driver_config, frames, residuals=NullSink(),
                              history=NullSink())
        self.callback_errors = 0
        self.backlog_updates = 0
        self.latency_s: deque[float] = deque(maxlen=2000)  # frame processing, wall s
        self.latency_cpu_s: deque[float] = deque(maxlen=2000)  # the same, thread CPU s
        self.received = dict.fromkeys(INPUTS, 0)
        self._rx_last_wall: dict[str, float | None] = dict.fromkeys(INPUTS)
        self._rate_snapshot = (time.monotonic(), dict(self.received))
        self._warned: dict[str, tuple[float, int]] = {}
        self._updates_published = -1
        self._finished = False
        self._maybe_resume()

        rel = ReliabilityPolicy.RELIABLE if p["qos_reliability"] == "reliable" \
            else ReliabilityPolicy.BEST_EFFORT
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=p["qos_depth"], reliability=rel)
        handlers = {"imu": self._on_imu, "stars": self._on_stars, "fix": self._on_fix,
                    "head": self._scalar_handler("head"), "air": self._scalar_handler("air"),
                    "pressure": self._scalar_handler("pressure")}
        # stars arrive as bytes read by numpy (residual_cdr.star_frame_from_cdr) unless this
        # RMW's wire format differs: rclpy's per-star objects cost ~30 ms for 5 000 stars
        self._raw_stars = star_decoder_matches_rmw()
        if not self._raw_stars:
            self.get_logger().warning("star CDR decoder does not match this RMW: reading "
                                      "StarCentroidArray as message objects (slower)")
        self._input_subs = [self.create_subscription(typ, topic, handlers[key], qos,
                                                     raw=key == "stars" and self._raw_stars)
                            for key, (topic, typ) in INPUTS.items()]
        out_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                             reliability=ReliabilityPolicy.RELIABLE)
        self.pub_estimate = self.create_publisher(CalibrationEstimate, "~/estimate", out_qos)
        latched = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.pub_camera_info = self.create_publisher(CameraInfo, "~/camera_info", latched)
        self.pub_tf_static = None if TFMessage is None else self.create_publisher(
            TFMessage, "/tf_static", latched)
        self._tf_sent: tuple[float, ...] | None = None
        if TFMessage is None:
            self.get_logger().warning("tf2_msgs is not installed (run scripts/setup.sh, "
                                      "which builds it): the installation goes to "
                                      "~/installation only, not to /tf_static")
        self.pub_installation = self.create_publisher(TransformStamped, "~/installation",
                                                      out_qos)
        self.pub_residuals = self.create_publisher(StarResidualArray, "~/residuals", out_qos)
        self.pub_diagnostics = self.create_publisher(DiagnosticArray, "/diagnostics", out_qos)
        self.pub_progress = self.create_publisher(Clock, "~/data_clock", out_qos)
        self.pub_inputs_matched = self.create_publisher(DiagnosticStatus, "~/inputs_matched",
                                                        latched)
        self._inputs_matched: dict[str, int] | None = None
        self._publish_inputs_matched()
        self.create_timer(MATCH_PERIOD_S, self._publish_inputs_matched,
                          clock=RosClock(clock_type=ClockType.STEADY_TIME))
        self._progress_ns = int(p["progress_period_s"] * 1e9)
        self._next_progress_ns = -1
        self._progress_due = None  # Clock to publish once the IMU callback's frames are out
        # ~/residuals serialized straight from the arrays (residual_cdr) unless this RMW's
        # wire format differs; then as StarResidual objects
        self._raw_residuals = encoder_matches_rmw()
        if not self._raw_residuals:
            self.get_logger().warning("residual CDR encoder does not match this RMW: "
                                      "publishing ~/residuals as message objects (slower)")
        self.create_service(Trigger, "~/save_calibration", self._srv_save)
        self.create_service(Trigger, "~/checkpoint", self._srv_checkpoint)
        self.create_service(Trigger, "~/reset", self._srv_reset)
        if p["estimate_rate_hz"] > 0:
            self.create_timer(1.0 / p["estimate_rate_hz"], self._publish_estimate)
        self.create_timer(1.0 / p["diagnostics_rate_hz"], self._publish_diagnostics)
        # the gyro-against-stars judgement runs here, between frames, not in their updates
        self.create_timer(CHECKS_PERIOD_S, self._run_checks)
        if p["checkpoint_file"] and p["checkpoint_period_s"] > 0:
            self.create_timer(p["checkpoint_period_s"], self._periodic_checkpoint)
        if self.view is not None:
            self.view.attach(self.cal, frames, (prior.camera.width, prior.camera.height),
                             self.pub_diagnostics.topic_name)
        self._publish_estimate()  # the prior's camera_info and installation, latched
        self.get_logger().info(
            f"calibrator ready: method={p['method']} effects={p['effects'] or '[]'} "
            f"({len(self.cal.parameter_names())} parameters), prior {p['prior_file']}")
        if not p["output_file"]:
            self.get_logger().warning(
                "output_file is not set: the calibration is not written at shutdown (set "
                "-p output_file:=RESULT.yaml, or call ~/save_calibration)")
        # Start-up objects (modules, messages, the model) are long-lived: keep them out of
        # the cyclic collector so that full collections in a callback stay short.
        gc.collect()
        gc.freeze()

    # ------------------------------------------------------------------ parameters
    def _declare_parameters(self) -> None:
        for name, (default, text, limits) in PARAMETERS.items():
            desc = ParameterDescriptor(description=text, read_only=True)
            if isinstance(limits, tuple) and len(limits) == 2 and all(
                    isinstance(x, (int, float)) for x in limits) and not isinstance(
                    default, str):
                if isinstance(default, bool):
                    pass
                elif isinstance(default, int):
                    desc.integer_range = [IntegerRange(from_value=int(limits[0]),
                                                       to_value=int(limits[1]), step=1)]
                else:
                    desc.floating_point_range = [FloatingPointRange(
                        from_value=float(limits[0]), to_value=float(limits[1]), step=0.0)]
            elif isinstance(limits, tuple):
                desc.additional_constraints = "one of: " + ", ".join(limits)
            elif name == "method":
                desc.additional_constraints = "one of: " + ", ".join(methods.names("filter"))
            declare(self, name, default, desc)  # (-p rate:=1 for a float; one-line errors)

    def _read_parameters(self) -> dict[str, Any]:
        p = {name: _value(self, name) for name in PARAMETERS}
        p["effects"] = [e.strip() for e in (p["effects"] or []) if e and e.strip()]
        errors = []
        for name, (_, _, limits) in PARAMETERS.items():
            v = p[name]
            if isinstance(limits, tuple) and isinstance(limits[0], str) and v not in limits:
                errors.append(f"{name}={v!r} is not one of {limits}")
            elif isinstance(limits, tuple) and not isinstance(v, (str, bool)) and (
                    not math.isfinite(v) or not limits[0] <= v <= limits[1]):
                errors.append(f"{name}={v!r} outside [{limits[0]}, {limits[1]}]")
        if p["method"] not in methods.names("filter"):
            errors.append(f"method={p['method']!r} is not one of "
                          f"{tuple(methods.names('filter'))}")
        errors += live_view.check_parameters(p)
        if not p["prior_file"]:
            errors.append("prior_file is required")
        elif not Path(p["prior_file"]).is_file():
            errors.append(f"prior_file {p['prior_file']!r} does not exist")
        known = set(registry.available()) if hasattr(registry, "available") else None
        for e in p["effects"]:
            if known is not None and e not in known:
                errors.append(f"unknown effect {e!r} (known: {', '.join(sorted(known))})")
        if errors:
            raise ValueError("invalid parameters: " + "; ".join(errors))
        return p

    # ------------------------------------------------------------------ checkpoints
    def _maybe_resume(self) -> None:
        ck = self.p["checkpoint_file"]
        if not (ck and self.p["resume"] and Path(ck).is_file()):
            return
        try:
            load_checkpoint(self.cal, ck)
        except CheckpointError as exc:
            self.get_logger().warning(f"cannot resume: {exc}; starting from the prior")
            self.cal.reset()
            return
        self.get_logger().info(
            f"resumed from {ck}: {self.cal.filter_counters()['updates']} updates so far")

    def save_checkpoint(self, wait: bool = True) -> str:
        """Checkpoint the state now; returns the file's path.

        The state is copied here (under the lock, < 1 ms) and written by the writer's
        thread (serialised, fsynced, renamed over the file: tens of ms).  ``wait``: return
        once it is written (and raise if the write failed); otherwise at once (the periodic
        checkpoint: a newer state replaces one not yet written).
        """
        if self._checkpoints is None:
            raise ValueError("checkpoint_file is not set")
        with self._lock:
            contents = checkpoint_contents(self.cal)
        self._checkpoints.submit(*contents)
        if wait:
            self._checkpoints.flush()
        return self.p["checkpoint_file"]

    def save_calibration(self) -> str:
        """Write the current calibration to ``output_file``; returns its path."""
        out = self.p["output_file"]
        if not out:
            raise ValueError("output_file is not set")
        with self._lock:
            cal = self.cal.calibration()
            cov = self.cal.named_covariance()
        save_calibration(cal, out, covariance=cov, provenance=self._provenance)
        return out

    def _periodic_checkpoint(self) -> None:
        failed = self._checkpoints.take_error()  # the last write's (in the writer's thread)
        if failed is not None:
            self._warn("checkpoint_failed", f"periodic checkpoint failed: {failed}")
        try:
            self.save_checkpoint(wait=False)
        except Exception as exc:  # noqa: BLE001 - a full disk must not stop the filter
            self._warn("checkpoint_failed", f"periodic checkpoint failed: {exc}")

    def finish(self) -> None:
        """End of input (shutdown): checkpoint, process what is held, write the result."""
        with self._lock:
            if self._finished:
                return
            self._finished = True
            if self._checkpoints is not None:
                try:  # before finishing, so a restart keeps the held messages; written
                    # (waited for) while the held messages are processed
                    self._checkpoints.take_error()  # a periodic write's: superseded
                    self.save_checkpoint(wait=False)
                except Exception as exc:  # noqa: BLE001
                    self.get_logger().error(f"final checkpoint failed: {exc}")
            self._handle(self.cal.finish(), time.perf_counter())
            if self.p["output_file"]:
                try:
                    path = self.save_calibration()
                    self.get_logger().info(f"calibration written to {path}")
                except Exception as exc:  # noqa: BLE001
                    self.get_logger().error(f"writing the calibration failed: {exc}")
            else:
                self.get_logger().warning("output_file is not set: the calibration was not "
                                          "written")
            if self._checkpoints is not None:
                try:
                    self._checkpoints.close()  # the last write done before the node goes
                except Exception as exc:  # noqa: BLE001
                    self.get_logger().error(f"final checkpoint failed: {exc}")
            if self.view is not None:
                self.view.close()
            self._bridge.remove()

    def destroy_node(self) -> None:
        """Wait for a checkpoint still being written (its thread ends), then destroy."""
        writer = getattr(self, "_checkpoints", None)  # None: the constructor failed first
        if writer is not None:
            try:
                writer.close()
            except Exception as exc:  # noqa: BLE001 - said, the node still goes
                self.get_logger().error(f"checkpoint failed: {exc}")
        super().destroy_node()

    # ------------------------------------------------------------------ services
    def _srv_save(self, request, response):
        try:
            response.message = f"written {self.save_calibration()}"
            response.success = True
        except Exception as exc:  # noqa: BLE001
            response.success, response.message = False, str(exc)
        return response

    def _srv_checkpoint(self, request, response):
        try:
            response.message = f"written {self.save_checkpoint()}"
            response.success = True
        except Exception as exc:  # noqa: BLE001
            response.success, response.message = False, str(exc)
        return response

    def _srv_reset(self, request, response):
        with self._lock:
            self.cal.reset()
            self._finished = False
            self._updates_published = -1
            if self.view is not None:
                self.view.reset()
        response.success, response.message = True, "filter reset to the prior"
        self.get_logger().warning("filter reset to the prior (service call)")
        return response

    # ------------------------------------------------------------------ inputs
    def _guard(self, key: str, fn, msg) -> None:
        t_in, c_in = time.perf_counter(), time.thread_time()
        self.received[key] += 1
        self._rx_last_wall[key] = time.monotonic()
        try:
            with self._lock:
                out = fn(msg)
                if out:
                    self._handle(out, t_in, c_in)
        except Exception as exc:  # noqa: BLE001 - garbage input must not kill the node
            self.callback_errors += 1
            self._warn("callback_errors", f"{key} message rejected: "
                       f"{type(exc).__name__}: {exc}")

    def _run_checks(self) -> None:
        """The checks the frames' updates left due (Calibrator.run_checks), between frames."""
        try:
            with self._lock:
                self.cal.run_checks()
        except Exception as exc:  # noqa: BLE001 - as a frame's callback would have counted it
            self.callback_errors += 1
            self._warn("callback_errors", f"gyro check: {type(exc).__name__}: {exc}")

    def _on_imu(self, msg: Imu) -> None:
        self._guard("imu", self._push_imu, msg)
        c = self._progress_due
        if c is not None:  # after the residuals of the frames this sample released
            self._progress_due = None
            self.pub_progress.publish(c)

    def _push_imu(self, msg: Imu) -> list[FrameOutcome]:
        w, f = msg.angular_velocity, msg.linear_acceleration
        stamp = _stamp_ns(msg.header)
        out = self.cal.push_imu(stamp, (w.x, w.y, w.z), (f.x, f.y, f.z), msg.header.frame_id)
        if self._progress_ns and stamp >= self._next_progress_ns:
            self._next_progress_ns = stamp + self._progress_ns
            c = Clock()
            c.clock = msg.header.stamp
            self._progress_due = c
        return out

    def _on_stars(self, msg: StarCentroidArray) -> None:
        self._guard("stars", self._push_stars, msg)

    def _push_stars(self, msg: StarCentroidArray | bytes) -> list[FrameOutcome]:
        frame = (star_frame_from_cdr(msg) if isinstance(msg, bytes)
                 else star_frame_from_message(msg))
        return self.cal.push_stars(frame)

    def _on_fix(self, msg: NavSatFix) -> None:
        self._guard("fix", lambda m: self.cal.push_fix(
            _stamp_ns(m.header), m.latitude, m.longitude, m.altitude, int(m.status.status)), msg)

    def _scalar_handler(self, key: str):
        field = "fluid_pressure" if key == "pressure" else "temperature"

        def cb(msg) -> None:
            self._guard(key, lambda m: self.cal.push_scalar(
                key, _stamp_ns(m.header), getattr(m, field)), msg)

        return cb

    # ------------------------------------------------------------------ outputs
    def _handle(self, outcomes: list[FrameOutcome], t_in: float,
                c_in: float | None = None) -> None:
        """Publish what the frames of one callback gave.

        Latency (callback entry → residuals published) is recorded for callbacks that
        updated exactly one frame — the steady state; a backlog processed at once (start-up
        before the time origin is known, an IMU outage ending) is counted separately.
        """
        n_updated = 0
        publish, view = self.p["publish_residuals"], self.view
        for o in outcomes:
            if publish:
                self.pub_residuals.publish(self._residual_bytes(o) if self._raw_residuals
                                           else self._residual_msg(o))
            if view is not None:
                view.add(o)
            n_updated += o.status == "updated"
        if n_updated == 1:
            self.latency_s.append(time.perf_counter() - t_in)
            if c_in is not None:  # CPU time of the same interval: wall minus it = waiting
                self.latency_cpu_s.append(time.thread_time() - c_in)
        elif n_updated > 1:
            self.backlog_updates += n_updated
        if n_updated and self.p["estimate_rate_hz"] <= 0:
            self._publish_estimate()

    def _residual_bytes(self, o: FrameOutcome) -> bytes:
        """:meth:`_residual_msg` serialized (the same message, without the Python objects)."""
        u = o.update
        if u is None:
            return encode_residual_array(o.stamp_ns, o.frame_id, float("nan"), 0)
        nis = float(u.nis)
        dof = int(u.dof) if math.isfinite(nis) else 0
        n = len(u.uv)
        mags = o.magnitude
        mags = np.asarray(mags, float) if len(mags) == n else np.full(n, np.nan)
        return encode_residual_array(o.stamp_ns, o.frame_id, nis, dof, np.asarray(o.catalog_id),
                                     u.uv, u.uv_pred, u.S, mags,
                                     ~np.asarray(u.accepted, bool))

    def _residual_msg(self, o: FrameOutcome) -> StarResidualArray:
        msg = StarResidualArray()
        msg.header.stamp = _time_msg(o.stamp_ns)
        msg.header.frame_id = o.frame_id
        u = o.update
        if u is None or not np.isfinite(u.nis):
            msg.nis = float("nan") if u is None else float(u.nis)
            msg.dof = 0
            if u is None:
                return msg
        else:
            msg.nis, msg.dof = float(u.nis), int(u.dof)
        mags = o.magnitude
        n = len(u.uv)
        mags = np.asarray(mags, float) if len(mags) == n else np.full(n, np.nan)
        cols = zip(np.asarray(o.catalog_id).tolist(), u.uv[:, 0].tolist(), u.uv[:, 1].tolist(),
                   u.uv_pred[:, 0].tolist(), u.uv_pred[:, 1].tolist(), u.S[:, 0, 0].tolist(),
                   u.S[:, 0, 1].tolist(), u.S[:, 1, 1].tolist(), mags.tolist(),
                   (~np.asarray(u.accepted, bool)).tolist(), strict=True)
        msg.residuals = [StarResidual(catalog_id=c, u=uu, v=vv, predicted_u=pu, predicted_v=pv,
                                      cov_uu=a, cov_uv=b, cov_vv=d, magnitude=m, gated=g)
                         for c, uu, vv, pu, pv, a, b, d, m, g in cols]
        return msg

    def estimate_messages(self) -> tuple[CalibrationEstimate, CameraInfo, TransformStamped]:
        """The current estimate as the three published messages."""
        with self._lock:
            cal = self.cal.calibration()
            theta, sigma = self.cal.state()
            conv = self.cal.convergence()
            last = self.cal.last_update
            updates = self.cal.filter_counters()["updates"]
            stamp = rclpy.time.Time(seconds=max(cal.stamp, 0.0)).to_msg()
        est = CalibrationEstimate()
        est.header.stamp = stamp
        est.header.frame_id = self.frame_ids["imu"]
        est.method = self.cal.method
        est.effects = [e.id for e in self.cal.model.effects]
        est.names = self.cal.parameter_names()
        est.values = [float(x) for x in theta]
        est.sigmas = [float(x) for x in sigma]
        q = cal.installation.as_quat()
        est.installation.x, est.installation.y, est.installation.z, est.installation.w = (
            float(x) for x in q)
        est.converged = bool(conv["converged"])
        est.updates = int(updates)
        est.nis = float(last.nis) if last is not None else float("nan")
        est.nis_dof = int(last.dof) if last is not None else 0
        cam = cal.camera.to_yaml_dict()
        info = CameraInfo()
        info.header.stamp = stamp
        info.header.frame_id = self.frame_ids["star_tracker"]
        info.width, info.height = int(cam["image_width"]), int(cam["image_height"])
        info.distortion_model = cam["distortion_model"]
        info.d = [float(x) for x in cam["distortion_coefficients"]["data"]]
        info.k = [float(x) for x in cam["camera_matrix"]["data"]]
        info.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        k = info.k
        info.p = [k[0], k[1], k[2], 0.0, k[3], k[4], k[5], 0.0, 0.0, 0.0, 1.0, 0.0]
        tf = TransformStamped()
        tf.header.stamp = stamp
        tf.header.frame_id = self.frame_ids["imu"]
        tf.child_frame_id = self.frame_ids["star_tracker"]
        (tf.transform.rotation.x, tf.transform.rotation.y, tf.transform.rotation.z,
         tf.transform.rotation.w) = (float(x) for x in q)
        return est, info, tf

    def _publish_estimate(self) -> None:
        try:
            est, info, tf = self.estimate_messages()
        except Exception as exc:  # noqa: BLE001
            self.callback_errors += 1
            self._warn("callback_errors", f"estimate not published: {exc}")
            return
        self.pub_estimate.publish(est)
        self.pub_camera_info.publish(info)
        self.pub_installation.publish(tf)
        self._publish_tf_static(tf)

    def inputs_matched(self) -> dict[str, int]:
        """What ``~/inputs_matched`` reports (resolved names).

        Input topic → publishers its subscription has matched; ``~/data_clock`` →
        subscribers its publisher has matched (the player's flow control).
        """
        out = {sub.topic_name: sub.get_publisher_count() for sub in self._input_subs}
        out[self.pub_progress.topic_name] = self.pub_progress.get_subscription_count()
        return out

    def _publish_inputs_matched(self) -> None:
        """``~/inputs_matched`` (latched) when a count changed (and once at start)."""
        counts = self.inputs_matched()
        if counts == self._inputs_matched:
            return
        self._inputs_matched = counts
        st = DiagnosticStatus(level=DiagnosticStatus.OK, name=self.get_fully_qualified_name(),
                              message=f"{sum(counts[s.topic_name] > 0 for s in self._input_subs)}"
                                      f" of {len(self._input_subs)} input topics have a matched "
                                      "publisher")
        st.values = [KeyValue(key=t, value=str(n)) for t, n in counts.items()]
        self.pub_inputs_matched.publish(st)

    def _publish_tf_static(self, tf: TransformStamped) -> None:
        """The installation on /tf_static, when it changed since it was last sent."""
        r = tf.transform.rotation
        q = (r.x, r.y, r.z, r.w)
        if self.pub_tf_static is None or q == self._tf_sent:
            return
        self.pub_tf_static.publish(TFMessage(transforms=[tf]))
        self._tf_sent = q

    def diagnostics(self) -> DiagnosticStatus:
        """The node's health as one DiagnosticStatus (also published on /diagnostics)."""
        now = time.monotonic()
        t_prev, n_prev = self._rate_snapshot
        dt = max(now - t_prev, 1e-9)
        rates = {k: (self.received[k] - n_prev[k]) / dt for k in INPUTS}
        self._rate_snapshot = (now, dict(self.received))
        with self._lock:
            counters = asdict(self.cal.counters)
            fc = self.cal.filter_counters()
            conv = self.cal.convergence()
            pending = self.cal.pending()
            initialized = self.cal.initialized
            cons = consistency(self.cal.stats.current(),  # the replay's statistics, so far
                               getattr(self.cal.config, "noise", None))
            degraded = self.cal.degraded()
        lat = np.asarray(self.latency_s) * 1e3
        st = DiagnosticStatus()
        st.name = f"{self.get_name()}: {self.p['method']} calibration"
        st.hardware_id = f"{self.frame_ids['imu']}+{self.frame_ids['star_tracker']}"
        problems, silent = [], {}
        for key in ("imu", "stars"):
            last = self._rx_last_wall[key]
            if last is None:
                problems.append(f"no {key} yet")
            elif now - last > self.p["silence_timeout_s"]:
                silent[key] = now - last  # (the seconds go to the values: a constant text)
                problems.append(f"{key} silent (nothing for over "
                                f"{self.p['silence_timeout_s']:g} s)")
        if problems:
            st.level = DiagnosticStatus.WARN
            st.message = "; ".join(problems)
        elif not initialized:
            st.level, st.message = DiagnosticStatus.WARN, "waiting for attitude initialization"
        else:
            st.level, st.message = verdict_status(cons, conv["converged"], degraded)
        if cons.get("verdict") == "model mismatch":
            self._warn("model_mismatch", mismatch_text(cons) + " (second half of the data "
                       "so far)")
        values: dict[str, Any] = {f"rate.{k}_hz": f"{v:.2f}" for k, v in rates.items()}
        values.update({f"silent.{k}_s": f"{v:.0f}" for k, v in silent.items()})
        values.update(verdict_values(cons))
        values.update({f"received.{k}": v for k, v in self.received.items()})
        values.update({f"input.{k}": v for k, v in counters.items()})
        values.update({f"filter.{k}": v for k, v in fc.items()})
        values.update({f"pending.{k}": v for k, v in pending.items()})
        values["callback_errors"] = self.callback_errors
        values["degraded"] = "; ".join(degraded) if degraded else "no"
        values["backlog_updates"] = self.backlog_updates
        values["converged"] = conv["converged"]
        # (the convergence test's: the last converge_window updates, joint over each frame)
        values["convergence.nis_per_dof"] = f"{conv['nis_ratio']:.3f}"
        values["sigma_ratio_min"] = f"{conv['sigma_ratio_min']:.4f}"
        last = self.cal.last_update
        values["last_nis"] = f"{last.nis:.3f}" if last is not None else "nan"
        if len(lat):
            values["latency_p50_ms"] = f"{np.percentile(lat, 50):.3f}"
            values["latency_p99_ms"] = f"{np.percentile(lat, 99):.3f}"
        st.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        self._warn_counters({**counters, **fc, "callback_errors": self.callback_errors})
        for key, seconds in silent.items():
            self._warn(f"silent_{key}", f"{key} silent for {seconds:.0f} s")
        return st

    def _publish_diagnostics(self) -> None:
        try:
            st = self.diagnostics()
        except Exception as exc:  # noqa: BLE001
            self.callback_errors += 1
            self._warn("callback_errors", f"diagnostics failed: {exc}")
            return
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [st]
        self.pub_diagnostics.publish(arr)
        if self.view is not None:
            self.view.diagnostics(arr)

    # ------------------------------------------------------------------ warnings
    def _warn(self, key: str, text: str) -> None:
        now = time.monotonic()
        last, suppressed = self._warned.get(key, (-math.inf, 0))
        if now - last >= self.p["warn_throttle_s"]:
            extra = f" ({suppressed} similar suppressed)" if suppressed else ""
            self.get_logger().warning(text + extra)
            self._warned[key] = (now, 0)
        else:
            self._warned[key] = (last, suppressed + 1)

    def _warn_counters(self, counts: dict[str, int]) -> None:
        prev = getattr(self, "_warn_prev", {})
        for k in _WARN_COUNTERS:
            v = int(counts.get(k, 0))
            if v > prev.get(k, 0):
                self._warn("count_" + k, f"{k}: +{v - prev.get(k, 0)} (total {v})")
        self._warn_prev = {k: int(counts.get(k, 0)) for k in _WARN_COUNTERS}


def usage() -> str:
    """``calibrator --help``: how to run it, its parameters, topics and services."""
    lines = ["usage: calibrator --ros-args -p prior_file:=PRIOR.yaml [-p NAME:=VALUE ...] "
             "[--params-file config/calibrator.yaml] [-r /imu/data:=/my/imu ...]",
             "       (ros2 run stellar_cal_ros calibrator --ros-args ...)", "",
             "Live star tracker + IMU calibration; see doc/ros_nodes.md and doc/interfaces.md.",
             "", "parameters (read-only, set at start):"]
    for name, (default, text, limits) in PARAMETERS.items():
        shown = "[]" if isinstance(default, Parameter.Type) else repr(default)
        rng = (f"; one of {', '.join(limits)}" if isinstance(limits, tuple) and isinstance(
            limits[0], str) else f"; in [{limits[0]}, {limits[1]}]" if limits else "")
        lines.append(f"  {name:22s} {text} (default {shown}{rng})")
    lines += ["", "subscribes: " + ", ".join(t for t, _ in INPUTS.values()),
              "publishes:  ~/estimate, ~/camera_info (latched), ~/installation, /tf_static, "
              "~/residuals, ~/data_clock, ~/inputs_matched (latched), /diagnostics, ~/view, "
              "~/residual_field",
              "services:   ~/save_calibration, ~/checkpoint, ~/reset (std_srvs/Trigger)"]
    return "\n".join(lines)


def make_executor():
    """The executor ``main`` spins: rclpy's EventsExecutor where it exists.

    At 200 Hz IMU the node uses ≈ 16 % of a core with the wait-set executor
    (``rclpy.spin``), ≈ 6 % with the events executor (doc/ros_nodes.md, Latency).
    ``STELLAR_CAL_EXECUTOR=single`` selects the SingleThreadedExecutor.
    """
    import os

    from rclpy.executors import SingleThreadedExecutor

    if os.environ.get("STELLAR_CAL_EXECUTOR", "events") != "single":
        try:
            from rclpy.experimental import EventsExecutor
        except ImportError:  # pragma: no cover - older rclpy
            pass
        else:
            return EventsExecutor()
    return SingleThreadedExecutor()


def main(argv: list[str] | None = None) -> int:
    """Run the node until shutdown; write the checkpoint and the calibration on the way out."""
    from stellar_cal_ros.nodes.runner import run_node

    return run_node("calibrator", CalibratorNode, usage, argv, make_executor,
                    lambda node: node.finish())

if __name__ == "__main__":
    sys.exit(main())
