"""A training run's history: one row per episode played, kept in the checkpoint and written as
history.csv (learning/training.py).

Columns, in this order (other code reads history.csv by these names):
- episode (1-based), then HISTORY_FIELDS: return (minus seconds), time (seconds charged),
  success and first_pick (0/1), steps, lambda (the episode's noise level);
- UPDATE_FIELDS, for the update the episode's round fed (every episode of a round has the same):
  update (its index, 1-based), then pg's figures (agents/policy_gradient.py: loss, value_loss,
  entropy in nats, grad_norm and value_grad_norm before clipping, lr, approx_kl); a column the
  agent never reported is empty, a figure it did not report for one update is nan;
- the agent's other figures, by name (es: best_fitness, mean_fitness, sigma; simple: xi, memory_keys).
In the checkpoint every column (but episode) is a float64 tensor "history/<column>"; a resumed run
continues them, so its history is the uninterrupted run's. Episodes of runs from before the update
columns have nan there.
"""
from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from ..rl.trajectory import Trajectory
from ..util.atomic_file import atomic_write

HISTORY_FIELDS = ("return", "time", "success", "first_pick", "steps", "lambda")
UPDATE_FIELDS = ("update", "loss", "value_loss", "entropy", "grad_norm", "value_grad_norm", "lr", "approx_kl")
TENSOR_PREFIX = "history/"

History = dict[str, list[float]]


def new_history() -> History:
    """An empty history (the columns every run has)."""
    return {k: [] for k in (*HISTORY_FIELDS, "update")}


def history_from_tensors(tensors: dict[str, np.ndarray]) -> History:
    """The history a checkpoint's tensors hold (the "history/..." ones; nan update columns for a
    checkpoint from before them)."""
    history = new_history()
    for name in sorted(tensors):
        if name.startswith(TENSOR_PREFIX):
            history[name[len(TENSOR_PREFIX):]] = np.asarray(tensors[name], np.float64).tolist()
    history["update"] = history["update"] or [float("nan")] * len(history["return"])
    return history


def updates_done(history: History) -> int:
    """The index of the last update recorded (0: none)."""
    return max((int(u) for u in history["update"] if np.isfinite(u)), default=0)


def columns(history: History | dict[str, np.ndarray]) -> list[str]:
    """history.csv's columns after "episode" (module docstring), those the history lacks included."""
    others = sorted(k for k in history if k not in HISTORY_FIELDS and k not in UPDATE_FIELDS)
    return [*HISTORY_FIELDS, *UPDATE_FIELDS, *others]


def record_round(history: History, trajectories: list[list[Trajectory]], figures: dict[str, float],
                 update: int) -> int:
    """Append a round's episodes (trajectories[actor][episode], actor by actor), each with the
    `update` index and the `figures` the agent's update returned (nan for a figure it reported
    before but not now; a new figure gets nan for the earlier episodes). Returns the episodes added.
    ValueError for a figure named like one of the episode columns."""
    for key in figures:
        if key in HISTORY_FIELDS or key in ("episode", "update"):
            raise ValueError(f"the agent's update returned a figure named {key!r}, which is a history column")
    before = len(history["return"])
    for per_actor in trajectories:
        for t in per_actor:
            for key, value in zip(HISTORY_FIELDS, (t.ret, t.time, float(t.success), float(t.first_pick_success),
                                                   t.steps, t.noise_lambda)):
                history[key].append(float(value))
    n = len(history["return"]) - before
    for key in figures:
        history.setdefault(key, [float("nan")] * before)
    history["update"].extend([float(update)] * n)
    for key in history:
        if key not in HISTORY_FIELDS and key != "update":
            history[key].extend([float(figures.get(key, float("nan")))] * n)
    return n


def history_arrays(history: History) -> dict[str, np.ndarray]:
    """The columns the history holds, in history.csv's order, as float64 arrays."""
    return {k: np.asarray(history[k], np.float64) for k in columns(history) if k in history}


def write_history_csv(history: dict[str, np.ndarray], path: Path) -> None:
    """history.csv (atomically): a header, then one row per episode (module docstring)."""
    names = columns(history)
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["episode", *names])
    for i in range(len(history["return"])):
        w.writerow([i + 1, *("" if k not in history else f"{history[k][i]:.6g}" for k in names)])
    atomic_write(path, buf.getvalue())

