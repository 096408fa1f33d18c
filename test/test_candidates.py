"""Ranked candidates in the operator backend and the environment: next_candidate takes the last
generator call's candidates in turn, generator results are reused for the same call, and the
shipped cell pipeline holds only blocks that need no ground truth."""
from __future__ import annotations

import numpy as np
import pytest
import yaml

from perception_config.blocks.base import GROUND_TRUTH, Kind
from perception_config.blocks.pipeline import load_pipeline, pipeline_from_dict
from perception_config.core.geometry import rotation_angle
from perception_config.rl.operators import Episode, InProcessOperators

PIPELINE = """\
generator: {block: ppf}
actions:
  - {name: icp_fine, block: icp_point_to_plane, params: {max_correspondence_distance: 0.01, final_distance: 0.003}}
  - {name: next_candidate, block: next_candidate}
  - {name: global_registration, block: global_registration, params: {max_seconds: 1.0}}
  - {name: pick, block: simulated_pick}
scoring: [psi_d, icp_fitness]
"""


def same_pose(a, b) -> bool:
    return float(np.linalg.norm(a.t - b.t)) < 1e-9 and rotation_angle(a.R, b.R) < 1e-7


@pytest.fixture(scope="module")
def frames(synthetic_dataset):
    from perception_config.datasets.bop import BopDataset

    ds = BopDataset(synthetic_dataset, split="test")
    return [ds.load_frame(*key) for key in ds.image_keys()[:2]]


def episode(frame, obj, seed: int = 3) -> Episode:
    return Episode(frame=frame, model=obj.model, ground_truth=obj.gt, noise_lambda=0.0, seed=seed,
                   key=(0, 0, obj.obj_id))


def an_object_with_candidates(ops: InProcessOperators, frames, at_least: int = 2):
    """(frame, object, start outcome) of the first object whose generator call ranks >= `at_least`."""
    for frame in frames:
        for obj in frame.objects:
            out = ops.start(episode(frame, obj))
            if out.result.ok and len(out.result.candidates) >= at_least:
                return frame, obj, out
    pytest.skip("ppf ranked no object's candidates on the tiny dataset's frames")


def test_next_candidate_takes_the_ranked_candidates_in_turn_then_fails_and_keeps_the_pose(frames):
    ops = InProcessOperators(pipeline_from_dict(yaml.safe_load(PIPELINE)), time_bounded=False)
    frame, obj, out = an_object_with_candidates(ops, frames)
    ranked = out.result.candidates
    assert same_pose(out.pose, ranked[0][1])
    assert [c for c, _ in ops.candidates] == [c for c, _ in ranked[1:]]
    state = ops.snapshot()
    for conf, pose in ranked[1:]:
        step = ops.apply("next_candidate")
        assert step.result.ok and step.result.info["confidence"] == conf
        assert same_pose(step.pose, pose) and same_pose(ops.pose, pose)
        assert set(step.scores) == set(ops.pipeline.score_names)
    assert ops.candidates == []
    last = ops.pose
    step = ops.apply("next_candidate")
    assert not step.result.ok and "no candidate left" in step.result.reason
    assert ops.pose is last  # the hypothesis stays
    # snapshot/restore brings the waiting candidates back (the oracle's branching)
    ops.restore(state)
    assert [c for c, _ in ops.candidates] == [c for c, _ in ranked[1:]]
    assert same_pose(ops.apply("next_candidate").pose, ranked[1][1])
    # a refinement keeps the list; a new generator call replaces it
    ops.apply("icp_fine")
    assert len(ops.candidates) == len(ranked) - 2
    gen = ops.apply("global_registration")
    assert [c for c, _ in ops.candidates] == ([c for c, _ in gen.result.candidates[1:]] if gen.result.ok else [])


