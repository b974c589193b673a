"""Test session set-up: one BLAS thread (see stellar_cal_ros/__init__.py) before numpy loads."""

import os

for _var in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


import pytest  # noqa: E402
from refdata import DATA, path  # noqa: E402
from ros_env import DISCOVERY, DOMAIN_ID, TRANSPORT  # noqa: E402


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


@pytest.fixture
def ros_context(monkeypatch):
    """A fresh rclpy Context in this process's private domain, localhost discovery, Fast DDS
    asked for UDP (:mod:`ros_env`: the localhost range keeps shared memory); shut down
    afterwards."""
    try:
        import rclpy
        import stellar_cal_msgs.msg  # noqa: F401
    except ImportError as exc:
        pytest.fail(f"rclpy / stellar_cal_msgs not importable ({exc}); run bash "
                    "scripts/setup.sh")
    for name, value in {**DISCOVERY, **TRANSPORT}.items():
        monkeypatch.setenv(name, value)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=DOMAIN_ID)
    try:
        yield ctx
    finally:
        ctx.try_shutdown()
