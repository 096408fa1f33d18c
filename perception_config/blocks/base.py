"""The block model: the paper's formally modelled building blocks.

A block declares its `kind` (generation | refinement | scoring | pick), its `name`, the inputs
it uses, its parameters with defaults and valid ranges, the seconds it is charged in the
environment's cost-table mode (`default_cost`), and the names and ranges of the scores it
returns (`score_names`, `score_ranges`, `lower_is_better`). Calling a block returns a
`BlockResult` (pose and/or scores, `ok`, a reason when not ok, elapsed seconds). A block never
raises on bad data: `Block.__call__` validates the inputs, times the call and turns any
exception into `ok=False` with a reason, so an agent (or a ROS service) can always go on.
A block that declares DEPTH answers ok=False "needs depth" at once, without work, on an RGB-only
frame (`Frame.depth` None): `frame_lacks` says which blocks cannot run on a frame.
"""
from __future__ import annotations

import importlib
import math
import pkgutil
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from enum import Enum
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from ..core.geometry import Pose
from ..core.models import ObjectModel
from ..core.scene import Frame


class Kind(str, Enum):
    GENERATION = "generation"
    REFINEMENT = "refinement"
    SCORING = "scoring"
    PICK = "pick"


# Inputs a block may declare.
RGB, DEPTH, MODEL, POSE, GROUND_TRUTH = "rgb", "depth", "model", "pose", "ground_truth"
# The reason a block that declares DEPTH gives, at once, on an RGB-only frame (Frame.depth None);
# the environment masks such actions (PerceptionConfigEnv.action_mask).
NEEDS_DEPTH = "needs depth"


def frame_lacks(inputs: tuple[str, ...], frame: Frame | None) -> str:
    """Why blocks with these `inputs` cannot run on `frame` at all, or '' when they can: a block
    that declares DEPTH on an RGB-only frame (depth None) "needs depth". A missing frame (None:
    through ROS the images stay in the operator nodes) is not judged here ('')."""
    if DEPTH in inputs and frame is not None and frame.depth is None:
        return f"{NEEDS_DEPTH}: the frame is RGB-only (no depth image)"
    return ""


@dataclass(frozen=True)
class Param:
    """A block parameter: default, valid range (numbers) or choices (strings), and what it means."""

    name: str
    default: Any
    low: float | None = None
    high: float | None = None
    choices: tuple[Any, ...] | None = None
    doc: str = ""

    def validate(self, value: Any) -> Any:
        if self.choices is not None:
            if value not in self.choices:
                raise ValueError(f"parameter {self.name!r} must be one of {list(self.choices)}, got {value!r}")
            return value
        if isinstance(self.default, bool):
            if not isinstance(value, bool):
                raise ValueError(f"parameter {self.name!r} must be true or false, got {value!r}")
            return value
        if isinstance(self.default, (int, float)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"parameter {self.name!r} must be a finite number, got {value!r}")
            if isinstance(self.default, int) and not isinstance(self.default, bool):
                if int(value) != value:
                    raise ValueError(f"parameter {self.name!r} must be an integer, got {value!r}")
                value = int(value)
            else:
                value = float(value)
            if (self.low is not None and value < self.low) or (self.high is not None and value > self.high):
                raise ValueError(f"parameter {self.name!r} must be in [{self.low}, {self.high}], got {value}")
        return value


@dataclass
class BlockInput:
    """What a block call sees: the frame, the object's model, the current hypothesis.

    `ground_truth` is given only to blocks that declare it (simulated initialisation, simulated
    pick). `frame` may be None for blocks that use no image (an operator node that has the
    ground truth but no camera frame yet can still run simulated_init). `cache` holds per-frame
    precomputations (edge maps, point clouds) that several blocks
    share; it belongs to the frame and is dropped with it. `rng` makes stochastic blocks seeded.
    `time_bounded=False` lifts the blocks' wall-clock bounds (`max_seconds`) for this call: they
    stop at their iteration bounds only, so the result does not depend on the machine's load
    (the environment's cost-table mode, where time is charged from the table anyway).
    """

    frame: Frame | None
    model: ObjectModel
    pose: Pose | None = None
    ground_truth: Pose | None = None
    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))
    cache: dict[str, Any] = field(default_factory=dict)
    scores: dict[str, float] = field(default_factory=dict)  # scores of `pose`, when known
    time_bounded: bool = True  # whether `max_seconds` bounds the call (wall clock)
    # the ranked candidates of the last generator call not yet taken, best first (next_candidate)
    candidates: list[tuple[float, Pose]] = field(default_factory=list)


