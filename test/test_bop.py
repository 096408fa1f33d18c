"""BOP reading and writing: round trips, units, the results CSV, and bad input named clearly."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from frames import box_mesh
from perception_config.core.geometry import Pose, exp_so3
from perception_config.core.models import load_model
from perception_config.core.ply import PlyError, write_ply
from perception_config.core.render import render
from perception_config.core.scene import Frame, SceneObject
from perception_config.datasets.bop import BopDataset
from perception_config.datasets.bop_images import read_depth, read_rgb, write_depth
from perception_config.datasets.bop_json import load_json
from perception_config.datasets.bop_models import load_models_info, write_models_info
from perception_config.datasets.bop_results import BopResult, read_results_csv, write_results_csv
from perception_config.datasets.bop_scene import CameraInfo
from perception_config.datasets.bop_writer import SceneWriter, compute_gt_info, write_frame
from perception_config.datasets.errors import BopAnnotationWarning, BopFormatError

W, H = 160, 120
K = np.array([[150.0, 0.0, 80.5], [0.0, 150.0, 60.5], [0.0, 0.0, 1.0]])
SIZES = {1: (80.0, 50.0, 30.0), 2: (40.0, 40.0, 40.0)}  # mm


def _pose(i: int, k: int) -> Pose:
    return Pose(exp_so3([0.3 * i, 0.2 * k + 0.1, 0.1]), [0.06 * (k - 0.5), 0.01 * i, 0.5 + 0.05 * k])


def make_tiny_dataset(root: Path, scenes: int = 2, images: int = 3) -> Path:
    """A small BOP dataset of two boxes: depth rendered from the models, rgb noise."""
    models_dir = root / "models"
    info = {}
    for obj_id, size in SIZES.items():
        v, f = box_mesh(size)
        write_ply(models_dir / f"obj_{obj_id:06d}.ply", v, f)
        info[obj_id] = {"diameter": float(np.linalg.norm(size)), "min_x": -size[0] / 2, "min_y": -size[1] / 2,
                        "min_z": -size[2] / 2, "size_x": size[0], "size_y": size[1], "size_z": size[2]}
    info[2]["symmetries_discrete"] = [np.diag([-1.0, -1.0, 1.0, 1.0]).reshape(-1).tolist()]
    write_models_info(models_dir, info)
    models = {i: load_model(models_dir / f"obj_{i:06d}.ply", i, load_models_info(models_dir)[i]) for i in SIZES}
    rng = np.random.default_rng(0)
    for s in range(1, scenes + 1):
        with SceneWriter(root, "test", s, depth_scale=0.1) as w:
            for i in range(images):
                objs = [SceneObject(obj_id=o, gt=_pose(i, k), model=models[o]) for k, o in enumerate(SIZES)]
                r = render([o.model for o in objs], [o.gt for o in objs], K, W, H)
                rgb = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
                frame = Frame(rgb, r.depth, K, scene_id=s, im_id=i * 2, objects=objs)
                w.add(frame, gt_info="compute", world_to_cam=Pose(exp_so3([0.0, 0.0, 0.1 * i]), [0.1, 0.0, 0.0]))
    return root


@pytest.fixture()
def tiny(tmp_path: Path) -> Path:
    return make_tiny_dataset(tmp_path / "tiny")


# --------------------------------------------------------------------------- reading


def test_tiny_dataset_reads_back(tiny: Path) -> None:
    ds = BopDataset(tiny)
    assert ds.scene_ids() == [1, 2] and ds.image_ids(1) == [0, 2, 4] and len(ds) == 6
    assert ds.image_keys()[:2] == [(1, 0), (1, 2)]
    f = ds.load_frame(1, 2)
    assert f.rgb.shape == (H, W, 3) and f.depth.dtype == np.float32 and f.stamp == pytest.approx(0.2)
    assert [o.obj_id for o in f.objects] == [1, 2]
    for k, o in enumerate(f.objects):
        np.testing.assert_allclose(o.gt.matrix(), _pose(1, k).matrix(), atol=1e-12)
        assert o.model is ds.model(o.obj_id) and 0.0 < o.visib_fract <= 1.0
    # depth exact at depth_scale 0.1 mm: rendered metres rounded to 0.1 mm
    expected = render([o.model for o in f.objects], [o.gt for o in f.objects], K, W, H).depth
    ok = np.isfinite(expected)
    np.testing.assert_array_equal(np.isfinite(f.depth), ok)
    assert np.abs(f.depth[ok] - expected[ok]).max() <= 0.05e-3 + 1e-6
    assert ds.model(2).is_symmetric and ds.model(1).diameter == pytest.approx(np.linalg.norm(SIZES[1]) / 1000)
    cam = ds.camera(1, 4)
    assert cam.depth_scale == 0.1 and cam.world_to_cam is not None
    np.testing.assert_allclose(cam.world_to_cam.t, [0.1, 0.0, 0.0], atol=1e-12)
    assert [f.im_id for f in ds.frames(with_models=False)] == [0, 2, 4, 0, 2, 4]


def test_lmo_frame_in_metres(lmo_dataset: BopDataset, lmo_frame) -> None:
    ds, f = lmo_dataset, lmo_frame
    assert ds.image_keys() == [(2, 3)]
    assert [o.obj_id for o in f.objects] == [1, 5, 6, 8, 9, 10, 11, 12]
    assert 0.5 < float(np.nanmedian(f.depth)) < 2.0
    assert np.isnan(f.depth).any() and not (f.depth == 0).any()
    np.testing.assert_allclose(f.objects[0].gt.t, [0.16168945982, -0.11374032768, 1.11283112737])
    assert f.objects[0].visib_fract == pytest.approx(0.19964507542147295)
    assert f.objects[0].bbox_visib == (401, 164, 20, 33)
    assert f.objects[5].model.is_symmetric and f.objects[0].model.diameter == pytest.approx(0.102099)
    assert ds.load_frame(2, 3, with_models=False).objects[0].model is None


def test_lmo_scene_round_trip(lmo_root: Path, lmo_dataset: BopDataset, tmp_path: Path) -> None:
    src = lmo_dataset
    out = tmp_path / "copy"
    write_models_info(out / "models", src.models_info)
    for p in (lmo_root / "models").glob("*.ply"):
        shutil.copy(p, out / "models" / p.name)
    for scene_id in src.scene_ids():
        with SceneWriter(out, "test", scene_id) as w:
            for im_id in src.image_ids(scene_id):
                w.add(src.load_frame(scene_id, im_id, with_models=False), gt_info=src.gt_info(scene_id, im_id),
                      depth_scale=src.camera(scene_id, im_id).depth_scale)
    dst = BopDataset(out)
    assert dst.image_keys() == src.image_keys() and dst.models_info == src.models_info
    for scene_id, im_id in src.image_keys():
        a, b = src.load_frame(scene_id, im_id), dst.load_frame(scene_id, im_id)
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_array_equal(a.depth, b.depth)  # NaN == NaN for array_equal
        np.testing.assert_array_equal(a.K, b.K)
        for oa, ob in zip(a.objects, b.objects, strict=True):
            assert oa.obj_id == ob.obj_id and oa.visib_fract == ob.visib_fract and oa.bbox_visib == ob.bbox_visib
            np.testing.assert_allclose(ob.gt.matrix(), oa.gt.matrix(), rtol=0, atol=1e-12)
        assert dst.gt_info(scene_id, im_id) == src.gt_info(scene_id, im_id)
    # the files are BOP: mm, row-major, the same numbers
    ga = load_json(lmo_root / "test/000002/scene_gt.json")["3"]
    gb = load_json(out / "test/000002/scene_gt.json")["3"]
    for ea, eb in zip(ga, gb):
        np.testing.assert_allclose(eb["cam_t_m2c"], ea["cam_t_m2c"], rtol=1e-12)
        # Rotations are projected onto SO(3) when read (LM-O stores them to ~2e-3).
        np.testing.assert_allclose(eb["cam_R_m2c"], ea["cam_R_m2c"], atol=3e-3)
        assert eb["obj_id"] == ea["obj_id"]
    for o in src.load_frame(*src.image_keys()[0], with_models=False).objects:
        np.testing.assert_allclose(o.gt.R @ o.gt.R.T, np.eye(3), atol=1e-12)
    assert not list(out.rglob("*.tmp"))


def test_lmo_compute_gt_info_agrees_with_bop(lmo_dataset: BopDataset, lmo_frame) -> None:
    ours = compute_gt_info(lmo_frame)
    for a, b in zip(ours, lmo_dataset.gt_info(2, 3), strict=True):
        assert a["visib_fract"] == pytest.approx(b["visib_fract"], abs=0.02)
        assert a["px_count_all"] == pytest.approx(b["px_count_all"], rel=0.02)
        assert np.abs(np.subtract(a["bbox_obj"], b["bbox_obj"])).max() <= 2


def test_writer_appends_and_write_frame(tiny: Path) -> None:
    ds = BopDataset(tiny)
    f = ds.load_frame(1, 2)
    f.im_id, f.scene_id = 9, 1
    write_frame(tiny, "test", f, gt_info=ds.gt_info(1, 2), depth_scale=0.1)
    ds2 = BopDataset(tiny)
    assert ds2.image_ids(1) == [0, 2, 4, 9]
    np.testing.assert_array_equal(ds2.load_frame(1, 9).depth, f.depth)
    f.scene_id = 3  # a new scene, jpg (lossy: a smooth image), no gt_info
    f.rgb = np.broadcast_to(np.linspace(0, 255, W, dtype=np.uint8)[None, :, None], (H, W, 3)).copy()
    write_frame(tiny, "test", f, rgb_ext=".jpg")
    g = BopDataset(tiny).load_frame(3, 9)
    assert np.abs(g.rgb.astype(int) - f.rgb).mean() < 3 and BopDataset(tiny).gt_info(3, 9) is None
    # all images of a scene carry gt_info or none do
    with pytest.raises(ValueError, match="scene_gt_info"):
        f.im_id = 10
        write_frame(tiny, "test", f, gt_info=ds.gt_info(1, 2))


def test_gray_rgb_becomes_three_channels(tmp_path: Path) -> None:
    gray = np.arange(12 * 16, dtype=np.uint8).reshape(12, 16)
    cv2.imwrite(str(tmp_path / "g.png"), gray)
    rgb = read_rgb(tmp_path / "g.png")
    assert rgb.shape == (12, 16, 3) and np.all(rgb[:, :, 1] == gray)


def test_results_csv_round_trip(tmp_path: Path) -> None:
    rows = [BopResult(2, 3, 5, 0.75, Pose(exp_so3([0.1, 0.2, 0.3]), [0.01, -0.02, 0.9]), 0.125),
            BopResult(2, 3, 9, 0.5, Pose.identity(), 0.125)]
    p = tmp_path / "res_lmo-test.csv"
    write_results_csv(p, rows)
    lines = p.read_text().splitlines()
    assert lines[0] == "scene_id,im_id,obj_id,score,R,t,time"
    assert lines[1].split(",")[5].split() == ["10.0", "-20.0", "900.0"]  # mm
    back = read_results_csv(p)
    assert [(r.scene_id, r.im_id, r.obj_id, r.score, r.time) for r in back] == \
        [(r.scene_id, r.im_id, r.obj_id, r.score, r.time) for r in rows]
    for a, b in zip(rows, back):
        np.testing.assert_allclose(b.pose.matrix(), a.pose.matrix(), atol=1e-15)
    p.write_text(lines[0] + "\n2,3,5,0.5,1 0 0 0 1 0 0 0,0 0 1,-1\n")
    with pytest.raises(BopFormatError, match="res_lmo-test.csv: line 2"):
        read_results_csv(p)


# --------------------------------------------------------------------------- bad input


def _scene(root: Path) -> Path:
    return root / "test" / "000001"


def _edit_json(path: Path, fn) -> None:
    content = json.loads(path.read_text())
    fn(content)
    path.write_text(json.dumps(content))


def test_corrupt_png_names_the_file(tiny: Path) -> None:
    rgb = _scene(tiny) / "rgb" / "000002.png"
    rgb.write_bytes(rgb.read_bytes()[:200])
    with pytest.raises(BopFormatError, match=r"rgb/000002\.png.*corrupt"):
        BopDataset(tiny).load_frame(1, 2)
    depth = _scene(tiny) / "depth" / "000004.png"
    depth.write_bytes(b"not a png")
    with pytest.raises(BopFormatError, match=r"depth/000004\.png.*corrupt"):
        BopDataset(tiny).load_frame(1, 4)
    (_scene(tiny) / "rgb" / "000000.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"rgb/000000\.png"):
        BopDataset(tiny).load_frame(1, 0)


def test_corrupt_json_names_the_file(tiny: Path) -> None:
    gt = _scene(tiny) / "scene_gt.json"
    gt.write_text(gt.read_text()[:-20])
    with pytest.raises(BopFormatError, match=r"000001/scene_gt\.json: corrupt JSON"):
        BopDataset(tiny).load_frame(1, 2)
    info = tiny / "models" / "models_info.json"
    info.write_text("{\"1\": {\"diameter\": -3}}")
    with pytest.raises(BopFormatError, match=r"models_info\.json: object 1 diameter must be positive"):
        load_models_info(tiny / "models")
    _edit_json(_scene(tiny).parent / "000002" / "scene_gt.json", lambda c: c["0"][0].update(cam_t_m2c=[1, 2]))
    with pytest.raises(BopFormatError, match=r"000002/scene_gt\.json: image 0 object #0 cam_t_m2c must be 3"):
        BopDataset(tiny).load_frame(2, 0)


def test_truncated_ply_names_the_file(tiny: Path) -> None:
    ply = tiny / "models" / "obj_000002.ply"
    ply.write_bytes(ply.read_bytes()[:-10])
    with pytest.raises(PlyError, match=r"obj_000002\.ply.*truncated"):
        BopDataset(tiny).load_frame(1, 2)


def test_rgb_and_depth_of_different_size(tiny: Path) -> None:
    cv2.imwrite(str(_scene(tiny) / "rgb" / "000002.png"), np.zeros((H // 2, W // 2, 3), np.uint8))
    with pytest.raises(BopFormatError, match=r"rgb/000002\.png is 80x60 but .*depth/000002\.png is 160x120"):
        BopDataset(tiny).load_frame(1, 2)


@pytest.mark.parametrize("scale,match", [
    (100.0, r"depth/000002\.png: median depth .* depth_scale 100.0 .*wrong depth_scale"),
    (0.0001, r"depth/000002\.png: median depth .*wrong depth_scale"),
    (0.0, r"scene_camera\.json: image 2 depth_scale 0.0"),
    (-1.0, r"scene_camera\.json: image 2 depth_scale -1.0"),
    (None, r"scene_camera\.json: image 2 has no depth_scale"),
])
def test_wrong_depth_scale(tiny: Path, scale, match: str) -> None:
    def edit(c):
        if scale is None:
            del c["2"]["depth_scale"]
        else:
            c["2"]["depth_scale"] = scale
    _edit_json(_scene(tiny) / "scene_camera.json", edit)
    with pytest.raises(BopFormatError, match=match):
        BopDataset(tiny).load_frame(1, 2)


def test_depth_scale_from_camera_json(tiny: Path) -> None:
    _edit_json(_scene(tiny) / "scene_camera.json", lambda c: c["2"].pop("depth_scale"))
    (tiny / "camera.json").write_text(json.dumps({"depth_scale": 0.1}))
    assert np.isfinite(BopDataset(tiny).load_frame(1, 2).depth).any()


def test_write_depth_refuses_overflow(tmp_path: Path) -> None:
    d = np.full((4, 4), 7.0, np.float32)
    with pytest.raises(ValueError, match=r"d\.png: depth up to 7\.000 m overflows uint16 at depth_scale 0\.1"):
        write_depth(tmp_path / "d.png", d, 0.1)
    write_depth(tmp_path / "d.png", d, 1.0)
    np.testing.assert_array_equal(read_depth(tmp_path / "d.png", 1.0), d)


def test_unknown_object_and_image_ids(tiny: Path) -> None:
    ds = BopDataset(tiny)
    with pytest.raises(BopFormatError, match=r"models_info\.json: unknown object id 99"):
        ds.model(99)
    with pytest.raises(BopFormatError, match=r"000001/scene_camera\.json: no image 7"):
        ds.load_frame(1, 7)
    with pytest.raises(FileNotFoundError, match=r"test/000005"):
        ds.load_frame(5, 0)
    _edit_json(_scene(tiny) / "scene_gt.json", lambda c: c["2"][1].update(obj_id=42))
    with pytest.raises(BopFormatError, match="unknown object id 42"):
        BopDataset(tiny).load_frame(1, 2)
    assert BopDataset(tiny).load_frame(1, 2, with_models=False).objects[1].obj_id == 42
    with pytest.raises(FileNotFoundError, match="nowhere"):
        BopDataset(tiny / "nowhere")


def test_gt_info_must_align_with_gt(tiny: Path) -> None:
    _edit_json(_scene(tiny) / "scene_gt_info.json", lambda c: c["4"].pop())
    with pytest.raises(BopFormatError, match=r"scene_gt_info\.json: image 4 has 1 entries but scene_gt\.json 2"):
        BopDataset(tiny).load_frame(1, 4)


def test_writer_gt_info_length_checked(tiny: Path) -> None:
    f = BopDataset(tiny).load_frame(1, 0)
    with SceneWriter(tiny, "test", 1) as w, pytest.raises(ValueError, match="1 gt_info entries for 2 objects"):
        w.add(f, gt_info=[{}])
    # the models_info writer validates too
    with pytest.raises(BopFormatError, match="symmetries_discrete"):
        write_models_info(tiny / "models", {1: {"diameter": 1.0, "symmetries_discrete": [[1, 0, 0]]}})
    assert CameraInfo(K).depth_scale is None


# --------------------------------------------------------------------------- real annotations, RGB-only


def _skew_first_rotation(scene: Path, err: float) -> None:
    """Scale the first cam_R_m2c of image 2 so that |det - 1| is about 3 * err."""
    def edit(c):
        c["2"][0]["cam_R_m2c"] = (np.asarray(c["2"][0]["cam_R_m2c"]) * (1.0 + err)).tolist()
    _edit_json(scene / "scene_gt.json", edit)


def test_nearly_orthonormal_rotations_are_projected_with_one_warning(tiny: Path) -> None:
    _skew_first_rotation(_scene(tiny), 0.01)  # |det - 1| ~ 0.03, as real annotations (LM-O: 0.014)
    with pytest.warns(BopAnnotationWarning) as caught:
        f = BopDataset(tiny).load_frame(1, 2)
    msgs = [str(w.message) for w in caught if issubclass(w.category, BopAnnotationWarning)]
    assert len(msgs) == 1 and "000001/scene_gt.json" in msgs[0] and "image 2 object #0" in msgs[0]
    assert "0.03" in msgs[0]  # the worst value, named
    R = f.objects[0].gt.R
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(R, _pose(1, 0).R, atol=1e-9)  # a uniform scale projects back exactly


def test_rotations_beyond_the_tolerance_are_refused(tiny: Path) -> None:
    _skew_first_rotation(_scene(tiny), 0.02)  # |det - 1| ~ 0.06 > 0.05
    with pytest.raises(BopFormatError, match=r"000001/scene_gt\.json: image 2 object #0 cam_R_m2c is not a rotation"):
        BopDataset(tiny).load_frame(1, 2)


def test_rgb_only_scene_and_dropping_depth(tiny: Path) -> None:
    with_depth = BopDataset(tiny).load_frame(1, 2)
    dropped = BopDataset(tiny, use_depth=False).load_frame(1, 2)
    assert with_depth.has_depth and not dropped.has_depth and dropped.depth is None
    np.testing.assert_array_equal(dropped.rgb, with_depth.rgb)
    assert (dropped.width, dropped.height) == (W, H)
    shutil.rmtree(_scene(tiny) / "depth")  # a BOP RGB-only scene has no depth folder
    f = BopDataset(tiny).load_frame(1, 2)
    assert f.depth is None and [o.obj_id for o in f.objects] == [1, 2]


def test_missing_depth_file_in_a_depth_scene_is_an_error(tiny: Path) -> None:
    (_scene(tiny) / "depth" / "000002.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"depth/000002\.png"):
        BopDataset(tiny).load_frame(1, 2)


def test_lmo_rgb_loads_without_depth(lmo_rgb_root: Path) -> None:
    ds = BopDataset(lmo_rgb_root)
    assert len(ds) == 20
    f = ds.load_frame(*ds.image_keys()[0])
    assert f.depth is None and f.rgb.shape == (480, 640, 3) and len(f.objects) == 8


def test_cli_names_a_repaired_annotation_in_one_line(tiny: Path, tmp_path: Path, capsys) -> None:
    import warnings

    from perception_config.cli import main

    _skew_first_rotation(_scene(tiny), 0.01)
    saved = warnings.showwarning
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            assert main(["show", "--dataset", str(tiny), "--out", str(tmp_path / "f.png")]) == 0
    finally:
        warnings.showwarning = saved
    err = [line for line in capsys.readouterr().err.splitlines() if line]
    assert len(err) == 1 and err[0].startswith("warning: ") and "000001/scene_gt.json" in err[0], err
