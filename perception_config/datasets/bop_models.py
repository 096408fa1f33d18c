"""The models folder of a BOP dataset: models_info.json (read, validated and written, in mm as BOP
defines it; core/models.py converts it when preparing a model), the model file paths, and
`ModelFolder`, a service's view of the folder.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..core.models import ObjectModel, load_model
from .bop_json import check_rotation, finite_numbers, int_keys, jsonable, load_json, save_json, short_ids
from .errors import BopFormatError

EXTENT_KEYS = ("min_x", "min_y", "min_z", "size_x", "size_y", "size_z")


def load_models_info(models_dir: str | os.PathLike) -> dict[int, dict[str, Any]]:
    """models_info.json of a models folder (or the file itself), keyed by int obj_id, in mm as
    BOP defines it. Validated: positive diameter, all six extents when any is given, discrete
    symmetries as 4x4 row-major rigid transforms, continuous ones as {axis, offset}."""
    path = Path(models_dir)
    if path.is_dir():
        path = path / "models_info.json"
    raw = int_keys(path, load_json(path))
    return {obj_id: _validate_model_info(path, obj_id, entry) for obj_id, entry in sorted(raw.items())}


def _validate_model_info(path: Path, obj_id: int, entry: Any) -> dict[str, Any]:
    where = f"object {obj_id}"
    if not isinstance(entry, dict):
        raise BopFormatError(f"{path}: {where} is not a JSON object")
    if "diameter" not in entry:
        raise BopFormatError(f"{path}: {where} has no diameter")
    d = finite_numbers(path, f"{where} diameter", entry["diameter"], 1)[0]
    if d <= 0:
        raise BopFormatError(f"{path}: {where} diameter must be positive (mm), got {d}")
    out: dict[str, Any] = dict(entry)
    out["diameter"] = float(d)
    present = [k for k in EXTENT_KEYS if k in entry]
    if present:
        if len(present) != len(EXTENT_KEYS):
            missing = sorted(set(EXTENT_KEYS) - set(present))
            raise BopFormatError(f"{path}: {where} lacks extents {missing}")
        for k in EXTENT_KEYS:
            out[k] = float(finite_numbers(path, f"{where} {k}", entry[k], 1)[0])
            if k.startswith("size") and out[k] < 0:
                raise BopFormatError(f"{path}: {where} {k} is negative")
    syms = entry.get("symmetries_discrete", [])
    if not isinstance(syms, list):
        raise BopFormatError(f"{path}: {where} symmetries_discrete must be a list")
    out_syms = []
    for i, s in enumerate(syms):
        T = finite_numbers(path, f"{where} symmetries_discrete[{i}]", s, 16).reshape(4, 4)
        if np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-6:
            raise BopFormatError(f"{path}: {where} symmetries_discrete[{i}] last row must be 0 0 0 1")
        check_rotation(path, f"{where} symmetries_discrete[{i}]", T[:3, :3], tol=1e-2)
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
        axis = finite_numbers(path, f"{where} symmetries_continuous[{i}].axis", s["axis"], 3)
        if np.linalg.norm(axis) < 1e-9:
            raise BopFormatError(f"{path}: {where} symmetries_continuous[{i}].axis is zero")
        offset = finite_numbers(path, f"{where} symmetries_continuous[{i}].offset", s["offset"], 3)
        out_cont.append({"axis": axis.tolist(), "offset": offset.tolist()})
    if "symmetries_continuous" in entry:
        out["symmetries_continuous"] = out_cont
    return out


def write_models_info(path: str | os.PathLike, info: Mapping[int, Mapping[str, Any]]) -> None:
    """Write models_info.json (mm) to a file or into a models folder; validated first."""
    path = Path(path)
    if path.is_dir() or path.suffix != ".json":
        path = path / "models_info.json"
    checked = {int(k): _validate_model_info(path, int(k), jsonable(dict(v))) for k, v in info.items()}
    save_json(path, checked)


def model_path(models_dir: str | os.PathLike, obj_id: int) -> Path:
    """The PLY file of an object in a models folder."""
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
            raise ValueError(f"unknown object id {object_id!r}; {self.dir} has {short_ids(sorted(self.info))}")
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


__all__ = ["load_models_info", "write_models_info", "model_path", "ModelFolder"]
