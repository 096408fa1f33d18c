"""The agents of an evaluation (learning/evaluation.py): the policies and agent names given, then
the baselines: the hindsight oracle, the engineer pipelines the pipeline's actions allow
(`fixed_sequences`), the best static pipeline and the best threshold rule (searched on the train
images: learning/evaluation_best_static.py) and the untrained random agent."""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

from ..agents.policy_settings import is_policy_file
from ..blocks.pipeline import Pipeline
from ..rl.env import PerceptionConfigEnv
from ..store.episode_store import policy_version

# Engineer pipelines evaluated as baselines; those naming actions the pipeline lacks are skipped.
DEFAULT_FIXED_SEQUENCES: tuple[tuple[str, ...], ...] = (
    ("icp_coarse", "icp_fine", "pick"),
    ("icp_coarse", "pick"),
    ("d2co", "icp_fine", "pick"),
    # The cell pipeline's ground-truth-free engineer sequences: refine, pick, and on a failed
    # pick the next ranked candidate (or another generator: ppf, global registration) and again.
    ("icp_coarse", "icp_fine", "pick", "next_candidate"),
    ("icp_fine", "pick", "next_candidate"),
    ("icp_coarse", "icp_fine", "pick", "ppf"),
    ("icp_coarse", "icp_fine", "pick", "global_registration"),
)


SEARCHED = ("best_static", "best_static_single", "best_threshold")  # baselines searched on the train images


@dataclass
class EvalAgent:
    """An agent under evaluation: its report name, its kind (random, fixed, oracle, pg, ...)."""

    name: str
    kind: str
    agent: Any  # an agents.Agent, or any object with act(obs, info) (begin_episode/observe optional)
    version: str | None = None  # a policy file's version (episode_store.policy_version); None for the others


def fixed_sequences(pipeline: Pipeline,
                    sequences: Iterable[Sequence[str]] = DEFAULT_FIXED_SEQUENCES) -> list[tuple[str, ...]]:
    """The engineer sequences whose actions all exist in the pipeline."""
    names = set(pipeline.action_names)
    return [tuple(s) for s in sequences if set(s) <= names]


def _policy_name(path: Path, kind: str) -> str:
    """A report name for a policy file: kind:<file stem>, or kind:<folder> for training's
    policy.* files (one run per folder)."""
    label = path.parent.name if path.stem == "policy" and path.parent.name else path.stem
    return kind if label == kind else f"{kind}:{label}"


def build_agents(
    env: PerceptionConfigEnv, policies: Sequence[Any], seed: int, include_baselines: bool = True,
    sequences: Iterable[Sequence[str]] = DEFAULT_FIXED_SEQUENCES, oracle_budget: int | None = None,
    best_static: Any = None, best_static_single: Any = None, best_threshold: Any = None,
) -> list[EvalAgent]:
    """The agents to evaluate: policy files (checked against the env's action set), agent
    names, or (name, agent) pairs / objects with `act`; then the baselines (oracle, the fixed
    pipelines, the best static pipeline, random) unless already given; `oracle_budget`: the
    oracle's operator calls per episode (its `node_budget`; default 2000). `best_static`: the
    searched BestStaticAgent (the name "best_static" among `policies` is this agent; None: no
    best_static baseline); `best_static_single`: its one sequence for every lambda (likewise);
    `best_threshold`: the searched threshold rule (likewise)."""
    from .. import agents

    out: list[EvalAgent] = []
    for spec in policies:
        if isinstance(spec, tuple) and len(spec) == 2 and hasattr(spec[1], "act"):
            out.append(EvalAgent(str(spec[0]), "custom", spec[1]))
        elif hasattr(spec, "act"):
            out.append(EvalAgent(str(getattr(spec, "name", type(spec).__name__)), "custom", spec))
        elif is_policy_file(spec):
            agent = agents.load_agent(Path(spec), env)
            out.append(EvalAgent(_policy_name(Path(spec), agent.kind), agent.kind, agent, policy_version(spec)))
        elif spec in SEARCHED:
            searched = {"best_static": best_static, "best_static_single": best_static_single,
                        "best_threshold": best_threshold}[spec]
            if searched is None:
                raise ValueError(f"agent {spec!r} is the result of a search on the train images: "
                                 "give best_static_episodes > 0 (CLI: --best-static-episodes N)")
            out.append(EvalAgent(spec, spec, searched))
        elif isinstance(spec, str):
            if spec not in agents.AGENTS:
                hint = f" and there is no file {spec}" if (os.sep in spec or "." in spec) else ""
                raise ValueError(f"unknown agent {spec!r}{hint}; known agents: {', '.join(sorted(agents.AGENTS))}")
            out.append(EvalAgent(spec, spec, agents.make_agent(spec, env=env, seed=seed)))
        else:
            raise ValueError(f"cannot evaluate {spec!r}: give a policy file, an agent name or an agent")
    names = [a.name for a in out]
    if len(set(names)) != len(names):
        raise ValueError(f"two agents under evaluation have the same name: {names}")
    if include_baselines:
        if "oracle" not in names:
            budget = {} if oracle_budget is None else {"node_budget": int(oracle_budget)}
            out.append(EvalAgent("oracle", "oracle", agents.make_agent("oracle", env=env, seed=seed, **budget)))
        for seq in fixed_sequences(env.pipeline, sequences):
            name = "fixed:" + "+".join(seq)
            if name not in names:
                out.append(EvalAgent(name, "fixed", agents.make_agent("fixed", env=env, seed=seed, sequence=list(seq))))
        for name, searched in (("best_static", best_static), ("best_static_single", best_static_single),
                               ("best_threshold", best_threshold)):
            if searched is not None and name not in names:
                out.append(EvalAgent(name, name, searched))
        if "random" not in names:
            out.append(EvalAgent("random", "random", agents.make_agent("random", env=env, seed=seed)))
    if not out:
        raise ValueError("nothing to evaluate: no policies given and include_baselines is off")
    return out
