"""Stop signals for long jobs (training): SIGINT, SIGTERM and SIGHUP end the work in an orderly way.

While `StopSignals` is installed, a stop signal is recorded; only inside `interruptible()` (the
part of the work that may be dropped, e.g. the episodes of a round) does the first one also
raise `Interrupted` at once. Everywhere else (a learning step, writing files) signals are only
recorded and the job checks `received` when it is safe: a second Ctrl-C during a save never
aborts the save. A signal whose disposition is SIG_IGN when installing is left ignored (`nohup`
sets SIGHUP so); a command that must react to SIGINT even when started as a background job of
a script (which inherits SIGINT ignored) installs `interrupt_once` first, as `perception-config
train` does: once a stop is on its way out (the job saved its work and raised StopRequested), one
more Ctrl-C is dropped rather than replacing the stop with death by SIGINT.

Exit codes (128 + the signal number, the shell's convention): 130 SIGINT, 143 SIGTERM, 129 SIGHUP.
"""
from __future__ import annotations

import contextlib
import signal
import threading
from typing import Any, Iterator

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
_stop_on_its_way = False  # a stop was raised: further SIGINTs to `interrupt_once` are dropped


class Interrupted(BaseException):
    """Raised inside `StopSignals.interruptible()` by the first stop signal (a BaseException:
    code that catches Exception, like a block's error handling, lets it through)."""


class StopRequested(KeyboardInterrupt):
    """A job stopped by a signal after saving its work; `signum` is the first signal received.
    A KeyboardInterrupt, so callers that handle Ctrl-C handle it."""

    def __init__(self, signum: int, message: str = "") -> None:
        super().__init__(message or f"stopped by {signal_name(signum)}")
        self.signum = int(signum)

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


def signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


class StopSignals:
    """Handlers of SIGINT, SIGTERM and SIGHUP while installed (main thread only: elsewhere
    Python cannot handle signals and this does nothing)."""

    def __init__(self) -> None:
        self.received: list[int] = []  # in arrival order
        self._armed = False
        self._previous: dict[int, Any] = {}

    @contextlib.contextmanager
    def installed(self) -> Iterator["StopSignals"]:
        if threading.current_thread() is threading.main_thread():
            for sig in STOP_SIGNALS:
                previous = signal.getsignal(sig)
                if previous is signal.SIG_IGN:
                    continue
                self._previous[sig] = previous
                signal.signal(sig, self._handle)
        try:
            yield self
        finally:
            self._armed = False
            if self.received:  # the job stops: the handlers restored below must not raise over it
                _mark_stop_on_its_way()
            for sig, previous in self._previous.items():
                signal.signal(sig, previous if previous is not None else signal.SIG_DFL)
            self._previous = {}

    @contextlib.contextmanager
    def interruptible(self) -> Iterator[None]:
        """The block is abandoned (Interrupted) by the first stop signal, also one received before."""
        if self.received:
            raise Interrupted
        self._armed = True
        try:
            yield
        finally:
            self._armed = False

    def _handle(self, signum: int, frame: Any) -> None:
        self.received.append(signum)
        if self._armed:
            self._armed = False
            raise Interrupted


def arm_interrupt_once() -> None:
    """Make SIGINT raise KeyboardInterrupt (also when the process started with it ignored), through
    `interrupt_once`."""
    global _stop_on_its_way
    _stop_on_its_way = False
    signal.signal(signal.SIGINT, interrupt_once)


def interrupt_once(signum: int, frame: Any) -> None:
    """SIGINT handler of a command: the first Ctrl-C raises KeyboardInterrupt; once a stop is on
    its way out (raised here, or by a job under `StopSignals` that a signal stopped), further ones
    are dropped. Python runs a handler between any two bytecodes, also in the `except` clause that
    reports the stop: a second KeyboardInterrupt raised there would end the process by SIGINT."""
    if _stop_on_its_way:
        return
    _mark_stop_on_its_way()
    raise KeyboardInterrupt


def _mark_stop_on_its_way() -> None:
    global _stop_on_its_way
    _stop_on_its_way = True
