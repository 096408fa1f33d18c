"""Scoring blocks: definitions on constructed frames, ground truth ranked above perturbed poses
on synthetic and real LM-O frames, shared cache, bad input (psi_rgb's own tests: test_psi_rgb.py)."""
from __future__ import annotations

import numpy as np
import pytest

from frames import box_model, perturbed_pose, random_box_scene, well_visible
from perception_config.blocks.appearance import PsiRgb
from perception_config.blocks.base import REGISTRY, BlockInput, Kind
from perception_config.blocks.scoring import IcpFitness, PsiC, PsiD
from perception_config.core.geometry import Pose
from perception_config.core.render import project, render
from perception_config.core.scene import Frame
from perception_config.vision.edges import image_derivatives, projected_directions

SCORERS = {"psi_d": PsiD, "psi_c": PsiC, "icp_fitness": IcpFitness, "psi_rgb": PsiRgb}
IMAGE_ONLY = ("psi_c", "psi_rgb")


def scores(frame, model, pose, cache=None) -> dict[str, float]:
    out: dict[str, float] = {}
    for cls in SCORERS.values():
        r = cls()(BlockInput(frame=frame, model=model, pose=pose, cache={} if cache is None else cache))
        assert r.ok, r.reason
        out.update(r.scores)
    return out


def test_registered_as_scoring_blocks() -> None:
    for name, cls in SCORERS.items():
        assert REGISTRY[name] is cls and cls.kind == Kind.SCORING
    assert PsiD.score_names == ("psi_d", "psi_d_m1", "psi_d_m2")
    assert PsiC.score_names == ("psi_c",)
    assert IcpFitness.score_names == ("icp_fitness", "icp_rmse")
    assert PsiRgb.score_names == ("psi_rgb", "psi_rgb_region", "psi_rgb_edges")
    assert PsiD().config["threshold"] == 0.005


def test_psi_d_components_on_constructed_depth() -> None:
    model, gt, frame = random_box_scene(0, depth_noise=0.0)
    r = render([model], [gt], frame.K, frame.width, frame.height)
    obj = np.isfinite(r.depth)

    def psi(depth: np.ndarray) -> dict[str, float]:
        res = PsiD()(BlockInput(frame=Frame(frame.rgb, depth.astype(np.float32), frame.K), model=model, pose=gt))
        assert res.ok, res.reason
        assert res.scores["psi_d"] == pytest.approx(res.scores["psi_d_m1"] + res.scores["psi_d_m2"])
        return res.scores

    assert psi(frame.depth) == pytest.approx({"psi_d": 1.0, "psi_d_m1": 1.0, "psi_d_m2": 0.0}, abs=1e-3)
    near = np.where(obj, r.depth + 0.003, frame.depth)  # 3 mm off: within 5 mm
    assert psi(near)["psi_d_m1"] == pytest.approx(1.0, abs=1e-3)
    far = np.where(obj, r.depth + 0.008, frame.depth)  # 8 mm off
    assert psi(far)["psi_d"] == pytest.approx(0.0, abs=1e-3)
    # the left half of the object has no observed depth: M2 = its share, M1 the rest
    holes = frame.depth.copy()
    cols = np.nonzero(obj.any(axis=0))[0]
    left = obj & (np.arange(frame.width)[None, :] < cols.mean())
    holes[left] = np.nan
    s = psi(holes)
    assert s["psi_d_m2"] == pytest.approx(left.sum() / obj.sum(), abs=1e-3)
    assert s["psi_d_m1"] == pytest.approx(1.0 - left.sum() / obj.sum(), abs=1e-3)


def test_psi_c_high_on_edges_zero_on_a_flat_image() -> None:
    model, gt, frame = random_box_scene(1)
    r = PsiC()(BlockInput(frame=frame, model=model, pose=gt))
    assert r.ok and r.scores["psi_c"] > 0.8, r.scores
    flat = Frame(np.full_like(frame.rgb, 128), frame.depth, frame.K)
    r = PsiC()(BlockInput(frame=flat, model=model, pose=gt))
    assert r.ok and r.scores["psi_c"] == 0.0
    # a gradient orthogonal to every contour normal is impossible; one along x everywhere
    # aligns only with the vertical contour parts: strictly between 0 and 1
    ramp = np.clip(np.arange(frame.width)[None, :, None] * 0.4 * np.ones((frame.height, 1, 3)), 0, 255).astype(np.uint8)
    r = PsiC(min_gradient=0.1)(BlockInput(frame=Frame(ramp, frame.depth, frame.K), model=model, pose=gt))
    assert r.ok and 0.1 < r.scores["psi_c"] < 0.9, r.scores


