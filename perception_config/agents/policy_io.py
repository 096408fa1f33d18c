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
Writes are atomic (perception_config.util.atomic_file). The metadata's `extra` holds what training
records: the environment settings (`env_settings`), the split, the pipeline.

A checksum only shows that a file is as it was written, not that what was written is sane: a
file re-checksummed after an edit passes it. So every number is range-checked too (`read_file`):
every number of the metadata finite, the training record's seeds, fractions, lambdas and counts
within `EXTRA_BOUNDS`, every tensor finite and the policy's weights within +-MAX_ABS_WEIGHT.
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..core.geometry import LAMBDA_MAX, check_noise_lambda
from ..rl.settings import MAX_OPS_LIMIT, settings_from_policy_meta
from ..util.atomic_file import atomic_write
from ..util.checksum import CHECKSUM_KEY, content_checksum
from ..util.safe_json import JsonLimitError, loads_limited, read_limited
from .base import Agent, EnvSpec
from .hparams import MAX_SEED, check_hparams
from .registry import AGENTS

FORMAT = "perception_config.policy"
VERSION = 1
META_KEY = "perception_config"
MAX_POLICY_BYTES = 256 * 1024 * 1024  # a policy/checkpoint file larger than this is refused before reading
MAX_HEADER_BYTES = 16 * 1024 * 1024  # the safetensors header (tensor table + metadata JSON)
MAX_JSON_DEPTH = 32  # nesting of the metadata JSON (what training writes nests <= 8 levels)
MAX_NAMES = 10_000  # entries of the action set / observation layout
MAX_ABS_WEIGHT = 1e6  # |policy weight| above this is refused (trained weights are of order 1 to 100)
MAX_COUNT = 2**62  # episodes, updates and other counters of the training record
# extra.<key>: (integer?, low, high) of the numbers training records (learning/training.py)
EXTRA_BOUNDS: dict[str, tuple[bool, float, float]] = {
    "split_seed": (True, 0, MAX_SEED), "seed": (True, 0, MAX_SEED), "test_fraction": (False, 0.0, 1.0),
    "validation_fraction": (False, 0.0, 1.0), "episodes": (True, 0, MAX_COUNT),
    "train_episodes_available": (True, 0, MAX_COUNT), "validation_episodes": (True, 0, MAX_COUNT),
    "validate_every": (True, 0, MAX_COUNT),
}
_DTYPES = {"F16": 2, "BF16": 2, "F32": 4, "F64": 8, "I8": 1, "I16": 2, "I32": 4, "I64": 8,
           "U8": 1, "U16": 2, "U32": 4, "U64": 8, "BOOL": 1}


class PolicyError(ValueError):
    """A policy or checkpoint file that cannot be used here; the message names the file."""


def write_file(path: str | Path, meta: dict[str, Any], tensors: dict[str, np.ndarray] | None = None) -> Path:
    """Write metadata (+ tensors: safetensors; without tensors: JSON) atomically, with the
    content checksum in the metadata."""
    meta = {"format": FORMAT, "version": VERSION, **meta}
    arrays = {k: np.ascontiguousarray(v) for k, v in (tensors or {}).items()}
    meta[CHECKSUM_KEY] = content_checksum(meta, arrays)
    if arrays:
        from safetensors.numpy import save

        data = save(arrays, metadata={META_KEY: json.dumps(meta)})
    else:
        data = (json.dumps(meta, indent=1) + "\n").encode()
    return atomic_write(path, data)


def _json(data: bytes, path: Path, what: str) -> Any:
    try:
        return loads_limited(data, f"{path} ({what})", MAX_POLICY_BYTES, MAX_JSON_DEPTH)
    except JsonLimitError as exc:
        raise PolicyError(f"policy file {exc}") from None


