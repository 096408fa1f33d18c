"""ICP refiners: convergence on synthetic and real LM-O frames, presets, guards and bad input."""
from __future__ import annotations

import numpy as np
import pytest

from frames import box_model, mean_point_distance, perturbed_pose, random_box_scene, synthetic_frame, well_visible
from perception_config.blocks.base import REGISTRY, BlockInput, Kind
from perception_config.blocks.icp import IcpPointToPlane, IcpPointToPoint, distance_schedule, unoccluded
from perception_config.core.geometry import Pose, exp_so3
from perception_config.core.scene import Frame

BLOCKS = [IcpPointToPoint, IcpPointToPlane]


def lmo_objects(frame: Frame) -> list:
    """The objects of the real LM-O frame that are more than 90 % visible: at least 4 of its 8."""
    objects = well_visible(frame, 0.9)
    assert len(objects) >= 4
    return objects


def test_registered_with_params() -> None:
    for cls, name in [(IcpPointToPoint, "icp_point_to_point"), (IcpPointToPlane, "icp_point_to_plane")]:
        assert REGISTRY[name] is cls and cls.kind == Kind.REFINEMENT
        assert set(cls.score_names) == {"icp_fitness", "icp_rmse"}
        names = {p.name for p in cls.params}
        assert {"max_correspondence_distance", "final_distance", "stages", "max_iterations", "max_seconds"} <= names
    # the YAML presets: coarse 30 -> 15 mm, fine 10 -> 5 mm
    coarse = IcpPointToPlane(max_correspondence_distance=0.03, final_distance=0.015, stages=2)
    fine = IcpPointToPlane(max_correspondence_distance=0.01, final_distance=0.005, stages=2)
    assert coarse.config["stages"] == 2 and fine.config["final_distance"] == 0.005
    with pytest.raises(ValueError):
        IcpPointToPlane(max_correspondence_distance=-1.0)
    with pytest.raises(ValueError):
        IcpPointToPlane(kernel="cauchy-ish")


def test_distance_schedule() -> None:
    np.testing.assert_allclose(distance_schedule(0.03, 0.006, 3), [0.03, np.sqrt(0.03 * 0.006), 0.006])
    assert distance_schedule(0.03, 0.015, 2) == pytest.approx([0.03, 0.015])
    assert distance_schedule(0.02, 0.005, 1) == [0.02]
    assert distance_schedule(0.01, 0.05, 2) == [0.01, 0.01]  # final above first is clipped


@pytest.mark.parametrize("cls", BLOCKS)
def test_improves_perturbed_pose_on_synthetic_frames(cls) -> None:
    block = cls()
    better = converged = 0
    for k in range(10):
        model, gt, frame = random_box_scene(k % 3)
        rng = np.random.default_rng(100 + k)
        start = perturbed_pose(gt, rng, rng.uniform(5, 10), rng.uniform(10, 20))
        r = block(BlockInput(frame=frame, model=model, pose=start))
        assert r.ok, r.reason
        assert 0 <= r.scores["icp_fitness"] <= 1 and r.scores["icp_rmse"] >= 0
        before, after = mean_point_distance(model, start, gt), mean_point_distance(model, r.pose, gt)
        better += after < before
        converged += after < 0.1 * model.diameter
    assert better >= 9 and converged >= 8, (better, converged)


def test_point_to_plane_converges_from_15deg_2cm() -> None:
    block = IcpPointToPlane()
    converged = 0
    for k in range(10):
        model, gt, frame = random_box_scene(k % 5)
        start = perturbed_pose(gt, np.random.default_rng(200 + k), 15.0, 20.0)
        r = block(BlockInput(frame=frame, model=model, pose=start))
        converged += r.ok and mean_point_distance(model, r.pose, gt) < 0.1 * model.diameter
    assert converged >= 8, converged


