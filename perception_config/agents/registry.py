"""The agents by name: `AGENTS` and `make_agent`."""
from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any

from .base import Agent, EnvSpec
from .best_static import BestStaticAgent
from .evolutionary import EvolutionaryAgent
from .fixed import FixedAgent
from .oracle import OracleAgent
from .random import RandomAgent
from .simple import SimpleAgent
from .threshold import ThresholdAgent


def _policy_gradient() -> type[Agent]:
    from .policy_gradient import PolicyGradientAgent

    return PolicyGradientAgent


class _Agents(Mapping):
    """Name -> agent class; the pg agent's module (torch, seconds to import) is imported when its
    class is first looked up, so a process that never uses it (a configurator serving the fixed
    sequence) does without torch."""

    def __init__(self, classes: dict[str, type[Agent] | Any]) -> None:
        self._classes = classes

    def __getitem__(self, name: str) -> type[Agent]:
        cls = self._classes[name]
        if not isinstance(cls, type):
            cls = self._classes[name] = cls()
        return cls

    def __contains__(self, name: object) -> bool:
        return name in self._classes

    def __iter__(self) -> Iterator[str]:
        return iter(self._classes)

    def __len__(self) -> int:
        return len(self._classes)


AGENTS: Mapping[str, type[Agent]] = _Agents({
    "random": RandomAgent,
    "simple": SimpleAgent,
    "pg": _policy_gradient,
    "es": EvolutionaryAgent,
    "fixed": FixedAgent,
    "oracle": OracleAgent,
    "best_static": BestStaticAgent,
    "threshold": ThresholdAgent,
})


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
