"""The images of a BOP scene: rgb (8-bit PNG or JPEG) and depth (uint16 PNG, times depth_scale =
mm), read into code units (uint8 RGB, float32 metres with NaN for missing) and written atomically.
A hostile file is refused before anything large is allocated (image_header.py).
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import cv2
import numpy as np

from ..core.geometry import MM
from ..util.atomic_file import atomic_write
from ..util.safe_json import JsonLimitError, read_limited
from .errors import BopFormatError
from .image_header import MAX_IMAGE_BYTES, check_image_header

MIN_MEDIAN_DEPTH = 0.01  # metres: a scene whose median depth is outside these bounds
MAX_MEDIAN_DEPTH = 20.0  # after scaling has the wrong depth_scale
RGB_EXTS = (".png", ".jpg", ".jpeg", ".tif")


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


__all__ = ["read_rgb", "read_depth", "write_rgb", "write_depth", "RGB_EXTS"]
