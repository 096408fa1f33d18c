"""BOP scenes recorded as rosbag2-compatible MCAP bags, and rosbag2 MCAP bags read back as Frames.

This package does not import rclpy: it writes and reads CDR with `mcap` + `mcap-ros2-support`
from the bag's own schema texts (ours come from rosbags' typestore: definitions.py); rosbag2
sqlite3 files are read through `rosbags`.

- writer.py: `BagWriter`, `write_frames`, `write_bag`; what a bag written here holds (topics,
  units, frame ids, clock, one chunk per frame, Ctrl-C handling) and where metadata.yaml goes.
- frames.py: `read_bag`, our bags and RGB-D camera recordings as Frames (grouping by stamp,
  incomplete frames, truncated files).
- mcap_reader.py: bag file discovery, damaged MCAP files, channels, decoders; sqlite_reader.py:
  rosbag2 .db3 files (through rosbags); storage.py: either kind, `iter_messages` (raw CDR),
  `first_messages`; compression.py: message-level zstd / lz4.
- topics.py: our topic names and types, `resolve_topics` for other recordings.
- messages.py: image and camera_info messages <-> numpy arrays.
- info.py: `bag_info`. errors.py: the errors and warnings.

Everything public is importable from `perception_config.datasets.bag`.
"""
from __future__ import annotations

from .errors import (
    BagFormatError,
    BagTruncatedError,
    BagTruncatedWarning,
    BagWarning,
    BagWriteInterrupted,
    ImageFormatError,
)
from .frames import read_bag
from .info import bag_info
from .mcap_reader import BagMessage
from .messages import (
    COLOR_ENCODINGS,
    DEPTH_ENCODINGS,
    OPTICAL_FRAME,
    camera_info_fields,
    depth_to_image_fields,
    image_msg_to_depth,
    image_msg_to_rgb,
    rgb_to_image_fields,
)
from .storage import first_messages, iter_messages, open_bag
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
    FrameTopics,
    resolve_topics,
)
from .writer import RECORDING_EPOCH_NS, ROSBAG2_VERSION, BagWriter, write_bag, write_frames

__all__ = [
    "BagFormatError", "BagTruncatedError", "BagTruncatedWarning", "BagWarning", "BagWriteInterrupted",
    "ImageFormatError", "read_bag", "bag_info", "BagMessage", "iter_messages", "first_messages", "open_bag",
    "COLOR_ENCODINGS", "DEPTH_ENCODINGS",
    "OPTICAL_FRAME", "camera_info_fields", "depth_to_image_fields", "image_msg_to_depth", "image_msg_to_rgb",
    "rgb_to_image_fields", "CAMERA_INFO", "CAMERA_INFO_TOPIC", "COLOR_TOPIC", "DEPTH_TOPIC", "FRAME_INFO_TOPIC",
    "GROUND_TRUTH_TOPIC", "IMAGE", "OBJECT_POSES", "STRING", "FrameTopics", "resolve_topics", "RECORDING_EPOCH_NS",
    "ROSBAG2_VERSION", "BagWriter", "write_bag", "write_frames",
]
