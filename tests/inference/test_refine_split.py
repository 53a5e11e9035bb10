"""The refinement cut between the two threads of ``overlap="full"`` (dfvo/inference/refine_split.py): the parts of
every cut, the flows of every cut equal one ``refine_consecutive`` call bit for bit (on a synthetic world's true
flow with a network-like smooth error), and the balance moves the cut to where a model of the two threads' times is
even, starting from the placement of each refinement mode."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from dfvo.inference.refine_split import RefineBalance, RefinePart, refine_stages, run_parts, split_refinement
from dfvo.matching.flow_refinement import FlowRefinementConfig, RefinementMode, refine_consecutive
from dfvo.synthetic import SyntheticWorld

H, W, PAIRS = 64, 224, 4


@pytest.fixture(scope="module")
def batch() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    world = SyntheticWorld(seed=3, num_frames=PAIRS + 1, height=H, width=W, scenario="drive")
    g = torch.Generator().manual_seed(1)

    def off() -> torch.Tensor:  # a smooth error of ~1 px, as a network's
        return F.interpolate(torch.randn(1, 2, 4, 12, generator=g), size=(H, W), mode="bilinear")[0]

    images = torch.stack([world.image(i) for i in range(PAIRS + 1)])
    fwd = torch.stack([world.flow(i, i + 1)[0] + off() for i in range(PAIRS)])
    bwd = torch.stack([world.flow(i + 1, i)[0] + off() for i in range(PAIRS)])
    return images, fwd, bwd


def test_the_stages_of_each_mode() -> None:
    modes = [s.mode for s in refine_stages(FlowRefinementConfig())]
    assert modes == [RefinementMode.dense, RefinementMode.pyramid]
    assert [s.mode for s in refine_stages(FlowRefinementConfig(mode="pyramid"))] == [RefinementMode.pyramid]
    assert [s.mode for s in refine_stages(FlowRefinementConfig(mode="dense"))] == [RefinementMode.dense]
    assert refine_stages(None) == [] and refine_stages(FlowRefinementConfig(iterations=0)) == []


def test_a_cut_gives_the_first_units_in_stage_order_to_the_network_thread() -> None:
    dense, pyr = refine_stages(FlowRefinementConfig())

    def spans(parts: list[RefinePart]) -> list[tuple[str, int, int]]:
        return [(p.cfg.mode.value, p.start, p.stop) for p in parts]

    main, tracker = split_refinement([dense, pyr], 4, 0)
    assert spans(main) == [] and spans(tracker) == [("dense", 0, 4), ("pyramid", 0, 4)]
    main, tracker = split_refinement([dense, pyr], 4, 3)
    assert spans(main) == [("dense", 0, 3)] and spans(tracker) == [("dense", 3, 4), ("pyramid", 0, 4)]
    main, tracker = split_refinement([dense, pyr], 4, 6)
    assert spans(main) == [("dense", 0, 4), ("pyramid", 0, 2)] and spans(tracker) == [("pyramid", 2, 4)]
    main, tracker = split_refinement([dense, pyr], 4, 8)
    assert spans(main) == [("dense", 0, 4), ("pyramid", 0, 4)] and spans(tracker) == []


@pytest.mark.parametrize("mode", ["dense_pyramid", "pyramid", "dense"])
def test_every_cut_refines_the_flows_of_one_call_bit_for_bit(batch: tuple, mode: str) -> None:
    images, fwd, bwd = batch
    cfg = FlowRefinementConfig(mode=mode)
    want_f, want_b = refine_consecutive(images, fwd, bwd, cfg)
    moved = ((want_f - fwd).abs() > 0.05).any(1).sum() + ((want_b - bwd).abs() > 0.05).any(1).sum()
    assert moved > 500  # the refinement moved many vectors: the comparison below means something
    stages = refine_stages(cfg)
    for units in range(len(stages) * PAIRS + 1):
        main, tracker = split_refinement(stages, PAIRS, units)
        f, b, seconds = run_parts(main, images, fwd, bwd)
        f, b, more = run_parts(tracker, images, f, b)
        assert torch.equal(f, want_f) and torch.equal(b, want_b), f"{mode}, cut {units}"
        assert set(seconds) | set(more) == set(range(len(stages)))  # every stage ran and was timed


def _settle(balance: RefineBalance, main_base: float, tracker_base: float, unit: list[float], batches: int = 40
            ) -> list[int]:
    """Feed the balance the per-pair busy times of a model: each thread's fixed work plus the refinement units it
    holds (``unit[s]`` seconds per pair of stage s)."""
    B = balance.batch_size
    for _ in range(batches):
        main_parts, tracker_parts = balance.parts(B)
        main = main_base + sum(unit[p.stage] * (p.stop - p.start) for p in main_parts) / B
        tracker = tracker_base + sum(unit[p.stage] * (p.stop - p.start) for p in tracker_parts) / B
        balance.observe(main, tracker, {s: unit[s] for s in range(len(unit))})
    return balance.history


def test_the_balance_moves_the_cut_to_where_the_threads_even_out() -> None:
    """A model batch of 4 pairs: dense 0.04 s and pyramid 0.05 s a pair (0.36 s of refinement a batch); the network
    thread holds the first c units, ``work(c)`` seconds of them; the cut should settle where the slower thread is
    fastest."""
    stages = refine_stages(FlowRefinementConfig())
    unit = [0.040, 0.050]
    work = {c: (0.04 * c if c <= 4 else 0.16 + 0.05 * (c - 4)) for c in range(9)}

    def best(main_base: float, tracker_base: float) -> int:
        slower = {c: max(4 * main_base + work[c], 4 * tracker_base + 0.36 - work[c]) for c in range(9)}
        assert sorted(slower.values())[0] < sorted(slower.values())[1]  # one best cut
        return min(slower, key=slower.get)

    # even as it starts (0.40 / 0.44 s a batch; one pyramid pair more would be 0.45 / 0.39): it stays
    history = _settle(RefineBalance(stages, 4), 0.060, 0.060, unit)
    assert history[0] == 4 and set(history) == {4} and best(0.060, 0.060) == 4
    # slow networks: the network thread sheds dense pairs to the tracker thread until even
    history = _settle(RefineBalance(stages, 4), 0.130, 0.060, unit)
    assert best(0.130, 0.060) == 1 and set(history[-20:]) == {1}
    # a slow tracker: the network thread takes pyramid pairs too
    history = _settle(RefineBalance(stages, 4), 0.060, 0.150, unit)
    assert best(0.060, 0.150) == 8 and set(history[-20:]) == {8}
    assert min(history) >= 0 and max(history) <= 8  # only cuts that exist


def test_the_first_batch_does_not_move_the_cut() -> None:
    """The first batch's times carry one-time costs (an OpenVINO compile takes seconds): they are not used."""
    balance = RefineBalance(refine_stages(FlowRefinementConfig()), 4)
    balance.observe(5.0, 0.1, {0: 0.04, 1: 0.05})  # a compile in the network thread
    assert balance.units == 4 and balance.main_seconds is None
    balance.observe(0.10, 0.10, {0: 0.04, 1: 0.05})
    balance.observe(0.10, 0.10, {0: 0.04, 1: 0.05})
    assert balance.units == 4


def test_each_mode_starts_where_it_ran_before_the_balance_existed() -> None:
    assert RefineBalance(refine_stages(FlowRefinementConfig()), 4).units == 4  # dense | pyramid
    assert RefineBalance(refine_stages(FlowRefinementConfig(mode="pyramid")), 4).units == 4  # beside the networks
    assert RefineBalance(refine_stages(FlowRefinementConfig(mode="dense")), 4).units == 0  # beside the tracker
    assert RefineBalance(refine_stages(None), 4).total == 0


def test_a_short_last_batch_keeps_the_cut_in_proportion() -> None:
    balance = RefineBalance(refine_stages(FlowRefinementConfig()), 4)
    main, tracker = balance.parts(2)
    assert [(p.stage, p.start, p.stop) for p in main] == [(0, 0, 2)]
    assert [(p.stage, p.start, p.stop) for p in tracker] == [(1, 0, 2)]
