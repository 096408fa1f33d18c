"""PerceptionConfigEnv: Gymnasium contract, reward = -seconds, episode ends, bad input."""
from __future__ import annotations

import math
import os
import subprocess
import sys
import textwrap

import gymnasium as gym
import numpy as np
import pytest

from perception_config.blocks import load_all
from perception_config.rl.env import PerceptionConfigEnv
from rl_helpers import BITWISE_PIPELINE, make_env, pipeline_file, tiny_dataset


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    return make_env(tmp_path_factory)


def _cost(block: str) -> float:
    """Cost-table seconds of an action: the block's own default_cost plus the scoring pass."""
    blocks = load_all()
    return blocks[block].default_cost + sum(blocks[s].default_cost for s in ("psi_d", "psi_c", "icp_fitness"))


def test_check_env_passes_on_the_registered_env_as_a_user_makes_it(tmp_path_factory):
    """What a user types, in a fresh interpreter: gymnasium.make with the registered id (the
    module-qualified form imports the package), the shipped pipeline (ICP included), the default
    settings (cost-table time); check_env on the env and on env.unwrapped."""
    script = textwrap.dedent(f"""
        import warnings
        import gymnasium as gym
        from gymnasium.utils.env_checker import check_env
        env = gym.make("perception_config.rl.env:PerceptionConfig-v0", dataset={str(tiny_dataset(tmp_path_factory))!r})
        assert env.unwrapped.settings.time_mode == "cost_table", env.unwrapped.settings
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # check_env's advice to pass env.unwrapped, done next
            check_env(env, skip_render_check=True)
        check_env(env.unwrapped, skip_render_check=True)
        print("check_env passed")
    """)
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
                         env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    assert run.returncode == 0 and "check_env passed" in run.stdout, run.stderr[-3000:]


def test_check_env_fails_on_measured_time(tmp_path_factory):
    """The measured-time option: rewards are wall-clock seconds, never equal twice; check_env
    says so (the reason cost-table time is the default)."""
    from gymnasium.utils.env_checker import check_env

    e = gym.make("PerceptionConfig-v0", dataset=tiny_dataset(tmp_path_factory), time_mode="measured")
    with pytest.raises(AssertionError, match="Deterministic step rewards are not equivalent"):
        check_env(e.unwrapped, skip_render_check=True)


def test_bitwise_pipeline_passes_check_env(tmp_path_factory):
    from gymnasium.utils.env_checker import check_env

    e = make_env(tmp_path_factory, BITWISE_PIPELINE, "bitwise.yaml")
    check_env(e, skip_render_check=True)


def test_icp_pipeline_is_bitwise_reproducible_in_cost_table_mode(tmp_path_factory):
    """With ICP, seeded episodes give bitwise the same observations, rewards and poses (Open3D on
    one thread during reset and step in cost-table mode), and the thread limit is restored."""
    import open3d as o3d

    e = make_env(tmp_path_factory)
    before = o3d.utility.get_max_threads()
    runs = []
    for _ in range(3):
        obs, _ = e.reset(seed=11)
        trace = [obs]
        for a in (0, 1, 0, 2):
            obs, reward, _term, _trunc, info = e.step(a)
            trace += [obs, np.float64(reward), info["pose"].R, info["pose"].t]
        runs.append(trace)
    for run in runs[1:]:
        for a, b in zip(runs[0], run):
            np.testing.assert_array_equal(a, b)
    assert o3d.utility.get_max_threads() == before


def test_registered_env_runs_stable_baselines3_ppo(tmp_path_factory):
    from stable_baselines3 import PPO

    e = gym.make("PerceptionConfig-v0", dataset=tiny_dataset(tmp_path_factory),
                 pipeline=pipeline_file(tmp_path_factory), time_mode="cost_table", max_ops=5)
    model = PPO("MlpPolicy", e, n_steps=64, batch_size=32, n_epochs=2, seed=0, device="cpu", verbose=0)
    model.learn(total_timesteps=256)
    assert model.num_timesteps >= 256
    obs, _ = e.reset(seed=1)
    action, _ = model.predict(obs, deterministic=True)
    assert e.action_space.contains(int(action))
    e.close()


def test_reset_contract_and_determinism(env):
    obs, info = env.reset(options={"episode": 1, "lambda": 0.4, "episode_seed": 7})
    assert env.observation_space.contains(obs)
    assert obs.shape == (len(env.observation_layout),)
    assert info["episode_index"] == 1 and info["noise_lambda"] == pytest.approx(0.4) and info["steps"] == 0
    obs2, _ = env.reset(options={"episode": 1, "lambda": 0.4, "episode_seed": 7})
    np.testing.assert_array_equal(obs, obs2)
    obs3, _ = env.reset(options={"episode": 1, "lambda": 0.4, "episode_seed": 8})
    assert not np.array_equal(obs, obs3)  # another initial hypothesis
    # Seeded resets draw the same episode, lambda and episode seed.
    a, ia = env.reset(seed=5)
    b, ib = env.reset(seed=5)
    np.testing.assert_array_equal(a, b)
    assert ia["episode_key"] == ib["episode_key"] and ia["noise_lambda"] == ib["noise_lambda"]
    assert env.settings.lambda_range[0] <= ia["noise_lambda"] <= env.settings.lambda_range[1]


