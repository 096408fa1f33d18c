"""`perception-config fit-score`: fit the learned pick-success score."""
from __future__ import annotations

import argparse
from pathlib import Path

from ..rl.episodes import DEFAULT_SPLIT_SEED, DEFAULT_TEST_FRACTION
from .args import one_core


def _cmd_fit_score(args: argparse.Namespace) -> int:
    one_core()
    from ..learning.pick_success_data import collect_step_rows, featurise, load_step_rows
    from ..learning.pick_success_fit import fit_score, format_metrics

    if args.store is None and args.dataset is None:
        raise ValueError("give --store DB (learn from stored episodes) or --dataset DIR (play episodes)")
    if args.store is not None:
        rows = load_step_rows(args.store)
        source = {"store": str(args.store), "rows": len(rows)}
    else:
        lambdas = [float(x) for x in args.lambdas.split(",")]
        keys = None
        if not args.all_images:  # the train images of the split agents are evaluated on
            from ..datasets.bop import BopDataset
            from ..rl.episodes import split_image_keys

            keys, _ = split_image_keys(BopDataset(args.dataset).image_keys(), args.test_fraction, args.split_seed)
        rows = collect_step_rows(args.dataset, args.episodes, lambdas, seed=args.seed, max_steps=args.max_steps,
                                 progress=not args.quiet, image_keys=keys)
        source = {"dataset": str(args.dataset), "episodes": args.episodes, "lambdas": lambdas, "seed": args.seed,
                  "max_steps": args.max_steps, "policy": "random (masked)",
                  "images": "all" if keys is None else {"train_of_split": [args.split_seed, args.test_fraction],
                                                        "image_keys": [list(k) for k in keys]}}
    source["command"] = " ".join(["perception-config fit-score", *(_argv_of(args))])
    frames = args.frames
    if frames is None and args.store is not None and (Path(args.store).parent / "frames").is_dir():
        frames = Path(args.store).parent / "frames"  # a configurator's learn_dir: its kept frames
    models = args.models if args.models is not None else (
        Path(args.dataset) / "models" if args.dataset is not None else None)
    table = featurise(rows, dataset=args.dataset if args.store is not None else None, progress=not args.quiet,
                      frames_dir=frames, models_dir=models)
    hidden = tuple(int(x) for x in args.hidden.split(",") if x.strip())
    base = None
    if args.recalibrate is not None:
        from ..blocks.pick_success import load_model

        base = load_model(str(args.recalibrate))
        source["recalibrated"] = str(args.recalibrate)
    metrics = fit_score(table, args.out, hidden=hidden, epochs=args.epochs, seed=args.seed, source=source, base=base)
    print(format_metrics(metrics))
    print(f"wrote {metrics['model']}, {metrics['reliability']} and {metrics['metrics_file']}")
    return 0


def _argv_of(args: argparse.Namespace) -> list[str]:
    """fit-score's options as given (recorded with the model, so it can be fitted again)."""
    out = ["--store", str(args.store)] if args.store is not None else []
    if args.dataset is not None:
        out += ["--dataset", str(args.dataset)]
    for flag, value in (("--frames", args.frames), ("--models", args.models)):
        if value is not None:
            out += [flag, str(value)]
    if args.store is None:
        out += ["--episodes", str(args.episodes), "--lambdas", args.lambdas, "--max-steps", str(args.max_steps)]
        out += ["--all-images"] if args.all_images else ["--split-seed", str(args.split_seed), "--test-fraction",
                                                         str(args.test_fraction)]
    if args.recalibrate is not None:
        out += ["--recalibrate", str(args.recalibrate)]
    return out + ["--hidden", args.hidden, "--epochs", str(args.epochs), "--seed", str(args.seed),
                  "--out", str(args.out)]


def add_parser(sub: argparse._SubParsersAction) -> None:
    fs = sub.add_parser(
        "fit-score", help="fit the learned pick-success score (block pick_success) from stored or played episodes",
        description="Fit the pick_success model: features of every hypothesis of the episodes (the episode store's "
                    "step rows, or episodes played here with a random masked policy), labelled by the pick "
                    "criterion against the ground truth; a small MLP, Platt-calibrated on held-out images; "
                    "prints AUC, Brier and ECE on the held-out test images.")
    fs.add_argument("--store", type=Path, help="an episode store (SQLite) to learn from")
    fs.add_argument("--dataset", type=Path, help="a BOP dataset to play episodes on; with --store: the dataset "
                                                 "folder the store's rows refer to (default: the path they name)")
    fs.add_argument("--frames", type=Path, default=None,
                    help="with --store: the frames the configurator kept (store/frames.py), for its estimates' rows "
                         "(default: frames/ beside the store, a learn_dir's); labelled by their ground truth, else "
                         "by the robot's reported pick outcomes")
    fs.add_argument("--models", type=Path, default=None,
                    help="the models folder of the kept frames' objects (default: the --dataset's models/)")
    fs.add_argument("--episodes", type=int, default=1500, help="episodes to play (--dataset)")
    fs.add_argument("--lambdas", default="0.1,0.3,0.5,0.7,1.0", help="noise levels of the played episodes")
    fs.add_argument("--split-seed", type=int, default=DEFAULT_SPLIT_SEED,
                    help="--dataset: play the train images of this train/test split (train's and evaluate's), so "
                         "the images agents are evaluated on stay unseen by the score")
    fs.add_argument("--test-fraction", type=float, default=DEFAULT_TEST_FRACTION, help="of that split")
    fs.add_argument("--all-images", action="store_true", help="--dataset: play every image, the test images too")
    fs.add_argument("--max-steps", type=int, default=8, help="actions per played episode at most")
    fs.add_argument("--recalibrate", metavar="MODEL", default=None,
                    help="keep this model's network, fit only its calibration to these episodes (e.g. a real camera "
                         "or cell's); 'pick_success' is the shipped one")
    fs.add_argument("--hidden", default="32,16", help="hidden layer widths of the MLP")
    fs.add_argument("--epochs", type=int, default=300, help="full-batch Adam steps")
    fs.add_argument("--seed", type=int, default=0)
    fs.add_argument("--out", type=Path, required=True, help="folder for the model, reliability.png, metrics.json")
    fs.add_argument("--quiet", action="store_true", help="no progress bars")
    fs.set_defaults(func=_cmd_fit_score)
