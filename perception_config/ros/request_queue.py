"""A bounded queue of service requests: every request is answered, none is silently dropped.

A node runs its requests one at a time. Before this queue, the service callback ran the work in
the executor thread, so while one request was served the others stayed in the middleware's
history (keep-last 10 by default) and the 11th and later were overwritten without an answer.

Now the executor thread only takes requests and sends answers; the work runs on one worker
thread, in arrival order. A request that finds `depth` requests already waiting is answered at
once with success=false "busy: N requests queued (request_queue=M)".

The service's QoS (`service_qos`) keeps all: the middleware holds every request until the node
takes it (taken at once, so few are ever held), and every answer until it is delivered. A
keep-last history of request_queue + 65 still lost the oldest requests of a burst of 80 that
arrived faster than one take per executor iteration (measured; docs/results/ros.md).

The answers of a service go to every client's reader of that service, which sorts out its own:
a client whose reader keeps the last 10 (rclpy's default) can lose its answer among many others
(14 clients in one process, 10 requests each: about a third lost). Clients that expect bursts
create their clients with a deeper QoS (e.g. `QoSProfile(depth=1000)`).

Busy answers are paced: at most one leaves the node every PACE (2 ms), so that a burst's
refusals do not arrive at the clients' readers faster than their executors take them (the busy
answers of a burst are otherwise all sent within a millisecond or two, and a default client
lost its own among them). The served answers are paced by the work itself.
"""
from __future__ import annotations

import concurrent.futures
import queue
import threading
from collections import deque
from typing import Any, Callable

from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future

MAX_REQUEST_QUEUE = 1000
PACE = 0.002  # s between two busy answers (paced refusals, below)
MAX_PACED = 1000  # busy answers waiting for their turn; beyond, answered at once


def check_request_queue(depth: Any) -> int:
    """The `request_queue` parameter: requests that may wait while one is served (0..1000)."""
    if isinstance(depth, bool) or not isinstance(depth, int) or not 0 <= depth <= MAX_REQUEST_QUEUE:
        raise ValueError(f"request_queue must be an integer in 0..{MAX_REQUEST_QUEUE}, got {depth!r}")
    return depth


def service_qos() -> QoSProfile:
    """Reliable, keep-all: no request is overwritten before the node takes it (the queue then
    bounds what the node holds), no answer before it is delivered."""
    return QoSProfile(history=HistoryPolicy.KEEP_ALL, depth=0, reliability=ReliabilityPolicy.RELIABLE)


class RequestQueue:
    """One worker thread running a node's requests in arrival order, at most `depth` waiting.

    Used from the executor thread: `busy()` when a request arrives (the refusal, or None), then
    `await run(fn, ...)` for each piece of its work, and `done()` when it is answered. The worker
    wakes the executor through a guard condition when a piece finishes.
    """

    def __init__(self, node: Node, depth: int, name: str) -> None:
        self.depth = check_request_queue(depth)
        self.held = 0  # requests admitted and not yet answered (waiting or being served)
        self.most_held = 0  # the high-water mark, for diagnostics
        self.refused = 0  # requests answered busy since the start, for diagnostics
        self._count = threading.Lock()  # busy()/done() come from the executor and from in-process callers
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        self._wake = node.create_guard_condition(lambda: None, callback_group=ReentrantCallbackGroup())
        self._paced: deque[Future] = deque()  # busy answers waiting for their turn
        self._pace_timer = node.create_timer(PACE, self._release, callback_group=ReentrantCallbackGroup())
        self._pace_timer.cancel()  # runs only while a busy answer waits
        # A daemon thread: a block that never returns must not keep the process from exiting.
        self._thread = threading.Thread(target=self._work, name=f"{name}_worker", daemon=True)
        self._thread.start()

    def busy(self) -> str | None:
        """None when the request is admitted (and counted), else the busy message."""
        with self._count:
            if self.held > self.depth:
                self.refused += 1
                return f"busy: {self.held - 1} requests queued (request_queue={self.depth})"
            self.held += 1
            self.most_held = max(self.most_held, self.held)
            return None

    def done(self) -> None:
        with self._count:
            self.held -= 1

    async def pace(self) -> None:
        """Await this busy answer's turn: at most one busy answer per PACE seconds leaves the node
        (module docstring); beyond MAX_PACED waiting, at once."""
        if len(self._paced) >= MAX_PACED:
            return
        turn: Future = Future()
        self._paced.append(turn)
        if self._pace_timer.is_canceled():
            self._pace_timer.reset()
        await turn

    def _release(self) -> None:
        if self._paced:
            self._paced.popleft().set_result(None)
        if not self._paced:
            self._pace_timer.cancel()

    async def run(self, fn: Callable[..., Any], *args: Any) -> Any:
        """fn(*args) on the worker thread, after the work queued before it; its result, or what it raised."""
        future: Future = Future()
        self._jobs.put((fn, args, future))
        return await future

    def run_waiting(self, fn: Callable[..., Any], args: tuple, timeout: float) -> Any:
        """fn(*args) on the worker thread, in turn, the calling thread waiting for it (another
        node of the process: local_services.py); its result or what it raised; TimeoutError after
        `timeout` s (the work still runs)."""
        future: concurrent.futures.Future = concurrent.futures.Future()
        self._jobs.put((fn, args, future))
        return future.result(timeout=max(0.0, timeout))

    def _work(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            fn, args, future = job
            try:
                future.set_result(fn(*args))
            except Exception as exc:  # handed to the awaiting callback, which answers
                future.set_exception(exc)
            if isinstance(future, concurrent.futures.Future):  # a thread waits on it, not the executor
                continue
            try:
                self._wake.trigger()
            except Exception:  # the node is being destroyed
                return

    def close(self) -> None:
        """Stop the worker after the work already queued (it is a daemon: exit does not wait)."""
        self._jobs.put(None)
