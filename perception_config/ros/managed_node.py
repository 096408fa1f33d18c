"""Managed (lifecycle) nodes: configure loads, activate serves, deactivate stops taking requests.

The operator nodes and the configurator are rclpy lifecycle nodes (`ros2 lifecycle`, the
`<node>/change_state` and `<node>/get_state` services, `<node>/transition_event`):

- **configure**: loads and checks everything it serves with (models, pipeline, policy, stores)
  and creates its services and subscriptions. A bad file fails the transition: the node stays
  unconfigured and says why (an ERROR line in its log and on `/diagnostics`).
- **activate**: serves; requests are taken.
- **deactivate**: stops taking requests (each is answered success=false "<node> is inactive:
  ..."); the ones already queued are answered.
- **cleanup**: frees what configure made (refused while requests are still being answered).
- **shutdown**: from any state, frees what is configured; the node is finalized and its
  process ends.

With `autostart` (the default) a node configures and activates itself when it starts, as an
unmanaged node would, and a failed configure ends its process (exit 2, "cannot start: <why>");
`perception-config launch` starts them with autostart:=false and drives them
(lifecycle_manager.py), so that a cell comes up in order and a misconfigured node is reported
by name before anything serves.

A subclass implements `setup()` (what configure does; it may raise ValueError/OSError naming the
problem) and `teardown()` (what it made besides ROS entities). Every service, subscription,
publisher, timer and client created during setup is destroyed by cleanup. Its services check
`serving` first (`refusal()` gives the answer of an inactive node).
"""
from __future__ import annotations

from typing import Any

from rclpy.client import Client
from rclpy.guard_condition import GuardCondition
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.publisher import Publisher
from rclpy.service import Service
from rclpy.subscription import Subscription
from rclpy.timer import Timer

from .diagnostics import Health
from .guard import GuardedNode
from .parameters import NodeParameter, declare

MANAGED_PARAMETERS = (
    NodeParameter("autostart", True, "true: configure and activate when the node starts (it serves at once; a "
                  "failed configure ends the process); false: wait unconfigured for a lifecycle manager "
                  "(perception-config launch, `ros2 lifecycle set`)", read_only=True),
)

SUCCESS, FAILURE = TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.FAILURE


