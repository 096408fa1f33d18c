"""Writing frames into BOP scenes: `SceneWriter` writes each image at once and the scene's JSON
files once at close (for a generator writing many frames); `write_frame` is the one-off
convenience; `compute_gt_info` computes scene_gt_info entries as bop_toolkit does.
"""
from __future__ import annotations

import os
from typing import Any, Literal, Mapping, Sequence

import numpy as np

from ..core.geometry import Pose
from ..core.scene import Frame
from .bop_images import RGB_EXTS, write_depth, write_rgb
from .bop_json import jsonable
from .bop_scene import (
    CameraInfo,
    load_scene_camera,
    load_scene_gt,
    load_scene_gt_info,
    scene_dir,
    write_scene_camera,
    write_scene_gt,
    write_scene_gt_info,
)

GtInfoArg = Sequence[Mapping[str, Any]] | Literal["compute"] | None


class SceneWriter:
    """Writes frames into one BOP scene: images at once, the three JSON files at flush/close.

    For generators: O(1) work per frame instead of rewriting growing JSON files each time.
    With append=True (default) existing entries of the scene are kept and extended; an added
    image id replaces its old entry. The scene's frames all carry scene_gt_info or none do.
    Use as a context manager; the JSON files are written even when the block raises, so the
    images already written stay described.
    """

    def __init__(
        self,
        root: str | os.PathLike,
        split: str,
        scene_id: int,
        *,
        depth_scale: float = 1.0,
        rgb_ext: str = ".png",
        append: bool = True,
        jpg_quality: int = 95,
    ) -> None:
        self.dir = scene_dir(root, split, scene_id)
        self.scene_id = int(scene_id)
        self.depth_scale = float(depth_scale)
        self.rgb_ext = rgb_ext if rgb_ext.startswith(".") else "." + rgb_ext
        if self.rgb_ext.lower() not in RGB_EXTS:
            raise ValueError(f"rgb_ext must be one of {RGB_EXTS}, got {rgb_ext!r}")
        self.jpg_quality = jpg_quality
        self.cameras: dict[int, CameraInfo] = {}
        self.gts: dict[int, list[tuple[int, Pose]]] = {}
        self.gt_infos: dict[int, list[dict[str, Any]]] | None = None  # None = undecided / absent
        if append and (self.dir / "scene_camera.json").exists():
            self.cameras = load_scene_camera(self.dir / "scene_camera.json")
            if (self.dir / "scene_gt.json").exists():
                self.gts = load_scene_gt(self.dir / "scene_gt.json")
            if (self.dir / "scene_gt_info.json").exists():
                self.gt_infos = load_scene_gt_info(self.dir / "scene_gt_info.json")
        self._dirty = False

    def __enter__(self) -> "SceneWriter":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def add(
        self,
        frame: Frame,
        gt_info: GtInfoArg = None,
        *,
        depth_scale: float | None = None,
        world_to_cam: Pose | None = None,
    ) -> None:
        """Write the frame's images now and record its camera and ground truth (objects with a
        gt pose). `gt_info`: scene_gt_info entries aligned with those objects, "compute" to
        compute them from the models and depth (compute_gt_info), or None to write none.
        The frame's im_id names the image; its scene_id is ignored (the writer's wins)."""
        im_id = int(frame.im_id)
        scale = self.depth_scale if depth_scale is None else float(depth_scale)
        objs = [(o.obj_id, o.gt) for o in frame.objects if o.gt is not None]
        infos: list[dict[str, Any]] | None
        if isinstance(gt_info, str):
            if gt_info != "compute":
                raise ValueError(f"gt_info must be entries, 'compute' or None, got {gt_info!r}")
            infos = compute_gt_info(frame)
        else:
            infos = [dict(jsonable(dict(e))) for e in gt_info] if gt_info is not None else None
        if infos is not None and len(infos) != len(objs):
            raise ValueError(f"image {im_id}: {len(infos)} gt_info entries for {len(objs)} objects with a gt pose")
        others = [i for i in self.cameras if i != im_id]
        if others:
            has = self.gt_infos is not None and any(i in self.gt_infos for i in others)
            if has != (infos is not None):
                raise ValueError(
                    f"{self.dir}: image {im_id} {'lacks' if has else 'has'} scene_gt_info but the scene's "
                    f"other images {'have' if has else 'do not'}: all or none"
                )
        rgb_path = self.dir / "rgb" / f"{im_id:06d}{self.rgb_ext}"
        for ext in RGB_EXTS:  # replacing an image with another format: drop the old file
            old = rgb_path.with_suffix(ext)
            if ext != self.rgb_ext and old.exists():
                old.unlink()
        depth_path = self.dir / "depth" / f"{im_id:06d}.png"
        if frame.depth is None:  # an RGB-only frame: the scene must be RGB-only (no depth folder)
            with_depth = [p.name for p in depth_path.parent.glob("*.png") if p != depth_path] \
                if depth_path.parent.is_dir() else []
            if with_depth:
                raise ValueError(f"{self.dir}: image {im_id} has no depth but the scene's images {with_depth[:3]} "
                                 "have: a scene is RGB-D or RGB-only, all or none")
        elif others and not depth_path.parent.is_dir():
            raise ValueError(f"{self.dir}: image {im_id} has depth but the scene's other images have none "
                             "(no depth folder): a scene is RGB-D or RGB-only, all or none")
        write_rgb(rgb_path, frame.rgb, self.jpg_quality)
        if frame.depth is None:
            depth_path.unlink(missing_ok=True)
            if depth_path.parent.is_dir() and not any(depth_path.parent.iterdir()):
                depth_path.parent.rmdir()
        else:
            write_depth(depth_path, frame.depth, scale)
        self.cameras[im_id] = CameraInfo(frame.K.copy(), scale, world_to_cam)
        self.gts[im_id] = objs  # type: ignore[assignment]
        if infos is not None:
            if self.gt_infos is None:
                self.gt_infos = {}
            self.gt_infos[im_id] = infos
        elif self.gt_infos is not None:
            self.gt_infos.pop(im_id, None)
        self._dirty = True

    def flush(self) -> None:
        """Write scene_camera.json, scene_gt.json and scene_gt_info.json (atomically)."""
        if not self._dirty:
            return
        write_scene_camera(self.dir / "scene_camera.json", self.cameras)
        write_scene_gt(self.dir / "scene_gt.json", self.gts)
        if self.gt_infos:
            write_scene_gt_info(self.dir / "scene_gt_info.json", self.gt_infos)
        elif (self.dir / "scene_gt_info.json").exists():  # its only image was replaced without
            (self.dir / "scene_gt_info.json").unlink()
        self._dirty = False

    def close(self) -> None:
        self.flush()


