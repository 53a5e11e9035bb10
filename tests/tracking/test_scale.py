"""Scale recovery: simple 1-D RANSAC exactness, its failure rule, depth sampling, iterative vs simple."""

import pytest
import torch

from dfvo.geometry.camera import project_points, transform_points
from dfvo.geometry.se3 import pose_from_axis_angle
from dfvo.tracking import TrackerConfig, VisualOdometry
from dfvo.tracking.config import ScaleConfig
from dfvo.tracking.scale import sample_depth, simple_scale, triangulated_depth

torch.set_num_threads(1)

def make_cfg(tracker: str = "hybrid", scale_method: str = "simple", depth_views: int = 1, **scale) -> TrackerConfig:
    """A tracker configuration; one-view scale unless asked (these sequences pass the earlier frames' depth only)."""
    return TrackerConfig(mode=tracker, scale=ScaleConfig(method=scale_method, depth_views=depth_views, **scale))


def test_simple_scale_exact_with_outliers():
    g = torch.Generator().manual_seed(0)
    z_tri = torch.rand(2, 400, generator=g, dtype=torch.float64) * 20 + 1
    z_cnn = z_tri * torch.tensor([[2.5], [0.7]], dtype=torch.float64)
    bad = torch.rand(2, 400, generator=g) < 0.3
    z_cnn = torch.where(bad, z_cnn * (1.5 + torch.rand(2, 400, generator=g, dtype=torch.float64)), z_cnn)
    mask = torch.ones(2, 400, dtype=torch.bool)
    gens = [torch.Generator().manual_seed(b) for b in range(2)]
    s, inl, ok = simple_scale(z_cnn, z_tri, mask, generators=gens)
    assert ok.all()
    assert torch.allclose(s, torch.tensor([2.5, 0.7], dtype=torch.float64), rtol=1e-12)
    assert torch.equal(inl, ~bad)


def test_simple_scale_needs_more_than_min_points():
    z = torch.ones(1, 30, dtype=torch.float64)
    mask = torch.zeros(1, 30, dtype=torch.bool)
    mask[:, :10] = True
    assert not simple_scale(z, z, mask, min_points=10)[2].any()
    mask[:, :11] = True
    assert simple_scale(z, z, mask, min_points=10)[2].all()


def test_sample_depth_crop_and_range():
    depth = torch.arange(100, dtype=torch.float32).reshape(1, 1, 10, 10)
    depth[0, 0, 9, 9] = 60.0
    pts = torch.tensor([[[3.0, 1.0], [3.0, 5.0], [9.0, 9.0], [4.2, 6.4]]])
    z, ok = sample_depth(depth, pts, max_depth=55.0, crop_top=0.3)
    assert z[0].tolist() == [13.0, 53.0, 60.0, 64.0]  # nearest pixel: (4.2, 6.4) -> column 4, row 6
    assert ok[0].tolist() == [False, True, False, False]  # top 30 % rows cut; 60 and 64 exceed 55 m
    depth2 = torch.full((1, 1, 10, 10), 10.0)
    z2, ok2 = sample_depth(depth2, pts, max_depth=50.0, crop_top=0.3)
    assert ok2[0].tolist() == [False, True, True, True]  # row 1 is in the top 30 %


def test_triangulated_depth_is_true_depth_over_baseline():
    g = torch.Generator().manual_seed(1)
    K = torch.tensor([[[700.0, 0, 320], [0, 700.0, 96], [0, 0, 1]]], dtype=torch.float64)
    X = torch.stack([torch.rand(1, 50, generator=g) * 10 - 5, torch.rand(1, 50, generator=g) * 2 - 1,
                     torch.rand(1, 50, generator=g) * 30 + 5], -1).double()
    T = pose_from_axis_angle(torch.tensor([[0.0, 0.02, 0.0]]).double(), torch.tensor([[0.1, 0.0, -1.5]]).double())
    pi, _ = project_points(X, K)
    pj, _ = project_points(transform_points(T, X), K)
    scale = T[:, :3, 3].norm(dim=-1)
    z, front = triangulated_depth(T[:, :3, :3], T[:, :3, 3] / scale, K, pi, pj)
    assert front.all()
    assert torch.allclose(z * scale, X[..., 2], rtol=1e-9)


def test_iterative_scale_beats_simple_on_a_moving_car():
    from dfvo.synthetic import SyntheticWorld

    w = SyntheticWorld(seed=0, num_frames=8, scenario="moving_car")
    k = 5
    r = w.render(k)
    assert r["dynamic_mask"].float().mean() > 0.5  # the car dominates the frame
    P = w.poses()
    T_true = torch.linalg.inv(P[k]) @ P[k + 1]
    T_before = torch.linalg.inv(P[k - 1]) @ P[k]
    errs = {}
    for method in ("simple", "iterative"):
        vo = VisualOdometry(make_cfg(scale_method=method, tracker="e"))
        vo.last_motion, vo.last_scale = T_before, float(T_before[:3, 3].norm())  # streaming state so far
        res = vo.step(r["flow_fwd"][None], r["flow_bwd"][None], r["depth"][None], w.intrinsics()[None])
        errs[method] = float((res.T_prev_cur[:3, 3] - T_true[:3, 3]).norm())
    assert errs["iterative"] < 1e-3
    assert errs["simple"] > 10 * errs["iterative"], errs
    # the two-view scale (later frame's depth too) inside Algorithm 2's re-estimation keeps the truck rejected
    vo = VisualOdometry(make_cfg(scale_method="iterative", tracker="e", depth_views=2))
    vo.last_motion, vo.last_scale = T_before, float(T_before[:3, 3].norm())
    res = vo.step(r["flow_fwd"][None], r["flow_bwd"][None], r["depth"][None], w.intrinsics()[None],
                  depth_cur=w.render(k + 1)["depth"][None])
    assert float((res.T_prev_cur[:3, 3] - T_true[:3, 3]).norm()) < 1e-3


def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="tracker.scale.method"):
        make_cfg(scale_method="magic")
    with pytest.raises(ValueError, match="depth_crop_top"):
        make_cfg(depth_crop_top=1.5)