def test_step_before_reset_and_bad_action(tmp_path_factory):
    e = make_env(tmp_path_factory)
    with pytest.raises(RuntimeError, match="reset"):
        e.step(0)
    e.reset(options={"episode": 0, "lambda": 0.3, "episode_seed": 0})
    with pytest.raises(ValueError, match="not in"):
        e.step(len(e.action_names))
    with pytest.raises(ValueError, match="not in"):
        e.step(-1)


def test_reward_is_minus_seconds_of_block_and_scoring(env):
    env.reset(options={"episode": 0, "lambda": 0.5, "episode_seed": 1})
    i = env.action_names.index("icp_coarse")
    obs, reward, terminated, truncated, info = env.step(i)
    assert reward == pytest.approx(-_cost("icp_point_to_plane"))
    assert info["seconds"] == pytest.approx(-reward) and info["episode_time"] == pytest.approx(-reward)
    assert env.observation_space.contains(obs)
    assert obs[env.observation_layout.index("last_action:icp_coarse")] == 1.0
    assert obs[env.observation_layout.index("progress:step")] == pytest.approx(1 / env.max_ops)
    assert not terminated and not truncated


def test_successful_pick_ends_the_episode(env):
    env.reset(options={"episode": 0, "lambda": 0.0, "episode_seed": 0})  # lambda 0: the ground truth
    _, reward, terminated, truncated, info = env.step(env.action_names.index("pick"))
    assert info["picked"] is True and terminated and not truncated
    assert reward == pytest.approx(-_cost("simulated_pick"))


def test_failed_pick_costs_the_robot_attempt(tmp_path_factory):
    e = make_env(tmp_path_factory, failed_pick_cost=3.7)
    e.reset(options={"episode": 0, "lambda": 2.0, "episode_seed": 3})  # far off: the pick fails
    obs, reward, terminated, truncated, info = e.step(e.action_names.index("pick"))
    assert info["ok"] and info["picked"] is False and not terminated and not truncated
    assert reward == pytest.approx(-(_cost("simulated_pick") + 3.7))
    assert info["seconds"] == pytest.approx(-reward)
    assert obs[e.observation_layout.index("progress:pick_failed")] == 1.0


def test_pick_is_masked_on_the_hypothesis_it_failed_on(tmp_path_factory):
    """After a failed pick the pick is masked until an action changes the hypothesis; an action
    that fails (the hypothesis stays) leaves it masked; a pick taken anyway is attempted."""
    from perception_config.agents.base import EnvSpec
    from perception_config.agents.fixed import FixedAgent

    e = make_env(tmp_path_factory)
    pick, refine = e.action_names.index("pick"), e.action_names.index("depth_refine")
    _, info = e.reset(options={"episode": 0, "lambda": 2.0, "episode_seed": 3})  # far off: the pick fails
    assert info["action_mask"].all()
    _, _, _, _, info = e.step(pick)
    assert info["picked"] is False and info["action_mask"][pick] == 0 and e.action_mask()[pick] == 0
    assert info["action_mask"].sum() == len(e.action_names) - 1
    assert e.frame_mask().all()  # the frame itself allows every action (the oracle searches with this)
    _, _, terminated, _, info = e.step(pick)  # taken anyway: the robot tries again
    assert info["ok"] and info["picked"] is False and not terminated and info["action_mask"][pick] == 0
    _, _, _, _, info = e.step(refine)
    assert info["ok"] and info["action_mask"].all()
    # the fixed agent goes on with its loop instead of picking the failed hypothesis again
    agent = FixedAgent(EnvSpec.from_env(e), sequence=["pick", "depth_refine"], after="pick")
    _, info = e.reset(options={"episode": 0, "lambda": 2.0, "episode_seed": 3})
    played = []
    for _ in range(4):
        a = agent.act(None, info)
        played.append(e.action_names[a])
        info = e.step(a)[4]
    assert played == ["pick", "depth_refine", "pick", "depth_refine"], played


def test_the_last_operation_is_a_pick_unless_the_pick_cannot_run(tmp_path_factory):
    """The final-pick rule: at the last of max_ops operations only the picks are allowed; where the
    pick is masked itself (it just failed on this hypothesis) the rule keeps nothing from running;
    `final_pick=False` turns it off."""
    e = make_env(tmp_path_factory, max_ops=3)
    pick, refine = e.action_names.index("pick"), e.action_names.index("depth_refine")
    _, info = e.reset(options={"episode": 0, "lambda": 2.0, "episode_seed": 3})  # far off: the pick fails
    assert info["action_mask"].all()
    info = e.step(refine)[4]
    assert info["action_mask"].all()  # one more operation may follow this one
    info = e.step(refine)[4]
    assert info["action_mask"].tolist() == [int(i == pick) for i in range(len(e.action_names))]
    assert info["loop_mask"].sum() == 0  # a rule for every agent, fixed plans included
    # a failed pick on the hypothesis: the last operation may be anything else
    e2 = make_env(tmp_path_factory, max_ops=2)
    e2.reset(options={"episode": 0, "lambda": 2.0, "episode_seed": 3})
    info = e2.step(pick)[4]
    assert info["picked"] is False and info["action_mask"][pick] == 0
    assert info["action_mask"].sum() == len(e2.action_names) - 1
    off = make_env(tmp_path_factory, max_ops=3, final_pick=False)
    off.reset(options={"episode": 0, "lambda": 2.0, "episode_seed": 3})
    off.step(refine)
    assert off.step(refine)[4]["action_mask"].all()


