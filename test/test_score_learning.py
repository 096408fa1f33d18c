"""The learner refits the pick-success score online: rows of the configurator's store
and kept frames (labelled by ground truth or by the robot's pick outcome), a miscalibrated
serving score replaced by a better candidate, an equal one discarded, a failing cycle that
changes nothing, and nodes that follow the score versions (in-process and scoring_node over
Fast DDS), including a rollback.

The estimates are recorded the way the configurator records them (an episode in the store with
source "configurator", its frame in frames/), from the tiny synthetic dataset: each image is
kept under three stamps (a cell sees its parts again), so that the score has frames to split.
"""
from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from rl_helpers import PIPELINE, pipeline_file
from ros_helpers import NodeProcess, call, publish_when_matched, wait_for_service

SCORED_PIPELINE = PIPELINE.replace("scoring: [psi_d, psi_c, icp_fitness]",
                                   "scoring: [psi_d, psi_c, icp_fitness, pick_success]")
BASE_SEC = 1_700_000_000
# Probabilities pushed far up: a serving score that says "pick" to everything (a camera or
# gripper the shipped model never saw); the cell's own outcomes must correct it.
OVERCONFIDENT = (0.3, 4.0)


def stamp_ns(i: int) -> int:
    return (BASE_SEC + i) * 1_000_000_000


@pytest.fixture(scope="module")
def data(synthetic_dataset, tmp_path_factory):
    from perception_config.rl.env import PerceptionConfigEnv

    pipe = pipeline_file(tmp_path_factory, SCORED_PIPELINE, name="scored.yaml")
    env = PerceptionConfigEnv(synthetic_dataset, pipe, time_mode="cost_table", min_visib_fract=0.3)
    return {"root": synthetic_dataset, "pipeline": pipe, "env": env}


@pytest.fixture(scope="module")
def recorded(data, tmp_path_factory):
    """Every episode of the tiny dataset three times (three stamps per image), played by a random masked
    policy, stored as the configurator stores an estimate; frames with their ground truth."""
    from perception_config.agents import make_agent
    from perception_config.online.policy_learner import FRAMES
    from perception_config.rl.episode_loop import acting_seed, play_episode
    from perception_config.store.episode_store import STORE_NAME, StoreWriter, store_episode
    from perception_config.store.frames import save_frame

    env = data["env"]
    out = tmp_path_factory.mktemp("score_recorded")
    agent = make_agent("random", env, seed=0)
    writer = StoreWriter(out / STORE_NAME, print)
    keys = sorted({(ek.scene_id, ek.im_id) for ek in env.source.episodes})
    for rep in range(3):
        for j, ek in enumerate(env.source.episodes):
            stamp, seed = stamp_ns(rep * len(keys) + keys.index((ek.scene_id, ek.im_id))), 2000 + 100 * rep + j
            traj = play_episode(env, agent, {"episode": j, "lambda": 0.7, "episode_seed": seed}, acting_seed(seed))
            assert store_episode(writer, traj, source="configurator", agent="random", policy_version="v0000",
                                 episode_seed=seed, frame_stamp_ns=stamp, image_ids=False)
        for i, key in enumerate(keys):  # each stamp's frame once (the configurator saves a stamp once)
            frame = env.source.frame(*key)
            save_frame(out / FRAMES, stamp_ns(rep * len(keys) + i), frame, {o.obj_id: o.gt for o in frame.objects})
    writer.close()
    return out


def overconfident_model(path: Path) -> Path:
    from perception_config.blocks.pick_success import SHIPPED_MODEL, load_model, resolve_model_path

    shipped = load_model(str(resolve_model_path(SHIPPED_MODEL)))
    from perception_config.vision.pick_success_model import PickSuccessModel

    bad = PickSuccessModel(shipped.feature_names, shipped.median, shipped.spread, shipped.layers)
    bad.calibration = OVERCONFIDENT
    bad.record = {"test": "overconfident"}
    return bad.save(path)


def learn_dir_with(tmp_path: Path, recorded: Path, serving_model: Path) -> Path:
    from perception_config.online.score_learner import score_versions

    learn_dir = tmp_path / "learn"
    shutil.copytree(recorded, learn_dir)
    assert score_versions(learn_dir).promote(serving_model, {"start": "test"}) == "v0000"
    return learn_dir


