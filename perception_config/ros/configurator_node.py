"""configurator_node: serves `estimate_pose` (EstimatePose.srv) by running a trained agent.

For each request the agent chooses operators from the current scores until a pick succeeds
or `max_ops` operators have run: the same PerceptionConfigEnv as in training, with the ROS
backend (ros_operators.RosOperators) whose operator calls are service requests to
generation_node, refinement_node, scoring_node and pick_node. The answer holds the final
hypothesis with its scores, whether the pick succeeded, the operator trace and the time.
Each estimate is also published: the pose as geometry_msgs/PoseStamped on `perception/pose`
(when there is one) and the trace as OperatorTrace on `perception/trace`; for a person
watching, the live view (debug_view.py) shows it on `perception/debug_image` and
`perception/markers`.

With `auto` set it estimates every new camera frame (auto_estimates.py).

Parameters: configurator_parameters.PARAMETERS, each with its description, range and choices
(`ros2 param describe configurator_node <name>`). With `learn`, online learning (learning.py).

Topics: `perception/policy_version` (std_msgs/String, transient local): the serving version after
every change. Service `report_pick_outcome` (ReportPickOutcome): the robot's pick result for an
estimate (EstimatePose's `estimate_id`), recorded on the episode's last step in the store; an
unknown estimate or a second report answers success=false with the reason.
A node that is down, or dies mid-estimate, makes the estimate answer success=false naming it.

Deadline: `estimate_timeout` (its description says what an estimate that reaches it answers).

Requests: the executor thread takes each request at once and answers busy ones at once; the
estimates run one at a time, in arrival order, on a worker thread (request_queue.py), which
spins the operator clients' own executor.

The operator clients are on a private node `<this node's name>_operators` (ros_operators.py):
remap the operator services with global rules, not `configurator_node:`-prefixed ones.
"""
from __future__ import annotations

import math
import sqlite3
import threading
import time
from pathlib import Path
from typing import Callable

import numpy as np
from geometry_msgs.msg import PoseStamped
from perception_config_interfaces.msg import OperatorTrace
from perception_config_interfaces.srv import EstimatePose, ReportPickOutcome
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from std_msgs.msg import Header, String

from ..agents import load_agent, make_agent
from ..agents.policy_settings import policy_settings
from ..blocks.pipeline import load_pipeline, pipeline_reference
from ..core.geometry import check_noise_lambda
from ..datasets.bop_models import ModelFolder
from ..rl.env import PerceptionConfigEnv
from ..rl.episode_loop import acting_seed, play_episode
from ..rl.operators import Episode
from ..store.episode_store import (
    PICK_SOURCES,
    STORE_NAME,
    EpisodeStoreError,
    StoreWriter,
    policy_version,
    store_episode,
)
from ..util.confine import confined
from .auto_estimates import AutoEstimates
from .camera_frames import stamp_text
from .configurator_parameters import PARAMETERS
from .debug_view import DebugView
from .diagnostics import NodeDiagnostics
from .estimate_action import CANCELLED, EstimateAction
from .learning import NodeLearning, version_qos
from .managed_node import ManagedNode
from .node_main import spin
from .operator_node import make_hypothesis
from .request_fields import parse_estimate_fields, parse_estimate_id, parse_object_id
from .request_queue import RequestQueue, service_qos
from .ros_operators import DeadlineReached, OperatorCallError, RosOperators

STORE_BUSY_TIMEOUT = 0.5  # s an estimate's answer may wait for another process's lock on the episode store


