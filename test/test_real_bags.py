"""Real rosbag2 recordings in: bags written by `rosbags` (MCAP and sqlite3, chunk and message
compression, both type-name forms) and by the `mcap` library (lz4 chunks), with raw and
image_transport-compressed images in the topic layouts of RealSense, Azure Kinect, ZED and OAK-D
drivers, read back by the project's reader and summarised by `bag info`."""
from __future__ import annotations

import sqlite3
import struct
import warnings

import cv2
import numpy as np
import pytest
import yaml

from perception_config.datasets.bag import BagFormatError, ImageFormatError, bag_info, iter_messages, read_bag
from perception_config.datasets.bag.messages import image_msg_to_depth
from real_bags import NS0, Spec, compressed_depth, write_camera_bag

CASES = {  # id -> the recording
    "mcap-plain-realsense": Spec(),
    "mcap-chunk-zstd-short-names-azure": Spec(compression="chunk-zstd", type_form="short", layout="azure_kinect",
                                              color="bgr8", depth="32FC1"),
    "mcap-chunk-lz4-zed": Spec(compression="chunk-lz4", layout="zed", depth="32FC1"),
    "mcap-message-zstd-short-names-oak-jpeg-compressedDepth": Spec(compression="message-zstd", type_form="short",
                                                                   layout="oak", color="jpeg",
                                                                   depth="compressedDepth-16UC1"),
    "mcap-message-lz4-realsense-png-compressedDepth32": Spec(compression="message-lz4", layout="realsense_old",
                                                             color="png", depth="compressedDepth-32FC1"),
    "db3-plain-realsense-jpeg-png-depth": Spec(storage="sqlite3", color="jpeg", depth="png"),
    "db3-message-zstd-short-names-azure": Spec(storage="sqlite3", compression="message-zstd", type_form="short",
                                               layout="azure_kinect", depth="compressedDepth-32FC1"),
}
LAYOUT_NAMES = {"realsense": "RealSense", "realsense_old": "RealSense", "azure_kinect": "Azure Kinect", "zed": "ZED",
                "oak": "OAK-D"}


def assert_frames(expect, got, spec: Spec) -> None:
    assert len(got) == len(expect) == spec.n
    for a, b in zip(expect, got):
        assert b.stamp == pytest.approx(a.stamp, abs=1e-9)
        np.testing.assert_allclose(b.K, a.K)
        np.testing.assert_array_equal(b.rgb, a.rgb)  # jpeg: `a` is what OpenCV's decoder gives
        assert b.depth.dtype == np.float32
        np.testing.assert_array_equal(np.isnan(b.depth), np.isnan(a.depth))
        np.testing.assert_allclose(b.depth, a.depth, rtol=1e-6, equal_nan=True)


@pytest.mark.parametrize("case", list(CASES))
def test_reads_real_recordings(tmp_path, case):
    spec = CASES[case]
    path = tmp_path / "bag"
    expect = write_camera_bag(path, spec)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing dropped, nothing to warn about
        got = list(read_bag(path))
    assert_frames(expect, got, spec)
    topics = spec.topics()
    info = bag_info(path)
    assert info["storage"] == spec.storage
    assert info["frames"] == spec.n and info["message_count"] == 4 * spec.n
    ft = info["frame_topics"]
    assert (ft["color"], ft["depth"], ft["camera_info"]) == (topics["color"], topics["depth"], topics["camera_info"])
    assert ft["layout"].startswith(LAYOUT_NAMES[spec.layout])
    kind, _, fmt = spec.compression.partition("-")
    assert info["compression"] == {"chunk": [fmt if kind == "chunk" else "none"],
                                   "message": [fmt if kind == "message" else "none"]}
    by_topic = {t["topic"]: t for t in info["topics"]}
    assert by_topic[topics["color"]]["type"] == ("sensor_msgs/msg/CompressedImage" if spec.color in ("jpeg", "png")
                                                 else "sensor_msgs/msg/Image")  # both type-name forms read alike
    assert all(t["count"] == spec.n for t in info["topics"])
    assert all(t["compression"] == (fmt if kind == "message" else "none") for t in info["topics"])
    # The raw messages of iter_messages are plain CDR, whatever the bag's compression.
    assert all(m.data[:2] in (b"\x00\x01", b"\x00\x00") for m in iter_messages(path))


def test_a_bare_mcap_file_with_message_compression_and_short_type_names(tmp_path):
    """The issue's recording: a .mcap file alone (no metadata.yaml to say it is compressed)."""
    spec = Spec(compression="message-zstd", type_form="short")
    expect = write_camera_bag(tmp_path / "rec", spec)
    (mcap,) = (tmp_path / "rec").glob("*.mcap")
    assert_frames(expect, list(read_bag(mcap)), spec)
    info = bag_info(mcap)
    assert info["compression"]["message"] == ["zstd"] and info["frames"] == spec.n


