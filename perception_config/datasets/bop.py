"""Read and write datasets in the BOP layout, converting millimetres to metres at the boundary.

Layout (bop_toolkit docs/bop_datasets_format.md):

    root/models[_eval|_cad]/models_info.json, obj_XXXXXX.ply      (mm)
    root/<split>/<scene 6 digits>/scene_camera.json                cam_K, depth_scale, [cam_R_w2c, cam_t_w2c mm]
                                 /scene_gt.json                    cam_R_m2c (row-major), cam_t_m2c (mm), obj_id
                                 /scene_gt_info.json               bbox_obj, bbox_visib, px_count_*, visib_fract
                                 /rgb/<im 6 digits>.png|jpg, depth/<im>.png (uint16 * depth_scale = mm)

Inside the code everything is metres (poses, depth, model vertices, diameters); `models_info`
stays in mm as BOP defines it (core/models.py converts it when preparing a model). Bad input raises
`BopFormatError` (a ValueError) or FileNotFoundError with the offending file in the message:
a reader never returns silently wrong data, so a wrong depth_scale fails loudly rather than
putting every object ten times too far away.

Writers are atomic (util/atomic_file.py), so a reader never sees half a JSON file.
A generator writing many frames uses `SceneWriter`, which writes each image at once and the
scene's JSON files once at close; `write_frame` is the one-off convenience.
"""
from __future__ import annotations

import csv
import io
import json
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Iterator, Literal, Mapping, Sequence

import cv2
import numpy as np

from ..core.geometry import MM, Pose, nearest_rotation
from ..core.models import ObjectModel, load_model
from ..core.scene import Frame, SceneObject
from ..util.atomic_file import atomic_write
from ..util.safe_json import JsonLimitError, read_json_file, read_limited
from .errors import BopAnnotationWarning, BopFormatError
from .image_header import MAX_IMAGE_BYTES, check_image_header

DEFAULT_FRAME_RATE = 10.0  # Hz: stamps of BOP frames without timing are im_id / rate
MIN_MEDIAN_DEPTH = 0.01  # metres: a scene whose median depth is outside these bounds
MAX_MEDIAN_DEPTH = 20.0  # after scaling has the wrong depth_scale
RGB_EXTS = (".png", ".jpg", ".jpeg", ".tif")
RESULTS_HEADER = ["scene_id", "im_id", "obj_id", "score", "R", "t", "time"]
_EXTENT_KEYS = ("min_x", "min_y", "min_z", "size_x", "size_y", "size_z")
MAX_JSON_BYTES = 256 * 1024 * 1024  # a BOP JSON file larger than this is refused before reading
MAX_JSON_DEPTH = 32  # BOP JSON files nest 4 levels; deeper is refused before parsing
# Real annotations are stored with a few digits: LM-O's cam_R_m2c reach |det - 1| = 0.014.
# Up to ROTATION_TOLERANCE they are projected onto SO(3) (one warning per file beyond
# ROTATION_SILENT, the rounding of 6-digit files); beyond it the matrix is refused.
ROTATION_TOLERANCE = 0.05
ROTATION_SILENT = 1e-3
_GT_INFO_KEYS = ("bbox_obj", "bbox_visib", "px_count_all", "px_count_valid", "px_count_visib", "visib_fract")


# --------------------------------------------------------------------------- small I/O helpers


def load_json(path: str | os.PathLike) -> Any:
    """JSON content of a BOP file; FileNotFoundError / BopFormatError naming the file.

    Read through perception_config.util.safe_json: a regular file (not a directory or a special
    file) of at most MAX_JSON_BYTES, nested at most MAX_JSON_DEPTH levels, checked before parsing."""
    try:
        return read_json_file(path, MAX_JSON_BYTES, MAX_JSON_DEPTH, what="BOP file")
    except FileNotFoundError:
        raise FileNotFoundError(f"BOP file not found: {path}") from None
    except JsonLimitError as e:
        raise BopFormatError(str(e)) from None


def save_json(path: str | os.PathLike, content: Mapping[Any, Any]) -> None:
    """Write a dict the way bop_toolkit does (one top-level entry per line, keys in numeric
    order when they are ids), atomically."""
    def order(k: Any) -> tuple[int, Any]:
        s = str(k)
        return (0, int(s)) if s.lstrip("-").isdigit() else (1, s)

    items = sorted(content.items(), key=lambda kv: order(kv[0]))
    lines = [f"  {json.dumps(str(k))}: {json.dumps(_jsonable(v), sort_keys=True)}" for k, v in items]
    text = "{\n" + ",\n".join(lines) + ("\n" if lines else "") + "}\n"
    atomic_write(Path(path), text.encode("utf-8"))


def _jsonable(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist())
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.floating):
        return float(v)
    return v


def _numbers(path: Path, where: str, value: Any, n: int) -> np.ndarray:
    """`value` as n finite floats, or BopFormatError naming file and place."""
    try:
        a = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise BopFormatError(f"{path}: {where} is not a list of numbers") from None
    if a.size != n or not np.all(np.isfinite(a)):
        raise BopFormatError(f"{path}: {where} must be {n} finite numbers, got {a.size}")
    return a


def rotation_error(R: np.ndarray) -> float:
    """How far a 3x3 matrix is from SO(3): max(|det R - 1|, max |R R^T - I|)."""
    return float(max(abs(np.linalg.det(R) - 1.0), np.abs(R @ R.T - np.eye(3)).max()))


def _check_rotation(path: Path, where: str, R: np.ndarray, tol: float = ROTATION_TOLERANCE) -> float:
    """The rotation error of R (see `rotation_error`); BopFormatError beyond `tol`."""
    err = rotation_error(R)
    if not err <= tol:
        raise BopFormatError(f"{path}: {where} is not a rotation matrix (row-major 3x3 expected; "
                             f"|det - 1| / orthogonality error {err:.3g} > {tol})")
    return err


