"""Agents: valid actions, policy files (round trip, mismatch, corruption), the oracle's bound."""
from __future__ import annotations

import itertools
import json

import numpy as np
import pytest

from perception_config.agents import AGENTS, EnvSpec, PolicyError, load_agent, make_agent, oracle_search, save_agent
from perception_config.agents.policy_io import read_file
from perception_config.rl.episode_loop import play_episode
from perception_config.rl.trajectory import returns_to_go
from rl_helpers import OTHER_PIPELINE, OTHER_SCORES_PIPELINE, make_env

# (episode index, lambda, episode seed) of the tiny dataset used by several tests.
EPISODES = [(i, lam, 100 + i) for i in range(0, 6, 2) for lam in (0.3, 0.8)]


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    return make_env(tmp_path_factory, max_ops=6)


def _options(i: int, lam: float, seed: int) -> dict:
    return {"episode": i, "lambda": lam, "episode_seed": seed}


def _agent(name: str, env, **kw):
    if name == "fixed":
        kw.setdefault("sequence", ["icp_coarse", "icp_fine", "pick"])
    if name == "es":
        kw.setdefault("population", 4)
    return make_agent(name, env, **kw)


@pytest.mark.parametrize("name", sorted(AGENTS))
def test_every_agent_acts_validly(env, name):
    agent = _agent(name, env, seed=3)
    for k, (i, lam, seed) in enumerate(EPISODES[:3]):
        traj = play_episode(env, agent, _options(i, lam, seed), act_seed=k)
        assert 1 <= traj.steps <= env.max_ops
        assert all(0 <= a < len(env.action_names) for a in traj.actions)
        assert traj.obs.shape == (traj.steps, len(env.observation_layout))
        assert np.all(traj.seconds > 0) and traj.time == pytest.approx(traj.seconds.sum())
        if traj.success:
            assert traj.names[-1] == "pick"
        else:
            assert traj.steps == env.max_ops  # only truncation ends an unsuccessful episode


def test_fixed_agent_sequence_restart_and_validation(env):
    spec = EnvSpec.from_env(env)
    agent = make_agent("fixed", spec, sequence=["icp_coarse", "icp_fine", "pick"], restart=1)
    names = [spec.action_names[agent.act(None, {"steps": t})] for t in range(7)]
    assert names == ["icp_coarse", "icp_fine", "pick", "icp_fine", "pick", "icp_fine", "pick"]
    agent = make_agent("fixed", spec, sequence=["icp_coarse", "pick"], after="pick")
    assert ([spec.action_names[agent.act(None, {"steps": t})] for t in range(4)]
            == ["icp_coarse", "pick", "pick", "pick"])
    with pytest.raises(ValueError, match="icp_turbo.*environment's actions are"):
        make_agent("fixed", spec, sequence=["icp_coarse", "icp_turbo", "pick"])
    with pytest.raises(ValueError, match="restart"):
        make_agent("fixed", spec, sequence=["pick"], restart=1)


def test_simple_agent_memory_is_a_running_average(env):
    spec = EnvSpec.from_env(env)
    agent = make_agent("simple", spec, xi_start=0.0, xi_min=0.0)
    trajs = [play_episode(env, _agent("fixed", env), _options(i, lam, s)) for i, lam, s in EPISODES[:4]]
    agent.update([trajs])
    # The memory at the empty prefix for the first action (icp_coarse) averages all returns.
    a0 = spec.action_names.index("icp_coarse")
    assert agent.n[()][a0] == 4
    assert agent.q[()][a0] == pytest.approx(np.mean([t.ret for t in trajs]))
    g1 = [returns_to_go(t.rewards)[1] for t in trajs]
    assert agent.q[(a0,)][spec.action_names.index("icp_fine")] == pytest.approx(np.mean(g1))
    # Greedy with xi = 0 follows the remembered sequence.
    agent.begin_episode(0)
    assert agent.act(trajs[0].obs[0], {"steps": 0}) == a0


def _actions_on(agent, observations: list[np.ndarray], seed: int = 11) -> list[int]:
    agent.begin_episode(seed)
    return [agent.act(o, {"steps": t}) for t, o in enumerate(observations)]


