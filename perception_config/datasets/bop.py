"""Read and write datasets in the BOP layout, converting millimetres to metres at the boundary.

Layout (bop_toolkit docs/bop_datasets_format.md):

    root/models[_eval|_cad]/models_info.json, obj_XXXXXX.ply      (mm)
    root/<split>/<scene 6 digits>/scene_camera.json                cam_K, depth_scale, [cam_R_w2c, cam_t_w2c mm]
                                 /scene_gt.json                    cam_R_m2c (row-major), cam_t_m2c (mm), obj_id
                                 /scene_gt_info.json               bbox_obj, bbox_visib, px_count_*, visib_fract
                                 /rgb/<im 6 digits>.png|jpg, depth/<im>.png (uint16 * depth_scale = mm)

Inside the code everything is metres (poses, depth, model vertices, diameters); `models_info`
stays in mm as BOP defines it (core/models.py converts it when preparing a model). Bad input raises
`BopFormatError` (a ValueError) or FileNotFoundError with the offending file in the message:
a reader never returns silently wrong data, so a wrong depth_scale fails loudly rather than
putting every object ten times too far away.

`BopDataset` reads a dataset split; the files it reads have their own modules: bop_json.py (JSON
files and the checks of their values), bop_models.py (models folder), bop_scene.py (a scene's
JSON files), bop_images.py (rgb and depth images). Writing: bop_writer.py (`SceneWriter`,
`write_frame`, `compute_gt_info`); results: bop_results.py (the results CSV).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Iterator

from ..core.geometry import Pose
from ..core.models import ObjectModel, load_model
from ..core.scene import Frame, SceneObject
from .bop_images import RGB_EXTS, read_depth, read_rgb
from .bop_json import finite_numbers, load_json, short_ids
from .bop_models import load_models_info, model_path
from .bop_scene import CameraInfo, check_depth_scale, load_scene_camera, load_scene_gt, load_scene_gt_info, scene_dir
from .errors import BopFormatError

DEFAULT_FRAME_RATE = 10.0  # Hz: stamps of BOP frames without timing are im_id / rate


class BopDataset:
    """A BOP dataset split: scenes, images, frames in metres, and its object models.

    Scene JSON files are read once per scene and kept; models are prepared once (core/models.py
    caches them per file). Frames get stamp = im_id / frame_rate (BOP has no timing)."""

    def __init__(
        self,
        root: str | os.PathLike,
        split: str = "test",
        models_subdir: str = "models",
        frame_rate: float = DEFAULT_FRAME_RATE,
        use_depth: bool = True,
    ) -> None:
        self.root = Path(root)
        self.use_depth = bool(use_depth)  # False: read as RGB-only even where depth exists
        self.split = split
        self.models_dir = self.root / models_subdir
        self.frame_rate = float(frame_rate)
        if not self.root.is_dir():
            raise FileNotFoundError(f"BOP dataset folder not found: {self.root}")
        self.split_dir = self.root / split
        if not self.split_dir.is_dir():
            raise FileNotFoundError(f"BOP split folder not found: {self.split_dir}")
        self._scenes: dict[int, tuple[dict[int, CameraInfo], dict[int, list] | None, dict[int, list] | None]] = {}
        self._models: dict[int, ObjectModel] = {}
        self._models_info: dict[int, dict[str, Any]] | None = None
        self._default_scale: float | None | bool = False  # False = not looked up yet

    def __repr__(self) -> str:
        return f"BopDataset(root={str(self.root)!r}, split={self.split!r}, models={self.models_dir.name!r})"

    def __len__(self) -> int:
        return len(self.image_keys())

    # --- index
    def scene_ids(self) -> list[int]:
        return sorted(int(p.name) for p in self.split_dir.iterdir() if p.is_dir() and p.name.isdigit())

    def image_ids(self, scene_id: int) -> list[int]:
        return sorted(self._scene(scene_id)[0])

    def image_keys(self) -> list[tuple[int, int]]:
        return [(s, i) for s in self.scene_ids() for i in self.image_ids(s)]

    def _scene(self, scene_id: int) -> tuple[dict[int, CameraInfo], dict[int, list] | None, dict[int, list] | None]:
        if scene_id not in self._scenes:
            d = scene_dir(self.root, self.split, scene_id)
            if not d.is_dir():
                raise FileNotFoundError(f"BOP scene folder not found: {d} (scenes: {self.scene_ids()})")
            cams = load_scene_camera(d / "scene_camera.json")
            gts = load_scene_gt(d / "scene_gt.json") if (d / "scene_gt.json").exists() else None
            infos = load_scene_gt_info(d / "scene_gt_info.json") if (d / "scene_gt_info.json").exists() else None
            self._scenes[scene_id] = (cams, gts, infos)
        return self._scenes[scene_id]

    def _image_file(self, scene_id: int, im_id: int, what: str) -> Path:
        d = scene_dir(self.root, self.split, scene_id)
        if what == "depth":
            return d / "depth" / f"{im_id:06d}.png"
        for sub in ("rgb", "gray"):
            for ext in RGB_EXTS:
                p = d / sub / f"{im_id:06d}{ext}"
                if p.exists():
                    return p
        raise FileNotFoundError(f"BOP rgb image not found: {d / 'rgb' / f'{im_id:06d}.png'} (nor .jpg, gray/)")

    def camera(self, scene_id: int, im_id: int) -> CameraInfo:
        cams = self._scene(scene_id)[0]
        if im_id not in cams:
            path = scene_dir(self.root, self.split, scene_id) / "scene_camera.json"
            raise BopFormatError(f"{path}: no image {im_id} (images: {short_ids(sorted(cams))})")
        return cams[im_id]

    def gt(self, scene_id: int, im_id: int) -> list[tuple[int, Pose]]:
        """Ground-truth (obj_id, Pose) of an image; [] for a split without scene_gt.json."""
        self.camera(scene_id, im_id)
        gts = self._scene(scene_id)[1]
        if gts is None:
            return []
        if im_id not in gts:
            path = scene_dir(self.root, self.split, scene_id) / "scene_gt.json"
            raise BopFormatError(f"{path}: no entry for image {im_id}, which scene_camera.json lists")
        return gts[im_id]

    def gt_info(self, scene_id: int, im_id: int) -> list[dict[str, Any]] | None:
        """scene_gt_info entries of an image (aligned with `gt`), None when the file is absent."""
        infos = self._scene(scene_id)[2]
        if infos is None:
            return None
        path = scene_dir(self.root, self.split, scene_id) / "scene_gt_info.json"
        if im_id not in infos:
            raise BopFormatError(f"{path}: no entry for image {im_id}")
        n = len(self.gt(scene_id, im_id))
        if len(infos[im_id]) != n:
            raise BopFormatError(f"{path}: image {im_id} has {len(infos[im_id])} entries but scene_gt.json {n}")
        return infos[im_id]

    def has_depth(self, scene_id: int, im_id: int) -> bool:
        """Whether the image has depth: the scene has a depth/ folder (BOP's RGB-only
        datasets and splits have none) and the reader was not told to drop it. A scene with
        a depth/ folder that lacks this image's file is an error, not an RGB-only image."""
        if not self.use_depth:
            return False
        return (scene_dir(self.root, self.split, scene_id) / "depth").is_dir()

    def _depth_scale(self, scene_id: int, im_id: int) -> float:
        scale = self.camera(scene_id, im_id).depth_scale
        if scale is not None:
            return scale
        if self._default_scale is False:  # dataset-wide camera.json may carry it
            cam_json = self.root / "camera.json"
            self._default_scale = None
            if cam_json.exists():
                c = load_json(cam_json)
                if isinstance(c, dict) and c.get("depth_scale") is not None:
                    self._default_scale = float(finite_numbers(cam_json, "depth_scale", c["depth_scale"], 1)[0])
                    check_depth_scale(cam_json, self._default_scale, "camera")
        if self._default_scale is None:
            path = scene_dir(self.root, self.split, scene_id) / "scene_camera.json"
            raise BopFormatError(f"{path}: image {im_id} has no depth_scale (nor has {self.root / 'camera.json'})")
        return float(self._default_scale)

    # --- models
    @property
    def models_info(self) -> dict[int, dict[str, Any]]:
        """models_info.json of the models folder (mm); {} when the file is absent."""
        if self._models_info is None:
            p = self.models_dir / "models_info.json"
            self._models_info = load_models_info(p) if p.exists() else {}
        return self._models_info

    def obj_ids(self) -> list[int]:
        if self.models_info:
            return sorted(self.models_info)
        return sorted(int(p.stem[4:]) for p in self.models_dir.glob("obj_*.ply") if p.stem[4:].isdigit())

    def model(self, obj_id: int) -> ObjectModel:
        """The prepared model of an object (metres), cached."""
        if obj_id not in self._models:
            path = model_path(self.models_dir, obj_id)
            info = self.models_info.get(obj_id)
            if self.models_info and info is None:
                raise BopFormatError(
                    f"{self.models_dir / 'models_info.json'}: unknown object id {obj_id} "
                    f"(known: {short_ids(sorted(self.models_info))})"
                )
            if not path.exists():
                raise BopFormatError(f"unknown object id {obj_id}: no model file {path}")
            self._models[obj_id] = load_model(path, obj_id, info)
        return self._models[obj_id]

    # --- frames
    def load_frame(self, scene_id: int, im_id: int, with_models: bool = True) -> Frame:
        """The frame of one image: rgb, depth (metres, NaN missing; None for an RGB-only dataset or
        with use_depth=False), K, and the annotated objects (gt pose, visib_fract and bbox_visib
        when scene_gt_info exists, and the model)."""
        cam = self.camera(scene_id, im_id)
        gts = self.gt(scene_id, im_id)
        infos = self.gt_info(scene_id, im_id)
        rgb_path = self._image_file(scene_id, im_id, "rgb")
        rgb = read_rgb(rgb_path)
        depth = None
        if self.has_depth(scene_id, im_id):
            depth_path = self._image_file(scene_id, im_id, "depth")
            depth = read_depth(depth_path, self._depth_scale(scene_id, im_id))
        if depth is not None and rgb.shape[:2] != depth.shape:
            raise BopFormatError(
                f"{rgb_path} is {rgb.shape[1]}x{rgb.shape[0]} but {depth_path} is {depth.shape[1]}x{depth.shape[0]}"
            )
        objects = []
        for k, (obj_id, pose) in enumerate(gts):
            info = infos[k] if infos is not None else {}
            bbox = info.get("bbox_visib")
            objects.append(
                SceneObject(
                    obj_id=obj_id,
                    gt=pose,
                    model=self.model(obj_id) if with_models else None,
                    visib_fract=float(info["visib_fract"]) if "visib_fract" in info else None,
                    bbox_visib=tuple(int(v) for v in bbox) if bbox is not None else None,  # type: ignore[arg-type]
                )
            )
        return Frame(
            rgb=rgb, depth=depth, K=cam.K, stamp=im_id / self.frame_rate,
            scene_id=scene_id, im_id=im_id, objects=objects,
        )

    def frames(self, with_models: bool = True) -> Iterator[Frame]:
        for scene_id, im_id in self.image_keys():
            yield self.load_frame(scene_id, im_id, with_models)


__all__ = ["BopDataset", "DEFAULT_FRAME_RATE"]
