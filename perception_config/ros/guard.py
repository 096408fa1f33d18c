"""The last-resort guard: no callback of a project node raises out of its executor.

An exception that leaves a callback ends `spin` and with it the node (and `perception-config
launch` then stops every node). Each node validates its requests at the edge (request_fields.py)
and answers a bad one with success=false; this guard is for what validation did not foresee:

- a service callback that raises is answered success=false, "internal error: <the exception>",
  and logged as an error;
- a subscription or timer callback that raises is logged as an error and the message dropped;
- a parameter callback that raises refuses the change with the exception as the reason.

The error lines are throttled per callback (at most one a second), so a client that keeps
sending the same bad request cannot flood the log. `GuardedNode` applies the guard to every
service, subscription, timer and parameter callback created on it, including those its helpers
(camera_frames.py, debug_view.py, ...) create through it.
"""
from __future__ import annotations

import functools
import inspect
from typing import Any, Callable

from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node

THROTTLE = 1.0  # s between two error lines of one callback


def _answer_error(node: Node, what: str, response: Any, exc: BaseException) -> Any:
    node.get_logger().error(f"{what} failed: {exc!r} (answered success=false; the node keeps serving)",
                            throttle_duration_sec=THROTTLE)
    health = getattr(node, "health", None)  # diagnostics.Health, where the node keeps one
    if health is not None:
        health.internal_error(f"{what}: {exc!r}")
    try:
        response.success = False
        response.message = f"internal error: {exc!r}"[:500]
    except (AttributeError, TypeError, AssertionError):
        pass
    return response


def guard_service(node: Node, what: str, callback: Callable[..., Any]) -> Callable[..., Any]:
    """A service callback (plain or async) that answers instead of raising."""
    if inspect.iscoroutinefunction(callback):
        @functools.wraps(callback)
        async def guarded_async(request: Any, response: Any) -> Any:
            try:
                return await callback(request, response)
            except Exception as exc:  # noqa: BLE001  (the last resort)
                return _answer_error(node, what, response, exc)
        return guarded_async

    @functools.wraps(callback)
    def guarded(request: Any, response: Any) -> Any:
        try:
            return callback(request, response)
        except Exception as exc:  # noqa: BLE001  (the last resort)
            return _answer_error(node, what, response, exc)
    return guarded


def guard_callback(node: Node, what: str, callback: Callable[..., Any]) -> Callable[..., Any]:
    """A subscription or timer callback (plain or async) that logs instead of raising."""
    if inspect.iscoroutinefunction(callback):
        @functools.wraps(callback)
        async def guarded_async(*args: Any) -> Any:
            try:
                return await callback(*args)
            except Exception as exc:  # noqa: BLE001  (the last resort)
                node.get_logger().error(f"{what} failed: {exc!r} (dropped)", throttle_duration_sec=THROTTLE)
        return guarded_async

    @functools.wraps(callback)
    def guarded(*args: Any) -> Any:
        try:
            return callback(*args)
        except Exception as exc:  # noqa: BLE001  (the last resort)
            node.get_logger().error(f"{what} failed: {exc!r} (dropped)", throttle_duration_sec=THROTTLE)
    return guarded


class GuardedNode(Node):
    """A Node whose service, subscription, timer and parameter callbacks are guarded (module docstring)."""

    def create_service(self, srv_type: Any, srv_name: str, callback: Callable[..., Any], **kwargs: Any) -> Any:
        return super().create_service(srv_type, srv_name, guard_service(self, f"service {srv_name}", callback),
                                      **kwargs)

    def create_subscription(self, msg_type: Any, topic: str, callback: Callable[..., Any], qos_profile: Any,
                            **kwargs: Any) -> Any:
        return super().create_subscription(msg_type, topic, guard_callback(self, f"topic {topic}", callback),
                                           qos_profile, **kwargs)

    def create_timer(self, timer_period_sec: float, callback: Callable[..., Any] | None, *args: Any,
                     **kwargs: Any) -> Any:
        if callback is not None:
            callback = guard_callback(self, f"timer {getattr(callback, '__name__', 'callback')}", callback)
        return super().create_timer(timer_period_sec, callback, *args, **kwargs)

    def add_on_set_parameters_callback(self, callback: Callable[..., SetParametersResult]) -> None:
        @functools.wraps(callback)
        def guarded(params: Any) -> SetParametersResult:
            try:
                return callback(params)
            except Exception as exc:  # noqa: BLE001  (the last resort)
                self.get_logger().error(f"parameter callback failed: {exc!r} (change refused)",
                                        throttle_duration_sec=THROTTLE)
                return SetParametersResult(successful=False, reason=f"internal error: {exc!r}"[:500])
        return super().add_on_set_parameters_callback(guarded)