class ConfiguratorNode(ManagedNode):
    """Serves `estimate_pose`: the agent plays one episode of the same environment as in
    training, whose operators are service calls to the operator nodes (RosOperators). A managed
    node (managed_node.py): configure loads the policy, pipeline, models, stores and learner."""

    def __init__(self, **kwargs) -> None:
        super().__init__("configurator_node", PARAMETERS, **kwargs)
        self._busy = threading.Lock()
        self.requests: RequestQueue | None = None
        self.learning: NodeLearning | None = None
        self.policy_version: str | None = None
        self.agent_name = ""
        self.counts = {"operator_failures": 0, "deadlines_reached": 0, "cancelled": 0}
        self.diagnostics = NodeDiagnostics(self, self.health, self._diagnostic_figures,
                                           warn_keys=("operator_failures", "deadlines_reached"))
        self.add_on_set_parameters_callback(self._on_set_parameters)

    def setup(self) -> None:
        p = {name: self.get_parameter(name).value for name in (
            "policy", "fixed_sequence", "pipeline", "models_dir", "max_ops", "noise_lambda", "operator_timeout",
            "fused_scoring", "auto", "auto_objects", "camera_qos", "max_ops_cap", "estimate_timeout",
            "request_queue")}
        self.use_depth = bool(self.get_parameter("use_depth").value)
        self.max_ops_cap = p["max_ops_cap"]
        if isinstance(self.max_ops_cap, bool) or not isinstance(self.max_ops_cap, int) or self.max_ops_cap < 1:
            raise ValueError(f"max_ops_cap must be an integer >= 1, got {self.max_ops_cap!r}")
        self.estimate_timeout = float(p["estimate_timeout"])
        if not (math.isfinite(self.estimate_timeout) and self.estimate_timeout > 0):
            raise ValueError(f"estimate_timeout must be > 0 seconds, got {p['estimate_timeout']!r}")

        if not p["models_dir"]:
            raise ValueError("models_dir is not set: give the BOP models folder the operator nodes use")
        self.models = ModelFolder(p["models_dir"])
        policy = p["policy"]
        if policy and not Path(policy).is_file():
            raise ValueError(f"policy file {policy} does not exist")
        settings = policy_settings([policy] if policy else [], pipeline=p["pipeline"] or None,
                                   max_ops=p["max_ops"] or None)
        pipeline = load_pipeline(settings.pipeline)
        self.default_lambda = check_noise_lambda(p["noise_lambda"], "noise_lambda")
        self.operators = RosOperators(pipeline, node_name=f"{self.get_name()}_operators",
                                      timeout=float(p["operator_timeout"]),
                                      fused_scoring=bool(p["fused_scoring"]))
        # The policy's own settings (max_ops is part of its observation); time is measured here.
        self.env = PerceptionConfigEnv(None, pipeline, settings.env.replace(time_mode="measured"),
                                       operators=self.operators)
        if policy:
            self.agent = load_agent(policy, self.env)
            self.agent_name = f"{self.agent.kind} policy {policy}"
            self.store_agent = self.agent.kind
        else:
            self.agent = make_agent("fixed", self.env, sequence=[s for s in p["fixed_sequence"] if s])
            self.agent_name = "fixed pipeline " + " -> ".join(s for s in p["fixed_sequence"] if s)
            self.store_agent = "fixed:" + "+".join(s for s in p["fixed_sequence"] if s)  # as evaluation names it
        self._rng = np.random.default_rng()
        self.policy_version = policy_version(policy) if policy else None
        self.pick_source = str(self.get_parameter("pick_source").value)
        if self.pick_source not in PICK_SOURCES:
            raise ValueError(f"pick_source must be one of {PICK_SOURCES}, got {self.pick_source!r}")
        store = str(self.get_parameter("episode_store").value or "")
        pinned = str(self.get_parameter("policy_version").value or "")
        if self.get_parameter("learn").value:
            learn_dir = str(self.get_parameter("learn_dir").value or "")
            if learn_dir and not store:  # the store in learn_dir, never through a link out of it
                store = str(confined(Path(learn_dir) / STORE_NAME, learn_dir, "episode store"))
            self.learning = NodeLearning(
                self, self.env, learn_dir, start=str(self.get_parameter("learn_start").value), policy=policy,
                fixed_sequence=[s for s in p["fixed_sequence"] if s],
                pipeline=pipeline_reference(settings.pipeline) if isinstance(settings.pipeline, (str, Path)) else None,
                models_dir=p["models_dir"], margin=float(self.get_parameter("learn_margin").value),
                every=int(self.get_parameter("learn_every").value),
                train_episodes=int(self.get_parameter("learn_train_episodes").value),
                check_episodes=int(self.get_parameter("learn_check_episodes").value), pinned=pinned,
                camera_qos=p["camera_qos"], use_depth=self.use_depth,
                score_pinned=str(self.get_parameter("score_version").value or ""))
            self.learning.start(self._swap)  # refuses to start when the selected version cannot be loaded
            self.create_timer(0.5, self._learning_tick, callback_group=MutuallyExclusiveCallbackGroup())
        elif pinned or self.get_parameter("score_version").value:
            raise ValueError("policy_version or score_version is set but learn is false: versions exist only with "
                             "online learning")
        self.version_pub = self.create_publisher(String, "perception/policy_version", version_qos()) \
            if self.learning is None else self.learning.pub
        if self.learning is None:
            self.version_pub.publish(String(data=self.policy_version or ""))
        self.episode_writer = StoreWriter(store, self.get_logger().error, synchronous="FULL",
                                        busy_timeout=STORE_BUSY_TIMEOUT) if store else None
        if self.episode_writer is not None and self.episode_writer.open():
            self.get_logger().info(f"appending every episode to the episode store {store}")

        self.pose_pub = self.create_publisher(PoseStamped, "perception/pose", 10)
        self.trace_pub = self.create_publisher(OperatorTrace, "perception/trace", 10)
        self.debug_view = None
        if self.get_parameter("publish_debug").value:
            self.debug_view = DebugView(self, p["camera_qos"], int(self.get_parameter("debug_image_max_width").value),
                                        int(self.get_parameter("marker_max_triangles").value))
        self.requests = RequestQueue(self, p["request_queue"], self.get_name())
        self.create_service(EstimatePose, "estimate_pose", self._on_estimate,
                            qos_profile=service_qos(), callback_group=ReentrantCallbackGroup())
        self.create_service(ReportPickOutcome, "report_pick_outcome", self._on_pick_outcome,
                            qos_profile=service_qos(), callback_group=MutuallyExclusiveCallbackGroup())
        self.action = EstimateAction(self)  # the estimate_pose action, on the same queue

        auto_objects = [parse_object_id(o) for o in p["auto_objects"] if o]  # checked also without auto
        auto_every_frame = bool(self.get_parameter("auto_every_frame").value)
        self.auto = AutoEstimates(self, self.estimate, auto_objects, auto_every_frame, p["camera_qos"]) \
            if p["auto"] else None
        self.serving_line = (f"serving estimate_pose with the {self.agent_name}, max_ops "
                             f"{min(self.env.max_ops, self.max_ops_cap)}, estimate_timeout {self.estimate_timeout:g} s"
                             + (", estimating every new frame" if p["auto"] else ""))

    # -- one estimate --------------------------------------------------------------------------
    def estimate(self, stamp_ns: int, object_id: str, max_operations: int = 0, noise_lambda: float = -1.0,
                 seed: int = 0, arrived: float | None = None, cancelled: Callable[[], bool] | None = None,
                 on_step: Callable[[str, dict], None] | None = None) -> EstimatePose.Response:
        """Run the agent on one object in one frame; the response (never raises). `arrived`: the
        request's arrival (time.monotonic(); default now): estimate_timeout counts from there,
        the time it waited in the queue included. `cancelled` is asked between operators (True:
        stop there, the hypothesis so far answered); `on_step(action, info)` after each one."""
        response = EstimatePose.Response()
        arrived = time.monotonic() if arrived is None else arrived
        deadline = arrived + self.estimate_timeout
        start = time.perf_counter() - (time.monotonic() - arrived)  # elapsed counts from the arrival
        oks: list[bool] = []
        try:
            object_id = parse_object_id(object_id)
        except ValueError as exc:
            response.success, response.message = False, str(exc)
            return response
        try:
            if not self._busy.acquire(timeout=max(0.0, deadline - time.monotonic())):
                raise DeadlineReached("the deadline came while waiting for the estimate before this one")
            try:
                if time.monotonic() >= deadline:
                    raise DeadlineReached(f"the deadline came while this request waited "
                                          f"{time.monotonic() - arrived:.3g} s in the queue")
                oks = self._run(response, stamp_ns, object_id, max_operations, noise_lambda, seed, deadline,
                                cancelled, on_step)
            finally:
                self._busy.release()
        except DeadlineReached as exc:
            response.success = False
            response.message = f"estimate_timeout ({self.estimate_timeout:g} s) reached: {exc}"
            self.counts["deadlines_reached"] += 1
        except (ValueError, OperatorCallError) as exc:
            response.success = False
            response.message = str(exc)
            if isinstance(exc, OperatorCallError):
                self.counts["operator_failures"] += 1
                self.get_logger().warning(f"estimate of object {object_id} failed: {exc}")
        except Exception as exc:  # answer, log, keep serving
            self.get_logger().error(f"estimate_pose failed: {exc!r}")
            response.success, response.message = False, f"internal error: {exc!r}"
            self.health.internal_error(response.message)
        self.health.answered += 1
        if not response.success and not response.message.startswith("internal error"):
            self.health.failure(response.message)
        if response.message.startswith(CANCELLED):
            self.counts["cancelled"] += 1
        response.elapsed = time.perf_counter() - start
        self._publish(response, object_id, oks)
        if self.debug_view is not None and response.success:
            self._show(response, object_id)
        self.get_logger().debug(f"object {object_id} at {stamp_text(stamp_ns)}: {response.message} after "
                                f"{', '.join(response.operations) or 'no operation'} ({response.elapsed:.3f} s)")
        return response

    def _run(self, response: EstimatePose.Response, stamp_ns: int, object_id: str, max_operations: int,
             noise_lambda: float, seed: int, deadline: float, cancelled: Callable[[], bool] | None = None,
             on_step: Callable[[str, dict], None] | None = None) -> list[bool]:
        """Fill the response; returns the ok flag of each operation."""
        lam = self.default_lambda if (math.isfinite(noise_lambda) and noise_lambda < 0) else float(noise_lambda)
        lam = check_noise_lambda(lam, "noise_lambda (negative = the configurator's)")
        model = self.models.model(object_id)
        seed = int(seed) if seed else int(self._rng.integers(1, 2**31))
        episode = Episode(frame=None, model=model, ground_truth=None, noise_lambda=lam, seed=seed,
                          key=(0, 0, model.obj_id), stamp_ns=stamp_ns, has_depth=self.use_depth)
        limit = self.operation_limit(max_operations)
        self.operators.deadline = deadline
        if self.learning is not None:  # between estimates: a promoted or pinned version starts serving here
            self.learning.sync(self._swap)
            self._capture(stamp_ns, warn=False)  # now: the camera cache may have dropped the frame by the end
        try:
            traj = play_episode(self.env, self.agent, {"episode": episode}, acting_seed(seed), max_steps=limit,
                                require_hypothesis=True, on_step=on_step,
                                stop=lambda: time.monotonic() >= deadline or (cancelled is not None and cancelled()))
        finally:
            self.operators.deadline = None
        frame_stamp = stamp_ns  # the frame the operators used (a request for "the latest" names none)
        if self.operators.stamp is not None:
            frame_stamp = int(self.operators.stamp.sec) * 1_000_000_000 + int(self.operators.stamp.nanosec)
        if self.episode_writer is not None:
            has_truth = self.learning is not None and self.learning.has_ground_truth(frame_stamp, model.obj_id)
            eid = store_episode(self.episode_writer, traj, source="configurator", agent=self.store_agent,
                                policy_version=self.policy_version, episode_seed=seed, frame_stamp_ns=frame_stamp,
                                pick_source=self.pick_source, image_ids=False,
                                label="ground_truth" if has_truth else None)
            response.estimate_id = int(eid or 0)
        if self.learning is not None:
            self._capture(frame_stamp, warn=True)
        info, names = traj.final_info, traj.names
        picked = traj.success
        header = Header(frame_id=self.operators.frame_id)
        if self.operators.stamp is not None:
            header.stamp = self.operators.stamp
        # as the operators answered it
        final = self.operators.pose_msg if self.operators.pose_msg is not None else info["pose"]
        response.hypothesis = make_hypothesis(header, object_id, final, info["scores"])
        response.picked = picked
        response.operations = names
        response.operation_elapsed = traj.operation_seconds  # measured (info["seconds"] adds charges)
        response.success = True
        response.message = "picked" if picked else f"no successful pick within {len(names)} operations"
        failed = [(n, r) for n, ok, r in zip(names, traj.oks, traj.reasons) if not ok and r]
        if not picked and failed:  # why the operators failed, e.g. a restarted node without the frame
            response.message += f"; {len(failed)} failed, the last: {failed[-1][0]}: {failed[-1][1]}"[:600]
        if traj.stopped and cancelled is not None and cancelled():
            response.message = f"{CANCELLED} {len(names)} operations; not picked"
        elif traj.stopped:
            response.message = (f"estimate_timeout ({self.estimate_timeout:g} s) reached after {len(names)} "
                                "operations; not picked")
        return traj.oks

    def _diagnostic_figures(self) -> dict:
        """The configurator's own figures on /diagnostics (diagnostics.py)."""
        return {"policy_version": self.policy_version or "", "agent": self.agent_name, **self.counts}

    def operation_limit(self, max_operations: int) -> int:
        """The operators an estimate may run: the request's (0 = the policy's max_ops), at most
        the policy's max_ops and max_ops_cap."""
        limit = self.env.max_ops if not max_operations else min(int(max_operations), self.env.max_ops)
        return min(limit, self.max_ops_cap)

    def _publish(self, response: EstimatePose.Response, object_id: str, oks: list[bool]) -> None:
        if response.success:
            msg = PoseStamped()
            msg.header = response.hypothesis.header
            msg.pose = response.hypothesis.pose
            self.pose_pub.publish(msg)
        trace = OperatorTrace()
        trace.header = response.hypothesis.header
        trace.object_id = object_id
        trace.operations = list(response.operations)
        trace.elapsed = list(response.operation_elapsed)
        trace.ok = oks
        trace.picked = bool(response.picked)
        trace.policy_version = self.policy_version or ""
        self.trace_pub.publish(trace)

    def _show(self, response: EstimatePose.Response, object_id: str) -> None:
        """The estimate on the live view (debug_view.py); never fails the estimate."""
        try:
            model = self.models.model(object_id)
        except Exception as exc:
            self.get_logger().warning(f"debug view: object {object_id}: {exc}")
            return
        self.debug_view.show(response.hypothesis, model, list(response.operations), bool(response.picked),
                             response.elapsed)

    # -- online learning ---------------------------------------------------------------------------
    def _swap(self, version: str, agent) -> None:
        """Serve another policy version (called between estimates, the estimate lock held)."""
        self.agent = agent
        self.policy_version = version
        seq = getattr(agent, "sequence", None)
        self.store_agent = "fixed:" + "+".join(seq) if agent.kind == "fixed" and seq else agent.kind
        self.agent_name = f"{agent.kind} policy version {version}"

    def _learning_tick(self) -> None:
        try:
            self.learning.drain()
            if self._busy.acquire(blocking=False):  # never waits for an estimate
                try:
                    self.learning.sync(self._swap)
                finally:
                    self._busy.release()
        except Exception as exc:  # noqa: BLE001  (the node keeps serving whatever the learner sent)
            self.get_logger().error(f"learn: {exc!r}; the current version keeps serving")

    # the version pins at run time: parameter -> (NodeLearning's check, when the pinned version serves)
    VERSION_PINS = {"policy_version": ("check_pin", "serving it from the next estimate"),
                    "score_version": ("check_score_pin", "the operator nodes following the score versions serve "
                                                         "it from their next scoring")}

    def _on_set_parameters(self, params) -> SetParametersResult:
        for param in params:
            if param.name not in self.VERSION_PINS:
                continue
            check, when = self.VERSION_PINS[param.name]
            if self.learning is None:
                return SetParametersResult(successful=False,
                                           reason=f"{param.name} needs learn:=true (no versions without it)")
            result = getattr(self.learning, check)(str(param.value or ""))
            if not result.successful:
                self.get_logger().warning(f"{param.name} {param.value!r} refused: {result.reason}")
                return result
            self.get_logger().info(f"{param.name} set to {param.value or 'the newest'}: {when}")
        return SetParametersResult(successful=True)

    def _capture(self, stamp_ns: int, warn: bool) -> None:
        """Keep the estimate's frame for the learner (learning.capture); never fails an estimate."""
        try:
            self.learning.capture(stamp_ns, warn=warn)
        except Exception as exc:  # noqa: BLE001  (learning must never fail an estimate)
            self.get_logger().error(f"learn: frame of the estimate not kept: {exc!r}")

    def _on_pick_outcome(self, request: ReportPickOutcome.Request, response: ReportPickOutcome.Response
                         ) -> ReportPickOutcome.Response:
        """The robot's pick result for a stored estimate: recorded on the episode's last step."""
        eid = int(request.estimate_id)
        try:
            eid = parse_estimate_id(eid)
            if self.episode_writer is None:
                raise EpisodeStoreError("no episode store: set episode_store (or learn with learn_dir)")
            store = self.episode_writer._ensure_open()
            rows = store.query("SELECT steps FROM episodes WHERE id = ? AND source = 'configurator'", (eid,))
            if not rows:
                raise EpisodeStoreError(f"unknown estimate {eid}: not an estimate of this store "
                                        f"({self.episode_writer.path})")
            store.record_pick_outcome(eid, int(rows[0][0] or 0), bool(request.picked), "robot")
        except (EpisodeStoreError, sqlite3.Error, OSError, ValueError) as exc:
            self.get_logger().warning(f"report_pick_outcome for estimate {eid} refused: {exc}")
            response.success, response.message = False, str(exc)
            return response
        response.success, response.message = True, f"estimate {eid}: picked={bool(request.picked)} recorded"
        return response

    def teardown(self) -> None:
        """Free what setup made (also after a setup that failed half-way)."""
        self.serving = False
        if getattr(self, "action", None) is not None:
            self.action.destroy()
            self.action = None
        if self.learning is not None:
            self.learning.close()
            self.learning = None
        if self.requests is not None:
            self.requests.close()
            self.requests = None
        operators = getattr(self, "operators", None)
        if operators is not None:
            print(f"[{self.get_name()}] operator calls: {operators.timing_summary()}", flush=True)
        if getattr(self, "debug_view", None) is not None:
            self.debug_view.close()
            print(f"[{self.get_name()}] {self.debug_view.timing()}", flush=True)
            self.debug_view = None
        if self._busy.acquire(timeout=2.0):  # not while an auto estimate is spinning the clients
            try:
                if operators is not None:
                    operators.close()
                    self.operators = None
                writer = getattr(self, "episode_writer", None)
                if writer is not None:
                    print(f"[{self.get_name()}] episode store: {writer.summary()}", flush=True)
                    writer.close()
                    self.episode_writer = None
            finally:
                self._busy.release()

    async def _on_estimate(self, request: EstimatePose.Request, response: EstimatePose.Response
                           ) -> EstimatePose.Response:
        try:  # a bad request is answered at once, without waiting in the queue
            parse_estimate_fields(request)
        except ValueError as exc:
            response.success, response.message = False, str(exc)
            return response
        arrived = time.monotonic()
        requests = self.requests  # this configuration's queue, also if a shutdown comes meanwhile
        if not self.serving or requests is None:
            response.success, response.message = False, self.refusal("estimate_pose")
            return response
        busy = requests.busy()
        if busy is not None:
            await requests.pace()
            response.success, response.message = False, busy
            return response
        try:
            return await requests.run(self._estimate_request, request, arrived)
        finally:
            requests.done()

    def _estimate_request(self, request: EstimatePose.Request, arrived: float) -> EstimatePose.Response:
        stamp_ns = parse_estimate_fields(request)
        return self.estimate(stamp_ns, request.object_id, request.max_operations, request.noise_lambda, request.seed,
                             arrived)



def main(args: list[str] | None = None) -> None:
    # Single-threaded: the executor only takes requests and answers; the estimates run on the
    # request queue's worker thread, whose operator calls spin their own executor (ros_operators.py).
    spin(ConfiguratorNode, args)


if __name__ == "__main__":
    main()