def test_two_cameras_cannot_choose_and_list_the_candidates(tmp_path, capsys):
    from perception_config.cli import main
    from real_bags import _write

    a, b = Spec(layout="realsense"), Spec(layout="zed")
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    records = []
    for spec in (a, b):
        write_camera_bag(tmp_path / spec.layout, spec)
        records += [(m.topic, m.type, m.log_time_ns, m.data) for m in iter_messages(tmp_path / spec.layout)]
    _write(tmp_path / "both", Spec(), ts, sorted(records, key=lambda r: r[2]))
    info = bag_info(tmp_path / "both")
    assert "frame_topics" not in info and "cannot tell which camera" in info["frame_topics_error"]
    assert {lay["color"] for lay in info["camera_layouts"]} == {a.topics()["color"], b.topics()["color"]}
    assert main(["bag", "info", str(tmp_path / "both")]) == 0
    out = capsys.readouterr().out
    assert "cannot choose the frame topics" in out and a.topics()["depth"] in out and b.topics()["depth"] in out
    with pytest.raises(BagFormatError, match="2 complete camera layouts"):
        read_bag(tmp_path / "both")
    t = b.topics()
    got = list(read_bag(tmp_path / "both", color_topic=t["color"], depth_topic=t["depth"],
                        camera_info_topic=t["camera_info"]))
    assert len(got) == b.n


def test_cli_bag_info_names_compression_layout_and_frame_topics(tmp_path, capsys):
    from perception_config.cli import main

    spec = Spec(storage="sqlite3", compression="message-zstd", layout="oak", color="jpeg",
                depth="compressedDepth-16UC1")
    write_camera_bag(tmp_path / "oak", spec)
    assert main(["bag", "info", str(tmp_path / "oak")]) == 0
    out = capsys.readouterr().out
    assert "storage: sqlite3" in out and "compression: chunks none; messages zstd" in out
    assert "would read frames from: (OAK-D" in out
    assert f"color         {spec.topics()['color']}" in out and f"depth         {spec.topics()['depth']}" in out
    assert "sensor_msgs/msg/CompressedImage" in out and "zstd-compressed" in out


def test_db3_without_message_definitions_uses_known_ones(tmp_path):
    """rosbag2 sqlite3 bags before Iron store no message definitions."""
    spec = Spec(storage="sqlite3", color="png", depth="compressedDepth-16UC1")
    expect = write_camera_bag(tmp_path / "old", spec)
    (db3,) = (tmp_path / "old").glob("*.db3")
    with sqlite3.connect(db3) as db:
        db.execute("DELETE FROM message_definitions")
    assert_frames(expect, list(read_bag(tmp_path / "old")), spec)


def test_damaged_compressed_message_names_file_topic_and_time(tmp_path):
    spec = Spec(storage="sqlite3", compression="message-zstd")
    write_camera_bag(tmp_path / "bad", spec)
    (db3,) = (tmp_path / "bad").glob("*.db3")
    with sqlite3.connect(db3) as db:
        topic = spec.topics()["color"]
        db.execute("UPDATE messages SET data = substr(data, 1, 20) WHERE id = (SELECT MIN(m.id) FROM messages m "
                   "JOIN topics t ON m.topic_id = t.id WHERE t.name = ?)", (topic,))
    with pytest.raises(BagFormatError, match=rf"{db3.name}: topic {topic}, log time {(NS0 + 3_000_000) / 1e9:.9f} s: "
                       "damaged zstd-compressed message"):
        list(read_bag(tmp_path / "bad"))


def test_not_a_rosbag2_database_and_file_compression_are_named(tmp_path):
    bad = tmp_path / "x.db3"
    with sqlite3.connect(bad) as db:
        db.execute("CREATE TABLE other (a)")
    with pytest.raises(BagFormatError, match="x.db3: not a readable rosbag2 sqlite3 database"):
        read_bag(bad)
    write_camera_bag(tmp_path / "f", Spec())
    meta = yaml.safe_load((tmp_path / "f" / "metadata.yaml").read_text())
    meta["rosbag2_bagfile_information"].update(compression_mode="FILE", compression_format="zstd")
    (tmp_path / "f" / "metadata.yaml").write_text(yaml.safe_dump(meta))
    with pytest.raises(BagFormatError, match="compressed whole.*decompress them first"):
        bag_info(tmp_path / "f")


