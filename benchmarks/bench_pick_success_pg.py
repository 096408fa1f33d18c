"""Policy gradient with and without the learned pick-success score, against the oracle.

    python benchmarks/bench_pick_success_pg.py [--dataset data/default] [--episodes 2000]
        [--pipelines default,pick_success] [--runs runs/bench-pick-success] [--out FILE.json]
        [--validation-fraction F --validate-every K] [--lr-half-life H] [--entropy-coef C]

For each pipeline (default: the default one and config/pick_success_pipeline.yaml, the same
actions with pick_success in the scoring set): trains the policy-gradient agent on the train
images (`perception-config train --agent pg`, same seed and episodes), then evaluates it with
the oracle (hindsight lower bound) at lambda = 0.5 on every test episode
(`perception-config evaluate --lambdas 0.5`, measured time as docs/results/learning.md's table, or with
`--time-mode cost_table` every block charged its table cost: independent of the machine's load).
Reports per pipeline: pg's mean time to success over the oracle's (docs/results/learning.md's "x the oracle"),
the same on the median, first-pick success and the success share. Both agents of a pipeline pay
its scoring pass, so the oracle of the pick_success pipeline is slower too: the absolute times
are reported beside the ratios. `--validation-fraction F` trains with validation-based policy
selection (learning/training.py: F of the train images held out, the greedy policy checked every K
episodes, the best one shipped); the test images are the same either way. `--lr-half-life H`
halves pg's learning rate every H training episodes, `--entropy-coef C` sets its entropy bonus
(default 0.01; agents/policy_gradient.py). The report lists
every test episode whose first pick failed or that ended without a successful pick (object,
lambda, operations, and the pick_success score at the failed pick where the pipeline has it).
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from perception_config.agents.policy_io import policy_info  # noqa: E402
from perception_config.learning.evaluation import evaluate  # noqa: E402
from perception_config.learning.training import train  # noqa: E402
from perception_config.util.atomic_file import atomic_write  # noqa: E402


def failures(store: Path, agent: str) -> list[dict]:
    """The test episodes of one agent (by its name in the evaluation's episode store)
    whose first pick failed or that did not end with a successful pick."""
    import sqlite3

    con = sqlite3.connect(f"file:{store}?mode=ro", uri=True)
    con.row_factory = sqlite3.Row
    out = []
    rows = con.execute("SELECT * FROM episodes WHERE agent = ? AND (first_pick_success = 0 OR success = 0)",
                       (agent,)).fetchall()
    for r in rows:
        steps = con.execute("SELECT * FROM steps WHERE episode_id = ? ORDER BY step", (r["id"],)).fetchall()
        first_pick = next((s for s in steps if s["picked"] is not None), None)
        scores = json.loads(first_pick["scores"]) if first_pick is not None and first_pick["scores"] else {}
        out.append({"scene_im": [r["scene_id"], r["im_id"]], "obj_id": r["obj_id"], "lambda": r["noise_lambda"],
                    "success": bool(r["success"]), "first_pick_success": bool(r["first_pick_success"]),
                    "actions": [s["action"] for s in steps],
                    "pick_success_at_first_pick": scores.get("pick_success")})
    return out


def measure(dataset: Path, pipeline: str, episodes: int, runs: Path, seed: int, time_mode: str | None = None,
            reuse: bool = False, validation_fraction: float = 0.0, validate_every: int = 250,
            agent_kwargs: dict | None = None) -> dict:
    run = runs / f"pg-{pipeline}"
    t0 = time.perf_counter()
    if reuse and (run / "policy.safetensors").exists():
        policy, train_s = run / "policy.safetensors", None
    else:
        policy = train(dataset, "pg", run, episodes, seed=seed, pipeline=pipeline, progress=True, overwrite=True,
                       validation_fraction=validation_fraction, validate_every=validate_every,
                       agent_kwargs=agent_kwargs)
        train_s = round(time.perf_counter() - t0, 1)
    extra = {"time_mode": time_mode} if time_mode else {}
    results = evaluate(dataset, [str(policy)], [0.5], runs / f"eval-{pipeline}-{time_mode or 'as-trained'}",
                       pipeline=pipeline, progress=True, include_baselines=True, plots=False, **extra)
    records = json.loads(results.read_text())
    first = json.loads((results.parent / "meta.json").read_text())["agents"][0]["name"]  # the policy comes first
    by = {r["agent"]: r for r in records if r["lambda"] == 0.5}
    pg, oracle = by[first], by["oracle"]
    out = {"train_seconds": train_s, "policy": str(policy), "time_mode": time_mode or "as trained (measured)"}
    extra = json.loads(json.dumps(policy_info(policy).get("extra", {})))
    if "selected" in extra:
        out["selected"] = {"episode": extra["selected"]["episode"], "of": extra["episodes"],
                           "validation": {k: extra["selected"]["validation"][k] for k in
                                          ("cost", "success", "first_pick", "time_to_success", "episodes")},
                           "validation_fraction": extra["validation_fraction"],
                           "validation_images": len(extra["validation_image_keys"])}
    try:
        out["pg_failures"] = failures(results.parent / "episodes.sqlite", first)
    except Exception as exc:  # noqa: BLE001  (the figures above stand without the listing)
        out["pg_failures"] = f"not listed: {type(exc).__name__}: {exc}"
    for name, r in (("pg", pg), ("oracle", oracle)):
        out[name] = {k: r[k] for k in ("episodes", "success", "first_pick_success")}
        out[name].update(mean_time_to_success=r["time_to_success"]["mean"],
                         median_time_to_success=r["time_to_success"]["median"],
                         mean_ops_to_success=r["ops_to_success"]["mean"])
    out["pg_over_oracle_mean"] = pg["time_to_success"]["mean"] / oracle["time_to_success"]["mean"]
    out["pg_over_oracle_median"] = pg["time_to_success"]["median"] / oracle["time_to_success"]["median"]
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dataset", type=Path, default=REPO / "data" / "default")
    ap.add_argument("--episodes", type=int, default=2000)
    ap.add_argument("--pipelines", default="default,pick_success")
    ap.add_argument("--runs", type=Path, default=REPO / "runs" / "bench-pick-success")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--time-mode", choices=("measured", "cost_table"), default=None,
                    help="evaluate in this time mode (default: the policy's, measured): cost_table charges every "
                         "block its table cost, so the comparison does not depend on the machine's load")
    ap.add_argument("--reuse", action="store_true", help="evaluate the policies already trained in --runs")
    ap.add_argument("--validation-fraction", type=float, default=0.0,
                    help="train with validation-based policy selection on this share of the train images")
    ap.add_argument("--validate-every", type=int, default=250, help="episodes between two validation checks")
    ap.add_argument("--lr-half-life", type=float, default=0.0,
                    help="halve pg's learning rate every this many training episodes (0: constant)")
    ap.add_argument("--entropy-coef", type=float, default=None, help="pg's entropy bonus (default: the agent's)")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "pick_success_pg.json")
    args = ap.parse_args()
    result = {"dataset": str(args.dataset), "episodes": args.episodes, "seed": args.seed, "lambda": 0.5,
              "validation_fraction": args.validation_fraction, "validate_every": args.validate_every,
              "lr_half_life": args.lr_half_life, "entropy_coef": args.entropy_coef,
              "pipelines": {}}
    agent_kwargs = {**({"lr_half_life": args.lr_half_life} if args.lr_half_life else {}),
                    **({"entropy_coef": args.entropy_coef} if args.entropy_coef is not None else {})} or None
    for name in args.pipelines.split(","):
        result["pipelines"][name] = m = measure(args.dataset, name, args.episodes, args.runs, args.seed,
                                                args.time_mode, args.reuse, args.validation_fraction,
                                                args.validate_every, agent_kwargs)
        print(f"{name}: pg {m['pg']['mean_time_to_success']:.3f} s mean to success = {m['pg_over_oracle_mean']:.1f}x "
              f"the oracle's {m['oracle']['mean_time_to_success']:.3f} s (median {m['pg_over_oracle_median']:.1f}x); "
              f"first pick {100 * m['pg']['first_pick_success']:.1f} %, success {100 * m['pg']['success']:.1f} %",
              flush=True)
        atomic_write(args.out, json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
