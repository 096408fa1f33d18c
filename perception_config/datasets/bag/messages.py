"""Images and camera_info <-> ROS message fields, as numpy arrays.

Duck-typed: any object with height, width, encoding, is_bigendian, step, data works as an
image message, e.g. an rclpy sensor_msgs.msg.Image; one with format and data (and no encoding)
as a sensor_msgs/CompressedImage: jpeg / png (image_transport `compressed`) or the
`compressedDepth` format (compressed_depth_image_transport: a 12-byte header, int32 format and
two float32 depth quantisation parameters, then a PNG of 16UC1 millimetres or, for 32FC1, of
the quantised inverse depth q with depth = A / (q - B), q = 0 missing), decoded with OpenCV.
At the boundary depth becomes float32 metres with NaN for missing, like everywhere in the code.
"""
from __future__ import annotations

import struct
from types import SimpleNamespace
from typing import Any

import numpy as np

from .errors import ImageFormatError

OPTICAL_FRAME = "camera_color_optical_frame"

COLOR_ENCODINGS = {  # encoding -> (channels, reverse channel order)
    "rgb8": (3, False),
    "bgr8": (3, True),
    "rgba8": (4, False),
    "bgra8": (4, True),
    "mono8": (1, False),
    "8UC3": (3, True),  # OpenCV's CV_8UC3 is BGR
}
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")


def _image_view(msg: Any, dtype: np.dtype, channels: int) -> np.ndarray:
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    enc = msg.encoding
    if h <= 0 or w <= 0:
        raise ImageFormatError(f"empty {enc} image ({w}x{h})")
    row = w * channels * dtype.itemsize
    if step < row:
        raise ImageFormatError(
            f"step {step} is smaller than width {w} x {channels * dtype.itemsize} bytes per {enc} pixel = {row}")
    n = len(msg.data)
    if n != step * h:
        raise ImageFormatError(f"{enc} image {w}x{h} has {n} data bytes, "
                               f"expected step x height = {step} x {h} = {step * h}")
    buf = np.frombuffer(msg.data, dtype=np.uint8).reshape(h, step)[:, :row]
    if dtype.itemsize > 1:
        dtype = dtype.newbyteorder(">" if msg.is_bigendian else "<")
        buf = np.ascontiguousarray(buf) if (step % dtype.itemsize) else buf
    arr = buf.view(dtype)
    return arr.reshape(h, w, channels) if channels > 1 else arr.reshape(h, w)


def is_compressed(msg: Any) -> bool:
    """True for a sensor_msgs/CompressedImage (format + data, no encoding)."""
    return not hasattr(msg, "encoding") and hasattr(msg, "format")


def _imdecode(data: Any, what: str) -> np.ndarray:
    import cv2

    buf = np.frombuffer(bytes(data), dtype=np.uint8)
    img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
    if img is None:
        raise ImageFormatError(f"{what}: {buf.size} bytes that OpenCV cannot decode as an image")
    return img


def compressed_image_fields(msg: Any, depth: bool) -> dict:
    """The sensor_msgs/Image fields (minus header) of a CompressedImage: colour as rgb8 (mono8 stays
    mono8), depth as 16UC1 millimetres or 32FC1 metres (NaN = missing). ImageFormatError when the
    data does not decode or the format is not one we read (compressedDepth rvl)."""
    fmt = str(msg.format)
    low = fmt.lower()
    data = bytes(msg.data)
    if "compresseddepth" in low:
        if "rvl" in low:
            raise ImageFormatError(f"CompressedImage format {fmt!r}: compressedDepth rvl is not supported "
                                   "(republish with the png format)")
        if len(data) < 12:
            raise ImageFormatError(f"compressedDepth image of {len(data)} bytes: shorter than its 12-byte header")
        _kind, quant_a, quant_b = struct.unpack("<iff", data[:12])
        q = _imdecode(data[12:], f"compressedDepth ({fmt!r}) PNG")
        if q.dtype != np.uint16 or q.ndim != 2:
            raise ImageFormatError(f"compressedDepth ({fmt!r}) PNG is {q.dtype} with shape {q.shape}, "
                                   "expected one 16-bit channel")
        source = low.split(";")[0].strip()
        if source == "32fc1":
            with np.errstate(divide="ignore", invalid="ignore"):
                d = (np.float32(quant_a) / (q.astype(np.float32) - np.float32(quant_b))).astype("<f4")
            d[q == 0] = np.nan
            return _fields(d, "32FC1")
        if source in ("16uc1", "mono16"):
            return _fields(q.astype("<u2"), "16UC1")
        raise ImageFormatError(f"compressedDepth format {fmt!r}: source encoding {source!r} is not 16UC1 or 32FC1")
    img = _imdecode(data, f"CompressedImage ({fmt!r})")
    if depth:
        if img.dtype != np.uint16 or img.ndim != 2:
            raise ImageFormatError(f"depth CompressedImage ({fmt!r}) decodes to {img.dtype} {img.shape}, "
                                   "expected a 16-bit single-channel PNG of millimetres")
        return _fields(img.astype("<u2"), "16UC1")
    if img.dtype != np.uint8:
        raise ImageFormatError(f"colour CompressedImage ({fmt!r}) decodes to {img.dtype}, expected 8-bit")
    if img.ndim == 2:
        return _fields(img, "mono8")
    rgb = img[:, :, 2::-1]  # OpenCV decodes to BGR(A)
    if "compressed rgb8" in low:  # pixels were encoded in RGB order
        rgb = img[:, :, :3]
    return _fields(np.ascontiguousarray(rgb), "rgb8")


