"""The embedded default dataset: synthetic BOP-format RGB-D scenes of industrial parts.

`generate(out, ...)` writes a complete BOP dataset (models/, models_eval/, camera.json,
test/<scene>/... with scene_camera.json, scene_gt.json, scene_gt_info.json, rgb/ and depth/
PNGs, and test_targets_bop19.json) of the procedural parts of `parts.py`, or of the models of a
given BOP models folder (e.g. the real LM-O models).

models_eval/ (what bop_toolkit's evaluation loads: obj_*.ply and models_info.json) holds the
same meshes as models/, byte for byte: the project's errors are computed on those meshes, so
bop_toolkit's MSSD / MSPD on models_eval equal the project's (BOP's own datasets resample
their evaluation meshes evenly instead).

Scenes (synthetic_scene.py; one arrangement of objects each; BOP-like: the images of a scene
are viewpoints):
- World frame z up, the floor at z = 0. Per scene, with a seeded generator: a bin (floor
  slab and four walls of 8 mm plastic, 10-14 cm high, sized to the objects; the walls occlude)
  or a table; 3-8 distinct objects (at most the number of models).
- Resting poses (stable_poses.py): each object lies on one of its stable faces (convex-hull
  faces whose plane contains the projection of the centre of mass), drawn with probability
  proportional to the solid angle of the face seen from the centre of mass (the quasi-static
  drop heuristic; rests that tip over within 8 deg, such as a disc on its rim, are dropped),
  with a random yaw; its lowest point touches the floor. Footprint circles are
  kept apart by rejection sampling; an object that does not fit after 80 tries is put on
  top of the ones it overlaps (a heap): no interpenetration either way.
- Camera: Linemod intrinsics (fx 572.41, fy 573.57, cx 325.26, cy 242.05) at 640x480, at
  0.5-1.0 m from a point near the bin centre, tilted 0-25 deg from vertical, random azimuth
  and +-45 deg roll, re-drawn until every object centre projects at least 16 px inside the image.
- One point light per scene (0.9-1.6 m above, offset), ambient term, cast shadows.

Rendering: objects with `render.render` (open3d ray casting, exact mutual occlusion); the
bin/table with one open3d RaycastingScene per scene in the world frame; the nearer hit wins.
RGB: procedural albedo textures, Lambert + Blinn-Phong (shiny parts get highlights), shadows,
blur, noise, gamma (sensor.py). Depth: sensor.simulate_depth (z-dependent noise, projector
shadows, edge dropout and flying pixels, grazing-angle and specular dropout, 1 mm quantum).
Depth PNGs use depth_scale 1.0 (1 unit = 1 mm, the sensor's quantum: lossless, 65 m range).

scene_gt_info.json follows bop_toolkit's calc_gt_info, with exact masks instead of its depth
test: px_count_all = pixels of the object rendered alone, including the part outside the
image (a virtual 3x image, as bop_toolkit); px_count_visib = pixels where the object is the
visible surface of the full scene (objects and bin); px_count_valid = in-image silhouette
pixels with a valid depth measurement; visib_fract = visib / all; bbox_obj / bbox_visib as
bop_toolkit (x, y, max-min width/height; bbox_obj may extend outside the image).

Output is deterministic for a seed (same PNG and JSON bytes; every scene and image draws
from its own generator seeded by (seed, scene, image)), and atomic: the dataset is written
to a hidden sibling folder marked `.incomplete` and renamed to `out` only when complete.
"""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from ..core.geometry import Pose
from ..util.atomic_file import atomic_write
from ..util.safe_json import read_json_file
from . import sensor
from .realism import Realism, annotation_error, draw_noise_scale, miscalibrate_depth
from .stable_poses import stable_poses
from .synthetic_scene import SynthObject, SynthScene, make_scene, sample_camera

__all__ = ["generate", "camera_from", "LINEMOD_K", "DEPTH_SCALE", "GENERATOR_NAME"]

LINEMOD_K = np.array([[572.4114, 0.0, 325.2611], [0.0, 573.57043, 242.04899], [0.0, 0.0, 1.0]])
DEPTH_SCALE = 1.0  # mm per depth PNG unit
GENERATOR_NAME = "perception_config.datasets.synthetic"


# --------------------------------------------------------------------------- one image


