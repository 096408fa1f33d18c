"""Real-image benchmark of the refiners and the scores: `perception-config bench real`.

Runs on any BOP dataset, with or without depth (blocks whose inputs a frame lacks are skipped
and listed). Cases: the first `n_frames` images, each annotated object with visib_fract >=
`min_visib` and a model. Starting poses come from the lambda noise model (geometry.perturb)
with a generator seeded from (seed, scene, image, object index, purpose, lambda index), so a
run is reproducible and does not depend on which blocks run. Tolerance: symmetry-aware
MSSD <= 0.1 x diameter (metrics.pose_mssd), the simulated pick's test.

Refiners (every refinement action of the pipeline, named by action, plus registered refinement
blocks no action uses): from each start (`lambdas`, 0 = the ground truth) x `seeds`, up to
`max_calls` successive calls, each on the previous call's output with a fresh BlockInput and
the frame's shared cache (as the environment does; a failed call ends the chain, the pose
stays). Per lambda: `improved` (MSSD after one call strictly below the start's), `within_before`,
`within_1` (after one call), `within_3` (after the last call), `reached_3` (within tolerance
after some call of the chain: the pick-when-good view of the convergence table), the median
MSSD / diameter and MSPD (px) after one call (the drift at lambda 0), the ok=False share with
the reasons counted, and the median ms per call. Per object id, per visibility (the annotated
visib_fract in VISIBILITY_BINS buckets: on real frames occlusion is what separates the easy
instances from the hard ones) and overall.

Scores (every registered scoring block the frames can feed): poses drawn at `auc_lambdas` x
`seeds` per object instance; AUC = the Mann-Whitney probability that a pose within tolerance
scores better than one outside (ties 1/2, lower_is_better scores reversed, a failed call ranks
below every value), counted over pairs of the same instance and summed per object id, per
visibility bucket and overall; `auc_pooled` over all pairs of the dataset. With
`refiner_costs`, a refiner that reports its cost at the start pose
(BlockResult.info["cost_before"], e.g. d2co, chamfer) is called on the same poses and that cost
ranked as a score too ("d2co:d2co_cost"; its ms are those of the whole refiner call).
"""
from __future__ import annotations

import json
import re
import time
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from ..blocks import load_all
from ..blocks.base import GROUND_TRUTH, Block, BlockInput, Kind
from ..blocks.pipeline import Pipeline, load_pipeline
from ..core.geometry import Pose, perturb
from ..core.metrics import eval_symmetries, mspd, pose_mssd
from ..core.scene import Frame, SceneObject
from ..datasets.bop import BopDataset
from ..datasets.bop_json import jsonable
from ..util.atomic_file import atomic_write
from .blocks import usable_objects

DEFAULT_LAMBDAS = (0.0, 0.1, 0.3)
DEFAULT_AUC_LAMBDAS = (0.05, 0.1, 0.2, 0.3, 0.5)
TOLERANCE = 0.1  # MSSD as a share of the diameter
VISIBILITY_BINS = (0.5, 0.7, 0.85)  # visib_fract edges of the per-visibility split (occlusion is what real frames add)
_REFINE, _SCORE = 0, 1  # purposes in the seed: refiner starts and scored poses never share a stream


def select_blocks(pipeline: Pipeline, names: Sequence[str] | None = None) -> tuple[dict[str, Block], dict[str, Block]]:
    """(refiners, scorers) by name: the pipeline's refinement actions (named by action), the
    registered refinement blocks no action uses, and every registered scoring block; `names`
    keeps only those (an unknown name is an error listing the known ones)."""
    registry = load_all()
    refiners: dict[str, Block] = {a.name: a.block for a in pipeline.actions if a.kind == Kind.REFINEMENT}
    used = {a.block.name for a in pipeline.actions}
    for name, cls in sorted(registry.items()):
        if cls.kind == Kind.REFINEMENT and name not in used and name not in refiners:
            refiners[name] = cls()
    scorers: dict[str, Block] = {name: cls() for name, cls in sorted(registry.items()) if cls.kind == Kind.SCORING}
    if names is not None:
        known = [*refiners, *scorers]
        unknown = [n for n in names if n not in known]
        if unknown:
            raise ValueError(f"bench real: unknown block(s) {unknown}; known: {', '.join(known)}")
        refiners = {n: b for n, b in refiners.items() if n in names}
        scorers = {n: b for n, b in scorers.items() if n in names}
    return refiners, scorers


