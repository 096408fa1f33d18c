"""The learned pick-success score on real photographs: AUC, Brier and ECE of a fitted model.

    python benchmarks/bench_pick_success.py [--model DIR] [--seeds 20] [--out benchmarks/results/pick_success_real.json]

Data (../shared, skipped when absent): the real LM-O RGB-D frame (../shared/data/lmo, scene 2
image 3), scored with its depth and again as RGB-only, and the twenty real LM-O photographs
without depth (../shared/data/lmo-rgb). Hypotheses: every annotated instance with visib_fract
>= 0.3, perturbed from its ground truth with the paper's noise model at lambda 0.1, 0.3 and
0.5, `--seeds` draws each; label: the pick criterion (symmetry-aware MSSD <= 0.1 x diameter)
against the ground truth. The model (default: the shipped one) was fitted on synthetic parts
only, so this measures transfer to real objects and a real sensor, not the fit. Writes the
JSON and a reliability PNG beside it; prints one line per set.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before numpy/open3d start their thread pools

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from perception_config.blocks.features import hypothesis_crop, pick_features  # noqa: E402
from perception_config.blocks.pick_success import SHIPPED_MODEL, load_model  # noqa: E402
from perception_config.core.geometry import perturb  # noqa: E402
from perception_config.core.metrics import pose_mssd  # noqa: E402
from perception_config.core.score_metrics import auc, score_metrics  # noqa: E402
from perception_config.datasets.bop import BopDataset  # noqa: E402
from perception_config.learning.pick_success_fit import plot_reliability  # noqa: E402
from perception_config.util.atomic_file import atomic_write  # noqa: E402

SHARED = REPO.parent / "shared" / "data"
LAMBDAS = (0.1, 0.3, 0.5)
SETS = ("lmo", "lmo-rgb", "ycbv-rgbd")  # folders of ../shared/data
BASELINES = ("psi_d", "psi_c", "icp_fitness", "psi_rgb")  # single scores the learned one is compared with


def score_frames(ds: BopDataset, model, seeds: int, use_depth: bool) -> dict[str, np.ndarray]:
    """Probabilities, labels, lambdas and feature times of the perturbed hypotheses of every frame."""
    p, y, lams, ms, inst, raw = [], [], [], [], [], {n: [] for n in BASELINES}
    for scene_id, im_id in ds.image_keys():
        frame = ds.load_frame(scene_id, im_id)
        for oi, obj in enumerate(frame.objects):
            visib = obj.visib_fract if obj.visib_fract is not None else 1.0
            if obj.model is None or obj.gt is None or visib < 0.3:
                continue
            cache: dict = {}
            d = obj.model.diameter
            for li, lam in enumerate(LAMBDAS):
                rng = np.random.default_rng([0, scene_id, im_id, oi, li])
                for _ in range(seeds):
                    pose = perturb(obj.gt, lam, d, rng)
                    t0 = time.perf_counter()
                    f = pick_features(frame, obj.model, pose, cache, use_depth=use_depth)
                    crop = hypothesis_crop(frame, obj.model, pose, cache, use_depth) if model.uses_crop else None
                    ms.append(1e3 * (time.perf_counter() - t0))
                    p.append(model.predict_one(f, crop))
                    y.append(pose_mssd(pose, obj.gt, obj.model) <= 0.1 * d)
                    lams.append(lam)
                    inst.append(hash((scene_id, im_id, oi)))
                    for n in BASELINES:
                        raw[n].append(f[n])
    return {"p": np.array(p), "y": np.array(y, bool), "lam": np.array(lams), "ms": np.array(ms),
            "instance": np.array(inst), **{f"score:{n}": np.array(v) for n, v in raw.items()}}


def within_instance_auc(v: np.ndarray, y: np.ndarray, instance: np.ndarray) -> float | None:
    """Mean over instances (with both outcomes) of the AUC among that instance's hypotheses, NaN
    scores ranked last: how well the score orders hypotheses of one object, as bench real does."""
    vals = []
    for k in np.unique(instance):
        sel = instance == k
        if 0 < y[sel].sum() < sel.sum():
            vals.append(auc(np.where(np.isfinite(v[sel]), v[sel], -np.inf), y[sel]))
    return float(np.mean(vals)) if vals else None


def summary(r: dict[str, np.ndarray]) -> dict:
    out = {k: v for k, v in score_metrics(r["p"], r["y"]).items() if k != "bins"}
    out["per_lambda"] = {f"{lam:g}": {k: v for k, v in score_metrics(r["p"][r["lam"] == lam], r["y"][r["lam"] == lam])
                                      .items() if k != "bins"} for lam in LAMBDAS}
    out["feature_ms_median"] = float(np.median(r["ms"])) if len(r["ms"]) else None
    # the same hypotheses ranked by single scores: pooled over instances and within each instance
    out["auc_pooled"] = {"pick_success": out["auc"]}
    out["auc_within_instance"] = {"pick_success": within_instance_auc(r["p"], r["y"], r["instance"])}
    for n in BASELINES:
        v = r[f"score:{n}"]
        if np.isfinite(v).any():
            out["auc_pooled"][n] = auc(np.where(np.isfinite(v), v, -np.inf), r["y"])
            out["auc_within_instance"][n] = within_instance_auc(v, r["y"], r["instance"])
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default=SHIPPED_MODEL, help="model file or folder (default: the shipped one)")
    ap.add_argument("--seeds", type=int, default=20, help="perturbed hypotheses per instance and lambda")
    ap.add_argument("--sets", nargs="+", choices=SETS, default=list(SETS),
                    help="the real sets to score (default: every one ../shared has)")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "pick_success_real.json")
    args = ap.parse_args()
    model = load_model(args.model)
    sets: dict[str, dict[str, np.ndarray]] = {}
    if "lmo" in args.sets and (SHARED / "lmo" / "models").is_dir():
        ds = BopDataset(SHARED / "lmo", "test")
        sets["lmo RGB-D"] = score_frames(ds, model, args.seeds, use_depth=True)
        sets["lmo as RGB-only"] = score_frames(ds, model, args.seeds, use_depth=False)
    if "ycbv-rgbd" in args.sets and (SHARED / "ycbv-rgbd" / "models").is_dir():
        sets["ycbv-rgbd RGB-D"] = score_frames(BopDataset(SHARED / "ycbv-rgbd", "test"), model, args.seeds,
                                               use_depth=True)
    if "lmo-rgb" in args.sets and (SHARED / "lmo-rgb" / "models").is_dir():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the annotations' near-rotations are projected, with a warning
            sets["lmo-rgb (RGB-only)"] = score_frames(BopDataset(SHARED / "lmo-rgb", use_depth=False), model,
                                                      args.seeds, use_depth=False)
    if not sets:
        print(f"no real data under {SHARED}: nothing measured")
        return 0
    result = {"model": str(args.model), "model_record": model.record, "seeds": args.seeds, "lambdas": list(LAMBDAS),
              "sets": {name: summary(r) for name, r in sets.items()}}
    for name, s in result["sets"].items():
        print(f"{name:20s} n={s['n']:5d} success {100 * s['base_rate']:5.1f} %  AUC {s['auc']:.3f}  "
              f"Brier {s['brier']:.3f}  ECE {s['ece']:.3f}  features {s['feature_ms_median']:.1f} ms")
        print("    AUC pooled / within instance: " + ", ".join(
            f"{n} {v:.3f}/{s['auc_within_instance'][n] or float('nan'):.3f}" for n, v in s["auc_pooled"].items()))
    atomic_write(args.out, json.dumps(result, indent=1) + "\n")
    png = plot_reliability({n: (r["p"], r["y"]) for n, r in sets.items()}, args.out.with_suffix(".png"),
                           "pick_success on real LM-O frames (model fitted on synthetic parts)")
    print(f"wrote {args.out} and {png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
