"""Recording Frames as a rosbag2-compatible MCAP bag: `BagWriter`, `write_frames`, `write_bag`.

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

* RGB-only frames (`Frame.depth` None): the bag has no depth topic at all (a recording is
  RGB-D or RGB-only, all frames alike; `read_bag` reads it back with depth None).
* Ground truth: position = t, orientation = the quaternion of the rotation nearest to R (BOP
  stores R with a few digits, orthonormal only to ~1e-4; a quaternion can carry only a rotation).
* Frame ids: every header says `camera_color_optical_frame`. BOP depth is registered to the
  colour image, so one optical frame serves colour, depth, camera_info and the ground truth.
* Clock: frame i is stamped `start_time_ns + i / rate_hz` (default start 1.7e9 s, a fixed epoch,
  so the same dataset always gives the same bag); log_time = publish_time = the header stamp.
* Why a frame_info topic (not a MCAP metadata record): it is written with each frame, so it
  survives an interrupted recording, a replay node can republish it, and ROS tools see it.
  The recording's parameters go into a MCAP metadata record named `perception_config`.
* Profile `ros2`, message encoding `cdr`, schemas `ros2msg` (complete message definitions from
  rosbags' typestore, definitions.py) named `sensor_msgs/msg/Image` etc., channel metadata with `offered_qos_profiles`
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
"""
from __future__ import annotations

import itertools
import json
import math
import os
import signal
import threading
from pathlib import Path
from typing import Any, Callable, Iterable

import yaml

from ...core.geometry import nearest_rotation, quaternion_from_matrix
from ...core.scene import Frame
from ...util.atomic_file import atomic_write
from .definitions import definition, type_hash
from .errors import BagWriteInterrupted
from .messages import OPTICAL_FRAME, camera_info_fields, depth_to_image_fields, header_fields, rgb_to_image_fields
from .topics import (
    CAMERA_INFO,
    CAMERA_INFO_TOPIC,
    COLOR_TOPIC,
    DEPTH_TOPIC,
    FRAME_INFO_TOPIC,
    GROUND_TRUTH_TOPIC,
    IMAGE,
    OBJECT_POSES,
    STRING,
)

