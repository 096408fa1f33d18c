"""Depth, normal and instance-mask rendering of object models at poses (the hot path).

Rendering is ray casting with open3d's `RaycastingScene` (Embree BVH on the CPU; no GPU, no
display, unlike open3d's OffscreenRenderer which needs Vulkan). The design follows the measured
facts in the project notes:

- One scene per model, built once in the model frame and cached; the camera moves by
  transforming the rays into the model frame (origin -R^T t, direction R^T d), never by
  rebuilding the BVH.
- Ray directions have camera-frame z = 1 (d = K^-1 [u, v, 1]); rotations keep that length, so
  the hit parameter `t_hit` is directly the z-depth in metres.
- Only pixels inside an object's projected box are cast, so a cropped single-object render
  costs ~1 ms and a full frame with several objects costs the sum of their boxes, not 640x480
  rays per object. Several objects: every model gets the rays of its own box and the nearest
  hit wins, which is exact occlusion.

Conventions: pixel (u, v) has its centre at integer coordinates (OpenCV), so `project` and
the renderer agree with `cv2.projectPoints`. Background depth is NaN (as `Frame.depth`),
background normals are 0 (safe in dot products) and background mask is -1. Normals are in the
camera frame and face the camera (scanned meshes have inconsistent winding).
"""
from __future__ import annotations

import os
import threading
import weakref
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import open3d as o3d

from .geometry import Pose
from .models import ObjectModel

Box = tuple[int, int, int, int]  # x, y, w, h in pixels

MIN_Z = 1e-3  # metres: points closer than this to the camera plane cannot be projected


def _default_threads() -> int:
    """Threads per cast: 1 unless OMP_NUM_THREADS says otherwise (workers run one per core)."""
    try:
        return max(0, int(os.environ.get("OMP_NUM_THREADS", "1")))
    except ValueError:
        return 1


@dataclass
class Rendering:
    """Rendered images of a pixel box (the whole image when not cropped).

    depth: (h, w) float32 z-depth in metres, NaN where no object.
    normals: (h, w, 3) float32 unit normals in the camera frame, facing the camera; 0 where no object.
    mask: (h, w) int16 index into the rendered models list, -1 where no object.
    offset: (x0, y0) of the box in the full image; `full_size` is (width, height) of the image.
    """

    depth: np.ndarray
    normals: np.ndarray
    mask: np.ndarray
    offset: tuple[int, int]
    full_size: tuple[int, int]

    @property
    def box(self) -> Box:
        return (self.offset[0], self.offset[1], int(self.depth.shape[1]), int(self.depth.shape[0]))

    @property
    def empty(self) -> bool:
        return self.depth.size == 0 or not bool(np.any(self.mask >= 0))

    def crop_slices(self) -> tuple[slice, slice]:
        """Slices (rows, cols) of the full image covered by this rendering."""
        x, y, w, h = self.box
        return slice(y, y + h), slice(x, x + w)

    def to_full(self) -> "Rendering":
        """The same rendering pasted into full-size images (background elsewhere)."""
        W, H = self.full_size
        depth = np.full((H, W), np.nan, np.float32)
        normals = np.zeros((H, W, 3), np.float32)
        mask = np.full((H, W), -1, np.int16)
        rs, cs = self.crop_slices()
        depth[rs, cs], normals[rs, cs], mask[rs, cs] = self.depth, self.normals, self.mask
        return Rendering(depth, normals, mask, (0, 0), self.full_size)