def refiner_starts(gt: Pose, lam: float, diameter: float, seeds: int, instance: list[int],
                   lam_index: int) -> list[Pose]:
    """The `seeds` refiner starts of one object instance at one lambda (the noise model around the
    ground truth), from a generator seeded by (seed, scene, image, object index) = `instance`, the
    purpose and the lambda's index: the same starts in every run and for every refiner. A chain's
    call `k` from start `s` uses the generator seeded by [*instance, lam_index, s, k]."""
    rng = np.random.default_rng([*instance, _REFINE, lam_index])
    return [perturb(gt, lam, diameter, rng) for _ in range(seeds)]


def _visibility_labels(edges: Sequence[float]) -> list[str]:
    return ([f"<{edges[0]:g}"] + [f"{a:g}-{b:g}" for a, b in zip(edges, edges[1:])] + [f">={edges[-1]:g}"]
            + ["unknown"])


VISIBILITY_LABELS = _visibility_labels(VISIBILITY_BINS)  # the buckets in their order


def visibility_bin(visib_fract: float | None) -> str:
    """The per-visibility bucket of an annotated object (VISIBILITY_LABELS: "<0.5", "0.5-0.7",
    "0.7-0.85", ">=0.85"; "unknown" without a visib_fract)."""
    if visib_fract is None or not np.isfinite(visib_fract):
        return VISIBILITY_LABELS[-1]
    return VISIBILITY_LABELS[int(np.searchsorted(VISIBILITY_BINS, visib_fract, side="right"))]


def _reason(text: str) -> str:
    """A failure reason with its numbers masked, so equal causes count together."""
    return re.sub(r"-?\d+(\.\d+)?(e-?\d+)?", "#", text)[:120]


@dataclass
class RefineRecord:
    """One start of one refiner on one object instance."""

    obj_id: int
    visib_bin: str
    lam_index: int
    mssd_before: float  # / diameter
    mssd_1: float
    mspd_1: float  # px
    within_3: bool
    reached_3: bool
    end: Pose  # after the last call
    mssd_end: float  # / diameter, after the last call
    ms: list[float] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)


def refine_chain(block: Block, frame: Frame, obj: SceneObject, start: Pose, rng_seed: list[int],
                 cache: dict[str, Any], max_calls: int, lam_index: int) -> RefineRecord:
    """Up to `max_calls` calls of `block`, each on the previous output with the frame's shared
    cache and a generator seeded by [*rng_seed, call] (a failed call ends the chain)."""
    model, gt = obj.model, obj.gt
    d = model.diameter
    before = pose_mssd(start, gt, model) / d
    pose, ms, failures, errors = start, [], [], []
    for call in range(max_calls):
        inp = BlockInput(frame=frame, model=model, pose=pose, ground_truth=gt if GROUND_TRUTH in block.inputs else None,
                         rng=np.random.default_rng([*rng_seed, call]), cache=cache)
        r = block(inp)
        ms.append(r.elapsed * 1e3)
        if not (r.ok and r.pose is not None):
            failures.append(_reason(r.reason or "no pose"))
        else:
            pose = r.pose
        errors.append(pose_mssd(pose, gt, model) / d)
        if call == 0:
            mspd_1 = mspd(pose.R, pose.t, gt.R, gt.t, frame.K, model.vertices, eval_symmetries(model))
        if failures:
            break
    return RefineRecord(obj.obj_id, visibility_bin(obj.visib_fract), lam_index, before, errors[0], mspd_1,
                        errors[-1] <= TOLERANCE, any(e <= TOLERANCE for e in errors), pose, errors[-1], ms, failures)


