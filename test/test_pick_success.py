"""The learned pick-success score: features, the model file, the block, fit-score, real frames."""
from __future__ import annotations

import json
import math
import pickle
import time

import numpy as np
import pytest

from perception_config.blocks.base import BlockInput, create
from perception_config.blocks.features import pick_features
from perception_config.blocks.pipeline import PipelineError, load_pipeline, pipeline_from_dict
from perception_config.core.geometry import Pose, perturb
from perception_config.core.metrics import pose_mssd
from perception_config.core.score_metrics import auc, score_metrics
from perception_config.datasets.bop import BopDataset
from perception_config.learning.pick_success_data import featurise, pick_label
from perception_config.vision.pick_features import FEATURE_NAMES, NEEDS_DEPTH, rgb_only
from perception_config.vision.pick_success_model import (
    MODEL_FILE,
    PickSuccessModel,
    PickSuccessModelError,
    encode,
    fit_mlp,
    fit_platt,
    robust_scaling,
)


def _shifted(pose: Pose, dx: float) -> Pose:
    return Pose(pose.R.copy(), pose.t + np.array([dx, 0.0, 0.0]))


@pytest.fixture(scope="module")
def tiny_frame(synthetic_dataset):
    ds = BopDataset(synthetic_dataset)
    frame = ds.load_frame(*ds.image_keys()[0])
    objs = [o for o in frame.objects if o.model is not None and o.gt is not None]
    return frame, objs


def test_features_finite_and_a_gt_pose_beats_a_3cm_shift(tiny_frame):
    frame, objs = tiny_frame
    cache: dict = {}
    ms = []
    for obj in objs[:3]:
        t0 = time.perf_counter()
        at_gt = pick_features(frame, obj.model, obj.gt, cache)
        ms.append(1e3 * (time.perf_counter() - t0))
        off = pick_features(frame, obj.model, _shifted(obj.gt, 0.03), cache)
        assert tuple(at_gt) == FEATURE_NAMES
        assert all(math.isfinite(v) for v in at_gt.values()), at_gt  # an RGB-D frame: every feature there
        assert at_gt["depth_inlier_02"] > off["depth_inlier_02"]
        assert at_gt["depth_abs_median"] < off["depth_abs_median"]
        assert at_gt["edge_distance"] < off["edge_distance"]
        assert at_gt["psi_d"] > off["psi_d"]
        blank = rgb_only(at_gt)
        assert all(math.isnan(blank[n]) for n in NEEDS_DEPTH)
        assert all(blank[n] == at_gt[n] for n in FEATURE_NAMES if n not in NEEDS_DEPTH)
        as_rgb = pick_features(frame, obj.model, obj.gt, None, use_depth=False)
        assert all(math.isnan(as_rgb[n]) for n in NEEDS_DEPTH)
        assert all(math.isfinite(as_rgb[n]) for n in FEATURE_NAMES if n not in NEEDS_DEPTH)
    print(f"pick_features: {np.median(ms):.1f} ms per call (median, first call of a pose)")


def test_labels_follow_the_pick_criterion(tiny_frame):
    _, objs = tiny_frame
    obj = objs[0]
    d = obj.model.diameter
    ok, share = pick_label(obj.model, obj.gt, [obj.gt])
    assert ok and share == pytest.approx(0.0, abs=1e-6)
    far = _shifted(obj.gt, 0.2 * d)
    ok, share = pick_label(obj.model, far, [obj.gt])
    assert not ok and share == pytest.approx(pose_mssd(far, obj.gt, obj.model) / d)
    # of two instances of the object the nearer decides
    assert pick_label(obj.model, far, [obj.gt, far])[0]


def _small_model(seed: int = 0) -> tuple[PickSuccessModel, np.ndarray]:
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(200, len(FEATURE_NAMES)))
    X[::7, 3] = np.nan
    y = X[:, 0] + 0.3 * rng.normal(size=200) > 0
    med, spread = robust_scaling(X)
    layers = fit_mlp(encode(X, med, spread), y, hidden=(8,), epochs=150, seed=seed)
    model = PickSuccessModel(FEATURE_NAMES, med, spread, layers)
    model.calibration = fit_platt(model.logit(X), y)
    return model, X


def test_model_round_trip_without_pickle(tmp_path, monkeypatch):
    model, X = _small_model()
    p = model.predict(X)
    assert np.all((p >= 0) & (p <= 1)) and auc(p, X[:, 0] > 0) > 0.9
    path = model.save(tmp_path / MODEL_FILE)

    def no_pickle(*a, **k):
        raise AssertionError("the model file must load without unpickling")

    monkeypatch.setattr(pickle, "load", no_pickle)
    monkeypatch.setattr(pickle, "loads", no_pickle)
    back = PickSuccessModel.load(tmp_path)  # the folder fit-score writes is accepted too
    np.testing.assert_allclose(back.predict(X), p, rtol=1e-6, atol=1e-7)
    assert back.feature_names == FEATURE_NAMES and back.calibration == model.calibration
    assert path.read_bytes()[8:9] == b"{"  # a safetensors file: length, then its JSON header


