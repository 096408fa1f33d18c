"""In-process calls between nodes composed into one process (composed.py).

rclpy has no intra-process transport: two nodes of one process still serialise every request
and pass it through the middleware. In a composed cell the configurator's operator calls take a
shorter path: the operator node answers the request object itself (`OperatorNode.answer_here`)
as it answers a request that came through the middleware: the same checks and refusals, the
same worker and queue (in turn with outside requests), the same answer and its `elapsed`,
counted in the node's diagnostics. The calling thread waits for it (up to the call's timeout)
without the executors' hand-offs.
Nothing else changes: every operator service is still served through the middleware to any
outside caller, and the configurator still publishes each estimate's trace and pose.

Only a process that enables it (composed.py) registers services; elsewhere `find` is None and
the calls go through the middleware.
"""
from __future__ import annotations

import threading
from typing import Any

_enabled = False
_services: dict[str, "LocalService"] = {}
_lock = threading.Lock()


class LocalService:
    """One service of an operator node of this process (`OperatorNode.answer_here`)."""

    def __init__(self, node: Any, name: str) -> None:
        self.node, self.name = node, name

    def call(self, request: Any, timeout: float) -> Any | None:
        """The response, or None when it did not come within `timeout` s."""
        return self.node.answer_here(self.name, request, timeout)


def enable() -> None:
    """Let the nodes of this process register their services (composed.py, before the nodes start)."""
    global _enabled
    _enabled = True


def register(resolved_name: str, service: LocalService) -> None:
    if _enabled:
        with _lock:
            _services[resolved_name] = service


def unregister(resolved_name: str) -> None:
    with _lock:
        _services.pop(resolved_name, None)


def find(resolved_name: str) -> LocalService | None:
    if not _enabled:
        return None
    with _lock:
        return _services.get(resolved_name)