def _refine_stats(records: list[RefineRecord]) -> dict[str, Any]:
    n = len(records)
    before = np.array([r.mssd_before for r in records])
    after = np.array([r.mssd_1 for r in records])
    ms = [m for r in records for m in r.ms]
    reasons = Counter(f for r in records for f in r.failures)
    return {
        "n": n,
        "improved": round(float(np.mean(after < before)), 4),
        "within_before": round(float(np.mean(before <= TOLERANCE)), 4),
        "within_1": round(float(np.mean(after <= TOLERANCE)), 4),
        "within_3": round(float(np.mean([r.within_3 for r in records])), 4),
        "reached_3": round(float(np.mean([r.reached_3 for r in records])), 4),
        "mssd_before": round(float(np.median(before)), 4),
        "mssd_1": round(float(np.median(after)), 4),
        "mspd_1": round(float(np.median([r.mspd_1 for r in records])), 3),
        "calls": len(ms),
        "fail_share": round(sum(reasons.values()) / max(len(ms), 1), 4),
        "reasons": dict(reasons.most_common()),
        "median_ms": round(float(np.median(ms)), 3) if ms else None,
    }


def _mann_whitney(good: np.ndarray, bad: np.ndarray) -> tuple[float, int]:
    """(wins, pairs): pairs (g, b) with g > b count 1, ties 1/2. NaN (a failed call) ranks lowest.
    Sorted counting, O(n log n): the pooled pairs of a large dataset never form a matrix."""
    if good.size == 0 or bad.size == 0:
        return 0.0, 0
    g = np.where(np.isnan(good), -np.inf, good)
    b = np.sort(np.where(np.isnan(bad), -np.inf, bad))
    below, not_above = np.searchsorted(b, g, side="left"), np.searchsorted(b, g, side="right")
    return float(np.sum(below) + 0.5 * np.sum(not_above - below)), int(g.size * b.size)


def _auc(wins: float, pairs: int) -> float | None:
    return round(wins / pairs, 4) if pairs else None


@dataclass
class _ScoreSamples:
    """The values of one score over the scored poses."""

    block: str
    lower_is_better: bool
    from_refiner: bool  # a refiner's own cost at the pose, before it moves (info["cost_before"])
    # key, obj_id, visibility bin, oriented value, within
    samples: list[tuple[int, int, str, float, bool]] = field(default_factory=list)
    ms: list[float] = field(default_factory=list)
    fails: int = 0

    def add(self, key: int, obj_id: int, visib_bin: str, value: float, within: bool, ms: float, ok: bool) -> None:
        self.samples.append((key, obj_id, visib_bin, value, within))
        self.ms.append(ms)
        self.fails += not ok

    def all_missing(self) -> bool:
        return all(np.isnan(s[3]) for s in self.samples)

    def stats(self) -> dict[str, Any]:
        return {"block": self.block, "lower_is_better": self.lower_is_better, "refiner_cost": self.from_refiner,
                **_score_stats(self.samples, self.ms, self.fails)}


