"""Object models: mesh, surface samples, diameter, symmetries and edge points, prepared once.

Everything every block needs about an object is computed here once per model file and cached,
so refinement and scoring never touch a mesh file in their hot loop. Units are metres inside
the code; BOP PLY files are millimetres and are converted when read.

PLY files are read and written with trimesh (ascii and binary, any property order, optional
normals and colours); its failures become PlyError naming the file. trimesh is imported only
when a file is read or written.

Surface sampling stays our own: with trimesh's sampler (trimesh.sample.sample_surface, area
weighted, barycentric normals) feeding the surface distance field, global registration found the
procedural bracket in 11-12 of 16 sample sets instead of 16 of 16 (measured 2026-12-02 over
three field seeds). Sharp edges stay our own too: they include boundary and non-manifold edges
(outlines for the edge refiners), which trimesh's face-adjacency angles do not cover.
"""
from __future__ import annotations

import io
import json
import math
import os
import warnings
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..util.atomic_file import atomic_write
from ..util.safe_json import JsonLimitError, read_limited
from .geometry import Pose

MM = 1e-3  # metres per millimetre: BOP files are in mm

DEFAULT_N_POINTS = 3000  # surface samples per model: enough for ICP and scores, cheap to transform
DEFAULT_CONT_STEP_DEG = 10.0  # sampling step of continuous symmetries
DEFAULT_EDGE_ANGLE_DEG = 30.0  # dihedral angle above which a mesh edge counts as sharp
DEFAULT_MAX_EDGE_POINTS = 2000
# Beyond these counts a scanned or finely subdivided mesh (millions of faces) is summarised, so it is
# prepared in seconds: qhull took 20 s on the 1M vertices of a fine sphere, all on its hull, and the
# diameter is quadratic in the hull's size (43 s for 90k points). Every LM-O model is far below both.
MAX_HULL_INPUT = 100_000  # vertices beyond which the convex hull is that of a subset ...
HULL_SUBSET = 20_000  # ... of about this many (qhull: ~1 s for 100k vertices all on the hull)
MAX_DIAMETER_POINTS = 10_000  # points the diameter is computed over exactly
COLLINEAR = 1e-4  # samples spread less than this share of the diameter across their line: degenerate


MAX_PLY_BYTES = 1024**3  # a model file larger than this (1 GiB) is refused before reading


class PlyError(ValueError):
    """A PLY file that cannot be read as a triangle mesh; the message names the file."""


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


# --------------------------------------------------------------------------- PLY reading and writing


def _load_ply_kwargs(path: Path) -> dict[str, Any]:
    """trimesh's PLY loader on the file's bytes (size-limited read first), with its failures turned
    into PlyError naming the file; checks that every element has the record count its header says."""
    try:  # a regular file (not a directory, FIFO or device) of at most MAX_PLY_BYTES
        data = read_limited(path, MAX_PLY_BYTES, "PLY file")
    except FileNotFoundError:
        raise FileNotFoundError(f"PLY file not found: {path}") from None
    except JsonLimitError as exc:
        raise PlyError(str(exc)) from None
    if not data.startswith(b"ply") or b"end_header" not in data:
        raise PlyError(f"{path}: not a PLY file (no 'ply' magic or no 'end_header')")
    fmt = next((ln.split()[1:2] for ln in data[:data.find(b"end_header")].split(b"\n") if ln.startswith(b"format")), [])
    if not fmt or fmt[0] not in (b"ascii", b"binary_little_endian", b"binary_big_endian"):
        # trimesh would read any other format as binary and report a size mismatch
        raise PlyError(f"{path}: unknown PLY format {fmt[0].decode(errors='replace') if fmt else '(none)'!r}")
    from trimesh.exchange.ply import load_ply  # lazy: trimesh is only needed when a file is read

    try:
        with warnings.catch_warnings():  # numpy warns on partial ascii rows; the count check reports them
            warnings.simplefilter("ignore")
            kwargs = load_ply(io.BytesIO(data), fix_texture=False, skip_materials=True)
    except Exception as exc:  # trimesh raises ValueError, KeyError, IndexError, ... on malformed files
        text = str(exc)
        if "unexpected length" in text:
            raise PlyError(f"{path}: truncated (or with extra bytes): the binary body's size is not what the "
                           "header describes") from None
        if isinstance(exc, KeyError):
            raise PlyError(f"{path}: bad PLY header: unknown type or element {text}") from None
        raise PlyError(f"{path}: malformed PLY ({type(exc).__name__}: {text})") from None
    for name, el in kwargs["metadata"]["_ply_raw"].items():
        got = _record_count(el.get("data"))
        if el.get("length", 0) and got != el["length"]:
            raise PlyError(f"{path}: truncated: element '{name}' has {got} of {el['length']} records")
    return kwargs


