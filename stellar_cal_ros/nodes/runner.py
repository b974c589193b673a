"""How a node executable runs: ``--help``, init, spin until shutdown, one-line errors."""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any

import rclpy
from rclpy.executors import ExternalShutdownException

from stellar_cal_ros.errors import StellarCalError


def help_requested(args: list[str]) -> bool:
    """Whether ``-h``/``--help`` is among the arguments before ``--ros-args``."""
    ros_args = args.index("--ros-args") if "--ros-args" in args else len(args)
    return any(a in ("-h", "--help") for a in args[1:ros_args])


def check_parameter_names(node: Any) -> None:
    """Raise ValueError naming every ``-p NAME:=...`` the node does not declare.

    rclpy keeps an override it has no declaration for and says nothing: a typo
    (``outptu_file``) would leave the real parameter at its default (no file written at
    shutdown).  Call after the node declared its parameters.
    """
    import difflib

    declared = set(node._parameters)
    unknown = [n for n in getattr(node, "_parameter_overrides", {})
               if n not in declared and not n.startswith("qos_overrides.")]
    if unknown:
        hints = []
        for n in sorted(unknown):
            close = difflib.get_close_matches(n, sorted(declared), n=1, cutoff=0.6)
            hints.append(f"{n!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
        raise ValueError(f"invalid parameters: unknown parameter {', '.join(hints)}; "
                         f"`{node.get_name()} --help` lists them")


def declare(node: Any, name: str, default: Any, descriptor: Any) -> None:
    """``node.declare_parameter`` with the errors a user makes turned into one line.

    A whole number given for a float parameter (``-p rate:=0``, ``-p field_period_s:=10``)
    is taken as that float (rclpy alone refuses an INTEGER for a DOUBLE); a value of the
    wrong type or out of range raises ValueError naming the parameter.
    """
    from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
    from rclpy.parameter import Parameter

    given = getattr(node, "_parameter_overrides", {}).get(name)
    if isinstance(default, float) and given is not None and \
            given.type_ == Parameter.Type.INTEGER:
        node._parameter_overrides[name] = Parameter(name, Parameter.Type.DOUBLE,
                                                    float(given.value))
    try:
        node.declare_parameter(name, default, descriptor)
    except (InvalidParameterValueException, InvalidParameterTypeException) as exc:
        raise ValueError(f"invalid parameters: {exc}") from exc


def run_node(name: str, factory: Callable[[], Any], usage: Callable[[], str],
             argv: list[str] | None = None, executor: Callable[[], Any] | None = None,
             finish: Callable[[Any], None] | None = None) -> int:
    """Run the node ``factory()`` until shutdown; 0, or 2 on a parameter / file error.

    ``finish(node)`` runs on the way out (checkpoint, final report).  The executor spins
    in a Python loop so Ctrl-C / SIGTERM reach the interpreter between calls
    (``EventsExecutor.spin()`` waits in C++ and does not return on SIGINT).
    """
    args = list(argv if argv is not None else sys.argv)
    if help_requested(args):
        print(usage())
        return 0
    try:
        rclpy.init(args=args)
    except Exception as exc:  # noqa: BLE001 - RCLError: malformed --ros-args (-p name:=)
        print(f"{name}: {str(exc).split(', at ')[0]}", file=sys.stderr)
        return 2
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
