"""Recording a run as it goes: one tracked frame written everywhere (:func:`write_frame`: the pose file, ``frames.csv``
with its covariance, the observers), and a stop by SIGINT/SIGTERM turned into :class:`RunInterrupted` so the partial
outputs are still written (:class:`SignalsToInterrupt`). Shared by the batch run (:mod:`dfvo.inference.pipeline`)
and the live run (:mod:`dfvo.inference.live`).
"""

from __future__ import annotations

import signal
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

from dfvo.geometry.pose_covariance import covariance_to_row
from dfvo.inference.loop import FrameRecord
from dfvo.inference.outputs import FramesCsv, writing
from dfvo.io.trajectory import TrajectoryWriter
from dfvo.tracking.diagnostics import FrameDiagnostics

__all__ = ["RunInterrupted", "SignalsToInterrupt", "write_frame", "stamp"]


class RunInterrupted(KeyboardInterrupt):
    """The run was stopped by a signal after its partial outputs were written; ``signum`` says which."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class SignalsToInterrupt:
    """While active, SIGTERM (and SIGINT) raise :class:`RunInterrupted` in the main thread.

    Inside :meth:`held` (one frame's writes: its pose line, its ``frames.csv`` row, the in-memory trajectory) a signal
    is kept until the block ends, so the pose file, ``frames.csv`` and the summary's ``frames_written`` always count the
    same frames.
    """

    def __enter__(self) -> SignalsToInterrupt:
        self.previous: dict[int, Any] = {}
        self._holding = False
        self._pending: int | None = None
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                self.previous[sig] = signal.signal(sig, self._on_signal)
            except ValueError:  # not the main thread: keep the defaults
                pass
        return self

    def _on_signal(self, signum: int, frame: Any) -> None:
        if self._holding:
            self._pending = self._pending or signum
            return
        raise RunInterrupted(signum)

    @contextmanager
    def held(self) -> Iterator[None]:
        """Keep a signal that arrives inside the block until the block has finished, then raise it."""
        self._holding = True
        try:
            yield
        finally:
            self._holding = False
        if self._pending is not None:
            signum, self._pending = self._pending, None
            raise RunInterrupted(signum)

    def __exit__(self, *exc: Any) -> None:
        for sig, handler in self.previous.items():
            signal.signal(sig, handler)


def stamp(seq: Any, index: int) -> float | None:
    """Frame ``index``'s timestamp of ``seq`` (None without timestamps)."""
    return None if seq.timestamps is None else float(seq.timestamps[index])


def write_frame(record: FrameRecord, poses: TrajectoryWriter, table: FramesCsv, trajectory: list[np.ndarray],
                 diagnostics: list[FrameDiagnostics], observers: list[Any], timestamp: float | None,
                 extra: dict[str, Any] | None = None) -> None:
    """Write one tracked frame everywhere (trajectory line, frames.csv row with its covariance, observers)."""
    T_w = record.result.T_w_cur.detach().cpu().double().numpy()
    record.timestamp = timestamp
    with writing(poses.path):
        poses.write(T_w, timestamp)
    with writing(table.path):
        table.write(record.result.diagnostics, record.stage_seconds,
                    {**covariance_to_row(record.result.covariance), **(extra or {})})
    trajectory.append(T_w)
    diagnostics.append(record.result.diagnostics)
    for obs in observers:
        obs.on_frame(record)
