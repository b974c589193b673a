"""Test session set-up: one BLAS thread (see stellar_cal_ros/__init__.py) before numpy loads."""

import os

for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
