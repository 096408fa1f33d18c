"""The operators behind the environment: one interface, two backends.

An episode is one object in one frame. The backend holds the episode's current hypothesis and
runs the pipeline's blocks on it: the generator at the start (and for a `regenerate` action),
any action by name, and the scoring set after every action. `InProcessOperators` calls the
blocks directly (training, evaluation); the ROS backend (perception_config/ros/) makes the
same calls as service requests to the operator nodes. Same environment, same policy, either
backend.
"""
from __future__ import annotations

import copy
import hashlib
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from ..blocks.base import GROUND_TRUTH, Block, BlockInput, BlockResult, Kind
from ..blocks.pipeline import Pipeline
from ..core.geometry import Pose, as_transmitted
from ..core.models import ObjectModel
from ..core.scene import Frame


@dataclass
class Episode:
    """One (frame, object) episode. `ground_truth` is None in a robot cell.

    `labels`: without ground truth, what judges a pick instead (online/pick_labels.PickLabels:
    the robot's own outcomes in this frame; an object with `judge(pose, model, scores)`).
    In-process the frame is here; through ROS the images stay in the operator nodes, `frame` is
    None and `stamp_ns` names the camera frame (0 = the latest). `has_depth`: whether the
    camera gives depth when the frame is not here (None = unknown; the frame's own wins).
    """

    frame: Frame | None
    model: ObjectModel
    ground_truth: Pose | None
    noise_lambda: float
    seed: int
    key: tuple[int, int, int] = (0, 0, 0)  # scene_id, im_id, obj_id
    stamp_ns: int = 0
    has_depth: bool | None = None
    labels: Any = None

    @property
    def depth_known_absent(self) -> bool:
        """True when the episode's camera is RGB-only (its frame has no depth, or, without the
        frame here, `has_depth` is False): the blocks that need depth cannot run."""
        return (self.frame.depth is None) if self.frame is not None else self.has_depth is False


def draw_seed(rng: np.random.Generator) -> int:
    """The seed of one stochastic block call, drawn from an episode stream (never 0: 0 = "draw
    one" in the services). Both backends seed every generator call from the episode's stream
    and every refiner call (D2CO samples contour points) from a second stream of the episode
    (`refiner_stream`), so an episode with the same seed computes the same hypotheses in-process
    and through ROS, and refiners do not shift the generator's draws."""
    return int(rng.integers(1, 2**32))


def refiner_stream(episode_seed: int) -> np.random.Generator:
    return np.random.default_rng([int(episode_seed), 1])


class FrameCaches:
    """Per-frame precomputations (edge maps, point clouds) of the most recent frames, an LRU.

    Keyed by the frame object's identity (checked, so a recycled id() cannot alias), so
    consecutive operator calls on the same frame share them.
    """

    def __init__(self, size: int = 4) -> None:
        self._caches: OrderedDict[int, dict[str, Any]] = OrderedDict()
        self._size = size

    def get(self, frame: Frame | None) -> dict[str, Any]:
        if frame is None:
            return {}
        key = id(frame)
        cache = self._caches.get(key)
        if cache is None or cache.get("__frame__") is not frame:
            cache = {"__frame__": frame}
            self._caches[key] = cache
        self._caches.move_to_end(key)
        while len(self._caches) > self._size:
            self._caches.popitem(last=False)
        return cache


def frame_fingerprint(frame: Frame, cache: dict[str, Any]) -> str:
    """A digest of the frame's images and intrinsics (a sparse grid of pixels: cheap, and two
    different camera frames do not share it), kept in the frame's cache."""
    digest = cache.get("__fingerprint__")
    if digest is None:
        h = hashlib.blake2b(digest_size=16)
        for img in (frame.rgb, frame.depth):
            if img is not None:
                h.update(np.ascontiguousarray(img[::7, ::5]).tobytes())
                h.update(str(img.shape).encode())
        h.update(np.asarray(frame.K, np.float64).tobytes())
        digest = cache["__fingerprint__"] = h.hexdigest()
    return digest


