"""Evaluation: every agent on the same test episodes at every noise level (the paper's Fig. 5).

`evaluate(...)` runs each agent (the given policies or agent names, plus the baselines: the
oracle, a few fixed engineer pipelines, the best static pipeline, the untrained random agent) on
the episodes of the TEST image ids only (the seeded split of `episodes.split_image_keys`, with
the same seed and fraction as the training run), for each noise level lambda. The comparison is
paired: at a given lambda every agent sees the same episodes with the same episode seeds, hence
the same initial hypothesis. Episode seeds depend on the episode, not on lambda, so the
hypotheses of one episode at growing lambda lie along the same random direction (common random
numbers: smoother curves over lambda, and the Fig. 4 grid shows one hypothesis moving away).

Success accounting. An episode succeeds when a pick succeeds within `max_ops` operations.
`ops_to_success` and `time_to_success` are statistics over the SUCCESSFUL episodes only
(operations counted up to and including the successful pick; time = the seconds the
environment charged, failed picks included at their robot attempt cost); `success` is the
share of episodes that succeeded, and must be read next to them: an agent that solves only
the easy episodes looks fast. Over ALL episodes: `episode_time`, the seconds charged (a
failed episode at the time it used up), and `episode_cost`, minus the return (episode_time
plus the env's truncation penalty for giving up); the best fixed pipeline is the one with the
lowest mean episode_cost. `first_pick_success` is the share of all episodes whose first
attempted pick succeeded (an episode without any pick attempt counts as a miss).

The best static pipeline (`best_static`, agents/best_static.py): before the sweep, at each lambda,
an exhaustive search over the fixed sequences of up to `best_static_length` actions with a pick,
each played as the fixed agent plays it, on `best_static_episodes` episodes of the TRAIN images
(an env over the split's train keys), scored by mean episode_cost; the agent then plays each
lambda's winner. `best_static_single` plays one sequence at every lambda: the lowest mean
episode_cost over all the lambdas' search episodes together (one pipeline for the whole noise
range, as a configurator like SMAC would fix it; neither it nor the learned agent is told the
noise level). Their records carry `sequence` and `search` (episodes, sequences, max_length,
mean_cost of the chosen, runner_up and runner_up_cost, seconds); meta.json's `best_static` the
search settings (learning/evaluation_best_static.py). On the same train episodes, twice each with
the lambdas taken in turn, `best_threshold`: the threshold rule (agents/threshold.py: pick once
the pick-success score clears a threshold, else refine along a loop) of the lowest mean
episode_cost, one rule for every lambda; its
records carry `rule` and `search`. It reads the scores, as the learned agent does: the strongest
simple dynamic baseline.

Outputs in `out/`:
- results.json   list of records, one per (agent, lambda) (schema in `summarise`)
- meta.json      settings: dataset, split, test image ids, pipeline, seeds, definitions
- episodes.jsonl one line per (agent, lambda, episode): action trace, poses, errors
- bop/<agent>-lam<x>_<dataset>-<split>.csv  BOP results of the final poses, one file per (agent,
  lambda), named as bop_toolkit's parser reads `{method}_{dataset}-{split}.csv`: no '.' and no
  '_' in the method (lambda 0.5 is written lam0p5), the dataset folder's name without '_', '-'
  or '.'; each (image, object) evaluated once (a plan cycling over the test episodes keeps its
  first pass in the CSV)
- bop/targets_<dataset>-<split>.json  bop_toolkit's test_targets_bop19.json format (im_id,
  inst_count, obj_id, scene_id) for exactly the episodes of the CSVs: pass its absolute path
  as eval_calc_errors/eval_calc_scores' --targets_filename (bop_toolkit_eval.py does)
- fig5.png, lambda_grid.png, episode_*.png   plots (see core/plots.py)
- episodes.sqlite the episode store (store/episode_store.py): every episode played, appended as it ends
  (source "evaluate"; a second evaluation into the same folder adds to it); a store that fails
  is one log line on stderr, the evaluation goes on

The parts: the agents (learning/evaluation_agents.py), the per-episode and per-(agent, lambda)
records (evaluation_records.py), the lambda sweep in-process or on Ray (evaluation_sweep.py), and
the BOP CSVs, plots and table (evaluation_export.py).

Parallel: `workers` N > 1 (or `ray_address`) plays the sweep as Ray tasks (learning/ray_workers.py), each
a chunk of one (agent, lambda)'s planned episodes; a worker rebuilds the agent from its snapshot
(the oracle searches in the worker's env) and its env from the dataset path, the pipeline and the
test image ids. The best_static search runs on the same workers first (chunks of its train
episodes, in an env of the train image ids). Every episode carries its seeds, so the records are
the same as in-process, in cost-table mode bit for bit (Open3D then runs on one thread here and in
the workers).
"""
from __future__ import annotations

