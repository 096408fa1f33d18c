"""Benchmark the renderer on one core: render_box of each LM-O model at its ground-truth pose
(640x480) and the full-frame render of all objects. Target (DESIGN.md): <= 3 ms per cropped
single-model render.

    python benchmarks/bench_render.py [--repeat 200] [--out bench_render.json]

Uses the real LM-O sample in ../shared/data/lmo when present, otherwise procedural tori of
LM-O size (~10k triangles) at LM-O-like distances.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before numpy/open3d start their thread pools

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from perception_config.core.geometry import Pose, exp_so3  # noqa: E402
from perception_config.core.models import ObjectModel, make_model  # noqa: E402
from perception_config.util.atomic_file import atomic_write  # noqa: E402

LMO = REPO.parent / "shared" / "data" / "lmo"
W, H = 640, 480


def torus(obj_id: int, R: float = 0.05, r: float = 0.02, nu: int = 100, nv: int = 50) -> ObjectModel:
    """A procedural torus (2 * nu * nv triangles) in metres."""
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, nu, endpoint=False), np.linspace(0, 2 * np.pi, nv, endpoint=False),
                       indexing="ij")
    verts = np.stack([(R + r * np.cos(v)) * np.cos(u), (R + r * np.cos(v)) * np.sin(u), r * np.sin(v)],
                     -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    a, b = i * nv + j, ((i + 1) % nu) * nv + j
    c, d = ((i + 1) % nu) * nv + (j + 1) % nv, i * nv + (j + 1) % nv
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return make_model(obj_id, verts, faces)


def scene() -> tuple[str, list[ObjectModel], list[Pose], np.ndarray]:
    if (LMO / "models" / "models_info.json").exists():
        from perception_config.datasets.bop import BopDataset

        frame = BopDataset(LMO).load_frame(2, 3)
        return "LM-O test/000002 image 3", [o.model for o in frame.objects], [o.gt for o in frame.objects], frame.K
    K = np.array([[572.4114, 0, 325.2611], [0, 573.57043, 242.04899], [0, 0, 1]])
    models = [torus(i + 1, R=0.03 + 0.01 * i) for i in range(4)]
    poses = [Pose(exp_so3([0.5 * i, 0.3, 0.1]), [0.12 * (i - 1.5), 0.05 * (i % 2), 1.0]) for i in range(4)]
    return "procedural tori (../shared absent)", models, poses, K


def timeit(fn, repeat: int) -> tuple[float, float]:
    fn()  # warm-up
    ts = np.empty(repeat)
    for k in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts[k] = time.perf_counter() - t0
    return float(np.median(ts) * 1e3), float(np.percentile(ts, 90) * 1e3)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=200)
    ap.add_argument("--out", type=Path, default=None, help="write the figures as JSON")
    args = ap.parse_args(argv)

    import open3d as o3d

    from perception_config.core.render import render, render_box

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    source, models, poses, K = scene()
    rows = []
    for m, p in zip(models, poses):
        t0 = time.perf_counter()
        rb = render_box(m, p, K, W, H, nthreads=1)  # cold: builds the scene and its BVH
        cold_ms = (time.perf_counter() - t0) * 1e3
        med, p90 = timeit(lambda m=m, p=p: render_box(m, p, K, W, H, nthreads=1), args.repeat)
        rows.append({"obj_id": m.obj_id, "faces": int(len(m.faces)), "box": list(rb.box),
                     "rays": int(rb.box[2] * rb.box[3]), "median_ms": med, "p90_ms": p90, "cold_ms": cold_ms})
    full_med, full_p90 = timeit(lambda: render(models, poses, K, W, H, nthreads=1), max(20, args.repeat // 4))

    print(f"render benchmark: {source}, {W}x{H}, one core "
          f"(nthreads=1, OMP_NUM_THREADS={os.environ['OMP_NUM_THREADS']})")
    print(f"{'obj':>4} {'faces':>6} {'box (x y w h)':>20} {'rays':>6} {'median ms':>10} {'p90 ms':>8} {'cold ms':>8}")
    for r in rows:
        box = " ".join(str(v) for v in r["box"])
        print(f"{r['obj_id']:>4} {r['faces']:>6} {box:>20} {r['rays']:>6} "
              f"{r['median_ms']:>10.2f} {r['p90_ms']:>8.2f} {r['cold_ms']:>8.1f}")
    print(f"full frame, {len(models)} objects: median {full_med:.2f} ms, p90 {full_p90:.2f} ms")
    worst = max(r["median_ms"] for r in rows)
    print(f"worst single-model median {worst:.2f} ms (target <= 3 ms): {'OK' if worst <= 3.0 else 'OVER'}")
    if args.out:
        out = {"source": source, "width": W, "height": H, "repeat": args.repeat, "render_box": rows,
               "full_frame": {"objects": len(models), "median_ms": full_med, "p90_ms": full_p90},
               "machine": {"python": platform.python_version(), "processor": platform.processor() or platform.machine(),
                           "open3d": o3d.__version__}}
        args.out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(args.out, json.dumps(out, indent=2) + "\n")
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
