"""LINE-MOD template matching (Hinterstoisser et al. 2012, OpenCV's cv2.linemod): the appearance-
based, ground-truth-free candidate source of the `linemod` generator (blocks/templates.py).

Templates: the model rendered (core/render.py) with a reference camera (focal `REF_FOCAL`, the object's
centre on the optical axis) from the vertices of an icosphere (`subdivisions`) times `n_inplane`
rotations about the optical axis, at `n_scales` apparent sizes (the diameter spanning `min_px` ..
`max_px` pixels, geometric steps): LINE-MOD has no scale search. The colour image given to the
ColorGradient modality is the rendered normal map (silhouette and crease edges, no texture); the
DepthNormal modality gets the rendered depth. Two detectors are built from the same renderings:
colour only (RGB-only frames) and colour + depth.

A match (template, top-left x, y) gives a pose (`pose_from_match`): the template's rotation turned
by the rotation taking the optical axis to the ray through the matched centre, the centre at the
depth where the model spans the template's pixel size with the frame's focal length, or at a
depth measured in the frame.

The per-model preparation (`linemod_templates`: seconds to a minute) is cached in memory and on
disk (vision/disk_cache.py, as ppf's tables): an .npz named by a hash of the model's geometry,
the parameters and `LINEMOD_FORMAT` holding the template poses and both detectors' classes as
OpenCV writes them (cv2.linemod keeps its extracted features; re-reading them is much faster than
rendering and extracting again). A file that cannot be read or does not match is rebuilt.
"""
from __future__ import annotations

import math
import tempfile
import threading
import weakref
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..core.geometry import Pose
from ..core.models import ObjectModel
from ..core.render import render_box
from .disk_cache import cache_dir, load_npz, model_digest, store_npz

LINEMOD_FORMAT = 1  # bump when the cached content changes: old files are rebuilt
REF_FOCAL = 572.0  # px: the templates' reference camera
CLASS = "obj"
PYRAMID_T = (4, 8)  # LINE-MOD's spreading per pyramid level (OpenCV's default is 5, 8)


@dataclass(frozen=True)
class TemplateParams:
    subdivisions: int = 2  # icosphere subdivisions: 0 -> 12 views, 1 -> 42, 2 -> 162, 3 -> 642
    n_inplane: int = 12  # rotations about the optical axis per view
    n_scales: int = 3
    min_px: float = 60.0  # apparent diameter (px) of the smallest template
    max_px: float = 130.0
    num_features: int = 63  # ColorGradient / DepthNormal features per template
    weak_threshold: float = 10.0
    strong_threshold: float = 55.0

    def key(self) -> str:
        return (f"{self.subdivisions}|{self.n_inplane}|{self.n_scales}|{self.min_px:.4g}|{self.max_px:.4g}|"
                f"{self.num_features}|{self.weak_threshold:.4g}|{self.strong_threshold:.4g}|{PYRAMID_T}")

    def scales(self) -> np.ndarray:
        if self.n_scales <= 1:
            return np.array([math.sqrt(self.min_px * self.max_px)])
        return np.geomspace(self.min_px, self.max_px, self.n_scales)


@dataclass
class Templates:
    """A model's templates: per template its rotation (model to reference camera) and apparent
    diameter (px); per detector ('rgb', 'rgbd') the template index of each LINE-MOD template id
    and the offset (px) from the matched top-left corner to the model centre's projection."""

    rotations: np.ndarray  # (T, 3, 3)
    pixels: np.ndarray  # (T,) apparent diameter (px) at REF_FOCAL
    surface: np.ndarray  # (T,) median depth of the visible surface minus the centre's, in diameters
    index: dict[str, np.ndarray]  # detector -> (n,) template of each id
    anchor: dict[str, np.ndarray]  # detector -> (n, 2) centre - top-left (px)
    detectors: dict[str, "cv2.linemod.Detector"] = field(default_factory=dict)
    centre: np.ndarray = field(default_factory=lambda: np.zeros(3))  # model-frame point on the optical axis