def _fields(a: np.ndarray, encoding: str) -> dict:
    a = np.ascontiguousarray(a)
    h, w = a.shape[:2]
    return {"height": h, "width": w, "encoding": encoding, "is_bigendian": 0, "step": a.strides[0],
            "data": a.tobytes()}


def _as_image(msg: Any, depth: bool) -> Any:
    return SimpleNamespace(**compressed_image_fields(msg, depth)) if is_compressed(msg) else msg


def image_msg_to_rgb(msg: Any) -> np.ndarray:
    """A colour image message (Image or CompressedImage) as uint8 HxWx3 RGB (a new array)."""
    msg = _as_image(msg, depth=False)
    enc = msg.encoding
    if enc not in COLOR_ENCODINGS:
        raise ImageFormatError(f"unsupported colour encoding {enc!r} (supported: {', '.join(COLOR_ENCODINGS)})")
    channels, reverse = COLOR_ENCODINGS[enc]
    a = _image_view(msg, np.dtype(np.uint8), channels)
    if channels == 1:
        return np.repeat(a[:, :, None], 3, axis=2)
    a = a[:, :, :3]
    if reverse:
        a = a[:, :, ::-1]
    return np.ascontiguousarray(a)


def image_msg_to_depth(msg: Any) -> np.ndarray:
    """A depth image message as float32 HxW metres, NaN where the sensor had no depth.

    16UC1 / mono16 are millimetres with 0 = missing; 32FC1 is metres with NaN, +-inf or 0 = missing.
    A CompressedImage (compressedDepth, or a 16-bit PNG of millimetres) is decoded first.
    """
    msg = _as_image(msg, depth=True)
    enc = msg.encoding
    if enc in ("16UC1", "mono16"):
        mm = _image_view(msg, np.dtype(np.uint16), 1)
        depth = mm.astype(np.float32)
        depth /= np.float32(1000.0)  # correctly rounded mm / 1000: the float32 bop_images.read_depth gives
        depth[mm == 0] = np.nan
        return depth
    if enc == "32FC1":
        depth = _image_view(msg, np.dtype(np.float32), 1).astype(np.float32)  # native order, a copy
        depth[~(np.isfinite(depth) & (depth > 0))] = np.nan
        return depth
    raise ImageFormatError(f"unsupported depth encoding {enc!r} (supported: {', '.join(DEPTH_ENCODINGS)})")


def rgb_to_image_fields(rgb: np.ndarray) -> dict:
    """Fields (minus header) of an rgb8 sensor_msgs/Image for uint8 HxWx3 RGB."""
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    h, w = rgb.shape[:2]
    return {"height": h, "width": w, "encoding": "rgb8", "is_bigendian": 0, "step": w * 3, "data": rgb.tobytes()}


def depth_to_image_fields(depth: np.ndarray, encoding: str = "16UC1") -> dict:
    """Fields (minus header) of a depth sensor_msgs/Image for float32 metres with NaN = missing.

    16UC1: millimetres rounded to the nearest mm; missing (NaN), <= 0 and beyond 65.535 m
    become 0, the ROS convention for "no depth". 32FC1: metres, missing stays NaN.
    """
    depth = np.asarray(depth, dtype=np.float32)
    h, w = depth.shape
    if encoding == "16UC1":
        with np.errstate(invalid="ignore"):
            mm = np.rint(depth * np.float32(1000.0))
            bad = ~np.isfinite(mm) | (mm <= 0) | (mm > 65535)
        mm[bad] = 0
        data = mm.astype("<u2").tobytes()
        return {"height": h, "width": w, "encoding": "16UC1", "is_bigendian": 0, "step": w * 2, "data": data}
    if encoding == "32FC1":
        d = depth.astype("<f4")
        return {"height": h, "width": w, "encoding": "32FC1", "is_bigendian": 0, "step": w * 4, "data": d.tobytes()}
    raise ValueError(f"depth_encoding must be '16UC1' or '32FC1', got {encoding!r}")


def camera_info_fields(K: np.ndarray, width: int, height: int) -> dict:
    """Fields (minus header) of a sensor_msgs/CameraInfo of an undistorted pinhole camera."""
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    P = np.zeros((3, 4))
    P[:, :3] = K
    return {
        "height": int(height), "width": int(width), "distortion_model": "plumb_bob",
        "d": [0.0] * 5, "k": K.flatten().tolist(), "r": np.eye(3).flatten().tolist(),
        "p": P.flatten().tolist(), "binning_x": 0, "binning_y": 0,
        "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
    }


def header_fields(stamp_ns: int, frame_id: str = OPTICAL_FRAME) -> dict:
    return {"stamp": {"sec": stamp_ns // 1_000_000_000, "nanosec": stamp_ns % 1_000_000_000}, "frame_id": frame_id}


def header_stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)
