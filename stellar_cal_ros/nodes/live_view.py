"""The calibrator's live view: ``~/view``, ``~/residual_field`` and an optional Foxglove server.

The channels and pictures of ``replay --viz`` (:mod:`stellar_cal_ros.viz`), live: the
``calibrator`` publishes ``~/view`` (``stellar_cal_msgs/CalibrationView``: every estimate
with its ±1σ band in display units, NIS/dof, the verdict) whenever an update happened since
the last tick, and ``~/residual_field`` (``sensor_msgs/CompressedImage``, PNG) for every
``field_period_s`` of data — the same bytes the replay writes, from the same functions.
Both are latched (transient local, depth 1): a viewer that connects late sees the last
picture at once.  On an apt ROS install ``foxglove_bridge`` shows them with the shipped
layout; on the PyPI install (no bridge) ``foxglove_port`` makes the node serve the same
channels (and ``/diagnostics``) itself with the Foxglove SDK's WebSocket server.

Cost on the update callback: :meth:`LiveView.add` appends the frame's outcome to a deque
(≈ 1 µs); the rest runs in a timer at ``view_rate_hz``: the view message (≈ 0.3 ms) and,
once per ``field_period_s`` of data, the residual-field picture (≈ 5–10 ms of CPU).  When
data arrive faster than the timer ticks (a bag played at ``rate: 0``), windows that ended
between two ticks are not drawn, only the last one (counted in ``fields_skipped``).
"""

from __future__ import annotations

from collections import deque
from typing import Any

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CompressedImage
from stellar_cal_msgs.msg import CalibrationView

from stellar_cal_ros.methods.results import consistency, residual_rows
from stellar_cal_ros.viz import MOVING, ViewMessages, residual_field, view_fields

#: the view's parameters: name: (default, description, range)
PARAMETERS: dict[str, tuple[Any, str, Any]] = {
    "view_rate_hz": (1.0, "rate of ~/view and of the check for a new ~/residual_field "
                     "(0: no live view)", (0.0, 100.0)),
    "field_period_s": (30.0, "data time per ~/residual_field picture, s", (1.0, 86400.0)),
    "foxglove_port": (0, "serve the live view on ws://<foxglove_address>:PORT with the "
                      "Foxglove SDK (0: off; needs the foxglove-sdk package)", (0, 65535)),
    "foxglove_address": ("0.0.0.0", "address the Foxglove server binds to "
                         "(127.0.0.1: this machine only)", None),
}


def check_parameters(p: dict[str, Any]) -> list[str]:
    """Errors in the view's parameters beyond their ranges."""
    if p["foxglove_port"] and not p["view_rate_hz"] > 0:
        return ["foxglove_port needs view_rate_hz > 0 (the view it serves)"]
    return []


