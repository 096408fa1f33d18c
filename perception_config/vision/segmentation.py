"""Scene segmentation of an RGB-D frame for the model-only generator (blocks/generation.py).

`segment_scene` removes the support surfaces (table, bin floor and walls; RANSAC planes) and
splits what stands on them into connected object-like regions of the depth image, cut at depth
jumps and concave creases, at three levels of detail (`Segmentation`, `Cluster`). Helpers:
organised points and normals of a depth image, a box-filtered depth, a robust region size.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ..core.scene import Frame

MIN_DEPTH_JUMP = 0.008  # metres: neighbour differences below this are noise or slanted surfaces
# An object spanning fewer pixels covers fewer than the 40 a region needs (segment_scene's
# min_pixels): a cube 6 px across covers at most ~21.
MIN_SPAN_PX = 6.0


@dataclass
class Cluster:
    """A connected object-like region of the depth image above the support surfaces."""

    pixels: np.ndarray  # (N,) flat pixel indices
    points: np.ndarray  # (N, 3) camera-frame points, metres
    extent: float  # robust diagonal of the PCA-aligned box, metres
    box: tuple[int, int, int, int]  # x, y, w, h in pixels
    colour_hist: np.ndarray | None = None  # hue histogram, filled on first use


@dataclass
class Segmentation:
    """Support surfaces removed, the rest split into clusters at three levels of detail (fine,
    split, coarse): the same object region can appear more than once, which is harmless for a
    generator that tries regions one after the other."""

    plane: np.ndarray | None  # (4,) n . p + d = 0, n towards the camera; None when no dominant plane
    plane_share: float  # share of valid pixels on the plane
    clusters: list[Cluster]
    n_valid: int
    points: np.ndarray  # (H, W, 3) organised camera-frame points, NaN where missing
    normals: np.ndarray  # (H, W, 3) unit normals from the smoothed depth, facing the camera; NaN where unknown
    labels: list[np.ndarray]  # per level, (H, W) int32 index into `clusters`, -1 outside
    support: np.ndarray  # (H, W) bool: pixels on the removed support surfaces (or below the table)

    @property
    def whole_levels(self) -> list[np.ndarray]:
        """The fine and coarse levels of `labels`, without the split one: their regions are whole
        objects as the depth shows them, where a split part can be a piece of a larger object
        (covering a piece is what a part placed on a larger object's face does)."""
        return self.labels[:1] + self.labels[-1:]


def organised_points(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W, 3) camera-frame points of every pixel (NaN where depth is missing or <= 0)."""
    h, w = depth.shape
    z = np.where(np.isfinite(depth) & (depth > 0), depth, np.nan).astype(np.float64)
    u = np.arange(w, dtype=np.float64)[None, :]
    v = np.arange(h, dtype=np.float64)[:, None]
    fx, fy, cx, cy, s = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    y = (v - cy) / fy * z
    x = (u - cx - s * (v - cy) / fy) / fx * z
    return np.stack([x, y, z], axis=-1)


def fit_plane_ransac(
    points: np.ndarray, rng: np.random.Generator, threshold: float, iterations: int = 200
) -> tuple[np.ndarray | None, np.ndarray]:
    """Dominant plane of (N, 3) points by RANSAC (vectorised over hypotheses on at most 4000
    samples) then two least-squares refits on the inliers. Returns (plane (4,) with the normal
    towards the camera origin, inlier mask), or (None, all-False mask) for degenerate input."""
    n = len(points)
    if n < 3:
        return None, np.zeros(n, bool)
    sample = points if n <= 4000 else points[rng.choice(n, 4000, replace=False)]
    idx = rng.integers(0, len(sample), size=(iterations, 3))
    a, b, c = sample[idx[:, 0]], sample[idx[:, 1]], sample[idx[:, 2]]
    normal = np.cross(b - a, c - a)
    norm = np.linalg.norm(normal, axis=1)
    ok = norm > 1e-9
    if not ok.any():
        return None, np.zeros(n, bool)
    normal, a = normal[ok] / norm[ok, None], a[ok]
    d = -np.einsum("ij,ij->i", normal, a)
    counts = (np.abs(sample @ normal.T + d) < threshold).sum(axis=0)
    best = int(np.argmax(counts))
    plane = np.r_[normal[best], d[best]]
    inl = np.abs(points @ plane[:3] + plane[3]) < threshold
    for _ in range(2):  # least-squares refit on the inliers, then re-select
        if inl.sum() < 3:
            break
        p = points[inl]
        centre = p.mean(axis=0)
        nrm = np.linalg.svd(p - centre, full_matrices=False)[2][2]
        plane = np.r_[nrm, -nrm @ centre]
        inl = np.abs(points @ plane[:3] + plane[3]) < threshold
    if plane[3] < 0:  # camera origin on the positive side: n . 0 + d > 0
        plane = -plane
    return plane, inl


def segment_scene(
    frame: Frame,
    rng: np.random.Generator,
    plane_distance: float = 0.008,
    depth_jump: float = 0.012,
    min_plane_share: float = 0.15,
    min_pixels: int = 40,
    concave_angle_deg: float = 30.0,
    support_extent: float = 0.25,
    max_planes: int = 5,
) -> Segmentation:
    """Remove the support surfaces (table, bin floor and walls) and split what stands on them
    into connected regions of the depth image.

    Support: the dominant plane's points and everything below it (the side away from the
    camera) are dropped; when no plane holds `min_plane_share` of the valid pixels (no table in
    view) every valid pixel is kept. Then up to `max_planes - 1` further planes are removed one
    at a time (RANSAC on what is left), each only as its largest connected patch in the image
    and only when that patch spans more than `support_extent` metres: bin floors and walls,
    not the flat faces of parts (which are smaller).

    Regions: 8-connected components after removing the pixels at depth jumps larger than
    max(`depth_jump` z^2, 8 mm) and on concave creases sharper than `concave_angle_deg` (where
    two touching objects meet; LCCP-style, convex edges of one object are kept). Three levels:
    "fine" additionally opens the mask with a 3x3 square (breaks thin bridges between touching
    objects: needed on the cluttered LM-O frame), "split" holds the parts of the coarse regions
    that wider openings break apart (split_regions: a box touching the keyboard behind it, a mug
    touching the brick in front of it, on the real YCB-Video frames), "coarse" does not open
    (keeps thin rims of small parts in one piece: needed for the synthetic bushings and
    flanges). Regions smaller than `min_pixels` are dropped; a region identical to one of an
    earlier level is kept once. An RGB-only frame (depth None) has no valid pixel: no plane, no
    region."""
    depth, K = frame.depth, frame.K
    if depth is None:  # an RGB-only frame: no depth to segment, no region (as an all-missing depth)
        depth = np.full((frame.height, frame.width), np.nan, np.float32)
    P = organised_points(depth, K)
    valid = np.isfinite(P[..., 2])
    n_valid = int(valid.sum())
    h, w = depth.shape
    if n_valid < 3:
        nan = np.full((h, w, 3), np.nan)
        return Segmentation(None, 0.0, [], n_valid, P, nan, [], np.zeros((h, w), bool))
    pts = P[valid]
    plane, inl = fit_plane_ransac(pts, rng, plane_distance)
    share = float(inl.mean()) if plane is not None else 0.0
    keep = valid.copy()
    if plane is not None and share >= min_plane_share:
        height = pts @ plane[:3] + plane[3]  # > 0 towards the camera
        keep[valid] = height > plane_distance
    else:
        plane = None
    for _ in range(max_planes - 1):
        rest = P[keep]
        if len(rest) < 100:
            break
        p2, inl2 = fit_plane_ransac(rest, rng, plane_distance)
        if p2 is None:
            break
        on = np.zeros_like(keep)
        on[keep] = inl2
        n_cc, lab, stats, _ = cv2.connectedComponentsWithStats(on.astype(np.uint8), connectivity=8)
        if n_cc < 2:
            break
        big = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        patch = lab == big
        if stats[big, cv2.CC_STAT_AREA] < 4 * min_pixels or robust_extent(P[patch]) < support_extent:
            break
        keep &= ~cv2.dilate(patch.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)

    z = np.where(valid, P[..., 2], np.nan)
    thr = np.maximum(depth_jump * np.nan_to_num(z, nan=1.0) ** 2, MIN_DEPTH_JUMP)
    cut = np.zeros_like(valid)
    with np.errstate(invalid="ignore"):
        jx = np.abs(np.diff(z, axis=1)) > np.minimum(thr[:, 1:], thr[:, :-1])
        jy = np.abs(np.diff(z, axis=0)) > np.minimum(thr[1:, :], thr[:-1, :])
    cut[:, 1:] |= jx
    cut[:, :-1] |= jx
    cut[1:, :] |= jy
    cut[:-1, :] |= jy
    Ps = organised_points(smooth_depth(depth), K)  # normals from raw 1 mm-quantised depth are noise
    normals = organised_normals(Ps)
    if concave_angle_deg < 180.0:
        cut |= concave_edges(Ps, normals, concave_angle_deg)
    coarse = (keep & ~cut).astype(np.uint8)
    fine = cv2.morphologyEx(coarse, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    n_fine, fine_labels = cv2.connectedComponents(fine, connectivity=8)
    n_coarse, coarse_labels = cv2.connectedComponents(coarse, connectivity=8)
    coarse_groups = pixel_groups(coarse_labels, n_coarse)
    n_split, split_labels = split_regions(coarse_groups, coarse_labels.shape, min_pixels)

    clusters: list[Cluster] = []
    seen: dict[tuple[int, int, int], int] = {}
    levels = []
    Pf = P.reshape(-1, 3)
    for n, labels, groups in ((n_fine, fine_labels, pixel_groups(fine_labels, n_fine)),
                              (n_split, split_labels, pixel_groups(split_labels, n_split)),
                              (n_coarse, coarse_labels, coarse_groups)):
        index = np.full(n, -1, np.int32)
        for lab in range(1, n):
            pix = groups[lab]
            if len(pix) < min_pixels:
                continue
            key = (len(pix), int(pix[0]), int(pix[-1]))
            if key in seen:
                index[lab] = seen[key]
                continue
            seen[key] = index[lab] = len(clusters)
            p = Pf[pix]
            xs, ys = pix % w, pix // w
            box = (int(xs.min()), int(ys.min()), int(xs.max() - xs.min()) + 1, int(ys.max() - ys.min()) + 1)
            clusters.append(Cluster(pix, p, robust_extent(p), box))
        levels.append(np.where(labels > 0, index[labels], -1).astype(np.int32))
    return Segmentation(plane, share, clusters, n_valid, P, normals, levels, valid & ~keep)


SPLIT_OPENINGS = (5, 9)  # pixels: the openings tried, smallest first, to split a region at its thin bridges


def pixel_groups(labels: np.ndarray, n: int) -> list[np.ndarray]:
    """The flat pixel indices of each label 0..n-1 of `labels` ((H, W) int), ascending."""
    flat = labels.ravel()
    order = np.argsort(flat, kind="stable")
    bounds = np.searchsorted(flat[order], np.arange(n + 1))
    return [order[bounds[lab]:bounds[lab + 1]] for lab in range(n)]


def split_regions(groups: list[np.ndarray], shape: tuple[int, int], min_pixels: int) -> tuple[int, np.ndarray]:
    """The "split" level: each region (`groups`: pixel_groups of a level's labels, 0 the
    background) that an opening of SPLIT_OPENINGS pixels (the smallest that does) breaks into
    two or more parts of 4 `min_pixels` or more, as those parts, labelled 1.. in an (H, W) image
    of `shape`; a region no opening splits is left out (it is already a region). Objects that
    touch through a bridge wider than the fine level's 3 pixels (a box against a keyboard behind
    it, a mug against a brick in front) come apart."""
    out = np.zeros(shape, np.int32)
    count = 1
    width = shape[1]
    for pix in groups[1:]:
        if len(pix) < 8 * min_pixels:
            continue
        ys, xs = pix // width, pix % width
        y0, x0 = ys.min(), xs.min()
        region = np.zeros((ys.max() - y0 + 1, xs.max() - x0 + 1), np.uint8)
        region[ys - y0, xs - x0] = 1
        for k in SPLIT_OPENINGS:
            opened = cv2.morphologyEx(region, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
            m, parts, stats, _ = cv2.connectedComponentsWithStats(opened, connectivity=8)
            big = [i for i in range(1, m) if stats[i, cv2.CC_STAT_AREA] >= 4 * min_pixels]
            if len(big) >= 2:
                for i in big:
                    py, px = np.nonzero(parts == i)
                    out[py + y0, px + x0] = count
                    count += 1
                break
    return count, out


def distinct_regions(clusters: list[Cluster], max_iou: float = 0.8) -> list[Cluster]:
    """`clusters` in their order without those overlapping an earlier kept one by more than
    `max_iou` (intersection over union of their pixels): the levels repeat most regions with a
    few pixels more or less, and a generator that fits a part to its best few regions would
    spend its slots on copies."""
    kept: list[Cluster] = []
    for cl in clusters:
        n = len(cl.pixels)
        if all(_iou(cl.pixels, k.pixels) <= max_iou for k in kept
               if min(n, len(k.pixels)) > max_iou * max(n, len(k.pixels))):
            kept.append(cl)
    return kept


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two sorted arrays of distinct pixel indices."""
    inter = len(np.intersect1d(a, b, assume_unique=True))
    return inter / (len(a) + len(b) - inter)


