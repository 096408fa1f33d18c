"""The ground-truth-free generators on a BOP dataset's frames: `perception-config bench generators`.

Every annotated object of the chosen images with a model (and visib_fract >= `min_visib`) is one
query; each generator (a registered generation block, with the parameters a pipeline gives it) is
called once per query on the frame, with the frame's own cache and a seeded generator (the
annotation only to a block that declares it as an input, like simulated_init). Its ranked
candidates (BlockResult.candidates, best first) are judged against the annotation:

- a candidate is right when its MSSD is <= `tolerance` x the diameter (0.1: the simulated pick);
- `top1` / `top5`: the first right candidate is the first / among the first five;
- `confident_wrong`: the first candidate's confidence is >= `confident` and its MSSD > 0.3 x the
  diameter: an answer the cell would act on, and far off;
- `refused`: the call answered ok=False (its ranked rest may still hold a right candidate).

Every figure is given twice: with the symmetries the models declare (what BOP scores), and with
the declared or derived ones (core/symmetry.py: where a model declares none, the rotations that
map its surface onto itself within 2 % of the diameter, e.g. the 180-degree flips of a box). A
flip of a nearly symmetric box is a different pose to BOP and the same grasp to a robot: the
second column is the one that says whether the cell would pick the part. `wrong_shape` counts
queries confidently wrong under the derived symmetries too.

`any` (with two generators or more): a query counts in top5 when any generator has a right
candidate in its top five (the cell's agent can call each of them).

With a verifier (`verifier`: the pick-success model, `shipped` or a fit-score folder) every
candidate is also scored by it (the probability that the pose is within the pick tolerance),
and each generator's summary gets `verifier`: its AUC, Brier score and expected calibration
error over all candidates (labels: right under the declared or derived symmetries;
core/score_metrics.py), and what the generator would answer if it ranked by the verifier and
refused below `refuse_below`: `offered` (share of queries answered), `top1` (answered and
right) and `confident_wrong` (answered and more than 0.3 d off). `verifier_all`: the same
metrics over every generator's candidates.
Per generator, overall and per object id. Shapes: plain dicts and lists, JSON-able.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from ..blocks import load_all
from ..blocks.base import GROUND_TRUTH, BlockInput, create
from ..blocks.pipeline import Pipeline
from ..blocks.verified import probability, verifier_block
from ..core.metrics import pose_mssd, pose_mssd_derived
from ..core.scene import Frame
from ..core.score_metrics import score_metrics
from ..datasets.bop import BopDataset

DEFAULT_GENERATORS = ("resting_pose", "ppf", "global_registration")
TOLERANCE = 0.1  # x diameter: the simulated pick's test
WRONG = 0.3  # x diameter: far off
CONFIDENT = 0.5  # a first candidate's confidence counted as confident
SYMMETRIES = ("declared", "derived")  # judged with the declared symmetries / declared or derived
REFUSE_BELOW = 0.5  # a generator ranking by the verifier answers only from this probability


def pipeline_params(pipeline: Pipeline | None) -> dict[str, dict[str, Any]]:
    """Each block's parameters as `pipeline` sets them (its generator and actions, by block name;
    the first wins), e.g. the cell's ppf within 1 s; {} without a pipeline (the blocks' defaults)."""
    if pipeline is None:
        return {}
    params: dict[str, dict[str, Any]] = {}
    for block in [pipeline.generator] + [a.block for a in pipeline.actions]:
        params.setdefault(block.name, dict(block.config))
    return params


def judge_candidates(candidates: Sequence[tuple[float, Any]], obj: Any, confident: float = CONFIDENT,
                     tolerance: float = TOLERANCE) -> dict[str, Any]:
    """One query's ranked candidates [(confidence, Pose)] against the annotated object `obj`
    (a SceneObject with gt and model): per symmetry set, the rank of the first right candidate
    (-1: none), the first candidate's MSSD / diameter and whether it is confidently wrong."""
    d = obj.model.diameter
    top_conf = float(candidates[0][0]) if candidates else 0.0
    out: dict[str, Any] = {"candidates": len(candidates), "top1_confidence": top_conf}
    for sym, err in (("declared", pose_mssd), ("derived", pose_mssd_derived)):
        errors = [err(p, obj.gt, obj.model) / d for _, p in candidates]
        if sym == "derived":
            out["mssd_d_derived"] = errors  # of every candidate, best first
        out[f"rank_{sym}"] = next((k for k, e in enumerate(errors) if e <= tolerance), -1)
        out[f"top1_mssd_d_{sym}"] = errors[0] if errors else None
        out[f"confident_wrong_{sym}"] = bool(errors and top_conf >= confident and errors[0] > WRONG)
    return out


