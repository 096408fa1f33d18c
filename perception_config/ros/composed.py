"""perception_cell: the cell's nodes composed into one process, one multi-threaded executor.

    perception_cell --nodes '[{"executable": "generation_node", "args": ["--ros-args", "-p", ...]}, ...]'

`perception-config launch --composed` (and replay-check --composed) start it; each entry is a
node of launcher/resolution.py (one of COMPOSABLE) with the ROS arguments it would get as its
own process, which apply to that node only (its parameters, remappings, `__node` name).

What composition changes, and what it does not:
- The configurator's operator calls run the operator nodes' service callbacks in this process
  (local_services.py): no serialisation and no middleware round trip. Every service, topic,
  lifecycle transition and `/diagnostics` status stays on the ROS graph as with separate
  processes: outside callers see the same nodes.
- One Python interpreter: the nodes share its lock (the blocks' numeric work mostly releases
  it) and their fate: a node that crashes the interpreter takes the cell down; one that raises
  in a callback does not (guard.py). Separate processes isolate a node that segfaults or leaks
  and let one node be restarted alone; they cost a middleware round trip per operator call.
"""
from __future__ import annotations

import argparse
import json
from typing import Any, Callable

from rclpy.executors import MultiThreadedExecutor

from . import local_services
from .node_main import run_nodes

# executable -> (module, class) of the nodes that can be composed
COMPOSABLE = {
    "generation_node": ("generation_node", "GenerationNode"),
    "refinement_node": ("refinement_node", "RefinementNode"),
    "scoring_node": ("scoring_node", "ScoringNode"),
    "pick_node": ("pick_node", "PickNode"),
    "configurator_node": ("configurator_node", "ConfiguratorNode"),
}
EXECUTABLE = "perception_cell"


def parse_nodes(text: str) -> list[dict[str, Any]]:
    """The --nodes JSON: a list of {"executable": one of COMPOSABLE, "args": [str, ...]}."""
    try:
        nodes = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"--nodes is not JSON: {exc}") from None
    if not isinstance(nodes, list) or not nodes:
        raise ValueError("--nodes must be a non-empty JSON list")
    for i, entry in enumerate(nodes):
        if not isinstance(entry, dict) or entry.get("executable") not in COMPOSABLE:
            raise ValueError(f"--nodes[{i}]: executable must be one of {', '.join(COMPOSABLE)}")
        args = entry.get("args", [])
        if not isinstance(args, list) or not all(isinstance(a, str) for a in args):
            raise ValueError(f"--nodes[{i}].args must be a list of strings")
    return nodes


def node_factory(executable: str, args: list[str]) -> Callable[[], Any]:
    import importlib

    module, name = COMPOSABLE[executable]
    cls = getattr(importlib.import_module(f"{__package__}.{module}"), name)
    # the node's own arguments only: the process's (none here) are not applied to it
    return lambda: cls(cli_args=list(args), use_global_arguments=False)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog=EXECUTABLE, description=__doc__.splitlines()[0])
    parser.add_argument("--nodes", required=True, help="JSON list of {executable, args} (module docstring)")
    parser.add_argument("--threads", type=int, default=0,
                        help="executor threads (default: one per node, at least 4)")
    known, _ros_args = parser.parse_known_args(argv)
    try:
        nodes = parse_nodes(known.nodes)
    except ValueError as exc:
        parser.error(str(exc))
    threads = known.threads or max(4, len(nodes))
    local_services.enable()
    run_nodes([node_factory(n["executable"], n.get("args", [])) for n in nodes], args=None,
              executor_factory=lambda: MultiThreadedExecutor(num_threads=threads))


if __name__ == "__main__":
    main()