@pytest.mark.parametrize("cls", BLOCKS)
def test_improves_perturbed_pose_on_real_lmo_frame(lmo_frame, cls) -> None:
    block, cache = cls(), {}
    better = trials = 0
    for i, o in enumerate(lmo_objects(lmo_frame)):
        rng = np.random.default_rng(300 + i)
        for _ in range(3):
            start = perturbed_pose(o.gt, rng, rng.uniform(5, 10), rng.uniform(10, 20))
            r = block(BlockInput(frame=lmo_frame, model=o.model, pose=start, cache=cache))
            trials += 1
            better += r.ok and mean_point_distance(o.model, r.pose, o.gt) < mean_point_distance(o.model, start, o.gt)
    assert better >= 0.8 * trials, (better, trials)


def test_point_to_plane_converges_on_real_lmo_frame(lmo_frame) -> None:
    block, cache = IcpPointToPlane(), {}
    converged = trials = 0
    for i, o in enumerate(lmo_objects(lmo_frame)):
        rng = np.random.default_rng(400 + i)
        for _ in range(3):
            start = perturbed_pose(o.gt, rng, 15.0, 20.0)
            r = block(BlockInput(frame=lmo_frame, model=o.model, pose=start, cache=cache))
            trials += 1
            converged += r.ok and mean_point_distance(o.model, r.pose, o.gt) < 0.1 * o.model.diameter
    assert converged >= 0.8 * trials, (converged, trials)


def test_coarse_then_fine_presets() -> None:
    coarse = IcpPointToPlane(max_correspondence_distance=0.03, final_distance=0.015, stages=2)
    fine = IcpPointToPlane(max_correspondence_distance=0.01, final_distance=0.005, stages=2)
    model, gt, frame = random_box_scene(1)
    start = perturbed_pose(gt, np.random.default_rng(7), 10.0, 15.0)
    cache: dict = {}
    r1 = coarse(BlockInput(frame=frame, model=model, pose=start, cache=cache))
    assert r1.ok, r1.reason
    r2 = fine(BlockInput(frame=frame, model=model, pose=r1.pose, cache=cache))
    assert r2.ok, r2.reason
    e0, e1, e2 = (mean_point_distance(model, p, gt) for p in (start, r1.pose, r2.pose))
    assert e1 < e0 and e2 <= e1 + 1e-4 and e2 < 0.003, (e0, e1, e2)


def test_occlusion_filter_keeps_pose_of_half_occluded_object() -> None:
    """A thin plate 2 cm in front of the object hides 60 % of it: matching the hidden part to
    the plate drags the pose onto it (~2-5 cm ADD measured); the occlusion filter drops those
    model points (< 1 mm)."""
    model = box_model()
    gt = Pose(exp_so3([0.5, -0.3, 0.2]), [0.0, 0.0, 0.7])
    z_front = gt.transform(model.points)[:, 2].min()
    plate = box_model(2, size=(0.06, 0.2, 0.004))
    frame = synthetic_frame([model, plate], [gt, Pose(np.eye(3), [0.02, 0.0, z_front - 0.02])], seed=3)
    errors = {}
    for flag in (True, False):
        block = IcpPointToPlane(occlusion_filter=flag)
        errs = []
        for k in range(5):
            start = perturbed_pose(gt, np.random.default_rng(500 + k), 5.0, 10.0)
            r = block(BlockInput(frame=frame, model=model, pose=start))
            errs.append(mean_point_distance(model, r.pose, gt) if r.ok else np.inf)
        errors[flag] = np.median(errs)
    assert errors[True] < 0.1 * model.diameter < errors[False], errors


def test_unoccluded_mask() -> None:
    K = np.array([[500.0, 0, 50], [0, 500.0, 50], [0, 0, 1]])
    depth = np.full((100, 100), np.nan, np.float32)
    depth[:, :50] = 0.5  # an observed surface on the left half at 0.5 m
    pts = np.array([[-0.01, 0, 0.6], [-0.01, 0, 0.51], [0.01, 0, 0.6], [5.0, 0, 1.0]])
    np.testing.assert_array_equal(unoccluded(pts, depth, K, 0.02), [False, True, True, True])


