"""What one played episode leaves behind (`Trajectory`) and the action-mask and return helpers
that the episode loop, the agents and the learners share."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class Trajectory:
    """One episode as an agent played it: the observation before each action, the actions, the
    rewards (minus seconds, minus penalties), and the outcome."""

    obs: np.ndarray  # (T, obs_dim) float32
    actions: np.ndarray  # (T,) int64
    rewards: np.ndarray  # (T,) float64: minus seconds, minus penalties (failed pick, truncation)
    seconds: np.ndarray  # (T,) float64: the time each action was charged (failed-pick attempts included)
    success: bool  # ended by a successful pick
    noise_lambda: float
    episode_index: int  # -1 for an episode given to reset (the configurator)
    first_pick_success: bool = False  # the first pick of the episode succeeded
    stopped: bool = False  # ended by play_episode's `stop` (a deadline), not by the env or max_steps
    names: list[str] = field(default_factory=list)  # action names, as actions
    oks: list[bool] = field(default_factory=list)  # whether each operator succeeded
    reasons: list[str] = field(default_factory=list)  # why each failed operator failed ("" where it succeeded)
    operation_seconds: list[float] = field(default_factory=list)  # measured seconds of each operator call
    block_seconds: list[float] = field(default_factory=list)  # of which the block itself (through ROS: in its node)
    time: float = 0.0  # seconds charged (env.episode_time: failed picks at their robot cost)
    cost: float = 0.0  # minus the return: time plus the truncation penalty
    initial_info: dict[str, Any] = field(default_factory=dict)  # reset's info (the initial hypothesis)
    final_info: dict[str, Any] = field(default_factory=dict)  # the last step's info (final pose, scores)
    # info["action_mask"] before each action (T, n) int8 (1 = could run); None when the env gave none
    masks: np.ndarray | None = None
    # Per action, for the episode store (store/episode_store.py): the scores and the hypothesis after
    # it (a geometry.Pose or None), and a pick's result where a pick action ran (None otherwise).
    step_scores: list[dict[str, float]] = field(default_factory=list)
    step_poses: list[Any] = field(default_factory=list)
    step_picked: list[bool | None] = field(default_factory=list)
    initial_operation_seconds: float = 0.0  # measured seconds of the generator call in reset

    @property
    def steps(self) -> int:
        return int(len(self.actions))

    def allowed_actions(self, n_actions: int) -> np.ndarray:
        """(T, n_actions) bool: the actions that could run before each step (all without masks).
        Where no action could run, nothing is masked (as `allowed_actions`)."""
        if self.masks is None or len(self.masks) != self.steps:
            return np.ones((self.steps, n_actions), bool)
        m = np.asarray(self.masks).reshape(self.steps, n_actions) != 0
        m[~m.any(axis=1)] = True
        return m

    @property
    def ret(self) -> float:
        return float(self.rewards.sum())


def allowed_actions(info: Any, n_actions: int) -> np.ndarray | None:
    """The actions that can run, as a bool array of `n_actions`, from the env's
    `info["action_mask"]`; None when there is no mask, when every action can run, or when none
    can (then nothing is masked): an agent acts exactly as without a mask, with the same random
    draws, whenever the mask does not restrict it."""
    mask = info.get("action_mask") if isinstance(info, dict) else None
    if mask is None:
        return None
    m = np.asarray(mask).reshape(-1) != 0
    if m.shape != (n_actions,):
        raise ValueError(f"info['action_mask'] has {m.size} entries, the agent has {n_actions} actions")
    if m.all() or not m.any():
        return None
    return m


def returns_to_go(rewards: np.ndarray, gamma: float = 1.0) -> np.ndarray:
    """G_t = sum_{k >= t} gamma^(k-t) r_k."""
    out = np.zeros(len(rewards), np.float64)
    running = 0.0
    for t in range(len(rewards) - 1, -1, -1):
        running = rewards[t] + gamma * running
        out[t] = running
    return out