def _score_stats(samples: list[tuple[int, int, str, float, bool]], ms: list[float], fails: int) -> dict[str, Any]:
    """samples: (instance key, obj_id, visibility bin, oriented score (higher = better, NaN failed), within)."""
    per_inst: dict[int, list[tuple[float, bool]]] = defaultdict(list)
    inst_group: dict[int, tuple[int, str]] = {}
    for key, obj_id, vbin, value, within in samples:
        per_inst[key].append((value, within))
        inst_group[key] = (obj_id, vbin)
    per_obj: dict[int, list[float]] = defaultdict(lambda: [0.0, 0])
    per_vis: dict[str, list[float]] = defaultdict(lambda: [0.0, 0])
    for key, vals in per_inst.items():
        v = np.array([x for x, _ in vals])
        w = np.array([y for _, y in vals])
        wins, pairs = _mann_whitney(v[w], v[~w])
        obj_id, vbin = inst_group[key]
        for acc in (per_obj[obj_id], per_vis[vbin]):
            acc[0] += wins
            acc[1] += pairs
    v = np.array([s[3] for s in samples])
    w = np.array([s[4] for s in samples], dtype=bool)
    pooled = _mann_whitney(v[w], v[~w])
    total = (sum(x[0] for x in per_obj.values()), sum(x[1] for x in per_obj.values()))
    return {
        "auc": _auc(*total), "pairs": total[1], "auc_pooled": _auc(*pooled),
        "poses": len(samples), "within_share": round(float(np.mean(w)), 4) if w.size else None,
        "fail_share": round(fails / max(len(ms), 1), 4),
        "median_ms": round(float(np.median(ms)), 3) if ms else None,
        "per_object": {str(k): {"auc": _auc(*x), "pairs": x[1]} for k, x in sorted(per_obj.items())},
        "per_visibility": {k: {"auc": _auc(*per_vis[k]), "pairs": per_vis[k][1]}
                           for k in sorted(per_vis, key=VISIBILITY_LABELS.index)},
    }


