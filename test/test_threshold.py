"""The threshold rule (agents/threshold.py): its decisions, the rules searched, its search costs
against its played costs, and the warm start that teaches the cheapest rule."""
from __future__ import annotations

import numpy as np
import pytest

from perception_config.agents import EnvSpec, make_agent
from perception_config.agents.best_static import search_players
from perception_config.agents.hparams import check_hparams
from perception_config.agents.policy_io import read_file
from perception_config.agents.threshold import THRESHOLDS, ThresholdAgent, threshold_rules
from perception_config.learning import warm_start as ws
from perception_config.learning.training import train
from perception_config.rl.episode_loop import play_episode
from perception_config.rl.settings import EnvSettings
from rl_helpers import make_env, pipeline_file, tiny_dataset

LAYOUT = ("score:psi_d", "score:pick_success", "missing:psi_d", "missing:pick_success", "progress:step")
SPEC = EnvSpec(("icp", "refine", "regenerate", "pick"), ("refinement", "refinement", "generation", "pick"),
               LAYOUT, 6)


def _obs(p, missing=0.0):
    return np.array([0.5, p, 0.0, missing, 0.0], np.float32)


def _mask(*allowed):
    return {"action_mask": np.array([int(a in allowed) for a in range(4)], np.int8)}


def test_the_rule_picks_above_its_threshold_and_loops_below_it():
    rule = ThresholdAgent(SPEC, "pick_success", 0.8, ["icp", "regenerate"])
    rule.begin_episode(0)
    assert rule.act(_obs(0.9), {"steps": 0}) == 3  # at once when the score clears it
    assert [rule.act(_obs(0.3), {}) for _ in range(3)] == [0, 2, 0]  # the loop, in turn
    assert rule.act(_obs(0.8), {}) == 3  # at the threshold: pick
    assert rule.act(_obs(0.95, missing=1.0), {}) == 2  # a missing score is 0: the loop goes on
    # masked loop actions are skipped where they come; none left: pick; pick masked too: the
    # pipeline's first action that can run
    assert rule.act(_obs(0.3), _mask(1, 2, 3)) == 2
    assert rule.act(_obs(0.3), _mask(1, 3)) == 3
    assert rule.act(_obs(0.9), _mask(1, 2)) == 2  # above the threshold, the pick masked: the loop
    assert rule.act(_obs(0.3), _mask(1)) == 1
    rule.act(_obs(0.3), {"steps": 0})  # a new episode restarts the loop
    assert rule.act(_obs(0.3), {}) == 2
    # rebuilt from its hyper-parameters (as from a policy file), it decides the same
    hp = rule.hparams()
    check_hparams("threshold", ThresholdAgent.HPARAM_BOUNDS, hp)
    again = make_agent("threshold", SPEC, **hp)
    assert again.hparams() == hp and again.act(_obs(0.3), {"steps": 0}) == 0


@pytest.mark.parametrize("kw, message", [
    ({"score": "psi_c"}, "scores no 'psi_c'"),
    ({"loop": ["pick"]}, "non-pick actions"),
    ({"loop": ["icp", "polish"]}, "non-pick actions"),
    ({"loop": []}, "non-pick actions"),
    ({"threshold": 1.5}, "threshold must be in"),
])
def test_a_bad_rule_is_refused_naming_what_is_wrong(kw, message):
    with pytest.raises(ValueError, match=message):
        ThresholdAgent(SPEC, **{"score": "pick_success", "loop": ["icp"], **kw})
    with pytest.raises(ValueError, match="threshold"):
        check_hparams("threshold", ThresholdAgent.HPARAM_BOUNDS, {"threshold": -0.1})


def test_the_rules_searched():
    rules = threshold_rules(SPEC)
    # the pick-success score only, when the pipeline has it; loops of 1..2 of the 3 non-pick
    # actions without (a, a): 3 + 6
    assert {r.score for r in rules} == {"pick_success"}
    loops = {tuple(r.loop) for r in rules}
    assert len(loops) == 9 and ("icp", "icp") not in loops and ("regenerate", "icp") in loops
    assert len(rules) == 9 * len(THRESHOLDS)
    # without it: each of the pipeline's scores (a rule's own default is the first)
    plain = EnvSpec(SPEC.action_names, SPEC.action_kinds, ("score:psi_d", "score:psi_c", "missing:psi_d",
                                                           "missing:psi_c"), 6)
    searched = threshold_rules(plain)
    assert [r.score for r in searched[::9 * len(THRESHOLDS)]] == ["psi_d", "psi_c"] and len(searched) == 2 * len(rules)
    assert ThresholdAgent(plain, loop=["icp"]).score == "psi_d"


def test_search_cost_is_the_rules_played_cost_bit_for_bit(tmp_path_factory):
    env = make_env(tmp_path_factory, max_ops=5)
    spec = EnvSpec.from_env(env)
    rules = threshold_rules(spec, thresholds=(0.3, 0.9), max_loop=1)
    plan = ws.demonstration_plan(list(range(len(env.source.episodes))), 3, (0.3, 1.0), seed=2)
    costs, _ = search_players(env, rules, plan)
    assert costs.shape == (3, len(rules)) and np.isfinite(costs).all()
    for j in (0, len(rules) - 1):
        rule = make_agent("threshold", spec, **rules[j].hparams())
        played = [play_episode(env, rule, options, seed).cost for options, seed in plan]
        assert played == list(costs[:, j])
    # the thresholds matter: a rule that picks at once costs otherwise than one that refines first
    assert len({tuple(np.round(costs[:, j], 9)) for j in range(len(rules))}) > 1


def test_a_run_warm_started_by_the_threshold_teacher_records_its_rule(tmp_path_factory):
    settings = EnvSettings(time_mode="cost_table", lambda_range=(0.2, 0.8), max_ops=5)
    out = tmp_path_factory.mktemp("threshold") / "run"
    policy = train(tiny_dataset(tmp_path_factory), "pg", out, 8, settings=settings,
                   pipeline=pipeline_file(tmp_path_factory), workers=1, progress=False, seed=3,
                   validation_fraction=0.34, validate_every=8,
                   agent_kwargs={"batch_episodes": 8, "warm_start": "threshold", "warm_start_episodes": 4,
                                 "imitation_epochs": 50})
    report = read_file(policy)[0]["extra"]["warm_start"]
    assert report["teacher"] == "threshold" and report["episodes_searched"] == 4
    rule = make_agent("threshold", EnvSpec.from_env(make_env(tmp_path_factory, max_ops=5)), **report["rule"])
    assert report["sequences_taught"] == {rule.describe(): 4} and report["rules"] > len(THRESHOLDS)
    assert np.isfinite(report["rule_cost"]) and 0.0 <= report["imitation_accuracy"] <= 1.0
