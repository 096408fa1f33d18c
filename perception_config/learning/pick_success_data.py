"""Training data of the learned pick-success score: step rows, their labels and features.

A step row is one hypothesis an episode held (the shape `EpisodeStore.iter_steps()` yields:
`episode_dataset`, `episode_scene_id`, `episode_im_id` (or `episode_frame_stamp_ns`: a frame the
configurator kept, store/frames.py), `episode_obj_id`, `pose` {"R", "t"}, `scores`, `picked`,
`pick_source`, ...). Rows come from the episode store (`load_step_rows`)
or are played here with a random masked policy (`collect_step_rows`, for a dataset without a
store). `featurise` turns rows into a FeatureTable: the frame of each row is read from its
dataset, the features of vision/pick_features.py computed at the row's pose, and the label
recomputed from the dataset's ground truth with the pick criterion (blocks/pick.py's default:
symmetry-aware MSSD <= 0.1 x diameter), so every stored hypothesis is labelled, not only the
picked ones; a stored pick outcome, where there is one, is the label of its row (a robot's
answer wins over the simulation). An object id that occurs more than once in a frame is
labelled against the nearest of its instances (a pick of any of them succeeds). Duplicate
hypotheses (an action that failed and left the pose as it was) are one row.
Rows of a frame with depth are also added RGB-only (the depth features blanked): one model
then serves RGB-D and RGB-only frames, and knows what the missing depth means.
The features of a hypothesis are kept per process (`FeatureMemo`: keyed by the frame's pixels
and intrinsics, the model instance and the pose), so the learner's next cycle, which featurises
the same stored hypotheses again plus the new ones, computes only the new ones.
"""
from __future__ import annotations

import hashlib
import math
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from ..blocks.features import pick_features
from ..blocks.pick import SimulatedPick
from ..core.geometry import Pose
from ..core.metrics import pose_mssd, pose_mssd_derived
from ..core.pose_json import pose_arrays, pose_from_json, pose_json
from ..datasets.bop import BopDataset
from ..vision.pick_features import FEATURE_NAMES, rgb_only
from ..vision.verifier_crop import without_depth

# the pick criterion: MSSD <= this x diameter, SimulatedPick's default (blocks/pick.py), read from the block
PICK_MSSD_SHARE = float(next(p.default for p in SimulatedPick.params if p.name == "mssd_threshold"))
DEFAULT_COLLECT_LAMBDAS = (0.1, 0.3, 0.5, 0.7, 1.0)
CANDIDATES_PER_CALL = 8  # collect_candidate_rows: the first this many ranked candidates of a call


def load_step_rows(store_path: str | Path, busy_timeout: float | None = None) -> list[dict[str, Any]]:
    """Every step row with a pose from the episode store at `store_path` (`busy_timeout`: seconds
    to wait for a writer's lock, the store's default when None)."""
    path = Path(store_path)
    if not path.is_file():
        raise FileNotFoundError(f"episode store {path} does not exist")
    from ..store.episode_store import EpisodeStore

    kw = {} if busy_timeout is None else {"busy_timeout": busy_timeout}
    with EpisodeStore(path, readonly=True, **kw) as store:
        return [row for row in store.iter_steps() if row.get("pose") is not None]


