"""`perception-config fit-score`: fit, calibrate and measure the pick-success model.

The rows' images are split three ways, never the rows (hypotheses of one frame are alike): the
held-out test images (episodes.split_image_keys, the agents' own train/test split, so the
default dataset's test images stay unseen), and of the rest a calibration share for Platt
scaling; the network trains on the remainder. Reported on the held-out images, for RGB-D and
RGB-only rows apart and together: AUC (the chance that a succeeding hypothesis scores above a
failing one), Brier score (mean squared error of the probability), ECE (expected calibration
error, 10 equal-width bins) and log loss; `reliability.png` plots the predicted probability
against the observed success rate per bin. Model, plot and metrics.json are written atomically.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..core.score_metrics import score_metrics
from ..rl.episodes import DEFAULT_SPLIT_SEED, DEFAULT_TEST_FRACTION, split_image_keys
from ..util.atomic_file import atomic_write
from ..vision.crop_network import fit_hybrid
from ..vision.pick_success_model import MODEL_FILE, PickSuccessModel, encode, fit_mlp, fit_platt, robust_scaling
from .pick_success_data import FeatureTable

CALIBRATION_FRACTION = 0.25  # share of the training images kept for calibration


def split_images(table: FeatureTable, test_fraction: float = DEFAULT_TEST_FRACTION, seed: int = DEFAULT_SPLIT_SEED,
                 calibration_fraction: float = CALIBRATION_FRACTION) -> dict[str, np.ndarray]:
    """Boolean row masks "fit", "calibration", "test" from a split of the rows' images."""
    keys = sorted(set(table.images))
    if len(keys) < 3:
        raise ValueError(f"fit-score needs hypotheses from at least 3 images (fit, calibration, test), got {len(keys)}")
    train, test = split_image_keys(keys, test_fraction, seed)
    fit, cal = split_image_keys(train, calibration_fraction, seed + 1) if len(train) >= 2 else (train, [])
    which = {k: "test" for k in test} | {k: "calibration" for k in cal} | {k: "fit" for k in fit}
    labels = np.array([which[k] for k in table.images])
    return {name: labels == name for name in ("fit", "calibration", "test")}


def fit_model(table: FeatureTable, hidden: Sequence[int] = (32, 16), epochs: int = 300, seed: int = 0,
              test_fraction: float = DEFAULT_TEST_FRACTION, split_seed: int = DEFAULT_SPLIT_SEED,
              base: PickSuccessModel | None = None, progress: bool = False,
              ) -> tuple[PickSuccessModel, dict[str, Any], dict[str, np.ndarray]]:
    """(model, metrics, split masks): the MLP trained on the fit images, Platt-calibrated on the
    calibration images, measured on the held-out images. With a `base` model, only recalibrated:
    its network kept, Platt scaling fitted again on the fit and calibration images (a camera or
    cell whose frames the base never saw: the ranking stays, the probabilities move). A table
    with crops trains a model with a crop branch (vision/crop_network.fit_hybrid; `progress`: its
    epochs' bar)."""
    masks = split_images(table, test_fraction, split_seed)
    fit, cal, test = masks["fit"], masks["calibration"], masks["test"]
    if base is not None:
        cal = fit | cal
    for name, m in (("fit", fit), ("calibration", cal)):
        if len(set(table.y[m].tolist())) < 2:
            which = "successes" if table.y[m].all() else "failures"
            raise ValueError(f"the {name} images' hypotheses are all {which}: nothing to learn from; collect more "
                             f"episodes (or several lambdas)")
    if base is not None and base.uses_crop and table.crops is None:
        raise ValueError("the model to recalibrate looks at crops: featurise the rows with crops=True")
    if base is None:
        median, spread = robust_scaling(table.X[fit])
        Z = encode(table.X[fit], median, spread)
        conv: list = []
        if table.crops is not None:
            conv, layers = fit_hybrid(Z, table.crops[fit], table.y[fit], hidden, epochs, seed=seed, progress=progress)
        else:
            layers = fit_mlp(Z, table.y[fit], hidden, epochs, seed=seed)
        model = PickSuccessModel(tuple(table.feature_names), median, spread, layers, conv=conv)
    else:
        model = PickSuccessModel(base.feature_names, base.median, base.spread, base.layers, conv=base.conv)
    model.calibration = fit_platt(model.logit(*table.inputs(cal)), table.y[cal])
    metrics: dict[str, Any] = {}
    for name, m in (("fit", fit), ("calibration", cal), ("test", test)):
        p = model.predict(*table.inputs(m))
        metrics[name] = {"all": score_metrics(p, table.y[m]),
                         "rgbd": score_metrics(p[~table.rgb_only[m]], table.y[m][~table.rgb_only[m]]),
                         "rgb_only": score_metrics(p[table.rgb_only[m]], table.y[m][table.rgb_only[m]])}
    metrics["images"] = {name: len({table.images[i] for i in np.flatnonzero(m)}) for name, m in masks.items()}
    model.record = {"hidden": [w.shape[0] for w, _ in model.layers[:-1]], "epochs": int(epochs), "seed": int(seed),
                    "crop_branch": [int(w.shape[0]) for w, _ in model.conv],
                    "rows": len(table), "images": metrics["images"],
                    "test": {k: {m: metrics["test"][k].get(m) for m in ("n", "auc", "brier", "ece")}
                             for k in ("all", "rgbd", "rgb_only")}}
    if base is not None:
        model.record.update(recalibrated_from=base.record, base_calibration=list(base.calibration))
        p = base.predict(*table.inputs(test))
        metrics["test_before_recalibration"] = {
            "all": score_metrics(p, table.y[test]),
            "rgbd": score_metrics(p[~table.rgb_only[test]], table.y[test][~table.rgb_only[test]]),
            "rgb_only": score_metrics(p[table.rgb_only[test]], table.y[test][table.rgb_only[test]])}
    return model, metrics, masks


