"""The threshold rule: pick as soon as a score clears a threshold, else refine along a loop.

The closed-loop pipeline an engineer with a calibrated score would write, and the simplest
dynamic policy: it reads one entry of the observation and nothing else.

    at every step:  score(hypothesis) >= threshold and a pick can run   ->  pick
                    otherwise                                           ->  the next action of
                                                                            `loop` that can run

| hyper-parameter | meaning                                                                      |
|-----------------|------------------------------------------------------------------------------|
| `score`         | the scoring block read, its `score:<name>` observation entry (in [0, 1]);    |
|                 | `pick_success` (the default where the pipeline scores it, else its first     |
|                 | score) is the calibrated probability that a pick succeeds                    |
| `threshold`     | pick at or above it (a missing score is 0: never picks on it)                |
| `loop`          | the actions played, in turn and over again, while the score is below it      |

The loop is played in order and cycled. An action the mask forbids (`info["action_mask"]`: a frame
without depth, the env's loop rule: the action was taken at this very hypothesis) is skipped
where it comes. When no loop action can run, the rule picks; when the pick cannot run either
(it just failed on this hypothesis), it takes the pipeline's first action that can. The env's
final-pick rule makes the last of `max_ops` operations a pick whatever the rule says.

The warm start's `threshold` teacher (learning/warm_start.py) searches the rules of THRESHOLDS x
every loop of 1..MAX_LOOP non-pick actions (`threshold_rules`; x every score where the pipeline has
no pick-success score) on train episodes, with the same
prefix-shared search as best_static (agents/best_static.py: `search_players`), and teaches the
cheapest.
"""
from __future__ import annotations

import itertools
from typing import Any, Sequence

import numpy as np

from ..rl.trajectory import allowed_actions
from .base import Agent, EnvSpec
from .hparams import SEED, Float, Name, StrList

THRESHOLDS = (0.5, 0.7, 0.8, 0.9, 0.95)  # the search's grid (calibrated probabilities)
MAX_LOOP = 2  # loops of 1..MAX_LOOP actions are searched
DEFAULT_SCORE = "pick_success"


class ThresholdAgent(Agent):
    """Pick once `score` >= `threshold`, else the next action of `loop` (module docstring)."""

    kind = "threshold"
    HPARAM_BOUNDS = {"score": Name(), "threshold": Float(0.0, 1.0), "loop": StrList(64), "seed": SEED}

    def __init__(self, spec: EnvSpec, score: str | None = None, threshold: float = 0.8,
                 loop: Sequence[str] | None = None, seed: int = 0) -> None:
        super().__init__(spec, seed)
        score = scored_by(spec, score)
        key = f"score:{score}"
        if not spec.pick_actions:
            raise ValueError("threshold rule: the pipeline has no pick action")
        if not 0.0 <= float(threshold) <= 1.0:
            raise ValueError(f"threshold rule: threshold must be in [0, 1], got {threshold!r}")
        names = list(spec.action_names)
        loop = [n for n, k in zip(names, spec.action_kinds) if k != "pick"][:1] if loop is None else list(loop)
        unknown = [a for a in loop if a not in names]
        picks = [a for a in loop if a in names and names.index(a) in spec.pick_actions]
        if not loop or unknown or picks:
            raise ValueError(f"threshold rule: the loop needs 1 or more of the pipeline's non-pick actions "
                             f"{[n for n, k in zip(names, spec.action_kinds) if k != 'pick']}, got {loop}")
        self.score, self.threshold, self.loop = score, float(threshold), [str(a) for a in loop]
        self._score_index = spec.observation_layout.index(key)
        self._missing_index = spec.observation_layout.index(f"missing:{score}")
        self._loop_ids = [names.index(a) for a in self.loop]
        self._pick = spec.pick_actions[0]
        self._t = 0  # the loop's position: the next loop action to try

    def begin_episode(self, seed: int | None = None) -> None:
        super().begin_episode(seed)
        self._t = 0

    def act(self, obs: np.ndarray, info: dict[str, Any]) -> int:
        if isinstance(info, dict) and info.get("steps", None) == 0:
            self._t = 0
        allowed = allowed_actions(info, self.spec.n_actions)
        ok = (lambda a: True) if allowed is None else (lambda a: bool(allowed[a]))
        obs = np.asarray(obs).reshape(-1)
        value = 0.0 if obs[self._missing_index] > 0.5 else float(obs[self._score_index])
        if value >= self.threshold and ok(self._pick):
            return self._pick
        n = len(self._loop_ids)
        for k in range(self._t, self._t + n):
            a = self._loop_ids[k % n]
            if ok(a):
                self._t = (k + 1) % n
                return a
        if ok(self._pick):
            return self._pick
        return next((a for a in range(self.spec.n_actions) if ok(a)), self._pick)

    def hparams(self) -> dict[str, Any]:
        return {"score": self.score, "threshold": self.threshold, "loop": list(self.loop), "seed": self.seed}

    def describe(self) -> str:
        return f"pick at {self.score} >= {self.threshold:g}, else {' > '.join(self.loop)}"


def threshold_rules(spec: EnvSpec, thresholds: Sequence[float] = THRESHOLDS,
                    max_loop: int = MAX_LOOP) -> list[ThresholdAgent]:
    """Every rule of the search (module docstring): thresholds x loops of 1..max_loop non-pick
    actions (shortest loops first, in the pipeline's order), on each of `searched_scores`."""
    refiners = [n for n, k in zip(spec.action_names, spec.action_kinds) if k != "pick"]
    loops = [loop for length in range(1, int(max_loop) + 1) for loop in itertools.product(refiners, repeat=length)
             if not _repeats_shorter(loop)]
    return [ThresholdAgent(spec, score, float(t), list(loop)) for score in searched_scores(spec) for loop in loops
            for t in thresholds]


def scored_by(spec: EnvSpec, score: str | None = None) -> str:
    """The score a rule reads: `score`, checked against the pipeline's; None: the pick-success
    score where the pipeline has it, else its first score."""
    scores = _scores(spec)
    if score is None:
        score = DEFAULT_SCORE if DEFAULT_SCORE in scores or not scores else scores[0]
    if f"score:{score}" not in spec.observation_layout:
        raise ValueError(f"threshold rule: the pipeline scores no {score!r}; its scores are {scores}")
    return str(score)


def searched_scores(spec: EnvSpec) -> list[str]:
    """The scores a search tries: the pick-success score where the pipeline has it, else each of
    its scores in turn (uncalibrated, in [0, 1]: which one tells a pickable pose best is what the
    search finds out)."""
    scores = _scores(spec)
    return [scored_by(spec)] if DEFAULT_SCORE in scores or not scores else scores


def _scores(spec: EnvSpec) -> list[str]:
    """The scoring blocks of the observation, in its order."""
    return [n.split(":", 1)[1] for n in spec.observation_layout if n.startswith("score:")]


def _repeats_shorter(loop: tuple[str, ...]) -> bool:
    """Whether the loop is a shorter loop played over again ((a, a) is (a); (a, b, a, b) is (a, b))."""
    n = len(loop)
    return any(n % k == 0 and loop == loop[:k] * (n // k) for k in range(1, n))
