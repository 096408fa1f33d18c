"""The scenes of the synthetic dataset (synthetic.py): objects dropped into a bin or onto a table
on their stable rests (stable_poses.py) and kept apart, the bin or table, one light, and the
cameras that see every object (see synthetic.py's docstring for the numbers).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..core.geometry import Pose
from . import sensor

CENTER_MARGIN_PX = 16
MIN_OBJECTS, MAX_OBJECTS = 3, 8

_ENV_MATERIALS = {  # name: (texture kind, ks, shininess)
    "bin": ("plastic", 0.12, 20.0),
    "table": ("wood", 0.05, 10.0),
    "concrete": ("concrete", 0.02, 6.0),
}
_BIN_COLOURS = [(0.10, 0.25, 0.55), (0.45, 0.46, 0.48), (0.12, 0.40, 0.20), (0.70, 0.35, 0.08), (0.12, 0.12, 0.13)]
_TABLE_COLOURS = {"wood": [(0.62, 0.45, 0.28), (0.75, 0.60, 0.42)],
                  "concrete": [(0.55, 0.55, 0.53), (0.42, 0.43, 0.45)]}


@dataclass
class SynthObject:
    """A model prepared for placement and shading."""

    obj_id: int
    model: Any  # ObjectModel (metres)
    material: str
    color: np.ndarray  # (3,) albedo when the model has no vertex colours
    rests: list[np.ndarray]
    rest_probs: np.ndarray
    tree: Any = None  # cKDTree over vertices for vertex-colour lookup


@dataclass
class SynthScene:
    """One scene: its objects, their poses on the floor, the bin or table, the light."""

    kind: str  # "bin" | "table"
    objects: list[SynthObject]
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


def _place(rng: np.random.Generator, objs: list[SynthObject], hx: float, hy: float, margin: float) -> list[Pose]:
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


def make_scene(rng: np.random.Generator, pool: list[SynthObject]) -> SynthScene:
    """A scene of 3-8 distinct objects of `pool`, with its raycasting scenes (environment, and
    everything for the shadows) built."""
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
    scene = SynthScene(
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


def sample_camera(rng: np.random.Generator, scene: SynthScene, K: np.ndarray, width: int, height: int) -> Pose:
    """A world-to-camera pose that sees every object centre at least CENTER_MARGIN_PX inside the image."""
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


__all__ = ["SynthObject", "SynthScene", "make_scene", "sample_camera"]
