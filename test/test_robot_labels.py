"""Labels from the robot's own picks (online/pick_labels.py) and the label kind of stored episodes:
how a replay judges a pick without ground truth, the label rules against wrong reports, and a
cell's store replayed by the learner."""
from __future__ import annotations

import sqlite3

import numpy as np
import pytest

from perception_config.core.geometry import Pose
from perception_config.core.metrics import pose_mssd
from perception_config.online.pick_labels import LABEL_TOLERANCE, PickLabels
from rl_helpers import CELL_PIPELINE, pipeline_file, tiny_dataset


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return tiny_dataset(tmp_path_factory)


@pytest.fixture(scope="module")
def obj(dataset):
    """(model, ground-truth pose) of the first object of the tiny dataset."""
    from perception_config.datasets.bop import BopDataset

    frame = BopDataset(dataset, split="test").load_frame(*BopDataset(dataset, split="test").image_keys()[0])
    o = next(o for o in frame.objects if o.model is not None)
    return o.model, o.gt


def shifted(pose: Pose, metres: float) -> Pose:
    return Pose(pose.R.copy(), pose.t + np.array([metres, 0.0, 0.0]))


def share(a: Pose, b: Pose, model) -> float:
    return pose_mssd(a, b, model) / model.diameter


def test_a_replayed_pick_is_judged_by_the_robots_outcomes(obj):
    model, truth = obj
    d = model.diameter
    picked = shifted(truth, 0.02 * d)  # the robot picked here: the truth is within 0.1 d of it
    labels = PickLabels(picked=[picked], failed=[shifted(truth, -0.4 * d)])
    near, middle, far = shifted(picked, 0.03 * d), shifted(picked, 0.12 * d), shifted(picked, 0.3 * d)
    assert share(near, picked, model) <= LABEL_TOLERANCE < share(middle, picked, model) < 0.2
    assert share(far, picked, model) > 0.2
    assert labels.judge(near, model)[0] is True
    assert labels.judge(picked, model)[0] is True
    # Not covered by a label: without the learned score it counts as a failure; the score decides otherwise.
    assert labels.judge(middle, model)[0] is False
    assert labels.judge(middle, model, {"pick_success": 0.8})[0] is True
    assert labels.judge(middle, model, {"pick_success": 0.2})[0] is False
    assert labels.judge(middle, model, {"pick_success": float("nan")})[0] is False
    # Beyond 0.2 d of every picked pose the truth (within 0.1 d of it) is out of reach: failed, whatever the score.
    assert labels.judge(far, model, {"pick_success": 0.99})[0] is False
    # Near a pose the robot failed at: failed.
    assert labels.judge(shifted(truth, -0.41 * d), model, {"pick_success": 0.99})[0] is False
    # Only failures known: every pose is judged by the score or counted failed.
    only_failed = PickLabels(failed=[shifted(truth, 0.3 * d)])
    assert only_failed.judge(truth, model)[0] is False
    assert only_failed.judge(truth, model, {"pick_success": 0.9})[0] is True
    assert only_failed.judge(shifted(truth, 0.31 * d), model, {"pick_success": 0.9})[0] is False
    # Confirmed: only a success at a pose the robot picked, not one the score granted.
    assert labels.confirms(near, model) and labels.confirms(picked, model)
    assert not labels.confirms(middle, model) and not only_failed.confirms(truth, model)


def test_labels_that_contradict_each_other_are_not_used(obj):
    model, truth = obj
    d = model.diameter
    agreeing = PickLabels(picked=[truth, shifted(truth, 0.15 * d)], failed=[shifted(truth, 0.5 * d)])
    assert agreeing.conflict(model) is None
    # two picked poses farther apart than 0.2 d cannot both be within 0.1 d of one truth
    assert "two picked poses" in PickLabels(picked=[truth, shifted(truth, 0.3 * d)]).conflict(model)
    # a failed pose (nearly) where the robot picked: a flipped report
    assert "a failed pose" in PickLabels(picked=[truth], failed=[shifted(truth, 0.005 * d)]).conflict(model)


