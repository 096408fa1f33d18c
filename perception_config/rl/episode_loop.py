"""The one episode loop: reset, then act, step and observe until the episode ends.

Training, evaluation, the ROS configurator and replay-check all play episodes through
`play_episode`, so they count operations, time, first picks and success the same way. The
agent's acting randomness is reseeded per episode (`act_seed`; `acting_seed(episode_seed)`
where an episode seed exists), so one agent's run of an episode does not depend on what ran
before it, in-process or through ROS. The agent sees the env's `info` (with its
`info["action_mask"]`) at every decision; the masks are kept in the trajectory for learners.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Protocol

import numpy as np

from ..blocks.base import Kind
from .trajectory import Trajectory

if TYPE_CHECKING:
    from .env import PerceptionConfigEnv


class EpisodeAgent(Protocol):
    """What the loop asks of an agent (agents.base.Agent is one)."""

    def begin_episode(self, seed: int | None = None) -> None: ...

    def act(self, obs: np.ndarray, info: dict[str, Any]) -> int: ...

    def observe(self, reward: float, obs: np.ndarray, terminated: bool, truncated: bool,
                info: dict[str, Any]) -> None: ...


def acting_seed(episode_seed: int) -> int:
    """The seed of an agent's acting randomness in the episode with this seed: evaluation and
    the ROS configurator act the same way on the same episode."""
    return int(np.random.SeedSequence([int(episode_seed), 1]).generate_state(1)[0])


def play_episode(
    env: PerceptionConfigEnv,
    agent: EpisodeAgent,
    options: dict[str, Any] | None = None,
    act_seed: int | None = None,
    *,
    max_steps: int | None = None,
    require_hypothesis: bool = False,
    stop: Callable[[], bool] | None = None,
    on_step: Callable[[str, dict[str, Any]], None] | None = None,
) -> Trajectory:
    """Play one episode of `env` with `agent` and return its trajectory.

    `options` go to `env.reset` (episode index or Episode, lambda, episode_seed); `act_seed`
    reseeds the agent's acting randomness. `max_steps` stops earlier than the env's max_ops
    (a request's own limit), without the truncation charge. `require_hypothesis`: raise
    ValueError when the generator gives no first hypothesis instead of letting the agent try,
    unless the refused call left ranked candidates and the pipeline can take them
    (next_candidate): the agent was trained to go on from there.
    `stop` is asked before each action; True ends the episode there like `max_steps` (the
    configurator's per-estimate deadline, or a cancelled goal) and sets `Trajectory.stopped`.
    `on_step(action_name, info)` is called after each action (the configurator's feedback).
    """
    env_ = getattr(env, "unwrapped", env)
    obs, info = env.reset(options=options)
    if require_hypothesis and not info["ok"] and not _candidates_wait(env_):
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
    reasons: list[str] = []
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
        reasons.append("" if info["ok"] else str(info.get("reason") or ""))
        op_seconds.append(float(env_.last_outcome.elapsed))  # measured, whatever the time mode charges
        block_seconds.append(float(env_.last_outcome.result.elapsed))
        pick_ran = bool(info["ok"]) and env_.pipeline.actions[a].kind == Kind.PICK
        if first_pick is None and pick_ran:
            first_pick = bool(info["picked"])
        step_scores.append(dict(info["scores"]))
        step_poses.append(info["pose"])
        step_picked.append(bool(info["picked"]) if pick_ran else None)
        if on_step is not None:
            on_step(names[-1], info)
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
        reasons=reasons,
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


def _candidates_wait(env: Any) -> bool:
    """Whether a refused first generator call left candidates that an action of the pipeline takes."""
    takes = any(getattr(a.block, "takes_candidate", False) for a in env.pipeline.actions)
    return takes and bool(getattr(env.ops, "candidates", None))
