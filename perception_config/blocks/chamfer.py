"""The paper's comparison methods for edge-based refinement: chamfer matching and chamfer-ICP.

Both use the model contour visible from the hypothesis (edges.model_contour) and the plain
(non-directional) distance transform of the image's Canny edges on a crop around it.
- `chamfer`: local search over pose perturbations (random, shrinking radius) keeping the pose
  with the lowest mean truncated chamfer distance of the projected contour points.
- `chamfer_icp`: ICP in the image: each projected contour point is matched to its nearest
  image edge pixel (the distance transform's labels), the pose is re-estimated from these
  2D-3D matches with PnP (Levenberg-Marquardt, from the current pose), and the matching
  distance shrinks from `max_match_px` to `min_match_px` over the iterations.
Like D2CO, both fix the image-plane position and rotation well and depth weakly.
"""
from __future__ import annotations

import time

import cv2
import numpy as np

from ..geometry import Pose, exp_so3
from ..render import projected_box
from .base import MODEL, POSE, RGB, Block, BlockInput, BlockResult, Kind, Param, register
from .edges import bilinear, canny_edges, crop_box, model_contour, project_with_directions


def _edge_distance(inp: BlockInput, margin: int, low: float, high: float):
    """(crop, distance transform, labels -> (x, y) of the nearest edge pixel) cached per crop."""
    frame, pose = inp.frame, inp.pose
    box = projected_box(inp.model, pose, frame.K, frame.width, frame.height)
    if box is None:
        return None, "the object at the hypothesis is outside the image"
    crop = crop_box(frame, box, margin, align=32)
    key = ("chamfer:dt", crop, low, high)
    entry = inp.cache.get(key)
    if entry is not None and entry[0] is frame.rgb:
        return entry[1], ""
    edges, _ = canny_edges(frame, inp.cache, low, high)
    x0, y0, w, h = crop
    e = edges[y0:y0 + h, x0:x0 + w]
    if not e.any():
        return None, "no image edges around the hypothesis"
    dt, labels = cv2.distanceTransformWithLabels(np.where(e > 0, 0, 255).astype(np.uint8), cv2.DIST_L2, 5,
                                                 labelType=cv2.DIST_LABEL_PIXEL)
    ey, ex = np.nonzero(e > 0)
    # OpenCV numbers zero pixels in row-major scan order starting at 1.
    order = np.argsort(ey * w + ex)
    lut = np.zeros((len(ex) + 1, 2), np.float64)
    lut[1:, 0], lut[1:, 1] = ex[order], ey[order]
    value = (crop, dt, labels, lut)
    inp.cache[key] = (frame.rgb, value)
    return value, ""


def _contour(inp: BlockInput, max_points: int):
    P, D = model_contour(inp.frame, inp.model, inp.pose, inp.cache, max_points, inp.rng)
    return P, D


@register
class ChamferMatching(Block):
    """Simple chamfer matching: a random local search minimising the mean chamfer distance."""

    kind = Kind.REFINEMENT
    name = "chamfer"
    inputs = (RGB, MODEL, POSE)
    score_names = ("chamfer_cost",)
    params = (
        Param("rounds", 4, 1, 20, doc="search rounds; the radius halves each round"),
        Param("candidates", 40, 4, 1000, doc="random poses tried per round"),
        Param("rotation_deg", 4.0, 0.1, 45.0, doc="first-round rotation radius (deg)"),
        Param("translation_mm", 6.0, 0.1, 100.0, doc="first-round image-plane translation radius (mm)"),
        Param("max_distance", 20.0, 1.0, 200.0, doc="truncation of the chamfer distance (px)"),
        Param("crop_margin", 40, 0, 400, doc="pixels around the hypothesis's box"),
        Param("canny_low", 40.0, 0.0, 1000.0), Param("canny_high", 100.0, 0.0, 1000.0),
        Param("max_points", 300, 20, 5000, doc="contour points used (random subset)"),
        Param("max_seconds", 0.1, 0.001, 10.0, doc="time bound (s)"),
    )

    def run(self, inp: BlockInput) -> BlockResult:
        c, frame, pose0 = self.config, inp.frame, inp.pose
        assert pose0 is not None
        start = time.perf_counter()
        edge, why = _edge_distance(inp, int(c["crop_margin"]), c["canny_low"], c["canny_high"])
        if edge is None:
            return BlockResult.fail(why)
        (x0, y0, _w, _h), dt, _labels, _lut = edge
        P, D = _contour(inp, int(c["max_points"]))
        if len(P) < 6:
            return BlockResult.fail(f"only {len(P)} contour points visible from the hypothesis")
        cap = float(c["max_distance"])
        dtc = np.minimum(dt, cap)

        def cost(R: np.ndarray, t: np.ndarray) -> float:
            uv, _ = project_with_directions(R, t, P, D, frame.K)
            return float(np.mean(bilinear(dtc, uv[:, 0] - x0, uv[:, 1] - y0, cap)))

        best_R, best_t = pose0.R, pose0.t
        best = cost0 = cost(best_R, best_t)
        rot, trans = np.radians(c["rotation_deg"]), c["translation_mm"] * 1e-3
        for _ in range(int(c["rounds"])):
            for _ in range(int(c["candidates"])):
                if time.perf_counter() - start > c["max_seconds"]:
                    break
                R = exp_so3(inp.rng.normal(0.0, rot / np.sqrt(3), 3)) @ best_R
                t = best_t + np.append(inp.rng.normal(0.0, trans / np.sqrt(2), 2), 0.0)
                value = cost(R, t)
                if value < best:
                    best, best_R, best_t = value, R, t
            rot, trans = rot / 2, trans / 2
        return BlockResult(ok=True, pose=Pose(best_R, best_t), scores={"chamfer_cost": best},
                           info={"cost_before": cost0, "improved": best < cost0})


