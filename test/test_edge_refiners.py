"""D2CO, chamfer matching and chamfer-ICP: the directional chamfer tensor is right, each refiner
reduces the image-plane error of perturbed hypotheses (synthetic and the real LM-O frame), and
bad input gives ok=False with a reason."""
from __future__ import annotations

import numpy as np
import pytest

from frames import box_model, default_pose, refine_from_lambda, refine_perturbed, synthetic_frame
from perception_config.blocks import create
from perception_config.blocks.base import BlockInput
from perception_config.core.geometry import Pose, perturb
from perception_config.core.metrics import pose_mssd
from perception_config.core.render import project
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



REFINERS = ("d2co", "chamfer", "chamfer_icp")
COST = {"d2co": "d2co_cost", "chamfer": "chamfer_cost", "chamfer_icp": "chamfer_cost"}


@pytest.fixture(scope="module")
def lmo_rgb_frame(lmo_rgb_frames):
    return lmo_rgb_frames[0]


def _visible(frame, least: float = 0.5):
    return [o for o in frame.objects if o.visib_fract is not None and o.visib_fract >= least and o.model is not None]


@pytest.mark.parametrize("name, need", [("d2co", 0.9), ("chamfer", 0.8), ("chamfer_icp", 0.9)])
def test_ground_truth_is_a_fixed_point_on_a_real_photograph(lmo_rgb_frame, name, need):
    """Started at the annotated pose, one call stays within the pick tolerance (MSSD <= 0.1 d)
    (measured over lmo-rgb: d2co ~97 %, chamfer_icp 100 %, chamfer 97 %, 87 % on the holepuncher
    (object 12), whose inner edges let its wide search turn it; chamfer kept 74 % with the plain,
    undirected distance and free out-of-plane rotation, 91 % before its wide search's colour check,
    94 % before that check's margin)."""
    frame, block, cache = lmo_rgb_frame, create(name), {}
    stays = []
    for obj in _visible(frame):
        for seed in range(2):
            r = block(BlockInput(frame=frame, model=obj.model, pose=obj.gt, cache=cache,
                                 rng=np.random.default_rng(seed), time_bounded=False))
            assert r.ok, r.reason
            stays.append(pose_mssd(r.pose, obj.gt, obj.model) <= 0.1 * obj.model.diameter)
    assert len(stays) >= 10
    assert np.mean(stays) >= need, f"{name}: {np.mean(stays):.0%} stayed within tolerance"


@pytest.mark.parametrize("name", ["d2co", "chamfer", "chamfer_icp"])
def test_three_calls_from_the_ground_truth_stay_within_tolerance(lmo_rgb_frame, name):
    """A correct pose is a fixed point of repeated calls too: each call on the previous one's
    output (as an episode does), three calls, the pose stays within the pick tolerance. Over
    lmo-rgb after 3 calls: d2co 98 % (95 % without its accept_margin, the calls creep);
    chamfer_icp 97 % (90 % with an isotropic 15 deg prior: the out-of-image-plane rotation the
    outline barely shows is held); chamfer 96 % (was 70 %, then 89 % before the wide search's colour
    check, 91 % before its margin); the last two weakest on object 12."""
    frame, block, cache = lmo_rgb_frame, create(name), {}
    stays = []
    for obj in _visible(frame):
        pose = obj.gt
        for call in range(3):
            r = block(BlockInput(frame=frame, model=obj.model, pose=pose, cache=cache,
                                 rng=np.random.default_rng(call), time_bounded=False))
            assert r.ok, r.reason
            pose = r.pose
        stays.append(pose_mssd(pose, obj.gt, obj.model) <= 0.1 * obj.model.diameter)
    assert len(stays) >= 5
    assert np.mean(stays) >= 0.8, f"{name}: {np.mean(stays):.0%} within tolerance after 3 calls"


def test_chamfer_improves_perturbed_hypotheses_on_real_photographs(lmo_rgb_frames):
    """From lambda 0.3 the directional chamfer search lowers the mean MSSD and improves at least
    45 % of the calls (about 60 % over all 20 lmo-rgb frames; the plain distance: 41 %)."""
    block, rng = create("chamfer"), np.random.default_rng(0)
    before, after, _ = refine_from_lambda(block, lmo_rgb_frames, _visible, rng, seeds=3)
    print(f"chamfer lambda 0.3: mean MSSD/d {np.mean(before):.3f} -> {np.mean(after):.3f}, "
          f"improved {np.mean(after < before):.0%}")
    assert len(before) >= 30
    assert np.mean(after) < np.mean(before) and np.mean(after < before) >= 0.45  # a no-op: 0 %


