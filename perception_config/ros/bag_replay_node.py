"""bag_replay_node: replays a rosbag2 bag (MCAP or sqlite3 .db3; what `perception-config bag write`
records, or a camera driver's recording) on ROS 2 topics, like `ros2 bag play`, publishing each
message's serialized bytes without decoding them, after undoing message-level compression (zstd,
lz4; MCAP chunk compression is undone by the reader).

    bag_replay_node --ros-args -p bag:=recording.mcap -p rate:=1.0 -p loop:=true

Topics: each of the bag's topics under its own name with the leading '/' removed, so a node
namespace and `--ros-args -r` remappings apply. A sensor_msgs/CompressedImage topic (image_transport
`<image>/compressed` jpeg/png, `<image>/compressedDepth`) is decoded and published as a
sensor_msgs/Image on `<image>` (rgb8 colour; 16UC1 millimetres or 32FC1 metres depth), the topic
and type the project's operator nodes (and rviz/Foxglove without image_transport plugins) subscribe
to; `decompress_images:=false` republishes the CompressedImage as recorded instead. A compressed
topic whose raw `<image>` topic is in the bag too is not replayed (the frames would arrive twice).
Before starting, the first message of every replayed topic is deserialised with the installed
message type and compared field by field with what the bag's own definition of the type gives
(and a compressed image is decoded): a topic that fails is an error naming the bag, topic and
type (exit 2), not a replay of bytes no subscriber can read. A bag of ours gives camera/color/image_raw,
camera/depth/image_raw (16UC1 mm), camera/camera_info, perception/ground_truth (ObjectPoses) and
perception/frame_info (std_msgs/String JSON). QoS: reliable, keep-last 10, volatile. Reliable so
that subscribers with the default QoS match and a consumer that keeps up loses no frame (best-effort
subscribers match too); keep-last 10 bounds memory, so with rate 0 a consumer slower than the
replay loses the oldest frames: give a rate to replay in real time.

Parameters: PARAMETERS below (`ros2 param describe bag_replay_node <name>`).

Pacing (rate > 0): a message is due at (its log time - the first message's log time) / rate after
the start, on the monotonic clock; a late message is published at once and the schedule does not
drift. A non-looping replay logs a summary (messages, frames = colour images, seconds, frames per
second), waits until its reliable subscribers have acknowledged every message (at most
ACK_TIMEOUT_S; Fast DDS acknowledges at its heartbeat, up to 3 s later: exiting before would lose
the last frames of a fast replay, cf. `ros2 bag play --wait-for-all-acked`) and exits 0. Ctrl-C or
SIGTERM stop it at once, also exit 0. A truncated bag replays its complete frames and logs a
warning. Bad parameters or an unreadable bag: an error naming it, exit 2.
"""
from __future__ import annotations

import importlib
import sys
import threading
import time
import warnings
from typing import Any

import rclpy
from rclpy.duration import Duration
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.parameter import Parameter
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future

from ..datasets.bag import BagTruncatedWarning, bag_info, first_messages, iter_messages
from ..datasets.bag.messages import compressed_image_fields
from ..datasets.bag.topics import COMPRESSED_IMAGE
from ..datasets.bag.type_names import check_type_name
from ..launcher.fastdds_shm import clean_stale_fastdds_shm
from ..launcher.ros_environment import configure_ros_environment
from .guard import GuardedNode
from .parameters import NodeParameter, declare

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT = 0, 1, 2
ACK_TIMEOUT_S = 5.0
QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)

PARAMETERS = (
    NodeParameter("bag", "", "bag file (.mcap) or rosbag2 bag directory; required", read_only=True),
    NodeParameter("rate", 1.0, "1.0 = the recorded timing, 2.0 = twice as fast, 0 = as fast as possible (>= 0)",
                  read_only=True, number=True),
    NodeParameter("loop", False, "start over at the end, one frame interval later. The stamps are the bag's own and "
                  "do not change between passes: nodes that cache frames by stamp see the same frames again",
                  read_only=True),
    NodeParameter("topics", Parameter.Type.STRING_ARRAY, "bag topics to replay (with or without the leading '/'; a "
                  "compressed image topic also by its raw image topic's name); not set = all", read_only=True),
    NodeParameter("wait_for_subscribers", 0, "before starting, wait until the colour topic (else the first replayed "
                  "topic) has this many subscribers, at most wait_timeout s (then a warning, and start)",
                  read_only=True),
    NodeParameter("wait_timeout", 10.0, "seconds wait_for_subscribers and wait_for wait at most", read_only=True,
                  number=True),
    NodeParameter("wait_for", Parameter.Type.STRING_ARRAY, "per-topic minimum subscribers, \"topic:count\" (e.g. "
                  "camera/color/image_raw:4 perception/ground_truth:3), all awaited within wait_timeout; replaces "
                  "wait_for_subscribers when set", read_only=True),
    NodeParameter("start_delay", 0.0, "seconds before the first message, after wait_for_subscribers (the other "
                  "topics may match a moment after the colour topic)", read_only=True, number=True),
    NodeParameter("decompress_images", True, "CompressedImage topics published decoded as sensor_msgs/Image",
                  read_only=True),
)