def _warn_projected(path: Path, where: str, worst: float) -> None:
    """One warning per file: its rotations were projected onto SO(3), the worst error named."""
    if worst > ROTATION_SILENT:
        warnings.warn(f"{path}: rotations projected onto SO(3); worst |det - 1| / orthogonality error "
                      f"{worst:.3g} ({where})", BopAnnotationWarning, stacklevel=3)


def _int_keys(path: Path, content: Any) -> dict[int, Any]:
    if not isinstance(content, dict):
        raise BopFormatError(f"{path}: expected a JSON object keyed by image id")
    out = {}
    for k, v in content.items():
        try:
            out[int(k)] = v
        except ValueError:
            raise BopFormatError(f"{path}: key {k!r} is not an integer id") from None
    return out


# --------------------------------------------------------------------------- models_info


def load_models_info(models_dir: str | os.PathLike) -> dict[int, dict[str, Any]]:
    """models_info.json of a models folder (or the file itself), keyed by int obj_id, in mm as
    BOP defines it. Validated: positive diameter, all six extents when any is given, discrete
    symmetries as 4x4 row-major rigid transforms, continuous ones as {axis, offset}."""
    path = Path(models_dir)
    if path.is_dir():
        path = path / "models_info.json"
    raw = _int_keys(path, load_json(path))
    return {obj_id: _validate_model_info(path, obj_id, entry) for obj_id, entry in sorted(raw.items())}


def _validate_model_info(path: Path, obj_id: int, entry: Any) -> dict[str, Any]:
    where = f"object {obj_id}"
    if not isinstance(entry, dict):
        raise BopFormatError(f"{path}: {where} is not a JSON object")
    if "diameter" not in entry:
        raise BopFormatError(f"{path}: {where} has no diameter")
    d = _numbers(path, f"{where} diameter", entry["diameter"], 1)[0]
    if d <= 0:
        raise BopFormatError(f"{path}: {where} diameter must be positive (mm), got {d}")
    out: dict[str, Any] = dict(entry)
    out["diameter"] = float(d)
    present = [k for k in _EXTENT_KEYS if k in entry]
    if present:
        if len(present) != len(_EXTENT_KEYS):
            missing = sorted(set(_EXTENT_KEYS) - set(present))
            raise BopFormatError(f"{path}: {where} lacks extents {missing}")
        for k in _EXTENT_KEYS:
            out[k] = float(_numbers(path, f"{where} {k}", entry[k], 1)[0])
            if k.startswith("size") and out[k] < 0:
                raise BopFormatError(f"{path}: {where} {k} is negative")
    syms = entry.get("symmetries_discrete", [])
    if not isinstance(syms, list):
        raise BopFormatError(f"{path}: {where} symmetries_discrete must be a list")
    out_syms = []
    for i, s in enumerate(syms):
        T = _numbers(path, f"{where} symmetries_discrete[{i}]", s, 16).reshape(4, 4)
        if np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-6:
            raise BopFormatError(f"{path}: {where} symmetries_discrete[{i}] last row must be 0 0 0 1")
        _check_rotation(path, f"{where} symmetries_discrete[{i}]", T[:3, :3], tol=1e-2)
        out_syms.append([float(x) for x in T.reshape(-1)])
    if "symmetries_discrete" in entry:
        out["symmetries_discrete"] = out_syms
    cont = entry.get("symmetries_continuous", [])
    if not isinstance(cont, list):
        raise BopFormatError(f"{path}: {where} symmetries_continuous must be a list")
    out_cont = []
    for i, s in enumerate(cont):
        if not isinstance(s, dict) or "axis" not in s or "offset" not in s:
            raise BopFormatError(f"{path}: {where} symmetries_continuous[{i}] needs axis and offset")
        axis = _numbers(path, f"{where} symmetries_continuous[{i}].axis", s["axis"], 3)
        if np.linalg.norm(axis) < 1e-9:
            raise BopFormatError(f"{path}: {where} symmetries_continuous[{i}].axis is zero")
        offset = _numbers(path, f"{where} symmetries_continuous[{i}].offset", s["offset"], 3)
        out_cont.append({"axis": axis.tolist(), "offset": offset.tolist()})
    if "symmetries_continuous" in entry:
        out["symmetries_continuous"] = out_cont
    return out


def write_models_info(path: str | os.PathLike, info: Mapping[int, Mapping[str, Any]]) -> None:
    """Write models_info.json (mm) to a file or into a models folder; validated first."""
    path = Path(path)
    if path.is_dir() or path.suffix != ".json":
        path = path / "models_info.json"
    checked = {int(k): _validate_model_info(path, int(k), _jsonable(dict(v))) for k, v in info.items()}
    save_json(path, checked)


def model_path(models_dir: str | os.PathLike, obj_id: int) -> Path:
    return Path(models_dir) / f"obj_{int(obj_id):06d}.ply"


class ModelFolder:
    """The object models of a BOP models folder, for a service: object ids as strings (as on the
    wire), models_info.json read up front (a bad folder fails at start, naming the file), each
    PLY loaded and prepared on first use and cached."""

    def __init__(self, models_dir: str | os.PathLike) -> None:
        self.dir = Path(models_dir)
        if not self.dir.is_dir():
            raise BopFormatError(f"models folder {self.dir} does not exist")
        self.info = load_models_info(self.dir)

    def obj_id(self, object_id: str) -> int:
        """The integer id of a known object; ValueError naming the id and the known ones."""
        try:
            obj_id = int(str(object_id).strip())
        except ValueError:
            obj_id = None
        if obj_id is None or obj_id not in self.info:
            raise ValueError(f"unknown object id {object_id!r}; {self.dir} has {_short(sorted(self.info))}")
        return obj_id

    def diameter(self, object_id: str) -> float:
        """Metres."""
        return float(self.info[self.obj_id(object_id)]["diameter"]) / 1000.0

    def model(self, object_id: str) -> ObjectModel:
        obj_id = self.obj_id(object_id)
        path = model_path(self.dir, obj_id)
        if not path.exists():
            raise ValueError(f"object {object_id!r} has no model file {path}")
        return load_model(path, obj_id, self.info[obj_id])


