"""The estimate_pose action's cancel latency, and the longest wait of a burst against a full queue.

    .venv/bin/python benchmarks/bench_action.py [--cancels 100] [--out benchmarks/results/action.json]

The four operator nodes and a configurator (fixed pipeline, estimate_timeout 2 s, request_queue
10) run as processes on a small synthetic dataset generated here, whose frames this process
publishes. Reported:
- cancel: goals (a fixed sequence of two refiners, so ten operators) cancelled as soon as their
  first feedback arrives; the operator then in flight
  finishes (its feedback arrives) and the result follows. Latency = the result's arrival minus
  that last feedback's arrival, both at the client (p50, p99, max); goals that ended before
  the cancel took effect (picked at once) are counted apart.
- burst: with refinement_node stopped (SIGSTOP: every estimate waits for it until its deadline),
  40 simultaneous service calls from 4 clients, then 40 goals: the longest wait from sending to
  the answer (target: <= estimate_timeout + 0.5 s = 2.5 s), and how many were served or refused.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import json
import platform
import signal
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
for p in (str(REPO), str(REPO / "benchmarks")):
    if p not in sys.path:
        sys.path.insert(0, p)

import rclpy  # noqa: E402

from perception_config.launcher.ros_environment import configure_ros_environment  # noqa: E402
from perception_config.util.atomic_file import atomic_write  # noqa: E402

OPERATORS = ("generation_node", "refinement_node", "scoring_node", "pick_node")


def publish_ground_truth(node, frame, stamp: int) -> None:
    from perception_config_interfaces.msg import ObjectPoses

    from perception_config.ros.conversions import pose_to_msg

    pub = node.create_publisher(ObjectPoses, "perception/ground_truth", 10)
    deadline = time.monotonic() + 30
    while pub.get_subscription_count() < 2:  # generation_node and pick_node
        if time.monotonic() > deadline:
            raise RuntimeError("perception/ground_truth's subscriptions did not match within 30 s")
        time.sleep(0.05)
    time.sleep(0.5)
    msg = ObjectPoses(object_ids=[str(o.obj_id) for o in frame.objects],
                      poses=[pose_to_msg(o.gt) for o in frame.objects])
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
    pub.publish(msg)


def spin_until(node, cond, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            return False
        rclpy.spin_once(node, timeout_sec=0.005)
    return True


def cancel_once(node, client, goal) -> tuple[int, float, float]:
    """One goal cancelled at its first feedback: (final status, the last feedback's arrival, the
    result's arrival)."""
    arrivals: list[float] = []
    sent = client.send_goal_async(goal, feedback_callback=lambda _m: arrivals.append(time.monotonic()))
    spin_until(node, sent.done, 30)
    handle = sent.result()
    result = handle.get_result_async()
    spin_until(node, lambda: bool(arrivals) or result.done(), 30)
    handle.cancel_goal_async()
    spin_until(node, result.done, 30)
    done = time.monotonic()
    return result.result().status, arrivals[-1] if arrivals else done, done


def measure_cancels(node, client, goal, n: int) -> dict:
    from action_msgs.msg import GoalStatus
    from tqdm import tqdm

    latencies, finished_first = [], 0
    for _ in tqdm(range(n), desc="cancels", unit="goal"):
        status, last_feedback, done = cancel_once(node, client, goal)
        if status != GoalStatus.STATUS_CANCELED:
            finished_first += 1
            continue
        latencies.append(done - last_feedback)
    lat = np.array(latencies) * 1000
    return {"cancelled": len(latencies), "ended_before_the_cancel": finished_first,
            "latency_ms": {"p50": float(np.percentile(lat, 50)), "p99": float(np.percentile(lat, 99)),
                           "max": float(lat.max())} if len(lat) else None}


def measure_burst(node, make_clients, call, n: int) -> dict:
    clients = make_clients()
    t0 = time.monotonic()
    pending = [call(clients[i % len(clients)]) for i in range(n)]
    came: dict[int, float] = {}
    answers: dict[int, object] = {}
    while len(came) < n and time.monotonic() - t0 < 60:
        rclpy.spin_once(node, timeout_sec=0.005)
        for i, p in enumerate(pending):
            if i not in came and p.done():
                came[i] = time.monotonic() - t0
                answers[i] = p.result()
    return {"answered": len(came), "of": n, "longest_wait_s": max(came.values()) if came else None,
            "answers": list(answers.values())}


def goal_burst(node, action, goal, n: int) -> dict:
    """n goals at once: each one's wait from sending to its rejection, or to its result."""
    t0 = time.monotonic()
    sent = [action.send_goal_async(goal) for _ in range(n)]
    results: dict[int, object] = {}
    waits: dict[int, float] = {}
    accepted = rejected = 0
    while len(waits) < n and time.monotonic() - t0 < 60:
        rclpy.spin_once(node, timeout_sec=0.005)
        for i, s in enumerate(sent):
            if i in waits or not s.done():
                continue
            handle = s.result()
            if not handle.accepted:
                waits[i] = time.monotonic() - t0
                rejected += 1
            elif i not in results:
                results[i] = handle.get_result_async()
                accepted += 1
            elif results[i].done():
                waits[i] = time.monotonic() - t0
    return {"answered": len(waits), "of": n, "accepted": accepted, "rejected": rejected,
            "longest_wait_s": max(waits.values()) if waits else None}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cancels", type=int, default=100)
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "action.json"))
    args = ap.parse_args()

    from perception_config_interfaces.action import EstimatePose as EstimatePoseAction
    from perception_config_interfaces.srv import EstimatePose
    from rclpy.action import ActionClient
    from rclpy.qos import QoSProfile

    from bench_burst import publish_frame
    from perception_config.datasets.bop import BopDataset
    from perception_config.datasets.synthetic import generate
    from perception_config.launcher.supervisor import Launcher, NodeSpec

    tmp = Path(tempfile.mkdtemp(prefix="bench_action_"))
    generate(tmp / "data", scenes=1, images_per_scene=1, seed=0, progress=False)
    ds = BopDataset(tmp / "data", split="test")
    frame = ds.load_frame(*ds.image_keys()[0])
    obj = frame.objects[0]
    stamp = 1_700_000_000 * 1_000_000_000
    common = {"models_dir": str(ds.models_dir)}
    specs = [NodeSpec(n, params=common) for n in OPERATORS]
    # a sequence that never picks before the last operator: ten operators to cancel between
    specs.append(NodeSpec("configurator_node", params={**common, "estimate_timeout": 2.0, "noise_lambda": 0.5,
                                                       "fixed_sequence": ["icp_coarse", "icp_fine"]}))

    configure_ros_environment()
    rclpy.init()
    node = rclpy.create_node("bench_action")
    out: dict = {"date": time.strftime("%Y-%m-%d"), "machine": platform.node(), "cpus": os.cpu_count()}
    with open(os.devnull, "w") as quiet, Launcher(specs, log_dir=tmp / "logs", out=quiet) as launcher:
        for name in (*OPERATORS, "configurator_node"):
            launcher.wait_for_line(name, "serving", timeout=60)
        publish_ground_truth(node, frame, stamp)  # the simulated generator and pick need it
        publish_frame(node, frame, stamp)
        deep = QoSProfile(depth=1000)  # a client that sends bursts (docs: the ROS interface)
        action = ActionClient(node, EstimatePoseAction, "estimate_pose", goal_service_qos_profile=deep,
                              result_service_qos_profile=deep, cancel_service_qos_profile=deep)
        action.wait_for_server(timeout_sec=30)

        def goal(lam: float = 0.5, seed: int = 0):
            g = EstimatePoseAction.Goal(object_id=str(obj.obj_id), noise_lambda=lam, seed=seed)
            g.frame.stamp.sec = stamp // 1_000_000_000
            return g

        warm = action.send_goal_async(goal())
        spin_until(node, warm.done, 30)
        r = warm.result().get_result_async()
        spin_until(node, r.done, 30)
        out["cancel"] = measure_cancels(node, action, goal(0.7), args.cancels)
        print("cancel:", out["cancel"], flush=True)

        pid = launcher.pid("refinement_node")
        os.kill(pid, signal.SIGSTOP)
        try:
            req = EstimatePose.Request(object_id=str(obj.obj_id), noise_lambda=0.5)
            req.frame.stamp.sec = stamp // 1_000_000_000
            service = measure_burst(
                node, lambda: [node.create_client(EstimatePose, "estimate_pose", qos_profile=QoSProfile(depth=100))
                               for _ in range(4)], lambda c: c.call_async(req), 40)
            served = sum(a.success for a in service.pop("answers"))
            out["burst_service"] = {**service, "success": served}
            print("burst, service:", out["burst_service"], flush=True)
            out["burst_action"] = goal_burst(node, action, goal(), 40)
            print("burst, action:", out["burst_action"], flush=True)
        finally:
            os.kill(pid, signal.SIGCONT)
    out["load"] = os.getloadavg()
    node.destroy_node()
    rclpy.try_shutdown()
    atomic_write(Path(args.out), json.dumps(out, indent=1).encode())
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