class GeneratorMemo:
    """Results of ground-truth-free generator calls, reused when the same call comes again.

    A generator's result is a function of the frame, the model, its parameters and (when it
    `uses_rng`) its seed; the hindsight oracle tries every action from many states, and training
    meets the same (image, object) in many episodes, so a search of 0.5-2 s would be repeated
    over and over. A reused result keeps the seconds the call took (`elapsed`): time is charged
    as if it had run. Keyed by `frame_fingerprint`, the object, the block's name and parameters,
    the seed (blocks that use it) and whether the call was time-bounded; an LRU of `size`."""

    def __init__(self, size: int = 4096) -> None:
        self._results: OrderedDict[tuple, BlockResult] = OrderedDict()
        self._size = size
        self.hits = 0

    @staticmethod
    def applies(block: Block) -> bool:
        """Whether results of `block` are reused: generators that search the frame (not
        simulated_init, which is cheap and reads the ground truth; not next_candidate)."""
        return block.kind == Kind.GENERATION and GROUND_TRUTH not in block.inputs and not block.takes_candidate

    def call(self, block: Block, inp: BlockInput, seed: int) -> BlockResult:
        if inp.frame is None:
            return block(inp)
        key = (frame_fingerprint(inp.frame, inp.cache), inp.model.obj_id, float(inp.model.diameter), block.name,
               tuple(sorted((k, repr(v)) for k, v in block.config.items())),
               seed if block.uses_rng else None, inp.time_bounded)
        hit = self._results.get(key)
        if hit is not None:
            self.hits += 1
            self._results.move_to_end(key)
            return copy.copy(hit)
        result = block(inp)
        self._results[key] = copy.copy(result)
        while len(self._results) > self._size:
            self._results.popitem(last=False)
        return result


@dataclass
class StepOutcome:
    """What one operator call did: the block's result, the scoring after it, the total time."""

    action: str
    result: BlockResult
    scores: dict[str, float]
    pose: Pose | None
    elapsed: float  # seconds: the block plus the scoring after it
    score_elapsed: float = 0.0
    info: dict[str, Any] = field(default_factory=dict)


class Operators(Protocol):
    """The backend interface the environment drives."""

    pipeline: Pipeline
    # the ranked candidates of the last generator call not yet taken, best first (next_candidate)
    candidates: list[tuple[float, Pose]]

    def start(self, episode: Episode) -> StepOutcome:
        """Begin an episode: run the generator and the scoring; the hypothesis is set."""

    def apply(self, action: str) -> StepOutcome:
        """Run one action of the pipeline on the current hypothesis, then the scoring."""

    def snapshot(self) -> Any:
        """An opaque copy of the episode state (hypothesis, scores, rng), for hindsight search."""

    def restore(self, state: Any) -> None:
        """Return to a state from `snapshot`."""

    def hypothesis(self) -> Any:
        """A copy of the current hypothesis and its scores (a tuple, the pose first; not the rng or
        candidates)."""

    def set_hypothesis(self, hypothesis: Any) -> None:
        """Make a hypothesis from `hypothesis()` the current one again, with its scores."""


