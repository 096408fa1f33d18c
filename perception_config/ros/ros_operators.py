"""The ROS backend of the environment's Operators interface (perception_config/rl/operators.py).

The same calls InProcessOperators makes, as service requests to the operator nodes: the
generator at the start and for a generation action (generate_hypothesis), a refinement action
(refine_hypothesis with the action's name), each with a seed drawn from the episode's streams
exactly as in-process, the pick (pick), and the scoring set after each (score_hypothesis). The
hypothesis lives here and travels with each request; the images stay in the operator nodes,
named by the frame's stamp (the generator resolves "latest" and every later call uses the
stamp it answered with).

Scoring: by default the generation and refinement nodes score their result in the same call
(`score` in the request: same scoring set, same per-frame caches, one round trip per action
instead of two); with `fused_scoring=False` every scoring is a score_hypothesis call to the
scoring node. After a pick or a failed operator the hypothesis is unchanged, and so are its
scores (scoring is deterministic): no call.

Candidates: a generator's answer carries its ranked candidates (`candidates`, `confidences`); the
ones below the answered pose wait here (all of them after a refusal, success=false, whose best
verified below the generator's threshold), and `next_candidate` takes the next of them in this
process, with no call but the scoring of the new hypothesis (the node answers them as it
answers poses, so they travel on unconverted).

Time: `StepOutcome.elapsed` is the wall time of the round trips (what the robot cell waits),
`result.elapsed` the node's own compute time.

An operator that fails (success=false: a refiner diverged, the frame has no depth there) is an
`ok=False` outcome, as in-process. A node that is not there or does not answer within
`timeout` (plus LAST_LOOK) raises `OperatorCallError`: the episode cannot go on. With `deadline` set, no call
waits past it (`DeadlineReached`).

In a composed process (composed.py) a call to an operator node of the same process runs its
service callback directly (local_services.py): no serialisation, no middleware.

Calls block the calling thread, which spins the clients itself: they live on a private node
with its own single-threaded executor, spun inline until the answer is there (cheaper than
answers taken by another executor thread and handed over: benchmarks/results/ros.json). So calls
can be made from anywhere, a callback of another executor included, but from one thread at a
time (the configurator serialises its estimates). `close()` destroys the private node.
"""
from __future__ import annotations

import math
import time
from collections import deque
from typing import Any

import numpy as np
import rclpy
from geometry_msgs.msg import Pose as PoseMsg
from perception_config_interfaces.msg import Hypothesis
from perception_config_interfaces.srv import GenerateHypothesis, Pick, RefineHypothesis, ScoreHypothesis
from rclpy.executors import SingleThreadedExecutor

from ..blocks.base import BlockInput, BlockResult, Kind
from ..blocks.pipeline import Pipeline
from ..core.geometry import Pose
from ..rl.operators import Episode, StepOutcome, draw_seed, refiner_stream
from . import local_services
from .conversions import msg_to_pose, pose_to_msg, stamp_to_nanoseconds

SERVICES = {"generate": "generate_hypothesis", "refine": "refine_hypothesis", "score": "score_hypothesis",
            "pick": "pick"}
NODES = {"generate": "generation_node", "refine": "refinement_node", "score": "scoring_node", "pick": "pick_node"}


LAST_LOOK = 1.0  # s waited past a timeout for an answer already on its way


class OperatorCallError(RuntimeError):
    """An operator node is not available or did not answer in time."""


class DeadlineReached(OperatorCallError):
    """The estimate's deadline (`RosOperators.deadline`) came before or during an operator call."""


