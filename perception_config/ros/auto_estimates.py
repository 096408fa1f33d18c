"""The configurator's auto mode (`auto: true`): an estimate of every new camera frame.

A new frame is seen on `camera/camera_info` when `auto_objects` names the objects, else on
the replayed ground truth (`perception/ground_truth`), which also names the frame's objects (a
test bench). The estimates run on a thread of their own, one frame at a time; frames that
arrive meanwhile are skipped except the latest, or all kept in turn with `auto_every_frame`.
"""
from __future__ import annotations

import threading
from collections import deque
from typing import Callable

from perception_config_interfaces.msg import ObjectPoses
from perception_config_interfaces.srv import EstimatePose
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo

from .camera_frames import camera_qos, stamp_text
from .request_fields import parse_stamp

FRAMES_KEPT = 64  # frames waiting for their estimates, and frames whose ground-truth objects are kept


class AutoEstimates:
    """Subscribes to the frames' arrival and estimates each new frame's objects with
    `estimate(stamp_ns, object_id)` on its own thread."""

    def __init__(self, node: Node, estimate: Callable[[int, str], EstimatePose.Response], objects: list[str],
                 every_frame: bool, qos: str) -> None:
        self.node = node
        self.estimate = estimate
        self.objects = objects
        self.every_frame = every_frame
        self._wake = threading.Event()
        self._lock = threading.Lock()
        self._queue: deque[int] = deque(maxlen=FRAMES_KEPT)
        self._ground_truth: dict[int, list[str]] = {}  # stamp -> the objects of the frame's ground truth
        topics = MutuallyExclusiveCallbackGroup()
        if objects:
            node.create_subscription(CameraInfo, "camera/camera_info", self._on_camera_info, camera_qos(qos),
                                     callback_group=topics)
        else:
            node.create_subscription(ObjectPoses, "perception/ground_truth", self._on_ground_truth, 10,
                                     callback_group=topics)
        self._thread = threading.Thread(target=self._loop, name="auto", daemon=True)
        self._thread.start()

    def _on_ground_truth(self, msg: ObjectPoses) -> None:
        stamp = self._stamp(msg)
        if stamp is None:
            return
        self._ground_truth[stamp] = list(msg.object_ids)
        while len(self._ground_truth) > FRAMES_KEPT:
            self._ground_truth.pop(next(iter(self._ground_truth)))
        self._new_frame(stamp)

    def _on_camera_info(self, msg: CameraInfo) -> None:
        stamp = self._stamp(msg)
        if stamp is not None:
            self._new_frame(stamp)

    def _stamp(self, msg: ObjectPoses | CameraInfo) -> int | None:
        try:
            return parse_stamp(msg.header.stamp, "header.stamp")
        except ValueError as exc:
            self.node.get_logger().warning(f"auto: ignored a message: {exc}")
            return None

    def _new_frame(self, stamp: int) -> None:
        with self._lock:
            if stamp in self._queue:
                return
            self._queue.append(stamp)
            if not self.every_frame:
                while len(self._queue) > 1:  # a cell wants the latest frame, not a backlog
                    self._queue.popleft()
        self._wake.set()

    def _loop(self) -> None:
        while True:
            self._wake.wait()
            with self._lock:
                if not self._queue:
                    self._wake.clear()
                    continue
                stamp = self._queue.popleft()
            objects = self.objects or self._ground_truth.get(stamp, [])
            if not objects:
                self.node.get_logger().warning(f"auto: no objects to estimate in the frame at {stamp_text(stamp)} "
                                               "(set auto_objects, or replay ground truth)")
            for object_id in objects:
                r = self.estimate(stamp, object_id)
                self.node.get_logger().info(f"auto {stamp_text(stamp)} object {object_id}: "
                                            f"{'picked' if r.picked else r.message} after {', '.join(r.operations)} "
                                            f"({r.elapsed:.3f} s)")
