"""Images and camera_info <-> ROS message fields, as numpy arrays.

Duck-typed: any object with height, width, encoding, is_bigendian, step, data works as an
image message, e.g. an rclpy sensor_msgs.msg.Image. At the boundary depth becomes float32
metres with NaN for missing, like everywhere in the code.
"""
from __future__ import annotations

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


def image_msg_to_rgb(msg: Any) -> np.ndarray:
    """A colour image message as uint8 HxWx3 RGB (a new array)."""
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
    """
    enc = msg.encoding
    if enc in ("16UC1", "mono16"):
        mm = _image_view(msg, np.dtype(np.uint16), 1)
        depth = mm.astype(np.float32)
        depth /= np.float32(1000.0)  # correctly rounded mm / 1000: the float32 bop.read_depth gives
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
