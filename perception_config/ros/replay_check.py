"""End-to-end check through ROS: record BOP test images to MCAP, replay them through the nodes
(each its own OS process), estimate every object with the configurator, and compare with the
same policy on the same episodes in-process.

    perception-config replay-check --dataset data/default --policy runs/demo-pg/policy.safetensors

1. The policy's test images (its split seed and test fraction; the first `images` of them) are
   recorded to `<out>/replay.mcap` (the bag format of datasets/bag/).
2. generation_node, refinement_node, scoring_node, pick_node, configurator_node and
   bag_replay_node are started with the launcher; the bag is replayed at `rate` x its recorded
   timing; the operator nodes cache every frame by stamp.
3. This process calls estimate_pose for every episode (object with visib_fract >= 0.3 and a
   unique id in its image) with the episode's lambda and seed, as the robot program would.
4. The nodes are stopped; the same episodes run in-process (same env, agent, lambda, seeds).

Generator draws, agent choices and the blocks are the same on both sides, so the operator
sequences should agree episode by episode (Open3D's ICP is reproducible only to ~1e-16, so
agreement is counted, not assumed); the success rates are compared against the binomial
noise of `images` episodes. Time: the operators' seconds (each call plus the scoring after
it) and the whole estimate's wall time, ROS over in-process. Writes `<out>/results.json`,
`<out>/episodes.jsonl` and `<out>/replay_check.png`; the configurator appends its episodes to
`<out>/episodes.sqlite` (the episode store, store/episode_store.py).
"""
from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
from tqdm import tqdm

from ..agents import load_agent, make_agent
from ..agents.policy_settings import policy_settings
from ..blocks.pipeline import pipeline_reference
from ..datasets.bag import RECORDING_EPOCH_NS, write_frames
from ..datasets.bop import BopDataset
from ..launcher.ros_environment import configure_ros_environment
from ..launcher.supervisor import Launcher, NodeSpec
from ..learning.evaluation import episode_seed
from ..rl.env import PerceptionConfigEnv
from ..rl.episode_loop import acting_seed, play_episode
from ..rl.episodes import split_image_keys
from ..store.episode_store import STORE_NAME
from ..util.atomic_file import atomic_output, atomic_write
from .estimate_client import EstimateClient

RECORD_RATE_HZ = 10.0


def success_noise(p: float, n: int) -> float:
    """Two standard errors of a success share over n episodes, plus one episode: the tolerance
    for 'the same success rate within noise'."""
    return 2.0 * math.sqrt(max(p * (1 - p), 0.0) / max(n, 1)) + 1.0 / max(n, 1)


def _agent(policy: Path | None, env: PerceptionConfigEnv):
    return load_agent(policy, env) if policy else make_agent("fixed", env)


def run_in_process(env: PerceptionConfigEnv, policy: Path | None, plan: list[dict[str, Any]]) -> list[dict[str, Any]]:
    agent = _agent(policy, env)
    out = []
    for ep in tqdm(plan, desc="in-process", unit="episode", leave=False):
        t0 = time.perf_counter()
        traj = play_episode(env, agent, {"episode": ep["episode"], "lambda": ep["lambda"], "episode_seed": ep["seed"]},
                            acting_seed(ep["seed"]))
        out.append({"picked": traj.success, "operations": traj.names, "operation_seconds": traj.operation_seconds,
                    "wall": time.perf_counter() - t0})
    return out


def run_through_ros(plan: list[dict[str, Any]], stamps: dict[tuple[int, int], int],
                    timeout: float = 120.0) -> list[dict[str, Any]]:
    node = rclpy.create_node(f"replay_check_{os.getpid()}")
    try:
        client = EstimateClient(node, timeout=timeout)
        return [client.call(stamps[(ep["scene_id"], ep["im_id"])], ep["obj_id"], ep["lambda"], ep["seed"])
                for ep in tqdm(plan, desc="through ROS", unit="episode", leave=False)]
    finally:
        node.destroy_node()


def record_images(ds: BopDataset, keys: list[tuple[int, int]], bag: Path,
                  quiet: bool = True) -> tuple[dict[tuple[int, int], int], bool]:
    """Record the images `keys` of `ds` to `bag` (replacing it) at RECORD_RATE_HZ; returns each
    image's stamp and whether the dataset is RGB-only (then the bag has no depth topic)."""
    for stale in (bag, bag.parent / "metadata.yaml"):
        stale.unlink(missing_ok=True)
    rgb_only = ds.load_frame(*keys[0], with_models=False).depth is None
    frames = (ds.load_frame(s, i, with_models=False) for s, i in keys)
    write_frames(frames, bag, RECORD_RATE_HZ, progress=not quiet, total=len(keys))
    return {key: RECORDING_EPOCH_NS + round(i * 1e9 / RECORD_RATE_HZ) for i, key in enumerate(keys)}, rgb_only


