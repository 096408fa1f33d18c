"""`perception-config estimate`: one estimate through the estimate_pose action, as a robot
program would call it: a line per operator while it runs, Ctrl-C cancels the goal between
operators (the result then holds the hypothesis so far), and the result at the end."""
from __future__ import annotations

import math
import time
from typing import Any, Callable

import rclpy
from action_msgs.msg import GoalStatus
from perception_config_interfaces.action import EstimatePose as EstimatePoseAction
from rclpy.action import ActionClient

from ..launcher.ros_environment import configure_ros_environment

STATUS = {GoalStatus.STATUS_SUCCEEDED: "succeeded", GoalStatus.STATUS_CANCELED: "cancelled",
          GoalStatus.STATUS_ABORTED: "aborted"}


def feedback_line(fb: Any) -> str:
    scores = "  ".join(f"{n}={v:.3f}" if math.isfinite(v) else f"{n}=nan" for n, v in zip(fb.score_names, fb.scores))
    return (f"[{fb.elapsed:6.3f} s] {fb.action:<16} {'ok    ' if fb.ok else 'failed'} {scores}  "
            f"({fb.operators_done} done, {fb.operators_left} left)")


def run_estimate(object_id: str, stamp_ns: int = 0, noise_lambda: float = -1.0, seed: int = 0,
                 max_operations: int = 0, action: str = "estimate_pose", timeout: float = 60.0,
                 say: Callable[[str], None] = print) -> int:
    """Send one goal and print its progress and result; the exit code (0 an estimate was made,
    1 not, 2 rejected or no server, 130 cancelled by Ctrl-C)."""
    configure_ros_environment()
    rclpy.init()
    node = rclpy.create_node(f"estimate_cli_{int(time.time() * 1000) % 10**9}")
    client = ActionClient(node, EstimatePoseAction, action)
    try:
        if not client.wait_for_server(timeout_sec=min(timeout, 20.0)):
            say(f"no {action} action server within {min(timeout, 20.0):g} s: is the configurator running?")
            return 2
        goal = EstimatePoseAction.Goal(object_id=str(object_id), max_operations=int(max_operations),
                                       noise_lambda=float(noise_lambda), seed=int(seed))
        goal.frame.stamp.sec, goal.frame.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
        sent = client.send_goal_async(goal, feedback_callback=lambda m: say(feedback_line(m.feedback)))
        rclpy.spin_until_future_complete(node, sent, timeout_sec=timeout)
        handle = sent.result()
        if handle is None or not handle.accepted:
            say("rejected: the configurator's request queue is full (retry later)" if handle is not None
                else f"no answer to the goal within {timeout:g} s")
            return 2
        result_future = handle.get_result_async()
        cancelled_by_user = False
        deadline = time.monotonic() + timeout
        while not result_future.done() and time.monotonic() < deadline:
            try:
                rclpy.spin_once(node, timeout_sec=0.05)
            except KeyboardInterrupt:
                if not cancelled_by_user:
                    cancelled_by_user = True
                    say("cancelling: the operator in flight finishes first")
                    handle.cancel_goal_async()
        if not result_future.done():
            say(f"no result within {timeout:g} s")
            return 1
        res = result_future.result()
        r = res.result
        p = r.hypothesis.pose.position
        say(f"{STATUS.get(res.status, str(res.status))}: {r.message} after {len(r.operations)} operations "
            f"({r.elapsed:.3f} s); picked={r.picked}; position ({p.x:.4f}, {p.y:.4f}, {p.z:.4f}) m"
            + (f"; estimate_id {r.estimate_id}" if r.estimate_id else ""))
        if cancelled_by_user:
            return 130
        return 0 if r.success else 1
    finally:
        client.destroy()
        node.destroy_node()
        rclpy.try_shutdown()
