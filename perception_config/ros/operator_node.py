"""What the four operator nodes share: parameters, models, camera frames, ground truth, answering.

Every operator node declares OPERATOR_PARAMETERS (below) and its own; `ros2 param describe`
gives each one's description, type and range.

A request names its frame by stamp (a hypothesis' header.stamp; zero = the latest frame). The
blocks run in the service callback; their per-frame precomputations are kept per cached frame.

Threads: a single-threaded executor takes every request as it arrives and sends every answer
(rclpy's multi-threaded executor's thread hand-offs cost more per service call than they bring;
per-call figures in benchmarks/results/ros.json); the blocks run on one worker thread, one
request at a time in arrival order (request_queue.py), so a request never waits unseen in the
middleware. A request whose frame (or ground truth) has not arrived yet waits in the executor
(a coroutine awaiting the next arrival or `frame_timeout`) without holding the worker; then its
handler runs again.

Every service answers: a bad request or a failed operator gives success=false and a message,
an unexpected exception is logged and answered the same way, and the node keeps serving.
"""
from __future__ import annotations

import inspect
import math
import threading
import time
from collections import OrderedDict
from typing import Any, Awaitable, Callable

import numpy as np
from geometry_msgs.msg import Pose as PoseMsg
from perception_config_interfaces.msg import Hypothesis, ObjectPoses
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.task import Future
from std_msgs.msg import Header

from ..blocks.base import DEPTH, GROUND_TRUTH, RGB, Block, BlockInput, BlockResult, Kind, create
from ..blocks.pick_success import PickSuccess, follow_score_versions
from ..blocks.pipeline import load_pipeline
from ..core.geometry import Pose
from ..core.models import ObjectModel
from ..datasets.bop_models import ModelFolder
from ..rl.operators import FrameCaches
from . import local_services
from .camera_frames import CAMERA_QOS, CameraFrames, FrameNotReady, stamp_text
from .conversions import msg_to_pose, pose_to_msg, stamp_to_nanoseconds
from .diagnostics import NodeDiagnostics
from .local_services import LocalService
from .managed_node import ManagedNode
from .parameters import INT_MAX, NodeParameter
from .request_fields import excerpt, parse_method, parse_object_id, parse_position, parse_scores, parse_stamp
from .request_queue import MAX_REQUEST_QUEUE, RequestQueue, service_qos
from .stamp_cache import StampCache

MAX_BLOCKS = 32  # blocks kept by (method, noise_lambda), least recently used dropped first

OPERATOR_PARAMETERS = (
    NodeParameter("models_dir", "", "BOP models folder (models_info.json + obj_XXXXXX.ply); required to serve",
                  read_only=True),
    NodeParameter("pipeline", "", "pipeline YAML or a shipped pipeline's name ('rgb'): its actions are served by "
                  "name (empty = the built-in default)", read_only=True),
    NodeParameter("cache_size", 30, "camera frames (and ground-truth messages) kept, by stamp",
                  limits=(1, INT_MAX), read_only=True),
    NodeParameter("frame_timeout", 1.0, "seconds a request waits for a frame that has not arrived yet"),
    NodeParameter("camera_qos", "reliable", "QoS of the camera subscriptions: reliable, or sensor_data "
                  "(best effort)", read_only=True, choices=CAMERA_QOS),
    NodeParameter("sync_tolerance", 0.0, "seconds between colour and depth stamps still paired (0 = equal stamps)",
                  limits=(0.0, math.inf), read_only=True),
    NodeParameter("use_depth", True, "true: frames are colour + depth + camera_info; false: an RGB-only camera, "
                  "frames of colour + camera_info alone (no depth subscription), and a block that needs depth "
                  "answers success=false \"... needs depth\"", read_only=True),
    NodeParameter("request_queue", 10, "requests that may wait while one is served; one more is answered at once "
                  "with success=false \"busy: N requests queued (request_queue=M)\"",
                  limits=(0, MAX_REQUEST_QUEUE), read_only=True),
    NodeParameter("pick_success_versions", "", "a folder of pick-success score versions (online learning, "
                  "`<learn_dir>/pick_success`; \"\" = none): the pipeline's pick_success scores follow its "
                  "selected version, checked before each scoring (blocks/pick_success.py)", read_only=True),
)


