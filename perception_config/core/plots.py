"""Evaluation figures (matplotlib Agg, PNG): the paper's Fig. 5 panels, a Fig. 4-style grid of
initial hypotheses per lambda, and Fig. 2-style pictures of single episodes.

Colours: ground truth blue, initial hypothesis red, final hypothesis green, observed depth grey.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..util.atomic_file import atomic_output  # noqa: E402
from .geometry import Pose  # noqa: E402
from .metrics import pose_mssd  # noqa: E402
from .models import ObjectModel  # noqa: E402
from .render import depth_to_points, project, render_box  # noqa: E402
from .scene import Frame  # noqa: E402

GT_COLOUR, INIT_COLOUR, FINAL_COLOUR = "#1f77ff", "#e41a1c", "#2ca02c"


def save_figure(fig: Any, path: str | os.PathLike, dpi: int = 110) -> Path:
    """Save a figure atomically and close it."""
    path = Path(path)
    try:
        with atomic_output(path) as tmp:
            fig.savefig(tmp, dpi=dpi)
    finally:
        plt.close(fig)
    return path


# --------------------------------------------------------------------------- Fig. 5


def _agent_style(name: str, kind: str, best_fixed: bool, k: int) -> dict[str, Any]:
    """Learned agents solid and bold, baselines thin: oracle black dotted, random grey dashed,
    fixed pipelines in browns (the best one dash-dotted and thicker). k counts within the group."""
    if name == "oracle":
        return {"color": "black", "ls": ":", "marker": "s"}
    if name == "random":
        return {"color": "0.55", "ls": "--", "marker": "x"}
    if kind == "fixed":
        colours, markers = ["#a0522d", "#d9a066", "#8c6d31", "#e6550d", "#bd9e39"], ["^", "v", "<", ">", "D"]
        return {"color": colours[k % len(colours)], "marker": markers[k % len(markers)],
                "ls": "-." if best_fixed else (0, (3, 2)), "lw": 1.8 if best_fixed else 1.0}
    colours = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#17becf", "#e377c2", "#bcbd22"]
    return {"color": colours[k % len(colours)], "ls": "-", "marker": "o", "lw": 2.0}


def plot_fig5(records: Sequence[dict[str, Any]], path: str | os.PathLike) -> Path:
    """The paper's Fig. 5 (plus success): operations and time to success (median, bars q1-q3,
    successful episodes only), % successful first picks and % success, each vs lambda, one line
    per agent."""
    agents = list(dict.fromkeys(r["agent"] for r in records))
    fig, axes = plt.subplots(2, 2, figsize=(13, 9), constrained_layout=True)
    panels = [
        (axes[0, 0], "ops_to_success", "operations to success", False),
        (axes[0, 1], "time_to_success", "computation time to success [s]", False),
        (axes[1, 0], "first_pick_success", "successful first picks [%]", True),
        (axes[1, 1], "success", "success within max_ops [%]", True),
    ]
    lams_all = sorted({r["lambda"] for r in records})
    step = min(np.diff(lams_all)) if len(lams_all) > 1 else 0.1
    counts = {"fixed": 0, "learned": 0}
    for i, name in enumerate(agents):
        rs = sorted((r for r in records if r["agent"] == name), key=lambda r: r["lambda"])
        kind = rs[0].get("kind", "")
        group = "fixed" if kind == "fixed" else "learned"
        style = _agent_style(name, kind, bool(rs[0].get("best_fixed")), counts[group])
        counts[group] += 1
        label = name + ("  (best fixed)" if rs[0].get("best_fixed") else "")
        offset = (i - (len(agents) - 1) / 2) * 0.4 * min(step, 0.1) / max(1, len(agents))  # error bars apart
        x = np.array([r["lambda"] for r in rs]) + offset
        lw = style.pop("lw", 1.4)
        for ax, key, _title, share in panels:
            if share:
                y = np.array([100.0 * r[key] for r in rs])
                ax.plot(x, y, lw=lw, ms=5, label=label, **style)
                continue
            med = np.array([np.nan if r[key]["median"] is None else r[key]["median"] for r in rs], float)
            q1 = np.array([np.nan if r[key]["q1"] is None else r[key]["q1"] for r in rs], float)
            q3 = np.array([np.nan if r[key]["q3"] is None else r[key]["q3"] for r in rs], float)
            yerr = np.vstack([np.nan_to_num(med - q1), np.nan_to_num(q3 - med)])
            ax.errorbar(x, med, yerr=yerr, lw=lw, ms=5, capsize=3, elinewidth=0.9, label=label, **style)
    for ax, _key, title, share in panels:
        ax.set_title(title + ("" if share else "  (median, bars q1-q3)"), fontsize=11)
        ax.set_xlabel("noise level lambda")
        ax.grid(True, alpha=0.3)
        ax.set_xticks(lams_all)
        ax.tick_params(axis="x", labelrotation=0, labelsize=8)
        if share:
            ax.set_ylim(-3, 103)
    # a time panel spanning orders of magnitude reads better on a log axis
    t = [r["time_to_success"][q] for r in records for q in ("q1", "q3") if r["time_to_success"][q]]
    if t and min(t) > 0 and max(t) / min(t) > 30:
        axes[0, 1].set_yscale("log")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=min(5, max(1, len(labels))), fontsize=9, frameon=False)
    n = records[0]["episodes"] if records else 0
    fig.suptitle(f"Agents vs noise level ({n} test episodes per lambda; time and operations over successful episodes)",
                 fontsize=12)
    return save_figure(fig, path)


# --------------------------------------------------------------------------- hypotheses on the image


def silhouette(model: ObjectModel, pose: Pose, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """Full-image boolean mask of the model rendered alone at the pose."""
    mask = np.zeros((height, width), bool)
    r = render_box(model, pose, K, width, height)
    if not r.empty:
        rs, cs = r.crop_slices()
        mask[rs, cs] = r.mask >= 0
    return mask


def _crop_box(model: ObjectModel, gt: Pose, K: np.ndarray, scale: float = 1.6,
              min_half: int = 40) -> tuple[int, int, int]:
    """A square crop (cx, cy, half size) around the object's projection at the ground truth."""
    uv = project(gt.transform(model.hull_points), K)
    uv = uv[np.all(np.isfinite(uv), axis=1)]
    if uv.size == 0:
        c = K @ gt.t
        return int(c[0] / c[2]), int(c[1] / c[2]), min_half
    lo, hi = uv.min(0), uv.max(0)
    cx, cy = (lo + hi) / 2
    half = max(min_half, int(scale * max(hi - lo) / 2))
    return int(round(cx)), int(round(cy)), half


