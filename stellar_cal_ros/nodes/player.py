"""``player`` node: publish a contract bag (``ros2 run stellar_cal_ros player``).

Messages go out unchanged (their CDR bytes from the bag), in log-time order, on the bag's
topic names (remappable), with:

* ``rate > 0``: paced at ``rate`` × real time by the log times (1 = real time);
* ``rate = 0``: as fast as the consumer keeps up — the calibrator reports the newest IMU
  stamp it has consumed on ``progress_topic`` (its ``~/data_clock``, rosgraph_msgs/Clock);
  the player holds back while the IMU it has published is more than ``max_lag_s`` ahead of
  that (so no subscription queue can overflow); after ``ack_timeout_s`` without progress it
  carries on (counted, warned);
* ``/clock`` (rosgraph_msgs/Clock) with the bag's log time every ``clock_period_s`` of bag
  time, for nodes run with ``use_sim_time: true``.

Before the first message it waits up to ``wait_for_subscribers_s`` until every topic it
plays has a subscriber (and, with ``rate: 0``, its progress subscription a publisher).  A
publisher seeing a subscriber does not mean the subscriber sees the publisher yet (DDS
matches both ends apart): messages sent in between are lost.  With ``match_topic`` (the
calibrator's latched ``~/inputs_matched``) it also waits until the consumer reports, for
every played topic it subscribes, at least as many matched publishers as the graph shows
on that topic (the player's own among them), and, with ``rate: 0``, for ``progress_topic``
at least as many matched subscribers as the graph shows (the acks reach the player).  A
wait that ends unmet is warned (the topics and why) and counted
(:attr:`PlayStats.unmatched_topics`); the playback goes on.

The bag — a ``.mcap`` file, a rosbag2 directory (MCAP or sqlite3) or a ROS 1 ``.bag``, the
formats every ``stellar-cal`` command reads — is read with
:class:`~stellar_cal_ros.io.reader.BagReader` (no rosbag2 needed; chunk CRCs verified; a ROS
1 bag's messages converted to CDR).  ``start_offset_s`` and ``duration_s`` select a part of
it.  The bag is checked before anything is published (:func:`check_bag`: missing, not a
bag, truncated / no summary); a damaged chunk met while playing stops the playback.  Either
way the node prints one line ``player: error: ...`` and exits with status 1.  ``player
--help`` lists the parameters; an unknown parameter name (a typo) is an error.
"""

from __future__ import annotations

import importlib
import os
import struct
import sys
import threading
import time
import warnings
from dataclasses import dataclass
from typing import Any

import rclpy
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import ParameterUninitializedException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock

from stellar_cal_ros.errors import BagError, StellarCalError, no_such_bag
from stellar_cal_ros.io.schemas import normalize_type
from stellar_cal_ros.nodes.runner import check_parameter_names, declare

IMU_TYPE = "sensor_msgs/msg/Imu"

PARAMETERS: dict[str, tuple[Any, str]] = {
    "bag": ("", "MCAP file to play (required)"),
    "rate": (1.0, "playback speed × real time; 0: as fast as the subscriber keeps up"),
    "start_offset_s": (0.0, "skip this much of the bag (log time), s"),
    "duration_s": (0.0, "play only this much (log time), s; 0: to the end"),
    "topics": (Parameter.Type.STRING_ARRAY, "topics to play (default: all)"),
    "publish_clock": (True, "publish /clock (rosgraph_msgs/Clock) with the bag's log time"),
    "clock_period_s": (0.01, "bag-time interval between /clock messages, s"),
    "qos_depth": (1000, "publisher queue depth (reliable, KEEP_LAST)"),
    "progress_topic": ("/calibrator/data_clock",
                       "flow control (rate 0): newest IMU stamp the consumer has used"),
    "max_lag_s": (0.5, "flow control: IMU published at most this far (stamps) ahead, s"),
    "ack_timeout_s": (5.0, "flow control: carry on after this long without progress"),
    "wait_for_subscribers_s": (5.0, "wait this long for a subscriber on every topic first "
                               "(0: no wait, no check)"),
    "match_topic": ("", "handshake: the consumer's latched report of the publishers it has "
                    "matched per topic (the calibrator's ~/inputs_matched); '' : off"),
    "exit_when_done": (True, "shut down after the last message"),
}