def _check_header(header: Any, data_len: int, path: Path) -> None:
    """The safetensors tensor table: dtypes known, shapes of non-negative ints whose byte size
    matches their offsets, inside the file. Checked before safetensors allocates anything."""
    if not isinstance(header, dict):
        raise PolicyError(f"policy file {path} is corrupt: the safetensors header is not a JSON object")
    for name, entry in header.items():
        if name == "__metadata__":
            if not isinstance(entry, dict) or not all(isinstance(v, str) for v in entry.values()):
                raise PolicyError(f"policy file {path} is corrupt: __metadata__ must map names to strings")
            continue
        ok = (isinstance(entry, dict) and entry.get("dtype") in _DTYPES and isinstance(entry.get("shape"), list)
              and all(isinstance(d, int) and not isinstance(d, bool) and 0 <= d < 2**40 for d in entry["shape"])
              and isinstance(entry.get("data_offsets"), list) and len(entry["data_offsets"]) == 2
              and all(isinstance(o, int) and not isinstance(o, bool) for o in entry["data_offsets"]))
        if not ok:
            raise PolicyError(f"policy file {path} is corrupt: tensor {str(name)[:80]!r} has a malformed entry")
        lo, hi = entry["data_offsets"]
        if not 0 <= lo <= hi <= data_len or int(np.prod(entry["shape"], dtype=object)) * _DTYPES[entry["dtype"]] \
                != hi - lo:
            raise PolicyError(f"policy file {path} is corrupt: tensor {str(name)[:80]!r} with shape {entry['shape']} "
                              f"does not fit its {hi - lo}-byte data or the file")


def _names(value: Any) -> bool:
    return isinstance(value, list) and len(value) <= MAX_NAMES and all(isinstance(x, str) for x in value)


def check_meta_schema(meta: Any, path: Path) -> None:
    """The metadata's types: format/version, agent (a name), env (action set, observation layout,
    max_ops), hparams/state/extra (JSON objects). PolicyError naming the file and the field."""
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise PolicyError(f"{path} is not a perception_config policy file (no {FORMAT!r} metadata)")
    version = meta.get("version", 0)
    if isinstance(version, bool) or not isinstance(version, int):
        raise PolicyError(f"policy file {path} is corrupt: version must be an integer, got {version!r}"[:300])
    if version > VERSION:
        raise PolicyError(f"{path} has format version {version}, this code reads <= {VERSION}")
    for key in ("agent", "env"):
        if key not in meta:
            raise PolicyError(f"policy file {path} is corrupt: metadata has no {key!r}")
    if not isinstance(meta["agent"], str):
        raise PolicyError(f"policy file {path} is corrupt: 'agent' must be a name, got {type(meta['agent']).__name__}")
    for key in ("hparams", "state", "extra", "train_state", "trainer"):
        if key in meta and not isinstance(meta[key], dict):
            raise PolicyError(f"policy file {path} is corrupt: {key!r} must be a JSON object, "
                              f"got {type(meta[key]).__name__}")
    if CHECKSUM_KEY in meta and not isinstance(meta[CHECKSUM_KEY], str):
        raise PolicyError(f"policy file {path} is corrupt: {CHECKSUM_KEY!r} must be a hex string")
    env = meta["env"]
    if not isinstance(env, dict):
        raise PolicyError(f"policy file {path} is corrupt: 'env' must be a JSON object, got {type(env).__name__}")
    for key in ("action_names", "action_kinds", "observation_layout"):
        if not _names(env.get(key)):
            raise PolicyError(f"policy file {path} is corrupt: env.{key} must be a list of at most "
                              f"{MAX_NAMES} strings")
    if len(env["action_kinds"]) != len(env["action_names"]):
        raise PolicyError(f"policy file {path} is corrupt: env.action_kinds and env.action_names differ in length")
    m = env.get("max_ops")
    if isinstance(m, bool) or not isinstance(m, int) or not 1 <= m <= MAX_OPS_LIMIT:
        raise PolicyError(f"policy file {path} is corrupt: env.max_ops must be an integer in [1, {MAX_OPS_LIMIT}], "
                          f"got {m!r}"[:300])
    actions = env.get("actions", [])
    if not isinstance(actions, list) or not all(isinstance(a, dict) for a in actions):
        raise PolicyError(f"policy file {path} is corrupt: env.actions must be a list of JSON objects")


def _walk_numbers(node: Any, where: str) -> Iterator[tuple[str, int | float]]:
    """(field, value) of every number in a JSON value, depth first (its depth is bounded by
    MAX_JSON_DEPTH); booleans are not numbers."""
    stack = [(where, node)]
    while stack:
        field, value = stack.pop()
        if isinstance(value, dict):
            stack.extend((f"{field}.{k}" if field else str(k), v) for k, v in value.items())
        elif isinstance(value, list):
            stack.extend((f"{field}[{i}]", v) for i, v in enumerate(value))
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            yield field, value


def _finite(value: int | float) -> bool:
    return isinstance(value, int) or math.isfinite(value)  # an int of any size is finite


def _in_range(path: Path, field: str, value: Any, integer: bool, lo: float, hi: float) -> None:
    ok = not isinstance(value, bool) and isinstance(value, (int, float)) and _finite(value) \
        and (not integer or isinstance(value, int) or value.is_integer()) and lo <= value <= hi
    if not ok:
        kind = "an integer" if integer else "a number"
        raise PolicyError(f"policy file {path} is corrupt: {field} must be {kind} in [{lo:g}, {hi:g}], "
                          f"got {value!r}"[:300])


