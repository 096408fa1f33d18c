"""`perception-config train`: train a configuration agent; `agent_params` reads its --agent-param
options."""
from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

# Light imports only (numpy): the command imports the rest it needs.
from ..rl.episodes import DEFAULT_SPLIT_SEED, DEFAULT_TEST_FRACTION, DEFAULT_VALIDATE_EVERY
from ..rl.settings import CALIBRATION_EPISODES, TIME_MODES, EnvSettings
from ..util.stop_signals import arm_interrupt_once
from .args import add_dataset_args, add_ray_args
from .notices import rgb_only_warning, warn

# The recipe that measured best (docs/results/configurator.md): pg with more entropy early and a
# learning rate that halves every 2000 episodes, the validation-best policy shipped; on a pipeline
# that scores the pick-success probability, first a warm start from the best threshold rule
# (searched on 48 train episodes) and then a gentler rate that keeps what the imitation learned
# (800 episodes are enough: the demo's). An --agent-param of the same name wins;
# --validation-fraction 0 ships the last policy.
RECIPES: dict[str, dict[str, Any]] = {"pg": {"entropy_coef": 0.05, "lr_half_life": 2000.0}}
SCORED_RECIPES: dict[str, dict[str, Any]] = {"pg": {"entropy_coef": 0.01, "lr": 0.005, "lr_half_life": 2000.0,
                                                    "warm_start": "threshold", "warm_start_episodes": 48}}
SCORE_OF_SCORED_RECIPES = "pick_success"
LEARNING_AGENTS = ("pg", "es", "simple")
RECIPE_VALIDATION_FRACTION = 0.2


def recipe_params(agent: str, items: list[str] | None, pipeline: str | None = None) -> dict[str, Any]:
    """The agent's hyper-parameters of a command-line run: the recipe (SCORED_RECIPES where the
    pipeline scores the pick-success probability, else RECIPES), then --agent-param."""
    recipes = RECIPES
    if agent in SCORED_RECIPES:
        from ..blocks.pipeline import load_pipeline

        if SCORE_OF_SCORED_RECIPES in load_pipeline(pipeline).score_names:
            recipes = SCORED_RECIPES
    return {**recipes.get(agent, {}), **agent_params(agent, items)}


def _cmd_train(args: argparse.Namespace) -> int:
    from ..learning.training import train

    # Also when started with SIGINT ignored (a background job of a script inherits that): Ctrl-C
    # and `kill -INT` must stop the run with its work saved. SIGHUP ignored (nohup) stays ignored.
    arm_interrupt_once()
    if args.validation_fraction is None:
        args.validation_fraction = RECIPE_VALIDATION_FRACTION if args.agent in LEARNING_AGENTS else 0.0
    lambda_range = tuple(args.lambda_range) if args.lambda_range else None
    settings = EnvSettings().replace(time_mode=args.time_mode, max_ops=args.max_ops, lambda_range=lambda_range,
                                     loop_mask=args.loop_mask, final_pick=args.final_pick,
                                     final_pick_best=args.final_pick_best, converge_tol=args.converge_tol)
    if args.seeds < 1:
        raise ValueError(f"--seeds must be >= 1, got {args.seeds}")
    if args.seeds > 1 and args.validation_fraction <= 0:  # before the cost model is measured
        raise ValueError("seed selection compares the runs' validation costs: validation_fraction must be > 0")
    agent_kwargs = recipe_params(args.agent, args.agent_param, args.pipeline)
    note = rgb_only_warning(args.dataset, args.pipeline, use_depth=args.use_depth)
    if note:  # once, before the calibration and the episodes that play without those actions
        warn(note)
    settings = settings.replace(cost_table=cost_table_for(args, settings))
    common = dict(
        settings=settings, pipeline=args.pipeline, progress=not args.quiet, resume=args.resume,
        test_fraction=args.test_fraction, split_seed=args.split_seed, workers=args.workers,
        ray_address=args.ray_address, overwrite=args.overwrite, checkpoint_every=args.checkpoint_every,
        use_depth=args.use_depth, store_episodes=args.store_episodes, validation_fraction=args.validation_fraction,
        validate_every=args.validate_every, agent_kwargs=agent_kwargs,
    )
    if args.seeds == 1:
        policy = train(args.dataset, args.agent, args.out, args.episodes, seed=args.seed, **common)
    else:
        from ..learning.seed_selection import SEEDS_CSV, train_seeds

        policy = train_seeds(args.dataset, args.agent, args.out, args.episodes,
                             list(range(args.seed, args.seed + args.seeds)), **common)
        print(Path(args.out, SEEDS_CSV).read_text(), end="")
    print(f"policy: {policy}")
    print(f"learning curve: {Path(args.out) / 'learning_curve.png'}")
    return 0


