"""Training the learning agents: episodes on the train split, checkpoints, a learning curve.

The loop is the same for every agent; the algorithms live in the agent files. One round:
1. `agent.actors()`: the policies to run (the pg/simple agent itself; the ES population);
2. draw `agent.episodes_per_actor` episodes from the TRAIN split: an object of a train image,
   lambda ~ U(lambda_range), an episode seed; every actor plays the same episodes;
3. play them, in this process or as Ray tasks on `workers` processes or a cluster (`ray_address`;
   learning/ray_workers.py: each worker builds its own env from an `EnvRecipe`, torch with one thread);
   env and actions are seeded per episode, so results do not depend on the number of workers
   or on which worker played what (except measured times);
4. `agent.update(trajectories)`: the algorithm's learning step; the figures it returns (pg: loss,
   entropy, gradient norms, lr, approx_kl) are recorded with the round's episodes.
Image ids are split by `split_image_keys(keys, test_fraction, split_seed)`; the test ids are
held out (stored in the policy metadata with the split seed and fraction, for evaluation).

Validation-based selection (learning/validation.py), with `validation_fraction` > 0: that share of the
train ids is held out of training too; every `validate_every` episodes, and at the end, the
greedy policy plays the same validation episodes, and policy.safetensors is the one with the
lowest mean validation cost (its episode and figures in the metadata's `extra.selected`), the
checkpoint keeps the latest state (and the selected weights, so a resumed run selects the
same), validation.csv and the learning curve show every check.

The environment's settings are one `EnvSettings` (rl/settings.py), recorded in the policy's
metadata (`extra.env_settings`) and restored wherever the policy is run.

Files in `out/`: policy.safetensors (or policy.json for agents without weights),
checkpoint.safetensors (policy + optimizer/population + episode counter + rng states +
history; written atomically every `checkpoint_every` episodes; `resume=True` continues from
it), history.csv (learning/training_history.py: a row per episode, with the update its round fed and
that update's figures) and learning_curve.png (learning/learning_curve.py), all written atomically;
episodes.sqlite (store/episode_store.py):
every episode played, appended by this process after each round (never by the workers), with
policy_version "train:<run folder>@<episodes learned before the round>" (+ "/actor<i>" for a
population); a store that fails (full disk, locked, corrupt) is one log line and training goes on.

Stopping (util/stop_signals.py): SIGINT (Ctrl-C), SIGTERM and SIGHUP drop the round in flight (its
episodes only: the trainer's rng goes back to the round's start, so a resumed run is the
uninterrupted one), cancel the round's Ray tasks and stop the local Ray, write the
checkpoint, policy, history and curve of the last completed round, then raise StopRequested
(a KeyboardInterrupt carrying the signal; the CLI exits 128 + its number). A signal during a
learning step or the save is only recorded: the step and the files are completed. A signal
ignored when train() starts (SIGHUP under nohup) stays ignored.

Reproducibility: in cost-table mode a seeded run repeats bit for bit (history and tensors), for
any number of workers: the blocks run without their wall-clock bounds (rl/env.py), Open3D on one
thread (its parallel ICP sums are not reproducible), and the per-frame caches hold nothing that
depends on the episodes played before (learning/ray_workers.py). Ray retries a task whose worker died
with the same result; a run stopped or crashed resumes from its checkpoint on a new cluster.
Rounds are whole: the episode count may overshoot `episodes` by less than one round.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, ContextManager

import numpy as np

from ..agents import AGENTS, Agent, EnvRecipe, EnvSpec, make_agent
from ..agents.policy_io import PolicyError, agent_meta, build_agent, check_compatible, read_file, save_agent, write_file
from ..blocks.pipeline import pipeline_reference
from ..datasets.bop import BopDataset
from ..rl.episode_loop import Trajectory, play_episode
from ..rl.episodes import DEFAULT_SPLIT_SEED, DEFAULT_TEST_FRACTION, DEFAULT_VALIDATE_EVERY, split_image_keys
from ..rl.settings import EnvSettings, settings_from_policy_meta
from ..store.episode_store import STORE_NAME, StoreWriter, store_episode
from ..util.open3d_threads import open3d_single_thread
from ..util.stop_signals import Interrupted, StopRequested, StopSignals, signal_name
from .learning_curve import plot_learning_curve
from .ray_workers import RayRunner, chunks, play_chunk, ray_wanted, snapshot
from .training_history import (
    TENSOR_PREFIX,
    history_arrays,
    history_from_tensors,
    new_history,
    record_round,
    updates_done,
    write_history_csv,
)
from .validation import SELECTION, Selection, default_lambdas, split_validation, validate, validation_episodes
from .validation import write_csv as write_validation_csv

POLICY_STEM = "policy"
CHECKPOINT = "checkpoint.safetensors"
VALIDATION_CSV = "validation.csv"
CURVE = "learning_curve.png"
HISTORY_CSV = "history.csv"


# -- playing a round --------------------------------------------------------------------------
def play_round(env: Any, actors: list[Agent], episodes: list[dict[str, Any]], act_seeds: np.ndarray,
               runner: RayRunner | None = None, recipe: Any = None) -> list[list[Trajectory]]:
    """Every actor plays every episode: trajectories[actor][episode]; in this process, or as Ray
    tasks of `runner` whose workers build their env from `recipe` (a RayRunner.put reference)."""
    if runner is None:
        return [[play_episode(env, actor, options, int(act_seeds[i, j])) for j, options in enumerate(episodes)]
                for i, actor in enumerate(actors)]
    pieces = chunks(len(episodes), len(actors), runner.cpus)  # every episode carries its seeds
    calls, owner = [], []
    for i, actor in enumerate(actors):
        snap = runner.put(snapshot(actor))
        for lo, hi in pieces:
            calls.append((recipe, snap, [(episodes[j], int(act_seeds[i, j])) for j in range(lo, hi)]))
            owner.append(i)
    out: list[list[Trajectory]] = [[] for _ in actors]
    for i, trajs in zip(owner, runner.map(play_chunk, calls)):
        out[i].extend(trajs)
    return out


# -- helpers --------------------------------------------------------------------------------
def _policy_path(out: Path, agent: Agent) -> Path:
    return out / (f"{POLICY_STEM}.safetensors" if agent.tensors() else f"{POLICY_STEM}.json")


# -- the training entry point ---------------------------------------------------------------
def train(
    dataset: str | Path,
    agent: str | Agent,
    out: str | Path,
    episodes: int,
    *,
    settings: EnvSettings | None = None,
    seed: int = 0,
    pipeline: str | Path | None = None,
    agent_kwargs: dict[str, Any] | None = None,
    split: str = "test",
    test_fraction: float = DEFAULT_TEST_FRACTION,
    split_seed: int = DEFAULT_SPLIT_SEED,
    workers: int | None = None,
    ray_address: str | None = None,
    checkpoint_every: int = 100,
    resume: bool = False,
    overwrite: bool = False,
    progress: bool = True,
    use_depth: bool = True,
    store_episodes: bool = True,
    validation_fraction: float = 0.0,
    validate_every: int = DEFAULT_VALIDATE_EVERY,
    validation_lambdas: tuple[float, ...] | None = None,
) -> Path:
    """Train `agent` ("pg", "es", "simple"; "random"/"fixed" just play) on the train split of
    a BOP dataset and write the policy, checkpoint, history and learning curve to `out`.

    Returns the policy file. `settings`: the environment's (default `EnvSettings()`; its
    lambda_range is the training distribution of lambda). `split`: the dataset's BOP split folder,
    whose image ids are divided by (`test_fraction`, `split_seed`). `workers`: N > 1 plays the
    episodes as tasks on a local Ray with N workers; `ray_address` joins a running Ray cluster
    instead; neither (or N = 1): in this process, without Ray. `resume=True` continues a run from
    out/checkpoint.safetensors up to `episodes` in total, with the checkpoint's agent
    hyperparameters (`agent_kwargs` are ignored); the dataset, split, pipeline and env settings
    must be the same (lambda_range may change); without it an existing run in `out` is an error
    unless `overwrite`. A stop signal writes everything of the last completed round and raises
    StopRequested (module docstring). `use_depth=False` reads the dataset as RGB-only (its depth
    ignored; an RGB-only dataset is RGB-only anyway): the actions that need depth are masked.
    `store_episodes`: append every episode to out/episodes.sqlite (module docstring).
    `validation_fraction` > 0: hold out that share of the train images and ship the policy with
    the lowest mean validation cost, checked every `validate_every` episodes and at the end at
    `validation_lambdas` (default: the ends of lambda_range and 0.5; learning/validation.py); 0 ships the
    last policy.
    """
    settings = settings or EnvSettings()
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if checkpoint_every < 1:
        raise ValueError(f"checkpoint_every must be >= 1, got {checkpoint_every}")
    if workers is not None and int(workers) < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if not 0.0 <= validation_fraction < 1.0:
        raise ValueError(f"validation_fraction must be in [0, 1), got {validation_fraction}")
    if validate_every < 1:
        raise ValueError(f"validate_every must be >= 1, got {validate_every}")
    name = agent if isinstance(agent, str) else agent.kind
    if name == "oracle":
        raise ValueError("the oracle is a hindsight search (a lower bound for evaluation), it cannot be trained")
    if name not in AGENTS:
        raise ValueError(f"unknown agent {name!r}; agents: {', '.join(AGENTS)}")
    out = Path(out)
    ckpt_path = out / CHECKPOINT
    if not resume and ckpt_path.exists() and not overwrite:
        raise FileExistsError(f"{out} already holds a training run ({CHECKPOINT}): pass resume=True to continue it "
                              "or overwrite=True to start again")
    if resume and not ckpt_path.exists():
        raise FileNotFoundError(f"cannot resume: no checkpoint {ckpt_path}")

    # The split: train on the train image ids only.
    ds = BopDataset(Path(dataset), split=split, use_depth=use_depth)
    train_keys, test_keys = split_image_keys(ds.image_keys(), test_fraction, split_seed)
    val_keys: list[tuple[int, int]] = []
    if validation_fraction > 0:
        train_keys, val_keys = split_validation(train_keys, validation_fraction, split_seed)
    # One environment over the train and validation images; training draws only train episodes.
    recipe = EnvRecipe(str(Path(dataset).resolve()), pipeline_reference(pipeline),
                       tuple(sorted(train_keys + val_keys)), split, settings, use_depth=bool(use_depth))
    env = recipe.make()
    spec = EnvSpec.from_env(env)
    val_set = set(val_keys)
    in_val = [(ek.scene_id, ek.im_id) in val_set for ek in env.source.episodes]
    train_idx = [i for i, v in enumerate(in_val) if not v]
    if not train_idx:
        raise ValueError("no training episodes left after holding out the validation images: "
                         "lower validation_fraction")
    val_lambdas = tuple(float(x) for x in (validation_lambdas or default_lambdas(settings)))
    val_options = validation_episodes([i for i, v in enumerate(in_val) if v], val_lambdas, split_seed) \
        if val_keys else []
    if val_keys and not val_options:
        raise ValueError(f"the validation images {val_keys} hold no usable episodes: raise validation_fraction")
    training_info = {
        "dataset": recipe.dataset, "bop_split": split, "split_seed": int(split_seed),
        "test_fraction": float(test_fraction),
        "train_image_keys": [list(k) for k in train_keys], "test_image_keys": [list(k) for k in test_keys],
        "train_episodes_available": len(train_idx), "env_settings": settings.to_json(), "pipeline": recipe.pipeline,
        "seed": int(seed), "use_depth": bool(use_depth), "validation_fraction": float(validation_fraction),
    }
    if val_keys:
        training_info.update(validation_image_keys=[list(k) for k in val_keys], validation_lambdas=list(val_lambdas),
                             validation_episodes=len(val_options), validate_every=int(validate_every))

    history = new_history()
    rng = np.random.default_rng(seed)
    done = 0
    selection = Selection()
    saved: dict[str, Any] = {}  # a resumed run's recorded extra
    if resume:
        meta, tensors = read_file(ckpt_path)
        check_compatible(meta, spec, ckpt_path)
        if meta["agent"] != name:
            raise PolicyError(f"checkpoint {ckpt_path} is a {meta['agent']!r} run, not {name!r}")
        saved = meta.get("extra", {})
        defaults = {"use_depth": True, "validation_fraction": 0.0}  # runs from before these keys
        for key in ("split_seed", "test_fraction", "dataset", "bop_split", "pipeline", "use_depth",
                    "validation_fraction", "validation_lambdas"):
            now = json.loads(json.dumps(training_info.get(key)))
            if saved.get(key, defaults.get(key)) != now:
                raise PolicyError(f"checkpoint {ckpt_path} was trained with {key}={saved.get(key)!r}, "
                                  f"this run has {now!r}: resume with the same settings")
        try:
            saved_settings = settings_from_policy_meta(meta, f"checkpoint {ckpt_path}")
        except ValueError as exc:
            raise PolicyError(str(exc)) from None
        changed = saved_settings.differences(settings) if saved_settings else ["none recorded"]
        if changed:
            raise PolicyError(f"checkpoint {ckpt_path} was trained with other environment settings "
                              f"({'; '.join(changed)}): resume with the same settings (lambda_range may change)")
        learner = build_agent(meta, tensors, spec, ckpt_path)
        learner.load_checkpoint({k: v for k, v in tensors.items() if k.startswith("train/")},
                                meta.get("train_state", {}))
        trainer = meta.get("trainer", {})
        done = int(trainer.get("episodes_done", 0))
        rng.bit_generator.state = trainer["rng"]
        history = history_from_tensors(tensors)
        selection = Selection.from_checkpoint(tensors, trainer.get("validation"))
    elif isinstance(agent, Agent):
        if agent.spec.action_names != spec.action_names or agent.spec.observation_layout != spec.observation_layout:
            raise ValueError("the agent was built for a different action set or observation layout "
                             "than this environment")
        learner = agent
    else:
        kw = {"seed": seed, **(agent_kwargs or {})}
        learner = make_agent(name, spec, **kw)
    learner.explore = True
    updates = updates_done(history)

    policy_path = _policy_path(out, learner)
    out.mkdir(parents=True, exist_ok=True)

    def save_checkpoint() -> None:
        tensors, state = learner.checkpoint()
        tensors = {**learner.tensors(), **tensors,
                   **{TENSOR_PREFIX + k: v for k, v in history_arrays(history).items()}}
        meta = agent_meta(learner, {**training_info, "episodes": done})
        meta["train_state"] = state
        meta["trainer"] = {"episodes_done": done, "rng": rng.bit_generator.state}
        if val_options:
            best_tensors, meta["trainer"]["validation"] = selection.to_checkpoint()
            tensors.update(best_tensors)
        write_file(ckpt_path, meta, tensors)

    def save_outputs(interrupted: bool) -> None:
        extra = {**training_info, "episodes": done, "interrupted": interrupted}
        shipped, selected = learner, None
        if val_options and selection.best is not None:
            shipped, selected = selection.best_agent(spec, learner), int(selection.best["episode"])
            extra["selected"] = {"episode": selected, "by": SELECTION, "validation": selection.best,
                                 "last": selection.history[-1]}
        save_agent(shipped, policy_path, extra)
        columns = history_arrays(history)
        write_history_csv(columns, out / HISTORY_CSV)
        if val_options:
            write_validation_csv(selection.history, out / VALIDATION_CSV)
        if done:
            plot_learning_curve(columns, out / CURVE, title=f"{name} on {Path(recipe.dataset).name}",
                                validation=selection.history if val_options else None, selected=selected,
                                n_actions=spec.n_actions)

    from tqdm import tqdm

    def play_greedy(actor: Agent, options: list[dict[str, Any]], act_seeds: np.ndarray) -> list[Trajectory]:
        return play_round(env, [actor], options, act_seeds[None, :], runner, recipe_ref)[0]

    def validation_due() -> bool:
        """Every `validate_every` episodes (the first round past each multiple) and at the end;
        after a warm start also before the first round (the imitating policy is a candidate)."""
        if not val_options or selection.last_episode == done:
            return False
        if done == 0 and "warm_start" in training_info:
            return True
        return done >= episodes or done // validate_every > max(selection.last_episode, 0) // validate_every

    writer = StoreWriter(out / STORE_NAME, lambda line: _quietly(print, line, file=sys.stderr, flush=True)) \
        if store_episodes else None

    def store_round(trajectories: list[list[Trajectory]], options: list[dict[str, Any]]) -> None:
        for i, per_actor in enumerate(trajectories):
            version = f"train:{out.name}@{done}" + (f"/actor{i}" if len(trajectories) > 1 else "")
            for t, opt in zip(per_actor, options):
                store_episode(writer, t, source="train", agent=name, policy_version=version,
                              dataset=recipe.dataset, episode_seed=opt["episode_seed"])

    # Ray first: ray.init installs its own SIGTERM handler, which the stop signals then replace.
    runner = RayRunner(workers, ray_address) \
        if ray_wanted(workers, ray_address) and (done < episodes or validation_due()) else None
    recipe_ref = runner.put(recipe) if runner is not None else None
    if resume and "warm_start" in saved:
        training_info["warm_start"] = saved["warm_start"]
    elif not resume and getattr(learner, "warm_start", "none") != "none":
        from .warm_start import warm_start

        try:
            with _reproducible_threads(settings):
                training_info["warm_start"] = report = warm_start(learner, env, train_idx, settings, seed,
                                                                  runner=runner, recipe_ref=recipe_ref,
                                                                  progress=progress)
        except BaseException:
            if runner is not None:
                runner.close()
            raise
        if progress:
            _quietly(print, f"warm start: imitated the {report['teacher']} on {report['episodes_demonstrated']} "
                            f"train episodes ({report['imitation_accuracy']:.0%} of its actions) in "
                            f"{report['seconds']:.0f} s", flush=True)
    stops = StopSignals()
    lo, hi = settings.lambda_range
    last_ckpt = done
    bar = tqdm(total=episodes, initial=min(done, episodes), disable=not progress, unit="ep", desc=f"train {name}")
    with stops.installed(), _reproducible_threads(settings):
        try:
            while not stops.received:
                if validation_due():  # before the next round: a check a signal dropped runs on resume
                    try:
                        with stops.interruptible():
                            record = validate(learner, val_options, play_greedy, done)
                    except Interrupted:
                        break
                    except Exception:
                        if stops.received:
                            break
                        if done > last_ckpt:
                            _save_quietly(save_checkpoint)
                        raise
                    best = selection.offer(record, learner)
                    if progress:
                        _quietly(bar.write, f"validation at {done} episodes: mean cost {record['cost']:.3f} s, "
                                            f"success {record['success']:.3f}, first pick {record['first_pick']:.3f}"
                                            + (" (best so far)" if best else ""))
                if done >= episodes:
                    break
                round_start = rng.bit_generator.state  # a dropped round is drawn again on resume
                actors = learner.actors()
                k = learner.episodes_per_actor
                options = [{"episode": train_idx[int(rng.integers(len(train_idx)))],
                            "lambda": float(rng.uniform(lo, hi)), "episode_seed": int(rng.integers(2**31))}
                           for _ in range(k)]
                act_seeds = rng.integers(2**31, size=(len(actors), k))
                try:
                    with stops.interruptible():  # only the episodes are dropped by a signal
                        trajectories = play_round(env, actors, options, act_seeds, runner, recipe_ref)
                except Interrupted:
                    rng.bit_generator.state = round_start
                    break
                except Exception:
                    rng.bit_generator.state = round_start
                    if stops.received:  # a worker ended by a signal to the whole process group
                        break
                    if done > last_ckpt:  # keep the rounds since the last checkpoint, then fail
                        _save_quietly(save_checkpoint)
                    raise
                # A learning step is never half done: signals from here on are only recorded.
                figures = learner.update(trajectories) or {}
                if writer is not None:
                    store_round(trajectories, options)
                updates += 1
                n_new = record_round(history, trajectories, figures, updates)
                done += n_new
                recent = slice(-100, None)
                _quietly(bar.update, n_new)
                _quietly(bar.set_postfix, ret=f"{np.mean(history['return'][recent]):.2f}",
                         success=f"{np.mean(history['success'][recent]):.2f}")
                if done - last_ckpt >= checkpoint_every:
                    save_checkpoint()
                    last_ckpt = done
        finally:
            _quietly(bar.close)
            if runner is not None:
                runner.close()
            if writer is not None:
                writer.close()
                if progress:
                    _quietly(print, f"episode store: {writer.summary()}", flush=True)
        # Signals that arrive now are recorded only: the files are written whole.
        interrupted = bool(stops.received)
        save_checkpoint()
        save_outputs(interrupted)
        if interrupted:  # raised while the handlers still record signals: a further Ctrl-C cannot replace it
            signum = stops.received[0]
            _quietly(print, f"stopped by {signal_name(signum)} after {done} episodes: wrote {policy_path}, "
                            f"{out / 'history.csv'} and {ckpt_path}", flush=True)
            raise StopRequested(signum, f"training stopped by {signal_name(signum)} after {done} episodes")
    return policy_path


def _quietly(func: Any, *args: Any, **kw: Any) -> None:
    """Progress output: a terminal that hung up (SIGHUP) must not stop the save."""
    try:
        func(*args, **kw)
    except OSError:
        pass


def _save_quietly(save: Any) -> None:
    try:
        save()
    except Exception:  # noqa: BLE001  (the error being raised is the one to report)
        pass


def _reproducible_threads(settings: EnvSettings) -> ContextManager[None]:
    """Cost-table mode: Open3D on one thread in this process while training (open3d_threads),
    so in-process ICP is bitwise reproducible."""
    return open3d_single_thread(settings.time_mode == "cost_table")