class InProcessOperators:
    """Runs the pipeline's blocks in this process.

    Per-frame precomputations (edge maps, point clouds) live in a small LRU keyed by the frame
    identity, so consecutive episodes on the same frame share them. `time_bounded=False` lifts
    the blocks' wall-clock bounds (`BlockInput.time_bounded`; the env's cost-table mode).
    Ground-truth-free generator results are reused for the same call (`GeneratorMemo`).
    After a generator call the candidates it ranked below its pose wait in `candidates` for
    `next_candidate`; a call that failed (its best candidate verified below the generator's
    threshold) leaves all it ranked, the first too, and none when it ranked none.
    """

    def __init__(self, pipeline: Pipeline, frame_cache_size: int = 4, time_bounded: bool = True) -> None:
        self.pipeline = pipeline
        self.time_bounded = bool(time_bounded)
        self._caches = FrameCaches(frame_cache_size)
        self._generators: dict[float, Any] = {}
        self.memo = GeneratorMemo()
        self.candidates: list[tuple[float, Pose]] = []
        self.episode: Episode | None = None
        self.pose: Pose | None = None
        self.scores: dict[str, float] = {}
        self.rng = np.random.default_rng(0)
        self.refiner_rng = refiner_stream(0)

    # -- helpers -------------------------------------------------------------------------
    def _input(self, pose: Pose | None, rng: np.random.Generator | None = None) -> BlockInput:
        ep = self.episode
        assert ep is not None, "no episode started"
        return BlockInput(
            frame=ep.frame, model=ep.model, pose=pose, ground_truth=ep.ground_truth,
            rng=self.rng if rng is None else rng, cache=self._caches.get(ep.frame), scores=dict(self.scores),
            time_bounded=self.time_bounded,
        )

    def _generate(self, block) -> BlockResult:
        """A generator call with its own seed from the episode's stream (see `draw_seed`); its
        ranked candidates below the pose become `candidates` (next_candidate takes them in turn)."""
        if block.takes_candidate:  # draws no seed: it searches nothing
            inp = self._input(self.pose)
            inp.candidates = list(self.candidates)
            result = block(inp)
            if result.ok:
                self.candidates = self.candidates[1:]
            return result
        seed = draw_seed(self.rng)
        inp = self._input(self.pose, np.random.default_rng(seed))
        result = self.memo.call(block, inp, seed) if GeneratorMemo.applies(block) else block(inp)
        # an accepted call's first candidate is the pose; a call whose best candidate verified below
        # its threshold (ok=False) leaves them all waiting: the agent sees how many and how confident
        self.candidates = [(c, as_transmitted(p)) for c, p in result.candidates[0 if not result.ok else 1:]]
        return result

    def _generator(self, noise_lambda: float):
        """The generator block with this episode's noise level, when it has one."""
        gen = self.pipeline.generator
        if "noise_lambda" not in gen.config:
            return gen
        block = self._generators.get(noise_lambda)
        if block is None:
            block = type(gen)(**{**gen.config, "noise_lambda": float(noise_lambda)})
            self._generators[noise_lambda] = block
        return block

    def _score(self) -> tuple[dict[str, float], float]:
        scores: dict[str, float] = {}
        elapsed = 0.0
        inp = self._input(self.pose)
        for block in self.pipeline.scoring:
            r = block(inp)
            elapsed += r.elapsed
            for name in block.score_names:
                scores[name] = float(r.scores.get(name, np.nan)) if r.ok else np.nan
        return scores, elapsed

    def _outcome(self, action: str, result: BlockResult) -> StepOutcome:
        if result.ok and result.pose is not None:
            self.pose = as_transmitted(result.pose)  # as the ROS nodes pass it on
        self.scores, score_elapsed = self._score()
        return StepOutcome(action, result, dict(self.scores), self.pose, result.elapsed + score_elapsed, score_elapsed)

    # -- the interface -------------------------------------------------------------------
    def start(self, episode: Episode) -> StepOutcome:
        self.episode = episode
        self.rng = np.random.default_rng(episode.seed)
        self.refiner_rng = refiner_stream(episode.seed)
        self.pose, self.scores, self.candidates = None, {}, []
        result = self._generate(self._generator(episode.noise_lambda))
        return self._outcome("generate", result)

    def apply(self, action: str) -> StepOutcome:
        act = self.pipeline.action(action)
        block = act.block
        if block.kind == Kind.GENERATION:
            assert self.episode is not None
            block = self._generator(self.episode.noise_lambda) if block.name == self.pipeline.generator.name else block
            return self._outcome(action, self._generate(block))
        assert self.episode is not None
        if block.kind == Kind.PICK and self.episode.ground_truth is None and self.episode.labels is not None:
            return self._outcome(action, self._labelled_pick())
        rng = np.random.default_rng(draw_seed(self.refiner_rng)) if block.kind == Kind.REFINEMENT else None
        result = block(self._input(self.pose, rng))
        return self._outcome(action, result)

    def _labelled_pick(self) -> BlockResult:
        """A pick judged by the episode's labels (no ground truth: the robot's outcomes)."""
        ep = self.episode
        assert ep is not None
        if self.pose is None:
            return BlockResult.fail("no hypothesis to pick")
        started = time.perf_counter()
        picked, figures = ep.labels.judge(self.pose, ep.model, self.scores)
        return BlockResult(ok=True, picked=bool(picked), scores=figures, info={"criterion": "robot labels"},
                           elapsed=time.perf_counter() - started)

    def snapshot(self) -> Any:
        return (self.pose, dict(self.scores), self.rng.bit_generator.state, self.refiner_rng.bit_generator.state,
                list(self.candidates))

    def hypothesis(self) -> Any:
        return self.pose, dict(self.scores)

    def set_hypothesis(self, hypothesis: Any) -> None:
        pose, scores = hypothesis
        self.pose, self.scores = pose, dict(scores)

    def restore(self, state: Any) -> None:
        self.pose, scores, rng_state, refiner_state, candidates = state
        self.candidates = list(candidates)
        self.scores = dict(scores)
        self.rng = np.random.default_rng()
        self.rng.bit_generator.state = rng_state
        self.refiner_rng = np.random.default_rng()
        self.refiner_rng.bit_generator.state = refiner_state
