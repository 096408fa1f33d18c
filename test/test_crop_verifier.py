"""The pick-success model's crop branch: the rendered-against-observed crop, the numpy CNN against
torch, the model file with convolutions, training on crops, the block and fit-score --crops."""
from __future__ import annotations

import json

import numpy as np
import pytest

from perception_config.blocks.base import BlockInput, create
from perception_config.blocks.features import hypothesis_crop
from perception_config.blocks.pipeline import pipeline_from_dict
from perception_config.core.geometry import Pose
from perception_config.datasets.bop import BopDataset
from perception_config.learning.pick_success_data import FeatureTable, collect_candidate_rows, featurise, pick_label
from perception_config.vision.crop_network import CONV_WIDTHS, _torch_net, check_conv, embed, fit_hybrid
from perception_config.vision.pick_features import FEATURE_NAMES
from perception_config.vision.pick_success_model import (
    MODEL_FILE,
    PickSuccessModel,
    PickSuccessModelError,
    encode,
    robust_scaling,
)
from perception_config.vision.verifier_crop import CHANNELS, CROP, DEPTH_CHANNELS, verifier_crop


def _shifted(pose: Pose, dx: float) -> Pose:
    return Pose(pose.R.copy(), pose.t + np.array([dx, 0.0, 0.0]))


@pytest.fixture(scope="module")
def frame_and_objects(synthetic_dataset):
    ds = BopDataset(synthetic_dataset)
    frame = ds.load_frame(*ds.image_keys()[0])
    return frame, [o for o in frame.objects if o.model is not None and o.gt is not None and (o.visib_fract or 1) > 0.5]


def test_the_crop_at_the_truth_agrees_and_a_shifted_one_does_not(frame_and_objects):
    frame, objs = frame_and_objects
    for obj in objs[:3]:
        cache: dict = {}
        at = verifier_crop(frame, obj.model, obj.gt, cache)
        off = verifier_crop(frame, obj.model, _shifted(obj.gt, 0.3 * obj.model.diameter), cache)
        assert at.shape == off.shape == (len(CHANNELS), CROP, CROP) and at.dtype == np.float32
        assert np.isfinite(at).all() and np.abs(at).max() <= 1.0 + 1e-6
        on = at[1] > 0
        assert 0.1 < on.mean() < 0.9  # the object fills the window's middle, with a margin around it
        both = on & (at[4] > 0)
        # at the truth the depth agrees to the sensor's noise; 0.3 d aside it does not
        assert np.median(np.abs(at[0][both])) < 0.3  # 3 % of the diameter
        assert np.mean(np.abs(off[0][(off[1] > 0) & (off[4] > 0)]) > 0.5) > np.mean(np.abs(at[0][both]) > 0.5) + 0.2
        # the image's edges lie on the rendered outline at the truth, better than when shifted
        outline = at[6] > 0.99
        assert at[5][outline].mean() > 0.5
    nothing = Pose(objs[0].gt.R.copy(), np.array([0.0, 0.0, -1.0]))  # behind the camera
    assert verifier_crop(frame, objs[0].model, nothing, {}) is None
    assert not hypothesis_crop(frame, objs[0].model, nothing, {}).any()
    as_rgb = hypothesis_crop(frame, objs[0].model, objs[0].gt, {}, use_depth=False)
    assert not as_rgb[list(DEPTH_CHANNELS)].any() and as_rgb[1].any()


