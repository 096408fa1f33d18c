"""bag_replay_node as its own OS process, received by this test process over Fast DDS: every
frame's messages arrive with the recorded stamps and data, the pacing follows `rate`, the node
exits 0 at the end and on Ctrl-C, and bad input makes it exit 2 naming the file."""
from __future__ import annotations

import json
import subprocess
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from perception_config.core.geometry import Pose, exp_so3, rotation_angle
from perception_config.core.scene import Frame, SceneObject
from perception_config.datasets.bag import RECORDING_EPOCH_NS, read_bag, write_frames
from ros_helpers import VENV_BIN, NodeProcess, ros_test_env

pytestmark = pytest.mark.ros

N_FRAMES, RATE_HZ, W, H = 5, 10.0, 64, 48
STAMPS = [RECORDING_EPOCH_NS + round(i * 1e9 / RATE_HZ) for i in range(N_FRAMES)]
TOPICS = {  # relative topic name -> message type (imported lazily: rclpy is loaded by the ros_node fixture)
    "camera/color/image_raw": ("sensor_msgs.msg", "Image"),
    "camera/depth/image_raw": ("sensor_msgs.msg", "Image"),
    "camera/camera_info": ("sensor_msgs.msg", "CameraInfo"),
    "perception/ground_truth": ("perception_config_interfaces.msg", "ObjectPoses"),
    "perception/frame_info": ("std_msgs.msg", "String"),
}
# Wait until the test node subscribes to every replayed topic (the colour topic alone matches
# first; the others can lag behind it on a loaded machine).
ALL_TOPICS_MATCHED = [f"{t}:1" for t in TOPICS]
COLOR = "camera/color/image_raw"


def _frames() -> list[Frame]:
    rng = np.random.default_rng(7)
    K = np.array([[60.0, 0.0, 31.5], [0.0, 61.0, 23.5], [0.0, 0.0, 1.0]])
    frames = []
    for i in range(N_FRAMES):
        depth = rng.uniform(0.4, 1.2, (H, W)).astype(np.float32)
        depth[rng.random((H, W)) < 0.1] = np.nan
        objects = [SceneObject(3, Pose(exp_so3([0.1 * i, -0.4, 0.2]), [0.05, -0.02, 0.8 + 0.01 * i])),
                   SceneObject(7, Pose(np.eye(3), [0.0, 0.1, 0.6]))]
        frames.append(Frame(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), depth, K, scene_id=2, im_id=10 + i,
                            objects=objects))
    return frames


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> tuple[Path, list[Frame]]:
    frames = _frames()
    path = tmp_path_factory.mktemp("bag") / "five.mcap"
    assert write_frames(frames, path, RATE_HZ) == N_FRAMES
    return path, frames


def _stamp(msg) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


class Recorder:
    """Subscriptions of the test's node on the replayed topics; messages with their arrival times."""

    def __init__(self, node, prefix: str = "", topics: dict[str, str] | None = None) -> None:
        import importlib

        from rclpy.qos import QoSProfile, ReliabilityPolicy

        self.node = node
        self.received: dict[str, list[tuple[float, object]]] = {}
        self._subs = []
        qos = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
        for topic, (module, name) in TOPICS.items():
            name_here = prefix + (topics or {}).get(topic, topic)
            cls = getattr(importlib.import_module(module), name)
            self.received[topic] = []
            self._subs.append(node.create_subscription(
                cls, name_here, lambda msg, t=topic: self.received[t].append((time.monotonic(), msg)), qos))

    def spin_until(self, done, timeout: float, process: NodeProcess | None = None) -> None:
        """Spin until done() or the timeout; once `process` has exited, at most 0.3 s more."""
        import rclpy

        deadline = time.monotonic() + timeout
        while not done() and time.monotonic() < deadline:
            rclpy.spin_once(self.node, timeout_sec=0.02)
            if process is not None and not process.alive():
                deadline = min(deadline, time.monotonic() + 0.3)

    def spin_for(self, seconds: float) -> None:
        self.spin_until(lambda: False, seconds)

    def count(self, topic: str = COLOR) -> int:
        return len(self.received[topic])

    def close(self) -> None:
        for s in self._subs:
            self.node.destroy_subscription(s)


@pytest.fixture()
def recorder(ros_node):
    rec = Recorder(ros_node)
    yield rec
    rec.close()


def _wait_exit(proc: NodeProcess, timeout: float = 10.0) -> int:
    try:
        proc.proc.wait(timeout)
    except subprocess.TimeoutExpired:
        pass
    return proc.stop()


