"""Seconds per learner cycle with a full frame ring: 300 stored frames, labelled by the robot's picks
or by ground truth.

    .venv/bin/python benchmarks/bench_learner_cycle.py [--frames 300] [--cycles 3]

Builds a learn_dir as a cell without ground truth leaves it: `--frames` kept frames (the
dataset's images under new stamps, as a cell sees its bin again; the frame ring's size, 300, by
default), every object of each estimated by the fixed pipeline of the cell pipeline in-process
(the blocks within their time bounds, as in the cell),
its picks answered by an honest simulated robot (`pick_source` robot, frames without ground
truth). Then times `learn_once` (the learner's cycle with the configurator's defaults: 200
training episodes, up to 200 check episodes, both replayed) `--cycles` times in a row with one
environment (as the learner process keeps it: the first cycle pays the generators' searches,
the next ones reuse them), and the same on a learn_dir whose frames keep their ground truth.
Writes results/learner_cycle.json.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

CELL = "cell"


def build(learn_dir: Path, dataset: Path, frames: int, ground_truth: bool, seed: int = 0) -> int:
    """The learn_dir (module docstring); the number of stored estimates."""
    from tqdm import tqdm

    from perception_config.agents import make_agent, save_agent
    from perception_config.blocks.pipeline import load_pipeline
    from perception_config.online.policy_learner import FRAMES, POLICIES, PolicyVersions
    from perception_config.rl.env import PerceptionConfigEnv
    from perception_config.rl.episode_loop import acting_seed, play_episode
    from perception_config.rl.operators import InProcessOperators
    from perception_config.store.episode_store import STORE_NAME, StoreWriter, store_episode
    from perception_config.store.frames import save_frame

    # The blocks keep their time bounds, as in the cell that records such estimates (cost-table
    # mode alone lifts them: an unbounded resting_pose search made the recording 16 s a frame).
    pipeline = load_pipeline(CELL)
    env = PerceptionConfigEnv(dataset, pipeline, time_mode="cost_table", min_visib_fract=0.3,
                              operators=InProcessOperators(pipeline, time_bounded=True))
    agent = make_agent("fixed", env, sequence=["icp_fine", "pick", "next_candidate"])
    keys = sorted({(ek.scene_id, ek.im_id) for ek in env.source.episodes})
    writer = StoreWriter(learn_dir / STORE_NAME, print)
    stored = 0
    base = 1_700_000_000_000_000_000
    for f in tqdm(range(frames), desc="recording", unit="frame"):
        key = keys[f % len(keys)]
        stamp = base + f * 100_000_000
        for j, ek in enumerate(env.source.episodes):
            if (ek.scene_id, ek.im_id) != key:
                continue
            s = seed + f * 1000 + j + 1
            traj = play_episode(env, agent, {"episode": j, "lambda": 0.5, "episode_seed": s}, acting_seed(s))
            store_episode(writer, traj, source="configurator", agent="fixed", policy_version="v0000", episode_seed=s,
                          frame_stamp_ns=stamp, image_ids=False, pick_source="simulated" if ground_truth else "robot")
            stored += 1
        frame = env.source.frame(*key)
        save_frame(learn_dir / FRAMES, stamp, frame, {o.obj_id: o.gt for o in frame.objects} if ground_truth else None,
                   keep=frames)
    writer.close()
    path = save_agent(agent, learn_dir / "start.json", {"env_settings": env.settings.to_json(), "pipeline": CELL})
    PolicyVersions(learn_dir / POLICIES).promote(path, {"start": "fixed"})
    return stored


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dataset", type=Path, default=REPO / "data" / "default")
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--cycles", type=int, default=3)
    p.add_argument("--work", type=Path, default=REPO / "outputs" / "bench_learner_cycle")
    p.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "learner_cycle.json")
    args = p.parse_args()

    import torch

    from perception_config.datasets.bop_models import ModelFolder
    from perception_config.online.policy_learner import LearnerSettings, learn_once
    from perception_config.rl.settings import EnvSettings
    from perception_config.util.open3d_threads import open3d_single_thread

    torch.set_num_threads(1)  # as the learner process runs
    results = {"frames": args.frames, "cycles": {}, "load": None}
    for kind in ("robot", "ground_truth"):
        learn_dir = args.work / kind
        shutil.rmtree(learn_dir, ignore_errors=True)
        learn_dir.mkdir(parents=True)
        stored = build(learn_dir, args.dataset, args.frames, kind == "ground_truth")
        settings = LearnerSettings(models_dir=str(args.dataset / "models"), pipeline=CELL,
                                   env_settings=EnvSettings().to_json())
        env, models = settings.env(learn_dir), ModelFolder(settings.models_dir)  # kept across cycles, as in the learner
        seconds, lines = [], []
        for c in range(args.cycles):
            t0 = time.perf_counter()
            with open3d_single_thread(True):
                r = learn_once(learn_dir, settings, env=env, models=models)
            seconds.append(time.perf_counter() - t0)
            lines.append({k: r.get(k) for k in ("outcome", "episodes", "trained_on", "trained_total", "labels",
                                                "reason", "cost", "serving_cost")})
            print(f"{kind}: cycle {c}: {seconds[-1]:.1f} s, {lines[-1]}", flush=True)
        results["cycles"][kind] = {"stored_estimates": stored, "seconds": seconds,
                                   "median_s": float(np.median(seconds)), "results": lines}
    results["load"] = os.getloadavg()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1) + "\n")
    for kind, r in results["cycles"].items():
        print(f"{kind}: {r['stored_estimates']} estimates on {args.frames} frames: a cycle takes "
              f"{r['median_s']:.1f} s (median of {len(r['seconds'])}; {', '.join(f'{s:.1f}' for s in r['seconds'])})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
