"""`perception-config calibrate`: measure the cost model (seconds per action and object, and per
scoring pass) that training and evaluation charge instead of wall time."""
from __future__ import annotations

import argparse
from pathlib import Path

from ..rl.settings import CALIBRATION_EPISODES
from .args import add_dataset_args, one_core


def _cmd_calibrate(args: argparse.Namespace) -> int:
    one_core()
    from ..bench.calibration import calibrate, write_cost_model
    from ..datasets.bop import BopDataset
    from ..rl.episodes import split_image_keys

    ds = BopDataset(args.dataset, use_depth=args.use_depth)
    keys = ds.image_keys()
    if not args.all_images:  # the train images of the split training uses: the test images stay unseen
        keys, _ = split_image_keys(keys, args.test_fraction, args.split_seed)
    model = calibrate(ds, args.pipeline, keys, episodes=args.episodes, seed=args.seed, use_depth=args.use_depth,
                      progress=not args.quiet)
    write_cost_model(model, args.out)
    print(format_cost_model(model))
    print(f"wrote {args.out}: pass it to train / evaluate / study as --cost-table {args.out}")
    return 0


def format_cost_model(model: dict) -> str:
    """The pooled entries of a cost model (one per action, the scoring pass), in ms."""
    table = model["cost_table"]
    rows = [(k, v) for k, v in table.items() if "@" not in k]
    objs = sorted({k.rsplit("@", 1)[1] for k in table if "@" in k}, key=lambda x: (len(x), x))
    lines = [f"cost model ({model['episodes']} episodes, {model['measured_seconds']} s, load "
             f"{model['machine']['load_1min']}): ms per call, median over {len(objs)} objects' calls"]
    lines += [f"  {k:<34} {1000 * v:8.1f}" for k, v in rows]
    return "\n".join(lines)


def add_parser(sub: argparse._SubParsersAction) -> None:
    from ..rl.episodes import DEFAULT_SPLIT_SEED, DEFAULT_TEST_FRACTION

    p = sub.add_parser(
        "calibrate", help="measure the cost model: seconds per action and object on this machine",
        description="Times every action of the pipeline (the block, then the scoring pass) on episodes of the "
                    "dataset's train images and writes the medians per action and object as a cost table. train "
                    "calibrates by itself unless given one; calibrate once and pass --cost-table FILE to runs that "
                    "must repeat bit for bit or share one model (seeds of a study).")
    add_dataset_args(p)
    p.add_argument("--out", type=Path, required=True, help="the cost model JSON to write")
    p.add_argument("--pipeline", type=Path, default=None,
                   help="pipeline YAML or shipped name (default, rgb, cell, pick_success; default: default)")
    p.add_argument("--episodes", type=int, default=CALIBRATION_EPISODES,
                   help=f"episodes timed ({CALIBRATION_EPISODES})")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--test-fraction", type=float, default=DEFAULT_TEST_FRACTION,
                   help="share of image ids held out for evaluation, never timed")
    p.add_argument("--split-seed", type=int, default=DEFAULT_SPLIT_SEED)
    p.add_argument("--all-images", action="store_true", help="time episodes of every image, test images too")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_cmd_calibrate)
