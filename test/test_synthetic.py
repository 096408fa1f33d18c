"""The synthetic BOP dataset: format, ground truth, sensor model, determinism, atomicity."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from perception_config.datasets import sensor, synthetic
from perception_config.datasets.synthetic import DEPTH_SCALE, LINEMOD_K, generate

W, H = 640, 480


@pytest.fixture(scope="module")
def bop(synthetic_dataset):
    """The session's synthetic dataset (conftest.py: 2 scenes x 2 images, seed 0) as a BopDataset."""
    from perception_config.datasets.bop import BopDataset

    return BopDataset(synthetic_dataset, "test")


def _rendered_images(bop):
    """Each image of the dataset: its frame, its scene_gt_info entries, and a render of its objects
    alone (no bin)."""
    from perception_config.core.render import render

    for s, i in bop.image_keys():
        f = bop.load_frame(s, i)
        yield f, bop.gt_info(s, i), render([o.model for o in f.objects], [o.gt for o in f.objects], f.K, W, H)


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


# --------------------------------------------------------------------------- format


def test_is_a_complete_bop_dataset(synthetic_dataset, bop):
    assert not (synthetic_dataset / ".incomplete").exists()
    assert not list(synthetic_dataset.parent.glob(f".{synthetic_dataset.name}.incomplete-*"))
    cam = json.loads((synthetic_dataset / "camera.json").read_text())
    assert (cam["width"], cam["height"], cam["depth_scale"]) == (W, H, DEPTH_SCALE)
    assert cam["fx"] == pytest.approx(LINEMOD_K[0, 0])
    assert bop.scene_ids() == [0, 1]
    assert bop.image_keys() == [(0, 0), (0, 1), (1, 0), (1, 1)]
    assert bop.obj_ids() == [1, 2, 3, 4, 5, 6]
    for s in (0, 1):
        for name in ("scene_camera.json", "scene_gt.json", "scene_gt_info.json"):
            assert (synthetic_dataset / "test" / f"{s:06d}" / name).is_file()
    targets = json.loads((synthetic_dataset / "test_targets_bop19.json").read_text())
    assert targets and {"im_id", "obj_id", "scene_id", "inst_count"} <= set(targets[0])
    info = json.loads((synthetic_dataset / "dataset_info.json").read_text())
    assert info["generator"] == synthetic.GENERATOR_NAME


def test_models_eval_holds_the_models_meshes_for_bop_toolkit(synthetic_dataset):
    """bop_toolkit's evaluation loads models_eval/obj_*.ply and models_eval/models_info.json:
    the generator writes the very meshes of models/ there (the project's errors use those)."""
    models, models_eval = synthetic_dataset / "models", synthetic_dataset / "models_eval"
    names = sorted(p.name for p in models_eval.iterdir())
    assert names == sorted([p.name for p in models.glob("obj_*.ply")] + ["models_info.json"])
    for name in names:
        assert (models_eval / name).read_bytes() == (models / name).read_bytes(), name


def test_frames_load_with_sensible_content(bop):
    for s, i in bop.image_keys():
        f = bop.load_frame(s, i)
        assert f.rgb.shape == (H, W, 3) and f.depth.shape == (H, W)
        assert np.allclose(f.K, LINEMOD_K)
        assert bop.camera(s, i).depth_scale == DEPTH_SCALE
        assert bop.camera(s, i).world_to_cam is not None
        ids = [o.obj_id for o in f.objects]
        assert 3 <= len(ids) <= 8 and len(set(ids)) == len(ids)
        valid = np.isfinite(f.depth)
        assert 0.80 < valid.mean() < 1.0  # some missing depth, not much
        assert 0.3 < np.median(f.depth[valid]) < 1.3
        assert f.rgb.std() > 5  # not a blank image
        # depth is quantised to the 1 mm sensor step
        mm = f.depth[valid] * 1000.0
        assert np.abs(mm - np.round(mm)).max() < 1e-2


def test_scenes_keep_their_arrangement_across_views(bop):
    """Images of a scene are viewpoints of one arrangement: model-to-world poses agree."""
    for s in bop.scene_ids():
        world = {}
        for i in bop.image_ids(s):
            w2c = bop.camera(s, i).world_to_cam
            for obj_id, pose in bop.gt(s, i):
                m2w = w2c.inverse().compose(pose)
                if obj_id in world:
                    assert np.allclose(world[obj_id].t, m2w.t, atol=1e-4)
                    assert np.allclose(world[obj_id].R, m2w.R, atol=1e-4)
                world[obj_id] = m2w
        # objects rest on or above the floor (z = 0), none below it
        for obj_id, m2w in world.items():
            z = m2w.transform(bop.model(obj_id).vertices)[:, 2]
            assert z.min() > -1e-4


