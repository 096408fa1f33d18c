"""The oracle: hindsight search for the fastest action sequence of one episode.

It is not a policy (it looks at the outcome of actions before taking them, including the
ground-truth pick) but the lower bound no agent can beat: it tries action sequences on the
very same episode state, and the operators' snapshot/restore let it branch from any node
without replaying the prefix. The episode's rng is part of the snapshot, so stochastic blocks
(e.g. `regenerate`) draw the same numbers as when the sequence is replayed in the env.

Search: uniform-cost (Dijkstra) over action sequences, costs = the env's own accounting
(`env.action_seconds`: measured or cost-table seconds of the block plus the scoring pass, plus
`failed_pick_cost` for a failed pick). A node is expanded by applying every action once:
- a successful pick is a solution (cost known: pushes the incumbent `best` down);
- a failed pick, a failed action and an action that moves the pose less than `noop_tol`
  (translation / diameter, rotation in rad) leave the state as it was: pruned, since the same
  sequence without them is cheaper;
- branch and bound: a node whose cost plus the cheapest pick already reaches `best` is not
  expanded; as nodes come off the queue cheapest first, the search ends when the next one
  does, and `best` is then optimal;
- memo: a (pose, rng state, candidates left) reached before at no higher cost and no deeper is pruned;
- actions that cannot run on the episode's frame (`env.frame_mask()`: depth blocks on an
  RGB-only frame) are never tried;
- depth is bounded by the env's remaining max_ops, work by `node_budget` operator calls.
`exact` says the search finished within the budget: then no cheaper sequence exists (with
cost-table time, exactly; with measured time, for the times measured during the search).
"""
from __future__ import annotations

import heapq
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..core.geometry import rotation_angle
from ..rl.trajectory import allowed_actions
from .base import Agent, EnvSpec
from .hparams import SEED, Float, Int


@dataclass
class OracleResult:
    """The best action sequence `oracle_search` found from a state, with its cost."""

    actions: list[str]  # the best sequence found (ends with a successful pick); [] if none
    seconds: float  # its cost; inf when no sequence was found
    found: bool
    exact: bool  # the search completed: no cheaper sequence exists
    evaluations: int  # operator calls spent
    times: list[float] = field(default_factory=list)  # seconds of each action of `actions`
    cheapest_non_pick: int = 0  # the action index that costs least without picking (fallback)


def _charge(env: Any, action: int, outcome: Any) -> tuple[float, bool, bool]:
    """(seconds, is_pick, picked) exactly as env.step accounts them."""
    block = env.pipeline.actions[action].block
    seconds = env.action_seconds(outcome, block)
    is_pick = block.kind.value == "pick"
    picked = bool(is_pick and outcome.result.ok and outcome.result.picked)
    if is_pick and outcome.result.ok and not outcome.result.picked:
        seconds += env.settings.failed_pick_cost
    return float(seconds), is_pick, picked