def check_frames(rec: Recorder, frames: list[Frame]) -> None:
    """Every topic got exactly the recorded frames, in order, with the recorded stamps and data."""
    from perception_config.ros.conversions import msg_to_pose

    for topic in TOPICS:
        msgs = [m for _, m in rec.received[topic]]
        if topic == "perception/frame_info":
            infos = [json.loads(m.data) for m in msgs]
            assert [i["stamp_ns"] for i in infos] == STAMPS
            assert [(i["scene_id"], i["im_id"]) for i in infos] == [(2, 10 + k) for k in range(N_FRAMES)]
        else:
            assert [_stamp(m) for m in msgs] == STAMPS, f"{topic}: wrong or missing stamps"
            assert all(m.header.frame_id == "camera_color_optical_frame" for m in msgs)
    for k, f in enumerate(frames):
        _, color = rec.received["camera/color/image_raw"][k]
        assert (color.encoding, color.width, color.height) == ("rgb8", W, H)
        np.testing.assert_array_equal(np.frombuffer(color.data, np.uint8).reshape(H, W, 3), f.rgb)
        _, depth = rec.received["camera/depth/image_raw"][k]
        assert depth.encoding == "16UC1" and depth.step == 2 * W
        mm = np.frombuffer(depth.data, "<u2").reshape(H, W)
        expected = np.where(np.isnan(f.depth), 0, np.rint(np.nan_to_num(f.depth) * 1000)).astype(np.uint16)
        np.testing.assert_array_equal(mm, expected)
        _, info = rec.received["camera/camera_info"][k]
        np.testing.assert_allclose(np.asarray(info.k).reshape(3, 3), f.K, rtol=0, atol=1e-12)
        assert (info.width, info.height) == (W, H)
        _, gt = rec.received["perception/ground_truth"][k]
        assert list(gt.object_ids) == ["3", "7"]
        for oid, pose_msg in zip(gt.object_ids, gt.poses):
            want = next(o.gt for o in f.objects if str(o.obj_id) == oid)
            got = msg_to_pose(pose_msg)
            assert np.allclose(got.t, want.t, atol=1e-12) and rotation_angle(got.R, want.R) < 1e-6


@pytest.mark.parametrize("rate, span", [(1.0, 0.4), (2.0, 0.2), (0.0, None)])
def test_replay_delivers_every_frame_at_the_recorded_pace(bag, recorder, tmp_path, rate, span):
    path, frames = bag
    node = NodeProcess("bag_replay_node", {"bag": str(path), "rate": rate, "wait_for": ALL_TOPICS_MATCHED,
                                           "start_delay": 0.5}, tmp_path)
    recorder.spin_until(lambda: all(recorder.count(t) >= N_FRAMES for t in TOPICS), 15.0, node)
    code = _wait_exit(node)
    recorder.spin_for(0.2)  # nothing else may arrive
    out = node.output()
    assert code == 0, f"bag_replay_node exited {code}:\n{out}"
    check_frames(recorder, frames)
    arrivals = [t for t, _ in recorder.received[COLOR]]
    measured = arrivals[-1] - arrivals[0]
    if span is None:  # as fast as possible: the 5 frames arrive within a small part of the 0.4 s recording
        assert measured < 0.15, out
    else:
        assert span - 0.06 < measured < span + 0.15, f"first to last frame took {measured:.3f} s, recorded {span} s"
    assert f"replayed {5 * N_FRAMES} messages, {N_FRAMES} frames" in out, out


def test_loop_repeats_the_bag_stamps_and_ctrl_c_stops_with_exit_0(bag, recorder, tmp_path):
    path, _ = bag
    node = NodeProcess("bag_replay_node", {"bag": str(path), "loop": True, "wait_for": ALL_TOPICS_MATCHED,
                                           "start_delay": 0.3}, tmp_path)
    recorder.spin_until(lambda: recorder.count() >= N_FRAMES + 2, 15.0, node)
    assert node.alive(), node.output()
    stamps = [_stamp(m) for _, m in recorder.received[COLOR]]
    assert stamps[:N_FRAMES + 2] == STAMPS + STAMPS[:2], "a second pass must replay the bag's own stamps"
    arrivals = [t for t, _ in recorder.received[COLOR]]
    gap = arrivals[N_FRAMES] - arrivals[N_FRAMES - 1]
    assert 0.05 < gap < 0.25, f"loop restarted {gap:.3f} s after the last frame (one frame interval is 0.1 s)"
    t0 = time.monotonic()
    code = node.stop()
    stopped_in = time.monotonic() - t0
    out = node.output()
    assert code == 0, f"exit {code} after SIGINT:\n{out}"
    assert stopped_in < 3.0, f"took {stopped_in:.1f} s to stop"
    assert "Traceback" not in out, out
    n = recorder.count()
    recorder.spin_for(0.3)
    assert recorder.count() == n, "messages arrived after the node stopped"


