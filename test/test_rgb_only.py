"""RGB-only data (no depth): blocks that need depth answer "needs depth" at once, the environment's
action mask, every agent respecting it, train/evaluate/bench/show on an RGB-only dataset, MCAP
recordings without a depth topic, an RGB-only camera in ROS, and the real LM-O RGB frames."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from perception_config.agents import AGENTS, make_agent
from perception_config.blocks.base import BlockInput, create
from perception_config.blocks.pipeline import pipeline_from_dict
from perception_config.datasets.bop import BopDataset
from perception_config.rl.env import PerceptionConfigEnv
from perception_config.rl.episode_loop import play_episode
from perception_config.rl.trajectory import allowed_actions

# Depth actions (icp_coarse, depth_refine), an RGB action (d2co) and the two that always run.
RGB_PIPELINE = """\
generator: {block: simulated_init, params: {noise_lambda: 0.5}}
actions:
  - {name: icp_coarse, block: icp_point_to_plane,
     params: {max_correspondence_distance: 0.03, final_distance: 0.01, stages: 2, max_seconds: 10.0}}
  - {name: d2co, block: d2co}
  - {name: depth_refine, block: depth_refine, params: {max_seconds: 10.0}}
  - {name: regenerate, block: simulated_init}
  - {name: pick, block: simulated_pick}