def service_specs(models_dir: Path, pipeline: Any, frames: int, rgb_only: bool,
                  configurator: dict[str, Any], operators: dict[str, Any] | None = None) -> list[NodeSpec]:
    """The four operator nodes (with `operators`' extra parameters) and the configurator (with
    `configurator`'s), caching `frames` frames by stamp (a few more), on `pipeline` (None: the
    built-in one)."""
    common: dict[str, Any] = {"models_dir": str(Path(models_dir).resolve()), "cache_size": max(30, frames + 5)}
    if pipeline:
        common["pipeline"] = pipeline_reference(pipeline)
    if rgb_only:  # the operators assemble colour + camera_info frames; the configurator masks depth actions
        common["use_depth"] = False
    specs = [NodeSpec(name, params={**common, **(operators or {})})
             for name in ("generation_node", "refinement_node", "scoring_node", "pick_node")]
    specs.append(NodeSpec("configurator_node", params={**common, **configurator}))
    return specs


def replay_spec(bag: Path, rate: float, rgb_only: bool, ground_truth_subscribers: int = 2,
                **params: Any) -> NodeSpec:
    """bag_replay_node starting once the four operator nodes subscribe to the camera topics and
    `ground_truth_subscribers` to the ground truth (generation and pick, plus any client), waiting
    up to a minute for them: five node processes importing Open3D and torch at once on 2 cores
    took 12 s to subscribe on a slow machine, past the node's default 10 s, and the replay then
    went to nobody."""
    cameras = ("camera/color/image_raw", "camera/camera_info") if rgb_only else \
        ("camera/color/image_raw", "camera/depth/image_raw", "camera/camera_info")
    wait_for = [f"{t}:4" for t in cameras] + [f"perception/ground_truth:{ground_truth_subscribers}"]
    return NodeSpec("bag_replay_node", params={"bag": str(bag), "rate": float(rate), "start_delay": 0.5,
                                               "wait_for": wait_for, "wait_timeout": 60.0, **params})


