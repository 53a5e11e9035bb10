"""The camera-height loss against a hand-built road and the synthetic world's exact depth."""

from __future__ import annotations

import math

import pytest
import torch
from omegaconf import OmegaConf

from dfvo.losses.road_height import road_height_log_l1
from dfvo.synthetic import CAMERA_HEIGHT, SyntheticSequenceDataset

FX, CX, CY, H, W = 200.0, 80.0, 24.0, 48, 160


def _level_road(height: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A level camera ``height`` m above a flat road: depth (1,1,H,W) = height * fy / (v - cy) below the horizon
    (hand-derived), 50 m above it; K (1,3,3); the road rows (1,1,H,W)."""
    v = torch.arange(H, dtype=torch.float64)[:, None].expand(H, W)
    road = v > CY + 2
    depth = torch.where(road, height * FX / (v - CY).clamp_min(1e-9), torch.full_like(v, 50.0))
    K = torch.tensor([[[FX, 0, CX], [0, FX, CY], [0, 0, 1]]], dtype=torch.float64)
    return depth[None, None], K, road[None, None]


def test_the_true_road_costs_nothing_and_a_scale_error_its_log() -> None:
    depth, K, road = _level_road(1.65)
    down = torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64)
    loss, count = road_height_log_l1(depth, K, down, road, torch.tensor([1.65], dtype=torch.float64))
    assert loss.item() < 1e-9 and int(count) == int(road.sum())
    for factor in (0.8, 1.1, 1.5):
        loss, _ = road_height_log_l1(depth * factor, K, down, road, torch.tensor([1.65], dtype=torch.float64))
        assert loss.item() == pytest.approx(abs(math.log(factor)), rel=1e-9)
    # no height for the sample: nothing counts, and the loss still carries the graph
    pred = (depth * 1.3).requires_grad_()
    loss, count = road_height_log_l1(pred, K, down, road, torch.tensor([0.0], dtype=torch.float64))
    assert int(count) == 0 and loss.item() == 0 and loss.requires_grad


def test_gradient_pulls_a_far_road_nearer_and_leaves_other_pixels() -> None:
    depth, K, road = _level_road(1.65)
    pred = (depth * 1.2).requires_grad_()
    down = torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64)
    road_height_log_l1(pred, K, down, road, torch.tensor([1.65], dtype=torch.float64))[0].backward()
    assert bool((pred.grad[road] > 0).all()) and bool((pred.grad[~road] == 0).all())


def test_a_tilted_normal_is_the_plane_of_a_pitched_camera() -> None:
    """Camera pitched down by 3 degrees above a road 1.5 m below: with the road's normal in the camera frame the
    loss of the exact depth is zero, with the level normal it is not."""
    a = math.radians(3.0)
    n = torch.tensor([[0.0, math.cos(a), math.sin(a)]], dtype=torch.float64)  # the road's down axis, camera frame
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    ray = torch.stack([(u - CX) / FX, (v - CY) / FX, torch.ones_like(u)], -1)
    along = (ray * n[0]).sum(-1)
    road = along > 0.05
    depth = torch.where(road, 1.5 / along.clamp_min(1e-9), torch.full_like(u, 50.0))[None, None]
    K = torch.tensor([[[FX, 0, CX], [0, FX, CY], [0, 0, 1]]], dtype=torch.float64)
    h = torch.tensor([1.5], dtype=torch.float64)
    assert road_height_log_l1(depth, K, n, road[None, None], h)[0].item() < 1e-9
    level = torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64)
    assert road_height_log_l1(depth, K, level, road[None, None], h)[0].item() > 0.01


def test_the_training_module_finds_the_synthetic_road_and_holds_it_at_the_camera_height() -> None:
    """DepthPoseModule._road_plane on the synthetic world's exact depth (camera 1.65 m above a flat road): a plane
    within 2 degrees of level, most of the road band on it; the loss of that depth ~0, of 1.25x that depth
    ~log 1.25; the module's loss has the per-scale terms."""
    from dfvo.training.depth_module import DepthPoseModule

    s = SyntheticSequenceDataset([0], 4, 96, 320, scenario="straight")[1]
    batch = {k: v[None] for k, v in s.items() if isinstance(v, torch.Tensor) and v.dim() > 0}
    cfg = OmegaConf.create({"model": {"_target_": "dfvo.training.depth_module.DepthPoseModule", "task": "depth",
                                      "name": "depth_stereo", "temporal": False, "w_camera_height": 1.0,
                                      "augment": None},
                            "data": {"height": 96, "width": 320, "seed": 0}})
    module = DepthPoseModule(cfg)
    depth = batch["depth"].clamp(max=module.max_depth)
    h = torch.tensor([CAMERA_HEIGHT])
    normal, on_road = module._road_plane(depth, batch["K"], h)
    assert math.degrees(math.acos(float(normal[0, 1]))) < 2.0
    assert int(on_road.sum()) > 1000  # the band is 16 rows x 129 columns at 320x96
    assert road_height_log_l1(depth, batch["K"], normal, on_road, h)[0].item() < 0.01
    loss, _ = road_height_log_l1(depth * 1.25, batch["K"], normal, on_road, h)
    assert loss.item() == pytest.approx(math.log(1.25), abs=0.01)
    assert not bool(module._road_plane(depth, batch["K"], torch.tensor([0.0]))[1].any())  # no height: no road
    total, terms, _ = module._losses({**batch, "camera_height": h})
    assert torch.isfinite(total) and {"camera_height_s0", "camera_height_s3", "road_pixels"} <= set(terms)