import json
import sys
from contextlib import nullcontext
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from ..agents.base import EnvRecipe, EnvSpec
from ..agents.best_static import BestStaticAgent
from ..agents.policy_settings import policy_settings
from ..agents.threshold import ThresholdAgent
from ..blocks.pipeline import Pipeline, load_pipeline, pipeline_reference
from ..core.geometry import LAMBDA_MAX, check_noise_lambda
from ..datasets.bop import BopDataset
from ..rl.env import PerceptionConfigEnv
from ..rl.episode_loop import Trajectory
from ..rl.episodes import EpisodeSource, split_image_keys
from ..store.episode_store import STORE_NAME, StoreWriter, store_episode
from ..util.atomic_file import atomic_write
from ..util.open3d_threads import open3d_single_thread
from .evaluation_agents import DEFAULT_FIXED_SEQUENCES, SEARCHED, EvalAgent, build_agents
from .evaluation_best_static import (
    DEFAULT_EPISODES,
    DEFAULT_MAX_LENGTH,
    best_static_agent,
    best_threshold_agent,
    check_options,
    search_seed,
    single_sequence_agent,
)
from .evaluation_export import make_plots, write_bop_csvs
from .evaluation_records import DEFINITIONS, mark_best_fixed, oracle_ratios, summarise
from .evaluation_sweep import sweep_here, sweep_on_ray
from .ray_workers import RayRunner, ray_wanted

DEFAULT_LAMBDAS: tuple[float, ...] = tuple(round(0.1 * i, 1) for i in range(1, 11))


def episode_seed(seed: int, j: int) -> int:
    """The seed of the j-th evaluation episode (the same at every lambda and for every agent)."""
    return int(np.random.SeedSequence([int(seed), int(j)]).generate_state(1)[0] % 2**31)


def _check_lambdas(lambdas: Iterable[float]) -> list[float]:
    out = [check_noise_lambda(lam) for lam in lambdas]
    if not out:
        raise ValueError("no lambda to evaluate")
    return out


def episode_plan(n_available: int, episodes_per_lambda: int | None, seed: int) -> list[tuple[int, int]]:
    """(episode index, episode seed) of the evaluation episodes, the same at every lambda.
    None = every test episode once; fewer = a seeded random subset; more = cycled (each pass
    with fresh seeds, so the hypotheses differ)."""
    if episodes_per_lambda is None:
        n = n_available
    else:
        n = int(episodes_per_lambda)
        if n < 1:
            raise ValueError(f"episodes_per_lambda must be >= 1, got {episodes_per_lambda}")
    order = np.random.default_rng(seed).permutation(n_available) if n < n_available else np.arange(n_available)
    return [(int(order[j % n_available]), episode_seed(seed, j)) for j in range(n)]


