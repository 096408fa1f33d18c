"""The simple memory agent of the paper: random with probability xi, else follow the memory.

What "memory" means here: a table over action histories. The key of a decision is the tuple
of actions already taken in this episode (the prefix; at step 0 the empty tuple), optionally
extended by the current scores binned into `score_bins` levels (score_bins=0, the default,
ignores the observation: the paper's agent remembers sequences, not states). For each key
and action a it holds n(key, a), how often a was taken there, and Q(key, a), the running
average of the return that followed (the sum of the rewards from that step to the end of
the episode: minus the seconds still spent until the episode ended). After every episode,
for each step t:  n <- n + 1;  Q <- Q + (G_t - Q) / n.

Acting: with probability xi a uniformly random action; otherwise the action with the
highest Q among those tried at this key; a key never seen before gets a random action.
xi decays per training episode: xi = max(xi_min, xi_start * xi_decay ** episodes).
A loaded agent is greedy (explore=False: xi = 0, still random at unseen keys).
Only actions that can run (`info["action_mask"]`) are chosen: random among them, greedy among
those tried (random among them when none was tried).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ..rl.trajectory import Trajectory, allowed_actions, returns_to_go
from .base import Agent, EnvSpec
from .hparams import SEED, Float, Int

Key = tuple[int, ...]


class SimpleAgent(Agent):
    """The paper's memory agent: xi-greedy over running-average returns per action history."""

    kind = "simple"
    HPARAM_BOUNDS = {"xi_start": Float(0.0, 1.0), "xi_min": Float(0.0, 1.0), "xi_decay": Float(0.0, 1.0),
                     "score_bins": Int(0, 1000), "seed": SEED}

    def __init__(self, spec: EnvSpec, xi_start: float = 1.0, xi_min: float = 0.05, xi_decay: float = 0.995,
                 score_bins: int = 0, seed: int = 0) -> None:
        super().__init__(spec, seed)
        if not (0.0 <= xi_min <= 1.0 and 0.0 <= xi_start <= 1.0 and 0.0 < xi_decay <= 1.0):
            raise ValueError("need 0 <= xi_min, xi_start <= 1 and 0 < xi_decay <= 1, "
                             f"got {xi_start}, {xi_min}, {xi_decay}")
        if score_bins < 0:
            raise ValueError(f"score_bins must be >= 0, got {score_bins}")
        self.xi_start, self.xi_min, self.xi_decay = float(xi_start), float(xi_min), float(xi_decay)
        self.score_bins = int(score_bins)
        self._score_idx = [i for i, name in enumerate(spec.observation_layout) if name.startswith("score:")]
        self.q: dict[Key, np.ndarray] = {}  # key -> Q per action
        self.n: dict[Key, np.ndarray] = {}  # key -> visit count per action
        self.episodes = 0
        self._history: list[int] = []

    @property
    def xi(self) -> float:
        return max(self.xi_min, self.xi_start * self.xi_decay ** self.episodes)

    def key(self, history: list[int] | tuple[int, ...], obs: np.ndarray) -> Key:
        k = tuple(int(a) for a in history)
        if self.score_bins:
            bins = np.minimum((np.asarray(obs)[self._score_idx] * self.score_bins).astype(int), self.score_bins - 1)
            k = k + (-1,) + tuple(int(b) for b in bins)  # -1 separates actions from score bins
        return k

    def begin_episode(self, seed: int | None = None) -> None:
        super().begin_episode(seed)
        self._history = []

    def act(self, obs: np.ndarray, info: dict[str, Any]) -> int:
        if isinstance(info, dict) and info.get("steps", len(self._history)) == 0:
            self._history = []  # a new episode even if begin_episode was not called
        k = self.key(self._history, obs)
        xi = self.xi if self.explore else 0.0
        allowed = allowed_actions(info, self.spec.n_actions)
        if k in self.n and self.rng.random() >= xi \
                and (allowed is None or (allowed & (self.n[k] > 0)).any()):
            tried = self.n[k] > 0 if allowed is None else (self.n[k] > 0) & allowed
            q = np.where(tried, self.q[k], -np.inf)
            best = np.flatnonzero(q == q.max())
            a = int(self.rng.choice(best))
        elif allowed is None:
            a = int(self.rng.integers(self.spec.n_actions))
        else:
            a = int(self.rng.choice(np.flatnonzero(allowed)))
        self._history.append(a)
        return a

    def update(self, trajectories: list[list[Trajectory]]) -> dict[str, float]:
        """The running-average update of every (key, action) an episode visited; returns xi (the
        exploration rate after this update) and memory_keys (the keys remembered)."""
        for per_actor in trajectories:
            for traj in per_actor:
                g = returns_to_go(traj.rewards)
                for t, a in enumerate(traj.actions):
                    k = self.key(traj.actions[:t].tolist(), traj.obs[t])
                    if k not in self.n:
                        self.q[k] = np.zeros(self.spec.n_actions)
                        self.n[k] = np.zeros(self.spec.n_actions, np.int64)
                    self.n[k][a] += 1
                    self.q[k][a] += (g[t] - self.q[k][a]) / self.n[k][a]
                self.episodes += 1
        return {"xi": self.xi, "memory_keys": float(len(self.n))}

    def hparams(self) -> dict[str, Any]:
        return {"xi_start": self.xi_start, "xi_min": self.xi_min, "xi_decay": self.xi_decay,
                "score_bins": self.score_bins, "seed": self.seed}

    def state(self) -> dict[str, Any]:
        return {
            "episodes": self.episodes,
            "memory": [{"key": list(k), "q": self.q[k].tolist(), "n": self.n[k].tolist()} for k in self.n],
        }

    def set_state(self, state: dict[str, Any]) -> None:
        """The memory from a file, checked: ValueError for anything but a list of entries with an
        integer key, finite Q and non-negative counts, one per action."""
        episodes = state.get("episodes", 0)
        if isinstance(episodes, bool) or not isinstance(episodes, int) or not 0 <= episodes < 2**62:
            raise ValueError(f"state.episodes must be an integer >= 0, got {episodes!r}"[:200])
        memory = state.get("memory", [])
        if not isinstance(memory, list):
            raise ValueError("state.memory must be a list")
        self.episodes = episodes
        self.q, self.n = {}, {}
        for i, entry in enumerate(memory):
            if not isinstance(entry, dict) or not isinstance(entry.get("key"), list) \
                    or not all(isinstance(x, int) and not isinstance(x, bool) and -2**31 <= x < 2**31
                               for x in entry["key"]):
                raise ValueError(f"memory entry #{i} must have a key of integers")
            k = tuple(entry["key"])
            q = np.asarray(entry.get("q"), np.float64)
            n = np.asarray(entry.get("n"), np.float64)
            if q.shape != (self.spec.n_actions,) or n.shape != q.shape:
                raise ValueError(f"memory entry {k} has {q.shape} actions, "
                                 f"the environment has {self.spec.n_actions}")
            if not (np.isfinite(q).all() and np.isfinite(n).all() and (n >= 0).all() and (n < 2**62).all()
                    and (n == np.round(n)).all()):
                raise ValueError(f"memory entry {k} must have finite Q values and non-negative integer counts")
            self.q[k], self.n[k] = q, n.astype(np.int64)

    def checkpoint(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        return {}, {}  # the memory and the episode count (xi) are the policy state
