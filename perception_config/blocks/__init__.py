"""Building blocks: generation, refinement, scoring, pick. See base.py for the block model."""
from __future__ import annotations

import importlib

from .base import REGISTRY, Block, BlockInput, BlockResult, Kind, Param, create, register

# The modules that define blocks; each registers its blocks on import.
BLOCK_MODULES = ("generation", "icp", "depth_refinement", "d2co", "chamfer", "scoring", "pick")


def load_all() -> dict[str, type[Block]]:
    """Import every block module (they register themselves) and return the registry."""
    for module in BLOCK_MODULES:
        importlib.import_module(f"{__name__}.{module}")
    return REGISTRY


__all__ = ["REGISTRY", "Block", "BlockInput", "BlockResult", "Kind", "Param", "create", "register", "load_all"]
