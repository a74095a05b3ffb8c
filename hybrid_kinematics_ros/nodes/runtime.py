"""One way to run a node's process: init, build the node (a startup error is one FATAL line and exit 1),
spin, and always clean up, also on Ctrl-C and external shutdown. ``kill -USR1 <pid>`` prints every
thread's Python stack to stderr (the node's log), to see where a process that will not stop is waiting."""

from __future__ import annotations

import faulthandler
import signal
from collections.abc import Callable

import rclpy
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.executors import Executor, ExternalShutdownException
from rclpy.node import Node


def read_only_parameter(node: Node, name: str, default, description: str):
    """Declare a described, read-only parameter and return its value. The nodes here read parameters once,
    at start (or on reload), so changing them at run time would silently do nothing: refuse it instead."""
    return node.declare_parameter(name, default, ParameterDescriptor(description=description, read_only=True)).value


class StartupError(RuntimeError):
    """The node cannot serve with its parameters; the message says which one to fix."""


def run_node(
    name: str,
    make_node: Callable[[], Node],
    make_executor: Callable[[], Executor],
    args: list[str] | None = None,
    spin: Callable[[Executor], None] | None = None,
    on_exit: Callable[[Node], None] | None = None,
    **init_kwargs,
) -> int:
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    rclpy.init(args=args, **init_kwargs)
    try:
        node = make_node()
    except StartupError as exc:
        rclpy.logging.get_logger(name).fatal(f"cannot start: {exc}")
        rclpy.try_shutdown()
        return 1
    executor = make_executor()
    executor.add_node(node)
    try:
        (spin or (lambda ex: ex.spin()))(executor)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if on_exit is not None:
            on_exit(node)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
