"""Run the re-runs of a diagnosis round concurrently: in this process, or on Dask.

:func:`open_runner` returns a :class:`Runs` bound to one bag and one method.  Its
:meth:`Runs.map` takes a list of :class:`Task` (a prior and an effect list) and yields each
run's :class:`~stellar_cal_ros.diagnosis.runstats.RunSummary` as it finishes.

Executors
---------
``workers=0`` or ``1``
    in this process, one run after the other (the Python API's default; tests).  A
    one-worker cluster would run the same runs one after the other while adding its own
    processes: on a 2-h round 71 CPU-s instead of 49 (measured, doc/benchmarks.md).
``workers=N`` (N ≥ 2)
    a ``dask.distributed.LocalCluster`` of N single-threaded worker *processes* (the
    Kalman filters are pure-Python loops: threads would serialize on the GIL).  The
    parent hands each run out when a worker is free, the highest priority (the longest
    expected run) first (:class:`_Hand`): Dask alone places a task when it is submitted.
``workers=None`` (the command line's default: automatic)
    in this process until a batch of runs would take at least :data:`CLUSTER_PAYS_S`
    CPU seconds one after the other (the batch's runs × the mean CPU time of the runs made
    so far here), then a local cluster of one worker per core (at most 16) for that batch
    and every later one.  The workers are forked from multiprocessing's fork server where
    the platform has one (:func:`start_method`: Linux; :func:`local_cluster`): a fresh
    single-threaded process that imports the package and reads the bag once
    (:mod:`~stellar_cal_ros.diagnosis.worker_start`), so they start holding both (not a
    fork of this process, which runs Dask's event-loop thread); each loads the compiled
    kernels at its first run.  Spawned, each imports the package, loads the kernels and
    reads the bag (measured, doc/benchmarks.md), and the rule asks for
    :data:`CLUSTER_PAYS_SPAWNED_S`.  Besides the start, Dask's scheduler and client take
    the parent's CPU while it waits (its timers slowed down: :data:`LOCAL_DASK_CONFIG`),
    and runs side by side take more CPU each; a round of
    a few short runs (a ``diagnose`` near the model) is done sooner in this process.  On
    a machine of at most :data:`IN_PROCESS_CORES` cores: in this process (two workers
    and the parent share two cores: measured, a round of ten re-runs gains at most
    1.1-1.4x on idle cores for +70 % CPU and +700 MB, and loses wall time beside any
    other job).
``scheduler=ADDRESS``
    an existing Dask cluster (``tcp://host:8786``): the user's cluster, its workers as
    they are.

How the bag reaches the workers
-------------------------------
A bag given by path is sent as the path: each worker reads it once and caches it (a
worker process keeps one bag; local workers start with it, read once by the fork server,
or by this process before a ``fork``).  The parent first asks every worker for the file's size;
when a worker cannot see the file (no shared filesystem) the bag's *bytes* are scattered
to all workers once (``Client.scatter(broadcast=True)``) and each worker parses its copy —
the parent never pickles a parsed bag.  A bag already in memory
(:class:`~stellar_cal_ros.methods.replay.BagData`, from a simulation) is scattered the same
way.  Workers return statistics only, never a filter or a residual table (except for the
runs that ask for one, see :class:`Task`).
"""

from __future__ import annotations

import contextlib
import heapq
import itertools
import logging
import os
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from stellar_cal_ros.core.memory import frozen_objects, trim_freed
from stellar_cal_ros.diagnosis import timeline
from stellar_cal_ros.diagnosis.runstats import (
    BagBytes,
    BagRef,
    RunSummary,
    bag_facts,
    evaluate,
    forget_bags,
    forget_held_prepared,
    forget_prepared,
)
from stellar_cal_ros.diagnosis.warm_up import WORKER_WARM_ENV
from stellar_cal_ros.errors import StellarCalError
from stellar_cal_ros.io.calibration import Calibration
from stellar_cal_ros.methods.replay import BagData

log = logging.getLogger(__name__)

#: the default number of local workers is one per core, up to this (a round has ~10-20
#: runs, and each worker holds the bag)
MAX_DEFAULT_WORKERS = 16
#: ``workers=None`` on a machine of at most this many cores: in this process (measured on
#: 2 cores, doc/benchmarks.md "the second worker's start, the critical path")
IN_PROCESS_CORES = 2
#: ``workers=None``: a batch of runs goes to a (then started) local cluster when it would
#: take at least this many CPU seconds in this process (see the module's doc).  A batch of
#: C CPU-s gains wall time on N workers when C > S / (1 - k/N), S the cluster's start (wall
#: until every worker holds the bag) and k the runs' CPU on N busy workers against here.
#: With workers forked from this process (``fork``, a user's choice: :func:`start_method`).
#: Measured on 2 cores (doc/benchmarks.md "forked workers"): forked workers S 0.9-1.8 s, k
#: 1.1-1.6 (load 10-18; 1.17-1.36 at lower load): C* <= 8.6 s on 2 workers, ~3 s on 4
CLUSTER_PAYS_S = 10.0
#: :data:`CLUSTER_PAYS_S` where the workers are spawned (macOS, Windows) or forked from the
#: fork server (Linux's default, :func:`start_method`): the package imported and the bag
#: read in a fresh process before the first worker holds it, S ~5 s on idle cores (spawned),
#: the fork server's start as long at 2.8 against 3.0 CPU-s (doc/benchmarks.md, H109)
CLUSTER_PAYS_SPAWNED_S = 20.0
#: priority of :meth:`Runs.on_bag` in the parent's queue (:class:`_Hand`; a run's is
#: 100 × its cost): a small statistic of the bag that the diagnosis waits for goes before
#: the runs queued ahead of need
ON_BAG_PRIORITY = 1_000_000
#: priority below every run waited for, of a run made ahead of need
#: (:meth:`Runs.run_ahead`): a free worker takes it, a worker with a run someone waits for
#: (a screening part beside the base run) does that first (measured: an ML run ahead taken
#: before the second screening part held the round up by its length)
AHEAD_PRIORITY = -1_000_000
#: priority of :meth:`Runs.spare`: below every run, waited for or ahead (a run ahead's is
#: :data:`AHEAD_PRIORITY` + 100 × its cost, its cost at least 0)
SPARE_PRIORITY = AHEAD_PRIORITY - 1
#: priority of a :meth:`Runs.spare` piece asked for while still queued: the parent waits
#: for it now, so it goes before everything queued, a statistic started earlier too
ASKED_PRIORITY = ON_BAG_PRIORITY + 1


