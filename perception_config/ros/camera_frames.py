"""The camera frames an operator node works on: colour, depth and camera_info assembled by stamp.

Subscribes to `camera/color/image_raw`, `camera/depth/image_raw` and `camera/camera_info`
(relative names: remap them, or push the node into the camera's namespace). A colour and a depth
image with the same header stamp make a frame (or the nearest depth within `sync_tolerance`
seconds, for drivers that stamp them apart); K comes from the camera_info of that stamp (a
frame waits for it once the camera has been seen to stamp camera_info like its images, as
image_transport's camera publishers do), else from the latest camera_info (a static publisher).
Frames are converted once, on arrival, and kept in a bounded `StampCache`, so a service request
names its frame by stamp and large images cross the middleware once, not at every operator call.

An RGB-only camera (`use_depth=False`; the operator nodes' parameter `use_depth`): no depth
subscription, a frame is the colour image + camera_info alone (Frame.depth None); the blocks
that need depth then answer "needs depth". The RGB-D path is unchanged.

A frame that cannot be used (unsupported encoding, a step or data size that contradicts the
image size, colour and depth of different sizes, a camera_info of another size or with a
degenerate K) is cached as the error, so the request that names it gets a message saying what
was wrong with which image.
"""
from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np
from rclpy.node import Node
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image

from ..core.scene import Frame
from ..datasets.bag import image_msg_to_depth, image_msg_to_rgb
from .request_fields import parse_stamp
from .stamp_cache import StampCache

MAX_PENDING = 16  # half-assembled frames kept (a colour image waiting for its depth, ...)


class FrameNotReady(ValueError):
    """The frame (or ground truth) a request names has not arrived (yet); the message says which."""


@dataclass
class CameraFrame:
    """A usable frame with the header it came with."""

    stamp_ns: int
    frame_id: str
    frame: Frame


@dataclass
class FrameError:
    """A frame that arrived but cannot be used, and why."""

    stamp_ns: int
    problem: str


CAMERA_QOS = ("reliable", "sensor_data")  # the camera_qos parameter's choices (camera_qos below)


def camera_qos(name: str) -> QoSProfile:
    """`reliable` (default: matches rosbag2 play, our replay node and most drivers) or
    `sensor_data` (best effort: also matches drivers that publish best effort)."""
    if name == "reliable":
        return QoSProfile(depth=10)
    if name == "sensor_data":
        return qos_profile_sensor_data
    raise ValueError(f"camera_qos must be 'reliable' or 'sensor_data', got {name!r}")


def stamp_text(stamp_ns: int) -> str:
    return f"{stamp_ns // 1_000_000_000}.{stamp_ns % 1_000_000_000:09d} s"


def assemble_frame(color: Any, depth: Any, info: Any) -> Frame:
    """Colour + depth + camera_info messages -> Frame; ValueError naming what is wrong. `depth`
    None: an RGB-only frame (Frame.depth None)."""
    try:
        rgb = image_msg_to_rgb(color)
    except ValueError as exc:
        raise ValueError(f"colour image: {exc}") from None
    depth_m = None
    if depth is not None:
        try:
            depth_m = image_msg_to_depth(depth)
        except ValueError as exc:
            raise ValueError(f"depth image: {exc}") from None
        if rgb.shape[:2] != depth_m.shape:
            raise ValueError(f"colour {rgb.shape[1]}x{rgb.shape[0]} and depth {depth_m.shape[1]}x{depth_m.shape[0]} "
                             "differ in size (depth must be registered to colour)")
    h, w = rgb.shape[:2]
    if (info.width, info.height) != (0, 0) and (info.width, info.height) != (w, h):
        raise ValueError(f"camera_info is {info.width}x{info.height} but the images are {w}x{h}")
    K = np.asarray(info.k, dtype=np.float64).reshape(3, 3)
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0 and K[2, 2] == 1.0):
        raise ValueError(f"camera_info has a degenerate K {K.flatten().tolist()}")
    return Frame(rgb=rgb, depth=depth_m, K=K)