def collect_step_rows(dataset: str | Path, n_episodes: int, lambdas: Sequence[float] = DEFAULT_COLLECT_LAMBDAS,
                      seed: int = 0, max_steps: int = 8, pipeline: Any = None, use_depth: bool = True,
                      progress: bool = True, image_keys: Sequence[tuple[int, int]] | None = None,
                      ) -> list[dict[str, Any]]:
    """Play `n_episodes` episodes of `dataset` (the images `image_keys`, default every image; give
    the train images of the split an agent is evaluated on, so its test images stay unseen)
    in-process with a random masked policy (uniform over the actions the frame allows, at most
    `max_steps` actions, ended by a successful pick), lambda drawn from `lambdas`; one row per
    hypothesis, in the store's shape. Seeded and in the env's cost-table mode: the same call gives
    the same rows on any machine load."""
    from tqdm import tqdm

    from ..rl.env import PerceptionConfigEnv

    if n_episodes < 1:
        raise ValueError(f"the number of episodes must be >= 1, got {n_episodes}")
    lambdas = [float(x) for x in lambdas]
    if not lambdas or not all(math.isfinite(x) and x >= 0 for x in lambdas):
        raise ValueError(f"lambdas must be finite numbers >= 0, got {lambdas}")
    root = Path(dataset)
    # cost-table mode: no wall-clock bound cuts a block short, so the rows do not depend on the load
    env = PerceptionConfigEnv(root, pipeline, split="test", use_depth=use_depth, max_ops=max(1, max_steps),
                              time_mode="cost_table", image_keys=None if image_keys is None else list(image_keys))
    rng = np.random.default_rng(seed)
    rows: list[dict[str, Any]] = []
    for ep in tqdm(range(n_episodes), desc="collect episodes", disable=not progress, unit="ep"):
        index = int(rng.integers(len(env.source)))
        lam = float(lambdas[int(rng.integers(len(lambdas)))])
        _, info = env.reset(options={"episode": index, "lambda": lam, "episode_seed": int(rng.integers(2**31))})
        scene_id, im_id, obj_id = env.episode.key
        base = {"episode_id": ep, "episode_dataset": str(root), "episode_scene_id": scene_id,
                "episode_im_id": im_id, "episode_obj_id": obj_id, "episode_noise_lambda": lam}
        for step in range(max_steps + 1):
            picked = info.get("picked") if step else None
            rows.append({**base, "step": step, "action": info["action"], "ok": bool(info["ok"]),
                         "scores": dict(info["scores"]),
                         "pose": pose_arrays(pose_json(info["pose"])),
                         "picked": None if picked is None else int(bool(picked)),
                         "pick_source": None if picked is None else "simulated"})
            if step == max_steps or (picked is not None and picked):
                break
            allowed = np.flatnonzero(info["action_mask"]) if info.get("action_mask") is not None else None
            choices = allowed if allowed is not None and len(allowed) else np.arange(len(env.action_names))
            _, _, terminated, truncated, info = env.step(int(rng.choice(choices)))
    return rows


def collect_candidate_rows(dataset: str | Path, pipeline: Any = None,
                           image_keys: Sequence[tuple[int, int]] | None = None,
                           per_call: int = CANDIDATES_PER_CALL, min_visib: float = 0.3, seed: int = 0,
                           use_depth: bool = True, progress: bool = True) -> list[dict[str, Any]]:
    """The ranked candidates (the first `per_call`) of every ground-truth-free generator of
    `pipeline` (its generator and actions of kind generation that need no ground truth, with its
    parameters; default the cell's) on every annotated object (visib_fract >= `min_visib`) of
    the images `image_keys` (default all) of `dataset`: one row per candidate, in the store's
    shape. They hold the generators' own mistakes (a box half a turn away, a part placed on its
    neighbour), the hard cases a verifier must learn to refuse. Seeded; the generators run within
    their wall-clock budgets, so a loaded machine gives fewer candidates."""
    from tqdm import tqdm

    from ..bench.generators import pipeline_params
    from ..blocks.base import GROUND_TRUTH, BlockInput, Kind, create
    from ..blocks.pipeline import load_pipeline

    pipe = pipeline if pipeline is not None and not isinstance(pipeline, (str, Path)) else load_pipeline(
        pipeline or "cell")
    params = pipeline_params(pipe)
    names = [b.name for b in [pipe.generator] + [a.block for a in pipe.actions]
             if b.kind == Kind.GENERATION and GROUND_TRUTH not in b.inputs]
    blocks = [create(n, **params.get(n, {})) for n in dict.fromkeys(names)]
    ds = BopDataset(Path(dataset), "test", use_depth=use_depth)
    keys = list(image_keys) if image_keys is not None else ds.image_keys()
    rows: list[dict[str, Any]] = []
    for scene_id, im_id in tqdm(keys, desc="generator candidates", disable=not progress, unit="image"):
        frame = ds.load_frame(scene_id, im_id)
        cache: dict = {}
        for index, o in enumerate(frame.objects):
            if o.gt is None or o.model is None or (o.visib_fract is not None and o.visib_fract < min_visib):
                continue
            for block in blocks:
                if block.frame_lacks(frame):
                    continue
                rng = np.random.default_rng([seed, scene_id, im_id, index])
                r = block(BlockInput(frame=frame, model=o.model, rng=rng, cache=cache))
                for _, pose in r.candidates[:per_call]:
                    rows.append({"episode_id": -1, "episode_dataset": str(dataset), "episode_scene_id": scene_id,
                                 "episode_im_id": im_id, "episode_obj_id": o.obj_id, "episode_noise_lambda": None,
                                 "action": block.name, "pose": pose_arrays(pose_json(pose)), "picked": None,
                                 "pick_source": None})
    return rows