def bench_real(
    dataset: str | Path, pipeline: Pipeline | None = None, n_frames: int | None = None, seeds: int = 5,
    lambdas: Iterable[float] = DEFAULT_LAMBDAS, auc_lambdas: Iterable[float] = DEFAULT_AUC_LAMBDAS,
    max_calls: int = 3, min_visib: float = 0.3, seed: int = 0, blocks: Sequence[str] | None = None,
    split: str = "test", use_depth: bool = True, refiner_costs: bool = True, progress: bool = True,
) -> dict[str, Any]:
    """The refiner and score benchmark on the dataset's frames; a JSON-able dict (see the module doc)."""
    from tqdm import tqdm

    t_start = time.perf_counter()
    lambdas, auc_lambdas = [float(x) for x in lambdas], [float(x) for x in auc_lambdas]
    for x in (*lambdas, *auc_lambdas):
        if not np.isfinite(x) or x < 0:
            raise ValueError(f"bench real: lambdas must be finite numbers >= 0, got {x}")
    if n_frames is not None and n_frames < 1:
        raise ValueError(f"bench real: the number of frames must be >= 1 (or None: all), got {n_frames}")
    if seeds < 1 or max_calls < 1:
        raise ValueError(f"bench real: seeds and max_calls must be >= 1, got {seeds} and {max_calls}")
    ds = BopDataset(Path(dataset), split=split, use_depth=use_depth)
    pipeline = pipeline or load_pipeline()
    refiners, scorers = select_blocks(pipeline, blocks)
    keys = ds.image_keys()[:n_frames]
    if not keys:
        raise ValueError(f"{dataset}: no images in split {split!r}")

    refine: dict[str, list[RefineRecord]] = {n: [] for n in refiners}
    score_samples: dict[str, _ScoreSamples] = {}
    skipped: dict[str, str] = {}
    ran: set[str] = set()
    n_instances, depth_frames, instance_key = 0, 0, 0
    bar = tqdm(total=len(keys), desc="bench real", disable=not progress, unit="frame")
    for scene_id, im_id in keys:
        frame = ds.load_frame(scene_id, im_id)
        depth_frames += frame.has_depth
        cache: dict[str, Any] = {}  # the frame's shared precomputations, as in the environment
        active_ref, active_sc = {}, {}
        for name, block in [*refiners.items(), *scorers.items()]:
            why = block.frame_lacks(frame)
            if why:
                skipped.setdefault(name, why.split(":")[0])  # "needs depth", without the explanation
            else:
                ran.add(name)
                (active_ref if name in refiners else active_sc)[name] = block
        for oi, obj in usable_objects(frame, min_visib):
            n_instances += 1
            instance_key += 1
            d = obj.model.diameter
            for li, lam in enumerate(lambdas):
                starts = refiner_starts(obj.gt, lam, d, seeds, [seed, scene_id, im_id, oi], li)
                for name, block in active_ref.items():
                    for s, start in enumerate(starts):
                        refine[name].append(refine_chain(block, frame, obj, start, [seed, scene_id, im_id, oi, li, s],
                                                          cache, max_calls, li))
            poses = []
            for li, lam in enumerate(auc_lambdas):
                rng = np.random.default_rng([seed, scene_id, im_id, oi, _SCORE, li])
                poses += [perturb(obj.gt, lam, d, rng) for _ in range(seeds)]
            within = [pose_mssd(p, obj.gt, obj.model) / d <= TOLERANCE for p in poses]
            cost_refiners = {n: b for n, b in active_ref.items() if b.score_names} if refiner_costs else {}
            for name, block in [*active_sc.items(), *cost_refiners.items()]:
                is_refiner = name in refiners
                for pi, (p, w) in enumerate(zip(poses, within)):
                    r = block(BlockInput(frame=frame, model=obj.model, pose=p, cache=cache,
                                         rng=np.random.default_rng([seed, scene_id, im_id, oi, _SCORE, pi]),
                                         ground_truth=obj.gt if GROUND_TRUTH in block.inputs else None))
                    values = ({f"{name}:{block.score_names[0]}": r.info.get("cost_before", np.nan)} if is_refiner
                              else {sn: r.scores.get(sn, np.nan) for sn in block.score_names})
                    for sn, v in values.items():
                        v = float(v) if r.ok and v is not None else np.nan
                        v = v if np.isfinite(v) else np.nan
                        lower = (block.score_names[0] if is_refiner else sn) in block.lower_is_better
                        samples = score_samples.setdefault(sn, _ScoreSamples(name, lower, is_refiner))
                        samples.add(instance_key, obj.obj_id, visibility_bin(obj.visib_fract), -v if lower else v, w,
                                    r.elapsed * 1e3, r.ok)
        bar.update(1)
    bar.close()
    if n_instances == 0:
        raise ValueError(f"{dataset}: no annotated object with a model and visib_fract >= {min_visib} "
                         f"in the first {len(keys)} images")

    refiner_out: dict[str, Any] = {}
    for name, records in refine.items():
        if not records:
            continue
        block = refiners[name]
        entry: dict[str, Any] = {"block": block.name, "params": dict(block.config), "overall": {}, "per_object": {},
                                 "per_visibility": {}}
        for li, lam in enumerate(lambdas):
            at = [r for r in records if r.lam_index == li]
            entry["overall"][f"{lam:g}"] = _refine_stats(at)
            for obj_id in sorted({r.obj_id for r in at}):
                entry["per_object"].setdefault(str(obj_id), {})[f"{lam:g}"] = _refine_stats(
                    [r for r in at if r.obj_id == obj_id])
            for vbin in sorted({r.visib_bin for r in at}, key=VISIBILITY_LABELS.index):
                entry["per_visibility"].setdefault(vbin, {})[f"{lam:g}"] = _refine_stats(
                    [r for r in at if r.visib_bin == vbin])
        refiner_out[name] = entry
    scores_out = {sn: x.stats() for sn, x in score_samples.items() if not (x.from_refiner and x.all_missing())}
    return {
        "dataset": str(dataset),
        "split": split,
        "frames": len(keys),
        "frames_with_depth": int(depth_frames),
        "instances": n_instances,
        "settings": {"seeds": seeds, "lambdas": lambdas, "auc_lambdas": auc_lambdas, "max_calls": max_calls,
                     "min_visib": min_visib, "seed": seed, "tolerance_mssd_per_diameter": TOLERANCE,
                     "visibility_bins": list(VISIBILITY_BINS),
                     "use_depth": use_depth, "refiner_costs": refiner_costs, "pipeline": pipeline.source},
        "skipped": {n: why for n, why in skipped.items() if n not in ran},
        "refiners": refiner_out,
        "scores": scores_out,
        "seconds": round(time.perf_counter() - t_start, 1),
    }


