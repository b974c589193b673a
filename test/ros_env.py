"""The ROS set-up every ROS test shares: one private DDS domain per test process, localhost
discovery, Fast DDS asked for UDP only (the ``ros_context`` fixture of conftest.py, and the
environment of the node processes the tests start: :func:`node_env`) — which the localhost
range overrides (below): the tests run on shared memory as well.

UDP asked for rather than Fast DDS's default shared memory: with shared memory a starved
process stopped receiving (beside 2 CPU hogs the kill -9 test's player got no
``~/data_clock`` ack after a completed handshake; doc/benchmarks.md, "The kill -9 test's
transport race").  Fast DDS reads the variable when a participant is created (each
``rclpy.Context``).  But with the localhost discovery range rmw_fastrtps (Jazzy) sets the
participant's transports itself, shared memory included: the variable (or an XML profile)
changes nothing there (checked: a participant maps ``/dev/shm/fastrtps_*`` either way; with
the default range and the variable it maps none).  A participant removes its 0.5 MB segment
when its process ends; one killed leaves it: :func:`own_shm_segments` before a kill and
:func:`remove_shm_segments` after it take the test's own leftovers away.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

#: this test process's domain (1..100; 0 is everybody's default)
DOMAIN_ID = 1 + (os.getpid() + 37) % 100
#: Fast DDS's transports asked for every participant (the localhost range overrides it)
TRANSPORT = {"FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"}
#: discovery on this machine only
DISCOVERY = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}


def node_env(**extra: str) -> dict[str, str]:
    """The environment of a node process a test starts: this process's domain and
    transport, this checkout's package first, unbuffered output."""
    return dict(os.environ, **TRANSPORT, **DISCOVERY, ROS_DOMAIN_ID=str(DOMAIN_ID),
                PYTHONPATH=str(Path(__file__).resolve().parents[1]), PYTHONUNBUFFERED="1",
                **extra)


def own_shm_segments(pid: int) -> list[Path]:
    """The Fast DDS shared-memory segments process ``pid`` created: those whose lock file
    (``/dev/shm/fastrtps_<16 hex>_el``) it holds open; not the port files all share."""
    out = []
    try:
        fds = list(Path(f"/proc/{pid}/fd").iterdir())
    except OSError:  # gone, or not Linux
        return out
    for fd in fds:
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        m = re.fullmatch(r"/dev/shm/(fastrtps_[0-9a-f]{16})_el", target)
        if m:
            out.append(Path("/dev/shm", m.group(1)))
    return out


def remove_shm_segments(segments: list[Path]) -> None:
    """Remove segments :func:`own_shm_segments` named, once their process was killed."""
    for seg in segments:
        for p in (seg, seg.with_name(seg.name + "_el")):
            p.unlink(missing_ok=True)
