"""The learn directory is confined: online learning reads and writes only inside `learn_dir`.

A symbolic link that leads out of it (a version file, versions.json, the policies/, pick_success/
or frames/ folder) is refused, for reading and for writing, with an error naming the path and
where it leads, and nothing is written outside; links that stay inside are allowed."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from perception_config.core.scene import Frame
from perception_config.online.score_learner import SCORES, refit_score_once, score_versions
from perception_config.store.frames import frame_path, load_frame, prune_frames, save_frame
from perception_config.util.confine import ConfinementError, confined
from perception_config.util.versions import PolicyVersionError, PolicyVersions

POLICY = {"format": "perception_config.policy", "agent": "random", "env": {}}  # content does not matter here


@pytest.fixture
def dirs(tmp_path) -> tuple[Path, Path, Path]:
    """(learn_dir, an outside folder holding a policy file, that file)."""
    learn, outside = tmp_path / "learn", tmp_path / "outside"
    learn.mkdir()
    outside.mkdir()
    secret = outside / "policy.json"
    secret.write_text(json.dumps({**POLICY, "note": "not promoted"}))
    return learn, outside, secret


def _source(tmp_path: Path, name: str = "candidate.json") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(POLICY))
    return path


def _tree(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


# --------------------------------------------------------------------------- the helper
def test_confined_resolves_links_and_names_where_they_lead(tmp_path):
    root = tmp_path / "root"
    (root / "a").mkdir(parents=True)
    (root / "in").symlink_to(root / "a")
    (root / "out").symlink_to(tmp_path)
    (root / "dangling").symlink_to(tmp_path / "nowhere")
    (root / "loop").symlink_to(root / "loop")
    assert confined(root / "in" / "x", root) == (root / "a" / "x").resolve()
    assert confined(root, root) == root.resolve()
    with pytest.raises(ConfinementError, match=rf"file {root / 'out'} leads to {tmp_path.resolve()}, outside"):
        confined(root / "out", root)
    with pytest.raises(ConfinementError, match=r"leads to .*nowhere, outside"):
        confined(root / "dangling", root)
    with pytest.raises(ConfinementError, match="cannot be resolved"):
        confined(root / "loop", root)
    link = tmp_path / "learn_link"
    link.symlink_to(root)  # learn_dir itself a link: what it holds is inside
    assert confined(link / "a", link) == (root / "a").resolve()


# --------------------------------------------------------------------------- policy versions
def test_a_version_file_linked_outside_is_refused_on_read(dirs, tmp_path):
    learn, _, secret = dirs
    versions = PolicyVersions(learn / "policies")
    v = versions.promote(_source(tmp_path))
    path = versions.path(v)
    path.unlink()
    path.symlink_to(secret)
    with pytest.raises(PolicyVersionError, match=rf"policy version v0000 file {path} leads to {secret.resolve()}, "
                                                 r"outside .*learn"):
        versions.path(v)


def test_policies_folder_linked_outside_is_refused_at_construction(dirs):
    learn, outside, _ = dirs
    before = _tree(outside)
    (learn / "policies").symlink_to(outside)
    with pytest.raises(PolicyVersionError, match=rf"policy versions folder {learn / 'policies'} leads to "
                                                 rf"{outside.resolve()}, outside {learn.resolve()}"):
        PolicyVersions(learn / "policies")
    # a link to a folder that does not exist yet: refused before anything is created
    (learn / "pick_success").symlink_to(outside / "new")
    with pytest.raises(PolicyVersionError, match=r"pick_success versions folder .* leads to .*new, outside"):
        score_versions(learn)
    assert _tree(outside) == before and not (outside / "new").exists()


def test_policies_folder_swapped_for_an_outside_link_is_refused_on_promotion(dirs, tmp_path):
    learn, outside, _ = dirs
    versions = PolicyVersions(learn / "policies")
    versions.promote(_source(tmp_path))
    (learn / "policies").rename(learn / "moved")
    (learn / "policies").symlink_to(outside)
    before = _tree(outside)
    for act in (lambda: versions.promote(_source(tmp_path)), lambda: versions.select(None), versions.current,
                versions.list):
        with pytest.raises(PolicyVersionError, match=r"policy versions folder .* leads to .*outside, outside"):
            act()
    assert _tree(outside) == before  # no version, no index, no lock file written there


def test_versions_index_linked_outside_is_refused(dirs, tmp_path):
    learn, outside, _ = dirs
    versions = PolicyVersions(learn / "policies")
    versions.promote(_source(tmp_path))
    index = outside / "versions.json"
    index.write_text(json.dumps({"versions": [{"version": "v0000", "file": "../outside/policy.json"}],
                                 "selected": None}))
    before = index.read_bytes()
    (learn / "policies" / "versions.json").unlink()
    (learn / "policies" / "versions.json").symlink_to(index)
    for act in (versions.current, lambda: versions.select("v0000"), lambda: versions.promote(_source(tmp_path))):
        with pytest.raises(PolicyVersionError, match=r"policy versions index .*versions\.json leads to "
                                                     r".*outside/versions\.json, outside"):
            act()
    assert index.read_bytes() == before
    # a lock file linked outside is not opened (opening it would create or touch the file there)
    (learn / "policies" / "versions.json").unlink()
    (learn / "policies" / ".lock").unlink(missing_ok=True)
    (learn / "policies" / ".lock").symlink_to(outside / "lock")
    with pytest.raises(PolicyVersionError, match=r"policy versions lock .*\.lock leads to .*outside/lock"):
        versions.select(None)
    assert not (outside / "lock").exists()


def test_links_that_stay_inside_are_allowed(tmp_path):
    learn = tmp_path / "learn"
    (learn / "other").mkdir(parents=True)
    (learn / "policies").symlink_to(learn / "other")
    versions = PolicyVersions(learn / "policies")
    v0 = versions.promote(_source(tmp_path))
    assert (learn / "other" / "v0000.json").exists() and (learn / "other" / "versions.json").exists()
    (learn / "kept.json").write_text(json.dumps(POLICY))
    (learn / "other" / "v0000.json").unlink()
    (learn / "other" / "v0000.json").symlink_to(learn / "kept.json")  # a version file linked inside
    assert json.loads(versions.path(v0).read_text()) == POLICY
    versions.select(v0)
    assert versions.current() == v0
    # an explicit root: the learn dir two levels up
    nested = PolicyVersions(learn / "sub" / "policies", root=learn)
    assert nested.promote(_source(tmp_path)) == "v0000"
    with pytest.raises(PolicyVersionError, match="outside"):
        PolicyVersions(tmp_path / "elsewhere", root=learn)


# --------------------------------------------------------------------------- score versions
def test_score_versions_are_confined_too(dirs, tmp_path):
    from perception_config.blocks.pick_success import SHIPPED_MODEL, PickSuccess

    learn, outside, _ = dirs
    versions = score_versions(learn)
    v = versions.promote(_source(tmp_path, "model.safetensors"))
    path = versions.path(v)
    path.unlink()
    hostile = outside / "model.safetensors"
    hostile.write_bytes(b"not served")
    path.symlink_to(hostile)
    with pytest.raises(PolicyVersionError, match=r"pick_success version v0000 file .* leads to .*outside"):
        versions.path(v)
    block = PickSuccess(model=SHIPPED_MODEL, versions=str(learn / SCORES))
    block.refresh()  # the version is refused: the model keeps serving, the block says why
    assert block.version is None and "leads to" in block._problem
    # the learner's cycle fails naming the folder (before reading the store or fitting anything)
    other = tmp_path / "learn2"
    other.mkdir()
    (other / SCORES).symlink_to(outside)
    result = refit_score_once(other, tmp_path / "models")
    assert result["outcome"] == "failed" and "pick_success versions folder" in result["reason"]
    assert "leads to" in result["reason"] and _tree(outside) == ["model.safetensors", "policy.json"]


# --------------------------------------------------------------------------- frames
def _frame() -> Frame:
    return Frame(rgb=np.zeros((4, 5, 3), np.uint8), depth=np.ones((4, 5), np.float32), K=np.eye(3))


def test_frames_folder_linked_outside_is_refused(dirs):
    learn, outside, _ = dirs
    (outside / "7.npz").write_bytes(b"someone else's")
    (learn / "frames").symlink_to(outside)
    before = _tree(outside)
    with pytest.raises(ConfinementError, match=rf"frames folder {learn / 'frames'} leads to .*outside, outside"):
        save_frame(learn / "frames", 123, _frame(), None, keep=0)  # keep=0 would prune everything there
    with pytest.raises(ConfinementError, match="frames folder .* leads to"):
        prune_frames(learn / "frames", 0)
    with pytest.raises(ValueError, match=r"frame file .*frames/7\.npz leads to .*outside/7\.npz, outside"):
        load_frame(frame_path(learn / "frames", 7))
    assert _tree(outside) == before


def test_a_frame_file_linked_outside_is_refused_and_inside_links_work(dirs):
    learn, outside, _ = dirs
    save_frame(learn / "frames", 1, _frame(), None)
    elsewhere = outside / "2.npz"
    save_frame(outside, 2, _frame(), None)  # a valid frame file, outside the learn dir
    frame_path(learn / "frames", 2).symlink_to(elsewhere)
    with pytest.raises(ValueError, match=r"frame file .*frames/2\.npz leads to .*outside/2\.npz, outside"):
        load_frame(frame_path(learn / "frames", 2))
    with pytest.raises(ValueError, match="leads to"):
        save_frame(learn / "frames", 2, _frame(), None)  # not written through the link
    assert load_frame(elsewhere)[0].rgb.shape == (4, 5, 3)  # untouched
    # the frames folder as a link inside learn_dir: saved, loaded, pruned there
    (learn / "kept").mkdir()
    (learn / "frames2").symlink_to(learn / "kept")
    for stamp in (10, 11, 12):
        save_frame(learn / "frames2", stamp, _frame(), None, keep=2)
    assert sorted(p.name for p in (learn / "kept").iterdir()) == ["11.npz", "12.npz"]
    frame, gt = load_frame(frame_path(learn / "frames2", 12))
    assert frame.rgb.shape == (4, 5, 3) and gt == {}
    with pytest.raises(ValueError, match="leads to"):  # an explicit root: the learn dir
        load_frame(elsewhere, root=learn)


def test_default_roots_keep_the_node_call_signatures(tmp_path):
    """The ROS layer calls PolicyVersions(dir / "policies"), score_versions(dir) and
    save_frame(dir / "frames", ...): the learn dir is the folder's parent by default."""
    learn = tmp_path / "learn"
    assert PolicyVersions(learn / "policies").root == learn
    assert score_versions(learn).root == learn
    path = save_frame(learn / "frames", 5, _frame(), None)
    assert path == learn / "frames" / "5.npz" and os.path.isfile(path)


