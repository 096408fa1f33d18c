"""Self-learning in a cell without ground truth: the robot's labels against replayed ground truth,
and robot programs that report wrong outcomes.

    .venv/bin/python benchmarks/bench_cell_labels.py [--estimates 400] [--seeds 0 1 2] [--parallel 2]

Runs `perception-config cell-sim` on the synthetic default (every image, the cell pipeline, from
the fixed pipeline, `--reference` the cell policy) for each seed twice: `--labels ground_truth`
(the nodes and the learner see the replayed ground truth) and `--labels robot` (only the
simulated robot knows it and answers each pick; the learner learns from its outcomes), then the
three poisoned robot programs on the first seed (`--robot-reports flipped | all-failed |
all-success`; `--poisoned` without a value: none). A run whose summary.json exists is not run
again: a benchmark stopped midway continues when started again. Each run ends with the hidden
evaluation (every kept version on the same episodes with the ground truth, cost-table time:
load-independent). The first run measures the reference
through the nodes; the others reuse its reference.csv.

Reported per run: the hidden cost and success of the first and last served versions, the
promotions and how many were truly worse (any drop on the hidden episodes) and significantly worse
(beyond their noise: learning/hidden_evaluation.paired_worse; `--rejudge` adds those tests to runs
made before them). Per seed, the robot run's improvement (hidden cost
start - end) as a share of the ground-truth run's. Writes results/cell_labels.json and .png; the
runs' folders go to outputs/bench_cell_labels/.

The cell's pipeline is the reference policy's. With the learned pick-success score in it (a
policy trained on benchmarks/cell_pick_success_pipeline.yaml), the robot-label learner judges
the poses no robot outcome covers by that score:
    perception-config train --dataset data/default --agent pg --episodes 400 --seeds 2 --workers 2 \
        --pipeline benchmarks/cell_pick_success_pipeline.yaml --out runs/cell-ps-pg
    .venv/bin/python benchmarks/bench_cell_labels.py --reference runs/cell-ps-pg/policy.safetensors \
        --work outputs/bench_cell_labels_score --out benchmarks/results/cell_labels_score.json --domain 80
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

CLI = [str(Path(sys.executable).parent / "perception-config")]


def run_name(labels: str, reports: str, seed: int) -> str:
    return f"{labels}-{reports}-s{seed}" if labels == "robot" else f"{labels}-s{seed}"


def command(args: argparse.Namespace, out: Path, labels: str, reports: str, seed: int,
            reference_csv: Path | None, learn: bool = True) -> list[str]:
    cmd = CLI + ["cell-sim", "--dataset", str(args.dataset), "--all-images", "--start", "fixed",
                 "--reference", str(args.reference), "--estimates", str(args.estimates), "--seed", str(seed),
                 "--labels", labels, "--robot-reports", reports, "--out", str(out), "--quiet",
                 "--hidden-seeds", str(args.hidden_seeds)]
    if reference_csv is not None:
        cmd += ["--reference-from", str(reference_csv)]
    if not learn:
        cmd += ["--no-learn"]
    elif args.lockstep:
        cmd += ["--lockstep"]
    if learn and args.learn_every:
        cmd += ["--learn-every", str(args.learn_every)]
    return cmd


def latency(args: argparse.Namespace) -> int:
    """`--latency N`: the robot cell with the learner and without it, N estimates each, at the same
    time (each its own ROS domain, so both see the same machine load); estimate_pose's wall time
    (request to answer, as the robot program waits) p50 and p99 of each."""
    reference_csv = args.work / run_name("ground_truth", "truth", args.seeds[0]) / "reference.csv"
    if not reference_csv.is_file():
        print(f"--latency reuses {reference_csv}: run the benchmark without --latency first", file=sys.stderr)
        return 2
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    procs = {}
    for i, learn in enumerate((True, False)):
        name = f"latency-{'learn' if learn else 'no-learn'}"
        a = argparse.Namespace(**{**vars(args), "estimates": args.latency, "hidden_seeds": 0})
        procs[name] = subprocess.Popen(command(a, args.work / name, "robot", "truth", args.seeds[0], reference_csv,
                                               learn), env={**env, "ROS_DOMAIN_ID": str(args.domain + 20 + i)},
                                       stdout=open(args.work / f"{name}.log", "w"), stderr=subprocess.STDOUT, cwd=REPO)
    for p in procs.values():
        p.wait()
    from perception_config.bench.cell_sim import read_estimates

    out = {}
    for name in procs:
        rows = [r for r in read_estimates(args.work / name / "estimates.csv") if r["answered"]]
        wall = np.array([r["estimate_wall_s"] for r in rows])
        out[name] = {"estimates": len(rows), "p50_s": float(np.percentile(wall, 50)),
                     "p99_s": float(np.percentile(wall, 99)), "mean_s": float(wall.mean())}
        print(f"{name}: {len(rows)} answered estimates, estimate_pose wall time p50 {out[name]['p50_s']:.3f} s, "
              f"p99 {out[name]['p99_s']:.3f} s")
    lines = (args.work / "latency-learn" / "learn" / "learner.log").read_text().splitlines()
    out["learner_cycles"] = sum("learner: candidate from" in line for line in lines)
    out["load"] = os.getloadavg()
    path = args.out.with_name(args.out.stem + "_latency.json")
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(f"learner cycles during the learning run: {out['learner_cycles']}; wrote {path}")
    return 0


def rejudge(args: argparse.Namespace, jobs: list[tuple[str, str, int]]) -> None:
    """`--rejudge`: for runs whose summary has no paired tests (made before they existed), the
    hidden evaluation again on the run's kept versions (the same episodes, cost-table time: the
    same figures) with the per-episode outcomes, and its paired tests added to summary.json."""
    from perception_config.agents.policy_settings import policy_settings
    from perception_config.datasets.bop import BopDataset
    from perception_config.learning.hidden_evaluation import evaluate_versions, hidden_summary
    from perception_config.util.atomic_file import atomic_write
    from perception_config.util.versions import PolicyVersions

    settings = policy_settings([args.reference])
    keys = sorted(BopDataset(args.dataset).image_keys())  # the bench runs --all-images
    for job in jobs:
        run = args.work / run_name(*job)
        path = run / "summary.json"
        if not path.is_file():
            continue
        s = json.loads(path.read_text())
        if "significantly_worse_promotions" in s or not (run / "learn" / "policies").is_dir():
            continue
        figures = evaluate_versions(run / "learn" / "policies", args.dataset, keys, settings.pipeline, settings.env,
                                    s["noise_lambda"], args.hidden_seeds, progress=True)
        served = s["versions"] + [PolicyVersions(run / "learn" / "policies").current()]
        again = hidden_summary(figures, [v for v in served if v])
        if abs(again["hidden_cost_end"] - s["hidden_cost_end"]) > 1e-6:
            print(f"{run.name}: the hidden evaluation did not repeat ({again['hidden_cost_end']} against "
                  f"{s['hidden_cost_end']}): summary left as it was", file=sys.stderr)
            continue
        s.update(again)
        atomic_write(path, json.dumps(s, indent=2) + "\n")
        print(f"{run.name}: {again['significantly_worse_promotions']} of {len(again['promotion_checks'])} promotions "
              "significantly worse")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dataset", type=Path, default=REPO / "data" / "default")
    p.add_argument("--reference", type=Path, default=REPO / "runs" / "demo-cell-pg" / "policy.safetensors")
    p.add_argument("--estimates", type=int, default=400)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--poisoned", nargs="*", default=["flipped", "all-failed", "all-success"])
    p.add_argument("--parallel", type=int, default=2,
                   help="runs at a time (the hidden figures are cost-table: load-free; the served ones are not)")
    p.add_argument("--hidden-seeds", type=int, default=1)
    p.add_argument("--domain", type=int, default=60, help="ROS_DOMAIN_ID of the first run (the next ones count up)")
    p.add_argument("--work", type=Path, default=REPO / "outputs" / "bench_cell_labels")
    p.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "cell_labels.json")
    p.add_argument("--lockstep", action="store_true",
                   help="cell-sim --lockstep: each estimate waits while the learner trains (a real cell's pace)")
    p.add_argument("--learn-every", type=int, default=0, metavar="K",
                   help="new estimates between two learner cycles (0: the configurator's default, 20)")
    p.add_argument("--rejudge", action="store_true",
                   help="add the hidden evaluation's paired tests to runs made before they existed, then collect")
    p.add_argument("--latency", type=int, default=0, metavar="N",
                   help="instead: the learner on against off, N estimates each at the same time (serving latency)")
    args = p.parse_args()
    if args.latency:
        return latency(args)
    if not args.reference.is_file():
        print(f"no reference policy {args.reference}: run ./scripts/demo.sh (it trains runs/demo-cell-pg)",
              file=sys.stderr)
        return 2
    args.work.mkdir(parents=True, exist_ok=True)
    jobs = [(labels, "truth", s) for s in args.seeds for labels in ("ground_truth", "robot")]
    jobs += [("robot", r, args.seeds[0]) for r in args.poisoned]
    first = jobs[0]
    reference_csv = args.work / run_name(*first) / "reference.csv"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    running: list[tuple[tuple, subprocess.Popen, float]] = []
    # A run with a summary is done: a benchmark stopped midway continues when started again.
    pending = []
    for job in jobs:
        summary = args.work / run_name(*job) / "summary.json"
        if summary.is_file():
            print(f"{run_name(*job)}: done before ({summary})", flush=True)
        else:
            pending.append(job)
    started_all = time.time()
    while pending or running:
        can_start = len(running) < args.parallel and pending and (pending[0] == first or reference_csv.is_file())
        if can_start:
            job = pending.pop(0)
            out = args.work / run_name(*job)
            log = open(args.work / f"{run_name(*job)}.log", "w")
            # a ROS domain per run: two cells on one domain would answer each other's requests
            domain = {"ROS_DOMAIN_ID": str(args.domain + jobs.index(job))}
            proc = subprocess.Popen(command(args, out, *job, None if job == first else reference_csv),
                                    stdout=log, stderr=subprocess.STDOUT, env={**env, **domain}, cwd=REPO)
            running.append((job, proc, time.time()))
            print(f"started {run_name(*job)}", flush=True)
            continue
        for item in list(running):
            job, proc, t0 = item
            if proc.poll() is not None:
                running.remove(item)
                print(f"{run_name(*job)}: exit {proc.returncode} after {time.time() - t0:.0f} s", flush=True)
        time.sleep(2.0)
    if args.rejudge:
        rejudge(args, jobs)
    results = collect(args, jobs)
    results["wall_s"] = time.time() - started_all
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1) + "\n")
    plot(results, args.out.with_suffix(".png"))
    print(report(results))
    return 0


def collect(args: argparse.Namespace, jobs: list[tuple[str, str, int]]) -> dict:
    runs = {}
    for job in jobs:
        path = args.work / run_name(*job) / "summary.json"
        if not path.is_file():
            runs[run_name(*job)] = {"missing": str(path)}
            continue
        s = json.loads(path.read_text())
        runs[run_name(*job)] = {
            "labels": job[0], "reports": job[1], "seed": job[2], "estimates": s["estimates"],
            "served_success": s["success"], "reported_success": s.get("reported_success"),
            "served_time_s": s["time_s"], "last_window_success": s["last_window_success"],
            "promotions": [p["version"] for p in s["promotions"]], "candidates": s["candidates"],
            "hidden_success_start": s.get("hidden_success_start"), "hidden_success_end": s.get("hidden_success_end"),
            "hidden_cost_start": s.get("hidden_cost_start"), "hidden_cost_end": s.get("hidden_cost_end"),
            "worse_promotions": s.get("worse_promotions"), "promotion_checks": s.get("promotion_checks"),
            "significantly_worse_promotions": s.get("significantly_worse_promotions"),
            "stored_labels": s.get("stored_labels"), "learner_lines": s.get("learner_lines", [])[-3:],
            "lockstep": s.get("lockstep"),
        }
    ratios = {}
    for seed in args.seeds:
        gt, rb = runs.get(run_name("ground_truth", "truth", seed), {}), runs.get(run_name("robot", "truth", seed), {})
        if "hidden_cost_start" in gt and "hidden_cost_start" in rb:
            g = gt["hidden_cost_start"] - gt["hidden_cost_end"]
            r = rb["hidden_cost_start"] - rb["hidden_cost_end"]
            ratios[str(seed)] = {"ground_truth_gain": g, "robot_gain": r, "share": (r / g) if g > 1e-9 else None}
    worse = sum(int(r.get("worse_promotions") or 0) for r in runs.values())
    significant = sum(int(r.get("significantly_worse_promotions") or 0) for r in runs.values())
    return {"estimates": args.estimates, "seeds": args.seeds, "lockstep": args.lockstep,
            "learn_every": args.learn_every or 20, "runs": runs, "improvement_share": ratios,
            "worse_promotions_total": worse, "significantly_worse_promotions_total": significant,
            "load": os.getloadavg()}


def report(results: dict) -> str:
    lines = []
    for name, r in results["runs"].items():
        if "missing" in r:
            lines.append(f"{name}: no summary ({r['missing']})")
            continue
        lines.append(f"{name}: hidden success {r['hidden_success_start']:.1%} -> {r['hidden_success_end']:.1%}, cost "
                     f"{r['hidden_cost_start']:.3f} -> {r['hidden_cost_end']:.3f} s; promoted {r['promotions']} of "
                     f"{r['candidates']} candidates, {r['worse_promotions']} truly worse; served success "
                     f"{r['served_success']:.1%} (reported {r['reported_success']:.1%})")
    for seed, v in results["improvement_share"].items():
        share = f"{v['share']:.0%}" if v["share"] is not None else "n/a (no gain with ground truth)"
        lines.append(f"seed {seed}: robot labels' cost gain {v['robot_gain']:.3f} s = {share} of ground truth's "
                     f"{v['ground_truth_gain']:.3f} s")
    lines.append(f"worse promotions over all runs: {results['worse_promotions_total']} (by the paired tests, "
                 f"significantly worse: {results['significantly_worse_promotions_total']})")
    return "\n".join(lines)


def plot(results: dict, path: Path) -> None:
    from perception_config.core.plots import plt, save_figure

    runs = {k: v for k, v in results["runs"].items() if "missing" not in v}
    names = list(runs)
    x = np.arange(len(names))
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), constrained_layout=True)
    for ax, key, label in ((axes[0], "cost", "hidden mean cost per episode [s]"),
                           (axes[1], "success", "hidden success share")):
        start = [runs[n][f"hidden_{key}_start"] for n in names]
        end = [runs[n][f"hidden_{key}_end"] for n in names]
        ax.bar(x - 0.2, start, 0.4, label="first served version", color="0.7")
        ax.bar(x + 0.2, end, 0.4, label="last served version", color="tab:blue")
        ax.set_xticks(x, names, rotation=35, ha="right", fontsize=8)
        ax.set_ylabel(label)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=8)
    axes[0].set_title(f"cell-sim, {results['estimates']} estimates, judged by the hidden ground truth")
    save_figure(fig, path)


if __name__ == "__main__":
    sys.exit(main())
