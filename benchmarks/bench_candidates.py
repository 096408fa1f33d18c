"""Benchmark the ground-truth-free generators' ranked candidates on one core: how often a
candidate within MSSD <= 0.1 d is the first (top-1) or among the first five (top-5), how often
the first is a confident wrong answer, and how long a call takes once the model is prepared.

    python benchmarks/bench_candidates.py [--generators resting_pose,ppf,global_registration,linemod]
        [--pipeline cell] [--out FILE.json]
        [--default PATH]

Data: the real LM-O RGB-D frame (../shared/data/lmo, 8 objects, clutter; every object, and
those with visib_fract >= 0.3) when present, and the synthetic default's test images
(data/default, the seeded split of the learning study) with visib_fract >= 0.3, and, for the
generators that run without depth (linemod), the twenty real LM-O photographs without depth
(../shared/data/lmo-rgb; every object and those with visib_fract >= 0.3). Success is
symmetry-aware MSSD <= 0.1 x diameter (the simulated pick). Confident wrong: the first
candidate's confidence >= --confident and MSSD > 0.3 d. Both generators rank their distinct
candidates (BlockResult.candidates, by verification score). Per-model preparation (ppf's point
pair tables, linemod's templates) is built into a fresh temporary cache first and timed apart:
the query times are after caching. With several generators, "any of them" counts a query when
any one has a right candidate in its top 5 (the cell's agent can call each).
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

from perception_config.blocks.base import create  # noqa: E402
from perception_config.util.atomic_file import atomic_write  # noqa: E402

LMO = REPO.parent / "shared" / "data" / "lmo"
LMO_RGB = REPO.parent / "shared" / "data" / "lmo-rgb"
DEFAULT = REPO / "data" / "default"


def frames_of(root: Path, test_split: bool) -> list:
    import warnings

    from perception_config.datasets.bop import BopDataset
    from perception_config.rl.episodes import split_image_keys

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the LM-O annotations' SO(3) projection warning
        ds = BopDataset(root, "test")
        keys = ds.image_keys()
        if test_split and len(keys) >= 2:
            keys = split_image_keys(keys)[1]
        return [ds.load_frame(s, i) for s, i in keys]




def pipeline_params(pipeline: str | None) -> dict[str, dict]:
    """Each generator's parameters as `pipeline` sets them (bench/generators.py); {} without one."""
    from perception_config.bench.generators import pipeline_params as params_of
    from perception_config.blocks.pipeline import load_pipeline

    return params_of(load_pipeline(pipeline)) if pipeline else {}


def evaluate(name: str, frames: list, min_visib: float, confident: float, params: dict | None = None) -> list[dict]:
    """bench/generators.py's rows, with the declared symmetries' figures under this file's keys."""
    from perception_config.bench.generators import generator_rows

    rows = generator_rows(name, frames, params, min_visib, confident)
    for r in rows:
        r.update(rank=r["rank_declared"], top1_mssd_d=r["top1_mssd_d_declared"],
                 confident_wrong=r["confident_wrong_declared"])
    return rows


def summary(rows: list[dict], min_visib: float = 0.0) -> dict:
    rows = [r for r in rows if r["visib_fract"] is None or r["visib_fract"] >= min_visib]
    if not rows:
        return {"queries": 0}
    rank = np.array([r["rank"] for r in rows])
    per_obj = {}
    for obj in sorted({r["obj_id"] for r in rows}):
        mine = [r for r in rows if r["obj_id"] == obj]
        per_obj[str(obj)] = {"queries": len(mine), "top5": sum(0 <= r["rank"] < 5 for r in mine) / len(mine)}
    return {"queries": len(rows), "top1": float(np.mean(rank == 0)), "top5": float(np.mean((rank >= 0) & (rank < 5))),
            "confident_wrong": float(np.mean([r["confident_wrong"] for r in rows])),
            "median_s": float(np.median([r["seconds"] for r in rows])),
            "p90_s": float(np.percentile([r["seconds"] for r in rows], 90)), "per_object": per_obj}


