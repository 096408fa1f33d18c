"""Validation-based policy selection (learning/validation.py, learning/training.py): the shipped policy is the
validation-best one, the validation images are disjoint from the training and test images,
and a resumed run selects exactly as the uninterrupted one."""
from __future__ import annotations

import csv
import sqlite3

import numpy as np
import pytest

from perception_config import cli
from perception_config.agents import load_agent, make_agent
from perception_config.agents.policy_io import PolicyError, read_file
from perception_config.learning.seed_selection import SEEDS_CSV, train_seeds, validated
from perception_config.learning.training import CHECKPOINT, VALIDATION_CSV, train
from perception_config.learning.validation import TENSOR_PREFIX, default_lambdas, split_validation, validation_episodes
from perception_config.rl.episode_loop import acting_seed, play_episode
from perception_config.rl.settings import EnvSettings
from rl_helpers import make_env, pipeline_file, tiny_dataset

# A short lambda range with expensive refinements: the untrained policy is poor, so the checks differ.
FAST = EnvSettings(time_mode="cost_table", lambda_range=(0.2, 0.8), max_ops=5)
VAL = {"validation_fraction": 0.34, "validate_every": 8}  # 1 of the tiny dataset's 3 train images


def _train(tmp_path_factory, out, episodes=32, **kw):
    args = {"workers": 1, "progress": False, "checkpoint_every": 8, "agent_kwargs": {"batch_episodes": 8, "lr": 0.05},
            "seed": 3, **VAL, **kw}
    return train(tiny_dataset(tmp_path_factory), "pg", out, episodes, settings=FAST,
                 pipeline=pipeline_file(tmp_path_factory), **args)


def _rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def straight_run(tmp_path_factory):
    """A run of 32 episodes, validated at 8, 16, 24 and 32; the tests only read it."""
    out = tmp_path_factory.mktemp("validated") / "run"
    return _train(tmp_path_factory, out, episodes=32)


def test_shipped_policy_is_the_validation_best_and_images_are_disjoint(tmp_path_factory, straight_run):
    path = straight_run
    out = path.parent
    meta, tensors = read_file(path)
    extra = meta["extra"]
    train_keys = {tuple(k) for k in extra["train_image_keys"]}
    val_keys = {tuple(k) for k in extra["validation_image_keys"]}
    test_keys = {tuple(k) for k in extra["test_image_keys"]}
    assert train_keys and val_keys and test_keys
    assert not (train_keys & val_keys or train_keys & test_keys or val_keys & test_keys)
    assert len(train_keys | val_keys | test_keys) == 4 and extra["validation_lambdas"] == [0.2, 0.5, 0.8]
    # No training episode was drawn from a validation image (the run's episode store has them all).
    with sqlite3.connect(out / "episodes.sqlite") as con:
        played = {tuple(r) for r in con.execute("SELECT DISTINCT scene_id, im_id FROM episodes WHERE source='train'")}
    assert played and played <= train_keys

    # Checks at 8, 16, 24, 32 (every 8 episodes and the end); the selected one has the lowest cost.
    rows = _rows(out / VALIDATION_CSV)
    assert [int(r["episode"]) for r in rows] == [8, 16, 24, 32]
    costs = [float(r["cost"]) for r in rows]
    best = max(i for i, c in enumerate(costs) if c == min(costs))  # ties: the later policy
    sel = extra["selected"]
    assert sel["episode"] == int(rows[best]["episode"]) and sel["validation"]["cost"] == pytest.approx(costs[best])
    assert extra["episodes"] == 32 and sel["last"]["episode"] == 32

    # The shipped policy really scores the selected cost: replay the validation episodes with it.
    env = make_env(tmp_path_factory, max_ops=5, lambda_range=(0.2, 0.8))
    val_index = [i for i, ek in enumerate(env.source.episodes) if (ek.scene_id, ek.im_id) in val_keys]
    options = validation_episodes(val_index, extra["validation_lambdas"], extra["split_seed"])
    assert len(options) == extra["validation_episodes"] == sel["validation"]["episodes"]
    agent = load_agent(path, env)
    replay = np.mean([play_episode(env, agent, o, acting_seed(o["episode_seed"])).cost for o in options])
    assert replay == pytest.approx(sel["validation"]["cost"], rel=1e-9)
    # The checkpoint keeps the latest policy (to resume) beside the selected weights.
    ck_meta, ck = read_file(out / CHECKPOINT)
    for k, v in tensors.items():
        np.testing.assert_array_equal(ck[TENSOR_PREFIX + k], v)
    assert ck_meta["trainer"]["validation"]["best"]["episode"] == sel["episode"]
    if sel["episode"] != 32:
        assert any(not np.array_equal(ck[k], v) for k, v in tensors.items())