def test_a_refused_generator_call_leaves_all_its_candidates_waiting(frames):
    """A generator whose best candidate verifies below its threshold answers ok=False and sets no
    hypothesis, but what it ranked waits for next_candidate, the first too: the agent sees how
    many and how confident (a flat bracket verifies at 0.1-0.3 where it is right)."""
    strict = yaml.safe_load(PIPELINE)
    strict["generator"]["params"] = {"min_verification": 1.0}  # a verification score never reaches 1
    ops = InProcessOperators(pipeline_from_dict(strict), time_bounded=False)
    for frame in frames:
        for obj in frame.objects:
            out = ops.start(episode(frame, obj))
            if out.result.candidates:
                break
        else:
            continue
        break
    else:
        pytest.skip("ppf ranked no object's candidates on the tiny dataset's frames")
    ranked = out.result.candidates
    assert not out.result.ok and "min_verification" in out.result.reason and ops.pose is None
    assert [c for c, _ in ops.candidates] == [c for c, _ in ranked]
    step = ops.apply("next_candidate")
    assert step.result.ok and step.result.info["confidence"] == ranked[0][0] and same_pose(ops.pose, ranked[0][1])
    assert len(ops.candidates) == len(ranked) - 1


def test_next_candidate_draws_no_seed_so_later_generator_calls_are_unchanged(frames):
    """Taking a candidate searches nothing: the episode's seed stream is where it was, so a
    generator call after it draws what it would have drawn without it."""
    pipe = pipeline_from_dict(yaml.safe_load(PIPELINE))
    a, b = InProcessOperators(pipe, time_bounded=False), InProcessOperators(pipe, time_bounded=False)
    frame, obj, _ = an_object_with_candidates(a, frames)
    b.start(episode(frame, obj))
    a.apply("next_candidate")
    assert a.rng.bit_generator.state == b.rng.bit_generator.state


def test_generator_results_are_reused_for_the_same_call_with_the_time_they_took(frames):
    ops = InProcessOperators(pipeline_from_dict(yaml.safe_load(PIPELINE)), time_bounded=False)
    frame, obj, first = an_object_with_candidates(ops, frames, at_least=1)
    hits = ops.memo.hits
    again = ops.start(episode(frame, obj, seed=99))  # ppf uses no seed: the same call
    assert ops.memo.hits == hits + 1
    assert same_pose(again.pose, first.pose) and again.result.elapsed == first.result.elapsed
    assert [c for c, _ in ops.candidates] == [c for c, _ in first.result.candidates[1:]]
    fresh = InProcessOperators(ops.pipeline, time_bounded=False)
    fresh.start(episode(frame, obj))
    other = next(o for o in frame.objects if o.obj_id != obj.obj_id)
    fresh.start(episode(frame, other))  # another object: a new search
    assert fresh.memo.hits == 0
    # global_registration draws from the episode's seed: the same seed state reuses, another does not
    state = ops.snapshot()
    r1 = ops.apply("global_registration")
    ops.restore(state)
    r2 = ops.apply("global_registration")
    assert ops.memo.hits == hits + 2 and r1.result.elapsed == r2.result.elapsed
    r3 = ops.apply("global_registration")  # the stream moved on: a new draw, a new search
    assert ops.memo.hits == hits + 2 and r3.result.elapsed != r2.result.elapsed


def test_the_env_observes_the_waiting_candidates_only_in_pipelines_that_can_take_them(synthetic_dataset):
    from perception_config.rl.env import PerceptionConfigEnv

    env = PerceptionConfigEnv(synthetic_dataset, pipeline_from_dict(yaml.safe_load(PIPELINE)),
                              time_mode="cost_table")
    assert env.observation_layout[-2:] == ["candidates:left", "candidates:next_confidence"]
    for seed in range(6):
        obs, _ = env.reset(seed=seed)
        assert env.observation_space.contains(obs)
        left = env.ops.candidates
        assert obs[-2] == pytest.approx(min(1.0, len(left) / 5)) and obs[-1] == pytest.approx(left[0][0] if left else 0)
        if left:
            obs, reward, *_ = env.step(env.action_names.index("next_candidate"))
            assert obs[-2] == pytest.approx(min(1.0, (len(left) - 1) / 5)) and -0.1 < reward < 0
            return
    default = PerceptionConfigEnv(synthetic_dataset, time_mode="cost_table")
    assert not any(n.startswith("candidates:") for n in default.observation_layout)


