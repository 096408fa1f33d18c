"""BOP scenes recorded as rosbag2-compatible MCAP bags, and rosbag2 MCAP bags read back as Frames.

This module does not import rclpy: it writes and reads CDR with `mcap` + `mcap-ros2-support`
from the schema texts shipped in `ros2msg_schemas.py`.

What a bag written here holds (one *frame* = these messages, all with the same header stamp)
--------------------------------------------------------------------------------------------
=============================  =============================================  ==========================
topic                          type                                           content
=============================  =============================================  ==========================
/camera/color/image_raw        sensor_msgs/msg/Image                          rgb8
/camera/depth/image_raw        sensor_msgs/msg/Image                          16UC1 millimetres, 0 = no
                                                                              depth (or 32FC1 metres,
                                                                              NaN = no depth, on request)
/camera/camera_info            sensor_msgs/msg/CameraInfo                     K, P = [K|0], plumb_bob with
                                                                              zero distortion, size
/perception/ground_truth       perception_config_interfaces/msg/ObjectPoses   model-to-camera poses in
                                                                              metres, BOP obj ids as
                                                                              strings
/perception/frame_info         std_msgs/msg/String                            JSON {"stamp_ns", "scene_id",
                                                                              "im_id", "index"}: maps the
                                                                              frame back to its BOP image
=============================  =============================================  ==========================

* Ground truth: position = t, orientation = the quaternion of the rotation nearest to R (BOP
  stores R with a few digits, orthonormal only to ~1e-4; a quaternion can carry only a rotation).
* Frame ids: every header says `camera_color_optical_frame`. BOP depth is registered to the
  colour image, so one optical frame serves colour, depth, camera_info and the ground truth.
* Clock: frame i is stamped `start_time_ns + i / rate_hz` (default start 1.7e9 s, a fixed epoch,
  so the same dataset always gives the same bag); log_time = publish_time = the header stamp.
* Why a frame_info topic (not a MCAP metadata record): it is written with each frame, so it
  survives an interrupted recording, a replay node can republish it, and ROS tools see it.
  The recording's parameters go into a MCAP metadata record named `perception_config`.
* Profile `ros2`, message encoding `cdr`, schemas `ros2msg` (rosbag2's complete message
  definitions) named `sensor_msgs/msg/Image` etc., channel metadata with `offered_qos_profiles`
  and `topic_type_hash` (RIHS01) like rosbag2 writes, and the bag's metadata embedded in a
  MCAP metadata record `rosbag2` (so `ros2 bag info file.mcap` works on the file alone).
* Each frame is one MCAP chunk (zstd by default), flushed to the OS when the frame is complete:
  a recorder that is killed loses at most the frame it was writing; `read_bag` recovers the
  complete frames before the cut. Ctrl-C / SIGTERM are deferred to the end of the current frame,
  then the file is finished properly (summary, footer, metadata.yaml) and `BagWriteInterrupted`
  (a KeyboardInterrupt) is raised.

Where metadata.yaml goes
------------------------
A rosbag2 bag is a directory holding `<name>_0.mcap` and `metadata.yaml`.
* `out_path` not ending in `.mcap` is that directory: it is created (it must not exist or must be
  empty) and gets `<dirname>_0.mcap` plus `metadata.yaml`.
* `out_path` ending in `.mcap` is the file itself. Its directory also gets a `metadata.yaml`
  (making the directory a rosbag2 bag) only when no other `.mcap` file is there and no
  `metadata.yaml` describing another file is there; otherwise the `.mcap` stands alone (it is a
  complete bag on its own: rosbag2 opens a single .mcap file, so do `read_bag` and MCAP tools).

Reading
-------
`read_bag` reads our bags and rosbag2 MCAP recordings of real RGB-D cameras: topics default to
ours, and when those are absent the colour, depth and camera_info topics are found by message
type and name (e.g. RealSense `/camera/camera/color/image_raw`,
`/camera/camera/aligned_depth_to_color/image_raw`, `/camera/camera/color/camera_info`).
Colour rgb8, bgr8, rgba8, bgra8, mono8, 8UC3 (as BGR); depth 16UC1 / mono16 (millimetres, 0 = missing) or
32FC1 (metres, NaN/inf/0 = missing). Messages are grouped into frames by header stamp (exactly,
or the nearest within `sync_tolerance_s` for drivers that stamp colour and depth apart); a
colour image without its depth/camera_info (or ground truth, when the bag has it) is dropped,
and one `BagWarning` at the end says how many.
At the boundary depth becomes float32 metres with NaN for missing, like everywhere in the code.

A truncated or damaged file (no footer: the recorder was killed, the copy was cut) is read up
to the damage: the complete frames before it are yielded, then a `BagTruncatedWarning` names
the file and the byte offset; with `strict=True` a `BagTruncatedError` is raised instead,
before any frame. Data that contradicts itself (image step/size/encoding, colour vs depth size,
camera_info size) raises `BagFormatError` naming the file, topic, stamp and problem.
"""
from __future__ import annotations

import json
import math
import os
import signal
import threading
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, NamedTuple

import numpy as np
import yaml

from ..geometry import Pose, matrix_from_quaternion, nearest_rotation, quaternion_from_matrix
from ..scene import Frame, SceneObject
from .ros2msg_schemas import SCHEMAS, TYPE_HASHES

IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
OBJECT_POSES = "perception_config_interfaces/msg/ObjectPoses"
STRING = "std_msgs/msg/String"

COLOR_TOPIC = "/camera/color/image_raw"
DEPTH_TOPIC = "/camera/depth/image_raw"
CAMERA_INFO_TOPIC = "/camera/camera_info"
GROUND_TRUTH_TOPIC = "/perception/ground_truth"
FRAME_INFO_TOPIC = "/perception/frame_info"
OPTICAL_FRAME = "camera_color_optical_frame"

RECORDING_EPOCH_NS = 1_700_000_000 * 1_000_000_000  # fixed start of the recording clock
ROSBAG2_VERSION = 9
# Chunks are closed at every frame boundary (Writer.flush); this only caps a single huge frame.
_CHUNK_SIZE = 256 * 1024 * 1024
_MAGIC = b"\x89MCAP0\r\n"
_SQLITE_MAGIC = b"SQLite format 3\x00"

