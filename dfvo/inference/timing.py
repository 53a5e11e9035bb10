"""Wall-clock time per stage of a run (``with timer("flow"): ...``), for ``summary.json`` and ``frames.csv``."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["StageTimer"]


class StageTimer:
    """Accumulates seconds per named stage; ``last[name]`` is the duration of the stage's latest call."""

    def __init__(self) -> None:
        self.total: dict[str, float] = {}
        self.last: dict[str, float] = {}

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        """Time the block as stage ``name``."""
        start = time.perf_counter()
        try:
            yield
        finally:
            self.add(name, time.perf_counter() - start)

    def add(self, name: str, seconds: float) -> None:
        """Add ``seconds`` to stage ``name``."""
        self.total[name] = self.total.get(name, 0.0) + seconds
        self.last[name] = seconds

    def ms_per_frame(self, frames: int) -> dict[str, float]:
        """Milliseconds per frame of every stage."""
        return {k: 1000.0 * v / max(frames, 1) for k, v in self.total.items()}