def test_rows_of_kept_frames_are_labelled_by_ground_truth_or_by_the_robot(tmp_path, data, recorded):
    """A kept frame with ground truth labels every hypothesis; a frame kept without it (a real
    cell) labels only the picked hypotheses, by the robot's outcome, which also wins over the
    ground truth's verdict; a frame pruned from the ring drops its rows; no models: named."""
    from perception_config.learning.pick_success_data import featurise, load_step_rows
    from perception_config.online.policy_learner import FRAMES
    from perception_config.store.episode_store import STORE_NAME, EpisodeStore
    from perception_config.store.frames import frame_path, load_frame, save_frame

    learn_dir = tmp_path / "learn"
    shutil.copytree(recorded, learn_dir)
    models = data["root"] / "models"
    rows = load_step_rows(learn_dir / STORE_NAME)
    assert rows and all(r["episode_im_id"] is None and r["episode_frame_stamp_ns"] for r in rows)
    full = featurise(rows, with_rgb_only=False, progress=False, frames_dir=learn_dir / FRAMES, models_dir=models)
    assert len({k for k in full.images}) == 12 and 0 < full.y.mean() < 1
    assert np.isfinite(full.mssd_share).all(), "every row labelled by the ground truth"

    # frame 0 loses its ground truth; the robot reports every pick on it, each the opposite of
    # what the simulation said
    frame, _ = load_frame(frame_path(learn_dir / FRAMES, stamp_ns(0)))
    save_frame(learn_dir / FRAMES, stamp_ns(0), frame, None)
    with EpisodeStore(learn_dir / STORE_NAME) as store:
        picks = store.query("SELECT s.episode_id, s.step, s.picked, s.pose FROM steps s JOIN episodes e "
                            "ON e.id = s.episode_id WHERE e.frame_stamp_ns = ? AND s.picked IS NOT NULL",
                            (stamp_ns(0),))
        assert picks, "the random policy picked on frame 0"
        for eid, step, simulated, _ in picks:
            store.record_pick_outcome(eid, step, not bool(simulated), "robot")
    robot = {pose: not bool(simulated) for _, _, simulated, pose in picks}  # one row per distinct pose
    rows = load_step_rows(learn_dir / STORE_NAME)
    table = featurise(rows, with_rgb_only=False, progress=False, frames_dir=learn_dir / FRAMES, models_dir=models)
    on0 = np.array([k[2] == stamp_ns(0) for k in table.images])
    assert on0.sum() == len(robot) < (np.array([k[2] == stamp_ns(0) for k in full.images])).sum(), \
        "without ground truth only the picked hypotheses are labelled"
    assert table.y[on0].sum() == sum(robot.values()), "by the robot's outcome"
    assert np.isnan(table.mssd_share[on0]).all()

    frame_path(learn_dir / FRAMES, stamp_ns(1)).unlink()  # pruned from the ring
    table = featurise(rows, with_rgb_only=False, progress=False, frames_dir=learn_dir / FRAMES, models_dir=models)
    assert stamp_ns(1) not in {k[2] for k in table.images}
    with pytest.raises(ValueError, match="pass the models folder"):
        featurise(rows, progress=False, frames_dir=learn_dir / FRAMES)


