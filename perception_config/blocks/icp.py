"""ICP refinement: the model surface visible from the hypothesis registered to the observed
scene points around it (Open3D legacy `registration_icp`; the tensor API is 20-80x slower on
CPU).

Choices that the measurements behind them made (15 deg / 2 cm starts, synthetic boxes and the
real LM-O frame, see the module tests):
- Source = the model's surface samples visible from the current hypothesis (z-buffer test on
  the cropped render), target = observed points in the hypothesis's box + the first
  correspondence distance, grid-subsampled to ~4000 points. Target normals come from the depth
  grid (cross product of neighbours): as good as a KNN PCA here and cheaper.
- Both clouds are centred on the visible model points before registering. Open3D linearises
  the rotation about the origin; about the camera (0.7-1 m away) a small rotation step turns
  into a large translation step and point-to-plane diverged in ~1 of 10 starts. Centred: 0/50
  on the boxes.
- Coarse to fine: a geometric schedule of correspondence distances from
  `max_correspondence_distance` to `final_distance` in `stages` steps, `max_iterations` each.
- Point-to-plane uses a Tukey robust kernel (width = half the stage distance) by default.
- Occlusion filter: before each stage, model points whose pixel shows an observed surface more
  than the stage distance in front of them are dropped (something occludes them; matching them
  drags the pose onto the occluder). It took an LM-O object with 50 % visibility from 49 mm
  ADD drift to 16 mm starting at the ground truth.
Scores: `icp_fitness` = share of the visible model points with a correspondence at the final
distance, `icp_rmse` = inlier RMSE (m).
"""
from __future__ import annotations

import time
from typing import ClassVar

import numpy as np
import open3d as o3d

from ..core.geometry import Pose
from ..vision.visibility import scene_patch, visible_surface
from .base import DEPTH, MODEL, POSE, Block, BlockInput, BlockResult, Kind, Param, register

_reg = o3d.pipelines.registration


def distance_schedule(first: float, final: float, stages: int) -> list[float]:
    """Geometric schedule of correspondence distances from `first` to `final` (m); a `final`
    above `first` is clipped to it."""
    first = float(first)
    final = min(float(final), first)
    if stages <= 1:
        return [first]
    return [first * (final / first) ** (i / (stages - 1)) for i in range(stages)]


def _cloud(points: np.ndarray, normals: np.ndarray | None = None) -> o3d.geometry.PointCloud:
    c = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64)))
    if normals is not None:
        c.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(normals, dtype=np.float64))
    return c


