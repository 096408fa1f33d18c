"""`perception-config fit-score`: fit the learned pick-success score."""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ..rl.episodes import DEFAULT_SPLIT_SEED, DEFAULT_TEST_FRACTION
from .args import one_core

CROP_EPOCHS = 12  # --crops: passes over the fit images' hypotheses


def _cmd_fit_score(args: argparse.Namespace) -> int:
    one_core()
    from ..learning.pick_success_data import collect_candidate_rows, collect_step_rows, featurise, load_step_rows
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
                                 progress=not args.quiet, image_keys=keys, pipeline=args.pipeline)
        if args.candidates:
            from ..datasets.bop import BopDataset

            pool = keys if keys is not None else BopDataset(args.dataset).image_keys()
            pick = np.random.default_rng(args.seed).permutation(len(pool))[:args.candidates]
            rows += collect_candidate_rows(args.dataset, args.candidates_pipeline, seed=args.seed,
                                           image_keys=[tuple(pool[i]) for i in sorted(pick)], progress=not args.quiet)
        source = {"dataset": str(args.dataset), "episodes": args.episodes, "lambdas": lambdas, "seed": args.seed,
                  "max_steps": args.max_steps, "policy": "random (masked)", "pipeline": args.pipeline,
                  "candidates": args.candidates_pipeline if args.candidates else None,
                  "images": "all" if keys is None else {"train_of_split": [args.split_seed, args.test_fraction],
                                                        "image_keys": [list(k) for k in keys]}}
    source["command"] = " ".join(["perception-config fit-score", *(_argv_of(args))])
    frames = args.frames
    if frames is None and args.store is not None and (Path(args.store).parent / "frames").is_dir():
        frames = Path(args.store).parent / "frames"  # a configurator's learn_dir: its kept frames
    models = args.models if args.models is not None else (
        Path(args.dataset) / "models" if args.dataset is not None else None)
    table = featurise(rows, dataset=args.dataset if args.store is not None else None, progress=not args.quiet,
                      frames_dir=frames, models_dir=models, crops=args.crops, symmetries=args.symmetries)
    hidden = tuple(int(x) for x in (args.hidden or ("64" if args.crops else "32,16")).split(",") if x.strip())
    epochs = args.epochs if args.epochs is not None else (CROP_EPOCHS if args.crops else 300)
    base = None
    if args.recalibrate is not None:
        from ..blocks.pick_success import load_model

        base = load_model(str(args.recalibrate))
        source["recalibrated"] = str(args.recalibrate)
    if base is not None and base.uses_crop and not args.crops:
        raise ValueError(f"{args.recalibrate} has a crop branch: recalibrate it with --crops")
    metrics = fit_score(table, args.out, hidden=hidden, epochs=epochs, seed=args.seed, source=source, base=base,
                        progress=not args.quiet)
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
        out += ["--pipeline", str(args.pipeline)] if args.pipeline is not None else []
        out += ["--candidates", str(args.candidates), "--candidates-pipeline", str(args.candidates_pipeline)
                ] if args.candidates else []
        out += ["--all-images"] if args.all_images else ["--split-seed", str(args.split_seed), "--test-fraction",
                                                         str(args.test_fraction)]
    if args.recalibrate is not None:
        out += ["--recalibrate", str(args.recalibrate)]
    out += ["--crops"] if args.crops else []
    out += ["--symmetries", args.symmetries] if args.symmetries != "declared" else []
    out += ["--hidden", args.hidden] if args.hidden is not None else []
    out += ["--epochs", str(args.epochs)] if args.epochs is not None else []
    return out + ["--seed", str(args.seed), "--out", str(args.out)]


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
    fs.add_argument("--pipeline", default=None,
                    help="--dataset: the pipeline whose actions the played episodes take (default: the default one)")
    fs.add_argument("--candidates", type=int, default=0, metavar="N",
                    help="--dataset: add the ranked candidates (the first 8) of the ground-truth-free generators of "
                         "--candidates-pipeline on every object of N of the images played (drawn by --seed): their "
                         "mistakes (flips, a neighbouring part) are what a verifier must learn to refuse; ~1 s a "
                         "generator and object")
    fs.add_argument("--candidates-pipeline", default="cell", help="whose generators and parameters (default: cell)")
    fs.add_argument("--crops", action="store_true",
                    help="also look at each hypothesis' rendered-against-observed crop (a small CNN beside the "
                         "features; vision/verifier_crop.py): the verifier for real frames")
    fs.add_argument("--symmetries", choices=("declared", "derived"), default="declared",
                    help="label against the symmetries the models declare (the simulated pick's), or 'derived': "
                         "where a model declares none, those of its surface (a flip of a nearly symmetric box is "
                         "right: for a cell's real parts)")
    fs.add_argument("--hidden", default=None, help="hidden layer widths of the MLP (default 32,16; with --crops 64)")
    fs.add_argument("--epochs", type=int, default=None,
                    help=f"full-batch Adam steps (default 300); with --crops passes over the data "
                         f"(default {CROP_EPOCHS})")
    fs.add_argument("--seed", type=int, default=0)
    fs.add_argument("--out", type=Path, required=True, help="folder for the model, reliability.png, metrics.json")
    fs.add_argument("--quiet", action="store_true", help="no progress bars")
    fs.set_defaults(func=_cmd_fit_score)
