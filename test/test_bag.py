"""MCAP bags: BOP frames -> rosbag2-compatible MCAP -> Frames, checked against independent
readers/writers (mcap, rosbags), interrupted and truncated recordings, malformed images."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml

from perception_config.core.geometry import Pose, exp_so3, nearest_rotation
from perception_config.core.scene import Frame, SceneObject
from perception_config.datasets import bag as bagmod
from perception_config.datasets.bag import (
    BagFormatError,
    BagTruncatedError,
    BagTruncatedWarning,
    BagWarning,
    bag_info,
    iter_messages,
    read_bag,
    write_bag,
    write_frames,
)
from perception_config.datasets.bag.definitions import WRITTEN_TYPES, definition, interfaces_msg_dir, type_hash

REPO = Path(__file__).resolve().parents[1]
EPOCH = 1_700_000_000 * 10**9


# --------------------------------------------------------------------------- helpers

def make_frame(i: int, h: int = 48, w: int = 64, seed: int = 0, n_obj: int = 3) -> Frame:
    rng = np.random.default_rng(seed * 1000 + i)
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    mm = rng.integers(250, 3000, (h, w))
    depth = mm.astype(np.float32) / np.float32(1000)  # whole millimetres, as BOP and 16UC1 hold them
    depth[rng.random((h, w)) < 0.15] = np.nan
    K = np.array([[500.0 + i, 0.0, w / 2 + 0.25], [0.0, 510.5, h / 2 - 0.5], [0.0, 0.0, 1.0]])
    objs = [SceneObject(j + 1 + i % 2, gt=Pose(exp_so3(rng.normal(size=3)), rng.normal(size=3) * 0.1 + [0, 0, 0.8]))
            for j in range(n_obj)]
    return Frame(rgb, depth, K, stamp=123.0, scene_id=3, im_id=10 + i, objects=objs)


def assert_same_frame(a: Frame, b: Frame, exact_depth: bool = True, project_R: bool = False) -> None:
    assert b.rgb.dtype == np.uint8 and b.depth.dtype == np.float32
    assert np.array_equal(a.rgb, b.rgb)
    assert np.array_equal(np.isnan(a.depth), np.isnan(b.depth))
    if exact_depth:
        assert np.array_equal(a.depth, b.depth, equal_nan=True)
    else:
        ok = ~np.isnan(a.depth)
        assert np.array_equal(np.rint(a.depth[ok] * 1000), np.rint(b.depth[ok] * 1000))
    assert np.array_equal(a.K, b.K)
    ga = [o for o in a.objects if o.gt is not None]
    assert [o.obj_id for o in ga] == [o.obj_id for o in b.objects]
    for oa, ob in zip(ga, b.objects):
        Ra = nearest_rotation(oa.gt.R) if project_R else oa.gt.R
        assert np.abs(Ra - ob.gt.R).max() < 1e-9
        assert np.abs(oa.gt.t - ob.gt.t).max() < 1e-9


def make_bop(root: Path, scenes=(1, 2), images=3, h=48, w=64) -> list[Frame]:
    from perception_config.datasets.bop_writer import SceneWriter

    frames = []
    for sid in scenes:
        with SceneWriter(root, "test", sid) as sw:
            for im in range(images):
                f = make_frame(len(frames), h, w, seed=sid)
                f.scene_id, f.im_id = sid, im
                sw.add(f)
                frames.append(f)
    return frames


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory) -> tuple[Path, list[Frame]]:
    d = tmp_path_factory.mktemp("small")
    frames = [make_frame(i) for i in range(6)]
    n = write_frames(frames, d / "bag")
    assert n == 6
    return d / "bag", frames


# --------------------------------------------------------------------------- schemas

def _ros_share(pkg: str) -> Path | None:
    """share/<pkg> of this interpreter's ROS prefix (the PyPI wheels), None when not installed."""
    d = Path(sys.prefix) / "share" / pkg
    return d if d.is_dir() else None


def _fields(msg_text: str, type_name: str) -> list[tuple]:
    """(name, type) of a .msg text's fields as rosbags parses them (comments and constants aside)."""
    from rosbags.typesys import get_types_from_msg

    return [(n, repr(t)) for n, t in get_types_from_msg(msg_text, type_name)[type_name][1]]


