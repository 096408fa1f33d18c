"""The cell simulation's driver: this process's view of the cell, and the estimates one after the other.

`CellNode` learns which frame is being replayed (and its objects) from the replayed ground truth,
or, in a cell without ground truth (`--labels robot`), from `perception/frame_info` and the
simulator's hidden truth; it collects the operator traces and the serving policy version. `drive`
estimates every object of each new frame in turn (the order and the records are described in
ros/cell_sim_run.py) and, with a simulated robot (ros/cell_sim_robot.py), reports each estimate's
pick outcome as a robot program does.
"""
from __future__ import annotations

import contextlib
import os
import time
from collections import deque
from typing import Callable

import rclpy
from perception_config_interfaces.msg import ObjectPoses, OperatorTrace
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String
from tqdm import tqdm

from ..bench.cell_sim import DEFAULT_WINDOW, EstimateLog, charged_time, first_pick_success, rolling_mean
from ..learning.evaluation import episode_seed
from ..util.stop_signals import Interrupted, StopSignals
from .cell_sim_robot import FRAME_INFO, SimulatedRobot, frame_info_stamp
from .estimate_client import EstimateClient

TRACE_WAIT_S = 2.0  # the trace is published before the answer is sent; it may arrive a moment after it


def running_elsewhere(names: tuple[str, ...], wait: float = 2.0, settle: float = 45.0) -> list[str]:
    """The nodes of `names` on this ROS domain (another cell: a launch, a replay-check, a
    cell-sim): looked for during `wait` s of discovery; nodes seen must still be there after up to
    `settle` s (a cell that is stopping, e.g. a configurator waiting for its learner, leaves the
    graph within seconds; a process killed before it left stays announced for Fast DDS's lease
    duration, 20 s).

    The graph is read by a participant of its own (a fresh rclpy context), not by this process's
    long-lived one: that one's graph cache can keep a stopped node for good when the node's last
    announcement arrives after its participant's removal (ros2/ros2#514), and a second cell-sim
    run from one process was refused for the first one's nodes after they had exited. A fresh
    participant learns only the participants alive now. Two cells on one domain answer each
    other's requests."""
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node(f"cell_sim_graph_{os.getpid()}", context=context)
    try:
        def seen(seconds: float) -> set[str]:
            deadline = time.monotonic() + seconds
            found: set[str] = set()
            while time.monotonic() < deadline:
                time.sleep(0.1)
                found |= {n for n in node.get_node_names() if n in names}
            return found

        found = seen(wait)
        deadline = time.monotonic() + settle
        while found and time.monotonic() < deadline:
            found = seen(0.5)
        return sorted(found)
    finally:
        node.destroy_node()
        context.try_shutdown()


class CellNode:
    """This process's view of the cell: the replayed frames' ground truth, the operator traces
    and the serving policy version, received while an estimate is awaited (EstimateClient spins
    the same node)."""

    def __init__(self, node: Node, hidden: dict[tuple[int, int], list[str]] | None = None) -> None:
        """`hidden`: in a cell without ground truth, each image's object ids by (scene_id, im_id)
        (the simulator's own knowledge); frames are then taken from perception/frame_info."""
        self.node = node
        self.fresh: list[tuple[int, list[str]]] = []  # frames arrived since the cell last got ready
        self.traces: deque[OperatorTrace] = deque(maxlen=64)
        self.version: str | None = None
        self.hidden = hidden
        if hidden is None:
            node.create_subscription(ObjectPoses, "perception/ground_truth", self._on_ground_truth, 10)
        else:
            node.create_subscription(String, FRAME_INFO, self._on_frame_info, 10)
        self._trace_sub = node.create_subscription(OperatorTrace, "perception/trace",
                                                   lambda msg: self.traces.append(msg), 64)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        node.create_subscription(String, "perception/policy_version", self._on_version, latched)

    def _on_ground_truth(self, msg: ObjectPoses) -> None:
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        self.fresh.append((stamp, list(msg.object_ids)))

    def _on_frame_info(self, msg: String) -> None:
        parsed = frame_info_stamp(msg)
        if parsed is not None and self.hidden is not None and parsed[1] in self.hidden:
            self.fresh.append((parsed[0], list(self.hidden[parsed[1]])))

    def _on_version(self, msg: String) -> None:
        self.version = msg.data or None

    def next_frame(self, done: set[int], timeout: float, alive: Callable[[], None]) -> tuple[int, list[str]]:
        """The first frame arriving from now on that is not in `done`; RuntimeError after
        `timeout` s without one; `alive()` raises when a node died."""
        self.fresh.clear()
        deadline = time.monotonic() + timeout
        while True:
            for stamp, ids in self.fresh:
                if stamp not in done:
                    return stamp, ids
            self.fresh.clear()
            if time.monotonic() > deadline:
                topic = "perception/ground_truth" if self.hidden is None else FRAME_INFO
                raise RuntimeError(f"no new frame on {topic} within {timeout:g} s")
            alive()
            rclpy.spin_once(self.node, timeout_sec=0.1)

    def wait_for_trace_publisher(self, timeout: float, alive: Callable[[], None]) -> None:
        """Wait until the configurator's trace publisher is matched with this subscription: a trace
        published before discovery completes is lost (volatile QoS), and its estimate's row with it."""
        deadline = time.monotonic() + timeout
        while self._trace_sub.get_publisher_count() < 1:
            if time.monotonic() > deadline:
                raise RuntimeError(f"perception/trace: no publisher matched within {timeout:g} s")
            alive()
            rclpy.spin_once(self.node, timeout_sec=0.05)

    def trace_for(self, stamp_ns: int, object_id: str, timeout: float = TRACE_WAIT_S) -> OperatorTrace | None:
        """The trace of the estimate just answered (its frame stamp and object), waiting briefly."""
        deadline = time.monotonic() + timeout
        while True:
            while self.traces:
                t = self.traces.popleft()
                if (t.header.stamp.sec * 1_000_000_000 + t.header.stamp.nanosec == stamp_ns
                        and t.object_id == object_id):
                    return t
            if time.monotonic() > deadline:
                return None
            rclpy.spin_once(self.node, timeout_sec=0.05)


