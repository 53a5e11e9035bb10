"""The photometric flow refinement of one batch shared between the two threads of ``overlap="full"``, and where to
cut it so that both threads are busy for the same time.

The refinement of a batch's B consecutive pairs is a list of stages (``dense_pyramid``: the dense refinement, then
the pyramid one on its result; other modes: one stage), each over the B pairs: ``len(stages) * B`` units, in stage
order and pair order. The network thread refines the first ``units`` of them right after the networks, the tracker
thread the rest before it tracks the batch. A pair's refined flows do not depend on which other pairs are refined
with it (every preparation is per frame, every update per pair), so any cut gives the flows of one
:func:`dfvo.matching.flow_refinement.refine_consecutive` call, bit for bit, and the cut may move between batches.

:class:`RefineBalance` moves the cut by one unit after a batch whenever that brings the two threads' busy times
(smoothed over batches) closer: the network thread's is the networks plus its refinement, the tracker thread's its
refinement plus the tracker. How long the parts take differs by machine (a faster network runtime, a CPU whose
cores slow each other down) and by sequence, so the cut is measured, not configured. (On CUDA the times are the host's
unless ``cuda_sync=true``: the cut then evens out the host's work; the poses are the same either way.)

Convention:
    Images (B+1,3,H,W) of the batch's frames in order; flows (B,2,H,W), ``flow_fwd[k]`` k->k+1 on frame k,
    ``flow_bwd[k]`` k+1->k on frame k+1 (:func:`dfvo.matching.flow_refinement.refine_consecutive`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import torch

from dfvo.matching.flow_refinement import FlowRefinementConfig, RefinementMode, refine_consecutive

__all__ = ["RefinePart", "RefineBalance", "refine_stages", "split_refinement", "whole_refinement", "run_parts"]


@dataclass(frozen=True)
class RefinePart:
    """Stage number ``stage`` of :func:`refine_stages` (``cfg``) over the pairs ``[start, stop)`` of a batch."""

    stage: int
    cfg: FlowRefinementConfig
    start: int
    stop: int


def refine_stages(refine: FlowRefinementConfig | None) -> list[FlowRefinementConfig]:
    """The stages of a refinement in the order they run: ``dense_pyramid`` -> [dense, pyramid]; ``dense`` or
    ``pyramid`` -> itself; none (None or ``iterations=0``) -> []."""
    if refine is None or refine.iterations == 0:
        return []
    if refine.mode == RefinementMode.dense_pyramid:
        return [replace(refine, mode=RefinementMode.dense), replace(refine, mode=RefinementMode.pyramid)]
    return [refine]


def split_refinement(stages: list[FlowRefinementConfig], pairs: int, main_units: int
                     ) -> tuple[list[RefinePart], list[RefinePart]]:
    """(the network thread's parts, the tracker thread's parts) of a batch of ``pairs`` pairs: the first
    ``main_units`` of the ``len(stages) * pairs`` (stage, pair) units, in stage order, and the rest.

    A pair's later stage runs in the network thread only when that thread ran all of the earlier stage, so every
    stage of a pair runs after its earlier ones, in the same thread or in the tracker thread afterwards."""
    main: list[RefinePart] = []
    tracker: list[RefinePart] = []
    for s, cfg in enumerate(stages):
        cut = min(pairs, max(0, main_units - s * pairs))
        if cut > 0:
            main.append(RefinePart(s, cfg, 0, cut))
        if cut < pairs:
            tracker.append(RefinePart(s, cfg, cut, pairs))
    return main, tracker


def whole_refinement(stages: list[FlowRefinementConfig], pairs: int) -> list[RefinePart]:
    """Every stage over all ``pairs`` pairs, in order: the refinement of a batch in one thread (the serial loop,
    ``overlap="load"``, frames one at a time); the flows of one ``refine_consecutive`` call, bit for bit."""
    return split_refinement(stages, pairs, len(stages) * pairs)[0]


def run_parts(parts: list[RefinePart], images: torch.Tensor, flow_fwd: torch.Tensor, flow_bwd: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor, dict[int, float]]:
    """Run ``parts`` in order on a batch (images (B+1,3,H,W), flows (B,2,H,W)): the flows with those pairs refined,
    and the seconds per pair of each stage that ran (by its number)."""
    per_pair: dict[int, float] = {}
    B = flow_fwd.shape[0]
    for part in parts:
        a, b = part.start, part.stop
        start = time.perf_counter()
        fwd, bwd = refine_consecutive(images[a:b + 1], flow_fwd[a:b], flow_bwd[a:b], part.cfg)
        if a == 0 and b == B:
            flow_fwd, flow_bwd = fwd, bwd
        else:  # (network outputs may be inference tensors: no in-place writes)
            flow_fwd = torch.cat([flow_fwd[:a], fwd, flow_fwd[b:]])
            flow_bwd = torch.cat([flow_bwd[:a], bwd, flow_bwd[b:]])
        per_pair[part.stage] = (time.perf_counter() - start) / (b - a)
    return flow_fwd, flow_bwd, per_pair


class RefineBalance:
    """Where the refinement of each batch is cut between the two threads (see the module docstring).

    Args:
        stages: :func:`refine_stages` of the refinement. batch_size: pairs per batch.
        smoothing: weight of a new batch's busy times in their running means (0..1].

    Attributes:
        units: the network thread's units of the next batch: starts with the dense stage (or a lone pyramid stage)
            in the network thread and the pyramid (or a lone dense) stage in the tracker thread.
        history: the cut of every batch so far.
    """

    def __init__(self, stages: list[FlowRefinementConfig], batch_size: int, smoothing: float = 0.3) -> None:
        self.stages, self.batch_size, self.smoothing = stages, int(batch_size), float(smoothing)
        self.total = len(stages) * self.batch_size
        # the first stage beside the networks, unless it is a lone dense one (then beside the tracker)
        lone_dense = len(stages) == 1 and stages[0].mode == RefinementMode.dense
        self.units = 0 if not stages or lone_dense else self.batch_size
        self.unit_seconds: dict[int, float] = {}
        self.main_seconds: float | None = None
        self.tracker_seconds: float | None = None
        self.history: list[int] = []
        self.observed = 0

    def parts(self, pairs: int) -> tuple[list[RefinePart], list[RefinePart]]:
        """The parts of a batch of ``pairs`` pairs (a last, shorter batch keeps the cut in proportion)."""
        self.history.append(self.units)
        units = round(self.units * pairs / self.batch_size) if pairs != self.batch_size else self.units
        return split_refinement(self.stages, pairs, units)

    def observe(self, main_seconds: float, tracker_seconds: float, unit_seconds: dict[int, float]) -> None:
        """One batch's busy seconds per pair in the network thread and in the tracker thread, and the seconds per
        pair of each refinement stage it measured; moves the cut by one unit when that evens the threads out. The
        first batch is not used: it carries one-time costs (a runtime compiling its model, first allocations)."""
        self.observed += 1
        if self.observed == 1:
            return
        for key, sec in unit_seconds.items():
            old = self.unit_seconds.get(key)
            self.unit_seconds[key] = sec if old is None else old + self.smoothing * (sec - old)
        if self.main_seconds is None:
            self.main_seconds, self.tracker_seconds = main_seconds, tracker_seconds
        else:
            self.main_seconds += self.smoothing * (main_seconds - self.main_seconds)
            self.tracker_seconds += self.smoothing * (tracker_seconds - self.tracker_seconds)
        gap = (self.tracker_seconds - self.main_seconds) * self.batch_size  # seconds per batch
        if gap > 0 and self.units < self.total:
            unit = self.unit_seconds.get(self.units // self.batch_size)
            if unit is not None and gap > unit:  # moving a unit shrinks the gap by twice its time: helps if gap > it
                self.units += 1
                self._moved(unit)
        elif gap < 0 and self.units > 0:
            unit = self.unit_seconds.get((self.units - 1) // self.batch_size)
            if unit is not None and -gap > unit:
                self.units -= 1
                self._moved(-unit)

    def _moved(self, unit: float) -> None:
        """The running means as if the last batches had run with the new cut (``unit`` seconds moved to the network
        thread; negative: to the tracker thread), so that one imbalance moves the cut once."""
        per_pair = unit / self.batch_size
        self.main_seconds += per_pair
        self.tracker_seconds -= per_pair
