"""Model parameters are range-checked, not only checksummed: a policy, a pick-success score model or
a cost model edited by someone who then recomputes the checksum (with this package's own writers,
as an attacker would) is refused with the loader's error naming the file, the field and the value;
the legitimately written ones still load."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from perception_config.agents import PolicyError, load_agent, make_agent, save_agent
from perception_config.agents.policy_io import CHECKSUM_KEY, content_checksum, read_file, write_file
from perception_config.bench.calibration import read_cost_table
from perception_config.blocks.pick_success import CONFIG_DIR, SHIPPED_MODEL, PickSuccess
from perception_config.vision.pick_success_model import PickSuccessModel, PickSuccessModelError
from test_hostile_files import SPEC, _policy, _rewrite_meta

SHIPPED = CONFIG_DIR / SHIPPED_MODEL


# --------------------------------------------------------------------------- policies
@pytest.mark.parametrize("change, match", [
    (lambda m: m["extra"].update(test_fraction=1e300), r"extra\.test_fraction must be a number in \[0, 1\], got 1e"),
    (lambda m: m["extra"].update(split_seed=-1), r"extra\.split_seed must be an integer .* got -1"),
    (lambda m: m["extra"].update(split_seed=0.5), r"extra\.split_seed must be an integer .* got 0\.5"),
    (lambda m: m["extra"].update(episodes=-3), r"extra\.episodes must be an integer .* got -3"),
    (lambda m: m["extra"].update(validation_lambdas=[0.5, 1e300]), r"extra\.validation_lambdas\[1\] must be in \[0, 2"),
    (lambda m: m["extra"].update(lambda_range=[0.1, -1]), r"extra\.lambda_range\[1\] must be in \[0, 2"),
    (lambda m: m["extra"].update(selected={"episode": -1e300}), r"extra\.selected\.episode must be an integer"),
    (lambda m: m["extra"].update(note={"x": [1.0, float("nan")]}), r"extra\.note\.x\[1\] = nan is not a finite number"),
    (lambda m: m["hparams"].update(lr=float("inf")), r"hparams\.lr = inf is not a finite number"),
    (lambda m: m.update(trainer={"episodes_done": -5}), r"trainer\.episodes_done must be an integer"),
    (lambda m: m["extra"].update(env_settings={"lambda_range": [0.1, 1e300]}), r"lambda_range high must be in"),
    (lambda m: m["extra"].update(env_settings={"truncation_cost": -1e300}), r"truncation_cost .* \[0, 3600\]"),
])
def test_rechecksummed_policy_metadata_out_of_range_is_refused(tmp_path, change, match):
    path = _policy(tmp_path, hidden=8)
    _rewrite_meta(path, change)
    with pytest.raises(PolicyError, match=match) as exc:
        load_agent(path, SPEC)
    assert str(path) in str(exc.value)


def test_rechecksummed_huge_weights_are_refused_and_trained_ones_load(tmp_path):
    path = _policy(tmp_path, hidden=8)
    assert load_agent(path, SPEC).hidden == 8  # as saved: within the bounds
    meta, tensors = read_file(path)
    tensors["policy.fc1.weight"][0, 0] = 1e30  # finite, but no training gets there
    meta.pop(CHECKSUM_KEY)
    write_file(path, meta, tensors)  # a consistent checksum
    with pytest.raises(PolicyError, match=r"tensor 'policy\.fc1\.weight' holds 1e\+30, outside \[-1e\+06, 1e\+06\]"):
        load_agent(path, SPEC)
    # the training state (optimizer moments) is checked for finiteness, not magnitude
    agent = make_agent("pg", SPEC, hidden=8)
    ok = save_agent(agent, tmp_path / "ok.policy", {"env_settings": {"max_ops": 6}, "split_seed": 3,
                                                    "test_fraction": 0.3, "validation_lambdas": [0.1, 0.5, 1.0]})
    assert load_agent(ok, SPEC).hidden == 8


def test_a_crafted_checksum_is_what_the_loader_computes(tmp_path):
    """How the hostile files above are made: the sha256 over the canonical metadata and the
    tensors (util/checksum.py), recomputed after the edit."""
    path = _policy(tmp_path, hidden=8)
    meta, tensors = read_file(path)
    assert content_checksum(meta, tensors) == meta[CHECKSUM_KEY]
    meta["extra"]["test_fraction"] = 1e300
    meta[CHECKSUM_KEY] = content_checksum(meta, tensors)
    from safetensors.numpy import save

    path.write_bytes(save(tensors, metadata={"perception_config": json.dumps(meta)}))
    with pytest.raises(PolicyError, match=r"test_fraction must be a number in \[0, 1\], got 1e\+300"):
        read_file(path)


# --------------------------------------------------------------------------- pick-success models
def _hostile_model(tmp_path: Path, change) -> Path:
    """The shipped model, changed, saved with a fresh checksum (PickSuccessModel.save writes one)."""
    model = PickSuccessModel.load(SHIPPED)
    change(model)
    return model.save(tmp_path / "hostile.safetensors")


@pytest.mark.parametrize("change, match", [
    (lambda m: setattr(m, "calibration", (-1e300, 0.0)), r"calibration\.a = -1e\+300 is outside \(0, 1000\]"),
    (lambda m: setattr(m, "calibration", (1e300, 0.0)), r"calibration\.a = 1e\+300 is outside \(0, 1000\]"),
    (lambda m: setattr(m, "calibration", (-1.0, 0.0)), r"calibration\.a = -1\.0 is outside"),
    (lambda m: setattr(m, "calibration", (1.0, 5e3)), r"calibration\.b = 5000\.0 is outside \[-1000, 1000\]"),
    (lambda m: m.layers[0][0].__setitem__((0, 0), 1e30), r"tensor 'layer0\.weight' holds 1e\+30 \(element 0\)"),
    (lambda m: m.layers[1][1].__setitem__(2, -2e4), r"tensor 'layer1\.bias' holds -20000 \(element 2\)"),
    (lambda m: m.layers[0][0].__setitem__((0, 1), np.nan), r"tensor 'layer0\.weight' is not finite"),
    (lambda m: m.spread.__setitem__(3, 0.0), r"tensor 'spread' holds 0 \(element 3\), outside \[1e-06, 1e\+06\]"),
    (lambda m: m.spread.__setitem__(3, -1.0), r"tensor 'spread' holds -1 \(element 3\)"),
    (lambda m: m.median.__setitem__(5, 1e300), r"tensor 'median' holds 1e\+300 \(element 5\)"),
])
def test_rechecksummed_pick_success_model_out_of_range_is_refused(tmp_path, change, match):
    path = _hostile_model(tmp_path, change)
    with pytest.raises(PickSuccessModelError, match=match) as exc:
        PickSuccessModel.load(path)
    assert str(path) in str(exc.value) and "is corrupt" in str(exc.value)
    with pytest.raises(ValueError, match="hostile.safetensors"):  # a pipeline naming it does not load
        PickSuccess(model=str(path))


def test_fitted_pick_success_models_load(tmp_path):
    """The shipped model and one fitted by fit_platt at its bounds load; the calibration a fitted
    anew stays inside what the loader accepts."""
    from perception_config.vision.pick_success_model import fit_platt

    model = PickSuccessModel.load(SHIPPED)
    assert 0 < model.calibration[0] <= 10
    rng = np.random.default_rng(0)
    logits = rng.normal(size=200) * 50  # separable: the unbounded optimum would run off to infinity
    a, b = fit_platt(logits, (logits > 0).astype(float))
    model.calibration = (a, b)
    back = PickSuccessModel.load(model.save(tmp_path / "refit.safetensors"))
    assert back.calibration == pytest.approx((a, b)) and 0 < a <= 10 and abs(b) <= 50


def test_a_hostile_score_version_does_not_serve(tmp_path):
    """Online learning's score versions: a re-checksummed version with a = -1e300 is skipped; the
    model that served keeps serving and the block says why."""
    from perception_config.online.score_learner import score_versions

    learn = tmp_path / "learn"
    versions = score_versions(learn)
    hostile = _hostile_model(tmp_path, lambda m: setattr(m, "calibration", (-1e300, 0.0)))
    block = PickSuccess(versions=str(learn / "pick_success"))
    versions.promote(hostile, {"start": "hostile"})
    block.refresh()
    assert block.version is None and "calibration.a = -1e+300" in block._problem


# --------------------------------------------------------------------------- cost models
@pytest.mark.parametrize("value, shown", [
    ("NaN", "nan"), ("Infinity", "inf"), ("-1", "-1"), ("1e300", "1e+300"), ("3601", "3601"), ("true", "True"),
    ('"0.1"', "'0.1'"),
])
def test_cost_model_entries_out_of_range_are_refused(tmp_path, value, shown):
    path = tmp_path / "cm.json"
    path.write_text('{"format": "perception_config.cost_model/1", "cost_table": {"action:icp_fine": 0.01, '
                    f'"action:pick": {value}}}}}')
    with pytest.raises(ValueError, match=r"cost model .*cm\.json: cost_table\['action:pick'\] must be a number of "
                                         r"seconds in \[0, 3600\], got " + re.escape(shown)) as exc:
        read_cost_table(path)
    assert str(path) in str(exc.value)


def test_cost_model_is_read_as_a_hostile_file(tmp_path):
    deep = tmp_path / "deep.json"
    deep.write_text('{"cost_table": ' + "[" * 5000 + "]" * 5000 + "}")
    with pytest.raises(ValueError, match=r"cost model .*deep\.json: not a readable JSON file .*nested 5001 levels"):
        read_cost_table(deep)
    with pytest.raises(ValueError, match=r"cost model .*: not a readable JSON file .*is a directory"):
        read_cost_table(tmp_path)
    many = tmp_path / "many.json"
    many.write_text(json.dumps({"cost_table": {f"action:a{i}": 0.01 for i in range(1001)}}))
    with pytest.raises(ValueError, match=r"many\.json: cost_table has 1001 entries, more than 1000"):
        read_cost_table(many)
    ok = tmp_path / "ok.json"
    ok.write_text(json.dumps({"cost_table": {"action:pick": 0.5, "scoring": 0.0001, "action:icp@3": 3600}}))
    assert read_cost_table(ok) == {"action:pick": 0.5, "scoring": 0.0001, "action:icp@3": 3600.0}
