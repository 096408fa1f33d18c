"""The cost model: what each action and the scoring pass cost on this machine, measured once.

Training on measured wall time teaches an agent the machine's load: the same action costs 20 ms
on an idle core and 60 ms beside another job, and the reward of one episode is never the same
twice (Gymnasium's check_env refuses it). The environment's cost-table mode charges fixed
seconds instead (rl/settings.py); `calibrate` measures them.

Measurement: on `episodes` episodes of the given images (an object of a frame, lambda drawn from
`lambdas`, seeded), the environment in cost-table mode (the blocks without their wall-clock
bounds, as training runs them) is reset, and from the first hypothesis, and again from the one
after a random refinement, every action is applied once (`env.snapshot()` / `env.restore()`
between them) and timed: the block's own seconds (`BlockResult.elapsed`) and the scoring pass
after it. The first call on each frame fills the frame's caches (point clouds, edge maps) and is
discarded, as training meets a frame many times.

The model (measured on the synthetic default: an ICP costs 6 ms on the smallest part and 27 ms on
the largest, the scoring pass 9-19 ms, so seconds depend on the object, not on the action alone):
per action and object the median of its calls (`action:<name>@<obj_id>`), per action the median
over all objects (`action:<name>`, for objects without enough calls, e.g. a part the cell sees
first), the scoring pass per object and overall (`scoring@<obj_id>`, `scoring`), and the first
generator call (`action:generate`). Values are rounded to 0.1 ms (at least 0.1 ms). A pick
action costs what the simulated pick measures: the robot's time of a successful pick is common to
every agent, a failed pick adds `failed_pick_cost` as in every time mode.
"""
from __future__ import annotations

import json
import os
import platform
import time
from collections import defaultdict
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from ..blocks.base import Kind
from ..blocks.pipeline import Pipeline, load_pipeline
from ..datasets.bop import BopDataset
from ..rl.env import PerceptionConfigEnv
from ..rl.episodes import EpisodeSource
from ..rl.settings import ACTION_KEY, CALIBRATION_EPISODES, GENERATE, SCORING_PASS, EnvSettings
from ..util.atomic_file import atomic_write
from ..util.open3d_threads import open3d_single_thread
from ..util.safe_json import read_json_file

MIN_CALLS_PER_OBJECT = 3  # fewer calls of an action on an object: only the pooled median is kept
RESOLUTION = 1e-4  # s: the model's unit (0.1 ms: 4 decimals), also its smallest value
FORMAT = "perception_config.cost_model/1"
MAX_COST_MODEL_BYTES = 64 * 1024 * 1024  # a cost model file larger than this is refused before reading
MAX_JSON_DEPTH = 32  # a calibrate output nests about 6 levels (its pipeline description)


def _seconds(values: Sequence[float]) -> float:
    return max(RESOLUTION, round(float(np.median(values)), 4))


