"""pg as a residual on a base sequence: untrained it plays the base exactly; the update sees the
base's proposals the acting saw; a policy with a base saves and loads; training searches the
base (base=best_static) on the training episodes, validates the untrained residual and records
the search."""
from __future__ import annotations

import numpy as np
import pytest

from perception_config.agents import make_agent
from perception_config.agents.base import EnvSpec
from perception_config.rl.episode_loop import play_episode
from rl_helpers import make_env, pipeline_file, tiny_dataset

BASE = ["icp_coarse", "pick", "regenerate"]


def _episodes(n: int) -> list[dict]:
    return [{"episode": i % 4, "lambda": 0.3 + 0.1 * (i % 5), "episode_seed": 100 + i} for i in range(n)]


def test_an_untrained_residual_plays_its_base_exactly(tmp_path_factory):
    env = make_env(tmp_path_factory)
    spec = EnvSpec.from_env(env)
    pg = make_agent("pg", spec, base=BASE, seed=5)
    pg.explore = False
    fixed = make_agent("fixed", spec, sequence=BASE)
    plain = make_agent("pg", spec, seed=5)
    plain.explore = False
    differs_from_plain = 0
    for k, options in enumerate(_episodes(6)):
        a = play_episode(env, pg, options=options, act_seed=k)
        b = play_episode(env, fixed, options=options, act_seed=k)
        c = play_episode(env, plain, options=options, act_seed=k)
        assert a.names == b.names and a.cost == b.cost, (a.names, b.names)
        differs_from_plain += a.names != c.names
    assert differs_from_plain, "the plain network plays the base too: the test shows nothing"


def test_the_update_recomputes_the_proposals_the_acting_saw(tmp_path_factory):
    env = make_env(tmp_path_factory)
    spec = EnvSpec.from_env(env)
    pg = make_agent("pg", spec, base=BASE, base_bonus=1.0, seed=1)
    pg.explore = True
    seen: list[np.ndarray] = []
    act = pg.act

    def recording_act(obs, info):
        a = act(obs, info)
        onehot = np.zeros(spec.n_actions, np.float32)
        if pg._base_next is not None:
            onehot[pg._base_next[0]] = 1
        seen.append(onehot)
        return a

    pg.act = recording_act
    trajs = [play_episode(env, pg, options=o, act_seed=k) for k, o in enumerate(_episodes(8))]
    recomputed = np.concatenate([pg.base_actions(t.actions, t.allowed_actions(spec.n_actions)) for t in trajs])
    np.testing.assert_array_equal(recomputed, np.stack(seen))
    deviated = sum(any(n != BASE[0] for n in t.names[:1]) for t in trajs)
    assert deviated, "exploration never left the base (bonus 1): nothing was learned from"
    figures = pg.update([trajs])
    assert np.isfinite(figures["loss"]) and figures["grad_norm"] > 0


def test_a_policy_with_a_base_saves_loads_and_refuses_an_unresolved_base(tmp_path_factory, tmp_path):
    from perception_config.agents.policy_io import load_agent, save_agent

    env = make_env(tmp_path_factory)
    spec = EnvSpec.from_env(env)
    pg = make_agent("pg", spec, base=BASE, seed=2)
    path = save_agent(pg, tmp_path / "policy.safetensors", {})
    back = load_agent(path, env)
    assert back.base == BASE and back.base_bonus == pg.base_bonus
    obs, info = env.reset(options=_episodes(1)[0])
    back.explore = pg.explore = False
    assert back.act(obs, info) == pg.act(obs, info) == spec.action_names.index(BASE[0])
    with pytest.raises(ValueError, match="training searches it"):
        make_agent("pg", spec, base="best_static")
    with pytest.raises(ValueError, match="unknown action"):
        make_agent("pg", spec, base=["icp_coarse", "teleport"])


def test_training_searches_the_base_and_validates_it_before_learning(tmp_path_factory, tmp_path, monkeypatch):
    import perception_config.learning.base_search as base_search
    from perception_config.learning.training import train

    monkeypatch.setattr(base_search, "DEFAULT_BASE_EPISODES", 6)  # a small search: the tiny dataset
    data = tiny_dataset(tmp_path_factory)
    pipe = pipeline_file(tmp_path_factory)
    policy = train(data, "pg", tmp_path / "run", 16, pipeline=pipe, progress=False, store_episodes=False,
                   validation_fraction=0.3, validate_every=8, agent_kwargs={"base": "best_static", "batch_episodes": 8},
                   test_fraction=0.25)
    from perception_config.agents.policy_io import read_file

    meta, _ = read_file(policy)
    found = meta["extra"]["base_search"]
    assert found["episodes"] == 6 and found["max_length"] == 3
    assert meta["hparams"]["base"] == found["sequence"] and "pick" in found["sequence"]
    episodes = [int(r["episode"]) for r in _validation_rows(policy.parent)]
    assert episodes[0] == 0 and episodes[-1] >= 16, episodes  # the untrained residual (its base) is a candidate


def _validation_rows(run):
    import csv

    with open(run / "validation.csv", newline="") as f:
        return list(csv.DictReader(f))