scoring: [psi_d, psi_c, icp_fitness]
"""
DEPTH_ACTIONS = {"icp_coarse", "depth_refine"}
EXPECTED_MASK = [0, 1, 0, 1, 1]


@pytest.fixture(scope="module")
def rgb_dataset(tmp_path_factory) -> Path:
    """The tiny synthetic dataset (2 scenes x 2 images, seed 0) written RGB-only."""
    from perception_config.datasets.synthetic import generate

    return generate(tmp_path_factory.mktemp("rgb_only") / "tiny_rgb", scenes=2, images_per_scene=2, seed=0,
                    progress=False, depth=False)


@pytest.fixture(scope="module")
def pipeline_path(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("rgb_pipe") / "pipeline.yaml"
    path.write_text(RGB_PIPELINE)
    return path


@pytest.fixture(scope="module")
def env(rgb_dataset, pipeline_path) -> PerceptionConfigEnv:
    return PerceptionConfigEnv(rgb_dataset, pipeline_path, time_mode="cost_table", max_ops=6)


def _options(i: int, lam: float = 0.4, seed: int = 7) -> dict:
    return {"episode": i, "lambda": lam, "episode_seed": seed}


# --------------------------------------------------------------------------- data and blocks

def test_synth_no_depth_is_the_same_dataset_without_depth(rgb_dataset, synthetic_dataset):
    for scene in ("000000", "000001"):
        rgb_scene, rgbd_scene = rgb_dataset / "test" / scene, synthetic_dataset / "test" / scene
        assert not (rgb_scene / "depth").exists() and (rgbd_scene / "depth").is_dir()
        for name in ("scene_gt.json", "scene_gt_info.json", "scene_camera.json"):
            assert (rgb_scene / name).read_bytes() == (rgbd_scene / name).read_bytes()
        for png in (rgbd_scene / "rgb").iterdir():
            assert (rgb_scene / "rgb" / png.name).read_bytes() == png.read_bytes()
    assert json.loads((rgb_dataset / "dataset_info.json").read_text())["depth"] is False
    frame = BopDataset(rgb_dataset).load_frame(0, 0)
    assert frame.depth is None and frame.rgb.shape == (480, 640, 3)


def test_a_block_needing_depth_answers_at_once_and_rgb_blocks_run(rgb_dataset):
    frame = BopDataset(rgb_dataset).load_frame(0, 1)
    obj = frame.objects[0]
    inp = BlockInput(frame=frame, model=obj.model, pose=obj.gt, ground_truth=obj.gt)
    for name in ("icp_point_to_plane", "icp_point_to_point", "depth_refine", "psi_d", "icp_fitness",
                 "global_registration"):
        block = create(name)
        r = block(inp)
        assert not r.ok and "needs depth" in r.reason and name in r.reason
        assert r.elapsed < 0.005  # refused before any work
        assert block.frame_lacks(frame)
    r = create("psi_c")(inp)
    assert r.ok and np.isfinite(r.scores["psi_c"])
    assert create("d2co").frame_lacks(frame) == "" and create("d2co")(inp).ok


def test_writer_refuses_to_mix_rgb_only_and_rgbd_frames_in_a_scene(tmp_path, rgb_dataset, synthetic_dataset):
    from perception_config.datasets.bop_writer import write_frame

    rgbd = BopDataset(synthetic_dataset).load_frame(0, 0)
    rgb = BopDataset(rgb_dataset).load_frame(0, 1)
    write_frame(tmp_path, "test", rgbd)
    with pytest.raises(ValueError, match="RGB-D or RGB-only"):
        write_frame(tmp_path, "test", rgb)
    write_frame(tmp_path / "b", "test", rgb, gt_info="compute")  # visibility from the rendered objects
    back = BopDataset(tmp_path / "b").load_frame(0, 1, with_models=False)
    assert back.depth is None and not (tmp_path / "b" / "test" / "000000" / "depth").exists()
    got = np.array([o.visib_fract for o in back.objects])
    want = np.array([o.visib_fract for o in rgb.objects])  # the generator's, from its own rendering
    assert np.abs(got - want).max() < 0.1, (got, want)


# --------------------------------------------------------------------------- environment

def test_the_mask_is_in_info_and_the_observation_layout_is_unchanged(env, synthetic_dataset, pipeline_path):
    obs, info = env.reset(options=_options(0))
    assert info["action_mask"].dtype == np.int8 and info["action_mask"].tolist() == EXPECTED_MASK
    assert env.action_mask().tolist() == EXPECTED_MASK
    _, _, _, _, info = env.step(env.action_names.index("d2co"))
    assert info["action_mask"].tolist() == EXPECTED_MASK
    layout = dict(zip(env.observation_layout, obs))
    assert layout["missing:psi_d"] == 1.0 and layout["missing:icp_fitness"] == 1.0 and layout["missing:psi_c"] == 0.0
    rgbd = PerceptionConfigEnv(synthetic_dataset, pipeline_path, time_mode="cost_table")
    assert rgbd.observation_layout == env.observation_layout
    _, info = rgbd.reset(options=_options(0))
    assert info["action_mask"].tolist() == [1] * 5
    # the same dataset read as RGB-only masks the same actions
    no_depth = PerceptionConfigEnv(synthetic_dataset, pipeline_path, time_mode="cost_table", use_depth=False)
    assert no_depth.reset(options=_options(0))[1]["action_mask"].tolist() == EXPECTED_MASK


def test_a_masked_action_taken_anyway_fails_with_needs_depth(env):
    env.reset(options=_options(1))
    before = env.last_outcome.pose
    a = env.action_names.index("icp_coarse")
    _, reward, terminated, truncated, info = env.step(a)
    assert not info["ok"] and "needs depth" in info["reason"]
    assert info["pose"] is before and not terminated and not truncated
    # charged like a failed action: the block's table cost plus the scoring that can run (psi_c)
    block = env.pipeline.actions[a].block
    expected = env.settings.block_cost(block) + env.settings.block_cost(create("psi_c"))
    assert info["seconds"] == pytest.approx(expected) and reward == pytest.approx(-expected)


# --------------------------------------------------------------------------- agents

def _agent(name: str, env, **kw):
    if name == "fixed":
        kw.setdefault("sequence", ["icp_coarse", "d2co", "depth_refine", "pick"])
    if name == "es":
        kw.setdefault("population", 3)
    if name == "oracle":
        kw.setdefault("node_budget", 60)
    return make_agent(name, env, **kw)


@pytest.mark.parametrize("name", sorted(AGENTS))
def test_no_agent_chooses_a_masked_action(env, name):
    agent = _agent(name, env, seed=5)
    chosen = []
    for k in range(4):
        traj = play_episode(env, agent, _options(k % 4, 0.3 + 0.1 * k, 20 + k), act_seed=k)
        chosen += traj.names
        assert traj.masks is not None and traj.masks.shape == (traj.steps, 5)
        assert (traj.masks <= EXPECTED_MASK).all()  # the depth actions always masked (pick too after a failed one)
        assert all(traj.masks[k][a] for k, a in enumerate(traj.actions)), (traj.names, traj.masks)
    assert chosen and not DEPTH_ACTIONS & set(chosen), chosen


def test_learners_respect_the_mask_after_updates(env):
    """simple, pg and es learn from masked trajectories and still never choose a masked action;
    pg's update uses the masked log-probabilities (finite loss, masked actions at probability 0)."""
    for name in ("simple", "pg", "es"):
        agent = _agent(name, env, seed=1, **({"batch_episodes": 4} if name == "pg" else {}))
        for r in range(3):
            actors = agent.actors()
            trajs = [[play_episode(env, a, _options(j, 0.5, 100 * r + j), act_seed=j) for j in range(2)]
                     for a in actors]
            stats = agent.update(trajs)
            assert all(np.isfinite(v) for v in stats.values()), (name, stats)
            assert not DEPTH_ACTIONS & {n for per in trajs for t in per for n in t.names}
    p = agent.probabilities(np.zeros(len(env.observation_layout)), np.array(EXPECTED_MASK, bool)) \
        if hasattr(agent, "probabilities") else None
    assert p is None or p[[0, 2]].sum() == 0.0