def _crop(img: np.ndarray, cx: int, cy: int, half: int, fill: float = 0) -> np.ndarray:
    """img[cy-half:cy+half, cx-half:cx+half], padded with `fill` where it leaves the image."""
    pad = [(half, half), (half, half)] + [(0, 0)] * (img.ndim - 2)
    big = np.pad(img, pad, constant_values=fill)
    return big[cy:cy + 2 * half, cx:cx + 2 * half]


def _draw_masks(ax: Any, frame: Frame, box: tuple[int, int, int],
                masks: Sequence[tuple[np.ndarray, str, float]]) -> None:
    cx, cy, half = box
    ax.imshow(_crop(frame.rgb, cx, cy, half, fill=40))
    for mask, colour, lw in masks:
        m = _crop(mask.astype(np.float32), cx, cy, half)
        if m.any():
            ax.contourf(m, levels=[0.5, 1.5], colors=[colour], alpha=0.18)
            ax.contour(m, levels=[0.5], colors=[colour], linewidths=lw)
    ax.set_xticks([])
    ax.set_yticks([])


def plot_lambda_grid(
    frame: Frame, model: ObjectModel, gt: Pose, hypotheses: Sequence[tuple[float, Pose | None]],
    path: str | os.PathLike, columns: int = 5,
) -> Path:
    """Fig. 4 style: the initial hypothesis of one frame/object at each lambda (red silhouette
    and contour) over the image crop, ground truth in blue; MSSD / diameter in each title."""
    W, H, K = frame.width, frame.height, frame.K
    box = _crop_box(model, gt, K, scale=2.2)
    gt_mask = silhouette(model, gt, K, W, H)
    n = len(hypotheses)
    cols = min(columns, n)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(max(6.0, 2.6 * cols), 2.8 * rows + 0.6), squeeze=False,
                             constrained_layout=True)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (lam, pose) in zip(axes.ravel(), hypotheses):
        ax.axis("on")
        masks = [(gt_mask, GT_COLOUR, 1.0)]
        if pose is not None:
            masks.append((silhouette(model, pose, K, W, H), INIT_COLOUR, 1.4))
            err = pose_mssd(pose, gt, model) / model.diameter
            ax.set_title(f"lambda = {lam:g}   MSSD = {err:.2f} d", fontsize=9)
        else:
            ax.set_title(f"lambda = {lam:g}   no hypothesis", fontsize=9)
        _draw_masks(ax, frame, box, masks)
    fig.suptitle(f"Initial hypotheses (red) vs ground truth (blue)\nscene {frame.scene_id} image {frame.im_id} "
                 f"object {model.obj_id}", fontsize=11)
    return save_figure(fig, path)


