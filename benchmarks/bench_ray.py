"""Episodes per second with 1 and N Ray workers: training (pg batches, the ES population) and the
evaluation sweep, back to back in one run so that the ratio sees the same machine load.

    python benchmarks/bench_ray.py [--dataset data/default] [--episodes 320]
        [--agents pg,pg:batch_episodes=32,es] [--workers 1,2] [--repeats 2] [--eval-episodes 6]
        [--lambdas 0.3,0.7] [--out benchmarks/results/ray.json]

An agent is a kind with optional hyper-parameters, `kind:KEY=VALUE:KEY=VALUE` (as `train
--agent-param`): pg's rounds are its `batch_episodes` (default 8), and each round ends with its
slowest worker, so the ratio depends on the batch.

For each agent, `train` (cost-table mode, the same seed) with each number of workers, the
configurations interleaved `--repeats` times (1, 2, 1, 2: a change of the machine's load hits
both). Per run: the wall seconds of the whole call and the steady-state episodes/s after the
first round (the first round includes the workers' start: importing the package and building
their env, several seconds on a loaded 2-core machine; a long training pays it once). A local
Ray is started once before the runs and reused by those with more than one worker (its start-up
is reported apart); with 1 worker nothing of Ray runs. Then `evaluate` of the first trained
policy with the baselines (oracle, fixed pipelines, random) at `--lambdas`, the whole call
timed. The histories / results of every number of workers must be the same bits (checked:
`same_results`). The load average is recorded before and after each run, and the CPU seconds
per episode of the whole process tree (the driver, Ray's processes and workers): what Ray costs
on top of the episodes, whatever the load.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from perception_config import training  # noqa: E402
from perception_config.cli import agent_params  # noqa: E402
from perception_config.learning.evaluation import evaluate  # noqa: E402
from perception_config.rl.settings import EnvSettings  # noqa: E402
from perception_config.util.atomic_file import atomic_write  # noqa: E402

ROUND_ENDS: list[float] = []  # perf_counter at the end of every round of the running train()
_PLAY_ROUND = training.play_round


def _timed_round(*args, **kw):
    """training.play_round, noting when each round ends (for the steady-state rate)."""
    out = _PLAY_ROUND(*args, **kw)
    ROUND_ENDS.append(time.perf_counter())
    return out


training.play_round = _timed_round


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16]


def _load() -> float:
    return round(os.getloadavg()[0], 2)


def _tree_cpu() -> dict[int, float]:
    """CPU seconds (user + system) of this process and its descendants (a local Ray's GCS,
    raylet and workers), by pid, from /proc."""
    tick = os.sysconf("SC_CLK_TCK")
    stats, children = {}, {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                f = Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            stats[int(entry)] = (int(f[11]) + int(f[12])) / tick
            children.setdefault(int(f[1]), []).append(int(entry))
    out, todo = {}, [os.getpid()]
    while todo:
        pid = todo.pop()
        if pid in stats:
            out[pid] = stats[pid]
        todo.extend(children.get(pid, ()))
    return out


def _cpu_since(before: dict[int, float]) -> float:
    return sum(v - before.get(p, 0.0) for p, v in _tree_cpu().items())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", type=Path, default=REPO / "data" / "default")
    ap.add_argument("--episodes", type=int, default=320, help="training episodes per run")
    ap.add_argument("--repeats", type=int, default=2, help="runs of each number of workers, interleaved")
    ap.add_argument("--agents", default="pg,pg:batch_episodes=32,es",
                    help="comma-separated kind[:KEY=VALUE...] (hyper-parameters as train --agent-param)")
    ap.add_argument("--workers", default="1,2", help="comma-separated numbers of workers")
    ap.add_argument("--eval-episodes", type=int, default=6, help="evaluation episodes per lambda (0: no evaluation)")
    ap.add_argument("--lambdas", default="0.3,0.7")
    ap.add_argument("--runs", type=Path, default=REPO / "runs" / "bench-ray")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "ray.json")
    a = ap.parse_args(argv)
    workers = [int(w) for w in a.workers.split(",")]
    settings = EnvSettings(time_mode="cost_table")
    report: dict = {"dataset": str(a.dataset), "episodes": a.episodes, "cpus": os.cpu_count(),
                    "time_mode": "cost_table", "train": {}, "evaluate": {}}

    runner = None
    if any(w > 1 for w in workers):
        from perception_config.learning.ray_workers import RayRunner

        t0 = time.perf_counter()
        runner = RayRunner(max(workers))
        report["ray_start_seconds"] = round(time.perf_counter() - t0, 2)
    try:
        policy = None
        for agent in a.agents.split(","):
            kind, *params = agent.split(":")
            kwargs = agent_params(kind, params)
            rows: dict[int, list[dict]] = {w: [] for w in workers}
            for rep in range(a.repeats):
                for w in workers:
                    out = a.runs / f"{agent.replace(':', '-')}-w{w}-{rep}"
                    ROUND_ENDS.clear()
                    cpu0 = _tree_cpu()
                    load0, t0 = _load(), time.perf_counter()
                    path = training.train(a.dataset, kind, out, a.episodes, settings=settings, seed=0, workers=w,
                                          agent_kwargs=kwargs, overwrite=True, progress=False)
                    dt = time.perf_counter() - t0
                    cpu = _cpu_since(cpu0)
                    per_round = a.episodes / len(ROUND_ENDS)
                    steady = (a.episodes - per_round) / (ROUND_ENDS[-1] - ROUND_ENDS[0])
                    rows[w].append({"seconds": round(dt, 2), "episodes_per_second": round(a.episodes / dt, 2),
                                    "steady_episodes_per_second": round(steady, 2),
                                    "first_round_seconds": round(ROUND_ENDS[0] - t0, 2),
                                    "cpu_seconds_per_episode": round(cpu / a.episodes, 4),
                                    "load_before": load0, "load_after": _load(),
                                    "history": _digest(out / "history.csv")})
                    print(f"train {agent} workers={w}: {dt:.1f} s, {a.episodes / dt:.2f} episodes/s, steady "
                          f"{steady:.2f} episodes/s (first round {ROUND_ENDS[0] - t0:.1f} s; CPU "
                          f"{cpu / a.episodes:.3f} s/episode; load {load0} -> {_load()})", flush=True)
                    policy = policy or path
            base = rows[workers[0]]
            report["train"][agent] = {
                "runs": rows,
                "speedup_whole_run": {w: round(sum(r["seconds"] for r in base) / sum(r["seconds"] for r in rs), 2)
                                      for w, rs in rows.items()},
                "speedup_steady": {w: round(sum(r["steady_episodes_per_second"] for r in rs)
                                            / sum(r["steady_episodes_per_second"] for r in base), 2)
                                   for w, rs in rows.items()},
                "same_results": len({r["history"] for rs in rows.values() for r in rs}) == 1}
        if a.eval_episodes and policy is not None:
            lams = [float(x) for x in a.lambdas.split(",")]
            rows = {}
            for w in workers:
                out = a.runs / f"eval-w{w}"
                load0, t0 = _load(), time.perf_counter()
                res = evaluate(a.dataset, [str(policy)], lams, out, episodes_per_lambda=a.eval_episodes,
                               time_mode="cost_table", plots=False, progress=False, workers=w)
                dt = time.perf_counter() - t0
                n = len(json.loads(res.read_text())) * a.eval_episodes
                rows[w] = {"seconds": round(dt, 2), "episodes": n, "episodes_per_second": round(n / dt, 2),
                           "load_before": load0, "load_after": _load(), "results": _digest(res)}
                print(f"evaluate workers={w}: {n} episodes in {dt:.1f} s, {n / dt:.2f} episodes/s "
                      f"(load {load0} -> {_load()})", flush=True)
            base = rows[workers[0]]["seconds"]
            report["evaluate"] = {"runs": rows, "speedup": {w: round(base / r["seconds"], 2) for w, r in rows.items()},
                                  "same_results": len({r["results"] for r in rows.values()}) == 1}
    finally:
        if runner is not None:
            runner.close()
    a.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(a.out, json.dumps(report, indent=1) + "\n")
    summary = {f"train {k}": [v["speedup_whole_run"], v["speedup_steady"]] for k, v in report["train"].items()}
    if report["evaluate"]:
        summary["evaluate"] = report["evaluate"]["speedup"]
    print(json.dumps(summary))
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