def test_masked_pg_log_prob_matches_the_sampling_distribution(env):
    import torch

    agent = make_agent("pg", env, seed=0, batch_episodes=2)
    traj = play_episode(env, agent, _options(0), act_seed=0)
    allowed = traj.allowed_actions(5)
    logits = agent.policy(torch.as_tensor(traj.obs))
    logp = torch.log_softmax(logits.masked_fill(~torch.as_tensor(allowed), -torch.inf), -1)
    for t in range(traj.steps):
        p = agent.probabilities(traj.obs[t], allowed[t])
        assert np.allclose(np.exp(logp[t].detach().numpy()), p, atol=1e-6)


def test_an_unrestricting_mask_changes_nothing(env):
    """All ones (or no mask at all): the same random draws and choices as before the mask existed."""
    n = len(env.action_names)
    assert allowed_actions({"action_mask": np.ones(n, np.int8)}, n) is None
    assert allowed_actions({}, n) is None
    for name in ("random", "simple", "pg"):
        a, b = _agent(name, env, seed=3), _agent(name, env, seed=3)
        obs = np.full(len(env.observation_layout), 0.3, np.float32)
        seq_a = [a.act(obs, {"steps": t}) for t in range(20)]
        seq_b = [b.act(obs, {"steps": t, "action_mask": np.ones(n, np.int8)}) for t in range(20)]
        assert seq_a == seq_b


def test_fixed_pipeline_skips_actions_that_cannot_run(env):
    mask = {"action_mask": np.array(EXPECTED_MASK, np.int8)}
    names = env.action_names
    default = make_agent("fixed", env)  # icp_coarse, icp_fine, pick if present, else the pick alone
    assert all(names[default.act(None, {"steps": t, **mask})] == "pick" for t in range(3))
    agent = make_agent("fixed", env, sequence=["icp_coarse", "d2co", "depth_refine", "pick"], restart=1)
    acted = [names[agent.act(None, {"steps": t, **mask})] for t in range(6)]
    assert acted == ["d2co", "pick", "d2co", "pick", "d2co", "pick"]
    full = [names[agent.act(None, {"steps": t})] for t in range(6)]
    assert full == ["icp_coarse", "d2co", "depth_refine", "pick", "d2co", "depth_refine"]


