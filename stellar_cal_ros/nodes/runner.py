"""How a node executable runs: ``--help``, init, spin until shutdown, one-line errors."""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any

import rclpy
from rclpy.executors import ExternalShutdownException

from stellar_cal_ros.errors import StellarCalError


def run_node(name: str, factory: Callable[[], Any], usage: Callable[[], str],
             argv: list[str] | None = None, executor: Callable[[], Any] | None = None,
             finish: Callable[[Any], None] | None = None) -> int:
    """Run the node ``factory()`` until shutdown; 0, or 2 on a parameter / file error.

    ``finish(node)`` runs on the way out (checkpoint, final report).  The executor spins
    in a Python loop so Ctrl-C / SIGTERM reach the interpreter between calls
    (``EventsExecutor.spin()`` waits in C++ and does not return on SIGINT).
    """
    args = list(argv if argv is not None else sys.argv)
    ros_args = args.index("--ros-args") if "--ros-args" in args else len(args)
    if any(a in ("-h", "--help") for a in args[1:ros_args]):
        print(usage())
        return 0
    rclpy.init(args=args)
    node = None
    code = 0
    try:
        node = factory()
        if executor is None:
            from rclpy.executors import SingleThreadedExecutor

            ex = SingleThreadedExecutor()
        else:
            ex = executor()
        ex.add_node(node)
        while rclpy.ok():
            ex.spin_once(timeout_sec=0.2)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ValueError, OSError, StellarCalError) as exc:  # parameters, prior file
        print(f"{name}: {exc}", file=sys.stderr)
        code = 2
    finally:
        if node is not None:
            if finish is not None:
                finish(node)
            node.destroy_node()
        rclpy.try_shutdown()
    return code
