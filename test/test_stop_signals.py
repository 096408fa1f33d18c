"""The command's SIGINT handler: the first Ctrl-C interrupts; once a stop is on its way out (a job
under StopSignals saved its work and is raising StopRequested), further ones are dropped, so the
exit code stays 130 however the Ctrl-Cs fall between the bytecodes of the `except` that reports it."""
from __future__ import annotations

import signal

import pytest

from perception_config.util.stop_signals import StopSignals, arm_interrupt_once


@pytest.fixture
def sigint_restored():
    previous = signal.getsignal(signal.SIGINT)
    yield
    signal.signal(signal.SIGINT, previous)


def test_the_first_ctrl_c_interrupts_and_the_next_ones_are_dropped(sigint_restored):
    arm_interrupt_once()
    with pytest.raises(KeyboardInterrupt):
        signal.raise_signal(signal.SIGINT)
    signal.raise_signal(signal.SIGINT)  # the KeyboardInterrupt is on its way: dropped
    arm_interrupt_once()  # the next command interrupts again
    with pytest.raises(KeyboardInterrupt):
        signal.raise_signal(signal.SIGINT)


def test_after_a_job_stopped_by_a_signal_a_further_ctrl_c_is_dropped(sigint_restored):
    arm_interrupt_once()
    stops = StopSignals()
    with stops.installed():
        signal.raise_signal(signal.SIGINT)  # recorded only
        assert stops.received == [signal.SIGINT]
    signal.raise_signal(signal.SIGINT)  # the handler restored on the way out does not raise over the stop
    assert signal.getsignal(signal.SIGINT).__name__ == "interrupt_once"


def test_a_job_that_ends_without_a_signal_leaves_ctrl_c_working(sigint_restored):
    arm_interrupt_once()
    with StopSignals().installed():
        pass
    with pytest.raises(KeyboardInterrupt):
        signal.raise_signal(signal.SIGINT)
