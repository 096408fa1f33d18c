"""What every agent shares: the environment's description, the agent interface, one episode.

An agent sees only an `EnvSpec` (action names and kinds, observation layout, max_ops), never
the environment object, so a policy can run against either operator backend (in-process or
ROS) and in worker processes. The exception is the oracle, which searches the live episode.

`EnvRecipe` is the picklable way to build the same environment again in a worker process.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np


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
    env_kwargs: dict[str, Any] = field(default_factory=dict)  # time_mode, max_ops, cost_table, ...

    def make(self) -> Any:
        from ..env import PerceptionConfigEnv

        keys = [tuple(k) for k in self.image_keys] if self.image_keys is not None else None
        return PerceptionConfigEnv(
            Path(self.dataset), self.pipeline, split=self.split, image_keys=keys, **self.env_kwargs
        )


class Agent:
    """The agent interface. Subclasses set `kind` and implement `act`.

    Training protocol (perception_config.training): the trainer asks `actors()` for the
    policies to run this round, runs each on `episodes_per_actor` episodes (all actors on the
    same episodes), and hands the trajectories to `update`. `explore` is True while training
    (sample / take random actions) and False when a loaded policy is evaluated (greedy).
    """

    kind: ClassVar[str] = ""

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

    def save(self, path: str | Path, extra: dict[str, Any] | None = None) -> Path:
        from .policy_io import save_agent

        return save_agent(self, path, extra)


@dataclass
class Trajectory:
    """One episode as an agent played it: the observation before each action, the actions,
    the rewards (minus seconds), and the outcome."""

    obs: np.ndarray  # (T, obs_dim) float32
    actions: np.ndarray  # (T,) int64
    rewards: np.ndarray  # (T,) float64: minus seconds, minus penalties (failed pick, truncation)
    seconds: np.ndarray  # (T,) float64: the time each action took (failed-pick attempts included)
    success: bool  # ended by a successful pick
    noise_lambda: float
    episode_index: int
    first_pick_success: bool = False  # the first pick of the episode succeeded
    names: list[str] = field(default_factory=list)

    @property
    def time(self) -> float:
        """Seconds the episode took (failed pick attempts included; the truncation penalty not)."""
        return float(self.seconds.sum())

    @property
    def steps(self) -> int:
        return int(len(self.actions))

    @property
    def ret(self) -> float:
        return float(self.rewards.sum())


def acting_seed(episode_seed: int) -> int:
    """The seed of an agent's acting randomness in the episode with this seed: evaluation and
    the ROS configurator act the same way on the same episode."""
    return int(np.random.SeedSequence([int(episode_seed), 1]).generate_state(1)[0])


def run_episode(env: Any, agent: Agent, options: dict[str, Any] | None = None, act_seed: int | None = None) -> Trajectory:
    """Play one episode of `env` with `agent` (reset options: episode, lambda, episode_seed)."""
    obs, info = env.reset(options=options)
    agent.begin_episode(act_seed)
    pick_ids = set(agent.spec.pick_actions)
    obs_l, act_l, rew_l, sec_l, names = [], [], [], [], []
    first_pick: bool | None = None
    terminated = truncated = False
    while not (terminated or truncated):
        a = int(agent.act(obs, info))
        obs_l.append(obs)
        obs, reward, terminated, truncated, info = env.step(a)
        act_l.append(a)
        rew_l.append(reward)
        sec_l.append(float(info.get("seconds", -reward)))
        names.append(agent.spec.action_names[a])
        if a in pick_ids and first_pick is None and info.get("ok"):
            first_pick = bool(info.get("picked"))
        agent.observe(reward, obs, terminated, truncated, info)
    return Trajectory(
        obs=np.asarray(obs_l, np.float32).reshape(len(obs_l), -1),
        actions=np.asarray(act_l, np.int64),
        rewards=np.asarray(rew_l, np.float64),
        seconds=np.asarray(sec_l, np.float64),
        success=bool(terminated),
        noise_lambda=float(info.get("noise_lambda") or 0.0),
        episode_index=int((options or {}).get("episode", -1)),
        first_pick_success=bool(first_pick),
        names=names,
    )


def returns_to_go(rewards: np.ndarray, gamma: float = 1.0) -> np.ndarray:
    """G_t = sum_{k >= t} gamma^(k-t) r_k."""
    out = np.zeros(len(rewards), np.float64)
    running = 0.0
    for t in range(len(rewards) - 1, -1, -1):
        running = rewards[t] + gamma * running
        out[t] = running
    return out
