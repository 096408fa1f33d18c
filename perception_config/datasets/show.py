"""A picture of one BOP frame with its ground truth: for checking a dataset by eye.

`show_frame` writes a PNG of two panels side by side, each the size of the frame:
- left: the RGB image, every ground-truth object rendered at its pose (objects occluding each
  other exactly) as a tinted silhouette where it agrees with the measured depth (within 2 cm,
  or depth missing: the visible part), its full silhouette as a contour in the object's colour,
  and a label "id" (+ name when models/parts.json has one, + visible fraction when
  scene_gt_info.json has it) at the projected model origin;
- right: the depth image in a colour map (turbo, near = blue), missing depth in magenta, the
  contours again, and a colour bar with the depth range in metres.
OpenCV only (no display, no matplotlib figure sizing): the PNG is exactly 2W x H.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..util.atomic_file import atomic_write

__all__ = ["show_frame", "object_colour"]

_PALETTE = [  # RGB, distinct and readable on grey
    (230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200), (245, 130, 48), (145, 30, 180),
    (70, 240, 240), (240, 50, 230), (210, 245, 60), (250, 190, 212), (0, 128, 128), (170, 110, 40),
]
MISSING_RGB = (255, 0, 255)


def object_colour(index: int) -> tuple[int, int, int]:
    return _PALETTE[index % len(_PALETTE)]


def _text(img: np.ndarray, s: str, org: tuple[int, int], scale: float = 0.45, colour=(255, 255, 255)) -> None:
    """Text on a dark box (readable on any background; no outline trick, whose glyph
    widths change with the thickness in OpenCV 5's font renderer)."""
    import cv2

    (tw, th), base = cv2.getTextSize(s, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    x, y = org
    y0, y1 = max(0, y - th - 2), min(img.shape[0], y + base)
    x0, x1 = max(0, x - 2), min(img.shape[1], x + tw + 2)
    img[y0:y1, x0:x1] = (img[y0:y1, x0:x1].astype(np.float32) * 0.35).astype(np.uint8)
    cv2.putText(img, s, org, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv2.LINE_AA)


def show_frame(
    dataset: str | os.PathLike,
    out_png: str | os.PathLike,
    scene_id: int | None = None,
    im_id: int | None = None,
    split: str = "test",
    use_depth: bool = True,
) -> Path:
    """Write a PNG (2W x H) of a frame of a BOP dataset with its ground-truth models overlaid
    (left) and its depth image (right). Defaults: the first scene and its first image. An
    RGB-only frame (or `use_depth=False`) shows on the right the ground truth's rendered depth,
    labelled as such, and overlays the full silhouettes on the left."""
    import cv2

    from ..core.render import render
    from .bop import BopDataset

    ds = BopDataset(dataset, split, use_depth=use_depth)
    scenes = ds.scene_ids()
    if not scenes:
        raise FileNotFoundError(f"no scenes in {ds.split_dir}")
    if scene_id is None:
        scene_id = scenes[0]
    if scene_id not in scenes:
        raise ValueError(f"scene {scene_id} is not in {ds.split_dir} (scenes: {scenes})")
    ims = ds.image_ids(scene_id)
    if im_id is None:
        im_id = ims[0]
    if im_id not in ims:
        raise ValueError(f"image {im_id} is not in scene {scene_id} "
                         f"(images: {ims[:20]}{' ...' if len(ims) > 20 else ''})")
    frame = ds.load_frame(scene_id, im_id)
    H, W = frame.height, frame.width
    names: dict[str, str] = {}
    pj = ds.models_dir / "parts.json"
    if pj.is_file():
        try:
            names = {k: v.get("name", "") for k, v in json.loads(pj.read_text()).items()}
        except (ValueError, AttributeError):
            names = {}

    objs = [o for o in frame.objects if o.gt is not None and o.model is not None]
    if objs:
        r = render([o.model for o in objs], [o.gt for o in objs], frame.K, W, H)
        mask, rdepth = r.mask, r.depth
    else:
        mask, rdepth = np.full((H, W), -1, np.int16), np.full((H, W), np.nan, np.float32)
    rgb_only = frame.depth is None
    measured = rdepth if rgb_only else frame.depth  # RGB-only: the rendered ground truth instead
    agree = (mask >= 0) & (~np.isfinite(measured) | (np.nan_to_num(measured, nan=0.0) >= rdepth - 0.02))

    left = frame.rgb.astype(np.float32).copy()
    for i in range(len(objs)):
        sel = agree & (mask == i)
        left[sel] = 0.55 * left[sel] + 0.45 * np.array(object_colour(i), np.float32)
    left = np.clip(left, 0, 255).astype(np.uint8)

    valid = np.isfinite(measured)
    right = np.zeros((H, W, 3), np.uint8)
    if valid.any():
        lo, hi = np.percentile(measured[valid], [1, 99])
        hi = max(hi, lo + 1e-3)
        d8 = np.clip((np.nan_to_num(measured, nan=lo) - lo) / (hi - lo) * 255, 0, 255).astype(np.uint8)
        right = cv2.cvtColor(cv2.applyColorMap(d8, cv2.COLORMAP_TURBO), cv2.COLOR_BGR2RGB)
    else:
        lo, hi = 0.0, 0.0
    right[~valid] = (0, 0, 0) if rgb_only else MISSING_RGB

    # contours of the full silhouettes (each object rendered with the others: its visible-
    # among-objects outline) and labels
    for i, _o in enumerate(objs):
        m = (mask == i).astype(np.uint8)
        if not m.any():
            continue
        contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        for img in (left, right):
            cv2.drawContours(img, contours, -1, object_colour(i), 1, cv2.LINE_AA)
    for i, o in enumerate(objs):
        c = frame.K @ o.gt.t
        if c[2] <= 0:
            continue
        u, v = int(round(c[0] / c[2])), int(round(c[1] / c[2]))
        label = str(o.obj_id)
        if names.get(str(o.obj_id)):
            label += " " + names[str(o.obj_id)]
        if o.visib_fract is not None:
            label += f" {100 * o.visib_fract:.0f}%"
        cv2.circle(left, (u, v), 3, object_colour(i), -1, cv2.LINE_AA)
        (tw, th), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.42, 1)
        x = int(np.clip(u + 5, 2, W - tw - 2))
        y = int(np.clip(v - 5, th + 2, H - 4))
        _text(left, label, (x, y), 0.42, object_colour(i))

    # header text and colour bar
    _text(left, f"{Path(dataset).name} {split} scene {scene_id} image {im_id}: {len(objs)} objects", (6, 16))
    if rgb_only:
        _text(right, f"no depth image: ground truth rendered, {lo:.3f}-{hi:.3f} m", (6, 16))
    else:
        _text(right, f"depth {lo:.3f}-{hi:.3f} m, magenta = missing ({100 * (~valid).mean():.1f}%)", (6, 16))
    bar_w, bar_h = min(200, W - 20), 10
    x0, y0 = W - bar_w - 10, H - bar_h - 10
    ramp = np.tile(np.linspace(0, 255, bar_w).astype(np.uint8), (bar_h, 1))
    right[y0:y0 + bar_h, x0:x0 + bar_w] = cv2.cvtColor(cv2.applyColorMap(ramp, cv2.COLORMAP_TURBO), cv2.COLOR_BGR2RGB)
    cv2.rectangle(right, (x0 - 1, y0 - 1), (x0 + bar_w, y0 + bar_h), (255, 255, 255), 1)
    _text(right, f"{lo:.2f} m", (x0, y0 - 4), 0.38)
    _text(right, f"{hi:.2f} m", (x0 + bar_w - 42, y0 - 4), 0.38)

    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    panel = np.concatenate([left, right], axis=1)
    ok, buf = cv2.imencode(".png", cv2.cvtColor(panel, cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError(f"could not encode {out}")
    return atomic_write(out, buf.tobytes())
