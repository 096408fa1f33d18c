"""The load-independent reward: the calibrated cost model (bench/calibration.py), its use by the
environment and by `perception-config train`; the loop rule (rl/pose_memory.py) and the env's
snapshot/restore."""
from __future__ import annotations

import json

import numpy as np
import pytest

from perception_config.agents.base import EnvSpec
from perception_config.agents.fixed import FixedAgent
from perception_config.bench.calibration import calibrate, read_cost_table, write_cost_model
from perception_config.core.geometry import Pose
from perception_config.rl.pose_memory import PoseMemory, loop_steps, same_pose, surface_move
from perception_config.rl.settings import EnvSettings
from rl_helpers import make_env, pipeline_file, tiny_dataset


def _pose(x: float, angle: float = 0.0) -> Pose:
    c, s = np.cos(angle), np.sin(angle)
    return Pose(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]), np.array([x, 0.0, 0.5]))


def test_pose_memory_marks_actions_taken_at_a_hypothesis_reached_again():
    d = 0.1  # m: the tolerance is 2e-3 x d = 0.2 mm
    p0, p1 = _pose(0.0), _pose(0.01)
    m = PoseMemory(d)
    m.visit(p0)
    assert m.record(p0, 0, p1) is False  # A: p0 -> p1, somewhere new
    assert m.stale(p1) == set()
    assert m.record(p1, 1, _pose(0.0001)) is True  # B: back to p0 (0.1 mm away: the same hypothesis)
    assert m.stale(p0) == {0}  # A again would go to p1 again: a loop
    assert m.record(p0, 2, p0) is True and m.stale(p0) == {0, 2}  # an action that left it unchanged
    assert not same_pose(p0, _pose(0.0003), d) and not same_pose(p0, _pose(0.0, 0.003), d)
    assert same_pose(None, None, d) and not same_pose(p0, None, d)
    # the evaluation's count: an action repeated at the same hypothesis, picks left out
    ref = "refinement"
    assert loop_steps(p0, [p1, p0, p1], ["a", "b", "a"], [ref] * 3, d) == 1  # A, B, A: the cycle come round
    assert loop_steps(p0, [p0, p0], ["a", "a"], [ref] * 2, d) == 1  # A unchanged, A again
    assert loop_steps(p0, [p0, p0, p0], ["a", "b", "pick"], [ref, ref, "pick"], d) == 0  # each once
    assert loop_steps(p0, [p0, p0], ["pick", "pick"], ["pick"] * 2, d) == 0


def test_pose_memory_names_an_action_that_converged():
    d = 0.1  # m
    m = PoseMemory(d)
    m.visit(_pose(0.0))
    m.record(_pose(0.0), 0, _pose(0.02))  # A moved every point 0.2 d: not converged
    assert m.converged(_pose(0.02), 0.01) == set()
    m.record(_pose(0.02), 0, _pose(0.0205))  # A again moved it 0.005 d: converged
    assert m.converged(_pose(0.0205), 0.01) == {0}
    assert m.stale(_pose(0.0205)) == set()  # 0.5 mm is more than POSE_TOL: not the same hypothesis
    assert m.converged(_pose(0.0205), 0.0) == set() and m.converged(None, 0.01) == set()
    # a rotation counts by what it moves the points: 0.03 rad moves one d / 2 from the origin 0.015 d
    assert surface_move(_pose(0.0), _pose(0.0, 0.03), d) == pytest.approx(0.015)
    m.record(_pose(0.0205), 1, _pose(0.0205, 0.03))
    assert m.converged(_pose(0.0205, 0.03), 0.01) == set()  # B moved it too far; A left it elsewhere


def test_env_masks_a_refiner_that_converged(tmp_path_factory):
    """icp_fine until its call moves no point of the object by 1 % of the diameter: then the
    convergence rule masks it (action_mask 0, loop_mask 1) though the hypothesis moved; with
    converge_tol 0 only the unchanged-hypothesis rule would."""
    env = make_env(tmp_path_factory, max_ops=20, converge_tol=0.01)
    fine = env.action_names.index("icp_fine")
    _, info = env.reset(options={"episode": 0, "lambda": 0.3, "episode_seed": 3})
    for _ in range(15):
        before = env.last_outcome.pose
        _, _, _, _, info = env.step(fine)
        if surface_move(before, env.last_outcome.pose, env.episode.model.diameter) <= 0.01:
            break
    else:
        raise AssertionError("icp_fine moved the hypothesis by more than 1 % for 15 calls")
    assert info["action_mask"][fine] == 0 and info["loop_mask"][fine] == 1
    pose, d = env.last_outcome.pose, env.episode.model.diameter
    assert fine in env._memory.converged(pose, 0.01)
    if not same_pose(before, pose, d):  # it moved: the unchanged-hypothesis rule alone would not mask it
        assert fine not in env._memory.stale(pose)


