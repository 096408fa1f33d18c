"""BOP pose errors checked against hand computations, brute force, and the real LM-O sample."""
from __future__ import annotations

import math

import numpy as np
import pytest

from frames import K_LINEMOD, box_mesh, box_model, cylinder_mesh, default_pose, synthetic_frame
from perception_config.core import metrics as M
from perception_config.core.geometry import Pose, exp_so3
from perception_config.core.models import make_model
from perception_config.core.render import render

HALF = np.array([0.04, 0.025, 0.015])  # half sizes of box_model()'s default 0.08 x 0.05 x 0.03 box
CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float) * HALF
FLIPS = [Pose.identity()] + [Pose(exp_so3(np.pi * np.eye(3)[i]), np.zeros(3)) for i in range(3)]


def symmetric_box():
    """The test box with its three declared 180 degree symmetries (identity first)."""
    v, f = box_mesh(tuple(2 * HALF))
    return make_model(7, v, f, symmetries=FLIPS, n_points=500)


def cylinder(radius: float = 0.03, height: float = 0.05, n: int = 64):
    """A closed n-gon prism about z with a declared continuous symmetry (BOP models_info, mm)."""
    v, faces = cylinder_mesh(radius, height, n)
    info = {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]}
    return make_model(8, v, faces, info=info, n_points=500)


def errors_on_corners(est: Pose, gt: Pose, syms=None) -> dict[str, float]:
    return {
        "add": M.add(est.R, est.t, gt.R, gt.t, CORNERS),
        "adi": M.adi(est.R, est.t, gt.R, gt.t, CORNERS),
        "mssd": M.mssd(est.R, est.t, gt.R, gt.t, CORNERS, syms),
        "re": M.re(est.R, gt.R),
        "te": M.te(est.t, gt.t),
    }


# --------------------------------------------------------------------------- hand-computed values


@pytest.mark.parametrize("d, direction", [(0.004, [1, 0, 0]), (0.012, [0.3, -0.5, 0.8])])
def test_pure_translation(d: float, direction) -> None:
    gt = default_pose()
    u = np.asarray(direction, float) / np.linalg.norm(direction)
    est = Pose(gt.R, gt.t + d * u)
    e = errors_on_corners(est, gt)
    # corners are >= 3 cm apart, so each gt corner's nearest estimated corner is its own: adi = add
    for key in ("add", "adi", "mssd", "te"):
        assert e[key] == pytest.approx(d, abs=1e-9), key
    assert e["re"] == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("axis, radial", [(2, math.hypot(HALF[0], HALF[1])), (0, math.hypot(HALF[1], HALF[2]))])
@pytest.mark.parametrize("angle", [math.radians(7), math.radians(60)])
def test_rotation_about_model_axis(axis: int, radial: float, angle: float) -> None:
    gt = default_pose()
    est = gt.compose(Pose(exp_so3(angle * np.eye(3)[axis]), np.zeros(3)))  # about the model origin
    e = errors_on_corners(est, gt)
    chord = 2 * math.sin(angle / 2) * radial  # every corner is `radial` from the axis
    assert e["re"] == pytest.approx(angle, abs=1e-7)
    assert e["te"] == pytest.approx(0.0, abs=1e-12)
    assert e["add"] == pytest.approx(chord, abs=1e-9)
    assert e["mssd"] == pytest.approx(chord, abs=1e-9)


def test_rotation_about_camera_axis_through_model_origin() -> None:
    gt = default_pose()
    axis = np.array([0.2, 1.0, -0.4]) / np.linalg.norm([0.2, 1.0, -0.4])
    angle = 0.3
    est = Pose(exp_so3(axis * angle) @ gt.R, gt.t)  # rotation about an axis through t
    x = CORNERS @ gt.R.T  # corners relative to the model origin, camera axes
    radial = np.linalg.norm(x - np.outer(x @ axis, axis), axis=1)
    expected = 2 * math.sin(angle / 2) * radial
    e = errors_on_corners(est, gt)
    assert e["re"] == pytest.approx(angle, abs=1e-7)
    assert e["add"] == pytest.approx(expected.mean(), abs=1e-9)
    assert e["mssd"] == pytest.approx(expected.max(), abs=1e-9)
    assert e["add"] < e["mssd"]  # the corners are not all equally far from this axis