def check_meta_ranges(meta: dict[str, Any], path: Path) -> None:
    """Every number of the metadata finite (JSON's NaN/Infinity refused); the training record's
    numbers (EXTRA_BOUNDS, the lambdas, the selected and checkpointed episode counts) in range.
    PolicyError naming the file, the field and the value."""
    for field, value in _walk_numbers(meta, ""):
        if not _finite(value):
            raise PolicyError(f"policy file {path} is corrupt: {field} = {value!r} is not a finite number")
    extra = meta.get("extra") or {}
    for key, (integer, lo, hi) in EXTRA_BOUNDS.items():
        if extra.get(key) is not None:
            _in_range(path, f"extra.{key}", extra[key], integer, lo, hi)
    for key in ("validation_lambdas", "lambda_range"):
        values = extra.get(key)
        if values is None:
            continue
        if not isinstance(values, list) or len(values) > MAX_NAMES:
            raise PolicyError(f"policy file {path} is corrupt: extra.{key} must be a list of noise levels, "
                              f"got {values!r}"[:300])
        for i, lam in enumerate(values):
            if isinstance(lam, bool):
                lam = None  # a boolean is no noise level
            try:
                check_noise_lambda(lam, f"extra.{key}[{i}]")
            except ValueError as exc:
                raise PolicyError(f"policy file {path} is corrupt: {exc} (noise levels are in [0, {LAMBDA_MAX:g}])") \
                    from None
    selected = extra.get("selected")
    if isinstance(selected, dict) and "episode" in selected:
        _in_range(path, "extra.selected.episode", selected["episode"], True, 0, MAX_COUNT)
    trainer = meta.get("trainer") or {}
    if "episodes_done" in trainer:
        _in_range(path, "trainer.episodes_done", trainer["episodes_done"], True, 0, MAX_COUNT)


def check_tensor_ranges(tensors: dict[str, np.ndarray], path: Path) -> None:
    """Every tensor finite except the training history (it holds NaN for figures not reported);
    the policy's weights (all but "train/" and "history/" tensors) within +-MAX_ABS_WEIGHT."""
    for name, t in tensors.items():
        if name.startswith("history/") or t.dtype.kind != "f":
            continue
        if not np.isfinite(t).all():
            raise PolicyError(f"policy file {path} is corrupt: tensor {name!r} holds NaN or infinite values")
        if not name.startswith("train/") and t.size:
            worst = float(np.abs(t).max())
            if worst > MAX_ABS_WEIGHT:
                raise PolicyError(f"policy file {path} is corrupt: tensor {name!r} holds {worst:g}, outside "
                                  f"[-{MAX_ABS_WEIGHT:g}, {MAX_ABS_WEIGHT:g}] (trained weights are of order 1)")


def read_file(path: str | Path) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """(metadata, tensors) of a policy/checkpoint file, validated; PolicyError naming the file.

    Checked in this order, so nothing large is allocated for a hostile file: a regular file of
    at most MAX_POLICY_BYTES; the JSON (metadata, safetensors header) at most MAX_JSON_DEPTH
    levels deep; the tensor table (dtypes, shapes against offsets and file size); the metadata
    schema (check_meta_schema) and the environment settings it records (rl/settings.py bounds);
    the metadata's numbers (check_meta_ranges); the content checksum; the tensors' values
    (check_tensor_ranges).
    Files written before the checksum existed have none: they are accepted with the other checks.
    """
    path = Path(path)
    try:
        data = read_limited(path, MAX_POLICY_BYTES, "policy file")
    except FileNotFoundError:
        raise PolicyError(f"policy file {path} does not exist") from None
    except JsonLimitError as exc:
        raise PolicyError(f"policy file {exc}") from None
    except OSError as exc:
        raise PolicyError(f"policy file {path} cannot be read: {exc.strerror or exc}") from None
    tensors: dict[str, np.ndarray] = {}
    if data.lstrip()[:1] == b"{":
        meta = _json(data, path, "JSON")
    else:
        if len(data) < 8:
            raise PolicyError(f"policy file {path} is corrupt or not a policy: shorter than a safetensors header")
        n = int.from_bytes(data[:8], "little")
        if n <= 0 or n > MAX_HEADER_BYTES or 8 + n > len(data):
            raise PolicyError(f"policy file {path} is corrupt or not a policy: header length {n} does not fit a "
                              f"{len(data)}-byte file (limit {MAX_HEADER_BYTES})")
        header = _json(data[8:8 + n], path, "safetensors header")
        _check_header(header, len(data) - 8 - n, path)
        raw_meta = header.get("__metadata__", {}).get(META_KEY)
        if raw_meta is None:
            raise PolicyError(f"{path} is not a perception_config policy file (no {FORMAT!r} metadata)")
        meta = _json(raw_meta.encode(), path, "metadata")
        check_meta_schema(meta, path)
        try:
            from safetensors.numpy import load

            tensors = dict(load(data))
        except Exception as exc:  # safetensors raises its own error types; all mean "corrupt"
            raise PolicyError(f"policy file {path} is corrupt or not a policy: {type(exc).__name__}: {exc}") from None
    check_meta_schema(meta, path)
    try:
        settings_from_policy_meta(meta, f"policy file {path}")
    except ValueError as exc:
        raise PolicyError(str(exc)) from None
    check_meta_ranges(meta, path)
    if CHECKSUM_KEY in meta and content_checksum(meta, tensors) != meta[CHECKSUM_KEY]:
        raise PolicyError(f"policy file {path} is corrupt: its content does not match its {CHECKSUM_KEY} checksum "
                          "(modified or damaged after it was written)")
    check_tensor_ranges(tensors, path)
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


