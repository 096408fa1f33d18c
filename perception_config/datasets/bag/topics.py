"""The topics of a bag: the names and types we write, and `resolve_topics`, which finds the
colour, depth, camera_info and ground-truth topics of other recordings: by the topic layout of
a known camera driver (DRIVER_LAYOUTS), else by type and name."""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Callable

from .errors import BagFormatError

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPES = (IMAGE, COMPRESSED_IMAGE)
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
OBJECT_POSES = "perception_config_interfaces/msg/ObjectPoses"
STRING = "std_msgs/msg/String"

COLOR_TOPIC = "/camera/color/image_raw"
DEPTH_TOPIC = "/camera/depth/image_raw"
CAMERA_INFO_TOPIC = "/camera/camera_info"
GROUND_TRUTH_TOPIC = "/perception/ground_truth"
FRAME_INFO_TOPIC = "/perception/frame_info"

# Driver topic layouts: colour, depth registered to colour, colour camera_info, relative to the
# driver's namespace (any: /camera, /camera/camera, /zed/zed_node, /oak, ...). An image topic may
# also be recorded compressed: <topic>/compressed (jpeg/png) or, for depth, <topic>/compressedDepth.
DRIVER_LAYOUTS: dict[str, tuple[str, str, str]] = {
    "RealSense (realsense2_camera)": ("color/image_raw", "aligned_depth_to_color/image_raw", "color/camera_info"),
    "Azure Kinect (Azure_Kinect_ROS_Driver)": ("rgb/image_raw", "depth_to_rgb/image_raw", "rgb/camera_info"),
    "ZED (zed_wrapper)": ("rgb/image_rect_color", "depth/depth_registered", "rgb/camera_info"),
    "OAK-D (depthai_ros_driver, depth aligned to rgb)": ("rgb/image_raw", "stereo/image_raw", "rgb/camera_info"),
    "OpenNI / Astra (openni2_camera)": ("rgb/image_raw", "depth_registered/image_raw", "rgb/camera_info"),
}


@dataclass(frozen=True)
class FrameTopics:
    color: str
    depth: str | None  # None: an RGB-only recording (frames with depth None)
    camera_info: str
    ground_truth: str | None = None
    frame_info: str | None = None
    layout: str | None = None  # the driver layout recognised, if any


def _image_variant(types: dict[str, str], base: str, depth: bool) -> str | None:
    """`base` if it is an Image topic, else its compressed image_transport topic, else None."""
    if types.get(base) == IMAGE:
        return base
    for suffix in (("/compressedDepth", "/compressed") if depth else ("/compressed",)):
        if types.get(base + suffix) == COMPRESSED_IMAGE:
            return base + suffix
    return None


