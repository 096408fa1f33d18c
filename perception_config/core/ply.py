"""PLY model files: read and written with trimesh (ascii and binary, any property order, optional
normals and colours); its failures become PlyError naming the file. trimesh is imported only
when a file is read or written.
"""
from __future__ import annotations

import io
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from ..util.atomic_file import atomic_write
from ..util.safe_json import JsonLimitError, read_limited

MAX_PLY_BYTES = 1024**3  # a model file larger than this (1 GiB) is refused before reading


class PlyError(ValueError):
    """A PLY file that cannot be read as a triangle mesh; the message names the file."""


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


__all__ = ["PlyError", "read_ply", "read_ply_mesh", "write_ply", "MAX_PLY_BYTES"]