@dataclass
class PlayStats:
    """What a playback did."""

    messages: int = 0
    acks: int = 0
    ack_timeouts: int = 0
    waits: int = 0
    unmatched_topics: int = 0  # topics the start-up wait ended without (warned; see unmatched)
    wall_s: float = 0.0
    bag_s: float = 0.0


def check_bag(path: str) -> tuple[dict[str, Any], int, int]:
    """Check ``path`` before anything is published: ``(topics, start_ns, end_ns)``.

    Any bag :class:`~stellar_cal_ros.io.reader.BagReader` reads (a ``.mcap`` file, a
    rosbag2 directory, a ROS 1 ``.bag``); an MCAP file must have its summary (a recording
    that was not closed is refused: ``stellar-cal info`` shows what is readable).

    Raises
    ------
    BagError
        Missing, not a bag, no summary, no message.
    """
    from stellar_cal_ros.io.reader import BagReader

    if not os.path.exists(path):
        raise no_such_bag(path)
    try:
        with warnings.catch_warnings(), BagReader(path) as reader:
            warnings.simplefilter("ignore")
            if not reader.has_summary:
                raise BagError(f"{path} has no summary section: truncated or not closed (the "
                               "recorder was killed?); `stellar-cal info` shows what is "
                               "readable")
            topics = reader.topics()
            start, end = reader.start_ns, reader.end_ns
    except BagError as exc:
        text = str(exc)
        if "MCAP" in text and os.path.isfile(path) and "magic" in text.lower():
            raise BagError(f"{path} is not an MCAP file, a rosbag2 directory or a ROS 1 bag") \
                from None
        raise
    if not topics or start is None or end is None:
        raise BagError(f"{path} holds no message")
    return topics, start, end


