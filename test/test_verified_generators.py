"""Generators that rank their candidates by the pick-success model and refuse below a probability
(blocks/verified.py), on a generator of known behaviour and on the shipped generators' params."""
from __future__ import annotations

import time

import numpy as np
import pytest

from perception_config.blocks.base import GROUND_TRUTH, MODEL, Block, BlockInput, BlockResult, Kind, create, register
from perception_config.blocks.verified import VERIFIER_PARAMS, RanksByVerifier
from perception_config.core.geometry import Pose
from perception_config.datasets.bop import BopDataset


@register
class FarFirst(RanksByVerifier, Block):
    """Ranks a pose a diameter aside first, confidently, and the annotated pose second."""

    kind = Kind.GENERATION
    name = "test_gen_far_first"
    default_cost = 0.0
    inputs = (MODEL, GROUND_TRUTH)
    params = VERIFIER_PARAMS

    def run(self, inp: BlockInput) -> BlockResult:
        time.sleep(0.3)  # a search (longer than the verifier takes for two candidates)
        gt = inp.ground_truth
        far = Pose(gt.R, gt.t + np.array([inp.model.diameter, 0.0, 0.0]))
        return BlockResult(ok=True, pose=far, scores={"gen_verification": 0.9}, candidates=[(0.9, far), (0.2, gt)])


@pytest.fixture(scope="module")
def query(synthetic_dataset):
    ds = BopDataset(synthetic_dataset, "test")
    frame = ds.load_frame(*ds.image_keys()[0])
    obj = max(frame.objects, key=lambda o: o.visib_fract or 0.0)
    return frame, obj


def _call(block, query):
    frame, obj = query
    return block(BlockInput(frame=frame, model=obj.model, ground_truth=obj.gt, rng=np.random.default_rng(0),
                            cache={}))


def test_without_a_verifier_the_generator_ranks_as_it_does(query):
    r = _call(create("test_gen_far_first"), query)
    assert r.ok and [c for c, _ in r.candidates] == [0.9, 0.2] and r.pose is r.candidates[0][1]


def test_the_verifier_ranks_the_right_candidate_first_and_gives_its_probability(query):
    frame, obj = query
    r = _call(create("test_gen_far_first", verifier="shipped", refuse_below=0.05), query)
    assert r.ok, r.reason
    (p_first, first), (p_second, second) = r.candidates
    assert np.allclose(first.t, obj.gt.t) and p_first > 0.5 > p_second  # the annotated pose, now first
    assert r.pose is first and r.info["own_confidence"] == [0.2, 0.9] and r.info["verifier"] == "shipped"
    assert r.scores == {"gen_verification": 0.9}  # the generator's own score stays for the agent
    assert r.elapsed >= 0.3  # the generator's search and the verifier's scoring


def test_below_refuse_below_the_call_is_refused_with_the_ranked_candidates_kept(query):
    r = _call(create("test_gen_far_first", verifier="shipped", refuse_below=1.0), query)
    assert not r.ok and "refuse_below 1.0" in r.reason and r.pose is None
    assert len(r.candidates) == 2 and r.candidates[0][0] >= r.candidates[1][0]


def test_a_verifier_that_cannot_be_loaded_fails_the_call_with_its_name(query, tmp_path):
    r = _call(create("test_gen_far_first", verifier=str(tmp_path / "no-model")), query)
    assert not r.ok and "no-model" in r.reason and r.elapsed >= 0.3


@pytest.mark.parametrize("name", ["ppf", "resting_pose", "global_registration", "linemod"])
def test_the_cells_generators_take_a_verifier(name):
    block = create(name, verifier="shipped", refuse_below=0.2)
    assert isinstance(block, RanksByVerifier) and block.config["refuse_below"] == 0.2
    assert create(name).config["verifier"] == ""  # off by default