def test_truncation_at_max_ops_is_charged(tmp_path_factory):
    e = make_env(tmp_path_factory, max_ops=3, truncation_cost=4.0)
    e.reset(options={"episode": 0, "lambda": 0.5, "episode_seed": 0})
    a = e.action_names.index("depth_refine")
    for k in range(3):
        _, reward, terminated, truncated, info = e.step(a)
        assert not terminated
        assert truncated == (k == 2)
    assert reward == pytest.approx(-_cost("depth_refine") - 4.0)
    assert info["truncation_cost"] == 4.0
    assert info["episode_time"] == pytest.approx(3 * _cost("depth_refine"))  # a penalty, not time


def test_measured_time_mode_rewards_wall_time(tmp_path_factory):
    e = make_env(tmp_path_factory, time_mode="measured")
    e.reset(options={"episode": 0, "lambda": 0.5, "episode_seed": 0})
    _, reward, _, _, info = e.step(e.action_names.index("icp_coarse"))
    assert 0.0 < info["seconds"] < 5.0 and reward == pytest.approx(-info["seconds"])


@pytest.mark.parametrize("lam", [-0.1, 2.5, math.nan])
def test_lambda_outside_range_is_rejected(env, lam):
    with pytest.raises(ValueError, match="lambda"):
        env.reset(options={"episode": 0, "lambda": lam})


def test_bad_constructor_arguments(tmp_path_factory):
    ds, pipe = tiny_dataset(tmp_path_factory), pipeline_file(tmp_path_factory)
    with pytest.raises(ValueError, match="lambda_range"):
        PerceptionConfigEnv(ds, pipe, lambda_range=(0.5, 3.0))
    with pytest.raises(ValueError, match="lambda_range"):
        PerceptionConfigEnv(ds, pipe, lambda_range=(0.8, 0.2))
    with pytest.raises(ValueError, match="max_ops"):
        PerceptionConfigEnv(ds, pipe, max_ops=0)
    with pytest.raises(ValueError, match="time_mode"):
        PerceptionConfigEnv(ds, pipe, time_mode="simulated")
    with pytest.raises(ValueError, match="episode index"):
        e = PerceptionConfigEnv(ds, pipe, time_mode="cost_table")
        e.reset(options={"episode": len(e.source)})


def test_empty_dataset_is_a_clear_error(tmp_path_factory):
    ds, pipe = tiny_dataset(tmp_path_factory), pipeline_file(tmp_path_factory)
    with pytest.raises(ValueError, match="no usable episodes"):
        PerceptionConfigEnv(ds, pipe, image_keys=[])
    from perception_config.datasets.bop import BopDataset
    from perception_config.rl.episodes import EpisodeSource

    with pytest.raises(ValueError, match="no usable episodes"):  # every object below the visibility bar
        EpisodeSource(BopDataset(ds), None, min_visib_fract=1.01)
    with pytest.raises(ValueError, match="min_visib_fract must be in \\[0, 1\\]"):
        PerceptionConfigEnv(ds, pipe, min_visib_fract=1.01)


def test_the_final_pick_takes_the_best_hypothesis_the_episode_reached(tmp_path_factory):
    """With final_pick_best and pick_success among the scores, the pick at the last operation is taken at the
    hypothesis of highest pick score reached when the current one scores lower (info
    "picked_best"); when the current one is the best it is picked as it is."""
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "perception_config" / "config" / "pick_success_pipeline.yaml")
    env = make_env(tmp_path_factory, text.read_text(), "pick_success.yaml", max_ops=4, final_pick_best=True)
    regenerate, pick = env.action_names.index("regenerate"), env.action_names.index("pick")
    seen = {True: 0, False: 0}
    for ep_seed in range(12):
        _, info = env.reset(options={"episode": 0, "lambda": 0.6, "episode_seed": ep_seed})
        reached = [(info["scores"]["pick_success"], info["pose"])]
        for _ in range(3):
            _, _, _, _, info = env.step(regenerate)
            reached.append((info["scores"]["pick_success"], info["pose"]))
        assert info["action_mask"].tolist() == [int(i == pick) for i in range(len(env.action_names))]
        _, _, _, _, info = env.step(pick)
        best_score, best_pose = max(reached, key=lambda r: r[0])
        assert info["picked_best"] == (best_score > reached[-1][0])
        expected = best_pose if info["picked_best"] else reached[-1][1]
        np.testing.assert_allclose(info["pose"].t, expected.t)
        np.testing.assert_allclose(info["pose"].R, expected.R)
        seen[info["picked_best"]] += 1
    assert seen[True] and seen[False], seen
