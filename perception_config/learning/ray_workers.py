"""Episodes played on several processes or machines, as Ray tasks (training rounds, the ES
population, the evaluation sweep).

`ray_wanted(workers, address)`: Ray is used only with `--workers N` (N > 1) or `--ray-address`;
otherwise the callers play in their own process and `ray` is never imported. `RayRunner`
starts a local Ray (N CPUs; its GCS, raylet, object manager and workers listen on 127.0.0.1
only, no dashboard, no usage report, quiet logs, no task events: they cost the GCS and the
workers CPU per task, and only the dashboard reads them) or joins a running cluster (`address`, e.g.
"127.0.0.1:6379" of `ray start --head`, or "auto"), and runs a list of calls of a module-level
function as tasks, results in call order. A process that already called `ray.init` is used as
it is (and left running).

Results do not depend on which worker plays which task: each task carries its policy snapshot
and its episodes with their seeds (`play_episode` reseeds the env and the agent per episode),
every worker builds its environment from the `EnvRecipe` (the dataset path and the pipeline;
the path must exist on every node), and the per-frame caches a worker keeps between tasks are
pure functions of their keys (the frame, the pose, the crop: vision/edges.TensorCache), so
what a process played before changes nothing. In cost-table mode a seeded run therefore gives
the same bits for 1 and N workers and across retries.

Faults: a task whose worker process dies (killed, out of memory, its node lost) is run again
elsewhere up to TASK_RETRIES times (Ray's max_retries), with the same result; an exception
raised by the task itself is a bug and is not retried: it reaches the caller as a RuntimeError
with the worker's traceback.
"""
from __future__ import annotations

import logging
import math
import os
import pickle
import signal
import sys
import threading
from collections import OrderedDict
from typing import Any, Callable, Sequence

from ..agents import AGENTS, Agent, EnvRecipe, EnvSpec
from ..rl.episode_loop import Trajectory, play_episode
from ..util.open3d_threads import limit_open3d_threads

TASK_RETRIES = 3  # runs of a task whose worker died, after the first
WAIT_SECONDS = 0.2  # the driver waits in slices this long, so that a stop signal is handled at once
TASKS_PER_CPU = 8  # a call is cut into at least this many tasks per CPU: the workers end a round together

Snapshot = tuple[str, dict[str, Any], dict[str, Any], dict[str, Any], bool]


def ray_wanted(workers: int | None, address: str | None) -> bool:
    """Ray only for more than one worker or a cluster address."""
    return bool(address) or (workers is not None and int(workers) > 1)


def chunks(n: int, groups: int, cpus: int) -> list[tuple[int, int]]:
    """[lo, hi) bounds cutting each of `groups` lists of `n` items (an actor's episodes, an
    (agent, lambda)'s plan) into pieces, so that all groups give about TASKS_PER_CPU tasks per
    CPU (one item per task at most). Small tasks balance the workers at the end of a round (an
    episode takes 1 to max_ops operations); the pieces change nothing in the results."""
    if n < 1:
        return []
    k = min(n, max(1, math.ceil(TASKS_PER_CPU * cpus / max(1, groups))))
    bounds = [round(i * n / k) for i in range(k + 1)]
    return list(zip(bounds[:-1], bounds[1:]))


# -- policies as data -------------------------------------------------------------------------
def snapshot(agent: Agent) -> Snapshot:
    """A picklable copy of an actor's policy: kind, hyper-parameters, tensors, state, explore."""
    return agent.kind, agent.hparams(), agent.tensors(), agent.state(), agent.explore


def rebuild(snap: Snapshot, spec: EnvSpec, env: Any = None) -> Agent:
    """The agent of a snapshot, for this process's env (the oracle searches in it)."""
    kind, hparams, tensors, state, explore = snap
    agent = AGENTS[kind](spec, **hparams)
    agent.set_tensors(tensors)
    agent.set_state(state)
    agent.explore = explore
    if env is not None and hasattr(agent, "attach"):
        agent.attach(env)
    return agent


# -- the worker side --------------------------------------------------------------------------
_ENVS: "OrderedDict[bytes, tuple[Any, EnvSpec]]" = OrderedDict()
_ENVS_KEPT = 2  # a training env and an evaluation env


def worker_env(recipe: EnvRecipe) -> tuple[Any, EnvSpec]:
    """This process's environment for `recipe`, built on first use and kept (with its frame and
    model caches) for the next tasks. Torch on one thread; in cost-table mode Open3D too (its
    parallel ICP sums are not reproducible)."""
    key = pickle.dumps(recipe)
    if key in _ENVS:
        _ENVS.move_to_end(key)
        return _ENVS[key]
    import torch

    from ..util.allocator import keep_freed_memory

    keep_freed_memory()  # the operators' arrays reuse freed memory (util/allocator.py)
    torch.set_num_threads(1)
    if recipe.settings.time_mode == "cost_table":
        limit_open3d_threads(1)
    env = recipe.make()
    _ENVS[key] = (env, EnvSpec.from_env(env))
    while len(_ENVS) > _ENVS_KEPT:
        _ENVS.popitem(last=False)
    return _ENVS[key]


def play_chunk(recipe: EnvRecipe, snap: Snapshot, episodes: Sequence[tuple[dict[str, Any], int]]) -> list[Trajectory]:
    """A task: one policy plays (episode options, acting seed) pairs in this worker's env."""
    env, spec = worker_env(recipe)
    agent = rebuild(snap, spec, env)
    return [play_episode(env, agent, options, int(seed)) for options, seed in episodes]