def test_corrupt_missing_and_mismatched_model_files_are_refused(tmp_path):
    model, _ = _small_model()
    path = model.save(tmp_path / "m.safetensors")
    data = bytearray(path.read_bytes())
    with pytest.raises(PickSuccessModelError, match="does not exist"):
        PickSuccessModel.load(tmp_path / "nothing.safetensors")
    bad = tmp_path / "flipped.safetensors"
    data[-3] ^= 0xFF  # a weight changed after writing
    bad.write_bytes(bytes(data))
    with pytest.raises(PickSuccessModelError, match="checksum"):
        PickSuccessModel.load(bad)
    cut = tmp_path / "cut.safetensors"
    cut.write_bytes(path.read_bytes()[:40])
    with pytest.raises(PickSuccessModelError, match="corrupt"):
        PickSuccessModel.load(cut)
    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(b"\x00" * 64)
    with pytest.raises(PickSuccessModelError):
        PickSuccessModel.load(junk)
    other = PickSuccessModel(FEATURE_NAMES[:-1] + ("colour_of_the_sky",), model.median, model.spread, model.layers)
    other_path = other.save(tmp_path / "other.safetensors")
    with pytest.raises(PickSuccessModelError, match="other features.*colour_of_the_sky.*fit-score"):
        PickSuccessModel.load(other_path)
    # the block and a pipeline that names a bad model are refused when built, naming the file
    with pytest.raises(ValueError, match="needs a model"):
        create("pick_success", model="")
    spec = {"generator": "simulated_init", "actions": [{"name": "pick", "block": "simulated_pick"}],
            "scoring": [{"block": "pick_success", "params": {"model": str(bad)}}]}
    with pytest.raises(PipelineError, match="flipped.safetensors.*checksum"):
        pipeline_from_dict(spec, "test.yaml")


def test_the_shipped_pipeline_scores_a_frame(tiny_frame):
    pipeline = load_pipeline("pick_success")
    assert pipeline.score_names[-1] == "pick_success"
    block = pipeline.scoring[-1]
    frame, objs = tiny_frame
    at_gt, off = [], []
    for obj in objs:
        cache: dict = {}
        r = block(BlockInput(frame=frame, model=obj.model, pose=obj.gt, cache=cache))
        assert r.ok and 0.0 <= r.scores["pick_success"] <= 1.0, r.reason
        at_gt.append(r.scores["pick_success"])
        r = block(BlockInput(frame=frame, model=obj.model, pose=_shifted(obj.gt, 0.03), cache=cache))
        off.append(r.scores["pick_success"])
    assert np.mean(at_gt) > 0.7 and np.mean(off) < 0.3, (at_gt, off)
    assert np.mean(np.array(at_gt) > np.array(off)) >= 0.9


def test_fit_score_on_a_tiny_dataset(synthetic_dataset, tmp_path, capsys):
    from perception_config.cli import main

    out = tmp_path / "model"
    # 24 episodes: 53 held-out rows, AUC 1.0 and Brier 0.00 (40 gave 91 rows, AUC 0.99, Brier 0.07)
    code = main(["fit-score", "--dataset", str(synthetic_dataset), "--episodes", "24", "--epochs", "300",
                 "--hidden", "16", "--quiet", "--out", str(out)])
    assert code == 0
    printed = capsys.readouterr().out
    assert "AUC" in printed and "Brier" in printed and "ECE" in printed
    for name in (MODEL_FILE, "reliability.png", "metrics.json"):
        assert (out / name).stat().st_size > 0, name
    metrics = json.loads((out / "metrics.json").read_text())
    test = metrics["test"]["rgbd"]
    assert test["n"] > 0 and test["auc"] > 0.6, test  # better than chance on the held-out image
    assert 0 <= test["brier"] <= 0.25
    block = create("pick_success", model=str(out))
    assert block.model.record["source"]["episodes"] == 24
    # recalibration keeps the network and fits only Platt's (a, b)
    again = tmp_path / "recalibrated"
    assert main(["fit-score", "--dataset", str(synthetic_dataset), "--episodes", "16", "--seed", "1",
                 "--recalibrate", str(out), "--quiet", "--out", str(again)]) == 0
    assert "before recalibration" in capsys.readouterr().out
    re = create("pick_success", model=str(again)).model
    for (w0, b0), (w1, b1) in zip(block.model.layers, re.layers):
        np.testing.assert_array_equal(w0, w1)
        np.testing.assert_array_equal(b0, b1)
    assert re.record["source"]["recalibrated"] == str(out) and "recalibrated_from" in re.record


def test_played_rows_are_reproducible(synthetic_dataset):
    from perception_config.learning.pick_success_data import collect_step_rows

    a = collect_step_rows(synthetic_dataset, 4, seed=3, max_steps=3, progress=False)
    b = collect_step_rows(synthetic_dataset, 4, seed=3, max_steps=3, progress=False)
    assert len(a) == len(b) >= 4 and {r["step"] for r in a} >= {0, 1}
    for ra, rb in zip(a, b):
        assert ra["action"] == rb["action"] and ra["episode_obj_id"] == rb["episode_obj_id"]
        if ra["pose"] is not None:
            np.testing.assert_array_equal(ra["pose"]["t"], rb["pose"]["t"])
    assert all(set(r) >= {"episode_dataset", "episode_scene_id", "episode_im_id", "episode_obj_id", "pose", "scores",
                          "picked", "pick_source"} for r in a)