def plot_episode(
    frame: Frame, model: ObjectModel, gt: Pose | None, initial: Pose | None, final: Pose | None,
    title: str, path: str | os.PathLike,
) -> Path:
    """Fig. 2 style: initial (red) and final (green) hypotheses on the image crop, ground truth
    blue; and a side view (camera x vs depth z) of the observed points around the object (dark
    grey on the object's ground-truth silhouette, light grey around it) with the model's
    camera-visible surface at the initial and final poses (an RGB-only frame: the models only)."""
    W, H, K = frame.width, frame.height, frame.K
    ref = gt or final or initial
    if ref is None:
        raise ValueError("plot_episode needs at least one pose")
    box = _crop_box(model, ref, K, scale=2.0)
    fig, (ax_img, ax_side) = plt.subplots(1, 2, figsize=(12, 5.6), constrained_layout=True,
                                          gridspec_kw={"width_ratios": [1, 1.15]})
    masks = []
    for pose, colour, lw, label in ((gt, GT_COLOUR, 1.0, "ground truth"), (initial, INIT_COLOUR, 1.4, "initial"),
                                    (final, FINAL_COLOUR, 1.6, "final")):
        if pose is not None:
            masks.append((silhouette(model, pose, K, W, H), colour, lw))
            ax_img.plot([], [], color=colour, lw=2, label=label)
    object_mask = masks[0][0]  # the reference pose's silhouette: ground truth when known
    _draw_masks(ax_img, frame, box, masks)
    ax_img.legend(loc="lower right", fontsize=8, framealpha=0.8)
    ax_img.set_title("image: hypotheses (contours)", fontsize=10)

    # observed points of the crop window near the object (3D distance to its centre), split
    # into those on the object (inside the reference silhouette) and the surroundings
    cx, cy, half = box
    x0, y0 = max(0, cx - half), max(0, cy - half)
    rows, cols = slice(y0, min(H, cy + half)), slice(x0, min(W, cx + half))
    if frame.depth is not None:
        win = frame.depth[rows, cols]
        pts = depth_to_points(win, K, (x0, y0))
        on_object = object_mask[rows, cols][np.isfinite(win) & (win > 0)]  # depth_to_points' pixel order
        near = np.linalg.norm(pts - ref.transform(model.points).mean(0), axis=1) < 0.9 * model.diameter
        pts, on_object = pts[near], on_object[near]
    else:  # an RGB-only frame: no observed points, the models only
        pts, on_object = np.zeros((0, 3)), np.zeros(0, bool)
    rng = np.random.default_rng(0)
    if len(pts) > 8000:
        keep = rng.choice(len(pts), 8000, replace=False)
        pts, on_object = pts[keep], on_object[keep]
    for pose, colour, label in ((initial, INIT_COLOUR, "model at initial"), (final, FINAL_COLOUR, "model at final")):
        if pose is not None:
            r = render_box(model, pose, K, W, H)  # the model surface the camera would see
            p = depth_to_points(r.depth, K, r.offset)
            if len(p) > 4000:
                p = p[rng.choice(len(p), 4000, replace=False)]
            ax_side.scatter(p[:, 0], p[:, 2], s=7, c=colour, alpha=0.45, lw=0, label=label, rasterized=True)
    if frame.depth is not None:
        ax_side.scatter(pts[~on_object, 0], pts[~on_object, 2], s=2, c="0.72", lw=0, label="observed: surroundings",
                        rasterized=True, zorder=2)
        ax_side.scatter(pts[on_object, 0], pts[on_object, 2], s=2.5, c="0.15", lw=0, label="observed: object",
                        rasterized=True, zorder=3)
    ax_side.set_aspect("equal", adjustable="datalim")
    ax_side.invert_yaxis()  # camera at the top, looking down the page
    ax_side.set_xlabel("camera x [m]")
    ax_side.set_ylabel("depth z [m] (camera above)")
    ax_side.grid(True, alpha=0.3)
    ax_side.legend(loc="lower right", fontsize=8, markerscale=4, framealpha=0.8)
    ax_side.set_title("side view: observed point cloud and model" if frame.depth is not None
                      else "side view: model (RGB-only frame: no observed depth)", fontsize=10)
    fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)


__all__ = ["plot_fig5", "plot_lambda_grid", "plot_episode", "silhouette"]
