"""`bench generators`: the generators' ranked candidates judged against the annotations, with the
declared symmetries and with the declared or derived ones, on generators of known behaviour."""
from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from perception_config.bench.generators import bench_generators, format_generators, judge_candidates, verifier_figures
from perception_config.blocks.base import GROUND_TRUTH, MODEL, Block, BlockInput, BlockResult, Kind, register
from perception_config.cli import main
from perception_config.core.geometry import Pose
from perception_config.core.symmetry import axis_angle_matrix


def _flip_z(model) -> Pose:
    """The 180-degree turn about the model's z axis through its box's centre."""
    c = model.bbox_min + model.bbox_size / 2
    R = axis_angle_matrix(np.array([0.0, 0.0, 1.0]), np.pi)
    return Pose(R, c - R @ c)


@register
class TruthFirst(Block):
    """A generator that ranks the annotated pose first, confidently."""

    kind = Kind.GENERATION
    name = "test_gen_truth_first"
    default_cost = 0.0
    inputs = (MODEL, GROUND_TRUTH)

    def run(self, inp: BlockInput) -> BlockResult:
        far = Pose(inp.ground_truth.R, inp.ground_truth.t + np.array([inp.model.diameter, 0.0, 0.0]))
        return BlockResult(ok=True, pose=inp.ground_truth, candidates=[(0.9, inp.ground_truth), (0.1, far)])


@register
class RefusesTheTruth(Block):
    """A generator that finds the annotated pose, rates it low and refuses."""

    kind = Kind.GENERATION
    name = "test_gen_refuses_truth"
    default_cost = 0.0
    inputs = (MODEL, GROUND_TRUTH)

    def run(self, inp: BlockInput) -> BlockResult:
        r = BlockResult.fail("verifies at 0.1 < min_verification 0.3")
        r.candidates = [(0.1, inp.ground_truth)]
        return r


def test_a_flip_of_a_box_that_declares_no_symmetry_is_wrong_to_bop_and_right_for_the_pick(make_box):
    box = make_box((0.1, 0.06, 0.03))
    assert not box.is_symmetric  # nothing declared
    gt = Pose(np.eye(3), np.array([0.0, 0.0, 0.5]))
    obj = SimpleNamespace(model=box, gt=gt)
    flipped = gt.compose(_flip_z(box))
    far = Pose(gt.R, gt.t + np.array([0.05, 0.0, 0.0]))  # wrong in shape too: 0.05 m is 0.42 d
    judged = judge_candidates([(0.9, flipped), (0.4, gt)], obj)
    assert judged["rank_declared"] == 1 and judged["rank_derived"] == 0
    assert judged["top1_mssd_d_declared"] > 0.9 and judged["top1_mssd_d_derived"] < 0.01
    assert judged["confident_wrong_declared"] and not judged["confident_wrong_derived"]
    judged = judge_candidates([(0.9, far)], obj)
    assert judged["rank_declared"] == judged["rank_derived"] == -1
    assert judged["confident_wrong_declared"] and judged["confident_wrong_derived"]
    # Below the confidence, a wrong first answer is not confidently wrong; no candidate, nothing is.
    assert not judge_candidates([(0.3, far)], obj)["confident_wrong_derived"]
    assert judge_candidates([], obj) == {"candidates": 0, "top1_confidence": 0.0, "rank_declared": -1,
                                       "top1_mssd_d_declared": None, "confident_wrong_declared": False,
                                       "rank_derived": -1, "top1_mssd_d_derived": None,
                                       "confident_wrong_derived": False, "mssd_d_derived": []}


def test_bench_generators_judges_every_query_and_writes_json_png_and_table(synthetic_dataset, tmp_path, capsys):
    out = tmp_path / "gens"
    assert main(["bench", "generators", "--dataset", str(synthetic_dataset), "--out", str(out), "--quiet",
                 "--generators", "test_gen_truth_first,test_gen_refuses_truth"]) == 0
    result = json.loads((out / "generators.json").read_text())
    assert (out / "generators.png").read_bytes()[:4] == b"\x89PNG"
    truth, refuses = (result["generators"][g]["summary"] for g in ("test_gen_truth_first", "test_gen_refuses_truth"))
    n = len(result["generators"]["test_gen_truth_first"]["rows"])
    assert n == truth["queries"] == refuses["queries"] > 0
    for sym in ("declared", "derived"):
        assert truth[sym] == {"top1": 1.0, "top5": 1.0, "confident_wrong": 0.0}
        assert refuses[sym] == {"top1": 1.0, "top5": 1.0, "confident_wrong": 0.0}  # right, but unsure
        assert result["any"][sym]["top5"] == 1.0
    assert truth["refused"] == 0.0 and refuses["refused"] == 1.0
    assert sum(f["queries"] for f in truth["per_object"].values()) == n
    assert all(r["reason"].startswith("verifies at") for r in result["generators"]["test_gen_refuses_truth"]["rows"])
    table = capsys.readouterr().out
    assert "test_gen_truth_first" in table and "test_gen_refuses_truth" in table and "any of them" in table


