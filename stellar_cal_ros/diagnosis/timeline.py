"""A timeline of a diagnosis's runs, for measuring its schedule on a loaded machine.

Off unless the environment variable :data:`ENV` names a file.  Then every process of the
command (the parent and each Dask worker; they inherit the environment) appends one JSON
line per event to that file:

* ``{"kind": "task", "pid", "key", "batch", "start", "end", "cpu", "read", "thread"}`` --
  one run or one statistic of the bag, where it ran: wall start/end (``time.time``), the
  CPU seconds of the process that ran it meanwhile (``time.process_time``: all its
  threads), of which ``read`` reading the bag, and of the thread that ran it alone
  (``thread``: a Dask worker's other threads, its event loop, are in ``cpu`` only);
* ``{"kind": "process", "pid", "created", "start", "cpu"}`` -- a process's first task:
  its creation time and the CPU it had used before it (imports, a worker's start);
* ``{"kind": "batch", "pid", "batch", "submit", "done", "cpu0", "cpu1", "wait"}`` -- the
  parent handing out a batch of runs and having the results it waits for (``wait``: their
  keys; runs made ahead are not waited for); ``cpu0``/``cpu1``: the parent's CPU then;
* ``{"kind": "end", "pid", "time", "cpu"}`` -- the parent closing its runner.

CPU seconds do not depend much on the load beside the command, wall seconds do: the
benchmark ``benchmarks/round_timeline.py`` replays the recorded schedule with each piece
of work lasting its CPU seconds, giving the command's time on idle cores.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from typing import Any

#: the environment variable naming the timeline file (unset: no timeline)
ENV = "STELLAR_CAL_TIMELINE"

_STARTED: set[int] = set()


def enabled() -> bool:
    """Whether a timeline is being written."""
    return bool(os.environ.get(ENV))


def write(event: dict[str, Any]) -> None:
    """Append ``event`` (with this process's id) to the timeline file."""
    path = os.environ.get(ENV)
    if not path:
        return
    event = {"pid": os.getpid(), **event}
    with open(path, "a", encoding="utf-8") as f:  # one short line: appended whole
        f.write(json.dumps(event) + "\n")


def _first_task() -> None:
    pid = os.getpid()
    if pid in _STARTED:
        return
    _STARTED.add(pid)
    try:
        import psutil

        created = psutil.Process(pid).create_time()
    except Exception:  # pragma: no cover - psutil is a dependency
        created = None
    write({"kind": "process", "created": created, "start": time.time(),
           "cpu": time.process_time()})


def traced(key: str, batch: int, bag: Any, fn: Callable[..., Any], *args: Any) -> Any:
    """``fn(bag, *args)``, recorded as task ``key`` of ``batch`` when a timeline is on."""
    if not enabled():
        return fn(bag, *args)
    from stellar_cal_ros.diagnosis.runstats import load_bag

    _first_task()
    start, cpu, own = time.time(), time.process_time(), time.thread_time()
    load_bag(bag)  # read here (once per process) to count it apart from the run
    read = time.process_time() - cpu
    try:
        return fn(bag, *args)
    finally:
        write({"kind": "task", "key": key, "batch": batch, "start": start,
               "end": time.time(), "cpu": time.process_time() - cpu, "read": read,
               "thread": time.thread_time() - own})


class Batches:
    """The parent's side: numbers its batches and records when each is handed out and done."""

    def __init__(self) -> None:
        self.n = 0

    def open(self) -> tuple[int, float, float]:
        """A new batch's number, wall time and the parent's CPU."""
        self.n += 1
        return self.n, time.time(), time.process_time()

    def close(self, batch: tuple[int, float, float], wait: list[str]) -> None:
        """Record ``batch`` (from :meth:`open`) as done, having waited for ``wait``."""
        n, submit, cpu0 = batch
        write({"kind": "batch", "batch": n, "submit": submit, "done": time.time(),
               "cpu0": cpu0, "cpu1": time.process_time(), "wait": list(wait)})

    @staticmethod
    def end() -> None:
        """Record the end of the runner (its parent's last CPU)."""
        write({"kind": "end", "time": time.time(), "cpu": time.process_time()})