@pytest.mark.parametrize("type_name", WRITTEN_TYPES)
def test_definitions_match_the_installed_ros_types(type_name):
    """The typestore's definition has the installed .msg's fields and ROS's own RIHS01 hash."""
    pkg, _, name = type_name.split("/")
    text = definition(type_name)
    sep = "=" * 80 + "\n"
    assert all(part.startswith("MSG: ") for part in text.split(sep)[1:])  # rosbag2's nesting form
    if pkg == "perception_config_interfaces":
        msg = interfaces_msg_dir() / f"{name}.msg"
        assert _fields(text.split(sep)[0], type_name) == _fields(msg.read_text(), type_name)
    share = _ros_share(pkg)
    if share is None or not (share / "msg" / f"{name}.json").is_file():
        pytest.skip(f"{pkg} not installed in {sys.prefix}")
    if pkg != "perception_config_interfaces":
        assert _fields(text.split(sep)[0], type_name) == _fields((share / "msg" / f"{name}.msg").read_text(), type_name)
    described = json.loads((share / "msg" / f"{name}.json").read_text())["type_hashes"]
    assert type_hash(type_name) == next(h["hash_string"] for h in described if h["type_name"] == type_name)


def test_definitions_parse_with_mcap_ros2_and_rosbags():
    from mcap_ros2._dynamic import generate_dynamic
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    for t in WRITTEN_TYPES:
        text = definition(t)
        assert t in generate_dynamic(t, text)
        store = get_typestore(Stores.EMPTY)
        sep = "=" * 80 + "\n"
        types = get_types_from_msg(text.split(sep)[0], t)
        for part in text.split(sep)[1:]:
            head, body = part.split("\n", 1)
            pkg, name = head[5:].split("/")
            types.update(get_types_from_msg(body, f"{pkg}/msg/{name}"))
        store.register(types)
        assert store.hash_rihs01(t) == type_hash(t)
    with pytest.raises(BagFormatError, match="no message definition for 'nope_msgs/msg/Nothing'"):
        definition("nope_msgs/msg/Nothing")


def test_rclpy_deserialises_every_topic_of_our_bag(small_bag):
    """What rosbag2 does when it plays a bag: the raw CDR goes to subscribers, which deserialise it
    with the installed message types (no definition text involved)."""
    import importlib

    from rclpy.serialization import deserialize_message

    path, frames = small_bag
    seen: dict[str, object] = {}
    for topic, type_name, _t, raw in iter_messages(path):
        if topic not in seen:
            pkg, _, name = type_name.split("/")
            seen[topic] = deserialize_message(raw, getattr(importlib.import_module(f"{pkg}.msg"), name))
    assert len(seen) == 5
    img = seen["/camera/color/image_raw"]
    assert (img.height, img.width, img.encoding) == (*frames[0].rgb.shape[:2], "rgb8")
    assert bytes(img.data) == frames[0].rgb.tobytes()
    gt = seen["/perception/ground_truth"]
    assert list(gt.object_ids) == [str(o.obj_id) for o in frames[0].objects]
    assert gt.poses[0].position.z == pytest.approx(frames[0].objects[0].gt.t[2], abs=1e-12)
    assert seen["/camera/camera_info"].header.frame_id == "camera_color_optical_frame"


# --------------------------------------------------------------------------- round trips

def test_round_trip_frames(small_bag):
    path, frames = small_bag
    assert sorted(p.name for p in path.iterdir()) == ["bag_0.mcap", "metadata.yaml"]
    out = list(read_bag(path))
    assert len(out) == len(frames)
    for i, (a, b) in enumerate(zip(frames, out)):
        assert_same_frame(a, b)
        assert b.stamp == pytest.approx(1.7e9 + i / 10.0, abs=1e-6)
        assert (b.scene_id, b.im_id) == (a.scene_id, a.im_id)
    # Reading the .mcap file alone gives the same.
    out2 = list(read_bag(path / "bag_0.mcap"))
    assert [f.stamp for f in out2] == [f.stamp for f in out]


def test_round_trip_32fc1_keeps_metres_and_nan(tmp_path):
    frames = [make_frame(i, seed=5) for i in range(2)]
    frames[0].depth[0, :5] = np.float32(0.12345678)  # sub-millimetre
    write_frames(frames, tmp_path / "f.mcap", rate_hz=30.0, depth_encoding="32FC1", compression="none")
    out = list(read_bag(tmp_path / "f.mcap"))
    for a, b in zip(frames, out):
        assert_same_frame(a, b, exact_depth=True)
    assert out[1].stamp - out[0].stamp == pytest.approx(1 / 30.0, abs=1e-6)