def cost_table_for(args: argparse.Namespace, settings: EnvSettings) -> dict[str, float] | None:
    """The cost table a run charges (cost-table time): --cost-table FILE (a `calibrate` output),
    `blocks` (the blocks' default costs: the same on every machine), else measured now on the
    train images and written to OUT/cost_model.json. A resumed run keeps its own (its checkpoint's,
    else OUT/cost_model.json: the seeds' runs); None with measured time."""
    if settings.time_mode != "cost_table":
        return None
    if args.resume and args.cost_table is None:
        from ..agents.policy_io import read_file
        from ..bench.calibration import read_cost_table
        from ..rl.settings import settings_from_policy_meta

        checkpoint = Path(args.out) / "checkpoint.safetensors"
        if checkpoint.exists():
            saved = settings_from_policy_meta(read_file(checkpoint)[0], f"checkpoint {checkpoint}")
            return dict(saved.cost_table) if saved is not None else None
        if (Path(args.out) / "cost_model.json").exists():
            return read_cost_table(Path(args.out) / "cost_model.json")
        return None  # train() says there is nothing to resume
    if args.cost_table is not None:
        if str(args.cost_table) == "blocks":
            return None
        from ..bench.calibration import read_cost_table

        return read_cost_table(args.cost_table)
    from ..bench.calibration import calibrate, write_cost_model
    from ..datasets.bop import BopDataset
    from ..rl.episodes import split_image_keys
    from .calibrate import format_cost_model

    if (Path(args.out) / "checkpoint.safetensors").exists() and not args.overwrite:
        return None  # train() refuses the run folder; no reason to measure first
    ds = BopDataset(args.dataset, use_depth=args.use_depth)
    train_keys, _ = split_image_keys(ds.image_keys(), args.test_fraction, args.split_seed)
    model = calibrate(ds, args.pipeline, train_keys, episodes=args.calibration_episodes, seed=args.seed,
                      use_depth=args.use_depth, progress=not args.quiet)
    write_cost_model(model, Path(args.out) / "cost_model.json")
    if not args.quiet:
        print(format_cost_model(model))
    return model["cost_table"]


def agent_params(agent: str, items: list[str] | None) -> dict[str, Any]:
    """`--agent-param KEY=VALUE` options as the agent's hyper-parameters: VALUE read as JSON
    (numbers, lists, strings without quotes too), checked against the agent's bounds."""
    from ..agents import AGENTS
    from ..agents.hparams import check_hparams

    out: dict[str, Any] = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--agent-param {item!r}: expected KEY=VALUE, e.g. entropy_coef=0.05")
        try:
            out[key.strip()] = json.loads(text)
        except json.JSONDecodeError:
            out[key.strip()] = text
    if out and agent in AGENTS:
        check_hparams(agent, AGENTS[agent].HPARAM_BOUNDS, out)
    return out


