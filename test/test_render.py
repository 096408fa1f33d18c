"""Renderer: analytic depth, occlusion, cropping, and agreement with real LM-O depth."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from perception_config.core.geometry import Pose, exp_so3
from perception_config.core.render import depth_to_points, project, projected_box, render, render_box

K = np.array([[572.4114, 0.0, 325.2611], [0.0, 573.57043, 242.04899], [0.0, 0.0, 1.0]])
W, H = 640, 480


def test_box_facing_camera_has_analytic_depth(make_box) -> None:
    size = (0.1, 0.06, 0.04)
    box = make_box(size)
    pose = Pose(np.eye(3), [0.02, -0.01, 0.8])
    r = render([box], [pose], K, W, H)
    assert r.depth.shape == (H, W) and r.depth.dtype == np.float32
    front = 0.8 - size[2] / 2
    # pixels whose centre projects strictly inside the front face
    corners = np.array([[x, y, front] for x in (-0.05, 0.05) for y in (-0.03, 0.03)]) + [0.02, -0.01, 0]
    uv = project(corners, K)
    u0, v0 = np.ceil(uv.min(axis=0) + 1e-6).astype(int)
    u1, v1 = np.floor(uv.max(axis=0) - 1e-6).astype(int)
    inside = r.depth[v0:v1 + 1, u0:u1 + 1]
    np.testing.assert_allclose(inside, front, atol=1e-6)
    np.testing.assert_allclose(r.normals[v0:v1 + 1, u0:u1 + 1], np.broadcast_to([0, 0, -1], inside.shape + (3,)),
                               atol=1e-6)
    assert np.all(r.mask[v0:v1 + 1, u0:u1 + 1] == 0)
    # background: NaN depth, zero normals, -1 mask; no object pixel outside the projected box
    assert np.isnan(r.depth[0, 0]) and r.mask[0, 0] == -1 and not r.normals[0, 0].any()
    vs, us = np.nonzero(r.mask >= 0)
    assert us.min() >= u0 - 1 and us.max() <= u1 + 1 and vs.min() >= v0 - 1 and vs.max() <= v1 + 1


def test_tilted_box_face_matches_ray_plane_intersection(make_box) -> None:
    size = (0.1, 0.1, 0.1)
    box = make_box(size)
    pose = Pose(exp_so3([0.3, -0.5, 0.2]), [-0.05, 0.03, 0.6])
    r = render([box], [pose], K, W, H)
    ok = np.isfinite(r.depth)
    assert ok.sum() > 1000
    # every hit lies on a face plane: n . X = half size, with n the face's camera-frame normal
    vs, us = np.nonzero(ok)
    n = r.normals[vs, us].astype(np.float64)
    rays = np.stack([us, vs, np.ones_like(us)], 1) @ np.linalg.inv(K).T
    # the analytic depth of each pixel on its face plane: n . (z d) = n . t + h  => z = (n . t + h) / n . d
    axis = np.argmax(np.abs(n @ pose.R), axis=1)  # model axis of the face
    h = np.asarray(size)[axis] / 2
    z = (n @ pose.t + h) / np.einsum("ij,ij->i", n, rays)
    np.testing.assert_allclose(r.depth[vs, us], z, atol=2e-5)


def test_occlusion_between_two_objects(make_box) -> None:
    near, far = make_box((0.08, 0.08, 0.02), 1), make_box((0.08, 0.08, 0.02), 2)
    p_near = Pose(np.eye(3), [0.0, 0.0, 0.5])
    p_far = Pose(np.eye(3), [0.03, 0.0, 0.7])
    r = render([far, near], [p_far, p_near], K, W, H)
    u_near = int(round(project(p_near.t[None], K)[0, 0]))
    v = int(round(K[1, 2]))
    assert r.mask[v, u_near] == 1 and r.depth[v, u_near] == pytest.approx(0.49, abs=1e-6)
    # a pixel right of the near box but on the far one
    u_far = int(round(project(np.array([[0.065, 0.0, 0.69]]), K)[0, 0]))
    assert r.mask[v, u_far] == 0 and r.depth[v, u_far] == pytest.approx(0.69, abs=1e-6)
    # the order of the list does not change the image, only the indices
    r2 = render([near, far], [p_near, p_far], K, W, H)
    np.testing.assert_array_equal(np.isnan(r.depth), np.isnan(r2.depth))
    np.testing.assert_array_equal(np.nan_to_num(r.depth), np.nan_to_num(r2.depth))
    np.testing.assert_array_equal(r.mask[r.mask >= 0], 1 - r2.mask[r2.mask >= 0])


def test_crop_equals_full_render_inside_the_crop(make_box) -> None:
    a, b = make_box((0.1, 0.06, 0.04), 1), make_box((0.05, 0.05, 0.05), 2)
    poses = [Pose(exp_so3([0.4, 0.2, 0.1]), [0.0, 0.0, 0.6]), Pose(exp_so3([0.1, 0.7, 0.0]), [0.04, 0.02, 0.5])]
    full = render([a, b], poses, K, W, H)
    crop = (300, 200, 70, 50)
    r = render([a, b], poses, K, W, H, crop=crop)
    assert r.box == crop and r.offset == (300, 200) and r.depth.shape == (50, 70)
    rs, cs = r.crop_slices()
    np.testing.assert_array_equal(r.mask, full.mask[rs, cs])
    np.testing.assert_array_equal(np.nan_to_num(r.depth, nan=-1), np.nan_to_num(full.depth[rs, cs], nan=-1))
    np.testing.assert_array_equal(r.normals, full.normals[rs, cs])
    back = r.to_full()
    assert back.depth.shape == (H, W) and np.isnan(back.depth[0, 0])
    # a crop hanging over the image border is clipped
    assert render([a], poses[:1], K, W, H, crop=(600, 450, 100, 100)).box == (600, 450, 40, 30)


def test_render_box_covers_the_object(make_box) -> None:
    m = make_box()
    pose = Pose(exp_so3([0.3, 0.3, 0.3]), [0.05, -0.02, 0.7])
    full = render([m], [pose], K, W, H)
    rb = render_box(m, pose, K, W, H)
    rs, cs = rb.crop_slices()
    assert (full.mask >= 0).sum() == (rb.mask >= 0).sum() > 0
    np.testing.assert_array_equal(rb.mask, full.mask[rs, cs])
    assert rb.box == projected_box(m, pose, K, W, H)


def test_rendering_without_normals_has_the_same_depth_and_mask(make_box) -> None:
    a, b = make_box((0.1, 0.06, 0.04), 1), make_box((0.05, 0.05, 0.05), 2)
    poses = [Pose(exp_so3([0.4, 0.2, 0.1]), [0.0, 0.0, 0.6]), Pose(exp_so3([0.1, 0.7, 0.0]), [0.04, 0.02, 0.5])]
    full = render([a, b], poses, K, W, H)
    bare = render([a, b], poses, K, W, H, with_normals=False)
    np.testing.assert_array_equal(bare.mask, full.mask)
    np.testing.assert_array_equal(np.nan_to_num(bare.depth, nan=-1), np.nan_to_num(full.depth, nan=-1))
    assert np.any(full.normals != 0) and not np.any(bare.normals) and bare.normals.shape == full.normals.shape
    box = render_box(a, poses[0], K, W, H, with_normals=False)
    assert box.box == render_box(a, poses[0], K, W, H).box and not box.to_full().normals.any()


def test_objects_outside_the_view(make_box) -> None:
    m = make_box()
    behind = render_box(m, Pose(np.eye(3), [0, 0, -1.0]), K, W, H)
    assert behind.empty and behind.depth.shape == (0, 0)
    aside = render_box(m, Pose(np.eye(3), [5.0, 0, 1.0]), K, W, H)
    assert aside.empty
    # straddling the camera plane: rendered over the whole image, only the part in front
    r = render([m], [Pose(np.eye(3), [0, 0, 0.0])], K, W, H)
    assert np.all(r.depth[np.isfinite(r.depth)] > 0)


def test_project_matches_opencv() -> None:
    pts = np.array([[0.1, -0.05, 0.9], [-0.2, 0.1, 1.5], [0.0, 0.0, 0.3]])
    uv_cv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, None)
    np.testing.assert_allclose(project(pts, K), uv_cv[:, 0], atol=1e-9)
    assert np.all(np.isnan(project(np.array([[0.1, 0.1, -1.0]]), K)))


def test_depth_to_points_lies_on_the_model(make_box) -> None:
    size = np.array([0.1, 0.06, 0.04])
    m = make_box(tuple(size))
    pose = Pose(exp_so3([0.5, -0.3, 0.2]), [0.0, 0.02, 0.5])
    rb = render_box(m, pose, K, W, H)
    pts = pose.inverse().transform(depth_to_points(rb.depth, K, rb.offset))
    # every point is on the box surface: max |coordinate / half-size| == 1
    np.testing.assert_allclose(np.abs(pts / (size / 2)).max(axis=1), 1.0, atol=1e-3)


def test_lmo_ground_truth_render_matches_real_depth(lmo_dataset, lmo_frame) -> None:
    frame = lmo_frame
    r = render([o.model for o in frame.objects], [o.gt for o in frame.objects], frame.K, frame.width, frame.height)
    both = np.isfinite(r.depth) & np.isfinite(frame.depth)
    diff = np.abs(r.depth[both] - frame.depth[both])
    med = float(np.median(diff))
    print(f"LM-O GT render vs real depth: median |diff| {med * 1e3:.2f} mm over {both.sum()} pixels")
    assert both.sum() > 10000
    assert med < 0.010
    # occlusion among the 8 models explains part of BOP's visibility: visible <= ours <= all
    for i, (o, info) in enumerate(zip(frame.objects, lmo_dataset.gt_info(2, 3))):
        ours = int((r.mask == i).sum())
        assert 0.95 * info["px_count_visib"] <= ours <= 1.02 * info["px_count_all"], o.obj_id
        rb = render_box(o.model, o.gt, frame.K, frame.width, frame.height)
        x, y, w, h = o.bbox_visib
        bx, by, bw, bh = rb.box
        assert bx <= x + 2 and by <= y + 2 and bx + bw >= x + w - 2 and by + bh >= y + h - 2
