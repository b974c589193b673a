"""One noise ML re-run of the 2-h bag with and without the gyro check, interleaved (issue 24.2).

``noise_runs.scale_task`` runs without the gyro-against-stars check (``gyro_check=False``):
this prints the CPU seconds of the same re-run both ways, in one process, and checks that
the log-likelihood and θ are the same bit for bit.

Run::

    python benchmarks/gyro_check_ab.py [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main() -> int:
    """Print the table."""
    from discovery_speed import ensure_2h_bag

    from stellar_cal_ros.core.noise import NoiseScales
    from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
    from stellar_cal_ros.diagnosis.noise_runs import scale_task
    from stellar_cal_ros.diagnosis.runstats import evaluate, load_bag
    from stellar_cal_ros.io.calibration import load_calibration

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    bag = ensure_2h_bag()
    prior = rerun_prior(load_calibration(bag.with_suffix(".prior.yaml")))
    spec, data = method_spec("psce"), load_bag(bag)
    t = scale_task("gyro", 0.1, prior, (), NoiseScales())
    cpu: dict[bool, list[float]] = {True: [], False: []}
    got: dict[bool, tuple] = {}
    print(f"load average {os.getloadavg()[0]:.1f} at start")
    for _ in range(args.repeat):
        for check in (True, False):
            c = time.process_time()
            out = evaluate(data, spec, t.prior, t.effects, 0.5, noise=t.noise,
                           gyro_check=check)
            cpu[check].append(time.process_time() - c)
            assert out.ok, out.error
            got.setdefault(check, (out.window["log_likelihood"], out.theta))
    print(f"load average {os.getloadavg()[0]:.1f} at the end")
    for check in (True, False):
        print(f"gyro check {'on ' if check else 'off'}: CPU-s per run "
              f"{' '.join(f'{x:.2f}' for x in cpu[check])}  mean {np.mean(cpu[check]):.2f}  "
              f"log-likelihood {got[check][0]!r}")
    same = got[True][0] == got[False][0] and np.array_equal(got[True][1], got[False][1])
    print("same log-likelihood and theta:", same)
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
