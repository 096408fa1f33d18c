"""A camera frame and the objects in it, in the units used inside the code."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from .geometry import Pose

if TYPE_CHECKING:  # core/models.py imports heavy libraries; only the type is needed here
    from .models import ObjectModel


@dataclass
class SceneObject:
    """One object instance in a frame; `gt` is its ground-truth pose when known."""

    obj_id: int
    gt: Pose | None = None
    model: "ObjectModel | None" = None
    visib_fract: float | None = None
    bbox_visib: tuple[int, int, int, int] | None = None  # x, y, w, h in pixels


@dataclass
class Frame:
    """A camera frame: rgb uint8 HxWx3, depth float32 metres (NaN = missing pixel) or None for
    an RGB-only camera (no depth sensor at all), K 3x3.

    `stamp` is seconds (float) on the recording's clock; `scene_id`/`im_id` name the
    BOP image it came from, when it came from one.
    """

    rgb: np.ndarray
    depth: np.ndarray | None
    K: np.ndarray
    stamp: float = 0.0
    scene_id: int = 0
    im_id: int = 0
    objects: list[SceneObject] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        if self.rgb.ndim != 3 or self.rgb.shape[2] != 3 or self.rgb.dtype != np.uint8:
            raise ValueError(f"rgb must be uint8 HxWx3, got {self.rgb.dtype} {self.rgb.shape}")
        if self.depth is None:
            return
        if self.depth.ndim != 2 or self.depth.dtype != np.float32:
            raise ValueError(f"depth must be float32 HxW metres, got {self.depth.dtype} {self.depth.shape}")
        if self.rgb.shape[:2] != self.depth.shape:
            raise ValueError(f"rgb {self.rgb.shape[:2]} and depth {self.depth.shape} differ in size")

    @property
    def has_depth(self) -> bool:
        return self.depth is not None

    @property
    def height(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def width(self) -> int:
        return int(self.rgb.shape[1])

    def object(self, obj_id: int) -> SceneObject:
        for o in self.objects:
            if o.obj_id == obj_id:
                return o
        raise KeyError(f"object {obj_id} is not in frame scene {self.scene_id} image {self.im_id}")
