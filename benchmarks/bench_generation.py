"""Benchmark the generation blocks on one core: how often the real generator
(`global_registration`, frame + model only) finds each object, and how long it takes;
plus the cost of `simulated_init`.

    python benchmarks/bench_generation.py [--budgets 2,10] [--scenes 4] [--images 2] [--out FILE.json]

Data: the real LM-O frame (../shared/data/lmo, scene 2 image 3: 8 objects, clutter,
occlusion) when present, and a small synthetic BOP dataset of the procedural parts generated
into a temporary folder (perception_config.datasets.synthetic; bins and tables, sensor noise).
Every annotated object of every frame is one query. Success: symmetry-aware MSSD < 0.1 x
diameter (BOP-style, as the simulated pick); ADD < 0.1 d is reported too. "found" is the share
of queries where any polished candidate was within 0.1 d (generation worked, whatever
verification chose). The search is bounded by wall clock, so on a loaded machine a budget buys
less search: compare budgets measured in one run.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before numpy/open3d start their thread pools

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

from perception_config.blocks.base import BlockInput  # noqa: E402
from perception_config.blocks.generation import GlobalRegistration, SimulatedInit  # noqa: E402
from perception_config.core.metrics import add, pose_mssd  # noqa: E402
from perception_config.util.atomic_file import atomic_write  # noqa: E402

LMO = REPO.parent / "shared" / "data" / "lmo"


def frames_of(root: Path) -> list:
    from perception_config.datasets.bop import BopDataset

    ds = BopDataset(root, "test")
    return [ds.load_frame(s, i) for s, i in ds.image_keys()]


def evaluate(frames: list, budget: float, seed: int) -> list[dict]:
    """One global_registration query per annotated object; a fresh cache per frame."""
    block = GlobalRegistration(max_seconds=budget)
    rows = []
    for frame in frames:
        cache: dict = {}
        for o in frame.objects:
            if o.gt is None or o.model is None:
                continue
            r = block(BlockInput(frame=frame, model=o.model, rng=np.random.default_rng(seed), cache=cache))
            d = o.model.diameter
            mssd = pose_mssd(r.pose, o.gt, o.model) / d if r.pose is not None else float("inf")
            add_d = add(r.pose.R, r.pose.t, o.gt.R, o.gt.t, o.model.points) / d if r.pose is not None else float("inf")
            found = any(pose_mssd(p, o.gt, o.model) / d < 0.1 for _, p in r.info.get("candidates", []))
            rows.append({
                "scene_id": frame.scene_id, "im_id": frame.im_id, "obj_id": o.obj_id,
                "visib_fract": o.visib_fract, "ok": r.ok, "mssd_d": mssd, "add_d": add_d,
                "success": bool(mssd < 0.1), "found": bool(found), "seconds": r.elapsed,
                "verification": r.scores.get("gen_verification"), "reason": r.reason,
                "clusters_tried": r.info.get("clusters_tried"),
            })
    return rows


def summary(rows: list[dict]) -> dict:
    n = len(rows)
    if n == 0:
        return {"queries": 0}
    return {
        "queries": n,
        "success_mssd": sum(r["success"] for r in rows) / n,
        "success_add": sum(r["add_d"] < 0.1 for r in rows) / n,
        "found": sum(r["found"] for r in rows) / n,
        "ok": sum(r["ok"] for r in rows) / n,
        "wrong_but_ok": sum(r["ok"] and not r["success"] for r in rows) / n,
        "median_s": float(np.median([r["seconds"] for r in rows])),
        "p90_s": float(np.percentile([r["seconds"] for r in rows], 90)),
    }


def simulated_init_ms(frames: list, repeat: int = 2000) -> float:
    frame = frames[0]
    o = next(o for o in frame.objects if o.gt is not None)
    block, rng = SimulatedInit(noise_lambda=0.5), np.random.default_rng(0)
    ts = np.empty(repeat)
    for k in range(repeat):
        t0 = time.perf_counter()
        block(BlockInput(frame=frame, model=o.model, ground_truth=o.gt, rng=rng))
        ts[k] = time.perf_counter() - t0
    return float(np.median(ts) * 1e3)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--budgets", default="2,10", help="comma-separated max_seconds values")
    ap.add_argument("--scenes", type=int, default=4, help="synthetic scenes (0: none)")
    ap.add_argument("--images", type=int, default=2, help="synthetic images per scene")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None, help="write all rows and summaries as JSON")
    args = ap.parse_args(argv)

    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    budgets = [float(b) for b in args.budgets.split(",") if b]
    sets: dict[str, list] = {}
    if (LMO / "models" / "models_info.json").exists():
        sets["LM-O real frame"] = frames_of(LMO)
    tmp = None
    if args.scenes > 0:
        from perception_config.datasets.synthetic import generate

        tmp = tempfile.TemporaryDirectory(prefix="bench_generation_")
        root = Path(tmp.name) / "synthetic"
        generate(root, scenes=args.scenes, images_per_scene=args.images, seed=args.seed, progress=False)
        sets[f"synthetic ({args.scenes} scenes x {args.images} images)"] = frames_of(root)
    if not sets:
        print("no data: ../shared/data/lmo is absent and --scenes 0")
        return 1

    print(f"generation benchmark, 640x480, one core (OMP_NUM_THREADS={os.environ['OMP_NUM_THREADS']}), "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    first = next(iter(sets.values()))
    sim_ms = simulated_init_ms(first)
    print(f"simulated_init: median {sim_ms:.3f} ms per call")
    print(f"{'data':<36} {'budget s':>8} {'queries':>7} {'MSSD<0.1d':>9} {'ADD<0.1d':>8} {'found':>6} "
          f"{'ok':>5} {'ok&wrong':>8} {'median s':>8} {'p90 s':>6}")
    out: dict = {"simulated_init_ms": sim_ms, "results": [],
                 "machine": {"python": platform.python_version(), "open3d": o3d.__version__,
                             "load_average": os.getloadavg()[0], "cpus": os.cpu_count()}}
    for name, frames in sets.items():
        for budget in budgets:
            rows = evaluate(frames, budget, args.seed)
            s = summary(rows)
            print(f"{name:<36} {budget:>8.1f} {s['queries']:>7} {s['success_mssd']:>9.0%} {s['success_add']:>8.0%} "
                  f"{s['found']:>6.0%} {s['ok']:>5.0%} {s['wrong_but_ok']:>8.0%} "
                  f"{s['median_s']:>8.2f} {s['p90_s']:>6.2f}")
            per_obj: dict[int, list] = {}
            for r in rows:
                per_obj.setdefault(r["obj_id"], []).append(r["success"])
            print("    per object (successes/queries): " + ", ".join(
                f"{k}: {sum(v)}/{len(v)}" for k, v in sorted(per_obj.items())))
            out["results"].append({"data": name, "budget_s": budget, "summary": s, "rows": rows})
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(args.out, json.dumps(out, indent=2, default=float) + "\n")
        print(f"wrote {args.out}")
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