# --------------------------------------------------------------------------- scene JSON files


@dataclass(frozen=True)
class CameraInfo:
    """One scene_camera.json entry in code units: K, depth_scale (depth PNG unit in mm), and
    the optional world-to-camera pose (cam_R_w2c, cam_t_w2c converted to metres)."""

    K: np.ndarray
    depth_scale: float | None = None
    world_to_cam: Pose | None = None


def load_scene_camera(path: str | os.PathLike) -> dict[int, CameraInfo]:
    path = Path(path)
    out: dict[int, CameraInfo] = {}
    worst, worst_at = 0.0, ""
    for im_id, e in sorted(_int_keys(path, load_json(path)).items()):
        if not isinstance(e, dict) or "cam_K" not in e:
            raise BopFormatError(f"{path}: image {im_id} has no cam_K")
        K = _numbers(path, f"image {im_id} cam_K", e["cam_K"], 9).reshape(3, 3)
        if K[0, 0] <= 0 or K[1, 1] <= 0 or np.abs(K[2] - [0, 0, 1]).max() > 1e-9:
            raise BopFormatError(f"{path}: image {im_id} cam_K is not a pinhole matrix: {K.tolist()}")
        scale = None
        if e.get("depth_scale") is not None:
            scale = float(_numbers(path, f"image {im_id} depth_scale", e["depth_scale"], 1)[0])
            _check_depth_scale(path, scale, f"image {im_id}")
        w2c = None
        if "cam_R_w2c" in e or "cam_t_w2c" in e:
            R = _numbers(path, f"image {im_id} cam_R_w2c", e.get("cam_R_w2c"), 9).reshape(3, 3)
            err = _check_rotation(path, f"image {im_id} cam_R_w2c", R)
            if err > worst:
                worst, worst_at = err, f"image {im_id} cam_R_w2c"
            t = _numbers(path, f"image {im_id} cam_t_w2c", e.get("cam_t_w2c"), 3) * MM
            w2c = Pose(nearest_rotation(R), t)
        out[im_id] = CameraInfo(K, scale, w2c)
    _warn_projected(path, worst_at, worst)
    return out


def _check_depth_scale(path: Path, scale: float, where: str) -> None:
    if not (math.isfinite(scale) and 0 < scale <= 1000):
        raise BopFormatError(f"{path}: {where} depth_scale {scale} is not a positive factor to mm")


def load_scene_gt(path: str | os.PathLike) -> dict[int, list[tuple[int, Pose]]]:
    """scene_gt.json as {im_id: [(obj_id, model-to-camera Pose in metres), ...]} in file order."""
    path = Path(path)
    out: dict[int, list[tuple[int, Pose]]] = {}
    worst, worst_at = 0.0, ""
    for im_id, entries in sorted(_int_keys(path, load_json(path)).items()):
        if not isinstance(entries, list):
            raise BopFormatError(f"{path}: image {im_id} must map to a list of objects")
        objs = []
        for i, e in enumerate(entries):
            where = f"image {im_id} object #{i}"
            if not isinstance(e, dict) or not {"cam_R_m2c", "cam_t_m2c", "obj_id"} <= e.keys():
                raise BopFormatError(f"{path}: {where} needs cam_R_m2c, cam_t_m2c and obj_id")
            R = _numbers(path, f"{where} cam_R_m2c", e["cam_R_m2c"], 9).reshape(3, 3)
            err = _check_rotation(path, f"{where} cam_R_m2c", R)
            if err > worst:
                worst, worst_at = err, f"{where} cam_R_m2c"
            t = _numbers(path, f"{where} cam_t_m2c", e["cam_t_m2c"], 3) * MM
            obj_id = e["obj_id"]
            if not isinstance(obj_id, int) or isinstance(obj_id, bool):
                raise BopFormatError(f"{path}: {where} obj_id must be an integer, got {obj_id!r}")
            # Stored with a few digits: project onto SO(3) at the boundary (ROTATION_TOLERANCE).
            objs.append((obj_id, Pose(nearest_rotation(R), t)))
        out[im_id] = objs
    _warn_projected(path, worst_at, worst)
    return out


def load_scene_gt_info(path: str | os.PathLike) -> dict[int, list[dict[str, Any]]]:
    """scene_gt_info.json as {im_id: [entry, ...]} (pixels and counts, no units to convert)."""
    path = Path(path)
    out: dict[int, list[dict[str, Any]]] = {}
    for im_id, entries in sorted(_int_keys(path, load_json(path)).items()):
        if not isinstance(entries, list):
            raise BopFormatError(f"{path}: image {im_id} must map to a list of objects")
        for i, e in enumerate(entries):
            if not isinstance(e, dict):
                raise BopFormatError(f"{path}: image {im_id} entry #{i} is not an object")
            if "visib_fract" in e:
                v = _numbers(path, f"image {im_id} entry #{i} visib_fract", e["visib_fract"], 1)[0]
                if not -1e-9 <= v <= 1 + 1e-9:
                    raise BopFormatError(f"{path}: image {im_id} entry #{i} visib_fract {v} outside [0, 1]")
            for k in ("bbox_obj", "bbox_visib"):
                if k in e:
                    _numbers(path, f"image {im_id} entry #{i} {k}", e[k], 4)
        out[im_id] = entries
    return out