def test_gt_centres_project_inside_the_image(bop):
    from perception_config.core.render import project

    for s, i in bop.image_keys():
        for obj_id, pose in bop.gt(s, i):
            assert pose.is_valid()
            assert 0.3 < pose.t[2] < 1.3
            u, v = project(pose.t[None], bop.camera(s, i).K)[0]
            assert 0 <= u < W and 0 <= v < H, (s, i, obj_id, u, v)


def test_gt_info_matches_masks(bop):
    """px counts and boxes re-rendered here agree with scene_gt_info; visibility is exact."""
    from perception_config.core.render import render_box
    from perception_config.datasets.bop_writer import compute_gt_info

    diffs = []
    for f, infos, r in _rendered_images(bop):
        bop19 = compute_gt_info(f)  # bop_toolkit's calc_gt_info from the noisy depth
        for k, (o, e) in enumerate(zip(f.objects, infos)):
            assert e["visib_fract"] == pytest.approx(e["px_count_visib"] / e["px_count_all"])
            solo = render_box(o.model, o.gt, f.K, W, H, margin=0)
            n_in = int((solo.mask >= 0).sum())
            assert e["px_count_all"] >= n_in
            assert e["px_count_all"] == bop19[k]["px_count_all"]
            assert e["bbox_obj"] == bop19[k]["bbox_obj"]
            assert e["px_count_valid"] == bop19[k]["px_count_valid"]
            # visible <= visible among the objects alone (the bin walls may hide more)
            assert e["px_count_visib"] <= int((r.mask == k).sum())
            assert e["px_count_valid"] <= n_in
            if e["px_count_visib"]:
                x, y, w, h = e["bbox_visib"]
                bx, by, bw, bh = e["bbox_obj"]
                assert bx <= x and by <= y and x + w <= bx + bw and y + h <= by + bh
            diffs.append(abs(e["visib_fract"] - bop19[k]["visib_fract"]))
    assert np.mean(diffs) < 0.05


# --------------------------------------------------------------------------- sensor model


def _plane(z: float):
    d = np.full((H, W), z, np.float32)
    n = np.zeros((H, W, 3), np.float32)
    n[..., 2] = -1.0
    return d, n


@pytest.mark.parametrize("z", [0.5, 0.8, 1.2])
def test_depth_noise_follows_the_z_model(z):
    d, n = _plane(z)
    out = sensor.simulate_depth(d, n, LINEMOD_K, np.random.default_rng(1))
    r = out[np.isfinite(out)] - z
    expected = np.sqrt(sensor.sigma_z(z) ** 2 + 0.001 ** 2 / 12)  # noise and 1 mm quantisation
    assert np.isnan(out).mean() < 0.01
    assert abs(r.mean()) < 2e-4
    assert r.std() == pytest.approx(expected, rel=0.05)
    assert sensor.sigma_z(0.4) == pytest.approx(0.0012)
    assert sensor.sigma_z(1.4) == pytest.approx(0.0012 + 0.0019)


def test_grazing_angles_lose_depth():
    rays = sensor.pixel_rays(LINEMOD_K, W, H)
    miss = []
    for deg in (40, 70, 85):
        th = np.radians(deg)
        nrm = np.array([np.sin(th), 0.0, -np.cos(th)])
        d = ((nrm @ [0, 0, 0.8]) / (rays @ nrm)).astype(np.float32)
        n = np.broadcast_to(nrm, (H, W, 3)).astype(np.float32)
        out = sensor.simulate_depth(d, n, LINEMOD_K, np.random.default_rng(2))
        miss.append(np.isnan(out[:, 300:340]).mean())
    assert miss[0] < 0.01 and miss[1] < 0.2 and miss[2] > 0.8


def test_shiny_surfaces_lose_more_depth_than_matte():
    d, n = _plane(0.7)
    matte = sensor.simulate_depth(d, n, LINEMOD_K, np.random.default_rng(3), shiny=np.zeros((H, W)))
    shiny = sensor.simulate_depth(d, n, LINEMOD_K, np.random.default_rng(3), shiny=np.ones((H, W)))
    assert np.isnan(shiny).mean() > np.isnan(matte).mean() + 0.08


def test_depth_steps_make_shadows_and_edge_dropout():
    d = np.full((H, W), 0.9, np.float32)
    d[200:280, 300:380] = 0.7  # a box in front of a wall
    n = np.zeros((H, W, 3), np.float32)
    n[..., 2] = -1.0
    out = sensor.simulate_depth(d, n, LINEMOD_K, np.random.default_rng(4))
    shadow_px = 572.4114 * 0.05 * (1 / 0.7 - 1 / 0.9)  # ~9 px left of the box
    band = np.isnan(out[210:270, 300 - int(shadow_px) + 1:300])
    assert band.mean() > 0.95
    assert np.isnan(out[210:270, 381:395]).mean() < 0.1  # no shadow on the projector side