def _record_count(data: Any) -> int:
    if data is None:
        return 0
    if isinstance(data, dict):
        return min((len(v) for v in data.values()), default=0)
    return len(data)


def _element_columns(data: Any) -> dict[str, np.ndarray]:
    """{property: array} of one element of trimesh's raw PLY structure (list properties: the lists)."""
    if isinstance(data, dict):  # ascii: scalar properties come as (n, 1) columns
        return {k: v[:, 0] if isinstance(v, np.ndarray) and v.ndim == 2 and v.shape[1] == 1 else v
                for k, v in data.items()}
    out = {}
    for name in data.dtype.names or ():
        col = data[name]
        out[name] = col["f1"] if col.dtype.names and "f1" in col.dtype.names else col
    return out


def read_ply(path: str | os.PathLike) -> dict[str, dict[str, np.ndarray]]:
    """Read a PLY file (trimesh) into {element: {property: array}}; a list property is a 2D array
    (one row per record) or a list of arrays when the lengths differ.

    Raises PlyError naming the file for anything malformed (bad header, truncated body, bad token).
    """
    path = Path(path)
    raw = _load_ply_kwargs(path)["metadata"]["_ply_raw"]
    return {name: _element_columns(el.get("data")) if el.get("data") is not None else {} for name, el in raw.items()}


