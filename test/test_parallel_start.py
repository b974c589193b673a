"""How the diagnosis' local Dask workers start (diagnosis/parallel.py: start_method, local_cluster).

The default on Linux is multiprocessing's fork server: a fresh single-threaded process that
imports the package and reads the bag once (diagnosis/worker_start.py), from which every
worker is forked -- not a fork of the diagnosis process, which runs Dask's event-loop
thread.  A user's choice (the package's variable, Dask's key or its variable) goes first.
"""

from __future__ import annotations

import os
import sys

import pytest

from stellar_cal_ros.diagnosis import parallel
from stellar_cal_ros.errors import StellarCalError


@pytest.fixture
def no_choice(monkeypatch):
    monkeypatch.delenv(parallel.START_ENV, raising=False)
    monkeypatch.delenv(parallel.DASK_START_ENV, raising=False)
    return monkeypatch


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the fork server: Linux")
def test_the_default_is_the_fork_server_and_a_users_choice_goes_first(no_choice):
    import dask

    assert parallel.start_method() == "forkserver"
    no_choice.setenv(parallel.START_ENV, "spawn")
    assert parallel.start_method() == "spawn"
    no_choice.setenv(parallel.START_ENV, "vfork")
    with pytest.raises(StellarCalError, match="cannot start by 'vfork'"):
        parallel.start_method()
    no_choice.delenv(parallel.START_ENV)
    with dask.config.set({parallel.DASK_START_KEY: "fork"}):
        assert parallel.start_method() == "fork"
    # Dask's default ('spawn') is no choice of the user's ...
    with dask.config.set({parallel.DASK_START_KEY: "spawn"}):
        assert parallel.start_method() == "forkserver"
        # ... unless its environment variable says it
        no_choice.setenv(parallel.DASK_START_ENV, "spawn")
        assert parallel.start_method() == "spawn"


def _held():
    """In a worker: its parent process and the bags it holds before any task."""
    from stellar_cal_ros.diagnosis import runstats

    return os.getppid(), [k[1] for k in runstats._BAG_CACHE]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the fork server: Linux")
def test_fork_server_workers_start_holding_the_bag_and_are_not_forks_of_this_process(
        tmp_path, no_choice):
    from distributed import Client

    from stellar_cal_ros.cli import main

    for seed in (3, 4):  # the second cluster's bag is another: the server starts again
        bag = tmp_path / f"b{seed}.mcap"
        assert main(["simulate", "--scenario", "psce_rotations", "--duration", "20",
                     "--seed", str(seed), "-o", str(bag)]) == 0
        with parallel.local_cluster(2, str(bag)) as cluster, Client(cluster) as client:
            held = client.run(_held)
            assert len(held) == 2
            for ppid, bags in held.values():
                assert ppid != os.getpid()  # forked from the server, not from here
                assert bags == [str(bag)]  # the server read it: the worker did not
        assert os.environ.get(parallel.WORKER_BAG_ENV) is None  # only while it starts


def _kernels_held() -> int:
    from stellar_cal_ros.methods import frame_step

    return len(frame_step.frame_steps.overloads)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the fork server: Linux")
def test_fork_server_workers_start_holding_the_methods_kernels(no_choice):
    """The fork server compiles or loads the method's kernels once (diagnosis/warm_up.py):
    its workers start holding them, instead of each compiling them side by side (two workers
    of a fresh install compiled 2 x 66 CPU-s)."""
    from distributed import Client

    from stellar_cal_ros.core.jit import HAVE_NUMBA

    if not HAVE_NUMBA:
        pytest.skip("numba is not installed")
    with parallel.local_cluster(2, None, warm="psce") as cluster, Client(cluster) as client:
        held = client.run(_kernels_held)
    assert len(held) == 2 and all(n >= 1 for n in held.values())
    assert os.environ.get(parallel.WORKER_WARM_ENV) is None  # only while it starts


def _worker_timers(dask_worker) -> dict[str, float]:
    return {name: pc.callback_time for name, pc in dask_worker.periodic_callbacks.items()}


def test_local_cluster_wakes_the_parent_seldom(no_choice):
    """The scheduler and the nannies run in this process's event loop: their timers cost
    the parent CPU per second of wall whatever the work (an idle two-worker cluster at
    Dask's defaults: 189 timer calls a second, 32-42 ms of CPU; doc/benchmarks.md "the
    parent's Dask CPU").  With :data:`parallel.LOCAL_DASK_CONFIG` 17, the workers' own
    timers as seldom, no work stealing and no active memory manager (which drops the
    copies of a bag scattered to every worker).  Fails on the tree before it (189)."""
    from distributed import Client

    with parallel.local_cluster(2, None) as cluster, Client(cluster) as client:
        servers = {"scheduler": cluster.scheduler, **cluster.workers}  # nannies here
        per_s = {f"{who} {name}": 1000 / pc.callback_time
                 for who, s in servers.items() for name, pc in s.periodic_callbacks.items()
                 if pc.is_running()}
        # 17.3 (8 of them Dask's fixed 250 ms idle checks); 189 at Dask's defaults
        assert sum(per_s.values()) < 20, per_s
        assert "stealing" not in cluster.scheduler.extensions
        assert not client.amm.running()
        for timers in client.run(_worker_timers).values():
            assert timers["tick"] >= 1000 and timers["memory_monitor"] >= 1000
            assert "profile" not in timers
