"""`perception-config evaluate`: compare agents on the test images over noise levels."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..learning.evaluation_best_static import DEFAULT_EPISODES, DEFAULT_MAX_LENGTH
from ..rl.episodes import DEFAULT_TEST_FRACTION
from ..rl.settings import TIME_MODES, EnvSettings
from .args import add_dataset_args, add_ray_args
from .notices import rgb_only_warning, warn


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from ..agents.policy_settings import policy_settings
    from ..learning.evaluation import DEFAULT_LAMBDAS, evaluate
    from ..learning.evaluation_export import format_table

    lambdas = [float(x) for x in args.lambdas.split(",")] if args.lambdas else list(DEFAULT_LAMBDAS)
    # the pipeline evaluate() plays: --pipeline, else the policies', else the default
    pipeline = policy_settings(args.policy, pipeline=args.pipeline).pipeline
    note = rgb_only_warning(args.dataset, pipeline, split=args.split, use_depth=args.use_depth)
    if note:
        warn(note)
    results = evaluate(
        args.dataset, args.policy, lambdas, args.out, episodes_per_lambda=args.episodes, seed=args.seed,
        pipeline=args.pipeline, split_seed=args.split_seed, test_fraction=args.test_fraction,
        include_baselines=not args.no_baselines, progress=not args.quiet, split=args.split, plots=not args.no_plots,
        time_mode=args.time_mode, max_ops=args.max_ops, use_depth=args.use_depth,
        store_episodes=args.store_episodes, workers=args.workers, ray_address=args.ray_address,
        oracle_budget=args.oracle_budget, best_static_length=args.best_static_length,
        best_static_episodes=args.best_static_episodes,
    )
    print(format_table(json.loads(results.read_text())))
    print(f"wrote {results} and the per-episode traces, BOP CSVs and plots in {results.parent}")
    print(f"BOP results for bop_toolkit, with the targets file of the evaluated episodes: {results.parent / 'bop'}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    ev = sub.add_parser("evaluate", help="compare agents on the test images over noise levels (Fig. 5)")
    add_dataset_args(ev)
    ev.add_argument("--out", type=Path, required=True, help="output folder (results.json, plots, BOP CSVs)")
    ev.add_argument("--policy", action="append", default=[], metavar="FILE|AGENT",
                    help="a policy file or an agent name (random, simple, ...); repeatable")
    ev.add_argument("--lambdas", default=None, help="comma-separated noise levels (default 0.1,...,1.0)")
    ev.add_argument("--episodes", type=int, default=None, help="episodes per lambda (default: every test episode)")
    ev.add_argument("--seed", type=int, default=0, help="episode seeds (the same for every agent)")
    ev.add_argument("--pipeline", type=Path, default=None,
                    help="pipeline YAML or shipped name (default, rgb, cell, pick_success; default: the policy's, "
                         "else default)")
    ev.add_argument("--split-seed", type=int, default=None,
                    help="train/test split seed (default: the policy's, else 0)")
    ev.add_argument("--test-fraction", type=float, default=None,
                    help=f"test share of the images (default: the policy's, else {DEFAULT_TEST_FRACTION})")
    ev.add_argument("--time-mode", choices=TIME_MODES, default=None,
                    help="measured wall time or the blocks' cost table (default: the policy's, else measured)")
    ev.add_argument("--max-ops", type=int, default=None,
                    help=f"operations per episode (default: the policy's, else {EnvSettings().max_ops})")
    ev.add_argument("--split", default="test", help="BOP split folder of the dataset")
    ev.add_argument("--no-baselines", action="store_true",
                    help="skip the oracle, fixed pipelines, best static pipeline and random agent")
    ev.add_argument("--oracle-budget", type=int, default=None, metavar="N",
                    help="the oracle's operator calls per episode (default 2000; fewer where actions are "
                         "generator searches, e.g. the cell pipeline)")
    ev.add_argument("--best-static-length", type=int, default=DEFAULT_MAX_LENGTH, metavar="N",
                    help="the best static pipeline's search: sequences of up to N actions with a pick, each played "
                         f"as a fixed pipeline on the train images (default {DEFAULT_MAX_LENGTH})")
    ev.add_argument("--best-static-episodes", type=int, default=DEFAULT_EPISODES, metavar="N",
                    help=f"train episodes of that search per lambda (default {DEFAULT_EPISODES}; 0: no best_static)")
    ev.add_argument("--no-plots", action="store_true")
    ev.add_argument("--no-episode-store", dest="store_episodes", action="store_false",
                    help="do not append the episodes to OUT/episodes.sqlite")
    add_ray_args(ev, "the (agent, lambda) episodes")
    ev.add_argument("--quiet", action="store_true", help="no progress bar")
    ev.set_defaults(func=_cmd_evaluate)
