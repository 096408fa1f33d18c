"""Warm start (learning/warm_start.py, PolicyGradientAgent.imitate): the teachers choose from the
search's costs, the policy learns their actions, and a warm-started run records what it
imitated, lets validation judge the imitating policy, and trains on the episodes of a run
without a warm start."""
from __future__ import annotations

import csv
import sqlite3

import numpy as np
import pytest

from perception_config.agents import EnvSpec, make_agent
from perception_config.agents.best_static import search_costs, static_sequences
from perception_config.agents.fixed import FixedAgent
from perception_config.agents.policy_io import read_file
from perception_config.learning import warm_start as ws
from perception_config.learning.training import VALIDATION_CSV, train
from perception_config.rl.settings import EnvSettings
from perception_config.rl.trajectory import Trajectory
from rl_helpers import make_env, pipeline_file, tiny_dataset

FAST = EnvSettings(time_mode="cost_table", lambda_range=(0.2, 0.8), max_ops=5)


def _traj(obs, actions, masks=None):
    n = len(actions)
    return Trajectory(obs=np.asarray(obs, np.float32), actions=np.asarray(actions, np.int64),
                      rewards=-np.ones(n), seconds=np.ones(n), success=True, noise_lambda=0.5, episode_index=0,
                      masks=None if masks is None else np.asarray(masks, np.int8))


def test_imitation_learns_the_teachers_actions_and_leaves_out_masked_ones():
    spec = EnvSpec(("a", "b", "pick"), ("refinement", "refinement", "pick"), ("x", "y"), 5)
    agent = make_agent("pg", spec, seed=1, imitation_epochs=200, imitation_smoothing=0.1)
    # The teacher takes b when x is high, pick when y is high, a otherwise.
    demos = [_traj([[1, 0], [0, 1]], [1, 2]), _traj([[0, 0], [0, 1]], [0, 2]),
             # a step the mask forbade (pick masked): it is no demonstration
             _traj([[0.5, 0.5]], [2], masks=[[1, 1, 0]])]
    figures = agent.imitate(demos)
    assert figures["imitation_steps"] == 4 and figures["imitation_accuracy"] == 1.0
    agent.explore = False
    assert [agent.act(np.array(o, np.float32), {}) for o in ([1, 0], [0, 0], [0, 1])] == [1, 0, 2]
    # smoothing keeps some probability on the other allowed actions (the policy still explores)
    p = agent.probabilities(np.array([1, 0], np.float32))
    assert 0.5 < p[1] < 0.99 and p.min() > 0.005
    with pytest.raises(ValueError, match="every demonstrated action was masked"):
        agent.imitate([_traj([[0.5, 0.5]], [2], masks=[[1, 1, 0]])])
    with pytest.raises(ValueError, match="warm_start must be one of"):
        make_agent("pg", spec, warm_start="expert")


def test_the_teachers_choose_from_the_search_costs():
    seqs = [("pick",), ("a", "pick"), ("b", "pick")]
    costs = np.array([[12.0, 0.5, 0.4],   # b then pick is cheapest here
                      [0.1, 0.3, 0.3],    # pick at once
                      [12.0, 13.0, 11.0]])  # nothing succeeds
    assert ws.teacher_sequences(seqs, costs, "hindsight", 10.0) == [("b", "pick"), ("pick",), None]
    # best_static: the lowest mean cost (a: 13.8 / 3 against b's 11.7 / 3), on every episode
    assert ws.teacher_sequences(seqs, costs, "best_static", 10.0) == [("b", "pick")] * 3
    with pytest.raises(ValueError, match="unknown teacher"):
        ws.teacher_sequences(seqs, costs, "human", 10.0)


def test_the_demonstrations_replay_the_searched_costs(tmp_path_factory):
    env = make_env(tmp_path_factory, max_ops=5)
    spec = EnvSpec.from_env(env)
    seqs = static_sequences(spec.action_names, spec.action_kinds, 2)
    plan = ws.demonstration_plan(list(range(len(env.source.episodes))), 4, (0.6, 1.2), seed=5)
    assert plan == ws.demonstration_plan(list(range(len(env.source.episodes))), 4, (0.6, 1.2), seed=5)
    costs, _ = search_costs(env, seqs, plan)
    chosen = ws.teacher_sequences(seqs, costs, "hindsight", 10.0)
    teachers = {c: FixedAgent(spec, list(c), after="repeat") for c in set(chosen) if c is not None}
    demos = ws._play(env, [teachers.get(c) for c in chosen], plan, None, None)
    kept = [k for k, c in enumerate(chosen) if c is not None]
    assert kept and len(demos) == len(kept)
    for k, t in zip(kept, demos):  # cost-table time: the replay is charged the search's cost, bit for bit
        assert t.cost == costs[k, seqs.index(chosen[k])] and t.success
        assert t.names[:len(chosen[k])] == list(chosen[k])[:t.steps]


def _run(tmp_path_factory, out, **agent):
    kw = {"batch_episodes": 8, "lr": 0.05, **agent}
    return train(tiny_dataset(tmp_path_factory), "pg", out, 16, settings=FAST, pipeline=pipeline_file(tmp_path_factory),
                 workers=1, progress=False, seed=3, validation_fraction=0.34, validate_every=8, agent_kwargs=kw)


def test_a_warm_started_run_records_its_teacher_and_validates_the_imitating_policy(tmp_path_factory):
    root = tmp_path_factory.mktemp("warm")
    warm = _run(tmp_path_factory, root / "warm", warm_start="hindsight", warm_start_episodes=6)
    cold = _run(tmp_path_factory, root / "cold")
    meta, _ = read_file(warm)
    report = meta["extra"]["warm_start"]
    assert report["teacher"] == "hindsight" and report["episodes_searched"] == 6
    assert 1 <= report["episodes_demonstrated"] <= 6 and report["demonstration_success"] == 1.0
    assert sum(report["sequences_taught"].values()) == report["episodes_demonstrated"]
    assert meta["hparams"]["warm_start"] == "hindsight" and "warm_start" not in read_file(cold)[0]["extra"]
    with open(warm.parent / VALIDATION_CSV) as f:
        assert [int(r["episode"]) for r in csv.DictReader(f)] == [0, 8, 16]
    with open(cold.parent / VALIDATION_CSV) as f:
        assert [int(r["episode"]) for r in csv.DictReader(f)] == [8, 16]

    def played(run):
        with sqlite3.connect(run.parent / "episodes.sqlite") as con:
            return con.execute("SELECT scene_id, im_id, noise_lambda, episode_seed FROM episodes "
                               "ORDER BY id").fetchall()
    assert played(warm) == played(cold)  # the demonstrations came from a stream of their own
    # Resumed further, the run keeps its report and does not search again.
    again = train(tiny_dataset(tmp_path_factory), "pg", warm.parent, 24, settings=FAST,
                  pipeline=pipeline_file(tmp_path_factory), workers=1, progress=False, seed=3,
                  validation_fraction=0.34, validate_every=8, resume=True)
    assert read_file(again)[0]["extra"]["warm_start"] == report
