"""The figures an agent's update reports (pg: gradient norms before clipping, the learning rate
used, the approximate KL of its step) and how training records them per episode
(learning/training_history.py). The run's history.csv and curve: test_training.py."""
from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from perception_config.agents import make_agent
from perception_config.learning.learning_curve import has_diagnostics, per_update
from perception_config.learning.training_history import (
    HISTORY_FIELDS,
    UPDATE_FIELDS,
    columns,
    history_arrays,
    history_from_tensors,
    record_round,
    updates_done,
)
from perception_config.rl.episode_loop import play_episode
from rl_helpers import make_env


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    """An env and 4 episodes of the random agent (pg learns from any trajectories)."""
    env = make_env(tmp_path_factory, max_ops=5)
    player = make_agent("random", env, seed=0)
    trajs = [play_episode(env, player, {"episode": i, "lambda": 0.5, "episode_seed": 7 + i}, act_seed=i)
             for i in range(4)]
    return env, trajs


def _grad_norm(net: torch.nn.Module) -> float:
    return float(torch.sqrt(sum((p.grad.double() ** 2).sum() for p in net.parameters())))


def test_pg_reports_the_gradient_norm_before_clipping_lr_and_approx_kl(batch):
    env, trajs = batch
    clipped = make_agent("pg", env, seed=0, batch_episodes=4, grad_clip=0.01)
    free = make_agent("pg", env, seed=0, batch_episodes=4, grad_clip=1e6)
    before = copy.deepcopy(clipped)
    a, b = clipped.update([trajs]), free.update([trajs])
    assert list(a) == ["loss", "value_loss", "entropy", "grad_norm", "value_grad_norm", "lr", "approx_kl"]
    # The same gradient (the clip only scales it): both report its norm, the clipped one's gradient is 0.01 long.
    assert a["grad_norm"] == b["grad_norm"] > 0.01
    assert _grad_norm(free.policy) == pytest.approx(b["grad_norm"], rel=1e-5)
    assert _grad_norm(clipped.policy) == pytest.approx(0.01, rel=1e-3)
    assert _grad_norm(free.value) == pytest.approx(b["value_grad_norm"], rel=1e-5)
    assert 0 <= a["entropy"] <= np.log(env.action_space.n) and a["lr"] == 0.02
    # approx_kl: CleanRL's mean[(ratio - 1) - log ratio] over the batch's states and taken actions,
    # recomputed here from the policy's probabilities before and after the step.
    ratios = []
    for t in trajs:
        for obs, action, allowed in zip(t.obs, t.actions, t.allowed_actions(env.action_space.n)):
            ratios.append(clipped.probabilities(obs, allowed)[action] / before.probabilities(obs, allowed)[action])
    r = np.array(ratios)
    assert a["approx_kl"] == pytest.approx(np.mean((r - 1) - np.log(r)), rel=1e-3, abs=1e-8)
    assert a["approx_kl"] > 0  # the step moved the policy


def test_pg_reports_the_decayed_lr_and_no_value_gradient_with_the_mean_baseline(batch):
    env, trajs = batch
    halving = make_agent("pg", env, seed=0, batch_episodes=4, lr_half_life=4.0)
    assert [halving.update([trajs])["lr"] for _ in range(3)] == pytest.approx([0.02, 0.01, 0.005])
    figures = make_agent("pg", env, seed=0, batch_episodes=4, baseline="mean").update([trajs])
    assert "value_grad_norm" not in figures and figures["grad_norm"] > 0
    assert make_agent("pg", env, seed=0).update([[]]) == {}  # nothing to learn from: no figures


