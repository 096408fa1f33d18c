"""The same episodes through ROS and in-process: the cell composed and as separate processes, and
the round trip of each operator call.

    .venv/bin/python benchmarks/bench_ros.py --replay-check 3 [--policy FILE|none] [--images 8]
    .venv/bin/python benchmarks/bench_ros.py [--dataset data/default] [--policy FILE] [--images 6] [--out FILE.json]

`--replay-check ROUNDS`: `perception-config replay-check` ROUNDS times in each node layout,
alternating separate processes and composed (one process, `launch --composed`) so that machine
noise hits both: every episode's estimate through estimate_pose against the same episode
in-process. Reported per layout: the median over rounds of the operator time and of the whole
estimate's wall time, ROS over in-process (targets: composed <= 1.15x, separate <= 1.30x), the
same ratio on the operators that change the hypothesis (generation and refinement: in-process
also re-scores an unchanged hypothesis after a pick, which the nodes skip), and whether every
episode was identical. Writes results/ros_layouts.json and .png; each round's replay-check folder
(bag, node logs, episodes) goes to outputs/bench_ros_layouts/.

Without it:

The four operator nodes run as separate processes (started with the launcher); this process
publishes the dataset's test images (camera topics + ground truth) once, then runs every episode
(object with visib_fract >= 0.3, lambda 0.5, seeded) twice, interleaved so machine noise hits both
alike: in-process (InProcessOperators) and through ROS (RosOperators: every operator call a
service request, as in configurator_node). The agent is the policy (default: the newest
runs/*/policy.safetensors) or the fixed pipeline.

Reported: the operator time of the whole set (each action plus the scoring after it), ROS over
in-process (target <= 1.10x); per action the median seconds on both sides and inside the
operator node; per service the median round trip, the node's own time and the difference
(middleware + rclpy). Writes JSON; the nodes' logs go to <out>.logs/.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before numpy/open3d start their thread pools

import argparse
import json
import platform
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import rclpy  # noqa: E402

from perception_config.launcher.ros_environment import configure_ros_environment  # noqa: E402
from perception_config.util.atomic_file import atomic_write  # noqa: E402

DEFAULT_OUT = str(REPO / "benchmarks" / "results" / "ros.json")


def newest_policy() -> Path | None:
    found = sorted((REPO / "runs").glob("*/policy.safetensors"), key=lambda p: p.stat().st_mtime)
    return found[-1] if found else None


def publish_frames(node, ds, keys) -> dict:
    from perception_config_interfaces.msg import ObjectPoses
    from sensor_msgs.msg import CameraInfo, Image

    from perception_config.ros.conversions import frame_to_msgs, pose_to_msg

    pubs = [node.create_publisher(t, n, 10) for t, n in (
        (ObjectPoses, "perception/ground_truth"), (CameraInfo, "camera/camera_info"),
        (Image, "camera/depth/image_raw"), (Image, "camera/color/image_raw"))]
    deadline = time.monotonic() + 30
    while any(p.get_subscription_count() < (2 if i == 0 else 4) for i, p in enumerate(pubs)):
        if time.monotonic() > deadline:
            raise RuntimeError("the operator nodes' subscriptions did not match within 30 s")
        time.sleep(0.05)
    stamps = {}
    for i, key in enumerate(keys):
        frame = ds.load_frame(*key)
        stamp = (1_700_000_000 + i) * 1_000_000_000
        color, depth, info = frame_to_msgs(frame, stamp)
        gt = ObjectPoses(header=color.header, object_ids=[str(o.obj_id) for o in frame.objects],
                         poses=[pose_to_msg(o.gt) for o in frame.objects])
        for pub, msg in zip(pubs, (gt, info, depth, color)):
            pub.publish(msg)
        stamps[key] = stamp
        time.sleep(0.05)
    time.sleep(0.5)
    return stamps


def run(env, agent, episode, seed, lam) -> tuple[list[str], list[float], list[float], bool]:
    from perception_config.rl.episode_loop import acting_seed, play_episode

    traj = play_episode(env, agent, {"episode": episode, "lambda": lam, "episode_seed": seed}, acting_seed(seed))
    # block_seconds through ROS: the operator node's own time
    return traj.names, traj.operation_seconds, traj.block_seconds, traj.success


def changed_hypothesis_ratio(episodes_jsonl: Path) -> float | None:
    """ROS over in-process operator time on the generation and refinement operators of the
    episodes whose operators agreed (picks excluded: module docstring)."""
    ros = local = 0.0
    for line in episodes_jsonl.read_text().splitlines():
        row = json.loads(line)
        r, loc = row["ros"], row["in_process"]
        if r["operations"] != loc["operations"]:
            continue
        for name, a, b in zip(r["operations"], r["operation_seconds"], loc["operation_seconds"]):
            if name != "pick":
                ros, local = ros + a, local + b
    return ros / local if local else None


def replay_layouts(args) -> int:
    from perception_config.ros.replay_check import replay_check

    policy = None if args.policy == "none" else (Path(args.policy) if args.policy else newest_policy())
    out = Path(args.out if args.out != DEFAULT_OUT else REPO / "benchmarks" / "results" / "ros_layouts.json")
    work = REPO / "outputs" / f"bench_{out.stem}"  # each round's bag, logs and episodes (not kept in git)
    configure_ros_environment()
    rclpy.init()
    rounds: list[dict] = []
    try:
        for r in range(args.replay_check):
            for composed in ((False, True) if r % 2 == 0 else (True, False)):
                layout = "composed" if composed else "separate"
                s = replay_check(args.dataset, work / f"{layout}_{r}", policy, images=args.images,
                                 noise_lambda=args.lam, composed=composed)
                row = {"round": r, "layout": layout, "episodes": s["episodes"],
                       "identical_episodes": s["identical_episodes"], "operator_time_ratio": s["operator_time_ratio"],
                       "wall_time_ratio": s["wall_time_ratio"],
                       "changed_hypothesis_ratio": changed_hypothesis_ratio(work / f"{layout}_{r}" / "episodes.jsonl"),
                       "load": os.getloadavg()[0]}
                rounds.append(row)
                print(f"round {r} {layout:9s}: operator time {row['operator_time_ratio']:.3f}x, wall "
                      f"{row['wall_time_ratio']:.3f}x, generation+refinement {row['changed_hypothesis_ratio']:.3f}x, "
                      f"{row['identical_episodes']}/{row['episodes']} identical", flush=True)
    finally:
        rclpy.try_shutdown()
    targets = {"composed": 1.15, "separate": 1.30}
    summary = {}
    for layout, target in targets.items():
        rows = [x for x in rounds if x["layout"] == layout]
        summary[layout] = {k: float(np.median([x[k] for x in rows])) for k in (
            "operator_time_ratio", "wall_time_ratio", "changed_hypothesis_ratio")}
        summary[layout]["range_operator_time_ratio"] = [min(x["operator_time_ratio"] for x in rows),
                                                        max(x["operator_time_ratio"] for x in rows)]
        summary[layout]["every_episode_identical"] = all(x["identical_episodes"] == x["episodes"] for x in rows)
        summary[layout]["target"] = target
        summary[layout]["target_met"] = max(summary[layout]["operator_time_ratio"],
                                            summary[layout]["wall_time_ratio"]) <= target
    result = {"machine": platform.node(), "policy": str(policy) if policy else "fixed pipeline",
              "images": args.images, "rounds": rounds, "summary": summary}
    atomic_write(out, json.dumps(result, indent=2) + "\n")
    _plot_layouts(out.with_suffix(".png"), rounds, targets)
    for layout, v in summary.items():
        print(f"{layout:9s}: median operator time {v['operator_time_ratio']:.3f}x, wall {v['wall_time_ratio']:.3f}x, "
              f"generation+refinement {v['changed_hypothesis_ratio']:.3f}x (target <= {v['target']:.2f}: "
              f"{'met' if v['target_met'] else 'missed'}); every episode identical: {v['every_episode_identical']}")
    print(f"wrote {out} and {out.with_suffix('.png')}")
    return 0


def _plot_layouts(path: Path, rounds: list[dict], targets: dict[str, float]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    keys = ("operator_time_ratio", "wall_time_ratio", "changed_hypothesis_ratio")
    labels = ("operator time", "estimate wall time", "generation + refinement")
    for i, layout in enumerate(targets):
        rows = [x for x in rounds if x["layout"] == layout]
        for j, key in enumerate(keys):
            xs = [i * 4 + j] * len(rows)
            ax.scatter(xs, [x[key] for x in rows], color=f"C{j}", label=labels[j] if i == 0 else None)
        ax.hlines(targets[layout], i * 4 - 0.5, i * 4 + 2.5, colors="k", linestyles="--", lw=0.8)
    ax.set_xticks([1, 5])
    ax.set_xticklabels([f"{layout} (target {t:.2f}x)" for layout, t in targets.items()])
    ax.set_ylabel("through ROS / in-process")
    ax.axhline(1.0, color="gray", lw=0.5)
    ax.legend(fontsize=8)
    ax.set_title("the same episodes through the nodes and in-process, per round")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dataset", default=str(REPO / "data" / "default"))
    p.add_argument("--policy", default=None,
                   help="policy file (default: the newest runs/*/policy.safetensors; 'none' = fixed)")
    p.add_argument("--images", type=int, default=6)
    p.add_argument("--lambda", dest="lam", type=float, default=0.5)
    p.add_argument("--separate-scoring", action="store_true",
                   help="every scoring a call to scoring_node (no fused scoring)")
    p.add_argument("--out", default=DEFAULT_OUT)
    p.add_argument("--replay-check", type=int, default=0, metavar="ROUNDS",
                   help="compare the layouts: replay-check ROUNDS times composed and separate (module docstring)")
    args = p.parse_args()
    if args.replay_check:
        return replay_layouts(args)

    from perception_config.agents import load_agent, make_agent
    from perception_config.agents.policy_settings import policy_settings
    from perception_config.blocks.pipeline import load_pipeline
    from perception_config.datasets.bop import BopDataset
    from perception_config.launcher.supervisor import Launcher, NodeSpec
    from perception_config.learning.evaluation import episode_seed
    from perception_config.rl.env import PerceptionConfigEnv
    from perception_config.rl.episodes import EpisodeSource, split_image_keys
    from perception_config.rl.operators import Episode
    from perception_config.ros.ros_operators import RosOperators

    policy = None if args.policy == "none" else (Path(args.policy) if args.policy else newest_policy())
    settings = policy_settings([policy] if policy else [])
    pipeline = load_pipeline(settings.pipeline)
    ds = BopDataset(Path(args.dataset), split="test")
    keys = split_image_keys(ds.image_keys(), settings.test_fraction, settings.split_seed)[1][: args.images]
    source = EpisodeSource(ds, keys)
    local_env = PerceptionConfigEnv(source, pipeline, settings.env.replace(time_mode="measured"))

    common = {"models_dir": str(Path(ds.models_dir).resolve()), "cache_size": len(keys) + 10}
    if settings.pipeline:
        common["pipeline"] = str(Path(settings.pipeline).resolve())
    logs = Path(args.out).with_suffix(".logs")
    configure_ros_environment()  # loopback defaults before rclpy starts
    rclpy.init()
    node = rclpy.create_node("bench_ros")  # publishes the frames
    ops = RosOperators(pipeline, node_name="bench_ros_operators", timeout=30.0, fused_scoring=not args.separate_scoring)
    ros_env = PerceptionConfigEnv(None, pipeline, settings.env.replace(time_mode="measured"), operators=ops)
    local_agent = load_agent(policy, local_env) if policy else make_agent("fixed", local_env)
    ros_agent = load_agent(policy, ros_env) if policy else make_agent("fixed", ros_env)

    with open(os.devnull, "w") as quiet, Launcher(
            [NodeSpec(n, params=common) for n in ("generation_node", "refinement_node", "scoring_node", "pick_node")],
            log_dir=logs, out=quiet) as launcher:
        for name in ("generation_node", "refinement_node", "scoring_node", "pick_node"):
            launcher.wait_for_line(name, "serving", timeout=60)
        stamps = publish_frames(node, ds, keys)
        per_action: dict[str, dict[str, list[float]]] = defaultdict(lambda: {"ros": [], "in_process": [], "node": []})
        totals = {"ros": 0.0, "in_process": 0.0}
        same = 0
        n = len(source)
        for j in range(n):
            ek = source.episodes[j]
            seed = episode_seed(0, j)
            l_names, l_sec, _, l_ok = run(local_env, local_agent, j, seed, args.lam)
            ep = source.load(j, args.lam, seed)
            ros_ep = Episode(frame=None, model=ep.model, ground_truth=None, noise_lambda=args.lam, seed=seed,
                             key=ep.key, stamp_ns=stamps[(ek.scene_id, ek.im_id)])
            r_names, r_sec, r_own, r_ok = run(ros_env, ros_agent, ros_ep, seed, args.lam)
            same += (l_names, l_ok) == (r_names, r_ok)
            if l_names == r_names:  # per-action figures only where both ran the same operators
                for a, x, y, z in zip(l_names, l_sec, r_sec, r_own):
                    per_action[a]["in_process"].append(x)
                    per_action[a]["ros"].append(y)
                    per_action[a]["node"].append(z)
                totals["in_process"] += sum(l_sec)
                totals["ros"] += sum(r_sec)
            print(f"\r{j + 1}/{n} episodes", end="", flush=True)
        print()
    ops.close()
    node.destroy_node()
    rclpy.try_shutdown()

    services: dict[str, dict[str, float]] = {}
    by_service: dict[str, list[tuple[float, float]]] = defaultdict(list)
    for which, rt, own in ops.round_trips:
        by_service[which].append((rt, own))
    for which, rows in by_service.items():
        rt = np.array([r for r, _ in rows]) * 1000
        own = np.array([o for _, o in rows]) * 1000
        services[which] = {"calls": len(rows), "round_trip_ms": float(np.median(rt)), "node_ms": float(np.median(own)),
                           "overhead_ms": float(np.median(rt - own))}
    actions = {a: {"n": len(v["ros"]), "ros_ms": float(np.median(v["ros"]) * 1000),
                   "node_ms": float(np.median(v["node"]) * 1000),
                   "in_process_ms": float(np.median(v["in_process"]) * 1000)} for a, v in per_action.items()}
    ratio = totals["ros"] / totals["in_process"] if totals["in_process"] else None
    result = {
        "machine": platform.node(), "policy": str(policy) if policy else "fixed pipeline", "images": len(keys),
        "fused_scoring": not args.separate_scoring, "episodes": n, "identical_episodes": same,
        "operator_seconds": totals, "ros_over_in_process": ratio,
        "target": 1.10, "actions": actions, "services": services,
    }
    out = Path(args.out)
    atomic_write(out, json.dumps(result, indent=2) + "\n")

    print(f"{n} episodes ({same} identical), policy {result['policy']}, "
          f"{'fused scoring' if result['fused_scoring'] else 'scoring through scoring_node'}")
    print(f"operator time through ROS / in-process: {ratio:.3f}x "
          f"({totals['ros']:.3f} s / {totals['in_process']:.3f} s; target <= 1.10)")
    print(f"{'action':<14}{'n':>5}{'in-process ms':>15}{'ROS ms':>9}{'in nodes ms':>13}")
    for a, v in sorted(actions.items()):
        print(f"{a:<14}{v['n']:>5}{v['in_process_ms']:>15.2f}{v['ros_ms']:>9.2f}{v['node_ms']:>13.2f}")
    print(f"{'service':<10}{'calls':>7}{'round trip ms':>15}{'node ms':>9}{'overhead ms':>13}")
    for s, v in sorted(services.items()):
        print(f"{s:<10}{v['calls']:>7}{v['round_trip_ms']:>15.2f}{v['node_ms']:>9.2f}{v['overhead_ms']:>13.2f}")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