def frame_segmentation(frame: Frame, cache: dict | None, plane_distance: float = 0.008) -> Segmentation:
    """The frame's segmentation, computed once per frame and `plane_distance` and kept in the
    frame's shared cache (BlockInput.cache) for every generator. Deterministic: the plane
    RANSAC has its own fixed seed, so every caller sees the same regions."""
    key = f"gen:segmentation:{plane_distance:.4f}"
    seg = cache.get(key) if cache is not None else None
    if seg is None:
        seg = segment_scene(frame, np.random.default_rng(0), plane_distance)
        if cache is not None:
            cache[key] = seg
    return seg


def too_small(seg: Segmentation, K: np.ndarray, diameter: float) -> str:
    """Why an object of `diameter` metres cannot make a region of this depth image, or '' when
    it can: even at the nearest observed depth it would span fewer than MIN_SPAN_PX pixels."""
    z = seg.points[..., 2]
    if not np.any(np.isfinite(z)):
        return ""
    z_near = float(np.nanmin(z))
    span = min(K[0, 0], K[1, 1]) * diameter / z_near
    if span >= MIN_SPAN_PX:
        return ""
    return (f"the model is too small to find: {diameter * 1e3:.1f} mm across spans {span:.1f} px at the nearest "
            f"depth ({z_near:.2f} m), under the {MIN_SPAN_PX:.0f} px a region needs")