def test_compressed_depth_formats():
    from types import SimpleNamespace

    mm = np.array([[0, 500, 1000], [65535, 1, 4000]], np.uint16)
    msg = SimpleNamespace(format="16UC1; compressedDepth png", data=compressed_depth(mm / 1000.0, "16UC1"))
    np.testing.assert_array_equal(image_msg_to_depth(msg), np.where(mm == 0, np.nan, mm / np.float32(1000)).astype(
        np.float32))
    d = np.array([[np.nan, 0.3, 1.0], [2.5, 9.0, 0.25]], np.float32)
    msg = SimpleNamespace(format="32FC1; compressedDepth", data=compressed_depth(d, "32FC1"))
    got = image_msg_to_depth(msg)
    assert np.isnan(got[0, 0]) and np.all(np.isfinite(got.flat[1:]))
    err = np.abs(got - d).flat[1:]
    assert np.all(err <= d.flat[1:] ** 2 / 100.0 + 1e-6), err  # one quantisation step of A / depth
    with pytest.raises(ImageFormatError, match="rvl is not supported"):
        image_msg_to_depth(SimpleNamespace(format="16UC1; compressedDepth rvl", data=struct.pack("<iff", 2, 0, 0)))
    with pytest.raises(ImageFormatError, match="cannot decode"):
        image_msg_to_depth(SimpleNamespace(format="16UC1; compressedDepth png", data=b"\0" * 40))
    ok, jpg = cv2.imencode(".jpg", np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(ImageFormatError, match="expected a 16-bit single-channel PNG"):
        image_msg_to_depth(SimpleNamespace(format="jpeg", data=jpg.tobytes()))


def test_topic_choice_prefers_raw_images_and_knows_openni():
    from perception_config.datasets.bag import resolve_topics

    img, comp, info = "sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/CameraInfo"
    both = {"/camera/color/image_raw": img, "/camera/color/image_raw/compressed": comp,
            "/camera/aligned_depth_to_color/image_raw": img,
            "/camera/aligned_depth_to_color/image_raw/compressedDepth": comp, "/camera/color/camera_info": info}
    ft = resolve_topics(both)
    assert (ft.color, ft.depth, ft.layout) == ("/camera/color/image_raw", "/camera/aligned_depth_to_color/image_raw",
                                               "RealSense (realsense2_camera)")
    openni = {"/camera/rgb/image_raw": img, "/camera/depth_registered/image_raw": img, "/camera/depth/image_raw": img,
              "/camera/rgb/camera_info": info, "/camera/ir/image": img}
    ft = resolve_topics(openni)
    assert (ft.color, ft.depth, ft.camera_info) == ("/camera/rgb/image_raw", "/camera/depth_registered/image_raw",
                                                    "/camera/rgb/camera_info")
    assert ft.layout.startswith("OpenNI")
    # No known layout: by name, and a tie is an error listing the candidates.
    tie = {"/a/color/image_raw": img, "/b/color/image_raw": img, "/a/color/camera_info": info}
    with pytest.raises(BagFormatError, match=r"cannot tell the colour image topic: candidates \['/a/color/image_raw', "
                                             r"'/b/color/image_raw'\]"):
        resolve_topics(tie, "x.mcap")


def test_the_issue_recording_rgb_only_image_raw(tmp_path, capsys):
    """A driver's recording as reported by a user: sensor_msgs/Image on /camera/image_raw, message-level zstd, the type
    written `sensor_msgs/Image`; bag info named no colour topic and the reader returned the
    compressed payloads."""
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from perception_config.cli import main
    from real_bags import K

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    rgb = np.arange(6 * 8 * 3, dtype=np.uint8).reshape(6, 8, 3)
    hdr = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=5, nanosec=0), frame_id="cam")
    img = T["sensor_msgs/msg/Image"](header=hdr, height=6, width=8, encoding="rgb8", is_bigendian=0, step=24,
                                     data=rgb.flatten())
    info = T["sensor_msgs/msg/CameraInfo"](
        header=hdr, height=6, width=8, distortion_model="plumb_bob", d=np.zeros(5), k=K.flatten(),
        r=np.eye(3).flatten(), p=np.hstack([K, np.zeros((3, 1))]).flatten(), binning_x=0, binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
    wr = Writer(tmp_path / "rec", version=9, storage_plugin=StoragePlugin.MCAP)
    wr.set_compression(CompressionMode.MESSAGE, CompressionFormat.ZSTD)
    with wr:
        for topic, t, msg in (("/camera/image_raw", "sensor_msgs/msg/Image", img),
                              ("/camera/camera_info", "sensor_msgs/msg/CameraInfo", info)):
            conn = wr.add_connection(topic, t.replace("/msg/", "/"), msgdef=ts.generate_msgdef(t, ros_version=2)[0],
                                     rihs01=ts.hash_rihs01(t))
            wr.write(conn, 5 * 10**9, ts.serialize_cdr(msg, t))
    (frame,) = read_bag(tmp_path / "rec")
    np.testing.assert_array_equal(frame.rgb, rgb)
    assert frame.depth is None
    assert main(["bag", "info", str(tmp_path / "rec")]) == 0
    out = capsys.readouterr().out
    assert "color         /camera/image_raw" in out and "depth         none (RGB-only)" in out
    assert "messages zstd" in out and "sensor_msgs/msg/Image" in out
