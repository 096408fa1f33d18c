"""generation_node: serves `generate_hypothesis` (GenerateHypothesis.srv).

Method `simulated_init`: the ground-truth pose replayed on `perception/ground_truth`
(ObjectPoses) perturbed by the lambda noise model (geometry.perturb), as in the paper's
systematic evaluation. Requests name the frame by stamp (zero = latest) and wait at most
`frame_timeout` seconds for a frame not yet arrived.
"""
from __future__ import annotations

import time

import numpy as np
import rclpy
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node

from perception_config_interfaces.msg import Hypothesis, ObjectPoses
from perception_config_interfaces.srv import GenerateHypothesis

from ..datasets.bop import load_models_info
from ..geometry import perturb
from .conversions import msg_to_pose, pose_to_msg, stamp_to_nanoseconds
from .stamp_cache import StampCache

METHODS = ("simulated_init",)


class GenerationNode(Node):
    def __init__(self) -> None:
        super().__init__("generation_node")
        self.declare_parameter("models_dir", "")
        self.declare_parameter("default_method", "simulated_init")
        self.declare_parameter("default_lambda", 0.5)
        self.declare_parameter("cache_size", 30)
        self.declare_parameter("frame_timeout", 1.0)

        models_dir = self.get_parameter("models_dir").value
        self._diameters: dict[str, float] = {}
        if models_dir:
            info = load_models_info(models_dir)
            self._diameters = {str(k): float(v["diameter"]) / 1000.0 for k, v in info.items()}
        else:
            self.get_logger().warning("no models_dir set: simulated_init cannot scale noise by diameter")
        self._ground_truth: StampCache[dict[str, object]] = StampCache(self.get_parameter("cache_size").value)
        self._rng = np.random.default_rng()

        # Separate callback groups: the service may wait for a frame while the subscription fills the cache.
        self.create_subscription(
            ObjectPoses, "perception/ground_truth", self._on_ground_truth, 10,
            callback_group=MutuallyExclusiveCallbackGroup(),
        )
        self.create_service(
            GenerateHypothesis, "generate_hypothesis", self._on_generate,
            callback_group=MutuallyExclusiveCallbackGroup(),
        )
        self.get_logger().info(f"serving generate_hypothesis ({', '.join(METHODS)}), {len(self._diameters)} models")

    def _on_ground_truth(self, msg: ObjectPoses) -> None:
        self._ground_truth.put(stamp_to_nanoseconds(msg.header.stamp), {"header": msg.header, "poses": dict(zip(msg.object_ids, msg.poses))})

    def _on_generate(self, request: GenerateHypothesis.Request, response: GenerateHypothesis.Response) -> GenerateHypothesis.Response:
        start = time.perf_counter()
        try:
            response.hypothesis = self._generate(request)
            response.success = True
            response.message = "ok"
        except ValueError as exc:
            response.success = False
            response.message = str(exc)
        except Exception as exc:  # a service answers whatever happens, and the node keeps serving
            self.get_logger().error(f"generate_hypothesis failed: {exc!r}")
            response.success = False
            response.message = f"internal error: {exc!r}"
        response.elapsed = time.perf_counter() - start
        return response

    def _generate(self, request: GenerateHypothesis.Request) -> Hypothesis:
        method = request.method or self.get_parameter("default_method").value
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; this node serves {', '.join(METHODS)}")
        lam = request.noise_lambda
        if np.isfinite(lam) and lam < 0:
            lam = self.get_parameter("default_lambda").value
        if not np.isfinite(lam) or not 0.0 <= lam <= 10.0:
            raise ValueError(f"noise_lambda must be in [0, 10] (negative = the node's default), got {lam}")
        stamp_ns = stamp_to_nanoseconds(request.frame.stamp)
        frame = self._ground_truth.get(stamp_ns, self.get_parameter("frame_timeout").value)
        if frame is None:
            which = "any frame" if stamp_ns == 0 else f"the frame stamped {stamp_ns} ns"
            raise ValueError(f"no ground truth for {which} arrived within frame_timeout")
        if request.object_id not in frame["poses"]:
            raise ValueError(f"object {request.object_id!r} is not in that frame (objects: {sorted(frame['poses'])})")
        if request.object_id not in self._diameters:
            raise ValueError(f"object {request.object_id!r} has no model in models_dir")
        gt = msg_to_pose(frame["poses"][request.object_id])
        rng = np.random.default_rng(request.seed) if request.seed else self._rng
        pose = perturb(gt, lam, self._diameters[request.object_id], rng)

        hyp = Hypothesis()
        hyp.header = frame["header"]
        hyp.object_id = request.object_id
        hyp.pose = pose_to_msg(pose)
        return hyp


def main(args: list[str] | None = None) -> None:
    rclpy.init(args=args)
    node = GenerationNode()
    executor = MultiThreadedExecutor(num_threads=4)
    executor.add_node(node)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
