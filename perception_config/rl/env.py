"""PerceptionConfig-v0: choose the next pose-estimation operator until the robot can pick.

Episode: one object in one frame of a BOP dataset, starting from the configured generator's
hypothesis (simulated initialisation at a noise level lambda, or a real generator). Without a
dataset (the ROS configurator) each reset is given its episode: options={"episode": Episode}.

Action space: Discrete(n) over the pipeline's actions, in the YAML's order (refiners with their
presets, regenerate, pick).

Observation space: Box(0, 1, (2 * n_scores + 1 + n + 4 [+ 2],), float32)
  - the scoring set's scores of the current hypothesis, each mapped to [0, 1] (the ranges
    the scoring blocks declare; a score without one through x / (1 + |x|)), plus a flag per score that it is
    missing (scoring failed, e.g. no hypothesis): [scores..., missing...]
  - progress: step / max_ops, one-hot of the last action (all zero at the start),
    pose change of the last step (translation / diameter, rotation / pi, both clipped to 1),
    1 if a pick already failed in this episode, 1 if the last action failed.
  - only in a pipeline with a `next_candidate` action (+2): the ranked candidates of the last
    generator call not yet taken (count / 5, clipped to 1) and the next one's confidence (0
    when none is left).

Action mask: reset's and every step's info carries `info["action_mask"]`, an np.int8 array of
n (1 = the action can run on this episode's frame, 0 = it cannot). An action cannot run when
its block needs an input the frame lacks: on an RGB-only frame (`Frame.depth` None) every block
that declares depth (the ICPs, depth_refine, global_registration). Every agent of the package
respects the mask. A masked action taken anyway does not crash: its block answers ok=False
"needs depth" at once, the hypothesis stays, and the step is charged like any failed action (the
block's cost-table seconds plus the scoring pass, or the measured time). With the frame in
the operator nodes (ROS, `Episode.frame` None) the mask follows `Episode.has_depth` (the
configurator's `use_depth` parameter); unknown (None): all ones, and an operator answers
"needs depth" itself. Besides the frame's mask (`frame_mask()`), `pick` is masked after a
failed pick until an action changes the hypothesis: the robot would try the very pose it just
failed on (in simulation it fails again, 2 s each; before this rule the policy-gradient agent
learned to repeat a failed pick until `max_ops`). A pick taken anyway is still attempted.
A generator that searches without a seed or the pose (ppf, resting_pose: `repeats_search`) is
masked once it ran in the episode: it would answer the same poses again (a trained agent called
ppf until `max_ops` after a failed pick); its candidates stay for next_candidate. Actions that
need a hypothesis stay allowed without one: they fail in milliseconds, the cheapest way to
give up on a part no generator finds (masking them, measured: the agent called 1 s generators
until `max_ops` instead, at a higher cost). Scoring blocks that need depth
are simply missing on an RGB-only frame (their missing flags are 1: the observation layout is
the same), and cost-table mode charges the scoring pass of the scoring blocks that can run only.

Reward: minus the seconds each action took (the block plus the scoring after it); a failed pick
also costs the robot's attempt time (`failed_pick_cost`, default 2 s). A successful pick ends
the episode (terminated); `max_ops` actions truncate it, and an episode truncated without a
successful pick is charged `truncation_cost` (default 10 s: giving up on the object). Without
that charge "never pick" would be the optimal policy: a few cheap operations cost less than
one pick attempt. It is a penalty, not time: it is in the reward and in
info["truncation_cost"], not in info["seconds"] / info["episode_time"].

Loop rule (`settings.loop_mask`, on by default): an action other than pick already taken at the
current hypothesis (the same pose within 2e-3 of the diameter and 2e-3 rad, rl/pose_memory.py:
it left the hypothesis unchanged, or the episode came back to it) is masked, and with
`settings.converge_tol` > 0 (default 0: off) so is one that has converged (its latest call moved
no point of the object by more than that share of the diameter and the hypothesis is still
where it left it), unless nothing else could run; `info["loop_mask"]` marks the actions masked
by this rule alone.

Final-pick rule (`settings.final_pick`, on by default): the last of the `max_ops` operations is
a pick: every other action is masked there (they could only end the episode truncated, at the
truncation charge; a pick may succeed), unless the pick cannot run itself (it just failed on this
hypothesis). It binds every agent, fixed pipelines included; `info["loop_mask"]` does not mark it.
With `settings.final_pick_best` (default off) and a pipeline that scores `pick_success` (the
calibrated probability that a pick succeeds), that last pick is taken at the best hypothesis the
episode reached by that score, when it scores higher than the current one (an anytime answer:
refiners can drift from a right pose; a hypothesis a pick failed on is not kept);
`info["picked_best"]` is True when it was.

Time: `time_mode="cost_table"` by default: fixed seconds per action and per scoring pass (the
settings' `cost_table`, a `perception-config calibrate` output, keyed `action:<name>@<obj_id>`,
`action:<name>`, then the block's name; the block's `default_cost` otherwise), so the reward does
not depend on the machine's load. In cost-table mode the in-process blocks run without their
wall-clock bounds (`max_seconds`), to their iteration bounds, and Open3D runs on one thread
during reset and step (its ICP sums in a scheduling-dependent order otherwise, ~1e-17 m apart;
the previous limit is restored after each call): the same seed and actions then give bitwise
the same observations, rewards and infos, on a loaded machine as on an idle one, which is what
Gymnasium's `check_env` asks: it passes on `gymnasium.make("PerceptionConfig-v0", dataset=...)`.
`time_mode="measured"` charges measured wall time instead (rewards no checker can find equal
twice); evaluation reports the measured wall time of the same episodes beside the charged one.

Settings: one `EnvSettings` (rl/settings.py: max_ops, failed_pick_cost, truncation_cost,
time_mode, cost_table, min_visib_fract, lambda_range, loop_mask, final_pick, final_pick_best,
converge_tol); keyword arguments of the same names override single fields
(`gymnasium.make("PerceptionConfig-v0", dataset=..., max_ops=5)`).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from ..blocks.base import DEPTH, POSE, Kind
from ..blocks.pipeline import Pipeline, load_pipeline
from ..core.geometry import check_noise_lambda, rotation_angle
from ..datasets.bop import BopDataset
from ..util.open3d_threads import open3d_single_thread
from .episodes import EpisodeSource
from .operators import Episode, InProcessOperators, Operators, StepOutcome
from .pose_memory import PoseMemory, within
from .settings import GENERATE, EnvSettings

PICK_SCORE = "pick_success"  # the score the final pick's hypothesis is chosen by (blocks/pick_success.py)


def normalise_score(value: float, score_range: tuple[float, float] | None) -> float:
    """A score mapped to [0, 1]: (x - low) / (high - low) clipped, or 0.5 + 0.5 x / (1 + |x|)
    without a range; 0 for NaN (a missing score has its own flag)."""
    if not math.isfinite(value):
        return 0.0
    if score_range is not None:
        low, high = score_range
        return float(np.clip((value - low) / (high - low), 0.0, 1.0))
    return float(0.5 + 0.5 * value / (1.0 + abs(value)))


class PerceptionConfigEnv(gym.Env):
    """The configuration task as a Gymnasium environment (spaces and reward: module docstring).

    `dataset`: a BOP dataset folder or `BopDataset` (episodes from its `image_keys`), an
    `EpisodeSource`, or None when every reset brings its own `Episode` (the configurator).
    `operators`: the backend that runs the blocks (default: in-process; the configurator passes
    the ROS one). `settings` and keyword overrides: see `EnvSettings`. `use_depth=False` reads
    a dataset folder as RGB-only (`BopDataset(use_depth=False)`: the depth actions are masked).
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        dataset: str | Path | BopDataset | EpisodeSource | None,
        pipeline: str | Path | Pipeline | None = None,
        settings: EnvSettings | None = None,
        *,
        split: str = "test",
        image_keys: list[tuple[int, int]] | None = None,
        operators: Operators | None = None,
        use_depth: bool = True,
        **overrides: Any,
    ) -> None:
        super().__init__()
        self.settings = (settings or EnvSettings()).replace(**overrides)
        self.source: EpisodeSource | None
        if dataset is None:  # episodes come with reset(options={"episode": Episode(...)})
            self.source = None
        elif isinstance(dataset, EpisodeSource):
            self.source = dataset
        else:
            ds = dataset if isinstance(dataset, BopDataset) else BopDataset(Path(dataset), split=split,
                                                                                 use_depth=use_depth)
            self.source = EpisodeSource(ds, image_keys, min_visib_fract=self.settings.min_visib_fract)
        self.pipeline = pipeline if isinstance(pipeline, Pipeline) else load_pipeline(pipeline)
        # Cost-table mode lifts the blocks' wall-clock bounds: a bound that cuts a block short on a
        # loaded machine would make the episode depend on timing (measured mode keeps them).
        self.ops: Operators = operators if operators is not None else InProcessOperators(
            self.pipeline, time_bounded=self.settings.time_mode == "measured")
        self._reproducible = self.settings.time_mode == "cost_table"  # see the module docstring: Time
        self._scoring_cost = self.settings.scoring_cost(self.pipeline.scoring)
        # the cost-table name of each action's block (the generator's first call: "generate")
        self._action_of = {id(a.block): a.name for a in self.pipeline.actions}
        self._action_of.setdefault(id(self.pipeline.generator), GENERATE)
        self.score_ranges = self.pipeline.score_ranges

        self.action_names = self.pipeline.action_names
        self.score_names = self.pipeline.score_names
        n_act, n_sc = len(self.action_names), len(self.score_names)
        self.observation_layout = (
            [f"score:{s}" for s in self.score_names] + [f"missing:{s}" for s in self.score_names]
            + ["progress:step"] + [f"last_action:{a}" for a in self.action_names]
            + ["progress:dt", "progress:drot", "progress:pick_failed", "progress:last_failed"]
        )
        self._candidate_features = any(a.block.takes_candidate for a in self.pipeline.actions)
        if self._candidate_features:
            self.observation_layout += ["candidates:left", "candidates:next_confidence"]
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
        self._mask = np.ones(len(self.action_names), np.int8)
        self._failed_pick_pose = None  # the hypothesis a pick failed on (pick masked while it stays)
        self._searched: set[int] = set()  # deterministic generator actions already called this episode
        self._picked_without_pose = False  # a pick was refused for want of a hypothesis
        self._memory: PoseMemory | None = None  # hypotheses reached, actions taken at each (loop rule)
        self._best: tuple[float, Any] | None = None  # (pick score, ops.hypothesis()) of the best reached

    def _frame_changed(self) -> None:
        """The action mask and the cost-table scoring pass of the episode's frame (RGB-only or not:
        `Episode.depth_known_absent`, the rule of `blocks.base.frame_lacks`)."""
        rgb_only = self.episode is not None and self.episode.depth_known_absent

        def lacks(block: Any) -> bool:
            return rgb_only and DEPTH in block.inputs

        self._mask = np.array([0 if lacks(a.block) else 1 for a in self.pipeline.actions], np.int8)
        runnable = [b for b in self.pipeline.scoring if not lacks(b)]
        self._scoring_cost = self.settings.scoring_cost(runnable, self._obj_id())

    def frame_mask(self) -> np.ndarray:
        """1 per action whose block can run on the current episode's frame, 0 where it needs an
        input the frame lacks (depth on an RGB-only frame); np.int8 of n actions."""
        return self._mask.copy()

    def action_mask(self) -> np.ndarray:
        """The frame's mask (frame_mask); while the hypothesis is one a pick failed on, 0 for the
        pick actions; 0 for a deterministic generator already called this episode (`repeats_search`:
        the same search, the same answer); while there is no hypothesis, 0 for the refiners
        (`refines_nothing`) and, once a pick was refused for want of one, for the picks too (giving
        up once is the pick's use there: looped to max_ops it was a cell agent's way to waste the
        candidates a refused generator call left); with `settings.final_pick`, 0 for every action
        but the picks at the last operation; with `settings.loop_mask`, 0 for the actions other
        than picks already taken at the current hypothesis (rl/pose_memory.py: they would go round
        in a loop); each unless nothing else could run. np.int8 of n actions."""
        return self._masks()[0]

    def loop_mask(self) -> np.ndarray:
        """1 for the actions that `action_mask` masks only by the loop rule (taken at this
        hypothesis before), np.int8 of n actions: an agent that plays a fixed plan (agents/fixed.py)
        may still play them."""
        return self._masks()[1]

    def _masks(self) -> tuple[np.ndarray, np.ndarray]:
        mask = self._mask.copy()
        pose = self.last_outcome.pose if self.last_outcome is not None else None

        def drop(ids: list[int]) -> None:  # unless nothing else could run
            if ids and mask.sum() > sum(int(mask[i]) for i in ids):
                mask[ids] = 0

        if pose is None:
            drop([i for i, a in enumerate(self.pipeline.actions) if refines_nothing(a.block)
                  or (self._picked_without_pose and a.block.kind == Kind.PICK)])
        if self._failed_pick_pose is not None and pose is not None and _same_pose(pose, self._failed_pick_pose):
            drop([i for i, a in enumerate(self.pipeline.actions) if a.block.kind == Kind.PICK])
        drop(sorted(self._searched))
        if self.settings.final_pick and self.steps == self.max_ops - 1:
            drop([i for i, a in enumerate(self.pipeline.actions) if a.block.kind != Kind.PICK])
        before_loop = mask.copy()
        if self.settings.loop_mask and self._memory is not None:
            looped = self._memory.stale(pose) | self._memory.converged(pose, self.settings.converge_tol)
            drop(sorted(i for i in looped if self.pipeline.actions[i].block.kind != Kind.PICK))
        return mask, (before_loop - mask).astype(np.int8)

    # -- the final pick's hypothesis ------------------------------------------------------
    def _note_best(self, outcome: StepOutcome) -> None:
        """Remember the hypothesis of the highest pick score reached (the final-pick rule; only
        with `final_pick_best`: nothing is copied on every step otherwise)."""
        if not (self.settings.final_pick and self.settings.final_pick_best):
            return
        score = outcome.scores.get(PICK_SCORE)
        if outcome.pose is None or score is None or not math.isfinite(score):
            return
        if self._best is None or score > self._best[0]:
            self._best = (float(score), self.ops.hypothesis())

    def _final_pick_at_best(self, block: Any) -> bool:
        """Before a pick at the last operation: make the best hypothesis reached the current one
        when it scores higher (module docstring: the final-pick rule); whether it did."""
        if not (self.settings.final_pick and self.settings.final_pick_best and block.kind == Kind.PICK
                and self.steps == self.max_ops - 1 and self._best is not None):
            return False
        current = self.last_outcome.scores.get(PICK_SCORE) if self.last_outcome is not None else None
        if current is not None and math.isfinite(current) and current >= self._best[0]:
            return False
        self.ops.set_hypothesis(self._best[1])
        return True

    # -- hindsight search -----------------------------------------------------------------
    _EPISODE_STATE = ("steps", "last_action", "last_outcome", "pose_change", "pick_failed", "last_failed",
                      "episode", "episode_time", "_mask", "_failed_pick_pose", "_searched", "_picked_without_pose",
                      "_memory", "_scoring_cost", "_best")

    def snapshot(self) -> Any:
        """An opaque copy of the episode's whole state (the env's and its operators'): `restore`
        returns to it, so a search can try actions from one state (agents/best_static.py)."""
        state = {k: getattr(self, k) for k in self._EPISODE_STATE}
        state["_searched"] = set(self._searched)
        state["_memory"] = self._memory.copy() if self._memory is not None else None
        return state, self.ops.snapshot()

    def restore(self, snapshot: Any) -> None:
        """Return to a state from `snapshot` (the same snapshot can be restored many times)."""
        state, ops_state = snapshot
        for k, v in state.items():
            setattr(self, k, v)
        self._searched = set(state["_searched"])
        self._memory = state["_memory"].copy() if state["_memory"] is not None else None
        self.ops.restore(ops_state)

    @property
    def max_ops(self) -> int:
        return self.settings.max_ops

    def _obj_id(self) -> int | None:
        return int(self.episode.model.obj_id) if self.episode is not None else None

    def cost_table_seconds(self, block: Any) -> float:
        """Seconds cost-table mode charges for an action with `block` (one of the pipeline's, or
        its generator) on the episode's object: the block plus the scoring pass (rl/settings.py)."""
        return self.settings.block_cost(block, self._action_of.get(id(block)), self._obj_id()) + self._scoring_cost

    def action_seconds(self, outcome: StepOutcome, block: Any) -> float:
        """Seconds an action with `block` is charged (before a failed pick's robot time)."""
        if self.settings.time_mode == "measured":
            return float(outcome.elapsed)
        return self.cost_table_seconds(block)

    def _obs(self) -> np.ndarray:
        scores = self.last_outcome.scores if self.last_outcome else {}
        vals = [scores.get(s, math.nan) for s in self.score_names]
        one_hot = np.zeros(len(self.action_names), np.float32)
        if self.last_action is not None:
            one_hot[self.last_action] = 1.0
        obs = np.concatenate([
            [normalise_score(v, self.score_ranges.get(s)) for s, v in zip(self.score_names, vals)],
            [0.0 if math.isfinite(v) else 1.0 for v in vals],
            [min(1.0, self.steps / self.max_ops)],
            one_hot,
            [min(1.0, self.pose_change[0]), min(1.0, self.pose_change[1] / math.pi),
             float(self.pick_failed), float(self.last_failed)],
        ]).astype(np.float32)
        if self._candidate_features:
            left = self.ops.candidates
            next_conf = float(np.clip(left[0][0], 0.0, 1.0)) if left else 0.0
            obs = np.concatenate([obs, np.array([min(1.0, len(left) / 5.0), next_conf], np.float32)])
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
        info["action_mask"], info["loop_mask"] = self._masks()
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
            lam = float(self.np_random.uniform(*self.settings.lambda_range))
        lam = check_noise_lambda(lam)
        self._reset_state()
        if given is not None:
            self.episode = given
        else:
            ep_seed = int(options.get("episode_seed", self.np_random.integers(2**31)))
            self.episode = self.source.load(int(index), lam, ep_seed)
        self._frame_changed()
        with open3d_single_thread(self._reproducible):
            outcome = self.ops.start(self.episode)
        self.last_outcome = outcome
        self._note_best(outcome)
        self._memory = PoseMemory(self.episode.model.diameter)
        self._memory.visit(outcome.pose)
        seconds = self.action_seconds(outcome, self.pipeline.generator)
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
        picked_best = self._final_pick_at_best(block)
        with open3d_single_thread(self._reproducible):
            outcome = self.ops.apply(name)
        seconds = self.action_seconds(outcome, block)
        reward = -seconds
        terminated = False
        if repeats_search(block):
            self._searched.add(a)
        if block.kind == Kind.PICK and before is None and outcome.pose is None:
            self._picked_without_pose = True
        if block.kind == Kind.PICK and outcome.result.ok:
            if outcome.result.picked:
                terminated = True
            else:
                self.pick_failed = True
                self._failed_pick_pose = outcome.pose if outcome.pose is not None else before
                if self._best is not None and self._failed_pick_pose is not None \
                        and _same_pose(self._best[1][0], self._failed_pick_pose):
                    self._best = None  # a pose a pick failed on is no answer
                reward -= self.settings.failed_pick_cost
                seconds += self.settings.failed_pick_cost
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
        if block.kind != Kind.PICK:
            self._note_best(outcome)
        if self._memory is not None:
            self._memory.record(before, a, after)
        truncated = not terminated and self.steps >= self.max_ops
        if truncated:
            reward -= self.settings.truncation_cost
        info = self._info(outcome, seconds)
        info["truncation_cost"] = self.settings.truncation_cost if truncated else 0.0
        info["picked_best"] = picked_best
        return self._obs(), float(reward), terminated, truncated, info


