"""Resting poses of a part on a support plane, and pose hypotheses from them (the `resting_pose`
generator, blocks/resting.py).

A part lying on a table or a bin floor rests on a face of its convex hull, and only on one whose
facet polygon holds the projection of its centre of mass (a stable placement). So a part on a
plane has, per stable face, three degrees of freedom left: where it lies on the plane and how
far it is turned about the plane's normal. `resting_poses` lists the stable faces of a model
once (convex hull facets grouped by normal; the largest first; faces the model's symmetries
make alike kept once). `rest_hypotheses` places each rest under an observed region of the frame
at a sweep of turns: the model's camera-facing samples are shifted so that their centroid on
the plane meets the region's, lifted so their top meets the region's top, and scored by a
truncated two-way nearest-point distance to the region's points (both in the plane's frame).
The best few per region go on to render-and-compare verification and ICP.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from ..geometry import Pose
from ..models import ObjectModel

MAX_SAMPLES = 150  # model and region points per comparison: enough to tell turns apart, cheap to query


@dataclass(frozen=True)
class RestingPose:
    """A stable face: R turns the model so that the face's outward normal points down (-z of
    the plane frame, z along the plane's normal towards the camera)."""

    R: np.ndarray  # (3, 3) model frame -> plane frame (before the turn about z)
    lift: float  # metres: height of the model's centroid above the plane in this rest
    height: float  # metres: the part's top above the plane
    area: float  # m^2: the face's area (larger faces are likelier rests)


def rotation_to(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector `a` onto unit vector `b`."""
    v, c = np.cross(a, b), float(a @ b)
    if c < -1.0 + 1e-9:  # opposite: half a turn about any axis perpendicular to a
        axis = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def _inside_polygon(p: np.ndarray, pts2: np.ndarray) -> bool:
    """Whether 2D point p lies inside the convex hull of pts2 (a degenerate hull: no)."""
    try:
        hull = ConvexHull(pts2)
    except Exception:  # noqa: BLE001  (collinear or too few points: no area to stand on)
        return False
    return bool(np.all(hull.equations[:, :2] @ p + hull.equations[:, 2] <= 1e-9))


def resting_poses(model: ObjectModel, max_poses: int = 6, merge_deg: float = 5.0) -> list[RestingPose]:
    """The model's stable faces on a plane, largest first (see the module docstring). The centre
    of mass is taken as the centroid of the surface samples."""
    hull = ConvexHull(model.hull_points)
    normals, offsets = hull.equations[:, :3], -hull.equations[:, 3]  # outward n . x = offset on the facet
    tri = hull.points[hull.simplices]
    areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    com = model.points.mean(axis=0)
    cos_merge = math.cos(math.radians(merge_deg))
    groups: list[list[int]] = []
    for f in np.argsort(-areas, kind="stable"):
        for g in groups:
            if normals[g[0]] @ normals[f] > cos_merge:
                g.append(int(f))
                break
        else:
            groups.append([int(f)])
    sym = [s.R for s in model.symmetries] or [np.eye(3)]
    rests: list[RestingPose] = []
    kept_normals: list[np.ndarray] = []
    for g in sorted(groups, key=lambda g: -areas[g].sum()):
        n = np.average(normals[g], axis=0, weights=areas[g] + 1e-12)
        n /= np.linalg.norm(n)
        h0 = float(np.max(offsets[g]))
        R = rotation_to(n, np.array([0.0, 0.0, -1.0]))
        verts = np.unique(hull.simplices[g].ravel())
        footprint = (hull.points[verts] @ R.T)[:, :2]
        if not _inside_polygon((R @ com)[:2], footprint):
            continue  # the centre of mass overhangs: the part tips over
        if any(any((S @ n) @ m > cos_merge for S in sym) for m in kept_normals):
            continue  # a face the symmetries make alike with a kept one
        z = model.hull_points @ n
        rests.append(RestingPose(R=R, lift=h0 - float(com @ n), height=h0 - float(z.min()), area=float(areas[g].sum())))
        kept_normals.append(n)
        if len(rests) >= max_poses:
            break
    return rests


def plane_basis(plane: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(B, o): the plane frame's axes as columns of B (x, y in the plane, z its normal towards
    the camera) and its origin o (camera frame): p_camera = o + B @ p_plane. `plane` is
    (n, d) with n . p + d = 0 and n facing the camera."""
    n = plane[:3] / np.linalg.norm(plane[:3])
    x = np.cross([0.0, 1.0, 0.0], n)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross([1.0, 0.0, 0.0], n)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(n, x), n], axis=1), -plane[3] / np.linalg.norm(plane[:3]) * n