class LiveView:
    """``~/view``, ``~/residual_field`` (and the Foxglove server) of one calibrator node.

    Build it early (:meth:`__init__` starts the server, so that a port in use stops the node
    before it does anything else), then :meth:`attach` it once the driver and the node's
    publishers exist.
    """

    def __init__(self, node, p: dict[str, Any]) -> None:
        self.node = node
        self.period = float(p["field_period_s"])
        self.rate = float(p["view_rate_hz"])
        self.server = None
        self.context = None
        if p["foxglove_port"]:
            self.context, self.server = _start_server(
                node.get_fully_qualified_name(), p["foxglove_address"], int(p["foxglove_port"]))
        self.messages = ViewMessages()
        self.counts = {"views": 0, "fields": 0, "fields_skipped": 0}
        self.channels: dict[str, Any] = {}
        self.reset()

    def reset(self) -> None:
        """Forget the frames seen (the filter restarts from the prior)."""
        self.recent: deque = deque()  # frame outcomes with an update, oldest first
        self.nis: deque[tuple[float, int]] = deque(maxlen=MOVING)
        self.t_first: float | None = None
        self.t_last = 0.0  # the last update's data time
        self.next_field = 0.0
        self.field_end: float | None = None  # a window that ended and waits for its picture
        self._updates_sent = -1

    def attach(self, cal, frames: dict[str, str], image_size: tuple[int, int],
               diagnostics_topic: str) -> None:
        """Create the publishers (and the server's channels) and start the timer.

        ``cal``: the node's driver; ``frames``: its frame ids; ``image_size``: the detector's
        width and height, px; ``diagnostics_topic``: the resolved ``/diagnostics``.
        """
        self.cal, self.frames, self.image_size = cal, frames, image_size
        latched = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        node = self.node
        self.pub_view = node.create_publisher(CalibrationView, "~/view", latched)
        self.pub_field = node.create_publisher(CompressedImage, "~/residual_field", latched)
        if self.context is not None:
            self.channels = self.messages.channels(self.context, {
                "view": self.pub_view.topic_name, "field": self.pub_field.topic_name,
                "diagnostics": diagnostics_topic})
        # first use compiles rosbags' serializers and imports the display units and PIL
        # (≈ 0.5 s): pay it now, not in the first tick while data flow
        theta, sigma = cal.state()
        self.messages.view(0, frames["imu"], view_fields(cal.parameter_names(), theta, sigma,
                                                         0, [], {}))
        self.messages.image(0, frames["star_tracker"], b"")
        import PIL.ImageDraw  # noqa: F401
        self.timer = node.create_timer(1.0 / self.rate, self.tick)

    # ----------------------------------------------------------------- the update callback
    def add(self, outcome) -> None:
        """Keep a frame's outcome (the update callback's only cost of the view)."""
        u = outcome.update
        if u is None:
            return
        self.recent.append(outcome)
        if outcome.status != "updated":
            return
        self.nis.append((float(u.nis), int(u.dof)))
        t = self.t_last = float(u.stamp)
        if self.t_first is None:  # the replay's rule (viz.write_viz): a picture every
            self.t_first, self.next_field = t, t + self.period  # period after the first
        elif t >= self.next_field:
            if self.field_end is not None:
                self.counts["fields_skipped"] += 1
            self.field_end, self.next_field = t, t + self.period

    # ----------------------------------------------------------------- the timer
    def tick(self) -> None:
        """Publish the view if an update happened, and the residual field if one is due."""
        try:
            with self.node._lock:
                self._publish_view()
                self._publish_field()
        except Exception as exc:  # noqa: BLE001 - a view must never stop the calibration
            self.node.callback_errors += 1
            self.node._warn("view_failed", f"live view not published: {exc}")

    def _publish_view(self) -> None:
        cal = self.cal
        updates = int(cal.filter_counters()["updates"])
        if updates == self._updates_sent or not self.nis:
            return
        theta, sigma = cal.state()
        fields = view_fields(cal.parameter_names(), theta, sigma, updates, self.nis,
                             consistency(cal.stats.current(),
                                         getattr(getattr(cal, "config", None), "noise", None)))
        data = self.messages.view(int(round(self.t_last * 1e9)), self.frames["imu"], fields)
        self.pub_view.publish(data)
        if "view" in self.channels:
            self.channels["view"].log(data)
        self._updates_sent = updates
        self.counts["views"] += 1

    def _publish_field(self) -> None:
        end = self.field_end
        if end is not None:
            self.field_end = None
            png = residual_field(self.residuals(end), end, self.period, self.t_first,
                                 *self.image_size)
            if png is not None:
                data = self.messages.image(int(round(end * 1e9)), self.frames["star_tracker"],
                                           png)
                self.pub_field.publish(data)
                if "field" in self.channels:
                    self.channels["field"].log(data)
                self.counts["fields"] += 1
        keep_from = self.next_field - self.period  # no later window reaches further back
        while self.recent and float(self.recent[0].update.stamp) <= keep_from:
            self.recent.popleft()

    def residuals(self, end: float) -> dict[str, Any]:
        """The residual-table columns of the kept frames up to ``end`` (the replay's rows)."""
        import numpy as np

        rows = [residual_rows(o.update, 0, o.catalog_id, o.magnitude, o.head_temperature)
                for o in self.recent if float(o.update.stamp) <= end]
        if not rows:
            return {"t": np.zeros(0)}
        return {k: np.concatenate([r[k] for r in rows]) for k in rows[0]}

    def diagnostics(self, message) -> None:
        """Forward a published ``/diagnostics`` message to the Foxglove server."""
        if "diagnostics" in self.channels:
            from rclpy.serialization import serialize_message

            self.channels["diagnostics"].log(serialize_message(message))

    def close(self) -> None:
        """Stop the Foxglove server."""
        if self.server is not None:
            self.server.stop()
            self.server = None


def _start_server(name: str, address: str, port: int):
    """(context, server) of a Foxglove WebSocket server; ValueError in one line if it fails."""
    try:
        import foxglove
    except ImportError as exc:
        raise ValueError(f"foxglove_port={port} needs the foxglove-sdk Python package "
                         "(pip install foxglove-sdk; on an apt ROS install foxglove_bridge "
                         f"shows the same topics): {exc}") from exc
    context = foxglove.Context()
    try:
        server = foxglove.start_server(name=name, host=address, port=port, context=context)
    except Exception as exc:  # noqa: BLE001 - the SDK raises its own types
        raise ValueError(f"foxglove_port={port}: cannot serve Foxglove on {address}:{port}: "
                         f"{exc}") from exc
    return context, server
