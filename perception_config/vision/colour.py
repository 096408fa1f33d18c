"""Colour evidence for the model-only generator: model and image colours compared by hue.

Colour is compared as hue in the rg-chromaticity plane, not as absolute chromaticity:
lighting, specular highlights and camera gamma desaturate colours (measured: the synthetic
renders show the brass elbow at about half its model saturation; real LM-O scans agree within
~0.05), but keep their hue. Grey stays grey.
"""
from __future__ import annotations

import math
import weakref

import numpy as np
from scipy.spatial import cKDTree

from ..core.models import ObjectModel
from ..core.scene import Frame
from .features import MODEL_CACHE_LOCK
from .segmentation import Cluster

MIN_BRIGHTNESS = 60  # r + g + b below this: too dark for a reliable chromaticity
GREY_RADIUS = 0.04  # chromaticity distance from (1/3, 1/3) below which a colour counts as grey
HUE_TOL_DEG = 30.0  # hue difference counted as agreement
HUE_BINS = 12  # histogram: one grey bin plus HUE_BINS hue sectors


def chromaticity(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) offset of the chromaticity (r, g) / (r + g + b) from grey (1/3, 1/3) of (N, 3)
    colours, and which are bright enough to tell."""
    c = np.asarray(rgb, dtype=np.float64).reshape(-1, 3)
    s = c.sum(axis=1)
    return c[:, :2] / np.maximum(s, 1.0)[:, None] - 1.0 / 3.0, s >= MIN_BRIGHTNESS


def colours_agree(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per row: do chromaticity offsets a and b (N, 2) agree? Both grey, or both coloured with
    hues within HUE_TOL_DEG (saturation may differ)."""
    ra, rb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
    grey_a, grey_b = ra < GREY_RADIUS, rb < GREY_RADIUS
    cos = np.sum(a * b, axis=1) / np.maximum(ra * rb, 1e-12)
    hue_ok = cos > math.cos(math.radians(HUE_TOL_DEG))
    return (grey_a & grey_b) | (~grey_a & ~grey_b & hue_ok)


def hue_histogram(rgb: np.ndarray) -> np.ndarray | None:
    """Normalised histogram (grey + HUE_BINS hue sectors) of the bright-enough colours; None
    when none are."""
    ch, ok = chromaticity(rgb)
    if not ok.any():
        return None
    ch = ch[ok]
    grey = np.linalg.norm(ch, axis=1) < GREY_RADIUS
    sector = 1 + (np.floor((np.arctan2(ch[:, 1], ch[:, 0]) + math.pi) / (2 * math.pi) * HUE_BINS).astype(int)
                  % HUE_BINS)
    h = np.bincount(np.where(grey, 0, sector), minlength=HUE_BINS + 1).astype(np.float64)
    # Spread each hue sector over its neighbours: a hue near a sector boundary (the LM-O duck's
    # model and image fall on either side of one) must not look like another colour.
    hue = h[1:]
    h[1:] = 0.5 * hue + 0.25 * np.roll(hue, 1) + 0.25 * np.roll(hue, -1)
    return h / h.sum()


_MODEL_COLOURS: "weakref.WeakKeyDictionary[ObjectModel, tuple[np.ndarray, np.ndarray | None]]" = (
    weakref.WeakKeyDictionary())


def model_point_colours(model: ObjectModel) -> tuple[np.ndarray, np.ndarray | None] | None:
    """Colours (P, 3) of the model's surface samples (nearest vertex colour) and their hue
    histogram; None when the model has no colours. Cached per model."""
    if model.colors is None:
        return None
    with MODEL_CACHE_LOCK:
        if model in _MODEL_COLOURS:
            return _MODEL_COLOURS[model]
    _, vi = cKDTree(model.vertices).query(model.points)
    cols = model.colors[vi].astype(np.float64)
    out = (cols, hue_histogram(cols))
    with MODEL_CACHE_LOCK:
        _MODEL_COLOURS[model] = out
    return out


def colour_similarity(model: ObjectModel, frame: Frame, cl: Cluster) -> float:
    """Bhattacharyya coefficient (0..1) of the hue histograms of the model and of a cluster's
    pixels; 1 when either has no usable colour (no evidence either way)."""
    mc = model_point_colours(model)
    if mc is None or mc[1] is None:
        return 1.0
    if cl.colour_hist is None:
        h = hue_histogram(frame.rgb.reshape(-1, 3)[cl.pixels])
        cl.colour_hist = h if h is not None else np.zeros(HUE_BINS + 1)
    if cl.colour_hist.sum() == 0:
        return 1.0
    return float(np.sqrt(mc[1] * cl.colour_hist).sum())
