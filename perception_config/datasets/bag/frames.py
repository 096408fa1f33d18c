"""rosbag2 bags read back as Frames: `read_bag`.

`read_bag` reads our bags and rosbag2 recordings of real RGB-D (or RGB-only) cameras: MCAP (chunk
compression zstd/lz4) or sqlite3 .db3 files, message-level compression (zstd, lz4), type names
'pkg/msg/Name' or 'pkg/Name'. Topics default to ours; when those are absent the colour, depth and
camera_info topics are those of a known driver layout (RealSense `/camera/camera/color/image_raw`,
`.../aligned_depth_to_color/image_raw`, `.../color/camera_info`; Azure Kinect, ZED, OAK-D, OpenNI:
topics.DRIVER_LAYOUTS), else found by message type and name.
Colour rgb8, bgr8, rgba8, bgra8, mono8, 8UC3 (as BGR) or a CompressedImage (jpeg, png); depth
16UC1 / mono16 (millimetres, 0 = missing), 32FC1 (metres, NaN/inf/0 = missing) or a
CompressedImage (compressedDepth png of 16UC1 or 32FC1, or a 16-bit png). Messages are grouped
into frames by header stamp (exactly, or the nearest within `sync_tolerance_s` for drivers that
stamp colour and depth apart); a colour image without its depth/camera_info (or ground truth,
when the bag has it) is dropped, and one `BagWarning` at the end says how many.
At the boundary depth becomes float32 metres with NaN for missing, like everywhere in the code.

A truncated or damaged file (no footer: the recorder was killed, the copy was cut) is read up
to the damage: the complete frames before it are yielded, then a `BagTruncatedWarning` names
the file and the byte offset; with `strict=True` a `BagTruncatedError` is raised instead,
before any frame. Data that contradicts itself (image step/size/encoding, colour vs depth size,
camera_info size) raises `BagFormatError` naming the file, topic, stamp and problem.
"""
from __future__ import annotations

import json
import os
import warnings
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from ...core.geometry import Pose, matrix_from_quaternion
from ...core.scene import Frame, SceneObject
from .errors import BagFormatError, BagTruncatedError, BagTruncatedWarning, BagWarning, ImageFormatError
from .mcap_reader import make_decoder, schema_name
from .messages import header_stamp_ns, image_msg_to_depth, image_msg_to_rgb
from .storage import BagFile, open_bag
from .topics import FrameTopics, resolve_topics


