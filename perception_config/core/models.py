"""Object models: mesh, surface samples, diameter, symmetries and edge points, prepared once.

Everything every block needs about an object is computed here once per model file and cached,
so refinement and scoring never touch a mesh file in their hot loop. Units are metres inside
the code; BOP PLY files are millimetres and are converted when read. The pieces live beside:
PLY files in core/ply.py, mesh helpers (normals, samples, hull, diameter, sharp edges) in
core/mesh.py, symmetries in core/symmetry.py.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .geometry import MM, Pose
from .mesh import (
    DEFAULT_EDGE_ANGLE_DEG,
    MAX_HULL_INPUT,
    convex_hull_points,
    max_pairwise_distance,
    normalize,
    sample_edges,
    sample_surface,
    sharp_edges,
    vertex_normals,
)
from .ply import PlyError, read_ply_mesh
from .symmetry import DEFAULT_CONT_STEP_DEG, symmetries_from_info

DEFAULT_N_POINTS = 3000  # surface samples per model: enough for ICP and scores, cheap to transform
DEFAULT_MAX_EDGE_POINTS = 2000
COLLINEAR = 1e-4  # samples spread less than this share of the diameter across their line: degenerate


@dataclass(eq=False)
class ObjectModel:
    """A rigid object model in metres, with everything derived from the mesh precomputed.

    Instances are shared through a cache: arrays are read-only and equality is identity
    (so a model can key per-model caches such as the renderer's raycasting scenes).
    """

    obj_id: int
    vertices: np.ndarray  # (N, 3) float64 metres, model frame
    faces: np.ndarray  # (M, 3) int32 vertex indices, triangles
    normals: np.ndarray  # (N, 3) float64 unit vertex normals
    diameter: float  # metres: max distance between two model points
    points: np.ndarray  # (P, 3) area-uniform surface samples
    point_normals: np.ndarray  # (P, 3) unit normals at `points`
    symmetries: list[Pose]  # symmetry transformations in the model frame, identity first
    edge_points: np.ndarray  # (E, 3) points on sharp mesh edges
    edge_dirs: np.ndarray  # (E, 3) unit 3D directions of those edges
    hull_points: np.ndarray  # (H, 3) convex hull vertices: tight projected boxes, diameter
    bbox_min: np.ndarray  # (3,) axis-aligned box corner in the model frame
    bbox_size: np.ndarray  # (3,) box extents
    colors: np.ndarray | None = None  # (N, 3) uint8 vertex colours, when the file has them
    path: Path | None = None
    info: dict[str, Any] | None = field(default=None, repr=False)  # the models_info entry (mm)

    def __repr__(self) -> str:
        return (
            f"ObjectModel(obj_id={self.obj_id}, vertices={len(self.vertices)}, faces={len(self.faces)}, "
            f"diameter={self.diameter:.4f} m, symmetries={len(self.symmetries)}, path={self.path})"
        )

    @property
    def is_symmetric(self) -> bool:
        return len(self.symmetries) > 1

    @property
    def corners(self) -> np.ndarray:
        """The 8 corners (8, 3) of the axis-aligned bounding box in the model frame."""
        idx = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], dtype=np.float64)
        return self.bbox_min + idx * self.bbox_size


def model_defect(model: ObjectModel) -> str:
    """Why `model` cannot be matched against a depth image, or '' when it can: no size, surface
    samples that are not finite, (nearly) collinear or coincident (zero-area faces), or without
    normals. make_model refuses a mesh of zero area outright; this also catches the nearly
    degenerate ones it accepts (a needle 1e-9 m across) and models assembled by other means
    (dataclasses.replace). Cheap: it reads the surface samples, not the mesh."""
    d, pts, nrm = float(model.diameter), model.points, model.point_normals
    name = f"model {model.obj_id}"
    if not (math.isfinite(d) and d > 0.0) or len(pts) < 3:
        return f"{name} is degenerate: diameter {d:.3g} m, {len(pts)} surface samples"
    if not (np.all(np.isfinite(pts)) and np.all(np.isfinite(nrm))):
        return f"{name} is degenerate: its surface samples or their normals are not finite"
    spread = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False) / math.sqrt(len(pts))
    if spread[1] < COLLINEAR * d:
        return (f"{name} is degenerate: its surface is (nearly) a line ({spread[1] * 1e3:.2g} mm across, "
                f"{d * 1e3:.1f} mm long; zero-area faces)")
    unit = np.abs(np.linalg.norm(nrm, axis=1) - 1.0) < 1e-3
    if unit.mean() < 0.5:
        return f"{name} has no normals: {int(np.sum(~unit))} of its {len(nrm)} surface samples have none"
    return ""


# --------------------------------------------------------------------------- model preparation


def make_model(
    obj_id: int,
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    normals: np.ndarray | None = None,
    colors: np.ndarray | None = None,
    info: Mapping[str, Any] | None = None,
    symmetries: list[Pose] | None = None,
    path: Path | None = None,
    n_points: int = DEFAULT_N_POINTS,
    cont_step_deg: float = DEFAULT_CONT_STEP_DEG,
    edge_angle_deg: float = DEFAULT_EDGE_ANGLE_DEG,
    max_edge_points: int = DEFAULT_MAX_EDGE_POINTS,
    seed: int = 0,
) -> ObjectModel:
    """Prepare an ObjectModel from a mesh in metres (procedural parts use this directly).

    `info` is a BOP models_info entry in mm: its diameter, extents and symmetries win over the
    values computed from the mesh. `symmetries` (metres), when given, overrides the info ones.
    """
    vertices = np.ascontiguousarray(vertices, dtype=np.float64).reshape(-1, 3)
    faces = np.ascontiguousarray(faces, dtype=np.int32).reshape(-1, 3)
    if len(faces) == 0 or faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(f"model {obj_id}: faces are empty or index outside the {len(vertices)} vertices")
    if not np.all(np.isfinite(vertices)):
        raise ValueError(f"model {obj_id}: vertices are not finite")
    if normals is None or np.asarray(normals).shape != vertices.shape:
        normals = vertex_normals(vertices, faces)
    else:
        normals = normalize(np.asarray(normals, dtype=np.float64))
        if np.any(np.linalg.norm(normals, axis=1) == 0):  # fill zero normals from the faces
            computed = vertex_normals(vertices, faces)
            zero = np.linalg.norm(normals, axis=1) == 0
            normals[zero] = computed[zero]
    hull = convex_hull_points(vertices)
    if info and "diameter" in info:
        diameter = float(info["diameter"]) * MM
    else:  # a huge mesh's hull is of a subset: the walk of max_pairwise_distance goes over every vertex
        diameter = max_pairwise_distance(hull if len(vertices) <= MAX_HULL_INPUT else vertices)
    if info and all(k in info for k in ("min_x", "min_y", "min_z", "size_x", "size_y", "size_z")):
        bbox_min = np.array([info["min_x"], info["min_y"], info["min_z"]], dtype=np.float64) * MM
        bbox_size = np.array([info["size_x"], info["size_y"], info["size_z"]], dtype=np.float64) * MM
    else:
        bbox_min = vertices.min(axis=0)
        bbox_size = vertices.max(axis=0) - bbox_min
    pts, pn = sample_surface(vertices, faces, normals, n_points, seed=seed + int(obj_id))
    edges = sharp_edges(vertices, faces, edge_angle_deg)
    ep, ed = sample_edges(vertices, edges, spacing=diameter / 200.0, max_points=max_edge_points,
                          seed=seed + int(obj_id))
    if symmetries is None:
        symmetries = symmetries_from_info(info, cont_step_deg)
    if colors is not None:
        colors = np.ascontiguousarray(colors, dtype=np.uint8).reshape(-1, 3)
        if len(colors) != len(vertices):
            raise ValueError(f"model {obj_id}: {len(colors)} colours for {len(vertices)} vertices")
    arrays = ([vertices, faces, normals, pts, pn, ep, ed, hull, bbox_min, bbox_size]
              + ([colors] if colors is not None else []))
    for a in arrays:
        a.flags.writeable = False  # shared through the cache
    return ObjectModel(
        obj_id=int(obj_id), vertices=vertices, faces=faces, normals=normals, diameter=diameter,
        points=pts, point_normals=pn, symmetries=list(symmetries), edge_points=ep, edge_dirs=ed,
        hull_points=hull, bbox_min=bbox_min, bbox_size=bbox_size, colors=colors, path=path,
        info=dict(info) if info else None,
    )


def load_model(
    ply_path: str | os.PathLike,
    obj_id: int,
    info: Mapping[str, Any] | None = None,
    *,
    n_points: int = DEFAULT_N_POINTS,
    cont_step_deg: float = DEFAULT_CONT_STEP_DEG,
    scale: float = MM,
) -> ObjectModel:
    """Load a PLY model (file units times `scale` = metres; BOP files are mm) and prepare it.

    Cached by (path, mtime, size, obj_id, info, options): a model is prepared once per process
    and the same instance is returned, until the file changes.
    """
    path = Path(ply_path).resolve()
    try:
        st = path.stat()
    except FileNotFoundError:
        raise FileNotFoundError(f"model file not found: {path}") from None
    info_key = json.dumps(info, sort_keys=True) if info else None
    return _load_model_cached(str(path), st.st_mtime_ns, st.st_size, int(obj_id), info_key,
                              int(n_points), float(cont_step_deg), float(scale))


@lru_cache(maxsize=64)
def _load_model_cached(
    path: str, mtime_ns: int, size: int, obj_id: int, info_key: str | None,
    n_points: int, cont_step_deg: float, scale: float,
) -> ObjectModel:
    vertices, faces, normals, colors = read_ply_mesh(path)
    info = json.loads(info_key) if info_key else None
    try:
        return make_model(
            obj_id, vertices * scale, faces, normals=normals, colors=colors, info=info,
            path=Path(path), n_points=n_points, cont_step_deg=cont_step_deg,
        )
    except ValueError as e:
        raise PlyError(f"{path}: {e}") from None


__all__ = ["ObjectModel", "load_model", "make_model", "model_defect", "DEFAULT_N_POINTS"]
