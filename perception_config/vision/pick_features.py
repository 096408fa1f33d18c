"""Features of a hypothesis for the learned pick-success score (blocks/pick_success.py; the scores
themselves come from the scoring blocks, run by blocks/features.py).

What a pick succeeds on is the pose error (symmetry-aware MSSD <= 0.1 x diameter), which no
score sees; these features are the evidence a frame gives about it, as plain floats (NaN where
the frame cannot tell, e.g. every depth feature on an RGB-only frame):

- the pipeline's own scores at the hypothesis (psi_d and its parts, psi_c, icp_fitness and
  icp_rmse, psi_rgb and its parts), from the scoring blocks with their default parameters, so
  a model trained here sees the same values whatever scoring set a pipeline runs; plus the
  shift (px, relative to the object's size in the image) at which psi_rgb's outline fits the
  image best: a hypothesis a few pixels off moves there;
- depth residuals (observed minus rendered depth over the rendered object pixels with an
  observed depth), relative to the object's diameter, so that one threshold serves parts of
  every size: signed median, median absolute residual, MAD, inlier shares at 1, 2 and 5 % of
  the diameter, the share observed more than 5 % behind the model (free-space violation: the
  sensor sees through where the object would be) and in front of it (occlusion), the share of
  rendered pixels without an observed depth;
- edge agreement of the rendered outline with the image's Canny edges (the per-frame edge
  cache psi_rgb and d2co share): mean truncated distance (share of the 10 px truncation), the
  share of outline pixels within 2 px of an edge, and the orientation-aware agreement at a 4 px
  truncation (psi_rgb_edges is the same at 10 px);
- visible fraction: the share of the model's surface samples that project into the image, and
  the share of the model's camera-facing samples that the z-buffer keeps (self-occlusion).

All of it reuses the rendering, visibility and edge caches of the frame (`cache`: the
BlockInput's). Measured per call (one core, shared machine): median 8.9 ms on the real LM-O
RGB-D frame, 7.8 ms on the real RGB photographs (benchmarks/bench_pick_success.py), ~15 ms on
the synthetic frames from a cold cache (test/test_pick_success.py prints it); one ICP or D2CO
call costs 20-40 ms.
"""
from __future__ import annotations

import math

import numpy as np

from ..core.geometry import Pose
from ..core.models import ObjectModel
from ..core.render import project
from ..core.scene import Frame
from .appearance import edge_agreement, nearest_edges
from .edges import canny_edges, silhouette_points
from .visibility import hypothesis_rendering, visible_surface

# The scores taken from the pipeline's scoring blocks (name -> block), in this order.
SCORE_FEATURES: tuple[tuple[str, str], ...] = (
    ("psi_d", "psi_d"), ("psi_d_m1", "psi_d"), ("psi_d_m2", "psi_d"),
    ("psi_c", "psi_c"),
    ("icp_fitness", "icp_fitness"), ("icp_rmse", "icp_fitness"),
    ("psi_rgb", "psi_rgb"), ("psi_rgb_region", "psi_rgb"), ("psi_rgb_edges", "psi_rgb"),
)
DEPTH_FEATURES: tuple[str, ...] = (
    "depth_median", "depth_abs_median", "depth_mad", "depth_inlier_01", "depth_inlier_02", "depth_inlier_05",
    "depth_behind", "depth_in_front", "depth_missing",
)
IMAGE_FEATURES: tuple[str, ...] = (
    "rgb_shift", "edge_distance", "edge_near_2px", "edge_oriented_4px", "in_image", "visible_share",
)
FEATURE_NAMES: tuple[str, ...] = tuple(n for n, _ in SCORE_FEATURES) + DEPTH_FEATURES + IMAGE_FEATURES
# Features that exist only with a depth image: on an RGB-only frame they are NaN.
NEEDS_DEPTH: frozenset[str] = frozenset({"psi_d", "psi_d_m1", "psi_d_m2", "icp_fitness", "icp_rmse", *DEPTH_FEATURES})

EDGE_TAU = 10.0  # px: truncation of the outline-to-edge distance (as psi_rgb)
EDGE_FINE_TAU = 4.0  # px: the orientation-aware agreement at a tighter truncation than psi_rgb_edges' 10 px
EDGE_MAX_ANGLE = math.radians(22.5)  # edge direction mismatch beyond which an edge does not count (as psi_rgb)
def depth_residuals(frame: Frame, model: ObjectModel, pose: Pose, cache: dict | None) -> dict[str, float]:
    """DEPTH_FEATURES (module docstring); all NaN on an RGB-only frame or an empty rendering."""
    out = dict.fromkeys(DEPTH_FEATURES, math.nan)
    if frame.depth is None:
        return out
    r = hypothesis_rendering(frame, model, pose, cache)
    if r.empty:
        return out
    obj = np.isfinite(r.depth)
    obs = frame.depth[r.crop_slices()][obj].astype(np.float64)
    ren = r.depth[obj].astype(np.float64)
    valid = np.isfinite(obs) & (obs > 0)
    out["depth_missing"] = float(1.0 - valid.mean())
    if not valid.any():
        return out
    d = float(model.diameter)
    res = (obs[valid] - ren[valid]) / d
    med = float(np.median(res))
    absres = np.abs(res)
    out.update(
        depth_median=med, depth_abs_median=float(np.median(absres)), depth_mad=float(np.median(np.abs(res - med))),
        depth_inlier_01=float(np.mean(absres <= 0.01)), depth_inlier_02=float(np.mean(absres <= 0.02)),
        depth_inlier_05=float(np.mean(absres <= 0.05)), depth_behind=float(np.mean(res > 0.05)),
        depth_in_front=float(np.mean(res < -0.05)),
    )
    return out


