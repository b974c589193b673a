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


@pytest.fixture
def cli(capsys):
    """``cli(*args)``: a ``stellar-cal`` command through ``cli.main`` in this process.

    Asserts it exits 0 (the message: its stderr's tail) and that every printed line's
    parentheses close, none at another's end (:mod:`printed_text`); returns its stdout.
    """
    from printed_text import parentheses_problems

    from stellar_cal_ros.cli import main

    def run(*args):
        capsys.readouterr()
        rc = main(list(args))
        out = capsys.readouterr()
        assert rc == 0, out.err[-3000:]
        bad = parentheses_problems([out.out, out.err])
        assert not bad, "\n".join(bad)
        return out.out

    return run