def test_symmetric_box_rotated_by_a_symmetry() -> None:
    model = symmetric_box()
    gt = default_pose()
    for sym in FLIPS[1:]:
        est = gt.compose(sym)
        assert M.pose_mssd(est, gt, model) == pytest.approx(0.0, abs=1e-7)
        assert M.mssd(est.R, est.t, gt.R, gt.t, CORNERS, model.symmetries) == pytest.approx(0.0, abs=1e-7)
        e = M.pose_errors(est, gt, model)
        assert e["add"] > 0.02 and e["re"] == pytest.approx(math.pi, abs=1e-6)
        assert e["adi"] < 0.003  # the surface maps onto itself: only sampling distance remains
        # without the declared symmetries the same pose is far off
        assert M.mssd(est.R, est.t, gt.R, gt.t, model.hull_points, None) > 0.05
    # a symmetry plus a 1 cm shift: MSSD sees just the shift
    est = Pose(gt.compose(FLIPS[3]).R, gt.t + [0.01, 0, 0])
    assert M.pose_mssd(est, gt, model) == pytest.approx(0.01, abs=1e-9)


def test_continuous_symmetry_is_sampled_finely_for_evaluation() -> None:
    model = cylinder()
    assert len(model.symmetries) == 36  # core/symmetry.py samples every 10 degrees
    syms = M.eval_symmetries(model)
    assert len(syms) == math.ceil(math.pi / M.MAX_SYM_DISC_STEP)
    assert M.eval_symmetries(model) is syms  # cached
    gt = default_pose()
    est = gt.compose(Pose(exp_so3([0, 0, math.radians(45)]), np.zeros(3)))  # between two coarse samples
    coarse = M.mssd(est.R, est.t, gt.R, gt.t, model.hull_points, model.symmetries)
    fine = M.pose_mssd(est, gt, model)
    # 5 deg off the nearest coarse sample on radius 3 cm: 2 r sin(2.5 deg)
    assert coarse == pytest.approx(2 * 0.03 * math.sin(math.radians(2.5)), rel=1e-6)
    assert fine < M.MAX_SYM_DISC_STEP * model.diameter
    # a tilt off the axis is not a symmetry: MSSD measures it
    tilt = gt.compose(Pose(exp_so3([math.radians(10), 0, 0]), np.zeros(3)))
    assert M.pose_mssd(tilt, gt, model) > 0.005


def test_fast_mssd_and_branch_and_bound_match_brute_force(monkeypatch) -> None:
    rng = np.random.default_rng(3)
    pts = rng.normal(0, 0.05, (700, 3))
    syms = [Pose.identity()] + [Pose(exp_so3(rng.normal(0, 2, 3)), rng.normal(0, 0.01, 3)) for _ in range(80)]
    K = K_LINEMOD
    gt = default_pose()
    gt = Pose(gt.R + rng.normal(0, 1e-3, (3, 3)), gt.t)  # as annotated rotations: not quite orthonormal

    def brute(est: Pose, project: bool) -> float:
        pe = est.transform(pts)
        best = math.inf
        for s in syms:
            pg = gt.compose(s).transform(pts)
            if project:
                pe2, pg2 = (p[:, :2] / p[:, 2:] * [K[0, 0], K[1, 1]] for p in (pe, pg))
                best = min(best, float(np.linalg.norm(pe2 - pg2, axis=1).max()))
            else:
                best = min(best, float(np.linalg.norm(pe - pg, axis=1).max()))
        return best

    for k in range(4):
        est = Pose(exp_so3(rng.normal(0, 1.0, 3)) @ gt.R, gt.t + rng.normal(0, 0.02, 3))
        if k == 3:
            est = gt.compose(syms[17])  # exactly a symmetry
        want_3d, want_px = brute(est, False), brute(est, True)
        for batch in (1_000_000, 5_000):  # direct, then batched branch and bound
            monkeypatch.setattr(M, "_MAX_BATCH", batch)
            assert M.mssd(est.R, est.t, gt.R, gt.t, pts, syms) == pytest.approx(want_3d, abs=1e-8)
            assert M.mspd(est.R, est.t, gt.R, gt.t, K, pts, syms) == pytest.approx(want_px, abs=1e-6)


