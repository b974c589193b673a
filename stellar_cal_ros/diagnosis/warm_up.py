"""Compile (or load) a filter method's numba kernels before the runs that need them.

A filter method's first run in a process compiles its kernels when no cache holds them
(≈ 63 CPU-s for ``psce``, ≈ 34 for ``swaying_base``, on 2 cores) or loads them
(≈ 1.2 CPU-s).  :func:`warm_up` does it on a short simulated bag of the method's scenario,
so that it is done once where it is cheapest:

* in the local cluster's fork server, before it forks the workers
  (:mod:`~stellar_cal_ros.diagnosis.worker_start`, :data:`WORKER_WARM_ENV`): every worker
  starts holding the kernels, instead of each compiling the same ones side by side (two
  workers compiled 2 × 66 CPU-s on a fresh install) or loading them;
* at installation (``python -m stellar_cal_ros.diagnosis.warm_up``, which
  ``scripts/setup.sh`` runs): the kernel cache (:func:`stellar_cal_ros.core.jit.kernel_cache_dir`)
  is shared by every checkout of the same kernel sources, so the first command of a fresh
  clone loads them.

The warm-up's own results are thrown away; nothing a run computes depends on it.
"""

from __future__ import annotations

import sys
import time

import numpy as np

#: environment: the filter method whose kernels the fork server warms up
#: (:func:`~stellar_cal_ros.diagnosis.parallel.local_cluster` sets it)
WORKER_WARM_ENV = "STELLAR_CAL_WORKER_WARM"

#: filter method -> (simulated scenario, seconds): a bag on which its replay calls every
#: kernel its runs call (measured, not tested: a CLI replay after :func:`main` compiles none,
#: doc/benchmarks.md; a test would compile them all, ~100 CPU-s)
WARM_UPS: dict[str, tuple[str, float]] = {
    "psce": ("psce_rotations", 20.0),
    "swaying_base": ("swaying", 20.0),
}


def warm_up(method: str) -> bool:
    """Replay a short simulated bag with ``method`` (its kernels compiled or loaded here).

    False (nothing done) without numba or for a method without a warm-up.
    """
    from stellar_cal_ros.core.jit import HAVE_NUMBA

    if not HAVE_NUMBA or method not in WARM_UPS:
        return False
    from stellar_cal_ros.methods.frames import bag_data_from_simulation
    from stellar_cal_ros.methods.replay import replay
    from stellar_cal_ros.sim.scenarios import get_scenario
    from stellar_cal_ros.sim.world import simulate

    scenario, seconds = WARM_UPS[method]
    sim = simulate(get_scenario(scenario), duration=seconds, seed=1)
    replay(bag_data_from_simulation(sim), sim.prior, method)
    return True


#: in the kernel cache's directory once :func:`main` warmed every method up (``setup.sh``)
DONE_MARKER = "warm-up.done"


def text_kernel() -> bool:
    """Compile (or load) the CSV writer's kernel (``float_text._table_text``); False: no numba.

    Every command that writes a history or residual table calls it (``io.residuals``).
    """
    from stellar_cal_ros.core import float_text

    one = np.zeros(1)
    return float_text.table_text([one, one.astype(np.int64), one.astype(bool)]) is not None


def main(argv: list[str] | None = None) -> int:
    """Warm up the methods named (default: every method of :data:`WARM_UPS`); one line each.

    Then the CSV writer's kernel (:func:`text_kernel`), and the kernels-used markers a
    command writes (:func:`~stellar_cal_ros.methods.frame_step.record_kernels_used`): the
    first command after it finds the state its own first run would have left, and says
    "compiling" only when it compiles.  With the default, :data:`DONE_MARKER` is written in
    the kernel cache's directory.
    """
    from stellar_cal_ros.core.jit import kernel_cache_dir
    from stellar_cal_ros.methods.frame_step import record_kernels_used

    methods = (argv if argv is not None else sys.argv[1:]) or list(WARM_UPS)
    for method in methods:
        t0 = time.process_time()
        done = warm_up(method)
        print(f"{method}: {'kernels ready' if done else 'nothing to compile'} "
              f"({time.process_time() - t0:.1f} CPU-s)", flush=True)
    t0 = time.process_time()
    if text_kernel():
        print(f"tables: kernel ready ({time.process_time() - t0:.1f} CPU-s)", flush=True)
    record_kernels_used()
    where = kernel_cache_dir()
    if set(methods) >= set(WARM_UPS) and where is not None and where.is_dir():
        (where / DONE_MARKER).write_text("")
    return 0


if __name__ == "__main__":  # pragma: no cover - the installation step
    sys.exit(main())
