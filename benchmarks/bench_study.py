"""The learned configurator against the strongest fixed pipeline, over seeds and datasets.

    python benchmarks/bench_study.py [--datasets default,seed1] [--pipelines pick_success,default,cell]
        [--seeds 5] [--restarts 1] [--episodes 1500] [--eval-episodes 60] [--workers 2]
        [--runs runs/bench-study]
        [--agent-param KEY=VALUE ...] [--tag NAME]

For each dataset (`default`: data/default, the demo's; `seedN`: the same generator with seed N,
synthesised into data/synthetic-seedN once) and pipeline: with `pick_success` the learned score
is first fitted on the dataset's train images (`perception-config fit-score`, 600 episodes) and a
pipeline file pointing at it is written; then `perception-config study` trains `--seeds` pg seeds
with the recipe's defaults (one cost model calibrated on the train images, validation-based
selection) and evaluates them next to the oracle, best_static, the engineer pipelines and random
on the same `--eval-episodes` test episodes per lambda (0.3, 0.5, 0.7; the cell pipeline: 0.5,
its generator has no noise level). A study stopped midway continues when run again.

Writes benchmarks/results/study_<dataset>_<pipeline>.json: per lambda, pg's k of N seeds beating
best_static, the pooled figures with 95 % bootstrap intervals and the time ratio to the oracle,
from the study's study.json (also copied with its study.png).
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
CLI = [sys.executable, "-m", "perception_config.cli"]


def dataset_path(name: str) -> Path:
    if name == "default":
        path = ROOT / "data" / "default"
        seed = 0
    elif name.startswith("seed") and name[4:].isdigit():
        seed = int(name[4:])
        path = ROOT / "data" / f"synthetic-seed{seed}"
    else:
        raise SystemExit(f"unknown dataset {name!r}: default or seedN")
    if not (path / "models" / "models_info.json").exists():
        run([*CLI, "synth", "--out", str(path), "--scenes", "4", "--images-per-scene", "10", "--seed", str(seed)])
    return path


def run(cmd: list[str]) -> None:
    print("$", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})


def pipeline_for(name: str, dataset: Path, runs: Path) -> str:
    """The pipeline argument: a shipped name, or for pick_success a file pointing at a score fitted
    on this dataset's train images."""
    if name != "pick_success":
        return name
    score = runs / "score"
    if not (score / "metrics.json").exists():
        run([*CLI, "fit-score", "--dataset", str(dataset), "--episodes", "600", "--out", str(score), "--quiet"])
    text = (ROOT / "perception_config" / "config" / "pick_success_pipeline.yaml").read_text()
    path = runs / "pick_success_pipeline.yaml"
    path.write_text(text.replace("params: {model: pick_success}", f"params: {{model: {score}}}"))
    return str(path)


def summary(study: dict) -> list:
    """The figures of the targets from a study.json: per lambda, k of N seeds beating the bar, the
    pooled cost / success against the bar's, the time ratio to the oracle (learning/study_report.py)."""
    keys = ("lambda", "bar", "bar_kind", "n_seeds", "k_beats", "k_beats_surely", "pooled_cost", "bar_cost",
            "pooled_success", "bar_success", "pooled_oracle_ratio")
    return [{k: c.get(k) for k in keys} for c in study.get("comparisons", [])]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--datasets", default="default,seed1")
    ap.add_argument("--pipelines", default="pick_success,default,cell")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--episodes", type=int, default=1500)
    ap.add_argument("--restarts", type=int, default=1, help="runs per seed, the validation-best kept")
    ap.add_argument("--eval-episodes", type=int, default=60)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--runs", type=Path, default=ROOT / "runs" / "bench-study")
    ap.add_argument("--agent-param", action="append", default=[], metavar="KEY=VALUE",
                    help="passed to the study (over the recipe's), e.g. entropy_coef=0.01")
    ap.add_argument("--tag", default="", help="appended to the results' file names (a variant's own files)")
    args = ap.parse_args()
    for ds_name in args.datasets.split(","):
        dataset = dataset_path(ds_name)
        for pipe_name in args.pipelines.split(","):
            runs = args.runs / f"{ds_name}-{pipe_name}"
            runs.mkdir(parents=True, exist_ok=True)
            pipeline = pipeline_for(pipe_name, dataset, runs)
            lambdas = "0.5" if pipe_name == "cell" else "0.3,0.5,0.7"
            started = time.monotonic()
            cmd = [*CLI, "study", "--dataset", str(dataset), "--out", str(runs / "study"), "--pipeline", pipeline,
                   "--seeds", str(args.seeds), "--restarts", str(args.restarts), "--episodes", str(args.episodes),
                   "--eval-episodes",
                   str(args.eval_episodes), "--lambdas", lambdas, "--workers", str(args.workers), "--quiet"]
            for item in args.agent_param:
                cmd += ["--agent-param", item]
            run(cmd)
            study = json.loads((runs / "study" / "study.json").read_text())
            record = {"dataset": ds_name, "pipeline": pipe_name, "command": " ".join(cmd[2:]),
                      "seconds": round(time.monotonic() - started, 1), "load_1min": os.getloadavg()[0],
                      "date": time.strftime("%Y-%m-%d"), "summary": summary(study), "study": study}
            RESULTS.mkdir(parents=True, exist_ok=True)
            name = f"study_{ds_name}_{pipe_name}{'_' + args.tag if args.tag else ''}"
            (RESULTS / f"{name}.json").write_text(json.dumps(record, indent=1, default=str) + "\n")
            if (runs / "study" / "study.png").exists():
                shutil.copy(runs / "study" / "study.png", RESULTS / f"{name}.png")
            print(f"wrote {RESULTS / name}.json", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
