"""The configurator's side of online learning (`learn: true`): versions, frames, the learner process.

- Versions (util/versions.PolicyVersions in `<learn_dir>/policies/`): version 0 is written at
  the first start (`learn_start`: the `policy` file, the fixed pipeline, or an untrained pg);
  later starts serve what the folder says. `policy_version` (a parameter) pins a kept version
  ("" = the newest promoted); the pin is written to versions.json, so the learner compares its
  candidates against the version that actually serves.
- Frames: the configurator subscribes to the camera (camera_frames.CameraFrames, a small cache)
  and to `perception/ground_truth`; after each estimate its frame and the frame's ground truth
  (when replayed) are written to `<learn_dir>/frames/` by a saver thread (store/frames.py), after
  the answer is on its way: the estimate never waits for the disk.
- The pick-success score (a pipeline that scores pick_success): version 0 of
  `<learn_dir>/pick_success/` is the pipeline's model (online/score_learner.py); `score_version` pins
  one. The operator nodes follow that folder themselves (their `pick_success_versions`).
- The learner (online/policy_learner.run_learner) runs in a separate process (multiprocessing spawn,
  niced, one thread), reads the store and the frames, and promotes new versions. This node
  drains its results on a timer (one log line per candidate, policy_learner.format_result) and
  swaps the serving agent only between estimates (`sync`, called with the estimate lock held).
"""
from __future__ import annotations

import multiprocessing
import queue
import tempfile
import threading
from pathlib import Path
from typing import Any, Callable

from rcl_interfaces.msg import SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile
from std_msgs.msg import String

from ..agents import Agent, load_agent, make_agent
from ..agents.policy_io import save_agent
from ..blocks.pipeline import pipeline_reference
from ..online.learner_link import LearnerLink
from ..online.policy_learner import FRAMES, POLICIES, LearnerSettings, format_result, run_learner
from ..online.score_learner import (
    SCORES,
    format_score_result,
    initial_score_version,
    pick_success_block,
    score_versions,
)
from ..rl.env import PerceptionConfigEnv
from ..store.frames import FRAME_RING, save_frame
from ..util.versions import PolicyVersionError, PolicyVersions
from .camera_frames import CameraFrame, CameraFrames, stamp_text
from .configurator_parameters import LEARN_STARTS
from .conversions import msg_to_pose
from .request_fields import parse_stamp
from .stamp_cache import StampCache

# Frames the configurator keeps for capture, by stamp: as many as an operator node (its cache_size
# default). Captured at the request and after the estimate; an estimate of the cell pipeline takes
# 0.5-3 s, longer than 8 frames of a 10 Hz camera, which lost 33 of 40 frames in a simulated cell.
CAMERA_CACHE = 30

SAVE_QUEUE = 16  # frames waiting for the saver thread
LEARNER_STOP_TIMEOUT = 5.0


def version_qos() -> QoSProfile:
    """perception/policy_version: the last value for late joiners (transient local, depth 1)."""
    return QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def initial_version(versions: PolicyVersions, start: str, policy: str, env: PerceptionConfigEnv,
                    fixed_sequence: list[str], extra: dict[str, Any]) -> str | None:
    """Write version 0 when the folder has none; the version written (None: kept what was there)."""
    if versions.newest() is not None:
        return None
    if start not in LEARN_STARTS:
        raise ValueError(f"learn_start must be one of {LEARN_STARTS}, got {start!r}")
    if policy and start != "policy":
        raise ValueError(f"learn_start {start!r} with a policy file: version 0 would be ambiguous "
                         "(learn_start 'policy' serves the file first)")
    if policy:
        return versions.promote(policy, {"start": "policy", "source": policy})
    if start == "untrained":
        agent: Agent = make_agent("pg", env, seed=0)
    else:
        agent = make_agent("fixed", env, sequence=fixed_sequence)
    with tempfile.TemporaryDirectory(dir=versions.folder) as tmp:
        path = save_agent(agent, Path(tmp) / ("start.safetensors" if agent.tensors() else "start.json"), extra)
        return versions.promote(path, {"start": "untrained" if start == "untrained" else "fixed"})