def test_the_numpy_network_is_torchs_forward():
    import torch

    torch.manual_seed(3)
    net = _torch_net(10, len(CHANNELS), (16,))
    crops = np.random.default_rng(0).normal(size=(3, len(CHANNELS), CROP, CROP)).astype(np.float32)
    conv = [(m.weight.detach().numpy(), m.bias.detach().numpy()) for m in net.conv if isinstance(m, torch.nn.Conv2d)]
    assert [w.shape[0] for w, _ in conv] == list(CONV_WIDTHS) and check_conv(conv, len(CHANNELS), CROP) == ""
    with torch.no_grad():
        h = net.conv(torch.from_numpy(crops))
        ref = torch.cat([h.mean(dim=(2, 3)), h.amax(dim=(2, 3))], 1).numpy()
    np.testing.assert_allclose(embed(crops, conv), ref, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(embed(crops, conv, chunk=2), ref, rtol=1e-4, atol=1e-5)  # in chunks: the same
    assert "convolution 1" in check_conv([conv[0], conv[2]], len(CHANNELS), CROP)


def _toy_table(n: int = 160, seed: int = 0) -> FeatureTable:
    """Crops whose label is visible only in the crop: the residual channel's sign in the middle."""
    rng = np.random.default_rng(seed)
    crops = rng.normal(0, 0.2, size=(n, len(CHANNELS), CROP, CROP)).astype(np.float32)
    y = rng.random(n) < 0.5
    crops[:, 0, 24:40, 24:40] += np.where(y, 0.0, 0.8)[:, None, None]  # wrong poses: a depth residual blob
    X = rng.normal(size=(n, len(FEATURE_NAMES)))  # features without information
    images = [("toy", 0, i % 12) for i in range(n)]
    return FeatureTable(X, y, images, np.zeros(n, bool), np.full(n, np.nan), np.full(n, np.nan),
                        crops=crops.astype(np.float16))


def test_a_crop_branch_learns_what_only_the_crop_shows_and_round_trips(tmp_path):
    from perception_config.learning.pick_success_fit import fit_model

    table = _toy_table()
    model, metrics, _ = fit_model(table, hidden=(16,), epochs=24, seed=0)
    assert model.uses_crop and model.record["crop_branch"] == list(CONV_WIDTHS)
    assert metrics["test"]["all"]["auc"] > 0.9, metrics["test"]["all"]  # features alone: ~0.5
    with pytest.raises(ValueError, match="crop"):
        model.predict(table.X[:2])
    path = model.save(tmp_path / MODEL_FILE)
    back = PickSuccessModel.load(path)
    assert back.uses_crop
    np.testing.assert_allclose(back.predict(*table.inputs(np.arange(10))), model.predict(*table.inputs(np.arange(10))),
                               rtol=1e-5, atol=1e-6)
    # a model without the branch is still written as version 1, as before
    median, spread = robust_scaling(table.X)
    plain = PickSuccessModel(FEATURE_NAMES, median, spread, [(np.zeros((1, 2 * len(FEATURE_NAMES))), np.zeros(1))])
    from perception_config.vision.pick_success_model import _read

    assert _read(plain.save(tmp_path / "plain.safetensors"))[0]["version"] == 1
    assert _read(path)[0]["version"] == 2
    assert encode(table.X[:1], median, spread).shape == (1, 2 * len(FEATURE_NAMES))


def test_a_crop_model_of_another_crop_or_with_bad_convolutions_is_refused(tmp_path):
    from perception_config.util.checksum import CHECKSUM_KEY, content_checksum

    table = _toy_table(n=60)
    median, spread = robust_scaling(table.X)
    rng = np.random.default_rng(1)
    widths = (len(CHANNELS),) + CONV_WIDTHS
    conv = [(rng.normal(0, 0.1, (widths[i + 1], widths[i], 3, 3)), np.zeros(widths[i + 1])) for i in range(4)]
    head = [(rng.normal(0, 0.1, (1, 2 * len(FEATURE_NAMES) + 2 * CONV_WIDTHS[-1])), np.zeros(1))]
    model = PickSuccessModel(FEATURE_NAMES, median, spread, head, conv=conv)
    path = model.save(tmp_path / "m.safetensors")
    assert PickSuccessModel.load(path).uses_crop

    from safetensors.numpy import save

    from perception_config.vision.pick_success_model import META_KEY, _read

    meta, tensors = _read(path)
    def narrow(m: dict, t: dict) -> None:
        t["conv2.weight"] = np.ascontiguousarray(t["conv2.weight"][:, :5])

    for change, message in ((lambda m, t: m["crop"].update(size=32), "another crop"),
                            (narrow, "convolution 2"),
                            (lambda m, t: m["crop"].update(n_conv=0), "n_conv")):
        m, t = json.loads(json.dumps(meta)), dict(tensors)
        change(m, t)
        m[CHECKSUM_KEY] = content_checksum(m, t)
        bad = tmp_path / "bad.safetensors"
        bad.write_bytes(save(t, metadata={META_KEY: json.dumps(m)}))
        with pytest.raises(PickSuccessModelError, match=message):
            PickSuccessModel.load(bad)


def test_the_block_and_featurise_use_the_crops_and_candidate_rows_hold_generator_mistakes(
        synthetic_dataset, frame_and_objects, tmp_path):
    frame, objs = frame_and_objects
    ds = BopDataset(synthetic_dataset)
    pipe = pipeline_from_dict({"generator": {"block": "resting_pose"},
                               "actions": [{"name": "icp", "block": "icp_point_to_plane"},
                                           {"name": "pick", "block": "simulated_pick"}],
                               "scoring": ["psi_d"]})
    rows = collect_candidate_rows(synthetic_dataset, pipe, image_keys=ds.image_keys()[:1], progress=False)
    assert rows and {r["action"] for r in rows} == {"resting_pose"}  # icp needs a pose: not a generator
    table = featurise(rows, progress=False, crops=True, symmetries="derived")
    assert table.crops is not None and len(table.crops) == len(table) and table.crops.dtype == np.float16
    rgb = table.rgb_only
    assert rgb.any() and not table.crops[rgb][:, list(DEPTH_CHANNELS)].any()
    assert table.crops[~rgb][:, 4].any()  # the RGB-D rows keep their depth
    assert len(table.subset(rgb).crops) == int(rgb.sum())
    with pytest.raises(ValueError, match="symmetries"):
        pick_label(objs[0].model, objs[0].gt, [objs[0].gt], "nearby")
    # a crop model in the block: its probability at the truth above one 0.3 d away
    toy = _toy_table(n=60)
    median, spread = robust_scaling(toy.X)
    conv, head = fit_hybrid(encode(toy.X, median, spread), toy.crops, toy.y, (8,), epochs=1, progress=False)
    PickSuccessModel(FEATURE_NAMES, median, spread, head, conv=conv).save(tmp_path / MODEL_FILE)
    block = create("pick_success", model=str(tmp_path))
    r = block(BlockInput(frame=frame, model=objs[0].model, pose=objs[0].gt, cache={}))
    assert r.ok and 0.0 <= r.scores["pick_success"] <= 1.0
