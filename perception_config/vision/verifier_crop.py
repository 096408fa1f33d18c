"""The rendered-against-observed crop a learned verifier looks at (render and compare, as the
scorers of CosyPose and MegaPose do, sized for a CPU).

`verifier_crop(frame, model, pose, cache)` renders the model at the hypothesis and samples a
square window around the rendering (side `CROP_MARGIN` x the rendered box's longer side,
centred on it) into a `CROP` x `CROP` grid, nearest neighbour. Channels (CHANNELS, in order;
every value O(1), relative to the object's diameter `d` so one network serves parts of every
size):

| # | name | value |
|---|---|---|
| 0 | residual | (observed - rendered depth) / d clipped to +-RESIDUAL_CLIP, scaled to +-1; 0 elsewhere |
| 1 | rendered_mask | 1 where the model is rendered |
| 2 | observed_rel | (observed depth - the rendered median) / d clipped to +-1; 0 without a depth |
| 3 | rendered_rel | (rendered depth - the rendered median) / d, 0 off the object |
| 4 | depth_valid | 1 where the sensor gave a depth |
| 5 | image_edges | exp(-distance to the nearest Canny edge of the grey image / EDGE_SCALE_PX) |
| 6 | rendered_outline | exp(-distance to the rendered outline / EDGE_SCALE_PX) |
| 7 | in_image | 1 where the window lies inside the image |

On an RGB-only frame the depth channels (0, 2, 4) are 0: a network trained with depth dropped
now and then (`drop_depth`) knows what a missing depth means. The edge channels are distances
(smooth), not edge pixels, so sampling a large object down to the grid loses no thin edge.
Colour itself is left out: the synthetic textures are not the real ones, edges and depth are
what transfers. Measured: ~1.5 ms a crop on a 640x480 frame after the rendering (cached per
frame and pose, shared with the pick features).
Shapes: the crop is float32 (len(CHANNELS), CROP, CROP); None when nothing is rendered.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from ..core.geometry import Pose
from ..core.models import ObjectModel
from ..core.scene import Frame
from .edges import canny_edges
from .visibility import hypothesis_rendering

CROP = 64  # px: the grid the window is sampled into
CROP_MARGIN = 1.4  # the window's side over the rendered box's longer side
RESIDUAL_CLIP = 0.1  # x diameter: residuals beyond this are all "far off"
EDGE_SCALE_PX = 3.0  # px in the grid: decay length of the edge distance channels
CHANNELS = ("residual", "rendered_mask", "observed_rel", "rendered_rel", "depth_valid", "image_edges",
            "rendered_outline", "in_image")
DEPTH_CHANNELS = (0, 2, 4)


def _window(r_box: tuple[int, int, int, int]) -> tuple[float, float, float]:
    """(x0, y0, step): the window's top-left corner in image pixels and its pixel step."""
    x, y, w, h = r_box
    side = CROP_MARGIN * max(w, h, 4)
    cx, cy = x + w / 2.0, y + h / 2.0
    return cx - side / 2.0, cy - side / 2.0, side / CROP


def _distance_channel(binary: np.ndarray, step: float) -> np.ndarray:
    """exp(-distance / EDGE_SCALE_PX) in grid pixels of a binary map already sampled to the grid
    (non-zero = edge); 0 everywhere when it has no edge."""
    if not binary.any():
        return np.zeros(binary.shape, np.float32)
    dist = cv2.distanceTransform(np.where(binary, 0, 255).astype(np.uint8), cv2.DIST_L2, 3)
    return np.exp(-dist / EDGE_SCALE_PX).astype(np.float32)


def _max_sample(edge_map: np.ndarray, xs: np.ndarray, ys: np.ndarray, inside: np.ndarray, step: float) -> np.ndarray:
    """The edge map (uint8, non-zero = edge) sampled to the grid so that no edge is lost: dilated
    by the grid's step before nearest sampling."""
    k = int(math.ceil(step))
    if k > 1:
        edge_map = cv2.dilate(edge_map, np.ones((k, k), np.uint8))
    out = edge_map[np.clip(ys, 0, edge_map.shape[0] - 1)[:, None], np.clip(xs, 0, edge_map.shape[1] - 1)[None, :]]
    return (out > 0) & inside


def verifier_crop(frame: Frame, model: ObjectModel, pose: Pose, cache: dict | None = None) -> np.ndarray | None:
    """The crop of CHANNELS at the hypothesis (module docstring); None when nothing is rendered."""
    r = hypothesis_rendering(frame, model, pose, cache)
    if r.empty:
        return None
    x0, y0, step = _window(r.box)
    grid = (np.arange(CROP, dtype=np.float64) + 0.5) * step
    xs, ys = np.floor(x0 + grid).astype(np.intp), np.floor(y0 + grid).astype(np.intp)
    inside = ((ys >= 0) & (ys < frame.height))[:, None] & ((xs >= 0) & (xs < frame.width))[None, :]
    # the rendering covers its box only
    rx, ry = xs - r.offset[0], ys - r.offset[1]
    rh, rw = r.depth.shape
    in_r = ((ry >= 0) & (ry < rh))[:, None] & ((rx >= 0) & (rx < rw))[None, :]
    ren = np.full((CROP, CROP), np.nan, np.float32)
    ren[in_r] = r.depth[np.clip(ry, 0, rh - 1)[:, None], np.clip(rx, 0, rw - 1)[None, :]][in_r]
    on_obj = np.isfinite(ren)
    d = float(model.diameter)
    z_ref = float(np.median(ren[on_obj])) if on_obj.any() else float(np.nanmedian(r.depth))
    out = np.zeros((len(CHANNELS), CROP, CROP), np.float32)
    out[1] = on_obj
    out[3] = np.where(on_obj, np.clip((ren - z_ref) / d, -1.0, 1.0), 0.0)
    out[7] = inside
    if frame.depth is not None:
        obs = frame.depth[np.clip(ys, 0, frame.height - 1)[:, None], np.clip(xs, 0, frame.width - 1)[None, :]]
        valid = inside & np.isfinite(obs) & (obs > 0)
        out[4] = valid
        out[2] = np.where(valid, np.clip((obs - z_ref) / d, -1.0, 1.0), 0.0)
        both = valid & on_obj
        out[0] = np.where(both, np.clip((obs - ren) / d, -RESIDUAL_CLIP, RESIDUAL_CLIP) / RESIDUAL_CLIP, 0.0)
    edges, _ = canny_edges(frame, cache)
    out[5] = _distance_channel(_max_sample(edges, xs, ys, inside, step), step)
    obj = on_obj.astype(np.uint8)
    outline = obj & (1 - cv2.erode(np.pad(obj, 1, mode="edge"), np.ones((3, 3), np.uint8))[1:-1, 1:-1])
    out[6] = _distance_channel(outline.astype(bool), step)
    return out


def without_depth(crop: np.ndarray) -> np.ndarray:
    """A copy of `crop` as an RGB-only frame gives it: its depth channels zero."""
    out = crop.copy()
    out[list(DEPTH_CHANNELS)] = 0
    return out


__all__ = ["CROP", "CHANNELS", "DEPTH_CHANNELS", "verifier_crop", "without_depth"]