def test_an_overconfident_score_is_replaced_and_an_equal_candidate_discarded(tmp_path, data, recorded):
    """Serving a score that calls every hypothesis pickable: the recalibrated candidate's held-out
    Brier is far lower and it is promoted as v0001; a block following the versions switches to
    it, and back on a rollback. The next cycle's candidate is no better than v0001: discarded."""
    from perception_config.blocks.base import BlockInput
    from perception_config.blocks.pick_success import PickSuccess
    from perception_config.online.score_learner import format_score_result, refit_score_once, score_versions

    learn_dir = learn_dir_with(tmp_path, recorded, overconfident_model(tmp_path / "bad.safetensors"))
    models = data["root"] / "models"
    env = data["env"]
    ek = env.source.episodes[0]
    frame = env.source.frame(ek.scene_id, ek.im_id)
    obj = next(o for o in frame.objects if o.obj_id == ek.obj_id)
    block = PickSuccess(versions=str(learn_dir / "pick_success"))
    far = type(obj.gt)(obj.gt.R, obj.gt.t + np.array([0.03, 0.0, 0.0]))  # 30 mm off: a failed pick

    def p_far() -> float:
        return block(BlockInput(frame=frame, model=obj.model, pose=far)).scores["pick_success"]

    before = p_far()
    assert block.version == "v0000" and before > 0.5, "the overconfident score serves first"

    first = refit_score_once(learn_dir, models, margin=0.05)
    line = format_score_result(first)
    print(line)
    assert first["outcome"] == "promoted" and first["version"] == "v0001", line
    assert first["brier"] < 0.5 * first["serving_brier"] and first["candidate"] == "recalibrated"
    assert line.startswith("learner: pick_success candidate (recalibrated) from ") and line.endswith("promoted v0001")
    after = p_far()
    assert block.version == "v0001" and after < before, "a following block serves the promoted version"

    versions = score_versions(learn_dir)
    versions.select("v0000")  # the configurator's score_version rollback
    assert p_far() == pytest.approx(before) and block.version == "v0000"
    versions.select("")

    second = refit_score_once(learn_dir, models, margin=0.05)
    print(format_score_result(second))
    assert second["outcome"] == "discarded" and second["serving"] == "v0001"
    assert [v["version"] for v in versions.list()] == ["v0000", "v0001"]
    assert not list((learn_dir / "candidates").glob("*")), "no candidate file left behind"


def test_a_score_cycle_that_cannot_fit_is_one_line_and_changes_nothing(tmp_path, data, recorded):
    from perception_config.online.score_learner import format_score_result, refit_score_once, score_versions
    from perception_config.store.episode_store import STORE_NAME

    learn_dir = learn_dir_with(tmp_path, recorded, overconfident_model(tmp_path / "bad.safetensors"))
    models = data["root"] / "models"
    index = score_versions(learn_dir).index.read_bytes()
    # too few frames: the ring pruned to 3
    kept = learn_dir / "kept"
    kept.mkdir()
    for p in sorted((learn_dir / "frames").glob("*.npz"))[3:]:
        p.rename(kept / p.name)
    r = refit_score_once(learn_dir, models)
    assert r["outcome"] == "failed" and "3 labelled frames" in r["reason"], r
    assert format_score_result(r).endswith("serving v0000 unchanged")
    for p in kept.glob("*.npz"):
        p.rename(learn_dir / "frames" / p.name)
    # a corrupt store
    (learn_dir / STORE_NAME).write_bytes(b"not a database" * 100)
    for suffix in ("-wal", "-shm"):
        (learn_dir / (STORE_NAME + suffix)).unlink(missing_ok=True)
    r = refit_score_once(learn_dir, models)
    assert r["outcome"] == "failed" and "cannot be read" in r["reason"], r
    assert score_versions(learn_dir).index.read_bytes() == index


