"""End to end across processes: synthetic BOP scenes recorded to MCAP, replayed by bag_replay_node
through the operator nodes and the configurator running a trained policy; the configurator's
results over the replayed frames must match the in-process run of the same policy on the same
episodes."""
from __future__ import annotations

import json

import pytest

from rl_helpers import pipeline_file, tiny_dataset
from ros_helpers import record_estimates

pytestmark = pytest.mark.ros


@pytest.fixture(scope="module")
def policy(tiny_pg_policy):
    """A pg policy trained briefly on the tiny dataset (conftest: once per session)."""
    return tiny_pg_policy


def test_replayed_bag_through_the_nodes_matches_in_process(ros_node, tmp_path_factory, tmp_path, policy):
    from perception_config.datasets.bag import bag_info
    from perception_config.datasets.bop import BopDataset
    from perception_config.ros.replay_check import format_summary, replay_check

    root = tiny_dataset(tmp_path_factory)
    keys = BopDataset(root, split="test").image_keys()  # every image: more episodes than the 1-image test split
    s = replay_check(root, tmp_path, policy=policy, image_keys=keys, images=len(keys), noise_lambda=0.5, rate=2.0)
    print(format_summary(s))
    info = bag_info(tmp_path / "replay.mcap")
    assert info["frames"] == len(keys)
    assert s["episodes"] >= 8 and s["answered"] == s["episodes"], s
    assert s["success_matches"], s
    # Same seeds, same frames, same blocks: episode by episode the same operators (Open3D's ICP is
    # reproducible only to ~1e-16, so one flip is tolerated).
    assert s["identical_episodes"] >= s["episodes"] - 1, s
    assert 0 < s["operator_time_ratio"] < 10
    rows = [json.loads(line) for line in (tmp_path / "episodes.jsonl").read_text().splitlines()]
    assert len(rows) == s["episodes"] and all(r["ros"]["operations"] for r in rows)
    assert all(len(r["ros"]["operations"]) <= 5 for r in rows)  # the policy's max_ops reached the configurator
    assert (tmp_path / "replay_check.png").stat().st_size > 10_000
    assert (tmp_path / "logs" / "bag_replay_node.log").read_text().strip()
    # The configurator appended every estimate to <out>/episodes.sqlite, with the policy's version.
    from perception_config.store.episode_store import EpisodeStore, policy_version

    with EpisodeStore(tmp_path / "episodes.sqlite", readonly=True) as store:
        eps = store.query("SELECT id, source, agent, policy_version, obj_id, episode_seed FROM episodes ORDER BY id")
        ops = [[r["action"] for r in store.iter_steps("s.episode_id = ? AND s.step > 0", (e[0],))] for e in eps]
    assert {e[1:4] for e in eps} == {("configurator", "pg", policy_version(policy))}
    assert [(e[4], e[5], o) for e, o in zip(eps, ops)] == \
        [(r["obj_id"], r["seed"], r["ros"]["operations"]) for r in rows]


def test_auto_mode_estimates_every_object_of_every_replayed_frame(ros_node, tmp_path_factory, tmp_path, request):
    """configurator_node with auto: each replayed frame's objects (from its ground truth) are
    estimated without a request, and every estimate is published as a trace and a pose."""
    import time

    import rclpy

    from perception_config.datasets.bag import write_bag
    from perception_config.datasets.bop import BopDataset
    from perception_config.launcher.supervisor import Launcher, NodeSpec

    root = tiny_dataset(tmp_path_factory)
    ds = BopDataset(root, split="test")
    expected = sum(len(ds.gt(*key)) for key in ds.image_keys())
    bag = tmp_path / "scenes.mcap"
    write_bag(root, bag, progress=False)
    traces, poses = record_estimates(ros_node, request, depth=50)
    common = {"models_dir": str(root / "models"), "pipeline": str(pipeline_file(tmp_path_factory))}
    specs = [NodeSpec(n, params=common) for n in ("generation_node", "refinement_node", "scoring_node", "pick_node")]
    specs.append(NodeSpec("configurator_node",
                          params={**common, "auto": True, "auto_every_frame": True, "noise_lambda": 0.3}))
    with open(tmp_path / "launch.log", "w") as log, Launcher(specs, log_dir=tmp_path / "logs", out=log) as launcher:
        for spec in specs:
            launcher.wait_for_line(spec.name, "serving", timeout=60)
        deadline = time.monotonic() + 20  # this process sees the configurator's publishers before the replay
        while (ros_node.count_publishers("perception/trace") < 1 or ros_node.count_publishers("perception/pose") < 1) \
                and time.monotonic() < deadline:
            rclpy.spin_once(ros_node, timeout_sec=0.05)
        time.sleep(0.5)
        # 4 frames at 10 Hz replayed at 0.2x; auto_every_frame: none is skipped even on a slow machine.
        # Start when every subscriber is there: four on the camera topics, three on the ground
        # truth (generation, pick, and the configurator, which takes nothing else).
        wait_for = [f"{t}:4" for t in ("camera/color/image_raw", "camera/depth/image_raw", "camera/camera_info")]
        replay = Launcher([NodeSpec("bag_replay_node", params={
            "bag": str(bag), "rate": 0.2, "wait_for": wait_for + ["perception/ground_truth:3"],
            "start_delay": 0.5})], out=log)
        with replay:
            deadline = time.monotonic() + 60
            while (len(traces) < expected or len(poses) < expected) and time.monotonic() < deadline:
                rclpy.spin_once(ros_node, timeout_sec=0.1)
        assert launcher.running() == [s.name for s in specs]  # every node still up, in the order started
    from collections import Counter

    got = Counter((t.header.stamp.sec, t.header.stamp.nanosec) for t in traces)
    assert len(traces) == expected, f"{len(traces)} traces for {expected} objects: {sorted(got.items())}"
    assert len(poses) == expected
    stamps = {(t.header.stamp.sec, t.header.stamp.nanosec) for t in traces}
    assert len(stamps) == len(ds.image_keys())
    assert all(t.operations and len(t.ok) == len(t.operations) for t in traces)
    assert sum(t.picked for t in traces) >= expected // 2