def save_real(result: dict[str, Any], out: str | Path) -> tuple[Path, Path]:
    """Write the result as JSON (`out`, or out/real.json for a folder) and its figure beside it (.png)."""
    out = Path(out)
    path = out if out.suffix == ".json" else out / "real.json"
    atomic_write(path, json.dumps(jsonable(result), indent=1, allow_nan=False) + "\n")
    return path, plot_real(result, path.with_suffix(".png"))


def _pct(x: float | None) -> str:
    return "–" if x is None else f"{100 * x:.0f}%"


def format_real(result: dict[str, Any], per_object: bool = True) -> str:
    """Markdown tables: refiners (overall line, then per object unless `per_object` is False, then
    per visibility bucket), then scores (AUC overall, pooled and per object; then per visibility)."""
    lams = [f"{x:g}" for x in result["settings"]["lambdas"]]
    k = result["settings"]["max_calls"]
    head = ["refiner", "object", "n"]
    for lam in lams:
        if float(lam) == 0:
            head += [f"λ=0 stays (1 / {k} calls)", "λ=0 MSSD/d", "λ=0 MSPD px"]
        else:
            head += [f"λ={lam} improved", f"λ={lam} within: start → 1 → {k} calls (reached)"]
    head += ["fail", "ms"]
    lines = [f"{result['dataset']}: {result['frames']} frames ({result['frames_with_depth']} with depth), "
             f"{result['instances']} object instances, {result['settings']['seeds']} seeds, "
             f"{result.get('seconds', 0):.0f} s"]
    if result["refiners"]:
        lines += ["", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]

    def row(name: str, obj: str, stats: dict[str, dict[str, Any]]) -> str:
        first = stats[lams[0]]
        cells = [name, obj, str(first["n"])]
        for lam in lams:
            s = stats[lam]
            if float(lam) == 0:
                cells += [f"{_pct(s['within_1'])} / {_pct(s['within_3'])}", f"{s['mssd_1']:.3f}", f"{s['mspd_1']:.1f}"]
            else:
                cells += [_pct(s["improved"]), f"{_pct(s['within_before'])} → {_pct(s['within_1'])} → "
                          f"{_pct(s['within_3'])} ({_pct(s['reached_3'])})"]
        calls = sum(s["calls"] for s in stats.values())
        fails = sum(s["fail_share"] * s["calls"] for s in stats.values())
        ms = [s["median_ms"] for s in stats.values() if s["median_ms"] is not None]
        cells += [_pct(fails / max(calls, 1)), f"{np.median(ms):.1f}" if ms else "–"]
        return "| " + " | ".join(cells) + " |"

    for name, entry in result["refiners"].items():
        lines.append(row(f"**{name}**", "all", entry["overall"]))
        for obj, stats in entry["per_object"].items() if per_object else ():
            lines.append(row("", obj, stats))
        for vbin, stats in entry.get("per_visibility", {}).items():
            lines.append(row("", f"visib {vbin}", stats))
    if result["skipped"]:
        lines += ["", "skipped: " + ", ".join(f"{n} ({why})" for n, why in result["skipped"].items())]
    objs = sorted({o for s in result["scores"].values() for o in s["per_object"]}, key=int)
    if result["scores"]:
        head = ["score", "AUC (same object)", "pooled", *[f"obj {o}" for o in objs], "fail", "ms"]
        lines += ["", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for sn, s in result["scores"].items():
            per = [s["per_object"].get(o, {}).get("auc") for o in objs]
            cells = [sn, _f2(s["auc"]), _f2(s["auc_pooled"]), *[_f2(x) for x in per], _pct(s["fail_share"]),
                     f"{s['median_ms']:.1f}" if s["median_ms"] is not None else "–"]
            lines.append("| " + " | ".join(cells) + " |")
        per_vis = {sn: s.get("per_visibility", {}) for sn, s in result["scores"].items()}
        bins = [b for b in VISIBILITY_LABELS if any(b in v for v in per_vis.values())]
        if bins:
            head = ["score", *[f"AUC visib {b} (pairs)" for b in bins]]
            lines += ["", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
            for sn, v in per_vis.items():
                cells = [f"{_f2(v.get(b, {}).get('auc'))} ({v.get(b, {}).get('pairs', 0)})" for b in bins]
                lines.append("| " + " | ".join([sn, *cells]) + " |")
    return "\n".join(lines)


def _f2(x: float | None) -> str:
    return "–" if x is None else f"{x:.2f}"


def plot_real(result: dict[str, Any], path: str | Path) -> Path:
    """Bars, overall and per object: the share within tolerance after one call from the ground
    truth (lambda 0, when measured), and at the largest lambda at the start / after one call /
    after the chain, for every refiner; then each score's AUC per object."""
    from ..core.plots import plt, save_figure

    lams = [f"{x:g}" for x in result["settings"]["lambdas"]]
    lam, k = lams[lams.index(max(lams, key=float))], result["settings"]["max_calls"]
    bars = ([("0", "within_1", "λ=0: stays (1 call)")] if "0" in lams and lam != "0" else []) + [
        (lam, "within_before", f"λ={lam}: start"), (lam, "within_1", f"λ={lam}: 1 call"),
        (lam, "within_3", f"λ={lam}: {k} calls")]
    refiners = list(result["refiners"].items())
    scores = list(result["scores"].items())
    fig, axes = plt.subplots(1 + len(refiners) + (1 if scores else 0), 1, squeeze=False,
                             figsize=(9, 2.4 * (1 + len(refiners) + bool(scores))))
    axes = axes[:, 0]
    w = 0.8 / len(bars)
    panels = [(axes[0], [n for n, _ in refiners], [e["overall"] for _, e in refiners], "all objects: within tol.")]
    panels += [(ax, [f"obj {o}" for o in e["per_object"]], list(e["per_object"].values()), name)
               for ax, (name, e) in zip(axes[1:], refiners)]
    for ax, ticks, stats, ylabel in panels:
        x = np.arange(len(ticks))
        for i, (at, key, label) in enumerate(bars):
            ax.bar(x + (i - (len(bars) - 1) / 2) * w, [s[at][key] for s in stats], w, label=label)
        ax.set_xticks(x, ticks)
        ax.set_ylim(0, 1)
        ax.set_ylabel(ylabel, fontsize=8)
    axes[0].legend(fontsize=7, ncol=len(bars))
    axes[0].set_title(f"{result['dataset']}: share within MSSD <= {TOLERANCE} d")
    if scores:
        ax = axes[-1]
        objs = sorted({o for _, s in scores for o in s["per_object"]}, key=int)
        x = np.arange(len(objs))
        w = 0.8 / len(scores)
        for i, (sn, s) in enumerate(scores):
            ax.bar(x + (i - (len(scores) - 1) / 2) * w,
                   [s["per_object"].get(o, {}).get("auc") or 0.0 for o in objs], w, label=sn)
        ax.axhline(0.5, color="grey", lw=0.8)
        ax.set_xticks(x, [f"obj {o}" for o in objs])
        ax.set_ylim(0, 1)
        ax.set_ylabel("AUC (in vs out)")
        ax.legend(fontsize=7, ncol=4)
    fig.tight_layout()
    return save_figure(fig, path)