@pytest.mark.parametrize("name", ["random", "fixed", "simple", "pg", "es"])
def test_save_load_round_trip_gives_identical_actions(env, tmp_path, name):
    agent = _agent(name, env, seed=5)
    trajs = [play_episode(env, agent, _options(i, lam, s), act_seed=j) for j, (i, lam, s) in enumerate(EPISODES[:4])]
    if name in ("simple", "pg"):
        agent.update([trajs])  # a trained state, not the initial one
    if name == "es":
        agent.actors()
        agent.update([trajs[:1], trajs[1:2], trajs[2:3], trajs[3:4]])
    observations = [o for t in trajs for o in t.obs]
    path = save_agent(agent, tmp_path / f"{name}.policy")
    loaded = load_agent(path, env, explore=True)
    assert type(loaded) is type(agent) and loaded.hparams() == agent.hparams()
    assert _actions_on(loaded, observations) == _actions_on(agent, observations)
    for explore in (False,):  # greedy evaluation too
        agent.explore = loaded.explore = explore
        assert _actions_on(loaded, observations) == _actions_on(agent, observations)
    for k, v in agent.tensors().items():
        np.testing.assert_array_equal(loaded.tensors()[k], v)


def test_weights_are_safetensors_and_tables_are_json(env, tmp_path):
    pg_path = save_agent(_agent("pg", env), tmp_path / "pg.bin")
    assert pg_path.read_bytes()[8:9] == b"{"  # safetensors: 8-byte header length, JSON header
    meta, tensors = read_file(pg_path)
    assert meta["agent"] == "pg" and meta["env"]["action_names"] == list(env.action_names)
    assert meta["env"]["observation_layout"] == list(env.observation_layout)
    assert meta["env"]["actions"] == json.loads(json.dumps(env.pipeline.describe()["actions"]))
    assert {"policy.fc1.weight", "policy.fc2.weight"} <= set(tensors)
    simple_path = save_agent(_agent("simple", env), tmp_path / "simple.json")
    assert json.loads(simple_path.read_text())["agent"] == "simple"
    assert not list(tmp_path.glob(".*tmp"))  # atomic writes leave no temporaries


def test_mismatched_action_set_is_a_clear_error(env, tmp_path_factory, tmp_path):
    path = save_agent(_agent("pg", env), tmp_path / "pg.safetensors")
    other = make_env(tmp_path_factory, OTHER_PIPELINE, "other.yaml")
    with pytest.raises(PolicyError, match=r"action set differs.*depth_refine.*icp_finest") as exc:
        load_agent(path, other)
    assert str(path) in str(exc.value)
    scores = make_env(tmp_path_factory, OTHER_SCORES_PIPELINE, "other_scores.yaml")
    with pytest.raises(PolicyError, match=r"observation layout differs.*psi_c"):
        load_agent(path, scores)
    json_path = save_agent(_agent("simple", env), tmp_path / "simple.json")
    with pytest.raises(PolicyError, match="action set differs"):
        load_agent(json_path, other)


def test_same_names_other_parameters_is_a_clear_error(env, tmp_path_factory, tmp_path):
    from rl_helpers import PIPELINE

    path = save_agent(_agent("pg", env), tmp_path / "pg.safetensors")
    changed = make_env(tmp_path_factory, PIPELINE.replace("final_distance: 0.003", "final_distance: 0.002"),
                       "changed.yaml")
    with pytest.raises(PolicyError, match="icp_fine.*0.003.*0.002"):
        load_agent(path, changed)



def test_a_parameter_a_block_gained_since_is_taken_at_its_default(env, tmp_path):
    from perception_config.agents.policy_io import check_compatible

    meta, _ = read_file(save_agent(_agent("pg", env), tmp_path / "pg.safetensors"))
    pick = next(a for a in meta["env"]["actions"] if a["block"] == "simulated_pick")
    assert pick["params"].pop("symmetries") == "declared"  # as saved before simulated_pick had it
    check_compatible(meta, EnvSpec.from_env(env))
    pick["params"]["symmetries"] = "derived"  # a policy that ran with another value does not fit
    with pytest.raises(PolicyError, match="pick.*derived.*declared"):
        check_compatible(meta, EnvSpec.from_env(env))

