"""Building blocks: generation, refinement, scoring, pick. See base.py for the block model.

Block modules are discovered, not listed: every module of this package registers its blocks
when imported (the `@register` decorator), and `load_all()` (base.py) imports them all, plus the modules
that other installed packages name under the entry-point group `perception_config.blocks`.
Adding a block is adding one file here (or in your own package with that entry point).
"""
from __future__ import annotations

from .base import (
                   ENTRY_POINT_GROUP,
                   REGISTRY,
                   Block,
                   BlockInput,
                   BlockResult,
                   Kind,
                   Param,
                   block_modules,
                   create,
                   load_all,
                   register,
)

__all__ = ["REGISTRY", "Block", "BlockInput", "BlockResult", "Kind", "Param", "create", "register", "load_all",
           "block_modules", "ENTRY_POINT_GROUP"]
