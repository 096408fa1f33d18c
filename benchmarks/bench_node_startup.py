"""Start-up time and peak memory of the four operator nodes, before the regrouping and now.

    .venv/bin/python benchmarks/bench_node_startup.py [--before /tmp/origC] [--current .] [--runs 5]

Each node is started as its own process from a source tree (`--before`: a worktree of the code
before the package was regrouped into layers, e.g. `git worktree add /tmp/origC 9d502af`;
`--current`: this repository), with PYTHONPATH and the working directory set to that tree and
this venv's python, the default pipeline and a models folder of the procedural parts. Per start:
  service_s      process start until the node's service is available to a client in this
                 process (what a launcher waits for; includes DDS discovery)
  constructed_s  process start until the node logs "serving ...", the last step of its
                 construction (no discovery; the service may be seen a moment before)
  peak_rss_mb    the process's peak resident memory (VmHWM) once both are done
  torch          whether torch is loaded then (libtorch mapped into the process)
Before the runs, each node starts once from each tree, not counted (its bytecode is compiled
then, as in an installed copy). The runs are interleaved (node by node, the two trees in
alternating order) so machine noise hits both alike; medians with min and max. Both trees get
the same ROS environment (this repo's Fast DDS profile, a domain of their own). Writes
results/node_startup.json and .png and prints a table; `uptime` before and after is recorded.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # before numpy/open3d start their thread pools

import argparse
import json
import random
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

NODES = {  # executable -> (module, service, its type)
    "generation_node": ("perception_config.ros.generation_node", "generate_hypothesis", "GenerateHypothesis"),
    "refinement_node": ("perception_config.ros.refinement_node", "refine_hypothesis", "RefineHypothesis"),
    "scoring_node": ("perception_config.ros.scoring_node", "score_hypothesis", "ScoreHypothesis"),
    "pick_node": ("perception_config.ros.pick_node", "pick", "Pick"),
}
START_TIMEOUT = 120.0


def uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()


def git_commit(tree: Path) -> str:
    return subprocess.run(["git", "-C", str(tree), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()


def node_env(tree: Path, domain: int) -> dict[str, str]:
    env = dict(os.environ)
    env.update(PYTHONPATH=str(tree), PYTHONUNBUFFERED="1", RCUTILS_LOGGING_BUFFERED_STREAM="0",
               ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE="SYSTEM_DEFAULT",
               FASTDDS_DEFAULT_PROFILES_FILE=str(REPO / "perception_config" / "ros" / "fastdds_profile.xml"))
    return env


def peak_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmHWM for process {pid}")


def torch_loaded(pid: int) -> bool:
    return "libtorch" in Path(f"/proc/{pid}/maps").read_text()


def start_once(client_node, executable: str, tree: Path, models: Path, domain: int) -> dict:
    """One start of `executable` from `tree`: the figures above, then SIGINT."""
    import perception_config_interfaces.srv as srv

    module, service, srv_type = NODES[executable]
    client = client_node.create_client(getattr(srv, srv_type), service)
    args = [sys.executable, "-c", f"from {module} import main; main()", "--ros-args", "-p", f"models_dir:={models}"]
    constructed: list[float] = []
    t0 = time.perf_counter()
    proc = subprocess.Popen(args, cwd=tree, env=node_env(tree, domain), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    output: list[str] = []

    def read() -> None:
        for line in proc.stdout:
            if not constructed and "serving" in line:
                constructed.append(time.perf_counter() - t0)
            output.append(line)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        while not client.wait_for_service(timeout_sec=0.005):
            if proc.poll() is not None or time.perf_counter() - t0 > START_TIMEOUT:
                raise RuntimeError(f"{executable} from {tree} did not serve:\n{''.join(output)}")
        service_s = time.perf_counter() - t0
        while not constructed:  # the service can be seen a moment before the node logs "serving"
            if proc.poll() is not None or time.perf_counter() - t0 > START_TIMEOUT:
                raise RuntimeError(f"{executable} from {tree} never logged 'serving':\n{''.join(output)}")
            time.sleep(0.005)
        record = {"service_s": service_s, "constructed_s": constructed[0], "peak_rss_mb": peak_rss_mb(proc.pid),
                  "torch": torch_loaded(proc.pid)}
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        reader.join(5)
        client_node.destroy_client(client)
    return record


def summary(values: list[float]) -> dict:
    return {"median": round(statistics.median(values), 4), "min": round(min(values), 4),
            "max": round(max(values), 4), "values": [round(v, 4) for v in values]}


def print_table(result: dict) -> None:
    def cell(stats: dict, digits: int) -> str:
        return f"{stats['median']:.{digits}f} ({stats['min']:.{digits}f}..{stats['max']:.{digits}f})"

    print(f"\n{'node':16s} {'tree':8s} {'service s (min..max)':>22s} {'constructed s':>22s} {'peak RSS MB':>22s}  "
          "torch")
    for n, by_variant in result["nodes"].items():
        for v, s in by_variant.items():
            print(f"{n:16s} {v:8s} {cell(s['service_s'], 2):>22s} {cell(s['constructed_s'], 2):>22s} "
                  f"{cell(s['peak_rss_mb'], 0):>22s}  {any(s['torch'])}")


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    nodes = list(result["nodes"])
    x = np.arange(len(nodes))
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    for ax, key, label in zip(axes, ("service_s", "constructed_s", "peak_rss_mb"),
                              ("start until the service is available (s)", "start until constructed (s)",
                               "peak RSS (MB)")):
        for i, (variant, colour) in enumerate((("before", "tab:gray"), ("current", "tab:blue"))):
            stats = [result["nodes"][n][variant][key] for n in nodes]
            med = np.array([s["median"] for s in stats])
            err = np.array([[m - s["min"] for m, s in zip(med, stats)], [s["max"] - m for m, s in zip(med, stats)]])
            ax.bar(x + (i - 0.5) * 0.38, med, 0.38, yerr=err, capsize=3, color=colour,
                   label=f"{variant} ({result['trees'][variant]['commit'][:7]})")
        ax.set_xticks(x, [n.replace("_node", "") for n in nodes])
        ax.set_title(label, fontsize=10)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"Operator node start-up, median of {result['runs']} runs (bars: min..max); "
                 f"load: {result['machine']['uptime_before'].split('load average:')[-1].strip()}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", type=Path, default=Path("/tmp/origC"), help="tree of the code before the regrouping")
    ap.add_argument("--current", type=Path, default=REPO, help="tree of the current code")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "node_startup.json")
    a = ap.parse_args()

    import rclpy

    from perception_config.datasets.parts import write_models

    trees = {"before": a.before.resolve(), "current": a.current.resolve()}
    domain = random.SystemRandom().choice([d for d in range(60, 101) if d != 42])
    os.environ.update({k: v for k, v in node_env(REPO, domain).items() if k.startswith(("ROS_", "FASTDDS_"))})
    before_load = uptime()
    records: dict[str, dict[str, list[dict]]] = {n: {v: [] for v in trees} for n in NODES}
    with tempfile.TemporaryDirectory(prefix="bench_node_startup_") as tmp:
        models = write_models(Path(tmp) / "models")
        rclpy.init()
        client_node = rclpy.create_node("bench_node_startup")
        try:
            for executable in NODES:  # warm-up: compiles each tree's bytecode
                for variant in trees:
                    start_once(client_node, executable, trees[variant], models, domain)
            for run in range(a.runs):
                for executable in NODES:
                    order = list(trees) if (run + list(NODES).index(executable)) % 2 == 0 else list(trees)[::-1]
                    for variant in order:
                        rec = start_once(client_node, executable, trees[variant], models, domain)
                        records[executable][variant].append(rec)
                        print(f"run {run + 1}/{a.runs} {executable:16s} {variant:8s} service {rec['service_s']:.2f} s "
                              f"constructed {rec['constructed_s']:.2f} s "
                              f"rss {rec['peak_rss_mb']:.0f} MB torch {rec['torch']}", flush=True)
        finally:
            client_node.destroy_node()
            rclpy.try_shutdown()
    result = {
        "measure": {"service_s": "process start until the node's service is available to a client (DDS discovery "
                                 "included)",
                    "constructed_s": "process start until the node logs 'serving ...' (end of its construction)",
                    "peak_rss_mb": "VmHWM of the node process once served and constructed (MiB)",
                    "torch": "libtorch mapped into the node process then"},
        "runs": a.runs,
        "parameters": "models_dir (the procedural parts), every other parameter its default (default pipeline)",
        "trees": {v: {"path": str(t), "commit": git_commit(t)} for v, t in trees.items()},
        "machine": {"uptime_before": before_load, "uptime_after": uptime(), "cpus": os.cpu_count(),
                    "python": sys.version.split()[0]},
        "nodes": {n: {v: {"service_s": summary([r["service_s"] for r in recs]),
                          "constructed_s": summary([r["constructed_s"] for r in recs]),
                          "peak_rss_mb": summary([r["peak_rss_mb"] for r in recs]),
                          "torch": [r["torch"] for r in recs]}
                      for v, recs in by_variant.items()}
                  for n, by_variant in records.items()},
    }
    from perception_config.util.atomic_file import atomic_write

    atomic_write(a.out, json.dumps(result, indent=1) + "\n")
    plot(result, a.out.with_suffix(".png"))
    print_table(result)
    print(f"\nload: before {before_load}\n      after  {result['machine']['uptime_after']}")
    print(f"wrote {a.out} and {a.out.with_suffix('.png')}")


if __name__ == "__main__":
    main()