def prepare_tables(frames_sets: dict[str, list]) -> dict:
    """Build ppf's tables into the (fresh) cache, then time reading them back from disk."""
    from perception_config.blocks.point_pairs import PointPairFeatures
    from perception_config.vision import ppf

    models = {id(o.model): o.model for frames in frames_sets.values() for f in frames for o in f.objects if o.model}
    c = PointPairFeatures().config
    built, disk = [], []
    for m in models.values():
        rel = max(c["sampling_rel"], c["min_sampling"] / m.diameter)
        t0 = time.perf_counter()
        ppf.ppf_model(m, rel, c["n_angle"])
        built.append(time.perf_counter() - t0)
        ppf._MEMORY.clear()
        t0 = time.perf_counter()
        _, source = ppf.ppf_model(m, rel, c["n_angle"])
        disk.append(time.perf_counter() - t0)
        assert source == "disk", source
    return {"models": len(models), "built_median_s": float(np.median(built)), "built_max_s": float(np.max(built)),
            "from_disk_median_s": float(np.median(disk))}


def prepare_templates(frames_sets: dict[str, list]) -> dict:
    """Build linemod's templates into the (fresh) cache, then time reading them back from disk."""
    from perception_config.blocks.templates import LineMod
    from perception_config.vision import linemod

    models = {id(o.model): o.model for frames in frames_sets.values() for f in frames for o in f.objects if o.model}
    params = LineMod().template_params()
    built, disk = [], []
    for m in models.values():
        t0 = time.perf_counter()
        t, _ = linemod.linemod_templates(m, params)
        built.append(time.perf_counter() - t0)
        linemod._MEMORY.clear()
        t0 = time.perf_counter()
        _, source = linemod.linemod_templates(m, params)
        disk.append(time.perf_counter() - t0)
        assert source == "disk", source
    return {"models": len(models), "templates": int(len(t.rotations)), "built_median_s": float(np.median(built)),
            "built_max_s": float(np.max(built)), "from_disk_median_s": float(np.median(disk))}