@dataclass
class Task:
    """One run: the method's baseline plus ``effects``, started from ``prior``.

    Two tasks are equal when they are the same run: every field but the name ``key`` and
    the ``cost`` estimate (the prior compared as an object: ``Calibration`` has no value
    equality), so a field added here counts unless it is marked ``compare=False``.
    """

    key: str = field(compare=False)
    prior: Calibration
    effects: tuple[str, ...]
    keep_residuals: bool = False
    #: expected relative run time: longer runs are started first
    cost: float = field(default=1.0, compare=False)
    #: candidates this run scores (a screening run, :mod:`~stellar_cal_ros.diagnosis.screening`)
    screen: tuple[str, ...] = ()
    candidate: bool = False  #: an augmented run (its data faults are flagged, not raised)
    #: the noise scales the run uses (:class:`~stellar_cal_ros.core.noise.NoiseScales`)
    noise: Any = None
    #: measure the stars' noise on this run's residuals (:mod:`~.noise`)
    star_noise: bool = False
    #: run the gyro-against-stars check (False: a re-run whose counters nobody reads, of a
    #: bag a run of the same diagnosis has judged: the noise scales' ML runs)
    gyro_check: bool = True
    #: keep the run's log-likelihood frame by frame (:attr:`RunSummary.frame_loglik`: the
    #: IMU noise search's sandwich σ; a few numbers a frame)
    frame_loglik: bool = False


#: runs ahead of need (:meth:`Runs.run_ahead`): the tasks, or a function returning them
Ahead = list[Task] | tuple[Task, ...] | Callable[[], list[Task]]


#: :meth:`Runs.run_ahead`'s ``then``: the runs ahead a finished run's result asks for
Then = Callable[[Task, RunSummary], list[Task]]


def _tasks(ahead: Ahead) -> list[Task]:
    return list(ahead()) if callable(ahead) else list(ahead)


def user_effect_classes() -> tuple[type, ...]:
    """Registered effect classes that a fresh worker process would not know."""
    from stellar_cal_ros.effects import registry

    return tuple(cls for cls in registry.EFFECTS.values() if not registry.is_library(cls))


def _on_bag(bag: BagRef, fn: Callable[..., Any], *args: Any) -> Any:
    from stellar_cal_ros.diagnosis.runstats import load_bag

    return fn(load_bag(bag), *args)


def _run(key: str, batch: int, bag: BagRef, fn: Callable[..., Any], *args: Any) -> Any:
    """``fn(bag, *args)`` where it runs (a worker, or here): on the timeline when it is on.

    Then the heap's pages the run freed go back to the system (:func:`~stellar_cal_ros.
    core.memory.trim_freed`): the next run's arrays are not held beside them.
    """
    try:
        return timeline.traced(key, batch, bag, fn, *args)
    finally:
        trim_freed()


#: environment override of how the local cluster's workers start: ``forkserver``, ``fork``
#: or ``spawn`` (else :func:`start_method` decides)
START_ENV = "STELLAR_CAL_WORKER_START"
#: Dask's own key (and its environment form) for the same choice, honoured when set
DASK_START_KEY = "distributed.worker.multiprocessing-method"
DASK_START_ENV = "DASK_DISTRIBUTED__WORKER__MULTIPROCESSING_METHOD"


def start_method() -> str:
    """How the local cluster's worker processes start.

    ``forkserver`` where the platform has it (Linux), else ``spawn`` (macOS and Windows,
    where forking is unsafe or missing).  The fork server is a fresh single-threaded
    process that imports the package (and reads the bag: :func:`local_cluster`) once;
    every worker is forked from it, holding them.  Forking *this* process (``fork``) gave
    the same start but copies a process that runs threads (Dask's event loop, which starts
    the workers; a lock one of them holds stays locked in the child).  Measured on 2 cores
    (``benchmarks/cluster_start.py``, doc/benchmarks.md).

    A user's choice goes first: :data:`START_ENV`, then Dask's
    ``distributed.worker.multiprocessing-method`` when it is set (its environment variable
    :data:`DASK_START_ENV`, or a value other than Dask's default ``spawn``).
    """
    import multiprocessing
    import sys

    have = multiprocessing.get_all_start_methods()
    asked = os.environ.get(START_ENV, "").strip() or _dask_start_method()
    if asked:
        if asked not in have:
            raise StellarCalError(f"the workers cannot start by {asked!r} here "
                                  f"({START_ENV} or {DASK_START_KEY}): one of "
                                  f"{', '.join(have)}")
        return asked
    if sys.platform.startswith("linux") and "forkserver" in have:
        return "forkserver"
    return "spawn"


def _dask_start_method() -> str:
    """Dask's ``multiprocessing-method`` where a user set it, else ``""``."""
    import dask

    try:
        import distributed  # noqa: F401  (its defaults are in the config from its import)
    except ImportError:  # pragma: no cover - a dependency of the package
        pass
    value = str(dask.config.get(DASK_START_KEY, "") or "")
    return value if (DASK_START_ENV in os.environ or value not in ("", "spawn")) else ""


#: the fork server's bag: :mod:`~stellar_cal_ros.diagnosis.worker_start` reads it
WORKER_BAG_ENV = "STELLAR_CAL_WORKER_BAG"


