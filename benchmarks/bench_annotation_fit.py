"""Where the refiners go when they leave a real annotation, and how well the annotations fit the photographs.

    python benchmarks/bench_annotation_fit.py [--dataset ../shared/data/lmo-rgb]
        [--refiners d2co,chamfer,chamfer_icp,region] [--lambdas 0,0.1] [--seeds 5] [--calls 3]
        [--out benchmarks/results/annotation_fit_lmo_rgb.json]

bench real counts a refiner chain that starts within the tolerance (at the annotation, lambda 0,
or near it, lambda 0.1) and ends beyond MSSD 0.1 d as a loss. On real photographs the annotation
is not the image's truth to the pixel (on LM-O it lies a few px off the photographed object in
places: see the PNG), so this asks, for every instance bench real uses (visib_fract >= 0.3):
- how far psi_rgb's outline fit moves the annotation's outline over the image (its best shift,
  1 px steps within 8 px): the annotation's misfit as the image cues see it. Occlusion biases this
  too, so read it per object and beside the picture;
- for each refiner's chains (bench real's starts, seeds and calls): the MSSD / d at the end, and
  whether the image fits the end better than the annotation, judged by psi_rgb at the pose (no
  shift search) and by each of its two cues alone, so a refiner is also judged by a cue it does
  not optimise (region by the edges, the edge refiners by the colour separation).
A PNG beside the JSON shows the lambda 0 chains that left the tolerance: the annotation's outline
in green, the chain's end in magenta. About 6 min on one core for lmo-rgb.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before numpy/open3d start their thread pools

import argparse
import io
import json
import sys
import warnings
from collections import Counter, defaultdict
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from perception_config.bench.blocks import usable_objects  # noqa: E402
from perception_config.bench.real import DEFAULT_LAMBDAS, TOLERANCE, refine_chain, refiner_starts  # noqa: E402
from perception_config.blocks import load_all  # noqa: E402
from perception_config.blocks.base import RGB, BlockInput, Kind  # noqa: E402
from perception_config.datasets.bop import BopDataset  # noqa: E402
from perception_config.util.atomic_file import atomic_write  # noqa: E402
from perception_config.vision.debug_overlay import outline  # noqa: E402

CUES = ("psi_rgb", "psi_rgb_region", "psi_rgb_edges")
ZOOM = 2  # the PNG's crops are upscaled this much


def image_fit(scorer, frame, obj, pose, cache) -> dict[str, float]:
    """psi_rgb and its two cues at the pose itself (the scorer has no shift search); -1 when refused
    (ranks below every fit)."""
    r = scorer(BlockInput(frame=frame, model=obj.model, pose=pose, cache=cache))
    return {k: round(float(r.scores[k]), 4) if r.ok else -1.0 for k in CUES}


def crop_with_outlines(frame, obj, end_pose, label: str) -> np.ndarray:
    """A ZOOM x crop around the annotation: its outline green, `end_pose`'s magenta, `label` on top."""
    big = cv2.resize(frame.rgb, None, fx=ZOOM, fy=ZOOM, interpolation=cv2.INTER_NEAREST)
    for pose, colour in ((obj.gt, (0, 255, 0)), (end_pose, (255, 0, 255))):
        for c in outline(obj.model, pose, frame.K, frame.width, frame.height):
            cv2.polylines(big, [(c * ZOOM + (ZOOM - 1) / 2).astype(np.int32)], True, colour, 1)
    u, v = (frame.K @ obj.gt.t)[:2] / obj.gt.t[2]
    half = 55 * ZOOM
    x0 = int(np.clip(ZOOM * u - half, 0, big.shape[1] - 2 * half))
    y0 = int(np.clip(ZOOM * v - half, 0, big.shape[0] - 2 * half))
    tile = np.ascontiguousarray(big[y0:y0 + 2 * half, x0:x0 + 2 * half])
    cv2.rectangle(tile, (0, 0), (2 * half, 18), (0, 0, 0), -1)
    cv2.putText(tile, label, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1, cv2.LINE_AA)
    return tile


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataset", default=str(ROOT.parent / "shared" / "data" / "lmo-rgb"))
    ap.add_argument("--refiners", default="d2co,chamfer,chamfer_icp,region")
    ap.add_argument("--calls", type=int, default=3, help="successive calls from the annotation (bench real's)")
    ap.add_argument("--min-visib", type=float, default=0.3, help="instances at least this visible (bench real's)")
    ap.add_argument("--lambdas", default="0,0.1", help="bench real's starting noise levels to follow (0 and 0.1: "
                    "the starts within the tolerance)")
    ap.add_argument("--seeds", type=int, default=5, help="starts per instance at lambda > 0 (bench real's)")
    ap.add_argument("--seed", type=int, default=0, help="bench real's seed: the same starts and calls as its rows")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "annotation_fit_lmo_rgb.json"))
    args = ap.parse_args()
    args.lambdas = [float(x) for x in args.lambdas.split(",")]
    unknown = [x for x in args.lambdas if x not in DEFAULT_LAMBDAS]
    if unknown:
        ap.error(f"--lambdas: {unknown} are not bench real's ({', '.join(f'{x:g}' for x in DEFAULT_LAMBDAS)})")
    registry = load_all()
    known = sorted(n for n, cls in registry.items() if cls.kind == Kind.REFINEMENT and RGB in cls.inputs)
    unknown = [n for n in args.refiners.split(",") if n not in known]
    if unknown:
        ap.error(f"--refiners: unknown {unknown}; image refiners: {', '.join(known)}")
    refiners = {n: registry[n]() for n in args.refiners.split(",")}
    at_pose, shift_search = registry["psi_rgb"](), registry["psi_rgb"]()
    at_pose.config.update(search_radius=0)
    shift_search.config.update(search_step=1)
    rows, tiles = [], []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the reader's rotation-projection warnings
        ds = BopDataset(args.dataset, use_depth=False)
        for scene_id, im_id in ds.image_keys():
            frame = ds.load_frame(scene_id, im_id)
            cache: dict = {}
            for oi, obj in usable_objects(frame, args.min_visib):
                d = obj.model.diameter
                s = shift_search(BlockInput(frame=frame, model=obj.model, pose=obj.gt, cache=cache))
                shift = [int(x) for x in s.info.get("shift_px", (0, 0))] if s.ok else None
                row = {"scene": scene_id, "image": im_id, "obj_id": obj.obj_id,
                       "visib_fract": round(float(obj.visib_fract), 3), "shift_px": shift,
                       "annotation": image_fit(at_pose, frame, obj, obj.gt, cache), "refiners": {}}
                for name, block in refiners.items():
                    row["refiners"][name] = chains = []
                    for lam in args.lambdas:  # bench real's starts and calls for its lambda rows
                        li = DEFAULT_LAMBDAS.index(lam)
                        starts = refiner_starts(obj.gt, lam, d, args.seeds if lam > 0 else 1,
                                                [args.seed, scene_id, im_id, oi], li)
                        for si, start in enumerate(starts):
                            rec = refine_chain(block, frame, obj, start, [args.seed, scene_id, im_id, oi, li, si],
                                               cache, args.calls, li)
                            pose, mssd = rec.end, rec.mssd_end
                            chains.append({"lambda": lam, "start": si, "mssd_start": round(float(rec.mssd_before), 4),
                                           "mssd": round(float(mssd), 4),
                                           "end": image_fit(at_pose, frame, obj, pose, cache)})
                            if lam == 0 and mssd > TOLERANCE:
                                tiles.append(crop_with_outlines(frame, obj, pose, f"im {im_id} obj {obj.obj_id} "
                                                                                  f"{name}: {mssd:.3f} d"))
                rows.append(row)
    result = summarise(rows, args)
    # the summary indented, then one compact line per instance (every chain's end and image fit)
    lines = ",\n".join(json.dumps(r, separators=(",", ":"), allow_nan=False) for r in rows)
    summary = json.dumps(result, indent=1, allow_nan=False)[:-2]  # without its closing "\n}"
    atomic_write(args.out, summary + ',\n "instances": [\n' + lines + "\n ]\n}\n")
    if tiles:
        png = Path(args.out).with_suffix(".png")
        cols = 6
        tiles += [np.zeros_like(tiles[0])] * (-len(tiles) % cols)
        grid = np.vstack([np.hstack(tiles[i:i + cols]) for i in range(0, len(tiles), cols)])
        buf = io.BytesIO()  # a 256-colour palette keeps the photographs' PNG small enough for the repository
        Image.fromarray(grid).quantize(256).save(buf, format="PNG", optimize=True)
        atomic_write(png, buf.getvalue())
    print(json.dumps(result, indent=1))
    return 0


