"""The region-based refiner (blocks/region.py, vision/region.py): the correspondence lines find a
colour transition, the ground truth is a fixed point on a real photograph, perturbed hypotheses
improve (synthetic and real), a call never returns a pose its own cost judges worse, bad
input gives ok=False with a reason within the time bound, and local (per-sector) colour
histograms are local and keep correct poses."""
from __future__ import annotations

import numpy as np

from frames import box_model, default_pose, refine_from_lambda, refine_perturbed, synthetic_frame
from perception_config.blocks import create
from perception_config.blocks.base import BlockInput
from perception_config.core.geometry import Pose, exp_so3, log_so3, perturb
from perception_config.core.metrics import pose_mssd
from perception_config.core.render import project
from perception_config.vision.appearance import band_posterior, outline_bands
from perception_config.vision.region import ColourModel, line_displacements, sector_posterior_map


def _px_error(model, K, est: Pose, gt: Pose) -> float:
    return float(np.mean(np.linalg.norm(project(est.transform(model.points), K)
                                        - project(gt.transform(model.points), K), axis=1)))


def test_lines_find_the_colour_transition():
    """A vertical step of the posterior map 3 px inward of the outline: lines pointing inward
    (+x) report a displacement of ~+3 px, lines pointing outward ~-3 px, a flat map ~0 with a
    large uncertainty."""
    pmap = np.full((40, 60), 0.1, np.float32)
    pmap[:, 33:] = 0.9  # foreground from x = 33 (the transition at 32.5)
    cm = ColourModel(np.zeros(1, np.float32), pmap, (0, 0), 4, 4, np.zeros((40, 60), np.int32))
    uv = np.array([[29.5, 20.0], [29.5, 25.0]])
    d, sd = line_displacements(cm, uv, np.array([[1.0, 0.0], [1.0, 0.0]]), 10)
    assert np.allclose(d, 3.0, atol=0.5) and np.all(sd < 1.5)
    flat = ColourModel(cm.posterior, np.full((40, 60), 0.5, np.float32), (0, 0), 4, 4, cm.codes)
    d, sd = line_displacements(flat, uv, np.array([[1.0, 0.0], [1.0, 0.0]]), 10)
    assert np.allclose(d, 0.0, atol=1e-6) and np.all(sd > 4.0)


def test_region_refiner_reduces_image_error_on_synthetic_frames():
    model, gt = box_model(), default_pose(0.6)
    frame = synthetic_frame([model], [gt], seed=1)
    improved = 0
    for start, r in refine_perturbed(create("region"), frame, model, gt, np.random.default_rng(0)):
        improved += _px_error(model, frame.K, r.pose, gt) < _px_error(model, frame.K, start, gt)
        assert r.scores["region_cost"] <= r.info["cost_before"] + 1e-12
    assert improved >= 8, f"region improved {improved}/10"


def _visible(frame, least: float = 0.5):
    return [o for o in frame.objects if o.visib_fract is not None and o.visib_fract >= least and o.model is not None]


def test_ground_truth_is_a_fixed_point_on_a_real_photograph(lmo_rgb_frames):
    frame, block, cache = lmo_rgb_frames[0], create("region"), {}
    stays = []
    for obj in _visible(frame):
        r = block(BlockInput(frame=frame, model=obj.model, pose=obj.gt, cache=cache, rng=np.random.default_rng(0)))
        assert r.ok, r.reason
        stays.append(pose_mssd(r.pose, obj.gt, obj.model) <= 0.1 * obj.model.diameter)
    assert len(stays) >= 5
    assert np.mean(stays) >= 0.9, f"{np.mean(stays):.0%} stayed within tolerance"


def test_region_refiner_improves_perturbed_hypotheses_on_real_photographs(lmo_rgb_frames):
    """From lambda 0.3 on two real frames the mean MSSD drops and at least half of the calls
    improve it (a no-op: 0 %; ~70 % over lmo-rgb)."""
    block, rng = create("region"), np.random.default_rng(0)
    before, after, _ = refine_from_lambda(block, lmo_rgb_frames, _visible, rng, seeds=2)
    print(f"region lambda 0.3: mean MSSD/d {before.mean():.3f} -> {after.mean():.3f}, "
          f"improved {np.mean(after < before):.0%}")
    assert len(before) >= 20
    assert after.mean() < before.mean() and np.mean(after < before) >= 0.5


def test_a_call_never_returns_a_pose_its_own_cost_judges_worse(lmo_rgb_frames):
    frame, block, cache = lmo_rgb_frames[0], create("region"), {}
    rng = np.random.default_rng(1)
    for obj in _visible(frame, 0.3)[:4]:
        for lam in (0.0, 0.3, 0.6):
            start = perturb(obj.gt, lam, obj.model.diameter, rng)
            r = block(BlockInput(frame=frame, model=obj.model, pose=start, cache=cache, rng=np.random.default_rng(0)))
            if not r.ok:
                continue
            assert r.scores["region_cost"] <= r.info["cost_before"] + 1e-12
            if not r.info["improved"]:  # the start comes back unchanged
                assert r.pose is start