#: Dask's settings for the diagnosis' local cluster (read when its scheduler, nannies and
#: workers start; a user's scheduler is left as it is).  The scheduler and one nanny per
#: worker run in this process's event loop, which Dask wakes on timers whatever the work:
#: at its defaults an idle two-worker cluster took 32-42 ms of the parent's CPU per second
#: of wall (2 cores, load 6-9; 5-9 CPU-s of a several round's 200-630 s), 5-6 ms with these
#: (measured, doc/benchmarks.md "the parent's Dask CPU").  None of them changes a result:
#:
#: * no statistical profiler in the workers: it samples the running filter's stack every
#:   10 ms of *wall* time, for a dashboard nobody opens here;
#: * the event loop's health tick (a warning after 3 s unresponsive) every 1 s, not 20 ms,
#:   in each of the scheduler, the nannies and the workers;
#: * the system monitor (CPU, memory, I/O for the dashboard) every 5 s, not 0.5 s;
#: * memory checked every 1 s, not 0.1 s (the nanny restarts a worker past 95 % of its
#:   share of the machine's memory; a run's memory grows over seconds, not tenths);
#: * no work stealing: :class:`_Hand` hands a piece out only to a free thread, so nothing
#:   waits at a busy worker to be stolen (its 1 s timer went over every worker's queue);
#: * no active memory manager: the one scattered object (a bag in memory,
#:   :meth:`DaskRuns._place_bag`) is on every worker on purpose (``broadcast=True``); the
#:   manager's replica reduction drops such copies every 2 s (Dask's ``Client.scatter``
#:   asks for it off with ``broadcast=True``), to be sent again to the next run's worker.
LOCAL_DASK_CONFIG = {
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "5s",
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.scheduler.work-stealing": False,
    "distributed.scheduler.active-memory-manager.start": False,
}


def local_cluster(n: int, bag: BagRef | None = None, method: str | None = None,
                  warm: str | None = None, steal: bool = False):
    """A ``LocalCluster`` of ``n`` single-threaded worker processes started by ``method``.

    The one local cluster of the package (the diagnosis', a campaign's:
    :func:`~stellar_cal_ros.campaign.runner.dask_client`), with
    :data:`LOCAL_DASK_CONFIG`'s timers.  ``steal``: work stealing on, for the tasks given to
    the scheduler at once (a campaign's runs, ``Client.map``): a run placed behind a longer
    one at a busy worker moves to a free one (the diagnosis hands a piece only to a free
    thread, :class:`_Hand`).

    ``method``: :func:`start_method`'s unless given.  ``forkserver``: the fork server
    preloads :mod:`~stellar_cal_ros.diagnosis.worker_start` (the package's imports and,
    for a ``bag`` given by path, the bag; the numba kernels of the filter method ``warm``,
    compiled or loaded once: :mod:`~stellar_cal_ros.diagnosis.warm_up`), so each worker
    starts holding them as a forked one did.  ``fork``: a bag given by path is read here
    first (the workers inherit it).  The server starts with the first cluster of this
    process and serves the later ones of the same bag and ``warm`` (a server started for
    others is restarted).
    """
    import dask
    from distributed import LocalCluster

    method = method or start_method()
    if method == "fork" and isinstance(bag, str):
        from stellar_cal_ros.diagnosis.runstats import load_bag

        load_bag(bag)  # read once here: every worker is forked holding it
    config = {**LOCAL_DASK_CONFIG, DASK_START_KEY: method}
    if steal:
        config["distributed.scheduler.work-stealing"] = True
    with dask.config.set(config), \
            _server_bag(method, bag, warm):
        if method == "forkserver":
            _preload_package()
            _server_for(bag, warm)
        return LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                            dashboard_address=":0", silence_logs=logging.ERROR)


def _preload_package() -> None:
    """Add :mod:`~stellar_cal_ros.diagnosis.worker_start` to the fork server's preload.

    Dask sets its own list (``distributed`` and its dependencies) the first time it asks
    for the context; asked here first, then extended.
    """
    import multiprocessing.forkserver as fs

    from distributed.utils import get_mp_context

    get_mp_context()  # Dask's preload list, set once
    have = list(getattr(fs._forkserver, "_preload_modules", None) or [])
    mine = "stellar_cal_ros.diagnosis.worker_start"
    if mine not in have:
        fs.set_forkserver_preload(have + [mine])


#: the bag the running fork server read (``(path, size, mtime)``) and the method it warmed up
#: (None: none, or a server this module did not start)
_SERVER_BAG: list[tuple | None] = [None]


def _server_for(bag: BagRef | None, warm: str | None = None) -> None:
    """Stop a running fork server that does not hold ``bag`` (a path) and ``warm``'s kernels.

    A server reads its bag and warms its kernels up when it starts; one started for another
    bag or method (or by another user of the fork server, without the package's preload)
    would leave every worker to read the bag, or compile or load the kernels, itself.
    """
    import multiprocessing.forkserver as fs

    key = (_bag_key(bag), warm)
    server = fs._forkserver
    if getattr(server, "_forkserver_pid", None) is not None and _SERVER_BAG[0] != key:
        try:
            server._stop()
        except Exception:  # noqa: BLE001 - multiprocessing internals: the workers read it
            log.debug("the fork server was not restarted", exc_info=True)
            return
    _SERVER_BAG[0] = key


def _bag_key(bag: BagRef | None) -> tuple | None:
    if not isinstance(bag, str):
        return None
    try:
        st = os.stat(bag)
    except OSError:
        return None
    return (bag, st.st_size, st.st_mtime_ns)


@contextlib.contextmanager
def _server_bag(method: str, bag: BagRef | None, warm: str | None = None):
    """The bag's path and the method to warm up in the environment while a fork server may start.

    :data:`WORKER_BAG_ENV` (a bag given by path) and :data:`WORKER_WARM_ENV` (``warm``).
    """
    if method != "forkserver":
        yield
        return
    setting = {WORKER_BAG_ENV: bag if isinstance(bag, str) else None, WORKER_WARM_ENV: warm}
    was = {name: os.environ.get(name) for name in setting}
    for name, value in setting.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value
    try:
        yield
    finally:
        for name, value in was.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def _file_size(path: str) -> int:
    try:
        return os.stat(path).st_size
    except OSError:
        return -1


