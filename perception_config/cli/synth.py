"""`perception-config synth`: a synthetic BOP dataset."""
from __future__ import annotations

import argparse
from pathlib import Path


def _cmd_synth(args: argparse.Namespace) -> int:
    from ..datasets.synthetic import generate

    generate(
        args.out,
        scenes=args.scenes,
        images_per_scene=args.images_per_scene,
        seed=args.seed,
        models_dir=args.models,
        progress=not args.quiet,
        depth=args.depth,
    )
    print(f"wrote BOP dataset {args.out}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    s = sub.add_parser("synth", help="write a synthetic BOP-format dataset")
    s.add_argument("--out", type=Path, required=True, help="output dataset folder")
    s.add_argument("--scenes", type=int, default=4)
    s.add_argument("--images-per-scene", type=int, default=10)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--models", type=Path, default=None,
                   help="a BOP models/ folder to place instead of the procedural parts")
    s.add_argument("--no-depth", dest="depth", action="store_false",
                   help="write an RGB-only dataset (no depth folders; the same images and annotations)")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=_cmd_synth)