def unoccluded(points_cam: np.ndarray, depth: np.ndarray, K: np.ndarray, slack: float) -> np.ndarray:
    """Mask of camera-frame points that are not hidden behind an observed surface more than
    `slack` metres in front of them (missing depth and points outside the image count as
    unoccluded)."""
    z = points_cam[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.rint(points_cam[:, 0] / z * K[0, 0] + points_cam[:, 1] / z * K[0, 1] + K[0, 2])
        v = np.rint(points_cam[:, 1] / z * K[1, 1] + K[1, 2])
    h, w = depth.shape
    inside = (z > 0) & (u >= 0) & (v >= 0) & (u < w) & (v < h)
    obs = np.full(len(points_cam), np.nan, np.float32)
    obs[inside] = depth[v[inside].astype(np.intp), u[inside].astype(np.intp)]
    with np.errstate(invalid="ignore"):
        return ~(obs < z - slack)


class _IcpBase(Block):
    kind = Kind.REFINEMENT
    inputs = (DEPTH, MODEL, POSE)
    score_names = ("icp_fitness", "icp_rmse")
    score_ranges = {"icp_fitness": (0.0, 1.0), "icp_rmse": (0.0, 0.01)}  # share; metres
    lower_is_better = ("icp_rmse",)
    point_to_plane: ClassVar[bool]
    params = (
        Param("max_correspondence_distance", 0.03, 0.001, 0.2, doc="first-stage correspondence distance (m)"),
        Param("final_distance", 0.006, 0.0005, 0.2,
              doc="last-stage correspondence distance (m); the schedule is geometric"),
        Param("stages", 3, 1, 8, doc="number of coarse-to-fine stages"),
        Param("max_iterations", 30, 1, 500, doc="ICP iterations per stage"),
        Param("max_seconds", 0.1, 0.001, 10.0, doc="time bound: no new stage starts after it (s)"),
        Param("min_fitness", 0.1, 0.0, 1.0,
              doc="below this share of visible model points with a correspondence: ok=False"),
        Param("min_points", 30, 3, 100000, doc="minimum visible model points, scene points and correspondences"),
        Param("max_scene_points", 4000, 100, 100000, doc="scene points budget (grid subsampling)"),
        Param("occlusion_filter", True, doc="drop model points hidden behind observed surfaces before each stage"),
    )

    def _estimation(self, distance: float) -> _reg.TransformationEstimation:
        return _reg.TransformationEstimationPointToPoint()

    def run(self, inp: BlockInput) -> BlockResult:
        cfg = self.config
        start = time.perf_counter()
        frame, model, pose = inp.frame, inp.model, inp.pose
        dists = distance_schedule(cfg["max_correspondence_distance"], cfg["final_distance"], cfg["stages"])
        vis = visible_surface(frame, model, pose, inp.cache)
        if len(vis) < cfg["min_points"]:
            return BlockResult.fail(f"only {len(vis)} model points visible at the hypothesis "
                                    f"(need {cfg['min_points']}): object outside the view?")
        scene = scene_patch(frame, model, pose, margin=dists[0], max_points=cfg["max_scene_points"],
                            with_normals=self.point_to_plane)
        if scene is None or len(scene) < cfg["min_points"]:
            n = 0 if scene is None else len(scene)
            return BlockResult.fail(f"only {n} observed points around the hypothesis (need {cfg['min_points']})")
        # Work in a frame centred on the visible model surface (see the module docstring).
        c = vis.points.mean(axis=0)
        src_all = vis.points - c
        target = _cloud(scene.points - c, scene.normals)
        T = np.eye(4)
        criteria = _reg.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6,
                                               max_iteration=cfg["max_iterations"])
        result, used, stages_run = None, len(src_all), 0
        deadline = self.deadline(inp, start)
        for d in dists:
            if stages_run and time.perf_counter() > deadline:
                break
            src = src_all
            if cfg["occlusion_filter"]:
                keep = unoccluded(src_all @ T[:3, :3].T + T[:3, 3] + c, frame.depth, frame.K, d)
                if keep.sum() >= cfg["min_points"]:
                    src = src_all[keep]
            used = len(src)
            result = _reg.registration_icp(_cloud(src), target, d, T, self._estimation(d), criteria)
            T = np.asarray(result.transformation)
            stages_run += 1
            if len(result.correspondence_set) < cfg["min_points"]:
                break
        assert result is not None
        n_corr = len(result.correspondence_set)
        fitness = n_corr / len(vis)
        scores = {"icp_fitness": float(fitness), "icp_rmse": float(result.inlier_rmse)}
        info = {"stages_run": stages_run, "distances": dists[:stages_run], "visible_points": len(vis),
                "source_points": used, "scene_points": len(scene), "correspondences": n_corr,
                "timed_out": stages_run < len(dists)}
        if n_corr < cfg["min_points"] or fitness < cfg["min_fitness"]:
            r = BlockResult.fail("ICP found too few correspondences "
                                 f"({n_corr}, fitness {fitness:.3f} < {cfg['min_fitness']})")
            r.scores, r.info = scores, info
            return r
        # camera-frame increment: translate to the centre, apply T, translate back
        dR, dt = T[:3, :3], T[:3, 3] + c - T[:3, :3] @ c
        new = Pose(dR, dt).compose(pose)
        return BlockResult(ok=True, pose=new, scores=scores, info=info)


@register
class IcpPointToPoint(_IcpBase):
    """Point-to-point ICP (Open3D legacy), coarse to fine, visible model surface to scene."""

    name = "icp_point_to_point"
    default_cost = 0.04
    point_to_plane = False


@register
class IcpPointToPlane(_IcpBase):
    """Point-to-plane ICP (Open3D legacy) with depth-grid scene normals and a robust kernel."""

    name = "icp_point_to_plane"
    default_cost = 0.02
    point_to_plane = True
    params = _IcpBase.params + (
        Param("kernel", "tukey", choices=("tukey", "huber", "none"),
              doc="robust loss; width relative to the stage distance"),
    )

    def _estimation(self, distance: float) -> _reg.TransformationEstimation:
        kernel = self.config["kernel"]
        if kernel == "tukey":
            return _reg.TransformationEstimationPointToPlane(_reg.TukeyLoss(k=distance / 2))
        if kernel == "huber":
            return _reg.TransformationEstimationPointToPlane(_reg.HuberLoss(k=distance / 4))
        return _reg.TransformationEstimationPointToPlane()


__all__ = ["IcpPointToPoint", "IcpPointToPlane", "distance_schedule", "unoccluded"]
