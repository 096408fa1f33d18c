"""Each node's health on `/diagnostics` (diagnostic_msgs/DiagnosticArray), once a second.

One DiagnosticStatus per node, named after it, with the figures a cell integrator watches (rqt's
Runtime Monitor, Foxglove or `ros2 topic echo /diagnostics` show them):

| key | what |
|---|---|
| `queue` | requests admitted and not yet answered (waiting or being served) |
| `queue_limit` | the `request_queue` parameter |
| `queue_high_water` | the most ever held at once |
| `answered` | requests answered since the start |
| `busy_refusals` | requests refused as busy since the start |
| `internal_errors` | requests answered "internal error" by the last-resort guard since the start |
| `last_error` | the last failure answered (its message, shortened), "" = none |
| the node's own | e.g. the configurator's `policy_version`, `operator_timeouts`, `deadlines_reached` |

| `state` | the lifecycle state: active, inactive, unconfigured (managed_node.py) |

Level: ERROR when the last configure failed (the message gives the reason) or an internal error
happened in the last period (since the previous status); WARN when the node is not active (it
refuses requests) or requests were refused busy or failed in the period (the configurator: an
operator that did not answer, a deadline reached); OK otherwise; the message says why.
"""
from __future__ import annotations

from typing import Any, Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node

PERIOD = 1.0  # s
TOPIC = "/diagnostics"
LEVELS = {"OK": DiagnosticStatus.OK, "WARN": DiagnosticStatus.WARN, "ERROR": DiagnosticStatus.ERROR}


class Health:
    """What a node counts for its diagnostics (module docstring); updated from any thread."""

    def __init__(self) -> None:
        self.answered = 0
        self.failed = 0  # answered success=false, other than busy
        self.internal_errors = 0
        self.last_error = ""
        self.extra: dict[str, Any] = {}  # the node's own figures
        self._seen = (0, 0, 0, {})  # failed, internal, refusals and the warn counters at the last status

    def failure(self, message: str) -> None:
        self.failed += 1
        self.last_error = str(message)[:200]

    def internal_error(self, message: str) -> None:
        self.internal_errors += 1
        self.failure(message)


class _NoQueue:
    held = depth = most_held = refused = 0


class NodeDiagnostics:
    """Publishes the node's status every PERIOD s. The node's `requests` (its RequestQueue, once
    configured) gives the queue figures; `extra()`: the node's own figures (a dict); `warn_keys`:
    those among them that count events and make the status WARN when they grew since the last one.
    A managed node's `diagnostic_state()` gives the level while it does not serve."""

    def __init__(self, node: Node, health: Health,
                 extra: Callable[[], dict[str, Any]] | None = None, warn_keys: tuple[str, ...] = ()) -> None:
        self.node, self.health = node, health
        self.extra, self.warn_keys = extra, warn_keys
        self.pub = node.create_publisher(DiagnosticArray, TOPIC, 10)
        self.timer = node.create_timer(PERIOD, self.publish, callback_group=MutuallyExclusiveCallbackGroup())

    def status(self) -> DiagnosticStatus:
        h = self.health
        q = getattr(self.node, "requests", None) or _NoQueue()
        extra = dict(self.extra()) if self.extra is not None and getattr(self.node, "configured", True) else {}
        not_serving = self.node.diagnostic_state() if hasattr(self.node, "diagnostic_state") else None
        failed0, internal0, refused0, warn0 = h._seen
        grew = [k for k in self.warn_keys if int(extra.get(k, 0)) > int(warn0.get(k, 0))]
        if not_serving is not None:
            level, message = not_serving
        elif h.internal_errors > internal0:
            level, message = "ERROR", f"{h.internal_errors - internal0} internal error(s): {h.last_error}"
        elif q.refused > refused0 or h.failed > failed0 or grew:
            parts = []
            if q.refused > refused0:
                parts.append(f"{q.refused - refused0} refused busy")
            if h.failed > failed0:
                parts.append(f"{h.failed - failed0} failed")
            parts += [f"{k} {int(extra[k]) - int(warn0.get(k, 0))}" for k in grew]
            level, message = "WARN", ", ".join(parts) + " in the last second"
        else:
            level, message = "OK", "serving"
        h._seen = (h.failed, h.internal_errors, q.refused, {k: extra.get(k, 0) for k in self.warn_keys})
        values = {"queue": q.held, "queue_limit": q.depth, "queue_high_water": q.most_held, "answered": h.answered,
                  "busy_refusals": q.refused, "internal_errors": h.internal_errors, "last_error": h.last_error,
                  **({"state": self.node.state_label()} if hasattr(self.node, "state_label") else {}), **extra}
        return DiagnosticStatus(level=LEVELS[level], name=self.node.get_fully_qualified_name(), message=message,
                                hardware_id="", values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])

    def publish(self) -> None:
        msg = DiagnosticArray(status=[self.status()])
        msg.header.stamp = self.node.get_clock().now().to_msg()
        self.pub.publish(msg)
