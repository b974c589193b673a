"""Test session set-up: one BLAS thread (see stellar_cal_ros/__init__.py) before numpy loads."""

import os

for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


import pytest  # noqa: E402
from refdata import DATA, path  # noqa: E402


@pytest.fixture(scope="session")
def reference_data():
    """The reference-data folder (``../shared/data``); skips, saying so, when it is absent."""
    return path(".", DATA).resolve()
