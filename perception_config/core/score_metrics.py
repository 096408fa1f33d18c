"""How well a probability tells right from wrong: AUC, Brier score, expected calibration error
and log loss of predictions p (n,) in [0, 1] for boolean labels y (n,), plain numpy.

Used for the pick-success score (its fit and held-out figures, the online score learner) and
for any verifier judged on real frames (bench generators).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

N_BINS = 10  # equal-width probability bins of the calibration table and the ECE


def auc(p: np.ndarray, y: np.ndarray) -> float:
    """Area under the ROC curve (Mann-Whitney, ties half); NaN with one class only."""
    p, y = np.asarray(p, float), np.asarray(y, bool)
    n1, n0 = int(y.sum()), int((~y).sum())
    if n1 == 0 or n0 == 0:
        return math.nan
    order = np.argsort(p, kind="mergesort")
    ranks = np.empty(len(p))
    sp = p[order]
    i = 0
    while i < len(sp):  # average ranks over ties
        j = i
        while j + 1 < len(sp) and sp[j + 1] == sp[i]:
            j += 1
        ranks[order[i:j + 1]] = 0.5 * (i + j) + 1
        i = j + 1
    return float((ranks[y].sum() - n1 * (n1 + 1) / 2) / (n1 * n0))


def calibration_bins(p: np.ndarray, y: np.ndarray, n_bins: int = N_BINS) -> list[dict[str, float]]:
    """Per equal-width probability bin: count, mean predicted probability, observed success rate."""
    p, y = np.asarray(p, float), np.asarray(y, float)
    idx = np.minimum((p * n_bins).astype(int), n_bins - 1)
    out = []
    for k in range(n_bins):
        sel = idx == k
        n = int(sel.sum())
        out.append({"low": k / n_bins, "high": (k + 1) / n_bins, "count": n,
                    "predicted": float(p[sel].mean()) if n else math.nan,
                    "observed": float(y[sel].mean()) if n else math.nan})
    return out


def score_metrics(p: np.ndarray, y: np.ndarray) -> dict[str, Any]:
    """AUC, Brier, ECE, log loss, counts and the base rate of predictions p for labels y."""
    p, y = np.asarray(p, float), np.asarray(y, bool)
    if len(p) == 0:
        return {"n": 0}
    bins = calibration_bins(p, y)
    ece = sum(b["count"] * abs(b["predicted"] - b["observed"]) for b in bins if b["count"]) / len(p)
    q = np.clip(p, 1e-7, 1 - 1e-7)
    return {"n": int(len(p)), "positives": int(y.sum()), "base_rate": float(y.mean()), "auc": auc(p, y),
            "brier": float(np.mean((p - y) ** 2)), "ece": float(ece),
            "log_loss": float(-np.mean(np.where(y, np.log(q), np.log(1 - q)))), "bins": bins}


__all__ = ["N_BINS", "auc", "calibration_bins", "score_metrics"]
