"""Test frames made with the project's renderer: one or more models at known poses, a noisy
depth image and a shaded RGB image, so blocks can be tested without a dataset on disk."""
from __future__ import annotations

from typing import Iterator

import numpy as np

from perception_config.blocks.base import Block, BlockInput, BlockResult
from perception_config.core.geometry import Pose, exp_so3, perturb
from perception_config.core.metrics import pose_mssd
from perception_config.core.models import ObjectModel, make_model
from perception_config.core.render import render
from perception_config.core.scene import Frame, SceneObject

K_LINEMOD = np.array([[572.4114, 0.0, 325.2611], [0.0, 573.57043, 242.04899], [0.0, 0.0, 1.0]])


def box_mesh(size: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (8, 3) and outward-wound triangles (12, 3) of a box centred at the origin."""
    half = np.asarray(size, dtype=np.float64) / 2.0
    v = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float) * half
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    faces = []
    for a, b, c, d in quads:
        for tri in ([a, b, c], [a, c, d]):
            n = np.cross(v[tri[1]] - v[tri[0]], v[tri[2]] - v[tri[0]])
            faces.append(tri if n @ v[tri].mean(axis=0) > 0 else tri[::-1])
    return v, np.array(faces, dtype=np.int32)


def cylinder_mesh(radius: float = 0.03, height: float = 0.05, n: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """A closed n-gon prism about z, centred (metres): (vertices, faces)."""
    a = 2 * np.pi * np.arange(n) / n
    ring = np.stack([radius * np.cos(a), radius * np.sin(a)], axis=1)
    v = np.concatenate([np.c_[ring, np.full(n, -height / 2)], np.c_[ring, np.full(n, height / 2)],
                        [[0, 0, -height / 2], [0, 0, height / 2]]])
    faces = []
    for i in range(n):
        j = (i + 1) % n
        faces += [(i, j, n + j), (i, n + j, n + i), (2 * n, j, i), (2 * n + 1, n + i, n + j)]
    return v, np.array(faces)


def box_model(obj_id: int = 1, size=(0.08, 0.05, 0.03)) -> ObjectModel:
    """A closed box model (metres) with sharp edges."""
    v, f = box_mesh(size)
    return make_model(obj_id, v, f)


def default_pose(z: float = 0.7) -> Pose:
    return Pose(exp_so3([0.6, -0.4, 0.3]), [0.02, -0.01, z])


def synthetic_frame(
    models: list[ObjectModel], poses: list[Pose], seed: int = 0, K: np.ndarray = K_LINEMOD,
    width: int = 640, height: int = 480, background_z: float | None = 0.9, depth_noise: float = 0.001,
) -> Frame:
    """Render models over a flat background plane; Gaussian depth noise; Lambert-shaded RGB."""
    rng = np.random.default_rng(seed)
    r = render(models, poses, K, width, height)
    depth = r.depth.copy()
    bg = np.isnan(depth)
    if background_z is not None:
        depth[bg] = background_z
    depth = depth + rng.normal(0.0, depth_noise, depth.shape).astype(np.float32)
    light = np.array([0.3, -0.5, -1.0])
    light /= np.linalg.norm(light)
    shade = np.clip(r.normals @ light, 0.0, 1.0)  # normals face the camera; light from the camera side
    gray = np.where(bg, 60.0, 40.0 + 200.0 * shade) + rng.normal(0, 2.0, shade.shape)
    rgb = np.clip(np.repeat(gray[..., None], 3, axis=2), 0, 255).astype(np.uint8)
    objects = [SceneObject(obj_id=m.obj_id, gt=p, model=m) for m, p in zip(models, poses)]
    return Frame(rgb=rgb, depth=depth.astype(np.float32), K=K, stamp=1.0, objects=objects)


def random_box_scene(seed: int, **frame_kw) -> tuple[ObjectModel, Pose, Frame]:
    """The box at a rotation drawn from `seed`, 0.7 m in front of the camera, in a frame rendered
    with that seed (`frame_kw` go to synthetic_frame)."""
    model = box_model()
    gt = Pose(exp_so3(np.random.default_rng(seed).normal(size=3)), [0.02, -0.01, 0.7])
    return model, gt, synthetic_frame([model], [gt], seed=seed, **frame_kw)


def perturbed_pose(gt: Pose, rng: np.random.Generator, deg: float | tuple[float, float] = 5.0,
                   mm: float | tuple[float, float] = 5.0) -> Pose:
    """`gt` rotated by exactly `deg` about a random axis and shifted by exactly `mm` in a random
    direction; a (low, high) pair draws the amount uniformly (after the axis and the direction)."""
    w, d = rng.normal(size=3), rng.normal(size=3)
    if isinstance(deg, tuple):
        deg = rng.uniform(*deg)
    if isinstance(mm, tuple):
        mm = rng.uniform(*mm)
    return Pose(exp_so3(w / np.linalg.norm(w) * np.radians(deg)) @ gt.R, gt.t + d / np.linalg.norm(d) * mm * 1e-3)


def refine_perturbed(block: Block, frame: Frame, model: ObjectModel, gt: Pose, rng: np.random.Generator, n: int = 10,
                     cache: dict | None = None, **perturbation) -> Iterator[tuple[Pose, BlockResult]]:
    """Run `block` from `n` starts perturbed_pose(gt, rng, **perturbation), the i-th call seeded
    with i, all sharing `cache`; each call must succeed. Yields (start, result). The calls are not
    time-bounded: these tests judge what the algorithm does, and a loaded CI machine must not cut
    a 0.1 s budget before its first step (the budgets have their own tests)."""
    cache = {} if cache is None else cache
    for i in range(n):
        start = perturbed_pose(gt, rng, **perturbation)
        r = block(BlockInput(frame=frame, model=model, pose=start, cache=cache, rng=np.random.default_rng(i),
                             time_bounded=False))
        assert r.ok, r.reason
        yield start, r


def refine_from_lambda(block: Block, frames: list[Frame], objects, rng: np.random.Generator, seeds: int,
                       lam: float = 0.3) -> tuple[np.ndarray, np.ndarray, list[BlockResult]]:
    """One call of `block` from `seeds` starts geometry.perturb(gt, lam) of every object
    `objects(frame)` lists, frame by frame (one cache per frame, the i-th start's call seeded with
    i); each call must succeed. Returns MSSD / diameter before and after, and the results."""
    before, after, results = [], [], []
    for frame in frames:
        cache: dict = {}
        for obj in objects(frame):
            for seed in range(seeds):
                start = perturb(obj.gt, lam, obj.model.diameter, rng)
                r = block(BlockInput(frame=frame, model=obj.model, pose=start, cache=cache,
                                     rng=np.random.default_rng(seed)))
                assert r.ok, r.reason
                before.append(pose_mssd(start, obj.gt, obj.model) / obj.model.diameter)
                after.append(pose_mssd(r.pose, obj.gt, obj.model) / obj.model.diameter)
                results.append(r)
    return np.array(before), np.array(after), results


def mean_point_distance(model: ObjectModel, a: Pose, b: Pose) -> float:
    """ADD (m): mean distance of the model's points under the two poses."""
    return float(np.mean(np.linalg.norm(a.transform(model.points) - b.transform(model.points), axis=1)))


def well_visible(frame: Frame, min_visib: float) -> list[SceneObject]:
    """The frame's objects of which more than `min_visib` is visible (BOP's visib_fract)."""
    return [o for o in frame.objects if o.visib_fract is not None and o.visib_fract > min_visib]


def resting_on_plane(model: ObjectModel, plane_z: float, xy: tuple[float, float] = (0.0, 0.0), turn: float = 0.0,
                     rest: int = 0) -> Pose:
    """The model lying on its `rest`-th stable face (vision/resting_poses) on the background plane
    z = `plane_z` of synthetic_frame, turned by `turn` radians about the plane's normal, its
    centroid over plane coordinates `xy` (metres)."""
    from perception_config.vision.resting_poses import plane_basis, resting_poses

    r = resting_poses(model)[rest]
    B, o = plane_basis(np.array([0.0, 0.0, -1.0, plane_z]))
    c, s = np.cos(turn), np.sin(turn)
    R_plane = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ r.R
    shift = np.array([xy[0], xy[1], r.lift])
    return Pose(B @ R_plane, o + B @ (shift - R_plane @ model.points.mean(axis=0)))