# --------------------------------------------------------------------------- the learner
def _store_with_one_estimate(path: Path, stamp: int) -> None:
    import sqlite3

    from perception_config.store.episode_store import EpisodeStore

    EpisodeStore(path).close()  # the schema
    with sqlite3.connect(path) as db:
        db.execute("INSERT INTO episodes (source, created, frame_stamp_ns, obj_id, noise_lambda, episode_seed) "
                   "VALUES ('configurator', 0, ?, 1, 0.5, 3)", (stamp,))


def test_the_learner_reads_and_writes_only_inside_learn_dir(dirs, tmp_path):
    from perception_config.core.geometry import Pose
    from perception_config.online.policy_learner import (
        LearnError,
        LearnerSettings,
        _save_candidate,
        _stored_count,
        learn_once,
        replayable_episodes,
    )

    learn, outside, _ = dirs
    before = _tree(outside)
    # policies/ linked outside: the cycle fails naming it, nothing is written there
    (learn / "policies").symlink_to(outside)
    settings = LearnerSettings(models_dir=str(tmp_path / "models"), pipeline=None, env_settings={})
    result = learn_once(learn, settings)
    assert result["outcome"] == "failed" and "policy versions folder" in result["reason"] \
        and "leads to" in result["reason"]
    # a kept frame linked outside: skipped (logged), not replayed
    _store_with_one_estimate(learn / "episodes.sqlite", 7)
    save_frame(outside, 7, _frame(), {1: Pose(np.eye(3), np.zeros(3))})
    (learn / "frames").mkdir()
    frame_path(learn / "frames", 7).symlink_to(outside / "7.npz")
    lines: list[str] = []
    assert replayable_episodes(learn, None, log=lines.append) == ([], 1)
    assert len(lines) == 1 and "frame file" in lines[0] and "leads to" in lines[0]
    assert _stored_count(learn) == 1
    # the store linked outside: not read
    (learn / "episodes.sqlite").rename(outside / "episodes.sqlite")
    (learn / "episodes.sqlite").symlink_to(outside / "episodes.sqlite")
    with pytest.raises(LearnError, match=r"episode store .* leads to .*outside/episodes\.sqlite, outside"):
        replayable_episodes(learn, None)
    assert _stored_count(learn) is None
    # the candidates folder linked outside: the candidate is not written there
    (learn / "candidates").symlink_to(outside)
    from perception_config.agents import EnvSpec, make_agent

    spec = EnvSpec(action_names=("a", "pick"), action_kinds=("refinement", "pick"), observation_layout=("step",),
                   max_ops=4)
    with pytest.raises(ConfinementError, match="candidates folder .* leads to"):
        _save_candidate(make_agent("random", spec), learn, settings, {})
    assert _tree(outside) == sorted(before + ["7.npz", "episodes.sqlite"])
