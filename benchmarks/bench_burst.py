"""Bursts of simultaneous requests: which ones a client's QoS depth lets it receive.

    .venv/bin/python benchmarks/bench_burst.py [--rounds 3] [--out benchmarks/results/burst.json]

One scoring_node (request_queue 10, the default) serves a frame of a small synthetic dataset
generated here; this process sends bursts of `score_hypothesis` requests, all at once, from C
clients in this process whose answer readers keep the last D answers (rclpy's default D = 10),
and waits up to 30 s for every answer. Each burst is answered by the node (served, or "busy" at
once when the queue is full); an answer a client never receives is "lost": a service's answers
reach every client's reader of that service, so a reader that keeps D answers can lose its own
among the others. Reported per (clients, burst, depth): served, busy and lost, summed over the
rounds, and the seconds until the last answer arrived. Writes JSON.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import rclpy  # noqa: E402

from perception_config.launcher.ros_environment import configure_ros_environment  # noqa: E402
from perception_config.util.atomic_file import atomic_write  # noqa: E402

GRID = [(1, 20), (1, 50), (1, 200), (4, 40), (4, 200)]  # (clients, requests in the burst)
DEPTHS = [10, 100, 1000]


def publish_frame(node, frame, stamp: int) -> None:
    from sensor_msgs.msg import CameraInfo, Image

    from perception_config.ros.conversions import frame_to_msgs

    pubs = [node.create_publisher(t, n, 10) for t, n in (
        (Image, "camera/color/image_raw"), (Image, "camera/depth/image_raw"), (CameraInfo, "camera/camera_info"))]
    deadline = time.monotonic() + 30
    while any(p.get_subscription_count() < 1 for p in pubs):
        if time.monotonic() > deadline:
            raise RuntimeError("scoring_node's camera subscriptions did not match within 30 s")
        time.sleep(0.05)
    time.sleep(0.5)
    color, depth, info = frame_to_msgs(frame, stamp)
    for pub, msg in ((pubs[2], info), (pubs[1], depth), (pubs[0], color)):
        pub.publish(msg)
    time.sleep(1.0)


def burst(node, request, clients: int, n: int, depth: int, timeout: float = 30.0) -> dict:
    from perception_config_interfaces.srv import ScoreHypothesis
    from rclpy.qos import QoSProfile

    cs = [node.create_client(ScoreHypothesis, "score_hypothesis", qos_profile=QoSProfile(depth=depth))
          for _ in range(clients)]
    try:
        for c in cs:  # each client once first: its answer reader is then known to the node
            if not c.wait_for_service(timeout_sec=20):
                raise RuntimeError("score_hypothesis did not appear")
            for _ in range(20):
                f = c.call_async(request)
                rclpy.spin_until_future_complete(node, f, timeout_sec=1.0)
                if f.done():
                    break
        t0 = time.monotonic()
        futures = [cs[i % clients].call_async(request) for i in range(n)]
        last = 0.0
        while not all(f.done() for f in futures) and time.monotonic() - t0 < timeout:
            rclpy.spin_once(node, timeout_sec=0.05)
            if any(f.done() for f in futures):
                last = time.monotonic() - t0
        answers = [f.result() for f in futures if f.done()]
        served = sum(a.success for a in answers)
        return {"served": served, "busy": len(answers) - served, "lost": n - len(answers), "last_answer_s": last}
    finally:
        for c in cs:
            node.destroy_client(c)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "burst.json"))
    args = p.parse_args()

    from perception_config_interfaces.msg import Hypothesis
    from perception_config_interfaces.srv import ScoreHypothesis

    from perception_config.datasets.bop import BopDataset
    from perception_config.datasets.synthetic import generate
    from perception_config.launcher.supervisor import Launcher, NodeSpec
    from perception_config.ros.conversions import pose_to_msg

    tmp = Path(tempfile.mkdtemp(prefix="bench_burst_"))
    generate(tmp / "data", scenes=1, images_per_scene=1, seed=0, progress=False)
    ds = BopDataset(tmp / "data", split="test")
    frame = ds.load_frame(*ds.image_keys()[0])
    obj = frame.objects[0]
    stamp = 1_700_000_000 * 1_000_000_000
    request = ScoreHypothesis.Request(hypothesis=Hypothesis(object_id=str(obj.obj_id), pose=pose_to_msg(obj.gt)))
    request.hypothesis.header.stamp.sec = 1_700_000_000

    configure_ros_environment()
    rclpy.init()
    node = rclpy.create_node("bench_burst")
    rows = []
    with open(os.devnull, "w") as quiet, Launcher(
            [NodeSpec("scoring_node", params={"models_dir": str(ds.models_dir)})], log_dir=tmp / "logs",
            out=quiet) as launcher:
        launcher.wait_for_line("scoring_node", "serving", timeout=60)
        publish_frame(node, frame, stamp)
        for clients, n in GRID:
            for depth in DEPTHS:
                total = {"served": 0, "busy": 0, "lost": 0, "last_answer_s": []}
                for _ in range(args.rounds):
                    r = burst(node, request, clients, n, depth)
                    for k in ("served", "busy", "lost"):
                        total[k] += r[k]
                    total["last_answer_s"].append(round(r["last_answer_s"], 3))
                row = {"clients": clients, "requests": n, "depth": depth, "rounds": args.rounds, **total}
                rows.append(row)
                print(f"{clients} client(s), burst {n:4d}, depth {depth:5d}: served {total['served']:4d}, "
                      f"busy {total['busy']:4d}, lost {total['lost']:4d}  (last answer {total['last_answer_s']} s)",
                      flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    out = {"date": time.strftime("%Y-%m-%d"), "machine": platform.node(), "cpus": os.cpu_count(),
           "load": os.getloadavg(), "request_queue": 10, "rows": rows}
    atomic_write(Path(args.out), json.dumps(out, indent=1).encode())
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
