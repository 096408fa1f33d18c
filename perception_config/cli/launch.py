"""`perception-config launch`: start the ROS 2 nodes as processes (launcher/)."""
from __future__ import annotations

import argparse
from pathlib import Path

from .notices import warn


def _cmd_launch(args: argparse.Namespace) -> int:
    from ..launcher.resolution import parse_nodes, resolve_nodes
    from ..launcher.supervisor import run

    def say(text: str) -> None:
        print(f"[launch] {text}", flush=True)

    specs = resolve_nodes(
        parse_nodes(args.nodes) if args.nodes else None, models=args.models, pipeline=args.pipeline,
        policy=args.policy, bag=args.bag, rate=args.rate, params_file=args.params_file,
        say=say, remaps=_remaps(args.remap or []), warn=warn,
    )
    bring_up = None
    if not args.unmanaged:  # the managed nodes wait unconfigured; launch drives them to active
        from ..ros.lifecycle_manager import MANAGED_EXECUTABLES, bring_up_launched

        for spec in specs:
            if Path(str(spec.executable)).name in MANAGED_EXECUTABLES:
                spec.params["autostart"] = False

        def bring_up(launcher) -> bool:
            # the launcher's own `say`: it writes under the lock its node-output threads write under,
            # so a status line is never cut by a node's line (print writes the text and the newline apart)
            return bring_up_launched(launcher, launcher.say)

    return run(specs, log_dir=args.log_dir, composed=args.composed, bring_up=bring_up)


def _remaps(items: list[str]) -> dict[str, str]:
    """--remap FROM:=TO options as a mapping; a malformed one is a clear error."""
    out = {}
    for item in items:
        source, sep, target = item.partition(":=")
        if not sep or not source or not target:
            raise ValueError(f"--remap {item!r}: expected FROM:=TO, e.g. "
                             "camera/color/image_raw:=/camera/camera/color/image_raw")
        out[source] = target
    return out


def add_parser(sub: argparse._SubParsersAction) -> None:
    la = sub.add_parser(
        "launch", help="start the ROS 2 nodes as processes, stream their logs, stop them on Ctrl-C",
        description="Start the nodes as separate processes (or, --composed, in one) with the loopback ROS "
                    "defaults; their output is printed as [node_name] lines. The operator nodes and the "
                    "configurator are managed (lifecycle) nodes: launch configures them in order, then activates "
                    "them, and stops everything naming the node (and its reason) when a transition fails. "
                    "Ctrl-C or SIGTERM stops them all (SIGINT, then SIGKILL after 10 s; exit 0 if all stopped "
                    "cleanly). A node that dies stops the others (exit 1).",
    )
    la.add_argument("--nodes", default=None, metavar="LIST",
                    help="comma-separated, from: generation, refinement, scoring, pick, configurator, bag_replay "
                         "(default: generation,refinement,scoring,pick,configurator)")
    la.add_argument("--models", type=Path, default=None, metavar="DIR",
                    help="BOP models folder "
                         "(default: data/default/models, else the procedural parts in data/parts_models)")
    la.add_argument("--pipeline", type=Path, default=None, metavar="YAML|NAME",
                    help="pipeline YAML, or a shipped pipeline by name: default, rgb, cell, pick_success "
                         "(default: default; cell = the real-camera set-up without ground truth, "
                         "docs/concepts/cell_without_ground_truth.md)")
    la.add_argument("--policy", default=None, metavar="FILE|none",
                    help="the policy the configurator serves, or none for its fixed pipeline; required when "
                         "the configurator starts, unless a --params-file sets policy or learn")
    la.add_argument("--bag", type=Path, default=None, metavar="FILE",
                    help="also start bag_replay_node on this MCAP bag")
    la.add_argument("--rate", type=float, default=None, metavar="R", help="bag_replay_node's replay rate")
    la.add_argument("--params-file", type=Path, default=None, metavar="YAML",
                    help="ROS params file passed to every node; the options above win over it")
    la.add_argument("--remap", action="append", metavar="FROM:=TO",
                    help="topic remapping for the operator nodes and the configurator (repeatable), e.g. the "
                         "camera driver's topics: camera/color/image_raw:=/camera/camera/color/image_raw")
    la.add_argument("--composed", action="store_true",
                    help="run the operator nodes and the configurator in one process with one multi-threaded "
                         "executor (the operator calls skip the middleware; docs/how-to/compose_the_cell.md); "
                         "default: one process per node")
    la.add_argument("--unmanaged", action="store_true",
                    help="let each node configure and activate itself at start (autostart), without the ordered "
                         "bring-up: quick tests")
    la.add_argument("--log-dir", type=Path, default=None, metavar="DIR",
                    help="also write each node's output to DIR/<node>.log")
    la.set_defaults(func=_cmd_launch)