def icosphere(subdivisions: int) -> np.ndarray:
    """Unit vertices of an icosahedron subdivided `subdivisions` times (12, 42, 162, 642, ...)."""
    p = (1.0 + math.sqrt(5.0)) / 2.0
    v = [[-1, p, 0], [1, p, 0], [-1, -p, 0], [1, -p, 0], [0, -1, p], [0, 1, p], [0, -1, -p], [0, 1, -p],
         [p, 0, -1], [p, 0, 1], [-p, 0, -1], [-p, 0, 1]]
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6],
         [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
         [8, 6, 7], [9, 8, 1]]
    verts = [np.array(x, float) / np.linalg.norm(x) for x in v]
    for _ in range(subdivisions):
        mid: dict[tuple[int, int], int] = {}

        def middle(a: int, b: int, mid: dict[tuple[int, int], int] = mid) -> int:
            k = (min(a, b), max(a, b))
            if k not in mid:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                mid[k] = len(verts) - 1
            return mid[k]

        f = [g for a, b, c in f for g in ([a, middle(a, b), middle(c, a)], [b, middle(b, c), middle(a, b)],
                                          [c, middle(c, a), middle(b, c)],
                                          [middle(a, b), middle(b, c), middle(c, a)])]
    return np.array(verts)


def look_at(direction: np.ndarray) -> np.ndarray:
    """Rotation (model to camera) of a camera on the ray `direction` from the model's origin,
    looking at it (camera z = -direction), its x axis horizontal in the model's x-y plane."""
    z = -direction / np.linalg.norm(direction)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def view_rotations(subdivisions: int, n_inplane: int) -> np.ndarray:
    """(V * n_inplane, 3, 3) template rotations: every icosphere view, turned about the optical axis."""
    views = [look_at(v) for v in icosphere(subdivisions)]
    return np.array([rot_z(2.0 * math.pi * k / n_inplane) @ R for R in views for k in range(n_inplane)])


def new_detector(params: TemplateParams, depth: bool) -> "cv2.linemod.Detector":
    modalities = [cv2.linemod.ColorGradient_create(params.weak_threshold, params.num_features,
                                                   params.strong_threshold)]
    if depth:  # 2 m range, 50 mm normal difference (OpenCV's defaults), 2 px extraction distance
        modalities.append(cv2.linemod.DepthNormal_create(2000, 50, params.num_features, 2))
    return cv2.linemod.Detector(modalities, list(PYRAMID_T))


def view_images(model: ObjectModel, R: np.ndarray, pixels: float, centre: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, float]:
    """The model at rotation R with `centre` on the optical axis, spanning `pixels` px, on a
    square canvas centred on the axis: (normals (s, s, 3) float32, 0 outside; depth (s, s) m,
    NaN outside; the centre's depth)."""
    z = REF_FOCAL * model.diameter / pixels
    size = int(math.ceil(pixels * 1.2)) + 16
    c = size / 2.0
    K = np.array([[REF_FOCAL, 0.0, c], [0.0, REF_FOCAL, c], [0.0, 0.0, 1.0]])
    r = render_box(model, Pose(R, np.array([0.0, 0.0, z]) - R @ centre), K, size, size).to_full()
    return r.normals, r.depth, z