def without_depth(frames: list) -> list:
    import dataclasses

    return [dataclasses.replace(f, depth=None) if f.depth is not None else f for f in frames]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--generators", default="resting_pose,ppf,global_registration")
    ap.add_argument("--confident", type=float, default=0.5, help="confidence counted as confident")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "candidates.json")
    ap.add_argument("--default", type=Path, default=DEFAULT, help="the synthetic default dataset (BOP layout)")
    ap.add_argument("--cache", type=Path, default=None,
                    help="prepared tables and templates kept here across runs (default: a fresh temporary folder, "
                         "so preparation is built and timed)")
    ap.add_argument("--no-rgb-only", action="store_true", help="leave out the RGB-only photographs")
    ap.add_argument("--pipeline", default=None,
                    help="run each generator with the parameters this pipeline gives it (e.g. 'cell': ppf within "
                         "1 s, as the cell's agent calls it); default: the blocks' own defaults")
    args = ap.parse_args(argv)
    params = pipeline_params(args.pipeline)

    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    cache = tempfile.TemporaryDirectory(prefix="bench_candidates_cache_")
    os.environ["PERCEPTION_CONFIG_CACHE"] = str(args.cache) if args.cache else cache.name
    sets: dict[str, tuple[list, float]] = {}
    if (LMO / "models" / "models_info.json").exists():
        lmo = frames_of(LMO, test_split=False)
        sets["LM-O real frame, all objects"] = (lmo, 0.0)
        sets["LM-O real frame, visib >= 0.3"] = (lmo, 0.3)
    sets["synthetic default, test images, visib >= 0.3"] = (frames_of(args.default, test_split=True), 0.3)
    rgb_sets: dict[str, tuple[list, float]] = {}
    if (LMO_RGB / "models" / "models_info.json").exists() and not args.no_rgb_only:
        rgb_sets["LM-O real photographs, no depth, all objects"] = (without_depth(frames_of(LMO_RGB, test_split=False)),
                                                                    0.0)
    print(f"candidates benchmark, one core (OMP_NUM_THREADS={os.environ['OMP_NUM_THREADS']}), "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    out: dict = {"machine": {"python": platform.python_version(), "open3d": o3d.__version__,
                             "load_average": os.getloadavg()[0], "cpus": os.cpu_count()}, "results": [],
           "cache_reused": bool(args.cache),  # True: the preparation times below are reads, not builds
           "pipeline": args.pipeline, "params": {n: params.get(n, {}) for n in args.generators.split(",") if n}}
    if "ppf" in args.generators:
        out["ppf_tables"] = prepare_tables({k: v[0] for k, v in sets.items()})
        t = out["ppf_tables"]
        print(f"ppf tables: {t['models']} models, built in {t['built_median_s']:.2f} s median "
              f"(max {t['built_max_s']:.2f}), read from disk in {t['from_disk_median_s'] * 1000:.0f} ms")
    if "linemod" in args.generators:
        out["linemod_templates"] = t = prepare_templates({k: v[0] for k, v in {**sets, **rgb_sets}.items()})
        print(f"linemod templates: {t['models']} models, {t['templates']} templates each, built in "
              f"{t['built_median_s']:.1f} s median (max {t['built_max_s']:.1f}), read from disk in "
              f"{t['from_disk_median_s']:.2f} s")
    print(f"{'data':<46} {'generator':<20} {'queries':>7} {'top-1':>6} {'top-5':>6} {'conf.wrong':>10} "
          f"{'median s':>8} {'p90 s':>6}")
    names = [g for g in args.generators.split(",") if g]
    runs = [(label, frames, v, name) for label, (frames, v) in sets.items() for name in names]
    # Generators that run without depth also on the RGB-only photographs (every object, and the
    # summary of those with visib_fract >= 0.3 beside it).
    runs += [(label, frames, v, name) for label, (frames, v) in rgb_sets.items() for name in names
             if frames and not create(name).frame_lacks(frames[0])]
    for label, frames, min_visib, name in runs:
        rows = evaluate(name, frames, min_visib, args.confident, params.get(name))
        summaries = [(label, summary(rows))]
        if label in rgb_sets:
            summaries.append((label.replace("all objects", "visib >= 0.3"), summary(rows, 0.3)))
        for text, s in summaries:
            out["results"].append({"data": text, "generator": name, "summary": s, "rows": rows})
            if not s["queries"]:
                continue
            print(f"{text:<46} {name:<20} {s['queries']:>7} {s['top1']:>6.0%} {s['top5']:>6.0%} "
                  f"{s['confident_wrong']:>10.0%} {s['median_s']:>8.2f} {s['p90_s']:>6.2f}")
            print(f"{'':<46} per object top-5: "
                  + ", ".join(f"{k}: {v['top5']:.0%}" for k, v in s["per_object"].items()), flush=True)
    # Together: a query counts when any of the generators has a right candidate in its top 5 (the
    # cell's agent can call each of them).
    by_data: dict[str, list[list[dict]]] = {}
    for res in out["results"]:
        if res["summary"].get("queries"):
            by_data.setdefault(res["data"], []).append([r for r in res["rows"] if r["visib_fract"] is None
                                                        or "visib >= 0.3" not in res["data"]
                                                        or r["visib_fract"] >= 0.3])
    for text, runs_of in by_data.items():
        if len(runs_of) < 2:
            continue
        hit = [any(0 <= run[k]["rank"] < 5 for run in runs_of) for k in range(len(runs_of[0]))]
        objs = [r["obj_id"] for r in runs_of[0]]
        per_obj = {str(o): float(np.mean([h for h, oo in zip(hit, objs) if oo == o])) for o in sorted(set(objs))}
        out.setdefault("together", []).append({"data": text, "generators": names, "queries": len(hit),
                                               "top5": float(np.mean(hit)), "per_object": per_obj})
        print(f"{text:<46} {'any of them':<20} {len(hit):>7} {'':>6} {np.mean(hit):>6.0%}")
        print(f"{'':<46} per object top-5: " + ", ".join(f"{k}: {v:.0%}" for k, v in per_obj.items()))
    atomic_write(args.out, json.dumps(out, indent=1, default=float))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
