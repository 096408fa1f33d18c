"""The best static pipeline of an evaluation (agents/best_static.py): one exhaustive search per
evaluated lambda, on TRAIN episodes (an env over the split's train image keys: the search never
sees a test image), then a BestStaticAgent that plays, per lambda, the sequence found for it.

Two bars come out of the same searched costs:

| agent                | plays                                             | told the noise level |
|----------------------|---------------------------------------------------|----------------------|
| `best_static`        | per lambda, the lowest mean cost at that lambda   | yes                  |
| `best_static_single` | one sequence: the lowest mean cost over all the   | no                   |
|                      | lambdas' search episodes together                 |                      |

| `best_threshold`     | one threshold rule (agents/threshold.py): pick   | no (reads the        |
|                      | once the pick-success score clears a threshold,  | pick-success score)  |
|                      | else refine along a loop; the lowest mean cost   |                      |
|                      | on the search episodes, lambdas taken in turn    |                      |

`best_static_single` is Dynamic Algorithm Configuration's static reference (one configuration for
the whole instance distribution, what SMAC or irace return for a cell): the noise level of a
hypothesis is not observed by the learned agent, nor known in a cell. `best_static` selects a
sequence per noise level with that knowledge: on its train episodes no single sequence beats it,
but each lambda's choice rests on a third of the episodes, and on test episodes the single
sequence has measured the stronger (docs/results/configurator.md).

At every lambda the search plays the same train episodes (the plan's episode indices and seeds,
drawn from a seeded rng; common random numbers, as the evaluation's own plan) at that lambda.
In this process, or with Ray workers as tasks of a few episodes each (`search_chunk`: each
returns its episodes' cost rows; the rows are put together in episode order and summed on the
driver, so the choice is the same bits for 1 and N workers).
"""
from __future__ import annotations

import contextlib
import time
from typing import Any, Sequence

import numpy as np

from ..agents.base import EnvRecipe, EnvSpec
from ..agents.best_static import BestStaticAgent, SearchResult, search_costs, search_players, static_sequences
from ..agents.fixed import FixedAgent
from ..agents.registry import AGENTS
from ..agents.threshold import ThresholdAgent, threshold_rules
from ..rl.episode_loop import acting_seed
from .ray_workers import RayRunner, chunks, worker_env

# Defaults measured on data/default (docs/concepts/evaluation.md): sequences up to 3 actions, 24
# train episodes per lambda: a lambda's search in about a minute on 2 workers.
DEFAULT_MAX_LENGTH = 3
DEFAULT_EPISODES = 24


def check_options(max_length: int, episodes: int) -> None:
    """ValueError naming the option when the search's settings are out of range."""
    for name, value, low in (("best_static_length", max_length, 1), ("best_static_episodes", episodes, 0)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
            raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")


def search_seed(seed: int) -> int:
    """The seed of the search's episode plan, derived from the evaluation's seed (not its
    episode seeds: those are the test episodes')."""
    return int(np.random.SeedSequence([int(seed), 7]).generate_state(1)[0] % 2**31)


def search_chunk(recipe: EnvRecipe, sequences: Sequence[Sequence[str]],
                 episodes: Sequence[tuple[dict[str, Any], int]]) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """A Ray task: the cost rows of some search episodes in the worker's train env, and their
    images (agents/best_static.search_costs)."""
    env, _spec = worker_env(recipe)
    return search_costs(env, sequences, episodes)


def search_rules_chunk(recipe: EnvRecipe, rules: Sequence[tuple[str, dict[str, Any]]],
                       episodes: Sequence[tuple[dict[str, Any], int]]) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """A Ray task: the cost rows of some search episodes for deterministic rules given as (agent
    kind, hparams) (the threshold rules) in the worker's train env."""
    env, spec = worker_env(recipe)
    return search_players(env, [AGENTS[kind](spec, **hp) for kind, hp in rules], episodes)


def search_rows(env: Any, players: Sequence[Any], episodes: Sequence[tuple[dict[str, Any], int]], *,
                runner: RayRunner | None = None, recipe_ref: Any = None, task: Any = None, remote: Any = None,
                bar: Any = None) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """The (episodes, players) cost rows of a search and each episode's image: in this process
    (`players`: agents, agents/best_static.search_players), or with `runner` as Ray tasks
    `task(recipe, remote, chunk of episodes)` (`remote`: the players' picklable descriptions,
    `recipe_ref`: the train env's recipe put in Ray), rows put together in episode order.
    `bar`: a progress bar advanced per episode."""
    if runner is None:
        return search_players(env, players, episodes, bar.update if bar is not None else None)
    calls = [(recipe_ref, remote, episodes[lo:hi]) for lo, hi in chunks(len(episodes), 1, runner.cpus)]
    parts = runner.map(task, calls, (lambda _k, part: bar.update(len(part[1]))) if bar is not None else None)
    return np.concatenate([rows for rows, _ in parts]), [key for _, keys in parts for key in keys]


def search_bar(total: int, desc: str, progress: bool) -> Any:
    """The search's progress bar as a context (tqdm, closed on leaving); without `progress` a
    context that gives None."""
    if not progress:
        return contextlib.nullcontext(None)
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="ep", dynamic_ncols=True)


