"""The best static pipeline: the fixed action sequence with the lowest mean episode cost on
training episodes, found by exhaustive search (Dynamic Algorithm Configuration's reference: the
best static configuration, what SMAC or irace would return), then played like a fixed pipeline.

Candidates: every sequence of 1..`max_length` of the pipeline's action names with at least one
pick action (`static_sequences`). Each is played exactly as `FixedAgent(sequence, after="repeat")`
plays it: the same agent object decides (its retry, pick and mask rules are not copied here).

Score: the mean episode cost over the search's episodes (minus the return: the seconds the env
charged, failed picks at their robot cost, plus the truncation penalty of giving up), charged in
the env's own time (its settings: cost-table seconds by default, load independent). Ties (means
within a nanosecond): the shorter sequence, then the names (`rank`).

Exhaustive and prefix-shared (`search_episode`): per episode, one walk of the tree of played
action prefixes. At a node every sequence still playing asks its FixedAgent for the next action
(on the node's obs and info); the sequences are grouped by the action they chose, and each group
steps the env once from the node's state (`env.snapshot()` / `env.restore(state)`, the whole
episode state, env and operators, restored before each branch). Sequences whose decisions
coincide share the env steps, so [pick] and [pick, icp_fine] cost one step while the first pick
succeeds. A sequence's FixedAgent moves along its own path only, so no agent state is copied.
Paths also meet again: an action from the same operator state (the same hypothesis, scores,
rng streams and candidates: [pick, icp_coarse] after a failed pick, and [icp_coarse]) gives the
same outcome, so the operators answer it from a per-episode memo keyed by their snapshot
(`StateMemo`: about half the operator calls of a search, 2.4x faster, measured on data/default).
The cost a sequence gets is, bit for bit in cost-table mode, what `play_episode` charges its
FixedAgent on the same episode options (test/test_best_static.py); with measured time, the
seconds measured the first time the memo met the call.

`BestStaticAgent(spec, sequences={lambda: names})` plays, per noise level, the sequence found for
it (`info["noise_lambda"]` says which; the nearest searched lambda for another one, the lowest
when the info has none); without sequences (nothing searched: a stand-in) it plays every action
of the pipeline in its order, as a fixed sequence. The search over an
evaluation's train episodes (one per lambda, in-process or on Ray workers) is
learning/evaluation_best_static.py.
"""
from __future__ import annotations

import itertools
import math
import pickle
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from ..core.geometry import check_noise_lambda
from .base import Agent, EnvSpec
from .fixed import FixedAgent
from .hparams import SEED, StrList

MAX_LENGTH_LIMIT = 8  # longer sequences are refused: 7 actions give 5.7 million of length 8


def static_sequences(action_names: Sequence[str], action_kinds: Sequence[str],
                     max_length: int) -> list[tuple[str, ...]]:
    """Every sequence of 1..max_length action names with at least one pick action, shortest
    first, then in the pipeline's action order."""
    if isinstance(max_length, bool) or not isinstance(max_length, (int, np.integer)) \
            or not 1 <= max_length <= MAX_LENGTH_LIMIT:
        raise ValueError(f"best_static max_length must be an integer in 1..{MAX_LENGTH_LIMIT}, got {max_length!r}")
    picks = {n for n, k in zip(action_names, action_kinds) if k == "pick"}
    if not picks:
        raise ValueError("best_static needs a pick action in the pipeline: a sequence without one never succeeds")
    return [seq for length in range(1, int(max_length) + 1)
            for seq in itertools.product(action_names, repeat=length) if picks & set(seq)]


def search_episode(env: Any, players: Sequence[FixedAgent], options: dict[str, Any],
                   act_seed: int | None = None) -> np.ndarray:
    """Episode cost (minus the return) of each player on one episode, float64 of len(players).

    One walk of the tree of played prefixes (module docstring). `options` and `act_seed` are
    what `play_episode` would be given; the env is reset with them and left at a final state of
    one of the branches.
    """
    env_ = getattr(env, "unwrapped", env)
    costs = np.full(len(players), np.nan)
    obs, info = env.reset(options=options)
    for p in players:
        p.begin_episode(act_seed)
    # A branch: the state to restore (None: the env is there), the action, its players, the cost so far.
    stack: list[tuple[Any, int, list[int], float]] = []

    def branch(state: Any, obs: np.ndarray, info: dict[str, Any], members: list[int], cost: float) -> None:
        groups: dict[int, list[int]] = {}
        for i in members:
            groups.setdefault(int(players[i].act(obs, info)), []).append(i)
        if len(groups) > 1 and state is None:
            state = env_.snapshot()
        for a, group in groups.items():
            stack.append((state, a, group, cost))

    branch(None, obs, info, list(range(len(players))), 0.0)
    while stack:
        state, a, members, cost = stack.pop()
        if state is not None:
            env_.restore(state)
        obs, reward, terminated, truncated, info = env.step(a)
        for i in members:
            players[i].observe(reward, obs, terminated, truncated, info)
        cost -= reward  # the same float operations as play_episode's
        if terminated or truncated:
            costs[members] = cost
        else:
            branch(None, obs, info, members, cost)
    return costs


