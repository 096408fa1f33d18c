"""The content checksum that policy and model files carry in their metadata: a sha256 over the
canonical metadata and the tensors, so a file is checked without a deep-learning framework."""
from __future__ import annotations

import hashlib
import json
from typing import Any

import numpy as np

CHECKSUM_KEY = "sha256"  # metadata entry: sha256 of the canonical metadata and the tensors (content_checksum)


def content_checksum(meta: dict[str, Any], tensors: dict[str, np.ndarray]) -> str:
    """sha256 over the canonical metadata JSON (without its checksum entry) and every tensor's
    name, dtype, shape and bytes, in name order."""
    h = hashlib.sha256()
    body = {k: v for k, v in meta.items() if k != CHECKSUM_KEY}
    h.update(json.dumps(body, sort_keys=True, separators=(",", ":")).encode())
    for name in sorted(tensors):
        a = np.ascontiguousarray(tensors[name])
        h.update(f"\0{name}\0{a.dtype.str}\0{a.shape}\0".encode())
        h.update(a.tobytes())
    return h.hexdigest()
