"""The embedded default dataset: synthetic BOP-format RGB-D scenes of industrial parts.

`generate(out, ...)` writes a complete BOP dataset (models/, models_eval/, camera.json,
test/<scene>/... with scene_camera.json, scene_gt.json, scene_gt_info.json, rgb/ and depth/
PNGs, and test_targets_bop19.json) of the procedural parts of `parts.py`, or of the models of a
given BOP models folder (e.g. the real LM-O models).

models_eval/ (what bop_toolkit's evaluation loads: obj_*.ply and models_info.json) holds the
same meshes as models/, byte for byte: the project's errors are computed on those meshes, so
bop_toolkit's MSSD / MSPD on models_eval equal the project's (BOP's own datasets resample
their evaluation meshes evenly instead).

Scenes (one arrangement of objects each; BOP-like: the images of a scene are viewpoints):
- World frame z up, the floor at z = 0. Per scene, with a seeded generator: a bin (floor
  slab and four walls of 8 mm plastic, 10-14 cm high, sized to the objects; the walls occlude)
  or a table; 3-8 distinct objects (at most the number of models).
- Resting poses: each object lies on one of its stable faces (convex-hull faces whose plane
  contains the projection of the centre of mass), drawn with probability proportional to
  the solid angle of the face seen from the centre of mass (the quasi-static drop
  heuristic; rests that tip over within 8 deg, such as a disc on its rim, are dropped),
  with a random yaw; its lowest point touches the floor. Footprint circles are
  kept apart by rejection sampling; an object that does not fit after 80 tries is put on
  top of the ones it overlaps (a heap): no interpenetration either way.
- Camera: Linemod intrinsics (fx 572.41, fy 573.57, cx 325.26, cy 242.05) at 640x480, at
  0.5-1.0 m from a point near the bin centre, tilted 0-25 deg from vertical, random azimuth
  and +-45 deg roll, re-drawn until every object centre projects at least 16 px inside the image.
- One point light per scene (0.9-1.6 m above, offset), ambient term, cast shadows.

Rendering: objects with `render.render` (open3d ray casting, exact mutual occlusion); the
bin/table with one open3d RaycastingScene per scene in the world frame; the nearer hit wins.
RGB: procedural albedo textures, Lambert + Blinn-Phong (shiny parts get highlights), shadows,
blur, noise, gamma (sensor.py). Depth: sensor.simulate_depth (z-dependent noise, projector
shadows, edge dropout and flying pixels, grazing-angle and specular dropout, 1 mm quantum).
Depth PNGs use depth_scale 1.0 (1 unit = 1 mm, the sensor's quantum: lossless, 65 m range).

scene_gt_info.json follows bop_toolkit's calc_gt_info, with exact masks instead of its depth
test: px_count_all = pixels of the object rendered alone, including the part outside the
image (a virtual 3x image, as bop_toolkit); px_count_visib = pixels where the object is the
visible surface of the full scene (objects and bin); px_count_valid = in-image silhouette
pixels with a valid depth measurement; visib_fract = visib / all; bbox_obj / bbox_visib as
bop_toolkit (x, y, max-min width/height; bbox_obj may extend outside the image).

Output is deterministic for a seed (same PNG and JSON bytes; every scene and image draws
from its own generator seeded by (seed, scene, image)), and atomic: the dataset is written
to a hidden sibling folder marked `.incomplete` and renamed to `out` only when complete.
"""
from __future__ import annotations

import json
import math
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..core.geometry import Pose
from ..util.atomic_file import atomic_write
from ..util.safe_json import read_json_file
from . import sensor

__all__ = ["generate", "LINEMOD_K", "DEPTH_SCALE", "stable_poses", "GENERATOR_NAME", "LAST_STATS"]

LINEMOD_K = np.array([[572.4114, 0.0, 325.2611], [0.0, 573.57043, 242.04899], [0.0, 0.0, 1.0]])
DEPTH_SCALE = 1.0  # mm per depth PNG unit
GENERATOR_NAME = "perception_config.datasets.synthetic"
CENTER_MARGIN_PX = 16
MIN_OBJECTS, MAX_OBJECTS = 3, 8
LAST_STATS: dict[str, float] = {}  # images, seconds, images_per_second of the last generate() (incl. model set-up)

