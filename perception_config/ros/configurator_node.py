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

With `auto` set it estimates every new camera frame (seen on `camera/camera_info`): the
objects in `auto_objects`, or, when that is empty, every object of the frame's replayed ground
truth (a test bench). Frames that arrive while an estimate runs are skipped, except the latest.

Parameters:
  policy            policy file (.safetensors) from `perception-config train` ("" = the fixed
                    pipeline `fixed_sequence`)
  fixed_sequence    the engineer's sequence used without a policy (icp_coarse, icp_fine, pick)
  pipeline          pipeline YAML ("" = the policy's, else the built-in default); must be the
                    operator nodes' pipeline
  models_dir        BOP models folder (the object's diameter is part of the agent's state)
  max_ops           operators per estimate (0 = the policy's training value, else 10)
  max_ops_cap       operators per estimate at most, whatever the policy file or request says (50)
  estimate_timeout  seconds one estimate may take (10.0), checked before each operator and
                    bounding each operator call's wait; see "Deadline" below
  request_queue     estimate requests that may wait while one runs (10); one more is answered at
                    once with success=false "busy: N requests queued (request_queue=M)"
  noise_lambda      lambda of simulated initialisation when a request does not give one (0.5)
  operator_timeout  seconds to wait for one operator call (10.0)
  fused_scoring     the generation and refinement nodes score their own result in the same call
                    (true: one round trip per action); false: every scoring is a call to
                    scoring_node (ros_operators.py)
  auto, auto_objects, auto_every_frame, camera_qos   see above
  use_depth         true (default): the camera gives depth; false: an RGB-only camera (the
                    operator nodes' use_depth false): the actions that need depth are masked
                    (info["action_mask"]), the agent never chooses them
  publish_debug     true (default): the live view (debug_view.py): `perception/debug_image`
                    (the frame with the final hypothesis's outline, object id, scores and the
                    operator trace) and `perception/markers` (the model's mesh at the pose),
                    each built only while it has a subscriber
  debug_image_max_width   the debug image is scaled down to this width (640; 0 = full size)
  marker_max_triangles    the marker mesh is decimated to at most this many triangles (500)
  episode_store     an episodes.sqlite file (store/episode_store.py) to which every estimate's episode is
                    appended (frame stamp, object, lambda, generator, every operator with its scores,
                    pose, times and outcome, the pick's result, the policy version); "" (default) =
                    off: a node has no run folder of its own, so where the store lives is the
                    launcher's choice (replay-check puts it in its output folder). Written with
                    synchronous=FULL (a robot's pick outlives a power cut). A store that cannot be
                    written (full disk, locked by another process for more than 0.5 s, corrupt,
                    not a store) is one error log line per estimate (repeats counted); the
                    estimate is answered as usual
  pick_source       who answers the pick_node's picks, recorded with each pick: "simulated" (default)
                    or "robot" (pick_node's robot_service set)
  learn             online learning (ros/learning.py, online/policy_learner.py): every estimate is stored
                    with its frame in `learn_dir`, a learner process trains candidates and promotes
                    those that beat the serving version on a replay of stored episodes; the serving
                    policy is swapped between estimates (false)
  learn_dir         the learning state: episodes.sqlite (the store, unless episode_store is given),
                    frames/, policies/ (v0000..., versions.json), learner.log; required with learn
  learn_start       version 0 when learn_dir has none: "policy" (the policy file, else the fixed
                    pipeline), "fixed" or "untrained" (a fresh pg policy)
  learn_margin      a candidate is promoted only if its replayed mean cost is below (1 - margin) x
                    the serving version's (0.05)
  learn_every       new stored estimates between two candidates (20)
  learn_train_episodes, learn_check_episodes   a candidate's training episodes (200) and the
                    newest stored episodes of its replay check (40)
  policy_version    (learn) pin a kept version at run time (`ros2 param set ... policy_version v0002`);
                    "" = the newest promoted; an unknown version is refused with the kept ones
  score_version     (learn, a pipeline with pick_success) the same for the learned pick-success score:
                    versions in `learn_dir`/pick_success/ (online/score_learner.py), followed by the
                    operator nodes whose `pick_success_versions` names that folder
Topics: `perception/policy_version` (std_msgs/String, transient local): the serving version after
every change. Service `report_pick_outcome` (ReportPickOutcome): the robot's pick result for an
estimate (EstimatePose's `estimate_id`), recorded on the episode's last step in the store; an
unknown estimate or a second report answers success=false with the reason.
A node that is down, or dies mid-estimate, makes the estimate answer success=false naming it.

Deadline: an estimate that reaches `estimate_timeout` between two operators answers
success=true, picked=false with the hypothesis so far; one that reaches it while waiting for an
operator's answer answers success=false. Both messages begin "estimate_timeout (X s) reached".

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
from collections import deque
from pathlib import Path

import numpy as np
from geometry_msgs.msg import PoseStamped
from perception_config_interfaces.msg import ObjectPoses, OperatorTrace
from perception_config_interfaces.srv import EstimatePose, ReportPickOutcome
from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo
from std_msgs.msg import Header, String

from ..agents import load_agent, make_agent
from ..agents.fixed import DEFAULT_SEQUENCE
from ..agents.policy_settings import policy_settings
from ..blocks.pipeline import load_pipeline, pipeline_reference
from ..core.geometry import check_noise_lambda
from ..datasets.bop import ModelFolder
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
from .camera_frames import camera_qos, stamp_text
from .debug_view import DebugView
from .learning import NodeLearning, version_qos
from .operator_node import make_hypothesis, spin
from .request_fields import parse_object_id, parse_stamp
from .request_queue import RequestQueue, service_qos
from .ros_operators import DeadlineReached, OperatorCallError, RosOperators

STORE_BUSY_TIMEOUT = 0.5  # s an estimate's answer may wait for another process's lock on the episode store


class ConfiguratorNode(Node):
    """Serves `estimate_pose`: the agent plays one episode of the same environment as in
    training, whose operators are service calls to the operator nodes (RosOperators)."""

    def __init__(self) -> None:
        super().__init__("configurator_node")
        self.declare_parameter("policy", "")
        self.declare_parameter("fixed_sequence", list(DEFAULT_SEQUENCE))
        self.declare_parameter("pipeline", "")
        self.declare_parameter("models_dir", "")
        self.declare_parameter("max_ops", 0)
        self.declare_parameter("max_ops_cap", 50)
        self.declare_parameter("estimate_timeout", 10.0)
        self.declare_parameter("request_queue", 10)
        self.declare_parameter("noise_lambda", 0.5)
        self.declare_parameter("operator_timeout", 10.0)
        self.declare_parameter("fused_scoring", True)
        self.declare_parameter("auto", False)
        self.declare_parameter("auto_objects", [""])
        self.declare_parameter("auto_every_frame", False)
        self.declare_parameter("camera_qos", "reliable")
        self.declare_parameter("use_depth", True)
        self.declare_parameter("publish_debug", True)
        self.declare_parameter("debug_image_max_width", 640)
        self.declare_parameter("marker_max_triangles", 500)
        self.declare_parameter("episode_store", "")
        self.declare_parameter("pick_source", "simulated")
        self.declare_parameter("learn", False)
        self.declare_parameter("learn_dir", "")
        self.declare_parameter("learn_start", "policy")
        self.declare_parameter("learn_margin", 0.05)
        self.declare_parameter("learn_every", 20)
        self.declare_parameter("learn_train_episodes", 200)
        self.declare_parameter("learn_check_episodes", 40)
        self.declare_parameter("policy_version", "")
        self.declare_parameter("score_version", "")
        self.use_depth = bool(self.get_parameter("use_depth").value)
        p = {name: self.get_parameter(name).value for name in (
            "policy", "fixed_sequence", "pipeline", "models_dir", "max_ops", "noise_lambda", "operator_timeout",
            "fused_scoring", "auto", "auto_objects", "camera_qos", "max_ops_cap", "estimate_timeout",
            "request_queue")}
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
        self._busy = threading.Lock()
        self.policy_version = policy_version(policy) if policy else None
        self.pick_source = str(self.get_parameter("pick_source").value)
        if self.pick_source not in PICK_SOURCES:
            raise ValueError(f"pick_source must be one of {PICK_SOURCES}, got {self.pick_source!r}")
        store = str(self.get_parameter("episode_store").value or "")
        self.learning: NodeLearning | None = None
        pinned = str(self.get_parameter("policy_version").value or "")
        if self.get_parameter("learn").value:
            learn_dir = str(self.get_parameter("learn_dir").value or "")
            store = store or (str(Path(learn_dir) / STORE_NAME) if learn_dir else "")
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
            self.learning.sync(self._swap)
            self.create_timer(0.5, self._learning_tick, callback_group=MutuallyExclusiveCallbackGroup())
        elif pinned or self.get_parameter("score_version").value:
            raise ValueError("policy_version or score_version is set but learn is false: versions exist only with "
                             "online learning")
        self.add_on_set_parameters_callback(self._on_set_parameters)
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

        self.auto_objects = [parse_object_id(o) for o in p["auto_objects"] if o]
        self.auto_every_frame = bool(self.get_parameter("auto_every_frame").value)
        self._auto_wake = threading.Event()
        self._auto_lock = threading.Lock()
        self._auto_queue: deque[int] = deque(maxlen=64)
        self._auto_gt: dict[int, list[str]] = {}
        if p["auto"]:  # a new frame is seen on camera_info, or on the ground truth that names its objects
            topics = MutuallyExclusiveCallbackGroup()
            if self.auto_objects:
                self.create_subscription(CameraInfo, "camera/camera_info", self._on_camera_info,
                                         camera_qos(p["camera_qos"]), callback_group=topics)
            else:
                self.create_subscription(ObjectPoses, "perception/ground_truth", self._on_ground_truth, 10,
                                         callback_group=topics)
            self._auto_thread = threading.Thread(target=self._auto_loop, name="auto", daemon=True)
            self._auto_thread.start()
        self.get_logger().info(f"serving estimate_pose with the {self.agent_name}, max_ops "
                               f"{min(self.env.max_ops, self.max_ops_cap)}, "
                               f"estimate_timeout {self.estimate_timeout:g} s"
                               + (", estimating every new frame" if p["auto"] else ""))

    # -- one estimate --------------------------------------------------------------------------
    def estimate(self, stamp_ns: int, object_id: str, max_operations: int = 0, noise_lambda: float = -1.0,
                 seed: int = 0) -> EstimatePose.Response:
        """Run the agent on one object in one frame; the response (never raises)."""
        response = EstimatePose.Response()
        start = time.perf_counter()
        oks: list[bool] = []
        try:
            object_id = parse_object_id(object_id)
        except ValueError as exc:
            response.success, response.message = False, str(exc)
            return response
        try:
            with self._busy:
                oks = self._run(response, stamp_ns, object_id, max_operations, noise_lambda, seed)
        except DeadlineReached as exc:
            response.success = False
            response.message = f"estimate_timeout ({self.estimate_timeout:g} s) reached: {exc}"
        except (ValueError, OperatorCallError) as exc:
            response.success = False
            response.message = str(exc)
            if isinstance(exc, OperatorCallError):
                self.get_logger().warning(f"estimate of object {object_id} failed: {exc}")
        except Exception as exc:  # answer, log, keep serving
            self.get_logger().error(f"estimate_pose failed: {exc!r}")
            response.success, response.message = False, f"internal error: {exc!r}"
        response.elapsed = time.perf_counter() - start
        self._publish(response, object_id, oks)
        if self.debug_view is not None and response.success:
            self._show(response, object_id)
        self.get_logger().debug(f"object {object_id} at {stamp_text(stamp_ns)}: {response.message} after "
                                f"{', '.join(response.operations) or 'no operation'} ({response.elapsed:.3f} s)")
        return response

    def _run(self, response: EstimatePose.Response, stamp_ns: int, object_id: str, max_operations: int,
             noise_lambda: float, seed: int) -> list[bool]:
        """Fill the response; returns the ok flag of each operation."""
        lam = self.default_lambda if (math.isfinite(noise_lambda) and noise_lambda < 0) else float(noise_lambda)
        lam = check_noise_lambda(lam, "noise_lambda (negative = the configurator's)")
        model = self.models.model(object_id)
        seed = int(seed) if seed else int(self._rng.integers(1, 2**31))
        episode = Episode(frame=None, model=model, ground_truth=None, noise_lambda=lam, seed=seed,
                          key=(0, 0, model.obj_id), stamp_ns=stamp_ns, has_depth=self.use_depth)
        limit = self.env.max_ops if not max_operations else min(int(max_operations), self.env.max_ops)
        limit = min(limit, self.max_ops_cap)
        deadline = time.monotonic() + self.estimate_timeout
        self.operators.deadline = deadline
        if self.learning is not None:  # between estimates: a promoted or pinned version starts serving here
            self.learning.sync(self._swap)
        try:
            traj = play_episode(self.env, self.agent, {"episode": episode}, acting_seed(seed), max_steps=limit,
                                require_hypothesis=True, stop=lambda: time.monotonic() >= deadline)
        finally:
            self.operators.deadline = None
        frame_stamp = stamp_ns  # the frame the operators used (a request for "the latest" names none)
        if self.operators.stamp is not None:
            frame_stamp = int(self.operators.stamp.sec) * 1_000_000_000 + int(self.operators.stamp.nanosec)
        if self.episode_writer is not None:
            eid = store_episode(self.episode_writer, traj, source="configurator", agent=self.store_agent,
                                policy_version=self.policy_version, episode_seed=seed, frame_stamp_ns=frame_stamp,
                                pick_source=self.pick_source, image_ids=False)
            response.estimate_id = int(eid or 0)
        if self.learning is not None:
            try:
                self.learning.capture(frame_stamp)
            except Exception as exc:  # noqa: BLE001  (learning must never fail an estimate)
                self.get_logger().error(f"learn: frame of the estimate not kept: {exc!r}")
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
        if traj.stopped:
            response.message = (f"estimate_timeout ({self.estimate_timeout:g} s) reached after {len(names)} "
                                "operations; not picked")
        return traj.oks

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

    def _on_pick_outcome(self, request: ReportPickOutcome.Request, response: ReportPickOutcome.Response
                         ) -> ReportPickOutcome.Response:
        """The robot's pick result for a stored estimate: recorded on the episode's last step."""
        eid = int(request.estimate_id)
        try:
            if self.episode_writer is None:
                raise EpisodeStoreError("no episode store: set episode_store (or learn with learn_dir)")
            store = self.episode_writer._ensure_open()
            rows = store.query("SELECT steps FROM episodes WHERE id = ? AND source = 'configurator'", (eid,))
            if not rows:
                raise EpisodeStoreError(f"unknown estimate {eid}: not an estimate of this store "
                                        f"({self.episode_writer.path})")
            store.record_pick_outcome(eid, int(rows[0][0] or 0), bool(request.picked), "robot")
        except (EpisodeStoreError, sqlite3.Error, OSError) as exc:
            self.get_logger().warning(f"report_pick_outcome for estimate {eid} refused: {exc}")
            response.success, response.message = False, str(exc)
            return response
        response.success, response.message = True, f"estimate {eid}: picked={bool(request.picked)} recorded"
        return response

    def on_exit(self) -> None:
        if self.learning is not None:
            self.learning.close()
        self.requests.close()
        print(f"[configurator_node] operator calls: {self.operators.timing_summary()}", flush=True)
        if self.debug_view is not None:
            self.debug_view.close()
            print(f"[configurator_node] {self.debug_view.timing()}", flush=True)
        if self._busy.acquire(timeout=2.0):  # not while an auto estimate is spinning the clients
            self.operators.close()
            if self.episode_writer is not None:
                print(f"[configurator_node] episode store: {self.episode_writer.summary()}", flush=True)
                self.episode_writer.close()
            self._busy.release()

    async def _on_estimate(self, request: EstimatePose.Request, response: EstimatePose.Response
                           ) -> EstimatePose.Response:
        busy = self.requests.busy()
        if busy is not None:
            response.success, response.message = False, busy
            return response
        try:
            return await self.requests.run(self._estimate_request, request)
        finally:
            self.requests.done()

    def _estimate_request(self, request: EstimatePose.Request) -> EstimatePose.Response:
        try:
            stamp_ns = parse_stamp(request.frame.stamp, "frame.stamp")
        except ValueError as exc:
            return EstimatePose.Response(success=False, message=str(exc))
        return self.estimate(stamp_ns, request.object_id, request.max_operations, request.noise_lambda, request.seed)

    # -- auto mode -------------------------------------------------------------------------------
    def _on_ground_truth(self, msg: ObjectPoses) -> None:
        stamp = self._stamp(msg)
        if stamp is None:
            return
        self._auto_gt[stamp] = list(msg.object_ids)
        while len(self._auto_gt) > 64:
            self._auto_gt.pop(next(iter(self._auto_gt)))
        self._new_frame(stamp)

    def _on_camera_info(self, msg: CameraInfo) -> None:
        stamp = self._stamp(msg)
        if stamp is not None:
            self._new_frame(stamp)

    def _stamp(self, msg: ObjectPoses | CameraInfo) -> int | None:
        try:
            return parse_stamp(msg.header.stamp, "header.stamp")
        except ValueError as exc:
            self.get_logger().warning(f"auto: ignored a message: {exc}")
            return None

    def _new_frame(self, stamp: int) -> None:
        with self._auto_lock:
            if stamp in self._auto_queue:
                return
            self._auto_queue.append(stamp)
            if not self.auto_every_frame:
                while len(self._auto_queue) > 1:  # a cell wants the latest frame, not a backlog
                    self._auto_queue.popleft()
        self._auto_wake.set()

    def _auto_loop(self) -> None:
        while True:
            self._auto_wake.wait()
            with self._auto_lock:
                if not self._auto_queue:
                    self._auto_wake.clear()
                    continue
                stamp = self._auto_queue.popleft()
            objects = self.auto_objects or self._auto_gt.get(stamp, [])
            if not objects:
                self.get_logger().warning(f"auto: no objects to estimate in the frame at {stamp_text(stamp)} "
                                          "(set auto_objects, or replay ground truth)")
            for object_id in objects:
                r = self.estimate(stamp, object_id)
                self.get_logger().info(f"auto {stamp_text(stamp)} object {object_id}: "
                                       f"{'picked' if r.picked else r.message} after {', '.join(r.operations)} "
                                       f"({r.elapsed:.3f} s)")


def main(args: list[str] | None = None) -> None:
    # Single-threaded: the executor only takes requests and answers; the estimates run on the
    # request queue's worker thread, whose operator calls spin their own executor (ros_operators.py).
    spin(ConfiguratorNode, args)


if __name__ == "__main__":
    main()