@pytest.mark.parametrize("cls", BLOCKS)
def test_bad_inputs_fail_with_a_reason(cls) -> None:
    model, gt, frame = random_box_scene(0)
    block = cls()

    def run(f: Frame, pose: Pose) -> str:
        r = block(BlockInput(frame=f, model=model, pose=pose))
        assert not r.ok and r.reason and r.pose is None
        return r.reason

    nan_frame = Frame(frame.rgb, np.full_like(frame.depth, np.nan), frame.K)
    assert "no valid pixel" in run(nan_frame, gt)
    assert "visible" in run(frame, Pose(gt.R, [3.0, 0.0, 0.7]))  # outside the view
    run(frame, Pose(gt.R, [0.0, 0.0, -0.7]))  # behind the camera
    run(frame, Pose(np.full((3, 3), np.nan), gt.t))
    run(frame, Pose(2.0 * gt.R, gt.t))  # not a rotation
    holes = frame.depth.copy()
    holes[100:400, 150:500] = np.nan  # no observed point near the object
    assert "observed points" in run(Frame(frame.rgb, holes, frame.K), gt)
    # nothing within the correspondence distance: the box hovers 4-5 cm in front of a wall
    wall = synthetic_frame([model], [Pose(gt.R, [0.3, 0.0, 0.7])], seed=1, background_z=0.74)
    assert "correspondences" in run(wall, Pose(np.eye(3), [-0.05, 0.0, 0.70]))


def test_time_bound_stops_after_the_first_stage() -> None:
    model, gt, frame = random_box_scene(2)
    start = perturbed_pose(gt, np.random.default_rng(9), 5.0, 10.0)
    r = IcpPointToPlane(max_seconds=0.001, stages=4)(BlockInput(frame=frame, model=model, pose=start))
    assert r.ok, r.reason
    assert r.info["stages_run"] < 4 and r.info["timed_out"]


def test_visible_surface_of_a_box_facing_the_camera() -> None:
    """Helpers in visibility.py: with the box square to the camera on the optical axis the front
    face (model z = -15 mm) is visible, plus side-face points within the z-buffer tolerance of
    the silhouette, nothing deeper; depth-grid normals of a plane are its normal."""
    from perception_config.vision.visibility import (
        default_visibility_tolerance,
        grid_normals,
        scene_patch,
        visible_surface,
    )

    model = box_model()
    pose = Pose(np.eye(3), [0.0, 0.0, 0.7])
    frame = synthetic_frame([model], [pose], seed=0, depth_noise=0.0)
    vis = visible_surface(frame, model, pose)
    front = np.isclose(model.points[:, 2], -0.015)
    assert set(np.flatnonzero(front)) <= set(vis.index)
    assert model.points[vis.index, 2].max() <= -0.015 + default_visibility_tolerance(model) + 1e-9
    patch = scene_patch(frame, model, pose, margin=0.01, with_normals=True)
    assert len(patch) > 100 and np.allclose(patch.points[:, 2], 0.685, atol=1e-4)
    assert np.allclose(patch.normals, [0.0, 0.0, -1.0], atol=1e-3)  # facing the camera
    tilted = np.stack(np.meshgrid(np.arange(5.0), np.arange(4.0)), axis=-1)
    grid = np.concatenate([tilted * 0.01, (0.5 + tilted[..., :1] * 0.01)], axis=-1)  # z rises with x
    n = grid_normals(grid)
    np.testing.assert_allclose(n[1:-1, 1:-1], np.broadcast_to([np.sqrt(0.5), 0, -np.sqrt(0.5)], (2, 3, 3)), atol=1e-6)
    assert np.isnan(n[0]).all() and np.isnan(n[:, -1]).all()