_ENV_MATERIALS = {  # name: (texture kind, ks, shininess)
    "bin": ("plastic", 0.12, 20.0),
    "table": ("wood", 0.05, 10.0),
    "concrete": ("concrete", 0.02, 6.0),
}
_BIN_COLOURS = [(0.10, 0.25, 0.55), (0.45, 0.46, 0.48), (0.12, 0.40, 0.20), (0.70, 0.35, 0.08), (0.12, 0.12, 0.13)]
_TABLE_COLOURS = {"wood": [(0.62, 0.45, 0.28), (0.75, 0.60, 0.42)],
                  "concrete": [(0.55, 0.55, 0.53), (0.42, 0.43, 0.45)]}


# --------------------------------------------------------------------------- resting poses


def _rot_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation taking unit vector a to unit vector b."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if c < -1 + 1e-9:  # opposite: half turn about any axis perpendicular to a
        axis = np.cross(a, [1.0, 0, 0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0, 1.0, 0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + K + K @ K / (1.0 + c)


def _center_of_mass(vertices: np.ndarray, faces: np.ndarray, hull_pts: np.ndarray) -> np.ndarray:
    """Solid centroid of a closed mesh; the hull's centroid when the mesh is not a solid."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    vol6 = np.einsum("ij,ij->i", a, np.cross(b, c))
    V = vol6.sum()
    ext = np.ptp(vertices, axis=0).max()
    if V > 1e-3 * ext ** 3:
        return ((a + b + c) * vol6[:, None]).sum(0) / (4.0 * V)
    from scipy.spatial import ConvexHull

    h = ConvexHull(hull_pts)
    o = hull_pts.mean(0)
    tri = hull_pts[h.simplices]
    v6 = np.einsum("ij,ij->i", tri[:, 0] - o, np.cross(tri[:, 1] - o, tri[:, 2] - o))
    cen = (tri[:, 0] + tri[:, 1] + tri[:, 2] + o) / 4.0  # centroids of the tetrahedra (o, a, b, c)
    return (cen * np.abs(v6)[:, None]).sum(0) / np.abs(v6).sum()


def stable_poses(
    vertices: np.ndarray, faces: np.ndarray, min_prob: float = 1e-3, min_tip_deg: float = 8.0,
) -> tuple[list[np.ndarray], np.ndarray]:
    """Stable resting orientations of a rigid body on a floor (z up): rotations R (model to
    world, before yaw) that put a convex-hull face down with the centre of mass above it, and
    their probabilities (solid angle of the face seen from the centre of mass, renormalised
    over the stable faces; faces below `min_prob` dropped).

    Marginal rests are dropped: the body must tip by at least `min_tip_deg` before its centre
    of mass passes over the edge of its support (the hull points within 2 % of its size of the
    floor, so a tessellated disc does not stand on its rim like a coin)."""
    from scipy.spatial import ConvexHull

    V = np.asarray(vertices, dtype=np.float64)
    hull = ConvexHull(V)
    com = _center_of_mass(V, np.asarray(faces), V[hull.vertices])
    tri = V[hull.simplices]
    a, b, c = tri[:, 0] - com, tri[:, 1] - com, tri[:, 2] - com
    la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
    num = np.abs(np.einsum("ij,ij->i", a, np.cross(b, c)))
    den = (la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", a, c) * lb
           + np.einsum("ij,ij->i", b, c) * la)
    omega = 2.0 * np.arctan2(num, den)  # solid angle of each hull triangle (Van Oosterom)
    eq = hull.equations
    scale = float(np.ptp(V, axis=0).max())
    # Coplanar hull triangles (one facet) share their plane: group by the rounded plane.
    key = np.round(np.column_stack([eq[:, :3] * 1e6, eq[:, 3:] / scale * 1e6])).astype(np.int64)
    first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)[1:]
    inv = inv.reshape(-1)
    # Is the projection of the centre of mass onto the triangle's plane inside the triangle?
    n = eq[:, :3]
    q = com - (np.einsum("ij,j->i", n, com) + eq[:, 3])[:, None] * n  # projection
    e0, e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 1], tri[:, 0] - tri[:, 2]
    s0 = np.einsum("ij,ij->i", np.cross(e0, q - tri[:, 0]), n)
    s1 = np.einsum("ij,ij->i", np.cross(e1, q - tri[:, 1]), n)
    s2 = np.einsum("ij,ij->i", np.cross(e2, q - tri[:, 2]), n)
    tol = -1e-9 * scale * scale
    inside = ((s0 >= tol) & (s1 >= tol) & (s2 >= tol)) | ((s0 <= -tol) & (s1 <= -tol) & (s2 <= -tol))
    ng = len(first)
    g_omega = np.bincount(inv, weights=omega, minlength=ng)
    g_stable = np.bincount(inv, weights=inside.astype(float), minlength=ng) > 0
    idx = np.flatnonzero(g_stable)
    tip = np.array([_tip_angle(V[hull.vertices], eq[first[g]], com, 0.02 * scale) for g in idx])
    if idx.size and (tip >= math.radians(min_tip_deg)).any():
        idx = idx[tip >= math.radians(min_tip_deg)]
    elif idx.size:
        idx = idx[[int(np.argmax(tip))]]
    if idx.size == 0:  # numerically unstable body: rest on the facet with the largest solid angle
        idx = np.array([int(np.argmax(g_omega))])
    probs = g_omega[idx] / g_omega[idx].sum()
    keep = probs >= min_prob
    if not keep.any():
        keep = probs == probs.max()
    idx, probs = idx[keep], probs[keep] / probs[keep].sum()
    down = np.array([0.0, 0.0, -1.0])
    rots = [_rot_between(n[first[g]], down) for g in idx]
    return rots, probs


def _tip_angle(hull_pts: np.ndarray, plane: np.ndarray, com: np.ndarray, eps: float) -> float:
    """Angle (rad) a body resting on `plane` (outward normal, offset) must tip before its
    centre of mass leaves the support polygon (hull points within eps of the plane)."""
    from scipy.spatial import ConvexHull, QhullError

    n, d = plane[:3], plane[3]
    heights = hull_pts @ n + d  # <= 0 inside
    sup = hull_pts[heights > -eps]
    R0 = _rot_between(n, np.array([0.0, 0.0, -1.0]))
    p2 = (sup @ R0.T)[:, :2]
    c2 = (com @ R0.T)[:2]
    h = float(-(com @ n + d))
    try:
        ch = ConvexHull(p2)
    except (QhullError, ValueError):
        return 0.0
    margin = float(-(ch.equations[:, :2] @ c2 + ch.equations[:, 2]).max())  # > 0 inside
    return math.atan2(margin, max(h, 1e-12))


# --------------------------------------------------------------------------- scene description


@dataclass
class _Obj:
    """A model prepared for placement and shading."""

    obj_id: int
    model: Any  # ObjectModel (metres)
    material: str
    color: np.ndarray  # (3,) albedo when the model has no vertex colours
    rests: list[np.ndarray]
    rest_probs: np.ndarray
    tree: Any = None  # cKDTree over vertices for vertex-colour lookup


@dataclass
class _Scene:
    kind: str  # "bin" | "table"
    objects: list[_Obj]
    world_poses: list[Pose]  # model to world
    boxes: list[tuple[np.ndarray, np.ndarray, str]]  # (min corner, max corner, material)
    textures: dict[str, np.ndarray]
    env_props: dict[str, tuple[float, float]]  # material -> (ks, shininess)
    light: np.ndarray  # world position
    light_power: float
    ambient: float
    target: np.ndarray  # point the cameras look at
    half: tuple[float, float]
    env_scene: Any = None
    env_ids: list[str] = field(default_factory=list)
    shadow_scene: Any = None


def _place(rng: np.random.Generator, objs: list[_Obj], hx: float, hy: float, margin: float) -> list[Pose]:
    placed: list[tuple[np.ndarray, float, float]] = []  # footprint centre, radius, top z
    poses: list[Pose | None] = [None] * len(objs)
    order = sorted(range(len(objs)), key=lambda i: -objs[i].model.diameter)
    for i in order:
        o = objs[i]
        k = int(rng.choice(len(o.rests), p=o.rest_probs))
        yaw = rng.uniform(-np.pi, np.pi)
        Rz = np.array([[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
        R = Rz @ o.rests[k]
        hp = o.model.hull_points @ R.T
        lo, hi = hp.min(0), hp.max(0)
        c_off = 0.5 * (lo[:2] + hi[:2])
        r = float(np.linalg.norm(hp[:, :2] - c_off, axis=1).max())
        ax, ay = max(hx - r - margin, 0.0), max(hy - r - margin, 0.0)
        best = None
        for _ in range(80):
            c = np.array([rng.uniform(-ax, ax), rng.uniform(-ay, ay)])
            if all(np.linalg.norm(c - pc) >= r + pr + 0.002 for pc, pr, _ in placed):
                best = (c, 0.0)
                break
        if best is None:  # heap: rest on top of what it overlaps
            c = np.array([rng.uniform(-ax, ax), rng.uniform(-ay, ay)])
            base = max([top for pc, pr, top in placed if np.linalg.norm(c - pc) < r + pr + 0.002], default=0.0)
            best = (c, base + 0.001)
        c, base = best
        t = np.array([c[0] - c_off[0], c[1] - c_off[1], base - lo[2]])
        poses[i] = Pose(R, t)
        placed.append((c, r, base + (hi[2] - lo[2])))
    return poses  # type: ignore[return-value]


def _box_mesh(lo: np.ndarray, hi: np.ndarray):
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_box(*(hi - lo))
    m.translate(lo)
    return np.asarray(m.vertices, np.float32), np.asarray(m.triangles, np.uint32)


def _make_scene(rng: np.random.Generator, pool: list[_Obj]) -> _Scene:
    import open3d as o3d

    n_hi = min(MAX_OBJECTS, len(pool))
    n_lo = min(MIN_OBJECTS, n_hi)
    n = int(rng.integers(n_lo, n_hi + 1))
    idx = sorted(rng.choice(len(pool), size=n, replace=False).tolist())
    objs = [pool[i] for i in idx]
    need = 1.8 * sum(math.pi * (0.45 * o.model.diameter) ** 2 for o in objs)
    w = math.sqrt(need * 4.0 / 3.0)
    hx, hy = max(0.17, w / 2), max(0.13, 0.75 * w / 2)
    kind = "bin" if rng.random() < 0.6 else "table"
    textures: dict[str, np.ndarray] = {}
    env_props: dict[str, tuple[float, float]] = {}
    boxes: list[tuple[np.ndarray, np.ndarray, str]] = []
    wt, ft = 0.008, 0.006
    tkind = "wood" if rng.random() < 0.5 else "concrete"
    tcol = _TABLE_COLOURS[tkind][int(rng.integers(len(_TABLE_COLOURS[tkind])))]
    textures["table"] = sensor.make_texture(rng, tkind, tcol)
    env_props["table"] = _ENV_MATERIALS["table" if tkind == "wood" else "concrete"][1:]
    if kind == "bin":
        hb = float(rng.uniform(0.10, 0.14))
        bcol = _BIN_COLOURS[int(rng.integers(len(_BIN_COLOURS)))]
        textures["bin"] = sensor.make_texture(rng, "plastic", bcol)
        env_props["bin"] = _ENV_MATERIALS["bin"][1:]
        X, Y = hx + wt, hy + wt
        boxes += [
            (np.array([-X, -Y, -ft]), np.array([X, Y, 0.0]), "bin"),
            (np.array([hx, -Y, 0.0]), np.array([X, Y, hb]), "bin"),
            (np.array([-X, -Y, 0.0]), np.array([-hx, Y, hb]), "bin"),
            (np.array([-hx, hy, 0.0]), np.array([hx, Y, hb]), "bin"),
            (np.array([-hx, -Y, 0.0]), np.array([hx, -hy, hb]), "bin"),
        ]
        table_top = -ft
        margin = 0.004
    else:
        table_top = 0.0
        margin = -0.02  # objects may reach a little beyond the nominal area
    boxes.append((np.array([-1.6, -1.6, table_top - 0.04]), np.array([1.6, 1.6, table_top]), "table"))
    poses = _place(rng, objs, hx, hy, margin)
    light = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), rng.uniform(0.9, 1.6)])
    scene = _Scene(
        kind=kind, objects=objs, world_poses=poses, boxes=boxes, textures=textures, env_props=env_props,
        light=light, light_power=float(rng.uniform(0.85, 1.15)), ambient=float(rng.uniform(0.18, 0.32)),
        target=np.array([rng.normal(0, 0.02), rng.normal(0, 0.02), 0.0]), half=(hx, hy),
    )
    env = o3d.t.geometry.RaycastingScene()
    shadow = o3d.t.geometry.RaycastingScene()
    for lo, hi, mat in boxes:
        v, f = _box_mesh(lo, hi)
        env.add_triangles(o3d.core.Tensor(v), o3d.core.Tensor(f))
        shadow.add_triangles(o3d.core.Tensor(v), o3d.core.Tensor(f))
        scene.env_ids.append(mat)
    for o, p in zip(objs, poses):
        v = p.transform(o.model.vertices).astype(np.float32)
        shadow.add_triangles(o3d.core.Tensor(v), o3d.core.Tensor(np.ascontiguousarray(o.model.faces, np.uint32)))
    scene.env_scene, scene.shadow_scene = env, shadow
    return scene


def _look_at(eye: np.ndarray, target: np.ndarray, roll: float) -> Pose:
    """World-to-camera pose (OpenCV camera: z forward, y down) looking from eye at target."""
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 1.0, 0.0])
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = math.cos(roll), math.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    R_c2w = np.stack([x, y, z], axis=1)
    return Pose(R_c2w.T, -R_c2w.T @ eye)


def _sample_camera(rng: np.random.Generator, scene: _Scene, K: np.ndarray, width: int, height: int) -> Pose:
    centres = np.array([p.t for p in scene.world_poses])
    for attempt in range(200):
        dist = rng.uniform(0.5, 1.0) * (1.0 + 0.01 * max(0, attempt - 100))
        tilt = math.radians(rng.uniform(0.0, 25.0))
        az = rng.uniform(-np.pi, np.pi)
        roll = math.radians(rng.uniform(-45.0, 45.0))
        target = scene.target + np.array([rng.normal(0, 0.02), rng.normal(0, 0.02), 0.0])
        eye = target + dist * np.array([math.sin(tilt) * math.cos(az), math.sin(tilt) * math.sin(az), math.cos(tilt)])
        w2c = _look_at(eye, target, roll)
        pc = w2c.transform(centres)
        uv = pc @ K.T
        uv = uv[:, :2] / uv[:, 2:3]
        m = CENTER_MARGIN_PX
        if np.all(pc[:, 2] > 0.1) and np.all((uv[:, 0] >= m) & (uv[:, 0] < width - m)
                                              & (uv[:, 1] >= m) & (uv[:, 1] < height - m)):
            return w2c
    raise RuntimeError("could not place a camera that sees every object centre")


# --------------------------------------------------------------------------- one image


def _apply(R: np.ndarray, a: np.ndarray) -> np.ndarray:
    """R @ a for (..., 3) arrays, elementwise (no BLAS call: BLAS threads stall on a busy
    machine for these tall-and-thin products)."""
    R = np.asarray(R, dtype=np.float32)
    return a[..., 0:1] * R[:, 0] + a[..., 1:2] * R[:, 1] + a[..., 2:3] * R[:, 2]


def _render_image(
    rng: np.random.Generator, scene: _Scene, w2c: Pose, K: np.ndarray, width: int, height: int,
    rays: np.ndarray, noise: sensor.DepthNoise,
) -> tuple[np.ndarray, np.ndarray, list[Pose], list[dict[str, Any]]]:
    import open3d as o3d

    from ..core.render import render, render_box
    from .parts import MATERIALS

    c2w = w2c.inverse()
    H, W = height, width
    poses = [w2c.compose(p) for p in scene.world_poses]  # model to camera
    models = [o.model for o in scene.objects]
    obj = render(models, poses, K, W, H)

    # World-frame rays of the pixels (camera z = 1 so t_hit is the z-depth), built separably.
    A = (c2w.R @ np.linalg.inv(K)).astype(np.float32)
    u = np.arange(W, dtype=np.float32)
    v = np.arange(H, dtype=np.float32)
    rays_w = (v[:, None] * A[:, 1] + A[:, 2])[:, None, :] + (u[:, None] * A[:, 0])[None, :, :]
    eye = c2w.t.astype(np.float32)
    cr = np.empty((H, W, 6), np.float32)
    cr[..., :3] = eye
    cr[..., 3:] = rays_w
    ans = scene.env_scene.cast_rays(o3d.core.Tensor(cr.reshape(-1, 6)), nthreads=1)
    env_depth = ans["t_hit"].numpy().reshape(H, W)
    env_gid = ans["geometry_ids"].numpy().reshape(H, W).astype(np.int64)
    env_n = ans["primitive_normals"].numpy().reshape(H, W, 3)  # world frame
    env_hit = np.isfinite(env_depth)

    obj_depth = np.where(obj.mask >= 0, obj.depth, np.float32(np.inf))
    use_obj = (obj.mask >= 0) & (obj_depth < env_depth)
    mask = np.where(use_obj, obj.mask, -1).astype(np.int16)
    depth = np.where(use_obj, obj_depth, np.where(env_hit, env_depth, np.float32(np.nan))).astype(np.float32)
    surface = np.isfinite(depth)
    n_w = env_n.copy()  # world-frame normals, then the camera-frame ones for the sensor model
    n_w[use_obj] = _apply(c2w.R, obj.normals[use_obj])
    flip = (n_w * rays_w).sum(-1) > 0  # face the camera
    n_w[flip] *= -1.0
    pts_w = eye + rays_w * np.where(surface, depth, np.float32(0.0))[..., None]

    # material maps
    albedo = np.zeros((H, W, 3), np.float32)
    ks = np.zeros((H, W), np.float32)
    shin = np.full((H, W), 10.0, np.float32)
    shiny = np.zeros((H, W), np.float32)
    env_sel = (~use_obj) & env_hit
    mats = sorted(set(scene.env_ids))
    mat_of_gid = np.array([mats.index(m) for m in scene.env_ids] + [-1], np.int64)
    env_mat = np.where(env_sel, mat_of_gid[np.minimum(env_gid, len(scene.env_ids))], -1)
    for mi, mat in enumerate(mats):
        sel = env_mat == mi
        if not sel.any():
            continue
        pw, nw = pts_w[sel], n_w[sel]
        tex = scene.textures[mat]
        size = tex.shape[0]
        texel = 0.5 / size  # the texture spans 0.5 m
        horizontal = np.abs(nw[:, 2]) > 0.7
        along_x = np.abs(nw[:, 0]) < np.abs(nw[:, 1])
        tu = np.where(horizontal | along_x, pw[:, 0], pw[:, 1])
        tv = np.where(horizontal, pw[:, 1], pw[:, 2])
        albedo[sel] = _sample_texture(tex, np.mod(tu / texel, size), np.mod(tv / texel, size))
        ks[sel], shin[sel] = scene.env_props[mat]
    for i, (o, pose) in enumerate(zip(scene.objects, poses)):
        sel = mask == i
        if not sel.any():
            continue
        if o.model.colors is not None and np.ptp(o.model.colors, axis=0).max() > 0:
            if o.tree is None:
                from scipy.spatial import cKDTree

                o.tree = cKDTree(o.model.vertices)
            pm = (rays[sel] * depth[sel][:, None] - pose.t) @ pose.R  # model frame
            _, nn = o.tree.query(pm)
            albedo[sel] = o.model.colors[nn].astype(np.float32) / 255.0
        else:
            albedo[sel] = o.color
        mp = MATERIALS.get(o.material, MATERIALS["matte"])
        ks[sel], shin[sel], shiny[sel] = mp["ks"], mp["shininess"], mp["dropout"]

    # cast shadows: is the light visible from the surface point?
    sr = np.empty((H, W, 6), np.float32)
    sr[..., :3] = pts_w + n_w * np.float32(2e-3)
    sr[..., 3:] = scene.light.astype(np.float32) - sr[..., :3]
    occ = scene.shadow_scene.test_occlusions(o3d.core.Tensor(sr.reshape(-1, 6)), tnear=0.0, tfar=1.0, nthreads=1)
    lit = ~occ.numpy().reshape(H, W).astype(bool)
    lin = sensor.shade(albedo, n_w, pts_w, scene.light, ks, shin, lit=lit, light_power=scene.light_power,
                       ambient=scene.ambient, ref_dist=float(np.linalg.norm(scene.light)), eye=eye)
    lin[~surface] = 0.02
    rgb = sensor.finish_rgb(lin, rng, exposure=0.85)
    normals = _apply(w2c.R, n_w)  # camera frame
    noisy = sensor.simulate_depth(depth, normals, K, rng, shiny=shiny, params=noise)

    # scene_gt_info, as bop_toolkit's calc_gt_info but with exact visibility masks
    infos = []
    Kbig = K.copy()
    Kbig[0, 2] += W
    Kbig[1, 2] += H
    valid = np.isfinite(noisy)
    for i, (m, pose) in enumerate(zip(models, poses)):
        solo = render_box(m, pose, K, W, H, margin=0)
        sy, sx = np.nonzero(solo.mask >= 0)
        sx, sy = sx + solo.offset[0], sy + solo.offset[1]
        xs_all, ys_all = sx, sy
        uv = m.hull_points @ pose.R.T + pose.t
        uv = uv @ K.T
        uv = uv[:, :2] / uv[:, 2:3]
        if uv[:, 0].min() < 1 or uv[:, 1].min() < 1 or uv[:, 0].max() > W - 2 or uv[:, 1].max() > H - 2:
            big = render_box(m, pose, Kbig, 3 * W, 3 * H, margin=0)
            by, bx = np.nonzero(big.mask >= 0)
            bx, by = bx + big.offset[0] - W, by + big.offset[1] - H
            out = (bx < 0) | (bx >= W) | (by < 0) | (by >= H)
            xs_all = np.concatenate([sx, bx[out]])
            ys_all = np.concatenate([sy, by[out]])
        vis = mask == i
        n_all = int(xs_all.size)
        n_vis = int(vis.sum())
        n_valid = int(valid[sy, sx].sum())
        vy, vx = np.nonzero(vis)
        infos.append({
            "bbox_obj": _bbox(xs_all, ys_all) if n_vis else [-1, -1, -1, -1],
            "bbox_visib": _bbox(vx, vy) if n_vis else [-1, -1, -1, -1],
            "px_count_all": n_all,
            "px_count_valid": n_valid,
            "px_count_visib": n_vis,
            "visib_fract": float(n_vis / n_all) if n_all else 0.0,
        })
    return rgb, noisy, poses, infos


def _sample_texture(tex: np.ndarray, x: np.ndarray, y: np.ndarray, row: int = 1024) -> np.ndarray:
    """Bilinear, wrapping texture lookup at N float pixel positions: (N, 3)."""
    import cv2

    n = len(x)
    m = -(-n // row) * row
    mx = np.zeros(m, np.float32)
    my = np.zeros(m, np.float32)
    mx[:n], my[:n] = x, y
    out = cv2.remap(tex, mx.reshape(-1, row), my.reshape(-1, row), cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    return out.reshape(-1, tex.shape[2])[:n]


def _bbox(xs: np.ndarray, ys: np.ndarray) -> list[int]:
    return [int(xs.min()), int(ys.min()), int(xs.max() - xs.min()), int(ys.max() - ys.min())]


# --------------------------------------------------------------------------- models


def _prepare_models(models_out: Path, models_dir: Path | None) -> list[_Obj]:
    from ..core.models import load_model
    from .bop_json import load_json, save_json
    from .bop_models import load_models_info
    from .parts import build_parts, write_models

    if models_dir is None:
        parts = build_parts()
        write_models(models_out, parts)
    else:
        models_dir = Path(models_dir)
        if not (models_dir / "models_info.json").is_file():
            raise FileNotFoundError(f"not a BOP models folder (no models_info.json): {models_dir}")
        info = load_models_info(models_dir)
        models_out.mkdir(parents=True, exist_ok=True)
        for obj_id in info:
            src = models_dir / f"obj_{obj_id:06d}.ply"
            if not src.is_file():
                raise FileNotFoundError(f"model file missing for object {obj_id}: {src}")
            shutil.copyfile(src, models_out / src.name)
        shutil.copyfile(models_dir / "models_info.json", models_out / "models_info.json")
        if (models_dir / "parts.json").is_file():
            save_json(models_out / "parts.json", load_json(models_dir / "parts.json"))
    info = load_models_info(models_out)
    meta = load_json(models_out / "parts.json") if (models_out / "parts.json").is_file() else {}
    pool = []
    for obj_id, entry in sorted(info.items()):
        model = load_model(models_out / f"obj_{obj_id:06d}.ply", obj_id, entry)
        m = meta.get(str(obj_id), {})
        rests, probs = stable_poses(model.vertices, model.faces)
        pool.append(_Obj(
            obj_id=obj_id, model=model, material=m.get("material", "matte"),
            color=np.asarray(m.get("color", (0.6, 0.6, 0.6)), np.float32), rests=rests, rest_probs=probs,
        ))
    return pool


def _write_models_eval(models: Path, models_eval: Path) -> None:
    """models_eval/: copies of the meshes and models_info.json of models/ (see the module docstring)."""
    models_eval.mkdir(parents=True, exist_ok=True)
    for src in sorted(models.glob("obj_*.ply")) + [models / "models_info.json"]:
        shutil.copyfile(src, models_eval / src.name)


# --------------------------------------------------------------------------- driver


def _write_json_atomic(path: Path, obj: Any) -> None:
    atomic_write(path, json.dumps(obj, indent=2, sort_keys=True) + "\n")


def _is_ours(path: Path) -> bool:
    try:
        return read_json_file(path / "dataset_info.json").get("generator") == GENERATOR_NAME
    except (OSError, ValueError, AttributeError):
        return False


def generate(
    out: str | os.PathLike,
    scenes: int = 4,
    images_per_scene: int = 10,
    seed: int = 0,
    models_dir: str | os.PathLike | None = None,
    progress: bool = True,
    width: int = 640,
    height: int = 480,
    depth: bool = True,
) -> Path:
    """Write a synthetic BOP dataset to `out` (split "test"); returns `out`.

    `depth=False` writes an RGB-only dataset (no depth folders): the same scenes, images and
    annotations as with depth (the same random draws), without the depth images.

    `models_dir`: a BOP models folder whose models are placed instead of the procedural
    parts (copied into out/models). An existing `out` is replaced only when it is an empty
    folder or a dataset this generator wrote; anything else raises ValueError.
    """
    from ..core.scene import Frame, SceneObject
    from .bop_writer import SceneWriter

    out = Path(out)
    if scenes < 1 or images_per_scene < 1:
        raise ValueError("need at least one scene and one image, "
                         f"got scenes={scenes} images_per_scene={images_per_scene}")
    if width < 64 or height < 48:
        raise ValueError(f"image size {width}x{height} is too small")
    if out.exists() and not (out.is_dir() and (not any(out.iterdir()) or _is_ours(out))):
        raise ValueError(f"{out} exists and is not a dataset written by this generator: refusing to replace it")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.incomplete-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    (tmp / ".incomplete").write_text("generation in progress or interrupted\n")
    K = LINEMOD_K.copy()
    if (width, height) != (640, 480):  # same field of view, scaled
        K[0] *= width / 640.0
        K[1] *= height / 480.0
    t0 = time.perf_counter()
    try:
        pool = _prepare_models(tmp / "models", Path(models_dir) if models_dir is not None else None)
        _write_models_eval(tmp / "models", tmp / "models_eval")
        _write_json_atomic(tmp / "camera.json", {
            "cx": float(K[0, 2]), "cy": float(K[1, 2]), "depth_scale": DEPTH_SCALE,
            "fx": float(K[0, 0]), "fy": float(K[1, 1]), "height": int(height), "width": int(width),
        })
        rays = sensor.pixel_rays(K, width, height).astype(np.float32)
        noise = sensor.DepthNoise()
        targets = []
        from tqdm import tqdm

        bar = tqdm(total=scenes * images_per_scene, desc="synth", unit="img", disable=not progress)
        try:
            for scene_id in range(scenes):
                scene = _make_scene(np.random.default_rng([seed, scene_id]), pool)
                with SceneWriter(tmp, "test", scene_id, depth_scale=DEPTH_SCALE, append=False) as writer:
                    for im_id in range(images_per_scene):
                        rng = np.random.default_rng([seed, scene_id, im_id, 1])
                        w2c = _sample_camera(rng, scene, K, width, height)
                        rgb, dimg, poses, infos = _render_image(rng, scene, w2c, K, width, height, rays, noise)
                        objects = [SceneObject(o.obj_id, gt=p) for o, p in zip(scene.objects, poses)]
                        frame = Frame(rgb=rgb, depth=dimg if depth else None, K=K, scene_id=scene_id, im_id=im_id,
                                      objects=objects)
                        writer.add(frame, gt_info=infos, world_to_cam=w2c)
                        targets += [{"im_id": im_id, "inst_count": 1, "obj_id": o.obj_id, "scene_id": scene_id}
                                    for o, inf in zip(scene.objects, infos) if inf["visib_fract"] >= 0.1]
                        bar.update(1)
        finally:
            bar.close()
        _write_json_atomic(tmp / "test_targets_bop19.json", targets)
        elapsed = time.perf_counter() - t0
        _write_json_atomic(tmp / "dataset_info.json", {
            "generator": GENERATOR_NAME, "seed": int(seed), "scenes": int(scenes),
            "images_per_scene": int(images_per_scene), "width": int(width), "height": int(height),
            "models": "procedural parts" if models_dir is None else "copied from a BOP models folder",
            "depth_scale": DEPTH_SCALE, "split": "test", "depth": bool(depth),
        })
        (tmp / ".incomplete").unlink()
        if out.exists():
            trash = out.parent / f".{out.name}.old-{os.getpid()}"
            os.rename(out, trash)
            os.rename(tmp, out)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            os.rename(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    n = scenes * images_per_scene
    LAST_STATS.clear()
    LAST_STATS.update(images=n, seconds=elapsed, images_per_second=n / elapsed if elapsed > 0 else float("inf"))
    return out
