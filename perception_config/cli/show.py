"""`perception-config show`: a frame with its ground-truth models overlaid, as a PNG."""
from __future__ import annotations

import argparse
from pathlib import Path

from .args import add_dataset_args


def _cmd_show(args: argparse.Namespace) -> int:
    from ..datasets.show import show_frame

    out = show_frame(args.dataset, args.out, scene_id=args.scene, im_id=args.image, split=args.split,
                     use_depth=args.use_depth)
    print(f"wrote {out}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    sh = sub.add_parser("show", help="write a PNG of a frame with the ground-truth models overlaid")
    add_dataset_args(sh)
    sh.add_argument("--out", type=Path, required=True)
    sh.add_argument("--scene", type=int, default=None, help="scene id (default: the first)")
    sh.add_argument("--image", type=int, default=None, help="image id (default: the first)")
    sh.add_argument("--split", default="test")
    sh.set_defaults(func=_cmd_show)