@dataclass
class BlockResult:
    """The outcome of one block call. `pose` is the new hypothesis (generation, refinement);
    `scores` the named scores (scoring, and refiners that measure something on the way);
    `picked` the outcome of a pick. `candidates`: a generator's ranked hypotheses, best first,
    as (confidence in [0, 1], pose), distinct from each other; empty for a generator that
    proposes one pose only (simulated_init)."""

    ok: bool
    pose: Pose | None = None
    scores: dict[str, float] = field(default_factory=dict)
    picked: bool | None = None
    reason: str = ""
    elapsed: float = 0.0
    info: dict[str, Any] = field(default_factory=dict)
    candidates: list[tuple[float, Pose]] = field(default_factory=list)

    @staticmethod
    def fail(reason: str) -> "BlockResult":
        return BlockResult(ok=False, reason=reason)


class Block(ABC):
    """Base class of all blocks. Subclasses set the class attributes and implement `run`."""

    kind: ClassVar[Kind]
    name: ClassVar[str]
    inputs: ClassVar[tuple[str, ...]] = ()
    params: ClassVar[tuple[Param, ...]] = ()
    # Seconds charged for one call in the environment's cost-table mode (rl/settings.py): about
    # the block's median on one core (benchmarks/results/blocks.json). Every block declares it.
    default_cost: ClassVar[float]
    # Names of the scores this block puts in BlockResult.scores (the observation layout of the
    # learning environment is built from the scoring blocks' names).
    score_names: ClassVar[tuple[str, ...]] = ()
    # (low, high) of each score, mapped to [0, 1] in the agent's observation; a score without a
    # range is squashed by x / (1 + |x|). `lower_is_better`: scores where small means good.
    score_ranges: ClassVar[dict[str, tuple[float, float]]] = {}
    lower_is_better: ClassVar[tuple[str, ...]] = ()
    # Generators: whether the result depends on `inp.rng` (False: the same frame, model and
    # parameters give the same result, so a backend may reuse it).
    uses_rng: ClassVar[bool] = True
    # True for a block that takes the next of `inp.candidates` (next_candidate): the backends
    # keep the last generator call's candidates and pass on those not yet taken.
    takes_candidate: ClassVar[bool] = False

    def __init__(self, **overrides: Any) -> None:
        declared = {p.name: p for p in self.params}
        unknown = sorted(set(overrides) - set(declared))
        if unknown:
            raise ValueError(f"block {self.name!r} has no parameter(s) {unknown}; it has {sorted(declared)}")
        self.config: dict[str, Any] = {n: p.default for n, p in declared.items()}
        for key, value in overrides.items():
            self.config[key] = declared[key].validate(value)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({', '.join(f'{k}={v!r}' for k, v in self.config.items())})"

    def __call__(self, inp: BlockInput) -> BlockResult:
        start = time.perf_counter()
        try:
            problem = self._check_inputs(inp)
            result = BlockResult.fail(problem) if problem else self.run(inp)
            if result.ok and result.pose is not None and not result.pose.is_valid():
                result = BlockResult.fail(f"{self.name} produced an invalid pose")
        except Exception as exc:  # a block never raises on bad data
            result = BlockResult.fail(f"{self.name} failed: {type(exc).__name__}: {exc}")
        result.elapsed = time.perf_counter() - start
        return result

    def _check_inputs(self, inp: BlockInput) -> str:
        """A reason the inputs are unusable for this block, or '' when they are fine."""
        if (RGB in self.inputs or DEPTH in self.inputs) and inp.frame is None:
            return "this block needs the camera frame, which is not there"
        lacks = frame_lacks(self.inputs, inp.frame)
        if lacks:
            return f"{self.name} {lacks}"
        if DEPTH in self.inputs and not np.any(np.isfinite(inp.frame.depth)):
            return "the depth image has no valid pixel"
        if POSE in self.inputs:
            if inp.pose is None:
                return "no hypothesis to work on"
            if not inp.pose.is_valid():
                return "the hypothesis is degenerate (NaN, not a rotation, or behind the camera)"
        if GROUND_TRUTH in self.inputs and inp.ground_truth is None:
            return "this block needs the ground-truth pose, which the frame does not have"
        return ""

    def frame_lacks(self, frame: Frame | None) -> str:
        """Why this block cannot run on `frame` at all ('needs depth' on an RGB-only frame), or ''."""
        return frame_lacks(self.inputs, frame)

    def deadline(self, inp: BlockInput, start: float) -> float:
        """The perf_counter() time after which the call starts no new step: `start` plus the
        block's `max_seconds`, or infinity when the call is not time-bounded."""
        return start + float(self.config["max_seconds"]) if inp.time_bounded else math.inf

    @abstractmethod
    def run(self, inp: BlockInput) -> BlockResult:
        """The algorithm; inputs have been checked. May raise: __call__ turns it into ok=False."""