def oracle_search(env: Any, node_budget: int = 2000, noop_tol: float = 1e-6) -> OracleResult:
    """Best action sequence from the env's current state (normally right after reset).

    The env is left exactly as it was (its operators are restored to the starting snapshot).
    """
    env = getattr(env, "unwrapped", env)
    if env.episode is None:
        raise RuntimeError("oracle_search needs an episode: call env.reset() first")
    ops = env.ops
    names = env.action_names
    # The frame's mask: what can never run on this frame (the search itself skips failed actions).
    runnable = [bool(m) for m in env.frame_mask()] if hasattr(env, "frame_mask") else [True] * len(names)
    pick_ids = [i for i, a in enumerate(env.pipeline.actions) if a.kind.value == "pick" and runnable[i]]
    pick_ids = pick_ids or [i for i, a in enumerate(env.pipeline.actions) if a.kind.value == "pick"]
    max_depth = env.max_ops - env.steps
    diameter = float(env.episode.model.diameter)
    cost_table = env.settings.time_mode == "cost_table"
    if cost_table:  # admissible: every solution ends with one pick
        min_pick = min(env.cost_table_seconds(env.pipeline.actions[i].block) for i in pick_ids)
    else:
        min_pick = 0.0  # replaced by the cheapest pick measured during the search

    root = ops.snapshot()
    root_pose = env.last_outcome.pose if env.last_outcome is not None else None
    best, best_path, best_times = math.inf, (), ()
    action_cost = [math.inf] * len(names)  # the cheapest seconds seen per action (the fallback)
    evaluations, counter, exhausted = 0, 0, False
    # Queue entries: (cost, tiebreak, depth, path, per-action seconds, pose, snapshot).
    heap: list[tuple[float, int, int, tuple[int, ...], tuple[float, ...], Any, Any]] = [
        (0.0, 0, 0, (), (), root_pose, root)]
    seen: dict[Any, list[tuple[float, int]]] = {}
    try:
        while heap:
            cost, _, depth, path, times, pose, state = heapq.heappop(heap)
            if cost + min_pick >= best:
                break  # every node left costs at least this much: `best` is optimal
            if depth >= max_depth:
                continue
            for a in range(len(names)):
                if not runnable[a]:
                    continue  # its block needs an input the frame lacks
                if evaluations >= node_budget:
                    exhausted = True
                    break
                ops.restore(state)
                outcome = ops.apply(names[a])
                evaluations += 1
                seconds, is_pick, picked = _charge(env, a, outcome)
                action_cost[a] = min(action_cost[a], seconds)
                c = cost + seconds
                if is_pick:
                    if not cost_table and outcome.result.ok:
                        pick_s = env.action_seconds(outcome, env.pipeline.actions[a].block)
                        min_pick = pick_s if min_pick == 0.0 else min(min_pick, pick_s)
                    if picked and c < best:
                        best, best_path, best_times = c, path + (a,), times + (seconds,)
                    continue  # a failed pick changes nothing but the time
                new = outcome.pose
                if not outcome.result.ok or new is None:
                    continue  # failed action: the hypothesis is unchanged
                if pose is not None and (np.linalg.norm(new.t - pose.t) / diameter < noop_tol
                                         and rotation_angle(new.R, pose.R) < noop_tol):
                    continue  # no-op: the same state, later
                if c + min_pick >= best:
                    continue
                rng = getattr(ops, "rng", None)
                key = (new.R.tobytes(), new.t.tobytes(), repr(rng.bit_generator.state) if rng is not None else "",
                       len(getattr(ops, "candidates", ())))  # the ranked candidates still waiting
                entries = seen.setdefault(key, [])
                if any(c0 <= c and d0 <= depth + 1 for c0, d0 in entries):
                    continue  # reached before, cheaper and no deeper
                entries.append((c, depth + 1))
                counter += 1
                heapq.heappush(heap, (c, counter, depth + 1, path + (a,), times + (seconds,), new, ops.snapshot()))
            if exhausted:
                break
    finally:
        ops.restore(root)
    found = best < math.inf
    non_pick = [a for a in range(len(names)) if a not in pick_ids and runnable[a]] or pick_ids
    cheapest = min(non_pick, key=lambda a: action_cost[a])
    return OracleResult([names[a] for a in best_path], best, found, not exhausted, evaluations, list(best_times),
                        cheapest)


class OracleAgent(Agent):
    """Plays the oracle's sequence. Needs the live env (`env=` or `attach`); not trainable.

    At the first decision of an episode it searches; it then replays the sequence. If the
    replay diverges (measured time: time-bounded blocks may stop at a different iteration)
    and the sequence runs out before the episode ends, it searches again from there. If no
    sequence is found (a hopeless episode, or the budget ran out) it spends the rest of the
    episode on the cheapest non-pick action: in hindsight every pick fails, and the cheapest
    way to the end of the episode is the best return there is (where the env's mask forbids it,
    at the last operation under the final-pick rule, a pick).
    """

    kind = "oracle"
    HPARAM_BOUNDS = {"node_budget": Int(1, 1_000_000), "noop_tol": Float(0.0, 1.0), "seed": SEED}

    def __init__(self, spec: EnvSpec, env: Any = None, node_budget: int = 2000, noop_tol: float = 1e-6,
                 seed: int = 0) -> None:
        super().__init__(spec, seed)
        if node_budget < 1:
            raise ValueError(f"node_budget must be >= 1, got {node_budget}")
        self.env = env
        self.node_budget, self.noop_tol = int(node_budget), float(noop_tol)
        self.plan: list[int] = []
        self.last_result: OracleResult | None = None
        self.results: list[OracleResult] = []  # one per search, for reports

    def attach(self, env: Any) -> None:
        self.env = env

    def begin_episode(self, seed: int | None = None) -> None:
        super().begin_episode(seed)
        self.plan = []

    def act(self, obs: np.ndarray, info: dict[str, Any]) -> int:
        if self.env is None:
            raise RuntimeError("the oracle needs the live environment: OracleAgent(spec, env=env) or agent.attach(env)")
        if (isinstance(info, dict) and info.get("steps") == 0) or not self.plan:
            res = oracle_search(self.env, self.node_budget, self.noop_tol)
            self.last_result = res
            self.results.append(res)
            self.plan = [self.spec.action_names.index(n) for n in res.actions] if res.found else [res.cheapest_non_pick]
        a = self.plan.pop(0)
        allowed = allowed_actions(info, self.spec.n_actions)
        if allowed is not None and not allowed[a] and allowed.any():
            # the fallback's action, forbidden by a rule of the env's (the final-pick rule at the
            # last operation): a pick where one may run, else the first action that may
            picks = [i for i in self.spec.pick_actions if allowed[i]]
            a = picks[0] if picks else int(np.flatnonzero(allowed)[0])
        return a

    def hparams(self) -> dict[str, Any]:
        return {"node_budget": self.node_budget, "noop_tol": self.noop_tol, "seed": self.seed}
