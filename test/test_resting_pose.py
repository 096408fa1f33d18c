"""`resting_pose` (the cell's generator): the stable faces of a part, the planar alignment, and the generator
on parts lying on a plane: a box turned on a table, the synthetic default's parts (objects on
the table in clutter), the real LM-O frame; symmetric poses of a ppf vote cluster as one."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from frames import box_model, resting_on_plane, synthetic_frame
from perception_config.blocks.base import BlockInput, create
from perception_config.core.geometry import Pose, exp_so3, rotation_to
from perception_config.core.metrics import pose_mssd
from perception_config.core.models import make_model
from perception_config.vision.ppf import canonical_poses
from perception_config.vision.resting_poses import (
    SHIFT_STEPS,
    moved_in_plane,
    planar_icp,
    planar_icp_many,
    planar_shift_step,
    plane_basis,
    resting_poses,
    settled_on_plane,
    sweep_in_plane,
)
from rl_helpers import tiny_dataset

LMO = Path(__file__).resolve().parents[2] / "shared" / "data" / "lmo"
YCBV = LMO.parent / "ycbv-rgbd"


def test_rotation_to_takes_a_onto_b():
    rng = np.random.default_rng(0)
    for _ in range(20):
        a, b = (v / np.linalg.norm(v) for v in rng.normal(size=(2, 3)))
        R = rotation_to(a, b)
        assert np.allclose(R @ a, b) and np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    R = rotation_to(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0]))  # opposite
    assert np.allclose(R @ [0, 0, 1], [0, 0, -1]) and np.isclose(np.linalg.det(R), 1.0)


def test_a_box_rests_on_its_three_face_pairs_largest_first():
    """A 60 x 40 x 20 mm box: three distinct rests (its 180 deg symmetries make opposite faces
    alike), the largest face first, each as high as the box's extent across it."""
    v = np.array([[x, y, z] for x in (-0.03, 0.03) for y in (-0.02, 0.02) for z in (-0.01, 0.01)])
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    flips = [Pose(np.diag(d).astype(float), np.zeros(3)) for d in ([1, -1, -1], [-1, 1, -1], [-1, -1, 1])]
    box = make_model(1, v, f, symmetries=[Pose(np.eye(3), np.zeros(3)), *flips])
    rests = resting_poses(box)
    assert [round(r.height * 1000) for r in rests] == [20, 40, 60]
    assert [round(r.area * 1e4) for r in rests] == [24, 12, 8]  # cm^2
    for r in rests:  # the contact face points down and the centroid is at half the height
        assert np.isclose(r.lift, r.height / 2, atol=1e-4)


def test_an_overhanging_face_is_not_a_rest():
    """A wedge whose sloped face would put the centre of mass outside the face it lies on."""
    v = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.02, 0], [0.1, 0.02, 0], [0, 0, 0.08], [0, 0.02, 0.08]], float)
    f = np.array([[0, 2, 1], [1, 2, 3], [0, 1, 4], [2, 5, 3], [0, 4, 5], [0, 5, 2], [1, 3, 5], [1, 5, 4]])
    wedge = make_model(1, v, f)
    com = wedge.points.mean(axis=0)
    for r in resting_poses(wedge, max_poses=10):
        down = r.R.T @ np.array([0.0, 0.0, -1.0])  # the contact face's outward normal, model frame
        contact = wedge.vertices[np.isclose(wedge.vertices @ down, (wedge.vertices @ down).max(), atol=1e-6)]
        footprint = (contact @ r.R.T)[:, :2]
        c = (r.R @ com)[:2]
        assert footprint[:, 0].min() - 1e-9 <= c[0] <= footprint[:, 0].max() + 1e-9
        assert footprint[:, 1].min() - 1e-9 <= c[1] <= footprint[:, 1].max() + 1e-9