@dataclass
class FeatureTable:
    """Features (n, F) float64 with NaN for missing, labels, and where each row came from."""

    X: np.ndarray
    y: np.ndarray  # (n,) bool: the pick succeeds
    images: list[tuple[str, int, int]]  # (dataset, scene_id, im_id) of each row: the split unit
    rgb_only: np.ndarray  # (n,) bool: the row's depth features are blanked (an RGB-only frame or copy)
    mssd_share: np.ndarray  # (n,) MSSD / diameter (NaN when the label is a stored pick outcome only)
    noise_lambda: np.ndarray  # (n,) the episode's lambda (NaN when unknown)
    feature_names: tuple[str, ...] = FEATURE_NAMES
    crops: np.ndarray | None = None  # (n, C, CROP, CROP) float16: each row's crop (featurise(crops=True))

    def __len__(self) -> int:
        return int(len(self.y))

    def subset(self, keep: np.ndarray) -> "FeatureTable":
        idx = np.flatnonzero(keep)
        return FeatureTable(self.X[idx], self.y[idx], [self.images[i] for i in idx], self.rgb_only[idx],
                            self.mssd_share[idx], self.noise_lambda[idx], self.feature_names,
                            None if self.crops is None else self.crops[idx])

    def inputs(self, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """(features, crops or None) of the rows `keep` (a mask or indices): a model's input."""
        return self.X[keep], None if self.crops is None else self.crops[keep]


def pick_label(model: Any, pose: Pose, ground_truths: Iterable[Pose], symmetries: str = "declared"
               ) -> tuple[bool, float]:
    """(picks, MSSD / diameter) of `pose` against the nearest of the instances' ground truths;
    `symmetries`: "declared" (the simulated pick's) or "derived" (the model's declared ones, or
    where it declares none those of its surface: a flip of a nearly symmetric box is right)."""
    if symmetries not in ("declared", "derived"):
        raise ValueError(f"symmetries must be 'declared' or 'derived', got {symmetries!r}")
    err = pose_mssd if symmetries == "declared" else pose_mssd_derived
    share = min((err(pose, gt, model) / model.diameter for gt in ground_truths), default=math.inf)
    return bool(share <= PICK_MSSD_SHARE), float(share)


def _dedupe(rows: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per (image, object, pose); a stored pick outcome of a duplicate is kept."""
    seen: dict[tuple, dict[str, Any]] = {}
    for row in rows:
        if row.get("pose") is None:
            continue
        p = row["pose"]
        key = (str(row.get("episode_dataset")), row.get("episode_scene_id"), row.get("episode_im_id"),
               row.get("episode_frame_stamp_ns"), int(row["episode_obj_id"]),
               np.asarray(p["R"], float).round(9).tobytes(), np.asarray(p["t"], float).round(9).tobytes())
        if key not in seen:
            seen[key] = dict(row)
        elif row.get("picked") is not None and (seen[key].get("picked") is None or (
                row.get("pick_source") == "robot" and seen[key].get("pick_source") != "robot")):
            seen[key]["picked"], seen[key]["pick_source"] = row["picked"], row.get("pick_source")
    return list(seen.values())


class FeatureMemo:
    """The features of hypotheses already featurised in this process (least recently used
    dropped beyond `size`). Features are a deterministic function of the frame's images and
    intrinsics, the model and the pose (vision/pick_features.py), so a kept entry is what
    `pick_features` would compute again."""

    def __init__(self, size: int = 50_000) -> None:
        self.size = int(size)
        self._entries: OrderedDict[tuple, tuple[Any, np.ndarray]] = OrderedDict()

    @staticmethod
    def frame_key(frame: Any) -> bytes:
        h = hashlib.blake2b(digest_size=16)
        for a in (frame.rgb, frame.depth, frame.K):
            if a is None:
                h.update(b"none")
                continue
            a = np.ascontiguousarray(a)
            h.update(f"{a.dtype.str}{a.shape}".encode())
            h.update(a.data)
        return h.digest()

    def features(self, frame: Any, frame_key: bytes, model: Any, pose: Pose, cache: dict) -> dict[str, float]:
        """pick_features(frame, model, pose, cache), from the memo when it was computed before.
        `model` keys by identity: models are shared, prepared instances (core/models.load_model)."""
        key = (frame_key, id(model), model.obj_id, np.asarray(pose.R, np.float64).tobytes(),
               np.asarray(pose.t, np.float64).tobytes())
        kept = self._entries.get(key)
        if kept is not None and kept[0] is model:
            self._entries.move_to_end(key)
            return dict(zip(FEATURE_NAMES, kept[1].tolist()))
        f = pick_features(frame, model, pose, cache)
        self._entries[key] = (model, np.array([f[n] for n in FEATURE_NAMES], np.float64))
        while len(self._entries) > self.size:
            self._entries.popitem(last=False)
        return f


FEATURES = FeatureMemo()


class _ImageSource:
    """The frame and the object instances (model, ground truths) of one row's image."""

    def __init__(self, dataset: str | Path | None, frames_dir: str | Path | None, models_dir: str | Path | None):
        self.dataset = dataset
        self.frames_dir = Path(frames_dir) if frames_dir is not None else None
        self.models_dir = models_dir
        self._datasets: dict[str, BopDataset] = {}
        self._models: Any = None

    def key(self, row: dict[str, Any]) -> tuple[str, int, int] | None:
        """(dataset, scene_id, im_id) of a dataset image, ("frames:<dir>", -1, stamp_ns) of a kept
        frame (the configurator's estimates, store/frames.py), None when neither is known."""
        if row.get("episode_im_id") is not None and row.get("episode_scene_id") is not None:
            root = str(self.dataset) if self.dataset is not None else str(row.get("episode_dataset"))
            return root, int(row["episode_scene_id"]), int(row["episode_im_id"])
        if row.get("episode_frame_stamp_ns") is not None and self.frames_dir is not None:
            return f"frames:{self.frames_dir}", -1, int(row["episode_frame_stamp_ns"])
        return None

    def load(self, key: tuple[str, int, int], obj_ids: set[int]
             ) -> tuple[Any, dict[int, tuple[Any, list[Pose]]]] | None:
        """The frame and, per object id, (model, ground-truth poses); None when a kept frame is gone."""
        root, scene_id, im_id = key
        if scene_id < 0:
            from ..datasets.bop_models import ModelFolder
            from ..store.frames import frame_path, load_frame

            path = frame_path(self.frames_dir, im_id)
            if not path.exists():
                return None  # pruned from the ring: its rows cannot be featurised
            frame, gt = load_frame(path)  # ValueError naming the file
            if self._models is None:
                if self.models_dir is None:
                    raise ValueError("the step rows name kept frames (the configurator's estimates): pass the "
                                     "models folder their objects come from")
                self._models = ModelFolder(self.models_dir)
            return frame, {i: (self._models.model(str(i)), [gt[i]] if i in gt else []) for i in obj_ids}
        if root not in self._datasets:
            if not (Path(root) / "models").is_dir():
                raise FileNotFoundError(f"the step rows name dataset {root!r}, which is not a BOP dataset folder "
                                        f"here (pass the dataset's folder)")
            self._datasets[root] = BopDataset(Path(root))
        frame = self._datasets[root].load_frame(scene_id, im_id)
        out: dict[int, tuple[Any, list[Pose]]] = {}
        for obj_id in obj_ids:
            instances = [o for o in frame.objects if o.obj_id == obj_id and o.model is not None]
            if not instances:
                raise ValueError(f"{root} scene {scene_id} image {im_id} has no object {obj_id} with a model")
            out[obj_id] = (instances[0].model, [o.gt for o in instances if o.gt is not None])
        return frame, out


def featurise(rows: Iterable[dict[str, Any]], dataset: str | Path | None = None, with_rgb_only: bool = True,
              progress: bool = True, frames_dir: str | Path | None = None,
              models_dir: str | Path | None = None, crops: bool = False,
              symmetries: str = "declared") -> FeatureTable:
    """The FeatureTable of step rows (module docstring). `dataset` replaces the rows' own
    `episode_dataset` (a store written on another machine names its path there). Rows of the
    configurator's estimates name a kept frame by stamp instead of an image: they are read from
    `frames_dir` (store/frames.py) with their objects' models from `models_dir`, labelled by the
    frame's ground truth when it came with one, else by a stored pick outcome alone (a robot
    cell: only the picked hypotheses are labelled); rows with neither, or whose frame was pruned,
    are left out. `crops`: each row's crop too (vision/verifier_crop.py; for a model with a crop
    branch). `symmetries`: of the label (pick_label)."""
    from tqdm import tqdm

    from ..blocks.features import hypothesis_crop

    rows = _dedupe(rows)
    if not rows:
        raise ValueError("no step rows with a hypothesis pose to learn from")
    source = _ImageSource(dataset, frames_dir, models_dir)
    groups: dict[tuple[str, int, int], list[dict[str, Any]]] = {}
    for row in rows:
        key = source.key(row)
        if key is not None:
            groups.setdefault(key, []).append(row)
    X, y, images, blank, share, lams, crop_rows = [], [], [], [], [], [], []
    bar = tqdm(total=len(rows), desc="features", disable=not progress, unit="pose")
    for key, group in groups.items():
        loaded = source.load(key, {int(r["episode_obj_id"]) for r in group})
        if loaded is None:
            bar.update(len(group))
            continue
        frame, objects = loaded
        cache: dict[str, Any] = {}
        frame_key = FEATURES.frame_key(frame)
        for row in group:
            bar.update(1)
            model, truths = objects[int(row["episode_obj_id"])]
            pose = pose_from_json(row["pose"])
            if not pose.is_valid():
                continue
            label, mssd = pick_label(model, pose, truths, symmetries) if truths else (None, math.nan)
            if row.get("picked") is not None:
                label = bool(row["picked"])
            if label is None:
                continue  # no ground truth and no pick outcome: nothing to learn from this row
            f = FEATURES.features(frame, frame_key, model, pose, cache)
            lam = row.get("episode_noise_lambda")
            variants = [(f, frame.depth is None)]
            if with_rgb_only and frame.depth is not None:
                variants.append((rgb_only(f), True))
            crop = hypothesis_crop(frame, model, pose, cache).astype(np.float16) if crops else None
            for feats, is_rgb in variants:
                if crop is not None:
                    crop_rows.append(without_depth(crop) if is_rgb else crop)
                X.append([feats[n] for n in FEATURE_NAMES])
                y.append(label)
                images.append(key)
                blank.append(is_rgb)
                share.append(mssd)
                lams.append(float(lam) if lam is not None else math.nan)
    bar.close()
    if not X:
        raise ValueError("no step row has a valid hypothesis pose with a label (ground truth or a pick outcome)")
    return FeatureTable(np.asarray(X, float), np.asarray(y, bool), images, np.asarray(blank, bool),
                        np.asarray(share, float), np.asarray(lams, float),
                        crops=np.stack(crop_rows) if crops else None)


__all__ = ["load_step_rows", "collect_step_rows", "featurise", "pick_label", "FeatureTable", "FeatureMemo",
           "PICK_MSSD_SHARE"]