def test_truncated_bag_replays_its_complete_frames_and_warns(bag, recorder, tmp_path):
    path, _ = bag
    cut = tmp_path / "cut.mcap"
    data = path.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.7)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        n = sum(1 for _ in read_bag(cut))  # what the reader recovers
    assert 1 <= n < N_FRAMES
    node = NodeProcess("bag_replay_node", {"bag": str(cut), "rate": 0.0, "wait_for": ALL_TOPICS_MATCHED,
                                           "start_delay": 0.5}, tmp_path)
    recorder.spin_until(lambda: not node.alive(), 15.0)
    recorder.spin_for(0.2)
    code = _wait_exit(node)
    out = node.output()
    assert code == 0, out
    for topic in TOPICS:
        if topic != "perception/frame_info":
            stamps = [_stamp(m) for _, m in recorder.received[topic]]
            assert stamps == STAMPS[:n], f"{topic}: not the {n} complete frames"
    assert "truncated" in out and str(cut) in out, out


def test_topics_filter_namespace_and_remapping(bag, ros_node, tmp_path):
    path, _ = bag
    rec = Recorder(ros_node, prefix="/replay/", topics={COLOR: "rgb"})
    log = tmp_path / "ns.log"
    try:
        with open(log, "w") as f:
            proc = subprocess.Popen(
                [str(VENV_BIN / "bag_replay_node"), "--ros-args", "-r", "__ns:=/replay",
                 "-r", "camera/color/image_raw:=rgb", "-p", f"bag:={path}", "-p", "rate:=0",
                 "-p", "topics:=[/camera/color/image_raw, perception/ground_truth]",
                 "-p", "wait_for_subscribers:=1", "-p", "start_delay:=0.5"],
                env=ros_test_env(), stdout=f, stderr=subprocess.STDOUT)
            rec.spin_until(lambda: proc.poll() is not None, 15.0)
            rec.spin_for(0.3)
            code = proc.wait(5)
        out = log.read_text()
        assert code == 0, out
        assert [_stamp(m) for _, m in rec.received[COLOR]] == STAMPS, out
        assert [_stamp(m) for _, m in rec.received["perception/ground_truth"]] == STAMPS
        assert all(rec.count(t) == 0 for t in ("camera/depth/image_raw", "camera/camera_info", "perception/frame_info"))
        assert "2 topics" in out
    finally:
        rec.close()


def test_wait_for_subscribers_gives_up_after_wait_timeout(bag, tmp_path):
    path, _ = bag
    t0 = time.monotonic()
    node = NodeProcess("bag_replay_node", {"bag": str(path), "rate": 0.0, "wait_for_subscribers": 3,
                                           "wait_timeout": 1.0}, tmp_path)
    code = _wait_exit(node)
    out = node.output()
    assert code == 0, out
    assert time.monotonic() - t0 > 1.0
    assert "of 3 subscribers after wait_timeout; starting anyway" in out, out
    assert f"replayed {5 * N_FRAMES} messages" in out, out


@pytest.mark.parametrize("case", ["missing", "corrupt", "empty", "negative_rate", "unknown_topic", "bad_wait_for"])
def test_bad_input_exits_2_naming_the_problem(bag, tmp_path, case):
    path, _ = bag
    params: dict[str, object] = {"bag": str(path)}
    if case == "missing":
        params["bag"] = expected = str(tmp_path / "no_such_bag.mcap")
    elif case == "corrupt":
        bad = tmp_path / "random.mcap"
        bad.write_bytes(np.random.default_rng(1).integers(0, 256, 4096, dtype=np.uint8).tobytes())
        params["bag"] = expected = str(bad)
    elif case == "empty":
        params["bag"], expected = '""', "parameter 'bag' is empty"
    elif case == "negative_rate":
        params["rate"], expected = -1.0, "'rate' must be >= 0"
    elif case == "bad_wait_for":
        params["wait_for"], expected = "['camera/color/image_raw:many']", "wait_for entry 'camera/color/image_raw:many'"
    else:
        params["topics"], expected = "[camera/nothing]", "camera/nothing"
    node = NodeProcess("bag_replay_node", params, tmp_path)
    code = _wait_exit(node)
    out = node.output()
    assert code == 2, f"exit {code}:\n{out}"
    assert expected in out and "[ERROR]" in out, out
    assert "Traceback" not in out, out