class ReplayError(Exception):
    """Bad parameters or an unreadable bag (exit code 2)."""


def field_difference(msg: Any, other: Any, path: str = "") -> str | None:
    """The first field where an rclpy message and the same message decoded another way (an object
    with the same field names as attributes, e.g. from the bag's schema) differ; None if equal."""
    for name in msg.get_fields_and_field_types():
        here = f"{path}.{name}" if path else name
        if not hasattr(other, name):
            return f"field {here} is not in the bag's definition"
        a, b = getattr(msg, name), getattr(other, name)
        if hasattr(a, "get_fields_and_field_types"):
            diff = field_difference(a, b, here)
        elif isinstance(a, (str, bool, int, float)):
            diff = None if a == b or (a != a and b != b) else f"{here}: {a!r} != {b!r}"[:200]
        else:  # a sequence or array: of messages or of numbers
            a, b = list(a), list(b)
            if len(a) != len(b):
                return f"{here}: {len(a)} != {len(b)} elements"
            if a and hasattr(a[0], "get_fields_and_field_types"):
                diff = next((d for i, (x, y) in enumerate(zip(a, b))
                             if (d := field_difference(x, y, f"{here}[{i}]")) is not None), None)
            else:
                bad = next((i for i, (x, y) in enumerate(zip(a, b)) if x != y and not (x != x and y != y)), None)
                diff = None if bad is None else f"{here}[{bad}]: {a[bad]!r} != {b[bad]!r}"
        if diff is not None:
            return diff
    return None


def message_class(type_name: str) -> type:
    """'sensor_msgs/msg/Image' -> the class sensor_msgs.msg.Image. The name is validated first
    (check_type_name: pattern and a known interface package), so bag content imports nothing else."""
    package, name = check_type_name(type_name)
    return getattr(importlib.import_module(f"{package}.msg"), name)


