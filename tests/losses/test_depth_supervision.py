"""Supervised log-depth L1 on the synthetic world's exact depth."""

from __future__ import annotations

import math

import pytest
import torch

from dfvo.losses.depth_supervision import log_depth_l1
from dfvo.synthetic import SKY_DEPTH, SyntheticWorld


@pytest.fixture(scope="module")
def true_depth() -> torch.Tensor:
    return SyntheticWorld(seed=0, num_frames=3, height=48, width=160, scenario="straight").depth(1)[None]


def test_exact_depth_costs_nothing_and_a_scale_error_costs_its_log(true_depth: torch.Tensor) -> None:
    max_depth = 100.0
    pred = true_depth.clamp(max=max_depth)  # the sky (1000 m) is taught as the network's farthest depth
    loss, count = log_depth_l1(pred, true_depth, max_depth)
    assert loss.item() < 1e-6 and int(count) == true_depth.numel()
    for factor in (0.82, 1.05, 2.0):
        loss, _ = log_depth_l1(pred * factor, true_depth, max_depth)
        assert loss.item() == pytest.approx(abs(math.log(factor)), rel=1e-4)


def test_pixels_without_ground_truth_are_ignored(true_depth: torch.Tensor) -> None:
    # a mixed batch: sample 0 synthetic, sample 1 a real image padded with zeros
    target = torch.cat([true_depth, torch.zeros_like(true_depth)])
    pred = torch.cat([true_depth.clamp(max=80.0), torch.rand_like(true_depth) * 50 + 1])
    loss, count = log_depth_l1(pred, target, 80.0)
    assert loss.item() < 1e-6 and int(count) == true_depth.numel()
    # sky excluded through ``valid``: a wrong sky prediction then costs nothing
    sky = true_depth >= SKY_DEPTH
    assert bool(sky.any())
    wrong_sky = torch.where(sky, torch.full_like(true_depth, 5.0), true_depth)
    assert log_depth_l1(wrong_sky, true_depth, 1e4, valid=~sky)[0].item() < 1e-6
    assert log_depth_l1(wrong_sky, true_depth, 1e4)[0].item() > 0.1
    # no ground truth at all: zero, with a gradient path
    pred = torch.ones(1, 1, 4, 4, requires_grad=True)
    loss, count = log_depth_l1(pred, torch.zeros(1, 1, 4, 4), 80.0)
    loss.backward()
    assert loss.item() == 0 and int(count) == 0 and pred.grad is not None


def test_gradient_pushes_towards_the_truth(true_depth: torch.Tensor) -> None:
    pred = (true_depth.clamp(max=80.0) * 0.8).requires_grad_(True)
    loss, _ = log_depth_l1(pred, true_depth, 80.0)
    loss.backward()
    assert bool((pred.grad < 0).all())  # too near everywhere: every depth should grow


def test_bad_shapes_say_what_was_expected() -> None:
    with pytest.raises(Exception, match="target"):
        log_depth_l1(torch.ones(1, 1, 4, 4), torch.ones(1, 1, 4, 5), 80.0)
