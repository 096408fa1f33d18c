"""Image edges and the model contour, for the edge-based refiners (D2CO, chamfer, chamfer-ICP).

- `canny_edges`: the Canny edge map and each edge pixel's direction in [0, pi), once per frame.
- `directional_chamfer_tensor`: D2CO's directional chamfer distance tensor on a crop
  (Liu et al., CVPR 2010; Imperoli & Pretto, ICVS 2015): edge pixels split into `n_bins`
  orientation bins over [0, pi), a distance transform per bin, then a forward/backward pass
  across bins (cyclic) adding `penalty` px per bin of orientation difference, so a model edge
  point pays for distance and for orientation mismatch. Truncated at `max_distance`.
- `model_contour`: 3D model-frame points with 3D tangent directions on the contour visible from
  a hypothesis: visible sharp mesh edges plus the rendered silhouette back-projected (scanned
  meshes such as LM-O have few sharp edges, so the outline carries most of the signal).
- `project_with_directions`: pixel positions and image-plane directions (angle in [0, pi)).
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from ..geometry import Pose
from ..models import ObjectModel
from ..render import Box
from ..scene import Frame
from .scoring import image_derivatives, silhouette_points
from .visibility import hypothesis_rendering, visible_edges


def canny_edges(frame: Frame, cache: dict | None, low: float = 40.0, high: float = 100.0) -> tuple[np.ndarray, np.ndarray]:
    """(edges uint8 HxW, direction float32 HxW in [0, pi) along the edge), cached per frame."""
    key = f"edges:canny:{low}:{high}"
    if cache is not None and key in cache and cache[key][0] is frame.rgb:
        return cache[key][1]
    gray = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY)
    edges = cv2.Canny(cv2.GaussianBlur(gray, (5, 5), 1.0), low, high)
    gx, gy = image_derivatives(frame, cache)
    # The edge runs perpendicular to the gradient.
    direction = np.mod(np.arctan2(gy, gx) + np.pi / 2, np.pi).astype(np.float32)
    if cache is not None:
        cache[key] = (frame.rgb, (edges, direction))
    return edges, direction


def directional_chamfer_tensor(
    edges: np.ndarray, direction: np.ndarray, n_bins: int = 60, penalty: float = 0.5, max_distance: float = 30.0,
) -> np.ndarray:
    """The (n_bins, H, W) float32 directional chamfer tensor of an edge map crop (see above)."""
    h, w = edges.shape
    ys, xs = np.nonzero(edges)
    bins = np.minimum((direction[ys, xs] / np.pi * n_bins).astype(np.intp), n_bins - 1)
    dct = np.empty((n_bins, h, w), np.float32)
    for b in range(n_bins):
        img = np.full((h, w), 255, np.uint8)
        sel = bins == b
        if sel.any():
            img[ys[sel], xs[sel]] = 0
            dct[b] = cv2.distanceTransform(img, cv2.DIST_L2, cv2.DIST_MASK_5)
        else:
            dct[b] = max_distance
    np.minimum(dct, max_distance, out=dct)
    # Orientation propagation, cyclic over [0, pi): two rounds forward and backward suffice
    # because the penalty accumulates past max_distance within n_bins steps.
    for _ in range(2):
        for b in range(n_bins):
            np.minimum(dct[b], dct[b - 1] + penalty, out=dct[b])
        for b in range(n_bins - 1, -1, -1):
            np.minimum(dct[b], dct[(b + 1) % n_bins] + penalty, out=dct[b])
    return dct


def crop_box(frame: Frame, box: Box, margin: int, align: int = 1) -> Box:
    """The box grown by `margin` px, its corners snapped outwards to multiples of `align` (so
    nearby hypotheses share a crop and its cached tensor), clipped to the image."""
    x, y, w, h = box
    x0, y0 = (max(0, x - margin) // align) * align, (max(0, y - margin) // align) * align
    x1 = min(frame.width, -(-(x + w + margin) // align) * align)
    y1 = min(frame.height, -(-(y + h + margin) // align) * align)
    return (x0, y0, x1 - x0, y1 - y0)


def model_contour(frame: Frame, model: ObjectModel, pose: Pose, cache: dict | None, max_points: int,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Model-frame contour points (N, 3) and unit tangent directions (N, 3) visible from `pose`."""
    pts, dirs = [], []
    edges = visible_edges(frame, model, pose, cache)
    if len(edges):
        pts.append(model.edge_points[edges.index])
        dirs.append(model.edge_dirs[edges.index])
    r = hypothesis_rendering(frame, model, pose, cache)
    uv, n2d = silhouette_points(r)
    if len(uv):
        x0, y0 = r.offset
        iu = np.clip(uv[:, 0].astype(np.intp) - x0, 0, r.depth.shape[1] - 1)
        iv = np.clip(uv[:, 1].astype(np.intp) - y0, 0, r.depth.shape[0] - 1)
        z = r.depth[iv, iu].astype(np.float64)
        ok = np.isfinite(z) & (np.linalg.norm(n2d, axis=1) > 1e-6)
        K = frame.K
        u, v, z = uv[ok, 0], uv[ok, 1], z[ok]
        p_cam = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)
        t2 = np.stack([-n2d[ok, 1], n2d[ok, 0]], axis=1)  # along the outline
        t_cam = np.stack([t2[:, 0] * z / K[0, 0], t2[:, 1] * z / K[1, 1], np.zeros(len(z))], axis=1)
        pts.append((p_cam - pose.t) @ pose.R)  # camera -> model frame
        dirs.append(t_cam @ pose.R)
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, 3))
    P, D = np.concatenate(pts), np.concatenate(dirs)
    norm = np.linalg.norm(D, axis=1)
    keep = norm > 1e-12
    P, D = P[keep], D[keep] / norm[keep, None]
    if len(P) > max_points:
        idx = rng.choice(len(P), max_points, replace=False)
        P, D = P[idx], D[idx]
    return P, D


def project_with_directions(R: np.ndarray, t: np.ndarray, P: np.ndarray, D: np.ndarray, K: np.ndarray,
                            eps: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) of model points under (R, t) and the image angle in [0, pi) of their
    tangents (the projection of P + eps D minus that of P). Points behind the camera get NaN."""
    pc = P @ R.T + t
    qc = pc + eps * (D @ R.T)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2]
        v = K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]
        uq = K[0, 0] * qc[:, 0] / qc[:, 2] + K[0, 2]
        vq = K[1, 1] * qc[:, 1] / qc[:, 2] + K[1, 2]
    behind = pc[:, 2] <= 1e-3
    u[behind] = np.nan
    angle = np.mod(np.arctan2(vq - v, uq - u), math.pi)
    return np.stack([u, v], axis=1), angle


def bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray, outside: float) -> np.ndarray:
    """Bilinear samples of a 2D array at float pixel coordinates; `outside` beyond the array."""
    h, w = img.shape
    ok = np.isfinite(x) & np.isfinite(y) & (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    out = np.full(x.shape, outside, np.float64)
    xs, ys = x[ok], y[ok]
    x0 = np.minimum(xs.astype(np.intp), w - 2) if w > 1 else np.zeros(len(xs), np.intp)
    y0 = np.minimum(ys.astype(np.intp), h - 2) if h > 1 else np.zeros(len(ys), np.intp)
    fx, fy = xs - x0, ys - y0
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    out[ok] = (img[y0, x0] * (1 - fx) * (1 - fy) + img[y0, x1] * fx * (1 - fy)
               + img[y1, x0] * (1 - fx) * fy + img[y1, x1] * fx * fy)
    return out
