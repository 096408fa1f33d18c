"""Warm start: before reinforcement learning, the policy imitates a teacher on train episodes.

A policy-gradient agent that starts from random weights has to find out by trial which of the
pipeline's actions pay: seeds that never tried `regenerate` often enough never learn it, and
the trained agents of one recipe then differ more from each other than from the baselines
(docs/results/configurator.md). A warm start gives every seed the same good beginning, and
reinforcement learning goes on from there to what no teacher here shows: when to deviate.

The teachers come from one exhaustive, prefix-shared search (agents/best_static.py:
`search_players`, in the env's own time) on the agent's `warm_start_episodes` TRAIN episodes,
lambda drawn from the settings' lambda_range: of the static sequences of 1..MAX_LENGTH actions,
or of the threshold rules (agents/threshold.py: pick once the pick-success score clears a
threshold, else refine along a loop; every threshold of THRESHOLDS x every loop of 1..2 actions):

| teacher       | plays on an episode                                  | knows the outcome | reads the scores |
|---------------|------------------------------------------------------|-------------------|------------------|
| `best_static` | the sequence with the lowest mean cost over them all | no                | no               |
| `hindsight`   | the cheapest sequence on this episode, if it picks   | yes (hindsight)   | no               |
| `threshold`   | the rule with the lowest mean cost over them all     | no                | one score        |

The hindsight teacher's episodes where no sequence succeeds are left out (nothing to imitate).
The chosen sequence is played again as `FixedAgent(sequence, after="repeat")` (the rule as its
ThresholdAgent) on the same episode options and acting seed (the search's costs are those of
this play, bit for bit in cost-table mode), and its trajectories are the demonstrations
`PolicyGradientAgent.imitate` fits. The static sequences cannot stop early on a hypothesis that is
already right; the threshold rule can, which is most of what separates the oracle's time from
theirs. The hindsight choices depend on what the policy cannot see (the ground truth): imitated,
they become the probability, given the scores, that an action is the right one, which the
reward then sharpens.

The demonstrations are drawn from their own seeded stream (the training seed's), so the training
episodes that follow are those of a run without a warm start.
"""
from __future__ import annotations

import time
from typing import Any, Sequence

import numpy as np

from ..agents.base import Agent
from ..agents.best_static import rank, static_sequences
from ..agents.fixed import FixedAgent
from ..agents.threshold import threshold_rules
from ..rl.episode_loop import acting_seed, play_episode
from ..rl.trajectory import Trajectory
from .evaluation_best_static import search_bar, search_chunk, search_rows, search_rules_chunk
from .ray_workers import RayRunner, chunks, play_chunk, snapshot

TEACHERS = ("best_static", "hindsight", "threshold")
MAX_LENGTH = 3  # sequences searched, as the evaluation's best_static (evaluation_best_static.py)


def demonstration_plan(train_idx: Sequence[int], n: int, lambda_range: tuple[float, float],
                       seed: int) -> list[tuple[dict[str, Any], int]]:
    """`n` (reset options, acting seed) pairs over the train episode indices, from a stream of
    its own (derived from the training seed)."""
    rng = np.random.default_rng([int(seed), 11])
    lo, hi = lambda_range
    plan = []
    for _ in range(int(n)):
        s = int(rng.integers(2**31))
        plan.append(({"episode": int(train_idx[int(rng.integers(len(train_idx)))]),
                      "lambda": float(rng.uniform(lo, hi)), "episode_seed": s}, acting_seed(s)))
    return plan


def teacher_sequences(sequences: Sequence[Sequence[str]], costs: np.ndarray, teacher: str,
                      success_cost: float) -> list[tuple[str, ...] | None]:
    """Per episode (a row of `costs`), the sequence the teacher plays, None where it shows
    nothing. `success_cost`: the highest cost of a successful play (a cost above it failed: the
    truncation charge; the caller takes it from the settings)."""
    if teacher == "best_static":
        best = tuple(sequences[rank(sequences, costs)[0]])
        return [best] * len(costs)
    if teacher != "hindsight":
        raise ValueError(f"unknown teacher {teacher!r}; teachers: {', '.join(TEACHERS)}")
    out: list[tuple[str, ...] | None] = []
    for row in costs:
        j = rank(sequences, row[None, :])[0]
        out.append(tuple(sequences[j]) if row[j] <= success_cost else None)
    return out