def test_planar_icp_recovers_a_turn_and_a_shift():
    rng = np.random.default_rng(1)
    # an L-shaped set of points (no symmetry in the plane), 1 mm noise
    model = np.concatenate([np.c_[rng.uniform(0, 0.06, 200), rng.uniform(0, 0.01, 200), rng.uniform(0, 0.01, 200)],
                            np.c_[rng.uniform(0, 0.01, 150), rng.uniform(0, 0.04, 150), rng.uniform(0, 0.01, 150)]])
    a = math.radians(9.0)
    Rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    observed = model @ Rz.T + [0.006, -0.004, 0.0] + rng.normal(0, 0.001, model.shape) * [1, 1, 0]
    R, shift = planar_icp(model, observed, 0.02, iterations=30)
    assert abs(math.degrees(math.atan2(R[1, 0], R[0, 0])) - 9.0) < 1.0
    assert np.allclose(shift[:2], [0.006, -0.004], atol=0.001) and shift[2] == 0.0 and np.allclose(R[2], [0, 0, 1])



def test_shift_steps_place_a_partly_hidden_part_under_its_region():
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(2)
    model = np.concatenate([np.c_[rng.uniform(0, 0.06, 200), rng.uniform(0, 0.01, 200), rng.uniform(0, 0.01, 200)],
                            np.c_[rng.uniform(0, 0.01, 150), rng.uniform(0, 0.04, 150), rng.uniform(0, 0.01, 150)]])
    prest = model - model.mean(axis=0)
    Rzs = np.stack([np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
                    for a in (0.0, 2.0, 4.0)])
    p = prest @ Rzs.transpose(0, 2, 1)  # (turns, P, 3)
    truth = np.array([0.012, -0.006, 0.0])
    q = p[0] + truth
    q = q[q[:, 0] < np.percentile(q[:, 0], 60)]  # the far end of the long arm hidden behind something
    vis = np.ones(p.shape[:2], bool)
    shifts = np.zeros((3, 3))
    shifts[:, :2] = q[:, :2].mean(axis=0) - p[..., :2].mean(axis=1)  # centroid on centroid: off by the hidden part
    start = np.linalg.norm(shifts[0, :2] - truth[:2])
    assert start > 0.006
    for _ in range(SHIFT_STEPS):
        shifts[:, :2] += planar_shift_step(p, vis, vis.sum(axis=1), shifts, q, cKDTree(q), prest, cKDTree(prest),
                                           Rzs, 0.02)
    assert np.linalg.norm(shifts[0, :2] - truth[:2]) < 0.75 * start  # measured: 14 -> 9 mm

def test_planar_icp_many_aligns_each_set_as_planar_icp_does_alone():
    """The batch pads the sets to one length: the padding must never match, and a set that
    converges or loses its matches must stop while the others go on."""
    rng = np.random.default_rng(2)
    observed = np.c_[rng.uniform(-0.03, 0.03, (150, 2)), rng.uniform(0.0, 0.02, 150)]
    sets = []
    for n in (60, 150, 90, 7):
        a = rng.uniform(-0.3, 0.3)
        Rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
        sets.append(observed[rng.choice(150, n)] @ Rz.T + rng.normal(0, 0.003, (n, 3)) * [1, 1, 0])
    sets.append(observed[:40] + [1.0, 0.0, 0.0])  # nothing within reach: not moved
    batch = planar_icp_many(sets, observed, 0.02)
    for m, (R, shift) in zip(sets, batch):
        R1, shift1 = planar_icp(m, observed, 0.02)
        assert np.allclose(R, R1, atol=1e-12) and np.allclose(shift, shift1, atol=1e-12)
    assert np.allclose(batch[-1][0], np.eye(3)) and np.allclose(batch[-1][1], 0.0)


def test_canonical_poses_merge_what_the_symmetries_make_alike():
    """A pose and its symmetric twins become one pose (ppf's vote clusters: a 6-fold part's votes
    add up instead of splitting six ways)."""
    sym = [Pose(exp_so3([0.0, 0.0, 2 * math.pi * k / 6]), np.zeros(3)) for k in range(6)]
    R0, t0 = exp_so3([0.3, -0.2, 0.5]), np.array([0.01, 0.02, 0.7])
    R = np.stack([R0 @ s.R for s in sym])
    t = np.stack([t0 + R0 @ s.t for s in sym])
    Rc, tc = canonical_poses(R, t, sym)
    assert np.allclose(Rc, Rc[0]) and np.allclose(tc, tc[0])
    assert np.allclose(canonical_poses(R, t, [])[0], R)  # without symmetries: unchanged