def camera_from(path: str | os.PathLike) -> tuple[np.ndarray, int, int]:
    """(K, width, height) of a camera: a BOP camera.json (fx, fy, cx, cy, width, height), or a BOP
    dataset folder (its camera.json, else its first test image's cam_K and size). ValueError
    naming the file when it cannot be read."""
    path = Path(path)
    if path.is_dir() and (path / "camera.json").is_file():
        path = path / "camera.json"
    if path.is_file():
        try:
            c = read_json_file(path, what="camera file")
            K = np.array([[float(c["fx"]), 0.0, float(c["cx"])], [0.0, float(c["fy"]), float(c["cy"])],
                          [0.0, 0.0, 1.0]])
            width, height = int(c["width"]), int(c["height"])
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"{path}: not a BOP camera.json (fx, fy, cx, cy, width, height): {e}") from e
    elif path.is_dir():
        from .bop import BopDataset

        ds = BopDataset(path, "test")
        keys = ds.image_keys()
        if not keys:
            raise ValueError(f"{path}: a BOP dataset without test images has no camera to copy")
        K = np.asarray(ds.camera(*keys[0]).K, dtype=np.float64)
        height, width = ds.load_frame(*keys[0]).rgb.shape[:2]
    else:
        raise ValueError(f"{path}: no such camera file or dataset folder")
    if not (np.isfinite(K).all() and K[0, 0] > 0 and K[1, 1] > 0 and width >= 64 and height >= 48):
        raise ValueError(f"{path}: unusable camera (K {K.tolist()}, {width}x{height})")
    return K, int(width), int(height)


def _apply(R: np.ndarray, a: np.ndarray) -> np.ndarray:
    """R @ a for (..., 3) arrays, elementwise (no BLAS call: BLAS threads stall on a busy
    machine for these tall-and-thin products)."""
    R = np.asarray(R, dtype=np.float32)
    return a[..., 0:1] * R[:, 0] + a[..., 1:2] * R[:, 1] + a[..., 2:3] * R[:, 2]