class StateMemo:
    """The env's operators with a memo: `apply(action)` from an operator state met before in this
    episode (the same `snapshot()`, compared as its pickled bytes) returns the outcome it gave
    then and restores the state it left. Everything else goes to the wrapped operators."""

    def __init__(self, ops: Any) -> None:
        self.ops = ops
        self._seen: dict[tuple[str, bytes], tuple[Any, Any]] = {}
        self.calls = self.hits = 0

    def __getattr__(self, name: str) -> Any:
        return getattr(self.ops, name)

    def start(self, episode: Any) -> Any:
        self._seen.clear()  # per episode: the frame, the model and the ground truth change
        return self.ops.start(episode)

    def apply(self, action: str) -> Any:
        self.calls += 1
        key = (action, pickle.dumps(self.ops.snapshot(), protocol=pickle.HIGHEST_PROTOCOL))
        seen = self._seen.get(key)
        if seen is not None:
            self.hits += 1
            self.ops.restore(seen[1])
            return seen[0]
        outcome = self.ops.apply(action)
        self._seen[key] = (outcome, self.ops.snapshot())
        return outcome

    def snapshot(self) -> Any:
        return self.ops.snapshot()

    def restore(self, state: Any) -> None:
        self.ops.restore(state)


def search_costs(env: Any, sequences: Sequence[Sequence[str]], episodes: Sequence[tuple[dict[str, Any], int]],
                 on_episode: Any = None) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """The episode cost of every sequence, played as FixedAgent(sequence, after="repeat"), on
    every (reset options, acting seed) episode: float64 (len(episodes), len(sequences)); and the
    (scene_id, im_id) of each episode's image. `on_episode()` is called after each episode (a
    progress bar). The env's operators are wrapped in a `StateMemo` while it runs."""
    spec = EnvSpec.from_env(getattr(env, "unwrapped", env))
    return search_players(env, [FixedAgent(spec, list(s), after="repeat") for s in sequences], episodes, on_episode)


def search_players(env: Any, players: Sequence[Agent], episodes: Sequence[tuple[dict[str, Any], int]],
                   on_episode: Any = None) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """`search_costs` for any deterministic players (each decides from the obs and info of its
    own path: FixedAgent, agents/threshold.ThresholdAgent): (len(episodes), len(players))."""
    env_ = getattr(env, "unwrapped", env)
    out = np.empty((len(episodes), len(players)))
    images: list[tuple[int, int]] = []
    ops = env_.ops
    env_.ops = StateMemo(ops)
    try:
        for k, (options, act_seed) in enumerate(episodes):
            out[k] = search_episode(env, players, options, act_seed)
            images.append((int(env_.episode.key[0]), int(env_.episode.key[1])))
            if on_episode is not None:
                on_episode()
    finally:
        env_.ops = ops
    return out, images


TIE_SECONDS = 1e-9  # mean costs this close are ties: the same seconds summed in another order


def rank(sequences: Sequence[Sequence[str]], costs: np.ndarray) -> list[int]:
    """Sequence indices best first: by mean cost over the episodes (the rows of `costs`, summed
    in row order; rounded to TIE_SECONDS, as two sequences that spend the same seconds in another
    order differ in the last bits), then the shorter sequence, then the names."""
    mean = np.asarray(costs, np.float64).sum(axis=0) / max(1, len(costs))
    return sorted(range(len(sequences)),
                  key=lambda i: (round(float(mean[i]) / TIE_SECONDS), len(sequences[i]), tuple(sequences[i])))


