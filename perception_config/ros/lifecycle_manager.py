"""Bring managed nodes up in order, and say which one failed and why.

`perception-config launch` (and replay-check) start the operator nodes and the configurator with
autostart:=false, then drive them here through the lifecycle services every managed node offers
(`<node>/change_state`, `<node>/get_state`; managed_node.py): configure each in order (the
operator nodes first, the configurator last), then activate each in the same order, so the
configurator serves only once the operators do. A transition that fails stops the bring-up:
the node is named with the reason it gave (its `/diagnostics` status, "configure failed: ..."),
and the launcher stops every node (exit 1).

The same by hand, with the ROS 2 command line: `ros2 lifecycle set /generation_node configure`,
then `activate`.
"""
from __future__ import annotations

import os
import time
from typing import Callable

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile

TRANSITIONS = ("configure", "activate", "deactivate", "cleanup", "shutdown")  # labels, from the current state
ORDER = ("generation_node", "refinement_node", "scoring_node", "pick_node", "configurator_node")
MANAGED_EXECUTABLES = ORDER  # the console scripts whose nodes are managed (managed_node.py)
READY_TIMEOUT = 90.0  # s for a node's lifecycle services to appear (five nodes importing torch on 2 cores)
TRANSITION_TIMEOUT = 120.0  # s for one transition (configure loads every model and the policy)


class LifecycleManager:
    """Lifecycle clients for `nodes` (node names, e.g. "generation_node"), on a private node."""

    def __init__(self, nodes: list[str]) -> None:
        self.node = rclpy.create_node(f"perception_config_lifecycle_{os.getpid()}")
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.nodes = list(nodes)
        self.change = {n: self.node.create_client(ChangeState, f"/{n}/change_state") for n in nodes}
        self.get = {n: self.node.create_client(GetState, f"/{n}/get_state") for n in nodes}
        self.status: dict[str, tuple[int, str]] = {}  # "/node" -> (level, message), the latest
        self._status_ns: dict[str, int] = {}  # "/node" -> the stamp (ns) of that status
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, QoSProfile(depth=100))

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        for status in msg.status:
            self.status[status.name] = (int.from_bytes(status.level, "little") if isinstance(status.level, bytes)
                                        else int(status.level), status.message)
            self._status_ns[status.name] = stamp_ns

    def _call(self, client, request, timeout: float):
        if not client.wait_for_service(timeout_sec=timeout):
            return None
        future = client.call_async(request)
        self.executor.spin_until_future_complete(future, timeout_sec=timeout)
        if not future.done():
            client.remove_pending_request(future)
            return None
        return future.result()

    def state(self, name: str, timeout: float = 5.0) -> str | None:
        """The node's lifecycle state label, None when it does not answer."""
        response = self._call(self.get[name], GetState.Request(), timeout)
        return None if response is None else response.current_state.label

    def transition(self, name: str, transition: str, timeout: float = TRANSITION_TIMEOUT) -> tuple[bool, str]:
        """(done, reason): the node's change_state; the reason of a failure from its diagnostics."""
        if transition not in TRANSITIONS:
            raise ValueError(f"unknown transition {transition!r}; one of {', '.join(TRANSITIONS)}")
        request = ChangeState.Request()
        request.transition.label = transition
        sent_ns = self.node.get_clock().now().nanoseconds
        response = self._call(self.change[name], request, timeout)
        if response is None:
            return False, f"its {transition} did not answer within {timeout:g} s"
        if response.success:
            return True, ""
        return False, self._reason(name, transition, sent_ns)

    def fresh_status(self, name: str, timeout: float = 2.5) -> tuple[int, str] | None:
        """The node's next /diagnostics status (level, message) within `timeout` s, else None."""
        key = f"/{name}"
        self.status.pop(key, None)
        deadline = time.monotonic() + timeout
        while key not in self.status and time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.1)
        return self.status.get(key)

    def _reason(self, name: str, transition: str, since_ns: int) -> str:
        """The node's own words for a failed transition: its diagnostics status stamped since the
        request (published when it failed, possibly before its answer came), waited for up to 2 s."""
        deadline = time.monotonic() + 2.0
        key = f"/{name}"
        while True:
            _, message = self.status.get(key, (0, ""))
            if self._status_ns.get(key, 0) >= since_ns and f"{transition} failed" in message:
                return message.split(f"{transition} failed: ", 1)[-1]
            if time.monotonic() >= deadline:
                break
            self.executor.spin_once(timeout_sec=0.1)
        state = self.state(name) or "not answering"
        return f"{transition} refused (state {state}; see the node's log)"

    def bring_up(self, say: Callable[[str], None], stop: Callable[[], bool] = lambda: False,
                 ready_timeout: float = READY_TIMEOUT) -> bool:
        """Configure every node, then activate every node, in ORDER. False (and why, said) on the
        first failure or when `stop()` turns true."""
        nodes = sorted(self.nodes, key=lambda n: ORDER.index(n) if n in ORDER else len(ORDER))
        deadline = time.monotonic() + ready_timeout
        for name in nodes:
            while not self.change[name].wait_for_service(timeout_sec=0.2):
                if stop():
                    return False
                if time.monotonic() > deadline:
                    say(f"{name} did not offer its lifecycle services within {ready_timeout:g} s")
                    return False
        for transition in ("configure", "activate"):
            for name in nodes:
                if stop():
                    return False
                started = time.monotonic()
                done, reason = self.transition(name, transition)
                if not done:
                    say(f"{name} failed to {transition}: {reason}")
                    return False
                say(f"{name}: {transition}d ({time.monotonic() - started:.1f} s)"
                    if transition == "configure" else f"{name}: active")
        return True

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()


def bring_up_launched(launcher, say: Callable[[str], None]) -> bool:
    """Drive the managed nodes a Launcher started (autostart:=false) to active (rclpy is
    initialised and shut down here when it was not already)."""
    from ..launcher.ros_environment import configure_ros_environment
    from ..launcher.supervisor import describe_exit

    names = [spec.name for spec in launcher.requested if spec.params.get("autostart") is False]
    if not names:
        return True
    own = not rclpy.ok()
    if own:
        configure_ros_environment()
        rclpy.init()
    manager = LifecycleManager(names)
    try:
        if manager.bring_up(say, stop=lambda: launcher.stop_requested or any(
                n not in launcher.running() for n in names)):
            return True
        for name in names:
            if name not in launcher.running():
                say(f"{name} exited ({describe_exit(launcher.returncode(name))}) before it was active")
                break
        return False
    finally:
        manager.close()
        if own:
            rclpy.try_shutdown()