class CameraFrames:
    """Subscriptions and the frame cache of one camera (thread-safe: the subscriptions fill it
    from one executor thread while service callbacks read it from another)."""

    def __init__(self, node: Node, capacity: int, qos: str = "reliable", sync_tolerance: float = 0.0,
                 callback_group: Any = None, on_arrival: Any = None, use_depth: bool = True) -> None:
        if not (math.isfinite(sync_tolerance) and sync_tolerance >= 0):
            raise ValueError(f"sync_tolerance must be >= 0 seconds, got {sync_tolerance}")
        self.frames: StampCache[CameraFrame | FrameError] = StampCache(capacity)
        self._tolerance_ns = int(round(sync_tolerance * 1e9))
        self._pending: OrderedDict[int, dict[str, Any]] = OrderedDict()
        self._infos: OrderedDict[int, Any] = OrderedDict()
        self._lock = threading.Lock()
        self._info_stamped_with_images = False
        self._logger = node.get_logger()
        self._node_name = node.get_name()
        self._started = time.monotonic()
        self._on_arrival = on_arrival
        self.use_depth = bool(use_depth)
        # the image roles a frame is made of: an RGB-only camera has no depth to wait for
        self._roles = ("color", "depth") if self.use_depth else ("color",)
        profile = camera_qos(qos)
        node.create_subscription(Image, "camera/color/image_raw", lambda m: self._add("color", m), profile,
                                 callback_group=callback_group)
        if self.use_depth:
            node.create_subscription(Image, "camera/depth/image_raw", lambda m: self._add("depth", m), profile,
                                     callback_group=callback_group)
        node.create_subscription(CameraInfo, "camera/camera_info", self._on_info, profile,
                                 callback_group=callback_group)

    # -- arrival ---------------------------------------------------------------------------
    def _stamp(self, msg: Any) -> int | None:
        """The message's stamp (ns), or None (logged) for one no request could name."""
        try:
            return parse_stamp(msg.header.stamp, "header.stamp")
        except ValueError as exc:
            self._logger.warning(f"ignored a camera message: {exc}")
            return None

    def _on_info(self, msg: CameraInfo) -> None:
        stamp = self._stamp(msg)
        if stamp is None:
            return
        with self._lock:
            self._infos[stamp] = msg
            if stamp in self._pending or self.frames.has(stamp):
                self._info_stamped_with_images = True
            while len(self._infos) > MAX_PENDING:
                self._infos.popitem(last=False)
            ready = [s for s, parts in self._pending.items() if all(r in parts for r in self._roles)]
        for stamp in ready:  # images that were waiting for a first camera_info
            self._try(stamp)

    def _add(self, role: str, msg: Image) -> None:
        stamp = self._stamp(msg)
        if stamp is None:
            return
        with self._lock:
            if role == "depth" and self._tolerance_ns and stamp not in self._pending:
                near = [s for s in self._pending
                        if abs(s - stamp) <= self._tolerance_ns and "depth" not in self._pending[s]]
                if near:  # file the depth under the colour image's stamp
                    stamp = min(near, key=lambda s: abs(s - stamp))
            self._pending.setdefault(stamp, {})[role] = msg
            while len(self._pending) > MAX_PENDING:
                old, parts = self._pending.popitem(last=False)
                missing = "depth" if "color" in parts else "colour"
                self._logger.warning(f"dropped the frame at {stamp_text(old)}: its {missing} image never arrived")
        self._try(stamp)

    def _try(self, stamp: int) -> None:
        with self._lock:
            parts = self._pending.get(stamp)
            if parts is None or not all(r in parts for r in self._roles):
                return
            info = self._infos.get(stamp)
            if info is None and not self._info_stamped_with_images and self._infos:
                info = next(reversed(self._infos.values()))
            if info is None:
                return  # wait for its camera_info
            if stamp in self._infos:
                self._info_stamped_with_images = True
            del self._pending[stamp]
        color = parts["color"]
        try:
            item: CameraFrame | FrameError = CameraFrame(stamp, color.header.frame_id,
                                                         assemble_frame(color, parts.get("depth"), info))
            item.frame.stamp = stamp * 1e-9
        except ValueError as exc:
            item = FrameError(stamp, str(exc))
            self._logger.warning(f"unusable camera frame at {stamp_text(stamp)}: {exc}")
        self.frames.put(stamp, item)
        if self._on_arrival is not None:
            self._on_arrival()

    def age(self) -> float:
        """Seconds since these subscriptions were made (the node's start)."""
        return time.monotonic() - self._started

    # -- requests ----------------------------------------------------------------------------
    def get(self, stamp_ns: int, timeout: float) -> CameraFrame:
        """The frame with this stamp (0 = the latest), without waiting: FrameNotReady when it has
        not arrived (the message names `timeout`, the wait the caller grants; operator_node awaits
        the next arrival and asks again), ValueError when it arrived unusable."""
        item = self.frames.get(stamp_ns)
        if item is None:
            which = "no camera frame" if stamp_ns == 0 else f"no camera frame stamped {stamp_text(stamp_ns)}"
            cached = self.frames.stamps()
            have = (f"{len(cached)} cached, {stamp_text(cached[0])} .. {stamp_text(cached[-1])}" if cached
                    else f"{self._node_name} has received none since it started {self.age():.0f} s ago: check the "
                         "camera topics, their remapping and camera_qos; a node (re)started after a frame was "
                         "published never receives that frame")
            raise FrameNotReady(f"{which} arrived within {timeout:g} s ({have})")
        if isinstance(item, FrameError):
            raise ValueError(f"the camera frame at {stamp_text(item.stamp_ns)} is unusable: {item.problem}")
        return item