def dominant_label(seg: Segmentation, r: Any) -> int:
    """The region (coarse level) that most of a rendering `r` (render.Rendering) lies on, or -1."""
    if r.empty or not seg.labels:
        return -1
    rs, cs = r.crop_slices()
    under = seg.labels[-1][rs, cs][r.mask >= 0]
    under = under[under >= 0]
    if not len(under):
        under = seg.labels[0][rs, cs][r.mask >= 0]
        under = under[under >= 0]
        if not len(under):
            return -1
    return int(np.bincount(under).argmax())


def smooth_depth(depth: np.ndarray, size: int = 5) -> np.ndarray:
    """Box-filtered depth over fully valid windows (NaN where any pixel of the window is
    missing): removes quantisation noise before differentiating, without bleeding into holes."""
    valid = np.isfinite(depth) & (depth > 0)
    z = np.where(valid, depth, 0.0).astype(np.float32)
    k = (size, size)
    zs = cv2.boxFilter(z, -1, k, normalize=True, borderType=cv2.BORDER_REPLICATE)
    vs = cv2.boxFilter(valid.astype(np.float32), -1, k, normalize=True, borderType=cv2.BORDER_REPLICATE)
    return np.where(vs > 0.999, zs, np.nan).astype(np.float32)


def concave_edges(P: np.ndarray, N: np.ndarray, angle_deg: float, step: int = 2) -> np.ndarray:
    """Pixels on a concave crease: neighbours `step` apart whose normals differ by more than
    `angle_deg` and face each other ((n1 - n2) . (p1 - p2) < 0)."""
    out = np.zeros(P.shape[:2], bool)
    cos_thr = math.cos(math.radians(angle_deg))
    for axis in (0, 1):
        a = (slice(None, -step), slice(None)) if axis == 0 else (slice(None), slice(None, -step))
        b = (slice(step, None), slice(None)) if axis == 0 else (slice(None), slice(step, None))
        n1, n2, p1, p2 = N[a], N[b], P[a], P[b]
        with np.errstate(invalid="ignore"):
            bent = np.sum(n1 * n2, axis=-1) < cos_thr
            concave = np.sum((n1 - n2) * (p1 - p2), axis=-1) < 0
        e = bent & concave
        out[a] |= e
        out[b] |= e
    return out