def test_resumed_run_selects_as_the_uninterrupted_one(tmp_path_factory, tmp_path, straight_run):
    straight = straight_run  # 32 episodes without a stop
    _train(tmp_path_factory, tmp_path / "split", episodes=16)
    resumed = _train(tmp_path_factory, tmp_path / "split", episodes=32, resume=True)
    a_meta, a = read_file(straight)
    b_meta, b = read_file(resumed)
    assert a_meta["extra"]["selected"] == b_meta["extra"]["selected"]
    for k in a:
        np.testing.assert_allclose(a[k], b[k], rtol=1e-6, atol=1e-7)
    # The check at the end of the first part (16) is a regular one: the histories are the same.
    assert _rows(straight.parent / VALIDATION_CSV) == _rows(tmp_path / "split" / VALIDATION_CSV)
    # The held-out images are part of the run: another fraction cannot resume it.
    with pytest.raises(PolicyError, match="validation_fraction"):
        _train(tmp_path_factory, tmp_path / "split", episodes=32, resume=True, validation_fraction=0.5)
    with pytest.raises(PolicyError, match="validation_fraction"):
        _train(tmp_path_factory, tmp_path / "split", episodes=32, resume=True, validation_fraction=0.0)


def test_validation_split_lambdas_and_bad_input():
    keys = [(1, i) for i in range(10)]
    fit, val = split_validation(keys, 0.2, 0)
    assert len(val) == 2 and not set(fit) & set(val) and set(fit) | set(val) == set(keys)
    assert split_validation(keys, 0.2, 0) == (fit, val) and split_validation(keys, 0.2, 1) != (fit, val)
    assert default_lambdas(EnvSettings()) == (0.1, 0.5, 1.0)
    assert default_lambdas(EnvSettings(lambda_range=(0.0, 0.2))) == (0.0, 0.1, 0.2)
    opts = validation_episodes([3, 5], (0.1, 0.5), 0)
    assert [(o["episode"], o["lambda"]) for o in opts] == [(3, 0.1), (3, 0.5), (5, 0.1), (5, 0.5)]
    assert opts == validation_episodes([3, 5], (0.1, 0.5), 0)
    with pytest.raises(ValueError, match="at least 2 train images"):
        split_validation([(1, 1)], 0.5, 0)
    with pytest.raises(ValueError, match="validation_fraction"):
        train("nowhere", "pg", "nowhere", 8, validation_fraction=1.0)
    with pytest.raises(ValueError, match="validate_every"):
        train("nowhere", "pg", "nowhere", 8, validation_fraction=0.2, validate_every=0)


def test_cli_train_flags(tmp_path_factory, tmp_path, capsys):
    out = tmp_path / "cli"
    code = cli.main(["train", "--dataset", str(tiny_dataset(tmp_path_factory)), "--out", str(out), "--episodes", "16",
                     "--pipeline", str(pipeline_file(tmp_path_factory)), "--time-mode", "cost_table",
                     "--cost-table", "blocks", "--max-ops", "5",
                     "--workers", "1", "--quiet", "--validation-fraction", "0.34", "--validate-every", "8"])
    assert code == 0
    meta, _ = read_file(out / "policy.safetensors")
    assert meta["extra"]["validation_fraction"] == 0.34 and meta["extra"]["validate_every"] == 8
    assert [int(r["episode"]) for r in _rows(out / VALIDATION_CSV)] == [8, 16]
    out0 = tmp_path / "off"
    assert cli.main(["train", "--dataset", str(tiny_dataset(tmp_path_factory)), "--out", str(out0), "--episodes", "8",
                     "--pipeline", str(pipeline_file(tmp_path_factory)), "--time-mode", "cost_table",
                     "--cost-table", "blocks", "--max-ops", "5",
                     "--workers", "1", "--quiet", "--validation-fraction", "0"]) == 0
    meta, _ = read_file(out0 / "policy.safetensors")
    assert "selected" not in meta["extra"] and not (out0 / VALIDATION_CSV).exists()