def generator_rows(name: str, frames: Iterable[Frame], params: dict[str, Any] | None = None,
                   min_visib: float = 0.0, confident: float = CONFIDENT, tolerance: float = TOLERANCE,
                   seed: int = 0, on_frame: Any = None, verifier: Any = None) -> list[dict[str, Any]]:
    """One row per query of generator `name` on `frames` (module doc); `on_frame()` after each
    frame. `verifier`: a pick_success block whose probability of each candidate goes in the
    row's `verifier` list."""
    block = create(name, **(params or {}))
    rows = []
    for frame in frames:
        cache: dict = {}
        for index, o in enumerate(frame.objects):
            if o.gt is None or o.model is None or (o.visib_fract is not None and o.visib_fract < min_visib):
                continue
            if block.frame_lacks(frame):
                continue
            rng = np.random.default_rng([seed, frame.scene_id, frame.im_id, index])
            inp = BlockInput(frame=frame, model=o.model, rng=rng, cache=cache,
                             ground_truth=o.gt if GROUND_TRUTH in block.inputs else None)
            r = block(inp)
            row = {"scene_id": frame.scene_id, "im_id": frame.im_id, "obj_id": o.obj_id,
                   "visib_fract": o.visib_fract, "ok": bool(r.ok), "reason": r.reason, "seconds": r.elapsed,
                   **judge_candidates(r.candidates, o, confident, tolerance)}
            if verifier is not None:
                row["verifier"] = [probability(verifier, inp, pose) for _, pose in r.candidates]
            rows.append(row)
        if on_frame is not None:
            on_frame()
    return rows


def verifier_figures(rows: list[dict[str, Any]], refuse_below: float = REFUSE_BELOW,
                     tolerance: float = TOLERANCE) -> dict[str, Any]:
    """The verifier on the rows' candidates (module doc): AUC, Brier and ECE over every
    candidate, and the answers of a generator that ranks by it and refuses below `refuse_below`."""
    p = np.array([x for r in rows for x in r["verifier"]], float)
    e = np.array([x for r in rows for x in r["mssd_d_derived"]], float)
    out = {k: v for k, v in score_metrics(p, e <= tolerance).items() if k != "bins"}
    offered = right = wrong = 0
    for r in rows:
        if not r["verifier"]:
            continue
        k = int(np.argmax(r["verifier"]))
        if r["verifier"][k] >= refuse_below:
            offered += 1
            right += r["mssd_d_derived"][k] <= tolerance
            wrong += r["mssd_d_derived"][k] > WRONG
    n = max(1, len(rows))
    out["ranked"] = {"refuse_below": refuse_below, "offered": offered / n, "top1": right / n,
                     "confident_wrong": wrong / n}
    return out