def test_a_box_lying_turned_on_a_table_is_found():
    model = box_model()
    for k, (xy, turn) in enumerate([((0.0, 0.0), 0.3), ((0.03, -0.02), 1.2), ((-0.02, 0.04), 2.6)]):
        gt = resting_on_plane(model, 0.75, xy, turn, rest=k % len(resting_poses(model)))
        frame = synthetic_frame([model], [gt], seed=k, background_z=0.75)
        r = create("resting_pose")(BlockInput(frame=frame, model=model, time_bounded=False))
        assert r.ok, r.reason
        # the box declares no symmetry but has them: the same corners, not the same corner labels
        found, true = r.pose.transform(model.vertices), gt.transform(model.vertices)
        assert np.linalg.norm(true[:, None] - found[None], axis=2).min(axis=1).max() < 0.05 * model.diameter, k
        assert r.candidates[0][1] is r.pose and 0.0 <= r.candidates[0][0] <= 1.0
        if k == 0:  # sweep_stop: a first candidate verifying that well ends the sweep (the box has rivals)
            assert len(r.candidates) >= 2
            swept = {stop: create("resting_pose", sweep_stop=stop)(BlockInput(frame=frame, model=model,
                                                                            time_bounded=False))
                     for stop in (0.0, 1.01)}
            assert swept[0.0].info["swept"] == 1 and swept[1.01].info["swept"] == 2
            assert np.allclose(swept[0.0].pose.matrix(), swept[1.01].pose.matrix(), atol=1e-9)


def test_the_sweep_turns_a_flange_back_onto_its_bolt_holes():
    """A flange lying on the table, hypothesised 20 deg off about the table's normal and 4 mm
    aside: its six-fold symmetric disc agrees with the depth almost as well, only the bolt holes
    tell (ICP leaves such a turn where it is). The sweep's best verifying pose is within MSSD
    0.1 d (the 6-fold symmetry counted); the wrong start is not."""
    from perception_config.core.geometry import MM
    from perception_config.datasets.parts import build_parts
    from perception_config.vision.segmentation import frame_segmentation
    from perception_config.vision.verification import verify

    part = next(p for p in build_parts() if p.name == "flange")
    model = make_model(part.obj_id, part.vertices * MM, part.faces,
                       info={"symmetries_discrete": part.symmetries_discrete})
    assert len(model.symmetries) == 6
    gt = resting_on_plane(model, 0.7, (0.01, -0.02), 0.4, rest=0)
    frame = synthetic_frame([model], [gt], background_z=0.7)
    cache: dict = {}
    seg = frame_segmentation(frame, cache, 0.008)
    B, _ = plane_basis(seg.plane)
    pivot = gt.transform(model.points.mean(axis=0)[None])[0]
    start = moved_in_plane(gt, B, pivot, math.radians(20.0), 0.004, 0.0)

    def score(pose):
        return verify(model, pose, frame, 0.01, seg=seg)[0]

    d = model.diameter
    assert pose_mssd(start, gt, model) > 0.15 * d
    s, found = sweep_in_plane(model, start, score(start), B, score)
    assert s > score(start) and pose_mssd(found, gt, model) <= 0.1 * d, pose_mssd(found, gt, model) / d
    # out of time: the start as it is
    s0, same = sweep_in_plane(model, start, score(start), B, score, deadline=0.0)
    assert s0 == score(start) and np.allclose(same.matrix(), start.matrix())


def test_a_candidate_floating_a_little_is_settled_onto_the_table():
    """A hex nut lying on the table, hypothesised 3 mm above it (a region's top is its edge
    pixels' and the sensor's noise too: 0.1 d, which the pick's MSSD counts in full): moved
    down onto the table, and the verification at a third of the tolerance, which judges the
    move, prefers it there; a gap of a third of the diameter (stacked) is left alone."""
    from perception_config.core.geometry import MM
    from perception_config.datasets.parts import build_parts
    from perception_config.vision.segmentation import frame_segmentation
    from perception_config.vision.verification import verify

    part = next(p for p in build_parts() if p.name == "hexnut")
    model = make_model(part.obj_id, part.vertices * MM, part.faces)
    gt = resting_on_plane(model, 0.7, (0.01, -0.02), 0.4, rest=0)
    frame = synthetic_frame([model], [gt], background_z=0.7)
    seg = frame_segmentation(frame, {}, 0.008)
    up = seg.plane[:3] / np.linalg.norm(seg.plane[:3])
    floating = Pose(gt.R, gt.t + 0.003 * up)
    d = model.diameter
    assert pose_mssd(floating, gt, model) > 0.07 * d
    settled = settled_on_plane(model, floating, seg.plane, 0.2 * d)
    assert settled is not None and pose_mssd(settled, gt, model) < 0.02 * d
    assert verify(model, settled, frame, 0.0033, seg=seg)[0] > verify(model, floating, frame, 0.0033, seg=seg)[0]
    assert settled_on_plane(model, Pose(gt.R, gt.t + 0.3 * d * up), seg.plane, 0.2 * d) is None
    sunk = settled_on_plane(model, Pose(gt.R, gt.t - 0.002 * up), seg.plane, 0.2 * d)
    assert sunk is not None and pose_mssd(sunk, gt, model) < 0.02 * d


