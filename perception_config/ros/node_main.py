"""main() of every node process: init, make the nodes, spin, shut down in order.

`spin` runs one node (each node's console script); `run_nodes` several in one process with one
executor (composed.py).
"""
from __future__ import annotations

import signal
import threading
import time
from typing import Any, Callable

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from ..launcher.fastdds_shm import clean_stale_fastdds_shm
from ..launcher.ros_environment import configure_ros_environment
from ..util.allocator import keep_freed_memory
from .managed_node import ManagedNode

# After a shutdown transition finalized every node, the process lives this long (s) before it
# destroys its nodes: the change_state answer is a reliable DDS sample that may still need a
# resend (writers heartbeat every 0.1 s, fastdds_profile.xml). Destroyed at once, a loaded
# machine lost the answer and the lifecycle manager waited its whole timeout for it.
FINALIZED_LINGER = 1.0


def spin(node_factory: Callable[[], Node], args: list[str] | None = None,
         executor_factory: Callable[[], Any] = SingleThreadedExecutor) -> None:
    """main() of a node: run_nodes with this one node."""
    run_nodes([node_factory], args, executor_factory)


def run_nodes(node_factories: list[Callable[[], Node]], args: list[str] | None = None,
              executor_factory: Callable[[], Any] = SingleThreadedExecutor) -> None:
    """Init, make the nodes (a managed node then starts: autostart configures and activates it),
    spin one executor (single-threaded by default) until Ctrl-C, SIGTERM or every node is
    finalized (the lifecycle shutdown transition), then shut the nodes down (a managed node frees
    what it configured), destroy them and shut rclpy down, in that order.

    Signals are Python's (rclpy's handler would shut the context down first, and a node
    destroyed after that leaves its DDS endpoints announced for the lease duration, about
    20 s: clients then see a service that no longer answers). The executor wakes every
    0.2 s so a signal is handled promptly. A node that cannot start (bad parameters, an
    unreadable models folder with autostart) logs why and the process exits 2.
    """
    configure_ros_environment()  # loopback defaults before rclpy starts
    clean_stale_fastdds_shm()  # segments of killed participants (launcher/fastdds_shm.py)
    keep_freed_memory()  # before the numeric work allocates (util/allocator.py)
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    # SIGINT and SIGTERM set a flag the loop checks (every 0.2 s at most), rather than raising
    # KeyboardInterrupt wherever the main thread happens to be: raised inside a __del__ it is
    # "ignored" by Python and the stop was lost. Also when started with SIGINT ignored (a
    # background job of a script inherits that): launchers stop nodes with SIGINT.
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda _signum, _frame: stop.set())
    nodes: list[Node] = []
    executor = None
    try:
        try:
            for factory in node_factories:
                node = factory()
                nodes.append(node)
                if isinstance(node, ManagedNode):
                    node.start()
        except (ValueError, OSError, ParameterException) as exc:  # the last: a value outside its range
            rclpy.logging.get_logger("perception_config").fatal(f"cannot start: {exc}")
            raise SystemExit(2) from None
        executor = executor_factory()
        for node in nodes:
            executor.add_node(node)
        while rclpy.ok() and not stop.is_set() and not all(getattr(n, "finalized", False) for n in nodes):
            executor.spin_once(timeout_sec=0.2)
        if not stop.is_set():  # finalized by a shutdown transition: its answer is still on its way
            linger = time.monotonic() + FINALIZED_LINGER
            while rclpy.ok() and time.monotonic() < linger:
                executor.spin_once(timeout_sec=0.05)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        for node in reversed(nodes):
            try:
                if isinstance(node, ManagedNode):
                    node.shutdown_now()
                elif hasattr(node, "on_exit"):
                    node.on_exit()
            except Exception as exc:  # noqa: BLE001  (the others still stop)
                node.get_logger().error(f"shutdown failed: {exc!r}")
        if executor is not None:
            executor.shutdown()
        for node in reversed(nodes):
            node.destroy_node()
        rclpy.try_shutdown()
