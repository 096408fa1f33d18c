"""A bounded cache of recent messages keyed by stamp, with a bounded wait for one not yet arrived.

Operator nodes keep the camera frames (and replayed ground truth) here so service requests can
name a frame by its stamp and large images cross the middleware once.
"""
from __future__ import annotations

import threading
import time
from collections import OrderedDict
from typing import Generic, TypeVar

T = TypeVar("T")


class StampCache(Generic[T]):
    """Thread-safe: subscriptions `put`, service callbacks `get` from other executor threads."""

    def __init__(self, capacity: int = 30) -> None:
        if capacity < 1:
            raise ValueError(f"cache capacity must be >= 1, got {capacity}")
        self._capacity = capacity
        self._items: OrderedDict[int, T] = OrderedDict()
        self._latest: int | None = None
        self._cond = threading.Condition()

    def put(self, stamp_ns: int, item: T) -> None:
        with self._cond:
            self._items[stamp_ns] = item
            self._items.move_to_end(stamp_ns)
            while len(self._items) > self._capacity:
                self._items.popitem(last=False)
            if self._latest is None or stamp_ns >= self._latest:
                self._latest = stamp_ns
            self._cond.notify_all()

    def get(self, stamp_ns: int, timeout: float) -> T | None:
        """The item with this stamp (0 = the latest), waiting up to `timeout` seconds for it."""
        deadline = time.monotonic() + max(0.0, timeout)
        with self._cond:
            while True:
                if stamp_ns == 0 and self._latest is not None and self._latest in self._items:
                    return self._items[self._latest]
                if stamp_ns != 0 and stamp_ns in self._items:
                    return self._items[stamp_ns]
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._cond.wait(remaining)

    def has(self, stamp_ns: int) -> bool:
        with self._cond:
            return stamp_ns in self._items

    def stamps(self) -> list[int]:
        with self._cond:
            return list(self._items)

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)