def test_adi_never_exceeds_add() -> None:
    model = box_model()
    pts = model.points[::6]
    rng = np.random.default_rng(11)
    gt = default_pose()
    for _ in range(40):
        est = Pose(exp_so3(rng.normal(0, 0.5, 3)) @ gt.R, gt.t + rng.normal(0, 0.03, 3))
        e_add = M.add(est.R, est.t, gt.R, gt.t, pts)
        e_adi = M.adi(est.R, est.t, gt.R, gt.t, pts)
        assert 0 <= e_adi <= e_add + 1e-12
        assert e_adi < e_add  # a generic pose: nearest neighbours are closer than correspondences


def test_mspd_of_an_image_plane_shift() -> None:
    fx, z, dx = K_LINEMOD[0, 0], 0.7, 0.01
    gt = Pose(np.eye(3), [0.0, 0.0, z])
    est = Pose(np.eye(3), [dx, 0.0, z])
    plane = np.array([[x, y, 0.0] for x in (-0.03, 0.0, 0.03) for y in (-0.02, 0.02)])  # all at depth z
    assert M.mspd(est.R, est.t, gt.R, gt.t, K_LINEMOD, plane, None) == pytest.approx(fx * dx / z, abs=1e-9)
    # the box corners: the nearest face (depth z - hz) moves the most in the image
    e = M.mspd(est.R, est.t, gt.R, gt.t, K_LINEMOD, CORNERS, None)
    assert e == pytest.approx(fx * dx / (z - HALF[2]), abs=1e-9)
    # a vertical shift uses fy
    est_v = Pose(np.eye(3), [0.0, dx, z])
    assert M.mspd(est_v.R, est_v.t, gt.R, gt.t, K_LINEMOD, plane, None) == pytest.approx(K_LINEMOD[1, 1] * dx / z,
                                                                                          abs=1e-9)
    assert M.mspd(gt.R, gt.t, gt.R, gt.t, K_LINEMOD, CORNERS, None) == 0.0


def test_nan_pose_gives_nan_errors_not_exceptions() -> None:
    gt = default_pose()
    bad = Pose(np.full((3, 3), np.nan), [0, 0, 1])
    e = errors_on_corners(bad, gt)
    assert all(math.isnan(v) for k, v in e.items() if k != "te")
    assert math.isnan(M.mspd(bad.R, bad.t, gt.R, gt.t, K_LINEMOD, CORNERS, FLIPS))


# --------------------------------------------------------------------------- VSD


@pytest.fixture(scope="module")
def box_scene():
    model = box_model()
    gt = default_pose()
    return model, gt, synthetic_frame([model], [gt], seed=4)


