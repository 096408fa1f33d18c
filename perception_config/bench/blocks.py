"""Block benchmarks: milliseconds per call of every block, and the refiners' convergence table.

Both run on the frames of a BOP dataset (640x480 for the synthetic default) with hypotheses
drawn by the lambda noise model around the ground truth, one core (the command sets
OMP_NUM_THREADS=1 before the numeric libraries load).

- `bench_blocks`: {name: {"median_ms", "p90_ms", "calls"}} for every registered block with
  its default parameters, every action preset of the pipeline, the cropped render and all
  scoring blocks together ("scores_total").
- `convergence_table`: for each refinement action and lambda, the share of episodes in which
  applying that refiner up to `max_applications` times reaches a successful simulated pick.

On RGB-only frames (an RGB-only dataset, or `use_depth=False`) the blocks and refiners that
need depth cannot run (`Block.frame_lacks`): they are left out of both (not timed, no row).
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from ..blocks import load_all
from ..blocks.base import Block, BlockInput, Kind, create
from ..blocks.pipeline import Pipeline, load_pipeline
from ..core.geometry import perturb
from ..core.render import render_box
from ..core.scene import Frame, SceneObject
from ..datasets.bop import BopDataset

DEFAULT_LAMBDAS = tuple(round(0.1 * i, 1) for i in range(1, 11))


def _stats(ms: list[float]) -> dict[str, float | int]:
    a = np.asarray(ms, dtype=np.float64)
    return {"median_ms": round(float(np.median(a)), 3), "p90_ms": round(float(np.percentile(a, 90)), 3),
            "calls": int(a.size)}


def usable_objects(frame: Frame, min_visib: float) -> list[tuple[int, SceneObject]]:
    """(index in frame.objects, object) of the annotated objects with a model and visib_fract >= min_visib."""
    return [(i, o) for i, o in enumerate(frame.objects)
            if o.gt is not None and o.model is not None and (o.visib_fract is None or o.visib_fract >= min_visib)]


def _cases(ds: BopDataset, n_frames: int, lam: float, seed: int,
           min_visib: float = 0.3) -> Iterable[tuple[Frame, Any, Any]]:
    """(frame, object, perturbed pose) over the first n_frames images."""
    rng = np.random.default_rng(seed)
    for scene_id, im_id in ds.image_keys()[:n_frames]:
        frame = ds.load_frame(scene_id, im_id)
        for _, obj in usable_objects(frame, min_visib):
            yield frame, obj, perturb(obj.gt, lam, obj.model.diameter, rng)


def bench_blocks(
    dataset: str | Path, pipeline: Pipeline | None = None, n_frames: int = 10, lam: float = 0.2,
    seed: int = 0, split: str = "test", progress: bool = True, use_depth: bool = True,
) -> dict[str, dict[str, float | int]]:
    """Median / p90 milliseconds per call of every block that can run on the dataset's frames
    (`use_depth=False`: read as RGB-only)."""
    from tqdm import tqdm

    ds = BopDataset(Path(dataset), split=split, use_depth=use_depth)
    pipeline = pipeline or load_pipeline()
    blocks: dict[str, Block] = {name: cls() for name, cls in load_all().items() if name != "external_pick"}
    for action in pipeline.actions:
        if action.name not in blocks:
            blocks[f"action:{action.name}"] = action.block
    times: dict[str, list[float]] = {name: [] for name in blocks}
    times["render"], times["scores_total"] = [], []
    cases = list(_cases(ds, n_frames, lam, seed))
    if not cases:
        raise ValueError(f"{dataset}: no usable (frame, object) pairs to benchmark")
    for frame, obj, pose in tqdm(cases, desc="bench blocks", disable=not progress, unit="object"):
        def inp(cache: dict[str, Any], at=pose, *, frame=frame, obj=obj) -> BlockInput:
            return BlockInput(frame=frame, model=obj.model, pose=at, ground_truth=obj.gt,
                              rng=np.random.default_rng(seed), cache=cache)

        runnable = {name: block for name, block in blocks.items() if not block.frame_lacks(frame)}
        # Cold: the block's first call on a frame (its per-frame caches empty).
        for name, block in runnable.items():
            times.setdefault(f"{name}:cold", []).append(block(inp({})).elapsed * 1e3)
        # Warm: what an episode sees after its first operator — per-frame caches filled by
        # calls at another hypothesis (the ground truth), then the perturbed one is timed.
        shared: dict[str, Any] = {}
        for block in runnable.values():
            block(inp(shared, obj.gt))
        for name, block in runnable.items():
            times[name].append(block(inp(shared)).elapsed * 1e3)
        t0 = time.perf_counter()
        render_box(obj.model, pose, frame.K, frame.width, frame.height)
        times["render"].append((time.perf_counter() - t0) * 1e3)
        times["scores_total"].append(sum(b(inp(shared)).elapsed for b in pipeline.scoring
                                         if not b.frame_lacks(frame)) * 1e3)
    return {name: _stats(ms) for name, ms in times.items() if ms}


def convergence_table(
    dataset: str | Path, pipeline: Pipeline | None = None, lambdas: Iterable[float] = DEFAULT_LAMBDAS,
    n_frames: int = 10, max_applications: int = 5, seed: int = 0, split: str = "test", progress: bool = True,
    use_depth: bool = True,
) -> dict[str, dict[str, float]]:
    """{refinement action: {lambda: share of episodes reaching a successful pick}}, for the
    refiners that can run on the dataset's frames (`use_depth=False`: read as RGB-only)."""
    from tqdm import tqdm

    ds = BopDataset(Path(dataset), split=split, use_depth=use_depth)
    pipeline = pipeline or load_pipeline()
    pick = create("simulated_pick")
    keys = ds.image_keys()[:n_frames]
    first = ds.load_frame(*keys[0]) if keys else None
    refiners = [a for a in pipeline.actions if a.kind == Kind.REFINEMENT and not a.block.frame_lacks(first)]
    lambdas = [float(x) for x in lambdas]
    table: dict[str, dict[str, float]] = {a.name: {} for a in refiners}
    table["none (pick at once)"] = {}
    bar = tqdm(total=len(lambdas) * (len(refiners) + 1), desc="convergence", disable=not progress)
    for lam in lambdas:
        cases = list(_cases(ds, n_frames, lam, seed))
        if not cases:
            raise ValueError(f"{dataset}: no usable (frame, object) pairs")
        caches: dict[int, dict[str, Any]] = {}
        for action in [None, *refiners]:
            successes = 0
            for frame, obj, pose in cases:
                cache = caches.setdefault(id(frame), {})
                inp = BlockInput(frame=frame, model=obj.model, pose=pose, ground_truth=obj.gt, cache=cache)
                picked = bool(pick(inp).picked)
                for _ in range(max_applications if action is not None and not picked else 0):
                    r = action.block(inp)
                    if r.ok and r.pose is not None:
                        inp.pose = r.pose
                    if pick(inp).picked:
                        picked = True
                        break
                successes += picked
            key = action.name if action is not None else "none (pick at once)"
            table[key][f"{lam:.1f}"] = round(successes / len(cases), 3)
            bar.update(1)
    bar.close()
    return table


def format_convergence(table: dict[str, dict[str, float]]) -> str:
    """A Markdown table: refiner x lambda, share of successful picks."""
    lams = list(next(iter(table.values())).keys())
    lines = ["| refiner | " + " | ".join(lams) + " |", "|---|" + "---|" * len(lams)]
    for name, row in table.items():
        lines.append(f"| {name} | " + " | ".join(f"{row[l]:.2f}" for l in lams) + " |")
    return "\n".join(lines)


def format_blocks(stats: dict[str, dict[str, float | int]]) -> str:
    lines = ["| block | median ms | p90 ms | calls |", "|---|---|---|---|"]
    for name, s in stats.items():
        lines.append(f"| {name} | {s['median_ms']:.2f} | {s['p90_ms']:.2f} | {s['calls']} |")
    return "\n".join(lines)


