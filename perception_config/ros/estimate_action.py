"""estimate_pose as an action (EstimatePose.action): feedback after every operator, cancel between them.

The configurator serves it beside the `estimate_pose` service (which stays for simple clients),
on the same request queue: one estimate at a time, in arrival order, `request_queue` waiting.

- **Goal**: the service's request. A goal that cannot be queued (the queue is full) is rejected
  at once, as is a goal sent while the node is not active (managed_node.py); the action protocol
  carries no reason with a rejection: the node logs it, and /diagnostics shows the queue and
  state. A goal whose fields are invalid is accepted and aborted at once, the reason in the
  result's message.
- **Feedback** after every operator: the action taken, whether it succeeded, the scores of the
  hypothesis after it, the seconds since the goal was accepted, the operators done and left.
- **Cancel** takes effect between operators: the operator in flight finishes, then the result
  carries the hypothesis so far with `cancelled` true and `picked` false (state CANCELED).
- **Result**: the service's response plus `cancelled`; SUCCEEDED when an estimate was made
  (picked or not), ABORTED when not (a bad goal, a node down, `estimate_timeout`).
  `estimate_timeout` counts from the goal's acceptance, as the service's from its arrival.
"""
from __future__ import annotations

import time
from typing import Any

from perception_config_interfaces.action import EstimatePose as EstimatePoseAction
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup

from .request_fields import parse_estimate_fields
from .request_queue import service_qos

CANCELLED = "cancelled after"  # how the configurator's answer to a cancelled estimate begins


class EstimateAction:
    """The action server of one configurator node (module docstring). `node` is the
    ConfiguratorNode: its request queue, `estimate` and `operation_limit`."""

    def __init__(self, node: Any, name: str = "estimate_pose") -> None:
        self.node = node
        # keep-all, as the service (request_queue.service_qos): no goal, cancel or result request
        # of a burst is overwritten before the node takes it
        self.server = ActionServer(node, EstimatePoseAction, name, execute_callback=self._execute,
                                   goal_callback=self._on_goal, cancel_callback=self._on_cancel,
                                   callback_group=ReentrantCallbackGroup(), goal_service_qos_profile=service_qos(),
                                   result_service_qos_profile=service_qos(),
                                   cancel_service_qos_profile=service_qos())

    def _on_goal(self, goal: Any) -> GoalResponse:
        """Admit the goal to the request queue, or reject it at once (the queue is full, or the
        node is not active)."""
        if not self.node.serving:
            self.node.get_logger().warning(f"estimate_pose goal rejected: {self.node.refusal('estimate_pose')}",
                                           throttle_duration_sec=1.0)
            return GoalResponse.REJECT
        busy = self.node.requests.busy()
        if busy is not None:
            self.node.get_logger().warning(f"estimate_pose goal rejected: {busy}", throttle_duration_sec=1.0)
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    def _on_cancel(self, goal_handle: Any) -> CancelResponse:
        return CancelResponse.ACCEPT  # honoured between operators (module docstring)

    async def _execute(self, goal_handle: Any) -> Any:
        accepted = time.monotonic()
        requests = self.node.requests  # admitted by _on_goal on this queue
        goal = goal_handle.request
        try:
            try:
                stamp_ns = parse_estimate_fields(goal)
            except ValueError as exc:
                goal_handle.abort()
                return EstimatePoseAction.Result(success=False, message=str(exc))
            limit = self.node.operation_limit(int(goal.max_operations))
            done = [0]

            def feedback(action: str, info: dict[str, Any]) -> None:
                done[0] += 1
                scores = info.get("scores") or {}
                goal_handle.publish_feedback(EstimatePoseAction.Feedback(
                    action=action, ok=bool(info.get("ok")), scores=[float(v) for v in scores.values()],
                    score_names=list(scores), elapsed=time.monotonic() - accepted, operators_done=done[0],
                    operators_left=max(0, limit - done[0])))

            response = await requests.run(
                self.node.estimate, stamp_ns, goal.object_id, goal.max_operations, goal.noise_lambda, goal.seed,
                accepted, lambda: goal_handle.is_cancel_requested, feedback)
            result = EstimatePoseAction.Result(
                success=response.success, message=response.message, hypothesis=response.hypothesis,
                picked=response.picked, operations=list(response.operations),
                operation_elapsed=list(response.operation_elapsed), elapsed=response.elapsed,
                estimate_id=response.estimate_id, cancelled=response.message.startswith(CANCELLED))
            if result.cancelled:
                goal_handle.canceled()
            elif result.success:
                goal_handle.succeed()
            else:
                goal_handle.abort()
            return result
        except Exception as exc:  # noqa: BLE001  (the last resort: answer, log, keep serving)
            self.node.get_logger().error(f"estimate_pose goal failed: {exc!r}")
            if goal_handle.is_active:
                goal_handle.abort()
            return EstimatePoseAction.Result(success=False, message=f"internal error: {exc!r}"[:500])
        finally:
            requests.done()

    def destroy(self) -> None:
        self.server.destroy()
