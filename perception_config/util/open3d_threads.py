"""Open3D's CPU thread limit: one thread makes its ICP bitwise reproducible.

Open3D's ICP sums its normal equations in parallel (oneTBB) in an order that depends on thread
scheduling: the same call gives poses that differ in the 16th-17th digit, which later operators
and a sampled action can amplify (and Gymnasium's check_env sees in the info's float64 scores).
Cost-table training and the cost-table environment run Open3D on one thread for that reason.
Kept free of torch and the agents so the environment can use it without their import time.
"""
from __future__ import annotations

from contextlib import contextmanager
from typing import Iterator


def limit_open3d_threads(n: int) -> int:
    """Set Open3D's CPU thread limit (process-wide); returns the previous one (0: not settable,
    Open3D < 0.20, which is then not reproducible; see docs/concepts/reproducibility.md)."""
    import open3d as o3d

    util = o3d.utility
    if not hasattr(util, "set_max_threads"):
        return 0
    previous = int(util.get_max_threads())
    util.set_max_threads(int(n))
    return previous


@contextmanager
def open3d_single_thread(active: bool = True) -> Iterator[None]:
    """Open3D limited to one thread inside the block when `active`, the previous limit restored
    on exit."""
    previous = limit_open3d_threads(1) if active else 0
    try:
        yield
    finally:
        if previous:
            limit_open3d_threads(previous)
