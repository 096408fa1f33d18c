"""The worker processes that play training episodes: spawned, one pipe each, stopped for sure.

Each worker builds its own environment from an `EnvRecipe` and plays the tasks it is sent (a
policy snapshot and a list of (episode options, acting seed)). Task k of a round always goes
to worker k mod n, one task at a time per worker: which process plays which episodes, and so
what its per-frame caches hold when it plays them, does not depend on timing, and a seeded run
with the same number of workers repeats bit for bit (cost-table mode).

Stopping is bounded: `close()` asks idle workers to leave, or terminates busy ones (SIGTERM),
and SIGKILLs whatever is still alive after `timeout` seconds. Workers ignore SIGINT and SIGHUP
(a Ctrl-C or a closed terminal reaches the whole process group; the parent decides), die on
SIGTERM, leave when their pipe closes (the parent is gone) and, on Linux, are sent SIGTERM by
the kernel when the parent dies (PR_SET_PDEATHSIG), so a killed parent orphans none of them.
Only pipes are used (no multiprocessing queues or semaphores): a killed run leaves nothing in
/dev/shm.
"""
from __future__ import annotations

import ctypes
import multiprocessing as mp
import os
import signal
import time
import traceback
from collections import deque
from multiprocessing.connection import Connection, wait
from typing import Any

from .agents import AGENTS, Agent, EnvRecipe, EnvSpec
from .episode_loop import Trajectory, play_episode
from .open3d_threads import limit_open3d_threads

Task = tuple[tuple, list[tuple[dict[str, Any], int]]]  # (policy snapshot, [(options, act_seed), ...])
_PR_SET_PDEATHSIG = 1


def snapshot(agent: Agent) -> tuple[str, dict[str, Any], dict[str, Any], dict[str, Any], bool]:
    """A picklable copy of an actor's policy."""
    return agent.kind, agent.hparams(), agent.tensors(), agent.state(), agent.explore


def rebuild(snap: tuple, spec: EnvSpec) -> Agent:
    """The agent a `snapshot` describes (a copy: training state such as optimizers not included)."""
    kind, hparams, tensors, state, explore = snap
    agent = AGENTS[kind](spec, **hparams)
    agent.set_tensors(tensors)
    agent.set_state(state)
    agent.explore = explore
    return agent


def _die_with_parent(parent_pid: int) -> None:
    """Linux: the kernel sends SIGTERM when the parent dies; elsewhere the closed pipe ends us."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
    except (OSError, AttributeError):
        return
    if os.getppid() != parent_pid:  # the parent died before the prctl
        os._exit(1)


def _worker_main(conn: Connection, recipe: EnvRecipe, parent_pid: int) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C and stops us
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    _die_with_parent(parent_pid)
    env = spec = None
    error = ""
    try:  # an error is kept for the first task: it reaches the parent with its message
        import torch

        torch.set_num_threads(1)
        if recipe.settings.time_mode == "cost_table":
            limit_open3d_threads(1)
        env = recipe.make()
        spec = EnvSpec.from_env(env)
    except Exception as exc:  # noqa: BLE001  (reported to the parent with the first task)
        error = f"a training worker could not build its environment: {type(exc).__name__}: {exc}"
    while True:
        try:
            task = conn.recv()
        except (EOFError, OSError):  # the parent is gone
            return
        if task is None:
            return
        if error:
            reply: tuple[bool, Any] = (False, error)
        else:
            try:
                snap, episodes = task
                agent = rebuild(snap, spec)
                reply = (True, [play_episode(env, agent, options, seed) for options, seed in episodes])
            except Exception:  # noqa: BLE001  (the parent raises it with the worker's traceback)
                reply = (False, "a training worker failed:\n" + traceback.format_exc())
        try:
            conn.send(reply)
        except (BrokenPipeError, OSError):
            return


class WorkerPool:
    """`n` spawned worker processes playing tasks; task k goes to worker k mod n."""

    def __init__(self, n: int, recipe: EnvRecipe) -> None:
        ctx = mp.get_context("spawn")
        self._procs: list[Any] = []
        self._conns: list[Connection] = []
        try:
            for i in range(int(n)):
                parent, child = ctx.Pipe()
                proc = ctx.Process(target=_worker_main, args=(child, recipe, os.getpid()),
                                   name=f"perception-config-train-worker-{i}", daemon=True)
                proc.start()
                child.close()
                self._procs.append(proc)
                self._conns.append(parent)
        except BaseException:
            self.close(now=True)
            raise

    @property
    def pids(self) -> list[int]:
        return [p.pid for p in self._procs if p.pid is not None]

    def run(self, tasks: list[Task]) -> list[list[Trajectory]]:
        """Every task's trajectories, in task order. A worker that dies or fails raises RuntimeError."""
        n = len(self._procs)
        queues = [deque(k for k in range(len(tasks)) if k % n == w) for w in range(n)]
        results: list[Any] = [None] * len(tasks)
        busy: dict[int, int] = {}  # worker -> task in flight

        def send_next(w: int) -> None:
            if queues[w]:
                k = queues[w].popleft()
                self._conns[w].send(tasks[k])
                busy[w] = k

        for w in range(n):
            send_next(w)
        while busy:
            ready = wait([self._conns[w] for w in busy])
            for w in [w for w in busy if self._conns[w] in ready]:
                try:
                    ok, value = self._conns[w].recv()
                except (EOFError, OSError):
                    self._died(w)
                if not ok:
                    raise RuntimeError(value)
                results[busy.pop(w)] = value
                send_next(w)
        return results

    def _died(self, w: int) -> None:
        proc = self._procs[w]
        # A signal to the whole process group may have ended it: give the parent's handler a
        # moment to run first (it stops the round with its own exception).
        time.sleep(0.2)
        proc.join(1.0)
        raise RuntimeError(
            f"training worker {w} (pid {proc.pid}) died (exit code {proc.exitcode}). If train() is called from a "
            "script, guard the call with `if __name__ == \"__main__\":` (workers are spawned and import the main "
            "module)")

    def close(self, timeout: float = 5.0, now: bool = False) -> None:
        """Stop every worker within about `timeout` s (+1 s for SIGKILL): idle ones leave when
        asked; busy ones (`now`, a dropped round) are terminated at once."""
        for proc, conn in zip(self._procs, self._conns):
            if now:
                proc.terminate()
            else:
                try:
                    conn.send(None)
                except OSError:
                    proc.terminate()
        deadline = time.monotonic() + timeout
        for proc in self._procs:
            proc.join(max(0.0, deadline - time.monotonic()))
            if proc.is_alive():
                proc.terminate()
        for proc in self._procs:
            proc.join(0.5)
            if proc.is_alive():
                proc.kill()
                proc.join(1.0)
        for conn in self._conns:
            conn.close()
        self._procs, self._conns = [], []
