"""The debug image a person watches: a camera frame with a pose hypothesis drawn on it.

`draw_hypothesis` scales the frame to at most `max_width` pixels wide (the intrinsics with it),
renders the model at the pose (render.render_box: one ray cast over the projected box), draws
the silhouette's outline and writes the object id, the scores and the operator trace in a
band at the top. Plain numpy + OpenCV on RGB uint8 images; no ROS here (ros/debug_view.py
turns the result into a sensor_msgs/Image).
"""
from __future__ import annotations

import math
from typing import Sequence

import cv2
import numpy as np

from ..core.geometry import Pose
from ..core.models import ObjectModel
from ..core.render import render_box

PICKED_RGB = (40, 220, 60)  # the outline of a hypothesis the robot picked: green
NOT_PICKED_RGB = (255, 150, 0)  # of one it did not (yet): orange
TEXT_RGB = (255, 255, 255)
FONT = cv2.FONT_HERSHEY_SIMPLEX


def scaled_intrinsics(K: np.ndarray, scale: float) -> np.ndarray:
    """K of the same camera with its image resized by `scale` (pixel centres at integers, as
    render.project and OpenCV: u' = (u + 0.5) * scale - 0.5)."""
    S = np.array([[scale, 0.0, 0.5 * scale - 0.5], [0.0, scale, 0.5 * scale - 0.5], [0.0, 0.0, 1.0]])
    return S @ np.asarray(K, dtype=np.float64).reshape(3, 3)


def fit_width(rgb: np.ndarray, K: np.ndarray, max_width: int) -> tuple[np.ndarray, np.ndarray]:
    """The image (a new array) and K, scaled down to at most `max_width` px wide (0 = as is)."""
    if max_width < 0:
        raise ValueError(f"max_width must be >= 0 (0 = full size), got {max_width}")
    h, w = rgb.shape[:2]
    if not max_width or w <= max_width:
        return rgb.copy(), np.asarray(K, dtype=np.float64).reshape(3, 3)
    scale = max_width / w
    size = (int(max_width), max(1, int(round(h * scale))))
    return cv2.resize(rgb, size, interpolation=cv2.INTER_AREA), scaled_intrinsics(K, size[0] / w)


def outline(model: ObjectModel, pose: Pose, K: np.ndarray, width: int, height: int) -> list[np.ndarray]:
    """The outline of the model's silhouette at `pose` in an image width x height: OpenCV
    contours (each (N, 1, 2) int32 pixel coordinates); [] when the object is not in view."""
    r = render_box(model, pose, K, width, height, margin=1)
    if r.empty:
        return []
    mask = (r.mask >= 0).astype(np.uint8)
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE, offset=r.offset)
    return list(contours)


def _score_text(scores: dict[str, float]) -> str:
    return "  ".join(f"{k} {v:.3f}" if math.isfinite(v) else f"{k} -" for k, v in scores.items())


def info_lines(object_id: str, scores: dict[str, float], operations: Sequence[str], picked: bool,
               seconds: float | None = None) -> list[str]:
    """The text written on the debug image: object and outcome, scores, operator trace."""
    head = f"object {object_id}: " + ("picked" if picked else "not picked")
    if seconds is not None:
        head += f" ({seconds * 1000:.0f} ms)"
    return [head, _score_text(scores) or "no scores", " > ".join(operations) or "no operation"]


def draw_text_band(img: np.ndarray, lines: Sequence[str]) -> None:
    """Write `lines` in a darkened band at the top of `img` (in place), shrinking the font so the
    longest line fits the width."""
    h, w = img.shape[:2]
    scale = max(0.3, min(0.6, w / 1100))
    widest = max(cv2.getTextSize(s, FONT, scale, 1)[0][0] for s in lines)
    if widest > w - 8:
        scale = max(0.25, scale * (w - 8) / widest)
    line_h = int(math.ceil(cv2.getTextSize("Ag", FONT, scale, 1)[0][1] * 1.8)) + 2
    band = min(h, line_h * len(lines) + 6)
    img[:band] = (img[:band].astype(np.uint16) * 2 // 5).astype(np.uint8)
    for i, s in enumerate(lines):
        cv2.putText(img, s, (4, line_h * (i + 1)), FONT, scale, TEXT_RGB, 1, cv2.LINE_AA)


def draw_hypothesis(rgb: np.ndarray, K: np.ndarray, model: ObjectModel, pose: Pose, lines: Sequence[str],
                    picked: bool, max_width: int = 0) -> np.ndarray:
    """A new RGB image: `rgb` scaled to at most `max_width` px wide (0 = full size) with the
    outline of `model` at `pose` (model-to-camera, metres; K the frame's intrinsics) and the
    text `lines` drawn on it."""
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"the image must be uint8 HxWx3 RGB, got {rgb.dtype} {rgb.shape}")
    img, K_img = fit_width(rgb, K, max_width)
    h, w = img.shape[:2]
    contours = outline(model, pose, K_img, w, h)
    thickness = max(2, int(round(w / 320)))
    cv2.drawContours(img, contours, -1, PICKED_RGB if picked else NOT_PICKED_RGB, thickness, cv2.LINE_AA)
    draw_text_band(img, lines)
    return img