REGISTRY: dict[str, type[Block]] = {}


def register(cls: type[Block]) -> type[Block]:
    """Class decorator adding a block to the registry under its `name`, after checking that it
    describes itself: kind, name, a finite default_cost >= 0, ranges only of its own scores."""
    where = f"block class {cls.__module__}.{cls.__qualname__}"
    if not isinstance(getattr(cls, "name", None), str) or not cls.name:
        raise TypeError(f"{where} has no name")
    if not isinstance(getattr(cls, "kind", None), Kind):
        raise TypeError(f"{where} ({cls.name!r}) has no kind (a Kind)")
    cost = getattr(cls, "default_cost", None)
    if isinstance(cost, bool) or not isinstance(cost, (int, float)) or not math.isfinite(cost) or cost < 0:
        raise TypeError(f"{where} ({cls.name!r}) must declare default_cost, its seconds per call in cost-table "
                        f"mode (a finite number >= 0), got {cost!r}")
    for score, bounds in cls.score_ranges.items():
        if score not in cls.score_names:
            raise TypeError(f"{where} ({cls.name!r}) gives a range for {score!r}, which is not one of its "
                            f"score_names {list(cls.score_names)}")
        low, high = bounds
        if not (math.isfinite(low) and math.isfinite(high) and high > low):
            raise TypeError(f"{where} ({cls.name!r}): the range of {score!r} must be finite with high > low, "
                            f"got {bounds}")
    unknown = [n for n in cls.lower_is_better if n not in cls.score_names]
    if unknown:
        raise TypeError(f"{where} ({cls.name!r}): lower_is_better names {unknown}, not among its score_names")
    if cls.name in REGISTRY and REGISTRY[cls.name] is not cls:
        raise ValueError(f"two blocks are named {cls.name!r}: {REGISTRY[cls.name].__name__} and {cls.__name__}")
    REGISTRY[cls.name] = cls
    return cls


def create(name: str, **params: Any) -> Block:
    """Instantiate a registered block with parameter overrides."""
    if not (_ALL_LOADED and name in REGISTRY):  # once loaded, a known block needs no second look
        load_all()  # the block modules register themselves on import
    if name not in REGISTRY:
        raise ValueError(f"unknown block {name!r}; known blocks: {', '.join(sorted(REGISTRY))}")
    return REGISTRY[name](**params)


# --------------------------------------------------------------------------- discovery
ENTRY_POINT_GROUP = "perception_config.blocks"
_NOT_BLOCK_MODULES = frozenset({"base", "pipeline", "features"})
# load_all() has imported every block module and plug-in once: create() of a registered name skips
# it from then on (listing the installed packages' entry points takes tens of ms, per block of a
# pipeline); an unknown name still looks again.
_ALL_LOADED = False


def block_modules() -> list[str]:
    """The modules of this package that define blocks (every module but base, pipeline and features)."""
    here = [str(Path(__file__).parent)]
    return sorted(m.name for m in pkgutil.iter_modules(here) if m.name not in _NOT_BLOCK_MODULES)


def load_all() -> dict[str, type[Block]]:
    """Import every block module (they register themselves) and return the registry."""
    global _ALL_LOADED
    for module in block_modules():
        importlib.import_module(f"{__package__}.{module}")
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        try:
            ep.load()
        except Exception as exc:  # a broken plug-in names itself instead of a bare traceback
            raise ImportError(f"block plug-in {ep.name!r} ({ep.value}, entry point group {ENTRY_POINT_GROUP}) "
                              f"failed to load: {type(exc).__name__}: {exc}") from exc
    _ALL_LOADED = True
    return REGISTRY
