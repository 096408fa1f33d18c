"""Model-to-scene registration from 3D features, for the model-only generator (blocks/generation.py).

- `fpfh`, `model_features`: FPFH descriptors (open3d) of a point cloud and of a model's
  voxel-downsampled surface samples (cached per model), with the model's principal-axis flips.
- `ransac_candidates`: compatibility-guided RANSAC over putative correspondences, every
  hypothesis scored on the whole cluster through the model's distance field; `kabsch_batch`:
  batched least-squares rigid transforms.
- `distance_field`: the model's surface distance field on a grid (cached per model).
"""
from __future__ import annotations

import math
import threading
import time
import weakref
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from ..core.geometry import Pose
from ..core.models import ObjectModel


def point_cloud(points: np.ndarray, normals: np.ndarray | None = None) -> o3d.geometry.PointCloud:
    """An open3d point cloud of (N, 3) points, with normals when given (copied as float64)."""
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(points, dtype=np.float64, order="C")))
    if normals is not None:
        pc.normals = o3d.utility.Vector3dVector(np.array(normals, dtype=np.float64, order="C"))
    return pc


def fpfh(pc: o3d.geometry.PointCloud, voxel: float) -> np.ndarray:
    """(N, 33) FPFH descriptors (radius 5 voxels) of a point cloud that has normals."""
    f = o3d.pipelines.registration.compute_fpfh_feature(
        pc, o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel, max_nn=100)
    )
    return np.asarray(f.data).T.copy()


@dataclass
class ModelFeatures:
    points: np.ndarray  # (N, 3) voxel-downsampled surface samples, model frame
    normals: np.ndarray
    features: np.ndarray  # (N, 33)
    tree: cKDTree  # over the normalised features
    centre: np.ndarray  # centroid of the surface samples
    flips: list[np.ndarray]  # 180 deg rotations about the principal axes (near-symmetry variants)


_MODEL_FEATURES: "weakref.WeakKeyDictionary[ObjectModel, dict[float, ModelFeatures]]" = weakref.WeakKeyDictionary()
MODEL_CACHE_LOCK = threading.Lock()  # guards the per-model caches here and in colour.py


def model_features(model: ObjectModel, voxel: float) -> ModelFeatures:
    """FPFH features of the model's surface samples at a voxel size; cached per model."""
    with MODEL_CACHE_LOCK:
        per = _MODEL_FEATURES.setdefault(model, {})
        mf = per.get(voxel)
    if mf is not None:
        return mf
    pc = point_cloud(model.points, model.point_normals).voxel_down_sample(voxel)
    pc.normalize_normals()
    feats = fpfh(pc, voxel)
    pts = np.asarray(pc.points).copy()
    mf = ModelFeatures(pts, np.asarray(pc.normals).copy(), feats, cKDTree(normalise_features(feats)),
                       model.points.mean(axis=0), principal_flips(model))
    with MODEL_CACHE_LOCK:
        per[voxel] = mf
    return mf


def principal_flips(model: ObjectModel) -> list[np.ndarray]:
    """Rotations by pi about the model's principal axes (through the centroid of its samples):
    the typical confusion of near-symmetric parts."""
    axes = np.linalg.svd(model.points - model.points.mean(axis=0), full_matrices=False)[2]
    return [2.0 * np.outer(a, a) - np.eye(3) for a in axes]


def flipped(pose: Pose, flip: np.ndarray, centre: np.ndarray) -> Pose:
    """`pose` turned by the model-frame rotation `flip` about the model point `centre`."""
    return Pose(pose.R @ flip, pose.R @ (centre - flip @ centre) + pose.t)