# --------------------------------------------------------------------------- train, evaluate, bench, show

def test_train_and_evaluate_on_an_rgb_only_dataset(rgb_dataset, pipeline_path, tmp_path):
    from perception_config.learning.evaluation import evaluate
    from perception_config.learning.training import train
    from perception_config.rl.settings import EnvSettings

    settings = EnvSettings().replace(time_mode="cost_table", max_ops=5)
    policy = train(rgb_dataset, "pg", tmp_path / "run", 8, settings=settings, pipeline=pipeline_path, workers=1,
                   progress=False, agent_kwargs={"batch_episodes": 4})
    results = evaluate(rgb_dataset, [policy], [0.3], tmp_path / "eval", episodes_per_lambda=3, progress=False,
                       plots=False, fixed=[("icp_coarse", "d2co", "pick")], best_static_episodes=2)
    records = json.loads(results.read_text())
    assert {r["agent"] for r in records} >= {"random", "oracle", "fixed:icp_coarse+d2co+pick"}
    episodes = [json.loads(line) for line in (tmp_path / "eval" / "episodes.jsonl").read_text().splitlines()]
    assert episodes and all(e["masked_actions"] == sorted(DEPTH_ACTIONS, key=["icp_coarse", "depth_refine"].index)
                            for e in episodes)
    assert not any(DEPTH_ACTIONS & set(e["actions"]) for e in episodes)


def test_cli_no_depth_reads_an_rgbd_dataset_as_rgb_only(synthetic_dataset, pipeline_path, tmp_path):
    from perception_config.cli import main

    out = tmp_path / "conv.json"
    assert main(["bench", "convergence", "--dataset", str(synthetic_dataset), "--no-depth", "--out", str(out),
                 "--pipeline", str(pipeline_path), "--frames", "1", "--lambdas", "0.3", "--applications", "1",
                 "--quiet"]) == 0
    assert set(json.loads(out.read_text())) == {"d2co", "none (pick at once)"}
    png = tmp_path / "show.png"
    assert main(["show", "--dataset", str(synthetic_dataset), "--no-depth", "--out", str(png)]) == 0
    assert png.stat().st_size > 1000


# --------------------------------------------------------------------------- MCAP and ROS

def test_bag_round_trip_without_depth(rgb_dataset, synthetic_dataset, tmp_path):
    from perception_config.datasets.bag import bag_info, read_bag, write_bag, write_frames

    n = write_bag(rgb_dataset, tmp_path / "rgb.mcap", progress=False)
    info = bag_info(tmp_path / "rgb.mcap")
    assert n == 4 and info["frames"] == 4
    assert "/camera/depth/image_raw" not in {t["topic"] for t in info["topics"]}
    ds = BopDataset(rgb_dataset)
    frames = list(read_bag(tmp_path / "rgb.mcap"))
    assert len(frames) == 4
    for frame, key in zip(frames, ds.image_keys()):
        orig = ds.load_frame(*key, with_models=False)
        assert frame.depth is None and (frame.scene_id, frame.im_id) == key
        assert np.array_equal(frame.rgb, orig.rgb) and np.allclose(frame.K, orig.K)
        assert [o.obj_id for o in frame.objects] == [o.obj_id for o in orig.objects]
    # a recording is RGB-D or RGB-only throughout
    rgbd = BopDataset(synthetic_dataset).load_frame(0, 0, with_models=False)
    with pytest.raises(ValueError, match="RGB-only"):
        write_frames([frames[0], rgbd], tmp_path / "mixed.mcap")
    # an RGB-D bag read as RGB-only on request
    write_bag(synthetic_dataset, tmp_path / "rgbd.mcap", progress=False)
    assert all(f.depth is not None for f in read_bag(tmp_path / "rgbd.mcap"))
    assert all(f.depth is None for f in read_bag(tmp_path / "rgbd.mcap", depth_topic=""))