def test_corrupt_policy_file_is_a_clear_error(env, tmp_path):
    good = save_agent(_agent("pg", env), tmp_path / "pg.safetensors").read_bytes()
    cases = {
        "truncated.safetensors": good[: len(good) // 2],
        "garbage.safetensors": bytes(range(256)) * 4,
        "empty.safetensors": b"",
        "broken.json": b'{"format": "perception_config.policy", "agent": ',
        "other.json": b'{"hello": "world"}',
    }
    for name, data in cases.items():
        path = tmp_path / name
        path.write_bytes(data)
        with pytest.raises(PolicyError, match=str(path).replace(".", r"\.")):
            load_agent(path, env)
    # A file whose tensors do not fit the network it names.
    meta, tensors = read_file(tmp_path / "pg.safetensors")
    from perception_config.agents.policy_io import write_file

    tensors["policy.fc1.weight"] = tensors["policy.fc1.weight"][:, :3]
    bad = write_file(tmp_path / "bad_shapes.safetensors",
                     {k: v for k, v in meta.items() if k not in ("format", "version")}, tensors)
    with pytest.raises(PolicyError, match="bad_shapes.*corrupt"):
        load_agent(bad, env)
    with pytest.raises(PolicyError, match="does not exist"):
        load_agent(tmp_path / "missing.safetensors", env)


def test_oracle_is_a_lower_bound_for_every_agent(env):
    agents = {n: _agent(n, env, seed=1) for n in ("random", "fixed", "simple", "pg", "es")}
    oracle = make_agent("oracle", env)
    for j, (i, lam, seed) in enumerate(EPISODES):
        opt = play_episode(env, oracle, _options(i, lam, seed))
        res = oracle.last_result
        assert res.found and res.exact and opt.success
        assert opt.time == pytest.approx(res.seconds)  # cost-table replay is exact
        for name, agent in agents.items():
            traj = play_episode(env, agent, _options(i, lam, seed), act_seed=j)
            if traj.success:
                assert opt.time <= traj.time + 1e-9, (name, i, lam, traj.names, res.actions)
            assert opt.ret >= traj.ret - 1e-9


def test_oracle_finds_the_brute_force_optimum(tmp_path_factory):
    """Every sequence of up to 3 actions, replayed from reset: the oracle's is the cheapest."""
    e = make_env(tmp_path_factory, max_ops=3)
    n = len(e.action_names)
    for i, lam, seed in [(0, 0.7, 2)]:  # the optimum takes 3 actions (two refinements, then pick)
        options = _options(i, lam, seed)
        best = np.inf
        for length in (1, 2, 3):
            for seq in itertools.product(range(n), repeat=length):
                e.reset(options=options)
                total, done = 0.0, False
                for k, a in enumerate(seq):
                    _, _, terminated, _, info = e.step(a)
                    total += info["seconds"]
                    if terminated:
                        done = k == length - 1  # a prefix already succeeded: counted on its own
                        break
                if done:
                    best = min(best, total)
        e.reset(options=options)
        before = e.ops.snapshot()
        res = oracle_search(e)
        assert e.ops.snapshot()[0] == before[0]  # the search leaves the episode as it was
        assert np.isfinite(best) and res.found and res.exact
        assert res.seconds == pytest.approx(best)
        assert res.evaluations < n * (n**3 - 1) // (n - 1)  # pruning: fewer calls than the full tree


def test_play_episode_stops_when_told_between_actions(env):
    """`stop` (the configurator's deadline) is asked before each action: the episode ends there,
    marked stopped, with the actions played so far."""
    full = play_episode(env, _agent("fixed", env), _options(0, 0.8, 100))
    asked = []

    def stop() -> bool:
        asked.append(1)
        return len(asked) > 2

    traj = play_episode(env, _agent("fixed", env), _options(0, 0.8, 100), stop=stop)
    assert traj.stopped and not full.stopped and full.steps > 2
    assert traj.steps == 2 and traj.names == full.names[:2] and not traj.success
    assert play_episode(env, _agent("fixed", env), _options(0, 0.8, 100), stop=lambda: True).steps == 0