COLOR_ENCODINGS = {  # encoding -> (channels, reverse channel order)
    "rgb8": (3, False),
    "bgr8": (3, True),
    "rgba8": (4, False),
    "bgra8": (4, True),
    "mono8": (1, False),
    "8UC3": (3, True),  # OpenCV's CV_8UC3 is BGR
}
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")


class BagFormatError(ValueError):
    """A bag that cannot be read as RGB-D frames; the message names the file, topic and problem."""


class BagTruncatedError(BagFormatError):
    """The MCAP file has no valid end (footer): a recording that was cut or killed."""


class BagWarning(UserWarning):
    pass


class BagTruncatedWarning(BagWarning):
    """Frames were read from a truncated file up to the damage; the rest is lost."""


class ImageFormatError(ValueError):
    """An image message whose encoding, step or size does not add up."""


class BagWriteInterrupted(KeyboardInterrupt):
    """Raised by the writers after Ctrl-C / SIGTERM, once the bag has been finished cleanly."""

    def __init__(self, path: Path, frames: int, signum: int):
        super().__init__(f"recording interrupted by {signal.Signals(signum).name} after {frames} frames; "
                         f"{path} is complete and readable")
        self.path = path
        self.frames = frames
        self.signum = signum


class BagMessage(NamedTuple):
    """A raw serialized message, for a replay node that publishes without decoding."""

    topic: str
    type: str  # schema name, e.g. sensor_msgs/msg/Image
    log_time_ns: int
    data: bytes  # CDR, as a ROS 2 publisher would send it


# --------------------------------------------------------------------------------------------
# Images <-> messages (duck-typed: any object with height, width, encoding, is_bigendian, step,
# data works, e.g. an rclpy sensor_msgs.msg.Image)
# --------------------------------------------------------------------------------------------

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
        raise ImageFormatError(f"{enc} image {w}x{h} has {n} data bytes, expected step x height = {step} x {h} = {step * h}")
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


