"""stellar_cal_ros: online calibration of a star tracker + gyroscope/IMU system.

Layers:

- :mod:`stellar_cal_ros.core`: numpy/scipy only -- state blocks, covariance updates, gating,
  IMU buffer, rotations, camera model, strapdown propagation, Earth orientation, gravity,
  catalogue and astrometry.
- :mod:`stellar_cal_ros.effects`: one module per physical effect (the extension point).
- :mod:`stellar_cal_ros.methods`: the estimation kernel and the methods assembled from it.
- :mod:`stellar_cal_ros.sim`: the truth-world simulator.
- :mod:`stellar_cal_ros.io`: bags and the calibration YAML.
- :mod:`stellar_cal_ros.nodes`: thin rclpy nodes.

BLAS threads: every matrix of the filters is small (N < 100), where a multi-threaded BLAS
only adds overhead — and on a loaded machine its spinning threads make a frame update 10×
slower (measured: 15 ms instead of 1.2 ms per swaying update with 8 processes on 2 cores).
So, unless the user set them, the thread counts of OpenBLAS / MKL / OpenMP default to 1 when
this package is imported before numpy; parallel work runs in processes (Dask workers).
"""

import os as _os
import sys as _sys

if "numpy" not in _sys.modules:
    for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"):
        _os.environ.setdefault(_var, "1")

__version__ = "0.1.0"
