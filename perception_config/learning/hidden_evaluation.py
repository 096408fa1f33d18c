"""The cell simulation's hidden judge: every served policy version on a fixed evaluation set.

`perception-config cell-sim` runs a cell whose learner may see only the robot's pick outcomes
(`--labels robot`). Whether its promotions truly helped is a question for the simulator's hidden
ground truth: after the run, each version kept in `<learn_dir>/policies/` plays the same fixed
episodes (every object of the bag's images with visib_fract >= 0.3, `seeds` episode seeds each,
the run's lambda), in-process, greedy, with the ground-truth simulated pick and cost-table time
(the same seconds for the same actions, whatever the machine's load); the blocks keep their time
bounds, as in the cell, and a generator's result is reused for the same call, so every version
meets the same hypotheses. A version's figures:
success share, first-pick share, mean cost (charged seconds + failed picks + truncation: what
the reward and the learner's gate optimise) and mean time. A promoted version is **worse** than
the one it replaced (the version serving when it was trained) when its mean cost is higher or
its success share lower on these episodes (`worse_promotions`), and **significantly worse** when
that holds beyond the episodes' own noise (`paired_worse`: a one-sided 95 % bound on the paired
cost differences above 0, or fewer successes by an exact sign test at p < 0.05;
`significantly_worse_promotions`).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..agents.policy_io import load_agent
from ..blocks.pipeline import load_pipeline
from ..learning.evaluation import episode_seed
from ..rl.env import PerceptionConfigEnv
from ..rl.episode_loop import acting_seed, play_episode
from ..rl.episodes import EpisodeSource
from ..rl.operators import InProcessOperators
from ..rl.settings import EnvSettings
from ..util.versions import PolicyVersions

HIDDEN_SEED = 7_000  # the evaluation episodes' seeds: fixed, apart from the cell's own


def evaluate_versions(policies: str | Path, dataset: str | Path, keys: Sequence[tuple[int, int]], pipeline: Any,
                      env_settings: EnvSettings, noise_lambda: float, seeds: int = 1, progress: bool = False
                      ) -> dict[str, dict[str, Any]]:
    """{version: figures} for every version kept in the `policies` folder (module docstring)."""
    from tqdm import tqdm

    versions = PolicyVersions(policies)
    pipe = load_pipeline(pipeline)
    # bounded as in the cell (an unbounded global registration takes 7 s a call); a generator's
    # result is reused for the same call, so every version meets the same hypotheses
    env = PerceptionConfigEnv(None, pipe, env_settings.replace(time_mode="cost_table"),
                              operators=InProcessOperators(pipe, time_bounded=True))
    source = EpisodeSource(dataset, list(keys))
    episodes = [source.load(i, noise_lambda, max(1, episode_seed(HIDDEN_SEED + s, i)))
                for s in range(int(seeds)) for i in range(len(source))]
    out: dict[str, dict[str, Any]] = {}
    entries = versions.list()
    bar = tqdm(total=len(entries) * len(episodes), desc="hidden evaluation", unit="episode", disable=not progress)
    try:
        for entry in entries:
            agent = load_agent(versions.path(entry["version"]), env)
            trajectories = []
            for ep in episodes:
                trajectories.append(play_episode(env, agent, {"episode": ep}, acting_seed(ep.seed)))
                bar.update(1)
            info = entry.get("info") or {}
            out[entry["version"]] = {
                "episodes": len(trajectories),
                "success": float(np.mean([t.success for t in trajectories])),
                "first_pick_success": float(np.mean([t.first_pick_success for t in trajectories])),
                "cost": float(np.mean([t.cost for t in trajectories])),
                "time_s": float(np.mean([t.time for t in trajectories])),
                "learned_from": info.get("serving") if isinstance(info, dict) else None,  # the gate's record
                # per episode, in the episodes' order (the same for every version): the paired tests
                "successes": [int(t.success) for t in trajectories],
                "costs": [round(float(t.cost), 4) for t in trajectories],
            }
    finally:
        bar.close()
    return out


def worse_promotions(figures: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """Each promoted version against the one it replaced: {"version", "previous", "cost",
    "previous_cost", "success", "previous_success", "worse"} (module docstring's rule)."""
    out = []
    for version, f in figures.items():
        previous = f.get("learned_from")
        if not previous or previous not in figures:
            continue
        p = figures[previous]
        worse = bool(f["cost"] > p["cost"] + 1e-9 or f["success"] < p["success"] - 1e-9)
        check = {"version": version, "previous": previous, "cost": f["cost"], "previous_cost": p["cost"],
                 "success": f["success"], "previous_success": p["success"], "worse": worse}
        if len(f.get("costs") or ()) == len(p.get("costs") or ()) > 1:
            check.update(paired_worse(f["costs"], p["costs"], f["successes"], p["successes"]))
        out.append(check)
    return out


def paired_worse(costs: Sequence[float], previous_costs: Sequence[float], successes: Sequence[int],
                 previous_successes: Sequence[int]) -> dict[str, Any]:
    """Whether a version is worse than its predecessor beyond the hidden set's own noise, on the
    same episodes: its cost higher (one-sided 95 % Student-t bound on the paired differences above
    0) or its successes fewer (exact one-sided sign test on the episodes only one of the two
    picked, p < 0.05). `cost_difference_bound`: the lower 95 % bound of the mean cost difference."""
    from scipy import stats

    d = np.asarray(costs, float) - np.asarray(previous_costs, float)
    n = len(d)
    sd = float(d.std(ddof=1))
    low = float(d.mean() - stats.t.ppf(0.95, n - 1) * sd / math.sqrt(n)) if sd > 0 else float(d.mean())
    s, ps = np.asarray(successes, int), np.asarray(previous_successes, int)
    lost, gained = int(((ps == 1) & (s == 0)).sum()), int(((ps == 0) & (s == 1)).sum())
    p_fewer = float(stats.binomtest(lost, lost + gained, 0.5, alternative="greater").pvalue) if lost + gained else 1.0
    return {"cost_difference_bound": low, "only_previous_picked": lost, "only_this_picked": gained,
            "fewer_successes_p": p_fewer, "significantly_worse": bool(low > 0 or p_fewer < 0.05)}


def hidden_summary(figures: dict[str, dict[str, Any]], served: Sequence[str]) -> dict[str, Any]:
    """The summary's hidden figures: the first and last served versions' success and cost, and
    how many promotions were worse than the version they replaced."""
    served = [v for v in served if v in figures]
    first = figures[served[0]] if served else None
    last = figures[served[-1]] if served else None
    checks = worse_promotions(figures)

    def get(f: dict[str, Any] | None, k: str) -> float | None:
        return None if f is None or not math.isfinite(f[k]) else f[k]

    return {"hidden_success_start": get(first, "success"), "hidden_success_end": get(last, "success"),
            "hidden_cost_start": get(first, "cost"), "hidden_cost_end": get(last, "cost"),
            "hidden_time_start": get(first, "time_s"), "hidden_time_end": get(last, "time_s"),
            "hidden_versions": {v: {k: x for k, x in f.items() if k not in ("successes", "costs")}
                                for v, f in figures.items()},
            "promotion_checks": checks, "worse_promotions": sum(c["worse"] for c in checks),
            "significantly_worse_promotions": sum(bool(c.get("significantly_worse")) for c in checks)}
