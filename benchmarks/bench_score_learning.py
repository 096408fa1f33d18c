"""A cell that learns its pick-success score: the learner's refit (online/score_learner.py) as estimates come in.

    python benchmarks/bench_score_learning.py [--dataset data/default] [--estimates 160] [--every 20]
        [--outcomes-only] [--out benchmarks/results/score_learning_synthetic.json]
    python benchmarks/bench_score_learning.py --dataset ../shared/data/lmo-rgb --rgb \\
        --out benchmarks/results/score_learning_lmo_rgb.json

The dataset's images are split by the agents' own train/test split (episodes.split_image_keys):
the "cell" sees the train images, one estimate after the other (every object of an image, a
random masked policy, lambda drawn from 0.1..1.0, cost-table time), each recorded the way the
configurator records it (the episode store with source "configurator", the frame kept in
frames/ with its ground truth). The score's judge is the test images, which the cell never
sees: their hypotheses (played the same way once, before the cell starts) are scored by the
serving version after every learner cycle (every `--every` estimates) — held-out AUC, Brier
and ECE of what serves, against the shipped model's (fitted on the default dataset's train
images: the test images are unseen by both). `--outcomes-only`: the frames are kept
without ground truth and every pick's result is reported as the robot's (report_pick_outcome),
so the learner has only the pick outcomes to learn from, as in a cell without ground truth.
`--rgb`: the dataset read without depth and the shipped RGB-only pipeline's actions.
Writes the JSON and a PNG beside it (held-out Brier of the serving score per estimate).
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import json
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from perception_config.agents import make_agent  # noqa: E402
from perception_config.blocks.pick_success import SHIPPED_MODEL, load_model, resolve_model_path  # noqa: E402
from perception_config.core.score_metrics import score_metrics  # noqa: E402
from perception_config.learning.pick_success_data import featurise  # noqa: E402
from perception_config.online.score_learner import format_score_result, refit_score_once, score_versions  # noqa: E402
from perception_config.rl.env import PerceptionConfigEnv  # noqa: E402
from perception_config.rl.episode_loop import acting_seed, play_episode  # noqa: E402
from perception_config.rl.episodes import DEFAULT_SPLIT_SEED, DEFAULT_TEST_FRACTION, split_image_keys  # noqa: E402
from perception_config.store.episode_store import STORE_NAME, EpisodeStore, StoreWriter, store_episode  # noqa: E402
from perception_config.store.frames import save_frame  # noqa: E402
from perception_config.util.atomic_file import atomic_write  # noqa: E402

LAMBDAS = (0.1, 0.3, 0.5, 0.7, 1.0)


def play(env: PerceptionConfigEnv, indices: list[int], seed: int) -> list:
    """One random-policy trajectory per episode index (seeded)."""
    agent = make_agent("random", env, seed=seed)
    rng = np.random.default_rng(seed)
    out = []
    for i in indices:
        lam = float(LAMBDAS[int(rng.integers(len(LAMBDAS)))])
        ep_seed = int(rng.integers(1, 2**31))
        out.append((i, lam, ep_seed, play_episode(env, agent, {"episode": i, "lambda": lam, "episode_seed": ep_seed},
                                                  acting_seed(ep_seed))))
    return out


def judge_table(env: PerceptionConfigEnv, dataset: Path, indices: list[int], seed: int, rgb: bool):
    """The held-out hypotheses (the test images), labelled by the ground truth."""
    with tempfile.TemporaryDirectory() as tmp:
        writer = StoreWriter(Path(tmp) / STORE_NAME, print)
        for _, _, ep_seed, traj in play(env, indices, seed):
            assert store_episode(writer, traj, source="evaluate", agent="random", policy_version="judge",
                                 dataset=str(dataset), episode_seed=ep_seed)
        writer.close()
        with EpisodeStore(Path(tmp) / STORE_NAME, readonly=True) as store:
            rows = [r for r in store.iter_steps() if r.get("pose") is not None]
    for r in rows:
        r["picked"] = None  # labels from the ground truth only
    return featurise(rows, dataset=dataset, with_rgb_only=False, progress=False)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", type=Path, default=REPO / "data" / "default")
    ap.add_argument("--rgb", action="store_true", help="RGB-only: no depth, the shipped rgb pipeline")
    ap.add_argument("--estimates", type=int, default=160, help="estimates of the cell (cycled over its images)")
    ap.add_argument("--every", type=int, default=20, help="estimates between two learner cycles")
    ap.add_argument("--margin", type=float, default=0.05)
    ap.add_argument("--outcomes-only", action="store_true",
                    help="frames kept without ground truth; the picks' results reported as the robot's")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "score_learning_synthetic.json")
    args = ap.parse_args()
    if not (args.dataset / "models").is_dir():
        print(f"no dataset at {args.dataset}: nothing measured")
        return 0
    warnings.simplefilter("ignore")  # real annotations' near-rotations are projected, with a warning
    pipeline = "rgb" if args.rgb else None
    env = PerceptionConfigEnv(args.dataset, pipeline, use_depth=not args.rgb, time_mode="cost_table", max_ops=6)
    keys = sorted({(e.scene_id, e.im_id) for e in env.source.episodes})
    train_keys, test_keys = split_image_keys(keys, DEFAULT_TEST_FRACTION, DEFAULT_SPLIT_SEED)
    train_set, test_set = set(map(tuple, train_keys)), set(map(tuple, test_keys))
    cell_idx = [i for i, e in enumerate(env.source.episodes) if (e.scene_id, e.im_id) in train_set]
    judge_idx = [i for i, e in enumerate(env.source.episodes) if (e.scene_id, e.im_id) in test_set]
    t0 = time.perf_counter()
    judge = judge_table(env, args.dataset, judge_idx, args.seed + 1, args.rgb)
    print(f"judge: {len(judge)} hypotheses of {len(set(judge.images))} images the cell never sees "
          f"({time.perf_counter() - t0:.0f} s)")

    shipped = load_model(str(resolve_model_path(SHIPPED_MODEL)))
    out_rows = []
    with tempfile.TemporaryDirectory() as tmp:
        learn_dir = Path(tmp) / "learn"
        versions = score_versions(learn_dir)
        versions.promote(resolve_model_path(SHIPPED_MODEL), {"start": SHIPPED_MODEL})
        writer = StoreWriter(learn_dir / STORE_NAME, print)
        order = [cell_idx[k % len(cell_idx)] for k in range(args.estimates)]
        stamp_of = {k: 1_700_000_000_000_000_000 + n * 1_000_000_000 for n, k in enumerate(sorted(train_set))}

        def judged(done: int, cycle: dict | None) -> None:
            model = load_model(str(versions.path(versions.current())))
            m = score_metrics(model.predict(judge.X), judge.y)
            row = {"estimates": done, "version": versions.current(), "auc": m["auc"], "brier": m["brier"],
                   "ece": m["ece"], "cycle": cycle}
            out_rows.append(row)
            print(f"{done:4d} estimates: serving {row['version']}  judge AUC {m['auc']:.3f}  Brier {m['brier']:.4f}  "
                  f"ECE {m['ece']:.3f}" + (f"   | {format_score_result(cycle)}" if cycle else ""))

        judged(0, None)
        trajectories = play(env, order, args.seed)
        for done, (i, _, ep_seed, traj) in enumerate(trajectories, start=1):
            e = env.source.episodes[i]
            stamp = stamp_of[(e.scene_id, e.im_id)]
            eid = store_episode(writer, traj, source="configurator", agent="random", policy_version="v0000",
                                episode_seed=ep_seed, frame_stamp_ns=stamp, image_ids=False)
            assert eid is not None
            frame = env.source.frame(e.scene_id, e.im_id)
            save_frame(learn_dir / "frames", stamp, frame,
                       None if args.outcomes_only else {o.obj_id: o.gt for o in frame.objects if o.gt is not None})
            if args.outcomes_only:  # the robot reports each pick (here: what the simulation said)
                with EpisodeStore(learn_dir / STORE_NAME) as store:
                    for step, picked in store.query("SELECT step, picked FROM steps WHERE episode_id = ? AND "
                                                    "picked IS NOT NULL", (eid,)):
                        store.record_pick_outcome(eid, step, bool(picked), "robot")
            if done % args.every == 0:
                t = time.perf_counter()
                cycle = refit_score_once(learn_dir, args.dataset / "models", args.margin, args.seed)
                cycle["cycle_seconds"] = time.perf_counter() - t
                judged(done, cycle)
        writer.close()
    m0 = score_metrics(shipped.predict(judge.X), judge.y)
    result = {"dataset": str(args.dataset), "rgb": args.rgb, "outcomes_only": args.outcomes_only,
              "estimates": args.estimates, "every": args.every, "margin": args.margin, "seed": args.seed,
              "cell_images": len(train_set), "judge_images": len(set(judge.images)), "judge_hypotheses": len(judge),
              "judge_success_rate": float(judge.y.mean()),
              "shipped": {k: m0[k] for k in ("auc", "brier", "ece")}, "per_cycle": out_rows,
              "promotions": sum(1 for r in out_rows if r["cycle"] and r["cycle"]["outcome"] == "promoted")}
    atomic_write(args.out, json.dumps(result, indent=1, default=float) + "\n")
    from perception_config.core.plots import plt, save_figure

    fig, ax = plt.subplots(figsize=(7, 4))
    xs = [r["estimates"] for r in out_rows]
    ax.step(xs, [r["brier"] for r in out_rows], where="post", label="serving score, Brier on unseen images")
    ax.axhline(m0["brier"], color="0.5", ls="--", label="shipped model")
    for r in out_rows:
        if r["cycle"] and r["cycle"]["outcome"] == "promoted":
            ax.annotate(r["version"], (r["estimates"], r["brier"]), fontsize=7)
    ax.set(xlabel="estimates of the cell", ylabel="Brier (lower is better)",
           title=f"pick_success learned in the cell: {Path(args.dataset).name}"
                 + (" (pick outcomes only)" if args.outcomes_only else ""))
    ax.legend(fontsize=8)
    fig.tight_layout()
    png = save_figure(fig, args.out.with_suffix(".png"))
    print(f"wrote {args.out} and {png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