def write_scene_camera(path: str | os.PathLike, cameras: Mapping[int, CameraInfo]) -> None:
    """Write scene_camera.json (cam_t_w2c converted to mm)."""
    content = {}
    for im_id, cam in cameras.items():
        e: dict[str, Any] = {"cam_K": np.asarray(cam.K, dtype=np.float64).reshape(-1).tolist()}
        if cam.depth_scale is not None:
            e["depth_scale"] = float(cam.depth_scale)
        if cam.world_to_cam is not None:
            e["cam_R_w2c"] = cam.world_to_cam.R.reshape(-1).tolist()
            e["cam_t_w2c"] = (cam.world_to_cam.t / MM).tolist()
        content[int(im_id)] = e
    save_json(path, content)


def write_scene_gt(path: str | os.PathLike, gts: Mapping[int, Sequence[tuple[int, Pose]]]) -> None:
    """Write scene_gt.json from {im_id: [(obj_id, Pose in metres)]} (t converted to mm)."""
    content = {
        int(im_id): [
            {"cam_R_m2c": p.R.reshape(-1).tolist(), "cam_t_m2c": (p.t / MM).tolist(), "obj_id": int(o)}
            for o, p in objs
        ]
        for im_id, objs in gts.items()
    }
    save_json(path, content)


def write_scene_gt_info(path: str | os.PathLike, infos: Mapping[int, Sequence[Mapping[str, Any]]]) -> None:
    """Write scene_gt_info.json from {im_id: [entry]} (entries as bop_toolkit's calc_gt_info)."""
    save_json(path, {int(k): [dict(e) for e in v] for k, v in infos.items()})


# --------------------------------------------------------------------------- images


def _decode(path: Path, flags: int) -> np.ndarray:
    """Decode an image file after refusing directories, special files, files over MAX_IMAGE_BYTES
    and images whose header declares more than the pixel limit (image_header.py): nothing large
    is allocated for a hostile file."""
    try:
        data = read_limited(path, MAX_IMAGE_BYTES, "BOP image")
    except FileNotFoundError:
        raise FileNotFoundError(f"BOP image not found: {path}") from None
    except JsonLimitError as e:
        raise BopFormatError(str(e)) from None
    check_image_header(data, path)
    buf = np.frombuffer(data, dtype=np.uint8)
    img = cv2.imdecode(buf, flags) if buf.size else None
    if img is None:
        raise BopFormatError(f"{path}: corrupt or unreadable image file")
    return img


def read_rgb(path: str | os.PathLike) -> np.ndarray:
    """An 8-bit colour image as uint8 HxWx3 RGB; gray images are replicated to 3 channels and
    an alpha channel is dropped."""
    path = Path(path)
    img = _decode(path, cv2.IMREAD_UNCHANGED)
    if img.dtype != np.uint8:
        raise BopFormatError(f"{path}: rgb image must be 8-bit, got {img.dtype}")
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, axis=2)
    if img.shape[2] == 1:
        return np.repeat(img, 3, axis=2)
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_depth(path: str | os.PathLike, depth_scale: float) -> np.ndarray:
    """A BOP depth PNG (uint16 * depth_scale = mm) as float32 metres with NaN for 0 (missing).

    Refuses a scale that makes the scene implausible (median valid depth outside
    1 cm .. 20 m): that is a wrong depth_scale, not a scene."""
    path = Path(path)
    if depth_scale is None or not math.isfinite(depth_scale) or depth_scale <= 0:
        raise BopFormatError(f"{path}: depth_scale must be a positive number, got {depth_scale}")
    raw = _decode(path, cv2.IMREAD_UNCHANGED)
    if raw.ndim != 2:
        raise BopFormatError(f"{path}: depth image must have one channel, got shape {raw.shape}")
    if raw.dtype not in (np.uint16, np.uint8):
        raise BopFormatError(f"{path}: depth image must be uint16, got {raw.dtype}")
    # float64 then one rounding: whole millimetres come out as the nearest float32 metres
    depth = ((raw * float(depth_scale)) / 1000.0).astype(np.float32)
    depth[raw == 0] = np.nan
    sample = depth[::4, ::4]
    sample = sample[np.isfinite(sample)]
    if sample.size:
        med = float(np.median(sample))
        if not MIN_MEDIAN_DEPTH <= med <= MAX_MEDIAN_DEPTH:
            raise BopFormatError(
                f"{path}: median depth {med:.4g} m with depth_scale {depth_scale} is implausible "
                f"(expected {MIN_MEDIAN_DEPTH}..{MAX_MEDIAN_DEPTH} m): suspect a wrong depth_scale"
            )
    return depth


def write_rgb(path: str | os.PathLike, rgb: np.ndarray, jpg_quality: int = 95) -> None:
    """Write uint8 HxWx3 RGB as PNG (lossless) or JPEG, chosen by the file extension; atomic."""
    path = Path(path)
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"{path}: rgb must be uint8 HxWx3, got {rgb.dtype} {rgb.shape}")
    ext = path.suffix.lower()
    if ext not in RGB_EXTS:
        raise ValueError(f"{path}: rgb extension must be one of {RGB_EXTS}")
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpg_quality)] if ext in (".jpg", ".jpeg") else []
    ok, buf = cv2.imencode(ext, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), params)
    if not ok:
        raise BopFormatError(f"{path}: could not encode the rgb image")
    atomic_write(path, buf.tobytes())


