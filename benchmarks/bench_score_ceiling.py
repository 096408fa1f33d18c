"""Where an image score's AUC is lost on real photographs, and whether the annotations cap it.

    python benchmarks/bench_score_ceiling.py [--dataset ../shared/data/lmo-rgb] [--frames N]
        [--out benchmarks/results/score_ceiling_lmo_rgb.json]

The poses are `perception-config bench real`'s scored poses (lambda 0.05-0.5 x 5 seeds per
object instance with visib_fract >= 0.3, the same seeds), the AUC its same-instance AUC
(a pose within MSSD <= 0.1 d against one outside). Three questions, in one run on one core:

1. The annotation ceiling: a scorer that ranks perfectly by MSSD to a "true" pose, the
   annotation perturbed by the lambda noise model (median 0.03 d at lambda 0.07, 0.047 d at
   0.1, about the refiners' drift from the annotation), judged against the annotation.
2. Where psi_rgb loses: the AUC and the share of the misranked pairs by the MSSD of the
   out-of-tolerance pose (0.10-0.15 d, 0.15-0.20 d, ...).
3. Fusion: psi_rgb plus weights (0, 0.25, ..., 1) of the other scores and refiner costs
   (psi_c, chamfer's and region's cost at the pose), each standardised over the run.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before numpy/open3d start their thread pools

import argparse
import itertools
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from perception_config.bench.blocks import usable_objects  # noqa: E402
from perception_config.bench.real import _SCORE, DEFAULT_AUC_LAMBDAS, TOLERANCE, _mann_whitney  # noqa: E402
from perception_config.blocks import create  # noqa: E402
from perception_config.blocks.base import BlockInput  # noqa: E402
from perception_config.core.geometry import perturb  # noqa: E402
from perception_config.core.metrics import pose_mssd  # noqa: E402
from perception_config.datasets.bop import BopDataset  # noqa: E402
from perception_config.util.atomic_file import atomic_write  # noqa: E402

SEEDS = 5
TRUE_LAMBDAS = (0.07, 0.1)  # the annotation's own error in the ceiling check
BUCKETS = (0.10, 0.15, 0.20, 0.25, np.inf)
WEIGHTS = (0.0, 0.25, 0.5, 0.75, 1.0)


def _pairs(instance: np.ndarray, good: np.ndarray, bad: np.ndarray, score: np.ndarray) -> tuple[float, float]:
    """(wins, pairs) of bench real's Mann-Whitney count over pairs (good, bad) of the same instance."""
    wins = pairs = 0.0
    for i in np.unique(instance):
        k = instance == i
        w, p = _mann_whitney(score[k & good], score[k & bad])
        wins, pairs = wins + w, pairs + p
    return wins, pairs


def same_instance_auc(instance: np.ndarray, within: np.ndarray, score: np.ndarray) -> float:
    """bench real's AUC: pairs (within, outside) of the same instance; higher scores better."""
    wins, pairs = _pairs(instance, within, ~within, score)
    return round(wins / pairs, 4) if pairs else float("nan")


