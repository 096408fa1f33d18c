"""A Ray cluster of two nodes on this machine (ray.cluster_utils.Cluster, each node its own
raylet, object store and workers, on 127.0.0.1): `train` and `evaluate` join it by address
(`--ray-address`), play on both nodes and give the in-process bits; a run checkpointed on one
cluster resumes on a new one (the whole cluster restarted) into the uninterrupted run."""
from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import pytest

from perception_config.learning.evaluation import evaluate
from perception_config.learning.training import train
from perception_config.rl.settings import EnvSettings
from rl_helpers import own_ray_task_processes, pipeline_file, same_evaluation, same_run, tiny_dataset

FAST = EnvSettings(time_mode="cost_table", lambda_range=(0.2, 0.8), max_ops=5)


def _start_cluster(nodes: int = 2):
    """`nodes` nodes of one CPU each on this machine."""
    from perception_config.learning.ray_workers import loopback_only

    loopback_only()  # the nodes on 127.0.0.1, as a local --workers run
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    for _ in range(nodes - 1):
        cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes()
    return cluster


@pytest.fixture(scope="module")
def cluster():
    """{"cluster": the running Cluster}; a test may replace it (restart), teardown stops the last."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    holder = {"cluster": _start_cluster()}
    yield holder
    holder["cluster"].shutdown()


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The same training in this process, without Ray: pg, 8 episodes in 2 rounds of 4 (4 tasks a
    round on the cluster), a checkpoint after each."""
    out = tmp_path_factory.mktemp("ref") / "run"
    _train(tmp_path_factory, out, episodes=8)
    return out


def _train(tmp_path_factory, out: Path, episodes: int, address: str | None = None, **kw) -> Path:
    return train(tiny_dataset(tmp_path_factory), "pg", out, episodes, settings=FAST, seed=5, ray_address=address,
                 pipeline=pipeline_file(tmp_path_factory), progress=False, agent_kwargs={"batch_episodes": 4},
                 checkpoint_every=4, **kw)


class _Watcher:
    """Records the parents (raylets) of the processes seen running a task of the given title.

    Every 10 ms it reads the titles of this test's Ray processes only ("ray::..." below this
    process, found by a scan of all of /proc every 0.25 s): scanning all of /proc every 10 ms
    cost the driver half a core. A worker is titled "ray::..." for seconds before its first
    task ends (the task imports torch and builds the env), so no worker is missed."""

    RESCAN_SECONDS = 0.25

    def __init__(self, title: str) -> None:
        self.title, self.parents = title, set()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        title, workers, rescan = self.title.encode(), {}, 0.0
        while not self._stop.is_set():
            if time.monotonic() >= rescan:
                workers = own_ray_task_processes("ray::")  # {pid: parent} of this test's Ray processes
                rescan = time.monotonic() + self.RESCAN_SECONDS
            for pid, parent in workers.items():
                try:
                    if Path(f"/proc/{pid}/cmdline").read_bytes().startswith(title):
                        self.parents.add(parent)
                except OSError:  # ended since the scan
                    pass
            time.sleep(0.01)

    def __enter__(self) -> "_Watcher":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


def _raylets(cluster) -> set[int]:
    from ray._private import ray_constants

    return {node.all_processes[ray_constants.PROCESS_TYPE_RAYLET][0].process.pid
            for node in [cluster.head_node, *cluster.worker_nodes]}


def test_train_and_evaluate_on_a_two_node_cluster(cluster, reference, tmp_path_factory, tmp_path):
    c = cluster["cluster"]
    with _Watcher("ray::play_chunk") as seen:
        policy = _train(tmp_path_factory, tmp_path / "run", episodes=8, address=c.address)
    same_run(tmp_path / "run", reference)
    assert seen.parents == _raylets(c) and len(seen.parents) == 2  # workers of both nodes played
    # best_static searches sequences of up to 2 actions (up to 3: about 2 s more for each evaluation)
    kw = dict(episodes_per_lambda=2, pipeline=pipeline_file(tmp_path_factory), time_mode="cost_table", max_ops=5,
              progress=False, plots=False, best_static_length=2, best_static_episodes=2)
    here = evaluate(tiny_dataset(tmp_path_factory), [str(policy)], [0.4], tmp_path / "ev1", **kw)
    there = evaluate(tiny_dataset(tmp_path_factory), [str(policy)], [0.4], tmp_path / "ev2", ray_address=c.address,
                     **kw)
    same_evaluation(here, there)
    assert (there.parent / "fig5.png").exists() is False  # plots=False: nothing else differs


def test_resume_after_the_whole_cluster_restarted(cluster, reference, tmp_path_factory, tmp_path):
    out = tmp_path / "run"
    _train(tmp_path_factory, out, episodes=4, address=cluster["cluster"].address)  # a checkpoint mid-run
    cluster["cluster"].shutdown()
    cluster["cluster"] = _start_cluster(nodes=1)  # a new cluster (one node: quicker): new processes and address
    _train(tmp_path_factory, out, episodes=8, address=cluster["cluster"].address, resume=True)
    same_run(out, reference)
