"""`perception-config bag write | info`: BOP scenes to MCAP, and a bag's summary."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from .args import add_dataset_args


def _cmd_bag_write(args: argparse.Namespace) -> int:
    from ..datasets.bag import write_bag

    n = write_bag(args.dataset, args.out, split=args.split, rate_hz=args.rate, progress=not args.quiet,
                  use_depth=args.use_depth)
    print(f"wrote {n} frames to {args.out}")
    return 0


def _cmd_bag_info(args: argparse.Namespace) -> int:
    from ..datasets.bag import bag_info

    info = bag_info(args.file)
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    for key, value in info.items():
        if key == "topics":
            print("topics:")
            for t in value:
                comp = f"  {t['compression']}-compressed" if t["compression"] != "none" else ""
                print(f"  {t['topic']:<48} {t['type']:<36} {t['count']:>6} msgs{comp}")
        elif key == "compression":
            print(f"compression: chunks {', '.join(value['chunk'])}; messages {', '.join(value['message'])}")
        elif key == "frame_topics":
            print("would read frames from:" + (f" ({value['layout']} layout)" if "layout" in value else ""))
            for role in ("color", "depth", "camera_info", "ground_truth", "frame_info"):
                shown = value.get(role) or ("none (RGB-only)" if role == "depth" else None)
                if shown:
                    print(f"  {role:<13} {shown}")
        elif key == "frame_topics_error":
            print(f"cannot choose the frame topics: {value}")
        elif key == "camera_layouts":
            print("complete camera layouts (pick one with read_bag(color_topic=, depth_topic=, camera_info_topic=)):")
            for lay in value:
                print(f"  {lay['driver']}: {lay['color']}, {lay['depth']}, {lay['camera_info']}")
        else:
            print(f"{key}: {value}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    b = sub.add_parser("bag", help="record BOP scenes to MCAP and inspect rosbag2 bags (MCAP or sqlite3)")
    bsub = b.add_subparsers(dest="bag_command", required=True)
    bw = bsub.add_parser("write", help="record a BOP dataset as a rosbag2-compatible MCAP file")
    add_dataset_args(bw)
    bw.add_argument("--out", type=Path, required=True)
    bw.add_argument("--split", default="test")
    bw.add_argument("--rate", type=float, default=10.0, help="frames per second on the recording's clock")
    bw.add_argument("--quiet", action="store_true")
    bw.set_defaults(func=_cmd_bag_write)
    bi = bsub.add_parser("info", help="summarise a bag: topics, types, counts, compression, and the colour, depth "
                         "and camera_info topics it would read (or the candidates when it cannot choose)")
    bi.add_argument("file", type=Path, help=".mcap or .db3 file, or a rosbag2 bag directory")
    bi.add_argument("--json", action="store_true", help="print the summary as JSON")
    bi.set_defaults(func=_cmd_bag_info)