def threshold_episodes(lams: Sequence[float], plan: Sequence[tuple[int, int]]) -> list[tuple[dict[str, Any], int]]:
    """The best_threshold search's episodes: the plan's episodes twice (once with one lambda, so
    with two lambdas in all), the lambdas taken in turn: a rule for every lambda, searched on
    twice the episodes of one lambda's best_static search rather than all of them."""
    lams = [float(x) for x in lams]
    return [({"episode": int(i), "lambda": lams[(k + r) % len(lams)], "episode_seed": int(s)}, acting_seed(s))
            for r in range(min(2, len(lams))) for k, (i, s) in enumerate(plan)]


def best_threshold_agent(env: Any, lams: Sequence[float], plan: Sequence[tuple[int, int]], seed: int = 0,
                         runner: RayRunner | None = None, recipe: EnvRecipe | None = None,
                         progress: bool = True) -> ThresholdAgent:
    """`best_threshold` (module docstring): every rule of `threshold_rules` on the train episodes
    of `plan` (`threshold_episodes`: lambdas in turn); the agent of the lowest mean cost (ties:
    the first rule, shortest loop and lowest threshold first). Its `search` holds the figures."""
    spec = EnvSpec.from_env(env)
    rules = threshold_rules(spec)
    episodes = threshold_episodes(lams, plan)
    if not episodes:
        raise ValueError("the best_threshold search needs at least one train episode")
    started = time.perf_counter()
    with search_bar(len(episodes), f"best_threshold search ({len(rules)} rules)", progress) as bar:
        costs, keys = search_rows(env, rules, episodes, runner=runner, task=search_rules_chunk,
                                  recipe_ref=runner.put(recipe) if runner is not None else None,
                                  remote=[(r.kind, r.hparams()) for r in rules], bar=bar)
    mean = costs.sum(axis=0) / len(costs)
    order = sorted(range(len(rules)), key=lambda j: round(float(mean[j]) / 1e-9))  # stable: ties keep rule order
    best = rules[order[0]]
    agent = ThresholdAgent(spec, **{**best.hparams(), "seed": int(seed)})
    images = sorted({(int(a), int(b)) for a, b in keys})
    agent.search = {"rules": len(rules), "episodes": len(costs), "mean_cost": float(mean[order[0]]),
                    "runner_up": rules[order[1]].describe() if len(order) > 1 else None,
                    "runner_up_cost": float(mean[order[1]]) if len(order) > 1 else None,
                    "seconds": time.perf_counter() - started, "images": [list(k) for k in images]}
    return agent


def best_static_agent(env: Any, lams: Sequence[float], plan: Sequence[tuple[int, int]], max_length: int,
                      seed: int = 0, runner: RayRunner | None = None, recipe: EnvRecipe | None = None,
                      progress: bool = True) -> BestStaticAgent:
    """Search every lambda of `lams` on the train episodes of `plan` ((episode index, episode
    seed) of `env`'s source, an env over the TRAIN images) and return the agent that plays the
    sequences found; its `search` holds each lambda's SearchResult. With `runner` (and the
    `recipe` of the same train env) the episodes are played as Ray tasks."""
    spec = EnvSpec.from_env(env)
    sequences = static_sequences(spec.action_names, spec.action_kinds, max_length)
    if not plan:
        raise ValueError("the best_static search needs at least one train episode")
    players = [FixedAgent(spec, list(seq), after="repeat") for seq in sequences] if runner is None else []
    results: dict[float, SearchResult] = {}
    all_costs: list[np.ndarray] = []
    all_images: list[tuple[int, int]] = []
    started = time.perf_counter()
    recipe_ref = runner.put(recipe) if runner is not None else None
    with search_bar(len(lams) * len(plan), "best_static search", progress) as bar:
        for lam in lams:
            if bar is not None:
                bar.set_postfix_str(f"lambda={lam:g} {len(sequences)} sequences")
            episodes = [({"episode": int(i), "lambda": float(lam), "episode_seed": int(s)}, acting_seed(s))
                        for i, s in plan]
            t0 = time.perf_counter()
            costs, images = search_rows(env, players, episodes, runner=runner, recipe_ref=recipe_ref,
                                        task=search_chunk, remote=sequences, bar=bar)
            results[lam] = SearchResult.from_costs(sequences, costs, max_length, time.perf_counter() - t0, images)
            all_costs.append(costs)
            all_images.extend(images)
    agent = BestStaticAgent(spec, {lam: r.sequence for lam, r in results.items()}, seed=seed)
    agent.search = results
    # the same costs pooled over the lambdas (rows in lambda order): one sequence for all of them
    agent.single_search = SearchResult.from_costs(sequences, np.concatenate(all_costs), max_length,
                                                  time.perf_counter() - started, all_images)
    return agent


def single_sequence_agent(searched: BestStaticAgent) -> BestStaticAgent:
    """`best_static_single` (module docstring): the searched agent's pooled choice, played at
    every lambda of its search."""
    pooled = searched.single_search
    agent = BestStaticAgent(searched.spec, {lam: pooled.sequence for lam in searched.search}, seed=searched.seed)
    agent.search = {lam: pooled for lam in searched.search}
    return agent
