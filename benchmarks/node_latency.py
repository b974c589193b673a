"""Per-star-frame update latency of the live ``calibrator`` node (2 Hz stars + 200 Hz IMU).

The calibrator runs in its own process (multiprocessing *spawn*: rclpy and fork do not
mix); this process publishes a bag in real time (default: a 600 s ``psce_rotations`` bag
simulated once into ``benchmarks/.cache/``; ``--bag`` e.g. the shared
``psce_ideal_900s.mcap``), with its 100 Hz IMU split
into 200 Hz samples (each 10 ms mean rate becomes two 5 ms samples of the same mean rate —
the same motion, twice the message rate), the star frames (2 Hz) and the 1 Hz environment
topics unchanged.  Reported:

* **compute latency** (measured in the node): from the callback that made a frame
  processable (normally the IMU sample that covers it) to its residuals published;
* **end-to-end latency**: frame published → its residuals received here; it includes the
  reorder window and the wait for the IMU sample covering the exposure (the bag's frames
  are published at their mid-exposure stamp, before that IMU exists);
* **compute CPU**: the calibrator thread's CPU time over the same interval (the wall
  latency minus it is time the thread was preempted or blocked);
* CPU: the calibrator process's CPU time / wall time, and per-core load from /proc/stat;
* **the end-to-end split** of every frame after the first 10 s (one monotonic clock in all
  processes): ``wait`` (frame published → the IMU sample that releases it published: the
  reorder window by design, more when this publisher falls behind its schedule), ``publish``
  (that sample's ``publish()`` call), ``queue`` (→ the node's callback entry: DDS, and the
  executor busy with another of the node's callbacks, ``busy_ms``), ``compute`` (→ the
  residuals published) and ``deliver`` (→ received here); the tail frames (e2e ≥ p99) one
  by one, and how far the publisher fell behind its real-time schedule;
* with ``--param checkpoint_file=F``: the periodic checkpoint's callbacks in the executor
  (wall and thread CPU: ``checkpoint_callback_ms``), the file writes in whichever thread
  (``checkpoint_write_ms``), and the frames whose releasing message waited while one ran
  (``split.behind_checkpoint``).  Add ``--param resume=false``: a checkpoint left by an
  earlier run of the same bag would make every message late.

``--node echo`` runs, instead of the calibrator, a node with the same topics and QoS that
does no work (it publishes an empty ``~/residuals`` as soon as the IMU sample
``--window`` newer than a frame arrives): what the machine and DDS alone give.
``--busy N`` runs N busy Python loops beside the node (a CPU load that does not vary from
run to run as a test suite does); ``--source-rt-priority N`` runs this process (publisher and
subscriber of the residuals) ``SCHED_FIFO`` too, as a sensor driver and a consumer given the
node's priority would be.

``--executor`` picks the calibrator's executor (``single``: rclpy's
SingleThreadedExecutor, as ``rclpy.spin``; ``events``: ``rclpy.experimental.EventsExecutor``).
``--rt-priority N`` runs the calibrator process
``SCHED_FIFO`` at priority N, as ``chrt -f N ros2 run stellar_cal_ros calibrator`` would.
``--load CMD`` runs CMD in a loop in another process while playing (e.g. a test suite:
``--load "python -m pytest -q test/test_camera.py test/test_kernel.py"``), to measure the
latency on a busy machine.  ``ROS_DOMAIN_ID`` is kept when set.  ``--param NAME=VALUE``
sets a calibrator parameter (e.g. ``view_rate_hz=0`` turns the live view off,
``foxglove_port=8765`` serves it); with ``--watch`` a Foxglove WebSocket client in another
process subscribes to every channel the node serves.  The live view's timer
(``~/view``, ``~/residual_field``) is timed too: ``view_tick_ms`` (thread CPU per tick that
published something) and ``field_ms`` (ticks that drew a residual field).

Usage::

    python benchmarks/node_latency.py [--duration 60] [--window 0.05] [--bag BAG]
        [--executor single|events] [--rt-priority N] [--load CMD] [--busy N]
        [--node calibrator|echo] [--source-rt-priority N] [--json out.json]
        [--param NAME=VALUE ...] [--watch]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import sys
import tempfile
import time
import uuid
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
TARGET_P99_MS = 3.0
BAG: Path = Path()  # set in main()


def _cpu_times() -> list[tuple[int, int]]:
    """(busy, total) jiffies per core from /proc/stat."""
    out = []
    with open("/proc/stat") as fh:
        for line in fh:
            if line.startswith("cpu") and line[3].isdigit():
                v = [int(x) for x in line.split()[1:]]
                idle = v[3] + v[4]
                out.append((sum(v) - idle, sum(v)))
    return out


def run_calibrator(prefix: str, params: dict, result_file: str, stop_file: str,
                   executor: str = "single", rt_priority: int = 0,
                   kind: str = "calibrator") -> None:
    """Child process: spin the node until ``stop_file`` exists, dump its statistics.

    ``kind``: ``calibrator``, or ``echo`` (:func:`echo_node`).
    """
    if rt_priority:  # as `chrt -f N ros2 run ...` would start it (needs CAP_SYS_NICE)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(rt_priority))
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from stellar_cal_ros.nodes.calibrator import INPUTS, CalibratorNode

    rclpy.init()
    args = ["--ros-args"]
    for topic, _ in INPUTS.values():
        args += ["-r", f"{topic}:={prefix}{topic}"]
    args += ["-r", f"/diagnostics:={prefix}/diagnostics"]
    name = "calibrator" + prefix.replace("/", "_")
    if kind == "echo":
        node = echo_node(name, args, params["reorder_window_s"])
    else:
        node = CalibratorNode(name, cli_args=args, parameter_overrides=[
            Parameter(k, value=v) for k, v in params.items()])
    if executor == "events":
        from rclpy.experimental import EventsExecutor

        ex = EventsExecutor()
    else:
        ex = SingleThreadedExecutor()
    ex.add_node(node)
    ticks: list[tuple[float, bool]] = []  # the live view's timer: thread CPU ms, drew a field
    view = getattr(node, "view", None)
    if view is not None:
        tick = view.tick

        def timed_tick() -> None:
            before = dict(view.counts)
            c = time.thread_time()
            tick()
            if view.counts != before:
                ticks.append(((time.thread_time() - c) * 1e3,
                              view.counts["fields"] != before["fields"]))

        view.tick = timed_tick
        view.timer.callback = timed_tick
    marks = _mark_events(node) if kind != "echo" else []
    split = _split_events(node)
    writes = _time_checkpoint_writes()
    wall0, cpu0 = time.perf_counter(), time.process_time()
    while not os.path.exists(stop_file):
        ex.spin_once(timeout_sec=0.05)
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    res = {"latency_ms": [x * 1e3 for x in node.latency_s],
           "latency_cpu_ms": [x * 1e3 for x in getattr(node, "latency_cpu_s", ())],
           "wall_s": wall, "cpu_s": cpu,
           "updates": node.cal.filter_counters()["updates"], "received": node.received,
           "backlog_updates": node.backlog_updates, "view_ticks": ticks,
           "view_counts": dict(view.counts) if view is not None else None,
           "counters": {k: v for k, v in vars(node.cal.counters).items()},
           "marks": marks, "checkpoint_writes": writes, **split}
    Path(result_file).write_text(json.dumps(res))
    node.destroy_node()
    rclpy.try_shutdown()


def _mark_events(node) -> list[dict]:
    """What ran inside each timed frame callback (the tail's suspects), one dict per latency.

    Garbage collections (``gc.callbacks``: ms and the oldest generation), the filter's
    covariance check, the IMU history trim (``drop_imu``) and the gyro judgement; the list
    grows as ``node.latency_s`` does.
    """
    import gc

    from stellar_cal_ros.methods.kernel import StarFilter

    ev = {"gc_ms": 0.0, "gc_gen": -1, "cov_check": 0, "imu_trim": 0, "gyro_judge": 0}
    t_gc = [0.0]

    def on_gc(phase: str, info: dict) -> None:
        if phase == "start":
            t_gc[0] = time.perf_counter()
        else:
            ev["gc_ms"] += (time.perf_counter() - t_gc[0]) * 1e3
            ev["gc_gen"] = max(ev["gc_gen"], int(info["generation"]))

    gc.callbacks.append(on_gc)
    def counting(f, key: str):
        def counted(*a, **k):
            ev[key] += 1
            return f(*a, **k)

        return counted

    for name, key in (("_check_covariance", "cov_check"), ("drop_imu", "imu_trim"),
                      ("judge_gyro", "gyro_judge")):
        setattr(StarFilter, name, counting(getattr(StarFilter, name), key))
    marks: list[dict] = []
    guard = node._guard

    def timed_guard(key, fn, msg) -> None:
        n = len(node.latency_s)
        for k in ev:
            ev[k] = -1 if k == "gc_gen" else 0
        guard(key, fn, msg)
        if len(node.latency_s) != n or len(node.latency_s) == node.latency_s.maxlen:
            marks.append(dict(ev, ms=node.latency_s[-1] * 1e3))

    node._guard = timed_guard
    node.bench_events = ev  # what ran in the last input callback (read by _split_events)
    return marks


def _time_checkpoint_writes() -> list[list[float]]:
    """[start, end] (perf_counter) of every checkpoint file write, in whichever thread."""
    from stellar_cal_ros.io import checkpoint as io_ck

    writes: list[list[float]] = []
    write = io_ck.write_checkpoint

    def timed_write(*a, **k):
        t0 = time.perf_counter()
        try:
            return write(*a, **k)
        finally:
            writes.append([t0, time.perf_counter()])

    io_ck.write_checkpoint = timed_write  # the background writer's (the module's name)
    import stellar_cal_ros.methods.checkpoint as m_ck

    m_ck.write_checkpoint = timed_write  # save_checkpoint's (its own reference)
    return writes


def _split_events(node) -> dict:
    """Per updated frame, the times the end-to-end split needs.

    All are ``perf_counter``, which is CLOCK_MONOTONIC: one clock for every process.

    ``frames``: [stamp_ns, stars callback entry, entry of the callback that released the
    frame, its key (0: an IMU sample, 1: the frame itself, 2: another input), the releasing
    IMU sample's stamp_ns (or 0), residuals published]; ``busy``: [name, start, end] of every
    timer callback and of every input callback over 0.5 ms — what the executor was doing
    while a released frame's message waited in its queue.
    """
    frames: list[list] = []
    busy: list[list] = []
    ck_cpu: list[float] = []  # the periodic checkpoint's thread CPU in the executor, ms
    star_cb: dict[int, float] = {}
    ctx = {"key": "", "imu": 0}
    guard, handle = node._guard, node._handle

    ev = getattr(node, "bench_events", None)

    def split_guard(key, fn, msg) -> None:
        t0 = time.perf_counter()
        ctx["key"] = key
        ctx["imu"] = (msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
                      if key == "imu" else 0)
        ctx["t"] = t0
        guard(key, fn, msg)
        t1 = time.perf_counter()
        if t1 - t0 > 5e-4:  # with what ran in it (a collection, the IMU trim ...)
            what = [k for k, v in (ev or {}).items() if k not in ("gc_ms", "gc_gen") and v]
            if ev and ev["gc_gen"] >= 0:
                what.append(f"gc{ev['gc_gen']}")
            busy.append([key + "".join("+" + w for w in what), t0, t1])

    def split_handle(outcomes, t_in, c_in=None) -> None:
        handle(outcomes, t_in, c_in)
        t_out = time.perf_counter()
        code = {"imu": 0, "stars": 1}.get(ctx["key"], 2)
        for o in outcomes:
            if o.status == "updated":
                frames.append([int(o.stamp_ns), star_cb.pop(int(o.stamp_ns), float("nan")),
                               t_in, code, ctx["imu"], t_out])

    cal = getattr(node, "cal", None)
    if cal is not None and hasattr(cal, "push_stars"):
        push = cal.push_stars

        def split_push(frame):
            star_cb[int(frame.stamp_ns)] = ctx["t"]
            return push(frame)

        cal.push_stars = split_push
    node._guard, node._handle = split_guard, split_handle
    for timer in node.timers:
        cb = timer.callback
        name = getattr(cb, "__name__", "timer").lstrip("_")

        def timed(cb=cb, name=name) -> None:
            t0, c0 = time.perf_counter(), time.thread_time()
            cb()
            busy.append([name, t0, time.perf_counter()])
            if name == "periodic_checkpoint":
                ck_cpu.append((time.thread_time() - c0) * 1e3)

        timer.callback = timed
    return {"frames": frames, "busy": busy, "checkpoint_cpu_ms": ck_cpu}


def echo_node(name: str, args: list[str], window_s: float):
    """A node with the calibrator's topics and none of its work: the machine's own tail.

    It subscribes to the same inputs (stars as raw bytes, IMU as messages, the same QoS) and
    publishes an empty ``~/residuals`` (``dof`` 1) for a star frame as soon as an IMU sample
    ``window_s`` newer than the frame arrives — the calibrator's reorder-window release,
    without the filter.  Its callbacks go through ``_guard``/``_handle`` like the
    calibrator's, so the benchmark's instrumentation times both alike.
    """
    from types import SimpleNamespace

    from rclpy.node import Node
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Imu
    from stellar_cal_msgs.msg import StarCentroidArray, StarResidualArray

    class Echo(Node):
        def __init__(self) -> None:
            super().__init__(name, cli_args=args)
            qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                             reliability=ReliabilityPolicy.RELIABLE)
            out = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                             reliability=ReliabilityPolicy.RELIABLE)
            self.window_ns = int(round(window_s * 1e9))
            self.pending: list[int] = []
            self.latency_s: list[float] = []
            self.latency_cpu_s: list[float] = []
            self.received = {"imu": 0, "stars": 0}
            self.backlog_updates = 0
            self.updates = 0
            self.pub = self.create_publisher(StarResidualArray, "~/residuals", out)
            self.create_subscription(Imu, "/imu/data", self._on_imu, qos)
            self.create_subscription(StarCentroidArray, "/star_tracker/stars", self._on_stars,
                                     qos, raw=True)
            self.cal = SimpleNamespace(filter_counters=lambda: {"updates": self.updates},
                                       counters=SimpleNamespace())

        def _on_imu(self, msg) -> None:
            self._guard("imu", self._push_imu, msg)

        def _on_stars(self, data: bytes) -> None:
            self._guard("stars", self._push_stars, data)

        def _guard(self, key, fn, msg) -> None:
            t_in, c_in = time.perf_counter(), time.thread_time()
            self.received[key] += 1
            out = fn(msg)
            if out:
                self._handle(out, t_in, c_in)

        def _push_imu(self, msg) -> list:
            t = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            done = [s for s in self.pending if s <= t - self.window_ns]
            self.pending = [s for s in self.pending if s > t - self.window_ns]
            return [SimpleNamespace(stamp_ns=s, status="updated") for s in done]

        def _push_stars(self, data: bytes) -> list:
            sec, nsec = np.frombuffer(data, "<i4", 2, 4)  # CDR LE: after the 4-byte header
            self.pending.append(int(sec) * 1_000_000_000 + int(np.uint32(nsec)))
            return []

        def _handle(self, outcomes, t_in, c_in=None) -> None:
            for o in outcomes:
                m = StarResidualArray()
                m.header.stamp.sec, m.header.stamp.nanosec = divmod(o.stamp_ns, 1_000_000_000)
                m.dof = 1
                self.pub.publish(m)
                self.updates += 1
            if len(outcomes) == 1:
                self.latency_s.append(time.perf_counter() - t_in)
                self.latency_cpu_s.append(time.thread_time() - c_in)

    return Echo()


def _split_report(res: dict, pub_t: dict[int, float], pub_done: dict[int, float],
                  rx: dict[int, float], settle_ns: int) -> dict:
    """The end-to-end latency of each frame split where it was spent (ms).

    * ``wait``: the frame's publication → the publication of the message that released it
      (the IMU sample ``reorder_window_s`` of data later; by design ≈ the window, more when
      the publisher fell behind);
    * ``publish``: that message's ``publish()`` call in the benchmark's process (the
      publisher preempted in it shows here);
    * ``queue``: that call's return → the callback's entry in the node (DDS delivery, and
      the executor busy with something else: ``busy_ms`` of it in the node's own callbacks);
    * ``compute``: callback entry → residuals published;
    * ``deliver``: residuals published → received by the benchmark's subscriber.
    """
    rows = []
    busy = res.get("busy") or []
    for stamp, _t_star, t_cb, code, imu, t_out in res.get("frames") or []:
        if stamp < settle_ns or stamp not in pub_t or stamp not in rx:
            continue
        rel = imu if code == 0 else stamp if code == 1 else None
        if rel not in pub_t:
            continue
        t_rel, t_done = pub_t[rel], pub_done[rel]
        blocked = sum(max(0.0, min(b1, t_cb) - max(b0, t_done)) for _, b0, b1 in busy)
        names = sorted({n for n, b0, b1 in busy if b1 > t_done and b0 < t_cb})
        rows.append({"stamp": stamp, "e2e": (rx[stamp] - pub_t[stamp]) * 1e3,
                     "wait": (t_rel - pub_t[stamp]) * 1e3, "publish": (t_done - t_rel) * 1e3,
                     "queue": (t_cb - t_done) * 1e3,
                     "compute": (t_out - t_cb) * 1e3, "deliver": (rx[stamp] - t_out) * 1e3,
                     "busy_ms": blocked * 1e3, "busy": names})
    if not rows:
        return {}
    out: dict = {"frames": len(rows)}
    for k in ("e2e", "wait", "publish", "queue", "compute", "deliver", "busy_ms"):
        x = np.array([r[k] for r in rows])
        out[k] = {"p50": float(np.percentile(x, 50)), "p99": float(np.percentile(x, 99)),
                  "max": float(x.max())}
    # the frames whose message waited while a periodic checkpoint ran in the executor
    behind = [r for r in rows if "periodic_checkpoint" in r["busy"]]
    out["behind_checkpoint"] = {
        "frames": len(behind), "queue_max": max((r["queue"] for r in behind), default=0.0),
        "busy_max": max((r["busy_ms"] for r in behind), default=0.0)}
    p99 = np.percentile([r["e2e"] for r in rows], 99)
    out["tail"] = [{k: (round(v, 2) if isinstance(v, float) else v) for k, v in r.items()
                    if k != "stamp"} for r in rows if r["e2e"] >= p99]
    return out


def _tail_report(marks: list[dict]) -> dict:
    """Of the frames at or above the p99 latency: how many ran a GC, a covariance check ..."""
    if not marks:
        return {}
    ms = np.array([m["ms"] for m in marks])
    p99 = float(np.percentile(ms, 99))
    tail = [m for m in marks if m["ms"] >= p99]
    out = {"frames": len(marks), "tail_frames": len(tail), "tail_ms": [m["ms"] for m in tail]}
    for key, hit in (("gc_any", lambda m: m["gc_gen"] >= 0),
                     ("gc_gen2", lambda m: m["gc_gen"] == 2),
                     ("cov_check", lambda m: m["cov_check"] > 0),
                     ("imu_trim", lambda m: m["imu_trim"] > 0),
                     ("gyro_judge", lambda m: m["gyro_judge"] > 0)):
        with_ = [m["ms"] for m in marks if hit(m)]
        out[key] = {"in_tail": sum(hit(m) for m in tail), "frames": len(with_),
                    "median_ms": float(np.median(with_)) if with_ else None}
    out["gc_ms_total"] = float(sum(m["gc_ms"] for m in marks))
    return out


def watch_foxglove(port: int, stop_file: str, result_file: str) -> None:
    """Child process: a Foxglove WebSocket client subscribed to every channel (tornado)."""
    import asyncio

    from tornado.httpclient import HTTPRequest
    from tornado.websocket import websocket_connect

    async def run() -> dict[str, int]:
        counts = {"channels": 0, "messages": 0, "bytes": 0}
        for _ in range(150):
            try:
                ws = await websocket_connect(HTTPRequest(f"ws://127.0.0.1:{port}", headers={
                    "Sec-WebSocket-Protocol": "foxglove.sdk.v1"}), subprotocols=["foxglove.sdk.v1"])
                break
            except OSError:
                await asyncio.sleep(0.2)
        else:
            return counts
        while not os.path.exists(stop_file):
            try:
                msg = await asyncio.wait_for(ws.read_message(), 0.5)
            except TimeoutError:
                continue
            if msg is None:
                break
            if isinstance(msg, str) and json.loads(msg)["op"] == "advertise":
                chans = json.loads(msg)["channels"]
                counts["channels"] += len(chans)
                ws.write_message(json.dumps({"op": "subscribe", "subscriptions": [
                    {"id": c["id"], "channelId": c["id"]} for c in chans]}))
            elif isinstance(msg, bytes):
                counts["messages"] += 1
                counts["bytes"] += len(msg)
        ws.close()
        return counts

    Path(result_file).write_text(json.dumps(asyncio.run(run())))


def _param(text: str) -> tuple[str, object]:
    name, _, value = text.partition("=")
    try:
        return name, json.loads(value)
    except json.JSONDecodeError:
        return name, value


def default_bag() -> Path:
    """The 600 s psce_rotations bag of the replay benchmarks (simulated once, cached)."""
    sys.path.insert(0, str(Path(__file__).parent))
    from psce_speed import ensure_bag

    return ensure_bag(600.0)


def load_loop(cmd: str, stop_file: str) -> None:
    """Child process: run ``cmd`` (a shell command) again and again until ``stop_file``."""
    import subprocess

    while not os.path.exists(stop_file):
        subprocess.run(cmd, shell=True, cwd=ROOT, stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL, check=False)


def busy_loop(stop_file: str) -> None:
    """Child process: a CPU-bound Python loop (a core's worth of load) until ``stop_file``."""
    n = 0
    while not os.path.exists(stop_file):
        for _ in range(200_000):
            n += 1


def load_stream(duration_s: float):
    """The messages to publish: (stamp_ns, kind, payload) in stamp order."""
    from mcap.reader import make_reader

    from stellar_cal_ros.io.bag import BagReader

    with BagReader(BAG) as r:
        imu = r.read_imu("/imu/data")
    start = int(imu.stamp_ns[0])
    end = start + int(duration_s * 1e9)
    ev = []
    sel = imu.stamp_ns < end
    dt = int(np.median(np.diff(imu.stamp_ns)))
    for s, w, f in zip(imu.stamp_ns[sel], imu.angular_velocity[sel],
                       imu.linear_acceleration[sel], strict=True):
        for ss in (int(s) - dt // 2, int(s)):
            ev.append((ss, "imu", (w, f)))
    with open(BAG, "rb") as fh:
        for _schema, ch, msg in make_reader(fh).iter_messages(ending_before=end):
            if ch.topic != "/imu/data":
                ev.append((msg.log_time, ch.topic, bytes(msg.data)))
    ev.sort(key=lambda e: e[0])
    return ev


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print the numbers."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0, help="bag seconds to play")
    ap.add_argument("--window", type=float, default=0.05, help="reorder_window_s")
    ap.add_argument("--bag", type=Path, help="bag to play (default: simulated 600 s)")
    ap.add_argument("--executor", choices=("single", "events"), default="single")
    ap.add_argument("--load", help="shell command run in a loop beside the node")
    ap.add_argument("--busy", type=int, default=0, metavar="N",
                    help="N processes of a busy Python loop beside the node (CPU load)")
    ap.add_argument("--node", choices=("calibrator", "echo"), default="calibrator",
                    help="echo: a node with the same topics and no work (the machine's tail)")
    ap.add_argument("--rt-priority", type=int, default=0,
                    help="run the calibrator process SCHED_FIFO at this priority (0: no)")
    ap.add_argument("--source-rt-priority", type=int, default=0, metavar="N",
                    help="run this process (the publisher and the residuals' subscriber) "
                         "SCHED_FIFO at N while playing (0: no)")
    ap.add_argument("--json", help="write the results here")
    ap.add_argument("--param", type=_param, action="append", default=[],
                    metavar="NAME=VALUE", help="a calibrator parameter (repeatable)")
    ap.add_argument("--watch", action="store_true",
                    help="with --param foxglove_port=N: a Foxglove client watches every channel")
    a = ap.parse_args(argv)
    global BAG
    BAG = a.bag or default_bag()
    prior = Path(str(BAG).removesuffix(".mcap") + ".prior.yaml")
    if not BAG.exists() or not prior.exists():
        print(f"{BAG} or {prior} missing", file=sys.stderr)
        return 2
    os.environ.setdefault("ROS_DOMAIN_ID", str(1 + (os.getpid() + 71) % 100))
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    prefix = "/bench" + uuid.uuid4().hex[:6]
    tmp = Path(tempfile.mkdtemp(prefix="node_latency_"))
    params = {"prior_file": str(prior), "reorder_window_s": a.window,
              "t0_imu_samples": 1000, "estimate_rate_hz": 1.0, "diagnostics_rate_hz": 1.0,
              **dict(a.param)}
    ctx = mp.get_context("spawn")
    child = ctx.Process(target=run_calibrator, args=(prefix, params, str(tmp / "res.json"),
                                                      str(tmp / "stop"), a.executor,
                                                      a.rt_priority, a.node))
    child.start()
    watcher = None
    if a.watch and params.get("foxglove_port"):
        watcher = ctx.Process(target=watch_foxglove, args=(
            int(params["foxglove_port"]), str(tmp / "stop_watch"), str(tmp / "watch.json")))
        watcher.start()
    loader = None
    if a.load:
        loader = ctx.Process(target=load_loop, args=(a.load, str(tmp / "stop_load")))
        loader.start()
    busy = [ctx.Process(target=busy_loop, args=(str(tmp / "stop_load"),))
            for _ in range(a.busy)]
    for b in busy:
        b.start()
    stream = load_stream(a.duration)

    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import FluidPressure, Imu, NavSatFix, Temperature
    from stellar_cal_msgs.msg import StarCentroidArray, StarResidualArray

    if a.source_rt_priority:  # after the children started (they must not inherit it);
        # before rclpy.init, so that the DDS threads of this process inherit it
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(a.source_rt_priority))
    rclpy.init()
    node = rclpy.create_node("bench_source" + prefix.replace("/", "_"))
    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    types = {"/star_tracker/stars": StarCentroidArray, "/gnss/fix": NavSatFix,
             "/star_tracker/temperature": Temperature, "/environment/temperature": Temperature,
             "/environment/pressure": FluidPressure}
    pubs = {t: node.create_publisher(c, prefix + t, qos) for t, c in types.items()}
    p_imu = node.create_publisher(Imu, prefix + "/imu/data", qos)
    sent: dict[int, float] = {}
    e2e: list[tuple[int, float]] = []
    pub_t: dict[int, float] = {}  # every message's publication (perf_counter), by stamp
    pub_done: dict[int, float] = {}  # ... and the return of its publish() call
    lag: list[float] = []  # publication − its real-time target, s (the publisher behind)
    rx: dict[int, float] = {}

    def on_res(msg) -> None:
        s = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        if s in sent and msg.dof > 0:
            rx[s] = time.perf_counter()
            e2e.append((s, (rx[s] - sent.pop(s)) * 1e3))

    node.create_subscription(StarResidualArray,
                             f"/calibrator{prefix.replace('/', '_')}/residuals", on_res, qos)
    from rclpy.executors import SingleThreadedExecutor

    ex = SingleThreadedExecutor()
    ex.add_node(node)
    deadline = time.monotonic() + 30
    while p_imu.get_subscription_count() == 0 and time.monotonic() < deadline:
        ex.spin_once(timeout_sec=0.05)
    print(f"playing {a.duration:.0f} s in real time: {len(stream)} messages "
          f"(IMU 200 Hz, stars 2 Hz) …", flush=True)
    cpu0 = _cpu_times()
    t_first = stream[0][0]
    wall0 = time.perf_counter()
    imu = Imu()
    imu.header.frame_id = "imu_link"
    for stamp, kind, payload in stream:
        target = wall0 + (stamp - t_first) * 1e-9
        while True:
            d = target - time.perf_counter()
            if d <= 0:
                break
            ex.spin_once(timeout_sec=min(d, 0.002))
        if kind == "imu":
            w, f = payload
            imu.header.stamp.sec, imu.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
            imu.angular_velocity.x, imu.angular_velocity.y, imu.angular_velocity.z = map(
                float, w)
            (imu.linear_acceleration.x, imu.linear_acceleration.y,
             imu.linear_acceleration.z) = map(float, f)
            pub_t[stamp] = t = time.perf_counter()
            p_imu.publish(imu)
        else:
            pub_t[stamp] = t = time.perf_counter()
            if kind == "/star_tracker/stars":
                sent[stamp] = t
            pubs[kind].publish(payload)
        pub_done[stamp] = time.perf_counter()
        lag.append(t - target)
    end = time.perf_counter() + 1.0
    while time.perf_counter() < end:
        ex.spin_once(timeout_sec=0.05)
    wall = time.perf_counter() - wall0
    cpu1 = _cpu_times()
    if a.source_rt_priority:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    (tmp / "stop_load").touch()
    (tmp / "stop_watch").touch()
    if watcher is not None:
        watcher.join(30)
    (tmp / "stop").touch()
    for b in busy:
        b.join(30)
    if loader is not None:
        loader.join(300)
    child.join(60)
    if not (tmp / "res.json").exists():
        print(f"the node process left no results (exit code {child.exitcode}; its errors are "
              "above)", file=sys.stderr)
        return 1
    res = json.loads((tmp / "res.json").read_text())
    node.destroy_node()
    rclpy.try_shutdown()

    lat = np.asarray(res["latency_ms"])
    lat_cpu = np.asarray(res.get("latency_cpu_ms", []))
    # steady state: frames after the start-up (t0 needs t0_imu_samples, then attitude init)
    settle_ns = t_first + int(10e9)
    e2e_a = np.asarray([x for s, x in e2e if s >= settle_ns])
    per_core = [100.0 * (b1 - b0) / max(t1 - t0, 1) for (b0, t0), (b1, t1) in
                zip(cpu0, cpu1, strict=True)]
    out = {
        "frames_updated": res["updates"],
        "frames_in_latency_stats": int(len(lat)),
        "backlog_updates_at_startup": res["backlog_updates"],
        "compute_latency_ms": {"p50": float(np.percentile(lat, 50)),
                               "p99": float(np.percentile(lat, 99)),
                               "max": float(lat.max())},
        # steady state: the first updates after the attitude initialization re-linearize
        # (iterated EKF, up to 5 predictions) while the datasheet prior is pixels off
        "compute_latency_ms (after the first 20 updates)": {
            "p50": float(np.percentile(lat[20:], 50)), "p99": float(np.percentile(lat[20:], 99)),
            "max": float(lat[20:].max())} if len(lat) > 20 else None,
        # thread CPU time of the same intervals (wall − CPU: preempted, or blocked in DDS)
        "compute_cpu_ms": {"p50": float(np.percentile(lat_cpu, 50)),
                           "p99": float(np.percentile(lat_cpu, 99)),
                           "max": float(lat_cpu.max())} if len(lat_cpu) else None,
        "end_to_end_latency_ms (after 10 s)": {"p50": float(np.percentile(e2e_a, 50)),
                                  "p99": float(np.percentile(e2e_a, 99)),
                                  "max": float(e2e_a.max())} if len(e2e_a) else None,
        "calibrator_cpu_percent_of_one_core": 100.0 * res["cpu_s"] / res["wall_s"],
        "per_core_load_percent": per_core,
        "cores": os.cpu_count(),
        "reorder_window_s": a.window,
        "executor": a.executor,
        "rt_priority": a.rt_priority,
        "source_rt_priority": a.source_rt_priority,
        "load": a.load or "",
        "bag": BAG.name,
        "received": res["received"],
        "wall_s": wall,
        "params": dict(a.param),
    }
    out["tail"] = _tail_report(res.get("marks") or [])
    out["node"] = a.node
    out["busy"] = a.busy
    lag_ms = np.asarray(lag) * 1e3
    out["publisher_lag_ms"] = {"p50": float(np.percentile(lag_ms, 50)),
                               "p99": float(np.percentile(lag_ms, 99)),
                               "max": float(lag_ms.max())}
    out["split"] = _split_report(res, pub_t, pub_done, rx, settle_ns)
    long_cb: dict[str, list[float]] = {}  # the node's callbacks over 1 ms, by what ran
    for name, b0, b1 in res.get("busy") or []:  # (after the first 10 s, as the split)
        if b1 - b0 > 1e-3 and b0 >= wall0 + 10.0:
            long_cb.setdefault(name, []).append((b1 - b0) * 1e3)
    out["callbacks_over_1ms"] = {k: {"n": len(v), "max_ms": max(v)} for k, v in
                                 sorted(long_cb.items())}
    ticks = res.get("view_ticks") or []
    if res.get("view_counts") is not None:
        views = [ms for ms, field in ticks if not field]
        fields = [ms for ms, field in ticks if field]
        out["view"] = {**res["view_counts"],
                       "view_tick_ms": {"p50": float(np.median(views)),
                                        "max": float(max(views))} if views else None,
                       "field_ms": {"p50": float(np.median(fields)),
                                    "max": float(max(fields))} if fields else None}
    if watcher is not None and (tmp / "watch.json").exists():
        out["foxglove_client"] = json.loads((tmp / "watch.json").read_text())
    print(json.dumps(out, indent=1))
    sp = out["split"]
    if sp:
        print(f"end-to-end split over {sp['frames']} frames (ms, p50 / p99 / max): " + "; ".join(
            f"{k} {sp[k]['p50']:.2f} / {sp[k]['p99']:.2f} / {sp[k]['max']:.2f}"
            for k in ("e2e", "wait", "publish", "queue", "compute", "deliver", "busy_ms")))
        print("  tail frames: " + " | ".join(
            f"e2e {r['e2e']:.1f} = wait {r['wait']:.1f} + publish {r['publish']:.1f} + queue "
            f"{r['queue']:.1f} (busy "
            f"{r['busy_ms']:.1f} {','.join(r['busy']) or '-'}) + compute {r['compute']:.2f} "
            f"+ deliver {r['deliver']:.1f}" for r in sp["tail"]))
    ck = [(b1 - b0) * 1e3 for name, b0, b1 in res.get("busy") or []
          if name == "periodic_checkpoint"]
    if ck:
        ck_cpu = res.get("checkpoint_cpu_ms") or [float("nan")]
        wr = [(b1 - b0) * 1e3 for b0, b1 in res.get("checkpoint_writes") or []]
        out["checkpoint_callback_ms"] = {"n": len(ck), "p50": float(np.median(ck)),
                                         "max": float(max(ck)),
                                         "thread_cpu_p50": float(np.median(ck_cpu)),
                                         "thread_cpu_max": float(max(ck_cpu))}
        out["checkpoint_write_ms"] = {"n": len(wr), "p50": float(np.median(wr)),
                                      "max": float(max(wr))} if wr else None
        bc = sp.get("behind_checkpoint") or {"frames": 0, "queue_max": 0.0, "busy_max": 0.0}
        print(f"periodic checkpoint in the executor: {len(ck)} callbacks, p50 "
              f"{np.median(ck):.2f} ms, max {max(ck):.2f} ms (thread CPU p50 "
              f"{np.median(ck_cpu):.2f}, max {max(ck_cpu):.2f} ms); file writes "
              + (f"p50 {np.median(wr):.1f} ms, max {max(wr):.1f} ms" if wr else "-")
              + f"; {bc['frames']} frames waited behind one (queue max "
              f"{bc['queue_max']:.1f} ms, of it checkpoint and other callbacks "
              f"{bc['busy_max']:.1f} ms)")
    if out["callbacks_over_1ms"]:
        print("node callbacks over 1 ms after 10 s (count, max ms): " + ", ".join(
            f"{k} {v['n']} ({v['max_ms']:.1f})" for k, v in out["callbacks_over_1ms"].items()))
    pl = out["publisher_lag_ms"]
    print(f"publisher behind its real-time schedule (ms): p50 {pl['p50']:.2f}, "
          f"p99 {pl['p99']:.2f}, max {pl['max']:.2f}")
    ok = out["compute_latency_ms"]["p99"] <= TARGET_P99_MS
    print(f"compute latency p50 {out['compute_latency_ms']['p50']:.2f} ms, "
          f"p99 {out['compute_latency_ms']['p99']:.2f} ms (target ≤ {TARGET_P99_MS} ms: "
          f"{'met' if ok else 'NOT met'})")
    steady = out["compute_latency_ms (after the first 20 updates)"]
    if steady:
        print(f"after the first 20 updates: p50 {steady['p50']:.2f} ms, "
              f"p99 {steady['p99']:.2f} ms, max {steady['max']:.2f} ms")
    if out["compute_cpu_ms"]:
        print(f"compute thread CPU p50 {out['compute_cpu_ms']['p50']:.2f} ms, "
              f"p99 {out['compute_cpu_ms']['p99']:.2f} ms")
    e2e_s = out["end_to_end_latency_ms (after 10 s)"]
    if e2e_s:
        print(f"end-to-end p50 {e2e_s['p50']:.1f} ms, p99 {e2e_s['p99']:.1f} ms")
    print(f"calibrator CPU {out['calibrator_cpu_percent_of_one_core']:.1f} % of one core; "
          f"per-core load " + ", ".join(f"{x:.0f} %" for x in per_core)
          + f"; load average {os.getloadavg()[0]:.2f}")
    tail = out["tail"]
    if tail:
        print(f"the {tail['tail_frames']} frames at/above p99 ("
              + ", ".join(f"{x:.2f}" for x in tail["tail_ms"]) + " ms) ran: "
              + ", ".join(f"{k} {tail[k]['in_tail']}" for k in (
                  "gc_any", "gc_gen2", "cov_check", "imu_trim", "gyro_judge"))
              + "; over all frames: " + ", ".join(
                  f"{k} {tail[k]['frames']} (median {tail[k]['median_ms'] or 0:.2f} ms)"
                  for k in ("gc_any", "cov_check", "imu_trim")))
    v = out.get("view")
    if v:
        def fmt(d: dict | None) -> str:
            return f"p50 {d['p50']:.2f} / max {d['max']:.2f} ms" if d else "-"

        print(f"live view: {v['views']} ~/view ({fmt(v['view_tick_ms'])} thread CPU a tick), "
              f"{v['fields']} ~/residual_field ({fmt(v['field_ms'])}), "
              f"{v['fields_skipped']} skipped"
              + (f"; Foxglove client got {out['foxglove_client']['messages']} messages"
                 if "foxglove_client" in out else ""))
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
