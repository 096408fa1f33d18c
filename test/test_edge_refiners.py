"""D2CO, chamfer matching and chamfer-ICP: the directional chamfer tensor is right, each refiner
reduces the image-plane error of perturbed hypotheses (synthetic and the real LM-O frame), and
bad input gives ok=False with a reason."""
from __future__ import annotations

import numpy as np
import pytest

from frames import box_model, default_pose, refine_perturbed, synthetic_frame
from perception_config.blocks import create
from perception_config.blocks.base import BlockInput
from perception_config.geometry import Pose
from perception_config.render import project
from perception_config.vision.edges import crop_box, directional_chamfer_tensor


def _px_error(model, K, est: Pose, gt: Pose) -> float:
    """Mean image distance (px) of the model's points: what edges can observe."""
    return float(np.mean(np.linalg.norm(project(est.transform(model.points), K)
                                        - project(gt.transform(model.points), K), axis=1)))


def test_directional_chamfer_tensor_distance_and_orientation():
    edges = np.zeros((40, 40), np.uint8)
    edges[20, 5:35] = 255  # a horizontal line: direction 0
    direction = np.zeros((40, 40), np.float32)
    dct = directional_chamfer_tensor(edges, direction, n_bins=60, penalty=0.5, max_distance=30.0)
    assert dct.shape == (60, 40, 40)
    assert dct[0, 20, 20] == 0.0 and dct[0, 25, 20] == pytest.approx(5.0, abs=0.15)
    # Orientation mismatch costs penalty per bin, cyclically: bin 10 and bin 50 are 10 bins away.
    assert dct[10, 20, 20] == pytest.approx(5.0, abs=1e-5) and dct[50, 20, 20] == pytest.approx(5.0, abs=1e-5)
    assert dct[30, 20, 20] == pytest.approx(15.0, abs=1e-5)  # the farthest orientation
    assert dct.max() <= 30.0


def test_crop_box_is_aligned_and_clipped():
    frame = synthetic_frame([box_model()], [default_pose()], seed=0)
    x, y, w, h = crop_box(frame, (100, 50, 60, 40), margin=40, align=32)
    assert x % 32 == 0 and y % 32 == 0 and x <= 60 and y <= 10 and x + w >= 200 and y + h >= 130
    assert (crop_box(frame, (600, 450, 40, 30), margin=40, align=32)[0]
            + crop_box(frame, (600, 450, 40, 30), 40, 32)[2] <= 640)


@pytest.mark.parametrize("name, need", [("d2co", 8), ("chamfer", 8), ("chamfer_icp", 6)])
def test_refiner_reduces_image_error_on_synthetic_frames(name, need):
    model, gt = box_model(), default_pose(0.6)
    frame = synthetic_frame([model], [gt], seed=1)
    improved = 0
    for start, r in refine_perturbed(create(name), frame, model, gt, np.random.default_rng(0)):
        improved += _px_error(model, frame.K, r.pose, gt) < _px_error(model, frame.K, start, gt)
    assert improved >= need, f"{name} improved {improved}/10"


def test_d2co_on_the_real_lmo_frame(lmo_frame):
    frame = lmo_frame
    block, rng, cache = create("d2co"), np.random.default_rng(0), {}
    before, after = [], []
    for obj in frame.objects:
        if obj.visib_fract is None or obj.visib_fract < 0.8:
            continue
        for start, r in refine_perturbed(block, frame, obj.model, obj.gt, rng, n=4, cache=cache, deg=8.0, mm=8.0):
            before.append(_px_error(obj.model, frame.K, start, obj.gt))
            after.append(_px_error(obj.model, frame.K, r.pose, obj.gt))
    assert len(before) >= 8
    improved = np.mean(np.array(after) < np.array(before))
    print(f"LM-O d2co: median px error {np.median(before):.2f} -> {np.median(after):.2f}, improved {improved:.0%}")
    assert improved >= 0.6 and np.median(after) < np.median(before)


@pytest.mark.parametrize("name", ["d2co", "chamfer", "chamfer_icp"])
def test_bad_input_gives_a_reason(name):
    model, gt = box_model(), default_pose()
    frame = synthetic_frame([model], [gt], seed=0)
    block = create(name)
    flat = synthetic_frame([model], [gt], seed=0)
    flat.rgb[:] = 90  # a uniform image: no edges at all
    cases = {
        "no edges": BlockInput(frame=flat, model=model, pose=gt),
        "outside": BlockInput(frame=frame, model=model, pose=Pose(gt.R, [5.0, 0.0, 0.7])),
        "behind": BlockInput(frame=frame, model=model, pose=Pose(gt.R, [0.0, 0.0, -0.7])),
        "nan": BlockInput(frame=frame, model=model, pose=Pose(np.full((3, 3), np.nan), gt.t)),
    }
    for what, inp in cases.items():
        r = block(inp)
        assert not r.ok and r.reason, f"{name} accepted {what}"