def message_class(type_name: str):
    """``pkg/msg/Type`` → the generated Python class."""
    pkg, _, name = type_name.replace("/msg/", "/").partition("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def _value(node: Node, name: str) -> Any:
    """A declared parameter's value; None for a typed one left unset (e.g. an empty list)."""
    try:
        return node.get_parameter(name).value
    except ParameterUninitializedException:
        return None


class PlayerNode(Node):
    """The ``player`` node (see the module docstring); :meth:`play` does the work."""

    def __init__(self, node_name: str = "player", **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        for name, (default, text) in PARAMETERS.items():
            declare(self, name, default, ParameterDescriptor(description=text, read_only=True))
        check_parameter_names(self)
        self.p = {name: _value(self, name) for name in PARAMETERS}
        self.p["topics"] = [t for t in (self.p["topics"] or []) if t]
        if not self.p["bag"]:
            raise ValueError("parameter 'bag' is required (`player --help` lists the "
                             "parameters)")
        if self.p["rate"] < 0 or self.p["max_lag_s"] <= 0 or self.p["qos_depth"] < 1:
            raise ValueError("rate must be >= 0, max_lag_s > 0 and qos_depth >= 1")
        # BagError: nothing is published
        self.topics, self.start_ns, self.end_ns = check_bag(self.p["bag"])
        self.error: str | None = None  # why a playback stopped early
        self.consumer_ns = -1  # newest IMU stamp the consumer reported
        self.stats = PlayStats()
        self._first_imu_ns: int | None = None
        self.consumer_matched: dict[str, int] | None = None  # match_topic's last report
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=self.p["qos_depth"],
                               reliability=ReliabilityPolicy.RELIABLE)
        self.clock_pub = self.create_publisher(Clock, "/clock", 10) \
            if self.p["publish_clock"] else None
        self._pubs: dict[str, Any] = {}
        self._progress_sub = None
        if self.p["rate"] == 0:
            self._progress_sub = self.create_subscription(
                Clock, self.p["progress_topic"], self._on_progress,
                QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        if self.p["match_topic"]:
            from diagnostic_msgs.msg import DiagnosticStatus

            self.create_subscription(DiagnosticStatus, self.p["match_topic"], self._on_matched,
                                     QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                                durability=DurabilityPolicy.TRANSIENT_LOCAL))

    def _on_progress(self, msg: Clock) -> None:
        with self._cond:
            self.stats.acks += 1
            self.consumer_ns = max(self.consumer_ns, rclpy.time.Time.from_msg(
                msg.clock).nanoseconds)
            self._cond.notify_all()

    def _on_matched(self, msg) -> None:
        counts = {}
        for kv in msg.values:
            try:
                counts[kv.key] = int(kv.value)
            except ValueError:
                continue
        self.consumer_matched = counts

    def stop(self) -> None:
        """Ask a running :meth:`play` to return."""
        self._stop.set()
        with self._cond:
            self._cond.notify_all()

    def _make_publishers(self) -> dict[str, Any]:
        want = set(self.p["topics"]) if self.p["topics"] else None
        for topic, info in self.topics.items():
            if want is not None and topic not in want or topic in self._pubs:
                continue
            name = info.schema_name
            try:
                if "|" in name:
                    raise ValueError("the topic's channels have different types")
                cls = message_class(name)
            except (ImportError, AttributeError, ValueError) as exc:
                self.get_logger().warning(f"{topic}: type {name} not available "
                                          f"({exc}); not played")
                continue
            self._pubs[topic] = (self.create_publisher(cls, topic, self._qos),
                                 normalize_type(name) == IMU_TYPE)
        return self._pubs

    def unmatched(self) -> list[str]:
        """The played topics a message could still be lost on, each with why."""
        report = self.consumer_matched
        out = []
        if self.p["match_topic"] and report is None:
            out.append(f"{self.p['match_topic']} (no report from the consumer)")
        ends = [(pub.topic_name, pub.get_subscription_count(), "no subscriber",
                 self.count_publishers, "the consumer has matched {} of {} publishers")
                for pub, _ in self._pubs.values()]
        if self._progress_sub is not None:
            ends.append((self._progress_sub.topic_name, self._progress_sub.get_publisher_count(),
                         "no progress publisher", self.count_subscribers,
                         "the consumer's progress publisher has matched {} of {} subscribers"))
        for name, here, none, graph_count, short in ends:
            # this end's match, then the consumer's (as many as the graph shows)
            if here == 0:
                out.append(f"{name} ({none})")
            elif report is not None and name in report and report[name] < graph_count(name):
                out.append(f"{name} ({short.format(report[name], graph_count(name))})")
        return out

    def _wait_for_subscribers(self) -> None:
        """Wait for the subscribers (and the match_topic handshake); warn if it ends unmet."""
        wait_s = self.p["wait_for_subscribers_s"]
        if wait_s <= 0:
            return
        deadline = time.monotonic() + wait_s
        missing = self.unmatched()
        while missing and time.monotonic() < deadline and not self._stop.is_set():
            time.sleep(0.02)
            missing = self.unmatched()
        if not missing or self._stop.is_set():
            return
        self.stats.unmatched_topics = len(missing)
        self.get_logger().warning(
            f"after {wait_s} s still unmatched: {', '.join(missing)}; playing anyway (messages "
            "may be lost)")

    def _wait_progress(self, imu_ns: int) -> None:
        """Flow control: block while the consumer lags the IMU published by > max_lag_s."""
        lag_ns = int(self.p["max_lag_s"] * 1e9)
        with self._cond:
            if self.consumer_ns < 0 and self.stats.acks == 0 and imu_ns - self._first_imu_ns \
                    < lag_ns:
                return  # start-up: nothing reported yet
            waited = False
            while not self._stop.is_set() and imu_ns - max(self.consumer_ns, self._first_imu_ns) \
                    > lag_ns:
                waited = True
                before = self.stats.acks
                self._cond.wait(self.p["ack_timeout_s"])
                if self.stats.acks == before and not self._stop.is_set():
                    self.stats.ack_timeouts += 1
                    self.get_logger().warning(
                        f"no progress on {self.p['progress_topic']} for "
                        f"{self.p['ack_timeout_s']} s: carrying on")
                    self.consumer_ns = imu_ns
            self.stats.waits += waited

    def play(self) -> PlayStats:
        """Publish the bag (blocking; call from a thread other than the executor's)."""
        from stellar_cal_ros.io.reader import BagReader

        rate = float(self.p["rate"])
        clock_ns = int(self.p["clock_period_s"] * 1e9)
        with BagReader(self.p["bag"]) as reader:  # strict: damage stops the playback
            pubs = self._make_publishers()
            self._wait_for_subscribers()
            start = self.start_ns + int(self.p["start_offset_s"] * 1e9)
            end = self.end_ns + 1 if self.p["duration_s"] <= 0 else \
                start + int(self.p["duration_s"] * 1e9)
            t_wall0 = time.perf_counter()
            first_log = None
            next_clock = None
            for topic, log_ns, data in reader.iter_raw(list(pubs)):
                if self._stop.is_set() or log_ns >= end:
                    break
                if log_ns < start:
                    continue
                if first_log is None:
                    first_log = next_clock = log_ns
                if rate > 0:
                    delay = t_wall0 + (log_ns - first_log) * 1e-9 / rate - time.perf_counter()
                    if delay > 0.0005:
                        time.sleep(delay)
                if self.clock_pub is not None and log_ns >= next_clock:
                    c = Clock()
                    c.clock = rclpy.time.Time(nanoseconds=log_ns).to_msg()
                    self.clock_pub.publish(c)
                    next_clock = log_ns + clock_ns
                pub, is_imu = pubs[topic]
                if is_imu and rate == 0 and len(data) >= 12:
                    sec, nsec = struct.unpack_from("<iI" if data[1] == 1 else ">iI", data, 4)
                    imu_ns = sec * 1_000_000_000 + nsec
                    if self._first_imu_ns is None:
                        self._first_imu_ns = imu_ns
                    self._wait_progress(imu_ns)
                pub.publish(data)
                self.stats.messages += 1
                self.stats.bag_s = (log_ns - first_log) * 1e-9
        self.stats.wall_s = time.perf_counter() - t_wall0
        self.get_logger().info(
            f"played {self.stats.messages} messages ({self.stats.bag_s:.1f} s of bag) in "
            f"{self.stats.wall_s:.1f} s, ack timeouts {self.stats.ack_timeouts}, unmatched "
            f"topics {self.stats.unmatched_topics}")
        return self.stats


def usage() -> str:
    """``player --help``: how to run it and its parameters."""
    lines = ["usage: player --ros-args -p bag:=BAG [-p NAME:=VALUE ...] [--params-file "
             "config/player.yaml] [-r /imu/data:=/my/imu ...]",
             "       (ros2 run stellar_cal_ros player --ros-args ...)", "",
             "Publish a bag (.mcap, rosbag2 directory or ROS 1 .bag) on its topics; see "
             "doc/ros_nodes.md.", "", "parameters (read-only, set at start):"]
    for name, (default, text) in PARAMETERS.items():
        shown = "[]" if isinstance(default, Parameter.Type) else repr(default)
        lines.append(f"  {name:24s} {text} (default {shown})")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Play the bag, then exit (or keep spinning if ``exit_when_done`` is false)."""
    from stellar_cal_ros.nodes.runner import help_requested

    args = list(argv if argv is not None else sys.argv)
    if help_requested(args):
        print(usage())
        return 0
    rclpy.init(args=args)
    node = None
    try:
        node = PlayerNode()
    except ValueError as exc:
        print(f"player: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    except StellarCalError as exc:
        print(f"player: error: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 1
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    done = threading.Event()

    def run() -> None:
        try:
            node.play()
        except Exception as exc:  # noqa: BLE001 - a damaged chunk: one line, exit status 1
            node.error = (f"{node.p['bag']}: playback stopped after {node.stats.messages} "
                          f"messages: {type(exc).__name__}: {exc}")
        finally:
            done.set()

    worker = threading.Thread(target=run, daemon=True)
    worker.start()
    try:
        while rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
            if done.is_set() and node.p["exit_when_done"]:
                break
    except (KeyboardInterrupt, ExternalShutdownException):
        node.stop()
    finally:
        worker.join(timeout=2.0)
        node.destroy_node()
        rclpy.try_shutdown()
    if node.error:
        print(f"player: error: {node.error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