def write_depth(path: str | os.PathLike, depth_m: np.ndarray, depth_scale: float = 1.0) -> None:
    """Write float metres (NaN or 0 = missing) as a uint16 PNG in units of depth_scale mm; atomic.

    Refuses depths that do not fit uint16 at that scale (rather than wrapping around)."""
    path = Path(path)
    if not (math.isfinite(depth_scale) and depth_scale > 0):
        raise ValueError(f"{path}: depth_scale must be positive, got {depth_scale}")
    d = np.asarray(depth_m, dtype=np.float64)
    if d.ndim != 2:
        raise ValueError(f"{path}: depth must be HxW, got shape {d.shape}")
    valid = np.isfinite(d)
    if np.any(np.isinf(d)) or np.any(d[valid] < 0):
        raise ValueError(f"{path}: depth has negative or infinite values")
    units = np.zeros(d.shape, np.float64)
    units[valid] = np.round(d[valid] / MM / depth_scale)
    top = float(units.max(initial=0.0))
    if top > np.iinfo(np.uint16).max:
        raise ValueError(
            f"{path}: depth up to {d[valid].max():.3f} m overflows uint16 at depth_scale {depth_scale} "
            f"(max {np.iinfo(np.uint16).max * depth_scale * MM:.3f} m); use depth_scale >= "
            f"{math.ceil(d[valid].max() / MM / np.iinfo(np.uint16).max * 100) / 100}"
        )
    ok, buf = cv2.imencode(".png", units.astype(np.uint16))
    if not ok:
        raise BopFormatError(f"{path}: could not encode the depth image")
    atomic_write(path, buf.tobytes())


# --------------------------------------------------------------------------- dataset reader


def scene_dir(root: str | os.PathLike, split: str, scene_id: int) -> Path:
    return Path(root) / split / f"{int(scene_id):06d}"


class BopDataset:
    """A BOP dataset split: scenes, images, frames in metres, and its object models.

    Scene JSON files are read once per scene and kept; models are prepared once (core/models.py
    caches them per file). Frames get stamp = im_id / frame_rate (BOP has no timing)."""

    def __init__(
        self,
        root: str | os.PathLike,
        split: str = "test",
        models_subdir: str = "models",
        frame_rate: float = DEFAULT_FRAME_RATE,
        use_depth: bool = True,
    ) -> None:
        self.root = Path(root)
        self.use_depth = bool(use_depth)  # False: read as RGB-only even where depth exists
        self.split = split
        self.models_dir = self.root / models_subdir
        self.frame_rate = float(frame_rate)
        if not self.root.is_dir():
            raise FileNotFoundError(f"BOP dataset folder not found: {self.root}")
        self.split_dir = self.root / split
        if not self.split_dir.is_dir():
            raise FileNotFoundError(f"BOP split folder not found: {self.split_dir}")
        self._scenes: dict[int, tuple[dict[int, CameraInfo], dict[int, list] | None, dict[int, list] | None]] = {}
        self._models: dict[int, ObjectModel] = {}
        self._models_info: dict[int, dict[str, Any]] | None = None
        self._default_scale: float | None | bool = False  # False = not looked up yet

    def __repr__(self) -> str:
        return f"BopDataset(root={str(self.root)!r}, split={self.split!r}, models={self.models_dir.name!r})"

    def __len__(self) -> int:
        return len(self.image_keys())

    # --- index
    def scene_ids(self) -> list[int]:
        return sorted(int(p.name) for p in self.split_dir.iterdir() if p.is_dir() and p.name.isdigit())

    def image_ids(self, scene_id: int) -> list[int]:
        return sorted(self._scene(scene_id)[0])

    def image_keys(self) -> list[tuple[int, int]]:
        return [(s, i) for s in self.scene_ids() for i in self.image_ids(s)]

    def _scene(self, scene_id: int) -> tuple[dict[int, CameraInfo], dict[int, list] | None, dict[int, list] | None]:
        if scene_id not in self._scenes:
            d = scene_dir(self.root, self.split, scene_id)
            if not d.is_dir():
                raise FileNotFoundError(f"BOP scene folder not found: {d} (scenes: {self.scene_ids()})")
            cams = load_scene_camera(d / "scene_camera.json")
            gts = load_scene_gt(d / "scene_gt.json") if (d / "scene_gt.json").exists() else None
            infos = load_scene_gt_info(d / "scene_gt_info.json") if (d / "scene_gt_info.json").exists() else None
            self._scenes[scene_id] = (cams, gts, infos)
        return self._scenes[scene_id]

    def _image_file(self, scene_id: int, im_id: int, what: str) -> Path:
        d = scene_dir(self.root, self.split, scene_id)
        if what == "depth":
            return d / "depth" / f"{im_id:06d}.png"
        for sub in ("rgb", "gray"):
            for ext in RGB_EXTS:
                p = d / sub / f"{im_id:06d}{ext}"
                if p.exists():
                    return p
        raise FileNotFoundError(f"BOP rgb image not found: {d / 'rgb' / f'{im_id:06d}.png'} (nor .jpg, gray/)")

    def camera(self, scene_id: int, im_id: int) -> CameraInfo:
        cams = self._scene(scene_id)[0]
        if im_id not in cams:
            path = scene_dir(self.root, self.split, scene_id) / "scene_camera.json"
            raise BopFormatError(f"{path}: no image {im_id} (images: {_short(sorted(cams))})")
        return cams[im_id]

    def gt(self, scene_id: int, im_id: int) -> list[tuple[int, Pose]]:
        """Ground-truth (obj_id, Pose) of an image; [] for a split without scene_gt.json."""
        self.camera(scene_id, im_id)
        gts = self._scene(scene_id)[1]
        if gts is None:
            return []
        if im_id not in gts:
            path = scene_dir(self.root, self.split, scene_id) / "scene_gt.json"
            raise BopFormatError(f"{path}: no entry for image {im_id}, which scene_camera.json lists")
        return gts[im_id]

    def gt_info(self, scene_id: int, im_id: int) -> list[dict[str, Any]] | None:
        """scene_gt_info entries of an image (aligned with `gt`), None when the file is absent."""
        infos = self._scene(scene_id)[2]
        if infos is None:
            return None
        path = scene_dir(self.root, self.split, scene_id) / "scene_gt_info.json"
        if im_id not in infos:
            raise BopFormatError(f"{path}: no entry for image {im_id}")
        n = len(self.gt(scene_id, im_id))
        if len(infos[im_id]) != n:
            raise BopFormatError(f"{path}: image {im_id} has {len(infos[im_id])} entries but scene_gt.json {n}")
        return infos[im_id]

    def has_depth(self, scene_id: int, im_id: int) -> bool:
        """Whether the image has depth: the scene has a depth/ folder (BOP's RGB-only
        datasets and splits have none) and the reader was not told to drop it. A scene with
        a depth/ folder that lacks this image's file is an error, not an RGB-only image."""
        if not self.use_depth:
            return False
        return (scene_dir(self.root, self.split, scene_id) / "depth").is_dir()

    def _depth_scale(self, scene_id: int, im_id: int) -> float:
        scale = self.camera(scene_id, im_id).depth_scale
        if scale is not None:
            return scale
        if self._default_scale is False:  # dataset-wide camera.json may carry it
            cam_json = self.root / "camera.json"
            self._default_scale = None
            if cam_json.exists():
                c = load_json(cam_json)
                if isinstance(c, dict) and c.get("depth_scale") is not None:
                    self._default_scale = float(_numbers(cam_json, "depth_scale", c["depth_scale"], 1)[0])
                    _check_depth_scale(cam_json, self._default_scale, "camera")
        if self._default_scale is None:
            path = scene_dir(self.root, self.split, scene_id) / "scene_camera.json"
            raise BopFormatError(f"{path}: image {im_id} has no depth_scale (nor has {self.root / 'camera.json'})")
        return float(self._default_scale)

    # --- models
    @property
    def models_info(self) -> dict[int, dict[str, Any]]:
        """models_info.json of the models folder (mm); {} when the file is absent."""
        if self._models_info is None:
            p = self.models_dir / "models_info.json"
            self._models_info = load_models_info(p) if p.exists() else {}
        return self._models_info

    def obj_ids(self) -> list[int]:
        if self.models_info:
            return sorted(self.models_info)
        return sorted(int(p.stem[4:]) for p in self.models_dir.glob("obj_*.ply") if p.stem[4:].isdigit())

    def model(self, obj_id: int) -> ObjectModel:
        """The prepared model of an object (metres), cached."""
        if obj_id not in self._models:
            path = model_path(self.models_dir, obj_id)
            info = self.models_info.get(obj_id)
            if self.models_info and info is None:
                raise BopFormatError(
                    f"{self.models_dir / 'models_info.json'}: unknown object id {obj_id} "
                    f"(known: {_short(sorted(self.models_info))})"
                )
            if not path.exists():
                raise BopFormatError(f"unknown object id {obj_id}: no model file {path}")
            self._models[obj_id] = load_model(path, obj_id, info)
        return self._models[obj_id]

    # --- frames
    def load_frame(self, scene_id: int, im_id: int, with_models: bool = True) -> Frame:
        """The frame of one image: rgb, depth (metres, NaN missing; None for an RGB-only dataset or
        with use_depth=False), K, and the annotated objects (gt pose, visib_fract and bbox_visib
        when scene_gt_info exists, and the model)."""
        cam = self.camera(scene_id, im_id)
        gts = self.gt(scene_id, im_id)
        infos = self.gt_info(scene_id, im_id)
        rgb_path = self._image_file(scene_id, im_id, "rgb")
        rgb = read_rgb(rgb_path)
        depth = None
        if self.has_depth(scene_id, im_id):
            depth_path = self._image_file(scene_id, im_id, "depth")
            depth = read_depth(depth_path, self._depth_scale(scene_id, im_id))
        if depth is not None and rgb.shape[:2] != depth.shape:
            raise BopFormatError(
                f"{rgb_path} is {rgb.shape[1]}x{rgb.shape[0]} but {depth_path} is {depth.shape[1]}x{depth.shape[0]}"
            )
        objects = []
        for k, (obj_id, pose) in enumerate(gts):
            info = infos[k] if infos is not None else {}
            bbox = info.get("bbox_visib")
            objects.append(
                SceneObject(
                    obj_id=obj_id,
                    gt=pose,
                    model=self.model(obj_id) if with_models else None,
                    visib_fract=float(info["visib_fract"]) if "visib_fract" in info else None,
                    bbox_visib=tuple(int(v) for v in bbox) if bbox is not None else None,  # type: ignore[arg-type]
                )
            )
        return Frame(
            rgb=rgb, depth=depth, K=cam.K, stamp=im_id / self.frame_rate,
            scene_id=scene_id, im_id=im_id, objects=objects,
        )

    def frames(self, with_models: bool = True) -> Iterator[Frame]:
        for scene_id, im_id in self.image_keys():
            yield self.load_frame(scene_id, im_id, with_models)


