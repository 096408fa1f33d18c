"""An episode as the episode store keeps it (store/episode_store.py): one row of `episodes` and
its rows of `steps` (step 0 is reset's initial hypothesis, 1.. the actions), before it is stored;
`record_from_trajectory` makes one from an episode `play_episode` played."""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ..rl.episode_loop import Trajectory


@dataclass
class StepRecord:
    """One row of `steps` (the episode id is given when it is stored)."""

    step: int
    action: str
    ok: bool
    seconds: float
    operation_seconds: float
    scores: dict[str, float]
    pose: Any = None  # geometry.Pose or None
    picked: bool | None = None
    pick_source: str | None = None


@dataclass
class EpisodeRecord:
    """One row of `episodes` and its steps, before it is stored."""

    source: str
    policy_version: str | None
    agent: str | None
    dataset: str | None
    scene_id: int | None
    im_id: int | None
    obj_id: int | None
    frame_stamp_ns: int | None
    noise_lambda: float | None
    generator: str | None
    episode_seed: int | None
    success: bool
    first_pick_success: bool
    time_s: float
    cost: float
    stopped: bool
    steps: list[StepRecord] = field(default_factory=list)
    label: str | None = None  # what judged its picks (episode_store.LABEL_KINDS); `pick_label` derives it
    created: float = field(default_factory=time.time)


def record_from_trajectory(traj: Trajectory, *, source: str, agent: str | None, policy_version: str | None,
                           dataset: str | None = None, episode_seed: int | None = None,
                           frame_stamp_ns: int | None = None, pick_source: str = "simulated") -> EpisodeRecord:
    """The store's record of an episode `play_episode` played: the object, frame key and lambda
    come from reset's info; what the trajectory cannot know (where it ran, the policy, the
    dataset, the episode seed, the camera stamp) is given. `pick_source`: who reported the picks
    ('simulated' for the pick simulation, 'robot' for a real cell)."""
    init = traj.initial_info
    key = init.get("episode_key") or (None, None, None)
    steps = [StepRecord(0, str(init.get("action", "")), bool(init.get("ok", False)), 0.0,
                        float(traj.initial_operation_seconds), dict(init.get("scores") or {}), init.get("pose"))]
    n = traj.steps
    scores = traj.step_scores if len(traj.step_scores) == n else [{}] * n
    poses = traj.step_poses if len(traj.step_poses) == n else [None] * n
    picked = traj.step_picked if len(traj.step_picked) == n else [None] * n
    ops = traj.operation_seconds if len(traj.operation_seconds) == n else [math.nan] * n
    for i in range(n):
        steps.append(StepRecord(i + 1, traj.names[i], bool(traj.oks[i]), float(traj.seconds[i]), float(ops[i]),
                                dict(scores[i]), poses[i], picked[i], pick_source if picked[i] is not None else None))
    lam = init.get("noise_lambda")
    return EpisodeRecord(
        source=source, policy_version=policy_version, agent=agent, dataset=dataset,
        scene_id=_int_or_none(key[0]), im_id=_int_or_none(key[1]), obj_id=_int_or_none(key[2]),
        frame_stamp_ns=int(frame_stamp_ns) if frame_stamp_ns else None,
        noise_lambda=float(lam) if lam is not None else None, generator=steps[0].action or None,
        episode_seed=_int_or_none(episode_seed), success=bool(traj.success),
        first_pick_success=bool(traj.first_pick_success), time_s=float(traj.time), cost=float(traj.cost),
        stopped=bool(traj.stopped), steps=steps, label=pick_label(steps, pick_source))


def pick_label(steps: list[StepRecord], pick_source: str) -> str:
    """The episode's label kind from its picks: "ground_truth" when the pick simulation (which
    judges against the ground truth) answered one, "robot" when a robot did, "none" without a
    pick outcome. A caller that knows more (the configurator, which holds the frame's ground
    truth) overrides it."""
    if not any(s.picked is not None for s in steps):
        return "none"
    return "robot" if pick_source == "robot" else "ground_truth"


def _int_or_none(x: Any) -> int | None:
    return None if x is None else int(x)