def test_seeds_ship_the_run_of_lowest_validation_cost(tmp_path_factory, tmp_path, capsys):
    """`train --seeds N`: one run per seed in OUT/seed-<s>/, the validation-best shipped
    (learning/seed_selection.py); a resumed call over finished runs trains nothing and ships the same."""
    out = tmp_path / "seeds"
    # 8 episodes, one check a run: the seeds' costs 6.20, 10.14 and 5.42 (with 16 each run also chose
    # its last check, and two seeds came within 0.001 of each other)
    args = ["train", "--dataset", str(tiny_dataset(tmp_path_factory)), "--out", str(out), "--episodes", "8",
            "--pipeline", str(pipeline_file(tmp_path_factory)), "--time-mode", "cost_table",
            "--cost-table", "blocks", "--max-ops", "5",
            "--lambda-range", "0.2", "0.8", "--workers", "1", "--quiet", "--validate-every", "8",
            "--agent-param", "batch_episodes=8", "--agent-param", "lr=0.05", "--seed", "3", "--seeds", "3"]
    assert cli.main(args + ["--validation-fraction", "0"]) == 2
    assert "validation_fraction must be > 0" in capsys.readouterr().err
    assert not out.exists()
    assert cli.main(args + ["--validation-fraction", "0.34"]) == 0
    rows = _rows(out / SEEDS_CSV)
    assert [int(r["seed"]) for r in rows] == [3, 4, 5] and [r["run"] for r in rows] == ["seed-3", "seed-4", "seed-5"]
    for r in rows:  # each row is its run's own selection
        v = validated(out / r["run"] / "policy.safetensors")
        assert float(r["validation_cost"]) == pytest.approx(v["cost"], rel=1e-5)
        assert int(r["selected_episode"]) == v["episode"] and read_file(out / r["run"] / "policy.safetensors")[0][
            "extra"]["seed"] == int(r["seed"])
    costs = [float(r["validation_cost"]) for r in rows]
    best = costs.index(min(costs))
    assert len(set(costs)) > 1  # the seeds' policies differ, so the choice is a real one
    assert [int(r["shipped"]) for r in rows] == [int(i == best) for i in range(3)]
    shipped = (out / "policy.safetensors").read_bytes()
    assert shipped == (out / rows[best]["run"] / "policy.safetensors").read_bytes()
    assert (out / "learning_curve.png").exists() and not (out / CHECKPOINT).exists()
    # Every run validated on the same episodes: their costs compare.
    metas = [read_file(out / r["run"] / "policy.safetensors")[0]["extra"] for r in rows]
    assert all(m["validation_image_keys"] == metas[0]["validation_image_keys"] for m in metas)
    # Without --resume the runs are not overwritten; with it, finished runs stay as they are.
    assert cli.main(args + ["--validation-fraction", "0.34"]) == 2
    assert cli.main(args + ["--validation-fraction", "0.34", "--resume"]) == 0
    assert (out / "policy.safetensors").read_bytes() == shipped and _rows(out / SEEDS_CSV) == rows
    with pytest.raises(ValueError, match="at least two seeds"):
        train_seeds("nowhere", "pg", tmp_path / "one", 8, [1, 1])
    # Over a single run's folder only with --overwrite, which drops that run's checkpoint and history.
    single = [a if a != str(out) else str(tmp_path / "single") for a in args[:-2]] + ["--episodes", "8",
                                                                                       "--validation-fraction", "0.34"]
    assert cli.main(single) == 0 and (tmp_path / "single" / CHECKPOINT).exists()
    assert cli.main(single + ["--seeds", "2"]) == 2 and "single training run" in capsys.readouterr().err
    assert cli.main(single + ["--seeds", "2", "--overwrite"]) == 0
    assert not (tmp_path / "single" / CHECKPOINT).exists() and not (tmp_path / "single" / "history.csv").exists()
    assert [r["run"] for r in _rows(tmp_path / "single" / SEEDS_CSV)] == ["seed-3", "seed-4"]