def lost_by_bucket(instance: np.ndarray, mssd: np.ndarray, score: np.ndarray) -> list[dict]:
    """psi_rgb's AUC and share of the misranked pairs, by the out-of-tolerance pose's MSSD / d."""
    within = mssd <= TOLERANCE
    rows, lost_total = [], 0.0
    for lo, hi in zip(BUCKETS[:-1], BUCKETS[1:]):
        wins, pairs = _pairs(instance, within, (mssd > lo) & (mssd <= hi), score)
        rows.append({"bad_mssd": [lo, None if np.isinf(hi) else hi], "pairs": int(pairs),
                     "auc": round(wins / pairs, 4) if pairs else None, "lost": pairs - wins})
        lost_total += pairs - wins
    for r in rows:
        r["share_of_lost"] = round(r.pop("lost") / lost_total, 3) if lost_total else None
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", default=str(ROOT.parent / "shared" / "data" / "lmo-rgb"))
    ap.add_argument("--frames", type=int, default=None, help="first N images (default: all)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "score_ceiling_lmo_rgb.json"))
    args = ap.parse_args()
    from tqdm import tqdm

    warnings.simplefilter("ignore")  # the LM-O annotations' SO(3) projection warning, once per file
    ds = BopDataset(Path(args.dataset), split="test")
    psi_rgb, psi_c = create("psi_rgb"), create("psi_c")
    costs = {"chamfer_cost": create("chamfer"), "region_cost": create("region")}
    rows: list[list[float]] = []
    t0, instance = time.perf_counter(), 0
    for scene_id, im_id in tqdm(ds.image_keys()[:args.frames], desc="frames", unit="frame"):
        frame = ds.load_frame(scene_id, im_id)
        cache: dict = {}
        for oi, obj in usable_objects(frame, 0.3):
            instance += 1
            d = obj.model.diameter
            trues = [perturb(obj.gt, lam, d, np.random.default_rng([7, instance, k]))
                     for k, lam in enumerate(TRUE_LAMBDAS)]
            for li, lam in enumerate(DEFAULT_AUC_LAMBDAS):
                rng = np.random.default_rng([0, scene_id, im_id, oi, _SCORE, li])
                for s in range(SEEDS):
                    pose = perturb(obj.gt, lam, d, rng)
                    seed = [0, scene_id, im_id, oi, _SCORE, li * SEEDS + s]  # bench real's pose index
                    scored = BlockInput(frame=frame, model=obj.model, pose=pose, cache=cache)
                    a, c = psi_rgb(scored), psi_c(scored)
                    row = [instance, pose_mssd(pose, obj.gt, obj.model) / d,
                           a.scores["psi_rgb"] if a.ok else np.nan, c.scores["psi_c"] if c.ok else np.nan]
                    for b in costs.values():
                        r = b(BlockInput(frame=frame, model=obj.model, pose=pose, cache=cache,
                                         rng=np.random.default_rng(seed)))
                        row.append(-float(r.info.get("cost_before", np.nan)))
                    row += [-pose_mssd(pose, t, obj.model) / d for t in trues]
                    row += [pose_mssd(t, obj.gt, obj.model) / d for t in trues]
                    rows.append(row)
    R = np.array(rows, dtype=np.float64)
    inst, mssd, within = R[:, 0], R[:, 1], R[:, 1] <= TOLERANCE
    names = ["psi_rgb", "psi_c", *costs]
    scores = {n: R[:, 2 + j] for j, n in enumerate(names)}
    n_true = len(TRUE_LAMBDAS)
    ceiling = [{"annotation_lambda": lam,
                "median_mssd_true_vs_annotation": round(float(np.median(R[:, -n_true + k])), 4),
                "auc_of_a_perfect_scorer": same_instance_auc(inst, within, R[:, 2 + len(names) + k])}
               for k, lam in enumerate(TRUE_LAMBDAS)]

    def standard(x: np.ndarray) -> np.ndarray:
        x = np.where(np.isfinite(x), x, np.nanmin(x))
        return (x - x.mean()) / max(x.std(), 1e-12)

    z = {n: standard(v) for n, v in scores.items()}
    best = max(((same_instance_auc(inst, within, z["psi_rgb"] + sum(w * z[n] for w, n in zip(ws, names[1:]))),
                 dict(zip(names[1:], ws))) for ws in itertools.product(WEIGHTS, repeat=len(names) - 1)),
               key=lambda x: x[0])
    result = {
        "dataset": args.dataset, "poses": len(R), "instances": instance,
        "auc": {n: same_instance_auc(inst, within, v) for n, v in scores.items()},
        "annotation_ceiling": ceiling,
        "psi_rgb_by_out_of_tolerance_mssd": lost_by_bucket(inst, mssd, scores["psi_rgb"]),
        "best_fusion": {"auc": best[0], "weights_on_standardised_scores": best[1]},
        "seconds": round(time.perf_counter() - t0, 1),
    }
    atomic_write(args.out, json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