def _header(stamp_ns: int, frame_id: str = OPTICAL_FRAME) -> dict:
    return {"stamp": {"sec": stamp_ns // 1_000_000_000, "nanosec": stamp_ns % 1_000_000_000}, "frame_id": frame_id}


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


# --------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------

def _metadata_yaml_files(meta: Path) -> list[str] | None:
    try:
        info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
        return [Path(p).name for p in info.get("relative_file_paths", [])]
    except Exception:
        return None


def _resolve_output(out_path: str | os.PathLike) -> tuple[Path, Path | None]:
    """(mcap file, metadata.yaml or None); see the module docstring."""
    out = Path(out_path)
    if out.suffix == ".mcap":
        if out.is_dir():
            raise ValueError(f"{out} is a directory; give a bag directory without the .mcap suffix or a file path")
        out.parent.mkdir(parents=True, exist_ok=True)
        others = [p for p in out.parent.glob("*.mcap") if p.name != out.name]
        meta = out.parent / "metadata.yaml"
        if others or (meta.exists() and _metadata_yaml_files(meta) != [out.name]):
            return out, None
        return out, meta
    if out.exists():
        if not out.is_dir():
            raise ValueError(f"{out} exists and is not a directory (a .mcap path writes a single file)")
        if any(out.iterdir()):
            raise ValueError(f"bag directory {out} exists and is not empty; remove it or choose another output")
    out.mkdir(parents=True, exist_ok=True)
    return out / f"{out.name}_0.mcap", out / "metadata.yaml"


class _DeferSignals:
    """Turn SIGINT/SIGTERM into a flag checked between frames (main thread only).

    A second signal while the first is pending raises KeyboardInterrupt at once; the writer's
    finally block still finishes the file.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.signum: int | None = None
        self._previous: dict[int, Any] = {}

    def _handler(self, signum: int, _frame: Any) -> None:
        if self.signum is not None:
            raise KeyboardInterrupt
        self.signum = signum

    def __enter__(self) -> "_DeferSignals":
        if threading.current_thread() is threading.main_thread():
            for s in self.SIGNALS:
                prev = signal.getsignal(s)
                if prev is signal.SIG_IGN or prev is None:
                    continue
                self._previous[s] = prev
                signal.signal(s, self._handler)
        return self

    def __exit__(self, *exc: Any) -> None:
        for s, prev in self._previous.items():
            signal.signal(s, prev)
        self._previous.clear()


class BagWriter:
    """Write Frames one by one into a rosbag2-compatible MCAP bag (see the module docstring).

    Use as a context manager; `write(frame)` stamps frame i at `start_time_ns + i / rate_hz`
    (the Frame's own stamp is ignored: a recording has its own clock). `close()` finishes the
    file (summary, footer) and writes metadata.yaml; call it also after errors (the context
    manager does), the bag is then valid with the frames written so far.
    """

    def __init__(
        self,
        out_path: str | os.PathLike,
        rate_hz: float = 10.0,
        *,
        start_time_ns: int = RECORDING_EPOCH_NS,
        compression: str = "zstd",
        depth_encoding: str = "16UC1",
        custom_data: dict[str, str] | None = None,
    ) -> None:
        from mcap.writer import CompressionType
        from mcap.writer import Writer as McapWriter
        from mcap_ros2._dynamic import serialize_dynamic

        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"rate_hz must be a positive number, got {rate_hz}")
        if depth_encoding not in ("16UC1", "32FC1"):
            raise ValueError(f"depth_encoding must be '16UC1' or '32FC1', got {depth_encoding!r}")
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE, "": CompressionType.NONE}
        if compression not in comp:
            raise ValueError(f"compression must be one of zstd, lz4, none; got {compression!r}")
        self.rate_hz = float(rate_hz)
        self.start_time_ns = int(start_time_ns)
        self.depth_encoding = depth_encoding
        self.custom_data = {str(k): str(v) for k, v in (custom_data or {}).items()}
        self.path, self.metadata_path = _resolve_output(out_path)
        self.frames = 0
        self._counts: dict[str, int] = {}
        self._first_ns: int | None = None
        self._last_ns: int | None = None
        self._closed = False

        self._file = open(self.path, "wb")
        try:
            from .. import __version__

            self._writer = McapWriter(self._file, chunk_size=_CHUNK_SIZE, compression=comp[compression])
            self._writer.start(profile="ros2", library=f"perception_config {__version__}")
            self._topics = [
                (FRAME_INFO_TOPIC, STRING), (CAMERA_INFO_TOPIC, CAMERA_INFO), (GROUND_TRUTH_TOPIC, OBJECT_POSES),
                (DEPTH_TOPIC, IMAGE), (COLOR_TOPIC, IMAGE),
            ]
            self._channels: dict[str, int] = {}
            self._encoders: dict[str, Callable[[Any], bytes]] = {}
            schema_ids: dict[str, int] = {}
            for topic, typ in self._topics:
                if typ not in schema_ids:
                    schema_ids[typ] = self._writer.register_schema(typ, "ros2msg", SCHEMAS[typ].encode())
                    self._encoders[typ] = serialize_dynamic(typ, SCHEMAS[typ])[typ]
                self._channels[topic] = self._writer.register_channel(
                    topic, "cdr", schema_ids[typ],
                    metadata={"offered_qos_profiles": "[]", "topic_type_hash": TYPE_HASHES[typ]},
                )
                self._counts[topic] = 0
            self._writer.add_metadata("perception_config", {
                "rate_hz": repr(self.rate_hz), "start_time_ns": str(self.start_time_ns),
                "depth_encoding": depth_encoding, "frame_id": OPTICAL_FRAME,
                "frame_info_topic": FRAME_INFO_TOPIC, **self.custom_data,
            })
            self._writer.flush()
        except BaseException:
            self._file.close()
            raise

    def stamp_ns(self, index: int) -> int:
        return self.start_time_ns + round(index * 1e9 / self.rate_hz)

    def _messages(self, frame: Frame, stamp_ns: int) -> list[tuple[str, bytes]]:
        header = _header(stamp_ns)
        h, w = frame.height, frame.width
        ids, poses = [], []
        for o in frame.objects:
            if o.gt is None:
                continue
            q = quaternion_from_matrix(nearest_rotation(o.gt.R))
            t = o.gt.t
            ids.append(str(o.obj_id))
            poses.append({"position": {"x": float(t[0]), "y": float(t[1]), "z": float(t[2])},
                          "orientation": {"x": float(q[0]), "y": float(q[1]), "z": float(q[2]), "w": float(q[3])}})
        info = {"stamp_ns": stamp_ns, "scene_id": int(frame.scene_id), "im_id": int(frame.im_id), "index": self.frames}
        enc = self._encoders
        return [
            (FRAME_INFO_TOPIC, enc[STRING]({"data": json.dumps(info)})),
            (CAMERA_INFO_TOPIC, enc[CAMERA_INFO]({"header": header, **camera_info_fields(frame.K, w, h)})),
            (GROUND_TRUTH_TOPIC, enc[OBJECT_POSES]({"header": header, "object_ids": ids, "poses": poses})),
            (DEPTH_TOPIC, enc[IMAGE]({"header": header, **depth_to_image_fields(frame.depth, self.depth_encoding)})),
            (COLOR_TOPIC, enc[IMAGE]({"header": header, **rgb_to_image_fields(frame.rgb)})),
        ]

    def write(self, frame: Frame) -> int:
        """Append one frame (all its messages, one chunk, flushed); returns its stamp in ns."""
        if self._closed:
            raise ValueError(f"{self.path}: the bag writer is closed")
        stamp = self.stamp_ns(self.frames)
        msgs = self._messages(frame, stamp)  # serialise everything first: no half-written frames
        for topic, data in msgs:
            self._writer.add_message(self._channels[topic], log_time=stamp, data=data,
                                     publish_time=stamp, sequence=self._counts[topic])
            self._counts[topic] += 1
        self._writer.flush()  # closes the chunk: a crash from here on cannot lose this frame
        self._first_ns = stamp if self._first_ns is None else self._first_ns
        self._last_ns = stamp
        self.frames += 1
        return stamp

    def rosbag2_metadata(self) -> dict:
        start = self._first_ns or 0
        duration = (self._last_ns - self._first_ns) if self._first_ns is not None else 0
        count = sum(self._counts.values())
        return {
            "version": ROSBAG2_VERSION,
            "storage_identifier": "mcap",
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": count,
            "topics_with_message_count": [
                {"topic_metadata": {"name": topic, "type": typ, "serialization_format": "cdr",
                                    "offered_qos_profiles": [], "type_description_hash": TYPE_HASHES[typ]},
                 "message_count": self._counts[topic]}
                for topic, typ in self._topics
            ],
            "compression_format": "",
            "compression_mode": "",
            "relative_file_paths": [self.path.name],
            "files": [{"path": self.path.name, "starting_time": {"nanoseconds_since_epoch": start},
                       "duration": {"nanoseconds": duration}, "message_count": count}],
            "custom_data": self.custom_data or None,
            "ros_distro": os.environ.get("ROS_DISTRO", ""),
        }

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            info = self.rosbag2_metadata()
            self._writer.add_metadata("rosbag2", {"serialized_metadata": yaml.safe_dump(info, sort_keys=False)})
            self._writer.finish()
        finally:
            self._file.close()
        if self.metadata_path is not None:
            tmp = self.metadata_path.with_name(self.metadata_path.name + ".tmp")
            tmp.write_text(yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False))
            os.replace(tmp, self.metadata_path)

    def __enter__(self) -> "BagWriter":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def write_frames(
    frames: Iterable[Frame],
    out_path: str | os.PathLike,
    rate_hz: float = 10.0,
    *,
    progress: bool = False,
    total: int | None = None,
    **writer_options: Any,
) -> int:
    """Record Frames into a bag (see `BagWriter` for the options); returns the number written.

    Ctrl-C or SIGTERM stop the recording after the current frame; the bag is finished cleanly
    and `BagWriteInterrupted` (a KeyboardInterrupt carrying `.frames` and `.path`) is raised.
    """
    from tqdm import tqdm

    with _DeferSignals() as sig:
        writer = BagWriter(out_path, rate_hz, **writer_options)
        try:
            with tqdm(total=total, disable=not progress, unit="frame", desc=f"recording {writer.path.name}") as bar:
                for frame in frames:
                    if sig.signum is not None:
                        break
                    writer.write(frame)
                    bar.update(1)
                    if sig.signum is not None:
                        break
        finally:
            writer.close()
        if sig.signum is not None:
            raise BagWriteInterrupted(writer.path, writer.frames, sig.signum)
    return writer.frames


def write_bag(
    dataset_dir: str | os.PathLike,
    out_path: str | os.PathLike,
    split: str = "test",
    rate_hz: float = 10.0,
    progress: bool = True,
    *,
    compression: str = "zstd",
    depth_encoding: str = "16UC1",
) -> int:
    """Record every image of a BOP dataset split as a rosbag2-compatible MCAP bag.

    Returns the number of frames written. Topics, units and layout are in the module
    docstring: colour rgb8, depth 16UC1 in millimetres with 0 = missing depth (BOP depth is
    rounded to whole millimetres; `depth_encoding="32FC1"` keeps metres as float32 with NaN
    = missing), camera_info, ground-truth ObjectPoses in metres, and /perception/frame_info
    mapping each stamp to its BOP (scene_id, im_id). `out_path`: a bag directory (created, with
    `<name>_0.mcap` and metadata.yaml) or a `.mcap` file path (metadata.yaml beside it only when
    it is the only bag in that directory). Ctrl-C / SIGTERM finish the file cleanly, then raise
    `BagWriteInterrupted`.
    """
    from .bop import BopDataset

    ds = BopDataset(dataset_dir, split=split)
    keys = list(ds.image_keys())
    frames = (ds.load_frame(scene_id, im_id, with_models=False) for scene_id, im_id in keys)
    return write_frames(
        frames, out_path, rate_hz, progress=progress, total=len(keys), compression=compression,
        depth_encoding=depth_encoding,
        custom_data={"dataset": Path(dataset_dir).resolve().name, "split": split, "frames": str(len(keys))},
    )


# --------------------------------------------------------------------------------------------
# Reading: files, damage, raw messages
# --------------------------------------------------------------------------------------------

def _bag_files(path: str | os.PathLike) -> list[Path]:
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"no such bag: {p}")
    if p.is_file():
        return [p]
    meta = p / "metadata.yaml"
    files: list[Path] = []
    if meta.is_file():
        try:
            info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
            storage = info.get("storage_identifier", "mcap")
            if storage != "mcap":
                raise BagFormatError(f"{p}: rosbag2 storage {storage!r} is not supported, only mcap "
                                     "(convert with `ros2 bag convert`)")
            files = [p / Path(f).name for f in info.get("relative_file_paths", [])]
        except BagFormatError:
            raise
        except Exception as exc:
            raise BagFormatError(f"{meta}: not a readable rosbag2 metadata.yaml ({exc})") from None
        missing = [str(f) for f in files if not f.is_file()]
        if missing:
            raise BagFormatError(f"{p}: metadata.yaml lists files that are missing: {missing}")
    if not files:
        files = sorted(p.glob("*.mcap"))
    if not files:
        raise BagFormatError(f"{p}: no .mcap file in this directory")
    return files


class _Schema(NamedTuple):
    name: str
    encoding: str
    data: bytes


class _ChannelInfo(NamedTuple):
    id: int
    topic: str
    message_encoding: str
    schema: _Schema | None


class _McapFile:
    """One MCAP file: indexed and complete, or damaged (read in file order up to the damage)."""

    def __init__(self, path: Path):
        from mcap.reader import SeekingReader

        self.path = path
        self.size = path.stat().st_size
        self.damage: str | None = None  # why the file is not complete
        self.damage_offset: int | None = None  # bytes read fine before the damage
        self._channels: dict[int, _ChannelInfo] | None = None
        self.counts: dict[int, int] = {}
        self.times: list[int] = []
        self.metadata: dict[str, dict[str, str]] = {}
        with open(path, "rb") as f:
            head = f.read(len(_SQLITE_MAGIC))
            if head.startswith(_SQLITE_MAGIC):
                raise BagFormatError(f"{path}: a rosbag2 sqlite3 (.db3) file, not MCAP; convert it with "
                                     "`ros2 bag convert` to mcap storage")
            if not head.startswith(_MAGIC):
                if len(head) < len(_MAGIC) and _MAGIC.startswith(head):
                    raise BagTruncatedError(f"{path}: truncated before its first MCAP record ({self.size} bytes)")
                raise BagFormatError(f"{path}: not an MCAP file (bad magic bytes)")
            f.seek(max(0, self.size - len(_MAGIC)))
            tail = f.read()
            self.summary = None
            self.header_profile = ""
            self.header_library = ""
            if self.size < 2 * len(_MAGIC) + 29 or tail != _MAGIC:
                self.damage = "no MCAP footer: the recording was cut or the recorder was killed"
            else:
                try:
                    f.seek(0)
                    reader = SeekingReader(f)
                    self.summary = reader.get_summary()
                    h = reader.get_header()
                    self.header_profile, self.header_library = h.profile, h.library
                except Exception as exc:  # damaged footer/summary
                    self.summary = None
                    self.damage = f"unreadable MCAP summary/footer ({exc})"

    @property
    def complete(self) -> bool:
        return self.damage is None

    # -- sequential scan: damaged files and files without an index ------------------------------
    def _record_batches(self) -> Iterator[list]:
        """The file's records in file order, a chunk's records as one batch (its CRC checked).

        Stops at the first record that cannot be read and notes the damage and its offset.
        """
        from mcap.records import Chunk, Footer, Header
        from mcap.stream_reader import StreamReader, breakup_chunk

        with open(self.path, "rb") as f:
            records = StreamReader(f, emit_chunks=True).records
            good = len(_MAGIC)
            while True:
                try:
                    rec = next(records)
                    batch = breakup_chunk(rec, validate_crc=True) if isinstance(rec, Chunk) else [rec]
                    good = f.tell()
                except StopIteration:
                    return
                except Exception as exc:  # cut or corrupt: everything before `good` was intact
                    if self.damage is None:
                        self.damage = f"damaged MCAP data ({type(exc).__name__}: {exc})"
                    self.damage_offset = good
                    return
                if isinstance(rec, Header):
                    self.header_profile, self.header_library = rec.profile, rec.library
                yield batch
                if isinstance(rec, Footer):
                    return

    def channels(self) -> dict[int, _ChannelInfo]:
        """Channels by id; also fills message counts, time range and metadata records."""
        if self._channels is not None:
            return self._channels
        chans: dict[int, _ChannelInfo] = {}
        counts: dict[int, int] = {}
        times: list[int] = []
        metadata: dict[str, dict[str, str]] = {}
        if self.summary is not None and self.summary.statistics is not None:
            schemas = {i: _Schema(s.name, s.encoding, s.data) for i, s in self.summary.schemas.items()}
            for i, c in self.summary.channels.items():
                chans[i] = _ChannelInfo(i, c.topic, c.message_encoding, schemas.get(c.schema_id))
            st = self.summary.statistics
            counts = dict(st.channel_message_counts)
            if st.message_count:
                times = [st.message_start_time, st.message_end_time]
            metadata = self._read_metadata_indexed()
        else:
            from mcap.records import Channel, Message, Metadata, Schema

            scm: dict[int, _Schema] = {}
            for batch in self._record_batches():
                for r in batch:
                    if isinstance(r, Schema):
                        scm[r.id] = _Schema(r.name, r.encoding, r.data)
                    elif isinstance(r, Channel):
                        chans[r.id] = _ChannelInfo(r.id, r.topic, r.message_encoding, scm.get(r.schema_id))
                    elif isinstance(r, Message):
                        counts[r.channel_id] = counts.get(r.channel_id, 0) + 1
                        times = [min(times[0], r.log_time), max(times[1], r.log_time)] if times else [r.log_time] * 2
                    elif isinstance(r, Metadata):
                        metadata[r.name] = dict(r.metadata)
        self._channels, self.counts, self.times, self.metadata = chans, counts, times, metadata
        return chans

    def _read_metadata_indexed(self) -> dict[str, dict[str, str]]:
        from mcap.reader import SeekingReader

        out: dict[str, dict[str, str]] = {}
        try:
            with open(self.path, "rb") as f:
                for m in SeekingReader(f).iter_metadata():
                    out[m.name] = dict(m.metadata)
        except Exception:
            pass
        return out

    def messages(self, channel_ids: set[int] | None) -> Iterator[tuple[_ChannelInfo, int, bytes]]:
        """(channel, log_time_ns, data): log-time order when indexed, else file order."""
        chans = self.channels()
        if self.summary is not None and self.summary.chunk_indexes:
            from mcap.reader import SeekingReader

            topics = None if channel_ids is None else sorted({chans[i].topic for i in channel_ids})
            if topics == []:
                return
            with open(self.path, "rb") as f:
                it = SeekingReader(f, validate_crcs=True).iter_messages(topics=topics, log_time_order=True)
                while True:
                    try:
                        _schema, channel, message = next(it)
                    except StopIteration:
                        return
                    except Exception as exc:
                        raise BagFormatError(f"{self.path}: damaged MCAP data ({type(exc).__name__}: {exc})") from None
                    yield chans[channel.id], message.log_time, message.data
        from mcap.records import Message

        for batch in self._record_batches():
            for r in batch:
                if isinstance(r, Message) and (channel_ids is None or r.channel_id in channel_ids):
                    ch = chans.get(r.channel_id)
                    if ch is not None:
                        yield ch, r.log_time, r.data

    def truncation_message(self) -> str:
        intact = f"; its first {self.damage_offset} of {self.size} bytes are intact" if self.damage_offset else ""
        return f"{self.path} is truncated or damaged ({self.damage}){intact}"


def _schema_name(ch: _ChannelInfo) -> str:
    return ch.schema.name if ch.schema is not None else ""


def _make_decoder(ch: _ChannelInfo, path: Path) -> Callable[[bytes], Any]:
    """CDR decoder of a channel, from the bag's own schema, or ours for a type we ship."""
    from mcap_ros2._dynamic import generate_dynamic

    if ch.message_encoding != "cdr":
        raise BagFormatError(f"{path}: topic {ch.topic} has message encoding {ch.message_encoding!r}, not cdr")
    name = _schema_name(ch)
    text = None
    if ch.schema is not None and ch.schema.encoding == "ros2msg" and ch.schema.data:
        text = ch.schema.data.decode("utf-8", errors="replace")
    elif name in SCHEMAS:  # e.g. a ros2idl or empty definition of a standard type
        text = SCHEMAS[name]
    if text is None:
        enc = ch.schema.encoding if ch.schema is not None else "none"
        raise BagFormatError(f"{path}: topic {ch.topic} ({name or 'no schema'}) has a {enc!r} schema this reader "
                             "cannot decode (ros2msg needed)")
    try:
        return generate_dynamic(name, text)[name]
    except Exception as exc:
        raise BagFormatError(f"{path}: topic {ch.topic}: cannot parse the message definition of {name} ({exc})") from None


def iter_messages(path: str | os.PathLike, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
    """Raw serialized messages (topic, type, log_time_ns, cdr bytes) of a bag file or directory.

    In log-time order per file (a damaged file: file order, up to the damage, then a
    BagTruncatedWarning). A replay node can publish `data` as is (rclpy publish of serialized
    bytes), without decoding.
    """
    wanted = None if topics is None else set(topics)
    for p in _bag_files(path):
        f = _McapFile(p)
        chans = f.channels()
        ids = None if wanted is None else {i for i, c in chans.items() if c.topic in wanted}
        for ch, log_time, data in f.messages(ids):
            yield BagMessage(ch.topic, _schema_name(ch), log_time, bytes(data))
        if not f.complete:
            warnings.warn(f.truncation_message(), BagTruncatedWarning, stacklevel=2)


# --------------------------------------------------------------------------------------------
# Reading: topics and frames
# --------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class FrameTopics:
    color: str
    depth: str
    camera_info: str
    ground_truth: str | None = None
    frame_info: str | None = None


def _pick(cands: list[str], score: Callable[[str], tuple]) -> list[str]:
    if not cands:
        return []
    best = max(score(c) for c in cands)
    return [c for c in cands if score(c) == best]


def resolve_topics(
    types: dict[str, str],
    path: str | os.PathLike = "",
    *,
    color_topic: str | None = None,
    depth_topic: str | None = None,
    camera_info_topic: str | None = None,
    ground_truth_topic: str | None = None,
) -> FrameTopics:
    """Choose the colour/depth/camera_info (and ground-truth) topics of a bag.

    `types` maps topic -> type. Given names must exist with the right type. Otherwise ours
    (/camera/color/image_raw ...) when present, else by type and name: colour = an Image topic
    named like color/rgb (not depth/infra), depth = an Image topic named like depth, preferring
    the one registered to colour (aligned_depth_to_color, depth_registered), camera_info = the
    CameraInfo beside the colour topic.
    """

    def check(topic: str, want: str, what: str) -> str:
        if topic not in types:
            raise BagFormatError(f"{path}: {what} topic {topic} is not in the bag (topics: {sorted(types)})")
        if types[topic] != want:
            raise BagFormatError(f"{path}: {what} topic {topic} has type {types[topic]}, expected {want}")
        return topic

    images = [t for t, ty in types.items() if ty == IMAGE]
    infos = [t for t, ty in types.items() if ty == CAMERA_INFO]
    low = {t: t.lower() for t in types}

    def is_depth(t: str) -> bool:
        return "depth" in low[t]

    def is_ir(t: str) -> bool:
        parts = low[t].replace("-", "/").split("/")
        return any(p.startswith("infra") or p in ("ir", "ir1", "ir2", "infrared") for p in parts)

    def fail(what: str, cands: list[str], kw: str) -> BagFormatError:
        return BagFormatError(f"{path}: cannot tell the {what} topic: candidates {sorted(cands) or 'none'} among "
                              f"{sorted(images + infos)}; pass {kw}=")

    # Colour
    if color_topic is not None:
        color = check(color_topic, IMAGE, "colour")
    elif types.get(COLOR_TOPIC) == IMAGE:
        color = COLOR_TOPIC
    else:
        cands = [t for t in images if not is_depth(t) and not is_ir(t)]
        best = _pick(cands, lambda t: (("color" in low[t]) or ("rgb" in low[t]), low[t].endswith("image_raw"),
                                       "rect" not in low[t]))
        if len(best) != 1:
            raise fail("colour image", best or cands, "color_topic")
        color = best[0]
    # Depth
    if depth_topic is not None:
        depth = check(depth_topic, IMAGE, "depth")
    elif types.get(DEPTH_TOPIC) == IMAGE and color == COLOR_TOPIC:
        depth = DEPTH_TOPIC
    else:
        cands = [t for t in images if is_depth(t) and t != color]
        best = _pick(cands, lambda t: (any(k in low[t] for k in ("aligned", "registered", "to_color")),
                                       low[t].endswith("image_raw") or low[t].endswith("image_rect_raw"),
                                       "compressed" not in low[t]))
        if len(best) != 1:
            raise fail("depth image", best or cands, "depth_topic")
        depth = best[0]
    # Camera info
    if camera_info_topic is not None:
        info = check(camera_info_topic, CAMERA_INFO, "camera_info")
    elif color == COLOR_TOPIC and types.get(CAMERA_INFO_TOPIC) == CAMERA_INFO:
        info = CAMERA_INFO_TOPIC
    else:
        beside = color.rsplit("/", 1)[0] + "/camera_info"
        if types.get(beside) == CAMERA_INFO:
            info = beside
        else:
            best = _pick([t for t in infos if "depth" not in low[t] and not is_ir(t)],
                         lambda t: (("color" in low[t]) or ("rgb" in low[t]),))
            if len(best) != 1:
                raise fail("camera_info (of the colour camera)", best or infos, "camera_info_topic")
            info = best[0]
    # Ground truth (optional)
    gt = None
    if ground_truth_topic is not None:
        gt = check(ground_truth_topic, OBJECT_POSES, "ground-truth")
    elif types.get(GROUND_TRUTH_TOPIC) == OBJECT_POSES:
        gt = GROUND_TRUTH_TOPIC
    else:
        cands = [t for t, ty in types.items() if ty == OBJECT_POSES]
        gt = cands[0] if len(cands) == 1 else None
    frame_info = FRAME_INFO_TOPIC if types.get(FRAME_INFO_TOPIC) == STRING else None
    return FrameTopics(color, depth, info, gt, frame_info)


class _Assembler:
    """Group decoded messages into frames by header stamp; drop incomplete ones cleanly."""

    REQUIRED = ("depth", "info")

    def __init__(self, path: Path, topics: FrameTopics, tolerance_ns: int, require_gt: bool, max_pending: int = 32):
        self.path = path
        self.topics = topics
        self.tol = tolerance_ns
        self.required = self.REQUIRED + (("gt",) if require_gt else ())
        self.max_pending = max_pending
        self.buf: dict[str, dict[int, Any]] = {r: {} for r in ("color", "depth", "info", "gt", "finfo")}
        self.max_seen: dict[str, int] = {}
        self.dropped: dict[str, int] = {}
        self.first_dropped: dict[str, int] = {}
        self.yielded = 0
        self._warned_distortion = False
        self._warned_ids = False

    def add(self, role: str, stamp: int, msg: Any) -> list[Frame]:
        self.buf[role][stamp] = msg
        self.max_seen[role] = max(self.max_seen.get(role, stamp), stamp)
        for r, b in self.buf.items():
            if r != "color" and len(b) > 4 * self.max_pending:  # orphans (e.g. depth with no colour)
                for s in sorted(b)[: len(b) - 4 * self.max_pending]:
                    del b[s]
        return self._emit(final=False)

    def finish(self) -> list[Frame]:
        return self._emit(final=True)

    def _match(self, role: str, c: int, force: bool) -> tuple[str, int | None]:
        b = self.buf[role]
        if c in b:
            return "ok", c
        best = None
        if self.tol > 0:
            near = [(abs(s - c), s) for s in b if abs(s - c) <= self.tol]
            best = min(near)[1] if near else None
        if not force and self.max_seen.get(role, -1) <= c + self.tol:
            return "wait", None
        return ("ok", best) if best is not None else ("missing", None)

    def _drop(self, c: int, reason: str) -> None:
        self.dropped[reason] = self.dropped.get(reason, 0) + 1
        self.first_dropped.setdefault(reason, c)
        del self.buf["color"][c]

    def _emit(self, final: bool) -> list[Frame]:
        out: list[Frame] = []
        colors = self.buf["color"]
        while colors:
            c = min(colors)
            force = final or len(colors) > self.max_pending
            matched: dict[str, int] = {}
            state = "ok"
            for role in self.required:
                st, s = self._match(role, c, force)
                if st != "ok":
                    state = st if st == "wait" else f"no {role}"
                    break
                matched[role] = s
            if state == "wait":
                break
            if state != "ok":
                self._drop(c, state)
                continue
            for role in ("gt", "finfo"):
                if role not in matched:
                    st, s = self._match(role, c, True)
                    if st == "ok":
                        matched[role] = s
            out.append(self._frame(c, {r: self.buf[r].pop(s) for r, s in matched.items()}, colors.pop(c)))
            lo = c - self.tol
            for r, b in self.buf.items():
                if r != "color":
                    for s in [s for s in b if s < lo]:
                        del b[s]
        self.yielded += len(out)
        return out

    def _err(self, topic: str, stamp: int, problem: str) -> BagFormatError:
        return BagFormatError(f"{self.path}: topic {topic}, stamp {stamp / 1e9:.9f} s: {problem}")

    def _frame(self, stamp: int, parts: dict[str, Any], color_msg: Any) -> Frame:
        t = self.topics
        try:
            rgb = image_msg_to_rgb(color_msg)
        except ImageFormatError as exc:
            raise self._err(t.color, stamp, str(exc)) from None
        try:
            depth = image_msg_to_depth(parts["depth"])
        except ImageFormatError as exc:
            raise self._err(t.depth, stamp, str(exc)) from None
        h, w = rgb.shape[:2]
        if depth.shape != (h, w):
            raise self._err(t.depth, stamp, f"depth image is {depth.shape[1]}x{depth.shape[0]} but colour image "
                            f"{t.color} is {w}x{h}: depth must be registered to colour (e.g. RealSense "
                            "aligned_depth_to_color)")
        info = parts["info"]
        iw, ih = int(info.width), int(info.height)
        if (iw, ih) != (0, 0) and (iw, ih) != (w, h):
            raise self._err(t.camera_info, stamp, f"camera_info is for {iw}x{ih} images but the images are {w}x{h}")
        if int(info.binning_x) > 1 or int(info.binning_y) > 1:
            raise self._err(t.camera_info, stamp, "camera_info with binning is not supported")
        roi = info.roi
        if int(roi.width) and (int(roi.width), int(roi.height)) != (w, h):
            raise self._err(t.camera_info, stamp, "camera_info with a region of interest is not supported")
        K = np.asarray(info.k, dtype=np.float64).reshape(3, 3)
        if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0):
            raise self._err(t.camera_info, stamp, f"camera_info has no valid intrinsics K={K.flatten().tolist()} "
                            "(uncalibrated camera?)")
        if not self._warned_distortion and any(abs(float(d)) > 1e-12 for d in info.d):
            self._warned_distortion = True
            warnings.warn(f"{self.path}: {t.camera_info} has non-zero distortion ({info.distortion_model}); frames "
                          "are used as an undistorted pinhole camera with K", BagWarning, stacklevel=4)
        objects: list[SceneObject] = []
        gt = parts.get("gt")
        if gt is not None:
            if len(gt.object_ids) != len(gt.poses):
                raise self._err(t.ground_truth or "", stamp, f"{len(gt.object_ids)} object_ids but {len(gt.poses)} poses")
            for oid, p in zip(gt.object_ids, gt.poses):
                try:
                    obj_id = int(oid)
                except ValueError:
                    if not self._warned_ids:
                        self._warned_ids = True
                        warnings.warn(f"{self.path}: ground-truth object id {oid!r} is not a BOP integer id; "
                                      "such objects are skipped", BagWarning, stacklevel=4)
                    continue
                q = (p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w)
                R = matrix_from_quaternion(q) if any(q) else np.eye(3)
                objects.append(SceneObject(obj_id, gt=Pose(R, (p.position.x, p.position.y, p.position.z))))
        scene_id = im_id = 0
        finfo = parts.get("finfo")
        if finfo is not None:
            scene_id, im_id = int(finfo.get("scene_id", 0)), int(finfo.get("im_id", 0))
        return Frame(rgb=rgb, depth=depth, K=K, stamp=stamp / 1e9, scene_id=scene_id, im_id=im_id, objects=objects)

    def drop_report(self) -> str | None:
        if not self.dropped:
            return None
        parts = [f"{n} without {reason[3:]} (first at stamp {self.first_dropped[reason] / 1e9:.9f} s)"
                 for reason, n in self.dropped.items()]
        return (f"{self.path}: dropped {sum(self.dropped.values())} incomplete frame(s) - colour images "
                + "; ".join(parts) + f"; {self.yielded} complete frames read")


def read_bag(
    path: str | os.PathLike,
    *,
    color_topic: str | None = None,
    depth_topic: str | None = None,
    camera_info_topic: str | None = None,
    ground_truth_topic: str | None = None,
    require_ground_truth: bool | None = None,
    sync_tolerance_s: float = 0.02,
    strict: bool = False,
) -> Iterator[Frame]:
    """Frames of a rosbag2 MCAP bag (a .mcap file or a bag directory), in stamp order.

    A frame = a colour image + the depth image + camera_info with the same header stamp (or the
    nearest within `sync_tolerance_s`; 0 = exact only) + the ground truth (ObjectPoses) when the
    bag has it, + its BOP ids from /perception/frame_info when present. Colour images lacking a
    partner are dropped (one BagWarning at the end says how many). `require_ground_truth`:
    None = required when the bag has a ground-truth topic. Topics: see `resolve_topics`.

    Frame.stamp is the header stamp in seconds; depth is float32 metres with NaN = missing.
    Raises BagFormatError (a ValueError) on images or camera_info that contradict themselves.
    A truncated/damaged file: the complete frames before the damage, then a
    BagTruncatedWarning; with strict=True, BagTruncatedError before any frame.
    Files, topics and truncation (strict) are checked when called; frames are read lazily.
    """
    files = _bag_files(path)
    mcaps = [_McapFile(p) for p in files]
    if strict:
        for f in mcaps:
            if not f.complete:
                raise BagTruncatedError(f.truncation_message())
    types: dict[str, str] = {}
    for f in mcaps:
        for ch in f.channels().values():
            types.setdefault(ch.topic, _schema_name(ch))
    try:
        topics = resolve_topics(types, path, color_topic=color_topic, depth_topic=depth_topic,
                                camera_info_topic=camera_info_topic, ground_truth_topic=ground_truth_topic)
    except BagFormatError as exc:
        damaged = [f for f in mcaps if not f.complete]
        if damaged:  # most likely cut before the channels were written
            raise BagTruncatedError(f"{damaged[0].truncation_message()}; nothing readable before the damage "
                                    f"({exc})") from None
        raise
    require_gt = (topics.ground_truth is not None) if require_ground_truth is None else bool(require_ground_truth)
    if require_gt and topics.ground_truth is None:
        raise BagFormatError(f"{path}: ground truth required but the bag has no ObjectPoses topic")
    roles = {topics.color: "color", topics.depth: "depth", topics.camera_info: "info"}
    if topics.ground_truth:
        roles[topics.ground_truth] = "gt"
    if topics.frame_info:
        roles[topics.frame_info] = "finfo"
    asm = _Assembler(Path(path), topics, int(round(max(0.0, sync_tolerance_s) * 1e9)), require_gt)
    return _iter_frames(mcaps, roles, asm)


def _iter_frames(mcaps: list[_McapFile], roles: dict[str, str], asm: _Assembler) -> Iterator[Frame]:
    for f in mcaps:
        chans = f.channels()
        ids = {i for i, c in chans.items() if c.topic in roles}
        decoders: dict[int, Callable[[bytes], Any]] = {}
        for ch, log_time, data in f.messages(ids):
            dec = decoders.get(ch.id)
            if dec is None:
                dec = decoders[ch.id] = _make_decoder(ch, f.path)
            role = roles[ch.topic]
            try:
                msg = dec(data)
                if role == "finfo":
                    msg = json.loads(msg.data)
                    stamp = int(msg.get("stamp_ns", log_time))
                else:
                    stamp = _stamp_ns(msg.header)
            except Exception as exc:
                raise BagFormatError(f"{f.path}: topic {ch.topic}: cannot decode a message at log time "
                                     f"{log_time / 1e9:.9f} s ({type(exc).__name__}: {exc})") from None
            yield from asm.add(role, stamp, msg)
        if not f.complete:
            yield from asm.finish()
            msg = f.truncation_message() + f"; read the {asm.yielded} complete frames before the damage"
            warnings.warn(msg, BagTruncatedWarning, stacklevel=2)
    yield from asm.finish()
    report = asm.drop_report()
    if report:
        warnings.warn(report, BagWarning, stacklevel=2)


def bag_info(path: str | os.PathLike) -> dict:
    """Summary of a bag: path, files, size, start/end (s), duration_s, message_count, frames
    (colour images that have depth and camera_info messages: an upper bound of what read_bag
    yields), topics [{topic, type, count}], the frame topics, recording metadata, truncated."""
    files = _bag_files(path)
    counts: dict[str, int] = {}
    types: dict[str, str] = {}
    t0, t1 = None, None
    truncated: list[str] = []
    recording: dict[str, str] = {}
    profile = library = ""
    size = 0
    for p in files:
        f = _McapFile(p)
        chans = f.channels()
        size += f.size
        profile, library = f.header_profile or profile, f.header_library or library
        for cid, n in f.counts.items():
            if cid in chans:
                counts[chans[cid].topic] = counts.get(chans[cid].topic, 0) + n
        for ch in chans.values():
            types.setdefault(ch.topic, _schema_name(ch))
            counts.setdefault(ch.topic, 0)
        if f.times:
            t0 = f.times[0] if t0 is None else min(t0, f.times[0])
            t1 = f.times[1] if t1 is None else max(t1, f.times[1])
        recording.update(f.metadata.get("perception_config", {}))
        if not f.complete:
            truncated.append(f.truncation_message())
    info: dict[str, Any] = {
        "path": str(path),
        "files": [str(p) for p in files],
        "size_bytes": size,
        "profile": profile,
        "library": library,
        "start": t0 / 1e9 if t0 is not None else None,
        "end": t1 / 1e9 if t1 is not None else None,
        "start_utc": (time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(t0 // 1_000_000_000))
                      + f".{t0 % 1_000_000_000:09d}Z") if t0 is not None else None,
        "duration_s": (t1 - t0) / 1e9 if t0 is not None else 0.0,
        "message_count": sum(counts.values()),
        "frames": 0,
        "topics": [{"topic": t, "type": types[t], "count": counts[t]} for t in sorted(types)],
        "truncated": bool(truncated),
    }
    try:
        ft = resolve_topics(types, path)
        info["frames"] = min(counts.get(ft.color, 0), counts.get(ft.depth, 0), counts.get(ft.camera_info, 0))
        info["frame_topics"] = {k: v for k, v in ft.__dict__.items() if v}
    except BagFormatError as exc:
        info["frame_topics"] = f"not an RGB-D bag ({exc})"
    if recording:
        info["recording"] = recording
    if truncated:
        info["damage"] = "; ".join(truncated)
    return info