def project(points_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixel coordinates (N, 2) of camera-frame points (N, 3); NaN for points with z <= MIN_Z."""
    p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    uvw = p @ np.asarray(K, dtype=np.float64).T
    z = uvw[:, 2:3]
    with np.errstate(invalid="ignore", divide="ignore"):
        uv = uvw[:, :2] / z
    uv[p[:, 2] <= MIN_Z] = np.nan
    return uv


def projected_box(
    model: ObjectModel, pose: Pose, K: np.ndarray, width: int, height: int, margin: int = 1
) -> Box | None:
    """Pixel box (x, y, w, h) of the model's projection clipped to the image, None when the
    object is entirely outside it. Uses the convex hull vertices: the projection of a convex
    hull contains the projection of the object, so the box is tight and never cuts it.
    When part of the object is behind the camera plane the whole image is returned."""
    pc = pose.transform(model.hull_points)
    if np.all(pc[:, 2] <= MIN_Z):
        return None
    if np.any(pc[:, 2] <= MIN_Z):
        return (0, 0, int(width), int(height))
    uv = project(pc, K)
    x0 = max(0, int(np.floor(uv[:, 0].min())) - margin)
    y0 = max(0, int(np.floor(uv[:, 1].min())) - margin)
    x1 = min(int(width), int(np.ceil(uv[:, 0].max())) + margin + 1)
    y1 = min(int(height), int(np.ceil(uv[:, 1].max())) + margin + 1)
    if x1 <= x0 or y1 <= y0:
        return None
    return (x0, y0, x1 - x0, y1 - y0)


# One raycasting scene per model, built lazily, dropped with the model.
_SCENES: "weakref.WeakKeyDictionary[ObjectModel, o3d.t.geometry.RaycastingScene]" = weakref.WeakKeyDictionary()
_SCENES_LOCK = threading.Lock()


def raycasting_scene(model: ObjectModel) -> o3d.t.geometry.RaycastingScene:
    """The cached open3d RaycastingScene of a model (model frame, metres)."""
    scene = _SCENES.get(model)
    if scene is None:
        with _SCENES_LOCK:
            scene = _SCENES.get(model)
            if scene is None:
                scene = o3d.t.geometry.RaycastingScene()
                scene.add_triangles(
                    o3d.core.Tensor(np.ascontiguousarray(model.vertices, dtype=np.float32)),
                    o3d.core.Tensor(np.ascontiguousarray(model.faces, dtype=np.uint32)),
                )
                _SCENES[model] = scene
    return scene


def _clip_box(box: Box | None, width: int, height: int) -> Box:
    if box is None:
        return (0, 0, int(width), int(height))
    x, y, w, h = (int(round(v)) for v in box)
    x0, y0 = max(0, x), max(0, y)
    x1, y1 = min(int(width), x + w), min(int(height), y + h)
    return (x0, y0, max(0, x1 - x0), max(0, y1 - y0))


def _intersect(a: Box, b: Box) -> Box | None:
    x0, y0 = max(a[0], b[0]), max(a[1], b[1])
    x1, y1 = min(a[0] + a[2], b[0] + b[2]), min(a[1] + a[3], b[1] + b[3])
    if x1 <= x0 or y1 <= y0:
        return None
    return (x0, y0, x1 - x0, y1 - y0)


def _cast(
    model: ObjectModel, pose: Pose, Kinv: np.ndarray, box: Box, nthreads: int, with_normals: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """Cast the rays of `box` at one model: z-depth (h, w) (inf = miss) and model-frame
    primitive normals (h, w, 3) oriented towards the camera (None without `with_normals`)."""
    x, y, w, h = box
    # Direction in the model frame for pixel (u, v): R^T K^-1 [u, v, 1] = u M0 + v M1 + M2,
    # with M = (R^T K^-1)^T = Kinv^T R (rows). Built separably: no per-pixel matrix products.
    M = Kinv.T @ pose.R
    rays = np.empty((h, w, 6), dtype=np.float32)
    rays[:, :, :3] = -pose.R.T @ pose.t
    u = np.arange(x, x + w, dtype=np.float64)
    v = np.arange(y, y + h, dtype=np.float64)
    np.add((v[:, None] * M[1] + M[2])[:, None, :], (u[:, None] * M[0])[None, :, :], out=rays[:, :, 3:],
           casting="same_kind")
    ans = raycasting_scene(model).cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=nthreads)
    depth = ans["t_hit"].numpy()
    if not with_normals:
        return depth, None
    normals = ans["primitive_normals"].numpy()
    # Face the camera: flip where the normal points along the ray (same sign in any frame).
    flip = np.einsum("hwc,hwc->hw", normals, rays[:, :, 3:]) > 0
    normals[flip] *= -1.0
    return depth, normals


def render(
    models: Sequence[ObjectModel],
    poses: Sequence[Pose],
    K: np.ndarray,
    width: int,
    height: int,
    crop: Box | None = None,
    nthreads: int | None = None,
    with_normals: bool = True,
) -> Rendering:
    """Render depth, normals and instance mask of `models` at `poses` (model-to-camera, metres)
    for a pinhole camera K of an image width x height, restricted to the pixel box `crop`
    (x, y, w, h; clipped to the image; None = whole image). Occlusion between the models is
    exact (nearest hit per pixel). `nthreads` threads per cast (default: OMP_NUM_THREADS or 1;
    0 = all cores). Without `with_normals` the normals are a read-only zero image (verification
    reads depth and mask only: a fifth less time per rendering)."""
    if len(models) != len(poses):
        raise ValueError(f"render: {len(models)} models but {len(poses)} poses")
    if len(models) > np.iinfo(np.int16).max:
        raise ValueError("render: too many models for an int16 mask")
    if width <= 0 or height <= 0:
        raise ValueError(f"render: bad image size {width}x{height}")
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    nthreads = _default_threads() if nthreads is None else nthreads
    box = _clip_box(crop, width, height)
    x, y, w, h = box
    depth = np.full((h, w), np.inf, np.float32)
    normals = np.zeros((h, w, 3), np.float32) if with_normals else np.broadcast_to(np.float32(0.0), (h, w, 3))
    mask = np.full((h, w), -1, np.int16)
    if w and h:
        Kinv = np.linalg.inv(K)
        for i, (model, pose) in enumerate(zip(models, poses)):
            obox = projected_box(model, pose, K, width, height)
            sub = _intersect(box, obox) if obox is not None else None
            if sub is None:
                continue
            d, n = _cast(model, pose, Kinv, sub, nthreads, with_normals)
            rs = slice(sub[1] - y, sub[1] - y + sub[3])
            cs = slice(sub[0] - x, sub[0] - x + sub[2])
            closer = d < depth[rs, cs]
            if not closer.any():
                continue
            depth[rs, cs][closer] = d[closer]
            mask[rs, cs][closer] = i
            if n is not None:
                normals[rs, cs][closer] = n[closer] @ pose.R.T.astype(np.float32)
    depth[mask < 0] = np.nan
    return Rendering(depth, normals, mask, (x, y), (int(width), int(height)))


def render_box(
    model: ObjectModel, pose: Pose, K: np.ndarray, width: int, height: int, margin: int = 1,
    nthreads: int | None = None, with_normals: bool = True,
) -> Rendering:
    """Render one model cropped to its projected box (plus `margin` px): the fast path for
    refinement and scoring. An object outside the image gives an empty (0 x 0) rendering."""
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    box = projected_box(model, pose, K, width, height, margin)
    if box is None:
        box = (0, 0, 0, 0)
    return render([model], [pose], K, width, height, crop=box, nthreads=nthreads, with_normals=with_normals)


def depth_to_points(depth: np.ndarray, K: np.ndarray, offset: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Back-project a (possibly cropped) depth image to camera-frame points (N, 3) of its valid
    pixels, row-major order; the inverse of rendering."""
    d = np.asarray(depth)
    v, u = np.nonzero(np.isfinite(d) & (d > 0))
    z = d[v, u].astype(np.float64)
    K = np.asarray(K, dtype=np.float64)
    uu, vv = u + offset[0], v + offset[1]
    x = (uu - K[0, 2] - K[0, 1] * (vv - K[1, 2]) / K[1, 1]) / K[0, 0] * z
    y = (vv - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], axis=1)


__all__ = ["Rendering", "render", "render_box", "project", "projected_box", "raycasting_scene", "depth_to_points",
           "Box"]