class Runs:
    """Runs of one method on one bag (in this process)."""

    workers = 1
    description = "in this process"

    def __init__(self, bag: BagRef, spec, fraction: float) -> None:
        self.bag = str(Path(bag).resolve()) if isinstance(bag, (str, Path)) else bag
        #: what reading the bag passed over (``on_error="skip"``, :meth:`BagReader.losses`)
        self.losses: dict[str, Any] = dict(getattr(bag, "losses", None) or {})
        self.spec = spec
        self.fraction = fraction
        self.classes = user_effect_classes()
        #: the noise scales every run uses unless its task says otherwise (set by the
        #: diagnosis once it has measured them, :mod:`~stellar_cal_ros.diagnosis.noise`)
        self.noise = None
        #: the latest noise verdict of the diagnosis using these runs
        self.verdict = None
        #: runs made ahead of need (:meth:`run_ahead`): (task, its noise, stats or a future)
        self._ahead: list[tuple[Task, Any, Any]] = []
        #: :meth:`on_bag`'s results by ``(fn, args)``: a statistic of the bag is computed once
        self._of_bag: dict[tuple, Any] = {}
        #: the batches of runs handed out (:mod:`~stellar_cal_ros.diagnosis.timeline`)
        self._batches = timeline.Batches()

    def noise_of(self, task: Task):
        """The noise scales ``task`` runs with."""
        return task.noise if task.noise is not None else self.noise

    def facts(self) -> dict[str, Any]:
        """Applicability facts of the bag (site, head temperature, frames, duration)."""
        batch = self._batches.open()
        try:
            return _run("facts", batch[0], self.bag, bag_facts)
        finally:
            self._batches.close(batch, ["facts"])

    def on_bag(self, fn: Callable[..., Any], *args: Any) -> Any:
        """``fn(bag_data, *args)`` where the bag is (a worker; the parent never reads it).

        For small statistics of the bag itself (``args`` hashable): computed once per
        ``(fn, args)``, however many steps (the noise's first runs, its measurement, each
        round) ask for it; with unhashable ``args`` (a calibration) computed every time.
        """
        key = (fn, args)
        try:
            hash(key)
        except TypeError:
            return self._compute_on_bag(fn, *args)
        if key not in self._of_bag:
            self._of_bag[key] = self._compute_on_bag(fn, *args)
        return self._of_bag[key]

    def on_bag_soon(self, fn: Callable[..., Any], *args: Any) -> None:
        """Start :meth:`on_bag` ``(fn, *args)`` now where a worker is free; ask for it later.

        On a cluster the statistic goes before any queued run, beside the runs handed out
        next (a later :meth:`on_bag` of the same ``(fn, args)`` waits for it); in this
        process, or with unhashable ``args``, nothing happens now (it is computed when
        asked for).
        """

    def later(self, fn: Callable[..., Any], *args: Any) -> Callable[[], Any]:
        """``fn(bag_data, *args)`` as a function to call when its value is needed.

        On a cluster the computation starts now (beside whatever the parent waits for
        next; a value nobody asks for is dropped, a computation already started runs to its
        end); in this process it runs when the value is asked for.  Not cached.
        """
        return lambda: self._compute_on_bag(fn, *args)

    def spare(self, fn: Callable[..., Any], *args: Any) -> Spare:
        """:meth:`later` for a value the caller may not ask for: started when a worker is spare.

        On a cluster it goes out once no other work is queued (:data:`SPARE_PRIORITY`: a
        worker that would idle at a batch's end takes it; asked for while still queued, it
        goes out next, :data:`ASKED_PRIORITY`), and the returned :class:`Spare`'s
        ``cancel()`` drops it while it is queued (True; one already running finishes,
        False); in this process it runs when asked for (``cancel()``: False, it can still
        be asked for).  Not cached.
        """
        return Spare(self.later(fn, *args))

    def _compute_on_bag(self, fn: Callable[..., Any], *args: Any) -> Any:
        batch = self._batches.open()
        try:
            return _run(fn.__name__, batch[0], self.bag, _on_bag, fn, *args)
        finally:
            self._batches.close(batch, [fn.__name__])

    def forget_tables(self) -> None:
        """The bag's shared direction tables dropped where the runs hold the bag.

        (:func:`~stellar_cal_ros.diagnosis.runstats.forget_prepared`; a later run that
        needs them makes them again, the same numbers.)
        """
        self.on_bag_each(forget_prepared, [()])

    def on_bag_each(self, fn: Callable[..., Any], calls: list[tuple]) -> list[Any]:
        """``[fn(bag_data, *args) for args in calls]`` where the bag is, not cached.

        On a cluster the calls run concurrently (one task each); here one after the other.
        """
        batch = self._batches.open()
        try:
            return [_run(f"{fn.__name__} {i}", batch[0], self.bag, _on_bag, fn, *args)
                    for i, args in enumerate(calls)]
        finally:
            self._batches.close(batch, [f"{fn.__name__} {i}" for i in range(len(calls))])

    def map(self, tasks: list[Task], ahead: Ahead = (), then: Then | None = None,
            running: list[tuple[Task, Any]] = ()) -> Iterator[tuple[Task, RunSummary]]:
        """Run ``tasks``; yield ``(task, stats)`` as each finishes.

        ``ahead`` and ``then``'s runs (:meth:`run_ahead`) are run after them and kept, not
        yielded.  ``running``: runs made ahead and taken while still running (on a
        cluster: ``(task, future)``), waited for and yielded with ``tasks``.
        """
        batch = self._batches.open()
        later: list[Task] = []
        for task, stats in running:
            yield task, self._resolve(task, stats)
        for task in sorted(tasks, key=lambda t: -t.cost):
            stats = self._evaluate(task, batch[0])
            later += then(task, stats) if then is not None else []
            yield task, stats
        self._ahead += [(t, self.noise_of(t), self._evaluate(t, batch[0]))
                        for t in _tasks(ahead) + later]
        self._batches.close(batch, [t.key for t in tasks] + [t.key for t, _ in running])

    def _evaluate(self, task: Task, batch: int = 0) -> RunSummary:
        return _run(task.key, batch, self.bag, evaluate, self.spec, task.prior, task.effects,
                    self.fraction, task.keep_residuals, (), task.screen, task.candidate,
                    self.noise_of(task), task.star_noise, task.gyro_check,
                    task.frame_loglik)

    def run_all(self, tasks: list[Task],
                done: Callable[[Task, RunSummary, str], None] | None = None,
                ahead: Ahead = (), then: Then | None = None) -> dict[str, RunSummary]:
        """Run ``tasks`` and return ``{key: stats}``.

        ``done(task, stats, where)`` is called as each finishes; ``where`` reads
        ``run 4/11, ETA 20 s`` (no ETA after the last).  ``ahead``, ``then``: see
        :meth:`run_ahead`.
        """
        from stellar_cal_ros.progress import format_seconds

        out = {}
        taken, running = [], []
        for task in tasks:
            stats = self._take_ahead(task)
            if stats is None:
                continue
            if self._pending(stats):  # still running: waited for with the batch
                running.append((task, stats))
            else:
                out[task.key] = self._resolve(task, stats)
                taken.append(task)
        tasks = [t for t in tasks if t.key not in out and all(t is not r for r, _ in running)]
        n, start = len(tasks) + len(taken) + len(running), time.perf_counter()
        if done is not None:  # made ahead: reported as the round's runs
            for k, task in enumerate(taken, 1):
                done(task, out[task.key], f"run {k}/{n} (made ahead)")
        for k, (task, stats) in enumerate(self.map(tasks, ahead, then, running),
                                          len(taken) + 1):
            out[task.key] = stats
            if done is not None:
                left = (time.perf_counter() - start) / (k - len(taken)) * (n - k)
                done(task, stats, f"run {k}/{n}"
                     + (f", ETA {format_seconds(left)}" if k < n else ""))
        return out

    def run_ahead(self, tasks: list[Task], ahead: Ahead,
                  done: Callable[[Task, RunSummary, str], None] | None = None,
                  then: Then | None = None) -> dict[str, RunSummary]:
        """:meth:`run_all` of ``tasks`` and, beside them, of ``ahead``; the stats of ``tasks``.

        ``ahead`` are runs a later step will probably ask for (an idle worker makes them
        now).  They are kept until :meth:`drop_ahead`; a later :meth:`run_all` of the
        *same* run (prior object, effects, noise scales, flags) takes them instead of
        running it again.  This returns when ``tasks`` are done: on a cluster
        (:class:`DaskRuns`) the runs ahead go on meanwhile (one nobody takes would
        otherwise hold the round up by its length, and :meth:`drop_ahead` cancels those
        not started); in this process they run after ``tasks``.  ``ahead`` may be a
        function returning them, called once ``tasks`` are handed out (when building them
        waits for a worker, :meth:`on_bag`, the runs ``tasks`` are not held up by it).

        ``then(task, stats)``, called as each of ``tasks`` finishes, returns further runs
        ahead that need its result (the candidates a screening run passes): on a cluster
        they are handed out at once, while the parent still waits for the rest of
        ``tasks``; in this process they run after ``ahead``.
        """
        return self.run_all(list(tasks), done, ahead if callable(ahead) else list(ahead),
                            then)

    def drop_ahead(self, keep: list[Task] = ()) -> None:
        """Forget the runs made ahead that nobody asked for, except the tasks ``keep``."""
        self._ahead = [a for a in self._ahead if any(a[0] is t for t in keep)]

    def forget_ahead(self, tasks: list[Task]) -> None:
        """Forget the runs made ahead that are ``tasks`` (on a cluster: cancelled if queued)."""
        self.drop_ahead(keep=[t for t, _, _ in self._ahead if all(t is not o for o in tasks)])

    def _take_ahead(self, task: Task) -> Any:
        """The run made ahead that is ``task`` (its stats, or a future), taken; else None."""
        run = replace(task, noise=self.noise_of(task))
        for i, (t, noise, stats) in enumerate(self._ahead):
            if replace(t, noise=noise) == run:
                del self._ahead[i]
                return stats
        return None

    def _pending(self, stats: Any) -> bool:
        """Whether a run made ahead is still to be waited for (in this process: never)."""
        return False

    def _resolve(self, task: Task, stats: Any) -> RunSummary:
        """The statistics of a run made ahead (in this process: already there)."""
        return stats

    def close(self) -> None:
        """Release the workers."""
        timeline.Batches.end()