class ManagedNode(GuardedNode, LifecycleNode):
    """A guarded lifecycle node (module docstring). `parameters` are declared before anything else."""

    def __init__(self, name: str, parameters: tuple[NodeParameter, ...], **kwargs: Any) -> None:
        super().__init__(name, **kwargs)
        declare(self, (*parameters, *MANAGED_PARAMETERS))
        self.health = Health()
        self.serving = False
        self.configured = False
        self.finalized = False
        self.configure_error = ""  # why the last configure failed ("" = it did not)
        self.serving_line = ""  # logged when the node starts serving (set by setup)
        self._made: list[Any] = []  # entities created by setup, destroyed by cleanup
        self._recording = False

    def start(self) -> None:
        """autostart: configure and activate now (ValueError with the reason when configure
        fails); else wait for a manager. Called once the subclass is constructed."""
        if not self.get_parameter("autostart").value:
            self.get_logger().info("unconfigured: waiting for a lifecycle manager (perception-config launch, "
                                   f"or `ros2 lifecycle set {self.get_fully_qualified_name()} configure` then "
                                   "activate)")
            return
        if self.trigger_configure() != SUCCESS:
            raise ValueError(self.configure_error or "configure failed")
        self.trigger_activate()

    # -- what a subclass provides ------------------------------------------------------------
    def setup(self) -> None:
        """Load and check what the node serves with, create its services (raise on a problem)."""

    def teardown(self) -> None:
        """Free what setup made, besides the ROS entities (also after a setup that failed half-way)."""

    def diagnostic_state(self) -> tuple[str, str] | None:
        """(level, message) for /diagnostics when the node is not serving; None when it is."""
        if self.serving:
            return None
        if self.configure_error:
            return "ERROR", f"configure failed: {self.configure_error}"
        return "WARN", f"{self.state_label()}: not serving"

    def state_label(self) -> str:
        return self._state_machine.current_state[1]

    def refusal(self, what: str) -> str:
        """The answer to a request that arrives while the node does not serve."""
        return (f"{self.get_name()} is {self.state_label()}: {what} is not served until it is activated "
                f"(perception-config launch activates it; ros2 lifecycle set {self.get_fully_qualified_name()} "
                "activate)")

    # -- entities made by setup ----------------------------------------------------------------
    def _made_now(self, entity: Any) -> Any:
        if getattr(self, "_recording", False):  # Node.__init__ creates its own entities first
            self._made.append(entity)
        return entity

    def create_service(self, *args: Any, **kwargs: Any) -> Any:
        return self._made_now(super().create_service(*args, **kwargs))

    def create_subscription(self, *args: Any, **kwargs: Any) -> Any:
        return self._made_now(super().create_subscription(*args, **kwargs))

    def create_publisher(self, *args: Any, **kwargs: Any) -> Any:
        return self._made_now(super().create_publisher(*args, **kwargs))

    def create_timer(self, *args: Any, **kwargs: Any) -> Any:
        return self._made_now(super().create_timer(*args, **kwargs))

    def create_client(self, *args: Any, **kwargs: Any) -> Any:
        return self._made_now(super().create_client(*args, **kwargs))

    def create_guard_condition(self, *args: Any, **kwargs: Any) -> Any:
        return self._made_now(super().create_guard_condition(*args, **kwargs))

    def _destroy_made(self) -> None:
        for entity in reversed(self._made):
            try:
                if isinstance(entity, Service):
                    self.destroy_service(entity)
                elif isinstance(entity, Subscription):
                    self.destroy_subscription(entity)
                elif isinstance(entity, Publisher):
                    self.destroy_publisher(entity)
                elif isinstance(entity, Timer):
                    self.destroy_timer(entity)
                elif isinstance(entity, Client):
                    self.destroy_client(entity)
                elif isinstance(entity, GuardCondition):
                    self.destroy_guard_condition(entity)
            except Exception as exc:  # noqa: BLE001  (free the rest)
                self.get_logger().warning(f"cleanup: {entity!r} not destroyed: {exc!r}")
        self._made = []

    def _free(self) -> None:
        try:
            self.teardown()
        finally:
            self._destroy_made()
            self.configured = False

    # -- transitions -----------------------------------------------------------------------------
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._recording = True
        try:
            self.setup()
        except Exception as exc:  # noqa: BLE001  (a bad file or value: the transition fails with the reason)
            self._recording = False
            reason = str(exc) if isinstance(exc, (ValueError, OSError)) else repr(exc)
            self.configure_error = reason or type(exc).__name__
            self.get_logger().error(f"configure failed: {self.configure_error}")
            self.health.failure(f"configure failed: {self.configure_error}")
            try:
                self._free()
            except Exception as free_exc:  # noqa: BLE001
                self.get_logger().warning(f"after the failed configure, cleanup failed too: {free_exc!r}")
            self.publish_diagnostics()
            return FAILURE
        self._recording = False
        self.configured = True
        self.configure_error = ""
        self.get_logger().info("configured")
        return SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.serving = True
        self.get_logger().info(self.serving_line or "serving")
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.serving = False
        self.get_logger().info("inactive: new requests are refused, queued ones answered")
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        held = self.requests_held()
        if held:
            self.get_logger().warning(f"cleanup refused: {held} request(s) still being answered; try again")
            return FAILURE
        self._free()
        self.get_logger().info("cleaned up: unconfigured")
        return SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.serving = False
        if self.configured:
            self._free()
        self.finalized = True
        return SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.serving = False
        self.get_logger().error("a transition raised: freeing what was configured (back to unconfigured)")
        if self.configured:
            self._free()
        return SUCCESS

    def shutdown_now(self) -> None:
        """At process exit: the shutdown transition from whatever state (frees what is configured)."""
        if self.finalized:
            return
        try:
            self.trigger_shutdown()
        except Exception:  # noqa: BLE001  (a state with no shutdown transition: free directly)
            self.serving = False
            if self.configured:
                self._free()
        self.finalized = True

    def destroy_node(self) -> None:
        """rclpy's LifecycleNode does not destroy its state machine, which holds the node: the
        process then exits with its DDS participant alive and Fast DDS leaves its shared-memory
        segments in /dev/shm. Its services first, then the state machine, then the node."""
        for name in ("_service_change_state", "_service_get_state", "_service_get_available_states",
                     "_service_get_available_transitions", "_service_get_transition_graph"):
            service = getattr(self, name, None)
            if service is not None:
                self.destroy_service(service)
        machine = getattr(self, "_state_machine", None)
        if machine is not None:
            machine.destroy_when_not_in_use()
        super().destroy_node()

    # -- hooks for the base's helpers --------------------------------------------------------------
    def requests_held(self) -> int:
        requests = getattr(self, "requests", None)
        return int(getattr(requests, "held", 0)) if requests is not None else 0

    def publish_diagnostics(self) -> None:
        diagnostics = getattr(self, "diagnostics", None)
        if diagnostics is not None:
            try:
                diagnostics.publish()
            except Exception:  # noqa: BLE001  (diagnostics never fail a transition)
                pass