def test_pg_learning_rate_half_life_and_resume(tmp_path_factory, tmp_path):
    """lr_half_life halves the policy's learning rate every H episodes learned; a resumed run
    continues the schedule (the update count is in the checkpoint); 0 keeps it constant."""
    env = make_env(tmp_path_factory, max_ops=5, lambda_range=(0.2, 0.8))
    agent = make_agent("pg", env, batch_episodes=4, lr=0.04, lr_half_life=8)
    constant = make_agent("pg", env, batch_episodes=4, lr=0.04)
    for k in range(4):
        trajs = [play_episode(env, agent, {"episode": i % len(env.source), "lambda": 0.5, "episode_seed": 10 * k + i},
                              act_seed=i) for i in range(4)]
        agent.update([trajs])
        constant.update([trajs])
        assert agent.optimizer.param_groups[0]["lr"] == pytest.approx(0.04 * 0.5 ** (4 * k / 8))
        assert constant.optimizer.param_groups[0]["lr"] == 0.04
    assert agent.current_lr() == pytest.approx(0.04 * 0.5 ** 2)
    with pytest.raises(ValueError, match="lr_half_life"):
        make_agent("pg", env, lr_half_life=-1)
    # Through training: the run resumed at 8 ends with the learning rate of the straight run (its
    # update after the resume is at the halved rate; from a restarted schedule it would not be).
    kw = {"agent_kwargs": {"batch_episodes": 8, "lr": 0.05, "lr_half_life": 8}, "validation_fraction": 0.0}
    straight = _train(tmp_path_factory, tmp_path / "straight", episodes=16, **kw)
    _train(tmp_path_factory, tmp_path / "split", episodes=8, **kw)
    resumed = _train(tmp_path_factory, tmp_path / "split", episodes=16, resume=True, **kw)
    a_meta, a = read_file(straight)
    _, b = read_file(resumed)
    assert a_meta["hparams"]["lr_half_life"] == 8
    for k in a:
        np.testing.assert_allclose(a[k], b[k], rtol=1e-6, atol=1e-7)


def test_agent_params_from_the_command_line_are_checked_against_the_agents_bounds():
    from perception_config.cli import agent_params

    assert agent_params("pg", ["entropy_coef=0.05", "lr_half_life=2000"]) == {"entropy_coef": 0.05,
                                                                             "lr_half_life": 2000}
    assert agent_params("pg", None) == {}
    for bad, says in ((["foo=1"], "unknown hyper-parameters \\['foo'\\] for agent 'pg'"),
                      (["entropy_coef=x"], "entropy_coef must be a finite number"),
                      (["lr_half_life=-1"], "lr_half_life"),
                      (["novalue"], "expected KEY=VALUE")):
        with pytest.raises(ValueError, match=says):
            agent_params("pg", bad)


def test_the_recipe_warm_starts_where_the_pipeline_scores_the_pick_success_probability():
    from perception_config.cli.train import RECIPES, SCORED_RECIPES, recipe_params

    scored = recipe_params("pg", None, "pick_success")
    assert scored == SCORED_RECIPES["pg"] and scored["warm_start"] == "threshold"
    for plain in ("default", "cell", None):  # no calibrated score for the rule to read
        assert recipe_params("pg", None, plain) == RECIPES["pg"] and "warm_start" not in RECIPES["pg"]
    # an --agent-param wins over the recipe; agents without a recipe get only theirs
    assert recipe_params("pg", ["warm_start=none", "lr=0.02"], "pick_success") == {**scored, "warm_start": "none",
                                                                                  "lr": 0.02}
    assert recipe_params("es", None, "pick_success") == {}