def drive(cell: CellNode, client: EstimateClient, log: EstimateLog, *, estimates: int | None, rounds: int | None,
          frames_per_round: int, noise_lambda: float, seed: int, pick_actions: list[str], failed_pick_cost: float,
          start_version: str, frame_timeout: float, alive: Callable[[], None], desc: str, window: int = DEFAULT_WINDOW,
          progress: bool = True, stop: StopSignals | None = None, robot: SimulatedRobot | None = None,
          pace: Callable[[int, Callable[[], None]], None] | None = None) -> bool:
    """Estimate frame after frame (ros/cell_sim_run.py) until `estimates` are done or `rounds`
    rounds are complete; rows go to `log`. With `robot` (a cell without ground truth) the robot
    answers the picks, its program reports each estimate's outcome (`report_pick_outcome`), and
    a row's `success` is the true outcome, `reported_success` the reported one. False when
    stopped by a stop signal (`stop`: SIGINT, SIGTERM, SIGHUP abandon the estimate in flight;
    without it, Ctrl-C). `pace` (online/learner_state.LearnerPace) is called with the estimates
    done before each estimate and may hold it."""
    interruptible = stop.interruptible if stop is not None else contextlib.nullcontext
    done: set[int] = set()
    round_no = index = 0
    succ: list[float] = []
    times: list[float] = []
    bar = tqdm(total=estimates, desc=desc, unit="estimate", disable=not progress)
    try:
        while (estimates is None or index < estimates) and (rounds is None or round_no < rounds):
            with interruptible():
                stamp, ids = cell.next_frame(done, frame_timeout, alive)
            done.add(stamp)
            counts = {i: ids.count(i) for i in ids}
            for obj in dict.fromkeys(ids):
                if counts[obj] != 1 or (estimates is not None and index >= estimates):
                    continue
                ep_seed = max(1, episode_seed(seed, index))
                with interruptible():  # the row is written outside: a signal never cuts a line short
                    if pace is not None:
                        pace(index, alive)
                    if robot is not None:
                        robot.begin()
                    answer = client.call(stamp, obj, noise_lambda, ep_seed)
                    trace = cell.trace_for(stamp, obj) if answer["success"] else None
                    if (robot is not None and robot.picks and answer["estimate_id"] and answer["operations"]
                            and answer["operations"][-1] in pick_actions):
                        # the configurator records a report on the estimate's last step: its last pick
                        robot.report(answer["estimate_id"], robot.picks[-1][1])
                oks = list(trace.ok) if trace is not None else None
                version = (getattr(trace, "policy_version", "") if trace is not None else "") or cell.version \
                    or start_version
                row = {
                    "index": index, "round": round_no, "wall_time": time.time(), "frame_stamp_ns": stamp,
                    "obj_id": int(obj), "seed": ep_seed, "answered": int(answer["success"]),
                    "success": int(robot.true_success() if robot is not None else answer["picked"]),
                    "reported_success": int(answer["picked"]),
                    "time_s": charged_time(answer["operations"], answer["operation_seconds"], oks, answer["picked"],
                                           pick_actions, failed_pick_cost),
                    "operator_s": float(sum(answer["operation_seconds"])), "estimate_wall_s": answer["wall"],
                    "first_pick_success": int(first_pick_success(answer["operations"], oks, answer["picked"],
                                                                 pick_actions)),
                    "operations": len(answer["operations"]), "policy_version": version,
                    "estimate_id": answer["estimate_id"], "trace": int(trace is not None),
                    "message": answer["message"],
                }
                log.append(row)
                succ.append(row["success"])
                times.append(row["time_s"])
                index += 1
                bar.update(1)
                bar.set_postfix(success=f"{rolling_mean(succ, window)[-1]:.2f}",
                                time=f"{rolling_mean(times, window)[-1]:.2f}s", version=version[:12])
            if len(done) >= frames_per_round:
                done.clear()
                round_no += 1
        return True
    except (KeyboardInterrupt, Interrupted):
        return False
    finally:
        bar.close()