def plot_reliability(p_by_set: dict[str, tuple[np.ndarray, np.ndarray]], path: str | Path, title: str = "") -> Path:
    """The reliability diagram (observed success rate against predicted probability per bin,
    marker area ~ count) and the histogram of predictions, one curve per named set."""
    from ..core.plots import plt, save_figure  # lazy: matplotlib (Agg) only when plotting

    fig, (ax, hx) = plt.subplots(1, 2, figsize=(10, 4.4))
    ax.plot([0, 1], [0, 1], color="0.6", lw=1, ls="--", label="perfectly calibrated")
    for name, (p, y) in p_by_set.items():
        if len(p) == 0:
            continue
        m = score_metrics(p, y)
        bins = [b for b in m["bins"] if b["count"]]
        ax.plot([b["predicted"] for b in bins], [b["observed"] for b in bins], marker="o",
                label=f"{name}: AUC {m['auc']:.3f}, Brier {m['brier']:.3f}, ECE {m['ece']:.3f} (n={m['n']})")
        ax.scatter([b["predicted"] for b in bins], [b["observed"] for b in bins],
                   s=[8 + 200 * b["count"] / m["n"] for b in bins], alpha=0.4)
        hx.hist(p, bins=20, range=(0, 1), histtype="step", lw=1.5, label=name)
    ax.set(xlabel="predicted pick-success probability", ylabel="observed success rate", xlim=(0, 1), ylim=(0, 1),
           title=title or "pick_success reliability (held-out images)")
    ax.legend(fontsize=7, loc="upper left")
    hx.set(xlabel="predicted probability", ylabel="hypotheses", title="predictions", yscale="log")
    hx.legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path)


def fit_score(table: FeatureTable, out_dir: str | Path, hidden: Sequence[int] = (32, 16), epochs: int = 300,
              seed: int = 0, source: dict[str, Any] | None = None, base: PickSuccessModel | None = None,
              progress: bool = False) -> dict[str, Any]:
    """Fit (or with `base` only recalibrate), calibrate, measure; write MODEL_FILE,
    reliability.png and metrics.json into `out_dir`. Returns the metrics (with the written paths)."""
    out = Path(out_dir)
    model, metrics, masks = fit_model(table, hidden, epochs, seed, base=base, progress=progress)
    model.record["source"] = source or {}
    test = masks["test"]
    p = model.predict(*table.inputs(test))
    y, rgb = table.y[test], table.rgb_only[test]
    model_path = model.save(out / MODEL_FILE)
    plot = plot_reliability({"RGB-D": (p[~rgb], y[~rgb]), "RGB-only": (p[rgb], y[rgb])}, out / "reliability.png")
    metrics.update(source=source or {}, files={"model": MODEL_FILE, "reliability": plot.name},
                   settings={"hidden": list(hidden), "epochs": epochs, "seed": seed, "rows": len(table)})
    atomic_write(out / "metrics.json", json.dumps(metrics, indent=1, default=_json_default) + "\n")
    metrics.update(model=str(model_path), reliability=str(plot), metrics_file=str(out / "metrics.json"))
    return metrics


def _json_default(x: Any) -> Any:
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    raise TypeError(f"not JSON: {type(x).__name__}")


def format_metrics(metrics: dict[str, Any]) -> str:
    """The held-out figures as a few lines."""
    lines = [f"held-out images: {metrics['images']['test']} (fit {metrics['images']['fit']}, "
             f"calibration {metrics['images']['calibration']})"]
    for which, title in (("test_before_recalibration", "before recalibration:"), ("test", None)):
        if which not in metrics:
            continue
        if title:
            lines.append(title)
        for key, label in (("rgbd", "RGB-D"), ("rgb_only", "RGB-only"), ("all", "all")):
            m = metrics[which][key]
            if m.get("n"):
                lines.append(f"  {label:8s} n={m['n']:5d} success {100 * m['base_rate']:5.1f} %  AUC {m['auc']:.3f}  "
                             f"Brier {m['brier']:.3f}  ECE {m['ece']:.3f}")
        if title:
            lines.append("recalibrated:")
    return "\n".join(lines)


__all__ = ["split_images", "fit_model", "fit_score", "plot_reliability",
           "format_metrics"]
