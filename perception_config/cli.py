"""The `perception-config` command: one subcommand per job, heavy imports deferred to the job."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path


def _cmd_synth(args: argparse.Namespace) -> int:
    from .datasets.synthetic import generate

    generate(
        args.out,
        scenes=args.scenes,
        images_per_scene=args.images_per_scene,
        seed=args.seed,
        models_dir=args.models,
        progress=not args.quiet,
    )
    print(f"wrote BOP dataset {args.out}")
    return 0


def _cmd_bag_write(args: argparse.Namespace) -> int:
    from .datasets.bag import write_bag

    n = write_bag(args.dataset, args.out, split=args.split, rate_hz=args.rate, progress=not args.quiet)
    print(f"wrote {n} frames to {args.out}")
    return 0


def _cmd_bag_info(args: argparse.Namespace) -> int:
    from .datasets.bag import bag_info

    info = bag_info(args.file)
    for key, value in info.items():
        if key == "topics":
            print("topics:")
            for t in value:
                print(f"  {t['topic']:<32} {t['type']:<32} {t['count']:>6} msgs")
        else:
            print(f"{key}: {value}")
    return 0


def _cmd_show(args: argparse.Namespace) -> int:
    from .datasets.show import show_frame

    out = show_frame(args.dataset, args.out, scene_id=args.scene, im_id=args.image, split=args.split)
    print(f"wrote {out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="perception-config", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("synth", help="write a synthetic BOP-format dataset")
    s.add_argument("--out", type=Path, required=True, help="output dataset folder")
    s.add_argument("--scenes", type=int, default=4)
    s.add_argument("--images-per-scene", type=int, default=10)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--models", type=Path, default=None, help="a BOP models/ folder to place instead of the procedural parts")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=_cmd_synth)

    b = sub.add_parser("bag", help="record BOP scenes to MCAP and inspect MCAP files")
    bsub = b.add_subparsers(dest="bag_command", required=True)
    bw = bsub.add_parser("write", help="record a BOP dataset as a rosbag2-compatible MCAP file")
    bw.add_argument("--dataset", type=Path, required=True)
    bw.add_argument("--out", type=Path, required=True)
    bw.add_argument("--split", default="test")
    bw.add_argument("--rate", type=float, default=10.0, help="frames per second on the recording's clock")
    bw.add_argument("--quiet", action="store_true")
    bw.set_defaults(func=_cmd_bag_write)
    bi = bsub.add_parser("info", help="summarise an MCAP file")
    bi.add_argument("file", type=Path)
    bi.set_defaults(func=_cmd_bag_info)

    sh = sub.add_parser("show", help="write a PNG of a frame with the ground-truth models overlaid")
    sh.add_argument("--dataset", type=Path, required=True)
    sh.add_argument("--out", type=Path, required=True)
    sh.add_argument("--scene", type=int, default=None, help="scene id (default: the first)")
    sh.add_argument("--image", type=int, default=None, help="image id (default: the first)")
    sh.add_argument("--split", default="test")
    sh.set_defaults(func=_cmd_show)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (FileNotFoundError, ValueError, KeyError) as exc:
        # Bad input: one clear line naming what was wrong, no traceback.
        print(f"perception-config {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
