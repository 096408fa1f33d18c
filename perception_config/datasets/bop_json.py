"""JSON files of the BOP layout: reading and writing them, and the checks of the values in them
(numbers, rotations, integer keys). Bad input raises BopFormatError (a ValueError) or
FileNotFoundError naming the offending file; writers are atomic (util/atomic_file.py), so a
reader never sees half a JSON file.
"""
from __future__ import annotations

import json
import os
import warnings
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from ..util.atomic_file import atomic_write
from ..util.safe_json import JsonLimitError, read_json_file
from .errors import BopAnnotationWarning, BopFormatError

MAX_JSON_BYTES = 256 * 1024 * 1024  # a BOP JSON file larger than this is refused before reading
MAX_JSON_DEPTH = 32  # BOP JSON files nest 4 levels; deeper is refused before parsing
# Real annotations are stored with a few digits: LM-O's cam_R_m2c reach |det - 1| = 0.014.
# Up to ROTATION_TOLERANCE they are projected onto SO(3) (one warning per file beyond
# ROTATION_SILENT, the rounding of 6-digit files); beyond it the matrix is refused.
ROTATION_TOLERANCE = 0.05
ROTATION_SILENT = 1e-3


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
    lines = [f"  {json.dumps(str(k))}: {json.dumps(jsonable(v), sort_keys=True)}" for k, v in items]
    text = "{\n" + ",\n".join(lines) + ("\n" if lines else "") + "}\n"
    atomic_write(Path(path), text.encode("utf-8"))


def jsonable(v: Any) -> Any:
    """`v` with numpy arrays and scalars turned into lists and Python numbers, dict keys into strings."""
    if isinstance(v, dict):
        return {str(k): jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return jsonable(v.tolist())
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.floating):
        return float(v)
    return v


def finite_numbers(path: Path, where: str, value: Any, n: int) -> np.ndarray:
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


def check_rotation(path: Path, where: str, R: np.ndarray, tol: float = ROTATION_TOLERANCE) -> float:
    """The rotation error of R (see `rotation_error`); BopFormatError beyond `tol`."""
    err = rotation_error(R)
    if not err <= tol:
        raise BopFormatError(f"{path}: {where} is not a rotation matrix (row-major 3x3 expected; "
                             f"|det - 1| / orthogonality error {err:.3g} > {tol})")
    return err


def warn_projected(path: Path, where: str, worst: float) -> None:
    """One warning per file: its rotations were projected onto SO(3), the worst error named."""
    if worst > ROTATION_SILENT:
        warnings.warn(f"{path}: rotations projected onto SO(3); worst |det - 1| / orthogonality error "
                      f"{worst:.3g} ({where})", BopAnnotationWarning, stacklevel=3)


def int_keys(path: Path, content: Any) -> dict[int, Any]:
    """A JSON object keyed by image id as {int id: value}; BopFormatError naming the file otherwise."""
    if not isinstance(content, dict):
        raise BopFormatError(f"{path}: expected a JSON object keyed by image id")
    out = {}
    for k, v in content.items():
        try:
            out[int(k)] = v
        except ValueError:
            raise BopFormatError(f"{path}: key {k!r} is not an integer id") from None
    return out


def short_ids(ids: Sequence[int], n: int = 20) -> str:
    """The first `n` ids, comma-separated, and how many there are in all when more."""
    s = ", ".join(str(i) for i in ids[:n])
    return s + (f", ... ({len(ids)} in all)" if len(ids) > n else "")


__all__ = [
    "load_json", "save_json", "jsonable", "finite_numbers", "rotation_error", "check_rotation", "warn_projected",
    "int_keys", "short_ids", "MAX_JSON_BYTES", "MAX_JSON_DEPTH", "ROTATION_TOLERANCE", "ROTATION_SILENT",
]