class _Assembler:
    """Group decoded messages into frames by header stamp; drop incomplete ones cleanly."""

    REQUIRED = ("depth", "info")

    def __init__(self, path: Path, topics: FrameTopics, tolerance_ns: int, require_gt: bool, max_pending: int = 32):
        self.path = path
        self.topics = topics
        self.tol = tolerance_ns
        required = self.REQUIRED if topics.depth is not None else ("info",)  # RGB-only: no depth to wait for
        self.required = required + (("gt",) if require_gt else ())
        self.max_pending = max_pending
        self.buf: dict[str, dict[int, Any]] = {r: {} for r in ("color", "depth", "info", "gt", "finfo")}
        self.max_seen: dict[str, int] = {}
        self.dropped: dict[str, int] = {}
        self.first_dropped: dict[str, int] = {}
        self.yielded = 0
        self._warned_distortion = False
        self._warned_ids = False

    def add(self, role: str, stamp: int, msg: Any) -> list[Frame]:
        self.buf[role][stamp] = msg
        self.max_seen[role] = max(self.max_seen.get(role, stamp), stamp)
        for r, b in self.buf.items():
            if r != "color" and len(b) > 4 * self.max_pending:  # orphans (e.g. depth with no colour)
                for s in sorted(b)[: len(b) - 4 * self.max_pending]:
                    del b[s]
        return self._emit(final=False)

    def finish(self) -> list[Frame]:
        return self._emit(final=True)

    def _match(self, role: str, c: int, force: bool) -> tuple[str, int | None]:
        b = self.buf[role]
        if c in b:
            return "ok", c
        best = None
        if self.tol > 0:
            near = [(abs(s - c), s) for s in b if abs(s - c) <= self.tol]
            best = min(near)[1] if near else None
        if not force and self.max_seen.get(role, -1) <= c + self.tol:
            return "wait", None
        return ("ok", best) if best is not None else ("missing", None)

    def _drop(self, c: int, reason: str) -> None:
        self.dropped[reason] = self.dropped.get(reason, 0) + 1
        self.first_dropped.setdefault(reason, c)
        del self.buf["color"][c]

    def _emit(self, final: bool) -> list[Frame]:
        out: list[Frame] = []
        colors = self.buf["color"]
        while colors:
            c = min(colors)
            force = final or len(colors) > self.max_pending
            matched: dict[str, int] = {}
            state = "ok"
            for role in self.required:
                st, s = self._match(role, c, force)
                if st != "ok":
                    state = st if st == "wait" else f"no {role}"
                    break
                matched[role] = s
            if state == "wait":
                break
            if state != "ok":
                self._drop(c, state)
                continue
            for role in ("gt", "finfo"):
                if role not in matched:
                    st, s = self._match(role, c, True)
                    if st == "ok":
                        matched[role] = s
            out.append(self._frame(c, {r: self.buf[r].pop(s) for r, s in matched.items()}, colors.pop(c)))
            lo = c - self.tol
            for r, b in self.buf.items():
                if r != "color":
                    for s in [s for s in b if s < lo]:
                        del b[s]
        self.yielded += len(out)
        return out

    def _err(self, topic: str, stamp: int, problem: str) -> BagFormatError:
        return BagFormatError(f"{self.path}: topic {topic}, stamp {stamp / 1e9:.9f} s: {problem}")

    def _frame(self, stamp: int, parts: dict[str, Any], color_msg: Any) -> Frame:
        """The frame of matched messages; BagFormatError for anything malformed in them, also what
        a damaged schema decodes into (a message missing fields, fields of the wrong type)."""
        try:
            return self._build_frame(stamp, parts, color_msg)
        except BagFormatError:
            raise
        except Exception as exc:
            raise self._err(self.topics.color, stamp, f"malformed frame messages ({type(exc).__name__}: {exc})"[:500]) \
                from None

    def _build_frame(self, stamp: int, parts: dict[str, Any], color_msg: Any) -> Frame:
        t = self.topics
        try:
            rgb = image_msg_to_rgb(color_msg)
        except ImageFormatError as exc:
            raise self._err(t.color, stamp, str(exc)) from None
        depth = None
        if t.depth is not None:
            try:
                depth = image_msg_to_depth(parts["depth"])
            except ImageFormatError as exc:
                raise self._err(t.depth, stamp, str(exc)) from None
        h, w = rgb.shape[:2]
        if depth is not None and depth.shape != (h, w):
            raise self._err(t.depth, stamp, f"depth image is {depth.shape[1]}x{depth.shape[0]} but colour image "
                            f"{t.color} is {w}x{h}: depth must be registered to colour (e.g. RealSense "
                            "aligned_depth_to_color)")
        info = parts["info"]
        iw, ih = int(info.width), int(info.height)
        if (iw, ih) != (0, 0) and (iw, ih) != (w, h):
            raise self._err(t.camera_info, stamp, f"camera_info is for {iw}x{ih} images but the images are {w}x{h}")
        if int(info.binning_x) > 1 or int(info.binning_y) > 1:
            raise self._err(t.camera_info, stamp, "camera_info with binning is not supported")
        roi = info.roi
        if int(roi.width) and (int(roi.width), int(roi.height)) != (w, h):
            raise self._err(t.camera_info, stamp, "camera_info with a region of interest is not supported")
        K = np.asarray(info.k, dtype=np.float64).reshape(3, 3)
        if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0):
            raise self._err(t.camera_info, stamp, f"camera_info has no valid intrinsics K={K.flatten().tolist()} "
                            "(uncalibrated camera?)")
        if not self._warned_distortion and any(abs(float(d)) > 1e-12 for d in info.d):
            self._warned_distortion = True
            warnings.warn(f"{self.path}: {t.camera_info} has non-zero distortion ({info.distortion_model}); frames "
                          "are used as an undistorted pinhole camera with K", BagWarning, stacklevel=4)
        objects: list[SceneObject] = []
        gt = parts.get("gt")
        if gt is not None:
            if len(gt.object_ids) != len(gt.poses):
                raise self._err(t.ground_truth or "", stamp,
                                f"{len(gt.object_ids)} object_ids but {len(gt.poses)} poses")
            for oid, p in zip(gt.object_ids, gt.poses):
                try:
                    obj_id = int(oid)
                except ValueError:
                    if not self._warned_ids:
                        self._warned_ids = True
                        warnings.warn(f"{self.path}: ground-truth object id {oid!r} is not a BOP integer id; "
                                      "such objects are skipped", BagWarning, stacklevel=4)
                    continue
                q = (p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w)
                R = matrix_from_quaternion(q) if any(q) else np.eye(3)
                objects.append(SceneObject(obj_id, gt=Pose(R, (p.position.x, p.position.y, p.position.z))))
        scene_id = im_id = 0
        finfo = parts.get("finfo")
        if finfo is not None:
            scene_id, im_id = int(finfo.get("scene_id", 0)), int(finfo.get("im_id", 0))
        return Frame(rgb=rgb, depth=depth, K=K, stamp=stamp / 1e9, scene_id=scene_id, im_id=im_id, objects=objects)

    def drop_report(self) -> str | None:
        if not self.dropped:
            return None
        parts = [f"{n} without {reason[3:]} (first at stamp {self.first_dropped[reason] / 1e9:.9f} s)"
                 for reason, n in self.dropped.items()]
        return (f"{self.path}: dropped {sum(self.dropped.values())} incomplete frame(s) - colour images "
                + "; ".join(parts) + f"; {self.yielded} complete frames read")


