"""Pipeline configuration: the action set and the scoring set, from YAML.

    generator: {block: simulated_init, params: {noise_lambda: 0.5}}
    actions:                       # the agent's discrete actions, in this order
      - {name: icp_coarse, block: icp_point_to_plane, params: {max_correspondence_distance: 0.03}}
      - {name: regenerate, block: simulated_init}
      - {name: pick, block: simulated_pick}
    scoring: [psi_d, psi_c, icp_fitness]   # run after every action; their scores form the state

An action is one block with one parameter preset. The file is checked when loaded: unknown
blocks or parameters, values out of range, duplicate names, an action of the wrong kind, or no
pick action give an error naming the file and the entry.
"""
from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from .base import DEPTH, Block, Kind, create


class PipelineError(ValueError):
    """A pipeline configuration that cannot be used; the message names the file and entry."""


@dataclass(frozen=True)
class Action:
    name: str
    block: Block

    @property
    def kind(self) -> Kind:
        return self.block.kind


@dataclass(frozen=True)
class Pipeline:
    generator: Block
    actions: tuple[Action, ...]
    scoring: tuple[Block, ...]
    source: str = ""

    @property
    def action_names(self) -> list[str]:
        return [a.name for a in self.actions]

    @property
    def score_names(self) -> list[str]:
        """The scores the scoring set produces, in order: the state layout of the environment."""
        return [n for b in self.scoring for n in b.score_names]

    @property
    def score_ranges(self) -> dict[str, tuple[float, float]]:
        """(low, high) of every score of the scoring set that declares one (Block.score_ranges)."""
        return {n: r for b in self.scoring for n, r in b.score_ranges.items()}

    @property
    def lower_is_better(self) -> frozenset[str]:
        """The scores of the scoring set where small means good."""
        return frozenset(n for b in self.scoring for n in b.lower_is_better)

    @property
    def depth_actions(self) -> list[str]:
        """The actions whose block needs depth: masked on an RGB-only frame (rl/env.py)."""
        return [a.name for a in self.actions if DEPTH in a.block.inputs]

    @property
    def depth_scoring(self) -> list[str]:
        """The scoring blocks that need depth: their scores are missing on an RGB-only frame."""
        return [b.name for b in self.scoring if DEPTH in b.inputs]

    def action(self, name: str) -> Action:
        for a in self.actions:
            if a.name == name:
                return a
        raise KeyError(f"no action {name!r} in the pipeline; actions: {self.action_names}")

    def describe(self) -> dict[str, Any]:
        """A JSON-able description (saved with policies so a mismatch can be detected)."""
        return {
            "generator": {"block": self.generator.name, "params": self.generator.config},
            "actions": [{"name": a.name, "block": a.block.name, "params": a.block.config} for a in self.actions],
            "scoring": [b.name for b in self.scoring],
            "score_names": self.score_names,
        }


def _make_block(spec: Any, where: str, source: str) -> Block:
    if isinstance(spec, str):
        spec = {"block": spec}
    if not isinstance(spec, dict) or "block" not in spec:
        raise PipelineError(f"{source}: {where} must be a block name or a mapping with 'block', got {spec!r}")
    params = spec.get("params") or {}
    if not isinstance(params, dict):
        raise PipelineError(f"{source}: {where}: 'params' must be a mapping, got {params!r}")
    try:
        return create(str(spec["block"]), **params)
    except ValueError as exc:
        raise PipelineError(f"{source}: {where}: {exc}") from None


def pipeline_from_dict(data: Any, source: str = "<pipeline>") -> Pipeline:
    if not isinstance(data, dict):
        raise PipelineError(f"{source}: a pipeline must be a mapping with generator, actions, scoring")
    missing = [k for k in ("generator", "actions", "scoring") if k not in data]
    if missing:
        raise PipelineError(f"{source}: missing {', '.join(missing)}")
    generator = _make_block(data["generator"], "generator", source)
    if generator.kind != Kind.GENERATION:
        raise PipelineError(f"{source}: generator {generator.name!r} is a {generator.kind.value} block")

    if not isinstance(data["actions"], list) or not data["actions"]:
        raise PipelineError(f"{source}: 'actions' must be a non-empty list")
    actions: list[Action] = []
    for i, spec in enumerate(data["actions"]):
        name = spec.get("name") if isinstance(spec, dict) else spec
        if not name or not isinstance(name, str):
            raise PipelineError(f"{source}: actions[{i}] needs a 'name'")
        if any(a.name == name for a in actions):
            raise PipelineError(f"{source}: two actions are named {name!r}")
        block = _make_block(spec, f"action {name!r}", source)
        if block.kind == Kind.SCORING:
            raise PipelineError(f"{source}: action {name!r} is a scoring block; scoring runs after every action")
        actions.append(Action(name, block))
    if not any(a.kind == Kind.PICK for a in actions):
        raise PipelineError(f"{source}: the actions contain no pick: an episode could never end in success")

    if not isinstance(data["scoring"], list) or not data["scoring"]:
        raise PipelineError(f"{source}: 'scoring' must be a non-empty list")
    scoring = tuple(_make_block(s, f"scoring[{i}]", source) for i, s in enumerate(data["scoring"]))
    for b in scoring:
        if b.kind != Kind.SCORING:
            raise PipelineError(f"{source}: scoring block {b.name!r} is a {b.kind.value} block")
    names = [n for b in scoring for n in b.score_names]
    if len(names) != len(set(names)):
        raise PipelineError(f"{source}: scoring blocks produce duplicate score names {names}")
    return Pipeline(generator, tuple(actions), scoring, source)


def shipped_pipelines() -> list[str]:
    """Names of the pipelines shipped in the package (`<name>_pipeline.yaml`): 'cell', 'default',
    'pick_success', 'rgb'."""
    return sorted(p.name[: -len("_pipeline.yaml")] for p in resources.files("perception_config.config").iterdir()
                  if p.name.endswith("_pipeline.yaml"))


def pipeline_reference(path: str | Path | None) -> str | None:
    """How a run records its pipeline: a shipped pipeline's name as is, a file as its absolute
    path, None for the default."""
    if path is None:
        return None
    if not Path(path).exists() and str(path) in shipped_pipelines():
        return str(path)
    return str(Path(path).resolve())


def load_pipeline(path: str | Path | None = None) -> Pipeline:
    """Load a pipeline YAML file, or a shipped pipeline by name ('default', 'rgb', 'cell'; None = the
    default). A file of that name in the working folder wins over the shipped one."""
    if path is None:
        path = "default"
    if not Path(path).exists() and str(path) in shipped_pipelines():
        name = f"{path}_pipeline.yaml"
        text = resources.files("perception_config.config").joinpath(name).read_text()
        source = f"<package>/config/{name}"
    else:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"pipeline configuration {path} does not exist "
                                    f"(shipped pipelines by name: {', '.join(shipped_pipelines())})")
        text, source = path.read_text(), str(path)
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise PipelineError(f"{source}: not valid YAML: {exc}") from None
    return pipeline_from_dict(data, source)