class NodeLearning:
    """Online learning of one configurator node (module docstring)."""

    def __init__(self, node: Node, env: PerceptionConfigEnv, learn_dir: str, *, start: str, policy: str,
                 fixed_sequence: list[str], pipeline: Any, models_dir: str, margin: float, every: int,
                 train_episodes: int, check_episodes: int, pinned: str, camera_qos: str, use_depth: bool,
                 frame_ring: int = FRAME_RING, score_pinned: str = "") -> None:
        if not learn_dir:
            raise ValueError("learn is true but learn_dir is not set: give a folder for the learning state "
                             "(episodes.sqlite, frames/, policies/, learner.log)")
        if not (0.0 <= margin < 1.0):
            raise ValueError(f"learn_margin must be in [0, 1), got {margin}")
        if every < 1 or train_episodes < 0 or check_episodes < 1:
            raise ValueError(f"need learn_every >= 1, learn_train_episodes >= 0, learn_check_episodes >= 1; got "
                             f"{every}, {train_episodes}, {check_episodes}")
        self.node = node
        self.env = env
        self.dir = Path(learn_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.log = node.get_logger()
        self.versions = PolicyVersions(self.dir / POLICIES)
        ref = pipeline_reference(pipeline) if isinstance(pipeline, (str, Path)) else None
        extra = {"env_settings": env.settings.replace(time_mode="cost_table").to_json(), "pipeline": ref}
        made = initial_version(self.versions, start, policy, env, fixed_sequence, extra)
        if made is not None:
            self.log.info(f"learn: version {made} written to {self.versions.folder} "
                          f"({'the policy ' + policy if policy else start})")
        self.versions.select(pinned or None)  # raises naming the kept versions when unknown
        self.scores: PolicyVersions | None = None
        made = initial_score_version(self.dir, env.pipeline)
        if made is not None:
            self.log.info(f"learn: pick_success version {made} written to {self.dir / SCORES} (the pipeline's model)")
        if pick_success_block(env.pipeline) is not None:
            self.scores = score_versions(self.dir)
            self.scores.select(score_pinned or None)
        elif score_pinned:
            raise ValueError("score_version is set but the pipeline has no pick_success score")
        self.serving: str | None = None
        self._synced_stamp: tuple[int, int] | None = None
        self.frame_ring = int(frame_ring)
        self.pub = node.create_publisher(String, "perception/policy_version", version_qos())

        # the frames of the estimates, and their replayed ground truth
        group = MutuallyExclusiveCallbackGroup()
        self.camera = CameraFrames(node, CAMERA_CACHE, camera_qos, callback_group=group, use_depth=use_depth)
        self.ground_truth: StampCache[dict[str, Any]] = StampCache(16)
        from perception_config_interfaces.msg import ObjectPoses

        node.create_subscription(ObjectPoses, "perception/ground_truth", self._on_ground_truth, 10,
                                 callback_group=group)
        self._saved: dict[int, None] = {}
        self._missing_logged: set[int] = set()
        self._save_queue: queue.Queue[tuple[int, CameraFrame, dict[int, Any]] | None] = queue.Queue(SAVE_QUEUE)
        self._saver = threading.Thread(target=self._save_loop, name="learn-frames", daemon=True)
        self._saver.start()
        self.frames_saved = 0

        # the learner process
        self.settings = LearnerSettings(models_dir=str(Path(models_dir).resolve()), pipeline=ref,
                                        env_settings=extra["env_settings"], margin=float(margin), every=int(every),
                                        train_episodes=int(train_episodes), check_episodes=int(check_episodes))
        ctx = multiprocessing.get_context("spawn")
        self.link = LearnerLink(ctx)  # never blocks this node when the learner dies (learner_link.py)
        self.process = ctx.Process(target=run_learner, args=(str(self.dir), self.settings),
                                   kwargs={"link": self.link.learner_end}, name="learner", daemon=True)
        self.process.start()
        self.link.started()
        self.log.info(f"learn: learner process {self.process.pid} started (a candidate every {every} stored "
                      f"estimates, {train_episodes} training episodes, replay check on the newest {check_episodes} "
                      f"of the held-out frames, margin {margin:g}); state in {self.dir}")

    # -- versions ----------------------------------------------------------------------------------
    def wanted(self) -> str:
        version = self.versions.current()
        if version is None:
            raise PolicyVersionError(f"no policy version in {self.versions.folder}")
        return version

    def load(self, version: str) -> Agent:
        return load_agent(self.versions.path(version), self.env)

    def start(self, swap: Callable[[str, Agent], None]) -> None:
        """At start-up: serve the version the folder selects, or refuse to start (ValueError naming
        the version and why it cannot be loaded: a node that cannot serve what it was told to
        must not serve something else silently)."""
        version = self.wanted()
        try:
            agent = self.load(version)
        except (ValueError, OSError) as exc:
            raise ValueError(f"learn: policy version {version} in {self.versions.folder} cannot be loaded ({exc}); "
                             "pin a kept version with policy_version, or restore the file") from None
        swap(version, agent)
        self.serving = version
        self._synced_stamp = self.versions.stamp()
        self.log.info(f"learn: serving policy version {version}")
        self.pub.publish(String(data=version))

    def sync(self, swap: Callable[[str, Agent], None]) -> None:
        """Call with the estimate lock held: when the version that should serve changed (a
        promotion, a pin), load it and `swap(version, agent)`; publish the serving version.
        A version that cannot be loaded is logged and the current one keeps serving."""
        stamp = self.versions.stamp()
        if stamp == self._synced_stamp:  # one try (and at most one error line) per change of the index
            return
        try:
            version = self.wanted()
            if version != self.serving:
                agent = self.load(version)
                before = self.serving
                swap(version, agent)
                self.serving = version
                self.log.info(f"learn: serving policy version {version}" + (f" (was {before})" if before else ""))
                self.pub.publish(String(data=version))
            self._synced_stamp = stamp
        except (PolicyVersionError, ValueError, OSError) as exc:
            self._synced_stamp = stamp  # not again until the index changes
            self.log.error(f"learn: cannot serve the new version ({exc}); version {self.serving} keeps serving")

    def check_pin(self, value: str) -> SetParametersResult:
        """The `policy_version` parameter: pin a kept version ("" = the newest); unknown: refused."""
        try:
            self.versions.select(value or None)
        except (PolicyVersionError, OSError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def check_score_pin(self, value: str) -> SetParametersResult:
        """The `score_version` parameter: pin a kept score version ("" = the newest)."""
        if self.scores is None:
            return SetParametersResult(successful=False, reason="the pipeline has no pick_success score")
        try:
            self.scores.select(value or None)
        except (PolicyVersionError, OSError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def drain(self) -> None:
        """The learner's results: one log line each (the cell simulation parses them)."""
        for kind, payload in self.link.results():
            if kind == "result":
                line = format_score_result(payload) if payload.get("what") == "pick_success" else \
                    format_result(payload)
                # two call sites: rclpy refuses one call site logging at two severities
                # ("Logger severity cannot be changed between calls"), and the line was lost
                if payload["outcome"] == "failed":
                    self.log.warning(line)
                else:
                    self.log.info(line)

    # -- frames ------------------------------------------------------------------------------------
    def _on_ground_truth(self, msg: Any) -> None:
        try:
            stamp = parse_stamp(msg.header.stamp, "header.stamp")
        except ValueError:
            return
        self.ground_truth.put(stamp, dict(zip(msg.object_ids, msg.poses)))

    def has_ground_truth(self, stamp_ns: int, obj_id: int) -> bool:
        """Whether the object's ground truth came for this frame (perception/ground_truth)."""
        for object_id in self.ground_truth.get(stamp_ns) or {}:
            try:
                if int(object_id) == int(obj_id):
                    return True
            except ValueError:
                continue
        return False

    def capture(self, stamp_ns: int, warn: bool = True) -> None:
        """Queue the estimate's frame for saving (once per stamp; 0 = the latest); never blocks.
        The configurator captures at the request (the camera cache holds a few frames only, and
        an estimate may outlast them) and again after the estimate (for the stamp the operators
        used); `warn`: log a frame that is not here."""
        if stamp_ns and stamp_ns in self._saved:
            return
        item = self.camera.frames.get(stamp_ns)
        if isinstance(item, CameraFrame) and item.stamp_ns in self._saved:
            return
        if not isinstance(item, CameraFrame):
            if warn and stamp_ns not in self._missing_logged:
                self._missing_logged.add(stamp_ns)
                self.log.warning(f"learn: the frame at {stamp_text(stamp_ns)} did not reach the configurator "
                                 "(camera topics): its estimate is stored but cannot be replayed")
            return
        gt: dict[int, Any] = {}
        for object_id, pose in (self.ground_truth.get(item.stamp_ns) or {}).items():
            try:
                gt[int(object_id)] = msg_to_pose(pose)
            except ValueError:
                continue
        try:
            self._save_queue.put_nowait((item.stamp_ns, item, gt))
        except queue.Full:
            self.log.warning(f"learn: frame at {stamp_text(stamp_ns)} not saved: {SAVE_QUEUE} frames already wait")
            return
        self._saved[item.stamp_ns] = None
        while len(self._saved) > 4 * self.frame_ring:
            self._saved.pop(next(iter(self._saved)))

    def _save_loop(self) -> None:
        while True:
            job = self._save_queue.get()
            if job is None:
                return
            stamp, item, gt = job
            try:
                save_frame(self.dir / FRAMES, stamp, item.frame, gt, keep=self.frame_ring)
                self.frames_saved += 1
            except (OSError, ValueError) as exc:
                self._saved.pop(stamp, None)
                self.log.error(f"learn: frame at {stamp_text(stamp)} not saved ({type(exc).__name__}: {exc}); "
                               "the estimate is stored, serving goes on")

    def close(self) -> None:
        self.link.stop()
        try:
            self._save_queue.put(None, timeout=2.0)
        except queue.Full:
            pass
        self._saver.join(timeout=10.0)
        if not self.link.ready():
            # still starting (importing): it has read and written nothing yet, so nothing is lost by
            # ending it now, and it would not look at `stop` before its imports are done
            self.process.terminate()
        self.process.join(LEARNER_STOP_TIMEOUT)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(2.0)
        if self.process.is_alive():
            self.process.kill()
            self.process.join(2.0)
        self.link.close()