def test_a_floating_part_is_no_rest():
    """A part hanging 10 cm above the table matches no stable face on it: ok=False, saying why."""
    model = box_model()
    frame = synthetic_frame([model], [Pose(exp_so3([0.4, 0.2, 0.1]), np.array([0.0, 0.0, 0.6]))], background_z=0.75)
    r = create("resting_pose")(BlockInput(frame=frame, model=model, time_bounded=False))
    assert not r.ok and "resting_pose" in r.reason


def test_the_synthetic_parts_on_the_table(tmp_path_factory):
    """The tiny synthetic dataset (the default's generator: six parts on a table): measured 9 of
    12 visible objects (visib_fract >= 0.3) with a candidate within MSSD 0.1 d in the top 5."""
    from perception_config.datasets.bop import BopDataset

    ds = BopDataset(tiny_dataset(tmp_path_factory), "test")
    block = create("resting_pose")
    found = total = 0
    for scene, im in ds.image_keys()[:2]:
        frame, cache = ds.load_frame(scene, im), {}
        for o in frame.objects:
            if o.visib_fract is not None and o.visib_fract < 0.3:
                continue
            r = block(BlockInput(frame=frame, model=o.model, cache=cache, time_bounded=False))
            total += 1
            found += any(pose_mssd(p, o.gt, o.model) <= 0.1 * o.model.diameter for _, p in r.candidates)
    assert total >= 8 and found >= 0.6 * total, (found, total)


@pytest.mark.skipif(not (LMO / "models" / "models_info.json").exists(), reason="../shared/data/lmo absent")
def test_the_real_lmo_frame():
    """The real LM-O RGB-D frame, 8 objects in clutter: measured 5 of 8 in the top 5 (the duck needs 16 regions)."""
    import warnings

    from perception_config.datasets.bop import BopDataset

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the annotations' SO(3) projection warning
        ds = BopDataset(LMO, "test")
        frame = ds.load_frame(*ds.image_keys()[0])
    block, cache, found = create("resting_pose"), {}, 0
    for o in frame.objects:
        r = block(BlockInput(frame=frame, model=o.model, cache=cache, time_bounded=False))
        found += any(pose_mssd(p, o.gt, o.model) <= 0.1 * o.model.diameter for _, p in r.candidates)
    assert found >= 5, found


@pytest.mark.skipif(not (YCBV / "models" / "models_info.json").exists(), reason="../shared/data/ycbv-rgbd absent")
def test_the_real_ycbv_frames():
    """Real YCB-Video RGB-D frames: the mug stands upright with its handle hidden (its turn shows only
    in what the body hides), the gelatin box touches the keyboard behind it in image 6 (one coarse
    region: the split level parts them). Both in the top 5 (measured: all 10 images, mug 9 of 10)."""
    from perception_config.core.metrics import pose_mssd_derived
    from perception_config.datasets.bop import BopDataset

    ds = BopDataset(YCBV, "test")
    block = create("resting_pose")
    for im_id, obj_id in ((1, 14), (6, 8)):
        frame = ds.load_frame(0, im_id)
        o = next(o for o in frame.objects if o.obj_id == obj_id)
        r = block(BlockInput(frame=frame, model=o.model, time_bounded=False))
        errors = [pose_mssd_derived(p, o.gt, o.model) / o.model.diameter for _, p in r.candidates]
        assert min(errors[:5]) <= 0.1, (im_id, obj_id, errors)
