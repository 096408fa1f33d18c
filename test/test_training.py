"""Training: the pg agent learns, checkpoints resume exactly, Ctrl-C keeps the work, the
learning curve is a PNG, history.csv has each update's diagnostics. (On Ray workers:
test_ray_workers.py, test_ray_cluster.py; the figures pg's update reports: test_training_diagnostics.py.)"""
from __future__ import annotations

import csv
import os
import shutil
import signal

import numpy as np
import pytest

from perception_config.agents import load_agent, make_agent
from perception_config.agents.policy_io import read_file
from perception_config.learning import training
from perception_config.learning.learning_curve import plot_learning_curve
from perception_config.learning.training import CHECKPOINT, CURVE, train
from perception_config.learning.training_history import HISTORY_FIELDS, UPDATE_FIELDS
from perception_config.rl.episode_loop import play_episode
from perception_config.rl.settings import EnvSettings, settings_from_policy_meta
from rl_helpers import make_env, pipeline_file, tiny_dataset

FAST = EnvSettings(time_mode="cost_table", lambda_range=(0.2, 0.8), max_ops=5)


def _train(tmp_path_factory, out, agent="pg", episodes=16, **kw):
    """train() on the tiny dataset; EnvSettings fields among `kw` change the FAST settings."""
    settings = FAST.replace(**{k: kw.pop(k) for k in list(kw) if k in EnvSettings.__dataclass_fields__})
    args = {"workers": 1, "progress": False, **kw}
    args.setdefault("agent_kwargs", {"batch_episodes": 8} if agent == "pg" else {})
    return train(tiny_dataset(tmp_path_factory), agent, out, episodes, settings=settings, seed=args.pop("seed", 0),
                 pipeline=pipeline_file(tmp_path_factory), **args)


@pytest.fixture(scope="module")
def run16(tmp_path_factory):
    """train() of 16 episodes, checkpointed every 8: the tests read it (and copy it to resume it)."""
    out = tmp_path_factory.mktemp("trained") / "run"
    path = _train(tmp_path_factory, out, checkpoint_every=8)
    assert path == out / "policy.safetensors"
    return out


def test_train_writes_policy_curve_and_split(tmp_path_factory, tmp_path, run16):
    path = run16 / "policy.safetensors"
    env = make_env(tmp_path_factory)
    agent = load_agent(path, env)
    assert agent.kind == "pg" and not agent.explore
    meta, _ = read_file(path)
    extra = meta["extra"]
    assert extra["episodes"] == 16 and extra["split_seed"] == 0 and extra["test_fraction"] == 0.3
    assert extra["env_settings"] == FAST.to_json() and settings_from_policy_meta(meta) == FAST  # restored on load
    train_keys = {tuple(k) for k in extra["train_image_keys"]}
    test_keys = {tuple(k) for k in extra["test_image_keys"]}
    assert train_keys and test_keys and not train_keys & test_keys and len(train_keys | test_keys) == 4
    png = (run16 / CURVE).read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    import matplotlib.image

    img = matplotlib.image.imread(run16 / CURVE)
    assert img.ndim == 3 and img.shape[0] > 200 and img.shape[1] > 200
    assert len((run16 / "history.csv").read_text().splitlines()) == 17
    # The same `out` again is refused unless resumed or overwritten.
    with pytest.raises(FileExistsError, match="resume=True"):
        _train(tmp_path_factory, run16)
    with pytest.raises(ValueError, match="oracle"):
        _train(tmp_path_factory, tmp_path / "oracle", agent="oracle")


def test_history_has_each_updates_diagnostics_and_the_curve_a_panel_of_them(tmp_path_factory, tmp_path, run16):
    with open(run16 / "history.csv") as f:
        rows = list(csv.reader(f))
    assert rows[0] == ["episode", *HISTORY_FIELDS, *UPDATE_FIELDS]  # the old columns first, in their order
    table = np.array([[float(x) for x in r] for r in rows[1:]])
    assert table.shape == (16, 1 + len(HISTORY_FIELDS) + len(UPDATE_FIELDS)) and np.isfinite(table).all()
    col = {name: table[:, i] for i, name in enumerate(rows[0])}
    assert col["update"].tolist() == [1.0] * 8 + [2.0] * 8  # two rounds of batch_episodes=8, one update each
    n_actions = load_agent(run16 / "policy.safetensors", make_env(tmp_path_factory)).spec.n_actions
    assert ((col["entropy"] >= 0) & (col["entropy"] <= np.log(n_actions))).all()
    assert (col["grad_norm"] > 0).all() and (col["value_grad_norm"] > 0).all() and (col["value_loss"] > 0).all()
    assert (col["approx_kl"] >= 0).all() and (col["lr"] == 0.02).all()  # pg's default lr, constant
    # One update's figures on all the episodes of its round; the two updates differ.
    for name in ("loss", "entropy", "grad_norm", "approx_kl"):
        assert len(set(col[name][:8])) == 1 and len(set(col[name][8:])) == 1 and col[name][0] != col[name][8], name
    _, tensors = read_file(run16 / CHECKPOINT)  # kept in the checkpoint, as history.csv rounds them
    np.testing.assert_allclose(tensors["history/entropy"], col["entropy"], rtol=1e-5)
    # The curve has a fourth panel (entropy, gradient norm, loss per update): taller than without them.
    import matplotlib.image

    without = {k: tensors[f"history/{k}"] for k in HISTORY_FIELDS}
    three = plot_learning_curve(without, tmp_path / "three.png")
    tall, short = matplotlib.image.imread(run16 / CURVE).shape, matplotlib.image.imread(three).shape
    assert tall[1] == short[1] and tall[0] > short[0] * 1.2, (tall, short)