def read_bag(
    path: str | os.PathLike,
    *,
    color_topic: str | None = None,
    depth_topic: str | None = None,
    camera_info_topic: str | None = None,
    ground_truth_topic: str | None = None,
    require_ground_truth: bool | None = None,
    sync_tolerance_s: float = 0.02,
    strict: bool = False,
) -> Iterator[Frame]:
    """Frames of a rosbag2 bag (a .mcap or .db3 file or a bag directory), in stamp order.

    A frame = a colour image + the depth image + camera_info with the same header stamp (or the
    nearest within `sync_tolerance_s`; 0 = exact only) + the ground truth (ObjectPoses) when the
    bag has it, + its BOP ids from /perception/frame_info when present. Colour images lacking a
    partner are dropped (one BagWarning at the end says how many). `require_ground_truth`:
    None = required when the bag has a ground-truth topic. Topics: see `resolve_topics`.

    Frame.stamp is the header stamp in seconds; depth is float32 metres with NaN = missing. A
    recording without a depth topic (or `depth_topic=""`) gives RGB-only frames (depth None).
    Raises BagFormatError (a ValueError) on images or camera_info that contradict themselves.
    A truncated/damaged file: the complete frames before the damage, then a
    BagTruncatedWarning; with strict=True, BagTruncatedError before any frame.
    Files, topics and truncation (strict) are checked when called; frames are read lazily.
    """
    mcaps = open_bag(path)
    if strict:
        for f in mcaps:
            if not f.complete:
                raise BagTruncatedError(f.truncation_message())
    types: dict[str, str] = {}
    for f in mcaps:
        for ch in f.channels().values():
            types.setdefault(ch.topic, schema_name(ch))
    try:
        topics = resolve_topics(types, path, color_topic=color_topic, depth_topic=depth_topic,
                                camera_info_topic=camera_info_topic, ground_truth_topic=ground_truth_topic)
    except BagFormatError as exc:
        damaged = [f for f in mcaps if not f.complete]
        if damaged:  # most likely cut before the channels were written
            raise BagTruncatedError(f"{damaged[0].truncation_message()}; nothing readable before the damage "
                                    f"({exc})") from None
        raise
    require_gt = (topics.ground_truth is not None) if require_ground_truth is None else bool(require_ground_truth)
    if require_gt and topics.ground_truth is None:
        raise BagFormatError(f"{path}: ground truth required but the bag has no ObjectPoses topic")
    roles = {topics.color: "color", topics.camera_info: "info"}
    if topics.depth is not None:
        roles[topics.depth] = "depth"
    if topics.ground_truth:
        roles[topics.ground_truth] = "gt"
    if topics.frame_info:
        roles[topics.frame_info] = "finfo"
    asm = _Assembler(Path(path), topics, int(round(max(0.0, sync_tolerance_s) * 1e9)), require_gt)
    return _iter_frames(mcaps, roles, asm)


def _iter_frames(mcaps: list[BagFile], roles: dict[str, str], asm: _Assembler) -> Iterator[Frame]:
    for f in mcaps:
        chans = f.channels()
        ids = {i for i, c in chans.items() if c.topic in roles}
        decoders: dict[int, Callable[[bytes], Any]] = {}
        for ch, log_time, data in f.messages(ids):
            dec = decoders.get(ch.id)
            if dec is None:
                dec = decoders[ch.id] = make_decoder(ch, f.path)
            role = roles[ch.topic]
            try:
                msg = dec(data)
                if role == "finfo":
                    msg = json.loads(msg.data)
                    stamp = int(msg.get("stamp_ns", log_time))
                else:
                    stamp = header_stamp_ns(msg.header)
            except Exception as exc:
                raise BagFormatError(f"{f.path}: topic {ch.topic}: cannot decode a message at log time "
                                     f"{log_time / 1e9:.9f} s ({type(exc).__name__}: {exc})") from None
            yield from asm.add(role, stamp, msg)
        if not f.complete:
            yield from asm.finish()
            msg = f.truncation_message() + f"; read the {asm.yielded} complete frames before the damage"
            warnings.warn(msg, BagTruncatedWarning, stacklevel=2)
    yield from asm.finish()
    report = asm.drop_report()
    if report:
        warnings.warn(report, BagWarning, stacklevel=2)