class DaskRuns(Runs):
    """Runs on a Dask cluster: a LocalCluster of processes, or the user's scheduler."""

    def __init__(self, bag: BagRef, spec, fraction: float, workers: int | None = None,
                 scheduler: str | None = None, lazy: bool = False) -> None:
        super().__init__(bag, spec, fraction)
        self.cluster = self.client = None
        self._start = (workers, scheduler)
        #: ``lazy``: in this process until a batch pays for the cluster (:meth:`pays`)
        self._cpu = [0, 0.0]  #: runs made in this process, their CPU seconds
        if lazy:
            self.description = "in this process (a local cluster once a batch pays for it)"
            self.workers = 1
        else:
            self._connect()

    def _connect(self) -> None:
        workers, scheduler = self._start
        try:
            from distributed import Client
        except ImportError as exc:  # pragma: no cover - a dependency of the package
            raise StellarCalError("parallel diagnosis needs dask.distributed "
                                  "(pip install 'dask[distributed]')") from exc
        if not log.isEnabledFor(logging.DEBUG):  # its start-up chatter, unless -v
            logging.getLogger("distributed").setLevel(logging.WARNING)
        if scheduler:
            try:
                self.client = Client(scheduler, timeout="20s")
            except Exception as exc:
                raise StellarCalError(f"cannot reach the Dask scheduler {scheduler}: "
                                      f"{exc}") from exc
            self.description = f"on the Dask cluster {scheduler}"
        else:
            n = workers or min(os.cpu_count() or 1, MAX_DEFAULT_WORKERS)
            timeline.write({"kind": "cluster", "time": time.time(),
                            "cpu": time.process_time()})
            # the method's kernels, compiled or loaded once in the fork server (a method
            # without a warm-up: nothing done there)
            self.cluster = local_cluster(n, self.bag, warm=getattr(self.spec, "name", None))
            self.client = Client(self.cluster)
            forget_bags()  # the workers hold the bag from now on
            self.description = f"on {n} local worker processes"
            if self._cpu[0]:
                n = self._cpu[0]
                self.description += f" (after {n} run{'s' * (n > 1)} in this process)"
        workers = self.client.scheduler_info()["workers"]
        self.workers = max(len(workers), 1)
        #: every piece of work goes out through this queue, to a free worker
        self._hand = _Hand(self.client.submit, sum(w.get("nthreads", 1)
                                                   for w in workers.values()))
        self.remote_bag = self._place_bag()

    def _place_bag(self) -> Any:
        """The path if every worker sees the same file, else scattered bytes or data."""
        bag = self.bag
        if isinstance(bag, str):
            size = _file_size(bag)
            seen = self.client.run(_file_size, bag)
            if seen and all(s == size for s in seen.values()):
                return bag
            log.info("the workers do not see %s: sending its %d bytes to each", bag, size)
            bag = BagBytes.of(bag)
        return self.client.scatter(bag, broadcast=True, hash=False)

    def pays(self, tasks: list[Task]) -> bool:
        """Whether ``tasks`` would take :data:`CLUSTER_PAYS_S` CPU-s here (lazy mode).

        :data:`CLUSTER_PAYS_SPAWNED_S` where the workers are not forked from this process
        (spawned, or from the fork server: :func:`start_method`).
        """
        n, cpu = self._cpu
        if not (len(tasks) > 1 and n > 0):
            return False
        c = len(tasks) * cpu / n
        # how the workers start matters between the two bounds only (start_method imports
        # Dask, which an in-process round otherwise never loads)
        return c >= CLUSTER_PAYS_SPAWNED_S or (c >= CLUSTER_PAYS_S and start_method() == "fork")

    def facts(self) -> dict[str, Any]:  # noqa: D102
        if self.client is None:
            return super().facts()
        batch = self._batches.open()
        out = self._hand(_run, "facts", batch[0], self.remote_bag, bag_facts,
                         pure=False).result()
        self._batches.close(batch, ["facts"])
        return out

    def on_bag_soon(self, fn: Callable[..., Any], *args: Any) -> None:  # noqa: D102
        key = (fn, args)
        try:
            if self.client is None or key in self._of_bag:
                return
        except TypeError:  # unhashable args: not cached, so not started ahead either
            return
        self._of_bag[key] = self._submit_on_bag(fn, *args)

    def on_bag(self, fn: Callable[..., Any], *args: Any) -> Any:  # noqa: D102
        out = super().on_bag(fn, *args)
        if isinstance(out, _Soon):
            out = self._of_bag[(fn, args)] = out.result()
        return out

    def later(self, fn: Callable[..., Any], *args: Any) -> Callable[[], Any]:  # noqa: D102
        if self.client is None:
            return super().later(fn, *args)
        return self._submit_on_bag(fn, *args).result

    def spare(self, fn: Callable[..., Any], *args: Any) -> Spare:  # noqa: D102
        if self.client is None:
            return super().spare(fn, *args)
        soon = self._submit_on_bag(fn, *args, priority=SPARE_PRIORITY)

        def asked() -> Any:  # (still queued: it goes first now, not after every run)
            self._hand.promote(soon.future, ASKED_PRIORITY)
            return soon.result()

        return Spare(asked, lambda: self._hand.cancel(soon.future))

    def _compute_on_bag(self, fn: Callable[..., Any], *args: Any) -> Any:
        if self.client is None:
            return super()._compute_on_bag(fn, *args)
        return self._submit_on_bag(fn, *args).result()

    def _submit_on_bag(self, fn: Callable[..., Any], *args: Any,
                       priority: int = ON_BAG_PRIORITY) -> _Soon:
        """``fn(bag_data, *args)`` submitted now, its own batch on the timeline."""
        # before any queued run (the default): a statistic of the bag is what the next step
        # waits for
        batch = self._batches.open()
        fut = self._hand(_run, fn.__name__, batch[0], self.remote_bag, _on_bag, fn, *args,
                         pure=False, priority=priority)
        return _Soon(fut, batch, fn.__name__, self._batches)

    def forget_tables(self) -> None:  # noqa: D102
        if self.client is None:
            return super().forget_tables()
        # the workers hold the bag (this process forgot its own when they started): one
        # call through on_bag_each would read it again here and leave theirs
        if isinstance(self.bag, BagData):
            forget_prepared(self.bag)
        self.client.run(forget_held_prepared)
        return None

    def on_bag_each(self, fn: Callable[..., Any], calls: list[tuple]) -> list[Any]:  # noqa: D102
        if self.client is None or len(calls) < 2:
            return super().on_bag_each(fn, calls)
        batch = self._batches.open()
        keys = [f"{fn.__name__} {i}" for i in range(len(calls))]
        futures = [self._hand(_run, k, batch[0], self.remote_bag, _on_bag, fn, *args,
                              pure=False) for k, args in zip(keys, calls, strict=True)]
        out = [f.result() for f in futures]
        self._batches.close(batch, keys)
        return out

    def _evaluate(self, task: Task, batch: int = 0) -> RunSummary:
        t = time.process_time()
        out = super()._evaluate(task, batch)
        self._cpu[0] += 1
        self._cpu[1] += time.process_time() - t
        return out

    def _submit(self, task: Task, batch: int, ahead: bool = False) -> Any:
        return self._hand(_run, task.key, batch, self.remote_bag, evaluate, self.spec,
                          task.prior, task.effects, self.fraction, task.keep_residuals,
                          self.classes, task.screen, task.candidate, self.noise_of(task),
                          task.star_noise, task.gyro_check, task.frame_loglik, pure=False,
                          priority=int(100 * task.cost) + (AHEAD_PRIORITY if ahead else 0),
                          key=f"stellar-cal-{task.key}-{uuid.uuid4().hex}")

    @staticmethod
    def _result(task: Task, fut: Any) -> RunSummary:
        try:
            out = fut.result()
        except Exception as exc:  # a worker died (killed, out of memory): a failed run
            out = RunSummary(effects=task.effects, error=f"{type(exc).__name__}: {exc}")
        fut.release()
        return out

    def map(self, tasks, ahead=(), then=None, running=()):  # noqa: D102
        if self.client is None:  # (lazy) nothing handed out before ``ahead`` is built
            ahead = _tasks(ahead)
        if self.client is None and self.pays(list(tasks) + list(ahead)):
            log.info("%d runs of ~%.1f CPU-s each: starting a local cluster", len(tasks),
                     self._cpu[1] / self._cpu[0])
            self._connect()
        if self.client is None:
            yield from super().map(tasks, ahead, then, running)
            return
        import queue

        batch = self._batches.open()
        futures = {self._submit(task, batch[0]): task for task in tasks}
        futures.update({fut: task for task, fut in running})
        done: queue.SimpleQueue[_Handed] = queue.SimpleQueue()
        for fut in futures:
            fut.when_done(done.put)
        # queued after ``tasks`` (a free worker takes them), kept as futures
        self._ahead += [(t, self.noise_of(t), self._submit(t, batch[0], ahead=True))
                        for t in _tasks(ahead)]
        while futures:
            fut = done.get()
            task = futures.pop(fut)
            stats = self._result(task, fut)
            # handed out now, beside the runs still waited for (the parent waits below)
            self._ahead += [(t, self.noise_of(t), self._submit(t, batch[0], ahead=True))
                            for t in (then(task, stats) if then is not None else [])]
            yield task, stats
        self._batches.close(batch, [t.key for t in tasks] + [t.key for t, _ in running])

    def _pending(self, stats: Any) -> bool:  # noqa: D102
        return not isinstance(stats, RunSummary)

    def drop_ahead(self, keep: list[Task] = ()) -> None:  # noqa: D102
        for task, _, fut in self._ahead:
            if not isinstance(fut, RunSummary) and not any(task is t for t in keep):
                with contextlib.suppress(Exception):
                    fut.cancel()  # not started: not run (one already running finishes)
        super().drop_ahead(keep)

    def _resolve(self, task: Task, stats: Any) -> RunSummary:
        return stats if isinstance(stats, RunSummary) else self._result(task, stats)

    def close(self) -> None:  # noqa: D102
        timeline.Batches.end()
        if self.client is None:
            return
        self._hand.close()
        with contextlib.suppress(Exception):
            self.client.close()
        if self.cluster is not None:
            # a worker busy past the nanny's 4 s grace is killed: expected at shutdown on a
            # loaded machine, not a warning for the user (kept with -v)
            if not log.isEnabledFor(logging.DEBUG):
                logging.getLogger("distributed.nanny").setLevel(logging.ERROR)
            with contextlib.suppress(Exception):
                self.cluster.close()


