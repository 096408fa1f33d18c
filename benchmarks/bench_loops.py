"""Degenerate loops: how many test episodes a greedy policy ends truncated after going round in a loop.

    python benchmarks/bench_loops.py --policy runs/bench-study/default-pick_success/study/seed-0/policy.safetensors
        [--no-mask-policy RUN/policy.safetensors] [--dataset data/default] [--episodes 100]
        [--lambdas 0.1,...,1.0] [--workers 2]

A loop step is an action that ends at a hypothesis the episode had already reached (it left the
hypothesis unchanged, or undid an earlier step; rl/pose_memory.py); a loop truncation is an episode
that used up max_ops without a successful pick and had such a step. Two remedies exist: the
observation's pose change of the last step (always there) and the environment's loop rule, which
masks actions already taken at the current hypothesis (`loop_mask`, on by default). For the policy
trained with the rule, its greedy episodes are counted with the rule (as deployed) and without it
(the observation feature alone at test time); `--no-mask-policy`, a policy trained with
`loop_mask` off (`perception-config train ... --no-loop-mask`), is counted
without the rule (the feature alone, trained and tested). `--episodes` per lambda over ten lambdas:
1000 test episodes per row by default (the test images cycled, each pass with fresh seeds).

Writes benchmarks/results/loops.json.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def count(dataset: Path, policy: Path, lambdas: list[float], episodes: int, workers: int, loop_mask: bool) -> dict:
    from perception_config.learning.evaluation import evaluate

    with tempfile.TemporaryDirectory() as tmp:
        results = evaluate(dataset, [str(policy)], lambdas, tmp, episodes_per_lambda=episodes,
                           include_baselines=False, plots=False, store_episodes=False, workers=workers,
                           loop_mask=loop_mask, progress=True)
        records = json.loads(Path(results).read_text())
        lines = [json.loads(line) for line in (Path(results).parent / "episodes.jsonl").read_text().splitlines()]
    truncated = [e for e in lines if e.get("truncated")]
    n = sum(r["episodes"] for r in records)
    return {"policy": str(policy), "loop_mask_at_test": loop_mask, "episodes": n,
            "truncated": sum(r["truncated"] for r in records),
            "loop_truncations": sum(r["loop_truncations"] for r in records),
            "success": sum(r["n_success"] for r in records) / n,
            "truncated_examples": [{"lambda": e["lambda"], "obj_id": e["obj_id"], "actions": e["actions"],
                                    "loop_steps": e["loop_steps"]} for e in truncated[:8]],
            "per_lambda": {str(r["lambda"]): {"truncated": r["truncated"], "loop_truncations": r["loop_truncations"],
                                              "success": r["success"]} for r in records}}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--policy", type=Path, required=True, help="a policy trained with the loop rule (the default)")
    ap.add_argument("--no-mask-policy", type=Path, default=None, help="a policy trained with loop_mask off")
    ap.add_argument("--dataset", type=Path, default=ROOT / "data" / "default")
    ap.add_argument("--episodes", type=int, default=100, help="per lambda")
    ap.add_argument("--lambdas", default=",".join(f"{0.1 * i:.1f}" for i in range(1, 11)))
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "loops.json")
    args = ap.parse_args()
    lambdas = [float(x) for x in args.lambdas.split(",")]
    rows = [count(args.dataset, args.policy, lambdas, args.episodes, args.workers, True),
            count(args.dataset, args.policy, lambdas, args.episodes, args.workers, False)]
    if args.no_mask_policy is not None:
        rows.append({**count(args.dataset, args.no_mask_policy, lambdas, args.episodes, args.workers, False),
                     "trained_with_loop_mask": False})
    out = {"date": time.strftime("%Y-%m-%d"), "load_1min": os.getloadavg()[0], "dataset": str(args.dataset),
           "rows": rows}
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    for r in rows:
        print(f"{r['policy']}: loop rule at test {r['loop_mask_at_test']}: {r['loop_truncations']} loop truncations, "
              f"{r['truncated']} truncated of {r['episodes']} episodes, success {100 * r['success']:.1f} %")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