def _short(ids: Sequence[int], n: int = 20) -> str:
    s = ", ".join(str(i) for i in ids[:n])
    return s + (f", ... ({len(ids)} in all)" if len(ids) > n else "")


# --------------------------------------------------------------------------- dataset writer

GtInfoArg = Sequence[Mapping[str, Any]] | Literal["compute"] | None


class SceneWriter:
    """Writes frames into one BOP scene: images at once, the three JSON files at flush/close.

    For generators: O(1) work per frame instead of rewriting growing JSON files each time.
    With append=True (default) existing entries of the scene are kept and extended; an added
    image id replaces its old entry. The scene's frames all carry scene_gt_info or none do.
    Use as a context manager; the JSON files are written even when the block raises, so the
    images already written stay described.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        split: str,
        scene_id: int,
        *,
        depth_scale: float = 1.0,
        rgb_ext: str = ".png",
        append: bool = True,
        jpg_quality: int = 95,
    ) -> None:
        self.dir = scene_dir(root, split, scene_id)
        self.scene_id = int(scene_id)
        self.depth_scale = float(depth_scale)
        self.rgb_ext = rgb_ext if rgb_ext.startswith(".") else "." + rgb_ext
        if self.rgb_ext.lower() not in RGB_EXTS:
            raise ValueError(f"rgb_ext must be one of {RGB_EXTS}, got {rgb_ext!r}")
        self.jpg_quality = jpg_quality
        self.cameras: dict[int, CameraInfo] = {}
        self.gts: dict[int, list[tuple[int, Pose]]] = {}
        self.gt_infos: dict[int, list[dict[str, Any]]] | None = None  # None = undecided / absent
        if append and (self.dir / "scene_camera.json").exists():
            self.cameras = load_scene_camera(self.dir / "scene_camera.json")
            if (self.dir / "scene_gt.json").exists():
                self.gts = load_scene_gt(self.dir / "scene_gt.json")
            if (self.dir / "scene_gt_info.json").exists():
                self.gt_infos = load_scene_gt_info(self.dir / "scene_gt_info.json")
        self._dirty = False

    def __enter__(self) -> "SceneWriter":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def add(
        self,
        frame: Frame,
        gt_info: GtInfoArg = None,
        *,
        depth_scale: float | None = None,
        world_to_cam: Pose | None = None,
    ) -> None:
        """Write the frame's images now and record its camera and ground truth (objects with a
        gt pose). `gt_info`: scene_gt_info entries aligned with those objects, "compute" to
        compute them from the models and depth (compute_gt_info), or None to write none.
        The frame's im_id names the image; its scene_id is ignored (the writer's wins)."""
        im_id = int(frame.im_id)
        scale = self.depth_scale if depth_scale is None else float(depth_scale)
        objs = [(o.obj_id, o.gt) for o in frame.objects if o.gt is not None]
        infos: list[dict[str, Any]] | None
        if isinstance(gt_info, str):
            if gt_info != "compute":
                raise ValueError(f"gt_info must be entries, 'compute' or None, got {gt_info!r}")
            infos = compute_gt_info(frame)
        else:
            infos = [dict(_jsonable(dict(e))) for e in gt_info] if gt_info is not None else None
        if infos is not None and len(infos) != len(objs):
            raise ValueError(f"image {im_id}: {len(infos)} gt_info entries for {len(objs)} objects with a gt pose")
        others = [i for i in self.cameras if i != im_id]
        if others:
            has = self.gt_infos is not None and any(i in self.gt_infos for i in others)
            if has != (infos is not None):
                raise ValueError(
                    f"{self.dir}: image {im_id} {'lacks' if has else 'has'} scene_gt_info but the scene's "
                    f"other images {'have' if has else 'do not'}: all or none"
                )
        rgb_path = self.dir / "rgb" / f"{im_id:06d}{self.rgb_ext}"
        for ext in RGB_EXTS:  # replacing an image with another format: drop the old file
            old = rgb_path.with_suffix(ext)
            if ext != self.rgb_ext and old.exists():
                old.unlink()
        depth_path = self.dir / "depth" / f"{im_id:06d}.png"
        if frame.depth is None:  # an RGB-only frame: the scene must be RGB-only (no depth folder)
            with_depth = [p.name for p in depth_path.parent.glob("*.png") if p != depth_path] \
                if depth_path.parent.is_dir() else []
            if with_depth:
                raise ValueError(f"{self.dir}: image {im_id} has no depth but the scene's images {with_depth[:3]} "
                                 "have: a scene is RGB-D or RGB-only, all or none")
        elif others and not depth_path.parent.is_dir():
            raise ValueError(f"{self.dir}: image {im_id} has depth but the scene's other images have none "
                             "(no depth folder): a scene is RGB-D or RGB-only, all or none")
        write_rgb(rgb_path, frame.rgb, self.jpg_quality)
        if frame.depth is None:
            depth_path.unlink(missing_ok=True)
            if depth_path.parent.is_dir() and not any(depth_path.parent.iterdir()):
                depth_path.parent.rmdir()
        else:
            write_depth(depth_path, frame.depth, scale)
        self.cameras[im_id] = CameraInfo(frame.K.copy(), scale, world_to_cam)
        self.gts[im_id] = objs  # type: ignore[assignment]
        if infos is not None:
            if self.gt_infos is None:
                self.gt_infos = {}
            self.gt_infos[im_id] = infos
        elif self.gt_infos is not None:
            self.gt_infos.pop(im_id, None)
        self._dirty = True

    def flush(self) -> None:
        """Write scene_camera.json, scene_gt.json and scene_gt_info.json (atomically)."""
        if not self._dirty:
            return
        write_scene_camera(self.dir / "scene_camera.json", self.cameras)
        write_scene_gt(self.dir / "scene_gt.json", self.gts)
        if self.gt_infos:
            write_scene_gt_info(self.dir / "scene_gt_info.json", self.gt_infos)
        elif (self.dir / "scene_gt_info.json").exists():  # its only image was replaced without
            (self.dir / "scene_gt_info.json").unlink()
        self._dirty = False

    def close(self) -> None:
        self.flush()


def write_frame(
    root: str | os.PathLike,
    split: str,
    frame: Frame,
    gt_info: GtInfoArg = None,
    *,
    depth_scale: float = 1.0,
    rgb_ext: str = ".png",
    world_to_cam: Pose | None = None,
) -> None:
    """Append one frame to scene frame.scene_id (rewrites that scene's JSON files: for many
    frames use SceneWriter)."""
    with SceneWriter(root, split, frame.scene_id, depth_scale=depth_scale, rgb_ext=rgb_ext) as w:
        w.add(frame, gt_info, world_to_cam=world_to_cam)


def compute_gt_info(frame: Frame, delta: float = 0.015) -> list[dict[str, Any]]:
    """scene_gt_info entries of a frame's objects with a gt pose and a model, as bop_toolkit's
    calc_gt_info (visib_mode bop19): each object rendered alone; a pixel is visible where the
    frame's distance is missing or not more than `delta` metres in front of the model.
    bbox_obj may extend outside the image (rendered into a 3x larger virtual image). An
    RGB-only frame (depth None) is compared with the depth of all its objects rendered together
    (occlusion among the annotated objects; clutter that is not annotated is not seen)."""
    from ..core.render import render, render_box

    H, W = frame.height, frame.width
    K = frame.K
    Kbig = K.copy()
    Kbig[0, 2] += W
    Kbig[1, 2] += H
    vv, uu = np.mgrid[0:H, 0:W]
    Kinv = np.linalg.inv(K)
    ray_norm = np.linalg.norm(np.stack([uu, vv, np.ones_like(uu)], -1) @ Kinv.T, axis=2)
    depth = frame.depth
    if depth is None:
        shown = [o for o in frame.objects if o.gt is not None and o.model is not None]
        depth = (render([o.model for o in shown], [o.gt for o in shown], K, W, H).depth if shown
                 else np.full((H, W), np.nan, np.float32))
    dist_test = np.nan_to_num(depth, nan=0.0) * ray_norm
    out = []
    for o in frame.objects:
        if o.gt is None:
            continue
        if o.model is None:
            raise ValueError(f"compute_gt_info: object {o.obj_id} of image {frame.im_id} has no model")
        r = render_box(o.model, o.gt, Kbig, 3 * W, 3 * H, margin=0)
        ys, xs = np.nonzero(r.mask >= 0)
        xs, ys = xs + r.offset[0] - W, ys + r.offset[1] - H
        bbox_obj = ([int(xs.min()), int(ys.min()), int(xs.max() - xs.min()), int(ys.max() - ys.min())] if xs.size
                    else [-1] * 4)
        inside = (xs >= 0) & (xs < W) & (ys >= 0) & (ys < H)
        xs, ys = xs[inside], ys[inside]
        z = r.depth[ys + H - r.offset[1], xs + W - r.offset[0]]
        dist_model = z * ray_norm[ys, xs]
        dt = dist_test[ys, xs]
        visib = (dt == 0) | (dist_model - dt <= delta)
        n_all, n_visib = int(xs.size), int(visib.sum())
        vx, vy = xs[visib], ys[visib]
        out.append({
            "bbox_obj": bbox_obj,
            "bbox_visib": ([int(vx.min()), int(vy.min()), int(vx.max() - vx.min()), int(vy.max() - vy.min())]
                           if n_visib else [-1] * 4),
            "px_count_all": n_all,
            "px_count_valid": int((dt > 0).sum()),
            "px_count_visib": n_visib,
            "visib_fract": n_visib / n_all if n_all else 0.0,
        })
    return out


# --------------------------------------------------------------------------- results CSV


@dataclass(frozen=True)
class BopResult:
    """One pose estimate for the BOP results CSV; pose in metres, time in seconds (-1 unknown;
    bop_toolkit wants the same time for all estimates of an image)."""

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    pose: Pose
    time: float = -1.0


def write_results_csv(path: str | os.PathLike, rows: Iterable[BopResult]) -> None:
    """Write `scene_id,im_id,obj_id,score,R,t,time` (R row-major, t in mm, space-separated)
    as bop_toolkit's inout.save_bop_results; atomic."""
    buf = io.StringIO()
    buf.write(",".join(RESULTS_HEADER) + "\n")
    for r in rows:
        R = " ".join(repr(float(x)) for x in r.pose.R.reshape(-1))
        t = " ".join(repr(float(x)) for x in r.pose.t / MM)
        buf.write(f"{int(r.scene_id)},{int(r.im_id)},{int(r.obj_id)},{float(r.score)!r},{R},{t},{float(r.time)!r}\n")
    atomic_write(Path(path), buf.getvalue().encode("utf-8"))


