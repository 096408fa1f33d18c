"""An environment rule on trained policies: a study's seeds and best_static with the rule off and on.

    python benchmarks/bench_final_pick.py [--rule final_pick|final_pick_best]
        [--study runs/bench-study/default-pick_success/study] [--dataset data/default]
        [--eval-episodes 60] [--lambdas 0.3,0.5,0.7]

Evaluates the study's pg policies (seed-*/policy.safetensors) and the best static pipeline (searched
again under each setting) on the same test episodes, once with the rule off and once on (rl/env.py:
`final_pick`, the last of max_ops operations is a pick; `final_pick_best`, that pick taken at the
best hypothesis reached by the pick-success score), and counts per lambda the seeds beating
best_static (lower mean episode cost, success not lower). The policies keep their training; only
the environment's rule changes. Writes benchmarks/results/<rule>.json.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import json
import sys
import time
from pathlib import Path

from perception_config.learning.evaluation import evaluate
from perception_config.learning.study_stats import count_beats

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def figures(results: list[dict]) -> dict:
    """Per lambda: every agent's success, mean episode cost and truncations; pg seeds beating best_static."""
    out: dict = {}
    for r in results:
        cost = r["episode_cost"]["mean"] if isinstance(r["episode_cost"], dict) else r["episode_cost"]
        out.setdefault(str(r["lambda"]), {})[r["agent"]] = {
            "success": r["success"], "cost": cost, "truncated": r["truncated"], "sequence": r.get("sequence")}
    for per in out.values():
        bar = per["best_static"]
        seeds = [a for a in per if a.startswith("pg")]
        per["k_beats"] = count_beats([per[a] for a in seeds], bar)
        per["n_seeds"] = len(seeds)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rule", choices=("final_pick", "final_pick_best"), default="final_pick")
    ap.add_argument("--study", type=Path, default=ROOT / "runs" / "bench-study" / "default-pick_success" / "study")
    ap.add_argument("--dataset", type=Path, default=ROOT / "data" / "default")
    ap.add_argument("--eval-episodes", type=int, default=60)
    ap.add_argument("--lambdas", default="0.3,0.5,0.7")
    ap.add_argument("--out", type=Path, default=None, help="evaluation folders (runs/bench-<rule>)")
    args = ap.parse_args()
    out = args.out or ROOT / "runs" / f"bench-{args.rule.replace('_', '-')}"
    # final_pick_best acts only through the final pick: that rule stays on in both of its evaluations
    fixed = {"final_pick": True} if args.rule == "final_pick_best" else {}
    policies = sorted(str(p) for p in args.study.glob("seed-*/policy.safetensors"))
    if not policies:
        raise SystemExit(f"no seed-*/policy.safetensors in {args.study}: run benchmarks/bench_study.py first")
    lams = [float(x) for x in args.lambdas.split(",")]
    record: dict = {"rule": args.rule, "study": str(args.study), "dataset": str(args.dataset),
                    "eval_episodes": args.eval_episodes, "date": time.strftime("%Y-%m-%d"),
                    "load_1min": os.getloadavg()[0]}
    for rule in (False, True):
        name = "on" if rule else "off"
        path = out / name / "results.json"
        if not path.exists():  # an evaluation already made is reused (the benchmark resumes)
            evaluate(args.dataset, [*policies, "best_static"], lambdas=lams, out=out / name,
                     episodes_per_lambda=args.eval_episodes, seed=0, include_baselines=False, plots=False,
                     store_episodes=False, **{**fixed, args.rule: rule})
        record[f"{args.rule}_{name}"] = figures(json.loads(path.read_text()))
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{args.rule}.json").write_text(json.dumps(record, indent=1) + "\n")
    off, on = record[f"{args.rule}_off"], record[f"{args.rule}_on"]
    for lam in map(str, lams):
        print(f"lambda {lam}: pg beats best_static in {off[lam]['k_beats']} (rule off) / {on[lam]['k_beats']} "
              f"(rule on) of {on[lam]['n_seeds']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