def organised_normals(P: np.ndarray, step: int = 2) -> np.ndarray:
    """(H, W, 3) unit normals of an organised point image from central differences `step`
    pixels apart, facing the camera; NaN where a neighbour is missing."""
    n = np.full_like(P, np.nan)
    s = step
    du = P[s:-s, 2 * s:] - P[s:-s, : -2 * s]
    dv = P[2 * s:, s:-s] - P[: -2 * s, s:-s]
    c = np.cross(du, dv)
    with np.errstate(invalid="ignore", divide="ignore"):
        c /= np.linalg.norm(c, axis=-1, keepdims=True)
        flip = np.einsum("hwc,hwc->hw", c, P[s:-s, s:-s]) > 0
    c[flip] *= -1.0
    n[s:-s, s:-s] = c
    return n


def robust_extent(points: np.ndarray) -> float:
    """Diagonal of the PCA-aligned box of the 2nd..98th percentiles: the size of the region,
    insensitive to a few stray pixels and to how the object is oriented."""
    if len(points) < 3:
        return 0.0
    c = points - points.mean(axis=0)
    axes = np.linalg.svd(c[:: max(1, len(c) // 2000)], full_matrices=False)[2]
    proj = c @ axes.T
    lo, hi = np.percentile(proj, [2, 98], axis=0)
    return float(np.linalg.norm(hi - lo))