class RosOperators:
    """The environment's operator backend over ROS 2: generator, refiner, scoring and pick calls
    are service requests to the operator nodes, with the same seeds as in-process (rl/operators.py).
    The clients live on a private node whose executor the calling thread spins itself."""

    def __init__(self, pipeline: Pipeline, node_name: str = "operator_clients", timeout: float = 10.0,
                 services: dict[str, str] | None = None, fused_scoring: bool = True) -> None:
        if not (math.isfinite(timeout) and timeout > 0):
            raise ValueError(f"operator timeout must be > 0 seconds, got {timeout}")
        self.node = rclpy.create_node(node_name)
        self._executor = SingleThreadedExecutor()
        self._executor.add_node(self.node)
        self.pipeline = pipeline
        self.timeout = float(timeout)
        self.fused_scoring = bool(fused_scoring)
        names = {**SERVICES, **(services or {})}
        types = {"generate": GenerateHypothesis, "refine": RefineHypothesis, "score": ScoreHypothesis, "pick": Pick}
        self.clients = {k: self.node.create_client(types[k], names[k]) for k in types}
        # the services' full names, to find them among this process's nodes (local_services.py)
        self._resolved = {k: self.node.resolve_service_name(names[k]) for k in types}
        self.episode: Episode | None = None
        self.pose: Pose | None = None
        self.pose_msg: PoseMsg | None = None  # self.pose as answered: passed on as it is, never converted again
        self.scores: dict[str, float] = {}
        # the last generator call's candidates not yet taken: (confidence, pose, answered message)
        self._candidates: list[tuple[float, Pose, PoseMsg]] = []
        self.stamp = None  # builtin_interfaces/Time of the episode's frame, once resolved
        self.frame_id = ""
        self.rng = np.random.default_rng(0)
        self.refiner_rng = refiner_stream(0)
        # (service, round trip s, the node's own s) of every call, for benchmarks and diagnostics
        self.round_trips: deque[tuple[str, float, float]] = deque(maxlen=10_000)
        # time.monotonic() by which the current estimate must end (None: no deadline); a call
        # waits at most until then and raises DeadlineReached
        self.deadline: float | None = None
        self._discovered: set[str] = set()  # services that have been ready once

    # -- calls -------------------------------------------------------------------------------
    def _call(self, which: str, request: Any) -> Any:
        client = self.clients[which]
        timeout, cut = self.timeout, False
        if self.deadline is not None:  # the estimate's deadline comes first
            remaining = self.deadline - time.monotonic()
            if remaining <= 0:
                raise DeadlineReached(f"the deadline came before calling {client.srv_name}")
            timeout, cut = min(timeout, remaining), remaining < timeout
        local = local_services.find(self._resolved[which])
        if local is not None:  # a node of this (composed) process: its callback, without the middleware
            return self._call_local(which, local, request, timeout, cut)
        # A node that has just started may not be discovered yet: wait for it, up to the call's
        # timeout the first time (discovery on a loaded machine takes seconds), 2 s once it has
        # been seen (then it is more likely gone than late).
        wait = min(timeout, 2.0) if which in self._discovered else timeout
        if not client.service_is_ready() and not client.wait_for_service(timeout_sec=wait):
            if cut and timeout <= wait:
                raise DeadlineReached(f"the deadline came while waiting for {client.srv_name} to be discovered")
            raise OperatorCallError(f"service {client.srv_name} is not available: is {NODES[which]} running?")
        self._discovered.add(which)
        start = time.perf_counter()
        future = client.call_async(request)
        self._executor.spin_until_future_complete(future, timeout_sec=timeout)
        if not future.done() and not cut:
            # A last look: this process may have been stopped (SIGSTOP, a suspended VM) while the
            # answer came; its middleware threads need a moment after resuming to hand it over.
            self._executor.spin_until_future_complete(future, timeout_sec=LAST_LOOK)
        if not future.done():
            client.remove_pending_request(future)
            if cut:
                raise DeadlineReached(f"the deadline came while waiting {timeout:.3g} s for {client.srv_name}")
            # Measured here, in this process: it cannot tell a stopped, overloaded or dead node
            # (or this process having been stopped) apart, so it names no cause.
            raise OperatorCallError(f"{client.srv_name} did not answer within {timeout:g} s "
                                    f"(operator_timeout; served by {NODES[which]})")
        response = future.result()
        if response is None:
            raise OperatorCallError(f"{client.srv_name} gave no answer (shutting down?)")
        self.round_trips.append((which, time.perf_counter() - start, float(response.elapsed)))
        return response

    def _call_local(self, which: str, local: local_services.LocalService, request: Any, timeout: float,
                    cut: bool) -> Any:
        start = time.perf_counter()
        response = local.call(request, timeout)
        if response is None:
            if cut:
                raise DeadlineReached(f"the deadline came while waiting {timeout:.3g} s for {self._resolved[which]}")
            raise OperatorCallError(f"{self._resolved[which]} did not answer within {timeout:g} s "
                                    f"(operator_timeout; served by {NODES[which]} in this process)")
        self.round_trips.append((which, time.perf_counter() - start, float(response.elapsed)))
        return response

    def _hypothesis(self) -> Hypothesis:
        assert self.episode is not None and self.pose is not None
        hyp = Hypothesis()
        if self.stamp is not None:
            hyp.header.stamp = self.stamp
        hyp.header.frame_id = self.frame_id
        hyp.object_id = str(self.episode.model.obj_id)
        hyp.pose = self.pose_msg if self.pose_msg is not None else pose_to_msg(self.pose)
        return hyp

    def _result(self, response: Any, pose_from: Hypothesis | None) -> BlockResult:
        """The answer as a BlockResult; the answered pose message rides in info["pose_msg"]."""
        if not response.success:
            return BlockResult(ok=False, reason=response.message, elapsed=float(response.elapsed))
        if pose_from is None:
            return BlockResult(ok=True, elapsed=float(response.elapsed))
        try:
            pose = msg_to_pose(pose_from.pose)
        except ValueError as exc:
            return BlockResult(ok=False, reason=f"the node answered an unusable pose: {exc}",
                               elapsed=float(response.elapsed))
        scores = dict(zip(pose_from.score_names, pose_from.scores))  # when asked for (fused scoring)
        return BlockResult(ok=True, pose=pose, scores=scores, elapsed=float(response.elapsed),
                           info={"pose_msg": pose_from.pose})

    def _generate(self, method: str) -> BlockResult:
        assert self.episode is not None
        req = GenerateHypothesis.Request(object_id=str(self.episode.model.obj_id), method=method,
                                         noise_lambda=float(self.episode.noise_lambda), seed=draw_seed(self.rng),
                                         score=self.fused_scoring)
        if self.stamp is not None:
            req.frame.stamp = self.stamp
        else:
            req.frame.stamp.sec, req.frame.stamp.nanosec = divmod(int(self.episode.stamp_ns), 1_000_000_000)
        res = self._call("generate", req)
        # "latest" is resolved once, by the first answer's frame: its hypothesis, or the first
        # candidate of a refusal (next_candidate scores that candidate on the same frame)
        answered = res.hypothesis if res.success else (res.candidates[0] if res.candidates else None)
        if answered is not None and self.stamp is None:
            self.stamp = answered.header.stamp
            self.frame_id = answered.header.frame_id
        first = 1 if res.success else 0  # a refused call's candidates all wait (InProcessOperators._generate)
        try:
            self._candidates = [(float(conf), msg_to_pose(h.pose), h.pose)
                                for conf, h in zip(res.confidences[first:], res.candidates[first:])]
        except ValueError:  # an unusable candidate pose: offer none rather than a wrong one
            self._candidates = []
        return self._result(res, res.hypothesis if res.success else None)

    @property
    def candidates(self) -> list[tuple[float, Pose]]:
        """The last generator call's ranked candidates not yet taken, best first."""
        return [(conf, pose) for conf, pose, _ in self._candidates]

    def _next_candidate(self, block: Any) -> BlockResult:
        """`next_candidate`, here: the block picks from the waiting candidates, no node is asked."""
        assert self.episode is not None
        result = block(BlockInput(frame=None, model=self.episode.model, pose=self.pose, candidates=self.candidates))
        if result.ok:
            result.info["pose_msg"] = self._candidates[0][2]
            self._candidates = self._candidates[1:]
        return result

    def _score(self) -> dict[str, float]:
        names = self.pipeline.score_names
        if self.pose is None:
            return {n: math.nan for n in names}
        res = self._call("score", ScoreHypothesis.Request(hypothesis=self._hypothesis()))
        if not res.success:
            return {n: math.nan for n in names}
        got = dict(zip(res.hypothesis.score_names, res.hypothesis.scores))
        return {n: float(got.get(n, math.nan)) for n in names}

    def _outcome(self, action: str, result: BlockResult, started: float) -> StepOutcome:
        t_score = time.perf_counter()
        names = self.pipeline.score_names
        if result.ok and result.pose is not None:
            self.pose, self.pose_msg = result.pose, result.info.get("pose_msg")
            if self.fused_scoring and set(names) <= set(result.scores):  # scored by the operator's node
                self.scores = {n: float(result.scores[n]) for n in names}
            else:
                self.scores = self._score()
        elif not self.scores:
            self.scores = self._score()
        # else: the hypothesis did not change (a pick, a failed operator): scoring is deterministic,
        # so the scores are the ones it already has, and a round trip is saved.
        now = time.perf_counter()
        return StepOutcome(action, result, dict(self.scores), self.pose, now - started, now - t_score)

    # -- the interface -------------------------------------------------------------------
    def start(self, episode: Episode) -> StepOutcome:
        self.episode = episode
        self.rng = np.random.default_rng(episode.seed)
        self.refiner_rng = refiner_stream(episode.seed)
        self.pose, self.pose_msg, self.scores, self._candidates = None, None, {}, []
        self.stamp, self.frame_id = None, ""
        started = time.perf_counter()
        return self._outcome("generate", self._generate(self.pipeline.generator.name), started)

    def apply(self, action: str) -> StepOutcome:
        act = self.pipeline.action(action)
        started = time.perf_counter()
        if act.kind == Kind.GENERATION:
            if act.block.takes_candidate:
                return self._outcome(action, self._next_candidate(act.block), started)
            return self._outcome(action, self._generate(action), started)
        if self.pose is None:
            return self._outcome(action, BlockResult.fail("no hypothesis to work on"), started)
        if act.kind == Kind.REFINEMENT:
            res = self._call("refine", RefineHypothesis.Request(hypothesis=self._hypothesis(), method=action,
                                                                 seed=draw_seed(self.refiner_rng),
                                                                 score=self.fused_scoring))
            return self._outcome(action, self._result(res, res.hypothesis if res.success else None), started)
        if act.kind == Kind.PICK:
            res = self._call("pick", Pick.Request(hypothesis=self._hypothesis()))
            result = self._result(res, None)
            result.picked = bool(res.picked) if res.success else None
            return self._outcome(action, result, started)
        raise ValueError(f"action {action!r} is a {act.kind.value} block, which is not an action")

    def snapshot(self) -> Any:
        return (self.pose, self.pose_msg, dict(self.scores), self.rng.bit_generator.state,
                self.refiner_rng.bit_generator.state, self.stamp, self.frame_id, list(self._candidates))

    def hypothesis(self) -> Any:
        return self.pose, self.pose_msg, dict(self.scores)

    def set_hypothesis(self, hypothesis: Any) -> None:
        pose, pose_msg, scores = hypothesis
        self.pose, self.pose_msg, self.scores = pose, pose_msg, dict(scores)

    def restore(self, state: Any) -> None:
        (self.pose, self.pose_msg, scores, rng_state, refiner_state, self.stamp, self.frame_id,
         candidates) = state
        self._candidates = list(candidates)
        self.scores = dict(scores)
        self.rng = np.random.default_rng()
        self.rng.bit_generator.state = rng_state
        self.refiner_rng = np.random.default_rng()
        self.refiner_rng.bit_generator.state = refiner_state

    def timing_summary(self) -> str:
        """Median round trip and node time per service over the recorded calls (for the logs)."""
        parts = []
        for which in SERVICES:
            rows = [(rt, own) for w, rt, own in self.round_trips if w == which]
            if rows:
                rt, own = (float(np.median([r[i] for r in rows])) * 1000 for i in (0, 1))
                parts.append(f"{SERVICES[which]} {len(rows)} calls, round trip {rt:.2f} ms (node {own:.2f} ms)")
        return "; ".join(parts) or "no operator calls"

    def close(self) -> None:
        """Destroy the private client node (before rclpy shuts down)."""
        self._executor.shutdown()
        self.node.destroy_node()

    @property
    def stamp_ns(self) -> int:
        return 0 if self.stamp is None else stamp_to_nanoseconds(self.stamp)
