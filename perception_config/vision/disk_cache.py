"""The on-disk cache of per-model preparations (ppf's point pair tables, linemod's templates):
where it lives, how an entry is named and how it is read and written.

An entry is a compressed .npz named by `model_digest` (the model's geometry, the parameters and
the format version) that also holds that digest; `load_npz` gives None for a missing, unreadable
or corrupt file (the caller then checks the digest and the shapes, and rebuilds on any doubt);
`store_npz` writes atomically and gives up quietly on a read-only folder (the preparation then
serves from memory only).
"""
from __future__ import annotations

import hashlib
import os
import zipfile
from pathlib import Path

import numpy as np

from ..core.models import ObjectModel
from ..util.atomic_file import atomic_output


def cache_dir() -> Path:
    """Where prepared per-model tables live: $PERCEPTION_CONFIG_CACHE, else
    $XDG_CACHE_HOME/perception_config, else ~/.cache/perception_config."""
    env = os.environ.get("PERCEPTION_CONFIG_CACHE")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "perception_config"


def model_digest(model: ObjectModel, params: str) -> str:
    """Hash of what a preparation is built from: the model's geometry and samples (vertices,
    faces, surface points and normals) and `params` (the parameters and the format version)."""
    h = hashlib.sha256()
    for a in (model.vertices, model.faces, model.points, model.point_normals):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(params.encode())
    return h.hexdigest()[:32]


def load_npz(path: Path, digest: str) -> dict[str, np.ndarray] | None:
    """Every array of the .npz at `path` when it holds `digest`; None when the file is missing,
    unreadable, corrupt or another entry's."""
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["digest"]) != digest:
                return None
            return {k: z[k] for k in z.files}
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError):
        return None  # corrupt or from another format: rebuilt by the caller


def store_npz(path: Path, digest: str, arrays: dict[str, np.ndarray]) -> bool:
    """Write `arrays` and `digest` to `path` atomically; False when the folder is not writable."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_output(path) as tmp:
            np.savez_compressed(tmp, digest=np.array(digest), **arrays)
    except OSError:
        return False  # a read-only cache folder: the preparation still serves from memory
    return True


__all__ = ["cache_dir", "model_digest", "load_npz", "store_npz"]
