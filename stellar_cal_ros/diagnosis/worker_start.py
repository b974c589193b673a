"""What a local Dask worker holds before its first task: imported in the fork server.

The local cluster's workers are forked from multiprocessing's fork server where the
platform has one (:func:`~stellar_cal_ros.diagnosis.parallel.start_method`): a fresh,
single-threaded process that imports this module once
(:func:`~stellar_cal_ros.diagnosis.parallel.local_cluster` adds it to the server's
preload).  Every worker then starts with the package's imports (numba, the filter, the
diagnosis' runs) and, when :data:`~stellar_cal_ros.diagnosis.parallel.WORKER_BAG_ENV`
names a bag, that bag read (:func:`~stellar_cal_ros.diagnosis.runstats.load_bag`), as a
worker forked from the diagnosis process did — without forking a process that runs
threads.  When :data:`~stellar_cal_ros.diagnosis.warm_up.WORKER_WARM_ENV` names a filter
method, its numba kernels are compiled (a fresh install) or loaded here, once
(:func:`~stellar_cal_ros.diagnosis.warm_up.warm_up`): the workers are forked holding them.
"""

from __future__ import annotations

import contextlib
import os

import stellar_cal_ros.diagnosis.discover  # noqa: F401  (the runs' imports)
import stellar_cal_ros.methods.frame_step  # noqa: F401  (numba, the kernels' modules)
from stellar_cal_ros.core.memory import return_freed_arrays, trim_freed
from stellar_cal_ros.diagnosis import parallel, runstats, warm_up


def _read_bag() -> None:
    path = os.environ.get(parallel.WORKER_BAG_ENV)
    if not path:
        return
    try:
        runstats.load_bag(path)
    except Exception:  # noqa: BLE001 - each worker reads it itself and says why
        runstats.forget_bags()


def _warm_up() -> None:
    method = os.environ.get(warm_up.WORKER_WARM_ENV)
    if not method:
        return
    with contextlib.suppress(Exception):  # (else each worker compiles or loads them itself)
        warm_up.warm_up(method)


return_freed_arrays()  # as the diagnosis process (a forked worker inherits it)
_warm_up()
trim_freed()  # (the warm-up's arrays: not in every worker)
_read_bag()