def calibrate(
    dataset: str | Path | BopDataset, pipeline: str | Path | Pipeline | None = None,
    image_keys: Sequence[tuple[int, int]] | None = None, episodes: int = CALIBRATION_EPISODES, seed: int = 0,
    lambdas: tuple[float, float] = (0.1, 1.0), min_visib_fract: float = 0.3, use_depth: bool = True,
    progress: bool = True,
) -> dict[str, Any]:
    """Measure the cost model on `episodes` episodes of `image_keys` (default: every image) of
    `dataset` (module docstring). Returns {"format", "cost_table": {key: seconds}, "calls": {key:
    count}, "spread": {key: [q1, q3]}, and what was measured where}."""
    if episodes < 1:
        raise ValueError(f"calibration needs at least 1 episode, got {episodes}")
    ds = dataset if isinstance(dataset, BopDataset) else BopDataset(Path(dataset), use_depth=use_depth)
    pipe = pipeline if isinstance(pipeline, Pipeline) else load_pipeline(pipeline)
    source = EpisodeSource(ds, list(image_keys) if image_keys is not None else None, min_visib_fract=min_visib_fract)
    env = PerceptionConfigEnv(source, pipe, EnvSettings(time_mode="cost_table", min_visib_fract=min_visib_fract,
                                                        loop_mask=False))
    rng = np.random.default_rng(seed)
    calls: dict[str, list[float]] = defaultdict(list)
    started = time.monotonic()
    with open3d_single_thread(True):  # as cost-table training runs Open3D
        _measure(env, source, pipe, episodes, lambdas, rng, calls, progress)
    return _model(calls, {
        "dataset": str(ds.root), "pipeline": pipe.describe(), "episodes": int(episodes), "seed": int(seed),
        "lambdas": list(lambdas), "use_depth": bool(use_depth), "image_keys": [list(k) for k in source.image_keys],
        "measured_seconds": round(time.monotonic() - started, 1), "machine": _machine(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    })


def _measure(env: PerceptionConfigEnv, source: EpisodeSource, pipe: Pipeline, episodes: int,
             lambdas: tuple[float, float], rng: np.random.Generator, calls: dict[str, list[float]],
             progress: bool) -> None:
    """Time every action from the first hypothesis and from one after a random refinement, on
    `episodes` episodes; appends the seconds to `calls` per `<key>@<obj_id>`."""
    from tqdm import tqdm

    refiners = [i for i, a in enumerate(pipe.actions) if a.kind == Kind.REFINEMENT]
    warm: set[tuple[int, int]] = set()
    for _ in tqdm(range(episodes), desc="calibrate", unit="ep", disable=not progress):
        index = int(rng.integers(len(source)))
        lam = float(rng.uniform(*lambdas))
        ek = source.episodes[index]
        env.reset(options={"episode": index, "lambda": lam, "episode_seed": int(rng.integers(1, 2**31))})
        obj = int(env.episode.model.obj_id)
        frame_key = (ek.scene_id, ek.im_id)
        if frame_key not in warm:  # fill the frame's caches: the first call on a frame is not typical
            warm.add(frame_key)
            start = env.snapshot()
            for i in range(len(pipe.actions)):
                env.restore(start)
                env.ops.apply(pipe.actions[i].name)
            env.restore(start)
            env.reset(options={"episode": index, "lambda": lam, "episode_seed": int(rng.integers(1, 2**31))})
        calls[f"{ACTION_KEY}{GENERATE}@{obj}"].append(float(env.last_outcome.result.elapsed))
        states = [env.snapshot()]
        if refiners:
            env.step(int(rng.choice(refiners)))
            states.append(env.snapshot())
        for state in states:
            for action in pipe.actions:
                env.restore(state)
                outcome = env.ops.apply(action.name)
                calls[f"{ACTION_KEY}{action.name}@{obj}"].append(float(outcome.result.elapsed))
                calls[f"{SCORING_PASS}@{obj}"].append(float(outcome.score_elapsed))


def _model(calls: Mapping[str, list[float]], about: dict[str, Any]) -> dict[str, Any]:
    """The cost table from the timed calls per `<key>@<obj_id>` (module docstring)."""
    pooled: dict[str, list[float]] = defaultdict(list)
    for key, values in calls.items():
        pooled[key.rsplit("@", 1)[0]].extend(values)
    table: dict[str, float] = {}
    count: dict[str, int] = {}
    spread: dict[str, list[float]] = {}
    for key, values in sorted(pooled.items()):
        table[key], count[key] = _seconds(values), len(values)
        spread[key] = [round(float(q), 5) for q in np.percentile(values, [25, 75])]
    for key, values in sorted(calls.items()):
        if len(values) >= MIN_CALLS_PER_OBJECT:
            table[key], count[key] = _seconds(values), len(values)
            spread[key] = [round(float(q), 5) for q in np.percentile(values, [25, 75])]
    return {"format": FORMAT, "cost_table": table, "calls": count, "spread": spread, **about}


def _machine() -> dict[str, Any]:
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    return {"cpus": os.cpu_count(), "processor": platform.processor() or platform.machine(),
            "load_1min": round(load[0], 2), "python": platform.python_version()}


def write_cost_model(model: Mapping[str, Any], path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, json.dumps(model, indent=1, allow_nan=False) + "\n")
    return path


def read_cost_table(path: str | Path) -> dict[str, float]:
    """The cost table of a `calibrate` output (or of a plain {key: seconds} JSON mapping); errors
    name the file. Read as a hostile file (safe_json: a regular file of at most MAX_COST_MODEL_BYTES,
    nested at most MAX_JSON_DEPTH levels), and every entry checked as EnvSettings checks a cost
    table (rl/settings.py): a finite number of seconds in [0, MAX_SECONDS] (NaN, Infinity,
    negative, 1e300 or a boolean refused, naming the file, the entry and the value), at most
    MAX_COST_TABLE_ENTRIES entries."""
    path = Path(path)
    try:
        data = read_json_file(path, MAX_COST_MODEL_BYTES, MAX_JSON_DEPTH, "cost model")
    except FileNotFoundError:
        raise FileNotFoundError(f"cost model {path} does not exist (write one with `perception-config calibrate`)") \
            from None
    except (OSError, ValueError) as exc:  # JsonLimitError (a ValueError): too large, too deep, not JSON
        raise ValueError(f"cost model {path}: not a readable JSON file ({exc})") from None
    table = data.get("cost_table", data) if isinstance(data, dict) else None
    if not isinstance(table, dict) or not all(isinstance(k, str) for k in table):
        raise ValueError(f"cost model {path}: expected a calibrate output with 'cost_table' or a mapping "
                         "of key to seconds")
    try:
        EnvSettings(cost_table=table)
    except ValueError as exc:
        raise ValueError(f"cost model {path}: {exc}") from None
    return {k: float(v) for k, v in table.items()}
