"""`perception-config estimate`: one estimate through the running configurator's estimate_pose
action, with a line per operator (what a robot program sees); Ctrl-C cancels it."""
from __future__ import annotations

import argparse


def _cmd_estimate(args: argparse.Namespace) -> int:
    from ..ros.estimate_progress import run_estimate

    if not args.stamp >= 0:
        raise ValueError(f"--stamp must be >= 0 seconds (0 = the latest frame), got {args.stamp}")
    stamp_ns = int(round(args.stamp * 1e9))
    return run_estimate(args.object, stamp_ns, args.noise_lambda, args.seed, args.max_operations, args.action,
                        args.timeout)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "estimate", help="one estimate through the running configurator's estimate_pose action, with its progress",
        description="Send one estimate_pose goal to the running configurator (perception-config launch) and print "
                    "a line per operator (action, scores, seconds, operators left), then the result. Ctrl-C cancels "
                    "the goal: the operator in flight finishes, the result holds the hypothesis so far. Exit 0: an "
                    "estimate was made; 1: not; 2: rejected (queue full) or no server; 130: cancelled.")
    p.add_argument("--object", required=True, metavar="ID", help="the object id (BOP obj_id)")
    p.add_argument("--stamp", type=float, default=0.0, metavar="S",
                   help="the camera frame's stamp in seconds (default 0: the latest frame)")
    p.add_argument("--lambda", dest="noise_lambda", type=float, default=-1.0, metavar="L",
                   help="test benches: the simulated initialisation's noise level (negative: the configurator's)")
    p.add_argument("--seed", type=int, default=0, help="test benches: the episode's seed (0: drawn)")
    p.add_argument("--max-operations", type=int, default=0, metavar="N", help="at most N operators (0: max_ops)")
    p.add_argument("--action", default="estimate_pose", help="the action's name (default: estimate_pose)")
    p.add_argument("--timeout", type=float, default=60.0, metavar="S", help="seconds to wait for the result")
    p.set_defaults(func=_cmd_estimate)
