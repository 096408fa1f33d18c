"""Edge features: the directional chamfer tensor is the exact cyclic min-plus of the per-bin
distance transforms, its interpolation and gradient are consistent, gradients and the
per-frame tensor cache behave."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from frames import box_model, default_pose, synthetic_frame
from perception_config.core.scene import Frame
from perception_config.vision.edges import TensorCache, directional_chamfer_tensor, image_gradients, sample_tensor


def test_tensor_is_the_cyclic_min_over_orientation_bins():
    rng = np.random.default_rng(1)
    h, w, n, pen, cap = 30, 40, 12, 0.7, 10.0
    edges = np.zeros((h, w), np.uint8)
    edges.flat[rng.integers(0, h * w, 25)] = 255
    direction = rng.uniform(0, np.pi, (h, w)).astype(np.float32)
    dct = directional_chamfer_tensor(edges, direction, n, pen, cap)
    ys, xs = np.nonzero(edges)
    bins = np.minimum((direction[ys, xs] * n / np.pi).astype(int), n - 1)
    base = np.full((n, h, w), cap, np.float32)
    for b in set(bins.tolist()):
        img = np.full((h, w), 255, np.uint8)
        img[ys[bins == b], xs[bins == b]] = 0
        base[b] = np.minimum(cv2.distanceTransform(img, cv2.DIST_L2, 5), cap)
    ref = np.stack([np.min([base[q] + pen * min(abs(b - q), n - abs(b - q)) for q in range(n)], axis=0)
                    for b in range(n)])
    np.testing.assert_allclose(dct, np.minimum(ref, cap), atol=1e-5)


def test_sampling_is_cyclic_in_orientation_and_its_gradient_matches_finite_differences():
    edges = np.zeros((50, 50), np.uint8)
    edges[25, 5:45] = 255
    edges[5:45, 10] = 255
    direction = np.zeros((50, 50), np.float32)
    direction[:, 10] = np.pi / 2
    dct = directional_chamfer_tensor(edges, direction, 60, 0.5, 30.0)
    x, y = np.array([20.3, 31.7]), np.array([21.6, 28.2])
    # orientation is modulo pi: just above 0 and just below pi interpolate the same two bins
    a = sample_tensor(dct, x, y, np.array([0.01, 0.01]), 30.0)
    b = sample_tensor(dct, x, y, np.array([np.pi - 0.01, np.pi - 0.01]), 30.0)
    assert np.all(np.abs(a - b) < 0.6)  # 0.02 rad apart: well within one bin's penalty
    # 3.6 px from the horizontal line at the centre of its bin: 3.6 px; at orientation 0 (halfway
    # between bins 59 and 0) half a bin's penalty more; vertical: the vertical line 10 px away
    # wins over the horizontal one plus 30 bins' penalty (3.6 + 15)
    at = lambda a: sample_tensor(dct, np.array([20.0]), np.array([21.4]), np.array([a]), 30.0)[0]  # noqa: E731
    assert at(np.pi / 120) == pytest.approx(3.6, abs=0.2)
    assert at(0.0) == pytest.approx(3.85, abs=0.2)
    assert at(np.pi / 120 + np.pi / 2) == pytest.approx(10.0, abs=0.2)
    assert at(np.pi / 120 + np.pi / 4) == pytest.approx(min(3.6 + 7.5, 10.0 + 7.5), abs=0.3)
    v, gx, gy = sample_tensor(dct, x, y, np.array([0.2, 1.3]), 30.0, gradient=True)
    eps = 1e-5
    vx = sample_tensor(dct, x + eps, y, np.array([0.2, 1.3]), 30.0)
    vy = sample_tensor(dct, x, y + eps, np.array([0.2, 1.3]), 30.0)
    np.testing.assert_allclose(gx, (vx - v) / eps, atol=1e-3)
    np.testing.assert_allclose(gy, (vy - v) / eps, atol=1e-3)
    assert abs(gy[0]) > 0.5  # above the horizontal line, moving down gets closer
    out = sample_tensor(dct, np.array([-5.0, np.nan]), np.array([3.0, 3.0]), np.array([0.0, 0.0]), 30.0, gradient=True)
    assert np.all(out[0] == 30.0) and np.all(out[1] == 0) and np.all(out[2] == 0)


def test_image_gradients_of_a_vertical_step():
    rgb = np.zeros((40, 60, 3), np.uint8)
    rgb[:, 30:] = 200
    frame = Frame(rgb=rgb, depth=np.full((40, 60), np.nan, np.float32), K=np.eye(3))
    cache: dict = {}
    mag, ang = image_gradients(frame, cache)
    assert mag.shape == (40, 60) and mag.dtype == np.float32
    assert mag[20, 29:31].min() > 20 and mag[20, 5] == 0
    assert abs(ang[20, 30]) < 1e-3  # gradient points to +x (dark to bright)
    assert image_gradients(frame, cache)[0] is mag  # cached per frame


def test_tensor_cache_reuses_the_same_crop_and_reports_empty_edges():
    model, pose = box_model(), default_pose()
    frame = synthetic_frame([model], [pose], seed=0)
    cache: dict = {}
    args = dict(margin=40, n_bins=60, penalty=0.5, max_distance=30.0, low=40.0, high=100.0)
    dct, crop, n = TensorCache.get(frame, cache, (300, 200, 60, 50), **args)
    assert n > 0 and dct.shape == (60, crop[3], crop[2])
    assert crop[0] <= 260 and crop[1] <= 160 and crop[0] + crop[2] >= 400 and crop[1] + crop[3] >= 290
    dct2, crop2, _ = TensorCache.get(frame, cache, (305, 204, 60, 50), **args)  # moved a few px
    assert dct2 is dct and crop2 == crop
    dct3, crop3, _ = TensorCache.get(frame, cache, (40, 40, 60, 50), **args)  # elsewhere
    assert dct3 is not dct and crop3 != crop
    # A box inside the first crop but with a crop of its own gets its own tensor, the one a
    # fresh cache builds: what a call returns does not depend on what was asked before.
    dct5, crop5, _ = TensorCache.get(frame, cache, (330, 220, 20, 20), **args)
    fresh, crop6, _ = TensorCache.get(frame, {}, (330, 220, 20, 20), **args)
    assert crop5 == crop6 != crop and dct5 is not dct and np.array_equal(dct5, fresh)
    frame.rgb[:] = 90
    flat = Frame(rgb=frame.rgb.copy(), depth=frame.depth, K=frame.K)
    dct4, _, n4 = TensorCache.get(flat, cache, (300, 200, 60, 50), **args)
    assert dct4 is None and n4 == 0


def test_edge_coherence_keeps_straight_edges_and_drops_zigzag_ones():
    import dataclasses

    from perception_config.vision.edges import edge_coherence

    model = box_model()
    assert edge_coherence(model).mean() > 0.95  # a box: long straight edges
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=model.edge_dirs.shape)
    noisy = dataclasses.replace(model, edge_dirs=dirs / np.linalg.norm(dirs, axis=1, keepdims=True))
    assert edge_coherence(noisy).mean() < 0.8  # directions at random: a scanned mesh's "sharp" edges


@pytest.mark.parametrize("loss", ["huber", "geman_mcclure", "tukey"])
def test_robust_weights_are_the_derivative_of_the_loss_over_the_residual(loss):
    from perception_config.vision.pose_solver import robust_rho, robust_weights

    r = np.array([-7.0, -2.5, -0.3, 0.4, 1.9, 2.1, 6.0])
    eps = 1e-6
    deriv = (robust_rho(r + eps, loss, 2.0) - robust_rho(r - eps, loss, 2.0)) / (2 * eps)
    np.testing.assert_allclose(robust_weights(r, loss, 2.0) * r, deriv, atol=1e-5)
    np.testing.assert_allclose(robust_rho(np.array([1e-3]), loss, 2.0), 0.5e-6, rtol=1e-3)  # 0.5 r^2 near 0
    if loss != "huber":  # redescending: a far point hardly pulls (Tukey: not at all)
        assert robust_weights(np.array([10.0]), loss, 2.0)[0] < 0.01


def test_crop_problem_names_tiny_blank_and_over_exposed_crops():
    from perception_config.vision.edges import crop_problem

    frame = synthetic_frame([box_model()], [default_pose()], seed=0)
    assert crop_problem(frame, (250, 180, 120, 100)) == ""
    assert "px" in crop_problem(frame, (300, 200, 5, 40))
    frame.rgb[:] = 255
    assert "over-exposed" in crop_problem(frame, (250, 180, 120, 100))
    frame.rgb[:] = 90
    assert "blank" in crop_problem(frame, (250, 180, 120, 100))
