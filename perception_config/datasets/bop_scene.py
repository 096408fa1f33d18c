"""The JSON files of a BOP scene folder (root/<split>/<scene 6 digits>/): scene_camera.json,
scene_gt.json and scene_gt_info.json, read and written in code units (metres; the files are mm).
Stored rotations are projected onto SO(3) up to bop_json.ROTATION_TOLERANCE, refused beyond.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from ..core.geometry import MM, Pose, nearest_rotation
from .bop_json import check_rotation, finite_numbers, int_keys, load_json, save_json, warn_projected
from .errors import BopFormatError


def scene_dir(root: str | os.PathLike, split: str, scene_id: int) -> Path:
    """The folder of a scene: root/<split>/<scene id, 6 digits>."""
    return Path(root) / split / f"{int(scene_id):06d}"


@dataclass(frozen=True)
class CameraInfo:
    """One scene_camera.json entry in code units: K, depth_scale (depth PNG unit in mm), and
    the optional world-to-camera pose (cam_R_w2c, cam_t_w2c converted to metres)."""

    K: np.ndarray
    depth_scale: float | None = None
    world_to_cam: Pose | None = None


def load_scene_camera(path: str | os.PathLike) -> dict[int, CameraInfo]:
    """scene_camera.json as {im_id: CameraInfo} (cam_t_w2c converted to metres)."""
    path = Path(path)
    out: dict[int, CameraInfo] = {}
    worst, worst_at = 0.0, ""
    for im_id, e in sorted(int_keys(path, load_json(path)).items()):
        if not isinstance(e, dict) or "cam_K" not in e:
            raise BopFormatError(f"{path}: image {im_id} has no cam_K")
        K = finite_numbers(path, f"image {im_id} cam_K", e["cam_K"], 9).reshape(3, 3)
        if K[0, 0] <= 0 or K[1, 1] <= 0 or np.abs(K[2] - [0, 0, 1]).max() > 1e-9:
            raise BopFormatError(f"{path}: image {im_id} cam_K is not a pinhole matrix: {K.tolist()}")
        scale = None
        if e.get("depth_scale") is not None:
            scale = float(finite_numbers(path, f"image {im_id} depth_scale", e["depth_scale"], 1)[0])
            check_depth_scale(path, scale, f"image {im_id}")
        w2c = None
        if "cam_R_w2c" in e or "cam_t_w2c" in e:
            R = finite_numbers(path, f"image {im_id} cam_R_w2c", e.get("cam_R_w2c"), 9).reshape(3, 3)
            err = check_rotation(path, f"image {im_id} cam_R_w2c", R)
            if err > worst:
                worst, worst_at = err, f"image {im_id} cam_R_w2c"
            t = finite_numbers(path, f"image {im_id} cam_t_w2c", e.get("cam_t_w2c"), 3) * MM
            w2c = Pose(nearest_rotation(R), t)
        out[im_id] = CameraInfo(K, scale, w2c)
    warn_projected(path, worst_at, worst)
    return out


def check_depth_scale(path: Path, scale: float, where: str) -> None:
    """BopFormatError unless `scale` is a positive factor to mm of at most 1000."""
    if not (math.isfinite(scale) and 0 < scale <= 1000):
        raise BopFormatError(f"{path}: {where} depth_scale {scale} is not a positive factor to mm")


def load_scene_gt(path: str | os.PathLike) -> dict[int, list[tuple[int, Pose]]]:
    """scene_gt.json as {im_id: [(obj_id, model-to-camera Pose in metres), ...]} in file order."""
    path = Path(path)
    out: dict[int, list[tuple[int, Pose]]] = {}
    worst, worst_at = 0.0, ""
    for im_id, entries in sorted(int_keys(path, load_json(path)).items()):
        if not isinstance(entries, list):
            raise BopFormatError(f"{path}: image {im_id} must map to a list of objects")
        objs = []
        for i, e in enumerate(entries):
            where = f"image {im_id} object #{i}"
            if not isinstance(e, dict) or not {"cam_R_m2c", "cam_t_m2c", "obj_id"} <= e.keys():
                raise BopFormatError(f"{path}: {where} needs cam_R_m2c, cam_t_m2c and obj_id")
            R = finite_numbers(path, f"{where} cam_R_m2c", e["cam_R_m2c"], 9).reshape(3, 3)
            err = check_rotation(path, f"{where} cam_R_m2c", R)
            if err > worst:
                worst, worst_at = err, f"{where} cam_R_m2c"
            t = finite_numbers(path, f"{where} cam_t_m2c", e["cam_t_m2c"], 3) * MM
            obj_id = e["obj_id"]
            if not isinstance(obj_id, int) or isinstance(obj_id, bool):
                raise BopFormatError(f"{path}: {where} obj_id must be an integer, got {obj_id!r}")
            # Stored with a few digits: project onto SO(3) at the boundary (ROTATION_TOLERANCE).
            objs.append((obj_id, Pose(nearest_rotation(R), t)))
        out[im_id] = objs
    warn_projected(path, worst_at, worst)
    return out


def load_scene_gt_info(path: str | os.PathLike) -> dict[int, list[dict[str, Any]]]:
    """scene_gt_info.json as {im_id: [entry, ...]} (pixels and counts, no units to convert)."""
    path = Path(path)
    out: dict[int, list[dict[str, Any]]] = {}
    for im_id, entries in sorted(int_keys(path, load_json(path)).items()):
        if not isinstance(entries, list):
            raise BopFormatError(f"{path}: image {im_id} must map to a list of objects")
        for i, e in enumerate(entries):
            if not isinstance(e, dict):
                raise BopFormatError(f"{path}: image {im_id} entry #{i} is not an object")
            if "visib_fract" in e:
                v = finite_numbers(path, f"image {im_id} entry #{i} visib_fract", e["visib_fract"], 1)[0]
                if not -1e-9 <= v <= 1 + 1e-9:
                    raise BopFormatError(f"{path}: image {im_id} entry #{i} visib_fract {v} outside [0, 1]")
            for k in ("bbox_obj", "bbox_visib"):
                if k in e:
                    finite_numbers(path, f"image {im_id} entry #{i} {k}", e[k], 4)
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


__all__ = [
    "CameraInfo", "scene_dir", "load_scene_camera", "load_scene_gt", "load_scene_gt_info", "check_depth_scale",
    "write_scene_camera", "write_scene_gt", "write_scene_gt_info",
]