def test_fit_score_reads_a_configurators_learn_dir(tmp_path, data, recorded):
    """`fit-score --store <learn_dir>/episodes.sqlite --models DIR` finds the kept frames beside
    the store and fits a model from the cell's estimates."""
    from perception_config.cli import main

    learn_dir = tmp_path / "learn"
    shutil.copytree(recorded, learn_dir)
    out = tmp_path / "fitted"
    assert main(["fit-score", "--store", str(learn_dir / "episodes.sqlite"), "--models", str(data["root"] / "models"),
                 "--epochs", "50", "--out", str(out), "--quiet"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert "--models" in metrics["source"]["command"] and sum(metrics["images"].values()) == 12
    assert (out / "pick_success.safetensors").is_file() and (out / "reliability.png").is_file()


def test_scoring_node_follows_the_score_versions(ros_node, data, tmp_path):
    """scoring_node with pick_success_versions: its pick_success is the selected version's,
    switched by a promotion and by a rollback without a restart."""
    from perception_config_interfaces.msg import Hypothesis
    from perception_config_interfaces.srv import ScoreHypothesis
    from sensor_msgs.msg import CameraInfo, Image

    from perception_config.blocks.base import BlockInput
    from perception_config.blocks.pick_success import SHIPPED_MODEL, PickSuccess, resolve_model_path
    from perception_config.online.score_learner import score_versions
    from perception_config.ros.conversions import frame_to_msgs, pose_to_msg

    versions = score_versions(tmp_path / "learn")
    versions.promote(resolve_model_path(SHIPPED_MODEL), {"start": "shipped"})
    env = data["env"]
    ek = env.source.episodes[0]
    frame = env.source.frame(ek.scene_id, ek.im_id)
    obj = next(o for o in frame.objects if o.obj_id == ek.obj_id)
    pose = type(obj.gt)(obj.gt.R, obj.gt.t + np.array([0.03, 0.0, 0.0]))  # 30 mm off: shipped says no

    def in_process(model: Path) -> float:
        return PickSuccess(model=str(model))(BlockInput(frame=frame, model=obj.model, pose=pose)).scores["pick_success"]

    node = NodeProcess("scoring_node", {"models_dir": data["root"] / "models", "pipeline": data["pipeline"],
                                        "pick_success_versions": versions.folder}, log_dir=tmp_path)
    try:
        client = ros_node.create_client(ScoreHypothesis, "score_hypothesis")
        wait_for_service(ros_node, client, process=node)
        stamp = stamp_ns(0)
        color, depth, info = frame_to_msgs(frame, stamp)
        pubs = [ros_node.create_publisher(t, n, 10) for t, n in ((CameraInfo, "camera/camera_info"),
                                                                 (Image, "camera/depth/image_raw"),
                                                                 (Image, "camera/color/image_raw"))]
        for pub, msg in zip(pubs, (info, depth, color)):
            publish_when_matched(ros_node, pub, msg)
        h = Hypothesis(object_id=str(obj.obj_id), pose=pose_to_msg(pose))
        h.header.stamp.sec, h.header.stamp.nanosec = divmod(stamp, 1_000_000_000)

        def served() -> float:
            res = call(ros_node, client, ScoreHypothesis.Request(hypothesis=h), timeout=30)
            assert res.success, res.message
            return dict(zip(res.hypothesis.score_names, res.hypothesis.scores))["pick_success"]

        shipped = in_process(versions.path("v0000"))
        assert served() == pytest.approx(shipped, abs=1e-6)
        versions.promote(overconfident_model(tmp_path / "bad.safetensors"), {"test": "promoted"})
        time.sleep(0.05)  # a later index mtime
        bad = in_process(versions.path("v0001"))
        assert bad > shipped + 0.05
        assert served() == pytest.approx(bad, abs=1e-6), "the promotion serves without a restart"
        versions.select("v0000")
        assert served() == pytest.approx(shipped, abs=1e-6), "the rollback serves at once"
        assert "pick_success follows the score versions" in node.output()
    finally:
        assert node.stop() == 0, node.output()


def test_the_configurator_writes_score_version_0_and_pins_score_versions(ros_node, data, tmp_path):
    """learn:=true on a pipeline that scores pick_success: version 0 of the score is the pipeline's
    model; the score_version parameter refuses an unknown version (naming the kept ones) and pins
    a kept one in the index the operator nodes follow."""
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters

    from perception_config.online.score_learner import score_versions

    learn_dir = tmp_path / "learn"
    node = NodeProcess("configurator_node", {"models_dir": data["root"] / "models", "pipeline": data["pipeline"],
                                             "publish_debug": "false", "learn": "true", "learn_dir": str(learn_dir)},
                       tmp_path)
    try:
        client = ros_node.create_client(SetParameters, "configurator_node/set_parameters")
        wait_for_service(ros_node, client, process=node)

        def set_score_version(value: str):
            req = SetParameters.Request(parameters=[Parameter(name="score_version", value=ParameterValue(
                type=ParameterType.PARAMETER_STRING, string_value=value))])
            return call(ros_node, client, req, timeout=10.0).results[0]

        versions = score_versions(learn_dir)
        deadline = time.monotonic() + 60  # the parameter services come up before the node's learning state
        while "learner process" not in node.output() and node.alive() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert [v["version"] for v in versions.list()] == ["v0000"], node.output()
        assert versions.list()[0]["info"]["start"].endswith("pick_success.safetensors")
        versions.promote(overconfident_model(tmp_path / "bad.safetensors"), {"test": "promoted"})
        refused = set_score_version("v0042")
        assert not refused.successful and "unknown pick_success version 'v0042'" in refused.reason
        assert "kept: v0000, v0001" in refused.reason and versions.current() == "v0001"
        assert set_score_version("v0000").successful and versions.current() == "v0000"
        assert set_score_version("").successful and versions.current() == "v0001"
        assert "pick_success version v0000 written" in node.output()
    finally:
        assert node.stop() == 0, node.output()
