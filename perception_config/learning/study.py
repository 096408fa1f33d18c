"""A multi-seed study: one agent trained with N seeds, all of them evaluated on the same test
episodes next to every baseline, and the comparison with confidence intervals.

`run_study(dataset, out, ...)`, in four steps, each kept when it is done:
1. the cost model: calibrated once on the train images into out/cost_model.json (or the
   `cost_table` given: a `calibrate` output, or "blocks" for the blocks' default costs); every
   seed is trained and evaluated with that one table, so their costs compare;
2. the seeds s0 .. s0+N-1, each an ordinary training run (learning/training.py) in
   out/seed-<s>/ with the same split, pipeline, settings and validation-based selection; with
   `restarts` R > 1 each seed is R runs (training seeds s, s + 1000, ..., learning/seed_selection.py
   in out/seed-<s>/) of which the one of lowest validation cost is the seed's policy: what a
   user who trains with `train --seeds R` ships, judged as one seed. A seed
   whose policy is complete (trained to `episodes`, not stopped) is kept as it is (not trained
   again, its files untouched); a seed stopped midway resumes from its checkpoint; a seed
   trained with other settings (another cost table, pipeline, agent) is an error naming it.
   So a study stopped by Ctrl-C continues where it stopped when run again. The wall seconds
   each seed's training took (summed over the runs of the study) are kept in
   out/training_seconds.json;
3. ONE evaluation (learning/evaluation.py) of the N policies and every baseline (the oracle, the
   fixed pipelines, random, best_static when evaluation has it) on the same `eval_episodes`
   test episodes per lambda, into out/evaluation/. A complete evaluation already there of the
   same policies (their content versions), lambdas, episodes, seed and evaluate arguments (its
   out/evaluation/study_stamp.json, written after it) is kept;
4. the statistics (learning/study_report.py, learning/study_stats.py): out/study.json, the plot
   out/study.png (learning/study_plot.py), and the table and verdicts `format_table` prints.

Stopping: a stop signal (SIGINT, SIGTERM, SIGHUP) during training stops it as `train` does (the
seed's work saved); during the calibration or the evaluation it abandons that step, which writes
its files only at its end (atomically). Either way StopRequested is raised (the CLI exits 128 + the
signal number) and everything done before stays valid for the next run.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any, Callable, Sequence

from ..agents.policy_io import read_file
from ..blocks.pipeline import pipeline_reference
from ..core.geometry import check_noise_lambda
from ..rl.episodes import DEFAULT_SPLIT_SEED, DEFAULT_TEST_FRACTION
from ..rl.settings import EnvSettings, settings_from_policy_meta
from ..util.atomic_file import atomic_write
from ..util.stop_signals import Interrupted, StopRequested, StopSignals, signal_name
from .study_report import analyse, load_evaluation

STUDY_JSON = "study.json"
STUDY_PNG = "study.png"
COST_MODEL = "cost_model.json"
EVALUATION = "evaluation"
TRAINING_SECONDS = "training_seconds.json"
STAMP = "study_stamp.json"  # in out/evaluation/: what the evaluation there was run on (evaluation_stamp)
LEARNING_AGENTS = ("pg", "es", "simple")
DEFAULT_SEEDS = 5
DEFAULT_EPISODES = 1000
DEFAULT_EVAL_EPISODES = 60
DEFAULT_LAMBDAS: tuple[float, ...] = (0.3, 0.5, 0.7)
DEFAULT_VALIDATION_FRACTION = 0.2
DEFAULT_RESTARTS = 1
RESTART_STRIDE = 1000  # a study seed s's restarts train with seeds s, s + RESTART_STRIDE, ...


def _say(progress: bool, text: str) -> None:
    if progress:
        print(text, flush=True)


def _stoppable(what: str, call: Callable[[], Any]) -> Any:
    """Run `call` so that the first stop signal abandons it: StopRequested naming the step."""
    stops = StopSignals()
    with stops.installed():
        try:
            with stops.interruptible():
                return call()
        except Interrupted:
            signum = stops.received[0]
            raise StopRequested(signum, f"study stopped by {signal_name(signum)} during {what}: what was done before "
                                        "is kept, run the same command again to continue") from None


# -- step 1: the cost model ---------------------------------------------------------------------
def study_cost_table(dataset: str | Path, out: Path, pipeline: str | Path | None, cost_table: str | Path | None,
                     seed: int, use_depth: bool, progress: bool) -> tuple[dict[str, float] | None, str]:
    """(the cost table every seed is charged, where it came from): `cost_table` "blocks" (None:
    the blocks' default costs), a FILE (a calibrate output), else out/cost_model.json, calibrated
    on the train images (the default split's) if the study has none yet."""
    from ..bench.calibration import calibrate, read_cost_table, write_cost_model

    if cost_table is not None and str(cost_table) == "blocks":
        return None, "blocks"
    if cost_table is not None:
        return read_cost_table(cost_table), str(Path(cost_table).resolve())
    path = out / COST_MODEL
    if path.exists():
        _say(progress, f"cost model: {path} (calibrated by an earlier run of this study)")
        return read_cost_table(path), str(path.resolve())
    from ..datasets.bop import BopDataset
    from ..rl.episodes import split_image_keys

    ds = BopDataset(Path(dataset), use_depth=use_depth)
    train_keys, _ = split_image_keys(ds.image_keys(), DEFAULT_TEST_FRACTION, DEFAULT_SPLIT_SEED)
    _say(progress, "calibrating the cost model on the train images (once for every seed)")
    model = _stoppable("the calibration", lambda: calibrate(ds, pipeline, train_keys, seed=seed, use_depth=use_depth,
                                                             progress=progress))
    write_cost_model(model, path)
    return model["cost_table"], str(path.resolve())


# -- step 2: the seeds ----------------------------------------------------------------------------
def policy_file(run: Path) -> Path | None:
    """The policy a training run folder shipped (policy.safetensors, or policy.json), or None."""
    return next((run / n for n in ("policy.safetensors", "policy.json") if (run / n).is_file()), None)


def restart_seeds(seed: int, restarts: int) -> list[int]:
    """The training seeds of one study seed's restarts."""
    return [int(seed) + RESTART_STRIDE * r for r in range(int(restarts))]


def runs_shipped_from(run: Path) -> int:
    """How many runs a study seed's folder chose its policy among (seed_selection's seeds.csv
    rows; 1 without it)."""
    from .seed_selection import SEEDS_CSV

    try:
        return max(1, len((run / SEEDS_CSV).read_text().strip().splitlines()) - 1)
    except OSError:
        return 1


def seed_state(run: Path, agent: str, episodes: int, settings: EnvSettings, pipeline: str | Path | None,
               validation_fraction: float, use_depth: bool, restarts: int = 1) -> str:
    """"done" (a complete policy trained as this study trains: kept), "resume" (a checkpoint
    to continue) or "new". A complete policy trained otherwise is a ValueError naming it."""
    from .training import CHECKPOINT

    policy = policy_file(run)
    if policy is not None:
        meta, _ = read_file(policy)
        extra = meta.get("extra") or {}
        if not extra.get("interrupted") and int(extra.get("episodes", 0)) >= episodes:
            trained = settings_from_policy_meta(meta, f"policy {policy}")
            problems = [f"agent {meta.get('agent')!r}, this study trains {agent!r}"] if meta.get("agent") != agent \
                else []
            problems += (trained.differences(settings) if trained is not None else ["no environment settings"])
            if extra.get("pipeline") != pipeline_reference(pipeline):
                problems.append(f"pipeline {extra.get('pipeline')!r}, this study has {pipeline_reference(pipeline)!r}")
            if float(extra.get("validation_fraction", 0.0)) != float(validation_fraction):
                problems.append(f"validation_fraction {extra.get('validation_fraction')}, this study has "
                                f"{validation_fraction}")
            if bool(extra.get("use_depth", True)) != bool(use_depth):
                problems.append(f"use_depth {extra.get('use_depth')}, this study has {use_depth}")
            shipped_from = runs_shipped_from(run)
            if shipped_from != restarts:
                problems.append(f"the best of {shipped_from} runs, this study has restarts {restarts}")
            if problems:
                raise ValueError(f"{policy} was trained with other settings than this study ({'; '.join(problems)}): "
                                 f"give the study another --out, or remove {run} to train that seed again")
            return "done"
    return "resume" if (run / CHECKPOINT).exists() else "new"


def _read_seconds(out: Path) -> dict[str, Any]:
    try:
        data = json.loads((out / TRAINING_SECONDS).read_text())
        return data if isinstance(data, dict) else {}
    except (OSError, ValueError):
        return {}


def train_study_seeds(dataset: str | Path, out: Path, agent: str, seeds: Sequence[int], episodes: int,
                      settings: EnvSettings, *, pipeline: str | Path | None, validation_fraction: float,
                      agent_kwargs: dict[str, Any] | None, workers: int | None, use_depth: bool,
                      progress: bool, ray_address: str | None = None, restarts: int = 1) -> dict[int, Path]:
    """Train (or keep, or resume) every seed's run in out/seed-<s>/ (`restarts` > 1: the runs of
    restart_seeds(s) there, the validation-best shipped); {seed: policy file}."""
    from .seed_selection import train_seeds
    from .training import train

    policies: dict[int, Path] = {}
    for k, s in enumerate(seeds):
        run = out / f"seed-{s}"
        state = seed_state(run, agent, episodes, settings, pipeline, validation_fraction, use_depth, restarts)
        if state == "done":
            policy = policy_file(run)
            assert policy is not None
            _say(progress, f"seed {s} ({k + 1} of {len(seeds)}): {run} is trained already, kept")
            policies[s] = policy
            continue
        _say(progress, f"seed {s} ({k + 1} of {len(seeds)}): "
                       f"{'resuming ' if state == 'resume' else 'training '}{run}")
        started = time.monotonic()
        common = dict(settings=settings, pipeline=pipeline, agent_kwargs=agent_kwargs, workers=workers,
                      ray_address=ray_address, progress=progress, use_depth=use_depth,
                      validation_fraction=validation_fraction)
        try:
            if restarts > 1:  # the finished restarts resume at their end: kept as they are
                policies[s] = train_seeds(dataset, agent, run, episodes, restart_seeds(s, restarts), resume=True,
                                          **common)
            else:
                policies[s] = train(dataset, agent, run, episodes, seed=int(s), resume=state == "resume", **common)
        except StopRequested as exc:
            raise StopRequested(exc.signum, f"study stopped by {signal_name(exc.signum)} while training seed {s} "
                                            f"(its work is saved in {run}): run the same command again to continue "
                                            "(the seeds trained are kept, this one resumes)") from exc
        finally:  # a stopped seed's seconds count too: it resumes from there
            seconds = _read_seconds(out)
            entry = seconds.get(str(s), {})
            entry["seconds"] = round(float(entry.get("seconds", 0.0)) + time.monotonic() - started, 3)
            seconds[str(s)] = entry
            atomic_write(out / TRAINING_SECONDS, json.dumps(seconds, indent=1, sort_keys=True) + "\n")
    return policies


# -- step 3: the evaluation -------------------------------------------------------------------------
def seed_agent_name(agent: str, seed: int) -> str:
    """The evaluation's name of out/seed-<s>/policy.* (evaluation_agents: kind:<run folder>)."""
    return f"{agent}:seed-{seed}"


def evaluation_stamp(policies: Sequence[Path], lambdas: Sequence[float], eval_episodes: int, eval_seed: int,
                     evaluate_kwargs: dict[str, Any]) -> dict[str, Any]:
    """What an evaluation of the study was run on: the policies (path and content version), the
    lambdas, the episodes, the seed and the other evaluate arguments."""
    from ..store.episode_store import policy_version

    return {"policies": [[str(p), policy_version(p)] for p in policies], "lambdas": [float(x) for x in lambdas],
            "episodes_per_lambda": int(eval_episodes), "seed": int(eval_seed),
            "evaluate": {k: v for k, v in sorted(evaluate_kwargs.items())}}


def evaluation_current(eval_dir: Path, stamp: dict[str, Any]) -> bool:
    """Whether eval_dir holds a complete evaluation whose STAMP equals `stamp` (evaluation_stamp)."""
    try:
        saved = json.loads((eval_dir / STAMP).read_text())
    except (OSError, ValueError):
        return False
    complete = all((eval_dir / n).is_file() for n in ("results.json", "episodes.jsonl", "meta.json"))
    return complete and saved == json.loads(json.dumps(stamp))


# -- the study ---------------------------------------------------------------------------------------
def run_study(
    dataset: str | Path,
    out: str | Path,
    *,
    pipeline: str | Path | None = None,
    agent: str = "pg",
    seeds: int = DEFAULT_SEEDS,
    seed: int = 0,
    restarts: int = DEFAULT_RESTARTS,
    episodes: int = DEFAULT_EPISODES,
    eval_episodes: int = DEFAULT_EVAL_EPISODES,
    lambdas: Sequence[float] = DEFAULT_LAMBDAS,
    workers: int | None = None,
    ray_address: str | None = None,
    cost_table: str | Path | None = None,
    validation_fraction: float = DEFAULT_VALIDATION_FRACTION,
    agent_kwargs: dict[str, Any] | None = None,
    eval_seed: int = 0,
    evaluate_kwargs: dict[str, Any] | None = None,
    use_depth: bool = True,
    progress: bool = True,
    command: Sequence[str] | None = None,
    **bootstrap: Any,
) -> dict[str, Any]:
    """Run the study of the module docstring into `out`; returns what out/study.json holds.

    `seeds` runs with seeds `seed`..`seed`+`seeds`-1 of `episodes` training episodes each (each the
    validation-best of `restarts` runs);
    `eval_episodes` test episodes per lambda of `lambdas` (evaluation seed `eval_seed`);
    `workers` / `ray_address`: as train's and evaluate's (each seed's rounds, the evaluation);
    `evaluate_kwargs`: more evaluate() arguments (e.g. best_static_episodes);
    `cost_table`: a calibrate output, "blocks", or None (calibrate once into out/); `command`:
    the command line, recorded; `bootstrap`: study_stats settings (resamples, level, seed)."""
    from .evaluation import evaluate
    from .study_plot import plot_study

    if agent not in LEARNING_AGENTS:
        raise ValueError(f"a study trains a learning agent ({', '.join(LEARNING_AGENTS)}), got {agent!r}")
    if seeds < 1:
        raise ValueError(f"seeds must be >= 1, got {seeds}")
    if not 1 <= restarts < RESTART_STRIDE:
        raise ValueError(f"restarts must be in [1, {RESTART_STRIDE - 1}], got {restarts}")
    if restarts > 1 and not validation_fraction > 0:
        raise ValueError("restarts are chosen among by their validation cost: validation_fraction must be > 0")
    if episodes < 1 or eval_episodes < 1:
        raise ValueError(f"episodes and eval_episodes must be >= 1, got {episodes} and {eval_episodes}")
    lams = [check_noise_lambda(float(x)) for x in lambdas]
    if not lams or len(set(lams)) != len(lams):
        raise ValueError(f"lambdas must be distinct noise levels, at least one, got {list(lambdas)}")
    if not Path(dataset).is_dir():
        raise FileNotFoundError(f"dataset {dataset} is not a folder")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    seed_list = list(range(int(seed), int(seed) + int(seeds)))

    table, table_source = study_cost_table(dataset, out, pipeline, cost_table, seed, use_depth, progress)
    settings = EnvSettings().replace(cost_table=table)
    policies = train_study_seeds(dataset, out, agent, seed_list, episodes, settings, pipeline=pipeline,
                                 validation_fraction=validation_fraction, agent_kwargs=agent_kwargs, workers=workers,
                                 use_depth=use_depth, progress=progress, ray_address=ray_address, restarts=restarts)
    paths = [policies[s] for s in seed_list]
    names = [seed_agent_name(agent, s) for s in seed_list]
    eval_dir = out / EVALUATION
    evaluate_kwargs = dict(evaluate_kwargs or {})
    stamp = evaluation_stamp(paths, lams, eval_episodes, eval_seed, evaluate_kwargs)
    if evaluation_current(eval_dir, stamp):
        _say(progress, f"evaluation: {eval_dir} holds these policies' evaluation already, kept")
    else:
        _say(progress, f"evaluating the {len(paths)} policies and the baselines on {eval_episodes} test episodes per "
                       f"lambda: {eval_dir}")
        (eval_dir / STAMP).unlink(missing_ok=True)  # a stopped evaluation leaves a mix of old and new files
        _stoppable("the evaluation", lambda: evaluate(
            dataset, [str(p) for p in paths], lams, eval_dir, episodes_per_lambda=eval_episodes, seed=eval_seed,
            progress=progress, workers=workers, ray_address=ray_address, use_depth=use_depth, **evaluate_kwargs))
        atomic_write(eval_dir / STAMP, json.dumps(stamp, indent=1) + "\n")
    records, episodes_played = load_evaluation(eval_dir)
    analysis = analyse(records, episodes_played, names, label=agent, seeds=seed_list, **bootstrap)
    seconds = _read_seconds(out)
    study = {
        "command": list(command) if command is not None else list(sys.argv),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "dataset": str(Path(dataset).resolve()), "out": str(out.resolve()), "agent": agent,
        "pipeline": pipeline_reference(pipeline), "seeds": seed_list, "restarts": int(restarts),
        "episodes": int(episodes),
        "eval_episodes": int(eval_episodes), "eval_seed": int(eval_seed), "evaluate_arguments": evaluate_kwargs,
        "validation_fraction": validation_fraction,
        "agent_params": dict(agent_kwargs or {}), "cost_model": table_source,
        "policies": {str(s): str(policies[s]) for s in seed_list},
        "training_seconds": {str(s): (seconds.get(str(s)) or {}).get("seconds") for s in seed_list},
        "evaluation": str(eval_dir), **analysis,
    }
    atomic_write(out / STUDY_JSON, json.dumps(study, indent=1, allow_nan=False) + "\n")
    plot_study(analysis, out / STUDY_PNG)
    return study


__all__ = ["run_study", "study_cost_table", "seed_state", "train_study_seeds", "evaluation_current",
           "evaluation_stamp", "policy_file", "seed_agent_name", "STUDY_JSON", "STUDY_PNG", "COST_MODEL", "EVALUATION",
           "TRAINING_SECONDS", "STAMP", "DEFAULT_RESTARTS", "restart_seeds",
           "DEFAULT_LAMBDAS", "DEFAULT_SEEDS", "DEFAULT_EPISODES", "DEFAULT_EVAL_EPISODES",
           "LEARNING_AGENTS"]
