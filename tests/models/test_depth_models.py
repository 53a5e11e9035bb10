"""Depth / pose networks: encoder sizes, parameter count, disparity range, pose round trip."""

from __future__ import annotations

import math

import pytest
import torch

from dfvo.geometry.se3 import pose_from_axis_angle
from dfvo.models.depth_net import DepthNet, disp_to_depth
from dfvo.models.pose_net import PoseNet, pose_to_axis_angle
from dfvo.models.resnet import ResNet18Encoder


@pytest.mark.parametrize("frames", [1, 2])
def test_encoder_feature_sizes(frames: int) -> None:
    enc = ResNet18Encoder(frames).eval()
    with torch.no_grad():
        feats = enc(torch.rand(2, 3 * frames, 64, 128))
    expected = [(64, 32, 64), (64, 16, 32), (128, 8, 16), (256, 4, 8), (512, 2, 4)]
    assert [tuple(f.shape[1:]) for f in feats] == expected
    assert all(f.shape[0] == 2 for f in feats)


def test_encoder_parameter_count_matches_resnet18() -> None:
    # torchvision's resnet18 has 11,689,512 parameters, of which the 1000-class fc layer holds 513,000
    n = sum(p.numel() for p in ResNet18Encoder(1).parameters())
    assert n == 11_689_512 - 513_000
    # the 6-channel stem adds 64*3*7*7 weights
    assert sum(p.numel() for p in ResNet18Encoder(2).parameters()) == n + 64 * 3 * 49


def test_encoder_rejects_bad_input() -> None:
    enc = ResNet18Encoder(1)
    with pytest.raises(Exception, match="3"):
        enc(torch.rand(1, 6, 64, 64))
    with pytest.raises(ValueError, match="multiples of 32"):
        enc(torch.rand(1, 3, 60, 64))


def test_depth_net_scales_and_range() -> None:
    net = DepthNet().eval()
    with torch.no_grad():
        out = net(torch.rand(2, 3, 64, 96))
    assert sorted(out) == [0, 1, 2, 3]
    for s, d in out.items():
        assert d.shape == (2, 1, 64 // 2**s, 96 // 2**s)
        assert (d > 0).all() and (d < 1).all()
    depth = net.depth(torch.rand(1, 3, 64, 96))
    assert depth.shape == (1, 1, 64, 96) and (depth >= 0.1).all() and (depth <= 100).all()


def test_disp_to_depth_values() -> None:
    d = disp_to_depth(torch.tensor([0.0, 1.0, 0.5]).reshape(1, 1, 1, 3), 0.1, 100.0)
    # 1 / (0.01 + 9.99 * disp)
    assert torch.allclose(d.flatten(), torch.tensor([100.0, 0.1, 1.0 / (0.01 + 9.99 * 0.5)]))
    with pytest.raises(ValueError, match="min_depth"):
        disp_to_depth(torch.zeros(1, 1, 1, 1), 10.0, 1.0)


def test_pose_round_trip() -> None:
    g = torch.Generator().manual_seed(0)
    aa = torch.randn(5, 3, generator=g) * 0.5
    t = torch.randn(5, 3, generator=g)
    T = pose_from_axis_angle(aa, t)
    aa2, t2 = pose_to_axis_angle(T)
    assert torch.allclose(aa2, aa, atol=1e-5) and torch.allclose(t2, t)
    # rotation angle = norm of the axis-angle vector
    angle = torch.arccos(((T[:, 0, 0] + T[:, 1, 1] + T[:, 2, 2]) - 1) / 2)
    assert torch.allclose(angle, aa.norm(dim=1), atol=1e-5)


def test_pose_net_outputs_small_rigid_motion() -> None:
    net = PoseNet().eval()
    with torch.no_grad():
        a, b = torch.rand(2, 3, 64, 64), torch.rand(2, 3, 64, 64)
        T = net(a, b)
        aa, t = net.parameters_of(a, b)
    assert T.shape == (2, 4, 4)
    R = T[:, :3, :3]
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3).expand(2, 3, 3), atol=1e-5)
    assert torch.allclose(T[:, 3], torch.tensor([0.0, 0, 0, 1]).expand(2, 4))
    assert torch.allclose(T, pose_from_axis_angle(aa, t))
    # monodepth2's 0.01 output scaling: an untrained net predicts a motion well under a metre / a radian
    assert t.norm(dim=1).max() < 0.5 and aa.norm(dim=1).max() < 0.5 * math.pi


def test_depth_net_init_depth() -> None:
    net = DepthNet(0.1, 100.0, init_depth=10.0).eval()
    with torch.no_grad():
        depth = net.depth(torch.rand(1, 3, 64, 64))
    # the heads' bias puts the untrained output near 10 m (the features add a small spread)
    assert 5.0 < float(depth.median()) < 20.0
    with pytest.raises(ValueError, match="init_depth"):
        DepthNet(0.1, 100.0, init_depth=200.0)
