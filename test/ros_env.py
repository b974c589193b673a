"""The ROS set-up every ROS test shares: one private DDS domain per test process, localhost
discovery, Fast DDS on UDP only (the ``ros_context`` fixture of conftest.py, and the
environment of the node processes the tests start: :func:`node_env`).

UDP rather than Fast DDS's default shared memory: with shared memory a starved process
stopped receiving (beside 2 CPU hogs the kill -9 test's player got no ``~/data_clock`` ack
after a completed handshake; doc/benchmarks.md, "The kill -9 test's transport race"), and
every participant left a 0.5 MB segment in /dev/shm when its process was killed.  Fast DDS
reads the variable when a participant is created (each ``rclpy.Context``).
"""

from __future__ import annotations

import os
from pathlib import Path

#: this test process's domain (1..100; 0 is everybody's default)
DOMAIN_ID = 1 + (os.getpid() + 37) % 100
#: Fast DDS's transports for every participant of the tests: UDP on loopback only
TRANSPORT = {"FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"}
#: discovery on this machine only
DISCOVERY = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}


def node_env(**extra: str) -> dict[str, str]:
    """The environment of a node process a test starts: this process's domain and
    transport, this checkout's package first, unbuffered output."""
    return dict(os.environ, **TRANSPORT, **DISCOVERY, ROS_DOMAIN_ID=str(DOMAIN_ID),
                PYTHONPATH=str(Path(__file__).resolve().parents[1]), PYTHONUNBUFFERED="1",
                **extra)
