"""Episodes of a BOP dataset: the (frame, object) pairs an agent trains and is evaluated on.

Image ids are split randomly (seeded) into disjoint train and test sets, so evaluation never
sees a frame the agent trained on. Objects that are barely visible (visib_fract below a
threshold) are not episodes: no operator could find them and no robot could pick them.
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.scene import Frame
from ..datasets.bop import BopDataset
from .operators import Episode

ImageKey = tuple[int, int]  # scene_id, im_id
DEFAULT_TEST_FRACTION = 0.3  # share of the image ids held out for evaluation
DEFAULT_SPLIT_SEED = 0
DEFAULT_VALIDATE_EVERY = 250  # training episodes between two validation checks (learning/validation.py)


def split_image_keys(keys: list[ImageKey], test_fraction: float = DEFAULT_TEST_FRACTION,
                     seed: int = DEFAULT_SPLIT_SEED) -> tuple[list[ImageKey], list[ImageKey]]:
    """Disjoint (train, test) image keys, a seeded random split; both non-empty when len >= 2."""
    if not 0.0 < test_fraction < 1.0:
        raise ValueError(f"test_fraction must be in (0, 1), got {test_fraction}")
    keys = sorted(set(keys))
    if len(keys) < 2:
        raise ValueError(f"a train/test split needs at least 2 images, the dataset has {len(keys)}")
    order = np.random.default_rng(seed).permutation(len(keys))
    n_test = min(len(keys) - 1, max(1, int(round(test_fraction * len(keys)))))
    test = sorted(keys[i] for i in order[:n_test])
    train = sorted(keys[i] for i in order[n_test:])
    return train, test


@dataclass(frozen=True)
class EpisodeKey:
    scene_id: int
    im_id: int
    index: int  # position of the object in the frame's object list (instances may repeat obj ids)
    obj_id: int


class EpisodeSource:
    """The episodes of some images of a dataset, with a small cache of loaded frames."""

    def __init__(
        self, dataset: BopDataset | str | Path, keys: list[ImageKey] | None = None,
        min_visib_fract: float = 0.3, frame_cache_size: int = 8,
    ) -> None:
        self.dataset = dataset if isinstance(dataset, BopDataset) else BopDataset(Path(dataset))
        self.image_keys = sorted(keys) if keys is not None else self.dataset.image_keys()
        self._frames: OrderedDict[ImageKey, Frame] = OrderedDict()
        self._frame_cache_size = frame_cache_size
        self.episodes: list[EpisodeKey] = []
        for scene_id, im_id in self.image_keys:
            gt = self.dataset.gt(scene_id, im_id)
            info = self.dataset.gt_info(scene_id, im_id)
            for i, (obj_id, _pose) in enumerate(gt):
                visib = info[i].get("visib_fract", 1.0) if info else 1.0
                if visib >= min_visib_fract:
                    self.episodes.append(EpisodeKey(scene_id, im_id, i, obj_id))
        if not self.episodes:
            raise ValueError(
                f"dataset {self.dataset.root} has no usable episodes in {len(self.image_keys)} images "
                f"(objects with visib_fract >= {min_visib_fract})"
            )

    def __len__(self) -> int:
        return len(self.episodes)

    def frame(self, scene_id: int, im_id: int) -> Frame:
        key = (scene_id, im_id)
        frame = self._frames.get(key)
        if frame is None:
            frame = self.dataset.load_frame(scene_id, im_id)
            self._frames[key] = frame
            while len(self._frames) > self._frame_cache_size:
                self._frames.popitem(last=False)
        self._frames.move_to_end(key)
        return frame

    def load(self, index: int, noise_lambda: float, seed: int) -> Episode:
        ek = self.episodes[index]
        frame = self.frame(ek.scene_id, ek.im_id)
        obj = frame.objects[ek.index]
        if obj.model is None:
            raise ValueError(f"object {ek.obj_id} of scene {ek.scene_id} image {ek.im_id} has no model")
        return Episode(frame, obj.model, obj.gt, float(noise_lambda), int(seed), (ek.scene_id, ek.im_id, ek.obj_id))