def test_projected_directions_match_finite_differences() -> None:
    K = np.array([[572.0, 0.0, 325.0], [0.0, 573.0, 242.0], [0.0, 0.0, 1.0]])
    rng = np.random.default_rng(0)
    p = rng.normal(size=(20, 3)) * 0.1 + [0, 0, 0.8]
    d = rng.normal(size=(20, 3))
    eps = 1e-6
    np.testing.assert_allclose(projected_directions(p, d, K), (project(p + eps * d, K) - project(p, K)) / eps,
                               rtol=1e-4, atol=1e-3)


def test_icp_fitness_definition() -> None:
    model, gt, frame = random_box_scene(2, depth_noise=0.0)
    r = IcpFitness()(BlockInput(frame=frame, model=model, pose=gt))
    assert r.ok and r.scores["icp_fitness"] > 0.97 and r.scores["icp_rmse"] < 0.002, r.scores
    away = Pose(gt.R, gt.t + [0.0, 0.0, 0.04])  # 4 cm behind: beyond the 1 cm threshold
    r = IcpFitness()(BlockInput(frame=frame, model=model, pose=away))
    assert r.ok and r.scores["icp_fitness"] < 0.05 and r.scores["icp_rmse"] <= 0.01, r.scores
    r = IcpFitness(threshold=0.05)(BlockInput(frame=frame, model=model, pose=away))
    # every point's shifted copy is 4 cm away; oblique faces have nearer neighbours
    assert r.scores["icp_fitness"] > 0.9 and 0.01 < r.scores["icp_rmse"] <= 0.0401, r.scores


def test_ground_truth_ranks_above_perturbed_on_synthetic_frames() -> None:
    wins = {"psi_d": 0, "psi_c": 0, "icp_fitness": 0, "psi_rgb": 0}
    for k in range(10):
        model, gt, frame = random_box_scene(k % 5)
        cache: dict = {}
        s_gt = scores(frame, model, gt, cache)
        s_bad = scores(frame, model, perturbed_pose(gt, np.random.default_rng(k), (5.0, 10.0), (10.0, 20.0)), cache)
        for name in wins:
            wins[name] += s_gt[name] > s_bad[name]
    assert all(w >= 9 for w in wins.values()), wins


def test_ground_truth_ranks_above_perturbed_on_real_lmo_frame(lmo_frame) -> None:
    wins = {"psi_d": 0, "psi_c": 0, "icp_fitness": 0, "psi_rgb": 0}
    trials, cache = 0, {}
    for i, o in enumerate(well_visible(lmo_frame, 0.9)):
        s_gt = scores(lmo_frame, o.model, o.gt, cache)
        rng = np.random.default_rng(20 + i)
        for _ in range(4):
            s_bad = scores(lmo_frame, o.model, perturbed_pose(o.gt, rng, (5.0, 10.0), (10.0, 20.0)), cache)
            trials += 1
            for name in wins:
                wins[name] += s_gt[name] > s_bad[name]
    assert trials >= 16
    assert wins["psi_d"] >= 0.9 * trials and wins["icp_fitness"] >= 0.9 * trials, (wins, trials)
    assert wins["psi_c"] >= 0.75 * trials and wins["psi_rgb"] >= 0.9 * trials, (wins, trials)


def test_cache_shares_one_render_and_gives_the_same_scores() -> None:
    model, gt, frame = random_box_scene(4)
    pose = perturbed_pose(gt, np.random.default_rng(3), (5.0, 10.0), (10.0, 20.0))
    cache: dict = {}
    shared = scores(frame, model, pose, cache)
    assert len(cache["visibility:render"]) == 1
    assert shared == scores(frame, model, pose, None)
    image_derivatives(frame, cache)
    gx, gy = image_derivatives(frame, cache)
    assert gx.shape == frame.depth.shape and gx.dtype == np.float32


@pytest.mark.parametrize("name", sorted(SCORERS))
def test_bad_inputs_fail_with_a_reason(name) -> None:
    model, gt, frame = random_box_scene(0)
    block = SCORERS[name]()

    def fails(f: Frame, pose: Pose) -> str:
        r = block(BlockInput(frame=f, model=model, pose=pose))
        assert not r.ok and r.reason and not r.scores
        return r.reason

    if name not in IMAGE_ONLY:  # psi_c and psi_rgb read the image, not the depth
        fails(Frame(frame.rgb, np.full_like(frame.depth, np.nan), frame.K), gt)
    fails(frame, Pose(gt.R, [3.0, 0.0, 0.7]))  # outside the view
    fails(frame, Pose(gt.R, [0.0, 0.0, -0.7]))  # behind the camera
    fails(frame, Pose(np.full((3, 3), np.nan), gt.t))
    fails(frame, Pose(2.0 * gt.R, gt.t))
    tiny = box_model(5, size=(0.0005, 0.0005, 0.0005))  # covers less than a pixel
    r = block(BlockInput(frame=frame, model=tiny, pose=gt))
    assert not r.ok and r.reason