def test_d2co_improves_perturbed_hypotheses_on_real_photographs(lmo_rgb_frames):
    """From lambda 0.3 on two real frames the mean MSSD drops and at least 50 % of the calls
    improve it (65 % over all 20 lmo-rgb frames with the region term, 57 % with edges alone)."""
    block, rng = create("d2co"), np.random.default_rng(0)
    before, after, results = refine_from_lambda(block, lmo_rgb_frames, _visible, rng, seeds=3)
    moved = np.array([r.info["improved"] for r in results])
    better = after < before
    print(f"d2co lambda 0.3: mean MSSD/d {np.mean(before):.3f} -> {np.mean(after):.3f}, "
          f"improved {np.mean(better):.0%}, "
          f"moved {np.mean(moved):.0%}, improved when moved {np.mean(better[moved]):.0%}")
    assert len(before) >= 30
    assert np.mean(after) < np.mean(before) and np.mean(better) >= 0.5  # a no-op: 0 %


@pytest.mark.parametrize("name", REFINERS)
def test_a_call_never_returns_a_pose_its_own_cost_judges_worse(lmo_rgb_frame, name):
    frame, block, cache = lmo_rgb_frame, create(name), {}
    rng = np.random.default_rng(1)
    for obj in _visible(frame, 0.3)[:4]:
        for lam in (0.0, 0.1, 0.3, 0.6):
            start = perturb(obj.gt, lam, obj.model.diameter, rng)
            r = block(BlockInput(frame=frame, model=obj.model, pose=start, cache=cache, rng=np.random.default_rng(0)))
            if not r.ok:
                continue
            assert r.scores[COST[name]] <= r.info["cost_before"] + 1e-12
            if not r.info["improved"]:  # the start comes back unchanged
                assert r.pose is start or (np.array_equal(r.pose.R, start.R) and np.array_equal(r.pose.t, start.t))


def _sphere_model():
    """A UV sphere (r = 4 cm): no sharp edges and no inner contour at all."""
    from perception_config.core.models import make_model

    n_lat, n_lon = 12, 24
    th = np.linspace(0, np.pi, n_lat + 1)
    ph = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    v = 0.04 * np.array([[np.sin(a) * np.cos(b), np.sin(a) * np.sin(b), np.cos(a)] for a in th for b in ph])
    faces = []
    for i in range(n_lat):
        for j in range(n_lon):
            a, b = i * n_lon + j, i * n_lon + (j + 1) % n_lon
            c, d = a + n_lon, b + n_lon
            faces += [[a, c, b], [b, c, d]]
    return make_model(7, v, np.array(faces, np.int32))


@pytest.mark.parametrize("name", REFINERS)
def test_hostile_images_and_objects_give_a_reason_within_the_time_bound(name):
    model, gt = box_model(), default_pose()
    frame = synthetic_frame([model], [gt], seed=0)
    block = create(name)
    bright = synthetic_frame([model], [gt], seed=0)
    bright.rgb[:] = 255  # over-exposed: saturated everywhere
    specks = synthetic_frame([model], [gt], seed=0)
    specks.rgb[:] = 254
    specks.rgb[::7, ::5] = 200  # saturated but for a few darker specks (which Canny would find)
    blank = synthetic_frame([model], [gt], seed=0)
    blank.rgb[:] = 90
    far = Pose(gt.R, gt.t * 20.0)  # 14 m away: a few pixels across
    border = Pose(gt.R, gt.t + np.array([0.40, 0.0, 0.0]))  # 5 % of it inside the right image border
    cases = {  # what: (input, a word the reason must contain)
        "over-exposed": (BlockInput(frame=bright, model=model, pose=gt), "over-exposed"),
        "over-exposed with specks": (BlockInput(frame=specks, model=model, pose=gt), "over-exposed"),
        "blank": (BlockInput(frame=blank, model=model, pose=gt), "blank"),
        "tiny crop": (BlockInput(frame=frame, model=model, pose=far), "px"),
        "under 10 % inside the image": (BlockInput(frame=frame, model=model, pose=border), "inside the image"),
    }
    for what, (inp, word) in cases.items():
        r = block(inp)
        assert not r.ok and word in r.reason, f"{name} on {what}: {r.ok} {r.reason!r}"
        assert r.elapsed < block.config["max_seconds"] + 0.05, f"{name} took {r.elapsed:.3f} s on {what}"
        print(f"{name}, {what}: {r.reason}")
    # A model without inner edges (a sphere): refined on its outline, never a crash, within the
    # time bound, and never worse by the block's own cost. chamfer_icp's first contour match takes
    # about its whole 0.1 s budget: the only refusal allowed is the budget's, and without the
    # bound it refines.
    sphere = _sphere_model()
    s_gt = Pose(np.eye(3), [0.0, 0.0, 0.6])
    s_frame = synthetic_frame([sphere], [s_gt], seed=4)
    start = Pose(s_gt.R, s_gt.t + np.array([0.004, -0.003, 0.0]))
    r = block(BlockInput(frame=s_frame, model=sphere, pose=start, rng=np.random.default_rng(0)))
    assert r.elapsed < block.config["max_seconds"] + 0.05
    if not r.ok:
        assert name == "chamfer_icp" and r.reason == "the time budget (0.1 s) ran out before any contour match", \
            f"{name} on a sphere: {r.reason!r}"
        r = block(BlockInput(frame=s_frame, model=sphere, pose=start, rng=np.random.default_rng(0),
                             time_bounded=False))
    assert r.ok, f"{name} on a sphere: {r.reason!r}"
    assert r.scores[COST[name]] <= r.info["cost_before"] + 1e-12
    assert np.linalg.norm(r.pose.t - s_gt.t) <= np.linalg.norm(start.t - s_gt.t) + 1e-3


