"""What every agent shares: the environment's description and the agent interface.

An agent sees only an `EnvSpec` (action names and kinds, observation layout, max_ops), never
the environment object, so a policy can run against either operator backend (in-process or
ROS) and in worker processes. The exception is the oracle, which searches the live episode.

`EnvRecipe` is the picklable way to build the same environment again in a worker process.
Episodes are played by perception_config.rl.episode_loop.play_episode; policies are saved and
loaded by policy_io.py.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from ..rl.settings import EnvSettings
from ..rl.trajectory import Trajectory
from .hparams import SEED


@dataclass(frozen=True)
class EnvSpec:
    """The parts of PerceptionConfigEnv a policy depends on; saved with every policy."""

    action_names: tuple[str, ...]
    action_kinds: tuple[str, ...]  # "refinement" | "generation" | "pick", per action
    observation_layout: tuple[str, ...]
    max_ops: int
    actions: tuple[dict[str, Any], ...] = ()  # pipeline.describe()["actions"]: name, block, params

    @classmethod
    def from_env(cls, env: Any) -> "EnvSpec":
        env = getattr(env, "unwrapped", env)
        described = env.pipeline.describe()["actions"]
        return cls(
            action_names=tuple(env.action_names),
            action_kinds=tuple(a.kind.value for a in env.pipeline.actions),
            observation_layout=tuple(env.observation_layout),
            max_ops=int(env.max_ops),
            actions=tuple(json.loads(json.dumps(described))),  # JSON-normalised, as when loaded
        )

    @property
    def n_actions(self) -> int:
        return len(self.action_names)

    @property
    def obs_dim(self) -> int:
        return len(self.observation_layout)

    @property
    def pick_actions(self) -> list[int]:
        return [i for i, k in enumerate(self.action_kinds) if k == "pick"]

    def to_json(self) -> dict[str, Any]:
        return {
            "action_names": list(self.action_names), "action_kinds": list(self.action_kinds),
            "observation_layout": list(self.observation_layout), "max_ops": self.max_ops,
            "actions": list(self.actions),
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "EnvSpec":
        return cls(tuple(d["action_names"]), tuple(d["action_kinds"]), tuple(d["observation_layout"]),
                   int(d["max_ops"]), tuple(d.get("actions", ())))


@dataclass(frozen=True)
class EnvRecipe:
    """A picklable description of an environment: worker processes build their own from it."""

    dataset: str
    pipeline: str | None = None  # a pipeline YAML path; None = the shipped default
    image_keys: tuple[tuple[int, int], ...] | None = None
    split: str = "test"
    settings: EnvSettings = field(default_factory=EnvSettings)
    use_depth: bool = True  # False: the dataset read as RGB-only (BopDataset(use_depth=False))

    def make(self) -> Any:
        from ..rl.env import PerceptionConfigEnv  # gymnasium and the blocks: only where an env is built

        keys = [tuple(k) for k in self.image_keys] if self.image_keys is not None else None
        return PerceptionConfigEnv(Path(self.dataset), self.pipeline, self.settings, split=self.split, image_keys=keys,
                                   use_depth=self.use_depth)


class Agent:
    """The agent interface. Subclasses set `kind` and implement `act`.

    Training protocol (perception_config.learning.training): the trainer asks `actors()` for the
    policies to run this round, runs each on `episodes_per_actor` episodes (all actors on the
    same episodes), and hands the trajectories to `update`. `explore` is True while training
    (sample / take random actions) and False when a loaded policy is evaluated (greedy).
    """

    kind: ClassVar[str] = ""
    # The hyper-parameters a policy file may give and their bounds (hparams.py), checked before
    # the agent is built from a file.
    HPARAM_BOUNDS: ClassVar[dict[str, Any]] = {"seed": SEED}

    @classmethod
    def expected_tensors(cls, spec: EnvSpec, hparams: dict[str, Any]) -> dict[str, tuple[int, ...]]:
        """The policy tensors (name -> shape) that `hparams` and `spec` imply: checked against a
        file's tensors before the agent is built. Agents without weights: none."""
        return {}

    def __init__(self, spec: EnvSpec, seed: int = 0) -> None:
        self.spec = spec
        self.seed = int(seed)
        self.rng = np.random.default_rng(seed)  # acting randomness; reseeded per episode by runners
        self.explore = True

    # -- acting ---------------------------------------------------------------------------
    def begin_episode(self, seed: int | None = None) -> None:
        """Start an episode; `seed` reseeds the acting randomness (reproducible rollouts)."""
        if seed is not None:
            self.rng = np.random.default_rng(seed)

    def act(self, obs: np.ndarray, info: dict[str, Any]) -> int:
        """The next action. `info` is the env's (reset's or the last step's): its
        `info["action_mask"]` (1 = the action can run) is the mask every agent respects; read it
        with `allowed_actions(info)`. An agent that ignores it still works (a masked action
        answers ok=False "needs depth")."""
        raise NotImplementedError

    def observe(self, reward: float, obs: np.ndarray, terminated: bool, truncated: bool, info: dict[str, Any]) -> None:
        """The outcome of the last action (online agents; the batch learners ignore it)."""

    # -- learning -------------------------------------------------------------------------
    @property
    def episodes_per_actor(self) -> int:
        return 1

    def actors(self) -> list["Agent"]:
        """The policies to run in this training round (one, or a population)."""
        return [self]

    def update(self, trajectories: list[list["Trajectory"]]) -> dict[str, float]:
        """Learn from one round: trajectories[actor][episode]. Non-learning agents do nothing."""
        return {}

    # -- persistence: policy (shipped) and training state (checkpoints) ----------------------
    def hparams(self) -> dict[str, Any]:
        """Constructor keyword arguments (JSON-able) that rebuild this agent."""
        return {"seed": self.seed}

    def tensors(self) -> dict[str, np.ndarray]:
        """The policy's weights; empty for agents saved as JSON only."""
        return {}

    def set_tensors(self, tensors: dict[str, np.ndarray]) -> None:
        if tensors:
            raise ValueError(f"agent {self.kind!r} has no tensors, the file has {sorted(tensors)}")

    def state(self) -> dict[str, Any]:
        """JSON-able policy state beyond the weights (e.g. the simple agent's memory)."""
        return {}

    def set_state(self, state: dict[str, Any]) -> None:
        pass

    def checkpoint(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Training state beyond the policy, for checkpoints: (tensors named "train/...",
        JSON-able dict: counters, optimizer moments' companions, rng states)."""
        return {}, {}

    def load_checkpoint(self, tensors: dict[str, np.ndarray], state: dict[str, Any]) -> None:
        """Restore what `checkpoint` returned (the policy itself is restored before)."""
