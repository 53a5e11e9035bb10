"""Wall-clock time per stage of a run (``with timer("flow"): ...``), for ``summary.json`` and ``frames.csv``.

Stages may run in different threads (the inference loop decodes frames and runs the tracker in background threads
while the networks run): ``add`` is thread-safe, and the per-stage totals then overlap, so their sum can exceed the
run's wall time. ``wait_*`` stages are the time the main thread spent blocked on a background stage.

Each stage also accumulates the process's CPU time (``time.process_time``: every thread of the process, torch's
OpenMP workers included) while it ran: on a shared machine the wall time follows the neighbours' load and the CPU
time the work. With stages in several threads at once (``overlap="full"``) a stage's CPU time also counts what the
other threads did meanwhile; compare CPU times in the serial loop (``overlap="none"`` or ``"load"``). The calling
thread's own CPU time (``time.thread_time``) is kept too: it leaves out the other threads, and with one torch thread
per busy thread (``overlap="full"`` on two cores) it is the stage's whole work, so it shows how the two threads'
work divides while they overlap (it misses torch's OpenMP workers when a stage runs on several threads).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import torch

from dfvo.inference.config import InferConfig

__all__ = ["Lap", "StageTimer"]


@dataclass
class Lap:
    """The wall seconds of one timed block (set when the block ends; ``with timer("flow") as lap: ...``)."""

    seconds: float = 0.0


class StageTimer:
    """Accumulates seconds per named stage; each timed block also hands its own duration back (:class:`Lap`), so a
    caller in any thread reads its own call's time.

    Args:
        cuda_sync: synchronise CUDA at every stage boundary (``cuda_sync`` of :class:`InferConfig`), so a stage's
            time is its GPU work; it serialises the GPU with the host, so runs with it are slower (measure FPS
            without it). Nothing happens where CUDA is not available.
    """

    def __init__(self, cuda_sync: bool = InferConfig.cuda_sync) -> None:
        self.cuda_sync = bool(cuda_sync)
        self.total: dict[str, float] = {}
        self.cpu_total: dict[str, float] = {}
        self.thread_cpu_total: dict[str, float] = {}
        # overlap="full": where the refinement was cut between the two threads (dfvo.inference.refine_split): the
        # units of a batch and the network thread's units of each batch; None for the other layouts
        self.refine_cut: dict[str, object] | None = None
        self._lock = threading.Lock()

    @contextmanager
    def __call__(self, name: str) -> Iterator[Lap]:
        """Time the block as stage ``name`` (wall, process and thread CPU time); yields the block's :class:`Lap`."""
        self._sync()
        lap = Lap()
        start, cpu, own = time.perf_counter(), time.process_time(), time.thread_time()
        try:
            yield lap
        finally:
            self._sync()
            lap.seconds = time.perf_counter() - start
            self.add(name, lap.seconds, time.process_time() - cpu, time.thread_time() - own)

    def _sync(self) -> None:
        if self.cuda_sync and torch.cuda.is_available():
            torch.cuda.synchronize()

    def add(self, name: str, seconds: float, cpu_seconds: float | None = None,
            thread_cpu_seconds: float | None = None) -> None:
        """Add ``seconds`` of wall time (and ``cpu_seconds`` of process CPU time and ``thread_cpu_seconds`` of the
        calling thread's, if known) to stage ``name`` (from any thread)."""
        with self._lock:
            self.total[name] = self.total.get(name, 0.0) + seconds
            if cpu_seconds is not None:
                self.cpu_total[name] = self.cpu_total.get(name, 0.0) + cpu_seconds
            if thread_cpu_seconds is not None:
                self.thread_cpu_total[name] = self.thread_cpu_total.get(name, 0.0) + thread_cpu_seconds

    def ms_per_frame(self, frames: int) -> dict[str, float]:
        """Milliseconds of wall time per frame of every stage."""
        with self._lock:
            return {k: 1000.0 * v / max(frames, 1) for k, v in self.total.items()}

    def cpu_ms_per_frame(self, frames: int) -> dict[str, float]:
        """Milliseconds of process CPU time per frame of every stage that measured it (see the module docstring)."""
        with self._lock:
            return {k: 1000.0 * v / max(frames, 1) for k, v in self.cpu_total.items()}

    def thread_cpu_ms_per_frame(self, frames: int) -> dict[str, float]:
        """Milliseconds per frame of the CPU time of the thread that ran each stage (see the module docstring)."""
        with self._lock:
            return {k: 1000.0 * v / max(frames, 1) for k, v in self.thread_cpu_total.items()}
