"""PerceptionConfig-v0: choose the next pose-estimation operator until the robot can pick.

Episode: one object in one frame of a BOP dataset, starting from the configured generator's
hypothesis (simulated initialisation at a noise level lambda, or a real generator). Without a
dataset (the ROS configurator) each reset is given its episode: options={"episode": Episode}.

Action space: Discrete(n) over the pipeline's actions, in the YAML's order (refiners with their
presets, regenerate, pick).

Observation space: Box(0, 1, (n_scores + 2 * 1 + n + 4,), float32)
  - the scoring set's scores of the current hypothesis, each mapped to [0, 1]
    (SCORE_RANGES; unknown scores through x / (1 + |x|)), plus a flag per score that it is
    missing (scoring failed, e.g. no hypothesis): [scores..., missing...]
  - progress: step / max_ops, one-hot of the last action (all zero at the start),
    pose change of the last step (translation / diameter, rotation / pi, both clipped to 1),
    1 if a pick already failed in this episode, 1 if the last action failed.

Reward: minus the seconds each action took (the block plus the scoring after it); a failed pick
also costs the robot's attempt time (`failed_pick_cost`, default 2 s). A successful pick ends
the episode (terminated); `max_ops` actions truncate it, and an episode truncated without a
successful pick is charged `truncation_cost` (default 10 s: giving up on the object). Without
that charge "never pick" would be the optimal policy: a few cheap operations cost less than
one pick attempt. It is a penalty, not time: it is in the reward and in
info["truncation_cost"], not in info["seconds"] / info["episode_time"].

Time: measured wall time by default; `time_mode="cost_table"` charges fixed seconds per action
(and per scoring pass) from `cost_table`, for reproducible runs and tests.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from .blocks.base import Kind
from .blocks.pipeline import Pipeline, load_pipeline
from .datasets.bop import BopDataset
from .episodes import EpisodeSource
from .geometry import rotation_angle
from .operators import Episode, InProcessOperators, Operators, StepOutcome

# Ranges that map a score to [0, 1]: (low, high) -> (x - low) / (high - low), clipped.
SCORE_RANGES: dict[str, tuple[float, float]] = {
    "psi_d": (0.0, 1.0),  # M1 + M2: shares of the same rendered pixels, disjoint
    "psi_d_m1": (0.0, 1.0),
    "psi_d_m2": (0.0, 1.0),
    "psi_c": (0.0, 1.0),
    "icp_fitness": (0.0, 1.0),
    "icp_rmse": (0.0, 0.01),
}

# Default seconds for the deterministic cost-table mode (medians of benchmarks/ on one core).
DEFAULT_COST_TABLE: dict[str, float] = {
    "simulated_init": 0.0005,
    "global_registration": 2.0,
    "icp_point_to_point": 0.04,
    "icp_point_to_plane": 0.02,
    "d2co": 0.04,
    "chamfer": 0.03,
    "chamfer_icp": 0.03,
    "depth_refine": 0.003,
    "simulated_pick": 0.5,
    "external_pick": 0.5,
    "scoring": 0.008,
}

LAMBDA_MAX = 2.0


def normalise_score(name: str, value: float) -> float:
    if not math.isfinite(value):
        return 0.0
    if name in SCORE_RANGES:
        low, high = SCORE_RANGES[name]
        return float(np.clip((value - low) / (high - low), 0.0, 1.0))
    return float(0.5 + 0.5 * value / (1.0 + abs(value)))


class PerceptionConfigEnv(gym.Env):
    metadata = {"render_modes": []}

    def __init__(
        self,
        dataset: str | Path | BopDataset | EpisodeSource | None,
        pipeline: str | Path | Pipeline | None = None,
        *,
        split: str = "test",
        image_keys: list[tuple[int, int]] | None = None,
        lambda_range: tuple[float, float] = (0.1, 1.0),
        max_ops: int = 10,
        failed_pick_cost: float = 2.0,
        truncation_cost: float = 10.0,
        time_mode: str = "measured",
        cost_table: dict[str, float] | None = None,
        min_visib_fract: float = 0.3,
        operators: Operators | None = None,
    ) -> None:
        super().__init__()
        lo, hi = (float(x) for x in lambda_range)
        if not (0.0 <= lo <= hi <= LAMBDA_MAX):
            raise ValueError(f"lambda_range must satisfy 0 <= low <= high <= {LAMBDA_MAX}, got {lambda_range}")
        if max_ops < 1:
            raise ValueError(f"max_ops must be >= 1, got {max_ops}")
        if time_mode not in ("measured", "cost_table"):
            raise ValueError(f"time_mode must be 'measured' or 'cost_table', got {time_mode!r}")
        self.source: EpisodeSource | None
        if dataset is None:  # episodes come with reset(options={"episode": Episode(...)})
            self.source = None
        elif isinstance(dataset, EpisodeSource):
            self.source = dataset
        else:
            ds = dataset if isinstance(dataset, BopDataset) else BopDataset(Path(dataset), split=split)
            self.source = EpisodeSource(ds, image_keys, min_visib_fract=min_visib_fract)
        self.pipeline = pipeline if isinstance(pipeline, Pipeline) else load_pipeline(pipeline)
        self.ops: Operators = operators if operators is not None else InProcessOperators(self.pipeline)
        self.lambda_range = (lo, hi)
        self.max_ops = int(max_ops)
        self.failed_pick_cost = float(failed_pick_cost)
        if not (math.isfinite(truncation_cost) and truncation_cost >= 0.0):
            raise ValueError(f"truncation_cost must be a finite number >= 0, got {truncation_cost}")
        self.truncation_cost = float(truncation_cost)
        self.time_mode = time_mode
        self.cost_table = {**DEFAULT_COST_TABLE, **(cost_table or {})}
        if time_mode == "cost_table":
            missing = [a.block.name for a in self.pipeline.actions if a.block.name not in self.cost_table]
            if missing:
                raise ValueError(f"cost_table has no entry for blocks {missing}")

        self.action_names = self.pipeline.action_names
        self.score_names = self.pipeline.score_names
        n_act, n_sc = len(self.action_names), len(self.score_names)
        self.observation_layout = (
            [f"score:{s}" for s in self.score_names] + [f"missing:{s}" for s in self.score_names]
            + ["progress:step"] + [f"last_action:{a}" for a in self.action_names]
            + ["progress:dt", "progress:drot", "progress:pick_failed", "progress:last_failed"]
        )
        self.observation_space = spaces.Box(0.0, 1.0, shape=(len(self.observation_layout),), dtype=np.float32)
        self.action_space = spaces.Discrete(n_act)
        self._n_scores = n_sc
        self._reset_state()

    # -- state ---------------------------------------------------------------------------
    def _reset_state(self) -> None:
        self.steps = 0
        self.last_action: int | None = None
        self.last_outcome: StepOutcome | None = None
        self.pose_change = (0.0, 0.0)
        self.pick_failed = False
        self.last_failed = False
        self.episode = None
        self.episode_time = 0.0

    def _seconds(self, outcome: StepOutcome, block_name: str) -> float:
        if self.time_mode == "measured":
            return float(outcome.elapsed)
        return self.cost_table[block_name] + self.cost_table["scoring"]  # "scoring": the whole scoring pass

    def _obs(self) -> np.ndarray:
        scores = self.last_outcome.scores if self.last_outcome else {}
        vals = [scores.get(s, math.nan) for s in self.score_names]
        one_hot = np.zeros(len(self.action_names), np.float32)
        if self.last_action is not None:
            one_hot[self.last_action] = 1.0
        obs = np.concatenate([
            [normalise_score(s, v) for s, v in zip(self.score_names, vals)],
            [0.0 if math.isfinite(v) else 1.0 for v in vals],
            [min(1.0, self.steps / self.max_ops)],
            one_hot,
            [min(1.0, self.pose_change[0]), min(1.0, self.pose_change[1] / math.pi),
             float(self.pick_failed), float(self.last_failed)],
        ]).astype(np.float32)
        return obs

    def _info(self, outcome: StepOutcome, seconds: float) -> dict[str, Any]:
        ep = self.episode
        info: dict[str, Any] = {
            "action": outcome.action, "ok": outcome.result.ok, "reason": outcome.result.reason,
            "seconds": seconds, "scores": dict(outcome.scores), "picked": outcome.result.picked,
            "episode_time": self.episode_time, "steps": self.steps,
            "episode_key": ep.key if ep else None, "noise_lambda": ep.noise_lambda if ep else None,
            "pose": outcome.pose,
        }
        return info

    # -- Gymnasium API -------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        options = options or {}
        index = options.get("episode")
        given = index if isinstance(index, Episode) else None
        if given is None and self.source is None:
            raise ValueError("this environment has no dataset: pass reset(options={'episode': Episode(...)})")
        if given is None and index is None:
            index = int(self.np_random.integers(len(self.source)))
        if given is None and not 0 <= int(index) < len(self.source):
            raise ValueError(f"episode index {index} out of range 0..{len(self.source) - 1}")
        lam = given.noise_lambda if given is not None else options.get("lambda")
        if lam is None:
            lam = float(self.np_random.uniform(*self.lambda_range))
        if not (math.isfinite(lam) and 0.0 <= lam <= LAMBDA_MAX):
            raise ValueError(f"lambda must be in [0, {LAMBDA_MAX}], got {lam}")
        self._reset_state()
        if given is not None:
            self.episode = given
        else:
            ep_seed = int(options.get("episode_seed", self.np_random.integers(2**31)))
            self.episode = self.source.load(int(index), lam, ep_seed)
        outcome = self.ops.start(self.episode)
        self.last_outcome = outcome
        seconds = self._seconds(outcome, self.pipeline.generator.name)
        self.episode_time = 0.0  # the initial hypothesis is common to all agents: not charged
        info = self._info(outcome, seconds)
        info["episode_index"] = -1 if given is not None else int(index)
        info["generation_seconds"] = seconds
        return self._obs(), info

    def step(self, action):
        if self.episode is None:
            raise RuntimeError("call reset() before step()")
        a = int(action)
        if not self.action_space.contains(a):
            raise ValueError(f"action {action!r} is not in {self.action_space}")
        name = self.action_names[a]
        block = self.pipeline.actions[a].block
        before = self.last_outcome.pose if self.last_outcome else None
        outcome = self.ops.apply(name)
        seconds = self._seconds(outcome, block.name)
        reward = -seconds
        terminated = False
        if block.kind == Kind.PICK and outcome.result.ok:
            if outcome.result.picked:
                terminated = True
            else:
                self.pick_failed = True
                reward -= self.failed_pick_cost
                seconds += self.failed_pick_cost
        self.steps += 1
        self.episode_time += seconds
        self.last_action = a
        self.last_failed = not outcome.result.ok
        after = outcome.pose
        if before is not None and after is not None:
            self.pose_change = (
                float(np.linalg.norm(after.t - before.t) / self.episode.model.diameter),
                rotation_angle(before.R, after.R),
            )
        else:
            self.pose_change = (0.0, 0.0)
        self.last_outcome = outcome
        truncated = not terminated and self.steps >= self.max_ops
        if truncated:
            reward -= self.truncation_cost
        info = self._info(outcome, seconds)
        info["truncation_cost"] = self.truncation_cost if truncated else 0.0
        return self._obs(), float(reward), terminated, truncated, info


def register() -> None:
    """Register `PerceptionConfig-v0` with Gymnasium (idempotent)."""
    if "PerceptionConfig-v0" not in gym.registry:
        gym.register(id="PerceptionConfig-v0", entry_point="perception_config.env:PerceptionConfigEnv")


register()