def reference_vsd(est: Pose, gt: Pose, depth: np.ndarray, K: np.ndarray, delta: float, taus, model) -> list[float]:
    """bop_toolkit's vsd ("bop19", step cost, normalised), transcribed on full-frame renders."""
    H, W = depth.shape
    d_est = np.nan_to_num(render([model], [est], K, W, H).depth, nan=0.0).astype(np.float64)
    d_gt = np.nan_to_num(render([model], [gt], K, W, H).depth, nan=0.0).astype(np.float64)
    d_test = np.nan_to_num(depth, nan=0.0).astype(np.float64)
    xs, ys = np.meshgrid(np.arange(W), np.arange(H))
    f = np.sqrt(((xs - K[0, 2]) / K[0, 0]) ** 2 + ((ys - K[1, 2]) / K[1, 1]) ** 2 + 1)
    dist_test, dist_gt, dist_est = d_test * f, d_gt * f, d_est * f
    visib_gt = np.logical_and(np.logical_or(dist_gt - dist_test <= delta, dist_test == 0), dist_gt > 0)
    visib_est = np.logical_and(np.logical_or(dist_est - dist_test <= delta, dist_test == 0), dist_est > 0)
    visib_est = np.logical_or(visib_est, np.logical_and(visib_gt, dist_est > 0))
    inter, union = visib_gt & visib_est, visib_gt | visib_est
    if union.sum() == 0:
        return [1.0] * len(taus)
    dists = np.abs(dist_gt[inter] - dist_est[inter]) / model.diameter
    return [(np.sum(dists >= tau) + union.sum() - inter.sum()) / union.sum() for tau in taus]


def test_vsd_zero_at_ground_truth_and_one_far_away(box_scene) -> None:
    model, gt, frame = box_scene
    args = (frame.depth, frame.K, M.VSD_DELTA, M.VSD_TAUS, True, model.diameter, model)
    assert np.all(M.vsd(gt.R, gt.t, gt.R, gt.t, *args) == 0.0)
    far = Pose(gt.R, gt.t + [0.15, 0.0, 0.0])  # in view, no overlap with the object
    np.testing.assert_allclose(M.vsd(far.R, far.t, gt.R, gt.t, *args), 1.0)
    outside = Pose(gt.R, gt.t + [5.0, 0.0, 0.0])  # out of the image
    np.testing.assert_allclose(M.vsd(outside.R, outside.t, gt.R, gt.t, *args), 1.0)
    nan = Pose(np.full((3, 3), np.nan), gt.t)
    np.testing.assert_allclose(M.vsd(nan.R, nan.t, gt.R, gt.t, *args), 1.0)


def test_vsd_depth_shift_depends_on_tau(box_scene) -> None:
    model, gt, frame = box_scene
    est = Pose(gt.R, gt.t + [0.0, 0.0, 0.008])  # 8 mm further away
    taus = [0.001, 0.002, 0.05, 0.2]
    e = M.vsd(est.R, est.t, gt.R, gt.t, frame.depth, frame.K, 0.015, taus, False, model.diameter, model)
    assert np.all(np.diff(e) <= 0)  # a larger tolerance never costs more
    assert e[0] > 0.9  # almost every pixel differs by more than 1 mm
    assert e[-1] < 0.15  # only the silhouette change remains
    tl = M.vsd(est.R, est.t, gt.R, gt.t, frame.depth, frame.K, 0.015, taus, False, model.diameter, model, "tlinear")
    # truncated linear cost min(d / tau, 1) >= step cost [d >= tau]; ~8 mm / 50 mm on the overlap
    assert np.all(tl >= np.asarray(e) - 1e-12) and 0.1 < tl[2] - e[2] < 0.25
    # 3 cm behind: the estimate is hidden by the observed surface, yet where the ground truth is
    # visible the estimate counts as visible too (bop_toolkit's estimate_visib_mask_est)
    behind = Pose(gt.R, gt.t + [0.0, 0.0, 0.03])
    e = M.vsd(behind.R, behind.t, gt.R, gt.t, frame.depth, frame.K, 0.015, [0.01, 0.05], False, model.diameter, model)
    assert e[0] > 0.95 and e[1] < 0.3