def test_history_records_each_updates_figures_and_resumes_old_checkpoints(batch):
    _, trajs = batch
    # A checkpoint from before the update columns: its episodes get nan there.
    old = {f"history/{k}": np.arange(3.0) for k in HISTORY_FIELDS}
    history = history_from_tensors(old)
    assert np.isnan(history["update"]).all() and len(history["update"]) == 3 and updates_done(history) == 0
    assert record_round(history, [trajs[:2]], {"xi": 0.5}, 1) == 2
    assert record_round(history, [trajs[2:3], trajs[3:]], {"xi": 0.25, "memory_keys": 4.0}, 2) == 2
    arrays = history_arrays(history)
    assert list(arrays) == [*HISTORY_FIELDS, "update", "memory_keys", "xi"]  # UPDATE_FIELDS the agent lacks: none
    assert columns(arrays) == [*HISTORY_FIELDS, *UPDATE_FIELDS, "memory_keys", "xi"]
    np.testing.assert_array_equal(arrays["update"], [np.nan] * 3 + [1, 1, 2, 2])
    np.testing.assert_array_equal(arrays["xi"], [np.nan] * 3 + [0.5, 0.5, 0.25, 0.25])
    np.testing.assert_array_equal(arrays["memory_keys"], [np.nan] * 5 + [4, 4])  # first reported by update 2
    assert arrays["return"][3:].tolist() == [t.ret for t in trajs] and updates_done(history) == 2
    # The curve's per-update points: the last episode of each update; no pg figures, no fourth panel.
    x, xi = per_update(arrays, "xi")
    assert x.tolist() == [5.0, 7.0] and xi.tolist() == [0.5, 0.25] and not has_diagnostics(arrays)
    assert has_diagnostics({**arrays, "entropy": np.array([np.nan] * 5 + [1.0, 1.0])})
    with pytest.raises(ValueError, match="'steps'"):
        record_round(history, [trajs[:1]], {"steps": 1.0}, 3)


def test_pg_further_passes_use_the_clipped_ratio(batch):
    """update_epochs = 1 is the REINFORCE step, bit for bit; K = 4 takes the same first step, then
    three clipped passes on the same episodes: the policy moves further (a larger approx_kl), and
    the passes stop pushing an action once its ratio leaves [1 - clip, 1 + clip]."""
    env, trajs = batch
    one = make_agent("pg", env, seed=0, batch_episodes=4)
    same = make_agent("pg", env, seed=0, batch_episodes=4, update_epochs=1)
    four = make_agent("pg", env, seed=0, batch_episodes=4, update_epochs=4, clip=0.1)
    wide = make_agent("pg", env, seed=0, batch_episodes=4, update_epochs=4, clip=5.0)
    f1, f_same, f4, f_wide = (a.update([trajs]) for a in (one, same, four, wide))
    assert f1 == f_same and all(np.array_equal(one.tensors()[k], same.tensors()[k]) for k in one.tensors())
    assert f4["loss"] == f1["loss"] and f4["grad_norm"] == f1["grad_norm"]  # the first pass is the same step
    assert f1["approx_kl"] < f4["approx_kl"] < f_wide["approx_kl"]  # the clip bounds how far the passes go
    assert four.hparams()["update_epochs"] == 4 and four.hparams()["clip"] == 0.1
    for bad in ({"update_epochs": 0}, {"clip": 0.0}):
        with pytest.raises(ValueError, match="update_epochs|clip"):
            make_agent("pg", env, seed=0, **bad)


def test_generalised_advantages_span_td_to_monte_carlo(batch):
    env, trajs = batch
    agent = make_agent("pg", env, seed=0, gae_lambda=0.5)
    values = np.random.default_rng(0).normal(size=sum(t.steps for t in trajs))
    starts = np.cumsum([0] + [t.steps for t in trajs])

    def per_episode(adv):
        return [adv[a:b] for a, b in zip(starts[:-1], starts[1:])]

    agent.gae_lambda = 1.0  # Monte Carlo: the return to go minus the value
    for t, adv, v in zip(trajs, per_episode(agent._gae(trajs, values)), per_episode(values)):
        np.testing.assert_allclose(adv, np.cumsum(t.rewards[::-1])[::-1] - v, rtol=1e-12, atol=1e-12)
    agent.gae_lambda = 0.0  # one-step TD errors, V = 0 after the last step
    for t, adv, v in zip(trajs, per_episode(agent._gae(trajs, values)), per_episode(values)):
        np.testing.assert_allclose(adv, t.rewards + np.append(v[1:], 0.0) - v, rtol=1e-12, atol=1e-12)
    agent.gae_lambda = 0.5
    figures = agent.update([trajs])
    assert np.isfinite([figures["loss"], figures["value_loss"], figures["grad_norm"]]).all()
    with pytest.raises(ValueError, match="gae_lambda"):
        make_agent("pg", env, gae_lambda=0.5, baseline="mean")
