"""bag_replay_node on real recordings (written by rosbags): message-compressed MCAP and sqlite3
bags with short type names and image_transport-compressed images replay as decodable
sensor_msgs/Image messages a real rclpy subscriber receives; a topic whose first message does not
deserialise stops the node before it starts (exit 2, naming the topic)."""
from __future__ import annotations

import subprocess
import time

import numpy as np
import pytest

from perception_config.datasets.bag.messages import image_msg_to_depth, image_msg_to_rgb
from real_bags import NS0, PERIOD_NS, Spec, write_camera_bag
from ros_helpers import NodeProcess

pytestmark = pytest.mark.ros

CASES = {
    "db3-message-zstd-jpeg-compressedDepth-azure": Spec(storage="sqlite3", compression="message-zstd",
                                                        type_form="short", layout="azure_kinect", color="jpeg",
                                                        depth="compressedDepth-16UC1"),
    "mcap-message-zstd-short-names-raw-realsense": Spec(compression="message-zstd", type_form="short"),
}


def _stamp(msg) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def _base(topic: str) -> str:
    return topic.removesuffix("/compressedDepth").removesuffix("/compressed").lstrip("/")


@pytest.mark.parametrize("case", list(CASES))
def test_replay_publishes_decodable_images(ros_node, tmp_path, case):
    import rclpy
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, Image

    spec = CASES[case]
    expect = write_camera_bag(tmp_path / "bag", spec)
    topics = {role: _base(t) for role, t in spec.topics().items()}
    got: dict[str, list] = {"color": [], "depth": [], "camera_info": []}
    qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    subs = [ros_node.create_subscription(CameraInfo if role == "camera_info" else Image, topics[role],
                                         got[role].append, qos) for role in got]
    node = NodeProcess("bag_replay_node", {"bag": str(tmp_path / "bag"), "rate": 0.0, "start_delay": 0.3,
                                           "wait_for": [f"{topics[r]}:1" for r in got]},
                       tmp_path)
    try:
        t_end = time.monotonic() + 20.0
        while time.monotonic() < t_end and not all(len(v) >= spec.n for v in got.values()):
            rclpy.spin_once(ros_node, timeout_sec=0.05)
        while time.monotonic() < t_end and node.alive() and "replayed" not in node.output():
            time.sleep(0.05)  # the summary is logged after the last message; its acks need not be awaited here
        code = node.stop()
        out = node.output()
    finally:
        for s in subs:
            ros_node.destroy_subscription(s)
    assert code == 0, out
    assert all(len(v) == spec.n for v in got.values()), ({k: len(v) for k, v in got.items()}, out)
    for k, frame in enumerate(expect):
        color, depth, info = got["color"][k], got["depth"][k], got["camera_info"][k]
        assert _stamp(color) == _stamp(depth) == _stamp(info) == NS0 + k * PERIOD_NS
        np.testing.assert_array_equal(image_msg_to_rgb(color), frame.rgb)
        assert depth.encoding == "16UC1"
        np.testing.assert_array_equal(image_msg_to_depth(depth), frame.depth)
        np.testing.assert_allclose(np.asarray(info.k).reshape(3, 3), frame.K)
    assert f"replayed {4 * spec.n} messages, {spec.n} frames" in out, out


@pytest.mark.parametrize("case", ["garbage", "other_definition"])
def test_a_topic_that_does_not_deserialise_is_refused_before_the_start(tmp_path, case):
    """garbage: bytes that are no Image; other_definition: a valid Image whose bag definition
    lists width before height, so the installed type would read other values than the bag means."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    bag = tmp_path / "bad"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as wr:
        if case == "garbage":
            conn = wr.add_connection("/camera/color/image_raw", "sensor_msgs/msg/Image", typestore=ts)
            wr.write(conn, 1, b"\x00\x01\x00\x00" + b"\xff" * 40)  # CDR header, then no valid Image
            expected = "first message of topic /camera/color/image_raw does not deserialise"
        else:
            text = ts.generate_msgdef("sensor_msgs/msg/Image", ros_version=2)[0]
            swapped = text.replace("uint32 height\nuint32 width", "uint32 width\nuint32 height")
            assert swapped != text
            conn = wr.add_connection("/camera/color/image_raw", "sensor_msgs/msg/Image", msgdef=swapped,
                                     rihs01=ts.hash_rihs01("sensor_msgs/msg/Image"))
            img = T["sensor_msgs/msg/Image"](
                header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=0),
                                                frame_id="cam"),
                height=2, width=3, encoding="mono8", is_bigendian=0, step=3, data=np.zeros(6, np.uint8))
            wr.write(conn, 1, ts.serialize_cdr(img, "sensor_msgs/msg/Image"))
            expected = "reads differently with the installed sensor_msgs/msg/Image than with the bag's own definition"
    node = NodeProcess("bag_replay_node", {"bag": str(bag), "rate": 0.0}, tmp_path)
    try:
        node.proc.wait(20)
    except subprocess.TimeoutExpired:
        pass
    code = node.stop()
    out = node.output()
    assert code == 2, out
    assert "[ERROR]" in out and expected in out, out
    assert str(bag) in out and "Traceback" not in out, out
    if case == "other_definition":
        assert "height: 2 != 3" in out, out