def read_results_csv(path: str | os.PathLike) -> list[BopResult]:
    """Read a BOP results CSV (t in mm -> metres); BopFormatError naming file and line."""
    path = Path(path)
    try:
        text = read_limited(path, MAX_JSON_BYTES, "BOP results file").decode("utf-8")
    except FileNotFoundError:
        raise FileNotFoundError(f"BOP results file not found: {path}") from None
    except JsonLimitError as e:
        raise BopFormatError(str(e)) from None
    except UnicodeDecodeError as e:
        raise BopFormatError(f"{path}: not UTF-8 text ({e.reason})") from None
    rows = list(csv.reader(io.StringIO(text)))
    if not rows or [c.strip() for c in rows[0]] != RESULTS_HEADER:
        raise BopFormatError(f"{path}: header must be {','.join(RESULTS_HEADER)}")
    out = []
    for ln, row in enumerate(rows[1:], start=2):
        if not row or not "".join(row).strip():
            continue
        if len(row) != len(RESULTS_HEADER):
            raise BopFormatError(f"{path}: line {ln} has {len(row)} columns, expected {len(RESULTS_HEADER)}")
        try:
            R = np.array(row[4].split(), dtype=np.float64)
            t = np.array(row[5].split(), dtype=np.float64)
            res = (int(row[0]), int(row[1]), int(row[2]), float(row[3]), float(row[6]))
        except ValueError:
            raise BopFormatError(f"{path}: line {ln} has a non-numeric value") from None
        if R.size != 9 or t.size != 3 or not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            raise BopFormatError(f"{path}: line {ln}: R needs 9 and t 3 finite numbers")
        out.append(BopResult(res[0], res[1], res[2], res[3], Pose(R.reshape(3, 3), t * MM), res[4]))
    return out


__all__ = [
    "BopFormatError", "BopDataset", "CameraInfo", "SceneWriter", "BopResult",
    "load_json", "save_json", "load_models_info", "write_models_info", "model_path",
    "load_scene_camera", "load_scene_gt", "load_scene_gt_info",
    "write_scene_camera", "write_scene_gt", "write_scene_gt_info",
    "read_rgb", "read_depth", "write_rgb", "write_depth", "write_frame", "compute_gt_info",
    "write_results_csv", "read_results_csv", "scene_dir", "DEFAULT_FRAME_RATE",
]