def warped_template(normals: np.ndarray, depth: np.ndarray, z: float, angle: float, scale: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """A view's rendering turned by `angle` about the optical axis (as rot_z(angle) turns the
    camera-frame object) and shrunk by `scale` (the object `1 / scale` times further): (colour
    image (normal map, BGR uint8), depth (uint16 mm), mask (uint8 255), centre pixel)."""
    src_c = normals.shape[0] / 2.0
    size = int(math.ceil(normals.shape[0] * scale))
    c = size / 2.0
    co, si = math.cos(angle), math.sin(angle)
    # inverse map: source = rot(-angle) (dest - c) / scale + src_c
    M = np.array([[co, si, 0.0], [-si, co, 0.0]]) / scale
    M[:, 2] = src_c - M[:, :2] @ np.array([c, c])
    flags = cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
    n = cv2.warpAffine(normals, M, (size, size), flags=flags, borderValue=0)
    d = cv2.warpAffine(np.nan_to_num(depth, nan=0.0), M, (size, size), flags=flags, borderValue=0)
    m = d > 0
    n2 = n.copy()
    n2[..., 0], n2[..., 1] = co * n[..., 0] - si * n[..., 1], si * n[..., 0] + co * n[..., 1]
    colour = np.zeros((size, size, 3), np.uint8)
    colour[m] = np.clip((n2[m] * 0.5 + 0.5) * 255.0, 0, 255).astype(np.uint8)
    dmm = np.zeros((size, size), np.uint16)
    dmm[m] = np.clip((d[m] + z * (1.0 / scale - 1.0)) * 1000.0, 1, 65535).astype(np.uint16)
    return colour, dmm, (m * 255).astype(np.uint8), c


def prepare_templates(model: ObjectModel, params: TemplateParams) -> tuple[Templates, dict[str, bytes]]:
    """Render every view once (largest size), turn and shrink it into the templates and add them
    to both detectors; returns them and each detector's classes as OpenCV writes them (for the
    disk cache)."""
    if len(model.faces) == 0 or not math.isfinite(model.diameter) or model.diameter <= 1e-4:
        raise ValueError(f"model {model.obj_id}: no surface to render (degenerate model)")
    centre = 0.5 * (model.points.min(axis=0) + model.points.max(axis=0))
    scales = params.scales()
    angles = 2.0 * math.pi * np.arange(params.n_inplane) / params.n_inplane
    dets = {"rgb": new_detector(params, False), "rgbd": new_detector(params, True)}
    rotations, pixels, surface = [], [], []
    index: dict[str, list[int]] = {k: [] for k in dets}
    anchor: dict[str, list[tuple[float, float]]] = {k: [] for k in dets}
    for direction in icosphere(params.subdivisions):
        R0 = look_at(direction)
        normals, depth, z = view_images(model, R0, float(scales[-1]), centre)
        if not np.isfinite(depth).any():
            continue
        offset = (float(np.nanmedian(depth)) - z) / model.diameter
        for px in scales:
            for a in angles:
                colour, dmm, mask, c = warped_template(normals, depth, z, float(a), float(px / scales[-1]))
                if not mask.any():
                    continue
                i = len(rotations)
                rotations.append(rot_z(float(a)) @ R0)
                pixels.append(float(px))
                surface.append(offset)
                for name, det in dets.items():
                    tid, bb = det.addTemplate([colour] if name == "rgb" else [colour, dmm], CLASS, mask)
                    if tid >= 0:
                        index[name].append(i)
                        anchor[name].append((c - bb[0], c - bb[1]))
    if not index["rgb"]:
        raise ValueError(f"model {model.obj_id}: no template has enough gradient features (degenerate model)")
    t = Templates(np.array(rotations).reshape(-1, 3, 3), np.array(pixels), np.array(surface),
                  {k: np.array(v, np.int32) for k, v in index.items()},
                  {k: np.array(v, np.float64).reshape(-1, 2) for k, v in anchor.items()}, dets, centre)
    return t, {k: _class_bytes(d) for k, d in dets.items()}


def _class_bytes(det: "cv2.linemod.Detector") -> bytes:
    with tempfile.TemporaryDirectory(prefix="linemod_") as tmp:
        det.writeClasses(str(Path(tmp) / "%s.yml.gz"))
        return (Path(tmp) / f"{CLASS}.yml.gz").read_bytes()


def _detector_from_bytes(params: TemplateParams, depth: bool, data: bytes) -> "cv2.linemod.Detector":
    det = new_detector(params, depth)
    with tempfile.TemporaryDirectory(prefix="linemod_") as tmp:
        (Path(tmp) / f"{CLASS}.yml.gz").write_bytes(data)
        det.readClasses([CLASS], str(Path(tmp) / "%s.yml.gz"))
    return det


def templates_hash(model: ObjectModel, params: TemplateParams) -> str:
    return model_digest(model, f"{model.diameter:.9g}|{params.key()}|{REF_FOCAL}|{LINEMOD_FORMAT}")


_MEMORY: "weakref.WeakKeyDictionary[ObjectModel, dict[str, Templates]]" = weakref.WeakKeyDictionary()
_LOCK = threading.Lock()


def _read_cached(path: Path, digest: str, params: TemplateParams) -> Templates | None:
    """The templates stored at `path`, or None when missing, unreadable or not the ones asked for."""
    z = load_npz(path, digest)
    if z is None:
        return None
    try:
        rotations, pixels, surface, centre = z["rotations"], z["pixels"], z["surface"], z["centre"]
        index = {k: z[f"index_{k}"].astype(np.int64) for k in ("rgb", "rgbd")}
        anchor = {k: z[f"anchor_{k}"] for k in ("rgb", "rgbd")}
        n = len(rotations)
        ok = (rotations.shape == (n, 3, 3) and pixels.shape == surface.shape == (n,) and centre.shape == (3,) and n > 0
              and all(anchor[k].shape == (len(index[k]), 2) and (len(index[k]) == 0 or 0 <= index[k].min()
                      and index[k].max() < n) for k in index) and len(index["rgb"]) > 0)
        if not ok:
            return None
        dets = {k: _detector_from_bytes(params, k == "rgbd", z[f"classes_{k}"].tobytes()) for k in index}
        if any(dets[k].numTemplates() != len(index[k]) for k in index):
            return None
    except (KeyError, ValueError, cv2.error):
        return None  # corrupt or from another format: rebuilt by the caller
    return Templates(rotations, pixels, surface, index, anchor, dets, centre)


def linemod_templates(model: ObjectModel, params: TemplateParams = TemplateParams(),
                      folder: Path | None = None) -> tuple[Templates, str]:
    """The model's templates and detectors: from memory, else the disk cache, else built and
    stored. Returns (templates, where they came from: 'memory' | 'disk' | 'built')."""
    key = params.key()
    with _LOCK:
        hit = _MEMORY.get(model, {}).get(key)
    if hit is not None:
        return hit, "memory"
    digest = templates_hash(model, params)
    path = (folder or cache_dir()) / "linemod" / f"linemod-{digest}.npz"
    t, source = _read_cached(path, digest, params), "disk"
    if t is None:
        (t, classes), source = prepare_templates(model, params), "built"
        store_npz(path, digest, {
            "rotations": t.rotations, "pixels": t.pixels, "surface": t.surface, "centre": t.centre,
            **{f"index_{k}": v for k, v in t.index.items()}, **{f"anchor_{k}": v for k, v in t.anchor.items()},
            **{f"classes_{k}": np.frombuffer(b, np.uint8) for k, b in classes.items()}})
    with _LOCK:
        _MEMORY.setdefault(model, {})[key] = t
    return t, source


@dataclass(frozen=True)
class TemplateMatch:
    similarity: float  # 0..100
    template: int  # index into Templates.rotations
    u: float  # px: the model centre's projection in the frame
    v: float


def match(t: Templates, rgb: np.ndarray, depth_mm: np.ndarray | None, threshold: float,
          max_matches: int, mask: np.ndarray | None = None) -> list[TemplateMatch]:
    """The best `max_matches` template matches above `threshold` (0..100) in an RGB image (with
    the depth image in mm for the colour + depth detector), best first; `mask` (uint8, 255 =
    used): the pixels whose features count."""
    name = "rgb" if depth_mm is None else "rgbd"
    if len(t.index[name]) == 0:
        name = "rgb"
        depth_mm = None
    bgr = np.ascontiguousarray(rgb[..., ::-1])
    sources = [bgr] if depth_mm is None else [bgr, depth_mm]
    if mask is None:
        found, _ = t.detectors[name].match(sources, float(threshold))
    else:
        found, _ = t.detectors[name].match(sources, float(threshold), masks=[mask] * len(sources))
    out = []
    for m in found[:max_matches]:
        i = int(m.template_id)
        ax, ay = t.anchor[name][i]
        out.append(TemplateMatch(float(m.similarity), int(t.index[name][i]), m.x + ax, m.y + ay))
    return out


def distinct_matches(found: list[TemplateMatch], cell_px: float, per_cell: int) -> list[TemplateMatch]:
    """`found` (best first) without repeats of a template within `cell_px` and with at most
    `per_cell` matches per `cell_px` grid cell: the best matches of every place in the image
    instead of hundreds of near-copies at the most textured one."""
    out, seen, count = [], set(), {}
    for m in found:
        cell = (int(m.u // cell_px), int(m.v // cell_px))
        if (m.template, cell) in seen or count.get(cell, 0) >= per_cell:
            continue
        seen.add((m.template, cell))
        count[cell] = count.get(cell, 0) + 1
        out.append(m)
    return out


def depth_agreement(points: np.ndarray, normals: np.ndarray, R: np.ndarray, t: np.ndarray, depth: np.ndarray,
                    K: np.ndarray, tol: float) -> np.ndarray:
    """A cheap render-free depth check of many poses (R (n, 3, 3), t (n, 3)) at once: over the
    camera-facing model samples that project into the image, (inliers - free-space violations) /
    samples, against the observed depth (NaN or 0: no measurement, neutral). In [-1, 1]."""
    cam = np.einsum("nij,pj->npi", R, points) + t[:, None, :]
    facing = np.einsum("nij,pj->npi", R, normals)
    front = np.einsum("npi,npi->np", facing, cam) < 0
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.round(cam[..., 0] / cam[..., 2] * K[0, 0] + K[0, 2])
        v = np.round(cam[..., 1] / cam[..., 2] * K[1, 1] + K[1, 2])
    h, w = depth.shape
    inside = front & (cam[..., 2] > 0) & (u >= 0) & (v >= 0) & (u < w) & (v < h)
    ui, vi = np.where(inside, u, 0).astype(np.intp), np.where(inside, v, 0).astype(np.intp)
    obs = depth[vi, ui]
    with np.errstate(invalid="ignore"):
        diff = obs - cam[..., 2]
        inl = inside & (np.abs(diff) < tol)
        viol = inside & (diff > tol)
    n = np.maximum(front.sum(axis=1), 1)
    return (inl.sum(axis=1) - viol.sum(axis=1)) / n


def ray_rotations(K: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotations taking the optical axis onto the rays through pixels uv (n, 2)."""
    d = np.linalg.solve(K, np.c_[uv, np.ones(len(uv))].T).T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    axis = np.stack([-d[:, 1], d[:, 0], np.zeros(len(d))], axis=1)  # z x d
    s = np.linalg.norm(axis, axis=1)
    k = axis / np.maximum(s, 1e-12)[:, None]
    ang = np.arctan2(s, d[:, 2])[:, None, None]
    Kx = np.zeros((len(d), 3, 3))
    Kx[:, 0, 1], Kx[:, 0, 2], Kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    Kx[:, 1, 0], Kx[:, 2, 0], Kx[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    return np.eye(3) + np.sin(ang) * Kx + (1.0 - np.cos(ang)) * (Kx @ Kx)


def poses_from_matches(t: Templates, matches: list[TemplateMatch], K: np.ndarray, diameter: float,
                       z: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The poses (R (n, 3, 3), t (n, 3)) the matches stand for: each template's rotation seen
    along the ray through its matched centre, the centre at depth `z` (n,) where given (finite),
    else at the template's range (its pixel size with the frame's focal length) along the ray."""
    K = np.asarray(K, np.float64)
    uv = np.array([[m.u, m.v] for m in matches], np.float64).reshape(-1, 2)
    idx = np.array([m.template for m in matches], np.intp)
    R = ray_rotations(K, uv) @ t.rotations[idx]
    ray = np.linalg.solve(K, np.c_[uv, np.ones(len(uv))].T).T
    rng = math.sqrt(K[0, 0] * K[1, 1]) * diameter / t.pixels[idx]
    c = ray / np.linalg.norm(ray, axis=1, keepdims=True) * rng[:, None]
    if z is not None:
        given = np.isfinite(z)
        c[given] = ray[given] * (z[given] / ray[given, 2])[:, None]
    return R, c - R @ t.centre


def pose_from_match(t: Templates, m: TemplateMatch, K: np.ndarray, diameter: float,
                    z: float | None = None) -> Pose:
    """The pose one match stands for (see poses_from_matches)."""
    R, tr = poses_from_matches(t, [m], K, diameter, None if z is None else np.array([z], float))
    return Pose(R[0], tr[0])


__all__ = ["TemplateParams", "Templates", "TemplateMatch", "linemod_templates", "prepare_templates", "match",
           "distinct_matches", "depth_agreement",
           "pose_from_match", "poses_from_matches", "icosphere", "view_rotations", "LINEMOD_FORMAT"]