def test_bench_generators_says_what_was_wrong(synthetic_dataset, tmp_path, capsys):
    assert main(["bench", "generators", "--dataset", str(synthetic_dataset), "--out", str(tmp_path / "x"),
                 "--generators", ",", "--quiet"]) == 2
    assert "--generators" in capsys.readouterr().err
    with pytest.raises(ValueError, match="no images"):
        bench_generators(synthetic_dataset, ["test_gen_truth_first"], n_frames=0, progress=False)


def test_the_table_reads_both_symmetry_columns():
    rows = {"queries": 2, "refused": 0.5, "declared": {"top1": 0.0, "top5": 0.5, "confident_wrong": 0.5},
            "derived": {"top1": 0.5, "top5": 1.0, "confident_wrong": 0.0}}
    result = {"dataset": "d", "images": 1, "min_visib": 0.0, "tolerance": 0.1, "confident": 0.5, "wrong": 0.3,
              "skipped": {"linemod": "the frames lack what it needs"},
              "generators": {"g": {"summary": {**rows, "median_s": 0.5, "p90_s": 1.0, "per_object": {"3": rows}}}}}
    text = format_generators(result)
    line = next(ln for ln in text.splitlines() if ln.startswith("g "))
    assert line.split()[2:10] == ["2", "50%", "0%", "50%", "50%", "50%", "100%", "0%"], line
    assert "linemod: not run" in text


def test_the_verifier_is_judged_on_the_candidates_and_ranks_and_refuses_them():
    rows = [  # three queries: candidates' probabilities and MSSD / diameter (derived symmetries)
        {"verifier": [0.2, 0.9], "mssd_d_derived": [0.8, 0.05]},  # ranked by it: right, answered
        {"verifier": [0.7, 0.1], "mssd_d_derived": [0.5, 0.02]},  # answered, confidently wrong
        {"verifier": [0.3], "mssd_d_derived": [0.01]},  # right but refused (p < 0.5)
    ]
    v = verifier_figures(rows)
    assert v["n"] == 5 and v["positives"] == 3
    # pairs (right, wrong): (0.9 > 0.2), (0.9 > 0.7), (0.1 < 0.2), (0.1 < 0.7), (0.3 > 0.2), (0.3 < 0.7): 3 of 6
    assert v["auc"] == pytest.approx(0.5)
    assert v["brier"] == pytest.approx(np.mean([0.2**2, 0.1**2, 0.7**2, 0.9**2, 0.7**2]))
    assert v["ranked"] == {"refuse_below": 0.5, "offered": pytest.approx(2 / 3), "top1": pytest.approx(1 / 3),
                           "confident_wrong": pytest.approx(1 / 3)}


def test_bench_generators_with_the_shipped_verifier(synthetic_dataset, tmp_path, capsys):
    out = tmp_path / "gens.json"
    assert main(["bench", "generators", "--dataset", str(synthetic_dataset), "--out", str(out), "--quiet",
                 "--generators", "test_gen_truth_first", "--verifier", "shipped"]) == 0
    result = json.loads(out.read_text())
    rows = result["generators"]["test_gen_truth_first"]["rows"]
    assert all(len(r["verifier"]) == len(r["mssd_d_derived"]) == 2 for r in rows)
    v = result["generators"]["test_gen_truth_first"]["summary"]["verifier"]
    assert v["n"] == 2 * len(rows) and v["positives"] == len(rows)
    assert v["auc"] > 0.9  # the annotated pose against one a diameter aside
    assert result["verifier_all"]["n"] == v["n"] and result["verifier"] == "shipped"
    assert "AUC" in capsys.readouterr().out
    assert main(["bench", "generators", "--dataset", str(synthetic_dataset), "--out", str(out), "--quiet",
                 "--generators", "test_gen_truth_first", "--verifier", str(tmp_path / "no-such-model")]) == 2
    assert "no-such-model" in capsys.readouterr().err
