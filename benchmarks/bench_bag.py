"""Benchmark MCAP bag throughput for 640x480 RGB-D frames: writing (Frames -> bag) and reading
(bag -> Frames, the replay path; target >= 30 frames/s), plus raw message iteration (what a
replay node publishing serialized messages does).

    python benchmarks/bench_bag.py [--frames 150] [--out bench_bag.json]

Frames are the real LM-O test frame in ../shared/data/lmo when present (real image content,
so compression behaves as on real data), each with a little per-frame noise so chunks do not
compress to nothing; otherwise procedural images. One core (OMP_NUM_THREADS=1).
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from perception_config.core.scene import Frame  # noqa: E402
from perception_config.datasets.bag import iter_messages, read_bag, write_frames  # noqa: E402
from perception_config.util.atomic_file import atomic_write  # noqa: E402

LMO = REPO.parent / "shared" / "data" / "lmo"
W, H = 640, 480


def base_frame() -> tuple[str, Frame]:
    if (LMO / "test").is_dir():
        from perception_config.datasets.bop import BopDataset

        ds = BopDataset(LMO)
        return "LM-O real frame", ds.load_frame(*ds.image_keys()[0], with_models=False)
    yy, xx = np.mgrid[0:H, 0:W]
    rgb = np.stack([(xx * 255 // W), (yy * 255 // H), ((xx + yy) % 256)], -1).astype(np.uint8)
    depth = (0.6 + 0.3 * np.sin(xx / 40.0) * np.cos(yy / 30.0)).astype(np.float32)
    depth[(xx // 16 + yy // 16) % 7 == 0] = np.nan
    K = np.array([[572.4, 0, 325.3], [0, 573.6, 242.0], [0, 0, 1]])
    return "procedural frame", Frame(rgb, depth, K)


def frames(base: Frame, n: int, seed: int = 0) -> list[Frame]:
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        rgb = np.clip(base.rgb.astype(np.int16) + rng.integers(-2, 3, base.rgb.shape), 0, 255).astype(np.uint8)
        depth = base.depth + rng.normal(0, 0.001, base.depth.shape).astype(np.float32)
        out.append(Frame(rgb, depth, base.K, scene_id=1, im_id=i, objects=base.objects))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--out", type=Path, default=None, help="write the figures as JSON here")
    args = ap.parse_args()

    source, base = base_frame()
    fs = frames(base, args.frames)
    h, w = base.rgb.shape[:2]
    results: dict = {"source": source, "size": f"{w}x{h}", "frames": args.frames, "python": platform.python_version(),
                     "machine": platform.machine(), "runs": []}
    print(f"{source}, {w}x{h}, {args.frames} frames")
    with tempfile.TemporaryDirectory() as tmp:
        for compression in ("zstd", "lz4", "none"):
            path = Path(tmp) / f"{compression}.mcap"
            t = time.perf_counter()
            write_frames(fs, path, compression=compression)
            t_write = time.perf_counter() - t
            size = path.stat().st_size
            t = time.perf_counter()
            n = sum(1 for _ in read_bag(path))
            t_read = time.perf_counter() - t
            assert n == args.frames
            t = time.perf_counter()
            m = sum(len(msg.data) for msg in iter_messages(path))
            t_raw = time.perf_counter() - t
            row = {
                "compression": compression,
                "write_fps": args.frames / t_write,
                "read_fps": args.frames / t_read,
                "raw_iter_fps": args.frames / t_raw,
                "mb_per_frame": size / args.frames / 1e6,
                "raw_mb_per_frame": m / args.frames / 1e6,
            }
            results["runs"].append(row)
            print(f"  {compression:<5} write {row['write_fps']:7.1f} frames/s   "
                  f"read_bag {row['read_fps']:7.1f} frames/s   "
                  f"iter_messages {row['raw_iter_fps']:7.1f} frames/s   {row['mb_per_frame']:.2f} MB/frame on disk "
                  f"({row['raw_mb_per_frame']:.2f} MB serialized)")
    ok = min(r["read_fps"] for r in results["runs"]) >= 30.0
    print(f"replay reading target >= 30 frames/s: {'met' if ok else 'NOT met'}")
    if args.out:
        atomic_write(args.out, json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