def test_fit_score_from_an_episode_store_of_a_training_run(synthetic_dataset, tmp_path, capsys):
    """The store a training run writes (episodes.sqlite) is fit-score's input: every stored
    hypothesis with a pose becomes a row labelled by the pick criterion."""
    from perception_config.cli import main
    from perception_config.learning.pick_success_data import load_step_rows

    run = tmp_path / "run"
    # 20 episodes: 178 rows, held-out AUC 0.98 (30: 257 rows, AUC 0.99)
    assert main(["train", "--dataset", str(synthetic_dataset), "--agent", "random", "--episodes", "20",
                 "--time-mode", "cost_table", "--cost-table", "blocks", "--workers", "1", "--out", str(run)]) == 0
    rows = load_step_rows(run / "episodes.sqlite")
    assert len(rows) >= 20 and all(r["pose"]["R"].shape == (3, 3) for r in rows)
    assert {r["episode_source"] for r in rows} == {"train"} and {r["step"] for r in rows} >= {0, 1}
    capsys.readouterr()
    out = tmp_path / "model"
    assert main(["fit-score", "--store", str(run / "episodes.sqlite"), "--epochs", "200", "--hidden", "16",
                 "--quiet", "--out", str(out)]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["test"]["rgbd"]["n"] > 0 and metrics["test"]["rgbd"]["auc"] > 0.6, metrics["test"]
    assert create("pick_success", model=str(out)).model.record["source"]["store"].endswith("episodes.sqlite")


def test_fit_score_names_its_bad_input(tmp_path, capsys):
    from perception_config.cli import main

    assert main(["fit-score", "--out", str(tmp_path)]) == 2
    assert "--store" in capsys.readouterr().err
    assert main(["fit-score", "--store", str(tmp_path / "none.db"), "--out", str(tmp_path)]) == 2
    assert "none.db" in capsys.readouterr().err
    with pytest.raises(ValueError, match="no step rows"):
        featurise([], progress=False)


def test_metrics_of_known_predictions():
    y = np.array([0, 0, 1, 1], bool)
    assert auc(np.array([0.1, 0.2, 0.8, 0.9]), y) == 1.0
    assert auc(np.array([0.9, 0.8, 0.2, 0.1]), y) == 0.0
    assert auc(np.full(4, 0.5), y) == 0.5
    m = score_metrics(np.array([0.0, 0.0, 1.0, 1.0]), y)
    assert m["brier"] == 0.0 and m["ece"] == 0.0
    m = score_metrics(np.full(4, 0.5), y)
    assert m["brier"] == pytest.approx(0.25) and m["ece"] == pytest.approx(0.0)


def _real_scores(frame, lam_seeds=((0.1, 0), (0.3, 1), (0.5, 2)), n: int = 4):
    block = create("pick_success")
    p, y = [], []
    for oi, obj in enumerate(frame.objects):
        if obj.model is None or obj.gt is None or (obj.visib_fract if obj.visib_fract is not None else 1.0) < 0.3:
            continue
        cache: dict = {}
        for lam, s in lam_seeds:
            rng = np.random.default_rng([s, oi])
            for _ in range(n):
                pose = perturb(obj.gt, lam, obj.model.diameter, rng)
                r = block(BlockInput(frame=frame, model=obj.model, pose=pose, cache=cache))
                if r.ok:
                    p.append(r.scores["pick_success"])
                    y.append(pose_mssd(pose, obj.gt, obj.model) <= 0.1 * obj.model.diameter)
    return np.array(p), np.array(y, bool)


def test_the_shipped_model_on_the_real_rgbd_frame(lmo_frame):
    p, y = _real_scores(lmo_frame)
    assert len(p) >= 40 and 0 < y.sum() < len(y)
    # trained on synthetic parts only; measured 0.9 (docs/results/pick_success.md)
    assert auc(p, y) > 0.7, (auc(p, y), p, y)


def test_played_rows_come_from_the_given_images_only(synthetic_dataset):
    """fit-score plays the train images of the split (image_keys): no row from another image."""
    from perception_config.datasets.bop import BopDataset
    from perception_config.learning.pick_success_data import collect_step_rows
    from perception_config.rl.episodes import split_image_keys

    train, test = split_image_keys(BopDataset(synthetic_dataset).image_keys())
    rows = collect_step_rows(synthetic_dataset, 6, seed=1, max_steps=2, progress=False, image_keys=train[:2])
    assert rows and {(r["episode_scene_id"], r["episode_im_id"]) for r in rows} <= set(train[:2])
    assert not {(r["episode_scene_id"], r["episode_im_id"]) for r in rows} & set(test)