def _subsample(p: np.ndarray, k: int = MAX_SAMPLES) -> np.ndarray:
    return p[:: max(1, len(p) // k)]


def _turn(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def planar_icp(model_pts: np.ndarray, observed: np.ndarray, max_dist: float,
               iterations: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Align (P, 3) model points to (N, 3) observed points (both in the plane frame) by a turn
    about z and a shift in the plane only: the resting face stays on the plane, the prior full
    ICP would give up (on a few hundred pixels of a small part it tilts it). Each observed point
    is matched to its nearest model point within `max_dist`. Returns (Rz, shift) with
    aligned = model_pts @ Rz.T + shift."""
    Rz, shift = np.eye(3), np.zeros(3)
    for _ in range(iterations):
        cur = model_pts @ Rz.T + shift
        dist, idx = cKDTree(cur).query(observed)
        ok = dist < max_dist
        if ok.sum() < 5:
            break
        src, dst = cur[idx[ok], :2], observed[ok, :2]
        cs, cd = src.mean(axis=0), dst.mean(axis=0)
        h = (src - cs).T @ (dst - cd)
        phi = math.atan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
        step = _turn(phi)
        t2 = cd - step[:2, :2] @ cs
        Rz = step @ Rz
        shift = step @ shift + np.array([t2[0], t2[1], 0.0])
        if abs(phi) < 1e-4 and np.linalg.norm(t2) < 1e-5:
            break
    return Rz, shift


def rest_hypotheses(
    model: ObjectModel, rests: list[RestingPose], plane: np.ndarray, region: np.ndarray, turns: int = 24,
    keep: int = 3, truncate: float = 0.1,
) -> list[tuple[float, Pose]]:
    """The `keep` best (cost, pose) of every rest at `turns` turns about the plane's normal,
    placed under `region` ((N, 3) camera-frame points of one observed region), each then
    aligned in the plane (planar_icp); cost: the mean truncated (`truncate` diameters) nearest
    distance, observed -> model and model -> observed, in diameters (lower is better). Rests
    much taller or much lower than the region are skipped (a part on its side does not fit a
    flat region)."""
    B, o = plane_basis(plane)
    q = _subsample((region - o) @ B)  # plane frame
    if len(q) < 5:
        return []
    top = float(np.percentile(q[:, 2], 98))
    centre = q[:, :2].mean(axis=0)
    view = np.append(centre, top / 2.0) - (-o) @ B  # camera -> region, plane frame
    view /= np.linalg.norm(view)
    tree_q = cKDTree(q)
    d, tau = model.diameter, truncate * model.diameter
    com = model.points.mean(axis=0)
    pts, nrm = model.points - com, model.point_normals

    def cost(vis: np.ndarray) -> float:
        model_to_obs = np.minimum(tree_q.query(vis)[0], tau).mean()
        return float(model_to_obs + np.minimum(cKDTree(vis).query(q)[0], tau).mean()) / d

    out: list[tuple[float, Pose]] = []
    for rest in rests:
        if top > rest.height + 0.25 * d + 0.01 or top < 0.4 * rest.height:
            continue
        base = max(0.0, top - rest.height)  # the part lies on the plane, or on something under it
        p0, n0 = pts @ rest.R.T, nrm @ rest.R.T
        found = []
        for k in range(turns):
            Rz = _turn(2.0 * math.pi * k / turns)
            p, n = p0 @ Rz.T, n0 @ Rz.T
            vis = p[n @ view < 0.0]
            vis = _subsample(vis if len(vis) >= 5 else p)
            shift = np.append(centre - vis[:, :2].mean(axis=0), base + rest.lift)
            found.append((cost(vis + shift), Rz, vis, shift))
        found.sort(key=lambda f: f[0])
        for _, Rz, vis, shift in found[:keep]:
            R2, s2 = planar_icp(vis + shift, q, 2.0 * tau)
            R_plane, shift = R2 @ Rz @ rest.R, R2 @ shift + s2
            out.append((cost(vis @ R2.T + shift),
                        Pose(B @ R_plane, o + B @ (shift - R_plane @ com))))
    out.sort(key=lambda f: f[0])
    return out


__all__ = ["RestingPose", "resting_poses", "rest_hypotheses", "planar_icp", "plane_basis", "rotation_to"]
