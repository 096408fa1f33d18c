"""`perception-config replay-check`: the nodes against the in-process episodes, through a bag
(ros/replay_check.py)."""
from __future__ import annotations

import argparse


def _cmd_replay_check(args: argparse.Namespace) -> int:
    from ..ros import replay_check  # imports rclpy: only for this command

    return replay_check.run_cli(args)


def add_parser(sub: argparse._SubParsersAction) -> None:
    rc = sub.add_parser(
        "replay-check", help="record test images to MCAP, replay them through the nodes, compare with in-process",
        description="Record the policy's test images to MCAP, replay them through generation/refinement/scoring/pick/"
                    "configurator/bag_replay nodes (separate processes, or --composed), estimate every object with "
                    "estimate_pose and "
                    "compare success and operator time with the same episodes in-process. Exit 0 when the success "
                    "rates agree within binomial noise.",
    )
    rc.add_argument("--dataset", required=True, help="BOP dataset folder (its test split is replayed)")
    rc.add_argument("--policy", default=None, help="policy file (default: the fixed pipeline)")
    rc.add_argument("--pipeline", default=None, help="pipeline YAML (default: the policy's, else the built-in one)")
    rc.add_argument("--out", default="outputs/replay_check", help="folder for the bag, logs, results.json and the plot")
    rc.add_argument("--images", type=int, default=8, help="test images to record and replay (8)")
    rc.add_argument("--lambda", dest="noise_lambda", type=float, default=0.5, help="noise level of the episodes (0.5)")
    rc.add_argument("--rate", type=float, default=1.0, help="replay rate, x the recorded 10 Hz (1.0)")
    rc.add_argument("--composed", action="store_true",
                    help="run the operator nodes and the configurator in one process (perception_cell), as "
                         "`launch --composed`; bag_replay_node stays a process of its own")
    rc.set_defaults(func=_cmd_replay_check)
