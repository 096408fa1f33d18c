"""Validation-based policy selection: which of a training run's policies to ship.

Why: a policy-gradient learner samples its way through a noisy trajectory of policies; the
last one is a random draw from the neighbourhood training ends in, and a single unlucky update
can leave it picking too early on one part. The greedy policy is scored every few hundred
episodes on images it never trains on, and the run ships the best one. The test images stay
untouched: selecting on them would make the evaluation optimistic.

- Images: the train image ids (after the train/test split) are split again,
  `split_image_keys(train ids, fraction, split_seed)`: the validation ids are held out of
  training (no training episode is drawn from them), disjoint from the test ids.
- Episodes: every usable object of the validation images at each validation lambda (default:
  both ends of the training lambda_range and 0.5, or its midpoint when 0.5 is outside), at
  most MAX_EPISODES (a seeded subset beyond), with fixed episode seeds derived from the split
  seed: every validation of a run plays the very same episodes, so the figures compare.
- Policy: a greedy copy of the learner (explore=False, as evaluation runs a policy), acting
  seeds as evaluation's (`acting_seed(episode_seed)`); the learner itself is not touched.
- Selection: the lowest mean cost (seconds charged + truncation penalty, the negative return
  the agents maximise); a tie goes to the later, longer-trained policy.
"""
from __future__ import annotations

import csv
import io
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from ..agents import Agent, EnvSpec
from ..rl.episode_loop import Trajectory, acting_seed
from ..rl.episodes import ImageKey, split_image_keys
from ..rl.settings import EnvSettings
from ..util.atomic_file import atomic_write
from .ray_workers import rebuild, snapshot

MAX_EPISODES = 300  # validation episodes per check (a seeded subset beyond): keeps a check cheap
TENSOR_PREFIX = "validation/best/"  # the selected policy's weights inside a checkpoint
SELECTION = "lowest mean validation cost (greedy policy)"


def split_validation(train_keys: Sequence[ImageKey], fraction: float, seed: int) -> tuple[list[ImageKey],
                                                                                            list[ImageKey]]:
    """(fit, validation) image keys: a seeded split of the train ids; needs at least 2 of them."""
    if len(set(train_keys)) < 2:
        raise ValueError(f"validation needs at least 2 train images to hold some out, the split has {len(train_keys)}")
    try:
        return split_image_keys(list(train_keys), fraction, seed)
    except ValueError as exc:
        raise ValueError(f"validation fraction: {exc}".replace("test_fraction", "validation_fraction")) from None


def default_lambdas(settings: EnvSettings) -> tuple[float, ...]:
    """Both ends of the training lambda_range and 0.5 (its midpoint when 0.5 is outside it)."""
    lo, hi = settings.lambda_range
    mid = 0.5 if lo <= 0.5 <= hi else (lo + hi) / 2
    return tuple(sorted({float(lo), float(mid), float(hi)}))


def validation_episodes(indices: Sequence[int], lambdas: Sequence[float], seed: int) -> list[dict[str, Any]]:
    """The fixed reset options of a run's validation: every episode index at every lambda."""
    rng = np.random.default_rng([int(seed), 0x7A11D])  # the split seed's own stream for validation
    options = [{"episode": int(i), "lambda": float(lam), "episode_seed": int(rng.integers(2**31))}
               for i in indices for lam in lambdas]
    if len(options) > MAX_EPISODES:
        keep = np.sort(rng.choice(len(options), MAX_EPISODES, replace=False))
        options = [options[k] for k in keep]
    return options