def summarise(rows: list[dict], args: argparse.Namespace) -> dict:
    """Per object: the annotation's best shift (median px, share >= 3 px); per refiner: the chains that
    left the tolerance, and how many of them end where each cue fits the image better than at the annotation."""
    shifts = defaultdict(list)
    for r in rows:
        if r["shift_px"] is not None:
            shifts[r["obj_id"]].append(float(np.hypot(*r["shift_px"])))
    every = [x for v in shifts.values() for x in v]
    per_object = {str(o): {"instances": len(v), "median_px": round(float(np.median(v)), 2),
                           "share_3px_or_more": round(float(np.mean(np.array(v) >= 3)), 3)}
                  for o, v in sorted(shifts.items())}
    refiners: dict = {}
    for name in args.refiners.split(","):
        for lam in args.lambdas:
            chains = [(r, c) for r in rows for c in r["refiners"][name] if c["lambda"] == lam]
            left = [(r, c) for r, c in chains if c["mssd_start"] <= TOLERANCE < c["mssd"]]
            refiners.setdefault(name, {})[f"{lam:g}"] = {
                "chains": len(chains), "started_within": sum(c["mssd_start"] <= TOLERANCE for _, c in chains),
                "left_tolerance": len(left),
                "left_and_image_fits_end_better": {k: sum(c["end"][k] > r["annotation"][k] for r, c in left)
                                                   for k in CUES},
                "all_chains_end_fits_better": {k: round(float(np.mean([c["end"][k] > r["annotation"][k]
                                                                       for r, c in chains])), 3) for k in CUES},
                "left_objects": dict(sorted(Counter(r["obj_id"] for r, _ in left).items())),
                "left_visib_fract_median": round(float(np.median([r["visib_fract"] for r, _ in left])), 3)
                if left else None}
    return {"dataset": str(args.dataset), "calls": args.calls, "lambdas": args.lambdas, "seeds": args.seeds,
            "min_visib": args.min_visib, "seed": args.seed,
            "tolerance_mssd_per_diameter": TOLERANCE,
            "annotation_shift": {"instances": len(every), "median_px": round(float(np.median(every)), 2),
                                 "share_3px_or_more": round(float(np.mean(np.array(every) >= 3)), 3),
                                 "per_object": per_object},
            "refiners": refiners}


if __name__ == "__main__":
    sys.exit(main())