def evaluate(
    dataset: str | Path | BopDataset,
    policies: Sequence[Any] = (),
    lambdas: Sequence[float] = DEFAULT_LAMBDAS,
    out: str | Path = "evaluation",
    episodes_per_lambda: int | None = None,
    seed: int = 0,
    pipeline: str | Path | Pipeline | None = None,
    split_seed: int | None = None,
    test_fraction: float | None = None,
    include_baselines: bool = True,
    progress: bool = True,
    *,
    split: str = "test",
    fixed: Iterable[Sequence[str]] = DEFAULT_FIXED_SEQUENCES,
    plots: bool = True,
    n_example_episodes: int = 2,
    use_depth: bool = True,
    store_episodes: bool = True,
    workers: int | None = None,
    ray_address: str | None = None,
    oracle_budget: int | None = None,
    best_static_length: int = DEFAULT_MAX_LENGTH,
    best_static_episodes: int = DEFAULT_EPISODES,
    **env_overrides: Any,
) -> Path:
    """Evaluate agents on the test images at each lambda; write the reports to `out`; return
    the path of results.json. See the module docstring for the outputs and definitions.

    policies: policy files, agent names of `perception_config.agents.AGENTS`, or agent objects
    / (name, agent) pairs. split_seed, test_fraction, pipeline and the environment settings
    default to what the policy files record from training (agents/policy_settings.py: the split, the
    pipeline and max_ops must agree with explicit values; other settings given here, e.g.
    time_mode="cost_table", win and are reported), else 0, 0.3, the shipped pipeline and
    `EnvSettings()`. `env_overrides`: EnvSettings fields. `fixed`: the engineer sequences
    evaluated as baselines (those naming actions the pipeline lacks are skipped; on RGB-only
    frames they skip the actions that cannot run). `use_depth=False` reads a dataset folder as
    RGB-only; every agent then chooses among the actions that can run (`info["action_mask"]`).
    `store_episodes`: append every episode to out/episodes.sqlite. `workers` N > 1 plays the
    episodes as tasks on a local Ray with N workers, `ray_address` on a running cluster (module
    docstring); neither (or N = 1): in this process, without Ray. `oracle_budget`: the oracle's
    operator calls per episode (default 2000; with generators among the actions each call can
    be a search of a second, so the cell pipeline's evaluation gives it fewer).
    `best_static_length`, `best_static_episodes`: the best static pipeline's search (module
    docstring): sequences of up to this many actions, this many train episodes per lambda; 0
    episodes: no best_static.
    """
    lams = _check_lambdas(lambdas)
    if workers is not None and int(workers) < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    check_options(best_static_length, best_static_episodes)
    out = Path(out)
    settings = policy_settings(policies, split_seed=split_seed, test_fraction=test_fraction, pipeline=pipeline,
                               dataset=dataset, **env_overrides)
    for note in settings.notes:
        print(f"note: {note}", file=sys.stderr)
    ds = dataset if isinstance(dataset, BopDataset) else BopDataset(Path(dataset), split=split, use_depth=use_depth)
    train_keys, test_keys = split_image_keys(ds.image_keys(), settings.test_fraction, settings.split_seed)
    pipe = settings.pipeline if isinstance(settings.pipeline, Pipeline) else load_pipeline(settings.pipeline)
    env_settings = settings.env.replace(lambda_range=(0.0, LAMBDA_MAX))  # every lambda is set per episode
    source = EpisodeSource(ds, test_keys, min_visib_fract=env_settings.min_visib_fract)
    env = PerceptionConfigEnv(source, pipe, env_settings)
    wants_best_static = best_static_episodes > 0 and (
        include_baselines or any(p in SEARCHED for p in policies if isinstance(p, str)))
    # the searched agents replace these stand-ins before the sweep; building the agents first finds bad
    # policies before the search
    spec = EnvSpec.from_env(env)
    stand_in = BestStaticAgent(spec) if wants_best_static else None
    single_stand_in = BestStaticAgent(spec) if wants_best_static else None
    rule_stand_in = ThresholdAgent(spec) if wants_best_static and spec.pick_actions else None
    agents = build_agents(env, policies, seed, include_baselines, fixed, oracle_budget, stand_in, single_stand_in,
                          rule_stand_in)
    plan = episode_plan(len(source), episodes_per_lambda, seed)
    recipe = None
    if ray_wanted(workers, ray_address):
        pipe_ref = settings.pipeline
        if not isinstance(pipe_ref, Pipeline):
            pipe_ref = pipeline_reference(pipe_ref)
        recipe = EnvRecipe(str(Path(ds.root).resolve()), pipe_ref, tuple(test_keys), split, env_settings,
                           use_depth=bool(getattr(ds, "use_depth", True)))
    best_static_meta = None
    if wants_best_static:
        best_static_meta = {"max_length": int(best_static_length), "episodes": int(best_static_episodes),
                            "seed": search_seed(seed), "train_images": len(train_keys),
                            "note": "exhaustive search per lambda on train episodes; mean episode_cost; "
                                    "best_static_single: the lambdas' episodes pooled"}

    bar = None
    records: list[dict[str, Any]] = []
    per_episode: list[dict[str, Any]] = []
    writer = StoreWriter(out / STORE_NAME, lambda line: print(line, file=sys.stderr, flush=True)) \
        if store_episodes else None

    def storer(ea: EvalAgent, ep_seed: int) -> Callable[[Trajectory], None] | None:
        if writer is None:
            return None
        return lambda t: store_episode(writer, t, source="evaluate", agent=ea.name, policy_version=ea.version,
                                       dataset=str(ds.root), episode_seed=ep_seed)

    try:
        with (RayRunner(workers, ray_address) if recipe is not None else nullcontext()) as runner, \
                open3d_single_thread(env_settings.time_mode == "cost_table"):
            if wants_best_static:  # an env of the TRAIN images: the search never sees a test image
                train_source = EpisodeSource(ds, train_keys, min_visib_fract=env_settings.min_visib_fract)
                train_env = PerceptionConfigEnv(train_source, pipe, env_settings)
                train_recipe = None if recipe is None else replace(recipe, image_keys=tuple(train_keys))
                searched = best_static_agent(
                    train_env, lams, episode_plan(len(train_env.source), best_static_episodes, search_seed(seed)),
                    best_static_length, seed, runner, train_recipe, progress)
                single = single_sequence_agent(searched)
                rule = None
                if any(ea.agent is rule_stand_in for ea in agents):
                    rule = best_threshold_agent(
                        train_env, lams, episode_plan(len(train_env.source), best_static_episodes, search_seed(seed)),
                        seed, runner, train_recipe, progress)
                    best_static_meta["best_threshold"] = {"rule": rule.describe(), **rule.search}
                for ea in agents:
                    if ea.agent is stand_in:
                        ea.agent = searched
                    elif ea.agent is single_stand_in:
                        ea.agent = single
                    elif ea.agent is rule_stand_in:
                        ea.agent = rule
            if progress:
                from tqdm import tqdm

                bar = tqdm(total=len(agents) * len(lams) * len(plan), desc="evaluate", unit="ep", dynamic_ncols=True)
            if runner is not None:
                sweep = sweep_on_ray(runner, recipe, agents, lams, plan, bar, storer)
            else:
                sweep = sweep_here(env, agents, lams, plan, bar, storer)
        for lam in lams:
            for ea in agents:
                eps = [{"agent": ea.name, **rec} for rec in sweep[(ea.name, lam)]]
                per_episode.extend(eps)
                records.append({**summarise(ea.name, lam, eps), "kind": ea.kind})
                if ea.kind == "best_threshold":
                    records[-1]["rule"] = ea.agent.describe()
                    records[-1]["search"] = dict(ea.agent.search)
                elif ea.kind in ("best_static", "best_static_single"):
                    records[-1]["sequence"] = ea.agent.sequence_for(lam)
                    if lam in ea.agent.search:
                        records[-1]["search"] = ea.agent.search[lam].to_json()
    finally:
        if bar is not None:
            bar.close()
        if writer is not None:
            writer.close()
    mark_best_fixed(records)
    oracle_ratios(records, per_episode)

    out.mkdir(parents=True, exist_ok=True)
    atomic_write(out / "results.json", json.dumps(records, indent=1, allow_nan=False) + "\n")
    atomic_write(out / "episodes.jsonl", "".join(json.dumps(e, allow_nan=False) + "\n" for e in per_episode))
    es = env.settings
    meta = {
        "dataset": str(ds.root), "split": split, "use_depth": bool(getattr(ds, "use_depth", True)),
        "split_seed": settings.split_seed,
        "test_fraction": settings.test_fraction, "test_images": [list(k) for k in test_keys],
        "n_train_images": len(train_keys), "episodes_per_lambda": len(plan), "seed": seed, "lambdas": lams,
        "time_mode": es.time_mode, "max_ops": es.max_ops, "failed_pick_cost": es.failed_pick_cost,
        "truncation_cost": es.truncation_cost, "min_visib_fract": es.min_visib_fract, "env_settings": es.to_json(),
        "settings_notes": settings.notes, "pipeline": pipe.describe(),
        "agents": [{"name": a.name, "kind": a.kind} for a in agents],
        "best_static": best_static_meta,
        "definitions": DEFINITIONS,
    }
    atomic_write(out / "meta.json", json.dumps(meta, indent=1, allow_nan=False) + "\n")
    write_bop_csvs(out / "bop", per_episode, Path(ds.root).name, split)
    if plots:
        make_plots(out, records, per_episode, env, lams, plan, n_example_episodes)
    return out / "results.json"
