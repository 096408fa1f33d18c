"""The learning curve of a training run (learning_curve.png), drawn from its per-episode history.

Panels, against the episode number (1-based):
1. return (minus seconds) per episode and its moving average;
2. time to success (seconds; successful episodes only) and its moving average;
3. success within max_ops and first-pick success rates (moving averages);
4. only when the agent reported them (pg): per update, the policy's entropy (nats, left axis,
   with its maximum log(n_actions) when `n_actions` is given), and the gradient norm before
   clipping and the loss (right axis); a point per update, at the last episode of its round.
   Entropy falling to 0 (a deterministic policy) or a gradient norm exploding shows a collapsing
   run here, before any evaluation.
The moving averages run over the last `window` = clip(episodes // 10, 1, 100) episodes. With
`validation` records (learning/validation.py) the greedy policy's validation figures are drawn
on panels 1-3, and the selected episode is marked on every panel.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..util.atomic_file import atomic_output

DIAGNOSTICS = ("entropy", "grad_norm", "loss")  # the figures of the fourth panel (when the agent reports them)


def moving_average(x: np.ndarray, window: int) -> np.ndarray:
    """Trailing mean over the last `window` finite values (NaN where there are none)."""
    x = np.asarray(x, np.float64)
    ok = np.isfinite(x)
    s = np.concatenate([[0.0], np.cumsum(np.where(ok, x, 0.0))])
    n = np.concatenate([[0], np.cumsum(ok)])
    idx = np.arange(1, len(x) + 1)
    lo = np.maximum(0, idx - window)
    cnt = n[idx] - n[lo]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(cnt > 0, (s[idx] - s[lo]) / np.maximum(cnt, 1), np.nan)


def per_update(history: dict[str, np.ndarray], key: str) -> tuple[np.ndarray, np.ndarray]:
    """(episode, value) of `key` once per update: history["update"] is each episode's update index
    (NaN where unknown), the figure is taken at the last episode (1-based) of each update."""
    update = np.asarray(history.get("update", ()), np.float64)
    values = np.asarray(history.get(key, np.full(len(update), np.nan)), np.float64)
    if len(update) == 0:
        return np.zeros(0), np.zeros(0)
    last = np.flatnonzero(np.isfinite(update) & np.append(update[1:] != update[:-1], True))
    return last + 1.0, values[last]


def has_diagnostics(history: dict[str, np.ndarray]) -> bool:
    """Whether the run's agent reported any of DIAGNOSTICS (the fourth panel is drawn)."""
    return any(np.isfinite(per_update(history, k)[1]).any() for k in DIAGNOSTICS if k in history)


def plot_learning_curve(history: dict[str, np.ndarray], path: str | Path, title: str = "",
                        validation: list[dict[str, Any]] | None = None, selected: int | None = None,
                        n_actions: int | None = None) -> Path:
    """The panels of the module docstring as a PNG at `path` (written atomically); `history`: the
    per-episode arrays of training.py ("return", "time", "success", "first_pick", optionally
    "update" and the agent's figures); `validation`: learning/validation.py records; `selected`:
    an episode to mark; `n_actions`: draws log(n_actions), the highest possible entropy."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(history["return"])
    ep = np.arange(1, n + 1)
    window = int(max(1, min(100, n // 10)))
    diagnostics = has_diagnostics(history)
    fig, axes = plt.subplots(4 if diagnostics else 3, 1, sharex=True, figsize=(8, 11.0 if diagnostics else 8.5))
    axes[0].plot(ep, history["return"], ".", ms=2, alpha=0.25, color="tab:blue")
    axes[0].plot(ep, moving_average(history["return"], window), color="tab:blue")
    axes[0].set_ylabel("return (-seconds)")
    t_succ = np.where(history["success"] > 0, history["time"], np.nan)
    axes[1].plot(ep, t_succ, ".", ms=2, alpha=0.25, color="tab:green")
    axes[1].plot(ep, moving_average(t_succ, window), color="tab:green")
    axes[1].set_ylabel("time to success (s)")
    axes[2].plot(ep, moving_average(history["success"], window), label="success within max_ops")
    axes[2].plot(ep, moving_average(history["first_pick"], window), label="first pick succeeds")
    axes[2].set_ylim(-0.02, 1.02)
    axes[2].set_ylabel("rate")
    axes[-1].set_xlabel("episode")
    if diagnostics:
        _plot_diagnostics(axes[3], history, n_actions)
    if validation:
        v_ep = np.array([r["episode"] for r in validation])
        tts = np.array([np.nan if r.get("time_to_success") is None else r["time_to_success"] for r in validation])
        axes[0].plot(v_ep, [-r["cost"] for r in validation], "o-", color="tab:red", ms=3,
                     label="validation, greedy (- mean cost)")
        axes[1].plot(v_ep, tts, "o-", color="tab:red", ms=3, label="validation, greedy")
        axes[2].plot(v_ep, [r["success"] for r in validation], "o--", ms=3, color="tab:purple",
                     label="validation success (greedy)")
        axes[2].plot(v_ep, [r["first_pick"] for r in validation], "o--", ms=3, color="tab:brown",
                     label="validation first pick (greedy)")
        if selected is not None:
            for ax in axes:
                ax.axvline(selected, color="tab:red", ls=":", lw=1)
            axes[0].plot([], [], color="tab:red", ls=":", label=f"selected (episode {selected})")
        axes[0].legend(loc="lower right")
        axes[1].legend(loc="upper right")
    axes[2].legend(loc="lower right")
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.suptitle(f"{title} (moving average over {window} episodes)")
    fig.tight_layout()
    try:
        with atomic_output(path) as tmp:
            fig.savefig(tmp, dpi=100)
    finally:
        plt.close(fig)
    return Path(path)


def _plot_diagnostics(ax: Any, history: dict[str, np.ndarray], n_actions: int | None) -> None:
    """Entropy on `ax` (left axis), gradient norm and loss on a twin axis (right), per update."""
    lines = []
    x, entropy = per_update(history, "entropy")
    lines += ax.plot(x, entropy, ".-", ms=3, lw=1, color="tab:olive", label="entropy (nats)")
    if n_actions and n_actions > 1:
        lines.append(ax.axhline(np.log(n_actions), color="tab:olive", ls="--", lw=1, label="log(n_actions)"))
    ax.set_ylim(bottom=0.0)
    ax.set_ylabel("policy entropy (nats)")
    right = ax.twinx()
    x, grad_norm = per_update(history, "grad_norm")
    lines += right.plot(x, grad_norm, ".-", ms=3, lw=1, color="tab:cyan", label="gradient norm (before clipping)")
    x, loss = per_update(history, "loss")
    lines += right.plot(x, loss, ".-", ms=3, lw=1, color="tab:gray", alpha=0.7, label="loss")
    right.set_ylabel("gradient norm, loss")
    ax.legend(lines, [ln.get_label() for ln in lines], loc="best", fontsize="small")
    ax.set_title("per update", fontsize="small", loc="left")
