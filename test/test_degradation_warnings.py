"""A degradation is said once, in one line: train and evaluate on an RGB-only dataset with a
pipeline that needs depth (the depth actions masked), and `launch --bag` of a bag that yields no
frame (images without CameraInfo, no image topic at all)."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from perception_config import cli
from perception_config.cli.notices import rgb_only_warning
from perception_config.datasets.bag import bag_info, camera_info_fields, rgb_to_image_fields, write_frames
from perception_config.datasets.bag.definitions import definition
from perception_config.launcher.resolution import bag_frames_problem, resolve_nodes

DEFAULT_DEPTH_ACTIONS = "icp_coarse, icp_fine, icp_point, depth_refine"
STAMP = 1_700_000_000 * 10**9


@pytest.fixture(scope="module")
def rgb_dataset(tmp_path_factory) -> Path:
    """The tiny synthetic dataset (2 scenes x 2 images, seed 0) written RGB-only."""
    from perception_config.datasets.synthetic import generate

    return generate(tmp_path_factory.mktemp("rgb_only") / "tiny_rgb", scenes=2, images_per_scene=2, seed=0,
                    progress=False, depth=False)


def _warnings(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("warning: ")]


# --------------------------------------------------------------------------- RGB-only datasets

def test_the_line_names_the_masked_actions_the_missing_scores_and_the_reason(rgb_dataset, synthetic_dataset, tmp_path):
    line = rgb_only_warning(rgb_dataset)
    assert line == (f"dataset {rgb_dataset} has no depth images: the depth actions {DEFAULT_DEPTH_ACTIONS} are "
                    "masked out and the depth scores psi_d, icp_fitness are missing; use --pipeline rgb for an "
                    "RGB pipeline")
    assert rgb_only_warning(rgb_dataset, "rgb") is None  # nothing to mask
    assert rgb_only_warning(synthetic_dataset) is None  # RGB-D
    assert rgb_only_warning(synthetic_dataset, use_depth=False).startswith(
        f"--no-depth reads dataset {synthetic_dataset} as RGB-only: the depth actions {DEFAULT_DEPTH_ACTIONS} ")
    mixed = tmp_path / "mixed"
    shutil.copytree(synthetic_dataset, mixed)
    shutil.rmtree(mixed / "test" / "000001" / "depth")
    assert rgb_only_warning(mixed) == (
        f"1 of 2 scenes of dataset {mixed} have no depth images (scenes 1): the depth actions "
        f"{DEFAULT_DEPTH_ACTIONS} are masked out and the depth scores psi_d, icp_fitness are missing on those "
        "scenes' frames; use --pipeline rgb for an RGB pipeline")


def test_train_and_evaluate_say_it_once_and_succeed(rgb_dataset, tmp_path, capsys):
    run = tmp_path / "run"
    common = ["--dataset", str(rgb_dataset), "--max-ops", "3", "--time-mode", "cost_table", "--no-episode-store",
              "--quiet"]
    assert cli.main(["train", *common, "--agent", "random", "--episodes", "4", "--out", str(run),
                     "--cost-table", "blocks"]) == 0
    err = capsys.readouterr().err
    assert _warnings(err) == [f"warning: {rgb_only_warning(rgb_dataset)}"], err
    policy = next(run.glob("policy.*"))
    evaluate = ["evaluate", *common, "--lambdas", "0.3", "--episodes", "2", "--no-baselines", "--no-plots"]
    assert cli.main([*evaluate, "--policy", str(policy), "--out", str(tmp_path / "eval")]) == 0
    err = capsys.readouterr().err
    assert _warnings(err) == [f"warning: {rgb_only_warning(rgb_dataset)}"], err
    episodes = [json.loads(line) for line in (tmp_path / "eval" / "episodes.jsonl").read_text().splitlines()]
    assert episodes and all("icp_coarse" in e["masked_actions"] for e in episodes)
    # the RGB pipeline masks nothing: no line
    assert cli.main([*evaluate, "--policy", "random", "--pipeline", "rgb", "--out", str(tmp_path / "rgb")]) == 0
    assert _warnings(capsys.readouterr().err) == []


# --------------------------------------------------------------------------- launch --bag

def _image_bag(path: Path, n: int = 3, camera_info: bool = False, images: bool = True) -> Path:
    """An MCAP bag (mcap-ros2-support's writer, the project's message definitions) of `n` colour
    images on /camera/color/image_raw, with or without /camera/camera_info, and a frame_info String."""
    from mcap_ros2.writer import Writer

    rgb = np.zeros((6, 8, 3), np.uint8)
    with open(path, "wb") as f, Writer(f) as w:
        s_img = w.register_msgdef("sensor_msgs/msg/Image", definition("sensor_msgs/msg/Image"))
        s_info = w.register_msgdef("sensor_msgs/msg/CameraInfo", definition("sensor_msgs/msg/CameraInfo"))
        s_str = w.register_msgdef("std_msgs/msg/String", definition("std_msgs/msg/String"))
        for k in range(n):
            t = STAMP + k * 100_000_000
            hdr = {"stamp": {"sec": t // 10**9, "nanosec": t % 10**9}, "frame_id": "cam"}
            if images:
                w.write_message("/camera/color/image_raw", s_img, {"header": hdr, **rgb_to_image_fields(rgb)},
                                log_time=t)
            if camera_info:
                ci = camera_info_fields(np.array([[10.0, 0, 4], [0, 10, 3], [0, 0, 1]]), 8, 6)
                w.write_message("/camera/camera_info", s_info, {"header": hdr, **ci}, log_time=t)
            w.write_message("/perception/frame_info", s_str, {"data": "{}"}, log_time=t)
    return path


def _models(folder: Path) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "models_info.json").write_text(json.dumps({"1": {"diameter": 100.0}}))
    return folder


def test_a_bag_without_camera_info_or_images_is_named_in_one_line(rgb_dataset, tmp_path):
    no_info = _image_bag(tmp_path / "no_info.mcap")
    line = bag_frames_problem(bag_info(no_info))
    assert line == (f"bag {no_info} yields no frames, the nodes will receive no camera frame: it has images but no "
                    "sensor_msgs/msg/CameraInfo topic, and a frame needs the colour camera's camera_info; topics: "
                    "/camera/color/image_raw (Image, 3 msgs), /perception/frame_info (String, 3 msgs)")
    no_image = _image_bag(tmp_path / "no_image.mcap", camera_info=True, images=False)
    line = bag_frames_problem(bag_info(no_image))
    assert line.startswith(f"bag {no_image} yields no frames") and "it has no image topic" in line
    assert "/camera/camera_info (CameraInfo, 3 msgs)" in line
    assert bag_frames_problem(bag_info(_image_bag(tmp_path / "ok.mcap", camera_info=True))) is None
    assert bag_frames_problem(None) is None  # unreadable: bag_replay_node names the problem
    from perception_config.datasets.bop import BopDataset

    ds = BopDataset(rgb_dataset)
    write_frames([ds.load_frame(0, 0, with_models=False)], tmp_path / "ours.mcap", 10.0)
    assert bag_frames_problem(bag_info(tmp_path / "ours.mcap")) is None


def test_camera_topics_launch_cannot_choose_or_without_messages():
    topics = [{"topic": t, "type": ty, "count": 0 if t.endswith("info") else 2}
              for t, ty in (("/a/image_raw", "sensor_msgs/msg/Image"), ("/b/image_raw", "sensor_msgs/msg/Image"),
                            ("/a/camera_info", "sensor_msgs/msg/CameraInfo"))]
    unclear = {"path": "x.mcap", "frames": 0, "topics": topics,
               "frame_topics_error": "x.mcap: cannot tell the colour image topic: candidates ['/a/image_raw', "
                                     "'/b/image_raw'] among [...]; pass color_topic="}
    line = bag_frames_problem(unclear)
    assert "launch cannot choose its camera topics (cannot tell the colour image topic: candidates" in line
    assert "--remap FROM:=TO" in line and "(x.mcap" not in line
    assert bag_frames_problem(unclear, remapped=True) is None  # --remap names them
    empty = {"path": "x.mcap", "frames": 0, "topics": topics,
             "frame_topics": {"color": "/a/image_raw", "camera_info": "/a/camera_info"}}
    assert ": no messages on /a/camera_info; topics: /a/image_raw (Image, 2 msgs)" in bag_frames_problem(empty)


def test_launch_warns_once_before_starting_the_nodes(tmp_path, monkeypatch, capsys):
    from perception_config.launcher import supervisor

    bag = _image_bag(tmp_path / "no_info.mcap")
    models = _models(tmp_path / "models")
    warned, said = [], []
    specs = resolve_nodes(bag=bag, models=models, policy="none", cwd=tmp_path, say=said.append, warn=warned.append)
    assert warned == [bag_frames_problem(bag_info(bag))] and not any("no frames" in s for s in said)
    assert specs[-1].name == "bag_replay_node"

    started = []
    monkeypatch.setattr(supervisor, "run", lambda specs, log_dir=None, **_: started.append(specs) or 0)
    monkeypatch.chdir(tmp_path)
    assert cli.main(["launch", "--bag", str(bag), "--models", str(models), "--policy", "none"]) == 0
    out, err = capsys.readouterr()
    assert _warnings(err) == [f"warning: {bag_frames_problem(bag_info(bag))}"], err
    assert "no frames" not in out and len(started) == 1