def test_dataset_shiny_parts_miss_more_depth(bop):
    import cv2

    materials = json.loads((bop.models_dir / "parts.json").read_text())
    miss = {"matte": [0, 0], "shiny": [0, 0]}
    for f, infos, r in _rendered_images(bop):
        for k, (o, e) in enumerate(zip(f.objects, infos)):
            if e["visib_fract"] < 0.9:
                continue
            inner = cv2.erode((r.mask == k).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
            m = materials[str(o.obj_id)]["material"]
            miss[m][0] += int(np.isnan(f.depth[inner]).sum())
            miss[m][1] += int(inner.sum())
    frac = {m: a / max(b, 1) for m, (a, b) in miss.items()}
    assert miss["matte"][1] > 0 and miss["shiny"][1] > 0
    assert frac["shiny"] > 2 * frac["matte"], frac


# --------------------------------------------------------------------------- determinism, atomicity


def test_same_seed_same_bytes(synthetic_dataset, tmp_path):
    again = generate(tmp_path / "again", scenes=2, images_per_scene=2, seed=0, progress=False)
    a, b = _files(synthetic_dataset), _files(again)
    assert a.keys() == b.keys()
    different = [k for k in a if a[k] != b[k]]
    assert different == []


def test_other_seed_other_data(synthetic_dataset, tmp_path):
    other = generate(tmp_path / "other", scenes=1, images_per_scene=1, seed=1, progress=False)
    a = (synthetic_dataset / "test/000000/rgb/000000.png").read_bytes()
    assert (other / "test/000000/rgb/000000.png").read_bytes() != a
    # the models are the same parts whatever the seed
    assert ((other / "models/models_info.json").read_bytes()
            == (synthetic_dataset / "models/models_info.json").read_bytes())


def test_interrupted_run_leaves_no_dataset(tmp_path, monkeypatch):
    calls = {"n": 0}
    real = synthetic._render_image

    def failing(*a, **k):
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(synthetic, "_render_image", failing)
    with pytest.raises(KeyboardInterrupt):
        generate(tmp_path / "ds", scenes=1, images_per_scene=3, seed=0, progress=False)
    assert not (tmp_path / "ds").exists()
    assert list(tmp_path.iterdir()) == []


def test_replaces_only_its_own_datasets(tmp_path):
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="refusing"):
        generate(foreign, scenes=1, images_per_scene=1, progress=False)
    assert (foreign / "notes.txt").read_text() == "mine"
    ours = generate(tmp_path / "ours", scenes=1, images_per_scene=1, seed=3, progress=False)
    (ours / "test/000000/rgb/000000.png").write_bytes(b"stale")
    generate(ours, scenes=1, images_per_scene=1, seed=3, progress=False)  # overwrite: fine
    assert (ours / "test/000000/rgb/000000.png").read_bytes() != b"stale"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["foreign", "ours"]
    with pytest.raises(ValueError):
        generate(tmp_path / "x", scenes=0, progress=False)


def test_stable_poses_of_a_box():
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_box(0.1, 0.06, 0.02)
    rots, probs = synthetic.stable_poses(np.asarray(m.vertices), np.asarray(m.triangles))
    assert len(rots) == 6 and probs.sum() == pytest.approx(1.0)
    # the big faces are the likeliest
    down = [np.round(R.T @ [0, 0, -1]).astype(int).tolist() for R in rots]
    big = [probs[k] for k, d in enumerate(down) if abs(d[2]) == 1]
    assert min(big) > max(p for k, p in enumerate(probs) if abs(down[k][2]) != 1)


# --------------------------------------------------------------------------- show, CLI, other models


def test_show_frame_writes_a_two_panel_png(synthetic_dataset, tmp_path):
    import cv2

    from perception_config.datasets.show import show_frame

    out = show_frame(synthetic_dataset, tmp_path / "show.png")
    img = cv2.imread(str(out))
    assert img.shape == (H, 2 * W, 3)
    out2 = show_frame(synthetic_dataset, tmp_path / "sub" / "s.png", scene_id=1, im_id=1)
    assert cv2.imread(str(out2)).shape == (H, 2 * W, 3)
    with pytest.raises(ValueError, match="scene 7"):
        show_frame(synthetic_dataset, tmp_path / "x.png", scene_id=7)
    with pytest.raises(ValueError, match="image 9"):
        show_frame(synthetic_dataset, tmp_path / "x.png", scene_id=0, im_id=9)