@dataclass
class SearchResult:
    """The outcome of one search (one lambda): the chosen sequence, the runner-up, their costs."""

    sequence: list[str]
    mean_cost: float
    runner_up: list[str] | None
    runner_up_cost: float | None
    episodes: int
    sequences: int
    max_length: int
    seconds: float  # wall seconds the search took
    images: list[tuple[int, int]]  # the (scene_id, im_id) searched, sorted, each once

    @classmethod
    def from_costs(cls, sequences: Sequence[Sequence[str]], costs: np.ndarray, max_length: int,
                   seconds: float, images: Sequence[tuple[int, int]] = ()) -> "SearchResult":
        if len(costs) == 0 or not np.isfinite(costs).all():
            raise ValueError("best_static search: every sequence needs a finite cost on at least one episode")
        order = rank(sequences, costs)
        mean = costs.sum(axis=0) / len(costs)
        second = order[1] if len(order) > 1 else None
        return cls(list(sequences[order[0]]), float(mean[order[0]]),
                   list(sequences[second]) if second is not None else None,
                   float(mean[second]) if second is not None else None,
                   len(costs), len(sequences), int(max_length), float(seconds),
                   sorted({(int(a), int(b)) for a, b in images}))

    def to_json(self) -> dict[str, Any]:
        return {"episodes": self.episodes, "sequences": self.sequences, "max_length": self.max_length,
                "mean_cost": self.mean_cost, "runner_up": self.runner_up, "runner_up_cost": self.runner_up_cost,
                "seconds": self.seconds, "images": [list(k) for k in self.images]}


class _SequencesByLambda:
    """The bound of BestStaticAgent's `sequences`: {lambda: [names]} with lambdas in [0, LAMBDA_MAX]."""

    def check(self, name: str, v: Any) -> None:
        if v is None:
            return
        if not isinstance(v, Mapping) or len(v) > 1000:
            raise ValueError(f"hyper-parameter {name} must map noise levels to action names, got {v!r}"[:300])
        for lam, seq in v.items():
            try:
                check_noise_lambda(float(lam))
            except (TypeError, ValueError):
                raise ValueError(f"hyper-parameter {name} has a key {lam!r} that is no noise level"[:300]) from None
            StrList(MAX_LENGTH_LIMIT).check(f"{name}[{lam}]", seq)


class BestStaticAgent(Agent):
    """Plays the searched sequence of the episode's noise level as a FixedAgent (module docstring)."""

    kind = "best_static"
    HPARAM_BOUNDS = {"sequences": _SequencesByLambda(), "seed": SEED}

    def __init__(self, spec: EnvSpec, sequences: Mapping[Any, Sequence[str]] | None = None, seed: int = 0) -> None:
        super().__init__(spec, seed)
        _SequencesByLambda().check("sequences", sequences)
        self.sequences = {check_noise_lambda(float(lam)): [str(s) for s in seq]
                          for lam, seq in sorted((sequences or {}).items(), key=lambda kv: float(kv[0]))}
        self._players = {lam: FixedAgent(spec, seq, after="repeat", seed=seed) for lam, seq in self.sequences.items()}
        self._default = FixedAgent(spec, list(spec.action_names), after="repeat", seed=seed)
        self.search: dict[float, SearchResult] = {}  # the search reports, where this process searched
        self.single_search: SearchResult | None = None  # the lambdas' costs pooled (evaluation_best_static)

    def sequence_for(self, noise_lambda: float | None) -> list[str]:
        """The sequence played at this noise level."""
        return list(self._player(noise_lambda).sequence)

    def _player(self, noise_lambda: float | None) -> FixedAgent:
        if not self._players:
            return self._default
        lams = list(self._players)
        if noise_lambda is None or not math.isfinite(float(noise_lambda)):
            return self._players[lams[0]]
        return self._players[min(lams, key=lambda lam: abs(lam - float(noise_lambda)))]

    def begin_episode(self, seed: int | None = None) -> None:
        super().begin_episode(seed)
        for p in [*self._players.values(), self._default]:
            p.begin_episode(seed)

    def act(self, obs: np.ndarray, info: dict[str, Any]) -> int:
        lam = info.get("noise_lambda") if isinstance(info, dict) else None
        return self._player(lam).act(obs, info)

    def hparams(self) -> dict[str, Any]:
        return {"sequences": {repr(lam): list(seq) for lam, seq in self.sequences.items()}, "seed": self.seed}
