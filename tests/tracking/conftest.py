"""Shared fixtures of the tracking tests."""

from __future__ import annotations

from collections.abc import Callable
from functools import cache

import pytest
import torch

from dfvo.synthetic import SyntheticWorld

StraightPairs = tuple[SyntheticWorld, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]


@cache
def _straight_pairs(num_frames: int) -> StraightPairs:
    w = SyntheticWorld(seed=0, num_frames=num_frames, scenario="straight")
    frames = [w.render(i, right=False) for i in range(num_frames - 1)]
    ff = torch.stack([f["flow_fwd"] for f in frames])
    fb = torch.stack([f["flow_bwd"] for f in frames])
    d = torch.stack([f["depth"] for f in frames])
    P = w.poses()
    rel = torch.linalg.inv(P[:-1]) @ P[1:]  # T_prev_cur
    return w, ff, fb, d, rel


@pytest.fixture(scope="session")
def straight_pairs() -> Callable[[int], StraightPairs]:
    """``straight_pairs(n)``: the straight synthetic world of seed 0 with ``n`` frames and its first ``n - 1``
    rendered with exact flow and depth: ``(world, flow_fwd (n-1,2,H,W), flow_bwd, depth (n-1,1,H,W), T_prev_cur
    (n-1,4,4))``, rendered once per ``n`` (the E-tracker takes every pair)."""
    return _straight_pairs


@cache
def _handheld_exact() -> tuple[torch.Tensor, ...]:
    w = SyntheticWorld(seed=1000, num_frames=16, scenario="handheld", height=96, width=320)
    frames = [w.render(i, right=False) for i in range(16)]
    return (torch.stack([f["flow_fwd"] for f in frames[:-1]]), torch.stack([f["flow_bwd"] for f in frames[:-1]]),
            torch.stack([f["depth"] for f in frames]) * 10.0, w.intrinsics(), w.poses())


@pytest.fixture(scope="session")
def handheld_exact() -> tuple[torch.Tensor, ...]:
    """The synthetic hand-held world (seed 1000, 16 frames, 96x320) with exact flows and its depth 10x too far (steps
    of 10-40 cm: the direction gate applies): forward and backward flows (15,2,H,W), depths (16,1,H,W), K (3,3),
    poses T_w_c (16,4,4); rendered once."""
    return _handheld_exact()


@cache
def _planar_exact() -> tuple[torch.Tensor, ...]:
    w = SyntheticWorld(seed=1003, num_frames=44, scenario="handheld_planar", height=96, width=320)
    frames = [w.render(i, right=False) for i in range(44)]
    return (torch.stack([f["flow_fwd"] for f in frames[:-1]]), torch.stack([f["flow_bwd"] for f in frames[:-1]]),
            torch.stack([f["depth"] for f in frames]), w.intrinsics(), w.poses())


@pytest.fixture(scope="session")
def planar_exact() -> tuple[torch.Tensor, ...]:
    """The planar hand-held world (seed 1003: the hand slows 3x at frames 16 and 34 and keeps its new pace; 44 frames,
    96x320; every pixel on the desk) with exact flows and depth: forward and backward flows (43,2,H,W), depths
    (44,1,H,W), K (3,3), poses T_w_c (44,4,4); rendered once."""
    return _planar_exact()