class _Handed:
    """A piece of work :class:`_Hand` gives the cluster once a worker is free: its future.

    Until then it waits in the parent's queue; :meth:`result`, :meth:`cancel` and
    :meth:`release` act as a Dask future's (a cancelled piece never runs; one already
    handed out runs to its end).
    """

    def __init__(self, hand: _Hand) -> None:
        self.hand = hand
        self.future: Any = None  #: the Dask future, once handed out
        self.finished = False
        self.cancelled = False
        self._out = threading.Event()  #: handed out (or cancelled)
        self._then: list[Callable[[_Handed], None]] = []

    def result(self) -> Any:
        self._out.wait()
        if self.future is None:
            from concurrent.futures import CancelledError

            raise CancelledError("cancelled before a worker took it")
        return self.future.result()

    def cancel(self) -> None:
        """Not handed out: never will be.  Handed out: it runs to its end, unused."""
        self.hand.cancel(self)

    def release(self) -> None:
        if self.future is not None:
            self.future.release()

    def when_done(self, fn: Callable[[_Handed], None]) -> None:
        """Call ``fn(self)`` once it has finished (at once if it has)."""
        with self.hand.lock:
            if not self.finished:
                self._then.append(fn)
                return
        fn(self)


class _Hand:
    """The parent's queue of work for the cluster: the next piece to a free worker.

    Dask places a task on a worker when it is submitted (each run is its own task group,
    never queued at the scheduler), so two pieces handed out together could run one after
    the other on one worker while the other idled.  Here at most ``slots`` pieces (the
    cluster's threads) are out at once, the rest wait here and the highest ``priority``
    (first come first among equals) goes out the moment one finishes: Dask then sends it to
    the free worker (measured, doc/benchmarks.md "a free worker takes the next run").
    """

    def __init__(self, submit: Callable[..., Any], slots: int) -> None:
        self.submit = submit  #: ``Client.submit``
        self.slots = max(int(slots), 1)
        self.lock = threading.Lock()
        self._queue: list[tuple[int, int, _Handed, tuple, dict]] = []
        self._order = itertools.count()
        self.out = 0  #: pieces handed out and not finished

    def __call__(self, *args: Any, priority: int = 0, **kwargs: Any) -> _Handed:
        """``submit(*args, priority=priority, **kwargs)`` when a worker is free."""
        piece = _Handed(self)
        with self.lock:
            heapq.heappush(self._queue, (-priority, next(self._order), piece, args,
                                         {**kwargs, "priority": priority}))
        self._pump()
        return piece

    def cancel(self, piece: _Handed) -> bool:
        """Drop ``piece`` if it is still queued (True); out already: it runs on (False)."""
        with self.lock:
            if piece.future is not None:
                return False  # out already: it finishes and frees its worker then
            piece.cancelled = True
            self._queue = [q for q in self._queue if q[2] is not piece]
            heapq.heapify(self._queue)
        piece._out.set()
        return True

    def promote(self, piece: _Handed, priority: int) -> bool:
        """Queue ``piece`` at ``priority`` if it is still queued lower (True); else False."""
        with self.lock:
            at = next((i for i, q in enumerate(self._queue) if q[2] is piece), None)
            if at is None or -self._queue[at][0] >= priority:
                return False
            _, _, _, args, kwargs = self._queue.pop(at)
            heapq.heapify(self._queue)
            heapq.heappush(self._queue, (-priority, next(self._order), piece, args,
                                         {**kwargs, "priority": priority}))
        self._pump()
        return True

    def _pump(self) -> None:
        """Hand out the queue's first pieces while workers are free."""
        while True:
            with self.lock:
                if self.out >= self.slots or not self._queue:
                    return
                _, _, piece, args, kwargs = heapq.heappop(self._queue)
                self.out += 1
            try:
                piece.future = self.submit(*args, **kwargs)
            except Exception:
                with self.lock:
                    self.out -= 1
                piece._out.set()
                raise
            piece._out.set()
            piece.future.add_done_callback(lambda _f, piece=piece: self._finished(piece))

    def _finished(self, piece: _Handed) -> None:
        with self.lock:
            self.out -= 1
            piece.finished = True
            then, piece._then = piece._then, []
        for fn in then:
            fn(piece)
        try:
            self._pump()
        except Exception:  # noqa: BLE001 - Dask's callback thread: the client closing
            log.debug("the next run was not handed out", exc_info=True)

    def close(self) -> None:
        """Hand nothing more out (the client closes): the queued pieces are cancelled."""
        with self.lock:
            queued, self._queue = [q[2] for q in self._queue], []
        for piece in queued:
            piece.cancelled = True
            piece._out.set()


