"""`perception-config synth`: a synthetic BOP dataset."""
from __future__ import annotations

import argparse
from pathlib import Path


def _cmd_synth(args: argparse.Namespace) -> int:
    from ..datasets.realism import Realism
    from ..datasets.synthetic import camera_from, generate

    size: dict = {}
    if args.camera is not None:
        try:
            K, width, height = camera_from(args.camera)
        except ValueError as e:
            print(f"perception-config synth: --camera: {e}")
            return 2
        size = {"K": K, "width": width, "height": height}
    generate(
        args.out,
        scenes=args.scenes,
        images_per_scene=args.images_per_scene,
        seed=args.seed,
        models_dir=args.models,
        progress=not args.quiet,
        depth=args.depth,
        realism=Realism() if args.realism else None,
        **size,
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
    s.add_argument("--camera", type=Path, default=None, metavar="PATH",
                   help="the camera of the images: a BOP camera.json or a BOP dataset folder (e.g. the real "
                        "dataset whose models --models places; default: Linemod's intrinsics at 640x480)")
    s.add_argument("--realism", action="store_true",
                   help="add the errors of a real cell, drawn per image and object: depth offset, scale and "
                        "warp, depth-to-colour misregistration, noise level, annotation error "
                        "(datasets/realism.py): training data for a verifier meant for real frames")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=_cmd_synth)