def test_cli_synth_and_show(tmp_path, capsys):
    from perception_config.cli import main

    assert main(["synth", "--out", str(tmp_path / "ds"), "--scenes", "1", "--images-per-scene", "1", "--quiet"]) == 0
    assert main(["show", "--dataset", str(tmp_path / "ds"), "--out", str(tmp_path / "s.png")]) == 0
    assert (tmp_path / "s.png").stat().st_size > 10000
    assert main(["show", "--dataset", str(tmp_path / "nope"), "--out", str(tmp_path / "t.png")]) == 2


def test_places_models_of_a_bop_models_folder(lmo_root, tmp_path):
    from perception_config.datasets.bop import BopDataset

    out = generate(tmp_path / "lmo_synth", scenes=1, images_per_scene=1, seed=0,
                   models_dir=lmo_root / "models", progress=False)
    ds = BopDataset(out)
    assert ds.obj_ids() == [1, 5, 6, 8, 9, 10, 11, 12]
    assert (out / "models/models_info.json").read_bytes() == (lmo_root / "models/models_info.json").read_bytes()
    assert (out / "models_eval/obj_000005.ply").read_bytes() == (out / "models/obj_000005.ply").read_bytes()
    f = ds.load_frame(0, 0)
    assert 3 <= len(f.objects) <= 8
    assert all(e["px_count_all"] > 0 for e in ds.gt_info(0, 0))


# --------------------------------------------------------------------------- realism, camera


def test_realism_adds_calibration_and_annotation_errors_and_nothing_else(synthetic_dataset, tmp_path):
    """The same scenes and views; the written ground truth within a few mm and degrees of the true
    pose and the depth offset, warped and shifted against the clean run; seeded."""
    from perception_config.core.geometry import rotation_angle
    from perception_config.datasets.bop import BopDataset
    from perception_config.datasets.realism import Realism

    real = generate(tmp_path / "real", scenes=1, images_per_scene=1, seed=0, progress=False, realism=Realism())
    again = generate(tmp_path / "again", scenes=1, images_per_scene=1, seed=0, progress=False, realism=Realism())
    assert _files(real) == _files(again)
    info = json.loads((real / "dataset_info.json").read_text())
    assert info["realism"]["annotation_mm"] == Realism().annotation_mm
    clean, noisy = BopDataset(synthetic_dataset), BopDataset(real)
    angles, moves, residuals = [], [], []
    for im in (0,):
        a, b = clean.load_frame(0, im), noisy.load_frame(0, im)
        assert (real / f"test/000000/rgb/{im:06d}.png").read_bytes() == \
            (synthetic_dataset / f"test/000000/rgb/{im:06d}.png").read_bytes()  # colour untouched
        for oa, ob in zip(a.objects, b.objects):
            assert oa.obj_id == ob.obj_id
            angles.append(np.degrees(rotation_angle(oa.gt.R, ob.gt.R)))
            moves.append(np.linalg.norm(oa.gt.t - ob.gt.t))
        both = np.isfinite(a.depth) & np.isfinite(b.depth)
        residuals.append(np.median(np.abs(a.depth[both] - b.depth[both])))
    assert 0 < max(angles) < 6 and 0 < max(moves) < 0.015, (angles, moves)
    assert max(residuals) > 5e-4  # offset, warp and shift move the depth by millimetres


def test_realism_ranges_are_checked():
    from perception_config.datasets.realism import Realism

    for bad in ({"depth_bias_mm": -1.0}, {"shift_px": 1.5}, {"noise_scale": (2.0, 1.0)}, {"annotation_deg": np.nan}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            Realism(**bad)


def test_synth_takes_the_camera_of_a_real_dataset(lmo_root, tmp_path, capsys):
    from perception_config.cli import main
    from perception_config.datasets.bop import BopDataset
    from perception_config.datasets.synthetic import camera_from

    K, w, h = camera_from(lmo_root)
    assert (w, h) == (640, 480) and K[0, 0] == pytest.approx(572.4114)
    cam = tmp_path / "camera.json"
    cam.write_text(json.dumps({"fx": 600.0, "fy": 610.0, "cx": 160.0, "cy": 120.0, "width": 320, "height": 240}))
    out = tmp_path / "ds"
    assert main(["synth", "--out", str(out), "--scenes", "1", "--images-per-scene", "1", "--camera", str(cam),
                 "--quiet"]) == 0
    f = BopDataset(out).load_frame(0, 0)
    assert f.rgb.shape[:2] == (240, 320) and f.K[0, 0] == 600.0 and f.K[1, 2] == 120.0
    cam.write_text(json.dumps({"fx": 600.0}))
    assert main(["synth", "--out", str(tmp_path / "bad"), "--camera", str(cam), "--quiet"]) == 2
    assert "camera.json" in capsys.readouterr().out
    assert not (tmp_path / "bad").exists()