@dataclass
class Spare:
    """A value :meth:`Runs.spare` started: call it for the value, ``cancel()`` to drop it."""

    get: Callable[[], Any]
    #: drop it if it has not started: True if dropped (in this process: nothing started,
    #: False)
    cancel: Callable[[], bool] = lambda: False

    def __call__(self) -> Any:
        """The value (waited for on a cluster; computed now in this process)."""
        return self.get()


@dataclass
class _Soon:
    """A statistic of the bag started ahead (:meth:`Runs.on_bag_soon`), not yet asked for."""

    future: Any
    batch: tuple[int, float, float]
    name: str
    batches: timeline.Batches

    def result(self) -> Any:
        out = self.future.result()
        self.batches.close(self.batch, [self.name])
        return out


@contextlib.contextmanager
def open_runner(bag: BagRef, spec, fraction: float, workers: int | None = 0,
                scheduler: str | None = None, on_error: str = "raise") -> Iterator[Runs]:
    """A :class:`Runs` for ``bag``: in process (``workers`` 0 or 1), local Dask or a scheduler.

    ``workers=None`` means automatic: in this process, and one worker process per core
    (at most :data:`MAX_DEFAULT_WORKERS`) from the first batch of runs that pays for them
    (:data:`CLUSTER_PAYS_S`; in this process on a machine of at most
    :data:`IN_PROCESS_CORES` cores).  A bag without the inputs the method needs (star
    frames, the IMU of a filter) is refused from its summary, before any run.
    ``on_error="skip"``: a damaged bag is read here past its damage
    (:func:`~stellar_cal_ros.methods.frames.read_bag_data`, the reader's skip mode) and
    the runs use what it holds; :attr:`Runs.losses` says what was lost.
    """
    lazy = workers is None and not scheduler
    if workers is None:
        cores = os.cpu_count() or 1
        workers = min(cores, MAX_DEFAULT_WORKERS) if cores > IN_PROCESS_CORES else 1
    if isinstance(bag, (str, Path)):  # (a path that does not exist: refused there)
        from stellar_cal_ros.methods.frames import method_reads_images

        images = method_reads_images(bag, getattr(spec, "name", ""))
        # a rosbag2 directory, star images (extracted once, not in every worker) or a bag
        # read past damage: read once here, sent to the runs as data
        if Path(bag).is_dir() or images or on_error == "skip":
            from stellar_cal_ros.methods.replay import read_bag_data

            bag = read_bag_data(bag, require_imu=False, on_error=on_error)
    runs = (DaskRuns(bag, spec, fraction, workers, scheduler, lazy) if scheduler or workers > 1
            else Runs(bag, spec, fraction))
    try:
        # (the imports' objects out of the collector's full passes: memory.frozen_objects)
        with frozen_objects():
            yield runs
    finally:
        runs.close()


