"""How much of a real frame's occlusion the other annotated objects explain.

    python benchmarks/bench_occluders.py [--dataset ../shared/data/lmo-rgb]
        [--out benchmarks/results/occluders_lmo_rgb.json]

Occlusion is what holds the refiners and psi_rgb back on real photographs (bench real's
per-visibility split). RBOT-style multi-object refinement would render the other parts'
hypotheses as occluders; this measures the most that could give: every annotated object is
rendered at its ground truth, and an instance's occlusion by them (1 - its visible share in that
rendering) is compared with its annotated occlusion (1 - visib_fract), per visib_fract bucket
(bench real's), over the instances bench real uses (visib_fract >= 0.3). What the annotated
objects do not explain is unannotated clutter (on LM-O's scene, the benchvise and the rest).
About 10 s on one core.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before numpy/open3d start their thread pools

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from perception_config.bench.real import VISIBILITY_LABELS, visibility_bin  # noqa: E402
from perception_config.core.render import render  # noqa: E402
from perception_config.datasets.bop import BopDataset  # noqa: E402
from perception_config.util.atomic_file import atomic_write  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", default=str(ROOT.parent / "shared" / "data" / "lmo-rgb"))
    ap.add_argument("--min-visib", type=float, default=0.3, help="instances at least this visible (bench real's)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "occluders_lmo_rgb.json"))
    args = ap.parse_args()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the reader's rotation-projection warnings
        ds = BopDataset(args.dataset, use_depth=False)
        rows = []  # (bucket, annotated occlusion, occlusion by the annotated objects)
        for scene_id, im_id in ds.image_keys():
            frame = ds.load_frame(scene_id, im_id)
            objs = [o for o in frame.objects if o.gt is not None and o.model is not None]
            if not objs:
                continue
            scene = render([o.model for o in objs], [o.gt for o in objs], frame.K, frame.width, frame.height,
                           with_normals=False)
            for i, o in enumerate(objs):
                if o.visib_fract is None or o.visib_fract < args.min_visib:
                    continue
                alone = render([o.model], [o.gt], frame.K, frame.width, frame.height, with_normals=False)
                n = int(np.count_nonzero(alone.mask >= 0))
                if n:
                    rows.append((visibility_bin(o.visib_fract), 1.0 - o.visib_fract,
                                 1.0 - np.count_nonzero(scene.mask == i) / n))
    buckets = {}
    for label in [*VISIBILITY_LABELS, "all"]:
        sel = [r for r in rows if label in ("all", r[0])]
        if not sel:
            continue
        occluded, by_annotated = sum(r[1] for r in sel), sum(r[2] for r in sel)
        buckets[label] = {"instances": len(sel), "occluded": round(occluded / len(sel), 3),
                          "by_annotated_objects": round(by_annotated / len(sel), 3),
                          "share_explained": round(by_annotated / occluded, 3) if occluded > 0 else None}
    result = {"dataset": str(args.dataset), "min_visib": args.min_visib, "by_visibility": buckets}
    atomic_write(args.out, json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