def repeats_search(block: Any) -> bool:
    """Whether a second call of this generator in an episode repeats the first: it searches the
    frame for the model without a seed or the current pose (ppf, resting_pose), so it answers
    the same poses again (a trained agent had learned to call ppf until max_ops after a failed
    pick). Its candidates stay reachable by next_candidate."""
    return (block.kind == Kind.GENERATION and not block.uses_rng and POSE not in block.inputs
            and not block.takes_candidate)


def refines_nothing(block: Any) -> bool:
    """Whether the block can only fail while there is no hypothesis: it needs the pose and is
    no pick (a pick without a pose fails in milliseconds, the cheapest way to give up on a part
    no generator finds, so it stays). After a refused generator call, trained agents looped an
    ICP that failed at once until max_ops (6 of a cell agent's 8 failures on the 68 test
    episodes) instead of taking the candidates the call left waiting."""
    return POSE in block.inputs and block.kind != Kind.PICK


def _same_pose(a: Any, b: Any, metres: float = 1e-4, radians: float = 1e-4) -> bool:
    """The same hypothesis to a robot: within 0.1 mm and 0.006 deg (an ICP that re-converges
    where it was moves it by less)."""
    return within(a, b, metres, radians)


def register() -> None:
    """Register `PerceptionConfig-v0` with Gymnasium (idempotent)."""
    if "PerceptionConfig-v0" not in gym.registry:
        gym.register(id="PerceptionConfig-v0", entry_point="perception_config.rl.env:PerceptionConfigEnv")


register()