def _render_image(
    rng: np.random.Generator, scene: SynthScene, w2c: Pose, K: np.ndarray, width: int, height: int,
    rays: np.ndarray, noise: sensor.DepthNoise,
) -> tuple[np.ndarray, np.ndarray, list[Pose], list[dict[str, Any]]]:
    import open3d as o3d

    from ..core.render import render, render_box
    from .parts import MATERIALS

    c2w = w2c.inverse()
    H, W = height, width
    poses = [w2c.compose(p) for p in scene.world_poses]  # model to camera
    models = [o.model for o in scene.objects]
    obj = render(models, poses, K, W, H)

    # World-frame rays of the pixels (camera z = 1 so t_hit is the z-depth), built separably.
    A = (c2w.R @ np.linalg.inv(K)).astype(np.float32)
    u = np.arange(W, dtype=np.float32)
    v = np.arange(H, dtype=np.float32)
    rays_w = (v[:, None] * A[:, 1] + A[:, 2])[:, None, :] + (u[:, None] * A[:, 0])[None, :, :]
    eye = c2w.t.astype(np.float32)
    cr = np.empty((H, W, 6), np.float32)
    cr[..., :3] = eye
    cr[..., 3:] = rays_w
    ans = scene.env_scene.cast_rays(o3d.core.Tensor(cr.reshape(-1, 6)), nthreads=1)
    env_depth = ans["t_hit"].numpy().reshape(H, W)
    env_gid = ans["geometry_ids"].numpy().reshape(H, W).astype(np.int64)
    env_n = ans["primitive_normals"].numpy().reshape(H, W, 3)  # world frame
    env_hit = np.isfinite(env_depth)

    obj_depth = np.where(obj.mask >= 0, obj.depth, np.float32(np.inf))
    use_obj = (obj.mask >= 0) & (obj_depth < env_depth)
    mask = np.where(use_obj, obj.mask, -1).astype(np.int16)
    depth = np.where(use_obj, obj_depth, np.where(env_hit, env_depth, np.float32(np.nan))).astype(np.float32)
    surface = np.isfinite(depth)
    n_w = env_n.copy()  # world-frame normals, then the camera-frame ones for the sensor model
    n_w[use_obj] = _apply(c2w.R, obj.normals[use_obj])
    flip = (n_w * rays_w).sum(-1) > 0  # face the camera
    n_w[flip] *= -1.0
    pts_w = eye + rays_w * np.where(surface, depth, np.float32(0.0))[..., None]

    # material maps
    albedo = np.zeros((H, W, 3), np.float32)
    ks = np.zeros((H, W), np.float32)
    shin = np.full((H, W), 10.0, np.float32)
    shiny = np.zeros((H, W), np.float32)
    env_sel = (~use_obj) & env_hit
    mats = sorted(set(scene.env_ids))
    mat_of_gid = np.array([mats.index(m) for m in scene.env_ids] + [-1], np.int64)
    env_mat = np.where(env_sel, mat_of_gid[np.minimum(env_gid, len(scene.env_ids))], -1)
    for mi, mat in enumerate(mats):
        sel = env_mat == mi
        if not sel.any():
            continue
        pw, nw = pts_w[sel], n_w[sel]
        tex = scene.textures[mat]
        size = tex.shape[0]
        texel = 0.5 / size  # the texture spans 0.5 m
        horizontal = np.abs(nw[:, 2]) > 0.7
        along_x = np.abs(nw[:, 0]) < np.abs(nw[:, 1])
        tu = np.where(horizontal | along_x, pw[:, 0], pw[:, 1])
        tv = np.where(horizontal, pw[:, 1], pw[:, 2])
        albedo[sel] = _sample_texture(tex, np.mod(tu / texel, size), np.mod(tv / texel, size))
        ks[sel], shin[sel] = scene.env_props[mat]
    for i, (o, pose) in enumerate(zip(scene.objects, poses)):
        sel = mask == i
        if not sel.any():
            continue
        if o.model.colors is not None and np.ptp(o.model.colors, axis=0).max() > 0:
            if o.tree is None:
                from scipy.spatial import cKDTree

                o.tree = cKDTree(o.model.vertices)
            pm = (rays[sel] * depth[sel][:, None] - pose.t) @ pose.R  # model frame
            _, nn = o.tree.query(pm)
            albedo[sel] = o.model.colors[nn].astype(np.float32) / 255.0
        else:
            albedo[sel] = o.color
        mp = MATERIALS.get(o.material, MATERIALS["matte"])
        ks[sel], shin[sel], shiny[sel] = mp["ks"], mp["shininess"], mp["dropout"]

    # cast shadows: is the light visible from the surface point?
    sr = np.empty((H, W, 6), np.float32)
    sr[..., :3] = pts_w + n_w * np.float32(2e-3)
    sr[..., 3:] = scene.light.astype(np.float32) - sr[..., :3]
    occ = scene.shadow_scene.test_occlusions(o3d.core.Tensor(sr.reshape(-1, 6)), tnear=0.0, tfar=1.0, nthreads=1)
    lit = ~occ.numpy().reshape(H, W).astype(bool)
    lin = sensor.shade(albedo, n_w, pts_w, scene.light, ks, shin, lit=lit, light_power=scene.light_power,
                       ambient=scene.ambient, ref_dist=float(np.linalg.norm(scene.light)), eye=eye)
    lin[~surface] = 0.02
    rgb = sensor.finish_rgb(lin, rng, exposure=0.85)
    normals = _apply(w2c.R, n_w)  # camera frame
    noisy = sensor.simulate_depth(depth, normals, K, rng, shiny=shiny, params=noise)

    # scene_gt_info, as bop_toolkit's calc_gt_info but with exact visibility masks
    infos = []
    Kbig = K.copy()
    Kbig[0, 2] += W
    Kbig[1, 2] += H
    valid = np.isfinite(noisy)
    for i, (m, pose) in enumerate(zip(models, poses)):
        solo = render_box(m, pose, K, W, H, margin=0)
        sy, sx = np.nonzero(solo.mask >= 0)
        sx, sy = sx + solo.offset[0], sy + solo.offset[1]
        xs_all, ys_all = sx, sy
        uv = m.hull_points @ pose.R.T + pose.t
        uv = uv @ K.T
        uv = uv[:, :2] / uv[:, 2:3]
        if uv[:, 0].min() < 1 or uv[:, 1].min() < 1 or uv[:, 0].max() > W - 2 or uv[:, 1].max() > H - 2:
            big = render_box(m, pose, Kbig, 3 * W, 3 * H, margin=0)
            by, bx = np.nonzero(big.mask >= 0)
            bx, by = bx + big.offset[0] - W, by + big.offset[1] - H
            out = (bx < 0) | (bx >= W) | (by < 0) | (by >= H)
            xs_all = np.concatenate([sx, bx[out]])
            ys_all = np.concatenate([sy, by[out]])
        vis = mask == i
        n_all = int(xs_all.size)
        n_vis = int(vis.sum())
        n_valid = int(valid[sy, sx].sum())
        vy, vx = np.nonzero(vis)
        infos.append({
            "bbox_obj": _bbox(xs_all, ys_all) if n_vis else [-1, -1, -1, -1],
            "bbox_visib": _bbox(vx, vy) if n_vis else [-1, -1, -1, -1],
            "px_count_all": n_all,
            "px_count_valid": n_valid,
            "px_count_visib": n_vis,
            "visib_fract": float(n_vis / n_all) if n_all else 0.0,
        })
    return rgb, noisy, poses, infos