def outline_edges(frame: Frame, model: ObjectModel, pose: Pose, cache: dict | None) -> dict[str, float]:
    """edge_distance, edge_near_2px, edge_oriented_4px of the rendered outline against the image's
    Canny edges (module docstring); NaN when nothing is rendered."""
    out = {"edge_distance": math.nan, "edge_near_2px": math.nan, "edge_oriented_4px": math.nan}
    r = hypothesis_rendering(frame, model, pose, cache)
    if r.empty:
        return out
    uv, n = silhouette_points(r)
    norm = np.linalg.norm(n, axis=1)
    ok = (norm > 1e-6) & np.all((uv >= 0) & (uv < (frame.width, frame.height)), axis=1)
    if not ok.any():
        return out
    uv, n = uv[ok].astype(np.intp), n[ok] / norm[ok, None]
    pad = int(math.ceil(EDGE_TAU)) + 1
    x0, y0 = max(0, int(uv[:, 0].min()) - pad), max(0, int(uv[:, 1].min()) - pad)
    x1, y1 = min(frame.width, int(uv[:, 0].max()) + pad + 1), min(frame.height, int(uv[:, 1].max()) + pad + 1)
    edges, direction = canny_edges(frame, cache)
    dist, angle = nearest_edges(edges[y0:y1, x0:x1], direction[y0:y1, x0:x1])
    local = uv - (x0, y0)
    d = np.minimum(dist[local[:, 1], local[:, 0]], EDGE_TAU)
    out["edge_distance"] = float(d.mean() / EDGE_TAU)
    out["edge_near_2px"] = float(np.mean(d <= 2.0))
    out["edge_oriented_4px"] = edge_agreement(np.minimum(dist, EDGE_FINE_TAU), angle, local.astype(np.float64), n,
                                              EDGE_FINE_TAU, EDGE_MAX_ANGLE)[0]
    return out


def visibility(frame: Frame, model: ObjectModel, pose: Pose, cache: dict | None) -> dict[str, float]:
    """in_image (share of the surface samples projecting into the image) and visible_share
    (share of the camera-facing samples the z-buffer keeps)."""
    pc = pose.transform(model.points)
    uv = project(pc, frame.K)
    with np.errstate(invalid="ignore"):
        inside = (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= frame.width - 1) & (uv[:, 1] <= frame.height - 1)
    normals = model.point_normals @ pose.R.T
    facing = int(np.count_nonzero(np.einsum("ij,ij->i", normals, pc) < 0))
    vis = len(visible_surface(frame, model, pose, cache))
    return {"in_image": float(inside.mean()), "visible_share": float(min(1.0, vis / facing)) if facing else math.nan}


def features_from_scores(frame: Frame, model: ObjectModel, pose: Pose, scores: dict[str, float],
                         rgb_info: dict, cache: dict) -> dict[str, float]:
    """Every feature of FEATURE_NAMES for the hypothesis `pose` of `model` in `frame` (NaN where
    the frame cannot tell), given the scoring blocks' `scores` and psi_rgb's `rgb_info` at that
    pose (blocks.features.pick_features runs them). `cache`: the frame's shared cache."""
    out = {n: scores.get(n, math.nan) for n, _ in SCORE_FEATURES}
    out.update(depth_residuals(frame, model, pose, cache))
    shift = rgb_info.get("shift_px")
    n_obj = rgb_info.get("object_pixels", 0)
    out["rgb_shift"] = float(math.hypot(*shift) / math.sqrt(n_obj)) if shift is not None and n_obj else math.nan
    out.update(outline_edges(frame, model, pose, cache))
    out.update(visibility(frame, model, pose, cache))
    return {n: float(out[n]) if out[n] is not None and math.isfinite(out[n]) else math.nan for n in FEATURE_NAMES}


def rgb_only(features: dict[str, float]) -> dict[str, float]:
    """The same features as an RGB-only frame would give them: those that need depth set to NaN
    (nothing else depends on depth)."""
    return {n: (math.nan if n in NEEDS_DEPTH else v) for n, v in features.items()}


__all__ = ["FEATURE_NAMES", "NEEDS_DEPTH", "SCORE_FEATURES", "features_from_scores", "rgb_only", "depth_residuals",
           "outline_edges", "visibility"]