class BagReplayNode(GuardedNode):
    """Publishes a bag's messages on their topics at the recorded pace (times `rate`), raw CDR."""

    def __init__(self) -> None:
        super().__init__("bag_replay_node")
        declare(self, PARAMETERS)

        self.bag = self.get_parameter("bag").value
        self.rate = self._number("rate")
        self.loop = self.get_parameter("loop").value
        self.wait_for = self.get_parameter("wait_for_subscribers").value
        self.wait_timeout = self._number("wait_timeout")
        self.start_delay = self._number("start_delay")
        self.decompress_images = bool(self.get_parameter("decompress_images").value)
        if not self.bag:
            raise ReplayError("parameter 'bag' is empty: give a bag file or directory (--ros-args -p bag:=FILE.mcap)")
        if self.rate < 0:
            raise ReplayError(f"parameter 'rate' must be >= 0 (1.0 = recorded timing, 0 = as fast as possible), "
                              f"got {self.rate}")
        try:
            info = bag_info(self.bag)
        except (OSError, ValueError) as exc:
            raise ReplayError(f"cannot replay bag {self.bag}: {exc}") from None
        if info.get("corrupt"):  # bag_info checked every chunk's CRC: refuse rather than fail midway
            raise ReplayError(f"cannot replay bag {self.bag}: {info['damage']}")
        if info["truncated"]:
            self.get_logger().warning(f"{info['damage']}: replaying the complete frames before the damage")

        wanted = {t.lstrip("/") for t in self.get_parameter_or("topics").value or []}
        frame_topics = info.get("frame_topics")
        frame_topics = frame_topics if isinstance(frame_topics, dict) else {}
        bag_topics = {t["topic"] for t in info["topics"]}
        self._pubs = {}  # bag topic -> publisher
        self._decode: dict[str, tuple[type, bool]] = {}  # CompressedImage bag topic -> (Image class, is depth)
        def base_of(topic: str) -> str:  # an image_transport compressed topic's raw image topic
            return topic.removesuffix("/compressedDepth").removesuffix("/compressed")

        for t in info["topics"]:
            name = t["topic"].lstrip("/")
            if wanted and name not in wanted and base_of(t["topic"]).lstrip("/") not in wanted:
                continue
            try:
                cls = message_class(t["type"])
            except (ValueError, ImportError, AttributeError):
                self.get_logger().warning(f"skipping {t['topic']}: message type {t['type']!r} is not installed")
                continue
            if t["type"] == COMPRESSED_IMAGE and self.decompress_images:
                base = base_of(t["topic"])
                if base != t["topic"] and base in bag_topics:
                    self.get_logger().info(f"not replaying {t['topic']}: the bag has its raw topic {base}")
                    continue
                from sensor_msgs.msg import Image

                depth = t["topic"] == frame_topics.get("depth") or "depth" in t["topic"].lower()
                self._decode[t["topic"]] = (cls, depth)
                cls, name = Image, base.lstrip("/")
            self._pubs[t["topic"]] = self.create_publisher(cls, name, QOS)
        names = {n.lstrip("/") for t in info["topics"] for n in (t["topic"], base_of(t["topic"]))}
        missing = wanted - names
        if missing:
            raise ReplayError(f"topics {sorted(missing)} are not in bag {self.bag} "
                              f"(it has {[t['topic'] for t in info['topics']]})")
        if not self._pubs:
            raise ReplayError(f"bag {self.bag}: no topic to replay")
        self._check_first_messages(info)
        self._color = frame_topics.get("color")
        self._wait_counts: dict[str, int] = {}  # bag topic -> minimum subscribers before starting
        for item in self.get_parameter_or("wait_for").value or []:
            name, _, count = str(item).rpartition(":")
            topic = next((t for t, p in self._pubs.items()
                          if name.lstrip("/") in (t.lstrip("/"), p.topic_name.lstrip("/"))), None)
            if topic is None or not count.isdigit():
                raise ReplayError(f"wait_for entry {item!r} must be 'topic:count' with a replayed topic "
                                  f"(topics: {sorted(self._pubs)})")
            self._wait_counts[topic] = int(count)
        if not self._wait_counts and self.wait_for:
            self._wait_counts[self._color if self._color in self._pubs else next(iter(self._pubs))] = int(self.wait_for)
        n = info["frames"]
        self._frame_gap_s = info["duration_s"] / (n - 1) if n > 1 else 0.0  # the pause between loop passes

        self.get_logger().info(f"replaying {self.bag}: {info['frames']} frames, {len(self._pubs)} topics, "
                               f"rate {self.rate:g}{' (as fast as possible)' if self.rate == 0 else ''}"
                               f"{', looping' if self.loop else ''}")
        self.done: Future = Future()  # its result is the exit code
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="replay", daemon=True)
        self._thread.start()

    def _check_first_messages(self, info: dict) -> None:
        """The first message of every replayed topic deserialises with the installed type into the
        same field values the bag's own definition of the type gives (and a compressed image
        decodes); ReplayError naming the bag, topic and type otherwise."""
        from rclpy.serialization import deserialize_message

        types = {t["topic"]: t["type"] for t in info["topics"]}
        try:
            firsts = first_messages(self.bag, list(self._pubs))
        except (OSError, ValueError) as exc:
            raise ReplayError(f"cannot replay bag {self.bag}: {exc}") from None
        for topic, first in firsts.items():
            cls = self._decode[topic][0] if topic in self._decode else self._pubs[topic].msg_type
            where = f"cannot replay bag {self.bag}: the first message of topic {topic}"
            try:
                msg = deserialize_message(first.message.data, cls)
            except Exception as exc:
                raise ReplayError(f"{where} does not deserialise as the installed {types[topic]} "
                                  f"({type(exc).__name__}: {exc}); the bag's definition of the type differs from "
                                  "the installed one or the data is damaged") from None
            if first.decoded is not None:
                diff = field_difference(msg, first.decoded)
                if diff is not None:
                    raise ReplayError(f"{where} reads differently with the installed {types[topic]} than with the "
                                      f"bag's own definition of it ({diff}): the definitions differ")
            if topic in self._decode:
                try:
                    compressed_image_fields(msg, self._decode[topic][1])
                except ValueError as exc:
                    raise ReplayError(f"{where} is a CompressedImage that does not decode: {exc}") from None

    def _publish(self, topic: str, data: bytes) -> None:
        decode = self._decode.get(topic)
        if decode is None:
            self._pubs[topic].publish(data)
            return
        from rclpy.serialization import deserialize_message
        from sensor_msgs.msg import Image

        compressed = deserialize_message(data, decode[0])
        self._pubs[topic].publish(Image(header=compressed.header, **compressed_image_fields(compressed, decode[1])))

    def _number(self, name: str) -> float:
        value = self.get_parameter(name).value
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ReplayError(f"parameter {name!r} must be a number, got {value!r}")
        return float(value)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)

    def _sleep(self, seconds: float) -> bool:
        """Sleep unless stopped; False when the replay must stop."""
        return not (self._stop.wait(seconds) if seconds > 0 else self._stop.is_set())

    def _wait_for_subscribers(self) -> bool:
        deadline = time.monotonic() + self.wait_timeout
        while True:
            short = [(self._pubs[t], n) for t, n in self._wait_counts.items()
                     if self._pubs[t].get_subscription_count() < n]
            if not short:
                return True
            if time.monotonic() > deadline:
                for pub, n in short:
                    self.get_logger().warning(f"{pub.topic_name} has {pub.get_subscription_count()} of {n} "
                                              "subscribers after wait_timeout; starting anyway")
                return True
            if not self._sleep(0.02):
                return False

    def _run(self) -> None:
        code = EXIT_OK
        try:
            if self._wait_for_subscribers() and self._sleep(self.start_delay):
                self._replay()
                self._wait_for_acks()
        except Exception as exc:
            if not self._stop.is_set() and self.context.ok():  # else: publishing failed because of Ctrl-C
                bad_bag = isinstance(exc, (OSError, ValueError))
                self.get_logger().error(f"replay of {self.bag} failed: {exc}" if bad_bag else f"replay failed: {exc!r}")
                code = EXIT_BAD_INPUT if bad_bag else EXIT_FAILED
        finally:
            self.done.set_result(code)

    def _wait_for_acks(self) -> None:
        """Before exiting: reliable subscribers still fetching the last messages would lose them."""
        deadline = time.monotonic() + ACK_TIMEOUT_S
        for pub in self._pubs.values():
            while not pub.wait_for_all_acked(Duration(seconds=0.05)):
                if self._stop.is_set() or time.monotonic() > deadline:
                    return

    def _replay(self) -> None:
        start, passes = time.monotonic(), 0
        while True:
            messages = frames = 0
            log0 = first = None
            due = start
            for m in iter_messages(self.bag, list(self._pubs)):
                if self.rate > 0:
                    log0 = m.log_time_ns if log0 is None else log0
                    due = start + (m.log_time_ns - log0) / 1e9 / self.rate
                if not self._sleep(due - time.monotonic()):
                    return
                self._publish(m.topic, m.data)
                first = time.monotonic() if first is None else first
                messages += 1
                frames += m.topic == self._color
            passes += 1
            seconds = time.monotonic() - (first or start)
            fps = (frames - 1) / seconds if frames > 1 and seconds > 0 else 0.0
            if self.context.ok():  # a loop logs at most every 10 s
                self.get_logger().info(f"{f'pass {passes}: ' if self.loop else ''}replayed {messages} messages, "
                                       f"{frames} frames in {seconds:.2f} s ({fps:.1f} frames/s)",
                                       throttle_duration_sec=10.0 if self.loop else 0.0)
            if not self.loop or messages == 0:
                return
            gap = self._frame_gap_s / self.rate if self.rate > 0 else 0.0
            start = max(due + gap, time.monotonic())


def main(args: list[str] | None = None) -> int:
    warnings.simplefilter("ignore", BagTruncatedWarning)  # the node logs the damage once, at the start
    configure_ros_environment()  # loopback defaults before rclpy starts
    clean_stale_fastdds_shm()  # segments of killed participants (launcher/fastdds_shm.py)
    rclpy.init(args=args)
    node = None
    try:
        node = BagReplayNode()
        rclpy.spin_until_future_complete(node, node.done)
        return node.done.result() if node.done.done() else EXIT_OK
    except (ReplayError, ParameterException) as exc:
        rclpy.logging.get_logger("bag_replay_node").error(str(exc))
        return EXIT_BAD_INPUT
    except (KeyboardInterrupt, ExternalShutdownException):
        return EXIT_OK
    finally:
        if node is not None:
            node.stop()
            node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
