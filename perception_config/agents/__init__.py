"""Configuration agents: they choose the next operator from the scores until the robot can pick.

`AGENTS` maps a name to its class; `make_agent(name, env_spec, **kw)` builds one (registry.py).
The spec is an `EnvSpec` (or an environment, from which it is taken). Policies are saved with
`save_agent(agent, path)` and loaded with `load_agent(path, env)` (policy_io.py: safetensors /
JSON, checked against the environment's action set and observation layout, never unpickled).
Episodes are played by perception_config.rl.episode_loop.play_episode.
"""
from __future__ import annotations

from .base import Agent, EnvRecipe, EnvSpec
from .oracle import OracleResult, oracle_search
from .policy_io import PolicyError, load_agent, policy_info, save_agent
from .registry import AGENTS, make_agent

__all__ = [
    "AGENTS", "Agent", "EnvRecipe", "EnvSpec", "OracleResult", "PolicyError",
    "load_agent", "make_agent", "oracle_search", "policy_info", "save_agent",
]