def test_resume_continues_exactly_where_the_checkpoint_left(tmp_path_factory, tmp_path, run16):
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        _train(tmp_path_factory, tmp_path / "none", resume=True)
    straight = _train(tmp_path_factory, tmp_path / "straight", episodes=32, checkpoint_every=8)
    shutil.copytree(run16, tmp_path / "split")  # the first 16 episodes, as trained by train()
    resumed = _train(tmp_path_factory, tmp_path / "split", episodes=32, checkpoint_every=8, resume=True)
    meta, tensors = read_file(tmp_path / "split" / CHECKPOINT)
    assert meta["trainer"]["episodes_done"] == 32
    assert len(tensors["history/return"]) == 32
    _, straight_tensors = read_file(tmp_path / "straight" / CHECKPOINT)
    # Same rng, optimizer moments and episodes: the resumed run is the uninterrupted one.
    np.testing.assert_allclose(tensors["history/return"], straight_tensors["history/return"])
    # ... its update diagnostics too, bit for bit (and history.csv byte for byte).
    assert sorted(k for k in tensors if k.startswith("history/")) == \
        sorted(k for k in straight_tensors if k.startswith("history/"))
    for k in ("update", "loss", "value_loss", "entropy", "grad_norm", "value_grad_norm", "lr", "approx_kl"):
        assert np.isfinite(tensors[f"history/{k}"]).all(), k
        np.testing.assert_array_equal(tensors[f"history/{k}"], straight_tensors[f"history/{k}"], err_msg=k)
    assert (tmp_path / "split" / "history.csv").read_bytes() == (tmp_path / "straight" / "history.csv").read_bytes()
    _, a = read_file(straight)
    _, b = read_file(resumed)
    for k in a:
        np.testing.assert_allclose(a[k], b[k], rtol=1e-6, atol=1e-7)
    # A different split cannot be resumed, nor other environment settings (lambda_range may change).
    with pytest.raises(ValueError, match="split_seed"):
        _train(tmp_path_factory, tmp_path / "split", episodes=40, resume=True, split_seed=1)
    with pytest.raises(ValueError, match="failed_pick_cost: 2.0 -> 3.0"):
        _train(tmp_path_factory, tmp_path / "split", episodes=40, resume=True, failed_pick_cost=3.0)
    _train(tmp_path_factory, tmp_path / "split", episodes=40, resume=True, lambda_range=(0.1, 0.9))


def test_ctrl_c_keeps_the_last_completed_round(tmp_path_factory, tmp_path, monkeypatch):
    calls = {"n": 0}
    real = training.play_episode

    def interrupting(*args, **kw):
        calls["n"] += 1
        if calls["n"] == 20:  # in the third round of 8 episodes
            os.kill(os.getpid(), signal.SIGINT)
        return real(*args, **kw)

    monkeypatch.setattr(training, "play_episode", interrupting)
    out = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        _train(tmp_path_factory, out, episodes=64, checkpoint_every=100)
    meta, _ = read_file(out / CHECKPOINT)
    assert meta["trainer"]["episodes_done"] == 16
    policy_meta, _ = read_file(out / "policy.safetensors")
    assert policy_meta["extra"]["interrupted"] is True and policy_meta["extra"]["episodes"] == 16
    assert (out / CURVE).exists()
    monkeypatch.setattr(training, "play_episode", real)
    _train(tmp_path_factory, out, episodes=24, resume=True)
    meta, _ = read_file(out / CHECKPOINT)
    assert meta["trainer"]["episodes_done"] == 24


def test_pg_learns_a_clear_best_action(tmp_path_factory, tmp_path):
    """Nearly exact initial poses and expensive refinements: picking at once is clearly best.
    The trained (greedy) policy must beat the random agent by a wide margin."""
    costs = {"icp_point_to_plane": 0.3, "depth_refine": 0.3, "simulated_init": 0.3}
    setting = dict(lambda_range=(0.0, 0.05), cost_table=costs, max_ops=5)
    path = _train(tmp_path_factory, tmp_path / "pg", episodes=160, seed=1, checkpoint_every=1000,
                  agent_kwargs={"batch_episodes": 8, "lr": 0.05}, **setting)
    env = make_env(tmp_path_factory, time_mode="cost_table", cost_table=costs, max_ops=5, lambda_range=(0.0, 0.05))
    episodes = [{"episode": i % len(env.source), "lambda": 0.03, "episode_seed": 500 + i} for i in range(20)]

    def mean_return(agent) -> float:
        return float(np.mean([play_episode(env, agent, o, act_seed=k).ret for k, o in enumerate(episodes)]))

    untrained = make_agent("pg", env, seed=1)
    untrained.explore = True  # the policy training starts from, as it acts while training
    before, random_ret = mean_return(untrained), mean_return(make_agent("random", env, seed=1))
    after = mean_return(load_agent(path, env))
    best = -(0.5 + 0.008)  # one successful pick
    # by a wide margin: random and the untrained policy spend 0.4-0.6 s more per episode (the
    # final-pick rule saves them the truncation, so the gap is not a factor of 2 any more)
    assert after > random_ret + 0.3 and after > before + 0.3, (after, random_ret, before)
    assert after == pytest.approx(best, abs=0.1)