def test_a_deterministic_generator_is_masked_once_it_searched_this_episode(synthetic_dataset):
    """ppf searches the frame without a seed or the pose: a second call in the episode repeats
    the first, so it is masked once called (a trained agent called it until max_ops after a
    failed pick); the randomised global_registration stays available, and a new episode
    unmasks ppf."""
    from perception_config.rl.env import PerceptionConfigEnv, repeats_search

    pipe = yaml.safe_load(PIPELINE)
    pipe["actions"].insert(0, {"name": "ppf", "block": "ppf", "params": {"max_seconds": 1.0}})
    env = PerceptionConfigEnv(synthetic_dataset, pipeline_from_dict(pipe), time_mode="cost_table")
    kinds = {a.name: repeats_search(a.block) for a in env.pipeline.actions}
    assert kinds == {"ppf": True, "icp_fine": False, "next_candidate": False, "global_registration": False,
                     "pick": False}
    ppf, gr = env.action_names.index("ppf"), env.action_names.index("global_registration")
    _, info = env.reset(seed=0)
    assert info["action_mask"].all()
    _, _, _, _, info = env.step(ppf)
    assert info["action_mask"][ppf] == 0 and info["action_mask"].sum() == len(env.action_names) - 1
    _, _, _, _, info = env.step(gr)
    assert info["action_mask"][gr] == 1 and info["action_mask"][ppf] == 0
    _, info = env.reset(seed=1)
    assert info["action_mask"].all()


def test_without_a_hypothesis_the_refiners_are_masked_and_pick_gives_up_once(synthetic_dataset):
    """After a refused generator call there is no hypothesis: an ICP can only fail (trained agents
    looped one until max_ops), so it is masked until a candidate is taken; pick (the cheap way
    to give up) stays until it was refused once, next_candidate and the generators stay."""
    from perception_config.rl.env import PerceptionConfigEnv, refines_nothing

    strict = yaml.safe_load(PIPELINE)
    strict["generator"]["params"] = {"min_verification": 1.0}  # every call refused: no hypothesis
    env = PerceptionConfigEnv(synthetic_dataset, pipeline_from_dict(strict), time_mode="cost_table")
    names = env.action_names
    assert [refines_nothing(a.block) for a in env.pipeline.actions] == [n == "icp_fine" for n in names]
    for seed in range(12):
        _, info = env.reset(seed=seed)
        assert env.last_outcome.pose is None
        mask = dict(zip(names, info["action_mask"].tolist()))
        assert mask == {"icp_fine": 0, "next_candidate": 1, "global_registration": 1, "pick": 1}
        # giving up by a pick without a pose: once (it fails in milliseconds), not again while none
        _, _, _, _, info = env.step(names.index("pick"))
        assert not env.last_outcome.result.ok and env.last_outcome.pose is None and not env.pick_failed
        mask = dict(zip(names, info["action_mask"].tolist()))
        assert mask == {"icp_fine": 0, "next_candidate": 1, "global_registration": 1, "pick": 0}
        _, _, _, _, info = env.step(names.index("next_candidate"))
        if env.last_outcome.pose is not None:  # a candidate taken: there is something to refine and pick
            assert info["action_mask"].all()
            return
    pytest.skip("no refused call left a candidate on the tiny dataset's first episodes")


def test_the_shipped_cell_pipeline_needs_no_ground_truth_but_the_simulated_pick():
    pipe = load_pipeline("cell")
    assert pipe.generator.name == "resting_pose" and GROUND_TRUTH not in pipe.generator.inputs
    names = pipe.action_names
    assert {"next_candidate", "ppf", "global_registration", "pick"} <= set(names)
    for action in pipe.actions:
        if action.kind != Kind.PICK:
            assert GROUND_TRUTH not in action.block.inputs, action.name
    assert all(GROUND_TRUTH not in b.inputs for b in pipe.scoring)
