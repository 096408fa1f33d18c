"""`perception-config study`: train an agent with N seeds, evaluate them all next to the baselines
on the same test episodes, and report the comparison with bootstrap intervals; `--verdict
EVAL_DIR` prints the one-line verdict of an evaluation folder's agent instead."""
from __future__ import annotations

import argparse
from pathlib import Path

from ..util.stop_signals import arm_interrupt_once
from .args import add_ray_args
from .notices import rgb_only_warning, warn


def _cmd_study(args: argparse.Namespace) -> int:
    if args.verdict is not None:
        from ..learning.study_report import verdict

        print(verdict(args.verdict, args.verdict_agent))
        return 0
    if args.dataset is None or args.out is None:
        raise ValueError("--dataset and --out are needed (or --verdict EVAL_DIR)")
    from ..learning.study import STUDY_JSON, STUDY_PNG, run_study
    from ..learning.study_report import format_table
    from .train import recipe_params

    # As train: Ctrl-C stops the study with its work saved, also when started with SIGINT ignored.
    arm_interrupt_once()
    try:
        lambdas = [float(x) for x in args.lambdas.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"--lambdas: expected comma-separated numbers, got {args.lambdas!r}") from None
    note = rgb_only_warning(args.dataset, args.pipeline, use_depth=args.use_depth)
    if note:  # once for the study, not once per seed's training and evaluation
        warn(note)
    study = run_study(
        args.dataset, args.out, pipeline=args.pipeline, agent=args.agent, seeds=args.seeds, seed=args.seed,
        restarts=args.restarts, episodes=args.episodes, eval_episodes=args.eval_episodes, lambdas=lambdas,
        workers=args.workers, ray_address=args.ray_address,
        cost_table=args.cost_table, validation_fraction=args.validation_fraction,
        agent_kwargs=recipe_params(args.agent, args.agent_param, args.pipeline), eval_seed=args.eval_seed,
        use_depth=args.use_depth,
        evaluate_kwargs={k: v for k, v in (("best_static_length", args.best_static_length),
                                           ("best_static_episodes", args.best_static_episodes)) if v is not None},
        progress=not args.quiet, command=_command(args))
    print(format_table(study))
    print(f"wrote {Path(args.out) / STUDY_JSON} and {Path(args.out) / STUDY_PNG}")
    return 0


def _command(args: argparse.Namespace) -> list[str]:
    """The study's command line with every option's value spelled out (defaults too), to repeat it."""
    cmd = ["perception-config", "study", "--dataset", str(args.dataset), "--out", str(args.out)]
    for name in ("pipeline", "agent", "seeds", "seed", "restarts", "episodes", "eval_episodes", "eval_seed", "lambdas",
                 "cost_table", "validation_fraction", "best_static_length", "best_static_episodes", "workers",
                 "ray_address"):
        value = getattr(args, name)
        if value is not None:
            cmd += [f"--{name.replace('_', '-')}", str(value)]
    for item in args.agent_param or []:
        cmd += ["--agent-param", item]
    return cmd + ([] if args.use_depth else ["--no-depth"])


