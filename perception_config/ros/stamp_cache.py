"""A bounded cache of recent messages keyed by stamp.

Operator nodes keep the camera frames (and replayed ground truth) here so service requests can
name a frame by its stamp and large images cross the middleware once. Lookups never wait: a
node awaits the next arrival in its executor and asks again (operator_node.py).
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Generic, TypeVar

T = TypeVar("T")


class StampCache(Generic[T]):
    """The last `capacity` items by stamp. Thread-safe: subscriptions `put`, service callbacks
    `get` from other executor threads."""

    def __init__(self, capacity: int = 30) -> None:
        if capacity < 1:
            raise ValueError(f"cache capacity must be >= 1, got {capacity}")
        self._capacity = capacity
        self._items: OrderedDict[int, T] = OrderedDict()
        self._latest: int | None = None
        self._lock = threading.Lock()

    def put(self, stamp_ns: int, item: T) -> None:
        with self._lock:
            self._items[stamp_ns] = item
            self._items.move_to_end(stamp_ns)
            while len(self._items) > self._capacity:
                self._items.popitem(last=False)
            if self._latest is None or stamp_ns >= self._latest:
                self._latest = stamp_ns

    def get(self, stamp_ns: int) -> T | None:
        """The item with this stamp (0 = the latest), or None when it is not (or no longer) here."""
        with self._lock:
            if stamp_ns == 0:
                return self._items.get(self._latest) if self._latest is not None else None
            return self._items.get(stamp_ns)

    def has(self, stamp_ns: int) -> bool:
        with self._lock:
            return stamp_ns in self._items

    def stamps(self) -> list[int]:
        with self._lock:
            return list(self._items)

    def __len__(self) -> int:
        with self._lock:
            return len(self._items)