def _chamfer_from_annotation(root, im_id: int, obj_id: int, seeds: int, **params) -> list[tuple[str, bool]]:
    """chamfer started at the annotation of object `obj_id` on lmo-rgb image `im_id`, once per
    seed (no time bound): (what became of the wide search, whether the pose stayed within the
    pick tolerance) per call."""
    import warnings

    from perception_config.datasets.bop import BopDataset

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        frame = BopDataset(root, use_depth=False).load_frame(2, im_id)
    obj = next(o for o in frame.objects if o.obj_id == obj_id)
    block, cache, outcomes = create("chamfer", max_seconds=10.0, **params), {}, []
    for seed in range(seeds):
        r = block(BlockInput(frame=frame, model=obj.model, pose=obj.gt, cache=cache, rng=np.random.default_rng(seed)))
        assert r.ok, r.reason
        outcomes.append((r.info["wide"], pose_mssd(r.pose, obj.gt, obj.model) <= 0.1 * obj.model.diameter))
    return outcomes


def test_chamfer_wide_search_must_also_separate_colours(lmo_rgb_root):
    """The holepuncher (object 12) on lmo-rgb image 38: started at the annotation, chamfer's wide
    search finds a turned pose whose outline meets more clutter edges; without the colour check
    it is taken and 2 of these 3 calls leave the pick tolerance, with it the check rejects it and
    every call stays (over lmo-rgb, one call from the ground truth: 92 -> 94 % within)."""
    checked = _chamfer_from_annotation(lmo_rgb_root, 38, 12, 3, wide_colour_check=True)
    unchecked = _chamfer_from_annotation(lmo_rgb_root, 38, 12, 3, wide_colour_check=False)
    assert [w for w, _ in checked].count("colour") >= 2, checked
    assert all(stays for _, stays in checked), checked
    assert [stays for _, stays in unchecked].count(False) >= 1, unchecked  # what the check prevents


@pytest.mark.parametrize("im_id, obj_id", [(27, 12), (64, 11)])
def test_chamfer_wide_result_must_separate_colours_clearly_better(lmo_rgb_root, im_id, obj_id):
    """Started at the annotation (the holepuncher on lmo-rgb image 27, the glue on image 64), the
    wide search finds a pose whose outline meets more clutter edges and separates the colours a
    little better too: with no colour margin it is taken and the call leaves the pick tolerance;
    with the default margin (0.08) it is rejected and every call stays (over lmo-rgb, one call
    from the ground truth: 94 -> 97 % within, from lambda 0.1: 92 -> 96 %)."""
    assert create("chamfer").config["wide_colour_margin"] == 0.08
    default = _chamfer_from_annotation(lmo_rgb_root, im_id, obj_id, 2)
    no_margin = _chamfer_from_annotation(lmo_rgb_root, im_id, obj_id, 2, wide_colour_margin=0.0)
    assert all(stays for _, stays in default), default
    assert ("colour", True) in default, default
    assert ("taken", False) in no_margin, no_margin  # what the margin prevents
