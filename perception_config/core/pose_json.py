"""A pose as JSON: {"R": 9 floats row-major, "t": 3 floats in metres}.

One encoding for every file that records poses: the evaluation's episodes.jsonl, the episode
store's `pose` column (store/episode_store.py) and the step rows the pick-success score learns
from (learning/pick_success_data.py, in the store's decoded shape, `pose_arrays`).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from .geometry import Pose


def pose_json(pose: Pose | None) -> dict[str, list[float]] | None:
    """{"R": 9 floats row-major, "t": 3 floats in metres} of a pose (None: no pose)."""
    if pose is None:
        return None
    return {"R": [float(v) for v in np.asarray(pose.R, np.float64).reshape(9)],
            "t": [float(v) for v in np.asarray(pose.t, np.float64).reshape(3)]}


def pose_from_json(d: dict[str, Any] | None) -> Pose | None:
    """The inverse of `pose_json` (R row-major, t metres; lists or arrays)."""
    if d is None:
        return None
    return Pose(np.asarray(d["R"]).reshape(3, 3), np.asarray(d["t"]))


def pose_arrays(d: dict[str, Any] | None) -> dict[str, np.ndarray] | None:
    """A pose's JSON as {"R": (3, 3) ndarray, "t": (3,) ndarray}, or None: how the episode
    store's readers get a step's pose."""
    if d is None:
        return None
    return {"R": np.asarray(d["R"], np.float64).reshape(3, 3), "t": np.asarray(d["t"], np.float64).reshape(3)}
