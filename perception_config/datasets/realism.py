"""What a real cell adds to a clean synthetic image: calibration errors and imperfect ground truth.

A verifier trained on synthetic images learns what a right pose looks like there: the rendered
model and the observed depth agree to the sensor's noise. On a real RGB-D frame the annotated
ground truth itself disagrees with the depth by several millimetres (measured at the annotated
poses of the real LM-O frame: median absolute depth residual 3.2 % of the diameter against 0.8 %
on synthetic images of the same meshes, 10 % of the pixels more than 5 % behind the model
against 1 %), because the depth camera's calibration, its registration to the colour camera
and the annotation are each a little off. A model that never saw that rates right poses on real
frames as wrong. `Realism` draws these errors per image and per object so that a synthetic
dataset carries them (`perception-config synth --realism`):

- per image: a depth offset (uniform, +-`depth_bias_mm`, 4 mm), a depth scale error (uniform,
  1 +- `depth_scale`, 0.5 %), a smooth depth warp (a 4 x 3 grid of uniform values upsampled,
  amplitude `warp_mm`, 2 mm: the calibration's residue), a misregistration of depth against colour
  (whole pixels, +-`shift_px`, 2), and the sensor model's depth noise x `noise_scale` (0.7-2.0);
- per object: an annotation error: the written ground truth is the true pose rotated by a
  Gaussian axis-angle of `annotation_deg` (1 deg) per axis and moved by `annotation_mm` (2 mm)
  per axis.

Every image gets errors drawn over the full ranges. Drawn with a random quality instead (most
images better calibrated than the ranges' limits), the verifier trained on them ranked the real
LM-O frame's hypotheses better but calibrated them worse (docs: Results, "The learned
pick-success score").

The ranges are those of consumer structured-light and stereo cameras after a factory calibration
(a few millimetres at 1 m) and of BOP's annotation accuracy (a few millimetres); they are
randomised, not fitted to any frame. Every draw comes from a generator of its own (seeded by the
dataset's seed, scene and image), so a dataset without `--realism` is the same bytes as before.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.geometry import Pose, exp_so3


@dataclass(frozen=True)
class Realism:
    """Ranges of the errors a real cell adds (module docstring); lengths in mm, angles in degrees."""

    depth_bias_mm: float = 4.0
    depth_scale: float = 0.005
    warp_mm: float = 2.0
    shift_px: int = 2
    noise_scale: tuple[float, float] = (0.7, 2.0)
    annotation_deg: float = 1.0
    annotation_mm: float = 2.0

    def __post_init__(self) -> None:
        for name in ("depth_bias_mm", "depth_scale", "warp_mm", "annotation_deg", "annotation_mm"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise ValueError(f"Realism.{name} must be a finite number >= 0, got {value!r}")
        if int(self.shift_px) != self.shift_px or self.shift_px < 0:
            raise ValueError(f"Realism.shift_px must be an integer >= 0, got {self.shift_px!r}")
        lo, hi = self.noise_scale
        if not (0 < lo <= hi and np.isfinite(hi)):
            raise ValueError(f"Realism.noise_scale must be 0 < low <= high, got {self.noise_scale!r}")


def draw_noise_scale(rng: np.random.Generator, r: Realism) -> float:
    """The image's factor on the sensor model's depth noise."""
    return float(rng.uniform(*r.noise_scale))


def miscalibrate_depth(depth: np.ndarray, rng: np.random.Generator, r: Realism) -> np.ndarray:
    """The float depth image (H, W) in metres (NaN = missing) as a miscalibrated camera reports
    it: scaled, offset, smoothly warped, then shifted by whole pixels against the colour image
    (the pixels shifted in from outside are missing)."""
    import cv2

    d = np.asarray(depth, dtype=np.float32)
    H, W = d.shape
    scale = 1.0 + rng.uniform(-r.depth_scale, r.depth_scale)
    bias = rng.uniform(-r.depth_bias_mm, r.depth_bias_mm) * 1e-3
    grid = rng.uniform(-1.0, 1.0, size=(3, 4)).astype(np.float32)
    warp = cv2.resize(grid, (W, H), interpolation=cv2.INTER_CUBIC) * np.float32(r.warp_mm * 1e-3)
    out = d * np.float32(scale) + np.float32(bias) + warp
    s = int(r.shift_px)
    dx, dy = (int(v) for v in rng.integers(-s, s + 1, size=2)) if s else (0, 0)
    if dx or dy:
        shifted = np.full_like(out, np.nan)
        ys, yd = (slice(0, H - dy), slice(dy, H)) if dy >= 0 else (slice(-dy, H), slice(0, H + dy))
        xs, xd = (slice(0, W - dx), slice(dx, W)) if dx >= 0 else (slice(-dx, W), slice(0, W + dx))
        shifted[yd, xd] = out[ys, xs]
        out = shifted
    return out.astype(np.float32)


def annotation_error(pose: Pose, rng: np.random.Generator, r: Realism) -> Pose:
    """`pose` (model to camera) as an annotator would write it: rotated about the model's origin
    by a Gaussian axis-angle of `annotation_deg` per axis and moved by `annotation_mm` per axis."""
    w = rng.normal(0.0, np.radians(r.annotation_deg), size=3)
    dt = rng.normal(0.0, r.annotation_mm * 1e-3, size=3)
    return Pose(pose.R @ exp_so3(w), pose.t + dt)
