"""Policy and checkpoint files: safe to load (no pickle, no code), checked against the env.

Two formats, told apart by content, not by name:
- safetensors (agents with weights: pg, es; and every training checkpoint): the tensors, and
  in the header's `__metadata__` one entry "perception_config" holding the JSON metadata.
- JSON (agents without weights: random, fixed, simple): the metadata alone.

The metadata names the agent type, its hyperparameters, its JSON state (e.g. the simple
agent's memory), the action set the policy was trained for (pipeline.describe()["actions"])
and the observation layout (env.observation_layout). `load_agent(path, env)` refuses a file
whose action set or observation layout differs from the environment's, saying what differs:
a policy's output index i means "action i of the set it was trained with", nothing else.
Writes are atomic (perception_config.atomic_file). The metadata's `extra` holds what training
records: the environment settings (`env_settings`), the split, the pipeline.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic_file import atomic_write
from .base import Agent, EnvSpec
from .registry import AGENTS

FORMAT = "perception_config.policy"
VERSION = 1
META_KEY = "perception_config"


class PolicyError(ValueError):
    """A policy or checkpoint file that cannot be used here; the message names the file."""


def write_file(path: str | Path, meta: dict[str, Any], tensors: dict[str, np.ndarray] | None = None) -> Path:
    """Write metadata (+ tensors: safetensors; without tensors: JSON) atomically."""
    meta = {"format": FORMAT, "version": VERSION, **meta}
    if tensors:
        from safetensors.numpy import save

        arrays = {k: np.ascontiguousarray(v) for k, v in tensors.items()}
        data = save(arrays, metadata={META_KEY: json.dumps(meta)})
    else:
        data = (json.dumps(meta, indent=1) + "\n").encode()
    return atomic_write(path, data)


def read_file(path: str | Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """(metadata, tensors) of a policy/checkpoint file; PolicyError naming the file otherwise."""
    path = Path(path)
    if not path.is_file():
        raise PolicyError(f"policy file {path} does not exist")
    data = path.read_bytes()
    tensors: dict[str, np.ndarray] = {}
    if data.lstrip()[:1] == b"{":
        try:
            meta = json.loads(data.decode())
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise PolicyError(f"policy file {path} is corrupt: not valid JSON ({exc})") from None
    else:
        try:
            if len(data) < 8:
                raise ValueError("shorter than a safetensors header")
            n = int.from_bytes(data[:8], "little")
            if n <= 0 or 8 + n > len(data):
                raise ValueError(f"header length {n} does not fit a {len(data)}-byte file")
            header = json.loads(data[8:8 + n].decode())
            meta = json.loads(header.get("__metadata__", {}).get(META_KEY, "null"))
            from safetensors.numpy import load

            tensors = dict(load(data))
        except Exception as exc:  # safetensors raises its own error types; all mean "corrupt"
            raise PolicyError(f"policy file {path} is corrupt or not a policy: {type(exc).__name__}: {exc}") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise PolicyError(f"{path} is not a perception_config policy file (no {FORMAT!r} metadata)")
    if int(meta.get("version", 0)) > VERSION:
        raise PolicyError(f"{path} has format version {meta.get('version')}, this code reads <= {VERSION}")
    for key in ("agent", "env"):
        if key not in meta:
            raise PolicyError(f"policy file {path} is corrupt: metadata has no {key!r}")
    return meta, tensors


def _diff_lists(name: str, saved: list[Any], current: list[Any]) -> str:
    missing = [x for x in saved if x not in current]
    extra = [x for x in current if x not in saved]
    parts = [f"the policy has {name} {saved}, the environment has {current}"]
    if missing:
        parts.append(f"not in the environment: {missing}")
    if extra:
        parts.append(f"new in the environment: {extra}")
    if not missing and not extra:
        parts.append("same entries, different order")
    return "; ".join(parts)


def check_compatible(meta: dict[str, Any], spec: EnvSpec, path: str | Path = "<policy>") -> None:
    """Raise PolicyError unless the file's action set and observation layout are the env's."""
    saved = EnvSpec.from_json(meta["env"])
    problems = []
    if list(saved.action_names) != list(spec.action_names):
        problems.append("action set differs: "
                        + _diff_lists("actions", list(saved.action_names), list(spec.action_names)))
    elif saved.actions and spec.actions and list(saved.actions) != list(spec.actions):
        changed = [f"{a['name']}: {a.get('block')} {a.get('params')} -> {b.get('block')} {b.get('params')}"
                   for a, b in zip(saved.actions, spec.actions) if a != b]
        problems.append("actions have the same names but different blocks or parameters: " + "; ".join(changed))
    if list(saved.observation_layout) != list(spec.observation_layout):
        problems.append("observation layout differs: "
                        + _diff_lists("observation entries", list(saved.observation_layout),
                                      list(spec.observation_layout)))
    if problems:
        raise PolicyError(f"policy {path} does not fit this environment: " + " | ".join(problems))


def agent_meta(agent: Agent, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    return {
        "agent": agent.kind, "hparams": agent.hparams(), "state": agent.state(),
        "env": agent.spec.to_json(), "extra": extra or {},
    }


def save_agent(agent: Agent, path: str | Path, extra: dict[str, Any] | None = None) -> Path:
    """Save the agent's policy (weights + metadata) to `path`, atomically."""
    return write_file(path, agent_meta(agent, extra), agent.tensors())


def build_agent(meta: dict[str, Any], tensors: dict[str, np.ndarray], spec: EnvSpec,
                path: str | Path = "<policy>") -> Agent:
    """An agent from file contents already checked against `spec`."""
    kind = meta["agent"]
    if kind not in AGENTS:
        raise PolicyError(f"policy {path} is for agent {kind!r}; known agents: {sorted(AGENTS)}")
    try:
        agent = AGENTS[kind](spec, **meta.get("hparams", {}))
        agent.set_tensors({k: v for k, v in tensors.items() if not k.startswith(("train/", "history/"))})
        agent.set_state(meta.get("state", {}))
    except PolicyError:
        raise
    except (ValueError, KeyError, TypeError) as exc:
        raise PolicyError(f"policy {path} is corrupt: cannot rebuild the {kind!r} agent: {exc}") from None
    return agent


def load_agent(path: str | Path, env: Any, explore: bool = False) -> Agent:
    """Load a policy for `env` (a PerceptionConfigEnv or an EnvSpec); greedy unless `explore`."""
    spec = env if isinstance(env, EnvSpec) else EnvSpec.from_env(env)
    meta, tensors = read_file(path)
    check_compatible(meta, spec, path)
    agent = build_agent(meta, tensors, spec, path)
    agent.explore = explore
    if not isinstance(env, EnvSpec) and hasattr(agent, "attach"):
        agent.attach(env)  # the oracle searches the live env
    return agent


def policy_info(path: str | Path) -> dict[str, Any]:
    """The metadata of a policy file (agent, hyperparameters, env, training info)."""
    meta, _ = read_file(path)
    return meta
