"""The block model: the paper's formally modelled building blocks.

A block declares its `kind` (generation | refinement | scoring | pick), its `name`, the inputs
it uses, and its parameters with defaults and valid ranges. Calling a block returns a
`BlockResult` (pose and/or scores, `ok`, a reason when not ok, elapsed seconds). A block never
raises on bad data: `Block.__call__` validates the inputs, times the call and turns any
exception into `ok=False` with a reason, so an agent (or a ROS service) can always go on.
"""
from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, ClassVar

import numpy as np

from ..geometry import Pose
from ..models import ObjectModel
from ..scene import Frame


class Kind(str, Enum):
    GENERATION = "generation"
    REFINEMENT = "refinement"
    SCORING = "scoring"
    PICK = "pick"


# Inputs a block may declare.
RGB, DEPTH, MODEL, POSE, GROUND_TRUTH = "rgb", "depth", "model", "pose", "ground_truth"


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
    ground truth but no camera frame yet can still run simulated_init). `cache` holds per-frame precomputations (edge maps, point clouds) that several blocks
    share; it belongs to the frame and is dropped with it. `rng` makes stochastic blocks seeded.
    """

    frame: Frame | None
    model: ObjectModel
    pose: Pose | None = None
    ground_truth: Pose | None = None
    rng: np.random.Generator = field(default_factory=lambda: np.random.default_rng(0))
    cache: dict[str, Any] = field(default_factory=dict)
    scores: dict[str, float] = field(default_factory=dict)  # scores of `pose`, when known


@dataclass
class BlockResult:
    """The outcome of one block call. `pose` is the new hypothesis (generation, refinement);
    `scores` the named scores (scoring, and refiners that measure something on the way);
    `picked` the outcome of a pick."""

    ok: bool
    pose: Pose | None = None
    scores: dict[str, float] = field(default_factory=dict)
    picked: bool | None = None
    reason: str = ""
    elapsed: float = 0.0
    info: dict[str, Any] = field(default_factory=dict)

    @staticmethod
    def fail(reason: str) -> "BlockResult":
        return BlockResult(ok=False, reason=reason)


class Block(ABC):
    """Base class of all blocks. Subclasses set the class attributes and implement `run`."""

    kind: ClassVar[Kind]
    name: ClassVar[str]
    inputs: ClassVar[tuple[str, ...]] = ()
    params: ClassVar[tuple[Param, ...]] = ()
    # Names of the scores this block puts in BlockResult.scores (the observation layout of the
    # learning environment is built from the scoring blocks' names).
    score_names: ClassVar[tuple[str, ...]] = ()

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

    @abstractmethod
    def run(self, inp: BlockInput) -> BlockResult:
        """The algorithm; inputs have been checked. May raise: __call__ turns it into ok=False."""


REGISTRY: dict[str, type[Block]] = {}


def register(cls: type[Block]) -> type[Block]:
    """Class decorator adding a block to the registry under its `name`."""
    if cls.name in REGISTRY and REGISTRY[cls.name] is not cls:
        raise ValueError(f"two blocks are named {cls.name!r}: {REGISTRY[cls.name].__name__} and {cls.__name__}")
    REGISTRY[cls.name] = cls
    return cls


def create(name: str, **params: Any) -> Block:
    """Instantiate a registered block with parameter overrides."""
    from . import load_all  # the block modules register themselves on import

    load_all()
    if name not in REGISTRY:
        raise ValueError(f"unknown block {name!r}; known blocks: {', '.join(sorted(REGISTRY))}")
    return REGISTRY[name](**params)