class OperatorNode(ManagedNode):
    """What every operator node shares: parameters, the models folder, the pipeline's blocks,
    the camera frame cache (and replayed ground truth) by stamp, awaiting a frame not yet
    arrived, and answering every request (success=false with a message on bad input).

    A managed node (managed_node.py): configure (`setup`) loads the pipeline and every model of
    the models folder and subscribes to the camera; activate serves."""

    def __init__(self, name: str, parameters: tuple[NodeParameter, ...], *, ground_truth: bool = False,
                 **kwargs: Any) -> None:
        """`parameters`: the node's, OPERATOR_PARAMETERS first. Nothing is loaded here: `start()`
        (called by node_main.run_nodes once the node is built) configures it, or a manager does."""
        super().__init__(name, parameters, **kwargs)
        self._with_ground_truth = ground_truth
        self.requests: RequestQueue | None = None
        self.models: ModelFolder | None = None
        self._models: dict[str, ObjectModel] = {}  # by object id, while configured
        self._blocks: OrderedDict[tuple[str, float | None], Block] = OrderedDict()  # LRU, MAX_BLOCKS
        self._problems_said: set[str] = set()  # degradations logged (once each)
        self._handlers: dict[str, tuple[Any, Callable[..., Any]]] = {}  # service -> (type, callback)
        self.diagnostics = NodeDiagnostics(self, self.health)  # /diagnostics, 1 Hz, from the start

    def setup(self) -> None:
        self.pipeline = load_pipeline(self.param("pipeline") or None)
        self.score_versions = str(self.param("pick_success_versions"))
        if self.score_versions:
            following = follow_score_versions(self.pipeline, self.score_versions)
            self.get_logger().info(f"pick_success follows the score versions in {self.score_versions}"
                                   if following else "pick_success_versions is set but the pipeline has no "
                                   "pick_success score: ignored")
        models_dir = self.param("models_dir")
        self.models = ModelFolder(models_dir) if models_dir else None
        if self.models is None:
            self.get_logger().warning("models_dir is not set: every request will be refused")
        else:  # every model loaded and checked now, not at the first request
            for obj_id in sorted(self.models.info):
                self.model(str(obj_id))
        cache_size = int(self.param("cache_size"))
        self._block_caches = FrameCaches(cache_size)
        self._service_group = ReentrantCallbackGroup()  # requests are taken at once; the queue orders them
        self.requests = RequestQueue(self, self.param("request_queue"), self.get_name())
        self._wait_group = ReentrantCallbackGroup()  # the timer and clients a waiting service callback awaits
        self._arrivals: list[Future] = []  # woken by the next frame or ground truth
        self._arrival_count = 0  # frames and ground truths arrived (the handlers run on another thread)
        self._arrival_signal = threading.Condition()  # notified at each arrival (answer_here waits on it)
        self._deadlines: list[tuple[float, Future]] = []  # woken (False) at their deadline
        # One timer for every deadline, running only while something waits (entities are not
        # created and destroyed per request).
        self._deadline_timer = self.create_timer(0.01, self._check_deadlines, callback_group=self._wait_group)
        self._deadline_timer.cancel()
        topics = MutuallyExclusiveCallbackGroup()
        self.camera = CameraFrames(self, cache_size, self.param("camera_qos"), float(self.param("sync_tolerance")),
                                   topics, on_arrival=self._arrived, use_depth=bool(self.param("use_depth")))
        self.ground_truth: StampCache[dict[str, Any]] | None = None
        if self._with_ground_truth:
            self.ground_truth = StampCache(cache_size)
            self.create_subscription(ObjectPoses, "perception/ground_truth", self._on_ground_truth, 10,
                                     callback_group=topics)

    def teardown(self) -> None:
        if self.requests is not None:
            self.requests.close()
        self.requests = None
        self.models = None
        self._models.clear()
        self._blocks.clear()
        for name in self._handlers:
            local_services.unregister(self.resolve_service_name(name))
        self._handlers.clear()

    def param(self, name: str) -> Any:
        return self.get_parameter(name).value

    # -- services ------------------------------------------------------------------------------
    def serve(self, srv_type: Any, name: str, handler: Callable[[Any, Any], Awaitable[None] | None],
              local: bool = True) -> None:
        """A service whose handler fills the response or raises ValueError (a bad request, a
        failed operator); success, message and elapsed are set here, whatever happens. A handler
        that raises FrameNotReady runs again after the next frame arrives, until frame_timeout."""

        async def callback(request: Any, response: Any) -> Any:
            requests = self.requests  # this configuration's queue, also if a shutdown comes meanwhile
            if not self.serving or requests is None:
                response.success, response.message = False, self.refusal(name)
                return response
            busy = requests.busy()
            if busy is not None:
                await requests.pace()
                response.success, response.message = False, busy
                return response
            try:
                await self._answer(name, handler, request, response, requests)
            finally:
                requests.done()
            return response

        self.create_service(srv_type, name, callback, qos_profile=service_qos(),
                            callback_group=self._service_group)
        self._handlers[name] = (srv_type, handler)
        if local:  # a synchronous handler: other nodes of a composed process may call it directly
            local_services.register(self.resolve_service_name(name), LocalService(self, name))

    async def _answer(self, name: str, handler: Callable[[Any, Any], Awaitable[None] | None], request: Any,
                      response: Any, requests: RequestQueue) -> None:
        """Run the handler on the worker (again after each arrival while its frame is not ready);
        fill success, message and elapsed (s, from the start of its turn) whatever happens."""
        start = time.perf_counter()
        deadline = start + float(self.param("frame_timeout"))
        try:
            while True:
                arrivals = self._arrival_count
                try:
                    pending = await requests.run(handler, request, response)
                    if inspect.isawaitable(pending):
                        await pending
                    break
                except FrameNotReady:
                    remaining = deadline - time.perf_counter()
                    if remaining <= 0:
                        raise
                    if self._arrival_count == arrivals:  # else it came while the handler ran: try again
                        await self.wait_for(None, remaining)  # the next arrival, or the deadline
            self._settle(name, response, start)
        except Exception as exc:  # noqa: BLE001  (answered: _settle)
            self._settle(name, response, start, exc)

    def answer_here(self, name: str, request: Any, timeout: float) -> Any | None:
        """The answer to a request from another node of this process (local_services.py): the
        same checks, queue and answer as the service callback (`serve`), without the middleware;
        the calling thread waits (at most `timeout` s: None) and waits for a frame not arrived yet
        itself. The work runs on this node's worker, in turn with the requests from outside."""
        srv_type, handler = self._handlers[name]
        response = srv_type.Response()
        requests = self.requests
        if not self.serving or requests is None:
            response.success, response.message = False, self.refusal(name)
            return response
        busy = requests.busy()
        if busy is not None:
            response.success, response.message = False, busy
            return response
        try:
            start = time.perf_counter()
            give_up = time.monotonic() + timeout
            deadline = start + float(self.param("frame_timeout"))
            try:
                while True:
                    arrivals = self._arrival_count
                    try:
                        requests.run_waiting(handler, (request, response), give_up - time.monotonic())
                        break
                    except FrameNotReady:
                        remaining = deadline - time.perf_counter()
                        if remaining <= 0:
                            raise
                        with self._arrival_signal:  # the next arrival, or the deadline
                            if self._arrival_count == arrivals:
                                self._arrival_signal.wait(min(remaining, max(0.0, give_up - time.monotonic())))
                self._settle(name, response, start)
            except TimeoutError:
                return None
            except Exception as exc:  # noqa: BLE001  (answered: _settle)
                self._settle(name, response, start, exc)
        finally:
            requests.done()
        return response

    def _settle(self, name: str, response: Any, start: float, exc: Exception | None = None) -> None:
        """Fill success, message and elapsed (s since `start`): ok, a refusal (ValueError: a bad
        request, a failed operator) or an internal error (logged; the node keeps serving)."""
        if exc is None:
            response.success = True
            response.message = response.message or "ok"
        elif isinstance(exc, ValueError):
            response.success = False
            response.message = str(exc)
            self.health.failure(f"{name}: {exc}")
        else:
            self.get_logger().error(f"{name} failed: {exc!r}")
            response.success = False
            response.message = f"internal error: {exc!r}"
            self.health.internal_error(f"{name}: {exc!r}")
        self.health.answered += 1
        response.elapsed = time.perf_counter() - start

    def _arrived(self) -> None:
        """A frame or ground truth arrived: wake the service callbacks (and in-process callers)
        waiting for one."""
        with self._arrival_signal:
            self._arrival_count += 1
            self._arrival_signal.notify_all()
        waiters, self._arrivals = self._arrivals, []
        for future in waiters:
            if not future.done():
                future.set_result(True)

    def _check_deadlines(self) -> None:
        now = time.monotonic()
        for deadline, future in self._deadlines:
            if deadline <= now and not future.done():
                future.set_result(False)
        self._deadlines = [(d, f) for d, f in self._deadlines if not f.done()]
        if not self._deadlines:
            self._deadline_timer.cancel()

    async def wait_for(self, future: Future | None, timeout: float) -> bool:
        """Await `future` (None: the next frame or ground-truth arrival) for at most `timeout` s,
        without blocking the executor (the subscriptions keep running). True when it completed
        in time."""
        woken = Future()
        if future is None:
            self._arrivals.append(woken)
        else:
            future.add_done_callback(lambda _: woken.done() or woken.set_result(True))
        self._deadlines.append((time.monotonic() + timeout, woken))
        if self._deadline_timer.is_canceled():
            self._deadline_timer.reset()
        return bool(await woken)

    # -- inputs ----------------------------------------------------------------------------------
    def model(self, object_id: str) -> ObjectModel:
        object_id = parse_object_id(object_id)
        model = self._models.get(object_id)
        if model is None:
            if self.models is None:
                raise ValueError("this node has no models: set its models_dir parameter to a BOP models folder")
            model = self._models[object_id] = self.models.model(object_id)  # load_model checks the file's mtime
        return model

    def _on_ground_truth(self, msg: ObjectPoses) -> None:
        assert self.ground_truth is not None
        try:
            stamp = parse_stamp(msg.header.stamp, "header.stamp")
        except ValueError as exc:
            self.get_logger().warning(f"ignored a ground-truth message: {exc}")
            return
        poses = dict(zip(msg.object_ids, msg.poses))
        self.ground_truth.put(stamp, {"header": msg.header, "poses": poses})
        self._arrived()

    def ground_truth_pose(self, stamp_ns: int, object_id: str) -> tuple[Pose, Header]:
        assert self.ground_truth is not None
        item = self.ground_truth.get(stamp_ns)
        if item is None:
            which = "any frame" if stamp_ns == 0 else f"the frame at {stamp_text(stamp_ns)}"
            none = "" if self.ground_truth.stamps() else (
                f" ({self.get_name()} has received none since it started {self.camera.age():.0f} s ago; a node "
                "(re)started after a frame was published never receives that frame's ground truth)")
            raise FrameNotReady(f"no ground truth for {which} arrived on perception/ground_truth "
                                f"within {float(self.param('frame_timeout')):g} s{none}")
        if object_id not in item["poses"]:
            raise ValueError(f"object {object_id!r} is not in the ground truth of that frame "
                             f"(objects: {excerpt(', '.join(sorted(item['poses'])), 200)})")
        try:
            return msg_to_pose(item["poses"][object_id]), item["header"]
        except ValueError as exc:
            raise ValueError(f"the ground truth of object {object_id!r} is unusable: {exc}") from None

    def block(self, method: str, kinds: tuple[Kind, ...], noise_lambda: float | None = None) -> tuple[str, Block]:
        """The block serving `method`: a pipeline action of one of `kinds` (with its preset), the
        pipeline's generator, or a registered block with its defaults. `noise_lambda` overrides
        a generator's noise level."""
        method = parse_method(method)
        pipe = self.pipeline
        served = [a.name for a in pipe.actions if a.kind in kinds]
        if Kind.GENERATION in kinds:
            served.insert(0, pipe.generator.name)
        key = (method, noise_lambda)
        if key in self._blocks:
            self._blocks.move_to_end(key)
        else:
            base: Block | None = None
            if method == pipe.generator.name and Kind.GENERATION in kinds:
                base = pipe.generator
            elif method in pipe.action_names and pipe.action(method).kind in kinds:
                base = pipe.action(method).block
            else:
                try:
                    base = create(method)
                except ValueError:
                    base = None
                if base is not None and base.kind not in kinds:
                    base = None
            if base is None:
                registered = f"the registered {'/'.join(k.value for k in kinds)} blocks"
                serves = f"{', '.join(dict.fromkeys(served))} and {registered}" if served else f"only {registered}"
                raise ValueError(f"unknown method {excerpt(method)}; this node serves {serves}")
            config = dict(base.config)
            if noise_lambda is not None and "noise_lambda" in config:
                config["noise_lambda"] = noise_lambda
            self._blocks[key] = type(base)(**config)
            if self.score_versions and isinstance(self._blocks[key], PickSuccess):
                self._blocks[key].follow_versions(self.score_versions)
            while len(self._blocks) > MAX_BLOCKS:  # e.g. one generator per distinct noise_lambda
                self._blocks.popitem(last=False)
        return method, self._blocks[key]

    def run_block(self, block: Block, stamp_ns: int, object_id: str, pose: Pose | None,
                  rng: np.random.Generator | None = None) -> tuple[BlockResult, Header]:
        """Run a block on the frame named by stamp (fetched only when the block uses images) and
        the ground truth (only when it declares it). Returns the result and the frame's header."""
        model = self.model(object_id)
        header = Header()
        frame = None
        if RGB in block.inputs or DEPTH in block.inputs:
            cam = self.camera.get(stamp_ns, float(self.param("frame_timeout")))  # FrameNotReady: the caller waits
            frame = cam.frame
            header.stamp.sec, header.stamp.nanosec = divmod(cam.stamp_ns, 1_000_000_000)
            header.frame_id = cam.frame_id
        gt = None
        if GROUND_TRUTH in block.inputs:
            gt, gt_header = self.ground_truth_pose(stamp_ns if frame is None else stamp_to_nanoseconds(header.stamp),
                                                   object_id)
            if frame is None:
                header = gt_header
        inp = BlockInput(frame=frame, model=model, pose=pose, ground_truth=gt,
                         rng=rng if rng is not None else np.random.default_rng(), cache=self._block_caches.get(frame))
        return block(inp), header

    def score(self, stamp_ns: int, object_id: str, pose: Pose, blocks: list[Block] | None = None
              ) -> tuple[dict[str, float], list[str], Header]:
        """The scores of a hypothesis (the pipeline's scoring set unless `blocks`), NaN for a block
        that cannot score it (as in-process); the failures; the frame's header."""
        scores: dict[str, float] = {}
        failed: list[str] = []
        header = Header()
        for block in (self.pipeline.scoring if blocks is None else blocks):
            result, header = self.run_block(block, stamp_ns, object_id, pose)
            self._say_once((result.info or {}).get("problem"))
            for name in block.score_names:
                scores[name] = float(result.scores.get(name, math.nan)) if result.ok else math.nan
            if not result.ok:
                failed.append(f"{block.name}: {result.reason}")
        return scores, failed, header


    def _say_once(self, problem: str | None) -> None:
        """A block's degradation (e.g. a pick_success version that cannot be loaded, the previous
        model serving): one warning line per distinct problem, not one per request."""
        if problem and problem not in self._problems_said:
            self._problems_said.add(problem)
            self.get_logger().warning(problem)