RECORDING_EPOCH_NS = 1_700_000_000 * 1_000_000_000  # fixed start of the recording clock
ROSBAG2_VERSION = 9
# Chunks are closed at every frame boundary (Writer.flush); this only caps a single huge frame.
_CHUNK_SIZE = 256 * 1024 * 1024


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
    manager does), the bag is then valid with the frames written so far. `depth=False` records
    RGB-only frames (depth None): no depth topic; every frame must then lack depth (and with
    depth=True have it).
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
        depth: bool = True,
    ) -> None:
        from mcap.writer import CompressionType
        from mcap.writer import Writer as McapWriter
        from mcap_ros2._dynamic import serialize_dynamic

        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"rate_hz must be a positive number, got {rate_hz}")
        if depth_encoding not in ("16UC1", "32FC1"):
            raise ValueError(f"depth_encoding must be '16UC1' or '32FC1', got {depth_encoding!r}")
        comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE,
                "": CompressionType.NONE}
        if compression not in comp:
            raise ValueError(f"compression must be one of zstd, lz4, none; got {compression!r}")
        self.rate_hz = float(rate_hz)
        self.start_time_ns = int(start_time_ns)
        self.depth_encoding = depth_encoding
        self.depth = bool(depth)
        self.custom_data = {str(k): str(v) for k, v in (custom_data or {}).items()}
        self.path, self.metadata_path = _resolve_output(out_path)
        self.frames = 0
        self._counts: dict[str, int] = {}
        self._first_ns: int | None = None
        self._last_ns: int | None = None
        self._closed = False

        self._file = open(self.path, "wb")
        try:
            from ... import __version__

            self._writer = McapWriter(self._file, chunk_size=_CHUNK_SIZE, compression=comp[compression])
            self._writer.start(profile="ros2", library=f"perception_config {__version__}")
            self._topics = [
                (FRAME_INFO_TOPIC, STRING), (CAMERA_INFO_TOPIC, CAMERA_INFO), (GROUND_TRUTH_TOPIC, OBJECT_POSES),
                (DEPTH_TOPIC, IMAGE), (COLOR_TOPIC, IMAGE),
            ]
            if not self.depth:  # an RGB-only recording: no depth topic at all
                self._topics.remove((DEPTH_TOPIC, IMAGE))
            self._channels: dict[str, int] = {}
            self._encoders: dict[str, Callable[[Any], bytes]] = {}
            schema_ids: dict[str, int] = {}
            for topic, typ in self._topics:
                if typ not in schema_ids:
                    schema_ids[typ] = self._writer.register_schema(typ, "ros2msg", definition(typ).encode())
                    self._encoders[typ] = serialize_dynamic(typ, definition(typ))[typ]
                self._channels[topic] = self._writer.register_channel(
                    topic, "cdr", schema_ids[typ],
                    metadata={"offered_qos_profiles": "[]", "topic_type_hash": type_hash(typ)},
                )
                self._counts[topic] = 0
            self._writer.add_metadata("perception_config", {
                "rate_hz": repr(self.rate_hz), "start_time_ns": str(self.start_time_ns),
                "depth_encoding": depth_encoding, "frame_id": OPTICAL_FRAME,
                "frame_info_topic": FRAME_INFO_TOPIC, **({} if self.depth else {"depth": "none"}),
                **self.custom_data,
            })
            self._writer.flush()
        except BaseException:
            self._file.close()
            raise

    def stamp_ns(self, index: int) -> int:
        return self.start_time_ns + round(index * 1e9 / self.rate_hz)

    def _messages(self, frame: Frame, stamp_ns: int) -> list[tuple[str, bytes]]:
        header = header_fields(stamp_ns)
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
        msgs = [
            (FRAME_INFO_TOPIC, enc[STRING]({"data": json.dumps(info)})),
            (CAMERA_INFO_TOPIC, enc[CAMERA_INFO]({"header": header, **camera_info_fields(frame.K, w, h)})),
            (GROUND_TRUTH_TOPIC, enc[OBJECT_POSES]({"header": header, "object_ids": ids, "poses": poses})),
        ]
        if self.depth:
            msgs.append((DEPTH_TOPIC, enc[IMAGE]({"header": header,
                                                  **depth_to_image_fields(frame.depth, self.depth_encoding)})))
        msgs.append((COLOR_TOPIC, enc[IMAGE]({"header": header, **rgb_to_image_fields(frame.rgb)})))
        return msgs

    def write(self, frame: Frame) -> int:
        """Append one frame (all its messages, one chunk, flushed); returns its stamp in ns."""
        if self._closed:
            raise ValueError(f"{self.path}: the bag writer is closed")
        if (frame.depth is not None) != self.depth:
            raise ValueError(f"{self.path}: frame {self.frames} (scene {frame.scene_id} image {frame.im_id}) "
                             f"{'has' if frame.depth is not None else 'lacks'} depth but the recording is "
                             f"{'RGB-D' if self.depth else 'RGB-only'}: all frames alike")
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
                                    "offered_qos_profiles": [], "type_description_hash": type_hash(typ)},
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
            atomic_write(self.metadata_path, yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False))

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
    Without a `depth` option the first frame decides: RGB-only frames make an RGB-only bag.
    """
    from tqdm import tqdm

    if "depth" not in writer_options:
        it = iter(frames)
        first = next(it, None)
        writer_options["depth"] = first is None or first.depth is not None
        frames = itertools.chain([first], it) if first is not None else it

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
    use_depth: bool = True,
) -> int:
    """Record every image of a BOP dataset split as a rosbag2-compatible MCAP bag.

    Returns the number of frames written. Topics, units and layout are in the module
    docstring: colour rgb8, depth 16UC1 in millimetres with 0 = missing depth (BOP depth is
    rounded to whole millimetres; `depth_encoding="32FC1"` keeps metres as float32 with NaN
    = missing), camera_info, ground-truth ObjectPoses in metres, and /perception/frame_info
    mapping each stamp to its BOP (scene_id, im_id). `out_path`: a bag directory (created, with
    `<name>_0.mcap` and metadata.yaml) or a `.mcap` file path (metadata.yaml beside it only when
    it is the only bag in that directory). Ctrl-C / SIGTERM finish the file cleanly, then raise
    `BagWriteInterrupted`. An RGB-only dataset (or `use_depth=False`) gives a bag without the
    depth topic.
    """
    from ..bop import BopDataset

    ds = BopDataset(dataset_dir, split=split, use_depth=use_depth)
    keys = list(ds.image_keys())
    frames = (ds.load_frame(scene_id, im_id, with_models=False) for scene_id, im_id in keys)
    return write_frames(
        frames, out_path, rate_hz, progress=progress, total=len(keys), compression=compression,
        depth_encoding=depth_encoding,
        custom_data={"dataset": Path(dataset_dir).resolve().name, "split": split, "frames": str(len(keys))},
    )