def _play(env: Any, chosen: Sequence[Agent | None],
          plan: Sequence[tuple[dict[str, Any], int]], runner: RayRunner | None, recipe_ref: Any) -> list[Trajectory]:
    """Each plan episode played by its chosen teacher (None: not played), in plan order."""
    by_agent: dict[int, list[int]] = {}
    agents: dict[int, Agent] = {}
    for k, agent in enumerate(chosen):
        if agent is not None:
            by_agent.setdefault(id(agent), []).append(k)
            agents[id(agent)] = agent
    out: dict[int, Trajectory] = {}
    if runner is None:
        for key, ks in by_agent.items():
            for k in ks:
                out[k] = play_episode(env, agents[key], plan[k][0], plan[k][1])
    else:
        calls, owners = [], []
        for key, ks in by_agent.items():
            snap = runner.put(snapshot(agents[key]))
            for lo, hi in chunks(len(ks), len(by_agent), runner.cpus):
                calls.append((recipe_ref, snap, [plan[k] for k in ks[lo:hi]]))
                owners.append(ks[lo:hi])
        for ks, trajs in zip(owners, runner.map(play_chunk, calls)):
            out.update(zip(ks, trajs))
    return [out[k] for k in sorted(out)]


def warm_start(learner: Agent, env: Any, train_idx: Sequence[int], settings: Any, seed: int, *,
               runner: RayRunner | None = None, recipe_ref: Any = None, progress: bool = True) -> dict[str, Any]:
    """Search, replay the teacher's choices and let `learner` imitate them (module docstring).
    `learner`: a PolicyGradientAgent with `warm_start` set; `env`: the training env (in-process,
    or with `runner` and the Ray reference of its recipe, its workers). Returns the report kept
    in the policy's metadata: teacher, episodes searched and demonstrated, the sequences taught
    (with how often), the imitation's figures and the seconds it took."""
    teacher = str(getattr(learner, "warm_start", "none"))
    if teacher not in TEACHERS:
        raise ValueError(f"warm_start must be one of {', '.join(TEACHERS)}, got {teacher!r}")
    started = time.perf_counter()
    spec = learner.spec
    plan = demonstration_plan(train_idx, int(learner.warm_start_episodes), settings.lambda_range, seed)
    if teacher == "threshold":
        rules = threshold_rules(spec)
        local, remote, task = rules, [(r.kind, r.hparams()) for r in rules], search_rules_chunk
    else:
        sequences = static_sequences(spec.action_names, spec.action_kinds, MAX_LENGTH)
        local = [FixedAgent(spec, list(seq), after="repeat") for seq in sequences]
        remote, task = sequences, search_chunk
    with search_bar(len(plan), f"warm start: {teacher} search", progress) as bar:
        costs = search_rows(env, local, plan, runner=runner, recipe_ref=recipe_ref, task=task, remote=remote,
                            bar=bar)[0]
    taught: dict[str, int] = {}
    if teacher == "threshold":
        mean = costs.sum(axis=0) / len(costs)
        best = rules[int(np.argmin(np.round(mean / 1e-9)))]  # ties: the first (shortest loop, lowest threshold)
        chosen: list[Agent | None] = [best] * len(plan)
        taught[best.describe()] = len(plan)
        extra: dict[str, Any] = {"rules": len(rules), "rule": best.hparams(), "rule_cost": float(mean.min())}
    else:
        # A successful play costs less than a truncation charge; no time budget reaches it (max_ops
        # operations of seconds each, far below the default 10 s, are what the search plays).
        seqs = teacher_sequences(sequences, costs, teacher, float(settings.truncation_cost))
        chosen = [local[sequences.index(seq)] if seq is not None else None for seq in seqs]
        for seq in seqs:
            if seq is not None:
                taught[" ".join(seq)] = taught.get(" ".join(seq), 0) + 1
        extra = {"max_length": MAX_LENGTH}
    demos = _play(env, chosen, plan, runner, recipe_ref)
    if teacher == "hindsight":
        demos = [t for t in demos if t.success]
    if not demos:
        raise ValueError(f"warm start: the {teacher} teacher succeeded on none of the {len(plan)} train episodes "
                         "searched; raise warm_start_episodes or train without a warm start")
    figures = learner.imitate(demos)
    return {"teacher": teacher, "episodes_searched": len(plan), "episodes_demonstrated": len(demos),
            "demonstration_success": float(np.mean([t.success for t in demos])),
            "sequences_taught": dict(sorted(taught.items(), key=lambda kv: (-kv[1], kv[0]))),
            **extra, **figures, "seconds": round(time.perf_counter() - started, 3)}

