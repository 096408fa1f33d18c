"""The base sequence of a residual policy (agents/policy_gradient.py, `base`): the best static
pipeline over the TRAINING distribution, searched before training starts.

`base="best_static"` among pg's hyper-parameters asks for it: one exhaustive, prefix-shared
search (agents/best_static.py) over the fixed sequences of up to `max_length` actions with a pick,
on `episodes` training episodes drawn (seeded by the run's seed) from the training images with
lambda uniform over the training range: the distribution pg trains on, where the evaluation's
best_static searches each test lambda apart. The validation images are never searched. The
sequence found, its mean cost and the runner-up go into the run's metadata (`base_search`).
"""
from __future__ import annotations

import time
from typing import Any, Sequence

import numpy as np

from ..agents.base import EnvSpec
from ..agents.best_static import SearchResult, search_costs, static_sequences
from ..agents.policy_gradient import BASE_SEARCH
from ..rl.episode_loop import acting_seed
from .evaluation_best_static import DEFAULT_MAX_LENGTH, search_chunk
from .ray_workers import RayRunner, chunks

__all__ = ["BASE_SEARCH", "DEFAULT_BASE_EPISODES", "base_plan", "search_base"]
DEFAULT_BASE_EPISODES = 36


def base_plan(train_idx: Sequence[int], lambda_range: tuple[float, float], episodes: int,
              seed: int) -> list[tuple[dict[str, Any], int]]:
    """(reset options, acting seed) of the search's episodes: `episodes` training episodes
    (without repeats while there are enough), lambda uniform over `lambda_range`."""
    if episodes < 1 or not len(train_idx):
        raise ValueError(f"the base search needs >= 1 episode and training episodes, got {episodes}, {len(train_idx)}")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 11]))
    picks = rng.choice(len(train_idx), size=episodes, replace=episodes > len(train_idx))
    lo, hi = lambda_range
    out = []
    for k in picks:
        episode_seed = int(rng.integers(2**31))
        out.append(({"episode": int(train_idx[int(k)]), "lambda": float(rng.uniform(lo, hi)),
                     "episode_seed": episode_seed}, acting_seed(episode_seed)))
    return out


def search_base(env: Any, train_idx: Sequence[int], lambda_range: tuple[float, float], seed: int,
                episodes: int | None = None, max_length: int = DEFAULT_MAX_LENGTH,
                runner: RayRunner | None = None, recipe: Any = None, progress: bool = True) -> SearchResult:
    """The best static sequence on the training distribution (module docstring). With `runner`
    (and the `recipe` of `env`) the episodes are played as Ray tasks. `episodes`: default
    DEFAULT_BASE_EPISODES."""
    spec = EnvSpec.from_env(env)
    sequences = static_sequences(spec.action_names, spec.action_kinds, max_length)
    plan = base_plan(train_idx, lambda_range, DEFAULT_BASE_EPISODES if episodes is None else episodes, seed)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(plan), desc=f"base search ({len(sequences)} sequences)", unit="ep", dynamic_ncols=True)
    t0 = time.perf_counter()
    try:
        if runner is None:
            costs, images = search_costs(env, sequences, plan, bar.update if bar is not None else None)
        else:
            ref = runner.put(recipe)
            calls = [(ref, sequences, plan[lo:hi]) for lo, hi in chunks(len(plan), 1, runner.cpus)]
            parts = runner.map(search_chunk, calls,
                               (lambda _k, part: bar.update(len(part[1]))) if bar is not None else None)
            costs = np.concatenate([rows for rows, _ in parts])
            images = [key for _, keys in parts for key in keys]
    finally:
        if bar is not None:
            bar.close()
    return SearchResult.from_costs(sequences, costs, max_length, time.perf_counter() - t0, images)
