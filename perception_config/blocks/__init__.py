"""Building blocks: generation, refinement, scoring, pick. See base.py for the block model.

Block modules are discovered, not listed: every module of this package registers its blocks
when imported (the `@register` decorator), and `load_all()` imports them all, plus the modules
that other installed packages name under the entry-point group `perception_config.blocks`.
Adding a block is adding one file here (or in your own package with that entry point).
"""
from __future__ import annotations

import importlib
import pkgutil
from importlib.metadata import entry_points

from .base import REGISTRY, Block, BlockInput, BlockResult, Kind, Param, create, register

ENTRY_POINT_GROUP = "perception_config.blocks"
_NOT_BLOCK_MODULES = frozenset({"base", "pipeline"})


def block_modules() -> list[str]:
    """The modules of this package that define blocks (every module but base and pipeline)."""
    return sorted(m.name for m in pkgutil.iter_modules(__path__) if m.name not in _NOT_BLOCK_MODULES)


def load_all() -> dict[str, type[Block]]:
    """Import every block module (they register themselves) and return the registry."""
    for module in block_modules():
        importlib.import_module(f"{__name__}.{module}")
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        try:
            ep.load()
        except Exception as exc:  # a broken plug-in names itself instead of a bare traceback
            raise ImportError(f"block plug-in {ep.name!r} ({ep.value}, entry point group {ENTRY_POINT_GROUP}) "
                              f"failed to load: {type(exc).__name__}: {exc}") from exc
    return REGISTRY


__all__ = ["REGISTRY", "Block", "BlockInput", "BlockResult", "Kind", "Param", "create", "register", "load_all",
           "block_modules"]