def _with_defaults(action: Any) -> Any:
    """A saved action description with the parameters its block has gained since at their
    defaults: a policy trained before a block grew an option ran with what its default is."""
    from ..blocks.base import REGISTRY, load_all

    if not isinstance(action, dict) or not isinstance(action.get("params"), dict):
        return action
    if action.get("block") not in REGISTRY:
        load_all()
    cls = REGISTRY.get(action.get("block"))
    if cls is None:
        return action
    return {**action, "params": {**{p.name: p.default for p in cls.params}, **action["params"]}}


def check_compatible(meta: dict[str, Any], spec: EnvSpec, path: str | Path = "<policy>") -> None:
    """Raise PolicyError unless the file's action set and observation layout are the env's."""
    try:
        saved = EnvSpec.from_json(meta["env"])
    except (KeyError, TypeError, ValueError) as exc:
        raise PolicyError(f"policy {path} is corrupt: its env description is malformed ({exc})") from None
    problems = []
    if list(saved.action_names) != list(spec.action_names):
        problems.append("action set differs: "
                        + _diff_lists("actions", list(saved.action_names), list(spec.action_names)))
    elif saved.actions and spec.actions and [_with_defaults(a) for a in saved.actions] != list(spec.actions):
        changed = [f"{a['name']}: {a.get('block')} {a.get('params')} -> {b.get('block')} {b.get('params')}"
                   for a, b in zip(saved.actions, spec.actions) if _with_defaults(a) != b]
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
    """An agent from file contents already checked against `spec`. Before anything is built:
    the hyper-parameters within the agent's HPARAM_BOUNDS, the policy tensors exactly those
    (names and shapes) the hyper-parameters and the environment imply."""
    kind = meta["agent"]
    if kind not in AGENTS:
        raise PolicyError(f"policy {path} is for agent {kind!r}"[:200] + f"; known agents: {sorted(AGENTS)}")
    cls = AGENTS[kind]
    hparams = meta.get("hparams", {})
    policy_tensors = {k: v for k, v in tensors.items() if not k.startswith(("train/", "history/", "validation/"))}
    try:
        check_hparams(kind, cls.HPARAM_BOUNDS, hparams)
    except ValueError as exc:
        raise PolicyError(f"policy {path}: {exc}") from None
    want = cls.expected_tensors(spec, hparams)
    got = {k: tuple(v.shape) for k, v in policy_tensors.items()}
    if got != want:
        raise PolicyError(f"policy {path} is corrupt: its tensors {got} are not the {want} that its "
                          f"{kind!r} hyper-parameters and the environment imply"[:1000])
    bad = [k for k, v in policy_tensors.items() if v.dtype.kind != "f"]
    if bad:
        raise PolicyError(f"policy {path} is corrupt: tensors {bad} are not floating point")
    try:
        agent = cls(spec, **hparams)
        agent.set_tensors(policy_tensors)
        agent.set_state(meta.get("state", {}))
    except PolicyError:
        raise
    except (ValueError, KeyError, TypeError, IndexError, OverflowError) as exc:
        raise PolicyError(f"policy {path} is corrupt: cannot rebuild the {kind!r} agent: {exc}"[:1000]) from None
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
