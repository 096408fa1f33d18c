"""D2CO: direct directional chamfer optimisation (Imperoli & Pretto, ICVS 2015).

The model contour visible from the hypothesis (sharp edges + rendered silhouette, 3D points with
tangents) is projected into the image; each point's cost is the directional chamfer tensor at
its pixel and its projected tangent's orientation bin (bilinear in the pixel). Levenberg-Marquardt
(scipy least_squares, method 'lm') minimises the sum of soft-L1 robustified costs over the 6-DoF pose,
parametrised as a rotation about the object origin and a translation, R = exp([w]x) R0,
t = t0 + d. The tensor is built once per frame and crop (cached), so later calls on the same
frame pay only the optimisation.

Edges constrain the image-plane position and the rotation well; depth along the viewing ray is
weakly constrained (only through scale), so D2CO pairs well with depth refinement or ICP.
"""
from __future__ import annotations

import time

import numpy as np
from scipy.optimize import least_squares

from ..geometry import Pose, exp_so3
from ..render import projected_box
from .base import MODEL, POSE, RGB, Block, BlockInput, BlockResult, Kind, Param, register
from .edges import canny_edges, crop_box, directional_chamfer_tensor, model_contour, project_with_directions


def sample_tensor(dct: np.ndarray, x: np.ndarray, y: np.ndarray, angle: np.ndarray, outside: float) -> np.ndarray:
    """Tensor values at float pixels (x, y) of a crop, in each point's nearest orientation bin."""
    n, h, w = dct.shape
    b = np.minimum((np.nan_to_num(angle) / np.pi * n).astype(np.intp), n - 1)
    ok = np.isfinite(x) & np.isfinite(y) & (x >= 0) & (y >= 0) & (x < w - 1) & (y < h - 1)
    out = np.full(x.shape, outside, np.float64)
    xs, ys, bs = x[ok], y[ok], b[ok]
    x0, y0 = xs.astype(np.intp), ys.astype(np.intp)
    fx, fy = xs - x0, ys - y0
    out[ok] = (dct[bs, y0, x0] * (1 - fx) * (1 - fy) + dct[bs, y0, x0 + 1] * fx * (1 - fy)
               + dct[bs, y0 + 1, x0] * (1 - fx) * fy + dct[bs, y0 + 1, x0 + 1] * fx * fy)
    return out


@register
class D2CO(Block):
    """Direct directional chamfer optimisation of the pose on image edges (LM over 6 DoF)."""

    kind = Kind.REFINEMENT
    name = "d2co"
    inputs = (RGB, MODEL, POSE)
    score_names = ("d2co_cost",)
    params = (
        Param("n_bins", 60, 8, 180, doc="orientation bins over [0, pi)"),
        Param("penalty", 0.5, 0.0, 10.0, doc="tensor cost per bin of orientation difference (px)"),
        Param("max_distance", 30.0, 2.0, 200.0, doc="truncation of the chamfer distance (px): robustness to clutter"),
        Param("crop_margin", 40, 0, 400, doc="pixels around the hypothesis's box the tensor covers"),
        Param("canny_low", 40.0, 0.0, 1000.0, doc="Canny low threshold"),
        Param("canny_high", 100.0, 0.0, 1000.0, doc="Canny high threshold"),
        Param("depth_prior_mm", 5.0, 0.1, 1000.0, doc="depth shift (mm) that costs 1 px per point: keeps the weakly observed depth"),
        Param("max_points", 300, 20, 5000, doc="contour points used (random subset)"),
        Param("robust_scale", 1.0, 0.1, 50.0, doc="soft-L1 scale of the per-point cost (px)"),
        Param("max_evaluations", 80, 10, 5000, doc="cost evaluations of the LM solver (finite-difference Jacobians included)"),
        Param("max_seconds", 0.2, 0.001, 10.0, doc="time bound of the optimisation (s)"),
    )

    def run(self, inp: BlockInput) -> BlockResult:
        c, frame, model, pose0 = self.config, inp.frame, inp.model, inp.pose
        assert pose0 is not None
        start = time.perf_counter()
        box = projected_box(model, pose0, frame.K, frame.width, frame.height)
        if box is None:
            return BlockResult.fail("the object at the hypothesis is outside the image")
        crop = crop_box(frame, box, int(c["crop_margin"]), align=32)
        edges, direction = canny_edges(frame, inp.cache, c["canny_low"], c["canny_high"])
        x0, y0, w, h = crop
        e_crop = edges[y0:y0 + h, x0:x0 + w]
        if not e_crop.any():
            return BlockResult.fail("no image edges around the hypothesis")
        key = ("d2co:tensor", crop, c["n_bins"], c["penalty"], c["max_distance"], c["canny_low"], c["canny_high"])
        entry = inp.cache.get(key)
        if entry is None or entry[0] is not frame.rgb:
            dct = directional_chamfer_tensor(e_crop, direction[y0:y0 + h, x0:x0 + w], c["n_bins"], c["penalty"], c["max_distance"])
            inp.cache[key] = (frame.rgb, dct)
        else:
            dct = entry[1]
        P, D = model_contour(frame, model, pose0, inp.cache, int(c["max_points"]), inp.rng)
        if len(P) < 6:
            return BlockResult.fail(f"only {len(P)} contour points visible from the hypothesis")

        K, R0, t0, cap = frame.K, pose0.R, pose0.t, float(c["max_distance"])
        ray = t0 / np.linalg.norm(t0)
        # Edges barely constrain depth along the viewing ray: a weak prior keeps it where it
        # was (1 depth_prior_mm of shift costs as much as every point 1 px further off).
        prior = np.sqrt(len(P)) / (c["depth_prior_mm"] * 1e-3)

        def edge_costs(x: np.ndarray) -> np.ndarray:
            uv, ang = project_with_directions(exp_so3(x[:3]) @ R0, t0 + x[3:], P, D, K)
            return sample_tensor(dct, uv[:, 0] - x0, uv[:, 1] - y0, ang, cap)

        scale = c["robust_scale"]

        def residuals(x: np.ndarray) -> np.ndarray:
            # Soft-L1 robust loss through the residuals (LM itself has none): hidden or
            # cluttered contour points must not dominate the squared cost.
            e = edge_costs(x)
            e = scale * np.sqrt(2.0 * (np.sqrt(1.0 + (e / scale) ** 2) - 1.0))
            return np.append(e, prior * float(ray @ x[3:]))

        cost0 = float(np.mean(edge_costs(np.zeros(6))))
        budget = max(0.0, c["max_seconds"] - (time.perf_counter() - start))
        # Evaluations are ~0.1 ms; bound their number by the remaining time as well.
        n_eval = int(min(c["max_evaluations"], max(10, budget / 2e-4)))
        sol = least_squares(residuals, np.zeros(6), method="lm", diff_step=1e-3, max_nfev=n_eval)
        cost = float(np.mean(edge_costs(sol.x)))
        if not np.all(np.isfinite(sol.x)) or cost >= cost0:
            return BlockResult(ok=True, pose=pose0, scores={"d2co_cost": cost0},
                               info={"improved": False, "evaluations": int(sol.nfev)})
        pose = Pose(exp_so3(sol.x[:3]) @ R0, t0 + sol.x[3:])
        return BlockResult(ok=True, pose=pose, scores={"d2co_cost": cost},
                           info={"improved": True, "cost_before": cost0, "evaluations": int(sol.nfev), "points": len(P)})