def test_env_masks_an_action_that_left_the_hypothesis_unchanged(tmp_path_factory):
    """icp_fine until it stops moving the hypothesis: then it is masked (action_mask 0, loop_mask 1)
    while the hypothesis stays; with loop_mask off it never is; a fixed plan still plays it."""
    for loop_mask in (True, False):
        env = make_env(tmp_path_factory, loop_mask=loop_mask, max_ops=20, converge_tol=0.0)
        fine = env.action_names.index("icp_fine")
        _, info = env.reset(options={"episode": 0, "lambda": 0.05, "episode_seed": 3})
        unchanged = False
        for _ in range(15):
            before = env.last_outcome.pose
            _, _, _, _, info = env.step(fine)
            if same_pose(before, env.last_outcome.pose, env.episode.model.diameter):
                unchanged = True
                break
        assert unchanged, "icp_fine kept moving the hypothesis for 15 calls"
        assert info["action_mask"][fine] == (0 if loop_mask else 1)
        assert info["loop_mask"][fine] == (1 if loop_mask else 0)
        if loop_mask:
            spec = EnvSpec.from_env(env)
            fixed = FixedAgent(spec, sequence=["icp_fine", "pick"])
            fixed._t = 0
            assert fixed.act(np.zeros(1), info) == fine  # an engineer's plan is not bound by the loop rule
            env.step(env.action_names.index("depth_refine"))
            if not same_pose(before, env.last_outcome.pose, env.episode.model.diameter):
                assert env.action_mask()[fine] == 1  # a new hypothesis: icp_fine may run again


def test_env_snapshot_restore_repeats_a_step_bit_for_bit(tmp_path_factory):
    env = make_env(tmp_path_factory)
    env.reset(options={"episode": 1, "lambda": 0.6, "episode_seed": 11})
    env.step(env.action_names.index("regenerate"))
    state = env.snapshot()
    outs = []
    for _ in range(2):
        env.restore(state)
        obs, r, term, trunc, info = env.step(env.action_names.index("icp_coarse"))
        obs2, r2, *_ = env.step(env.action_names.index("regenerate"))
        outs.append((obs.tobytes(), r, term, trunc, info["action_mask"].tobytes(), obs2.tobytes(), r2, env.steps,
                     env.episode_time))
    assert outs[0] == outs[1]


@pytest.fixture(scope="module")
def cost_model(tmp_path_factory):
    ds = tiny_dataset(tmp_path_factory)
    return calibrate(ds, pipeline_file(tmp_path_factory), episodes=6, seed=1, progress=False)


def test_calibrate_measures_every_action_and_the_scoring_pass(cost_model, tmp_path_factory):
    table = cost_model["cost_table"]
    for name in ("icp_coarse", "icp_fine", "depth_refine", "regenerate", "pick", "generate"):
        assert f"action:{name}" in table and table[f"action:{name}"] >= 1e-4
    assert table["scoring"] >= 1e-4
    calls = cost_model["calls"]
    assert calls["action:icp_coarse"] == 12  # 6 episodes x 2 states
    per_object = [k for k in table if k.startswith("action:icp_coarse@")]
    assert per_object, "no per-object entry from 6 episodes x 2 states"
    assert all(calls[k] >= 3 for k in per_object)
    assert all(v == round(v, 4) for v in table.values())  # 0.1 ms resolution
    # the env charges it: an icp_coarse step costs the table's action + scoring pass of the object
    env = make_env(tmp_path_factory, cost_table=table)
    env.reset(options={"episode": 0, "lambda": 0.5, "episode_seed": 2})
    obj = env.episode.model.obj_id
    _, r, *_ = env.step(env.action_names.index("icp_coarse"))
    want = table.get(f"action:icp_coarse@{obj}", table["action:icp_coarse"]) \
        + table.get(f"scoring@{obj}", table["scoring"])
    assert r == pytest.approx(-want, abs=1e-12)


def test_cost_model_file_round_trip_and_bad_files(cost_model, tmp_path):
    path = write_cost_model(cost_model, tmp_path / "cm.json")
    assert read_cost_table(path) == cost_model["cost_table"]
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ValueError, match="bad.json"):
        read_cost_table(tmp_path / "bad.json")
    (tmp_path / "neg.json").write_text(json.dumps({"cost_table": {"action:pick": -1}}))
    with pytest.raises(ValueError, match="neg.json.*action:pick"):
        read_cost_table(tmp_path / "neg.json")
    with pytest.raises(FileNotFoundError, match="calibrate"):
        read_cost_table(tmp_path / "missing.json")


def test_train_calibrates_by_default_and_keeps_the_model_in_the_policy(tmp_path_factory, tmp_path):
    """`perception-config train`: the cost model measured on the train images is written to
    OUT/cost_model.json and is the policy's cost table; --resume keeps it."""
    from perception_config.agents.policy_io import read_file
    from perception_config.cli import main

    ds, pipe = tiny_dataset(tmp_path_factory), pipeline_file(tmp_path_factory)
    out = tmp_path / "run"
    args = ["train", "--dataset", str(ds), "--pipeline", str(pipe), "--agent", "pg", "--out", str(out), "--quiet",
            "--no-episode-store", "--calibration-episodes", "3", "--final-pick-best", "--converge-tol", "0.02"]
    assert main([*args, "--episodes", "8"]) == 0
    model = json.loads((out / "cost_model.json").read_text())
    assert model["episodes"] == 3  # --calibration-episodes
    meta, _ = read_file(out / "policy.safetensors")
    settings = EnvSettings.from_json(meta["extra"]["env_settings"])
    assert settings.time_mode == "cost_table" and settings.cost_table == model["cost_table"]
    assert settings.final_pick_best is True and settings.converge_tol == 0.02  # the rules' options, kept
    extra = meta["extra"]  # measured on the train images (validation's included), never on the test images
    assert model["image_keys"] == sorted(extra["train_image_keys"] + extra.get("validation_image_keys", []))
    assert not {tuple(k) for k in model["image_keys"]} & {tuple(k) for k in extra["test_image_keys"]}
    assert main([*args, "--episodes", "16", "--resume"]) == 0
    meta2, _ = read_file(out / "policy.safetensors")
    assert meta2["extra"]["env_settings"]["cost_table"] == model["cost_table"]
    assert meta2["extra"]["episodes"] >= 16
