"""The lambda sweep of an evaluation (learning/evaluation.py): every (agent, lambda)'s planned
episodes, played in this process (`sweep_here`) or as Ray tasks (`sweep_on_ray`: each task a
chunk of one (agent, lambda)'s plan, `evaluation_chunk`), the records in the in-process order
and the episodes handed to the store in that order too."""
from __future__ import annotations

from typing import Any, Callable, Sequence

from ..agents.base import EnvRecipe
from ..rl.env import PerceptionConfigEnv
from ..rl.episode_loop import Trajectory
from .evaluation_agents import EvalAgent
from .evaluation_records import episode_record
from .ray_workers import RayRunner, chunks, rebuild, snapshot, worker_env

Sweep = dict[tuple[str, float], list[dict[str, Any]]]  # (agent, lambda) -> episode records, plan order
Storer = Callable[[EvalAgent, int], Callable[[Trajectory], None] | None]


def sweep_here(env: PerceptionConfigEnv, agents: Sequence[EvalAgent], lams: Sequence[float],
               plan: Sequence[tuple[int, int]], bar: Any, storer: Storer) -> Sweep:
    """Every (agent, lambda)'s planned episodes in this process."""
    out: Sweep = {}
    for lam in lams:
        for ea in agents:
            if bar is not None:
                bar.set_postfix_str(f"{ea.name} lambda={lam:g}")
            eps = out.setdefault((ea.name, lam), [])
            for index, ep_seed in plan:
                eps.append(episode_record(env, ea.agent, index, lam, ep_seed, storer(ea, ep_seed)))
                if bar is not None:
                    bar.update(1)
    return out


def evaluation_chunk(recipe: EnvRecipe, agent: Any, lam: float,
                     plan: Sequence[tuple[int, int]]) -> list[tuple[dict[str, Any], Trajectory]]:
    """A Ray task: one agent (a `ray_workers.snapshot` or a picklable object with `act`) plays
    planned episodes at one lambda in the worker's env; (record, trajectory) per episode."""
    env, spec = worker_env(recipe)
    player = rebuild(agent, spec, env) if isinstance(agent, tuple) else agent
    trajs: list[Trajectory] = []
    recs = [episode_record(env, player, index, lam, ep_seed, trajs.append) for index, ep_seed in plan]
    return list(zip(recs, trajs))


def sweep_on_ray(runner: RayRunner, recipe: EnvRecipe, agents: Sequence[EvalAgent], lams: Sequence[float],
                 plan: Sequence[tuple[int, int]], bar: Any, storer: Storer) -> Sweep:
    """The sweep as Ray tasks on `runner`: each (agent, lambda)'s plan in pieces (ray_workers.chunks)."""
    from ..agents.base import Agent

    recipe_ref = runner.put(recipe)
    pieces = chunks(len(plan), len(agents) * len(lams), runner.cpus)
    refs = [runner.put(snapshot(ea.agent) if isinstance(ea.agent, Agent) else ea.agent) for ea in agents]
    calls, keys = [], []
    for lam in lams:  # the in-process order
        for ea, ref in zip(agents, refs):
            for lo, hi in pieces:
                calls.append((recipe_ref, ref, lam, list(plan[lo:hi])))
                keys.append((ea, lam))

    done: dict[int, list[tuple[dict[str, Any], Trajectory]]] = {}
    stored = [0]  # the calls before this one are in the store: it gets the in-process order

    def arrived(k: int, result: list[tuple[dict[str, Any], Trajectory]]) -> None:
        done[k] = result
        while stored[0] in done:
            j = stored[0]
            ea = keys[j][0]
            for (_rec, traj), (_index, ep_seed) in zip(done.pop(j), calls[j][3]):
                store = storer(ea, ep_seed)
                if store is not None:
                    store(traj)
            stored[0] += 1
        if bar is not None:
            bar.set_postfix_str(f"{keys[k][0].name} lambda={keys[k][1]:g}")
            bar.update(len(result))

    results = runner.map(evaluation_chunk, calls, arrived)
    out: Sweep = {}
    for (ea, lam), result in zip(keys, results):
        out.setdefault((ea.name, lam), []).extend(rec for rec, _traj in result)
    return out