# -- the driver side --------------------------------------------------------------------------
def _is_loopback(address: str) -> bool:
    """A cluster address on this machine's loopback ("127.0.0.1:6379", "localhost:6379", "[::1]:6379")."""
    host = address.split("://")[-1].rsplit(":", 1)[0].strip("[]")
    return host == "localhost" or host == "::1" or host.startswith("127.")


def loopback_only() -> None:
    """A local Ray on 127.0.0.1 only. ray.init(_node_ip_address="127.0.0.1") is turned into the
    machine's address, and its gRPC servers listen on every interface; Ray's local-only mode (the
    one it runs on macOS and Windows, RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0) takes 127.0.0.1 as the
    node's address and binds the GCS, the raylet, the object manager and the workers to it.
    The variable is read when ray is imported; a process that imported it before gets the
    same switch set on the imported module. The worker processes inherit the variable."""
    os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
    constants = sys.modules.get("ray._private.ray_constants")
    if constants is not None:
        constants.ENABLE_RAY_CLUSTER = False


class RayRunner:
    """Runs calls of module-level functions as Ray tasks; see the module docstring.

    `workers`: CPUs of the local Ray this starts (ignored when joining a cluster: the cluster's
    CPUs count). `address`: a running cluster to join. `close()` stops the local Ray it started
    or disconnects from the cluster; a Ray this process had already initialised stays."""

    def __init__(self, workers: int | None = None, address: str | None = None) -> None:
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # no usage report leaves the machine
        if not address or _is_loopback(address):  # else Ray would look for 127.0.0.1's GCS on the LAN address
            loopback_only()
        import ray

        self._ray = ray
        self._owned = not ray.is_initialized()
        self._sigterm: Any = None  # ray.init replaces the driver's SIGTERM handler: put back on close
        if self._owned and threading.current_thread() is threading.main_thread():
            self._sigterm = signal.getsignal(signal.SIGTERM)
        if self._owned:
            kw: dict[str, Any] = {"include_dashboard": False, "logging_level": logging.WARNING,
                                  "log_to_driver": False, "configure_logging": True}
            if address:
                ray.init(address=address, **kw)
            else:
                ray.init(num_cpus=max(1, int(workers or 1)), **kw)
        self._remotes: dict[Callable[..., Any], Any] = {}

    @property
    def cpus(self) -> int:
        """The CPUs of the cluster: how many tasks run at once."""
        return max(1, int(self._ray.cluster_resources().get("CPU", 1)))

    def put(self, value: Any) -> Any:
        """A value every task of this runner may read (sent once to the object store)."""
        return self._ray.put(value)

    def _remote(self, func: Callable[..., Any]) -> Any:
        if func not in self._remotes:
            self._remotes[func] = self._ray.remote(num_cpus=1, max_retries=TASK_RETRIES, retry_exceptions=False,
                                                   enable_task_events=False)(func)
        return self._remotes[func]

    def map(self, func: Callable[..., Any], calls: Sequence[tuple[Any, ...]],
            on_result: Callable[[int, Any], None] | None = None) -> list[Any]:
        """func(*call) for every call, as tasks; the results in call order. `on_result(k, r)` is
        called as results arrive. Any exception (a failed task, a stop signal) cancels the rest."""
        ray = self._ray
        remote = self._remote(func)
        refs = [remote.remote(*call) for call in calls]
        index = {ref: k for k, ref in enumerate(refs)}
        results: list[Any] = [None] * len(refs)
        pending = list(refs)
        try:
            while pending:
                done, pending = ray.wait(pending, num_returns=len(pending), timeout=WAIT_SECONDS,
                                         fetch_local=True)
                for ref in done:
                    k = index[ref]
                    try:
                        results[k] = ray.get(ref)
                    except ray.exceptions.RayTaskError as exc:
                        raise RuntimeError(f"a Ray task ({getattr(func, '__name__', func)}) failed:\n{exc}") from None
                    except ray.exceptions.RayError as exc:
                        raise RuntimeError(f"a Ray task ({getattr(func, '__name__', func)}) was lost after "
                                           f"{TASK_RETRIES} retries: {type(exc).__name__}: {exc}") from None
                    if on_result is not None:
                        on_result(k, results[k])
        except BaseException:
            # A local Ray this runner started is shut down next (close), which ends its workers.
            # Force-cancelling them first races Ray's own retry of a killed task and can crash
            # the driver in the middle of saving (a RAY_CHECK in task_manager.cc; ray-project/ray
            # #54260). On a joined cluster the tasks get a KeyboardInterrupt instead: their
            # workers live on, so nothing is retried.
            if not self._owned:
                for ref in pending:
                    try:
                        ray.cancel(ref, force=False)
                    except Exception:  # noqa: BLE001  (already finished or gone: nothing to cancel)
                        pass
            raise
        return results

    def close(self) -> None:
        """Stop the local Ray this runner started, or leave the cluster it joined."""
        if self._owned and self._ray.is_initialized():
            self._ray.shutdown()
        if self._sigterm is not None and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, self._sigterm)
        self._owned, self._sigterm = False, None

    def __enter__(self) -> "RayRunner":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
