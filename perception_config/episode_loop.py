"""The one episode loop: reset, then act, step and observe until the episode ends.

Training, evaluation, the ROS configurator and replay-check all play episodes through
`play_episode`, so they count operations, time, first picks and success the same way. The
agent's acting randomness is reseeded per episode (`act_seed`; `acting_seed(episode_seed)`
where an episode seed exists), so one agent's run of an episode does not depend on what ran
before it, in-process or through ROS. The agent sees the env's `info` (with its
`info["action_mask"]`) at every decision; the masks are kept in the trajectory for learners.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from .blocks.base import Kind

if TYPE_CHECKING:
    from .agents.base import Agent
    from .env import PerceptionConfigEnv


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
    operation_seconds: list[float] = field(default_factory=list)  # measured seconds of each operator call
    block_seconds: list[float] = field(default_factory=list)  # of which the block itself (through ROS: in its node)
    time: float = 0.0  # seconds charged (env.episode_time: failed picks at their robot cost)
    cost: float = 0.0  # minus the return: time plus the truncation penalty
    initial_info: dict[str, Any] = field(default_factory=dict)  # reset's info (the initial hypothesis)
    final_info: dict[str, Any] = field(default_factory=dict)  # the last step's info (final pose, scores)
    # info["action_mask"] before each action (T, n) int8 (1 = could run); None when the env gave none
    masks: np.ndarray | None = None
    # Per action, for the episode store (episode_store.py): the scores and the hypothesis after
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
        Where no action could run, nothing is masked (as `agents.base.allowed_actions`)."""
        if self.masks is None or len(self.masks) != self.steps:
            return np.ones((self.steps, n_actions), bool)
        m = np.asarray(self.masks).reshape(self.steps, n_actions) != 0
        m[~m.any(axis=1)] = True
        return m

    @property
    def ret(self) -> float:
        return float(self.rewards.sum())


def acting_seed(episode_seed: int) -> int:
    """The seed of an agent's acting randomness in the episode with this seed: evaluation and
    the ROS configurator act the same way on the same episode."""
    return int(np.random.SeedSequence([int(episode_seed), 1]).generate_state(1)[0])


def play_episode(
    env: PerceptionConfigEnv,
    agent: Agent,
    options: dict[str, Any] | None = None,
    act_seed: int | None = None,
    *,
    max_steps: int | None = None,
    require_hypothesis: bool = False,
    stop: Callable[[], bool] | None = None,
) -> Trajectory:
    """Play one episode of `env` with `agent` and return its trajectory.

    `options` go to `env.reset` (episode index or Episode, lambda, episode_seed); `act_seed`
    reseeds the agent's acting randomness. `max_steps` stops earlier than the env's max_ops
    (a request's own limit), without the truncation charge. `require_hypothesis`: raise
    ValueError when the generator gives no first hypothesis instead of letting the agent try.
    `stop` is asked before each action; True ends the episode there like `max_steps` (the
    configurator's per-estimate deadline) and sets `Trajectory.stopped`.
    """
    env_ = getattr(env, "unwrapped", env)
    obs, info = env.reset(options=options)
    if require_hypothesis and not info["ok"]:
        raise ValueError(f"no first hypothesis: {info['reason']}")
    agent.begin_episode(act_seed)
    initial_info = info
    initial_elapsed = float(env_.last_outcome.elapsed) if env_.last_outcome is not None else 0.0
    obs_l: list[np.ndarray] = []
    act_l: list[int] = []
    rew_l: list[float] = []
    sec_l: list[float] = []
    names: list[str] = []
    oks: list[bool] = []
    op_seconds: list[float] = []
    block_seconds: list[float] = []
    mask_l: list[np.ndarray] = []
    step_scores: list[dict[str, float]] = []
    step_poses: list[Any] = []
    step_picked: list[bool | None] = []
    first_pick: bool | None = None
    cost = 0.0
    terminated = truncated = stopped = False
    while not (terminated or truncated):
        if stop is not None and stop():
            stopped = True
            break
        a = int(agent.act(obs, info))
        obs_l.append(obs)
        if "action_mask" in info:
            mask_l.append(np.asarray(info["action_mask"], np.int8))
        obs, reward, terminated, truncated, info = env.step(a)
        agent.observe(reward, obs, terminated, truncated, info)
        cost -= reward
        act_l.append(a)
        rew_l.append(reward)
        sec_l.append(float(info["seconds"]))
        names.append(env_.action_names[a])
        oks.append(bool(info["ok"]))
        op_seconds.append(float(env_.last_outcome.elapsed))  # measured, whatever the time mode charges
        block_seconds.append(float(env_.last_outcome.result.elapsed))
        pick_ran = bool(info["ok"]) and env_.pipeline.actions[a].kind == Kind.PICK
        if first_pick is None and pick_ran:
            first_pick = bool(info["picked"])
        step_scores.append(dict(info["scores"]))
        step_poses.append(info["pose"])
        step_picked.append(bool(info["picked"]) if pick_ran else None)
        if max_steps is not None and len(act_l) >= max_steps:
            break
    index = (options or {}).get("episode", -1)
    return Trajectory(
        obs=np.asarray(obs_l, np.float32).reshape(len(obs_l), np.asarray(obs).size),  # (0, obs_dim): stopped at once
        actions=np.asarray(act_l, np.int64),
        rewards=np.asarray(rew_l, np.float64),
        seconds=np.asarray(sec_l, np.float64),
        success=bool(terminated and info["picked"]),
        noise_lambda=float(info.get("noise_lambda") or 0.0),
        episode_index=int(index) if isinstance(index, (int, np.integer)) else -1,
        first_pick_success=bool(first_pick),
        stopped=stopped,
        names=names,
        oks=oks,
        operation_seconds=op_seconds,
        block_seconds=block_seconds,
        time=float(env_.episode_time),
        cost=float(cost),
        initial_info=initial_info,
        final_info=info,
        masks=np.asarray(mask_l, np.int8).reshape(len(mask_l), -1) if mask_l and len(mask_l) == len(act_l) else None,
        step_scores=step_scores,
        step_poses=step_poses,
        step_picked=step_picked,
        initial_operation_seconds=initial_elapsed,
    )
