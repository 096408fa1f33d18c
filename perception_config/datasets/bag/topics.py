"""The topics of a bag: the names and types we write, and `resolve_topics`, which finds the
colour, depth, camera_info and ground-truth topics of other recordings by type and name."""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Callable

from .errors import BagFormatError

IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
OBJECT_POSES = "perception_config_interfaces/msg/ObjectPoses"
STRING = "std_msgs/msg/String"

COLOR_TOPIC = "/camera/color/image_raw"
DEPTH_TOPIC = "/camera/depth/image_raw"
CAMERA_INFO_TOPIC = "/camera/camera_info"
GROUND_TRUTH_TOPIC = "/perception/ground_truth"
FRAME_INFO_TOPIC = "/perception/frame_info"


@dataclass(frozen=True)
class FrameTopics:
    color: str
    depth: str | None  # None: an RGB-only recording (frames with depth None)
    camera_info: str
    ground_truth: str | None = None
    frame_info: str | None = None


def _pick(cands: list[str], score: Callable[[str], tuple]) -> list[str]:
    if not cands:
        return []
    best = max(score(c) for c in cands)
    return [c for c in cands if score(c) == best]


def resolve_topics(
    types: dict[str, str],
    path: str | os.PathLike = "",
    *,
    color_topic: str | None = None,
    depth_topic: str | None = None,
    camera_info_topic: str | None = None,
    ground_truth_topic: str | None = None,
) -> FrameTopics:
    """Choose the colour/depth/camera_info (and ground-truth) topics of a bag.

    `types` maps topic -> type. Given names must exist with the right type. Otherwise ours
    (/camera/color/image_raw ...) when present, else by type and name: colour = an Image topic
    named like color/rgb (not depth/infra), depth = an Image topic named like depth, preferring
    the one registered to colour (aligned_depth_to_color, depth_registered), camera_info = the
    CameraInfo beside the colour topic. `depth_topic=""` reads the bag as RGB-only (depth None),
    as does a bag without any depth-like Image topic; two or more candidates are an error.
    """

    def check(topic: str, want: str, what: str) -> str:
        if topic not in types:
            raise BagFormatError(f"{path}: {what} topic {topic} is not in the bag (topics: {sorted(types)})")
        if types[topic] != want:
            raise BagFormatError(f"{path}: {what} topic {topic} has type {types[topic]}, expected {want}")
        return topic

    images = [t for t, ty in types.items() if ty == IMAGE]
    infos = [t for t, ty in types.items() if ty == CAMERA_INFO]
    low = {t: t.lower() for t in types}

    def is_depth(t: str) -> bool:
        return "depth" in low[t]

    def is_ir(t: str) -> bool:
        parts = low[t].replace("-", "/").split("/")
        return any(p.startswith("infra") or p in ("ir", "ir1", "ir2", "infrared") for p in parts)

    def fail(what: str, cands: list[str], kw: str) -> BagFormatError:
        return BagFormatError(f"{path}: cannot tell the {what} topic: candidates {sorted(cands) or 'none'} among "
                              f"{sorted(images + infos)}; pass {kw}=")

    # Colour
    if color_topic is not None:
        color = check(color_topic, IMAGE, "colour")
    elif types.get(COLOR_TOPIC) == IMAGE:
        color = COLOR_TOPIC
    else:
        cands = [t for t in images if not is_depth(t) and not is_ir(t)]
        best = _pick(cands, lambda t: (("color" in low[t]) or ("rgb" in low[t]), low[t].endswith("image_raw"),
                                       "rect" not in low[t]))
        if len(best) != 1:
            raise fail("colour image", best or cands, "color_topic")
        color = best[0]
    # Depth
    depth: str | None
    if depth_topic == "":
        depth = None  # RGB-only, on request
    elif depth_topic is not None:
        depth = check(depth_topic, IMAGE, "depth")
    elif types.get(DEPTH_TOPIC) == IMAGE and color == COLOR_TOPIC:
        depth = DEPTH_TOPIC
    else:
        cands = [t for t in images if is_depth(t) and t != color]
        best = _pick(cands, lambda t: (any(k in low[t] for k in ("aligned", "registered", "to_color")),
                                       low[t].endswith("image_raw") or low[t].endswith("image_rect_raw"),
                                       "compressed" not in low[t]))
        if not cands:
            depth = None  # no depth image at all: an RGB-only recording
        elif len(best) != 1:
            raise fail("depth image", best or cands, "depth_topic")
        else:
            depth = best[0]
    # Camera info
    if camera_info_topic is not None:
        info = check(camera_info_topic, CAMERA_INFO, "camera_info")
    elif color == COLOR_TOPIC and types.get(CAMERA_INFO_TOPIC) == CAMERA_INFO:
        info = CAMERA_INFO_TOPIC
    else:
        beside = color.rsplit("/", 1)[0] + "/camera_info"
        if types.get(beside) == CAMERA_INFO:
            info = beside
        else:
            best = _pick([t for t in infos if "depth" not in low[t] and not is_ir(t)],
                         lambda t: (("color" in low[t]) or ("rgb" in low[t]),))
            if len(best) != 1:
                raise fail("camera_info (of the colour camera)", best or infos, "camera_info_topic")
            info = best[0]
    # Ground truth (optional)
    gt = None
    if ground_truth_topic is not None:
        gt = check(ground_truth_topic, OBJECT_POSES, "ground-truth")
    elif types.get(GROUND_TRUTH_TOPIC) == OBJECT_POSES:
        gt = GROUND_TRUTH_TOPIC
    else:
        cands = [t for t, ty in types.items() if ty == OBJECT_POSES]
        gt = cands[0] if len(cands) == 1 else None
    frame_info = FRAME_INFO_TOPIC if types.get(FRAME_INFO_TOPIC) == STRING else None
    return FrameTopics(color, depth, info, gt, frame_info)