def driver_layouts(types: dict[str, str]) -> list[tuple[str, str, str, str]]:
    """(driver, colour, depth, camera_info) of every known driver layout complete in the bag."""
    found = []
    for driver, (c_rel, d_rel, i_rel) in DRIVER_LAYOUTS.items():
        for t in types:
            for suffix in ("", "/compressed"):
                if not t.endswith("/" + c_rel + suffix) and t != c_rel + suffix:
                    continue
                ns = t[: len(t) - len(c_rel + suffix)]  # "" or "/camera/" ...
                color = _image_variant(types, ns + c_rel, depth=False)
                depth = _image_variant(types, ns + d_rel, depth=True)
                info = ns + i_rel if types.get(ns + i_rel) == CAMERA_INFO else None
                if color == t and depth and info:
                    found.append((driver, color, depth, info))
    return sorted(set(found))


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

    `types` maps topic -> type ('pkg/msg/Name'). Given names must exist with the right type
    (Image or CompressedImage for images). Otherwise ours (/camera/color/image_raw ...) when
    present; else a known driver's layout (DRIVER_LAYOUTS: RealSense, Azure Kinect, ZED, OAK-D,
    OpenNI; raw or compressed images) when exactly one is complete; else by type and name:
    colour = an image topic named like color/rgb (not depth/infra), depth = one named like depth,
    preferring the one registered to colour (aligned_depth_to_color, depth_registered,
    depth_to_rgb), camera_info = the CameraInfo beside the colour topic; raw Image topics before
    compressed ones. `depth_topic=""` reads the bag as RGB-only (depth None), as does a bag
    without any depth-like image topic; two or more equally good candidates are an error that
    lists them.
    """

    def check(topic: str, want: tuple[str, ...], what: str) -> str:
        if topic not in types:
            raise BagFormatError(f"{path}: {what} topic {topic} is not in the bag (topics: {sorted(types)})")
        if types[topic] not in want:
            raise BagFormatError(f"{path}: {what} topic {topic} has type {types[topic]}, expected "
                                 f"{' or '.join(want)}")
        return topic

    images = [t for t, ty in types.items() if ty in IMAGE_TYPES]
    infos = [t for t, ty in types.items() if ty == CAMERA_INFO]
    low = {t: t.lower() for t in types}

    def is_depth(t: str) -> bool:
        name = low[t]
        return ("depth" in name or name.endswith("/stereo/image_raw")) and not any(
            k in name for k in ("rgb_to_depth", "color_to_depth"))

    def is_ir(t: str) -> bool:
        parts = low[t].replace("-", "/").split("/")
        return any(p.startswith("infra") or p in ("ir", "ir1", "ir2", "infrared") for p in parts)

    def raw(t: str) -> bool:
        return types[t] == IMAGE

    def fail(what: str, cands: list[str], kw: str) -> BagFormatError:
        return BagFormatError(f"{path}: cannot tell the {what} topic: candidates {sorted(cands) or 'none'} among "
                              f"{sorted(images + infos)}; pass {kw}=")

    layout = None
    if color_topic is None or depth_topic is None or camera_info_topic is None:
        layouts = driver_layouts(types)
        if color_topic is not None:
            layouts = [lay for lay in layouts if lay[1] == color_topic]
        if len(layouts) > 1:
            listed = "; ".join(f"{d}: {c}, {dp}, {i}" for d, c, dp, i in layouts)
            raise BagFormatError(f"{path}: cannot tell which camera to read: {len(layouts)} complete camera layouts "
                                 f"({listed}); pass color_topic=, depth_topic= and camera_info_topic=")
        layout = layouts[0] if layouts else None
    # Colour
    if color_topic is not None:
        color = check(color_topic, IMAGE_TYPES, "colour")
    elif types.get(COLOR_TOPIC) == IMAGE:
        color = COLOR_TOPIC
    elif layout is not None:
        color = layout[1]
    else:
        cands = [t for t in images if not is_depth(t) and not is_ir(t) and not low[t].endswith("compresseddepth")]
        best = _pick(cands, lambda t: (("color" in low[t]) or ("rgb" in low[t]), raw(t),
                                       low[t].removesuffix("/compressed").endswith("image_raw"), "rect" not in low[t]))
        if len(best) != 1:
            raise fail("colour image", best or cands, "color_topic")
        color = best[0]
    # Depth
    depth: str | None
    if depth_topic == "":
        depth = None  # RGB-only, on request
    elif depth_topic is not None:
        depth = check(depth_topic, IMAGE_TYPES, "depth")
    elif types.get(DEPTH_TOPIC) == IMAGE and color == COLOR_TOPIC:
        depth = DEPTH_TOPIC
    elif layout is not None and color == layout[1]:
        depth = layout[2]
    else:
        cands = [t for t in images if is_depth(t) and t != color]
        best = _pick(cands, lambda t: (any(k in low[t] for k in ("aligned", "registered", "to_color", "to_rgb")),
                                       raw(t), low[t].endswith("image_raw") or low[t].endswith("image_rect_raw")))
        if not cands:
            depth = None  # no depth image at all: an RGB-only recording
        elif len(best) != 1:
            raise fail("depth image", best or cands, "depth_topic")
        else:
            depth = best[0]
    # Camera info
    if camera_info_topic is not None:
        info = check(camera_info_topic, (CAMERA_INFO,), "camera_info")
    elif color == COLOR_TOPIC and types.get(CAMERA_INFO_TOPIC) == CAMERA_INFO:
        info = CAMERA_INFO_TOPIC
    elif layout is not None and color == layout[1]:
        info = layout[3]
    else:
        base = color.removesuffix("/compressed")
        beside = base.rsplit("/", 1)[0] + "/camera_info"
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
        gt = check(ground_truth_topic, (OBJECT_POSES,), "ground-truth")
    elif types.get(GROUND_TRUTH_TOPIC) == OBJECT_POSES:
        gt = GROUND_TRUTH_TOPIC
    else:
        cands = [t for t, ty in types.items() if ty == OBJECT_POSES]
        gt = cands[0] if len(cands) == 1 else None
    frame_info = FRAME_INFO_TOPIC if types.get(FRAME_INFO_TOPIC) == STRING else None
    used_layout = layout[0] if layout is not None and (color, depth, info) == layout[1:] else None
    return FrameTopics(color, depth, info, gt, frame_info, used_layout)
