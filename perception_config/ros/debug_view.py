"""The configurator's live view: each estimate as an image and as 3D markers.

Topics (relative names, like the others):
  perception/debug_image  sensor_msgs/Image rgb8: the camera frame of the estimate (scaled to at
                          most `debug_image_max_width` px wide) with the final hypothesis's
                          outline (green: picked, orange: not picked), the object id, its
                          scores and the operator trace (vision/debug_overlay.py)
  perception/markers      visualization_msgs/MarkerArray: the model's mesh (decimated to at most
                          `marker_max_triangles`) as a TRIANGLE_LIST at the hypothesis pose, and
                          a TEXT_VIEW_FACING label with the object id, outcome and scores;
                          namespaces `model` and `label`, marker id = the object id, so the
                          next estimate of the same object replaces its markers
Both carry the hypothesis's header: frame_id = the camera frame of the colour image
(e.g. camera_color_optical_frame), stamp = the image's stamp. Poses are model-to-camera, so
a viewer whose display frame is the camera frame needs no TF at all.

Cost: nothing is built for a topic nobody subscribes to. The camera subscriptions this view
needs (`camera/color/image_raw`, `camera/camera_info`, the configurator's `camera_qos`) exist
only while perception/debug_image has a subscriber (checked every second), so without a
viewer the configurator receives no images. Frames are kept as messages (no conversion on
arrival) and converted only for the estimate that shows them.
The markers need no image. Drawing and publishing run on the view's own thread: an estimate
only hands its result over (microseconds) and its answer never waits for the view; the first
estimate of an object also prepares its marker mesh there (quadric decimation, up to ~1.3 s for
a 46k-triangle LM-O model). `timing()` reports both figures.
"""
from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any

import numpy as np
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import Point
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from ..core.geometry import Pose
from ..core.models import ObjectModel
from ..datasets.bag import image_msg_to_rgb, rgb_to_image_fields
from ..vision.debug_overlay import draw_hypothesis, info_lines
from .camera_frames import camera_qos, stamp_text
from .conversions import msg_to_pose, stamp_to_nanoseconds
from .stamp_cache import StampCache

FRAMES_KEPT = 8  # colour images kept by stamp for the view (an estimate runs on a recent frame)
QUEUE = 4  # estimates waiting for the view thread; beyond, the oldest is not shown
PICKED = ColorRGBA(r=0.16, g=0.86, b=0.24, a=0.7)
NOT_PICKED = ColorRGBA(r=1.0, g=0.59, b=0.0, a=0.7)
WHITE = ColorRGBA(r=1.0, g=1.0, b=1.0, a=1.0)


def decimated_mesh(model: ObjectModel, max_triangles: int) -> tuple[np.ndarray, np.ndarray]:
    """The model's vertices (metres) and triangles, reduced to at most `max_triangles` by
    quadric decimation (Open3D) when it has more."""
    if max_triangles < 1:
        raise ValueError(f"marker_max_triangles must be >= 1, got {max_triangles}")
    v, f = np.array(model.vertices, np.float64), np.array(model.faces, np.int64)  # copies: open3d writes
    if len(f) <= max_triangles:
        return v, f
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(f.astype(np.int32)))
    small = mesh.simplify_quadric_decimation(target_number_of_triangles=int(max_triangles))
    return np.asarray(small.vertices, np.float64), np.asarray(small.triangles, np.int64)


def triangle_points(vertices: np.ndarray, faces: np.ndarray) -> list[Point]:
    """A TRIANGLE_LIST's points: three per triangle, in the model frame (metres)."""
    return [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in vertices[faces.reshape(-1)]]


def hypothesis_markers(header: Header, object_id: str, pose_msg: Any, mesh_points: list[Point], label: str,
                       picked: bool, label_offset: float) -> MarkerArray:
    """The model mesh at the pose and a text label `label_offset` metres above it (camera -y)."""
    mid = int(object_id) if object_id.isdigit() else abs(hash(object_id)) % (2**31)
    model = Marker(header=header, ns="model", id=mid, type=Marker.TRIANGLE_LIST, action=Marker.ADD,
                   pose=pose_msg, color=PICKED if picked else NOT_PICKED, lifetime=Duration())
    model.scale.x = model.scale.y = model.scale.z = 1.0
    model.points = mesh_points
    text = Marker(header=header, ns="label", id=mid, type=Marker.TEXT_VIEW_FACING, action=Marker.ADD,
                  color=WHITE, text=label, lifetime=Duration())
    text.pose.position.x = pose_msg.position.x
    text.pose.position.y = pose_msg.position.y - label_offset
    text.pose.position.z = pose_msg.position.z
    text.pose.orientation.w = 1.0
    text.scale.z = max(0.01, label_offset / 3)  # text height, metres
    return MarkerArray(markers=[model, text])


def rgb_image_msg(rgb: np.ndarray, header: Header) -> Image:
    return Image(header=header, **rgb_to_image_fields(rgb))