@register
class ChamferIcp(Block):
    """Chamfer-ICP: nearest image edge pixel per contour point, then PnP; repeated."""

    kind = Kind.REFINEMENT
    name = "chamfer_icp"
    inputs = (RGB, MODEL, POSE)
    score_names = ("chamfer_cost",)
    params = (
        Param("iterations", 8, 1, 100, doc="match-and-solve iterations"),
        Param("max_match_px", 15.0, 1.0, 200.0, doc="first-iteration matching distance (px)"),
        Param("min_match_px", 3.0, 0.5, 200.0, doc="last-iteration matching distance (px)"),
        Param("crop_margin", 40, 0, 400, doc="pixels around the hypothesis's box"),
        Param("canny_low", 40.0, 0.0, 1000.0), Param("canny_high", 100.0, 0.0, 1000.0),
        Param("max_points", 300, 20, 5000, doc="contour points used (random subset)"),
        Param("max_seconds", 0.1, 0.001, 10.0, doc="time bound (s)"),
    )

    def run(self, inp: BlockInput) -> BlockResult:
        c, frame, pose0 = self.config, inp.frame, inp.pose
        assert pose0 is not None
        start = time.perf_counter()
        edge, why = _edge_distance(inp, int(c["crop_margin"]), c["canny_low"], c["canny_high"])
        if edge is None:
            return BlockResult.fail(why)
        (x0, y0, w, h), dt, labels, lut = edge
        P, D = _contour(inp, int(c["max_points"]))
        if len(P) < 6:
            return BlockResult.fail(f"only {len(P)} contour points visible from the hypothesis")
        K = frame.K
        rvec, _ = cv2.Rodrigues(pose0.R)
        tvec = pose0.t.reshape(3, 1).copy()
        n_it = int(c["iterations"])
        dists = np.geomspace(c["max_match_px"], min(c["min_match_px"], c["max_match_px"]), n_it)
        mean_dist = np.nan
        for it in range(n_it):
            if time.perf_counter() - start > c["max_seconds"]:
                break
            R = cv2.Rodrigues(rvec)[0]
            uv, _ = project_with_directions(R, tvec.ravel(), P, D, K)
            u, v = uv[:, 0] - x0, uv[:, 1] - y0
            inside = np.isfinite(u) & (u >= 0) & (v >= 0) & (u < w - 0.5) & (v < h - 0.5)
            iu, iv = np.round(u[inside]).astype(np.intp), np.round(v[inside]).astype(np.intp)
            d = dt[iv, iu]
            near = d <= dists[it]
            if near.sum() < 6:
                break
            match = lut[labels[iv[near], iu[near]]] + (x0, y0)
            mean_dist = float(np.mean(d[near]))
            obj = P[inside][near].astype(np.float64)
            ok, rvec_new, tvec_new = cv2.solvePnP(obj, match.astype(np.float64), K, None, rvec.copy(), tvec.copy(),
                                                 useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
            if not ok or not np.all(np.isfinite(tvec_new)) or tvec_new[2, 0] <= 0:
                break
            rvec, tvec = rvec_new, tvec_new
        pose = Pose(cv2.Rodrigues(rvec)[0], tvec.ravel())
        if not np.isfinite(mean_dist):
            return BlockResult.fail("too few contour points near image edges to match")
        return BlockResult(ok=True, pose=pose, scores={"chamfer_cost": mean_dist})