def _sample_texture(tex: np.ndarray, x: np.ndarray, y: np.ndarray, row: int = 1024) -> np.ndarray:
    """Bilinear, wrapping texture lookup at N float pixel positions: (N, 3)."""
    import cv2

    n = len(x)
    m = -(-n // row) * row
    mx = np.zeros(m, np.float32)
    my = np.zeros(m, np.float32)
    mx[:n], my[:n] = x, y
    out = cv2.remap(tex, mx.reshape(-1, row), my.reshape(-1, row), cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    return out.reshape(-1, tex.shape[2])[:n]


def _bbox(xs: np.ndarray, ys: np.ndarray) -> list[int]:
    return [int(xs.min()), int(ys.min()), int(xs.max() - xs.min()), int(ys.max() - ys.min())]


# --------------------------------------------------------------------------- models


def _prepare_models(models_out: Path, models_dir: Path | None) -> list[SynthObject]:
    from ..core.models import load_model
    from .bop_json import load_json, save_json
    from .bop_models import load_models_info
    from .parts import build_parts, write_models

    if models_dir is None:
        parts = build_parts()
        write_models(models_out, parts)
    else:
        models_dir = Path(models_dir)
        if not (models_dir / "models_info.json").is_file():
            raise FileNotFoundError(f"not a BOP models folder (no models_info.json): {models_dir}")
        info = load_models_info(models_dir)
        models_out.mkdir(parents=True, exist_ok=True)
        for obj_id in info:
            src = models_dir / f"obj_{obj_id:06d}.ply"
            if not src.is_file():
                raise FileNotFoundError(f"model file missing for object {obj_id}: {src}")
            shutil.copyfile(src, models_out / src.name)
        shutil.copyfile(models_dir / "models_info.json", models_out / "models_info.json")
        if (models_dir / "parts.json").is_file():
            save_json(models_out / "parts.json", load_json(models_dir / "parts.json"))
    info = load_models_info(models_out)
    meta = load_json(models_out / "parts.json") if (models_out / "parts.json").is_file() else {}
    pool = []
    for obj_id, entry in sorted(info.items()):
        model = load_model(models_out / f"obj_{obj_id:06d}.ply", obj_id, entry)
        m = meta.get(str(obj_id), {})
        rests, probs = stable_poses(model.vertices, model.faces)
        pool.append(SynthObject(
            obj_id=obj_id, model=model, material=m.get("material", "matte"),
            color=np.asarray(m.get("color", (0.6, 0.6, 0.6)), np.float32), rests=rests, rest_probs=probs,
        ))
    return pool


def _write_models_eval(models: Path, models_eval: Path) -> None:
    """models_eval/: copies of the meshes and models_info.json of models/ (see the module docstring)."""
    models_eval.mkdir(parents=True, exist_ok=True)
    for src in sorted(models.glob("obj_*.ply")) + [models / "models_info.json"]:
        shutil.copyfile(src, models_eval / src.name)


# --------------------------------------------------------------------------- driver


def _write_json_atomic(path: Path, obj: Any) -> None:
    atomic_write(path, json.dumps(obj, indent=2, sort_keys=True) + "\n")


def _is_ours(path: Path) -> bool:
    try:
        return read_json_file(path / "dataset_info.json").get("generator") == GENERATOR_NAME
    except (OSError, ValueError, AttributeError):
        return False


def generate(
    out: str | os.PathLike,
    scenes: int = 4,
    images_per_scene: int = 10,
    seed: int = 0,
    models_dir: str | os.PathLike | None = None,
    progress: bool = True,
    width: int = 640,
    height: int = 480,
    depth: bool = True,
    K: np.ndarray | None = None,
    realism: Realism | None = None,
) -> Path:
    """Write a synthetic BOP dataset to `out` (split "test"); returns `out`.

    `depth=False` writes an RGB-only dataset (no depth folders): the same scenes, images and
    annotations as with depth (the same random draws), without the depth images.

    `models_dir`: a BOP models folder whose models are placed instead of the procedural
    parts (copied into out/models). `K`: the intrinsics of a width x height camera (default:
    Linemod's, scaled to the size; `camera_from` reads a real dataset's). `realism`: the
    calibration and annotation errors of a real cell, drawn per image and object
    (realism.py); None: none (the bytes of a dataset without it do not change). An existing
    `out` is replaced only when it is an empty folder or a dataset this generator wrote;
    anything else raises ValueError.
    """
    from ..core.scene import Frame, SceneObject
    from .bop_writer import SceneWriter

    out = Path(out)
    if scenes < 1 or images_per_scene < 1:
        raise ValueError("need at least one scene and one image, "
                         f"got scenes={scenes} images_per_scene={images_per_scene}")
    if width < 64 or height < 48:
        raise ValueError(f"image size {width}x{height} is too small")
    if out.exists() and not (out.is_dir() and (not any(out.iterdir()) or _is_ours(out))):
        raise ValueError(f"{out} exists and is not a dataset written by this generator: refusing to replace it")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.incomplete-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    (tmp / ".incomplete").write_text("generation in progress or interrupted\n")
    if K is None:
        K = LINEMOD_K.copy()
        if (width, height) != (640, 480):  # same field of view, scaled
            K[0] *= width / 640.0
            K[1] *= height / 480.0
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    try:
        pool = _prepare_models(tmp / "models", Path(models_dir) if models_dir is not None else None)
        _write_models_eval(tmp / "models", tmp / "models_eval")
        _write_json_atomic(tmp / "camera.json", {
            "cx": float(K[0, 2]), "cy": float(K[1, 2]), "depth_scale": DEPTH_SCALE,
            "fx": float(K[0, 0]), "fy": float(K[1, 1]), "height": int(height), "width": int(width),
        })
        rays = sensor.pixel_rays(K, width, height).astype(np.float32)
        noise = sensor.DepthNoise()
        targets = []
        from tqdm import tqdm

        bar = tqdm(total=scenes * images_per_scene, desc="synth", unit="img", disable=not progress)
        try:
            for scene_id in range(scenes):
                scene = make_scene(np.random.default_rng([seed, scene_id]), pool)
                with SceneWriter(tmp, "test", scene_id, depth_scale=DEPTH_SCALE, append=False) as writer:
                    for im_id in range(images_per_scene):
                        rng = np.random.default_rng([seed, scene_id, im_id, 1])
                        w2c = sample_camera(rng, scene, K, width, height)
                        image_noise, real_rng = noise, None
                        if realism is not None:  # its own generator: the other draws stay the same
                            real_rng = np.random.default_rng([seed, scene_id, im_id, 2])
                            f = draw_noise_scale(real_rng, realism)
                            image_noise = dataclasses.replace(noise, sigma_a=noise.sigma_a * f,
                                                              sigma_b=noise.sigma_b * f)
                        rgb, dimg, poses, infos = _render_image(rng, scene, w2c, K, width, height, rays,
                                                                image_noise)
                        if real_rng is not None:
                            dimg = miscalibrate_depth(dimg, real_rng, realism)
                            poses = [annotation_error(p, real_rng, realism) for p in poses]
                        objects = [SceneObject(o.obj_id, gt=p) for o, p in zip(scene.objects, poses)]
                        frame = Frame(rgb=rgb, depth=dimg if depth else None, K=K, scene_id=scene_id, im_id=im_id,
                                      objects=objects)
                        writer.add(frame, gt_info=infos, world_to_cam=w2c)
                        targets += [{"im_id": im_id, "inst_count": 1, "obj_id": o.obj_id, "scene_id": scene_id}
                                    for o, inf in zip(scene.objects, infos) if inf["visib_fract"] >= 0.1]
                        bar.update(1)
        finally:
            bar.close()
        _write_json_atomic(tmp / "test_targets_bop19.json", targets)
        _write_json_atomic(tmp / "dataset_info.json", {
            "generator": GENERATOR_NAME, "seed": int(seed), "scenes": int(scenes),
            "images_per_scene": int(images_per_scene), "width": int(width), "height": int(height),
            "models": "procedural parts" if models_dir is None else "copied from a BOP models folder",
            "depth_scale": DEPTH_SCALE, "split": "test", "depth": bool(depth),
            **({"realism": dataclasses.asdict(realism)} if realism is not None else {}),
        })
        (tmp / ".incomplete").unlink()
        if out.exists():
            trash = out.parent / f".{out.name}.old-{os.getpid()}"
            os.rename(out, trash)
            os.rename(tmp, out)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            os.rename(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out