def normalise_features(f: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(f, axis=1, keepdims=True)
    return f / np.maximum(n, 1e-9)


def kabsch_batch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid transforms (B, 3, 3), (B, 3) mapping src (B, k, 3) onto dst."""
    cs, cd = src.mean(axis=1), dst.mean(axis=1)
    H = np.einsum("bki,bkj->bij", src - cs[:, None], dst - cd[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("bij,bjk->bik", U, Vt)))
    D = np.zeros_like(H)
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = np.einsum("bji,bjk,bkl->bil", Vt, D, np.transpose(U, (0, 2, 1)))
    t = cd - np.einsum("bij,bj->bi", R, cs)
    return R, t


def ransac_candidates(
    src: np.ndarray,
    dst: np.ndarray,
    scene: np.ndarray,
    scene_normals: np.ndarray,
    field: "DistanceField",
    threshold: float,
    iterations: int,
    keep: int,
    rng: np.random.Generator,
    deadline: float,
    min_separation: float,
    batch: int = 256,
) -> list[tuple[Pose, int]]:
    """RANSAC over putative correspondences src[i] (model) <-> dst[i] (scene).

    Sampling is guided by pairwise consistency (as in spectral matching / TEASER's compatibility
    graph): two correspondences are compatible when they preserve their distance within
    `threshold`; a minimal sample is a correspondence, a random compatible one, and a third
    compatible with both. With FPFH on real partial views only a few per cent of the putative
    correspondences are right, so uniform triples would almost never be all inliers. Each
    Kabsch transform is scored by how many `scene` points lie within `threshold` of the model
    surface, with normals agreeing within 60 deg, once mapped into the model frame (a lookup
    in the model's distance field): every hypothesis is scored on the whole cluster, not only
    on the correspondences. Returns up to `keep` hypotheses with the best scores whose model
    centres are at least `min_separation` apart or whose rotations differ by > 30 deg: distinct
    candidates for verification, unlike open3d's single best."""
    n = len(src)
    if n < 3 or len(scene) == 0:
        return []
    ld = cdist(dst, dst)
    compat = np.abs(cdist(src, src) - ld) < threshold
    compat &= ld > 2.0 * threshold
    del ld
    r, cols = np.nonzero(compat)  # row-major: the compatible partners of each, as CSR
    deg = np.bincount(r, minlength=n)
    ptr = np.r_[0, np.cumsum(deg)]
    firsts = np.flatnonzero(deg >= 2)
    if len(firsts) == 0:
        return []
    found_R, found_t, found_c = [], [], []
    done = 0
    cos60 = 0.5
    while done < iterations and time.perf_counter() < deadline:
        b = min(batch, iterations - done)
        done += b
        i = firsts[rng.integers(0, len(firsts), b)]
        j = cols[ptr[i] + (rng.random(b) * deg[i]).astype(np.int64)]
        ks = cols[ptr[i][:, None] + (rng.random((b, 8)) * deg[i][:, None]).astype(np.int64)]
        okk = compat[j[:, None], ks] & (ks != j[:, None])
        has = okk.any(axis=1)
        if not has.any():
            continue
        k = ks[np.arange(b), np.argmax(okk, axis=1)]
        idx = np.stack([i, j, k], axis=1)[has]
        R, t = kabsch_batch(src[idx], dst[idx])
        in_model = np.matmul(scene[None] - t[:, None], R)  # rows: R^T (p - t)
        n_model = np.matmul(scene_normals[None], R)
        dist, nrm = field.lookup(in_model)
        agree = np.sum(n_model * nrm, axis=2) > cos60
        count = ((dist < threshold) & agree).sum(axis=1)
        found_R.append(R)
        found_t.append(t)
        found_c.append(count)
    if not found_R:
        return []
    R, t, count = np.concatenate(found_R), np.concatenate(found_t), np.concatenate(found_c)
    out: list[tuple[Pose, int]] = []
    centre = field.centre
    cos30 = 1.0 + 2.0 * math.cos(math.radians(30.0))
    for i in np.argsort(-count, kind="stable"):
        if len(out) >= keep or count[i] < 3:
            break
        c_i = R[i] @ centre + t[i]
        if any(np.linalg.norm(p.R @ centre + p.t - c_i) < min_separation and np.trace(p.R.T @ R[i]) > cos30
               for p, _ in out):
            continue
        out.append((Pose(R[i], t[i]), int(count[i])))
    return out


@dataclass
class DistanceField:
    """Unsigned distance (metres) to the model surface on a regular grid in the model frame."""

    origin: np.ndarray
    cell: float
    grid: np.ndarray  # (nx, ny, nz) float32
    normals: np.ndarray  # (nx, ny, nz, 3) float32 outward normal of the nearest surface sample
    centre: np.ndarray  # centroid of the surface

    def lookup(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance (inf outside the grid) and nearest-surface normal of points (..., 3)."""
        ijk = ((p - self.origin) * (1.0 / self.cell)).astype(np.int64)  # truncation: p >= origin inside
        nx, ny, nz = self.grid.shape
        inside = (p[..., 0] >= self.origin[0]) & (p[..., 1] >= self.origin[1]) & (p[..., 2] >= self.origin[2])
        inside &= (ijk[..., 0] < nx) & (ijk[..., 1] < ny) & (ijk[..., 2] < nz)
        flat = np.where(inside, (ijk[..., 0] * ny + ijk[..., 1]) * nz + ijk[..., 2], 0)
        d = np.where(inside, self.grid.ravel()[flat], np.inf)
        return d, self.normals.reshape(-1, 3)[flat]


_FIELDS: "weakref.WeakKeyDictionary[ObjectModel, DistanceField]" = weakref.WeakKeyDictionary()


def distance_field(model: ObjectModel, cells: int = 64, margin: int = 6) -> DistanceField:
    """The model's surface distance field (cell = diameter / cells), cached per model: dense
    surface samples mark occupied cells, an exact Euclidean distance transform does the rest."""
    with MODEL_CACHE_LOCK:
        f = _FIELDS.get(model)
    if f is not None:
        return f
    from scipy.ndimage import distance_transform_edt

    from ..core.mesh import face_normals, sample_surface

    cell = model.diameter / cells
    _, area = face_normals(model.vertices, model.faces)
    n = int(min(400_000, max(20_000, 6.0 * area.sum() / cell**2)))
    pts, nrm = sample_surface(model.vertices, model.faces, model.normals, n, seed=0)
    origin = pts.min(axis=0) - margin * cell
    shape = np.ceil((pts.max(axis=0) + margin * cell - origin) / cell).astype(int) + 1
    occ = np.ones(shape, bool)
    ijk = np.floor((pts - origin) / cell).astype(int)
    occ[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = False
    cell_normals = np.zeros((*shape, 3), np.float32)
    cell_normals[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = nrm
    dist, nearest = distance_transform_edt(occ, return_indices=True)
    grid = np.maximum(dist * cell - 0.5 * cell, 0.0).astype(np.float32)  # cell centre to surface, roughly
    normals = cell_normals[nearest[0], nearest[1], nearest[2]]
    f = DistanceField(origin, cell, grid, normals, model.points.mean(axis=0))
    with MODEL_CACHE_LOCK:
        _FIELDS[model] = f
    return f