def read_ply_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Triangle mesh of a PLY file (trimesh) in file units: vertices (N,3) float64, faces (M,3) int32,
    vertex normals (N,3) or None, vertex colours (N,3) uint8 or None. Quads are split in two.
    """
    path = Path(path)
    kwargs = _load_ply_kwargs(path)
    raw = kwargs["metadata"]["_ply_raw"]
    vertex = raw.get("vertex")
    if vertex is None or not all(k in vertex["properties"] for k in "xyz"):
        raise PlyError(f"{path}: no 'vertex' element with x, y, z")
    vertices = np.asarray(kwargs.get("vertices", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
    if len(vertices) == 0 or not np.all(np.isfinite(vertices)):
        raise PlyError(f"{path}: vertices are empty or not finite")
    normals = kwargs.get("vertex_normals")
    normals = None if normals is None else np.asarray(normals, dtype=np.float64)
    colors = None
    columns = _element_columns(vertex["data"])
    for names in (("red", "green", "blue"), ("diffuse_red", "diffuse_green", "diffuse_blue")):
        if all(k in columns for k in names):
            c = np.stack([np.asarray(columns[k]) for k in names], axis=1)
            if c.dtype.kind == "f":  # float colours in [0, 1]
                c = np.clip(c * 255.0 + 0.5, 0, 255)
            colors = c.astype(np.uint8)
            break
    face = raw.get("face")
    if face is None or not any(k in face["properties"] for k in ("vertex_indices", "vertex_index")):
        raise PlyError(f"{path}: no 'face' element with vertex_indices (a model needs triangles)")
    faces = kwargs.get("faces")
    if faces is None or len(faces) == 0:
        raise PlyError(f"{path}: mesh has no faces")
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise PlyError(f"{path}: face index out of range [0, {len(vertices)})")
    return vertices, faces.astype(np.int32), normals, colors


def write_ply(
    path: str | os.PathLike,
    vertices: np.ndarray,
    faces: np.ndarray,
    normals: np.ndarray | None = None,
    colors: np.ndarray | None = None,
    binary: bool = True,
) -> None:
    """Write a triangle mesh as PLY (trimesh's exporter) in the caller's units (BOP model files are
    mm), with optional vertex normals and uint8 colours (written as red, green, blue, alpha=255);
    atomic (util/atomic_file.py)."""
    import trimesh
    from trimesh.exchange.ply import export_ply

    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    mesh = trimesh.Trimesh(
        vertices=v, faces=f, process=False, validate=False,
        vertex_normals=None if normals is None else np.asarray(normals, dtype=np.float64).reshape(-1, 3),
        vertex_colors=None if colors is None else np.asarray(colors, dtype=np.uint8).reshape(-1, 3),
    )
    data = export_ply(mesh, encoding="binary" if binary else "ascii", vertex_normal=normals is not None,
                      include_attributes=False)
    atomic_write(Path(path), data)


# --------------------------------------------------------------------------- mesh helpers


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit face normals (M,3) (zero for degenerate faces) and face areas (M,)."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    n = np.cross(b - a, c - a)
    norm = np.linalg.norm(n, axis=1)
    area = 0.5 * norm
    with np.errstate(invalid="ignore", divide="ignore"):
        n = np.where(norm[:, None] > 0, n / norm[:, None], 0.0)
    return n, area


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals, for meshes whose file carries none. Summed by bincount in
    the order np.add.at would (corner 0 of every face, then 1, then 2): the same bits, without
    add.at's slow loop (a second for 2M faces)."""
    fn, area = face_normals(vertices, faces)
    weighted = np.tile(fn * area[:, None], (3, 1))
    index = faces.T.ravel()
    acc = np.stack([np.bincount(index, weighted[:, k], len(vertices)) for k in range(3)], axis=1)
    return _normalize(acc)


def _normalize(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, v / n, 0.0)


def sample_surface(
    vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, n: int, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """n points uniform over the surface area, with barycentrically interpolated vertex normals
    (smoother than face normals on scanned meshes). Deterministic for a given seed."""
    rng = np.random.default_rng(seed)
    fn, area = face_normals(vertices, faces)
    if area.sum() <= 0:
        raise ValueError("mesh has zero surface area")
    fi = rng.choice(len(faces), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    w = np.stack([1.0 - s, s * (1.0 - r2), s * r2], axis=1)  # uniform barycentric weights
    tri = faces[fi]
    pts = np.einsum("nk,nkd->nd", w, vertices[tri])
    nrm = _normalize(np.einsum("nk,nkd->nd", w, normals[tri]))
    bad = np.linalg.norm(nrm, axis=1) < 0.5  # opposing vertex normals: use the face normal
    nrm[bad] = fn[fi[bad]]
    return pts, nrm


def convex_hull_points(vertices: np.ndarray, max_input: int = MAX_HULL_INPUT) -> np.ndarray:
    """Vertices of the convex hull (falls back to all vertices for flat/degenerate meshes). Beyond
    `max_input` vertices, the hull of a subset: the vertices extreme along 128 directions and
    about HULL_SUBSET more spread evenly over the mesh. It lies inside the true hull by a fraction
    of their spacing (at most 0.07 mm on the 2M-face part of test_generator_bad_input; projected
    boxes keep a pixel of margin)."""
    from scipy.spatial import ConvexHull, QhullError

    subset = vertices
    if len(vertices) > max_input:
        dirs = _fibonacci_directions(128).astype(np.float32)
        top, arg = np.full(len(dirs), -np.inf), np.zeros(len(dirs), np.int64)
        for i in range(0, len(vertices), 50_000):  # in blocks: (50k, 128) projections at a time
            proj = vertices[i:i + 50_000].astype(np.float32) @ dirs.T
            k = np.argmax(proj, axis=0)
            better = proj[k, np.arange(len(dirs))] > top
            top[better], arg[better] = proj[k[better], np.flatnonzero(better)], i + k[better]
        subset = vertices[np.union1d(arg, _spread_subset(vertices, HULL_SUBSET))]
    try:
        return subset[ConvexHull(subset).vertices]
    except (QhullError, ValueError):
        return subset


def _spread_subset(points: np.ndarray, n: int) -> np.ndarray:
    """Indices of about `n` (at most 2 n) points spread evenly over the space they take: the
    first point in each cell of a grid, the cell sized from the count of occupied cells at a
    first size (a surface's count grows as 1 / cell^2)."""
    lo = points.min(axis=0)
    size = float(np.linalg.norm(points.max(axis=0) - lo)) / 100.0 or 1.0
    for _ in range(3):
        cell = np.floor((points - lo) / size).astype(np.int64)  # < 2^21 per axis: 100 cells or fewer
        _, first = np.unique((cell[:, 0] << 42) | (cell[:, 1] << 21) | cell[:, 2], return_index=True)
        if len(first) <= 2 * n:
            break
        size *= math.sqrt(len(first) / n)
    return first if len(first) <= 2 * n else first[:: -(-len(first) // n)]


def _fibonacci_directions(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = k * math.pi * (3.0 - math.sqrt(5.0))
    r = np.sqrt(1.0 - z**2)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def max_pairwise_distance(points: np.ndarray, max_points: int = MAX_DIAMETER_POINTS) -> float:
    """Largest distance between two points, in blocks to bound memory. Beyond `max_points` (the
    hull of a finely tessellated round part), the largest over an even subset, then grown by
    walking from an end of the best pair to the farthest point of the whole set, and from there
    on, until it no longer grows: short of the exact value by a sliver of the subset's spacing."""
    from scipy.spatial.distance import cdist

    pts = points if len(points) <= max_points else points[:: -(-len(points) // max_points)]
    best, end = 0.0, 0
    for i in range(0, len(pts), 2048):
        d = cdist(pts[i:i + 2048], pts, "sqeuclidean")
        k = int(np.argmax(d))
        if d.flat[k] > best:
            best, end = float(d.flat[k]), i + k // len(pts)
    if pts is not points:
        a = pts[end]
        while True:
            d = np.sum((points - a) ** 2, axis=1)
            k = int(np.argmax(d))
            if d[k] <= best:
                break
            best, a = float(d[k]), points[k]
    return math.sqrt(best)


def sharp_edges(
    vertices: np.ndarray, faces: np.ndarray, angle_deg: float = DEFAULT_EDGE_ANGLE_DEG
) -> np.ndarray:
    """(K, 2) vertex index pairs of mesh edges whose dihedral angle exceeds angle_deg.

    Boundary edges of open meshes (one adjacent face) count as sharp: they are outlines.
    Edges with more than two faces are sharp when any adjacent pair exceeds the angle.
    """
    fn, _ = face_normals(vertices, faces)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).astype(np.int64)
    e.sort(axis=1)
    face_of = np.tile(np.arange(len(faces)), 3)
    key = e[:, 0] * len(vertices) + e[:, 1]
    order = np.argsort(key, kind="stable")
    key, e, face_of = key[order], e[order], face_of[order]
    first = np.r_[True, key[1:] != key[:-1]]
    starts = np.flatnonzero(first)
    counts = np.diff(np.r_[starts, len(key)])
    cos_thr = math.cos(math.radians(angle_deg))
    # Compare each half-edge's face with the first face of its group (covers 2-face edges exactly).
    group = np.cumsum(first) - 1
    cosang = np.einsum("ij,ij->i", fn[face_of], fn[face_of[starts[group]]])
    sharp_member = (cosang < cos_thr) & ~first
    sharp_group = np.zeros(len(starts), dtype=bool)
    sharp_group[group[sharp_member]] = True
    sharp_group |= counts == 1
    return e[starts[sharp_group]]


def sample_edges(
    vertices: np.ndarray, edges: np.ndarray, spacing: float, max_points: int, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Points evenly spaced (about `spacing`) along edges, with unit edge directions; at most
    max_points (a seeded subset when more)."""
    if len(edges) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    a, b = vertices[edges[:, 0]], vertices[edges[:, 1]]
    d = b - a
    length = np.linalg.norm(d, axis=1)
    keep = length > 0
    a, d, length = a[keep], d[keep], length[keep]
    total = float(length.sum())
    if total <= 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    spacing = max(spacing, total / (4 * max_points))  # do not build a huge array first
    k = np.maximum(1, np.round(length / spacing).astype(np.int64))
    ei = np.repeat(np.arange(len(length)), k)
    # position (i + 0.5) / k along each edge
    offs = np.arange(len(ei)) - np.repeat(np.cumsum(k) - k, k)
    s = (offs + 0.5) / k[ei]
    pts = a[ei] + s[:, None] * d[ei]
    dirs = d[ei] / length[ei, None]
    if len(pts) > max_points:
        sel = np.sort(np.random.default_rng(seed).choice(len(pts), max_points, replace=False))
        pts, dirs = pts[sel], dirs[sel]
    return pts, dirs


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


# --------------------------------------------------------------------------- symmetries


def axis_angle_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation by `angle` (rad) about the unit vector `axis`."""
    from .geometry import exp_so3

    axis = np.asarray(axis, dtype=np.float64)
    return exp_so3(axis / np.linalg.norm(axis) * angle)


def symmetries_from_info(info: Mapping[str, Any] | None, cont_step_deg: float = DEFAULT_CONT_STEP_DEG) -> list[Pose]:
    """Symmetry transformations (model frame, metres) of a BOP models_info entry (mm).

    As bop_toolkit's get_symmetry_transformations: the discrete ones (identity first) each
    combined with every sample of the continuous ones, which are sampled every cont_step_deg.
    """
    disc = [Pose.identity()]
    cont: list[Pose] = []
    if info:
        for sym in info.get("symmetries_discrete", []) or []:
            T = np.asarray(sym, dtype=np.float64).reshape(4, 4)
            disc.append(Pose(T[:3, :3], T[:3, 3] * MM))
        steps = max(1, int(round(360.0 / cont_step_deg)))
        for sym in info.get("symmetries_continuous", []) or []:
            axis = np.asarray(sym["axis"], dtype=np.float64)
            offset = np.asarray(sym["offset"], dtype=np.float64) * MM
            for i in range(steps):  # i = 0 is the identity, kept so discrete ones survive alone
                R = axis_angle_matrix(axis, 2.0 * np.pi * i / steps)
                cont.append(Pose(R, offset - R @ offset))
    if not cont:
        return disc
    return [c.compose(d) for d in disc for c in cont]


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
        normals = _normalize(np.asarray(normals, dtype=np.float64))
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


def clear_model_cache() -> None:
    """Forget prepared models (e.g. in long-running processes after replacing datasets)."""
    _load_model_cached.cache_clear()


__all__ = [
    "ObjectModel", "PlyError", "read_ply", "read_ply_mesh", "write_ply", "load_model", "make_model",
    "symmetries_from_info", "sample_surface", "sharp_edges", "sample_edges", "vertex_normals",
    "face_normals", "convex_hull_points", "max_pairwise_distance", "clear_model_cache", "model_defect", "MM",
]
