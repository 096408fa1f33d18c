"""Depth refinement: move the hypothesis along the camera ray through the object centre by the
median difference between observed and rendered depth over the object's rendered pixels.

It fixes the error that edges and 2D methods leave worst constrained (distance along the
viewing ray) in one render (~1-3 ms). Robustness: differences beyond `max_diff_factor` x the
object diameter are ignored (background seen past a misplaced silhouette, occluders far in
front), the median takes care of the rest, and at least `min_pixels` usable pixels are required.
Moving along the ray through the centre keeps the object's image position and moves every
model point by the same vector, whose z is the shift: only the image scale changes slightly.
A second pass (re-render at the shifted pose) changed the result by < 0.5 mm in the tests and
doubles the cost (the render dominates: ~1.5 ms for a 100 px object, ~5 ms for 250 px), so
`iterations` defaults to 1.
"""
from __future__ import annotations

import time

import numpy as np

from ..core.geometry import Pose
from ..core.models import ObjectModel
from ..core.scene import Frame
from ..vision.visibility import hypothesis_rendering
from .base import DEPTH, MODEL, POSE, Block, BlockInput, BlockResult, Kind, Param, register


def model_centre(model: ObjectModel) -> np.ndarray:
    """Centre of the model's axis-aligned bounding box (model frame, m)."""
    return np.asarray(model.bbox_min, dtype=np.float64) + np.asarray(model.bbox_size, dtype=np.float64) / 2.0


def depth_offset(frame: Frame, model: ObjectModel, pose: Pose, max_diff: float,
                 cache: dict | None = None) -> tuple[float, int, int]:
    """Median of (observed - rendered) depth over the rendered object pixels with valid observed
    depth and |difference| <= max_diff; returns (median in m or NaN, pixels used, object pixels)."""
    r = hypothesis_rendering(frame, model, pose, cache)
    if r.empty:
        return float("nan"), 0, 0
    obs = frame.depth[r.crop_slices()]
    obj = np.isfinite(r.depth)
    diff = (obs - r.depth)[obj]
    with np.errstate(invalid="ignore"):
        use = np.abs(diff) <= max_diff  # NaN observed depth fails the test
    n = int(use.sum())
    return (float(np.median(diff[use])) if n else float("nan")), n, int(obj.sum())


def shift_along_ray(pose: Pose, centre_model: np.ndarray, dz: float) -> Pose:
    """The pose moved along the camera ray through the object centre so that the centre's
    depth changes by dz (m); the rotation is kept."""
    c = pose.transform(np.asarray(centre_model, dtype=np.float64)[None])[0]
    if c[2] <= 0:
        raise ValueError("the object centre is behind the camera")
    return Pose(pose.R, pose.t + c * (dz / c[2]))


@register
class DepthRefine(Block):
    """Shift along the camera ray by the median observed-minus-rendered depth."""

    kind = Kind.REFINEMENT
    name = "depth_refine"
    default_cost = 0.003
    inputs = (DEPTH, MODEL, POSE)
    params = (
        Param("max_diff_factor", 0.5, 0.01, 5.0, doc="ignore depth differences beyond this x the object diameter"),
        Param("min_pixels", 50, 1, 1000000, doc="minimum object pixels with usable observed depth"),
        Param("iterations", 1, 1, 10, doc="render-and-shift passes (more correct the small scale change)"),
        Param("tolerance", 0.0005, 0.0, 0.1, doc="stop when the shift is below this (m)"),
        Param("max_seconds", 0.05, 0.001, 10.0, doc="time bound: no new pass starts after it (s)"),
    )

    def run(self, inp: BlockInput) -> BlockResult:
        cfg = self.config
        start = time.perf_counter()
        model, pose = inp.model, inp.pose
        centre = model_centre(model)
        max_diff = cfg["max_diff_factor"] * model.diameter
        total, passes, used, pixels = 0.0, 0, 0, 0
        deadline = self.deadline(inp, start)
        for i in range(cfg["iterations"]):
            if i and time.perf_counter() > deadline:
                break
            dz, used, pixels = depth_offset(inp.frame, model, pose, max_diff, inp.cache)
            if pixels == 0:
                return BlockResult.fail("the object does not project into the image at the hypothesis")
            if used < cfg["min_pixels"]:
                if i == 0:
                    return BlockResult.fail(
                        f"only {used} of {pixels} object pixels have observed depth within {max_diff:.3f} m "
                        f"(need {cfg['min_pixels']})")
                break
            pose = shift_along_ray(pose, centre, dz)
            total += dz
            passes += 1
            if abs(dz) < cfg["tolerance"]:
                break
        return BlockResult(ok=True, pose=pose,
                           info={"shift": total, "passes": passes, "pixels_used": used, "object_pixels": pixels})


__all__ = ["DepthRefine", "depth_offset", "shift_along_ray", "model_centre"]
