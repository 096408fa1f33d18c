"""The agents by name: `AGENTS` and `make_agent`."""
from __future__ import annotations

from typing import Any

from .base import Agent, EnvSpec
from .evolutionary import EvolutionaryAgent
from .fixed import FixedAgent
from .oracle import OracleAgent
from .policy_gradient import PolicyGradientAgent
from .random import RandomAgent
from .simple import SimpleAgent

AGENTS: dict[str, type[Agent]] = {
    "random": RandomAgent,
    "simple": SimpleAgent,
    "pg": PolicyGradientAgent,
    "es": EvolutionaryAgent,
    "fixed": FixedAgent,
    "oracle": OracleAgent,
}


def make_agent(name: str, env_spec: EnvSpec | Any = None, *, env: Any = None, **kw: Any) -> Agent:
    """Build agent `name` for an environment: `env_spec` is an EnvSpec or an env (whose spec is
    taken); or pass `env=`. The oracle also needs the live env, which is attached when given."""
    if name not in AGENTS:
        raise ValueError(f"unknown agent {name!r}; agents: {', '.join(AGENTS)}")
    if env_spec is not None and not isinstance(env_spec, EnvSpec):
        env = env_spec if env is None else env
        env_spec = None
    if env_spec is None:
        if env is None:
            raise ValueError("make_agent needs an EnvSpec or an environment (env=...)")
        env_spec = EnvSpec.from_env(env)
    if name == "oracle" and env is not None:
        kw.setdefault("env", env)
    return AGENTS[name](env_spec, **kw)