def test_vsd_matches_bop_toolkit_transcription_with_occlusion_and_missing_depth(box_scene) -> None:
    model, gt, frame = box_scene
    depth = frame.depth.copy()
    # an occluder 10 cm in front of the object over part of it, and a hole of missing depth
    u0 = int(K_LINEMOD[0, 2] + K_LINEMOD[0, 0] * gt.t[0] / gt.t[2])
    v0 = int(K_LINEMOD[1, 2] + K_LINEMOD[1, 1] * gt.t[1] / gt.t[2])
    depth[v0 - 40:v0 + 40, u0 - 60:u0] = gt.t[2] - 0.1
    depth[v0 - 10:v0 + 30, u0 + 5:u0 + 30] = np.nan
    rng = np.random.default_rng(5)
    for _ in range(3):
        est = Pose(exp_so3(rng.normal(0, 0.05, 3)) @ gt.R, gt.t + rng.normal(0, 0.004, 3))
        got = M.vsd(est.R, est.t, gt.R, gt.t, depth, K_LINEMOD, 0.015, M.VSD_TAUS, True, model.diameter, model)
        want = reference_vsd(est, gt, depth, K_LINEMOD, 0.015, M.VSD_TAUS, model)
        np.testing.assert_allclose(got, want, atol=1e-12)
        assert 0 < got[-1] < got[0] <= 1
    # NaN is missing depth exactly as 0 is for bop_toolkit
    zero = np.where(np.isnan(depth), 0.0, depth).astype(np.float32)
    np.testing.assert_array_equal(
        M.vsd(est.R, est.t, gt.R, gt.t, depth, K_LINEMOD, 0.015, M.VSD_TAUS, True, model.diameter, model),
        M.vsd(est.R, est.t, gt.R, gt.t, zero, K_LINEMOD, 0.015, M.VSD_TAUS, True, model.diameter, model),
    )


def test_vsd_without_depth_counts_the_object_visible(box_scene) -> None:
    model, gt, frame = box_scene
    empty = np.full_like(frame.depth, np.nan)
    assert np.all(M.vsd(gt.R, gt.t, gt.R, gt.t, empty, K_LINEMOD, 0.015, [0.1], True, model.diameter, model) == 0)
    far = Pose(gt.R, gt.t + [0.15, 0.0, 0.0])
    assert M.vsd(far.R, far.t, gt.R, gt.t, empty, K_LINEMOD, 0.015, [0.1], True, model.diameter, model)[0] == 1.0
    # fully hidden behind an occluder: nothing visible, BOP defines the error as 1
    wall = np.full_like(frame.depth, 0.3)
    assert M.vsd(gt.R, gt.t, gt.R, gt.t, wall, K_LINEMOD, 0.015, [0.1], True, model.diameter, model)[0] == 1.0


def test_pose_errors_keys(box_scene) -> None:
    model, gt, frame = box_scene
    est = Pose(gt.R, gt.t + [0.002, 0, 0])
    assert set(M.pose_errors(est, gt, model)) == {"add", "adi", "mssd", "re", "te"}
    e = M.pose_errors(est, gt, model, K=frame.K, depth=frame.depth)
    assert set(e) == {"add", "adi", "mssd", "re", "te", "mspd", "vsd"}
    assert e["vsd"].shape == (len(M.VSD_TAUS),)
    assert e["add"] == pytest.approx(0.002) and e["mssd"] == pytest.approx(0.002)
    with pytest.raises(ValueError, match="needs the camera matrix"):
        M.pose_errors(est, gt, model, depth=frame.depth)


# --------------------------------------------------------------------------- recall


def test_recall_on_hand_made_arrays() -> None:
    np.testing.assert_allclose(M.recall([0.01, 0.02, np.nan, 0.05, np.inf], [0.005, 0.015, 0.05, 1.0]),
                               [0.0, 0.2, 0.4, 0.6])
    np.testing.assert_allclose(M.recall([], [0.1, 0.2]), [0.0, 0.0])