def write_frame(
    root: str | os.PathLike,
    split: str,
    frame: Frame,
    gt_info: GtInfoArg = None,
    *,
    depth_scale: float = 1.0,
    rgb_ext: str = ".png",
    world_to_cam: Pose | None = None,
) -> None:
    """Append one frame to scene frame.scene_id (rewrites that scene's JSON files: for many
    frames use SceneWriter)."""
    with SceneWriter(root, split, frame.scene_id, depth_scale=depth_scale, rgb_ext=rgb_ext) as w:
        w.add(frame, gt_info, world_to_cam=world_to_cam)


def compute_gt_info(frame: Frame, delta: float = 0.015) -> list[dict[str, Any]]:
    """scene_gt_info entries of a frame's objects with a gt pose and a model, as bop_toolkit's
    calc_gt_info (visib_mode bop19): each object rendered alone; a pixel is visible where the
    frame's distance is missing or not more than `delta` metres in front of the model.
    bbox_obj may extend outside the image (rendered into a 3x larger virtual image). An
    RGB-only frame (depth None) is compared with the depth of all its objects rendered together
    (occlusion among the annotated objects; clutter that is not annotated is not seen)."""
    from ..core.render import render, render_box

    H, W = frame.height, frame.width
    K = frame.K
    Kbig = K.copy()
    Kbig[0, 2] += W
    Kbig[1, 2] += H
    vv, uu = np.mgrid[0:H, 0:W]
    Kinv = np.linalg.inv(K)
    ray_norm = np.linalg.norm(np.stack([uu, vv, np.ones_like(uu)], -1) @ Kinv.T, axis=2)
    depth = frame.depth
    if depth is None:
        shown = [o for o in frame.objects if o.gt is not None and o.model is not None]
        depth = (render([o.model for o in shown], [o.gt for o in shown], K, W, H).depth if shown
                 else np.full((H, W), np.nan, np.float32))
    dist_test = np.nan_to_num(depth, nan=0.0) * ray_norm
    out = []
    for o in frame.objects:
        if o.gt is None:
            continue
        if o.model is None:
            raise ValueError(f"compute_gt_info: object {o.obj_id} of image {frame.im_id} has no model")
        r = render_box(o.model, o.gt, Kbig, 3 * W, 3 * H, margin=0)
        ys, xs = np.nonzero(r.mask >= 0)
        xs, ys = xs + r.offset[0] - W, ys + r.offset[1] - H
        bbox_obj = ([int(xs.min()), int(ys.min()), int(xs.max() - xs.min()), int(ys.max() - ys.min())] if xs.size
                    else [-1] * 4)
        inside = (xs >= 0) & (xs < W) & (ys >= 0) & (ys < H)
        xs, ys = xs[inside], ys[inside]
        z = r.depth[ys + H - r.offset[1], xs + W - r.offset[0]]
        dist_model = z * ray_norm[ys, xs]
        dt = dist_test[ys, xs]
        visib = (dt == 0) | (dist_model - dt <= delta)
        n_all, n_visib = int(xs.size), int(visib.sum())
        vx, vy = xs[visib], ys[visib]
        out.append({
            "bbox_obj": bbox_obj,
            "bbox_visib": ([int(vx.min()), int(vy.min()), int(vx.max() - vx.min()), int(vy.max() - vy.min())]
                           if n_visib else [-1] * 4),
            "px_count_all": n_all,
            "px_count_valid": int((dt > 0).sum()),
            "px_count_visib": n_visib,
            "visib_fract": n_visib / n_all if n_all else 0.0,
        })
    return out


__all__ = ["SceneWriter", "write_frame", "compute_gt_info"]