def add_parser(sub: argparse._SubParsersAction) -> None:
    tr = sub.add_parser(
        "train", help="train a configuration agent on the train images of a BOP dataset",
        description="Ctrl-C (SIGINT), SIGTERM and SIGHUP stop the run: the round in flight is dropped, the workers "
                    "are stopped, and the policy, history.csv, learning curve and checkpoint of the last completed "
                    "round are written (a second signal does not abort that). Exit codes: 0 done, 2 bad input, "
                    "130 SIGINT, 143 SIGTERM, 129 SIGHUP; --resume continues the run.")
    add_dataset_args(tr)
    tr.add_argument("--agent", choices=("random", "simple", "pg", "es", "fixed"), default="pg")
    tr.add_argument("--out", type=Path, required=True, help="run folder: policy, checkpoint, learning curve")
    tr.add_argument("--episodes", type=int, default=1000)
    env = EnvSettings()
    tr.add_argument("--lambda-range", type=float, nargs=2, default=None, metavar=("A", "B"),
                    help="lambda of the training episodes ~ U(A, B) "
                         f"(default {env.lambda_range[0]:g} {env.lambda_range[1]:g})")
    tr.add_argument("--seed", type=int, default=0)
    tr.add_argument("--seeds", type=int, default=1, metavar="N",
                    help="train N runs (seeds --seed .. --seed+N-1, in OUT/seed-<s>/) and ship the one of lowest "
                         "validation cost as OUT/policy.safetensors, with OUT/seeds.csv; needs --validation-fraction "
                         "(default 1: one run in OUT)")
    tr.add_argument("--pipeline", type=Path, default=None,
                    help="pipeline YAML, or a shipped pipeline by name: default, rgb, cell, pick_success "
                         "(default: default)")
    tr.add_argument("--time-mode", choices=TIME_MODES, default=None,
                    help=f"what an action costs: cost_table (the cost model, the same whatever the machine's load) or "
                         f"measured wall time (default {env.time_mode})")
    tr.add_argument("--cost-table", default=None, metavar="FILE|blocks",
                    help="the cost model to charge (a `perception-config calibrate` output), or `blocks` for the "
                         "blocks' default costs; default: calibrated on the train images first (about 20 s), written "
                         "to OUT/cost_model.json; a resumed run keeps its own")
    tr.add_argument("--calibration-episodes", type=int, default=CALIBRATION_EPISODES, metavar="N",
                    help=f"train episodes the default calibration times every action on "
                         f"(default {CALIBRATION_EPISODES}, as `perception-config calibrate`)")
    tr.add_argument("--max-ops", type=int, default=None, help=f"operations per episode (default {env.max_ops})")
    tr.add_argument("--no-loop-mask", dest="loop_mask", action="store_false",
                    help="do not mask the actions already taken at the current hypothesis (the loop rule, "
                         "docs/concepts/environment.md): the agent must learn to avoid loops from its observation")
    tr.add_argument("--no-final-pick", dest="final_pick", action="store_false",
                    help="do not make the last of the max-ops operations a pick (the final-pick rule, "
                         "docs/concepts/environment.md)")
    tr.add_argument("--final-pick-best", action="store_true",
                    help="take that last pick at the best hypothesis the episode reached by the pick_success "
                         "score (pipelines that score it; docs/concepts/environment.md)")
    tr.add_argument("--converge-tol", type=float, default=None, metavar="F",
                    help="the loop rule also masks an action whose latest call moved no point of the object by "
                         f"more than F x diameter (default {env.converge_tol:g}: off)")
    tr.add_argument("--test-fraction", type=float, default=DEFAULT_TEST_FRACTION,
                    help="share of image ids held out for evaluation")
    tr.add_argument("--split-seed", type=int, default=DEFAULT_SPLIT_SEED)
    tr.add_argument("--checkpoint-every", type=int, default=100, metavar="N",
                    help="write the checkpoint every N episodes (100); a stop signal always writes it")
    tr.add_argument("--validation-fraction", type=float, default=None, metavar="F",
                    help="hold out this share of the train images (seeded by --split-seed; the test images are "
                         "untouched), check the greedy policy on them every --validate-every episodes and at the "
                         "end, and ship the one with the lowest mean cost (0: the last policy; default "
                         f"{RECIPE_VALIDATION_FRACTION:g} for the learning agents {', '.join(LEARNING_AGENTS)}, "
                         "else 0)")
    tr.add_argument("--validate-every", type=int, default=DEFAULT_VALIDATE_EVERY, metavar="K",
                    help=f"episodes between two validation checks ({DEFAULT_VALIDATE_EVERY})")
    tr.add_argument("--agent-param", action="append", metavar="KEY=VALUE",
                    help="an agent hyper-parameter (repeatable), e.g. pg's entropy_coef=0.02 batch_episodes=16 "
                         "warm_start=threshold gae_lambda=0.8; "
                         "over the recipe's (pg: entropy_coef=0.05 lr_half_life=2000; on a pipeline scoring "
                         "pick_success: warm_start=threshold warm_start_episodes=48 lr=0.005 entropy_coef=0.01 "
                         "lr_half_life=2000) "
                         "(checked against the agent's bounds; ignored by --resume, which keeps the checkpoint's)")
    tr.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    tr.add_argument("--overwrite", action="store_true", help="start again over an existing run in --out")
    tr.add_argument("--no-episode-store", dest="store_episodes", action="store_false",
                    help="do not append the episodes to OUT/episodes.sqlite")
    add_ray_args(tr, "each round's episodes (pg's batch, the ES population; a round waits for its slowest "
                      "episode, so give pg batch_episodes >= 4 N)")
    tr.add_argument("--quiet", action="store_true")
    tr.set_defaults(func=_cmd_train)