def test_depth_16uc1_is_millimetres_with_zero_for_missing():
    d = np.array([[0.5, np.nan, 0.0], [70.0, -1.0, 0.0004]], dtype=np.float32)
    f = bagmod.depth_to_image_fields(d)
    mm = np.frombuffer(f["data"], "<u2").reshape(2, 3)
    assert mm.tolist() == [[500, 0, 0], [0, 0, 0]]
    assert (f["encoding"], f["step"], f["is_bigendian"]) == ("16UC1", 6, 0)


def test_write_bag_from_bop_dataset_and_metadata(tmp_path):
    from perception_config.datasets.bop import BopDataset

    make_bop(tmp_path / "ds")
    n = write_bag(tmp_path / "ds", tmp_path / "rec", rate_hz=5.0, progress=False)
    assert n == 6
    ds = BopDataset(tmp_path / "ds")
    out = list(read_bag(tmp_path / "rec"))
    assert [(f.scene_id, f.im_id) for f in out] == ds.image_keys()
    for i, (key, b) in enumerate(zip(ds.image_keys(), out)):
        assert_same_frame(ds.load_frame(*key, with_models=False), b)  # bit-exact depth, like bop_images.read_depth
        assert b.stamp == pytest.approx(1.7e9 + i / 5.0, abs=1e-6)

    meta = yaml.safe_load((tmp_path / "rec" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == 9 and meta["storage_identifier"] == "mcap"
    assert meta["relative_file_paths"] == ["rec_0.mcap"]
    assert meta["message_count"] == 30
    assert meta["starting_time"]["nanoseconds_since_epoch"] == EPOCH
    assert meta["duration"]["nanoseconds"] == 5 * 200_000_000
    topics = {t["topic_metadata"]["name"]: t for t in meta["topics_with_message_count"]}
    assert topics["/camera/depth/image_raw"]["topic_metadata"]["type"] == "sensor_msgs/msg/Image"
    assert (topics["/perception/ground_truth"]["topic_metadata"]["type"]
            == "perception_config_interfaces/msg/ObjectPoses")
    assert all(t["message_count"] == 6 and t["topic_metadata"]["serialization_format"] == "cdr"
               for t in topics.values())
    assert meta["custom_data"]["split"] == "test"

    info = bag_info(tmp_path / "rec")
    assert info["frames"] == 6 and info["message_count"] == 30 and not info["truncated"]
    assert info["duration_s"] == pytest.approx(1.0) and info["start"] == pytest.approx(1.7e9)
    assert {t["topic"]: (t["type"], t["count"]) for t in info["topics"]}["/camera/color/image_raw"] == (
        "sensor_msgs/msg/Image", 6)


def test_mcap_layout_is_rosbag2(small_bag):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path, frames = small_bag
    with open(path / "bag_0.mcap", "rb") as f:
        r = make_reader(f, decoder_factories=[DecoderFactory()])
        assert r.get_header().profile == "ros2"
        s = r.get_summary()
        assert {c.message_encoding for c in s.channels.values()} == {"cdr"}
        assert {sc.encoding for sc in s.schemas.values()} == {"ros2msg"}
        assert {sc.name for sc in s.schemas.values()} == {
            "sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo", "std_msgs/msg/String",
            "perception_config_interfaces/msg/ObjectPoses"}
        for c in s.channels.values():
            assert c.metadata["topic_type_hash"].startswith("RIHS01_")
            assert yaml.safe_load(c.metadata["offered_qos_profiles"]) == []
        assert s.statistics.chunk_count == len(frames)  # one chunk per frame
        seen = {}
        for _schema, channel, message, msg in r.iter_decoded_messages():
            assert message.log_time == message.publish_time
            assert (message.log_time == msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
                    if hasattr(msg, "header") else True)
            if hasattr(msg, "header"):
                assert msg.header.frame_id == "camera_color_optical_frame"
            seen[channel.topic] = msg
        assert seen["/camera/depth/image_raw"].encoding == "16UC1"
        assert seen["/camera/color/image_raw"].encoding == "rgb8"
        ci = seen["/camera/camera_info"]
        assert ci.distortion_model == "plumb_bob" and list(ci.d) == [0.0] * 5
        assert np.allclose(np.array(ci.p).reshape(3, 4)[:, :3], frames[-1].K)
        assert (ci.width, ci.height) == (64, 48)
        assert json.loads(seen["/perception/frame_info"].data)["im_id"] == frames[-1].im_id
        md = {m.name: m.metadata for m in r.iter_metadata()}
        assert "rosbag2" in md and "perception_config" in md
        embedded = yaml.safe_load(md["rosbag2"]["serialized_metadata"])
        assert embedded["message_count"] == 5 * len(frames)


def test_rosbags_reads_our_bag(small_bag, tmp_path):
    from rosbags.highlevel import AnyReader

    path, frames = small_bag
    colors, depths, gts = [], [], []
    with AnyReader([path]) as reader:  # checks our RIHS01 hashes against the schemas too
        for conn, t, raw in reader.messages():
            m = reader.deserialize(raw, conn.msgtype)
            if conn.topic == "/camera/color/image_raw":
                colors.append((t, m.data.reshape(m.height, m.width, 3)))
            elif conn.topic == "/camera/depth/image_raw":
                depths.append(m.data.view("<u2").reshape(m.height, m.width))
            elif conn.topic == "/perception/ground_truth":
                gts.append(m)
    assert [t for t, _ in colors] == [EPOCH + i * 100_000_000 for i in range(len(frames))]
    for f, (_, rgb), mm, gt in zip(frames, colors, depths, gts):
        assert np.array_equal(rgb, f.rgb)
        valid = ~np.isnan(f.depth)
        assert np.array_equal(mm[valid], np.rint(f.depth[valid] * 1000).astype(np.uint16))
        assert np.all(mm[~valid] == 0)
        assert list(gt.object_ids) == [str(o.obj_id) for o in f.objects]
        assert gt.poses[0].position.z == pytest.approx(f.objects[0].gt.t[2], abs=1e-12)
    # A single .mcap file with metadata.yaml beside it is a bag directory for rosbags too.
    write_frames(frames[:2], tmp_path / "one" / "x.mcap")
    with AnyReader([tmp_path / "one"]) as reader:
        assert sum(1 for _ in reader.messages()) == 10


def test_output_path_rules(tmp_path):
    f = [make_frame(0)]
    write_frames(f, tmp_path / "a" / "first.mcap")
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["first.mcap", "metadata.yaml"]
    write_frames(f, tmp_path / "a" / "second.mcap")  # a second bag there: no metadata.yaml for it
    meta = yaml.safe_load((tmp_path / "a" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["relative_file_paths"] == ["first.mcap"]
    write_frames(f, tmp_path / "a" / "first.mcap")  # rewriting the described file keeps it described
    assert len(list(read_bag(tmp_path / "a" / "second.mcap"))) == 1
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x.txt").write_text("keep me")
    with pytest.raises(ValueError, match="not empty"):
        write_frames(f, tmp_path / "full")


def test_iter_messages_gives_raw_cdr_in_time_order(small_bag):
    from mcap.reader import make_reader

    path, frames = small_bag
    msgs = list(iter_messages(path))
    assert len(msgs) == 5 * len(frames)
    assert [m.log_time_ns for m in msgs] == sorted(m.log_time_ns for m in msgs)
    with open(path / "bag_0.mcap", "rb") as f:
        ref = [(c.topic, m.log_time, m.data) for _s, c, m in make_reader(f).iter_messages()]
    assert [(m.topic, m.log_time_ns, m.data) for m in msgs] == ref
    only = list(iter_messages(path, topics=["/camera/camera_info"]))
    assert {m.type for m in only} == {"sensor_msgs/msg/CameraInfo"} and len(only) == len(frames)
    assert isinstance(only[0].data, bytes)


def test_cli_bag_info_and_write(small_bag, tmp_path, capsys):
    from perception_config.cli import main

    path, _ = small_bag
    assert main(["bag", "info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "/camera/color/image_raw" in out and "frames: 6" in out
    make_bop(tmp_path / "ds", scenes=(4,), images=2)
    assert main(["bag", "write", "--dataset", str(tmp_path / "ds"), "--out", str(tmp_path / "o.mcap"), "--quiet"]) == 0
    assert len(list(read_bag(tmp_path / "o.mcap"))) == 2


def test_real_lmo_frame_round_trip(lmo_root, lmo_dataset, tmp_path):
    ds = lmo_dataset
    n = write_bag(lmo_root, tmp_path / "lmo", progress=False)
    out = list(read_bag(tmp_path / "lmo"))
    assert n == len(out) == len(ds.image_keys())
    for key, b in zip(ds.image_keys(), out):
        a = ds.load_frame(*key, with_models=False)
        assert (b.scene_id, b.im_id) == key
        # BOP stores R with a few digits (orthonormal to ~1e-4): the bag carries the nearest rotation.
        assert_same_frame(a, b, exact_depth=False, project_R=True)
        for oa, ob in zip(a.objects, b.objects):
            assert np.abs(oa.gt.R - ob.gt.R).max() < 1e-3


# --------------------------------------------------------------------------- real rosbag2 recordings

def _rosbags_camera_bag(path: Path, color_enc: str, depth_enc: str, n: int = 4, jitter_ns: int = 0,
                        h: int = 24, w: int = 32):
    """A rosbag2 MCAP bag written by rosbags, laid out like a RealSense driver's recording."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    Image, CameraInfo = ts.types["sensor_msgs/msg/Image"], ts.types["sensor_msgs/msg/CameraInfo"]
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    RoI = ts.types["sensor_msgs/msg/RegionOfInterest"]
    K = np.array([[300.0, 0, 16.5], [0, 301.0, 12.25], [0, 0, 1]])
    rng = np.random.default_rng(1)
    expect = []

    def header(ns: int, frame: str):
        return Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame)

    def image(ns, enc, arr, frame):
        arr = np.ascontiguousarray(arr)
        step = arr.shape[1] * (arr.itemsize * (arr.shape[2] if arr.ndim == 3 else 1))
        return Image(header=header(ns, frame), height=arr.shape[0], width=arr.shape[1], encoding=enc,
                     is_bigendian=0, step=step, data=np.frombuffer(arr.tobytes(), np.uint8))

    def info(ns, frame, ww, hh):
        return CameraInfo(header=header(ns, frame), height=hh, width=ww, distortion_model="plumb_bob",
                          d=np.zeros(5), k=K.flatten(), r=np.eye(3).flatten(),
                          p=np.hstack([K, np.zeros((3, 1))]).flatten(), binning_x=0, binning_y=0,
                          roi=RoI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))

    ns0 = 1_720_000_000 * 10**9 + 123_456
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as wr:
        c_col = wr.add_connection("/camera/camera/color/image_raw", "sensor_msgs/msg/Image", typestore=ts)
        c_info = wr.add_connection("/camera/camera/color/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts)
        c_dep = wr.add_connection("/camera/camera/aligned_depth_to_color/image_raw", "sensor_msgs/msg/Image",
                                  typestore=ts)
        c_dinfo = wr.add_connection("/camera/camera/aligned_depth_to_color/camera_info", "sensor_msgs/msg/CameraInfo",
                                    typestore=ts)
        c_raw = wr.add_connection("/camera/camera/depth/image_rect_raw", "sensor_msgs/msg/Image", typestore=ts)
        c_ir = wr.add_connection("/camera/camera/infra1/image_rect_raw", "sensor_msgs/msg/Image", typestore=ts)
        for i in range(n):
            t = ns0 + i * 33_333_333
            rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
            if color_enc == "bgr8":
                carr = rgb[:, :, ::-1]
            elif color_enc == "mono8":
                rgb = np.repeat(rng.integers(0, 256, (h, w, 1), dtype=np.uint8), 3, axis=2)
                carr = rgb[:, :, 0]
            else:
                carr = rgb
            mm = rng.integers(200, 4000, (h, w)).astype(np.uint16)
            mm[rng.random((h, w)) < 0.2] = 0
            depth = mm.astype(np.float32) / np.float32(1000)
            depth[mm == 0] = np.nan
            if depth_enc == "32FC1":
                darr = depth.copy()
                darr[0, 0], darr[0, 1] = np.float32(0.0), np.float32(np.inf)
                depth[0, 0] = depth[0, 1] = np.nan
            else:
                darr = mm
            td = t + jitter_ns
            # log times: later than the stamps; the depth of a frame arrives before its colour
            wr.write(c_raw, td + 1_000_000,
                     ts.serialize_cdr(image(td, "16UC1", mm[:, :-2], "camera_depth_optical_frame"),
                                      "sensor_msgs/msg/Image"))
            wr.write(c_dep, td + 2_000_000, ts.serialize_cdr(image(td, depth_enc, darr, "camera_color_optical_frame"),
                                                             "sensor_msgs/msg/Image"))
            wr.write(c_dinfo, td + 2_000_000, ts.serialize_cdr(info(td, "camera_color_optical_frame", w, h),
                                                               "sensor_msgs/msg/CameraInfo"))
            wr.write(c_ir, t + 2_500_000,
                     ts.serialize_cdr(image(t, "mono8", rgb[:, :, 0], "camera_infra1_optical_frame"),
                                      "sensor_msgs/msg/Image"))
            wr.write(c_col, t + 3_000_000, ts.serialize_cdr(image(t, color_enc, carr, "camera_color_optical_frame"),
                                                            "sensor_msgs/msg/Image"))
            wr.write(c_info, t + 3_000_000, ts.serialize_cdr(info(t, "camera_color_optical_frame", w, h),
                                                             "sensor_msgs/msg/CameraInfo"))
            expect.append(Frame(rgb, depth, K, stamp=t / 1e9))
    return expect


@pytest.mark.parametrize("color_enc,depth_enc", [("bgr8", "32FC1"), ("rgb8", "16UC1"), ("mono8", "16UC1")])
def test_reads_realsense_style_bag_written_by_rosbags(tmp_path, color_enc, depth_enc):
    expect = _rosbags_camera_bag(tmp_path / "rs", color_enc, depth_enc)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = list(read_bag(tmp_path / "rs"))
    assert len(out) == len(expect)
    for a, b in zip(expect, out):
        assert_same_frame(a, b)
        assert b.stamp == pytest.approx(a.stamp, abs=1e-9)
        assert b.objects == []
    info = bag_info(tmp_path / "rs")
    assert info["frame_topics"]["depth"] == "/camera/camera/aligned_depth_to_color/image_raw"
    assert info["frame_topics"]["color"] == "/camera/camera/color/image_raw"
    assert info["frame_topics"]["camera_info"] == "/camera/camera/color/camera_info"


def test_stamps_matched_within_tolerance(tmp_path):
    expect = _rosbags_camera_bag(tmp_path / "rs", "rgb8", "16UC1", n=3, jitter_ns=2_000_000)
    out = list(read_bag(tmp_path / "rs"))  # depth stamped 2 ms after colour: nearest within 20 ms
    assert len(out) == 3 and out[0].stamp == pytest.approx(expect[0].stamp, abs=1e-9)
    with pytest.warns(BagWarning, match="dropped 3 incomplete"):
        assert list(read_bag(tmp_path / "rs", sync_tolerance_s=0.0)) == []
    # Explicit topics must exist; an explicit wrong one is named in the error.
    with pytest.raises(BagFormatError, match="/nope"):
        list(read_bag(tmp_path / "rs", depth_topic="/nope"))
    # The unregistered depth topic has another size: a clear error, not a silently cropped frame.
    with pytest.raises(BagFormatError, match="registered"):
        list(read_bag(tmp_path / "rs", depth_topic="/camera/camera/depth/image_rect_raw"))


# --------------------------------------------------------------------------- malformed data

def _custom_bag(path: Path, color: dict, depth: dict, info: dict | None = None, stamp: int = EPOCH) -> Path:
    """One frame written with mcap-ros2-support's own Writer, fields as given."""
    from mcap_ros2.writer import Writer

    hdr = {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9}, "frame_id": "cam"}
    with open(path, "wb") as f, Writer(f) as w:
        s_img = w.register_msgdef("sensor_msgs/msg/Image", definition("sensor_msgs/msg/Image"))
        s_info = w.register_msgdef("sensor_msgs/msg/CameraInfo", definition("sensor_msgs/msg/CameraInfo"))
        w.write_message("/camera/color/image_raw", s_img, {"header": hdr, **color}, log_time=stamp)
        w.write_message("/camera/depth/image_raw", s_img, {"header": hdr, **depth}, log_time=stamp)
        ci = bagmod.camera_info_fields(np.array([[100.0, 0, 4], [0, 100, 3], [0, 0, 1]]), color["width"],
                                       color["height"])
        ci.update(info or {})
        w.write_message("/camera/camera_info", s_info, {"header": hdr, **ci}, log_time=stamp)
    return path


def _rgb(h=6, w=8):
    return bagmod.rgb_to_image_fields(np.arange(h * w * 3, dtype=np.uint8).reshape(h, w, 3))


def _depth(h=6, w=8):
    return bagmod.depth_to_image_fields(np.full((h, w), 0.5, np.float32))


def test_custom_writer_frame_reads(tmp_path):
    out = list(read_bag(_custom_bag(tmp_path / "ok.mcap", _rgb(), _depth())))
    assert len(out) == 1 and out[0].rgb.shape == (6, 8, 3) and np.all(out[0].depth == np.float32(0.5))


def test_padded_step_and_big_endian_are_decoded():
    rgb = np.arange(6 * 8 * 3, dtype=np.uint8).reshape(6, 8, 3)
    padded = np.zeros((6, 8 * 3 + 5), np.uint8)
    padded[:, :24] = rgb.reshape(6, 24)
    msg = type("M", (), dict(height=6, width=8, encoding="rgb8", is_bigendian=0, step=29, data=padded.tobytes()))
    assert np.array_equal(bagmod.image_msg_to_rgb(msg), rgb)
    mm = np.array([[0, 1000, 65535]], ">u2")
    msg = type("M", (), dict(height=1, width=3, encoding="16UC1", is_bigendian=1, step=6, data=mm.tobytes()))
    d = bagmod.image_msg_to_depth(msg)
    assert np.isnan(d[0, 0]) and d[0, 1] == np.float32(1.0) and d[0, 2] == pytest.approx(65.535)


@pytest.mark.parametrize("case,color,depth,info,topic,match", [
    ("step", {**_rgb(), "step": 20}, _depth(), None, "/camera/color/image_raw", "step 20 is smaller"),
    ("size", {**_rgb(), "data": _rgb()["data"][:-3]}, _depth(), None, "/camera/color/image_raw", "data bytes"),
    ("encoding", {**_rgb(), "encoding": "yuv422"}, _depth(), None, "/camera/color/image_raw",
     "unsupported colour encoding 'yuv422'"),
    ("depth_encoding", _rgb(), {**_depth(), "encoding": "8UC1"}, None, "/camera/depth/image_raw",
     "unsupported depth encoding"),
    ("mismatch", _rgb(), _depth(4, 8), None, "/camera/depth/image_raw", "8x4 but colour image"),
    ("info_size", _rgb(), _depth(), {"width": 640, "height": 480}, "/camera/camera_info",
     "640x480 images but the images are 8x6"),
    ("info_k", _rgb(), _depth(), {"k": [0.0] * 9}, "/camera/camera_info", "no valid intrinsics"),
])
def test_malformed_images_raise_clear_errors(tmp_path, case, color, depth, info, topic, match):
    path = _custom_bag(tmp_path / f"{case}.mcap", color, depth, info)
    with pytest.raises(BagFormatError, match=match) as ei:
        list(read_bag(path))
    assert str(path) in str(ei.value) and topic in str(ei.value)


def test_not_an_mcap_file(tmp_path):
    (tmp_path / "x.mcap").write_bytes(b"SQLite format 3\x00" + b"\x00" * 100)
    with pytest.raises(BagFormatError, match="sqlite3"):
        list(read_bag(tmp_path / "x.mcap"))
    (tmp_path / "y.mcap").write_text("hello world, not a bag")
    with pytest.raises(BagFormatError, match="not an MCAP file"):
        bag_info(tmp_path / "y.mcap")


# --------------------------------------------------------------------------- truncation

def test_truncated_file_yields_a_prefix_of_complete_frames(small_bag, tmp_path):
    path, frames = small_bag
    data = (path / "bag_0.mcap").read_bytes()
    reference = list(read_bag(path))
    cuts = sorted(set([1, 7, 8, 20, 300] + list(np.linspace(400, len(data) - 1, 23).astype(int)) + [len(data) - 8]))
    recovered = []
    for cut in cuts:
        p = tmp_path / f"cut{cut}.mcap"
        p.write_bytes(data[:cut])
        with pytest.raises(BagTruncatedError, match=p.name):
            list(read_bag(p, strict=True))
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                out = list(read_bag(p))
        except BagTruncatedError as exc:  # cut before the first frame: a clear error naming the file
            assert p.name in str(exc) and "truncated" in str(exc)
            recovered.append(0)
            continue
        assert any(issubclass(w.category, BagTruncatedWarning) and p.name in str(w.message) for w in caught)
        for a, b in zip(reference, out):
            assert_same_frame(a, b)
            assert (a.stamp, a.scene_id, a.im_id) == (b.stamp, b.scene_id, b.im_id)
        recovered.append(len(out))
        assert bag_info(p)["truncated"]
    assert recovered == sorted(recovered)  # a later cut never recovers fewer frames
    assert recovered[-1] == len(frames)  # a cut in the summary loses no frame
    assert 0 < recovered[len(recovered) // 2] < len(frames)


# --------------------------------------------------------------------------- interrupted recordings

def _bop_for_interrupt(root: Path, n: int) -> None:
    """A BOP scene of n 640x480 images sharing one image pair (hard links): fast to make."""
    from perception_config.datasets.bop_scene import write_scene_camera, write_scene_gt
    from perception_config.datasets.bop_writer import SceneWriter

    f = make_frame(0, 480, 640)
    f.scene_id, f.im_id = 1, 0
    with SceneWriter(root, "test", 1) as sw:
        sw.add(f)
        cams, gts = dict(sw.cameras), dict(sw.gts)
    scene = root / "test" / "000001"
    for i in range(1, n):
        for sub in ("rgb", "depth"):
            os.link(scene / sub / "000000.png", scene / sub / f"{i:06d}.png")
        cams[i], gts[i] = cams[0], gts[0]
    write_scene_camera(scene / "scene_camera.json", cams)
    write_scene_gt(scene / "scene_gt.json", gts)


@pytest.fixture(scope="module")
def big_bop(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("big") / "ds"
    _bop_for_interrupt(root, 400)
    return root


def _start_recording(dataset: Path, out: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen(
        [sys.executable, "-m", "perception_config.cli", "bag", "write", "--dataset", str(dataset),
         "--out", str(out), "--quiet"], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    mcap = out / f"{out.name}_0.mcap"
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:  # wait until a few frames are on disk
        if mcap.exists() and mcap.stat().st_size > 4_000_000:
            return proc
        if proc.poll() is not None:
            break
        time.sleep(0.02)
    proc.kill()
    raise AssertionError(f"recording did not start: {proc.communicate()}")


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_interrupted_recording_is_a_valid_bag(big_bop, tmp_path, sig):
    from mcap.reader import make_reader
    from rosbags.highlevel import AnyReader

    out = tmp_path / "rec"
    proc = _start_recording(big_bop, out)
    proc.send_signal(sig)
    _stdout, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 130, stderr
    assert "interrupted" in stderr
    mcap = out / "rec_0.mcap"
    with open(mcap, "rb") as f:  # a finished file: summary and footer present
        s = make_reader(f).get_summary()
    counts = set(s.statistics.channel_message_counts.values())
    assert len(counts) == 1  # every frame has all of its messages
    n = counts.pop()
    assert 1 <= n < 400
    meta = yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["message_count"] == 5 * n
    with AnyReader([out]) as reader:
        assert sum(1 for _ in reader.messages()) == 5 * n
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = list(read_bag(out))
    assert [f.im_id for f in got] == list(range(n))
    assert all(len(f.objects) == 3 for f in got)


def test_killed_recording_loses_at_most_the_last_frame(big_bop, tmp_path):
    out = tmp_path / "rec"
    proc = _start_recording(big_bop, out)
    time.sleep(0.3)
    proc.kill()  # SIGKILL: no cleanup at all
    proc.communicate(timeout=30)
    mcap = out / "rec_0.mcap"
    size = mcap.stat().st_size
    with pytest.raises(BagTruncatedError):
        list(read_bag(out / "rec_0.mcap", strict=True))
    with pytest.warns(BagTruncatedWarning, match="rec_0.mcap"):
        got = list(read_bag(mcap))
    assert [f.im_id for f in got] == list(range(len(got)))
    # ~1.5 MB per frame on disk before compression; every complete chunk was recovered.
    per_frame = (size - 2000) / max(1, len(got))
    assert len(got) >= 1 and per_frame < 2 * 1.6e6
    assert bag_info(mcap)["truncated"]
