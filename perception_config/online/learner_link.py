"""The link between a configurator and its learner process: a stop signal, a ready flag, results.

None of the three can block the configurator when the learner dies at any point (SIGTERM to the
process group reaches both; a kill; an out-of-memory end):
- stop: one byte on a pipe the learner polls. A multiprocessing Event cannot be used: its
  `set()` (Condition.notify_all) waits for every sleeper to acknowledge its wake-up, and a learner
  killed inside `Event.wait()` never does, so the configurator hung on exit;
- ready: a lock-free shared byte;
- results: a pipe whose write end only the learner holds, so a learner that dies mid-message
  ends the configurator's read with EOFError instead of leaving it waiting for the rest (a
  multiprocessing Queue's reader holds its own copy of the write end).
When the configurator dies, the learner's `stopped()` becomes true (EOF on the stop pipe).

Use: `link = LearnerLink(ctx)`; `Process(..., kwargs={"link": link.learner_end})`; after
`start()`, `link.started()` (closes the configurator's copies of the learner's ends).
"""
from __future__ import annotations

import multiprocessing.connection
from typing import Any, Iterator


class LearnerEnd:
    """The learner's side (pickled into the spawned process)."""

    def __init__(self, stop: multiprocessing.connection.Connection, results: multiprocessing.connection.Connection,
                 ready: Any) -> None:
        self._stop, self._results, self._ready = stop, results, ready

    def stopped(self) -> bool:
        """True once the configurator asked to stop, or closed its end (it ended)."""
        try:
            return self._stop.poll(0)
        except (OSError, EOFError):
            return True

    def wait(self, timeout: float) -> bool:
        """Sleep up to `timeout` s, returning early (True) when stopped."""
        try:
            return self._stop.poll(timeout)
        except (OSError, EOFError):
            return True

    def set_ready(self) -> None:
        self._ready.value = 1

    def send(self, kind: str, payload: dict[str, Any]) -> None:
        """One result for the configurator; dropped when it is gone."""
        try:
            self._results.send((kind, payload))
        except (OSError, ValueError):
            pass


class LearnerLink:
    """The configurator's side (module docstring)."""

    def __init__(self, ctx: Any) -> None:
        stop_r, self._stop_w = ctx.Pipe(duplex=False)
        self._results_r, results_w = ctx.Pipe(duplex=False)
        self._ready = ctx.RawValue("b", 0)
        self.learner_end = LearnerEnd(stop_r, results_w, self._ready)
        self._stopped = False

    def started(self) -> None:
        """After the learner started: drop this process's copies of the learner's ends."""
        self.learner_end._stop.close()
        self.learner_end._results.close()

    def ready(self) -> bool:
        return bool(self._ready.value)

    def stop(self) -> None:
        """Never blocks: one byte fits any pipe buffer, and the read end is the learner's."""
        if self._stopped:
            return
        self._stopped = True
        try:
            self._stop_w.send_bytes(b"x")
        except OSError:
            pass

    def results(self) -> Iterator[tuple[str, dict[str, Any]]]:
        """The results that arrived, without waiting; ends at EOF (the learner is gone)."""
        while True:
            try:
                if not self._results_r.poll(0):
                    return
                item = self._results_r.recv()
            except (OSError, EOFError, ValueError):
                return
            yield item

    def close(self) -> None:
        for conn in (self._stop_w, self._results_r):
            try:
                conn.close()
            except OSError:
                pass
