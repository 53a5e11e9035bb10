"""A signal during one frame's writes is kept until they are done (the pose file and the summary count the same
frames)."""

from __future__ import annotations

import os
import signal

import pytest

from dfvo.inference.recording import RunInterrupted, SignalsToInterrupt


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signal_inside_held_block_waits_for_the_block(sig: signal.Signals) -> None:
    written: list[str] = []
    with pytest.raises(RunInterrupted) as caught, SignalsToInterrupt() as interrupts:
        with interrupts.held():
            written.append("pose line")
            os.kill(os.getpid(), sig)  # delivered here, between the two writes
            written.append("frames.csv row")
        written.append("next frame")  # never reached: the kept signal is raised when the block ends
    assert written == ["pose line", "frames.csv row"]
    assert caught.value.signum == sig


def test_signal_outside_held_block_interrupts_at_once_and_handlers_are_restored() -> None:
    before = signal.getsignal(signal.SIGTERM)
    reached = False
    with pytest.raises(RunInterrupted) as caught, SignalsToInterrupt():
        os.kill(os.getpid(), signal.SIGTERM)
        reached = True
    assert not reached and caught.value.signum == signal.SIGTERM
    assert signal.getsignal(signal.SIGTERM) is before


def test_held_block_without_signal_and_an_error_inside_it() -> None:
    with SignalsToInterrupt() as interrupts:
        with interrupts.held():
            pass
        with pytest.raises(OSError, match="disk full"), interrupts.held():
            raise OSError("disk full")
        with pytest.raises(RunInterrupted):  # the hold ended with the error: signals interrupt again
            os.kill(os.getpid(), signal.SIGINT)
