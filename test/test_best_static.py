"""The best static pipeline (agents/best_static.py, learning/evaluation_best_static.py): the
prefix-shared search charges each sequence what its FixedAgent is charged, bit for bit; it chooses
the cheapest; evaluate() runs it on train images only and reports it."""
from __future__ import annotations

import json

import numpy as np
import pytest

from perception_config.agents import EnvSpec, make_agent
from perception_config.agents.best_static import (
    BestStaticAgent,
    SearchResult,
    search_costs,
    static_sequences,
)
from perception_config.agents.fixed import FixedAgent
from perception_config.agents.hparams import check_hparams
from perception_config.learning.evaluation import evaluate
from perception_config.learning.ray_workers import rebuild, snapshot
from perception_config.rl.episode_loop import acting_seed, play_episode
from perception_config.rl.operators import InProcessOperators
from rl_helpers import make_env, pipeline_file, tiny_dataset

MAX_OPS = 5
# (episode index, lambda, episode seed): high lambdas, so that first picks fail and sequences branch
EPISODES = [(0, 0.9, 11), (1, 1.3, 12), (2, 0.6, 13), (3, 1.6, 14)]
# every sequence of up to 2 actions with a pick, and a few longer ones
EXTRA = [("icp_coarse", "icp_fine", "pick"), ("regenerate", "pick", "depth_refine"), ("pick", "icp_fine", "pick")]


@pytest.fixture(scope="module")
def searched(tmp_path_factory):
    env = make_env(tmp_path_factory, max_ops=MAX_OPS)
    spec = EnvSpec.from_env(env)
    sequences = static_sequences(spec.action_names, spec.action_kinds, 2) + EXTRA
    episodes = [({"episode": i, "lambda": lam, "episode_seed": s}, acting_seed(s)) for i, lam, s in EPISODES]
    costs, images = search_costs(env, sequences, episodes)
    played = [[play_episode(env, FixedAgent(spec, list(seq), after="repeat"), options, act_seed)
               for seq in sequences] for options, act_seed in episodes]
    return {"env": env, "spec": spec, "sequences": sequences, "costs": costs, "images": images, "played": played}


def test_static_sequences_are_every_sequence_with_a_pick():
    names, kinds = ("a", "b", "pick"), ("refinement", "refinement", "pick")
    seqs = static_sequences(names, kinds, 2)
    assert seqs == [("pick",), ("a", "pick"), ("b", "pick"), ("pick", "a"), ("pick", "b"), ("pick", "pick")]
    assert len(static_sequences(names, kinds, 3)) == 3 ** 3 - 2 ** 3 + len(seqs)


def test_search_cost_is_the_fixed_agents_played_cost_bit_for_bit(searched):
    costs, played = searched["costs"], searched["played"]
    assert costs.shape == (len(EPISODES), len(searched["sequences"]))
    for k, trajs in enumerate(played):
        for j, traj in enumerate(trajs):
            assert costs[k, j] == traj.cost, (k, searched["sequences"][j], costs[k, j], traj.cost)
    # the case is not trivial: first picks failed, sequences branched and were truncated
    assert any(not t.first_pick_success for ts in played for t in ts)
    assert any(t.steps == MAX_OPS and not t.success for ts in played for t in ts)
    assert len({t.cost for t in played[1]}) > 3
    # the search left the env with its own operators, and its images are the episodes'
    assert type(searched["env"].ops) is InProcessOperators
    keys = [searched["env"].source.episodes[i] for i, _, _ in EPISODES]
    assert searched["images"] == [(k.scene_id, k.im_id) for k in keys]


def test_the_chosen_sequence_has_the_lowest_mean_cost(searched):
    sequences, played = searched["sequences"], searched["played"]
    brute = [float(np.mean([played[k][j].cost for k in range(len(EPISODES))])) for j in range(len(sequences))]
    result = SearchResult.from_costs(sequences, searched["costs"], 3, 0.0, searched["images"])
    best = min(range(len(sequences)), key=lambda j: (round(brute[j], 9), len(sequences[j]), sequences[j]))
    assert tuple(result.sequence) == sequences[best]
    assert result.mean_cost == pytest.approx(brute[best], abs=1e-12)
    assert all(result.mean_cost <= b + 1e-12 for b in brute)
    assert result.runner_up is not None and result.runner_up_cost >= result.mean_cost
    assert len(set(brute)) > 2  # the ranking had something to rank


def test_the_agent_plays_each_lambdas_sequence_and_survives_a_snapshot(searched):
    spec, env = searched["spec"], searched["env"]
    agent = BestStaticAgent(spec, {0.2: ["icp_coarse", "pick"], 1.0: ["regenerate", "pick"]}, seed=3)
    copy = rebuild(snapshot(agent), spec)
    assert copy.hparams() == agent.hparams() == {
        "sequences": {"0.2": ["icp_coarse", "pick"], "1.0": ["regenerate", "pick"]}, "seed": 3}
    check_hparams("best_static", BestStaticAgent.HPARAM_BOUNDS, agent.hparams())
    for lam, first in ((0.2, "icp_coarse"), (0.3, "icp_coarse"), (0.9, "regenerate"), (1.4, "regenerate")):
        traj = play_episode(env, copy, {"episode": 0, "lambda": lam, "episode_seed": 5}, 0)
        assert traj.names[0] == first
        fixed = play_episode(env, FixedAgent(spec, agent.sequence_for(lam)), {"episode": 0, "lambda": lam,
                                                                            "episode_seed": 5}, 0)
        assert traj.names == fixed.names and traj.cost == fixed.cost
    assert make_agent("best_static", spec).sequence_for(0.5) == list(spec.action_names)  # nothing searched


