r"""The gyro bias's random walk as a noise hypothesis: the run's log-likelihood over its density.

The model's gyro bias is a constant unless the noise scales give it a random walk
(``NoiseScales(gyro_bias_rw=D)``, ``--noise-scale gyro_bias_rw=D``).  This script re-runs the
current model (psce baseline) on a bag with the bias given a random walk of each density in
deg/h/√h, or with the gyro's white noise scaled (``gK``: ``NoiseScales(gyro=K)``),
and prints the evaluation window's log-likelihood and NIS/dof and the RMS residual::

    python benchmarks/gyro_bias_walk_ml.py BAG 0,0.3,1,3,10,g10

``BAG`` without its suffix (``BAG.mcap``, ``BAG.prior.yaml``), e.g. a bag of
``benchmarks/unseen_cases.py OUT --cases bias_walk10``.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from stellar_cal_ros.core.noise import NoiseScales
from stellar_cal_ros.diagnosis.discover import method_spec, rerun_prior
from stellar_cal_ros.diagnosis.runstats import quiet
from stellar_cal_ros.io.calibration import load_calibration
from stellar_cal_ros.methods.frames import read_bag_data


def main(bag: str, items: str) -> None:
    """Print one line per item of ``items`` (densities in deg/h/√h, or ``gK``)."""
    data = read_bag_data(bag + ".mcap")
    prior = rerun_prior(load_calibration(bag + ".prior.yaml"))
    spec = method_spec("psce")
    for item in items.split(","):
        if item.startswith("g"):
            noise = NoiseScales(gyro=float(item[1:]))
        else:
            noise = NoiseScales(gyro_bias_rw=float(item))
        t0 = time.perf_counter()
        with quiet():
            r = spec.runner(data, prior, [], keep_tables=True, eval_fraction=0.5,
                            noise=None if noise.identity else noise)
        w = r.stats.window(0.5)
        du, dv = np.asarray(r.residuals["du"]), np.asarray(r.residuals["dv"])
        print(f"{item:>6}  loglik {w['log_likelihood']:9.1f}  NIS/dof "
              f"{w['nis']['mean'] / 2:.3f}  rms u {np.sqrt(np.mean(du**2)):.4f} "
              f"v {np.sqrt(np.mean(dv**2)):.4f} px  [{time.perf_counter() - t0:.1f} s]",
              flush=True)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