@pytest.mark.ros
def test_an_rgb_only_camera_assembles_frames_from_colour_and_camera_info(ros_node, rgb_dataset, synthetic_dataset):
    """CameraFrames(use_depth=False) makes frames of colour + camera_info alone; a block needing
    depth answers "needs depth" on them; the RGB-D camera still waits for the depth image."""
    from perception_config.ros.camera_frames import CameraFrames
    from perception_config.ros.conversions import frame_to_msgs

    frame = BopDataset(rgb_dataset).load_frame(0, 0)
    color, depth, info = frame_to_msgs(frame, 5_000_000_000)
    assert depth is None
    cam = CameraFrames(ros_node, 4, use_depth=False)
    cam._on_info(info)
    cam._add("color", color)
    got = cam.get(5_000_000_000, 0.0).frame
    assert got.depth is None and np.array_equal(got.rgb, frame.rgb) and np.allclose(got.K, frame.K)
    obj = frame.objects[0]
    r = create("icp_point_to_plane")(BlockInput(frame=got, model=obj.model, pose=obj.gt))
    assert not r.ok and "needs depth" in r.reason

    rgbd = BopDataset(synthetic_dataset).load_frame(0, 0)
    color, depth, info = frame_to_msgs(rgbd, 6_000_000_000)
    cam2 = CameraFrames(ros_node, 4)
    cam2._on_info(info)
    cam2._add("color", color)
    assert not cam2.frames.has(6_000_000_000)  # waits for its depth
    cam2._add("depth", depth)
    assert cam2.get(6_000_000_000, 0.0).frame.depth is not None


# --------------------------------------------------------------------------- real RGB photographs

def test_an_episode_runs_end_to_end_on_real_lmo_rgb(lmo_rgb_root):
    data = yaml.safe_load(RGB_PIPELINE)
    env = PerceptionConfigEnv(BopDataset(lmo_rgb_root), pipeline_from_dict(data), time_mode="cost_table",
                              max_ops=4)
    agent = make_agent("fixed", env, sequence=["icp_coarse", "d2co", "d2co", "pick"])
    traj = play_episode(env, agent, _options(3, 0.2, 11), act_seed=0)
    assert traj.initial_info["action_mask"].tolist() == EXPECTED_MASK
    assert traj.names[:2] == ["d2co", "d2co"] and all(traj.oks[:2])
    scores = traj.final_info["scores"]
    assert np.isfinite(scores["psi_c"]) and np.isnan(scores["psi_d"]) and np.isnan(scores["icp_fitness"])


def test_the_shipped_rgb_pipeline_by_name(rgb_dataset, tmp_path):
    """`--pipeline rgb` names the shipped RGB pipeline: no action needs depth, so nothing is
    masked on an RGB-only dataset; launch passes the name on; an unknown name lists the shipped."""
    from perception_config.blocks.pipeline import load_pipeline, shipped_pipelines
    from perception_config.launcher.resolution import resolve_nodes

    assert {"default", "rgb"} <= set(shipped_pipelines())
    pipe = load_pipeline(Path("rgb"))
    assert [a.name for a in pipe.actions] == ["d2co", "region", "regenerate", "pick"]
    env = PerceptionConfigEnv(rgb_dataset, "rgb", time_mode="cost_table", max_ops=4)
    _, info = env.reset(seed=0, options=_options(0))
    assert info["action_mask"].tolist() == [1, 1, 1, 1]
    _, _, _, _, info = env.step(1)  # region
    assert info["ok"], info
    specs = resolve_nodes(nodes=["refinement"], models=rgb_dataset / "models", pipeline="rgb", cwd=tmp_path,
                          say=lambda _: None)
    assert "pipeline:=rgb" in " ".join(specs[0].arguments())
    with pytest.raises(FileNotFoundError, match="shipped pipelines by name: cell, default, pick_success, rgb"):
        load_pipeline("nope")
