"""`bench real`: the refiner and score benchmark on a BOP dataset, with blocks of known behaviour."""
from __future__ import annotations

import json

import numpy as np
import pytest

from perception_config.bench.real import (
    VISIBILITY_LABELS,
    bench_real,
    format_real,
    save_real,
    select_blocks,
    visibility_bin,
)
from perception_config.blocks.base import GROUND_TRUTH, MODEL, POSE, Block, BlockInput, BlockResult, Kind, register
from perception_config.blocks.pipeline import load_pipeline
from perception_config.cli import main
from perception_config.core.metrics import pose_mssd


def _mssd_d(inp: BlockInput) -> float:
    return pose_mssd(inp.pose, inp.ground_truth, inp.model) / inp.model.diameter


@register
class Unchanged(Block):
    """A refiner that returns its input: never improves, never leaves the tolerance."""

    kind = Kind.REFINEMENT
    name = "test_bench_unchanged"
    default_cost = 0.0
    inputs = (MODEL, POSE)

    def run(self, inp: BlockInput) -> BlockResult:
        return BlockResult(ok=True, pose=inp.pose)


@register
class AlwaysFails(Block):
    """A refiner that answers ok=False with a reason that carries a number."""

    kind = Kind.REFINEMENT
    name = "test_bench_fails"
    default_cost = 0.0
    inputs = (MODEL, POSE)

    def run(self, inp: BlockInput) -> BlockResult:
        return BlockResult.fail(f"too few edge points ({inp.rng.integers(0, 9)} < 10)")


@register
class MinusMssd(Block):
    """A perfect score: minus the MSSD to the ground truth over the diameter (higher = better)."""

    kind = Kind.SCORING
    name = "test_bench_minus_mssd"
    default_cost = 0.0
    inputs = (MODEL, POSE, GROUND_TRUTH)
    score_names = ("minus_mssd",)

    def run(self, inp: BlockInput) -> BlockResult:
        return BlockResult(ok=True, scores={"minus_mssd": -_mssd_d(inp)})


@register
class Mssd(Block):
    """The negation: the MSSD, once declared lower-is-better (a perfect score) and once not."""

    kind = Kind.SCORING
    name = "test_bench_mssd"
    default_cost = 0.0
    inputs = (MODEL, POSE, GROUND_TRUTH)
    score_names = ("mssd_lower_better", "mssd_higher_better")
    lower_is_better = ("mssd_lower_better",)

    def run(self, inp: BlockInput) -> BlockResult:
        e = _mssd_d(inp)
        return BlockResult(ok=True, scores={"mssd_lower_better": e, "mssd_higher_better": e})


TEST_BLOCKS = ["test_bench_unchanged", "test_bench_fails", "test_bench_minus_mssd", "test_bench_mssd"]


def _shares(stats: dict) -> list[float]:
    return [stats[k] for k in ("improved", "within_before", "within_1", "within_3", "reached_3", "fail_share")]


def test_known_blocks_on_synthetic(synthetic_dataset):
    res = bench_real(synthetic_dataset, n_frames=2, seeds=1, blocks=[*TEST_BLOCKS, "d2co", "psi_d"], progress=False)
    assert res["frames"] == 2 and res["frames_with_depth"] == 2 and res["instances"] > 0
    assert res["skipped"] == {}
    assert set(res["refiners"]) == {"test_bench_unchanged", "test_bench_fails", "d2co"}
    for entry in res["refiners"].values():
        for stats in [*entry["overall"].values(), *(s for o in entry["per_object"].values() for s in o.values())]:
            assert all(0.0 <= x <= 1.0 for x in _shares(stats))
            assert stats["calls"] >= stats["n"] and stats["median_ms"] >= 0
        assert sum(s["n"] for o in entry["per_object"].values() for s in [o["0.3"]]) == entry["overall"]["0.3"]["n"]
        assert sum(v["0.3"]["n"] for v in entry["per_visibility"].values()) == entry["overall"]["0.3"]["n"]
        assert set(entry["per_visibility"]) <= set(VISIBILITY_LABELS)
    same = res["refiners"]["test_bench_unchanged"]["overall"]
    assert same["0"]["within_before"] == same["0"]["within_1"] == same["0"]["within_3"] == 1.0
    assert same["0"]["mssd_1"] == 0.0 and same["0"]["mspd_1"] == pytest.approx(0.0, abs=1e-6)
    for lam in ("0", "0.1", "0.3"):
        s = same[lam]
        assert s["improved"] == 0.0 and s["fail_share"] == 0.0 and s["calls"] == 3 * s["n"]
        assert s["within_before"] == s["within_1"] == s["within_3"] == s["reached_3"]
        assert s["mssd_1"] == s["mssd_before"]
    for s in res["refiners"]["test_bench_fails"]["overall"].values():  # a failed call ends the chain
        assert s["fail_share"] == 1.0 and s["calls"] == s["n"] and s["improved"] == 0.0
        assert s["reasons"] == {"too few edge points (# < #)": s["n"]} and s["within_1"] == s["within_before"]
    scores = res["scores"]
    assert scores["minus_mssd"]["pairs"] > 0
    assert scores["minus_mssd"]["auc"] == 1.0 and scores["minus_mssd"]["auc_pooled"] == 1.0
    assert scores["mssd_lower_better"]["auc"] == 1.0 and scores["mssd_lower_better"]["lower_is_better"]
    assert scores["mssd_higher_better"]["auc"] == 0.0 and scores["mssd_higher_better"]["auc_pooled"] == 0.0
    assert all(o["auc"] in (None, 1.0) for o in scores["minus_mssd"]["per_object"].values())
    by_visibility = scores["minus_mssd"]["per_visibility"]
    assert all(v["auc"] in (None, 1.0) for v in by_visibility.values())
    assert sum(v["pairs"] for v in by_visibility.values()) == scores["minus_mssd"]["pairs"]
    assert all(v["auc"] in (None, 0.0) for v in scores["mssd_higher_better"]["per_visibility"].values())
    assert 0.0 <= scores["psi_d"]["auc"] <= 1.0 and {"psi_d_m1", "psi_d_m2"} <= set(scores)
    # d2co's own cost at the pose (before it moves), ranked like a score; the unchanged refiner reports none.
    assert scores["d2co:d2co_cost"]["refiner_cost"] and 0.0 <= scores["d2co:d2co_cost"]["auc"] <= 1.0
    assert not any(k.startswith("test_bench_unchanged") for k in scores)
    table = format_real(res)
    assert "**test_bench_unchanged**" in table and "minus_mssd" in table
    assert "| visib " in table and "AUC visib" in table