def test_evaluate_searches_train_images_only_and_reports_the_sequence(tmp_path_factory, tmp_path):
    out = tmp_path / "ev"
    agents = ["best_static", "best_static_single", "best_threshold", "random"]
    results = evaluate(tiny_dataset(tmp_path_factory), agents, [0.3, 1.2], out,
                       episodes_per_lambda=2, pipeline=pipeline_file(tmp_path_factory), time_mode="cost_table",
                       max_ops=4, include_baselines=False, progress=False, plots=False, store_episodes=False,
                       best_static_length=2, best_static_episodes=3)
    records = json.loads(results.read_text())
    meta = json.loads((out / "meta.json").read_text())
    assert meta["best_static"]["max_length"] == 2 and meta["best_static"]["episodes"] == 3
    test_images = {tuple(k) for k in meta["test_images"]}
    mine = [r for r in records if r["agent"] == "best_static"]
    assert [r["lambda"] for r in mine] == [0.3, 1.2] and all(r["kind"] == "best_static" for r in mine)
    episodes = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    for r in mine:
        assert r["sequence"] and "pick" in r["sequence"] and len(r["sequence"]) <= 2
        s = r["search"]
        assert s["episodes"] == 3 and s["sequences"] == 10 and s["max_length"] == 2 and s["seconds"] > 0
        assert s["runner_up_cost"] >= s["mean_cost"] and s["runner_up"] != r["sequence"]
        assert s["images"] and not {tuple(k) for k in s["images"]} & test_images  # never a test image
        played = [e for e in episodes if e["agent"] == "best_static" and e["lambda"] == r["lambda"]]
        assert played and all(e["actions"][0] == r["sequence"][0] for e in played)
    assert "random" in {r["agent"] for r in records}
    # best_static_single: one sequence for both lambdas, chosen on their 2 x 3 search episodes
    # together; no sequence beats each lambda's own choice there, so its mean is not below theirs.
    single = [r for r in records if r["agent"] == "best_static_single"]
    assert [r["lambda"] for r in single] == [0.3, 1.2] and all(r["kind"] == "best_static_single" for r in single)
    assert single[0]["sequence"] == single[1]["sequence"] and "pick" in single[0]["sequence"]
    s = single[0]["search"]
    assert s["episodes"] == 6 and s["sequences"] == 10 and not {tuple(k) for k in s["images"]} & test_images
    assert s["mean_cost"] >= np.mean([r["search"]["mean_cost"] for r in mine]) - 1e-9
    played = [e for e in episodes if e["agent"] == "best_static_single"]
    assert played and all(e["actions"][0] == single[0]["sequence"][0] for e in played)
    # best_threshold: one rule for both lambdas, from the same 2 x 3 train episodes; it is at
    # least as cheap there as the rules it beat, and it plays as it says
    rule = [r for r in records if r["agent"] == "best_threshold"]
    assert [r["lambda"] for r in rule] == [0.3, 1.2] and all(r["kind"] == "best_threshold" for r in rule)
    # the pipeline has no pick-success score: every one of its scores is searched
    from perception_config.agents.threshold import searched_scores

    scores = searched_scores(EnvSpec.from_env(make_env(tmp_path_factory)))
    assert len(scores) > 1 and rule[0]["rule"] == rule[1]["rule"]
    assert rule[0]["rule"].split(" >= ")[0] in {f"pick at {n}" for n in scores}
    s = rule[0]["search"]
    assert s["episodes"] == 6 and s["rules"] == 16 * 5 * len(scores) and s["runner_up_cost"] >= s["mean_cost"]
    assert s["images"] and not {tuple(k) for k in s["images"]} & test_images
    loop = rule[0]["rule"].split(", else ")[1].split(" > ")
    played = [e for e in episodes if e["agent"] == "best_threshold"]
    assert played and all(a in loop + ["pick"] for e in played for a in e["actions"][:-1])


def test_bad_options_give_clear_errors(tmp_path_factory, tmp_path, capsys):
    from perception_config.cli import main

    data, pipe = tiny_dataset(tmp_path_factory), pipeline_file(tmp_path_factory)
    kw = dict(pipeline=pipe, progress=False, plots=False)
    with pytest.raises(ValueError, match="best_static_length must be an integer >= 1, got 0"):
        evaluate(data, [], [0.5], tmp_path / "x", best_static_length=0, **kw)
    with pytest.raises(ValueError, match="best_static_episodes must be an integer >= 0, got -1"):
        evaluate(data, [], [0.5], tmp_path / "x", best_static_episodes=-1, **kw)
    with pytest.raises(ValueError, match="best_static.*give best_static_episodes > 0"):
        evaluate(data, ["best_static"], [0.5], tmp_path / "x", best_static_episodes=0, include_baselines=False, **kw)
    with pytest.raises(ValueError, match=r"max_length must be an integer in 1\.\.8, got 9"):
        static_sequences(("pick",), ("pick",), 9)
    with pytest.raises(ValueError, match="needs a pick action"):
        static_sequences(("a",), ("refinement",), 2)
    with pytest.raises(ValueError, match="sequences has a key 'x' that is no noise level"):
        check_hparams("best_static", BestStaticAgent.HPARAM_BOUNDS, {"sequences": {"x": ["pick"]}})
    spec = EnvSpec(("a", "pick"), ("refinement", "pick"), ("o",), 5)
    with pytest.raises(ValueError, match="unknown action"):
        BestStaticAgent(spec, {0.5: ["a", "jump"]})
    rc = main(["evaluate", "--dataset", str(data), "--out", str(tmp_path / "cli"), "--lambdas", "0.5",
               "--best-static-length", "0", "--quiet"])
    assert rc == 2 and "best_static_length must be an integer >= 1, got 0" in capsys.readouterr().err