def summarise(trajectories: Sequence[Trajectory], episodes_done: int) -> dict[str, Any]:
    """Mean cost, success, first-pick share and mean time to success, overall and per lambda."""
    def stats(ts: Sequence[Trajectory]) -> dict[str, Any]:
        ok = [t.time for t in ts if t.success]
        return {"cost": float(np.mean([t.cost for t in ts])), "success": float(np.mean([t.success for t in ts])),
                "first_pick": float(np.mean([t.first_pick_success for t in ts])),
                "time_to_success": float(np.mean(ok)) if ok else None, "episodes": len(ts)}

    out = {"episode": int(episodes_done), **stats(trajectories)}
    lambdas = sorted({round(t.noise_lambda, 6) for t in trajectories})
    out["per_lambda"] = {f"{lam:g}": stats([t for t in trajectories if round(t.noise_lambda, 6) == lam])
                         for lam in lambdas}
    return out


@dataclass
class Selection:
    """The validation history of a run and the best policy so far (a snapshot of its weights)."""

    history: list[dict[str, Any]] = field(default_factory=list)
    best: dict[str, Any] | None = None  # the history entry of the selected policy
    best_tensors: dict[str, np.ndarray] = field(default_factory=dict)
    best_state: dict[str, Any] = field(default_factory=dict)

    @property
    def last_episode(self) -> int:
        return int(self.history[-1]["episode"]) if self.history else -1

    def offer(self, record: dict[str, Any], agent: Agent) -> bool:
        """Record a validation; keep `agent`'s policy if it is the best so far (ties: the later)."""
        self.history.append(record)
        if self.best is None or record["cost"] <= self.best["cost"]:
            self.best = record
            self.best_tensors = {k: np.array(v, copy=True) for k, v in agent.tensors().items()}
            self.best_state = agent.state()
            return True
        return False

    def best_agent(self, spec: EnvSpec, like: Agent) -> Agent:
        """The selected policy as an agent of `like`'s kind and hyper-parameters."""
        return rebuild((like.kind, like.hparams(), self.best_tensors, self.best_state, False), spec)

    # -- checkpoints ------------------------------------------------------------------------
    def to_checkpoint(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        tensors = {TENSOR_PREFIX + k: v for k, v in self.best_tensors.items()}
        return tensors, {"history": self.history, "best": self.best, "best_state": self.best_state}

    @classmethod
    def from_checkpoint(cls, tensors: dict[str, np.ndarray], meta: dict[str, Any] | None) -> "Selection":
        meta = meta or {}
        best_tensors = {k[len(TENSOR_PREFIX):]: np.array(v) for k, v in tensors.items() if k.startswith(TENSOR_PREFIX)}
        return cls(list(meta.get("history", [])), meta.get("best"), best_tensors, dict(meta.get("best_state") or {}))


def validate(learner: Agent, options: list[dict[str, Any]], play: Callable[[Agent, list[dict[str, Any]], np.ndarray],
             list[Trajectory]], episodes_done: int) -> dict[str, Any]:
    """Play the validation episodes with a greedy copy of `learner` (`play(agent, options,
    act_seeds)` plays them, in this process or the workers) and summarise them."""
    kind, hparams, tensors, state, _ = snapshot(learner)
    greedy = rebuild((kind, hparams, tensors, state, False), learner.spec)
    seeds = np.array([acting_seed(o["episode_seed"]) for o in options], np.int64)
    return summarise(play(greedy, options, seeds), episodes_done)


def write_csv(history: Sequence[dict[str, Any]], path: Any) -> None:
    """validation.csv: one row per check, the overall figures then the cost per lambda."""
    lambdas = sorted({lam for rec in history for lam in rec.get("per_lambda", {})}, key=float)
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["episode", "cost", "success", "first_pick", "time_to_success", *(f"cost_lambda_{x}" for x in lambdas)])
    for rec in history:
        tts = rec.get("time_to_success")
        w.writerow([rec["episode"], f"{rec['cost']:.6g}", f"{rec['success']:.6g}", f"{rec['first_pick']:.6g}",
                    "" if tts is None else f"{tts:.6g}",
                    *(f"{rec['per_lambda'][x]['cost']:.6g}" if x in rec.get("per_lambda", {}) else ""
                      for x in lambdas)])
    atomic_write(path, buf.getvalue())
