"""What running a policy needs from its training: the split, the pipeline, the env settings.

A policy file records (metadata `extra`, written by learning/training.py) the split seed and test
fraction of its train/test split, its pipeline YAML and its `EnvSettings`. Evaluation, the
configurator and replay-check start from these (`policy_settings`):
- split_seed, test_fraction, pipeline: an explicit value must agree with the files (evaluating
  on the training images, or with another action set, would be meaningless);
- max_ops is part of the observation (step / max_ops): an explicit value must agree too;
- the other env settings (time mode, costs, visibility threshold) may be changed; every change
  against what a policy was trained with is listed in `notes`, for the caller to say so.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from ..rl.episodes import DEFAULT_SPLIT_SEED, DEFAULT_TEST_FRACTION
from ..rl.settings import EnvSettings, settings_from_policy_meta
from .policy_io import policy_info


@dataclass
class PolicySettings:
    split_seed: int
    test_fraction: float
    pipeline: Any  # a YAML path, a Pipeline object, or None (the shipped default)
    env: EnvSettings
    notes: list[str] = field(default_factory=list)  # settings that differ from a policy's training


def is_policy_file(spec: Any) -> bool:
    """A path to an existing file (not an agent name such as "random")."""
    return isinstance(spec, (str, os.PathLike)) and (Path(spec).suffix != "" or os.sep in str(spec)) \
        and Path(spec).is_file()


def _same(key: str, a: Any, b: Any) -> bool:
    if key == "pipeline":
        return Path(a).resolve() == Path(b).resolve()
    if key == "test_fraction":
        return math.isclose(float(a), float(b))
    return int(a) == int(b)


def _same_folder(a: Any, b: Any) -> bool:
    try:
        folder = b.root if hasattr(b, "image_keys") else b  # a BopDataset or a path (Path.root is "/")
        return Path(a).resolve() == Path(folder).resolve()
    except (TypeError, OSError):
        return False


def policy_settings(
    policies: Sequence[Any] = (), *, split_seed: int | None = None, test_fraction: float | None = None,
    pipeline: Any = None, dataset: Any = None, **env_overrides: Any,
) -> PolicySettings:
    """The settings to run `policies` (files; agent names and objects are skipped) with.

    Explicit values (not None) win, but split_seed, test_fraction, pipeline and max_ops must
    agree with what the files record (ValueError naming the file otherwise); the files must
    agree with each other on them. `dataset`: the folder the policies will play; a policy trained
    on another dataset (simulated images of the real frames' meshes, say) has no train images
    there, so its split is neither checked nor taken. `env_overrides`: EnvSettings fields
    (max_ops, time_mode, ...).
    """
    given = {"split_seed": split_seed, "test_fraction": test_fraction, "pipeline": pipeline,
             "max_ops": env_overrides.get("max_ops")}
    out = dict(given)
    source = {k: "the arguments" for k, v in given.items() if v is not None}
    trained: list[tuple[str, EnvSettings]] = []
    for spec in policies:
        if not is_policy_file(spec):
            continue
        meta = policy_info(Path(spec))
        extra = meta.get("extra") or {}
        recorded_env = settings_from_policy_meta(meta, f"policy {spec}")
        if recorded_env is not None:
            trained.append((str(spec), recorded_env))
        recorded = {"split_seed": extra.get("split_seed"), "test_fraction": extra.get("test_fraction"),
                    "pipeline": extra.get("pipeline"), "max_ops": recorded_env.max_ops if recorded_env else None}
        if dataset is not None and extra.get("dataset") and not _same_folder(extra["dataset"], dataset):
            recorded.update(split_seed=None, test_fraction=None)  # trained elsewhere: no image of here was seen
        for key, value in recorded.items():
            if value is None:
                continue
            if key == "pipeline" and out[key] is not None and not isinstance(out[key], (str, os.PathLike)):
                continue  # a Pipeline object: the policy loader checks its action set
            if out[key] is None:
                out[key], source[key] = value, f"policy {spec}"
            elif not _same(key, out[key], value):
                raise ValueError(
                    f"policy {spec} was trained with {key}={value!r} but {source[key]} give {key}={out[key]!r}: "
                    + ("evaluating on its training images would be meaningless"
                       if key in ("split_seed", "test_fraction")
                       else "run each policy with the settings it was trained with"))
    base = trained[0][1] if trained else EnvSettings()
    env = base.replace(**{**env_overrides, "max_ops": out["max_ops"]})
    notes = [f"policy {path} was trained with other settings ({'; '.join(diff)})"
             for path, settings in trained if (diff := settings.differences(env))]
    return PolicySettings(
        split_seed=DEFAULT_SPLIT_SEED if out["split_seed"] is None else int(out["split_seed"]),
        test_fraction=DEFAULT_TEST_FRACTION if out["test_fraction"] is None else float(out["test_fraction"]),
        pipeline=out["pipeline"], env=env, notes=notes,
    )