def _figures(rows: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {"queries": len(rows), "refused": float(np.mean([not r["ok"] for r in rows]))}
    for sym in SYMMETRIES:
        rank = np.array([r[f"rank_{sym}"] for r in rows])
        out[sym] = {"top1": float(np.mean(rank == 0)), "top5": float(np.mean((rank >= 0) & (rank < 5))),
                    "confident_wrong": float(np.mean([r[f"confident_wrong_{sym}"] for r in rows]))}
    return out


def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Figures of one generator's rows: overall, per object id, and its call times."""
    if not rows:
        return {"queries": 0}
    out = _figures(rows)
    out["median_s"] = float(np.median([r["seconds"] for r in rows]))
    out["p90_s"] = float(np.percentile([r["seconds"] for r in rows], 90))
    out["per_object"] = {str(obj): _figures([r for r in rows if r["obj_id"] == obj])
                         for obj in sorted({r["obj_id"] for r in rows})}
    if all("verifier" in r for r in rows):
        out["verifier"] = verifier_figures(rows)
    return out


def any_generator(rows_by_generator: dict[str, list[dict[str, Any]]]) -> dict[str, Any]:
    """top5 when any generator has a right candidate in its top five, per symmetry set, overall
    and per object id (the generators' rows are of the same queries, in the same order)."""
    runs = list(rows_by_generator.values())
    n = len(runs[0])
    objs = [r["obj_id"] for r in runs[0]]
    out: dict[str, Any] = {"queries": n, "generators": list(rows_by_generator), "per_object": {}}
    for sym in SYMMETRIES:
        hit = np.array([any(0 <= run[k][f"rank_{sym}"] < 5 for run in runs) for k in range(n)])
        out[sym] = {"top5": float(hit.mean())}
        for o in sorted(set(objs)):
            mine = np.array([oo == o for oo in objs])
            out["per_object"].setdefault(str(o), {})[sym] = {"top5": float(hit[mine].mean())}
    return out


def bench_generators(dataset: str | Path, generators: Sequence[str] = DEFAULT_GENERATORS,
                     pipeline: Pipeline | None = None, n_frames: int | None = None, min_visib: float = 0.0,
                     confident: float = CONFIDENT, split: str = "test", use_depth: bool = True, seed: int = 0,
                     verifier: str | None = None, progress: bool = True) -> dict[str, Any]:
    """The generators benchmark on the dataset's first `n_frames` images (all by default); a
    JSON-able dict: per generator its summary and rows, and `any` (module doc). `verifier`: a
    pick-success model (`shipped`, or a fit-score folder) scoring every candidate."""
    from tqdm import tqdm

    load_all()
    t0 = time.perf_counter()
    ds = BopDataset(Path(dataset), split=split, use_depth=use_depth)
    keys = ds.image_keys()[:n_frames]
    if not keys:
        raise ValueError(f"{dataset}: no images in split {split!r}")
    frames = [ds.load_frame(s, i) for s, i in keys]
    params = pipeline_params(pipeline)
    judge = None
    if verifier is not None:
        judge = verifier_block(verifier)
    runnable = [g for g in generators if not create(g, **params.get(g, {})).frame_lacks(frames[0])]
    skipped = sorted(set(generators) - set(runnable))
    rows_by: dict[str, list[dict[str, Any]]] = {}
    with tqdm(total=len(frames) * len(runnable), desc="bench generators", unit="frame", disable=not progress) as bar:
        for g in runnable:
            bar.set_postfix_str(g)
            rows_by[g] = generator_rows(g, frames, params.get(g), min_visib, confident, seed=seed,
                                        on_frame=lambda: bar.update(1), verifier=judge)
    result: dict[str, Any] = {
        "dataset": str(dataset), "split": split, "images": len(frames), "use_depth": use_depth,
        "min_visib": min_visib, "confident": confident, "tolerance": TOLERANCE, "wrong": WRONG, "seed": seed,
        "verifier": verifier,
        "skipped": {g: "the frames lack what it needs" for g in skipped},
        "generators": {g: {"params": params.get(g, {}), "summary": summarize(rows), "rows": rows}
                       for g, rows in rows_by.items()},
        "seconds": round(time.perf_counter() - t0, 1),
    }
    if len(rows_by) >= 2 and all(rows_by.values()):
        result["any"] = any_generator(rows_by)
    if judge is not None and any(rows_by.values()):
        result["verifier_all"] = verifier_figures([r for rows in rows_by.values() for r in rows])
    return result


def _pct(x: float | None) -> str:
    return "   -" if x is None else f"{100 * x:3.0f}%"


def format_generators(result: dict[str, Any], per_object: bool = True) -> str:
    """The result as a table: per generator (and per object), top-1 / top-5 / confident wrong
    with the declared symmetries and with the declared or derived ones."""
    head = (f"{'generator':<20} {'object':>6} {'queries':>7} {'refused':>7}   declared: top-1 top-5 conf.wrong"
            f"   derived: top-1 top-5 conf.wrong")
    lines = [f"{result['dataset']} ({result['images']} images, visib >= {result['min_visib']}): first right "
             f"candidate within MSSD {result['tolerance']} d; confident wrong: confidence >= {result['confident']} "
             f"and MSSD > {result['wrong']} d", head]

    def line(name: str, obj: str, f: dict[str, Any]) -> str:
        d, v = f["declared"], f["derived"]
        return (f"{name:<20} {obj:>6} {f['queries']:>7} {_pct(f['refused']):>7}   {'':>9} {_pct(d['top1']):>5} "
                f"{_pct(d['top5']):>5} {_pct(d['confident_wrong']):>10}   {'':>8} {_pct(v['top1']):>5} "
                f"{_pct(v['top5']):>5} {_pct(v['confident_wrong']):>10}")

    for g, res in result["generators"].items():
        s = res["summary"]
        if not s["queries"]:
            lines.append(f"{g:<20} {'all':>6} {0:>7}")
            continue
        lines.append(line(g, "all", s) + f"   {s['median_s']:.2f} s median")
        if per_object:
            lines += [line("", k, f) for k, f in s["per_object"].items()]
    if "any" in result:
        a = result["any"]
        lines.append(f"{'any of them':<20} {'all':>6} {a['queries']:>7} {'':>7}   {'':>9} {'':>5} "
                     f"{_pct(a['declared']['top5']):>5} {'':>10}   {'':>8} {'':>5} {_pct(a['derived']['top5']):>5}")
    for g, why in result["skipped"].items():
        lines.append(f"{g}: not run ({why})")
    judged = [(g, r["summary"]["verifier"]) for g, r in result["generators"].items() if "verifier" in r["summary"]]
    if judged:
        lines.append(f"verifier {result['verifier']} on the candidates (right: within {result['tolerance']} d, "
                     f"declared or derived symmetries); ranked by it, answering from p >= {REFUSE_BELOW}:")
        lines.append(f"{'generator':<20} {'candidates':>10} {'AUC':>6} {'Brier':>6} {'ECE':>6}   {'answered':>8} "
                     f"{'right':>6} {'conf.wrong':>10}")
        for g, v in judged + ([("all", result["verifier_all"])] if "verifier_all" in result else []):
            k = v["ranked"]
            lines.append(f"{g:<20} {v['n']:>10} {_f3(v.get('auc')):>6} {_f3(v.get('brier')):>6} "
                         f"{_f3(v.get('ece')):>6}   {_pct(k['offered']):>8} {_pct(k['top1']):>6} "
                         f"{_pct(k['confident_wrong']):>10}")
    return "\n".join(lines)


def _f3(x: float | None) -> str:
    return "-" if x is None or not np.isfinite(x) else f"{x:.3f}"


def plot_generators(result: dict[str, Any], path: str | Path) -> Path:
    """Per generator and object: top-5 and confident wrong, declared and derived symmetries (PNG)."""
    from ..core.plots import plt, save_figure

    gens = [g for g, r in result["generators"].items() if r["summary"]["queries"]]
    objs = sorted({k for g in gens for k in result["generators"][g]["summary"]["per_object"]}, key=int)
    fig, axes = plt.subplots(1, 2, figsize=(4 + 1.2 * len(objs) * max(1, len(gens)) / 2, 4), squeeze=False)
    width = 0.8 / max(1, len(gens))
    x = np.arange(len(objs) + 1)
    for ax, (key, title) in zip(axes[0], (("top5", "top-5 (right in the first five)"),
                                          ("confident_wrong", "confident wrong"))):
        for k, g in enumerate(gens):
            s = result["generators"][g]["summary"]
            figs = [s] + [s["per_object"].get(o) for o in objs]
            for sym, alpha in (("declared", 0.45), ("derived", 1.0)):
                vals = [f[sym][key] if f else np.nan for f in figs]
                ax.bar(x + k * width, vals, width * 0.9, alpha=alpha, color=f"C{k}",
                       label=g if sym == "derived" else None)
        ax.set_xticks(x + width * (len(gens) - 1) / 2, ["all"] + [f"obj {o}" for o in objs])
        ax.set_ylim(0, 1)
        ax.set_title(title)
        ax.grid(axis="y", alpha=0.3)
    axes[0][0].legend(fontsize=7, title="dark: declared or derived symmetries\nlight: declared only",
                      title_fontsize=7)
    fig.suptitle(f"generators on {Path(result['dataset']).name}: {result['images']} images")
    fig.tight_layout()
    return save_figure(fig, path)


def save_generators(result: dict[str, Any], out: str | Path) -> tuple[Path, Path]:
    """generators.json and generators.png into the folder `out` (or `out` itself if it ends in .json)."""
    from ..datasets.bop_json import save_json

    out = Path(out)
    json_path = out if out.suffix == ".json" else out / "generators.json"
    json_path.parent.mkdir(parents=True, exist_ok=True)
    save_json(json_path, result)
    return json_path, plot_generators(result, json_path.with_suffix(".png"))