def test_stored_episodes_record_their_label_kind_and_an_old_store_gains_the_column(tmp_path, dataset):
    from perception_config.online.pick_labels import label_counts
    from perception_config.store.episode_record import EpisodeRecord, StepRecord
    from perception_config.store.episode_store import EpisodeStore

    def record(pick_source: str | None, picked: bool | None) -> EpisodeRecord:
        steps = [StepRecord(0, "generate", True, 0.0, 0.01, {}, Pose.identity()),
                 StepRecord(1, "pick", picked is not None, 0.0, 0.01, {}, Pose.identity(), picked, pick_source)]
        from perception_config.store.episode_record import pick_label

        return EpisodeRecord("configurator", "v0000", "fixed", None, None, None, 1, 10, 0.5, "generate", 3,
                             bool(picked), bool(picked), 0.1, 0.1, False, steps,
                             label=pick_label(steps, pick_source or "simulated"))

    path = tmp_path / "episodes.sqlite"
    with EpisodeStore(path) as store:
        simulated = store.append(record("simulated", True))
        robot = store.append(record("robot", False))
        unpicked = store.append(record(None, None))
        store.record_pick_outcome(unpicked, 1, True, "robot")  # a robot program's report labels it
        labels = dict(store.query("SELECT id, label FROM episodes"))
    assert labels == {simulated: "ground_truth", robot: "robot", unpicked: "robot"}
    assert label_counts(path) == {"ground_truth": 1, "robot": 2}
    # A store made before the column existed: read-only it is read as it is, opened for writing it gains it.
    db = sqlite3.connect(path)
    db.execute("ALTER TABLE episodes DROP COLUMN label")
    db.commit()
    db.close()
    with EpisodeStore(path, readonly=True) as store:
        assert not store.has_column("episodes", "label")
    assert label_counts(path) == {}
    with EpisodeStore(path) as store:
        assert store.has_column("episodes", "label")
        store.append(record("robot", True))
    assert label_counts(path) == {"unknown": 3, "robot": 1}


def test_a_cells_store_is_replayed_on_the_robots_labels(tmp_path, tmp_path_factory, dataset):
    """Episodes a cell stored without ground truth (frames without it, picks answered by an honest
    robot) are replayable; replaying the serving policy with the stored seeds reproduces each
    recorded outcome, judged by the labels alone. Wrong reports are caught where the same frame
    was estimated twice, and a robot that reports every pick failed leaves nothing to replay."""
    from perception_config.agents import make_agent
    from perception_config.datasets.bop_models import ModelFolder
    from perception_config.online.policy_learner import FRAMES, replay, replayable_episodes
    from perception_config.rl.env import PerceptionConfigEnv
    from perception_config.rl.episode_loop import acting_seed, play_episode
    from perception_config.store.episode_store import STORE_NAME, EpisodeStore, StoreWriter, store_episode
    from perception_config.store.frames import save_frame

    pipe = pipeline_file(tmp_path_factory, CELL_PIPELINE, "cell_labels.yaml")
    env = PerceptionConfigEnv(dataset, pipe, time_mode="cost_table", min_visib_fract=0.3)
    agent = make_agent("fixed", env, sequence=["icp_fine", "pick", "next_candidate"])
    episodes = list(range(min(6, len(env.source.episodes))))
    keys = sorted({(env.source.episodes[j].scene_id, env.source.episodes[j].im_id) for j in episodes})

    def record(learn_dir, flip=lambda i, picked: picked, passes=1):
        writer = StoreWriter(learn_dir / STORE_NAME, print)
        outcomes = []
        for p in range(passes):
            for j in episodes:
                ek = env.source.episodes[j]
                seed = 100 + 10 * p + j
                traj = play_episode(env, agent, {"episode": j, "lambda": 0.5, "episode_seed": seed}, acting_seed(seed))
                stamp = 1_700_000_000_000_000_000 + keys.index((ek.scene_id, ek.im_id))
                eid = store_episode(writer, traj, source="configurator", agent="fixed", policy_version="v0000",
                                    episode_seed=seed, frame_stamp_ns=stamp, image_ids=False, pick_source="robot")
                outcomes.append((eid, traj.success))
        writer.close()
        with EpisodeStore(learn_dir / STORE_NAME) as store:  # the robot program's answers, as it reported them
            for i, (eid, _) in enumerate(outcomes):
                store._db.execute("UPDATE steps SET picked = ? WHERE episode_id = ? AND step = (SELECT MAX(step) "
                                  "FROM steps WHERE episode_id = ? AND picked IS NOT NULL)",
                                  (int(flip(i, _picked_last(store, eid))), eid, eid))
        for i, key in enumerate(keys):  # the frames as a cell keeps them: no ground truth
            save_frame(learn_dir / FRAMES, 1_700_000_000_000_000_000 + i, env.source.frame(*key), None)
        return outcomes

    honest = tmp_path / "honest"
    outcomes = record(honest)
    models = ModelFolder(dataset / "models")
    stats: dict[str, int] = {}
    replayable, looked = replayable_episodes(honest, models, stats=stats)
    assert looked == len(outcomes)
    assert stats["ground_truth"] == 0 and stats["robot"] == len(replayable) == sum(s for _, s in outcomes)
    assert all(ep.ground_truth is None and ep.labels is not None for ep in replayable)
    confirmed: list[bool] = []
    _, wins = replay(env, agent, replayable, confirmed)
    assert all(wins)  # the serving policy's own picks, judged by its labels: what the robot said
    assert confirmed == wins  # ... at the poses the robot picked: confirmed, not the score's
    # Without a generator free of ground truth (or told so) nothing is replayed on robot labels.
    assert replayable_episodes(honest, models, robot_labels_ok=False)[0] == []

    # Every pick reported failed: no picked pose anywhere, nothing to replay (without the learned score).
    failed = tmp_path / "all_failed"
    record(failed, flip=lambda i, picked: False)
    stats = {}
    assert replayable_episodes(failed, models, stats=stats)[0] == []
    assert stats["unlabelled"] > 0 and stats["robot"] == 0

    # Each frame estimated twice, the second pass reported flipped: contradicting objects are left out.
    flipped = tmp_path / "flipped"
    n = len(episodes)
    record(flipped, flip=lambda i, picked: (not picked) if i >= n else picked, passes=2)
    stats = {}
    kept, _ = replayable_episodes(flipped, models, stats=stats)
    assert stats["conflicting"] > 0
    with EpisodeStore(flipped / STORE_NAME, readonly=True) as store:
        objects = {(s, o) for s, o in store.query("SELECT frame_stamp_ns, obj_id FROM episodes")}
    assert len({(ep.stamp_ns, ep.model.obj_id) for ep in kept}) + stats["conflicting"] <= len(objects)


