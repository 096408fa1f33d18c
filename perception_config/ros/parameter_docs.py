"""The nodes' parameters as a table for the generated reference, read from the very
NodeParameter specs the nodes declare (parameters.py): what `ros2 param describe` shows,
without a running ROS graph."""
from __future__ import annotations

from typing import Any

from . import bag_replay_node, configurator_parameters, generation_node, pick_node, refinement_node, scoring_node
from .managed_node import MANAGED_PARAMETERS


def node_parameter_table() -> dict[str, list[dict[str, Any]]]:
    """Node executable name -> one row per parameter, in declaration order: name, type,
    default (None: not set), description, range ("[low, high]", "inf" = no upper limit;
    "" = none) and read_only (read only at start-up)."""
    nodes = {
        "generation_node": generation_node.PARAMETERS + MANAGED_PARAMETERS,
        "refinement_node": refinement_node.PARAMETERS + MANAGED_PARAMETERS,
        "scoring_node": scoring_node.PARAMETERS + MANAGED_PARAMETERS,
        "pick_node": pick_node.PARAMETERS + MANAGED_PARAMETERS,
        "configurator_node": configurator_parameters.PARAMETERS + MANAGED_PARAMETERS,
        "bag_replay_node": bag_replay_node.PARAMETERS,
    }
    return {node: [p.row() for p in parameters] for node, parameters in nodes.items()}
