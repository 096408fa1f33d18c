"""Training and evaluation as Ray tasks on a local Ray (one per module: Ray takes seconds to
start): seeded cost-table runs give the same bits with 1 and 2 workers (pg batches, the ES
population, the evaluation sweep with the oracle), a worker killed mid-task is retried with the
same result, a failing task raises with its traceback, the local Ray listens on 127.0.0.1 only,
and without --workers nothing of Ray is imported."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from perception_config.agents import EnvRecipe
from perception_config.agents.policy_io import read_file
from perception_config.learning.evaluation import evaluate
from perception_config.learning.training import CHECKPOINT, train
from perception_config.rl.settings import EnvSettings
from perception_config.store.episode_store import STORE_NAME, EpisodeStore
from rl_helpers import own_ray_task_processes, pipeline_file, same_evaluation, same_run, tiny_dataset

FAST = EnvSettings(time_mode="cost_table", lambda_range=(0.2, 0.8), max_ops=5)
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def local_ray():
    """A local Ray with 2 workers, as `--workers 2` starts it; train/evaluate reuse it."""
    from perception_config.learning.ray_workers import RayRunner

    runner = RayRunner(workers=2)
    yield runner
    runner.close()


@pytest.fixture(scope="module")
def pg_in_process(tmp_path_factory) -> Path:
    """The reference: pg, 8 episodes in 2 rounds of 4, in this process (no Ray)."""
    out = tmp_path_factory.mktemp("pg1") / "pg1"
    _train(tmp_path_factory, out, workers=1)
    return out


def _train(tmp_path_factory, out: Path, workers: int, agent: str = "pg", episodes: int = 8, **kw) -> Path:
    agent_kwargs = {"batch_episodes": 4} if agent == "pg" else {"population": 4, "episodes_per_generation": 2}
    return train(tiny_dataset(tmp_path_factory), agent, out, episodes, settings=FAST, seed=3, workers=workers,
                 pipeline=pipeline_file(tmp_path_factory), progress=False, agent_kwargs=agent_kwargs, **kw)


def _evaluate(tmp_path_factory, out: Path, policy: Path, workers: int) -> Path:
    # best_static searches sequences of up to 2 actions (up to 3: about 2 s more for each evaluation; its
    # tasks, one per chunk of episodes, and their order are the same)
    return evaluate(tiny_dataset(tmp_path_factory), [str(policy)], [0.3, 0.7], out, episodes_per_lambda=2,
                    pipeline=pipeline_file(tmp_path_factory), time_mode="cost_table", max_ops=5, progress=False,
                    plots=False, workers=workers, best_static_length=2, best_static_episodes=2)


def test_one_and_two_workers_give_the_same_bits(local_ray, pg_in_process, tmp_path_factory, tmp_path):
    # pg: rounds of 4 episodes (one per task) over the workers, the policy updated between them.
    policy = pg_in_process / "policy.safetensors"
    _train(tmp_path_factory, tmp_path / "pg2", workers=2)
    same_run(pg_in_process, tmp_path / "pg2")
    # ES: the population's individuals as tasks.
    _train(tmp_path_factory, tmp_path / "es1", workers=1, agent="es", episodes=8)
    _train(tmp_path_factory, tmp_path / "es2", workers=2, agent="es", episodes=8)
    same_run(tmp_path / "es1", tmp_path / "es2")
    meta, tensors = read_file(tmp_path / "es2" / CHECKPOINT)
    assert meta["train_state"]["generation"] == 1 and sum(k.startswith("train/pop.") for k in tensors) == 4 * 6
    # The store is written by the driver, once per episode, in the same order.
    with EpisodeStore(pg_in_process / STORE_NAME, readonly=True) as s1, \
            EpisodeStore(tmp_path / "pg2" / STORE_NAME, readonly=True) as s2:
        query = "SELECT episode_seed, steps, noise_lambda FROM episodes ORDER BY rowid"
        assert s1.query(query) == s2.query(query) and len(s1.query(query)) == 8
    # Evaluation: the policy and the baselines (the oracle searches in the worker's env).
    r1 = _evaluate(tmp_path_factory, tmp_path / "ev1", policy, workers=1)
    r2 = _evaluate(tmp_path_factory, tmp_path / "ev2", policy, workers=2)
    same_evaluation(r1, r2)
    agents = {r["agent"] for r in json.loads(r2.read_text())}
    assert {"pg:pg1", "oracle", "random"} <= agents, agents
    query = "SELECT agent, episode_seed, noise_lambda, steps FROM episodes ORDER BY rowid"
    with EpisodeStore(r1.parent / STORE_NAME, readonly=True) as s1, \
            EpisodeStore(r2.parent / STORE_NAME, readonly=True) as s2:
        assert s1.query(query) == s2.query(query) and len(s2.query(query)) == len(agents) * 2 * 2


def test_a_warm_start_searches_and_replays_on_the_workers_with_the_same_bits(local_ray, tmp_path_factory, tmp_path):
    # The threshold teacher's search (rules as Ray tasks over chunks of episodes) and its replay.
    kw = {"batch_episodes": 4, "warm_start": "threshold", "warm_start_episodes": 4}
    runs = []
    for workers in (1, 2):
        out = tmp_path / f"ws{workers}"
        train(tiny_dataset(tmp_path_factory), "pg", out, 4, settings=FAST, seed=3, workers=workers,
              pipeline=pipeline_file(tmp_path_factory), progress=False, agent_kwargs=kw)
        runs.append(out)
    same_run(*runs)

    def report(obj):  # the warm start's report in the checkpoint's metadata, without its seconds
        if isinstance(obj, dict):
            if isinstance(obj.get("warm_start"), dict) and "teacher" in obj["warm_start"]:
                return {k: v for k, v in obj["warm_start"].items() if k != "seconds"}
            return next((r for r in map(report, obj.values()) if r is not None), None)
        return None

    one, two = (report(read_file(r / CHECKPOINT)[0]) for r in runs)
    assert one is not None and one == two and one["teacher"] == "threshold" and one["episodes_searched"] == 4


def test_a_worker_killed_mid_round_is_retried_with_the_same_result(local_ray, pg_in_process, tmp_path_factory,
                                                                   tmp_path):
    killed: list[int] = []
    stop = threading.Event()

    def killer() -> None:  # SIGKILL the first worker seen playing episodes, once
        while not stop.is_set() and not killed:
            for pid in own_ray_task_processes("ray::play_chunk"):
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
                break
            time.sleep(0.005)

    thread = threading.Thread(target=killer, daemon=True)
    thread.start()
    try:
        _train(tmp_path_factory, tmp_path / "killed", workers=2)
    finally:
        stop.set()
        thread.join()
    assert killed, "no worker was seen playing a task"
    same_run(tmp_path / "killed", pg_in_process)


def test_a_failing_task_raises_with_its_traceback(local_ray, tmp_path_factory):
    from perception_config.learning.ray_workers import play_chunk

    recipe = EnvRecipe(str(tiny_dataset(tmp_path_factory)), str(pipeline_file(tmp_path_factory)), settings=FAST)
    with pytest.raises(RuntimeError, match="(?s)play_chunk.*KeyError: 'no_such_agent'"):
        local_ray.map(play_chunk, [(recipe, ("no_such_agent", {}, {}, {}, True), [])])


def _listening(pids: set[int]) -> list[str]:
    """The local addresses (hex, as /proc/net/tcp* gives them) of the TCP sockets these
    processes listen on."""
    inodes = set()
    for pid in pids:
        try:
            for fd in os.listdir(f"/proc/{pid}/fd"):
                link = os.readlink(f"/proc/{pid}/fd/{fd}")
                if link.startswith("socket:["):
                    inodes.add(link[8:-1])
        except OSError:
            continue
    out = []
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            f = line.split()
            if f[3] == "0A" and f[9] in inodes:  # LISTEN
                out.append(f[1].rsplit(":", 1)[0])
    return out


def _descendants(pid: int) -> set[int]:
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                ppid = int(Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()[1])
            except OSError:
                continue
            children.setdefault(ppid, []).append(int(entry))
    out, todo = set(), [pid]
    while todo:
        p = todo.pop()
        out.add(p)
        todo.extend(children.get(p, ()))
    return out


LOOPBACK_HEX = {"0100007F", "0000000000000000FFFF00000100007F"}  # 127.0.0.1, ::ffff:127.0.0.1


def test_the_local_ray_listens_on_loopback_only(local_ray):
    addresses = _listening(_descendants(os.getpid()))
    assert len(addresses) >= 3, addresses  # the GCS, the raylet, this driver's worker, ...
    assert set(addresses) <= LOOPBACK_HEX, addresses


def test_without_workers_nothing_of_ray_starts(tmp_path_factory, tmp_path):
    """train and evaluate without --workers (and with 1) in a fresh interpreter: ray is never imported."""
    code = f"""
import sys
from perception_config.learning.training import train
from perception_config.learning.evaluation import evaluate
from perception_config.rl.settings import EnvSettings
s = EnvSettings(time_mode="cost_table", lambda_range=(0.2, 0.8), max_ops=5)
p = train({str(tiny_dataset(tmp_path_factory))!r}, "pg", {str(tmp_path / "run")!r}, 4, settings=s,
          pipeline={str(pipeline_file(tmp_path_factory))!r}, progress=False, agent_kwargs={{"batch_episodes": 4}})
evaluate({str(tiny_dataset(tmp_path_factory))!r}, [str(p)], [0.5], {str(tmp_path / "ev")!r}, episodes_per_lambda=2,
         include_baselines=False, progress=False, plots=False, workers=1)
assert "ray" not in sys.modules, [m for m in sys.modules if m.startswith("ray")]
print("no ray")
"""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0 and "no ray" in proc.stdout, proc.stderr[-3000:]