def add_parser(sub: argparse._SubParsersAction) -> None:
    from ..learning.study import (
        DEFAULT_EPISODES,
        DEFAULT_EVAL_EPISODES,
        DEFAULT_LAMBDAS,
        DEFAULT_RESTARTS,
        DEFAULT_SEEDS,
        DEFAULT_VALIDATION_FRACTION,
    )

    p = sub.add_parser(
        "study", help="train N seeds, evaluate them next to the baselines, compare with confidence intervals",
        description="Calibrates the cost model once (OUT/cost_model.json, unless --cost-table), trains the seeds "
                    "--seed .. --seed+N-1 with it in OUT/seed-<s>/, evaluates every policy and every baseline "
                    "(oracle, fixed pipelines, random, best_static) on the same test episodes per lambda in "
                    "OUT/evaluation/, and writes OUT/study.json and OUT/study.png and prints a table and one verdict "
                    "per lambda: in how many seeds the agent beats best_static (lower mean episode cost, success "
                    "not lower; the best fixed pipeline when the evaluation has no best_static), the paired cost "
                    "difference and the time ratio to the oracle, with 95 % percentile bootstrap intervals. "
                    "Resumable: a seed whose policy is complete is not trained again, a seed stopped midway resumes "
                    "from its checkpoint, and a finished evaluation of the same policies is kept; so a study stopped "
                    "by Ctrl-C (SIGINT), SIGTERM or SIGHUP continues where it stopped when the same command is run "
                    "again. Exit codes: 0 done, 2 bad input, 130 SIGINT, 143 SIGTERM, 129 SIGHUP. "
                    "--verdict EVAL_DIR instead prints one line for an agent of any evaluation folder against "
                    "best_static and the oracle, with intervals.")
    p.add_argument("--dataset", type=Path, default=None, help="BOP dataset folder (needed unless --verdict)")
    p.add_argument("--no-depth", dest="use_depth", action="store_false",
                   help="read the dataset as RGB-only (its depth images ignored)")
    p.add_argument("--out", type=Path, default=None,
                   help="study folder: cost_model.json, seed-<s>/, evaluation/, study.json, study.png")
    p.add_argument("--pipeline", type=Path, default=None,
                   help="pipeline YAML or shipped name (default, rgb, cell, pick_success; default: default)")
    p.add_argument("--agent", choices=("pg", "es", "simple"), default="pg")
    p.add_argument("--seeds", type=int, default=DEFAULT_SEEDS, metavar="N", help=f"seeds trained ({DEFAULT_SEEDS})")
    p.add_argument("--seed", type=int, default=0, metavar="S0", help="the first seed (0)")
    p.add_argument("--restarts", type=int, default=DEFAULT_RESTARTS, metavar="R",
                   help="runs per seed (training seeds s, s+1000, ...), the one of lowest validation cost being "
                        f"the seed's policy, as `train --seeds R` ships ({DEFAULT_RESTARTS})")
    p.add_argument("--episodes", type=int, default=DEFAULT_EPISODES, metavar="E",
                   help=f"training episodes per seed ({DEFAULT_EPISODES})")
    p.add_argument("--eval-episodes", type=int, default=DEFAULT_EVAL_EPISODES, metavar="M",
                   help=f"test episodes per lambda, the same for every agent ({DEFAULT_EVAL_EPISODES})")
    p.add_argument("--eval-seed", type=int, default=0, help="the evaluation's episode seeds (0)")
    p.add_argument("--lambdas", default=",".join(f"{x:g}" for x in DEFAULT_LAMBDAS),
                   help=f"comma-separated noise levels evaluated ({','.join(f'{x:g}' for x in DEFAULT_LAMBDAS)})")
    p.add_argument("--cost-table", default=None, metavar="FILE|blocks",
                   help="the cost model every seed is charged (a `perception-config calibrate` output), or `blocks` "
                        "for the blocks' default costs; default: calibrated once on the train images into "
                        "OUT/cost_model.json (kept for the next run of the study)")
    p.add_argument("--validation-fraction", type=float, default=DEFAULT_VALIDATION_FRACTION, metavar="F",
                   help="each seed ships its policy of lowest validation cost on this held-out share of the train "
                        f"images, as train --validation-fraction ({DEFAULT_VALIDATION_FRACTION})")
    p.add_argument("--agent-param", action="append", metavar="KEY=VALUE",
                   help="an agent hyper-parameter (repeatable), as train's")
    p.add_argument("--best-static-length", type=int, default=None, metavar="N",
                   help="the best static pipeline's search in the evaluation: sequences of up to N actions (default: "
                        "evaluate's)")
    p.add_argument("--best-static-episodes", type=int, default=None, metavar="N",
                   help="train episodes of that search per lambda (default: evaluate's; 0: no best_static, the "
                        "best fixed pipeline is the bar)")
    add_ray_args(p, "each seed's training rounds and the evaluation")
    p.add_argument("--verdict", type=Path, default=None, metavar="EVAL_DIR",
                   help="only print the verdict line of an evaluation folder (results.json + episodes.jsonl): its "
                        "learned agent against best_static and the oracle over all its lambdas")
    p.add_argument("--verdict-agent", default=None, metavar="NAME",
                   help="the agent of --verdict (default: the evaluation's only learned agent)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=_cmd_study)