def test_recall_is_strict_like_bop_toolkit() -> None:
    """An error equal to a threshold is a miss (bop_toolkit's pose_matching: error < threshold)."""
    np.testing.assert_array_equal(M.recall([0.1, 0.2], [0.1, 0.2, np.nextafter(0.2, 1.0)]), [0.0, 0.5, 1.0])
    # at the BOP thresholds themselves: e / d exactly 0.05 and MSPD exactly 5 px miss the first
    assert M.average_recall_mssd([0.05], 1.0) == pytest.approx(9 / 10)
    assert M.average_recall_mspd([5.0], 640) == pytest.approx(9 / 10)


def test_average_recalls_on_hand_made_arrays() -> None:
    # e / d = 0.03, 0.22, 0.6: thresholds 0.05..0.2 accept one, 0.25..0.5 accept two
    assert M.average_recall_mssd([0.003, 0.022, 0.06], 0.1) == pytest.approx((4 * 1 + 6 * 2) / 30)
    # per-estimate diameters: the same errors relative to different objects
    assert M.average_recall_mssd([0.003, 0.044, 0.06], [0.1, 0.2, 0.1]) == pytest.approx(16 / 30)
    # width 1280 doubles the thresholds to 10..100 px: 3 px passes 10, 27 px 8, 100 px none (strict)
    assert M.average_recall_mspd([3.0, 27.0, 100.0], 1280) == pytest.approx((10 + 8 + 0) / 30)
    assert M.average_recall_mspd([3.0, 27.0, 100.0], 640) == pytest.approx((10 + 5 + 0) / 30)
    # two estimates x two taus: column 0 recall 0.5 everywhere; column 1 0,0,.5,.5,.5,.5,1,1,1,1
    # (0.3 is not below the threshold 0.3: strict)
    errors = [[0.02, 0.3], [0.6, 0.12]]
    assert M.average_recall_vsd(errors) == pytest.approx((0.5 + 0.6) / 2)
    assert M.average_recall_vsd([[0.0] * 10, [1.0] * 10]) == pytest.approx(0.5)


# --------------------------------------------------------------------------- real LM-O


def test_lmo_ground_truth_and_a_10mm_shift(lmo_frame) -> None:
    frame = lmo_frame
    assert len(frame.objects) == 8
    fx = frame.K[0, 0]
    for obj in frame.objects:
        model, gt = obj.model, obj.gt
        e0 = M.pose_errors(gt, gt, model, K=frame.K, depth=frame.depth)
        for key in ("add", "adi", "mssd", "te", "mspd"):
            assert e0[key] == pytest.approx(0.0, abs=1e-7), (obj.obj_id, key)
        assert e0["re"] == pytest.approx(0.0, abs=1e-6)
        assert np.all(e0["vsd"] == 0.0)
        shifted = Pose(gt.R, gt.t + [0.010, 0.0, 0.0])
        e = M.pose_errors(shifted, gt, model, K=frame.K, depth=frame.depth)
        assert e["add"] == pytest.approx(0.010, abs=1e-9)
        assert e["te"] == pytest.approx(0.010, abs=1e-12)
        assert e["mssd"] == pytest.approx(0.010, abs=1e-9)
        assert e["adi"] < 0.010
        z_min = gt.transform(model.vertices)[:, 2].min()
        assert e["mspd"] == pytest.approx(fx * 0.010 / z_min, rel=1e-9)
        assert np.all(np.diff(e["vsd"]) <= 0) and 0 < e["vsd"][0] <= 1
    # the eggbox (10) and glue (11) are symmetric: their declared symmetry costs no MSSD
    for obj_id in (10, 11):
        obj = frame.object(obj_id)
        assert len(obj.model.symmetries) == 2
        flipped = obj.gt.compose(obj.model.symmetries[1])
        e = M.pose_errors(flipped, obj.gt, obj.model)
        assert e["mssd"] == pytest.approx(0.0, abs=1e-7)
        assert e["add"] > 0.1 * obj.model.diameter and e["re"] > 3.0
