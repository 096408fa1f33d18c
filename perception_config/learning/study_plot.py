"""The plot of a study (study.png): the seeds' spread against the baselines, per lambda.

Two panels, the lambdas side by side on the x axis: mean episode cost (seconds; top) and success
(%; bottom). In each lambda's slot every seed is a point with its 95 % bootstrap interval (left to
right in seed order) and the seeds pooled a diamond; the bar (best_static, or the best fixed
pipeline), the best fixed pipeline (when it is not the bar) and the oracle are horizontal bands
across the slot: the line their mean, the band their interval.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..core.plots import save_figure

SLOT = 0.8  # width of one lambda's slot on the x axis (the slots are 1 apart)
BANDS = (("bar", "#1f77b4"), ("best_fixed", "#a0522d"), ("oracle", "0.2"))


def _interval(d: dict[str, Any] | None, scale: float) -> tuple[float, float, float] | None:
    if not d or d.get("mean") is None:
        return None
    mean = d["mean"] * scale
    lo = d["lo"] * scale if d.get("lo") is not None else mean
    hi = d["hi"] * scale if d.get("hi") is not None else mean
    return mean, lo, hi


def plot_study(analysis: dict[str, Any], path: str | Path, title: str = "") -> Path:
    """Draw `analysis` (study_report.analyse output) as a PNG at `path`, written atomically."""
    import matplotlib
    import matplotlib.pyplot as plt  # Agg: core.plots sets it

    lambdas = analysis["lambdas"]
    learned = analysis["learned"]
    rows = {(r["agent"], r["lambda"]): r for r in analysis["agents"]}
    pooled = {p["lambda"]: p for p in analysis["pooled"]}
    bands = {"bar": analysis["bar"]["name"], "oracle": "oracle" if any(a == "oracle" for a, _ in rows) else None,
             "best_fixed": analysis["best_fixed"] if analysis["best_fixed"] != analysis["bar"]["name"] else None}
    labels = {"bar": f"{analysis['bar']['name']} (bar)" if analysis["bar"]["kind"] == "best_static"
              else f"best fixed: {analysis['bar']['name']} (bar)",
              "best_fixed": f"best fixed: {analysis['best_fixed']}", "oracle": "oracle"}
    n = len(learned)
    offsets = np.linspace(-0.3 * SLOT, 0.2 * SLOT, n) if n > 1 else np.zeros(1)
    colours = matplotlib.colormaps["viridis"](np.linspace(0.1, 0.85, max(n, 1)))
    fig, axes = plt.subplots(2, 1, figsize=(max(6.0, 2.2 * len(lambdas) + 1.5), 8.0), sharex=True)
    panels = (("episode_cost", "mean episode cost [s]", 1.0), ("success", "success [%]", 100.0))
    for ax, (key, ylabel, scale) in zip(axes, panels):
        for i, lam in enumerate(lambdas):
            x0, x1 = i - SLOT / 2, i + SLOT / 2
            for band, colour in BANDS:
                name = bands[band]
                iv = _interval(rows.get((name, lam), {}).get(key), scale) if name else None
                if iv is None:
                    continue
                ax.fill_between([x0, x1], iv[1], iv[2], color=colour, alpha=0.12, lw=0)
                ax.hlines(iv[0], x0, x1, colors=colour, lw=1.5, label=labels[band] if i == 0 else None,
                          linestyles="-" if band == "bar" else "--")
            for k, agent in enumerate(learned):
                iv = _interval(rows.get((agent, lam), {}).get(key), scale)
                if iv is not None:
                    ax.errorbar(i + offsets[k], iv[0], yerr=[[iv[0] - iv[1]], [iv[2] - iv[0]]], fmt="o", ms=4,
                                color=colours[k], capsize=2, label=agent if i == 0 else None)
            iv = _interval(pooled.get(lam, {}).get(key), scale)
            if iv is not None:
                ax.errorbar(i + 0.32 * SLOT, iv[0], yerr=[[iv[0] - iv[1]], [iv[2] - iv[0]]], fmt="D", ms=6,
                            color="#d62728", capsize=3, label=f"{analysis['label']}, seeds pooled" if i == 0 else None)
        ax.set_ylabel(ylabel)
        ax.grid(True, axis="y", alpha=0.3)
    axes[-1].set_xticks(range(len(lambdas)), [f"lambda {lam:g}" for lam in lambdas])
    handles, names = axes[0].get_legend_handles_labels()
    fig.legend(handles, names, loc="lower center", ncol=min(3, max(1, len(names))), fontsize=7, frameon=False)
    level = 100 * analysis["bootstrap"]["level"]
    fig.suptitle(title or f"{analysis['label']}: {n} seeds vs the baselines\n(points and bands: means and {level:g} % "
                          "bootstrap intervals)", fontsize=9)
    rows_of_legend = (len(names) + 2) // 3
    fig.tight_layout(rect=(0, 0.02 + 0.025 * rows_of_legend, 1, 0.95))
    return save_figure(fig, path)


__all__ = ["plot_study"]
