"""The environment's settings in one object: saved with every policy, restored when it is loaded.

`EnvSettings` holds everything that changes what an episode costs or how long it may run:
max_ops (also part of the observation: step / max_ops), the failed-pick and truncation charges,
the time mode and its cost table, the visibility threshold of the episodes and the training
lambda range. Training writes `settings.to_json()` into the policy's metadata; evaluation, the
configurator and replay-check start from `policy_settings(...)` and say when they run a policy
under other settings (`describe_differences`).

Cost-table mode charges an action the first of these the table holds: `action:<name>@<obj_id>`
(this action on this object), `action:<name>`, `<block name>`; else the block's own
`default_cost`. The scoring pass after every action costs `scoring@<obj_id>`, else `scoring`, else
the sum of the scoring blocks' costs. A calibrated table (`perception-config calibrate`,
learning/calibration.py) holds the medians measured on this machine per action and object; the
blocks' `default_cost` are round figures of the same order, for runs without one.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping

from ..core.geometry import check_noise_lambda

TIME_MODES = ("measured", "cost_table")
SCORING_PASS = "scoring"  # the cost-table key of the whole scoring pass (overrides the sum)
CALIBRATION_EPISODES = 24  # train episodes a calibration times every action on
ACTION_KEY = "action:"  # cost-table keys of single actions: action:<name> and action:<name>@<obj_id>
GENERATE = "generate"  # the action name of an episode's first generator call (action:generate)
MAX_OPS_LIMIT = 1000  # max_ops above this is refused (a policy file could otherwise ask for 10^7 operations)
MAX_SECONDS = 3600.0  # s: a cost (failed pick, truncation, cost-table entry) above this is refused
MAX_COST_TABLE_ENTRIES = 1000


@dataclass(frozen=True)
class EnvSettings:
    """Settings of PerceptionConfigEnv (units: seconds, shares). Validated when built: max_ops in
    [1, MAX_OPS_LIMIT], every cost in [0, MAX_SECONDS] s, at most MAX_COST_TABLE_ENTRIES cost-table entries."""

    max_ops: int = 10  # operations before an episode is truncated
    failed_pick_cost: float = 2.0  # s, the robot's attempt added to a failed pick
    truncation_cost: float = 10.0  # s-equivalent penalty of giving up (reward only, not time)
    time_mode: str = "cost_table"  # "cost_table" (reproducible, load-independent) or "measured" wall time
    cost_table: Mapping[str, float] = field(default_factory=dict)  # s per action / block (module docstring)
    min_visib_fract: float = 0.3  # episodes: objects at least this visible
    lambda_range: tuple[float, float] = (0.1, 1.0)  # lambda ~ U(range) when a reset names none
    loop_mask: bool = True  # mask actions already taken at the current hypothesis (rl/pose_memory.py)
    final_pick: bool = True  # the last of max_ops operations is a pick (rl/env.py: the final-pick rule)
    final_pick_best: bool = False  # that last pick at the best hypothesis reached by pick_success (rl/env.py)
    converge_tol: float = 0.0  # loop rule: mask an action whose latest call moved no point > this x diameter

    def __post_init__(self) -> None:
        m = self.max_ops
        if isinstance(m, bool) or not isinstance(m, (int, float)) or not float(m).is_integer() \
                or not 1 <= m <= MAX_OPS_LIMIT:
            raise ValueError(f"max_ops must be an integer in [1, {MAX_OPS_LIMIT}], got {m!r}")
        object.__setattr__(self, "max_ops", int(m))
        for name in ("failed_pick_cost", "truncation_cost"):
            object.__setattr__(self, name, _seconds(getattr(self, name), name))
        if self.time_mode not in TIME_MODES:
            raise ValueError(f"time_mode must be one of {list(TIME_MODES)}, got {self.time_mode!r}")
        if not isinstance(self.cost_table, Mapping):
            raise ValueError(f"cost_table must be a mapping of block name to seconds, got {self.cost_table!r}")
        if len(self.cost_table) > MAX_COST_TABLE_ENTRIES:
            raise ValueError(f"cost_table has {len(self.cost_table)} entries, more than {MAX_COST_TABLE_ENTRIES}")
        table = {str(k): _seconds(v, f"cost_table[{k!r}]") for k, v in self.cost_table.items()}
        object.__setattr__(self, "cost_table", table)
        visib = float(self.min_visib_fract)
        if not (math.isfinite(visib) and 0.0 <= visib <= 1.0):
            raise ValueError(f"min_visib_fract must be in [0, 1], got {self.min_visib_fract!r}")
        object.__setattr__(self, "min_visib_fract", visib)
        tol = float(self.converge_tol)
        if not (math.isfinite(tol) and 0.0 <= tol <= 1.0):
            raise ValueError(f"converge_tol must be in [0, 1], got {self.converge_tol!r}")
        object.__setattr__(self, "converge_tol", tol)
        try:
            lo, hi = self.lambda_range
        except (TypeError, ValueError):
            raise ValueError(f"lambda_range must be (low, high), got {self.lambda_range!r}") from None
        lo, hi = check_noise_lambda(lo, "lambda_range low"), check_noise_lambda(hi, "lambda_range high")
        if lo > hi:
            raise ValueError(f"lambda_range must satisfy low <= high, got {self.lambda_range!r}")
        object.__setattr__(self, "lambda_range", (lo, hi))
        for name in ("loop_mask", "final_pick", "final_pick_best"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be true or false, got {getattr(self, name)!r}")

    # -- building and comparing -------------------------------------------------------------
    def replace(self, **changes: Any) -> "EnvSettings":
        """A copy with some fields changed (None values are ignored: 'not given')."""
        known = {f.name for f in dataclasses.fields(self)}
        unknown = sorted(set(changes) - known)
        if unknown:
            raise ValueError(f"unknown environment settings {unknown}; known: {sorted(known)}")
        return dataclasses.replace(self, **{k: v for k, v in changes.items() if v is not None})

    def to_json(self) -> dict[str, Any]:
        return {
            "max_ops": self.max_ops, "failed_pick_cost": self.failed_pick_cost,
            "truncation_cost": self.truncation_cost, "time_mode": self.time_mode,
            "cost_table": dict(self.cost_table), "min_visib_fract": self.min_visib_fract,
            "lambda_range": list(self.lambda_range), "loop_mask": self.loop_mask,
            "final_pick": self.final_pick, "final_pick_best": self.final_pick_best,
            "converge_tol": self.converge_tol,
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any], source: str = "settings") -> "EnvSettings":
        """Settings from `to_json` output (or a policy's older `env_kwargs`); unknown keys and bad
        values are errors naming `source`."""
        if not isinstance(data, Mapping):
            raise ValueError(f"{source}: environment settings must be a mapping, got {type(data).__name__}")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"{source}: unknown environment settings {unknown}; known: {sorted(known)}")
        values = {k: v for k, v in data.items() if v is not None}
        if "lambda_range" in values:
            values["lambda_range"] = tuple(values["lambda_range"])
        try:
            return cls(**values)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{source}: {exc}") from None

    def differences(self, other: "EnvSettings", ignore: Iterable[str] = ("lambda_range",)) -> list[str]:
        """'name: self -> other' for every field that differs (lambda_range ignored by default:
        evaluation and the configurator set lambda per episode)."""
        out = []
        for f in dataclasses.fields(self):
            a, b = getattr(self, f.name), getattr(other, f.name)
            if f.name not in ignore and a != b:
                out.append(f"{f.name}: {a!r} -> {b!r}")
        return out

    # -- cost-table mode --------------------------------------------------------------------
    def block_cost(self, block: Any, action: str | None = None, obj_id: int | None = None) -> float:
        """Seconds charged for one call of `block` (as the action named `action`, on object
        `obj_id`) in cost-table mode (module docstring: which entry wins)."""
        table = self.cost_table
        if action is not None:
            for key in ((f"{ACTION_KEY}{action}@{obj_id}",) if obj_id is not None else ()) + (f"{ACTION_KEY}{action}",):
                if key in table:
                    return float(table[key])
        return float(table.get(block.name, block.default_cost))

    def scoring_cost(self, scoring: Iterable[Any], obj_id: int | None = None) -> float:
        """Seconds charged for the scoring pass over `scoring` blocks (on object `obj_id`) in
        cost-table mode."""
        if obj_id is not None and f"{SCORING_PASS}@{obj_id}" in self.cost_table:
            return float(self.cost_table[f"{SCORING_PASS}@{obj_id}"])
        if SCORING_PASS in self.cost_table:
            return float(self.cost_table[SCORING_PASS])
        total = 0.0
        for block in scoring:
            total += self.block_cost(block)
        return total


def _seconds(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or not 0 <= value <= MAX_SECONDS:
        raise ValueError(f"{name} must be a number of seconds in [0, {MAX_SECONDS:g}], got {value!r}")
    return float(value)


def settings_from_policy_meta(meta: Mapping[str, Any], source: str = "policy") -> EnvSettings | None:
    """The settings a policy was trained under, from its metadata; None when it records none.
    Reads `extra.env_settings` and, for policies written before it existed, `extra.env_kwargs`
    with `extra.lambda_range`."""
    extra = meta.get("extra") or {}
    if not isinstance(extra, Mapping):
        raise ValueError(f"{source}: metadata 'extra' must be a mapping")
    if "env_settings" in extra:
        return EnvSettings.from_json(extra["env_settings"], f"{source} (env_settings)")
    kwargs = extra.get("env_kwargs")
    if not kwargs:
        return None
    data = dict(kwargs)
    if extra.get("lambda_range") is not None:
        data.setdefault("lambda_range", extra["lambda_range"])
    return EnvSettings.from_json(data, f"{source} (env_kwargs)")
