"""The gates' limits from the sequence's own changes of motion (dfvo.tracking.gates.MotionSpread), hand-derived."""

from __future__ import annotations

import math

import pytest
import torch

from dfvo.tracking.config import GateConfig
from dfvo.tracking.gates import MotionSpread, check_direction, check_length

FORWARD = torch.tensor([0.0, 0.0, 1.0])


def _yaw(deg: float) -> torch.Tensor:
    a = math.radians(deg)
    return torch.tensor([math.sin(a), 0.0, math.cos(a)])


def test_a_cars_steady_motion_keeps_the_fixed_limits() -> None:
    cfg = GateConfig()
    spread = MotionSpread(cfg)
    for k in range(30):
        spread.add(1.2 * (1 + 0.02 * math.sin(k)), _yaw(0.5 * math.sin(0.3 * k)))
    assert spread.length_ratio == cfg.max_length_ratio and spread.direction_deg == cfg.max_direction_change_deg


def test_a_hands_changes_widen_the_limits_to_three_robust_sigmas() -> None:
    """Log length changes -0.4..0.4 (median 0, median absolute deviation 0.2): ratio exp(3 * 1.4826 * 0.2) = 2.434;
    direction changes 5..45 degrees (median 25): 3 * 1.4826 * 25 = 111.2 degrees."""
    cfg = GateConfig()
    spread = MotionSpread(cfg)
    logs = [-0.4, -0.3, -0.2, -0.1, 0.0, 0.1, 0.2, 0.3, 0.4]
    length, heading = 1.0, 0.0
    spread.add(length, _yaw(heading))
    for d, turn in zip(logs, [5, 10, 15, 20, 25, 30, 35, 40, 45]):
        length, heading = length * math.exp(d), heading + turn
        spread.add(length, _yaw(heading))
    assert spread.length_ratio == pytest.approx(math.exp(3 * 1.4826 * 0.2), rel=1e-6)
    assert spread.direction_deg == pytest.approx(3 * 1.4826 * 25, rel=1e-4)
    # the widened limits decide: a step 0.45 of the expected is too short at ratio 2, plausible at 2.434
    assert check_length("E", 0.45, 1.0, cfg, image_motion_px=5.0) is not None
    assert check_length("E", 0.45, 1.0, cfg, image_motion_px=5.0, max_ratio=spread.length_ratio) is None
    assert check_direction("E", _yaw(100), FORWARD, 1.0, cfg) is not None
    assert check_direction("E", _yaw(100), FORWARD, 1.0, cfg, spread.direction_deg) is None
    assert "(> 111)" in check_direction("E", _yaw(120), FORWARD, 1.0, cfg, spread.direction_deg)


LOGS = [-0.4, -0.3, -0.2, -0.1, 0.0, 0.1, 0.2, 0.3, 0.4]  # nine changes: 3 robust sigmas = exp(0.8896) = 2.434


def _feed(spread: MotionSpread, logs: list[float], gap_after: int | None = None) -> None:
    length = 1.0
    spread.add(length, FORWARD)
    for k, d in enumerate(logs):
        length *= math.exp(d)
        spread.add(length, FORWARD)
        if k == gap_after:
            spread.add(None, None)


def test_untracked_frames_break_the_pairs_and_few_changes_keep_the_fixed_limits() -> None:
    widened = math.exp(3 * 1.4826 * 0.2)
    enough = MotionSpread(GateConfig(adaptive_min_changes=9))
    _feed(enough, LOGS)
    assert enough.length_ratio == pytest.approx(widened)
    few = MotionSpread(GateConfig(adaptive_min_changes=10))
    _feed(few, LOGS)
    assert few.length_ratio == 2.0
    broken = MotionSpread(GateConfig(adaptive_min_changes=9))
    _feed(broken, LOGS, gap_after=3)  # the frame after the gap starts a new pair: 8 changes
    assert broken.length_ratio == 2.0
    off = MotionSpread(GateConfig(adaptive_sigmas=0.0, adaptive_min_changes=1))
    _feed(off, LOGS)
    assert off.length_ratio == 2.0


def test_a_cars_stop_does_not_widen_the_length_gate_but_a_hands_short_steps_do() -> None:
    """A car waits at a light: 20 steps of 2-50 mm of noise without parallax after 40 steps of 1 m; the gate keeps
    its ratio 2 during the stop and after it. The same short steps with 3 px of parallax (a hand moving a few
    centimetres) are motion: their spread widens it."""
    g = torch.Generator().manual_seed(0)
    noise = torch.exp(torch.empty(20).uniform_(math.log(0.002), math.log(0.05), generator=g)).tolist()
    for parallax, widened in ((0.2, False), (3.0, True)):
        spread = MotionSpread(GateConfig())
        for _ in range(40):
            spread.add(1.0, FORWARD)
        ratios = []
        for length in noise:
            spread.add(length, FORWARD, parallax_px=parallax)
            ratios.append(spread.length_ratio)
        for _ in range(5):
            spread.add(1.0, FORWARD)
            ratios.append(spread.length_ratio)
        assert (max(ratios) > 2.5) == widened
        if not widened:
            assert set(ratios) == {2.0}


def test_short_steps_do_not_count_for_the_direction() -> None:
    """Directions of steps at most stop_length (a car at a stop: E's direction is noise) are not changes."""
    cfg = GateConfig(adaptive_min_changes=3)
    spread = MotionSpread(cfg)
    for k in range(12):
        spread.add(0.05, _yaw(170 * (k % 2)))
    assert spread.direction_deg == cfg.max_direction_change_deg


def test_settings_are_checked() -> None:
    with pytest.raises(ValueError, match="adaptive_sigmas"):
        GateConfig(adaptive_sigmas=-1)