def hypothesis_pose(msg: Hypothesis) -> tuple[int, str, Pose]:
    """(stamp_ns, object_id, pose) of a hypothesis in a request; ValueError for a NaN/degenerate pose,
    a malformed object id or stamp (request_fields.py)."""
    try:
        pose = msg_to_pose(msg.pose)
        parse_position(*pose.t, what="hypothesis.pose.position")
        parse_scores(msg.scores, msg.score_names)
    except ValueError as exc:
        raise ValueError(f"the hypothesis is unusable: {exc}") from None
    if not msg.object_id:
        raise ValueError("the hypothesis has no object_id")
    return parse_stamp(msg.header.stamp, "hypothesis.header.stamp"), parse_object_id(msg.object_id), pose


def answered_pose(pose: Pose) -> tuple[PoseMsg, Pose]:
    """An operator's output pose as it is answered, and as every receiver reads it back
    (geometry.as_transmitted): the node scores that one, so scores, cached renderings and the
    next operator all see the pose the in-process operators see."""
    msg = pose_to_msg(pose)
    return msg, msg_to_pose(msg)


def make_hypothesis(header: Header, object_id: str, pose: Pose | PoseMsg | None,
                    scores: dict[str, float] | None = None) -> Hypothesis:
    """A Hypothesis message; `pose` as a message is sent as it is (not converted again)."""
    hyp = Hypothesis()
    hyp.header = header
    hyp.object_id = object_id
    if isinstance(pose, PoseMsg):
        hyp.pose = pose
    elif pose is not None:
        hyp.pose = pose_to_msg(pose)
    scores = scores or {}
    hyp.score_names = list(scores)
    hyp.scores = [float(v) for v in scores.values()]
    return hyp