class DebugView:
    """The debug image and marker publishers of a node, with the lazy camera subscriptions the
    image needs. `show` hands a finished estimate to the view's own thread, which draws and
    publishes it: the estimate's answer never waits for the view."""

    def __init__(self, node: Node, qos: str = "reliable", max_width: int = 640, max_triangles: int = 500) -> None:
        if int(max_width) < 0:
            raise ValueError(f"debug_image_max_width must be >= 0 (0 = full size), got {max_width}")
        if int(max_triangles) < 1:
            raise ValueError(f"marker_max_triangles must be >= 1, got {max_triangles}")
        self.node = node
        self.max_width = int(max_width)
        self.max_triangles = int(max_triangles)
        self._qos = camera_qos(qos)
        self.image_pub = node.create_publisher(Image, "perception/debug_image", 2)
        self.marker_pub = node.create_publisher(MarkerArray, "perception/markers", 2)
        self.images: StampCache[Image] = StampCache(FRAMES_KEPT)
        self.infos: StampCache[CameraInfo] = StampCache(FRAMES_KEPT)
        self._subs: list[Any] = []
        self._meshes: dict[int, list[Point]] = {}
        # estimates waiting to be shown; a view that falls behind drops the oldest
        self._jobs: deque[tuple] = deque(maxlen=QUEUE)
        self._wake = threading.Condition()
        self._closed = False
        self.added: deque[float] = deque(maxlen=1000)  # s added to each estimate (handing it over)
        self.seconds: deque[float] = deque(maxlen=1000)  # s the view thread spent per estimate shown
        self._thread = threading.Thread(target=self._loop, name="debug_view", daemon=True)
        self._thread.start()
        self._timer = node.create_timer(1.0, self._follow_viewers)
        self._follow_viewers()

    # -- camera subscriptions, only while someone watches the image ---------------------------
    def _follow_viewers(self) -> None:
        watched = self.image_pub.get_subscription_count() > 0
        if watched and not self._subs:
            self._subs = [
                self.node.create_subscription(Image, "camera/color/image_raw", self._on_image, self._qos),
                self.node.create_subscription(CameraInfo, "camera/camera_info", self._on_info, self._qos),
            ]
        elif not watched and self._subs:
            for sub in self._subs:
                self.node.destroy_subscription(sub)
            self._subs = []

    def _on_image(self, msg: Image) -> None:
        self.images.put(stamp_to_nanoseconds(msg.header.stamp), msg)

    def _on_info(self, msg: CameraInfo) -> None:
        self.infos.put(stamp_to_nanoseconds(msg.header.stamp), msg)

    # -- one estimate --------------------------------------------------------------------------
    def show(self, hypothesis: Any, model: ObjectModel, operations: list[str], picked: bool,
             seconds: float | None = None) -> None:
        """Hand a finished estimate's final hypothesis (a perception_config_interfaces/Hypothesis)
        to the view thread; nothing when no one subscribes to either topic."""
        start = time.perf_counter()
        want_image = self.image_pub.get_subscription_count() > 0
        want_markers = self.marker_pub.get_subscription_count() > 0
        if want_image or want_markers:
            with self._wake:
                self._jobs.append((hypothesis, model, list(operations), bool(picked), seconds, want_image,
                                   want_markers))
                self._wake.notify()
        self.added.append(time.perf_counter() - start)

    def _loop(self) -> None:
        while True:
            with self._wake:
                while not self._jobs and not self._closed:
                    self._wake.wait()
                if self._closed:
                    return
                job = self._jobs.popleft()
            start = time.perf_counter()
            if self._draw(*job):
                self.seconds.append(time.perf_counter() - start)

    def _draw(self, hypothesis: Any, model: ObjectModel, operations: list[str], picked: bool,
              seconds: float | None, want_image: bool, want_markers: bool) -> bool:
        """Publish the estimate's image and markers; False (logged) when it could not be shown."""
        object_id = hypothesis.object_id
        try:
            pose = msg_to_pose(hypothesis.pose)
            scores = dict(zip(hypothesis.score_names, (float(s) for s in hypothesis.scores)))
            if want_image:
                lines = info_lines(object_id, scores, operations, picked, seconds)
                msg = self._image(hypothesis.header, model, pose, lines, picked)
                if msg is not None:
                    self.image_pub.publish(msg)
            if want_markers:
                label = f"{object_id} {'picked' if picked else 'not picked'} " + " ".join(
                    f"{k} {v:.2f}" for k, v in scores.items())
                self.marker_pub.publish(hypothesis_markers(hypothesis.header, object_id, hypothesis.pose,
                                                           self._mesh_points(model), label, picked,
                                                           0.6 * model.diameter))
        except Exception as exc:  # an unusable frame or pose, a node shutting down: say so, keep going
            if not self._closed:
                self.node.get_logger().warning(f"debug view: object {object_id}: {exc}")
            return False
        return True

    def _mesh_points(self, model: ObjectModel) -> list[Point]:
        points = self._meshes.get(model.obj_id)  # only the view thread fills it
        if points is None:
            points = triangle_points(*decimated_mesh(model, self.max_triangles))
            self._meshes[model.obj_id] = points
        return points

    def _image(self, header: Header, model: ObjectModel, pose: Pose, lines: list[str], picked: bool) -> Image | None:
        stamp = stamp_to_nanoseconds(header.stamp)
        color = self.images.get(stamp)
        info = self.infos.get(stamp) or self.infos.get(0)
        if color is None or info is None:
            missing = "colour image" if color is None else "camera_info"
            self.node.get_logger().debug(f"debug image: no {missing} of the frame at {stamp_text(stamp)} "
                                         "(the view follows the camera only while debug_image is watched)")
            return None
        K = np.asarray(info.k, dtype=np.float64).reshape(3, 3)
        img = draw_hypothesis(image_msg_to_rgb(color), K, model, pose, lines, picked, self.max_width)
        return rgb_image_msg(img, header)

    def close(self, timeout: float = 2.0) -> None:
        """Stop the view thread (before the node is destroyed)."""
        with self._wake:
            self._closed = True
            self._wake.notify()
        self._thread.join(timeout)

    def timing(self) -> str:
        """What the view cost (for the node's exit summary)."""
        if not self.seconds:
            return "debug view: nothing shown"
        return (f"debug view: {len(self.seconds)} estimates shown, median {np.median(self.added) * 1000:.3f} ms "
                f"added to an estimate; drawing and publishing on the view thread median "
                f"{np.median(self.seconds) * 1000:.2f} ms, max {max(self.seconds) * 1000:.1f} ms")
