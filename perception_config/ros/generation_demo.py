"""The foundation's end-to-end check: this process replays one BOP frame's ground truth and asks
a generation_node in another process for hypotheses over a lambda sweep, printing the errors.

    python -m perception_config.ros.generation_demo --dataset data/default
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import rclpy
from rclpy.node import Node

from perception_config_interfaces.msg import ObjectPoses
from perception_config_interfaces.srv import GenerateHypothesis

from ..datasets.bop import BopDataset
from ..geometry import rotation_angle
from .conversions import msg_to_pose, pose_to_msg, seconds_to_stamp


def run(dataset: Path, split: str, lambdas: list[float], timeout: float) -> int:
    ds = BopDataset(dataset, split=split)
    scene_id, im_id = ds.image_keys()[0]
    frame = ds.load_frame(scene_id, im_id, with_models=False)
    node = Node("generation_demo")
    pub = node.create_publisher(ObjectPoses, "perception/ground_truth", 10)
    client = node.create_client(GenerateHypothesis, "generate_hypothesis")
    if not client.wait_for_service(timeout_sec=timeout):
        print(f"generate_hypothesis did not appear within {timeout} s: is generation_node running "
              f"with the same ROS_DOMAIN_ID?", file=sys.stderr)
        return 1
    while pub.get_subscription_count() == 0:
        rclpy.spin_once(node, timeout_sec=0.05)
    gt = ObjectPoses()
    gt.header.stamp = seconds_to_stamp(frame.stamp if frame.stamp > 0 else 1.0)
    gt.header.frame_id = "camera_color_optical_frame"
    gt.object_ids = [str(o.obj_id) for o in frame.objects]
    gt.poses = [pose_to_msg(o.gt) for o in frame.objects]
    pub.publish(gt)
    print(f"published ground truth of scene {scene_id} image {im_id}: objects {gt.object_ids}")
    print(f"{'object':>6} {'lambda':>6} {'|dt| mm':>8} {'angle deg':>9} {'round trip ms':>13}")
    obj = frame.objects[0]
    for lam in lambdas:
        req = GenerateHypothesis.Request(object_id=str(obj.obj_id), method="simulated_init", noise_lambda=lam, seed=1)
        req.frame.stamp = gt.header.stamp
        t0 = node.get_clock().now()
        future = client.call_async(req)
        rclpy.spin_until_future_complete(node, future, timeout_sec=timeout)
        res = future.result()
        ms = (node.get_clock().now() - t0).nanoseconds / 1e6
        if res is None or not res.success:
            print(f"request failed: {res.message if res else 'no answer'}", file=sys.stderr)
            return 1
        pose = msg_to_pose(res.hypothesis.pose)
        dt = np.linalg.norm(pose.t - obj.gt.t) * 1000
        print(f"{obj.obj_id:>6} {lam:>6.1f} {dt:>8.1f} {np.degrees(rotation_angle(pose.R, obj.gt.R)):>9.1f} {ms:>13.2f}")
    node.destroy_node()
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dataset", type=Path, required=True)
    p.add_argument("--split", default="test")
    p.add_argument("--lambdas", default="0,0.2,0.5,1.0")
    p.add_argument("--timeout", type=float, default=20.0)
    args = p.parse_args(argv)
    rclpy.init()
    try:
        return run(args.dataset, args.split, [float(x) for x in args.lambdas.split(",")], args.timeout)
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
