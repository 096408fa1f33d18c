"""Benchmark bag_replay_node: 640x480 RGB-D frames replayed from a bag by the node (its own OS
process) and received by this process over Fast DDS (rclpy subscriptions on colour and depth,
messages deserialized as any consumer would). Target: >= 30 complete frames per second.

    python benchmarks/bench_replay.py [--frames 60] [--runs 3] [--out benchmarks/results/replay.json]

1. rate 0 (as fast as possible), `--runs` times: complete frames received (colour + depth of
   the same stamp) per second, from the first to the last complete frame, and the frame loss;
   the median over the runs is the figure.
2. rate 1.0 on a 30 Hz recording: no frame may be lost, and the replay must take the recorded time.

Frames: the same as benchmarks/bench_bag.py (the real LM-O test frame with per-frame noise when
../shared/data/lmo is present, else procedural images), recorded at 30 Hz with zstd. The node and
this subscriber share the machine's 2 cores. ROS_DOMAIN_ID: yours if exported, else a random one
in 60..100 so the run does not disturb other ROS processes on the machine.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import json
import platform
import random
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
for p in (REPO, Path(__file__).resolve().parent):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

os.environ.setdefault("ROS_DOMAIN_ID", str(random.SystemRandom().choice([d for d in range(60, 101) if d != 42])))
os.environ["PYTHONUNBUFFERED"] = "1"

from bench_bag import base_frame, frames  # noqa: E402
from perception_config.datasets.bag import write_frames  # noqa: E402
from perception_config.util.atomic_file import atomic_write  # noqa: E402

NODE = Path(sys.executable).parent / "bag_replay_node"
TARGET_FPS = 30.0


class Receiver:
    """Colour and depth subscriptions of this process; arrival time per stamp."""

    def __init__(self) -> None:
        from perception_config.launcher.ros_environment import configure_ros_environment

        configure_ros_environment()  # the loopback defaults, before rclpy starts
        import rclpy
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import Image

        rclpy.init()
        self.node = rclpy.create_node(f"bench_replay_{os.getpid()}")
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.color: dict[int, float] = {}
        self.depth: dict[int, float] = {}
        for topic, store in (("camera/color/image_raw", self.color), ("camera/depth/image_raw", self.depth)):
            self.node.create_subscription(Image, topic, lambda m, s=store: s.setdefault(
                m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec, time.monotonic()), qos)

    def run(self, bag: Path, rate: float, n: int, log: Path) -> dict:
        import rclpy

        self.color.clear()
        self.depth.clear()
        with open(log, "w") as f:
            proc = subprocess.Popen(
                [str(NODE), "--ros-args", "-p", f"bag:={bag}", "-p", f"rate:={rate}",
                 "-p", "wait_for_subscribers:=1", "-p", "start_delay:=0.5"],
                stdout=f, stderr=subprocess.STDOUT, env=dict(os.environ))
            deadline = time.monotonic() + 60 + n / TARGET_FPS / max(rate, 1e-3)
            while proc.poll() is None and time.monotonic() < deadline:
                rclpy.spin_once(self.node, timeout_sec=0.01)
            end = time.monotonic() + 0.5  # messages still in flight
            while time.monotonic() < end:
                rclpy.spin_once(self.node, timeout_sec=0.01)
            if proc.poll() is None:
                proc.kill()
            code = proc.wait()
        out = log.read_text()
        complete = sorted(max(self.color[s], self.depth[s]) for s in set(self.color) & set(self.depth))
        span = complete[-1] - complete[0] if len(complete) > 1 else 0.0
        node_fps = re.search(r"frames in [\d.]+ s \(([\d.]+) frames/s\)", out)
        gaps = [b - a for a, b in zip(complete, complete[1:])]
        return {
            "rate": rate, "exit_code": code, "frames": n, "colour_received": len(self.color),
            "depth_received": len(self.depth), "complete": len(complete), "lost": n - len(complete),
            "loss": 1 - len(complete) / n, "seconds": span,
            "fps": (len(complete) - 1) / span if span > 0 else 0.0,
            "max_gap_ms": 1e3 * max(gaps) if gaps else None,
            "node_fps": float(node_fps.group(1)) if node_fps else None,
        }

    def close(self) -> None:
        import rclpy

        self.node.destroy_node()
        rclpy.try_shutdown()


def write_json(path: Path, data: dict) -> None:
    atomic_write(path, json.dumps(data, indent=2) + "\n")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--record-hz", type=float, default=30.0, help="recording rate of the bag (paced run)")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "replay.json")
    args = ap.parse_args(argv)
    if not NODE.exists():
        print(f"{NODE} is missing: install the package (source scripts/setup_env.sh)", file=sys.stderr)
        return 1

    source, base = base_frame()
    h, w = base.rgb.shape[:2]
    receiver = Receiver()
    with tempfile.TemporaryDirectory(prefix="bench_replay_") as tmp:
        bag = Path(tmp) / "replay.mcap"
        write_frames(frames(base, args.frames), bag, args.record_hz)
        mb = bag.stat().st_size / 1e6
        print(f"bag_replay_node -> rclpy subscriber, {source}, {w}x{h} RGB-D, {args.frames} frames recorded at "
              f"{args.record_hz:g} Hz ({mb:.0f} MB, zstd), ROS_DOMAIN_ID {os.environ['ROS_DOMAIN_ID']}, "
              f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
        print(f"{'run':>4} {'rate':>5} {'complete':>9} {'lost':>5} {'seconds':>8} {'frames/s':>9} "
              f"{'node frames/s':>14} {'max gap ms':>11} {'exit':>5}")
        rows = []
        for k in range(args.runs + 1):
            rate = 0.0 if k < args.runs else 1.0
            r = receiver.run(bag, rate, args.frames, Path(tmp) / f"node_{k}.log")
            r["log_tail"] = (Path(tmp) / f"node_{k}.log").read_text()[-600:] if r["exit_code"] else ""
            rows.append(r)
            label = str(k + 1) if rate == 0 else "paced"
            print(f"{label:>4} {rate:>5g} {r['complete']:>4}/{r['frames']:<4} {r['lost']:>5} {r['seconds']:>8.2f} "
                  f"{r['fps']:>9.1f} {r['node_fps'] or float('nan'):>14.1f} {r['max_gap_ms'] or float('nan'):>11.1f} "
                  f"{r['exit_code']:>5}")
    receiver.close()

    fast = [r for r in rows if r["rate"] == 0]
    paced = rows[-1]
    expected_s = (args.frames - 1) / args.record_hz
    summary = {
        "median_fps_rate0": statistics.median(r["fps"] for r in fast),
        "median_loss_rate0": statistics.median(r["loss"] for r in fast),
        "max_loss_rate0": max(r["loss"] for r in fast),
        "paced_lost": paced["lost"],
        "paced_seconds": paced["seconds"],
        "paced_expected_seconds": expected_s,
        "target_fps": TARGET_FPS,
    }
    summary["target_met"] = summary["median_fps_rate0"] >= TARGET_FPS and paced["lost"] == 0
    print(f"rate 0: median {summary['median_fps_rate0']:.1f} complete frames/s, median loss "
          f"{summary['median_loss_rate0']:.1%} (target >= {TARGET_FPS:g} frames/s: "
          f"{'met' if summary['median_fps_rate0'] >= TARGET_FPS else 'NOT met'})")
    print(f"rate 1.0 at {args.record_hz:g} Hz: {paced['lost']} frames lost, {paced['seconds']:.2f} s for a recording "
          f"of {expected_s:.2f} s")
    write_json(args.out, {
        "source": source, "size": f"{w}x{h}", "frames": args.frames, "record_hz": args.record_hz,
        "bag_mb": mb, "summary": summary, "runs": rows,
        "machine": {"python": platform.python_version(), "machine": platform.machine(), "cpus": os.cpu_count(),
                    "load_average": os.getloadavg()[0]},
    })
    print(f"wrote {args.out}")
    return 0 if all(r["exit_code"] == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