def replay_check(
    dataset: str | Path, out: str | Path, policy: str | Path | None = None, pipeline: str | Path | None = None,
    images: int = 8, noise_lambda: float = 0.5, seed: int = 0, rate: float = 1.0, quiet: bool = True,
    image_keys: list[tuple[int, int]] | None = None, composed: bool = False,
) -> dict[str, Any]:
    """Run the check (see the module docstring); returns the summary written to results.json.
    `image_keys` replaces the policy's test images (e.g. every image of a tiny dataset);
    `composed`: the five service nodes in one process (ros/composed.py)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    policy = Path(policy).resolve() if policy else None
    settings = policy_settings([policy] if policy else [], pipeline=pipeline)
    ds = BopDataset(Path(dataset), split="test")
    if image_keys is None:
        image_keys = split_image_keys(ds.image_keys(), settings.test_fraction, settings.split_seed)[1]
    keys = sorted(image_keys)[: max(1, int(images))]

    bag = out / "replay.mcap"
    stamps, rgb_only = record_images(ds, keys, bag, quiet)

    # The policy's settings, time measured (the configurator measures it too).
    env = PerceptionConfigEnv(ds, settings.pipeline, settings.env.replace(time_mode="measured"), image_keys=keys)
    counts: dict[tuple[int, int, int], int] = {}
    for ek in env.source.episodes:
        counts[(ek.scene_id, ek.im_id, ek.obj_id)] = counts.get((ek.scene_id, ek.im_id, ek.obj_id), 0) + 1
    plan = [{"episode": j, "scene_id": ek.scene_id, "im_id": ek.im_id, "obj_id": ek.obj_id,
             "lambda": float(noise_lambda), "seed": episode_seed(seed, j)}
            for j, ek in enumerate(env.source.episodes) if counts[(ek.scene_id, ek.im_id, ek.obj_id)] == 1]

    specs = service_specs(Path(ds.models_dir), settings.pipeline, len(keys), rgb_only,
                          {"policy": str(policy or ""), "noise_lambda": float(noise_lambda),
                           "max_ops": settings.env.max_ops, "episode_store": str(out.resolve() / STORE_NAME)})
    specs.append(replay_spec(bag, rate, rgb_only))
    log_dir = out / "logs"
    with open(out / "launch.log", "w") as launch_log:
        launcher = Launcher(specs, log_dir=log_dir, out=launch_log if quiet else None, composed=composed)
        servers = {s.name for s in specs[:5]}
        with launcher:
            deadline = time.monotonic() + 60.0 + len(keys) / (RECORD_RATE_HZ * rate if rate > 0 else 1e9)
            while launcher.returncode("bag_replay_node") is None and time.monotonic() < deadline:
                if launcher.wait(timeout=0.2) is not None:  # a node died: the launcher stopped them all
                    break
            if launcher.returncode("bag_replay_node") != 0 or set(launcher.running()) != servers:
                raise RuntimeError(f"the replay did not finish cleanly (see {log_dir}): "
                                   f"still running {launcher.running()}")
            ros = run_through_ros(plan, stamps)
            if set(launcher.running()) != servers:
                raise RuntimeError(f"a node died during the check (see {log_dir}): still running {launcher.running()}")
    local = run_in_process(env, policy, plan)
    return _summarise(out, plan, ros, local, policy, keys, composed)


def _summarise(out: Path, plan, ros, local, policy, keys, composed: bool = False) -> dict[str, Any]:
    n = len(plan)
    p_ros = sum(r["picked"] for r in ros) / n
    p_local = sum(r["picked"] for r in local) / n
    same = sum(r["operations"] == l_["operations"] and r["picked"] == l_["picked"] for r, l_ in zip(ros, local))
    ops_ros = sum(sum(r["operation_seconds"]) for r in ros)
    ops_local = sum(sum(l_["operation_seconds"]) for l_ in local)
    wall_ros = sum(r["wall"] for r in ros)
    wall_local = sum(l_["wall"] for l_ in local)
    tol = success_noise(p_local, n)
    summary = {
        "policy": str(policy) if policy else "fixed pipeline", "images": len(keys), "episodes": n,
        "nodes": "composed (one process)" if composed else "separate processes",
        "answered": sum(r["success"] for r in ros),
        "success_ros": p_ros, "success_in_process": p_local, "success_tolerance": tol,
        "success_matches": abs(p_ros - p_local) <= tol,
        "identical_episodes": same,
        "operator_seconds_ros": ops_ros, "operator_seconds_in_process": ops_local,
        "operator_time_ratio": ops_ros / ops_local if ops_local > 0 else None,
        "wall_seconds_ros": wall_ros, "wall_seconds_in_process": wall_local,
        "wall_time_ratio": wall_ros / wall_local if wall_local > 0 else None,
        "median_episode_wall_ros": float(np.median([r["wall"] for r in ros])),
        "median_episode_wall_in_process": float(np.median([l_["wall"] for l_ in local])),
    }
    atomic_write(out / "results.json", json.dumps(summary, indent=2) + "\n")
    atomic_write(out / "episodes.jsonl", "".join(json.dumps({**p, "ros": r, "in_process": l_}) + "\n"
                                                 for p, r, l_ in zip(plan, ros, local)))
    _plot(out / "replay_check.png", ros, local, summary)
    return summary


def _plot(path: Path, ros, local, summary) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    ax = axes[0]
    ax.bar(["in-process", "through ROS"], [summary["success_in_process"], summary["success_ros"]],
           color=["tab:blue", "tab:orange"])
    ax.set_ylim(0, 1)
    ax.set_ylabel("episodes with a successful pick")
    ax.set_title(f"{summary['episodes']} episodes, {summary['identical_episodes']} identical")
    ax = axes[1]
    x = [sum(l_["operation_seconds"]) * 1000 for l_ in local]
    y = [sum(r["operation_seconds"]) * 1000 for r in ros]
    ax.scatter(x, y, s=14, c=["tab:green" if r["picked"] else "tab:red" for r in ros])
    top = max(x + y + [1.0]) * 1.05
    ax.plot([0, top], [0, top], "k--", lw=0.8, label="equal")
    ax.plot([0, top], [0, 1.1 * top], ":", color="gray", lw=0.8, label="1.10x")
    ax.set_xlabel("operator time in-process (ms)")
    ax.set_ylabel("operator time through ROS (ms)")
    ax.set_title(f"ROS / in-process: {summary['operator_time_ratio']:.2f}x")
    ax.legend()
    fig.tight_layout()
    try:
        with atomic_output(path) as tmp:
            fig.savefig(tmp, dpi=110)
    finally:
        plt.close(fig)


def format_summary(s: dict[str, Any]) -> str:
    verdict = "matches" if s["success_matches"] else "DIFFERS from"
    return "\n".join([
        f"replayed {s['images']} images, {s['episodes']} episodes, policy: {s['policy']}, nodes: {s['nodes']}",
        f"success through ROS {s['success_ros']:.1%} {verdict} in-process {s['success_in_process']:.1%} "
        f"(tolerance {s['success_tolerance']:.1%}); {s['identical_episodes']} of {s['episodes']} episodes identical",
        f"operator time through ROS / in-process: {s['operator_time_ratio']:.3f}x "
        f"({s['operator_seconds_ros']:.3f} s / {s['operator_seconds_in_process']:.3f} s); "
        f"whole estimate wall time {s['wall_time_ratio']:.3f}x",
    ])


def run_cli(args: Any) -> int:
    """`perception-config replay-check`: exit 0 when the success rates match within noise."""
    configure_ros_environment()  # loopback defaults before rclpy starts
    rclpy.init()
    try:
        s = replay_check(args.dataset, args.out, args.policy, args.pipeline, args.images, args.noise_lambda,
                         rate=args.rate, composed=args.composed)
    finally:
        rclpy.try_shutdown()
    print(format_summary(s))
    print(f"wrote {Path(args.out) / 'results.json'} and {Path(args.out) / 'replay_check.png'}")
    return 0 if s["success_matches"] else 1
