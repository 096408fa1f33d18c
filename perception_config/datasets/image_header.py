"""The size of an image read from its header, before anything is decoded.

A 20000 x 20000 PNG of a few kilobytes decodes into 1.2 GB (1.9 GB peak with the conversions):
`check_image_header` reads width and height from the PNG IHDR chunk, the JPEG SOFn segment or
the TIFF first IFD and refuses an image over MAX_IMAGE_SIDE pixels a side or MAX_IMAGE_PIXELS
pixels in all, and any other format, with a BopFormatError naming the file. Only then may the
caller decode it (OpenCV's own limit, 2^30 pixels, is far above what a frame needs).
"""
from __future__ import annotations

import os
import struct

from .errors import BopFormatError

MAX_IMAGE_SIDE = 16384  # pixels: a side longer than this is refused before decoding
MAX_IMAGE_PIXELS = 8192 * 8192  # 64 Mi pixels (e.g. 8192 x 8192): more is refused before decoding
MAX_IMAGE_BYTES = 256 * 1024 * 1024  # an image file larger than this is refused before reading

_PNG = b"\x89PNG\r\n\x1a\n"
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def _error(path: str | os.PathLike, msg: str) -> Exception:
    return BopFormatError(f"{path}: {msg}")


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD9)):  # no length
            i += 2
            continue
        (seg_len,) = struct.unpack(">H", data[i + 2:i + 4])
        if marker in _SOF:
            if i + 9 > len(data):
                return None
            h, w = struct.unpack(">HH", data[i + 5:i + 9])
            return w, h
        if marker == 0xDA or seg_len < 2:  # scan data before any frame header
            return None
        i += 2 + seg_len
    return None


def _tiff_size(data: bytes) -> tuple[int, int] | None:
    end = "<" if data[:2] == b"II" else ">"
    try:
        (ifd,) = struct.unpack(end + "I", data[4:8])
        (n,) = struct.unpack(end + "H", data[ifd:ifd + 2])
        size: dict[int, int] = {}
        for k in range(min(n, 4096)):
            tag, typ, _count, raw = struct.unpack(end + "HHI4s", data[ifd + 2 + 12 * k:ifd + 14 + 12 * k])
            if tag in (256, 257):
                size[tag] = struct.unpack(end + ("H" if typ == 3 else "I"), raw[:2] if typ == 3 else raw)[0]
    except struct.error:
        return None
    return (size[256], size[257]) if len(size) == 2 else None


def image_size(data: bytes) -> tuple[str, tuple[int, int] | None]:
    """(format, (width, height) or None when the header is unreadable); format "" if unknown."""
    if data.startswith(_PNG):
        if len(data) >= 24 and data[12:16] == b"IHDR":
            w, h = struct.unpack(">II", data[16:24])
            return "PNG", (w, h)
        return "PNG", None
    if data.startswith(b"\xff\xd8"):
        return "JPEG", _jpeg_size(data)
    if data[:4] in (b"II*\x00", b"MM\x00*"):
        return "TIFF", _tiff_size(data)
    return "", None


def check_image_header(data: bytes, path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of a PNG, JPEG or TIFF file's bytes within the limits; BopFormatError otherwise."""
    fmt, size = image_size(data)
    if not fmt:
        raise _error(path, "corrupt or unreadable image file: not a PNG, JPEG or TIFF image")
    if size is None:
        raise _error(path, f"corrupt {fmt} image: no readable width and height in its header")
    w, h = size
    if w < 1 or h < 1:
        raise _error(path, f"{fmt} image header declares an empty image ({w} x {h})")
    if w > MAX_IMAGE_SIDE or h > MAX_IMAGE_SIDE or w * h > MAX_IMAGE_PIXELS:
        raise _error(path, f"{fmt} image of {w} x {h} pixels is over the limit ({MAX_IMAGE_SIDE} a side, "
                           f"{MAX_IMAGE_PIXELS} pixels); refused before decoding")
    return w, h
