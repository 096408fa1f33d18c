"""The pick-success features of a hypothesis (vision/pick_features.py), with the scores they take
from the scoring blocks at their default parameters (psi_d, psi_c, icp_fitness, psi_rgb), so a
model trained here sees the same values whatever scoring set a pipeline runs. Blocks are made
through the registry (`create`), never imported: this is block infrastructure, not a block."""
from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np

from ..core.geometry import Pose
from ..core.models import ObjectModel
from ..core.scene import Frame
from ..vision.pick_features import SCORE_FEATURES, features_from_scores
from ..vision.verifier_crop import CHANNELS, CROP, verifier_crop, without_depth
from .base import BlockInput, create

_scorers: dict[str, Any] = {}


def _score_blocks() -> dict[str, Any]:
    """The scoring blocks at their default parameters, created once per process."""
    if not _scorers:
        for block in dict.fromkeys(b for _, b in SCORE_FEATURES):
            _scorers[block] = create(block)
    return _scorers


def pipeline_scores(frame: Frame, model: ObjectModel, pose: Pose, cache: dict | None) -> tuple[dict[str, float], dict]:
    """The scores of SCORE_FEATURES at `pose` (NaN where a block cannot run, e.g. psi_d on an
    RGB-only frame) and psi_rgb's info (its best-fit shift)."""
    inp = BlockInput(frame=frame, model=model, pose=pose, cache=cache if cache is not None else {})
    out: dict[str, float] = {}
    rgb_info: dict = {}
    for name, block in _score_blocks().items():
        r = block(inp)
        for score in block.score_names:
            v = r.scores.get(score, math.nan) if r.ok else math.nan
            out[score] = float(v) if v is not None and math.isfinite(v) else math.nan
        if name == "psi_rgb" and r.ok:
            rgb_info = r.info
    return out, rgb_info


def pick_features(frame: Frame, model: ObjectModel, pose: Pose, cache: dict | None = None,
                  use_depth: bool = True) -> dict[str, float]:
    """Every feature of FEATURE_NAMES for the hypothesis `pose` of `model` in `frame` (NaN where
    the frame cannot tell). `use_depth=False` treats the frame as RGB-only (the depth features
    NaN) without copying it. `cache`: the frame's shared cache (BlockInput.cache)."""
    if cache is None:
        cache = {}
    if not use_depth and frame.depth is not None:
        frame = replace(frame, depth=None)
        cache = {}  # the caches hold depth-derived entries keyed by pose only
    scores, rgb_info = pipeline_scores(frame, model, pose, cache)
    return features_from_scores(frame, model, pose, scores, rgb_info, cache)


def hypothesis_crop(frame: Frame, model: ObjectModel, pose: Pose, cache: dict | None = None,
                    use_depth: bool = True) -> np.ndarray:
    """The rendered-against-observed crop of the hypothesis (vision/verifier_crop.py), zeros when
    nothing is rendered; `use_depth=False`: the depth channels zero, as on an RGB-only frame."""
    crop = verifier_crop(frame, model, pose, cache)
    if crop is None:
        return np.zeros((len(CHANNELS), CROP, CROP), np.float32)
    return crop if use_depth else without_depth(crop)
