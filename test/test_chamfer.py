"""Chamfer matching and chamfer-ICP: the nearest-edge table is right, chamfer-ICP keeps the
weakly observed depth (plain PnP on nearest-edge matches drifted by centimetres), chamfer
stays within its candidate budget, the start-anchored prior holds out-of-plane rotation more
than rotation about the viewing ray, and the ground truth is a fixed point on a clean frame."""
from __future__ import annotations

import numpy as np

from frames import box_model, default_pose, mean_point_distance, perturbed_pose, refine_perturbed, synthetic_frame
from perception_config.blocks import create
from perception_config.blocks.base import BlockInput
from perception_config.core.geometry import Pose, exp_so3, log_so3
from perception_config.core.scene import Frame
from perception_config.vision.chamfer import edge_distance
from perception_config.vision.pose_solver import (
    NO_TRANSLATION_PRIOR,
    levenberg_marquardt,
    prior_information,
    viewing_frame,
)

_perturbed, _add = perturbed_pose, mean_point_distance


def test_edge_distance_labels_point_at_the_nearest_edge_pixel():
    rgb = np.full((60, 80, 3), 40, np.uint8)
    rgb[20:40, 30:55] = 220  # a bright rectangle: its outline is the only edge
    frame = Frame(rgb=rgb, depth=np.full((60, 80), np.nan, np.float32), K=np.eye(3))
    dt, labels, lut, n = edge_distance(frame, {}, 40.0, 100.0)
    assert n > 0
    ey, ex = np.nonzero(dt == 0)
    rng = np.random.default_rng(0)
    for v, u in zip(rng.integers(0, 60, 30), rng.integers(0, 80, 30)):
        nx, ny = lut[labels[v, u]]
        brute = np.sqrt((ex - u) ** 2 + (ey - v) ** 2).min()
        assert abs(np.hypot(nx - u, ny - v) - brute) < 1.0
        assert abs(dt[v, u] - brute) < 0.1 * brute + 0.5


def test_chamfer_icp_improves_the_3d_error_without_depth_drift():
    model, gt = box_model(), default_pose()
    frame = synthetic_frame([model], [gt], seed=2)
    better, depth_moves = 0, []
    for start, r in refine_perturbed(create("chamfer_icp"), frame, model, gt, np.random.default_rng(3)):
        better += _add(model, r.pose, gt) < _add(model, start, gt)
        depth_moves.append(abs(r.pose.t[2] - start.t[2]))
    assert better >= 7, f"chamfer_icp improved {better}/10"
    assert max(depth_moves) < 0.01


def test_chamfer_stays_within_its_candidate_budget_and_lowers_its_cost():
    model, gt = box_model(), default_pose()
    frame = synthetic_frame([model], [gt], seed=2)
    start = _perturbed(gt, np.random.default_rng(5))
    # without the wall-clock bound: the budget under test is the candidates', on a loaded machine too
    r = create("chamfer", rounds=3, candidates=20)(BlockInput(frame=frame, model=model, pose=start, time_bounded=False))
    assert r.ok and r.info["candidates"] <= 120  # the careful and the wide search, 60 each
    only = create("chamfer", rounds=3, candidates=20, wide_rotation_deg=0.0)
    assert only(BlockInput(frame=frame, model=model, pose=start, time_bounded=False)).info["candidates"] <= 60
    assert r.scores["chamfer_cost"] < r.info["cost_before"]
    ray = start.t / np.linalg.norm(start.t)
    assert abs((r.pose.t - start.t) @ ray) < 1e-9  # depth along the viewing ray is not searched


def test_the_prior_holds_out_of_plane_rotation_more_than_rotation_about_the_ray():
    """prior_information: rotation about the viewing ray is weakly held, rotation out of the image
    plane and depth strongly, image-plane translation not at all; the MAP solver stops where the
    data's pull meets the prior."""
    t0 = np.array([0.1, -0.05, 0.8])
    B = viewing_frame(t0)
    assert np.allclose(B @ B.T, np.eye(3)) and np.allclose(B[0], t0 / np.linalg.norm(t0))
    A = prior_information(t0, 100, 15.0, 3.0, 5.0)
    assert np.allclose(A, A.T)
    about, out = B[0] @ A[:3, :3] @ B[0], B[1] @ A[:3, :3] @ B[1]
    assert np.isclose(out / about, 25.0)  # (15 / 3)^2
    assert abs(B[1] @ A[3:, 3:] @ B[1]) < 1e-9 and B[0] @ A[3:, 3:] @ B[0] > 0
    # Data pulling the rotation by 10 deg about each axis (residuals = rotation vector x 100 px/rad):
    # about the ray it mostly follows (prior 15 deg), out of the plane the prior (3 deg) holds it.
    anchor, goal = Pose(np.eye(3), t0), 0.17 * np.ones(3)

    def evaluate(R, t):
        return np.concatenate([100 * (log_so3(R) - goal), 100 * (t - t0)]), 100 * np.eye(6)

    R, _, _ = levenberg_marquardt(evaluate, anchor.R, t0, NO_TRANSLATION_PRIOR, 1e6, 50, float("inf"), anchor=anchor.t,
                                  rotation_anchor=anchor.R, information=A)
    w = log_so3(R)
    assert abs(w @ B[0]) > 0.6 * abs(goal @ B[0])
    assert np.linalg.norm(w - (w @ B[0]) * B[0]) < 0.5 * np.linalg.norm(goal - (goal @ B[0]) * B[0])
    assert np.allclose(exp_so3(w), R)


def test_a_correct_pose_is_a_fixed_point_on_a_synthetic_frame():
    """Started at the ground truth on a clean synthetic frame, both refiners stay within a
    small fraction of the pick tolerance, call after call."""
    model, gt = box_model(), default_pose()
    frame = synthetic_frame([model], [gt], seed=2)
    for name in ("chamfer", "chamfer_icp"):
        pose, cache = gt, {}
        for call in range(3):
            r = create(name)(BlockInput(frame=frame, model=model, pose=pose, cache=cache,
                                        rng=np.random.default_rng(call), time_bounded=False))
            assert r.ok, r.reason
            pose = r.pose
        assert _add(model, pose, gt) < 0.03 * model.diameter, name
