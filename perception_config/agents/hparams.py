"""Declared bounds of the agents' hyper-parameters, checked before an agent is built from a file.

Each agent class declares `HPARAM_BOUNDS: {name: bound}`; `check_hparams` refuses unknown names,
wrong types and values outside the bounds (ValueError naming the parameter), so a crafted
policy file cannot make the constructor allocate a network of 10^12 units. The bounds are far
above what training uses (e.g. hidden <= 4096 where 32 is the default).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

MAX_SEED = 2**63 - 1


def _check_bounds(name: str, v: float, lo: float, hi: float) -> None:
    if not lo <= v <= hi:
        raise ValueError(f"hyper-parameter {name} = {v!r} is outside its bounds [{lo}, {hi}]")


@dataclass(frozen=True)
class Int:
    lo: int
    hi: int

    def check(self, name: str, v: Any) -> None:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not float(v).is_integer():
            raise ValueError(f"hyper-parameter {name} must be an integer, got {v!r}")
        _check_bounds(name, v, self.lo, self.hi)


@dataclass(frozen=True)
class Float:
    lo: float
    hi: float

    def check(self, name: str, v: Any) -> None:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ValueError(f"hyper-parameter {name} must be a finite number, got {v!r}")
        _check_bounds(name, v, self.lo, self.hi)


@dataclass(frozen=True)
class Choice:
    options: tuple[str, ...]

    def check(self, name: str, v: Any) -> None:
        if v not in self.options:
            raise ValueError(f"hyper-parameter {name} must be one of {list(self.options)}, got {v!r}")


@dataclass(frozen=True)
class IntList:
    length: int
    item: Int

    def check(self, name: str, v: Any) -> None:
        if not isinstance(v, (list, tuple)) or len(v) != self.length:
            raise ValueError(f"hyper-parameter {name} must be a list of {self.length} integers, got {v!r}"[:300])
        for i, x in enumerate(v):
            self.item.check(f"{name}[{i}]", x)


@dataclass(frozen=True)
class StrList:
    max_len: int
    nullable: bool = False

    def check(self, name: str, v: Any) -> None:
        if v is None and self.nullable:
            return
        if not isinstance(v, (list, tuple)) or not 1 <= len(v) <= self.max_len \
                or not all(isinstance(s, str) and len(s) <= 256 for s in v):
            raise ValueError(f"hyper-parameter {name} must be a list of 1..{self.max_len} names, got {v!r}"[:300])


@dataclass(frozen=True)
class Name:
    max_len: int = 256

    def check(self, name: str, v: Any) -> None:
        if not isinstance(v, str) or not 1 <= len(v) <= self.max_len:
            raise ValueError(f"hyper-parameter {name} must be a name of 1..{self.max_len} characters, got {v!r}"[:300])


SEED = Int(0, MAX_SEED)


def check_hparams(kind: str, bounds: Mapping[str, Any], hparams: Any) -> None:
    """ValueError unless `hparams` is a mapping of declared names to values within their bounds."""
    if not isinstance(hparams, Mapping):
        raise ValueError(f"hparams of agent {kind!r} must be a JSON object, got {type(hparams).__name__}")
    unknown = sorted(str(k) for k in hparams if k not in bounds)
    if unknown:
        raise ValueError(f"unknown hyper-parameters {unknown[:10]} for agent {kind!r}; known: {sorted(bounds)}")
    for name, value in hparams.items():
        bounds[name].check(name, value)