def _picked_last(store, eid: int) -> bool:
    row = store.query("SELECT picked FROM steps WHERE episode_id = ? AND picked IS NOT NULL ORDER BY step DESC LIMIT 1",
                      (eid,))
    return bool(row[0][0]) if row else False


def test_a_refused_first_call_with_candidates_is_served_not_refused(tmp_path_factory, dataset):
    """The configurator's `require_hypothesis`: a first generator call refused below its verification
    threshold leaves its ranked candidates, and a pipeline with next_candidate goes on from there (as
    its policy was trained); without next_candidate there is nothing to go on with: refused."""
    from perception_config.agents import make_agent
    from perception_config.rl.env import PerceptionConfigEnv
    from perception_config.rl.episode_loop import play_episode

    strict = CELL_PIPELINE.replace("generator: {block: resting_pose}",
                                   "generator: {block: resting_pose, params: {min_verification: 0.999}}")
    env = PerceptionConfigEnv(dataset, pipeline_file(tmp_path_factory, strict, "strict_cell.yaml"),
                              time_mode="cost_table", min_visib_fract=0.3)
    agent = make_agent("fixed", env, sequence=["next_candidate", "pick"])
    for j in range(len(env.source.episodes)):
        env.reset(options={"episode": j, "episode_seed": 5})
        if env.ops.candidates:
            break
    else:
        pytest.skip("resting_pose ranked no candidate on the tiny dataset")
    traj = play_episode(env, agent, {"episode": j, "episode_seed": 5}, 1, require_hypothesis=True)
    assert not traj.initial_info["ok"] and traj.names[0] == "next_candidate" and traj.oks[0]
    no_next = strict.replace("  - {name: next_candidate, block: next_candidate}\n", "")
    env2 = PerceptionConfigEnv(dataset, pipeline_file(tmp_path_factory, no_next, "strict_no_next.yaml"),
                               time_mode="cost_table", min_visib_fract=0.3)
    with pytest.raises(ValueError, match="no first hypothesis"):
        play_episode(env2, make_agent("fixed", env2, sequence=["pick"]), {"episode": j, "episode_seed": 5}, 1,
                     require_hypothesis=True)