def test_visibility_buckets():
    assert VISIBILITY_LABELS == ["<0.5", "0.5-0.7", "0.7-0.85", ">=0.85", "unknown"]
    assert [visibility_bin(v) for v in (0.3, 0.5, 0.69, 0.7, 0.85, 1.0, None, float("nan"))] == [
        "<0.5", "0.5-0.7", "0.5-0.7", "0.7-0.85", ">=0.85", ">=0.85", "unknown", "unknown"]


def test_reproducible_and_independent_of_the_blocks(synthetic_dataset):
    one = bench_real(synthetic_dataset, n_frames=1, seeds=2, blocks=["test_bench_unchanged"], progress=False)
    two = bench_real(synthetic_dataset, n_frames=1, seeds=2, blocks=["d2co", "test_bench_unchanged"],
                     progress=False)
    a, b = one["refiners"]["test_bench_unchanged"], two["refiners"]["test_bench_unchanged"]
    assert [v["mssd_before"] for v in a["overall"].values()] == [v["mssd_before"] for v in b["overall"].values()]
    assert a["per_object"].keys() == b["per_object"].keys()


def test_scores_only_and_lambda_zero_only_are_written(synthetic_dataset, tmp_path):
    for blocks, lambdas in ((["test_bench_minus_mssd"], [0.1]), (["test_bench_unchanged"], [0.0])):
        res = bench_real(synthetic_dataset, n_frames=1, seeds=1, lambdas=lambdas, blocks=blocks, progress=False)
        js, png = save_real(res, tmp_path / f"{blocks[0]}.json")
        assert json.loads(js.read_text())["settings"]["lambdas"] == lambdas and png.stat().st_size > 0


def test_mann_whitney_counts_ties_half_and_failures_lowest():
    from perception_config.bench.real import _mann_whitney

    # 1~1 tie, 1>nan, nan~nan tie, 3 beats all three: 0.5 + 1 + 0.5 + 3 of 9 pairs
    assert _mann_whitney(np.array([1.0, np.nan, 3.0]), np.array([1.0, 2.0, np.nan])) == (5.0, 9)
    assert _mann_whitney(np.array([1.0]), np.array([])) == (0.0, 0)


def test_bad_input(synthetic_dataset):
    with pytest.raises(ValueError, match="unknown block.*no_such_block"):
        select_blocks(load_pipeline(), ["no_such_block"])
    with pytest.raises(ValueError, match="number of frames"):
        bench_real(synthetic_dataset, n_frames=0, progress=False)
    with pytest.raises(ValueError, match="lambdas"):
        bench_real(synthetic_dataset, lambdas=[-0.1], progress=False)
    with pytest.raises(ValueError, match="visib_fract"):
        bench_real(synthetic_dataset, n_frames=1, min_visib=1.5, blocks=["test_bench_unchanged"], progress=False)


def test_rgb_only_frames_skip_depth_blocks(lmo_rgb_root, tmp_path, capsys):
    out = tmp_path / "res"
    code = main(["bench", "real", "--dataset", str(lmo_rgb_root), "--out", str(out), "--frames", "1", "--seeds", "1",
                 "--blocks", "d2co,icp_coarse,depth_refine,psi_c,psi_d", "--no-refiner-costs", "--quiet"])
    assert code == 0
    res = json.loads((out / "real.json").read_text())
    assert (out / "real.png").stat().st_size > 0
    assert res["frames_with_depth"] == 0
    assert res["skipped"] == {"icp_coarse": "needs depth", "depth_refine": "needs depth", "psi_d": "needs depth"}
    assert list(res["refiners"]) == ["d2co"] and list(res["scores"]) == ["psi_c"]
    assert np.isfinite(res["scores"]["psi_c"]["auc"])
    assert "skipped: icp_coarse (needs depth)" in capsys.readouterr().out


def test_rgbd_frame_read_as_rgb_only(lmo_root, tmp_path):
    assert main(["bench", "real", "--dataset", str(lmo_root), "--out", str(tmp_path / "r.json"), "--seeds", "1",
                 "--lambdas", "0.1", "--blocks", "icp_coarse,psi_c", "--no-depth", "--quiet"]) == 0
    res = json.loads((tmp_path / "r.json").read_text())
    assert res["frames_with_depth"] == 0 and res["skipped"] == {"icp_coarse": "needs depth"}
    assert res["settings"]["use_depth"] is False and list(res["scores"]) == ["psi_c"]