# ---------------------------------------------------------------------------- measurement
def tree_cpu(root: int | None = None, descendants_only: bool = False,
             reaped: bool = False) -> dict[int, float]:
    """CPU seconds (user + system) of a process and its live descendants, by process id.

    The one reader of a process tree's CPU (the benchmarks' and tests' measurements of a
    round with workers: a local cluster's workers are the fork server's children, never
    reaped into the command's rusage).  ``root``: a process id (default this process);
    ``descendants_only``: without the root; ``reaped``: each process's count includes its
    reaped children's (``children_user + children_system``).  A process that ends while
    it is read is left out.
    """
    import psutil

    out: dict[int, float] = {}
    try:
        top = psutil.Process(root)
        tree = top.children(recursive=True)
    except psutil.Error:
        return out
    for p in tree if descendants_only else [top, *tree]:
        try:
            t = p.cpu_times()
        except psutil.Error:
            continue
        out[p.pid] = t.user + t.system + (t.children_user + t.children_system if reaped
                                          else 0.0)
    return out


class TreeCPU:
    """CPU seconds of a process tree while this is entered (:func:`tree_cpu`, in ``cpu``).

    ``root``, ``descendants_only``: as :func:`tree_cpu` (``descendants_only``: e.g. a child
    whose own CPU its reaped rusage gives exactly).  Descendants that come and go (a local
    cluster's workers) are read every ``period`` s until they exit: their last ``period``
    is missed.
    """

    def __init__(self, period: float = 0.2, root: int | None = None,
                 descendants_only: bool = False) -> None:
        self.period, self.cpu = period, 0.0
        self.root, self.descendants_only = root, descendants_only
        self._done = threading.Event()

    def _read(self) -> dict[int, float]:
        return tree_cpu(self.root, self.descendants_only)

    def _watch(self) -> None:
        while not self._done.wait(self.period):
            self._last.update(self._read())

    def __enter__(self) -> TreeCPU:
        self._start = self._read()
        self._last = dict(self._start)
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._done.set()
        self._thread.join()
        self._last.update(self._read())
        self.cpu = sum(v - self._start.get(pid, 0.0) for pid, v in self._last.items())