def test_bad_input_gives_a_reason_within_the_time_bound():
    model, gt = box_model(), default_pose()
    frame = synthetic_frame([model], [gt], seed=0)
    block = create("region")
    bright = synthetic_frame([model], [gt], seed=0)
    bright.rgb[:] = 255
    blank = synthetic_frame([model], [gt], seed=0)
    blank.rgb[:] = 90
    cases = {  # what: (input, a word the reason must contain)
        "over-exposed": (BlockInput(frame=bright, model=model, pose=gt), "over-exposed"),
        "blank": (BlockInput(frame=blank, model=model, pose=gt), "blank"),
        "tiny crop": (BlockInput(frame=frame, model=model, pose=Pose(gt.R, gt.t * 20.0)), "px"),
        "under 10 % inside the image": (BlockInput(frame=frame, model=model,
                                                   pose=Pose(gt.R, gt.t + np.array([0.40, 0.0, 0.0]))),
                                        "inside the image"),
        "outside": (BlockInput(frame=frame, model=model, pose=Pose(gt.R, [5.0, 0.0, 0.7])), "outside"),
        "behind": (BlockInput(frame=frame, model=model, pose=Pose(gt.R, [0.0, 0.0, -0.7])), ""),
        "nan": (BlockInput(frame=frame, model=model, pose=Pose(np.full((3, 3), np.nan), gt.t)), ""),
    }
    for what, (inp, word) in cases.items():
        r = block(inp)
        assert not r.ok and r.reason and word in r.reason, f"region on {what}: {r.ok} {r.reason!r}"
        assert r.elapsed < block.config["max_seconds"] + 0.05, f"region took {r.elapsed:.3f} s on {what}"


def _out_of_plane_deg(start: Pose, end: Pose) -> float:
    """The rotation from `start` to `end` off the viewing ray through the object origin (deg)."""
    w = log_so3(end.R @ start.R.T)
    ray = start.t / np.linalg.norm(start.t)
    return float(np.degrees(np.linalg.norm(w - (w @ ray) * ray)))


def test_the_out_of_plane_prior_holds_rotation_off_the_viewing_ray():
    """out_of_plane_prior_deg restrains only the rotation that tilts the object out of the image
    plane: held at 0.5 deg, a call tilts the start by well under a degree, yet still moves it onto
    the image (image-plane position and rotation about the ray stay free); the default 15 deg
    tilts it further."""
    model, gt = box_model(), default_pose(0.6)
    frame = synthetic_frame([model], [gt], seed=1)
    start = Pose(exp_so3(np.radians([6.0, -5.0, 0.0])) @ gt.R, gt.t + [0.008, -0.006, 0.0])
    tilts = {}
    for deg in (0.5, 15.0):
        r = create("region", out_of_plane_prior_deg=deg)(BlockInput(frame=frame, model=model, pose=start,
                                                                    rng=np.random.default_rng(0)))
        assert r.ok and r.info["improved"], r.reason or r.info
        assert _px_error(model, frame.K, r.pose, gt) < 0.7 * _px_error(model, frame.K, start, gt)
        tilts[deg] = _out_of_plane_deg(start, r.pose)
    assert tilts[0.5] < 1.0 and tilts[15.0] > 2.0 * tilts[0.5], tilts


def test_sector_histograms_are_local():
    """A square object of colour 1 whose background has its colour on the left and colour 2 on
    the right: the whole bands' histograms give colour 1 the same posterior (2/3) on both sides;
    per sector it is foreground on the right (nothing outside there shares it) and uncertain
    (~0.5) on the left, and the map has no seam between sectors."""
    codes = np.where(np.arange(80)[None, :] < 40, 1, 2).repeat(80, axis=0).astype(np.int32)
    mask = np.zeros((80, 80), np.uint8)
    mask[25:55, 25:55] = 1
    codes[mask > 0] = 1
    inner, outer = outline_bands(mask, 6)
    whole = band_posterior(codes, inner, outer, 1)
    assert abs(whole[1] - 2 / 3) < 0.01
    pmap = sector_posterior_map(codes, inner, outer, (0, 0), codes, (0, 0), np.array([39.5, 39.5]), 1, 8, 10.0)
    right, left = pmap[40, 52], pmap[40, 27]  # inside the object, 3 px from its right / left edge
    assert right > 0.9 and abs(left - 0.5) < 0.1, (right, left)
    ring = pmap[mask > 0]
    assert ring.min() >= left - 0.05 and ring.max() <= right + 0.05
    assert np.abs(np.diff(pmap[26, 26:54])).max() < 0.1  # along the top edge, across sector borders


def test_sector_histograms_keep_correct_poses_on_real_photographs(lmo_rgb_frames):
    """With local histograms (`sectors` 12) the region refiner keeps the annotated poses of the two
    real frames within tolerance over three calls each (lmo-rgb, 2 seeds: 100 % against 94 % with
    the whole bands' histograms), and still improves perturbed synthetic hypotheses."""
    block = create("region", sectors=12)
    stays = []
    for frame in lmo_rgb_frames:
        cache = {}
        for obj in _visible(frame, 0.3):
            pose = obj.gt
            for call in range(3):
                r = block(BlockInput(frame=frame, model=obj.model, pose=pose, cache=cache,
                                     rng=np.random.default_rng(call), time_bounded=False))
                assert r.ok, r.reason
                pose = r.pose
            stays.append(pose_mssd(pose, obj.gt, obj.model) <= 0.1 * obj.model.diameter)
    assert len(stays) >= 10 and np.mean(stays) >= 0.95, f"{np.mean(stays):.0%} of {len(stays)} stayed"
    model, gt = box_model(), default_pose(0.6)
    frame = synthetic_frame([model], [gt], seed=1)
    improved = sum(_px_error(model, frame.K, r.pose, gt) < _px_error(model, frame.K, start, gt)
                   for start, r in refine_perturbed(block, frame, model, gt, np.random.default_rng(0)))
    assert improved >= 8, f"region with sectors improved {improved}/10"
